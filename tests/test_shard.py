"""Controller scale-out by robot key ranges (services/shard.py): selectors agree with Zenoh's
own key-expression matching, and two controllers over real Zenoh split a fleet between them
without either seeing the other's poses."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import pytest
import zenoh
from confnav.services.bus import InMemoryNetwork, key_matches
from confnav.services.controller import ControllerService, main
from confnav.services.keys import KeyError_, Keys
from confnav.services.shard import MAX_ID_SUBSCRIPTIONS, RobotSelector, chunk_matches
from conftest import identity_loader, wait_for
from test_services_controller import Client, FakeTransform, solution

K = Keys()
IDS = ["a", "a1", "ab7", "b7", "b17", "b170", "x-7", "r1", "r10", "ba"]
PATTERNS = ["a$*", "$*7", "b$*7", "b$*1$*", "$*a$*", "r1", "*", "x-$*"]


@pytest.mark.parametrize("pattern", PATTERNS)
def test_selector_agrees_with_zenoh_key_expressions(pattern: str) -> None:
    sel = RobotSelector.parse(pattern)
    [expr] = sel.key_exprs(K, "pose")
    ke = zenoh.KeyExpr(expr)  # a valid Zenoh 1.x key expression
    for rid in IDS:
        key = K.robot(rid, "pose")
        zenoh_says = ke.intersects(zenoh.KeyExpr(key))
        assert (rid in sel) == zenoh_says, (pattern, rid)
        assert key_matches(expr, key) == zenoh_says, (pattern, rid)  # the in-memory bus
        if "$*" in pattern:
            assert chunk_matches(pattern, rid) == zenoh_says


def test_selector_lists_and_errors() -> None:
    sel = RobotSelector.parse("a$*,r1,r2")
    assert "ab" in sel and "r1" in sel and "r2" in sel and "r3" not in sel and 5 not in sel
    assert sel.key_exprs(K, "goal") == [
        "confnav/robot/a$*/goal",
        "confnav/robot/r1/goal",
        "confnav/robot/r2/goal",
    ]
    many = RobotSelector([f"r{i}" for i in range(MAX_ID_SUBSCRIPTIONS + 1)])
    assert many.key_exprs(K, "pose") == [K.any_robot("pose")]  # filtered in the process
    assert "r3" in many and "r99" not in many
    for bad in ("a*", "$*", "a$*$*", "a/b", "**", "", "a,,b", "a b", "a$"):
        with pytest.raises(KeyError_):
            RobotSelector.parse(bad)


def test_cli_rejects_a_bad_selector_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    args = argparse.Namespace(robots="a*", stale_after=0.5, linger_ms=0.0)
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--robots" in err and "'a*'" in err


def _two_shards(bus_a: Any, bus_b: Any) -> tuple[ControllerService, ControllerService]:
    a = ControllerService(
        bus_a, K, RobotSelector.parse("a$*"), map_loader=identity_loader, health_period=0.2
    )
    b = ControllerService(
        bus_b, K, RobotSelector.parse("b$*,c1"), map_loader=identity_loader, health_period=0.2
    )
    a.start()
    b.start()
    return a, b


def _drive(cl: Client, a: ControllerService, b: ControllerService) -> None:
    robots = ["a1", "a2", "b1", "c1", "z9"]
    for r in robots:
        cl.goal(r)
    wait_for(lambda: a.counters["goals"] == 2 and b.counters["goals"] == 2, timeout=10)
    wait_for(lambda: a.counters["maps_installed"] and b.counters["maps_installed"], timeout=10)
    wait_for(lambda: all(x._robots[r].ctrl for x, r in ((a, "a2"), (b, "c1"))), timeout=10)
    for _ in range(3):
        for r in robots:
            cl.pose(r, 0.2, 0.5)
            time.sleep(0.01)

    def answered() -> dict[str, set[int]]:
        return {
            r: {c.pose_seq for c in cl.cmds if c.robot_id == r and c.pose_seq >= 0}
            for r in robots[:4]
        }

    wait_for(lambda: all(len(s) == 3 for s in answered().values()), timeout=10)
    time.sleep(0.3)
    # each shard received exactly its robots' poses: the others were never delivered
    assert a.counters["poses"] == 6 and b.counters["poses"] == 6
    assert set(a._robots) == {"a1", "a2"} and set(b._robots) == {"b1", "c1"}
    assert not [c for c in cl.cmds if c.robot_id == "z9"]  # nobody's robot: no command
    # every pose answered exactly once
    assert len([c for c in cl.cmds if c.robot_id != "z9" and c.pose_seq >= 0]) == 12


@pytest.mark.timeout(60)
def test_two_controllers_split_the_fleet_over_real_zenoh(make_bus: Callable[[], Any]) -> None:
    tr = FakeTransform(make_bus())
    tr.solutions["cd"] = solution()
    a, b = _two_shards(make_bus(), make_bus())
    try:
        cl = Client(make_bus())
        time.sleep(0.3)
        _drive(cl, a, b)
    finally:
        a.stop()
        b.stop()


def test_two_controllers_split_the_fleet_in_memory(mem_net: InMemoryNetwork) -> None:
    tr = FakeTransform(mem_net.bus("tr"))
    tr.solutions["cd"] = solution()
    a, b = _two_shards(mem_net.bus("a"), mem_net.bus("b"))
    try:
        _drive(Client(mem_net.bus("client")), a, b)
    finally:
        a.stop()
        b.stop()
