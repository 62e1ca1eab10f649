"""Dense GNK matrices kept complex (``gnk.DENSE_INTERLEAVED``, issue 24): the products, row
sums, corner blocks and solutions equal those of the two real copies (the path before) to
rounding, on a graded L-shaped room (a 270-degree corner) and on a hole's exterior map. Round
7: the parts written into two contiguous real matrices during the assembly
(``gnk.DENSE_SPLIT_ASSEMBLY``, the default) are the complex matrix's bit for bit."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from confnav.conformal import gnk
from confnav.conformal.boundary import graded_polygon
from confnav.conformal.diskmap import exterior_map, interior_map

L_ROOM = np.array([0, 2, 2 + 1j, 1 + 1j, 1 + 2j, 2j]) + 0j


@pytest.fixture(autouse=True)
def _complex_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tests below compare the complex matrix's paths (round 7's split parts: last)."""
    monkeypatch.setattr(gnk, "DENSE_SPLIT_ASSEMBLY", False)


def _operators(
    monkeypatch: pytest.MonkeyPatch, eta: np.ndarray, deta: np.ndarray, A: np.ndarray
) -> tuple[gnk._Operator, gnk._Operator]:
    monkeypatch.setattr(gnk, "DENSE_INTERLEAVED", False)
    split = gnk._Operator(eta, deta, A)
    monkeypatch.setattr(gnk, "DENSE_INTERLEAVED", True)
    kept = gnk._Operator(eta, deta, A)
    return split, kept


@pytest.mark.parametrize("nodes", [24, 96])
def test_interleaved_products_equal_the_real_copies(
    monkeypatch: pytest.MonkeyPatch, nodes: int
) -> None:
    mesh = graded_polygon(L_ROOM, nodes)
    A = mesh.eta - (0.5 + 0.5j)
    split, kept = _operators(monkeypatch, mesh.eta, mesh.deta, A)
    assert kept.K is not None and split.K is None
    assert np.array_equal(split.rowr, kept.rowr) and np.array_equal(split.rowi, kept.rowi)
    x, eps = _products_agree(kept, split, seed=1)
    # exact algebra on top of rounding: (I - N) x = 2x - Im S(x), M's dense part = Re S(x)
    assert np.max(np.abs(kept.I_minus_N(x) - (2 * x - kept.S(x).imag))) <= eps
    labels = mesh.corner_blocks()
    a, b = gnk._CornerBlocks(split, labels), gnk._CornerBlocks(kept, labels)
    for u, v in zip(a.blocks, b.blocks, strict=True):
        assert np.array_equal(u, v)


def _maps_agree_with_the_flag_off_and_on(monkeypatch: pytest.MonkeyPatch, flag: str) -> None:
    """Interior and exterior maps (corner blocks, GMRES to rounding) with ``gnk.<flag>``
    off and on agree to 1e-13: the iterations match and the boundary values are the same
    map."""
    mesh = graded_polygon(L_ROOM, 80)
    hole = mesh.reversed()
    out = {}
    for on in (False, True):
        monkeypatch.setattr(gnk, flag, on)
        f = interior_map(mesh.eta, mesh.deta, 0.5 + 0.5j, rtol=1e-14, corners=mesh.corner_blocks())
        F = exterior_map(hole.eta, hole.deta, 0.5 + 0.5j, rtol=1e-14, corners=hole.corner_blocks())
        out[on] = (f, F)
    for old, new in zip(out[False], out[True], strict=True):
        assert abs(old.gmres_iterations - new.gmres_iterations) <= 1
        assert np.max(np.abs(old.f - new.f)) < 1e-13
        assert abs(old.scale - new.scale) < 1e-13 * old.scale


def test_maps_equal_the_real_copies_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """The interleaved dense path's maps are the path before's (to 1e-13)."""
    _maps_agree_with_the_flag_off_and_on(monkeypatch, "DENSE_INTERLEAVED")


@pytest.mark.parametrize("coincide", [False, True])
def test_coincident_node_scan_only_where_nodes_coincide(
    monkeypatch: pytest.MonkeyPatch, coincide: bool
) -> None:
    """``gnk.ZERO_SCAN_ALWAYS = False`` (round 6) scans a dense matrix for coincident nodes
    only where ``np.unique`` finds some: the same matrix bit for bit as the scan of every
    matrix, on distinct graded nodes and on nodes with an exact duplicate (no mutual term,
    no inf or nan left)."""
    mesh = graded_polygon(L_ROOM, 48)
    eta, deta = mesh.eta.copy(), mesh.deta.copy()
    if coincide:
        eta[5] = eta[4]  # two image nodes merged into one point
        deta[4] = deta[5] = 0.0  # both dead
    A = eta - (0.5 + 0.5j)
    monkeypatch.setattr(gnk, "ZERO_SCAN_ALWAYS", True)
    every = gnk._Operator(eta, deta, A)
    monkeypatch.setattr(gnk, "ZERO_SCAN_ALWAYS", False)
    some = gnk._Operator(eta, deta, A)
    assert every.K is not None and some.K is not None
    assert np.array_equal(every.K, some.K)
    assert np.all(np.isfinite(some.K))


