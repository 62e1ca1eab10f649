"""Build a navigation function by name: the one place that knows both kinds.

It sits above :mod:`confnav.navigation.navfn` (the KR function and the circle domain),
:mod:`confnav.navigation.critical` (automatic k) and :mod:`confnav.navigation.harmonic`, so none
of those imports another in a circle.
"""

from __future__ import annotations

from typing import Literal

from numpy.typing import ArrayLike

from confnav.errors import NavigationError
from confnav.navigation.critical import choose_k
from confnav.navigation.harmonic import HarmonicNavigation, RecentredHarmonic
from confnav.navigation.navfn import (
    NAVFN_NAMES,
    CircleDomain,
    HasCircles,
    KoditschekRimon,
    NavigationFunction,
)

__all__ = ["make_navfn"]


def make_navfn(
    name: Literal["kr", "harmonic"] | str,
    domain: CircleDomain | HasCircles,
    goal: complex,
    *,
    k: float | Literal["auto"] = "auto",
    samples: ArrayLike | None = None,
) -> NavigationFunction:
    """Build a navigation function by name (``"kr"`` or ``"harmonic"``).

    For ``"kr"``, ``k="auto"`` picks the smallest k of :data:`confnav.navigation.critical.K_LADDER`
    whose critical points check out (one minimum, M saddles); an integer k is used as is.
    ``samples`` (harmonic only): circle-domain points where the fit must be accurate relative
    to the size of G (see :meth:`confnav.navigation.harmonic.GreenBasis.fit`). A harmonic fit
    that does not converge is redone on a Moebius image of the domain that spreads crowded
    circles (:class:`confnav.navigation.harmonic.RecentredHarmonic`); if that fails too, its
    error is raised (the controller then falls back to Koditschek-Rimon).
    """
    dom = CircleDomain.of(domain)
    if name == "kr":
        if isinstance(k, str):
            if k != "auto":
                raise NavigationError(f"k must be a number or 'auto', got {k!r}")
            return choose_k(dom, goal).navfn
        return KoditschekRimon(dom, goal, k)
    if name == "harmonic":
        try:
            return HarmonicNavigation(dom, goal, samples=samples)
        except NavigationError as exc:
            if "did not converge" not in str(exc) or dom.n_obstacles < 2:
                raise
        # circles crowded towards one point of the unit circle (the anchor at one end of a
        # long map): the same Green's function fitted where a Moebius map spreads them
        return RecentredHarmonic(dom, goal, samples=samples)
    raise NavigationError(f"unknown navigation function {name!r}; choose from {NAVFN_NAMES}")
