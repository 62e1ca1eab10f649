"""Charts of an atlas: one conformal map per cell, solved in parallel; single map or atlas.

A cell whose solve fails (``CrowdingError``, ``ConvergenceError``, an invalid cell polygon)
is data, not an accident: its tile is split into four and the decomposition is redone; the
maps of cells that did not change are reused (keyed by the cell workspace's content hash).
"""

from __future__ import annotations

import logging
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import (
    FIRST_COMPLETED,
    Executor,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
    as_completed,
    wait,
)
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Polygon

from confnav.atlas.decompose import (
    Decomposition,
    Tile,
    bottleneck,
    decompose,
    elongation,
    outer_depth,
)
from confnav.conformal.cmap import ConformalMap, SolveReport
from confnav.conformal.solver import UNUSABLE_ERROR, AccuracyWarning, crowding_reason, solve
from confnav.errors import ConfnavError, CrowdingError, SolverError, fmt_point
from confnav.geometry import Workspace

__all__ = [
    "Atlas",
    "ChartRecord",
    "PartialAtlas",
    "atlas_reason",
    "navigation_map",
    "needs_atlas",
    "single_map_or_atlas",
    "solve_atlas",
    "solve_auto",
]

log = logging.getLogger(__name__)

Pairs = Sequence[tuple[complex, complex]]
Routes = Pairs | Callable[[], Pairs]
"""Robots' (start, goal) pairs, or a callable returning the current ones (:func:`solve_atlas`)."""

#: elongation (``area / (2 r)^2``) above which one map is not attempted (crowding of a
#: channel ~ exp(-pi L/w): at L/w = 10 about 2e-14, the end of double precision)
SINGLE_MAP_MAX_RATIO = 8.0

#: A chart is crowded (its tile is split) when a point ``margin`` inside its cell maps closer
#: than this to the unit circle: the elongation misses a narrow channel inside a wider cell
#: (measured: alcove_dock shrunk by 0.2 m, a 0.28 m channel under a table in a cell of
#: elongation 4.2; a robot 0.3 m inside mapped 8e-15 *outside* the disk and got a NaN field).
CROWDED_GAP = 1e-10

#: :func:`confnav.atlas.decompose.bottleneck` above this: one map is not attempted.  Measured:
#: 0-1.6 where one map solves (the shared scenes, a studio, a U-trap, two offices, two squares
#: 0.01 apart, the README's office map: 1.57, solved in 104 s); 4.35 on a SLAM studio shrunk by
#: 0.3 m (its single map crowded to 1.5e-12 after 7.5 min), 6.5-10.9 on a SLAM apartment shrunk
#: by 0.3 m (GMRES failed on 18,360 nodes after 131 s), 21.9 for a pocket behind a 5 cm slit.
BOTTLENECK_MAX_RATIO = 3.0

#: :func:`confnav.atlas.decompose.outer_depth` below this: one map is not attempted (the
#: first sweep would send an obstacle this close to the unit circle; 1e-6 is also where
#: :func:`confnav.conformal.solver.crowding_reason` calls a boundary crowded).  Measured at
#: 10,000 grid nodes against the single-map attempt at 1e-3 (bench/results/outer_depth.json):
#: crowded at 1.8e-10 (the outside check's clinic: rooms behind 0.9 m doors, beds 0.2 m
#: from two walls; no other test flagged it, its attempt failed after 1.5 s at load 4.0 and
#: 12.6 s at load 10), 3.4e-8 (the README's office shrunk by 0.2 m), 1.1e-18 (the clinic
#: shrunk by 0.3 m); solved at 1.0e-4 (the door scene), 3.9e-2 (the default workspace
#: shrunk by 0.2 m), 3.4e-2 and 5.6e-2 (two SLAM maps).  The README's office map reads
#: 1.6e-5 and its single map crowds in a later sweep (flagged as too elongated): this test
#: sees the first sweep only.
OUTER_DEPTH_MIN = 1e-6


@dataclass(frozen=True)
class ChartRecord:
    """How one cell's chart was obtained: solve wall time (in the worker), nodes, error
    estimate, smallest radius; ``error`` is the failure message of a failed attempt;
    ``tol_met`` is the solver's own ``diagnostics.tol_met`` (False for a chart kept because it
    meets ``accept`` -- :meth:`~confnav.conformal.cmap.SolveReport.meets` -- but not ``tol``)."""

    cell: int
    wall_time: float
    n_nodes: int
    error_estimate: float
    min_radius: float
    tile: Tile
    error: str = ""
    tol_met: bool = True
    #: content hash of the cell's workspace (``cell`` numbers the cells of the round that
    #: solved it; a chart kept from an earlier round has a different number now)
    key: str = ""


