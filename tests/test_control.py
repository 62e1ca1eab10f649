"""Theorem 2 control law and the normalized speed law against exact maps (Mobius self-maps and
the identity of a circle domain): same paths, speed profile, saturation, status codes (flat is
not stalled), goal changes, bad input, defaults shared with the Goal message."""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
import pytest
from confnav.schemas import Goal
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
    ctl = Controller(MOB, 0.1j, navfn=navfn, k=6, speed_law="theorem2", gain=2.5, v_max=np.inf)
    z = interior_points(SEED, 200, 1e-3)
    u = ctl.velocity(z)
    v = ctl.lyapunov
    h = 1e-6
    grad_v = (v(z + h) - v(z - h)) / (2 * h) + 1j * (v(z + 1j * h) - v(z - 1j * h)) / (2 * h)
    assert_allclose(u, -2.5 * grad_v, rtol=1e-5, atol=1e-9 * np.max(np.abs(u)))


def test_identity_map_gives_the_plain_gradient() -> None:
    ctl = Controller(IdentityMap(SEED), 0.2j, navfn="kr", k=6, speed_law="theorem2", v_max=np.inf)
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
    fut = ctl.search_critical_points()
    assert ctl.search_critical_points() is fut  # once per controller
    cp = fut.result(timeout=60)
    assert cp.ok and cp.saddles.size == SEED.n_obstacles
    assert ctl(saddle_ws).status == Status.STALLED
    assert ctl(0.5 + 0j).status == Status.MOVING


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
    norm = Controller(MOB, 0.1j, navfn=plain.navfn, gain=2.0, v_max=0.4, goal_tol=1e-3)
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
