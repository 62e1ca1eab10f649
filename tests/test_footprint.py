"""Footprint inflation against shapes with known Minkowski sums (Steiner's formula for convex
polygons: area(P + D_r) = area(P) + perimeter(P) r + pi r^2), containment of the true sum,
merging of obstacles and walls, and the typed error for a goal cut off by a narrow passage."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import shapely

from confnav.errors import WorkspaceError
from confnav.geometry import Workspace
from confnav.maps.footprint import (
    UnreachableGoalError,
    derived_ws_id,
    inflate,
    parse_derived_ws_id,
    shrink_free_space,
)

ROOM = [(-5, -5), (5, -5), (5, 5), (-5, 5)]


def square(c: complex, s: float) -> list[tuple[float, float]]:
    h = s / 2
    return [
        (c.real - h, c.imag - h),
        (c.real + h, c.imag - h),
        (c.real + h, c.imag + h),
        (c.real - h, c.imag + h),
    ]


def true_sum_boundary(poly: np.ndarray, r: float, n: int = 64) -> np.ndarray:
    """Points on the boundary of (convex ccw polygon) + D_r: offset edges and corner arcs."""
    pts = []
    m = len(poly)
    for k in range(m):
        a, b = poly[k], poly[(k + 1) % m]
        nrm = -1j * (b - a) / abs(b - a)  # outward normal of a ccw polygon
        t = np.linspace(0, 1, n)
        pts.append(a + t * (b - a) + r * nrm)
        nxt = -1j * (poly[(k + 2) % m] - b) / abs(poly[(k + 2) % m] - b)
        ang0, ang1 = np.angle(nrm), np.angle(nxt)
        ang1 = ang1 + 2 * np.pi * (ang1 < ang0)
        pts.append(b + r * np.exp(1j * np.linspace(ang0, ang1, n)))
    return np.concatenate(pts)


@pytest.mark.parametrize("quad_segs", [2, 4, 16])
def test_square_round_join_area_and_containment(quad_segs: int) -> None:
    s, r = 1.0, 0.3
    ws = Workspace(ROOM, [square(0.5 + 0.2j, s)])
    inf = shrink_free_space(ws, r, join="round", quad_segs=quad_segs)
    assert len(inf.components) == 1
    hole = shapely.Polygon(inf.components[0].interiors[0])
    exact = s * s + 4 * s * r + math.pi * r * r
    rp = inf.effective_radius
    assert rp > r
    # the polygon contains the true sum, so its area lies between the exact area and that of
    # the sum with the circumscribed radius r' (the polygonisation bound)
    assert exact <= hole.area <= s * s + 4 * s * rp + math.pi * rp * rp
    # containment, checked on the analytic boundary of the true sum
    b = true_sum_boundary(np.array([complex(*p) for p in square(0.5 + 0.2j, s)]), r)
    assert not np.any(shapely.contains_xy(inf.components[0], b.real, b.imag))
    # and every point of the shrunk boundary is at least r from the square
    assert shapely.distance(
        inf.components[0].boundary, shapely.Polygon(square(0.5 + 0.2j, s))
    ) >= r * (1 - 1e-12)


def test_square_mitre_is_exact_square() -> None:
    s, r = 1.0, 0.25
    ws = Workspace(ROOM, [square(0j, s)])
    out = inflate(ws, r, join="mitre")
    assert out.n_obstacles == 1
    assert (
        abs(
            shapely.Polygon(np.column_stack([out.obstacles[0].real, out.obstacles[0].imag])).area
            - (s + 2 * r) ** 2
        )
        < 1e-12
    )
    # walls: the room [-5,5]^2 shrinks to [-4.75, 4.75]^2 (convex corners need no join)
    x0, y0, x1, y1 = shapely.Polygon(np.column_stack([out.outer.real, out.outer.imag])).bounds
    assert np.allclose([x0, y0, x1, y1], [-4.75, -4.75, 4.75, 4.75], atol=1e-12)


def test_triangle_steiner_formula() -> None:
    tri = np.array([0.6 + 0.3j, 1.3 + 0.4j, 0.85 + 1.0j])
    r = 0.1
    ws = Workspace(ROOM, [np.column_stack([tri.real, tri.imag])])
    inf = shrink_free_space(ws, r, join="round", quad_segs=16)
    hole = shapely.Polygon(inf.components[0].interiors[0])
    p = shapely.Polygon(np.column_stack([tri.real, tri.imag]))
    exact = p.area + p.length * r + math.pi * r * r
    rp = inf.effective_radius
    assert exact <= hole.area <= p.area + p.length * rp + math.pi * rp * rp
    assert (hole.area - exact) / exact < 0.01  # 16 segments per quadrant: well under 1 %
    b = true_sum_boundary(tri, r)
    assert not np.any(shapely.contains_xy(inf.components[0], b.real, b.imag))


def test_merging_obstacles_and_walls() -> None:
    # two squares 0.3 apart merge at r = 0.2; a square 0.1 from the wall joins the outer boundary
    ws = Workspace(ROOM, [square(0j, 1), square(1.3 + 0j, 1), square(-3 + 4.4j, 1)])
    out = inflate(ws, 0.2)
    assert out.n_obstacles == 1  # the merged pair; the third is part of the wall now
    assert len(out.outer) > 4
    # and nothing of it is within r of the original obstacles
    orig = shapely.MultiPolygon(
        [
            shapely.Polygon(square(0j, 1)),
            shapely.Polygon(square(1.3 + 0j, 1)),
            shapely.Polygon(square(-3 + 4.4j, 1)),
        ]
    )
    assert shapely.distance(out.polygon, orig) >= 0.2 * (1 - 1e-12)


def test_narrow_passage_names_goal_and_component() -> None:
    # a wall across the room at x in [-0.1, 0.1] with a 0.3 m gap: too narrow for r = 0.2
    outer = [(-5, -5), (5, -5), (5, 5), (0.1, 5), (0.1, 0.15), (-0.1, 0.15), (-0.1, 5), (-5, 5)]
    wall_low = [(-0.1, -4.85), (0.1, -4.85), (0.1, -0.15), (-0.1, -0.15)]
    ws = Workspace(outer, [wall_low])
    inf = shrink_free_space(ws, 0.2)
    assert len(inf.components) == 2
    # r = 0.1 passes the gap; the wall stub (0.15 from the outer wall) joins the outer boundary
    passed = inflate(ws, 0.1, require={"goal": 3 + 0j}, keep=-3 + 0j)
    assert passed.n_obstacles == 0 and passed.contains(3 + 0j) and passed.contains(-3 + 0j)
    with pytest.raises(UnreachableGoalError, match=r"goal \(3, 0\).*component 1 of 2"):
        inflate(ws, 0.2, keep=-3 + 2j, require={"goal": 3 + 0j})
    with pytest.raises(UnreachableGoalError, match=r"within r=0\.2") as err:
        inflate(ws, 0.2, keep=4.9 + 0j)
    # the message offers the nearest point the robot's centre can reach: 4.8, just inside
    near = str(err.value).split("the nearest point that does is (")[1].split(")")[0]
    x, y = (float(v) for v in near.split(", "))
    assert 4.79 < x < 4.8 and y == pytest.approx(0, abs=1e-9)
    inflate(ws, 0.2, keep=complex(x, y))  # and it is indeed reachable


def test_a_goal_exactly_a_radius_from_the_wall_is_refused_before_any_solve() -> None:
    """Found from the CLI: a goal at the back of a charging alcove exactly r (radius +
    look-ahead, 0.35) from the wall was inside the mitre-shrunk space to rounding, the map
    sent it onto the unit circle, and `confnav simulate` failed after a 77 s solve with "not
    inside the circle domain". It is refused at once, with a point the robot can reach."""
    outer = [(0, 0), (10, 0), (10, 7), (0, 7), (0, 4), (-0.8, 4), (-0.8, 3), (0, 3)]
    ws = Workspace(outer, [square(5 + 3.5j, 1)])
    with pytest.raises(UnreachableGoalError, match=r"\(-0\.45, 3\.5\) is within r=0\.35") as err:
        inflate(ws, 0.35, keep=-0.45 + 3.5j)
    near = str(err.value).split("the nearest point that does is (")[1].split(")")[0]
    x, y = (float(v) for v in near.split(", "))
    assert -0.45 < x < -0.448 and y == pytest.approx(3.5, abs=1e-3)  # 1e-4 of the size in
    nav = inflate(ws, 0.35, keep=complex(x, y))  # that one is reachable ...
    assert nav.contains(complex(x, y))
    inflate(ws, 0.35, keep=-0.44 + 3.5j)  # ... and so is a goal 1 cm further out
    with pytest.raises(UnreachableGoalError, match=r"start 0 \(-0\.45, 3\.6\)"):
        inflate(ws, 0.35, keep=5 + 1j, require={"start 0": -0.45 + 3.6j})


