"""Fleet roadmap sizes and build times (issue 25: what the controller's roadmap build costs).

    python bench/bench_roadmap.py [--workspace FILE ...] [--radii 0 0.2 0.35] [--out FILE.json]

For the default workspace and each ``--workspace`` file, shrunk by each filter radius: the
roadmap ``fleet_coord.fleet_roadmap`` builds (nodes at least ``MIN_SPACING`` apart) and the
one of nodes ``(2 rho + 5 cm) / sin 60deg`` apart, as before that floor (``unfloored``): nodes,
edges, build seconds (CPU of this process) and the all-pairs distance matrix's size.  Prints a
table, writes bench/results/roadmap_sizes.json with the commit.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from provenance import commit  # script mode: bench/ is on sys.path

from confnav import Workspace, default_workspace, inflate
from confnav.navigation.fleet_coord import MIN_SPACING, fleet_roadmap
from confnav.navigation.roadmap import build_roadmap

RESULTS = Path(__file__).resolve().parent / "results" / "roadmap_sizes.json"


def measure(ws: Workspace, rho: float, floored: bool) -> dict[str, Any]:
    """One roadmap's size and build time."""
    t0 = time.process_time()
    if floored:
        rm = fleet_roadmap(ws, rho)
    else:  # the spacing before MIN_SPACING (RoadmapCoordinator.build's default then)
        gap = 2.0 * rho + 0.05
        sp = gap / np.sqrt(0.75)
        rm = build_roadmap(ws, sp, pass_gap=gap, edge_clearance=0.03, max_edge=2.2 * sp,
                           prune_leaves=True)  # fmt: skip
    cpu = time.process_time() - t0
    return {"nodes": rm.size, "edges": len(rm.edges), "spacing": rm.spacing,
            "build_cpu_s": cpu, "dist_mb": rm.dist.nbytes / 1e6}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--workspace", nargs="*", default=[], help="workspace JSON files")
    ap.add_argument("--radii", type=float, nargs="*", default=[0.0, 0.2, 0.35])
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    spaces = [("default", default_workspace())]
    spaces += [(Path(f).stem, Workspace.load(f)) for f in args.workspace]
    rows = []
    print(f"{'workspace':16s} {'rho':>5s} {'roadmap':9s} {'nodes':>6s} {'edges':>6s} "
          f"{'spacing':>7s} {'build s':>8s} {'dist MB':>9s}")  # fmt: skip
    for name, ws0 in spaces:
        for rho in args.radii:
            ws = inflate(ws0, rho) if rho > 0 else ws0
            for floored in (True, False):
                kind = "floored" if floored else "unfloored"
                r = {"workspace": name, "rho": rho, "roadmap": kind, **measure(ws, rho, floored)}
                rows.append(r)
                print(f"{name:16s} {rho:5.2f} {r['roadmap']:9s} {r['nodes']:6d} {r['edges']:6d} "
                      f"{r['spacing']:7.3f} {r['build_cpu_s']:8.2f} {r['dist_mb']:9.1f}",
                      flush=True)  # fmt: skip
    doc = {"about": "fleet roadmap sizes and build times (bench_roadmap.py)", "commit": commit(),
           "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
           "command": " ".join(sys.argv), "min_spacing": MIN_SPACING, "rows": rows}  # fmt: skip
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
