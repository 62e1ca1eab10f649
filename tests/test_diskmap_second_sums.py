"""A map's derivative from the second-order sums of its two barycentric charges
(``diskmap.DERIVATIVE_FROM_SECOND_SUMS``, an experiment of issue 24): the exact derivative on
a circle, and the third-charge path's values off the curve."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.conformal import diskmap


def _circle(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = 2 * np.pi * np.arange(n) / n
    return np.exp(1j * t), 1j * np.exp(1j * t)


@pytest.mark.parametrize("flag", [False, True])
def test_derivatives_of_the_disk_automorphism_are_exact(
    monkeypatch: pytest.MonkeyPatch, flag: bool
) -> None:
    """f(z) = (z - a)/(1 - conj(a) z) is the unit disk's map sending a to 0 with f'(a) > 0 (a
    real); f'(z) = (1 - |a|^2)/(1 - conj(a) z)^2; outside, F(z) = z (the circle itself)."""
    eta, deta = _circle(256)
    a = 0.3
    f = diskmap.interior_map(eta, deta, a, smooth=True)
    F = diskmap.exterior_map(eta[::-1].copy(), -deta[::-1].copy(), 0j, smooth=True)
    monkeypatch.setattr(diskmap, "DERIVATIVE_FROM_SECOND_SUMS", flag)
    z = 0.8 * np.exp(1j * np.linspace(0, 6, 200))  # also enough points for expansions
    w, dw = f.evaluate(z)
    assert np.max(np.abs(w - (z - a) / (1 - a * z))) < 1e-13
    assert dw is not None
    assert np.max(np.abs(dw - (1 - a * a) / (1 - a * z) ** 2)) < 1e-12
    zo = 1.25 * np.exp(1j * np.linspace(0, 6, 200))
    W, dW = F.evaluate(zo)
    assert np.max(np.abs(W - zo)) < 1e-13
    assert dW is not None and np.max(np.abs(dW - 1)) < 1e-12


def test_second_sums_match_the_third_charge_off_the_curve(monkeypatch: pytest.MonkeyPatch) -> None:
    t = 2 * np.pi * np.arange(512) / 512
    eta = np.exp(1j * t) + 0.2 * np.exp(-2j * t)
    deta = 1j * np.exp(1j * t) - 0.4j * np.exp(-2j * t)
    f = diskmap.interior_map(eta, deta, 0.1j, smooth=True)
    z = 0.5 * np.exp(1j * np.linspace(0, 6, 300))
    out = []
    for flag in (False, True):
        monkeypatch.setattr(diskmap, "DERIVATIVE_FROM_SECOND_SUMS", flag)
        out.append(f.evaluate(z))
    assert np.array_equal(out[0][0], out[1][0])
    assert np.max(np.abs(out[0][1] - out[1][1])) < 1e-13


def test_a_solve_gives_the_third_charge_paths_map(monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole solve (sweeps on smooth grids, FMM and expansions) with either derivative:
    the same sweeps and circle domain to 1e-11, both tol_met."""
    import warnings

    import confnav
    from confnav.scenes.workspaces import mirror_squares

    maps = []
    for flag in (False, True):
        monkeypatch.setattr(diskmap, "DERIVATIVE_FROM_SECOND_SUMS", flag)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", confnav.AccuracyWarning)
            maps.append(confnav.solve(mirror_squares(0.1), tol=1e-7))
    a, b = maps
    assert a.diagnostics.tol_met and b.diagnostics.tol_met
    assert a.diagnostics.sweeps == b.diagnostics.sweeps
    assert np.max(np.abs(a.centers - b.centers)) < 1e-11
    assert np.max(np.abs(a.radii - b.radii)) < 1e-11
