"""Fleets that avoid each other: robot-robot contacts, arrival and the filter's cost.

    python bench/bench_fleet.py [--quick] [--out bench/results/fleet.json]

Core simulation (:func:`confnav.navigation.fleet_sim.simulate_fleet`: every robot its own
Controller and goal on one map, commands held 0.05 s, pairwise barrier rows + side passing +
the wall hold cap, contacts checked along every step with swept disks and the core's chord
check).  Scenarios (disk robots r = 0.2 m, v_max 0.5 m/s, maps of the free space shrunk by r):

* ``swap N``: N robots on a ring of radius 3.5 m (3.0 m for N <= 4) in a 10 x 8 m room with
  two 1.2 m boxes, each sent to the opposite point;
* ``door 8``: two 4.9 m rooms joined by a 1.2 m door in a 0.2 m wall, 4 robots each way;
* ``person``: one robot crossing the room while a person (disk 0.3 m, 1.2 m/s) walks across
  its path, timed to meet it (without the filter the two touch);
* ``warehouse``: 20 unicycles (body 0.2 m, look-ahead 0.1 m, omega_max 2 rad/s) in the
  README's ``examples/warehouse.yaml`` (map of the free space shrunk by 0.3 m, tol 1e-4,
  solved once per run), 10 rounds of random goals: every robot has 10 random goals (goal k
  of all robots at least 0.8 m apart), the next one issued when it reaches the current one;
  a robot done with its 10 goals parks at the last (and yields to robots it blocks, the
  rule of ``fleet.yield_way``); 200 goals, time limit 900 s (skip: ``--no-warehouse``).
  Three designs on the same goals: ``warehouse_roadmap`` (the robots move on a roadmap as
  planned by PIBT, :mod:`confnav.navigation.fleet_coord`; done robots park on the roadmap
  and are pushed aside), ``warehouse`` (the local rules that are on by default) and
  ``warehouse_gates`` (single-lane passages as mutexes); ``--roadmap-only`` runs the first.

Per scenario: robot-robot, mover and wall contacts, arrival %, time to the last arrival
against the slowest robot's lone run (the same robot alone on the same map; target <= 2x),
deadlocks detected, infeasible projections, the filter's cost per robot and step (rows,
side passing, projection, the wall cap's clearance; Python overhead included, so small
fleets pay more per robot), and the same run without the filter (``ghost contacts``).
A batched cost row measures rows + projection alone for 200 robots.  Prints a table, writes
JSON with the commit and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import git, loadavg

from confnav import Controller, Workspace, inflate, solve
from confnav.navigation.fleet import pairwise_rows, project_rows
from confnav.navigation.fleet_sim import Mover, simulate_fleet

RESULTS = Path(__file__).resolve().parent / "results"
R = 0.2
TOL = 1e-6
T_MAX = 200.0
WAREHOUSE_T_MAX = 900.0
#: Koditschek-Rimon on the warehouse: with the default harmonic function a lone unicycle of
#: this run (goal 4.46+7.19j, start 8.36+0.55j in the bottom aisle) was driven into the aisle's
#: wall and stopped there (the far field of G is rounding-limited on this map: its gradient
#: in the bottom aisle points at the wall), and each new goal's harmonic fit costs 0.25-30 s.
WAREHOUSE_NAVFN = "kr"
STALL_S = 240.0  # services: no goal reached for this long (nominal sim s) ends the run
STATUS_HISTORY = 8  # services: distinct statuses kept per robot (the unarrived's records)
NEIGHBOUR_R = 2.0  # services: an unarrived robot's neighbours at the end lie within (m)

ROOM = Workspace(
    [(0, 0), (10, 0), (10, 8), (0, 8)],
    [
        [(3, 2.5), (4.2, 2.5), (4.2, 3.7), (3, 3.7)],
        [(6, 4.5), (7.2, 4.5), (7.2, 5.7), (6, 5.7)],
    ],
)
DOOR = Workspace(
    [
        (0, 0), (4.9, 0), (4.9, 3.4), (5.1, 3.4), (5.1, 0), (10, 0), (10, 8), (5.1, 8),
        (5.1, 4.6), (4.9, 4.6), (4.9, 8), (0, 8),
    ]
)  # fmt: skip


def shrunk_map(ws: Workspace) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(inflate(ws, R), TOL)


def run(
    ws: Workspace,
    cmap: Any,
    starts: np.ndarray,
    goals: np.ndarray,
    movers: list[Mover] = (),
    roadmap: bool = False,
    auto: bool = False,
) -> dict[str, Any]:
    """One scenario (``roadmap``: with the PIBT coordinator, as ``--fleet-coordinator
    roadmap`` in the controller service; ``auto``: the roadmap if
    :func:`~confnav.navigation.fleet_coord.choose_coordinator` chooses it, as
    ``--fleet-coordinator auto``)."""
    ctrls = [Controller(cmap, g) for g in goals]
    coord = None
    choice: dict[str, Any] = {}
    if roadmap or auto:
        from confnav.navigation.fleet_coord import RoadmapCoordinator, choose_coordinator

        coord = RoadmapCoordinator.build(cmap, len(ctrls), R)
        if auto:
            pick, width, where = choose_coordinator(coord, R)
            choice = {"auto_choice": pick, "narrowest_passage_m": width,
                      "narrowest_at": [where.real, where.imag]}  # fmt: skip
            if pick == "local":
                coord = None
    t0 = time.perf_counter()
    res = simulate_fleet(ctrls, starts, ws, radius=R, movers=movers, t_max=T_MAX, coordinator=coord)
    wall = time.perf_counter() - t0
    ghost = simulate_fleet(ctrls, starts, ws, radius=R, movers=movers, t_max=T_MAX, avoid=False)
    lone = [
        simulate_fleet([c], [s], ws, radius=R, t_max=T_MAX).arrival_time[0]
        for c, s in zip(ctrls, starts, strict=True)
    ]
    slowest = float(np.nanmax(lone))
    last = res.last_arrival
    return {
        "robots": len(ctrls),
        "robot_contacts": res.robot_contacts,
        "mover_contacts": res.mover_contacts,
        "wall_contacts": res.wall_contacts,
        "arrived_pct": 100.0 * res.arrival_rate,
        "last_arrival_s": last if np.isfinite(last) else None,
        "slowest_lone_s": slowest,
        "ratio": last / slowest if np.isfinite(last) else None,
        "min_gap_m": res.min_gap if np.isfinite(res.min_gap) else None,
        "min_mover_gap_m": res.min_mover_gap if np.isfinite(res.min_mover_gap) else None,
        "min_wall_clearance_m": res.min_wall_clearance,
        "deadlocks": res.deadlocks,
        "infeasible": res.infeasible,
        "filter_us_per_robot_step": res.filter_us_per_robot_step,
        "steps": res.steps,
        "wall_s": wall,
        "ghost_robot_contacts": ghost.robot_contacts,
        "ghost_mover_contacts": ghost.mover_contacts,
        **choice,
    }


def ring(n: int) -> tuple[np.ndarray, np.ndarray]:
    rad = 3.0 if n <= 4 else 3.5
    ang = 2 * np.pi * np.arange(n) / n + 0.1  # off the axes: no robot starts on a box's axis
    starts = 5 + 4j + rad * np.exp(1j * ang)
    return starts, 5 + 4j - rad * np.exp(1j * ang)


def door() -> tuple[np.ndarray, np.ndarray]:
    ys = np.array([2.5, 3.5, 4.5, 5.5])
    left = 2.0 + 1j * ys
    right = 8.0 + 1j * ys[::-1]
    return np.concatenate([left, right]), np.concatenate([right, left])


_WAREHOUSE_MAP: dict[float, tuple[Any, Any, float]] = {}


def run_start() -> dict[str, Any]:
    """A results file's provenance at the start of a run: the commit (the code the run and
    its processes use), whether the tree was dirty, the start time and load."""
    return {
        "commit": git("rev-parse", "HEAD"),
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
        "started": datetime.now(UTC).isoformat(timespec="seconds"),
        "load_before": loadavg(),
    }


def run_end(stamp: dict[str, Any]) -> dict[str, Any]:
    """The provenance block of a results file: :func:`run_start`'s with the end time and
    load (the keys in the order the files have always had)."""
    return {
        "commit": stamp["commit"],
        "dirty": stamp["dirty"],
        "started": stamp["started"],
        "finished": datetime.now(UTC).isoformat(timespec="seconds"),
        "load_before": stamp["load_before"],
        "load_after": loadavg(),
    }


def warehouse_map(inflate_by: float) -> tuple[Any, Any, float]:
    """The README's warehouse, its map shrunk by ``inflate_by`` (solved once per run) and the
    solve's wall time."""
    if inflate_by not in _WAREHOUSE_MAP:
        from confnav import import_map

        root = Path(__file__).resolve().parent.parent
        ws = import_map(str(root / "examples" / "warehouse.yaml"))
        ws = getattr(ws, "workspace", ws)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cmap = solve(inflate(ws, inflate_by), 1e-4)
        _WAREHOUSE_MAP[inflate_by] = (ws, cmap, time.perf_counter() - t0)
    return _WAREHOUSE_MAP[inflate_by]


