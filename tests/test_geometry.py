"""Workspace validation, normalisation, clearance and (Geo)JSON round trips."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely

from confnav import Workspace, WorkspaceError
from confnav.geometry import signed_area
from confnav.scenes.workspaces import default_workspace, mixed_obstacles

SQUARE = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
SMALL = [[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]]


def test_orientation_is_normalised_to_counter_clockwise() -> None:
    ws = Workspace(SQUARE[::-1], [SMALL[::-1]], anchor=[0.6, 0.0])
    assert signed_area(ws.outer) > 0
    assert all(signed_area(o) > 0 for o in ws.obstacles)


def test_closing_vertex_is_accepted() -> None:
    ws = Workspace([*SQUARE, SQUARE[0]], anchor=[0, 0])
    assert ws.outer.size == 4


def test_default_anchor_is_a_point_of_maximal_clearance() -> None:
    ws = Workspace(SQUARE, [[[0.3, -0.9], [0.9, -0.9], [0.9, -0.3], [0.3, -0.3]]])
    # the best point is in the empty upper-left part; compare with a fine grid search
    x, y = np.meshgrid(np.linspace(-1, 1, 201), np.linspace(-1, 1, 201))
    z = (x + 1j * y).ravel()
    best = float(np.max(ws.clearance(z)))
    assert float(ws.clearance(ws.anchor)) >= best - 0.02


def test_clearance_is_signed_exact_distance() -> None:
    ws = Workspace(SQUARE, [SMALL], anchor=[0.6, 0])
    z = np.array([0.6 + 0j, 0.0 + 0.0j, 0.3 + 0j, 1.5 + 0j])
    np.testing.assert_allclose(ws.clearance(z), [0.4, -0.2, 0.1, -0.5], atol=1e-15)
    poly = ws.polygon
    pts = np.random.default_rng(0).uniform(-1, 1, (200, 2))
    ref = shapely.distance(poly.boundary, shapely.points(pts))
    got = np.abs(ws.clearance(pts[:, 0] + 1j * pts[:, 1]))
    np.testing.assert_allclose(got, ref, atol=1e-14)


@pytest.mark.parametrize(
    ("outer", "obstacles", "anchor", "message"),
    [
        ([[0, 0], [1, 0]], [], None, "outer: a polygon needs at least 3 vertices"),
        ([[0, 0], [1, 0], [1, 0], [0, 1]], [], None, "outer: vertices 1 and 2 are repeated"),
        ([[0, 0], [2, 0], [1, 0], [1, 1]], [], None, "collinear-degenerate"),
        ([[0, 0], [1, 0], [2, 0]], [], None, "outer: vertex 0 is collinear-degenerate"),
        ([[0, 0], [1, 1], [1, 0], [0, 1]], [], None, "outer: polygon is self-intersecting"),
        (SQUARE, [[[0, 0], [float("nan"), 0], [0, 1]]], None, "obstacle 0: vertex coordinates"),
        (SQUARE, [[[0.5, 0.5], [1.5, 0.5], [0.5, 0.8]]], None, "obstacle 0: must lie strictly"),
        (SQUARE, [[[0.5, 0.5], [1.0, 0.5], [0.5, 0.8]]], None, "obstacle 0: must lie strictly"),
        (SQUARE, [SMALL, [[0.1, 0.1], [0.5, 0.1], [0.5, 0.5]]], None, "obstacles 0 and 1 overlap"),
        (SQUARE, [SMALL, [[0.2, 0.2], [0.5, 0.2], [0.5, 0.5]]], None, "obstacles 0 and 1 touch"),
        (SQUARE, [SMALL], [0.0, 0.0], "anchor (0, 0) is not in the free space"),
        (SQUARE, [SMALL], [2.0, 0.0], "anchor (2, 0) is not in the free space"),
        (SQUARE, [SMALL], [float("inf"), 0.0], "anchor must be finite"),
        ("not a polygon", [], None, "outer: vertices must be a list"),
    ],
)
def test_bad_workspaces_are_rejected_with_a_clear_message(
    outer: object, obstacles: list, anchor: object, message: str
) -> None:
    with pytest.raises(WorkspaceError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Workspace(outer, obstacles, anchor)  # type: ignore[arg-type]


def test_json_round_trip_and_errors() -> None:
    ws = default_workspace()
    again = Workspace.from_json(ws.to_json())
    assert again == ws
    assert again.content_hash == ws.content_hash
    assert json.loads(ws.to_json())["anchor"] == [0.0, 0.0]
    with pytest.raises(WorkspaceError, match="not valid JSON"):
        Workspace.from_json("{")
    with pytest.raises(WorkspaceError, match="unknown keys"):
        Workspace.from_json(json.dumps({"outer": SQUARE, "holes": []}))
    with pytest.raises(WorkspaceError, match="needs an 'outer'"):
        Workspace.from_json("{}")


def test_content_hash_changes_with_the_geometry() -> None:
    a = Workspace(SQUARE, [SMALL], anchor=[0.6, 0])
    b = Workspace(SQUARE, [[[-0.2, -0.2], [0.2, -0.2], [0.2, 0.21], [-0.2, 0.2]]], anchor=[0.6, 0])
    assert a.content_hash != b.content_hash


def test_geojson_round_trip(tmp_path: object) -> None:
    ws = default_workspace()
    gj = ws.to_geojson()
    # RFC 7946: exterior ring counter-clockwise, holes clockwise, rings closed
    rings = gj["geometry"]["coordinates"]
    assert rings[0][0] == rings[0][-1]
    assert len(rings) == 1 + ws.n_obstacles
    again = Workspace.from_geojson(gj)
    assert again == ws
    multi = {"type": "MultiPolygon", "coordinates": [rings]}
    assert Workspace.from_geojson(multi).n_obstacles == ws.n_obstacles
    with pytest.raises(WorkspaceError, match="exactly one part"):
        Workspace.from_geojson({"type": "MultiPolygon", "coordinates": [rings, rings]})
    with pytest.raises(WorkspaceError, match="Polygon or MultiPolygon"):
        Workspace.from_geojson({"type": "Point", "coordinates": [0, 0]})


def test_load_and_save(tmp_path) -> None:  # type: ignore[no-untyped-def]
    ws = default_workspace()
    p = tmp_path / "ws.json"
    ws.save(p)
    assert Workspace.load(p) == ws
    g = tmp_path / "ws.geojson"
    g.write_text(json.dumps(ws.to_geojson()))
    assert Workspace.load(g) == ws
    with pytest.raises(WorkspaceError, match="cannot read workspace file"):
        Workspace.load(tmp_path / "missing.json")


def test_default_workspace_matches_the_seed() -> None:
    ws = default_workspace()
    assert ws.anchor == 0
    assert [o.size for o in ws.obstacles] == [3, 4, 12, 8]
    star = ws.obstacles[2]
    # first tip straight up, radii 0.4 / 0.2 around (-1.05, -0.8)
    r = np.abs(star - (-1.05 - 0.8j))
    np.testing.assert_allclose(np.sort(r), [0.2] * 6 + [0.4] * 6, atol=1e-15)
    assert np.isclose(star[np.argmax(star.imag)], -1.05 - 0.4j)


@pytest.mark.parametrize("n", [1, 7, 20])
def test_mixed_obstacles_are_valid_and_disjoint(n: int) -> None:
    ws = mixed_obstacles(n, seed=3)
    assert ws.n_obstacles == n
    assert ws.contains(ws.anchor)
