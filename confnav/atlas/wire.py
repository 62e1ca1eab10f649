"""Atlases on the wire: the index of cells (:class:`confnav.schemas.AtlasIndex`) and the
per-robot switching controller the controller service runs on an atlas.

Pure (no Zenoh, no I/O): the transform service turns a solved :class:`Atlas` into an index
(:func:`index_fields`) and one ``TransformSolution`` per chart; the controller service
rebuilds the atlas from them (:func:`atlas_from_index`) and drives each robot with an
:class:`AtlasController`, which keeps that robot's active chart and applies the switching
rule of :class:`confnav.atlas.compose.AtlasNavigator` (hysteresis, strictly decreasing rank)
at every pose.  ``replay --check`` rebuilds the same objects from a recording.
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike
from shapely.geometry import LineString, MultiLineString, Polygon
from shapely.geometry.base import BaseGeometry

from confnav.atlas.charts import Atlas, PartialAtlas, navigation_map
from confnav.atlas.compose import AtlasNavigator, Overlap, overlaps
from confnav.atlas.decompose import Cell, Decomposition, _cell_workspace, elongation
from confnav.conformal.cmap import EXPANSION_MIN_POINTS
from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.navigation import defaults
from confnav.navigation.control import ControlOutput, Status
from confnav.navigation.unicycle import UnicycleController

__all__ = [
    "ATLAS_MARKER",
    "ATLAS_SUFFIX",
    "AtlasController",
    "AtlasMap",
    "NavMaps",
    "ProgressiveController",
    "atlas_from_index",
    "atlas_map_of",
    "atlas_revision",
    "atlas_ws_id",
    "chart_ws_id",
    "index_fields",
    "is_chart_ws_id",
    "parse_atlas_ws_id",
]

#: Start of the error a transform query answers for a workspace solved as an atlas.
ATLAS_MARKER = "atlas:"

#: Suffix of the id under which a workspace's atlas is solved on request, whatever one map
#: of it would be (:func:`atlas_ws_id`): a host whose single map cannot steer a robot (its
#: navigation function flat to rounding there) asks for it.
ATLAS_SUFFIX = "~atlas"

#: Largest distance (relative to the workspace's diameter) between a cell's boundary and its
#: chart's: 10 times the simplification of :func:`confnav.atlas.decompose` (1e-9).
CHART_MATCH = 1e-8


def chart_ws_id(ws_id: str, index: int) -> str:
    """The workspace id under which chart ``index`` of atlas ``ws_id`` is published."""
    return f"{ws_id}~c{index}"


def atlas_ws_id(ws_id: str) -> str:
    """The id of ``ws_id`` solved as an atlas (``{ws}~atlas``; itself for such an id)."""
    return ws_id if parse_atlas_ws_id(ws_id) is not None else ws_id + ATLAS_SUFFIX


def parse_atlas_ws_id(ws_id: str) -> str | None:
    """The workspace of an id from :func:`atlas_ws_id` (None for other ids)."""
    base = ws_id.removesuffix(ATLAS_SUFFIX)
    return base if base and base != ws_id else None


def is_chart_ws_id(ws_id: str) -> bool:
    """True for an id of the form :func:`chart_ws_id` makes (``{ws}~c{i}``)."""
    head, sep, tail = ws_id.rpartition("~c")
    return bool(sep and head and tail.isdigit())


def atlas_revision(chart_revisions: Sequence[str]) -> str:
    """Revision of an atlas: a hash of its charts' revisions in cell order."""
    return hashlib.sha256("|".join(chart_revisions).encode()).hexdigest()


def _lines(g: BaseGeometry) -> list[list[tuple[float, float]]]:
    """The polylines of a (multi)line geometry, as lists of points."""
    parts = getattr(g, "geoms", [g])
    return [
        [(float(x), float(y)) for x, y in p.coords]
        for p in parts
        if isinstance(p, LineString) and not p.is_empty and len(p.coords) >= 2
    ]


