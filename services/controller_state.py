"""The controller service's shared state: robot records, maps, the publisher thread,
commands, statuses and the reasons a robot stops (services/controller.py puts the jobs
together)."""

from __future__ import annotations

import logging
import math
import queue
import re
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from confnav.schemas import (
    WAITING_FOR_MAP,
    CommandBatch,
    Goal,
    TransformSolution,
    encode,
)
from confnav.schemas.fast import robot_status_json, velocity_command_json
from confnav.services import navigation
from confnav.services.bus import Bus
from confnav.services.keys import Keys
from confnav.services.runtime import Service
from confnav.services.shard import RobotSelector

from confnav.atlas.wire import ATLAS_MARKER

if TYPE_CHECKING:
    from confnav.services.neighbours import Neighbours

log = logging.getLogger(__name__)

#: Decimal figures in a status message (distances, errors): not part of its identity.
_FIGURES = re.compile(r"[-+]?\d+\.\d+(?:e[-+]?\d+)?")

#: The map error of a goal's workspace before the transform service answered its query.
NO_ANSWER_YET = "waiting for the map"


def map_being_solved(error: str) -> bool:
    """Whether a map error only says the map has no revision yet: the transform service's
    answer while it solves the workspace (``workspace 'x' is being solved; retry``,
    docs/SERVICES.md), its answer that the workspace is an atlas (whose index and charts the
    controller is fetching: ``atlas: ...``), or no answer yet. Robots hold on it instead of
    stopping."""
    return error == NO_ANSWER_YET or "is being solved" in error or error.startswith(ATLAS_MARKER)


def waiting_note(ws_id: str) -> str:
    """The status message of a robot holding for the first revision of its map."""
    return f"{WAITING_FOR_MAP} {ws_id!r} (being solved; the robot moves once it is installed)"


POSE_BLOCK = 256
"""Most poses per control step: one vectorized block, whose commands go out before the next
block is computed (pipelining). A block has a fixed cost (one map evaluation, the wall safety
layer, the fleet filter's rows: about 10 ms at 200 robots) besides its per-pose cost, so
blocks of 32 spent most of the controller's time on that fixed part once 200 robots were
waiting (docs/SERVICES.md, "Scale")."""
MAX_BACKLOG = 100_000
"""Most robots with a pose waiting. Of several waiting poses of one robot only the newest is
answered (the older ones are superseded: counted, never commanded), so an overloaded
controller falls back to answering every robot's latest pose instead of a growing queue."""


class PoseLike(Protocol):
    """What the pose step reads of a pose: a :class:`~confnav.schemas.Pose` or one entry of a
    :class:`~confnav.schemas.PoseBatch` (``controller_poses.BatchPose``)."""

    @property
    def robot_id(self) -> str: ...
    @property
    def stamp_ns(self) -> int: ...
    @property
    def seq(self) -> int: ...
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def theta(self) -> float: ...


@dataclass
class _CmdBatch:
    """The commands of one step answering a :class:`~confnav.schemas.PoseBatch`: the columns
    of its :class:`~confnav.schemas.CommandBatch`."""

    key: str
    sim_id: str
    robot_ids: list[str] = field(default_factory=list)
    linear: list[tuple[float, float]] = field(default_factory=list)
    angular: list[float] = field(default_factory=list)
    pose_seq: list[int] = field(default_factory=list)
    pose_stamp_ns: list[int] = field(default_factory=list)
    map_revision: list[str | None] = field(default_factory=list)
    frame: list[str] = field(default_factory=list)
    chart: list[int | None] = field(default_factory=list)

    def payload(self) -> bytes:
        """The wire bytes (our own valid values: not re-validated, as with the fast path of
        single commands; tests/test_controller_scale.py decodes them with the model)."""
        return encode(
            CommandBatch.model_construct(
                sim_id=self.sim_id, stamp_ns=time.time_ns(), robot_ids=self.robot_ids,
                linear=self.linear, angular=self.angular, pose_seq=self.pose_seq,
                pose_stamp_ns=self.pose_stamp_ns, map_revision=self.map_revision,
                frame=self.frame, chart=self.chart,
            )
        )  # fmt: skip


MapLoader = Callable[[TransformSolution], Any]
ControllerFactory = Callable[[Any, Goal], navigation.ControllerLike]


