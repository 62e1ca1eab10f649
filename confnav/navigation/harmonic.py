"""Harmonic navigation function from the Green's function of a circle domain.

``G(w) = log|w - w_d| - h(w)`` with ``h`` harmonic in the circle domain and
``h = log|zeta - w_d|`` on every boundary circle, so ``G = 0`` on the boundary.  ``G`` is
split into an exact part and a fitted series (logarithmic conjugation / Laurent expansion in
each hole [1]_ [2]_):

    G = G_0 - sum_{j near} I_j - S,
    G_0(w) = log|(w - w_d) / (1 - conj(w_d) w)|              (Green's function of the disk),
    I_j(w) = log|(w - p_j) / (1 - conj(p_j) w)|,  p_j = c_j + r_j^2 / conj(w_d - c_j),
    S(w)   = a_0 + Re sum_n a_n w^n + sum_j [ b_j log|w - c_j| + Re sum_n b_jn (r_j/(w-c_j))^n ].

``G_0`` and ``I_j`` vanish on the outer circle (so ``S`` does too); ``I_j`` is the image charge
of the pole in a circle the goal is near (exact for one circle): it takes the near-singular
part of the data.  ``S`` is fitted by least squares to ``G_0 - sum I_j`` on equispaced
collocation points of every circle.  Why this split: when the goal lies in a pocket (its image
close to a circle), ``G`` is tiny (1e-11 measured with the goal in a charging alcove) over
most of the domain; ``G_0`` is evaluated without cancellation
(``1 - |M(w)|^2 = (1-|w|^2)(1-|w_d|^2)/|1 - conj(w_d) w|^2``) and the data of ``S`` is as
small as ``G`` there, so the fit's *relative* accuracy carries over to ``G``, its gradient
and ``1 - phi``.  (With the boundary data ``log|zeta - w_d|`` of size 1, as before, the fit
error 1e-10 swamped ``G`` and a robot followed it into a wall.)

**Cost bounded per map.**  The least-squares matrix depends on the circle domain only, not on
the goal (the boundary data is linear in it, DESIGN.md section 3): :class:`GreenBasis` builds
it once per map, scales its columns, and stores its pseudo-inverse from a QR factorization;
a new goal is then one matrix-vector product plus a residual check on points between the
collocation points.  The number of terms per circle grows on a ladder (a finer basis is
factored only when a goal needs it, and kept for the next goals); a fit that misses ``tol``
with ``max_terms`` raises :class:`NavigationError` (the controller then falls back to
Koditschek-Rimon with automatic k and says so).

``phi_H = exp(2 G)`` is 1 on every boundary circle, has a single minimum (at w_d) and exactly
M saddles, and needs no tuning.  Its gradient is evaluated without the pole:
``grad phi_H = 2 e^{-2h} ((w - w_d) conj((1 - |w_d|^2)/(1 - conj(w_d) w)) - |w - w_d|^2
grad H)`` with ``H = S + sum I_j`` (``grad G_0`` in closed form, no cancellation).

References
----------
.. [1] S. Axler, "Harmonic functions from a complex analysis viewpoint", Amer. Math. Monthly
   93 (1986) 246-258 (logarithmic conjugation theorem).
.. [2] L. N. Trefethen, "Series solution of Laplace problems", ANZIAM J. 60 (2018) 1-26.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from confnav.errors import NavigationError
from confnav.navigation.navfn import CircleDomain, NavigationFunction
from confnav.types import CArray, FArray

__all__ = ["GreenBasis", "GreenDiagnostics", "GreenFunction", "HarmonicNavigation"]


_CHUNK = 4096
#: Terms per circle tried in turn (a goal that needs more moves the map's basis up the ladder).
TERM_LADDER: tuple[int, ...] = (12, 24, 36, 48, 64, 96, 128, 160, 192, 256)
#: Default cap of the terms per circle: bounds the per-map cost (normal equations of size
#: ~2 n (M + 1)); a goal that needs more gets the Koditschek-Rimon fallback of the controller.
DEFAULT_MAX_TERMS = 128
#: Memory one factorization may take (design, check and Cholesky matrices); caps the terms
#: per circle for many obstacles (issue 9: <= 1 GB with 20 obstacles).
MEMORY_BUDGET = 768 << 20
#: The pole gets an image charge in circle j when ``|w_d - c_j| < NEAR * r_j``.
NEAR = 3.0
#: Accuracy of G needed where robots drive, relative to the smallest |G| at the sample points
#: (the fit's error in G is at most its boundary residual: maximum principle).
REL_TOL = 1e-3
#: Below this boundary error the fit is rounding (data of size 1, double precision).
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
    image charge was used; basis_seconds: time spent factoring for this fit (0: reused).
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


class _Level:
    """One rung of the ladder: the scaled design matrix, the Cholesky factor of its normal
    equations (the basis is well conditioned: each family is orthogonal on its own circle and
    the near-singular parts are taken out by the exact terms) and the check matrix."""

    def __init__(self, domain: CircleDomain, n: int) -> None:
        self.n = n
        self.p = 3 * n + 16
        self.zeta = _boundary_points(domain, self.p, 0.0)
        self.zeta_check = _boundary_points(domain, self.p, 0.5)
        a = _design(domain, self.zeta, n)
        self.scale = np.linalg.norm(a, axis=0)
        self.scale[self.scale == 0] = 1.0
        a /= self.scale
        self.at = np.ascontiguousarray(a.T)
        gram = self.at @ a
        self.chol = scipy.linalg.cho_factor(gram, check_finite=False)
        self.check = _design(domain, self.zeta_check, n)

    def solve(self, rhs: FArray) -> FArray:
        """Least-squares coefficients for boundary data ``rhs`` (one back-substitution)."""
        coef = scipy.linalg.cho_solve(self.chol, self.at @ rhs, check_finite=False)
        return np.asarray(coef / self.scale, dtype=np.float64)

    @property
    def nbytes(self) -> int:
        return int(self.at.nbytes + self.chol[0].nbytes + self.check.nbytes)


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
        fits = [n for n in TERM_LADDER if _level_bytes(domain.n_obstacles, n) <= MEMORY_BUDGET]
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
        """Factor the levels the given goals (default: the domain's centre 0 and a point
        between each circle and its neighbour) need; later goals then cost one solve."""
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
        self._levels = {}  # only one factorization in memory at a time
        t0 = time.perf_counter()
        lv = _Level(self.domain, n)
        self._levels = {n: lv}
        return lv, time.perf_counter() - t0

    def fit(
        self, pole: complex, samples: CArray | None = None
    ) -> tuple[FArray, CArray, GreenDiagnostics]:
        """(series coefficients, image points, diagnostics) for a pole; raises
        :class:`NavigationError` if ``max_terms`` terms do not reach the tolerance.

        The boundary residual must be below ``tol`` and below ``REL_TOL * min |G|`` over
        ``samples`` (circle-domain points where robots drive): by the maximum principle the
        error of ``G`` anywhere is at most the boundary residual, so where the goal sits in a
        pocket and ``G`` is 1e-11 over the room the fit must be that much finer (or fail).
        """
        c, r = self.domain.centers, self.domain.radii
        near = np.flatnonzero(np.abs(pole - c) < NEAR * r)
        images = c[near] + r[near] ** 2 / np.conj(pole - c[near])
        history: list[tuple[int, float]] = []
        spent = 0.0
        ladder = [n for n in TERM_LADDER if n <= self.max_terms] or [TERM_LADDER[0]]
        with self._lock:
            i = min(self._start, len(ladder) - 1)
            while True:
                lv, dt = self._level(ladder[i])
                spent += dt
                coef = lv.solve(_data(lv.zeta, pole, images))
                data_c = _data(lv.zeta_check, pole, images)
                res = float(np.max(np.abs(lv.check @ coef - data_c), initial=0.0))
                thr = self.tol
                if samples is not None and samples.size:
                    g = _data(samples, pole, images) - _design(self.domain, samples, lv.n) @ coef
                    gmin = float(np.min(np.abs(g[np.isfinite(g)]), initial=np.inf))
                    thr = max(min(thr, REL_TOL * gmin), FLOOR)
                history.append((lv.n, res))
                ok = res <= thr
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
            lv.n, lv.p, res, self.tol, ok, tuple(history), thr, tuple(int(j) for j in near), spent
        )
        if not ok:
            raise NavigationError(
                f"Green's function series did not converge: boundary error {res:.2e} "
                f"(needed {thr:.1e}) with {lv.n} terms per circle (circles too close to "
                "each other or to the goal?)"
            )
        return coef, images, diag


def _level_bytes(m: int, n: int) -> int:
    """Bytes of a :class:`_Level` with ``n`` terms per circle and ``m`` holes."""
    cols = 1 + 2 * n * (m + 1) + m
    rows = (m + 1) * (3 * n + 16)
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


def _boundary_points(domain: CircleDomain, p: int, offset: float) -> CArray:
    e = np.exp(2j * np.pi * (np.arange(p) + offset) / p)
    parts = [e] + [cj + rj * e for cj, rj in zip(domain.centers, domain.radii, strict=True)]
    return np.concatenate(parts)


def _design(domain: CircleDomain, z: CArray, n: int) -> FArray:
    """Real design matrix of ``S``, columns in the order of :meth:`GreenFunction._unpack`."""
    c, r = domain.centers, domain.radii
    cols: list[FArray] = [np.ones(z.shape)]
    wp = z[:, None] ** np.arange(1, n + 1)
    cols += [wp.real, wp.imag]
    if c.size:
        d = z[:, None] - c  # (P, M)
        cols.append(np.log(np.abs(d)))
        u = (r / d)[:, :, None] ** np.arange(1, n + 1)  # (P, M, n)
        cols += [u.real.reshape(z.size, -1), u.imag.reshape(z.size, -1)]
    return np.column_stack([x[:, None] if x.ndim == 1 else x for x in cols])


def _disk_green(z: CArray, pole: complex) -> FArray:
    """``G_0 = log|(z - p)/(1 - conj(p) z)|`` without cancellation near the unit circle:
    ``|M|^2 = 1 - (1 - |z|^2)(1 - |p|^2)/|1 - conj(p) z|^2`` (Moebius identity)."""
    q = 1.0 - np.conj(pole) * z
    one_minus = (1.0 - np.abs(z)) * (1.0 + np.abs(z)) * (1.0 - abs(pole)) * (1.0 + abs(pole))
    with np.errstate(divide="ignore"):
        return np.asarray(0.5 * np.log1p(-one_minus / (q * q.conjugate()).real), dtype=np.float64)


def _image_terms(z: CArray, images: CArray) -> FArray:
    """``sum_j I_j(z) = sum_j log|(z - p_j)/(1 - conj(p_j) z)|``."""
    if images.size == 0:
        return np.zeros(z.shape)
    zz = z[:, None]
    return np.asarray(
        np.log(np.abs((zz - images) / (1.0 - np.conj(images) * zz))).sum(axis=1),
        dtype=np.float64,
    )


def _data(z: CArray, pole: complex, images: CArray) -> FArray:
    """Boundary data of ``S``: ``G_0 - sum_j I_j`` (0 on the outer circle: set exactly)."""
    d = _disk_green(z, pole) - _image_terms(z, images)
    return np.asarray(np.where(np.abs(z) == 1.0, 0.0, d), dtype=np.float64)


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
        m = self.domain.n_obstacles
        i = 0
        self._a0 = float(coef[i])
        i += 1
        # Re(p w^n) + Im(...) q  ==  Re((p - i q) w^n)
        a = coef[i : i + n] - 1j * coef[i + n : i + 2 * n]
        i += 2 * n
        self._b = coef[i : i + m]
        i += m
        bre = coef[i : i + m * n].reshape(m, n)
        bim = coef[i + m * n : i + 2 * m * n].reshape(m, n)
        bl = bre - 1j * bim  # (M, n)
        nn = np.arange(1, n + 1)
        coefs = np.concatenate([a[None, :], bl], axis=0)  # (M+1, n)
        cm = np.zeros((m + 1, n + 1, 2 * (m + 1)), dtype=np.complex128)
        for j in range(m + 1):
            cm[j, 1:, j] = coefs[j]  # F: powers 1..n
            cm[j, :-1, m + 1 + j] = nn * coefs[j]  # sum n B u^(n-1): powers 0..n-1
        self._coef_matrix = cm.reshape((m + 1) * (n + 1), 2 * (m + 1))

    def parts(self, w: ArrayLike) -> tuple[FArray, FArray, CArray]:
        """``(G, h, grad H)`` at ``w`` (same shape), ``H = S + sum_j I_j``, complex gradient
        ``dH/dw1 + i dH/dw2``; ``h = log|1 - conj(w_d) w| + H``."""
        w = np.asarray(w, dtype=np.complex128)
        flat = w.ravel()
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if flat.size <= _CHUNK:
                g, h, gh = self._eval(flat)
            else:
                parts = [self._eval(flat[i : i + _CHUNK]) for i in range(0, flat.size, _CHUNK)]
                g, h, gh = (np.concatenate([q[k] for q in parts]) for k in range(3))
        return g.reshape(w.shape), h.reshape(w.shape), gh.reshape(w.shape)

    def h(self, w: ArrayLike) -> FArray:
        """``h = log|w - w_d| - G`` (harmonic, ``log|zeta - w_d|`` on the boundary)."""
        return self.parts(w)[1]

    def _eval(self, z: CArray) -> tuple[FArray, FArray, CArray]:
        # Variables u_0 = w (outer circle), u_j = r_j / (w - c_j); F = sum_j sum_n B_jn u_j^n,
        # F' = sum_j u_j'(w) sum_n n B_jn u_j^(n-1) with u_0' = 1, u_j' = -u_j^2 / r_j.
        # For S = Re F + ... with F analytic, grad S = conj(F'); grad log|w - q| = 1/conj(w - q).
        m1 = self.domain.n_obstacles + 1
        d = z[:, None] - self.domain.centers  # (P, M)
        u = np.concatenate([z[:, None], self.domain.radii / d], axis=1)  # (P, M+1)
        upow = np.empty((z.size, m1, self._n + 1), dtype=np.complex128)
        upow[:, :, 0] = 1.0
        upow[:, :, 1:] = u[:, :, None]
        np.cumprod(upow, axis=2, out=upow)
        res = upow.reshape(z.size, -1) @ self._coef_matrix  # (P, 2(M+1))
        dudw = np.concatenate([np.ones((z.size, 1)), -(u[:, 1:] ** 2) / self.domain.radii], axis=1)
        f = res[:, :m1].sum(axis=1)
        fp = (res[:, m1:] * dudw).sum(axis=1)
        s = self._a0 + f.real + np.log(np.abs(d)) @ self._b
        grad_h = np.conj(fp) + (1.0 / np.conj(d)) @ self._b
        im = self._images
        if im.size:
            zz = z[:, None]
            s = s + _image_terms(z, im)
            # grad log|z - p| - grad log|1 - conj(p) z| = 1/conj(z - p) + p/conj(1 - conj(p) z)
            grad_h = grad_h + (1.0 / np.conj(zz - im) + im / np.conj(1.0 - np.conj(im) * zz)).sum(
                axis=1
            )
        g = _disk_green(z, self.pole) - s
        h = np.log(np.abs(1.0 - np.conj(self.pole) * z)) + s
        return g, h, grad_h


class HarmonicNavigation(NavigationFunction):
    """Harmonic navigation function ``phi_H = exp(2 G)`` (DESIGN.md section 3).

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

    def with_goal(self, goal: complex) -> HarmonicNavigation:
        return HarmonicNavigation(
            self.domain, goal, tol=self.tol, basis=self.green.basis, samples=self.samples
        )
