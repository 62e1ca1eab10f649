"""The fleet roadmap in a maze of single-lane passages: the TurtleBot3 sandbox (a SLAM map:
nine pillars in a hexagon) for a 0.22 m unicycle with a 0.1 m look-ahead (filter radius
0.32 m), where three robots through the services met head-on in a lane for good
(bench/results/slam_services_s17_final_all.json: 13 of 15 arrived)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_fleet_coord_async import _teleport  # robots that are where their plan sends them

from confnav import Workspace, inflate
from confnav.maps.occupancy import import_map
from confnav.navigation.fleet_coord import (
    PARKED,
    RETURN_LEG,
    LineLaw,
    RoadmapCoordinator,
    choose_coordinator,
)
from confnav.navigation.roadmap import (
    TIGHT_EDGE_CLEARANCE,
    build_roadmap,
    free_path,
    segment_clearance,
)
from confnav.navigation.shortest_path import ShortestPaths

RHO = 0.32
SANDBOX = Path(__file__).parent / "data" / "slam" / "tb3_sandbox.yaml"


@pytest.fixture(scope="module")
def maze() -> Any:
    return inflate(import_map(SANDBOX).workspace, RHO)


def test_a_maze_keeps_a_roadmap_with_cycles_where_the_comfort_margin_left_none(maze: Any) -> None:
    """With the default edge clearance (0.03 m) the sandbox's lanes pinch nearer the walls
    than that: its roadmap is chains, its 2-core empty, so the fleet had no roadmap and
    ``auto`` chose the local rules.  The tighter core keeps the lanes round the pillars:
    cycles (as many edges as nodes or more), every edge free, nodes a robot's disk apart, and
    ``auto`` chooses the roadmap (the lanes are single-lane)."""
    gap = 2 * RHO + 0.05
    sp = gap / np.sqrt(0.75)
    chains = build_roadmap(maze, sp, pass_gap=gap, edge_clearance=0.03, max_edge=2.2 * sp)
    assert chains.size > 0 and len(chains.edges) < chains.size  # a forest: no 2-core
    c = RoadmapCoordinator.build(None, 0, RHO, node_law="line", workspace=maze)
    rm = c.roadmap
    assert rm.size >= 8 and len(rm.edges) >= rm.size
    a, b = rm.nodes[rm.edges[:, 0]], rm.nodes[rm.edges[:, 1]]
    assert np.all(segment_clearance(maze, a, b) >= TIGHT_EDGE_CLEARANCE)
    d = np.abs(rm.nodes[:, None] - rm.nodes[None, :]) + np.eye(rm.size) * 1e9
    assert d.min() >= sp - 1e-9
    assert np.all([len(nb) >= 2 for nb in rm.neighbours])  # a 2-core
    choice, width, _ = choose_coordinator(c, RHO)
    assert choice == "roadmap" and width < 2 * RHO


def test_a_robot_parked_where_no_node_sees_its_goal_goes_back_round_the_walls(
    maze: Any,
) -> None:
    """Robot a's goal in the sandbox's outer ring is seen by no roadmap node (its goal node is
    the nearest one, behind a pillar): its own law takes it there round the walls.  When
    robot b's way runs through that node, a leaves its goal for its node along a free
    polyline round the pillar (each leg a straight law; the corner passed, the next), and b
    arrives.  Before: a was sent straight back across the pillar (``returning to roadmap
    node 6 to park off the goal``), stood at the pillar's wall, and b waited for that node
    until the end of the run."""
    c = RoadmapCoordinator.build(None, 0, RHO, node_law="line", workspace=maze)
    nodes = c.roadmap.nodes
    goals = np.array([-1.731 - 0.973j, -0.652 - 1.779j])  # a: the ring; b: below the lanes
    ga, gb = c.goal_node_of(goals[0]), c.goal_node_of(goals[1])
    assert segment_clearance(maze, [nodes[ga]], [goals[0]])[0] <= 0  # no node sees it
    start_b = complex(nodes[np.argmin(np.abs(nodes - (-0.52 + 0.58j)))])  # b up the lane
    p = np.array([complex(nodes[ga]), start_b])
    for z in p:
        c.add(complex(z))
    done = np.array([False, True])  # b waits, done, until a has parked
    t = 0.0
    for _ in range(200):
        _teleport(c, p, goals, done, t)
        t += 0.2
        if int(c.mode[0]) == PARKED:
            break
    assert int(c.mode[0]) == PARKED and abs(p[0] - goals[0]) < 1e-12
    done[1] = False  # b's goal: its way down the lane runs through a's goal node
    via = c.roadmap.dist[c.at[1], ga] + c.roadmap.dist[ga, gb]
    assert via <= c.roadmap.dist[c.at[1], gb] + 1e-9
    left = False
    for _ in range(400):
        drive, _ = c.update(t, p, goals, done)
        if int(c.mode[0]) == RETURN_LEG and not left:
            left = True
            way = c.return_ways[0]
            assert len(way) >= 2 and way[-1] == nodes[ga]  # corners, the node last
            legs = np.array([goals[0], *way])
            assert np.all(segment_clearance(maze, legs[:-1], legs[1:]) > 0)
            assert isinstance(drive[0], LineLaw) and drive[0].goal == way[0]
            for z in way[:-1]:  # a passes each corner: the next leg's law
                p[0] = z
                drive, _ = c.update(t, p, goals, done)
        _teleport(c, p, goals, done, t)
        t += 0.2
        if done[1]:
            break
    assert left and done[1] and abs(p[1] - goals[1]) < 1e-12  # a left its goal, b arrived


def test_free_path_goes_round_a_wall_nearly_as_short_as_the_shortest_path() -> None:
    """A 4 x 3 m room with a wall from the floor to 0.5 m below the ceiling: from one side
    to the other the straight segment is not free; the polyline goes round the wall's end,
    every leg free, at most 3 % longer than the exact shortest path (visibility graph), and
    a free segment comes back as itself."""
    ws = Workspace([(0, 0), (1.9, 0), (1.9, 2.5), (2.1, 2.5), (2.1, 0), (4, 0), (4, 3), (0, 3)])
    a, b = 1.0 + 0.5j, 3.0 + 0.5j
    way = free_path(ws, a, b)
    assert way is not None and way[-1] == b and len(way) >= 2
    legs = np.concatenate([[a], way])
    assert np.all(segment_clearance(ws, legs[:-1], legs[1:]) > 0)  # a lower bound
    length = float(np.abs(np.diff(legs)).sum())
    exact = float(ShortestPaths(ws, b).lengths([a])[0])
    assert exact <= length <= 1.03 * exact
    assert np.array_equal(free_path(ws, a, 1.5 + 2.0j), np.array([1.5 + 2.0j]))
