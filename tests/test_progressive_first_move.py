"""A progressive atlas's first commands come quickly (issue 23, "ready within 2 s";
docs/SLAM.md "Progressive atlas"): what the controller does per revision is computed once or
at once, a coarse chart is its own navigation map, and the start cells' solves start before
the decomposition's last pass. Each test checks the quick path against the slow one."""

from __future__ import annotations

import threading
import warnings
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely

import confnav
from confnav.atlas.charts import (
    PartialAtlas,
    _decompose_previewing,
    _early_starts,
    _round_by_chart,
    _solve_one,
    navigation_map,
    route_order,
)
from confnav.atlas.compose import AtlasNavigator
from confnav.atlas.decompose import decompose
from confnav.atlas.scenes import office
from confnav.atlas.wire import ProgressiveController
from confnav.conformal.solver import AccuracyWarning
from confnav.geometry import Workspace
from confnav.maps.footprint import inflate
from confnav.maps.occupancy import import_map
from confnav.navigation.safety import SafetyFilter
from confnav.scenes.scenarios import random_starts

SLAM = Path(__file__).parent / "data" / "slam"


#: tests/test_slam_atlas.py's cell of tb3_sandbox: solved to 1e-3 its estimate is about 4e-4
SANDBOX_CELL = [
    (-1.637007, 1.410445),
    (-1.687007, 1.360445),
    (-1.744730, 1.244999),
    (-1.560271, 1.244999),
    (-1.438514, 1.488514),
    (-1.296556, 1.559493),
    (-1.296556, 1.677940),
    (-1.517039, 1.650380),
]


@pytest.fixture(scope="module")
def office_dec() -> Any:
    return decompose(office().workspace)


def _points(ws: Workspace, n: int, seed: int) -> np.ndarray:
    x0, y0, x1, y1 = ws.bounds
    rng = np.random.default_rng(seed)
    return rng.uniform(x0 - 0.1, x1 + 0.1, n) + 1j * rng.uniform(y0 - 0.1, y1 + 0.1, n)


def test_depths_of_a_point_in_every_cell_equal_each_cells_depth(office_dec: Any) -> None:
    dec = office_dec
    for z in _points(dec.workspace, 60, seed=3):
        got = dec.depths(z)
        want = np.array([c.depth(np.array([z]))[0] for c in dec.cells])
        np.testing.assert_array_equal(got, want)


def test_touching_pairs_are_the_intersecting_cells(office_dec: Any) -> None:
    dec = office_dec
    a, b = dec.touching
    got = set(zip(a.tolist(), b.tolist(), strict=True))
    want = {
        (i, j)
        for i, ci in enumerate(dec.cells)
        for j, cj in enumerate(dec.cells)
        if shapely.intersects(ci.polygon, cj.polygon)
    }
    assert got == want
    assert dec.keys == tuple(c.workspace.content_hash for c in dec.cells)


def test_one_robots_initial_cell_is_the_batchs(office_dec: Any) -> None:
    """initial_cells of one point (every cell at once) against the per-cell loop of a batch,
    on a partial atlas (some charts installed)."""
    dec = office_dec
    n = len(dec.cells)
    rng = np.random.default_rng(5)
    installed = rng.random(n) < 0.6
    maps: list[Any] = [object() if k else None for k in installed]
    goal = complex(dec.centres[0])
    nav = AtlasNavigator(PartialAtlas(dec, (None,) * n, 1e-3), goal, nav_maps=maps)
    pts = _points(dec.workspace, 80, seed=7)
    batch = nav.initial_cells(np.concatenate([pts, pts]))[: pts.size]  # the loop (>1 point)
    one = np.array([int(nav.initial_cells(np.array([z]))[0]) for z in pts])
    np.testing.assert_array_equal(one, batch)
    assert (one >= 0).any() and (one < 0).any()


def test_a_coarse_chart_is_its_own_navigation_map_and_an_accurate_one_is_coarsened() -> None:
    ws = Workspace(SANDBOX_CELL, [])
    text, _, err = _solve_one(ws.to_json(), 1e-3, 1e-2, 0.01)
    assert err == ""
    coarse = confnav.ConformalMap.from_json(text)
    assert coarse.diagnostics.boundary_residual > 1e-7
    nm = navigation_map(coarse)
    assert nm is coarse and nm._fast
    # what for_navigation finds for it: no coarsening within 1e-7 of the chart
    assert confnav.ConformalMap.from_json(text).for_navigation().n_nodes == coarse.n_nodes
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        fine = confnav.solve(ws, 1e-10)
    assert fine.diagnostics.boundary_residual <= 1e-7
    a, b = navigation_map(fine), fine.for_navigation()
    assert a.n_nodes == b.n_nodes
    z = _points(ws, 400, seed=1)
    z = z[ws.clearance(z) > 0.01]
    np.testing.assert_array_equal(a.T(z), b.T(z))


@pytest.fixture(scope="module")
def depot() -> Workspace:
    return inflate(import_map(SLAM / "depot.yaml").workspace, 0.32)


def test_the_depots_start_cells_of_the_first_pass_are_cells_of_the_last(depot: Workspace) -> None:
    """decompose redoes its pass with a margin derived from the passages and says so
    (``on_pass``): the start cells of that pass, whose solves a progressive atlas starts
    then, are cells of the final decomposition (same content hash), solved with its margin."""
    starts = [complex(2.0, 1.0), complex(-5.0, 3.0), complex(10.0, -2.0)]
    starts = [z for z in starts if depot.clearance(np.array([z]))[0] > 0.2]
    assert starts
    pairs = [(z, starts[0]) for z in starts]
    passes: list[tuple[Any, float]] = []
    dec = decompose(depot, fine=starts, on_pass=lambda d, m: passes.append((d, m)))
    assert passes, "the depot's margin is derived twice"
    first, margin = passes[-1]
    assert margin == dec.margin and first.margin != dec.margin
    early = route_order(first, pairs)[: len(pairs)]
    assert set(first.keys[i] for i in early) <= set(dec.keys)


