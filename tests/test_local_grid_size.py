"""``circledomain._local_grid_size`` looks up only the points near the curve: the same sizes
as looking up every point (the rule it implements, written out here)."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.conformal import circledomain as cd


def _all_points(S: np.ndarray, dS: np.ndarray, others: np.ndarray, tail: float) -> tuple[int, bool]:
    """The rule on every point: d/h >= ln(1/tail)/pi at the nearest grid point's spacing."""
    m = S.size
    d = np.abs(others[:, None] - S[None, :])
    i = np.argmin(d, axis=1)
    h = np.abs(dS[i]) * 2 * np.pi / m
    ratio = float(np.min(d[np.arange(others.size), i] / h))
    need = cd.TAIL_BAND * np.log(1 / tail) / np.pi  # modes from 7m/16 on (what _tail reads)
    if ratio >= need:
        return m, False
    want = cd._round_size(m * need / max(ratio, 1e-12))  # the grid-size ladder (GRID_STEPS)
    return min(want, cd.SMOOTH_MAX), want > cd.SMOOTH_MAX


@pytest.mark.parametrize("m", [64, 256])
@pytest.mark.parametrize("gap", [1e-1, 3e-3, 1e-4, 1e-7])
def test_sizes_equal_the_rule_on_every_point(m: int, gap: float) -> None:
    """An ellipse-like curve and a cloud of points, one of them ``gap`` from the curve."""
    rng = np.random.default_rng(int(1e4 * gap) + m)
    s = 2 * np.pi * np.arange(m) / m
    S = (1.0 + 0.2 * np.cos(2 * s)) * np.exp(1j * s) + (0.3 - 0.1j)
    dS = np.gradient(S) * m / (2 * np.pi)  # a spacing scale is all the rule reads
    far = 3.0 * (rng.uniform(-1, 1, 2000) + 1j * rng.uniform(-1, 1, 2000))
    far = far[np.min(np.abs(far[:, None] - S[None, :]), axis=1) > 0.05]
    k = 17
    normal = 1j * (S[(k + 1) % m] - S[k - 1])
    close = S[k] + gap * normal / abs(normal) * np.array([1.0, 2.0, 5.0])
    others = np.concatenate([far, close])
    tail = 1e-11
    assert cd._local_grid_size(S, dS, others, tail) == _all_points(S, dS, others, tail)
    assert cd._local_grid_size(S, dS, far, tail) == _all_points(S, dS, far, tail)


@pytest.mark.parametrize("steps", [1, 8])
def test_round_size_is_the_smallest_size_of_the_ladder(
    steps: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``_round_size``: the smallest ``2^k (1 + j/steps)`` at least the need (and at least
    2 steps, so even), powers of two with one step per octave."""
    monkeypatch.setattr(cd, "GRID_STEPS", steps)
    ladder = sorted(
        {2**k * (steps + j) // steps for k in range(16) if 2**k >= steps for j in range(steps)}
        | {2**16}
    )
    for need in [1.0, 16.0, 17.0, 63.9, 64.0, 65.0, 396.2, 2235.0, 4096.0, 4097.0, 16383.5]:
        got = cd._round_size(need)
        want = min(n for n in ladder if n >= max(need, 2 * steps))
        assert got == want, (need, got, want)
        assert got % 2 == 0


def test_grading_search_never_leaves_a_smaller_gap(monkeypatch: pytest.MonkeyPatch) -> None:
    """The golden-section search between the list's strengths keeps the list's best when it
    finds nothing better, and finds the larger gap between two near-touching circles."""
    s = 2 * np.pi * np.arange(2000) / 2000
    for gap in (1e-3, 1e-2, 3e-2):
        other = (1.3 + gap) + 0.3 * np.exp(1j * s)
        monkeypatch.setattr(cd, "GRADING_REFINE", 0)
        _c0, g0 = cd._grading(other)
        monkeypatch.setattr(cd, "GRADING_REFINE", 8)
        c1, g1 = cd._grading(other)
        assert g1 >= g0 > 0
        assert abs(c1) <= cd.GRADING_RHO[-1]
        # the gap reported is the gap of the grading returned
        zeta = (other - c1) / (1.0 - np.conj(c1) * other)
        assert g1 == pytest.approx(min(np.min(np.abs(np.abs(zeta) - 1.0)), 1 / abs(c1) - 1), 1e-12)
    assert g1 > 1.05 * g0  # at 0.03 the list's best (0.8) left 0.25, the search 0.27
