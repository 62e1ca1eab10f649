"""Atlas of conformal charts: decomposition invariants, the composition's assumptions
(local goals deep in overlaps, acyclic order), chart accuracy against a closed form, switching
without chattering, and a corridor a single map cannot do, navigated end to end."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import shapely
from scipy.optimize import brentq
from scipy.special import ellipk

import confnav
from confnav.atlas import (
    Atlas,
    AtlasNavigator,
    atlas_reason,
    bottleneck,
    decompose,
    elongation,
    needs_atlas,
    overlaps,
    plan,
    solve_atlas,
    solve_auto,
)
from confnav.atlas.charts import BOTTLENECK_MAX_RATIO
from confnav.atlas.scenes import corridor, office, spiral, warehouse
from confnav.errors import SolverError, WorkspaceError
from confnav.geometry import Workspace
from confnav.navigation.shortest_path import ShortestPaths
from confnav.scenes.scenarios import random_starts

TOL = 1e-6  # navigation needs T to ~1e-6 of the unit disk; the test scenes are small


def pillar_corridor(length: float = 12.0, anchor: tuple[float, float] | None = None) -> Workspace:
    """A 1 m wide corridor with a 0.4 m pillar 1 m from its far end."""
    x = length - 1.2
    pillar = [(x, 0.3), (x + 0.4, 0.3), (x + 0.4, 0.7), (x, 0.7)]
    return Workspace([(0, 0), (length, 0), (length, 1), (0, 1)], [pillar], anchor=anchor)


@pytest.fixture(scope="module")
def atlas() -> Atlas:
    return solve_atlas(pillar_corridor(), TOL, workers=2)


GOAL = 11.6 + 0.5j  # behind the pillar, at the far end


# ---------------------------------------------------------------- decomposition invariants
@pytest.mark.parametrize(
    "ws",
    [pillar_corridor(), spiral(30).workspace, office().workspace, warehouse(4, 3).workspace],
    ids=["pillar corridor", "spiral 30", "office", "warehouse 12"],
)
def test_cells_cover_the_free_space_and_respect_their_bounds(ws: Workspace) -> None:
    dec = decompose(ws)
    free = ws.polygon
    assert dec.uncovered_area() <= 1e-9 * free.area
    for c in dec.cells:
        assert c.ratio <= (dec.max_ratio_holes if c.workspace.n_obstacles else dec.max_ratio)
        assert c.workspace.n_obstacles <= dec.max_obstacles
        # a cell is a piece of the free space, and its workspace is that piece
        assert c.polygon.difference(free).area <= 1e-9 * c.polygon.area
        assert abs(c.workspace.polygon.area - c.polygon.area) <= 1e-9 * c.polygon.area


def test_overlaps_hold_a_margin_disk_and_connect_the_cells(atlas: Atlas) -> None:
    dec = atlas.decomposition
    links = overlaps(atlas)
    assert links
    for o in links:
        common = dec.cells[o.a].polygon.intersection(dec.cells[o.b].polygon)
        p = shapely.Point(o.point.real, o.point.imag)
        assert common.contains(p)
        assert common.boundary.distance(p) >= dec.margin * (1 - 1e-9)
    # the free space is connected, so every cell must reach the goal
    pl = plan(atlas, GOAL, links)
    assert np.all(np.isfinite(pl.rank))


def test_local_goals_lie_deep_in_the_next_cell_and_the_order_is_acyclic(atlas: Atlas) -> None:
    nav = AtlasNavigator(atlas, GOAL)
    pl = nav.plan
    cells = atlas.decomposition.cells
    margin = atlas.decomposition.margin
    assert pl.goal_cells
    for i in range(len(cells)):
        j = int(pl.next[i])
        if j < 0:
            assert i in pl.goal_cells and pl.local_goal[i] == GOAL
            continue
        assert pl.rank[j] < pl.rank[i]  # strictly closer: no cycle
        g = pl.local_goal[i : i + 1]
        # deep inside the overlap: beyond the hysteresis in the next cell, a margin from walls
        assert cells[j].depth(g)[0] >= margin > nav.hysteresis
        assert cells[i].workspace.clearance(g)[0] >= margin * (1 - 1e-9)
        assert cells[j].workspace.clearance(g)[0] >= margin * (1 - 1e-9)
    # following next from any cell ends in a goal cell within len(cells) steps
    for i in range(len(cells)):
        seen = [i]
        while pl.next[seen[-1]] >= 0:
            seen.append(int(pl.next[seen[-1]]))
            assert len(seen) <= len(cells)
        assert seen[-1] in pl.goal_cells


# ---------------------------------------------------------------- charts
def _rectangle_derivative(a: float, b: float) -> float:
    """f'(0) of the map of [-a, a] x [-b, b] onto the disk, f(0) = 0 (DESIGN.md section 4):
    (1 + k) K / (2 a) with K'/K = 2 b / a."""
    m = brentq(lambda m: ellipk(1 - m) / ellipk(m) - 2 * b / a, 1e-12, 1 - 1e-12)
    return float((1 + np.sqrt(m)) * ellipk(m) / (2 * a))


