"""Koebe-type iteration: a multiply connected domain onto a circle domain.

One sweep (Nasser, CMFT 2015; the seed's "multiple single-connected problems"):

1. for each hole k: the exterior map F_k of the current image of hole k (alpha = c_k) is
   applied to hole k (which becomes the unit circle) and, by the exterior Cauchy formula, to
   every other boundary, the points c_j and the anchor image; c_k becomes 0;
2. the interior map of the outer image with alpha = anchor image is applied to everything.

At convergence every step is a similarity: ``c_j`` are the centres, ``r_j`` the radii. Each
sweep normalises only its last map, so the rotations of the earlier exterior maps stay in the
composition; at the end everything is rotated by ``e^{-i arg D}``, D = T'(anchor)
(docs/METHOD.md sec. 2, "Final rotation").

Two representations of each boundary (this module's design choice):

* the *passive nodes*: the images of the graded polygon nodes, with their t-derivatives. They
  are what the final map is made of (``W_k = T(eta_k)``).
* after the boundary's own map in the first sweep, a *smooth grid*: ``m`` points uniform in the
  angle of the circle it was just mapped to. Later maps are analytic near it, so it is an
  analytic curve sampled uniformly, and its GNK solves converge exponentially. Only in the first
  sweep is a GNK solved on a polygon (graded mesh, algebraic convergence ~ n^-p).

A passive node keeps a parameter ``u`` along its boundary (position = smooth curve at ``u``).
When a boundary's own map is applied again, ``u`` moves by the map's boundary correspondence,
found by trigonometric interpolation on the smooth grid. Re-solving on the graded nodes instead
would keep their corner-singular parametrisation in every sweep: slower convergence, and the
images of the nodes next to sharp tips coalesce and destabilise the iteration.

Convergence is measured as the change of the passive nodes away from the vertices and of the
centres. The iteration converges linearly, its contraction factor rho depending on the geometry
(~0.01 per sweep on the seed's workspace, but approaching 1 as two circles approach each other:
the reflections that make up the Koebe/Schottky group move a circle by ~ (r/d)^2 of its
neighbour's correction, and for nearly touching circles that ratio is close to 1). The loop
stops only when the remaining error, extrapolated from the observed contraction as
``change * rho / (1 - rho)`` (geometric tail), is below ``tol``; a run that stops making
progress (rounding floor or a true stall) or reaches ``max_sweeps`` is returned with
``converged = False`` and its extrapolated ``iteration_error``, never as converged.

Acceleration (tried, measured, not used): Anderson mixing (Walker & Ni 2011) of the state after
each sweep (hole curves, correspondences u, centres) cut the sweeps at gap 0.01 from 61 to 24,
but converged to a wrong map: the correspondences u are only transported by the maps (the
sweep's Jacobian has eigenvalue 1 in them), so the second-order error of an affine combination
of nearby states is never removed (mirror asymmetry of the radii 6e-7, boundary residual
2.2e-4, against 1e-8 and 2.5e-6 plain; the residual check refused the map). Extrapolating the
domain alone loses the composition of maps that *is* the answer.

Warm starts (tried, measured, not used): starting each smooth-grid GNK solve from the previous
sweep's mu of the same boundary (read off at equal laid angles) made GMRES *slower* (gap 0.1:
794 iterations against 721 from zero). Near the fixed point mu tends to 0 (every map becomes a
similarity, whose mu vanishes), shrinking by the contraction per sweep, so the old mu is
further from the new one than zero is. Its best multiple ``t mu_old`` (least squares, one
extra product) is 1e-3 relative away, but GMRES gains three digits in about one iteration on
these smooth grids (~3 iterations per solve for 1e-11 relative), and the start costs one
product more than a zero start: 2645 FMM sums against 2371 at gap 0.01, 80 nodes per side.

Accelerations (issue 24 item 1; ``accel`` / ``solve(..., koebe_accel=...)``, default
``"none"``; :mod:`confnav.conformal.acceleration`). Both keep the iterate a *conformal image*
of the polygon domain -- every change of state is an analytic map applied to all of it (grids,
their derivatives, passive nodes through their parameters u, the anchor derivative D) -- so
they only change where the next sweep starts, never the fixed point; and both end with at
least three plain sweeps whose own history gives the reported iteration error:

* ``"extrapolate"``: when two successive plain contraction ratios agree (rho in (0.2, 0.99)),
  one sweep keeps every grid (no regrid: each grid point stays the image of the same point,
  so the sweep map G is known on every grid), then ``z -> z + (G(z) - z)/(1 - rho)`` (the
  geometric tail, Aitken's delta^2 on the slowest mode) is applied to the whole domain. The
  next plain sweep confirms it: if its change is not smaller than the extrapolating sweep's,
  the state before the extrapolation is restored (a tested safeguard).
* ``"sor"``: over-relaxed hole maps ``(1 - omega) s_k (z - alpha_k) + omega F_k(z)`` with
  Young's omega from the observed plain contraction, halved when the change grows.

Measured (bench/bench_koebe.py at b80c539; two squares ``gap`` apart to 1e-8, all mesh
levels, CPU seconds of one run; bench/results/koebe*.json, bench/README.md "Where the targets
stand"): gap 0.01, sweeps per level plain / sor / extrapolate 61 / 45 / 34, 123.5 / 96.4 /
83.0 s, asymmetry 2.5e-12 / 1.1e-12 / 3.1e-12 under an estimate of 1.2e-9 (honest), maps
within 2.7e-11 of each other; gap 0.03: 24 / 21 / 19, 14.6 / 13.6 / 11.2 s. Where the plain
contraction is fast (gap 0.1, the default workspace, 50 obstacles) nothing triggers and the
runs are the plain ones; on the default workspace shrunk by 0.2 m an accepted extrapolation
saved no sweep (14 = 14 per level, 42.7 against 41.3 s). So the default stays ``"none"`` (it
must win on every measured case); ``"extrapolate"`` is the candidate. What neither removes:
~4 sweeps per extrapolation cycle are plain, so a near-touching level still takes 3x the
sweeps of a well-separated one.
Tried before and not used (full-state Anderson mixing, GMRES warm starts): below.

References
----------
.. [1] M. M. S. Nasser, "Fast computation of the circular map", Comput. Methods Funct. Theory
   15 (2015) 187-223, secs. 3-4 (the iteration, ~100x error reduction per sweep).
.. [2] P. Henrici, "Applied and Computational Complex Analysis", Vol. 3, Wiley 1986,
   sec. 13.3 (trigonometric interpolation of boundary correspondence functions).
.. [3] docs/METHOD.md sec. 2 (checked formulas, final rotation, convergence test).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from confnav.conformal.acceleration import (
    KOEBE_ACCELS,
    RHO_MIN,
    RelaxedMap,
    extrapolate_curve,
    optimal_omega,
)
from confnav.conformal.boundary import BoundaryMesh
from confnav.conformal.diskmap import CurveMap, exterior_map, interior_map
from confnav.conformal.gnk import GMRES_RTOL
from confnav.conformal.triginterp import trig_eval, upsample
from confnav.errors import ConvergenceError, CrowdingError, UnresolvedCrowdingError
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Circles smaller than this (relative to the unit disk) cannot be resolved in double precision:
#: the image nodes of such a boundary crowd together below rounding (docs/METHOD.md sec. 6).
CROWDING_RADIUS = 1e-11
MAX_SWEEPS = 200
#: Default acceleration of the sweeps (:mod:`confnav.conformal.acceleration`).
KOEBE_ACCEL = "none"
#: Two successive plain contraction ratios agreeing to this (relative) set the over-relaxation.
RATIO_AGREE = 0.2
#: Largest contraction extrapolated along (1/(1 - rho) = 20) and plain sweeps between a
#: rejected extrapolation and the next one.
RHO_EXTRAPOLATE = 0.95
EXTRAPOLATE_WAIT = 3
#: Sweeps without any decrease of the change (below the best of the three before) after which
#: the iteration counts as stalled: at the rounding floor, or not converging at all.
STALL_SWEEPS = 3
#: Largest contraction factor used to extrapolate: a slower run is treated as stalled.
RHO_MAX = 0.99
#: Smooth-grid sizes: start, cap, and the smallest Fourier tail (relative) resolved: the grid
#: resolves its curve to ``SMOOTH_PER_TOL * tol`` (the tail then adds nothing measurable to the
#: map's error), but never below rounding, SMOOTH_TAIL.
SMOOTH_START = 64
SMOOTH_MAX = 16384
SMOOTH_TAIL = 1e-15
SMOOTH_PER_TOL = 1e-3


@dataclass
class CircleDomainResult:
    """Boundary images and circle domain after the Koebe-type iteration."""

    W: list[ComplexArray]
    dW: list[ComplexArray]
    centers: ComplexArray
    radii: FloatArray
    derivative_at_anchor: float
    sweeps: int
    history: list[float] = field(default_factory=list)
    circularity: float = 0.0  # max deviation of the passive nodes from their circles
    gmres_iterations: int = 0
    smooth_nodes: list[int] = field(default_factory=list)
    wall_time: float = 0.0
    #: Remaining error of the iteration, extrapolated from the observed contraction.
    iteration_error: float = 0.0
    #: False if the iteration stopped without meeting its tolerance (stall or sweep limit).
    converged: bool = True
    #: Largest relative Fourier tail of a smooth grid solved on while above its target (at
    #: SMOOTH_MAX, or laid too small in an early sweep; 0: none).
    resolution_error: float = 0.0
    #: The first sweep's GNK solution of each boundary on its graded mesh (outer first): the
    #: next mesh level's first guess (:func:`confnav.conformal.boundary.resample`).
    first_mu: list[FloatArray | None] = field(default_factory=list)
    #: Largest absolute GNK residual of any solve (:attr:`CurveMap.gmres_residual`).
    gmres_residual: float = 0.0
    #: Sweeps with over-relaxed hole maps (``accel="sor"``) and the last omega used.
    relaxed_sweeps: int = 0
    omega: float = 1.0
    #: Extrapolations of the sweep map (``accel="extrapolate"``) and how many were rejected.
    extrapolations: int = 0
    rejected_extrapolations: int = 0


def _winding(curve: ComplexArray, z: complex) -> float:
    """Winding number of a closed polyline about z (sanity check of alpha)."""
    d = np.angle(np.roll(curve, -1) - z) - np.angle(curve - z)
    d = (d + np.pi) % (2 * np.pi) - np.pi
    return float(d.sum() / (2 * np.pi))


def _tail(samples: ComplexArray) -> float:
    """Relative size of the top eighth of the Fourier modes of a periodic sample."""
    c = np.abs(np.fft.fft(samples))
    m = samples.size
    q = max(1, m // 16)
    return float(np.max(c[m // 2 - q : m // 2 + q + 1]) / max(np.max(c), 1e-300))


@dataclass
class _Boundary:
    """One boundary during the iteration (j = 0 outer, ccw; j > 0 hole, cw)."""

    P: ComplexArray  # passive node images
    dP: ComplexArray  # their t-derivatives
    mask: np.ndarray  # passive nodes away from vertices
    hole: bool
    S: ComplexArray | None = None  # smooth grid (uniform in s), None before the first own map
    dS: ComplexArray | None = None  # dS/ds
    u: FloatArray | None = None  # parameter of each passive node along the smooth curve
    du: FloatArray | None = None  # du/dt at each passive node
    m: int = SMOOTH_START
    c: complex = 0j  # Moebius grading of the smooth grid (0: uniform in angle)
    tail: float = SMOOTH_TAIL  # Fourier tail (relative) the smooth grid must reach
    capped_tail: float = 0.0  # Fourier tail of the grid while it is at SMOOTH_MAX (0: not)

    def own_map(
        self, alpha: complex, others: ComplexArray, rtol: float, x0: FloatArray | None = None
    ) -> CurveMap:
        """Solve the disk map of this boundary's current image and move it onto |w| = 1.

        ``x0``: a first guess of the GNK solution, used in the first sweep (on the polygon's
        graded mesh; the previous mesh level's solution there).

        ``others`` are points of the other boundaries: if they have come closer to this curve
        than its smooth grid resolves, the grid is refined first (exact FFT upsampling of an
        analytic curve), so that the GNK solve and the Cauchy sums across the gap are accurate.
        """
        self._resolve(others)
        if self.S is None:  # first sweep: the polygon, on its graded mesh
            cm = (exterior_map if self.hole else interior_map)(self.P, self.dP, alpha, rtol, x0)
            sgn = -1.0 if self.hole else 1.0
            self.u = sgn * np.unwrap(np.angle(cm.f))
            self.u = self.u - 2 * np.pi * np.floor(self.u[0] / (2 * np.pi))
            self.du = sgn * (cm.df / cm.f).imag
        else:
            assert self.dS is not None and self.u is not None and self.du is not None
            cm = (exterior_map if self.hole else interior_map)(self.S, self.dS, alpha, rtol)
            sgn = -1.0 if self.hole else 1.0
            s_grid = 2 * np.pi * np.arange(self.S.size) / self.S.size
            grid = _mobius_grid(self.c, sgn, s_grid)[2]  # angle of each grid point when laid
            new = sgn * np.unwrap(np.angle(cm.f))
            new = new - 2 * np.pi * np.round((new[0] - grid[0]) / (2 * np.pi))
            s_u, ds_du = _mobius_param(self.c, sgn, self.u)
            delta, ddelta = trig_eval(new - grid, s_u, derivative=True).real
            self.du = self.du * (1.0 + ddelta * ds_du)
            self.u = self.u + delta
            if _tail(self.S) > self.tail:
                self.m = min(2 * self.S.size, SMOOTH_MAX)  # under-resolved: at least double
        sgn = -1.0 if self.hole else 1.0
        self.P = np.exp(1j * sgn * self.u)
        self.dP = 1j * sgn * self.P * self.du
        self.S = self.dS = None  # the grid is laid by regrid() once the others are mapped
        return cm

    def _resolve(self, others: ComplexArray) -> None:
        """Refine the smooth grid where other boundaries came close (see :meth:`own_map`)."""
        if self.S is not None:
            assert self.dS is not None
            m, capped = _local_grid_size(self.S, self.dS, others, self.tail)
            tail = _tail(self.S)
            if capped or self.S.size >= SMOOTH_MAX or tail > self.tail:
                # solved on an under-resolved grid: the aliasing error changes the domain for
                # good (later sweeps map the changed domain, at every mesh level alike)
                self.capped_tail = max(self.capped_tail, tail)
            if m > self.S.size:
                self.S, self.dS = upsample(np.stack([self.S, self.dS]), m)

    def relaxed_map(
        self, alpha: complex, others: ComplexArray, rtol: float, omega: float
    ) -> RelaxedMap:
        """Over-relaxed own map of a hole (:mod:`confnav.conformal.acceleration`).

        The hole's curve is moved by ``F^omega`` on its smooth grid like any other boundary:
        its grid, grading and the passive parameters u stay (no regrid: the curve is no
        circle). Only after the first sweep (the hole has a smooth grid). With ``omega = 1``
        (the outer boundary too: its interior map) the grid points are moved by the plain map,
        so that every grid point stays the image of the same point (``accel="extrapolate"``).
        """
        assert self.S is not None and self.dS is not None
        assert self.hole or omega == 1.0
        self._resolve(others)
        cm = (exterior_map if self.hole else interior_map)(self.S, self.dS, alpha, rtol)
        rm = RelaxedMap(cm, omega)
        self.S, self.dS = rm.on_curve()
        if _tail(self.S) > self.tail:
            self.m = min(2 * self.S.size, SMOOTH_MAX)
        return rm

    def passive(self) -> tuple[ComplexArray, ComplexArray]:
        """Passive nodes and their t-derivatives: the smooth curve at the parameters u."""
        if self.S is None:
            return self.P, self.dP
        assert self.dS is not None and self.u is not None and self.du is not None
        s_u, ds_du = _mobius_param(self.c, -1.0 if self.hole else 1.0, self.u)
        p, dp = trig_eval(np.stack([self.S, self.dS]), s_u)
        return p, dp * ds_du * self.du

    def regrid(self, others: ComplexArray) -> None:
        """Lay the smooth grid on the unit circle this boundary was just mapped to.

        The later maps are analytic outside (hole) / inside (outer) the other boundaries, which
        lie at relative distance delta from the circle; the Fourier coefficients of the curve
        then decay like (1 + delta)^-j, so m = 2 ln(1/eps) / ln(1 + delta) points resolve it.
        Where another boundary comes close (delta small) on one side only, the grid is graded
        towards it by a disk automorphism (:func:`_grading`): in the uniform parameter s the
        close approach is magnified, and m follows from the gap seen in s.
        """
        self.c, gap = _grading(others)
        m, capped = _grid_size(gap, self.tail)
        self.m = max(self.m, m)
        if capped and self.m >= SMOOTH_MAX:
            # held at its cap: modes decay like (1 + gap)^-j, so the grid resolves the curve
            # to about (1 + gap)^(-m/2) -- an error kept even if no later sweep solves on it
            # (the passive nodes of the final sweep are read off this grid)
            self.capped_tail = max(self.capped_tail, float((1.0 + gap) ** (-self.m / 2)))
        sgn = -1.0 if self.hole else 1.0
        s_grid = 2 * np.pi * np.arange(self.m) / self.m
        self.S, self.dS = _mobius_grid(self.c, sgn, s_grid)[:2]


#: Grading strengths tried (|c| of the Moebius map); 0 = uniform. Above 0.999 the angle of
#: the grid would come within ~0.1 rad of wrapping (see :func:`_mobius_grid`).
GRADING_RHO = (0.0, 0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.998, 0.999)


def _wrap(x: FloatArray) -> FloatArray:
    return np.asarray((x + np.pi) % (2 * np.pi) - np.pi)


def _mobius_grid(
    c: complex, sgn: float, s: FloatArray
) -> tuple[ComplexArray, ComplexArray, FloatArray, FloatArray]:
    """Grid graded by the disk automorphism phi(z) = (z + c)/(1 + conj(c) z).

    Returns z(s) = phi(e^{i sgn s}), dz/ds, the angle theta(s) = sgn arg z(s) (continuous,
    theta(s) - s periodic) and theta'(s) = |phi'(e^{i sgn s})| = (1 - |c|^2)/|1 + conj(c) e|^2:
    points are denser by (1 + |c|)/(1 - |c|) towards c/|c| (Henrici, Vol. 1, sec. 5.3: the
    automorphisms of the disk map the circle onto itself).
    """
    e = np.exp(1j * sgn * s)
    den = 1.0 + np.conj(c) * e
    z = (e + c) / den
    dphi = (1.0 - abs(c) ** 2) / den**2
    theta = s + _wrap(sgn * np.angle(z) - s)
    return np.asarray(z), np.asarray(dphi * 1j * sgn * e), theta, np.asarray(np.abs(dphi))


def _mobius_param(c: complex, sgn: float, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The grid parameter s of the circle point at angle u (inverse of :func:`_mobius_grid`)
    and ds/du = |phi^-1'(e^{i sgn u})|."""
    if c == 0:
        return u, np.ones_like(u)
    e = np.exp(1j * sgn * u)
    den = 1.0 - np.conj(c) * e
    zeta = (e - c) / den
    s = u + _wrap(sgn * np.angle(zeta) - u)
    return s, np.asarray((1.0 - abs(c) ** 2) / np.abs(den) ** 2)


def _grading(others: ComplexArray) -> tuple[complex, float]:
    """Moebius grading of a grid on the unit circle and the gap it leaves to ``others``.

    The other boundaries at relative distance delta limit the Fourier decay of the curve; in
    the graded parameter s they are seen through phi^-1, which preserves the circle. Of the
    strengths :data:`GRADING_RHO` towards the nearest other point, the one whose smallest gap
    in s is largest wins (0 when nothing is close: the uniform grid). The grading map itself
    has a pole at zeta = -1/conj(c) (sent to infinity, where a hole's exterior map has its
    pole too), so the curve's modes decay no faster than rho^j: a gap of at most 1/rho - 1.
    (Missed for the outer boundary, whose ``others`` never enclose that pole: rho 0.95 laid
    256 points whose Fourier tail was 3.4e-3, and the under-resolved early sweeps moved the
    circle domain by 5e-5 at every mesh level alike -- a boundary residual of 1e-4 that the
    level difference, 3e-13, could not see; near_touching shrunk by 0.3.)
    """
    if others.size == 0:
        return 0j, 1.0
    dist = np.abs(np.abs(others) - 1.0)
    k = int(np.argmin(dist))
    if dist[k] > 0.05:  # nothing close: uniform (the grid is small anyway)
        return 0j, float(dist[k])
    direction = others[k] / abs(others[k])
    best = (0j, float(dist[k]))
    for rho in GRADING_RHO[1:]:
        c = rho * direction
        zeta = (others - c) / (1.0 - np.conj(c) * others)
        gap = min(float(np.min(np.abs(np.abs(zeta) - 1.0))), 1.0 / rho - 1.0)
        if gap > best[1]:
            best = (complex(c), gap)
    return best


def _local_grid_size(
    S: ComplexArray, dS: ComplexArray, others: ComplexArray, tail: float
) -> tuple[int, bool]:
    """Grid size for which every other point keeps the distance the tail needs from the curve.

    A uniform grid with spacing h resolves an analytic curve to the Fourier ``tail`` while the
    nearest singularity keeps d/h >= ln(1/tail)/pi away (that is m = 2 ln(1/tail)/delta on a
    circle, delta = d/r); checked point by point with the local spacing |dS| 2pi/m of the
    nearest grid point, so it holds for graded grids too.
    """
    m = S.size
    if others.size == 0:
        return m, False
    tree = cKDTree(np.column_stack([S.real, S.imag]))
    d, i = tree.query(np.column_stack([others.real, others.imag]))
    h = np.abs(dS[i]) * 2 * np.pi / m
    ratio = float(np.min(d / np.maximum(h, 1e-300)))
    need_ratio = np.log(1 / tail) / np.pi
    if ratio >= need_ratio:
        return m, False
    want = int(2 ** np.ceil(np.log2(m * need_ratio / max(ratio, 1e-12))))
    return min(want, SMOOTH_MAX), want > SMOOTH_MAX


def _grid_size(gap: float, tail: float) -> tuple[int, bool]:
    """Uniform grid size resolving an analytic curve whose nearest singularity is at relative
    distance ``gap`` to a relative Fourier ``tail``: modes decay like (1 + gap)^-j, so
    m = 2 ln(1/tail) / ln(1 + gap) (power of 2, capped at
    :data:`SMOOTH_MAX`); the flag says the cap was hit (the grid is then under-resolved and
    its Fourier tail is reported as ``resolution_error``)."""
    if not np.isfinite(gap):
        raise ConvergenceError("a boundary image became non-finite (NaN or inf)")
    need = 2 * np.log(1 / tail) / np.log1p(max(gap, 1e-6))
    m = int(2 ** np.ceil(np.log2(max(need, SMOOTH_START))))
    return min(m, SMOOTH_MAX), m > SMOOTH_MAX


def _curves(bnds: list[_Boundary], skip: int) -> ComplexArray:
    """One set of points per boundary but ``skip`` (smooth grid if any, else passive nodes)."""
    pts = _others(bnds, skip)
    return np.concatenate(pts) if pts else np.zeros(0, np.complex128)


def _others(bnds: list[_Boundary], skip: int) -> list[ComplexArray]:
    """What the maps move: the smooth grid of a boundary, or its passive nodes before it has
    one (first sweep). Passive nodes on a smooth curve follow from their parameter ``u``."""
    return [b.S if b.S is not None else b.P for j, b in enumerate(bnds) if j != skip]


def _apply(
    cm: CurveMap | RelaxedMap, bnds: list[_Boundary], skip: int, pts: ComplexArray
) -> ComplexArray:
    """Apply a curve map to every boundary but ``skip`` (passive and smooth) and to points."""
    z = np.concatenate([*_others(bnds, skip), pts])
    fz, dfz = cm.evaluate(z, derivative=True)
    assert dfz is not None
    off = 0
    for j, b in enumerate(bnds):
        if j == skip:
            continue
        if b.S is not None:
            assert b.dS is not None
            s = b.S.size
            b.S, b.dS = fz[off : off + s], b.dS * dfz[off : off + s]
        else:
            s = b.P.size
            b.P, b.dP = fz[off : off + s], b.dP * dfz[off : off + s]
        off += s
    return np.asarray(np.concatenate([fz[off:], dfz[off:]]))


def koebe_iteration(
    meshes: list[BoundaryMesh],
    hole_points: list[complex],
    anchor: complex,
    tol: float,
    max_sweeps: int = MAX_SWEEPS,
    progress: Callable[[int, float], None] | None = None,
    gmres_tol: float = GMRES_RTOL,
    first_guess: list[FloatArray | None] | None = None,
    accel: str | None = None,
) -> CircleDomainResult:
    """Run the iteration on graded meshes (outer counter-clockwise, holes clockwise).

    Parameters
    ----------
    meshes
        ``meshes[0]`` the outer boundary (ccw), ``meshes[1:]`` the holes (cw).
    hole_points
        A point inside each hole (initial ``c_j``).
    anchor
        The point sent to 0.
    tol
        Stop when the remaining error, extrapolated from the change of the boundary images
        (away from vertices) and its observed contraction, is below ``tol``.
    gmres_tol
        Relative residual of every GNK solve (:func:`confnav.conformal.gnk.gmres_rtol`).
    accel
        ``"none"`` (plain sweeps) or ``"sor"`` (over-relaxed hole maps,
        :mod:`confnav.conformal.acceleration`); None: :data:`KOEBE_ACCEL`. With ``"sor"`` the
        run ends with plain sweeps whose own history (at least three sweeps) gives the
        reported iteration error, so the certificate never rests on relaxed sweeps.
    """
    accel = KOEBE_ACCEL if accel is None else accel
    if accel not in KOEBE_ACCELS:
        raise ValueError(f"accel must be one of {KOEBE_ACCELS}, got {accel!r}")
    t0 = time.perf_counter()
    bnds = [
        _Boundary(
            P=m.eta.copy(),
            dP=m.deta.copy(),
            mask=m.interior_mask(),
            hole=j > 0,
            tail=max(SMOOTH_TAIL, SMOOTH_PER_TOL * tol),
        )
        for j, m in enumerate(meshes)
    ]
    M = len(meshes) - 1
    c = np.array(hole_points, dtype=np.complex128)
    a = complex(anchor)
    D = 1.0 + 0j
    history: list[float] = []
    gm_its = 0
    gm_res = 0.0
    sweeps = 0
    guess = list(first_guess) if first_guess is not None else [None] * (M + 1)
    first_mu: list[FloatArray | None] = [None] * (M + 1)
    # "plain": plain sweeps (all of them with accel "none"); "relaxed": over-relaxed hole maps
    # with omega; "final": plain sweeps after the relaxed ones, their own history certifies
    phase, omega = "plain", 1.0
    phase_history: list[float] = []
    relaxed_sweeps = 0
    extrapolations = rejected = hold = 0
    rho_ext = prev_change = 0.0
    s_old: list[tuple[ComplexArray, ComplexArray]] = []
    D_old = D
    snapshot: tuple[list[_Boundary], ComplexArray, complex] = (bnds, c, D)
    remaining, converged = float("inf"), False
    for sweep in range(1, max_sweeps + 1):
        sweeps = sweep
        relaxed = phase in ("relaxed", "material")
        if phase == "material":  # a plain sweep that keeps every grid (no regrid)
            omega = 1.0
            s_old = [
                (b.S.copy(), b.dS.copy()) for b in bnds if b.S is not None and b.dS is not None
            ]
            D_old = D
        # after a sweep that kept its grids (relaxed or extrapolating) a change of u is no
        # change of position (the holes kept their parameters u while their curves moved): such
        # sweeps and the plain sweep after them measure the change on the passive node images
        # themselves; every other sweep measures it as plain sweeps do (so a run in which no
        # acceleration acts is the plain run)
        by_position = relaxed or phase == "confirm" or (phase == "final" and not phase_history)
        u_old = [None if b.u is None else b.u.copy() for b in bnds]
        p_old = [b.passive()[0] for b in bnds] if by_position else []
        c_old = c.copy()
        for k in range(1, M + 1):
            b = bnds[k]
            curve = b.P if b.S is None else b.S
            if abs(_winding(curve, c[k - 1])) < 0.5:
                raise ConvergenceError(
                    f"Koebe iteration lost track of obstacle {k - 1} in sweep {sweep} "
                    "(its tracked point left the boundary image)"
                )
            others = np.concatenate([[a], np.delete(c, k - 1)])
            if relaxed:
                R = b.relaxed_map(c[k - 1], _curves(bnds, k), gmres_tol, omega)
                gm_its += R.gmres_iterations
                gm_res = max(gm_res, R.gmres_residual)
                out = _apply(R, bnds, k, others)
                if omega == 1.0:
                    _check_images(
                        _curves(bnds, k), out[: others.size], True, f"obstacle {k - 1}", sweep
                    )
                if not (np.all(np.isfinite(out)) and np.all(np.isfinite(_curves(bnds, -1)))):
                    raise ConvergenceError(
                        f"the relaxed map of obstacle {k - 1} in sweep {sweep} produced "
                        "non-finite boundary images"
                    )
            else:
                F = _own_map(
                    b,
                    c[k - 1],
                    f"obstacle {k - 1}",
                    meshes[k],
                    _curves(bnds, k),
                    gmres_tol,
                    guess[k],
                )
                gm_its += F.gmres_iterations
                gm_res = max(gm_res, F.gmres_residual)
                if sweep == 1:
                    first_mu[k] = F.mu
                out = _apply(F, bnds, k, others)
                _check_images(
                    _curves(bnds, k), out[: others.size], True, f"obstacle {k - 1}", sweep
                )
                _regrid(b, _curves(bnds, k), f"obstacle {k - 1}", sweep)
            img, dimg = out[: others.size], out[others.size :]
            a, D = complex(img[0]), D * complex(dimg[0])
            c = np.insert(img[1:], k - 1, 0.0)
        f0: CurveMap | RelaxedMap
        if phase == "material":
            f0 = bnds[0].relaxed_map(a, _curves(bnds, 0), gmres_tol, 1.0)
        else:
            f0 = _own_map(
                bnds[0], a, "the outer boundary", meshes[0], _curves(bnds, 0), gmres_tol, guess[0]
            )
            if sweep == 1:
                first_mu[0] = f0.mu
        gm_its += f0.gmres_iterations
        gm_res = max(gm_res, f0.gmres_residual)
        out = _apply(f0, bnds, 0, c)
        _check_images(_curves(bnds, 0), out[: c.size], False, "the outer boundary", sweep)
        if phase != "material":
            _regrid(bnds[0], _curves(bnds, 0), "the outer boundary", sweep)
        c, D, a = out[: c.size], D * f0.scale, 0j
        # change of the boundary correspondence (arc length moved on each circle, away from the
        # vertices) and of the centres
        radii = np.array([1.0] + [_radius(bnds[j], c[j - 1]) for j in range(1, M + 1)])
        if relaxed:
            relaxed_sweeps += 1
        if by_position:
            change = max(
                float(np.max(np.abs(b.passive()[0][b.mask] - po[b.mask])))
                for b, po in zip(bnds, p_old, strict=True)
            )
        else:
            change = max(
                (float(np.max(np.abs(b.u[b.mask] - uo[b.mask]))) * r if uo is not None else 1.0)
                for b, uo, r in zip(bnds, u_old, radii, strict=True)
                if b.u is not None
            )
        if M:
            change = max(change, float(np.max(np.abs(c - c_old))))
        history.append(change)
        phase_history.append(change)
        if progress is not None:
            progress(sweep, change)
        if not np.isfinite(change):
            raise ConvergenceError(f"Koebe iteration produced non-finite values in sweep {sweep}")
        if M == 0:
            # no obstacles: the first sweep's interior map of the polygon IS the Riemann map
            # onto the unit disk; the iteration only makes hole images circular ([1], sec. 3),
            # so nothing is left to iterate (a second sweep re-solved the unit circle on its
            # smooth grid: half of every atlas cell's solve, measured)
            remaining, converged = 0.0, True
            break
        radii = radii[1:]
        if M and radii.min() < CROWDING_RADIUS:
            j = int(np.argmin(radii))
            raise CrowdingError(
                f"obstacle {j}'s circle has radius {radii[j]:.1e}: too small to resolve in double "
                "precision (crowding: a long, narrow passage leads to it)"
            )
        if phase == "material":
            # extrapolate the sweep map G along its geometric tail: z -> z + (w - 1)(G(z) - z),
            # an analytic map of the domain (acceleration.extrapolate_sweep); the next plain
            # sweep must confirm it
            snapshot = (copy.deepcopy(bnds), c.copy(), D)
            prev_change = change
            w_ext = 1.0 / (1.0 - rho_ext)
            for b, (S0, dS0) in zip(bnds, s_old, strict=True):
                assert b.S is not None and b.dS is not None
                b.S, b.dS = extrapolate_curve(S0, dS0, b.S, b.dS, w_ext)
            D = D_old * ((1.0 - w_ext) + w_ext * D / D_old)  # H'(0), H = (1 - w) id + w G
            extrapolations += 1
            phase, phase_history = "confirm", []
            continue
        if phase == "confirm":
            if not change < prev_change:  # rejected: back to the state before extrapolating
                bnds, c, D = snapshot
                a = 0j
                rejected += 1
                phase, phase_history = "plain", []
                hold = sweep + EXTRAPOLATE_WAIT  # no new extrapolation for a while
                continue
            phase = "plain"
        if (
            accel == "extrapolate"
            and phase == "plain"
            and sweep >= max(4, hold)
            and len(phase_history) >= 3
        ):
            r1 = phase_history[-1] / max(phase_history[-2], 1e-300)
            r0 = phase_history[-2] / max(phase_history[-3], 1e-300)
            rem, ok = _remaining_error(phase_history)
            if (
                RHO_MIN < r1 < RHO_MAX
                and abs(r1 - r0) <= RATIO_AGREE * r1
                and not (ok and rem <= tol)
            ):
                rho_ext = min(r1, RHO_EXTRAPOLATE)
                phase = "material"
                continue
        if accel == "sor" and phase == "plain" and sweep >= 4:
            # the plain contraction, once two successive ratios agree (the slowest mode
            # dominates), sets omega
            r1 = history[-1] / max(history[-2], 1e-300)
            r0 = history[-2] / max(history[-3], 1e-300)
            omega = optimal_omega(r1) if abs(r1 - r0) <= RATIO_AGREE * r1 else 1.0
            if omega > 1.0:
                phase, phase_history = "relaxed", []
                continue
        if phase == "relaxed":
            rem, ok = _remaining_error(phase_history)
            grew = len(phase_history) > 1 and change > phase_history[-2]
            if grew:  # safeguard: the relaxation overshoots -- halve it towards plain sweeps
                omega = 1.0 + 0.5 * (omega - 1.0)
            if (ok and rem <= tol) or omega < 1.05 or not np.isfinite(change):
                phase, phase_history = "final", []  # plain sweeps certify the result
            continue
        if (phase == "final" or extrapolations) and len(phase_history) < STALL_SWEEPS:
            continue  # at least three plain sweeps: two observed plain contractions
        remaining, converged = _remaining_error(phase_history)
        if converged and remaining <= tol:
            break
        if len(phase_history) > STALL_SWEEPS and change >= min(
            phase_history[-STALL_SWEEPS - 1 : -1]
        ):
            converged = False  # no progress: rounding floor or a true stall -- reported
            break
    else:
        converged = False  # sweep limit: the extrapolated remaining error is reported
    if phase in ("relaxed", "material", "confirm") or (
        (extrapolations or relaxed_sweeps) and len(phase_history) < STALL_SWEEPS
    ):
        # sweep limit before the final plain sweeps could certify anything
        remaining, converged = float("inf"), False
    if len(phase_history) < 2:
        phase_history = history[-STALL_SWEEPS - 1 :]
    iteration_error = remaining if converged and remaining <= tol else _stalled_error(phase_history)
    rot = complex(np.exp(-1j * np.angle(D)))
    for b in bnds:
        # the final passive nodes are interpolated from each smooth grid as the last sweep left
        # it (moved by the maps after its own): its Fourier tail there is a resolution error
        # too, whether or not a sweep solved on it (a final grid above its target tail was
        # not counted before)
        if b.S is not None:
            tail = _tail(b.S)
            if tail > b.tail:
                b.capped_tail = max(b.capped_tail, tail)
    passive = [b.passive() for b in bnds]
    W = [p[0] * rot for p in passive]
    dW = [p[1] * rot for p in passive]
    c = c * rot
    radii = np.array([_radius(bnds[j], c[j - 1] / rot) for j in range(1, M + 1)])
    circ = float(np.max(np.abs(np.abs(W[0]) - 1.0)))
    for j in range(1, M + 1):
        circ = max(circ, float(np.max(np.abs(np.abs(W[j] - c[j - 1]) - radii[j - 1]))))
    return CircleDomainResult(
        W=W,
        dW=dW,
        centers=c,
        radii=radii,
        derivative_at_anchor=float(abs(D)),
        sweeps=sweeps,
        history=history,
        circularity=circ,
        gmres_iterations=gm_its,
        smooth_nodes=[b.m for b in bnds],
        wall_time=time.perf_counter() - t0,
        iteration_error=iteration_error,
        converged=bool(converged and iteration_error <= tol),
        resolution_error=max(b.capped_tail for b in bnds),
        first_mu=first_mu,
        gmres_residual=gm_res,
        relaxed_sweeps=relaxed_sweeps,
        omega=omega,
        extrapolations=extrapolations,
        rejected_extrapolations=rejected,
    )


def _remaining_error(history: list[float]) -> tuple[float, bool]:
    """Error left after the last sweep, from the observed linear contraction.

    With changes h_n shrinking by rho per sweep the iterate is h_n rho / (1 - rho) from the
    limit (geometric tail; Aitken's delta^2 estimate). rho is the larger of the last two
    observed ratios (the safe side; one after two sweeps); a single sweep gives no estimate.
    """
    if len(history) < 2:
        return float("inf"), False
    h = history
    rho = max(h[i] / max(h[i - 1], 1e-300) for i in range(max(1, len(h) - 2), len(h)))
    if rho >= RHO_MAX:
        return float("inf"), False
    return h[-1] * rho / (1 - rho), True


def _stalled_error(history: list[float]) -> float:
    """Error bound of an iteration stopped before its tolerance was met.

    While the change still contracts (sweep limit reached) the geometric tail applies; once it
    stalls, the iterates wander within the last changes and the limit is known no better than
    the largest of them, extrapolated with the slowest contraction accepted (RHO_MAX is not:
    a stall at the rounding floor is taken at face value, ``max(last changes)``)."""
    remaining, ok = _remaining_error(history)
    if ok:
        return max(remaining, history[-1])
    return max(history[-STALL_SWEEPS - 1 :])


def _own_map(
    b: _Boundary,
    alpha: complex,
    name: str,
    mesh: BoundaryMesh,
    others: ComplexArray,
    rtol: float,
    x0: FloatArray | None = None,
) -> CurveMap:
    """``b.own_map`` with failures reported against the boundary and its sharpest corner."""
    try:
        return b.own_map(alpha, others, rtol, x0)
    except ConvergenceError as exc:
        v = mesh.eta[mesh.tau == 0]
        turn = np.angle((np.roll(v, -1) - v) / (v - np.roll(v, 1)))
        sharpest = float(np.degrees(np.min(np.pi - np.abs(turn))))
        if sharpest < NEEDLE_DEGREES:
            why = (
                f"its sharpest corner is {sharpest:.1f} degrees -- needle-like corners make the "
                "equation nearly singular: blunt them or use more nodes"
            )
        else:  # no needle: what is left is a crowded region (measured on an imported map)
            why = (
                f"its sharpest corner is {sharpest:.1f} degrees, not needle-like; a region "
                "reached through a narrow passage (crowding) also makes the equation "
                "ill-conditioned: widen the passage or solve the workspace as an atlas "
                "(confnav atlas)"
            )
        raise ConvergenceError(
            f"{name}: the boundary integral equation did not converge ({exc}); {why}"
        ) from exc


#: Corners sharper than this (degrees) are needle-like: the GNK operator of such a polygon can
#: have a spurious eigenvalue near 0 (confnav.conformal.meshing).
NEEDLE_DEGREES = 20.0


#: Points of other boundaries on the wrong side of a disk map's circle, all within this band
#: of it, are a crowded region the mesh cannot resolve (measured on a door 0.2 m wide and 0.75
#: m long after shrinking by a robot's footprint: a whole obstacle of the far room at
#: |w| - 1 = 4.25e-6 at 80 and 256 nodes per side alike), not an unstable discretisation
#: (a needle tip's spurious eigenvalue sends points far across: |w| 0.28 for 5.85).
CROWDED_BAND = 1e-3


def _check_images(
    curves: ComplexArray, points: ComplexArray, hole: bool, name: str, sweep: int
) -> None:
    """A disk map must send the rest of the domain into its image: outside the unit circle for
    a hole's exterior map, inside it for the outer boundary's interior map.

    A discrete map that does not is meaningless (seen when the GNK operator of a polygon with a
    needle-like tip has a spurious eigenvalue near 0, see confnav.conformal.meshing): it is
    reported here rather than left to break the next sweep.
    """
    w = np.abs(np.concatenate([curves, points]))
    bad = w <= 1.0 if hole else w >= 1.0
    band = float(np.max(np.abs(w[bad] - 1.0))) if np.any(bad) else np.inf
    if np.all(np.isfinite(w)) and band < CROWDED_BAND:
        raise UnresolvedCrowdingError(
            f"the map of {name} in sweep {sweep} sent {int(np.sum(bad))} points of other "
            f"boundaries just {'inside' if hole else 'outside'} the unit circle (all within "
            f"{band:.1e} of it): a region reached through a narrow passage is crowded into a "
            "tiny arc this mesh cannot resolve; solve the workspace as an atlas (confnav "
            "atlas; the transform service does so automatically)"
        )
    if np.any(bad) or not np.all(np.isfinite(w)):
        worst = float(np.min(w) if hole else np.max(w))
        raise ConvergenceError(
            f"the map of {name} in sweep {sweep} sent other parts of the domain "
            f"{'inside' if hole else 'outside'} the unit circle (|w| = {worst:.3g}): its "
            "discretisation is unstable (sharp corners need more nodes)"
        )


def _regrid(b: _Boundary, others: ComplexArray, name: str, sweep: int) -> None:
    """``b.regrid`` after its map, with non-finite results reported against the boundary."""
    if not (np.all(np.isfinite(others)) and np.all(np.isfinite(b.P))):
        raise ConvergenceError(
            f"the map of {name} in sweep {sweep} produced non-finite boundary images"
        )
    b.regrid(others)


def _radius(b: _Boundary, center: complex) -> float:
    """Mean distance of the smooth grid from the centre (weighted uniform in angle)."""
    if b.S is None:
        return float(np.mean(np.abs(b.P - center)))
    s = 2 * np.pi * np.arange(b.S.size) / b.S.size
    w = _mobius_grid(b.c, -1.0 if b.hole else 1.0, s)[3]
    return float(np.sum(np.abs(b.S - center) * w) / np.sum(w))


__all__ = ["CROWDING_RADIUS", "CircleDomainResult", "koebe_iteration"]
