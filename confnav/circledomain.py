"""Koebe-type iteration: a multiply connected domain onto a circle domain.

State: the images ``W_j`` of the boundary nodes (j = 0 outer, 1..M holes), their
t-derivatives ``dW_j``, points ``c_j`` inside each hole's image, the image ``a`` of the anchor
and the derivative ``D`` of the composed map at the anchor. One sweep (Nasser, CMFT 2015, and
the seed's "multiple single-connected problems"):

1. for each hole k: the exterior map F_k of the current curve W_k (alpha = c_k) is applied to
   W_k (which becomes the unit circle) and, by the exterior Cauchy formula, to every other W_j,
   their derivatives (chain rule), the points c_j and the anchor image; c_k becomes 0;
2. the interior map of the outer image with alpha = a is applied to everything (a -> 0).

At convergence every step is a similarity: ``c_j`` are the centres and ``r_j = mean|W_j - c_j|``
the radii. Each sweep normalises only its last map, so the rotations of the earlier exterior
maps stay in the composition; after convergence everything is rotated by ``e^{-i arg D}`` so
that ``T'(anchor) > 0`` (DESIGN.md sec. 2, "Final rotation").

Convergence is measured on nodes away from the vertices only, and the loop also stops when the
change stalls: rounding near re-entrant corners keeps the all-nodes change near 1e-9..1e-11.

References
----------
.. [1] M. M. S. Nasser, "Fast computation of the circular map", Comput. Methods Funct. Theory
   15 (2015) 187-223, secs. 3-4 (the iteration, ~100x error reduction per sweep).
.. [2] P. Koebe, "Abhandlungen zur Theorie der konformen Abbildung IV", Acta Math. 41 (1918).
.. [3] DESIGN.md sec. 2 (checked formulas, final rotation, convergence test).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from confnav.boundary import BoundaryMesh
from confnav.diskmap import CurveMap, exterior_map, interior_map
from confnav.errors import ConvergenceError, CrowdingError
from confnav.geometry import ComplexArray, FloatArray

#: Circles smaller than this (relative to the unit disk) cannot be resolved in double precision:
#: the image nodes of such a boundary crowd together below rounding (DESIGN.md sec. 6).
CROWDING_RADIUS = 1e-11
MAX_SWEEPS = 80
#: A sweep that does not reduce the change below this fraction of the best of the two before
#: counts as stalled (the change has reached the discretisation or rounding floor).
STALL_RATIO = 0.7


@dataclass
class CircleDomainResult:
    """Boundary images and circle domain after the Koebe-type iteration."""

    W: list[ComplexArray]
    dW: list[ComplexArray]
    centers: ComplexArray
    radii: FloatArray
    derivative_at_anchor: complex
    sweeps: int
    history: list[float] = field(default_factory=list)
    circularity: float = 0.0  # max over holes of max_k | |W_jk - c_j| - r_j |, and outer
    gmres_iterations: int = 0
    wall_time: float = 0.0


def _winding(curve: ComplexArray, z: complex) -> float:
    """Winding number of a closed polyline about z (for sanity checks of alpha)."""
    d = np.angle(np.roll(curve, -1) - z) - np.angle(curve - z)
    d = (d + np.pi) % (2 * np.pi) - np.pi
    return float(d.sum() / (2 * np.pi))


def _apply(
    cm: CurveMap, W: list[ComplexArray], dW: list[ComplexArray], pts: ComplexArray,
    skip: int,
) -> tuple[ComplexArray, ComplexArray]:
    """Apply a curve map to all W_j (j != skip), their derivatives, and extra points.

    Returns the images and derivatives of ``pts`` (the anchor image and hole points).
    """
    idx = [j for j in range(len(W)) if j != skip]
    sizes = [W[j].size for j in idx]
    z = np.concatenate([*(W[j] for j in idx), pts])
    fz, dfz = cm.evaluate(z, derivative=True)
    assert dfz is not None
    off = 0
    for j, s in zip(idx, sizes, strict=True):
        W[j] = fz[off : off + s]
        dW[j] = dW[j] * dfz[off : off + s]
        off += s
    return fz[off:], dfz[off:]


def koebe_iteration(
    meshes: list[BoundaryMesh],
    hole_points: list[complex],
    anchor: complex,
    tol: float,
    max_sweeps: int = MAX_SWEEPS,
    progress: Callable[[int, float], None] | None = None,
) -> CircleDomainResult:
    """Run the iteration on graded meshes (outer counter-clockwise, holes clockwise).

    Parameters
    ----------
    meshes
        ``meshes[0]`` the outer boundary (ccw), ``meshes[1:]`` the holes (cw).
    hole_points
        A point inside each hole (initial ``c_j``).
    anchor
        The point sent to 0.
    tol
        Stop when the change of the boundary images (away from vertices) is below ``tol``.
    """
    t0 = time.perf_counter()
    W = [m.eta.copy() for m in meshes]
    dW = [m.deta.copy() for m in meshes]
    masks = [m.interior_mask() for m in meshes]
    M = len(meshes) - 1
    c = np.array(hole_points, dtype=np.complex128)
    a = complex(anchor)
    D = 1.0 + 0j
    history: list[float] = []
    gm_its = 0
    sweeps = 0
    for sweep in range(1, max_sweeps + 1):
        sweeps = sweep
        W_old = [w.copy() for w in W]
        for k in range(1, M + 1):
            if abs(_winding(W[k], c[k - 1])) < 0.5:
                raise ConvergenceError(
                    f"Koebe iteration lost track of obstacle {k - 1} in sweep {sweep} "
                    "(its tracked point left the boundary image)"
                )
            F = exterior_map(W[k], dW[k], c[k - 1])
            gm_its += F.gmres_iterations
            others = np.concatenate([[a], np.delete(c, k - 1)])
            img, dimg = _apply(F, W, dW, others, skip=k)
            W[k], dW[k] = F.f, F.df
            a, D = complex(img[0]), D * complex(dimg[0])
            c = np.insert(img[1:], k - 1, 0.0)
        f0 = interior_map(W[0], dW[0], a)
        gm_its += f0.gmres_iterations
        img, _ = _apply(f0, W, dW, c, skip=0)
        W[0], dW[0] = f0.f, f0.df
        c, D, a = img, D * f0.scale, 0j
        change = max(
            float(np.max(np.abs(W[j][masks[j]] - W_old[j][masks[j]]))) for j in range(M + 1)
        )
        history.append(change)
        if progress is not None:
            progress(sweep, change)
        radii = np.array([np.mean(np.abs(W[j][masks[j]] - c[j - 1])) for j in range(1, M + 1)])
        if M and radii.min() < CROWDING_RADIUS:
            j = int(np.argmin(radii))
            raise CrowdingError(
                f"obstacle {j}'s circle has radius {radii[j]:.1e}: too small to resolve in double "
                "precision (crowding: a long, narrow passage leads to it)"
            )
        if not np.all(np.isfinite(change)):
            raise ConvergenceError(f"Koebe iteration produced non-finite values in sweep {sweep}")
        if change < tol:
            break
        if sweep >= 4 and change > STALL_RATIO * min(history[-3:-1]):
            break  # stalled at the discretisation/rounding level: the error estimate decides
    else:
        raise ConvergenceError(
            f"Koebe iteration did not converge in {max_sweeps} sweeps (last change "
            f"{history[-1]:.2e} > tol {tol:.1e})"
        )
    # Final rotation so that T'(anchor) > 0.
    rot = np.exp(-1j * np.angle(D))
    W = [w * rot for w in W]
    dW = [d * rot for d in dW]
    c = c * rot
    radii = np.array([np.mean(np.abs(W[j][masks[j]] - c[j - 1])) for j in range(1, M + 1)])
    circ = float(np.max(np.abs(np.abs(W[0][masks[0]]) - 1.0)))
    for j in range(1, M + 1):
        circ = max(circ, float(np.max(np.abs(np.abs(W[j][masks[j]] - c[j - 1]) - radii[j - 1]))))
    return CircleDomainResult(
        W=W, dW=dW, centers=c, radii=radii, derivative_at_anchor=abs(D), sweeps=sweeps,
        history=history, circularity=circ, gmres_iterations=gm_its,
        wall_time=time.perf_counter() - t0,
    )


__all__ = ["CROWDING_RADIUS", "CircleDomainResult", "koebe_iteration"]
