"""Mesh levels start their first-sweep GNK solves from the previous level's solution.

The first guess changes the work, never the answer: GMRES stops at a residual relative to the
right-hand side, whatever it started from.
"""

from __future__ import annotations

import numpy as np
import pytest

import confnav
from confnav.conformal import solver
from confnav.conformal.boundary import BoundaryMesh, graded_polygon, resample

TRIANGLE = np.array([0.3 + 0.2j, 1.1 + 0.4j, 0.7 + 1.0j])


def _two_triangles() -> confnav.Workspace:
    """The certificate's mirror-symmetric pair (bench/bench_core.py, "triangles")."""
    room = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
    return confnav.Workspace(room, [-np.conj(TRIANGLE)[::-1], TRIANGLE], anchor=[0, -1])


def test_resample_carries_a_smooth_function_between_levels() -> None:
    """A function smooth in the mesh's side parameter, sampled on a coarse graded mesh, is
    reproduced on a finer one of the same polygon to the spline's O(h^4); a mesh of another
    polygon (a side split into two) is refused rather than mismatched."""
    square = np.array([0, 1, 1 + 1j, 1j], dtype=complex)
    coarse = graded_polygon(square, [40, 56, 40, 48]).reversed()
    fine = graded_polygon(square, [60, 84, 60, 72]).reversed()

    def f(m: BoundaryMesh) -> np.ndarray:
        x = m.side + m.tau / (2 * np.pi)
        return np.cos(2 * np.pi * x / 4) + 0.3 * np.sin(3 * 2 * np.pi * x / 4)

    got = resample(coarse, f(coarse), fine)
    assert got is not None
    assert np.max(np.abs(got - f(fine))) < 1e-5
    split = graded_polygon(np.r_[square[:2], 1 + 0.5j, square[2:]], [40, 20, 20, 40, 48])
    assert resample(coarse, f(coarse), split) is None


@pytest.mark.parametrize("tol", [1e-9])
def test_warm_start_gives_the_same_map_with_fewer_iterations(
    monkeypatch: pytest.MonkeyPatch, tol: float
) -> None:
    """Same circle domain to far below tol (the GMRES tolerance is 1e-3 tol), and fewer GMRES
    iterations in total (measured 143 -> 117 on this workspace)."""
    ws = _two_triangles()
    monkeypatch.setattr(solver, "WARM_START", False)
    cold = confnav.solve(ws, tol)
    monkeypatch.setattr(solver, "WARM_START", True)
    warm = confnav.solve(ws, tol)
    assert cold.diagnostics.nodes_per_side == warm.diagnostics.nodes_per_side
    assert np.max(np.abs(cold.centers - warm.centers)) < 1e-11
    assert np.max(np.abs(cold.radii - warm.radii)) < 1e-11
    assert warm.diagnostics.gmres_iterations < 0.9 * cold.diagnostics.gmres_iterations
    assert warm.diagnostics.tol_met and cold.diagnostics.tol_met
