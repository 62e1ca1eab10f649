"""Issue 24 items 2-3: refine only the sides whose residual asks; warm re-solves.

Both must give the map a cold, everywhere-refined solve gives, to the tolerance both certify,
with the full certificate (three levels, residual).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import confnav
from confnav import ConformalMap, Workspace
from confnav.conformal import solver
from confnav.conformal.boundary import BoundaryMesh, graded_polygon
from confnav.conformal.circledomain import _reusable, koebe_iteration
from confnav.conformal.diskmap import exterior_map
from confnav.conformal.meshing import PanelPlan, plan_boundaries
from confnav.geometry import interior_point
from confnav.scenes.workspaces import default_workspace, mirror_squares

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]


def _solve(ws: Workspace, tol: float, **kw: object) -> ConformalMap:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        return confnav.solve(ws, tol=tol, **kw)  # type: ignore[arg-type]


def _distance(a: ConformalMap, b: ConformalMap) -> float:
    return float(max(np.max(np.abs(a.centers - b.centers)), np.max(np.abs(a.radii - b.radii))))


def box(x: float, y: float, s: float = 0.4) -> list[list[float]]:
    return [[x, y], [x + s, y], [x + s, y + s], [x, y + s]]


def room(dx: float = 0.0, extra: bool = False) -> Workspace:
    obstacles = [box(-1.5, -1.5), box(0.5 + dx, -1.0), box(-1.0, 0.8)]
    if extra:
        obstacles.append(box(1.0, 1.0, 0.3))
    return Workspace(ROOM, obstacles, anchor=[0.0, 0.0])


# ---------------------------------------------------------------- per-side refinement
def test_sides_asked_for_by_the_residual_are_the_ones_refined() -> None:
    ws = mirror_squares(0.1)
    m = _solve(ws, 1e-6, nodes_per_side=54)
    plans = solver.plan_boundaries(ws, 54, 1e-6)
    z, res, owner = m.boundary_residuals()
    tol = float(np.quantile(res, 0.98))  # a tolerance that only a few points miss
    bad = solver._bad_sides(m, plans, tol)
    assert 0 < len(bad) < sum(p.nodes.size for p in plans)
    for zi, j in zip(z[res > tol], owner[res > tol], strict=True):
        v = np.asarray(plans[int(j)].vertices)
        sides = [k for jj, k in bad if jj == j]
        a, e = v[sides], np.roll(v, -1)[sides] - v[sides]
        t = np.clip(((zi - a) * np.conj(e)).real / np.abs(e) ** 2, 0, 1)
        assert np.min(np.abs(zi - (a + t * e))) < 1e-12  # the point lies on a returned side


def test_local_refinement_gives_the_full_refinements_map(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two squares 0.1 apart at 1e-8: the discretisation is met at 80 nodes per side but the
    residual (1e-6) is not; refining only the sides it names meets tol and gives the circle
    domain of the everywhere-refined solve, mirror symmetric."""
    ws = mirror_squares(0.1)
    local = _solve(ws, 1e-8)
    d = local.diagnostics
    assert d.tol_met, d.table()
    assert any("refined_sides" in r for r in d.refinements), d.refinements
    assert (
        max(abs(local.radii[0] - local.radii[1]), abs(local.centers[0] + np.conj(local.centers[1])))
        <= 1e-8
    )
    monkeypatch.setattr(solver, "LOCAL_REFINEMENT", False)
    full = _solve(ws, 1e-8)
    assert full.diagnostics.tol_met
    assert not any("refined_sides" in r for r in full.diagnostics.refinements)
    assert _distance(local, full) <= d.error_estimate + full.diagnostics.error_estimate


