"""Controller service: commands from the navigation library, hot swap, watchdog; in memory
(exact identity map of a circle domain) and over real Zenoh."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from confnav.schemas import (
    WAITING_FOR_MAP,
    Goal,
    GoalCancel,
    Pose,
    RobotStatus,
    SolveDiagnostics,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    WorkspaceDelete,
    decode,
    encode,
)
from confnav.services import controller_cache
from confnav.services.bus import InMemoryNetwork, QueryError
from confnav.services.controller import ControllerService
from confnav.services.controller_state import _Robot
from confnav.services.keys import Keys
from confnav.services.transform import definition_hash
from conftest import IdentityMap, identity_loader, wait_for

from confnav.navigation.control import Controller

K = Keys()
CENTERS = [(0.4, 0.0)]
RADII = [0.15]


def _state(cl: Any, robot: str) -> str | None:
    """The robot's last status state, None before the first status arrives."""
    status = cl.last_status(robot)
    return None if status is None else status.state


def solution(
    ws: str = "cd", centers: list[tuple[float, float]] = CENTERS, rev: str = "rev1"
) -> TransformSolution:
    return TransformSolution(
        ws_id=ws,
        revision=rev,
        definition_hash="h-" + rev,
        workspace_hash="ws-" + ws,
        stamp_ns=time.time_ns(),
        anchor=(0.0, 0.0),
        centers=centers,
        radii=RADII,
        diagnostics=SolveDiagnostics(
            sweeps=1, error_estimate=0, wall_time=0, tol=1e-10, boundary_residual=0, tol_met=True
        ),
        coefficients={"centers": [list(c) for c in centers], "radii": RADII},
    )


class FakeTransform:
    """A transform service stand-in: liveliness token + queryable serving given solutions."""

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.solutions: dict[str, TransformSolution] = {}
        self.solving: set[str] = set()  # answered "being solved" (the real service's words)
        self.q = bus.queryable("confnav/ws/*/transform", self._answer)
        self.token = bus.declare_token(K.alive("transform", bus.zid))

    def _answer(self, key: str, payload: bytes | None) -> list[tuple[str, bytes]]:
        ws = K.parse(key).ident
        if ws in self.solving:
            raise QueryError(f"workspace {ws!r} is being solved; retry")
        if ws not in self.solutions:
            raise QueryError(f"unknown workspace {ws!r}")
        return [(key, encode(self.solutions[ws]))]


class Client:
    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.cmds: list[VelocityCommand] = []
        self.status: list[RobotStatus] = []
        bus.subscribe(
            K.any_robot("cmd_vel"), lambda k, p: self.cmds.append(decode(VelocityCommand, p))
        )
        bus.subscribe(
            K.any_robot("status"), lambda k, p: self.status.append(decode(RobotStatus, p))
        )
        self.seq = 0

    def pose(self, rid: str, x: float, y: float) -> None:
        self.seq += 1
        p = Pose(robot_id=rid, stamp_ns=time.time_ns(), seq=self.seq, x=x, y=y)
        self.bus.publish(K.robot(rid, "pose"), encode(p))

    def goal(self, rid: str, ws: str = "cd", xy: tuple[float, float] = (-0.5, 0.0)) -> Goal:
        g = Goal(robot_id=rid, ws_id=ws, goal=xy, v_max=0.5, tolerance=0.02)
        self.bus.publish(K.robot(rid, "goal"), encode(g))
        return g

    def last_cmd(self, rid: str) -> VelocityCommand | None:
        c = [m for m in self.cmds if m.robot_id == rid]
        return c[-1] if c else None

    def wait_stopped(self, rid: str) -> VelocityCommand:
        """Wait until the newest command to ``rid`` is a stop, and return it.

        Commands and statuses reach this client on two subscriber threads, so the stop command
        may be recorded after the status announcing it (CI saw that once): wait, don't assert.
        """

        def stopped() -> VelocityCommand | None:
            c = self.last_cmd(rid)
            return c if c is not None and c.linear == (0.0, 0.0) else None

        return wait_for(stopped)

    def answer(self, rid: str) -> VelocityCommand | None:
        """The command answering the last pose sent (watchdog stops have pose_seq -1)."""
        c = [m for m in self.cmds if m.robot_id == rid and m.pose_seq == self.seq]
        return c[-1] if c else None

    def last_status(self, rid: str) -> RobotStatus | None:
        s = [m for m in self.status if m.robot_id == rid]
        return s[-1] if s else None


