"""Property tests: on random easy workspaces the solver is accurate (a typed error fails).

Accuracy is checked independently of the solver's own estimate: points on the obstacle sides
(off the mesh nodes) must land on their circles, and a solve at a 100x smaller tolerance must
agree with the first one within its tolerance.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import confnav
from confnav import CrowdingError, Workspace

SQUARE = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
TOL = 1e-5


@st.composite
def workspaces(draw: st.DrawFn) -> Workspace:
    """1-3 rectangles or triangles, one per cell of a 2x2 grid (disjoint by construction)."""
    n = draw(st.integers(1, 3))
    cells = draw(st.permutations(range(4)))[:n]
    obstacles = []
    for c in cells:
        cx, cy = -0.5 + (c % 2), -0.5 + (c // 2)
        # well separated (issue 8: these must solve): gaps >= 0.15 to the walls and >= 0.3
        # between obstacles; near-touching pairs are tests/test_accuracy_certificate.py's
        w = draw(st.floats(0.08, 0.3))
        h = draw(st.floats(0.08, 0.3))
        dx = draw(st.floats(-0.05, 0.05))
        dy = draw(st.floats(-0.05, 0.05))
        x0, y0 = cx + dx, cy + dy
        if draw(st.booleans()):
            obstacles.append(
                [[x0 - w, y0 - h], [x0 + w, y0 - h], [x0 + w, y0 + h], [x0 - w, y0 + h]]
            )
        else:
            obstacles.append([[x0 - w, y0 - h], [x0 + w, y0 - h], [x0, y0 + h]])
    return Workspace(SQUARE, obstacles)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(workspaces())
def test_random_workspaces_are_accurate_or_rejected(ws: Workspace) -> None:
    # 1-3 well-separated convex obstacles are easy: a typed error is a failure here
    with warnings.catch_warnings():
        warnings.simplefilter("error", confnav.AccuracyWarning)
        m = confnav.solve(ws, tol=TOL)
    with warnings.catch_warnings():  # the reference: its own tol may be out of reach
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        fine = confnav.solve(ws, tol=TOL / 100)
    assert m.diagnostics.tol_met, m.diagnostics.table()
    assert m.diagnostics.boundary_residual <= TOL
    # independent refinement: the finer solve agrees within the requested tolerance
    assert np.max(np.abs(m.centers - fine.centers)) <= TOL
    assert np.max(np.abs(m.radii - fine.radii)) <= TOL
    # boundary residual: side points off the nodes land on their circles
    for j, poly in enumerate(ws.obstacles):
        pts = poly + 0.37 * (np.roll(poly, -1) - poly)
        r = np.abs(m.T(pts) - m.centers[j])
        np.testing.assert_allclose(r, m.radii[j], atol=10 * TOL)
    outer_pts = ws.outer + 0.37 * (np.roll(ws.outer, -1) - ws.outer)
    np.testing.assert_allclose(np.abs(m.T(outer_pts)), 1.0, atol=10 * TOL)


def test_crowding_is_detected_not_returned() -> None:
    # an obstacle in a chamber behind a corridor of length/width 10: its circle would have a
    # radius ~exp(-pi * 10) ~ 1e-14, below what double precision resolves (docs/METHOD.md sec. 6)
    h = 0.05
    outer = [
        [-1, -1],
        [1, -1],
        [1, -h],
        [2, -h],
        [2, -0.3],
        [2.6, -0.3],
        [2.6, 0.3],
        [2, 0.3],
        [2, h],
        [1, h],
        [1, 1],
        [-1, 1],
    ]
    ws = Workspace(outer, [[[2.2, -0.1], [2.4, -0.1], [2.4, 0.1], [2.2, 0.1]]])
    with pytest.raises(CrowdingError, match="too small to resolve in double precision"):
        confnav.solve(ws, tol=1e-8)