def _ring(coords: Any) -> list[tuple[float, float]]:
    """A shapely ring's vertices without the closing one (exactly, not simplified)."""
    return [(float(x), float(y)) for x, y in list(coords)[:-1]]


def index_fields(atlas: Atlas | PartialAtlas) -> dict[str, Any]:
    """The JSON-able description of an atlas's cells and decomposition (no charts): the
    fields of :class:`confnav.schemas.AtlasIndex` but the ids, revisions and stamp (of a
    partial revision: no solve times, ``pending`` cells)."""
    dec = atlas.decomposition
    full = atlas if isinstance(atlas, Atlas) else None
    times = {i: r.wall_time for i, r in enumerate(full.chart_records)} if full else {}
    cells = []
    for c in dec.cells:
        cells.append(
            {
                "index": c.index,
                "outer": _ring(c.polygon.exterior.coords),
                "obstacles": [_ring(h.coords) for h in c.polygon.interiors],
                "cut": _lines(c.cut),
                "tile": tuple(float(v) for v in c.tile),
                "solve_time": float(times.get(c.index, 0.0)),
                "pending": atlas.charts[c.index] is None,
            }
        )
    return {
        "margin": float(dec.margin),
        "tol": float(atlas.tol),
        "cells": cells,
        "wall_time": float(atlas.wall_time),
        "cpu_time": float(full.cpu_time) if full else 0.0,
        "decomposition": {
            "workspace": dec.workspace.to_dict(),
            "tile": dec.tile,
            "overlap": dec.overlap,
            "max_ratio": dec.max_ratio,
            "max_ratio_holes": dec.max_ratio_holes,
            "max_obstacles": dec.max_obstacles,
        },
    }


_SHARED: weakref.WeakValueDictionary[str, Workspace] = weakref.WeakValueDictionary()
_SHARED_LOCK = threading.Lock()


def shared_workspace(ws: Workspace) -> Workspace:
    """The one :class:`Workspace` object of this geometry in the process (by
    ``content_hash``; kept while something holds it): ``ws`` itself, or an equal workspace
    registered before. The safety layer's grid is built once per workspace object
    (:func:`confnav.navigation.safety.safety_filter`), so every revision of an atlas rebuilt
    from its index (:func:`atlas_from_index`) shares one grid, and a grid built ahead of the
    first revision (the controller service, from the definition) is the one it uses."""
    key = ws.content_hash
    with _SHARED_LOCK:
        hit = _SHARED.get(key)
        if hit is not None:
            return hit
        _SHARED[key] = ws
        return ws


#: Decomposition properties that depend only on the cells' polygons and cut edges (not on
#: which cells have a chart): a later revision with the same cells takes them as computed.
_CELL_PROPERTIES = ("centres", "touching", "_shapes", "links", "passage")


def cells_key(index: Any) -> str:
    """A hash of an ``AtlasIndex``'s cells as geometry (polygons, cut edges, tiles, margin
    and decomposition parameters; not the charts): equal for the revisions of one round of
    a progressive atlas, which differ only in which cells have their chart."""
    dec = dict(index.decomposition)
    ws = dec.pop("workspace", None)
    h = hashlib.sha256()
    h.update(repr((float(index.margin), sorted(dec.items()))).encode())
    h.update(repr(ws).encode())
    for c in index.cells:
        h.update(repr((c.index, c.outer, c.obstacles, c.cut, tuple(c.tile))).encode())
    return h.hexdigest()


