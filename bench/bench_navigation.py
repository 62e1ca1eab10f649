"""Navigation benchmark with realistic goals and the library defaults only (issue 9).

    nice python bench/bench_navigation.py [--starts 1000] [--seed 0] [--only NAME ...]
        [--methods harmonic kr] [--map-cache DIR] [--jobs 1] [--out FILE]

Scenarios: the default workspace, the L-room, mixed 10 and mixed 20, two cups, rooms written
like real ones (goal inside a U-shaped shelf's cup, at the end of a wall alcove, behind a 0.8 m
door in a wall, an office with desks, counter, pillar and partition;
:mod:`confnav.scenes.scenarios`) and the realistic scenes of bench/scenes (goal from scenes.json).
Each scenario: ``--starts`` uniform random starts (0.05 m from walls), every robot driven by
``Controller(cmap, goal)`` or ``Controller(cmap, goal, navfn="kr")`` with nothing else set,
on the map the controller service uses (``for_navigation`` at its accuracy).

Targets: success >= 99.9 %, 0 collisions, median time to goal <= 1.5 x shortest path / v_max
(per robot, median over the arrived ones); harmonic fit with 20 obstacles: per-map precompute
<= 10 s, per goal <= 50 ms, memory <= 1 GB.  Prints a table; writes JSON with the commit,
date, load average before/after and "met"/"missed" per target.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # small matrices; threads only fight over the cores

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from provenance import git, loadavg  # noqa: E402  (script mode: bench/ on sys.path)

import confnav  # noqa: E402
from confnav.errors import ConfnavError  # noqa: E402
from confnav.geometry import Workspace  # noqa: E402
from confnav.navigation import defaults  # noqa: E402
from confnav.navigation.control import Controller  # noqa: E402
from confnav.navigation.messages import NAV_ACCURACY  # noqa: E402
from confnav.navigation.shortest_path import ShortestPaths  # noqa: E402
from confnav.navigation.sim import simulate  # noqa: E402
from confnav.scenes.scenarios import (  # noqa: E402
    Scenario,
    alcove_room,
    cup_room,
    cup_trap,
    default_scenario,
    door_rooms,
    l_room,
    mixed,
    office,
    random_starts,
)

RESULTS = Path(__file__).resolve().parent / "results" / "navigation_defaults.json"
SCENES = Path(__file__).resolve().parent / "scenes"
TARGET_SUCCESS = 0.999
TARGET_TIME_RATIO = 1.5
TARGET_PRECOMPUTE_S = 10.0
TARGET_GOAL_S = 0.05
TARGET_MEMORY_B = 1 << 30
T_MAX = 1e4


def scenarios() -> list[Scenario]:
    out = [
        default_scenario(),
        l_room(),
        mixed(10),
        mixed(20),
        cup_trap(0.8),
        cup_trap(1.6),
        cup_room(),
        alcove_room(),
        door_rooms(),
        office(),
    ]
    if (SCENES / "scenes.json").exists():
        meta = json.loads((SCENES / "scenes.json").read_text())
        for name, d in meta.items():
            ws = Workspace.load(SCENES / d["workspace"])
            out.append(Scenario(f"scene {name}", ws, complex(*d["goal"]), d["description"]))
    return out


def solve_cached(ws: Workspace, cache: Path | None) -> Any:
    """The controller service's map of ``ws`` (cached on disk by the workspace hash)."""
    path = cache / f"{ws.content_hash[:16]}.json" if cache else None
    cmap = None
    if path is not None and path.exists():
        try:
            cmap = confnav.ConformalMap.from_json(path.read_text())
        except ConfnavError as exc:  # e.g. an older map format: a cache miss, re-solved
            print(f"map cache {path.name}: {exc}; re-solving", flush=True)
    if cmap is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cmap = confnav.solve(ws)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(cmap.to_json())
    return cmap.for_navigation(accuracy=NAV_ACCURACY)


