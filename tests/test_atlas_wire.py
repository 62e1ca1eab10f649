"""Atlases on the wire (issue 15 item 3), without processes: the index and chart messages of a
solved atlas rebuild the same atlas (the same plan, exactly); the per-robot switching
controller the controller service runs follows the composition's rule, drives a robot to the
goal without a collision, and is deterministic (what ``replay --check`` relies on); the
transform service's atlas store answers queries as documented."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from confnav.schemas import AtlasIndex, Goal, TransformSolution, decode, encode
from confnav.services.atlas_transform import AtlasStore, messages_of
from confnav.services.bus import QueryError
from confnav.services.navigation import commands, make_controller
from confnav.services.transform import solution_result
from test_atlas import GOAL, TOL, pillar_corridor

from confnav.atlas import Atlas, AtlasNavigator, plan, solve_atlas
from confnav.atlas.wire import (
    ATLAS_MARKER,
    AtlasMap,
    atlas_map_of,
    chart_ws_id,
    index_fields,
    is_chart_ws_id,
)
from confnav.conformal.cmap import ConformalMap
from confnav.navigation.control import Status


@pytest.fixture(scope="module")
def atlas() -> Atlas:
    return solve_atlas(pillar_corridor(), TOL, workers=2)


@pytest.fixture(scope="module")
def wire(atlas: Atlas) -> tuple[AtlasIndex, list[TransformSolution]]:
    result = {
        "atlas": index_fields(atlas),
        "charts": [solution_result(m, TOL) for m in atlas.charts],
    }
    index, charts = messages_of("pc", "h" * 64, result)
    # through bytes, as on the bus and in a recording
    return decode(AtlasIndex, encode(index)), [decode(TransformSolution, encode(c)) for c in charts]


def rebuilt(wire: tuple[AtlasIndex, list[TransformSolution]]) -> AtlasMap:
    index, charts = wire
    maps = {c.revision: ConformalMap.from_dict(c.coefficients) for c in charts}
    return atlas_map_of(index, maps)


def test_chart_ids() -> None:
    assert chart_ws_id("floor", 7) == "floor~c7" and is_chart_ws_id("floor~c7")
    assert not is_chart_ws_id("floor") and not is_chart_ws_id("floor~r0.3")
    assert not is_chart_ws_id("~c3") and not is_chart_ws_id("floor~cx")


def test_the_wire_rebuilds_the_same_atlas_and_plan(
    atlas: Atlas, wire: tuple[AtlasIndex, list[TransformSolution]]
) -> None:
    index, charts = wire
    assert [c.chart_ws_id for c in index.cells] == [
        chart_ws_id("pc", i) for i in range(len(charts))
    ]
    am = rebuilt(wire)
    for a, b in zip(atlas.decomposition.cells, am.atlas.decomposition.cells, strict=True):
        assert a.polygon.symmetric_difference(b.polygon).area <= 1e-12
        assert a.cut.hausdorff_distance(b.cut) <= 1e-12
        assert a.workspace.content_hash == b.workspace.content_hash
    p0, p1 = plan(atlas, GOAL), plan(am.atlas, GOAL)
    assert np.array_equal(p0.rank, p1.rank) and np.array_equal(p0.next, p1.next)
    assert np.array_equal(p0.local_goal, p1.local_goal)
    # a chart of another cell is refused
    swapped = index.cells[0].model_copy(update={"chart_revision": index.cells[1].chart_revision})
    bad = index.model_copy(update={"cells": [swapped, *index.cells[1:]]})
    maps = {c.revision: ConformalMap.from_dict(c.coefficients) for c in charts}
    with pytest.raises(Exception, match="not its cell's map"):
        atlas_map_of(bad, maps)
    with pytest.raises(Exception, match="missing"):
        atlas_map_of(index, {})


def _bent(index: AtlasIndex, offset: float) -> AtlasIndex:
    """``index`` with a vertex added to cell 0's outer ring: the middle of its longest edge,
    moved ``offset`` off it (as the simplification of a cell polygon moves its boundary)."""
    cell = index.cells[0]
    ring = [complex(*p) for p in cell.outer]
    k = max(range(len(ring)), key=lambda i: abs(ring[(i + 1) % len(ring)] - ring[i]))
    a, b = ring[k], ring[(k + 1) % len(ring)]
    m = (a + b) / 2 + offset * 1j * (b - a) / abs(b - a)
    outer = [*cell.outer[: k + 1], (m.real, m.imag), *cell.outer[k + 1 :]]
    cells = [cell.model_copy(update={"outer": outer}), *index.cells[1:]]
    return index.model_copy(update={"cells": cells})


def test_a_cell_polygon_within_the_simplification_of_its_chart_is_its_chart(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    """A chart's workspace is its cell polygon simplified within 1e-9 of the diameter: the
    rebuilt atlas accepts a boundary that far off its chart's (an area test refused a chart
    of the README's office shrunk by 0.3 m, at 5.4e-10 of the cell's area), and refuses one
    a visible distance off."""
    index, charts = wire
    maps = {c.revision: ConformalMap.from_dict(c.coefficients) for c in charts}
    diameter = atlas_map_of(index, maps).atlas.workspace.diameter
    poly0 = atlas_map_of(index, maps).atlas.decomposition.cells[0].polygon
    near = _bent(index, 3e-9 * diameter)
    am = atlas_map_of(near, maps)
    assert am.atlas.decomposition.cells[0].polygon.symmetric_difference(poly0).area > 0
    with pytest.raises(Exception, match="not its cell's map"):
        atlas_map_of(_bent(index, 1e-6 * diameter), maps)


def drive(ctrl: object, z: complex, dt: float = 0.02, steps: int = 3000) -> list[complex]:
    path = [z]
    for _ in range(steps):
        u, code = commands(ctrl, np.array([z]))  # type: ignore[arg-type]
        if code[0] == Status.ARRIVED:
            break
        assert code[0] == Status.MOVING
        z = z + dt * complex(u[0])
        path.append(z)
    return path


def test_the_switching_controller_drives_a_robot_down_the_order(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    am = rebuilt(wire)
    g = Goal(robot_id="r", ws_id="pc", goal=(GOAL.real, GOAL.imag), v_max=1.0, tolerance=0.02)
    ctrl = make_controller(am, g)
    nav = AtlasNavigator(am.atlas, GOAL, nav_maps=am.nav_maps, links=am.links)
    path = drive(ctrl, 0.3 + 0.4j)
    assert abs(path[-1] - GOAL) <= 0.02 + 0.02  # arrived (one step of slack)
    ws = am.atlas.workspace
    assert float(np.min(ws.clearance(np.array(path)))) > 0  # no collision
    hist = ctrl.history  # type: ignore[attr-defined]
    assert len(hist) >= 3
    assert all(nav.plan.rank[b] < nav.plan.rank[a] for a, b in itertools.pairwise(hist))
    # deterministic: a fresh controller fed the same poses commands the same, bit for bit
    again = make_controller(am, g)
    u1, _ = commands(ctrl.__class__(ctrl.nav), np.array(path[:400]))  # type: ignore[attr-defined]
    u2, _ = commands(again, np.array(path[:400]))
    assert np.array_equal(u1, u2)
    # a unicycle gets the look-ahead law around its own switching controller
    uni = make_controller(am, g.model_copy(update={"drive": "unicycle", "lookahead": 0.05}))
    assert uni.frame == "body" and uni.controller.__class__ is ctrl.__class__  # type: ignore[attr-defined]


def test_the_atlas_store_answers_queries(wire: tuple[AtlasIndex, list[TransformSolution]]) -> None:
    index, charts = wire
    store = AtlasStore()
    assert store.answer("p/ws/pc/transform", "pc", "transform") is None  # not an atlas
    with pytest.raises(QueryError, match="not solved as an atlas"):
        store.answer("p/ws/pc/atlas", "pc", "atlas")
    store.put("pc", encode(index), {c.ws_id: encode(c) for c in charts})
    assert store.answer("p/ws/pc/atlas", "pc", "atlas") == [("p/ws/pc/atlas", encode(index))]
    cid = charts[2].ws_id
    assert store.answer(f"p/ws/{cid}/transform", cid, "transform") == [
        (f"p/ws/{cid}/transform", encode(charts[2]))
    ]
    with pytest.raises(QueryError, match=f"^{ATLAS_MARKER}"):
        store.answer("p/ws/pc/transform", "pc", "transform")
    assert [k for k, _ in store.answer_wildcard("p/ws/*/atlas")] == ["p/ws/pc/atlas"]
    store.forget("pc")
    assert store.answer(f"p/ws/{cid}/transform", cid, "transform") is None
    with pytest.raises(QueryError):
        store.answer_wildcard("p/ws/*/atlas")


def test_an_atlas_stands_in_for_a_body_until_its_footprint_atlas(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    """The unshrunk atlas steers a robot with a body (its ``{ws}~r{R}`` atlas not solved yet),
    every chart's commands filtered against the exact free space shrunk by the footprint."""
    from confnav.services.navigation import shrunk_workspace, stands_in

    am = rebuilt(wire)
    radius = 0.03
    g = Goal(robot_id="r", ws_id="pc", goal=(GOAL.real, GOAL.imag), v_max=1.0, tolerance=0.02,
             robot_radius=radius)  # fmt: skip
    assert stands_in(am, g)
    ctrl = make_controller(am, g)
    shrunk = shrunk_workspace(am, g)
    path = drive(ctrl, 0.3 + 0.4j)
    assert abs(path[-1] - GOAL) <= 0.02 + 0.02
    assert ctrl.nav.controller(ctrl.active_chart).safety.workspace is shrunk  # type: ignore[attr-defined]
    # the body stays clear of the walls (exact distance, every step); 1e-9: rounding
    assert float(np.min(am.atlas.workspace.clearance(np.array(path)))) >= radius - 1e-9


