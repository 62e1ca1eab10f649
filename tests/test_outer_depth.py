"""The a-priori crowding test of the first Koebe sweep (:func:`confnav.atlas.decompose.
outer_depth`): the finite-difference Green's function against the exact one of a disk, and
the floor plan that crowds without a long channel (rooms behind doors, furniture near their
walls) sent to the atlas by :func:`confnav.atlas.atlas_reason`, while a door between two
rooms, which one map solves, is not."""

from __future__ import annotations

import numpy as np

from confnav.atlas.charts import OUTER_DEPTH_MIN, atlas_reason
from confnav.atlas.decompose import outer_depth
from confnav.geometry import Workspace

#: The outside check's clinic (bench/results/outside_clinic.json): a 12 x 6 m corridor, three
#: rooms behind 0.9 m doors in 0.1 m walls, beds 0.2 m from two walls, a table.
CLINIC_OUTER = [
    (0, 0), (12, 0), (12, 2), (10.4, 2), (10.4, 2.1), (12, 2.1), (12, 6), (8.05, 6),
    (8.05, 2.1), (9.5, 2.1), (9.5, 2.0), (6.4, 2.0), (6.4, 2.1), (7.95, 2.1), (7.95, 6),
    (4.05, 6), (4.05, 2.1), (5.5, 2.1), (5.5, 2.0), (2.4, 2.0), (2.4, 2.1), (3.95, 2.1),
    (3.95, 6), (0, 6), (0, 2.1), (1.5, 2.1), (1.5, 2.0), (0, 2.0),
]  # fmt: skip
CLINIC_OBSTACLES = [
    [(0.2, 4.5), (1.2, 4.5), (1.2, 5.8), (0.2, 5.8)],
    [(5.0, 0.8), (7.0, 0.8), (7.0, 1.1), (5.0, 1.1)],
    [(6.8, 2.5), (7.7, 2.5), (7.7, 3.0), (6.8, 3.0)],
    [(5.0, 4.5), (5.4, 4.5), (5.4, 4.9), (5.0, 4.9)],
    [(10.5, 4.5), (11.8, 4.5), (11.8, 5.8), (10.5, 5.8)],
    [(9.0, 3.0), (9.4, 3.0), (9.4, 3.4), (9.0, 3.4)],
]

#: The project's shared door scene: two rooms joined by a 0.8 m door in a 0.15 m wall.
DOOR_OUTER = [
    (6.15, 2.8), (6.15, 5.0), (12.0, 5.0), (12.0, 0.0), (6.15, 0.0), (6.15, 2.0),
    (6.0, 2.0), (6.0, 0.0), (0.0, 0.0), (0.0, 5.0), (6.0, 5.0), (6.0, 2.8),
]  # fmt: skip
DOOR_OBSTACLES = [
    [(1, 1), (2.5, 1), (2.5, 1.8), (1, 1.8)],
    [(3.5, 3), (4.2, 3), (4.2, 4.5), (3.5, 4.5)],
    [(8, 0.8), (10.5, 0.8), (10.5, 1.6), (8, 1.6)],
    [(9, 3), (10.5, 3), (10.5, 4.4), (10.1, 4.4), (10.1, 3.4), (9, 3.4)],
]


def test_the_green_function_of_a_disk() -> None:
    """In the unit disk with its pole at 0 the Green's function is ``-log|z|``: on a small
    square centred at 0.5 its smallest value is ``-log`` of the square's farthest point."""
    t = np.linspace(0, 2 * np.pi, 512, endpoint=False)
    disk = list(zip(np.cos(t), np.sin(t), strict=True))
    sq = [(0.45, -0.05), (0.55, -0.05), (0.55, 0.05), (0.45, 0.05)]
    ws = Workspace(disk, [sq], anchor=0j)
    g, where = outer_depth(ws)
    exact = -np.log(abs(0.55 + 0.05j))
    assert abs(g - exact) <= 0.03 * exact
    assert abs(where.real - 0.55) <= 0.02 and abs(abs(where.imag) - 0.05) <= 0.02
    finer, _ = outer_depth(ws, cells=40_000)
    assert abs(finer - exact) < abs(g - exact) + 1e-3  # converges with the grid
    assert outer_depth(Workspace(disk, [], anchor=0j))[0] == float("inf")


def test_rooms_behind_doors_with_furniture_at_the_walls_go_to_the_atlas() -> None:
    clinic = Workspace(CLINIC_OUTER, CLINIC_OBSTACLES)
    g, where = outer_depth(clinic)
    assert g < OUTER_DEPTH_MIN
    assert where.imag > 2.1  # in a room, not in the corridor
    why = atlas_reason(clinic)
    assert "outer boundary" in why and "crowds" in why
    # the corridor alone (doors walled up): nothing near the unit circle, one map
    corridor = Workspace([(0, 0), (12, 0), (12, 2), (0, 2)], [CLINIC_OBSTACLES[1]])
    assert outer_depth(corridor)[0] > 1e-3 and atlas_reason(corridor) == ""


def test_a_door_between_two_rooms_is_one_map() -> None:
    """The door scene of the project's shared scenes (two rooms joined by a 0.8 m door in a
    0.15 m wall, furniture at least 0.8 m from the walls; its single map solves in 1.6 s)
    stays a single map."""
    ws = Workspace(DOOR_OUTER, DOOR_OBSTACLES)
    g, _ = outer_depth(ws)
    assert g > 10 * OUTER_DEPTH_MIN
    assert atlas_reason(ws) == ""
