"""Mesh planning: nodes per polygon side from the corners, the gaps and a tolerance.

Two error sources decide how many graded-mesh nodes a panel needs:

* **corners.** At a corner with free-space angle ``a pi`` the map behaves like ``r^(1/a)``; on
  Kress's graded mesh that is ``tau^(p/a)`` and the trapezoidal rule converges like
  ``n^-(p/a + 1)`` [1]. Panels ending at a polygon corner get ``level^(e_ref/e)`` nodes, where
  ``e = p/a + 1`` of the polygon's worst corner; ``level`` is the refinement knob of
  :func:`confnav.solver.solve`.
* **proximity.** The Cauchy sums across a gap of width d between a panel and another boundary
  (or the anchor, or a non-adjacent side of the same polygon) converge like ``e^(-2 pi d/h)``
  for mesh spacing h [2], so ``h <= 2 pi d / ln(10/tol)``; the mid-side spacing of Kress's
  sigma mesh is ``2 len / n``. (Splitting long sides into shorter panels near close features
  was tried and measured worse: the grading at the split points wastes nodes, and on the
  default workspace 48 nodes on an unsplit outer side beat ~60 on split panels by 70x in the
  centres.)

References
----------
.. [1] R. Kress, Numer. Math. 58 (1990) 145-161 (graded meshes, convergence order).
.. [2] J. Helsing, R. Ojala, "On the evaluation of layer potentials close to their sources",
   J. Comput. Phys. 227 (2008) 2899-2921 (near-singular quadrature error ~ e^(-2 pi d/h)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from confnav.boundary import GRADING_P
from confnav.geometry import ComplexArray, Workspace

#: Free-space corner angle (units of pi) taken as the reference for ``level``.
REF_ANGLE = 1.75
#: Kress's grading narrows the strip of analyticity of the integrands (sigma has complex poles
#: near the middle of each side), so the e^(-2 pi d/h) rate is reached only for about half
#: the spacing: measured on the 4x2 rectangle, factor 1 leaves 3e-10 error at tol 1e-12,
#: factor 2 gives 1.3e-12 (the exact f'(0) of DESIGN.md sec. 4).
GRADING_STRIP = 2.0
#: Level at which the proximity rule is applied as derived (it scales like a straight corner).
LEVEL_BASE = 80
#: Every boundary's node total is a multiple of this, so that every 2nd/4th/8th node is again
#: an equispaced trapezoidal rule on the same parametrisation (fast evaluation of the map).
NODE_MULTIPLE = 8
#: Fewest nodes on any panel.
MIN_NODES = 12
#: Cap on the proximity requirement per panel.
MAX_NODES_PER_PANEL = 2000


@dataclass(frozen=True)
class PanelPlan:
    """Sides of one boundary: its vertices and the graded-mesh node count of each side."""

    vertices: ComplexArray
    nodes: np.ndarray

    @property
    def total(self) -> int:
        return int(self.nodes.sum())


def corner_exponent(polygon: ComplexArray, hole: bool, p: int = GRADING_P) -> float:
    """Convergence exponent ``p/a + 1`` of the polygon's worst corner seen from the free space."""
    e_in = polygon - np.roll(polygon, 1)
    e_out = np.roll(polygon, -1) - polygon
    interior = np.pi - np.angle(e_out / e_in)  # interior angle of the (ccw) polygon
    a = (2 * np.pi - interior) / np.pi if hole else interior / np.pi
    return p / max(float(a.max()), 0.75) + 1.0


def _lines(a: ComplexArray, b: ComplexArray) -> np.ndarray:
    xy = np.stack([np.column_stack([a.real, a.imag]), np.column_stack([b.real, b.imag])], axis=1)
    return np.asarray(shapely.linestrings(xy))


def _proximity_nodes(length: np.ndarray, d: np.ndarray, tol: float) -> np.ndarray:
    """Nodes for mesh spacing 2 len/n <= 2 pi d / (GRADING_STRIP ln(10/tol))."""
    n = np.ceil(GRADING_STRIP * 2 * length * np.log(10 / tol) / (2 * np.pi * np.maximum(d, 1e-12)))
    return np.asarray(np.minimum(n, MAX_NODES_PER_PANEL))


def _feature_distance(z: ComplexArray, features: shapely.Geometry) -> np.ndarray:
    """Distance of each side to the features and to the non-adjacent sides of its polygon."""
    L = z.size
    segs = _lines(z, np.roll(z, -1))
    d = np.asarray(shapely.distance(segs, features), dtype=float)
    if L > 3:  # non-adjacent sides of the same polygon (the arms of a U, a spiral)
        dd = shapely.distance(segs[:, None], segs[None, :])
        k = np.arange(L)
        gap = (k[:, None] - k[None, :]) % L
        dd = np.where((gap <= 1) | (gap >= L - 1), np.inf, dd)
        d = np.minimum(d, dd.min(axis=1))
    return d


def plan_boundaries(ws: Workspace, level: int, tol: float) -> list[PanelPlan]:
    """Panels and nodes for every boundary (outer first) at one refinement level."""
    e_ref = GRADING_P / REF_ANGLE + 1.0
    # The proximity requirement refines with the level too (like a straight corner, exponent
    # p + 1), so that every error source shrinks as the level grows.
    scale = (level / LEVEL_BASE) ** (e_ref / (GRADING_P + 1.0))
    polys = ws.boundaries
    rings = [shapely.LinearRing(np.column_stack([z.real, z.imag])) for z in polys]
    anchor = shapely.Point(ws.anchor.real, ws.anchor.imag)
    plans = []
    for j, z in enumerate(polys):
        others = shapely.union_all([anchor, *(g for i, g in enumerate(rings) if i != j)])
        n_corner = max(MIN_NODES, int(np.ceil(level ** (e_ref / corner_exponent(z, j > 0)))))
        d = _feature_distance(z, others)
        n_prox = np.ceil(scale * _proximity_nodes(np.abs(np.roll(z, -1) - z), d, tol))
        n = np.maximum(n_corner, n_prox).astype(np.intp)
        n[0] += (-int(n.sum())) % NODE_MULTIPLE  # totals divisible: see ConformalMap.coarsened
        plans.append(PanelPlan(vertices=z, nodes=n))
    return plans


__all__ = ["PanelPlan", "corner_exponent", "plan_boundaries"]