def setup(net: Any, **kw: Any) -> tuple[ControllerService, FakeTransform, Client]:
    tr = FakeTransform(net.bus("tr"))
    tr.solutions["cd"] = solution()
    ctl = ControllerService(net.bus("ctl"), K, map_loader=identity_loader, health_period=0.2, **kw)
    ctl.start()
    return ctl, tr, Client(net.bus("client"))


def expected_u(goal: Goal, z: complex, centers: list[tuple[float, float]] = CENTERS) -> complex:
    m = IdentityMap([complex(*c) for c in centers], RADII)
    c = Controller(
        m,
        complex(*goal.goal),
        navfn=goal.navfn,
        gain=goal.gain,
        v_max=goal.v_max,
        goal_tol=goal.tolerance,
    )
    return complex(np.asarray(c(np.asarray(z)).u).item())


def same(u: complex, v: complex) -> bool:
    """Equal up to rounding: batched and single-point evaluation may differ in the last ulp."""
    return abs(u - v) <= 1e-12 * max(abs(v), 1e-300)


def test_command_is_the_libraries_control_law(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        g = cl.goal("r1")
        wait_for(lambda: ctl.robot_state("r1") is not None and ctl.counters["maps_installed"])
        cl.pose("r1", 0.2, 0.5)
        cmd = wait_for(lambda: cl.answer("r1"))
        assert cmd.map_revision == "rev1"
        assert same(complex(*cmd.linear), expected_u(g, 0.2 + 0.5j))
        assert abs(complex(*cmd.linear)) > 0
        wait_for(lambda: cl.last_status("r1") and cl.last_status("r1").state == "navigating")
        # at the goal: zero command, state arrived
        cl.pose("r1", -0.5 + 0.01, 0.0)
        wait_for(lambda: _state(cl, "r1") == "arrived")
        cl.wait_stopped("r1")
    finally:
        ctl.stop()


def test_many_robots_in_one_process(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        rids = [f"r{i}" for i in range(30)]
        goals = {r: cl.goal(r) for r in rids}
        wait_for(lambda: ctl.counters["goals"] == 30 and ctl.counters["maps_installed"])
        wait_for(lambda: all(ctl.robot_state(r) is not None for r in rids))
        time.sleep(0.1)
        for i, r in enumerate(rids):
            cl.pose(r, 0.1 * np.cos(i), 0.6 * np.sin(i))

        def answered(r: str) -> VelocityCommand | None:
            c = [m for m in cl.cmds if m.robot_id == r and m.pose_seq > 0]
            return c[-1] if c else None

        wait_for(lambda: all(answered(r) for r in rids))
        for i, r in enumerate(rids):
            z = complex(0.1 * np.cos(i), 0.6 * np.sin(i))
            assert same(complex(*answered(r).linear), expected_u(goals[r], z))
    finally:
        ctl.stop()


def test_hot_swap_keeps_the_robot_moving(mem_net: InMemoryNetwork) -> None:
    ctl, tr, cl = setup(mem_net)
    try:
        g = cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"] == 1)
        cl.pose("r1", 0.0, 0.5)
        assert wait_for(lambda: cl.answer("r1")).map_revision == "rev1"
        cl.cmds.clear()
        cl.status.clear()
        new_centers = [(0.3, -0.3)]
        tr.bus.publish(K.ws("cd", "transform"), encode(solution(centers=new_centers, rev="rev2")))
        for _ in range(20):  # poses keep coming through the swap
            cl.pose("r1", 0.0, 0.5)
            time.sleep(0.005)
        wait_for(lambda: cl.last_cmd("r1").map_revision == "rev2")
        revs = [c.map_revision for c in cl.cmds]
        assert revs == sorted(revs)  # (rev1 ...) then rev2, never back
        assert all(abs(complex(*c.linear)) > 0 for c in cl.cmds)  # never stopped
        assert all(s.state == "navigating" for s in cl.status)
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.cmds[-1].pose_seq == cl.seq)
        assert same(complex(*cl.cmds[-1].linear), expected_u(g, 0.5j, new_centers))
    finally:
        ctl.stop()


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b'{"robot_id":"r1","stamp_ns":1,"x":NaN,"y":0}', "nan_input"),
        (b'{"robot_id":"r1","stamp_ns":1,"x":0.1,"y":Infinity}', "nan_input"),
        (b"{garbage", "invalid_input"),
        (b'{"schema_version":3,"robot_id":"r1","stamp_ns":1,"x":0.1,"y":0}', "invalid_input"),
        (b'{"robot_id":"r2","stamp_ns":1,"x":0.1,"y":0}', "invalid_input"),  # wrong robot
        (b"x" * 100_000, "invalid_input"),  # oversized
    ],
)
def test_bad_pose_stops_the_robot_with_a_reason(
    mem_net: InMemoryNetwork, payload: bytes, reason: str
) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.answer("r1") and abs(complex(*cl.answer("r1").linear)) > 0)
        cl.bus.publish(K.robot("r1", "pose"), payload)
        wait_for(lambda: _state(cl, "r1") == "stopped")
        assert cl.last_status("r1").reason == reason
        cl.wait_stopped("r1")
        cl.pose("r1", 0.0, 0.5)  # a good pose again: moving again, service alive
        wait_for(lambda: _state(cl, "r1") == "navigating")
    finally:
        ctl.stop()


