"""Fast trigonometric interpolation (confnav.conformal.triginterp) against the direct sum."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.conformal import circledomain
from confnav.conformal.triginterp import trig_eval, upsample
from confnav.scenes.workspaces import default_workspace
from confnav.types import CArray, FArray


def _direct(samples: CArray, x: FArray) -> tuple[CArray, CArray, CArray]:
    """Direct sum of the interpolant (modes -m/2..m/2, Nyquist split) and its first two
    derivatives, the phases k x reduced mod 2 pi in extended precision."""
    m = samples.size
    c = np.fft.fftshift(np.fft.fft(samples) / m)
    k = np.arange(-(m // 2), -(m // 2) + m).astype(float)
    if m % 2 == 0:
        c = np.r_[c, 0.5 * c[0]]
        c[0] *= 0.5
        k = np.r_[k, m / 2]
    kx = np.mod(np.outer(x.astype(np.longdouble), k.astype(np.longdouble)), 2 * np.pi)
    e = np.exp(1j * kx.astype(np.float64))
    return e @ c, e @ (1j * k * c), e @ (-(k**2) * c)


def _rel(a: CArray, b: CArray, scale: CArray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(scale)))


def _ok(got: CArray, ref: CArray, dref: CArray, x: FArray) -> bool:
    """``got`` within 1e-13 of max |ref|, plus the conditioning of the evaluation itself: each
    phase k x is only known to ~ eps |k x|, which moves the value by up to ~ eps |x| max |ref'|
    (a white spectrum up to mode m/2 has |ref'| ~ m |ref|: there this term dominates, for the
    direct sum too; for the solver's smooth data it is negligible)."""
    eps = np.finfo(np.float64).eps
    err = float(np.max(np.abs(got - ref)))
    return err <= 1e-13 * float(np.max(np.abs(ref))) + 2 * eps * float(
        np.max(np.abs(x)) * np.max(np.abs(dref))
    )


@pytest.mark.parametrize("m", [8, 37, 256, 2048])
def test_random_band_limited(m: int) -> None:
    """White spectrum up to the Nyquist mode (the hardest case for the local interpolation),
    odd and even m, points anywhere on the real line (periodicity), values and derivatives."""
    rng = np.random.default_rng(m)
    s = rng.standard_normal(m) + 1j * rng.standard_normal(m)
    x = np.r_[rng.uniform(-2 * np.pi, 4 * np.pi, 3000), 2 * np.pi * np.arange(m) / m]
    val, der, der2 = _direct(s, x)
    got = trig_eval(s, x, derivative=True)
    assert got.shape == (2, x.size)
    assert _ok(got[0], val, der, x)
    assert _ok(got[1], der, der2, x)
    assert _ok(got[0, -m:], s, der[-m:], x[-m:])  # interpolates the samples


def test_decaying_spectrum_large_m() -> None:
    """An analytic periodic function (geometric Fourier decay) on m = 16384 points: the
    evaluation is at rounding level, several rows at once."""
    m = 16384
    t = 2 * np.pi * np.arange(m) / m
    f = np.stack([1 / (1.05 - np.exp(1j * t)), np.exp(np.cos(3 * t)) + 0j])
    x = np.random.default_rng(1).uniform(0, 2 * np.pi, 500)
    exact = np.stack([1 / (1.05 - np.exp(1j * x)), np.exp(np.cos(3 * x)) + 0j])
    got = trig_eval(f, x)
    for r in range(2):
        val, der, _ = _direct(f[r], x)
        assert _ok(got[r], val, der, x)
    assert _rel(got[1], exact[1], exact[1]) < 1e-13  # fully resolved: the function itself


def test_upsample_is_the_interpolant() -> None:
    rng = np.random.default_rng(2)
    s = rng.standard_normal(64) + 1j * rng.standard_normal(64)
    fine = upsample(s, 256)
    x = 2 * np.pi * np.arange(256) / 256
    assert _rel(fine, _direct(s, x)[0], s) < 1e-13


def test_solver_data(monkeypatch: pytest.MonkeyPatch) -> None:
    """The smooth grids and passive parameters the Koebe iteration actually evaluates (default
    workspace): every call agrees with the direct sum to 1e-13 of max |f|, plus the phases'
    conditioning (:func:`_ok`). That term matters for the carried levels' Taylor rows (the
    recorded curves' s-derivatives up to order 8, ``circledomain._derivative_rows``), whose
    spectra are dominated by their top modes: on such a row of 416 samples at x ~ 2 pi the
    interpolant and the direct sum each stood ~5e-14 of max |f| from an extended-precision
    sum, 1.1e-13 apart (with grid sizes of eighths of an octave; 8.5e-14 on a 512-sample row
    before, where the sampled calls were other ones)."""
    calls: list[tuple[CArray, FArray]] = []
    real = circledomain.trig_eval

    def spy(rows: CArray, x: FArray, derivative: bool = False) -> CArray:
        calls.append((np.atleast_2d(np.asarray(rows, np.complex128)).copy(), x.copy()))
        return real(rows, x, derivative)

    monkeypatch.setattr(circledomain, "trig_eval", spy)
    import confnav

    confnav.solve(default_workspace(), 1e-6)
    assert calls
    for rows, x in calls[:: max(1, len(calls) // 12)]:
        got = real(rows, x, derivative=True)
        for r, f in enumerate(rows):
            val, der, der2 = _direct(f, x)
            assert _ok(got[r], val, der, x)
            assert _ok(got[rows.shape[0] + r], der, der2, x)
