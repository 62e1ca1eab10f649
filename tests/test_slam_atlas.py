"""Atlas charts on real SLAM maps (issue 23, "Real SLAM maps"): what failed there, reproduced
on a small cell (one the decomposition cut from nav2's tb3_sandbox shrunk by a 0.22 m body plus
a 0.1 m look-ahead, tests/data/slam/NOTICE; bench/bench_slam.py drives the whole maps)."""

from __future__ import annotations

import warnings

import pytest

import confnav
from confnav.atlas.charts import _solve_one
from confnav.conformal.solver import UNUSABLE_ERROR, AccuracyWarning
from confnav.geometry import Workspace

#: A cell of tb3_sandbox shrunk by 0.32 m (rounded to the micrometre): solved to 1e-3 its map's
#: error estimate is about 4e-4, inside the tolerance asked for but above UNUSABLE_ERROR.
SANDBOX_CELL = [
    (-1.637007, 1.410445),
    (-1.687007, 1.360445),
    (-1.744730, 1.244999),
    (-1.560271, 1.244999),
    (-1.438514, 1.488514),
    (-1.296556, 1.559493),
    (-1.296556, 1.677940),
    (-1.517039, 1.650380),
]


def test_a_coarse_chart_is_accepted_up_to_its_tolerance() -> None:
    """A chart asked for 1e-3 (the first, coarse rung) whose estimate lies between
    UNUSABLE_ERROR (1e-4) and 1e-3 is a chart, not a failure: before, every such cell failed,
    its tile was split down to the smallest side and the atlas of tb3_sandbox and of nav2's
    depot raised SolverError ("estimated error 2.2e-04 is too large to navigate with")."""
    ws = Workspace(SANDBOX_CELL, [])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        est = confnav.solve(ws, 1e-3, max_error=1e-2).diagnostics.error_estimate
    assert UNUSABLE_ERROR < est <= 1e-3  # the case: refused by solve's default max_error
    chart, _, err = _solve_one(ws.to_json(), 1e-3, 1e-2, 0.01)
    assert err == ""
    m = confnav.ConformalMap.from_json(chart)
    assert m.diagnostics.error_estimate == pytest.approx(est)
    assert m.diagnostics.tol_met


def test_a_tight_tolerance_keeps_refusing_unusable_charts() -> None:
    """tol 1e-8 keeps the refusal threshold of solve (max(UNUSABLE_ERROR, tol, accept)): the
    cell above then solves to 1e-8 rather than stopping at 4e-4."""
    ws = Workspace(SANDBOX_CELL, [])
    chart, _, err = _solve_one(ws.to_json(), 1e-8, 1e-6, 0.01)
    assert err == ""
    assert confnav.ConformalMap.from_json(chart).diagnostics.error_estimate <= 1e-6
