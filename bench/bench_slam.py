"""Real SLAM maps (issue 23, target "Real SLAM maps"): import, first command, robots arriving.

    python bench/bench_slam.py [--quick] [--maps depot ...] [--pairs 10] [--refine 1e-6 1e-8]
                               [--rungwise [--rungs 1|2|3]] [--out bench/results/slam.json]
    python -m bench slam [--quick]

The maps are ROS ``map_server`` occupancy grids from public Apache-2.0 repositories
(``tests/data/slam/``, NOTICE there: nav2's depot, tb3_sandbox, warehouse and empty_room,
ROBOTIS's TurtleBot3 world). The body is a TurtleBot's: a disk of radius 0.22 m driven as a
unicycle through a look-ahead point 0.1 m ahead of its axle (the README's ``--robot-radius 0.22
--unicycle 0.1``), so the steered point navigates the free space shrunk by 0.32 m
(:func:`confnav.maps.footprint.inflate`, as ``confnav simulate`` and the services'
``{ws}~r{R}`` do). ``--pairs`` random start/goal pairs per map (seed ``SEED``; both at least
0.05 m + the look-ahead inside the shrunk free space, random headings). For each map
(default, the progressive atlas, docs/SLAM.md "Progressive atlas"):

1. **import**: :func:`confnav.maps.occupancy.import_map` with the defaults of ``confnav
   import-map`` (wall time; obstacles, vertices, Hausdorff error, border closed or not);
2. **footprint**: the shrunk free space (wall time; obstacles, vertices);
3. **goals**: every robot's goal is given at once; the atlas is solved progressively
   (:func:`confnav.atlas.solve_atlas` with ``priority`` = the pairs, ``on_partial``, ``fine``
   = the starts; ``LADDER[0]`` = 1e-3 accepted up to ``COARSE_MAX_ERROR``) on a pool of 2
   worker processes started before the clocks; the safety layer's grid of the exact shrunk
   free space is built in a worker meanwhile. At each partial revision every robot that has
   not moved yet gets its law on it and its command at its start is evaluated: **ready** is
   the wall time of a robot's first non-zero command, measured, not simulated, from the
   YAML file (``ready_s``, the first robot's; import + footprint included) and from the goal
   (``ready_after_goal_s`` per robot, what the services see: their workspace is imported
   already). Target: <= 2 s (``READY_TARGET_S``);
4. **refined**: then complete atlases to each ``--refine`` tolerance (default 1e-6), one
   after the other, each a revision at the wall time it is complete;
5. **drive**: each pair driven from the goal's time on, the revisions installed at their
   wall times (simulated time = the robot's real time: windows cut at every installation),
   the safety layer on the exact shrunk free space (:mod:`confnav.navigation.safety`),
   collisions and clearances those of the 0.22 m body against the imported walls; per pair:
   arrived, collided, the reason of a failure, simulated time of the first move and of the
   end, revisions offered and swaps, wall time.

``--services`` runs :mod:`bench_slam_services` instead: the same maps, body and (the first)
pairs through real service processes, goal to first command per robot
(``bench/results/slam_services.json``).

``--rungwise`` runs the former bench instead: each rung (1e-3, 1e-6, the README's accuracy)
solved whole, its first robot's controller built, every pair driven on it alone.

Wall times on a shared machine: the load average is recorded beside every map's figures.
"""

from __future__ import annotations

import os

# one BLAS thread per process, as the services' launcher sets (docs/SERVICES.md, "Performance
# notes"), before numpy loads; the worker processes inherit it. Measured on the depot at load
# 4.3-4.8: with OpenBLAS's threads the 10 robots were ready 3.1-10.9 s after the goal (a
# controller's 256-point sample evaluation took 0.24 s instead of milliseconds, its threads
# fighting the two chart workers over the 2 cores), with one thread 1.9-2.4 s
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT))
from provenance import git, loadavg  # noqa: E402

