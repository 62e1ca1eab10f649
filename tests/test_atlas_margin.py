"""The atlas margin from the passages: narrow doors get a margin that fits them by default, a
given margin that cannot fit is a typed error naming the passage, and a robot in a cell cut
off from the goal's says so (reason ``unreachable``) instead of "outside the free space"."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from shapely.geometry import Point, box
from test_atlas import TOL, pillar_corridor

from confnav.atlas import Atlas, AtlasNavigator, PassageError, decompose, overlaps, solve_atlas
from confnav.atlas.decompose import AUTO_MARGIN_FRACTION, Decomposition, inscribed
from confnav.atlas.wire import AtlasController
from confnav.cli.app import main
from confnav.errors import fmt_point
from confnav.geometry import Workspace
from confnav.maps.footprint import inflate
from confnav.navigation.messages import command, decide
from confnav.navigation.sim import ERROR

# /work/shared/scenes/door.json: two 6 x 5 m rooms joined by a 0.8 m door in a 0.15 m wall
DOOR_OUTER = [(6.15, 2.8), (6.15, 5), (12, 5), (12, 0), (6.15, 0), (6.15, 2), (6, 2), (6, 0),
              (0, 0), (0, 5), (6, 5), (6, 2.8)]  # fmt: skip
DOOR_FURNITURE = [
    [(1, 1), (2.5, 1), (2.5, 1.8), (1, 1.8)],
    [(3.5, 3), (4.2, 3), (4.2, 4.5), (3.5, 4.5)],
    [(8, 0.8), (10.5, 0.8), (10.5, 1.6), (8, 1.6)],
    [(9, 3), (10.5, 3), (10.5, 4.4), (10.1, 4.4), (10.1, 3.4), (9, 3.4)],
]
DOOR_GOAL = 11.2 + 4.3j
DOOR_STARTS = [0.5 + 0.5j, 0.5 + 4.5j, 5.5 + 4.6j, 3 + 2.5j, 7 + 4.5j]
BODY = 0.3  # a robot of radius 0.2 with a 0.1 m safety (or look-ahead): the door is 0.2 m


def door_shrunk() -> Workspace:
    """The door scene for the centre of that robot: its door 0.8 - 2 * 0.3 = 0.2 m wide."""
    return inflate(Workspace(DOOR_OUTER, DOOR_FURNITURE), BODY, keep=DOOR_GOAL)


def two_rooms() -> Workspace:
    """Two 5 x 4 m rooms joined by a 0.25 m doorway through a 0.6 m wall, a table in each."""
    y0, y1 = 1.9, 2.15
    outer = [(0, 0), (5, 0), (5, y0), (5.6, y0), (5.6, 0), (10.6, 0), (10.6, 4), (5.6, 4),
             (5.6, y1), (5, y1), (5, 4), (0, 4)]  # fmt: skip
    tables = [
        [(1, 1), (2.2, 1), (2.2, 1.8), (1, 1.8)],
        [(8, 2.2), (9.2, 2.2), (9.2, 3.1), (8, 3.1)],
    ]
    return Workspace(outer, tables)


ROOMS_GOAL = 10.1 + 0.5j
# (workspace, the doorway as a box, its width, goal, starts beyond the door)
SCENES = {
    "door scene shrunk by 0.3 m": (
        door_shrunk, box(5.7, 2.3, 6.45, 2.5), 0.2, DOOR_GOAL,
        [*DOOR_STARTS[:4], 0.4 + 2.5j, 5.6 + 0.4j, 2.5 + 4.6j],
    ),
    "two rooms, 0.25 m door": (
        two_rooms, box(5, 1.9, 5.6, 2.15), 0.25, ROOMS_GOAL,
        [0.5 + 0.5j, 0.5 + 3.5j, 4.6 + 3.6j, 3 + 2.5j, 4.8 + 0.3j, 1.6 + 2.4j, 7 + 3.5j],
    ),
}  # fmt: skip


def connected(dec: Decomposition) -> bool:
    """Do the overlaps at least ``margin`` deep link every cell (the plan's cell graph)?"""
    links = [o for o in dec.links if o.depth >= dec.margin]
    n = len(dec.cells)
    a = [o.a for o in links]
    b = [o.b for o in links]
    graph = csr_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    return bool(connected_components(graph, directed=False)[0] == 1)


@functools.cache
def solved(name: str) -> Atlas:
    """The scene's atlas with the defaults (solved once per test session)."""
    return solve_atlas(SCENES[name][0](), TOL, workers=2)


@pytest.fixture(params=sorted(SCENES))
def scene(request: pytest.FixtureRequest) -> tuple[str, Atlas]:
    return request.param, solved(request.param)


# ---------------------------------------------------------------- the margin
@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_margin_fits_the_narrowest_passage_the_cells_need(name: str) -> None:
    make, door, width, _, _ = SCENES[name]
    ws = make()
    dec = decompose(ws)
    thin = dec.passage
    assert thin is not None
    # the decomposition cuts through the doorway, and that is its narrowest passage
    assert door.contains(Point(thin.point.real, thin.point.imag))
    assert 2 * float(ws.clearance(np.array([thin.point]))[0]) == pytest.approx(width, rel=1e-3)
    assert thin.depth == pytest.approx(width / 2, rel=1e-3)
    # the old default (a tenth of the inradius) does not fit it; the derived margin does
    assert 0.1 * inscribed(ws.polygon)[1] > width / 2
    assert dec.margin == pytest.approx(AUTO_MARGIN_FRACTION * thin.depth)
    assert connected(dec)
    assert dec.uncovered_area() <= 1e-9 * ws.polygon.area


def test_a_wide_workspace_keeps_the_default_margin() -> None:
    ws = pillar_corridor()
    dec = decompose(ws)
    assert dec.margin == pytest.approx(0.1 * inscribed(ws.polygon)[1])
    assert dec.passage is not None and dec.passage.depth >= dec.margin
    assert connected(dec)


def test_a_given_margin_overrides_and_one_that_cannot_fit_names_the_passage() -> None:
    ws = door_shrunk()
    assert decompose(ws, margin=0.08).margin == 0.08  # given and fits: kept as given
    with pytest.raises(PassageError) as err:
        decompose(ws, margin=0.13)
    e = err.value
    assert box(5.7, 2.3, 6.45, 2.5).contains(Point(e.point.real, e.point.imag))
    assert e.width == pytest.approx(0.2, rel=1e-3) and e.margin == 0.13
    text = str(e)
    assert fmt_point(e.point) in text and "0.2 m wide" in text and "margin below 0.1 m" in text
    assert "\n" not in text


# ---------------------------------------------------------------- defaults navigate
def test_defaults_drive_every_start_through_the_narrow_door(scene: tuple[str, Atlas]) -> None:
    name, atlas = scene
    _, door, _, goal, starts = SCENES[name]
    assert atlas.decomposition.margin < door.bounds[3] - door.bounds[1]  # the derived one
    nav = AtlasNavigator(atlas, goal)
    assert np.all(np.isfinite(nav.plan.rank))
    run = nav.run(np.array(starts))
    assert run.success.all(), run.reasons
    assert not run.collided.any()
    assert np.all(run.min_clearance > 0)
    assert all(r == "arrived" for r in run.reasons)
    for cells in run.cells:  # through the door, down the plan: ranks strictly decrease
        assert all(nav.plan.rank[a] > nav.plan.rank[b] for a, b in itertools.pairwise(cells))


def test_confnav_atlas_defaults_on_the_door_with_a_robot_radius(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "door.json"
    Workspace(DOOR_OUTER, DOOR_FURNITURE).save(path)
    starts = ";".join(f"{z.real},{z.imag}" for z in DOOR_STARTS)
    args = ["atlas", str(path), f"--goal={DOOR_GOAL.real},{DOOR_GOAL.imag}",
            f"--starts={starts}", "--robot-radius=0.2", "--unicycle=0.1", "--tol=1e-6",
            "--workers=1"]  # fmt: skip
    out = tmp_path / "runs.json"
    code = main([*args, "--json", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "5 arrived; collisions 0" in text
    # the door's half-width halved (the channels under the furniture, 0.2 m too, are
    # crowded: their tiles split, and the passage named may be one of those)
    assert "margin 0.05 m (automatic); thinnest overlap the cells need: " in text
    assert all(r["reason"] == "arrived" for r in json.loads(out.read_text())["runs"])
    # a given margin that cannot fit: one line naming the passage, no robot run
    assert main([*args, "--margin=0.13"]) == 1
    cap = capsys.readouterr()
    assert "arrived" not in cap.out
    err = cap.err.strip()
    assert len(err.splitlines()) == 1 and "passage at (6.14" in err and "0.2 m wide" in err


# ---------------------------------------------------------------- cut off from the goal
def test_a_robot_cut_off_from_the_goal_is_told_why() -> None:
    """An atlas whose margin the door cannot hold (as one rebuilt from an older index could
    be: ``decompose`` refuses to make one): the left room's cells have no rank."""
    atlas = solved("door scene shrunk by 0.3 m")
    thin = dataclasses.replace(atlas.decomposition, margin=0.13)
    cut = dataclasses.replace(atlas, decomposition=thin)
    assert len(overlaps(cut)) < len(overlaps(atlas))
    nav = AtlasNavigator(cut, DOOR_GOAL)
    left, right = 0.5 + 0.5j, 7 + 4.5j
    run = nav.run(np.array([left, right]))
    assert run.status[0] == ERROR and run.success[1]
    why = run.reasons[0]
    assert "cut off from the goal's cells" in why and "margin 0.13 m" in why
    x, y = map(float, re.search(r"way, at \(([-\d.]+), ([-\d.]+)\)", why).groups())  # type: ignore[union-attr]
    assert box(5.7, 2.3, 6.45, 2.5).contains(Point(x, y)) and "0.2 m wide" in why  # the door
    assert run.reasons[1] == "arrived" and nav.cut_off(right) == ""
    # what the controller service publishes (the decision replay --check recomputes too)
    ctrl = AtlasController(nav)
    u, code = command(ctrl, left.real, left.imag)
    d = decide(ctrl, u, code)
    assert (d.u, d.state, d.reason) == (0j, "stopped", "unreachable") and d.message == why
    # outside every cell it is still "outside_workspace"; back inside, moving again
    u, code = command(ctrl, 6.05, 1.0)  # in the wall
    assert decide(ctrl, u, code).reason == "outside_workspace"
    u, code = command(ctrl, right.real, right.imag)
    assert decide(ctrl, u, code).reason == "ok" and abs(u) > 0


def test_one_tile_keeps_its_narrow_channels() -> None:
    """A workspace one tile holds has no cut: nothing may be cleaned off (measured: the
    near_touching scene shrunk by 0.2 m lost 4.0 of its 15.6 m^2, robots there in no cell)."""
    table = [(1.5, 0.1), (2.5, 0.1), (2.5, 0.8), (1.5, 0.8)]  # 0.1 m from the wall
    ws = Workspace([(0, 0), (4, 0), (4, 4), (0, 4)], [table])
    dec = decompose(ws, tile=10.0)
    assert len(dec.cells) == 1 and dec.cells[0].cut.is_empty
    assert dec.uncovered_area() <= 1e-12 * ws.polygon.area