def test_pose_outside_the_map_stops(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        cl.pose("r1", 0.4, 0.0)  # inside the obstacle disk
        cmd = wait_for(lambda: cl.answer("r1"))
        assert cmd.linear == (0.0, 0.0)
        wait_for(
            lambda: cl.last_status("r1") and cl.last_status("r1").reason == "outside_workspace"
        )
    finally:
        ctl.stop()


def test_stale_pose_watchdog(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, stale_after=0.2)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        t_sent = time.monotonic()  # the controller receives the pose after this instant
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.answer("r1") and abs(complex(*cl.answer("r1").linear)) > 0)
        # an event, not a window: the watchdog fires (generous timeout for a loaded machine),
        # and never before stale_after has passed since the last pose (a bound load cannot break)
        wait_for(lambda: getattr(cl.last_status("r1"), "reason", None) == "stale_pose", timeout=20)
        assert time.monotonic() - t_sent >= 0.2
        assert cl.wait_stopped("r1").pose_seq == -1
    finally:
        ctl.stop()


def test_missing_map_reports_the_transform_error(mem_net: InMemoryNetwork) -> None:
    ctl, tr, cl = setup(mem_net, fetch_period=0.05)
    try:
        cl.goal("r1", ws="nowhere")
        wait_for(lambda: ctl.counters["goals"] == 1)  # goal and pose travel separately
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.last_status("r1") and cl.last_status("r1").reason == "missing_map")
        cl.wait_stopped("r1")
        wait_for(
            lambda: (cl.pose("r1", 0, 0.5), "unknown workspace" in cl.last_status("r1").message)[1]
        )
        # the map appears later: fetched by query, the robot moves
        tr.solutions["nowhere"] = solution("nowhere")

        def moving() -> bool:
            cl.pose("r1", 0.0, 0.5)
            return cl.last_status("r1").state == "navigating"

        wait_for(moving, timeout=10, interval=0.05)
        assert cl.last_status("r1").state == "navigating"
    finally:
        ctl.stop()


def test_a_robot_whose_map_is_being_solved_holds_navigating_not_stopped(
    mem_net: InMemoryNetwork,
) -> None:
    # issue 23, item 2: never `stopped (missing_map)` for a map that is being solved; the
    # robot holds (zero command) with a status saying what it waits for, then moves
    ctl, tr, cl = setup(mem_net, fetch_period=0.05)
    try:
        tr.solving.add("late")
        cl.goal("r1", ws="late")
        wait_for(lambda: ctl.counters["goals"] == 1)

        def held() -> bool:
            cl.pose("r1", 0.0, 0.5)
            s = cl.last_status("r1")
            return s is not None and s.message.startswith(WAITING_FOR_MAP)

        wait_for(held, timeout=10, interval=0.05)
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.answer("r1") is not None)
        assert cl.answer("r1").linear == (0.0, 0.0)
        s = cl.last_status("r1")
        assert (s.state, s.reason) == ("navigating", "ok")
        assert s.message.startswith(WAITING_FOR_MAP) and "'late'" in s.message
        # the first revision comes: the robot moves on it
        tr.solutions["late"] = solution("late")
        tr.solving.discard("late")

        def moving() -> bool:
            cl.pose("r1", 0.0, 0.5)
            c = cl.last_cmd("r1")
            return c is not None and c.linear != (0.0, 0.0)

        wait_for(moving, timeout=10, interval=0.05)
        assert not [m for m in cl.status if m.robot_id == "r1" and m.state == "stopped"]
    finally:
        ctl.stop()


def test_dead_transform_service_stops_robots_until_it_returns(mem_net: InMemoryNetwork) -> None:
    ctl, tr, cl = setup(mem_net)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.last_status("r1") and cl.last_status("r1").state == "navigating")
        tr.token.close()
        wait_for(lambda: not ctl.transform_alive)
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: getattr(cl.last_status("r1"), "reason", None) == "transform_service_dead")
        cl.wait_stopped("r1")
        assert ctl.health().state == "degraded"
        tr.bus.declare_token(K.alive("transform", "again"))
        wait_for(lambda: ctl.transform_alive)
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: _state(cl, "r1") == "navigating")
    finally:
        ctl.stop()


