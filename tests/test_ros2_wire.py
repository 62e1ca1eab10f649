"""rmw_zenoh's wire format and the CDR codec, without ROS.

Sources (cited per test): ros2/rmw_zenoh snapshot bfc065f8c80cc3bc4d1963dc44ac5a472460903a
(``/work/.mirror/ros2+rmw_zenoh``), rmw_zenoh_cpp/src/detail/liveliness_utils.cpp,
type_support_common.cpp, qos.cpp; the zenoh 1.x attachment from ros2/rmw_zenoh
534747dca92adf15e1b1b975123037ca278db5ba attachment_helpers.cpp and zenoh-cpp
8efbd20edbc790dbfa1a89252ebdcddd58117893 include/zenoh/api/ext/serialization.hxx.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
import xxhash
from confnav.services.ros2 import codec, wire

TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_type_hashes_match_published_jazzy_hashes() -> None:
    # REP 2011 RIHS01 of two Jazzy types as `ros2 topic info -v` prints them (Twist) and as
    # rmw_zenoh's newer docs/design.md quotes for /chatter (String): fixed published values.
    assert codec.type_hash("geometry_msgs/msg/Twist") == TWIST_HASH
    assert codec.type_hash("std_msgs/msg/String") == STRING_HASH
    for t in (codec.ODOMETRY, codec.POSE_STAMPED, codec.POSE_COV_STAMPED, codec.OCCUPANCY_GRID):
        h = codec.type_hash(t)
        assert h.startswith("RIHS01_") and len(h) == 7 + 64
        int(h[7:], 16)


def test_dds_type_name() -> None:
    # type_support_common.cpp _create_type_name: "<namespace>::" + "dds_::" + name + "_"
    assert wire.dds_type_name("geometry_msgs/msg/Twist") == "geometry_msgs::msg::dds_::Twist_"
    assert wire.dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    with pytest.raises(wire.Ros2Error):
        wire.dds_type_name("Twist")


def test_data_key() -> None:
    # liveliness_utils.cpp TopicInfo::TopicInfo: domain "/" strip_slashes(name) "/" type "/" hash
    key = wire.topic_key(0, "/r1/cmd_vel", "geometry_msgs/msg/Twist", TWIST_HASH)
    assert key == f"0/r1/cmd_vel/geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}"
    assert wire.topic_key(7, "/chatter", "std_msgs/msg/String", STRING_HASH) == (
        f"7/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert wire.ros2dds_key("/r1/cmd_vel") == "r1/cmd_vel"


def test_names() -> None:
    assert wire.mangle("/r1/cmd_vel") == "%r1%cmd_vel"
    assert wire.demangle("%r1%cmd_vel") == "/r1/cmd_vel"
    assert wire.resolve("/r1", "odom") == "/r1/odom"
    assert wire.resolve("r1/", "odom") == "/r1/odom"
    assert wire.resolve("/", "goal_pose") == "/goal_pose"
    assert wire.resolve("/r1", "/map") == "/map"
    for bad in ("odom x", "1odom", "od//om"):
        with pytest.raises(wire.Ros2Error):
            wire.resolve("/r1", bad)


def test_qos_keyexpr() -> None:
    # qos_to_keyexpr (liveliness_utils.cpp): "R:D:H,depth:dl_s,dl_ns:ls_s,ls_ns:L,lease_s,lease_ns",
    # a field empty when it equals qos.cpp's default of the zenoh 1.x rmw_zenoh (7efeee2b,
    # RMW_ZENOH_DEFAULT_*: reliable, volatile, keep last, 42, infinite, automatic)
    assert wire.qos_keyexpr(wire.QoS()) == "::,:,:,:,,"
    # rclcpp QoS(10) after QoS::best_available_qos: reliable, volatile, keep last 10, durations
    # and liveliness "default" mapped to rmw_zenoh's: only the depth is written
    assert wire.qos_keyexpr(wire.DEFAULT_QOS) == "::,10:,:,:,,"
    assert wire.qos_keyexpr(wire.SENSOR_QOS) == "2::,5:,:,:,,"  # best effort, volatile, 5
    assert wire.qos_keyexpr(wire.MAP_QOS) == ":1:,1:,:,:,,"  # transient local (1) is written
    full = wire.QoS(2, 1, 2, 3, (1, 2), (3, 4), 3, (5, 6))
    assert wire.qos_keyexpr(full) == "2:1:2,3:1,2:3,4:3,5,6"
    assert wire.qos_keyexpr(wire.QoS(deadline=(0, 0))) == "::,:0,0:,:,,"


def test_token_of_a_real_node_with_default_qos() -> None:
    # teleop_twist_keyboard: node "teleop_twist_keyboard", create_publisher(Twist, "cmd_vel", 10)
    # in the root namespace, domain 0. Entity::Entity (liveliness_utils.cpp, 3411fdec) writes
    # AdminSpace/DomainId/Zid/Nid/Id/EntityStr/Enclave/Namespace/NodeName/TopicName/TopicType/
    # TopicTypeHash/TopicQoS with "/" mangled to "%" (enclave "/" and namespace "/" -> "%"), and
    # qos_to_keyexpr leaves every default field empty: reliable and volatile are rmw_zenoh's
    # defaults (qos.cpp), so only the depth 10 is written. The GID is XXH3-128 of that text.
    info = wire.TopicInfo("/cmd_vel", "geometry_msgs/msg/Twist", TWIST_HASH, wire.DEFAULT_QOS)
    zid = "f446b0e7bcea4bbcc4bc5f1f757e6683"
    token = wire.liveliness_token(
        0, zid, 0, 10, wire.EntityKind.PUBLISHER, "/", "teleop_twist_keyboard", info
    )
    real = (
        f"@ros2_lv/0/{zid}/0/10/MP/%/%/teleop_twist_keyboard/%cmd_vel/"
        f"geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}/::,10:,:,:,,"
    )
    assert token == real
    # durability written as "2" (as before) is another token, hence another GID
    assert wire.entity_gid(token) != wire.entity_gid(real.replace("/::,10:", "/:2:,10:"))


def test_liveliness_tokens() -> None:
    # Entity::Entity: AdminSpace/DomainId/Zid/Nid/Id/EntityStr/Enclave/Namespace/NodeName
    # [/TopicName/TopicType/TopicTypeHash/TopicQoS], every name through mangle_name
    node = wire.liveliness_token(0, "aabb", 0, 0, wire.EntityKind.NODE, "/", "confnav_bridge")
    assert node == "@ros2_lv/0/aabb/0/0/NN/%/%/confnav_bridge"
    info = wire.TopicInfo("/r1/cmd_vel", "geometry_msgs/msg/Twist", TWIST_HASH, wire.DEFAULT_QOS)
    pub = wire.liveliness_token(0, "aabb", 0, 3, wire.EntityKind.PUBLISHER, "/", "b", info)
    assert pub == (
        "@ros2_lv/0/aabb/0/3/MP/%/%/b/%r1%cmd_vel/geometry_msgs::msg::dds_::Twist_/"
        f"{TWIST_HASH}/::,10:,:,:,,"
    )
    sub = wire.liveliness_token(5, "z", 2, 4, wire.EntityKind.SUBSCRIPTION, "/robots", "n", info)
    assert sub.startswith("@ros2_lv/5/z/2/4/MS/%/%robots/n/%r1%cmd_vel/")
    with pytest.raises(wire.Ros2Error):
        wire.liveliness_token(0, "z", 0, 1, wire.EntityKind.PUBLISHER, "/", "n")
    with pytest.raises(wire.Ros2Error):
        wire.liveliness_token(0, "z", 0, 0, wire.EntityKind.NODE, "/", "n", info)


def test_zid_chunk() -> None:
    # liveliness_utils.cpp zid_to_str: bytes id[15] .. id[0] of the little-endian u128, each
    # `ss << std::hex << int(byte)` (no padding); zenoh prints the u128 in hex, no leading 0s
    assert wire.zid_chunk("a0b0c") == "0" * 13 + "abc"
    assert wire.zid_chunk("f446b0e7bcea4bbcc4bc5f1f757e6683") == "f446b0e7bcea4bbcc4bc5f1f757e6683"
    assert wire.zid_chunk("100f0e0d0c0b0a090807060504030201") == "10fedcba987654321"
    with pytest.raises(wire.Ros2Error):
        wire.zid_chunk("xyz")


def test_gid_is_xxh3_128_of_the_token_low_then_high() -> None:
    # Entity::Entity: memcpy(gid, &hash.low64, 8); memcpy(gid + 8, &hash.high64, 8) (x86: LE)
    token = "@ros2_lv/0/aabb/0/0/NN/%/%/confnav_bridge"
    digest = xxhash.xxh3_128_digest(token.encode())  # canonical: high64 BE, then low64 BE
    high, low = struct.unpack(">QQ", digest)
    assert wire.entity_gid(token) == struct.pack("<QQ", low, high)
    assert len(wire.entity_gid(token)) == wire.GID_SIZE


def test_attachment_bytes() -> None:
    # AttachmentData::serialize_to_zbytes (534747dc): int64 seq, int64 timestamp, array<u8,16>;
    # zenoh-cpp serialization.hxx: integers little endian, an array as LEB128 length + elements
    gid = bytes(range(16))
    att = wire.Attachment(5, 1_700_000_000_123_456_789, gid)
    data = att.encode()
    assert data == struct.pack("<qq", 5, 1_700_000_000_123_456_789) + b"\x10" + gid
    assert wire.Attachment.decode(data) == att
    with pytest.raises(wire.Ros2Error):
        wire.Attachment.decode(data[:20])
    with pytest.raises(wire.Ros2Error):
        wire.Attachment(1, 1, b"short").encode()


@pytest.mark.parametrize("kind", ["odometry", "amcl", "pose"])
def test_pose_round_trip(kind: codec.PoseKind) -> None:
    for yaw in (0.0, 0.7, -2.5, math.pi - 1e-9):
        p = codec.PlanarPose(1.25, -3.5, yaw, 1_700_000_000_000_000_123, "map")
        q = codec.decode_pose(codec.encode_pose(p, kind), kind)
        assert (q.x, q.y, q.stamp_ns, q.frame_id) == (p.x, p.y, p.stamp_ns, p.frame_id)
        assert abs(q.yaw - yaw) < 1e-12


def test_yaw_from_general_quaternion() -> None:
    # a rotation about z by a, then about x by b: yaw stays a (Z-Y-X Euler)
    a, b = 0.9, 0.3
    qz = np.array([0, 0, math.sin(a / 2), math.cos(a / 2)])  # x, y, z, w
    qx = np.array([math.sin(b / 2), 0, 0, math.cos(b / 2)])

    def mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # Hamilton product, (x, y, z, w)
        pv, pw, qv, qw = p[:3], p[3], q[:3], q[3]
        return np.array([*(pw * qv + qw * pv + np.cross(pv, qv)), pw * qw - pv @ qv])

    q = mul(qz, qx)

    class Q:
        x, y, z, w = (float(v) for v in q)

    assert abs(codec.yaw_of(Q) - a) < 1e-12


def test_twist_round_trip_and_bytes() -> None:
    data = codec.encode_twist(0.25, -0.5, 0.125)
    # CDR little endian: encapsulation 00 01 00 00, then six float64
    assert data == b"\x00\x01\x00\x00" + struct.pack("<6d", 0.25, -0.5, 0, 0, 0, 0.125)
    assert codec.decode_twist(data) == (0.25, -0.5, 0.125)
    stamped = codec.encode_twist(1.0, 2.0, 3.0, True, 5_000_000_007, "base_link")
    assert codec.decode_twist(stamped, True) == (1.0, 2.0, 3.0)


def test_grid_round_trip() -> None:
    cells = np.array([[0, 100, -1, 0], [0, 0, 50, 100], [-1, -1, 0, 0]], dtype=np.int8)
    g = codec.Grid(cells, 0.05, codec.PlanarPose(-1.0, -2.0, 0.0, 42, "map"))
    h = codec.decode_grid(codec.encode_grid(g))
    np.testing.assert_array_equal(h.cells, cells)
    assert h.resolution == pytest.approx(0.05, rel=1e-7)  # float32 on the wire
    assert h.origin == g.origin


def test_bad_cdr_is_a_clear_error() -> None:
    with pytest.raises(wire.Ros2Error, match="invalid CDR"):
        codec.decode_pose(b"\x00\x01\x00\x00\x01", "odometry")
    nan = codec.encode_pose(codec.PlanarPose(math.nan, 0.0, 0.0, 0, "map"), "pose")
    with pytest.raises(wire.Ros2Error, match="non-finite"):
        codec.decode_pose(nan, "pose")
