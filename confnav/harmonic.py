"""Harmonic navigation function from the Green's function of a circle domain.

``G(w) = log|w - w_d| - h(w)`` with ``h`` harmonic in the circle domain and
``h = log|zeta - w_d|`` on every boundary circle, so ``G = 0`` on the boundary.  ``h`` is a
real series (logarithmic conjugation / Laurent expansion in each hole [1]_ [2]_):

    h(w) = a_0 + Re sum_n a_n w^n + sum_j [ b_j log|w - c_j| + Re sum_n b_jn (r_j/(w-c_j))^n ]
           + log|1 - conj(w_d) w| + sum_j log|w - p_j|,

where the last terms, fixed, are the image charges of the pole in each circle (exact for one
circle, ``p_j = c_j + r_j^2 / conj(w_d - c_j)``): they take the near-singular part of the
boundary data when the goal is close to a circle, so the fitted series stays well conditioned.
The real coefficients are fitted by least squares on equispaced collocation points of every
circle and the number of terms grows (extrapolating the observed geometric rate) until the
boundary error, measured on points in between, is below
``tol``; convergence is geometric in the number of terms [2]_.

``phi_H = |w - w_d|^2 e^{-2h} = e^{2G}`` is 1 on every boundary circle, has a single minimum
(at w_d) and exactly M saddles, and needs no tuning.  Its gradient is evaluated without the
pole: ``grad phi_H = 2 e^{-2h} ((w - w_d) - |w - w_d|^2 grad h)`` (complex gradient form).

References
----------
.. [1] S. Axler, "Harmonic functions from a complex analysis viewpoint", Amer. Math. Monthly
   93 (1986) 246-258 (logarithmic conjugation theorem).
.. [2] L. N. Trefethen, "Series solution of Laplace problems", ANZIAM J. 60 (2018) 1-26.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError
from confnav.navfn import CircleDomain, NavigationFunction

__all__ = ["GreenDiagnostics", "GreenFunction", "HarmonicNavigation"]

CArray = NDArray[np.complex128]
FArray = NDArray[np.float64]

_CHUNK = 4096


@dataclass(frozen=True)
class GreenDiagnostics:
    """How the series for ``h`` was fitted.

    n_terms: Laurent terms per circle; n_collocation: collocation points per circle;
    residual: max boundary error of ``h`` on check points between the collocation points;
    history: (n_terms, residual) per attempt; converged: residual <= tol.
    """

    n_terms: int
    n_collocation: int
    residual: float
    tol: float
    converged: bool
    history: tuple[tuple[int, float], ...]


class GreenFunction:
    """``h`` (the regular part of the Green's function) of a circle domain for one pole.

    Parameters
    ----------
    domain : CircleDomain
    pole : complex, inside the domain.
    tol : target max boundary error of ``h``.
    max_terms : upper bound of the number of Laurent terms per circle.

    Raises
    ------
    NavigationError
        if the series does not reach ``100 * tol`` with ``max_terms`` terms.
    """

    def __init__(
        self, domain: CircleDomain, pole: complex, *, tol: float = 1e-10, max_terms: int = 256
    ) -> None:
        self.domain = domain
        self.pole = complex(pole)
        c, r = domain.centers, domain.radii
        # image charges of the pole in each circle, with fixed unit coefficients
        self._images = c + r**2 / np.conj(self.pole - c)
        self._s0 = 1.0
        self._s = np.ones(c.size)
        history: list[tuple[int, float]] = []
        n = 12
        while True:
            p = 3 * n + 16
            zeta = self._boundary_points(p, offset=0.0)
            a = self._design(zeta, n)
            rhs = np.log(np.abs(zeta - self.pole)) - self._image_part(zeta)
            scale = np.linalg.norm(a, axis=0)
            scale[scale == 0] = 1.0
            a /= scale
            # the basis is well conditioned (each family orthogonal on its own circle, the
            # near-singular image parts taken out), so the normal equations are accurate
            gram = a.T @ a
            try:
                coef = scipy.linalg.solve(gram, a.T @ rhs, assume_a="pos", check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                coef = scipy.linalg.lstsq(a, rhs, lapack_driver="gelsy", check_finite=False)[0]
            coef = coef / scale
            self._n = n
            self._unpack(coef, n)
            zc = self._boundary_points(p, offset=0.5)
            res = float(np.max(np.abs(self.h(zc) - np.log(np.abs(zc - self.pole)))))
            history.append((n, res))
            if res <= tol or n >= max_terms:
                break
            n = min(self._next_n(history, tol), max_terms)
        self.diagnostics = GreenDiagnostics(n, p, res, tol, res <= tol, tuple(history))
        if res > 100 * tol:
            raise NavigationError(
                f"Green's function series did not converge: boundary error {res:.2e} with "
                f"{n} terms per circle (circles too close to each other or to the goal?)"
            )

    def _image_part(self, z: CArray) -> FArray:
        """``log|1 - conj(w_d) z| + sum_j log|z - p_j|`` (fixed part of h)."""
        out = np.log(np.abs(1.0 - np.conj(self.pole) * z))
        if self._images.size:
            out = out + np.log(np.abs(z[:, None] - self._images)).sum(axis=1)
        return np.asarray(out, dtype=np.float64)

    @staticmethod
    def _next_n(history: list[tuple[int, float]], tol: float) -> int:
        """Next number of terms: extrapolate the geometric rate of the last two attempts."""
        n, res = history[-1]
        if len(history) < 2 or not res < history[-2][1]:
            return 2 * n
        n0, res0 = history[-2]
        per_term = np.log(res / res0) / (n - n0)  # log of the rate per term (< 0)
        need = n + np.log(tol / res) / per_term
        return int(np.clip(np.ceil(1.1 * need) + 2, n + 4, 2 * n))

    def _boundary_points(self, p: int, offset: float) -> CArray:
        e = np.exp(2j * np.pi * (np.arange(p) + offset) / p)
        parts = [e] + [
            cj + rj * e for cj, rj in zip(self.domain.centers, self.domain.radii, strict=True)
        ]
        return np.concatenate(parts)

    def _design(self, z: CArray, n: int) -> FArray:
        """Real design matrix, columns in the order of :meth:`_unpack`."""
        c, r = self.domain.centers, self.domain.radii
        cols: list[FArray] = [np.ones(z.shape)]
        wp = z[:, None] ** np.arange(1, n + 1)
        cols += [wp.real, wp.imag]
        if c.size:
            d = z[:, None] - c  # (P, M)
            cols.append(np.log(np.abs(d)))
            u = (r / d)[:, :, None] ** np.arange(1, n + 1)  # (P, M, n)
            cols += [u.real.reshape(z.size, -1), u.imag.reshape(z.size, -1)]
        return np.column_stack([x[:, None] if x.ndim == 1 else x for x in cols])

    def _unpack(self, coef: FArray, n: int) -> None:
        m = self.domain.n_obstacles
        i = 0
        self._a0 = float(coef[i])
        i += 1
        # Re(p w^n) + Im(...) q  ==  Re((p - i q) w^n)
        self._a = coef[i : i + n] - 1j * coef[i + n : i + 2 * n]
        i += 2 * n
        self._b = coef[i : i + m]
        i += m
        bre = coef[i : i + m * n].reshape(m, n)
        bim = coef[i + m * n : i + 2 * m * n].reshape(m, n)
        bl = bre - 1j * bim  # (M, n)
        nn = np.arange(1, n + 1)
        coefs = np.concatenate([self._a[None, :], bl], axis=0)  # (M+1, n)
        cm = np.zeros((m + 1, n + 1, 2 * (m + 1)), dtype=np.complex128)
        for j in range(m + 1):
            cm[j, 1:, j] = coefs[j]  # F: powers 1..n
            cm[j, :-1, m + 1 + j] = nn * coefs[j]  # sum n B u^(n-1): powers 0..n-1
        self._coef_matrix = cm.reshape((m + 1) * (n + 1), 2 * (m + 1))

    def h_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        """``h(w)`` and its complex gradient ``dh/dw1 + i dh/dw2`` (same shape as w)."""
        w = np.asarray(w, dtype=np.complex128)
        flat = w.ravel()
        if not np.isfinite(flat).all():  # NaN poses: silence the complex-division warnings
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                return self._h_and_gradient(flat, w.shape)
        return self._h_and_gradient(flat, w.shape)

    def _h_and_gradient(self, flat: CArray, shape: tuple[int, ...]) -> tuple[FArray, CArray]:
        if flat.size <= _CHUNK:
            h, gh = self._eval(flat)
        else:
            parts = [self._eval(flat[i : i + _CHUNK]) for i in range(0, flat.size, _CHUNK)]
            h = np.concatenate([q[0] for q in parts])
            gh = np.concatenate([q[1] for q in parts])
        return h.reshape(shape), gh.reshape(shape)

    def h(self, w: ArrayLike) -> FArray:
        return self.h_and_gradient(w)[0]

    def _eval(self, z: CArray) -> tuple[FArray, CArray]:
        # Variables u_0 = w (outer circle), u_j = r_j / (w - c_j); F = sum_j sum_n B_jn u_j^n,
        # F' = sum_j u_j'(w) sum_n n B_jn u_j^(n-1) with u_0' = 1, u_j' = -u_j^2 / r_j.
        # For h = Re F with F analytic, grad h = conj(F'); for log|w - q|, grad = 1/conj(w - q).
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
        q = 1.0 - np.conj(self.pole) * z
        di = z[:, None] - self._images
        h = (
            self._a0
            + f.real
            + self._s0 * np.log(np.abs(q))
            + np.log(np.abs(d)) @ self._b
            + np.log(np.abs(di)) @ self._s
        )
        fp = fp - self._s0 * np.conj(self.pole) / q
        glog = (1.0 / np.conj(d)) @ self._b + (1.0 / np.conj(di)) @ self._s
        return h, np.conj(fp) + glog


class HarmonicNavigation(NavigationFunction):
    """Harmonic navigation function ``phi_H = |w - w_d|^2 exp(-2 h)`` (DESIGN.md section 3).

    ``diagnostics`` holds the :class:`GreenDiagnostics` of the series for ``h``.  ``tol``
    bounds the boundary error of ``h``; it must stay far below ``1 - phi_H`` where robots
    drive: far from the goal (corners of the outer polygon) ``1 - phi_H`` is ~1e-7 a few
    centimetres from a wall, and with ``tol = 1e-7`` a robot there was seen to follow the
    error into the wall.  Hence the default 1e-10.
    """

    name = "harmonic"

    def __init__(self, domain: CircleDomain, goal: complex, *, tol: float = 1e-10) -> None:
        super().__init__(domain, goal)
        self.tol = tol
        self.green = GreenFunction(domain, self.goal, tol=tol)
        self.diagnostics = self.green.diagnostics

    def value_and_gradient(self, w: ArrayLike) -> tuple[FArray, CArray]:
        w = np.asarray(w, dtype=np.complex128)
        h, gh = self.green.h_and_gradient(w)
        e = w - self.goal
        g = (e * e.conjugate()).real
        ex = np.exp(-2.0 * h)
        phi = g * ex
        grad = 2.0 * ex * (e - g * gh)
        outside = ~(self.domain.clearance(w) >= 0)
        if np.any(outside):
            phi = np.where(outside, np.nan, phi)
            grad = np.where(outside, np.nan + 0j, grad)
        return phi, grad

    def with_goal(self, goal: complex) -> HarmonicNavigation:
        return HarmonicNavigation(self.domain, goal, tol=self.tol)
