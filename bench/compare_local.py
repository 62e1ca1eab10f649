"""Per-side refinement against everywhere refinement, one case, same process (issue 24 item 2).

    python bench/compare_local.py CASE MODES TOL     # CASE: mixed10, default, gap01, gap001, shrunk
                                                     # MODES: local,full

Prints one JSON line per mode: wall and CPU time, load average before and after, tol_met, the
error estimate and its parts, the refinements (levels, partial levels with ``refined_sides``)
and, for the mirror-symmetric square pairs, the true asymmetry of the circle domain. The lines
of a run are kept in ``bench/results/local_refinement.json`` (with the commit they ran at).
"""

from __future__ import annotations

import json
import os
import sys
import time
import warnings

import numpy as np

from confnav import Workspace
from confnav.conformal import solver
from confnav.maps.footprint import inflate
from confnav.scenes.workspaces import default_workspace, mixed_obstacles

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]


def squares(gap: float) -> Workspace:
    """Two unit squares ``gap`` apart, mirror images under x -> -x, anchor on the axis."""
    g = gap / 2
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    return Workspace(ROOM, [left, right], anchor=[0, 1.5])


CASES = {
    "mixed10": lambda: mixed_obstacles(10),
    "default": default_workspace,
    "gap01": lambda: squares(0.1),
    "gap001": lambda: squares(0.01),
    "shrunk": lambda: inflate(default_workspace(), 0.2),
}


def main() -> None:
    case, modes, tol = sys.argv[1], sys.argv[2].split(","), float(sys.argv[3])
    ws = CASES[case]()
    warnings.simplefilter("ignore")
    for mode in modes:
        solver.LOCAL_REFINEMENT = mode == "local"
        l0 = os.getloadavg()[0]
        t, c = time.perf_counter(), time.process_time()
        m = solver.solve(ws, tol)
        d = m.diagnostics
        out = {
            "case": case,
            "mode": mode,
            "tol": tol,
            "wall": time.perf_counter() - t,
            "cpu": time.process_time() - c,
            "load": [l0, os.getloadavg()[0]],
            "tol_met": d.tol_met,
            "est": d.error_estimate,
            "residual": d.boundary_residual,
            "disc": d.discretisation_error,
            "nodes": sum(d.nodes),
            "refinements": [{k: float(v) for k, v in r.items()} for r in d.refinements],
        }
        if case.startswith("gap"):
            asym = max(abs(m.radii[0] - m.radii[1]), abs(m.centers[0] + np.conj(m.centers[1])))
            out["asymmetry"] = float(asym)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