def test_bad_goal_is_rejected_and_bad_goal_point_reported(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        cl.bus.publish(K.robot("r1", "goal"), b'{"robot_id":"r1"}')
        wait_for(lambda: ctl.counters["rejected"] == 1)
        wait_for(lambda: getattr(cl.last_status("r1"), "reason", "") == "invalid_input")
        assert "goal rejected" in cl.last_status("r1").message  # answered on the bus
        cl.bus.publish(K.robot("r1", "goal"), encode(Goal(robot_id="r9", ws_id="cd", goal=(0, 0))))
        wait_for(lambda: ctl.counters["rejected"] == 2)
        wait_for(lambda: "'r9'" in cl.last_status("r1").message)
        cl.goal("r1", xy=(0.4, 0.0))  # inside the obstacle: NavigationError from the library
        wait_for(lambda: ctl.counters["navigation_errors"] >= 1)
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.last_status("r1") and cl.last_status("r1").reason == "navigation_error")
        cl.wait_stopped("r1")
    finally:
        ctl.stop()


@pytest.mark.timeout(60)
def test_controller_over_real_zenoh(make_bus: Callable[[], Any]) -> None:
    tr = FakeTransform(make_bus())
    tr.solutions["cd"] = solution()
    ctl = ControllerService(make_bus(), K, map_loader=identity_loader, health_period=0.2)
    ctl.start()
    try:
        cl = Client(make_bus())
        time.sleep(0.3)
        g = cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"], timeout=10)
        cl.pose("r1", 0.2, 0.5)
        cmd = wait_for(lambda: cl.answer("r1"), timeout=5)
        assert same(complex(*cmd.linear), expected_u(g, 0.2 + 0.5j))
        tr.token.close()
        wait_for(lambda: not ctl.transform_alive, timeout=5)
        cl.pose("r1", 0.2, 0.5)
        wait_for(
            lambda: getattr(cl.last_status("r1"), "reason", None) == "transform_service_dead",
            timeout=5,
        )
    finally:
        ctl.stop()


def test_only_the_newest_waiting_pose_of_a_robot_is_answered(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        cl.goal("r1")
        cl.goal("r2")
        wait_for(lambda: ctl.counters["goals"] == 2 and ctl.counters["maps_installed"])
        wait_for(lambda: ctl._robots["r2"].ctrl is not None)

        def pose(rid: str, seq: int) -> tuple[str, bytes]:
            p = Pose(robot_id=rid, stamp_ns=time.time_ns(), seq=seq, x=0.0, y=0.5)
            return (K.robot(rid, "pose"), encode(p))

        # a backlog as an overloaded controller would find it
        ctl._on_poses([pose("r1", 1), pose("r2", 1), pose("r1", 2), pose("r1", 3), pose("r2", 2)])
        wait_for(lambda: {(c.robot_id, c.pose_seq) for c in cl.cmds} >= {("r1", 3), ("r2", 2)})
        answered = [(c.robot_id, c.pose_seq) for c in cl.cmds if c.pose_seq > 0]
        assert sorted(answered) == [("r1", 3), ("r2", 2)]
        assert ctl.counters["poses_superseded"] == 3
    finally:
        ctl.stop()


def test_poses_before_the_goal_count_no_spurious_stale_pose(mem_net: InMemoryNetwork) -> None:
    """A robot publishing poses (10 Hz) before its goal: the goal is followed by commands,
    never by a stale_pose stop (the pose before the goal is remembered, the goal time counts
    as the start of the watchdog)."""
    ctl, _tr, cl = setup(mem_net, stale_after=0.3)
    try:
        cl.goal("r0")  # another robot, so that the map is there
        wait_for(lambda: ctl.counters["maps_installed"])
        for _ in range(3):
            cl.pose("r1", 0.0, 0.5)
            time.sleep(0.1)
        cl.goal("r1")
        for _ in range(10):
            time.sleep(0.1)
            cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: _state(cl, "r1") == "navigating")
        assert not [s for s in cl.status if s.robot_id == "r1" and s.reason == "stale_pose"]
    finally:
        ctl.stop()


