"""Reading confnav recordings: :class:`Recording` and :func:`decode_message`.

:class:`Recording` opens an MCAP file written by the recorder (layout in
:mod:`confnav.recording.layout`) with the indexed reader and turns format problems into
:class:`RecordingError` with a message that says what to do (not an MCAP file, no footer: run
``confnav recover``, ...). Times: MCAP ``log_time``/``publish_time`` are integer nanoseconds
since the Unix epoch.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.reader import McapReader, make_reader
from mcap.records import Channel, Schema

from confnav.errors import ConfnavError
from confnav.recording.layout import METADATA_NAME, RAW_MESSAGE_ENCODING
from confnav.recording.recover import MCAP_MAGIC, has_footer
from confnav.schemas import MODELS_BY_TYPE, DecodeError, Message, decode

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000


class RecordingError(ConfnavError):
    """A recording that cannot be read or lacks what a command needs."""


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded message: ``topic`` (the Zenoh key), raw ``data``, times in ns."""

    topic: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    schema_name: str
    message_encoding: str
    channel_id: int


@dataclass(frozen=True)
class ChannelInfo:
    """A channel of a recording with its message count and log-time range (ns)."""

    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    metadata: Mapping[str, str]
    count: int

    @property
    def invalid(self) -> bool:
        """The recorder's channel for payloads that were not valid messages."""
        return self.message_encoding == RAW_MESSAGE_ENCODING


class Recording:
    """An open, finished (indexed) MCAP recording.

    Raises :class:`RecordingError` if the file is missing, not an MCAP file, has no footer
    (writer killed: ``confnav recover`` fixes it) or its summary cannot be read.
    Use as a context manager.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: no such file")
        with open(self.path, "rb") as probe:
            if probe.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise RecordingError(f"{self.path}: not an MCAP file")
        if not has_footer(self.path):
            raise RecordingError(
                f"{self.path}: the MCAP file has no footer (the writer was killed before it "
                f"finished); run `confnav recover {self.path} -o FIXED.mcap` and use FIXED.mcap"
            )
        self._file: IO[bytes] = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        try:
            self._reader: McapReader = make_reader(self._file)
            summary = self._reader.get_summary()
            self.metadata: dict[str, dict[str, str]] = {
                m.name: dict(m.metadata) for m in self._reader.iter_metadata()
            }
        except (McapError, ValueError, OSError, EOFError) as exc:
            self._file.close()
            raise RecordingError(f"{self.path}: unreadable MCAP file: {exc}") from exc
        if summary is None:
            self._file.close()
            raise RecordingError(f"{self.path}: MCAP file without a summary section")
        self._schemas: dict[int, Schema] = dict(summary.schemas)
        self._channels: dict[int, Channel] = dict(summary.channels)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        self.message_count = summary.statistics.message_count if summary.statistics else 0
        self.start_ns = summary.statistics.message_start_time if summary.statistics else 0
        self.end_ns = summary.statistics.message_end_time if summary.statistics else 0
        self.channels: dict[int, ChannelInfo] = {}
        for cid, ch in sorted(self._channels.items()):
            schema = self._schemas.get(ch.schema_id)
            self.channels[cid] = ChannelInfo(
                id=cid,
                topic=ch.topic,
                message_encoding=ch.message_encoding,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                metadata=dict(ch.metadata),
                count=int(counts.get(cid, 0)),
            )

    def __enter__(self) -> Recording:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    @property
    def prefix(self) -> str:
        """Key prefix recorded in the ``confnav`` metadata (default ``confnav``)."""
        return self.metadata.get(METADATA_NAME, {}).get("prefix", "confnav")

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS_PER_S if self.message_count else 0.0

    def topics(self) -> list[str]:
        return sorted({c.topic for c in self.channels.values()})

    def raw_schemas(self) -> dict[int, Schema]:
        return dict(self._schemas)

    def raw_channels(self) -> dict[int, Channel]:
        return dict(self._channels)

    def iter_messages(self, topics: Iterable[str] | None = None) -> Iterator[RecordedMessage]:
        """Messages in log-time order (ties in file order), optionally only on ``topics``."""
        wanted = None if topics is None else list(topics)
        try:
            for schema, channel, msg in self._reader.iter_messages(
                topics=wanted, log_time_order=True
            ):
                yield RecordedMessage(
                    topic=channel.topic,
                    data=bytes(msg.data),
                    log_time_ns=int(msg.log_time),
                    publish_time_ns=int(msg.publish_time),
                    sequence=int(msg.sequence),
                    schema_name=schema.name if schema else "",
                    message_encoding=channel.message_encoding,
                    channel_id=channel.id,
                )
        except (McapError, ValueError, OSError, EOFError) as exc:
            raise RecordingError(f"{self.path}: corrupt data while reading: {exc}") from exc

    def iter_attachments(self) -> Iterator[Any]:
        return self._reader.iter_attachments()


def decode_message(msg: RecordedMessage) -> Message | None:
    """The confnav model instance of a recorded message, or None (not a confnav schema,
    recorded as invalid, or no longer valid: logged)."""
    if msg.message_encoding != "json":
        return None
    model = MODELS_BY_TYPE.get(msg.schema_name)
    if model is None:
        return None
    try:
        return decode(model, msg.data, limit=len(msg.data))
    except DecodeError as exc:
        logger.warning("%s at %d ns: %s", msg.topic, msg.log_time_ns, exc)
        return None


__all__ = ["ChannelInfo", "RecordedMessage", "Recording", "RecordingError", "decode_message"]
