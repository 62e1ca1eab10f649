"""The one-robot control step (scalar path) gives the batch path's results.

A single pose goes through ``ConformalMap._forward1`` (Python scalars, the expansion row of
``LocalExpansions.sums1``), ``NavigationFunction.value_and_gradient1`` and
``Controller._step1``; a batch goes through the vectorized code.  Both evaluate the same
formulas in the same order, so they agree to rounding: 1e-14 relative here, statuses and
saturation flags exactly.  Points: random free-space poses, poses near the walls and corners
(outside every local expansion: the barycentric fallback), the goal itself, poses within the
goal tolerance, a boundary node, poses outside the free space and NaN poses.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import confnav
from confnav.conformal.cmap import ConformalMap
from confnav.navigation.control import Controller, ControlOutput, Status
from confnav.navigation.harmonic import HarmonicNavigation
from confnav.navigation.navfn import KoditschekRimon, NavigationFunction, obstacle_function
from confnav.scenes.workspaces import default_workspace

RTOL = 1e-14
GOAL = -1.5 + 0.2j


@pytest.fixture(scope="module")
def nav_map() -> ConformalMap:
    m = confnav.solve(default_workspace(), tol=1e-8).for_navigation()
    m.T_and_dT(np.array([0.5 + 0.1j, 0.6 + 0.1j]))  # builds the local expansions
    assert m._expansion is not None
    return m


def _points(m: ConformalMap) -> np.ndarray:
    ws = m.workspace
    rng = np.random.default_rng(7)
    z = rng.uniform(-2, 2, 4000) + 1j * rng.uniform(-2, 2, 4000)
    z = z[ws.contains(z)]
    clear = ws.clearance(z)
    verts = np.concatenate([ws.outer, *ws.obstacles])
    corner = (verts[:, None] + np.array([1e-4, 1e-3, 2e-2]) * np.exp(0.8j)).ravel()
    corner = corner[ws.contains(corner)]
    at_goal = GOAL + np.array([0, 0.01, 0.019j, 0.05])  # the goal, within goal_tol, beyond
    outside = np.array([3 + 3j, 0.9 + 0.7j, -0.8 + 0.6j])  # outside; inside obstacles
    bad = np.array([np.nan, complex(np.nan, 1.0), complex(np.inf, 0.0)])
    return np.concatenate(
        [z[:40], z[clear < 0.02][:25], corner[:25], at_goal, [m._eta[17]], outside, bad]
    )


def _close(a: Any, b: Any, rtol: float = RTOL, atol: float = 0.0) -> bool:
    """Equal NaN pattern and |a - b| <= rtol |b| + atol elsewhere."""
    a, b = np.asarray(a), np.asarray(b)
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    if not np.array_equal(nan_a, nan_b) or a.shape != b.shape:
        return False
    ok = ~nan_b
    return bool(np.all(np.abs(a[ok] - b[ok]) <= rtol * np.abs(b[ok]) + atol))


def _conditioning(m: ConformalMap, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Condition numbers of T = N/D and T' = (N'D - N D')/D^2 as floating-point sums: the
    same quotients of the sums of |terms|, over |T| resp. |T'| (>= 1)."""
    with np.errstate(all="ignore"):
        zf = np.where(np.isfinite(z), z, 0)
        r = np.abs(1.0 / (m._eta[None, :] - zf[:, None]))
        aN, aD = r @ np.abs(m._q_W), r @ np.abs(m._q_deta)
        adN, adD = (r * r) @ np.abs(m._q_W), (r * r) @ np.abs(m._q_deta)
        w, dw = m.T_and_dT(z)
        D = np.abs((1.0 / (m._eta[None, :] - zf[:, None])) @ m._q_deta)
        cw = (aN / D + np.abs(w) * aD / D) / np.abs(w)
        cdw = (adN * D + aN * adD) / D**2 / np.abs(dw)
    return np.maximum(np.nan_to_num(cw, nan=1.0), 1.0), np.maximum(np.nan_to_num(cdw, nan=1.0), 1.0)


