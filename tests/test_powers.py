"""confnav.powers.power_table: the products np.cumprod forms, bitwise."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.powers import power_table


def _cumprod(x: np.ndarray, n: int) -> np.ndarray:
    """What the series evaluations did before: ones, then x repeated, accumulated."""
    t = np.empty((*x.shape, n + 1), dtype=np.complex128)
    t[..., 0] = 1.0
    t[..., 1:] = x[..., None]
    np.cumprod(t, axis=-1, out=t)
    return t


@pytest.mark.parametrize("shape", [(1000, 8), (1, 8), (7, 1), (2, 1), (1, 1), (16, 1), (300,)])
@pytest.mark.parametrize("n", [0, 1, 24, 48])
def test_power_table_is_cumprod_bitwise(shape: tuple[int, ...], n: int) -> None:
    rng = np.random.default_rng(sum(shape) + n)
    x = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) * rng.uniform(
        0.1, 1.2, shape
    )
    got = power_table(x, n)
    assert got.shape == (*shape, n + 1)
    assert np.array_equal(got, _cumprod(x, n))  # bitwise, not approximately


def test_power_table_rows_match_single_row_cumprod() -> None:
    """A row of a batch's table is bitwise the table of that point alone (the one-robot paths
    build theirs with np.cumprod on one row)."""
    rng = np.random.default_rng(5)
    x = (rng.standard_normal((500, 1)) + 1j * rng.standard_normal((500, 1))) * 0.9
    table = power_table(x, 48)
    for i in range(0, 500, 37):
        assert np.array_equal(table[i, 0], _cumprod(x[i, 0:1], 48)[0])


def test_power_table_values() -> None:
    x = np.array([2.0 + 0j, 1j, -0.5 + 0j])
    assert np.array_equal(power_table(x, 3).real[0], [1, 2, 4, 8])
    assert np.array_equal(power_table(x, 4)[1], [1, 1j, -1, -1j, 1])
    assert np.array_equal(power_table(x, 2)[2], [1, -0.5, 0.25])
