"""Recorder: exact message counts per channel, schemas, metadata, raw channel for invalid
payloads, finish on SIGTERM, bounded loss on SIGKILL (real processes over Zenoh)."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from confnav.schemas import MODELS_BY_TYPE, Goal, Pose, RobotStatus, encode, schema_bytes
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.recorder import Recorder, free_path
from conftest import confnav_cmd, square_definition, subprocess_env, wait_for
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from confnav.recording import layout as L
from confnav.recording.recover import has_footer, scan

K = Keys()


def read_all(
    path: Path,
) -> tuple[Counter[str], list[tuple[Any, Any, Any]], dict[str, dict[str, str]]]:
    """Counts per (topic) of valid messages, every (schema, channel, message), metadata."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        msgs = list(reader.iter_messages())
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    counts = Counter(ch.topic for _, ch, _ in msgs if ch.message_encoding == L.MESSAGE_ENCODING)
    return counts, msgs, meta


def test_exact_counts_schemas_and_metadata(mem_net: InMemoryNetwork, tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    rec = Recorder(mem_net.bus("rec"), K, path, config={"run": "test"}, health_period=0)
    rec.start()
    pub = mem_net.bus("pub")
    sent: Counter[str] = Counter()
    try:
        pub.publish(K.ws("sq", "definition"), encode(square_definition("sq")))
        sent[K.ws("sq", "definition")] += 1
        for i in range(300):
            for rid in ("r1", "r2"):
                key = K.robot(rid, "pose")
                pub.publish(
                    key, encode(Pose(robot_id=rid, stamp_ns=1000 + i, seq=i, x=0.1 * i, y=0))
                )
                sent[key] += 1
        pub.publish(K.robot("r1", "goal"), encode(Goal(robot_id="r1", ws_id="sq", goal=(0, 0))))
        sent[K.robot("r1", "goal")] += 1
        st = RobotStatus(robot_id="r2", stamp_ns=5, state="stopped", reason="nan_input")
        pub.publish(K.robot("r2", "status"), encode(st))
        sent[K.robot("r2", "status")] += 1
        raw = [
            (K.robot("r1", "pose"), b"{not json"),
            (K.robot("r1", "pose"), b'{"robot_id":"r1","stamp_ns":1,"x":NaN,"y":0}'),
            ("confnav/unknown/thing", b"hello"),
        ]
        for key, payload in raw:
            pub.publish(key, payload)
        wait_for(lambda: rec.recorded == sum(sent.values()) + len(raw))
    finally:
        rec.stop()

    counts, msgs, meta = read_all(path)
    assert counts == sent
    raw_got = [
        (ch.topic, m.data) for _, ch, m in msgs if ch.message_encoding == L.RAW_MESSAGE_ENCODING
    ]
    assert raw_got == raw
    for _, ch, _ in msgs:
        if ch.message_encoding == L.RAW_MESSAGE_ENCODING:
            assert ch.schema_id == 0 and ch.metadata == L.INVALID_CHANNEL_METADATA
    # every valid payload validates against its channel's schema, which names its model
    validators: dict[int, Any] = {}
    for schema, _ch, m in msgs:
        if schema is None:
            continue
        assert schema.encoding == L.SCHEMA_ENCODING and schema.name.startswith("confnav.")
        # the channel schema is exactly what `confnav schemas export` writes
        assert schema.data == schema_bytes(MODELS_BY_TYPE[schema.name])
        v = validators.setdefault(
            schema.id, jsonschema.Draft202012Validator(json.loads(schema.data))
        )
        payload = json.loads(m.data)
        v.validate(payload)
        assert payload["type"] == schema.name
        stamp = payload.get("stamp_ns", 0)
        assert m.publish_time == (stamp if stamp > 0 else m.log_time)
    # one channel per key, poses in order
    seqs = [
        json.loads(m.data)["seq"] for _, ch, m in msgs if ch.topic == K.robot("r2", "pose") and _
    ]
    assert seqs == list(range(300))
    md = meta[L.METADATA_NAME]
    assert md["prefix"] == "confnav" and json.loads(md["config"]) == {"run": "test"}
    assert md["zenoh_version"] != "" and md["mcap_version"] != ""


def test_never_overwrites_an_existing_recording(mem_net: InMemoryNetwork, tmp_path: Path) -> None:
    """Each start writes a new file (demo.mcap, demo.1.mcap, demo.2.mcap); the bytes of the
    files already there are untouched, also of a footer-less one left by a crash."""
    path = tmp_path / "demo.mcap"
    path.write_bytes(b"\x89MCAP0\r\nprevious run, killed")
    before = path.read_bytes()
    written = []
    for run in range(2):
        rec = Recorder(mem_net.bus(f"rec{run}"), K, path, health_period=0)
        rec.start()
        pub = mem_net.bus(f"pub{run}")
        pub.publish(
            K.robot("r1", "pose"), encode(Pose(robot_id="r1", stamp_ns=1, seq=run, x=0, y=0))
        )
        wait_for(lambda rec=rec: rec.recorded == 1)  # type: ignore[misc]
        rec.stop()
        written.append(rec.path)
    assert written == [tmp_path / "demo.1.mcap", tmp_path / "demo.2.mcap"]
    assert path.read_bytes() == before
    for run, p in enumerate(written):
        counts, msgs, _meta = read_all(p)
        assert counts == {K.robot("r1", "pose"): 1}
        assert json.loads(msgs[0][2].data)["seq"] == run
    assert free_path(path) == tmp_path / "demo.3.mcap"
    assert free_path(tmp_path / "new.mcap") == tmp_path / "new.mcap"


def test_mcap_writer_flush_makes_every_message_durable(tmp_path: Path) -> None:
    """Pins the mcap API the bounded SIGKILL loss rests on: after the public
    ``Writer.flush()`` every message added so far is in a complete chunk in the file (as a
    killed process leaves it), and writing continues in a new chunk."""
    from mcap.writer import CompressionType, Writer

    path = tmp_path / "f.mcap"
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        w.start("confnav", "test")
        cid = w.register_channel("t", "json", 0)
        for i in range(3):
            w.add_message(cid, log_time=i, data=b"%d" % i, publish_time=i)
        w.flush()  # type: ignore[no-untyped-call]
        got = [bytes(r.data) for r in scan(path).records if type(r).__name__ == "Message"]
        assert got == [b"0", b"1", b"2"] and not has_footer(path)
        w.add_message(cid, log_time=3, data=b"3", publish_time=3)
        w.flush()  # type: ignore[no-untyped-call]
        got = [bytes(r.data) for r in scan(path).records if type(r).__name__ == "Message"]
        assert got == [b"0", b"1", b"2", b"3"]
        w.finish()  # type: ignore[no-untyped-call]
    assert has_footer(path)


def _start_recorder(endpoint: str, out: Path, flush: float = 0.5) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        confnav_cmd(
            "serve",
            "recorder",
            "--connect",
            endpoint,
            "--out",
            str(out),
            "--flush-interval",
            str(flush),
        ),
        env=subprocess_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def _publish_for(bus: Any, seconds: float, rate: float = 200.0) -> list[tuple[int, float]]:
    """Publish numbered poses for ``seconds``; return (seq, monotonic send time)."""
    sent = []
    t0 = time.monotonic()
    i = 0
    while time.monotonic() - t0 < seconds:
        bus.publish(
            K.robot("r1", "pose"),
            encode(Pose(robot_id="r1", stamp_ns=time.time_ns(), seq=i, x=0, y=0)),
        )
        sent.append((i, time.monotonic()))
        i += 1
        time.sleep(1.0 / rate)
    return sent


def _wait_alive(bus: Any, service: str, timeout: float = 30) -> None:
    wait_for(lambda: bus.alive(K.alive_of(service)), timeout=timeout, interval=0.1)


@pytest.mark.timeout(90)
@pytest.mark.integration
def test_sigterm_finishes_the_file(
    make_bus: Callable[[], Any], zenoh_router: str, tmp_path: Path
) -> None:
    out = tmp_path / "term.mcap"
    proc = _start_recorder(zenoh_router, out)
    try:
        bus = make_bus()
        _wait_alive(bus, "recorder")
        time.sleep(0.2)
        sent = _publish_for(bus, 1.0)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    counts, _msgs, meta = read_all(out)  # the indexed reader accepts it: summary written
    assert counts[K.robot("r1", "pose")] == len(sent)
    assert L.METADATA_NAME in meta


@pytest.mark.timeout(90)
@pytest.mark.integration
def test_sigkill_loses_at_most_about_a_second(
    make_bus: Callable[[], Any], zenoh_router: str, tmp_path: Path
) -> None:
    out = tmp_path / "kill.mcap"
    proc = _start_recorder(zenoh_router, out, flush=0.5)
    try:
        bus = make_bus()
        _wait_alive(bus, "recorder")
        time.sleep(0.2)
        sent = _publish_for(bus, 2.5)
        t_kill = time.monotonic()
        proc.kill()
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # the file has no footer; the streaming reader recovers every complete chunk
    seqs = []
    with open(out, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if type(rec).__name__ == "Message":
                    payload = json.loads(rec.data)
                    if payload.get("type") == "confnav.Pose":
                        seqs.append(payload["seq"])
        except Exception:
            pass  # the truncated tail
    assert seqs == list(range(len(seqs)))  # a prefix, in order
    lost = [t for s, t in sent if s >= len(seqs)]
    assert len(seqs) > 0
    assert not lost or t_kill - min(lost) <= 1.0, (
        f"lost {len(lost)} messages from the last {t_kill - min(lost):.2f} s"
    )
    # a restart (as the launcher does it) writes a new file and leaves the killed one intact
    killed = out.read_bytes()
    proc = _start_recorder(zenoh_router, out, flush=0.5)
    try:
        _wait_alive(bus, "recorder")
        wait_for(lambda: (tmp_path / "kill.1.mcap").exists())
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert out.read_bytes() == killed
    assert has_footer(tmp_path / "kill.1.mcap")


def test_memory_per_chunk_does_not_grow_with_the_channels(
    mem_net: InMemoryNetwork, tmp_path: Path
) -> None:
    """The soak's recorder grew 20 % in 4 minutes: the MCAP writer keeps its summary indexes
    until the file is finished, and the per-chunk message indexes hold one offset per channel
    of every chunk (400 with 100 robots). Without them a chunk costs the same few hundred
    bytes whatever the channel count; the file still reads back per topic, message for
    message."""
    import tracemalloc

    rec = Recorder(
        mem_net.bus("rec"), K, tmp_path / "many.mcap", flush_interval=3600, health_period=0
    )
    rec.start()
    keys = [K.robot(f"r{i}", kind) for i in range(100) for kind in ("pose", "cmd_vel")]
    keys += [K.robot(f"r{i}", kind) for i in range(100) for kind in ("status", "goal")]

    def chunk(n: int) -> None:  # one message per channel, one chunk (raw payloads: no decode)
        for key in keys:
            rec._on_message(key, b"%d" % n)
        rec.flush()

    try:
        for n in range(5):  # warm-up: channels registered, buffers sized
            chunk(n)
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            for n in range(5, 45):
                chunk(n)
            per_chunk = (tracemalloc.get_traced_memory()[0] - base) / 40
        finally:
            tracemalloc.stop()
    finally:
        rec.stop()
    # with message indexes: 400 dict entries a chunk, about 40 kB
    assert per_chunk < 2000, per_chunk
    with open(rec.path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and len(summary.chunk_indexes) == 45
        got = [(ch.topic, m.data) for _, ch, m in reader.iter_messages(topics=[keys[7]])]
    assert got == [(keys[7], b"%d" % n) for n in range(45)]
