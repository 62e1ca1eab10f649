"""The live view: ``FoxgloveLiveService`` over real Zenoh, read by a WebSocket client speaking
Foxglove's WebSocket protocol (the ``websockets`` package): advertised channels, a scene with the
workspace polygon, the robot at its pose and its goal, and the status passed through."""

from __future__ import annotations

import asyncio
import json
import struct
import time
from typing import Any

import pytest
import websockets
from conftest import square_definition

from confnav.schemas import Goal, Pose, RobotStatus, encode
from confnav.services.foxglove_live import FoxgloveLiveService
from confnav.services.keys import Keys

pytestmark = pytest.mark.integration

K = Keys()
SCENE = "confnav/viz/room/scene"
STATUS = "confnav/robot/r1/status"
SUBPROTOCOL = "foxglove.sdk.v1"
"""foxglove-sdk 0.30 accepts only this name of the protocol (the successor of
``foxglove.websocket.v1``, same ops and binary framing); it rejects a client offering only
the old name with HTTP 400."""


def _publish(bus: Any) -> None:
    bus.publish(K.ws("room", "definition"), encode(square_definition("room", [(0.3, 0.3)])))
    bus.publish(K.robot("r1", "goal"), encode(Goal(robot_id="r1", ws_id="room", goal=(-0.5, 0.25))))
    for i in range(3):
        pose = Pose(robot_id="r1", stamp_ns=time.time_ns(), seq=i, x=0.1 * i, y=-0.2, theta=0.5)
        bus.publish(K.robot("r1", "pose"), encode(pose))
    status = RobotStatus(
        robot_id="r1", stamp_ns=time.time_ns(), state="navigating", reason="ok", ws_id="room"
    )
    bus.publish(K.robot("r1", "status"), encode(status))


async def _client(port: int, bus: Any) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL, "foxglove.websocket.v1"]
    ) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        info = json.loads(await asyncio.wait_for(ws.recv(), 5))
        assert info["op"] == "serverInfo"
        channels: dict[str, dict[str, Any]] = {}
        _publish(bus)
        while SCENE not in channels or STATUS not in channels:
            msg = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                for ch in json.loads(msg)["channels"]:
                    channels[ch["topic"]] = ch
        subs = {1: channels[SCENE]["id"], 2: channels[STATUS]["id"]}
        await ws.send(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [{"id": s, "channelId": c} for s, c in subs.items()],
                }
            )
        )
        got: dict[int, dict[str, Any]] = {}
        deadline = time.monotonic() + 10
        republish = 0.0
        while len(got) < 2 or not _has_robot(got.get(1)):
            now = time.monotonic()
            if now > deadline:
                raise AssertionError(f"no scene with the robot and goal; got {sorted(got)}")
            if now > republish:  # messages sent before the subscription are not replayed
                _publish(bus)
                republish = now + 0.5
            msg = await asyncio.wait_for(ws.recv(), 5)
            if isinstance(msg, bytes) and msg[0] == 0x01:  # MessageData
                sub_id, _log_time = struct.unpack_from("<IQ", msg, 1)
                got[sub_id] = json.loads(msg[13:])
        return channels[SCENE], got[1], got[2]


def _has_robot(scene: dict[str, Any] | None) -> bool:
    ids = {e["id"] for e in (scene or {}).get("entities", [])}
    return {"workspace", "robot/r1", "goal/r1"} <= ids


def test_live_scene_over_websocket(make_bus: Any) -> None:
    service_bus, pub_bus = make_bus(), make_bus()
    svc = FoxgloveLiveService(service_bus, port=0, full_period=0.3, health_period=0)
    svc.start()
    try:
        channel, scene, status = asyncio.run(_client(svc.port, pub_bus))
    finally:
        svc.stop()
    assert channel["schemaName"] == "foxglove.SceneUpdate"
    assert channel["encoding"] == "json"
    assert channel["schemaEncoding"] == "jsonschema"
    ents = {e["id"]: e for e in scene["entities"]}
    outer = [(p["x"], p["y"]) for p in ents["workspace"]["lines"][0]["points"]]
    assert outer[:4] == [(-0.7, -0.7), (0.7, -0.7), (0.7, 0.7), (-0.7, 0.7)]
    assert len(ents["workspace"]["lines"]) == 2  # outer polygon and one obstacle
    cube = ents["robot/r1"]["cubes"][0]["pose"]["position"]
    assert (cube["x"], cube["y"]) == (pytest.approx(0.2), pytest.approx(-0.2))
    goal = ents["goal/r1"]["spheres"][0]["pose"]["position"]
    assert (goal["x"], goal["y"]) == (pytest.approx(-0.5), pytest.approx(0.25))
    assert status["type"] == "confnav.RobotStatus" and status["state"] == "navigating"