@dataclass(frozen=True)
class Atlas:
    """A decomposition with one conformal map (chart) per cell.

    ``charts[i]`` belongs to ``decomposition.cells[i]`` (solved to ``tol``); ``records`` lists
    every solve including failed attempts; ``wall_time`` is the elapsed time of the whole
    solve, ``cpu_time`` the sum of the per-chart solve times (their ratio is the speed-up).
    """

    decomposition: Decomposition
    charts: tuple[ConformalMap, ...]
    tol: float
    records: tuple[ChartRecord, ...] = field(repr=False)
    wall_time: float = 0.0
    workers: int = 1

    @property
    def workspace(self) -> Workspace:
        return self.decomposition.workspace

    @property
    def chart_records(self) -> tuple[ChartRecord, ...]:
        """The successful solve of each final cell's chart, in cell order."""
        by_key = {r.key: r for r in self.records if not r.error}
        return tuple(by_key[c.workspace.content_hash] for c in self.decomposition.cells)

    @property
    def diagnostics(self) -> SolveReport:
        """The worst chart's diagnostics: a chart that misses its ``tol`` before one that
        meets it, then the largest error estimate (the atlas is as accurate as its worst
        chart)."""
        return max(
            (c.diagnostics for c in self.charts),
            key=lambda d: (not d.tol_met, d.error_estimate),
        )

    @property
    def tol_met(self) -> bool:
        """Every chart met ``tol`` by the solver's own certificate."""
        return all(c.diagnostics.tol_met for c in self.charts)

    @property
    def cpu_time(self) -> float:
        return float(sum(r.wall_time for r in self.records))

    @property
    def speedup(self) -> float:
        return self.cpu_time / self.wall_time if self.wall_time > 0 else float("nan")


@dataclass(frozen=True)
class PartialAtlas:
    """An atlas while its charts are being solved: the decomposition of one round of
    :func:`solve_atlas` and the charts solved so far (``None``: not yet, or failed and to be
    split in the next round). What :func:`solve_atlas`'s ``on_partial`` receives; an
    :class:`confnav.atlas.compose.AtlasNavigator` drives on its installed charts
    (docs/SLAM.md "Progressive atlas")."""

    decomposition: Decomposition
    charts: tuple[ConformalMap | None, ...]
    tol: float
    #: the round of :func:`solve_atlas` (0: the first decomposition; a later round's cells
    #: are the former ones with failed tiles split)
    round: int = 0
    #: seconds since :func:`solve_atlas` started
    wall_time: float = 0.0

    @property
    def workspace(self) -> Workspace:
        return self.decomposition.workspace

    @property
    def installed(self) -> tuple[int, ...]:
        """The cells whose charts are solved."""
        return tuple(i for i, m in enumerate(self.charts) if m is not None)

    @property
    def complete(self) -> bool:
        return all(m is not None for m in self.charts)


#: The accuracy of a chart's navigation map (``ConformalMap.for_navigation``'s default).
NAV_ACCURACY = 1e-7


def navigation_map(m: Any, accuracy: float = NAV_ACCURACY) -> Any:
    """A chart's navigation map: ``m.for_navigation(accuracy)``, or ``m`` itself (flagged
    for its local expansions, as ``for_navigation`` does when it returns the map) when the
    chart's own boundary residual exceeds ``accuracy``.

    ``for_navigation`` keeps a coarsened map only if its boundary residual is within
    ``accuracy`` and T, T' stay within it of the chart: a coarse chart (a progressive atlas's
    first revision, residual ~1e-4) would spend two to four 400-point evaluations of the
    full map and its coarsenings to return itself (measured on the depot's 1e-3 charts: the
    largest part of a progressive atlas's work in the controller's process, 5.8 of 12 s of
    its first round, and none was coarsened). The map itself steers exactly as the chart
    does; it costs evaluation speed only, on charts with few nodes."""
    if not m.diagnostics.boundary_residual <= accuracy:
        m._fast = True
        return m
    return m.for_navigation(accuracy)


def _corners(poly: Polygon) -> int:
    """Vertices of a polygon, holes included."""
    return len(poly.exterior.coords) - 1 + sum(len(h.coords) - 1 for h in poly.interiors)


