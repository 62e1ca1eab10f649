"""The controller service's first move: a robot whose footprint map ``{ws}~r{R}`` has no
revision yet drives at once on the map of the base workspace ``{ws}`` (steering only), with the
safety layer on the *exact* shrunk workspace, and swaps to the footprint map between two
commands when its first revision is installed (docs/NAVIGATION.md, "First move";
docs/SERVICES.md, progressive maps).

Why this is safe: the body (a disk of radius R around the robot's reference point; for a
unicycle the look-ahead point with R = radius + look-ahead) is clear of every wall iff the
reference point lies in the free space shrunk by R [Latombe 1991, ch. 4]. The safety layer
(:mod:`confnav.navigation.safety`) keeps the reference point in the workspace it is given,
whatever the map commands; it is given the shrunk workspace itself, computed here from the
base map's workspace with the same functions the transform service derives ``{ws}~r{R}`` with
(:func:`confnav.services.definitions.derived_definition`, i.e.
:func:`confnav.maps.footprint.inflate`), so the geometry the robot is kept in is the one its
footprint map is later solved for (checked when that map arrives: ``footprint_mismatch``
counts a difference). The base map only steers: its flow may lead into a gap narrower than
the body, where the filter holds the robot (no collision, no progress) until the footprint
map arrives.
"""

from __future__ import annotations

import cmath
import logging
import threading
from collections import OrderedDict
from typing import Any

from confnav.schemas import Goal
from confnav.services import navigation
from confnav.services.controller_cache import ControllerCacheMixin
from confnav.services.controller_state import _Map, _Robot
from confnav.services.controller_warm import WarmMixin, prime
from confnav.services.definitions import definition_of, derived_definition, workspace_of

from confnav.maps.footprint import UnreachableGoalError, parse_derived_ws_id

log = logging.getLogger(__name__)

#: Most shrunk workspaces kept (one per base geometry and footprint radius in use).
SHRUNK_CACHE_SIZE = 64


def base_of(ws_id: str) -> str | None:
    """The base workspace of a footprint workspace id ``{ws}~r{R}`` (None for others)."""
    parsed = parse_derived_ws_id(ws_id)
    return None if parsed is None else parsed[0]


def shrunk_workspace(base_workspace: Any, ws_id: str) -> Any:
    """The exact workspace of the footprint id ``ws_id`` (``{base}~r{R}``) derived from the
    base workspace: the transform service's own derivation
    (:func:`~confnav.services.definitions.derived_definition`) of the base definition, so the
    result is the geometry ``{base}~r{R}`` is solved for (raises ``WorkspaceError``). Only the
    anchor may differ (a solved map records the anchor it chose; the safety layer does not
    use it): :func:`same_geometry` compares the rest."""
    parsed = parse_derived_ws_id(ws_id)
    if parsed is None:
        raise ValueError(f"{ws_id!r} is not a footprint workspace id")
    base_defn = definition_of(parsed[0], base_workspace)
    return workspace_of(derived_definition(ws_id, base_defn))


def same_geometry(a: Any, b: Any) -> bool:
    """Whether two workspaces have the same boundary polygons (bitwise; anchors aside)."""
    import numpy as np

    pa, pb = a.boundaries, b.boundaries
    return len(pa) == len(pb) and all(np.array_equal(x, y) for x, y in zip(pa, pb, strict=True))


def make_controller_on_base(cmap: Any, goal: Goal, shrunk: Any) -> navigation.ControllerLike:
    """The goal's feedback law on the base map ``cmap`` with the safety layer on the exact
    shrunk workspace ``shrunk`` (``goal.ws_id`` is the footprint workspace). The goal must be
    in the shrunk free space (the error of :func:`navigation.make_controller` otherwise)."""
    g = complex(goal.goal[0], goal.goal[1])
    if not bool(shrunk.contains(g)):
        raise UnreachableGoalError(
            f"goal {goal.goal} of robot {goal.robot_id!r} is unreachable: it is not in "
            f"{goal.ws_id!r}, the largest component of the workspace shrunk by the footprint "
            f"{navigation.footprint_radius(goal):g} m (within that distance of an obstacle, or "
            "cut off by a passage narrower than twice it)"
        )
    if getattr(cmap, "is_atlas", False):  # an atlas base: its switching law, same filter
        return cmap.controller(goal, shrunk)  # type: ignore[no-any-return]
    return navigation.point_law(cmap, goal, shrunk)