def test_a_partial_level_never_claims_more_than_its_base_plus_its_change(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ws = mirror_squares(0.1)
    m = _solve(ws, 1e-8)
    refs = m.diagnostics.refinements
    k = next(i for i, r in enumerate(refs) if "refined_sides" in r)
    base = max(i for i in range(k) if "refined_sides" not in refs[i])
    assert refs[k]["error_estimate"] == pytest.approx(
        refs[base]["error_estimate"] + refs[k]["difference"]
    )


# ---------------------------------------------------------------- warm re-solve
@pytest.fixture(scope="module")
def cold() -> ConformalMap:
    return _solve(room(), 1e-8)


def test_the_same_workspace_is_not_solved_again(cold: ConformalMap) -> None:
    assert confnav.solve(room(), tol=1e-8, initial=cold) is cold
    assert confnav.solve(room(), tol=1e-7, initial=cold) is cold
    again = _solve(room(), 1e-10, initial=cold)  # tighter: solved again
    assert again is not cold and again.diagnostics.tol_met


def test_a_moved_obstacle_re_solves_warm_to_the_cold_map(
    cold: ConformalMap, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The levels path of a warm re-solve (the fallback of the one-level warm start,
    tests/test_resolve_warm.py)."""
    monkeypatch.setattr(solver, "WARM_RESOLVE", False)
    ws = room(dx=0.2)
    warm = _solve(ws, 1e-8, initial=cold)
    ref = _solve(ws, 1e-8)
    assert warm.diagnostics.tol_met and ref.diagnostics.tol_met
    assert _distance(warm, ref) <= warm.diagnostics.error_estimate + ref.diagnostics.error_estimate
    # the coarse levels are skipped, three levels are still solved
    lv_warm = [r["nodes_per_side"] for r in warm.diagnostics.refinements]
    lv_cold = [r["nodes_per_side"] for r in ref.diagnostics.refinements]
    assert lv_warm[0] > lv_cold[0]
    assert len(lv_warm) >= 2 and "ratio" in warm.diagnostics.refinements[1]


def test_an_added_obstacle_re_solves_warm(cold: ConformalMap) -> None:
    ws = room(extra=True)
    warm = _solve(ws, 1e-8, initial=cold)
    assert warm.diagnostics.tol_met
    assert warm.centers.size == 4
    ref = _solve(ws, 1e-8)
    assert _distance(warm, ref) <= warm.diagnostics.error_estimate + ref.diagnostics.error_estimate


def test_a_looser_initial_map_says_nothing_about_the_levels(cold: ConformalMap) -> None:
    loose = _solve(room(dx=0.2), 1e-4)
    assert solver._warm_start_level(loose, 1e-8) == 0
    assert (
        solver._warm_start_level(cold, 1e-8)
        == solver.LEVELS.index(cold.diagnostics.nodes_per_side) - 2
    )


def test_boundary_residuals_are_evaluated_once_and_equal_a_fresh_evaluation(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The certificate and the choice of sides read one evaluation: the kept residuals are
    bitwise a fresh evaluation's, the second call evaluates nothing, and they cannot be
    changed through the arrays returned."""
    m = _solve(mirror_squares(0.1), 1e-6, nodes_per_side=54)
    fresh = m._boundary_residuals()
    first = m.boundary_residuals()
    for a, b in zip(fresh, first, strict=True):
        assert np.array_equal(a, b)
    assert m.diagnostics.boundary_residual == float(np.max(first[1]))
    calls: list[int] = []
    monkeypatch.setattr(m, "_boundary_residuals", lambda: calls.append(1))
    again = m.boundary_residuals()
    assert not calls and all(x is y for x, y in zip(again, first, strict=True))
    with pytest.raises(ValueError):
        again[1][0] = 0.0


# ---------------------------------------------------------------- reused first-sweep maps
def _level_meshes(plans: list[PanelPlan]) -> list[BoundaryMesh]:
    return [graded_polygon(plans[0].vertices, plans[0].nodes)] + [
        graded_polygon(p.vertices, p.nodes).reversed() for p in plans[1:]
    ]


def test_a_refined_re_solve_reuses_the_first_sweep_maps_before_the_refined_boundary() -> None:
    """Round 5 (issue 24): the last hole's mesh refined, the first sweep's maps of the holes
    before it are taken from the base solve (their equations are the same bit for bit), the
    refined hole and the outer boundary (mapped after it) are solved anew, and the circle
    domain is the one a re-solve without reuse gives, to the sweeps' tolerance."""
    ws, tol = room(), 1e-8
    coarse, fine = plan_boundaries(ws, 36, tol), plan_boundaries(ws, 54, tol)
    holes = [interior_point(o) for o in ws.obstacles]
    base = koebe_iteration(_level_meshes(coarse), holes, ws.anchor, 1e-9)
    assert len(base.first_maps) == 4 and all(f is not None for f in base.first_maps)
    assert base.reused_first_maps == 0
    meshes = _level_meshes(coarse[:3] + fine[3:])  # the last hole refined
    reused = koebe_iteration(meshes, holes, ws.anchor, 1e-9, reuse_first=base.first_maps)
    fresh = koebe_iteration(meshes, holes, ws.anchor, 1e-9)
    assert reused.reused_first_maps == 2
    assert reused.first_maps[1] is base.first_maps[1]
    assert reused.first_maps[2] is base.first_maps[2]
    assert reused.first_maps[3] is not base.first_maps[3]
    assert reused.first_maps[0] is not base.first_maps[0]
    assert reused.converged and fresh.converged
    dist = max(
        np.max(np.abs(reused.centers - fresh.centers)), np.max(np.abs(reused.radii - fresh.radii))
    )
    assert dist <= 2e-9  # both within the sweeps' tolerance (1e-9) of one fixed point
    # the refinement moved the circle domain by far more than the reuse did
    assert np.max(np.abs(base.radii - fresh.radii)) > 10 * dist


def test_a_map_of_another_curve_is_never_reused() -> None:
    ws = room()
    m = _level_meshes(plan_boundaries(ws, 36, 1e-8))[1]
    c = complex(interior_point(ws.obstacles[0]))
    cm = exterior_map(m.eta, m.deta, c, 1e-12)
    assert _reusable(cm, m.eta, m.deta, c, True)
    assert not _reusable(cm, m.eta, m.deta, c, False)
    assert not _reusable(cm, m.eta, m.deta, c + 1e-15, True)
    eta = m.eta.copy()
    eta[3] += 1e-14
    assert not _reusable(cm, eta, m.deta, c, True)


# ---------------------------------------------------------------- where the ladder starts
def test_a_sharp_obstacle_tip_starts_the_ladder_higher(monkeypatch: pytest.MonkeyPatch) -> None:
    """Round 5 (issue 24): the default workspace (a 47.6-degree tip: free-space angle 312.4)
    starts at 80 nodes per side to 1e-8 and at 120 to 1e-10; two squares (270 at most) keep
    the tolerance's start; a loose tolerance, a fixed mesh and the switch off are unchanged."""
    sharp, blunt = default_workspace(), mirror_squares(0.1)
    assert solver.largest_free_angle(sharp) == pytest.approx(312.4, abs=0.1)
    assert solver.largest_free_angle(blunt) == pytest.approx(270.0)
    assert solver._mesh_levels(1e-8, None, None, sharp)[0] == 80
    assert solver._mesh_levels(1e-10, None, None, sharp)[0] == 120
    assert solver._mesh_levels(1e-6, None, None, sharp)[0] == solver.LEVELS[0]
    assert solver._mesh_levels(1e-8, None, None, blunt)[0] == 36
    assert solver._mesh_levels(1e-10, None, None, blunt)[0] == 80
    assert solver._mesh_levels(1e-8, 54, None, sharp) == [24, 36, 54]
    monkeypatch.setattr(solver, "START_BY_CORNERS", False)
    assert solver._mesh_levels(1e-8, None, None, sharp)[0] == 36


def test_a_ladder_started_higher_certifies_on_the_same_three_levels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The default workspace to 1e-8: started at 80 nodes per side, the estimate at 180
    rests on 80, 120 and 180 as when started at 36 -- the same estimate, and the two maps
    within it of each other."""
    m = _solve(default_workspace(), 1e-8)
    d = m.diagnostics
    assert d.tol_met, d.table()
    levels = [int(r["nodes_per_side"]) for r in d.refinements]
    assert levels[0] == 120 and d.nodes_per_side >= 180  # the first estimate: 120 against 80
    monkeypatch.setattr(solver, "START_BY_CORNERS", False)
    low = _solve(default_workspace(), 1e-8)
    assert low.diagnostics.tol_met
    assert int(low.diagnostics.refinements[0]["nodes_per_side"]) == 54
    assert low.diagnostics.nodes_per_side == d.nodes_per_side
    assert d.error_estimate == pytest.approx(low.diagnostics.error_estimate, rel=1e-3)
    assert _distance(m, low) <= d.error_estimate + low.diagnostics.error_estimate


@pytest.mark.parametrize("refined", [3, 0])
def test_a_first_sweep_resumed_from_a_snapshot_is_the_one_that_reapplies_the_maps(
    refined: int,
) -> None:
    """The re-solve's first sweep started from the base's snapshot before the first refined
    boundary (the last hole; the outer boundary, mapped last) gives the circle domain of the
    one that applies the reused maps again, to rounding."""
    ws, tol = room(), 1e-8
    coarse, fine = plan_boundaries(ws, 36, tol), plan_boundaries(ws, 54, tol)
    holes = [interior_point(o) for o in ws.obstacles]
    base = koebe_iteration(_level_meshes(coarse), holes, ws.anchor, 1e-9, snapshots=True)
    # before each hole and the outer map (key 0: the sweep's order of the holes)
    assert sorted(base.first_snapshots) == [0, 1, 2, 3, 4]
    assert base.first_snapshots[0] == (1, 2, 3) and base.order == [1, 2, 3]
    plans = list(coarse)
    plans[refined] = fine[refined]
    meshes = _level_meshes(plans)
    again = koebe_iteration(meshes, holes, ws.anchor, 1e-9, reuse_first=base.first_maps)
    resumed = koebe_iteration(
        meshes,
        holes,
        ws.anchor,
        1e-9,
        reuse_first=base.first_maps,
        reuse_snapshots=base.first_snapshots,
    )
    first = 3 if refined == 3 else 4
    assert again.resumed_at == 1 and resumed.resumed_at == first
    assert again.reused_first_maps == resumed.reused_first_maps == first - 1
    assert resumed.sweeps == again.sweeps
    dist = max(
        np.max(np.abs(resumed.centers - again.centers)), np.max(np.abs(resumed.radii - again.radii))
    )
    assert dist <= 1e-13
    assert max(np.max(np.abs(a - b)) for a, b in zip(resumed.W, again.W, strict=True)) <= 1e-12


# ---------------------------------------------------------------- round 7: the sweep's order
def test_the_sweep_order_puts_the_sharpest_tips_last_and_keeps_ties() -> None:
    """Holes by their largest free-space angle, bluntest first; equal angles (the squares of
    a mirror-symmetric workspace, up to rounding) keep their natural order."""
    tri = [[0.5, 0.5], [0.9, 0.55], [0.5, 0.6]]  # a thin triangle: the sharpest tip
    ws = Workspace(ROOM, [box(-1.5, -1.5), tri, box(-1.0, 0.8)], anchor=[0.0, 0.0])
    assert solver._sweep_order(ws) == [1, 3, 2]
    assert solver._sweep_order(mirror_squares(0.1)) == [1, 2]
    assert solver._sweep_order(room()) == [1, 2, 3]


def test_an_ordered_sweep_resumes_only_with_its_own_order() -> None:
    """Round 7: the base swept its holes in the order 3, 1, 2 and the refined hole 2 comes
    last: the re-solve in the same order reuses both holes before it and resumes from the
    snapshot before it, the same circle domain as re-applying the maps. A re-solve in the
    natural order reuses nothing (hole 1's first-sweep equation is not the base's: there it
    came after hole 3's map) and does not resume from snapshots of another order; its circle
    domain differs by far less than the level's discretisation error."""
    ws, tol = room(), 1e-8
    coarse, fine = plan_boundaries(ws, 36, tol), plan_boundaries(ws, 54, tol)
    holes = [interior_point(o) for o in ws.obstacles]
    order = [3, 1, 2]
    base = koebe_iteration(
        _level_meshes(coarse), holes, ws.anchor, 1e-9, snapshots=True, order=order
    )
    plans = list(coarse)
    plans[2] = fine[2]
    meshes = _level_meshes(plans)
    kw = {"reuse_first": base.first_maps, "reuse_snapshots": base.first_snapshots}
    resumed = koebe_iteration(meshes, holes, ws.anchor, 1e-9, order=order, **kw)  # type: ignore[arg-type]
    again = koebe_iteration(
        meshes, holes, ws.anchor, 1e-9, order=order, reuse_first=base.first_maps
    )
    assert resumed.resumed_at == 3 and resumed.reused_first_maps == 2
    assert again.resumed_at == 1 and again.reused_first_maps == 2
    dist = max(
        np.max(np.abs(resumed.centers - again.centers)), np.max(np.abs(resumed.radii - again.radii))
    )
    assert dist <= 1e-13
    natural = koebe_iteration(meshes, holes, ws.anchor, 1e-9, snapshots=True, **kw)  # type: ignore[arg-type]
    assert natural.resumed_at == 1 and natural.reused_first_maps == 0  # hole 1 was not first
    assert natural.first_snapshots[0] == (1, 2, 3)  # its own order, not the base's
    dist = max(
        np.max(np.abs(natural.centers - again.centers)), np.max(np.abs(natural.radii - again.radii))
    )
    change = max(
        np.max(np.abs(base.centers - again.centers)), np.max(np.abs(base.radii - again.radii))
    )
    # another discretisation path of the same meshes: far within what refining one hole moved
    assert dist <= 1e-2 * change, (dist, change)
    with pytest.raises(ValueError, match="permutation"):
        koebe_iteration(meshes, holes, ws.anchor, 1e-9, order=[1, 2, 2])


def test_a_refined_maps_residual_takes_the_base_denominators_to_rounding(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Round 7 (``solver.REUSE_DENOMINATORS``): a map with one hole re-meshed takes its
    residual's denominator sums at the other boundaries' check points from the base map's,
    corrected by the re-meshed hole's terms; its residual equals the one summed afresh to
    rounding (the map is large enough for the FMM branch that keeps the sums)."""
    ws, tol = room(), 1e-8
    coarse, fine = plan_boundaries(ws, 180, tol), plan_boundaries(ws, 256, tol)
    plans = list(coarse)
    plans[2] = fine[2]

    def level(ps: list[PanelPlan]) -> solver._Level:
        res, meshes = solver._solve_level(ws, 180, tol, None, plans=ps)
        return (res, [m.eta for m in meshes], [m.deta for m in meshes], 180, 0.0, [])

    base = solver._make_map(ws, level(coarse), tol, [], [], 0.0)
    assert base._denominators is not None  # the FMM branch: sums kept
    refined = level(plans)
    fresh = solver._make_map(ws, refined, tol, [], [], 0.0)
    taken: list[bool] = []
    real = ConformalMap._denominators_from

    def spy(self: ConformalMap, targets: list[np.ndarray]) -> np.ndarray | None:
        out = real(self, targets)
        taken.append(out is not None)
        return out

    monkeypatch.setattr(ConformalMap, "_denominators_from", spy)
    reused = solver._make_map(ws, refined, tol, [], [], 0.0, denominators_from=base)
    assert taken == [True]
    za, ra, oa = fresh.boundary_residuals()
    zb, rb, ob = reused.boundary_residuals()
    assert np.array_equal(za, zb) and np.array_equal(oa, ob)
    assert np.all(np.isfinite(rb))
    assert np.max(np.abs(ra - rb)) <= 1e-13
    assert reused.diagnostics.boundary_residual == pytest.approx(
        fresh.diagnostics.boundary_residual, rel=1e-6, abs=1e-14
    )
