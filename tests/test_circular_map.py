"""Newton steps on the circle domain (confnav.conformal.circular_map) against exact answers."""

from __future__ import annotations

import numpy as np
import pytest

import confnav
from confnav.conformal.circular_map import _fit_circles, _terms, newton_step
from confnav.errors import SolverError

CENTERS = np.array([-0.4 + 0.1j, 0.35 - 0.2j])
RADII = np.array([0.2, 0.25])


def _circle_nodes(n: int = 256) -> list[np.ndarray]:
    t = 2 * np.pi * np.arange(n) / n
    e = np.exp(1j * t)
    return [e] + [c + r * e[::-1] for c, r in zip(CENTERS, RADII, strict=True)]


def _iterate(W: list[np.ndarray], centers: np.ndarray, steps: int) -> tuple:
    """Newton steps as circular_map.nasser_iteration applies them (exact map, rescale)."""
    from confnav.conformal.circular_map import _basis

    radii, circ = _fit_circles(W, centers)
    for _ in range(steps):
        terms = _terms(centers, radii, 1e-12, W)
        coef, shifts, _ = newton_step(W, centers, radii, terms)
        W = [w + _basis(w, centers, radii, terms)[0] @ coef for w in W]
        R0 = float(np.mean(np.abs(W[0])))
        W = [w / R0 for w in W]
        centers = (centers + shifts) / R0
        radii, circ = _fit_circles(W, centers)
    return W, centers, radii, circ


def test_circle_domain_is_a_fixed_point() -> None:
    """A circle domain needs no correction: the step is zero to rounding."""
    W = _circle_nodes()
    radii, circ = _fit_circles(W, CENTERS)
    assert circ < 1e-14
    coef, shifts, d = newton_step(W, CENTERS, radii, _terms(CENTERS, radii, 1e-12, W))
    assert np.max(np.abs(coef)) < 1e-12
    assert np.max(np.abs(shifts)) < 1e-12 and np.max(np.abs(d)) < 1e-12


def test_image_of_circle_domain_maps_back() -> None:
    """The image of a circle domain D under Phi(z) = z + eps z^2 (Phi(0) = 0, Phi'(0) = 1)
    has D itself as its circle domain (uniqueness under the normalisation): the Newton steps
    must return the original centres and radii, converging quadratically."""
    eps = 2e-3
    W0 = _circle_nodes()
    W = [w + eps * w**2 for w in W0]
    centers = CENTERS + eps * CENTERS**2  # first guess: the images of the centres
    circs = []
    for steps in (1, 2, 3):
        _, c, r, circ = _iterate(W, centers, steps)
        circs.append(circ)
    assert circs[0] < 1e-4 and circs[1] < circs[0] ** 1.5 * 10 and circs[2] < 1e-12
    assert np.max(np.abs(c - CENTERS)) < 1e-10
    assert np.max(np.abs(r - RADII)) < 1e-10


def test_unknown_method_is_refused() -> None:
    ws = confnav.Workspace(
        [[-2, -2], [2, -2], [2, 2], [-2, 2]], [[[0, 0], [1, 0], [1, 1], [0, 1]]], anchor=[-1, -1]
    )
    with pytest.raises(SolverError, match="method"):
        confnav.solve(ws, 1e-4, method="bogus")


def test_newton_levels_are_never_certified() -> None:
    """solve(method="nasser") finishes levels by Newton steps that only the nodes constrain:
    measured 1.6e-8 mirror asymmetry under a certificate of 2e-9, so it must never report
    tol_met; its (uncertified) estimate still bounds the mirror asymmetry of its map."""
    g = 0.05
    room = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    ws = confnav.Workspace(room, [left, right], anchor=[0, 1.5])
    with pytest.warns(confnav.AccuracyWarning):
        m = confnav.solve(ws, 1e-6, nodes_per_side=32, method="nasser", max_error=0.1)
    d = m.diagnostics
    assert not d.tol_met and not d.iteration_converged
    asym = max(abs(m.radii[0] - m.radii[1]), abs(m.centers[0] + np.conj(m.centers[1])))
    assert asym <= d.error_estimate
