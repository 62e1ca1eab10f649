"""Real SLAM maps through the services (issue 23, "Real SLAM maps"): goal to first command.

    python bench/bench_slam.py --services [--quick] [--maps depot ...] [--pairs 3]
                               [--out bench/results/slam_services.json]
    python -m bench slam_services [--quick]

The maps, the body and the start/goal pairs are :mod:`bench_slam`'s (the first ``--pairs``
of its ``PAIRS`` pairs per map, seed ``SEED``, whose starts and goals are ``SEPARATION``
apart: a 0.22 m unicycle with a 0.1 m look-ahead, so its map is ``{map}~r0.32``). Per map,
real service processes as ``confnav launch`` starts them
(``confnav -v serve router|transform|controller|simulator``, INFO logs as the launcher
writes them to its log directory, TCP loopback, one BLAS thread each, the services'
defaults: a progressive atlas with route hints): the transform service loads the imported
map (``confnav import-map``'s defaults, a workspace file), the simulator the same map with
one unicycle per pair (``--robot ID=MAP:X,Y,THETA:r=0.22:drive=unicycle``, 50 Hz). Once
every service is alive and the base map ``{map}`` has a first revision (or has failed: the
unshrunk depot does), the bench waits up to ``--settle`` s for the transform service to be
idle (its health: nothing solving or refining), then publishes every robot's goal at once
(``Goal`` with ``robot_radius`` 0.22, ``drive`` unicycle) and measures per robot, from its
goal's publication:

- ``first_cmd_s``: the first non-zero ``cmd_vel`` (linear or angular), the robot moves;
  target <= 2 s (``READY_TARGET_S``);
- ``arrive_s``: its ``arrived`` status (``--arrive-timeout``);
- collisions: the simulator's wall ``CollisionEvent`` s (``wall_events``; robot-robot ones
  apart, ``robot_events``) and, from every pose after the goal, how often the 0.22 m disk
  around ``base_link`` entered a wall of the imported map (``body_collisions``,
  ``min_body_clearance_m``);
- the footprint map's first partial atlas: when it was published, its solved cells, and
  whether the robot's start (its look-ahead point) lies in one of them (``start_in_first``);
- the route hints: the controller's ``route_hints_sent`` and the transform's
  ``route_hints`` counters (from their health).

``--no-maps-ahead``: the simulator does not ask for its robots' footprint maps at start
(``serve simulator --no-maps-ahead``), so the goals are their first use: the transform
derives and solves ``{map}~r0.32`` from the goals on. By default it asks (as the service
does), and the footprint map is solved during the settling time, beside the base map.
``--no-route-hints``: the controllers send no route hints (``serve controller
--no-route-hints``): the transform solves the cells in its own order, for the ratio.
``--quick``: tb3_world and empty_room, 2 pairs. Load averages are recorded per map (a shared
2-core machine: the wall times inflate with the load).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_services import connect, free_port, require_services, spawn
from confnav.schemas import (
    AtlasIndex,
    CollisionEvent,
    Goal,
    Pose,
    RobotStatus,
    ServiceHealth,
    TransformStatus,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services import navigation
from confnav.services.keys import Keys
from provenance import commit, loadavg

from confnav.maps.footprint import inflate
from confnav.maps.occupancy import import_map
from confnav.scenes.scenarios import random_starts

K = Keys()
HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "slam_services.json"
PAIRS = 3
#: m between any two starts or goals of the robots sharing a map (two 0.22 m bodies, 0.2 m to
#: pass): pairs_of
SEPARATION = 2 * 0.22 + 0.2
QUICK_PAIRS = 2
SETTLE_S = 20.0
ARRIVE_TIMEOUT_S = 180.0


Pair = tuple[complex, complex, float]
"""A robot's start (``base_link``), goal and heading."""


