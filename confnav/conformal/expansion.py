"""O(1)-per-point evaluation of the map's Cauchy sums by local (Taylor) expansions on a quadtree.

``ConformalMap`` evaluates T and T' from the discrete Cauchy sums (docs/METHOD.md sec. 2)

    S_j(z) = sum_k q_jk / (eta_k - z),   j = 1 (q = w W eta', sum N), 2 (q = w eta', sum D),

and their derivatives ``S_j'(z) = sum_k q_jk / (eta_k - z)^2``: a cost linear in the boundary
nodes per point. This module covers the free space with the leaves of a quadtree; in a leaf
box with centre c and circumradius R both sums are replaced by their Taylor polynomials of
degree p about c (the local expansions of the fast multipole method [1], [2]):

    1/(eta - z) = sum_{m>=0} (z - c)^m / (eta - c)^(m+1)            (|z - c| < |eta - c|),
    S(z) = sum_{m=0}^{p} b_m (z - c)^m,   b_m = sum_k q_k / (eta_k - c)^(m+1).

Construction is the downward pass of the FMM ([1] sec. 3.2): a node eta_k is *far* from a box
when ``rho_k = R/|eta_k - c| <= separation``; a box's expansion is its parent's, re-expanded
about the box centre (exact for polynomials: ``zeta_parent = delta + zeta_child/2`` in scaled
variables, [2] Lemma 3.3), plus the Taylor coefficients of the nodes that are far from the box
but were not far from its parent. Far from the parent implies far from the child, so every
node enters once per branch. A box with no near node is a leaf; boxes at ``max_level`` that
still have near nodes are not covered, and points there (within a few finest box sizes of a
wall) are left to the direct barycentric formula, which stays accurate up to the boundary. The
cost of a build is about (nodes x boxes near each node x p), not (leaves x nodes x p).

Truncation bound (the standard FMM estimate, [1] Lemma 2.3, [2] sec. 3, here for the Cauchy
kernel): a node with d_k = |eta_k - c| and rho_k = R/d_k < 1 contributes at most

    |q_k|/d_k   * rho_k^(p+1) / (1 - rho_k)                        to |S - S_p|,
    |q_k|/d_k^2 * ((p+1) rho_k^p - p rho_k^(p+1)) / (1 - rho_k)^2  to |S' - S_p'|,

at every z with |z - c| <= R. A child's disk lies in its parent's, so a leaf's bound is the sum
of these terms over the boxes where each node entered; the builder records the largest.
Evaluation is a table look-up of the leaf and one polynomial of degree p: its cost does not
depend on the number of boundary nodes. Since ``|D| -> 2 pi`` in the free space, T = N/D and
T' = (N'D - N D')/D^2 then differ from the direct formula by about (bound / pi) absolutely,
plus the rounding both share.

References
----------
.. [1] L. Greengard, V. Rokhlin, "A fast algorithm for particle simulations", J. Comput. Phys.
   73 (1987) 325-348, sec. 2 (multipole and local expansions, Lemmas 2.1-2.3) and sec. 3.2.
.. [2] R. Beatson, L. Greengard, "A short course on fast multipole methods", in Wavelets,
   Multilevel Methods and Elliptic PDEs, Oxford Univ. Press (1997) 1-37, sec. 3.
"""

from __future__ import annotations

import cmath
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import shapely
from scipy.special import comb

from confnav.powers import power_table
from confnav.types import BArray as BoolArray
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray
from confnav.types import IArray as IntArray

#: Default polynomial degree of the local expansions.
DEFAULT_DEGREE = 48
#: Default separation: a node is far from a box when R/|eta - c| <= this.
DEFAULT_SEPARATION = 0.4
#: Default depth of the quadtree: the finest boxes are 2^-8 of the bounding square.
DEFAULT_MAX_LEVEL = 8
# children in the order (2i, 2j), (2i+1, 2j), (2i, 2j+1), (2i+1, 2j+1): offsets of their
# centres from the parent's, in units of the parent's side / 4
_CHILD_DX = np.array([-1, 1, -1, 1])
_CHILD_DY = np.array([-1, -1, 1, 1])


