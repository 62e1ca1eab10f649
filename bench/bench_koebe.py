"""Koebe-sweep accelerations side by side (issue 24 item 1).

    python bench/bench_koebe.py [--gaps 0.1 0.03] [--tol 1e-8] [--out bench/results/koebe.json]
    python -m bench koebe [--quick]

Two unit squares ``gap`` apart in a 4 x 4 room, mirror images under x -> -x with the anchor on
the axis: the circle domain is mirror-symmetric, so its asymmetry (radii, centres) is a true
error of the map, an exact lower bound the error estimate must not undercut. Each case is
solved by ``confnav.solve(ws, tol, koebe_accel=...)`` with every acceleration
(:mod:`confnav.conformal.acceleration`): ``none`` (plain sweeps), ``sor`` (over-relaxed hole
maps), ``extrapolate`` (geometric-tail extrapolation of the sweep map, confirmed by the next
sweep). Reported per run: sweeps per mesh level (from the progress messages), Cauchy sums (GNK
products and map evaluations, counted) and how many of them ran through the FMM, GMRES
iterations (all levels, counted), CPU time (``time.process_time``,
less sensitive to the other processes on a shared machine than the wall time, also given),
the error estimate, boundary residual, tol_met, the asymmetry (honest when <= estimate) and
the distance of the centres and radii from the plain sweeps' map (both maps' estimates bound
it when both are honest).
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from bench_core import code_info, machine_info  # script mode: bench/ is on sys.path

import confnav
from confnav import ConformalMap, Workspace
from confnav.conformal import cauchy, circledomain, diskmap, gnk, meshing
from confnav.conformal.acceleration import KOEBE_ACCELS
from confnav.conformal.circular_map import METHODS
from confnav.maps.footprint import inflate
from confnav.scenes.workspaces import (
    default_workspace,
    mirror_asymmetry,
    mirror_squares,
    mixed_obstacles,
)

#: Solver designs (issue 24, measured side by side with ``--designs``): module settings.
#: ``before``: dense GNK matrices on every smooth grid up to gnk.DENSE_MAX_NODES and every mesh
#: level's sweeps started from the polygon (the solver up to a1fd614); ``fmm_smooth``: smooth
#: grids above gnk.SMOOTH_DENSE_MAX_NODES through FMM products; ``carry``: that and each
#: level's sweeps after the first started from the previous level's map (the default since
#: the first sweep's tangents are its curves', circledomain._consistent_tangents); ``corner``:
#: that and the first sweep's graded GNK solves right-preconditioned by their corner blocks
#: (gnk.CORNER_PRECONDITIONER, the default since it was measured against ``carry``). Those run
#: with the BLAS library's own thread count; ``*_blas1`` with one BLAS thread during the solve
#: (solver.SOLVE_BLAS_THREADS = 1, the default since ``corner_blas1`` was measured).
#: ``lean``: that and the expansions' power tables built per degree (``cauchy._powers``) and
#: the grid-size look-up limited to points within reach (``circledomain._local_grid_size``);
#: every other design runs the implementations before them (:func:`_cumprod_powers`,
#: :func:`_grid_size_all_points`). ``once``: that and each map's boundary residuals evaluated
#: once (``ConformalMap.boundary_residuals`` kept); the others evaluate them at every call
#: (:func:`_residuals_every_call`, as before). ``interleaved``: that and the dense GNK
#: matrices kept complex (gnk.DENSE_INTERLEAVED); the others copy their parts into two real
#: matrices (as before). ``second_sums``: that and the maps' derivatives in the sweeps from the
#: second-order sums of two charges (diskmap.DERIVATIVE_FROM_SECOND_SUMS; on by default since the
#: harmonic one-robot gradient's fix, :func:`fleet_step_rounding`). ``fine_grids``: that and
#: smooth-grid sizes rounded up to eighths of an octave (circledomain.GRID_STEPS = 8), not to
#: powers of two, from the rule for the band _tail reads (circledomain.TAIL_BAND; every other
#: design: GRID_STEPS = 1, TAIL_BAND = 1). ``graded``: that and the smooth grids'
#: Moebius grading strength searched between the listed ones (circledomain.GRADING_REFINE;
#: every other design: the list alone). ``modes2``: that and the extrapolation of two
#: geometric modes (circledomain.EXTRAPOLATE_MODES = 2, minimal polynomial extrapolation from
#: three grid-keeping sweeps; every other design: one mode, as before round 4), extrapolating
#: from plain contractions above 0.5 as one mode does; ``modes2_low``: that from contractions
#: above 0.2 (circledomain.RHO_EXTRAPOLATE_MIN_MODES). ``reuse`` (round 5): that and a
#: per-side refinement's re-solve taking the base level's first-sweep maps whose equations
#: are unchanged (solver.REFINE_REUSE); ``round5``: that and the ladder started higher for a
#: workspace with an obstacle tip sharper than 60 degrees (solver.START_BY_CORNERS);
#: ``round5s``: that and the re-solve's first sweep resumed from the base level's snapshot
#: (solver.REFINE_SNAPSHOTS); ``round6``: that and the mesh planner's feature distances taken
#: only to the features whose bounding boxes can be nearest (meshing.NEAR_FEATURES_FIRST;
#: every other design: the distances to every feature, as before; the same plans bit for bit)
#: and the dense GNK matrices scanned for coincident nodes only where np.unique finds some
#: (gnk.ZERO_SCAN_ALWAYS = False; every other design: every matrix scanned) and assembled by
#: blocks of rows (gnk.ASSEMBLY_BLOCK_BYTES; every other design: whole-matrix passes) -- the
#: same matrices bit for bit. ``round7``: that and the holes swept in the order of their
#: sharpest tips, bluntest first (solver.SWEEP_ORDER; every other design: 1..M);
#: ``round7b``: that and the dense GNK matrices' real and imaginary parts written into two
#: contiguous real matrices during the assembly (gnk.DENSE_SPLIT_ASSEMBLY; every other design:
#: the complex matrix kept, DENSE_INTERLEAVED); ``round7c``: that and smooth grids of up to
#: 2048 nodes solved with dense GNK matrices (gnk.SMOOTH_DENSE_MAX_NODES; every other design
#: with ``smooth_fmm``: 1024); ``round7d``: that and a per-side refinement's map taking the
#: denominator sums of its residual from the map it refines where its nodes are the same
#: (solver.REUSE_DENOMINATORS; every other design: summed afresh).
_LEAN = {"smooth_fmm": True, "carry": True, "corner": True, "blas1": True, "lean": True}


def _cumulative(
    base: dict[str, bool], *steps: tuple[str, dict[str, bool]]
) -> dict[str, dict[str, bool]]:
    """Designs that each add their flags to the one before (the first to ``base``)."""
    out: dict[str, dict[str, bool]] = {}
    cur = dict(base)
    for name, extra in steps:
        cur = {**cur, **extra}
        out[name] = cur
    return out


DESIGNS: dict[str, dict[str, bool]] = {
    "before": {"smooth_fmm": False, "carry": False, "corner": False, "blas1": False},
    "fmm_smooth": {"smooth_fmm": True, "carry": False, "corner": False, "blas1": False},
    "carry": {"smooth_fmm": True, "carry": True, "corner": False, "blas1": False},
    "corner": {"smooth_fmm": True, "carry": True, "corner": True, "blas1": False},
    "carry_blas1": {"smooth_fmm": True, "carry": True, "corner": False, "blas1": True},
    "corner_blas1": {"smooth_fmm": True, "carry": True, "corner": True, "blas1": True},
    "lean": _LEAN,
    # each design below is the one before it plus what its name says
    **_cumulative(
        _LEAN,
        ("once", {"once": True}),
        ("interleaved", {"interleaved": True}),
        ("second_sums", {"second_sums": True}),
        ("fine_grids", {"fine_grids": True}),
        ("graded", {"graded": True}),
        # round 4: the extrapolation removes two geometric modes
        # (circledomain.EXTRAPOLATE_MODES; every design above: one) ...
        ("modes2", {"modes2": True}),
        # ... from plain contractions above 0.2 instead of 0.5 (the default)
        ("modes2_low", {"rho_low": True}),
        # round 5: a per-side refinement's re-solve reuses the base level's unchanged
        # first-sweep maps (solver.REFINE_REUSE; every design above: off) ...
        ("reuse", {"reuse": True}),
        # ... and a workspace with an obstacle tip sharper than 60 degrees starts the ladder
        # higher (solver.START_BY_CORNERS; every design above: off): the default since round 5
        ("round5", {"start": True}),
        # ... and the re-solve's first sweep resumed from the base level's snapshot before the
        # first refined boundary (solver.REFINE_SNAPSHOTS; every design above: off)
        ("round5s", {"snapshots": True}),
        # ... and the mesh planner's feature distances pruned by bounding boxes
        ("round6", {"prune": True}),
        # round 7: the holes swept in the order of their change between the last two levels
        # (solver.SWEEP_ORDER; every design above: 1..M)
        ("round7", {"order": True}),
        # ... and the dense GNK matrices' parts written into two contiguous real matrices
        # during the assembly (gnk.DENSE_SPLIT_ASSEMBLY; every design above: kept complex)
        ("round7b", {"split": True}),
        # ... and smooth grids up to 2048 nodes solved densely (gnk.SMOOTH_DENSE_MAX_NODES;
        # every design above: 1024)
        ("round7c", {"smooth2048": True}),
        # ... and a refined map's residual taking its base's denominator sums where its nodes
        # are the base's (solver.REUSE_DENOMINATORS; every design above: summed afresh)
        ("round7d", {"denominators": True}),
    ),
}
#: The solver's own setting (restored after :func:`fleet_step_rounding`).
DERIVATIVE_DEFAULT = diskmap.DERIVATIVE_FROM_SECOND_SUMS


def _residuals_every_call(m: ConformalMap) -> Any:
    """``ConformalMap.boundary_residuals`` as it was before ``once``: evaluated at every call."""
    return m._boundary_residuals()


def _cumprod_powers(w: np.ndarray, p: int) -> np.ndarray:
    """``cauchy._powers`` as it was before ``lean``: cumprod along a (points, degrees) array."""
    W = np.empty((w.size, p + 1), np.complex128)
    W[:, 0] = 1.0
    W[:, 1:] = w[:, None]
    np.cumprod(W, axis=1, out=W)
    return W.T


def _grid_size_all_points(
    S: np.ndarray, dS: np.ndarray, others: np.ndarray, tail: float
) -> tuple[int, bool]:
    """``circledomain._local_grid_size`` as it was before ``lean``: every point looked up."""
    from scipy.spatial import cKDTree

    from confnav.conformal.circledomain import SMOOTH_MAX

    m = S.size
    if others.size == 0:
        return m, False
    tree = cKDTree(np.column_stack([S.real, S.imag]))
    d, i = tree.query(np.column_stack([others.real, others.imag]))
    h = np.abs(dS[i]) * 2 * np.pi / m
    ratio = float(np.min(d / np.maximum(h, 1e-300)))
    need_ratio = np.log(1 / tail) / np.pi
    if ratio >= need_ratio:
        return m, False
    want = int(2 ** np.ceil(np.log2(m * need_ratio / max(ratio, 1e-12))))
    return min(want, SMOOTH_MAX), want > SMOOTH_MAX


def use_design(name: str) -> None:
    """Set the module switches of a design (:data:`DESIGNS`)."""
    from confnav.conformal import solver

    d = DESIGNS[name]
    smooth = _SMOOTH_DEFAULT if d.get("smooth2048", False) else _SMOOTH_BEFORE_ROUND7
    gnk.SMOOTH_DENSE_MAX_NODES = smooth if d["smooth_fmm"] else gnk.DENSE_MAX_NODES
    solver.LEVEL_CARRY = d["carry"]
    gnk.CORNER_PRECONDITIONER = d["corner"]
    solver.SOLVE_BLAS_THREADS = 1 if d["blas1"] else None
    lean = d.get("lean", False)
    setattr(cauchy, "_powers", _POWERS if lean else _cumprod_powers)  # noqa: B010
    setattr(circledomain, "_local_grid_size", _GRID_SIZE if lean else _grid_size_all_points)  # noqa: B010
    once = d.get("once", False)
    gnk.DENSE_INTERLEAVED = d.get("interleaved", False)
    diskmap.DERIVATIVE_FROM_SECOND_SUMS = d.get("second_sums", False)
    circledomain.GRID_STEPS = _GRID_STEPS if d.get("fine_grids", False) else 1
    circledomain.TAIL_BAND = _TAIL_BAND if d.get("fine_grids", False) else 1.0
    circledomain.GRADING_REFINE = _GRADING_REFINE if d.get("graded", False) else 0
    circledomain.EXTRAPOLATE_MODES = _EXTRAPOLATE_MODES if d.get("modes2", False) else 1
    circledomain.RHO_EXTRAPOLATE_MIN_MODES = (
        _RHO_MIN_MODES if d.get("rho_low", False) else circledomain.RHO_EXTRAPOLATE_MIN
    )
    setattr(ConformalMap, "boundary_residuals", _RESIDUALS if once else _residuals_every_call)  # noqa: B010
    solver.REFINE_REUSE = d.get("reuse", False)
    solver.START_BY_CORNERS = d.get("start", False)
    solver.REFINE_SNAPSHOTS = d.get("snapshots", False)
    meshing.NEAR_FEATURES_FIRST = _NEAR_FEATURES if d.get("prune", False) else 1 << 30
    solver.SWEEP_ORDER = d.get("order", False)
    gnk.DENSE_SPLIT_ASSEMBLY = d.get("split", False)
    solver.REUSE_DENOMINATORS = d.get("denominators", False)
    gnk.ZERO_SCAN_ALWAYS = not d.get("prune", False)
    gnk.ASSEMBLY_BLOCK_BYTES = _BLOCK_BYTES if d.get("prune", False) else 0


_SMOOTH_DEFAULT = gnk.SMOOTH_DENSE_MAX_NODES
_SMOOTH_BEFORE_ROUND7 = 1024
_POWERS = cauchy._powers
_GRID_SIZE = circledomain._local_grid_size
_RESIDUALS = ConformalMap.boundary_residuals
_GRID_STEPS = circledomain.GRID_STEPS
_TAIL_BAND = circledomain.TAIL_BAND
_GRADING_REFINE = circledomain.GRADING_REFINE
_EXTRAPOLATE_MODES = circledomain.EXTRAPOLATE_MODES
_RHO_MIN_MODES = circledomain.RHO_EXTRAPOLATE_MIN_MODES
_NEAR_FEATURES = meshing.NEAR_FEATURES_FIRST
_BLOCK_BYTES = gnk.ASSEMBLY_BLOCK_BYTES


def asymmetry(m: ConformalMap) -> float:
    return mirror_asymmetry(m.centers, m.radii)


class _Counter:
    """Counts the calls of a module function (patched in place, restored by ``undo``)."""

    def __init__(self, module: Any, name: str) -> None:
        self.module, self.name = module, name
        self.orig = getattr(module, name)
        self.calls = 0
        self.iterations = 0  # GMRES iterations, for solve_gnk
        setattr(module, name, self)

    def __call__(self, *args: Any, **kw: Any) -> Any:
        self.calls += 1
        out = self.orig(*args, **kw)
        self.iterations += int(getattr(out, "iterations", 0))
        return out

    def undo(self) -> None:
        setattr(self.module, self.name, self.orig)


def scene(name: str) -> Workspace:
    """The asymmetric cases: the default workspace, it shrunk for a 0.2 m robot,
    ``mixed_obstacles(50, seed=0)`` and a 2 x 1 m room with a square pillar."""
    if name == "default":
        return default_workspace()
    if name == "shrunk":
        return inflate(default_workspace(), 0.2)
    if name == "mixed50":
        return mixed_obstacles(50, seed=0)
    if name == "room":  # the carried levels' regression case (tests/test_level_carry.py)
        return Workspace(
            [(0, 0), (2, 0), (2, 1), (0, 1)], [[(0.8, 0.3), (1.2, 0.3), (1.2, 0.7), (0.8, 0.7)]]
        )
    raise ValueError(f"unknown scene {name!r}")


def run_one(
    gap: float | str,
    tol: float,
    accel: str,
    method: str = "koebe",
    nodes_per_side: int | None = None,
    design: str = "carry",
) -> tuple[dict[str, Any], ConformalMap]:
    use_design(design)
    levels: list[list[Any]] = []  # [label, sweeps]

    def progress(msg: str) -> None:
        if msg.startswith("solving with") or msg.startswith("refining"):
            levels.append([msg.split(" at ")[0].replace("solving with ", ""), 0])
        elif "nodes/side: sweep" in msg and levels:
            # with method="nasser" the Newton steps are reported as sweeps after the sweeps
            levels[-1][1] = int(msg.split("sweep ")[1].split(",")[0])

    counters = [
        _Counter(cauchy, "_fmm"),  # FMM calls (above cauchy.FMM_THRESHOLD interactions)
        _Counter(gnk, "cauchy_self"),  # Cauchy sums of the GNK products (GMRES)
        _Counter(diskmap, "cauchy_sums"),  # Cauchy sums evaluating the maps
        _Counter(diskmap, "solve_gnk"),  # GNK solves and their GMRES iterations
    ]
    load = os.getloadavg()[0]
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", confnav.AccuracyWarning)
            ws = mirror_squares(gap) if isinstance(gap, float) else scene(gap)
            m = confnav.solve(
                ws,
                tol=tol,
                koebe_accel=accel,
                progress=progress,
                method=method,
                nodes_per_side=nodes_per_side,
            )
    finally:
        for c in counters:
            c.undo()
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    d = m.diagnostics
    row = {
        "gap": gap,
        "tol": tol,
        "accel": accel,
        "method": method,
        "design": design,
        "nodes_per_side": nodes_per_side,
        "cpu_s": cpu,
        "wall_s": wall,
        "load1": load,
        "levels": [{"level": lv, "sweeps": s} for lv, s in levels],
        "sweeps_total": int(sum(s for _, s in levels)),
        "fmm_sums": counters[0].calls,
        "cauchy_sums": counters[1].calls + counters[2].calls,
        "gmres_iterations_final_level": d.gmres_iterations,
        "gnk_solves": counters[3].calls,
        "gmres_iterations": counters[3].iterations,
        "error_estimate": d.error_estimate,
        "iteration_error": d.iteration_error,
        "boundary_residual": d.boundary_residual,
        "tol_met": d.tol_met,
    }
    if isinstance(gap, float):
        row["asymmetry"] = asymmetry(m)
        row["honest"] = bool(asymmetry(m) <= max(d.error_estimate, 1e-15))
    return row, m


def _line(r: dict[str, Any]) -> str:
    sw = " ".join(str(x["sweeps"]) for x in r["levels"])
    case = f"gap {r['gap']:g}" if isinstance(r["gap"], float) else str(r["gap"])
    return (
        f"  {case:<9} {r.get('design', ''):<10} {r.get('method', 'koebe'):<6} {r['accel']:<11} "
        f"sweeps/level [{sw}] "
        f"total {r['sweeps_total']:4d}"
        f"  GMRES {r['gmres_iterations']:5d}  FMM {r['fmm_sums']:5d}  CPU {r['cpu_s']:6.1f} s "
        f"(wall {r['wall_s']:6.1f}, load {r['load1']:.1f})  est {r['error_estimate']:.1e} "
        f"res {r['boundary_residual']:.1e} "
        + (
            f"asym {r['asymmetry']:.1e} {'honest' if r['honest'] else 'CLAIMS TOO MUCH'} "
            if "asymmetry" in r
            else ""
        )
        + f"tol_met {r['tol_met']}  vs plain {r.get('distance_from_plain', 0.0):.1e}"
    )


#: ``--corner-study``: (scene, nodes per side, tol) whose first sweep's graded GNK solves are
#: re-solved with corner blocks of several sizes (fractions of each side; None: no blocks).
CORNER_CASES = (("default", 180, 1e-10), ("mixed50", 120, 1e-8))
CORNER_FRACTIONS = (None, 0.5, 0.25, 0.125)


def _first_sweep_solves(name: str, nodes: int, tol: float) -> list[tuple[Any, ...]]:
    """The arguments of the first sweep's GNK solves of one cold level, with their meshes."""
    from confnav.conformal import circledomain, solver

    calls: list[tuple[Any, ...]] = []
    state: dict[str, Any] = {}
    real_solve = diskmap.solve_gnk  # type: ignore[attr-defined]
    real_own, real_sweep = circledomain._own_map, circledomain._sweep

    def own(b: Any, alpha: complex, nm: str, mesh: Any, *a: Any) -> Any:
        state["mesh"] = mesh
        return real_own(b, alpha, nm, mesh, *a)

    def record(*a: Any, **kw: Any) -> Any:
        calls.append((a, kw, state["mesh"]))
        return real_solve(*a, **kw)

    def sweep(it: Any, k: int, *a: Any) -> Any:
        if k > 1:
            raise StopIteration  # the first sweep is all the study needs
        return real_sweep(it, k, *a)

    setattr(diskmap, "solve_gnk", record)  # noqa: B010
    setattr(circledomain, "_own_map", own)  # noqa: B010
    setattr(circledomain, "_sweep", sweep)  # noqa: B010
    try:
        solver._solve_level(scene(name), nodes, tol, None)
    except StopIteration:
        pass
    finally:
        setattr(diskmap, "solve_gnk", real_solve)  # noqa: B010
        setattr(circledomain, "_own_map", real_own)  # noqa: B010
        setattr(circledomain, "_sweep", real_sweep)  # noqa: B010
    return calls