class _Pool:
    """Records submissions; the futures resolve at once (a failed solve for every job)."""

    def __init__(self) -> None:
        self.jobs: list[tuple[str, float]] = []

    def submit(self, fn: Any, job: str, tol: float, accept: float, depth: float) -> Future[Any]:
        self.jobs.append((Workspace.from_json(job).content_hash, depth))
        f: Future[Any] = Future()
        f.set_result(("", 0.0, "not solved here"))
        return f


def test_an_early_solve_counts_only_with_the_rounds_margin(office_dec: Any) -> None:
    dec = office_dec
    start = complex(dec.centres[0])
    pairs = [(start, complex(dec.centres[-1]))]
    pool, pending, depths = _Pool(), {}, {}  # type: ignore[var-annotated]
    _early_starts(pool, pairs, (1e-3, 1e-2), pending, depths)(dec, dec.margin)  # type: ignore[arg-type]
    first = route_order(dec, pairs)[0]
    assert pool.jobs == [(dec.keys[first], dec.margin)]
    # the round takes it over: the start cell is not submitted again, every other cell is
    todo = list(range(len(dec.cells)))
    args = (dec, list(dec.keys), todo, set(), (1e-3, 1e-2))
    _round_by_chart(pool, *args, pending, {}, [], lambda: None, 99, False, depths)  # type: ignore[arg-type]
    assert [k for k, _ in pool.jobs].count(dec.keys[first]) == 1
    assert len(pool.jobs) == len(dec.cells)
    # one solved with another probe depth is solved again
    pool2, pending2, depths2 = _Pool(), {}, {}  # type: ignore[var-annotated]
    _early_starts(pool2, pairs, (1e-3, 1e-2), pending2, depths2)(dec, dec.margin / 2)  # type: ignore[arg-type]
    _round_by_chart(pool2, *args, pending2, {}, [], lambda: None, 99, False, depths2)  # type: ignore[arg-type]
    assert pool2.jobs.count((dec.keys[first], dec.margin)) == 1
    assert len(pool2.jobs) == len(dec.cells) + 1


def test_the_safety_grid_lists_every_segment_a_cell_needs(depot: Workspace) -> None:
    """The grid built without a loop per cell: each cell's candidates are exactly the
    segments within its reach of the cell centre (brute force), its lower clearance bound
    the centre's exact clearance less the half diagonal."""
    flt = SafetyFilter(depot)
    g = flt.grid
    a, b = depot._segments  # type: ignore[attr-defined]
    rng = np.random.default_rng(2)
    r = g.h * np.sqrt(0.5)
    for cell in rng.choice(g.nx * g.ny, 300, replace=False):
        ix, iy = divmod(int(cell), g.ny)
        q = complex(g.x0 + (ix + 0.5) * g.h, g.y0 + (iy + 0.5) * g.h)
        d = b - a
        t = np.clip(((q - a) * np.conj(d)).real / np.abs(d) ** 2, 0, 1)
        dist = np.abs(q - (a + t * d))
        dq = dist.min()
        reach = max(min(flt.kappa * (dq + r), flt.lookahead) + r, dq + 2 * r)
        want = set(np.flatnonzero(dist <= reach * (1 - 1e-12)).tolist())
        maybe = set(np.flatnonzero(dist <= reach * (1 + 1e-12)).tolist())
        got = set(int(s) for s in g.candidates[cell] if s >= 0)
        assert want <= got <= maybe
        if g.side[cell] == 1:
            assert g.free_speed[cell] == pytest.approx(
                min(flt.alpha * min(dq - r, flt.lookahead), flt.slope * (dq - r)), abs=1e-12
            )


def test_robots_start_on_the_first_passs_cells_while_the_decomposition_is_cut_again(
    depot: Workspace,
) -> None:
    """While decompose cuts its second pass (the depot's margin is derived again), the start
    cells' charts solved for the new margin are shown on the first pass's cells with that
    margin: a robot gets a non-zero command there; the decomposition returned is the
    settled one."""
    start, goal = complex(2.0, 1.0), complex(random_starts(depot, 1, seed=1, margin=0.2)[0])
    assert depot.clearance(np.array([start, goal])).min() > 0.2
    pairs = [(start, goal)]
    pending: dict[str, Future[Any]] = {}
    shown = threading.Event()
    previews: list[tuple[Any, tuple[Any, ...]]] = []

    def early(d: Any, margin: float) -> None:
        i = route_order(d, pairs)[0]
        f: Future[Any] = Future()
        f.set_result(_solve_one(d.cells[i].workspace.to_json(), 1e-3, 1e-2, margin))
        pending[d.keys[i]] = f
        assert shown.wait(60), "no preview while the second pass waits"

    def preview(d: Any, charts: tuple[Any, ...]) -> None:
        previews.append((d, charts))
        shown.set()

    dec = _decompose_previewing(depot, set(), early, pending, preview, {"fine": [start]})
    assert dec.keys == decompose(depot, fine=[start]).keys  # the settled decomposition
    d, charts = previews[0]
    assert d.margin == dec.margin and d.keys != dec.keys  # the first pass's cells
    assert sum(c is not None for c in charts) == 1
    law = ProgressiveController(goal, speed=0.5, safety=depot)
    law.offer(PartialAtlas(d, charts, 1e-3))
    assert abs(complex(law(np.array([start])).u[0])) > 0
