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
    need = np.log(1 / tail) / np.pi
    if ratio >= need:
        return m, False
    want = int(2 ** np.ceil(np.log2(m * need / max(ratio, 1e-12))))
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
