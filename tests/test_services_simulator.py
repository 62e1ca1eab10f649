"""Simulator service: integration with the last command, zero when commands stop, collisions,
pause/reset/spawn, bad inputs; in memory and over real Zenoh."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import pytest
from confnav.schemas import (
    CollisionEvent,
    Pose,
    SimControl,
    SpawnRequest,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.simulator import RobotSpec, SimulatorService, parse_robots
from conftest import square_definition, wait_for

K = Keys()


def cmd(rid: str, vx: float, vy: float) -> bytes:
    return encode(VelocityCommand(robot_id=rid, stamp_ns=time.time_ns(), linear=(vx, vy)))


def make(net: Any, **kw: Any) -> SimulatorService:
    """A simulator whose loop is not started (steps driven by the test) unless asked."""
    sim = SimulatorService(net.bus("sim"), K, robots=[("r1", "sq", 0.0, 0.0)], **kw)
    return sim


def test_integrates_last_command_and_stops_without_commands(mem_net: InMemoryNetwork) -> None:
    sim = make(mem_net, cmd_timeout=0.3)
    client = mem_net.bus("client")
    poses: list[Pose] = []
    client.subscribe(K.robot("r1", "pose"), lambda k, p: poses.append(decode(Pose, p)))
    sim._stop.set()  # no background loop: the test steps by hand
    sim.start()
    try:
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 0.5, -0.25))
        wait_for(lambda: sim.counters["commands"] == 1)
        for _ in range(10):
            sim.step(0.02)
        z = sim.positions()["r1"]
        assert abs(z - (0.1 - 0.05j)) < 1e-12
        time.sleep(0.35)  # commands stopped: the robot stops
        sim.step(0.02)
        assert sim.positions()["r1"] == z
        wait_for(lambda: len(poses) == 11)
        assert [p.seq for p in poses] == list(range(11))
        assert all(p.stamp_ns > 0 for p in poses) and poses[-1].x == pytest.approx(0.1)
    finally:
        sim.stop()


def test_collision_reported_once_and_robot_stays(mem_net: InMemoryNetwork) -> None:
    sim = make(mem_net)
    client = mem_net.bus("client")
    hits: list[CollisionEvent] = []
    client.subscribe(
        K.robot("r1", "collision"), lambda k, p: hits.append(decode(CollisionEvent, p))
    )
    sim._stop.set()
    sim.start()
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.2, -0.025)])))
        wait_for(lambda: sim.health_detail()[0] == "ok")
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 1.0, 0.0))
        wait_for(lambda: sim.counters["commands"] == 1)
        for _ in range(30):  # x goes 0 -> 0.3, through the obstacle [0.2, 0.25]
            sim.step(0.01)
        wait_for(lambda: hits)
        assert len(hits) == 1 and hits[0].robot_id == "r1" and hits[0].clearance <= 0
        assert 0.2 <= sim.positions()["r1"].real <= 0.21
    finally:
        sim.stop()


def test_pause_reset_spawn_remove(mem_net: InMemoryNetwork) -> None:
    sim = make(mem_net, cmd_timeout=10.0)
    client = mem_net.bus("client")
    sim._stop.set()
    sim.start()
    try:
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 1.0, 0.0))
        wait_for(lambda: sim.counters["commands"] == 1)
        sim.step(0.1)
        client.publish(K.sim("sim", "control"), encode(SimControl(action="pause")))
        wait_for(lambda: sim.paused)
        sim.step(0.1)
        assert sim.positions()["r1"] == pytest.approx(0.1)
        client.publish(K.sim("sim", "control"), encode(SimControl(action="resume")))
        client.publish(K.sim("sim", "control"), encode(SimControl(action="reset", robot_id="r1")))
        wait_for(lambda: not sim.paused and sim.positions()["r1"] == 0)
        sim.step(0.1)  # reset also dropped the command
        assert sim.positions()["r1"] == 0
        client.publish(
            K.sim("sim", "spawn"),
            encode(SpawnRequest(robot_id="r2", ws_id="sq", position=(0.3, 0.4))),
        )
        wait_for(lambda: "r2" in sim.positions())
        assert sim.positions()["r2"] == 0.3 + 0.4j
        client.publish(K.sim("sim", "control"), encode(SimControl(action="remove", robot_id="r2")))
        wait_for(lambda: "r2" not in sim.positions())
        # bad inputs: rejected, counted, the simulator carries on
        for key in (K.sim("sim", "spawn"), K.sim("sim", "control"), K.robot("r1", "cmd_vel")):
            client.publish(key, b"{bad")
            client.publish(key, b'{"schema_version":9}')
        client.publish(K.robot("r1", "cmd_vel"), b'{"robot_id":"r1","stamp_ns":1,"linear":[NaN,0]}')
        client.publish(K.robot("r1", "cmd_vel"), b"x" * 200_000)
        # commands wait in a latest-per-robot queue: a bad one is rejected or superseded
        wait_for(lambda: sim.counters["rejected"] + sim.counters["commands_superseded"] == 8)
        sim.step(0.1)
        assert sim.positions()["r1"] == 0
    finally:
        sim.stop()


@pytest.mark.timeout(60)
def test_simulator_over_real_zenoh_faster_than_real_time(make_bus: Callable[[], Any]) -> None:
    sim = SimulatorService(
        make_bus(), K, robots=[("r1", "sq", 0.0, 0.0)], rate_hz=50, time_scale=4.0, cmd_timeout=60.0
    )
    client = make_bus()
    poses: list[Pose] = []
    client.subscribe(K.robot("r1", "pose"), lambda k, p: poses.append(decode(Pose, p)))
    sim.start()
    try:
        time.sleep(0.3)
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 0.2, 0.0))
        wait_for(lambda: sim.counters["commands"] == 1)
        n0, t0 = len(poses), time.monotonic()
        # an event, not a window: 200 poses (4 sim seconds) arrive (generous timeout for a
        # loaded machine); the loop never runs ahead of 4x real time (50 steps per sim second
        # at 4x: one step per 5 ms of wall time, at most 10 steps late caught up in a burst),
        # a bound load cannot break
        wait_for(lambda: len(poses) >= n0 + 200, timeout=40)
        elapsed = time.monotonic() - t0
        assert elapsed >= (200 - 20) * (1 / 50) / 4.0 * 0.99  # 20: burst and in flight
        seqs = [p.seq for p in poses]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # none lost
        assert poses[-1].x > 0.5  # 0.2 m/s for ~4 sim seconds
    finally:
        sim.stop()


@pytest.mark.timeout(60)
def test_commands_only_on_the_exact_key_with_the_robots_id(make_bus: Callable[[], Any]) -> None:
    """Over real Zenoh: a put on ``confnav/robot/*/cmd_vel`` reaches the simulator's
    subscriber but is rejected, and so is a command naming another robot."""
    sim = SimulatorService(make_bus(), K, robots=[("r1", "sq", 0.0, 0.0)], cmd_timeout=5.0)
    sim._stop.set()  # stepped by hand
    sim.start()
    client = make_bus()
    try:
        time.sleep(0.3)
        client.publish("confnav/robot/*/cmd_vel", cmd("r1", 1.0, 0.0))
        client.publish(K.robot("r1", "cmd_vel"), cmd("r2", 1.0, 0.0))
        wait_for(lambda: sim.counters["rejected"] == 2, timeout=10)
        sim.step(0.1)
        assert sim.positions()["r1"] == 0j and sim.counters["commands"] == 0
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 1.0, 0.0))
        wait_for(lambda: sim.counters["commands"] == 1, timeout=10)
        sim.step(0.1)
        assert sim.positions()["r1"] == pytest.approx(0.1)
    finally:
        sim.stop()


