"""Harmonic navigation function from the Green's function of a circle domain.

``G(w) = log|w - w_d| - h(w)`` with ``h`` harmonic in the circle domain and
``h = log|zeta - w_d|`` on every boundary circle, so ``G = 0`` on the boundary.  ``G`` is
split into an exact part and a fitted series:

    G = G_0 + sum_i s_i L(w; p_i) - S,
    G_0(w) = log|(w - w_d) / (1 - conj(w_d) w)|              (Green's function of the disk),
    L(w; p) = log|(w - p) / (1 - conj(p) w)|                 (image pair, 0 on |w| = 1),
    S(w)   = sum_j [ b_j L_j(w) + Re sum_n (B_jn u_j^n - conj(B_jn) v_j^n) ],
    L_j = log|(w - c_j) / (1 - conj(c_j) w)|,  u_j = r_j / (w - c_j),
    v_j = conj(u_j(1 / conj(w))) = r_j w / (1 - conj(c_j) w).

Every term vanishes identically on the outer circle (``|w| = 1`` gives ``v_j = conj(u_j)``):
each hole's multipole series comes with its reflection in the unit circle, the first level of
the method of images / Schottky group of the circle domain [3]_ [4]_.  ``S`` is complete for
harmonic functions vanishing on ``|w| = 1`` (logarithmic conjugation [1]_: ``H = sum_j (b_j
log|w - c_j| + Re F_j) + Re F_0`` with ``F_j`` analytic outside hole j; the outer condition
forces ``F_0 = -sum_j F_j^*`` with ``F_j^*(w) = conj(F_j(1/conj(w)))``), and it is fitted by
least squares on the hole circles only.  Why the reflected terms: a small hole close to the
outer circle puts a singularity of a plain Taylor series in ``w`` just outside ``|w| = 1``
(convergence rate 0.97-0.9997 per term measured on mixed 20, the door and the warehouse,
which never reached 1e-10 with 128 terms); with the reflections taken out exactly, each
hole's series converges at the rate of the limit points of the reflections in that hole and
its neighbours (<= 0.52 on every scene here: 1e-13 with 32-48 terms) and the columns, scaled
to unit norm, give a least-squares matrix of condition 4-20.

``G_0`` and the image pairs vanish on the outer circle too.  The images take the
near-singular part of the data: a point charge ``sigma`` at ``x`` (first the pole, +1, and its
reflection ``1/conj(w_d)``, -1) within ``NEAR r_j`` of hole j gets the charge ``-sigma`` at its
reflection ``x* = c_j + r_j^2 / conj(x - c_j)`` in circle j (on the circle ``|w - x| =
|w - x*| |x - c_j| / r_j``, so the pair cancels up to a constant, which the series carries),
paired with ``+sigma`` at ``1/conj(x*)``; the new charges are reflected in turn, up to
``IMAGE_DEPTH`` levels (the method of images truncated where the charges are far from every
other circle [3]_).  When the goal lies in a pocket (its image close to a circle), ``G`` is
tiny (1e-11 measured with the goal in a charging alcove) over most of the domain; ``G_0`` is
evaluated without cancellation (``1 - |M(w)|^2 = (1-|w|^2)(1-|w_d|^2)/|1 - conj(w_d) w|^2``)
and the data of ``S`` is as small as ``G`` there, so the fit's *relative* accuracy carries
over to ``G``, its gradient and ``1 - phi``.

**Cost bounded per map.**  The least-squares matrix depends on the circle domain only, not on
the goal (the boundary data is linear in it, docs/METHOD.md section 3): :class:`GreenBasis` builds
it once per map, scales its columns and stores a QR factorization; a new goal is then one
``Q^T b`` and a triangular solve plus a residual check on points between the collocation
points.  The number of terms per circle grows on a ladder (a finer basis is factored only
when a goal needs it, and kept for the next goals); a fit that misses ``tol`` with
``max_terms`` raises :class:`NavigationError` (the controller then falls back to
Koditschek-Rimon with automatic k and says so).

``phi_H = exp(2 G)`` is 1 on every boundary circle, has a single minimum (at w_d) and exactly
M saddles, and needs no tuning.  Its gradient is evaluated without the pole:
``grad phi_H = 2 e^{-2h} ((w - w_d) conj((1 - |w_d|^2)/(1 - conj(w_d) w)) - |w - w_d|^2
grad H)`` with ``H = S - sum_i s_i L(w; p_i)`` (``grad G_0`` in closed form, no cancellation).

References
----------
.. [1] S. Axler, "Harmonic functions from a complex analysis viewpoint", Amer. Math. Monthly
   93 (1986) 246-258 (logarithmic conjugation theorem).
.. [2] L. N. Trefethen, "Series solution of Laplace problems", ANZIAM J. 60 (2018) 1-26.
.. [3] D. Crowdy, "The Schottky-Klein prime function on the Schottky double of planar
   domains", Comput. Methods Funct. Theory 10 (2010) 501-517 (reflections in the circles).
.. [4] D. Crowdy and J. Marshall, "Green's functions for Laplace's equation in multiply
   connected domains", IMA J. Appl. Math. 72 (2007) 278-301.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from confnav.errors import NavigationError
from confnav.navigation.navfn import CircleDomain, NavigationFunction
from confnav.powers import power_table
from confnav.types import CArray, FArray, IArray

__all__ = [
    "GreenBasis",
    "GreenDiagnostics",
    "GreenFunction",
    "HarmonicNavigation",
    "RecentredHarmonic",
    "conformal_centre",
    "moebius_domain",
]


_CHUNK = 4096
#: Terms per circle tried in turn (a goal that needs more moves the map's basis up the ladder).
TERM_LADDER: tuple[int, ...] = (16, 24, 32, 48, 64, 96, 128, 192, 256)
#: Default cap of the terms per circle: bounds the per-map cost (a QR factorization with
#: M (2 n + 1) columns); a goal that needs more gets the Koditschek-Rimon fallback of the
#: controller.
DEFAULT_MAX_TERMS = 128
#: Memory one factorization may take (Q, R and the check matrix); caps the terms per circle
#: for many obstacles (issue 9: <= 1 GB with 20 obstacles).
MEMORY_BUDGET = 768 << 20
#: Work one factorization may take (QR flops; ~5 s on one core of this machine): caps the
#: terms per circle for many obstacles (64 with 20 obstacles; issue 9: <= 10 s per map).
FLOP_BUDGET = 6e10
#: A pair of circles whose limit point in hole j lies farther than ``LIMIT_RATE r_j`` from
#: ``c_j`` (the hole's own series would converge at that rate per term) gets a multipole
#: centre of its own at the limit point.
LIMIT_RATE = 0.6
#: Columns of the pivoted QR kept: diagonal of R above RCOND times its largest entry.
RCOND = 1e-14
#: Reflections iterated to find a limit point (converges like the square of the pair's rate).
LIMIT_ITER = 400
#: A charge gets an image in circle j when it is within ``NEAR * r_j`` of ``c_j``.
NEAR = 3.0
#: Levels of images of images (a goal in a gap between two close circles: the images
#: converge to the pair's limit points; the series takes the rest).
IMAGE_DEPTH = 6
#: At most this many image pairs per goal.
IMAGE_LIMIT = 128
#: Accuracy of G needed where robots drive, relative to |G| at each sample point (bound of
#: the error by the residuals and harmonic measures: :meth:`GreenBasis.fit`).
REL_TOL = 1e-3
#: A residual this small is rounding (data of size 1 through a QR solve): climbing the
#: ladder further only costs factorizations (measured floor 3e-15..1e-13; 1e-14..2.6e-13 on
#: the README's warehouse shrunk by 0.32 m, rising with the terms). Also the relative
#: rounding of ``G`` at a sample: its terms (data and series, each up to ~1) cancel to
#: ``|G|``, so an error bound below ``ROUNDING`` times their size is not asked for.
ROUNDING = 1e-13
#: Least absolute error of G accepted at a sample (terms of size below 1).
FLOOR = 1e-15
#: Bases kept per process (LRU over circle domains), so new goals on a map reuse its factors.
CACHE_SIZE = 4


@dataclass(frozen=True)
class GreenDiagnostics:
    """How the series for ``h`` was fitted.

    n_terms: Laurent terms per circle; n_collocation: collocation points per circle;
    residual: max boundary error of ``S`` on check points between the collocation points;
    threshold: what it had to reach (``min(tol, REL_TOL min |G(samples)|)``); history:
    (n_terms, residual) per attempt; converged: residual <= threshold; images: circles whose
    image charge was used; basis_seconds: time spent factoring for this fit (0: reused);
    rounding_limited: samples where ``G`` is certified to the rounding of its terms
    (:data:`ROUNDING` times their size) rather than to ``REL_TOL |G|``: ``REL_TOL |G|`` is below
    that rounding, or the error bound (harmonic measures times the residual) exceeds it and the
    fit was accepted at its own rounding floor (:data:`ROUNDING` times the size of the
    boundary data). ``|G|`` there (the far end of a long room, 1e-16..1e-12) is as accurate as
    double precision allows, and no more.
    """

    n_terms: int
    n_collocation: int
    residual: float
    tol: float
    converged: bool
    history: tuple[tuple[int, float], ...]
    threshold: float = 0.0
    images: tuple[int, ...] = ()
    basis_seconds: float = 0.0
    rounding_limited: int = 0


class _Level:
    """One rung of the ladder: the QR factors of the column-scaled design matrix on the hole
    circles (the outer circle needs no rows: every basis function vanishes there) and the
    check matrix on the points halfway between the collocation points."""

    def __init__(self, cen: _Centres, n: int) -> None:
        self.n = n
        self.p = 3 * n + 16
        self.cen = cen
        self.zeta = _boundary_points(cen, self.p, 0.0)
        self.zeta_check = _boundary_points(cen, self.p, 0.5)
        self.hole_of_row = np.repeat(cen.hole, self.p)  # rows grouped by centre
        a = _design(cen, self.zeta, n)
        self.scale = np.linalg.norm(a, axis=0)
        self.scale[self.scale == 0] = 1.0
        a /= self.scale
        if a.size:
            # pivoted QR, truncated where the columns are dependent to rounding (the
            # limit-point series overlap the holes' own series): a basic solution with
            # moderate coefficients instead of an ill-conditioned triangular solve
            q, r, piv = scipy.linalg.qr(
                a, mode="economic", pivoting=True, overwrite_a=True, check_finite=False
            )
            d = np.abs(np.diag(r))
            k = int(np.count_nonzero(d > RCOND * d[0]))
            self.r, self.qt, self.piv = r[:k, :k], np.ascontiguousarray(q[:, :k].T), piv[:k]
        else:  # no holes: S = 0
            self.qt, self.r = np.zeros((0, a.shape[0])), np.zeros((0, 0))
            self.piv = np.zeros(0, dtype=np.intp)
        self.cols = a.shape[1]
        self.check = _design(cen, self.zeta_check, n)
        self._measures: tuple[bytes, FArray] | None = None

    def measures(self, samples: CArray) -> FArray:
        """(S, M) harmonic measures of the hole circles at ``samples`` (the harmonic
        functions 1 on circle j and 0 on the other circles, fitted with this basis); cached
        for the last ``samples`` (a controller passes the same points for every goal)."""
        key = samples.tobytes()
        if self._measures is None or self._measures[0] != key:
            m = self.cen.m
            ind = (self.hole_of_row[:, None] == np.arange(m)).astype(float)  # 1 on circle j
            om = np.abs(_design(self.cen, samples, self.n) @ self.solve(ind))
            self._measures = (key, np.asarray(om, dtype=np.float64))
        return self._measures[1]

    def solve(self, rhs: FArray) -> FArray:
        """Least-squares coefficients for boundary data ``rhs`` (``R^-1 Q^T rhs``)."""
        coef = np.zeros((self.cols, *rhs.shape[1:]))
        if self.r.size:
            coef[self.piv] = scipy.linalg.solve_triangular(
                self.r, self.qt @ rhs, check_finite=False
            )
        return np.asarray((coef.T / self.scale).T, dtype=np.float64)

    @property
    def nbytes(self) -> int:
        return int(self.qt.nbytes + self.r.nbytes + self.check.nbytes)


class GreenBasis:
    """Per-map precompute of the Green's function fit (see the module docstring).

    ``fit(pole)`` returns the series coefficients for one goal; the least-squares factors are
    built on first need and shared by all goals (thread-safe).  Use :meth:`for_domain` to
    share one basis per circle domain across controllers.
    """

    def __init__(
        self, domain: CircleDomain, *, tol: float = 1e-10, max_terms: int = DEFAULT_MAX_TERMS
    ) -> None:
        self.domain = domain
        self.tol = float(tol)
        self.centres = _Centres.of(domain)
        k = self.centres.c.size
        fits = [
            n
            for n in TERM_LADDER
            if _level_bytes(k, n) <= MEMORY_BUDGET and _level_flops(k, n) <= FLOP_BUDGET
        ]
        self.max_terms = min(int(max_terms), max(fits or [TERM_LADDER[0]]))
        self._levels: dict[int, _Level] = {}
        # index in TERM_LADDER of the smallest level worth trying; advanced only by a converged
        # fit, so a goal's function never depends on which goals failed before (replay --check
        # recomputes commands in another order)
        self._start = 0
        self._lock = threading.Lock()

    _cache: ClassVar[OrderedDict[tuple[bytes, bytes, float, int], GreenBasis]] = OrderedDict()
    _cache_lock: ClassVar[threading.Lock] = threading.Lock()

    @classmethod
    def for_domain(
        cls, domain: CircleDomain, *, tol: float = 1e-10, max_terms: int = DEFAULT_MAX_TERMS
    ) -> GreenBasis:
        """The shared basis of a circle domain (an LRU of :data:`CACHE_SIZE` domains)."""
        key = (domain.centers.tobytes(), domain.radii.tobytes(), float(tol), int(max_terms))
        with cls._cache_lock:
            b = cls._cache.get(key)
            if b is None:
                b = cls._cache[key] = cls(domain, tol=tol, max_terms=max_terms)
                while len(cls._cache) > CACHE_SIZE:
                    cls._cache.popitem(last=False)
            else:
                cls._cache.move_to_end(key)
            return b

    def precompute(self, goals: ArrayLike | None = None) -> GreenBasis:
        """Factor the levels the given goals (default: the anchor's image 0) need; later
        goals then cost one solve (or a finer level, factored once, if they need it)."""
        pts = np.atleast_1d(np.asarray(0j if goals is None else goals, dtype=np.complex128))
        for p in pts.ravel():
            if bool(self.domain.contains(p)):
                self.fit(complex(p))
        return self

    @property
    def n_terms(self) -> int:
        """Terms per circle of the level new goals start from."""
        return TERM_LADDER[self._start]

    @property
    def nbytes(self) -> int:
        return sum(lv.nbytes for lv in self._levels.values())

    def _level(self, n: int) -> tuple[_Level, float]:
        lv = self._levels.get(n)
        if lv is not None:
            return lv, 0.0
        k = self.centres.c.size
        # keep the levels factored so far while they fit the memory budget together: a goal
        # that climbs the ladder and fails must not make the next goal factor every rung
        # again (on the warehouse shrunk by 0.32 m each goal re-factored 24..64 terms:
        # 20-120 s per goal)
        kept = {m: lv for m, lv in self._levels.items() if m < n}
        while kept and sum(_level_bytes(k, m) for m in kept) + _level_bytes(k, n) > MEMORY_BUDGET:
            kept.pop(min(kept))
        t0 = time.perf_counter()
        lv = _Level(self.centres, n)
        self._levels = {**kept, n: lv}
        return lv, time.perf_counter() - t0

    def fit(
        self, pole: complex, samples: CArray | None = None
    ) -> tuple[FArray, _Images, GreenDiagnostics]:
        """(series coefficients, image pairs, diagnostics) for a pole; raises
        :class:`NavigationError` if ``max_terms`` terms do not reach the tolerance.

        The boundary residual must be below ``tol``, and the error of ``G`` at ``samples``
        (circle-domain points where robots drive) below ``REL_TOL |G|`` there.  The error is
        harmonic with boundary values at most ``rho_j`` (the residual) on circle j, so at a
        point s it is at most ``sum_j omega_j(s) rho_j`` with ``omega_j`` the harmonic measure
        of circle j (maximum principle; ``omega_j`` fitted once per map and samples,
        :meth:`_Level.measures`).  Where the goal sits in a pocket or behind a door and ``G``
        is 1e-12 in the far room, this asks the circles of the far room for a residual that
        much finer, not the circles next to the goal (their error reaches the far room damped
        by the same harmonic measure that makes ``G`` small there).
        """
        images, holes = _image_charges(self.domain, pole)
        m = self.domain.n_obstacles
        history: list[tuple[int, float]] = []
        spent = 0.0
        ladder = [n for n in TERM_LADDER if n <= self.max_terms] or [TERM_LADDER[0]]
        with self._lock:
            i = min(self._start, len(ladder) - 1)
            while True:
                lv, dt = self._level(ladder[i])
                spent += dt
                rhs = _data(lv.zeta, pole, images)
                coef = lv.solve(rhs)
                # the fit's own rounding floor: data of this size through a QR solve
                res_floor = ROUNDING * max(1.0, float(np.max(np.abs(rhs), initial=0)))
                dev = np.abs(lv.check @ coef - _data(lv.zeta_check, pole, images))
                rho = np.zeros(m)  # per hole circle
                np.maximum.at(rho, lv.hole_of_row, dev)
                res = float(np.max(rho, initial=0.0))
                thr = self.tol
                limited = 0
                if samples is not None and samples.size and res > 0:
                    data = _data(samples, pole, images)
                    terms = _design(lv.cen, samples, lv.n) * coef
                    g = data - terms.sum(axis=1)
                    fin = np.isfinite(g)
                    spread = lv.measures(samples)[fin] @ (rho / res)  # in [0, ~1]
                    # G at a sample is a sum of terms of size up to ~1 (the data is a log):
                    # it is known to no better than the rounding of that sum, so asking the
                    # fit for less is asking for noise (a long room's far end has |G| 1e-12;
                    # every goal of a SLAM map failed with "needed 1.2e-15" at 1e-14)
                    size = np.abs(data[fin]) + np.abs(terms[fin]).sum(axis=1)
                    floor = np.maximum(FLOOR, ROUNDING * size)
                    allowed = (REL_TOL * np.abs(g[fin]) + floor) / np.maximum(spread, 1e-300)
                    thr = min(thr, float(np.min(allowed, initial=np.inf)))
                    # samples whose accuracy the rounding sets, not REL_TOL |G|: below its
                    # terms' rounding, or beyond a residual at the fit's floor (below)
                    limited = int(np.count_nonzero((REL_TOL * np.abs(g[fin]) < floor)
                                                   | (allowed < res)))  # fmt: skip
                history.append((lv.n, res))
                # at the rounding floor more terms cannot lower the residual: the fit is as
                # good as double precision makes it, and the samples it cannot certify to
                # REL_TOL |G| are counted in the diagnostics (rounding_limited), not failed
                at_floor = res <= res_floor
                ok = res <= thr or (at_floor and res <= self.tol)
                if ok or i + 1 >= len(ladder):
                    break
                need = _extrapolate(history, thr)
                if need > 3.0 * ladder[-1]:
                    break  # the geometric rate says max_terms will not do: give up now
                i = max(i + 1, int(np.searchsorted(ladder, need)))
                i = min(i, len(ladder) - 1)
            if ok:  # later goals start here (never after a failure: see _start in __init__)
                self._start = max(self._start, i)
        diag = GreenDiagnostics(
            lv.n, lv.p, res, self.tol, ok, tuple(history), thr, holes, spent, limited
        )
        if not ok:
            raise NavigationError(
                f"Green's function series did not converge: boundary error {res:.2e} "
                f"(needed {thr:.1e}) with {lv.n} terms per circle (circles too close to "
                "each other or to the goal?)"
            )
        return coef, images, diag


def _level_flops(m: int, n: int) -> float:
    """Floating-point operations of the QR factorization of a :class:`_Level` (m centres)."""
    cols = m * (2 * n + 1)
    return 2.0 * m * (3 * n + 16) * cols * cols


def _level_bytes(m: int, n: int) -> int:
    """Bytes of a :class:`_Level` with ``n`` terms per centre and ``m`` centres."""
    cols = m * (2 * n + 1)
    rows = m * (3 * n + 16)
    return 8 * (2 * rows * cols + cols * cols)


def _extrapolate(history: list[tuple[int, float]], thr: float) -> float:
    """Terms needed for ``thr`` from the geometric rate of the last two attempts (inf if the
    error did not decrease)."""
    n, res = history[-1]
    if len(history) < 2:
        return n + 1.0
    n0, res0 = history[-2]
    if not (0 < res < res0):
        return float("inf")
    per_term = np.log(res / res0) / (n - n0)  # log of the rate per term (< 0)
    return float(1.1 * (n + np.log(thr / res) / per_term) + 2)


@dataclass(frozen=True)
class _Centres:
    """Multipole centres of the basis: the M holes (c_j, r_j), then the limit points of the
    pairs of circles that nearly touch (module docstring), each with the distance ``delta``
    to its hole's circle as radius and the index of its hole."""

    c: CArray
    r: FArray
    hole: IArray
    m: int

    @classmethod
    def of(cls, domain: CircleDomain) -> _Centres:
        c, r = domain.centers, domain.radii
        m = c.size
        # the limit point in hole j of the pair (j, k) (k = m: the outer circle) is the fixed
        # point of the composition of the two reflections, reached by iterating them
        j, k = (a.ravel() for a in np.meshgrid(np.arange(m), np.arange(m + 1), indexing="ij"))
        keep = j != k
        j, k = j[keep], k[keep]
        cj, rj = c[j], r[j]
        outer = k == m
        ck = np.where(outer, 0, c[np.minimum(k, m - 1)]) if m else np.zeros(0, complex)
        rk = np.where(outer, 1.0, r[np.minimum(k, m - 1)]) if m else np.zeros(0)
        z = cj.copy()
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(LIMIT_ITER):
                z = ck + rk**2 / np.conj(z - ck)  # in circle k (the unit circle: 1/conj(z))
                z = cj + rj**2 / np.conj(z - cj)  # back in circle j
        rate = np.abs(z - cj) / rj
        near = np.isfinite(z) & (rate > LIMIT_RATE) & (rate < 1)
        return cls(
            np.concatenate([c, z[near]]),
            np.concatenate([r, (rj * (1 - rate))[near]]),
            np.concatenate([np.arange(m), j[near]]).astype(np.intp),
            m,
        )


def _boundary_points(cen: _Centres, p: int, offset: float) -> CArray:
    """``p`` points per centre on its hole's circle (none on the outer circle): equispaced
    for a hole; for a limit point at distance ``delta`` inside circle (c, r), the image of
    equispaced points under the disk automorphism ``(e + a)/(1 + conj(a) e)``, ``|a| = (r -
    delta)/(r + delta)`` towards it, which packs them ``r/delta`` times denser next to it
    (where its terms ``(delta/(w - lambda))^k`` live)."""
    e = np.exp(2j * np.pi * (np.arange(p) + offset) / p)
    hc, hr = cen.c[cen.hole], cen.r[cen.hole]
    t = np.where(np.arange(cen.c.size) < cen.m, 0.0, (hr - cen.r) / (hr + cen.r))
    with np.errstate(invalid="ignore"):
        a = t * np.exp(1j * np.angle(cen.c - hc))
    mob = (e[None, :] + a[:, None]) / (1.0 + np.conj(a)[:, None] * e[None, :])
    return np.asarray((hc[:, None] + hr[:, None] * mob).ravel())


def _variables(cen: _Centres, z: CArray) -> tuple[CArray, CArray, CArray, CArray]:
    """``(u, v, w - c, 1 - conj(c) w)``, each (P, K): ``u_j = r_j / (w - c_j)`` and its
    reflection in the unit circle ``v_j = r_j w / (1 - conj(c_j) w)`` (module docstring)."""
    zz = z[:, None]
    d = zz - cen.c
    q = 1.0 - np.conj(cen.c) * zz
    return cen.r / d, cen.r * zz / q, d, q


def _design(cen: _Centres, z: CArray, n: int) -> FArray:
    """Real design matrix of ``S``, columns in the order of :meth:`GreenFunction._unpack`:
    ``L_j`` (M), ``Re(u_j^k - v_j^k)`` (M n), ``Im(u_j^k + v_j^k)`` (M n); with
    ``B = a - i b`` these are the columns of ``a`` and ``b`` in ``Re(B u^k - conj(B) v^k)``."""
    u, v, d, q = _variables(cen, z)
    k = np.arange(1, n + 1)
    un = u[:, :, None] ** k  # (P, M, n)
    vn = v[:, :, None] ** k
    return np.column_stack(
        [
            np.log(np.abs(d / q)),
            (un - vn).real.reshape(z.size, u.shape[1] * n),
            (un + vn).imag.reshape(z.size, u.shape[1] * n),
        ]
    )


def _disk_green(z: CArray, pole: complex) -> FArray:
    """``G_0 = log|M|``, ``M = (z - p)/(1 - conj(p) z)``, to relative accuracy everywhere: near
    the unit circle from ``|M|^2 = 1 + t``, ``t = -(1 - |z|^2)(1 - |p|^2)/|1 - conj(p) z|^2``
    (the Moebius identity, Ahlfors, Complex Analysis, ch. 1 sec. 3.5) without cancellation,
    near the pole (``t < -1/2``) from ``|z - p|/|1 - conj(p) z|`` itself, where ``1 + t``
    would keep only the absolute rounding of 1 (phi at the goal then differed by 10 ulps
    of 1 between a batch and one robot)."""
    q = 1.0 - np.conj(pole) * z
    one_minus = (1.0 - np.abs(z)) * (1.0 + np.abs(z)) * (1.0 - abs(pole)) * (1.0 + abs(pole))
    t = -one_minus / (q * q.conjugate()).real
    with np.errstate(divide="ignore", invalid="ignore"):
        near = np.log(np.abs(z - pole) / np.abs(q))
        return np.asarray(np.where(t < -0.5, near, 0.5 * np.log1p(t)), dtype=np.float64)


class _OnePoint(NamedTuple):
    """``(G, h, grad H)`` of :meth:`GreenFunction._eval` at one point: its operations in its
    order on short vectors, in ~35 numpy calls instead of ~60 on (1, K) arrays with their
    errstate guard and the domain test (the single-robot control step).

    Every denominator is ``ga w + de``, in one (2, T) array: the holes' ``d = w - c_j`` and
    ``q = 1 - conj(c_j) w`` (the series variables are ``u = r / d``, ``v = r w / q``), the
    image points' ``w - p_i`` and ``1 - conj(p_i) w``, and ``w`` and the pole's
    ``1 - conj(w_d) w``; each entry is bitwise the batch's (``1 w + (-c) = w - c``).  Every
    complex product, quotient and modulus is numpy's as in the batch: numpy's complex
    multiply may fuse and its modulus is its own hypot, so Python's scalars differ by an ulp,
    which ``G_0`` magnifies 30-fold where ``|M| << 1``, and the harmonic gradient's
    cancellation 100-fold (tests/test_single_robot_path.py, test_fleet_step.py).
    """

    ga: CArray  # (2, T) with den = ga w + de: rows (d, w - p, w) and (q, 1 - conj(p) w, q_d)
    de: CArray
    al: CArray  # (2, K): the series variables (u, v) = (al w + be) / den[:, :K]
    be: CArray
    r: FArray
    rm: FArray  # radii of the M holes (the first M centres)
    cf: CArray
    cd: CArray
    start: CArray  # (2K, n + 1) of ones
    c: CArray  # centres, then image points (for the gradients of the logarithms)
    b: FArray
    sg: FArray
    pole: complex

    @classmethod
    def of(
        cls, cen: _Centres, images: _Images, cf: CArray, cd: CArray, b: FArray, pole: complex
    ) -> _OnePoint:
        c, r, p = cen.c, cen.r, images.points
        one, zero = np.ones(c.size, complex), np.zeros(c.size, complex)
        ones = np.ones(p.size, complex)
        return cls(
            ga=np.array([np.r_[one, ones, 1.0], np.r_[-np.conj(c), -np.conj(p), -np.conj(pole)]]),
            de=np.array([np.r_[-c, -p, 0.0], np.r_[one, ones, 1.0]]),
            al=np.array([zero, r + 0j]),
            be=np.array([r + 0j, zero]),
            r=r,
            rm=r[: cen.m],
            cf=cf,
            cd=cd,
            start=np.ones(cf.shape, dtype=np.complex128),
            c=np.r_[c, p],
            b=b,
            sg=images.signs,
            pole=pole,
        )

    def parts(self, w: complex) -> tuple[float, float, complex] | None:
        """``(G, h, grad H)`` at ``w``; None outside the closed domain (as
        :meth:`CircleDomain.clearance`: ``1 - |w|`` and ``|w - c_j| - r_j``, numpy's moduli);
        the operations of ``_eval`` in its order, on the rows of one (2, T) array."""
        k, m = self.r.size, self.rm.size
        den = self.ga * w + self.de  # (d, w - p, w), (q, 1 - conj(p) w, 1 - conj(w_d) w)
        size = np.abs(den[:, -1]).tolist()  # |w|, |1 - conj(w_d) w|
        clearance = 1.0 - size[0]
        if m:
            clearance = min(clearance, float(np.minimum.reduce(np.abs(den[0, :m]) - self.rm)))
        if not clearance >= 0:  # outside (or NaN)
            return None
        x = (self.al * w + self.be) / den[:, :k]  # u, v
        xpow = self.start.copy()
        xpow[:, 1:] = x.reshape(-1, 1)
        xpow.cumprod(axis=1, out=xpow)
        u, q, r = x[0], den[1, :k], self.r
        dxdw = np.concatenate([-(u * u) / r, r / (q * q)])
        f = np.einsum("pjk,jk->p", xpow[None], self.cf)
        fp = np.einsum("pjk,jk,pj->p", xpow[None], self.cd, dxdw[None])
        top, bot = den[0, :-1], den[1, :-1]  # (d, w - p), (q, 1 - conj(p) w)
        logs = np.log(np.abs(top / bot))
        grads = 1.0 / np.conj(top) + self.c / np.conj(bot)
        s = float(f.real[0] + logs[:k] @ self.b)
        gh = complex(np.conj(fp[0]) + grads[:k] @ self.b)
        if self.sg.size:  # H = S - sum_i s_i L(w; p_i), as _Images.value and .gradient
            s = s - float(logs[k:] @ self.sg)
            gh = gh - complex(grads[k:] @ self.sg)
        # G_0 as _disk_green, h = log|1 - conj(w_d) w| + S
        qd = den[1, -1:]
        qq = float((qd * qd.conjugate()).real[0])
        aw, ap = size[0], abs(self.pole)
        t = -((1.0 - aw) * (1.0 + aw) * (1.0 - ap) * (1.0 + ap)) / qq
        if t < -0.5:  # near the pole: |w - p|/|q| itself (as _disk_green)
            near = np.abs(np.array([w - self.pole, qd[0]]))
            with np.errstate(divide="ignore"):
                g0 = float(np.log(near[0] / near[1]))
        elif t > -1.0:
            g0 = 0.5 * float(np.log1p(np.array(t)))
        else:  # NaN
            g0 = math.nan
        return g0 - s, float(np.log(np.array(size[1]))) + s, gh


class _Images(NamedTuple):
    """Image pairs ``sum_i s_i L(w; p_i)`` of one pole (module docstring)."""

    points: CArray
    signs: FArray

    def value(self, z: CArray) -> FArray:
        if self.points.size == 0:
            return np.zeros(z.shape)
        zz = z[:, None]
        p = self.points
        return np.asarray(np.log(np.abs((zz - p) / (1.0 - np.conj(p) * zz))) @ self.signs)

    def gradient(self, z: CArray) -> CArray:
        """grad L(w; p) = 1/conj(w - p) + p/conj(1 - conj(p) w)."""
        if self.points.size == 0:
            return np.zeros(z.shape, dtype=np.complex128)
        zz = z[:, None]
        p = self.points
        return np.asarray((1.0 / np.conj(zz - p) + p / np.conj(1.0 - np.conj(p) * zz)) @ self.signs)


def _image_charges(domain: CircleDomain, pole: complex) -> tuple[_Images, tuple[int, ...]]:
    """The image pairs of the pole and the holes they lie in (module docstring)."""
    c, r = domain.centers, domain.radii
    pts: list[complex] = []
    sgn: list[float] = []
    front: list[tuple[complex, float]] = [(pole, 1.0)]
    if pole != 0:
        front.append((1.0 / np.conj(pole), -1.0))
    holes: set[int] = set()
    for _ in range(IMAGE_DEPTH):
        new: list[tuple[complex, float]] = []
        for x, sig in front:
            d = np.abs(x - c)
            for j in np.flatnonzero((d < NEAR * r) & (d > r)):
                xs = complex(c[j] + r[j] ** 2 / np.conj(x - c[j]))
                pts.append(xs)
                sgn.append(-sig)
                holes.add(int(j))
                new += [(xs, -sig), (1.0 / np.conj(xs), sig)]
        front = new
        if not front or len(pts) >= IMAGE_LIMIT:
            break
    k = min(len(pts), IMAGE_LIMIT)
    im = _Images(np.asarray(pts[:k], dtype=np.complex128), np.asarray(sgn[:k]))
    return im, tuple(sorted(holes))


def _data(z: CArray, pole: complex, images: _Images) -> FArray:
    """Boundary data of ``S``: ``G_0 + sum_i s_i L(z; p_i)`` (0 on the outer circle)."""
    return np.asarray(_disk_green(z, pole) + images.value(z), dtype=np.float64)


class GreenFunction:
    """The Green's function ``G`` of a circle domain for one pole (and ``h = log|w-w_d| - G``).

    Parameters
    ----------
    domain : CircleDomain
    pole : complex, inside the domain.
    tol : target boundary error of the fitted series, relative to the size of its data.
    max_terms : upper bound of the number of Laurent terms per circle.
    basis : the map's :class:`GreenBasis` (default: the shared one of ``domain``).
    samples : circle-domain points where ``G`` must be accurate relative to its size
        (:meth:`GreenBasis.fit`), e.g. the images of free-space points.

    Raises
    ------
    NavigationError
        if the series does not reach ``tol`` with ``max_terms`` terms.
    """

    def __init__(
        self,
        domain: CircleDomain,
        pole: complex,
        *,
        tol: float = 1e-10,
        max_terms: int = DEFAULT_MAX_TERMS,
        basis: GreenBasis | None = None,
        samples: CArray | None = None,
    ) -> None:
        self.domain = domain
        self.pole = complex(pole)
        if basis is None:
            basis = GreenBasis.for_domain(domain, tol=tol, max_terms=max_terms)
        self.basis = basis
        coef, self._images, self.diagnostics = basis.fit(self.pole, samples)
        self._n = self.diagnostics.n_terms
        self._unpack(coef, self._n)

    def _unpack(self, coef: FArray, n: int) -> None:
        self._cen = self.basis.centres
        m = self._cen.c.size
        self._b = coef[:m]
        # a Re(X) + b Im(X) == Re((a - i b) X): B_jk = a_jk - i b_jk
        big_b = coef[m : m + m * n].reshape(m, n) - 1j * coef[m + m * n :].reshape(m, n)
        k = np.arange(1, n + 1)
        # F = sum_k (B u^k - conj(B) v^k); per variable X in (u_1..u_M, v_1..v_M): the
        # coefficients of X^0..X^n in F and in dF/dX
        cx = np.concatenate([big_b, -np.conj(big_b)], axis=0)  # (2M, n)
        self._cf = np.zeros((2 * m, n + 1), dtype=np.complex128)
        self._cf[:, 1:] = cx
        self._cd = np.zeros((2 * m, n + 1), dtype=np.complex128)
        self._cd[:, :-1] = k * cx
        self._rows: dict[tuple[int, int], CArray] = {}
        self._one = _OnePoint.of(self._cen, self._images, self._cf, self._cd, self._b, self.pole)

    def _row(self, n: int, n_img: int) -> CArray:
        """This function's row of :func:`_stacked_parts`: the series coefficients ``_cf``,
        ``_cd`` padded to ``n`` terms, ``b``, the pole, the image points and their signs
        padded to ``n_img`` (cached per shape: a fleet's step stacks the same rows again)."""
        row = self._rows.get((n, n_img))
        if row is None:
            pad = ((0, 0), (0, n - self._n))
            m = self._images.points.size
            row = np.concatenate(
                [
                    np.pad(self._cf, pad).ravel(),
                    np.pad(self._cd, pad).ravel(),
                    self._b,
                    [self.pole],
                    np.pad(self._images.points, (0, n_img - m)),
                    np.pad(self._images.signs, (0, n_img - m)),
                ]
            ).astype(np.complex128)
            if len(self._rows) >= 4:
                self._rows.clear()
            self._rows[(n, n_img)] = row
        return row

    def parts(self, w: ArrayLike) -> tuple[FArray, FArray, CArray]:
        """``(G, h, grad H)`` at ``w`` (same shape), ``H = S - sum_i s_i L(w; p_i)``, complex
        gradient ``dH/dw1 + i dH/dw2``; ``h = log|1 - conj(w_d) w| + H``."""
        w = np.asarray(w, dtype=np.complex128)
        flat = w.ravel()
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if flat.size <= _CHUNK:
                g, h, gh = self._eval(flat)
            else:
                parts = [self._eval(flat[i : i + _CHUNK]) for i in range(0, flat.size, _CHUNK)]
                g, h, gh = (np.concatenate([q[k] for q in parts]) for k in range(3))
        return g.reshape(w.shape), h.reshape(w.shape), gh.reshape(w.shape)

    def parts1(self, z: complex) -> tuple[float, float, complex]:
        """:meth:`parts` of one point as Python scalars: :meth:`_eval` on a 1-point array
        (the series sums of a batch, bitwise), without :meth:`parts`' reshaping and chunking;
        the control step's faster path is :meth:`_parts1`."""
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            g, h, gh = self._eval(np.array([complex(z)]))
        return float(g[0]), float(h[0]), complex(gh[0])

    def _parts1(self, z: complex) -> tuple[float, float, complex] | None:
        """:meth:`parts1` in ~35 numpy calls on short vectors (:class:`_OnePoint`); None
        outside the closed domain (where :meth:`parts1` has no meaning either)."""
        return self._one.parts(z)

    def h(self, w: ArrayLike) -> FArray:
        """``h = log|w - w_d| - G`` (harmonic, ``log|zeta - w_d|`` on the boundary)."""
        return self.parts(w)[1]

    def _eval(self, z: CArray) -> tuple[FArray, FArray, CArray]:
        # F = sum_j sum_k (B_jk u_j^k - conj(B_jk) v_j^k); S = Re F + sum_j b_j L_j;
        # u' = -u^2 / r, v' = r / (1 - conj(c) w)^2; for S = Re F, grad S = conj(F');
        # grad log|(w - c)/(1 - conj(c) w)| = 1/conj(w - c) + c/conj(1 - conj(c) w).
        s: FArray | float = 0.0
        grad_h: CArray | complex = 0j
        if self._cen.c.size:
            u, v, d, q = _variables(self._cen, z)
            x = np.concatenate([u, v], axis=1)  # (P, 2M)
            xpow = power_table(x, self._n)
            r = self._cen.r
            dxdw = np.concatenate([-(u * u) / r, r / (q * q)], axis=1)
            f = np.einsum("pjk,jk->p", xpow, self._cf)
            fp = np.einsum("pjk,jk,pj->p", xpow, self._cd, dxdw)
            s = f.real + np.log(np.abs(d / q)) @ self._b
            c = self._cen.c
            grad_h = np.conj(fp) + (1.0 / np.conj(d) + c / np.conj(q)) @ self._b
        if self._images.points.size:  # H = S - sum_i s_i L(w; p_i)
            s = s - self._images.value(z)
            grad_h = grad_h - self._images.gradient(z)
        g = _disk_green(z, self.pole) - s
        h = np.log(np.abs(1.0 - np.conj(self.pole) * z)) + s
        if not isinstance(grad_h, np.ndarray):  # no holes and no images: H = 0
            grad_h = np.zeros(z.shape, dtype=np.complex128)
        return g, h, grad_h


#: Complex entries of one stacked coefficient block (points x 2K x terms): bounds the memory
#: of :func:`stacked_parts` (about 3 such arrays live at once, 16 bytes each).
_STACK_ENTRIES = 1 << 20


def stacked_parts(greens: Sequence[GreenFunction], z: CArray) -> tuple[FArray, FArray, CArray]:
    """:meth:`GreenFunction.parts` of ``greens[i]`` at ``z[i]`` (1-D) in one vectorized pass:
    the greens share one basis (centres), so the powers ``u_j^k, v_j^k`` are the same
    functions of ``z`` and only the coefficients differ per point; they are stacked, zero
    padded to the longest series, with each pole's images (padding has weight 0)."""
    per_point = 2 * greens[0]._cen.c.size * (max(g._n for g in greens) + 1)
    step = max(1, _STACK_ENTRIES // max(per_point, 1))
    if z.size <= step:
        return _stacked_parts(greens, z)
    parts = [_stacked_parts(greens[i : i + step], z[i : i + step]) for i in range(0, z.size, step)]
    g, h, gh = (np.concatenate([q[j] for q in parts]) for j in range(3))
    return g, h, gh


def _stacked_parts(greens: Sequence[GreenFunction], z: CArray) -> tuple[FArray, FArray, CArray]:
    cen = greens[0]._cen
    p = z.size
    n = max(g._n for g in greens)
    k = cen.c.size
    n_img = max(g._images.points.size for g in greens)
    # one row per point (its goal's coefficients, zero padded), stacked in one call
    table = np.stack([g._row(n, n_img) for g in greens])
    a, e = 2 * k * (n + 1), 4 * k * (n + 1)
    cf = table[:, :a].reshape(p, 2 * k, n + 1)
    cd = table[:, a:e].reshape(p, 2 * k, n + 1)
    b = table[:, e : e + k].real
    pole = table[:, e + k]
    ip = table[:, e + k + 1 : e + k + 1 + n_img]  # image points, 0 where padded
    isg = table[:, e + k + 1 + n_img :].real  # their signs, 0 where padded
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        s = np.zeros(p, dtype=np.float64)
        grad_h = np.zeros(p, dtype=np.complex128)
        if k:  # the same sums as GreenFunction._eval, with per-point coefficients
            u, v, d, q = _variables(cen, z)
            x = np.concatenate([u, v], axis=1)
            xpow = power_table(x, n)
            r = cen.r
            dxdw = np.concatenate([-(u * u) / r, r / (q * q)], axis=1)
            f = np.einsum("pjk,pjk->p", xpow, cf)
            fp = np.einsum("pjk,pjk,pj->p", xpow, cd, dxdw)
            s = f.real + np.einsum("pj,pj->p", np.log(np.abs(d / q)), b)
            grad_h = np.conj(fp) + np.einsum("pj,pj->p", 1.0 / np.conj(d) + cen.c / np.conj(q), b)
        if n_img:  # H = S - sum_i s_i L(w; p_i) (as _Images.value/.gradient, padded)
            zz = z[:, None]
            used = isg != 0
            lv = np.where(used, np.log(np.abs((zz - ip) / (1.0 - np.conj(ip) * zz))), 0.0)
            gv = np.where(used, 1.0 / np.conj(zz - ip) + ip / np.conj(1.0 - np.conj(ip) * zz), 0)
            s = s - np.einsum("pi,pi->p", lv, isg)
            grad_h = grad_h - np.einsum("pi,pi->p", gv, isg)
        big_g = _disk_green(z, pole) - s  # type: ignore[arg-type]
        h = np.log(np.abs(1.0 - np.conj(pole) * z)) + s
    return big_g, h, grad_h


def _exp(x: float) -> float:
    """``e^x`` in Python floats, inf on overflow (as numpy with ``over="ignore"``)."""
    try:
        return math.exp(x)
    except OverflowError:
        return math.inf


class HarmonicNavigation(NavigationFunction):
    """Harmonic navigation function ``phi_H = exp(2 G)`` (docs/METHOD.md section 3).

    ``diagnostics`` holds the :class:`GreenDiagnostics` of the series.  ``tol`` bounds the
    boundary error of the series, and so the error of ``G`` everywhere; with ``samples``
    (points where robots drive) also relative to ``min |G|`` there (:meth:`GreenBasis.fit`).
    The map's factorization is shared through :meth:`GreenBasis.for_domain` (or ``basis``).
    """

    name = "harmonic"

    def __init__(
        self,
        domain: CircleDomain,
        goal: complex,
        *,
        tol: float = 1e-10,
        basis: GreenBasis | None = None,
        samples: ArrayLike | None = None,
    ) -> None:
        super().__init__(domain, goal)
        self.tol = tol
        self.samples = None if samples is None else np.asarray(samples, dtype=np.complex128)
        self.green = GreenFunction(domain, self.goal, tol=tol, basis=basis, samples=self.samples)
        self.diagnostics = self.green.diagnostics

    def value_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        w = np.asarray(w, dtype=np.complex128)
        big_g, h, grad_h = self.green.parts(w)
        wd = self.goal
        e = w - wd
        g = (e * e.conjugate()).real
        with np.errstate(over="ignore", invalid="ignore"):
            phi = np.exp(2.0 * big_g)
            q = 1.0 - np.conj(wd) * w
            grad = 2.0 * np.exp(-2.0 * h) * (e * np.conj((1.0 - abs(wd) ** 2) / q) - g * grad_h)
        phi = np.where(g == 0, 0.0, phi)
        outside = ~(self.domain.clearance(w) >= 0)
        if np.any(outside):
            phi = np.where(outside, np.nan, phi)
            grad = np.where(outside, np.nan + 0j, grad)
        return phi, grad

    def value_and_gradient1(self, w: complex) -> tuple[float, complex]:
        parts = self.green._parts1(w)
        if parts is None:  # outside the closed domain (or NaN)
            return np.nan, complex(np.nan, 0.0)
        big_g, h, grad_h = parts
        wd = self.goal
        e = w - wd
        g = (e * e.conjugate()).real
        if g == 0:
            return 0.0, 0j  # at the goal (the batch formula gives exactly 0 there)
        phi = _exp(2.0 * big_g)
        # The gradient with numpy's complex operations on one-element arrays, as the batch
        # and the fleet's stacked step form it: Python's complex multiply and divide differ
        # from numpy's by an ulp, which the cancellation of the two terms amplifies ~100-fold
        # (one robot's step against the fleet step on the same map values, median relative:
        # 4.7e-15 before, 1.3e-14 on a map solved with second sums; now 2.2e-16 / 2.1e-16;
        # the two formulas on the same parts 4.5e-15 / 2.3e-15 apart:
        # bench/results/second_sums_fleet_step.json, tests/test_fleet_step.py).
        wa, wda, gha = np.array([w]), np.array([wd]), np.array([grad_h])
        ea = wa - wda
        with np.errstate(over="ignore", invalid="ignore"):
            q = 1.0 - np.conj(wda) * wa
            ga = (
                2.0
                * np.exp(-2.0 * np.array([h]))
                * (ea * np.conj((1.0 - np.abs(wda) ** 2) / q) - g * gha)
            )
        return phi, complex(ga[0])

    @classmethod
    def value_and_gradient_stacked(
        cls, fns: Sequence[NavigationFunction], w: CArray
    ) -> tuple[FArray, CArray]:
        """:meth:`value_and_gradient` with a goal per point, all series in one pass
        (:func:`stacked_parts`) when they share one basis, i.e. one map."""
        hs = [f for f in fns if isinstance(f, HarmonicNavigation)]
        if len(hs) != len(fns) or len({id(f.green._cen) for f in hs}) > 1:
            return super().value_and_gradient_stacked(fns, w)
        w = np.asarray(w, dtype=np.complex128)
        big_g, h, grad_h = stacked_parts([f.green for f in hs], w)
        wd = np.array([f.goal for f in hs], dtype=np.complex128)
        e = w - wd
        g = (e * e.conjugate()).real
        with np.errstate(over="ignore", invalid="ignore"):
            phi = np.exp(2.0 * big_g)
            q = 1.0 - np.conj(wd) * w
            grad = 2.0 * np.exp(-2.0 * h) * (e * np.conj((1.0 - np.abs(wd) ** 2) / q) - g * grad_h)
        phi = np.where(g == 0, 0.0, phi)
        outside = ~(hs[0].domain.clearance(w) >= 0)
        if np.any(outside):
            phi = np.where(outside, np.nan, phi)
            grad = np.where(outside, np.nan + 0j, grad)
        return np.asarray(phi, dtype=np.float64), np.asarray(grad, dtype=np.complex128)

    def with_goal(self, goal: complex) -> HarmonicNavigation:
        return HarmonicNavigation(
            self.domain, goal, tol=self.tol, basis=self.green.basis, samples=self.samples
        )


def moebius_domain(domain: CircleDomain, a: complex) -> CircleDomain:
    """The circle domain ``m(domain)`` for the disk automorphism ``m(w) = (w - a)/(1 -
    conj(a) w)`` (exact: the diameter of each circle on the line through its centre and the
    pole ``1/conj(a)`` is orthogonal to it, so its image, a line through the image of the
    pole at infinity, is a diameter of the image circle [5]_)."""
    c, r = domain.centers, domain.radii
    if a == 0:
        return domain
    u = 1.0 / np.conj(a) - c
    u = u / np.abs(u)
    p1, p2 = _moebius(c + r * u, a), _moebius(c - r * u, a)
    return CircleDomain(0.5 * (p1 + p2), 0.5 * np.abs(p1 - p2))


def _moebius(w: ArrayLike, a: complex) -> CArray:
    w = np.asarray(w, dtype=np.complex128)
    return np.asarray((w - a) / (1.0 - np.conj(a) * w), dtype=np.complex128)


def conformal_centre(domain: CircleDomain, iters: int = 50) -> complex:
    """A point ``a`` whose automorphism ``m_a`` puts the radius-weighted centroid of the image
    circles at 0 (fixed-point iteration, composing ``m_c o m_a = rotation o m_b`` with
    ``b = (c + a)/(1 + conj(a) c)``): circles crowded near one point of the unit circle (the
    anchor at one end of a long map) are spread over the disk."""
    a = 0j
    for _ in range(iters):
        d = moebius_domain(domain, a)
        c = complex(np.sum(d.radii * d.centers) / np.sum(d.radii)) if d.radii.size else 0j
        if abs(c) < 1e-9:
            break
        a = (c + a) / (1.0 + np.conj(a) * c)
    return complex(a)


class RecentredHarmonic(NavigationFunction):
    """:class:`HarmonicNavigation` fitted on the Moebius image ``m_a(domain)`` that spreads
    crowded circles (:func:`conformal_centre`), by the conformal invariance of the Green's
    function [4]_: ``G_D(w, w_d) = G_{m(D)}(m(w), m(w_d))``, so ``phi(w) = phi'(m(w))`` and
    ``grad phi(w) = grad phi'(m(w)) conj(m'(w))`` with ``m'(w) = (1 - |a|^2)/(1 - conj(a)
    w)^2``. The convergence check is the image's own (residual on its circles, accuracy at
    the images of the samples): G is the same function, so the bound carries over.

    Used when the plain fit does not converge (:func:`confnav.navigation.factory.make_navfn`):
    on the README's warehouse shrunk by 0.32 m, 3 of 10 goals failed at 64 terms per circle
    (boundary error 1e-12..4e-12, needed 2.4e-13..6.3e-13); on the image all converged with 48.

    .. [5] T. Needham, *Visual Complex Analysis*, Oxford 1997, ch. 3 (Moebius maps send
       circles to circles and preserve angles).
    """

    name = "harmonic"

    def __init__(
        self,
        domain: CircleDomain,
        goal: complex,
        *,
        tol: float = 1e-10,
        samples: ArrayLike | None = None,
        centre: complex | None = None,
    ) -> None:
        super().__init__(domain, goal)
        self.tol = tol
        self.centre = conformal_centre(domain) if centre is None else complex(centre)
        self.image = moebius_domain(domain, self.centre)
        self.samples = None if samples is None else np.asarray(samples, dtype=np.complex128)
        img_samples = None if self.samples is None else _moebius(self.samples, self.centre)
        self.inner = HarmonicNavigation(
            self.image,
            complex(_moebius(self.goal, self.centre)),
            tol=tol,
            basis=GreenBasis.for_domain(self.image, tol=tol),
            samples=img_samples,
        )
        self.diagnostics = self.inner.diagnostics

    def value_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        w = np.asarray(w, dtype=np.complex128)
        a = self.centre
        phi, grad = self.inner.value_and_gradient(_moebius(w, a))
        dm = (1.0 - abs(a) ** 2) / (1.0 - np.conj(a) * w) ** 2
        return phi, np.asarray(grad * np.conj(dm), dtype=np.complex128)

    def value_and_gradient1(self, w: complex) -> tuple[float, complex]:
        phi, grad = self.value_and_gradient(np.array([w]))
        return float(phi[0]), complex(grad[0])

    def with_goal(self, goal: complex) -> RecentredHarmonic:
        return RecentredHarmonic(
            self.domain, goal, tol=self.tol, samples=self.samples, centre=self.centre
        )
