"""Theorem 2 control law and the normalized speed law against exact maps (Mobius self-maps and
the identity of a circle domain): same paths, speed profile, saturation, status codes (flat is
not stalled), goal changes, bad input, defaults shared with the Goal message."""

from __future__ import annotations

import inspect
from concurrent.futures import CancelledError
from typing import Any

import numpy as np
import pytest
from confnav.schemas import Goal
from confnav.services.critical_search import CriticalSearchWorker
from numpy.testing import assert_allclose

from confnav.errors import NavigationError
from confnav.navigation import defaults
from confnav.navigation.control import Controller, Status, speed_law
from confnav.navigation.critical import find_critical_points
from confnav.navigation.navfn import CircleDomain
from confnav.navigation.sim import simulate

SEED = CircleDomain(
    np.array([0.4227371 + 0.2466153j, -0.4018952 + 0.2782662j, -0.4826272 - 0.3720324j,
              0.0160941 - 0.3776479j]),
    np.array([0.1420658, 0.1593344, 0.1413721, 0.2170942]),
)  # fmt: skip


def _circumcircle(p: np.ndarray) -> tuple[complex, float]:
    a, b, c = p
    d = 2 * (a.real * (b.imag - c.imag) + b.real * (c.imag - a.imag) + c.real * (a.imag - b.imag))
    sa, sb, sc = abs(a) ** 2, abs(b) ** 2, abs(c) ** 2
    ux = (sa * (b.imag - c.imag) + sb * (c.imag - a.imag) + sc * (a.imag - b.imag)) / d
    uy = (sa * (c.real - b.real) + sb * (a.real - c.real) + sc * (b.real - a.real)) / d
    return complex(ux, uy), float(abs(a - complex(ux, uy)))


class MobiusMap:
    """Exact conformal map T(z) = (z - a)/(1 - conj(a) z) of the circle domain ``src`` (the
    'workspace') onto another circle domain; ``workspace`` gives clearance/contains."""

    def __init__(self, src: CircleDomain, a: complex) -> None:
        self.src, self.a = src, a
        cr = [
            _circumcircle(self._t(c + r * np.exp(2j * np.pi * np.array([0, 1 / 3, 2 / 3]))))
            for c, r in zip(src.centers, src.radii, strict=True)
        ]
        self.centers = np.array([c for c, _ in cr])
        self.radii = np.array([r for _, r in cr])
        self.workspace = src
        self.calls = 0

    def _t(self, z: Any) -> Any:
        return (z - self.a) / (1 - np.conj(self.a) * z)

    def inverse(self, w: Any) -> Any:
        return (w + self.a) / (1 + np.conj(self.a) * w)

    def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
        self.calls += 1
        z = np.asarray(z, dtype=complex)
        out = ~(self.src.clearance(z) >= 0)
        w = self._t(z)
        dw = (1 - abs(self.a) ** 2) / (1 - np.conj(self.a) * z) ** 2
        return np.where(out, np.nan, w), np.where(out, np.nan, dw)


class IdentityMap:
    def __init__(self, dom: CircleDomain) -> None:
        self.centers, self.radii, self.workspace = dom.centers, dom.radii, dom

    def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
        z = np.asarray(z, dtype=complex)
        out = ~(self.workspace.clearance(z) >= 0)
        return np.where(out, np.nan, z), np.where(out, np.nan, 1.0 + 0j)


MOB = MobiusMap(SEED, 0.2 - 0.1j)


def interior_points(dom: CircleDomain, n: int, margin: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1, 1, 8 * n) + 1j * rng.uniform(-1, 1, 8 * n)
    return w[dom.clearance(w) > margin][:n]


