"""The coarse rung of a progressive map: ``confnav.solve`` to the first revision's tolerance.

    python bench/bench_coarse.py [--runs 3] [--out bench/results/coarse.json] [--no-reference]
    python -m bench coarse [--quick]

The transform service publishes a first revision solved to ``LADDER[0]`` (1e-3), accepted up to
``COARSE_MAX_ERROR`` (1e-2) (services/definitions.py), then refines (issue 23 item 2: "1e-3
within about a second on room-sized workspaces"). This benchmark solves exactly that, with
the service's constants, on the workspaces a robot with a body gets (``{ws}~r{R}``, the
free space shrunk by :func:`confnav.maps.footprint.inflate`, as ``derived_definition`` does):

* the default workspace unshrunk and shrunk by 0.1, 0.2 and 0.3 m (0.2 m body + 0.1 m
  look-ahead of a unicycle);
* the README's ``examples/warehouse.yaml`` and ``examples/office.yaml`` (``import_map``)
  shrunk by 0.2 and 0.3 m. The office with a body is an atlas case (its single map raises a
  crowding error; the service then solves an atlas): the row records the error and the time
  spent until it.

Every shrunk case is run twice in the same process: ``mitre_limit`` 5 (the footprint's
previous default: far-reaching mitre spikes at sharp corners) and the current
:data:`confnav.maps.footprint.MITRE_LIMIT` (``before`` / ``after`` rows). Reported per row:
the median over ``--runs`` solves of the CPU time (``time.process_time``: all threads of this
process, less sensitive to the other processes of a shared machine than the wall time, also
given) and of the wall time, the load average, the polygon sides and the narrowest gap between
boundaries, nodes per boundary at the coarsest mesh level and at the level returned, the mesh
levels solved and the Koebe sweeps of each (from the progress messages), the error estimate,
its parts, and ``tol_met``. The first solve of the process (imports, caches: what a fresh
worker pays once) is timed apart and not in the medians.

Honesty (no ``--no-reference``): each default-workspace case with the current footprint is
also solved to 1e-7, and the coarse map's true error (its centres and radii against that
reference's) must not exceed its estimate plus the reference's.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from bench_core import code_info, machine_info  # script mode: bench/ is on sys.path

import confnav
from confnav import ConformalMap, Workspace
from confnav.conformal.meshing import plan_boundaries
from confnav.conformal.solver import LEVELS
from confnav.maps.footprint import MITRE_LIMIT, inflate
from confnav.maps.occupancy import import_map
from confnav.scenes.workspaces import default_workspace

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from services.definitions import COARSE_MAX_ERROR, LADDER  # noqa: E402

#: The footprint's mitre limit before the bounded mitre (confnav.maps.footprint.MITRE_LIMIT).
OLD_MITRE_LIMIT = 5.0
#: Tolerance of the reference solve the coarse maps are checked against.
REFERENCE_TOL = 1e-7
#: Target (issue 23 item 2): the coarse rung of the default workspace shrunk by 0.2 m "within
#: about a second", taken as 1 s of CPU time (median).
TARGET_CPU_S = 1.0


def bases() -> dict[str, Workspace]:
    return {
        "default": default_workspace(),
        "warehouse": import_map(ROOT / "examples" / "warehouse.yaml").workspace,
        "office": import_map(ROOT / "examples" / "office.yaml").workspace,
    }


def min_gap(ws: Workspace) -> float:
    rings = [shapely.LinearRing(np.column_stack([z.real, z.imag])) for z in ws.boundaries]
    gaps = [rings[i].distance(rings[k]) for i in range(len(rings)) for k in range(i)]
    return float(min(gaps)) if gaps else float("inf")


def solve_once(ws: Workspace, tol: float) -> tuple[ConformalMap | None, dict[str, Any]]:
    sweeps: dict[int, int] = {}

    def progress(msg: str) -> None:
        head, _, tail = msg.strip().partition(" nodes/side: sweep ")
        if tail:
            ns = int(head)
            sweeps[ns] = sweeps.get(ns, 0) + 1

    t0, c0 = time.perf_counter(), time.process_time()
    err = None
    m = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            m = confnav.solve(ws, tol, max_error=COARSE_MAX_ERROR, progress=progress)
        except confnav.ConfnavError as exc:
            err = f"{type(exc).__name__}: {exc}"
    out: dict[str, Any] = {
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "sweeps_per_level": {str(k): v for k, v in sorted(sweeps.items())},
        "error": err,
    }
    return m, out


def summary(m: ConformalMap) -> dict[str, Any]:
    d = m.diagnostics
    return {
        "nodes": [int(n) for n in d.nodes],
        "nodes_per_side": int(d.nodes_per_side),
        "levels": [int(r["nodes_per_side"]) for r in d.refinements],
        "error_estimate": float(d.error_estimate),
        "discretisation_error": float(d.discretisation_error),
        "iteration_error": float(d.iteration_error),
        "boundary_residual": float(d.boundary_residual),
        "tol_met": bool(d.tol_met),
        "unverified": list(d.unverified),
    }


def true_error(m: ConformalMap, ref: ConformalMap) -> float:
    return float(
        max(np.max(np.abs(m.centers - ref.centers), initial=0.0),
            np.max(np.abs(m.radii - ref.radii), initial=0.0))
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="solves per row (medians)")
    ap.add_argument("--quick", action="store_true", help="default workspace only, 1 run")
    ap.add_argument("--no-reference", action="store_true", help="skip the 1e-7 reference solves")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "coarse.json")
    a = ap.parse_args(argv)
    runs = 1 if a.quick else max(1, a.runs)
    tol = LADDER[0]
    info = machine_info()
    code = code_info()
    ws_bases = bases()
    cases = [("default", r) for r in (0.0, 0.1, 0.2, 0.3)]
    if not a.quick:
        cases += [(n, r) for n in ("warehouse", "office") for r in (0.2, 0.3)]
    _, first = solve_once(ws_bases["default"], tol)  # imports and caches: a fresh worker
    rows: list[dict[str, Any]] = []
    print(f"coarse rung: tol {tol:g}, max_error {COARSE_MAX_ERROR:g}, {runs} run(s) per row")
    print(f"first solve in the process (default, unshrunk): {first['cpu_s']:.2f} s CPU")
    hdr = (
        f"{'case':<16} {'mitre':>5} {'sides':>5} {'gap':>7} {'coarsest':>9} {'nodes':>6} "
        f"{'levels':<13} {'CPU s':>6} {'wall s':>6} {'load':>5} {'estimate':>9} met"
    )
    print(hdr)
    for name, r in cases:
        for variant, ml in (("before", OLD_MITRE_LIMIT), ("after", MITRE_LIMIT)):
            if r == 0 and variant == "before":
                continue
            ws = ws_bases[name] if r == 0 else inflate(ws_bases[name], r, mitre_limit=ml)
            row: dict[str, Any] = {
                "case": f"{name}~r{r:g}" if r else name,
                "workspace": name,
                "radius": r,
                "variant": variant if r else "unshrunk",
                "mitre_limit": ml if r else None,
                "tol": tol,
                "max_error": COARSE_MAX_ERROR,
                "sides": [len(b) for b in ws.boundaries],
                "min_gap": min_gap(ws),
                "coarsest_nodes": [p.total for p in plan_boundaries(ws, LEVELS[0], tol)],
                "loadavg": list(os.getloadavg()),
            }
            per: list[dict[str, Any]] = []
            m = None
            for _ in range(runs):
                m, rec = solve_once(ws, tol)
                per.append(rec)
            row["cpu_s"] = statistics.median(p["cpu_s"] for p in per)
            row["wall_s"] = statistics.median(p["wall_s"] for p in per)
            row["runs_cpu_s"] = [p["cpu_s"] for p in per]
            row["sweeps_per_level"] = per[-1]["sweeps_per_level"]
            row["error"] = per[-1]["error"]
            if m is not None:
                row.update(summary(m))
            if (
                m is not None
                and name == "default"
                and variant != "before"
                and not (a.quick or a.no_reference)
            ):
                ref, rrec = solve_once(ws, REFERENCE_TOL)
                if ref is not None:
                    err = true_error(m, ref)
                    row["reference"] = {
                        "tol": REFERENCE_TOL,
                        "error_estimate": float(ref.diagnostics.error_estimate),
                        "cpu_s": rrec["cpu_s"],
                        "true_error_of_coarse": err,
                        "honest": err
                        <= m.diagnostics.error_estimate + ref.diagnostics.error_estimate,
                    }
            row["loadavg_end"] = list(os.getloadavg())
            rows.append(row)
            est = f"{row['error_estimate']:.1e}" if m is not None else "-"
            met = str(row.get("tol_met", False)) if m is not None else row["error"][:40]
            print(
                f"{row['case']:<16} {(ml if r else 0):>5g} {sum(row['sides']):>5} "
                f"{row['min_gap']:>7.4f} {sum(row['coarsest_nodes']):>9} "
                f"{sum(row.get('nodes', [0])):>6} {row.get('levels', '-')!s:<13} "
                f"{row['cpu_s']:>6.2f} {row['wall_s']:>6.2f} {row['loadavg'][0]:>5.2f} "
                f"{est:>9} {met}"
                + (
                    f"  true error {row['reference']['true_error_of_coarse']:.1e}"
                    if "reference" in row
                    else ""
                ),
                flush=True,
            )
    targets: list[dict[str, Any]] = []
    for r in (0.1, 0.2):
        pair = {x["variant"]: x for x in rows if x["case"] == f"default~r{r:g}"}
        after, before = pair["after"], pair["before"]
        targets.append(
            {
                "target": f"default workspace shrunk by {r:g} m to {tol:g} in <= "
                f"{TARGET_CPU_S:g} s CPU, tol_met",
                "value": f"{after['cpu_s']:.2f} s CPU ({before['cpu_s']:.2f} s with mitre limit "
                f"{OLD_MITRE_LIMIT:g}, same run)",
                "met": bool(after["cpu_s"] <= TARGET_CPU_S and after.get("tol_met")),
            }
        )
    refs = [x["reference"] for x in rows if "reference" in x]
    if refs:
        targets.append(
            {
                "target": "coarse maps honest: true error <= estimate (+ the 1e-7 reference's)",
                "value": ", ".join(f"{x['true_error_of_coarse']:.1e}" for x in refs),
                "met": all(x["honest"] for x in refs),
            }
        )
    for t in targets:
        print(f"{t['target']}: {t['value']}: {'met' if t['met'] else 'missed'}")
    info["loadavg_end"] = list(os.getloadavg())
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(
        json.dumps(
            {
                "machine": info,
                "code": code,
                "tol": tol,
                "max_error": COARSE_MAX_ERROR,
                "first_solve": first,
                "rows": rows,
                "targets": targets,
            },
            indent=1,
        )
        + "\n"
    )
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
