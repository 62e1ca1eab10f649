"""Issue 8: the map is never silently wrong.

Exact checks needing no reference: a workspace symmetric under the mirror x -> -x with the
anchor on the axis has a circle domain symmetric under w -> -conj(w) (the mirrored map
-conj(T(-conj z)) is again the normalised map, which is unique), so mirrored obstacles get
equal radii and mirrored centres. Near-touching pairs, a stopped iteration, the a-posteriori
boundary residual, and maps bound to their workspace.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import confnav
from confnav import ConformalMap, GapError, MapMismatchError, SerializationError, Workspace
from confnav.cli.app import main
from confnav.conformal import circledomain, solver
from confnav.navigation.control import Controller
from confnav.scenes.workspaces import mirror_asymmetry, mirror_squares

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]


def asymmetry(m: ConformalMap) -> float:
    """Distance of the circle domain from its mirror image (0 exactly)."""
    return mirror_asymmetry(m.centers, m.radii)


def _solve(ws: Workspace, tol: float) -> ConformalMap:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        return confnav.solve(ws, tol=tol)


def triangles() -> Workspace:
    """Two triangles, mirror images under x -> -x, anchor on the axis."""
    tri = np.array([0.3 + 0.2j, 1.1 + 0.4j, 0.7 + 1.0j])
    return Workspace(ROOM, [-np.conj(tri)[::-1], tri], anchor=[0, -1])


# ---------------------------------------------------------------- mirror symmetry
@pytest.mark.parametrize("tol", [1e-6, 1e-9])
def test_mirror_symmetric_triangles_get_mirrored_circles(tol: float) -> None:
    m = _solve(triangles(), tol)
    assert m.diagnostics.tol_met, m.diagnostics.table()
    assert asymmetry(m) <= tol
    assert abs(m.dT(-1j).imag) < 1e-10  # T'(anchor) > 0


@pytest.mark.slow
def test_gap_0_1_is_accurate_and_symmetric() -> None:
    tol = 1e-4
    m = _solve(mirror_squares(0.1), tol)
    d = m.diagnostics
    # never claims an accuracy it lacks: the asymmetry is a lower bound of the true error
    assert asymmetry(m) <= max(d.error_estimate, 1e-14), d.table()
    assert d.tol_met, d.table()
    assert asymmetry(m) <= tol


def test_gap_0_001_is_a_typed_error_naming_both_obstacles() -> None:
    with pytest.raises(GapError, match=r"obstacle 0 .*obstacle 1 .*0\.001 apart"):
        confnav.solve(mirror_squares(0.001), tol=1e-6)


# ---------------------------------------------------------------- the iteration error
def test_contraction_extrapolation() -> None:
    # geometric changes 0.1 * 0.5^n: the remaining error is the tail, change * rho/(1 - rho)
    h = [0.1 * 0.5**n for n in range(6)]
    rem, ok = circledomain._remaining_error(h)
    assert ok and rem == pytest.approx(h[-1])
    # a slow iteration (rho = 0.9) is far from converged although its change is small
    h = [1e-5 * 0.9**n for n in range(6)]
    rem, ok = circledomain._remaining_error(h)
    assert ok and rem == pytest.approx(9 * h[-1])
    # no progress at all: no extrapolation, the stalled error is the largest recent change
    h = [1e-3, 5.6e-5, 5.5e-5, 5.7e-5, 5.6e-5]
    assert not circledomain._remaining_error(h)[1]
    assert circledomain._stalled_error(h) == pytest.approx(5.7e-5)


def test_a_stopped_iteration_is_reported_not_taken_as_converged(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the failure: the iteration stopped early at every mesh level alike, so the level
    # difference could not see it. Stop it after 3 sweeps at every level.
    real = solver.koebe_iteration

    def three_sweeps(*args: object, **kw: object) -> circledomain.CircleDomainResult:
        return real(*args, **kw, max_sweeps=3)  # type: ignore[arg-type]

    monkeypatch.setattr(solver, "koebe_iteration", three_sweeps)
    with pytest.warns(confnav.AccuracyWarning, match="did not converge"):
        m = confnav.solve(triangles(), tol=1e-8)
    d = m.diagnostics
    assert not d.tol_met and not d.iteration_converged
    assert d.iteration_error >= d.history[-1] > 1e-8
    assert d.error_estimate >= d.iteration_error
    assert d.discretisation_error < d.iteration_error  # the old estimate alone said "met"


# ---------------------------------------------------------------- boundary residual
def test_boundary_residual_is_computed_and_carried() -> None:
    m = _solve(triangles(), 1e-7)
    r = m.diagnostics.boundary_residual
    assert 0 < r <= 1e-7 and r == m.boundary_residual()
    again = ConformalMap.from_json(m.to_json())
    assert again.diagnostics.boundary_residual == r


def test_coarsened_maps_carry_their_own_residual() -> None:
    m = _solve(triangles(), 1e-9)
    c = m.coarsened(8)
    # fewer nodes are least accurate at the walls: its own residual, not the full map's
    assert c.diagnostics.boundary_residual == c.boundary_residual()
    assert c.diagnostics.boundary_residual > m.diagnostics.boundary_residual
    assert c.diagnostics.error_estimate >= c.diagnostics.boundary_residual
    nav = m.for_navigation(accuracy=1e-7)
    assert nav.diagnostics.boundary_residual <= 1e-7


def test_navigation_check_points_on_narrow_domains() -> None:
    # A 10x10 room with a 0.2-wide ring corridor has no point 1% of its size from the walls:
    # for_navigation() then failed with a ValueError (max of an empty array). Solving that
    # room takes minutes (bench --certificate has it); here the fallback itself: asking for
    # more far points than exist returns the points of largest clearance, all in free space.
    room = [[0, 0], [10, 0], [10, 10], [0, 10]]
    ring = Workspace(room, [[[0.2, 0.2], [9.8, 0.2], [9.8, 9.8], [0.2, 9.8]]], anchor=[0.1, 5])
    # _check_points looks only at the map's workspace
    z = ConformalMap._check_points(SimpleNamespace(workspace=ring), seed=0)  # type: ignore[arg-type]
    assert 0 < z.size <= 400
    d = ring.clearance(z)
    assert np.all(d > 0) and np.all(np.diff(d) <= 0)  # the most clearance first
    assert int(np.sum(d > 0.01 * ring.diameter)) < 10  # the old rule's only points (if any)


# ---------------------------------------------------------------- maps bound to workspaces
def test_content_hash_is_canonical() -> None:
    a = Workspace(ROOM, [[[0, 0], [1, 0], [0, 1]]], anchor=[-1, -1])
    b = Workspace(ROOM[::-1], [[[0, 1], [1, 0], [0, 0]]], anchor=[-1, -1])  # other orientation
    c = Workspace(ROOM, [[[-0.0, 0], [1, 0], [0, 1]]], anchor=[-1, -1])  # -0.0
    assert a.content_hash == b.content_hash == c.content_hash
    assert len(a.content_hash) == 64
    assert a.content_hash != a.with_anchor([-1, -1.5]).content_hash


def test_map_carries_the_workspace_hash_and_refuses_another() -> None:
    ws = Workspace(ROOM, [[[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]], anchor=[0, 1])
    other = Workspace(ROOM, anchor=[0, 1])
    m = _solve(ws, 1e-6)
    assert m.workspace_hash == ws.content_hash
    d = json.loads(m.to_json())
    assert d["workspace_hash"] == ws.content_hash
    m.check_workspace(ws)
    with pytest.raises(MapMismatchError, match="not for the one in use"):
        m.check_workspace(other)
    with pytest.raises(MapMismatchError):
        Controller(m, 1.5 + 1.5j, workspace=other)
    Controller(m, 1.5 + 1.5j, workspace=ws)
    # a tampered file (hash of another workspace) and an old version-1 map are refused
    with pytest.raises(SerializationError, match="workspace_hash"):
        ConformalMap.from_dict({**d, "workspace_hash": other.content_hash})
    with pytest.raises(SerializationError, match="version 1"):
        ConformalMap.from_dict({**d, "version": 1})


def test_simulate_refuses_a_map_of_another_workspace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    office = Workspace(ROOM, [[[-0.1, -1.9], [0.1, -1.9], [0.1, 1], [-0.1, 1]]])  # a partition
    empty = Workspace(ROOM, anchor=office.anchor)
    ws_path, map_path = tmp_path / "office.json", tmp_path / "other_map.json"
    office.save(ws_path)
    map_path.write_text(_solve(empty, 1e-6).to_json())
    code = main(
        ["simulate", str(ws_path), "--map", str(map_path), "--goal", "1,1", "--starts=-1,-1"]
    )
    assert code != 0
    assert "not for the one in use" in capsys.readouterr().err


def test_the_worst_boundary_point_is_named_on_its_boundary() -> None:
    """The residual's largest point lies on the boundary it is attributed to, and an unusable
    map's error names it (a user can look there)."""
    c = _solve(triangles(), 1e-9).coarsened(8)
    z, res, owner = c.boundary_residuals()
    assert float(np.max(res)) == c.boundary_residual()
    p, name = c.worst_boundary_point()
    j = int(owner[int(np.argmax(res))])
    assert p == z[int(np.argmax(res))]
    assert name == ("the outer boundary" if j == 0 else f"obstacle {j - 1}")
    poly = c.workspace.boundaries[j]
    edges = np.roll(poly, -1) - poly
    t = np.clip(((p - poly) * np.conj(edges)).real / np.abs(edges) ** 2, 0, 1)
    assert np.min(np.abs(poly + t * edges - p)) < 1e-12 * c.workspace.diameter
