"""A fleet's roadmap built in a child process (services/roadmap_worker.py) and the parts of the
core it rests on (confnav/navigation/fleet_coord.py: fleet_roadmap, plan_fleet_roadmap,
NodeLaws): the child's roadmap is the in-process one, its errors come back as errors, point
robots need no roadmap, node laws are made once each, when asked for."""

from __future__ import annotations

import numpy as np
import pytest
from confnav.services.roadmap_worker import RoadmapBuildError, build_in_child
from test_fleet_coord_async import DOOR, R  # the 0.9 m door, r 0.2

from confnav import Workspace, inflate
from confnav.errors import NavigationError
from confnav.navigation.fleet_coord import (
    LANE_FACTOR,
    MIN_SPACING,
    NodeLaws,
    RoadmapCoordinator,
    choose_coordinator,
    fleet_roadmap,
    plan_fleet_roadmap,
)

ROOM = Workspace([(0, 0), (6, 0), (6, 3), (0, 3)])


def test_the_child_builds_the_roadmap_built_in_process() -> None:
    """Through a real child process: the door's roadmap (``auto`` chooses it: the door is a
    single-lane passage for r 0.2) has the same nodes, edges and distances as the one built
    here, and the same choice, width and place; the open room's choice is ``local`` and no
    roadmap comes back."""
    ws = inflate(DOOR, R)
    here = plan_fleet_roadmap(ws, R, True)
    there = build_in_child(ws, R, True)
    assert here.choice == there.choice == "roadmap"
    assert here.roadmap is not None and there.roadmap is not None
    assert np.array_equal(here.roadmap.nodes, there.roadmap.nodes)
    assert np.array_equal(here.roadmap.edges, there.roadmap.edges)
    assert np.array_equal(here.roadmap.dist, there.roadmap.dist)
    assert (here.width, here.where) == (there.width, there.where)
    assert there.width < 0.9  # the door's width less the robot's on each side, about
    room = build_in_child(inflate(ROOM, R), R, True)
    assert room.choice == "local" and room.roadmap is None and room.width >= LANE_FACTOR * R


def test_a_failed_build_in_the_child_says_why() -> None:
    """A free space with no point clear enough for a node: the child's NavigationError comes
    back as the build's error, with its message (the controller logs it and keeps the local
    rules)."""
    narrow = Workspace([(0, 0), (4, 0), (4, 0.1), (0, 0.1)])
    with pytest.raises(NavigationError, match="clearance"):
        plan_fleet_roadmap(narrow, R, False)
    with pytest.raises(RoadmapBuildError, match=r"NavigationError: .*clearance"):
        build_in_child(narrow, R, False)


def test_point_robots_need_no_roadmap_and_small_ones_a_coarse_one() -> None:
    """``auto`` leaves point robots to the local rules without building anything (no passage
    is single-lane for a point); a forced roadmap for tiny robots has nodes at least
    MIN_SPACING apart, not 2 rho + 5 cm (thousands of nodes)."""
    fr = plan_fleet_roadmap(ROOM, 0.0, True)
    assert fr.choice == "local" and fr.roadmap is None
    rm = fleet_roadmap(ROOM, 0.0)
    assert rm.spacing == MIN_SPACING
    d = np.abs(rm.nodes[:, None] - rm.nodes[None, :]) + np.eye(rm.size) * 1e9
    assert d.min() >= MIN_SPACING - 1e-9
    assert fleet_roadmap(inflate(ROOM, R), R).spacing == pytest.approx((2 * R + 0.05) / 0.75**0.5)


def test_node_laws_are_made_when_first_asked_for_and_kept() -> None:
    """NodeLaws: nothing is made at construction; each node's law once, the same object
    after; negative indices and bounds as a list's."""
    made: list[int] = []
    laws = NodeLaws(np.array([0j, 1 + 0j, 2 + 1j]), lambda v, z: made.append(v) or (v, z))
    assert len(laws) == 3 and made == []
    assert laws[1] == (1, 1 + 0j) and laws[1] is laws[1] and made == [1]
    assert laws[-1] == (2, 2 + 1j) and made == [1, 2]
    with pytest.raises(IndexError):
        laws[3]
    assert [v for v, _ in laws] == [0, 1, 2]  # iteration stops at the end


def test_the_coordinator_on_a_roadmap_is_the_built_one() -> None:
    """``on_roadmap`` on the child's roadmap gives the coordinator ``build`` gives: the same
    roadmap, main component, choice and node laws (straight laws, one per node asked for)."""
    ws = inflate(DOOR, R)
    built = RoadmapCoordinator.build(None, 0, R, node_law="line", workspace=ws)
    fr = build_in_child(ws, R, False)
    assert fr.roadmap is not None
    on = RoadmapCoordinator.on_roadmap(fr.roadmap, None, 0, R, node_law="line", workspace=ws)
    assert np.array_equal(on.main, built.main)
    assert np.array_equal(on.roadmap.edges, built.roadmap.edges)
    assert choose_coordinator(on, R) == choose_coordinator(built, R)
    assert on.node_ctrls[0].goal == built.node_ctrls[0].goal == complex(on.roadmap.nodes[0])
