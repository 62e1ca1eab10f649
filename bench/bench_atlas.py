"""Atlas benchmark (issue 15): floor plans and warehouses navigated by sequential composition.

    nice python bench/bench_atlas.py [--starts 1000] [--seed 0] [--tol 1e-8] [--workers 2]
                                     [--scenario office --scenario ...] [--out FILE]

Scenarios: an office floor (30 x 2 m corridor, ten rooms behind 0.9 m doors); a warehouse of
100 shelves (4 x 1 m) with 2 m aisles (62 x 32 m: 100 such shelves do not fit 40 x 20 m with
2 m aisles, see confnav.atlas.scenes.warehouse); spiral corridors with L/w = 10 and 30.
Per scenario: cells, per-chart solve times, total solve wall time and the parallel speed-up
(sum of chart times / wall time; with --serial also the wall time of a 1-worker solve),
then uniform random starts run through :class:`confnav.atlas.AtlasNavigator` with default
parameters: success, collisions, chart switches, path length over the shortest path.

Targets: >= 99.9 % success, 0 collisions, median path <= 1.3 x shortest, total solve <= 60 s
on 2 cores.  Prints a table and writes JSON (commit, date, load average before and after).
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from provenance import commit, loadavg  # noqa: E402  (script mode: bench/ on sys.path)

from confnav.atlas import AtlasNavigator, needs_atlas, solve_atlas  # noqa: E402
from confnav.atlas.scenes import office, spiral, warehouse  # noqa: E402
from confnav.errors import ConfnavError  # noqa: E402
from confnav.navigation.shortest_path import ShortestPaths  # noqa: E402
from confnav.scenes.scenarios import Scenario, random_starts  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "atlas.json"
SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "office": office,
    "warehouse": warehouse,
    "spiral10": lambda: spiral(10),
    "spiral30": lambda: spiral(30),
}
TARGETS = {"success": 0.999, "collisions": 0, "median_ratio": 1.3, "solve_s": 60.0}


def bench(
    sc: Scenario, n: int, seed: int, tol: float, workers: int, serial: bool
) -> dict[str, Any]:
    ws = sc.workspace
    load0 = loadavg()
    try:
        serial_wall = solve_atlas(ws, tol, workers=1).wall_time if serial else float("nan")
        atlas = solve_atlas(ws, tol, workers=workers)
    except ConfnavError as exc:  # a failure is a result too
        return {"scenario": sc.name, "error": str(exc), "load_before": load0}
    times = np.array([r.wall_time for r in atlas.records if not r.error])
    failed = [r for r in atlas.records if r.error]
    nav = AtlasNavigator(atlas, sc.goal)
    starts = random_starts(ws, n, seed=seed)
    t0 = time.perf_counter()
    run = nav.run(starts)
    run_wall = time.perf_counter() - t0
    short = ShortestPaths(ws, sc.goal).lengths(starts)
    ratio = run.path_length[run.success] / short[run.success]
    med = float(np.median(ratio)) if ratio.size else float("nan")
    out: dict[str, Any] = {
        "scenario": sc.name,
        "description": sc.description,
        "obstacles": ws.n_obstacles,
        "needs_atlas": needs_atlas(ws),
        "cells": len(atlas.charts),
        "cell_obstacles_max": max(c.workspace.n_obstacles for c in atlas.decomposition.cells),
        "tol": tol,
        "margin": atlas.decomposition.margin,
        "solve_wall_s": atlas.wall_time,
        "solve_cpu_s": atlas.cpu_time,
        "speedup": atlas.speedup,
        "serial_wall_s": serial_wall,
        "speedup_vs_serial": serial_wall / atlas.wall_time,
        "workers": workers,
        "chart_s": {
            "min": float(times.min()),
            "median": float(np.median(times)),
            "max": float(times.max()),
        },
        "chart_times_s": [round(float(t), 4) for t in times],
        "chart_nodes": [r.n_nodes for r in atlas.records if not r.error],
        "failed_charts": [{"tile": r.tile, "error": r.error} for r in failed],
        "charts_tol_missed": [
            {"cell": r.cell, "error_estimate": r.error_estimate}
            for r in atlas.records
            if not r.error and not r.tol_met
        ],
        "starts": n,
        "seed": seed,
        "success": run.success_rate,
        "collisions": int(run.collided.sum()),
        "outcome": run.message,
        "switches_max": int(run.switches.max()),
        "median_ratio": med,
        "p95_ratio": float(np.percentile(ratio, 95)) if ratio.size else float("nan"),
        "min_clearance": float(run.min_clearance.min()),
        "run_wall_s": run_wall,
        "load_before": load0,
        "load_after": loadavg(),
    }
    out["met"] = {
        "success": out["success"] >= TARGETS["success"],
        "collisions": out["collisions"] == TARGETS["collisions"],
        "median_ratio": med <= TARGETS["median_ratio"],
        "solve_s": atlas.wall_time <= TARGETS["solve_s"],
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--starts", type=int, default=1000, help="random starts per scenario")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=1e-8, help="chart tolerance")
    ap.add_argument("--workers", type=int, default=2, help="solver processes")
    ap.add_argument(
        "--serial", action="store_true", help="also solve with 1 worker (true speed-up)"
    )
    ap.add_argument("--scenario", action="append", choices=sorted(SCENARIOS), default=None)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    names = args.scenario or list(SCENARIOS)
    rows = []
    for name in names:
        r = bench(SCENARIOS[name](), args.starts, args.seed, args.tol, args.workers, args.serial)
        rows.append(r)
        if "error" in r:
            print(f"{r['scenario']:<15} FAILED: {r['error']}", flush=True)
            continue
        m = r["met"]
        print(
            f"{r['scenario']:<15} cells {r['cells']:>4}  solve {r['solve_wall_s']:6.1f} s "
            f"(cpu {r['solve_cpu_s']:6.1f} s, x{r['speedup']:.2f}; chart "
            f"{r['chart_s']['median']:.2f}/{r['chart_s']['max']:.2f} s med/max; "
            f"1 worker {r['serial_wall_s']:.1f} s) "
            f"[{'met' if m['solve_s'] else 'missed'}]  "
            f"success {100 * r['success']:6.2f}% [{'met' if m['success'] else 'missed'}]  "
            f"collisions {r['collisions']} [{'met' if m['collisions'] else 'missed'}]  "
            f"path x{r['median_ratio']:.3f} [{'met' if m['median_ratio'] else 'missed'}]  "
            f"switches <= {r['switches_max']}  run {r['run_wall_s']:.0f} s  "
            f"load {r['load_before']} -> {r['load_after']}",
            flush=True,
        )
    doc = {
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": platform.node(),
        "cpus": os.cpu_count(),
        "argv": vars(args) | {"out": str(args.out)},
        "targets": TARGETS,
        "note": "timings under a shared machine's load (load_before/after); not idle figures",
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
