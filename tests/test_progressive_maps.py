"""Progressive maps (issue 23 item 2): the transform service publishes a coarse revision of a
workspace first and refined revisions up to its tol, each with its honest certificate; the
controller drives on the newest revision and swaps revisions without stopping the robot;
``confnav goal`` returns once the robot moves. Real Zenoh; waits for events."""

from __future__ import annotations

import itertools
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from confnav.schemas import (
    Goal,
    RobotStatus,
    SpawnRequest,
    TransformSolution,
    TransformStatus,
    decode,
    encode,
)
from confnav.services.controller import ControllerService
from confnav.services.definitions import REFINING, revision_ladder
from confnav.services.keys import Keys
from confnav.services.transform import TransformService
from conftest import (
    HolonomicRobot,
    RobotWatch,
    confnav_cmd,
    launched_system,
    square_definition,
    subprocess_env,
    wait_for,
)

K = Keys()


def test_revision_ladder() -> None:
    assert revision_ladder(1e-8) == [1e-3, 1e-6, 1e-8]
    assert revision_ladder(1e-10) == [1e-3, 1e-6, 1e-10]
    assert revision_ladder(1e-4) == [1e-3, 1e-4]
    assert revision_ladder(1e-3) == [1e-3]
    assert revision_ladder(1e-2) == [1e-2]


