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
from confnav.schemas import Goal, Pose, RobotStatus, decode, encode
from confnav.services.foxglove_live import FoxgloveLiveService
from confnav.services.keys import Keys
from conftest import square_definition

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
        request = json.dumps(
            {
                "op": "subscribe",
                "subscriptions": [{"id": s, "channelId": c} for s, c in subs.items()],
            }
        )
        await ws.send(request)
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
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                # a channel re-advertised (the service does so when foxglove-sdk refused a
                # subscription to it as unknown): subscribe again, as the Foxglove app does
                for ch in json.loads(msg)["channels"]:
                    for sub_id, topic in ((1, SCENE), (2, STATUS)):
                        if ch["topic"] == topic:
                            channels[topic] = ch
                            again = {"id": sub_id, "channelId": ch["id"]}
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [again]}))
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


def test_demo_live_and_manifest_entries(tmp_path: Any) -> None:
    import shlex
    import tomllib

    from confnav.services.demo import demo_config
    from confnav.services.launcher import LaunchConfig
    from conftest import REPO

    from confnav.cli.app import build_parser

    parser = build_parser()
    assert parser.parse_args(["demo", "--live"]).live == 8765
    assert parser.parse_args(["demo", "--live", "9000"]).live == 9000
    assert parser.parse_args(["demo"]).live is None
    cfg = demo_config("unixsock-stream/x", tmp_path, {"r1": 0j}, 1.0, None, live_port=9000)
    assert [s.name for s in cfg.services][:2] == ["foxglove", "recorder"]
    assert cfg.services[0].args == ["--port", "9000"]
    assert "foxglove" not in [s.name for s in demo_config("u", tmp_path, {}, 1.0, None).services]

    # deploy/local.toml: both entries present and valid, off by default (enabled = false)
    path = REPO / "deploy" / "local.toml"
    raw = {s["name"]: s for s in tomllib.loads(path.read_text())["service"]}
    assert raw["foxglove"]["enabled"] is False and raw["ros2"]["enabled"] is False
    assert not {"ros2", "foxglove"} & {s.name for s in LaunchConfig.load(path).services}
    for name in ("ros2", "foxglove"):
        args = parser.parse_args(["serve", name, *raw[name]["args"]])
        assert callable(args.func), shlex.join(raw[name]["args"])
    on = dict(raw["ros2"], enabled=True)
    assert [s.name for s in LaunchConfig.from_dict({"service": [on]}).services] == ["ros2"]


async def _connect(port: int) -> Any:
    ws = await websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL, "foxglove.websocket.v1"]
    )
    assert ws.subprotocol == SUBPROTOCOL
    return ws


