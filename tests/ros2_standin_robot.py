"""A stand-in ROS 2 robot speaking rmw_zenoh's wire format with nothing but zenoh and rosbags
(no confnav import: an independent implementation of the same documented format).

It publishes ``nav_msgs/msg/Odometry`` on ``<ns>/odom`` at ``--rate`` Hz and integrates the
``geometry_msgs/msg/Twist`` it receives on ``<ns>/cmd_vel`` as a holonomic base (the twist is in
its body frame: world velocity = R(yaw) v, yaw' = w). It prints one JSON line per 0.1 s:
position, yaw, commands received, commands whose attachment decoded. Stops on SIGTERM/SIGINT.

Formats, from ros2/rmw_zenoh (snapshot bfc065f8c80cc3bc4d1963dc44ac5a472460903a,
rmw_zenoh_cpp/src/detail/liveliness_utils.cpp ``TopicInfo::TopicInfo``; type name from
type_support_common.cpp ``_create_type_name``): ``<domain>/<topic>/<pkg>::msg::dds_::<Name>_/
<RIHS01 hash>``; attachment from ros2/rmw_zenoh 534747dca92adf15e1b1b975123037ca278db5ba
attachment_helpers.cpp: int64 sequence number, int64 source timestamp, 16 gid bytes.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, z_deserialize, z_serialize

TS = get_typestore(Stores.ROS2_JAZZY)
ODOM = "nav_msgs/msg/Odometry"
TWIST = "geometry_msgs/msg/Twist"


def data_key(domain: int, topic: str, ros_type: str) -> str:
    pkg, sub, name = ros_type.split("/")
    return f"{domain}/{topic.strip('/')}/{pkg}::{sub}::dds_::{name}_/{TS.hash_rihs01(ros_type)}"


def odometry(x: float, y: float, yaw: float, stamp_ns: int) -> bytes:
    t = TS.types
    import numpy as np

    v0 = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id="odom",
    )
    msg = t[ODOM](
        header=header,
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t[TWIST](linear=v0, angular=v0), covariance=np.zeros(36)
        ),
    )
    return bytes(TS.serialize_cdr(msg, ODOM))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--ns", default="/r1")
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--yaw", type=float, default=0.0)
    ap.add_argument("--rate", type=float, default=50.0)
    args = ap.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock = threading.Lock()
    state = {"x": args.x, "y": args.y, "yaw": args.yaw, "v": (0.0, 0.0, 0.0)}
    counts = {"cmds": 0, "attached": 0}
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    def on_cmd(sample: zenoh.Sample) -> None:
        msg = TS.deserialize_cdr(sample.payload.to_bytes(), TWIST)
        ok = False
        if sample.attachment is not None:
            seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], sample.attachment)
            ok = seq > 0 and stamp > 0 and len(gid) == 16
        with lock:
            state["v"] = (msg.linear.x, msg.linear.y, msg.angular.z)
            counts["cmds"] += 1
            counts["attached"] += ok

    gid = bytes(range(16))
    with zenoh.open(conf) as session:
        ns = args.ns.rstrip("/")
        session.declare_subscriber(data_key(args.domain, f"{ns}/cmd_vel", TWIST), on_cmd)
        pub = session.declare_publisher(data_key(args.domain, f"{ns}/odom", ODOM))
        dt = 1.0 / args.rate
        seq = 0
        next_print = 0.0
        t_last = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            h, t_last = now - t_last, now
            with lock:
                vx, vy, wz = state["v"]
                c, s = math.cos(state["yaw"]), math.sin(state["yaw"])
                state["x"] += h * (c * vx - s * vy)
                state["y"] += h * (s * vx + c * vy)
                state["yaw"] += h * wz
                x, y, yaw = state["x"], state["y"], state["yaw"]
                line = {"x": x, "y": y, "yaw": yaw, **counts}
            seq += 1
            stamp = time.time_ns()
            att = z_serialize((Int64(seq), Int64(stamp), gid))
            pub.put(odometry(x, y, yaw, stamp), attachment=att)
            if now >= next_print:
                next_print = now + 0.1
                print(json.dumps(line), flush=True)
            stop.wait(dt)
    return 0


if __name__ == "__main__":
    sys.exit(main())