import confnav  # noqa: E402
from confnav.atlas import AtlasNavigator, solve_atlas  # noqa: E402
from confnav.atlas.charts import PartialAtlas, atlas_reason  # noqa: E402
from confnav.atlas.wire import AtlasController, NavMaps, ProgressiveController  # noqa: E402
from confnav.conformal.solver import UNUSABLE_ERROR, crowding_reason  # noqa: E402
from confnav.errors import ConfnavError, CrowdingError  # noqa: E402
from confnav.geometry import Workspace  # noqa: E402
from confnav.maps.footprint import inflate  # noqa: E402
from confnav.maps.occupancy import import_map  # noqa: E402
from confnav.navigation import defaults  # noqa: E402
from confnav.navigation.control import Controller  # noqa: E402
from confnav.navigation.safety import safety_filter  # noqa: E402
from confnav.navigation.sim import STATUS_NAMES  # noqa: E402
from confnav.navigation.unicycle import UnicycleController, simulate_unicycle  # noqa: E402
from confnav.scenes.scenarios import random_starts  # noqa: E402
from services.definitions import COARSE_MAX_ERROR, LADDER  # noqa: E402

MAPS_DIR = ROOT / "tests" / "data" / "slam"
RESULTS = Path(__file__).resolve().parent / "results" / "slam.json"
#: Smallest first: the warehouse (1006 x 1674 cells of 3 cm) last.
MAPS = ("tb3_world", "tb3_sandbox", "empty_room", "depot", "warehouse")
QUICK_MAPS = ("tb3_world", "empty_room")
#: A TurtleBot-sized body (issue 23): radius and unicycle look-ahead, m.
RADIUS = 0.22
LOOKAHEAD = 0.1
SEED = 1
PAIRS = 10
#: Issue 23's target: each map ready to drive within 2 s.
READY_TARGET_S = 2.0
#: The README commands' accuracies: ``confnav simulate`` (one map) and ``confnav atlas``.
FINAL_SINGLE_TOL = 1e-10
FINAL_ATLAS_TOL = 1e-8
WORKERS = 2
#: Time limit per pair: this many workspace diameters at v_max (the atlas's own runs allow 20;
#: the pairs of the first runs arrived within 2 diameters, the rest stood still till 20).
T_MAX_DIAMETERS = 6.0


def _now() -> float:
    return time.perf_counter()


def n_vertices(ws: Workspace) -> int:
    d = ws.to_dict()
    return len(d["outer"]) + sum(len(o) for o in d["obstacles"])


class FirstMap:
    """The map the robots drive on: one conformal map or an atlas (with its charts'
    ``for_navigation`` maps, made once per atlas as the controller's ``AtlasMap`` does)."""

    def __init__(self, kind: str, obj: Any, why: str, seconds: float, detail: dict[str, Any]):
        self.kind, self.obj, self.why, self.seconds, self.detail = kind, obj, why, seconds, detail
        self.nav_maps: list[Any] | None = None

    def prepare(self) -> None:
        if self.kind == "atlas" and self.nav_maps is None:
            self.nav_maps = [m.for_navigation() for m in self.obj.charts]

    def controller(self, goal: complex, nav_ws: Workspace) -> Any:
        """One robot's law for ``goal`` with the safety layer on the exact ``nav_ws``."""
        if self.kind == "single":
            return Controller(self.obj, goal, safety=nav_ws)
        self.prepare()
        # the safety layer: the atlas's workspace (nav_ws), every chart's commands filtered
        nav = AtlasNavigator(self.obj, goal, speed=defaults.V_MAX, nav_maps=self.nav_maps)
        return AtlasController(nav)