def run_case(sc: Scenario, n: int, seed: int, cache: Path | None, methods: list[str]) -> Any:
    t0 = time.perf_counter()
    cmap = solve_cached(sc.workspace, cache)
    starts = random_starts(sc.workspace, n, seed, margin=0.05)
    shortest = ShortestPaths(sc.workspace, sc.goal).lengths(starts)
    row: dict[str, Any] = {
        "scenario": sc.name,
        "description": sc.description,
        "n_obstacles": sc.workspace.n_obstacles,
        "goal": [sc.goal.real, sc.goal.imag],
        "n_starts": n,
        "methods": {},
    }
    for method in methods:
        tb = time.perf_counter()
        try:
            ctl = (
                Controller(cmap, sc.goal)
                if method == "harmonic"
                else Controller(cmap, sc.goal, navfn="kr")
            )
        except confnav.ConfnavError as exc:
            row["methods"][method] = {"error": str(exc)}
            continue
        build = time.perf_counter() - tb
        res = simulate(ctl, starts, t_max=T_MAX)
        ok = res.success & np.isfinite(shortest) & (shortest > 0)
        ratio = res.time[ok] / (shortest[ok] / ctl.v_max)
        law = law_time(shortest[ok], ctl.v_max, ctl.gain, ctl.goal_tol) / (shortest[ok] / ctl.v_max)
        fails = [
            {"start": [z.real, z.imag], "status": r.status, "reason": r.reason}
            for z, r in zip(starts, res.runs(), strict=True)
            if not r.success
        ]
        row["methods"][method] = {
            "navfn": ctl.navfn.name,
            "k": getattr(ctl.navfn, "k", None),
            "fallback": ctl.fallback or None,
            "build_s": build,
            "success_rate": res.success_rate,
            "collisions": int(res.collided.sum()),
            "stalled": int((res.status == 2).sum()),
            "timeouts": int((res.status == 3).sum()),
            "errors": int((res.status == 4).sum()),
            "median_time_ratio": float(np.median(ratio)) if ratio.size else None,
            "p90_time_ratio": float(np.quantile(ratio, 0.9)) if ratio.size else None,
            "median_law_ratio": float(np.median(law)) if law.size else None,
            "median_path_ratio": float(np.median(res.path_length[ok] / shortest[ok]))
            if ok.any()
            else None,
            "min_clearance": float(np.min(res.min_clearance)),
            "sim_wall_s": res.wall_time,
            "failures": fails[:50],
        }
    row["wall_s"] = time.perf_counter() - t0
    return row


def law_time(length: Any, v_max: float, gain: float, tol: float) -> Any:
    """Time the default speed law ``v = min(v_max, gain d)`` needs along a path of ``length``
    straight to the goal, stopping at ``tol``: ``(L - d0)/v_max + ln(min(L, d0)/tol)/gain``
    with ``d0 = v_max/gain`` (the exponential approach, ``d' = -gain d``, below ``d0``).  Its
    ratio to ``L/v_max`` is what the profile alone costs, whatever the path."""
    length = np.asarray(length, dtype=float)
    d0 = v_max / gain
    near = np.log(np.maximum(np.minimum(length, d0), tol) / tol) / gain
    return np.maximum(length - d0, 0.0) / v_max + near


def harmonic_cost(cache: Path | None, n_goals: int = 20) -> dict[str, Any]:
    """Per-map precompute, per-goal solve and memory of the harmonic fit on mixed 20, with
    the accuracy the controller asks (its sample points); memory is the peak of the numpy
    allocations during precompute and goals (tracemalloc)."""
    from confnav.navigation.control import _samples
    from confnav.navigation.harmonic import GreenBasis, HarmonicNavigation
    from confnav.navigation.navfn import CircleDomain

    sc = mixed(20)
    cmap = solve_cached(sc.workspace, cache)
    dom = CircleDomain.of(cmap)
    samples = _samples(cmap)
    goals = np.asarray(cmap.T(random_starts(sc.workspace, n_goals, 7, margin=0.1)))
    tracemalloc.start()
    t0 = time.process_time()
    basis = GreenBasis(dom).precompute()
    pre = time.process_time() - t0
    times, fails = [], 0
    for wd in goals:
        t1 = time.process_time()
        try:
            HarmonicNavigation(dom, complex(wd), basis=basis, samples=samples)
        except confnav.ConfnavError:
            fails += 1
        times.append(time.process_time() - t1)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {
        "scenario": sc.name,
        "precompute_s": pre,
        "terms_per_circle": basis.n_terms,
        "per_goal_median_s": float(np.median(times)),
        "per_goal_max_s": float(np.max(times)),
        "goals": n_goals,
        "goals_not_converged": fails,
        "basis_bytes": basis.nbytes,
        "peak_traced_bytes": peak,
        "timing": "CPU seconds of this process (process_time)",
    }


def _met(ok: bool) -> str:
    return "met" if ok else "missed"


