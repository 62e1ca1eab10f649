"""A fleet step (every robot its own goal, one vectorized pass) equals each robot's own step.

``fleet_step`` stacks the goals' navigation functions (Koditschek-Rimon with a goal and k per
robot; the harmonic series with each goal's coefficients, zero padded) and the controllers'
parameters.  The formulas are those of ``Controller.from_map_values``; the sums run in another
order (padded to the longest series), so the results agree to rounding, which the harmonic
gradient ``2 e^{-2h} (e conj(...) - g grad h)`` amplifies where its two terms nearly cancel:
the bulk of the robots agree to RTOL_BULK, every robot to RTOL (5.6e-12 was seen in the full
suite, where the map's shared basis had been extended by earlier tests); statuses and
saturation exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import confnav
from confnav.conformal.cmap import ConformalMap
from confnav.navigation.control import Controller, Status
from confnav.navigation.fleet import fleet_step
from confnav.navigation.navfn import KoditschekRimon, value_and_gradient_stacked
from confnav.scenes.scenarios import random_starts
from confnav.scenes.workspaces import default_workspace

RTOL = 1e-10
RTOL_BULK = 1e-14


@pytest.fixture(scope="module")
def nav_map() -> ConformalMap:
    return confnav.solve(default_workspace(), tol=1e-8).for_navigation()


def _close(a: Any, b: Any) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
        return False
    ok = ~np.isnan(b)
    return bool(np.all(np.abs(a[ok] - b[ok]) <= RTOL * np.abs(b[ok]) + 1e-300))


def _bulk_at_rounding(a: np.ndarray, b: np.ndarray) -> bool:
    """The median relative difference over the finite, non-zero entries is rounding."""
    ok = np.isfinite(b) & (b != 0)
    return bool(np.median(np.abs(a[ok] - b[ok]) / np.abs(b[ok])) <= RTOL_BULK)


def _poses(m: ConformalMap, goals: np.ndarray) -> np.ndarray:
    """Free-space poses, a pose at and one within tolerance of some goals, bad poses."""
    z = random_starts(m.workspace, 60, seed=3, margin=0.01)
    extra = [goals[0], goals[1] + 0.01, complex(np.nan, 0.0), 3 + 3j, 0.9 + 0.7j]
    return np.concatenate([z, extra])


def _fleet(m: ConformalMap, **kw: Any) -> tuple[list[Controller], np.ndarray]:
    goals = random_starts(m.workspace, 12, seed=11, margin=0.1)
    base = Controller(m, goals[0], **kw)
    ctrls = [base] + [base.with_goal(g) for g in goals[1:]]
    z = _poses(m, goals)
    return [ctrls[i % len(ctrls)] for i in range(z.size)], z


@pytest.mark.parametrize("navfn", ["harmonic", "kr"])
def test_fleet_step_equals_each_robots_own_step(nav_map: ConformalMap, navfn: str) -> None:
    ctrls, z = _fleet(nav_map, navfn=navfn)
    assert len({id(c.navfn) for c in ctrls}) == 12  # twelve goals, each its own function
    w, dw = nav_map.T_and_dT(np.where(np.isfinite(z), z, 0j))
    c = ctrls[0].clearance(np.where(np.isfinite(z), z, 0j))
    out = fleet_step(ctrls, z, w, dw, c)
    ones = []
    for i, ctl in enumerate(ctrls):
        one = ctl.from_map_values(z[i : i + 1], w[i : i + 1], dw[i : i + 1], c[i : i + 1])
        assert out.status[i] == one.status[0], i
        assert out.saturated[i] == one.saturated[0], i
        assert _close(out.u[i], one.u[0]), (i, out.u[i], one.u[0])
        assert _close(out.phi[i], one.phi[0]), (i, out.phi[i], one.phi[0])
        ones.append(one)
    assert _bulk_at_rounding(out.u, np.array([o.u[0] for o in ones]))
    assert _bulk_at_rounding(out.phi, np.array([o.phi[0] for o in ones]))
    statuses = set(out.status.tolist())
    assert {Status.MOVING, Status.ARRIVED, Status.ERROR} <= statuses
    assert np.count_nonzero(np.abs(out.u) > 0) >= 50  # most robots move


def test_fleet_step_with_mixed_laws_parameters_and_stall_points(nav_map: ConformalMap) -> None:
    """KR and harmonic goals, both speed laws, per-robot gains and caps, no clearance given
    (computed inside), and a controller whose stall points include a robot's position."""
    goals = random_starts(nav_map.workspace, 4, seed=5, margin=0.1)
    ctrls = [
        Controller(nav_map, goals[0]),
        Controller(nav_map, goals[1], navfn="kr", k=8.0, gain=2.0, v_max=0.3),
        Controller(nav_map, goals[2], speed_law="theorem2", gain=50.0, v_max=1.0),
        Controller(nav_map, goals[3], navfn="kr", slow_distance=0.0, hold_time=0.0),
    ]
    z = _poses(nav_map, goals)
    fleet = [ctrls[i % 4] for i in range(z.size)]
    w, dw = nav_map.T_and_dT(np.where(np.isfinite(z), z, 0j))
    # a stall point at robot 5's image: reported STALLED by its controller alone
    cp = ctrls[1].critical_points()
    ctrls[1]._critical = type(cp)(**{**cp.__dict__, "saddles": np.array([w[5]])})
    out = fleet_step(fleet, z, w, dw)
    for i, ctl in enumerate(fleet):
        one = ctl.from_map_values(z[i : i + 1], w[i : i + 1], dw[i : i + 1])
        assert out.status[i] == one.status[0] and out.saturated[i] == one.saturated[0], i
        assert _close(out.u[i], one.u[0]), (i, out.u[i], one.u[0])
    assert out.status[5] == Status.STALLED


def test_stacked_navigation_functions_match_one_by_one(nav_map: ConformalMap) -> None:
    dom = Controller(nav_map, 0.0 + 1.5j).domain
    rng = np.random.default_rng(2)
    w = 0.9 * np.sqrt(rng.uniform(0, 1, 400)) * np.exp(2j * np.pi * rng.uniform(0, 1, 400))
    goals = w[dom.contains(w)][:5]
    fns = [KoditschekRimon(dom, g, k=6.0 + i) for i, g in enumerate(goals)]
    pts = w[:200]
    fleet = [fns[i % 5] for i in range(pts.size)]
    phi, grad = value_and_gradient_stacked(fleet, pts)
    for i, f in enumerate(fleet):
        p1, g1 = f.value_and_gradient(pts[i : i + 1])
        assert _close(phi[i], p1[0]) and _close(grad[i], g1[0]), i
    assert np.isnan(phi).any()  # points inside holes: NaN, as one by one
    with pytest.raises(ValueError, match="navigation functions for"):
        value_and_gradient_stacked(fleet[:3], pts)


def test_fleet_step_refuses_controllers_on_different_maps(nav_map: ConformalMap) -> None:
    other = confnav.solve(default_workspace(), tol=1e-6).for_navigation()
    a, b = Controller(nav_map, 0.0 + 1.5j), Controller(other, 0.0 + 1.5j)
    z = np.array([1.5 + 1.5j, 1.5 - 1.5j])
    w, dw = nav_map.T_and_dT(z)
    with pytest.raises(ValueError, match="one map"):
        fleet_step([a, b], z, w, dw)
