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

Rotation: once the open segment holds ``split_size`` bytes or spans ``split_duration`` seconds
(checked at every flush; 0 turns either off), the writer is finished (summary and indexes
written, its memory freed: the mcap writer keeps one index entry per chunk until then) and the
next segment is created beside the first, ``STEM.partK.SUFFIX`` (K = 001, 002...; after a
restart ``demo.1.mcap`` -> ``demo.1.part001.mcap``), so both a restart and a split show in the
names. Every segment is a complete MCAP file: schemas, the metadata record (with the segment
number and the first segment's name) and the latched state (:mod:`confnav.recording.latch`:
latest definitions, transforms, atlas indexes, statuses, goals) re-written at its start on
channels marked ``confnav.latched``, so any segment alone replays, inspects and checks. The
switch happens under the writer lock: each message is in exactly one segment.

Payloads that are not valid messages are recorded too, on a raw channel with the same topic:
every message that reached the recorder is in the file.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from pathlib import Path
from typing import IO, Any, Final

from confnav.schemas import DecodeError, Message, decode, model_for_key_parts
from confnav.services.bus import Bus
from confnav.services.keys import KeyError_, Keys
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal
from mcap.writer import CompressionType, IndexType, Writer

from confnav.argtypes import output_path
from confnav.recording import allocator
from confnav.recording import layout as L
from confnav.recording.latch import LatchedState

log = logging.getLogger(__name__)

MAX_RAW_BYTES = 64 * 1024 * 1024

#: Summary indexes written. Not the per-chunk message indexes: the writer keeps, until the
#: file is finished, one offset per channel of every chunk (with 100 robots, 400 channels in
#: every chunk, 2 or more chunks a second: its memory grew by about 150 kB/s, +20 % in 4 min
#: of the soak), while every chunk holds every robot's channels anyway, so they would not let
#: a reader skip chunks (readers scan the chunk instead; the format makes them optional).
INDEX_TYPES = IndexType.ALL & ~IndexType.MESSAGE

#: Default rotation limits. 1 h bounds what the writer holds until a segment is finished (one
#: chunk index, about 450 bytes, a chunk: with 100 robots 2-3 chunks a second, about 4 MB an
#: hour) and keeps segments a size that copies, uploads and opens in Foxglove comfortably;
#: 512 MB caps a busy system's segment (100 robots at 20 Hz record about 0.6 GB an hour
#: compressed: 124 MB in the 12 min soak of bench/bench_chaos.py).
SPLIT_SIZE_MB: Final = 512.0
SPLIT_DURATION_S: Final = 3600.0

#: s between ``malloc_trim`` calls (:mod:`confnav.recording.allocator`; also after a split).
TRIM_INTERVAL_S: Final = 60.0


def free_path(path: str | Path) -> Path:
    """``path`` if nothing exists there, else the first ``STEM.N.SUFFIX`` (N = 1, 2...) free."""
    p = Path(path)
    n = 0
    cand = p
    while cand.exists():
        n += 1
        cand = p.with_name(f"{p.stem}.{n}{p.suffix}")
    return cand


def segment_path(first: str | Path, k: int) -> Path:
    """Name of segment ``k`` >= 1 of the recording whose first segment is ``first``:
    ``STEM.partK.SUFFIX``, K zero-padded to 3 digits (``demo.1.mcap``, k=2 ->
    ``demo.1.part002.mcap``)."""
    if k < 1:
        raise ValueError("segment numbers after the first start at 1")
    p = Path(first)
    return p.with_name(f"{p.stem}.part{k:03d}{p.suffix}")


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


def open_segment(first: Path, k: int) -> tuple[int, Path, IO[bytes]]:
    """Create segment ``k`` of ``first`` exclusively, or the next number free (a file left
    there is never overwritten); return its number, path and binary stream."""
    while True:
        cand = segment_path(first, k)
        try:
            return k, cand, open(cand, "xb")
        except FileExistsError:
            k += 1


