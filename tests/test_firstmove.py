"""First move (issue 23): a robot whose footprint map ``{ws}~r{R}`` has no revision yet drives
at once on the base map ``{ws}`` with the safety layer on the exact shrunk workspace, never
leaves that shrunk free space, and swaps to the footprint map when it is installed. Real Zenoh
sessions; the footprint map's solve is held back by a gate, so "before" is an event, not a
time window."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from confnav.schemas import (
    Goal,
    RobotStatus,
    TransformSolution,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services import navigation
from confnav.services.controller import ControllerService
from confnav.services.controller_footprint import same_geometry, shrunk_workspace
from confnav.services.definitions import definition_of, workspace_of
from confnav.services.keys import Keys
from confnav.services.transform import TransformService, solve_definition
from conftest import HolonomicRobot, square_definition, wait_for

from confnav.geometry import Workspace
from confnav.maps.footprint import UnreachableGoalError, inflate

K = Keys()
RADIUS = 0.1


class _GatedSolve:
    """The transform's solve, holding back every footprint workspace (``~r`` in its id)
    until :attr:`gate` is set."""

    def __init__(self) -> None:
        self.gate = threading.Event()

    def __call__(self, defn_json: str) -> dict[str, Any]:
        if "~r" in WorkspaceDefinition.model_validate_json(defn_json).ws_id:
            self.gate.wait(300)
        return solve_definition(defn_json)


class _Statuses:
    def __init__(self, bus: Any, rid: str) -> None:
        self.lock = threading.Lock()
        self.seen: list[RobotStatus] = []
        bus.subscribe(K.robot(rid, "status"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.seen.append(decode(RobotStatus, payload))

    def all(self) -> list[RobotStatus]:
        with self.lock:
            return list(self.seen)


@contextlib.contextmanager
def _system(make_bus: Callable[[], Any], defn: WorkspaceDefinition) -> Iterator[Any]:
    """Transform (footprint maps gated) and controller services; ``defn`` solved and
    installed in the controller."""
    gated = _GatedSolve()
    tr = TransformService(
        make_bus(), K, executor="thread", solve_fn=gated, progressive=False, health_period=0.2
    )
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    tr.start()
    ctl.start()
    client = make_bus()
    client.publish(K.ws(defn.ws_id, "definition"), encode(defn))
    try:
        wait_for(lambda: tr.state_of(defn.ws_id) == "solved", timeout=120)
        wait_for(lambda: defn.ws_id in ctl._maps, timeout=60)  # the controller has the map
        yield gated, tr, ctl, client, defn
    finally:
        gated.gate.set()
        ctl.stop()
        tr.stop()


@pytest.fixture
def system(make_bus: Callable[[], Any]) -> Iterator[Any]:
    defn = square_definition("sq", [(0.0, 0.1)]).model_copy(update={"tol": 1e-6})
    with _system(make_bus, defn) as parts:
        yield parts


def test_a_robot_with_a_body_moves_before_its_footprint_map_and_swaps_to_it(
    system: Any, make_bus: Callable[[], Any]
) -> None:
    gated, tr, ctl, client, defn = system
    did = "sq~r0.1"
    statuses = _Statuses(client, "r1")
    robot = HolonomicRobot(make_bus(), "r1", (-0.45, -0.45))
    try:
        goal = Goal(robot_id="r1", ws_id="sq", goal=(0.45, 0.45), robot_radius=RADIUS,
                    v_max=0.25, tolerance=0.03)  # fmt: skip
        client.publish(K.robot("r1", "goal"), encode(goal))
        # a non-zero command while the footprint map is held back (it has no revision)
        wait_for(robot.moving_commands, timeout=60)
        assert tr.state_of(did) != "solved" and not gated.gate.is_set()
        base_rev = tr._ws["sq"].revision
        assert {c.map_revision for c in robot.moving_commands()} == {base_rev}
        wait_for(lambda: any("unshrunk map" in s.message for s in statuses.all()), timeout=30)
        s0 = next(s for s in statuses.all() if s.state == "navigating")
        assert s0.reason == "ok" and "footprint map 'sq~r0.1' being solved" in s0.message
        # the robot drives a while on the base map, then the footprint map is released
        wait_for(lambda: abs(robot.z - complex(-0.45, -0.45)) > 0.15, timeout=60)
        gated.gate.set()
        wait_for(lambda: tr.state_of(did) == "solved", timeout=120)
        final = tr._ws[did].revision
        wait_for(lambda: any(s.map_revision == final for s in statuses.all()), timeout=60)
        wait_for(lambda: statuses.all()[-1].state == "arrived", timeout=120)
        seen = statuses.all()
        first = next(i for i, s in enumerate(seen) if s.state == "navigating")
        after = seen[first:]
        assert all(s.state in ("navigating", "arrived") for s in after), [
            (s.state, s.reason, s.message) for s in after if s.state != "navigating"
        ]
        revs = [s.map_revision for s in after]
        assert revs[0] == base_rev and revs[-1] == final
        # on the footprint map the status no longer says "unshrunk"
        assert not any("unshrunk" in s.message for s in after if s.map_revision == final)
        # the shrunk geometry the robot was kept in is the one its map was solved for
        sol = decode(TransformSolution, client.query(K.ws(did, "transform"))[0].payload or b"")
        local = shrunk_workspace(workspace_of(defn), did)
        assert same_geometry(local, navigation.load_map(sol).workspace)
        assert ctl.counters.get("footprint_mismatch", 0) == 0
        assert ctl.counters["controllers_built_on_base"] >= 1
        # the body never touched a wall: every position in the exact shrunk free space
        with robot.lock:
            path = np.array(robot.path)
        exact = workspace_of(defn)
        assert float(exact.clearance(path).min()) >= RADIUS - 1e-9
        assert float(inflate(exact, RADIUS).clearance(path).min()) >= 0.0
        assert abs(path[-1] - complex(0.45, 0.45)) <= 0.03 + 0.01
    finally:
        robot.stop.set()


def test_a_goal_outside_the_shrunk_free_space_is_refused_before_the_footprint_map(
    system: Any, make_bus: Callable[[], Any]
) -> None:
    """A goal 0.05 m from the wall for a 0.1 m body: the clear error (unreachable) at once,
    not a drive on the base map, and no command that moves."""
    gated, _tr, _ctl, client, _defn = system
    statuses = _Statuses(client, "r2")
    robot = HolonomicRobot(make_bus(), "r2", (-0.45, -0.45))
    try:
        goal = Goal(robot_id="r2", ws_id="sq", goal=(0.65, 0.0), robot_radius=RADIUS)
        client.publish(K.robot("r2", "goal"), encode(goal))
        st = wait_for(
            lambda: next((s for s in statuses.all() if s.reason == "navigation_error"), None),
            timeout=60,
        )
        assert st.state == "stopped" and "UnreachableGoalError" in st.message
        assert "sq~r0.1" in st.message and not gated.gate.is_set()
        assert robot.moving_commands() == []
    finally:
        robot.stop.set()


def test_where_the_unshrunk_map_hugs_an_obstacle_the_body_stays_in_the_shrunk_space(
    make_bus: Callable[[], Any],
) -> None:
    """Two thin obstacles, 0.12 m apart, the lower one joined to the wall by the 0.1 m body:
    the unshrunk map's own path round the upper one passes closer than 0.1 m to it (checked
    here: it leaves the shrunk free space), the robot driven on that map with the safety
    layer on the exact shrunk workspace never does, and it arrives with its footprint map
    still held back."""
    a = [(-0.05, 0.06), (0.05, 0.06), (0.05, 0.3), (-0.05, 0.3)]
    b = [(-0.05, -0.45), (0.05, -0.45), (0.05, -0.06), (-0.05, -0.06)]
    defn = WorkspaceDefinition(ws_id="gap", outer=[(-0.7, -0.7), (0.7, -0.7), (0.7, 0.7),
                               (-0.7, 0.7)], obstacles=[a, b], tol=1e-4)  # fmt: skip
    with _system(make_bus, defn) as (gated, tr, ctl, client, _):
        statuses = _Statuses(client, "r3")
        robot = HolonomicRobot(make_bus(), "r3", (-0.45, 0.0))
        try:
            goal = Goal(robot_id="r3", ws_id="gap", goal=(0.45, 0.0), robot_radius=RADIUS,
                        v_max=0.25, tolerance=0.03)  # fmt: skip
            client.publish(K.robot("r3", "goal"), encode(goal))
            wait_for(lambda: statuses.all() and statuses.all()[-1].state == "arrived", timeout=120)
            assert tr.state_of("gap~r0.1") != "solved" and not gated.gate.is_set()
            seen = statuses.all()
            nav = [s for s in seen if s.state == "navigating"]
            assert nav and all("unshrunk map 'gap'" in s.message for s in nav)
            assert not any(s.state == "stopped" for s in seen[seen.index(nav[0]) :])
            with robot.lock:
                path = np.array(robot.path)
            shrunk = inflate(workspace_of(defn), RADIUS)
            assert float(shrunk.clearance(path).min()) >= 0.0
            assert float(workspace_of(defn).clearance(path).min()) >= RADIUS - 1e-9
            assert ctl.counters["controllers_built_on_base"] >= 1
            # the same map with the unshrunk walls' filter only (a point robot's law): its
            # path leaves the shrunk free space, so the body's filter was needed
            reply = client.query(K.ws("gap", "transform"))[0].payload or b""
            # no body (no stand-in), at the speed this check's 0.05 s steps were made for
            point = goal.model_copy(update={"robot_radius": 0.0, "v_max": 0.1})
            free = navigation.make_controller(
                navigation.load_map(decode(TransformSolution, reply)), point
            )
            z, bare = complex(-0.45, 0.0), []
            for _ in range(600):
                u, _code = navigation.command(free, z.real, z.imag)
                z += 0.05 * u
                bare.append(z)
            assert float(shrunk.clearance(np.array(bare)).min()) < 0.0
        finally:
            robot.stop.set()


def test_make_controller_builds_the_stand_in_as_the_controller_does() -> None:
    """``navigation.make_controller`` (what ``replay --check`` rebuilds commands with) builds
    the stand-in from (unshrunk map, goal with a body): the safety layer on the exact shrunk
    workspace, and a goal the body cannot reach refused at once."""
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


def _one_map(defn_json: str) -> dict[str, Any]:
    """The transform's solve forced to one map (no a-priori atlas test, no crowding test):
    a single map whose navigation function is flat far from the goal. ``{ws}~atlas`` ids are
    solved chart by chart by the service itself, not by this function."""
    import warnings

    from confnav.services.definitions import solution_result

    from confnav.conformal.solver import solve

    defn = WorkspaceDefinition.model_validate_json(defn_json)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solution_result(solve(workspace_of(defn), defn.tol), defn.tol)


def test_a_robot_where_the_navigation_function_is_flat_drives_on_the_atlas(
    make_bus: Callable[[], Any],
) -> None:
    """A 1 m x 10.5 m corridor on one map, the goal 0.6 m from one end, the robot 9.4 m away:
    there the goal's Green's function is below double precision (1 - phi = 5.6e-13). The
    controller says so in the robot's status, asks for the corridor's atlas (``cor~atlas``),
    swaps the robot to it (commands carry its active chart) and the robot arrives without
    touching a wall. Without the check the robot stays on the flat single map forever."""
    from confnav.services.controller_flat import flat_here

    from confnav.atlas.wire import atlas_ws_id

    # anchored in the middle: each end crowds by exp(-5 pi) only, and phi decays honestly
    ws = Workspace([(0, 0), (10.5, 0), (10.5, 1), (0, 1)], [], anchor=5.25 + 0.5j)
    defn = definition_of("cor", ws, tol=1e-6)
    start, target = (10.0, 0.5), (0.6, 0.5)
    tr = TransformService(
        make_bus(), K, executor="thread", solve_fn=_one_map, progressive=False, health_period=0.2
    )
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    tr.start()
    ctl.start()
    client = make_bus()
    robot = None
    try:
        client.publish(K.ws("cor", "definition"), encode(defn))
        wait_for(lambda: "cor" in ctl._maps, timeout=120)
        goal = Goal(robot_id="f1", ws_id="cor", goal=target, v_max=1.0, tolerance=0.05)
        # the premise: the single map's law is flat at the start
        law = navigation.make_controller(ctl._maps["cor"].cmap, goal)
        assert "flat" in flat_here(law, start) and flat_here(law, (1.5, 0.5)) == ""
        statuses = _Statuses(client, "f1")
        robot = HolonomicRobot(make_bus(), "f1", start)
        wait_for(lambda: robot is not None and robot.seq > 2, timeout=30)  # its pose is known
        client.publish(K.robot("f1", "goal"), encode(goal))
        aid = atlas_ws_id("cor")
        wait_for(lambda: any("flat" in s.message for s in statuses.all()), timeout=60)
        wait_for(lambda: aid in ctl._maps, timeout=300)  # the atlas, solved on request
        on_atlas = lambda: [c for c in robot.moving_commands() if c.chart is not None]  # noqa: E731
        wait_for(on_atlas, timeout=60)
        wait_for(lambda: statuses.all()[-1].state == "arrived", timeout=120)
        assert ctl.counters["flat_starts"] == 1
        # the atlas was installed cold and the charts of the robot's path warmed in the
        # background (services/controller_warm.py): its first chart at least
        am = ctl._maps[aid].cmap
        first = on_atlas()[0].chart
        assert first is not None
        wait_for(lambda: am.is_warm(first), timeout=120)
        assert ctl.counters["charts_warmed"] >= 1
        assert {c.map_revision for c in on_atlas()} == {ctl._maps[aid].revision}
        with robot.lock:
            path = np.array(robot.path)
        assert float(ws.clearance(path).min()) > 0.0
        assert abs(path[-1] - complex(*target)) <= 0.05 + 0.05
    finally:
        if robot is not None:
            robot.stop.set()
        ctl.stop()
        tr.stop()
