"""``solve(workspace, tol)``: the conformal navigation transformation with an error estimate.

The node count is chosen by refinement, not by a magic constant: the Koebe-type iteration is run
on graded meshes of increasing size (nodes per side from :data:`LEVELS`), and the change of the
circle domain (centres and radii) between two consecutive levels is the error estimate of the
finer one. Refinement stops when the estimate is below ``tol`` or the finest level is reached.
With grading exponent p = 5 the error decays like n^-5 (DESIGN.md sec. 2), so each step of
``LEVELS`` (x1.5) cuts the error by about 7x and the estimate is an upper bound in practice.

A map whose estimate misses ``tol`` is returned with ``diagnostics.tol_met = False`` and an
:class:`AccuracyWarning`; one whose estimate exceeds :data:`UNUSABLE_ERROR` raises
:class:`~confnav.errors.SolverError` -- a silently wrong map is never returned.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable

import numpy as np

from confnav.boundary import graded_polygon
from confnav.circledomain import CircleDomainResult, koebe_iteration
from confnav.cmap import ConformalMap, SolveDiagnostics
from confnav.errors import ConvergenceError, SolverError
from confnav.geometry import ComplexArray, Workspace, interior_point
from confnav.meshing import plan_boundaries

log = logging.getLogger(__name__)

#: Mesh levels: nodes per side at the workspace's sharpest corner, coarse to fine (x1.5 steps,
#: 256 is the finest at which the p = 7 graded mesh stays clear of rounding at the vertices).
LEVELS: tuple[int, ...] = (24, 36, 54, 80, 120, 180, 256)
#: Error decay assumed between two levels (n^-5 .. n^-11 measured on the default workspace);
#: the estimate uses the slower of this and the contraction observed over the last three
#: levels, so it errs on the safe side. A two-level estimate was measured to under-estimate a
#: thin triangle's error 5x (pre-asymptotic convergence at its 14-degree tip; hypothesis
#: test), hence three levels at least.
ASSUMED_ORDER = 5.0
#: Levels solved before an estimate may stop the refinement.
MIN_LEVELS = 3
#: An estimated error above this makes the map useless for navigation: raise instead.
UNUSABLE_ERROR = 1e-4


class AccuracyWarning(UserWarning):
    """The map's estimated error is above the requested tolerance."""


def _solve_level(
    ws: Workspace,
    nodes_per_side: int,
    tol: float,
    progress: Callable[[str], None] | None,
) -> tuple[CircleDomainResult, list[ComplexArray], list[ComplexArray]]:
    plans = plan_boundaries(ws, nodes_per_side, tol)
    meshes = [graded_polygon(plans[0].vertices, plans[0].nodes)] + [
        graded_polygon(p.vertices, p.nodes).reversed() for p in plans[1:]
    ]
    holes = [interior_point(o) for o in ws.obstacles]

    def _p(sweep: int, change: float) -> None:
        if progress is not None:
            progress(f"  {nodes_per_side} nodes/side: sweep {sweep}, change {change:.1e}")

    res = koebe_iteration(meshes, holes, ws.anchor, tol=0.1 * tol, progress=_p)
    return res, [m.eta for m in meshes], [m.deta for m in meshes]


def _difference(a: CircleDomainResult, b: CircleDomainResult) -> float:
    if a.centers.size == 0:
        return float(abs(a.derivative_at_anchor - b.derivative_at_anchor))
    return float(max(np.max(np.abs(a.centers - b.centers)), np.max(np.abs(a.radii - b.radii))))


def solve(
    workspace: Workspace,
    tol: float = 1e-10,
    *,
    nodes_per_side: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> ConformalMap:
    """Compute the conformal map of ``workspace`` onto a circle domain.

    Parameters
    ----------
    workspace
        The validated workspace; its anchor is sent to 0.
    tol
        Target accuracy of the circle domain (centres and radii, absolute, unit-disk scale).
    nodes_per_side
        Fix the mesh instead of refining (the error estimate then uses the next coarser level).
    progress
        Called with one-line progress messages.

    Raises
    ------
    SolverError, CrowdingError, ConvergenceError
        The map cannot be computed to a usable accuracy.
    """
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise SolverError(f"tol must be in (0, 1), got {tol}")
    t0 = time.perf_counter()
    if nodes_per_side is not None:
        if nodes_per_side < 8:
            raise SolverError("nodes_per_side must be at least 8")
        levels = [max(8, round(nodes_per_side / 1.5)), nodes_per_side]
    else:
        start = 0 if tol >= 1e-7 else (1 if tol >= 1e-9 else 3)
        levels = list(LEVELS[start:])
    refinements: list[dict[str, float]] = []
    prev: CircleDomainResult | None = None
    prev_diff: float | None = None
    best: tuple[CircleDomainResult, list[ComplexArray], list[ComplexArray], int, float] | None
    best = None
    for i, ns in enumerate(levels):
        if progress is not None:
            progress(f"solving with {ns} nodes per side at the sharpest corners")
        try:
            res, eta, deta = _solve_level(workspace, ns, tol, progress)
        except ConvergenceError as exc:
            if best is None:
                raise
            log.warning("refinement to level %d failed (%s); keeping level %d", ns, exc, best[3])
            break
        if prev is not None:
            diff = _difference(res, prev)
            # error of the finer solve ~ diff * rho/(1 - rho), rho = error ratio per level:
            # the slower of the assumed order and the observed contraction (Aitken).
            rho = (levels[i - 1] / ns) ** ASSUMED_ORDER
            if prev_diff is not None and prev_diff > 0:
                rho = max(rho, diff / prev_diff)
            rho = min(rho, 0.9)
            est = diff * rho / (1 - rho)
            refinements.append(
                {
                    "nodes_per_side": ns,
                    "difference": diff,
                    "error_estimate": est,
                    "wall_time": res.wall_time,
                }
            )
            best = (res, eta, deta, ns, est)
            prev_diff = diff
            if est <= tol and i + 1 >= MIN_LEVELS:
                break
        prev = res
    if best is None:
        raise SolverError("refinement needs at least two mesh levels")
    res, eta, deta, ns, est = best
    if est > UNUSABLE_ERROR:
        raise SolverError(
            f"the map's estimated error {est:.1e} is too large to navigate with "
            f"(even at {ns} nodes per side)"
        )
    diag = SolveDiagnostics(
        tol=tol,
        error_estimate=est,
        tol_met=est <= tol,
        sweeps=res.sweeps,
        history=res.history,
        nodes=[e.size for e in eta],
        nodes_per_side=ns,
        circularity=res.circularity,
        gmres_iterations=res.gmres_iterations,
        wall_time=time.perf_counter() - t0,
        refinements=refinements,
    )
    if not diag.tol_met:
        warnings.warn(
            f"conformal map: estimated error {est:.1e} is above tol {tol:.1e} "
            f"(finest mesh {ns} nodes per side)",
            AccuracyWarning,
            stacklevel=2,
        )
    return ConformalMap(workspace, eta, deta, res.W, res.dW, res.centers, res.radii, diag)


__all__ = ["LEVELS", "AccuracyWarning", "solve"]
