"""Safety layer benchmark (issue 23 item 1): wrong and coarse maps, activity, cost.

    python bench/bench_safety.py [--starts 1000] [--quick] [--out bench/results/safety.json]

On the default workspace (the true geometry every run is checked against):

1. **Wrong and coarse maps.**  ``wrong``: the map solved (tol 1e-6) for the workspace with the
   rectangle moved by 0.1 m in x; ``missing``: the map solved for the workspace without the
   rectangle (an obstacle placed after mapping); ``coarse``: the map at 8 nodes per side
   (error estimate
   ~3e-2: the solver refuses it for navigation, ``UNUSABLE_ERROR``; the refusal is lifted for
   this map only, as the safety layer is meant to allow).  ``--starts`` random starts (>= 2 cm
   from the true walls) split over four goals, simulated by ``confnav.navigation.sim.simulate``
   against the TRUE clearance with the safety layer filtering against the true workspace
   (``Controller(..., safety=true_ws)``), and without it for comparison.  Target: 0
   collisions with the filter; arrivals are reported (not guaranteed by the filter).
2. **Activity on an accurate map** (tol 1e-6): the share of the law's commands the filter
   changes, over every velocity evaluation of the simulation and over the accepted points of
   the paths; the same share at the accepted points for other rates ``alpha``.
3. **Cost**: the filter alone on a batch of 1000 (and 100) robots, the law's commands at
   random free-space poses (mostly inactive) and commands aimed at the nearest wall (every
   robot filtered); and the controller's batched step with and without it.  Target <= 5 us
   per robot at 1000 robots.  Timings are wall times on a shared machine: the load average
   is recorded beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import git, loadavg

import confnav
from confnav.conformal import solver as _solver
from confnav.geometry import Workspace
from confnav.navigation.control import Controller
from confnav.navigation.safety import SafetyFilter
from confnav.navigation.sim import STATUS_NAMES, simulate
from confnav.scenes.scenarios import random_starts
from confnav.scenes.workspaces import default_workspace

RESULTS = Path(__file__).resolve().parent / "results" / "safety.json"
#: one far corner and three goals around the rectangle (the obstacle the wrong maps get wrong)
GOALS = (1.5 + 1.5j, -1.2 + 0.65j, -0.85 + 1.15j, -0.45 + 0.65j)
TARGET_US = 5.0
T_MAX = 200.0  # s per robot (a 4 m room at <= 0.5 m/s); stalled robots end earlier


def maps(ws: Workspace) -> dict[str, Any]:
    obs = list(ws.obstacles)
    obs[1] = obs[1] + 0.1  # the rectangle, 0.1 m to the right
    moved = Workspace(ws.outer, obs, anchor=ws.anchor)
    out: dict[str, Any] = {}
    t = time.perf_counter()
    out["accurate"] = confnav.solve(ws, tol=1e-6).for_navigation()
    out["wrong"] = confnav.solve(moved, tol=1e-6).for_navigation()
    missing = Workspace(ws.outer, obs[:1] + obs[2:], anchor=ws.anchor)
    out["missing"] = confnav.solve(missing, tol=1e-6).for_navigation()
    keep = _solver.UNUSABLE_ERROR
    _solver.UNUSABLE_ERROR = float("inf")  # this map only: the coarse map the layer allows
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out["coarse"] = confnav.solve(ws, tol=1e-2, nodes_per_side=8)
    finally:
        _solver.UNUSABLE_ERROR = keep
    print(f"# maps solved in {time.perf_counter() - t:.1f} s (load {loadavg()})", flush=True)
    return out


def drive(cmap: Any, ws: Workspace, starts: np.ndarray, safety: bool) -> dict[str, Any]:
    """Every start to one of GOALS (split evenly), checked against the true clearance."""
    counts = np.zeros(len(STATUS_NAMES), dtype=np.int64)
    minclr = np.inf
    commands = changed = infeasible = 0
    t0 = time.perf_counter()
    for k, goal in enumerate(GOALS):
        z = starts[k :: len(GOALS)]
        ctl = Controller(cmap, goal, safety=ws if safety else False)
        res = simulate(ctl, z, clearance=ws.clearance, t_max=T_MAX)
        counts += np.bincount(res.status, minlength=len(STATUS_NAMES))
        minclr = min(minclr, float(res.min_clearance.min()))
        c = ctl.safety_counts
        commands, changed, infeasible = (
            commands + c.commands,
            changed + c.changed,
            infeasible + c.infeasible,
        )
    row = {s: int(n) for s, n in zip(STATUS_NAMES, counts, strict=True)}
    row.update(
        starts=int(starts.size),
        min_clearance=minclr,
        commands_filtered=commands,
        commands_changed=changed,
        commands_infeasible=infeasible,
        wall_s=time.perf_counter() - t0,
    )
    return row


def activity(cmap: Any, ws: Workspace, starts: np.ndarray) -> dict[str, Any]:
    """How often the filter changes an accurate map's command."""
    evals = changed = 0
    pts = []
    for k, goal in enumerate(GOALS):
        ctl = Controller(cmap, goal)
        res = simulate(ctl, starts[k :: len(GOALS)], record_paths=True, t_max=T_MAX)
        evals += ctl.safety_counts.commands
        changed += ctl.safety_counts.changed
        assert res.paths is not None
        pts.append((ctl, np.concatenate(res.paths)))
    at_points = {}
    n_points = sum(p.size for _, p in pts)
    for alpha in (1.0, 1.5, 1.9):
        flt = SafetyFilter(ws, alpha=alpha)
        n = 0
        for ctl, p in pts:
            n += int(flt(p, ctl.law_velocity(p)).changed.sum())
        at_points[f"alpha={alpha:g}"] = {"changed": n, "fraction": n / n_points}
    return {
        "evaluations": evals,
        "evaluations_changed": changed,
        "fraction_evaluations": changed / max(evals, 1),
        "accepted_points": n_points,
        "at_accepted_points": at_points,
    }


