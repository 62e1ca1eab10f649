"""``confnav serve foxglove``: the running system, live in the Foxglove app.

Serves Foxglove's WebSocket protocol (``foxglove.websocket.v1``) through the official
``foxglove-sdk``: open Foxglove, "Open connection", ``ws://HOST:PORT`` (default
``ws://127.0.0.1:8765``). The scene is the one the recordings carry, built by the same
:class:`confnav.recording.scene_builder.SceneBuilder` from the same messages: per workspace
``{prefix}/viz/{ws}/scene`` (polygons, robots, trails, goals; frame ``workspace``) and
``{prefix}/viz/{ws}/circle_domain``; the robots' and workspaces' status messages are passed
through unchanged on their own keys (``{prefix}/robot/{r}/status``, ``{prefix}/ws/{ws}/status``,
JSON with the confnav JSON Schema).

A full scene goes out every ``full_period`` seconds even when nothing moves, so a client that
connects late sees the workspace at once; on start the service asks the transform services
for the solved maps (the queryable on ``{prefix}/ws/*/transform``).

Every channel is latched: when a client subscribes, the channel's latest message is sent again
(a scene channel gets a full scene), so the first message of a channel (logged before any
client could subscribe to the channel it created) and a status older than the client still
reach it. The re-send runs on a worker thread, not in the SDK's ``on_subscribe`` callback
(foxglove-sdk may call it before the client's sink is attached to the channel, and a message
logged there is dropped: foxglove/foxglove-sdk pull request 533).

Clients may publish (``clientPublish`` capability, JSON): a message on a client channel named
``{prefix}/robot/{r}/goal`` is validated as a :class:`confnav.schemas.Goal` for robot ``r``
and put on the bus under that key, as ``confnav goal`` would; anything else is counted as
rejected and logged, never raised.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import queue
import re
import threading
import time
from typing import TYPE_CHECKING, Any

from confnav.schemas import DecodeError, Goal, decode, encode, schema_bytes, schema_name
from confnav.services.bus import Bus
from confnav.services.keys import Keys
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal

from confnav.errors import ConfnavError
from confnav.recording.scene import (
    MESSAGE_ENCODING,
    SCENE_SCHEMA_NAME,
    SCHEMA_ENCODING,
    scene_update_schema_text,
)
from confnav.recording.scene_builder import SceneBuilder, SceneMessage, decode_on_key

if TYPE_CHECKING:
    from foxglove.websocket import ServerListener

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
STATUS_KINDS = ("status",)  # passed through as they are (robot and workspace status)
LATCH_AGAIN_S = 0.3  # a subscription's latched message is sent at once and again after this
SDK_CLIENT_LOGGER = "foxglove.websocket.connected_client"  # where the SDK logs refusals


class FoxgloveLiveService(Service):
    """See the module docstring. ``port=0`` picks a free port (then read :attr:`port`)."""

    name = "foxglove"

    def __init__(
        self,
        bus: Bus,
        keys: Keys | None = None,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        full_period: float = 1.0,
        health_period: float = 1.0,
    ) -> None:
        super().__init__(bus, keys, health_period)
        self.host = host
        self.port = port
        self.full_period = full_period
        self._builder = SceneBuilder(self.keys.prefix)
        self._lock = threading.Lock()  # the builder and the channel table
        self._channels: dict[str, Any] = {}
        self._latest: dict[str, tuple[str, int]] = {}  # status topic -> (payload, log time)
        # topics a client subscribed to; ids of channels a client was told are unknown (int)
        self._resend: queue.Queue[str | int | None] = queue.Queue()
        self._schemas: dict[str, tuple[str, bytes]] = {}  # topic -> (schema name, schema)
        self._unknown = _UnknownChannelHandler(self._resend)
        self._client_topics: dict[tuple[int, int], str] = {}  # (client, client channel) -> topic
        self._server: Any = None
        self._ctx: Any = None

    def _start(self) -> None:
        import foxglove  # 0.6 s to import: only where the live view runs
        from foxglove.websocket import Capability

        self._ctx = foxglove.Context()
        self._server = foxglove.start_server(
            name="confnav",
            host=self.host,
            port=self.port,
            context=self._ctx,
            capabilities=[Capability.ClientPublish],
            supported_encodings=["json"],
            server_listener=_listener(self),
        )
        self.port = int(self._server.port)
        self._handles.append(self.bus.subscribe(self.keys.all(), self._on_message))
        self.spawn(self._periodic, "scene")
        self.spawn(self._latch, "latch")
        logging.getLogger(SDK_CLIENT_LOGGER).addHandler(self._unknown)
        log.info("foxglove live view on ws://%s:%d", self.host, self.port)

    def stop(self) -> None:
        super().stop()
        logging.getLogger(SDK_CLIENT_LOGGER).removeHandler(self._unknown)
        self._resend.put(None)
        if self._server is not None:
            self._server.stop()
            self._server = None

    # latching and client publishing ---------------------------------------------------------
    def _latch(self) -> None:
        """Re-send a channel's latest message to the clients when one subscribes to it: at
        once, and again after :data:`LATCH_AGAIN_S` (the SDK may attach the new client's sink
        to the channel only after ``on_subscribe``: a message logged before is not sent to
        it, foxglove/foxglove-sdk pull request 533). Duplicates are harmless: a status or a
        full scene replaces the last one."""
        due: list[tuple[float, str]] = []  # second sends: (monotonic time, topic)
        while not self._stop.is_set():
            timeout = max(0.0, due[0][0] - time.monotonic()) if due else None
            try:
                item = self._resend.get(timeout=timeout)
            except queue.Empty:
                item = heapq.heappop(due)[1]
            if item is None:
                return
            try:
                with self._lock:
                    topic = self._reopen(item) if isinstance(item, int) else item
                    if topic is None:
                        continue
                    heapq.heappush(due, (time.monotonic() + LATCH_AGAIN_S, topic))
                    now = time.time_ns()
                    if topic in self._latest:
                        payload, _t = self._latest[topic]
                        self._channels[topic].log(payload, log_time=now)
                        self.count("latched")
                    else:  # a scene channel: a full scene of every workspace
                        self._send(self._builder.flush(now))
            except Exception:
                self.count("errors")
                log.exception("latched re-send of %s failed", item)

    def _reopen(self, channel_id: int) -> str | None:
        """A client was refused channel ``channel_id`` as unknown (foxglove-sdk 0.30: a channel
        created while a client is connected can be advertised to it before the server knows
        it; the client then never hears from it). Close the channel and open it again under a
        new id: clients get unadvertise + advertise and subscribe again. Returns its topic
        (None when the id is not one of ours, or no longer open)."""
        topic = next((t for t, ch in self._channels.items() if ch.id() == channel_id), None)
        if topic is None:
            return None
        self._channels.pop(topic).close()
        self._channel(topic, *self._schemas[topic])
        self.count("channels_reopened")
        log.info("channel %d (%s) refused to a client as unknown: re-advertised", channel_id, topic)
        return topic

    def _on_client_message(self, topic: str, data: bytes) -> None:
        """A client's message: a Goal on ``{prefix}/robot/{r}/goal`` goes to the bus."""
        try:
            parsed = self.keys.parse(topic)
            if parsed.group != "robot" or parsed.kind != "goal":
                raise ValueError(f"clients may publish Goals only, not on {topic!r}")
            goal = decode(Goal, data)
            if goal.robot_id != parsed.ident:
                raise ValueError(f"goal for {goal.robot_id!r} on {topic!r}")
        except (DecodeError, ValueError) as exc:
            self.count("client_rejected")
            log.warning("client message on %s rejected: %s", topic, exc)
            return
        self.bus.publish(self.keys.robot(goal.robot_id, "goal"), encode(goal))
        self.count("client_goals")

    # channels -----------------------------------------------------------------------------
    def _channel(self, topic: str, schema: str, data: bytes) -> Any:
        import foxglove

        ch = self._channels.get(topic)
        if ch is None:
            self._schemas[topic] = (schema, data)
            ch = self._channels[topic] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=schema, encoding=SCHEMA_ENCODING, data=data),
                message_encoding=MESSAGE_ENCODING,
                context=self._ctx,
            )
        return ch

    def _send(self, messages: list[SceneMessage]) -> None:
        schema = scene_update_schema_text().encode()
        for m in messages:
            ch = self._channel(m.topic, SCENE_SCHEMA_NAME, schema)
            ch.log(json.dumps(m.message, separators=(",", ":")), log_time=m.log_time_ns)
            self.count("scenes")

    # input --------------------------------------------------------------------------------
    def _on_message(self, key: str, payload: bytes) -> None:
        try:
            message = decode_on_key(self.keys, key, payload)
        except DecodeError as exc:
            self.count("rejected")
            log.warning("rejected %s: %s", key, exc)
            return
        if message is None:
            return
        now = time.time_ns()
        with self._lock:
            if key.rsplit("/", 1)[-1] in STATUS_KINDS:
                model = type(message)
                ch = self._channel(key, schema_name(model), schema_bytes(model))
                text = payload.decode("utf-8", "replace")
                self._latest[key] = (text, now)
                ch.log(text, log_time=now)
                self.count("status")
                return
            try:
                scenes = self._builder.observe(message, now)
            except (ConfnavError, ValueError) as exc:  # a map that does not load
                self.count("errors")
                log.warning("map on %s not drawn: %s", key, exc)
                scenes = self._builder.flush(now)
            self._send(scenes)

    def _periodic(self) -> None:
        self._fetch_maps()
        while not self._stop.wait(self.full_period):
            with self._lock:
                try:
                    self._send(self._builder.flush(time.time_ns()))
                except Exception:
                    self.count("errors")
                    log.exception("periodic scene failed")

    def _fetch_maps(self) -> None:
        try:
            replies = self.bus.query(self.keys.any_ws("transform"), timeout=2.0)
        except Exception as exc:
            log.info("no maps fetched at start: %s", exc)
            return
        for r in replies:
            if r.ok and r.payload is not None:
                self._on_message(r.key, r.payload)


