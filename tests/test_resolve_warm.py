"""Warm re-solve from the previous map (issue 24 item 3, confnav/conformal/warm.py).

The start is built from exact identities (the Cauchy decomposition of a map over its
boundaries, the jump relation); each is checked on its own, then the warm map against a cold
solve of the same workspace and against the mirror symmetry of a symmetric change.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import confnav
from confnav import ConformalMap, Workspace
from confnav.conformal import solver, warm
from confnav.scenes.workspaces import MIRROR_ROOM, mirror_asymmetry, mirror_squares

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
L_SHAPE = [[-0.5, -0.5], [0.3, -0.5], [0.3, -0.2], [-0.2, -0.2], [-0.2, 0.3], [-0.5, 0.3]]


def _solve(ws: Workspace, tol: float, **kw: object) -> ConformalMap:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        return confnav.solve(ws, tol=tol, **kw)  # type: ignore[arg-type]


def _far(m: ConformalMap, seed: int) -> np.ndarray:
    """Free-space points 0.3 or more from the walls: the plain trapezoidal Cauchy sums (no
    barycentric quotient) are accurate only there (near a wall they err like e^(-2 pi d/h))."""
    z = m._check_points(seed, 400)
    return np.asarray(z[m.workspace.clearance(z) > 0.3][:50])


def _distance(a: ConformalMap, b: ConformalMap) -> float:
    return float(max(np.max(np.abs(a.centers - b.centers)), np.max(np.abs(a.radii - b.radii))))


def box(x: float, y: float, s: float = 0.4) -> list[list[float]]:
    return [[x, y], [x + s, y], [x + s, y + s], [x, y + s]]


def room(dx: float = 0.0) -> Workspace:
    ell = [[x + 1.0, y + 1.0] for x, y in L_SHAPE]  # reflex corner: one the map compresses
    return Workspace(ROOM, [box(-1.5, -1.5), box(0.5 + dx, -1.0), ell], anchor=[0.0, 0.0])


@pytest.fixture(scope="module")
def cold() -> ConformalMap:
    return _solve(room(), 1e-8)


def test_the_cauchy_terms_of_the_boundaries_sum_to_the_map(cold: ConformalMap) -> None:
    eta, deta, W, dW = cold._parts
    comps = warm._components(eta, deta, W, dW)
    z = _far(cold, 0)
    total = sum(warm._term(c, z)[0] for c in comps)
    dtotal = sum(warm._term(c, z)[1] for c in comps)
    assert np.max(np.abs(total - cold.T(z))) < 1e-8
    assert np.max(np.abs(dtotal - cold.dT(z))) < 1e-7


def test_an_unchanged_workspace_starts_on_the_previous_map(cold: ConformalMap) -> None:
    st = warm.warm_state(cold, room(), 1e-8)
    assert st is not None
    for p, w in zip(st.P, cold._parts[2], strict=True):
        assert np.array_equal(p, w)  # no term moved: the previous boundary values exactly
    assert st.deviation < 1e-8  # the previous circles (their circularity)
    assert abs(st.a) < 1e-12
    assert abs(st.D - complex(cold.dT(np.array([0j]))[0])) < 1e-9


def test_the_start_of_a_moved_obstacle_is_analytic_on_the_new_domain(cold: ConformalMap) -> None:
    """Its boundary values (the jump relation) and its values inside (the moved sums) are two
    computations of one analytic function: the Cauchy formula of the first gives the second."""
    ws = room(dx=0.2)
    st = warm.warm_state(cold, ws, 1e-8)
    assert st is not None
    assert st.source == [0, 1, 2, 3]
    eta = [m.eta for m in st.meshes]
    deta = [m.deta for m in st.meshes]
    start = ConformalMap(ws, eta, deta, st.P, st.dP, cold.centers, cold.radii, cold.diagnostics)
    comps = warm._components(*cold._parts)
    shift = [0j, 0j, 0.2 + 0j, 0j]
    z = _far(start, 1)
    poles, beta = warm._corner_correction(ws, st.source, shift, comps, dict(enumerate(shift)))
    inside = sum(warm._term(c, z - d)[0] for c, d in zip(comps, shift, strict=True))
    inside = inside - warm._rational(poles, beta, z)[0]
    assert np.max(np.abs(start.T(z, check=False) - inside)) < 1e-7
    assert start.T(np.array([ws.anchor]), check=False)[0] == pytest.approx(st.a, abs=1e-7)


def test_the_corner_correction_cancels_the_linear_term_at_compressed_corners(
    cold: ConformalMap,
) -> None:
    ws = room(dx=0.2)
    comps = warm._components(*cold._parts)
    shift = [0j, 0j, 0.2 + 0j, 0j]
    kept = dict(enumerate(shift))
    poles, beta = warm._corner_correction(ws, [0, 1, 2, 3], shift, comps, kept)
    assert poles.size == 4 + 1  # the room's four corners, the L's reflex corner
    assert not np.any(ws.contains(poles))  # outside the free space: L is analytic on it
    ell = np.array([complex(x + 1.0, y + 1.0) for x, y in L_SHAPE])
    v = ell[3]  # the reflex corner (-0.2, -0.2) + (1, 1)
    q = warm._perturbation(comps, kept, 3, 0j, np.array([v]), 1e-12)[1][0]
    assert abs(q) > 1e-5  # the moved box pulls on it
    assert abs(q - warm._rational(poles, beta, np.array([v]))[1][0]) < 1e-12 * max(1, abs(q))


def test_a_moved_obstacle_re_solves_at_one_level_to_the_cold_map(cold: ConformalMap) -> None:
    ws = room(dx=0.2)
    hot = _solve(ws, 1e-8, initial=cold)
    ref = _solve(ws, 1e-8)
    d = hot.diagnostics
    assert d.tol_met and ref.diagnostics.tol_met, d.table()
    assert [r.get("warm_start") for r in d.refinements] == [1.0]  # one level, warm
    assert d.nodes_per_side == cold.diagnostics.nodes_per_side
    r = d.refinements[0]
    assert r["error_estimate"] == pytest.approx(r["inherited_error"] * (1 + r["deviation"]))
    assert d.error_estimate >= max(d.iteration_error, d.boundary_residual)
    assert _distance(hot, ref) <= d.error_estimate + ref.diagnostics.error_estimate


def test_a_narrowed_gap_falls_back_to_the_levels(cold: ConformalMap) -> None:
    """The moved box within 0.05 of the wall: the previous mesh does not resolve the new gap,
    so the warm start declines and the levels run (the full three-level certificate)."""
    ws = room(dx=1.05)
    assert warm.warm_state(cold, ws, 1e-8) is None
    m = _solve(ws, 1e-8, initial=cold)
    assert m.diagnostics.tol_met
    assert not any("warm_start" in r for r in m.diagnostics.refinements)


def test_a_symmetric_move_keeps_the_mirror_symmetry() -> None:
    """Both squares moved down by 0.05: the new circle domain is mirror symmetric exactly, so
    the warm map's asymmetry is a true error its estimate must bound."""
    before = mirror_squares(0.3)
    after = Workspace(
        MIRROR_ROOM, [np.asarray(o) - 0.05j for o in before.obstacles], anchor=before.anchor
    )
    hot = _solve(after, 1e-8, initial=_solve(before, 1e-8))
    d = hot.diagnostics
    assert d.tol_met and any("warm_start" in r for r in d.refinements), d.table()
    assert mirror_asymmetry(hot.centers, hot.radii) <= d.error_estimate
    ref = _solve(after, 1e-8)
    assert _distance(hot, ref) <= d.error_estimate + ref.diagnostics.error_estimate


def test_without_the_warm_path_the_levels_start_higher(
    cold: ConformalMap, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(solver, "WARM_RESOLVE", False)
    m = _solve(room(dx=0.2), 1e-8, initial=cold)
    assert m.diagnostics.tol_met
    assert "ratio" in m.diagnostics.refinements[1]  # three levels observed


def test_another_room_or_mostly_new_obstacles_start_cold(cold: ConformalMap) -> None:
    ws = room()
    bigger = Workspace([[-2.5, -2], [2, -2], [2, 2], [-2.5, 2]], ws.obstacles, anchor=[0.0, 0.0])
    assert warm.warm_state(cold, bigger, 1e-8) is None  # the outer boundary changed
    others = Workspace(ROOM, [box(-1.4, -1.5, 0.3), box(0.6, -1.0, 0.3)], anchor=[0.0, 0.0])
    assert warm.warm_state(cold, others, 1e-8) is None  # no obstacle kept
    m = _solve(others, 1e-8, initial=cold)
    assert m.diagnostics.tol_met and "ratio" in m.diagnostics.refinements[1]
