"""Foxglove scene channels in MCAP files: registration, the recorder hook and ``confnav viz``.

:class:`SceneChannels` registers the vendored ``foxglove.SceneUpdate`` schema and one channel
per scene topic on an :class:`mcap.writer.Writer`; :class:`FoxgloveSceneWriter` is the hook the
recorder calls for every recorded message (decoded with the confnav schemas, fed to a
:class:`~confnav.recording.scene_builder.SceneBuilder`); :func:`add_scene_channels` copies a
finished recording adding those channels (``confnav viz``).
"""

from __future__ import annotations

import json
import logging
import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mcap.writer import CompressionType, Writer

from confnav.errors import ConfnavError
from confnav.recording.reader import Recording, RecordingError, decode_message
from confnav.recording.scene import (
    MESSAGE_ENCODING,
    SCENE_SCHEMA_NAME,
    SCHEMA_ENCODING,
    is_viz_topic,
    scene_update_schema_text,
)
from confnav.recording.scene_builder import (
    DEFAULT_FULL_PERIOD_NS,
    DEFAULT_PERIOD_NS,
    DEFAULT_TRAIL_POINTS,
    MapLike,
    SceneBuilder,
    SceneMessage,
    decode_on_key,
)
from confnav.schemas import DecodeError, Message, TransformSolution
from confnav.services.keys import Keys

logger = logging.getLogger(__name__)


class SceneChannels:
    """Registers the ``foxglove.SceneUpdate`` schema and scene channels lazily on a Writer."""

    def __init__(self, writer: Writer) -> None:
        self._writer = writer
        self._schema_id: int | None = None
        self._channels: dict[str, int] = {}

    def channel_id(self, topic: str) -> int:
        if self._schema_id is None:
            self._schema_id = self._writer.register_schema(
                name=SCENE_SCHEMA_NAME,
                encoding=SCHEMA_ENCODING,
                data=scene_update_schema_text().encode("utf-8"),
            )
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=self._schema_id
            )
        return self._channels[topic]

    def write(self, msg: SceneMessage) -> None:
        data = json.dumps(msg.message, separators=(",", ":")).encode("utf-8")
        self._writer.add_message(
            channel_id=self.channel_id(msg.topic),
            log_time=msg.log_time_ns,
            publish_time=msg.log_time_ns,
            data=data,
        )


