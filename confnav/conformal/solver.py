"""``solve(workspace, tol)``: the conformal navigation transformation with an error estimate.

The node count is chosen by refinement, not by a magic constant: the Koebe-type iteration is run
on graded meshes of increasing size (nodes per side from :data:`LEVELS`), and the change of the
circle domain (centres and radii) between consecutive levels gives the discretisation error of
the finer one. With grading exponent p the error decays like n^-p (DESIGN.md sec. 2), so each
step of ``LEVELS`` (x1.5) cuts it by about 7x.

The error estimate covers every error source (issue 8), each measured on its own:

* discretisation: the level differences above, extrapolated;
* iteration: the Koebe iteration runs until its remaining error, extrapolated from the
  observed contraction, is below ``tol / 10``; a stalled or unfinished iteration is reported
  (``iteration_converged = False``), never taken as converged;
* a-posteriori: :meth:`ConformalMap.boundary_residual` -- T at points between the nodes on
  every side (midpoints, and points graded towards every corner) must land on its circle;
* size caps: a smooth grid held at its cap adds its Fourier tail; a level that would need more
  nodes than the mesh allows (a gap too narrow) ends the refinement and is listed in ``caps``.

``tol_met`` is true only if all are within ``tol``. A map that misses ``tol`` is returned with
``tol_met = False`` and an :class:`AccuracyWarning`; one whose estimate exceeds
:data:`UNUSABLE_ERROR` (or the caller's ``max_error``) raises
:class:`~confnav.errors.SolverError` -- a silently wrong map is never returned.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable

import numpy as np

from confnav.conformal.boundary import BoundaryMesh, graded_polygon, resample
from confnav.conformal.circledomain import CircleDomainResult, koebe_iteration
from confnav.conformal.cmap import ConformalMap, SolveReport
from confnav.conformal.gnk import gmres_rtol
from confnav.conformal.meshing import plan_boundaries
from confnav.errors import (
    ConvergenceError,
    GapError,
    SolverError,
    UnresolvedCrowdingError,
    fmt_point,
)
from confnav.geometry import Workspace, interior_point
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

log = logging.getLogger(__name__)

#: Mesh levels: nodes per side at the workspace's sharpest corner, coarse to fine (x1.5 steps).
#: Above 256 the nodes next to the vertices of the p = 7 mesh fall within rounding of them; they
#: are dropped as sources (confnav.conformal.gnk.alive_nodes), and the finer levels are needed by
#: needle-like tips: a 10-degree tip reaches 1e-6 only at 576 (measured: 3.4e-8, residual
#: 6.8e-9, mirror asymmetry 2e-15; at 256 the residual is 1.1e-4).
LEVELS: tuple[int, ...] = (24, 36, 54, 80, 120, 180, 256, 384, 576)
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
#: Share of ``tol`` left to the Koebe iteration's remaining error (the rest: discretisation).
ITERATION_SHARE = 0.1
#: Start the first sweep's GNK solves of a level from the previous level's solutions, resampled
#: onto the new graded meshes (issue 12: "reuse of the previous level's solution as the GMRES
#: start"). Measured on the default workspace, 180 -> 256 nodes per side: 185 -> 144 GMRES
#: iterations of those solves (the spline transfer errs by 1e-6..5e-5 relative, limited by
#: the corners, and GMRES on the second-kind operator gains about a digit per 4-5 iterations);
#: the map is the same to the GMRES tolerance (tests/test_solver_warm_start.py).
WARM_START = True


class AccuracyWarning(UserWarning):
    """The map's estimated error is above the requested tolerance."""


#: A level's graded meshes and its first sweep's GNK solutions (the next level's first guess).
_Warm = tuple[list[BoundaryMesh], list[FloatArray | None]]


