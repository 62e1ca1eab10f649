"""Progressive atlas (issue 23, docs/SLAM.md "Progressive atlas"): the charts a robot's route
needs are solved first and handed out as partial revisions; a robot drives through the cells
whose charts are installed, holds (zero command, not an error) where the next chart is
missing, continues when it is installed, and swaps to a complete or refined atlas without
stopping."""

from __future__ import annotations

import concurrent.futures as cf
import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import shapely
from confnav.services.bus import InMemoryNetwork
from confnav.services.controller import ControllerService
from confnav.services.keys import Keys

from confnav.atlas import Atlas, solve_atlas
from confnav.atlas.charts import PartialAtlas, route_order
from confnav.atlas.compose import AtlasNavigator
from confnav.atlas.decompose import decompose
from confnav.atlas.scenes import office
from confnav.atlas.wire import AtlasController, NavMaps, ProgressiveController
from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.navigation.control import Status

TOL = 1e-6
START, GOAL = 0.5 + 0.5j, 9.4 + 0.5j


def pillar_corridor(length: float = 10.0) -> Workspace:
    """A 1 m wide corridor with a 0.4 m pillar 1 m from its far end (as tests/test_atlas.py)."""
    x = length - 1.2
    pillar = [(x, 0.3), (x + 0.4, 0.3), (x + 0.4, 0.7), (x, 0.7)]
    return Workspace([(0, 0), (length, 0), (length, 1), (0, 1)], [pillar])


@pytest.fixture(scope="module")
def progressive() -> tuple[Atlas, list[PartialAtlas]]:
    revisions: list[PartialAtlas] = []
    atlas = solve_atlas(
        pillar_corridor(), TOL, workers=1, priority=[(START, GOAL)], on_partial=revisions.append
    )
    return atlas, revisions


def _drive(law: object, z: complex, steps: int, dt: float = 0.02) -> tuple[complex, int, float]:
    """Euler steps of a point robot under ``law`` (held command): final point, last status,
    smallest clearance to the walls (the collision test)."""
    ws = pillar_corridor()
    clr = float("inf")
    code = int(Status.MOVING)
    for _ in range(steps):
        out = law(np.array([z]))  # type: ignore[operator]
        code = int(out.status[0])
        if code != Status.MOVING:
            break
        z = z + dt * complex(out.u[0])
        clr = min(clr, float(ws.clearance(np.array([z]))[0]))
    return z, code, clr


def test_route_cells_come_first_and_the_result_is_the_plain_atlas(
    progressive: tuple[Atlas, list[PartialAtlas]],
) -> None:
    atlas, revisions = progressive
    dec = atlas.decomposition
    route = route_order(dec, [(START, GOAL)])
    assert len(route) >= 3, "the corridor needs several cells between start and goal"
    # the start cell holds the start; the route ends in a cell holding the goal
    assert dec.cells[route[0]].depth(np.array([START]))[0] > 0
    assert dec.cells[route[-1]].depth(np.array([GOAL]))[0] > 0
    # the first revision has the start cell's chart alone, the next ones add the route in order
    first = [r for r in revisions if r.round == 0]
    assert first[0].installed == (route[0],)
    for k in range(1, len(route)):
        assert set(first[k].installed) == set(route[: k + 1])
    # each revision extends the former one (within a round); the last one is complete
    for a, b in itertools.pairwise(first):
        assert set(a.installed) <= set(b.installed)
    assert revisions[-1].complete
    # the same atlas as the plain solve: same cells, charts with the same coefficients
    plain = solve_atlas(pillar_corridor(), TOL, workers=1)
    assert [c.workspace.content_hash for c in plain.decomposition.cells] == [
        c.workspace.content_hash for c in dec.cells
    ]
    for m, p in zip(atlas.charts, plain.charts, strict=True):
        np.testing.assert_allclose(m.radii, p.radii, rtol=0, atol=1e-12)


def test_a_partial_atlas_drives_the_robot_through_its_installed_cells_to_the_goal(
    progressive: tuple[Atlas, list[PartialAtlas]],
) -> None:
    atlas, revisions = progressive
    route = route_order(atlas.decomposition, [(START, GOAL)])
    # the first revision holding the whole route, not yet complete
    part = next(r for r in revisions if set(route) <= set(r.installed))
    assert not part.complete, "the route should not need every cell of the corridor"
    law = ProgressiveController(GOAL)
    law.offer(part)
    z, code, clr = _drive(law, START, 2000)
    assert code == Status.ARRIVED and abs(z - GOAL) < 0.05
    assert clr > 0
    assert law.law is not None
    assert set(law.law.history) <= set(part.installed)
    with pytest.raises(NavigationError, match="not installed"):
        law.law.nav.controller(next(i for i in range(len(part.charts)) if i not in part.installed))