def test_replayed_or_reordered_poses_are_not_fresh(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, stale_after=0.3)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        t = time.time_ns()
        newest = Pose(robot_id="r1", stamp_ns=t, seq=10, x=0.0, y=0.5)
        cl.bus.publish(K.robot("r1", "pose"), encode(newest))
        wait_for(lambda: any(c.pose_seq == 10 for c in cl.cmds))
        # older poses (a replay of the past, or reordered delivery) keep coming: not answered,
        # and the robot goes stale as if no pose came
        # the old poses keep coming until the robot goes stale: were they taken as fresh, the
        # watchdog would never fire (an event with a generous timeout, not a time window)
        sent = 0

        def stale_while_old_poses_keep_coming() -> bool:
            nonlocal sent
            old = Pose(robot_id="r1", stamp_ns=t - 1000 * (sent + 1), seq=9, x=0.0, y=0.5)
            cl.bus.publish(K.robot("r1", "pose"), encode(old))
            sent += 1
            stale = getattr(cl.last_status("r1"), "reason", "") == "stale_pose"
            return sent >= 8 and stale

        wait_for(stale_while_old_poses_keep_coming, timeout=20, interval=0.05)
        assert ctl.counters["poses_out_of_order"] >= 7  # some may be superseded in the queue
        assert {c.pose_seq for c in cl.cmds} <= {10, -1}
    finally:
        ctl.stop()


def test_cancel_and_idle_ttl_forget_robots(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, idle_ttl=0.3)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: _state(cl, "r1") == "navigating")
        cl.bus.publish(K.robot("r1", "cancel"), encode(GoalCancel(robot_id="r1")))
        wait_for(lambda: _state(cl, "r1") == "idle")
        cl.wait_stopped("r1")
        assert "r1" not in ctl._robots
        # a robot with a goal that falls silent is forgotten after the TTL: statuses stop
        cl.goal("r2")
        wait_for(lambda: _state(cl, "r2") == "stopped")  # stale_pose
        wait_for(lambda: "r2" not in ctl._robots, timeout=3)
        # the farewell status is published after the robot is dropped: wait for it
        wait_for(lambda: cl.last_status("r2").state == "idle")
        assert "forgotten" in cl.last_status("r2").message
        n = len(cl.status)
        time.sleep(0.6)
        assert len(cl.status) == n  # nothing more about forgotten robots
        assert ctl.counters["robots_forgotten"] == 2
    finally:
        ctl.stop()


def test_goal_above_the_caps_is_refused_with_a_status(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, max_gain=5.0, max_speed=1.0)
    try:
        for kw in ({"gain": 50.0}, {"v_max": 3.0}):
            g = Goal(robot_id="r1", ws_id="cd", goal=(-0.5, 0.0), **kw)  # type: ignore[arg-type]
            cl.bus.publish(K.robot("r1", "goal"), encode(g))
            wait_for(lambda: "above the caps" in getattr(cl.last_status("r1"), "message", ""))
            assert cl.last_status("r1").reason == "invalid_input"
            cl.status.clear()
        assert ctl._robots["r1"].goal is None
    finally:
        ctl.stop()


def _definition(obstacles: list[list[tuple[float, float]]]) -> WorkspaceDefinition:
    return WorkspaceDefinition(
        ws_id="cd", outer=[(-1, -1), (1, -1), (1, 1), (-1, 1)], obstacles=obstacles
    )