@pytest.mark.parametrize("navfn", ["kr", "harmonic"])
def test_law_is_minus_gradient_of_pulled_back_lyapunov(navfn: str) -> None:
    ctl = Controller(
        MOB, 0.1j, navfn=navfn, k=6, speed_law="theorem2", gain=2.5, v_max=np.inf, hold_time=0
    )  # the bare law (no cap for held commands)
    z = interior_points(SEED, 200, 1e-3)
    u = ctl.velocity(z)
    v = ctl.lyapunov
    h = 1e-6
    grad_v = (v(z + h) - v(z - h)) / (2 * h) + 1j * (v(z + 1j * h) - v(z - 1j * h)) / (2 * h)
    assert_allclose(u, -2.5 * grad_v, rtol=1e-5, atol=1e-9 * np.max(np.abs(u)))


def test_identity_map_gives_the_plain_gradient() -> None:
    ctl = Controller(
        IdentityMap(SEED), 0.2j, navfn="kr", k=6, speed_law="theorem2", v_max=np.inf, hold_time=0
    )
    z = interior_points(SEED, 50, 1e-3)
    assert_allclose(ctl.velocity(z), -ctl.navfn.gradient(z), rtol=1e-14)


def test_saturation_keeps_direction_and_bound() -> None:
    free = Controller(MOB, 0.1j, navfn="harmonic", speed_law="theorem2", gain=3.0, v_max=np.inf)
    sat = Controller(MOB, 0.1j, navfn=free.navfn, speed_law="theorem2", gain=3.0, v_max=0.05)
    z = interior_points(SEED, 300, 1e-3)
    u0, out = free.velocity(z), sat(z)
    assert np.all(np.abs(out.u) <= 0.05 * (1 + 1e-12))
    big = np.abs(u0) > 0.05
    assert big.any() and (~big).any()
    assert_allclose(np.angle(out.u[big] / u0[big]), 0, atol=1e-12)
    assert_allclose(out.u[~big], u0[~big], rtol=1e-14)
    assert np.array_equal(out.saturated, big)


def test_saturated_law_decreases_lyapunov_along_paths() -> None:
    ctl = Controller(MOB, 0.1j, navfn="kr", k=6, speed_law="theorem2", v_max=0.02)
    starts = interior_points(SEED, 20, 0.05, seed=2)
    res = simulate(ctl, starts, record_paths=True, atol=1e-7)
    assert res.success.all(), res.message
    assert np.all(res.max_speed <= 0.02 * (1 + 1e-9))
    for p in res.paths or ():
        v = ctl.lyapunov(p)
        assert np.all(np.diff(v) < 0)


def test_status_codes() -> None:
    ctl = Controller(MOB, 0.1j, navfn="kr", k=6, goal_tol=1e-3)
    cp = find_critical_points(ctl.navfn)
    saddle_ws = MOB.inverse(cp.saddles[0])  # workspace point of a saddle
    z = np.array([0.1j + 5e-4, 0.5 + 0j, np.nan, 0.99 + 0.5j, saddle_ws, SEED.centers[0]])
    # the critical points are not searched on the control path: unknown saddle -> MOVING
    assert ctl(saddle_ws).status == Status.MOVING
    ctl.critical_points()
    out = ctl(z)
    assert list(out.status) == [
        Status.ARRIVED,
        Status.MOVING,
        Status.ERROR,
        Status.ERROR,
        Status.STALLED,
        Status.ERROR,
    ]
    assert out.u[0] == 0 and out.u[2] == 0 and out.u[3] == 0
    assert np.isnan(out.phi[2]) and np.isfinite(out.phi[1])
    assert out.u.shape == z.shape and ctl(0.5 + 0j).u.shape == ()


def test_background_search_makes_the_saddle_stall_without_blocking() -> None:
    ctl = Controller(MOB, 0.1j, navfn="kr", k=6, goal_tol=1e-3)
    saddle_ws = MOB.inverse(find_critical_points(ctl.navfn).saddles[0])
    worker = CriticalSearchWorker()
    fut = ctl.search_critical_points(worker)
    assert ctl.search_critical_points(worker) is fut  # once per controller
    cp = fut.result(timeout=60)
    assert cp.ok and cp.saddles.size == SEED.n_obstacles
    assert ctl(saddle_ws).status == Status.STALLED
    assert ctl(0.5 + 0j).status == Status.MOVING


