"""Navigation functions on a circle domain (unit disk minus M disjoint closed disks).

Points are complex numbers w = w1 + i w2.  A gradient is returned in complex form
``dphi/dw1 + i dphi/dw2``.  Two navigation functions are provided, chosen by name:

``"kr"``
    Koditschek-Rimon [1]_ ``phi_k = g / (g^k + beta)^(1/k)``, ``g = |w - w_d|^2``,
    ``beta = (1 - |w|^2) prod_j (|w - c_j|^2 - r_j^2)``.  A navigation function only for
    k above a geometry-dependent threshold: see :mod:`confnav.navigation.critical` for a check
    and for an automatic choice of k; :func:`confnav.navigation.factory.make_navfn` builds
    either by name.
``"harmonic"``
    ``phi_H = |w - w_d|^2 exp(-2 h)`` with ``log|w - w_d| - h`` the Green's function of the
    circle domain (:mod:`confnav.navigation.harmonic`): tuning-free, 1 on every boundary circle, one
    minimum and exactly M saddles.

References
----------
.. [1] D. E. Koditschek and E. Rimon, "Robot navigation functions on manifolds with
   boundary", Advances in Applied Mathematics 11 (1990) 412-442.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError, fmt_point
from confnav.types import CArray, FArray

__all__ = [
    "NAVFN_NAMES",
    "CircleDomain",
    "HasCircles",
    "KoditschekRimon",
    "NavigationFunction",
    "value_and_gradient_stacked",
]


NAVFN_NAMES: tuple[str, ...] = ("kr", "harmonic")
MAX_K: float = 200.0


class HasCircles(Protocol):
    """Anything with the centres and radii of a circle domain (e.g. a ConformalMap)."""

    @property
    def centers(self) -> Any: ...

    @property
    def radii(self) -> Any: ...


@dataclass(frozen=True, eq=False)
class CircleDomain:
    """The circle domain ``|w| < 1`` minus the closed disks ``|w - c_j| <= r_j``.

    Parameters
    ----------
    centers : (M,) complex array
    radii : (M,) float array, all positive; the disks lie inside the unit disk and are
        pairwise disjoint (checked).
    """

    centers: CArray
    radii: FArray

    def __post_init__(self) -> None:
        c = np.atleast_1d(np.asarray(self.centers, dtype=np.complex128)).ravel()
        r = np.atleast_1d(np.asarray(self.radii, dtype=np.float64)).ravel()
        if c.shape != r.shape:
            raise NavigationError(f"{c.size} centres but {r.size} radii")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r > 0)):
            raise NavigationError("circle domain: centres must be finite and radii positive")
        if np.any(np.abs(c) + r >= 1.0):
            raise NavigationError("circle domain: a disk is not inside the unit disk")
        if c.size > 1:
            d = np.abs(c[:, None] - c[None, :]) - r[:, None] - r[None, :]
            np.fill_diagonal(d, np.inf)
            if np.any(d <= 0):
                raise NavigationError("circle domain: two disks overlap")
        object.__setattr__(self, "centers", c)
        object.__setattr__(self, "radii", r)

    @classmethod
    def of(cls, obj: HasCircles) -> CircleDomain:
        """The circle domain of anything with ``centers`` and ``radii``."""
        if isinstance(obj, CircleDomain):
            return obj
        return cls(np.asarray(obj.centers), np.asarray(obj.radii))

    @property
    def n_obstacles(self) -> int:
        return int(self.centers.size)

    def clearance(self, w: ArrayLike) -> FArray:
        """Signed distance to the nearest circle (> 0 inside the domain)."""
        w = np.asarray(w, dtype=np.complex128)
        d = 1.0 - np.abs(w)
        if self.centers.size:
            dj = np.abs(w[..., None] - self.centers) - self.radii
            d = np.minimum(d, dj.min(axis=-1))
        return np.asarray(d, dtype=np.float64)

    def clearance1(self, w: complex) -> float:
        """:meth:`clearance` of one point (a Python float)."""
        d = 1.0 - abs(w)
        if self.centers.size:
            d = min(d, float(np.minimum.reduce(np.abs(w - self.centers) - self.radii)))
        return d

    def contains(self, w: ArrayLike) -> NDArray[np.bool_]:
        """True strictly inside the circle domain (NaN gives False)."""
        return np.asarray(self.clearance(w) > 0)


class NavigationFunction(ABC):
    """A navigation function on a circle domain with its analytic gradient.

    Implementations provide :meth:`value_and_gradient` (vectorized over any array shape)
    and :meth:`with_goal`.  Values are in [0, 1]: 0 only at the goal, 1 on every boundary
    circle; outside the closed domain the result is NaN.
    """

    name: ClassVar[str]

    def __init__(self, domain: CircleDomain, goal: complex) -> None:
        goal = complex(goal)
        if not np.isfinite(goal):
            raise NavigationError(f"goal {goal} is not finite")
        if not bool(domain.contains(goal)):
            raise NavigationError(f"goal {fmt_point(goal)} is not inside the circle domain")
        self.domain = domain
        self.goal = goal

    @abstractmethod
    def value_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        """``(phi(w), dphi/dw1 + i dphi/dw2)``, same shape as ``w``."""

    @abstractmethod
    def with_goal(self, goal: complex) -> NavigationFunction:
        """The same kind of navigation function with another goal (same domain)."""

    def value_and_gradient1(self, w: complex) -> tuple[float, complex]:
        """:meth:`value_and_gradient` of one point as Python scalars (the one-robot control
        step); implementations override it with scalar arithmetic (same formulas)."""
        phi, g = self.value_and_gradient(np.asarray(w, dtype=np.complex128))
        return float(phi), complex(g)

    @classmethod
    def value_and_gradient_stacked(
        cls, fns: Sequence[NavigationFunction], w: CArray
    ) -> tuple[FArray, CArray]:
        """``fns[i].value_and_gradient(w[i])`` for every i (1-D ``w``): many goals on one
        domain, e.g. a fleet whose robots each have their own goal.  This default calls
        :meth:`value_and_gradient1` per point; subclasses evaluate all goals in one
        vectorized pass (:func:`value_and_gradient_stacked` picks the implementation)."""
        out = [f.value_and_gradient1(complex(x)) for f, x in zip(fns, w.tolist(), strict=True)]
        return (
            np.array([o[0] for o in out], dtype=np.float64),
            np.array([o[1] for o in out], dtype=np.complex128),
        )

    def value(self, w: ArrayLike) -> FArray:
        return self.value_and_gradient(w)[0]

    def gradient(self, w: ArrayLike) -> CArray:
        return self.value_and_gradient(w)[1]

    def hessian(self, w: ArrayLike, step: ArrayLike | None = None) -> FArray:
        """(..., 2, 2) Hessian by central differences of the analytic gradient."""
        w = np.asarray(w, dtype=np.complex128)
        if step is None:
            step = 1e-6 * np.clip(self.domain.clearance(w), 1e-12, 1.0)
        h = np.asarray(step, dtype=np.float64)
        gx = (self.gradient(w + h) - self.gradient(w - h)) / (2 * h)
        gy = (self.gradient(w + 1j * h) - self.gradient(w - 1j * h)) / (2 * h)
        hess = np.empty((*w.shape, 2, 2))
        hess[..., 0, 0] = gx.real
        hess[..., 1, 0] = gx.imag
        hess[..., 0, 1] = gy.real
        hess[..., 1, 1] = gy.imag
        return 0.5 * (hess + np.swapaxes(hess, -1, -2))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(M={self.domain.n_obstacles}, goal={self.goal:.6g})"


def obstacle_function(domain: CircleDomain, w: CArray) -> tuple[FArray, CArray]:
    """``beta = prod_j beta_j`` and its gradient, from prefix/suffix products (no division).

    ``beta_0 = 1 - |w|^2``, ``beta_j = |w - c_j|^2 - r_j^2`` [1]_; ``grad beta_0 = -2 w``,
    ``grad beta_j = 2 (w - c_j)``.
    """
    d = w[..., None] - domain.centers  # (..., M)
    b = np.concatenate(
        [(1.0 - (w * w.conjugate()).real)[..., None], (d * d.conjugate()).real - domain.radii**2],
        axis=-1,
    )
    db = np.concatenate([-2.0 * w[..., None], 2.0 * d], axis=-1)
    ones = np.ones((*w.shape, 1))
    pre = np.cumprod(np.concatenate([ones, b[..., :-1]], axis=-1), axis=-1)
    suf = np.cumprod(np.concatenate([ones, b[..., :0:-1]], axis=-1), axis=-1)[..., ::-1]
    beta = pre[..., -1] * b[..., -1]
    dbeta = np.sum(db * (pre * suf), axis=-1)
    return beta, dbeta


def obstacle_function1(
    centers: list[complex], radii2: list[float], w: complex
) -> tuple[float, complex]:
    """:func:`obstacle_function` of one point (``radii2``: the squared radii), Python scalars;
    the same prefix/suffix products in the same order (a loop over the M obstacles)."""
    b = [1.0 - (w * w.conjugate()).real]
    db = [-2.0 * w]
    for c, r2 in zip(centers, radii2, strict=True):
        d = w - c
        b.append((d * d.conjugate()).real - r2)
        db.append(2.0 * d)
    n = len(b)
    pre = [1.0] * n
    for i in range(1, n):
        pre[i] = pre[i - 1] * b[i - 1]
    suf = [1.0] * n
    for i in range(n - 2, -1, -1):
        suf[i] = suf[i + 1] * b[i + 1]
    dbeta = sum((db[i] * (pre[i] * suf[i]) for i in range(n)), 0j)
    return pre[-1] * b[-1], dbeta


class KoditschekRimon(NavigationFunction):
    """Koditschek-Rimon navigation function ``phi_k`` on a circle domain [1]_.

    Uses the squared distance ``g = |w - w_d|^2`` (smooth at the goal; docs/METHOD.md section 6)
    and the cancellation-free gradient of docs/METHOD.md section 3,
    ``grad phi_k = D^(-1/k-1) (beta grad g - (g/k) grad beta)``, ``D = g^k + beta``.

    Parameters
    ----------
    domain : CircleDomain
    goal : complex, the goal w_d inside the domain.
    k : float >= 1.  The seed paper uses k = 6; whether k is large enough for a given
        geometry is checked by :func:`confnav.navigation.critical.find_critical_points`.
    """

    name = "kr"

    def __init__(self, domain: CircleDomain, goal: complex, k: float = 6.0) -> None:
        super().__init__(domain, goal)
        kf = float(k)
        if not np.isfinite(kf) or kf < 1.0 or kf > MAX_K:
            raise NavigationError(f"k must be a number in [1, {MAX_K:g}], got {k!r}")
        self.k = kf
        self._circles1 = (domain.centers.tolist(), (domain.radii**2).tolist())

    def value_and_gradient1(self, w: complex) -> tuple[float, complex]:
        e = w - self.goal
        g = (e * e.conjugate()).real
        beta, dbeta = obstacle_function1(*self._circles1, w)
        if not beta >= 0:  # outside the closed domain (as value_and_gradient)
            return np.nan, complex(np.nan, 0.0)
        big_d = g**self.k + beta
        root = abs(big_d) ** (-1.0 / self.k)
        return g * root, (root / big_d) * (beta * 2.0 * e - (g / self.k) * dbeta)

    def value_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        w = np.asarray(w, dtype=np.complex128)
        e = w - self.goal
        g = (e * e.conjugate()).real
        beta, dbeta = obstacle_function(self.domain, w)
        big_d = g**self.k + beta
        root = np.abs(big_d) ** (-1.0 / self.k)  # abs: no warning outside (NaN'd below)
        phi = g * root
        grad = (root / big_d) * (beta * 2.0 * e - (g / self.k) * dbeta)
        outside = ~(beta >= 0)
        if np.any(outside):
            phi = np.where(outside, np.nan, phi)
            grad = np.where(outside, np.nan + 0j, grad)
        return phi, grad

    @classmethod
    def value_and_gradient_stacked(
        cls, fns: Sequence[NavigationFunction], w: CArray
    ) -> tuple[FArray, CArray]:
        """:meth:`value_and_gradient` with a goal and k per point (same domain: ``beta`` does
        not depend on the goal); the same formulas, so equal to rounding."""
        kr = [f for f in fns if isinstance(f, KoditschekRimon)]
        if len(kr) != len(fns) or len({id(f.domain) for f in kr}) > 1:
            return super().value_and_gradient_stacked(fns, w)
        w = np.asarray(w, dtype=np.complex128)
        goal = np.array([f.goal for f in kr], dtype=np.complex128)
        k = np.array([f.k for f in kr], dtype=np.float64)
        e = w - goal
        g = (e * e.conjugate()).real
        beta, dbeta = obstacle_function(kr[0].domain, w)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            big_d = g**k + beta
            root = np.abs(big_d) ** (-1.0 / k)
            phi = g * root
            grad = (root / big_d) * (beta * 2.0 * e - (g / k) * dbeta)
        outside = ~(beta >= 0)
        if np.any(outside):
            phi = np.where(outside, np.nan, phi)
            grad = np.where(outside, np.nan + 0j, grad)
        return np.asarray(phi, dtype=np.float64), np.asarray(grad, dtype=np.complex128)

    def with_goal(self, goal: complex) -> KoditschekRimon:
        return KoditschekRimon(self.domain, goal, self.k)

    def __repr__(self) -> str:
        return f"KoditschekRimon(M={self.domain.n_obstacles}, goal={self.goal:.6g}, k={self.k:g})"


def value_and_gradient_stacked(
    fns: Sequence[NavigationFunction], w: ArrayLike
) -> tuple[FArray, CArray]:
    """``(phi_i(w_i), grad phi_i(w_i))`` for navigation functions ``fns[i]`` at points
    ``w[i]`` (1-D): each kind (class) of function evaluated in one vectorized pass by its
    :meth:`NavigationFunction.value_and_gradient_stacked`."""
    w = np.asarray(w, dtype=np.complex128).reshape(-1)
    if len(fns) != w.size:
        raise ValueError(f"{len(fns)} navigation functions for {w.size} points")
    phi = np.empty(w.size, dtype=np.float64)
    grad = np.empty(w.size, dtype=np.complex128)
    groups: dict[type[NavigationFunction], list[int]] = {}
    for i, f in enumerate(fns):
        groups.setdefault(type(f), []).append(i)
    for cls, idx in groups.items():
        ii = np.asarray(idx, dtype=np.intp)
        phi[ii], grad[ii] = cls.value_and_gradient_stacked([fns[i] for i in idx], w[ii])
    return phi, grad
