"""Simulator service: kinematic robots driven by the last ``cmd_vel``: points ``x' = u``
(world-frame commands) or unicycles (body-frame twists ``v``, ``omega``, moved along exact
arcs); a robot with a radius collides as a disk and reports its body's clearance.

Robots come from the config or from ``SpawnRequest`` on ``{prefix}/sim/{sim}/spawn``. Every
tick (``rate_hz``, sim time step ``1/rate_hz``; ``time_scale`` > 1 runs faster than real time)
each robot moves by ``u * dt`` with its last command, a timestamped ``Pose`` is published on
``{prefix}/robot/{r}/pose``, and leaving the free space (``Workspace.clearance`` <= 0, the
core's exact polygon distance) is reported once as a ``CollisionEvent``; a collided robot stays
where it hit. ``SimControl`` on ``{prefix}/sim/{sim}/control`` pauses, resumes, resets (back to
the spawn pose) or removes robots. Workspaces for the collision check come from files or from
``{prefix}/ws/*/definition``.

A command is applied only while it is current, so that a lagging controller cannot drive a
robot on where it was long ago: it stops (zero) once no command came for ``cmd_timeout`` wall
seconds, and a command that answers a pose (``pose_seq`` >= 0) is applied only until
``max_cmd_age`` sim seconds after that pose; a command answering a pose older than that, one
from before a reset (the robot was moved), or one that was never published is not applied.
Commands go through a bounded latest-per-robot queue (a backlog of stale commands is
skipped, counted as ``commands_superseded``). With ``pose_batch`` the poses of a step go out as
one ``PoseBatch`` on ``{prefix}/sim/{sim}/poses`` instead (controllers answer with one
``CommandBatch`` on ``{prefix}/sim/{sim}/cmd_vel``, whose entries are judged as the
``VelocityCommand`` each stands for). The budget: the plant moves at most
``max_cmd_age * |u|`` on a command away from the pose it was computed for.
"""

from __future__ import annotations