def base_charts_start(cmap: Any, z: complex | None) -> bool:
    """Whether the base map can steer a robot whose reference point is ``z``: a single map
    always; a partial atlas only if a chart of a cell holding ``z`` is out (else the robot
    would hold for that chart on the base map, and building its law there cost the
    controller's interpreter 0.5-0.9 s beside the footprint atlas's install: the warehouse,
    docs/SLAM.md "Background atlases"). ``z`` None (no pose yet): assumed charted."""
    if z is None or not getattr(cmap, "is_atlas", False):
        return True
    pending = set(getattr(cmap, "pending", ()))
    if not pending:
        return True
    import shapely

    pt = shapely.points(z.real, z.imag)
    cells = cmap.atlas.decomposition.cells
    return any(
        i not in pending and bool(shapely.covers(c.polygon, pt)) for i, c in enumerate(cells)
    )


def base_workspace(cmap: Any) -> Any:
    """The exact workspace of a base map: a single map's, or an atlas's whole workspace."""
    if getattr(cmap, "is_atlas", False):
        return cmap.atlas.workspace
    return cmap.workspace


def reference_point(ctrl: Any, x: float, y: float, theta: float) -> complex:
    """The point the law keeps in the shrunk free space: the position, or a unicycle's
    look-ahead point ``x + d e^{i theta}`` (docs/NAVIGATION.md, unicycles)."""
    d = float(getattr(ctrl, "d", 0.0)) if getattr(ctrl, "frame", "world") == "body" else 0.0
    return complex(x, y) + d * cmath.exp(1j * theta)


def base_note(r: _Robot) -> str:
    """The status message of a robot driving on the base map (module docstring)."""
    assert r.goal is not None
    return (
        f"navigating on the unshrunk map {r.base_ws!r} with the body's exact safety layer; "
        f"footprint map {r.goal.ws_id!r} being solved (where the unshrunk map leads into a gap "
        "too narrow for the body, the safety layer holds the robot until it arrives)"
    )


def off_shrunk(r: _Robot, theta: float) -> str:
    """Why a robot on the base map is outside the shrunk free space ("" if it is not)."""
    if r.shrunk is None or r.position is None:
        return ""
    p = reference_point(r.ctrl, r.position[0], r.position[1], theta)
    c = float(r.shrunk.clearance1(p))
    if c >= 0:
        return ""
    return (
        f"pose outside {r.goal.ws_id if r.goal else '?'!r}, the free space shrunk by the "
        f"footprint ({-c:.3g} m inside the footprint's margin)"
    )


