"""Fleet coordination on a roadmap: the roadmap's geometry, PIBT steps, robots that swap
through a single-lane door with the coordinator."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import shortest_path

from confnav import Controller, Workspace, inflate, solve
from confnav.navigation.fleet_coord import RoadmapCoordinator, pibt_step
from confnav.navigation.fleet_sim import simulate_fleet
from confnav.navigation.roadmap import (
    Roadmap,
    build_roadmap,
    segment_clearance,
    segment_segment_distance,
)

# two 4 x 4 m rooms joined by a 0.8 m door in a 0.2 m wall (as tests/test_fleet_yield.py):
# for disks of r 0.2 the door's free width for centres is 0.4, a single lane
CORRIDOR = Workspace(
    [
        (0, 0), (4, 0), (4, 1.6), (4.2, 1.6), (4.2, 0), (8.2, 0), (8.2, 4), (4.2, 4),
        (4.2, 2.4), (4, 2.4), (4, 4), (0, 4),
    ]
)  # fmt: skip
R = 0.2


@pytest.fixture(scope="module")
def corridor_map():  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(inflate(CORRIDOR, R), 1e-6)


def test_segment_segment_distance_exact() -> None:
    # parallel unit segments 0.5 apart; crossing; collinear with a gap; point to segment
    assert segment_segment_distance(0, 1, 0.5j, 1 + 0.5j) == pytest.approx(0.5)
    assert segment_segment_distance(-1, 1, -1j, 1j) == 0.0
    assert segment_segment_distance(0, 1, 1.5, 3) == pytest.approx(0.5)
    assert segment_segment_distance(2 + 1j, 2 + 1j, 0, 4) == pytest.approx(1.0)
    # skew: the nearest points are an endpoint (1, 0) and the segment x = 2 at y in [-1, 1]
    assert segment_segment_distance(0, 1, 2 - 1j, 2 + 1j) == pytest.approx(1.0)


def test_roadmap_nodes_apart_edges_free_and_clear_of_third_nodes(corridor_map) -> None:  # type: ignore[no-untyped-def]
    ws = corridor_map.workspace
    gap = 2 * R + 0.05
    sp = gap / np.sqrt(0.75)
    rm = build_roadmap(ws, sp, pass_gap=gap, edge_clearance=0.03, prune_leaves=True)
    z = rm.nodes
    d = np.abs(z[:, None] - z[None, :]) + np.diag(np.full(z.size, np.inf))
    assert d.min() >= sp - 1e-9
    assert (ws.clearance(z) >= rm.min_clearance - 1e-9).all() and ws.contains(z).all()
    a, b = z[rm.edges[:, 0]], z[rm.edges[:, 1]]
    assert (segment_clearance(ws, a, b) >= 0.03).all()
    for e, (u, v) in enumerate(rm.edges.tolist()):
        others = np.setdiff1d(np.arange(z.size), [u, v])
        assert segment_segment_distance(z[others], z[others], a[e], b[e]).min() >= gap - 1e-9
    # 2-core: no dead ends; one component through the door; shortest paths are symmetric
    assert min(len(x) for x in rm.neighbours) >= 2
    assert len(set(rm.components().tolist())) == 1
    assert np.isfinite(rm.dist).all() and np.allclose(rm.dist, rm.dist.T)
    left, right = z.real < 4.0, z.real > 4.2
    assert left.any() and right.any()


def test_pibt_step_never_gives_a_node_to_two_robots(corridor_map) -> None:  # type: ignore[no-untyped-def]
    """Random occupancies, goals, priorities, fixed robots and closed nodes: every result is
    one node per robot, each a stay or a move along an edge, no swap, no move into a closed
    or blocked node, fixed robots stay."""
    gap = 2 * R + 0.05
    rm = build_roadmap(corridor_map.workspace, gap / np.sqrt(0.75), pass_gap=gap)
    rng = np.random.default_rng(1)
    adj = {(u, v) for u, v in rm.edges.tolist()} | {(v, u) for u, v in rm.edges.tolist()}
    moved = 0
    for _ in range(300):
        n = int(rng.integers(2, min(rm.size, 30)))
        at = rng.choice(rm.size, n, replace=False)
        goal = rng.integers(0, rm.size, n)
        prio = rng.random(n) * 10
        fixed = rng.random(n) < 0.1
        closed = set(rng.choice(rm.size, 3, replace=False).tolist())
        blocked = set(rng.choice(rm.size, 2, replace=False).tolist())
        nxt = pibt_step(
            rm, at.tolist(), goal.tolist(), prio.tolist(), fixed=fixed.tolist(),
            closed_nodes=closed, blocked=blocked, rng=rng,
        )  # fmt: skip
        assert len(set(nxt)) == n
        for i in range(n):
            u, v = int(at[i]), nxt[i]
            assert v == u or (u, v) in adj
            if v != u:
                moved += 1
                assert v not in closed and v not in blocked
            if fixed[i]:
                assert v == u
        swaps = {(int(at[i]), nxt[i]) for i in range(n) if nxt[i] != at[i]}
        assert not any((v, u) in swaps for u, v in swaps)
    assert moved > 0


def test_pibt_highest_priority_pushes_through_a_chain() -> None:
    """A path 0-1-2-3 with a cycle 3-4-5-3: robot A (top priority) at 0 going to 5 pushes
    robot B (at 1) ahead of it, and B steps into the cycle's side."""
    nodes = np.array([0, 1, 2, 3, 3.5 + 0.8j, 4], dtype=np.complex128)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [3, 5]], dtype=np.intp)
    nb = tuple(
        np.array([b if a == u else a for a, b in edges.tolist() if u in (a, b)]) for u in range(6)
    )

    w = np.abs(nodes[edges[:, 1]] - nodes[edges[:, 0]])
    dist = shortest_path(csr_matrix((w, (edges[:, 0], edges[:, 1])), shape=(6, 6)), directed=False)
    rm = Roadmap(nodes, edges, nb, dist, 1.0, 0.0)
    at, goal = [0, 1], [5, 1]
    for _ in range(6):
        at = pibt_step(rm, at, goal, [10.0, 0.0])
    assert at[0] == 5 and at[1] != 5