class Watch:
    """Everything the bench needs from the bus, stamped with the monotonic receive time."""

    def __init__(self, bus: Any, ids: list[str], nav_ws_id: str) -> None:
        self.lock = threading.Lock()
        self.cmds: dict[str, list[tuple[float, VelocityCommand]]] = {r: [] for r in ids}
        self.status: dict[str, list[tuple[float, RobotStatus]]] = {r: [] for r in ids}
        self.poses: dict[str, list[tuple[float, Pose]]] = {r: [] for r in ids}
        self.events: list[tuple[float, CollisionEvent]] = []
        self.ws_status: list[tuple[float, TransformStatus]] = []
        self.indexes: list[tuple[float, AtlasIndex]] = []
        self.health: dict[str, ServiceHealth] = {}
        self.nav_ws_id = nav_ws_id
        bus.subscribe(K.any_robot("cmd_vel"), self._robot(self.cmds, VelocityCommand))
        bus.subscribe(K.any_robot("status"), self._robot(self.status, RobotStatus))
        bus.subscribe(K.any_robot("pose"), self._robot(self.poses, Pose))
        bus.subscribe(K.any_robot("collision"), self._on_event)
        bus.subscribe(K.any_ws("status"), self._on_ws_status)
        bus.subscribe(K.ws(nav_ws_id, "atlas"), self._on_index)
        bus.subscribe(f"{K.prefix}/health/*/*", self._on_health)

    def _robot(self, store: dict[str, list[Any]], model: type[Any]) -> Any:
        def on(key: str, payload: bytes) -> None:
            msg = decode(model, payload)
            with self.lock:
                if msg.robot_id in store:
                    store[msg.robot_id].append((time.monotonic(), msg))

        return on

    def _on_event(self, key: str, payload: bytes) -> None:
        e = decode(CollisionEvent, payload)
        with self.lock:
            self.events.append((time.monotonic(), e))

    def _on_ws_status(self, key: str, payload: bytes) -> None:
        s = decode(TransformStatus, payload)
        with self.lock:
            self.ws_status.append((time.monotonic(), s))

    def _on_index(self, key: str, payload: bytes) -> None:
        i = decode(AtlasIndex, payload)
        with self.lock:
            self.indexes.append((time.monotonic(), i))

    def _on_health(self, key: str, payload: bytes) -> None:
        h = decode(ServiceHealth, payload)
        with self.lock:
            self.health[h.service] = h


def wait(pred: Any, timeout: float, period: float = 0.02) -> Any:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(period)
    return None


