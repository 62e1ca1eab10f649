"""Newton steps on the whole circle domain after a few Koebe sweeps (``solve(method="nasser")``).

What Nasser's method is (read before coding). The issue (24, item 1) names "Nasser's method with
one generalized-Neumann-kernel system over all boundaries per step". Nasser's own implementation
of "Fast computation of the circular map" ([1]; ``pcm/cirmapb.m`` of PlgCirMap [2], read for
this module) is *not* that: it is Koebe's iteration, one GNK solve per boundary (the exterior
map of hole k, then the interior map of the outer boundary), the other boundaries moved by
Cauchy integrals -- the sweep :func:`confnav.conformal.circledomain.koebe_iteration` already
implements (with smooth regridding, which PlgCirMap does not do). Its cost per sweep is
``O(m^2 n + m n log n)`` with the FMM, but its *number* of sweeps is Koebe's, ~ rho^-1 with
rho -> 1 as circles approach ([1], sec. 5: the close-to-touching example needs many more
iterations). So a port would add nothing; what is built here is the issue's other candidate,
a Newton iteration on the circle domain, using all boundaries in one linear system per step.

The Newton step. After a few Koebe sweeps every boundary image ``Gamma_j`` is an analytic curve
close to a circle ``|z - c_j| = r_j`` (outer: ``c_0 = 0, r_0 = 1``). Seek one map
``Phi(z) = z + g(z)``, ``g`` analytic in the current domain with ``g(0) = 0`` (the anchor stays
at 0), that makes every boundary circular to first order: at ``z = c_j + rho e^{i theta}`` on
``Gamma_j`` the distance from the new centre ``c_j + s_j`` is, to first order in ``g``,

    rho + Re[(g(z) - s_j) e^{-i theta}] = r_j + d_j,                 (linearised circle condition)

with unknown centre shifts ``s_j`` (``s_0 = 0``) and radius changes ``d_j``. This is the
linearisation of the circle-domain conditions used by Wegmann's Newton-type method
(R. Wegmann [3]) and by the least-squares circle fits of Trefethen's series method [4]; here
``g`` is a truncated Laurent/Taylor series, one expansion per boundary,

    g(z) = sum_{k=1}^{K_0} a_k z^k + sum_{j>=1} sum_{k=1}^{K_j} b_{jk} (r_j / (z - c_j))^k,

analytic in the domain (every pole ``c_j`` inside hole j), with ``Im a_1 = 0`` (the rotation is
fixed by ``Phi'(0) > 0``). All boundaries' conditions are fitted at once by weighted least
squares (arc-length weights) in the passive nodes; ``Phi`` is then applied *exactly* to every
node and to its derivative (``dW <- Phi'(W) dW``), so the nodes stay images of the
polygon's nodes under one analytic map and their defect is second order in the step:
quadratic convergence while the series resolve ``g``. (Unlike the sweeps' maps, which are
solved by the GNK on the grids they move, the fitted ``g`` is only constrained *at* the
nodes: see "Measured".)
Each step rescales by the outer radius (``W <- W / R_0``) and multiplies ``Phi'(0)`` into
the anchor derivative.

Safeguards: a step that does not shrink the defect (largest distance of a node from its
boundary's circle), or a step whose dense least-squares problem would exceed
:data:`MAX_UNKNOWNS`, ends the Newton phase; if no step met the tolerance the Koebe sweeps run
the level to the tolerance from the polygon instead (the result then *is* the sweeps' result,
the cost of the Newton attempt included). The reported iteration error of a Newton-finished
level is the largest of the geometric tail ``h rho / (1 - rho)`` of the last two step sizes,
the circularity and the error of the sweeps' state Newton started from, and the level is not
reported as converged (below).

Measured (before any bench; ``tests/test_circular_map.py`` and by hand, two squares 0.1
apart, 48-180 nodes per side):

* on exact data the step is right: the nodes of a circle domain give a zero step (1e-12), and
  the image of a circle domain under ``z + 2e-3 z^2`` is mapped back onto it (centres and
  radii to 1e-10) with quadratic decrease of the defect;
* on the solver's nodes the defect at the nodes falls quadratically (1e-7, 1e-13, 1e-15 in
  three steps after three sweeps) -- but the map is *not* right to that: with the first
  sweeps run at a loose tol (1e-3; coarse smooth grids) its circles were 6.5e-6 mirror-
  asymmetric, run at the final tol for 6 sweeps still 1.6e-8 under a certificate of 2e-9
  (the boundary residual sees only the nodes, which are on circles by construction; between
  them the fitted series is not controlled: the graded nodes leave angular gaps of up to 22
  degrees on the outer boundary of that scene, where a series of 86 terms is not determined
  by the data; capping the terms by the gaps (4-14 per boundary) stalls at 1e-5 instead).
  Hence a Newton-finished level is never reported as converged (``converged = False``), and
  ``solve(method="nasser")`` never reports ``tol_met``: it is kept as a measured, experimental
  candidate, not as a solver. The side-by-side figures are in bench/README.md ("Where the
  targets stand", issue 24 item 1) and ``bench/results/koebe_methods.json``.

What a certified Newton step would need (not built): ``g`` found by the GNK itself on the
nodes (one Riemann-Hilbert problem over all boundaries, ``Re[A_j g] = gamma_j + h_j`` with
``A_j = e^{-i theta}``-type coefficients whose indices admit the centre shifts; Wegmann [3]),
so that the step is consistent with the Nystrom discretisation the certificate checks,
instead of a series fitted to the nodes.

References
----------
.. [1] M. M. S. Nasser, "Fast computation of the circular map", Comput. Methods Funct. Theory
   15 (2015) 187-223.
.. [2] M. M. S. Nasser, "PlgCirMap: a MATLAB toolbox for computing conformal mappings from
   polygonal multiply connected domains onto circular domains", SoftwareX 11 (2020) 100464
   (github.com/mmsnasser/PlgCirMap, ``pcm/cirmapb.m``).
.. [3] R. Wegmann, "Fast conformal mapping of multiply connected regions", J. Comput. Appl.
   Math. 130 (2001) 119-138.
.. [4] L. N. Trefethen, "Series solution of Laplace problems", ANZIAM J. 60 (2018) 1-26.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import scipy.linalg

from confnav.conformal.boundary import BoundaryMesh
from confnav.conformal.circledomain import CircleDomainResult, koebe_iteration
from confnav.conformal.gnk import GMRES_RTOL
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Methods understood by :func:`confnav.solve` (``method=``).
METHODS = ("koebe", "nasser")
#: Koebe sweeps (at the final tol's grid resolution) before the Newton steps.
START_SWEEPS = 6
MAX_STEPS = 12
#: Series terms per boundary: at least / at most.
TERMS_MIN = 4
TERMS_MAX = 160
#: Nodes per series term at least (a series with more terms than samples interpolates the
#: nodes and oscillates between them: measured, circularity 1e-7 at the nodes with a mirror
#: asymmetry of 7e-6).
OVERSAMPLE = 2
#: Largest number of real series unknowns of one dense least-squares step (~ 4000 rows per
#: 1000 unknowns: 0.3 s; 50 obstacles would need ~ 10^4 unknowns, 2e12 flops and 1.6 GB).
MAX_UNKNOWNS = 3000
#: Weight of the smoothness penalty (see :func:`newton_step`).
SMOOTH_PENALTY = 1e-9


@dataclass
class CircularMapResult(CircleDomainResult):
    """A :class:`CircleDomainResult` with the Newton steps that finished it."""

    newton_steps: int = 0
    #: Series terms per boundary (outer first) of the last step.
    terms: list[int] | None = None
    #: True if a Newton step was rejected and the sweeps finished the level instead.
    fell_back: bool = False


def _max_gap(W: list[ComplexArray], centers: ComplexArray) -> FloatArray:
    """Largest angular gap (radians) between the nodes of each boundary, seen from its centre."""
    out = []
    for w, c in zip(W, np.concatenate([[0j], centers]), strict=True):
        th = np.sort(np.angle(w - c))
        out.append(float(np.max(np.diff(np.concatenate([th, [th[0] + 2 * np.pi]])))))
    return np.array(out)


def _terms(
    centers: ComplexArray, radii: FloatArray, tol: float, W: list[ComplexArray]
) -> list[int]:
    """Series length per boundary from the closest approach of another boundary.

    ``g``'s singularities behind a boundary lie near the images of the neighbours in it
    (reflections); with ``q = r/(r + sqrt(r gap))`` their distance ratio, ``K ~ log(tol)/log q``.
    """
    c = np.concatenate([[0j], centers])
    r = np.concatenate([[1.0], radii])
    gaps = np.full(c.size, np.inf)
    for j in range(c.size):
        d = np.abs(c - c[j])
        gap_j = np.where(np.arange(c.size) == j, np.inf, d - r - r[j])
        if j > 0:
            gap_j[0] = r[0] - np.abs(c[j]) - r[j]  # distance to the outer circle
        else:
            gap_j = 1.0 - np.abs(c) - r
            gap_j[0] = np.inf
        gaps[j] = max(float(np.min(gap_j)), 1e-12)
    q = r / (r + np.sqrt(r * gaps))
    k = np.ceil(np.log(max(tol, 1e-15) * 1e-2) / np.log(np.maximum(q, 1e-3)))
    # a mode of period below OVERSAMPLE times the largest gap is not seen by the nodes
    cap = np.minimum(TERMS_MAX, np.array([w.size for w in W]) // OVERSAMPLE)
    return [int(v) for v in np.clip(k, TERMS_MIN, np.maximum(cap, TERMS_MIN))]


def _weights(W: ComplexArray) -> FloatArray:
    """Arc-length quadrature weights of a closed polyline (half the two adjacent chords)."""
    d = np.abs(np.roll(W, -1) - W)
    return np.asarray(0.5 * (d + np.roll(d, 1)))


def _basis(
    z: ComplexArray, centers: ComplexArray, radii: FloatArray, terms: list[int]
) -> tuple[ComplexArray, ComplexArray]:
    """Columns of ``g`` and ``g'`` at ``z`` (complex coefficients; outer series first)."""
    cols, dcols = [], []
    k0 = np.arange(1, terms[0] + 1)
    cols.append(z[:, None] ** k0)
    dcols.append(k0 * z[:, None] ** (k0 - 1))
    for j, (c, r) in enumerate(zip(centers, radii, strict=True)):
        k = np.arange(1, terms[j + 1] + 1)
        t = r / (z - c)
        cols.append(t[:, None] ** k)
        dcols.append(-k * t[:, None] ** (k + 1) / r)
    return np.hstack(cols), np.hstack(dcols)


