"""Transformation service: solve, cache by content hash, publish on change, queryable with
reply_err, bad inputs never crash it; in memory and over real Zenoh."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from confnav.schemas import (
    TransformSolution,
    TransformStatus,
    WorkspaceDefinition,
    WorkspaceDelete,
    decode,
    encode,
)
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.transform import TransformService, solve_definition
from conftest import fake_solve, square_definition, wait_for

K = Keys()


class Recorder:
    """Collects messages by key from a bus."""

    def __init__(self, bus: Any, expr: str = "confnav/**") -> None:
        self.msgs: list[tuple[str, bytes]] = []
        bus.subscribe(expr, lambda k, p: self.msgs.append((k, p)))

    def on(self, key: str) -> list[bytes]:
        return [p for k, p in self.msgs if k == key]


def start(net_or_bus: Any, **kw: Any) -> TransformService:
    bus = net_or_bus.bus("tr") if isinstance(net_or_bus, InMemoryNetwork) else net_or_bus
    kw.setdefault("executor", "thread")
    kw.setdefault("solve_fn", fake_solve)
    svc = TransformService(bus, K, health_period=0.2, **kw)
    svc.start()
    return svc


def test_solves_publishes_and_serves(mem_net: InMemoryNetwork) -> None:
    client = mem_net.bus("client")
    rec = Recorder(client)
    svc = start(mem_net)
    try:
        defn = square_definition("sq", [(0.2, 0.0)])
        client.publish(K.ws("sq", "definition"), encode(defn))
        wait_for(lambda: rec.on(K.ws("sq", "transform")))
        sol = decode(TransformSolution, rec.on(K.ws("sq", "transform"))[0])
        assert sol.ws_id == "sq" and sol.centers == [(0.2, 0.0)]
        states = [decode(TransformStatus, p).state for p in rec.on(K.ws("sq", "status"))]
        assert states == ["solving", "solved"]
        replies = client.query(K.ws("sq", "transform"))
        assert len(replies) == 1 and replies[0].ok
        assert decode(TransformSolution, replies[0].payload or b"").revision == sol.revision

        # same content (new stamp): cached, not re-solved, not re-published
        client.publish(K.ws("sq", "definition"), encode(defn.model_copy(update={"stamp_ns": 9})))
        # same geometry under another id: served from the cache by content hash
        client.publish(K.ws("sq2", "definition"), encode(defn.model_copy(update={"ws_id": "sq2"})))
        wait_for(lambda: rec.on(K.ws("sq2", "transform")))
        assert svc.counters["solves_started"] == 1 and svc.counters["cache_hits"] == 1
        assert len(rec.on(K.ws("sq", "transform"))) == 1

        # changed: re-solved, new revision published
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.3, 0.0)])))
        wait_for(lambda: len(rec.on(K.ws("sq", "transform"))) == 2)
        sol2 = decode(TransformSolution, rec.on(K.ws("sq", "transform"))[1])
        assert sol2.revision != sol.revision and sol2.centers == [(0.3, 0.0)]
        assert svc.counters["solves_started"] == 2
        # a wildcard query gets one reply per solved workspace, on concrete keys
        keys = sorted(r.key for r in client.query("confnav/ws/*/transform"))
        assert keys == [K.ws("sq", "transform"), K.ws("sq2", "transform")]
    finally:
        svc.stop()


def test_reply_err_for_unknown_invalid_and_pending(mem_net: InMemoryNetwork) -> None:
    client = mem_net.bus("client")
    gate = threading.Event()

    def slow(defn_json: str) -> dict[str, Any]:
        gate.wait(10)
        return fake_solve(defn_json)

    svc = start(mem_net, solve_fn=slow)
    try:
        [r] = client.query(K.ws("nope", "transform"))
        assert not r.ok and "unknown workspace 'nope'" in (r.error or "")

        crossing = WorkspaceDefinition(
            ws_id="bow",
            outer=[(0, 0), (1, 1), (1, 0), (0, 1)],  # self-intersecting
        )
        client.publish(K.ws("bow", "definition"), encode(crossing))
        wait_for(lambda: svc.state_of("bow") == "failed")
        [r] = client.query(K.ws("bow", "transform"))
        assert not r.ok and "'bow' is invalid" in (r.error or "")

        client.publish(K.ws("sq", "definition"), encode(square_definition("sq")))
        wait_for(lambda: svc.state_of("sq") == "solving")
        [r] = client.query(K.ws("sq", "transform"))
        assert not r.ok and "being solved" in (r.error or "")
        gate.set()
        wait_for(lambda: svc.state_of("sq") == "solved")
        [r] = client.query(K.ws("sq", "transform"))
        assert r.ok
    finally:
        gate.set()
        svc.stop()


def test_bad_inputs_never_crash(mem_net: InMemoryNetwork) -> None:
    client = mem_net.bus("client")
    svc = start(mem_net)
    try:
        key = K.ws("sq", "definition")
        good = square_definition("sq")
        bad = [
            b"{not json",
            b"\xff\xfe\x00",
            encode(good).replace(b'"schema_version":1', b'"schema_version":7'),
            encode(good).replace(b"-0.7", b"NaN", 1),
            encode(good)[:-1] + b',"x":1}',
            b'{"pad":"' + b"x" * (3 * 1024 * 1024) + b'"}',  # oversized
            encode(good.model_copy(update={"ws_id": "other"})),  # id differs from key
        ]
        for p in bad:
            client.publish(key, p)
        client.publish(key, encode(good))
        wait_for(lambda: svc.state_of("sq") == "solved")
        assert svc.counters["rejected"] == len(bad)
        assert svc.counters["solves_started"] == 1
    finally:
        svc.stop()


def test_solves_workspaces_concurrently(mem_net: InMemoryNetwork) -> None:
    client = mem_net.bus("client")
    running = {"now": 0, "max": 0}
    lock = threading.Lock()

    def slow(defn_json: str) -> dict[str, Any]:
        with lock:
            running["now"] += 1
            running["max"] = max(running["max"], running["now"])
        time.sleep(0.3)
        with lock:
            running["now"] -= 1
        return fake_solve(defn_json)

    svc = start(mem_net, solve_fn=slow, workers=3)
    try:
        t0 = time.monotonic()
        for i in range(3):
            client.publish(
                K.ws(f"w{i}", "definition"), encode(square_definition(f"w{i}", [(0.1 * i, 0)]))
            )
        wait_for(lambda: all(svc.state_of(f"w{i}") == "solved" for i in range(3)))
        assert running["max"] == 3
        assert time.monotonic() - t0 < 0.85  # not 3 x 0.3 s in a row
    finally:
        svc.stop()


def test_solver_failure_is_reported(mem_net: InMemoryNetwork) -> None:
    from confnav.errors import CrowdingError

    def crowded(defn_json: str) -> dict[str, Any]:
        raise CrowdingError("circles below double precision")

    client = mem_net.bus("client")
    rec = Recorder(client)
    svc = start(mem_net, solve_fn=crowded)
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq")))
        wait_for(lambda: svc.state_of("sq") == "failed")
        [r] = client.query(K.ws("sq", "transform"))
        assert not r.ok and "CrowdingError" in (r.error or "")
        # the status message follows the state change: wait for it on the bus
        wait_for(
            lambda: decode(TransformStatus, rec.on(K.ws("sq", "status"))[-1]).state == "failed",
            timeout=10,
        )
        st = decode(TransformStatus, rec.on(K.ws("sq", "status"))[-1])
        assert st.state == "failed" and "double precision" in st.message
        wait_for(lambda: svc.health().state == "degraded")
    finally:
        svc.stop()


def test_disk_cache_survives_restart(mem_net: InMemoryNetwork, tmp_path: Path) -> None:
    client = mem_net.bus("client")
    calls = {"n": 0}

    def counting(defn_json: str) -> dict[str, Any]:
        calls["n"] += 1
        return fake_solve(defn_json)

    for _ in range(2):
        svc = start(mem_net, solve_fn=counting, cache_dir=tmp_path)
        try:
            client.publish(K.ws("sq", "definition"), encode(square_definition("sq")))
            wait_for(lambda svc=svc: svc.state_of("sq") == "solved")
        finally:
            svc.stop()
    assert calls["n"] == 1
    # a definition put on the bus is served again after a restart, without being re-sent
    svc = start(mem_net, solve_fn=counting, cache_dir=tmp_path)
    try:
        wait_for(lambda: svc.state_of("sq") == "solved")
        assert client.query(K.ws("sq", "transform"))[0].ok
    finally:
        svc.stop()
    assert calls["n"] == 1


@pytest.mark.timeout(120)
def test_real_solver_in_process_pool_over_zenoh(make_bus: Callable[[], Any]) -> None:
    """The real solver in a spawned worker process; the solution comes back over Zenoh and
    loads into a map identical to an in-process solve."""
    from confnav.services.navigation import load_map

    svc_bus, client = make_bus(), make_bus()
    svc = TransformService(svc_bus, K, executor="process", workers=1, health_period=0.5)
    svc.start()
    try:
        rec = Recorder(client)
        time.sleep(0.3)
        defn = square_definition("sq", [(0.2, 0.1)])
        client.publish(K.ws("sq", "definition"), encode(defn))
        wait_for(lambda: rec.on(K.ws("sq", "transform")), timeout=90)
        # progressive: a coarse revision first; the final one (the definition's tol) last
        wait_for(lambda: svc.state_of("sq") == "solved", timeout=90)
        [r] = client.query(K.ws("sq", "transform"))
        assert r.ok and r.key == K.ws("sq", "transform")
        sol = decode(TransformSolution, r.payload or b"")
        direct = solve_definition(defn.model_dump_json())
        assert sol.revision == direct["revision"]
        cmap = load_map(sol)
        assert cmap.revision == sol.revision
        [bad] = client.query(K.ws("nope", "transform"))
        assert not bad.ok and "unknown workspace" in (bad.error or "")
        alive = client.alive(K.alive_of("transform"))
        assert alive == [K.alive("transform", svc_bus.zid)]
    finally:
        svc.stop()


def dying_solve(defn_json: str) -> dict[str, Any]:
    """Runs in a pool worker: the worker dies (like an OOM kill) while solving a workspace
    with two obstacles, every time, and a one-obstacle workspace on its first attempt
    (a marker file in $CONFNAV_TEST_DIR remembers it)."""
    import os

    defn = WorkspaceDefinition.model_validate_json(defn_json)
    marker = Path(os.environ["CONFNAV_TEST_DIR"]) / f"{defn.ws_id}.died"
    if len(defn.obstacles) >= 2 or not marker.exists():
        marker.touch()
        os._exit(9)
    return fake_solve(defn_json)


@pytest.mark.timeout(120)
def test_dead_worker_rebuilds_the_pool_retries_then_fails_with_the_reason(
    mem_net: InMemoryNetwork, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CONFNAV_TEST_DIR", str(tmp_path))
    client = mem_net.bus("client")
    rec = Recorder(client)
    svc = start(mem_net, executor="process", workers=1, solve_fn=dying_solve, max_attempts=2)
    try:
        client.publish(K.ws("once", "definition"), encode(square_definition("once", [(0.2, 0)])))
        wait_for(lambda: svc.state_of("once") == "solved", timeout=60)
        assert svc.counters["pool_rebuilds"] >= 1 and svc.counters["solve_retries"] == 1
        two = square_definition("two", [(0.2, 0), (-0.3, 0.1)])
        client.publish(K.ws("two", "definition"), encode(two))
        wait_for(lambda: svc.state_of("two") == "failed", timeout=60)
        # the status message follows the state change: wait for it on the bus
        wait_for(
            lambda: decode(TransformStatus, rec.on(K.ws("two", "status"))[-1]).state == "failed",
            timeout=10,
        )
        st = decode(TransformStatus, rec.on(K.ws("two", "status"))[-1])
        assert st.state == "failed" and "solver worker died 2 times" in st.message
        [r] = client.query(K.ws("two", "transform"))
        assert not r.ok and "died" in (r.error or "")
        assert svc.health().state == "degraded"
        # the service still solves after all that
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.1, 0)])))
        (tmp_path / "sq.died").touch()
        wait_for(lambda: svc.state_of("sq") == "solved", timeout=60)
    finally:
        svc.stop()


def test_solve_timeout_fails_the_workspace(mem_net: InMemoryNetwork) -> None:
    gate = threading.Event()

    def stuck(defn_json: str) -> dict[str, Any]:
        gate.wait(20)
        return fake_solve(defn_json)

    client = mem_net.bus("client")
    rec = Recorder(client)
    svc = start(mem_net, solve_fn=stuck, solve_timeout=0.4)
    try:
        t0 = time.monotonic()
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq")))
        wait_for(lambda: svc.state_of("sq") == "failed", timeout=20)
        assert time.monotonic() - t0 >= 0.4  # not before the timeout

        def last_status() -> TransformStatus | None:
            got = rec.on(K.ws("sq", "status"))
            return decode(TransformStatus, got[-1]) if got else None

        # the state flips under the lock and the status is published just after it
        wait_for(lambda: (s := last_status()) is not None and s.state == "failed", timeout=5)
        st = last_status()
        assert st is not None
        assert "timed out after 0.4 s" in st.message
        gate.set()  # the late result is ignored
        time.sleep(0.2)
        assert svc.state_of("sq") == "failed" and not rec.on(K.ws("sq", "transform"))
    finally:
        gate.set()
        svc.stop()


def test_lru_cache_persist_valid_only_delete_and_path_safe_ids(
    mem_net: InMemoryNetwork, tmp_path: Path
) -> None:
    client = mem_net.bus("client")
    rec = Recorder(client)
    cache = tmp_path / "cache"
    svc = start(mem_net, cache_dir=cache, max_cached=2)
    try:
        for i in range(4):
            client.publish(
                K.ws(f"w{i}", "definition"), encode(square_definition(f"w{i}", [(0.1 * i, 0)]))
            )
        wait_for(lambda: all(svc.state_of(f"w{i}") == "solved" for i in range(4)))
        assert len(svc._results) == 2 and svc.counters["cache_evictions"] == 2
        # invalid definitions are not persisted (not re-announced at the next start)
        bow = WorkspaceDefinition(ws_id="bow", outer=[(0, 0), (1, 1), (1, 0), (0, 1)])
        client.publish(K.ws("bow", "definition"), encode(bow))
        wait_for(lambda: svc.state_of("bow") == "failed")
        # ids that look like path parts stay inside the definitions directory
        for ws_id in ("..", ".", "~"):
            client.publish(K.ws(ws_id, "definition"), encode(square_definition(ws_id)))
            wait_for(lambda ws_id=ws_id: svc.state_of(ws_id) == "solved")
        files = sorted(p.name for p in (cache / "definitions").iterdir())
        assert files == sorted(
            ["ws-...json", "ws-..json", "ws-~.json", *[f"ws-w{i}.json" for i in range(4)]]
        )
        assert [p.name for p in tmp_path.iterdir()] == ["cache"]
        # delete: forgotten, reported, not served, not restored at the next start
        client.publish(K.ws("w1", "delete"), encode(WorkspaceDelete(ws_id="w1")))
        wait_for(lambda: svc.state_of("w1") is None)
        assert decode(TransformStatus, rec.on(K.ws("w1", "status"))[-1]).state == "deleted"
        [r] = client.query(K.ws("w1", "transform"))
        assert not r.ok and "unknown workspace" in (r.error or "")
    finally:
        svc.stop()
    svc = start(mem_net, cache_dir=cache)
    try:
        wait_for(lambda: svc.state_of("w0") == "solved" and svc.state_of("..") == "solved")
        assert svc.state_of("w1") is None and svc.state_of("bow") is None
    finally:
        svc.stop()


@pytest.mark.timeout(60)
def test_every_bad_query_gets_reply_err(make_bus: Callable[[], Any]) -> None:
    """(A verbatim chunk such as ``@x`` never matches the ``*`` of the queryable: Zenoh does not
    route such a query to it at all.)"""
    svc = start(make_bus())
    client = make_bus()
    try:
        time.sleep(0.3)
        for key in (
            "confnav/ws/" + "x" * 500 + "/transform",  # an id longer than 64 characters
            "confnav/ws/*/transform",  # nothing solved yet: no match
            "confnav/ws/nope/transform",
        ):
            replies = client.query(key, timeout=5)
            assert len(replies) == 1 and not replies[0].ok, key
            assert replies[0].error, key
    finally:
        svc.stop()
