"""Single-lane passages (``confnav.navigation.traffic``): gates found from exact geometry, the
mutex's grants and waits on hand cases."""

from __future__ import annotations

import numpy as np
import pytest

from confnav import Workspace
from confnav.errors import NavigationError
from confnav.navigation.traffic import Gates, Traffic, find_gates, segment_distance

# two 4 x 4 m rooms joined by a 0.8 m door in a 0.2 m wall (tests/test_fleet_yield.py)
DOOR = Workspace(
    [
        (0, 0), (4, 0), (4, 1.6), (4.2, 1.6), (4.2, 0), (8.2, 0), (8.2, 4), (4.2, 4),
        (4.2, 2.4), (4, 2.4), (4, 4), (0, 4),
    ]
)  # fmt: skip
# a 6 x 4 room with a 1 x 1 box whose top is 0.8 m below the top wall, far from the others
BOX = Workspace(
    [(0, 0), (6, 0), (6, 4), (0, 4)], [[(2.5, 2.2), (3.5, 2.2), (3.5, 3.2), (2.5, 3.2)]]
)


def test_gate_between_a_box_and_a_wall_for_wide_disks_only() -> None:
    # one component only (the door is a notch of the outer polygon): not found (stated)
    assert find_gates(DOOR, 0.2).count == 0
    # the box: 0.8 m to the top wall, 1.2 m to the bottom... of its own side: 2.2 m
    g = find_gates(BOX, 0.3)  # centres' width 0.8 - 0.6 = 0.2 < 0.6 + 0.1
    assert g.count == 1
    assert g.width[0] == pytest.approx(0.2, abs=1e-12)  # grid points on the bisector y = 3.6
    assert g.pair[0].tolist() == [0, 1]
    assert abs(g.axis[0].imag) < 1e-9  # along the passage (x)
    # the centre line: the principal axis of the run, which bends toward the box beyond its
    # corners (the parabolas): within 0.1 m of the bisector y = 3.6
    assert abs(g.a[0].imag - 3.6) < 0.1 and abs(g.b[0].imag - 3.6) < 0.1
    # the narrow run: the bisector's distance c < 2 rho + margin / 2 = 0.65 beyond the box's
    # corners too (c = 0.4 over the box, then the parabola to the corner): it spans the box
    assert (g.a[0].real < 2.5 and g.b[0].real > 3.5) or (g.b[0].real < 2.5 and g.a[0].real > 3.5)
    # disks of 0.15: 0.8 - 0.3 = 0.5 >= 0.3 + 0.1 wide: two pass, no gate
    assert find_gates(BOX, 0.15).count == 0
    with pytest.raises(NavigationError):
        find_gates(BOX, 0.0)


def test_segment_distance_exact() -> None:
    d = segment_distance(np.array([0j, 2 + 1j, -1 + 0j]), np.array([0j]), np.array([1 + 0j]))
    assert d[:, 0] == pytest.approx([0.0, np.sqrt(2.0), 1.0])


def _gate() -> Gates:
    return Gates(
        a=np.array([0j]), b=np.array([1 + 0j]), width=np.array([0.2]),
        pair=np.array([[0, 1]]), lane=0.6,
    )  # fmt: skip


def _path(p: complex, v: complex, k: int = 15) -> np.ndarray:
    return p + v * 0.1 * np.arange(k + 1)


def test_mutex_first_come_and_waits() -> None:
    tr = Traffic(_gate(), 2)  # occupy 0.35, stop 0.85
    # robot 0 west of the gate heading east, its path enters it; robot 1 far east, not yet
    p = np.array([-0.6 + 0j, 3.0 + 0j])
    paths = np.array([_path(p[0], 1), _path(p[1], -1)])
    wait, hold = tr.update(p, paths, [True, True])
    assert tr.gate.tolist() == [0, -1] and hold.tolist() == [True, False] and not wait.any()
    assert tr.dirn[0] == 1
    # robot 1 comes within 1.5 m: it requests westward, robot 0 holds eastward: robot 1 waits
    p = np.array([-0.2 + 0j, 1.7 + 0j])
    paths = np.array([_path(p[0], 1), _path(p[1], -1)])
    wait, hold = tr.update(p, paths, [True, True])
    assert tr.gate.tolist() == [0, 0] and tr.dirn[1] == -1
    assert hold.tolist() == [True, False] and wait.tolist() == [False, True]  # 0.7 < 0.85
    assert tr.waits == 1
    # robot 0 comes out on the east side, its path leads away: released; robot 1 granted
    p = np.array([1.6 + 0.8j, 1.7 + 0j])
    paths = np.array([_path(p[0], 1j), _path(p[1], -1)])
    wait, hold = tr.update(p, paths, [True, True])
    assert tr.gate[0] == -1 and not wait[1]
    wait, hold = tr.update(p, paths, [True, True])
    assert hold.tolist() == [False, True]


def test_mutex_simultaneous_requests_nearer_wins_and_same_direction_follows() -> None:
    tr = Traffic(_gate(), 3)
    p = np.array([-0.5 + 0j, 1.6 + 0j, -1.2 + 0j])  # 0 nearer than 1; 2 behind 0
    paths = np.array([_path(p[0], 1), _path(p[1], -1), _path(p[2], 1)])
    wait, hold = tr.update(p, paths, [True, True, True])
    assert hold.tolist() == [True, False, False]
    assert wait.tolist() == [False, True, False]  # 1 is 0.6 from the gate; 2 is 1.2 away
    # next step: 2 (same direction as the holder) came after 1's request: it waits its turn
    wait, hold = tr.update(p, paths, [True, True, True])
    assert hold.tolist() == [True, False, False]
    # a waiting robot must not step toward its gate
    assert tr.toward(p, np.array([0j, -0.5 + 0j, 0j])).tolist() == [False, True, False]