def solve_map(nav_ws: Workspace, tol: float, max_error: float | None, pool: Any) -> FirstMap:
    """One map unless the service's rules say atlas (before or during the solve)."""
    t0 = _now()
    why = atlas_reason(nav_ws)
    if not why:
        try:
            refuse = UNUSABLE_ERROR if max_error is None else max_error
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = confnav.solve(nav_ws, tol, max_error=refuse)
            why = crowding_reason(m.diagnostics)
            if not why:
                d = m.diagnostics
                return FirstMap(
                    "single",
                    m.for_navigation(),
                    "",
                    _now() - t0,
                    {"error_estimate": float(d.error_estimate), "tol_met": bool(d.tol_met)},
                )
            why = f"one map crowds: {why}"
        except CrowdingError as exc:
            why = f"one map crowds: {exc}"
    single_s = _now() - t0
    accept = max(tol, max_error or 0.0, 1e-6)
    atlas = solve_atlas(nav_ws, tol, workers=WORKERS, accept=accept, executor=pool)
    charts = [r.wall_time for r in atlas.chart_records]
    return FirstMap(
        "atlas",
        atlas,
        why,
        _now() - t0,
        {
            "single_attempt_s": round(single_s, 3),
            "charts": len(atlas.charts),
            "chart_max_s": round(max(charts), 3),
            "chart_median_s": round(float(np.median(charts)), 3),
            "error_estimate": float(max(m.diagnostics.error_estimate for m in atlas.charts)),
        },
    )


def drive(fm: FirstMap, ws: Workspace, nav_ws: Workspace, pairs: list[tuple[complex, complex,
          float]]) -> list[dict[str, Any]]:  # fmt: skip
    """Each pair: one unicycle from its start and heading to its goal, safety layer on."""
    out = []
    t_max = T_MAX_DIAMETERS * nav_ws.diameter / defaults.V_MAX
    for start, goal, heading in pairs:
        t0 = _now()
        try:
            law = fm.controller(goal, nav_ws)
            uc = UnicycleController(law, LOOKAHEAD, v_max=defaults.V_MAX)
            r = simulate_unicycle(
                uc, [start], [heading], clearance=ws.clearance, radius=RADIUS, t_max=t_max
            )
            status = STATUS_NAMES[int(r.status[0])]
            stop = getattr(law, "stop_reason", None)
            row = {
                "arrived": bool(r.success[0]),
                "collided": bool(r.collided[0]),
                "status": status,
                "reason": "" if r.success[0] else (stop[1] if stop else status),
                "time_s": float(r.time[0]),
                "min_clearance": float(r.min_clearance[0]),
            }
        except ConfnavError as exc:
            row = {"arrived": False, "collided": False, "status": "error",
                   "reason": f"{type(exc).__name__}: {exc}"}  # fmt: skip
        row.update(start=[start.real, start.imag], goal=[goal.real, goal.imag],
                   wall_s=round(_now() - t0, 3))  # fmt: skip
        out.append(row)
    return out


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "pairs": len(rows),
        "arrived": sum(r["arrived"] for r in rows),
        "collided": sum(r["collided"] for r in rows),
    }


def run_rung(ws: Workspace, nav_ws: Workspace, pairs: list[tuple[complex, complex, float]],
             tol: float, max_error: float | None, pool: Any) -> dict[str, Any]:  # fmt: skip
    """Solve the map to ``tol`` (one map or an atlas), build the first robot's controller,
    drive every pair on it."""
    try:
        fm = solve_map(nav_ws, tol, max_error, pool)
    except ConfnavError as exc:
        print(f"  tol {tol:g}: failed: {exc}", flush=True)
        return {"tol": tol, "error": f"{type(exc).__name__}: {exc}"}
    t0 = _now()
    fm.prepare()
    fm.controller(pairs[0][1], nav_ws)
    t_ctl = _now() - t0
    out: dict[str, Any] = {"tol": tol, "max_error": max_error, "kind": fm.kind, "why": fm.why,
                           "seconds": round(fm.seconds, 3), "controller_s": round(t_ctl, 3),
                           **fm.detail}  # fmt: skip
    print(f"  tol {tol:g}: {fm.kind} in {fm.seconds:.2f} s ({fm.why or 'one map'}); first "
          f"controller {t_ctl:.2f} s; load {loadavg()}", flush=True)  # fmt: skip
    rows = drive(fm, ws, nav_ws, pairs)
    out["pairs"] = rows
    out["summary"] = summary(rows)
    print(f"  tol {tol:g}: {out['summary']}; load {loadavg()}", flush=True)
    return out


