"""CDR conversion of the ROS 2 messages the bridge speaks, through ``rosbags``' typestore for
ROS 2 Jazzy (no hand-packed bytes), and their RIHS01 type hashes (REP 2011).

Planar view: a pose is ``(x, y, yaw)`` in the frame of its header, ``yaw`` from the
quaternion's rotation about z (the Z-Y-X Euler yaw ``atan2(2(wz + xy), 1 - 2(y^2 + z^2))``,
as ``tf2::getYaw``; Diebel, "Representing Attitude", 2006, eq. 290); a planar pose is written
back as the rotation ``(0, 0, sin(yaw/2), cos(yaw/2))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any, Final, Literal

import numpy as np
from confnav.services.ros2.wire import Ros2Error
from rosbags.typesys import Stores, get_typestore

TWIST: Final = "geometry_msgs/msg/Twist"
TWIST_STAMPED: Final = "geometry_msgs/msg/TwistStamped"
ODOMETRY: Final = "nav_msgs/msg/Odometry"
POSE_COV_STAMPED: Final = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED: Final = "geometry_msgs/msg/PoseStamped"
OCCUPANCY_GRID: Final = "nav_msgs/msg/OccupancyGrid"

PoseKind = Literal["odometry", "amcl", "pose"]
POSE_TYPES: Final[dict[str, str]] = {
    "odometry": ODOMETRY,
    "amcl": POSE_COV_STAMPED,
    "pose": POSE_STAMPED,
}


@cache
def typestore() -> Any:
    """The ROS 2 Jazzy message definitions (``rosbags.typesys.Stores.ROS2_JAZZY``)."""
    return get_typestore(Stores.ROS2_JAZZY)


@cache
def type_hash(ros_type: str) -> str:
    """``RIHS01_<sha256 hex>`` of a message type (REP 2011), computed by rosbags."""
    return str(typestore().hash_rihs01(ros_type))


def _t(name: str) -> Any:
    return typestore().types[name]


def _stamp(ns: int) -> Any:
    return _t("builtin_interfaces/msg/Time")(
        sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000)
    )


def _header(stamp_ns: int, frame_id: str) -> Any:
    return _t("std_msgs/msg/Header")(stamp=_stamp(stamp_ns), frame_id=frame_id)


def _ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def yaw_of(q: Any) -> float:
    """Rotation about z of the quaternion ``q`` (x, y, z, w); see the module docstring."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _quat(yaw: float) -> Any:
    return _t("geometry_msgs/msg/Quaternion")(
        x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)
    )


def _decode(data: bytes, ros_type: str) -> Any:
    try:
        return typestore().deserialize_cdr(data, ros_type)
    except Exception as exc:  # rosbags raises several types on a short or bad buffer
        raise Ros2Error(f"invalid CDR for {ros_type}: {exc}") from exc


def _encode(msg: Any, ros_type: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, ros_type))


@dataclass(frozen=True)
class PlanarPose:
    """A pose in the plane: metres and radians in frame ``frame_id``; ``stamp_ns`` from the
    header (nanoseconds; 0 when the sender left it unset)."""

    x: float
    y: float
    yaw: float
    stamp_ns: int
    frame_id: str


def _pose_msg(p: PlanarPose) -> Any:
    point = _t("geometry_msgs/msg/Point")(x=float(p.x), y=float(p.y), z=0.0)
    return _t("geometry_msgs/msg/Pose")(position=point, orientation=_quat(p.yaw))


def encode_pose(p: PlanarPose, kind: PoseKind, child_frame: str = "base_link") -> bytes:
    """A planar pose as Odometry (zero twist), PoseWithCovarianceStamped or PoseStamped."""
    header = _header(p.stamp_ns, p.frame_id)
    pose = _pose_msg(p)
    cov = np.zeros(36, dtype=np.float64)
    if kind == "odometry":
        zero = _t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        twist = _t("geometry_msgs/msg/TwistWithCovariance")(
            twist=_t(TWIST)(linear=zero, angular=zero), covariance=cov
        )
        pwc = _t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=cov)
        msg = _t(ODOMETRY)(header=header, child_frame_id=child_frame, pose=pwc, twist=twist)
    elif kind == "amcl":
        pwc = _t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=cov)
        msg = _t(POSE_COV_STAMPED)(header=header, pose=pwc)
    else:
        msg = _t(POSE_STAMPED)(header=header, pose=pose)
    return _encode(msg, POSE_TYPES[kind])


