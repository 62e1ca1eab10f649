"""The corner-block right preconditioner of the graded GNK solves (issue 24): exact answers,
the same solution as plain GMRES, its blocks equal on the dense and the FMM path, and fewer
GMRES iterations (counted, not timed)."""

from __future__ import annotations

import numpy as np
import pytest

from confnav.conformal import cauchy, gnk
from confnav.conformal.boundary import graded_polygon
from confnav.conformal.diskmap import exterior_map, interior_map

SQUARE = np.array([-1 - 1j, 1 - 1j, 1 + 1j, -1 + 1j])
#: An L-shaped room: a 270-degree corner, the kind that costs GMRES most.
L_ROOM = np.array([0, 2, 2 + 1j, 1 + 1j, 1 + 2j, 2j]) + 0j


def test_corner_blocks_partition_the_nodes_near_each_vertex() -> None:
    """Labels: the first quarter of side s belongs to vertex s, the last to vertex s + 1, the
    rest to none; reversing the mesh keeps every node's label."""
    mesh = graded_polygon(SQUARE, 40)
    lab = mesh.corner_blocks()
    first = mesh.tau < np.pi / 2
    last = mesh.tau > 3 * np.pi / 2
    assert np.array_equal(lab[first], mesh.side[first])
    assert np.array_equal(lab[last], (mesh.side[last] + 1) % 4)
    assert np.all(lab[~(first | last)] == -1)
    # tau = 2pi i/40: i < 10 on the first vertex side, i > 30 on the last
    assert np.array_equal(np.bincount(lab[lab >= 0]), [19, 19, 19, 19])
    rev = mesh.reversed()
    idx = (-np.arange(mesh.n)) % mesh.n
    assert np.array_equal(rev.corner_blocks(), lab[idx])


def test_square_conformal_radius_and_capacity_are_exact_with_the_preconditioner() -> None:
    """f'(0) = Gamma(1/4)^2/(8 sqrt(pi)) for the square [-1, 1]^2 (Schwarz-Christoffel) and
    its capacity Gamma(1/4)^2/(2 pi^(3/2)), with corner blocks and fewer iterations."""
    mesh = graded_polygon(SQUARE, 160)
    f = interior_map(mesh.eta, mesh.deta, 0j, rtol=1e-14, corners=mesh.corner_blocks())
    plain = interior_map(mesh.eta, mesh.deta, 0j, rtol=1e-14)
    assert abs(f.scale - 0.9270373386506859) < 1e-11
    assert f.gmres_iterations < plain.gmres_iterations
    hole = mesh.reversed()
    F = exterior_map(hole.eta, hole.deta, 0j, rtol=1e-14, corners=hole.corner_blocks())
    assert abs(1 / F.scale - 1.1803405990160960) < 1e-10


@pytest.mark.parametrize("nodes", [48, 120])
def test_preconditioned_solution_is_the_plain_one(nodes: int) -> None:
    """The same discrete equation solved both ways: mu, h and the map agree to the GMRES
    tolerance's level; the preconditioned run needs at most two thirds of the iterations on an
    L-shaped room (a 270-degree corner)."""
    mesh = graded_polygon(L_ROOM, nodes)
    alpha = 0.5 + 0.5j
    A = mesh.eta - alpha
    gamma = -np.log(np.abs(A))
    plain = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-14)
    pre = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-14, corners=mesh.corner_blocks())
    assert np.max(np.abs(pre.mu - plain.mu)) < 1e-11
    assert abs(pre.h - plain.h) < 1e-12
    assert 3 * pre.iterations <= 2 * plain.iterations
    # the residual it reports is the true one of the unpreconditioned equation
    op = gnk._Operator(mesh.eta, mesh.deta, A)
    true = float(np.linalg.norm(op.I_minus_N(pre.mu) + op.M(gamma)))
    assert true <= 1.5 * pre.residual