#: The progressive atlas's revisions: the first (its charts solved along the robots' routes
#: first, installed batch by batch), then complete refined atlases (``--refine``).
PROGRESSIVE_REFINE = (1e-6,)
#: Simulated seconds per window of the time-coupled drive (revisions are installed at their
#: own times, between windows)
WINDOW_S = 0.5


def _first_command(law: ProgressiveController, uc: UnicycleController, start: complex,
                   heading: float) -> bool:  # fmt: skip
    """Whether the robot at its start gets a non-zero command now."""
    out = uc(np.array([start]), np.array([heading]))
    return bool(abs(out.u[0]) > 0)


def progressive(nav_ws: Workspace, pairs: list[tuple[complex, complex, float]], pool: Any,
                t_goal: float, t_before: float,
                refine: tuple[float, ...]) -> tuple[dict[str, Any], list[Any]]:  # fmt: skip
    """The progressive atlas as a controller gets it: every robot's goal given at wall time
    ``t_goal`` (``t_before`` seconds after the YAML file was opened: import + footprint),
    the first revision's charts solved along their routes first (``solve_atlas(priority=...,
    on_partial=...)``); at each partial revision every robot still waiting builds its law
    on it and evaluates its command at its start: **ready** is the wall time of a robot's
    first non-zero command, measured here, not simulated. Then the refined atlases.

    Returns the figures and the schedule ``[(seconds after t_goal, revision)]`` the drive
    installs at those times."""
    first_tol = LADDER[0]
    # the exact geometry's safety grid depends on the workspace only: built from the goal's
    # time on, beside the decomposition and the chart solves (as a controller can when a
    # workspace arrives); the charts' local expansions are built after the first commands
    # (a chart evaluates by the direct formula meanwhile, docs/NAVIGATION.md)
    # (in a worker process: in this one it would hold the interpreter lock against the
    # decomposition, measured 1.4 -> 2.7 s on the warehouse)
    flt = safety_filter(nav_ws, hold_time=defaults.HOLD_TIME)
    grid = pool.submit(_grid_of, nav_ws.to_json(), defaults.HOLD_TIME)
    maps = NavMaps(defer_expansions=True)
    laws = [ProgressiveController(g, nav_maps=maps, speed=defaults.V_MAX, safety=nav_ws)
            for _, g, _ in pairs]  # fmt: skip
    ucs = [UnicycleController(law, LOOKAHEAD, v_max=defaults.V_MAX) for law in laws]
    ready: list[float | None] = [None] * len(pairs)
    what: list[dict[str, Any] | None] = [None] * len(pairs)
    schedule: list[tuple[float, Any]] = []

    def on_partial(pa: PartialAtlas) -> None:
        if flt._grid is None:  # the commands need the grid: wait for it, install it
            g = grid.result()
            with flt._lock:
                flt._grid = flt._grid or g
        maps.of(pa)  # the controller's work on a revision: its new charts' navigation maps
        schedule.append((_now() - t_goal, pa))
        for k, (start, _goal, head) in enumerate(pairs):
            if ready[k] is not None:
                continue
            laws[k].offer(pa)
            if _first_command(laws[k], ucs[k], start, head):
                t = _now() - t_goal
                ready[k] = t
                law = laws[k].law
                what[k] = {"round": pa.round, "charts_installed": len(pa.installed),
                           "cells": len(pa.charts), "tol": pa.tol,
                           "active_chart": None if law is None else law.active_chart}  # fmt: skip

    accept = max(first_tol, COARSE_MAX_ERROR)
    t0 = _now()
    atlas = solve_atlas(nav_ws, first_tol, workers=WORKERS, accept=accept, executor=pool,
                        priority=[(s, g) for s, g, _ in pairs], on_partial=on_partial,
                        fine=[s for s, _, _ in pairs])  # fmt: skip
    t_first = _now() - t0
    schedule.append((_now() - t_goal, atlas))
    charts = [r.wall_time for r in atlas.chart_records]
    out: dict[str, Any] = {
        "first_tol": first_tol,
        "first_accept": accept,
        "first_atlas_s": round(t_first, 3),
        "charts": len(atlas.charts),
        "chart_max_s": round(max(charts), 3),
        "chart_median_s": round(float(np.median(charts)), 3),
        "failed_solves": sum(bool(r.error) for r in atlas.records),
        "revisions_first": len(schedule),
        "error_estimate": float(max(m.diagnostics.error_estimate for m in atlas.charts)),
        "ready_after_goal_s": [None if r is None else round(r, 3) for r in ready],
        "ready_what": what,
    }
    first = next((k for k in range(len(pairs)) if ready[k] is not None), None)
    fastest = min((r for r in ready if r is not None), default=None)
    out["first_robot_ready_s"] = None if ready[0] is None else round(t_before + ready[0], 3)
    out["fastest_robot_ready_s"] = None if fastest is None else round(t_before + fastest, 3)
    out["slowest_robot_ready_s"] = (
        None if None in ready else round(t_before + max(r for r in ready if r is not None), 3)
    )
    out["first_ready_robot"] = first
    refined = []
    for tol in refine:
        t1 = _now()
        at = solve_atlas(nav_ws, tol, workers=WORKERS, executor=pool)
        schedule.append((_now() - t_goal, at))
        refined.append({"tol": tol, "seconds": round(_now() - t1, 3), "charts": len(at.charts),
                        "installed_after_goal_s": round(schedule[-1][0], 3)})  # fmt: skip
    out["refined"] = refined
    return out, schedule


