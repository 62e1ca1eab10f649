"""Disk maps of one closed curve from the GNK equation, and their Cauchy-formula evaluation.

Interior map (bounded domain inside ``eta`` onto ``|w| < 1``, ``f(alpha) = 0``,
``f'(alpha) > 0``): ``A = eta - alpha``, ``gamma = -log|eta - alpha|``; then

    f(eta) = (eta - alpha)/|eta - alpha| e^{i mu},      f'(alpha) = e^{-h},
    df/dt  = i (Im(eta'/(eta - alpha)) + mu') f.

Exterior map (unbounded domain outside a clockwise ``eta`` onto ``|w| > 1``, ``F(inf) = inf``,
``F'(inf) > 0``, ``alpha`` inside the curve): ``A = 1``, ``gamma = log|eta - alpha|``,
``Phi = gamma + h + i mu``; then

    F(eta) = (eta - alpha)/|eta - alpha| e^{-i mu + i Im Phi_inf},
    F'(inf) = e^{h - Re Phi_inf},   Phi_inf = (1/2pi i) oint_ccw Phi/(zeta - alpha) dzeta.

Off the curve the maps are evaluated by the barycentric Cauchy formula, which stays accurate up
to the boundary (the discretisation error of numerator and denominator cancels):

    f(z) = sum f_k eta'_k/(eta_k - z) / sum eta'_k/(eta_k - z),
    f'(z) = sum (df/dt)_k/(eta_k - z) / sum eta'_k/(eta_k - z);

outside a hole it is applied to the bounded function ``g = F/(z - alpha)``, with
``g(z) = [g_inf + (1/2pi i) sum w g eta'/(eta - z)] / [1 + (1/2pi i) sum w eta'/(eta - z)]``.

References
----------
.. [1] M. M. S. Nasser, "Numerical conformal mapping via a boundary integral equation with the
   generalized Neumann kernel", SIAM J. Sci. Comput. 31 (2009) 1695-1715, secs. 4-5.
.. [2] J.-P. Berrut, L. N. Trefethen, "Barycentric Lagrange interpolation", SIAM Rev. 46
   (2004); A. P. Austin, P. Kravanja, L. N. Trefethen, SIAM J. Numer. Anal. 52 (2014) 1795-1821
   (barycentric Cauchy formula near the boundary).
.. [3] docs/METHOD.md sec. 2 (formulas checked against two independent implementations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from confnav.conformal.cauchy import cauchy_sums, cauchy_sums2
from confnav.conformal.gnk import (
    GMRES_RTOL,
    solve_gnk,
    spectral_derivative,
    spectral_derivative_complex,
)
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: A map's derivative (``evaluate(z, derivative=True)``, what the Koebe sweeps ask for on
#: every other boundary) from the second-order sums of its two barycentric charges, the exact
#: derivative of the quotient ``N/D`` (with the FMM one call gives both orders: the Hessian
#: of the same expansions), instead of the Cauchy sum of a third charge, the boundary
#: derivative: pyfmmlib's ``lfmm2dparttarg`` takes one charge vector per call, and a complex
#: charge already uses both of its real outputs, so the third sum was a third FMM call.
#: Measured side by side (bench/README.md, "Residuals evaluated once; dense GNK matrices
#: kept complex", ``koebe_second_sums.json``, CPU s): two squares 0.01 apart 16.9 -> 14.9
#: (FMM sums 905 -> 771), 50 obstacles 15.5 -> 15.3 (171 -> 151), the default shrunk by
#: 0.2 m 2.9 -> 2.8, the default workspace to 1e-10 1.1 -> 0.9; the same sweeps and
#: estimates, the maps within 6.8e-12 (two squares 4.6e-14). False: the third charge (before).
#: On by default since the harmonic fleet step and each robot's own step agree at rounding
#: again: with it the fleet step (tests/test_fleet_step.py, the same map values into both)
#: differed from each robot's own step by a median 1.3e-14 relative, over that test's bound
#: 1e-14 (4.7e-15 without it). The map was not the cause (it moves by ~1e-12, the same inputs
#: go to both paths): one robot's harmonic gradient was formed with Python's complex
#: multiply and divide, the fleet's with numpy's, an ulp apart and amplified ~100-fold by
#: the gradient's cancellation (the two formulas on the same parts: median 2.3e-15 with it,
#: 4.5e-15 without); with numpy's operations in both
#: (``HarmonicNavigation.value_and_gradient1``) the medians are 2.1e-16 with it and 2.2e-16
#: without (``bench/results/second_sums_fleet_step.json``, ``python bench/bench_koebe.py
#: --fleet-step``).
DERIVATIVE_FROM_SECOND_SUMS = True


@dataclass(frozen=True)
class CurveMap:
    """A disk map of one curve: boundary values plus what is needed to evaluate it elsewhere.

    Attributes
    ----------
    eta, deta
        The curve and its t-derivative at the nodes.
    f, df
        The map's boundary values and their t-derivatives (``|f| = 1``).
    alpha
        Interior map: the point sent to 0. Exterior map: a point inside the curve.
    exterior
        True for the exterior map of a hole.
    scale
        ``f'(alpha)`` (interior) or ``F'(inf)`` (exterior); real and positive.
    gmres_iterations
        Iterations of the GNK solve (diagnostic).
    mu
        The GNK solution at the nodes (a first guess for the same curve on a finer mesh).
    """

    eta: ComplexArray
    deta: ComplexArray
    f: ComplexArray
    df: ComplexArray
    alpha: complex
    exterior: bool
    scale: float
    gmres_iterations: int
    mu: FloatArray | None = None
    #: Absolute residual the GNK solve left (:attr:`confnav.conformal.gnk.GNKSolution.residual`).
    gmres_residual: float = 0.0

    def evaluate(
        self, z: ComplexArray, derivative: bool = True
    ) -> tuple[ComplexArray, ComplexArray | None]:
        """The map and its derivative at points z inside its domain (off the curve)."""
        z = np.asarray(z, dtype=np.complex128).ravel()
        if self.exterior:
            return self._evaluate_exterior(z, derivative)
        return self._evaluate_interior(z, derivative)

    def _sums(self, z: ComplexArray, charges: list[ComplexArray]) -> list[ComplexArray]:
        """sum_k q_k/(eta_k - z) for each charge vector q."""
        return [-c for c in cauchy_sums(self.eta, charges, z)]

    def _evaluate_interior(
        self, z: ComplexArray, derivative: bool
    ) -> tuple[ComplexArray, ComplexArray | None]:
        if derivative and DERIVATIVE_FROM_SECOND_SUMS:
            first, second = cauchy_sums2(self.eta, [self.f * self.deta, self.deta], z)
            N, D = -first[0], -first[1]  # sum q/(eta - z); its z-derivative sum q/(z - eta)^2
            return N / D, (second[0] * D - N * second[1]) / D**2
        charges = [self.f * self.deta, self.deta] + ([self.df] if derivative else [])
        sums = self._sums(z, charges)
        w = sums[0] / sums[1]
        dw = sums[2] / sums[1] if derivative else None
        return w, dw

    def _evaluate_exterior(
        self, z: ComplexArray, derivative: bool
    ) -> tuple[ComplexArray, ComplexArray | None]:
        a = self.alpha
        g = self.f / (self.eta - a)
        # dg/dt as the spectral derivative of the samples of g: its weighted sum is exactly 0,
        # as it must be for g'(z) = O(1/z^2) at infinity. (A dg assembled from the boundary
        # formula is inexact at the corners, and F' = g + (z - a) g' then carries that error
        # undiminished to every distance.)
        dg = spectral_derivative_complex(g)
        w2pi = 2 * np.pi / self.eta.size / (2j * np.pi)
        if derivative and DERIVATIVE_FROM_SECOND_SUMS:
            first, second = cauchy_sums2(self.eta, [g * self.deta, self.deta], z)
            den = 1.0 - w2pi * first[1]
            gz = (self.scale - w2pi * first[0]) / den
            dgz = w2pi * (second[0] - gz * second[1]) / den
            return (z - a) * gz, gz + (z - a) * dgz
        charges = [g * self.deta, self.deta] + ([dg] if derivative else [])
        sums = self._sums(z, charges)
        den = 1.0 + w2pi * sums[1]
        gz = (self.scale + w2pi * sums[0]) / den  # g(inf) = F'(inf)
        Fz = (z - a) * gz
        if not derivative:
            return Fz, None
        dgz = (w2pi * sums[2]) / den
        return Fz, gz + (z - a) * dgz


def interior_map(
    eta: ComplexArray,
    deta: ComplexArray,
    alpha: complex,
    rtol: float = GMRES_RTOL,
    x0: FloatArray | None = None,
    smooth: bool = False,
    corners: np.ndarray | None = None,
) -> CurveMap:
    """Map the inside of a counter-clockwise curve onto the unit disk (docs/METHOD.md sec. 2).

    ``rtol``: relative GMRES residual of the GNK solve
    (:func:`confnav.conformal.gnk.gmres_rtol`); ``x0``: a first guess of its ``mu``;
    ``smooth``: a smooth grid, ``corners``: the vertex blocks of a graded polygon mesh (its
    GMRES preconditioner; see :func:`confnav.conformal.gnk.solve_gnk`)."""
    A = eta - alpha
    gamma = -np.log(np.abs(A))
    sol = solve_gnk(eta, deta, A, gamma, rtol, x0, smooth, corners)
    theta_dot = (deta / A).imag + spectral_derivative(sol.mu)
    f = A / np.abs(A) * np.exp(1j * sol.mu)
    return CurveMap(
        eta=eta,
        deta=deta,
        f=f,
        df=1j * theta_dot * f,
        alpha=complex(alpha),
        exterior=False,
        scale=float(np.exp(-sol.h)),
        gmres_iterations=sol.iterations,
        mu=sol.mu,
        gmres_residual=sol.residual,
    )


def exterior_map(
    eta: ComplexArray,
    deta: ComplexArray,
    alpha: complex,
    rtol: float = GMRES_RTOL,
    x0: FloatArray | None = None,
    smooth: bool = False,
    corners: np.ndarray | None = None,
) -> CurveMap:
    """Map the outside of a clockwise curve onto |w| > 1 with F'(inf) > 0 (docs/METHOD.md sec. 2).

    ``rtol``: relative GMRES residual of the GNK solve
    (:func:`confnav.conformal.gnk.gmres_rtol`); ``x0``: a first guess of its ``mu``;
    ``smooth``: a smooth grid, ``corners``: the vertex blocks of a graded polygon mesh (its
    GMRES preconditioner; see :func:`confnav.conformal.gnk.solve_gnk`)."""
    A = np.ones_like(eta)
    gamma = np.log(np.abs(eta - alpha))
    sol = solve_gnk(eta, deta, A, gamma, rtol, x0, smooth, corners)
    phi = gamma + sol.h + 1j * sol.mu
    # Phi_inf = (1/2pi i) oint_ccw Phi/(zeta - alpha) dzeta; eta runs clockwise -> minus sign.
    phi_inf = -(2 * np.pi / eta.size) / (2j * np.pi) * np.sum(phi * deta / (eta - alpha))
    theta_dot = (deta / (eta - alpha)).imag - spectral_derivative(sol.mu)
    f = (eta - alpha) / np.abs(eta - alpha) * np.exp(-1j * sol.mu + 1j * phi_inf.imag)
    return CurveMap(
        eta=eta,
        deta=deta,
        f=f,
        df=1j * theta_dot * f,
        alpha=complex(alpha),
        exterior=True,
        scale=float(np.exp(sol.h - phi_inf.real)),
        gmres_iterations=sol.iterations,
        mu=sol.mu,
        gmres_residual=sol.residual,
    )


__all__ = ["CurveMap", "exterior_map", "interior_map"]
