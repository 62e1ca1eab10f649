"""Fleets: pairwise barrier rows, their projection, swept-disk contacts, swaps without contact."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest
from scipy.optimize import minimize

from confnav import Controller, Workspace, inflate, solve
from confnav.navigation.fleet import (
    DeadlockMonitor,
    Rows,
    pairwise_rows,
    project_rows,
    side_pass,
    swept_min_distance,
)
from confnav.navigation.fleet_sim import Mover, simulate_fleet

ROOM = Workspace(
    [(0, 0), (10, 0), (10, 8), (0, 8)],
    [
        [(3, 2.5), (4.2, 2.5), (4.2, 3.7), (3, 3.7)],
        [(6, 4.5), (7.2, 4.5), (7.2, 5.7), (6, 5.7)],
    ],
)


@pytest.fixture(scope="module")
def room_map():  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(inflate(ROOM, 0.2), 1e-5)


def test_rows_hand_computed_reciprocal_pair() -> None:
    # centres 0.8 apart, radii 0.2: gap 0.4; alpha = 0.5 / 0.25 = 2; each takes half: b = -0.4
    rows = pairwise_rows([0, 0.8], 0.2, 0.5, hold_time=0.25, fraction=0.5)
    assert rows.a.shape == (2, 1)
    assert rows.a[0, 0] == pytest.approx(-1.0) and rows.a[1, 0] == pytest.approx(1.0)
    assert rows.b[:, 0] == pytest.approx([-0.4, -0.4])
    assert rows.gap[:, 0] == pytest.approx([0.4, 0.4])
    assert rows.who[:, 0].tolist() == [1, 0]


def test_rows_far_pair_gives_no_row() -> None:
    # gap 0.6: b = -0.6 < -v_max: the speed limit already meets the row, so none is made
    rows = pairwise_rows([0, 1.0], 0.2, 0.5, hold_time=0.25, fraction=0.5)
    assert rows.count.tolist() == [0, 0]


def test_rows_mover_full_responsibility_with_its_velocity() -> None:
    # mover at 1 (r 0.3) coming at 1 m/s toward the robot at 0 (r 0.2): gap 0.5, n = -1,
    # b = -alpha h + Re(conj(n) v) = -1 + 1 = 0: the robot may not approach at all
    rows = pairwise_rows([0j], 0.2, 0.5, others=[1.0], others_radius=[0.3], others_velocity=[-1.0])
    assert rows.a[0, 0] == pytest.approx(-1.0)
    assert rows.b[0, 0] == pytest.approx(0.0)
    assert rows.who[0, 0] == 1
    # a cooperative other robot: half, no velocity term
    rows = pairwise_rows(
        [0j], 0.2, 0.5, others=[0.8], others_radius=[0.2], others_cooperative=[True]
    )
    assert rows.b[0, 0] == pytest.approx(-0.4)


def test_projection_hand_case_and_cap() -> None:
    u, ok = project_rows([0.5 + 0j], [[-1.0 + 0j]], [[-0.4]], [0.5])
    assert ok[0] and u[0] == pytest.approx(0.4)
    # two rows meeting at a corner: Re(u) <= 0.1 and Im(u) >= 0.2, nominal 0.5: corner 0.1+0.2i
    u, ok = project_rows([0.5 + 0j], [[-1.0 + 0j, 1j]], [[-0.1, 0.2]], [1.0])
    assert u[0] == pytest.approx(0.1 + 0.2j)
    # the cap binds with a row: |u| <= 0.3 and Im(u) >= 0.2, nominal 1: u = sqrt(0.05) + 0.2i
    u, ok = project_rows([1.0 + 0j], [[1j]], [[0.2]], [0.3])
    assert u[0] == pytest.approx(np.sqrt(0.09 - 0.04) + 0.2j)
    # infeasible (a row asks for 1 m/s away, the cap allows 0.5): least violation, flagged
    u, ok = project_rows([0j], [[1.0 + 0j]], [[1.0]], [0.5])
    assert not ok[0] and u[0] == pytest.approx(0.5)


def test_projection_matches_a_generic_qp_solver() -> None:
    rng = np.random.default_rng(3)
    n, k = 40, 4
    un = rng.normal(size=n) + 1j * rng.normal(size=n)
    a = np.exp(2j * np.pi * rng.random((n, k)))
    b = -rng.random((n, k)) * 0.8  # u = 0 feasible
    cap = 0.5 + rng.random(n)
    u, ok = project_rows(un, a, b, cap)
    assert ok.all()
    for i in range(n):
        cons = [
            {"type": "ineq", "fun": lambda v, q=q, bb=bb: q.real * v[0] + q.imag * v[1] - bb}
            for q, bb in zip(a[i], b[i], strict=True)
        ]
        cons.append({"type": "ineq", "fun": lambda v, c=cap[i]: c * c - v[0] ** 2 - v[1] ** 2})
        ref = minimize(
            lambda v, t=un[i]: (v[0] - t.real) ** 2 + (v[1] - t.imag) ** 2,
            [0.0, 0.0],
            constraints=cons,
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 500},
        )
        assert abs(u[i] - complex(*ref.x)) < 1e-5
        assert np.all(np.real(np.conj(a[i]) * u[i]) >= b[i] - 1e-9)
        assert abs(u[i]) <= cap[i] * (1 + 1e-9)


def test_held_commands_never_bring_two_disks_into_contact() -> None:
    """Any pair of commands meeting their rows, held hold_time: the gap stays >= (1 -
    fraction) of the gap at the start (docs/NAVIGATION.md, "Fleets")."""
    rng = np.random.default_rng(7)
    T, frac = 0.25, 0.5
    for _ in range(200):
        z = rng.random(2) * 1.0 + 1j * rng.random(2) * 1.0
        r = 0.1 + 0.1 * rng.random(2)
        if abs(z[0] - z[1]) <= r.sum():
            continue
        rows = pairwise_rows(z, r, 2.0, hold_time=T, fraction=frac)
        un = 2.0 * np.exp(2j * np.pi * rng.random(2))
        u, ok = project_rows(un, rows.a, rows.b, 2.0)
        assert ok.all()
        dmin, _ = swept_min_distance(z[0], z[0] + u[0] * T, z[1], z[1] + u[1] * T)
        gap0 = abs(z[0] - z[1]) - r.sum()
        assert dmin - r.sum() >= (1 - frac) * gap0 - 1e-12


def test_swept_check_finds_a_pass_through_the_step_ends_miss() -> None:
    # a runs from -1 to 1 in one step past b at 0.05i; radii 0.05: the ends are 1.0 apart,
    # the closest approach is 0.05 at mid-step: contact (0.05 < 0.1)
    dmin, s = swept_min_distance(-1 + 0j, 1 + 0j, 0.05j, 0.05j)
    assert abs(-1 - 0.05j) > 0.1 and abs(1 - 0.05j) > 0.1
    assert dmin == pytest.approx(0.05) and s == pytest.approx(0.5)
    # both moving: a 0 -> 2, b 2i -> 2 + ... crossing; closed form at s* = 1/2
    dmin, s = swept_min_distance(0j, 2 + 0j, 1 + 1j, 1 - 1j)
    assert dmin == pytest.approx(0.0, abs=1e-15) and s == pytest.approx(0.5)


def test_side_pass_turns_right_only_near_a_robot_ahead() -> None:
    rows = pairwise_rows([0j, 0.7], 0.2, 0.5)
    u = side_pass([0.5 + 0j, -0.5 + 0j], rows)
    assert u[0].imag < 0 and u[1].imag > 0  # both to their right
    assert abs(u[0]) == pytest.approx(0.5)
    u_free = side_pass([0.5 + 0j], Rows.empty(1))
    assert u_free[0] == 0.5


def test_deadlock_monitor_flags_no_progress_while_engaged() -> None:
    mon = DeadlockMonitor(2, window=1.0, progress=0.1)
    rows = pairwise_rows([0j, 0.5], 0.2, 0.5)
    first = None
    for k in range(30):
        blocked = mon.update(0.1 * k, [3.0, 3.0], rows)
        if first is None and blocked.any():
            first = k
            assert blocked.all()
    assert first == 11  # the first update more than window = 1 s after the start (t = 1.1)
    one = Rows(rows.a[:1], rows.b[:1], rows.who[:1], rows.gap[:1])
    mon2 = DeadlockMonitor(1, window=1.0)
    for k in range(30):  # progressing: never blocked
        assert not mon2.update(0.1 * k, [3.0 - 0.2 * k], one).any()


@pytest.mark.parametrize("n", [2, 4])
def test_ring_swap_no_contact_and_everyone_arrives(room_map, n: int) -> None:  # type: ignore[no-untyped-def]
    ang = 2 * np.pi * np.arange(n) / n
    starts = 5 + 4j + 3.0 * np.exp(1j * ang)
    goals = 5 + 4j - 3.0 * np.exp(1j * ang)
    ctrls = [Controller(room_map, g) for g in goals]
    res = simulate_fleet(ctrls, starts, ROOM, radius=0.2, t_max=80)
    assert res.robot_contacts == 0 and res.wall_contacts == 0
    assert res.arrived.all()
    assert res.min_gap > 0
    ghosts = simulate_fleet(ctrls, starts, ROOM, radius=0.2, t_max=80, avoid=False)
    assert ghosts.robot_contacts > 0  # the same swap without the filter drives through


def test_person_crossing_a_robots_path(room_map) -> None:  # type: ignore[no-untyped-def]
    ctrl = Controller(room_map, 8.5 + 1.2j)
    # the person walks down x = 5 at 1.2 m/s and, undisturbed, meets the robot (ghost below)
    person = Mover(start=5.0 + 7.6j, end=5.0 + 0.35j, radius=0.3, speed=1.2, t_start=3.25)
    res = simulate_fleet([ctrl], [1.0 + 1.2j], ROOM, radius=0.2, movers=[person], t_max=60)
    assert res.mover_contacts == 0 and res.wall_contacts == 0 and res.arrived.all()
    ghost = simulate_fleet(
        [ctrl], [1.0 + 1.2j], ROOM, radius=0.2, movers=[person], t_max=60, avoid=False
    )
    assert ghost.mover_contacts > 0


def test_unicycles_swap_through_their_look_ahead_disks() -> None:
    """Four unicycles (body 0.2 m around the axle, look-ahead 0.1 m: filter disk 0.3 m around
    the look-ahead point, map of the room shrunk by 0.3): no body touches another or a wall,
    all arrive; ghosts touch."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cmap = solve(inflate(ROOM, 0.3), 1e-5)
    ang = 2 * np.pi * np.arange(4) / 4 + 0.1
    starts = 5 + 4j + 3.0 * np.exp(1j * ang)
    goals = 5 + 4j - 3.0 * np.exp(1j * ang)
    ctrls = [Controller(cmap, g) for g in goals]
    kw: dict[str, Any] = {"radius": 0.2, "lookahead": 0.1, "theta": np.angle(goals - starts)}
    res = simulate_fleet(ctrls, starts, ROOM, t_max=80, **kw)
    assert res.robot_contacts == 0 and res.wall_contacts == 0 and res.arrived.all()
    assert simulate_fleet(ctrls, starts, ROOM, t_max=80, avoid=False, **kw).robot_contacts > 0