def atlas_from_index(
    index: Any, charts: Sequence[Any], previous: Atlas | PartialAtlas | None = None
) -> Atlas | PartialAtlas:
    """Rebuild an :class:`Atlas` from an ``AtlasIndex`` message and its charts' maps (cell
    order).  Cell polygons and cut edges exactly as published (the plan is then the same).
    A partial revision (cells ``pending``, their charts ``None``) gives a
    :class:`PartialAtlas` whose pending cells get their workspace from the cell polygon.

    ``previous``: an atlas rebuilt from an index with the same cells (:func:`cells_key`,
    checked by the caller), e.g. the previous revision of a progressive atlas's round: its
    workspace, the cells whose chart did not change and the decomposition's overlaps,
    centres and shapes are reused, so a revision that adds charts costs their checks only
    (rebuilding every cell and the overlaps took 0.14-0.43 s per revision of the
    warehouse's 74 cells at load 4-6, bench/results/atlas_install.json)."""
    if len(charts) != len(index.cells):
        raise NavigationError(
            f"atlas {index.ws_id!r}: {len(charts)} charts for {len(index.cells)} cells"
        )
    if previous is not None and len(previous.decomposition.cells) != len(index.cells):
        previous = None
    dec_d = dict(index.decomposition)
    ws_d = dec_d.pop("workspace")
    ws = (
        previous.decomposition.workspace
        if previous is not None
        else shared_workspace(Workspace.from_dict(ws_d))
    )
    cells = []
    # the chart's workspace is the cell polygon without collinear vertices: simplified within
    # 1e-9 of the workspace's diameter (confnav.atlas.decompose._cell_workspace), which moves
    # the boundary by that much and its area by up to that times its length (the README's
    # office shrunk by 0.3 m: 5.4e-10 of a cell's area, and a chart refused at 1e-9 of it)
    tol = CHART_MATCH * ws.diameter
    for k, (c, m) in enumerate(zip(index.cells, charts, strict=True)):
        old = None if previous is None else previous.decomposition.cells[k]
        if old is not None and previous is not None and m is previous.charts[k]:
            cells.append(old)  # the same cell with the same chart (or still pending)
            continue
        poly = old.polygon if old is not None else Polygon(c.outer, [list(o) for o in c.obstacles])
        if m is None:  # pending: the cell as published, its chart to come
            if not getattr(c, "pending", False):
                raise NavigationError(f"atlas {index.ws_id!r}: chart {c.index} missing")
            cell_ws = _cell_workspace(poly, ws.diameter)
        else:
            if poly.boundary.hausdorff_distance(m.workspace.polygon.boundary) > tol:
                raise NavigationError(
                    f"atlas {index.ws_id!r}: chart {c.index} is not its cell's map"
                )
            cell_ws = m.workspace
        if old is not None:
            cells.append(Cell(c.index, poly, cell_ws, old.cut, old.tile, old.ratio))
            continue
        cut: BaseGeometry = MultiLineString([list(line) for line in c.cut])
        cells.append(Cell(c.index, poly, cell_ws, cut, tuple(c.tile), elongation(poly)))
    dec = Decomposition(
        ws,
        tuple(cells),
        float(dec_d["tile"]),
        float(dec_d["overlap"]),
        float(index.margin),
        float(dec_d["max_ratio"]),
        float(dec_d["max_ratio_holes"]),
        int(dec_d["max_obstacles"]),
    )
    if previous is not None:  # cached properties of the same polygons and cuts
        done = vars(previous.decomposition)
        vars(dec).update({p: done[p] for p in _CELL_PROPERTIES if p in done})
    if any(m is None for m in charts):
        return PartialAtlas(dec, tuple(charts), float(index.tol), 0, float(index.wall_time))
    return Atlas(dec, tuple(charts), float(index.tol), (), index.wall_time, 1)


def is_pending(cell: Any) -> bool:
    """Whether an ``AtlasCell`` of a partial revision has no chart yet."""
    return bool(getattr(cell, "pending", False))