class _UnknownChannelHandler(logging.Handler):
    """Catches foxglove-sdk's "attempted to subscribe to unknown channel: N" (logged through
    Python logging) and hands the channel id to the service's worker, which re-advertises it."""

    PATTERN = re.compile(r"subscribe to unknown channel: (\d+)")

    def __init__(self, out: queue.Queue[str | int | None]) -> None:
        super().__init__(logging.ERROR)
        self.out = out

    def emit(self, record: logging.LogRecord) -> None:
        m = self.PATTERN.search(record.getMessage())
        if m:
            self.out.put(int(m[1]))


def _listener(service: FoxgloveLiveService) -> ServerListener:
    """foxglove-sdk's ``ServerListener`` (subclassed, so every callback the SDK may call
    exists; the SDK's defaults do nothing): subscriptions trigger the latched re-send, client
    channels are remembered by (client, channel id), client messages go to the service. The
    callbacks run on the SDK's threads: they only hand work over and never raise."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            service._resend.put(str(channel.topic))

        def on_client_advertise(self, client: Any, channel: Any) -> None:
            service._client_topics[(int(client.id), int(channel.id))] = str(channel.topic)

        def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
            service._client_topics.pop((int(client.id), int(client_channel_id)), None)

        def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
            topic = service._client_topics.get((int(client.id), int(client_channel_id)))
            if topic is None:
                service.count("client_rejected")
                return
            service._on_client_message(topic, bytes(data))

    return Listener()


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "foxglove", help="serve the live scene to the Foxglove app (WebSocket)"
    )
    p.add_argument("--host", default="127.0.0.1", help="bind address (default %(default)s)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="WebSocket port")
    p.add_argument("--full-period", type=float, default=1.0, help="s between full scenes")
    add_zenoh_args(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    def make(bus: Bus, keys: Keys) -> Service:
        return FoxgloveLiveService(bus, keys, args.host, args.port, args.full_period)

    return run_until_signal(make, args)
