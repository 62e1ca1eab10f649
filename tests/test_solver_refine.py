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
from confnav.scenes.workspaces import mirror_squares

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