def table(rows: list[dict[str, Any]]) -> str:
    head = f"{'scenario':24s} {'method':9s} {'nf':10s} {'success':>8s} {'coll':>4s} "
    head += f"{'stall':>5s} {'tout':>4s} {'t/(L/v)':>7s} {'law':>5s} {'minclr':>7s}"
    lines = [head, "-" * len(head)]
    for r in rows:
        for m, d in r["methods"].items():
            if "error" in d:
                lines.append(f"{r['scenario']:24s} {m:9s} error: {d['error'][:60]}")
                continue
            nf = d["navfn"] + (f" k={d['k']:g}" if d["k"] else "")
            tr = d["median_time_ratio"]
            lr = d.get("median_law_ratio")
            lines.append(
                f"{r['scenario']:24s} {m:9s} {nf:10s} {100 * d['success_rate']:7.2f}% "
                f"{d['collisions']:4d} {d['stalled']:5d} {d['timeouts']:4d} "
                f"{'-' if tr is None else f'{tr:7.3f}':>7s} "
                f"{'-' if lr is None else f'{lr:5.2f}':>5s} {d['min_clearance']:7.4f}"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--starts", type=int, default=1000, help="random starts per scenario")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", help="scenario names (substring match)")
    ap.add_argument("--methods", nargs="*", default=["harmonic", "kr"], choices=["harmonic", "kr"])
    ap.add_argument("--map-cache", type=Path, default=Path("/tmp/confnav-bench-maps"))
    ap.add_argument("--jobs", type=int, default=1, help="scenarios in parallel (processes)")
    ap.add_argument("--no-cost", action="store_true", help="skip the harmonic cost bench")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    started = datetime.now(UTC).isoformat(timespec="seconds")
    commit = git("rev-parse", "HEAD")  # the code that runs (read before any checkout/merge)
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    load0 = loadavg()
    t0 = time.perf_counter()
    cases = [s for s in scenarios() if not args.only or any(o in s.name for o in args.only)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futs = [
            pool.submit(run_case, sc, args.starts, args.seed, args.map_cache, args.methods)
            for sc in cases
        ]
        rows = []
        for sc, f in zip(cases, futs, strict=True):
            rows.append(f.result())
            print(f"# {sc.name}: {rows[-1]['wall_s']:.0f} s  (load {loadavg()})", flush=True)
    cost = None if args.no_cost else harmonic_cost(args.map_cache)
    targets: dict[str, str] = {}
    for r in rows:
        for m, d in r["methods"].items():
            key = f"{r['scenario']} / {m}"
            if "error" in d:
                targets[key] = "missed (no controller)"
                continue
            tr = d["median_time_ratio"]
            targets[key] = (
                f"success {_met(d['success_rate'] >= TARGET_SUCCESS)}, "
                f"collisions {_met(d['collisions'] == 0)}, "
                f"time {_met(tr is not None and tr <= TARGET_TIME_RATIO)}"
            )
    if cost is not None:
        targets["harmonic precompute (mixed 20)"] = _met(
            cost["precompute_s"] <= TARGET_PRECOMPUTE_S
        )
        targets["harmonic per goal (mixed 20)"] = _met(
            cost["per_goal_median_s"] <= TARGET_GOAL_S and cost["goals_not_converged"] == 0
        )
        targets["harmonic memory (mixed 20)"] = _met(
            max(cost["basis_bytes"], cost["peak_traced_bytes"]) <= TARGET_MEMORY_B
        )
    text = table(rows)
    print(text)
    if cost is not None:
        print("harmonic fit, mixed 20:", json.dumps(cost))
    for k, v in targets.items():
        print(f"  {k}: {v}")
    doc = {
        "commit": commit,
        "dirty": dirty,
        "started": started,
        "finished": datetime.now(UTC).isoformat(timespec="seconds"),
        "load_before": load0,
        "load_after": loadavg(),
        "note": "timings under the load shown (shared machine), not idle figures",
        "cpu_count": os.cpu_count(),
        "starts_per_scenario": args.starts,
        "seed": args.seed,
        "defaults": {
            "navfn": defaults.NAVFN,
            "speed_law": defaults.SPEED_LAW,
            "gain": defaults.GAIN,
            "v_max": defaults.V_MAX,
            "goal_tol": defaults.GOAL_TOL,
        },
        "t_max": T_MAX,
        "total_s": time.perf_counter() - t0,
        "rows": rows,
        "harmonic_cost": cost,
        "targets": targets,
        "table": text,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out} ({doc['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
