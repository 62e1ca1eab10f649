"""Over-relaxed Koebe sweeps (accel="sor") reach the plain sweeps' fixed point, honestly."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from confnav import Workspace
from confnav.conformal import circledomain
from confnav.conformal.acceleration import optimal_omega
from confnav.conformal.boundary import graded_polygon
from confnav.conformal.circledomain import CircleDomainResult, koebe_iteration
from confnav.conformal.meshing import plan_boundaries
from confnav.geometry import interior_point

ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
TOL = 1e-9


def squares(gap: float) -> Workspace:
    """Two unit squares ``gap`` apart, mirror images under x -> -x, anchor on the axis."""
    g = gap / 2
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    return Workspace(ROOM, [left, right], anchor=[0, 1.5])


def _run(ws: Workspace, accel: str, nodes: int = 24) -> CircleDomainResult:
    plans = plan_boundaries(ws, nodes, TOL)
    meshes = [graded_polygon(plans[0].vertices, plans[0].nodes)] + [
        graded_polygon(p.vertices, p.nodes).reversed() for p in plans[1:]
    ]
    holes = [interior_point(o) for o in ws.obstacles]
    return koebe_iteration(meshes, holes, ws.anchor, tol=TOL, accel=accel)


def _asymmetry(r: CircleDomainResult) -> float:
    return float(max(abs(r.radii[0] - r.radii[1]), abs(r.centers[0] + np.conj(r.centers[1]))))


@pytest.fixture(scope="module")
def plain() -> CircleDomainResult:
    return _run(squares(0.03), "none")


def test_sor_reaches_the_plain_fixed_point_honestly(plain: CircleDomainResult) -> None:
    r = _run(squares(0.03), "sor")
    assert r.relaxed_sweeps > 0 and r.omega > 1.0  # the acceleration was used
    assert r.converged and plain.converged
    # same map on the same mesh: both within their (honest) iteration errors of the limit
    bound = r.iteration_error + plain.iteration_error
    assert np.max(np.abs(r.radii - plain.radii)) <= bound
    assert np.max(np.abs(r.centers - plain.centers)) <= bound
    assert max(np.max(np.abs(a - b)) for a, b in zip(r.W, plain.W, strict=True)) <= 10 * bound
    # mirror symmetry is exact for the continuous problem; on one coarse mesh level the
    # discretisation breaks it a little (same for both): the accelerated map is no less
    # symmetric than the plain one, up to their iteration errors
    assert _asymmetry(r) <= _asymmetry(plain) + bound
    assert r.circularity <= 10 * TOL  # ends with plain sweeps: the holes are circles


def test_overshooting_relaxation_is_halved_and_still_converges(
    plain: CircleDomainResult, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(circledomain, "optimal_omega", lambda rho: 1.95)
    r = _run(squares(0.03), "sor")
    assert r.omega < 1.95  # the safeguard acted: the change grew and omega was halved
    assert r.converged
    bound = r.iteration_error + plain.iteration_error
    assert np.max(np.abs(r.radii - plain.radii)) <= bound
    assert _asymmetry(r) <= _asymmetry(plain) + bound


def test_optimal_omega_is_young_s_formula() -> None:
    rho = 0.79
    assert optimal_omega(rho) == pytest.approx(2.0 / (1.0 + np.sqrt(1.0 - rho)))
    assert optimal_omega(0.1) == 1.0  # fast enough: plain sweeps
    assert optimal_omega(float("nan")) == 1.0


@pytest.mark.parametrize("modes", [1, 2])
def test_extrapolation_reaches_the_plain_fixed_point(
    plain: CircleDomainResult, monkeypatch: pytest.MonkeyPatch, modes: int
) -> None:
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", modes)
    r = _run(squares(0.03), "extrapolate")
    assert r.extrapolations > 0 and r.converged
    assert r.sweeps < plain.sweeps
    bound = r.iteration_error + plain.iteration_error
    assert np.max(np.abs(r.radii - plain.radii)) <= bound
    assert np.max(np.abs(r.centers - plain.centers)) <= bound
    assert _asymmetry(r) <= _asymmetry(plain) + bound
    assert r.circularity <= 10 * TOL


@pytest.mark.parametrize("modes", [1, 2])
def test_a_bad_extrapolation_is_rejected(
    plain: CircleDomainResult, monkeypatch: pytest.MonkeyPatch, modes: int
) -> None:
    # an extrapolation four times too long overshoots: the next sweep's change grows, and
    # the state before the extrapolation is restored (one mode: the tail's weight w; several
    # modes: the step from the last state, sum_j gamma_j x_j - x_last, made four times longer)
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", modes)
    orig = circledomain.extrapolate_curve

    def overshoot(*args: Any) -> Any:
        *curves, w = args
        return orig(*curves, 4.0 * w)

    orig_weights = circledomain._mpe_weights

    def overshoot_weights(x: Any) -> Any:
        gamma = orig_weights(x)
        if gamma is None:
            return None
        last = np.zeros_like(gamma)
        last[-1] = 1.0
        return last + 4.0 * (gamma - last)

    monkeypatch.setattr(circledomain, "extrapolate_curve", overshoot)
    monkeypatch.setattr(circledomain, "_mpe_weights", overshoot_weights)
    r = _run(squares(0.03), "extrapolate")
    assert r.rejected_extrapolations > 0
    assert r.converged
    bound = r.iteration_error + plain.iteration_error
    assert np.max(np.abs(r.radii - plain.radii)) <= bound


def test_unknown_acceleration_is_refused() -> None:
    with pytest.raises(ValueError, match="accel"):
        _run(squares(0.1), "anderson", nodes=12)


def test_where_nothing_triggers_the_run_is_the_plain_one() -> None:
    # well separated (plain contraction ~0.14): neither acceleration acts, and the run is the
    # plain run bit for bit (same change measure, same stopping sweep)
    plain = _run(squares(0.1), "none")
    for accel in ("extrapolate", "sor"):
        r = _run(squares(0.1), accel)
        assert r.extrapolations == 0 and r.relaxed_sweeps == 0
        assert r.sweeps == plain.sweeps and r.history == plain.history
        assert np.array_equal(r.radii, plain.radii) and np.array_equal(r.centers, plain.centers)


@pytest.mark.parametrize(
    ("modes", "rho", "extrapolates"),
    [
        (1, 0.3, False),
        (1, 0.45, False),
        (1, 0.7, True),
        (2, 0.15, False),
        (2, 0.3, True),
        (2, 0.7, True),
    ],
)
def test_extrapolation_starts_only_above_its_smallest_contraction(
    modes: int, rho: float, extrapolates: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One mode: two agreeing plain contraction ratios start an extrapolation only above
    RHO_EXTRAPOLATE_MIN (0.5): below it four plain sweeps gain rho^4 <= 0.06 anyway, and on the
    shrunk workspace (rho ~0.23) extrapolating cost a sweep. Two modes: above
    RHO_EXTRAPOLATE_MIN_MODES (0.2), as the cycle must pay anyway (next test)."""
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", modes)
    sched = circledomain._Schedule("extrapolate", tol=1e-12)
    sched.phase_history = [rho**k for k in range(5)]
    assert sched._start_extrapolation(sweep=6) is extrapolates
    assert (sched.phase == "material") is extrapolates


