"""Local expansions of the Cauchy sums (confnav/conformal/expansion.py) against exact answers.

Exact references: the trapezoidal Cauchy sum of the unit circle has the closed form
``sum_k (2pi/n) i w^k/(w^k - z) = 2 pi i/(1 - z^n)`` (w = e^(2 pi i/n); expand in z); for
the solved map, the barycentric formula summed directly in extended precision (long double).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from confnav.conformal.cmap import ConformalMap
from confnav.conformal.expansion import LocalExpansions
from confnav.navigation.control import Controller


def _circle(n: int) -> tuple[np.ndarray, np.ndarray]:
    eta = np.exp(2j * np.pi * np.arange(n) / n)
    return eta, (2 * np.pi / n) * 1j * eta  # q = w eta'


def _sums_longdouble(
    eta: np.ndarray, q: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """sum q/(eta - z) and sum q/(eta - z)^2 in extended precision (long double)."""
    r = 1 / (eta.astype(np.clongdouble)[None, :] - z.astype(np.clongdouble)[:, None])
    ql = q.astype(np.clongdouble)
    return (r @ ql).astype(np.complex128), ((r * r) @ ql).astype(np.complex128)


def test_circle_sum_matches_closed_form_up_to_the_wall() -> None:
    n = 200
    eta, q = _circle(n)
    ex = LocalExpansions(eta, q[:, None], degree=48, separation=0.4, max_level=8)
    rng = np.random.default_rng(0)
    r = 1 - np.geomspace(0.5, 1e-4, 4000)
    z = r * np.exp(2j * np.pi * rng.random(r.size))
    covered, S, dS = ex.sums(z)
    zl = z.astype(np.clongdouble)  # z^n near |z| = 1 needs more than double precision
    exact = (2j * np.pi / (1 - zl**n)).astype(np.complex128)
    dexact = (2j * np.pi * n * zl ** (n - 1) / (1 - zl**n) ** 2).astype(np.complex128)
    # the nodes are e^(2 pi i k/n) rounded to double, which alone moves the sum by up to
    # ~3e-13 at 1e-4 from the wall: the reference is the sum over the stored nodes in long
    # double, itself checked against the closed form where the expansions cover
    ref, dref = _sums_longdouble(eta, q, z)
    # a point is covered once its finest box is R/separation from every node: all points
    # 2.5 finest boxes (R = h/sqrt 2, 1/0.4 + 1 = 3.5 R) from the nodes are
    dist = np.abs(z[:, None] - eta[None, :]).min(axis=1)
    assert covered[dist >= 2.5 * ex.stats.finest_box].all()
    assert 0.4 < covered.mean() < 1  # the points crowd the wall geometrically
    c = covered
    assert np.max(np.abs(ref[c] - exact[c])) <= 1e-12
    assert np.max(np.abs(dref[c] - dexact[c]) / (1 + np.abs(dexact[c]))) <= 1e-12
    assert np.max(np.abs(S[c, 0] - ref[c])) <= 1e-13  # |S| ~ 2 pi: ~1e-14 relative
    assert np.max(np.abs(dS[c, 0] - dref[c]) / (1 + np.abs(dref[c]))) <= 1e-12
    # the recorded truncation bound is what makes this hold
    assert ex.stats.max_bound <= 1e-15 and ex.stats.max_bound_derivative <= 1e-13
    # nodes closer than the expansions reach: the points are reported as not covered
    assert not ex.sums(eta[:5] * (1 - 1e-6))[0].any()
    # outside the tree's square: not covered, no exception
    assert not ex.sums(np.array([5 + 5j, np.nan]))[0].any()


def test_degree_and_separation_trade_accuracy() -> None:
    eta, q = _circle(300)
    loose = LocalExpansions(eta, q[:, None], degree=8, separation=0.5, max_level=6)
    tight = LocalExpansions(eta, q[:, None], degree=48, separation=0.4, max_level=6)
    z = 0.5 * np.exp(2j * np.pi * np.linspace(0, 1, 50))
    exact = 2j * np.pi / (1 - z**300)  # |z| = 0.5: z^300 underflows harmlessly
    e_loose = np.max(np.abs(loose.sums(z)[1][:, 0] - exact))
    e_tight = np.max(np.abs(tight.sums(z)[1][:, 0] - exact))
    assert e_tight <= 1e-13 < e_loose <= loose.stats.max_bound  # the bound is a bound
    with pytest.raises(ValueError):
        LocalExpansions(eta, q[:, None], separation=1.5)


@pytest.fixture(scope="module")
def nav_map() -> ConformalMap:
    import confnav
    from confnav.scenes.workspaces import default_workspace

    return confnav.solve(default_workspace(), tol=1e-8).for_navigation()


def _direct_longdouble(m: ConformalMap, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The barycentric T and T' summed in extended precision (the reference)."""
    eta = m._eta.astype(np.clongdouble)
    q = m._Q_fwd.astype(np.clongdouble)
    R = 1 / (eta[None, :] - z.astype(np.clongdouble)[:, None])
    S = R @ q
    S2 = (R * R) @ q
    T = S[:, 0] / S[:, 1]
    dT = (S2[:, 0] * S[:, 1] - S[:, 0] * S2[:, 1]) / S[:, 1] ** 2
    return T.astype(np.complex128), dT.astype(np.complex128)