_WAREHOUSE_CTRLS: dict[tuple[int, int], list[list[Controller]]] = {}


def free_spots(shrunk: Any, rng: np.random.Generator, k: int) -> np.ndarray:
    """``k`` random points of the shrunk free space at least 0.05 m inside it and 0.8 m
    apart (the warehouse rounds' starts and goals, core and services alike)."""
    xs = [z.real for z in shrunk.outer]
    ys = [z.imag for z in shrunk.outer]
    out: list[complex] = []
    while len(out) < k:
        c = complex(rng.uniform(min(xs), max(xs)), rng.uniform(min(ys), max(ys)))
        if shrunk.clearance(np.array([c]))[0] < 0.05:
            continue
        if out and np.min(np.abs(np.array(out) - c)) < 0.8:
            continue
        out.append(c)
    return np.array(out)


def warehouse(
    rounds: int,
    seed: int = 0,
    yielding: bool = True,
    traffic: bool = False,
    roadmap: bool = False,
    node_law: str = "kr",
    aside: str | None = None,
    come_back: str | None = None,
) -> dict[str, Any]:
    """20 unicycles, ``rounds`` random goals each in the README's warehouse, a new goal issued
    on arrival; a robot done with its goals parks at its last one (and yields).  ``traffic``:
    the single-lane passages as mutexes and the goal-conflict rule (``simulate_fleet``'s
    ``traffic`` and ``goal_yield``).  ``roadmap``: the robots move on a roadmap as planned by
    :class:`confnav.navigation.fleet_coord.RoadmapCoordinator` (PIBT; done robots park on
    the roadmap and are pushed aside)."""
    rd, d, n = 0.2, 0.1, 20
    ws, cmap, solve_s = warehouse_map(rd + d)
    shrunk = cmap.workspace
    rng = np.random.default_rng(seed)

    def spots(k: int) -> np.ndarray:
        return free_spots(shrunk, rng, k)

    p = spots(n)  # look-ahead points at the start
    th = rng.uniform(-np.pi, np.pi, n)
    x = p - d * np.exp(1j * th)
    goals = np.array([spots(n) for _ in range(rounds)])  # round k: n goals 0.8 m apart
    key = (rounds, seed)
    if key not in _WAREHOUSE_CTRLS:  # the same goals in every variant: built once per run
        _WAREHOUSE_CTRLS[key] = [
            [Controller(cmap, g, navfn=WAREHOUSE_NAVFN) for g in goals[:, i]] for i in range(n)
        ]
    ctrls = _WAREHOUSE_CTRLS[key]
    coord = None
    if roadmap:
        from confnav.navigation.fleet_coord import RoadmapCoordinator

        coord = RoadmapCoordinator.build(cmap, n, rd + d, node_law=node_law)
        if aside is not None:  # which pushed robots step aside first (pibt_step)
            coord.aside = aside
        if come_back is not None:  # when a done robot pushed off its goal goes back
            coord.come_back = come_back
    t0 = time.perf_counter()
    res = simulate_fleet(
        [c[0] for c in ctrls],
        x,
        ws,
        radius=rd,
        lookahead=d,
        theta=th,
        omega_max=2.0,
        t_max=WAREHOUSE_T_MAX,
        next_goals=[c[1:] for c in ctrls],
        yielding=yielding,
        traffic=traffic,
        goal_yield=traffic,
        coordinator=coord,
    )
    wall = time.perf_counter() - t0
    assert res.reached is not None
    reached = int(res.reached.sum())
    print(
        f"#   warehouse{'' if yielding else ' (no yield rule)'}{' (gates)' if traffic else ''}"
        f"{' (roadmap)' if roadmap else ''}: "
        f"{reached}/{res.goals} goals "
        f"reached, {res.robot_contacts} robot / {res.wall_contacts} wall contacts, "
        f"t {res.t_end:.1f} s, {wall:.0f} s wall (load {loadavg()})",
        flush=True,
    )
    return {
        "robots": n,
        "rounds": rounds,
        "navfn": WAREHOUSE_NAVFN,
        "yield_rule": yielding,
        "traffic": traffic,
        "roadmap": roadmap,
        "roadmap_nodes": coord.roadmap.size if coord is not None else None,
        "roadmap_edges": len(coord.roadmap.edges) if coord is not None else None,
        "ticks": coord.ticks if coord is not None else None,
        "idle_ticks": coord.idle_ticks if coord is not None else None,
        "tick_timeouts": coord.timeouts if coord is not None else None,
        "reverts": coord.reverts if coord is not None else None,
        "node_law": node_law if coord is not None else None,
        "gates": res.gates,
        "gate_waits": res.waits,
        "goal_yield_steps": res.goal_yields,
        "solve_s": solve_s,
        "robot_contacts": res.robot_contacts,
        "wall_contacts": res.wall_contacts,
        "goals": res.goals,
        "reached": reached,
        "arrived_pct": 100.0 * reached / res.goals,
        "robots_done": int(res.arrived.sum()),
        "last_arrival_s": res.last_arrival if np.isfinite(res.last_arrival) else None,
        "t_end_s": res.t_end,
        "t_max_s": WAREHOUSE_T_MAX,
        "min_gap_m": res.min_gap if np.isfinite(res.min_gap) else None,
        "min_wall_clearance_m": res.min_wall_clearance,
        "deadlocks": res.deadlocks,
        "yield_steps": res.yields,
        "infeasible": res.infeasible,
        "filter_us_per_robot_step": res.filter_us_per_robot_step,
        "steps": res.steps,
        "wall_s": wall,
    }


