"""The external-robot recipe of README "Plugging in a real robot" and docs/SERVICES.md, as a
script: raw Zenoh and JSON only (no confnav import), a kinematic robot that integrates the
``cmd_vel`` it receives, and a goal sent with nothing but the required fields (every other
``Goal`` field takes the library default).

    python examples/external_robot.py ENDPOINT ROBOT_ID WS_ID X0,Y0 GX,GY [TIMEOUT_S]

Exits 0 when the controller reports ``arrived`` within 5 cm of the goal, 1 otherwise; prints
the distance travelled.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time

import zenoh


def main(endpoint: str, rid: str, ws: str, start: str, goal: str, timeout: float) -> int:
    x, y = (float(v) for v in start.split(","))
    gx, gy = (float(v) for v in goal.split(","))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    cmd = [0.0, 0.0]
    state = {"state": "", "reason": ""}
    lock = threading.Lock()

    def on_cmd(sample: zenoh.Sample) -> None:  # runs on a Zenoh thread: never block
        v = json.loads(sample.payload.to_bytes())["linear"]
        with lock:
            cmd[:] = v

    def on_status(sample: zenoh.Sample) -> None:
        s = json.loads(sample.payload.to_bytes())
        with lock:
            state.update(state=s["state"], reason=s["reason"])

    travelled = 0.0
    with zenoh.open(conf) as s:
        s.declare_subscriber(f"confnav/robot/{rid}/cmd_vel", on_cmd)
        s.declare_subscriber(f"confnav/robot/{rid}/status", on_status)
        t0 = last = time.monotonic()
        seq, goal_sent = 0, False
        while time.monotonic() - t0 < timeout:
            now = time.monotonic()
            with lock:
                vx, vy = cmd
                done = state["state"] == "arrived"
                answered = bool(state["state"])
            dt, last = now - last, now
            x, y = x + vx * dt, y + vy * dt
            travelled += math.hypot(vx, vy) * dt
            s.put(
                f"confnav/robot/{rid}/pose",
                json.dumps(
                    {
                        "type": "confnav.Pose",
                        "schema_version": 1,
                        "robot_id": rid,
                        "stamp_ns": time.time_ns(),
                        "seq": seq,
                        "x": x,
                        "y": y,
                        "theta": 0.0,
                    }
                ),
            )
            seq += 1
            if not goal_sent or (not answered and seq % 50 == 0):  # until the controller answers
                s.put(
                    f"confnav/robot/{rid}/goal",
                    json.dumps(
                        {
                            "type": "confnav.Goal",
                            "schema_version": 1,
                            "robot_id": rid,
                            "ws_id": ws,
                            "goal": [gx, gy],
                        }
                    ),
                )
                goal_sent = True
            if done:
                break
            time.sleep(0.02)
    dist = math.hypot(x - gx, y - gy)
    print(f"{state['state'] or 'no status'} ({state['reason']}): travelled {travelled:.3f} m, "
          f"{dist:.3f} m from the goal after {time.monotonic() - t0:.1f} s")  # fmt: skip
    return 0 if state["state"] == "arrived" and dist <= 0.05 else 1


if __name__ == "__main__":
    a = sys.argv[1:]
    sys.exit(main(a[0], a[1], a[2], a[3], a[4], float(a[5]) if len(a) > 5 else 120.0))