def test_every_chart_is_accurate(atlas: Atlas) -> None:
    checked = 0
    for cell, m in zip(atlas.decomposition.cells, atlas.charts, strict=True):
        assert m.diagnostics.error_estimate <= TOL
        assert np.all(m.radii > 1e-3)  # no crowding inside a cell
        # rectangular cells against the closed form: the conformal radius at the centre,
        # |f'(c)| / (1 - |f(c)|^2), does not depend on the anchor
        if cell.workspace.n_obstacles == 0 and cell.workspace.outer.size == 4:
            x0, y0, x1, y1 = cell.polygon.bounds
            c = complex((x0 + x1) / 2, (y0 + y1) / 2)
            w, dw = m.T_and_dT(np.array([c]))
            radius = abs(dw[0]) / (1 - abs(w[0]) ** 2)
            exact = _rectangle_derivative((x1 - x0) / 2, (y1 - y0) / 2)
            assert radius == pytest.approx(exact, rel=1e-5)
            checked += 1
    assert checked >= 2
    assert atlas.cpu_time > 0 and atlas.wall_time > 0


def test_solve_atlas_splits_a_tile_whose_cell_fails() -> None:
    ws = pillar_corridor()
    base = decompose(ws)
    tile = base.cells[0].tile
    dec = decompose(ws, split=[tile])
    assert len(dec.cells) > len(base.cells)
    assert all(c.tile != tile for c in dec.cells)
    assert dec.uncovered_area() <= 1e-9 * ws.polygon.area


def slit_pocket(width: float = 0.05, length: float = 1.2) -> Workspace:
    """A 4 x 3 m room with a table and, off its top wall, a 0.5 m pocket reached only through
    a slit ``width`` wide and ``length`` long: one chart holding the slit crowds the pocket
    like exp(-pi length / width)."""
    a, b = 2 - width / 2, 2 + width / 2
    top = 3 + length
    outer = [(0, 0), (4, 0), (4, 3), (b, 3), (b, top), (2.25, top), (2.25, top + 0.5),
             (1.75, top + 0.5), (1.75, top), (a, top), (a, 3), (0, 3)]  # fmt: skip
    return Workspace(outer, [[(1, 1), (2.5, 1), (2.5, 1.6), (1, 1.6)]])


def test_a_failed_chart_splits_below_min_tile_until_it_maps() -> None:
    """The a-priori tests stop at ``min_tile`` (here 1.2 m: tiles of 2.55 m); the cells holding
    the slit then crowd, and their tiles are split further on the failure alone (the studio
    of a SLAM grid: a speck 6 cm from the sofa failed at min_tile before)."""
    ws = slit_pocket()
    a = solve_atlas(ws, TOL, workers=2, min_tile=1.2)
    sides = [c.tile[2] - c.tile[0] for c in a.decomposition.cells]
    assert min(sides) < 1.2 / 2  # split on failure, below min_tile
    assert any(r.error.startswith("crowded") for r in a.records)  # why they split
    # each final cell's own solve (cell numbers change between rounds; the hash does not)
    recs = a.chart_records
    assert [r.key for r in recs] == [c.workspace.content_hash for c in a.decomposition.cells]
    assert all(not r.error and r.n_nodes == m.n_nodes for r, m in zip(recs, a.charts, strict=True))
    assert a.decomposition.uncovered_area() <= 1e-9 * ws.polygon.area
    # every chart maps its cell's deep points away from the unit circle: the pocket's centre
    pocket = complex(2.0, 4.45)
    inside = [i for i, c in enumerate(a.decomposition.cells) if c.depth(np.array([pocket]))[0] > 0]
    assert inside
    for i in inside:
        assert 1 - abs(complex(a.charts[i].T(np.array([pocket]))[0])) > 1e-6