def test_background_search_skips_controllers_nobody_holds() -> None:
    """A robot's goal replaced before its search began: the search is cancelled, not run
    (the worker is busy with the first controller while the second is dropped)."""
    worker = CriticalSearchWorker()
    held = Controller(MOB, 0.1j, navfn="kr", k=6)
    first = held.search_critical_points(worker)
    dropped = Controller(MOB, 0.3 - 0.2j, navfn="kr", k=6)
    fut = dropped.search_critical_points(worker)
    del dropped
    assert first.result(timeout=60).ok
    with pytest.raises(CancelledError):
        fut.result(timeout=60)
    assert held.search_critical_points(worker) is first  # a held one keeps its result


def test_the_core_starts_no_thread() -> None:
    """Controllers, their steps and critical points run in the caller's thread; background
    searches need an executor the host passes (issue 26 item 16)."""
    import threading

    before = set(threading.enumerate())
    ctl = Controller(MOB, 0.1j, navfn="kr", k=6)
    ctl(np.array([0.5 + 0j, 0.2 - 0.3j]))
    assert ctl.critical_points().ok
    assert set(threading.enumerate()) == before
    with pytest.raises(TypeError):
        ctl.search_critical_points()  # type: ignore[call-arg]


def test_new_goal_reuses_the_map() -> None:
    m = MobiusMap(SEED, 0.2 - 0.1j)
    ctl = Controller(m, 0.1j, navfn="harmonic")
    ctl2 = ctl.with_goal((0.5, 0.55))
    assert ctl2.cmap is m and ctl2.domain is ctl.domain
    assert ctl2.goal == 0.5 + 0.55j
    assert_allclose(ctl2.navfn.goal, m.T_and_dT(0.5 + 0.55j)[0])
    assert ctl2(0.5 + 0.55j).status == Status.ARRIVED
    res = simulate(ctl2, [-0.7 + 0.0j, 0.6 - 0.6j])
    assert res.success.all(), res.message


def test_bad_input() -> None:
    with pytest.raises(NavigationError, match="free space"):
        Controller(MOB, SEED.centers[2])
    with pytest.raises(NavigationError, match="free space"):
        Controller(MOB, 1.5 + 0j)
    with pytest.raises(NavigationError, match="not finite"):
        Controller(MOB, (np.nan, 0.0))
    with pytest.raises(NavigationError, match="pair"):
        Controller(MOB, (1.0, 2.0, 3.0))
    with pytest.raises(NavigationError, match="gain"):
        Controller(MOB, 0j, gain=0.0)
    with pytest.raises(NavigationError, match="v_max"):
        Controller(MOB, 0j, v_max=-1.0)
    with pytest.raises(NavigationError, match="k must"):
        Controller(MOB, 0j, navfn="kr", k=0)
    with pytest.raises(NavigationError, match="free space"):
        Controller(MOB, 0j).with_goal(SEED.centers[0])


def test_normalized_law_has_the_theorem2_paths_and_the_speed_profile() -> None:
    plain = Controller(
        MOB, 0.1j, navfn="harmonic", speed_law="theorem2", v_max=np.inf, goal_tol=1e-3
    )
    # the speed profile of the bare normalized law (the hold cap is tested on its own below)
    norm = Controller(MOB, 0.1j, navfn=plain.navfn, gain=2.0, v_max=0.4, goal_tol=1e-3, hold_time=0)
    z = interior_points(SEED, 300, 1e-3, seed=7)
    u0, u1 = plain.velocity(z), norm.velocity(z)
    # same direction, speed min(v_max, gain |x - x_d|) whatever |grad phi| is
    assert_allclose(np.angle(u1 / u0), 0, atol=1e-12)
    assert_allclose(np.abs(u1), np.minimum(0.4, 2.0 * np.abs(z - 0.1j)), rtol=1e-13)
    assert np.ptp(np.log10(np.abs(u0))) > 1.5  # the plain law's speed varies a lot here
    starts = z[:30]
    res0 = simulate(plain, starts, record_paths=True, atol=1e-7)
    res1 = simulate(norm, starts, record_paths=True, atol=1e-7)
    assert res0.success.all() and res1.success.all(), (res0.message, res1.message)
    # a time change: the same curves (same lengths up to the integrator's tolerance) ...
    assert_allclose(res1.path_length, res0.path_length, rtol=2e-3)
    for p in res1.paths or ():
        assert np.all(np.diff(norm.lyapunov(p)) < 0)
    # ... traversed within the bound L / v_max + log(v_max / (gain tol)) / gain
    bound = res1.path_length / 0.4 + np.log(0.4 / (2.0 * 1e-3)) / 2.0
    assert np.all(res1.time <= bound * (1 + 1e-3))