def test_charts_start_cold_and_command_what_warm_charts_command(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    """An installed atlas's charts evaluate by the direct formula until warmed (their local
    expansions built, :meth:`AtlasMap.warm`); a robot's commands are the same either way to
    1e-9 (the tolerance of ``replay --check``); ``prepare`` builds a robot's starting chart
    without touching its switching state; the warm-up order is nearest first."""
    g = Goal(robot_id="r", ws_id="pc", goal=(GOAL.real, GOAL.imag), v_max=1.0, tolerance=0.02)
    cold, warm = rebuilt(wire), rebuilt(wire)
    n = len(cold.nav_maps)
    assert cold.cold_charts() == list(range(n)) and not cold.is_warm(0)
    assert all(warm.warm(i) for i in range(n)) and warm.cold_charts() == []
    assert not warm.warm(0)  # built once
    start = 0.3 + 0.4j
    ctrl = make_controller(cold, g)
    first = ctrl.prepare(start)  # type: ignore[attr-defined]
    assert ctrl.active_chart is None and first  # type: ignore[attr-defined]
    assert cold.cold_by_distance([start])[0] == (first[0], 0.0)
    far = cold.cold_by_distance([GOAL])
    assert far[0][1] == 0.0 and far[-1][1] > 5.0  # the far end of the corridor last
    path = drive(make_controller(warm, g), start)
    u_cold, s_cold = commands(ctrl, np.array(path))
    u_warm, s_warm = commands(make_controller(warm, g), np.array(path))
    assert np.array_equal(s_cold, s_warm)
    assert float(np.max(np.abs(u_cold - u_warm))) <= 1e-9
    assert cold.cold_charts() == list(range(n))  # driving never warmed a chart
    cold.build_on_first_use()  # the old behaviour: the next evaluation builds them
    commands(make_controller(cold, g), np.array(path[:1]))
    assert cold.is_warm(first[0])


def test_revisions_rebuilt_from_their_indexes_share_one_workspace_and_safety_grid(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    """Every revision of an atlas rebuilt from its index, and a workspace of the same
    geometry built elsewhere (the controller's, ahead of the map), is one object, so the
    safety layer's grid (built once per workspace object) is built once."""
    from confnav.atlas.wire import shared_workspace
    from confnav.geometry import Workspace
    from confnav.navigation import defaults
    from confnav.navigation.safety import safety_filter

    index, _ = wire
    ahead = shared_workspace(Workspace.from_dict(dict(index.decomposition)["workspace"]))
    grid = safety_filter(ahead, hold_time=defaults.HOLD_TIME).grid
    a, b = rebuilt(wire), rebuilt(wire)
    assert a is not b and a.atlas.workspace is b.atlas.workspace is ahead
    assert safety_filter(a.atlas.workspace, hold_time=defaults.HOLD_TIME).grid is grid
    other = Workspace([(0, 0), (3, 0), (3, 1), (0, 1)])
    assert shared_workspace(other) is other  # another geometry: its own object


def _partial(index: AtlasIndex, pending: set[int]) -> AtlasIndex:
    """``index`` as a progressive atlas's partial revision whose cells ``pending`` have no
    chart yet (what :func:`messages_of` makes of a ``PartialAtlas``)."""
    from confnav.services.atlas_transform import PENDING

    from confnav.atlas.wire import atlas_revision

    cells = [
        c.model_copy(update={"pending": True, "chart_revision": PENDING})
        if c.index in pending
        else c
        for c in index.cells
    ]
    return index.model_copy(
        update={"cells": cells, "revision": atlas_revision([c.chart_revision for c in cells])}
    )


def test_a_revision_that_adds_charts_reuses_the_cells_and_extends_the_laws(
    wire: tuple[AtlasIndex, list[TransformSolution]],
) -> None:
    """The next revision of a progressive atlas's round (same cells, more charts) rebuilt
    with the installed one as ``previous`` is the atlas a fresh rebuild gives (same cells,
    plan and overlaps; its cells and overlaps reused), and a robot's law on the installed
    revision, extended with the new charts, commands bit for bit what a law built on the
    new revision commands along the same poses."""
    index, charts = wire
    maps = {c.revision: ConformalMap.from_dict(c.coefficients) for c in charts}
    n = len(index.cells)
    assert n >= 3
    first = atlas_map_of(_partial(index, set(range(1, n))), maps)
    second = atlas_map_of(_partial(index, {n - 1}), maps, previous=first)
    full = atlas_map_of(index, maps, previous=second)
    fresh = atlas_map_of(index, maps)
    assert first.pending == list(range(1, n)) and second.pending == [n - 1] and not full.pending
    assert first.cells_key == second.cells_key == full.cells_key == fresh.cells_key
    d1, d2, d3 = (m.atlas.decomposition for m in (first, second, full))
    assert d2.cells[0] is d1.cells[0]  # the same cell with the same chart
    assert d3.cells[0] is d1.cells[0] and d3.cells[1] is d2.cells[1]
    assert d3.links is d1.links and full.links is first.links
    for a, b in zip(d3.cells, fresh.atlas.decomposition.cells, strict=True):
        assert a.polygon.equals_exact(b.polygon, 0.0) and a.cut.equals_exact(b.cut, 0.0)
        assert a.workspace.content_hash == b.workspace.content_hash
    assert d3.links == fresh.atlas.decomposition.links
    p0, p1 = plan(full.atlas, GOAL, full.links), plan(fresh.atlas, GOAL, fresh.links)
    assert np.array_equal(p0.rank, p1.rank) and np.array_equal(p0.next, p1.next)
    assert np.array_equal(p0.local_goal, p1.local_goal)
    assert second.extends(first) and full.extends(second) and full.extends(first)
    assert not first.extends(second)  # a revision with fewer charts

    g = Goal(robot_id="r", ws_id="pc", goal=(GOAL.real, GOAL.imag), v_max=1.0, tolerance=0.02)
    for drv in ({}, {"drive": "unicycle", "lookahead": 0.05}):
        goal = g.model_copy(update=drv)
        before = make_controller(second, goal)
        law = full.extend(before, second)
        assert law is not None and type(law) is type(before)
        nav = getattr(law, "controller", law).nav
        old_nav = getattr(before, "controller", before).nav  # type: ignore[attr-defined]
        assert nav.missing() == [] and nav.atlas is full.atlas and nav.plan is old_nav.plan
        assert old_nav.missing() == [n - 1]  # the law on the previous revision is unchanged
        built = make_controller(fresh, goal)
        path = drive(make_controller(fresh, g), 0.3 + 0.4j)[:600]
        u1, c1 = commands(law, np.array(path))
        u2, c2 = commands(built, np.array(path))
        assert np.array_equal(u1, u2) and np.array_equal(c1, c2)
    # a law on another revision than the one named, or a revision of other cells: refused
    law = make_controller(first, g)
    assert full.extend(law, second) is None
    moved = index.model_copy(update={"margin": float(index.margin) * 0.999})
    assert not atlas_map_of(moved, maps).extends(first)
