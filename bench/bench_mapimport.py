"""Occupancy-grid import benchmark: ``confnav import-map`` on 400x400 grids.

    python bench/bench_mapimport.py [--runs 5] [--navigate] [--out bench/results/mapimport.json]

Grids (400 x 400 cells, written as YAML + PGM and read back, so the timing is the whole import
from the map file):
- ``default``: the seed's default workspace rasterised at 4.2 m / 400 (slanted edges, a star);
- ``office``: examples/office (256 x 176) padded with unknown cells to 400 x 400;
- ``office_noisy``: the same with 0.3 % of the free cells flipped to occupied (SLAM speckle),
  imported with ``min_obstacle_cells=2`` (specks dropped: the non-conservative option).

Target (issue 13): a 400x400 grid in <= 2 s. With ``--navigate`` the warehouse example is also
imported, solved and simulated (20 random starts) to check that the output solves and navigates.
Timings are wall times on a shared machine: the 1-minute load average is recorded beside each.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from confnav.maps.occupancy import import_map, rasterize
from confnav.scenes.workspaces import default_workspace

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "mapimport.json"
TARGET_S = 2.0
N = 400


def write(tmp: Path, name: str, img: np.ndarray, res: float, origin: tuple[float, float]) -> Path:
    Image.fromarray(img.astype(np.uint8), mode="L").save(tmp / f"{name}.pgm")
    (tmp / f"{name}.yaml").write_text(
        f"image: {name}.pgm\nresolution: {res}\norigin: [{origin[0]}, {origin[1]}, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    return tmp / f"{name}.yaml"


def grids(tmp: Path) -> list[tuple[str, Path, dict[str, Any]]]:
    res = 4.2 / N
    free = rasterize(default_workspace(), res, (-2.1, -2.1), (N, N))
    out = [("default", write(tmp, "default", np.where(free, 254, 0), res, (-2.1, -2.1)), {})]
    office = np.asarray(Image.open(ROOT / "examples" / "office.pgm"), dtype=np.uint8)
    big = np.full((N, N), 205, dtype=np.uint8)
    big[: office.shape[0], : office.shape[1]] = office
    out.append(("office", write(tmp, "office", big, 0.05, (-0.4, -0.4)), {}))
    rng = np.random.default_rng(0)
    noisy = big.copy()
    flip = (noisy == 254) & (rng.random(noisy.shape) < 0.003)
    noisy[flip] = 0
    out.append(
        (
            "office_noisy",
            write(tmp, "office_noisy", noisy, 0.05, (-0.4, -0.4)),
            {"min_obstacle_cells": 2},
        )
    )
    return out


def navigate(tmp: Path) -> dict[str, Any]:
    """Import, solve and simulate the warehouse example through the CLI (the contract)."""
    ws = tmp / "warehouse.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cli = [sys.executable, "-m", "confnav"]
    t0 = time.perf_counter()
    subprocess.run(
        [*cli, "import-map", str(ROOT / "examples" / "warehouse.yaml"), "-o", str(ws)],
        check=True,
        env=env,
        capture_output=True,
    )
    t1 = time.perf_counter()
    solve = subprocess.run(
        [*cli, "solve", str(ws), "-o", str(tmp / "map.json"), "-q"], env=env, capture_output=True
    )
    t2 = time.perf_counter()
    sim = subprocess.run(
        [
            *cli,
            "simulate",
            str(ws),
            "--map",
            str(tmp / "map.json"),
            "--goal=9,7",
            "--random",
            "20",
            "--gain",
            "100",
            "--vmax",
            "0.5",
            "--t-max",
            "300",
            "--json",
            str(tmp / "s.json"),
        ],
        env=env,
        capture_output=True,
        text=True,
    )
    t3 = time.perf_counter()
    summary = json.loads((tmp / "s.json").read_text())["summary"] if sim.returncode == 0 else {}
    return {
        "import_s": t1 - t0,
        "solve_s": t2 - t1,
        "solve_exit": solve.returncode,
        "simulate_s": t3 - t2,
        "simulate_exit": sim.returncode,
        "simulate_stdout": sim.stdout.strip(),
        "summary": summary,
        "loadavg1": os.getloadavg()[0],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--navigate", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    doc: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "commit": commit,
        "loadavg_start": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
        "target_s": TARGET_S,
        "rows": [],
    }
    print(f"load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    header = f"{'grid':<14}{'median s':>9}{'min s':>8}{'obst':>6}{'verts':>7}{'H cell':>8}"
    print(header + f"{'load':>6}  target")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for name, path, kw in grids(tmp):
            times, res = [], None
            for _ in range(args.runs):
                t0 = time.perf_counter()
                res = import_map(path, **kw)
                times.append(time.perf_counter() - t0)
            assert res is not None
            med = statistics.median(times)
            row = {
                "grid": name,
                "shape": list(res.report.shape),
                "median_s": med,
                "min_s": min(times),
                "obstacles": res.workspace.n_obstacles,
                "vertices": res.report.vertices,
                "hausdorff_cells": res.report.hausdorff_cells,
                "dropped_specks": res.report.dropped_specks,
                "loadavg1": os.getloadavg()[0],
                "target": "met" if med <= TARGET_S else "missed",
            }
            doc["rows"].append(row)
            print(
                f"{name:<14}{med:>9.3f}{min(times):>8.3f}{row['obstacles']:>6}"
                f"{row['vertices']:>7}{row['hausdorff_cells']:>8.3f}{row['loadavg1']:>6.1f}  "
                f"{row['target']}"
            )
        if args.navigate:
            nav = navigate(tmp)
            doc["navigate_warehouse"] = nav
            print(
                f"warehouse: import {nav['import_s']:.2f} s, solve {nav['solve_s']:.1f} s "
                f"(exit {nav['solve_exit']}), simulate {nav['simulate_s']:.1f} s: "
                f"{nav['simulate_stdout']} (load {nav['loadavg1']:.1f})"
            )
    doc["loadavg_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