def test_undefined_direction_gives_zero_not_nan() -> None:
    ctl = Controller(MOB, 0.1j, navfn="kr", k=6, goal_tol=1e-9)
    saddle_ws = MOB.inverse(ctl.critical_points().saddles[0])
    u = ctl.velocity(np.array([0.1j, saddle_ws]))
    # at the goal f = 0 exactly: u = 0; at the numerical saddle f is rounding noise, so the
    # direction is defined (and flips around it): finite, at most v_max
    assert np.all(np.isfinite(u)) and u[0] == 0 and abs(u[1]) <= ctl.v_max * (1 + 1e-12)
    f = np.array([0j, 1e-300 + 0j, np.nan + 0j, 3 - 4j])
    out, sat = speed_law(f, np.array([1.0, 1.0, 1.0, 0.1]), gain=1.0, v_max=0.5)
    assert out[0] == 0 and np.isnan(out[2]) and np.isfinite(out[1])
    assert_allclose(out[[1, 3]], [0.5, 0.1 * (3 - 4j) / 5], rtol=1e-15)
    assert list(sat) == [False, True, False, False]


def test_goal_message_defaults_are_the_library_defaults() -> None:
    goal = Goal(robot_id="r", ws_id="w", goal=(0.0, 0.0))
    ctl_defaults = {
        k: p.default for k, p in inspect.signature(Controller.__init__).parameters.items()
    }
    pairs = {
        "navfn": ("navfn", defaults.NAVFN),
        "speed_law": ("speed_law", defaults.SPEED_LAW),
        "gain": ("gain", defaults.GAIN),
        "v_max": ("v_max", defaults.V_MAX),
        "tolerance": ("goal_tol", defaults.GOAL_TOL),
    }
    for field, (param, value) in pairs.items():
        assert getattr(goal, field) == ctl_defaults[param] == value, field
    assert goal.k is None and ctl_defaults["k"] == "auto"  # None on the wire means auto
    assert (defaults.SPEED_LAW, defaults.V_MAX, defaults.GAIN) == ("normalized", 0.5, 1.0)


def _segment_misses_circle(a: np.ndarray, b: np.ndarray, c: complex, r: float) -> np.ndarray:
    """Exact: the closed segment [a, b] stays farther than r from c (closest point formula)."""
    d = b - a
    t = np.clip(((c - a) * np.conj(d)).real / np.maximum(np.abs(d) ** 2, 1e-300), 0.0, 1.0)
    return np.asarray(np.abs(a + t * d - c) > r)