def test_two_robots_swap_through_a_single_lane_door(corridor_map) -> None:  # type: ignore[no-untyped-def]
    """Two robots swap rooms through a door where two disks cannot pass each other: with the
    coordinator both arrive (each through one excursion from its goal node) with no contact,
    and every tick gave the two robots different nodes (``tick`` checks it)."""
    starts = np.array([1.0 + 2.0j, 7.2 + 2.0j])
    goals = starts[::-1].copy()
    ctrls = [Controller(corridor_map, g) for g in goals]
    co = RoadmapCoordinator.build(corridor_map, 2, R)
    res = simulate_fleet(ctrls, starts, CORRIDOR, radius=R, t_max=120, coordinator=co)
    assert res.robot_contacts == 0 and res.wall_contacts == 0 and res.min_gap > 0
    assert res.arrived.all()
    assert co.ticks > 0 and co.excursions_done == 2
    assert len(set(co.at.tolist())) == 2


def test_a_robot_parked_in_the_door_is_pushed_aside(corridor_map) -> None:  # type: ignore[no-untyped-def]
    """Robot 0's goal is in the door: done, it parks on the roadmap there with priority 0.
    Robot 1, given its goal later (its first goal is near its start), must pass through the
    door: PIBT pushes the parked robot off the door's node, robot 1 arrives, no contact."""
    starts = np.array([2.0 + 2.0j, 1.0 + 1.0j])
    first = [Controller(corridor_map, 4.1 + 2.0j), Controller(corridor_map, 1.2 + 0.8j)]
    later = [[], [Controller(corridor_map, 7.0 + 2.0j)]]
    co = RoadmapCoordinator.build(corridor_map, 2, R)
    res = simulate_fleet(
        first, starts, CORRIDOR, radius=R, t_max=120, next_goals=later, coordinator=co,
        record_paths=True,
    )  # fmt: skip
    assert res.robot_contacts == 0 and res.wall_contacts == 0
    assert res.reached is not None and res.reached.tolist() == [1, 2] and res.arrived.all()
    assert res.arrival_time[0] < res.arrival_time[1]  # robot 0 was parked when 1 came by
    assert res.paths is not None
    assert (np.abs(res.paths[:, 1] - (4.1 + 2.0j)) < 0.2).any()  # robot 1 went through the door
    parked = res.paths[int(np.rint(res.arrival_time[0] / 0.05)) :, 0]
    assert np.abs(parked - (4.1 + 2.0j)).max() > 2 * R  # robot 0 left the door after parking