def decode_pose(data: bytes, kind: PoseKind) -> PlanarPose:
    """The planar pose in an Odometry / PoseWithCovarianceStamped / PoseStamped message.
    Raises :class:`Ros2Error` on bad CDR or a non-finite pose."""
    msg = _decode(data, POSE_TYPES[kind])
    pose = msg.pose if kind == "pose" else msg.pose.pose
    out = PlanarPose(
        float(pose.position.x),
        float(pose.position.y),
        yaw_of(pose.orientation),
        _ns(msg.header),
        str(msg.header.frame_id),
    )
    if not all(math.isfinite(v) for v in (out.x, out.y, out.yaw)):
        raise Ros2Error(f"non-finite pose in {POSE_TYPES[kind]}")
    return out


def encode_twist(
    vx: float,
    vy: float,
    wz: float,
    stamped: bool = False,
    stamp_ns: int = 0,
    frame_id: str = "base_link",
) -> bytes:
    """A planar velocity as ``geometry_msgs/msg/Twist`` (or ``TwistStamped``)."""
    v3 = _t("geometry_msgs/msg/Vector3")
    twist = _t(TWIST)(
        linear=v3(x=float(vx), y=float(vy), z=0.0), angular=v3(x=0.0, y=0.0, z=float(wz))
    )
    if not stamped:
        return _encode(twist, TWIST)
    return _encode(
        _t(TWIST_STAMPED)(header=_header(stamp_ns, frame_id), twist=twist), TWIST_STAMPED
    )


def decode_twist(data: bytes, stamped: bool = False) -> tuple[float, float, float]:
    """``(vx, vy, wz)`` of a Twist or TwistStamped."""
    msg = _decode(data, TWIST_STAMPED if stamped else TWIST)
    t = msg.twist if stamped else msg
    return float(t.linear.x), float(t.linear.y), float(t.angular.z)


@dataclass(frozen=True)
class Grid:
    """An occupancy grid: ``cells`` (height, width) int8 (-1 unknown, 0..100 occupied %), row 0
    at the origin, ``resolution`` m/cell, ``origin`` the planar pose of cell (0, 0)'s corner."""

    cells: np.ndarray
    resolution: float
    origin: PlanarPose


def encode_grid(g: Grid) -> bytes:
    h, w = g.cells.shape
    info = _t("nav_msgs/msg/MapMetaData")(
        map_load_time=_stamp(g.origin.stamp_ns),
        resolution=float(g.resolution),
        width=int(w),
        height=int(h),
        origin=_pose_msg(g.origin),
    )
    msg = _t(OCCUPANCY_GRID)(
        header=_header(g.origin.stamp_ns, g.origin.frame_id),
        info=info,
        data=np.ascontiguousarray(g.cells, dtype=np.int8).reshape(-1),
    )
    return _encode(msg, OCCUPANCY_GRID)


def decode_grid(data: bytes) -> Grid:
    msg = _decode(data, OCCUPANCY_GRID)
    info = msg.info
    h, w = int(info.height), int(info.width)
    cells = np.asarray(msg.data, dtype=np.int8)
    if cells.size != h * w:
        raise Ros2Error(f"occupancy grid has {cells.size} cells, not {w} x {h}")
    o = info.origin
    origin = PlanarPose(
        float(o.position.x),
        float(o.position.y),
        yaw_of(o.orientation),
        _ns(msg.header),
        str(msg.header.frame_id),
    )
    return Grid(cells.reshape(h, w), float(info.resolution), origin)