async def _advertised(ws: Any, topic: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """serverInfo, then the advertisement of ``topic`` (waiting for it, 10 s)."""
    info = json.loads(await asyncio.wait_for(ws.recv(), 5))
    assert info["op"] == "serverInfo"
    while True:
        msg = await asyncio.wait_for(ws.recv(), 10)
        if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
            for ch in json.loads(msg)["channels"]:
                if ch["topic"] == topic:
                    return info, ch


def test_a_late_client_gets_the_latest_status_without_a_new_one(make_bus: Any) -> None:
    """Latched channels: statuses published once, before any client connected (the first
    messages of their channel, logged as the channel was created), reach a client that
    subscribes afterwards: the latest one, with nothing published again."""
    service_bus, pub_bus = make_bus(), make_bus()
    svc = FoxgloveLiveService(service_bus, port=0, full_period=30.0, health_period=0)
    svc.start()
    try:
        for state in ("navigating", "stopped"):
            status = RobotStatus(
                robot_id="r1", stamp_ns=time.time_ns(), state=state, reason="ok", ws_id="room"
            )
            seen = svc.counters["status"]
            deadline = time.monotonic() + 10
            # the first one is put again until the service's subscription is routed (Zenoh
            # drops what is put before the two sessions know of each other: seen once on a
            # loaded machine); the second then goes once, over the route that exists
            pub_bus.publish(K.robot("r1", "status"), encode(status))
            while svc.counters["status"] == seen:
                assert time.monotonic() < deadline, "the service never got the status"
                time.sleep(0.2)
                if state == "navigating" and svc.counters["status"] == seen:
                    pub_bus.publish(K.robot("r1", "status"), encode(status))

        async def late_client() -> dict[str, Any]:
            ws = await _connect(svc.port)
            try:
                _info, ch = await _advertised(ws, STATUS)
                sub = {"id": 7, "channelId": ch["id"]}
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
                while True:  # an event: the latched message (10 s per frame, no re-publish)
                    msg = await asyncio.wait_for(ws.recv(), 10)
                    if isinstance(msg, bytes) and msg[0] == 0x01:
                        sub_id, _t = struct.unpack_from("<IQ", msg, 1)
                        assert sub_id == 7
                        return dict(json.loads(msg[13:]))
            finally:
                await ws.close()

        got = asyncio.run(late_client())
    finally:
        svc.stop()
    assert got["type"] == "confnav.RobotStatus" and got["state"] == "stopped"


def test_a_client_publishes_a_goal_that_reaches_the_bus(make_bus: Any) -> None:
    """clientPublish: a Goal a Foxglove client publishes (JSON) on ``confnav/robot/r9/goal``
    is validated and put on the bus; a goal naming another robot, or a message on a key that
    is not a goal, is rejected (counted) and never reaches the bus."""
    service_bus, listen_bus = make_bus(), make_bus()
    goals: list[Goal] = []
    listen_bus.subscribe(K.any_robot("goal"), lambda k, p: goals.append(decode(Goal, p)))
    svc = FoxgloveLiveService(service_bus, port=0, full_period=30.0, health_period=0)
    svc.start()
    try:

        async def publishing_client() -> dict[str, Any]:
            ws = await _connect(svc.port)
            try:
                info = json.loads(await asyncio.wait_for(ws.recv(), 5))
                channels = [
                    {"id": 1, "topic": K.robot("r9", "goal"), "encoding": "json",
                     "schemaName": "confnav.Goal"},
                    {"id": 2, "topic": K.robot("r9", "pose"), "encoding": "json",
                     "schemaName": "confnav.Pose"},
                ]  # fmt: skip
                await ws.send(json.dumps({"op": "advertise", "channels": channels}))

                def data(channel: int, message: Any) -> bytes:  # client MessageData, op 0x01
                    return struct.pack("<BI", 0x01, channel) + json.dumps(message).encode()

                wrong = json.loads(encode(Goal(robot_id="r8", ws_id="room", goal=(0.1, 0.2))))
                await ws.send(data(1, wrong))
                await ws.send(data(2, {"robot_id": "r9"}))
                good = json.loads(encode(Goal(robot_id="r9", ws_id="room", goal=(-0.5, 0.25))))
                await ws.send(data(1, good))
                deadline = time.monotonic() + 10
                while not goals:  # an event: the goal on the bus
                    assert time.monotonic() < deadline, "the client's goal never reached the bus"
                    await asyncio.sleep(0.02)
                return dict(info)
            finally:
                await ws.close()

        info = asyncio.run(publishing_client())
        deadline = time.monotonic() + 10
        while svc.counters["client_rejected"] < 2:
            assert time.monotonic() < deadline, dict(svc.counters)
            time.sleep(0.02)
    finally:
        svc.stop()
    assert "clientPublish" in info["capabilities"]
    assert "json" in info.get("supportedEncodings", [])
    assert [(g.robot_id, g.ws_id, g.goal) for g in goals] == [("r9", "room", (-0.5, 0.25))]
    assert svc.counters["client_goals"] == 1


def test_a_unicycle_is_drawn_in_the_circle_domain_of_the_map_it_drives_on() -> None:
    """A unicycle of radius r and look-ahead d drives on the map of its workspace shrunk by
    r + d (``{ws}~r{r+d}``) and the map steers the point d ahead of its axle: that point is
    drawn in the shrunk workspace's circle domain, and the robot is not drawn in the circle
    domain of the unshrunk map it does not drive on."""
    import math
    import types

    from confnav.schemas import SolveDiagnostics, TransformSolution, WorkspaceDefinition

    from confnav.maps.footprint import derived_ws_id
    from confnav.recording import scene_builder as sb

    square = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]

    class Scaled:  # T(z) = z * s: stand-in maps with their workspace's polygons
        def __init__(self, s: float) -> None:
            self.s = s
            outer = [complex(*p) for p in square]
            self.workspace = types.SimpleNamespace(outer=outer, obstacles=[])

        def T(self, z: Any) -> Any:
            return z * self.s

    def solution(ws_id: str) -> TransformSolution:
        diag = SolveDiagnostics(
            sweeps=1, error_estimate=0.0, wall_time=0.0, tol=1e-10, boundary_residual=0.0,
            tol_met=True,
        )  # fmt: skip
        return TransformSolution(
            ws_id=ws_id, revision="r", definition_hash="d", workspace_hash="h", stamp_ns=1,
            anchor=(0.0, 0.0), centers=[(0.5, 0.5)], radii=[0.1], diagnostics=diag,
            coefficients={},
        )  # fmt: skip

    shrunk = derived_ws_id("w1", 0.2 + 0.1)
    maps = {"w1": Scaled(0.5), shrunk: Scaled(1 / 3)}
    builder = sb.SceneBuilder(period_ns=0, map_loader=lambda sol: maps[sol.ws_id])
    t = 1_700_000_000_000_000_000
    builder.observe(WorkspaceDefinition(ws_id="w1", outer=square, obstacles=[]), t)
    goal = Goal(
        robot_id="u1", ws_id="w1", goal=(0.0, 0.0), drive="unicycle", robot_radius=0.2,
        lookahead=0.1,
    )  # fmt: skip
    builder.observe(goal, t)
    builder.observe(Pose(robot_id="u1", stamp_ns=t, seq=0, x=0.3, y=-0.2, theta=0.5), t)
    builder.observe(solution("w1"), t)
    builder.observe(solution(shrunk), t)
    msgs = {m.topic: m.message for m in builder.flush(t + 1)}
    plain = msgs["confnav/viz/w1/circle_domain"]
    assert "robot/u1" not in {e["id"] for e in plain["entities"]}
    cd = msgs[f"confnav/viz/{shrunk}/circle_domain"]
    robot = next(e for e in cd["entities"] if e["id"] == "robot/u1")
    pos = robot["cubes"][0]["pose"]["position"]
    px, py = 0.3 + 0.1 * math.cos(0.5), -0.2 + 0.1 * math.sin(0.5)
    # scene coordinates are rounded to 1e-6
    assert pos["x"] == pytest.approx(px / 3, abs=1e-6)
    assert pos["y"] == pytest.approx(py / 3, abs=1e-6)
    # the workspace scene still shows the robot's body where it is
    body = next(e for e in msgs["confnav/viz/w1/scene"]["entities"] if e["id"] == "robot/u1")
    assert body["cubes"][0]["pose"]["position"]["x"] == pytest.approx(0.3)