def atlas_map_of(index: Any, maps: Mapping[str, Any], previous: AtlasMap | None = None) -> AtlasMap:
    """The :class:`AtlasMap` of an ``AtlasIndex`` whose charts' navigation maps are in ``maps``
    (by revision): what the controller installs and ``replay --check`` rebuilds. A partial
    revision's pending cells have no chart (robots hold there until a later revision).

    ``previous``: the atlas map installed before (e.g. the previous revision of a
    progressive atlas): if its cells are this index's (:func:`cells_key`) their geometry,
    overlaps and links are reused (:func:`atlas_from_index`), and :meth:`AtlasMap.extends`
    lets the host extend its robots' laws instead of rebuilding them."""
    missing = [
        c.chart_ws_id for c in index.cells if not is_pending(c) and c.chart_revision not in maps
    ]
    if missing:
        raise NavigationError(f"atlas {index.ws_id!r}: charts {missing[:5]} missing")
    charts = [None if is_pending(c) else maps[c.chart_revision] for c in index.cells]
    key = cells_key(index)
    same = previous is not None and previous.cells_key == key
    before = previous.atlas if same and previous is not None else None
    atlas = atlas_from_index(index, charts, before)  # the navigation maps serve as the charts
    links = previous.links if same and previous is not None else []
    am = AtlasMap(
        index.ws_id, index.revision, index.definition_hash, atlas, nav_maps=charts, links=links
    )
    am.chart_revisions = [c.chart_revision for c in index.cells]
    am.cells_key = key
    return am


def _expansions_built(m: Any) -> bool:
    """Whether a navigation map has its local expansions (True for a map without any)."""
    return getattr(m, "_expansion", True) is not None


def _defer_expansions(m: Any) -> None:
    """A ``for_navigation`` map evaluates by the direct formula until :func:`_build_expansions`
    (its ``_fast`` flag builds the expansions on the first evaluation otherwise)."""
    if not _expansions_built(m):
        m._fast = False


def _build_expansions(m: Any) -> None:
    """Build a navigation map's local expansions now (``ConformalMap._expansions`` builds
    them for a batch of ``EXPANSION_MIN_POINTS``), then let every evaluation use them: the
    flag goes up only after the build, so a robot's step on this chart meanwhile keeps the
    direct formula instead of building them a second time."""
    m._expansions(EXPANSION_MIN_POINTS)
    m._fast = True