def test_definition_change_stops_robots_near_the_new_geometry(mem_net: InMemoryNetwork) -> None:
    """An obstacle appears 0.1 m from robot A: A is stopped at once (zero command, reason
    map_outdated, before any new pose), B (0.5 m away) keeps moving on the old map; A's poses
    are refused until the map of the new definition is installed, then A moves again."""
    ctl, tr, cl = setup(mem_net, margin=0.25)
    old = _definition([[(0.35, -0.05), (0.45, -0.05), (0.4, 0.05)]])
    tr.solutions["cd"] = solution()
    try:
        cl.goal("A")
        cl.goal("B")
        wait_for(lambda: ctl.counters["goals"] == 2 and ctl.counters["maps_installed"])
        cl.pose("A", 0.0, 0.5)
        cl.pose("B", 0.0, -0.5)
        wait_for(lambda: _state(cl, "A") == _state(cl, "B") == "navigating")
        # commands reach this client on another thread than statuses: wait for both answers,
        # so that the first command to A counted below is the one the definition caused
        wait_for(lambda: len({c.robot_id for c in cl.cmds if c.pose_seq >= cl.seq - 1}) == 2)
        assert ctl.counters["definitions_changed"] == 0
        new = _definition([*old.obstacles, [(-0.1, 0.6), (0.1, 0.6), (0.0, 0.75)]])
        n_cmds = len(cl.cmds)
        t0 = time.time_ns()
        tr.bus.publish(K.ws("cd", "definition"), encode(new))
        stop = wait_for(lambda: [c for c in cl.cmds[n_cmds:] if c.robot_id == "A"])[0]
        latency = (stop.stamp_ns - t0) / 1e9  # definition put -> stop command decided
        assert stop.linear == (0.0, 0.0) and stop.pose_seq == -1  # no pose needed
        wait_for(lambda: getattr(cl.last_status("A"), "reason", "") == "map_outdated")
        print(f"definition -> stop latency {latency * 1e3:.2f} ms")
        for _ in range(3):
            cl.pose("A", 0.0, 0.5)
            cl.pose("B", 0.0, -0.5)
            time.sleep(0.02)
        seq_a, seq_b = cl.seq - 1, cl.seq

        def answer(rid: str, seq: int) -> VelocityCommand | None:
            c = [m for m in cl.cmds if m.robot_id == rid and m.pose_seq == seq]
            return c[-1] if c else None

        a, b = wait_for(
            lambda: (
                (answer("A", seq_a), answer("B", seq_b))
                if answer("A", seq_a) and answer("B", seq_b)
                else None
            )
        )
        assert a.linear == (0.0, 0.0)
        assert abs(complex(*b.linear)) > 0 and _state(cl, "B") == "navigating"
        # the map of the new definition arrives: A moves again
        sol = solution(rev="rev2").model_copy(update={"definition_hash": definition_hash(new)})
        tr.bus.publish(K.ws("cd", "transform"), encode(sol))
        wait_for(lambda: ctl.counters["maps_installed"] == 2)

        def moving() -> bool:
            cl.pose("A", 0.0, 0.5)
            return _state(cl, "A") == "navigating"

        wait_for(moving, timeout=5, interval=0.05)
    finally:
        ctl.stop()


def test_deleted_workspace_stops_its_robots(mem_net: InMemoryNetwork) -> None:
    ctl, tr, cl = setup(mem_net)
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"])
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: _state(cl, "r1") == "navigating")
        del tr.solutions["cd"]
        tr.bus.publish(K.ws("cd", "delete"), encode(WorkspaceDelete(ws_id="cd")))
        wait_for(lambda: getattr(cl.last_status("r1"), "reason", "") == "missing_map")
        cl.wait_stopped("r1")
        cl.pose("r1", 0.0, 0.5)
        wait_for(lambda: cl.answer("r1") is not None)
        assert cl.answer("r1").linear == (0.0, 0.0)
    finally:
        ctl.stop()


def test_stall_at_a_saddle_is_reported_without_asking_for_the_critical_points(
    mem_net: InMemoryNetwork,
) -> None:
    # Nobody calls critical_points(): the service starts the search in the background when it
    # builds the controller, and reports "stalled" at the saddle once the points have landed.
    ctl, _tr, cl = setup(mem_net)
    try:
        g = cl.goal("r1")
        wait_for(lambda: ctl.robot_state("r1") is not None and ctl.counters["maps_installed"])
        ref = Controller(IdentityMap([complex(*c) for c in CENTERS], RADII), complex(*g.goal))
        (saddle,) = ref.critical_points().saddles  # one hole: one saddle, behind it
        assert abs(saddle.imag) < 1e-9 and 0.55 < saddle.real < 1.0  # mirror symmetry

        def stalled() -> bool:
            cl.pose("r1", saddle.real + 0.005, saddle.imag)
            time.sleep(0.05)
            s = cl.last_status("r1")
            return s is not None and "stalled" in s.message

        wait_for(stalled, timeout=30)
        assert cl.last_status("r1").state == "navigating"
        # away from the saddle: moving, no stall
        cl.pose("r1", 0.2, 0.5)
        cmd = wait_for(lambda: cl.answer("r1"))
        assert same(complex(*cmd.linear), expected_u(g, 0.2 + 0.5j))
        wait_for(lambda: "stalled" not in cl.last_status("r1").message)
    finally:
        ctl.stop()


class WalledIdentityMap(IdentityMap):
    """The identity map with its workspace (the circle domain: exact clearance), as a solved
    map has, so the controller's cap for held commands is on; counts map evaluations."""

    def __init__(self, centers: list[complex], radii: list[float]) -> None:
        super().__init__(centers, radii)
        from confnav.navigation.navfn import CircleDomain

        self.workspace = CircleDomain(self.centers, self.radii)
        self.sizes: list[int] = []

    def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
        self.sizes.append(np.asarray(z).size)
        return super().T_and_dT(z)

    def T(self, z: Any) -> np.ndarray:
        """T alone, as a solved map has it: what the controller's flat-phi check evaluates
        (one point, off the pose path: services/controller_flat.py), not counted in sizes."""
        return np.asarray(z, dtype=np.complex128)