def test_bottleneck_finds_a_region_behind_a_long_narrow_passage() -> None:
    """A pocket behind a 5 cm x 1.2 m slit (L/w = 24) is found a priori, where the slit is;
    two near-touching squares (gap 0.01: the circles come close, nothing crowds) and a room
    with a 0.9 m door are not."""
    ws = slit_pocket()
    q, where = bottleneck(ws.polygon)
    assert q > BOTTLENECK_MAX_RATIO and abs(where.real - 2) < 0.025 and 3 < where.imag < 4.2
    assert elongation(ws.polygon) < 8 and needs_atlas(ws)  # elongation alone misses it
    assert "narrow passage at (1.99" in atlas_reason(ws)

    def sq(x: float) -> list[tuple[float, float]]:
        return [(x, -0.5), (x + 1, -0.5), (x + 1, 0.5), (x, 0.5)]

    pair = Workspace([(-2, -2), (2, -2), (2, 2), (-2, 2)], [sq(-1.005), sq(0.005)])
    assert bottleneck(pair.polygon)[0] < 1 and not needs_atlas(pair)
    wall = [(0, 0), (5.95, 0), (5.95, 2.0), (6.05, 2.0), (6.05, 0), (12, 0), (12, 5), (6.05, 5),
            (6.05, 2.9), (5.95, 2.9), (5.95, 5), (0, 5)]  # fmt: skip
    assert bottleneck(Workspace(wall, []).polygon)[0] < 1


def test_a_loop_around_an_obstacle_is_no_channel_with_loops() -> None:
    """A 0.6 m wide ring around a 1.8 m box in a 3 m room: elongation 10.6 (a loop of length
    ~10 w), yet conformally an annulus; ``loops=True`` fills the box and finds nothing, while a
    dead-end corridor of the same elongation stays too elongated."""
    box = [(-0.9, -0.9), (0.9, -0.9), (0.9, 0.9), (-0.9, 0.9)]
    ring = Workspace([(-1.5, -1.5), (1.5, -1.5), (1.5, 1.5), (-1.5, 1.5)], [box])
    assert "too elongated" in atlas_reason(ring) and atlas_reason(ring, loops=True) == ""
    assert "too elongated" in atlas_reason(corridor(10).workspace, loops=True)


def test_a_failed_tile_at_the_smallest_split_stays() -> None:
    """A failed tile splits down to a side of FORCED_MIN_MARGINS margins, no further."""
    ws = slit_pocket()
    dec = decompose(ws, margin=0.05)
    small = next(c.tile for c in decompose(ws, margin=0.05, split=[dec.cells[0].tile]).cells)
    side = small[2] - small[0]
    split = [small]
    for _ in range(8):  # split the same corner until it stops
        cells = decompose(ws, margin=0.05, split=split).cells
        corner = min((c.tile for c in cells), key=lambda t: (t[2] - t[0], t[0], t[1]))
        if corner in split:
            break
        split.append(corner)
        side = corner[2] - corner[0]
    assert 2 * 0.05 <= side < 4 * 0.05 + 1e-9


def test_bad_parameters_are_clear_errors() -> None:
    with pytest.raises(WorkspaceError, match="overlap"):
        decompose(pillar_corridor(), overlap=1.5)
    with pytest.raises(confnav.NavigationError, match="no cell"):
        plan_goal_outside()


def plan_goal_outside() -> None:
    ws = corridor(3).workspace
    a = solve_atlas(ws, TOL, workers=1)
    plan(a, 10 + 10j)


