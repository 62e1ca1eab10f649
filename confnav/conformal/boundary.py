"""Graded-mesh discretisation of polygon boundaries (Kress's sigma-transformation).

A polygon is parametrised by ``t in [0, 2pi)`` with equispaced nodes ``t_i = 2pi i / n``. Side
``k`` owns ``n_k`` consecutive nodes (its share ``[S_k, S_{k+1})`` of the parameter range) and is
traversed with Kress's grading function ``sigma`` so that all derivatives of ``eta(t)`` up to
order ``p - 1`` vanish at the vertices. The trapezoidal rule on the graded parametrisation then
converges like ``n^-p`` despite the corner singularities.

With equal shares ``S_k = 2pi(k-1)/L`` this is exactly docs/METHOD.md section 2 (and the seed's
eqs. (sigma), (g), (eta), with the errata of docs/METHOD.md section 6); unequal ``n_k`` let long
sides and sides close to other boundaries get more nodes without changing the scheme.

References
----------
.. [1] R. Kress, "A Nystrom method for boundary integral equations in domains with corners",
   Numer. Math. 58 (1990) 145-161, eqs. (3.1)-(3.3) (the sigma-transformation).
.. [2] M. M. S. Nasser, "Fast solution of boundary integral equations with the generalized
   Neumann kernel", ETNA 44 (2015) 189-229, sec. 2 (graded meshes for corners).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Grading exponent. docs/METHOD.md sec. 2 recommends p = 5 because p >= 6 puts nodes within 1e-16
#: of the vertices. Here such nodes are dropped as quadrature sources (their weight is below
#: rounding, see confnav.conformal.gnk.alive_nodes) and only the first Koebe sweep works on the
#: graded
#: mesh, so p = 7 is safe up to ~256 nodes per side and cuts the error of the default workspace
#: at 128 nodes per side from 9e-7 (p = 5) to 5e-9 (measured). From 384 nodes per side live
#: nodes on the two sides of a corner can merge in floating point; alive_nodes keeps one.
GRADING_P = 7


def _v(tau: FloatArray, p: int) -> FloatArray:
    """Kress's cubic v(tau) [1, eq. (3.2)]."""
    return (1 / p - 0.5) * ((np.pi - tau) / np.pi) ** 3 + (tau - np.pi) / (p * np.pi) + 0.5


def _dv(tau: FloatArray, p: int) -> FloatArray:
    return -3 * (1 / p - 0.5) * (np.pi - tau) ** 2 / np.pi**3 + 1 / (p * np.pi)


def kress_sigma(tau: FloatArray, p: int = GRADING_P) -> tuple[FloatArray, FloatArray]:
    """sigma(tau) = 2pi v^p / (v^p + v(2pi - tau)^p) and its derivative [1, eq. (3.1)].

    Maps [0, 2pi] onto itself, increasing, with sigma^(j)(0) = sigma^(j)(2pi) = 0 for
    j = 1..p-1.
    """
    a = _v(tau, p)
    b = _v(2 * np.pi - tau, p)
    ap, bp = a**p, b**p
    den = ap + bp
    sig = 2 * np.pi * ap / den
    # d/dtau [a^p/(a^p+b^p)] with a' = v'(tau), b' = -v'(2pi - tau)
    da = p * a ** (p - 1) * _dv(tau, p)
    db = -p * b ** (p - 1) * _dv(2 * np.pi - tau, p)
    dsig = 2 * np.pi * (da * bp - ap * db) / den**2
    return sig, dsig


#: Part of each side (in tau, from either end) whose nodes form its vertices' blocks in the GNK
#: corner preconditioner (:meth:`BoundaryMesh.corner_blocks`). Measured on the first sweep's
#: graded GNK solves of one cold level (``python bench/bench_koebe.py --corner-study``,
#: bench/results/koebe_corner_blocks.json; GMRES iterations in total and CPU s with one BLAS
#: thread, for no blocks / 1/2 / 1/4 / 1/8 of each side): default workspace at 180 nodes per
#: side 195 / 67 / 93 / 118 iterations, 0.26 / 0.16 / 0.20 / 0.17 s; 50 mixed obstacles at 120
#: 1963 / 617 / 864 / 1098, 1.16 / 1.08 / 0.90 / 0.91 s. A quarter: a quarter of the halves'
#: factorisation work (blocks half as large), the fewest seconds where the boundaries are many.
CORNER_BLOCK_FRACTION = 0.25


