"""rmw_zenoh's wire format: data keys, liveliness tokens, QoS strings, GIDs and attachments.

Pure functions (no session). Every format is taken from the rmw_zenoh source, cited per item:

- snapshot ``ros2/rmw_zenoh`` commit ``bfc065f8c80cc3bc4d1963dc44ac5a472460903a`` (the one
  fetched to ``/work/.mirror/ros2+rmw_zenoh``), file ``rmw_zenoh_cpp/src/detail/
  liveliness_utils.cpp``: data key (``TopicInfo::TopicInfo``), token layout
  (``Entity::Entity``, ``KeyexprIndex``), the session id chunk (``zid_to_str``), name
  mangling (``mangle_name``), QoS string (``qos_to_keyexpr``) and the entity GID (XXH3-128
  of the token, ``low64`` then ``high64``); ``type_support_common.cpp``
  (``_create_type_name``) for the DDS type name. ``qos_to_keyexpr`` is unchanged in the zenoh
  1.x rmw_zenoh (commit ``3411fdec149fe0c932f24d4d79ef908eb81d7482``).
- The defaults an omitted QoS field stands for: ``rmw_zenoh_cpp/src/detail/qos.cpp``
  (``RMW_ZENOH_DEFAULT_*``, ``QoS::QoS``) of the zenoh 1.x rmw_zenoh (commits
  ``7efeee2b9009b816a4bd4a3148af3cca40f753d5`` and ``5e10d47b06c3fe327105d06a8350be455411ea5b``):
  reliable, **volatile**, keep last, depth 42, infinite deadline, lifespan and lease, automatic
  liveliness. (The ``bfc065f8`` snapshot still had transient local.) A real node's QoS first goes
  through ``QoS::best_available_qos``, which turns the rmw "system default" values (0, and the
  zero durations) into these defaults, so rclcpp's ``QoS(10)`` is written ``::,10:,:,:,,``.
- The attachment: that snapshot still builds on zenoh-c 0.11 (``z_bytes_map`` attachments),
  whose protocol a zenoh 1.x session (eclipse-zenoh-python here, and rmw_zenoh in ROS 2 Jazzy
  and later) cannot talk to. The zenoh 1.x layout is ``ros2/rmw_zenoh`` commit
  ``534747dca92adf15e1b1b975123037ca278db5ba``, ``rmw_zenoh_cpp/src/detail/
  attachment_helpers.cpp`` (``AttachmentData::serialize_to_zbytes``): ``zenoh::ext::Serializer``
  of ``int64 sequence_number``, ``int64 source_timestamp``, ``std::array<uint8_t, 16>
  source_gid``; zenoh-cpp ``include/zenoh/api/ext/serialization.hxx`` (commit
  ``8efbd20edbc790dbfa1a89252ebdcddd58117893``) writes an array as a sequence (LEB128 length,
  then the elements), i.e. exactly what :func:`zenoh.ext.z_serialize` writes for
  ``(Int64, Int64, bytes)``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

import xxhash
from zenoh import ZBytes
from zenoh.ext import Int64, z_deserialize, z_serialize

ADMIN_SPACE: Final = "@ros2_lv"
SLASH_REPLACEMENT: Final = "%"
GID_SIZE: Final = 16  # RMW_GID_STORAGE_SIZE (Jazzy)

# rmw/types.h enum values (rmw_qos_*_policy_e)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1


class Ros2Error(ValueError):
    """A name, key, token or attachment that does not fit rmw_zenoh's format."""


class EntityKind(StrEnum):
    """The ``<entity>`` chunk of a liveliness token (``liveliness_utils.cpp``: NODE_STR...)."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


INFINITE: Final = (9_223_372_036, 854_775_807)  # RMW_DURATION_INFINITE (sec, nsec)


@dataclass(frozen=True)
class QoS:
    """The QoS policies in a token; the defaults are rmw_zenoh's (``qos.cpp``: reliable,
    volatile, keep last 42, infinite deadline / lifespan / lease, automatic liveliness).
    Durations are (sec, nsec)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] = INFINITE


SENSOR_QOS: Final = QoS(reliability=BEST_EFFORT, durability=VOLATILE, depth=5)
"""rmw_qos_profile_sensor_data (odometry, poses)."""
DEFAULT_QOS: Final = QoS(durability=VOLATILE, depth=10)
"""rclcpp's ``QoS(10)``: reliable, volatile, keep last 10 (cmd_vel, goal_pose)."""
MAP_QOS: Final = QoS(durability=TRANSIENT_LOCAL, depth=1)
"""nav2's map server: reliable, transient local, keep last 1."""


