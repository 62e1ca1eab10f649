"""Regression cases for the Koebe solver found by the property test (issue 8, item 5).

Needle-like tips: with too few nodes on the sides of a sharp corner the discrete GNK operator
``I - N`` gets a spurious eigenvalue near 0 and its "solution" is meaningless (the first map
of a 24.7-degree triangle sent the outer square inside the unit disk). See
confnav.conformal.meshing (sharp-corner node rule) and circledomain._check_images.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import confnav
from confnav import Workspace
from confnav.conformal import gnk
from confnav.conformal.boundary import graded_polygon
from confnav.conformal.gnk import gmres_rtol
from confnav.conformal.meshing import sharp_corner_nodes
from confnav.errors import SolverError

SQUARE = [[-1, -1], [1, -1], [1, 1], [-1, 1]]

#: Convex triangles 0.1875..0.25 from the walls (tip 24.7 / 22.6 degrees): MUST solve to 1e-7.
TRIANGLES = [
    [(-0.609375, -0.75), (-0.390625, -0.75), (-0.5, -0.25)],
    [(-0.609375, -0.8125), (-0.390625, -0.8125), (-0.5, -0.1875)],
    [(-0.59375, -0.8125), (-0.40625, -0.8125), (-0.5, -0.1875)],
]


def _smallest_eigenvalue(vertices: np.ndarray, nodes: int | np.ndarray) -> float:
    """Smallest |eigenvalue| of the discrete exterior-map operator I - N (A = 1) of a hole."""
    mesh = graded_polygon(vertices, nodes).reversed()
    op = gnk._Operator(mesh.eta, mesh.deta, np.ones_like(mesh.eta))
    mat = np.column_stack([op.I_minus_N(e) for e in np.eye(mesh.n)])
    return float(np.min(np.abs(np.linalg.eigvals(mat))))


def test_the_defect_was_a_spurious_eigenvalue_and_the_node_rule_removes_it() -> None:
    """The cause, pinned: 29 nodes per side on the 24.7-degree triangle put an eigenvalue of the
    discrete I - N at 7e-4 (the exact operator's spectrum starts at theta/pi = 0.137); the
    sharp-corner rule's node counts keep it near theta/pi."""
    tri = np.array([complex(*v) for v in TRIANGLES[0]])
    assert _smallest_eigenvalue(tri, 29) < 2e-3
    rule = sharp_corner_nodes(tri)
    assert rule.max() >= 32
    for extra in (0, 3, 8):
        assert _smallest_eigenvalue(tri, rule + extra) > 0.03


@pytest.mark.parametrize("tri", TRIANGLES)
def test_single_convex_triangle_solves(tri: list[tuple[float, float]]) -> None:
    cm = confnav.solve(Workspace(SQUARE, [tri]), tol=1e-7)
    d = cm.diagnostics
    assert d.tol_met and d.error_estimate <= 1e-7
    assert d.boundary_residual <= 1e-7
    assert d.circularity <= 1e-7
    # the anchor's image is a Cauchy sum of boundary values solved to the GMRES residual
    # gmres_rtol(1e-7) = 1e-10: it is 0 to that accuracy (measured 9e-13 from a zero first
    # guess, 1.2e-12 from the previous level's solution; it was asserted below 1e-12 before
    # the first guesses, a margin the GMRES tolerance never promised)
    assert abs(complex(cm.T(cm.workspace.anchor))) < gmres_rtol(1e-7)


def test_a_fixed_coarse_mesh_on_a_sharp_tip_is_never_silently_wrong() -> None:
    """At 24 nodes per side the two levels agree (2e-7) while both are wrong: the boundary
    residual sees it, and the map is refused instead of returned."""
    with pytest.raises(SolverError, match="boundary residual"):
        confnav.solve(Workspace(SQUARE, [TRIANGLES[0]]), tol=1e-7, nodes_per_side=24)


@pytest.mark.parametrize("tip_degrees", [10, 15, 20, 25, 30])
def test_thin_mirror_symmetric_triangles(tip_degrees: float) -> None:
    """Isosceles triangles with tips of 10-30 degrees on the mirror axis of the square, anchor on
    the axis: the circle's centre must lie on the axis (exact), to within the estimate."""
    w = 0.5 * np.tan(np.radians(tip_degrees) / 2)
    ws = Workspace(SQUARE, [[(-w, -0.75), (w, -0.75), (0, -0.25)]], anchor=[0, 0.5])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an AccuracyWarning fails the test
        cm = confnav.solve(ws, tol=1e-6)
    d = cm.diagnostics
    assert d.tol_met and d.boundary_residual <= 1e-6
    assert abs(cm.centers[0].real) <= max(d.error_estimate, 1e-14)
    assert 0 < cm.radii[0] < 0.2


def test_nodes_merged_by_rounding_are_one_source() -> None:
    """Live nodes closer than MERGED_NODE_ULPS ulps of the previous live node (cyclically) are
    dropped as sources, one node of each merged group stays."""
    eta = np.exp(1j * np.linspace(0, 2 * np.pi, 12, endpoint=False)) * 3.0
    eta[5] = eta[4] + 1e-16  # merged with its predecessor
    eta[11] = eta[0]  # merged across the start of the curve
    deta = 1j * eta
    alive = gnk.alive_nodes(eta, deta)
    assert alive.sum() == 10 and alive[4] and not alive[5]
    assert alive[0] != alive[11]
    distinct = eta.copy()
    distinct[5] = eta[4] + 1e-12  # 1e-12 apart: far above rounding, both stay
    distinct[11] = eta[11] * np.exp(0.3j)
    assert gnk.alive_nodes(distinct, 1j * distinct).all()


def test_inflated_default_workspace_solves_at_384_nodes_per_side() -> None:
    """The default workspace shrunk by a robot radius of 0.08 (``confnav demo``'s unicycle):
    at 384 nodes per side graded nodes on the two sides of a corner of obstacle 3 merge in
    floating point under its exterior map's inversion. That level ran GMRES on NaN to its
    iteration limit (50 s) and failed, leaving the map 1.1e-10 short of tol 1e-10."""
    ws = confnav.inflate(confnav.default_workspace(), 0.08)
    with warnings.catch_warnings():
        warnings.simplefilter("error", confnav.AccuracyWarning)
        cmap = confnav.solve(ws, tol=1e-10, nodes_per_side=384)
    rep = cmap.diagnostics
    assert rep.nodes_per_side == 384 and rep.tol_met
    assert rep.boundary_residual <= 1e-10 and rep.error_estimate <= 1e-10


def test_a_crowded_room_behind_a_narrow_door_is_a_crowding_error() -> None:
    """Two rooms joined by a 0.8 m door, shrunk by a 0.3 m footprint: the door becomes a
    0.2 x 0.75 m channel and the far room, obstacle included, is crowded to within 4e-6 of the
    circle. Every level failed alike with a message blaming sharp corners (40 s for six
    levels); now the second alike level ends it with a CrowdingError that says what to do."""
    door = Path(__file__).resolve().parents[1] / "bench" / "scenes" / "door.json"
    ws = confnav.inflate(confnav.Workspace.load(door), 0.3, keep=complex(11.2, 4.3))
    levels: list[str] = []
    with pytest.raises(confnav.CrowdingError, match=r"narrow passage.*atlas") as err:
        confnav.solve(ws, progress=lambda m: levels.append(m) if "nodes per side at" in m else 0)
    assert isinstance(err.value, confnav.UnresolvedCrowdingError)
    assert len(levels) == 2


def test_a_graded_smooth_grid_resolves_its_own_pole() -> None:
    """A smooth grid graded by phi(z) = (z + c)/(1 + conj(c) z) is S(s) = phi(e^{is}), whose
    Fourier coefficients are exactly |c|^j (phi has a pole at -1/conj(c)). The outer
    boundary's grid laid towards a small circle 0.0135 inside it (near_touching shrunk by 0.3
    after one sweep) took |c| = 0.95 and 256 points: tail 3.4e-3, far above the 1e-14 it had to
    reach, and that under-resolved sweep moved the circle domain for good."""
    from confnav.conformal.circledomain import _Boundary, _tail

    hole = (1.0 - 0.0135 - 0.062) * np.exp(2.3j) + 0.062 * np.exp(
        1j * np.linspace(0, 2 * np.pi, 400, endpoint=False)
    )
    none = np.zeros(1, complex)
    b = _Boundary(P=none, dP=none, mask=np.ones(1, bool), hole=False)
    b.tail = 1e-14
    b.regrid(hole)
    assert b.S is not None
    rho = abs(b.c)
    assert rho ** (b.S.size / 2) <= b.tail  # the exact decay at the Nyquist mode
    assert _tail(b.S) <= b.tail


def test_near_touching_shrunk_by_a_diff_drive_footprint_is_circular_between_nodes() -> None:
    """near_touching shrunk as ``confnav simulate --robot-radius 0.2 --unicycle 0.1`` shrinks it
    (0.3: the cabinets and the table merge into the walls, the triangle stays, crowded behind a
    bend): the map was refused with a boundary residual of 1e-4 on the triangle while the mesh
    levels agreed to 3e-13 (an under-resolved smooth grid of the outer boundary in the early
    sweeps, alike at every level). Checked independently of the solver's own residual: T on 64
    points of every side, between the nodes, must lie on its circle to the requested tol."""
    scene = Path(__file__).resolve().parents[1] / "bench" / "scenes" / "near_touching.json"
    starts = [0.4 + 0.4j, 0.4 + 2.5j, 3.5 + 1.5j, 2.5 + 2.6j, 5.6 + 1.5j]
    ws = confnav.inflate(
        confnav.Workspace.load(scene),
        0.2 + 0.1,
        keep=5.5 + 3.5j,
        require={f"start {k}": z for k, z in enumerate(starts)},
        mitre_limit=5.0,  # the footprint's mitre limit when the report was made
    )
    assert ws.n_obstacles == 1 and len(ws.boundaries[1]) == 3  # the merged scene of the report
    tol = 1e-10
    with warnings.catch_warnings():
        warnings.simplefilter("error", confnav.AccuracyWarning)
        cm = confnav.solve(ws, tol=tol)
    d = cm.diagnostics
    assert d.tol_met and d.boundary_residual <= tol and d.error_estimate <= tol
    frac = (np.arange(64) + 0.5) / 64
    centres = np.concatenate([[0j], cm.centers])
    radii = np.concatenate([[1.0], cm.radii])
    for j, v in enumerate(ws.boundaries):
        z = (v[:, None] + np.outer(np.roll(v, -1) - v, frac)).ravel()
        w = cm.T(z, check=False)
        assert np.max(np.abs(np.abs(w - centres[j]) - radii[j])) <= tol, j
    assert abs(complex(cm.T(ws.anchor))) <= 1e-12


def test_an_under_resolved_smooth_grid_is_reported_not_hidden(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The same scene with the outer grid forced back to the old over-optimistic grading (rho
    0.95, 256 points): the tail of the grid solved on (0.95^128 ~ 1e-3) must reach
    ``resolution_error``, even though the iteration later doubles the grid to resolution."""
    from confnav.conformal import circledomain, solver

    scene = Path(__file__).resolve().parents[1] / "bench" / "scenes" / "near_touching.json"
    ws = confnav.inflate(confnav.Workspace.load(scene), 0.3, keep=5.5 + 3.5j)

    grading = circledomain._grading

    def old_grading(others: np.ndarray) -> tuple[complex, float]:
        if np.any(np.abs(others) > 1.0):  # a hole's grid (the outer curve is around it)
            return grading(others)
        k = int(np.argmin(np.abs(np.abs(others) - 1.0)))
        return complex(0.95 * others[k] / abs(others[k])), 0.4

    monkeypatch.setattr(circledomain, "_grading", old_grading)
    res = solver._solve_level(ws, 80, 1e-10, None)[0]
    assert res.resolution_error >= 1e-4
    assert max(res.smooth_nodes) >= 1024  # it did refine, too late for the early sweeps