def test_robot_in_a_movers_way_leaves_sideways() -> None:
    # a robot on the path of a person 1 m away walking at it (1 m/s): the capsule's nearest
    # point is the robot itself; the row asks it to leave to the right of the person's motion
    rows = pairwise_rows(
        [0j], 0.2, 0.5, others=[1.0], others_radius=[0.3], others_velocity=[-1.0], horizon=2.0
    )
    assert rows.a[0, 0] == pytest.approx(1j)  # person heads -x: its right is +y
    assert rows.b[0, 0] == pytest.approx(2 * 0.5)  # -alpha * gap with gap = -0.5
    u, ok = project_rows([0.5 + 0j], rows.a, rows.b, [0.5])
    assert not ok[0] and u[0] == pytest.approx(0.5j)  # as fast as it can, sideways


def test_points_are_not_bodies_but_avoid_movers() -> None:
    # a point robot next to a disk robot: no rows either way (points drive as before)
    rows = pairwise_rows([0j, 0.3], [0.0, 0.2], 0.5)
    assert rows.count.tolist() == [0, 0]
    # the same point next to a mover of radius 0.2: it keeps out of the mover's disk
    rows = pairwise_rows([0j], 0.0, 0.5, others=[0.3], others_radius=[0.2], others_mover=[True])
    assert rows.count.tolist() == [1] and rows.gap[0, 0] == pytest.approx(0.1)