def test_map_single_point_equals_batch(nav_map: ConformalMap) -> None:
    z = _points(nav_map)
    ex = nav_map._expansion
    assert ex is not None
    cov = ex.sums(z)[0]
    assert cov.sum() >= 30 and (~cov & np.isfinite(nav_map.T(z))).sum() >= 30  # both paths
    w, dw = nav_map.T_and_dT(z)
    cond_w, cond_dw = _conditioning(nav_map, z)
    # away from the walls T' = (N'D - N D')/D^2 from the expansion's sums (bitwise the
    # batch's, checked below) is rounded in scalars against numpy's vector arithmetic: a few
    # ulp of its terms, i.e. relative to |T'| times the cancellation in N'D - N D' (measured
    # up to 154 on these points, the rounding then 1.3e-14 relative: 1 ulp of the terms)
    _, S, dS = ex.sums(z)
    with np.errstate(all="ignore"):
        terms = np.abs(dS[:, 0] * S[:, 1]) + np.abs(S[:, 0] * dS[:, 1])
        cancel = np.nan_to_num(terms / np.abs(dS[:, 0] * S[:, 1] - S[:, 0] * dS[:, 1]), nan=1.0)
    for k in range(z.size):
        w1, dw1 = nav_map.T_and_dT1(z[k])
        w0, dw0 = nav_map.T_and_dT(z[k])  # 0-d array in, 0-d arrays out
        assert w0.shape == dw0.shape == ()
        # near a wall the direct sums (one robot: 1-D dots; a batch: BLAS) add 6000 terms in
        # another order: rounding relative to the sums of the terms' moduli, not to |T'|
        rw = RTOL * (1.0 if cov[k] else cond_w[k])
        rd = RTOL * (max(cancel[k], 1.0) if cov[k] else cond_dw[k])
        assert _close(w1, w[k], rw) and _close(dw1, dw[k], rd), (k, z[k], w1 - w[k], dw1 - dw[k])
        assert _close(w0, w[k], rw) and _close(dw0, dw[k], rd)
        if cov[k]:  # the expansion's row is bitwise the batch's
            s1 = ex.sums1(complex(z[k]))
            _, S, dS = ex.sums(z[k : k + 2] if k + 1 < z.size else z[k - 1 : k + 1])
            row = 0 if k + 1 < z.size else 1
            assert s1 is not None
            assert np.array_equal(s1, np.concatenate([S[row], dS[row]]))
    assert np.isnan(nav_map.T_and_dT1(np.nan)[0]) and np.isnan(nav_map.T_and_dT1(3 + 3j)[1])
    # a boundary node: the node's own value, as the batch
    assert nav_map.T_and_dT1(nav_map._eta[17])[0] == nav_map._W[17]


@pytest.mark.parametrize("navfn", ["kr", "harmonic"])
def test_navfn_single_point_equals_batch(nav_map: ConformalMap, navfn: str) -> None:
    ctl = Controller(nav_map, GOAL, navfn=navfn, k=8)
    nf = ctl.navfn
    rng = np.random.default_rng(2)
    w = rng.uniform(-1, 1, 400) + 1j * rng.uniform(-1, 1, 400)
    w = np.concatenate([w, [nf.goal, nf.goal + 1e-9, 1.2 + 0j, complex(nf.domain.centers[0])]])
    phi, g = nf.value_and_gradient(w)
    assert np.isnan(phi).sum() > 50 and np.isfinite(phi).sum() > 150
    with np.errstate(invalid="ignore", divide="ignore"):
        cond = _gradient_conditioning(nf, w) / np.abs(g)
    assert np.nanmedian(cond) < 1e3  # the bound stays far below the gradient's size
    for k in range(w.size):
        p1, g1 = nf.value_and_gradient1(complex(w[k]))
        assert isinstance(p1, float) and isinstance(g1, complex)
        rg = RTOL * max(1.0, float(np.nan_to_num(cond[k], nan=1.0)))
        assert _close(p1, phi[k]) and _close(g1, g[k], rg), (k, w[k], p1 - phi[k], g1 - g[k])
    assert nf.value_and_gradient1(nf.goal) == (0.0, 0j)


def _gradient_conditioning(nf: NavigationFunction, w: np.ndarray) -> np.ndarray:
    """Sum of the moduli of the two terms whose difference is the gradient (Koditschek-Rimon:
    ``root/D (beta 2 e - g/k grad beta)``; harmonic: ``2 e^-2h (e conj(...) - g grad H)``):
    near the boundary and the saddles they nearly cancel, and rounding in either path is
    relative to them, not to |grad phi|."""
    with np.errstate(all="ignore"):
        e = w - nf.goal
        g = np.abs(e) ** 2
        if isinstance(nf, KoditschekRimon):
            beta, dbeta = obstacle_function(nf.domain, w)
            big_d = g**nf.k + beta
            root = np.abs(big_d) ** (-1.0 / nf.k)
            return np.asarray(
                root / np.abs(big_d) * (2 * np.abs(beta * e) + g / nf.k * np.abs(dbeta))
            )
        assert isinstance(nf, HarmonicNavigation)
        _, h, grad_h = nf.green.parts(w)
        q = 1.0 - np.conj(nf.goal) * w
        a = np.abs(e * (1.0 - abs(nf.goal) ** 2) / q)
        return np.asarray(2 * np.exp(-2 * h) * (a + g * np.abs(grad_h)))