class _Log:
    """Messages of a key expression, in arrival order, with an event per arrival."""

    def __init__(self, bus: Any, expr: str) -> None:
        self.msgs: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        bus.subscribe(expr, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.msgs.append((key, payload))

    def on(self, key: str) -> list[bytes]:
        with self.lock:
            return [p for k, p in self.msgs if k == key]


def test_transform_publishes_revisions_with_decreasing_error(
    make_bus: Callable[[], Any],
) -> None:
    """tol 1e-8: a coarse revision (status 'solved (coarse, refining)', state refining), then
    finer ones; each certificate honest (tol_met for its own tol), estimates decreasing, the
    last one meets 1e-8 and is what queries answer."""
    client = make_bus()
    log = _Log(client, "confnav/ws/**")
    svc = TransformService(make_bus(), K, executor="thread", health_period=0.2)
    assert svc.progressive  # the library's solver: revisions by default
    svc.start()
    try:
        defn = square_definition("sq", [(0.2, 0.0)]).model_copy(update={"tol": 1e-8})
        client.publish(K.ws("sq", "definition"), encode(defn))

        def solutions() -> list[TransformSolution]:
            return [decode(TransformSolution, p) for p in log.on(K.ws("sq", "transform"))]

        def final_status() -> bool:
            st = [decode(TransformStatus, p) for p in log.on(K.ws("sq", "status"))]
            return bool(st) and st[-1].state == "solved" and not st[-1].message

        wait_for(lambda: any(s.diagnostics.tol == 1e-8 for s in solutions()), timeout=240)
        wait_for(final_status)
        sols = solutions()
        assert len(sols) >= 2, [s.diagnostics for s in sols]
        est = [s.diagnostics.error_estimate for s in sols]
        assert all(b < a for a, b in itertools.pairwise(est)), est
        assert sols[0].diagnostics.tol == 1e-3 and sols[0].diagnostics.tol_met
        assert all(s.diagnostics.error_estimate <= s.diagnostics.tol for s in sols)
        assert sols[-1].diagnostics.tol == 1e-8 and sols[-1].diagnostics.tol_met
        assert len({s.revision for s in sols}) == len(sols)
        statuses = [decode(TransformStatus, p) for p in log.on(K.ws("sq", "status"))]
        coarse = [s for s in statuses if s.message.startswith(REFINING)]
        assert coarse and coarse[0].state == "solved" and coarse[0].revision == sols[0].revision
        assert statuses[-1].state == "solved" and statuses[-1].revision == sols[-1].revision
        assert not statuses[-1].message.startswith(REFINING)
        replies = client.query(K.ws("sq", "transform"))
        assert decode(TransformSolution, replies[0].payload or b"").revision == sols[-1].revision
    finally:
        svc.stop()


def test_controller_moves_on_the_coarse_revision_and_across_the_swap(
    make_bus: Callable[[], Any],
) -> None:
    """A robot with a body (its map sq~r0.05 unsolved until its goal asks for it) drives on the
    coarse revision ('navigating on a coarse map, refining') and keeps navigating across the
    swap to the refined revisions: no 'stopped' status once it moved, and it arrives."""
    client = make_bus()
    statuses: list[RobotStatus] = []
    lock = threading.Lock()

    tr = TransformService(make_bus(), K, executor="thread", health_period=0.2)
    # The final revision of the robot's map waits until the robot has reported driving on a
    # coarse one: without this gate a fast refinement (or a slow controller under load) may
    # swap before any coarse status is published, and the test would check nothing.
    coarse_seen = threading.Event()
    gate_on = threading.Event()
    solve_fn = tr._solve_fn

    def gated_solve(defn_json: str, tol: float, *rest: Any) -> Any:
        if gate_on.is_set() and tol <= 1e-8:
            coarse_seen.wait(timeout=120)
        return solve_fn(defn_json, tol, *rest)

    tr._solve_fn = gated_solve

    def on_status(key: str, payload: bytes) -> None:
        s = decode(RobotStatus, payload)
        with lock:
            statuses.append(s)
        if s.state == "navigating" and "navigating on a coarse map, refining" in s.message:
            coarse_seen.set()

    client.subscribe(K.robot("r1", "status"), on_status)
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    tr.start()
    ctl.start()
    robot = HolonomicRobot(make_bus(), "r1", (-0.45, -0.45))
    try:
        defn = square_definition("sq", [(0.0, 0.1)]).model_copy(update={"tol": 1e-8})
        client.publish(K.ws("sq", "definition"), encode(defn))
        wait_for(lambda: tr.state_of("sq") == "solved", timeout=120)
        assert tr.state_of("sq~r0.05") is None  # solved on first use, below
        gate_on.set()  # from here on, a solve to 1e-8 is the robot's map's final revision
        goal = Goal(robot_id="r1", ws_id="sq", goal=(0.45, 0.45), robot_radius=0.05,
                    v_max=0.08, tolerance=0.03)  # fmt: skip
        client.publish(K.robot("r1", "goal"), encode(goal))

        def final_revision() -> str | None:
            return tr._ws["sq~r0.05"].revision if tr.state_of("sq~r0.05") == "solved" else None

        final = wait_for(final_revision, timeout=240)
        # the robot reports driving on the final revision (or has arrived)
        wait_for(
            lambda: any(s.map_revision == final for s in list(statuses) if s.state != "stopped"),
            timeout=60,
        )
        with lock:
            seen = list(statuses)
        first = next(i for i, s in enumerate(seen) if s.state == "navigating")
        after = seen[first:]
        assert all(s.state in ("navigating", "arrived") for s in after), [
            (s.state, s.reason, s.message) for s in after if s.state not in ("navigating",)
        ]
        revisions = [s.map_revision for s in after if s.state == "navigating"]
        assert (len(set(revisions)) >= 2 and revisions[-1] == final) or seen[-1].state == "arrived"
        assert revisions[0] != final  # it moved before the final revision existed

        assert any("navigating on a coarse map, refining" in s.message for s in after)
    finally:
        robot.stop.set()
        ctl.stop()
        tr.stop()


@pytest.mark.timeout(300)
def test_confnav_goal_returns_once_the_robot_moves(tmp_path: Path) -> None:
    """Router, transform, controller and simulator as processes; ``confnav goal`` for a robot
    with a body whose map is solved on first use: exit 0 once the robot navigates (on the
    first revision), and the robot arrives."""
    from confnav.services.launcher import ServiceSpec

    from confnav.geometry import Workspace

    d = square_definition("sq", [(0.0, 0.1)])
    ws_file = tmp_path / "sq.json"
    Workspace(d.outer, d.obstacles).save(ws_file)
    services = [
        ServiceSpec("transform", ["--workspace", f"sq={ws_file}"]),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", ["--workspace", f"sq={ws_file}", "--robot", "r1=sq:-0.45,-0.45"]),
    ]
    watch = RobotWatch()
    with launched_system(services, tmp_path, prefix="cng") as system:
        watch.attach(system.bus, system.keys)
        out = subprocess.run(
            [*confnav_cmd("goal", "r1", "0.45,0.45", "--ws", "sq", "--robot-radius", "0.05",
                          "--v-max", "0.3", "--timeout", "30"),
             "--mode", "client", "--connect", system.launcher.config.connect[0]],
            capture_output=True, text=True, env=subprocess_env(), timeout=240,
        )  # fmt: skip
        assert out.returncode == 0, out.stdout + out.stderr
        assert "navigating" in out.stdout

        def arrived() -> bool:
            with watch.lock:
                s = watch.status.get("r1", [])
                return bool(s) and s[-1].state == "arrived"

        wait_for(arrived, timeout=120, interval=0.2)
        with watch.lock:
            assert watch.collisions == []
            assert all(s.ws_id == "sq~r0.05" for s in watch.status["r1"] if s.ws_id)


def test_a_crowding_error_mid_solve_falls_back_to_the_atlas(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 23 item 3: a single-map solve that raises a crowding error mid-solve (not flagged
    by the a-priori test) makes the worker ask for an atlas, at every revision of the ladder."""
    from confnav.services import atlas_transform
    from confnav.services.definitions import workspace_of

    from confnav.errors import UnresolvedCrowdingError

    calls: list[tuple[float, float | None]] = []

    def crowding(ws: Any, tol: float, **kw: Any) -> Any:
        calls.append((tol, kw.get("max_error")))
        raise UnresolvedCrowdingError("circles crowd in sweep 2")

    monkeypatch.setattr(atlas_transform, "solve", crowding)  # the worker's own imports
    monkeypatch.setattr(atlas_transform, "atlas_reason", lambda ws: "")
    ws = workspace_of(square_definition("sq", [(0.0, 0.1)]))
    for tol, max_error in ((1e-3, 1e-2), (1e-8, None)):
        out = atlas_transform.single_or_atlas(ws, tol, max_error=max_error)
        assert out == {"needs_atlas": "one map crowds: circles crowd in sweep 2"}
    assert calls == [(1e-3, 1e-2), (1e-8, None)]


def test_robot_radius_maps_are_solved_ahead_of_use(mem_net: Any) -> None:
    """{ws}~r{R} is solved before any goal asks: for the service's --robot-radius values when a
    workspace is defined, and for a robot spawned with a body (radius, plus the library's
    look-ahead for a unicycle); a point robot adds nothing."""
    from conftest import fake_solve

    client = mem_net.bus("client")
    svc = TransformService(
        mem_net.bus("tr"), K, executor="thread", solve_fn=fake_solve, robot_radii=(0.05,)
    )
    svc.start()
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.0, 0.1)])))
        wait_for(lambda: svc.state_of("sq~r0.05") == "solved")
        spawn = f"{K.prefix}/sim/sim/spawn"
        point = SpawnRequest(robot_id="p", ws_id="sq", position=(0.0, 0.0))
        client.publish(spawn, encode(point))
        disk = SpawnRequest(robot_id="d", ws_id="sq", position=(0.0, 0.0), robot_radius=0.04)
        client.publish(spawn, encode(disk))
        uni = disk.model_copy(update={"robot_id": "u", "drive": "unicycle"})
        client.publish(spawn, encode(uni))  # 0.04 + the default look-ahead 0.1
        wait_for(lambda: svc.state_of("sq~r0.04") == "solved")
        wait_for(lambda: svc.state_of("sq~r0.14") == "solved")
        client.publish(spawn, b"{not json")  # ignored, never a crash
        assert svc.counters["spawn_radii"] == 2
        assert sorted(w for w in svc._ws if "~r" in w) == ["sq~r0.04", "sq~r0.05", "sq~r0.14"]
    finally:
        svc.stop()


def test_ros2_bridge_options_solve_the_footprint_map_ahead(make_bus: Callable[[], Any]) -> None:
    """``serve ros2 --drive unicycle --robot-radius R --lookahead D``: the bridge asks for the
    map of ``{ws}~r{R+D}`` at start, so the transform service solves it before any goal."""
    from confnav.services.ros2.bridge import BridgeConfig, RobotSpec, Ros2Bridge
    from conftest import fake_solve

    tr = TransformService(make_bus(), K, executor="thread", solve_fn=fake_solve)
    tr.start()
    bus = make_bus()
    cfg = BridgeConfig(
        robots=(RobotSpec("r1", "sq"),), drive="unicycle", robot_radius=0.05, lookahead=0.1
    )
    bridge = Ros2Bridge(bus, bus.session, cfg, health_period=0, map_import=None)
    bridge.start()
    try:
        make_bus().publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.0, 0.1)])))
        wait_for(lambda: tr.state_of("sq~r0.15") == "solved", timeout=30)
    finally:
        bridge.stop()
        tr.stop()