def test_a_robot_holds_at_a_missing_chart_and_goes_on_when_it_is_installed(
    progressive: tuple[Atlas, list[PartialAtlas]],
) -> None:
    atlas, revisions = progressive
    route = route_order(atlas.decomposition, [(START, GOAL)])
    first = revisions[0]
    assert first.installed == (route[0],)
    maps = NavMaps()
    law = ProgressiveController(GOAL, nav_maps=maps)
    # before any revision: zero command, still MOVING (waiting), never an error
    out = law(np.array([START]))
    assert out.u[0] == 0 and out.status[0] == Status.MOVING
    law.offer(first)
    z, code, clr = _drive(law, START, 2000)
    # it stopped at its local goal, waiting for the next cell's chart
    assert code == Status.MOVING and clr > 0
    out = law(np.array([z]))
    assert out.u[0] == 0 and out.status[0] == Status.MOVING
    assert law.waiting == route[1]
    assert abs(z - complex(law.law.nav.plan.local_goal[route[0]])) < 0.05  # type: ignore[union-attr]
    # the controller service's status says what the robot holds for
    svc = ControllerService(InMemoryNetwork().bus("ctl"), Keys())
    robot = SimpleNamespace(ctrl=law, base_ws=None, atlas_ws=None, ctrl_revision=None)
    assert f"holding for chart {route[1]} of the atlas (being solved" in svc._map_note(robot)  # type: ignore[arg-type]
    # a unicycle's look-ahead law wraps the atlas controller: its status says the same
    wrapped = SimpleNamespace(ctrl=SimpleNamespace(controller=law.law), base_ws=None,
                              atlas_ws=None, ctrl_revision=None)  # fmt: skip
    assert f"holding for chart {route[1]} of the atlas (being solved" in svc._map_note(wrapped)  # type: ignore[arg-type]
    held = law.law
    # the complete atlas extends the revision: installed in place (same law), it goes on
    law.offer(atlas)
    assert law.law is held and law.swaps == 0
    out = law(np.array([z]))
    assert abs(out.u[0]) > 0 and law.waiting is None
    assert "holding" not in svc._map_note(robot)  # type: ignore[arg-type]
    z, code, clr = _drive(law, z, 2000)
    assert code == Status.ARRIVED and abs(z - GOAL) < 0.05 and clr > 0


def test_a_refined_atlas_is_swapped_in_between_two_commands(
    progressive: tuple[Atlas, list[PartialAtlas]],
) -> None:
    atlas, _ = progressive
    law = ProgressiveController(GOAL)
    law.offer(atlas)
    z, _, _ = _drive(law, START, 200)  # under way
    assert abs(z - START) > 1.0
    refined = solve_atlas(pillar_corridor(), 1e-8, workers=1)
    law.offer(refined)
    assert law.swaps == 1 and law.law is not None and law.law.nav.atlas is refined
    out = law(np.array([z]))
    assert abs(out.u[0]) > 0 and out.status[0] == Status.MOVING  # no stop at the swap
    z, code, clr = _drive(law, z, 2000)
    assert code == Status.ARRIVED and abs(z - GOAL) < 0.05 and clr > 0


def test_a_start_in_no_installed_cell_waits_while_one_outside_every_cell_is_an_error(
    progressive: tuple[Atlas, list[PartialAtlas]],
) -> None:
    atlas, revisions = progressive
    route = route_order(atlas.decomposition, [(START, GOAL)])
    nav = AtlasNavigator(revisions[0], GOAL)
    ctrl = AtlasController(nav)
    far = 5.0 + 0.5j  # in a cell of the route whose chart is not installed yet
    assert not any(revisions[0].decomposition.cells[i].depth(np.array([far]))[0] > 0
                   for i in revisions[0].installed)  # fmt: skip
    out = ctrl(np.array([far]))
    assert out.u[0] == 0 and out.status[0] == Status.MOVING
    assert ctrl.waiting in route
    out = ctrl(np.array([20.0 + 0.5j]))  # outside the workspace
    assert out.status[0] == Status.ERROR
    with pytest.raises(NavigationError, match="every chart"):
        nav.run([START])


def test_on_a_process_pool_revisions_come_chart_by_chart_route_first() -> None:
    revisions: list[PartialAtlas] = []
    atlas = solve_atlas(
        pillar_corridor(), TOL, workers=2, priority=[(START, GOAL)], on_partial=revisions.append
    )
    route = route_order(atlas.decomposition, [(START, GOAL)])
    first = [r for r in revisions if r.round == 0]
    # a revision per route chart as it comes, the route's cells first; other cells solved on
    # the second worker meanwhile ride along (how many: a matter of timing, not checked)
    on_route = [len(set(r.installed) & set(route)) for r in first]
    assert all(b - a in (0, 1) for a, b in itertools.pairwise(on_route)), on_route
    assert on_route[0] == 1 and on_route[-1] >= 2
    assert revisions[-1].complete


