"""Controller service: per robot, goal + map + pose -> velocity command and status.

Subscribes ``{prefix}/robot/*/goal``, ``.../cancel``, ``.../pose``, ``{prefix}/ws/*/transform``,
``{prefix}/ws/*/definition`` and the liveliness of ``{prefix}/alive/transform/*``; fetches
missing maps with a query on ``{prefix}/ws/{ws}/transform``; publishes ``cmd_vel`` and
``status`` per robot. A re-solved map is loaded and the robots' controllers rebuilt off the
pose path, then swapped in atomically. A workspace solved as an atlas (``{prefix}/ws/{ws}/atlas``)
is fetched by ``services/atlas_client.py`` and each of its robots gets its own chart-switching
controller (docs/ATLAS.md section 5).

A workspace definition that differs from the one the installed map was solved from makes
that map outdated: until a map of the new definition is installed, every robot of the
workspace closer than ``margin`` to the new geometry (or inside a new obstacle) is stopped
(reason ``map_outdated``) at once, and at each of its poses; the others keep moving on the old
map (a robot moves at most ``v_max`` per control period, so with ``margin`` above that it is
stopped before it can reach the new geometry).

Watchdog (zero velocity and a status saying why): stale pose (none for ``stale_after`` s since
the last pose or the goal; a pose only counts when its ``(stamp_ns, seq)`` is newer than the
last one, so replayed or reordered poses are not fresh), missing map, NaN or invalid pose,
position outside the map, no live transform service. Malformed goals (and goals above the
``max_gain``/``max_speed`` caps) clear the robot's goal and are answered with a status
(``idle``, ``invalid_input``); a ``GoalCancel`` and ``idle_ttl`` s without a pose or goal
forget a robot. Poses go through a bounded latest-per-robot queue; commands and statuses are
published by one publisher thread (never under a lock), in the order they were decided.
Many robots per process; ``robots`` restricts which ones this process drives.
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from confnav.schemas import (
    AtlasIndex,
    DecodeError,
    Goal,
    GoalCancel,
    Pose,
    RobotStatus,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services import navigation
from confnav.services.atlas_client import fetch_atlas
from confnav.services.bus import Bus
from confnav.services.keys import KeyError_, Keys
from confnav.services.neighbours import Neighbours
from confnav.services.neighbours import attach as attach_neighbours
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal
from confnav.services.shard import RobotSelector, robot_key_exprs, serialized
from confnav.services.transform import definition_hash, workspace_of

from confnav.atlas.wire import ATLAS_MARKER, AtlasMap, is_chart_ws_id
from confnav.navigation.control import Controller
from confnav.navigation.fleet import fleet_step

log = logging.getLogger(__name__)

POSE_BLOCK = 32
"""Most poses per control step: one vectorized block, whose commands go out before the next
block is computed (pipelining)."""
CTRL_CACHE_SIZE = 4096
"""Most controllers kept for reuse (a new goal with the parameters of a cached one costs no
harmonic solve); robots hold the ones they use, so eviction only forgets old goals."""
MAX_BACKLOG = 100_000
"""Most robots with a pose waiting. Of several waiting poses of one robot only the newest is
answered (the older ones are superseded: counted, never commanded), so an overloaded
controller falls back to answering every robot's latest pose instead of a growing queue."""

_CMD_HEADER = {
    name: VelocityCommand.model_fields[name].default for name in ("type", "schema_version")
}
"""The constant fields of a command, given to ``model_construct``: it then resolves no
defaults (20 -> 9 us per command, the same bytes)."""

MapLoader = Callable[[TransformSolution], Any]
ControllerFactory = Callable[[Any, Goal], navigation.ControllerLike]


@dataclass
class _Map:
    revision: str
    cmap: Any
    definition_hash: str = ""


@dataclass
class _Pending:
    """A definition newer than the installed map: its geometry, until its map is installed."""

    definition_hash: str
    workspace: Any  # confnav.geometry.Workspace


@dataclass
class _Robot:
    robot_id: str
    goal: Goal | None = None
    ctrl: navigation.ControllerLike | None = None
    ctrl_revision: str | None = None
    ctrl_error: str = ""
    last_pose_t: float | None = None  # monotonic receive time of the last fresh pose
    last_stamp: tuple[int, int] = (-1, -1)  # (stamp_ns, seq) of the last fresh pose
    goal_t: float = 0.0  # monotonic time the goal was set
    seen_t: float = 0.0  # monotonic time of the last pose or goal (idle TTL)
    position: tuple[float, float] | None = None
    status_key: tuple[str, str, str | None, str] = ("", "", None, "")
    status_t: float = 0.0
    stale_reported: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)