def warehouse_goals(rounds: int, seed: int = 0) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """The warehouse (unshrunk), the 20 unicycles' axles and headings at the start and their
    ``rounds`` goals per robot (``goals[k, i]``): the same draws as :func:`warehouse` (points
    of the free space shrunk by r + d, at least 0.05 m inside it, 0.8 m apart)."""
    from confnav import import_map

    rd, d, n = 0.2, 0.1, 20
    root = Path(__file__).resolve().parent.parent
    ws = import_map(str(root / "examples" / "warehouse.yaml"))
    ws = getattr(ws, "workspace", ws)
    shrunk = inflate(ws, rd + d)
    rng = np.random.default_rng(seed)

    def spots(k: int) -> np.ndarray:
        return free_spots(shrunk, rng, k)

    p = spots(n)
    th = rng.uniform(-np.pi, np.pi, n)
    x = p - d * np.exp(1j * th)
    goals = np.array([spots(n) for _ in range(rounds)])
    return ws, x, th, goals


def services_warehouse(
    rounds: int, coordinator: str, time_scale: float, t_max: float, seed: int = 0
) -> dict[str, Any]:
    """The warehouse rounds through the services: a router, a transform, a controller
    (``--fleet-coordinator coordinator``) and a simulator (20 Hz steps, ``time_scale`` times
    real time, one ``PoseBatch`` per step), each its own process on loopback TCP; this
    process is the client: it publishes the warehouse's definition, spawns the 20 unicycles
    (``SpawnRequest``, r 0.2 m, look-ahead 0.1 m), sends each robot its next ``Goal`` when a
    status says it arrived at the current one (``arrived`` within 0.15 m of it, the axle
    being 0.1 m behind the steered point), and counts the simulator's ``CollisionEvent``s
    (robot-robot contacts once per pair, walls once per robot), until every goal is reached
    or ``t_max`` s of simulated time (nominal: wall time x ``time_scale``) have passed, or no
    goal was reached for :data:`STALL_S` s (``stalled``)."""
    import tempfile

    from bench_services import connect, cpu_seconds, free_port, spawn
    from confnav.schemas import (
        CollisionEvent,
        Goal,
        RobotStatus,
        SpawnRequest,
        decode,
        encode,
    )
    from confnav.services.definitions import definition_of
    from confnav.services.keys import Keys

    keys = Keys()
    ws, x, th, goals = warehouse_goals(rounds, seed)
    n = x.size
    rid = [f"w{i:02d}" for i in range(n)]
    tmp = Path(tempfile.mkdtemp(prefix="confnav-fleet-"))
    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--mode", "client", "--connect", ep]
    procs: dict[str, Any] = {}
    lock = threading.Lock()
    k_of = [0] * n  # index of each robot's current goal
    sent_ns = [0] * n
    reached_t: list[list[float]] = [[] for _ in range(n)]
    pairs: set[tuple[str, str]] = set()
    walls: set[str] = set()
    waits: dict[str, int] = {}
    statuses = 0
    # per robot: the last status and the last STATUS_HISTORY distinct (state, reason, message)
    # with the nominal time each began (what a robot that does not arrive was doing)
    last: list[Any] = [None] * n
    history: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    try:
        procs["router"] = spawn("serve", "router", "--listen", ep, log=tmp / "router.log")
        wait_port(ep, 120.0)  # a loaded box: the router's start took over 30 s
        procs["transform"] = spawn("serve", "transform", *common, "--cache-dir",
                                   str(tmp / "cache"), log=tmp / "transform.log")  # fmt: skip
        procs["controller"] = spawn("-v", "serve", "controller", *common,  # -v: auto's choice
                                    "--fleet-coordinator", coordinator,
                                    log=tmp / "controller.log")  # fmt: skip
        procs["simulator"] = spawn("serve", "simulator", *common, "--rate", "20",
                                   "--time-scale", str(time_scale), "--pose-batch",
                                   log=tmp / "simulator.log")  # fmt: skip
        bus = connect(ep)
        t0 = [0.0]

        def send_goal(i: int) -> None:
            g = goals[k_of[i], i]
            sent_ns[i] = time.time_ns()
            bus.publish(keys.robot(rid[i], "goal"), encode(Goal(
                robot_id=rid[i], ws_id="warehouse", goal=(g.real, g.imag), navfn=WAREHOUSE_NAVFN,
                robot_radius=0.2, drive="unicycle", lookahead=0.1, omega_max=2.0)))  # fmt: skip

        def on_status(key: str, payload: bytes) -> None:
            nonlocal statuses
            s = decode(RobotStatus, payload)
            if not s.robot_id.startswith("w") or s.position is None:
                return
            i = int(s.robot_id[1:])
            with lock:
                statuses += 1
                last[i] = s
                h = history[i]
                if not h or (h[-1]["state"], h[-1]["reason"], h[-1]["message"]) != (
                    s.state, s.reason, s.message):  # fmt: skip
                    h.append({"t_s": (time.monotonic() - t0[0]) * time_scale, "state": s.state,
                              "reason": s.reason, "message": s.message,
                              "position": s.position})  # fmt: skip
                    del h[:-STATUS_HISTORY]
                if s.message.startswith("waiting for"):
                    waits[s.robot_id] = waits.get(s.robot_id, 0) + 1
                if k_of[i] >= rounds or s.state != "arrived" or s.stamp_ns < sent_ns[i]:
                    return
                g = goals[k_of[i], i]
                if abs(complex(*s.position) - g) > 0.15:
                    return  # parked on the roadmap, or an earlier goal's status
                reached_t[i].append((time.monotonic() - t0[0]) * time_scale)
                k_of[i] += 1
                if k_of[i] < rounds:
                    send_goal(i)

        def on_collision(key: str, payload: bytes) -> None:
            e = decode(CollisionEvent, payload)
            with lock:
                if e.other_robot_id is None:
                    walls.add(e.robot_id)
                else:
                    a, b = sorted((e.robot_id, e.other_robot_id))
                    pairs.add((a, b))

        bus.subscribe(keys.any_robot("status"), on_status)
        bus.subscribe(keys.any_robot("collision"), on_collision)
        deadline = time.monotonic() + 60
        while len(bus.alive(keys.alive_of("controller"))) < 1 or not bus.alive(
            keys.alive_of("transform")
        ):
            if time.monotonic() > deadline:
                raise RuntimeError("services did not come up")
            time.sleep(0.2)
        defn = definition_of("warehouse", ws, 1e-4)
        bus.publish(keys.ws("warehouse", "definition"), encode(defn))
        time.sleep(2.0)  # the simulator learns the walls from the definition
        for i in range(n):
            bus.publish(keys.sim("sim", "spawn"), encode(SpawnRequest(
                robot_id=rid[i], ws_id="warehouse", position=(x[i].real, x[i].imag),
                theta=float(th[i]), robot_radius=0.2, drive="unicycle")))  # fmt: skip
        time.sleep(1.0)
        t0[0] = time.monotonic()
        for i in range(n):
            send_goal(i)
        cpu0 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        last_progress = time.monotonic()
        done_before = 0
        stalled = False
        while (time.monotonic() - t0[0]) * time_scale < t_max:
            time.sleep(1.0)
            with lock:
                done = sum(k_of)
            if done >= n * rounds:
                break
            if done != done_before:
                done_before, last_progress = done, time.monotonic()
            elif (time.monotonic() - last_progress) * time_scale > STALL_S:
                stalled = True
                break
            sim_t = (time.monotonic() - t0[0]) * time_scale
            if int(sim_t) % 30 == 0:
                print(f"#   {coordinator}: {done}/{n * rounds} goals, {sim_t:.0f} s", flush=True)
        wall = time.monotonic() - t0[0]
        cpu = {k: cpu_seconds(p.pid) - cpu0[k] for k, p in procs.items()}
        bus.close()
    finally:
        for p in procs.values():
            p.terminate()
        for p in procs.values():
            try:
                p.wait(timeout=10)
            except Exception:
                p.kill()
    reached = sum(k_of)
    arrivals = [t for ts in reached_t for t in ts]
    log_lines = (tmp / "controller.log").read_text(errors="replace").splitlines()
    unarrived = not_arrived(rid, k_of, rounds, goals, last, history, log_lines)
    fleet_log = [ln for ln in log_lines if "fleet coordinator auto" in ln or "fleet roadmap" in ln]
    print(
        f"#   services warehouse ({coordinator}): {reached}/{n * rounds} goals, "
        f"{len(pairs)} robot pairs / {len(walls)} wall contacts, wall {wall:.0f} s "
        f"(load {loadavg()})",
        flush=True,
    )
    return {
        "coordinator": coordinator,
        "robots": n,
        "rounds": rounds,
        "seed": seed,
        "navfn": WAREHOUSE_NAVFN,
        "goals": n * rounds,
        "reached": reached,
        "arrived_pct": 100.0 * reached / (n * rounds),
        "robot_contacts": len(pairs),
        "robot_contact_pairs": sorted(pairs),
        "wall_contacts": len(walls),
        "last_arrival_s": max(arrivals) if arrivals else None,
        "t_max_s": t_max,
        "stalled": stalled,
        "stall_s": STALL_S,
        "time_scale": time_scale,
        "sim_rate_hz": 20.0,
        "wall_s": wall,
        "cpu_s": cpu,
        "statuses": statuses,
        "waiting_statuses": sum(waits.values()),
        "controller_fleet_log": fleet_log[:10],
        "not_arrived": unarrived,
        "final_statuses": final_statuses(rid, last, k_of),
        "note": "times are nominal simulated seconds (wall time x time_scale) since the first "
        "goals; the simulator steps at 20 Hz of simulated time",
    }


