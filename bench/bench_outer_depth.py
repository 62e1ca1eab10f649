"""The first sweep's a-priori crowding test (issue 23, round 4; ``confnav.atlas.decompose.
outer_depth``): its value and cost against the single-map attempt it spares.

    python bench/bench_outer_depth.py [--out bench/results/outer_depth.json]

Per workspace (the outside check's clinic, the shared door scene, the README's office map,
the default workspace, SLAM maps; some shrunk by a body): ``outer_depth`` at 10,000 (the
test's), 40,000 and 160,000 grid nodes with its wall time, the other a-priori reasons
(elongation, bottleneck), and the single-map attempt the transform service makes first
(``solve(ws, 1e-3, max_error=1e-2)``, the first rung of its ladder): its outcome and wall
time. Load average recorded (a shared machine)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from provenance import commit, loadavg  # noqa: E402

from confnav.atlas.charts import OUTER_DEPTH_MIN, SINGLE_MAP_MAX_RATIO  # noqa: E402
from confnav.atlas.decompose import bottleneck, elongation, outer_depth  # noqa: E402
from confnav.conformal.solver import solve  # noqa: E402
from confnav.errors import CrowdingError, SolverError  # noqa: E402
from confnav.geometry import Workspace  # noqa: E402

OUT = ROOT / "bench" / "results" / "outer_depth.json"


def workspaces() -> list[tuple[str, Workspace]]:
    from test_outer_depth import CLINIC_OBSTACLES, CLINIC_OUTER, DOOR_OBSTACLES, DOOR_OUTER

    from confnav.maps.footprint import inflate
    from confnav.maps.occupancy import import_map
    from confnav.scenes.workspaces import default_workspace

    office = import_map(ROOT / "examples" / "office.yaml").workspace
    slam = ROOT / "tests" / "data" / "slam"
    clinic = Workspace(CLINIC_OUTER, CLINIC_OBSTACLES)
    return [
        ("clinic", clinic),
        ("clinic~r0.3", inflate(clinic, 0.3)),
        ("door", Workspace(DOOR_OUTER, DOOR_OBSTACLES)),
        ("office", office),
        ("office~r0.2", inflate(office, 0.2)),
        ("default", default_workspace()),
        ("default~r0.2", inflate(default_workspace(), 0.2)),
        ("tb3_world", import_map(slam / "tb3_world.yaml").workspace),
        ("empty_room", import_map(slam / "empty_room.yaml").workspace),
    ]


def single(ws: Workspace) -> dict[str, Any]:
    t = time.perf_counter()
    try:
        m = solve(ws, 1e-3, max_error=1e-2)
        out = f"solved (estimate {m.diagnostics.error_estimate:.1e})"
    except CrowdingError as exc:
        out = f"CrowdingError: {str(exc)[:120]}"
    except SolverError as exc:
        out = f"{type(exc).__name__}: {str(exc)[:120]}"
    return {"single_map": out, "single_map_s": round(time.perf_counter() - t, 3)}


def main() -> int:
    import logging
    import warnings

    logging.disable(logging.WARNING)
    warnings.simplefilter("ignore")
    sys.path.insert(0, str(ROOT / "tests"))
    out = Path(sys.argv[sys.argv.index("--out") + 1]) if "--out" in sys.argv else OUT
    rows = []
    for name, ws in workspaces():
        row: dict[str, Any] = {"workspace": name, "load": loadavg()}
        for cells in (10_000, 40_000, 160_000):
            t = time.perf_counter()
            g, _ = outer_depth(ws, cells)
            row[f"outer_depth_{cells}"] = g
            row[f"outer_depth_{cells}_s"] = round(time.perf_counter() - t, 3)
        row["elongation"] = round(elongation(ws.polygon), 2)
        row["bottleneck"] = round(bottleneck(ws.polygon)[0], 2)
        row["flagged_by_outer_depth"] = row["outer_depth_10000"] < OUTER_DEPTH_MIN
        row["flagged_before"] = row["elongation"] > SINGLE_MAP_MAX_RATIO or row["bottleneck"] > 3
        row.update(single(ws))
        rows.append(row)
        print(json.dumps(row), flush=True)
    doc = {
        "benchmark": "outer_depth",
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "threshold": OUTER_DEPTH_MIN,
        "rows": rows,
    }
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
