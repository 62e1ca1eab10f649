"""Over-relaxed (SOR-type) Koebe sweeps: an acceleration that keeps the map conformal.

One Koebe sweep applies, hole after hole, the exterior map ``F_k`` of hole k's current image
(``F(inf) = inf``, ``F'(inf) = s_k > 0``) to the whole domain. Near the fixed point every
``F_k`` is close to the similarity ``L_k(z) = s_k (z - alpha_k)``; the over-relaxed map

    F_k^omega(z) = (1 - omega) L_k(z) + omega F_k(z),      omega in [1, 2),

is an analytic function outside hole k as well (a combination of two analytic maps), so for
moderate corrections it is univalent there and maps the domain *conformally* onto a new
domain. The iteration therefore still composes conformal maps of the polygon domain, and its
fixed point (the circle domain with its normalisation) is the same as that of plain sweeps:
the over-relaxation only changes where the next sweep starts. This is why it is safe where
extrapolating the state is not (see :mod:`confnav.conformal.circledomain`: Anderson mixing of
hole curves and correspondences combined states that are no conformal image of the polygon
domain, and converged to a wrong map).

Hole k's own image becomes ``(1 - omega) L_k(S) + omega F_k(S)``: no longer a circle, but an
analytic curve sampled on the same smooth grid (the parameters u of the passive nodes stay,
as for any other boundary the map moves). The linearised Koebe iteration is a block
Gauss-Seidel iteration (one block per boundary; Henrici, Vol. 3, sec. 17.7 for Koebe's
iteration as successive maps), and for Gauss-Seidel with contraction rho the over-relaxation
omega_opt = 2 / (1 + sqrt(1 - rho)) gives omega_opt - 1 (Young's theorem for consistently
ordered matrices; D. M. Young, "Iterative Solution of Large Linear Systems", Academic Press
1971, ch. 6, thm 6.2.3); for the nonlinear iteration, Ortega & Rheinboldt, "Iterative Solution
of Nonlinear Equations in Several Variables", Academic Press 1970, sec. 10.3 (local
convergence of nonlinear SOR follows from that of its linearisation). The Koebe blocks are not
consistently ordered in general, so omega is estimated from the observed plain contraction and
safeguarded (halved towards 1 when the change grows).

References
----------
.. [1] D. M. Young, "Iterative Solution of Large Linear Systems", Academic Press 1971, ch. 6.
.. [2] J. M. Ortega, W. C. Rheinboldt, "Iterative Solution of Nonlinear Equations in Several
   Variables", Academic Press 1970, sec. 10.3.
.. [3] P. Henrici, "Applied and Computational Complex Analysis", Vol. 3, Wiley 1986, sec. 17.7.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from confnav.conformal.diskmap import CurveMap
from confnav.conformal.triginterp import upsample
from confnav.types import CArray as ComplexArray

#: Accelerations of the Koebe sweeps understood by :func:`koebe_iteration`.
KOEBE_ACCELS = ("none", "sor", "extrapolate")
#: Largest over-relaxation used (omega -> 2 is the edge of convergence of SOR).
OMEGA_MAX = 1.8
#: Plain contractions below this are fast enough: no over-relaxation.
RHO_MIN = 0.2


def optimal_omega(rho: float) -> float:
    """Young's optimal over-relaxation for a Gauss-Seidel contraction ``rho`` (clipped)."""
    if not np.isfinite(rho) or rho <= RHO_MIN:
        return 1.0
    rho = min(rho, 0.999)
    return float(min(OMEGA_MAX, 2.0 / (1.0 + np.sqrt(1.0 - rho))))


@dataclass(frozen=True)
class RelaxedMap:
    """``F^omega = (1 - omega) s (z - alpha) + omega F`` for an exterior map ``F``."""

    cm: CurveMap
    omega: float

    @property
    def gmres_iterations(self) -> int:
        return self.cm.gmres_iterations

    @property
    def scale(self) -> float:
        """``F'(alpha)`` of an interior map (``omega = 1`` only)."""
        return self.cm.scale

    @property
    def gmres_residual(self) -> float:
        return self.cm.gmres_residual

    def evaluate(
        self, z: ComplexArray, derivative: bool = True
    ) -> tuple[ComplexArray, ComplexArray | None]:
        """The relaxed map and its derivative at points off hole k."""
        z = np.asarray(z, dtype=np.complex128).ravel()
        f, df = self.cm.evaluate(z, derivative=derivative)
        w, s, a = self.omega, self.cm.scale, self.cm.alpha
        fz = (1.0 - w) * s * (z - a) + w * f
        if not derivative:
            return np.asarray(fz), None
        assert df is not None
        return np.asarray(fz), np.asarray((1.0 - w) * s + w * df)

    def on_curve(self) -> tuple[ComplexArray, ComplexArray]:
        """Image of hole k's own curve (its smooth grid) and its s-derivative."""
        cm, w = self.cm, self.omega
        return (
            np.asarray((1.0 - w) * cm.scale * (cm.eta - cm.alpha) + w * cm.f),
            np.asarray((1.0 - w) * cm.scale * cm.deta + w * cm.df),
        )


def extrapolate_curve(
    S0: ComplexArray, dS0: ComplexArray, S1: ComplexArray, dS1: ComplexArray, w: float
) -> tuple[ComplexArray, ComplexArray]:
    """``H = (1 - w) id + w G`` on one boundary's grid: ``S0`` (with its s-derivative) the
    grid before a sweep that kept every grid point, ``S1 = G(S0)`` after it.

    ``H`` is analytic in the domain wherever ``G`` is, and its derivative along the curve is
    ``(1 - w) dS0 + w dS1`` (chain rule). With ``w = 1/(1 - rho)`` it jumps to the limit of a
    sequence contracting geometrically by rho (Aitken's delta^2 on the slowest mode; A. Sidi,
    "Vector Extrapolation Methods with Applications", SIAM 2017, ch. 1). A grid refined during
    the sweep is matched by exact FFT upsampling of the old curve (same parameters s).
    """
    if S0.size != S1.size:
        S0, dS0 = upsample(np.stack([S0, dS0]), S1.size)
    return np.asarray(S0 + w * (S1 - S0)), np.asarray(dS0 + w * (dS1 - dS0))


__all__ = [
    "KOEBE_ACCELS",
    "OMEGA_MAX",
    "RelaxedMap",
    "extrapolate_curve",
    "optimal_omega",
]