def drive_progressive(ws: Workspace, nav_ws: Workspace,
                      pairs: list[tuple[complex, complex, float]],
                      schedule: list[tuple[float, Any]]) -> list[dict[str, Any]]:  # fmt: skip
    """Each pair driven from the goal's time on, revisions installed at their times
    (simulated time = the robot's real time): windows of ``WINDOW_S`` cut at every
    installation; the robot holds (zero command) until a chart holding it is installed."""
    out = []
    t_max = T_MAX_DIAMETERS * nav_ws.diameter / defaults.V_MAX
    maps = NavMaps()
    times = [t for t, _ in schedule]
    for start, goal, heading in pairs:
        t0 = _now()
        law = ProgressiveController(goal, nav_maps=maps, speed=defaults.V_MAX, safety=nav_ws)
        uc = UnicycleController(law, LOOKAHEAD, v_max=defaults.V_MAX)
        z, th, s, nxt = start, heading, 0.0, 0
        status, minclr, moved_at, row = "timeout", np.inf, None, None
        while s < t_max:
            while nxt < len(schedule) and times[nxt] <= s + 1e-12:
                law.offer(schedule[nxt][1])
                nxt += 1
            if moved_at is None and abs(uc(np.array([z]), np.array([th])).u[0]) > 0:
                moved_at = s
            end = min(s + WINDOW_S, times[nxt] if nxt < len(schedule) else np.inf, t_max)
            r = simulate_unicycle(uc, [z], [th], clearance=ws.clearance, radius=RADIUS,
                                  t_max=max(end - s, 1e-6))  # fmt: skip
            minclr = min(minclr, float(r.min_clearance[0]))
            s += max(float(r.time[0]), 1e-6)
            z, th = complex(r.final[0]), float(r.final_theta[0])
            code = STATUS_NAMES[int(r.status[0])]
            if code in ("arrived", "collided", "error"):
                status = code
                break
        stop = getattr(law.law, "stop_reason", None) if law.law is not None else None
        row = {"arrived": status == "arrived", "collided": status == "collided",
               "status": status, "reason": "" if status == "arrived" else
               (stop[1] if stop else status), "time_s": round(s, 3),
               "first_move_s": None if moved_at is None else round(moved_at, 3),
               "min_clearance": minclr, "revisions_offered": law.offers,
               "swaps": law.swaps}  # fmt: skip
        row.update(start=[start.real, start.imag], goal=[goal.real, goal.imag],
                   wall_s=round(_now() - t0, 3))  # fmt: skip
        out.append(row)
    return out