class FootprintMixin(ControllerCacheMixin, WarmMixin):
    """Robots on the base map while their footprint map is being solved (module docstring)."""

    def _init_footprint(self) -> None:
        if not hasattr(self, "_shrunk"):
            self._shrunk: OrderedDict[tuple[str, str], Any] = OrderedDict()
            self._shrunk_lock = threading.Lock()

    def _on_base_available(self, base: _Map | None = None) -> bool:
        """Only with the library's controllers (a test's factory keeps the old behaviour) and
        a base map with its exact workspace (a single map, or an atlas)."""
        if self._make_ctrl is not navigation.make_controller:
            return False
        if base is None:
            return True
        cmap = base.cmap
        return (
            hasattr(cmap, "atlas")
            if getattr(cmap, "is_atlas", False)
            else hasattr(cmap, "workspace")
        )

    def _shrunk_of(self, base: _Map, ws_id: str) -> Any:
        """The exact shrunk workspace of ``ws_id`` for the geometry of the base map ``base``
        (cached per base geometry: the revisions of one definition share it, and with it the
        safety layer's grid); raises what the derivation raises."""
        self._init_footprint()
        key = (str(getattr(base.cmap, "workspace_hash", base.revision)), ws_id)
        with self._shrunk_lock:
            hit = self._shrunk.get(key)
            if hit is not None:
                self._shrunk.move_to_end(key)
                return hit
        shrunk = shrunk_workspace(base_workspace(base.cmap), ws_id)
        self.count("footprint_workspaces_built")
        with self._shrunk_lock:
            self._shrunk[key] = shrunk
            while len(self._shrunk) > SHRUNK_CACHE_SIZE:
                self._shrunk.popitem(last=False)
        return shrunk

    def _build_on_base(
        self, base: _Map, goal: Goal
    ) -> tuple[navigation.ControllerLike | None, str, Any]:
        """``(controller, error, shrunk workspace)`` of ``goal`` on the base map ``base``."""
        try:
            shrunk = self._shrunk_of(base, goal.ws_id)
        except Exception as exc:
            self.count("navigation_errors")
            return None, f"{type(exc).__name__}: {exc}", None
        key: tuple[object, ...] = ("base", base.revision, *navigation.goal_key(goal))
        if getattr(base.cmap, "per_robot", False):  # an atlas: the controller holds the chart
            key = (*key, goal.robot_id)
        with self._build_lock:
            ctrl = self._ctrl_cache.get(key)
            if ctrl is not None:
                self._ctrl_cache.move_to_end(key)
                return ctrl, "", shrunk
        try:
            ctrl = make_controller_on_base(base.cmap, goal, shrunk)
        except Exception as exc:
            self.count("navigation_errors")
            return None, f"{type(exc).__name__}: {exc}", shrunk
        flt = getattr(getattr(ctrl, "controller", ctrl), "safety", None)
        try:  # the shrunk workspace's safety grid: built here, not in the first pose step
            getattr(flt, "grid", None)
        except Exception:
            log.debug("safety grid", exc_info=True)
        self.count("controllers_built_on_base")
        with self._build_lock:
            self._ctrl_cache[key] = ctrl
            self._ctrl_cache.move_to_end(key)
        search = getattr(getattr(ctrl, "controller", ctrl), "search_critical_points", None)
        if search is not None:
            search(navigation.CRITICAL_SEARCH)
        return ctrl, "", shrunk

    def _adopt_base(self, r: _Robot, base_ws: str, base: _Map) -> None:
        """Drive ``r`` on the base map ``base`` while its footprint map has no revision
        (unless it has one of ``base`` already, or its goal or map changed meanwhile)."""
        with r.lock:
            goal = r.goal
            if (
                goal is None
                or base_of(goal.ws_id) != base_ws
                or goal.ws_id in self._maps
                or (r.base_ws == base_ws and r.ctrl_revision == base.revision)
            ):
                return
        if not base_charts_start(base.cmap, self._reference_of(r, goal)):
            self.count("base_uncharted_start")
            return  # the robot holds for its footprint map (or a later base revision)
        with self._goal_building():
            ctrl, err, shrunk = self._build_on_base(base, goal)
            prime(ctrl, r.position)
        with r.lock:
            if r.goal is not goal or goal.ws_id in self._maps:
                return  # a new goal, or the footprint map came meanwhile: it wins
            r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, base.revision, err
            r.base_ws, r.shrunk = base_ws, shrunk
        if ctrl is not None:
            log.info(
                "robot %r: driving on %r (revision %s) with the exact safety layer of %r "
                "until its map is solved", r.robot_id, base_ws, base.revision[:12], goal.ws_id,
            )  # fmt: skip

    @staticmethod
    def _reference_of(r: _Robot, goal: Goal) -> complex | None:
        """The point ``r``'s law would steer (its position, or a unicycle's look-ahead
        point), None without a pose."""
        with r.lock:
            pos, theta = r.position, r.theta
        return None if pos is None else navigation.steered_point(goal, pos[0], pos[1], theta)

    def _base_installed(self, ws_id: str, m: _Map) -> None:
        """A map of ``ws_id`` was installed: its robots still waiting for a footprint map
        ``{ws_id}~r{R}`` drive on it meanwhile."""
        if base_of(ws_id) is not None or not self._on_base_available(m):
            return
        with self._lock:
            robots = [
                r
                for r in self._robots.values()
                if r.goal is not None
                and r.goal.ws_id not in self._maps
                and base_of(r.goal.ws_id) == ws_id
            ]
        for r in robots:
            self._adopt_base(r, ws_id, m)

    def _footprint_installed(self, ws_id: str, m: _Map) -> None:
        """A footprint map was installed: check its geometry is the one its robots were kept
        in on the base map (counted; the robots have just been swapped to it)."""
        if base_of(ws_id) is None:
            return
        self._init_footprint()
        with self._shrunk_lock:
            mine = [w for (_, did), w in self._shrunk.items() if did == ws_id]
        got = getattr(m.cmap, "workspace", None)
        if mine and got is not None and not any(same_geometry(w, got) for w in mine):
            self.count("footprint_mismatch")
            log.warning("workspace %r: its map's geometry differs from the one derived here", ws_id)