@dataclass(frozen=True)
class BoundaryMesh:
    """Nodes of one closed polygonal curve on the graded mesh.

    Attributes
    ----------
    eta, deta
        Node positions ``eta(t_i)`` and derivatives ``eta'(t_i)`` (complex, shape (n,)).
    side
        Index of the side each node lies on.
    tau
        The node's position within its side, in [0, 2pi) (0 = at the side's first vertex).
    """

    eta: ComplexArray
    deta: ComplexArray
    side: NDArray[np.intp]
    tau: FloatArray

    @property
    def n(self) -> int:
        return int(self.eta.size)

    @property
    def weight(self) -> float:
        """Trapezoidal weight 2pi/n."""
        return 2 * np.pi / self.n

    def interior_mask(self, margin: float = 0.125) -> NDArray[np.bool_]:
        """Nodes away from the vertices: outside the first/last ``margin`` of each side.

        Convergence is measured only there (docs/METHOD.md sec. 2, "Convergence test"): rounding
        near re-entrant corners keeps the change at vertex-adjacent nodes near 1e-9..1e-11.
        """
        lo = 2 * np.pi * margin
        return np.asarray((self.tau >= lo) & (self.tau <= 2 * np.pi - lo))

    def corner_blocks(self, fraction: float = CORNER_BLOCK_FRACTION) -> NDArray[np.intp]:
        """The vertex block of each node: the nodes in the first ``fraction`` of a side (in
        tau) belong to its first vertex (label ``side``), those in the last to its second
        (``side + 1``), the others to none (-1); the same labels in either direction. The
        blocks of the GNK corner preconditioner (:func:`confnav.conformal.gnk.solve_gnk`)."""
        L = int(self.side.max()) + 1 if self.side.size else 1
        lo, hi = 2 * np.pi * fraction, 2 * np.pi * (1.0 - fraction)
        lab = np.where(self.tau < lo, self.side, np.where(self.tau > hi, (self.side + 1) % L, -1))
        return np.asarray(lab, dtype=np.intp)

    def reversed(self) -> BoundaryMesh:
        """The same nodes traversed the other way: eta(-t) (derivative negated)."""
        idx = (-np.arange(self.n)) % self.n
        return BoundaryMesh(self.eta[idx], -self.deta[idx], self.side[idx], self.tau[idx])


def graded_polygon(
    vertices: ComplexArray, nodes_per_side: NDArray[np.intp] | int, p: int = GRADING_P
) -> BoundaryMesh:
    """Graded mesh of a polygon, traversed in the given vertex order.

    Parameters
    ----------
    vertices
        Polygon vertices (L,), in traversal order, no closing copy.
    nodes_per_side
        Nodes on each side (scalar or (L,)); each at least 4.
    p
        Grading exponent (default 5).
    """
    v = np.asarray(vertices, dtype=np.complex128)
    L = v.size
    nk = np.broadcast_to(np.asarray(nodes_per_side, dtype=np.intp), (L,)).copy()
    if np.any(nk < 4):
        raise ValueError("need at least 4 nodes per side")
    n = int(nk.sum())
    side = np.repeat(np.arange(L), nk)
    first = np.concatenate([[0], np.cumsum(nk)[:-1]])
    local = np.arange(n) - first[side]  # node index within its side
    tau = 2 * np.pi * local / nk[side]  # position in [0, 2pi) along the side
    sig, dsig = kress_sigma(tau, p)
    edge = np.roll(v, -1) - v
    eta = v[side] + edge[side] * sig / (2 * np.pi)
    # d eta/dt = edge * sigma'(tau)/(2pi) * dtau/dt with dtau/dt = n / n_k
    deta = edge[side] * dsig / (2 * np.pi) * (n / nk[side])
    eta[local == 0] = v[side[local == 0]]  # exact vertices
    return BoundaryMesh(eta, deta, side, tau)


def _vertex_order(m: BoundaryMesh) -> tuple[ComplexArray, FloatArray]:
    """The mesh's vertices by side, and every node's position ``side + tau/2pi`` along the
    polygon in its original (unreversed) order."""
    at = m.tau == 0
    return m.eta[at][np.argsort(m.side[at])], m.side + m.tau / (2 * np.pi)


def resample(old: BoundaryMesh, values: FloatArray, new: BoundaryMesh) -> FloatArray | None:
    """Values at the nodes of ``old`` carried to the nodes of ``new``, a mesh of the same
    polygon with other node counts per side (a first guess, not an exact transfer).

    Interpolated by a periodic cubic spline in ``side + tau/2pi``: on Kress's graded mesh the
    functions of the boundary integral equation are smooth in tau up to the vertices (their
    tau-derivatives vanish there to order p - 1, see :func:`kress_sigma`), so one spline runs
    through the corners (C. de Boor, "A Practical Guide to Splines", Springer 1978, ch. IV:
    the cubic spline interpolant errs by O(h^4) times the fourth derivative). Returns None
    when the two meshes are not of the same polygon (its sides split differently).
    """
    from scipy.interpolate import CubicSpline

    v_old, x_old = _vertex_order(old)
    v_new, x_new = _vertex_order(new)
    if v_old.shape != v_new.shape or not np.array_equal(v_old, v_new) or values.shape != (old.n,):
        return None
    order = np.argsort(x_old)
    x = np.r_[x_old[order], v_old.size]
    y = np.asarray(values, dtype=np.float64)[order]
    spline = CubicSpline(x, np.r_[y, y[0]], bc_type="periodic")
    return np.asarray(spline(x_new), dtype=np.float64)


__all__ = ["GRADING_P", "BoundaryMesh", "graded_polygon", "kress_sigma", "resample"]