def bench_map(name: str, n_pairs: int, rungs: list[float | None], pool: Any,
              refine: tuple[float, ...] | None = None) -> dict[str, Any]:  # fmt: skip
    yaml = MAPS_DIR / f"{name}.yaml"
    row: dict[str, Any] = {"map": name, "load_start": loadavg()}
    t0 = _now()
    res = import_map(yaml)
    t_import = _now() - t0
    ws = res.workspace
    rep = res.report
    row["import"] = {
        "seconds": round(t_import, 3),
        "grid": list(rep.shape),
        "obstacles": ws.n_obstacles,
        "vertices": n_vertices(ws),
        "hausdorff_cells": float(rep.hausdorff_cells),
        "notes": list(rep.warnings),
    }
    t0 = _now()
    nav_ws = inflate(ws, RADIUS + LOOKAHEAD)
    t_inflate = _now() - t0
    row["footprint"] = {
        "seconds": round(t_inflate, 3),
        "radius": RADIUS + LOOKAHEAD,
        "obstacles": nav_ws.n_obstacles,
        "vertices": n_vertices(nav_ws),
    }
    pts = random_starts(nav_ws, 2 * n_pairs, seed=SEED, margin=0.05 + LOOKAHEAD)
    heads = np.random.default_rng(SEED).uniform(-np.pi, np.pi, n_pairs)
    pairs = [(complex(pts[i]), complex(pts[n_pairs + i]), float(heads[i])) for i in range(n_pairs)]
    print(f"{name}: import {t_import:.2f} s ({ws.n_obstacles} obstacles, {n_vertices(ws)} "
          f"vertices), footprint {t_inflate:.2f} s ({nav_ws.n_obstacles} obstacles, "
          f"{n_vertices(nav_ws)} vertices); load {loadavg()}", flush=True)  # fmt: skip
    if refine is not None:  # the progressive atlas (the default)
        t_before = t_import + t_inflate
        prog, schedule = progressive(nav_ws, pairs, pool, _now(), t_before, refine)
        rows = drive_progressive(ws, nav_ws, pairs, schedule)
        prog["pairs"] = rows
        prog["summary"] = summary(rows)
        row["progressive"] = prog
        row["ready_s"] = prog["first_robot_ready_s"]
        row["ready_after_import_s"] = (
            None if prog["ready_after_goal_s"][0] is None else prog["ready_after_goal_s"][0]
        )
        row["ready_target_met"] = bool(row["ready_s"] is not None
                                       and row["ready_s"] <= READY_TARGET_S)  # fmt: skip
        print(
            f"  progressive: first robot ready {row['ready_s']} s from the YAML "
            f"({row['ready_after_import_s']} s after import; all robots "
            f"{prog['ready_after_goal_s']}); first atlas {prog['first_atlas_s']} s "
            f"({prog['charts']} charts); {prog['summary']}; load {loadavg()}",
            flush=True,
        )
        row["load_end"] = loadavg()
        return row
    row["rungs"] = []
    kind = None
    for k, tol in enumerate(rungs):
        if tol is None:  # the README commands' accuracy, by the first rung's kind
            tol = FINAL_SINGLE_TOL if kind == "single" else FINAL_ATLAS_TOL
        rung = run_rung(ws, nav_ws, pairs, tol, COARSE_MAX_ERROR if k == 0 else None, pool)
        row["rungs"].append(rung)
        if "error" in rung:
            break
        kind = rung["kind"]
        if k == 0:
            ready = t_import + t_inflate + rung["seconds"] + rung["controller_s"]
            row["ready_s"] = round(ready, 3)
            row["ready_target_met"] = ready <= READY_TARGET_S
            print(f"  ready to drive {ready:.2f} s (target {READY_TARGET_S:g} s)", flush=True)
    row["load_end"] = loadavg()
    return row


