"""A robot with a body moves before its footprint map exists (issue 23): the unshrunk map
steers it, the safety layer on the exact shrunk workspace keeps its body clear, and the
footprint map ``{ws}~r{R}`` takes over when it lands (real Zenoh sessions)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest
from confnav.schemas import Goal, RobotStatus, WorkspaceDefinition, decode, encode
from confnav.services import navigation
from confnav.services.controller import ControllerService
from confnav.services.keys import Keys
from confnav.services.transform import TransformService, solve_definition
from conftest import square_definition, wait_for
from test_progressive_maps import _Robot

from confnav.geometry import Workspace
from confnav.maps.footprint import UnreachableGoalError

K = Keys()
RADIUS = 0.1
START, GOAL = (0.0, -0.45), (0.0, 0.45)
#: A square room barred across but for a 0.05 m slit on the left (closed to the body) and a
#: 0.28 m door on the right (open to it). A point robot on the unshrunk map passes the door
#: 0.096 m from the bar's end, closer than the body's radius: the exact-geometry filter is
#: what keeps the body clear (the test fails without it).
BARRED = square_definition("sq").model_copy(
    update={"obstacles": [[(-0.65, -0.025), (0.42, -0.025), (0.42, 0.025), (-0.65, 0.025)]]}
)


def _gated_solver(gate: threading.Event) -> Callable[[str], dict[str, Any]]:
    """The library's solve, held for footprint workspaces until ``gate`` opens."""

    def solve(defn_json: str) -> dict[str, Any]:
        if "~r" in WorkspaceDefinition.model_validate_json(defn_json).ws_id:
            assert gate.wait(timeout=300)
        return solve_definition(defn_json)

    return solve


@pytest.mark.timeout(300)
def test_a_body_moves_on_the_unshrunk_map_until_its_footprint_map_lands(
    make_bus: Callable[[], Any],
) -> None:
    client = make_bus()
    statuses: list[RobotStatus] = []
    lock = threading.Lock()

    def on_status(key: str, payload: bytes) -> None:
        with lock:
            statuses.append(decode(RobotStatus, payload))

    client.subscribe(K.robot("r1", "status"), on_status)
    gate = threading.Event()
    tr = TransformService(make_bus(), K, executor="thread", solve_fn=_gated_solver(gate))
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    tr.start()
    ctl.start()
    robot = _Robot(make_bus(), "r1", START)
    track: list[complex] = []
    try:
        defn = BARRED
        client.publish(K.ws("sq", "definition"), encode(defn))
        wait_for(lambda: tr.state_of("sq") == "solved", timeout=120)
        base_rev = tr._ws["sq"].revision
        wait_for(lambda: getattr(ctl._maps.get("sq"), "revision", None) == base_rev, timeout=60)
        goal = Goal(robot_id="r1", ws_id="sq", goal=GOAL, robot_radius=RADIUS, v_max=0.3,
                    tolerance=0.03)  # fmt: skip
        client.publish(K.robot("r1", "goal"), encode(goal))

        def at_the_door() -> bool:
            with robot.lock:
                track.append(robot.z)
            return robot.z.real > 0.45

        wait_for(at_the_door, timeout=90, interval=0.05)  # the footprint map held back
        assert tr.state_of("sq~r0.1") != "solved"
        with lock:
            early = [s for s in statuses if s.state == "navigating"]
        assert early and all(s.map_revision == base_rev for s in early)
        assert "unshrunk map 'sq'" in early[-1].message
        assert "footprint map 'sq~r0.1' being solved" in early[-1].message
        assert not any(s.state == "stopped" for s in statuses), [
            (s.state, s.reason, s.message) for s in statuses if s.state == "stopped"
        ]

        gate.set()  # the footprint map lands (crowded at this door: solved as an atlas)
        wait_for(lambda: tr.state_of("sq~r0.1") == "solved", timeout=180)

        def arrived_on_footprint_map() -> bool:
            with robot.lock:
                track.append(robot.z)
            with lock:
                return any(
                    s.state == "arrived" and s.map_revision not in (None, base_rev)
                    for s in statuses
                )

        wait_for(arrived_on_footprint_map, timeout=180, interval=0.05)
        with lock:
            seen = list(statuses)
        assert all(s.state in ("navigating", "arrived") for s in seen), [
            (s.state, s.reason, s.message) for s in seen
        ]
        # the body never touched the obstacle or a wall (exact distance, sampled at 20 Hz)
        ws = Workspace(defn.outer, defn.obstacles)
        clearance = min(float(ws.clearance(z)) for z in track)
        assert clearance >= RADIUS - 2e-3, clearance
    finally:
        gate.set()
        robot.stop.set()
        ctl.stop()
        tr.stop()


def test_the_stand_in_refuses_a_goal_outside_the_shrunk_free_space() -> None:
    """The unshrunk map would accept it; the body cannot reach it: a clear error at once."""
    import confnav

    defn = square_definition("sq", [])
    ws = Workspace(defn.outer, defn.obstacles)
    cmap = confnav.solve(ws, 1e-4)
    cmap.ws_id = "sq"  # what load_map records
    goal = Goal(robot_id="r1", ws_id="sq", goal=(0.65, 0.0), robot_radius=RADIUS)
    assert navigation.stands_in(cmap, goal)
    with pytest.raises(
        UnreachableGoalError, match=r"unreachable.*largest component of the workspace shrunk"
    ):
        navigation.make_controller(cmap, goal)
    ok = goal.model_copy(update={"goal": (0.5, 0.0)})
    ctrl = navigation.make_controller(cmap, ok)
    shrunk = navigation.shrunk_workspace(cmap, ok)
    assert ctrl.safety.workspace is shrunk  # type: ignore[union-attr]
    assert shrunk.boundaries[0].size and not shrunk.contains(0.65 + 0j)
    assert not navigation.stands_in(cmap, ok.model_copy(update={"robot_radius": 0.0}))