def route_order(
    dec: Decomposition, pairs: Sequence[tuple[complex, complex]], links: Any = None
) -> list[int]:
    """The cells the robots of ``pairs`` (start, goal) need, in the order they need them:
    every robot's start cell first, then a second cell holding each start (if any: a start
    cell whose chart fails leaves its robot another), then the second cells of their cell
    routes (:func:`confnav.atlas.compose.plan`), and so on. A start cell is the cell holding the
    start (and leading to the goal) with the fewest vertices, the quickest to solve (the
    cell of the start's own tile after :func:`decompose`'s ``fine`` split; ties: the lowest
    rank); a robot drives on it while it is the only chart installed that holds it. A pair
    whose goal or start lies in no cell adds nothing."""
    from confnav.atlas.compose import plan  # compose imports this module

    stub = PartialAtlas(dec, (None,) * len(dec.cells), 0.0)
    routes: list[list[int]] = []
    others: list[list[int]] = []  # the other cells holding each start, fewest vertices first
    for start, goal in pairs:
        try:
            p = plan(stub, complex(goal), links)
        except ConfnavError:
            continue
        pt = np.array([complex(start)])
        held = [i for i, c in enumerate(dec.cells) if c.depth(pt)[0] > 0 and np.isfinite(p.rank[i])]
        if not held:
            continue
        held.sort(key=lambda i: (_corners(dec.cells[i].polygon), p.rank[i]))
        a = held[0]
        others.append(held[1:])
        route: list[int] = []
        while a >= 0 and a not in route:
            route.append(a)
            a = int(p.next[a])
        routes.append(route)
    out: list[int] = []
    for r in routes:  # every start cell first
        if r[0] not in out:
            out.append(r[0])
    for o in others:  # then one more cell holding each start: a start cell whose chart
        if o and o[0] not in out:  # fails (crowded) leaves its robot another way to start
            out.append(o[0])
    for k in range(1, max((len(r) for r in routes), default=0)):
        for r in routes:
            if k < len(r) and r[k] not in out:
                out.append(r[k])
    return out


def _solve_one(ws_json: str, tol: float, accept: float, depth: float) -> tuple[str, float, str]:
    """Worker: (map JSON or "", wall time, error message).  Runs in a child process.

    A map is kept on the solver's own certificate: its ``tol_met``, or, when it misses
    ``tol``, the same criterion at ``accept`` (every error source within ``accept``, the
    Koebe iteration converged, no size cap hit: :meth:`SolveReport.meets`), never on the
    error estimate alone; one that maps a point ``depth`` inside the cell within
    :data:`CROWDED_GAP` of the unit circle is not (probes: the vertices of the cell shrunk
    by ``depth``, which reach into the ends of its channels)."""
    t0 = time.perf_counter()
    try:
        ws = Workspace.from_json(ws_json)
        with warnings.catch_warnings():
            # the solver's verdict is read from its diagnostics below, not from the warning
            warnings.simplefilter("ignore", AccuracyWarning)
            # a chart asked for a tolerance coarser than UNUSABLE_ERROR (a first, coarse
            # revision) is accepted up to it, as solve(max_error=...) does for one map
            m = solve(ws, tol, max_error=max(UNUSABLE_ERROR, tol, accept))
        diag = m.diagnostics
        if not (diag.tol_met or diag.meets(max(tol, accept))):
            why = [f"estimate {diag.error_estimate:.1e}"]
            if not diag.iteration_converged:
                why.append("Koebe iteration not converged")
            why += diag.caps
            return "", time.perf_counter() - t0, "tolerance not met (" + "; ".join(why) + ")"
        probe = shapely.get_coordinates(ws.polygon.buffer(-depth).boundary)
        if probe.size:
            z = probe[:, 0] + 1j * probe[:, 1]
            gap = 1 - np.abs(m.T(z, check=False))
            k = int(np.argmin(gap))
            if not gap[k] >= CROWDED_GAP:
                return (
                    "",
                    time.perf_counter() - t0,
                    (
                        f"crowded: {fmt_point(z[k])}, {depth:.3g} m inside, maps {gap[k]:.1e} "
                        "from the unit circle"
                    ),
                )
        return m.to_json(), time.perf_counter() - t0, ""
    except ConfnavError as exc:
        return "", time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"


def fmt_tile(t: Tile) -> str:
    """A tile as ``(x0, y0)-(x1, y1)``, 4 decimals."""
    return f"{fmt_point(complex(t[0], t[1]))}-{fmt_point(complex(t[2], t[3]))}"


