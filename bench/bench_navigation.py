"""Navigation benchmark: conformal navigation (KR k=6, KR auto k, harmonic) vs a naive
potential field, over random starts in several workspaces; plus the cost of a control step.

    python bench/bench_navigation.py [--quick] [--n 1000] [--seed 0]

Prints a table and writes bench/results/navigation.json.  Targets (issue 3): >= 99.5% success
with zero collisions wherever the map solves; control step <= 50 us single, <= 5 us per robot
in a batch of 1000.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # small matrices; threads only fight over the 2 cores

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor, as_completed  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

import confnav  # noqa: E402
from confnav.baseline import PotentialField  # noqa: E402
from confnav.control import Controller  # noqa: E402
from confnav.critical import find_critical_points  # noqa: E402
from confnav.errors import ConfnavError  # noqa: E402
from confnav.scenarios import (  # noqa: E402
    Scenario,
    cup_trap,
    default_scenario,
    l_room,
    mixed,
    random_starts,
    spiral_corridor,
)
from confnav.shortest_path import ShortestPaths  # noqa: E402
from confnav.sim import STALLED, TIMEOUT, simulate  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "navigation.json"
METHODS = ("KR k=6", "KR auto", "harmonic", "APF")  # the issue's four
FLOOR_METHODS = ("KR auto+floor", "harmonic+floor")  # with --floor
V_MIN = 0.25  # speed floor of "harmonic+floor" (direction kept; 0 for the plain law)
V_MAX = 1.0
T_MAX = 1e5


def scenarios() -> list[Scenario]:
    return [
        default_scenario(),
        cup_trap(0.4),
        cup_trap(0.8),
        cup_trap(1.6),
        l_room(),
        mixed(10),
        mixed(20),
        spiral_corridor(2),
        spiral_corridor(5),
        spiral_corridor(10),
    ]


def make_field(method: str, cmap: Any, sc: Scenario) -> tuple[Any, dict[str, Any]]:
    info: dict[str, Any] = {}
    if method == "APF":
        return PotentialField(sc.workspace, sc.goal, v_max=V_MAX), info
    if method == "KR k=6":
        ctl = Controller(cmap, sc.goal, navfn="kr", k=6, v_max=V_MAX)
        cp = find_critical_points(ctl.navfn)
        info["critical_points"] = cp.message
        info["k_ok"] = cp.ok
    elif method.startswith("KR auto"):
        v_min = V_MIN if method.endswith("+floor") else 0.0
        ctl = Controller(cmap, sc.goal, navfn="kr", k="auto", v_max=V_MAX, v_min=v_min)
    else:
        v_min = V_MIN if method == "harmonic+floor" else 0.0
        ctl = Controller(cmap, sc.goal, navfn="harmonic", v_max=V_MAX, v_min=v_min)
        info["green_terms"] = ctl.navfn.diagnostics.n_terms  # type: ignore[attr-defined]
    if hasattr(ctl.navfn, "k"):
        info["k"] = ctl.navfn.k  # type: ignore[attr-defined]
    return ctl, info


def solve_cached(ws: Any, cache: Path | None) -> Any:
    """``confnav.solve`` with an optional on-disk cache keyed by the workspace hash."""
    path = cache / f"{ws.content_hash[:16]}.json" if cache else None
    if path is not None and path.exists():
        nav = confnav.ConformalMap.from_json(path.read_text()).for_navigation()
        nav.from_cache = True  # type: ignore[attr-defined]
        return nav
    cmap = confnav.solve(ws)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(cmap.to_json())
    # robots are driven through the map the controller service uses (checked within 1e-7)
    return cmap.for_navigation()


def run_case(
    sc: Scenario, n: int, seed: int, cache: Path | None = None, methods: tuple[str, ...] = METHODS
) -> tuple[dict[str, Any], Any]:
    ws = sc.workspace
    row: dict[str, Any] = {"scenario": sc.name, "n_obstacles": ws.n_obstacles, "methods": {}}
    starts = random_starts(ws, n, seed, margin=0.05)
    t0 = time.perf_counter()
    shortest = ShortestPaths(ws, sc.goal).lengths(starts)
    row["shortest_path_time"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cmap = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cmap = solve_cached(ws, cache)
        row["map"] = {
            "solve_time": time.perf_counter() - t0,
            "from_cache": bool(getattr(cmap, "from_cache", False)),
            "solve_wall_time_recorded": float(cmap.diagnostics.wall_time),
            "error_estimate": float(cmap.diagnostics.error_estimate),
            "min_radius": float(cmap.radii.min()) if cmap.radii.size else None,
            "goal_image_abs": float(abs(complex(cmap.T(sc.goal)))),
            "warnings": [str(w.message) for w in caught],
        }
    except ConfnavError as exc:
        row["map"] = {"error": f"{type(exc).__name__}: {exc}"}
    for method in methods:
        if cmap is None and method != "APF":
            row["methods"][method] = {"error": "no map"}
            continue
        try:
            t0 = time.perf_counter()
            fld, info = make_field(method, cmap, sc)
            setup = time.perf_counter() - t0
            res = simulate(fld, starts, t_max=T_MAX, atol=1e-4, max_step=0.025 * ws.diameter)
        except ConfnavError as exc:
            row["methods"][method] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        if method != "APF" and not res.success.all():
            # why: parked at a critical point (saddle / spurious minimum) or crawling where
            # phi is flat or |T'| tiny
            cp = fld.check()
            crit = np.concatenate([cp.saddles, cp.spurious_minima, cp.maxima])
            wf = np.asarray(cmap.T(res.final[~res.success]))
            near = (
                np.min(np.abs(wf[:, None] - crit[None, :]), axis=1) < 1e-2
                if crit.size
                else np.zeros(wf.size, dtype=bool)
            )
            info["failed_at_critical_point"] = int(near.sum())
            info["failed_crawling"] = int((~near).sum())
            info["critical_points"] = cp.message
        ok = res.success & np.isfinite(shortest) & (shortest > 0)
        ratio = res.path_length[ok] / shortest[ok]
        row["methods"][method] = {
            **info,
            "setup_time": setup,
            "wall_time": res.wall_time,
            "success_rate": res.success_rate,
            "collisions": int(res.collided.sum()),
            "stalled": int((res.status == STALLED).sum()),
            "timeouts": int((res.status == TIMEOUT).sum()),
            "errors": int((res.status == 4).sum()),
            "median_time": float(np.median(res.time[res.success])) if res.success.any() else None,
            "p95_time": float(np.quantile(res.time[res.success], 0.95))
            if res.success.any()
            else None,
            "median_path_ratio": float(np.median(ratio)) if ratio.size else None,
            "p95_path_ratio": float(np.quantile(ratio, 0.95)) if ratio.size else None,
            "min_clearance": float(res.min_clearance.min()),
            "nfev": res.nfev,
        }
    return row, cmap


def _case_worker(
    sc: Scenario, n: int, seed: int, cache: Path | None, methods: tuple[str, ...]
) -> tuple[dict[str, Any], float]:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        row, _ = run_case(sc, n, seed, cache, methods)
    return row, time.perf_counter() - t0


def _timeit(fn: Any, reps: int) -> float:
    fn()
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        best = min(best, (time.perf_counter() - t0) / reps)
    return float(best)


def control_step_cost(cmap: Any, quick: bool) -> dict[str, Any]:
    sc = default_scenario()
    z1 = np.asarray(1.5 + 1.0j)
    zb = random_starts(sc.workspace, 1000, 3)
    reps1, repsb = (200, 5) if quick else (2000, 20)
    out: dict[str, Any] = {}
    for name in ("kr", "harmonic"):
        ctl = Controller(cmap, sc.goal, navfn=name, k=6, v_max=V_MAX)
        w1, wb = cmap.T(z1), cmap.T(zb)
        out[name] = {
            "single_us": 1e6 * _timeit(lambda c=ctl: c(z1), reps1),
            "single_velocity_us": 1e6 * _timeit(lambda c=ctl: c.velocity(z1), reps1),
            "batch1000_per_robot_us": 1e6 * _timeit(lambda c=ctl: c(zb), repsb) / zb.size,
            "navfn_single_us": 1e6 * _timeit(lambda c=ctl, w=w1: c.navfn.gradient(w), reps1),
            "navfn_batch1000_per_robot_us": 1e6
            * _timeit(lambda c=ctl, w=wb: c.navfn.gradient(w), repsb)
            / zb.size,
        }
    out["T_and_dT"] = {
        "single_us": 1e6 * _timeit(lambda: cmap.T_and_dT(z1), reps1),
        "batch1000_per_robot_us": 1e6 * _timeit(lambda: cmap.T_and_dT(zb), repsb) / zb.size,
    }
    return out


def _fmt(v: Any, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| scenario | M | map | method | success % | coll. | stalled | timeout "
        "| median t | median L/L* | min clear. | note |"
    )
    lines = [head, "|" + "---|" * 12]
    for row in rows:
        mp = row["map"]
        mtxt = (
            "FAILED"
            if "error" in mp
            else f"err {mp['error_estimate']:.0e}"
            + (f", r_min {mp['min_radius']:.3f}" if mp.get("min_radius") else "")
        )
        for method, r in row["methods"].items():
            if "error" in r:
                note = r["error"][:90]
                lines.append(
                    f"| {row['scenario']} | {row['n_obstacles']} | {mtxt} | {method} "
                    f"| - | - | - | - | - | - | - | {note} |"
                )
                continue
            notes = []
            if "k" in r and method.startswith("KR auto"):
                notes.append(f"k={r['k']:g}")
            if "k_ok" in r and not r["k_ok"]:
                notes.append("k=6 fails check: " + r["critical_points"])
            if r.get("failed_crawling"):
                notes.append(f"{r['failed_crawling']} crawling")
            if r.get("failed_at_critical_point"):
                notes.append(f"{r['failed_at_critical_point']} at a critical point")
            note = "; ".join(notes)
            lines.append(
                f"| {row['scenario']} | {row['n_obstacles']} | {mtxt} | {method} "
                f"| {100 * r['success_rate']:.1f} | {r['collisions']} | {r['stalled']} "
                f"| {r['timeouts']} | {_fmt(r['median_time'], '.3g')} "
                f"| {_fmt(r['median_path_ratio'], '.3f')} | {r['min_clearance']:.3f} | {note} |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="100 starts, fewer timing reps")
    ap.add_argument("--n", type=int, default=None, help="starts per scenario (default 1000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--map-cache", type=Path, default=None, help="reuse solved maps here")
    ap.add_argument("--jobs", type=int, default=2, help="scenarios in parallel (processes)")
    ap.add_argument("--floor", action="store_true", help="also run the speed-floor variants")
    args = ap.parse_args()
    n = args.n or (100 if args.quick else 1000)
    t_start = time.perf_counter()
    methods = METHODS + (FLOOR_METHODS if args.floor else ())
    cases = scenarios()
    order = sorted(range(len(cases)), key=lambda i: -cases[i].workspace.n_obstacles)
    rows: list[dict[str, Any]] = [{} for _ in cases]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {
            pool.submit(_case_worker, cases[i], n, args.seed, args.map_cache, methods): i
            for i in order
        }
        for fut in as_completed(futures):
            i = futures[fut]
            rows[i], dt = fut.result()
            print(f"# {cases[i].name}: {dt:.1f} s", flush=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default_map = solve_cached(default_scenario().workspace, args.map_cache)
    cost = control_step_cost(default_map, args.quick)
    text = table(rows)
    print()
    print(text)
    print()
    print("control step (default workspace, v_max saturation on):")
    for name, c in cost.items():
        print(f"  {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in c.items()))
    doc = {
        "n_starts": n,
        "seed": args.seed,
        "v_max": V_MAX,
        "v_min_floor": V_MIN if args.floor else None,
        "methods": list(methods),
        "jobs": args.jobs,
        "t_max": T_MAX,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "total_time": time.perf_counter() - t_start,
        "rows": rows,
        "control_step": cost,
        "table": text,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out} ({doc['total_time']:.0f} s)")


if __name__ == "__main__":
    main()
