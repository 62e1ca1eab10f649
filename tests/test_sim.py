"""Batch simulator: exact trajectories, collision detection, stalls, the seed's four starts."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose

from confnav.errors import NavigationError
from confnav.navigation.control import Controller, Status
from confnav.navigation.navfn import CircleDomain
from confnav.navigation.sim import COLLIDED, STALLED, simulate

DISK = CircleDomain(np.zeros(0, complex), np.zeros(0))
CLUTTER = CircleDomain(
    np.array([0.438 + 0.281j, 0.218 + 0.791j, -0.024 - 0.464j, 0.191 - 0.348j, 0.299 - 0.635j,
              0.535 - 0.512j, -0.616 + 0.484j, -0.126 + 0.783j]),
    np.array([0.093, 0.09, 0.098, 0.093, 0.074, 0.048, 0.078, 0.085]),
)  # fmt: skip


class IdentityMap:
    def __init__(self, dom: CircleDomain) -> None:
        self.centers, self.radii, self.workspace = dom.centers, dom.radii, dom

    def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
        z = np.asarray(z, dtype=complex)
        out = ~(self.workspace.clearance(z) >= 0)
        return np.where(out, np.nan, z), np.where(out, np.nan, 1.0 + 0j)


class ConstantField:
    def __init__(self, u: complex, dom: CircleDomain) -> None:
        self.u, self.goal, self.goal_tol, self.workspace = u, 10.0 + 0j, 1e-3, dom

    def velocity(self, z: Any) -> np.ndarray:
        return np.full(np.shape(z), self.u, dtype=complex)


def test_exact_exponential_approach() -> None:
    # harmonic phi on the disk with goal 0 is |w|^2: u = -2K z, z(t) = z0 exp(-2Kt)
    gain, tol = 0.7, 1e-3
    ctl = Controller(
        IdentityMap(DISK),
        0j,
        navfn="harmonic",
        speed_law="theorem2",
        gain=gain,
        v_max=np.inf,
        goal_tol=tol,
        hold_time=0,  # the law alone (the held-command cap slows it near the wall)
    )
    z0 = np.array([0.9, -0.5 + 0.5j, 0.01j, 0.3 - 0.8j])
    res = simulate(ctl, z0, atol=1e-8)
    assert res.success.all()
    # arrival time from the cubic Hermite interpolant of the last step: ~1e-5 relative
    assert_allclose(res.time, np.log(np.abs(z0) / tol) / (2 * gain), rtol=1e-4)
    assert_allclose(res.path_length, np.abs(z0) - tol, rtol=1e-9)
    assert_allclose(res.final_distance, tol, rtol=1e-9)
    assert_allclose(res.max_speed, 2 * gain * np.abs(z0), rtol=1e-12)
    assert_allclose(res.min_clearance, 1 - np.abs(z0), rtol=1e-12)
    assert (res.starts == z0).all()


def test_normalized_law_exact_arrival_time() -> None:
    # radial paths on the disk; speed v_max until d = v_max/gain, then d' = -gain d:
    # t = (d0 - v/g)/v + log((v/g)/tol)/g for d0 > v/g, log(d0/tol)/g otherwise
    v, g, tol = 0.5, 2.0, 1e-3
    ctl = Controller(
        IdentityMap(DISK), 0j, navfn="harmonic", gain=g, v_max=v, goal_tol=tol, hold_time=0
    )
    z0 = np.array([0.9, -0.5 + 0.5j, 0.1j, 0.3 - 0.8j])
    d0 = np.abs(z0)
    res = simulate(ctl, z0, atol=1e-9)
    assert res.success.all()
    knee = v / g
    exact = np.where(d0 > knee, (d0 - knee) / v + np.log(knee / tol) / g, np.log(d0 / tol) / g)
    assert_allclose(res.time, exact, rtol=1e-4)
    assert_allclose(res.path_length, d0 - tol, rtol=1e-9)
    assert_allclose(res.max_speed, np.minimum(v, g * d0), rtol=1e-12)


def test_kr_paths_are_radial_on_the_disk() -> None:
    ctl = Controller(IdentityMap(DISK), 0j, navfn="kr", k=6, goal_tol=1e-3)
    z0 = np.array([0.95 + 0j, 0.6 - 0.7j])
    res = simulate(ctl, z0, record_paths=True)
    assert res.success.all()
    assert_allclose(res.path_length, np.abs(z0) - 1e-3, rtol=1e-9)
    for p, s in zip(res.paths or (), z0, strict=True):
        assert_allclose(np.angle(p / s), 0, atol=1e-12)


def test_collision_between_accepted_points_is_caught() -> None:
    # a thin disk on a straight line crossed with steps of 0.5: only the chord check sees it
    dom = CircleDomain(np.array([0.0j]), np.array([0.01]))
    res = simulate(ConstantField(1.0 + 0j, dom), [-0.9 + 0.005j], max_step=0.5, record_paths=True)
    assert res.collided[0] and not res.success[0]
    assert res.status[0] == COLLIDED
    assert res.min_clearance[0] <= 0
    path = (res.paths or ())[0]
    assert np.all(dom.clearance(path) > 0)  # no accepted point is inside: the chord check saw it
    assert path[-2].real < 0 < path[-1].real  # stopped on the step that crossed the disk
    # just missing it is not a collision
    res = simulate(ConstantField(1.0 + 0j, dom), [-0.9 + 0.0101j], max_step=0.5, t_max=1.7)
    assert not res.collided[0]
    assert 1e-4 - 1e-12 <= res.min_clearance[0] <= 1.01e-4  # true minimum: 1e-4 at x = 0


def test_k6_stalls_in_clutter_and_auto_k_does_not() -> None:
    ident = IdentityMap(CLUTTER)
    rng = np.random.default_rng(5)
    z = rng.uniform(-1, 1, 3000) + 1j * rng.uniform(-1, 1, 3000)
    z = z[CLUTTER.clearance(z) > 0.01][:300]
    bad = simulate(Controller(ident, 0j, navfn="kr", k=6), z, t_max=1e3)
    assert not bad.collided.any()
    assert (~bad.success).sum() > 0
    stuck = bad.final[~bad.success]
    from confnav.navigation.critical import find_critical_points
    from confnav.navigation.navfn import KoditschekRimon

    spurious = find_critical_points(KoditschekRimon(CLUTTER, 0j, 6)).spurious_minima
    assert spurious.size == 1
    assert np.all(np.abs(stuck - spurious[0]) < 1e-3)  # they all sit in the spurious minimum
    assert np.all(bad.status[~bad.success] == STALLED)
    # classified by the critical point they sit at, not by a small gradient
    runs = bad.runs()
    assert all("critical point" in runs[i].reason for i in np.flatnonzero(~bad.success))
    k6 = Controller(ident, 0j, navfn="kr", k=6)
    k6.critical_points()
    assert np.all(k6(stuck).status == Status.STALLED)
    good = simulate(Controller(ident, 0j, navfn="kr", k="auto"), z, t_max=1e5)
    assert good.success.all(), good.message
    harm = simulate(Controller(ident, 0j, navfn="harmonic"), z, t_max=1e3)
    assert harm.success.all(), harm.message


def test_flat_is_not_stalled(alcove_map: Any) -> None:
    # goal at the end of a 0.5 x 1.5 m alcove: in the room 1 - phi ~ 1e-5 and the Theorem 2
    # field is ~5e-5 m/s (a crawl), yet with the defaults the robots are MOVING at v_max and
    # arrive; the plain law makes no progress and is classified as such, not as a saddle
    starts = np.array([0.3 + 0.3j, 2.7 + 0.3j, 0.3 + 1.7j])
    ctl = Controller(alcove_map, ALCOVE_GOAL)
    plain = Controller(alcove_map, ALCOVE_GOAL, speed_law="theorem2")
    assert np.all(np.abs(plain.velocity(starts)) < 1e-4)
    out = ctl(starts)
    assert np.all(out.status == Status.MOVING)
    assert_allclose(np.abs(out.u), ctl.v_max, rtol=1e-12)
    res = simulate(ctl, starts)
    assert res.success.all() and not res.collided.any(), res.message
    assert np.all(res.time < 15.0)
    crawl = simulate(plain, starts, t_max=100.0)
    assert np.all(crawl.status == STALLED)
    assert all(r.reason.startswith("no progress") for r in crawl.runs())


@pytest.mark.slow
def test_goal_in_a_pocket_is_reached_from_far_starts_with_the_defaults(cup_map: Any) -> None:
    from confnav.scenes.scenarios import random_starts

    starts = np.r_[np.array([1.8 + 0j, 1.8 + 1.8j, -1.8 - 1.8j, 0.0 + 1.5j]),
                   random_starts(cup_map.workspace, 40, seed=11)]  # fmt: skip
    for navfn in ("harmonic", "kr"):
        ctl = Controller(cup_map, CUP_GOAL, navfn=navfn)
        res = simulate(ctl, starts)
        assert res.success.all() and not res.collided.any(), (navfn, res.message)
        assert np.all(res.time < 60.0)  # a few metres at 0.5 m/s, not a crawl


def test_bad_starts() -> None:
    ctl = Controller(IdentityMap(DISK), 0j, navfn="harmonic")
    with pytest.raises(NavigationError, match="finite"):
        simulate(ctl, [np.nan + 0j])
    with pytest.raises(NavigationError, match="free space"):
        simulate(ctl, [(0.2, 0.1), (1.5, 0.0)])
    res = simulate(ctl, [(0.2, 0.1)])  # (N, 2) real input
    assert res.starts[0] == 0.2 + 0.1j and res.success[0]


def test_runs_are_typed_records() -> None:
    ctl = Controller(IdentityMap(DISK), 0j, navfn="harmonic")
    res = simulate(ctl, [0.5 + 0j, 0.0005 + 0j])
    r0, r1 = res.runs()
    assert r0.success and r0.status == "arrived" and r0.n_steps > 0
    assert r1.success and r1.time == 0.0 and r1.n_steps == 0  # already there
    d = r0.to_dict()
    assert d["start"] == [0.5, 0.0] and set(d) >= {"success", "collided", "time", "path_length"}
    assert "2 arrived" in res.message and res.success_rate == 1.0


def _default_map() -> Any:
    import confnav
    from confnav.scenes.workspaces import default_workspace

    return confnav.solve(default_workspace())


@pytest.fixture(scope="module")
def default_map() -> Any:
    return _default_map()


ALCOVE_GOAL = 1.75 + 3.2j  # 0.3 m from the end of a 0.5 m wide, 1.5 m deep alcove


@pytest.fixture(scope="module")
def alcove_map() -> Any:
    import warnings

    import confnav
    from confnav.geometry import Workspace

    ws = Workspace([(0, 0), (3, 0), (3, 2), (2, 2), (2, 3.5), (1.5, 3.5), (1.5, 2), (0, 2)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # accuracy 3e-9 at the re-entrant corners: plenty
        return confnav.solve(ws).for_navigation()


CUP_GOAL = 0.2 + 0.0j  # 0.15 m from the bottom of a 0.8 x 0.8 cup that opens away from it


@pytest.fixture(scope="module")
def cup_map() -> Any:
    import confnav
    from confnav.scenes.scenarios import cup_trap

    return confnav.solve(cup_trap(0.8).workspace).for_navigation()


@pytest.mark.parametrize("navfn", ["kr", "harmonic"])
def test_seed_four_starts_reach_the_goal(default_map: Any, navfn: str) -> None:
    from confnav.scenes.workspaces import DEFAULT_GOAL, DEFAULT_STARTS

    ctl = Controller(default_map, DEFAULT_GOAL, navfn=navfn, k=6, gain=1.0)
    res = simulate(ctl, np.array(DEFAULT_STARTS), t_max=1e6)
    assert res.success.all(), res.message
    assert not res.collided.any()
    assert np.all(res.min_clearance > 0)
    # never faster than the straight line
    assert np.all(res.path_length >= np.abs(np.array(DEFAULT_STARTS) - DEFAULT_GOAL) - 1e-3)


def test_shortest_path_around_a_square() -> None:
    from confnav.geometry import Workspace
    from confnav.navigation.shortest_path import ShortestPaths, bend_vertices

    sq = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]
    ws = Workspace([(-2, -2), (2, -2), (2, 2), (-2, 2)], [sq])
    assert set(bend_vertices(ws)) == {complex(x, y) for x, y in sq}  # outer square: convex
    sp = ShortestPaths(ws, -1.0 + 0j)
    got = sp.lengths([1.0 + 0j, -1.5 + 1j, 0.0 + 0.6j, 1.0 + 0.5j])
    exact = [
        1 + np.sqrt(2),  # around two corners
        np.sqrt(1.25),  # direct
        np.sqrt(0.26) + np.sqrt(0.5),  # direct line cut by the square: via (-0.5, 0.5)
        1.5 + np.sqrt(0.5),  # along the top edge
    ]
    assert_allclose(got, exact, rtol=1e-12)


def test_path_ratio_is_against_the_goal_disk_and_never_below_one() -> None:
    from confnav.navigation.shortest_path import path_ratio

    # a straight 0.1 m trip that stops at the 0.02 m goal disk: 0.08 m driven, ratio exactly 1
    # (against the goal itself it read 0.8); a start inside the disk has no ratio
    got = path_ratio([0.08, 0.3, 0.0], [0.1, 0.2, 0.01], 0.02)
    assert_allclose(got[:2], [1.0, 0.3 / 0.18], rtol=1e-12)
    assert np.isnan(got[2])


def test_potential_field_gets_trapped_in_the_cup() -> None:
    from confnav.navigation.baseline import PotentialField
    from confnav.scenes.scenarios import cup_trap

    sc = cup_trap(1.2)
    apf = PotentialField(sc.workspace, sc.goal)
    # straight behind the cup's bottom, on the axis: the attractive pull is cancelled
    res = simulate(apf, [-1.8 + 0.0j, 1.0 + 1.5j])
    assert res.status[0] == STALLED and not res.collided[0]
    assert res.final[0].real < 0.7  # stuck inside or at the mouth of the cup
    assert res.success[1]


def test_scenarios_are_valid_and_random_starts_keep_the_margin() -> None:
    from confnav.scenes.scenarios import (
        cup_trap,
        default_scenario,
        l_room,
        random_starts,
        spiral_corridor,
    )

    for sc in (default_scenario(), cup_trap(0.4), l_room(), spiral_corridor(10)):
        assert sc.workspace.contains(sc.goal)
        z = random_starts(sc.workspace, 200, seed=3)
        assert z.size == 200 and np.all(sc.workspace.clearance(z) >= 0.05)
        assert_allclose(z, random_starts(sc.workspace, 200, seed=3))
    # the corridor's centreline length over width
    sc = spiral_corridor(10, width=0.4)
    assert_allclose(sc.workspace.polygon.area, 10 * 0.4**2, rtol=0.05)


def test_harmonic_on_the_default_map(default_map: Any) -> None:
    from confnav.navigation.critical import find_critical_points
    from confnav.scenes.workspaces import DEFAULT_GOAL

    ctl = Controller(default_map, DEFAULT_GOAL, navfn="harmonic")
    cp = find_critical_points(ctl.navfn)
    assert cp.ok and cp.index_consistent, cp.message
    assert cp.saddles.size == default_map.radii.size == 4
    # phi o T -> 1 at the polygons: at 1e-3 from every edge midpoint, 1 - V <= |grad V| 1e-3
    # (|grad V| < 20 at these points); not closer: the map's T' loses accuracy within ~1e-4
    ws = default_map.workspace
    for j, p in enumerate(ws.boundaries):
        mid = 0.5 * (p + np.roll(p, -1))
        normal = 1j * (np.roll(p, -1) - p) / np.abs(np.roll(p, -1) - p)  # left of a ccw edge
        pts = mid + (1e-3 if j == 0 else -1e-3) * normal  # into the free space
        assert_allclose(ws.clearance(pts), 1e-3, rtol=1e-6)
        v = ctl.lyapunov(pts)
        assert np.all((v < 1) & (v > 1 - 2e-2))


def test_goal_change_needs_no_solve(default_map: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    import confnav
    import confnav.conformal.solver
    from confnav.scenes.workspaces import DEFAULT_STARTS

    def no_solve(*a: Any, **k: Any) -> Any:
        raise AssertionError("a goal change must not solve")

    monkeypatch.setattr(confnav, "solve", no_solve)
    monkeypatch.setattr(confnav.conformal.solver, "solve", no_solve)
    ctl = Controller(default_map, 0j, navfn="kr", k=6)
    for goal in (1.5 - 1.5j, -1.5 + 1.5j):
        new = ctl.with_goal(goal)
        assert new.cmap is default_map and new.goal == goal
        res = simulate(new, np.array(DEFAULT_STARTS), t_max=1e6)
        assert res.success.all() and not res.collided.any(), res.message
    with pytest.raises(NavigationError):
        ctl.with_goal(0.9 + 0.6j)  # inside the triangle
