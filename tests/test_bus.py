"""The Bus interface: key matching, the in-memory bus, and the Zenoh bus over unix sockets."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from confnav.services.bus import InMemoryNetwork, QueryError, key_matches
from conftest import wait_for


@pytest.mark.parametrize(
    ("expr", "key", "match"),
    [
        ("a/**", "a/b/c", True),
        ("a/**", "a", True),
        ("a/*/c", "a/b/c", True),
        ("a/*/c", "a/b/d/c", False),
        ("a/**/c", "a/b/d/c", True),
        ("a/b", "a/b/c", False),
        ("*/b", "a/b", True),
    ],
)
def test_key_matches(expr: str, key: str, match: bool) -> None:
    assert key_matches(expr, key) is match


def _queryable(key: str, payload: bytes | None) -> list[tuple[str, bytes]]:
    if "bad" in key:
        raise QueryError(f"unknown workspace in {key}")
    if "boom" in key:
        raise RuntimeError("bug")
    return [(key, b'{"ok": true}')]


def _exercise(make: Callable[[], Any]) -> None:
    """The same contract checked on both implementations."""
    a, b = make(), make()
    got: list[tuple[str, bytes]] = []
    fails = {"n": 0}

    def handler(key: str, payload: bytes) -> None:
        if payload == b"raise":
            fails["n"] += 1
            raise ValueError("handler bug")
        got.append((key, payload))
        if payload == b"echo":  # handlers may publish (not on a Zenoh thread)
            b.publish("t/echo/back", b"pong")

    b.subscribe("t/**", handler)
    b.queryable("t/ws/*/transform", _queryable)
    time.sleep(0.3)
    a.publish("t/x/1", b"raise")  # the subscription survives a failing handler
    a.publish("t/x/1", b"one")
    a.publish("t/y/2", b"echo")
    wait_for(lambda: ("t/echo/back", b"pong") in got, 5)
    assert got[:2] == [("t/x/1", b"one"), ("t/y/2", b"echo")]
    assert fails["n"] == 1

    ok = a.query("t/ws/w1/transform", timeout=2.0)
    assert [(r.key, r.payload, r.ok) for r in ok] == [("t/ws/w1/transform", b'{"ok": true}', True)]
    err = a.query("t/ws/bad/transform", timeout=2.0)
    assert len(err) == 1 and not err[0].ok
    assert "unknown workspace" in (err[0].error or "")
    boom = a.query("t/ws/boom/transform", timeout=2.0)
    assert len(boom) == 1 and "internal error" in (boom[0].error or "")

    events: list[tuple[str, bool]] = []
    a.subscribe_liveliness("t/alive/**", lambda k, alive: events.append((k, alive)))
    tok = b.declare_token("t/alive/svc/1")
    wait_for(lambda: ("t/alive/svc/1", True) in events, 5)
    # a liveliness query may lag the subscriber's event by a few ms: poll
    wait_for(lambda: a.alive("t/alive/**") == ["t/alive/svc/1"], 5)
    tok.close()
    wait_for(lambda: ("t/alive/svc/1", False) in events, 5)
    wait_for(lambda: a.alive("t/alive/**") == [], 5)


def test_in_memory_bus(mem_net: InMemoryNetwork) -> None:
    buses = []

    def make() -> Any:
        buses.append(mem_net.bus())
        return buses[-1]

    try:
        _exercise(make)
    finally:
        for b in buses:
            b.close()


@pytest.mark.timeout(60)
def test_zenoh_bus(make_bus: Callable[[], Any]) -> None:
    _exercise(make_bus)


@pytest.mark.timeout(60)
def test_zenoh_bus_delivers_in_order_without_loss(make_bus: Callable[[], Any]) -> None:
    a, b = make_bus(), make_bus()
    got: list[int] = []
    done = threading.Event()

    def handler(key: str, payload: bytes) -> None:
        got.append(int(payload))
        time.sleep(0.0001)  # a slow handler must not make Zenoh drop anything
        if len(got) == 5000:
            done.set()

    b.subscribe("t/seq", handler)
    time.sleep(0.3)
    for i in range(5000):
        a.publish("t/seq", str(i).encode())
    assert done.wait(20)
    assert got == list(range(5000))


@pytest.mark.timeout(60)
def test_zenoh_session_closed_on_exit(zenoh_router: str) -> None:
    from confnav.services.bus import ZenohBus, zenoh_config

    with ZenohBus(zenoh_config("client", connect=[zenoh_router])) as bus:
        bus.subscribe("t/**", lambda k, p: None)
        tok = bus.declare_token("t/alive/x")
    assert bus.session.is_closed()
    tok.close()  # closing handles after the session is fine


@pytest.mark.parametrize("kind", ["memory", "zenoh"])
def test_subscribe_latest_keeps_the_newest_per_key_and_counts_the_rest(
    kind: str, mem_net: InMemoryNetwork, request: pytest.FixtureRequest
) -> None:
    """While the handler is busy, only the newest sample of each key waits (a bounded
    queue); every sample is either delivered or counted as dropped, none is lost unseen;
    at most ``max_keys`` keys wait."""
    if kind == "memory":
        pub, sub = mem_net.bus("pub"), mem_net.bus("sub")
    else:
        make = request.getfixturevalue("make_bus")
        pub, sub = make(), make()
    gate = threading.Event()
    got: list[tuple[str, bytes]] = []
    dropped = [0]
    lock = threading.Lock()

    def handler(items: list[tuple[str, bytes]]) -> None:
        gate.wait(10)
        with lock:
            got.extend(items)

    def on_dropped(n: int) -> None:
        with lock:
            dropped[0] += n

    sub.subscribe_latest("t/*", handler, on_dropped, max_keys=3)
    time.sleep(0.3)
    pub.publish("t/a", b"0")  # taken by the handler, which then blocks
    time.sleep(0.2)
    for i in range(1, 51):
        for k in ("a", "b", "c", "d"):
            pub.publish(f"t/{k}", str(i).encode())
    time.sleep(0.5)
    gate.set()
    wait_for(lambda: len(got) + dropped[0] == 1 + 200, timeout=10)
    time.sleep(0.2)
    assert len(got) + dropped[0] == 201
    assert got[0] == ("t/a", b"0")
    # after the first: a, b, c with their newest sample; d never had room (3 keys waiting)
    assert sorted(got[1:]) == [("t/a", b"50"), ("t/b", b"50"), ("t/c", b"50")]


_BURST = """
import sys
import time
import zenoh
from confnav.services.bus import flush, zenoh_config

