"""Benchmark: goal to the first non-zero command for a robot with a body, through the services.

A router, a transform service, a controller and a simulator, each its own process on TCP
loopback (as ``confnav launch`` starts them); a client spawns a unicycle (``SpawnRequest`` on
the simulator's spawn key) on the default workspace and sends it a goal with its body
(``robot_radius``, ``drive="unicycle"``, the library's look-ahead), and measures, from the goal's
publication:

- ``first_cmd_s``: the first ``cmd_vel`` with a non-zero velocity (the robot moves);
- ``first_navigating_s``: the first ``navigating`` status, with its message (on a coarse map:
  "navigating on a coarse map, refining");
- ``revisions``: the map revisions the robot was commanded on, with the time each was first
  used, and their estimated errors (from the transform's statuses);
- ``final_s``: the first command on the final revision (the workspace's tol).

Cases (each with a fresh transform service, so nothing is cached; the goal is sent 1 s (ros2:
0.5 s) after the workspace's own map ``{ws}`` has its first revision and the controller has
installed it (its health's ``maps_installed``), ``base_first_revision_s`` after the services
are up, so what is measured is the robot's footprint map ``{ws}~r{R}``, which a
robot with a body drives without, on ``{ws}`` with the safety layer on the exact shrunk
workspace, until its first revision: docs/NAVIGATION.md, "First move"):

- ``build``: no services: what the controller builds before that first command on the base
  map, cold, per workspace: the exact shrunk workspace (``shrunk_workspace``, the transform
  service's derivation) and the safety layer's grid on it;
- ``solve``: no services: ``confnav.solve`` of the workspace shrunk by the footprint to the first
  revision's tol (1e-3, ``max_error`` 1e-2) in this process, twice (the first call includes
  the solver's warm-up): what the first revision costs;
- ``first_use``: the robot is spawned as a point (no radius known to the system); the goal's
  ``{ws}~r{R}`` map is solved when the controller first asks for it;
- ``spawned``: the robot is spawned with its body, so the transform service starts solving its
  ``{ws}~r{R}`` map at the spawn (ahead of use); the goal is sent once the first revision of
  that map is out (``spawn_to_first_revision_s``), as for a robot that waits for its first
  goal a few seconds after it was switched on;
- ``ros2``: no simulator: ``confnav serve ros2 --drive unicycle --robot-radius R --lookahead
  0.1`` and a stand-in ROS 2 robot speaking rmw_zenoh's wire format (tests/ros2_standin_robot.py:
  odometry out, ``cmd_vel`` twists in); the goal is a ``geometry_msgs/PoseStamped`` on the
  robot's ``goal_pose`` and the first move is the first non-zero ``Twist`` on its ``cmd_vel``
  (decoded from the ROS side); the map is solved on first use, as in issue 23's trial;
- ``office``, ``warehouse``: ``first_use`` on the README's maps (``examples/*.yaml`` imported
  as ``confnav import-map`` does) with the README's body (radius 0.2 m, unicycle with 0.1 m
  look-ahead: ``{ws}~r0.3``).

- ``office_no_warmup``, ``warehouse_no_warmup``: the same with the controller's
  ``--atlas-warmup first-use`` (each atlas chart builds its local expansions when a robot first
  uses it, on the goal's path: the behaviour before the background warm-up), for the ratio in
  one run.

Every service case also records whether the robot arrived (its ``arrived`` status,
``arrive_s`` after the goal, ``--arrive-timeout``) and its collisions: the simulator's wall
``CollisionEvent`` s and, from the poses after the goal, how often the body's disk (radius
``robot_radius`` around the pose) entered a wall or obstacle of the exact workspace
(``body_collisions``, ``min_body_clearance_m``; :func:`outcome`).

``ahead s`` in the table: spawn to the first revision (``spawned``); ``first cmd s``: goal to
the first non-zero command; ``final rev s``: goal to the first command on the final revision;
``arrive s``: goal to arrival; ``coll``: collisions (events + body).

Target (issue 23): goal to first non-zero command <= 2 s with a 0.2 m unicycle on the default
workspace. Prints a table and writes bench/results/firstmove.json (``--quick``: one run of
each case, ``firstmove.quick.json`` through ``python -m bench firstmove --quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from bench_services import (
    connect,
    free_port,
    require_services,
    spawn,
)  # the services bench's process helpers
from confnav.schemas import (
    CollisionEvent,
    Goal,
    Pose,
    RobotStatus,
    ServiceHealth,
    SpawnRequest,
    TransformStatus,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import Keys
from provenance import commit  # script mode: bench/ is on sys.path

HERE = Path(__file__).resolve().parent
CASES = (
    "build", "solve", "first_use", "spawned", "ros2", "office", "warehouse", "office_no_warmup",
    "warehouse_no_warmup",
)  # fmt: skip
#: the README's maps (examples/*.yaml, imported as ``confnav import-map`` does): start, goal
MAPS = {"office": ((8.5, 6.5), (1.5, 1.5)), "warehouse": ((1.2, 3.0), (9.0, 7.0))}
#: ``{map}_no_warmup``: the controller with ``--atlas-warmup first-use`` (each chart builds its
#: local expansions when a robot first uses it: the behaviour before the background warm-up)
NO_WARMUP = "_no_warmup"
K = Keys()


def stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()


class Watch:
    """Commands, statuses and transform statuses of one robot / workspace, timestamped."""

    def __init__(self, bus: ZenohBus, rid: str) -> None:
        self.lock = threading.Lock()
        self.cmds: list[tuple[float, VelocityCommand]] = []
        self.status: list[tuple[float, RobotStatus]] = []
        self.ws_status: list[tuple[float, TransformStatus]] = []
        bus.subscribe(K.robot(rid, "cmd_vel"), self._on(self.cmds, VelocityCommand))
        bus.subscribe(K.robot(rid, "status"), self._on(self.status, RobotStatus))
        bus.subscribe(K.any_ws("status"), self._on(self.ws_status, TransformStatus))
        self.poses: list[tuple[float, Pose]] = []
        self.collisions: list[tuple[float, CollisionEvent]] = []
        bus.subscribe(K.robot(rid, "pose"), self._on(self.poses, Pose))
        bus.subscribe(K.robot(rid, "collision"), self._on(self.collisions, CollisionEvent))
        self.maps_installed = 0  # the controller's counter, from its health
        bus.subscribe(f"{K.prefix}/health/controller/*", self._on_health)

    def _on_health(self, key: str, payload: bytes) -> None:
        h = decode(ServiceHealth, payload)
        with self.lock:
            self.maps_installed = max(self.maps_installed, h.counters.get("maps_installed", 0))

    def _on(self, store: list[Any], model: type[Any]) -> Any:
        def on(key: str, payload: bytes) -> None:
            msg = decode(model, payload)
            with self.lock:
                store.append((time.monotonic(), msg))

        return on


def wait(pred: Any, timeout: float) -> Any:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(0.02)
    return None


def example_workspace(name: str, tmp: Path) -> str:
    """``examples/{name}.yaml`` imported as ``confnav import-map`` does, as a workspace file."""
    from confnav.maps.occupancy import import_map

    out = tmp / f"{name}.json"
    if not out.exists():
        out.write_text(import_map(HERE.parent / "examples" / f"{name}.yaml").workspace.to_json())
    return str(out)


def base_ready(watch: Watch, ws_id: str) -> Any:
    """The monotonic time of the workspace's first solved revision once the controller has
    installed a map (its health's ``maps_installed``, published every second): the system is
    up (None: not yet)."""
    with watch.lock:
        if watch.maps_installed < 1:
            return None
        for t, s in watch.ws_status:
            if s.ws_id == ws_id and s.state == "solved" and s.revision:
                return t
    return None


def run_case(case: str, args: argparse.Namespace, tmp: Path, n: int) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--mode", "client", "--connect", ep]
    logs = tmp / f"{case}{n}"
    logs.mkdir(parents=True, exist_ok=True)
    procs = [spawn("serve", "router", "--listen", ep, log=logs / "router.log")]
    name = case.removesuffix(NO_WARMUP)
    ws_id = name if name in MAPS else "default"
    radius = args.map_radius if name in MAPS else args.radius
    start, goal_xy = MAPS.get(name, (tuple(args.start), tuple(args.goal)))
    warmup = ["--atlas-warmup", "first-use" if case.endswith(NO_WARMUP) else "background"]
    try:
        time.sleep(1.0)
        source = example_workspace(name, tmp) if name in MAPS else "builtin:default"
        ws = ["--workspace", f"{ws_id}={source}"]
        procs.append(spawn("serve", "transform", *common, *ws, log=logs / "transform.log"))
        procs.append(spawn("serve", "controller", *common, *warmup, log=logs / "controller.log"))
        procs.append(spawn("serve", "simulator", *common, *ws, log=logs / "simulator.log"))
        rid = "u1"
        with connect(ep) as bus:
            require_services(bus, 60, logs)
            watch = Watch(bus, rid)
            t_up = time.monotonic()
            body = case == "spawned"
            req = SpawnRequest(
                robot_id=rid,
                ws_id=ws_id,
                position=(start[0], start[1]),
                theta=0.0,
                stamp_ns=time.time_ns(),
                robot_radius=radius if body else 0.0,
                # first_use: a point (nothing for the transform to solve ahead); the simulator
                # integrates the controller's body-frame twists either way
                drive="unicycle" if body else "holonomic",
            )
            t_spawn = time.monotonic()
            bus.publish(f"{K.prefix}/sim/sim/spawn", encode(req))
            first_rev_s: float | None = None
            if body:

                def first_revision() -> float | None:
                    with watch.lock:
                        for t, s in watch.ws_status:
                            if "~r" in s.ws_id and s.state == "solved" and s.revision:
                                return t - t_spawn
                    return None

                first_rev_s = wait(first_revision, args.timeout)
            # the workspace's own map (its first revision) exists before the goal: the system
            # is up; the goal's footprint map {ws}~r{R} is what is measured
            t_base = wait(lambda: base_ready(watch, ws_id), args.timeout)
            time.sleep(1.0)
            goal = Goal(
                robot_id=rid,
                ws_id=ws_id,
                goal=(goal_xy[0], goal_xy[1]),
                robot_radius=radius,
                drive="unicycle",
                stamp_ns=time.time_ns(),
            )
            t0 = time.monotonic()
            bus.publish(K.robot(rid, "goal"), encode(goal))

            def moving() -> float | None:
                with watch.lock:
                    for t, c in watch.cmds:
                        if t >= t0 and (c.linear[0] != 0.0 or c.angular != 0.0):
                            return t - t0
                return None

            first = wait(moving, args.timeout)
            final_rev: str | None = None

            def final() -> str | None:
                with watch.lock:
                    for _, s in watch.ws_status:
                        if "~r" in s.ws_id and s.state == "solved" and not s.message:
                            return s.revision
                return None

            arrived = wait(lambda: arrival(watch, t0), args.arrive_timeout) if first else None
            final_rev = wait(final, args.final_timeout) if first is not None else None
            time.sleep(0.5)
            with watch.lock:
                cmds = [(t - t0, c) for t, c in watch.cmds if t >= t0]
                status = [(t - t0, s) for t, s in watch.status if t >= t0]
                ws_status = [(t - t0, s) for t, s in watch.ws_status]
                poses = [p for t, p in watch.poses if t >= t0]
                events = [e for _, e in watch.collisions]
        revs: dict[str, float] = {}
        for t, c in cmds:
            if c.map_revision and c.map_revision not in revs and (c.linear[0] or c.angular):
                revs[c.map_revision] = t
        notes = {s.revision: s.message for _, s in ws_status if s.revision and "~r" in s.ws_id}
        nav = [(t, s) for t, s in status if s.state == "navigating"]
        stopped_after_moving = [
            (round(t, 2), s.reason)
            for t, s in status
            if first is not None and t > first and s.state == "stopped"
        ]
        return {
            "case": case,
            "run": n,
            "workspace": ws_id,
            "robot_radius": radius,
            "start": list(start),
            "goal": list(goal_xy),
            "base_first_revision_s": None if t_base is None else t_base - t_up,
            "spawn_to_first_revision_s": first_rev_s if body else None,
            "first_cmd_s": first,
            "first_navigating_s": nav[0][0] if nav else None,
            "first_navigating_message": nav[0][1].message if nav else None,
            "revisions": [
                {"revision": r[:12], "first_used_s": t, "transform_status": notes.get(r, "")}
                for r, t in revs.items()
            ],
            "final_s": revs.get(final_rev) if final_rev else None,
            "stopped_after_moving": stopped_after_moving,
            "on_base_map": any("unshrunk map" in s.message for _, s in nav),
            "controller_atlas_warmup": warmup[1],
            "footprint_map_statuses": [
                (round(t, 2), s.state, (s.revision or "")[:12], s.message[:80])
                for t, s in ws_status
                if "~r" in s.ws_id
            ],
            "last_status": None
            if not status
            else (status[-1][1].state, status[-1][1].reason, status[-1][1].message[:160]),
            **outcome(arrived, poses, events, base_ws(name, tmp), radius, goal_xy),
            "loadavg": list(os.getloadavg()),
        }
    finally:
        stop(procs[::-1])


def arrival(watch: Watch, t0: float) -> float | None:
    """Goal to the first ``arrived`` status (None: not yet)."""
    with watch.lock:
        for t, s in watch.status:
            if t >= t0 and s.state == "arrived":
                return t - t0
    return None


def base_ws(name: str, tmp: Path) -> Any:
    """The exact workspace the robot's body must stay in (its walls and obstacles)."""
    from confnav.geometry import Workspace
    from confnav.scenes.workspaces import default_workspace

    return Workspace.load(example_workspace(name, tmp)) if name in MAPS else default_workspace()


def outcome(
    arrived_s: float | None,
    poses: list[Pose],
    events: list[CollisionEvent],
    ws: Any,
    radius: float,
    goal: tuple[float, float],
) -> dict[str, Any]:
    """Whether the robot arrived (its ``arrived`` status, goal to it in s) and its collisions:

    - ``collision_events``: the simulator's ``CollisionEvent`` s against the walls (on the
      radius it was spawned with: 0 for a robot spawned as a point, ``first_use``);
    - ``body_collisions``: from the poses after the goal, the times the disk of the body's
      radius around the robot's position (``base_link``) entered a wall or obstacle of the
      exact workspace (runs of poses with clearance < radius), and ``min_body_clearance_m``,
      the smallest clearance of that disk (poses at the simulator's rate; between two poses
      the simulator's own check applies).
    """
    import numpy as np

    z = np.array([complex(p.x, p.y) for p in poses], dtype=np.complex128)
    gap = np.asarray(ws.clearance(z), dtype=np.float64) - radius if z.size else np.zeros(0)
    inside = gap < 0
    runs = int(inside[0]) + int(np.count_nonzero(inside[1:] & ~inside[:-1])) if z.size else 0
    last = poses[-1] if poses else None
    return {
        "arrived": arrived_s is not None,
        "arrive_s": arrived_s,
        "collision_events": sum(1 for e in events if e.other_robot_id is None),
        "body_collisions": runs,
        "min_body_clearance_m": float(gap.min()) if gap.size else None,
        "final_distance_m": None if last is None else abs(complex(last.x, last.y) - complex(*goal)),
        "poses_checked": int(z.size),
    }


def run_solve(args: argparse.Namespace, n: int) -> dict[str, Any]:
    """The ``solve`` case: the first revision's solve in this process (see the docstring)."""
    import warnings

    from confnav.services.definitions import COARSE_MAX_ERROR, LADDER

    from confnav.conformal.solver import solve
    from confnav.maps.footprint import inflate
    from confnav.scenes.workspaces import default_workspace

    ws = inflate(default_workspace(), args.radius + 0.1)
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = solve(ws, LADDER[0], max_error=COARSE_MAX_ERROR)
        times.append(time.perf_counter() - t0)
    d = m.diagnostics
    return {
        "case": "solve",
        "run": n,
        "spawn_to_first_revision_s": None,
        "first_cmd_s": None,
        "solve_s": times,
        "tol": LADDER[0],
        "error_estimate": d.error_estimate,
        "tol_met": d.tol_met,
        "nodes": list(d.nodes),
        "final_s": None,
        "revisions": [],
        "first_navigating_message": None,
        "loadavg": list(os.getloadavg()),
    }


def run_build(args: argparse.Namespace, tmp: Path, n: int) -> dict[str, Any]:
    """The ``build`` case: what a robot waiting for its footprint map costs the controller
    before its first command on the base map: the exact shrunk workspace (derived from the
    base workspace as the transform service derives ``{ws}~r{R}``) and the safety layer's grid
    on it (both cold: new objects), per workspace."""
    from confnav.services.controller_footprint import shrunk_workspace

    from confnav.geometry import Workspace
    from confnav.navigation.safety import SafetyFilter
    from confnav.scenes.workspaces import default_workspace

    bases = {"default": (default_workspace(), args.radius + 0.1)}
    for name in MAPS:
        bases[name] = (Workspace.load(example_workspace(name, tmp)), args.map_radius + 0.1)
    out: dict[str, Any] = {}
    for name, (ws, footprint) in bases.items():
        t0 = time.perf_counter()
        shrunk = shrunk_workspace(ws, f"{name}~r{footprint:g}")
        t1 = time.perf_counter()
        _ = SafetyFilter(shrunk).grid
        t2 = time.perf_counter()
        out[name] = {"footprint_m": footprint, "shrink_s": t1 - t0, "grid_s": t2 - t1,
                     "total_s": t2 - t0}  # fmt: skip
    return {
        "case": "build",
        "run": n,
        "spawn_to_first_revision_s": None,
        "first_cmd_s": None,
        "build": out,
        "final_s": None,
        "revisions": [],
        "first_navigating_message": None,
        "loadavg": list(os.getloadavg()),
    }


def run_ros2(args: argparse.Namespace, tmp: Path, n: int) -> dict[str, Any]:
    """The ``ros2`` case (see the module docstring)."""
    import zenoh
    from confnav.services.ros2 import codec

    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--mode", "client", "--connect", ep]
    logs = tmp / f"ros2{n}"
    logs.mkdir(parents=True, exist_ok=True)
    procs = [spawn("serve", "router", "--listen", ep, log=logs / "router.log")]
    rid = "u1"
    try:
        time.sleep(1.0)
        ws = ["--workspace", "default=builtin:default"]
        procs.append(spawn("serve", "transform", *common, *ws, log=logs / "transform.log"))
        procs.append(spawn("serve", "controller", *common, log=logs / "controller.log"))
        bridge = ["--robot", f"{rid}=default", "--drive", "unicycle"]
        bridge += ["--robot-radius", str(args.radius), "--lookahead", "0.1"]
        procs.append(spawn("serve", "ros2", *common, *bridge, log=logs / "bridge.log"))
        robot = [sys.executable, str(HERE.parent / "tests" / "ros2_standin_robot.py")]
        robot += ["--connect", ep, "--ns", f"/{rid}", "--x", str(args.start[0])]
        robot += ["--y", str(args.start[1]), "--yaw", "0"]
        with connect(ep) as bus:
            require_services(bus, 60, logs, ("transform", "controller", "ros2"))
            with open(logs / "robot.log", "wb") as f:  # the router is up: the robot connects
                procs.append(subprocess.Popen(robot, stdout=f, stderr=subprocess.STDOUT))
            watch = Watch(bus, rid)
            t_up = time.monotonic()
            moves: list[float] = []
            cmd_key = f"0/{rid}/cmd_vel/geometry_msgs::msg::dds_::Twist_/" + codec.type_hash(
                codec.TWIST
            )
            goal_key = f"0/{rid}/goal_pose/geometry_msgs::msg::dds_::PoseStamped_/"
            goal_key += codec.type_hash(codec.POSE_STAMPED)

            def on_twist(sample: Any) -> None:
                vx, _vy, wz = codec.decode_twist(sample.payload.to_bytes())
                if vx != 0.0 or wz != 0.0:
                    moves.append(time.monotonic())

            with zenoh.open(zenoh_config("client", connect=[ep])) as ros:
                ros.declare_subscriber(cmd_key, on_twist)
                posed: list[bool] = []
                bus.subscribe(K.robot(rid, "pose"), lambda k, p: posed.append(True))
                if not wait(lambda: posed, 60):  # its odometry on the bus, through the bridge
                    raise RuntimeError(f"no odometry from the stand-in robot (logs in {logs})")
                # the workspace's own map exists (its first revision): the system is up
                t_base = wait(lambda: base_ready(watch, "default"), args.timeout)
                time.sleep(0.5)
                t0 = time.monotonic()
                pose = codec.PlanarPose(args.goal[0], args.goal[1], 0.0, time.time_ns(), "odom")
                ros.put(goal_key, codec.encode_pose(pose, "pose"))
                first = wait(lambda: [t - t0 for t in moves if t >= t0][:1], args.timeout)
                arrived = wait(lambda: arrival(watch, t0), args.arrive_timeout) if first else None
                time.sleep(0.5)
            with watch.lock:
                status = [(t - t0, s) for t, s in watch.status if t >= t0]
                poses = [p for t, p in watch.poses if t >= t0]
                events = [e for _, e in watch.collisions]
        nav = [(t, s) for t, s in status if s.state == "navigating"]
        return {
            "case": "ros2",
            "run": n,
            "workspace": "default",
            "robot_radius": args.radius,
            "base_first_revision_s": None if t_base is None else t_base - t_up,
            "spawn_to_first_revision_s": None,
            "first_cmd_s": first[0] if first else None,
            "first_navigating_s": nav[0][0] if nav else None,
            "first_navigating_message": nav[0][1].message if nav else None,
            "revisions": sorted({s.map_revision[:12] for _, s in nav if s.map_revision}),
            "final_s": None,
            "stopped_after_moving": [
                (round(t, 2), s.reason)
                for t, s in status
                if first and t > first[0] and s.state == "stopped"
            ],
            "on_base_map": any("unshrunk map" in s.message for _, s in nav),
            **outcome(
                arrived, poses, events, base_ws("default", tmp), args.radius, tuple(args.goal)
            ),
            "loadavg": list(os.getloadavg()),
        }
    finally:
        stop(procs[::-1])


def report(rows: list[dict[str, Any]]) -> None:
    print(
        f"{'case':<19} {'run':>3} {'ahead s':>8} {'first cmd s':>11} {'final rev s':>11} "
        f"{'revs':>4} {'arrive s':>8} {'coll':>4}  load"
    )
    for r in rows:
        f = "-" if r["first_cmd_s"] is None else f"{r['first_cmd_s']:.2f}"
        g = "-" if r["final_s"] is None else f"{r['final_s']:.2f}"
        load = " ".join(f"{x:.1f}" for x in r["loadavg"])
        ahead = r["spawn_to_first_revision_s"]
        a = "-" if ahead is None else f"{ahead:.2f}"
        if r["case"] == "build":
            parts = [f"{w} {b['total_s']:.3f} s (shrink {b['shrink_s']:.3f}, grid "
                     f"{b['grid_s']:.3f})" for w, b in r["build"].items()]  # fmt: skip
            print(f"{'build':<19} {r['run']:>3} " + ", ".join(parts) + f"  {load}")
            continue
        if r["case"] == "solve":
            print(
                f"{'solve':<19} {r['run']:>3} tol {r['tol']:.0e}: "
                + ", ".join(f"{t:.2f} s" for t in r["solve_s"])
                + f" (cold, warm), estimate {r['error_estimate']:.1e}, tol_met {r['tol_met']}"
                + f"  {load}"
            )
            continue
        arr = "-" if r.get("arrive_s") is None else f"{r['arrive_s']:.1f}"
        coll = r.get("body_collisions", 0) + r.get("collision_events", 0)
        print(
            f"{r['case']:<19} {r['run']:>3} {a:>8} {f:>11} {g:>11} {len(r['revisions']):>4} "
            f"{arr:>8} {coll:>4}  {load}"
        )
        if r["first_navigating_message"]:
            print(f"{'':14} first status: navigating ({r['first_navigating_message']})")


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="one run of each case")
    ap.add_argument("--runs", type=int, default=None, help="runs per case (default 3)")
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    ap.add_argument(
        "--radius",
        type=float,
        default=0.1,
        help="robot radius, m (unicycle; with the 0.1 m look-ahead the map is the workspace "
        "shrunk by 0.2 m, default~r0.2, as in issue 23's ROS 2 trial)",
    )
    ap.add_argument(
        "--map-radius",
        type=float,
        default=0.2,
        help="robot radius on the README's office and warehouse maps, m (unicycle, 0.1 m "
        "look-ahead: the README's --robot-radius 0.2 --unicycle 0.1)",
    )
    ap.add_argument("--start", type=float, nargs=2, default=(-1.5, 1.5))
    ap.add_argument("--goal", type=float, nargs=2, default=(1.5, 1.5))
    ap.add_argument("--timeout", type=float, default=600.0, help="s to wait for the first move")
    ap.add_argument(
        "--final-timeout",
        type=float,
        default=None,
        help="s to wait for the final revision (default 900; --quick: 0, not waited for)",
    )
    ap.add_argument(
        "--arrive-timeout",
        type=float,
        default=300.0,
        help="s after the goal to wait for the robot's 'arrived' status",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # stop the services (finally)
    runs = args.runs or (1 if args.quick else 3)
    if args.final_timeout is None:
        args.final_timeout = 0.0 if args.quick else 900.0
    out = Path(
        args.out or HERE / "results" / ("firstmove.quick.json" if args.quick else "firstmove.json")
    )
    tmp = Path(tempfile.mkdtemp(prefix="confnav-firstmove-"))
    results: dict[str, Any] = {
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "loadavg_start": list(os.getloadavg()),
        "workspace": "default",
        "robot": {"radius": args.radius, "drive": "unicycle", "lookahead": "library default"},
        "start": list(args.start),
        "goal": list(args.goal),
        "target_first_cmd_s": 2.0,
        "rows": [],
    }
    for case in args.cases:
        for n in range(runs):
            if case == "build":
                row = run_build(args, tmp, n)
            elif case == "solve":
                row = run_solve(args, n)
            elif case == "ros2":
                row = run_ros2(args, tmp, n)
            else:
                row = run_case(case, args, tmp, n)
            results["rows"].append(row)
            report([row])
    results["loadavg_end"] = list(os.getloadavg())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1, default=float) + "\n")
    print()
    report(results["rows"])
    print(f"wrote {out} (logs in {tmp})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