def qos_keyexpr(qos: QoS) -> str:
    """``liveliness_utils.cpp`` ``qos_to_keyexpr``: ``R:D:H,depth:dl_s,dl_ns:ls_s,ls_ns:L,lease_s,
    lease_ns`` (``:`` between policies, ``,`` within one; enums and durations in decimal), each
    field left empty when it equals rmw_zenoh's default (:class:`QoS`)."""
    d = QoS()

    def f(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (
        f"{f(qos.reliability, d.reliability)}:{f(qos.durability, d.durability)}:"
        f"{f(qos.history, d.history)},{f(qos.depth, d.depth)}:"
        f"{f(qos.deadline[0], d.deadline[0])},{f(qos.deadline[1], d.deadline[1])}:"
        f"{f(qos.lifespan[0], d.lifespan[0])},{f(qos.lifespan[1], d.lifespan[1])}:"
        f"{f(qos.liveliness, d.liveliness)},{f(qos.lease[0], d.lease[0])},"
        f"{f(qos.lease[1], d.lease[1])}"
    )


def zid_chunk(zid: str) -> str:
    """The ``<zid>`` chunk of a token from zenoh's string form of a session id (hex of the
    little-endian u128, no leading zeros): ``liveliness_utils.cpp`` ``zid_to_str`` prints the 16
    bytes from the most significant one, each in hex without zero padding."""
    try:
        value = int(zid, 16)
        raw = value.to_bytes(16, "big")
    except (ValueError, OverflowError) as exc:
        raise Ros2Error(f"not a zenoh id: {zid!r}") from exc
    return "".join(f"{b:x}" for b in raw)


def mangle(name: str) -> str:
    """``mangle_name``: every ``/`` becomes ``%`` (a token chunk holds a whole ROS name)."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle(chunk: str) -> str:
    return chunk.replace(SLASH_REPLACEMENT, "/")


_NAME = re.compile(r"^(/[A-Za-z_~{][A-Za-z0-9_{}]*)+$|^/$")


def resolve(namespace: str, name: str) -> str:
    """Fully qualified ROS name of ``name`` in ``namespace`` (``/ns`` + ``/`` + ``name``);
    an absolute ``name`` stays as is. Raises :class:`Ros2Error` on an invalid name."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    full = name if name.startswith("/") else (ns.rstrip("/") + "/" + name)
    if full != "/" and not _NAME.match(full):
        raise Ros2Error(f"invalid ROS name {full!r}")
    return full


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_``
    (``type_support_common.cpp`` ``_create_type_name``: namespace ``::``, ``dds_::``,
    name ``_``)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise Ros2Error(f"ROS type {ros_type!r} is not of the form pkg/msg/Name")
    pkg, sub, name = parts
    return f"{pkg}::{sub}::dds_::{name}_"


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """Data key ``<domain_id>/<topic without leading/trailing '/'>/<dds type>/<type hash>``
    (``TopicInfo::TopicInfo``: slashes inside the topic are kept)."""
    return f"{int(domain_id)}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


def ros2dds_key(topic: str) -> str:
    """zenoh-bridge-ros2dds style: the fully qualified topic without its leading ``/``."""
    return topic.strip("/")


@dataclass(frozen=True)
class TopicInfo:
    name: str  # fully qualified topic
    ros_type: str  # pkg/msg/Name
    type_hash: str  # RIHS01_<64 hex>
    qos: QoS


def liveliness_token(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: EntityKind,
    namespace: str,
    node_name: str,
    topic: TopicInfo | None = None,
    enclave: str = "/",
) -> str:
    """``@ros2_lv/<domain>/<zid>/<nid>/<id>/<entity>/<enclave>/<namespace>/<node>`` and, for a
    publisher or subscription, ``/<topic>/<dds type>/<type hash>/<qos>``; names mangled
    (``Entity::Entity`` with ``KeyexprIndex``; a node is its own ``nid`` and ``id``,
    ``rmw_node_data.cpp``)."""
    if (topic is None) != (kind == EntityKind.NODE):
        raise Ros2Error("a node token has no topic; every other entity needs one")
    parts = [
        ADMIN_SPACE,
        str(int(domain_id)),
        zid,
        str(node_id),
        str(entity_id),
        kind.value,
        mangle(enclave),
        mangle(namespace or "/"),
        mangle(node_name),
    ]
    if topic is not None:
        parts += [
            mangle(topic.name),
            mangle(dds_type_name(topic.ros_type)),
            mangle(topic.type_hash),
            qos_keyexpr(topic.qos),
        ]
    if any(not p for p in parts):
        raise Ros2Error(f"empty chunk in liveliness token {parts!r}")
    return "/".join(parts)


def entity_gid(token: str) -> bytes:
    """The 16-byte GID of an entity: XXH3-128 of its token, ``low64`` then ``high64`` in host
    (little-endian) order (``Entity::Entity``: two ``memcpy``)."""
    h = xxhash.xxh3_128_intdigest(token.encode("utf-8"))
    low, high = h & 0xFFFF_FFFF_FFFF_FFFF, h >> 64
    return low.to_bytes(8, "little") + high.to_bytes(8, "little")


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's per-sample attachment: sequence number, source timestamp (ns since the
    epoch) and the publisher's GID."""

    sequence_number: int
    source_timestamp: int
    source_gid: bytes

    def encode(self) -> bytes:
        if len(self.source_gid) != GID_SIZE:
            raise Ros2Error(f"source gid must have {GID_SIZE} bytes")
        data = (Int64(self.sequence_number), Int64(self.source_timestamp), self.source_gid)
        return z_serialize(data).to_bytes()

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        try:
            seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], ZBytes(data))
        except Exception as exc:  # ZDeserializeError and short buffers
            raise Ros2Error(f"not an rmw_zenoh attachment: {exc}") from exc
        if len(gid) != GID_SIZE:
            raise Ros2Error(f"attachment gid has {len(gid)} bytes, not {GID_SIZE}")
        return cls(int(seq), int(stamp), bytes(gid))
