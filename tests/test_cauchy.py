"""Fast Cauchy sums (confnav/conformal/cauchy.py) against direct summation in long double.

Every path (multipole outside a curve, local expansion inside it, FMM and direct near it) must
agree with the exact sum to the rounding of a direct double-precision sum: errors are scaled
by ``sum |q_k| / d`` (``sum |q_k| / d^2`` for the second-order sums), d the distance from the
target to the nearest source, the size of one term.
"""

from __future__ import annotations

import numpy as np
import pytest

import confnav.conformal.cauchy as cy


def _exact(s: np.ndarray, Q: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = 1 / (t[:, None].astype(np.clongdouble) - s[None, :].astype(np.clongdouble))
    Ql = Q.astype(np.clongdouble)
    return (r @ Ql).astype(np.complex128), ((r * r) @ Ql).astype(np.complex128)


def _curve(n: int, centre: complex, size: float) -> np.ndarray:
    th = 2 * np.pi * np.arange(n) / n
    return np.asarray(centre + size * (1 + 0.3 * np.cos(3 * th)) * np.exp(1j * th))


@pytest.mark.parametrize(
    ("centre", "size", "box", "fmm"),
    [
        (0.3 + 0.1j, 0.2, 3.0, False),  # a hole: most targets far outside (multipole)
        (0.0, 1.0, 0.65, False),  # an outer curve: targets inside (local expansion)
        (0.0, 1.0, 0.65, True),  # the same with the near targets on the FMM
    ],
)
def test_sums_match_long_double(
    centre: complex, size: float, box: float, fmm: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if fmm:
        if not cy.HAVE_FMM:
            pytest.skip("pyfmmlib not available")
        monkeypatch.setattr(cy, "FMM_THRESHOLD", 1000)
    rng = np.random.default_rng(3)
    s = _curve(600, centre, size)
    Q = rng.normal(size=(s.size, 3)) + 1j * rng.normal(size=(s.size, 3))
    t = box * (rng.uniform(-1, 1, 3000) + 1j * rng.uniform(-1, 1, 3000))
    d = np.min(np.abs(t[:, None] - s[None, :]), axis=1)
    t = t[d > 1e-3]
    d = d[d > 1e-3]
    one, two = cy.cauchy_sums2(s, list(Q.T), t, second=True)
    ref1, ref2 = _exact(s, Q, t)
    scale = np.sum(np.abs(Q), axis=0)[None, :]
    err1 = np.abs(np.column_stack(one) - ref1) * d[:, None] / scale
    err2 = np.abs(np.column_stack(two) - ref2) * d[:, None] ** 2 / scale
    # pyfmmlib at FMM_IPREC = 4: ~1e-15 for the field, ~1e-13 for the Hessian (measured)
    assert np.max(err1) <= 1e-14 and np.max(err2) <= (1e-13 if fmm else 1e-14)
    first_only = cy.cauchy_sums(s, list(Q.T), t)
    np.testing.assert_array_equal(np.column_stack(first_only), np.column_stack(one))


def test_expansions_cover_the_far_targets() -> None:
    """The split itself: far targets take an expansion, the others are left to the direct sum
    (checked through which targets the expansion pass leaves)."""
    s = _curve(200, 0.0, 0.1)  # radius <= 0.13
    t = np.array([0.2, 0.3, 0.35, 1.0, 10.0], dtype=np.complex128)
    t = np.concatenate([t, np.full(40, 5.0 + 0j)])  # enough targets to expand
    one = np.empty((t.size, 1), np.complex128)
    left = cy._expanded(s, np.ones((s.size, 1), np.complex128), t, one, None)
    c = 0.5 * complex(s.real.min() + s.real.max(), s.imag.min() + s.imag.max())
    R = np.max(np.abs(s - c))
    near = {i for i in range(t.size) if R / abs(t[i] - c) > cy.EXPANSION_RATIO}
    assert near == {0, 1} and set(left.tolist()) == near


def test_degrees_bound_the_truncation() -> None:
    for edge, p in zip(cy.EXPANSION_BANDS, cy._BAND_DEGREES, strict=True):
        assert cy._tail_bound(edge, p) <= cy.EXPANSION_EPS < cy._tail_bound(edge, p - 1)


def test_powers_are_the_cumulative_products() -> None:
    """The expansions' power table equals ``cumprod`` of the same factors to rounding (a
    complex product may round differently in numpy's two loops: one ulp per factor)."""
    rng = np.random.default_rng(5)
    w = rng.normal(size=300) + 1j * rng.normal(size=300)
    for p in (0, 1, 2, 17):
        W = np.empty((w.size, p + 1), np.complex128)
        W[:, 0] = 1.0
        W[:, 1:] = w[:, None]
        np.cumprod(W, axis=1, out=W)
        np.testing.assert_allclose(cy._powers(w, p), W.T, rtol=4 * max(p, 1) * 2.0**-52, atol=0)