def walled_loader(sol: Any) -> WalledIdentityMap:
    c = sol.coefficients
    return WalledIdentityMap([complex(x, y) for x, y in c["centers"]], list(c["radii"]))


def _library_u(m: Any, goal: Goal, z: complex) -> complex:
    law = Controller(m, complex(*goal.goal), gain=goal.gain, v_max=goal.v_max)
    return complex(np.asarray(law(np.asarray(z)).u).item())


def test_held_command_keeps_the_robot_off_the_wall(mem_net: InMemoryNetwork) -> None:
    """Through the service: a robot 1 cm from the disk obstacle gets a command that, held for
    the simulator's whole max_cmd_age, moves it at most half that (the end point is exactly
    outside the disk); a robot far from the walls gets the uncapped speed min(v_max, d)."""
    from confnav.navigation import defaults

    tr = FakeTransform(mem_net.bus("tr"))
    tr.solutions["cd"] = solution()
    ctl = ControllerService(mem_net.bus("ctl"), K, map_loader=walled_loader, health_period=0.2)
    ctl.start()
    cl = Client(mem_net.bus("client"))
    try:
        goals = {r: cl.goal(r) for r in ("near", "far")}
        wait_for(lambda: ctl.counters["goals"] == 2 and ctl.counters["maps_installed"])
        wait_for(lambda: all(ctl.robot_state(r) is not None for r in goals))
        c, rad = complex(*CENTERS[0]), RADII[0]
        z_near, z_far = c + (rad + 0.01) * 1j, -0.2 + 0.3j
        cl.pose("near", z_near.real, z_near.imag)
        u_near = complex(*wait_for(lambda: cl.answer("near")).linear)
        cl.pose("far", z_far.real, z_far.imag)
        u_far = complex(*wait_for(lambda: cl.answer("far")).linear)
        hold = defaults.HOLD_TIME
        assert 0 < abs(u_near) * hold <= defaults.HOLD_FRACTION * 0.01 * (1 + 1e-12)
        # the whole held segment [z, z + u hold] stays outside the disk and inside |z| < 1
        t = np.linspace(0.0, 1.0, 1001)
        path = z_near + u_near * hold * t
        assert np.all(np.abs(path - c) > rad) and np.all(np.abs(path) < 1)
        m = walled_loader(solution())
        assert same(u_near, _library_u(m, goals["near"], z_near))
        # far (clearance 0.52 m: cap 2.1 m/s) the speed is the normalized law's min(v_max, d)
        assert abs(abs(u_far) - min(0.5, abs(z_far - (-0.5 + 0j)))) <= 1e-12
        assert same(u_far, _library_u(m, goals["far"], z_far))
    finally:
        ctl.stop()


def test_robots_with_their_own_goals_share_one_map_evaluation(mem_net: InMemoryNetwork) -> None:
    """Sixteen robots, sixteen goals, one map: a block of their poses evaluates T and T' once
    for all of them, and every command equals the robot's own controller's (bitwise here:
    the identity map's values do not depend on the batch)."""
    tr = FakeTransform(mem_net.bus("tr"))
    tr.solutions["cd"] = solution()
    ctl = ControllerService(
        mem_net.bus("ctl"), K, map_loader=walled_loader, health_period=0.2, linger=0.2
    )
    ctl.start()
    cl = Client(mem_net.bus("client"))
    try:
        rids = [f"r{i}" for i in range(16)]
        goals = {r: cl.goal(r, xy=(-0.6 + 0.04 * i, 0.3 * np.sin(i))) for i, r in enumerate(rids)}
        wait_for(lambda: ctl.counters["controllers_built"] == 16)
        wait_for(lambda: all(ctl.robot_state(r) is not None for r in rids))
        m = ctl._maps["cd"].cmap
        m.sizes.clear()
        poses = {r: complex(0.1 * np.cos(i), 0.6 * np.sin(i)) for i, r in enumerate(rids)}
        for r, z in poses.items():
            cl.pose(r, z.real, z.imag)

        def answered(r: str) -> VelocityCommand | None:
            c = [x for x in cl.cmds if x.robot_id == r and x.pose_seq > 0]
            return c[-1] if c else None

        wait_for(lambda: all(answered(r) for r in rids))
        assert sum(m.sizes) == 16 and len(m.sizes) < 16  # evaluated together, once each
        ref = walled_loader(solution())
        for r in rids:
            got = complex(*answered(r).linear)
            want = _library_u(ref, goals[r], poses[r])
            assert abs(got - want) <= 1e-15 * abs(want) and abs(want) > 0
    finally:
        ctl.stop()


