"""The GNK solve on the FMM path: exact answers, agreement with the dense path, and its count of
FMM sums (each is ~20 ms on a 4096-point smooth grid, and near-touching obstacles make
thousands of them: issue 8)."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.conformal import cauchy, gnk
from confnav.conformal.diskmap import exterior_map, interior_map

pytestmark = pytest.mark.skipif(not cauchy.HAVE_FMM, reason="pyfmmlib not available")

A_AX, B_AX, N = 2.0, 1.0, 768


def _ellipse_cw() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = 2 * np.pi * np.arange(N) / N
    return t, A_AX * np.cos(t) - 1j * B_AX * np.sin(t), -A_AX * np.sin(t) - 1j * B_AX * np.cos(t)


@pytest.fixture
def fmm_calls(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Force the FMM path of the GNK operator for a small curve and count the FMM sums."""
    monkeypatch.setattr(gnk, "DENSE_MAX_NODES", 0)
    monkeypatch.setattr(cauchy, "FMM_THRESHOLD", 1000)
    calls = [0]
    real = cauchy._fmm

    def counted(*args: object, **kwargs: object) -> object:
        calls[0] += 1
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(cauchy, "_fmm", counted)
    return calls


def test_fmm_path_exterior_map_of_an_ellipse_is_exact(fmm_calls: list[int]) -> None:
    """Joukowski: z = (a+b)/2 w + (a-b)/2 / w maps |w| > 1 onto the outside of the ellipse, so
    F(a cos t - i b sin t) = e^{-it} and F'(inf) = 2/(a+b); h (hence F'(inf)) comes from
    M mu, which the solve takes from GMRES's last product."""
    t, eta, deta = _ellipse_cw()
    F = exterior_map(eta, deta, 0j)
    assert abs(F.scale - 2 / (A_AX + B_AX)) <= 1e-13
    assert np.max(np.abs(F.f - np.exp(-1j * t))) <= 1e-12
    assert fmm_calls[0] > 0  # the FMM path was taken


def test_fmm_path_counts_one_sum_per_iteration_plus_three(fmm_calls: list[int]) -> None:
    """Per solve: the operator's row sums, S(gamma) (giving both M gamma for the right-hand
    side and (I - N) gamma for h), one per GMRES iteration and GMRES's closing true residual,
    whose sum also gives M mu: iterations + 3 (it was + 5)."""
    _, eta, deta = _ellipse_cw()
    alpha = 0.3 + 0.2j
    A = eta[::-1] - alpha  # the interior problem of the same ellipse, counter-clockwise
    gamma = -np.log(np.abs(A))
    sol = gnk.solve_gnk(eta[::-1], -deta[::-1], A, gamma, rtol=1e-13)
    assert sol.iterations < gnk.GMRES_RESTART  # one cycle: no restart products
    assert fmm_calls[0] == sol.iterations + 3


def test_fmm_and_dense_paths_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """The interior map of the ellipse (alpha off-centre: no closed form) on both paths."""
    _, eta, deta = _ellipse_cw()
    eta, deta = eta[::-1], -deta[::-1]
    dense = interior_map(eta, deta, 0.3 + 0.2j)
    monkeypatch.setattr(gnk, "DENSE_MAX_NODES", 0)
    monkeypatch.setattr(cauchy, "FMM_THRESHOLD", 1000)
    fmm = interior_map(eta, deta, 0.3 + 0.2j)
    assert abs(fmm.scale - dense.scale) <= 1e-13 * dense.scale
    assert np.max(np.abs(fmm.f - dense.f)) <= 1e-12


def test_smooth_grid_takes_the_matrix_free_path_and_agrees(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A smooth grid above SMOOTH_DENSE_MAX_NODES (but below DENSE_MAX_NODES) is solved with
    FMM products, not a dense matrix, and gives the dense map: the same operator."""
    monkeypatch.setattr(gnk, "SMOOTH_DENSE_MAX_NODES", 512)
    monkeypatch.setattr(cauchy, "FMM_THRESHOLD", 1000)
    _, eta, deta = _ellipse_cw()
    eta, deta = eta[::-1], -deta[::-1]
    built: list[bool] = []
    real_init = gnk._Operator.__init__

    def spy(self: gnk._Operator, *args: object, **kwargs: object) -> None:
        real_init(self, *args, **kwargs)  # type: ignore[arg-type]
        built.append(self.dense)

    monkeypatch.setattr(gnk._Operator, "__init__", spy)
    dense = interior_map(eta, deta, 0.3 + 0.2j)
    smooth = interior_map(eta, deta, 0.3 + 0.2j, smooth=True)
    assert built == [True, False]
    assert abs(smooth.scale - dense.scale) <= 1e-13 * dense.scale
    assert np.max(np.abs(smooth.f - dense.f)) <= 1e-12