def newton_step(
    W: list[ComplexArray], centers: ComplexArray, radii: FloatArray, terms: list[int]
) -> tuple[ComplexArray, ComplexArray, FloatArray]:
    """Fit one step (see module docstring): ``(coefficients, centre shifts, radius changes)``.

    Unknowns (real): ``Re, Im`` of every series coefficient, except ``Im a_1``; ``Re, Im s_j``
    and ``d_j`` of each hole (the outer radius stays 1: with ``d_0`` free, ``g = a z`` with
    ``s_j = a c_j, d_j = a r_j`` would solve the homogeneous problem).
    """
    M = len(W) - 1
    z = np.concatenate(W)
    owner = np.concatenate([np.full(w.size, j) for j, w in enumerate(W)])
    c = np.concatenate([[0j], centers])[owner]
    r = np.concatenate([[1.0], radii])[owner]
    e = np.exp(-1j * np.angle(z - c))  # e^{-i theta}
    rho = np.abs(z - c)
    sw = np.sqrt(np.concatenate([_weights(w) for w in W]))
    B, _ = _basis(z, centers, radii, terms)
    nb = B.shape[1]
    # Re[(x + i y) B e] = x Re(B e) - y Im(B e)
    Be = B * e[:, None]
    A_g = np.hstack([Be.real, -Be.imag])
    A_g = np.delete(A_g, nb, axis=1)  # Im a_1 = 0
    # centre shifts: -Re[s e] = -(sx Re e - sy Im e) on hole j only
    A_s = np.zeros((z.size, 2 * M))
    A_d = np.zeros((z.size, M))  # no d_0: g = a z would be a null direction
    for j in range(M + 1):
        on = owner == j
        if j:
            A_d[on, j - 1] = -1.0
            A_s[on, 2 * (j - 1)] = -e[on].real
            A_s[on, 2 * (j - 1) + 1] = e[on].imag
    A = np.hstack([A_g, A_s, A_d]) * sw[:, None]
    rhs = -(rho - r) * sw
    # smoothness penalty on the series (Tikhonov): k^2 |coefficient| * SMOOTH_PENALTY, so that
    # modes the nodes do not resolve (angular gaps of up to 20 degrees on the outer boundary
    # between clustered corner nodes, measured) stay small instead of oscillating between nodes
    kk = np.concatenate([np.arange(1, t + 1) for t in terms]).astype(float)
    pen = np.concatenate([kk, kk])
    pen = np.delete(pen, nb)
    P = np.zeros((pen.size, A.shape[1]))
    P[np.arange(pen.size), np.arange(pen.size)] = SMOOTH_PENALTY * pen**2 * np.sqrt(np.sum(sw**2))
    A = np.vstack([A, P])
    rhs = np.concatenate([rhs, np.zeros(pen.size)])
    scale = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    x = scipy.linalg.lstsq(A / scale, rhs, lapack_driver="gelsd", cond=1e-13)[0] / scale
    xg = np.insert(x[: 2 * nb - 1], nb, 0.0)
    coef = xg[:nb] + 1j * xg[nb:]
    xs = x[2 * nb - 1 : 2 * nb - 1 + 2 * M]
    shifts = xs[0::2] + 1j * xs[1::2]
    d = x[2 * nb - 1 + 2 * M :]
    return np.asarray(coef), np.asarray(shifts), np.asarray(d)


