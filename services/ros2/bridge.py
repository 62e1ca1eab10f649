"""``confnav serve ros2``: a ROS 2 node on Zenoh (rmw_zenoh's wire format, no ROS installed)
that translates between ROS 2 topics and confnav's keys. It navigates nothing itself.

Per robot (id ``r``, ROS namespace ``/ns``, workspace ``ws``):

- ``/ns/odom`` (``nav_msgs/msg/Odometry``; or ``PoseWithCovarianceStamped`` from AMCL, or
  ``PoseStamped``) -> ``{prefix}/robot/r/pose`` (``Pose``; yaw from the quaternion);
- ``/ns/goal_pose`` (``geometry_msgs/msg/PoseStamped``) -> ``{prefix}/robot/r/goal`` (``Goal``
  with the bridge's navigation parameters);
- ``{prefix}/robot/r/cmd_vel`` (``VelocityCommand``, workspace frame) -> ``/ns/cmd_vel``
  (``geometry_msgs/msg/Twist`` or ``TwistStamped``), in the robot's body frame (rotated by
  the last pose's yaw: a holonomic base) or, with ``cmd_frame="world"``, unrotated.

The workspace frame is the frame of the poses (``map`` for AMCL, ``odom`` for odometry);
there is no TF lookup, so a goal in another frame is rejected (counted, logged).

A map topic (``nav_msgs/msg/OccupancyGrid``) is subscribed when configured and published as a
``WorkspaceDefinition`` through the occupancy-grid import (``confnav.maps.occupancy``). Without that
module the bridge says so in its health (state ``degraded``, detail "map import not
available") and a log line, and publishes nothing for the map.

Key styles: ``rmw_zenoh`` (default): data keys ``<domain>/<topic>/<dds type>/<RIHS01 hash>``,
rmw_zenoh's attachment on every sample, and liveliness tokens for the node, its publishers and
subscriptions (see :mod:`.wire`), so ``ros2 topic list`` / ``echo`` on an rmw_zenoh system see
the bridge. ``ros2dds``: the zenoh-bridge-ros2dds keys ``<namespace>/<topic>`` with plain CDR
payloads, no attachment and no tokens (that bridge does the discovery on the DDS side).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal

import numpy as np
import zenoh
from confnav.schemas import (
    DecodeError,
    Goal,
    Pose,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.bus import Bus
from confnav.services.definitions import definition_of
from confnav.services.keys import KeyError_, Keys, validate_id
from confnav.services.ros2 import codec, wire
from confnav.services.ros2.codec import PoseKind
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal

from confnav.navigation import defaults

_GOAL_FIELDS = Goal.model_fields

log = logging.getLogger(__name__)

KeyStyle = Literal["rmw_zenoh", "ros2dds"]
MapImport = Callable[[codec.Grid, str], WorkspaceDefinition]
"""(grid, workspace id) -> definition; ``"auto"``: the occupancy-grid import if present."""
QUEUE_SIZE = 1024  # ROS samples waiting for the worker; beyond this the oldest are dropped


@dataclass(frozen=True)
class RobotSpec:
    """A robot: confnav id, its workspace and its ROS namespace (default ``/<id>``)."""

    robot_id: str
    ws_id: str
    namespace: str = ""

    @property
    def ns(self) -> str:
        return self.namespace or "/" + self.robot_id

    @classmethod
    def parse(cls, text: str) -> RobotSpec:
        """``ID=WS`` or ``ID=WS@/namespace``."""
        rid, sep, rest = text.partition("=")
        if not sep or not rest:
            raise ValueError(f"robot {text!r}: expected ID=WS or ID=WS@/namespace")
        ws, _, ns = rest.partition("@")
        spec = cls(validate_id(rid, "robot id"), validate_id(ws, "workspace id"), ns)
        wire.resolve(spec.ns, "cmd_vel")  # raises on an invalid namespace
        return spec


@dataclass(frozen=True)
class BridgeConfig:
    """What the bridge speaks; see the module docstring."""

    robots: tuple[RobotSpec, ...]
    domain_id: int = 0
    key_style: KeyStyle = "rmw_zenoh"
    node_name: str = "confnav_bridge"
    pose_topic: str = "odom"
    pose_kind: PoseKind = "odometry"
    goal_topic: str = "goal_pose"
    cmd_topic: str = "cmd_vel"
    cmd_stamped: bool = False
    cmd_frame: Literal["body", "world"] = "body"
    base_frame: str = "base_link"
    map_topic: str | None = None
    map_ws: str | None = None
    navfn: Literal["harmonic", "kr"] = defaults.NAVFN
    gain: float = defaults.GAIN
    v_max: float = defaults.V_MAX
    tolerance: float = defaults.GOAL_TOL
    #: ``unicycle``: differential-drive bases (Goal.drive): the controller then sends body
    #: twists (linear.x, angular.z) that pass through unrotated; a holonomic base gets the
    #: workspace-frame command rotated into its body frame.
    drive: Literal["holonomic", "unicycle"] = "holonomic"
    robot_radius: float = 0.0
    lookahead: float = _GOAL_FIELDS["lookahead"].default
    omega_max: float = _GOAL_FIELDS["omega_max"].default


@dataclass
class _Endpoint:
    """One ROS publisher or subscription: its topic, type, data key and (rmw_zenoh) token."""

    topic: str
    ros_type: str
    key: str
    token: str | None
    gid: bytes
    publisher: Any = None
    seq: int = 0


@dataclass
class _RobotState:
    spec: RobotSpec
    cmd: _Endpoint
    yaw: float | None = None
    frame: str | None = None
    seq: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class Ros2Bridge(Service):
    """See the module docstring. ``session`` is the Zenoh session for the ROS side (it needs
    attachments and tokens on keys outside the confnav prefix); ``bus`` the confnav side;
    ``map_import`` turns a received OccupancyGrid into a definition (None: maps are not
    converted)."""

    name = "ros2"

    def __init__(
        self,
        bus: Bus,
        session: zenoh.Session,
        config: BridgeConfig,
        keys: Keys | None = None,
        health_period: float = 1.0,
        map_import: MapImport | Literal["auto"] | None = "auto",
    ) -> None:
        super().__init__(bus, keys, health_period)
        if not config.robots:
            raise ValueError("the ROS 2 bridge needs at least one robot")
        self.session = session
        self.config = config
        self._zid = wire.zid_chunk(str(session.info.zid()))
        self._next_id = 1  # entity ids; 0 is the node (rmw_node_data.cpp: nid = id)
        self._robots: dict[str, _RobotState] = {}
        self._ros: list[Any] = []  # zenoh publishers, subscribers, tokens
        self._queue: queue.Queue[tuple[Callable[[bytes], None], bytes]] = queue.Queue(QUEUE_SIZE)
        self._map_import = _find_map_import() if map_import == "auto" else map_import
        self._map_problem = ""

    # ROS side -----------------------------------------------------------------------------
    def _endpoint(
        self, kind: wire.EntityKind, topic: str, ros_type: str, qos: wire.QoS
    ) -> _Endpoint:
        c = self.config
        type_hash = codec.type_hash(ros_type)
        if c.key_style == "ros2dds":
            return _Endpoint(topic, ros_type, wire.ros2dds_key(topic), None, bytes(wire.GID_SIZE))
        info = wire.TopicInfo(topic, ros_type, type_hash, qos)
        token = wire.liveliness_token(
            c.domain_id, self._zid, 0, self._next_id, kind, "/", c.node_name, info
        )
        self._next_id += 1
        key = wire.topic_key(c.domain_id, topic, ros_type, type_hash)
        return _Endpoint(topic, ros_type, key, token, wire.entity_gid(token))

    def _declare_token(self, token: str | None) -> None:
        if token is not None:
            self._ros.append(self.session.liveliness().declare_token(token))

    def _publisher(self, topic: str, ros_type: str) -> _Endpoint:
        ep = self._endpoint(wire.EntityKind.PUBLISHER, topic, ros_type, wire.DEFAULT_QOS)
        ep.publisher = self.session.declare_publisher(ep.key)
        self._ros.append(ep.publisher)
        self._declare_token(ep.token)
        return ep

    def _subscription(
        self, topic: str, ros_type: str, qos: wire.QoS, handler: Callable[[bytes], None]
    ) -> None:
        ep = self._endpoint(wire.EntityKind.SUBSCRIPTION, topic, ros_type, qos)
        # any type hash: a sender with another (or no) hash of the same type still arrives
        keyexpr = ep.key.rsplit("/", 1)[0] + "/*" if ep.token is not None else ep.key

        def on_sample(sample: zenoh.Sample) -> None:  # Zenoh thread: enqueue only
            item = (handler, sample.payload.to_bytes())
            try:
                self._queue.put_nowait(item)
            except queue.Full:
                self.count("ros_dropped")

        self._ros.append(self.session.declare_subscriber(keyexpr, on_sample))
        self._declare_token(ep.token)

    def _put(self, ep: _Endpoint, payload: bytes) -> None:
        if ep.token is None:  # ros2dds: plain CDR
            ep.publisher.put(payload)
            return
        ep.seq += 1
        att = wire.Attachment(ep.seq, time.time_ns(), ep.gid)
        ep.publisher.put(payload, attachment=att.encode())

    # lifecycle ----------------------------------------------------------------------------
    def _start(self) -> None:
        c = self.config
        if c.key_style == "rmw_zenoh":
            node = wire.liveliness_token(
                c.domain_id, self._zid, 0, 0, wire.EntityKind.NODE, "/", c.node_name
            )
            self._declare_token(node)
        cmd_type = codec.TWIST_STAMPED if c.cmd_stamped else codec.TWIST
        for spec in c.robots:
            cmd = self._publisher(wire.resolve(spec.ns, c.cmd_topic), cmd_type)
            state = self._robots[spec.robot_id] = _RobotState(spec, cmd)
            self._subscription(
                wire.resolve(spec.ns, c.pose_topic),
                codec.POSE_TYPES[c.pose_kind],
                wire.SENSOR_QOS,
                partial(self._on_ros_pose, state),
            )
            self._subscription(
                wire.resolve(spec.ns, c.goal_topic),
                codec.POSE_STAMPED,
                wire.DEFAULT_QOS,
                partial(self._on_ros_goal, state),
            )
        if c.map_topic:
            self._subscription(
                wire.resolve("/", c.map_topic), codec.OCCUPANCY_GRID, wire.MAP_QOS, self._on_map
            )
        self._handles.append(_Closer(self._close_ros))  # closed after the cmd_vel subscription
        self._handles.append(self.bus.subscribe(self.keys.any_robot("cmd_vel"), self._on_cmd))
        self.spawn(self._work, "ros")
        self.spawn(self._ask_maps, "maps")

    def _ask_maps(self) -> None:
        """Ask the transform service for the robots' maps once at start-up, so that they are
        solved before the first goal (progressive maps, docs/SERVICES.md): each robot's
        workspace ``{ws}`` (a robot with a body drives on it, with the safety layer on the
        exact shrunk geometry, until its footprint map is solved: docs/ROS2.md) and the map of
        its footprint ``{ws}~r{R}``; retried every 2 s while no transform service knows the
        workspace (at most 5 minutes)."""
        from confnav.services.definitions import ask_for_maps, footprint_of

        from confnav.maps.footprint import derived_ws_id

        c = self.config
        radius = footprint_of(c.robot_radius, c.drive, c.lookahead)
        ws_ids = {s.ws_id for s in c.robots} | {derived_ws_id(s.ws_id, radius) for s in c.robots}
        ask_for_maps(self.bus, self.keys, sorted(ws_ids), self._stop)

    def _close_ros(self) -> None:
        """Stop every robot (a base without a cmd_vel timeout keeps its last command), then
        undeclare the ROS entities (their tokens vanish from the ROS graph)."""
        for robot in self._robots.values():
            try:
                self._put(robot.cmd, codec.encode_twist(0.0, 0.0, 0.0, self.config.cmd_stamped))
            except Exception:
                log.warning("%s: final zero command failed", robot.spec.robot_id, exc_info=True)
        for h in reversed(self._ros):
            try:
                h.undeclare()
            except Exception:
                log.debug("undeclaring a ROS entity failed", exc_info=True)
        self._ros.clear()

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                handler, data = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                handler(data)
            except Exception:  # a bad message never stops the bridge
                self.count("errors")
                log.exception("ROS message handling failed")

    def health_detail(self) -> tuple[str, str]:
        if self._map_problem:
            return "degraded", self._map_problem
        return "ok", ""

    # ROS -> confnav -----------------------------------------------------------------------
    def _on_ros_pose(self, robot: _RobotState, data: bytes) -> None:
        try:
            p = codec.decode_pose(data, self.config.pose_kind)
        except wire.Ros2Error as exc:
            self.count("rejected")
            log.warning("%s: rejected pose: %s", robot.spec.robot_id, exc)
            return
        with robot.lock:
            robot.yaw, robot.frame = p.yaw, p.frame_id
            robot.seq += 1
            seq = robot.seq
        pose = Pose(
            robot_id=robot.spec.robot_id,
            stamp_ns=p.stamp_ns or time.time_ns(),
            seq=seq,
            x=p.x,
            y=p.y,
            theta=p.yaw,
        )
        self.bus.publish(self.keys.robot(robot.spec.robot_id, "pose"), encode(pose))
        self.count("poses")

    def _on_ros_goal(self, robot: _RobotState, data: bytes) -> None:
        c = self.config
        try:
            p = codec.decode_pose(data, "pose")
        except wire.Ros2Error as exc:
            self.count("rejected")
            log.warning("%s: rejected goal: %s", robot.spec.robot_id, exc)
            return
        with robot.lock:
            frame = robot.frame
        if frame is not None and p.frame_id and p.frame_id != frame:
            self.count("rejected")
            log.warning(
                "%s: goal in frame %r but poses in %r (no TF here): ignored",
                robot.spec.robot_id,
                p.frame_id,
                frame,
            )
            return
        goal = Goal(
            robot_id=robot.spec.robot_id,
            ws_id=robot.spec.ws_id,
            goal=(p.x, p.y),
            navfn=c.navfn,
            gain=c.gain,
            v_max=c.v_max,
            tolerance=c.tolerance,
            stamp_ns=time.time_ns(),
            drive=c.drive,
            robot_radius=c.robot_radius,
            lookahead=c.lookahead,
            omega_max=c.omega_max,
        )
        self.bus.publish(self.keys.robot(robot.spec.robot_id, "goal"), encode(goal))
        self.count("goals")

    def _on_map(self, data: bytes) -> None:
        try:
            grid = codec.decode_grid(data)
        except wire.Ros2Error as exc:
            self.count("rejected")
            log.warning("rejected map: %s", exc)
            return
        self.count("maps")
        ws_id = self.config.map_ws or self.config.robots[0].ws_id
        if self._map_import is None:
            self._map_problem = "map import not available: OccupancyGrid received, not converted"
            log.warning("%s (workspace %r)", self._map_problem, ws_id)
            return
        try:
            definition = self._map_import(grid, ws_id)
        except Exception as exc:
            self.count("rejected")
            self._map_problem = f"map import failed: {exc}"
            log.warning("%s", self._map_problem)
            return
        self._map_problem = ""
        self.bus.publish(self.keys.ws(ws_id, "definition"), encode(definition))

    # confnav -> ROS -----------------------------------------------------------------------
    def _on_cmd(self, key: str, payload: bytes) -> None:
        try:
            rid = self.keys.parse(key).ident
            cmd = decode(VelocityCommand, payload)
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected command on %s: %s", key, exc)
            return
        robot = self._robots.get(rid)
        if robot is None:
            return
        vx, vy = cmd.linear
        if cmd.frame != self.config.cmd_frame:  # a unicycle's command is a body twist already
            with robot.lock:
                yaw = robot.yaw
            if yaw is None:  # no pose yet: the controller only commands with a pose
                self.count("cmd_without_pose")
                return
            # world -> body: rotate by -yaw; body -> world: by +yaw
            c = math.cos(yaw)
            s = math.sin(yaw) if cmd.frame == "world" else -math.sin(yaw)
            vx, vy = c * vx + s * vy, -s * vx + c * vy
        payload_cdr = codec.encode_twist(
            vx, vy, cmd.angular, self.config.cmd_stamped, cmd.stamp_ns, self.config.base_frame
        )
        self._put(robot.cmd, payload_cdr)
        self.count("commands")


class _Closer:
    def __init__(self, fn: Callable[[], None]) -> None:
        self.close = fn


FREE_THRESH = 0.196
"""map_server's default ``free_thresh``: a cell is free when its occupancy ``v / 100 < 0.196``
(ROS ``map_server`` documentation, "Map format"); unknown (-1) and every other cell count as
occupied, as in the occupancy-grid import."""


def _find_map_import() -> MapImport | None:
    """The OccupancyGrid -> WorkspaceDefinition conversion through the occupancy-grid import
    (``confnav.maps.occupancy.workspace_from_grid``), or None if this confnav has no import."""
    try:
        mod = importlib.import_module("confnav.maps.occupancy")
    except ModuleNotFoundError as exc:
        if exc.name != "confnav.maps.occupancy":
            raise
        return None
    return partial(_grid_definition, mod.workspace_from_grid)


def _grid_definition(
    workspace_from_grid: Callable[..., Any], grid: codec.Grid, ws_id: str
) -> WorkspaceDefinition:
    """An OccupancyGrid (row 0 at the origin, the bottom) as a workspace definition in the
    grid's frame; the import takes image rows (row 0 at the top), hence the flip."""
    cells = grid.cells.astype(np.float64)
    free = (cells >= 0) & (cells / 100.0 < FREE_THRESH)
    origin = (grid.origin.x, grid.origin.y, grid.origin.yaw)
    result = workspace_from_grid(free[::-1], grid.resolution, origin)
    return definition_of(ws_id, result.workspace)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "ros2", help="bridge ROS 2 topics (rmw_zenoh wire format) to the confnav keys"
    )
    p.add_argument(
        "--robot",
        action="append",
        required=True,
        metavar="ID=WS[@/NS]",
        help="a robot, its workspace and ROS namespace (default /ID); repeatable",
    )
    p.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID (default 0)")
    p.add_argument("--key-style", choices=("rmw_zenoh", "ros2dds"), default="rmw_zenoh")
    p.add_argument("--node-name", default="confnav_bridge")
    p.add_argument("--pose-topic", default="odom")
    p.add_argument(
        "--pose-type",
        choices=tuple(codec.POSE_TYPES),
        default="odometry",
        help="odometry: nav_msgs/Odometry; amcl: PoseWithCovarianceStamped; pose: PoseStamped",
    )
    p.add_argument("--goal-topic", default="goal_pose")
    p.add_argument("--cmd-topic", default="cmd_vel")
    p.add_argument("--twist-stamped", action="store_true", help="publish TwistStamped")
    p.add_argument("--cmd-frame", choices=("body", "world"), default="body")
    p.add_argument("--base-frame", default="base_link", help="frame_id of TwistStamped")
    p.add_argument("--map-topic", default=None, help="OccupancyGrid topic (e.g. /map)")
    p.add_argument("--map-ws", default=None, help="workspace id of the map (default: 1st robot's)")
    p.add_argument("--navfn", choices=("harmonic", "kr"), default=defaults.NAVFN)
    p.add_argument("--gain", type=float, default=defaults.GAIN, help="1/s (default %(default)s)")
    p.add_argument("--v-max", type=float, default=defaults.V_MAX, help="m/s (default %(default)s)")
    p.add_argument(
        "--tolerance", type=float, default=defaults.GOAL_TOL, help="m (default %(default)s)"
    )
    p.add_argument(
        "--drive",
        choices=("holonomic", "unicycle"),
        default="holonomic",
        help="unicycle: differential-drive bases get (linear.x, angular.z) twists that steer a "
        "point --lookahead ahead of the axle (default %(default)s)",
    )
    p.add_argument("--robot-radius", type=float, default=0.0, help="m (default %(default)s)")
    p.add_argument(
        "--lookahead",
        type=float,
        default=BridgeConfig.lookahead,
        help="m, unicycle only (default %(default)s)",
    )
    p.add_argument(
        "--omega-max",
        type=float,
        default=BridgeConfig.omega_max,
        help="rad/s, unicycle only (default %(default)s)",
    )
    add_zenoh_args(p)
    p.set_defaults(func=main)