import argparse
import cmath
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from confnav.schemas import (
    CollisionEvent,
    CommandBatch,
    DecodeError,
    Goal,
    MapQuery,
    Pose,
    PoseBatch,
    RouteHint,
    SimControl,
    SpawnRequest,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.schemas.messages import MAX_ROUTES
from confnav.services.bus import Bus
from confnav.services.definitions import (
    ask_for_maps,
    footprint_of,
    load_definition,
    parse_sources,
    workspace_of,
)
from confnav.services.keys import KeyError_, Keys, validate_id
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal
from scipy.spatial import cKDTree

from confnav.errors import fmt_point
from confnav.maps.footprint import derived_ws_id
from confnav.navigation import defaults
from confnav.navigation.fleet import swept_min_distance
from confnav.navigation.sim import _chord_check
from confnav.navigation.unicycle import step_exact

log = logging.getLogger(__name__)


@dataclass
class SimRobot:
    robot_id: str
    ws_id: str
    z: complex
    theta: float = 0.0
    start: complex = 0j
    start_theta: float = 0.0
    u: complex = 0j
    cmd_t: float = -1e18  # monotonic time of the last command
    cmd_pose_seq: int = -1  # the pose the held command answers (-1: none given)
    seq: int = 0
    # sim time of the latest published poses, seq - len(pose_t) ... seq - 1 (cleared on reset;
    # as many as are younger than max_cmd_age: older ones cannot date an applicable command)
    pose_t: deque[float] = field(default_factory=deque)
    collided: bool = False
    sim_time: float = 0.0
    radius: float = 0.0  # body disk (m): collisions and clearances are the body's
    drive: str = "holonomic"  # "unicycle": moves only by body-frame twists
    twist: tuple[float, float] | None = None  # (v, omega) of the last body-frame command


@dataclass(frozen=True)
class RobotSpec:
    """One ``--robot`` item: where a robot starts and what body it has."""

    rid: str
    ws: str
    x: float
    y: float
    theta: float = 0.0
    radius: float = 0.0
    drive: str = "holonomic"


ROBOT_SPEC = "ID=WS:X,Y[,THETA][:r=RADIUS][:drive=unicycle]"


class SimulatorService(Service):
    """See the module docstring. ``robots``: the robots at start (:class:`RobotSpec`, or
    (robot id, ws id, x, y) tuples: points)."""

    name = "simulator"

    def __init__(
        self,
        bus: Bus,
        keys: Keys | None = None,
        sim_id: str = "sim",
        robots: list[RobotSpec] | list[tuple[str, str, float, float]] | None = None,
        sources: dict[str, str] | None = None,
        rate_hz: float = 50.0,
        time_scale: float = 1.0,
        cmd_timeout: float = 0.25,
        health_period: float = 1.0,
        max_cmd_age: float = defaults.HOLD_TIME,
        pose_batch: bool = False,
        maps_ahead: bool = True,
    ) -> None:
        super().__init__(bus, keys, health_period)
        self.sim_id = validate_id(sim_id, "simulator id")
        #: ask the transform service for the footprint maps of the robots given at start
        #: (:meth:`_ask_maps`); ``serve simulator --no-maps-ahead``: on first use only
        self.maps_ahead = maps_ahead
        # one PoseBatch per step on {prefix}/sim/{sim}/poses instead of a Pose per robot
        self.pose_batch = pose_batch
        self.rate_hz = rate_hz
        self.time_scale = time_scale
        self.cmd_timeout = cmd_timeout
        self.max_cmd_age = max_cmd_age
        self.paused = False
        self._lock = threading.Lock()
        self._robots: dict[str, SimRobot] = {}
        self._workspaces: dict[str, Any] = {}
        self._sources = dict(sources or {})
        self.collisions: list[CollisionEvent] = []
        self._touching: set[tuple[str, str]] = set()  # robot pairs in contact (sorted ids)
        self.ticks = 0
        for item in robots or []:
            spec = item if isinstance(item, RobotSpec) else RobotSpec(*item)
            self.spawn_robot(
                spec.rid,
                spec.ws,
                complex(spec.x, spec.y),
                spec.theta,
                radius=spec.radius,
                drive=spec.drive,
            )

    def spawn_robot(
        self,
        rid: str,
        ws_id: str,
        z: complex,
        theta: float = 0.0,
        radius: float = 0.0,
        drive: str = "holonomic",
    ) -> None:
        validate_id(rid, "robot id")
        validate_id(ws_id, "workspace id")
        memory = math.ceil(self.max_cmd_age * self.rate_hz) + 2
        with self._lock:
            self._robots[rid] = SimRobot(
                rid,
                ws_id,
                z,
                theta,
                z,
                theta,
                radius=radius,
                drive=drive,
                pose_t=deque(maxlen=memory),
            )
        log.info("robot %r spawned at %s on %r", rid, fmt_point(z), ws_id)

    def _start(self) -> None:
        for ws_id, src in self._sources.items():
            try:
                self._workspaces[ws_id] = workspace_of(load_definition(ws_id, src))
            except Exception as exc:
                log.error("cannot load workspace %r from %s: %s", ws_id, src, exc)
        k = self.keys
        self._handles.append(self.bus.subscribe(k.any_ws("definition"), self._on_definition))
        self._handles.append(
            self.bus.subscribe_latest(k.any_robot("cmd_vel"), self._on_cmds, self._cmds_dropped)
        )
        self._handles.append(  # a controller's answers to a PoseBatch (any simulator mode)
            self.bus.subscribe(k.sim(self.sim_id, "cmd_vel"), self._on_cmd_batch)
        )
        self._handles.append(self.bus.subscribe(k.sim(self.sim_id, "spawn"), self._on_spawn))
        self._handles.append(self.bus.subscribe(k.sim(self.sim_id, "control"), self._on_control))
        self.spawn(self._loop, "loop")
        if self.maps_ahead:
            self.spawn(self._ask_maps, "maps")

    def _ask_maps(self) -> None:
        """The robots given at start with a body: ask the transform service for the map of
        each one's footprint ``{ws}~r{R}`` (R: its radius, plus the library's look-ahead for a
        unicycle, as for a ``SpawnRequest``), so that it is solved before their goals come
        (docs/SERVICES.md, "ahead of use"; the ROS 2 bridge does the same for its robots).
        The query carries each robot's start (its steered point, as the controller's route
        hints: a route from the start to itself), so that an atlas solves the start cells
        first and counts as one robots wait for (docs/SLAM.md "Background atlases")."""
        lookahead = float(Goal.model_fields["lookahead"].default)
        with self._lock:
            robots = list(self._robots.values())
        routes: dict[str, list[RouteHint]] = {}
        for r in robots:
            radius = footprint_of(r.radius, r.drive, lookahead)
            if radius <= 0:
                continue
            z = r.z + (lookahead * cmath.exp(1j * r.theta) if r.drive == "unicycle" else 0)
            start = (float(z.real), float(z.imag))
            hint = RouteHint(robot_id=r.robot_id, start=start, goal=start)
            routes.setdefault(derived_ws_id(r.ws_id, radius), []).append(hint)
        payloads = {
            ws: encode(MapQuery(stamp_ns=time.time_ns(), routes=hints[:MAX_ROUTES]))
            for ws, hints in routes.items()
        }
        if routes:
            ask_for_maps(self.bus, self.keys, list(routes), self._stop, payloads=payloads)

    def health_detail(self) -> tuple[str, str]:
        with self._lock:
            missing = sorted({r.ws_id for r in self._robots.values()} - set(self._workspaces))
        if missing:
            return "degraded", f"no workspace for collision checks: {missing}"
        return "ok", "paused" if self.paused else ""

    # inputs ----------------------------------------------------------------------------
    def _on_definition(self, key: str, payload: bytes) -> None:
        self.count("definitions_received")
        try:
            ws_id = self.keys.parse(key).ident
            defn = decode(WorkspaceDefinition, payload)
            if defn.ws_id != ws_id:
                raise DecodeError("invalid_input", "ws id differs from key")
            ws = workspace_of(defn)
        except Exception as exc:
            self.count("rejected")
            log.warning("rejected definition on %s: %s", key, exc)
            return
        with self._lock:
            self._workspaces[ws_id] = ws

    def _on_cmds(self, items: list[tuple[str, bytes]]) -> None:
        for key, payload in items:
            self._on_cmd(key, payload)

    def _cmds_dropped(self, n: int) -> None:
        self.count("commands_received", n)
        self.count("commands_superseded", n)

    def pose_age(self, r: SimRobot, pose_seq: int) -> float | None:
        """Sim seconds since the pose ``pose_seq`` of ``r`` (None: not a pose published since
        the last reset and within memory, or not published yet). Call under the lock."""
        i = pose_seq - (r.seq - len(r.pose_t))
        if not 0 <= i < len(r.pose_t):
            return None
        return r.sim_time - r.pose_t[i]

    def _current(self, r: SimRobot, now: float) -> bool:
        """Whether the held command of ``r`` may still be applied (see the module docstring)."""
        if now - r.cmd_t > self.cmd_timeout:
            return False
        if r.cmd_pose_seq < 0:
            return True
        age = self.pose_age(r, r.cmd_pose_seq)
        return age is not None and age <= self.max_cmd_age

    def _on_cmd(self, key: str, payload: bytes) -> None:
        """A command counts only on a robot's exact key and naming that robot: a put on
        ``{prefix}/robot/*/cmd_vel`` (which reaches this subscriber too) or with another
        robot's id is rejected; so is one answering a pose that is not current (stale)."""
        self.count("commands_received")
        try:
            rid = self.keys.parse(key).ident  # a wildcard chunk is not an id: rejected
            cmd = decode(VelocityCommand, payload)
            if cmd.robot_id != rid:
                raise DecodeError("invalid_input", f"command on {key} names {cmd.robot_id!r}")
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.debug("rejected command on %s: %s", key, exc)
            return
        with self._lock:
            self._apply(rid, cmd.linear, cmd.angular, cmd.frame, cmd.pose_seq, time.monotonic())

    def _on_cmd_batch(self, key: str, payload: bytes) -> None:
        """A ``CommandBatch`` (a controller's answers to this simulator's ``PoseBatch``): each
        entry is judged exactly as the ``VelocityCommand`` it stands for."""
        try:
            batch = decode(CommandBatch, payload)
            if batch.sim_id != self.sim_id:
                raise DecodeError("invalid_input", f"batch on {key} names {batch.sim_id!r}")
        except DecodeError as exc:
            self.count("rejected")
            log.debug("rejected command batch on %s: %s", key, exc)
            return
        self.count("commands_received", len(batch.robot_ids))
        now = time.monotonic()
        with self._lock:
            for rid, lin, ang, frame, seq in zip(
                batch.robot_ids, batch.linear, batch.angular, batch.frame, batch.pose_seq,
                strict=True,
            ):  # fmt: skip
                self._apply(rid, lin, ang, frame, seq, now)

    def _apply(
        self,
        rid: str,
        linear: tuple[float, float],
        angular: float,
        frame: str,
        pose_seq: int,
        now: float,
    ) -> None:
        """Hold a valid command for robot ``rid`` (see the module docstring). Under the lock."""
        r = self._robots.get(rid)
        if r is None:
            self.count("commands_unknown_robot")
            return
        u = complex(linear[0], linear[1])
        if frame == "world" and r.drive == "unicycle" and u != 0j:
            self.count("rejected")  # a differential drive cannot move sideways
            return
        if pose_seq >= 0:
            age = self.pose_age(r, pose_seq)
            if age is None or age > self.max_cmd_age or pose_seq < r.cmd_pose_seq:
                self.count("commands_stale")  # old, from before a reset, or reordered
                return
        r.u = u if frame == "world" else 0j
        r.twist = (linear[0], angular) if frame == "body" else None
        r.cmd_t = now
        r.cmd_pose_seq = pose_seq
        self.count("commands")

    def _on_spawn(self, key: str, payload: bytes) -> None:
        self.count("spawns_received")
        try:
            req = decode(SpawnRequest, payload)
        except DecodeError as exc:
            self.count("rejected")
            log.warning("rejected spawn request: %s", exc)
            return
        self.spawn_robot(
            req.robot_id,
            req.ws_id,
            complex(*req.position),
            req.theta,
            req.robot_radius,
            req.drive,
        )

    def _on_control(self, key: str, payload: bytes) -> None:
        self.count("controls_received")
        try:
            ctl = decode(SimControl, payload)
        except DecodeError as exc:
            self.count("rejected")
            log.warning("rejected control: %s", exc)
            return
        with self._lock:
            targets = [r for r in self._robots.values() if ctl.robot_id in (None, r.robot_id)]
            if ctl.action == "pause":
                self.paused = True
            elif ctl.action == "resume":
                self.paused = False
            elif ctl.action == "reset":
                for r in targets:
                    r.z, r.theta, r.u, r.collided = r.start, r.start_theta, 0j, False
                    r.twist = None
                    r.cmd_t, r.cmd_pose_seq = -1e18, -1
                    r.pose_t.clear()  # commands answering earlier poses are not applied
            elif ctl.action == "remove":
                for r in targets:
                    self._robots.pop(r.robot_id, None)
        log.info("simulator %s: %s %s", self.sim_id, ctl.action, ctl.robot_id or "all")

    # integration -------------------------------------------------------------------------
    def _integrate(self, robots: list[SimRobot], dt: float, now: float) -> list[CollisionEvent]:
        """Move the robots by their current commands; the new collisions. Under the lock.

        A held command is integrated exactly (a straight segment ``u dt``; a unicycle's arc,
        :func:`~confnav.navigation.unicycle.step_exact`), and contacts are checked along the
        step, not at its ends: walls with the core's chord check
        (:func:`confnav.navigation.sim._chord_check`, the exact clearance is 1-Lipschitz),
        robots with the exact closest approach of the two centres over the step
        (:func:`confnav.navigation.fleet.swept_min_distance`; a unicycle's axle along its
        chord)."""
        hits: list[CollisionEvent] = []
        by_ws: dict[str, list[tuple[SimRobot, complex]]] = {}
        for r in robots:
            z0 = r.z
            if not r.collided:
                fresh = self._current(r, now)
                u = r.u if fresh else 0j
                if fresh and r.twist is not None:  # body-frame twist: exact arc (unicycle)
                    z1, th1 = step_exact(r.z, r.theta, r.twist[0], r.twist[1], dt)
                    r.z, r.theta = complex(z1), float(th1)
                elif u != 0j:
                    r.z += u * dt
                    r.theta = math.atan2(u.imag, u.real)
                r.sim_time += dt
            by_ws.setdefault(r.ws_id, []).append((r, z0))
        stamp = time.time_ns()
        for ws_id, group in by_ws.items():
            ws = self._workspaces.get(ws_id)
            moving = [(r, z0) for r, z0 in group if not r.collided]
            if ws is not None and moving:
                hits += self._wall_hits(ws, ws_id, moving, stamp)
        # robots of one floor: a derived workspace ({ws}~r0.2) is the same floor
        floors: dict[str, list[tuple[SimRobot, complex]]] = {}
        for ws_id, group in by_ws.items():
            floors.setdefault(ws_id.split("~", 1)[0], []).extend(group)
        for group in floors.values():
            hits += self._robot_hits(group, stamp)
        return hits

    def _wall_hits(
        self, ws: Any, ws_id: str, group: list[tuple[SimRobot, complex]], stamp: int
    ) -> list[CollisionEvent]:
        z0 = np.array([z for _, z in group], dtype=np.complex128)
        z1 = np.array([r.z for r, _ in group], dtype=np.complex128)
        rad = np.array([r.radius for r, _ in group], dtype=np.float64)
        c1 = np.asarray(ws.clearance(z1), dtype=float) - rad  # the body's clearance
        hit = ~(c1 > 0.0)  # also NaN
        low = c1.copy()
        moved = (z1 != z0) & ~hit
        for rv in np.unique(rad[moved]):
            idx = np.flatnonzero(moved & (rad == rv))
            c0 = np.asarray(ws.clearance(z0[idx]), dtype=float) - rv

            def body(q: Any, rv: float = float(rv)) -> Any:
                return np.asarray(ws.clearance(q), dtype=float) - rv

            h, lo = _chord_check(z0[idx], z1[idx], c0, c1[idx], body)
            hit[idx] |= h
            low[idx] = np.minimum(low[idx], lo)
        out = []
        for (r, _), bad, c in zip(group, hit, low, strict=True):
            if bad:
                r.collided = True
                out.append(
                    CollisionEvent(
                        robot_id=r.robot_id,
                        ws_id=ws_id,
                        stamp_ns=stamp,
                        position=(r.z.real, r.z.imag),
                        clearance=min(float(c), 0.0) if math.isfinite(c) else -1.0,
                    )
                )
        return out

    def _robot_hits(
        self, group: list[tuple[SimRobot, complex]], stamp: int
    ) -> list[CollisionEvent]:
        """Robot-robot contacts along the step (swept disks); each new contact once, as one
        event per robot naming the other; both robots stop where they touched.  Robots
        without a radius are points, not bodies: they touch nothing."""
        z0 = np.array([z for _, z in group], dtype=np.complex128)
        z1 = np.array([r.z for r, _ in group], dtype=np.complex128)
        rad = np.array([r.radius for r, _ in group], dtype=np.float64)
        mid = 0.5 * (z0 + z1)
        reach = 2 * float(rad.max()) + float(np.abs(z1 - z0).max()) + 1e-9
        pairs = cKDTree(np.column_stack([mid.real, mid.imag])).query_pairs(
            reach, output_type="ndarray"
        )
        ids = [r.robot_id for r, _ in group]
        touching: set[tuple[str, str]] = set()
        out: list[CollisionEvent] = []
        if pairs.size:
            a, b = pairs[:, 0], pairs[:, 1]
            dmin, s = swept_min_distance(z0[a], z1[a], z0[b], z1[b])
            gap = dmin - rad[a] - rad[b]
            for i, j, g, f in zip(a, b, gap, s, strict=True):
                if not g <= 0 or rad[i] <= 0 or rad[j] <= 0:  # a point is not a body
                    continue
                key = (min(ids[i], ids[j]), max(ids[i], ids[j]))
                touching.add(key)
                if key in self._touching:
                    continue
                for k, other in ((i, j), (j, i)):
                    r = group[k][0]
                    at = z0[k] + f * (z1[k] - z0[k])
                    r.collided = True
                    r.z = complex(at)  # stays where it touched
                    out.append(
                        CollisionEvent(
                            robot_id=r.robot_id,
                            ws_id=r.ws_id,
                            stamp_ns=stamp,
                            position=(at.real, at.imag),
                            clearance=float(g),
                            other_robot_id=ids[other],
                        )
                    )
        # pairs of this floor that are apart again may touch anew later
        mine = set(ids)
        self._touching = {p for p in self._touching if not (p[0] in mine and p[1] in mine)}
        self._touching |= touching
        return out

    def step(self, dt: float) -> None:
        """Advance every robot by ``dt`` sim seconds and publish the poses (robot state is
        changed under the lock: a command is judged against the poses actually published)."""
        now = time.monotonic()
        hits: list[CollisionEvent] = []
        out: list[tuple[str, Pose]] = []
        with self._lock:
            robots = list(self._robots.values())
            if not self.paused:
                hits = self._integrate(robots, dt, now)
            stamp = time.time_ns()
            for r in robots:
                out.append(
                    (
                        r.robot_id,
                        Pose(
                            robot_id=r.robot_id,
                            stamp_ns=stamp,
                            seq=r.seq,
                            x=r.z.real,
                            y=r.z.imag,
                            theta=r.theta,
                        ),
                    )
                )
                r.seq += 1
                r.pose_t.append(r.sim_time)
        if self.pose_batch and out:  # one message for the step (docs/SERVICES.md, "Scale")
            batch = PoseBatch(
                sim_id=self.sim_id,
                stamp_ns=stamp,
                robot_ids=[p.robot_id for _, p in out],
                stamps_ns=[p.stamp_ns for _, p in out],
                seq=[p.seq for _, p in out],
                x=[p.x for _, p in out],
                y=[p.y for _, p in out],
                theta=[p.theta for _, p in out],
            )
            self.bus.publish(self.keys.sim(self.sim_id, "poses"), encode(batch))
        else:
            for rid, pose in out:
                self.bus.publish(self.keys.robot(rid, "pose"), encode(pose))
        self.count("poses", len(out))
        for ev in hits:
            log.warning("robot %r collided at %s", ev.robot_id, ev.position)
            self.collisions.append(ev)
            self.bus.publish(self.keys.robot(ev.robot_id, "collision"), encode(ev))
        self.ticks += 1

    def _loop(self) -> None:
        dt = 1.0 / self.rate_hz
        period = dt / self.time_scale
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                self.step(dt)
            except Exception:
                log.exception("simulation step failed")
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -10 * period:  # fell far behind: do not try to catch up in a burst
                next_t = time.monotonic()
            elif delay > 0 and self._stop.wait(delay):
                return

    def positions(self) -> dict[str, complex]:
        with self._lock:
            return {rid: r.z for rid, r in self._robots.items()}


def parse_robots(items: list[str]) -> list[RobotSpec]:
    """``ID=WS:X,Y[,THETA][:r=RADIUS][:drive=holonomic|unicycle]`` items (m, rad).

    Without ``r=`` a robot is a point (it touches nothing); a robot spawned by a
    ``SpawnRequest`` carries the same fields."""
    return [_parse_robot(item) for item in items]


def _parse_robot(item: str) -> RobotSpec:
    def bad(why: str) -> SystemExit:
        return SystemExit(f"--robot expects {ROBOT_SPEC}, got {item!r}: {why}")

    rid, eq, rest = item.partition("=")
    ws, colon, tail = rest.partition(":")
    if not (eq and colon and rid and ws):
        raise bad("no ID=WS: part")
    xy, *options = tail.split(":")
    try:
        coords = [float(v) for v in xy.split(",")]
    except ValueError:
        raise bad(f"{xy!r} is not X,Y[,THETA]") from None
    if len(coords) not in (2, 3) or not all(math.isfinite(c) for c in coords):
        raise bad(f"{xy!r} is not X,Y[,THETA] with finite numbers")
    radius, drive = 0.0, "holonomic"
    for opt in options:
        key, _, value = opt.partition("=")
        if key == "r":
            try:
                radius = float(value)
            except ValueError:
                raise bad(f"radius {value!r} is not a number") from None
            if not (math.isfinite(radius) and radius >= 0.0):
                raise bad(f"radius {value!r} must be finite and >= 0")
        elif key == "drive" and value in ("holonomic", "unicycle"):
            drive = value
        else:
            raise bad(f"unknown option {opt!r} (r=RADIUS or drive=holonomic|unicycle)")
    theta = coords[2] if len(coords) == 3 else 0.0
    return RobotSpec(rid, ws, coords[0], coords[1], theta, radius, drive)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("simulator", help="run the simulator service")
    add_zenoh_args(p)
    p.add_argument("--sim-id", default="sim")
    p.add_argument(
        "--robot",
        action="append",
        default=[],
        metavar=ROBOT_SPEC,
        help="a robot at start (repeatable): heading THETA in rad, 0 if left out; body radius "
        "r in m, 0 if left out (a point that touches nothing); drive holonomic if left out",
    )
    p.add_argument("--workspace", action="append", default=[], metavar="ID=PATH")
    p.add_argument("--rate", type=float, default=50.0, help="simulated steps per second, Hz")
    p.add_argument("--time-scale", type=float, default=1.0, help=">1: faster than real time")
    p.add_argument("--cmd-timeout", type=float, default=0.25, help="s without command -> stop")
    p.add_argument(
        "--max-cmd-age",
        type=float,
        default=defaults.HOLD_TIME,
        help="sim s after the pose a command answers -> stop",
    )
    p.add_argument(
        "--pose-batch",
        action="store_true",
        help="publish one PoseBatch per step on {prefix}/sim/{sim}/poses instead of a Pose per "
        "robot (controllers answer with one CommandBatch; docs/SERVICES.md, Scale)",
    )
    p.add_argument(
        "--maps-ahead",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="ask the transform service for the footprint map {ws}~r{R} of every --robot with "
        "a body at start, so that it is solved before its goal (the default); "
        "--no-maps-ahead: solved when the first goal asks for it",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    robots = parse_robots(args.robot)
    sources = parse_sources(args.workspace)
    return run_until_signal(
        lambda bus, keys: SimulatorService(
            bus,
            keys,
            args.sim_id,
            robots,
            sources,
            rate_hz=args.rate,
            time_scale=args.time_scale,
            cmd_timeout=args.cmd_timeout,
            max_cmd_age=args.max_cmd_age,
            pose_batch=args.pose_batch,
            maps_ahead=args.maps_ahead,
        ),
        args,
    )