def test_a_goal_cut_off_in_a_small_pocket_is_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    """A goal whose component is not the largest is kept, but said: a SLAM speck in an alcove's
    mouth left a studio's robots 0.18 of its 26.7 m^2, and `confnav atlas --random` drew every
    start inside that pocket and reported success."""
    outer = [(0, 0), (4, 0), (4, 3), (2.025, 3), (2.025, 3.5), (2.4, 3.5), (2.4, 4.2),
             (1.6, 4.2), (1.6, 3.5), (1.975, 3.5), (1.975, 3), (0, 3)]  # fmt: skip
    ws = Workspace(outer, [])
    with caplog.at_level("WARNING", logger="confnav.maps.footprint"):
        pocket = inflate(ws, 0.1, keep=2 + 3.85j)
    assert pocket.polygon.area < 0.5
    (rec,) = caplog.records
    assert "(2, 3.85)" in rec.getMessage() and "not in the largest" in rec.getMessage()
    caplog.clear()
    with caplog.at_level("WARNING", logger="confnav.maps.footprint"):
        room = inflate(ws, 0.1, keep=1 + 1j)
    assert room.polygon.area > 10 and not caplog.records


def test_bad_input() -> None:
    ws = Workspace(ROOM, [square(0j, 1)])
    with pytest.raises(WorkspaceError, match="bevel"):
        shrink_free_space(ws, 0.1, join="bevel")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radius"):
        inflate(ws, -0.1)
    with pytest.raises(WorkspaceError, match="no free space"):
        inflate(ws, 6.0)
    assert inflate(ws, 0.0) is ws