def atlas_reason(ws: Workspace, *, loops: bool = False) -> str:
    """Why one map of ``ws`` would crowd, a priori ("" if nothing says so): the free space
    too elongated (:func:`elongation`), a region reached only through a long narrow
    passage (:func:`bottleneck`; found in 0.1-0.8 s, where a single map of such a floor plan
    took 7.5 minutes to fail), or an obstacle the first sweep would send next to the unit
    circle (:func:`confnav.atlas.decompose.outer_depth`, 0.02-0.09 s: rooms behind doors
    with furniture near their walls, whose single map failed after 12.6 s under load).

    ``loops``: measure the elongation with the obstacles filled in.  A channel that loops
    around an obstacle is an annulus, conformally a ring of modulus ~ w/L, not a crowding
    channel (a 4 m room around a 1 m box shrunk by 0.4 m: elongation 10.4, its single map
    fine); filled, only the arms that end somewhere count.  Off by default: a warehouse's
    aisles between shelf rows are loops too, and its single map is not attempted."""
    poly = Polygon(ws.polygon.exterior) if loops else ws.polygon
    q = elongation(poly)
    if q > SINGLE_MAP_MAX_RATIO:
        return f"too elongated for one map (area / (2 inradius)^2 = {q:.3g})"
    q, where = bottleneck(ws.polygon)
    if q > BOTTLENECK_MAX_RATIO:
        return (
            f"a region is reached only through a narrow passage at {fmt_point(where)} "
            f"(length / width >= {q:.3g}): one map crowds it"
        )
    g, where = outer_depth(ws)
    if g < OUTER_DEPTH_MIN:
        return (
            f"the map of the outer boundary would send the obstacle at {fmt_point(where)} "
            f"within about {g:.1g} of the unit circle (Green's function estimate): one map "
            "crowds it"
        )
    return ""


def single_map_or_atlas(ws: Workspace, m: ConformalMap | None = None) -> str:
    """Why ``ws`` should be solved as an atlas ("" for a single map): the a-priori reasons
    (:func:`atlas_reason`) and, given a solved map ``m`` of it, the crowding measured by the
    solve (:func:`confnav.conformal.solver.crowding_reason`: its smallest circle and each
    boundary's crowding in ``m.diagnostics``)."""
    why = [atlas_reason(ws)]
    if m is not None:
        why.append(crowding_reason(m.diagnostics))
    return "; ".join(w for w in why if w)


def needs_atlas(ws: Workspace) -> bool:
    """A-priori test: would one map of the free space crowd (:func:`atlas_reason`)?"""
    return bool(atlas_reason(ws))


def _collect(
    dec: Decomposition,
    keys: list[str],
    batch: list[int],
    results: list[tuple[str, float, str]],
    done: dict[str, ConformalMap],
    records: list[ChartRecord],
) -> list[Tile]:
    """Record a batch of cell solves: the maps into ``done`` (by cell key), one
    :class:`ChartRecord` each into ``records``; returns the tiles of the failed cells."""
    failed: list[Tile] = []
    for i, (text, wall, err) in zip(batch, results, strict=True):
        cell = dec.cells[i]
        if err:
            records.append(ChartRecord(i, wall, 0, np.nan, np.nan, cell.tile, err, key=keys[i]))
            log.info("cell %d (tile %s) failed: %s", i, cell.tile, err)
            failed.append(cell.tile)
            continue
        m = ConformalMap.from_json(text)
        done[keys[i]] = m
        radii = np.asarray(m.radii)
        records.append(
            ChartRecord(
                i,
                wall,
                m.n_nodes,
                float(m.diagnostics.error_estimate),
                float(radii.min()) if radii.size else 1.0,
                cell.tile,
                tol_met=bool(m.diagnostics.tol_met),
                key=keys[i],
            )
        )
    return failed


def _round_by_chart(
    pool: ProcessPoolExecutor,
    dec: Decomposition,
    keys: list[str],
    todo: list[int],
    urgent: set[int],
    tols: tuple[float, float],
    pending: dict[str, Future[tuple[str, float, str]]],
    done: dict[str, ConformalMap],
    records: list[ChartRecord],
    partial: Callable[[], None],
    every: int,
    eager: bool,
    depths: dict[str, float] | None = None,
) -> tuple[list[Tile], bool]:
    """One round of :func:`solve_atlas` chart by chart: every cell of ``todo`` submitted in
    order (the routes' cells first; a cell whose solve is still pending from an earlier
    round is not submitted again), a partial revision after each route cell and every
    ``every`` others. With ``eager`` the round ends at the first failed route cell (its tile
    is split at once; the other solves stay in ``pending`` for the next round). Returns the
    failed tiles and whether the round ended early."""
    tol, accept = tols
    depths = {} if depths is None else depths
    for i in todo:
        # a solve started before this decomposition (:func:`_early_starts`) counts if it
        # probed this decomposition's margin
        if keys[i] not in pending or depths.get(keys[i], dec.margin) != dec.margin:
            job = dec.cells[i].workspace.to_json()
            pending[keys[i]] = pool.submit(_solve_one, job, tol, accept, dec.margin)
            depths[keys[i]] = dec.margin
    wait = {pending[keys[i]]: i for i in todo}
    failed: list[Tile] = []
    since = 0
    for fut in as_completed(wait):
        i = wait[fut]
        pending.pop(keys[i], None)
        bad = _collect(dec, keys, [i], [fut.result()], done, records)
        failed += bad
        since += 1
        if i in urgent or since >= every:
            partial()
            since = 0
        if bad and eager and i in urgent:
            return failed, True
    if since:
        partial()
    return failed, False