@pytest.mark.parametrize("law", ["normalized", "theorem2"])
def test_held_command_never_leaves_the_free_space(law: str) -> None:
    """A command held for the whole hold time moves the robot along the segment
    [z, z + u hold_time]: from poses 1e-6..0.05 from every wall, that segment stays inside
    the circle domain (exact distance of a segment to each circle), using at most
    HOLD_FRACTION of the clearance; far from the walls the speed is that of the bare law."""
    hold = defaults.HOLD_TIME
    assert hold == 0.25  # the simulator's max_cmd_age (services/simulator.py reads it too)
    gain = 50.0 if law == "theorem2" else 1.0
    ctl = Controller(MOB, 0.1j, navfn="harmonic", speed_law=law, gain=gain, v_max=0.5)
    bare = Controller(MOB, 0.1j, navfn=ctl.navfn, speed_law=law, gain=gain, v_max=0.5, hold_time=0)
    assert ctl.hold_time == hold and bare.hold_time == 0
    rng = np.random.default_rng(3)
    walls = [(0j, 1.0), *zip(SEED.centers, SEED.radii, strict=True)]
    z = []
    for c, r in walls:  # poses just off each wall, on the free side
        th = rng.uniform(0, 2 * np.pi, 200)
        gap = 10 ** rng.uniform(-6, np.log10(0.05), 200)
        z.append(c + (r - gap if c == 0 and r == 1.0 else r + gap) * np.exp(1j * th))
    zz = np.concatenate(z)
    zz = zz[SEED.clearance(zz) > 0]
    u = ctl(zz).u
    end = zz + u * hold
    clear = SEED.clearance(zz)
    assert np.all(np.abs(u) * hold <= defaults.HOLD_FRACTION * clear * (1 + 1e-12))
    assert np.all(np.abs(end) < 1.0)  # the unit disk is convex: both ends inside suffice
    for c, r in zip(SEED.centers, SEED.radii, strict=True):
        assert np.all(_segment_misses_circle(zz, end, c, r))
    # the bare law's held command could reach the wall (in the worst direction, straight at
    # it) from many of these poses; the capped one from none, whatever its direction
    assert np.mean(np.abs(bare(zz).u) * hold > clear) > 0.5
    # same direction everywhere (a positive rescaling: same paths)
    moving = np.abs(u) > 0
    assert_allclose(np.angle(u[moving] / bare(zz).u[moving]), 0, atol=1e-12)
    # far from the walls (clearance >= v_max hold / HOLD_FRACTION) nothing changes, bitwise
    far = interior_points(SEED, 100, 0.5 * hold / defaults.HOLD_FRACTION, seed=5)
    assert far.size > 40
    out, out0 = ctl(far), bare(far)
    assert np.array_equal(out.u, out0.u) and np.array_equal(out.saturated, out0.saturated)


def test_hold_time_needs_a_workspace_and_is_checked() -> None:
    class NoWorkspace:
        centers, radii = SEED.centers, SEED.radii

        def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
            return IdentityMap(SEED).T_and_dT(z)

    assert Controller(NoWorkspace(), 0.2j, navfn="kr", k=6).hold_time == 0  # default: off
    with pytest.raises(NavigationError, match="hold_time needs a map with a workspace"):
        Controller(NoWorkspace(), 0.2j, navfn="kr", k=6, hold_time=0.25)
    for bad in (-0.1, np.inf, np.nan):
        with pytest.raises(NavigationError, match="hold_time"):
            Controller(MOB, 0.1j, navfn="kr", k=6, hold_time=bad)


def test_map_values_entry_point_is_the_controller() -> None:
    """``from_map_values`` with one evaluation of T for robots of several goals gives each
    controller's own commands and statuses, bitwise (the T values are the same)."""
    base = Controller(MOB, 0.1j, navfn="harmonic", goal_tol=1e-3)
    ctls = [base.with_goal(g) for g in (0.1j, -0.3 + 0.6j, 0.5 - 0.5j, 0.3 + 0.0j)]
    z = np.concatenate([interior_points(SEED, 40, 1e-4, seed=s) for s in range(4)])
    z[3] = np.nan  # a bad pose: ERROR with u = 0 on both paths
    z[7] = ctls[0].goal  # arrived
    with np.errstate(invalid="ignore"):  # the exact map at the NaN pose
        w, dw = MOB.T_and_dT(z)
    for i, ctl in enumerate(ctls):
        sl = slice(40 * i, 40 * (i + 1))
        a, b = ctl.from_map_values(z[sl], w[sl], dw[sl]), ctl(z[sl])
        c = ctl.from_map_values(z[sl], w[sl], dw[sl], ctls[0].clearance(z[sl]))  # shared
        assert ctl.uses_clearance  # the hold cap is on: the shared clearance is used
        for f in ("u", "status", "phi", "w", "saturated"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=f != "saturated"), f
            assert np.array_equal(getattr(c, f), getattr(b, f), equal_nan=f != "saturated"), f
    assert ctls[0](z[:8]).status[3] == Status.ERROR and ctls[0](z[:8]).status[7] == Status.ARRIVED


