"""Walls first (issue 23 item 1 with fleets, issue 25): a robot that robots press against a
wall, where its wall rows and its pairwise rows have no common command, gets a command its
walls allow -- it may fail the pairwise row (the other robot's own row keeps the pair apart),
never the wall. Found on tb3_sandbox through the services (two robots deadlocked under the
local fleet rules; one body 1.5 mm into a wall after 77 s)."""

from __future__ import annotations

import numpy as np

from confnav.geometry import Workspace
from confnav.navigation.fleet import Rows, project_with_walls
from confnav.navigation.safety import safety_filter

BOX = Workspace([(0, 0), (4, 0), (4, 4), (0, 4)], [])


def _pressed(z: complex, push: float) -> Rows:
    """One pairwise row on a robot at ``z``: a neighbour above demands it move down at
    ``push`` m/s at least."""
    return Rows(
        a=np.array([[-1j]]),
        b=np.array([[push]]),
        who=np.array([[1]], dtype=np.intp),
        gap=np.array([[0.05]]),
    )


def test_a_robot_pressed_against_a_wall_keeps_off_it() -> None:
    f = safety_filter(BOX)
    z = np.array([2.0 + 0.02j])  # 2 cm above the bottom wall
    u_nom = np.array([0.0 + 0.0j])
    rows = _pressed(complex(z[0]), push=0.5)
    u, ok = project_with_walls(u_nom, z, rows, np.array([1.0]), [f])
    assert not ok[0]  # no command meets both: the robot is pressed against the wall
    # the command is one the walls allow: their filter leaves it as it is, bit for bit
    assert f(z, u).u[0] == u[0]
    assert not f(z, u).changed[0]
    # and it does not drive down at the pressing speed (the least-violation command did)
    assert -u[0].imag < 0.5


def test_a_robot_the_walls_do_not_limit_follows_the_rows() -> None:
    f = safety_filter(BOX)
    z = np.array([2.0 + 2.0j])  # mid-room: the row is met, the walls are far
    rows = _pressed(complex(z[0]), push=0.5)
    u, ok = project_with_walls(np.array([0j]), z, rows, np.array([1.0]), [f])
    assert ok[0] and abs(u[0] - (-0.5j)) < 1e-12
