"""Unicycle robots: the look-ahead feedback linearisation is exact (p' = u), limits keep the
direction, and from random starts and headings every robot arrives without the body touching
an obstacle (exact circle domain, T = identity, so the clearance is known in closed form)."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.control import Controller
from confnav.errors import NavigationError
from confnav.unicycle import (
    UnicycleController,
    look_ahead_point,
    simulate_unicycle,
    step_exact,
    twist_from_velocity,
)
from tests.conftest import IdentityMap

CENTERS = [0.45 + 0.1j, -0.4 + 0.35j, -0.2 - 0.45j]
RADII = [0.15, 0.12, 0.14]


def clearance(z: np.ndarray) -> np.ndarray:
    """Exact signed distance to the circle domain's boundary (unit disk minus disks)."""
    z = np.asarray(z, dtype=complex)
    d = 1.0 - np.abs(z)
    for c, r in zip(CENTERS, RADII, strict=True):
        d = np.minimum(d, np.abs(z - c) - r)
    return d


def test_linearisation_is_exact() -> None:
    rng = np.random.default_rng(1)
    z = rng.normal(size=50) + 1j * rng.normal(size=50)
    th = rng.uniform(-np.pi, np.pi, 50)
    u = rng.normal(size=50) + 1j * rng.normal(size=50)
    d = 0.2
    v, om = twist_from_velocity(u, th, d)
    # p' = x' + i d theta' e^{i theta} = (v + i d omega) e^{i theta} must equal u
    np.testing.assert_allclose((v + 1j * d * om) * np.exp(1j * th), u, rtol=1e-14, atol=1e-14)
    # and along a short exact arc the finite difference of p matches u to O(dt)
    dt = 1e-6
    z1, th1 = step_exact(z, th, v, om, dt)
    dp = (look_ahead_point(z1, th1, d) - look_ahead_point(z, th, d)) / dt
    np.testing.assert_allclose(dp, u, atol=1e-5 * np.abs(u).max())


def test_limits_scale_keeping_direction() -> None:
    rng = np.random.default_rng(2)
    u = 3 * (rng.normal(size=200) + 1j * rng.normal(size=200))
    th = rng.uniform(-np.pi, np.pi, 200)
    d, vmax, wmax = 0.1, 0.5, 1.0
    v, om = twist_from_velocity(u, th, d, vmax, wmax)
    assert np.all(np.abs(v) <= vmax * (1 + 1e-12)) and np.all(np.abs(om) <= wmax * (1 + 1e-12))
    us = (v + 1j * d * om) * np.exp(1j * th)  # the p velocity actually commanded
    # same direction as u (a positive multiple), one limit active
    np.testing.assert_allclose(np.angle(us / u), 0.0, atol=1e-12)
    active = np.isclose(np.abs(v), vmax) | np.isclose(np.abs(om), wmax)
    assert np.all(active | np.isclose(np.abs(us), np.abs(u)))


def test_exact_arc() -> None:
    # a full turn at omega = 1, v = 1 returns to the start; a quarter turn ends at (1, 1)
    z, th = step_exact(0j, 0.0, 1.0, 1.0, 2 * np.pi)
    assert abs(z) < 1e-14 and th == pytest.approx(2 * np.pi)
    z, _ = step_exact(0j, 0.0, 1.0, 1.0, np.pi / 2)
    assert abs(z - (1 + 1j)) < 1e-14


def test_random_starts_converge_without_collision() -> None:
    r, d = 0.04, 0.05
    # the map of the free space shrunk by r + d: exact for a circle domain
    scale = 1 / (1 - r - d)  # rescale so that the outer circle is the unit circle
    cmap = IdentityMap([c * scale for c in CENTERS], [(rr + r + d) * scale for rr in RADII])

    class Scaled:
        centers, radii = cmap.centers, cmap.radii

        def T_and_dT(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            w, dw = cmap.T_and_dT(np.asarray(z) * scale)
            return w, dw * scale

    goal = 0.05 + 0.55j
    ctl = Controller(Scaled(), goal, v_max=0.5, goal_tol=0.01, v_min=0.2)
    uc = UnicycleController(ctl, d, v_max=0.5, omega_max=2.0)
    rng = np.random.default_rng(7)
    z = rng.uniform(-1, 1, 400) + 1j * rng.uniform(-1, 1, 400)
    z = z[clearance(z) > r + 2 * d][:40]  # then p = z + d e^{i theta} has clearance > r + d
    th = rng.uniform(-np.pi, np.pi, z.size)
    res = simulate_unicycle(uc, z, th, clearance=clearance, radius=r, t_max=60.0)
    assert z.size == 40
    assert res.collided.sum() == 0, res.message
    assert res.success.all(), res.message
    assert np.all(res.final_distance <= 0.01 + 1e-12)
    assert res.min_clearance.min() > 0


def test_bad_parameters() -> None:
    ctl = Controller(IdentityMap([0.5 + 0j], [0.1]), -0.5 + 0j)
    with pytest.raises(NavigationError):
        UnicycleController(ctl, 0.0)
    with pytest.raises(NavigationError):
        UnicycleController(ctl, 0.1, omega_max=0.0)
    uc = UnicycleController(ctl, 0.1)
    with pytest.raises(NavigationError, match="body"):
        simulate_unicycle(uc, [0.45 + 0j], [0.0], clearance=clearance, radius=0.05)