def _time(f: Any, reps: int) -> float:
    f()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def cost(cmap: Any, ws: Workspace, reps: int) -> dict[str, Any]:
    ctl = Controller(cmap, GOALS[0])
    off = Controller(cmap, GOALS[0], safety=False)
    flt = ctl.safety
    assert flt is not None
    out: dict[str, Any] = {}
    for n in (100, 1000):
        z = random_starts(ws, n, seed=11, margin=0.002)
        law = ctl.law_velocity(z)
        r = flt.rows(z)
        nearest = np.argmax(np.where(np.isfinite(r.bounds), r.bounds, -np.inf), axis=1)
        into = -0.5 * r.normals[np.arange(n), nearest]  # at the nearest wall, full speed
        into = np.where(np.abs(into) > 0, into, -0.5)
        hit = flt(z, into)
        out[str(n)] = {
            "law_commands_us": _time(lambda z=z, law=law: flt(z, law), reps) / n * 1e6,
            "law_commands_changed": int(flt(z, law).changed.sum()),
            "into_walls_us": _time(lambda z=z, u=into: flt(z, u), reps) / n * 1e6,
            "into_walls_changed": int(hit.changed.sum()),
            "step_with_us": _time(lambda z=z: ctl(z), reps) / n * 1e6,
            "step_without_us": _time(lambda z=z: off(z), reps) / n * 1e6,
        }
    return out


def table(doc: dict[str, Any]) -> str:
    lines = [
        "map       filter  starts  arrived  collided  stalled  timeout  error  min clearance",
    ]
    for name, r in doc["drive"].items():
        lines.append(
            f"{name:<17s} {r['starts']:6d}  {r['arrived']:7d}  {r['collided']:8d}  "
            f"{r['stalled']:7d}  {r['timeout']:7d}  {r['error']:5d}  {r['min_clearance']:.2e}"
        )
    a = doc["activity"]
    lines.append(
        f"accurate map: filter changed {a['evaluations_changed']} of {a['evaluations']} "
        f"evaluations ({100 * a['fraction_evaluations']:.3f} %); at accepted points: "
        + ", ".join(
            f"{k} {100 * v['fraction']:.3f} %" for k, v in a["at_accepted_points"].items()
        )
    )
    for n, c in doc["cost"].items():
        lines.append(
            f"cost at {n} robots: filter {c['law_commands_us']:.2f} us/robot on the law's "
            f"commands ({c['law_commands_changed']} changed), {c['into_walls_us']:.2f} us "
            f"aimed at walls ({c['into_walls_changed']} changed); controller step "
            f"{c['step_with_us']:.2f} us with, {c['step_without_us']:.2f} us without"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--starts", type=int, default=1000)
    ap.add_argument("--quick", action="store_true", help="200 starts, fewer timing repeats")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    n = 200 if args.quick else args.starts
    reps = 5 if args.quick else 30
    started = datetime.now(UTC).isoformat(timespec="seconds")
    commit = git("rev-parse", "HEAD")
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    load0 = loadavg()
    t0 = time.perf_counter()
    ws = default_workspace()
    m = maps(ws)
    starts = random_starts(ws, n, seed=args.seed, margin=0.02)
    drive_rows: dict[str, Any] = {}
    for name in ("wrong", "missing", "coarse"):
        for safety in (True, False):
            key = f"{name:<7s} {'on' if safety else 'off'}"
            drive_rows[key] = drive(m[name], ws, starts, safety)
            print(f"# {key}: {drive_rows[key]['wall_s']:.0f} s (load {loadavg()})", flush=True)
    act = activity(m["accurate"], ws, starts[: max(40, n // 5)])
    print(f"# activity done (load {loadavg()})", flush=True)
    cst = cost(m["accurate"], ws, reps)
    targets = {
        "0 collisions with the filter (wrong, missing, coarse)": "met"
        if all(r["collided"] == 0 for k, r in drive_rows.items() if k.endswith("on"))
        else "missed",
        f"filter <= {TARGET_US} us/robot at 1000 robots (law's commands)": "met"
        if cst["1000"]["law_commands_us"] <= TARGET_US
        else "missed",
        f"filter <= {TARGET_US} us/robot at 1000 robots (every robot filtered)": "met"
        if cst["1000"]["into_walls_us"] <= TARGET_US
        else "missed",
    }
    doc: dict[str, Any] = {
        "commit": commit,
        "dirty": dirty,
        "started": started,
        "load_before": load0,
        "cpu_count": os.cpu_count(),
        "note": "timings under the load shown (shared machine), not idle figures",
        "starts": n,
        "goals": [[g.real, g.imag] for g in GOALS],
        "t_max": T_MAX,
        "maps": {
            k: {"error_estimate": float(v.diagnostics.error_estimate)} for k, v in m.items()
        },
        "drive": drive_rows,
        "activity": act,
        "cost": cst,
        "targets": targets,
    }
    doc["table"] = table(doc)
    doc["load_after"] = loadavg()
    doc["total_s"] = time.perf_counter() - t0
    print(doc["table"])
    for k, v in targets.items():
        print(f"  {k}: {v}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out} ({doc['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