def _grid_of(ws_json: str, hold_time: float) -> Any:
    """Worker: the safety layer's grid of a workspace (what ``SafetyFilter.grid`` builds)."""
    return safety_filter(Workspace.from_json(ws_json), hold_time=hold_time).grid


def _warm_worker(_: int) -> int:
    import confnav.atlas.charts  # noqa: F401

    return os.getpid()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--services" in argv:  # the same maps, body and pairs through the service processes
        from bench_slam_services import main as services_main

        return services_main([a for a in argv if a != "--services"])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", nargs="+", choices=MAPS, default=None)
    ap.add_argument("--pairs", type=int, default=PAIRS)
    ap.add_argument(
        "--rungs",
        type=int,
        default=3,
        choices=(1, 2, 3),
        help="1: the first rung (1e-3) only; 2: and 1e-6; 3: and the README's accuracy",
    )
    ap.add_argument("--quick", action="store_true", help=f"{', '.join(QUICK_MAPS)}, no final")
    ap.add_argument(
        "--rungwise",
        action="store_true",
        help="the former bench: each rung solved whole, then driven (--rungs)",
    )
    ap.add_argument(
        "--refine",
        type=float,
        nargs="*",
        default=list(PROGRESSIVE_REFINE),
        help="the progressive atlas's refined revisions (default: 1e-6)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    maps = args.maps or (QUICK_MAPS if args.quick else MAPS)
    rungs: list[float | None] = [LADDER[0], LADDER[1], None][: 1 if args.quick else args.rungs]
    doc: dict[str, Any] = {
        "benchmark": "slam",
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "commit": git("rev-parse", "HEAD"),
        "loadavg_start": loadavg(),
        "cpu_count": os.cpu_count(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "body": {"radius": RADIUS, "lookahead": LOOKAHEAD, "v_max": defaults.V_MAX},
        "seed": SEED,
        "first_tol": LADDER[0],
        "first_max_error": COARSE_MAX_ERROR,
        "rungs": [r if r is not None else "readme" for r in rungs],
        "ready_target_s": READY_TARGET_S,
        "t_max_diameters": T_MAX_DIAMETERS,
        "maps": [],
    }
    with ProcessPoolExecutor(max_workers=WORKERS) as pool:
        # the worker processes started before any clock runs, as a transform service's pool
        # is at its start
        list(pool.map(_warm_worker, range(WORKERS)))
        for name in maps:
            refine = None if args.rungwise else tuple(args.refine if not args.quick else ())
            doc["maps"].append(bench_map(name, args.pairs, rungs, pool, refine))
            args.out.write_text(json.dumps(doc, indent=1) + "\n")  # partial results survive
    doc["loadavg_end"] = loadavg()
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"{'map':<12}{'obst':>5}{'verts':>6}{'kind':>7}{'ready s':>9}  arrived per rung")
    doc["mode"] = "rungwise" if args.rungwise else "progressive"
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    for r in doc["maps"]:
        if "progressive" in r:
            p = r["progressive"]
            print(f"{r['map']:<12}{r['import']['obstacles']:>5}{r['import']['vertices']:>6}"
                  f"  ready {r['ready_s']} s (after import {r['ready_after_import_s']} s), "
                  f"{p['summary']}")  # fmt: skip
            continue
        kind = r["rungs"][0].get("kind", "-") if r.get("rungs") else "-"
        per = "  ".join(
            f"{g['tol']:g}: " + (f"{g['summary']['arrived']}/{g['summary']['pairs']} "
                                 f"coll {g['summary']['collided']}" if "summary" in g else "error")
            for g in r.get("rungs", [])
        )  # fmt: skip
        print(
            f"{r['map']:<12}{r['import']['obstacles']:>5}{r['import']['vertices']:>6}"
            f"{kind:>7}{r.get('ready_s', float('nan')):>9.2f}  {per}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