def test_derived_ids() -> None:
    assert derived_ws_id("office", 0.25) == "office~r0.25"
    assert derived_ws_id("office", 0.25000001) == "office~r0.2501"  # rounded up
    assert derived_ws_id("office", 0.0) == "office"
    assert parse_derived_ws_id("office~r0.25") == ("office", 0.25)
    assert parse_derived_ws_id("office") is None
    assert parse_derived_ws_id("office~rx") is None


def test_transform_service_solves_footprint_workspaces(mem_net: Any) -> None:
    """A query for {ws}~r{R} makes the transform service solve ws shrunk by R (own cache key);
    an impossible radius gets a reply_err saying why."""
    from confnav.schemas import TransformSolution, WorkspaceDefinition, decode, encode
    from confnav.services.keys import Keys
    from confnav.services.transform import TransformService
    from conftest import fake_solve, square_definition, wait_for

    K = Keys()
    solved: list[WorkspaceDefinition] = []

    def solve_fn(defn_json: str) -> dict[str, Any]:
        d = WorkspaceDefinition.model_validate_json(defn_json)
        solved.append(d)
        ws = Workspace(d.outer, d.obstacles)
        res = fake_solve(defn_json)
        res["diagnostics"] = {**res["diagnostics"], "boundary_residual": 0.0, "tol_met": True}
        return {**res, "workspace_hash": ws.content_hash}

    svc = TransformService(mem_net.bus("tr"), K, executor="thread", solve_fn=solve_fn)
    svc.start()
    client = mem_net.bus("client")
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.2, 0.0)])))
        wait_for(lambda: svc.state_of("sq") == "solved")
        first = client.query(K.ws("sq~r0.05", "transform"))  # not solved yet: retry later
        assert len(first) == 1 and not first[0].ok
        wait_for(lambda: svc.state_of("sq~r0.05") == "solved")
        rep = client.query(K.ws("sq~r0.05", "transform"))
        assert rep[0].ok and decode(TransformSolution, rep[0].payload or b"").ws_id == "sq~r0.05"
        d = solved[-1]
        assert d.ws_id == "sq~r0.05"
        ws = Workspace(d.outer, d.obstacles)
        # the room [-0.7, 0.7]^2 shrinks to [-0.65, 0.65]^2; the 0.05 square grows to 0.15
        assert np.allclose(ws.bounds, (-0.65, -0.65, 0.65, 0.65), atol=1e-12)
        assert shapely.Polygon(d.obstacles[0]).area == pytest.approx(0.15**2, rel=1e-12)
        bad = client.query(K.ws("sq~r0.8", "transform"))
        assert not bad[0].ok and "no free space" in (bad[0].error or "")
        assert svc.state_of("nope~r0.1") is None
    finally:
        svc.stop()


def test_controller_names_an_unreachable_goal() -> None:
    """The controller service's adapter turns 'goal not in the map' on a footprint map into an
    UnreachableGoalError naming the robot, the goal and the shrunk workspace."""
    from confnav.schemas import Goal
    from confnav.services import navigation
    from conftest import IdentityMap

    cmap = IdentityMap([0.4 + 0j], [0.25])  # the map of "room~r0.1": the obstacle grown by 0.1
    ok = Goal(robot_id="r1", ws_id="room", goal=(-0.5, 0.0), robot_radius=0.1)
    assert navigation.map_ws_id(ok) == "room~r0.1"
    navigation.make_controller(cmap, ok)
    bad = ok.model_copy(update={"goal": (0.2, 0.0)})  # free for a point, not for the body
    with pytest.raises(UnreachableGoalError, match=r"robot 'r1'.*'room~r0\.1'"):
        navigation.make_controller(cmap, bad)
    uni = ok.model_copy(update={"drive": "unicycle", "lookahead": 0.05})
    assert navigation.map_ws_id(uni) == "room~r0.15"


