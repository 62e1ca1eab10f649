"""The controller's install of a progressive atlas's revisions, in process (issue 23, round 4).

    python bench/bench_atlas_install.py [--map warehouse] [--out bench/results/atlas_install.json]

Solves a SLAM map's footprint atlas (``bench_slam``'s body: 0.22 m + 0.1 m look-ahead, so
``{map}~r0.32``; tol 1e-4, 2 workers) keeping every partial revision the solve publishes,
turns each into the index and chart messages the transform service sends (encoded), then
replays the controller's install of the revisions in order, twice: **before** (every revision
rebuilt from its index, every robot's law built anew: main up to 85476d2) and **after**
(``atlas_map_of(..., previous=)`` and ``AtlasMap.extend``: each robot's law made
from its law on the previous revision), for 3 unicycle goals
(``bench_slam_services``' pairs). Per revision and phase: decode of the new charts, their
load (``load_map``), the atlas rebuild, the robots' laws, their first-chart preparation
(``AtlasController.prepare``, as the controller's prime does). Fetching over the bus is not
included (``bench_slam_services`` measures the whole path). Load average recorded."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from bench_slam import LOOKAHEAD, MAPS_DIR, PAIRS, RADIUS, SEED  # noqa: E402
from bench_slam_services import pairs_of  # noqa: E402
from confnav.schemas import AtlasIndex, Goal, TransformSolution, decode, encode  # noqa: E402
from confnav.services.atlas_transform import atlas_result, messages_of  # noqa: E402
from confnav.services.navigation import load_map, make_controller  # noqa: E402
from provenance import commit, loadavg  # noqa: E402

from confnav.atlas.charts import solve_atlas  # noqa: E402
from confnav.atlas.wire import atlas_map_of, is_pending  # noqa: E402
from confnav.maps.footprint import inflate  # noqa: E402
from confnav.maps.occupancy import import_map  # noqa: E402

OUT = ROOT / "bench" / "results" / "atlas_install.json"


def revisions(name: str) -> tuple[Any, list[tuple[bytes, dict[str, bytes]]], float]:
    ws = inflate(import_map(MAPS_DIR / f"{name}.yaml").workspace, RADIUS + LOOKAHEAD)
    results: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    done = solve_atlas(
        ws, 1e-4, workers=2, accept=1e-3, on_partial=lambda pa: results.append(atlas_result(pa))
    )
    solve_s = time.perf_counter() - t0
    results.append(atlas_result(done))
    out = []
    for res in results:
        index, charts = messages_of(f"{name}~r0.32", "h" * 64, res)
        out.append((encode(index), {c.revision: encode(c) for c in charts}))
    return ws, out, solve_s


def replay(
    name: str, ws: Any, revs: list[tuple[bytes, dict[str, bytes]]], after: bool
) -> list[dict[str, Any]]:
    pairs = pairs_of(ws, 3, PAIRS, SEED)
    goals = [
        Goal(
            robot_id=f"r{k}",
            ws_id=f"{name}~r0.32",
            goal=(g.real, g.imag),
            robot_radius=RADIUS,
            drive="unicycle",
            lookahead=LOOKAHEAD,
        )
        for k, (_, g, _) in enumerate(pairs)
    ]
    known: dict[str, Any] = {}
    prev = None
    laws: list[Any] | None = None
    rows = []
    for ib, charts in revs:
        row: dict[str, Any] = {}
        index = decode(AtlasIndex, ib)
        maps: dict[str, Any] = {}
        dec_s = load_s = 0.0
        new = 0
        for cell in index.cells:
            if is_pending(cell):
                continue
            if cell.chart_revision in known:
                maps[cell.chart_revision] = known[cell.chart_revision]
                continue
            a = time.perf_counter()
            sol = decode(TransformSolution, charts[cell.chart_revision])
            b = time.perf_counter()
            maps[sol.revision] = load_map(sol)
            dec_s += b - a
            load_s += time.perf_counter() - b
            new += 1
        t = time.perf_counter()
        am = atlas_map_of(index, maps, previous=prev if after else None)
        row["atlas_s"] = time.perf_counter() - t
        known = am.known_charts()
        t = time.perf_counter()
        made = (
            [am.extend(c, prev) for c in laws]
            if after and laws is not None and prev is not None
            else None
        )
        if made is not None and all(m is not None for m in made):
            laws = made
            row["laws"] = "extended"
        else:
            laws = [make_controller(am, g) for g in goals]
            row["laws"] = "built"
        row["laws_s"] = time.perf_counter() - t
        t = time.perf_counter()
        for law, (s, _, th) in zip(laws, pairs, strict=True):
            getattr(law, "controller", law).prepare(s + LOOKAHEAD * np.exp(1j * th))
        row["prepare_s"] = time.perf_counter() - t
        row.update(
            charts=sum(not is_pending(c) for c in index.cells),
            cells=len(index.cells),
            new_charts=new,
            decode_s=dec_s,
            load_s=load_s,
        )
        row["total_s"] = dec_s + load_s + row["atlas_s"] + row["laws_s"] + row["prepare_s"]
        rows.append({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()})
        prev = am
    return rows


def main() -> int:
    import argparse
    import logging

    logging.disable(logging.WARNING)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default="warehouse")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    load0 = loadavg()
    ws, revs, solve_s = revisions(args.map)
    doc: dict[str, Any] = {
        "benchmark": "atlas_install",
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "map": args.map,
        "revisions": len(revs),
        "solve_s": round(solve_s, 2),
        "loadavg_start": load0,
    }
    for phase, after in (("before", False), ("after", True), ("before_again", False)):
        doc[phase] = replay(args.map, ws, revs, after)
        doc[f"loadavg_{phase}"] = loadavg()
    for phase in ("before", "after", "before_again"):
        rows = doc[phase][1:]  # the first revision builds everything in both
        doc[f"{phase}_median_total_s"] = float(np.median([r["total_s"] for r in rows]))
        doc[f"{phase}_median_atlas_laws_prepare_s"] = float(
            np.median([r["atlas_s"] + r["laws_s"] + r["prepare_s"] for r in rows])
        )
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print("revision  charts  new | before: atlas laws prep total | after: atlas laws prep total")
    for k, (b, a) in enumerate(zip(doc["before"], doc["after"], strict=True)):
        print(
            f"{k:8d} {a['charts']:4d}/{a['cells']:<3d} {a['new_charts']:3d} | "
            f"{b['atlas_s']:.3f} {b['laws_s']:.3f} {b['prepare_s']:.3f} {b['total_s']:.3f} | "
            f"{a['atlas_s']:.3f} {a['laws_s']:.3f} {a['prepare_s']:.3f} {a['total_s']:.3f} "
            f"({a['laws']})"
        )
    print({k: v for k, v in doc.items() if "median" in k or k.startswith("loadavg")})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
