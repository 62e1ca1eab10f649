"""A goal leg on a crowded atlas chart: the robot's own law against the stalled-leg rule.

    python bench/bench_goal_leg.py [--out bench/results/fleet_goal_leg.json]

Reproduces, in the core, the robot that lost 8 goals and held 10 robots in the services
warehouse (bench/results/fleet_services_final_seed0.json, w17, goal 2): the README's
warehouse shrunk by 0.3 m (body 0.2 m + look-ahead 0.1 m) as an atlas (tol 1e-4, as the
transform service solves ``warehouse~r0.3``), a unicycle (v_max 0.5 m/s, omega_max 2 rad/s,
commands held 0.05 s, exact arcs) starting its goal leg near its goal node (3.85, 7.30),
heading east, to its goal (4.005, 7.641), 0.06 m off the top aisle's wall in the shrunk
space.  Rows:

* ``own law``: the robot's own atlas law (``AtlasNavigator`` + ``UnicycleController``, what
  the controller service drives on the goal leg) for 60 s; the active chart's ``|T'|`` and
  the disk distance between the robot's look-ahead point and the goal where it ends;
* ``stalled-leg rule``: the same start with :class:`~confnav.navigation.fleet_coord
  .RoadmapCoordinator`'s rule on top (no 0.02 m of progress in ``leg_patience`` s: the
  straight law to the goal where that segment is free): when it switched and when the
  robot arrived.

Prints a table; writes JSON with the commit and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fleet import RESULTS, run_end, run_start, warehouse_goals

from confnav import inflate
from confnav.atlas.charts import solve_atlas
from confnav.atlas.compose import AtlasNavigator
from confnav.atlas.wire import AtlasController
from confnav.navigation.control import Status
from confnav.navigation.fleet_coord import (
    LEG_PROGRESS,
    LineLaw,
    RoadmapCoordinator,
)
from confnav.navigation.roadmap import segment_clearance
from confnav.navigation.safety import safety_filter
from confnav.navigation.unicycle import UnicycleController, step_exact

GOAL = complex(4.005355600671637, 7.640971891502693)  # w17's goal 2 (seed 0)
START = complex(3.85, 7.30)  # its axle where it started the leg (its status history)
DT, T_MAX, V_MAX, OMEGA_MAX, D = 0.05, 60.0, 0.5, 2.0, 0.1


def drive(atlas: Any, rule: bool) -> dict[str, Any]:
    """The goal leg from :data:`START` for up to :data:`T_MAX` s, with or without the
    stalled-leg rule (``RoadmapCoordinator.leg_patience``, its default)."""
    nav = AtlasNavigator(atlas, GOAL, speed=V_MAX, navfn="kr", goal_tol=0.05)
    own = UnicycleController(AtlasController(nav), D, v_max=V_MAX, omega_max=OMEGA_MAX)
    line = LineLaw(GOAL, safety_filter(atlas.workspace), v_max=V_MAX, gain=4.0)
    straight = UnicycleController(line, D, v_max=V_MAX, omega_max=OMEGA_MAX)
    patience = RoadmapCoordinator.leg_patience
    z, th, t = START, 0.0, 0.0
    best, t_best, switched = np.inf, 0.0, None
    law = own
    out: Any = None
    while t < T_MAX:
        out = law(np.array([z]), np.array([th]))
        p = complex(out.point[0])
        if int(out.status[0]) == Status.ARRIVED:
            break
        if abs(p - GOAL) < best - LEG_PROGRESS:
            best, t_best = abs(p - GOAL), t
        stalled = rule and switched is None and t - t_best >= patience
        if stalled and segment_clearance(atlas.workspace, np.array([p]), np.array([GOAL]))[0] > 0:
            switched, law = t, straight
            continue
        u = complex(out.u[0])
        zz, tt = step_exact(np.array([z]), np.array([th]), np.array([u.real]),
                            np.array([u.imag]), DT)  # fmt: skip
        z, th, t = complex(zz[0]), float(tt[0]), t + DT
    p = complex(out.point[0])
    arrived = int(out.status[0]) == Status.ARRIVED
    row: dict[str, Any] = {
        "arrived": arrived,
        "t_arrival_s": round(t, 2) if arrived else None,
        "t_switch_s": None if switched is None else round(switched, 2),
        "final_distance_m": abs(p - GOAL),
        "final_clearance_m": float(atlas.workspace.clearance(np.array([p]))[0]),
    }
    chart = nav.controller(0)
    try:
        w, dw = chart.cmap.T_and_dT(np.array([p, GOAL]))
        row["chart_abs_dT"] = float(abs(dw[0]))
        row["disk_distance_robot_goal"] = float(abs(w[0] - w[1]))
    except Exception as exc:  # a point off chart 0: say so, the row stands
        row["chart_note"] = f"{type(exc).__name__}: {exc}"
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, default=RESULTS / "fleet_goal_leg.json")
    args = ap.parse_args()
    stamp = run_start()
    ws = warehouse_goals(1, 0)[0]
    t0 = time.perf_counter()
    atlas = solve_atlas(inflate(ws, 0.3), 1e-4, workers=1)
    solve_s = time.perf_counter() - t0
    rows = {"own law": drive(atlas, False), "stalled-leg rule": drive(atlas, True)}
    print(f"atlas of the warehouse shrunk by 0.3 m: {len(atlas.charts)} charts, {solve_s:.1f} s")
    print("| goal leg | arrived | t arrival s | t switch s | final distance m | chart abs T' |")
    print("|---|---|---|---|---|---|")
    for name, r in rows.items():
        dt = r.get("chart_abs_dT", float("nan"))
        print(f"| {name} | {r['arrived']} | {r['t_arrival_s']} | {r['t_switch_s']} | "
              f"{r['final_distance_m']:.3f} | {dt:.1e} |")  # fmt: skip
    res = {**run_end(stamp), "cpu_count": os.cpu_count(), "goal": [GOAL.real, GOAL.imag],
           "start": [START.real, START.imag], "atlas_charts": len(atlas.charts),
           "atlas_solve_s": solve_s, "leg_patience_s": RoadmapCoordinator.leg_patience,
           "rows": rows}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