def test_a_goal_the_map_sends_onto_a_circle_is_refused_in_workspace_terms() -> None:
    """A goal inside the workspace whose image lies on (or, by the map's error, across) a
    circle of the circle domain -- a goal on a wall to rounding, as in a charging alcove whose
    shrunk back wall ran through it -- is refused in the words of the workspace, not with the
    circle-domain coordinates the navigation function would report."""

    class OnCircle:
        """T = identity onto SEED, and no workspace test of its own: the goal gets to T."""

        centers, radii, workspace = SEED.centers, SEED.radii, None

        def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
            z = np.asarray(z, dtype=complex)
            return z, np.ones_like(z)

    ctl_map = OnCircle()
    with pytest.raises(NavigationError, match=r"goal \(1, 0\) is too close to a wall"):
        Controller(ctl_map, 1.0 + 0j)
    edge = SEED.centers[0] + SEED.radii[0]  # on an obstacle's circle
    with pytest.raises(NavigationError, match="too close to a wall"):
        Controller(ctl_map, edge)
    Controller(ctl_map, 0.9 + 0j)  # inside: fine


@pytest.fixture(scope="module")
def room_map() -> Any:
    """A real solved map: a 2 x 1 m room with a square pillar (corners, straight walls)."""
    import confnav
    from confnav.geometry import Workspace

    ws = Workspace(
        [(0, 0), (2, 0), (2, 1), (0, 1)], [[(0.8, 0.3), (1.2, 0.3), (1.2, 0.7), (0.8, 0.7)]]
    )
    return confnav.solve(ws, tol=1e-8).for_navigation()


def test_held_command_stays_in_a_polygonal_room(room_map: Any) -> None:
    """The solver's map of a room: from poses 1e-6..0.05 m from the walls (and in every
    corner) the segment a held command travels lies in the free polygon (shapely's exact
    predicate), and the cap binds there; T' of a real map makes no difference to the bound."""
    import shapely

    ws = room_map.workspace
    ctl = Controller(room_map, 1.8 + 0.5j)
    rng = np.random.default_rng(1)
    z = rng.uniform(0, 2, 20000) + 1j * rng.uniform(0, 1, 20000)
    corners = np.concatenate(ws.boundaries)
    gap = 10 ** rng.uniform(-6, -1.3, (corners.size, 40))
    near = corners[:, None] + gap * np.exp(2j * np.pi * rng.uniform(0, 1, (corners.size, 40)))
    z = np.concatenate([z, near.ravel()])
    c = ws.clearance(z)
    z, c = z[(c > 0) & (c < 0.05)], c[(c > 0) & (c < 0.05)]
    assert z.size > 500
    out = ctl(z)
    # u is NaN (the service stops the robot) within ~1e-5 m of a room corner, where T rounds
    # to just outside the unit disk and phi is NaN: not moving, so not checked here
    moving = (out.status == Status.MOVING) & np.isfinite(out.u)
    assert moving.mean() > 0.95
    z, c, u = z[moving], c[moving], out.u[moving]
    assert np.all(np.abs(u) * ctl.hold_time <= defaults.HOLD_FRACTION * c * (1 + 1e-12))
    end = z + u * ctl.hold_time
    segs = shapely.linestrings(
        np.stack([np.stack([z.real, z.imag], -1), np.stack([end.real, end.imag], -1)], 1)
    )
    assert np.all(shapely.contains(ws.polygon, segs))
    assert not out.saturated[moving].any()  # within 0.05 m the cap (2 c <= 0.1 m/s) binds
