"""Recorder: everything under the prefix into one MCAP file (layout: :mod:`.mcap_layout`).

One channel per concrete key, the model's JSON Schema as channel schema, zstd chunks. A chunk
is closed and written to the OS at least every ``flush_interval`` seconds (the public
``mcap.writer.Writer.flush``), so a SIGKILL loses at most about that much (the non-seeking
reader, or ``confnav recover``, gets the rest); SIGINT/SIGTERM drain the queue and finish the
file.

An existing file is never truncated nor overwritten: each start writes a new file, ``--out``
itself if it does not exist yet, else the first free ``STEM.N.SUFFIX`` (``demo.mcap`` ->
``demo.1.mcap`` -> ``demo.2.mcap``...), created exclusively, so a restart (after a crash, by
the launcher) is visible as a new file next to the footer-less one ``confnav recover`` mends.

Payloads that are not valid messages are recorded too, on a raw channel with the same topic:
every message that reached the recorder is in the file.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path
from typing import IO, Any

from confnav.schemas import DecodeError, Message, decode, model_for_key_parts
from confnav.services.bus import Bus
from confnav.services.keys import KeyError_, Keys
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal
from mcap.writer import CompressionType, IndexType, Writer

from confnav.argtypes import output_path
from confnav.recording import layout as L

log = logging.getLogger(__name__)

MAX_RAW_BYTES = 64 * 1024 * 1024

#: Summary indexes written. Not the per-chunk message indexes: the writer keeps, until the
#: file is finished, one offset per channel of every chunk (with 100 robots, 400 channels in
#: every chunk, 2 or more chunks a second: its memory grew by about 150 kB/s, +20 % in 4 min
#: of the soak), while every chunk holds every robot's channels anyway, so they would not let
#: a reader skip chunks (readers scan the chunk instead; the format makes them optional).
INDEX_TYPES = IndexType.ALL & ~IndexType.MESSAGE


def free_path(path: str | Path) -> Path:
    """``path`` if nothing exists there, else the first ``STEM.N.SUFFIX`` (N = 1, 2...) free."""
    p = Path(path)
    n = 0
    cand = p
    while cand.exists():
        n += 1
        cand = p.with_name(f"{p.stem}.{n}{p.suffix}")
    return cand


def open_new(path: str | Path) -> tuple[Path, IO[bytes]]:
    """Create a new file at :func:`free_path` (exclusively: never truncates one, even if
    another process creates the same name meanwhile); return its path and binary stream."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    while True:
        cand = free_path(path)
        try:
            return cand, open(cand, "xb")
        except FileExistsError:
            continue