def _split_boxes(
    split: np.ndarray,
    ix: np.ndarray,
    iy: np.ndarray,
    beta: ComplexArray,
    bnd: FloatArray,
    pb: np.ndarray,
    pk: np.ndarray,
    shift: ComplexArray,
) -> tuple[np.ndarray, np.ndarray, ComplexArray, FloatArray, np.ndarray, np.ndarray]:
    """Split the boxes marked ``split`` into their four children: each child inherits the
    parent's polynomial re-expanded about its own centre (``shift``), its error bounds and
    its near (box, node) pairs ``pb``, ``pk``."""
    idx = np.cumsum(split) - 1
    ix, iy, beta, bnd = ix[split], iy[split], beta[split], bnd[split]
    pb = idx[pb]
    nb = ix.size
    ix = (2 * ix[None, :] + (_CHILD_DX[:, None] > 0)).ravel()
    iy = (2 * iy[None, :] + (_CHILD_DY[:, None] > 0)).ravel()
    beta = np.einsum("bmc,jmi->jbic", beta, shift).reshape(4 * nb, beta.shape[1], beta.shape[2])
    bnd = np.tile(bnd, (4, 1))
    pb = (np.arange(4)[:, None] * nb + pb[None, :]).ravel()
    pk = np.tile(pk, 4)
    return ix, iy, beta, bnd, pb, pk


@dataclass(frozen=True)
class ExpansionStats:
    """How the evaluator was built: leaves per level, degree, separation, largest truncation
    bounds of any leaf (sums, derivatives; absolute), finest box side, build time (s)."""

    leaves: int
    leaves_per_level: list[int]
    degree: int
    separation: float
    max_level: int
    max_bound: float
    max_bound_derivative: float
    finest_box: float
    build_time: float


def _shift_matrices(p: int) -> ComplexArray:
    """(4, p+1, p+1): beta_child = beta_parent @ M[j] for child j (module docstring):
    ``M[m, i] = C(m, i) delta^(m-i) 2^-i`` from ``(delta + zeta/2)^m``, delta = child centre
    in the parent's scaled variable. Rows sum in modulus to (|delta| + 1/2)^m = 1: stable."""
    m = np.arange(p + 1)
    binom = comb(m[:, None], m[None, :])  # C(m, i), zero for i > m
    out = np.zeros((4, p + 1, p + 1), np.complex128)
    for j in range(4):
        delta = (_CHILD_DX[j] + 1j * _CHILD_DY[j]) * np.sqrt(2.0) / 4
        e = m[:, None] - m[None, :]
        with np.errstate(invalid="ignore"):
            pw = np.where(e >= 0, delta ** np.maximum(e, 0), 0)
        out[j] = binom * pw * 0.5 ** m[None, :]
    return out


