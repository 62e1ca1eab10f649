"""Recorder memory (issue 10, soak): the queue depth in its health over real Zenoh, and the glibc
malloc tuning of :mod:`confnav.recording.allocator` doing what it says (checked in fresh
processes through glibc's own ``mallinfo2``)."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from confnav.schemas import Pose, ServiceHealth, decode, encode
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.recorder import Recorder
from conftest import wait_for
from mcap.reader import make_reader

from confnav.recording import allocator

K = Keys()
GLIBC = platform.libc_ver()[0] == "glibc"


def test_queue_depth_in_health(make_bus: Callable[[], Any], tmp_path: Path) -> None:
    """While the writer is held, the N poses published over Zenoh wait in the recorder's queue
    (N - 1: one is in the handler, waiting for the writer) and its health, on the wire, says so
    (its own health messages queue up behind them too); once released, all are written, in
    order, and the queue is empty."""
    n = 40
    rec = Recorder(make_bus(), K, tmp_path / "q.mcap", health_period=0.1, flush_interval=0.05)
    watcher, pub = make_bus(), make_bus()
    seen: list[ServiceHealth] = []
    watcher.subscribe(
        f"{K.prefix}/health/recorder/*", lambda k, p: seen.append(decode(ServiceHealth, p))
    )
    rec.start()
    try:
        with rec._wlock:  # the writer busy (a slow disk): messages must wait, not vanish
            for i in range(n):
                pub.publish(
                    K.robot("r1", "pose"),
                    encode(Pose(robot_id="r1", stamp_ns=i + 1, x=float(i), y=0.0)),
                )
            wait_for(lambda: rec.queued() >= n - 1, 10)
            wait_for(lambda: any(h.gauges.get("queued", 0) >= n - 1 for h in seen), 10)
            held = rec.recorded
        wait_for(lambda: rec.recorded >= held + n and rec.queued() <= 1, 10)
        gauges = rec.health().gauges
        assert gauges["queued_peak"] >= n - 1
        if Path("/proc/self/statm").exists():
            assert gauges["rss_kib"] > 10_000  # a Python process with Zenoh: tens of MB
    finally:
        rec.stop()
    with open(rec.path, "rb") as f:
        msgs = make_reader(f).iter_messages(topics=[K.robot("r1", "pose")])
        xs = [json.loads(m.data)["x"] for _, _, m in msgs]
    assert xs == [float(i) for i in range(n)]


def run_c(body: str) -> dict[str, int]:
    """Run ``body`` in a fresh Python process with ``libc`` (glibc, ``mallinfo2`` typed) at
    hand; it prints a JSON dict, returned."""
    prelude = textwrap.dedent(
        """
        import ctypes, json
        from confnav.recording import allocator
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc.restype = ctypes.c_void_p
        libc.malloc.argtypes = [ctypes.c_size_t]
        libc.free.argtypes = [ctypes.c_void_p]
        class MallInfo2(ctypes.Structure):
            _fields_ = [(n, ctypes.c_size_t) for n in (
                "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                "uordblks", "fordblks", "keepcost")]
        libc.mallinfo2.restype = MallInfo2
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(body)],
        capture_output=True, text=True, check=True, timeout=60,
    )  # fmt: skip
    return dict(json.loads(out.stdout))


@pytest.mark.skipif(not GLIBC, reason="glibc malloc only")
@pytest.mark.parametrize("tuned", [False, True])
def test_mmap_threshold_stays_fixed(tuned: bool) -> None:
    """glibc raises its mmap threshold when a large mmapped block is freed, so the next block
    of that size comes from an arena heap (where its hole fragments); after ``tune`` it is
    mmapped again (and unmapped when freed): one more mmapped block each time."""
    got = run_c(
        f"""
        if {tuned}:
            assert allocator.tune()
        before = libc.mallinfo2().hblks
        p = libc.malloc(4 << 20)
        first = libc.mallinfo2().hblks - before
        libc.free(p)
        p = libc.malloc(4 << 20)
        print(json.dumps({{"first": first, "second": libc.mallinfo2().hblks - before}}))
        """
    )
    assert got == {"first": 1, "second": 1 if tuned else 0}


@pytest.mark.skipif(not GLIBC, reason="glibc malloc only")
def test_trim_returns_free_heap_pages() -> None:
    """200k small blocks freed, but one at the heap's top keeps glibc from shrinking the heap
    by itself: the free bytes stay mapped (~100 MB in ``fordblks``, resident) until ``trim``
    hands their pages back, after which the resident size is that much smaller."""
    got = run_c(
        """
        ps = [libc.malloc(500) for _ in range(200_000)]
        keep = libc.malloc(500)
        for p in ps:
            libc.free(p)
        before = allocator.rss_kib()
        free_kib = libc.mallinfo2().fordblks // 1024
        trimmed = allocator.trim()
        print(json.dumps({"before": before, "after": allocator.rss_kib(),
                          "free": free_kib, "trimmed": int(trimmed)}))
        """
    )
    assert got["free"] > 90_000
    assert got["trimmed"] == 1
    assert got["before"] - got["after"] > 0.9 * got["free"]


def test_rss_kib_matches_proc_status() -> None:
    if not Path("/proc/self/status").exists():
        assert allocator.rss_kib() is None
        return
    rss = allocator.rss_kib()
    status = Path("/proc/self/status").read_text()
    vm = int(next(ln for ln in status.splitlines() if ln.startswith("VmRSS:")).split()[1])
    assert rss is not None and abs(rss - vm) < 2048  # read moments apart: within 2 MiB


def test_soak_flush_window_is_one_chunk(mem_net: InMemoryNetwork, tmp_path: Path) -> None:
    """Half a second (one flush) of the 100-robot soak's traffic, 2200 messages of about 290
    bytes on 400 channels, is one chunk: chunks are closed by the flush, not by size, so the
    writer keeps 2 chunk indexes a second, not 8 (the soak's memory growth)."""
    rec = Recorder(mem_net.bus("rec"), K, tmp_path / "w.mcap", flush_interval=3600)
    rec.start()
    keys = [K.robot(f"r{i}", k) for i in range(100) for k in ("pose", "cmd_vel", "status", "goal")]
    try:
        for i in range(2200):
            rec._on_message(keys[i % len(keys)], b"%290d" % i)  # not JSON: raw channels
        rec.flush()
    finally:
        rec.stop()
    with open(rec.path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 2200
    assert len(summary.chunk_indexes) == 1