def _products_agree(kept: Any, other: Any, seed: int) -> tuple[np.ndarray, float]:
    """``S``, ``I - N`` and ``M`` of two operators of one mesh agree on a random vector to
    64 roundings of the largest row's absolute sum; returns the vector and that bound."""
    x = np.random.default_rng(seed).standard_normal(kept.n)
    scale = float(np.sum(np.abs(other.Ki) * np.abs(x)[None, :], axis=1).max())
    eps = 64 * np.finfo(float).eps * scale
    assert np.max(np.abs(kept.S(x) - other.S(x))) <= eps
    assert np.max(np.abs(kept.I_minus_N(x) - other.I_minus_N(x))) <= eps
    assert np.max(np.abs(kept.M(x) - other.M(x))) <= eps
    return x, eps


def _room_nodes(coincide: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The L room's graded nodes (61 per side), their derivatives and ``eta - z0``; with
    ``coincide`` two neighbouring nodes made one (a zero-length panel)."""
    mesh = graded_polygon(L_ROOM, 61)
    eta, deta = mesh.eta.copy(), mesh.deta.copy()
    if coincide:
        eta[13] = eta[12]
        deta[12] = deta[13] = 0.0
    return eta, deta, eta - (0.5 + 0.5j)


@pytest.mark.parametrize("coincide", [False, True])
def test_blocked_assembly_equals_whole_matrix_passes(
    monkeypatch: pytest.MonkeyPatch, coincide: bool
) -> None:
    """The dense matrix assembled by blocks of rows (``gnk.ASSEMBLY_BLOCK_BYTES``, round 6)
    equals the whole-matrix passes (0) bit for bit, and so do its row sums, with blocks of 8
    rows (the ends not a multiple) and with coincident nodes."""
    eta, deta, A = _room_nodes(coincide)
    monkeypatch.setattr(gnk, "ASSEMBLY_BLOCK_BYTES", 0)
    monkeypatch.setattr(gnk, "ZERO_SCAN_ALWAYS", True)
    whole = gnk._Operator(eta, deta, A)
    monkeypatch.setattr(gnk, "ASSEMBLY_BLOCK_BYTES", 1)  # 8 rows per block
    monkeypatch.setattr(gnk, "ZERO_SCAN_ALWAYS", False)
    blocked = gnk._Operator(eta, deta, A)
    assert whole.K is not None and blocked.K is not None and eta.size % 8 != 0
    assert np.array_equal(whole.K, blocked.K)
    assert np.array_equal(whole.rowr, blocked.rowr) and np.array_equal(whole.rowi, blocked.rowi)
    assert np.all(np.isfinite(blocked.K))


@pytest.mark.parametrize(("coincide", "block"), [(False, 1 << 22), (True, 1)])
def test_split_assembly_writes_the_complex_matrix_parts_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch, coincide: bool, block: int
) -> None:
    """Round 7 (``gnk.DENSE_SPLIT_ASSEMBLY``): the real and imaginary parts written block by
    block are the complex matrix's bit for bit (one block, and blocks of 8 rows with the end
    not a multiple; with coincident nodes), and so are the row sums and corner blocks; the
    products agree to rounding."""
    eta, deta, A = _room_nodes(coincide)
    monkeypatch.setattr(gnk, "ASSEMBLY_BLOCK_BYTES", block)
    kept = gnk._Operator(eta, deta, A)
    monkeypatch.setattr(gnk, "DENSE_SPLIT_ASSEMBLY", True)
    parts = gnk._Operator(eta, deta, A)
    assert kept.K is not None and parts.K is None
    assert parts.Kr.flags.c_contiguous and parts.Ki.flags.c_contiguous
    assert np.array_equal(kept.K.real, parts.Kr) and np.array_equal(kept.K.imag, parts.Ki)
    assert np.array_equal(kept.rowr, parts.rowr) and np.array_equal(kept.rowi, parts.rowi)
    assert np.all(np.isfinite(parts.Kr)) and np.all(np.isfinite(parts.Ki))
    _products_agree(kept, parts, seed=2)
    labels = graded_polygon(L_ROOM, 61).corner_blocks()
    a, b = gnk._CornerBlocks(kept, labels), gnk._CornerBlocks(parts, labels)
    for u, v in zip(a.blocks, b.blocks, strict=True):
        assert np.array_equal(u, v)


def test_maps_of_the_split_assembly_equal_the_complex_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    """The maps from the split parts are those from the complex matrix (to 1e-13)."""
    _maps_agree_with_the_flag_off_and_on(monkeypatch, "DENSE_SPLIT_ASSEMBLY")