def _lagging_run(make_bus: Callable[[], Any], lag: int, steps: int) -> SimulatorService:
    """Over real Zenoh, stepped by hand (dt 0.02 s): a controller that drives r1 from 0 to
    the goal x = 0.15, 0.05 m from the obstacle face x = 0.2, with the proportional law
    ``u = min(0.5, 20 |g - z|)`` towards g (no overshoot with fresh poses: ``20 dt < 1``), but
    answers pose k with the command computed on pose ``k - lag`` (a controller lagging behind
    its input, as under overload), each command stamped with the pose it was computed on and
    arriving fresh. Returns the simulator after ``steps`` steps (stopped)."""
    sim = SimulatorService(make_bus(), K, robots=[("r1", "sq", 0.0, 0.0)], cmd_timeout=5.0)
    sim._stop.set()  # stepped by hand
    ctl = make_bus()
    poses: list[Pose] = []
    ctl.subscribe(K.robot("r1", "pose"), lambda k, p: poses.append(decode(Pose, p)))
    sim.start()
    try:
        ctl.publish(K.ws("sq", "definition"), encode(square_definition("sq", [(0.2, -0.025)])))
        wait_for(lambda: sim.health_detail()[0] == "ok", timeout=10)
        for k in range(steps):
            sim.step(0.02)
            wait_for(lambda n=k: len(poses) > n, timeout=10)
            p = poses[max(0, k - lag)]
            e = 0.15 - p.x
            u = math.copysign(min(0.5, 20 * abs(e)), e)
            before = sim.counters["commands"] + sim.counters["commands_stale"]
            ctl.publish(
                K.robot("r1", "cmd_vel"),
                encode(
                    VelocityCommand(
                        robot_id="r1",
                        stamp_ns=time.time_ns(),
                        linear=(u, 0.0),
                        pose_seq=p.seq,
                        pose_stamp_ns=p.stamp_ns,
                    )
                ),
            )
            wait_for(
                lambda b=before: sim.counters["commands"] + sim.counters["commands_stale"] > b,
                timeout=10,
            )
    finally:
        sim.stop()
    return sim