def final_statuses(rid: list[str], last: list[Any], k_of: list[int]) -> dict[str, Any]:
    """Every robot's last status and goals reached (what the fleet around a stalled robot
    was doing)."""
    return {
        r: None
        if s is None
        else {
            "state": s.state,
            "reason": s.reason,
            "message": s.message,
            "position": s.position,
            "goals_reached": k,
        }
        for r, s, k in zip(rid, last, k_of, strict=True)
    }


def wait_port(ep: str, timeout: float) -> None:
    """Wait until the router accepts TCP connections on ``ep`` (``tcp/host:port``)."""
    import socket

    host, port = ep.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host, int(port)), timeout=1.0).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no router on {ep} after {timeout} s") from None
            time.sleep(0.3)


def not_arrived(
    rid: list[str],
    k_of: list[int],
    rounds: int,
    goals: np.ndarray,
    last: list[Any],
    history: list[list[dict[str, Any]]],
    log_lines: list[str],
) -> list[dict[str, Any]]:
    """One record per robot that did not reach all its goals: the goal it was on, its last
    status (state, reason, message, position, distance to goal), its last
    :data:`STATUS_HISTORY` distinct statuses, its neighbours at the end (every other robot
    whose last status position is within :data:`NEIGHBOUR_R` m, nearest first, with its
    state, message and whether it was done) and the controller's last log lines naming it."""
    out = []
    for i, r in enumerate(rid):
        if k_of[i] >= rounds:
            continue
        s = last[i]
        g = goals[k_of[i], i]
        pos = complex(*s.position) if s is not None and s.position is not None else None
        nbrs = []
        for j, o in enumerate(last):
            if j == i or o is None or o.position is None or pos is None:
                continue
            dist = abs(complex(*o.position) - pos)
            if dist <= NEIGHBOUR_R:
                nbrs.append({"robot": rid[j], "distance_m": dist, "position": o.position,
                             "state": o.state, "reason": o.reason, "message": o.message,
                             "done": k_of[j] >= rounds})  # fmt: skip
        nbrs.sort(key=lambda e: e["distance_m"])
        out.append({
            "robot": r,
            "goal_index": k_of[i],
            "goal": (float(g.real), float(g.imag)),
            "last_position": s.position if s is not None else None,
            "distance_to_goal_m": abs(pos - g) if pos is not None else None,
            "last_status": None if s is None else {
                "state": s.state, "reason": s.reason, "message": s.message,
                "distance_to_goal": s.distance_to_goal, "chart": s.chart},
            "status_history": history[i],
            "neighbours": nbrs,
            "controller_log": [ln for ln in log_lines if r in ln][-8:],
        })  # fmt: skip
    return out