@dataclass
class _Map:
    revision: str
    cmap: Any
    definition_hash: str = ""
    error_estimate: float | None = None  # the solution's certificate (None: an atlas)


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
    # on the base map while the footprint map {ws}~r{R} is solved (services/controller_footprint)
    base_ws: str = ""  # the base workspace driven on ("" when on the goal's own map)
    shrunk: Any = None  # the exact shrunk workspace its safety layer keeps it in
    # its navigation function flat where it stood (services/controller_flat.py)
    atlas_ws: str = ""  # the atlas {ws}~atlas it asked for ("" if none)
    flat_note: str = ""  # why
    flat_checked: Any = None  # the law last checked for flatness
    last_pose_t: float | None = None  # monotonic receive time of the last fresh pose
    last_stamp: tuple[int, int] = (-1, -1)  # (stamp_ns, seq) of the last fresh pose
    goal_t: float = 0.0  # monotonic time the goal was set
    seen_t: float = 0.0  # monotonic time of the last pose or goal (idle TTL)
    position: tuple[float, float] | None = None
    theta: float = 0.0  # heading of the last fresh pose (a unicycle's look-ahead point)
    status_key: tuple[str, str, str | None, str] = ("", "", None, "")
    status_t: float = 0.0
    stale_reported: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)


class ControllerCore(Service):
    """The controller service's state and what every job uses: robot records, the publisher
    thread, commands and statuses, why a robot must stop (services/controller.py)."""

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
        # progressive maps (docs/SERVICES.md): the map revisions the transform services said
        # are coarse ones being refined (newest last, at most 4096); revision -> its estimate
        self._refining: OrderedDict[str, None] = OrderedDict()
        # ws id -> robot id -> (goal, goal's ws) of the route hint last sent for that map
        # (services/controller_maps.py; the fetch thread's own)
        self._hinted: dict[str, dict[str, tuple[Any, str]]] = {}
        # ws id -> the transform's error when its routes were last sent with a map query: a
        # query retried on the same error sends only new routes (services/controller_maps.py)
        self._hint_error: dict[str, str] = {}
        self.route_hints = True  # serve controller --no-route-hints: queries without payload
        # footprint ws id -> its exact shrunk workspace, whose safety grid was built before
        # its map came (services/controller_maps.py, _prebuild_safety)
        self._prebuilt: OrderedDict[str, Any] = OrderedDict()
        # ws id -> the newest AtlasIndex waiting for the atlas fetch running for it (None:
        # one runs, nothing waits); services/controller_maps.py, _fetch_atlas
        self._atlas_busy: dict[str, Any] = {}
        self._estimates: dict[str, float] = {}
        # robot id -> the status note of its re-entry command this step (controller_poses.py,
        # _reentered; confnav/navigation/reentry.py)
        self._reentry_notes: dict[str, str] = {}
        # (key, payload) or a list of them (one control step's messages, in order)
        self._out: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._held = threading.local()  # .msgs: the messages of the step this thread runs
        # (.batch: the commands answering a pose batch, published as one CommandBatch)
        self._step_lock = threading.Lock()  # one pose step at a time (poses, pose batches)
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
        self._status_keys: dict[str, str] = {}  # robot id -> status key
        self.swapped = threading.Event()  # set on each hot swap (tests)
        self.neighbours: Neighbours | None = None  # fleet hook (services/neighbours.py)

    # publishing (one thread, never under a lock) ---------------------------------------
    def _emit(self, key: str, payload: bytes) -> None:
        """Queue a message; the publisher thread sends them in this order. Inside
        :meth:`_hold` the messages are queued together when it ends (one queue operation
        per control step: each one wakes the publisher thread)."""
        held = getattr(self._held, "msgs", None)
        if held is not None:
            held.append((key, payload))
        else:
            self._out.put((key, payload))

    def _hold(self, batch_key: str | None = None, sim_id: str = "") -> None:
        """Collect this thread's messages until :meth:`_release`; with ``batch_key``, the
        commands that answer poses go into one ``CommandBatch`` of simulator ``sim_id`` on
        that key (a step of a pose batch)."""
        self._held.msgs = []
        self._held.batch = None if batch_key is None else _CmdBatch(batch_key, sim_id)

    def _release(self) -> None:
        """Queue the messages collected since :meth:`_hold`, in order (a ``CommandBatch``
        first: each robot's command before its status, as with single commands)."""
        msgs, self._held.msgs = getattr(self._held, "msgs", None), None
        batch, self._held.batch = getattr(self._held, "batch", None), None
        if batch is not None and batch.robot_ids:
            msgs = [(batch.key, batch.payload()), *(msgs or [])]
        if msgs:
            self._out.put(msgs)

    def _send_commands(self) -> None:
        """Publish the ``CommandBatch`` collected so far now, before the statuses of the step
        (:meth:`_defer_statuses`): a robot's command waits for no one's status."""
        batch = getattr(self._held, "batch", None)
        if batch is not None and batch.robot_ids:
            # published from this thread (Zenoh's put gives the GIL up meanwhile): queued, it
            # waited for the publisher thread to get the GIL from this one, busy with the
            # statuses, up to a switch interval (5 ms; p99 4.8-7.5 ms above the steps')
            try:
                self.bus.publish(batch.key, batch.payload())
            except Exception:
                self.count("publish_errors")
                log.exception("publishing on %s failed", batch.key)
            self._held.batch = _CmdBatch(batch.key, batch.sim_id)

    def _defer_statuses(self, on: bool) -> list[tuple[Any, ...]]:
        """From ``on``: :meth:`_status` calls of this thread are kept, not made; off: the kept
        calls, to be made (each robot's command then goes out before its status)."""
        kept: list[tuple[Any, ...]] = getattr(self._held, "statuses", None) or []
        self._held.statuses = [] if on else None
        return kept

    def _publish_loop(self) -> None:
        while True:
            try:
                item = self._out.get(timeout=0.1)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            for key, payload in item if isinstance(item, list) else (item,):
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

    def _outdated(self, r: _Robot) -> str | None:
        """Why the robot's map contradicts the current geometry near it, or None."""
        assert r.goal is not None
        pending = self._pending.get(r.goal.ws_id) or self._pending.get(r.base_ws)
        if pending is None or r.position is None:
            return None
        c = float(pending.workspace.clearance(complex(*r.position)))
        if c >= self.margin:
            return None
        return (
            f"workspace {r.goal.ws_id!r} changed: {c:.3f} m from the new geometry "
            f"(margin {self.margin:g} m); waiting for its map"
        )

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
        self._status_keys.pop(rid, None)
        self.count("robots_forgotten")

    def _blocker(self, r: _Robot) -> tuple[str, str] | None:
        """Why this robot must not move now, or None."""
        if self.require_transform and not self._transform_alive:
            return "transform_service_dead", "no transform service is alive"
        if r.ctrl is None:
            assert r.goal is not None
            if r.ctrl_error:
                return "navigation_error", r.ctrl_error
            err = self._map_errors.get(r.goal.ws_id, NO_ANSWER_YET)
            return "missing_map", err
        if self._pending:
            outdated = self._outdated(r)
            if outdated is not None:
                return "map_outdated", outdated
        return None

    def _map_note(self, r: _Robot) -> str:
        """What the robot drives on, when it is a coarse revision of a map being refined
        or the base map while its footprint map is being solved, or an atlas revision whose
        next chart is still being solved (docs/SLAM.md, "Progressive atlas")."""
        law = r.ctrl
        # a unicycle's look-ahead law wraps the atlas controller that holds (its .controller)
        waiting = getattr(
            law, "waiting", getattr(getattr(law, "controller", None), "waiting", None)
        )
        if isinstance(waiting, int):
            return (
                f"holding for chart {waiting} of the atlas (being solved; the robot goes on "
                "once it is installed)"
            )
        if r.base_ws:
            from confnav.services.controller_footprint import base_note

            return base_note(r)
        if r.atlas_ws:
            return self._flat_note(r)  # type: ignore[attr-defined,no-any-return]
        rev = r.ctrl_revision
        if rev is None or rev not in self._refining:
            return ""
        est = self._estimates.get(rev)
        tail = "" if est is None else f" (estimated error {est:.1e})"
        return f"navigating on a coarse map, refining{tail}"

    def _blocked_status(self, r: _Robot, blocker: tuple[str, str]) -> tuple[str, str, str]:
        """(state, reason, message) of a robot that must not move: a robot whose map is
        being solved holds (``navigating``, what it waits for in the message:
        docs/SERVICES.md, progressive maps); any other blocker stops it with its reason."""
        reason, message = blocker
        if reason == "missing_map" and r.goal is not None and map_being_solved(message):
            return "navigating", "ok", waiting_note(r.goal.ws_id)
        return "stopped", reason, message

    def _block(
        self, r: _Robot, blocker: tuple[str, str], now: float, pose: PoseLike | None = None
    ) -> None:
        """Zero command and the status of :meth:`_blocked_status`."""
        state, reason, message = self._blocked_status(r, blocker)
        if state == "stopped":
            self._stop_robot(r, reason, message, now, pose)
        else:
            self.count("holds_map_being_solved")
            self._publish_cmd(r, 0j, pose)
            self._status(r, state, reason, message, now)

    def _stop_robot(
        self, r: _Robot, reason: str, message: str, now: float, pose: PoseLike | None = None
    ) -> None:
        self.count(f"stops_{reason}")
        self._publish_cmd(r, 0j, pose)
        self._status(r, "stopped", reason, message, now)

    def _publish_cmd(self, r: _Robot, u: complex, pose: PoseLike | None) -> None:
        body = getattr(r.ctrl, "frame", "world") == "body"  # unicycle: u = v + i omega
        batch: _CmdBatch | None = getattr(self._held, "batch", None)
        if batch is not None and pose is not None:  # answers a pose of a pose batch
            batch.robot_ids.append(r.robot_id)
            batch.linear.append((u.real, 0.0) if body else (u.real, u.imag))
            batch.angular.append(u.imag if body else 0.0)
            batch.pose_seq.append(pose.seq)
            batch.pose_stamp_ns.append(pose.stamp_ns)
            batch.map_revision.append(r.ctrl_revision)
            batch.frame.append("body" if body else "world")
            batch.chart.append(getattr(r.ctrl, "active_chart", None))
            self.count("commands")
            return
        # the wire bytes of VelocityCommand written directly (schemas/fast.py: the same bytes
        # as encode(VelocityCommand(...)), 12 -> 2.5 us); our own finite values, no
        # re-validation on the hot path (checked against the model in the tests and by readers)
        payload = velocity_command_json(
            r.robot_id,
            time.time_ns(),
            (u.real, 0.0) if body else (u.real, u.imag),
            u.imag if body else 0.0,
            pose.seq if pose is not None else -1,
            pose.stamp_ns if pose is not None else 0,
            r.ctrl_revision,
            "body" if body else "world",
            getattr(r.ctrl, "active_chart", None),
        )
        key = self._cmd_keys.get(r.robot_id)
        if key is None:
            key = self._cmd_keys[r.robot_id] = self.keys.robot(r.robot_id, "cmd_vel")
        self._emit(key, payload)
        self.count("commands")

    def _status(self, r: _Robot, state: str, reason: str, message: str, now: float) -> None:
        kept = getattr(self._held, "statuses", None)
        if kept is not None:  # a pose batch's step: after its commands (_defer_statuses)
            kept.append((r, state, reason, message, now))
            return
        chart = getattr(r.ctrl, "active_chart", None)
        # a message that differs only in its measured figures ("0.88 m off it") is the same
        # status: repeated once per period, not on every pose (docs/SERVICES.md, "Scale")
        skey = (state, reason, r.ctrl_revision, _FIGURES.sub("#", message) + f"|{chart}")
        if skey == r.status_key and now - r.status_t < self.status_period:
            return
        if skey[:2] != r.status_key[:2]:  # a new state or reason: worth a line in the log
            log.info("robot %r: %s (%s)%s", r.robot_id, state, reason,
                     f": {message}" if message else "")  # fmt: skip
        t = now
        if skey != r.status_key:  # the periodic repeats of robots that changed state in one
            # step are spread over the period (each robot at its own phase), so that no step
            # publishes every robot's status at once (docs/SERVICES.md, "Scale")
            t -= (zlib.crc32(r.robot_id.encode()) % 1024) / 1024 * self.status_period
        r.status_key, r.status_t = skey, t
        dist = None
        if r.position is not None and r.goal is not None:
            dx, dy = r.position[0] - r.goal.goal[0], r.position[1] - r.goal.goal[1]
            dist = (dx * dx + dy * dy) ** 0.5
        if dist is not None and not math.isfinite(dist):  # |x| near 1e154 or more: no figure
            dist = None
        # the wire bytes of RobotStatus written directly (schemas/fast.py: the same bytes as
        # encode(RobotStatus(...)); our own values: a state and reason of the schema's)
        payload = robot_status_json(
            r.robot_id,
            time.time_ns(),
            state,
            reason,
            message[:4000],
            r.goal.ws_id if r.goal else None,
            r.ctrl_revision,
            r.position,
            dist,
            chart,
        )
        key = self._status_keys.get(r.robot_id)
        if key is None:
            key = self._status_keys[r.robot_id] = self.keys.robot(r.robot_id, "status")
        self._emit(key, payload)

    def robot_state(self, rid: str) -> tuple[str, str] | None:
        """(state, reason) last published for a robot (tests)."""
        with self._lock:
            r = self._robots.get(rid)
        return None if r is None else (r.status_key[0], r.status_key[1])
