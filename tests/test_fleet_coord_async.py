"""The fleet coordinator for a pose-driven host (:class:`FleetCoordinator`): robots named by
id that come and go, poses in partial batches; a robot alone is not coordinated."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest

from confnav import Controller, Workspace, inflate, solve
from confnav.errors import NavigationError
from confnav.navigation.control import Status
from confnav.navigation.fleet_coord import (
    ALONE,
    GOAL_LEG,
    PARKED,
    RETURN_LEG,
    ROAD,
    FleetCoordinator,
    LineLaw,
    RoadmapCoordinator,
    choose_coordinator,
    pibt_step,
)
from confnav.navigation.fleet_sim import simulate_fleet
from confnav.navigation.roadmap import segment_clearance

R = 0.2
# a 6 x 3 m room split at x = 3 by a 0.2 m wall with a 0.9 m door: one robot at a time
DOOR = Workspace(
    [
        (0, 0), (2.9, 0), (2.9, 1.05), (3.1, 1.05), (3.1, 0), (6, 0), (6, 3), (3.1, 3),
        (3.1, 1.95), (2.9, 1.95), (2.9, 3), (0, 3),
    ]
)  # fmt: skip
STARTS = np.array([0.8 + 1.0j, 0.8 + 2.0j, 5.2 + 2.0j, 5.2 + 1.0j])
GOALS = 6.0 - STARTS.real + 1j * STARTS.imag


@pytest.fixture(scope="module")
def door_map() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(inflate(DOOR, R), 1e-6)


def test_alone_is_not_coordinated_and_a_second_robot_engages(door_map: Any) -> None:
    fc = FleetCoordinator(RoadmapCoordinator.build(door_map, 0, R), ttl=2.0)
    [pl] = fc.plan(0.0, ["a"], [STARTS[0]], [GOALS[0]], ["g"])
    assert pl == ALONE and fc.size == 0
    plans = fc.plan(0.1, ["a", "b"], STARTS[:2], GOALS[:2], ["g", "g"])
    assert [p.coordinated for p in plans] == [True, True] and fc.size == 2
    c = fc.coord
    assert c.n == 2 and c.at[0] != c.at[1]  # distinct nodes, nearest its start
    for i in range(2):
        free = np.setdiff1d(c.main, c.at[:i])
        assert c.at[i] == free[np.argmin(np.abs(c.roadmap.nodes[free] - STARTS[i]))]
    assert all(p.ctrl is c.node_ctrls[int(c.at[i])] for i, p in enumerate(plans))
    assert plans[0].note == f"joining the roadmap at node {int(c.at[0])}"
    # b is not heard from for more than ttl: forgotten; a is alone again, let go
    [pl] = fc.plan(2.5, ["a"], [STARTS[0]], [GOALS[0]], ["g"])
    assert pl == ALONE and fc.size == 0 and fc.coord.n == 0


def test_remove_renumbers_the_robots_and_their_excursions(door_map: Any) -> None:
    c = RoadmapCoordinator.build(door_map, 0, R)
    for z in STARTS[:3]:
        c.add(z)
    at = c.at.copy()
    c.excursions = {2: c._excursion(2)}
    c.mode[2] = GOAL_LEG
    c.remove(0)
    assert c.n == 2 and list(c.at) == list(at[1:]) and set(c.excursions) == {1}
    assert c.mode.tolist() == [RETURN_LEG, GOAL_LEG]
    with pytest.raises(NavigationError):
        c.remove(5)


def test_add_refuses_when_every_node_is_taken(door_map: Any) -> None:
    c = RoadmapCoordinator.build(door_map, 0, R)
    for _ in range(c.main.size):
        c.add(3.0 + 1.5j)
    assert np.unique(c.at).size == c.main.size
    with pytest.raises(NavigationError, match="no free roadmap node"):
        c.add(3.0 + 1.5j)


class _Partial:
    """A :class:`FleetCoordinator` seen by ``simulate_fleet`` as its coordinator, fed as the
    controller service feeds it: each step only a random part of the robots' poses (the
    others keep their last plan), goals named by their point."""

    def __init__(self, fc: FleetCoordinator, n: int, seed: int = 3) -> None:
        self.fc, self.ids = fc, [f"r{i}" for i in range(n)]
        self.rng = np.random.default_rng(seed)
        self.last = [ALONE] * n

    def start(self, p: Any) -> None:
        pass

    def update(self, t: float, p: Any, goals: Any, done: Any) -> tuple[list[Any], np.ndarray]:
        pick = np.flatnonzero(self.rng.random(len(self.ids)) < 0.5)
        got = self.fc.plan(
            t, [self.ids[i] for i in pick], p[pick], goals[pick], [complex(g) for g in goals[pick]]
        )
        for i, pl in zip(pick.tolist(), got, strict=True):
            self.last[i] = pl
        return [pl.ctrl for pl in self.last], np.array([pl.goal_leg for pl in self.last])

    def reached(self, i: int) -> None:
        self.fc.reached(self.ids[i])


def test_four_robots_swap_through_the_door_fed_in_partial_batches(door_map: Any) -> None:
    """Two robots each side of a door one robot wide swap sides, the coordinator fed half
    the poses per step at random: all four arrive, no contact.  Without it (the local rules:
    side passing, yielding, the deadlock step) none arrives within 120 s."""
    ctrls = [Controller(door_map, complex(g)) for g in GOALS]
    fc = FleetCoordinator(RoadmapCoordinator.build(door_map, 0, R), ttl=2.0)
    res = simulate_fleet(ctrls, STARTS, DOOR, radius=R, t_max=120.0,
                         coordinator=_Partial(fc, 4))  # type: ignore[arg-type]  # fmt: skip
    assert res.arrived.all() and res.robot_contacts == 0 and res.wall_contacts == 0
    # every robot done: parked at its goal, on the roadmap, or on its way back to its goal
    assert fc.size == 4 and all(
        int(m) in (ROAD, RETURN_LEG, PARKED, GOAL_LEG) for m in fc.coord.mode
    )
    # the last to arrive stays at its goal (nobody needs its way): it is not driven off it
    last = int(np.argmax(res.arrival_time))
    assert int(fc.coord.mode[fc._index[f"r{last}"]]) == PARKED
    local = simulate_fleet(ctrls, STARTS, DOOR, radius=R, t_max=120.0)
    assert local.robot_contacts == 0 and not local.arrived.any()


def test_describe_says_what_a_robot_does(door_map: Any) -> None:
    fc = FleetCoordinator(RoadmapCoordinator.build(door_map, 0, R), ttl=10.0)
    c = fc.coord
    nodes = c.roadmap.nodes
    u = int(c.main[0])
    v = int(c.roadmap.neighbours[u][0])
    fc.plan(0.0, ["a", "b"], [nodes[v], nodes[u]], [nodes[v], nodes[v]], [0, 0])
    # a stands on v, b on u wants v (its goal node), both settled on the roadmap
    c.at[:] = c.nxt[:] = c.origin[:] = [v, u]
    c.mode[:] = ROAD
    c.goal_node[:] = [v, v]
    assert fc.describe(1) == f"waiting for a at node {u} (next node {v})"
    c.nxt[1] = v
    togo = c.roadmap.dist[v, v]
    assert fc.describe(1) == f"following roadmap to goal: node {u} -> {v}, {togo:.1f} m to go"
    c.mode[0] = GOAL_LEG
    assert fc.describe(0) == f"driving off the roadmap from node {v} to its goal"
    c.mode[0] = ROAD
    assert fc.describe(0, parked=True) == f"arrived; parked on roadmap node {v}"


def test_the_service_shell_coordinates_two_robots_never_one(door_map: Any, mem_net: Any) -> None:
    """``CoordMixin._coord_plans`` (services/controller_coord.py) on the controller service:
    a robot alone gets no plan (its own law, bitwise as before); with a second robot on the
    same map the roadmap is built off the pose path and both get plans (``roadmap``, and the
    default ``auto``: the 0.9 m door is a single-lane passage); with ``--fleet-coordinator
    local`` never; ``auto`` leaves an open room to the local rules."""
    import time as _time

    from confnav.schemas import Goal, Pose
    from confnav.services import navigation
    from confnav.services.controller import ControllerService
    from confnav.services.controller_state import _Robot
    from confnav.services.keys import Keys

    ctl = ControllerService(mem_net.bus("ctl"), Keys())
    assert ctl.fleet_coordinator == "auto"  # the default
    rows = []
    for i, rid in enumerate("ab"):
        g = Goal(robot_id=rid, ws_id="door", goal=(GOALS[i].real, GOALS[i].imag), robot_radius=R)
        r = _Robot(robot_id=rid, goal=g, ctrl=navigation.point_law(door_map, g))
        pose = Pose(robot_id=rid, stamp_ns=1, x=STARTS[i].real, y=STARTS[i].imag)
        rows.append((r, pose, r.ctrl))
    assert ctl._coord_plans(rows[:1], 0.0) == {}
    assert ctl._coord_plans(rows[:1], 0.1) == {}  # alone: no roadmap is even built
    assert ctl.counters.get("roadmaps_built", 0) == 0
    ctl._coord_plans(rows, 0.2)  # two robots: the roadmap is built in the background
    wait = _time.monotonic() + 30
    while not ctl.counters.get("roadmaps_built") and _time.monotonic() < wait:
        _time.sleep(0.05)
    plans = ctl._coord_plans(rows, 0.3)
    assert set(plans) == {"a", "b"} and all(p.coordinated for p in plans.values())
    assert plans["a"].note.startswith("joining the roadmap at node")
    assert ctl._coord_plans(rows[:1], 3.0) == {}  # b gone for more than the ttl: a alone
    assert ctl.counters.get("fleet_auto_roadmap") == 1  # decided once, for the map
    for mode in ("roadmap", "local"):
        other = ControllerService(mem_net.bus(f"ctl-{mode}"), Keys())
        other.fleet_coordinator = mode
        other._coord_plans(rows, 0.0)
        wait = _time.monotonic() + 30
        while mode == "roadmap" and not other.counters.get("roadmaps_built"):
            assert _time.monotonic() < wait
            _time.sleep(0.05)
        assert bool(other._coord_plans(rows, 0.1)) == (mode == "roadmap")
        assert not any(k.startswith("fleet_auto") for k in other.counters)
    # an open room (the door's room without its wall): auto keeps the local rules
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        room_map = solve(inflate(Workspace([(0, 0), (6, 0), (6, 3), (0, 3)]), R), 1e-6)
    room = ControllerService(mem_net.bus("ctl-room"), Keys())
    rows = [(r, pose, navigation.point_law(room_map, r.goal)) for r, pose, _ in rows]  # type: ignore[arg-type]
    for r, _, law in rows:
        r.ctrl = law
    room._coord_plans(rows, 0.0)
    wait = _time.monotonic() + 30
    while not room.counters.get("fleet_auto_local"):
        assert _time.monotonic() < wait
        _time.sleep(0.05)
    assert room._coord_plans(rows, 0.1) == {} and room.counters["fleet_auto_local"] == 1
    assert not room.counters.get("roadmaps_built")


def test_a_robot_held_off_its_node_goes_back_where_it_came_from(door_map: Any) -> None:
    """A robot on its way from node u to v that makes no progress for ``late_limit`` s is
    sent back to u (reverts), unless another robot is on, bound for or coming from u."""
    c = RoadmapCoordinator.build(door_map, 0, R, late_limit=3.0)
    nodes = c.roadmap.nodes
    u = int(c.main[0])
    v = int(c.roadmap.neighbours[u][0])
    c.add(nodes[u])
    c.mode[:] = ROAD
    c.at[:], c.nxt[:], c.origin[:] = v, v, u
    c._best[:], c._t_best[:] = np.inf, 0.0
    p = np.array([0.5 * (nodes[u] + nodes[v])])  # half way, and it stays there
    goal = np.array([nodes[v]])
    for t in np.arange(0.0, 2.9, 0.05):
        c.update(float(t), p, goal, np.array([False]))
    assert c.nxt[0] == v and c.reverts == 0  # not yet 3 s
    for t in np.arange(2.9, 4.5, 0.05):
        c.update(float(t), p, goal, np.array([False]))
    assert c.reverts == 1 and c.nxt[0] == u and c.origin[0] == v
    # with a second robot bound for the node it would go back to: no revert
    c2 = RoadmapCoordinator.build(door_map, 0, R, late_limit=3.0)
    c2.add(nodes[u])
    w = next(int(x) for x in c2.main if int(x) not in (u, v))
    c2.add(nodes[w])
    c2.mode[:] = ROAD
    c2.at[:], c2.nxt[:], c2.origin[:] = [v, u], [v, u], [u, w]
    c2._best[:], c2._t_best[:] = np.inf, 0.0
    p2 = np.array([0.5 * (nodes[u] + nodes[v]), 0.5 * (nodes[u] + nodes[w])])
    for t in np.arange(0.0, 4.5, 0.05):
        c2.update(float(t), p2, np.array([nodes[v], nodes[u]]), np.array([False, False]))
    # robot 1 may go back to w (free); robot 0's node u stays robot 1's: robot 0 stays put
    assert int(c2.nxt[0]) == v and int(c2.origin[0]) == u
    assert len({int(c2.nxt[0]), int(c2.nxt[1])}) == 2


# a single-lane passage (0.7 m: 0.3 m for the centres of 0.2 m robots) between two rooms, with
# a side pocket above its middle, large enough to hold a cycle of roadmap nodes
LANE = Workspace(
    [
        (0, 0), (2, 0), (2, 0.65), (5.5, 0.65), (5.5, 0), (7.5, 0), (7.5, 2), (5.5, 2),
        (5.5, 1.35), (4.4, 1.35), (4.4, 3.0), (2.8, 3.0), (2.8, 1.35), (2, 1.35), (2, 2),
        (0, 2),
    ]
)  # fmt: skip


def _teleport(c: RoadmapCoordinator, p: np.ndarray, goals: np.ndarray, done: np.ndarray,
              t: float) -> None:  # fmt: skip
    """One step of robots that are where their plan sends them at once: on the roadmap at
    their next node, on the goal leg at their goal (then reached), parked at their goal."""
    c.update(t, p, goals, done)
    for i in range(c.n):
        m = int(c.mode[i])
        if m == GOAL_LEG:
            p[i] = goals[i]
            c.reached(i)
            done[i] = True
        elif m == PARKED:
            p[i] = goals[i]
        elif m == RETURN_LEG:
            p[i] = c.roadmap.nodes[int(c.at[i])]
        else:
            p[i] = c.roadmap.nodes[int(c.nxt[i])]


@pytest.mark.parametrize("come_back", ["idle", "clear"])
def test_a_robot_pushed_in_a_lane_steps_into_the_pocket_and_comes_back(come_back: str) -> None:
    """Robot b is parked at its goal in a single-lane passage; robot a crosses the passage.
    b is pushed off its goal ahead of a, then into the side pocket (off a's shortest path,
    not along the lane ahead of a to its far end), and once a has passed, b goes back to its
    goal and parks there.  Before: b was pushed along the lane ahead of a and stayed where it
    was pushed."""
    ws = inflate(LANE, R)
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=ws)
    c.come_back = come_back  # once a is done too (default), or once a has passed b's goal
    nodes = c.roadmap.nodes
    pocket = np.flatnonzero(nodes.imag > 1.5)  # the pocket's nodes (the lane's are below)
    far_room = np.flatnonzero(nodes.real > 5.3)
    assert pocket.size >= 3 and far_room.size
    goals = np.array([0.8 + 1.0j, 2.25 + 1.0j])  # a: first in its room; b: in the lane
    p = np.array([0.8 + 0.6j, 2.25 + 1.0j])
    for z in p:
        c.add(complex(z))
    done = np.array([False, False])
    t = 0.0
    for _ in range(100):  # b reaches its goal and parks; a waits in its room
        _teleport(c, p, goals, done, t)
        t += 0.2
    assert int(c.mode[1]) == PARKED and done[1]
    home = int(c.goal_node[1])
    goals[0], done[0] = 7.0 + 1.0j, False  # a crosses the lane
    b_nodes: list[int] = []
    for _ in range(400):
        _teleport(c, p, goals, done, t)
        t += 0.2
        b_nodes.append(int(c.nxt[1]))
        if done.all() and int(c.mode[1]) == PARKED:
            break
    assert done[0] and abs(p[0] - goals[0]) < 1e-12  # a crossed
    assert any(v != home for v in b_nodes)  # b was pushed off its goal ...
    assert set(b_nodes) & set(pocket.tolist())  # ... into the pocket
    assert not set(b_nodes) & set(far_room.tolist())  # not to the lane's far end
    # it steps aside at the pocket's near corner (x 3.1-3.2 m), not pushed on along the lane
    # ahead of a (before: on to x 4.0 under the pocket, then into its far corner)
    assert max(float(nodes[v].real) for v in b_nodes) < 3.5
    assert int(c.mode[1]) == PARKED and int(c.at[1]) == home and p[1] == goals[1]  # back


def test_pibt_a_meek_robot_pushes_no_one_and_a_pushed_one_steps_aside() -> None:
    """On the lane's roadmap: a robot pushed by another takes the node off the pusher's
    shortest path (the pocket) before the one ahead of it on the lane; a meek robot (done,
    going back) with the same wish does not push: it stays."""
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    rm = c.roadmap
    nodes = rm.nodes
    # three lane nodes under the pocket's near corner: u (left), v (the corner), the pocket
    # node above v and the lane node after v (both neighbours of v)
    v = int(np.flatnonzero(np.isclose(nodes, 3.2 + 1.1j, atol=0.06))[0])
    u = int(np.flatnonzero(np.isclose(nodes, 2.25 + 1.0j, atol=0.06))[0])
    far = int(np.argmax(nodes.real))
    nb = rm.neighbours[v].tolist()
    up = max((w for w in nb if w != u), key=lambda w: nodes[w].imag)
    ahead = min((w for w in nb if w not in (u, up)), key=lambda w: rm.dist[w, far])
    assert rm.dist[ahead, far] < rm.dist[up, far]  # the lane node is on the way, the pocket not
    # robot 0 on u heads for the far room; robot 1 (done: its goal is its node) stands on v
    out = pibt_step(rm, [u, v], [far, v], [1.0, 0.0])
    assert out == [v, up]  # pushed: into the pocket, not ahead along the lane
    # the same with robot 0 meek: it does not push robot 1, so it stays on u
    out = pibt_step(rm, [u, v], [far, v], [1.0, 0.0], meek=[True, False])
    assert out == [u, v]


def test_pibt_a_meek_robot_on_a_closed_node_pushes_its_way_off_it() -> None:
    """A robot that must leave a closed node (an excursion's) is not meek: where its only
    way off is a node another robot stands on, it pushes that robot.  Through the services
    (warehouse, seed 0, 3 rounds) a done robot on an excursion's node stood boxed in by
    another done robot; meek, it stayed, and the robot whose excursion needed the node
    waited for it to clear (bench/results/fleet_services_latch_seed0_3rounds.json).
    Before: it stayed (its last resort)."""
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    rm = c.roadmap
    nodes = rm.nodes
    v = int(np.flatnonzero(np.isclose(nodes, 3.2 + 1.1j, atol=0.06))[0])
    u = int(np.flatnonzero(np.isclose(nodes, 2.25 + 1.0j, atol=0.06))[0])
    left = int(np.flatnonzero(np.isclose(nodes, 1.7 + 1.0j, atol=0.06))[0])
    assert sorted(rm.neighbours[u].tolist()) == sorted([left, v])
    # robot 0 (done, meek) on the closed node u; robot 1 (done) on v; robot 2 fixed on left
    kw: dict[str, Any] = {"closed_nodes": {u}, "fixed": [False, False, True]}
    out = pibt_step(rm, [u, v, left], [u, v, left], [0.0, 0.0, 0.0], meek=[True, True, False],
                    **kw)  # fmt: skip
    assert out[0] == v and out[1] not in (u, v) and out[2] == left
    assert len(set(out)) == 3


def test_auto_chooses_the_roadmap_where_a_passage_is_single_lane() -> None:
    """``auto`` (:func:`choose_coordinator`): the bench's open room (the swaps) and its 1.2 m
    door (two robots of 0.2 m pass in it) keep the local rules; the lane (0.7 m) and the
    0.9 m door (the local rules freeze there: the door test above) get the roadmap.  The
    narrowest width is the centres' free space across the passage: the passage less 2 r."""
    room = Workspace(  # bench/bench_fleet.py's ROOM and DOOR
        [(0, 0), (10, 0), (10, 8), (0, 8)],
        [
            [(3, 2.5), (4.2, 2.5), (4.2, 3.7), (3, 3.7)],
            [(6, 4.5), (7.2, 4.5), (7.2, 5.7), (6, 5.7)],
        ],
    )
    door12 = Workspace(
        [
            (0, 0), (4.9, 0), (4.9, 3.4), (5.1, 3.4), (5.1, 0), (10, 0), (10, 8), (5.1, 8),
            (5.1, 4.6), (4.9, 4.6), (4.9, 8), (0, 8),
        ]
    )  # fmt: skip
    got = {}
    for name, ws in (("room", room), ("door 1.2", door12), ("lane", LANE), ("door 0.9", DOOR)):
        c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(ws, R))
        got[name] = choose_coordinator(c, R)
    assert {k: v[0] for k, v in got.items()} == {
        "room": "local", "door 1.2": "local", "lane": "roadmap", "door 0.9": "roadmap"
    }  # fmt: skip
    assert got["door 1.2"][1] == pytest.approx(1.2 - 2 * R, abs=0.01)
    assert got["door 0.9"][1] == pytest.approx(0.9 - 2 * R, abs=0.01)
    assert got["lane"][1] == pytest.approx(0.7 - 2 * R, abs=0.01)
    assert abs(got["door 0.9"][2] - (3.0 + 1.5j)) < 0.1  # found in the door


