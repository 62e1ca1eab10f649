"""``confnav.solve`` runs with one BLAS thread (solver.SOLVE_BLAS_THREADS) unless the
environment sets a count, and restores the count on return; the map is the same."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import confnav
from confnav import Workspace
from confnav.conformal import solver

ROOM = [[0, 0], [2, 0], [2, 1], [0, 1]]
PILLAR = [[[0.8, 0.4], [1.2, 0.4], [1.2, 0.6], [0.8, 0.6]]]


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def _solve_seeing_threads() -> tuple[confnav.ConformalMap, list[list[int]]]:
    seen: list[list[int]] = []
    m = confnav.solve(
        Workspace(ROOM, PILLAR, anchor=[0.3, 0.5]),
        tol=1e-6,
        progress=lambda _msg: seen.append(_blas_threads()),
    )
    return m, seen


@pytest.mark.skipif(not _blas_threads(), reason="no BLAS library found by threadpoolctl")
def test_solve_runs_with_one_blas_thread_and_restores_the_count(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for var in solver.BLAS_THREAD_ENV:
        monkeypatch.delenv(var, raising=False)
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        m1, seen = _solve_seeing_threads()
        assert seen and all(set(s) == {1} for s in seen)
        assert _blas_threads() == before  # restored on return
        monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
        m2, seen2 = _solve_seeing_threads()
        assert seen2 and all(s == before for s in seen2)  # the environment's count wins
    # the same arithmetic whatever the thread count: the same map to rounding
    assert np.max(np.abs(m1.radii - m2.radii)) < 1e-12
    assert np.max(np.abs(m1.centers - m2.centers)) < 1e-12