def solve_atlas(
    ws: Workspace,
    tol: float = 1e-8,
    *,
    workers: int = 2,
    accept: float = 1e-6,
    max_rounds: int = 8,
    progress: Callable[[str], None] | None = None,
    executor: Executor | None = None,
    priority: Routes = (),
    on_partial: Callable[[PartialAtlas], None] | None = None,
    split_early: bool = False,
    batch: int | None = None,
    **decompose_kw: Any,
) -> Atlas:
    """Decompose ``ws`` (:func:`confnav.atlas.decompose`) and solve every cell's map.

    Cells are solved by a process pool of ``workers`` (1: in this process), or by
    ``executor`` (its ``map`` gets :func:`_solve_one` and the job lists; not shut down here:
    the transform service's executor spreads cells over its pool and its peers).  A chart that
    misses ``tol`` is kept if its error estimate is within ``accept`` (the accuracy the
    controller evaluates to, ``ConformalMap.for_navigation``; recorded with ``tol_met``
    False: splitting does not help a chart whose error comes from one re-entrant corner).
    A failed cell's tile is split and the decomposition redone (at most ``max_rounds``
    times); unchanged cells keep their maps.

    Progressive (docs/SLAM.md "Progressive atlas"): with ``priority`` (robots' (start,
    goal) pairs) the cells their routes need are solved first (:func:`route_order`), and
    ``on_partial`` receives a :class:`PartialAtlas` after each batch (``workers`` route
    cells, or ``batch`` others, default ``4 workers``; chart by chart on a process pool),
    at the start of a round that reuses charts, and once complete: a controller drives on
    the charts solved so far. The result is the same atlas. ``split_early``: a failed route
    cell ends its round at once (off: it delayed the first robot on tb3_world).

    ``priority`` may be a callable returning the pairs (routes that arrive while the atlas
    solves: :func:`_routes_of`).

    Raises
    ------
    SolverError
        if some cell still fails after ``max_rounds`` rounds (the message names it).
    """
    t0 = time.perf_counter()
    routes = _routes_of(priority)
    split: set[Tile] = set(decompose_kw.pop("split", ()))
    done: dict[str, ConformalMap] = {}
    records: list[ChartRecord] = []
    own = executor is None and workers > 1
    pool = ProcessPoolExecutor(max_workers=workers) if own else executor
    pending: dict[str, Future[tuple[str, float, str]]] = {}  # cell key -> its solve
    depths: dict[str, float] = {}  # cell key -> the probe depth its pending solve was given
    eager_left = max_rounds  # early splits of a route's failed cell (not counted as rounds)
    try:
        _round, rounds = -1, -1
        while rounds < max_rounds:
            _round, rounds = _round + 1, rounds + 1
            pairs = routes()
            dec = _decompose_round(
                ws, split, pool, pairs, on_partial, (tol, accept), pending, depths,
                decompose_kw, _round, t0,
            )  # fmt: skip
            keys = list(dec.keys)
            pairs = routes()  # routes that came while the decomposition was cut
            todo, first = _round_order(dec, keys, done, pairs)
            if progress is not None:
                progress(f"atlas: {len(dec.cells)} cells, solving {len(todo)}")

            partial = _partial_of(on_partial, dec, keys, done, tol, _round, t0)
            if on_partial is not None and len(todo) < len(keys):
                partial()  # the charts this round reuses
            every = max(1, batch if batch is not None else 4 * max(1, workers))
            batches: Iterable[list[int]] = [todo]
            if on_partial is not None:
                batches = _Batches(dec, todo, len(first), pairs, routes, workers, every)
            failed: list[Tile] = []
            if on_partial is not None and isinstance(pool, ProcessPoolExecutor):
                failed, ended = _round_by_chart(
                    pool, dec, keys, todo, set(first), (tol, accept), pending, done, records,
                    partial, every, split_early and eager_left > 0, depths,
                )  # fmt: skip
                if ended:  # a route's cell failed: split it now, the other solves pending
                    eager_left -= 1
                    rounds -= 1
                batches = []
            failed += _solve_batches(
                pool, dec, keys, batches, (tol, accept), pending, depths, done, records, partial
            )
            if not failed:
                charts = tuple(done[k] for k in keys)
                return Atlas(dec, charts, tol, tuple(records), time.perf_counter() - t0, workers)
            _check_splittable(failed, split, records, dec.margin)
            split |= set(failed)
        raise _still_failing(records, max_rounds)
    finally:
        for f in pending.values():  # solves of cells a later round no longer has
            f.cancel()
        if own and pool is not None:
            pool.shutdown()