def corner_study(out: Path) -> int:
    """The first sweep's graded GNK solves of one cold mesh level, recorded, then solved again
    with each block size of the corner preconditioner (``gnk._CornerBlocks``, blocks of the
    nodes within a fraction of each side from its vertices): GMRES iterations and CPU seconds
    (one BLAS thread, as ``confnav.solve`` runs), and the largest difference of mu from the
    unpreconditioned solution."""
    from threadpoolctl import threadpool_limits

    info, code = machine_info(), code_info()
    rows: list[dict[str, Any]] = []
    for name, nodes, tol in CORNER_CASES:
        calls = _first_sweep_solves(name, nodes, tol)
        plain_mu: list[Any] = []
        for frac in CORNER_FRACTIONS:
            its, diff = 0, 0.0
            c0 = time.process_time()
            with threadpool_limits(limits=1, user_api="blas"):
                for i, (a, kw, mesh) in enumerate(calls):
                    args = list(a)
                    args[7] = None if frac is None else mesh.corner_blocks(frac)
                    sol = gnk.solve_gnk(*args, **kw)
                    its += sol.iterations
                    if frac is None:
                        plain_mu.append(sol.mu)
                    else:
                        diff = max(diff, float(np.max(np.abs(sol.mu - plain_mu[i]))))
            rows.append(
                {
                    "scene": name,
                    "nodes_per_side": nodes,
                    "tol": tol,
                    "solves": len(calls),
                    "nodes": int(sum(c[0][0].size for c in calls)),
                    "fraction": frac,
                    "gmres_iterations": its,
                    "cpu_s": time.process_time() - c0,
                    "max_mu_difference": diff,
                    "load1": os.getloadavg()[0],
                }
            )
            print(
                f"  {name} {nodes}/side: blocks {frac}: GMRES {its}, CPU "
                f"{rows[-1]['cpu_s']:.2f} s, mu within {diff:.1e}",
                flush=True,
            )
    info["loadavg_end"] = list(os.getloadavg())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": info, "code": code, "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