def _wedges(width: float, tip_deg: float = 50.0) -> Workspace:
    """Two wedge-shaped obstacles (tip angle ``tip_deg``) pointing at each other, their tips
    ``width`` apart at the origin: the passage between them is ``width`` wide."""
    h = 2 * math.tan(math.radians(tip_deg / 2))
    left = [(-width / 2, 0), (-width / 2 - 2, -h), (-width / 2 - 2, h)]
    right = [(width / 2, 0), (width / 2 + 2, h), (width / 2 + 2, -h)]
    return Workspace(ROOM, [left, right])


def _door(width: float, tip_deg: float = 50.0) -> Workspace:
    """A wall across the room, part of the outer boundary, with a door ``width`` wide between
    two pointed jambs (tip angle ``tip_deg``): the passage is between parts of one ring."""
    h = 0.5 * math.tan(math.radians(tip_deg / 2))
    w = width / 2
    outer = [(-5, -5), (5, -5), (5, 5), (-5, 5), (-5, h), (-0.5 - w, h), (-w, 0),
             (-0.5 - w, -h), (-5, -h)]  # fmt: skip
    hole = [(w, 0), (0.5 + w, h), (4.9, h), (4.9, -h), (0.5 + w, -h)]
    return Workspace(outer, [hole])


@pytest.mark.parametrize("make", [_wedges, _door], ids=["two obstacles", "door in a wall"])
def test_a_passage_stays_open_exactly_when_the_true_minkowski_sum_leaves_it_open(
    make: Any,
) -> None:
    """Mitre joins grew two facing 50-degree corners by about 0.45 m each for a 0.32 m disk and
    closed a 0.78 m passage the disk passes; the passage is now reopened from the round-join
    shrink (circumscribed: still inside the exact one), and a 0.60 m passage stays closed."""
    r = 0.32
    for width, is_open in ((0.78, True), (0.66, True), (0.60, False)):
        ws = make(width)
        inf = shrink_free_space(ws, r)
        mid = shapely.Point(0, 0)  # the middle of the passage
        # exact: the disk fits at the middle iff the passage is wider than 2 r
        assert (float(ws.clearance(np.array([0j]))[0]) > r) == is_open
        assert any(c.contains(mid) for c in inf.components) == is_open, width
        assert (inf.reopened > 0) == is_open  # the mitre alone closes all three
        # still conservative: every point of the result is >= r from every wall and obstacle
        union = shapely.MultiPolygon(list(inf.components))
        assert shapely.distance(union.boundary, ws.polygon.boundary) >= r * (1 - 1e-9)
        assert ws.polygon.buffer(1e-9).contains(union)
        # the mitre's vertices stay away from the passage: only the reopened pieces are round
        mitre_only = ws.polygon.buffer(-r, join_style="mitre", mitre_limit=5.0)
        n = sum(len(c.exterior.coords) + sum(len(h.coords) for h in c.interiors)
                for c in inf.components)  # fmt: skip
        n_mitre = sum(len(c.exterior.coords) + sum(len(h.coords) for h in c.interiors)
                      for c in getattr(mitre_only, "geoms", [mitre_only]))  # fmt: skip
        assert n <= n_mitre + 40
    # with the passage open, a goal across it is reachable from the other side
    inflate(make(0.78), r, keep=complex(0, 3), require={"goal": complex(0, -3)})
    if make is _door:
        with pytest.raises(UnreachableGoalError):
            inflate(make(0.60), r, keep=complex(0, 3), require={"goal": complex(0, -3)})


def test_sharp_tip_is_capped_by_the_bounded_mitre_and_still_contains_the_sum() -> None:
    """A 20-degree tip: a plain mitre would reach r / sin(10 deg) = 5.8 r beyond it; the
    bounded mitre cuts it at MITRE_LIMIT r (a cut tangent to or beyond the disk), so the grown
    obstacle still contains the tip's disk and the whole true Minkowski sum."""
    from confnav.maps.footprint import MITRE_LIMIT

    half = math.radians(10.0)
    tip = 1.0 + 0j
    tri = [(tip.real, tip.imag), (-1.0, -2.0 * math.tan(half)), (-1.0, 2.0 * math.tan(half))]
    r = 0.2
    out = inflate(Workspace(ROOM, [tri]), r)
    grown = shapely.Polygon(np.column_stack([out.obstacles[0].real, out.obstacles[0].imag]))
    reach = grown.bounds[2] - tip.real  # how far the grown obstacle extends beyond the tip
    assert r * (1 - 1e-9) <= reach <= MITRE_LIMIT * r * (1 + 1e-9)
    exact = shapely.Polygon(tri).buffer(r, quad_segs=256)  # inscribed: inside the true sum
    assert grown.buffer(1e-12).contains(exact)