def test_channels_created_while_a_client_is_connected_all_reach_it(mem_net: Any) -> None:
    """40 status channels created while a client is connected, the client subscribing to each
    as soon as it is advertised (as the Foxglove app does): foxglove-sdk 0.30 refuses some of
    those subscriptions as "unknown channel" (1-3 of 40 in every run here) and such a channel
    stayed silent; the service now re-advertises a refused channel, so every one delivers."""
    import logging

    from confnav.services import foxglove_live

    svc = FoxgloveLiveService(mem_net.bus("svc"), port=0, full_period=30.0, health_period=0)
    svc.start()
    pub = mem_net.bus("pub")
    n = 40

    async def client() -> set[str]:
        ws = await _connect(svc.port)
        try:
            await asyncio.wait_for(ws.recv(), 5)  # serverInfo
            for i in range(n):
                st = RobotStatus(
                    robot_id=f"q{i}", stamp_ns=time.time_ns(), state="navigating", reason="ok"
                )
                pub.publish(K.robot(f"q{i}", "status"), encode(st))
            subs: dict[int, str] = {}
            got: set[str] = set()
            deadline = time.monotonic() + 20  # an event with a generous timeout
            while len(got) < n:
                assert time.monotonic() < deadline, f"{n - len(got)} channels stayed silent"
                try:
                    msg = await asyncio.wait_for(ws.recv(), 1)
                except TimeoutError:
                    continue
                if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                    for ch in json.loads(msg)["channels"]:
                        subs[len(subs) + 1] = ch["topic"]
                        sub = {"id": len(subs), "channelId": ch["id"]}
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
                elif isinstance(msg, bytes) and msg[0] == 0x01:
                    got.add(subs[struct.unpack_from("<I", msg, 1)[0]])
            return got
        finally:
            await ws.close()

    try:
        got = asyncio.run(client())
        # a refusal the SDK logs is handled: the channel is re-advertised under a new id
        topic = K.robot("q0", "status")
        old = svc._channels[topic].id()
        logging.getLogger(foxglove_live.SDK_CLIENT_LOGGER).error(
            "Client 127.0.0.1:1 attempted to subscribe to unknown channel: %d", old
        )
        deadline = time.monotonic() + 10
        while svc._channels[topic].id() == old:
            assert time.monotonic() < deadline, "the refused channel was not re-advertised"
            time.sleep(0.02)
    finally:
        svc.stop()
    assert got == {K.robot(f"q{i}", "status") for i in range(n)}
    assert svc.counters["channels_reopened"] >= 1