def fleet_step_rounding(out: Path) -> int:
    """``--fleet-step``: the harmonic fleet step against each robot's own step
    (tests/test_fleet_step.py's case: the default workspace at 1e-8, 60 robots, 12 goals) on
    the map solved with and without ``diskmap.DERIVATIVE_FROM_SECOND_SUMS``; the relative
    differences of the commands ``u`` (median: the test's bulk bound, largest); and where the
    two paths differ: the Green's function parts of the stacked series against one robot's,
    and the gradient formula in Python's complex arithmetic against numpy's on the same parts
    (medians)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    import math

    import test_fleet_step as tfs  # the test's own fleet and poses

    from confnav.navigation.fleet import fleet_step
    from confnav.navigation.harmonic import stacked_parts

    info, code = machine_info(), code_info()
    rows = []
    for flag in (True, False):
        diskmap.DERIVATIVE_FROM_SECOND_SUMS = flag
        m = confnav.solve(default_workspace(), tol=1e-8).for_navigation()
        ctrls, z = tfs._fleet(m, navfn="harmonic")
        zz = np.where(np.isfinite(z), z, 0j)
        w, dw = m.T_and_dT(zz)
        c = ctrls[0].clearance(zz)
        out_f = fleet_step(ctrls, z, w, dw, c)
        u1 = np.array(
            [
                ctl.from_map_values(z[i : i + 1], w[i : i + 1], dw[i : i + 1], c[i : i + 1]).u[0]
                for i, ctl in enumerate(ctrls)
            ]
        )
        ok = np.isfinite(u1) & (u1 != 0)
        rel = np.abs(out_f.u[ok] - u1[ok]) / np.abs(u1[ok])
        # where the two paths differ: the Green's function parts (G, h, grad H) of the
        # stacked series against one robot's, and the gradient formula in Python's complex
        # arithmetic (as value_and_gradient1 had it) against numpy's, on the same parts
        idx = np.flatnonzero(ok)
        fns = [ctrls[i].navfn for i in idx]
        wi = w[idx]
        big_g, h, gh = stacked_parts([f.green for f in fns], wi)
        one = [f.green._parts1(complex(x)) for f, x in zip(fns, wi, strict=True)]
        h1 = np.array([p[1] for p in one])
        gh1 = np.array([p[2] for p in one])
        parts_rel = np.concatenate(
            [
                np.abs(big_g - [p[0] for p in one]) / np.abs([p[0] for p in one]),
                np.abs(h - h1) / np.abs(h1),
                np.abs(gh - gh1) / np.abs(gh1),
            ]
        )
        wd = np.array([f.goal for f in fns])
        e = wi - wd
        g = (e * e.conjugate()).real
        q = 1.0 - np.conj(wd) * wi
        grad_np = 2.0 * np.exp(-2.0 * h1) * (e * np.conj((1.0 - np.abs(wd) ** 2) / q) - g * gh1)
        grad_py = np.array(
            [
                2.0
                * math.exp(-2.0 * float(hh))
                * (
                    complex(ee) * ((1.0 - abs(complex(d)) ** 2) / complex(qq)).conjugate()
                    - float(gg) * complex(gx)
                )
                for hh, ee, d, qq, gg, gx in zip(h1, e, wd, q, g, gh1, strict=True)
            ]
        )
        rows.append(
            {
                "second_sums": flag,
                "median_rel": float(np.median(rel)),
                "max_rel": float(np.max(rel)),
                "robots": int(ok.sum()),
                "parts_median_rel": float(np.median(parts_rel)),
                "python_formula_median_rel": float(
                    np.median(np.abs(grad_py - grad_np) / np.abs(grad_np))
                ),
            }
        )
        print(
            f"second sums {flag}: median {rows[-1]['median_rel']:.2e}, "
            f"largest {rows[-1]['max_rel']:.2e} over {rows[-1]['robots']} robots",
            flush=True,
        )
    diskmap.DERIVATIVE_FROM_SECOND_SUMS = DERIVATIVE_DEFAULT
    out.write_text(
        json.dumps(
            {
                "what": fleet_step_rounding.__doc__,
                "test_bound_median": tfs.RTOL_BULK,
                "machine": info,
                "code": code,
                "rows": rows,
            },
            indent=1,
        )
        + "\n"
    )
    print(f"wrote {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaps", type=float, nargs="*", default=[0.1, 0.03])
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument(
        "--scenes",
        nargs="*",
        default=[],
        choices=["default", "shrunk", "mixed50", "room"],
        help="asymmetric cases too: default workspace, it shrunk by 0.2 m, 50 mixed obstacles, "
        "a 2 x 1 m room with a pillar",
    )
    ap.add_argument(
        "--case-tol",
        nargs="*",
        default=[],
        metavar="CASE=TOL",
        help="another tol for a case (e.g. default=1e-10), the rest at --tol",
    )
    ap.add_argument("--accels", nargs="+", default=list(KOEBE_ACCELS))
    ap.add_argument(
        "--methods",
        nargs="+",
        default=["koebe"],
        choices=list(METHODS),
        help="iteration: Koebe sweeps, or sweeps then Newton steps (confnav.conformal."
        "circular_map); 'nasser' runs with accel 'none' only",
    )
    ap.add_argument(
        "--nodes-per-side",
        type=int,
        default=None,
        help="cap: a fixed mesh (three levels up to this) instead of refining to tol",
    )
    ap.add_argument(
        "--designs",
        nargs="+",
        default=["carry"],
        choices=list(DESIGNS),
        help="solver designs side by side (DESIGNS); the first is the reference for distances",
    )
    ap.add_argument("--append", action="store_true", help="add the rows to those already in --out")
    ap.add_argument("--quick", action="store_true", help="gap 0.1 only")
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "results" / "koebe.json"
    )
    ap.add_argument(
        "--corner-study",
        action="store_true",
        help="only the corner preconditioner's block sizes on the first sweep's solves",
    )
    ap.add_argument(
        "--fleet-step",
        action="store_true",
        help="only the fleet step against each robot's own step, second sums on and off",
    )
    a = ap.parse_args(argv)
    if a.fleet_step:
        return fleet_step_rounding(
            a.out if a.out.name != "koebe.json" else a.out.with_name("second_sums_fleet_step.json")
        )
    if a.corner_study:
        return corner_study(
            a.out if a.out.name != "koebe.json" else a.out.with_name("koebe_corner_blocks.json")
        )
    gaps = [0.1] if a.quick else a.gaps
    info, code = machine_info(), code_info()
    print(
        f"Koebe accelerations, commit {code['commit'][:12]}, load {os.getloadavg()[0]:.2f}, "
        f"tol {a.tol:g}",
        flush=True,
    )
    # untimed warm-up: the first solve of a process pays one-time costs (imports, caches)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        confnav.solve(mirror_squares(0.1), tol=1e-4)
    rows = []
    cases: list[float | str] = [*gaps, *a.scenes]
    case_tol = {k: float(v) for k, v in (c.split("=") for c in a.case_tol)}
    for gap in cases:
        tol = case_tol.get(str(gap), a.tol)
        plain: ConformalMap | None = None
        runs = [(des, meth, acc) for des in a.designs for meth in a.methods for acc in a.accels]
        runs = [(des, meth, acc) for des, meth, acc in runs if meth == "koebe" or acc == "none"]
        for i, (des, meth, acc) in enumerate(runs):
            c0 = time.process_time()
            try:
                r, m = run_one(gap, tol, acc, meth, a.nodes_per_side, des)
            except confnav.ConfnavError as exc:  # a refused map is a result too
                r = {
                    "gap": gap,
                    "tol": tol,
                    "accel": acc,
                    "method": meth,
                    "design": des,
                    "cpu_s": time.process_time() - c0,
                    "load1": os.getloadavg()[0],
                    "error": f"{type(exc).__name__}: {exc}",
                }
                rows.append(r)
                print(f"  {gap} {meth} {acc}: {r['error']} (CPU {r['cpu_s']:.1f} s)", flush=True)
                continue
            if i == 0:  # the reference run of the case (first design, method and accel)
                plain = m
            elif plain is not None:
                r["distance_from_plain"] = float(
                    max(
                        np.max(np.abs(m.radii - plain.radii)),
                        np.max(np.abs(m.centers - plain.centers)),
                    )
                )
                r["distance_bounded"] = bool(
                    r["distance_from_plain"]
                    <= m.diagnostics.error_estimate + plain.diagnostics.error_estimate
                )
            rows.append(r)
            print(_line(r), flush=True)
    info["loadavg_end"] = list(os.getloadavg())
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if a.append and a.out.exists():
        rows = json.loads(a.out.read_text())["rows"] + rows
    a.out.write_text(json.dumps({"machine": info, "code": code, "rows": rows}, indent=1) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