class ControllerService(Service):
    """See the module docstring."""

    name = "controller"

    def __init__(
        self,
        bus: Bus,
        keys: Keys | None = None,
        robots: set[str] | RobotSelector | None = None,
        stale_after: float = 0.5,
        status_period: float = 0.25,
        fetch_period: float = 0.5,
        require_transform: bool = True,
        map_loader: MapLoader = navigation.load_map,
        controller_factory: ControllerFactory = navigation.make_controller,
        health_period: float = 1.0,
        linger: float = 0.0,
        margin: float = 0.25,
        max_gain: float = 1000.0,
        max_speed: float = 2.0,
        idle_ttl: float = 60.0,
        max_robots: int = 100_000,
    ) -> None:
        super().__init__(bus, keys, health_period)
        self.only = robots
        self.stale_after = stale_after
        self.status_period = status_period
        self.fetch_period = fetch_period
        self.require_transform = require_transform
        self.linger = linger  # s to wait for more poses before a control step (throughput)
        self.margin = margin  # m from a changed geometry within which robots stop
        self.max_gain = max_gain
        self.max_speed = max_speed
        self.idle_ttl = idle_ttl  # s without pose or goal after which a robot is forgotten
        self.max_robots = max_robots
        self._load_map = map_loader
        self._make_ctrl = controller_factory
        self._lock = threading.Lock()
        self._robots: dict[str, _Robot] = {}
        self._maps: dict[str, _Map] = {}
        self._map_errors: dict[str, str] = {}
        self._pending: dict[str, _Pending] = {}  # ws id -> definition newer than its map
        self._out: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._transform_alive: set[str] = set()
        self._wake_fetch = threading.Event()
        # (map revision, goal key) -> controller: robots with the same goal share one (the
        # navigation function is built once, and their poses are evaluated in one call)
        # controllers by (map revision, goal and law parameters): robots with one goal share
        # one; least recently used first, at most CTRL_CACHE_SIZE (goals change all the time)
        self._ctrl_cache: OrderedDict[tuple[object, ...], navigation.ControllerLike] = OrderedDict()
        self._build_lock = threading.Lock()
        self._rids: dict[str, str] = {}  # pose key -> robot id
        self._cmd_keys: dict[str, str] = {}  # robot id -> cmd_vel key
        self.swapped = threading.Event()  # set on each hot swap (tests)
        self.neighbours: Neighbours | None = None  # fleet hook (services/neighbours.py)

    def _start(self) -> None:
        k = self.keys
        self._handles.append(self.bus.subscribe_liveliness(k.alive_of("transform"), self._on_live))
        self.spawn(self._publish_loop, "publish")
        self._handles.append(self.bus.subscribe(k.any_ws("transform"), self._on_transform))
        self._handles.append(self.bus.subscribe(k.any_ws("definition"), self._on_definition))
        self._handles.append(self.bus.subscribe(k.any_ws("delete"), self._on_ws_delete))
        self._handles.append(self.bus.subscribe(k.any_ws("atlas"), self._on_atlas))
        # this process's robots only (scale-out: services/shard.py, docs/SERVICES.md)
        exprs = robot_key_exprs(k, "goal", self.only)
        on_goals = serialized(self._on_goals) if len(exprs) > 1 else self._on_goals
        for expr in exprs:
            self._handles.append(self.bus.subscribe_latest(expr, on_goals, self._goals_dropped))
        for expr in robot_key_exprs(k, "cancel", self.only):
            self._handles.append(self.bus.subscribe(expr, self._on_cancel))
        exprs = robot_key_exprs(k, "pose", self.only)
        on_poses = serialized(self._on_poses) if len(exprs) > 1 else self._on_poses
        for expr in exprs:
            self._handles.append(  # bounded: the newest waiting pose of each robot wins
                self.bus.subscribe_latest(
                    expr,
                    on_poses,
                    self._poses_dropped,
                    max_keys=MAX_BACKLOG,
                    linger=self.linger,
                )
            )
        self.neighbours = attach_neighbours(self)  # fleet hook: every robot's pose, movers
        self.spawn(self._fetch_loop, "fetch")
        self.spawn(self._watchdog_loop, "watchdog")

    # publishing (one thread, never under a lock) ---------------------------------------
    def _emit(self, key: str, payload: bytes) -> None:
        """Queue a message; the publisher thread sends them in this order."""
        self._out.put((key, payload))

    def _publish_loop(self) -> None:
        while True:
            try:
                key, payload = self._out.get(timeout=0.1)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            try:
                self.bus.publish(key, payload)
            except Exception:
                self.count("publish_errors")
                log.exception("publishing on %s failed", key)

    def _poses_dropped(self, n: int) -> None:
        self.count("poses", n)
        self.count("poses_superseded", n)

    def _goals_dropped(self, n: int) -> None:
        self.count("goals_received", n)
        self.count("goals_superseded", n)

    def stop(self) -> None:
        self._stop.set()
        self._wake_fetch.set()
        super().stop()

    def health_detail(self) -> tuple[str, str]:
        if self.require_transform and not self.transform_alive:
            return "degraded", "no transform service alive"
        return "ok", ""

    @property
    def transform_alive(self) -> bool:
        return bool(self._transform_alive)

    # liveliness and maps -----------------------------------------------------------------
    def _on_live(self, key: str, alive: bool) -> None:
        if alive:
            self._transform_alive.add(key)
        else:
            self._transform_alive.discard(key)
        log.info("transform service %s %s", key, "alive" if alive else "gone")
        self._wake_fetch.set()

    def _on_transform(self, key: str, payload: bytes) -> None:
        self.count("transforms_received")
        try:
            ws_id = self.keys.parse(key).ident
            sol = decode(TransformSolution, payload)
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected transform on %s: %s", key, exc)
            return
        if sol.ws_id != ws_id:
            self.count("rejected")
            return
        if is_chart_ws_id(ws_id):  # a chart of an atlas: installed with its atlas
            return
        self._install(sol)

    def _install(self, sol: TransformSolution | AtlasMap) -> None:
        """Load a solution (or take a fetched atlas) and rebuild the controllers of its
        robots, then swap (hot)."""
        ws_id = sol.ws_id
        cur = self._maps.get(ws_id)
        if cur is not None and cur.revision == sol.revision:
            return
        try:
            cmap = sol if isinstance(sol, AtlasMap) else self._load_map(sol)
        except Exception as exc:
            self.count("map_load_errors")
            self._map_errors[ws_id] = f"cannot load map: {exc}"
            log.error("workspace %r: cannot load map %s: %s", ws_id, sol.revision[:12], exc)
            return
        new = _Map(sol.revision, cmap, sol.definition_hash)
        with self._lock:
            goals = {
                r.robot_id: r.goal
                for r in self._robots.values()
                if r.goal and r.goal.ws_id == ws_id
            }
        built = {rid: self._build(new, g) for rid, g in goals.items() if g}
        with self._build_lock:
            live = {m.revision for w, m in self._maps.items() if w != ws_id} | {new.revision}
            self._ctrl_cache = OrderedDict(
                (k, c) for k, c in self._ctrl_cache.items() if k[0] in live
            )
        late: list[_Robot] = []  # goals that changed or came while the map was being built
        with self._lock:
            self._maps[ws_id] = new
            self._map_errors.pop(ws_id, None)
            pending = self._pending.get(ws_id)
            if pending is not None and pending.definition_hash == sol.definition_hash:
                del self._pending[ws_id]  # the map of the current geometry: robots go on
            for r in self._robots.values():
                with r.lock:
                    if r.goal is None or r.goal.ws_id != ws_id:
                        continue
                    if r.goal is not goals.get(r.robot_id):
                        late.append(r)
                        continue
                    ctrl, err = built[r.robot_id]
                    r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, new.revision, err
        for r in late:
            self._adopt(r, ws_id, new)
        self.count("maps_installed")
        log.info("workspace %r: map %s installed (%d robots)", ws_id, sol.revision[:12], len(goals))
        self.swapped.set()

    # definition changes -----------------------------------------------------------------
    def _on_definition(self, key: str, payload: bytes) -> None:
        """A definition unlike the installed map's: stop the robots near the new geometry."""
        self.count("definitions_received")
        try:
            ws_id = self.keys.parse(key).ident
            defn = decode(WorkspaceDefinition, payload)
            if defn.ws_id != ws_id:
                raise DecodeError("invalid_input", f"definition on {key} names {defn.ws_id!r}")
            h = definition_hash(defn)
            workspace = workspace_of(defn)
        except (KeyError_, DecodeError, ValueError) as exc:  # WorkspaceError is a ValueError
            self.count("rejected")
            log.warning("rejected definition on %s: %s", key, exc)
            return
        self.count("definitions")
        now = time.monotonic()
        with self._lock:
            cur = self._maps.get(ws_id)
            if cur is not None and cur.definition_hash == h:
                self._pending.pop(ws_id, None)  # back to the geometry of the installed map
                return
            old = self._pending.get(ws_id)
            if old is not None and old.definition_hash == h:
                return  # announced again
            self._pending[ws_id] = _Pending(h, workspace)
            robots = [r for r in self._robots.values() if r.goal and r.goal.ws_id == ws_id]
        self.count("definitions_changed")
        log.warning("workspace %r: definition changed; robots near it stop until its map", ws_id)
        for r in robots:
            with r.lock:
                if r.goal is None or r.goal.ws_id != ws_id or r.position is None:
                    continue
                blocker = self._outdated(r)
                if blocker is not None:
                    self._stop_robot(r, "map_outdated", blocker, now)
        self._wake_fetch.set()

    def _on_ws_delete(self, key: str, payload: bytes) -> None:
        """A deleted workspace: its map is dropped, its robots stop (missing_map)."""
        ws_id = self.workspace_to_delete(key, payload)
        if ws_id is None:
            return
        now = time.monotonic()
        with self._lock:
            self._maps.pop(ws_id, None)
            self._pending.pop(ws_id, None)
            self._map_errors[ws_id] = f"workspace {ws_id!r} was deleted"
            robots = [r for r in self._robots.values() if r.goal and r.goal.ws_id == ws_id]
        self.count("workspaces_deleted")
        for r in robots:
            with r.lock:
                if r.goal is None or r.goal.ws_id != ws_id:
                    continue
                r.ctrl, r.ctrl_revision, r.ctrl_error = None, None, ""
                self._stop_robot(r, "missing_map", self._map_errors[ws_id], now)

    def _outdated(self, r: _Robot) -> str | None:
        """Why the robot's map contradicts the current geometry near it, or None."""
        assert r.goal is not None
        pending = self._pending.get(r.goal.ws_id)
        if pending is None or r.position is None:
            return None
        c = float(pending.workspace.clearance(complex(*r.position)))
        if c >= self.margin:
            return None
        return (
            f"workspace {r.goal.ws_id!r} changed: {c:.3f} m from the new geometry "
            f"(margin {self.margin:g} m); waiting for its map"
        )

    def _build(self, m: _Map, goal: Goal) -> tuple[navigation.ControllerLike | None, str]:
        key = (m.revision, *navigation.goal_key(goal))
        if getattr(m.cmap, "per_robot", False):  # an atlas: the controller holds the chart
            key = (*key, goal.robot_id)
        with self._build_lock:
            ctrl = self._ctrl_cache.get(key)
            if ctrl is not None:
                self._ctrl_cache.move_to_end(key)
                return ctrl, ""
            try:
                ctrl = self._make_ctrl(m.cmap, goal)
            except Exception as exc:
                self.count("navigation_errors")
                return None, f"{type(exc).__name__}: {exc}"
            self.count("controllers_built")
            self._ctrl_cache[key] = ctrl
            while len(self._ctrl_cache) > CTRL_CACHE_SIZE:  # robots keep what they use
                self._ctrl_cache.popitem(last=False)
            search = getattr(getattr(ctrl, "controller", ctrl), "search_critical_points", None)
            if search is not None:  # in the background: STALLED near a saddle once they land
                search(navigation.CRITICAL_SEARCH)
            return ctrl, ""

    def _fetch_loop(self) -> None:
        while not self._stop.is_set():
            self._wake_fetch.wait(self.fetch_period)
            self._wake_fetch.clear()
            if self._stop.is_set():
                return
            with self._lock:
                needed = {
                    r.goal.ws_id
                    for r in self._robots.values()
                    if r.goal is not None and r.goal.ws_id not in self._maps
                } | set(self._pending)
            for ws_id in sorted(needed):
                self._fetch(ws_id)

    def _fetch(self, ws_id: str) -> None:
        self.count("queries")
        try:
            replies = self.bus.query(self.keys.ws(ws_id, "transform"), timeout=2.0)
        except Exception as exc:
            self._map_errors[ws_id] = f"query failed: {exc}"
            return
        if not replies:
            self._map_errors[ws_id] = "no transform service answered"
            return
        for rep in replies:
            if not rep.ok or rep.payload is None:
                self._map_errors[ws_id] = rep.error or "error"
                if (rep.error or "").startswith(ATLAS_MARKER):  # solved as an atlas
                    self._fetch_atlas(ws_id)
                    return
                continue
            try:
                sol = decode(TransformSolution, rep.payload)
            except DecodeError as exc:
                self._map_errors[ws_id] = str(exc)
                continue
            self._install(sol)
            return

    def _fetch_atlas(self, ws_id: str, index: AtlasIndex | None = None) -> None:
        """Fetch and install the atlas of ``ws_id`` (services/atlas_client.py)."""
        try:
            self._install(fetch_atlas(self.bus, self.keys, ws_id, index))
        except Exception as exc:
            self._map_errors[ws_id] = f"cannot fetch atlas: {exc}"
            log.warning("workspace %r: cannot fetch atlas: %s", ws_id, exc)

    def _on_atlas(self, key: str, payload: bytes) -> None:
        """A (re)solved atlas: fetched and installed off the subscriber thread."""
        try:
            index = decode(AtlasIndex, payload)
            if index.ws_id != self.keys.parse(key).ident:
                raise DecodeError("invalid_input", f"atlas on {key} names {index.ws_id!r}")
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected atlas on %s: %s", key, exc)
            return
        cur = self._maps.get(index.ws_id)
        if cur is None or cur.revision != index.revision:
            self.spawn(lambda: self._fetch_atlas(index.ws_id, index), "atlas-fetch")

    # goals -------------------------------------------------------------------------------
    def _robot(self, rid: str) -> _Robot | None:
        """The robot's record (created; None if not driven here or over ``max_robots``)."""
        if self.only is not None and rid not in self.only:
            return None
        with self._lock:
            r = self._robots.get(rid)
            if r is None:
                if len(self._robots) >= self.max_robots:
                    self.count("robots_over_limit")
                    return None
                r = self._robots[rid] = _Robot(rid, seen_t=time.monotonic())
            return r

    def _on_goals(self, items: list[tuple[str, bytes]]) -> None:
        self.count("goals_received", len(items))
        for key, payload in items:
            self._on_goal(key, payload)

    def _on_goal(self, key: str, payload: bytes) -> None:
        try:
            rid = self.keys.parse(key).ident
        except KeyError_ as exc:
            self.count("rejected")
            log.warning("rejected goal on %s: %s", key, exc)
            return
        try:
            goal = decode(Goal, payload)
            if goal.robot_id != rid:
                raise DecodeError("invalid_input", f"goal on {key} names robot {goal.robot_id!r}")
            if goal.gain > self.max_gain or goal.v_max > self.max_speed:
                raise DecodeError(
                    "invalid_input",
                    f"gain {goal.gain:g} / v_max {goal.v_max:g} above the caps "
                    f"{self.max_gain:g} / {self.max_speed:g}",
                )
        except DecodeError as exc:
            self.count("rejected")
            log.warning("rejected goal on %s: %s", key, exc)
            self._reject_goal(rid, str(exc))
            return
        # a robot with a footprint drives on the map of the shrunk workspace ({ws}~r{radius})
        goal = goal.model_copy(update={"ws_id": navigation.map_ws_id(goal)})
        r = self._robot(rid)
        if r is None:
            return
        with r.lock:
            r.seen_t = time.monotonic()
            same = r.goal is not None and navigation.goal_key(r.goal) == navigation.goal_key(goal)
        if same:  # goals are state: a repeated one (e.g. republished at 1 Hz) changes nothing
            self.count("goals_repeated")
            return
        self.count("goals")
        m = self._maps.get(goal.ws_id)
        ctrl, err = self._build(m, goal) if m is not None else (None, "")
        with r.lock:
            r.goal, r.ctrl, r.ctrl_error = goal, ctrl, err
            r.ctrl_revision = m.revision if m is not None else None
            r.stale_reported = False
            r.status_key = ("", "", None, "")
            r.goal_t = r.seen_t = time.monotonic()
        current = self._maps.get(goal.ws_id)
        if current is not None and current is not m:  # a map landed while this goal was set
            self._adopt(r, goal.ws_id, current)
        elif m is None:
            self._wake_fetch.set()
        log.info("robot %r: goal %s on %r", rid, goal.goal, goal.ws_id)

    def _adopt(self, r: _Robot, ws_id: str, m: _Map) -> None:
        """Give ``r`` the controller of workspace ``ws_id``'s map ``m`` for its current goal,
        unless it has one of ``m`` already or its goal moved elsewhere meanwhile.

        A goal and a map installation race: the installation builds for the goals it saw, the
        goal handler for the map it saw; whichever comes second catches the robot the first
        one missed (a lost race left a robot without a controller until the next map)."""
        with r.lock:
            goal = r.goal
            if goal is None or goal.ws_id != ws_id or r.ctrl_revision == m.revision:
                return
        ctrl, err = self._build(m, goal)
        with r.lock:
            if r.goal is goal and r.ctrl_revision != m.revision:
                r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, m.revision, err

    def _reject_goal(self, rid: str, message: str) -> None:
        """A malformed goal: the robot's goal is cleared (zero command) and the sender told."""
        r = self._robot(rid)
        if r is None:
            return
        now = time.monotonic()
        with r.lock:
            if r.goal is not None:
                self._publish_cmd(r, 0j, None)
            r.goal, r.ctrl, r.ctrl_error, r.ctrl_revision = None, None, "", None
            r.seen_t = now
            r.status_key = ("", "", None, "")
            self._status(r, "idle", "invalid_input", f"goal rejected: {message}", now)

    def _on_cancel(self, key: str, payload: bytes) -> None:
        """Cancel: zero command, ``idle`` status, and the robot is forgotten."""
        self.count("cancels_received")
        got = self.decode_keyed(GoalCancel, key, payload, "robot_id", "cancel")
        if got is None:
            return
        rid = got[0]
        self.count("cancels")
        self._forget(rid, "cancelled")

    def _forget(self, rid: str, why: str) -> None:
        with self._lock:
            r = self._robots.pop(rid, None)
        if r is None:
            return
        with r.lock:
            if r.goal is not None:
                self._publish_cmd(r, 0j, None)
            r.goal = None
            r.status_key = ("", "", None, "")
            self._status(r, "idle", "no_goal", why, time.monotonic())
        self._cmd_keys.pop(rid, None)
        self.count("robots_forgotten")

    # poses (hot path) -------------------------------------------------------------------------
    def _on_poses(self, items: list[tuple[str, bytes]]) -> None:
        """Every waiting pose: the newest per robot, in blocks of :data:`POSE_BLOCK`."""
        self.count("poses", len(items))
        if len(items) > 1:
            newest = {key: i for i, (key, _) in enumerate(items)}
            if len(newest) < len(items):
                self.count("poses_superseded", len(items) - len(newest))
                items = [items[i] for i in sorted(newest.values())]
        for s in range(0, len(items), POSE_BLOCK):
            self._pose_block(items[s : s + POSE_BLOCK])

    def _rid_of(self, key: str) -> str | None:
        """Robot id of a pose key (cached: the hot path parses each key once)."""
        rid = self._rids.get(key)
        if rid is None:
            try:
                rid = self.keys.parse(key).ident
            except KeyError_:
                return None
            if len(self._rids) < 100_000:
                self._rids[key] = rid
        return rid

    def _pose_block(self, items: list[tuple[str, bytes]]) -> None:
        """Decode, one vectorized control-law call per shared controller, publish."""
        now = time.monotonic()
        groups: dict[int, tuple[navigation.ControllerLike, list[tuple[_Robot, Pose]]]] = {}
        for key, payload in items:
            rid = self._rid_of(key)
            if rid is None:
                self.count("rejected")
                continue
            with self._lock:
                r = self._robots.get(rid)
            if r is None:  # remembered before its goal (the watchdog must not miss it)
                r = self._robot(rid)
                if r is None:
                    continue
            try:
                pose = decode(Pose, payload)
                if pose.robot_id != rid:
                    raise DecodeError("invalid_input", f"pose on {key} names {pose.robot_id!r}")
            except DecodeError as exc:
                self.count("rejected")
                reason = "nan_input" if exc.reason == "nan_input" else "invalid_input"
                with r.lock:
                    r.seen_t = now
                    if r.goal is not None:
                        r.last_pose_t = now  # the robot is alive, but its input is unusable
                        self._stop_robot(r, reason, str(exc), now)
                continue
            with r.lock:
                r.seen_t = now
                stamp = (pose.stamp_ns, pose.seq)
                if stamp <= r.last_stamp:  # replayed or reordered: not fresh, not answered
                    self.count("poses_out_of_order")
                    continue
                r.last_stamp = stamp
                r.last_pose_t = now
                r.position = (pose.x, pose.y)
                r.stale_reported = False
                if r.goal is None:
                    continue
                blocker = self._blocker(r)
                if blocker is not None:
                    self._stop_robot(r, blocker[0], blocker[1], now, pose)
                    continue
                ctrl = r.ctrl
            assert ctrl is not None
            groups.setdefault(id(ctrl), (ctrl, []))[1].append((r, pose))
        members_of = list(groups.values())
        results = list(zip(members_of, self._control(members_of), strict=True))
        # --- fleet hook (services/neighbours.py): keep robots off each other and movers ---
        if self.neighbours is not None:
            results = self.neighbours.filter_block(results, now)
        # --- end fleet hook ---
        for (ctrl, members), res in results:
            if isinstance(res, Exception):
                self.count("navigation_errors")
                for r, pose in members:
                    with r.lock:
                        self._stop_robot(
                            r, "navigation_error", f"{type(res).__name__}: {res}", now, pose
                        )
                continue
            u, codes = res
            for (r, pose), ui, code in zip(members, u.tolist(), codes.tolist(), strict=True):
                with r.lock:
                    self._act(r, pose, navigation.decide(ctrl, complex(ui), int(code)), now)

    def _control(
        self, groups: list[tuple[navigation.ControllerLike, list[tuple[_Robot, Pose]]]]
    ) -> list[tuple[np.ndarray, np.ndarray] | Exception]:
        """``(u, codes)`` (or the error) of each controller group of a pose block, in order.

        The map does not depend on the goal: the groups of world-frame controllers on one map
        (robots with their own goals) get ``T``, ``T'`` and the clearance from one evaluation
        for all their poses and each group's law from ``Controller.from_map_values``; the others one
        control-law call per group (:func:`navigation.commands`).
        """
        zs = [np.array([complex(p.x, p.y) for _, p in members]) for _, members in groups]
        out: list[tuple[np.ndarray, np.ndarray] | Exception | None] = [None] * len(groups)
        laws: list[Any] = [ctrl for ctrl, _ in groups]
        by_map: dict[int, list[int]] = {}
        for i, law in enumerate(laws):
            if hasattr(law, "from_map_values") and hasattr(law, "cmap"):
                by_map.setdefault(id(law.cmap), []).append(i)
        for idx in by_map.values():
            if len(idx) < 2:  # one goal on this map: the plain call below
                continue
            try:
                zall = np.concatenate([zs[i] for i in idx])
                w, dw = laws[idx[0]].cmap.T_and_dT(zall)
                use = [i for i in idx if getattr(laws[i], "uses_clearance", False)]
                c = laws[use[0]].clearance(zall) if use else None
            except Exception as exc:
                for i in idx:
                    out[i] = exc
                continue
            if all(isinstance(laws[i], Controller) for i in idx):
                try:  # every goal's law in one vectorized pass (navigation.fleet)
                    fleet = [laws[i] for i in idx for _ in range(zs[i].size)]
                    o = fleet_step(fleet, zall, w, dw, c)
                    self.count("fleet_steps")
                except Exception:  # a bug there must not stop the fleet: one by one below
                    log.exception("fleet step failed; evaluating each goal on its own")
                else:
                    s = 0
                    for i in idx:
                        n = zs[i].size
                        out[i] = (np.asarray(o.u[s : s + n]), np.asarray(o.status[s : s + n]))
                        s += n
                    continue
            s = 0
            for i in idx:
                n = zs[i].size
                try:
                    ci = None if c is None else c[s : s + n]
                    o = laws[i].from_map_values(zs[i], w[s : s + n], dw[s : s + n], ci)
                    out[i] = (np.asarray(o.u, dtype=complex), np.asarray(o.status, dtype=int))
                except Exception as exc:
                    out[i] = exc
                s += n
        for i, (ctrl, members) in enumerate(groups):
            if out[i] is not None:
                continue
            th = np.array([p.theta for _, p in members])
            try:
                out[i] = navigation.commands(ctrl, zs[i], th)
            except Exception as exc:
                out[i] = exc
        return [o for o in out if o is not None]

    def _act(self, r: _Robot, pose: Pose, d: navigation.Decision, now: float) -> None:
        """Publish what :func:`navigation.decide` made of the control law's output."""
        if r.goal is None or r.last_stamp != (pose.stamp_ns, pose.seq):
            return  # cancelled, or a newer pose came meanwhile: it gets the answer
        blocker = self._blocker(r)  # again: the geometry may have changed meanwhile
        if blocker is not None:
            self._stop_robot(r, blocker[0], blocker[1], now, pose)
        elif d.state == "stopped":
            self._stop_robot(r, d.reason, d.message, now, pose)
        else:
            self._publish_cmd(r, d.u, pose)
            self._status(r, d.state, d.reason, d.message, now)

    def _blocker(self, r: _Robot) -> tuple[str, str] | None:
        """Why this robot must not move now, or None."""
        if self.require_transform and not self._transform_alive:
            return "transform_service_dead", "no transform service is alive"
        if r.ctrl is None:
            assert r.goal is not None
            if r.ctrl_error:
                return "navigation_error", r.ctrl_error
            err = self._map_errors.get(r.goal.ws_id, "waiting for the map")
            return "missing_map", err
        if self._pending:
            outdated = self._outdated(r)
            if outdated is not None:
                return "map_outdated", outdated
        return None

    def _stop_robot(
        self, r: _Robot, reason: str, message: str, now: float, pose: Pose | None = None
    ) -> None:
        self.count(f"stops_{reason}")
        self._publish_cmd(r, 0j, pose)
        self._status(r, "stopped", reason, message, now)

    def _publish_cmd(self, r: _Robot, u: complex, pose: Pose | None) -> None:
        # model_construct: our own finite values, no re-validation on the hot path (the
        # payloads are checked against the schema in the tests and by every reader)
        body = getattr(r.ctrl, "frame", "world") == "body"  # unicycle: u = v + i omega
        cmd = VelocityCommand.model_construct(
            **_CMD_HEADER,
            robot_id=r.robot_id,
            stamp_ns=time.time_ns(),
            linear=(u.real, 0.0) if body else (u.real, u.imag),
            angular=u.imag if body else 0.0,
            frame="body" if body else "world",
            pose_seq=pose.seq if pose is not None else -1,
            pose_stamp_ns=pose.stamp_ns if pose is not None else 0,
            map_revision=r.ctrl_revision,
            chart=getattr(r.ctrl, "active_chart", None),
        )
        key = self._cmd_keys.get(r.robot_id)
        if key is None:
            key = self._cmd_keys[r.robot_id] = self.keys.robot(r.robot_id, "cmd_vel")
        self._emit(key, encode(cmd))
        self.count("commands")

    def _status(self, r: _Robot, state: str, reason: str, message: str, now: float) -> None:
        chart = getattr(r.ctrl, "active_chart", None)
        skey = (state, reason, r.ctrl_revision, message + f"|{chart}")
        if skey == r.status_key and now - r.status_t < self.status_period:
            return
        if skey[:2] != r.status_key[:2]:  # a new state or reason: worth a line in the log
            log.info("robot %r: %s (%s)%s", r.robot_id, state, reason,
                     f": {message}" if message else "")  # fmt: skip
        r.status_key, r.status_t = skey, now
        dist = None
        if r.position is not None and r.goal is not None:
            dx, dy = r.position[0] - r.goal.goal[0], r.position[1] - r.goal.goal[1]
            dist = (dx * dx + dy * dy) ** 0.5
        status = RobotStatus(
            robot_id=r.robot_id,
            stamp_ns=time.time_ns(),
            state=state,  # type: ignore[arg-type]
            reason=reason,  # type: ignore[arg-type]
            message=message[:4000],
            ws_id=r.goal.ws_id if r.goal else None,
            map_revision=r.ctrl_revision,
            position=r.position,
            distance_to_goal=dist,
            chart=chart,
        )
        self._emit(self.keys.robot(r.robot_id, "status"), encode(status))

    # watchdog -------------------------------------------------------------------------------
    def _watchdog_loop(self) -> None:
        period = min(0.05, self.stale_after / 4)
        next_ttl = time.monotonic() + 1.0
        while not self._stop.wait(period):
            now = time.monotonic()
            with self._lock:
                robots = list(self._robots.values())
            if now >= next_ttl:  # forget robots silent for idle_ttl s
                next_ttl = now + 1.0
                for r in robots:
                    if now - r.seen_t > self.idle_ttl:
                        self._forget(r.robot_id, f"forgotten after {self.idle_ttl:g} s silent")
            for r in robots:
                with r.lock:
                    if r.goal is None:
                        continue
                    last = r.goal_t if r.last_pose_t is None else max(r.last_pose_t, r.goal_t)
                    if now - last > self.stale_after:
                        if not r.stale_reported:
                            r.stale_reported = True
                            self._stop_robot(
                                r, "stale_pose", f"no pose for {self.stale_after:g} s", now
                            )
                        else:
                            self._status(r, "stopped", "stale_pose", "", now)
                        continue
                    blocker = self._blocker(r)
                    if blocker is not None:  # stop now; the pose path keeps it stopped
                        if r.status_key[:2] != ("stopped", blocker[0]):
                            self._stop_robot(r, blocker[0], blocker[1], now)
                        else:
                            self._status(r, "stopped", blocker[0], blocker[1], now)

    def robot_state(self, rid: str) -> tuple[str, str] | None:
        """(state, reason) last published for a robot (tests)."""
        with self._lock:
            r = self._robots.get(rid)
        return None if r is None else (r.status_key[0], r.status_key[1])


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("controller", help="run the controller service")
    add_zenoh_args(p)
    p.add_argument(
        "--robots",
        default=None,
        help="robots this process drives: comma-separated ids and Zenoh chunk patterns such "
        "as 'a$*' (ids starting with a) or '$*7'; others' poses are not even delivered "
        "(default: all; see docs/SERVICES.md, scale-out)",
    )
    p.add_argument("--stale-after", type=float, default=0.5, help="pose timeout, s")
    p.add_argument(
        "--linger-ms",
        type=float,
        default=0.0,
        help="ms to wait for more poses before a control step (larger batches, less CPU)",
    )
    p.add_argument(
        "--margin",
        type=float,
        default=0.25,
        help="m: on a definition change, robots this close to the new geometry stop until "
        "its map is installed (default %(default)s)",
    )
    p.add_argument("--max-gain", type=float, default=1000.0, help="largest goal gain, 1/s")
    p.add_argument("--max-speed", type=float, default=2.0, help="largest goal v_max, m/s")
    p.add_argument(
        "--idle-ttl", type=float, default=60.0, help="s without pose or goal: robot forgotten"
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    try:
        robots = RobotSelector.parse(args.robots) if args.robots else None
    except KeyError_ as exc:
        print(f"confnav serve controller: --robots: {exc}", file=sys.stderr)
        return 2
    return run_until_signal(
        lambda bus, keys: ControllerService(
            bus,
            keys,
            robots,
            stale_after=args.stale_after,
            linger=args.linger_ms / 1e3,
            margin=args.margin,
            max_gain=args.max_gain,
            max_speed=args.max_speed,
            idle_ttl=args.idle_ttl,
        ),
        args,
    )
