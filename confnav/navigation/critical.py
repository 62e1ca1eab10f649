"""Critical points of a navigation function on a circle domain, and an automatic k for phi_k.

A navigation function on a circle domain with M holes has one minimum (the goal), M saddles
and no maximum; Morse theory (phi constant and maximal on the boundary) gives the index sum
``#min - #saddle + #max = 1 - M`` for any Morse function of this kind [1]_.  For the
Koditschek-Rimon phi_k with k below a geometry-dependent threshold, spurious minima appear
close to the circles on the side away from the goal [1]_.

The search is numerical: |grad phi| is sampled on a Cartesian grid and on polar grids around
every circle whose radial layers are log-spaced down to 1e-9 of the radius (where spurious
minima hide), discrete local minima of |grad phi| seed a damped Newton iteration on
grad phi = 0 (Hessian by central differences of the analytic gradient), and converged points
are deduplicated and classified by the Hessian.  The index sum is reported as a consistency
check of the search.

References
----------
.. [1] D. E. Koditschek and E. Rimon, "Robot navigation functions on manifolds with
   boundary", Advances in Applied Mathematics 11 (1990) 412-442.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from confnav.errors import NavigationError
from confnav.navigation.navfn import CircleDomain, KoditschekRimon, NavigationFunction
from confnav.types import CArray

__all__ = [
    "COARSE_GRID",
    "K_LADDER",
    "AutoK",
    "CriticalPoints",
    "choose_k",
    "find_critical_points",
    "search_critical_points",
]


#: k values tried, in order, by :func:`choose_k` (the seed's k = 6 first).
K_LADDER: tuple[float, ...] = (6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 80, 100)


@dataclass(frozen=True)
class CriticalPoints:
    """Critical points found in the circle domain (complex arrays).

    ``ok`` is True when there is exactly one minimum (at the goal), M saddles and no maximum;
    ``index_consistent`` when #min - #saddle + #max = 1 - M (the search missed nothing that
    the index theorem can see).
    """

    minima: CArray
    saddles: CArray
    maxima: CArray
    degenerate: CArray
    n_obstacles: int
    goal: complex
    n_candidates: int

    @property
    def index_consistent(self) -> bool:
        return self.minima.size - self.saddles.size + self.maxima.size == 1 - self.n_obstacles

    @property
    def spurious_minima(self) -> CArray:
        return self.minima[np.abs(self.minima - self.goal) > 1e-6]

    @property
    def ok(self) -> bool:
        return (
            self.minima.size == 1
            and self.spurious_minima.size == 0
            and self.saddles.size == self.n_obstacles
            and self.maxima.size == 0
            and self.degenerate.size == 0
        )

    @property
    def message(self) -> str:
        return (
            f"{self.minima.size} minima ({self.spurious_minima.size} spurious), "
            f"{self.saddles.size} saddles (expected {self.n_obstacles}), "
            f"{self.maxima.size} maxima, {self.degenerate.size} degenerate; index sum "
            f"{'consistent' if self.index_consistent else 'INCONSISTENT'}"
        )


@dataclass(frozen=True)
class AutoK:
    """Result of :func:`choose_k`: the chosen k, its navigation function and what was tried."""

    k: float
    navfn: KoditschekRimon
    critical_points: CriticalPoints
    tried: tuple[tuple[float, str], ...] = field(default=())


def _sample_grids(domain: CircleDomain, n_theta: int, n_layers: int, n_grid: int) -> list[CArray]:
    """2-D arrays of sample points (axis 0 periodic for the polar grids)."""
    th = np.exp(2j * np.pi * np.arange(n_theta) / n_theta)
    s = np.geomspace(1e-9, 1.0, n_layers)
    grids: list[CArray] = [th[:, None] * (1.0 - 0.5 * s)[None, :]]  # near the outer circle
    for c, r in zip(domain.centers, domain.radii, strict=True):
        grids.append(c + th[:, None] * (r * (1.0 + s))[None, :])
    x = np.linspace(-1.0, 1.0, n_grid)
    grids.append(x[None, :] + 1j * x[:, None])
    return grids


def _local_minima(a: NDArray[np.float64], periodic: bool) -> NDArray[np.intp]:
    """Flat indices of the discrete local minima (8-neighbourhood) of a 2-D array."""
    pad = np.pad(a, 1, mode="constant", constant_values=np.inf)
    if periodic:
        pad[0, 1:-1] = a[-1]
        pad[-1, 1:-1] = a[0]
    core = pad[1:-1, 1:-1]
    is_min = np.isfinite(core)
    n0, n1 = a.shape
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                is_min &= core <= pad[1 + di : 1 + di + n0, 1 + dj : 1 + dj + n1]
    return np.flatnonzero(is_min)


def find_critical_points(
    navfn: NavigationFunction,
    *,
    n_theta: int = 256,
    n_layers: int = 48,
    n_grid: int = 201,
    newton_iter: int = 60,
) -> CriticalPoints:
    """Find and classify the critical points of ``navfn`` in its circle domain."""
    dom = navfn.domain
    cands: list[CArray] = [np.array([navfn.goal])]
    for k, grid in enumerate(_sample_grids(dom, n_theta, n_layers, n_grid)):
        inside = dom.clearance(grid) > 0
        a = np.full(grid.shape, np.inf)
        a[inside] = np.abs(navfn.gradient(grid[inside]))
        a[~np.isfinite(a)] = np.inf
        idx = _local_minima(a, periodic=k < len(dom.centers) + 1)
        cands.append(grid.ravel()[idx])
    w = np.concatenate(cands)
    n_cand = w.size
    # damped Newton on grad phi = 0, vectorized over candidates
    done = np.zeros(w.size, dtype=bool)
    alive = np.ones(w.size, dtype=bool)
    for _ in range(newton_iter):
        act = alive & ~done
        if not act.any():
            break
        wa = w[act]
        g = navfn.gradient(wa)
        hess = navfn.hessian(wa)
        det = hess[:, 0, 0] * hess[:, 1, 1] - hess[:, 0, 1] * hess[:, 1, 0]
        clr = dom.clearance(wa)
        limit = 0.5 * clr
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            dx = -(hess[:, 1, 1] * g.real - hess[:, 0, 1] * g.imag) / det
            dy = -(-hess[:, 1, 0] * g.real + hess[:, 0, 0] * g.imag) / det
            step = dx + 1j * dy
            big = np.abs(step) > limit
            step = np.where(big, step / np.abs(step) * limit, step)
        new = wa + step
        ok = np.isfinite(new) & (dom.clearance(new) > 0)
        conv = ok & (np.abs(step) <= 1e-10 * np.minimum(clr, 1.0) + 1e-15) & ~big
        ia = np.flatnonzero(act)
        w[ia[ok]] = new[ok]
        done[ia[conv]] = True
        alive[ia[~ok]] = False
    pts = w[done]
    # deduplicate
    keep: list[complex] = []
    for p in pts[np.argsort(dom.clearance(pts))[::-1]]:
        tol = 1e-6 * max(float(dom.clearance(p)), 1e-12)
        if all(abs(p - q) > tol for q in keep):
            keep.append(complex(p))
    pts = np.array(keep, dtype=np.complex128)
    if pts.size:
        hess = navfn.hessian(pts)
        ev = np.linalg.eigvalsh(hess)
        scale = np.max(np.abs(ev), axis=1)
        degenerate = np.min(np.abs(ev), axis=1) <= 1e-8 * scale
        mins = (ev[:, 0] > 0) & ~degenerate
        maxs = (ev[:, 1] < 0) & ~degenerate
        sads = (ev[:, 0] < 0) & (ev[:, 1] > 0) & ~degenerate
    else:
        degenerate = mins = maxs = sads = np.zeros(0, dtype=bool)
    return CriticalPoints(
        minima=pts[mins],
        saddles=pts[sads],
        maxima=pts[maxs],
        degenerate=pts[degenerate],
        n_obstacles=dom.n_obstacles,
        goal=navfn.goal,
        n_candidates=n_cand,
    )


#: Coarse sampling of :func:`search_critical_points` (about 11x fewer points than the defaults
#: of :func:`find_critical_points`).
COARSE_GRID: dict[str, int] = {"n_theta": 64, "n_layers": 16, "n_grid": 61}


def search_critical_points(navfn: NavigationFunction) -> CriticalPoints:
    """:func:`find_critical_points`, first on a coarse grid where theory says what to find.

    The harmonic navigation function ``exp(2 G)`` has the critical points of the Green's
    function ``G`` of the (M+1)-connected circle domain: exactly M of them, counted with
    multiplicity, besides the pole (J. L. Walsh, *The Location of Critical Points of Analytic
    and Harmonic Functions*, AMS Colloquium Publications 34, 1950, ch. VIII), and no local
    minimum or maximum (G is harmonic).  So a coarse search that finds one minimum at the goal
    and M non-degenerate saddles has found all of them; anything else (a saddle missed in a
    narrow gap, a point classified degenerate) repeats the search on the full grid.  Other
    functions (Koditschek-Rimon: spurious minima come and go with k) always get the full grid.
    """
    if navfn.name == "harmonic":
        cp = find_critical_points(navfn, **COARSE_GRID)
        if cp.ok and cp.index_consistent:
            return cp
    return find_critical_points(navfn)


def choose_k(domain: CircleDomain, goal: complex, ladder: tuple[float, ...] = K_LADDER) -> AutoK:
    """Smallest k of ``ladder`` for which phi_k has one minimum, M saddles and no maximum.

    Raises :class:`NavigationError` when no k of the ladder passes (e.g. extreme crowding);
    the harmonic navigation function is the fallback then.
    """
    tried: list[tuple[float, str]] = []
    for k in ladder:
        nf = KoditschekRimon(domain, goal, k)
        cp = find_critical_points(nf)
        tried.append((float(k), cp.message))
        if cp.ok and cp.index_consistent:
            return AutoK(float(k), nf, cp, tuple(tried))
    raise NavigationError(
        "no k in " + ", ".join(f"{k:g}" for k in ladder) + " gives a valid Koditschek-Rimon "
        "navigation function here (last: " + tried[-1][1] + "); use navfn='harmonic'"
    )