def _partial_of(
    on_partial: Callable[[PartialAtlas], None] | None,
    dec: Decomposition,
    keys: list[str],
    done: dict[str, ConformalMap],
    tol: float,
    rnd: int,
    t0: float,
) -> Callable[[], None]:
    """What :func:`solve_atlas` calls after a batch of round ``rnd``: ``on_partial`` with the
    charts solved so far (``done``, read at the call), or nothing."""

    def partial() -> None:
        if on_partial is not None:
            charts = tuple(done.get(k) for k in keys)
            on_partial(PartialAtlas(dec, charts, tol, rnd, time.perf_counter() - t0))

    return partial


def _still_failing(records: list[ChartRecord], max_rounds: int) -> SolverError:
    """The error of an atlas whose last failed cell still fails after ``max_rounds`` splits."""
    bad = [r for r in records if r.error][-1]
    return SolverError(
        f"atlas: cell of tile {fmt_tile(bad.tile)} still fails after {max_rounds} splits: "
        f"{bad.error}"
    )


def _decompose_round(
    ws: Workspace,
    split: set[Tile],
    pool: Executor | None,
    priority: Sequence[tuple[complex, complex]],
    on_partial: Callable[[PartialAtlas], None] | None,
    tols: tuple[float, float],
    pending: dict[str, Future[tuple[str, float, str]]],
    depths: dict[str, float],
    decompose_kw: dict[str, Any],
    rnd: int,
    t0: float,
) -> Decomposition:
    """One round's decomposition of :func:`solve_atlas`; progressive with robots on a
    process pool, the start cells' solves start at each pass (:func:`_early_starts`) and
    ``on_partial`` previews the first pass's cells (:func:`_decompose_previewing`)."""
    early = (
        _early_starts(pool, priority, tols, pending, depths)  # type: ignore[arg-type]
        if priority and on_partial is not None and _submits(pool)
        else None
    )
    if early is None or on_partial is None:
        return decompose(ws, split=split, **decompose_kw)
    show = on_partial

    def preview(d: Decomposition, c: tuple[ConformalMap | None, ...]) -> None:
        show(PartialAtlas(d, c, tols[0], rnd, time.perf_counter() - t0))

    return _decompose_previewing(ws, split, early, pending, preview, decompose_kw)


def _solve_batches(
    pool: Executor | None,
    dec: Decomposition,
    keys: list[str],
    batches: Iterable[list[int]],
    tols: tuple[float, float],
    pending: dict[str, Future[tuple[str, float, str]]],
    depths: dict[str, float],
    done: dict[str, ConformalMap],
    records: list[ChartRecord],
    partial: Callable[[], None],
) -> list[Tile]:
    """:func:`solve_atlas`'s batches of one round (not chart by chart): each batch solved and
    recorded, then ``partial``; the robots' cells on an executor that solves single charts
    one revision per chart (:func:`_solve_streaming`). Returns the failed tiles."""
    failed: list[Tile] = []
    for chunk in batches:
        if isinstance(batches, _Batches) and batches.route and pool and _submits(pool):
            for i, got1 in _solve_streaming(pool, dec, keys, chunk, tols, pending, depths):
                failed += _collect(dec, keys, [i], [got1], done, records)
                partial()
            continue
        got = _solve_chunk(pool, dec, chunk, *tols)
        failed += _collect(dec, keys, chunk, got, done, records)
        partial()
    return failed


def _submits(pool: Executor | None) -> bool:
    """Whether ``pool`` solves single charts (``submit``) as well as lists: a process pool,
    or an executor that says so (``submits_charts``: the transform service's, whose
    ``submit`` runs one job through its chart share)."""
    return isinstance(pool, ProcessPoolExecutor) or bool(getattr(pool, "submits_charts", False))


def _solve_streaming(
    pool: Executor,
    dec: Decomposition,
    keys: list[str],
    chunk: list[int],
    tols: tuple[float, float],
    pending: dict[str, Future[tuple[str, float, str]]],
    depths: dict[str, float],
) -> Iterator[tuple[int, tuple[str, float, str]]]:
    """The cells ``chunk`` solved at once on ``pool``, yielded as each is done: a solve
    started early for a cell (``pending``, probed at this decomposition's margin) is taken
    over, the others submitted.  For the robots' cells of a progressive atlas on an
    executor that is not a process pool: before, the transform service published its first
    revision once both workers' route cells were done, and started them only after the
    decomposition's last pass (measured on the SLAM warehouse, first use: the first revision
    1.46 s after the goals against 0.75 s in process with early starts and a revision per
    chart)."""
    tol, accept = tols
    wait: dict[Future[tuple[str, float, str]], int] = {}
    for i in chunk:
        fut = pending.pop(keys[i], None)
        if fut is None or depths.get(keys[i], dec.margin) != dec.margin or fut.cancelled():
            job = dec.cells[i].workspace.to_json()
            fut = pool.submit(_solve_one, job, tol, accept, dec.margin)
        depths.pop(keys[i], None)
        wait[fut] = i
    for fut in as_completed(wait):
        yield wait[fut], fut.result()


