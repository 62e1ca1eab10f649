"""Recover an MCAP file left without a footer (writer killed before ``finish()``).

The indexed reader (:func:`mcap.reader.make_reader`) needs the summary and footer at the end of
the file and rejects such a file. Everything before the cut is still there: this module walks
the data section record by record, keeps every *complete* record (a record is complete when
its full length is in the file; a chunk additionally when it decompresses and its CRC, if
written, matches), and writes them into a new, finished and indexed MCAP file with
:class:`mcap.writer.Writer`.

Schemas, channels, messages (with their log/publish times in integer nanoseconds, unchanged),
metadata and attachments are copied; schema and channel ids may be renumbered (the writer
assigns them), topics and payloads are byte-identical. Messages keep their file order.
"""

from __future__ import annotations

import logging
import os
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import IO, Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from confnav.errors import ConfnavError

logger = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = 9  # opcode (1 byte) + length (8 bytes, little endian)


class RecoverError(ConfnavError):
    """The input cannot be recovered (not an MCAP file, unreadable, ...)."""


@dataclass
class RecoverReport:
    """What :func:`recover` found and wrote.

    ``complete`` tells whether the input already had its footer (nothing was lost);
    ``lost_bytes`` counts the bytes at the end that did not form a complete record and
    ``bad_chunks`` the complete-length chunks that failed to decompress or their CRC.
    """

    source: Path
    output: Path
    complete: bool
    messages: int = 0
    chunks: int = 0
    bad_chunks: int = 0
    schemas: int = 0
    channels: int = 0
    metadata: int = 0
    attachments: int = 0
    lost_bytes: int = 0
    messages_per_topic: Counter[str] = field(default_factory=Counter)
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None

    def summary(self) -> str:
        state = "complete (had a footer)" if self.complete else "truncated (no footer)"
        lines = [
            f"{self.source}: {state}",
            f"  recovered {self.messages} messages on {self.channels} channels "
            f"from {self.chunks} chunks ({self.schemas} schemas, {self.metadata} metadata, "
            f"{self.attachments} attachments)",
            f"  lost: {self.lost_bytes} trailing bytes, {self.bad_chunks} corrupt chunks",
            f"  written: {self.output}",
        ]
        return "\n".join(lines)


_READERS: dict[int, Callable[[ReadDataStream, int], Any]] = {
    Opcode.HEADER: lambda s, n: Header.read(s),
    Opcode.SCHEMA: lambda s, n: Schema.read(s),
    Opcode.CHANNEL: lambda s, n: Channel.read(s),
    Opcode.MESSAGE: lambda s, n: Message.read(s, n),
    Opcode.CHUNK: lambda s, n: Chunk.read(s),
    Opcode.METADATA: lambda s, n: Metadata.read(s),
    Opcode.ATTACHMENT: lambda s, n: Attachment.read(s),
}


@dataclass
class _Scan:
    header: Header | None = None
    records: list[Any] = field(default_factory=list)  # Schema/Channel/Message/Metadata/Attachment
    chunks: int = 0
    bad_chunks: int = 0
    lost_bytes: int = 0
    complete: bool = False