def _fit_circles(W: list[ComplexArray], centers: ComplexArray) -> tuple[FloatArray, float]:
    """Radii (weighted mean distance from the centres) and the circularity defect."""
    radii = np.array(
        [
            np.sum(np.abs(w - c) * _weights(w)) / np.sum(_weights(w))
            for w, c in zip(W[1:], centers, strict=True)
        ]
    )
    circ = float(np.max(np.abs(np.abs(W[0]) - 1.0)))
    for w, c, r in zip(W[1:], centers, radii, strict=True):
        circ = max(circ, float(np.max(np.abs(np.abs(w - c) - r))))
    return radii, circ


def nasser_iteration(
    meshes: list[BoundaryMesh],
    hole_points: list[complex],
    anchor: complex,
    tol: float,
    progress: Callable[[int, float], None] | None = None,
    gmres_tol: float = GMRES_RTOL,
    first_guess: list[FloatArray | None] | None = None,
    accel: str | None = None,
) -> CircularMapResult:
    """:data:`START_SWEEPS` Koebe sweeps, then Newton steps on the whole circle domain.

    Same arguments and result (plus Newton diagnostics) as
    :func:`confnav.conformal.circledomain.koebe_iteration`.
    """
    t0 = time.perf_counter()
    kw: dict[str, Any] = dict(
        progress=progress, gmres_tol=gmres_tol, first_guess=first_guess, accel=accel
    )
    # the sweeps run at the final tol (their smooth grids resolve the curves to
    # SMOOTH_PER_TOL * tol: started at a loose tol, the coarser grids' aliasing changed the
    # domain for good -- measured: mirror asymmetry 6.5e-6 at gap 0.1 under an estimate of
    # 2e-9), but only for START_SWEEPS sweeps
    start = koebe_iteration(meshes, hole_points, anchor, tol=tol, max_sweeps=START_SWEEPS, **kw)
    base = {f.name: getattr(start, f.name) for f in fields(CircleDomainResult)}
    M = len(meshes) - 1
    if M == 0:
        return CircularMapResult(**base)
    W = [w.copy() for w in start.W]
    dW = [d.copy() for d in start.dW]
    centers = start.centers.copy()
    radii, circ = _fit_circles(W, centers)
    D = start.derivative_at_anchor
    history = list(start.history)
    steps, changes = 0, []
    terms = _terms(centers, radii, tol, W)
    ok = False
    for _ in range(MAX_STEPS):
        terms = _terms(centers, radii, tol, W)
        if 2 * sum(terms) > MAX_UNKNOWNS:
            break  # a dense least-squares problem too large: the sweeps finish the level
        coef, shifts, _ = newton_step(W, centers, radii, terms)
        g_new, dW_new = [], []
        change = 0.0
        for w, dw in zip(W, dW, strict=True):
            B, dB = _basis(w, centers, radii, terms)
            g = B @ coef
            change = max(change, float(np.max(np.abs(g))))
            g_new.append(w + g)
            dW_new.append(dw * (1.0 + dB @ coef))
        R0 = float(np.sum(np.abs(g_new[0]) * _weights(g_new[0])) / np.sum(_weights(g_new[0])))
        W_t = [w / R0 for w in g_new]
        dW_t = [d_ / R0 for d_ in dW_new]
        c_t = (centers + shifts) / R0
        r_t, circ_t = _fit_circles(W_t, c_t)
        step = max(change, float(np.max(np.abs(c_t - centers))), abs(R0 - 1.0))
        if not (np.isfinite(circ_t) and circ_t < circ):
            break  # rejected: the sweeps finish the level
        steps += 1
        W, dW, centers, radii, circ = W_t, dW_t, c_t, r_t, circ_t
        D = D * float(coef[0].real + 1.0) / R0
        changes.append(step)
        history.append(step)
        if progress is not None:
            progress(start.sweeps + steps, step)
        if len(changes) >= 2:
            rho = changes[-1] / max(changes[-2], 1e-300)
            if rho < 0.5 and max(changes[-1] * rho / (1 - rho), circ) <= tol:
                ok = True
                break
    if not ok:
        res = koebe_iteration(meshes, hole_points, anchor, tol=tol, **kw)
        out = {f.name: getattr(res, f.name) for f in fields(CircleDomainResult)}
        out["sweeps"] = res.sweeps + start.sweeps
        out["gmres_iterations"] = res.gmres_iterations + start.gmres_iterations
        out["wall_time"] = time.perf_counter() - t0
        return CircularMapResult(**out, newton_steps=steps, terms=terms, fell_back=True)
    rho = changes[-1] / max(changes[-2], 1e-300)
    base.update(
        W=W,
        dW=dW,
        centers=centers,
        radii=radii,
        derivative_at_anchor=D,
        history=history,
        circularity=circ,
        # not certified (see the module docstring, "Measured"): the nodes are on circles to
        # rounding, but the map between them is not checked by anything; the error reported
        # is the one of the sweeps' state Newton started from, and the level never counts as
        # converged, so ``solve`` never reports ``tol_met`` on a Newton-finished level
        iteration_error=max(changes[-1] * rho / (1 - rho), circ, start.iteration_error),
        converged=False,
        wall_time=time.perf_counter() - t0,
    )
    return CircularMapResult(**base, newton_steps=steps, terms=terms)


__all__ = ["METHODS", "CircularMapResult", "nasser_iteration", "newton_step"]