def test_a_goal_arriving_while_its_map_is_installed_gets_a_controller(
    mem_net: InMemoryNetwork,
) -> None:
    """A goal handled while the map of its workspace is being installed (after the
    installation took its snapshot of the goals, before the map was visible) gets a controller
    of that map: a lost race used to leave the robot without one until the next map."""
    import threading

    from confnav.services.navigation import make_controller

    entered, release = threading.Event(), threading.Event()

    def slow_factory(cmap: Any, goal: Goal) -> Any:
        if goal.robot_id == "r1":  # the installation is building r1's controller
            entered.set()
            assert release.wait(10)
        return make_controller(cmap, goal)

    ctl, _tr, cl = setup(mem_net, controller_factory=slow_factory)
    try:
        cl.goal("r1")
        assert entered.wait(10)
        cl.goal("r2", xy=(-0.5, 0.2))
        wait_for(lambda: "r2" in ctl._robots and ctl._robots["r2"].goal is not None)
        assert ctl.counters["maps_installed"] == 0  # the map is not installed yet
        release.set()
        wait_for(lambda: ctl.counters["maps_installed"] == 1)
        wait_for(lambda: ctl._robots["r2"].ctrl is not None)
        cl.pose("r2", 0.0, 0.5)
        cmd = wait_for(lambda: cl.answer("r2"))
        assert cmd.map_revision == "rev1" and abs(complex(*cmd.linear)) > 0
    finally:
        release.set()
        ctl.stop()


def test_controller_cache_is_bounded_and_robots_keep_theirs(
    mem_net: InMemoryNetwork, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Goals that change all the time must not pile up controllers (each holds a harmonic
    fit): the cache keeps the most recent CTRL_CACHE_SIZE; a robot keeps driving with its own
    controller after it was evicted, and robots with their own goals on one map are answered
    in one fleet step, each as its own controller would."""
    monkeypatch.setattr(controller_cache, "CTRL_CACHE_SIZE", 2)
    ctl, _tr, cl = setup(mem_net, linger=0.2)  # the four poses in one control step
    try:
        goals = {"r1": (-0.5, 0.0), "r2": (-0.5, 0.3), "r3": (0.0, -0.6), "r4": (0.5, 0.5)}
        for rid, xy in goals.items():
            cl.bus.publish(
                K.robot(rid, "goal"),
                encode(Goal(robot_id=rid, ws_id="cd", goal=xy, v_max=0.5, tolerance=0.02)),
            )
        wait_for(lambda: ctl.counters["controllers_built"] == 4)
        assert len(ctl._ctrl_cache) == 2
        for rid in goals:
            cl.pose(rid, 0.0, 0.5 if rid != "r4" else -0.5)
        wait_for(lambda: all(_state(cl, rid) == "navigating" for rid in goals))
        assert ctl.counters["fleet_steps"] >= 1
        for rid, xy in goals.items():
            cmd = wait_for(lambda rid=rid: cl.last_cmd(rid))
            g = Goal(robot_id=rid, ws_id="cd", goal=xy, v_max=0.5, tolerance=0.02)
            z = complex(0.0, 0.5 if rid != "r4" else -0.5)
            assert same(complex(*cmd.linear), expected_u(g, z)), rid
    finally:
        ctl.stop()


def test_a_status_changing_only_in_its_figures_is_repeated_once_per_period(
    mem_net: InMemoryNetwork,
) -> None:
    ctl, _tr, cl = setup(mem_net, status_period=60.0)
    try:
        r = _Robot("r9")
        t = time.monotonic()
        for i in range(20):  # twenty poses, each a new distance: one status
            note = f"getting to node 14, {0.9 - i / 100:.2f} m off it"
            ctl._status(r, "navigating", "ok", note, t)
        ctl._status(r, "navigating", "ok", "getting to node 13, 0.70 m off it", t)  # new node
        ctl._status(r, "navigating", "ok", "waiting at node 13", t)  # new wording
        wait_for(lambda: len([s for s in cl.status if s.robot_id == "r9"]) >= 3)
        time.sleep(0.2)  # nothing else is on its way
        got = [s.message for s in cl.status if s.robot_id == "r9"]
        assert got == [
            "getting to node 14, 0.90 m off it",
            "getting to node 13, 0.70 m off it",
            "waiting at node 13",
        ]
    finally:
        ctl.stop()
