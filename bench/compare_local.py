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

from confnav.conformal import solver
from confnav.maps.footprint import inflate
from confnav.scenes.workspaces import (
    default_workspace,
    mirror_asymmetry,
    mirror_squares,
    mixed_obstacles,
)

CASES = {
    "mixed10": lambda: mixed_obstacles(10),
    "default": default_workspace,
    "gap01": lambda: mirror_squares(0.1),
    "gap001": lambda: mirror_squares(0.01),
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
            out["asymmetry"] = mirror_asymmetry(m.centers, m.radii)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