class LocalExpansions:
    """Local expansions of Cauchy sums ``sum_k q_jk/(eta_k - z)`` on an adaptive quadtree.

    Parameters
    ----------
    nodes : (n,) complex, the boundary nodes eta_k.
    charges : (n, c) complex, one column per sum (weights folded in).
    region : optional shapely geometry; boxes not meeting it get no expansion (saves the
        boxes inside obstacles and outside the outer boundary).
    degree : polynomial degree p of each expansion.
    separation : a node is far from a box (radius R, centre c) when R/|eta - c| <= this.
    max_level : depth of the quadtree (the finest box side is the bounding square / 2^level).
    """

    def __init__(
        self,
        nodes: ComplexArray,
        charges: ComplexArray,
        region: shapely.Geometry | None = None,
        degree: int = DEFAULT_DEGREE,
        separation: float = DEFAULT_SEPARATION,
        max_level: int = DEFAULT_MAX_LEVEL,
    ) -> None:
        t0 = time.perf_counter()
        eta = np.asarray(nodes, dtype=np.complex128).ravel()
        q = np.asarray(charges, dtype=np.complex128).reshape(eta.size, -1)
        if not (degree >= 1 and 0 < separation < 1 and 0 <= max_level <= 12 and eta.size):
            raise ValueError("need degree >= 1, 0 < separation < 1, 0 <= max_level <= 12, nodes")
        self.degree = p = int(degree)
        self.max_level = int(max_level)
        nsum = self._nsum = q.shape[1]
        x0, y0 = float(eta.real.min()), float(eta.imag.min())
        side = max(float(eta.real.max()) - x0, float(eta.imag.max()) - y0)
        pad = 1e-9 * side
        self._origin = complex(x0 - pad, y0 - pad)
        side += 2 * pad
        self._n_fine = 1 << self.max_level
        self._h_fine = side / self._n_fine
        # leaf table at the finest level: fine cell (iy, ix) -> leaf index, -1 = not covered
        self._table = np.full((self._n_fine, self._n_fine), -1, dtype=np.int32)
        aq = np.abs(q).max(axis=1)
        shift = _shift_matrices(p)
        centres: list[ComplexArray] = []
        radii: list[FloatArray] = []
        coefs: list[ComplexArray] = []
        bounds: list[FloatArray] = []
        per_level: list[int] = []
        # active boxes of the level and their (box, node) near pairs
        ix = np.zeros(1, np.int64)
        iy = np.zeros(1, np.int64)
        beta = np.zeros((1, p + 1, nsum), np.complex128)
        bnd = np.zeros((1, 2))
        pb = np.zeros(eta.size, np.int64)
        pk = np.arange(eta.size)
        for level in range(self.max_level + 1):
            h = side / (1 << level)
            R = h / np.sqrt(2.0)
            c = self._origin + h * ((ix + 0.5) + 1j * (iy + 0.5))
            if region is not None and level > 0:
                boxes = shapely.box(c.real - h / 2, c.imag - h / 2, c.real + h / 2, c.imag + h / 2)
                meet = np.asarray(shapely.intersects(region, boxes), dtype=bool)
                new_index = np.cumsum(meet) - 1
                keep = meet[pb]
                pb, pk = new_index[pb[keep]], pk[keep]
                ix, iy, c, beta, bnd = ix[meet], iy[meet], c[meet], beta[meet], bnd[meet]
            diff = eta[pk] - c[pb]
            with np.errstate(divide="ignore"):  # a node on a box centre: rho = inf, near
                rho = R / np.abs(diff)
            far = rho <= separation
            self._add_far(beta, bnd, pb[far], diff[far], rho[far], q[pk[far]], aq[pk[far]], R)
            pb, pk = pb[~far], pk[~far]
            leaf = np.bincount(pb, minlength=c.size) == 0
            if leaf.any():
                first = sum(x.size for x in centres)
                centres.append(c[leaf])
                radii.append(np.full(int(leaf.sum()), R))
                coefs.append(beta[leaf])
                bounds.append(bnd[leaf])
                s = 1 << (self.max_level - level)
                for n, (i, j) in enumerate(zip(ix[leaf], iy[leaf], strict=True)):
                    self._table[j * s : (j + 1) * s, i * s : (i + 1) * s] = first + n
            per_level.append(int(leaf.sum()))
            if level == self.max_level:
                break
            ix, iy, beta, bnd, pb, pk = _split_boxes(~leaf, ix, iy, beta, bnd, pb, pk, shift)
        self._store_leaves(centres, radii, coefs)
        worst = np.concatenate(bounds).max(axis=0) if bounds else np.zeros(2)
        self.stats = ExpansionStats(
            leaves=int(self._centres.size),
            leaves_per_level=per_level,
            degree=p,
            separation=float(separation),
            max_level=self.max_level,
            max_bound=float(worst[0]),
            max_bound_derivative=float(worst[1]),
            finest_box=self._h_fine,
            build_time=time.perf_counter() - t0,
        )

    def _store_leaves(
        self, centres: list[ComplexArray], radii: list[FloatArray], coefs: list[ComplexArray]
    ) -> None:
        """Keep the leaves' centres, radii and coefficients: columns [0, c) beta_m of the
        sums, [c, 2c) (m+1) beta_(m+1) / R of their derivatives, so that S = sum beta_m zeta^m
        and S' = sum gamma_m zeta^m with zeta = (z - c)/R."""
        p, nsum = self.degree, self._nsum
        self._centres = np.concatenate(centres) if centres else np.zeros(0, np.complex128)
        self._radii = np.concatenate(radii) if radii else np.zeros(0)
        b = np.concatenate(coefs) if coefs else np.zeros((0, p + 1, nsum), np.complex128)
        self._coef = np.zeros((b.shape[0], p + 1, 2 * nsum), np.complex128)
        self._coef[:, :, :nsum] = b
        self._coef[:, :-1, nsum:] = (
            b[:, 1:] * np.arange(1, p + 1)[None, :, None] / self._radii[:, None, None]
        )

    def _add_far(
        self,
        beta: ComplexArray,
        bnd: FloatArray,
        box: IntArray,
        diff: ComplexArray,
        rho: FloatArray,
        q: ComplexArray,
        aq: FloatArray,
        R: float,
    ) -> None:
        """Add the Taylor coefficients ``q R^m/(eta - c)^(m+1)`` of newly far nodes to their
        boxes' beta (in place) and their truncation bounds (module docstring) to bnd."""
        if not box.size:
            return
        p = self.degree
        inv = 1.0 / diff
        T = np.empty((box.size, p + 1), np.complex128)
        T[:, 0] = inv
        T[:, 1:] = (R * inv)[:, None]
        np.cumprod(T, axis=1, out=T)  # inv * (R inv)^m
        terms = (T[:, :, None] * q[:, None, :]).reshape(box.size, -1)
        gather = sp.csr_matrix(
            (np.ones(box.size), (box, np.arange(box.size))), shape=(beta.shape[0], box.size)
        )
        beta += (gather @ terms).reshape(beta.shape)
        d = np.abs(diff)
        t0 = aq / d * rho ** (p + 1) / (1 - rho)
        t1 = aq / d**2 * ((p + 1) * rho**p - p * rho ** (p + 1)) / (1 - rho) ** 2
        bnd[:, 0] += np.bincount(box, t0, minlength=beta.shape[0])
        bnd[:, 1] += np.bincount(box, t1, minlength=beta.shape[0])

    # ------------------------------------------------------------------ evaluation
    def leaf_of(self, z: ComplexArray) -> IntArray:
        """Leaf index of each point (-1 where no expansion covers it)."""
        with np.errstate(invalid="ignore"):  # non-finite points are simply not inside
            rel = (np.asarray(z, dtype=np.complex128) - self._origin) / self._h_fine
            inside = (
                (rel.real >= 0)
                & (rel.real < self._n_fine)
                & (rel.imag >= 0)
                & (rel.imag < self._n_fine)
            )
        i = np.where(inside, rel.real, 0).astype(np.int64)
        j = np.where(inside, rel.imag, 0).astype(np.int64)
        return np.where(inside, self._table[j, i], -1).astype(np.int64)

    def sums(self, z: ComplexArray) -> tuple[BoolArray, ComplexArray, ComplexArray]:
        """(covered, S, S') at the points: S and S' are (points, c) arrays of the sums and
        their derivatives, valid where ``covered`` (NaN elsewhere)."""
        zz = np.asarray(z, dtype=np.complex128).ravel()
        if zz.size == 1:  # one robot: scalar look-up, no per-array overhead
            return self._sums1(complex(zz[0]))
        leaf = self.leaf_of(zz)
        covered = leaf >= 0
        out = np.full((zz.size, 2 * self._nsum), np.nan + 0j)
        if covered.any():
            lf = leaf[covered]
            zeta = (zz[covered] - self._centres[lf]) / self._radii[lf]
            V = power_table(zeta[:, None], self.degree)  # (points, 1, degree + 1)
            out[covered] = np.matmul(V, self._coef[lf])[:, 0, :]
        return covered, out[:, : self._nsum], out[:, self._nsum :]

    def _sums1(self, z: complex) -> tuple[BoolArray, ComplexArray, ComplexArray]:
        """:meth:`sums` of a single point, from :meth:`sums1`."""
        out = np.full((1, 2 * self._nsum), np.nan + 0j)
        s = self.sums1(z)
        if s is not None:
            out[0] = s
        return np.array([s is not None]), out[:, : self._nsum], out[:, self._nsum :]

    def sums1(self, z: complex) -> ComplexArray | None:
        """The sums and their derivatives at one point as one (2c,) array (sums first), None
        where no expansion covers it.  Bitwise the row of :meth:`sums` for the same point: the
        same leaf, ``zeta`` in numpy scalars, powers by cumprod, the same dot; Python scalars
        for the look-up (no per-array overhead: the one-robot control step)."""
        if not cmath.isfinite(z):
            return None
        rel = (np.complex128(z) - self._origin) / self._h_fine  # as leaf_of, bitwise
        x, y = float(rel.real), float(rel.imag)
        if not (0 <= x < self._n_fine and 0 <= y < self._n_fine):
            return None
        lf = int(self._table[int(y), int(x)])
        if lf < 0:
            return None
        zeta = (np.complex128(z) - self._centres[lf]) / self._radii[lf]
        V = np.empty(self.degree + 1, np.complex128)
        V[0] = 1.0
        V[1:] = zeta
        np.cumprod(V, out=V)
        return np.asarray(V @ self._coef[lf])

    def error_bound(self) -> tuple[float, float]:
        """Largest truncation bound of any leaf: (sums, derivatives), absolute."""
        return self.stats.max_bound, self.stats.max_bound_derivative


__all__ = ["ExpansionStats", "LocalExpansions"]