def stop(procs: list[Any]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except Exception:
            p.kill()


def pairs_of(
    nav_ws: Any, n: int, all_pairs: int, seed: int
) -> list[tuple[complex, complex, float]]:
    """:mod:`bench_slam`'s pairs of a map (its ``all_pairs`` with ``seed``): the first ``n``
    whose starts and goals are at least ``SEPARATION`` apart from those of the pairs taken
    before (robots that share a map at once: two bodies cannot both stand on goals closer
    than their diameter; before, a tb3_world goal 0.28 m from another robot's made one of
    them yield for good)."""
    from bench_slam import LOOKAHEAD

    pts = random_starts(nav_ws, 2 * all_pairs, seed=seed, margin=0.05 + LOOKAHEAD)
    heads = np.random.default_rng(seed).uniform(-np.pi, np.pi, all_pairs)
    out: list[tuple[complex, complex, float]] = []
    taken: list[complex] = []
    for i in range(all_pairs):
        s, g = complex(pts[i]), complex(pts[all_pairs + i])
        if all(abs(s - q) >= SEPARATION and abs(g - q) >= SEPARATION for q in taken):
            out.append((s, g, float(heads[i])))
            taken += [s, g]
        if len(out) == n:
            break
    return out


def base_settled(w: Watch, ws_id: str) -> bool:
    """The base map has a first revision (a map, a partial atlas) or has failed."""
    with w.lock:
        return any(
            s.ws_id == ws_id and (s.state in ("solved", "failed") or "charts solved" in s.message)
            for _, s in w.ws_status
        )


def transform_idle(w: Watch) -> bool:
    with w.lock:
        h = w.health.get("transform")
    if h is None:
        return False
    try:
        d = json.loads(h.detail)
    except ValueError:
        return False
    return not d.get("solving") and not d.get("refining")


def body_collisions(ws: Any, poses: list[Pose], radius: float) -> dict[str, Any]:
    """Runs of poses whose ``radius`` disk around ``base_link`` enters a wall, and the least
    clearance of that disk (vectorized ``Workspace.clearance``)."""
    z = np.array([complex(p.x, p.y) for p in poses], dtype=np.complex128)
    if not z.size:
        return {"body_collisions": 0, "min_body_clearance_m": None, "poses_checked": 0}
    gap = np.asarray(ws.clearance(z), dtype=np.float64) - radius
    inside = gap < 0
    runs = int(inside[0]) + int(np.count_nonzero(inside[1:] & ~inside[:-1]))
    return {
        "body_collisions": runs,
        "min_body_clearance_m": float(gap.min()),
        "poses_checked": int(z.size),
    }


def in_cells(index: AtlasIndex, z: complex, solved_only: bool = True) -> bool:
    import shapely

    for c in index.cells:
        if solved_only and c.pending:
            continue
        poly = shapely.Polygon(c.outer)
        for o in c.obstacles:
            poly = poly.difference(shapely.Polygon(o))
        if poly.contains(shapely.Point(z.real, z.imag)):
            return True
    return False


def run_map(name: str, n_pairs: int, args: Any, tmp: Path) -> dict[str, Any]:
    from bench_slam import LOOKAHEAD, MAPS_DIR, RADIUS, SEED
    from bench_slam import PAIRS as ALL_PAIRS

    row: dict[str, Any] = {"map": name, "load_start": loadavg()}
    res = import_map(MAPS_DIR / f"{name}.yaml")
    ws = res.workspace
    src = tmp / f"{name}.json"
    src.write_text(ws.to_json())
    nav_ws = inflate(ws, RADIUS + LOOKAHEAD)
    pairs = pairs_of(nav_ws, n_pairs, ALL_PAIRS, SEED)
    ids = [f"r{k}" for k in range(len(pairs))]
    goals = [
        Goal(
            robot_id=rid,
            ws_id=name,
            goal=(g.real, g.imag),
            robot_radius=RADIUS,
            drive="unicycle",
            lookahead=LOOKAHEAD,
        )
        for rid, (_, g, _) in zip(ids, pairs, strict=True)
    ]
    nav_ws_id = navigation.map_ws_id(goals[0])
    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--mode", "client", "--connect", ep]
    logs = tmp / name
    logs.mkdir(parents=True, exist_ok=True)
    wsarg = ["--workspace", f"{name}={src}"]
    robots = []
    for rid, (s, _, th) in zip(ids, pairs, strict=True):
        robots += [
            "--robot",
            f"{rid}={name}:{s.real:.4f},{s.imag:.4f},{th:.4f}:r={RADIUS}:drive=unicycle",
        ]
    procs = [spawn("-v", "serve", "router", "--listen", ep, log=logs / "router.log")]
    try:
        time.sleep(1.0)
        t_launch = time.monotonic()
        procs.append(
            spawn(
                "-v",
                "serve",
                "transform",
                *common,
                *wsarg,
                "--workers",
                "2",
                log=logs / "transform.log",
            )
        )
        hints = [] if args.route_hints else ["--no-route-hints"]
        procs.append(
            spawn("-v", "serve", "controller", *common, *hints, log=logs / "controller.log")
        )
        procs.append(
            spawn(
                "-v",
                "serve",
                "simulator",
                *common,
                *wsarg,
                *robots,
                "--rate",
                "50",
                *([] if args.maps_ahead else ["--no-maps-ahead"]),
                log=logs / "simulator.log",
            )
        )
        with connect(ep) as bus:
            w = Watch(bus, ids, nav_ws_id)
            require_services(bus, 90, logs)
            t_up = time.monotonic()
            wait(lambda: base_settled(w, name), args.settle)
            t_base = time.monotonic()
            idle = bool(
                wait(lambda: transform_idle(w), max(0.0, args.settle - (t_base - t_up)), period=0.2)
            )
            wait(lambda: all(w.poses[r] for r in ids), 30)
            row["base_settled_s"] = round(t_base - t_up, 2)
            row["transform_idle_at_goal"] = idle
            row["services_up_s"] = round(t_up - t_launch, 2)
            row["load_at_goal"] = loadavg()
            t0 = time.monotonic()
            stamp = time.time_ns()
            for g in goals:
                bus.publish(
                    K.robot(g.robot_id, "goal"), encode(g.model_copy(update={"stamp_ns": stamp}))
                )

            def done() -> bool:
                with w.lock:
                    return all(
                        any(t >= t0 and s.state == "arrived" for t, s in w.status[r]) for r in ids
                    )

            wait(done, args.arrive_timeout, period=0.2)
            time.sleep(0.5)
            with w.lock:
                cmds = {r: [(t - t0, c) for t, c in w.cmds[r] if t >= t0] for r in ids}
                status = {r: [(t - t0, s) for t, s in w.status[r] if t >= t0] for r in ids}
                poses = {r: [p for t, p in w.poses[r] if t >= t0] for r in ids}
                events = [e for t, e in w.events if t >= t0]
                indexes = [(t - t0, i) for t, i in w.indexes if t >= t0]
                health = dict(w.health)
        first_idx = next(((t, i) for t, i in indexes if any(not c.pending for c in i.cells)), None)
        robots_out = []
        for k, rid in enumerate(ids):
            s, g, th = pairs[k]
            moving = [
                t
                for t, c in cmds[rid]
                if c.linear[0] != 0.0 or c.linear[1] != 0.0 or c.angular != 0.0
            ]
            arrived = [t for t, st in status[rid] if st.state == "arrived"]
            nav = [(t, st) for t, st in status[rid] if st.state == "navigating"]
            look = s + LOOKAHEAD * np.exp(1j * th)
            last = status[rid][-1][1] if status[rid] else None
            robots_out.append(
                {
                    "robot": rid,
                    "start": [s.real, s.imag],
                    "heading": th,
                    "goal": [g.real, g.imag],
                    "first_cmd_s": round(moving[0], 3) if moving else None,
                    "first_navigating_s": round(nav[0][0], 3) if nav else None,
                    "first_navigating_message": nav[0][1].message[:160] if nav else None,
                    "arrived": bool(arrived),
                    "arrive_s": round(arrived[0], 2) if arrived else None,
                    "start_in_first": None if first_idx is None else in_cells(first_idx[1], look),
                    "wall_events": sum(
                        1 for e in events if e.robot_id == rid and e.other_robot_id is None
                    ),
                    "robot_events": sum(
                        1 for e in events if e.robot_id == rid and e.other_robot_id is not None
                    ),
                    "last_status": None
                    if last is None
                    else [last.state, last.reason, last.message[:160]],
                    "last_pose": None
                    if not poses[rid]
                    else [poses[rid][-1].x, poses[rid][-1].y, poses[rid][-1].theta],
                    **body_collisions(ws, poses[rid], RADIUS),
                }
            )
        tr = health.get("transform")
        ctl = health.get("controller")
        row.update(
            {
                "nav_ws": nav_ws_id,
                "first_partial_s": None if first_idx is None else round(first_idx[0], 3),
                "first_partial_charts": None
                if first_idx is None
                else sum(not c.pending for c in first_idx[1].cells),
                "first_partial_cells": None if first_idx is None else len(first_idx[1].cells),
                "revisions_after_goal": len(indexes),
                "route_hints_received": None if tr is None else tr.counters.get("route_hints", 0),
                "route_hints_sent": None
                if ctl is None
                else ctl.counters.get("route_hints_sent", 0),
                "robots": robots_out,
                "load_end": loadavg(),
            }
        )
        return row
    finally:
        stop(procs[::-1])


def summarize(rows: list[dict[str, Any]], target: float) -> dict[str, Any]:
    rs = [r for m in rows for r in m.get("robots", [])]
    firsts = [r["first_cmd_s"] for r in rs]
    ok = [f for f in firsts if f is not None]
    return {
        "robots": len(rs),
        "moved": len(ok),
        "within_target": sum(f <= target for f in ok),
        "arrived": sum(r["arrived"] for r in rs),
        "wall_events": sum(r["wall_events"] for r in rs),
        "robot_events": sum(r["robot_events"] for r in rs),
        "body_collisions": sum(r["body_collisions"] for r in rs),
        "first_cmd_max_s": max(ok) if ok else None,
        "first_cmd_median_s": float(np.median(ok)) if ok else None,
    }


def table(doc: dict[str, Any]) -> None:
    t = doc["target_first_cmd_s"]
    print(
        f"\n{'map':<12}{'robot':>6}{'first cmd s':>12}{'<=2s':>6}{'arrived':>9}{'arrive s':>9}"
        f"{'wall':>5}{'body':>5}{'rr':>4}{'start 1st':>10}  load at goal"
    )
    for m in doc["maps"]:
        if "error" in m:
            print(f"{m['map']:<12} error: {m['error']}")
            continue
        for r in m["robots"]:
            f = r["first_cmd_s"]
            print(
                f"{m['map']:<12}{r['robot']:>6}{'-' if f is None else f'{f:.2f}':>12}"
                f"{'yes' if f is not None and f <= t else 'no':>6}{r['arrived']!s:>9}"
                f"{'-' if r['arrive_s'] is None else r['arrive_s']:>9}{r['wall_events']:>5}"
                f"{r['body_collisions']:>5}{r['robot_events']:>4}"
                f"{r['start_in_first']!s:>10}  {m['load_at_goal'].split()[0]}"
            )
        print(
            f"{'':12}first partial atlas {m['first_partial_s']} s after the goals "
            f"({m['first_partial_charts']} of {m['first_partial_cells']} charts); route hints "
            f"sent {m['route_hints_sent']}, received {m['route_hints_received']}; transform "
            f"idle at goal: {m['transform_idle_at_goal']}"
        )
    print(f"summary: {doc['summary']}")


def main(argv: list[str]) -> int:
    import argparse

    from bench_slam import LOOKAHEAD, MAPS, QUICK_MAPS, RADIUS, READY_TARGET_S, SEED

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", nargs="+", choices=MAPS, default=None)
    ap.add_argument("--pairs", type=int, default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--settle",
        type=float,
        default=SETTLE_S,
        help="s to wait for the base map and an idle transform before the goals",
    )
    ap.add_argument("--arrive-timeout", type=float, default=ARRIVE_TIMEOUT_S)
    ap.add_argument(
        "--route-hints",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="--no-route-hints: the controller sends none (the transform's own order)",
    )
    ap.add_argument(
        "--maps-ahead",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the simulator asks for its robots' footprint maps at start (the default, as "
        "`serve simulator` does); --no-maps-ahead: the footprint map is first asked for by "
        "the goals (its first use)",
    )
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # stop the services (finally)
    maps = args.maps or (QUICK_MAPS if args.quick else MAPS)
    n = args.pairs or (QUICK_PAIRS if args.quick else PAIRS)
    out = args.out or (RESULTS.with_suffix(".quick.json") if args.quick else RESULTS)
    tmp = Path(tempfile.mkdtemp(prefix="confnav-slamsvc-"))
    doc: dict[str, Any] = {
        "benchmark": "slam_services",
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_start": loadavg(),
        "cpu_count": os.cpu_count(),
        "body": {"radius": RADIUS, "lookahead": LOOKAHEAD, "drive": "unicycle"},
        "seed": SEED,
        "pairs_per_map": n,
        "settle_s": args.settle,
        "route_hints": args.route_hints,
        "maps_ahead": args.maps_ahead,
        "arrive_timeout_s": args.arrive_timeout,
        "target_first_cmd_s": READY_TARGET_S,
        "maps": [],
    }
    for name in maps:
        t = time.monotonic()
        try:
            row = run_map(name, n, args, tmp)
        except Exception as exc:  # a map that fails is a result, the others still run
            row = {"map": name, "error": f"{type(exc).__name__}: {exc}", "load_end": loadavg()}
        row["wall_s"] = round(time.monotonic() - t, 1)
        doc["maps"].append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "robots"}), flush=True)
        for r in row.get("robots", []):
            print("   ", json.dumps(r), flush=True)
        out.write_text(json.dumps(doc, indent=1) + "\n")  # partial results survive
    doc["summary"] = summarize(doc["maps"], READY_TARGET_S)
    doc["loadavg_end"] = loadavg()
    out.write_text(json.dumps(doc, indent=1) + "\n")
    table(doc)
    print(f"wrote {out} (logs in {tmp})")
    return 0