@pytest.mark.timeout(120)
def test_commands_on_outdated_poses_are_not_applied(make_bus: Callable[[], Any]) -> None:
    """The mechanism of the collisions of the overloaded soak: commands arriving on time but
    computed on poses long gone drove robots on where they had been. Lagging 20 steps
    (0.4 s, beyond ``max_cmd_age`` = 0.25 s), the loop overshoots the goal by up to 0.2 m and
    hits the obstacle unless such commands are refused (the robot then stays put: 0 m on a
    command older than its budget); lagging 2 steps (0.04 s) it reaches the goal."""
    sim = _lagging_run(make_bus, lag=20, steps=60)
    assert sim.collisions == []
    assert sim.counters["commands_stale"] >= 40
    assert 0.0 <= sim.positions()["r1"].real < 0.15
    sim = _lagging_run(make_bus, lag=2, steps=60)
    assert sim.collisions == [] and sim.counters["commands_stale"] == 0
    assert sim.positions()["r1"] == pytest.approx(0.15, abs=1e-3)


def test_commands_from_before_a_reset_are_not_applied(mem_net: InMemoryNetwork) -> None:
    """A command answering a pose from before a reset (the robot was moved back to its
    start) is not applied there; one answering a pose after the reset is."""
    sim = make(mem_net, cmd_timeout=10.0)
    client = mem_net.bus("client")
    sim._stop.set()
    sim.start()

    def answer(seq: int, vx: float) -> None:
        n = sim.counters["commands_received"]
        client.publish(
            K.robot("r1", "cmd_vel"),
            encode(VelocityCommand(robot_id="r1", stamp_ns=1, linear=(vx, 0.0), pose_seq=seq)),
        )
        wait_for(lambda: sim.counters["commands_received"] > n)

    try:
        sim.step(0.02)  # pose 0
        answer(0, 1.0)
        sim.step(0.02)  # pose 1 at x = 0.02
        client.publish(K.sim("sim", "control"), encode(SimControl(action="reset", robot_id="r1")))
        wait_for(lambda: sim.positions()["r1"] == 0)
        answer(1, 1.0)  # computed on pose 1, before the reset
        answer(2, 1.0)  # pose 2 is not published yet
        assert sim.counters["commands_stale"] == 2
        sim.step(0.02)  # pose 2, at the start
        assert sim.positions()["r1"] == 0
        answer(2, 1.0)
        sim.step(0.02)
        assert sim.positions()["r1"] == pytest.approx(0.02)
    finally:
        sim.stop()


def test_robot_option_gives_bodies_headings_and_drives() -> None:
    a, b, c = parse_robots(
        ["a=room:1.0,0.5", "b=room:2,0.5,3.14:r=0.18:drive=unicycle", "c=room:-1,2:r=0"]
    )
    assert a == RobotSpec("a", "room", 1.0, 0.5)  # a point, holonomic, heading 0
    assert (b.x, b.y, b.theta, b.radius, b.drive) == (2.0, 0.5, 3.14, 0.18, "unicycle")
    assert (c.radius, c.drive) == (0.0, "holonomic")
    for item, why in [
        ("a:room:1,2", "no ID=WS: part"),
        ("a=room:1", "is not X,Y"),
        ("a=room:1,nan", "finite"),
        ("a=room:1,2:r=-0.1", "must be finite and >= 0"),
        ("a=room:1,2:r=big", "is not a number"),
        ("a=room:1,2:drive=tank", "unknown option"),
    ]:
        with pytest.raises(SystemExit, match=why):
            parse_robots([item])


def test_robots_from_the_option_collide_as_their_bodies(mem_net: InMemoryNetwork) -> None:
    """Two bodies of radius 0.1 from ``--robot`` specs, centres 0.3 apart, one driving at the
    other: a robot-robot contact once the centres are 0.2 apart (points would never touch)."""
    specs = parse_robots(["r1=sq:0,0:r=0.1", "r2=sq:0.3,0:r=0.1"])
    sim = SimulatorService(mem_net.bus("sim"), K, robots=specs)
    client = mem_net.bus("client")
    hits: list[CollisionEvent] = []
    client.subscribe(
        K.robot("r1", "collision"), lambda k, p: hits.append(decode(CollisionEvent, p))
    )
    sim._stop.set()
    sim.start()
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq", [])))
        wait_for(lambda: sim.health_detail()[0] == "ok")
        client.publish(K.robot("r1", "cmd_vel"), cmd("r1", 1.0, 0.0))
        wait_for(lambda: sim.counters["commands"] == 1)
        for _ in range(20):  # r1 would go 0 -> 0.2: contact at 0.1
            sim.step(0.01)
        wait_for(lambda: hits)
        assert hits[0].other_robot_id == "r2" and hits[0].clearance <= 0
        assert sim.positions()["r1"].real == pytest.approx(0.1, abs=0.011)
    finally:
        sim.stop()