def test_fine_splits_a_starts_tile_until_its_cell_is_small_and_the_cells_still_cover() -> None:
    ws = office().workspace
    plain = decompose(ws)
    corners = {i: len(c.polygon.exterior.coords) - 1 for i, c in enumerate(plain.cells)}
    # a start in the plain decomposition's cell with the most vertices
    big = max(corners, key=lambda i: corners[i])
    assert corners[big] > 12
    tile = plain.cells[big].tile
    core = shapely.box(*tile).intersection(plain.cells[big].polygon)
    p = core.representative_point()
    start = complex(p.x, p.y)
    fine = decompose(ws, fine=[start], fine_vertices=12, margin=plain.margin)
    assert fine.uncovered_area() < 1e-9 * ws.polygon.area
    assert len(fine.cells) > len(plain.cells)
    # the cell holding the start in its core tile: at most 12 vertices, or its tile at the
    # smallest side (min_tile = tile / 16)
    pt = np.array([start])
    own = [c for c in fine.cells
           if c.tile[0] <= start.real < c.tile[2] and c.tile[1] <= start.imag < c.tile[3]
           and c.depth(pt)[0] > 0]  # fmt: skip
    assert own
    for c in own:
        n = len(c.polygon.exterior.coords) - 1 + sum(len(h.coords) - 1 for h in c.polygon.interiors)
        assert n <= 12 or (c.tile[2] - c.tile[0]) < 2 * fine.tile / 16 + 1e-9
    # cells far from the start are the plain ones
    far = {c.workspace.content_hash for c in plain.cells if c.polygon.distance(
        plain.cells[big].polygon) > 2 * plain.tile}  # fmt: skip
    assert far <= {c.workspace.content_hash for c in fine.cells}


def test_routes_that_arrive_mid_solve_go_into_the_next_batch() -> None:
    """``priority`` as a callable (the transform service's route hints): a robot's route that
    arrives after the first batch puts its start cell into the next one, ahead of the cells
    of the route known from the start (and of the plain largest-first order)."""
    ws = pillar_corridor()
    known, late = (START, GOAL), (GOAL, START)  # the late robot starts at the far end
    routes = [known]
    revisions: list[PartialAtlas] = []

    def on_partial(pa: PartialAtlas) -> None:
        revisions.append(pa)
        if late not in routes:
            routes.append(late)  # arrives while the first batch's chart was being solved

    atlas = solve_atlas(ws, TOL, workers=1, batch=1, priority=lambda: list(routes),
                        on_partial=on_partial)  # fmt: skip
    dec = atlas.decomposition
    first = [r for r in revisions if r.round == 0]
    assert len({r.decomposition.keys for r in first}) == 1 and len(first) >= 3
    mine, theirs = route_order(dec, [known]), route_order(dec, [late])
    assert first[0].installed == (mine[0],)
    # without the late route the known route's second cell would come next: a different one
    assert theirs[0] not in mine[:2]
    assert set(first[1].installed) - set(first[0].installed) == {theirs[0]}
    assert revisions[-1].complete


class _ChartExecutor(cf.Executor):
    """An executor that is not a process pool but solves single charts (``submit``), as the
    transform service's (services/atlas_transform.py, ``SharedExecutor``)."""

    submits_charts = True

    def __init__(self) -> None:
        self.pool = cf.ProcessPoolExecutor(2)
        self.submitted = 0

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[no-untyped-def,override]
        self.submitted += 1
        return self.pool.submit(fn, *args, **kwargs)

    def map(self, fn, *iterables, **_kw):  # type: ignore[no-untyped-def,override]
        return self.pool.map(fn, *iterables)

    def shutdown(self, wait: bool = True, **_kw: object) -> None:
        self.pool.shutdown(wait)


def test_on_an_executor_that_submits_charts_each_robots_chart_is_a_revision() -> None:
    """Two robots at the corridor's two ends, two workers: each of their start cells' charts
    is a revision as it comes (before, on the transform service's executor, the first
    revision waited for both: the robot whose chart came first waited for the other's), the
    start cells solved through ``submit``; the result is the plain atlas."""
    routes = [(START, GOAL), (GOAL, START)]
    revisions: list[PartialAtlas] = []
    ex = _ChartExecutor()
    try:
        atlas = solve_atlas(pillar_corridor(), TOL, workers=2, executor=ex, batch=2,
                            priority=routes, on_partial=revisions.append)  # fmt: skip
    finally:
        ex.shutdown()
    starts = [[route_order(r.decomposition, [rt])[0] for rt in routes] for r in revisions]
    got = [sum(k in r.installed for k in s) for r, s in zip(revisions, starts, strict=True)]
    first = next(k for k, n in enumerate(got) if n)
    assert got[first] == 1, got  # one robot's chart, not both
    assert max(got) == 2 and ex.submitted >= 2
    plain = solve_atlas(pillar_corridor(), TOL, workers=1)
    assert atlas.decomposition.keys == plain.decomposition.keys
    assert revisions[-1].complete
