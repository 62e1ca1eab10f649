"""Fleets: idle robots yield (the rule of ``fleet.yield_way``), goals issued on arrival."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from confnav import Controller, Workspace, inflate, solve
from confnav.navigation.fleet import DeadlockMonitor, Rows, pairwise_rows, side_pass, yield_way
from confnav.navigation.fleet_sim import simulate_fleet

# two 4 x 4 m rooms joined by a 0.8 m door in a 0.2 m wall: two disks of r 0.2 cannot pass
# each other in the door (its free width for centres is 0.4)
CORRIDOR = Workspace(
    [
        (0, 0), (4, 0), (4, 1.6), (4.2, 1.6), (4.2, 0), (8.2, 0), (8.2, 4), (4.2, 4),
        (4.2, 2.4), (4, 2.4), (4, 4), (0, 4),
    ]
)  # fmt: skip


@pytest.fixture(scope="module")
def corridor_map():  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(inflate(CORRIDOR, 0.2), 1e-6)


def test_yield_way_hand_case() -> None:
    # robot 0 idle at 0.6 on robot 1's line (robot 1 at 0 heading +x): forward-left at 45 deg,
    # sqrt(2) * 0.5 long; a robot behind or beside is not blocked
    rows = pairwise_rows([0.6 + 0j, 0j], 0.2, 0.5)
    u, yl = yield_way([0j, 0.5 + 0j], [0.6 + 0j, 0j], 0.2, [True, False], rows, 0.5)
    assert yl.tolist() == [True, False]
    assert u[0] == pytest.approx(0.5 + 0.5j)
    assert u[1] == 0.5
    # clearly to the right of robot 1's line (l = -0.3 < -(0.2 + 0.2) / 2): forward-right
    rows = pairwise_rows([0.5 - 0.3j, 0j], 0.2, 0.5)
    u, yl = yield_way([0j, 0.5 + 0j], [0.5 - 0.3j, 0j], 0.2, [True, False], rows, 0.5)
    assert yl[0] and u[0] == pytest.approx(0.5 - 0.5j)
    # behind robot 1: no yield; beside it beyond the swept width: no yield
    for z0 in (-0.6 + 0j, 0.3 + 0.45j):
        rows = pairwise_rows([z0, 0j], 0.2, 0.5)
        u, yl = yield_way([0j, 0.5 + 0j], [z0, 0j], 0.2, [True, False], rows, 0.5)
        assert not yl.any() and u[0] == 0
    # both idle: nobody yields
    rows = pairwise_rows([0.6 + 0j, 0j], 0.2, 0.5)
    u, yl = yield_way([0j, 0.5 + 0j], [0.6 + 0j, 0j], 0.2, [True, True], rows, 0.5)
    assert not yl.any()


def test_parked_robot_in_a_corridor_yields_so_the_other_arrives(corridor_map) -> None:  # type: ignore[no-untyped-def]
    """Robot 0 is parked at its goal in the middle of a door too narrow to pass; robot 1
    drives through it.  Without the yield rule robot 1 never gets by (the filter holds it off
    robot 0); with it robot 0 steps out of the door ahead of robot 1, which arrives, with no
    contact either way."""
    starts = np.array([4.1 + 2.0j, 1.0 + 2.0j])
    goals = np.array([4.1 + 2.0j, 7.0 + 2.0j])
    ctrls = [Controller(corridor_map, g) for g in goals]
    res = simulate_fleet(ctrls, starts, CORRIDOR, radius=0.2, t_max=60)
    assert res.robot_contacts == 0 and res.wall_contacts == 0 and res.min_gap > 0
    assert res.arrived.all() and res.yields > 0
    stuck = simulate_fleet(ctrls, starts, CORRIDOR, radius=0.2, t_max=60, yielding=False)
    assert stuck.robot_contacts == 0 and not stuck.arrived[1]


def test_goals_on_arrival_and_a_lone_robot_unchanged(corridor_map) -> None:  # type: ignore[no-untyped-def]
    """A robot with three goals reaches them in order (a new goal on arrival); alone, the
    yield rule changes nothing (its path is the same with and without it)."""
    a, b, c = 1.0 + 2.0j, 6.0 + 2.0j, 2.0 + 3.0j
    first = Controller(corridor_map, b)
    rest = [Controller(corridor_map, c), Controller(corridor_map, b)]
    kw = {"radius": 0.2, "t_max": 80.0, "record_paths": True}
    res = simulate_fleet([first], [a], CORRIDOR, next_goals=[rest], **kw)  # type: ignore[arg-type]
    assert res.goals == 3 and res.reached is not None and res.reached.tolist() == [3]
    assert res.arrived.all() and res.final is not None
    assert abs(res.final[0] - b) <= first.goal_tol + 0.5 * 0.05  # one step at most past it
    assert res.paths is not None
    assert np.abs(res.paths[:, 0] - c).min() <= 0.05  # it went back to c on the way
    off = simulate_fleet([first], [a], CORRIDOR, next_goals=[rest], yielding=False, **kw)  # type: ignore[arg-type]
    assert np.array_equal(res.paths, off.paths)


def test_side_pass_fades_near_walls_and_picks_the_free_side() -> None:
    rows = pairwise_rows([0j, 0.7], 0.2, 0.5)
    u = side_pass([0.5 + 0j, -0.5 + 0j], rows, clearance=[0.3, 0.05])
    assert u[0].imag < 0  # 0.3 m off the walls: the full turn to the right
    assert u[1] == -0.5  # 0.05 m off a wall: no turn (the hold cap would freeze it)
    half = side_pass([0.5 + 0j, -0.5 + 0j], rows, blocked=[True, False], clearance=[0.175, 1])
    assert np.angle(half[0]) == pytest.approx(-np.pi / 4)  # halfway in the band: half of 90
    # blocked, the nearest neighbour clearly to the right (bearing -45 deg): turn left
    rows = pairwise_rows([0j, 0.5 - 0.5j], 0.2, 0.5)
    u = side_pass([0.5 + 0j, 0j], rows, blocked=[True, False])
    assert u[0] == pytest.approx(0.5j)
    # straight ahead (a head-on pair): both to the right, as before
    rows = pairwise_rows([0j, 0.6], 0.2, 0.5)
    u = side_pass([0.5 + 0j, -0.5 + 0j], rows, blocked=[True, True])
    assert u[0] == pytest.approx(-0.5j) and u[1] == pytest.approx(0.5j)


def test_deadlock_monitor_lets_a_robot_close_in_on_its_goal() -> None:
    rows = pairwise_rows([0j, 0.5], 0.2, 0.5)  # engaged: gap 0.1
    one = Rows(rows.a[:1], rows.b[:1], rows.who[:1], rows.gap[:1])
    closing, still = DeadlockMonitor(1), DeadlockMonitor(1)
    hit_closing = hit_still = False
    for k in range(60):  # 0.3 m from the goal, the law's exponential approach (gain 1)
        t = 0.05 * k
        hit_closing |= bool(closing.update(t, [0.3 * np.exp(-t)], one)[0])
        hit_still |= bool(still.update(t, [0.3], one)[0])
    assert not hit_closing and hit_still
