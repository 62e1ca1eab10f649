"""Koditschek-Rimon navigation function, circle domains, critical points and automatic k."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from confnav.errors import NavigationError
from confnav.navigation.critical import choose_k, find_critical_points
from confnav.navigation.factory import make_navfn
from confnav.navigation.navfn import CircleDomain, KoditschekRimon

# circle domain of the default workspace (docs/METHOD.md section 5)
SEED = CircleDomain(
    np.array([0.4227371 + 0.2466153j, -0.4018952 + 0.2782662j, -0.4826272 - 0.3720324j,
              0.0160941 - 0.3776479j]),
    np.array([0.1420658, 0.1593344, 0.1413721, 0.2170942]),
)  # fmt: skip
# 8 circles on which phi_6 has a spurious minimum (found by random search)
CLUTTER = CircleDomain(
    np.array([0.438 + 0.281j, 0.218 + 0.791j, -0.024 - 0.464j, 0.191 - 0.348j, 0.299 - 0.635j,
              0.535 - 0.512j, -0.616 + 0.484j, -0.126 + 0.783j]),
    np.array([0.093, 0.09, 0.098, 0.093, 0.074, 0.048, 0.078, 0.085]),
)  # fmt: skip


def interior_points(dom: CircleDomain, n: int, margin: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w = rng.uniform(-1, 1, 8 * n) + 1j * rng.uniform(-1, 1, 8 * n)
    return w[dom.clearance(w) > margin][:n]


def fd_gradient(f, w: np.ndarray, h: float = 1e-6) -> np.ndarray:
    return (f(w + h) - f(w - h)) / (2 * h) + 1j * (f(w + 1j * h) - f(w - 1j * h)) / (2 * h)


def boundary_points(dom: CircleDomain, n: int = 200) -> list[np.ndarray]:
    e = np.exp(2j * np.pi * np.arange(n) / n)
    # a hair inside the closed domain (rounding would put exact circle points outside)
    eps = 1e-12
    return [(1 - eps) * e] + [
        c + r * (1 + eps) * e for c, r in zip(dom.centers, dom.radii, strict=True)
    ]


@pytest.mark.parametrize("k", [2.0, 6.0, 20.0])
@pytest.mark.parametrize("goal", [0j, 0.3 + 0.5j, -0.2 - 0.75j])
def test_kr_gradient_matches_finite_differences(k: float, goal: complex) -> None:
    nf = KoditschekRimon(SEED, goal, k)
    w = interior_points(SEED, 400, 1e-3)
    g = nf.gradient(w)
    fd = fd_gradient(nf.value, w)
    # central differences: truncation ~h^2 phi''' and rounding ~eps/h; relative to |g| + floor
    assert_allclose(g, fd, rtol=2e-6, atol=1e-8 * np.max(np.abs(g)))


def test_kr_is_zero_at_goal_one_on_boundary_and_in_between() -> None:
    nf = KoditschekRimon(SEED, 0.1 + 0.2j, 6)
    assert nf.value(0.1 + 0.2j) == 0.0
    assert nf.gradient(0.1 + 0.2j) == 0.0
    from confnav.navigation.navfn import obstacle_function

    for b in boundary_points(SEED):
        # phi = 1 - beta / (k g^k) + O(beta^2): 1 on the circle, beta ~ 1e-12 a hair inside
        beta = obstacle_function(SEED, b)[0]
        g = abs(b - nf.goal) ** 2
        assert np.all(beta > 0)
        assert np.all(np.abs(nf.value(b) - 1.0) <= 1.01 * beta / (6 * g**6) + 1e-15)
    v = nf.value(interior_points(SEED, 2000, 1e-6))
    assert np.all((v > 0) & (v < 1))


def test_kr_nan_outside_the_domain() -> None:
    nf = KoditschekRimon(SEED, 0j, 6)
    phi, g = nf.value_and_gradient(np.array([1.2, SEED.centers[0], 0.5j]))
    assert np.isnan(phi[0]) and np.isnan(phi[1]) and np.isfinite(phi[2])
    assert np.isnan(g[0]) and np.isnan(g[1])


def test_kr_gradient_has_no_cancellation_far_from_goal() -> None:
    # textbook form: grad phi = D^(-1/k) grad g - g D^(-1/k-1) (g^(k-1) grad g + grad beta / k)
    # subtracts nearly equal terms where beta << g^k; ours must stay accurate there.
    nf = KoditschekRimon(SEED, 0j, 20)
    w = np.array([0.95 + 0.0j, -0.1 + 0.93j])
    g = nf.gradient(w)
    h = 1e-7
    ref = fd_gradient(nf.value, w, h)
    assert np.all(np.abs(g) > 0)
    assert_allclose(g, ref, rtol=1e-4)


def test_obstacle_function_matches_product() -> None:
    from confnav.navigation.navfn import obstacle_function

    w = interior_points(SEED, 50, 0.0)
    beta, dbeta = obstacle_function(SEED, w)
    ref = (1 - abs(w) ** 2) * np.prod(abs(w[:, None] - SEED.centers) ** 2 - SEED.radii**2, axis=1)
    assert_allclose(beta, ref, rtol=1e-12)
    fd = fd_gradient(lambda z: obstacle_function(SEED, z)[0], w, 1e-6)
    assert_allclose(dbeta, fd, rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize(
    ("centers", "radii"),
    [
        ([0.5], [0.6]),  # sticks out of the unit disk
        ([0.2, 0.3], [0.1, 0.1]),  # overlap
        ([0.2], [-0.1]),  # negative radius
        ([np.nan], [0.1]),
        ([0.2, 0.3], [0.1]),
    ],
)
def test_circle_domain_rejects_bad_input(centers: list[complex], radii: list[float]) -> None:
    with pytest.raises(NavigationError):
        CircleDomain(np.array(centers, dtype=complex), np.array(radii))


def test_bad_goal_and_k_raise_navigation_error() -> None:
    with pytest.raises(NavigationError, match="not inside"):
        KoditschekRimon(SEED, SEED.centers[1], 6)
    with pytest.raises(NavigationError, match="not inside"):
        KoditschekRimon(SEED, 1.5, 6)
    with pytest.raises(NavigationError, match="not finite"):
        KoditschekRimon(SEED, complex(np.nan, 0), 6)
    for k in (0.5, np.nan, np.inf, -6):
        with pytest.raises(NavigationError, match="k must be"):
            KoditschekRimon(SEED, 0j, k)
    with pytest.raises(NavigationError, match="unknown navigation function"):
        make_navfn("apf", SEED, 0j)
    with pytest.raises(NavigationError, match="'auto'"):
        make_navfn("kr", SEED, 0j, k="big")  # type: ignore[arg-type]


def test_critical_points_of_phi6_on_the_seed_domain() -> None:
    cp = find_critical_points(KoditschekRimon(SEED, 0j, 6))
    assert cp.ok and cp.index_consistent, cp.message
    assert_allclose(cp.minima, [0j], atol=1e-12)
    # one saddle "behind" every circle (on the far side from the goal, off the boundary)
    for c, r in zip(SEED.centers, SEED.radii, strict=True):
        d = np.abs(cp.saddles - c)
        j = np.argmin(d)
        assert r < d[j] < 2 * r
        assert abs(np.angle(cp.saddles[j] / c)) < 0.5


def test_small_k_gives_spurious_minima_and_auto_k_fixes_them() -> None:
    cp2 = find_critical_points(KoditschekRimon(SEED, 0j, 2))
    assert not cp2.ok
    assert cp2.spurious_minima.size >= 1
    assert cp2.index_consistent, cp2.message  # the search still sees everything
    nf = KoditschekRimon(SEED, 0j, 2)
    # a spurious minimum is a true minimum: gradient zero, phi larger around it
    for m in cp2.spurious_minima:
        assert abs(nf.gradient(m)) < 1e-12
        ring = m + 1e-4 * np.exp(2j * np.pi * np.arange(16) / 16)
        assert np.all(nf.value(ring) > nf.value(m))


def test_auto_k_in_clutter() -> None:
    cp6 = find_critical_points(KoditschekRimon(CLUTTER, 0j, 6))
    assert not cp6.ok and cp6.spurious_minima.size == 1, cp6.message
    auto = choose_k(CLUTTER, 0j)
    assert auto.k > 6
    assert auto.critical_points.ok
    assert auto.tried[0][0] == 6.0 and "spurious" in auto.tried[0][1]
    nf = make_navfn("kr", CLUTTER, 0j)  # default k is "auto"
    assert isinstance(nf, KoditschekRimon) and nf.k == auto.k


def test_auto_k_raises_when_nothing_works() -> None:
    with pytest.raises(NavigationError, match="harmonic"):
        choose_k(CLUTTER, 0j, ladder=(2.0,))