# ---------------------------------------------------------------- switching
def test_switching_has_hysteresis_and_never_goes_back(atlas: Atlas) -> None:
    nav = AtlasNavigator(atlas, GOAL)
    cells = atlas.decomposition.cells
    pl = nav.plan
    # points along the corridor's centre line
    line = np.linspace(0.0, 12.0, 2401) + 0.5j
    found = 0
    for i in map(int, np.argsort(pl.rank)[::-1]):
        j = int(pl.next[i])
        if j < 0:
            continue
        xs = line[cells[i].depth(line) > 0]
        out = nav.switch(xs, np.full(xs.size, i, dtype=np.int64))
        # the rule, point by point: the lowest-ranked cell of lower rank than i holding the
        # point deeper than the hysteresis, else i
        lower = [c for c in range(len(cells)) if pl.rank[c] < pl.rank[i]]
        depth = np.array([cells[c].depth(xs) for c in lower])
        expected = np.full(xs.size, i)
        for k in np.argsort([pl.rank[c] for c in lower])[::-1]:  # lowest rank written last
            expected[depth[k] > nav.hysteresis] = lower[k]
        assert np.array_equal(out, expected)
        assert np.all(pl.rank[out] <= pl.rank[i])
        # inside cell j but closer to its cut than the hysteresis (and no deeper in any other
        # lower cell): no switch
        d_j = cells[j].depth(xs)
        shallow = (d_j > 0) & (d_j <= nav.hysteresis) & np.all(depth <= nav.hysteresis, axis=0)
        found += int(shallow.sum())
        assert np.all(out[shallow] == i)
        # a robot jittering across the switching line: switches, never back, at most once
        # per lower cell
        k = int(np.flatnonzero(out != i)[0])
        cur = np.array([i])
        seq = [i]
        for step in range(60):
            z = xs[max(k - 3, 0) : k + 4]
            cur = nav.switch(z[step % z.size : step % z.size + 1], cur)
            seq.append(int(cur[0]))
        changes = sum(a != b for a, b in itertools.pairwise(seq))
        assert 1 <= changes <= len(lower)
        assert np.all(np.diff(pl.rank[seq]) <= 0) and i not in seq[1 + seq.index(seq[-1]) :]
    assert found > 0  # the hysteresis band was exercised


# ---------------------------------------------------------------- end to end
@pytest.mark.slow
def test_corridor_a_single_map_cannot_do_is_navigated_by_the_atlas(atlas: Atlas) -> None:
    # anchored at the near end, the single map of this corridor (L/w = 12) fails: the
    # pillar's circle crowds below what the integral equation resolves
    with pytest.raises(SolverError):
        confnav.solve(pillar_corridor(anchor=(0.5, 0.5)), TOL)
    assert needs_atlas(pillar_corridor())
    ws = atlas.workspace
    nav = AtlasNavigator(atlas, GOAL)
    starts = random_starts(ws, 24, seed=3)
    run = nav.run(starts, record_paths=True)
    assert run.success.all(), run.message
    assert not run.collided.any()
    assert np.all(run.min_clearance > 0)
    # every chart's commands pass the safety layer against the whole workspace (a chart's cut
    # edges are not walls: the robots above crossed them)
    assert nav._controllers
    for ctl in nav._controllers.values():
        assert ctl.safety is not None and ctl.safety.workspace is ws
        assert ctl.safety_counts.commands > 0
    # the recorded paths (windows joined) are the robots' paths: start, end and length
    assert run.paths is not None and len(run.paths) == starts.size
    for k, p in enumerate(run.paths):
        assert p[0] == starts[k] and p[-1] == run.final[k]
        assert np.sum(np.abs(np.diff(p))) == pytest.approx(run.path_length[k], rel=1e-9)
        assert np.all(ws.clearance(p) > 0)
    # each robot's cells go strictly down the order: at most one visit per cell
    for seq in run.cells:
        ranks = nav.plan.rank[list(seq)]
        assert np.all(np.diff(ranks) < 0)
    short = ShortestPaths(ws, GOAL).lengths(starts)
    assert np.median(run.path_length / short) <= 1.3


def test_solve_auto_picks_one_map_for_a_room_and_an_atlas_for_a_corridor() -> None:
    room = Workspace([(0, 0), (2, 0), (2, 2), (0, 2)])
    assert not needs_atlas(room)
    assert isinstance(solve_auto(room, TOL), confnav.ConformalMap)
    res = solve_auto(corridor(12).workspace, TOL, workers=1)
    assert isinstance(res, Atlas) and len(res.charts) >= 3