def has_footer(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` ends with a footer record and the MCAP magic (a finished file)."""
    size = os.path.getsize(path)
    if size < 2 * len(MCAP_MAGIC) + _RECORD_HEADER + 20:
        return False
    with open(path, "rb") as f:
        f.seek(-(len(MCAP_MAGIC) + _RECORD_HEADER + 20), os.SEEK_END)
        tail = f.read()
    return tail[0] == Opcode.FOOTER and tail.endswith(MCAP_MAGIC)


def _iter_framed(f: IO[bytes], size: int, scan: _Scan) -> Iterator[tuple[int, bytes]]:
    """(opcode, body) of each record whose full length is in the file; stops at the cut."""
    pos = len(MCAP_MAGIC)
    while pos < size:
        head = f.read(_RECORD_HEADER)
        if len(head) < _RECORD_HEADER:
            scan.lost_bytes = size - pos
            return
        opcode = head[0]
        length = int.from_bytes(head[1:], "little")
        if pos + _RECORD_HEADER + length > size:
            scan.lost_bytes = size - pos
            return
        body = f.read(length)
        pos += _RECORD_HEADER + length
        yield opcode, body
        if opcode == Opcode.FOOTER:
            scan.complete = True
            return


def _chunk_records(chunk: Chunk) -> list[Any]:
    """Records of a chunk; raises ValueError if it does not decompress or its CRC fails."""
    if chunk.compression == "zstd":
        try:
            data = zstandard.ZstdDecompressor().decompress(
                chunk.data, max_output_size=chunk.uncompressed_size
            )
        except zstandard.ZstdError as exc:
            raise ValueError(f"zstd: {exc}") from exc
    elif chunk.compression == "":
        data = chunk.data
    else:  # lz4 and others: let the library try
        return list(breakup_chunk(chunk, validate_crc=True))
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"size {len(data)} != {chunk.uncompressed_size}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("CRC mismatch")
    plain = Chunk(
        compression="",
        data=data,
        message_start_time=chunk.message_start_time,
        message_end_time=chunk.message_end_time,
        uncompressed_crc=0,
        uncompressed_size=len(data),
    )
    return list(breakup_chunk(plain, validate_crc=False))


def scan(path: str | os.PathLike[str]) -> _Scan:
    """Read every complete record of ``path`` (chunks expanded) in file order."""
    result = _Scan()
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise RecoverError(f"{path}: not an MCAP file (bad magic)")
        for opcode, body in _iter_framed(f, size, result):
            reader = _READERS.get(opcode)
            if reader is None:
                continue  # indexes, statistics, summary records: rebuilt by the writer
            try:
                record = reader(ReadDataStream(BytesIO(body)), len(body))
            except Exception as exc:  # malformed record of complete length
                logger.warning("skipping malformed record (opcode %#x): %s", opcode, exc)
                continue
            if isinstance(record, Header):
                result.header = record
            elif isinstance(record, Chunk):
                try:
                    inner = _chunk_records(record)
                except Exception as exc:  # corrupt chunk: keep the others
                    logger.warning("skipping corrupt chunk: %s", exc)
                    result.bad_chunks += 1
                    continue
                result.chunks += 1
                result.records.extend(inner)
            else:
                result.records.append(record)
    if result.header is None:
        raise RecoverError(f"{path}: no MCAP header record")
    return result


def recover(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    chunk_size: int = 1024 * 1024,
    compression: CompressionType = CompressionType.ZSTD,
) -> RecoverReport:
    """Rewrite ``source`` into a valid indexed MCAP ``output`` with every complete record.

    Raises :class:`RecoverError` if ``source`` is not an MCAP file or ``output`` is ``source``.
    """
    src, dst = Path(source), Path(output)
    if not src.is_file():
        raise RecoverError(f"{src}: no such file")
    if dst.exists() and dst.resolve() == src.resolve():
        raise RecoverError("the output must be a different file from the input")
    found = scan(src)
    report = RecoverReport(
        source=src,
        output=dst,
        complete=found.complete,
        chunks=found.chunks,
        bad_chunks=found.bad_chunks,
        lost_bytes=found.lost_bytes,
    )
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    topics: dict[int, str] = {}
    pending: list[Channel] = []  # channels seen before their schema (should not happen)
    tmp = dst.with_name(dst.name + ".part")
    assert found.header is not None
    with open(tmp, "wb") as out:
        writer = Writer(out, chunk_size=chunk_size, compression=compression)
        writer.start(profile=found.header.profile, library=found.header.library)

        def add_channel(ch: Channel) -> None:
            sid = 0 if ch.schema_id == 0 else schema_ids[ch.schema_id]
            channel_ids[ch.id] = writer.register_channel(
                topic=ch.topic,
                message_encoding=ch.message_encoding,
                schema_id=sid,
                metadata=dict(ch.metadata),
            )
            topics[ch.id] = ch.topic
            report.channels += 1

        for rec in found.records:
            if isinstance(rec, Schema):
                if rec.id not in schema_ids:
                    schema_ids[rec.id] = writer.register_schema(
                        name=rec.name, encoding=rec.encoding, data=bytes(rec.data)
                    )
                    report.schemas += 1
                    for ch in [c for c in pending if c.schema_id == rec.id]:
                        pending.remove(ch)
                        add_channel(ch)
            elif isinstance(rec, Channel):
                if rec.id in channel_ids:
                    continue
                if rec.schema_id != 0 and rec.schema_id not in schema_ids:
                    pending.append(rec)
                else:
                    add_channel(rec)
            elif isinstance(rec, Message):
                cid = channel_ids.get(rec.channel_id)
                if cid is None:
                    logger.warning("message on unknown channel %d dropped", rec.channel_id)
                    continue
                writer.add_message(
                    channel_id=cid,
                    log_time=rec.log_time,
                    data=bytes(rec.data),
                    publish_time=rec.publish_time,
                    sequence=rec.sequence,
                )
                report.messages += 1
                report.messages_per_topic[topics[rec.channel_id]] += 1
                t = rec.log_time
                if report.first_log_time_ns is None or t < report.first_log_time_ns:
                    report.first_log_time_ns = t
                if report.last_log_time_ns is None or t > report.last_log_time_ns:
                    report.last_log_time_ns = t
            elif isinstance(rec, Metadata):
                writer.add_metadata(rec.name, dict(rec.metadata))
                report.metadata += 1
            elif isinstance(rec, Attachment):
                writer.add_attachment(
                    create_time=rec.create_time,
                    log_time=rec.log_time,
                    name=rec.name,
                    media_type=rec.media_type,
                    data=bytes(rec.data),
                )
                report.attachments += 1
        if pending:
            logger.warning("%d channels without their schema dropped", len(pending))
        writer.finish()  # type: ignore[no-untyped-call]
    os.replace(tmp, dst)
    logger.info("recovered %d messages from %s into %s", report.messages, src, dst)
    return report


__all__ = ["RecoverError", "RecoverReport", "has_footer", "recover", "scan"]
