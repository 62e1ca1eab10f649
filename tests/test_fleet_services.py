"""Fleets through the services: the simulator reports robot-robot contacts along each step
(real Zenoh), the movers message, two robots swapping through the whole system."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from confnav.schemas import (
    CollisionEvent,
    DecodeError,
    Movers,
    SpawnRequest,
    VelocityCommand,
    decode,
    encode,
    model_for_key_parts,
)
from confnav.services.keys import Keys
from confnav.services.simulator import SimulatorService
from confnav.services.transform import workspace_of
from conftest import square_definition, wait_for

K = Keys()


def test_movers_message_and_key() -> None:
    msg = decode(
        Movers,
        b'{"ws_id": "hall", "stamp_ns": 5, "movers": [{"mover_id": "p1", "position": [1.0, 2.0],'
        b' "radius": 0.3, "velocity": [1.2, 0.0]}]}',
    )
    assert decode(Movers, encode(msg)) == msg
    assert msg.movers[0].velocity == (1.2, 0.0)
    key = K.ws("hall", "movers")
    assert key == "confnav/ws/hall/movers"
    parsed = K.parse(key)
    assert model_for_key_parts(parsed.group, parsed.kind) is Movers
    for bad in (
        b'{"ws_id": "hall", "stamp_ns": 5, "movers": [{"mover_id": "p", "position": [0, 0], '
        b'"radius": 0.0}]}',  # radius must be > 0
        b'{"ws_id": "hall", "stamp_ns": 5, "movers": [{"mover_id": "p", "position": [0, 0], '
        b'"radius": 0.3, "velocity": [NaN, 0]}]}',
    ):
        with pytest.raises(DecodeError):
            decode(Movers, bad)


@pytest.mark.timeout(60)
def test_simulator_reports_a_robot_pass_through_the_step_ends_miss(
    make_bus: Callable[[], Any],
) -> None:
    """r1 (disk 0.05) drives from x = -0.3 to 0.1 in one 0.4 s step past r2 (disk 0.05)
    standing at (0, 0.05): both step ends are > 0.1 apart, the closest approach (0.05, at
    x = 0) is a contact: one event per robot, naming the other; both stop there."""
    sim = SimulatorService(make_bus(), K, sources={}, cmd_timeout=30.0)
    sim._workspaces["sq"] = workspace_of(square_definition("sq"))
    sim._stop.set()  # stepped by hand
    sim.start()
    client = make_bus()
    events: list[CollisionEvent] = []
    client.subscribe(
        K.any_robot("collision"), lambda k, p: events.append(decode(CollisionEvent, p))
    )
    try:
        time.sleep(0.3)
        for rid, x, y in (("r1", -0.3, 0.0), ("r2", 0.0, 0.05)):
            client.publish(
                K.sim("sim", "spawn"),
                encode(SpawnRequest(robot_id=rid, ws_id="sq", position=(x, y), robot_radius=0.05)),
            )
        wait_for(lambda: len(sim.positions()) == 2, timeout=10)
        client.publish(
            K.robot("r1", "cmd_vel"),
            encode(VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(), linear=(1.0, 0.0))),
        )
        wait_for(lambda: sim.counters["commands"] == 1, timeout=10)
        sim.step(0.4)
        wait_for(lambda: len(events) == 2, timeout=10)
        by = {e.robot_id: e for e in events}
        assert by["r1"].other_robot_id == "r2" and by["r2"].other_robot_id == "r1"
        assert by["r1"].clearance == pytest.approx(-0.05)
        assert by["r1"].position == pytest.approx((0.0, 0.0), abs=1e-12)
        assert sim.positions()["r1"] == pytest.approx(0.0, abs=1e-12)  # stopped where it hit
        sim.step(0.4)  # the contact is reported once
        time.sleep(0.2)
        assert len(events) == 2 and len(sim.collisions) == 2
    finally:
        sim.stop()


def test_simulator_step_end_only_robots_apart_no_event(mem_net: Any) -> None:
    """The same pass 0.11 m to the side: closest approach 0.11 > 0.1, no event."""
    sim = SimulatorService(mem_net.bus("sim"), K, cmd_timeout=30.0)
    sim.spawn_robot("r1", "sq", -0.3 + 0j, radius=0.05)
    sim.spawn_robot("r2", "sq", 0.11j, radius=0.05)
    sim._robots["r1"].u = 1.0 + 0j
    sim._robots["r1"].cmd_t = time.monotonic()
    sim.step(0.4)
    assert sim.collisions == [] and sim.positions()["r1"] == pytest.approx(0.1)


@contextmanager
def _services(
    make_bus: Callable[[], Any], room: Any
) -> Iterator[tuple[Any, Any, Any, dict[str, str]]]:
    """In-process transform, controller and simulator on real Zenoh, ``room`` published and
    known to the simulator: (simulator, controller, client bus, each robot's last state)."""
    from confnav.schemas import RobotStatus
    from confnav.services.controller import ControllerService
    from confnav.services.transform import TransformService

    services: list[Any] = [
        TransformService(make_bus(), K, executor="thread", health_period=0.5),
        ControllerService(make_bus(), K, health_period=0.5),  # the local rules, below
        SimulatorService(make_bus(), K, rate_hz=50, time_scale=2.0, cmd_timeout=1.0),
    ]
    client = make_bus()
    state: dict[str, str] = {}
    client.subscribe(
        K.any_robot("status"),
        lambda k, p: state.__setitem__(
            decode(RobotStatus, p).robot_id, decode(RobotStatus, p).state
        ),
    )
    services[1].fleet_coordinator = "local"  # these tests are of the local rules (auto
    # would coordinate the 0.8 m door's robots on a roadmap: tests/test_fleet_coord_*.py)
    for s in services:
        s.start()
    try:
        time.sleep(0.5)
        client.publish(K.ws(room.ws_id, "definition"), encode(room))
        wait_for(lambda: room.ws_id in services[2]._workspaces, timeout=30)
        yield services[2], services[1], client, state
    finally:
        for s in reversed(services):
            s.stop()


@pytest.mark.timeout(180)
def test_two_robots_swap_through_the_services(make_bus: Callable[[], Any]) -> None:
    """Real Zenoh, in-process transform, controller and simulator: two disk robots (r 0.2)
    swap head-on along one line in a 4 x 2 m room (the symmetric case a pure safety filter
    freezes in): the simulator reports no contact and both arrive."""
    from confnav.schemas import Goal, WorkspaceDefinition

    room = WorkspaceDefinition(ws_id="hall", outer=[(0, 0), (4, 0), (4, 2), (0, 2)], tol=1e-6)
    with _services(make_bus, room) as (sim, ctl, client, state):
        starts = {"a": (0.6, 1.0), "b": (3.4, 1.0)}
        for rid, (x, y) in starts.items():
            client.publish(
                K.sim("sim", "spawn"),
                encode(SpawnRequest(robot_id=rid, ws_id="hall", position=(x, y), robot_radius=0.2)),
            )
        wait_for(lambda: len(sim.positions()) == 2, timeout=10)
        for rid, (x, y) in starts.items():
            goal = (4.0 - x, y)
            client.publish(
                K.robot(rid, "goal"),
                encode(Goal(robot_id=rid, ws_id="hall", goal=goal, robot_radius=0.2)),
            )
        wait_for(lambda: state.get("a") == "arrived" and state.get("b") == "arrived", timeout=150)
        assert sim.collisions == []
        pos = sim.positions()
        assert abs(pos["a"] - (3.4 + 1.0j)) < 0.05 and abs(pos["b"] - (0.6 + 1.0j)) < 0.05
        assert ctl.neighbours is not None and ctl.neighbours.counters.get("filtered", 0) > 0


def test_recorder_records_movers(mem_net: Any, tmp_path: Any) -> None:
    from confnav.schemas import MoverDisk
    from confnav.services.recorder import Recorder

    from confnav.recording.reader import Recording, decode_message

    rec = Recorder(mem_net.bus("rec"), K, tmp_path / "m.mcap", health_period=0)
    rec.start()
    try:
        pub = mem_net.bus("tracker")
        msg = Movers(
            ws_id="hall",
            stamp_ns=time.time_ns(),
            movers=[MoverDisk(mover_id="p1", position=(1.0, 2.0), radius=0.3)],
        )
        pub.publish(K.ws("hall", "movers"), encode(msg))
        wait_for(lambda: rec.recorded >= 1, timeout=10)
    finally:
        rec.stop()
    with Recording(tmp_path / "m.mcap") as r:
        got = [decode_message(m) for m in r.iter_messages() if m.topic.endswith("/movers")]
    assert got == [msg]


class _R:
    """The controller's per-robot record, as far as the fleet hook reads it."""

    def __init__(self, rid: str, radius: float) -> None:
        from confnav.schemas import Goal

        self.robot_id = rid
        self.goal = Goal(robot_id=rid, ws_id="hall", goal=(5.0, 0.0), robot_radius=radius)


class _Law:
    frame = "world"


def _block(poses: list[tuple[str, float, float]], u: list[complex], radius: float = 0.2) -> Any:
    import numpy as np
    from confnav.schemas import Pose

    members = [(_R(rid, radius), Pose(robot_id=rid, stamp_ns=1, x=x, y=y)) for rid, x, y in poses]
    return [((_Law(), members), (np.array(u, dtype=complex), np.zeros(len(u), dtype=int)))]


def test_hook_leaves_a_lone_robot_bitwise_and_keeps_two_apart() -> None:
    from confnav.services.neighbours import Neighbours

    nb = Neighbours(K)
    lone = _block([("a", 0.0, 0.0)], [0.3 + 0.1j])
    out = nb.filter_block(lone)
    assert out[0][1][0][0] == 0.3 + 0.1j  # bitwise: no neighbour, no change
    # two robots 0.6 m apart (gap 0.2) driving at each other at 0.5 m/s: each may close at
    # most alpha * gap / 2 = 0.2 m/s along the line (and turns right: side passing)
    pair = _block([("a", 0.0, 0.0), ("b", 0.6, 0.0)], [0.5 + 0j, -0.5 + 0j])
    out = nb.filter_block(pair)
    ua, ub = out[0][1][0]
    assert ua.real <= 0.2 + 1e-12 and -ub.real <= 0.2 + 1e-12
    assert ua.imag < 0 < ub.imag  # both keep right
    # points (radius 0) are no bodies: untouched
    pts = _block([("a", 0.0, 0.0), ("b", 0.6, 0.0)], [0.5 + 0j, -0.5 + 0j], radius=0.0)
    assert list(nb.filter_block(pts)[0][1][0]) == [0.5 + 0j, -0.5 + 0j]


def test_hook_avoids_movers_from_the_bus(mem_net: Any) -> None:
    """A person (0.3 m) on ``ws/hall/movers`` 0.8 m ahead walking at the robot at 1 m/s: the
    robot's command toward it is replaced by one that opens the gap (full responsibility)."""
    from confnav.schemas import MoverDisk
    from confnav.services.neighbours import Neighbours

    nb = Neighbours(K)
    for h in nb.subscribe(mem_net.bus("ctl")):
        assert h is not None
    msg = Movers(
        ws_id="hall",
        stamp_ns=time.time_ns(),
        movers=[MoverDisk(mover_id="p", position=(1.0, 0.0), radius=0.3, velocity=(-1.0, 0.0))],
    )
    mem_net.bus("tracker").publish(K.ws("hall", "movers"), encode(msg))
    wait_for(lambda: nb._movers)
    out = nb.filter_block(_block([("a", 0.0, 0.0)], [0.5 + 0j]))
    u = out[0][1][0][0]
    # gap 0.5, n = -1: Re(-u) >= -2 * 0.5 + 1 = 0 (plus the 2 s capsule ahead): no approach
    assert u.real <= 1e-9 and abs(u) <= 0.5 + 1e-9


@pytest.mark.timeout(240)
def test_parked_robot_yields_through_the_services(make_bus: Callable[[], Any]) -> None:
    """Real Zenoh, in-process transform, controller and simulator: robot a is parked at its
    goal in the middle of a 0.8 m door (two disks of r 0.2 cannot pass there), robot b is
    sent through it.  The controller's fleet step applies the fleet simulation's yield rule
    (``fleet.yield_way`` on robots done with their goal): a steps out of the door ahead of b,
    b arrives, no contact.  Without the rule b is held off a for good (the core twin:
    tests/test_fleet_yield.py)."""
    from confnav.schemas import Goal, WorkspaceDefinition

    outer = [
        (0, 0), (4, 0), (4, 1.6), (4.2, 1.6), (4.2, 0), (8.2, 0), (8.2, 4), (4.2, 4),
        (4.2, 2.4), (4, 2.4), (4, 4), (0, 4),
    ]  # fmt: skip
    room = WorkspaceDefinition(ws_id="door", outer=outer, tol=1e-6)
    with _services(make_bus, room) as (sim, ctl, client, state):

        def send(rid: str, start: tuple[float, float], goal: tuple[float, float]) -> None:
            client.publish(
                K.sim("sim", "spawn"),
                encode(SpawnRequest(robot_id=rid, ws_id="door", position=start, robot_radius=0.2)),
            )
            wait_for(lambda: rid in sim.positions(), timeout=10)
            client.publish(
                K.robot(rid, "goal"),
                encode(Goal(robot_id=rid, ws_id="door", goal=goal, robot_radius=0.2)),
            )

        send("a", (4.1, 2.0), (4.1, 2.0))
        wait_for(lambda: state.get("a") == "arrived", timeout=60)
        send("b", (1.0, 2.0), (7.0, 2.0))
        wait_for(lambda: state.get("b") == "arrived", timeout=180)
        assert sim.collisions == []
        assert abs(sim.positions()["b"] - (7.0 + 2.0j)) < 0.05
        nb = ctl.neighbours
        assert nb is not None and nb.counters.get("yields", 0) > 0


def test_hook_parked_robot_steps_aside() -> None:
    """The fleet simulation's yield rule in the controller's fleet step: robot a parked at its
    goal (status arrived) 0.6 m ahead of robot b driving at it steps forward-left along b's
    motion (``fleet.yield_way``: 0.5 (1 + 1j) / sqrt(2) * sqrt(2)), b keeps right."""
    import numpy as np
    from confnav.services.neighbours import Neighbours

    from confnav.navigation.control import Status

    nb = Neighbours(K)
    block = _block([("a", 0.6, 0.0), ("b", 0.0, 0.0)], [0j, 0.5 + 0j])
    block[0][1][1][0] = Status.ARRIVED
    for m in block[0][0][1]:
        m[0].goal = m[0].goal.model_copy(update={"goal": (m[1].x, m[1].y)})
    block[0][0][1][1][0].goal = block[0][0][1][1][0].goal.model_copy(update={"goal": (5.0, 0.0)})
    out = nb.filter_block(block)
    ua, ub = out[0][1][0]
    assert nb.counters.get("yields", 0) == 1
    assert out[0][1][1][0] == Status.MOVING  # off its goal: reported moving
    assert ua.real > 0 and ua.imag > 0 and abs(np.angle(ua) - np.pi / 4) < 1e-9
    assert ub.imag < 0  # keeps right


def test_a_robot_whose_body_is_unknown_counts_as_the_largest_known_body() -> None:
    """Robot b stands 0.4 m ahead of robot a (r 0.18) with no goal and no spawn request seen
    (a simulator's config robot before its goal: the studio outside check's contact). b
    counts as a disk of a's radius, gap 0.04 m, so a may close at most alpha * gap = 0.08 m/s
    (non-cooperative: full responsibility); as a point (the old rule: gap 0.22 m) it could
    close at 0.44 m/s and drove into b."""
    from confnav.schemas import Pose
    from confnav.services.neighbours import Neighbours

    nb = Neighbours(K)
    nb.note_pose("b", Pose(robot_id="b", stamp_ns=1, x=0.4, y=0.0))
    out = nb.filter_block(_block([("a", 0.0, 0.0)], [0.5 + 0j], radius=0.18))
    u = out[0][1][0][0]
    assert u.real <= 2.0 * (0.4 - 0.36) + 1e-9
