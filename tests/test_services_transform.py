"""Transformation service: solve, cache by content hash, publish on change, queryable with
reply_err, bad inputs never crash it; in memory and over real Zenoh."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import fake_solve, square_definition, wait_for

from confnav.schemas import TransformSolution, TransformStatus, WorkspaceDefinition, decode, encode
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.transform import TransformService, solve_definition

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