def test_two_mode_extrapolation_starts_only_when_its_cycle_pays(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # rho 0.7, remaining error 0.24 * 0.7 / 0.3 = 0.56: three plain sweeps reach tol = 0.56 *
    # 0.7^3, fewer than the cycle (three grid-keeping sweeps, the confirming one, two plain)
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", 2)
    history = [0.7**k for k in range(5)]
    rem = history[-1] * 0.7 / 0.3
    for tol, starts in ((rem * 0.7**3, False), (rem * 0.7**9, True)):
        sched = circledomain._Schedule("extrapolate", tol=tol)
        sched.phase_history = list(history)
        assert sched._start_extrapolation(sweep=6) is starts


def test_mpe_is_exact_for_two_geometric_modes() -> None:
    # x_j = x* + a 0.8^j v + b (-0.5)^j w (real-linear modes of a complex state): the weights
    # from x_0 .. x_3 combine x_1 .. x_3 into x* to rounding, whatever the ratios
    rng = np.random.default_rng(0)
    xs, v, w = (rng.normal(size=50) + 1j * rng.normal(size=50) for _ in range(3))
    x = [np.asarray(xs + 0.3 * 0.8**j * v + 0.2 * (-0.5) ** j * w, np.complex128) for j in range(4)]
    gamma = circledomain._mpe_weights(x)
    assert gamma is not None and gamma.sum() == pytest.approx(1.0)
    limit = sum(g * xj for g, xj in zip(gamma, x[1:], strict=True))
    assert np.max(np.abs(limit - xs)) <= 1e-12


def test_mpe_refuses_a_mode_at_one() -> None:
    # a mode that does not contract (the state drifting by the same step every sweep: a double
    # root at 1): the polynomial's coefficients sum to ~0, no weights
    rng = np.random.default_rng(1)
    xs, v, w = (rng.normal(size=40) + 1j * rng.normal(size=40) for _ in range(3))
    x = [np.asarray(xs + 0.3 * j * v + 0.2 * 0.5**j * w, np.complex128) for j in range(4)]
    assert circledomain._mpe_weights(x) is None


def test_two_modes_take_fewer_sweeps_to_the_same_fixed_point(
    plain: CircleDomainResult, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", 1)
    one = _run(squares(0.03), "extrapolate")
    monkeypatch.setattr(circledomain, "EXTRAPOLATE_MODES", 2)
    two = _run(squares(0.03), "extrapolate")
    assert two.converged and two.extrapolations > 0
    assert two.sweeps <= one.sweeps
    bound = two.iteration_error + plain.iteration_error
    assert np.max(np.abs(two.radii - plain.radii)) <= bound
    assert np.max(np.abs(two.centers - plain.centers)) <= bound
