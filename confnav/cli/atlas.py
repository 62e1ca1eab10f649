"""``confnav atlas``: solve a workspace as an atlas of charts and navigate by composition.

``confnav atlas WS.json --goal=X,Y (--starts="X,Y;X,Y" | --random N --seed S) [--tol 1e-8]
[--workers 2] [--tile T] [--margin M] [--hysteresis H] [--speed V] [--json OUT.json]``

Prints the cells (tile, obstacles, nodes, solve time) and the runs' summary: success,
collisions, chart switches, path length over the shortest path.  Exit 0 only if every robot
arrived without collision.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from confnav.argtypes import output_path, positive_int
from confnav.cli.simulate import _point, _points


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "atlas",
        help="solve a large or corridor-rich workspace as an atlas and navigate through it",
        description="Decompose the free space into overlapping cells, solve each cell's "
        "conformal map in parallel, and simulate robots under the sequentially composed "
        "navigation laws (docs/ATLAS.md).",
    )
    p.add_argument("workspace", type=Path, help="workspace JSON/GeoJSON")
    p.add_argument("--goal", type=_point, required=True, help="goal X,Y (use --goal=X,Y)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--starts", type=_points, help='starts "X,Y;X,Y;..." (one argument)')
    g.add_argument("--random", type=positive_int, metavar="N", help="N random starts in free space")
    p.add_argument("--seed", type=int, default=0, help="seed for --random")
    p.add_argument(
        "--tol",
        type=float,
        default=1e-8,
        help="accuracy of each chart's circle domain (dimensionless)",
    )
    p.add_argument("--workers", type=int, default=2, help="solver processes")
    p.add_argument("--tile", type=float, help="initial tile side, m (default 6 x inradius)")
    p.add_argument("--margin", type=float, help="local-goal depth in overlaps, m")
    p.add_argument("--hysteresis", type=float, help="switching depth, m (default margin/2)")
    p.add_argument("--speed", type=float, default=1.0, help="commanded speed, m/s")
    p.add_argument("--json", type=output_path, help="write cells, plan and runs here")
    p.set_defaults(func=run_atlas)


def run_atlas(args: argparse.Namespace) -> int:
    from confnav.atlas import AtlasNavigator, solve_atlas
    from confnav.geometry import Workspace
    from confnav.navigation.shortest_path import ShortestPaths
    from confnav.navigation.sim import STATUS_NAMES
    from confnav.scenes.scenarios import random_starts

    ws = Workspace.load(args.workspace)
    kw = {k: getattr(args, k) for k in ("tile", "margin") if getattr(args, k) is not None}
    atlas = solve_atlas(ws, args.tol, workers=args.workers, **kw)
    print(
        f"atlas: {len(atlas.charts)} cells, solved in {atlas.wall_time:.2f} s "
        f"(charts {atlas.cpu_time:.2f} s, speed-up x{atlas.speedup:.2f})"
    )
    print(f"{'cell':>4} {'obst':>4} {'nodes':>6} {'time s':>7} {'error':>8}")
    ok_records = [r for r in atlas.records if not r.error]
    for r in ok_records:
        n_obs = atlas.decomposition.cells[r.cell].workspace.n_obstacles
        print(f"{r.cell:>4} {n_obs:>4} {r.n_nodes:>6} {r.wall_time:>7.2f} {r.error_estimate:>8.1e}")
    nav = AtlasNavigator(atlas, args.goal, hysteresis=args.hysteresis, speed=args.speed)
    doc: dict[str, Any] = {
        "cells": [
            {"tile": c.tile, "workspace": c.workspace.to_dict(), "rank": float(nav.plan.rank[i])}
            for i, c in enumerate(atlas.decomposition.cells)
        ],
        "solve_wall_s": atlas.wall_time,
        "chart_s": [r.wall_time for r in ok_records],
    }
    starts = (
        np.asarray(args.starts, dtype=np.complex128)
        if args.starts
        else random_starts(ws, args.random, seed=args.seed)
        if args.random
        else None
    )
    code = 0
    if starts is not None:
        run = nav.run(starts)
        short = ShortestPaths(ws, nav.goal).lengths(starts)
        ratio = run.path_length / short
        ok = run.success
        med = float(np.median(ratio[ok])) if ok.any() else float("nan")
        print(
            f"{starts.size} robots: {run.message}; collisions {int(run.collided.sum())}; "
            f"switches <= {int(run.switches.max())}; median path x{med:.3f} of shortest"
        )
        doc["runs"] = [
            {
                "start": [complex(s).real, complex(s).imag],
                "status": STATUS_NAMES[int(st)],
                "path_length": float(pl),
                "shortest": float(sh),
                "cells": list(cs),
            }
            for s, st, pl, sh, cs in zip(
                starts, run.status, run.path_length, short, run.cells, strict=True
            )
        ]
        code = 0 if bool(run.success.all()) and not run.collided.any() else 1
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return code