def _early_starts(
    pool: ProcessPoolExecutor,
    priority: Sequence[tuple[complex, complex]],
    tols: tuple[float, float],
    pending: dict[str, Future[tuple[str, float, str]]],
    depths: dict[str, float],
) -> Callable[[Decomposition, float], None]:
    """:func:`decompose`'s ``on_pass`` for a progressive atlas: when a pass is redone with a
    new margin, start solving the robots' start cells of that pass (:func:`route_order`)
    with the new margin as the probe depth, while the next pass is cut. A cell the next pass
    leaves unchanged (the same content hash, as a cell whose tile band and pieces do not
    depend on the margin) takes its solve over; another one is wasted worker time."""
    tol, accept = tols

    def start(dec: Decomposition, margin: float) -> None:
        for i in route_order(dec, priority)[: len(priority)]:
            key = dec.keys[i]
            if key not in pending:
                job = dec.cells[i].workspace.to_json()
                pending[key] = pool.submit(_solve_one, job, tol, accept, margin)
                depths[key] = margin

    return start


def _with_margin(dec: Decomposition, margin: float) -> Decomposition:
    """A decomposition pass's cells with the margin of the next pass (the cached cell graph
    kept: it does not depend on the margin). Every invariant of the cell graph holds: the
    next margin is :data:`confnav.atlas.decompose.AUTO_MARGIN_FRACTION` times the depth of
    this pass's passage, so the overlaps at least that deep connect every cell."""
    out = replace(dec, margin=margin)
    for name in ("links", "passage", "keys", "centres", "touching"):
        if name in dec.__dict__:
            out.__dict__[name] = dec.__dict__[name]
    return out


def _decompose_previewing(
    ws: Workspace,
    split: set[Tile],
    early: Callable[[Decomposition, float], None],
    pending: dict[str, Future[tuple[str, float, str]]],
    preview: Callable[[Decomposition, tuple[ConformalMap | None, ...]], None],
    decompose_kw: dict[str, Any],
) -> Decomposition:
    """:func:`decompose` with ``on_pass=early`` in a thread; meanwhile this thread shows the
    start cells' charts as they come (``preview``, a partial revision) on the first pass's
    cells with the next pass's margin (:func:`_with_margin`), the margin they were solved
    for: the robots move while the decomposition is cut again. Returns the settled
    decomposition (the same as :func:`decompose`'s), whose round collects those solves."""
    got: dict[str, Decomposition] = {}
    passed = threading.Event()

    def on_pass(d: Decomposition, margin: float) -> None:
        got["dec"] = _with_margin(d, margin)
        passed.set()
        early(d, margin)

    maps: dict[str, ConformalMap | None] = {}
    with ThreadPoolExecutor(1) as thread:
        fut = thread.submit(
            decompose, ws, split=split, on_pass=on_pass, **decompose_kw
        )  # fmt: skip
        while not fut.done():
            if not passed.wait(0.02):
                continue
            d = got["dec"]
            jobs = [pending[k] for k in d.keys if k in pending and k not in maps]
            if not jobs:
                wait([fut], timeout=0.05)
                continue
            waiting: list[Future[Any]] = [fut, *jobs]
            wait(waiting, return_when=FIRST_COMPLETED)
            new = False
            for k in d.keys:
                f = pending.get(k)
                if k in maps or f is None or not f.done() or f.cancelled():
                    continue
                text, _, err = f.result()
                maps[k] = None if err else ConformalMap.from_json(text)
                new = new or maps[k] is not None
            if new and not fut.done():
                preview(d, tuple(maps.get(k) for k in d.keys))
        return fut.result()


def _round_order(
    dec: Decomposition,
    keys: list[str],
    done: dict[str, ConformalMap],
    priority: Sequence[tuple[complex, complex]],
) -> tuple[list[int], list[int]]:
    """The cells a round solves (those without a map yet) in the order it solves them, and
    the routes' cells among them (:func:`route_order`), which come first; the others
    largest first, so that the pool's tail is short."""
    todo = [i for i, k in enumerate(keys) if k not in done]
    todo.sort(key=lambda i: -dec.cells[i].polygon.length)
    first = [i for i in route_order(dec, priority) if i in set(todo)] if priority else []
    return first + [i for i in todo if i not in set(first)], first