class Recorder(Service):
    """See the module docstring. ``config`` goes into the ``confnav`` metadata record;
    ``requested_path`` is ``path`` as given, ``path`` the file actually written (after start)."""

    name = "recorder"

    def __init__(
        self,
        bus: Bus,
        keys: Keys | None = None,
        path: str | Path = "confnav.mcap",
        config: dict[str, Any] | None = None,
        foxglove: bool = False,
        flush_interval: float = L.FLUSH_INTERVAL_S,
        chunk_size: int = L.CHUNK_SIZE,
        health_period: float = 1.0,
    ) -> None:
        super().__init__(bus, keys, health_period)
        self.requested_path = Path(path)
        self.path = Path(path)
        self.config = dict(config or {})
        self.flush_interval = flush_interval
        self.chunk_size = chunk_size
        self._foxglove = foxglove
        self._wlock = threading.Lock()
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._viz: Any = None
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[tuple[str, bool], int] = {}
        self._dirty = False
        self._finished = False
        self.recorded = 0

    def _start(self) -> None:
        self.path, self._stream = open_new(self.requested_path)
        if self.path != self.requested_path:
            log.warning("%s exists: recording to %s", self.requested_path, self.path)
        w = Writer(
            self._stream,
            chunk_size=self.chunk_size,
            compression=CompressionType.ZSTD,
            index_types=INDEX_TYPES,
        )
        w.start(
            profile=L.PROFILE,
            library=f"confnav-recorder {L.metadata_record('', {})['confnav_version']}",
        )
        w.add_metadata(L.METADATA_NAME, L.metadata_record(self.keys.prefix, self.config))
        self._writer = w
        if self._foxglove:
            from confnav.recording.scene_writer import FoxgloveSceneWriter

            self._viz = FoxgloveSceneWriter(w, self.keys.prefix)
        self._stream.flush()
        self._handles.append(self.bus.subscribe(self.keys.all(), self._on_message))
        self.spawn(self._flush_loop, "flush")
        log.info("recording %s to %s", self.keys.all(), self.path)

    # writing ---------------------------------------------------------------------------
    def _channel(self, key: str, model: type[Message] | None) -> int:
        w = self._writer
        assert w is not None
        valid = model is not None
        cid = self._channels.get((key, valid))
        if cid is not None:
            return cid
        if model is not None:
            sid = self._schemas.get(model)
            if sid is None:
                sid = w.register_schema(
                    name=L.schema_name(model), encoding=L.SCHEMA_ENCODING, data=L.schema_data(model)
                )
                self._schemas[model] = sid
            cid = w.register_channel(topic=key, message_encoding=L.MESSAGE_ENCODING, schema_id=sid)
        else:
            cid = w.register_channel(
                topic=key,
                message_encoding=L.RAW_MESSAGE_ENCODING,
                schema_id=0,
                metadata=dict(L.INVALID_CHANNEL_METADATA),
            )
        self._channels[(key, valid)] = cid
        return cid

    def _on_message(self, key: str, payload: bytes) -> None:
        log_time = L.log_time_ns()
        msg: Message | None = None
        model: type[Message] | None = None
        try:
            parsed = self.keys.parse(key)
            model = model_for_key_parts(parsed.group, parsed.kind)
            if model is not None:
                msg = decode(model, payload, limit=max(len(payload), 1))
        except (KeyError_, DecodeError):
            msg = None
        if msg is None:
            model = None
            self.count("recorded_raw")
            payload = payload[:MAX_RAW_BYTES]
        with self._wlock:
            if self._writer is None or self._finished:
                self.count("dropped_after_finish")
                return
            cid = self._channel(key, model)
            self._writer.add_message(
                channel_id=cid,
                log_time=log_time,
                data=payload,
                publish_time=L.publish_time_ns(msg, log_time),
            )
            self.recorded += 1
            self._dirty = True
            if self._viz is not None and msg is not None:
                self._viz.on_message(key, payload, log_time)
        self.count("recorded")

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (survives a SIGKILL)."""
        with self._wlock:
            if self._writer is None or self._finished or not self._dirty:
                return
            self._writer.flush()  # type: ignore[no-untyped-call]  # closes the chunk, writes
            self._dirty = False

    def health_detail(self) -> tuple[str, str]:
        return "ok", f"file {self.path}"

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval):
            try:
                self.flush()
            except Exception:
                log.exception("flush failed")

    def stop(self) -> None:
        """Stop receiving, write what is queued, finish the file (summary, index)."""
        super().stop()  # closes the subscription after its queue is drained
        with self._wlock:
            if self._writer is not None and not self._finished:
                if self._viz is not None:
                    self._viz.close()
                self._writer.finish()  # type: ignore[no-untyped-call]
                self._finished = True
            if self._stream is not None:
                self._stream.close()
                self._stream = None
        log.info("recording finished: %d messages in %s", self.recorded, self.path)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("recorder", help="record everything to MCAP")
    add_zenoh_args(p)
    p.add_argument(
        "--out",
        type=output_path,
        default="confnav.mcap",
        help="MCAP file to write; if it exists, the first free OUT-STEM.N.mcap instead",
    )
    p.add_argument("--foxglove", action="store_true", help="add Foxglove scene channels")
    p.add_argument(
        "--flush-interval", type=float, default=L.FLUSH_INTERVAL_S, help="s between flushes"
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    config = {k: v for k, v in vars(args).items() if k != "func"}
    return run_until_signal(
        lambda bus, keys: Recorder(
            bus,
            keys,
            args.out,
            config,
            foxglove=args.foxglove,
            flush_interval=args.flush_interval,
        ),
        args,
    )