@dataclass
class AtlasMap:
    """What the controller service installs for a workspace solved as an atlas: the atlas,
    its charts' navigation maps and cell overlaps (shared by every goal), and the revision.

    ``per_robot``: every robot gets its own controller (it holds the robot's active chart).
    """

    ws_id: str
    revision: str
    definition_hash: str
    atlas: Atlas | PartialAtlas
    nav_maps: list[Any] = field(default_factory=list)
    links: list[Overlap] = field(default_factory=list)
    is_atlas: bool = True
    per_robot: bool = True
    #: the charts' revisions in cell order (from the index; "" unknown): a later revision of
    #: a progressive atlas reuses the charts it shares with this one
    chart_revisions: list[str] = field(default_factory=list)
    #: :func:`cells_key` of the index this map was rebuilt from ("" unknown)
    cells_key: str = ""
    _warm_locks: list[threading.Lock] = field(default_factory=list, init=False, repr=False)
    _warm_failed: set[int] = field(default_factory=set, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.nav_maps:
            self.nav_maps = [None if m is None else navigation_map(m) for m in self.atlas.charts]
        if not self.links:
            self.links = overlaps(self.atlas)
        # charts start cold (module docstring of :meth:`warm`): a robot's first command on a
        # chart never waits for that chart's local expansions
        self._warm_locks = [threading.Lock() for _ in self.nav_maps]
        for m in self.nav_maps:
            if m is not None:
                _defer_expansions(m)

    @property
    def pending(self) -> list[int]:
        """The cells whose charts a later revision brings (a partial revision; else [])."""
        return [i for i, m in enumerate(self.nav_maps) if m is None]

    def is_warm(self, i: int) -> bool:
        """Whether chart ``i`` evaluates through its local expansions (see :meth:`warm`; a
        pending cell counts as warm: nothing to build)."""
        m = self.nav_maps[i]
        return m is None or i in self._warm_failed or _expansions_built(m)

    def known_charts(self) -> dict[str, Any]:
        """The installed charts' navigation maps by chart revision (pending cells left out)."""
        return {
            r: m
            for r, m in zip(self.chart_revisions, self.nav_maps, strict=False)
            if r and m is not None
        }

    def extends(self, old: AtlasMap) -> bool:
        """Whether this revision has ``old``'s cells and every chart of ``old`` (the next
        revision of a progressive atlas's round: it only adds charts)."""
        return (
            bool(self.cells_key)
            and self.cells_key == old.cells_key
            and len(self.nav_maps) == len(old.nav_maps)
            and all(a is None or a is b for a, b in zip(old.nav_maps, self.nav_maps, strict=True))
        )

    def extend(self, ctrl: Any, old: AtlasMap) -> Any:
        """A robot's law on this revision made from ``ctrl``, its law from :meth:`controller`
        on ``old`` (an :class:`AtlasController`, or the look-ahead law around one), if this
        revision :meth:`extends` ``old``; None otherwise. The new law is what
        :meth:`controller` would build here (a fresh switching state: the robot re-enters
        at its next pose, as after any revision, and ``replay --check`` rebuilds the same),
        but it shares ``ctrl``'s plan and the chart laws it built
        (:meth:`confnav.atlas.compose.AtlasNavigator.extended`): a robot's swap to the next
        revision costs no plan and no chart law, where a new controller per robot and
        revision rebuilt the law of its chart (bench/results/atlas_install.json)."""
        law = getattr(ctrl, "controller", ctrl)
        nav = getattr(law, "nav", None)
        if not isinstance(law, AtlasController) or nav is None or not self.extends(old):
            return None
        have = nav.nav_maps
        if len(have) != len(old.nav_maps) or any(
            a is not b for a, b in zip(have, old.nav_maps, strict=True)
        ):
            return None  # a law of another revision than ``old``
        new = AtlasController(nav.extended(self.atlas, self.nav_maps))
        if law is ctrl:
            return new
        if isinstance(ctrl, UnicycleController):
            return UnicycleController(new, ctrl.d, v_max=ctrl.v_max, omega_max=ctrl.omega_max)
        return None

    def cold_charts(self) -> list[int]:
        """The charts not warmed yet, in cell order."""
        return [i for i in range(len(self.nav_maps)) if not self.is_warm(i)]

    def warm(self, i: int) -> bool:
        """Build chart ``i``'s local expansions (True if built by this call).

        A chart's navigation map (``ConformalMap.for_navigation``) evaluates T and T' either by
        the barycentric Cauchy formula over its boundary nodes (O(nodes) per point, exact to
        rounding) or through local expansions (O(1) per point, within 1e-12 of the former:
        docs/METHOD.md, barycentric Cauchy sums; tests/test_expansion.py), which cost about a
        second per chart to build (measured on the README's office map: 1.2 s of a robot's
        first command on an idle machine, 3-4 s under load). An atlas installed here starts
        with every chart on the direct formula, so a goal costs its plan and the first
        chart's law only; a host (the controller service's warm-up thread) calls this for
        the charts its robots will need first, and each chart switches to its expansions as
        soon as they exist. Thread-safe: one build per chart; concurrent callers of the same
        chart wait for it rather than build it twice."""
        m = self.nav_maps[i]
        if self.is_warm(i):
            return False
        with self._warm_locks[i]:
            if self.is_warm(i):
                return False
            _build_expansions(m)
            return True

    def build_on_first_use(self) -> None:
        """Every cold chart builds its expansions on its first evaluation instead (the
        behaviour of a plain ``for_navigation`` map: no warm-up thread needed, but the first
        command on each chart waits for them)."""
        for i in self.cold_charts():
            self.nav_maps[i]._fast = True

    def warm_failed(self, i: int) -> None:
        """Chart ``i``'s expansions could not be built: it stays on the direct formula and
        counts as warm (nothing left to do for it)."""
        self._warm_failed.add(i)

    def cold_by_distance(self, points: ArrayLike) -> list[tuple[int, float]]:
        """The cold charts with the distance of their cells to the nearest of ``points``,
        nearest first (with no points: in cell order, distance ``inf``)."""
        cold = self.cold_charts()
        pts = np.atleast_1d(np.asarray(points, dtype=np.complex128)).ravel()
        pts = pts[np.isfinite(pts)]
        if not cold or pts.size == 0:
            return [(i, float("inf")) for i in cold]
        cells = self.atlas.decomposition.cells
        polys = np.array([cells[i].polygon for i in cold], dtype=object)
        geoms = shapely.points(pts.real, pts.imag)
        d = np.asarray(shapely.distance(polys[:, None], geoms[None, :]), dtype=np.float64)
        near = d.min(axis=1)
        return [(cold[int(k)], float(near[k])) for k in np.argsort(near, kind="stable")]

    def controller(
        self, goal: Any, safety: Workspace | None = None
    ) -> AtlasController | UnicycleController:
        """The switching controller of one robot for a ``Goal`` message; ``safety``: the
        workspace every chart's commands are filtered against (default: the atlas's own; the
        footprint's shrunk workspace when this atlas steers a body before its own atlas is
        solved, docs/NAVIGATION.md "Driving before the footprint map").

        A unicycle (``drive == "unicycle"``) gets the look-ahead law
        (:class:`confnav.navigation.unicycle.UnicycleController`) around its own
        :class:`AtlasController`: the look-ahead point is what is navigated and switched, so
        the atlas must be that of the free space shrunk by radius + look-ahead (the controller
        service and ``replay --check`` install the map of ``map_ws_id(goal)``, ``{ws}~r{R}``).
        """
        drive = getattr(goal, "drive", "holonomic")
        if drive not in ("holonomic", "unicycle"):
            raise NavigationError(
                f"atlas workspaces drive holonomic or unicycle robots, not {drive!r}"
            )
        extra: dict[str, Any] = {} if safety is None else {"safety": safety}
        nav = AtlasNavigator(
            self.atlas,
            complex(goal.goal[0], goal.goal[1]),
            speed=float(goal.v_max),
            nav_maps=self.nav_maps,
            links=self.links,
            navfn=goal.navfn,
            goal_tol=float(goal.tolerance),
            **extra,
        )
        ctrl = AtlasController(nav)
        if drive == "unicycle":
            return UnicycleController(
                ctrl,
                float(goal.lookahead),
                v_max=float(goal.v_max),
                omega_max=float(goal.omega_max),
            )
        return ctrl


class AtlasController:
    """One robot's hybrid law on an atlas: the active chart's Theorem 2 law, switched by
    :meth:`AtlasNavigator.switch` (hysteresis) and at local goals (to the next cell).

    Called with the robot's position (a one-element array; a longer array is taken as the
    same robot's successive positions).  ``active_chart`` is the chart of the last call;
    ``history`` the sequence of active charts.  ``goal``, ``goal_tol`` and ``v_max`` are those
    of the whole run (the final goal, not a chart's local goal): what
    :class:`confnav.navigation.unicycle.UnicycleController` and the simulators read.
    """

    def __init__(self, nav: AtlasNavigator) -> None:
        self.nav = nav
        self.goal: complex = nav.goal
        # what the goal cell's chart controller is built with (AtlasNavigator.controller)
        self.goal_tol = float(nav.controller_kw.get("goal_tol", defaults.GOAL_TOL))
        self.v_max = nav.speed
        self.active_chart: int | None = None
        self.history: list[int] = []
        self.fallback = ""
        #: (status reason, message) of the last call's stop when it is no bare ERROR: a
        #: robot in a cell cut off from the goal's is "unreachable", not outside the space
        self.stop_reason: tuple[str, str] | None = None
        #: on a partial atlas: the cell whose chart the robot holds for (zero command,
        #: status MOVING), None when it drives
        self.waiting: int | None = None

    def prepare(self, z: complex) -> list[int]:
        """Build, ahead of the robot's first pose at ``z``, what its first command needs: the
        laws of the charts it would start on (every lowest-ranked cell holding ``z``) and
        their safety layers' grids. Changes no state of the switching rule (the host calls
        this off the pose path, e.g. when a goal arrives); returns those charts."""
        nav = self.nav
        a = int(nav.initial_cells(np.array([complex(z)]))[0])
        if a < 0:
            return []
        law = nav.controller(a)
        flt = getattr(law, "safety", None)
        if flt is not None:
            _ = flt.grid  # the exact geometry's grid (shared by the charts' filters)
        return [a]

    def _set(self, i: int) -> None:
        self.active_chart = i
        if not self.history or self.history[-1] != i:
            self.history.append(i)

    def _uninstalled_here(self, pt: np.ndarray) -> int | None:
        """A reachable cell holding ``pt`` whose chart is not installed (lowest rank), or
        None: on a partial atlas the robot holds there until that chart comes."""
        nav = self.nav
        missing = nav.missing()
        if not missing:
            return None
        depth = nav.atlas.decomposition.depths(complex(pt[0]))
        held = [i for i in missing if np.isfinite(nav.plan.rank[i]) and depth[i] > 0]
        return min(held, key=lambda i: nav.plan.rank[i]) if held else None

    def _one(self, z: complex) -> tuple[complex, int]:
        nav = self.nav
        pt = np.array([z])
        self.stop_reason = None
        self.waiting = None
        if not np.isfinite(z):
            return 0j, int(Status.ERROR)
        a = self.active_chart
        if a is None or not nav.cells[a].depth(pt)[0] > 0:
            a = int(nav.initial_cells(pt)[0])  # first pose, or left the cell: re-enter
            if a < 0:
                wait = self._uninstalled_here(pt)
                if wait is not None:  # a partial atlas: hold until its chart is installed
                    self.waiting = wait
                    return 0j, int(Status.MOVING)
                why = nav.cut_off(z)
                if why:
                    self.stop_reason = ("unreachable", why)
                return 0j, int(Status.ERROR)
        a = int(nav.switch(pt, np.array([a], dtype=np.int64))[0])
        self._set(a)
        out = nav.controller(a)(pt)
        code = int(out.status[0])
        if code == Status.ARRIVED and nav.plan.next[a] >= 0:  # local goal: next cell
            nxt = int(nav.plan.next[a])
            if not nav.installed(nxt):  # a partial atlas: hold at the local goal
                self.waiting = nxt
                return 0j, int(Status.MOVING)
            a = nxt
            self._set(a)
            out = nav.controller(a)(pt)
            code = int(out.status[0])
        return complex(out.u[0]), code

    def __call__(self, z: ArrayLike) -> ControlOutput:
        zz = np.atleast_1d(np.asarray(z, dtype=np.complex128))
        res = [self._one(complex(v)) for v in zz.ravel()]
        u = np.array([r[0] for r in res], dtype=np.complex128).reshape(zz.shape)
        st = np.array([r[1] for r in res], dtype=np.int8).reshape(zz.shape)
        nan = np.full(zz.shape, np.nan)
        sat = np.zeros(zz.shape, dtype=bool)
        return ControlOutput(u=u, status=st, phi=nan, w=nan + 0j, saturated=sat)


class NavMaps:
    """The charts' navigation maps (``ConformalMap.for_navigation``) of the revisions of a
    progressive atlas, each made once (keyed by the chart object) and shared by every robot."""

    def __init__(self, *, defer_expansions: bool = False) -> None:
        self._maps: dict[int, tuple[Any, Any]] = {}  # id(chart) -> (chart, its map)
        #: new maps evaluate by the direct formula until :meth:`warm` builds their local
        #: expansions (:meth:`AtlasMap.warm`): a first command does not wait for them
        self.defer_expansions = defer_expansions

    def of(self, atlas: Atlas | PartialAtlas) -> list[Any]:
        """One navigation map per cell of ``atlas`` (None where its chart is missing)."""
        out: list[Any] = []
        for m in atlas.charts:
            if m is None:
                out.append(None)
                continue
            got = self._maps.get(id(m))
            if got is None or got[0] is not m:
                got = (m, navigation_map(m))
                if self.defer_expansions:
                    _defer_expansions(got[1])
                self._maps[id(m)] = got
            out.append(got[1])
        return out

    def warm(self) -> int:
        """Build the local expansions of every map still on the direct formula (how many)."""
        n = 0
        for _, nm in list(self._maps.values()):
            if not _expansions_built(nm):
                _build_expansions(nm)
                n += 1
        return n


def _cell_keys(atlas: Atlas | PartialAtlas) -> tuple[str, ...]:
    return atlas.decomposition.keys


class ProgressiveController:
    """One robot's law on an atlas that is being solved (docs/SLAM.md "Progressive atlas"):
    it drives on the newest revision offered (:meth:`offer`), a :class:`PartialAtlas` or a
    complete :class:`Atlas`, through an :class:`AtlasController`.

    A revision with the same cells whose charts extend the current ones (the next batch of
    :func:`confnav.atlas.charts.solve_atlas`) is installed into the running law (its plan,
    active chart and built laws stay); any other (a round that split cells, a refined atlas)
    gets a new law, swapped in between two commands: the robot re-enters it at its pose,
    without stopping. Before any chart holding the robot is installed the command is zero
    with status MOVING (``waiting`` says for which cell). ``controller_kw``: those of
    :class:`confnav.atlas.compose.AtlasNavigator` (``speed``, ``safety``, ``navfn``,
    ``goal_tol``...)."""

    def __init__(self, goal: complex, *, nav_maps: NavMaps | None = None, **controller_kw: Any):
        self.goal = complex(goal)
        self.controller_kw = controller_kw
        self.v_max = float(controller_kw.get("speed", 1.0))
        self.goal_tol = float(controller_kw.get("goal_tol", defaults.GOAL_TOL))
        self.nav_maps = nav_maps if nav_maps is not None else NavMaps()
        self.law: AtlasController | None = None
        self.revision: Atlas | PartialAtlas | None = None
        self._keys: tuple[str, ...] = ()
        self._maps: list[Any] = []
        #: how many revisions were offered; how many of them replaced the law (new cells
        #: or refined charts) rather than extending it
        self.offers = 0
        self.swaps = 0

    def offer(self, atlas: Atlas | PartialAtlas) -> None:
        """Drive on ``atlas`` from the next command on (module docstring)."""
        maps = self.nav_maps.of(atlas)
        keys = _cell_keys(atlas)
        self.offers += 1
        law = self.law
        if (
            law is not None
            and keys == self._keys
            and all(old is None or new is old for old, new in zip(self._maps, maps, strict=True))
        ):
            for i, (old, new) in enumerate(zip(self._maps, maps, strict=True)):
                if old is None and new is not None:
                    law.nav.install(i, new)
        else:
            nav = AtlasNavigator(atlas, self.goal, nav_maps=maps, **self.controller_kw)
            self.law = AtlasController(nav)
            self.swaps += law is not None
        self.revision, self._keys, self._maps = atlas, keys, maps

    @property
    def waiting(self) -> int | None:
        """The cell whose chart the robot holds for (None: it drives, or no revision yet)."""
        return None if self.law is None else self.law.waiting

    def __call__(self, z: ArrayLike) -> ControlOutput:
        if self.law is None:  # no revision yet: hold
            zz = np.atleast_1d(np.asarray(z, dtype=np.complex128))
            nan = np.full(zz.shape, np.nan)
            return ControlOutput(
                u=np.zeros(zz.shape, dtype=np.complex128),
                status=np.full(zz.shape, int(Status.MOVING), dtype=np.int8),
                phi=nan,
                w=nan + 0j,
                saturated=np.zeros(zz.shape, dtype=bool),
            )
        return self.law(z)