def _solve_level(
    ws: Workspace,
    nodes_per_side: int,
    tol: float,
    progress: Callable[[str], None] | None,
    warm: _Warm | None = None,
) -> tuple[CircleDomainResult, list[BoundaryMesh]]:
    plans = plan_boundaries(ws, nodes_per_side, tol)
    meshes = [graded_polygon(plans[0].vertices, plans[0].nodes)] + [
        graded_polygon(p.vertices, p.nodes).reversed() for p in plans[1:]
    ]
    holes = [interior_point(o) for o in ws.obstacles]
    guess: list[FloatArray | None] | None = None
    if warm is not None and WARM_START:
        guess = [
            None if mu is None else resample(old, mu, new)
            for old, mu, new in zip(warm[0], warm[1], meshes, strict=True)
        ]

    def _p(sweep: int, change: float) -> None:
        if progress is not None:
            progress(f"  {nodes_per_side} nodes/side: sweep {sweep}, change {change:.1e}")

    res = koebe_iteration(
        meshes,
        holes,
        ws.anchor,
        tol=ITERATION_SHARE * tol,
        progress=_p,
        gmres_tol=gmres_rtol(tol),
        first_guess=guess,
    )
    return res, meshes


def _make_map(
    ws: Workspace,
    level: tuple[CircleDomainResult, list[ComplexArray], list[ComplexArray], int, float],
    tol: float,
    caps: list[str],
    refinements: list[dict[str, float]],
    t0: float,
) -> ConformalMap:
    """The map of one solved level with its full error budget (residual computed here)."""
    res, eta, deta, ns, disc = level
    diag = SolveReport(
        tol=tol,
        error_estimate=float("inf"),
        tol_met=False,
        sweeps=res.sweeps,
        history=res.history,
        nodes=[e.size for e in eta],
        nodes_per_side=ns,
        circularity=res.circularity,
        gmres_iterations=res.gmres_iterations,
        wall_time=0.0,
        discretisation_error=disc,
        iteration_error=res.iteration_error,
        iteration_converged=res.converged,
        boundary_residual=float("inf"),
        resolution_error=res.resolution_error,
        caps=list(caps),
        refinements=list(refinements),
    )
    m = ConformalMap(ws, eta, deta, res.W, res.dW, res.centers, res.radii, diag)
    m.diagnostics = diag.with_residual(m.boundary_residual())
    m.diagnostics.wall_time = time.perf_counter() - t0
    return m


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
    max_error: float = UNUSABLE_ERROR,
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
    max_error
        Largest estimated error of a map that is returned (with ``tol_met`` saying whether it
        meets ``tol``) rather than refused. The default, :data:`UNUSABLE_ERROR`, is for callers
        whose safety rests on the map; a caller that keeps its robots out of the walls on the
        exact geometry (the controller's safety filter, docs/NAVIGATION.md) may accept a
        coarse map (e.g. ``tol=1e-3, max_error=1e-2``): the certificate stays honest, the map
        then only costs path quality (docs/SERVICES.md, progressive maps).

    Raises
    ------
    SolverError, CrowdingError, ConvergenceError
        The map cannot be computed to a usable accuracy.
    """
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise SolverError(f"tol must be in (0, 1), got {tol}")
    if not (np.isfinite(max_error) and max_error > 0):
        raise SolverError(f"max_error must be positive and finite, got {max_error}")
    t0 = time.perf_counter()
    if nodes_per_side is not None:
        if nodes_per_side < 8:
            raise SolverError("nodes_per_side must be at least 8")
        levels = [max(8, round(nodes_per_side / 1.5)), nodes_per_side]
    else:
        start = 0 if tol >= 1e-7 else (1 if tol >= 1e-9 else 3)
        levels = list(LEVELS[start:])
    refinements: list[dict[str, float]] = []
    caps: list[str] = []
    prev: CircleDomainResult | None = None
    prev_ns = 0
    failed: ConvergenceError | None = None
    prev_diff: float | None = None
    best: tuple[CircleDomainResult, list[ComplexArray], list[ComplexArray], int, float] | None
    best = None
    cmap: ConformalMap | None = None
    solved = 0  # levels solved (a skipped level does not count)
    warm: _Warm | None = None
    for ns in levels:
        if progress is not None:
            progress(f"solving with {ns} nodes per side at the sharpest corners")
        try:
            res, meshes = _solve_level(workspace, ns, tol, progress, warm)
        except GapError as exc:
            if best is None:
                raise
            caps.append(f"node limit at {ns} nodes per side: {exc}")
            log.warning("refinement to level %d stopped (%s); keeping level %d", ns, exc, best[3])
            break
        except ConvergenceError as exc:
            if isinstance(exc, UnresolvedCrowdingError) and isinstance(
                failed, UnresolvedCrowdingError
            ):
                raise  # two levels alike: refining does not resolve crowding
            if best is None:
                # no usable pair of levels yet: a coarse level whose discretisation is unstable
                # (e.g. a needle-like tip, see confnav.conformal.meshing) is skipped, not fatal
                failed = exc
                log.warning("level %d failed (%s); refining", ns, exc)
                continue
            log.warning("refinement to level %d failed (%s); keeping level %d", ns, exc, best[3])
            break
        warm = (meshes, res.first_mu)  # the next level's first guesses
        eta, deta = [m.eta for m in meshes], [m.deta for m in meshes]
        if prev is not None:
            diff = _difference(res, prev)
            # error of the finer solve ~ diff * rho/(1 - rho), rho = error ratio per level:
            # the slower of the assumed order and the observed contraction (Aitken).
            rho = (prev_ns / ns) ** ASSUMED_ORDER
            if prev_diff is not None and prev_diff > 0:
                rho = max(rho, diff / prev_diff)
            rho = min(rho, 0.9)
            est = diff * rho / (1 - rho)
            refinements.append(
                {
                    "nodes_per_side": ns,
                    "difference": diff,
                    "error_estimate": est,
                    "iteration_error": res.iteration_error,
                    "wall_time": res.wall_time,
                }
            )
            best = (res, eta, deta, ns, est)
            cmap = None
            prev_diff = diff
            if est <= tol and solved + 1 >= MIN_LEVELS:
                # the discretisation is fine; the a-posteriori residual must agree, else refine
                cmap = _make_map(workspace, best, tol, caps, refinements, t0)
                # kept per level: a residual above tol at a level whose discretisation estimate
                # is below it says what forced the next (costlier) level
                refinements[-1]["boundary_residual"] = cmap.diagnostics.boundary_residual
                if cmap.diagnostics.boundary_residual <= tol:
                    break
        prev, prev_ns = res, ns
        solved += 1
    if best is None:
        if failed is not None:
            raise failed
        raise SolverError("refinement needs at least two mesh levels")
    if cmap is None:
        cmap = _make_map(workspace, best, tol, caps, refinements, t0)
    diag = cmap.diagnostics
    if diag.error_estimate > max_error:
        where = ""
        if diag.boundary_residual >= diag.error_estimate:  # name the place: a user can see it
            z, name = cmap.worst_boundary_point()
            where = f"; largest on {name} at {fmt_point(z)}"
        raise SolverError(
            f"the map's estimated error {diag.error_estimate:.1e} is too large to navigate "
            f"with (even at {diag.nodes_per_side} nodes per side; discretisation "
            f"{diag.discretisation_error:.1e}, iteration {diag.iteration_error:.1e}, "
            f"boundary residual {diag.boundary_residual:.1e}{where})"
        )
    if not diag.tol_met:
        why = [
            f"{name} {val:.1e}"
            for name, val in (
                ("discretisation", diag.discretisation_error),
                ("iteration", diag.iteration_error),
                ("boundary residual", diag.boundary_residual),
                ("smooth-grid resolution", diag.resolution_error),
            )
            if val > tol
        ]
        if not diag.iteration_converged:
            why.append("the Koebe iteration did not converge (stalled or sweep limit)")
        why += diag.caps
        warnings.warn(
            f"conformal map: estimated error {diag.error_estimate:.1e}, tol {tol:.1e} not met "
            f"(finest mesh {diag.nodes_per_side} nodes per side): " + "; ".join(why),
            AccuracyWarning,
            stacklevel=2,
        )
    return cmap


__all__ = ["LEVELS", "AccuracyWarning", "solve"]