def test_first_guess_is_used_through_the_preconditioner() -> None:
    """x0 = the solution itself: GMRES has nothing left to do (0 or 1 iterations)."""
    mesh = graded_polygon(L_ROOM, 64)
    A = mesh.eta - (0.5 + 0.5j)
    gamma = -np.log(np.abs(A))
    sol = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-12, corners=mesh.corner_blocks())
    again = gnk.solve_gnk(
        mesh.eta, mesh.deta, A, gamma, rtol=1e-12, x0=sol.mu, corners=mesh.corner_blocks()
    )
    assert again.iterations <= 1
    assert np.max(np.abs(again.mu - sol.mu)) < 1e-10


def test_blocks_are_the_operator_restricted_to_them() -> None:
    """Each block is (I - N) on its nodes (dense matrix column by column), and P^-1 P = I."""
    mesh = graded_polygon(L_ROOM, 32)
    A = mesh.eta - (0.5 + 0.5j)
    op = gnk._Operator(mesh.eta, mesh.deta, A)
    n = mesh.n
    full = np.column_stack([op.I_minus_N(e) for e in np.eye(n)])
    pc = gnk._CornerBlocks(op, mesh.corner_blocks())
    for idx, B in zip(pc.groups, pc.blocks, strict=True):
        np.testing.assert_allclose(B, full[np.ix_(idx, idx)], rtol=0, atol=1e-13)
    np.testing.assert_allclose(pc.diag, np.diag(full)[pc.single], rtol=0, atol=1e-13)
    x = np.random.default_rng(1).standard_normal(n)
    np.testing.assert_allclose(pc.solve(pc.apply(x)), x, rtol=0, atol=1e-12)


@pytest.mark.skipif(not cauchy.HAVE_FMM, reason="pyfmmlib not available")
def test_matrix_free_blocks_equal_the_dense_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the FMM path the blocks are built from the kernel directly and the row sums from
    the FMM: the same blocks as the dense path's to 1e-12, the same solution."""
    mesh = graded_polygon(L_ROOM, 48)
    A = mesh.eta - (0.5 + 0.5j)
    gamma = -np.log(np.abs(A))
    lab = mesh.corner_blocks()
    dense_op = gnk._Operator(mesh.eta, mesh.deta, A)
    dense = gnk._CornerBlocks(dense_op, lab)
    dense_sol = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-14, corners=lab)
    monkeypatch.setattr(gnk, "DENSE_MAX_NODES", 0)
    monkeypatch.setattr(cauchy, "FMM_THRESHOLD", 1000)
    free_op = gnk._Operator(mesh.eta, mesh.deta, A)
    assert not free_op.dense
    free = gnk._CornerBlocks(free_op, lab)
    for Bd, Bf in zip(dense.blocks, free.blocks, strict=True):
        np.testing.assert_allclose(Bf, Bd, rtol=0, atol=1e-12)
    np.testing.assert_allclose(free.diag, dense.diag, rtol=0, atol=1e-12)
    free_sol = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-14, corners=lab)
    assert np.max(np.abs(free_sol.mu - dense_sol.mu)) < 1e-11


def test_a_singular_block_or_a_failed_run_falls_back_to_plain_gmres(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """No block inverse (LinAlgError), or a preconditioned run that cannot converge (NaN
    products): the solve is the plain one, not an error."""
    mesh = graded_polygon(L_ROOM, 48)
    A = mesh.eta - (0.5 + 0.5j)
    gamma = -np.log(np.abs(A))
    plain = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-13)
    lab = mesh.corner_blocks()

    def singular(_: np.ndarray) -> np.ndarray:
        raise np.linalg.LinAlgError("singular")

    with monkeypatch.context() as mp:
        mp.setattr(gnk.np.linalg, "inv", singular)
        assert gnk._CornerBlocks.build(gnk._Operator(mesh.eta, mesh.deta, A), lab) is None
        sol = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-13, corners=lab)
        assert sol.iterations == plain.iterations
        np.testing.assert_array_equal(sol.mu, plain.mu)
    with monkeypatch.context() as mp:
        mp.setattr(gnk._CornerBlocks, "solve", lambda self, y: np.full_like(y, np.nan))
        sol = gnk.solve_gnk(mesh.eta, mesh.deta, A, gamma, rtol=1e-13, corners=lab)
        np.testing.assert_array_equal(sol.mu, plain.mu)