def batched_cost(n: int = 200, reps: int = 20) -> dict[str, Any]:
    """rows + projection for n robots (r 0.2) at random in a 30 x 30 m hall, 3 per 10 m^2."""
    rng = np.random.default_rng(0)
    z = rng.random(n) * 30 + 1j * rng.random(n) * 30
    keep = [0]
    for i in range(1, n):  # no overlaps
        if np.min(np.abs(z[i] - z[keep])) > 0.45:
            keep.append(i)
    z = z[keep]
    u = 0.5 * np.exp(2j * np.pi * rng.random(z.size))
    t0 = time.perf_counter()
    for _ in range(reps):
        rows = pairwise_rows(z, R, 0.5)
        project_rows(u, rows.a, rows.b, 0.5)
    dt = (time.perf_counter() - t0) / reps
    return {
        "robots": int(z.size),
        "us_per_robot": 1e6 * dt / z.size,
        "rows_per_robot_max": int(rows.count.max()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="swaps of 4 and 8 and the person only")
    ap.add_argument("--out", type=Path, default=RESULTS / "fleet.json")
    ap.add_argument("--no-warehouse", action="store_true", help="skip the warehouse rounds")
    ap.add_argument("--rounds", type=int, default=10, help="warehouse goals per robot")
    ap.add_argument(
        "--roadmap-only", action="store_true", help="only the roadmap row of the warehouse"
    )
    ap.add_argument(
        "--extra-seeds",
        type=int,
        default=0,
        help="the roadmap row again on the goals of seeds 1..N (warehouse_roadmap_seeds)",
    )
    ap.add_argument(
        "--services",
        action="store_true",
        help="only the warehouse through the services (router, transform, controller and "
        "simulator processes), with each --coordinator; writes results/fleet_services.json",
    )
    ap.add_argument(
        "--roadmap-scenarios",
        action="store_true",
        help="only the swaps and the door with the roadmap coordinator and with the local "
        "rules (the controller service's two --fleet-coordinator choices); writes "
        "results/fleet_roadmap_scenarios.json",
    )
    ap.add_argument(
        "--node-laws",
        action="store_true",
        help="only the warehouse with the roadmap coordinator, Koditschek-Rimon node laws "
        "against straight ones (LineLaw, the laws on an atlas); writes "
        "results/fleet_node_laws.json",
    )
    ap.add_argument(
        "--coordinator",
        action="append",
        choices=("roadmap", "local", "auto"),
        help="--services and --roadmap-scenarios: the --fleet-coordinator choices to run "
        "(repeatable; default roadmap, resp. local and roadmap)",
    )
    ap.add_argument("--seed", type=int, default=0, help="services: the warehouse goals' seed")
    ap.add_argument(
        "--aside",
        action="append",
        choices=("all", "done"),
        help="--node-laws: the straight node laws with each of these pushed-robot rules "
        "(RoadmapCoordinator.aside); writes results/fleet_node_laws_aside.json",
    )
    ap.add_argument(
        "--come-back",
        action="append",
        choices=("idle", "clear"),
        help="--node-laws: the straight node laws, seeds 0 and 1, with each of these rules for "
        "when a pushed done robot goes back (RoadmapCoordinator.come_back); writes "
        "results/fleet_node_laws_comeback.json (or --out)",
    )
    ap.add_argument("--time-scale", type=float, default=2.0, help="services: simulator speed")
    ap.add_argument("--t-max", type=float, default=WAREHOUSE_T_MAX, help="services: sim s")
    args = ap.parse_args()
    if args.services:
        services_main(args)
        return
    if args.roadmap_scenarios:
        roadmap_scenarios_main(args)
        return
    if args.node_laws:
        node_laws_main(args)
        return
    stamp = run_start()
    room_map = shrunk_map(ROOM)
    rows: dict[str, dict[str, Any]] = {}
    for n in (4, 8) if args.quick else (4, 8, 20):
        rows[f"swap {n}"] = run(ROOM, room_map, *ring(n))
        print(f"# swap {n} done (load {loadavg()})", flush=True)
    if not args.quick:
        rows["door 8"] = run(DOOR, shrunk_map(DOOR), *door())
        print(f"# door done (load {loadavg()})", flush=True)
    person = Mover(start=5.0 + 7.6j, end=5.0 + 0.35j, radius=0.3, speed=1.2, t_start=3.25)
    rows["person"] = run(ROOM, room_map, np.array([1.0 + 1.2j]), np.array([8.5 + 1.2j]), [person])
    wh = wh_gates = wh_road = None
    extra: list[dict[str, Any]] = []
    if not (args.no_warehouse or args.quick):
        wh_road = warehouse(args.rounds, roadmap=True)
        for k in range(1, args.extra_seeds + 1):
            extra.append(warehouse(args.rounds, seed=k, roadmap=True) | {"seed": k})
        if not args.roadmap_only:
            wh = warehouse(args.rounds)
            wh_gates = warehouse(args.rounds, traffic=True)
    cost = batched_cost()
    hdr = (
        f"{'scenario':10s} {'N':>3s} {'r-r':>4s} {'mov':>4s} {'wall':>4s} {'arr%':>5s} "
        f"{'last s':>7s} {'lone s':>7s} {'ratio':>6s} {'min gap':>8s} {'dl':>3s} "
        f"{'us/rob':>7s} {'ghost':>5s}"
    )
    print(hdr)
    for name, r in rows.items():
        last = r["last_arrival_s"]
        print(
            f"{name:10s} {r['robots']:3d} {r['robot_contacts']:4d} {r['mover_contacts']:4d} "
            f"{r['wall_contacts']:4d} {r['arrived_pct']:5.0f} "
            f"{(last if last is not None else float('nan')):7.2f} {r['slowest_lone_s']:7.2f} "
            f"{(r['ratio'] if r['ratio'] is not None else float('nan')):6.2f} "
            f"{min(r['min_gap_m'] or np.inf, r['min_mover_gap_m'] or np.inf):8.4f} "
            f"{r['deadlocks']:3d} {r['filter_us_per_robot_step']:7.1f} "
            f"{r['ghost_robot_contacts'] + r['ghost_mover_contacts']:5d}"
        )
    print(
        f"batched rows + projection, {cost['robots']} robots: {cost['us_per_robot']:.2f} us/robot"
    )
    whs = (
        ("warehouse", wh),
        ("warehouse, gates", wh_gates),
        ("warehouse, roadmap", wh_road),
        *((f"warehouse, roadmap, seed {e['seed']}", e) for e in extra),
    )
    for wname, w in whs:
        if w is None:
            continue
        print(
            f"{wname}: {w['robots']} unicycles x {w['rounds']} goals: "
            f"{w['robot_contacts']} robot / {w['wall_contacts']} wall contacts, "
            f"{w['reached']}/{w['goals']} = {w['arrived_pct']:.1f}% of goals reached, "
            f"min gap {w['min_gap_m']:.4f} m, last arrival {w['last_arrival_s']} s, "
            f"{w['yield_steps']} yield steps, {w['gates']} gates, {w['gate_waits']} wait steps"
        )
    targets = {
        name: {
            "no contact": r["robot_contacts"] + r["mover_contacts"] + r["wall_contacts"] == 0,
            "all arrive": r["arrived_pct"] == 100.0,
            "within 2x lone": r["ratio"] is not None and r["ratio"] <= 2.0,
        }
        for name, r in rows.items()
    }
    for wname, w in whs:
        if w is not None:
            targets[wname] = {
                "no contact": w["robot_contacts"] + w["wall_contacts"] == 0,
                "99% arrive": w["arrived_pct"] >= 99.0,
            }
    for name, t in targets.items():
        print(f"  {name}: " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in t.items()))
    doc = {
        **run_end(stamp),
        "note": "timings under the load shown (shared machine), not idle figures",
        "cpu_count": os.cpu_count(),
        "quick": args.quick,
        "robot_radius": R,
        "map_tol": TOL,
        "control_period_s": 0.05,
        "scenarios": rows,
        "batched_cost": cost,
        "warehouse": wh,
        "warehouse_gates": wh_gates,
        "warehouse_roadmap": wh_road,
        "warehouse_roadmap_seeds": extra,
        "targets": targets,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {args.out}")


def node_laws_main(args: argparse.Namespace) -> None:
    """``--node-laws``: the warehouse rounds with the coordinator's two node laws; with
    ``--aside``: the straight node laws with each of the coordinator's ``aside`` rules."""
    stamp = run_start()
    if args.come_back:
        rows = {
            f"line, come back {rule}, seed {seed}": warehouse(
                args.rounds, seed=seed, roadmap=True, node_law="line", come_back=rule
            )
            | {"come_back": rule, "seed": seed}
            for rule in args.come_back
            for seed in (0, 1)
        }
        out = RESULTS / "fleet_node_laws_comeback.json"
        if args.out != RESULTS / "fleet.json":
            out = args.out
    elif args.aside:
        rows = {
            f"line, aside {rule}": warehouse(args.rounds, roadmap=True, node_law="line", aside=rule)
            | {"aside": rule}
            for rule in args.aside
        }
        out = RESULTS / "fleet_node_laws_aside.json"
    else:
        rows = {law: warehouse(args.rounds, roadmap=True, node_law=law) for law in ("kr", "line")}
        out = RESULTS / "fleet_node_laws.json"
    doc = {
        **run_end(stamp),
        "cpu_count": os.cpu_count(),
        "warehouse_roadmap": rows,
    }
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {out}")


def roadmap_scenarios_main(args: argparse.Namespace) -> None:
    """``--roadmap-scenarios``: swap 4, 8, 20 and door 8, local rules against the roadmap."""
    stamp = run_start()
    room_map = shrunk_map(ROOM)
    door_map = shrunk_map(DOOR)
    cases = {f"swap {n}": (ROOM, room_map, *ring(n)) for n in (4, 8, 20)}
    cases["door 8"] = (DOOR, door_map, *door())
    rows: dict[str, dict[str, Any]] = {}
    modes = args.coordinator or ["local", "roadmap"]
    for name, (ws, cm, st, gl) in cases.items():
        for mode in modes:
            r = run(ws, cm, st, gl, roadmap=mode == "roadmap", auto=mode == "auto")
            rows[f"{name}, {mode}"] = r
            print(
                f"{name:8s} {mode:8s} contacts {r['robot_contacts']}/{r['wall_contacts']} "
                f"arrived {r['arrived_pct']:.0f}% last {r['last_arrival_s']} s "
                f"(lone {r['slowest_lone_s']:.2f} s, ratio {r['ratio']}) load {loadavg()}",
                flush=True,
            )
    out = (
        RESULTS / "fleet_roadmap_scenarios.json" if args.out == RESULTS / "fleet.json" else args.out
    )
    doc = {
        **run_end(stamp),
        "cpu_count": os.cpu_count(),
        "robot_radius": R,
        "map_tol": TOL,
        "control_period_s": 0.05,
        "scenarios": rows,
    }
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {out}")


def services_main(args: argparse.Namespace) -> None:
    """``--services``: the warehouse rounds through the services, one row per coordinator."""
    stamp = run_start()  # the code the processes run (started now)
    out = RESULTS / "fleet_services.json" if args.out == RESULTS / "fleet.json" else args.out
    rows = {
        c: services_warehouse(args.rounds, c, args.time_scale, args.t_max, seed=args.seed)
        for c in (args.coordinator or ["roadmap"])
    }
    for c, w in rows.items():
        print(
            f"services warehouse, {c}: {w['robots']} unicycles x {w['rounds']} goals: "
            f"{w['robot_contacts']} robot / {w['wall_contacts']} wall contacts, "
            f"{w['reached']}/{w['goals']} = {w['arrived_pct']:.1f}% reached, last arrival "
            f"{w['last_arrival_s']} s (nominal), wall {w['wall_s']:.0f} s"
        )
        for u in w["not_arrived"]:
            ls = u["last_status"] or {}
            nb = [(e["robot"], round(e["distance_m"], 2), e["message"]) for e in u["neighbours"]]
            print(f"  not arrived {u['robot']} goal {u['goal_index']} at {u['goal']}: "
                  f"{ls.get('state')} / {ls.get('reason')}: {ls.get('message')!r}, "
                  f"{u['distance_to_goal_m']} m off; neighbours "
                  f"{nb}")  # fmt: skip
    doc = {
        **run_end(stamp),
        "note": "timings under the load shown (shared machine), not idle figures",
        "cpu_count": os.cpu_count(),
        "warehouse_services": rows,
    }
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