class FoxgloveSceneWriter:
    """Recorder hook: adds the Foxglove scene channels to a recording as it is written.

    Usage in the recorder (on the thread that owns the writer, never in a Zenoh callback)::

        viz = FoxgloveSceneWriter(writer, prefix)
        ...                                   # for every recorded message:
        writer.add_message(channel_id, log_time_ns, data, publish_time_ns)
        viz.on_message(topic, data, log_time_ns)
        ...
        viz.close(last_log_time_ns)           # before writer.finish()

    A message that does not decode with its key's schema, or a map that does not load, is
    logged (the first of each topic as a warning) and counted in :attr:`errors` by reason; the
    recording goes on. Anything else is a bug and propagates.
    """

    def __init__(
        self,
        writer: Writer,
        prefix: str = "confnav",
        *,
        period_ns: int = DEFAULT_PERIOD_NS,
        full_period_ns: int = DEFAULT_FULL_PERIOD_NS,
        trail_points: int = DEFAULT_TRAIL_POINTS,
        map_loader: Callable[[TransformSolution], MapLike] | None = None,
    ) -> None:
        self.keys = Keys(prefix)
        self.builder = SceneBuilder(
            prefix,
            period_ns=period_ns,
            full_period_ns=full_period_ns,
            trail_points=trail_points,
            map_loader=map_loader,
        )
        self.channels = SceneChannels(writer)
        self.errors: Counter[str] = Counter()
        self._warned: set[str] = set()
        self._last_ns = 0

    def on_message(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Observe one recorded message (raw JSON bytes on key ``topic``), write scenes due."""
        self._last_ns = max(self._last_ns, int(log_time_ns))
        try:
            message = decode_on_key(self.keys, topic, data)
        except DecodeError as exc:
            self._error(topic, exc.reason, exc)
            return
        if message is not None:  # None: not a confnav message key, nothing to draw
            self.observe(topic, message, log_time_ns)

    def observe(self, topic: str, message: Message, log_time_ns: int) -> None:
        """Observe one decoded message and write the scenes due."""
        self._last_ns = max(self._last_ns, int(log_time_ns))
        try:
            scenes = self.builder.observe(message, int(log_time_ns))
        except (ConfnavError, ValueError) as exc:  # a map that does not load
            self._error(topic, "map", exc)
            scenes = self.builder.flush(int(log_time_ns))
        for msg in scenes:
            self.channels.write(msg)

    def _error(self, topic: str, reason: str, exc: Exception) -> None:
        self.errors[reason] += 1
        level = logging.DEBUG if topic in self._warned else logging.WARNING
        self._warned.add(topic)
        logger.log(level, "foxglove scene: %s on %s not drawn: %s", reason, topic, exc)

    def close(self, log_time_ns: int | None = None) -> None:
        """Write the final scenes (at ``log_time_ns``, default the last message's log time)."""
        now = self._last_ns if log_time_ns is None else int(log_time_ns)
        for msg in self.builder.flush(now):
            self.channels.write(msg)
        if self.errors:
            logger.warning("foxglove scene: messages not drawn: %s", dict(self.errors))


@dataclass
class VizReport:
    source: Path
    output: Path
    messages_copied: int = 0
    scene_messages: Counter[str] = field(default_factory=Counter)
    errors: Counter[str] = field(default_factory=Counter)  # messages not drawn, by reason


def add_scene_channels(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    period_ns: int = DEFAULT_PERIOD_NS,
) -> VizReport:
    """Copy ``source`` to ``output`` with the Foxglove scene channels added.

    Every schema, channel, message (times unchanged), metadata record and attachment is copied;
    scene channels already in ``source`` are dropped and regenerated.
    """
    src, dst = Path(source), Path(output)
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise RecordingError("the output must be a different file from the input")
    with Recording(src) as rec:
        prefix = rec.prefix
        report = VizReport(source=src, output=dst)
        tmp = dst.with_name(dst.name + ".part")
        with open(tmp, "wb") as f:
            writer = Writer(f, compression=CompressionType.ZSTD)
            writer.start(profile="confnav", library="confnav viz")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            schemas = rec.raw_schemas()
            for cid, ch in sorted(rec.raw_channels().items()):
                if is_viz_topic(ch.topic, prefix):
                    continue
                if ch.schema_id and ch.schema_id not in schema_ids:
                    s = schemas[ch.schema_id]
                    schema_ids[ch.schema_id] = writer.register_schema(
                        name=s.name, encoding=s.encoding, data=bytes(s.data)
                    )
                channel_ids[cid] = writer.register_channel(
                    topic=ch.topic,
                    message_encoding=ch.message_encoding,
                    schema_id=schema_ids.get(ch.schema_id, 0),
                    metadata=dict(ch.metadata),
                )
            for name, data in rec.metadata.items():
                writer.add_metadata(name, data)
            for att in rec.iter_attachments():
                writer.add_attachment(
                    create_time=att.create_time,
                    log_time=att.log_time,
                    name=att.name,
                    media_type=att.media_type,
                    data=bytes(att.data),
                )
            scenes = FoxgloveSceneWriter(writer, prefix, period_ns=period_ns)
            for msg in rec.iter_messages():
                if msg.channel_id not in channel_ids:
                    continue
                writer.add_message(
                    channel_id=channel_ids[msg.channel_id],
                    log_time=msg.log_time_ns,
                    data=msg.data,
                    publish_time=msg.publish_time_ns,
                    sequence=msg.sequence,
                )
                report.messages_copied += 1
                message = decode_message(msg)  # None: not a valid confnav message (logged)
                if message is not None:
                    scenes.observe(msg.topic, message, msg.log_time_ns)
            scenes.close()
            report.errors = scenes.errors
            writer.finish()  # type: ignore[no-untyped-call]
        os.replace(tmp, dst)
    with Recording(dst) as out:
        for c in out.channels.values():
            if c.schema_name == SCENE_SCHEMA_NAME:
                report.scene_messages[c.topic] += c.count
    return report


__all__ = ["FoxgloveSceneWriter", "SceneChannels", "VizReport", "add_scene_channels"]