with zenoh.open(zenoh_config("client", connect=[sys.argv[1]])) as session:
    pub = session.declare_publisher("burst/a", congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.5)  # routes settled: the puts go out back to back
    for i in range(int(sys.argv[2])):
        pub.put(b"%08d" % i + b"x" * 300)
    flush(session)
"""


def test_a_process_that_publishes_and_exits_loses_nothing(
    make_bus: Callable[[], Any], zenoh_router: str
) -> None:
    """A real process puts a burst back to back, as ``confnav replay --max`` does, and closes
    its session at once: with :func:`flush` before the close every message arrives, in order.
    Without it the transmission queue's tail was dropped under load (measured outside the suite:
    138-258 of 20,000 lost with four busy processes on two cores; the golden replay test lost
    192 of 2,154 in CI). The loss depends on scheduling and this test does not reproduce it on
    demand; it checks that the barrier returns and that nothing is lost or reordered with it."""
    import subprocess
    import sys

    from conftest import subprocess_env

    n = 20_000
    got: list[int] = []
    sub = make_bus()
    sub.subscribe("burst/a", lambda _k, p: got.append(int(p[:8])))
    wait_for(lambda: len(sub.session.info.routers_zid()) > 0)
    time.sleep(0.2)  # the router has the subscription before the publisher starts
    res = subprocess.run(
        [sys.executable, "-c", _BURST, zenoh_router, str(n)],
        capture_output=True,
        text=True,
        timeout=60,
        env=subprocess_env(),
    )
    assert res.returncode == 0, res.stderr
    wait_for(lambda: len(got) >= n, timeout=10)
    assert got == list(range(n))
