"""Proximity grading of the polygon mesh (issue 8, item 2).

The local spacing of the graded mesh must satisfy ``h(x) <= 2 pi d(x) / (GRADING_STRIP
ln(10/tol))`` at every point x of a side, d(x) the distance of x to the nearest other boundary,
the anchor or a non-adjacent side of its own polygon (confnav.conformal.meshing). Checked here
on the mesh as built (spacing of consecutive nodes against the distance computed independently
with shapely), and by exact answers: mirror symmetry of a near-touching pair, the boundary
residual of a thin wall.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import shapely

from confnav import ConformalMap, Workspace, solve
from confnav.conformal.boundary import graded_polygon
from confnav.conformal.meshing import (
    GRADING_STRIP,
    LEVEL_BASE,
    MAX_NODES_PER_PANEL,
    plan_boundaries,
)

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
#: An L-shaped wall 0.15 thick (the apartment scene's interior walls): the two faces of each
#: arm are non-adjacent sides of the same polygon, 0.15 apart.
WALL = [[-1.0, -1.0], [1.0, -1.0], [1.0, -0.85], [-0.85, -0.85], [-0.85, 1.0], [-1.0, 1.0]]


def _max_spacing_ratio(ws: Workspace, tol: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Largest ``h / allowed`` over consecutive node pairs of every boundary at LEVEL_BASE,
    and the (node count, side) of the wall's plan."""
    plans = plan_boundaries(ws, LEVEL_BASE, tol)
    worst = 0.0
    for j, plan in enumerate(plans):
        mesh = graded_polygon(plan.vertices, plan.nodes)
        z = plan.vertices
        L = z.size
        for k in range(L):  # test code: per side is fine (a handful of sides)
            e = mesh.eta[mesh.side == k]
            e = np.append(e, z[(k + 1) % L])
            h = np.abs(np.diff(e))
            mid = 0.5 * (e[1:] + e[:-1])
            feats = [shapely.Point(ws.anchor.real, ws.anchor.imag)]
            feats += [
                shapely.LinearRing(np.column_stack([b.real, b.imag]))
                for i, b in enumerate(ws.boundaries)
                if i != j
            ]
            feats += [
                shapely.LineString(
                    [(z[i].real, z[i].imag), (z[(i + 1) % L].real, z[(i + 1) % L].imag)]
                )
                for i in range(L)
                if (i - k) % L not in (0, 1, L - 1)
            ]
            pts = shapely.points(mid.real, mid.imag)
            d = np.min([shapely.distance(pts, f) for f in feats], axis=0)
            allowed = 2 * np.pi * d / (GRADING_STRIP * np.log(10 / tol))
            worst = max(worst, float(np.max(h / allowed)))
    return worst, plans[1].nodes, plans[1].vertices


def test_thin_wall_is_graded_at_its_narrow_part() -> None:
    tol = 1e-8
    ws = Workspace(ROOM, [WALL], anchor=[1.0, 1.0])
    worst, nodes, _ = _max_spacing_ratio(ws, tol)
    # sampled rule (PROXIMITY_SAMPLES per side) and discrete vs continuous spacing: a few percent
    assert worst <= 1.05, worst
    # the faces along the thin arms (sides 0, 2, 3, 5: 0.15 from the opposite face) carry the
    # nodes; the end caps (sides 1 and 4, 0.15 long, adjacent to both faces) need few
    assert min(nodes[[0, 2, 3, 5]]) > 2 * max(nodes[[1, 4]]), nodes


def test_close_approach_at_a_corner_needs_few_nodes() -> None:
    """Two squares 0.01 apart: the facing sides are resolved all along, the sides meeting them
    only near the corner, where Kress's grading already makes the spacing small."""
    tol = 1e-8
    g = 0.005
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    ws = Workspace(ROOM, [left, right], anchor=[0, 1.5])
    worst, nodes, _ = _max_spacing_ratio(ws, tol)
    assert worst <= 1.05, worst
    facing, meeting = nodes[1], max(nodes[0], nodes[2])
    assert facing > 1000 and meeting < facing / 5, nodes


def _solve(ws: Workspace, tol: float) -> ConformalMap:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an AccuracyWarning fails the test
        return solve(ws, tol=tol)


def test_near_touching_mirror_pair_is_symmetric_to_tol() -> None:
    tol = 1e-7
    g = 0.025  # gap 0.05
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    m = _solve(Workspace(ROOM, [left, right], anchor=[0, 1.5]), tol)
    assert m.diagnostics.tol_met
    assert abs(m.radii[0] - m.radii[1]) <= tol
    assert abs(m.centers[0] + np.conj(m.centers[1])) <= tol
    assert m.diagnostics.boundary_residual <= tol


def test_thin_wall_map_passes_the_boundary_residual() -> None:
    tol = 1e-6
    m = _solve(Workspace(ROOM, [WALL], anchor=[1.0, 1.0]), tol)
    assert m.diagnostics.tol_met
    assert m.diagnostics.boundary_residual <= tol


def test_a_close_approach_narrower_than_the_samples_is_not_missed() -> None:
    """A corner 0.03 from the middle of a 4 m wall: narrower than the reach of the rule's
    samples along the wall (~6 cm), the wall still gets the spacing the gap needs."""
    tri = [[-0.3, -1.0], [0.0, -1.97], [0.3, -1.0]]
    worst, _, _ = _max_spacing_ratio(Workspace(ROOM, [tri], anchor=[0, 1.0]), 1e-6)
    assert worst <= 1.05, worst


def test_a_gap_along_part_of_a_long_wall_gets_its_own_panel() -> None:
    """near_touching: a 1.2 m table 0.05 from a 6 m wall. One panel per side forced the gap's
    spacing onto the whole wall (4337 nodes at 256 nodes per side: GapError, the solve stopped
    at 8.5e-9 for tol 1e-10). The wall is now split around the table (collinear vertices on
    the wall, exactly), no side exceeds the cap, and the spacing rule holds on every panel."""
    scene = Path(__file__).resolve().parents[1] / "bench" / "scenes" / "near_touching.json"
    ws = Workspace.load(scene)
    outer = plan_boundaries(ws, 256, 1e-10)[0]
    v = outer.vertices
    added = v[~np.isin(v, ws.boundaries[0])]
    assert np.isin(ws.boundaries[0], v).all() and added.size == 2
    assert np.all(added.imag == 0.0)  # on the wall y = 0
    assert 3.5 < added.real.min() < 4.0 and 5.2 < added.real.max() < 5.7  # table: 4 .. 5.2
    assert outer.nodes.max() <= MAX_NODES_PER_PANEL
    worst, _, _ = _max_spacing_ratio(ws, 1e-10)
    assert worst <= 1.05, worst