class Recorder(Service):
    """See the module docstring. ``config`` goes into the ``confnav`` metadata record;
    ``requested_path`` is ``path`` as given, ``path`` the segment being written (after start),
    ``segments`` every file written so far. ``split_size`` (bytes) and ``split_duration`` (s)
    are the rotation limits, 0 = off."""

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
        split_size: int = int(SPLIT_SIZE_MB * 1e6),
        split_duration: float = SPLIT_DURATION_S,
    ) -> None:
        super().__init__(bus, keys, health_period)
        if split_size < 0 or not split_duration >= 0:
            raise ValueError("split_size and split_duration must be >= 0 (0 = off)")
        self.requested_path = Path(path)
        self.path = Path(path)
        self.segments: list[Path] = []
        self.config = dict(config or {})
        self.flush_interval = flush_interval
        self.chunk_size = chunk_size
        self.split_size = split_size
        self.split_duration = split_duration
        self._foxglove = foxglove
        self._wlock = threading.Lock()
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._viz: Any = None
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._latched = LatchedState()
        self._segment = 0
        self._segment_start = 0.0  # monotonic s
        self._segment_messages = 0
        self._dirty = False
        self._finished = False
        self.recorded = 0
        self._pending: Any = lambda: 0  # the subscription's queue depth
        self.queued_peak = 0  # deepest queue seen (sampled at every flush)

    def _start(self) -> None:
        with self._wlock:
            self._open_segment()
        if self.path != self.requested_path:
            log.warning("%s exists: recording to %s", self.requested_path, self.path)
        sub = self.bus.subscribe(self.keys.all(), self._on_message)
        self._pending = getattr(sub, "pending", self._pending)
        self._handles.append(sub)
        self.spawn(self._flush_loop, "flush")
        log.info("recording %s to %s", self.keys.all(), self.path)

    # segments --------------------------------------------------------------------------
    def _open_segment(self) -> None:
        """Create the next segment (the first: ``--out`` or a free ``STEM.N``), start its
        writer and re-write the latched state at its start. Under ``_wlock``."""
        if not self.segments:
            self.path, self._stream = open_new(self.requested_path)
        else:
            self._segment, self.path, self._stream = open_segment(
                self.segments[0], self._segment + 1
            )
        self.segments.append(self.path)
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
        md = L.metadata_record(self.keys.prefix, self.config)
        md.update(segment=str(self._segment), first_segment=self.segments[0].name)
        w.add_metadata(L.METADATA_NAME, md)
        self._writer = w
        self._schemas.clear()
        self._channels.clear()
        self._segment_start = time.monotonic()
        self._segment_messages = 0
        if self._foxglove:
            from confnav.recording.scene_writer import FoxgloveSceneWriter

            self._viz = FoxgloveSceneWriter(w, self.keys.prefix)
        start_ns = L.log_time_ns()
        for e in self._latched.entries():
            w.add_message(
                channel_id=self._channel(e.key, e.model, "latched"),
                log_time=start_ns,
                data=e.data,
                publish_time=e.publish_time_ns,
            )
            if self._viz is not None:
                self._viz.on_message(e.key, e.data, start_ns)
        w.flush()  # type: ignore[no-untyped-call]
        self._stream.flush()

    def _finish_segment(self) -> None:
        """Finish the open segment (final scenes, summary, footer) and close it. Under
        ``_wlock``."""
        if self._writer is not None and not self._finished:
            if self._viz is not None:
                self._viz.close()
                self._viz = None
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._finished = True
        self._writer = None
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def _split_due(self) -> bool:
        """The open segment has messages and reached ``split_size`` or ``split_duration``.
        Under ``_wlock``."""
        if self._stream is None or self._finished or self._segment_messages == 0:
            return False
        if self.split_size and self._stream.tell() >= self.split_size:
            return True
        age = time.monotonic() - self._segment_start
        return bool(self.split_duration) and age >= self.split_duration

    def split(self, only_if_due: bool = False) -> Path | None:
        """Finish the open segment and continue in a new one; return the new one's path.
        With ``only_if_due``, only when a rotation limit is reached (else None)."""
        with self._wlock:
            if only_if_due and not self._split_due():
                return None
            if self._writer is None or self._finished:
                raise RuntimeError("the recorder is not recording")
            old = self.path
            self._finish_segment()
            self._finished = False
            self._open_segment()
        self.count("splits")
        allocator.trim()  # the finished writer's buffers and indexes
        log.info("segment %s finished, recording to %s", old, self.path)
        return self.path

    # writing ---------------------------------------------------------------------------
    def _channel(self, key: str, model: type[Message] | None, role: str = "valid") -> int:
        """Channel of ``key`` in the open segment: ``role`` ``valid`` (the model's schema),
        ``latched`` (the same, marked as re-written state) or ``raw`` (``model`` None)."""
        w = self._writer
        assert w is not None
        cid = self._channels.get((key, role))
        if cid is not None:
            return cid
        if model is not None:
            sid = self._schemas.get(model)
            if sid is None:
                sid = w.register_schema(
                    name=L.schema_name(model), encoding=L.SCHEMA_ENCODING, data=L.schema_data(model)
                )
                self._schemas[model] = sid
            meta = dict(L.LATCHED_CHANNEL_METADATA) if role == "latched" else {}
            cid = w.register_channel(
                topic=key, message_encoding=L.MESSAGE_ENCODING, schema_id=sid, metadata=meta
            )
        else:
            cid = w.register_channel(
                topic=key,
                message_encoding=L.RAW_MESSAGE_ENCODING,
                schema_id=0,
                metadata=dict(L.INVALID_CHANNEL_METADATA),
            )
        self._channels[(key, role)] = cid
        return cid

    def _on_message(self, key: str, payload: bytes) -> None:
        msg: Message | None = None
        model: type[Message] | None = None
        parsed = None
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
            # receive time taken under the lock: log times follow the file order, and a
            # segment's latched copies (stamped with its start) precede all its messages
            log_time = L.log_time_ns()
            publish_time = L.publish_time_ns(msg, log_time)
            self._writer.add_message(
                channel_id=self._channel(key, model, "valid" if model else "raw"),
                log_time=log_time,
                data=payload,
                publish_time=publish_time,
            )
            self.recorded += 1
            self._segment_messages += 1
            self._dirty = True
            if msg is not None and model is not None and parsed is not None:
                self._latched.observe(
                    key, parsed.group, parsed.ident, parsed.kind, model, payload,
                    log_time, publish_time,
                )  # fmt: skip
                if self._viz is not None:
                    self._viz.on_message(key, payload, log_time)
        self.count("recorded")

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (survives a SIGKILL)."""
        with self._wlock:
            if self._writer is None or self._finished or not self._dirty:
                return
            self._writer.flush()  # type: ignore[no-untyped-call]  # closes the chunk, writes
            self._dirty = False

    def queued(self) -> int:
        """Messages received and not yet written (the recorder falling behind if it grows)."""
        return int(self._pending())

    def health_detail(self) -> tuple[str, str]:
        return "ok", f"file {self.path}"

    def health_gauges(self) -> dict[str, int]:
        g = {"queued": self.queued(), "queued_peak": self.queued_peak}
        rss = allocator.rss_kib()
        if rss is not None:
            g["rss_kib"] = rss
        return g

    def _flush_loop(self) -> None:
        next_trim = time.monotonic() + TRIM_INTERVAL_S
        while not self._stop.wait(self.flush_interval):
            try:
                self.queued_peak = max(self.queued_peak, self.queued())
                self.flush()
                self.split(only_if_due=True)
                if time.monotonic() >= next_trim:
                    next_trim = time.monotonic() + TRIM_INTERVAL_S
                    allocator.trim()
            except Exception:
                log.exception("flush failed")

    def stop(self) -> None:
        """Stop receiving, write what is queued, finish the file (summary, index)."""
        super().stop()  # closes the subscription after its queue is drained
        with self._wlock:
            self._finish_segment()
        log.info(
            "recording finished: %d messages in %s",
            self.recorded,
            ", ".join(str(p) for p in self.segments) or self.path,
        )


def non_negative_float(text: str) -> float:
    """An argparse ``type=`` for a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return value


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("recorder", help="record everything to MCAP")
    add_zenoh_args(p)
    p.add_argument(
        "--out",
        type=output_path,
        default="confnav.mcap",
        help="MCAP file to write; if it exists, the first free OUT-STEM.N.mcap instead",
    )
    p.add_argument(
        "--split-size",
        type=non_negative_float,
        default=SPLIT_SIZE_MB,
        metavar="MB",
        help="start a new segment OUT-STEM.partK.mcap once this many MB are written (0 = off)",
    )
    p.add_argument(
        "--split-duration",
        type=non_negative_float,
        default=SPLIT_DURATION_S,
        metavar="S",
        help="start a new segment after this many seconds (0 = off)",
    )
    p.add_argument("--foxglove", action="store_true", help="add Foxglove scene channels")
    p.add_argument(
        "--flush-interval", type=float, default=L.FLUSH_INTERVAL_S, help="s between flushes"
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    allocator.tune()  # before Zenoh's and our threads exist
    config = {k: v for k, v in vars(args).items() if k != "func"}
    return run_until_signal(
        lambda bus, keys: Recorder(
            bus,
            keys,
            args.out,
            config,
            foxglove=args.foxglove,
            flush_interval=args.flush_interval,
            split_size=int(args.split_size * 1e6),
            split_duration=args.split_duration,
        ),
        args,
    )
