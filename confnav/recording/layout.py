"""MCAP layout shared by the recorder (issue 4) and replay / inspect / recover (issue 5).

Conventions (keep exactly; readers depend on them):

- one channel per concrete Zenoh key; ``topic`` = the full key (``confnav/robot/r1/pose``);
  ``message_encoding`` = :data:`MESSAGE_ENCODING` (``"json"``);
- schema ``encoding`` = :data:`SCHEMA_ENCODING` (``"jsonschema"``), schema ``name`` =
  ``"confnav.<Model>"`` (:func:`schema_name`), schema ``data`` = the model's JSON Schema bytes
  (:func:`schema_data`, identical to ``confnav schemas export``);
- every payload also carries ``type`` (= the schema name) and ``schema_version``;
- a payload that reached the recorder but is not a valid message (malformed JSON, wrong
  version, unknown key...) is still recorded, on a second channel with the same topic,
  ``schema_id`` 0, ``message_encoding`` :data:`RAW_MESSAGE_ENCODING` and channel metadata
  ``{"confnav.invalid": "true"}``;
- ``log_time`` = recorder receive time, ``publish_time`` = the message's ``stamp_ns`` if it has
  a positive one, else ``log_time``; both integer nanoseconds since the Unix epoch;
- a recording may be split into segments (recorder ``--split-size`` / ``--split-duration``):
  each is a complete MCAP file that starts with the latched state (latest workspace
  definitions, transforms, atlas indexes, statuses, goals: :mod:`confnav.recording.latch`)
  re-written at the segment's start time, on channels with the same topic and schema and
  channel metadata :data:`LATCHED_CHANNEL_METADATA` (``{"confnav.latched": "true"}``):
  copies, to be skipped when counting or joining the messages of several segments;
- one metadata record named :data:`METADATA_NAME` (``"confnav"``) with the versions of
  confnav / zenoh / mcap, the key prefix and the JSON config of the recording; workspace
  definitions are recorded as their normal channel messages;
- zstd chunks of at most :data:`CHUNK_SIZE` bytes, and a chunk is closed at least every
  :data:`FLUSH_INTERVAL_S` seconds and written to the OS, so a SIGKILL loses at most about one
  second; SIGINT/SIGTERM finish the file (summary and index).
"""

from __future__ import annotations

import json
import time
from importlib import metadata as _md
from typing import Any, Final

from confnav.schemas import Message, schema_bytes
from confnav.schemas import schema_name as _schema_name

MESSAGE_ENCODING: Final = "json"
SCHEMA_ENCODING: Final = "jsonschema"
RAW_MESSAGE_ENCODING: Final = "x-confnav-raw"
INVALID_CHANNEL_METADATA: Final = {"confnav.invalid": "true"}
LATCHED_CHANNEL_METADATA: Final = {"confnav.latched": "true"}
METADATA_NAME: Final = "confnav"
#: 1 MiB: at 100 robots (4400 messages, 1.3 MB a second) chunks are then closed by the flush
#: (2 a second), not by size (8 a second with 256 KiB): the MCAP writer keeps about 450 bytes
#: of index for every chunk until the segment is finished (measured with tracemalloc replaying
#: the soak's traffic), 13 MB an hour at 256 KiB.
CHUNK_SIZE: Final = 1024 * 1024
FLUSH_INTERVAL_S: Final = 0.5
PROFILE: Final = "confnav"


def schema_name(model: type[Message]) -> str:
    """Schema name of a model, ``"confnav.<Model>"``."""
    return _schema_name(model)


def schema_data(model: type[Message]) -> bytes:
    """Schema data of a model: its JSON Schema (serialization mode), canonical bytes."""
    return schema_bytes(model)


def log_time_ns() -> int:
    """Recorder receive time, integer ns since the Unix epoch."""
    return time.time_ns()


def publish_time_ns(message: Message | None, log_time: int) -> int:
    """The message's own ``stamp_ns`` if it has a positive one, else ``log_time``."""
    stamp = getattr(message, "stamp_ns", None) if message is not None else None
    return stamp if isinstance(stamp, int) and stamp > 0 else log_time


def _version(dist: str) -> str:
    try:
        return _md.version(dist)
    except _md.PackageNotFoundError:
        return "unknown"


def metadata_record(prefix: str, config: dict[str, Any]) -> dict[str, str]:
    """Content of the ``confnav`` metadata record (all values strings, as MCAP requires)."""
    return {
        "confnav_version": _version("confnav"),
        "zenoh_version": _version("eclipse-zenoh"),
        "mcap_version": _version("mcap"),
        "prefix": prefix,
        "config": json.dumps(config, sort_keys=True, default=str),
        "created_ns": str(time.time_ns()),
    }
