"""The safety layer on exact geometry (confnav.navigation.safety; docs/NAVIGATION.md "Safety
layer").

Exact answers: the projection against closed-form cases (one half-plane, a corner, a line and
the speed circle, infeasible rows) and random problems against the KKT conditions (multipliers
from scipy's non-negative least squares: sufficient for optimality of a convex problem); the wall
rows against hand-computed geometry in a square room; the pruned filter against the projection
with every wall segment's row.  Simulations: a deliberately wrong map collides without the
filter and never with it; an accurate map's commands are left alone on nearly every step and
bitwise where the filter is inactive.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from conftest import IdentityMap
from scipy.optimize import nnls

import confnav
from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.navigation.control import Controller, Status
from confnav.navigation.safety import SafetyFilter, project
from confnav.navigation.sim import simulate
from confnav.navigation.unicycle import UnicycleController, look_ahead_point, twist_from_velocity
from confnav.scenes.scenarios import random_starts
from confnav.scenes.workspaces import default_workspace

S2 = math.sqrt(0.5)


def _one(u: complex, normals: list[complex], bounds: list[float], cap: float | None = None) -> Any:
    return project(
        np.array([u]),
        np.array([normals], dtype=complex).reshape(1, -1),
        np.array([bounds], dtype=float).reshape(1, -1),
        None if cap is None else np.array([cap]),
    )


# ------------------------------------------------------------------ projection, closed form
def test_one_half_plane() -> None:
    # 2 y >= -1 (a non-unit normal): the projection of 1 - 2i is 1 - 0.5i
    p = _one(1 - 2j, [2j], [-1.0])
    assert p.u[0] == pytest.approx(1 - 0.5j, abs=1e-15)
    assert p.changed[0] and not p.infeasible[0]


def test_two_half_planes_at_a_corner() -> None:
    # x >= 0.2, y >= 0.1: the corner
    assert _one(-1 - 1j, [1, 1j], [0.2, 0.1]).u[0] == pytest.approx(0.2 + 0.1j, abs=1e-15)
    # y >= 0 and y >= x (an obtuse wedge): an edge point, then the vertex 0
    rows: list[complex] = [1j, -1 + 1j]
    assert _one(2 - 0.5j, rows, [0, 0]).u[0] == pytest.approx(0.75 + 0.75j, abs=1e-15)
    p = _one(0.5 - 2j, rows, [0, 0])
    assert abs(p.u[0]) <= 1e-15 and p.changed[0]


def test_line_and_speed_circle() -> None:
    assert _one(3 + 4j, [], [], cap=1.0).u[0] == pytest.approx(0.6 + 0.8j, abs=1e-15)
    # x >= 0.6 and |u| <= 1 from 2i: the line meets the circle at 0.6 + 0.8i
    assert _one(2j, [1], [0.6], cap=1.0).u[0] == pytest.approx(0.6 + 0.8j, abs=1e-15)


def test_infeasible_rows_give_zero_and_a_flag() -> None:
    p = _one(0.3 + 0.1j, [1, -1], [1.0, 1.0])  # x >= 1 and x <= -1
    assert p.infeasible[0] and p.u[0] == 0 and p.changed[0]
    p = _one(0.3j, [1], [1.0], cap=0.5)  # x >= 1 but |u| <= 0.5
    assert p.infeasible[0] and p.u[0] == 0


def test_feasible_commands_are_kept_bitwise_and_nan_passes() -> None:
    rng = np.random.default_rng(0)
    u = rng.normal(size=50) + 1j * rng.normal(size=50)
    a = np.exp(2j * np.pi * rng.random((50, 3)))
    b = (np.conj(a) * u[:, None]).real - rng.random((50, 3))  # every row slack
    b[:, 2] = -np.inf  # padding
    p = project(u, a, b, np.abs(u) + 0.1)
    assert np.array_equal(p.u, u) and not p.changed.any() and not p.infeasible.any()
    q = project(np.array([np.nan + 0j]), np.array([[1 + 0j]]), np.array([[0.0]]))
    assert np.isnan(q.u[0]) and not q.changed[0] and not q.infeasible[0]


def test_extra_rows_are_appended_rows() -> None:
    rng = np.random.default_rng(1)
    n = 40
    u = rng.normal(size=n) + 1j * rng.normal(size=n)
    a = np.exp(2j * np.pi * rng.random((n, 5)))
    b = -rng.random((n, 5))
    cap = rng.uniform(0.2, 2.0, n)
    whole = project(u, a, b, cap)
    split = project(u, a[:, :2], b[:, :2], cap, extra_normals=a[:, 2:], extra_bounds=b[:, 2:])
    assert np.array_equal(whole.u, split.u)
    with pytest.raises(NavigationError):
        project(u, a, b, extra_normals=a)


def test_projection_meets_the_kkt_conditions() -> None:
    rng = np.random.default_rng(2)
    n = 60
    m = 5
    u = 2 * (rng.normal(size=n) + 1j * rng.normal(size=n))
    a = np.exp(2j * np.pi * rng.random((n, m))) * rng.uniform(0.5, 2, (n, m))
    b = -rng.uniform(0, 1, (n, m))  # 0 feasible: every problem has a solution
    b[rng.random((n, m)) < 0.3] = -np.inf
    cap = rng.uniform(0.1, 1.5, n)
    p = project(u, a, b, cap)
    slack = (np.conj(a) * p.u[:, None]).real - b
    assert slack.min() >= -1e-12 and np.all(np.abs(p.u) <= cap * (1 + 1e-12))  # feasible
    for i in range(n):  # KKT: 2 (u - u0) = sum l_j a_j - 2 mu u, l, mu >= 0 on active rows
        x = p.u[i]
        act = np.flatnonzero(np.isfinite(b[i]) & (slack[i] <= 1e-9))
        cols = [a[i, j] for j in act]
        if abs(x) >= cap[i] * (1 - 1e-9):
            cols.append(-2 * x)
        target = 2 * (x - u[i])
        if not cols:
            assert abs(target) <= 1e-12, i  # unconstrained: u0 itself
            continue
        mat = np.array([[c.real for c in cols], [c.imag for c in cols]])
        _, resid = nnls(mat, np.array([target.real, target.imag]))
        assert resid <= 1e-9 * max(1.0, abs(target)), i
    assert not p.infeasible.any()


# ------------------------------------------------------------------ wall rows
@pytest.fixture(scope="module")
def room() -> Workspace:
    """A 4 x 4 m room with a 1 x 1 m box at (1..2, 1..2)."""
    return Workspace([(0, 0), (4, 0), (4, 4), (0, 4)], [[(1, 1), (2, 1), (2, 2), (1, 2)]])


def _live(r: Any) -> list[tuple[complex, float, float]]:
    out = []
    for a, b, d in zip(r.normals[0], r.bounds[0], r.distance[0], strict=True):
        if np.isfinite(b):
            out.append((complex(a), float(b), float(d)))
    return sorted(out, key=lambda x: (x[2], x[0].real, x[0].imag))


def test_wall_rows_in_a_corner(room: Workspace) -> None:
    # alpha 1.5, hold 0.25 s, fraction 0.5: cap = 2 c, rows within kappa c = 4/3 c
    f = SafetyFilter(room, alpha=1.5, margin=0.0)
    r = f.rows(np.array([0.5 + 0.5j]))
    assert r.clearance[0] == pytest.approx(0.5, abs=1e-15)
    assert r.cap[0] == pytest.approx(1.0, abs=1e-15)
    rows = _live(r)  # the two walls; the box corner (0.707 m > 0.667 m) is implied by the cap
    assert len(rows) == 2
    assert {complex(round(x[0].real, 15), round(x[0].imag, 15)) for x in rows} == {1, 1j}
    assert [x[1] for x in rows] == pytest.approx([-0.75, -0.75], abs=1e-15)


def test_a_vertex_gives_one_row(room: Workspace) -> None:
    f = SafetyFilter(room, alpha=1.5, margin=0.0)
    r = f.rows(np.array([0.8 + 0.8j]))  # nearest: the box corner (1, 1)
    d = abs(0.2 + 0.2j)
    assert r.clearance[0] == pytest.approx(d, abs=1e-15)
    rows = _live(r)
    assert len(rows) == 1  # the corner ends one side and starts the next: one row
    assert rows[0][0] == pytest.approx(-S2 - S2 * 1j, abs=1e-15)
    assert rows[0][1] == pytest.approx(-1.5 * d, abs=1e-15)
    r = f.rows(np.array([1.5 + 0.7j]))  # under the box's bottom side
    rows = _live(r)
    assert len(rows) == 1 and rows[0][0] == pytest.approx(-1j, abs=1e-15)
    assert rows[0][2] == pytest.approx(0.3, abs=1e-15)


def test_lookahead_truncation_lowers_the_cap(room: Workspace) -> None:
    f = SafetyFilter(room, alpha=1.5, margin=0.0, lookahead=1.0)
    r = f.rows(np.array([3 + 3j]))  # c = 1: rows would reach 4/3 m > 1 m
    rows = _live(r)
    assert [x[2] for x in rows] == pytest.approx([1.0, 1.0], abs=1e-15)  # right and top walls
    assert r.cap[0] == pytest.approx(1.5, abs=1e-15)  # alpha * lookahead < 2 c
    m = SafetyFilter(room, alpha=1.5, margin=0.1).rows(np.array([0.05 + 2j]))
    live = _live(m)  # within the margin the robot may not approach: bound 0
    assert live[0][1] == 0.0 and live[0][0] == pytest.approx(1, abs=1e-15)


def test_points_outside_get_zero(room: Workspace) -> None:
    f = SafetyFilter(room)
    p = f(np.array([1.5 + 1.5j, 5 + 5j, np.nan + 0j]), np.array([0.1, 0.1, 0.1 + 0j]))
    assert list(p.u[:2]) == [0, 0] and list(p.infeasible) == [True, True, False]
    assert p.u[2] == 0.1  # a NaN pose: not filtered


def test_pruned_rows_equal_every_segments_rows() -> None:
    """The grid, the reach kappa c and the vertex rule drop only rows the cap implies."""
    ws = default_workspace()
    f = SafetyFilter(ws, margin=0.0)
    rng = np.random.default_rng(0)
    z = rng.uniform(-2, 2, 8000) + 1j * rng.uniform(-2, 2, 8000)
    z = z[ws.contains(z)]
    u = 0.5 * np.exp(2j * np.pi * rng.random(z.size))
    got = f(z, u)
    a, b = ws._segments  # type: ignore[attr-defined]
    d = b - a
    t = np.clip(((z[:, None] - a) * np.conj(d)).real / np.abs(d) ** 2, 0, 1)
    p = a + t * d
    dist = np.abs(z[:, None] - p)
    c = ws.clearance(z)
    full = project(u, (z[:, None] - p) / dist, -f.alpha * dist, f.slope * c)
    assert np.abs(got.u - full.u).max() <= 1e-14
    assert got.changed.sum() > z.size / 4  # the test exercises the rows
    slack = (np.conj((z[:, None] - p) / dist) * got.u[:, None]).real + f.alpha * dist
    assert slack.min() >= -1e-14
    assert np.all(np.abs(got.u) <= f.slope * c * (1 + 1e-12))


# ------------------------------------------------------------------ controller, simulations
def _ring_room() -> Workspace:
    """The truth: a square room with a square box; the wrong 'map' below thinks the box is a
    disk of radius 0.15 and the room the unit disk."""
    sq = [(-0.7, -0.7), (0.7, -0.7), (0.7, 0.7), (-0.7, 0.7)]
    return Workspace(sq, [[(-0.3, -0.3), (0.3, -0.3), (0.3, 0.3), (-0.3, 0.3)]])


def _starts(ws: Workspace, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(-0.7, 0.7, 8 * n) + 1j * rng.uniform(-0.7, 0.7, 8 * n)
    return z[ws.clearance(z) > 0.02][:n]


def test_a_wrong_map_never_collides_with_the_filter() -> None:
    truth = _ring_room()
    wrong = IdentityMap([0j], [0.15])  # a plain wrong conformal map: the identity
    z = _starts(truth, 50, 1)
    off = simulate(Controller(wrong, 0.6 + 0j, safety=False), z, clearance=truth.clearance)
    assert off.collided.sum() >= 1  # the setup can fail
    ctl = Controller(wrong, 0.6 + 0j, safety=SafetyFilter(truth))
    on = simulate(ctl, z, clearance=truth.clearance, t_max=100)
    assert on.collided.sum() == 0
    assert on.min_clearance.min() > 0
    assert ctl.safety_counts.changed > 0


@pytest.fixture(scope="module")
def nav_map() -> Any:
    return confnav.solve(default_workspace(), tol=1e-6).for_navigation()


def test_an_accurate_map_is_left_alone(nav_map: Any) -> None:
    ws = nav_map.workspace
    ctl = Controller(nav_map, 1.5 + 1.5j)
    assert ctl.safety is not None and ctl.safety.workspace is ws
    res = simulate(ctl, random_starts(ws, 30, seed=3, margin=0.05))
    assert res.collided.sum() == 0 and res.success.all()
    counts = ctl.safety_counts
    assert counts.commands > 1000
    # nearly never: only where the law heads for a convex corner faster than alpha * distance
    # (0.14% of the evaluations here; bench/bench_safety.py measures it on 1000 starts)
    assert counts.changed <= 0.01 * counts.commands, counts
    # where the filter is inactive the command is the law's, bitwise
    z = random_starts(ws, 400, seed=4, margin=0.002)
    out = ctl(z)
    law = Controller(nav_map, 1.5 + 1.5j, safety=False)(z)
    assert out.filtered is not None and law.filtered is None
    same = ~out.filtered
    assert np.array_equal(out.u[same], law.u[same])
    assert np.array_equal(out.status, law.status)


def test_scalar_and_batch_paths_agree_with_the_filter_acting(nav_map: Any) -> None:
    ws = nav_map.workspace
    moved = [o + 0.05 for o in ws.obstacles]
    truth = Workspace(ws.outer, moved, anchor=ws.anchor)
    ctl = Controller(nav_map, 1.5 + 1.5j, safety=truth)  # the map is off by 5 cm
    z = random_starts(truth, 300, seed=6, margin=0.003)
    z = z[np.isfinite(nav_map.T_and_dT(z)[0])]
    batch = ctl(z)
    law = Controller(nav_map, 1.5 + 1.5j, safety=False)
    law_batch = law(z).u
    assert batch.filtered is not None and batch.filtered.sum() >= 5
    for i in np.flatnonzero(batch.filtered)[:20]:
        one = ctl(z[i : i + 1])
        assert one.filtered is not None and bool(one.filtered[0])
        # the two paths' laws agree to rounding (tests/test_single_robot_path.py), the rows
        # are the same, and a projection onto a convex set is non-expansive
        gap = abs(law(z[i : i + 1]).u[0] - law_batch[i])
        assert abs(one.u[0] - batch.u[i]) <= gap + 1e-15 * abs(batch.u[i]), i
        assert one.status[0] == batch.status[i] and one.saturated[0] == batch.saturated[i]


def test_unicycles_drive_the_filtered_look_ahead_command() -> None:
    truth = _ring_room()
    ctl = Controller(IdentityMap([0j], [0.15]), 0.6 + 0j, safety=SafetyFilter(truth))
    uc = UnicycleController(ctl, 0.05, v_max=0.5, omega_max=2.0)
    z = np.array([-0.45 + 0.02j, -0.5 - 0.35j])
    th = np.array([0.0, 0.3])
    out = uc(z, th)
    ref = ctl(look_ahead_point(z, th, 0.05))
    assert ref.filtered is not None and ref.filtered[0]  # heading into the box's side
    # the twist of the filtered point command, scaled by s <= 1 to the limits (a scaled safe
    # command stays safe: the safe set is convex and holds 0)
    v, omega = twist_from_velocity(ref.u, th, 0.05, 0.5, 2.0)
    assert np.array_equal(out.u, v + 1j * omega)
    assert (out.status != Status.ERROR).all()


def test_safety_option_errors() -> None:
    m = IdentityMap([0j], [0.15])
    with pytest.raises(NavigationError, match="safety=True needs"):
        Controller(m, 0.6 + 0j, safety=True)
    with pytest.raises(NavigationError, match="safety must be"):
        Controller(m, 0.6 + 0j, safety="yes")  # type: ignore[arg-type]
    assert Controller(m, 0.6 + 0j).safety is None  # no workspace: nothing to filter against
    with pytest.raises(NavigationError, match="hold_fraction"):
        SafetyFilter(_ring_room(), hold_fraction=1.0)
