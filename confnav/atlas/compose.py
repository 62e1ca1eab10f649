"""Sequential composition of navigation functions over an atlas (Burridge, Rizzi, Koditschek).

For a goal, every cell gets a rank (its cost to the goal over the cell graph) and a local
goal: the goal itself in the goal cell, otherwise a point deep inside the overlap with the
next cell on its shortest cell path.  A robot runs the Theorem 2 law of its active cell's
chart (:class:`confnav.Controller`) and switches to a cell of strictly lower rank as soon as
it lies inside that cell deeper than ``hysteresis`` (distance to its cut edges).  Why this
keeps collision avoidance and almost-global convergence: docs/ATLAS.md.

References
----------
.. [1] R. R. Burridge, A. A. Rizzi, D. E. Koditschek, "Sequential composition of dynamically
   dexterous robot behaviors", Int. J. Robotics Research 18(6) (1999) 534-555.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from confnav.atlas.charts import Atlas, PartialAtlas, navigation_map
from confnav.atlas.decompose import Overlap
from confnav.errors import NavigationError, fmt_point
from confnav.navigation.control import Controller
from confnav.navigation.sim import ARRIVED, COLLIDED, ERROR, STALLED, TIMEOUT, Outcomes, simulate
from confnav.types import CArray

__all__ = ["AtlasNavigator", "AtlasRun", "CellPlan", "Overlap", "overlaps", "plan"]

#: The reason of a run that ended otherwise than cut off (indexed by status code).
_REASONS = (
    "arrived",
    "hit an obstacle",
    "no progress over 20 supervisor windows (a saddle)",
    "time limit",
    "velocity undefined (NaN) or step size underflow",
)


def overlaps(atlas: Atlas | PartialAtlas) -> list[Overlap]:
    """Every pair of cells whose intersection holds a disk of radius ``margin``.

    Thinner overlaps are no edges of the cell graph (a local goal needs that depth); the
    decomposition made sure the others connect every cell (:attr:`Decomposition.passage`).
    """
    margin = atlas.decomposition.margin
    return [o for o in atlas.decomposition.links if o.depth >= margin]


@dataclass(frozen=True)
class CellPlan:
    """The composition for one goal: per cell its rank (cost to the goal; ``inf`` if the goal
    cannot be reached from it), next cell (-1 in a goal cell) and local goal."""

    goal: complex
    rank: NDArray[np.float64]
    next: NDArray[np.int64]
    local_goal: CArray
    goal_cells: tuple[int, ...]


def plan(
    atlas: Atlas | PartialAtlas, goal: complex, links: list[Overlap] | None = None
) -> CellPlan:
    """Shortest cell paths to ``goal`` (Dijkstra on the cell graph).

    Edge weight between cells i and j: ``|c_i - p_ij| + |p_ij - c_j|`` with ``c`` the cells'
    deepest points and ``p_ij`` their overlap point (a path length through the overlap).
    A goal cell (the goal a margin from its cut edges) has rank ``|c - goal|``; every other
    cell's next cell has a strictly lower rank (weights > 0): the order is acyclic.
    """
    cells = atlas.decomposition.cells
    n = len(cells)
    links = overlaps(atlas) if links is None else links
    goal = complex(goal)
    centre = atlas.decomposition.centres
    # goal cells: the goal at least a margin from their cut edges (some tile's core holds
    # it, that deep); a cell that merely touches it would put its chart's goal on its boundary
    depth = np.array([c.depth(np.array([goal]))[0] for c in cells])
    margin = atlas.decomposition.margin
    inside = [int(i) for i in np.flatnonzero(depth >= margin)]
    inside = inside or [int(i) for i in np.flatnonzero(depth > 0)]
    if not inside:
        raise NavigationError(f"goal {fmt_point(goal)} lies in no cell of the atlas")
    # node n is the goal; edges cell <-> cell through the overlap point
    rows, cols, w = [], [], []
    via: dict[tuple[int, int], complex] = {}
    for o in links:
        cost = abs(centre[o.a] - o.point) + abs(o.point - centre[o.b])
        rows += [o.a, o.b]
        cols += [o.b, o.a]
        w += [max(cost, 1e-12)] * 2
        via[(o.a, o.b)] = via[(o.b, o.a)] = o.point
    for i in inside:
        rows += [i, n]
        cols += [n, i]
        w += [max(abs(centre[i] - goal), 1e-12)] * 2
    graph = csr_matrix((w, (rows, cols)), shape=(n + 1, n + 1))
    dist, pred = dijkstra(graph, directed=False, indices=n, return_predecessors=True)
    rank = np.asarray(dist[:n], dtype=np.float64)
    nxt = np.asarray(pred[:n], dtype=np.int64)  # predecessor on the path from the goal
    nxt[nxt == n] = -1
    nxt[~np.isfinite(rank)] = -1
    local = np.array(
        [goal if nxt[i] < 0 else via[(i, int(nxt[i]))] for i in range(n)], dtype=np.complex128
    )
    goal_cells = tuple(i for i in inside if nxt[i] < 0)
    return CellPlan(goal, rank, nxt, local, goal_cells)


@dataclass
class _Robots:
    """The robots of :meth:`AtlasNavigator.run` between windows: positions, active cells,
    outcome codes (-1: running) and what is accumulated per robot."""

    z: CArray
    active: NDArray[np.int64]
    status: NDArray[np.int8]
    length: NDArray[np.float64]
    t: NDArray[np.float64]
    minclr: NDArray[np.float64]
    switches: NDArray[np.int64]
    history: list[list[int]]
    still: NDArray[np.int64]  # windows in a row without moving
    pieces: list[list[CArray]]

    @classmethod
    def at(cls, z: CArray, active: NDArray[np.int64], clearance: NDArray[np.float64]) -> _Robots:
        n = z.size
        status = np.full(n, -1, dtype=np.int8)
        status[active < 0] = ERROR
        return cls(
            z=z,
            active=active,
            status=status,
            length=np.zeros(n),
            t=np.zeros(n),
            minclr=clearance,
            switches=np.zeros(n, dtype=np.int64),
            history=[[int(a)] for a in active],
            still=np.zeros(n, dtype=np.int64),
            pieces=[[z[k : k + 1].copy()] for k in range(n)],
        )


@dataclass(frozen=True)
class AtlasRun(Outcomes):
    """Result of :meth:`AtlasNavigator.run` (per start arrays; status names as in
    :data:`confnav.navigation.sim.STATUS_NAMES`).  ``switches`` counts chart switches per robot,
    ``cells`` lists each robot's sequence of active cells and ``reasons`` says in one line per
    robot why its run ended (a start in a cell cut off from the goal's: :meth:`AtlasNavigator.
    cut_off`)."""

    starts: CArray
    success: NDArray[np.bool_]
    collided: NDArray[np.bool_]
    status: NDArray[np.int8]
    path_length: NDArray[np.float64]
    time: NDArray[np.float64]
    min_clearance: NDArray[np.float64]
    final: CArray
    switches: NDArray[np.int64]
    cells: tuple[tuple[int, ...], ...]
    wall_time: float
    reasons: tuple[str, ...] = ()
    #: each robot's accepted points when ``record_paths`` was set (windows joined)
    paths: tuple[CArray, ...] | None = None


class AtlasNavigator:
    """Hybrid feedback: the Theorem 2 law of the active chart, switched down the cell order.

    Parameters
    ----------
    atlas : a solved :class:`Atlas`, or a :class:`PartialAtlas` whose missing charts
        (``None``) are installed later (:meth:`install`, docs/SLAM.md "Progressive atlas").
        The plan is made on the whole cell graph (it needs the decomposition only); a robot
        drives on installed charts only, holds (zero command) where its cell's chart or the
        next cell's is missing, and moves on when it is installed.
    goal : the goal (in the free space).
    hysteresis : depth inside a lower-ranked cell (distance to its cut edges) at which a
        robot switches to it; default ``margin / 2``.  Must be below ``margin`` (local goals
        lie at least ``margin`` deep).
    speed : commanded speed (workspace units per time unit): the unit direction of the
        Theorem 2 field times ``speed``, slowing linearly within ``floor_radius`` of a goal
        (the controller's normalized speed law, ``v = min(speed, speed |x - x_d| /
        floor_radius)``; a positive rescaling keeps the integral curves).
    nav_maps, links : the charts' ``for_navigation()`` maps and :func:`overlaps`, when the
        caller already has them (one per atlas, shared by every goal); computed otherwise.
    controller_kw : further :class:`confnav.Controller` keywords (``navfn``, ``goal_tol``).
        ``safety`` defaults to the *whole* workspace (``atlas.workspace``): every chart's
        commands pass the safety layer of :mod:`confnav.navigation.safety` against the
        workspace in use, not against the chart (whose cut edges are not walls).
    """

    def __init__(
        self,
        atlas: Atlas | PartialAtlas,
        goal: complex,
        *,
        hysteresis: float | None = None,
        speed: float = 1.0,
        floor_radius: float | None = None,
        nav_maps: Sequence[Any] | None = None,
        links: list[Overlap] | None = None,
        **controller_kw: Any,
    ) -> None:
        self.atlas = atlas
        self.cells = atlas.decomposition.cells
        margin = atlas.decomposition.margin
        self.hysteresis = float(hysteresis) if hysteresis is not None else margin / 2
        if not 0 < self.hysteresis < margin:
            raise NavigationError(f"hysteresis must be in (0, margin={margin:g})")
        self.plan = plan(atlas, goal, links)
        self.goal = self.plan.goal
        self.speed = float(speed)
        self.floor_radius = float(floor_radius) if floor_radius is not None else margin
        self.controller_kw = controller_kw
        self._controllers: dict[int, Controller] = {}
        self._nav_maps: list[Any] = (
            list(nav_maps)
            if nav_maps is not None
            else [None if m is None else navigation_map(m) for m in atlas.charts]
        )
        a, b = atlas.decomposition.touching
        rank = self.plan.rank
        # the cells a robot in cell i may switch to: strictly lower rank, intersecting i
        self.lower: list[list[int]] = [[] for _ in self.cells]
        for i, j in zip(a.tolist(), b.tolist(), strict=True):
            if rank[j] < rank[i]:
                self.lower[i].append(j)
        for lst in self.lower:
            lst.sort(key=lambda j: rank[j])

    def installed(self, i: int) -> bool:
        """Whether cell ``i`` has its chart (always, on a complete atlas)."""
        return self._nav_maps[i] is not None

    def install(self, i: int, nav_map: Any) -> None:
        """Install cell ``i``'s chart (its ``for_navigation`` map) into a partial atlas; the
        plan, the switching order and the laws already built stay as they are."""
        if not 0 <= i < len(self._nav_maps):
            raise NavigationError(f"no cell {i} in this atlas ({len(self._nav_maps)} cells)")
        if nav_map is None:
            raise NavigationError(f"cell {i}: no chart to install")
        self._nav_maps[i] = nav_map

    def extended(self, atlas: Atlas | PartialAtlas, nav_maps: Sequence[Any]) -> AtlasNavigator:
        """This navigator on ``atlas``, a revision with the same cells whose charts are
        ``nav_maps`` (every chart installed here among them, as the same objects): the
        plan, the switching order and the chart laws built so far are shared (they depend
        on the cells, the goal and each chart only), the charts are ``atlas``'s. What a
        navigator built on ``atlas`` computes, without recomputing the plan or the laws."""
        if len(nav_maps) != len(self._nav_maps) or any(
            a is not None and a is not b for a, b in zip(self._nav_maps, nav_maps, strict=True)
        ):
            raise NavigationError("not a revision that extends this navigator's charts")
        new = copy.copy(self)
        new.atlas, new.cells = atlas, atlas.decomposition.cells
        new._nav_maps = list(nav_maps)
        new._controllers = dict(self._controllers)
        return new

    @property
    def nav_maps(self) -> tuple[Any, ...]:
        """The charts' navigation maps the law drives on (None: not installed)."""
        return tuple(self._nav_maps)

    def missing(self) -> list[int]:
        """The cells whose charts are not installed (empty on a complete atlas)."""
        return [i for i, m in enumerate(self._nav_maps) if m is None]

    def controller(self, i: int) -> Controller:
        """The Theorem 2 law of cell ``i``'s chart towards its local goal (built on demand)."""
        if self._nav_maps[i] is None:
            raise NavigationError(f"cell {i}: its chart is not installed yet")
        if i not in self._controllers:
            kw = dict(self.controller_kw)
            kw.setdefault("safety", self.atlas.workspace)  # the walls, not the chart's cuts
            self._controllers[i] = Controller(
                self._nav_maps[i],
                complex(self.plan.local_goal[i]),
                v_max=self.speed,
                gain=self.speed / self.floor_radius,
                **kw,
            )
        return self._controllers[i]

    def cut_off(self, z: complex) -> str:
        """Why a robot at ``z`` in the atlas cannot be driven to the goal ("" if it can, or
        if ``z`` lies in no cell).

        A point whose cells all have an infinite rank lies in a part of the atlas that no
        overlap at least ``margin`` deep links to the goal's cells (an atlas decomposed with
        a margin too large for a passage, e.g. rebuilt from an older index:
        :func:`confnav.atlas.decompose` refuses to make one); the message names the deepest
        overlap that leads out of that part.
        """
        pt = np.array([complex(z)])
        inside = [i for i, c in enumerate(self.cells) if c.depth(pt)[0] > 0]
        rank = self.plan.rank
        if not inside or any(np.isfinite(rank[i]) for i in inside):
            return ""
        margin = self.atlas.decomposition.margin
        msg = (
            f"cell {inside[0]} is cut off from the goal's cells: no overlap at least the margin "
            f"{margin:.3g} m deep leads there"
        )
        exits = [
            o
            for o in self.atlas.decomposition.links
            if np.isfinite(rank[o.a]) != np.isfinite(rank[o.b])
        ]
        if exits:
            o = max(exits, key=lambda o: o.depth)
            w = 2 * float(self.atlas.workspace.clearance(np.array([o.point]))[0])
            msg += (
                f"; the widest way, at {fmt_point(o.point)} (free space {w:.3g} m wide), "
                f"holds a disk of radius {o.depth:.3g} m only"
            )
        return msg

    def initial_cells(self, z: ArrayLike) -> NDArray[np.int64]:
        """For each point, the lowest-ranked reachable cell containing it whose chart is
        installed (-1: none)."""
        z = np.atleast_1d(np.asarray(z, dtype=np.complex128))
        if z.size == 1:  # one robot (a controller's pose): every cell at once
            ok = (
                (self.atlas.decomposition.depths(complex(z.ravel()[0])) > 0)
                & np.isfinite(self.plan.rank)
                & np.array([m is not None for m in self._nav_maps])
            )
            if not ok.any():
                return np.full(z.shape, -1, dtype=np.int64)
            cand = np.flatnonzero(ok)
            # the first of the lowest rank, as the loop below takes it
            return np.full(z.shape, int(cand[np.argmin(self.plan.rank[cand])]), dtype=np.int64)
        best = np.full(z.shape, -1, dtype=np.int64)
        best_rank = np.full(z.shape, np.inf)
        for i, c in enumerate(self.cells):
            r = self.plan.rank[i]
            if not np.isfinite(r) or self._nav_maps[i] is None:
                continue
            inside = c.depth(z) > 0
            take = inside & (r < best_rank)
            best[take], best_rank[take] = i, r
        return best

    def switch(self, z: ArrayLike, active: NDArray[np.int64]) -> NDArray[np.int64]:
        """The active cells after the switching rule: the lowest-ranked cell of strictly lower
        rank than the active one, its chart installed, in which the point lies deeper than
        ``hysteresis``."""
        z = np.atleast_1d(np.asarray(z, dtype=np.complex128))
        out = active.copy()
        for i in np.unique(active):
            if i < 0:
                continue
            idx = np.flatnonzero(active == i)
            pending = np.ones(idx.size, dtype=bool)
            for j in self.lower[int(i)]:  # ascending rank: the first hit is the lowest
                if self._nav_maps[j] is None:
                    continue
                deep = pending & (self.cells[j].depth(z[idx]) > self.hysteresis)
                out[idx[deep]] = j
                pending &= ~deep
                if not pending.any():
                    break
        return out

    def run(
        self,
        starts: ArrayLike,
        *,
        window: float | None = None,
        t_max: float | None = None,
        max_step: float | None = None,
        atol: float = 1e-6,
        record_paths: bool = False,
    ) -> AtlasRun:
        """Simulate robots from ``starts`` (complex array) to the goal.

        Each active cell's robots are integrated by :func:`confnav.navigation.sim.simulate` for
        ``window`` time units (default: the time to cross 4 ``hysteresis``), collisions checked
        against the *whole* workspace; between windows the switching rule is applied (a
        supervisor at a fixed rate).  A robot that reaches a local goal switches to the next
        cell (it lies ``margin`` deep there).  ``record_paths`` keeps every robot's accepted
        points (for plots).
        """
        import time as _time

        t0 = _time.perf_counter()
        if self.missing():
            raise NavigationError(
                f"run needs every chart; cells {self.missing()[:8]} have none yet (drive a "
                "partial atlas pose by pose, confnav.atlas.wire.AtlasController)"
            )
        ws = self.atlas.workspace
        z = np.atleast_1d(np.asarray(starts, dtype=np.complex128)).copy()
        if np.any(~(ws.clearance(z) > 0)):
            raise NavigationError("a start is not in the free space")
        window = float(window) if window is not None else 4 * self.hysteresis / self.speed
        t_max = float(t_max) if t_max is not None else 20 * ws.diameter / self.speed
        max_step = float(max_step) if max_step is not None else 2 * self.hysteresis
        r = _Robots.at(z, self.initial_cells(z), np.asarray(ws.clearance(z), dtype=np.float64))
        reasons = [
            (self.cut_off(z[k]) or "in no cell of the atlas") if r.active[k] < 0 else ""
            for k in range(z.size)
        ]
        while True:
            run = np.flatnonzero(r.status < 0)
            if run.size == 0:
                break
            for i in np.unique(r.active[run]):
                self._window(
                    r, int(i), run[r.active[run] == i], window, max_step, atol, record_paths
                )
            self._supervise(r, t_max)
        return AtlasRun(
            starts=np.atleast_1d(np.asarray(starts, dtype=np.complex128)),
            success=r.status == ARRIVED,
            collided=r.status == COLLIDED,
            status=r.status,
            path_length=r.length,
            time=r.t,
            min_clearance=r.minclr,
            final=r.z,
            switches=r.switches,
            cells=tuple(tuple(h) for h in r.history),
            wall_time=_time.perf_counter() - t0,
            reasons=tuple(
                rs or _REASONS[int(st)] for rs, st in zip(reasons, r.status, strict=True)
            ),
            paths=tuple(np.concatenate(p) for p in r.pieces) if record_paths else None,
        )

    def _window(
        self,
        r: _Robots,
        i: int,
        idx: NDArray[np.intp],
        window: float,
        max_step: float,
        atol: float,
        record_paths: bool,
    ) -> None:
        """Integrate the robots ``idx`` of cell ``i`` for one window under cell i's chart
        (collisions against the whole workspace); those at the local goal switch to the next
        cell (they lie ``margin`` deep there), and one that has not moved for 20 windows is
        stalled (a saddle)."""
        ws = self.atlas.workspace
        res = simulate(
            self.controller(i), r.z[idx], clearance=ws.clearance, t_max=window,
            max_step=max_step, atol=atol, stall_distance=1e-12, stall_steps=10**9,
            record_paths=record_paths,
        )  # fmt: skip
        if record_paths and res.paths is not None:
            for k, piece in zip(idx.tolist(), res.paths, strict=True):
                r.pieces[k].append(piece[1:])  # its first point ends the last window
        moved = np.abs(res.final - r.z[idx])
        r.z[idx] = res.final
        r.length[idx] += res.path_length
        r.t[idx] += res.time
        r.minclr[idx] = np.minimum(r.minclr[idx], res.min_clearance)
        st = res.status
        r.status[idx[st == COLLIDED]] = COLLIDED
        r.status[idx[st == ERROR]] = ERROR
        arrived = idx[st == ARRIVED]
        if self.plan.next[i] < 0:
            r.status[arrived] = ARRIVED
        else:  # at the local goal: margin deep in the next cell
            r.active[arrived] = self.plan.next[i]
            r.switches[arrived] += 1
            for k in arrived:
                r.history[k].append(int(self.plan.next[i]))
        going = (st == TIMEOUT) | (st == STALLED)
        r.still[idx] = np.where(going & (moved < 1e-9), r.still[idx] + 1, 0)
        r.status[idx[going & (r.still[idx] >= 20)]] = STALLED

    def _supervise(self, r: _Robots, t_max: float) -> None:
        """Between windows: time out robots past ``t_max``, then apply the switching rule
        (:meth:`switch`) to the others."""
        run = np.flatnonzero(r.status < 0)
        over = run[r.t[run] >= t_max]
        r.status[over] = TIMEOUT
        run = np.flatnonzero(r.status < 0)
        if run.size:
            new = self.switch(r.z[run], r.active[run])
            changed = run[new != r.active[run]]
            for k, a in zip(changed.tolist(), new[new != r.active[run]].tolist(), strict=True):
                r.history[k].append(int(a))
            r.switches[changed] += 1
            r.active[run] = new