def _check_splittable(
    failed: list[Tile], split: set[Tile], records: list[ChartRecord], margin: float
) -> None:
    """Raise :class:`SolverError` if every failed tile was split before and still fails (it
    is at the smallest split)."""
    if set(failed) <= split:
        bad = [r for r in records if r.error][-1]
        side = bad.tile[2] - bad.tile[0]
        raise SolverError(
            f"atlas: cell of tile {fmt_tile(bad.tile)} fails and its tile ({side:.3g} m) "
            f"is at the smallest split (margin {margin:.3g} m): {bad.error}"
        )


def _batches(todo: list[int], n_first: int, workers: int, every: int) -> list[list[int]]:
    """The cells of ``todo`` in the batches a progressive round solves them in: its first
    ``n_first`` (the routes' cells) ``workers`` at a time, then the others ``every`` at a
    time."""
    size = max(1, workers)
    out = [todo[k : k + size] for k in range(0, n_first, size)]
    rest = todo[n_first:]
    return out + [rest[k : k + every] for k in range(0, len(rest), every)]


def _routes_of(priority: Routes) -> Callable[[], tuple[tuple[complex, complex], ...]]:
    """``priority`` as a callable returning the current pairs as a tuple (a fixed sequence
    returns itself; a callable that raises counts as no routes: hints only steer the order).

    A callable ``priority`` of :func:`solve_atlas` (robots' routes that arrive while the atlas
    solves: the transform service's route hints, docs/SLAM.md "Progressive atlas") is read at
    each round's start and, when cells are solved batch by batch (an ``executor`` such as the
    transform service's, with ``on_partial``), before every batch: the cells of routes that
    came meanwhile go into the next batch. On a process pool chart by chart, every cell of a
    round is submitted at its start, so new routes count from the next round."""
    if not callable(priority):
        fixed = tuple((complex(a), complex(b)) for a, b in priority)
        return lambda: fixed

    def read() -> tuple[tuple[complex, complex], ...]:
        try:
            return tuple((complex(a), complex(b)) for a, b in priority())
        except Exception:  # the caller's hints must never stop the solve
            log.warning("atlas: route hints unreadable: ignored", exc_info=True)
            return ()

    return read


class _Batches:
    """The batches of one round (:func:`_batches`), re-ordered when the routes change: before
    each batch the current routes are read, and the cells the new routes need
    (:func:`route_order`) among those still to solve go first, ``workers`` at a time."""

    def __init__(
        self,
        dec: Decomposition,
        todo: list[int],
        n_first: int,
        pairs: Pairs,
        routes: Callable[[], tuple[tuple[complex, complex], ...]],
        workers: int,
        every: int,
    ) -> None:
        self.dec, self.left, self.n_first = dec, list(todo), n_first
        self.pairs, self.routes = tuple(pairs), routes
        self.size, self.every = max(1, workers), max(1, every)
        self.route = False  # the last chunk: robots' route cells

    def __iter__(self) -> Iterator[list[int]]:
        while self.left:
            now = self.routes()
            if now != self.pairs:
                self.pairs = now
                left = set(self.left)
                first = [i for i in route_order(self.dec, now) if i in left] if now else []
                if first:
                    log.info("atlas: %d route cells moved to the front", len(first))
                    self.left = first + [i for i in self.left if i not in set(first)]
                    self.n_first = len(first)
            self.route = self.n_first > 0
            take = min(self.size, self.n_first) if self.route else self.every
            chunk, self.left = self.left[:take], self.left[take:]
            self.n_first = max(0, self.n_first - len(chunk))
            yield chunk


def _solve_chunk(
    pool: Executor | None, dec: Decomposition, chunk: list[int], tol: float, accept: float
) -> list[tuple[str, float, str]]:
    """Solve the cells ``chunk`` of ``dec`` on ``pool`` (None: in this process)."""
    jobs = [dec.cells[i].workspace.to_json() for i in chunk]
    n = len(jobs)
    if pool is None:
        return [_solve_one(j, tol, accept, dec.margin) for j in jobs]
    return list(pool.map(_solve_one, jobs, [tol] * n, [accept] * n, [dec.margin] * n))


def solve_auto(
    ws: Workspace, tol: float = 1e-8, *, workers: int = 2, **decompose_kw: Any
) -> ConformalMap | Atlas:
    """One map where one map is well conditioned, an atlas otherwise.

    Tries a single :func:`confnav.solve` unless :func:`needs_atlas` says the free space is too
    elongated; a ``CrowdingError`` (or an unusable accuracy) of that solve falls back to
    :func:`solve_atlas`.
    """
    if not needs_atlas(ws):
        try:
            m = solve(ws, tol)
            crowded = crowding_reason(m.diagnostics)
            if not crowded:
                return m
            log.info("the single map crowds (%s); solving an atlas", crowded)
        except (CrowdingError, SolverError) as exc:
            log.info("single map failed (%s); solving an atlas", exc)
    return solve_atlas(ws, tol, workers=workers, **decompose_kw)