def config_from_args(args: argparse.Namespace) -> BridgeConfig:
    try:
        robots = tuple(RobotSpec.parse(r) for r in args.robot)
    except (ValueError, KeyError_) as exc:
        raise SystemExit(f"confnav serve ros2: error: {exc}") from exc
    return BridgeConfig(
        robots=robots,
        domain_id=args.domain_id,
        key_style=args.key_style,
        node_name=args.node_name,
        pose_topic=args.pose_topic,
        pose_kind=args.pose_type,
        goal_topic=args.goal_topic,
        cmd_topic=args.cmd_topic,
        cmd_stamped=args.twist_stamped,
        cmd_frame=args.cmd_frame,
        base_frame=args.base_frame,
        map_topic=args.map_topic,
        map_ws=args.map_ws,
        navfn=args.navfn,
        gain=args.gain,
        v_max=args.v_max,
        tolerance=args.tolerance,
        drive=args.drive,
        robot_radius=args.robot_radius,
        lookahead=args.lookahead,
        omega_max=args.omega_max,
    )


def main(args: argparse.Namespace) -> int:
    config = config_from_args(args)

    def make(bus: Bus, keys: Keys) -> Service:
        return Ros2Bridge(bus, bus.session, config, keys)  # type: ignore[attr-defined]

    return run_until_signal(make, args)