def test_straight_node_laws_do_not_take_a_robot_with_no_node_in_sight(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With straight node laws (an atlas) a robot that sees no free node would drive into a
    wall toward the nearest one and stay there (tb3_world through the services: 'joining the
    roadmap at node 3' for 180 s); ``add`` refuses it (the host leaves it to the local rules
    and asks again on its next pose). With a node in sight it is taken as before."""
    from confnav.navigation import fleet_coord

    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    real = fleet_coord.segment_clearance
    monkeypatch.setattr(fleet_coord, "segment_clearance", lambda ws, a, b: real(ws, a, b) - 1e3)
    with pytest.raises(NavigationError, match="no free roadmap node in straight sight"):
        c.add(0.8 + 0.6j)
    assert c.n == 0
    monkeypatch.setattr(fleet_coord, "segment_clearance", real)
    assert c.add(0.8 + 0.6j) == 0 and c.mode[0] == RETURN_LEG


# the outside check's studio flat (/work/outside/studio.json): a 1 m lane under a table
# (1.0-2.6 x 1.0-1.7 m) whose roadmap (bodies 0.18 m, look-ahead 0.1 m: rho 0.28 m) is a
# pocketless path of nodes from the lane's east end (3.33, 0.73) to the west of the room
STUDIO = Workspace(
    [
        (0, 0), (7, 0), (7, 3.2), (5.2, 3.2), (5.2, 3.0), (4.9, 3.0), (4.9, 4.6), (6.2, 4.6),
        (6.2, 5.5), (0, 5.5), (0, 3.4), (-0.9, 3.4), (-0.9, 2.4), (0, 2.4),
    ],
    [
        [(1.0, 1.0), (2.6, 1.0), (2.6, 1.7), (1.0, 1.7)],
        [(3.6, 4.2), (4.6, 4.2), (4.6, 5.2), (4.3, 5.2), (4.3, 4.5), (3.6, 4.5)],
        [(2.5, 2.45), (4.9, 2.45), (4.9, 2.55), (2.5, 2.55)],
        [(5.6, 0.5), (6.6, 0.5), (6.6, 0.58), (5.6, 0.58)],
        [(0.4, 4.6), (1.4, 4.6), (1.4, 5.2), (0.4, 5.2)],
    ],
)  # fmt: skip


def test_a_done_robot_cornered_in_a_lane_leads_the_way_out() -> None:
    """The studio swap (run_studio.sh): a (west end of the lane) and b (its east end) swap,
    c and d swap in the room above.  a reaches its goal at the lane's east end first; b,
    whose way west runs through a's goal, makes it leave; a, done and cornered (the lane has
    no pocket), leads the way out east past the junction and steps off b's way, b drives
    through, and a comes back: all four end parked at their goals.  Before: a was pushed
    west along the lane ahead of b, past b's goal, and stayed there behind b (3.1 m off its
    goal; 3.09 m through the services, bench/results/fleet_studio_auto.json)."""
    rho = 0.28
    c = RoadmapCoordinator.build(None, 0, rho, node_law="line", workspace=inflate(STUDIO, rho))
    starts = np.array([1.0 + 0.5j, 3.5 + 0.5j, 0.6 + 3.9j, 3.0 + 3.6j])
    goals = np.array([3.5 + 0.5j, 1.0 + 0.5j, 3.0 + 3.6j, 0.6 + 3.9j])
    p = starts.copy()
    for z in p:
        c.add(complex(z))
    done = np.zeros(4, dtype=bool)
    t = 0.0
    for _ in range(300):
        _teleport(c, p, goals, done, t)
        t += 0.2
        if done.all() and all(int(m) == PARKED for m in c.mode):
            break
    assert done.all()
    assert np.all(np.abs(p - goals) < 1e-12)  # every robot ends at its goal ...
    assert all(int(m) == PARKED for m in c.mode)  # ... parked there
    assert c.made_way > 0  # a led the way out of the lane


# the README's warehouse (examples/warehouse.yaml): three 6 m shelves and two pillars; for
# unicycles of the services bench (body 0.2 m, look-ahead 0.1 m: rho 0.3 m) each aisle's
# roadmap is a lane of nodes 0.8 m apart between the west and east ends
WAREHOUSE = Workspace(
    [(0, 0), (10, 0), (10, 8), (1, 8), (1, 7.2), (0, 7.2)],
    [
        [(2, 1.6), (8, 1.6), (8, 2.2), (2, 2.2)],
        [(2, 3.8), (8, 3.8), (8, 4.4), (2, 4.4)],
        [(2, 6.0), (8, 6.0), (8, 6.6), (2, 6.6)],
        [(8.8, 2.8), (9.2, 2.8), (9.2, 3.2), (8.8, 3.2)],
        [(8.8, 5.0), (9.2, 5.0), (9.2, 5.4), (8.8, 5.4)],
    ],
)


def test_a_robot_parked_at_the_end_of_a_push_chain_leaves_the_way() -> None:
    """The services warehouse's seed-1 stall (fleet_services_diag_seed1.json): in the
    bottom aisle two robots done with their goals stand on the lane between an active robot
    and its goal node, and a robot parked at its goal holds the lane's next node beyond
    them, out of the active robot's way and over ``3 gap`` from it along the roadmap.  The
    active robot's push runs down the two done robots and must end on that node: the parked
    robot leaves it, the chain moves, and the active robot reaches its goal.  Before: the
    push failed every tick and the active robot waited for good (``waiting for w04 at node
    21``; 198 of 200 goals)."""
    rho = 0.3
    c = RoadmapCoordinator.build(None, 0, rho, node_law="line", workspace=inflate(WAREHOUSE, rho))
    nodes = c.roadmap.nodes

    def node(z: complex) -> int:
        return int(np.flatnonzero(np.abs(nodes - z) < 0.06)[0])

    n12, n15, n18, n21 = (node(z) for z in (1.75 + 0.8j, 2.55 + 0.8j, 3.35 + 0.8j, 4.15 + 0.8j))
    assert set(c.roadmap.neighbours[n15].tolist()) == {n12, n18}  # a lane: no pocket
    # P parks at its goal off node 12; D1, D2 park at nodes 15, 18; A waits at node 21
    goals = np.array([1.75 + 0.55j, nodes[n15], nodes[n18], nodes[n21]])
    p = goals.copy()
    p[0] = nodes[n12]
    for z in p:
        c.add(complex(z))
    done = np.zeros(4, dtype=bool)
    t = 0.0
    for _ in range(60):
        _teleport(c, p, goals, done, t)
        t += 0.2
    assert done.all() and all(int(m) == PARKED for m in c.mode)
    assert int(c.at[0]) == n12
    for i in (1, 2):  # D1, D2: pushed off their goals earlier, now done on the roadmap
        c.mode[i] = ROAD
        c.excursions.pop(i, None)
    goals[3], done[3] = 2.886 + 0.69j, False  # A's next goal: its goal node is node 15
    assert c.goal_node_of(goals[3]) == n15
    assert c.roadmap.dist[n21, n12] > 3.0 * c.gap  # P is not near A ...
    for _ in range(300):
        _teleport(c, p, goals, done, t)
        t += 0.2
        if done[3]:
            break
    assert done[3] and abs(p[3] - goals[3]) < 1e-12  # ... yet leaves the way: A arrives


def test_straight_node_laws_give_the_goal_leg_a_straight_fallback() -> None:
    """With straight node laws (an atlas) the goal leg and the parked robot have the
    straight law to the goal point as their fallback (``Plan.fallback``; the segment from the
    goal node is free), which the controller service drives where the robot's own law has
    no value: through the services (seed 0) a robot's own atlas law was NaN 0.3-0.4 m from
    its goal in the top aisle (a chart flat to rounding there); the robot stopped on its goal
    leg ``outside the mapped free space`` for good and 12 robots queued behind it
    (bench/results/fleet_services_diag_seed0.json).  Before: no fallback."""
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    fc = FleetCoordinator(c)
    goals = np.array([0.8 + 1.0j, 6.8 + 1.0j])
    p = np.array([1.0 + 0.6j, 6.5 + 0.6j])
    t, plans = _on_goal_leg(c, fc, p, goals)
    pl = plans[0]  # its own law drives it ...
    law = pl.fallback  # ... and this where its own has no value
    assert isinstance(law, LineLaw) and law.goal == goals[0]
    z0 = complex(c.roadmap.nodes[int(c.at[0])])  # its goal node: the leg's start
    o = law(np.array([z0]))
    e = (goals[0] - z0) / abs(goals[0] - z0)
    assert int(o.status[0]) == Status.MOVING
    assert abs(o.u[0] / abs(o.u[0]) - e) < 1e-9  # straight at the goal (the filter is idle)
    o = law(np.array([goals[0]]))
    assert int(o.status[0]) == Status.ARRIVED and o.u[0] == 0
    fc.reached("a")
    pl = fc.plan(t, ["a", "b"], p, goals, [1, 1])[0]
    assert pl.parked and pl.ctrl is None and pl.fallback is law  # parked: the same fallback


def _on_goal_leg(c: RoadmapCoordinator, fc: FleetCoordinator, p: np.ndarray,
                 goals: np.ndarray) -> tuple[float, list[Any]]:  # fmt: skip
    """Robots teleported to their next nodes until robot ``a`` takes its goal leg."""
    t, plans = 0.0, []
    for _ in range(100):
        plans = fc.plan(t, ["a", "b"], p, goals, [1, 1])
        if plans[0].goal_leg:
            break
        for i in range(2):
            p[i] = c.roadmap.nodes[int(c.at[i] if c.mode[i] != ROAD else c.nxt[i])]
        t += 0.2
    assert plans[0].goal_leg and plans[0].ctrl is None
    return t, plans


def test_a_goal_leg_without_progress_drives_the_rest_straight() -> None:
    """A robot on its goal leg whose own law brings it no ``LEG_PROGRESS`` m nearer its goal
    for ``leg_patience`` s drives the rest of the leg on the straight law (where the segment
    to the goal is free): through the services a unicycle's own atlas law was rounding noise
    0.27 m from its goal (a crowded chart), with a value, so the NaN fallback never took
    over; it turned on the spot for good (bench/results/fleet_services_final_seed0.json).
    A robot that progresses keeps its own law."""
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    fc = FleetCoordinator(c)
    goals = np.array([0.8 + 1.0j, 6.8 + 1.0j])
    p = np.array([1.0 + 0.6j, 6.5 + 0.6j])
    t, plans = _on_goal_leg(c, fc, p, goals)
    z0 = p[0]
    e = (goals[0] - z0) / abs(goals[0] - z0)
    steps = int(np.ceil(c.leg_patience / 0.2)) + 5
    assert 0.005 * steps < 0.8 * abs(goals[0] - z0)
    for k in range(steps):  # slow but progressing (0.005 m per 0.2 s): its own law throughout
        p[0] = z0 + 0.005 * (k + 1) * e
        t += 0.2
        plans = fc.plan(t, ["a", "b"], p, goals, [1, 1])
        assert plans[0].goal_leg and plans[0].ctrl is None, k
    held, t_held = p[0], t  # then stuck (its last 0.02 m counted at most 0.8 s before)
    while t - t_held < c.leg_patience - 1.0 - 1e-9:  # its own law while patience lasts
        t += 0.2
        plans = fc.plan(t, ["a", "b"], p, goals, [1, 1])
        assert plans[0].ctrl is None
    t = t_held + c.leg_patience + 0.2
    pl = fc.plan(t, ["a", "b"], p, goals, [1, 1])[0]
    assert pl.goal_leg and isinstance(pl.ctrl, LineLaw) and pl.ctrl.goal == goals[0]
    assert pl.fallback is None and "straight" in pl.note
    p[0] = held + 0.3 * (goals[0] - held)  # latched for the rest of the leg, progress or not
    pl = fc.plan(t + 0.2, ["a", "b"], p, goals, [1, 1])[0]
    assert isinstance(pl.ctrl, LineLaw)
    fc.reached("a")  # the leg ends: parked, its own law (and the fallback) again
    pl = fc.plan(t + 0.4, ["a", "b"], p, goals, [1, 1])[0]
    assert pl.parked and pl.ctrl is None and isinstance(pl.fallback, LineLaw)


def test_a_stalled_goal_leg_behind_a_wall_keeps_its_own_law() -> None:
    """No straight law where the segment to the goal is not free: a robot stalled where a
    wall stands between it and its goal keeps its own law (the straight one would pin it
    to the wall)."""
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=inflate(LANE, R))
    fc = FleetCoordinator(c)
    goals = np.array([0.8 + 1.0j, 6.8 + 1.0j])
    p = np.array([1.0 + 0.6j, 6.5 + 0.6j])
    t, _ = _on_goal_leg(c, fc, p, goals)
    p[0] = 3.6 + 2.6j  # up the lane's pocket: the pocket's corner hides the goal
    ws = inflate(LANE, R)
    assert segment_clearance(ws, np.array([p[0]]), np.array([goals[0]]))[0] <= 0
    for _ in range(int(np.ceil(2 * c.leg_patience / 0.2)) + 2):
        t += 0.2
        pl = fc.plan(t, ["a", "b"], p, goals, [1, 1])[0]
        assert pl.goal_leg and pl.ctrl is None


def test_a_stalled_goal_leg_off_the_free_segment_goes_by_way_of_its_goal_node() -> None:
    """A robot stalled on its goal leg where the segment to its goal is not free but the one
    to its goal node is drives straight back to that node, then straight to the goal (the
    node's segment to the goal is free by construction): in the services warehouse (seed 1)
    a robot's own law took it round a pillar, off the free segment, where a parked robot
    held it 1.27 m from its goal."""
    ws = inflate(LANE, R)
    c = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=ws)
    fc = FleetCoordinator(c)
    goals = np.array([0.4 + 1.6j, 6.8 + 1.0j])  # a's goal in the left room's corner
    p = np.array([1.0 + 0.6j, 6.5 + 0.6j])
    t, _ = _on_goal_leg(c, fc, p, goals)
    home = complex(c.roadmap.nodes[int(c.at[0])])
    p[0] = 2.8 + 0.9j  # in the lane: the room's wall hides the goal, not the goal node
    assert segment_clearance(ws, np.array([p[0]]), np.array([goals[0]]))[0] <= 0
    assert segment_clearance(ws, np.array([p[0]]), np.array([home]))[0] > 0
    t += c.leg_patience + 0.2
    pl = fc.plan(t, ["a", "b"], p, goals, [1, 1])[0]
    assert pl.goal_leg and isinstance(pl.ctrl, LineLaw) and pl.ctrl.goal == home
    assert "by way of its goal node" in pl.note
    o = pl.ctrl(np.array([p[0]]))
    assert int(o.status[0]) == Status.MOVING  # no arrival off the goal
    p[0] = home + 0.5 * c.node_tol  # back at its goal node: straight to the goal
    pl = fc.plan(t + 0.2, ["a", "b"], p, goals, [1, 1])[0]
    assert pl.goal_leg and isinstance(pl.ctrl, LineLaw) and pl.ctrl.goal == goals[0]
    assert "straight" in pl.note
