"""The ROS 2 bridge over real Zenoh (unix socket, multicast off), without ROS.

In process: the liveliness tokens a ROS 2 graph cache sees, ROS -> confnav (odometry -> Pose,
goal_pose -> Goal), confnav -> ROS (VelocityCommand -> Twist with rmw_zenoh's attachment, in the
body frame), bad input, the map without an import, and the zenoh-bridge-ros2dds key style.
Multi-process: a stand-in ROS 2 robot (tests/ros2_standin_robot.py: zenoh + rosbags, nothing
from confnav) reaches its goal through the bridge and the real transform and controller.

Formats cited in tests/test_ros2_wire.py (rmw_zenoh bfc065f8c80cc3bc4d1963dc44ac5a472460903a
liveliness_utils.cpp; 534747dca92adf15e1b1b975123037ca278db5ba attachment_helpers.cpp).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from confnav.schemas import (
    Goal,
    Pose,
    RobotStatus,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.keys import Keys
from confnav.services.ros2 import codec, wire
from confnav.services.ros2.bridge import (
    BridgeConfig,
    RobotSpec,
    Ros2Bridge,
    add_parser,
    config_from_args,
)
from conftest import REPO, confnav_cmd, subprocess_env, wait_for

from confnav.geometry import Workspace
from confnav.navigation import defaults

pytestmark = pytest.mark.integration

K = Keys()
TWIST_KEY = "0/r1/cmd_vel/geometry_msgs::msg::dds_::Twist_/" + codec.type_hash(codec.TWIST)
ODOM_KEY = "0/r1/odom/nav_msgs::msg::dds_::Odometry_/" + codec.type_hash(codec.ODOMETRY)
GOAL_KEY = "0/r1/goal_pose/geometry_msgs::msg::dds_::PoseStamped_/" + codec.type_hash(
    codec.POSE_STAMPED
)


class Collect:
    """Thread-safe list of (key, payload, attachment) from a subscriber or a bus handler."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.items: list[tuple[str, bytes, bytes | None]] = []

    def sample(self, s: zenoh.Sample) -> None:
        att = s.attachment.to_bytes() if s.attachment is not None else None
        with self.lock:
            self.items.append((str(s.key_expr), s.payload.to_bytes(), att))

    def bus(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.items.append((key, payload, None))

    def get(self) -> list[tuple[str, bytes, bytes | None]]:
        with self.lock:
            return list(self.items)


def _odom(x: float, y: float, yaw: float, frame: str = "odom") -> bytes:
    return codec.encode_pose(
        codec.PlanarPose(x, y, yaw, 1_700_000_000_000_000_000, frame), "odometry"
    )


@pytest.fixture
def bridge(make_bus: Any) -> Iterator[tuple[Ros2Bridge, Any, zenoh.Session]]:
    bus, ros_bus = make_bus(), make_bus()
    cfg = BridgeConfig(
        robots=(RobotSpec("r1", "room"), RobotSpec("r2", "room", "/fleet/b")),
        map_topic="map",
        gain=3.0,
        v_max=0.4,
    )
    svc = Ros2Bridge(bus, bus.session, cfg, health_period=0, map_import=None)
    svc.start()
    try:
        yield svc, bus, ros_bus.session
    finally:
        svc.stop()


def test_liveliness_tokens_of_node_publishers_subscriptions(bridge: Any) -> None:
    _svc, bus, ros = bridge
    zid = wire.zid_chunk(str(bus.session.info.zid()))
    got = wait_for(
        lambda: (
            t
            if len(t := {str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**")}) >= 8
            else None
        ),
        timeout=5,
    )
    h = codec.type_hash
    head = f"@ros2_lv/0/{zid}/0"
    node = "%/%/confnav_bridge"
    want = {
        f"{head}/0/NN/{node}",
        f"{head}/1/MP/{node}/%r1%cmd_vel/geometry_msgs::msg::dds_::Twist_/"
        f"{h(codec.TWIST)}/::,10:,:,:,,",
        f"{head}/2/MS/{node}/%r1%odom/nav_msgs::msg::dds_::Odometry_/"
        f"{h(codec.ODOMETRY)}/2::,5:,:,:,,",
        f"{head}/3/MS/{node}/%r1%goal_pose/geometry_msgs::msg::dds_::PoseStamped_/"
        f"{h(codec.POSE_STAMPED)}/::,10:,:,:,,",
        f"{head}/4/MP/{node}/%fleet%b%cmd_vel/geometry_msgs::msg::dds_::Twist_/"
        f"{h(codec.TWIST)}/::,10:,:,:,,",
        f"{head}/5/MS/{node}/%fleet%b%odom/nav_msgs::msg::dds_::Odometry_/"
        f"{h(codec.ODOMETRY)}/2::,5:,:,:,,",
        f"{head}/6/MS/{node}/%fleet%b%goal_pose/geometry_msgs::msg::dds_::PoseStamped_/"
        f"{h(codec.POSE_STAMPED)}/::,10:,:,:,,",
        f"{head}/7/MS/{node}/%map/nav_msgs::msg::dds_::OccupancyGrid_/"
        f"{h(codec.OCCUPANCY_GRID)}/:1:,1:,:,:,,",
    }
    assert got == want


def test_pose_goal_and_command_translation(bridge: Any) -> None:
    _svc, bus, ros = bridge
    poses, goals, twists = Collect(), Collect(), Collect()
    bus.subscribe(K.robot("r1", "pose"), poses.bus)
    bus.subscribe(K.robot("r1", "goal"), goals.bus)
    sub = ros.declare_subscriber("0/r1/cmd_vel/**", twists.sample)
    try:
        time.sleep(0.3)
        att = wire.Attachment(1, time.time_ns(), bytes(16)).encode()
        ros.put(ODOM_KEY, _odom(0.25, -0.5, math.pi / 2), attachment=att)
        p = decode(Pose, wait_for(poses.get)[0][1])
        assert (p.robot_id, p.x, p.y, p.seq) == ("r1", 0.25, -0.5, 1)
        assert p.theta == pytest.approx(math.pi / 2, abs=1e-12)
        assert p.stamp_ns == 1_700_000_000_000_000_000

        goal = codec.encode_pose(codec.PlanarPose(-0.4, 0.3, 0.0, 0, "odom"), "pose")
        ros.put(GOAL_KEY, goal)
        g = decode(Goal, wait_for(goals.get)[0][1])
        assert (g.robot_id, g.ws_id, g.goal, g.gain, g.v_max) == (
            "r1",
            "room",
            (-0.4, 0.3),
            3.0,
            0.4,
        )

        sent = [((1.0, 0.0), "world", 0.0), ((0.0, 2.0), "world", 0.0), ((0.3, 0.0), "body", 0.7)]
        for i, (lin, frame, omega) in enumerate(sent):
            cmd = VelocityCommand(
                robot_id="r1",
                stamp_ns=time.time_ns(),
                linear=lin,
                angular=omega,
                pose_seq=i,
                frame=frame,  # type: ignore[arg-type]
            )
            bus.publish(K.robot("r1", "cmd_vel"), encode(cmd))
        items = wait_for(lambda: t if len(t := twists.get()) >= 3 else None)
    finally:
        sub.undeclare()
    assert {k for k, _, _ in items} == {TWIST_KEY}
    # yaw = pi/2: world (1, 0) is body (0, -1); world (0, 2) is body (2, 0); a unicycle's body
    # twist (v = 0.3, omega = 0.7) passes unrotated
    v1, v2, v3 = (codec.decode_twist(d) for _, d, _ in items)
    np.testing.assert_allclose(v1, (0.0, -1.0, 0.0), atol=1e-15)
    np.testing.assert_allclose(v2, (2.0, 0.0, 0.0), atol=1e-15)
    np.testing.assert_allclose(v3, (0.3, 0.0, 0.7), atol=1e-15)
    atts = [wire.Attachment.decode(a) for _, _, a in items if a is not None]
    assert [a.sequence_number for a in atts] == [1, 2, 3]
    token = next(
        str(r.ok.key_expr)
        for r in ros.liveliness().get("@ros2_lv/0/**")
        if "/MP/" in str(r.ok.key_expr) and "%r1%cmd_vel" in str(r.ok.key_expr)
    )
    assert all(a.source_gid == wire.entity_gid(token) for a in atts)
    assert all(abs(a.source_timestamp - time.time_ns()) < 10e9 for a in atts)


def test_bad_input_and_map_without_import(bridge: Any) -> None:
    svc, bus, ros = bridge
    poses, goals = Collect(), Collect()
    bus.subscribe(K.robot("r1", "pose"), poses.bus)
    bus.subscribe(K.robot("r1", "goal"), goals.bus)
    time.sleep(0.3)
    ros.put(ODOM_KEY, b"\x00\x01\x00\x00garbage")
    bus.publish(K.robot("r1", "cmd_vel"), b"{not json")
    wait_for(lambda: svc.counters["rejected"] >= 2)
    ros.put(ODOM_KEY, _odom(0.1, 0.1, 0.0, frame="odom"))  # the service still works
    wait_for(poses.get)
    ros.put(GOAL_KEY, codec.encode_pose(codec.PlanarPose(0.0, 0.0, 0.0, 0, "map"), "pose"))
    wait_for(lambda: svc.counters["rejected"] >= 3)  # goal in another frame than the poses
    assert goals.get() == []

    grid = codec.Grid(np.zeros((4, 5), dtype=np.int8), 0.1, codec.PlanarPose(0, 0, 0, 0, "map"))
    key = "0/map/nav_msgs::msg::dds_::OccupancyGrid_/" + codec.type_hash(codec.OCCUPANCY_GRID)
    ros.put(key, codec.encode_grid(grid))
    wait_for(lambda: svc.counters["maps"] >= 1)
    assert svc.health_detail() == (
        "degraded",
        "map import not available: OccupancyGrid received, not converted",
    )
    assert svc.health().state == "degraded"


def test_ros2dds_key_style(make_bus: Any) -> None:
    bus, ros_bus = make_bus(), make_bus()
    ros = ros_bus.session
    cfg = BridgeConfig(robots=(RobotSpec("r1", "room"),), key_style="ros2dds", cmd_frame="world")
    svc = Ros2Bridge(bus, bus.session, cfg, health_period=0)
    poses, twists = Collect(), Collect()
    bus.subscribe(K.robot("r1", "pose"), poses.bus)
    sub = ros.declare_subscriber("r1/cmd_vel", twists.sample)
    svc.start()
    try:
        time.sleep(0.3)
        ros.put("r1/odom", _odom(0.3, 0.2, 1.0))
        p = decode(Pose, wait_for(poses.get)[0][1])
        assert (p.x, p.y) == (0.3, 0.2)
        cmd = VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(), linear=(0.5, -0.25))
        bus.publish(K.robot("r1", "cmd_vel"), encode(cmd))
        (key, data, att), *_ = wait_for(twists.get)
        tokens = list(ros.liveliness().get("@ros2_lv/**"))
        svc.stop()
        stop = wait_for(lambda: t[-1] if len(t := twists.get()) >= 2 else None)
    finally:
        sub.undeclare()
        svc.stop()
    assert key == "r1/cmd_vel" and att is None
    assert codec.decode_twist(data) == (0.5, -0.25, 0.0)  # world frame: not rotated
    assert tokens == []
    assert codec.decode_twist(stop[1]) == (0.0, 0.0, 0.0)  # stopping the bridge stops the robot


def test_robot_spec_parsing() -> None:
    assert RobotSpec.parse("r1=room") == RobotSpec("r1", "room", "")
    assert RobotSpec.parse("r1=room").ns == "/r1"
    assert RobotSpec.parse("a=w@/fleet/a").ns == "/fleet/a"
    for bad in ("r1", "r1=", "r/1=room", "r1=room@/bad ns"):
        with pytest.raises(ValueError):
            RobotSpec.parse(bad)


def test_cli_bad_robot_is_one_line_error() -> None:
    r = subprocess.run(
        confnav_cmd("serve", "ros2", "--robot", "r1"),
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=60,
    )
    assert r.returncode != 0
    assert "expected ID=WS" in r.stderr and "Traceback" not in r.stderr


# ------------------------------------------------------------------------------------------
# a stand-in ROS 2 robot reaches its goal through the bridge and the real services
# ------------------------------------------------------------------------------------------
ROOM = Workspace(
    [(-1, -1), (1, -1), (1, 1), (-1, 1)],
    [[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2), (0.2, 0.2)]],
    anchor=0j,
)
START, YAW0, GOAL, TOL = (0.8, -0.6), 0.8, (-0.6, 0.0), 0.02


@pytest.mark.slow
def test_standin_robot_reaches_goal(zenoh_router: str, make_bus: Any, tmp_path: Path) -> None:
    room = tmp_path / "room.json"
    ROOM.save(room)
    zen = ["--connect", zenoh_router]
    env = subprocess_env()
    procs: dict[str, subprocess.Popen[str]] = {}

    def start(name: str, argv: list[str]) -> None:
        log = (tmp_path / f"{name}.log").open("w")
        procs[name] = subprocess.Popen(
            argv, stdout=subprocess.PIPE if name == "robot" else log, stderr=log, text=True, env=env
        )

    status = Collect()
    bus = make_bus()
    bus.subscribe(K.robot("r1", "status"), status.bus)
    lines: list[dict[str, Any]] = []
    try:
        start(
            "transform",
            confnav_cmd(
                "serve",
                "transform",
                "--workspace",
                f"room={room}",
                "--cache-dir",
                str(tmp_path / "cache"),
                *zen,
            ),
        )
        start("controller", confnav_cmd("serve", "controller", *zen))
        start(
            "bridge",
            confnav_cmd(
                "serve",
                "ros2",
                "--robot",
                "r1=room",
                "--gain",
                "100",
                "--v-max",
                "0.5",
                "--tolerance",
                str(TOL),
                *zen,
            ),
        )
        start(
            "robot",
            [
                sys.executable,
                str(REPO / "tests" / "ros2_standin_robot.py"),
                "--connect",
                zenoh_router,
                "--ns",
                "/r1",
                "--x",
                str(START[0]),
                "--y",
                str(START[1]),
                "--yaw",
                str(YAW0),
            ],
        )
        wait_for(lambda: len(bus.alive(K.alive_of("ros2"))) == 1, timeout=60)
        wait_for(lambda: len(bus.alive(K.alive_of("transform"))) == 1, timeout=60)
        wait_for(lambda: len(bus.alive(K.alive_of("controller"))) == 1, timeout=60)
        with zenoh.open(_client_conf(zenoh_router)) as ros:
            goal = codec.encode_pose(codec.PlanarPose(*GOAL, 0.0, 0, "odom"), "pose")
            time.sleep(0.5)
            ros.put(GOAL_KEY, goal)

            def arrived() -> bool:
                s = status.get()
                return bool(s) and decode(RobotStatus, s[-1][1]).state == "arrived"

            wait_for(arrived, timeout=90, interval=0.1)
        time.sleep(0.3)
    finally:
        for p in procs.values():
            p.terminate()
        for name, p in procs.items():
            out, _ = p.communicate(timeout=20)
            if name == "robot":
                lines = [json.loads(line) for line in out.splitlines() if line.strip()]
    last = lines[-1]
    assert math.hypot(last["x"] - GOAL[0], last["y"] - GOAL[1]) <= TOL + 1e-3
    assert last["cmds"] > 10 and last["attached"] == last["cmds"]
    # never inside the obstacle (clearance of every printed position > 0)
    assert all(ROOM.clearance(complex(d["x"], d["y"])) > 0 for d in lines)


def _client_conf(endpoint: str) -> zenoh.Config:
    from confnav.services.bus import zenoh_config

    return zenoh_config("client", connect=[endpoint])


def test_map_through_the_occupancy_grid_import(make_bus: Any) -> None:
    """With ``confnav.maps.occupancy`` present, an OccupancyGrid becomes a WorkspaceDefinition in
    the grid's frame: a walled 2.0 m x 1.5 m room (0.05 m cells) with a 0.3 m x 0.2 m block."""
    pytest.importorskip("confnav.maps.occupancy")
    bus, ros_bus = make_bus(), make_bus()
    res, (w, h) = 0.05, (40, 30)
    cells = np.full((h, w), 0, dtype=np.int8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100  # walls (row 0 = bottom)
    cells[0, :5] = -1  # unknown counts as occupied
    cells[10:14, 20:26] = 100  # block: x in [1.0, 1.3) + ox, y in [0.5, 0.7) + oy
    ox, oy = -1.0, -0.75
    grid = codec.Grid(cells, res, codec.PlanarPose(ox, oy, 0.0, 0, "map"))
    cfg = BridgeConfig(robots=(RobotSpec("r1", "room"),), map_topic="/map")
    svc = Ros2Bridge(bus, bus.session, cfg, health_period=0)
    defs = Collect()
    bus.subscribe(K.ws("room", "definition"), defs.bus)
    svc.start()
    try:
        time.sleep(0.3)
        key = "0/map/nav_msgs::msg::dds_::OccupancyGrid_/" + codec.type_hash(codec.OCCUPANCY_GRID)
        ros_bus.session.put(key, codec.encode_grid(grid))
        d = decode(WorkspaceDefinition, wait_for(defs.get, timeout=20)[0][1])
        assert svc.health_detail() == ("ok", "")
        # a grid the import rejects (no free cell at all): a status, nothing sent (a free space
        # open to the image border is walled by it since issue 23, not rejected)
        full_grid = codec.Grid(np.full((h, w), 100, dtype=np.int8), res, grid.origin)
        ros_bus.session.put(key, codec.encode_grid(full_grid))
        wait_for(lambda: svc.health_detail()[0] == "degraded", timeout=20)
        assert "map import failed" in svc.health_detail()[1]
        assert len(defs.get()) == 1
    finally:
        svc.stop()

    def bbox(poly: list[tuple[float, float]]) -> np.ndarray:
        a = np.asarray(poly)
        return np.array([a[:, 0].min(), a[:, 1].min(), a[:, 0].max(), a[:, 1].max()])

    # free cells: columns 1..38, rows 1..28 -> [ox + 0.05, ox + 1.95] x [oy + 0.05, oy + 1.45];
    # the import is conservative (free space never grows) and within one cell of the cells
    res = float(np.float32(res))  # OccupancyGrid.info.resolution is a float32 on the wire
    want_outer = np.array([ox + res, oy + res, ox + 39 * res, oy + 29 * res])
    got = bbox(d.outer)
    assert np.all(np.abs(got - want_outer) <= res + 1e-9)
    assert got[0] >= want_outer[0] - 1e-9 and got[2] <= want_outer[2] + 1e-9
    assert len(d.obstacles) == 1
    want_block = np.array([ox + 20 * res, oy + 10 * res, ox + 26 * res, oy + 14 * res])
    blk = bbox(d.obstacles[0])
    assert np.all(np.abs(blk - want_block) <= res + 1e-9)
    assert blk[0] <= want_block[0] + 1e-9 and blk[2] >= want_block[2] - 1e-9


def test_differential_drive_goal_asks_for_body_twists(make_bus: Any) -> None:
    """``--drive unicycle``: goals from goal_pose ask the controller for a unicycle (its
    commands are body twists, passed through unrotated: see the translation test)."""
    bus, ros_bus = make_bus(), make_bus()
    cfg = config_from_args(
        build_args(["--robot", "r1=room", "--drive", "unicycle", "--robot-radius", "0.2",
                    "--lookahead", "0.15"])
    )  # fmt: skip
    assert (cfg.drive, cfg.robot_radius, cfg.lookahead) == ("unicycle", 0.2, 0.15)
    svc = Ros2Bridge(bus, bus.session, cfg, health_period=0, map_import=None)
    svc.start()
    goals = Collect()
    bus.subscribe(K.robot("r1", "goal"), goals.bus)
    try:
        time.sleep(0.3)
        ros_bus.session.put(GOAL_KEY, codec.encode_pose(codec.PlanarPose(1, 2, 0, 0, ""), "pose"))
        g = decode(Goal, wait_for(goals.get)[0][1])
    finally:
        svc.stop()
    assert (g.drive, g.robot_radius, g.lookahead, g.goal) == ("unicycle", 0.2, 0.15, (1.0, 2.0))
    assert (g.gain, g.v_max, g.tolerance) == (defaults.GAIN, defaults.V_MAX, defaults.GOAL_TOL)


def build_args(argv: list[str]) -> Any:
    """The ``confnav serve ros2`` options parsed as the CLI parses them."""
    import argparse

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    return parser.parse_args(["ros2", *argv])