def _same(
    one: ControlOutput, batch: ControlOutput, k: int, cond: float = 1.0, shape: tuple[int, ...] = ()
) -> None:
    for f in ("u", "phi", "w", "status", "saturated"):
        a, b = getattr(one, f), getattr(batch, f)
        assert a.shape == shape and a.dtype == b.dtype, f
        if f in ("status", "saturated"):
            assert a.reshape(()) == b[k], (f, k, a, b[k])
        else:
            # phi ~ |w - w_d|^2 at the goal, where w carries rounding of 1e-16: 1e-30 absolute
            atol = 1e-30 if f == "phi" else 0.0
            assert _close(a.reshape(()), b[k], RTOL * cond, atol), (f, k, a, b[k], cond)


def _step_conditioning(ctl: Controller, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: the factor by which rounding may exceed 1e-14 relative in the control law
    alone (the gradient's cancellation, :func:`_gradient_conditioning`) and in the whole step
    (times the map's near the walls, :func:`_conditioning`, where no expansion covers z)."""
    m = ctl.cmap
    assert isinstance(m, ConformalMap) and m._expansion is not None
    zq = np.where(np.isfinite(z), z, GOAL)
    w = m.T(zq)
    with np.errstate(invalid="ignore", divide="ignore"):
        law = _gradient_conditioning(ctl.navfn, w) / np.abs(ctl.navfn.gradient(w))
    law = np.maximum(np.nan_to_num(law, nan=1.0, posinf=1.0), 1.0)
    cov = m._expansion.sums(zq)[0]
    cw, cdw = _conditioning(m, zq)
    # e = w - w_d cancels near the goal: w's rounding relative to |e|, squared for the
    # harmonic G_0 = log1p(-(1 - |M|^2)) (accurate at the walls; near the pole 1 - |M|^2 ~ 1
    # cancels: 1 ulp of w moves G by 2e-12 at 0.01 m from the goal, identical w gives identical
    # phi)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.abs(w - ctl.goal_w)
        goal = np.where(e > 0, np.maximum(np.nan_to_num(np.abs(w) / e, nan=1.0), 1.0), 1.0)
    if isinstance(ctl.navfn, HarmonicNavigation):
        goal = goal**2
    return law, law * goal * np.where(cov, 1.0, np.maximum(cw, cdw))


@pytest.mark.parametrize("navfn", ["kr", "harmonic"])
def test_controller_single_robot_equals_batch(nav_map: ConformalMap, navfn: str) -> None:
    """Both speed laws, with and without the held-command cap and the wall slow-down."""
    z = _points(nav_map)
    base = Controller(nav_map, GOAL, navfn=navfn, k=8)
    cond_law, cond_step = _step_conditioning(base, z)
    # random poses: 1e-14 relative for KR; the harmonic gradient's two terms cancel to 2-3
    # digits over most of the room (measured median ~200), rounding of either path with them
    assert np.median(cond_step[:40]) < (10 if navfn == "kr" else 1e3)
    statuses: set[int] = set()
    caps = 0
    for law in ("normalized", "theorem2"):
        for hold in (0.0, 0.25, 2.0):
            for slow in (0.0, 0.3) if law == "normalized" else (0.0,):
                ctl = Controller(
                    nav_map,
                    GOAL,
                    navfn=base.navfn,
                    speed_law=law,
                    v_max=0.5 if law == "normalized" else 0.05,
                    gain=1.0 if law == "normalized" else 3.0,
                    hold_time=hold,
                    slow_distance=slow,
                )
                batch = ctl(z)
                w, dw = nav_map.T_and_dT(np.where(np.isfinite(z), z, GOAL))
                c = ctl.clearance(np.where(np.isfinite(z), z, GOAL)) if ctl.uses_clearance else None
                for k in range(z.size):
                    _same(ctl(z[k]), batch, k, cond_step[k])
                    _same(ctl(z[k : k + 1].reshape(1, 1)), batch, k, cond_step[k], (1, 1))
                    ck = None if c is None else c[k]
                    # the batch's own map values: the control law alone
                    _same(ctl.from_map_values(z[k], w[k], dw[k], ck), batch, k, cond_law[k])
                statuses |= set(batch.status.tolist())
                if hold > 0:
                    caps += int(np.sum(~batch.saturated & (batch.status == Status.MOVING)))
    assert {Status.MOVING, Status.ARRIVED, Status.ERROR} <= statuses
    assert caps > 0  # the hold cap binds somewhere


def test_stalled_single_robot_equals_batch(nav_map: ConformalMap) -> None:
    """Near a saddle of phi (critical points known) a single robot is STALLED as in a batch."""
    ctl = Controller(nav_map, GOAL, navfn="kr", k=8, stall_radius=0.05)
    cp = ctl.critical_points()
    assert cp.saddles.size
    s = nav_map.inverse(cp.saddles)
    s = s[np.isfinite(s)]
    z = (s[:, None] + np.array([0, 0.01, 0.03j, 0.2])).ravel()
    batch = ctl(z)
    assert (batch.status == Status.STALLED).any() and (batch.status == Status.MOVING).any()
    step = _step_conditioning(ctl, z)[1]
    for k in range(z.size):
        _same(ctl(z[k]), batch, k, step[k])