def _test_points(m: ConformalMap) -> dict[str, np.ndarray]:
    ws = m.workspace
    rng = np.random.default_rng(3)
    z = rng.uniform(-2, 2, 3000) + 1j * rng.uniform(-2, 2, 3000)
    z = z[ws.contains(z)]
    clear = ws.clearance(z)
    verts = np.concatenate([ws.outer, *ws.obstacles])
    near_corner = (
        verts[:, None] + np.array([1e-3, 1e-2, 5e-2]) * np.exp(2j * np.pi * 0.13)
    ).ravel()
    near_corner = np.concatenate(
        [near_corner, (verts[:, None] + 0.03 * np.exp(2j * np.pi * rng.random((1, 8)))).ravel()]
    )
    near_corner = near_corner[ws.contains(near_corner)]
    return {
        "random": z[:600],
        "near walls": z[(clear < 0.06)][:400],
        "near corners": near_corner,
        "default starts": np.array([1.5 + 1j, -1.5 + 1j, -1 - 1.5j, 0.05 - 1.5j, 0j]),
    }


def test_map_through_expansions_matches_direct_formula(nav_map: ConformalMap) -> None:
    m = nav_map
    pts = _test_points(m)
    allz = np.concatenate(list(pts.values()))
    w, dw = m.T_and_dT(allz)
    ex = m._expansion
    assert ex is not None  # a navigation map evaluates through the expansions
    assert ex.stats.max_bound <= 1e-15 and ex.stats.max_bound_derivative <= 1e-13
    covered = ex.sums(allz)[0]
    n_random = pts["random"].size
    assert covered[:n_random].mean() > 0.9  # most of the free space is covered
    assert not covered.all()  # and the walls' band is evaluated directly: both paths run
    ref, dref = _direct_longdouble(m, allz)
    direct = ConformalMap.from_dict(m.to_dict())  # same nodes, direct formula only
    wd, dwd = np.full_like(w, np.nan), np.full_like(w, np.nan)
    wd[~covered], dwd[~covered] = direct.T_and_dT(allz[~covered])  # the same sub-batch
    assert direct._expansion is None
    start = 0
    for name, z in pts.items():
        sl = slice(start, start + z.size)
        start += z.size
        c = covered[sl]
        assert np.all(np.isfinite(w[sl])), name
        # covered points: within 1e-12 of the extended-precision sum (T absolute, T' relative)
        assert np.max(np.abs(w[sl][c] - ref[sl][c]), initial=0) <= 1e-12, name
        rel = np.abs(dw[sl][c] - dref[sl][c]) / np.abs(dref[sl][c])
        assert np.max(rel, initial=0) <= 1e-12, (name, np.max(rel))
        # the others: the direct formula (whose own error in a pocket reaches ~1e-12 in T')
        np.testing.assert_array_equal(w[sl][~c], wd[sl][~c])
        np.testing.assert_array_equal(dw[sl][~c], dwd[sl][~c])


def test_controller_commands_unchanged(nav_map: ConformalMap) -> None:
    """The control step through the expansions equals the one from the direct formula."""
    direct = ConformalMap.from_dict(nav_map.to_dict())  # same nodes, no expansions
    assert not direct._fast
    z = _test_points(nav_map)["random"][:200]
    for navfn in ("kr", "harmonic"):
        a = Controller(nav_map, 0j, navfn=navfn, k=6)(z)
        b = Controller(direct, 0j, navfn=navfn, k=6)(z)
        assert direct._expansion is None
        np.testing.assert_array_equal(a.status, b.status)
        assert np.max(np.abs(a.u - b.u) / np.maximum(np.abs(b.u), 1e-300)) <= 1e-10


def test_large_batch_builds_expansions_on_any_map(nav_map: ConformalMap, monkeypatch: Any) -> None:
    import confnav.conformal.cmap as cm

    m = ConformalMap.from_dict(nav_map.to_dict())
    z = _test_points(nav_map)["random"][:300]
    m.T_and_dT(z[:2])
    assert m._expansion is None  # small batches of an ordinary map: direct
    monkeypatch.setattr(cm, "EXPANSION_MIN_POINTS", 100)
    w, dw = m.T_and_dT(z)
    assert m._expansion is not None
    c = m._expansion.sums(z)[0]
    assert c.mean() > 0.9
    ref, dref = _direct_longdouble(m, z)
    assert np.max(np.abs(w[c] - ref[c])) <= 1e-12
    assert np.max(np.abs(dw[c] - dref[c]) / np.abs(dref[c])) <= 1e-12


def test_single_point_path_equals_the_batch_path(
    nav_map: ConformalMap, monkeypatch: pytest.MonkeyPatch
) -> None:
    import confnav.conformal.cmap as cm

    ex = nav_map._expansion or LocalExpansions(nav_map._eta, nav_map._Q_fwd)
    pts = _test_points(nav_map)
    z = np.concatenate([pts["random"][:20], pts["near walls"][:20], [9 + 9j]])
    cov, S, dS = ex.sums(z)
    assert cov.any() and not cov.all()
    for k in range(z.size):
        c1, S1, dS1 = ex.sums(z[k : k + 1])
        assert c1[0] == cov[k]
        if cov[k]:
            # same polynomial, powers by np.power instead of cumprod: rounding only
            # (D' ~ 0 in the free space: absolute against the sums' size)
            np.testing.assert_allclose(S1[0], S[k], rtol=0, atol=1e-14 * np.abs(S[k]).max())
            np.testing.assert_allclose(dS1[0], dS[k], rtol=0, atol=1e-13 * np.abs(dS[k]).max())
        else:
            assert np.isnan(S1[0]).all()
    # a single robot through the map on the expansion path (as on a map with many nodes)
    monkeypatch.setattr(cm, "EXPANSION_SINGLE_NODES", 0)
    ref, dref = _direct_longdouble(nav_map, z[:40])
    for k in np.flatnonzero(cov[:40]):  # (the others take the direct formula)
        w, dw = nav_map.T_and_dT(z[k])
        assert abs(w - ref[k]) <= 1e-12 and abs(dw - dref[k]) <= 1e-12 * abs(dref[k])
