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
``"extrapolate"``, :data:`KOEBE_ACCEL`; :mod:`confnav.conformal.acceleration`). Both keep
the iterate a *conformal image* of the polygon domain -- every change of state is an analytic
map applied to all of it (grids, their derivatives, passive nodes through their parameters u,
the anchor derivative D) -- so
they only change where the next sweep starts, never the fixed point; and both end with at
least three plain sweeps whose own history gives the reported iteration error:

* ``"extrapolate"``: when two successive plain contraction ratios agree (rho in (0.5, 0.99),
  :data:`RHO_EXTRAPOLATE_MIN`),
  one sweep keeps every grid (no regrid: each grid point stays the image of the same point,
  so the sweep map G is known on every grid), then ``z -> z + (G(z) - z)/(1 - rho)`` (the
  geometric tail, Aitken's delta^2 on the slowest mode) is applied to the whole domain. The
  next plain sweep confirms it: if its change is not smaller than the extrapolating sweep's,
  the state before the extrapolation is restored (a tested safeguard).
  Two modes (round 4, :data:`EXTRAPOLATE_MODES` = 2, the default): after one extrapolation of the
  slowest mode the next-slowest dominated the plain ratios for a sweep or two and the slowest came
  back (two squares 0.01 apart, traced in an ad-hoc run), so each cycle removed little more than
  one plain sweep would. Now three sweeps keep their grids (states x_0 .. x_3, every grid point
  the image of the same point) and the minimal polynomial extrapolation of degree 2
  (:func:`_extrapolate_modes`, real weights summing to 1: again an analytic map of the whole
  domain) removes both modes whatever their ratios; it starts once the plain sweeps left (from the
  observed contraction) exceed its cycle of six, with the same confirmation, rejection and final
  plain sweeps. Measured side by side (``bench/bench_koebe.py --gaps 0.01 0.03 --scenes default
  shrunk mixed50 --case-tol default=1e-10 --accels extrapolate --designs graded modes2``,
  ``bench/results/koebe_round4_modes2.json`` at e765f88, one run, load 5.5-9.2, CPU s, one mode /
  two modes): two squares 0.01 apart 34/6/3/3 -> 25/8/3/3 sweeps per level (46 -> 39; the carried
  level's floor contraction is now the 0.85 seen after the last extrapolation), FMM sums 758 ->
  633, 10.6 -> 8.6 s, asymmetry 1.5e-12 / 8.9e-13 under the estimate 1.2e-9, the maps 4.4e-12
  apart; 0.03 apart 31 -> 28 sweeps, 1.4 -> 1.2 s; the default workspace (1e-10), it shrunk by 0.2
  m and 50 obstacles: nothing triggers, the runs are the same bit for bit. Three modes (four
  grid-keeping sweeps) did no better on two squares 0.01 apart in an ad-hoc run (the fit's weights
  exceeded :data:`GAMMA_MAX` and it fell back to one mode), so two it is. As the cycle must pay
  anyway, two modes start from plain contractions above 0.2 (:data:`RHO_EXTRAPOLATE_MIN_MODES`;
  one mode: 0.5). Side by side (``--gaps 0.01 0.03 0.1 --scenes room default shrunk mixed50
  --designs graded modes2 modes2_low``, ``bench/results/koebe_round4_rho.json`` at ec05683, load
  2.0-2.7, CPU s, one mode / two from 0.5 / two from 0.2): two squares 0.01 apart 46 / 39 / 39
  sweeps (28/5/3/3 from 0.2), 10.2 / 8.7 / 8.7 s, asymmetry 1.5e-12 / 8.9e-13 / 2.0e-12 under
  1.2e-9; 0.03 apart 31 / 28 / 25 sweeps; the default workspace shrunk by 0.2 m (rho ~0.23) 32 /
  32 / 27 sweeps (its cold level 15 -> 10), 2.8 / 2.8 / 2.3 s, the maps 1.9e-15 apart; two squares
  0.1 apart, a room with a pillar, the default workspace and 50 obstacles: the same sweeps in all
  three.
* ``"sor"``: over-relaxed hole maps ``(1 - omega) s_k (z - alpha_k) + omega F_k(z)`` with
  Young's omega from the observed plain contraction, halved when the change grows.

Measured (bench/bench_koebe.py at b80c539; two squares ``gap`` apart to 1e-8, all mesh
levels, CPU seconds of one run; bench/results/koebe*.json, bench/README.md "Where the targets
stand"): gap 0.01, sweeps per level plain / sor / extrapolate 61 / 45 / 34, 123.5 / 96.4 /
83.0 s, asymmetry 2.5e-12 / 1.1e-12 / 3.1e-12 under an estimate of 1.2e-9 (honest), maps
within 2.7e-11 of each other; gap 0.03: 24 / 21 / 19, 14.6 / 13.6 / 11.2 s. Where the plain
contraction is fast (gap 0.1, the default workspace, 50 obstacles) nothing triggers and the
runs are the plain ones; on the default workspace shrunk by 0.2 m an accepted extrapolation
saved no sweep (14 = 14 per level, 42.7 against 41.3 s). With the carried levels only the cold
first level runs many sweeps, and extrapolating only contractions above 0.5 it wins or does
the same sweeps on every case measured, so it is the default (``bench/bench_koebe.py --gaps
0.01 0.03 0.1 --scenes room default shrunk mixed50 --case-tol default=1e-10 --accels none
extrapolate --designs carry``, ``bench/results/koebe_extrapolate_default.json`` at 0c0b8fa,
one run, load 1.6-5.8, CPU s, none / extrapolate): two squares 0.01 apart 74 / 46 sweeps
(61/7/3/3 against 34/6/3/3), 36.5 / 25.9 s, asymmetry 1.1e-12 / 1.5e-12 under 1.2e-9, the
maps 6.1e-12 apart; 0.03 apart 33 / 31 sweeps, 9.1 / 6.8 s; 0.1 apart, a room with a pillar,
the default workspace (1e-10), it shrunk by 0.2 m (rho ~0.23, where extrapolating from 0.2
had cost a sweep) and 50 obstacles: nothing triggers, the same sweeps and GMRES iterations
as plain. What neither removes:
~4 sweeps per extrapolation cycle are plain, so a near-touching level still takes 3x the
sweeps of a well-separated one.
Tried before and not used (full-state Anderson mixing, GMRES warm starts): below.

Carried levels (issue 24; ``carry=`` / ``trace=``, :class:`LevelCarry`, used by
:mod:`confnav.conformal.solver` between mesh levels). After a level's first sweep every
boundary is a smooth analytic curve, and the sweeps after it compose a conformal map Phi of
that domain onto the circle domain; they depend on the mesh only through the first sweep, so
every level repeated them (the same history to two digits). A traced level lays tracers on
each boundary's smooth grid after its first sweep (TRACER_FACTOR per grid point, parameters u
like the passive nodes', so they follow every map, regrid, relaxation and extrapolation as
those do) and records where they end: Phi on each curve as a trigonometric interpolant. The
next level, after its own first sweep (its own polygon GNK solves: its discretisation),
finds each point of its smooth grids on the recorded curves at a complex parameter (Newton's
method on a Taylor expansion about a real one; the interpolant of an analytic periodic
function is analytic in a strip, Henrici Vol. 3 sec. 13.3) and applies Phi there: the
analytic continuation of one map across its curves, so the fixed point is unchanged, as for
the accelerations; the anchor's image and the derivative there follow from the same boundary
values (Cauchy formula). Points not found to TRANSPLANT_RTOL, a Taylor term above it or a
tracked centre outside its image refuse the transplant (the level runs cold). Certification:
the sweep after the transplant is measured on the passive nodes' positions, and the
contraction is never taken below the one observed by the cold first level over its whole run
(``LevelCarry.rho``). The first sweep's curves define the domain: their tangents are reset
to the curves' own derivatives (:func:`_consistent_tangents`), since the graded maps'
derivatives off their curves differ from them by the level's discretisation error, and a map
composed on such tangents is not conformal on the curves' domain -- carried across levels,
that defect kept every carried level at the coarsest one's boundary error (a 9.2e-8 residual
on a room with a pillar, 8.6e-11 cold) and made T(anchor) of a 24.7-degree triangle 5e-10
(1.2e-12 cold), which 100x finer grids on traced levels had hidden there; with consistent
tangents both are as cold on the usual grids (tests/test_level_carry.py). Measured:
:mod:`confnav.conformal.solver` module docstring and bench/README.md ("Where the time goes").

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
from math import factorial
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from confnav.conformal.acceleration import (
    KOEBE_ACCELS,
    RelaxedMap,
    extrapolate_curve,
    optimal_omega,
)
from confnav.conformal.boundary import BoundaryMesh
from confnav.conformal.diskmap import CurveMap, exterior_map, interior_map
from confnav.conformal.gnk import GMRES_RTOL, spectral_derivative_complex
from confnav.conformal.triginterp import trig_eval, upsample
from confnav.errors import ConvergenceError, CrowdingError, UnresolvedCrowdingError
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Circles smaller than this (relative to the unit disk) cannot be resolved in double precision:
#: the image nodes of such a boundary crowd together below rounding (docs/METHOD.md sec. 6).
CROWDING_RADIUS = 1e-11
MAX_SWEEPS = 200
#: Default acceleration of the sweeps (:mod:`confnav.conformal.acceleration`).
KOEBE_ACCEL = "extrapolate"
#: Two successive plain contraction ratios agreeing to this (relative) set the over-relaxation.
RATIO_AGREE = 0.2
#: Largest contraction extrapolated along (1/(1 - rho) = 20) and plain sweeps between a
#: rejected extrapolation and the next one.
RHO_EXTRAPOLATE = 0.95
#: Smallest plain contraction extrapolated: an extrapolation cycle takes about four sweeps (the
#: one that keeps its grids, the confirming one and the plain sweeps that certify), over which
#: plain sweeps at rho <= 0.5 already gain rho^4 <= 0.06. Measured with the carried levels
#: (bench/results/koebe_carry_extrapolate.json): on the default workspace shrunk by 0.2 m
#: (rho ~0.23) extrapolating at RHO_MIN = 0.2 cost a sweep (33 against 32), on two squares
#: 0.01 apart (rho 0.79) it saved 28 (46 against 74 sweeps).
RHO_EXTRAPOLATE_MIN = 0.5
#: The same for the multi-mode extrapolation (:data:`EXTRAPOLATE_MODES` > 1), which starts
#: only when the plain sweeps left exceed its cycle anyway (:func:`_plain_sweeps_left`): on
#: the default workspace shrunk by 0.2 m (rho ~0.23) it took the cold level from 15 to 10
#: sweeps (bench/README.md "Round 4", ``koebe_round4_rho.json``).
RHO_EXTRAPOLATE_MIN_MODES = 0.2
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
#: Smooth-grid sizes a required size is rounded up to: this many steps per octave, the sizes
#: ``2^k (1 + j / GRID_STEPS)`` (1: powers of two, as before). The required size
#: (:func:`_grid_size`, :func:`_local_grid_size`) already resolves the curve to its tail;
#: rounding to a power of two added up to 2x more points, and every FMM sum and map
#: evaluation on the grid costs in proportion (two squares 0.01 apart: 2235 points needed on
#: each hole, 4096 laid). Whether a grid resolves its curve stays checked a posteriori (its
#: Fourier tail, :func:`_tail`; an under-resolved grid doubles).
GRID_STEPS = 8
#: What :func:`_tail` measures is the largest Fourier mode within m/16 of the Nyquist mode m/2,
#: so a grid resolves its curve to ``tail`` only if the modes from 7m/16 on have decayed to it:
#: the sizes of :func:`_grid_size` and :func:`_local_grid_size` are this factor (16/14) above
#: the Nyquist-mode rule. The powers of two had hidden the difference in their rounding (a
#: grid graded towards its own pole at |c| = 0.857 laid 448 points with a measured tail of
#: 3.8e-14 against 1e-14 without it; tests/test_solver_regressions.py).
TAIL_BAND = 16.0 / 14.0


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
    #: The first sweep's own map of each boundary (outer first; None where it was a relaxed
    #: map): a re-solve of the same level with some sides refined reuses those whose input --
    #: the curve the map was solved on and its alpha -- is the same (``reuse_first``).
    first_maps: list[CurveMap | None] = field(default_factory=list)
    #: First-sweep maps taken from ``reuse_first`` instead of solved (their input identical).
    reused_first_maps: int = 0
    #: The first sweep's iterate before some of its maps (``snapshots=True``; :func:`_sweep`).
    first_snapshots: dict[int, Any] = field(default_factory=dict)
    #: The hole a first sweep resumed at from ``reuse_snapshots`` (1: none, :func:`_resume`).
    resumed_at: int = 1
    #: The order in which every sweep mapped the holes (1..M; ``order`` of
    #: :func:`koebe_iteration`): a re-solve that reuses this solve's first-sweep maps and
    #: snapshots must sweep in the same order.
    order: list[int] = field(default_factory=list)
    #: Largest absolute GNK residual of any solve (:attr:`CurveMap.gmres_residual`).
    gmres_residual: float = 0.0
    #: Sweeps with over-relaxed hole maps (``accel="sor"``) and the last omega used.
    relaxed_sweeps: int = 0
    omega: float = 1.0
    #: Extrapolations of the sweep map (``accel="extrapolate"``) and how many were rejected.
    extrapolations: int = 0
    rejected_extrapolations: int = 0
    #: The converged map of the sweeps after the first (the next level's start), if traced.
    carry: LevelCarry | None = None
    #: This level's sweeps started from the previous level's map (:func:`_transplant`).
    transplanted: bool = False


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
    #: Tracers (:class:`LevelCarry`): parameters u, like the passive nodes', of the points of
    #: the smooth grid as the first sweep left it; None: not traced.
    tu: FloatArray | None = None

    def own_map(
        self,
        alpha: complex,
        others: ComplexArray,
        rtol: float,
        x0: FloatArray | None = None,
        corners: np.ndarray | None = None,
        reuse: CurveMap | None = None,
    ) -> CurveMap:
        """Solve the disk map of this boundary's current image and move it onto |w| = 1.

        ``x0``: a first guess of the GNK solution, used in the first sweep (on the polygon's
        graded mesh; the previous mesh level's solution there); ``corners``: that mesh's
        vertex blocks (:meth:`~confnav.conformal.boundary.BoundaryMesh.corner_blocks`, the
        first sweep's GMRES preconditioner); ``reuse``: a first-sweep map of a previous solve,
        taken instead of solving if it was solved on this very curve (nodes and t-derivatives
        equal bit for bit) with the same ``alpha`` -- the same GNK equation, solved to the same
        GMRES tolerance (:func:`_reusable`).

        ``others`` are points of the other boundaries: if they have come closer to this curve
        than its smooth grid resolves, the grid is refined first (exact FFT upsampling of an
        analytic curve), so that the GNK solve and the Cauchy sums across the gap are accurate.
        """
        self._resolve(others)
        if self.S is None:  # first sweep: the polygon, on its graded mesh
            if reuse is not None and _reusable(reuse, self.P, self.dP, alpha, self.hole):
                cm = reuse
            else:
                cm = (exterior_map if self.hole else interior_map)(
                    self.P, self.dP, alpha, rtol, x0, corners=corners
                )
            sgn = -1.0 if self.hole else 1.0
            self.u = sgn * np.unwrap(np.angle(cm.f))
            self.u = self.u - 2 * np.pi * np.floor(self.u[0] / (2 * np.pi))
            self.du = sgn * (cm.df / cm.f).imag
        else:
            assert self.dS is not None and self.u is not None and self.du is not None
            cm = (exterior_map if self.hole else interior_map)(
                self.S, self.dS, alpha, rtol, smooth=True
            )
            sgn = -1.0 if self.hole else 1.0
            s_grid = 2 * np.pi * np.arange(self.S.size) / self.S.size
            grid = _mobius_grid(self.c, sgn, s_grid)[2]  # angle of each grid point when laid
            new = sgn * np.unwrap(np.angle(cm.f))
            new = new - 2 * np.pi * np.round((new[0] - grid[0]) / (2 * np.pi))
            s_u, ds_du = _mobius_param(self.c, sgn, self.u)
            if self.tu is None:
                delta, ddelta = trig_eval(new - grid, s_u, derivative=True).real
            else:  # the tracers move with the correspondence as the passive nodes do
                s_t = _mobius_param(self.c, sgn, self.tu)[0]
                both = trig_eval(new - grid, np.concatenate([s_u, s_t]), derivative=True).real
                delta, ddelta = both[0, : s_u.size], both[1, : s_u.size]
                self.tu = self.tu + both[0, s_u.size :]
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
        cm = (exterior_map if self.hole else interior_map)(
            self.S, self.dS, alpha, rtol, smooth=True
        )
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
#: Gap evaluations of a golden-section search between the neighbours of the best of
#: :data:`GRADING_RHO` (0: the list alone). On two squares 0.01 apart the list's best left the
#: holes a gap of 0.025 in the graded parameter (2235 points needed) where a strength between
#: 0.95 and 0.98 leaves more (2048 laid).
GRADING_REFINE = 8


def _reusable(cm: CurveMap, P: ComplexArray, dP: ComplexArray, alpha: complex, hole: bool) -> bool:
    """Whether ``cm`` solved this very first-sweep equation: the same curve nodes and
    t-derivatives (bit for bit) and the same ``alpha`` and kind -- the GNK system is a function
    of these alone (:func:`confnav.conformal.diskmap.exterior_map`), so ``cm`` is its solution
    to the GMRES tolerance it was solved to."""
    return (
        cm.exterior == hole
        and complex(cm.alpha) == complex(alpha)
        and cm.eta.shape == P.shape
        and bool(np.array_equal(cm.eta, P))
        and bool(np.array_equal(cm.deta, dP))
    )


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

    def gap_at(rho: float) -> float:
        c = rho * direction
        zeta = (others - c) / (1.0 - np.conj(c) * others)
        return min(float(np.min(np.abs(np.abs(zeta) - 1.0))), 1.0 / rho - 1.0)

    gaps = [float(dist[k])] + [gap_at(rho) for rho in GRADING_RHO[1:]]
    i = int(np.argmax(gaps))
    best = (complex(GRADING_RHO[i] * direction), gaps[i])
    if i == 0 or GRADING_REFINE == 0:
        return best
    # golden-section search between the neighbours of the best strength, in log(1 - rho):
    # the gap is the smaller of the others' (growing with rho up to the best) and the
    # grading pole's 1/rho - 1 (falling), so one maximum lies between them
    lo = float(np.log(1.0 - GRADING_RHO[min(i + 1, len(GRADING_RHO) - 1)]))  # larger rho
    hi = float(np.log(1.0 - GRADING_RHO[i - 1]))
    g = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)  # a < b
    fa, fb = gap_at(1.0 - np.exp(a)), gap_at(1.0 - np.exp(b))
    for _ in range(GRADING_REFINE - 2):
        if fa >= fb:  # the maximum is in [lo, b]
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = gap_at(1.0 - np.exp(a))
        else:  # in [a, hi]
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = gap_at(1.0 - np.exp(b))
    for t, f in ((a, fa), (b, fb)):
        if f > best[1]:
            best = (complex((1.0 - np.exp(t)) * direction), f)
    return best


def _local_grid_size(
    S: ComplexArray, dS: ComplexArray, others: ComplexArray, tail: float
) -> tuple[int, bool]:
    """Grid size for which every other point keeps the distance the tail needs from the curve.

    A uniform grid with spacing h resolves an analytic curve to the Fourier ``tail`` while the
    nearest singularity keeps d/h >= ln(1/tail)/pi away (that is m = 2 ln(1/tail)/delta on a
    circle, delta = d/r); checked point by point with the local spacing |dS| 2pi/m of the
    nearest grid point, so it holds for graded grids too. Points farther from the curve's
    centre c than ``max |S - c| + need h_max`` are farther than ``need h`` from every grid
    point (triangle inequality) and cannot decide the size: only the others are looked up.
    """
    m = S.size
    if others.size == 0:
        return m, False
    need_ratio = TAIL_BAND * np.log(1 / tail) / np.pi
    c = complex(np.mean(S))
    h_max = float(np.max(np.abs(dS))) * 2 * np.pi / m
    reach = float(np.max(np.abs(S - c))) + need_ratio * h_max
    near = others[np.abs(others - c) <= reach]
    if near.size == 0:
        return m, False
    tree = cKDTree(np.column_stack([S.real, S.imag]))
    d, i = tree.query(np.column_stack([near.real, near.imag]))
    h = np.abs(dS[i]) * 2 * np.pi / m
    ratio = float(np.min(d / np.maximum(h, 1e-300)))
    if ratio >= need_ratio:
        return m, False
    want = _round_size(m * need_ratio / max(ratio, 1e-12))
    return min(want, SMOOTH_MAX), want > SMOOTH_MAX


def _round_size(need: float) -> int:
    """The smallest grid size ``2^k (1 + j / GRID_STEPS)`` (j = 0 .. GRID_STEPS - 1) that is
    at least ``need`` (:data:`GRID_STEPS`); at least 2 GRID_STEPS, so every size is even."""
    need = max(float(need), 2.0 * GRID_STEPS)
    if not np.isfinite(need) or need > 4 * SMOOTH_MAX:
        return 4 * SMOOTH_MAX
    k = int(np.floor(np.log2(need)))
    step = 2**k // GRID_STEPS if 2**k >= GRID_STEPS else 1
    return int(-(-int(np.ceil(need)) // step) * step)


def _grid_size(gap: float, tail: float) -> tuple[int, bool]:
    """Uniform grid size resolving an analytic curve whose nearest singularity is at relative
    distance ``gap`` to a relative Fourier ``tail``: modes decay like (1 + gap)^-j, so
    m = 2 ln(1/tail) / ln(1 + gap) (times :data:`TAIL_BAND`, rounded up by :func:`_round_size`,
    capped at
    :data:`SMOOTH_MAX`); the flag says the cap was hit (the grid is then under-resolved and
    its Fourier tail is reported as ``resolution_error``)."""
    if not np.isfinite(gap):
        raise ConvergenceError("a boundary image became non-finite (NaN or inf)")
    need = TAIL_BAND * 2 * np.log(1 / tail) / np.log1p(max(gap, 1e-6))
    m = _round_size(max(need, SMOOTH_START))
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


@dataclass
class _Iterate:
    """The iterate of the sweeps: the boundary images, the points c_j tracked inside the
    holes, the anchor's image ``a`` and the derivative ``D`` of the composed maps there."""

    bnds: list[_Boundary]
    c: ComplexArray
    a: complex
    D: complex


@dataclass
class _Tally:
    """GMRES work and worst residual over every GNK solve, and the first sweep's solutions."""

    first_mu: list[FloatArray | None]
    iterations: int = 0
    residual: float = 0.0
    #: the first sweep's own maps (recorded) and those of a previous solve to reuse
    first_maps: list[CurveMap | None] = field(default_factory=list)
    reuse: list[CurveMap | None] = field(default_factory=list)
    reused: int = 0
    #: the first sweep's snapshots (recorded; None: not recorded) by position (:func:`_sweep`)
    snapshots: dict[int, Any] | None = None

    def add(self, cm: CurveMap | RelaxedMap) -> None:
        self.iterations += cm.gmres_iterations
        self.residual = max(self.residual, cm.gmres_residual)

    def first(self, k: int, cm: CurveMap) -> None:
        """Record boundary k's first-sweep map; its GMRES work counts once, where solved."""
        self.first_mu[k] = cm.mu
        if self.first_maps:
            self.first_maps[k] = cm
        if self.reuse and self.reuse[k] is cm:
            self.reused += 1
            self.residual = max(self.residual, cm.gmres_residual)
        else:
            self.add(cm)

    def reusable(self, k: int, sweep: int) -> CurveMap | None:
        return self.reuse[k] if sweep == 1 and self.reuse else None


@dataclass
class StartImage:
    """A conformal image of the polygon domain to start the sweeps from instead of the
    domain itself (a warm re-solve, :mod:`confnav.conformal.warm`): the images of the graded
    nodes and their t-derivatives, a point inside each hole's image, the anchor's image and
    the map's derivative there."""

    P: list[ComplexArray]
    dP: list[ComplexArray]
    c: ComplexArray
    a: complex
    D: complex
    #: Per boundary, a smooth grid of its image (uniform in ``s``, the angle on a circle it
    #: came from), its ``d/ds``, and the parameter ``u`` of each graded node on it with
    #: ``du/dt``; None: the boundary starts from its graded nodes ``P`` (first sweep on them).
    smooth: list[tuple[ComplexArray, ComplexArray, FloatArray, FloatArray] | None] = field(
        default_factory=list
    )


def _initial_iterate(
    meshes: list[BoundaryMesh],
    hole_points: list[complex],
    anchor: complex,
    tol: float,
    start: StartImage | None = None,
) -> _Iterate:
    """The polygon domain itself (or ``start``, an image of it): passive nodes on the graded
    meshes, no smooth grids yet; each grid must resolve its curve to ``SMOOTH_PER_TOL * tol``
    (never below rounding)."""
    bnds = [
        _Boundary(
            P=m.eta.copy() if start is None else start.P[j].copy(),
            dP=m.deta.copy() if start is None else start.dP[j].copy(),
            mask=m.interior_mask(),
            hole=j > 0,
            tail=max(SMOOTH_TAIL, SMOOTH_PER_TOL * tol),
        )
        for j, m in enumerate(meshes)
    ]
    if start is not None:
        for b, sm in zip(bnds, start.smooth, strict=False):
            if sm is not None:
                b.S, b.dS = sm[0].copy(), sm[1].copy()
                b.u, b.du = sm[2].copy(), sm[3].copy()
                b.m = int(sm[0].size)
        return _Iterate(bnds, np.array(start.c, dtype=np.complex128), start.a, start.D)
    return _Iterate(bnds, np.array(hole_points, dtype=np.complex128), complex(anchor), 1.0 + 0j)


def _check_tracked(b: _Boundary, center: complex, name: str, sweep: int) -> None:
    """The tracked point c_k must stay inside the image of its hole (winding number 1)."""
    curve = b.P if b.S is None else b.S
    if abs(_winding(curve, center)) < 0.5:
        raise ConvergenceError(
            f"Koebe iteration lost track of {name} in sweep {sweep} "
            "(its tracked point left the boundary image)"
        )


def _map_hole(
    it: _Iterate,
    k: int,
    sweep: int,
    phase: str,
    omega: float,
    mesh: BoundaryMesh,
    guess: FloatArray | None,
    tally: _Tally,
    gmres_tol: float,
) -> None:
    """Step 1 of a sweep for hole k ([1], sec. 3): the exterior map of its image with
    alpha = c_k sends it onto the unit circle and every other boundary, the other c_j and the
    anchor image along (exterior Cauchy formula); c_k becomes 0, D takes the map's derivative
    at the anchor. Relaxed and extrapolating sweeps move the hole by the over-relaxed map on
    its smooth grid instead (:meth:`_Boundary.relaxed_map`, no regrid)."""
    b, name = it.bnds[k], f"obstacle {k - 1}"
    _check_tracked(b, it.c[k - 1], name, sweep)
    others = np.concatenate([[it.a], np.delete(it.c, k - 1)])
    if phase in ("relaxed", "material"):
        R = b.relaxed_map(it.c[k - 1], _curves(it.bnds, k), gmres_tol, omega)
        tally.add(R)
        out = _apply(R, it.bnds, k, others)
        if omega == 1.0:
            _check_images(_curves(it.bnds, k), out[: others.size], True, name, sweep)
        if not (np.all(np.isfinite(out)) and np.all(np.isfinite(_curves(it.bnds, -1)))):
            raise ConvergenceError(
                f"the relaxed map of {name} in sweep {sweep} produced non-finite boundary images"
            )
    else:
        F = _own_map(
            b,
            it.c[k - 1],
            name,
            mesh,
            _curves(it.bnds, k),
            gmres_tol,
            guess,
            tally.reusable(k, sweep),
        )
        if sweep == 1:
            tally.first(k, F)
        else:
            tally.add(F)
        out = _apply(F, it.bnds, k, others)
        _check_images(_curves(it.bnds, k), out[: others.size], True, name, sweep)
        _regrid(b, _curves(it.bnds, k), name, sweep)
    img, dimg = out[: others.size], out[others.size :]
    it.a, it.D = complex(img[0]), it.D * complex(dimg[0])
    it.c = np.insert(img[1:], k - 1, 0.0)


def _map_outer(
    it: _Iterate,
    sweep: int,
    phase: str,
    mesh: BoundaryMesh,
    guess: FloatArray | None,
    tally: _Tally,
    gmres_tol: float,
) -> None:
    """Step 2 of a sweep ([1], sec. 3): the interior map of the outer image with alpha = the
    anchor image sends it onto the unit circle, the anchor to 0 and the holes along; D takes
    its derivative at the anchor. An extrapolating sweep moves the outer grid by the plain
    map without regridding it."""
    name = "the outer boundary"
    b0 = it.bnds[0]
    f0: CurveMap | RelaxedMap
    if phase == "material":
        f0 = b0.relaxed_map(it.a, _curves(it.bnds, 0), gmres_tol, 1.0)
    else:
        f0 = _own_map(
            b0, it.a, name, mesh, _curves(it.bnds, 0), gmres_tol, guess, tally.reusable(0, sweep)
        )
    if phase != "material" and sweep == 1:
        assert isinstance(f0, CurveMap)
        tally.first(0, f0)
    else:
        tally.add(f0)
    out = _apply(f0, it.bnds, 0, it.c)
    _check_images(_curves(it.bnds, 0), out[: it.c.size], False, name, sweep)
    if phase != "material":
        _regrid(b0, _curves(it.bnds, 0), name, sweep)
    it.c, it.D, it.a = out[: it.c.size], it.D * f0.scale, 0j


def _sweep(
    it: _Iterate,
    sweep: int,
    phase: str,
    omega: float,
    meshes: list[BoundaryMesh],
    guess: list[FloatArray | None],
    tally: _Tally,
    gmres_tol: float,
    first_hole: int = 1,
    order: list[int] | None = None,
) -> None:
    """One sweep of the iteration ([1], secs. 3-4): every hole's map in ``order`` (default
    1..M), then the outer one (from position ``first_hole`` of that order on: a first sweep
    resumed from a snapshot, :func:`_resume`). A recording first sweep keeps snapshots of the
    iterate before some of its maps (:data:`SNAPSHOTS`, by position in the order)."""
    M = len(it.bnds) - 1
    seq = list(range(1, M + 1)) if order is None else order
    for pos in range(first_hole, M + 2):
        if sweep == 1 and tally.snapshots is not None and pos in _snapshot_positions(M):
            tally.snapshots[pos] = copy.deepcopy(it)
        if pos <= M:
            k = seq[pos - 1]
            _map_hole(it, k, sweep, phase, omega, meshes[k], guess[k], tally, gmres_tol)
    _map_outer(it, sweep, phase, meshes[0], guess[0], tally, gmres_tol)


#: Snapshots of the first sweep's iterate kept for a re-solve of the same level with some
#: sides refined (:func:`_resume`): before the first hole, every ``ceil(M / SNAPSHOTS)``-th
#: hole of the sweep's order and the outer boundary's map (position M + 1). Key 0 holds the
#: order itself (a resume needs the same order).
SNAPSHOTS = 8


def _snapshot_positions(M: int) -> set[int]:
    step = max(1, -(-M // SNAPSHOTS))
    return set(range(1, M + 1, step)) | {M + 1}


def _changed(init: _Iterate, meshes: list[BoundaryMesh]) -> list[int]:
    """Boundaries whose graded mesh differs from the snapshot's initial one (bit for bit)."""
    return [
        i
        for i, (b, m) in enumerate(zip(init.bnds, meshes, strict=True))
        if not (
            b.P.shape == m.eta.shape
            and bool(np.array_equal(b.P, m.eta))
            and bool(np.array_equal(b.dP, m.deta))
        )
    ]


def _resume(
    it: _Iterate,
    snapshots: dict[int, Any],
    reuse: list[CurveMap | None],
    meshes: list[BoundaryMesh],
    tally: _Tally,
    order: list[int],
) -> int:
    """Start a first sweep from a previous solve's snapshot (:data:`SNAPSHOTS`) instead of
    the polygon domain, where every map before it is reused anyway (:func:`_reusable`): the
    last snapshot at or before the first boundary (in the sweep's ``order``, which must be the
    previous solve's) whose mesh changed.
    The snapshot's iterate is the previous solve's state there; the changed boundaries' nodes
    (not mapped yet at that point) are moved by the same maps the snapshot's boundaries were
    moved by -- the reused ones, evaluated with their derivatives as :func:`_apply` does --
    so the iterate is the one a first sweep through those maps gives. Returns the position in
    the order to go on from (1: nothing resumed, ``it`` untouched)."""
    init = snapshots.get(1)
    M = len(it.bnds) - 1
    if init is None or len(init.bnds) != M + 1 or not reuse:
        return 1
    if snapshots.get(0) != tuple(order):
        return 1
    if not (np.array_equal(init.c, it.c) and init.a == it.a and init.D == it.D):
        return 1
    changed = _changed(init, meshes)
    seq = [*order, 0]  # the boundary mapped at each position 1..M + 1
    first = next((pos + 1 for pos, i in enumerate(seq) if i in changed), M + 2)
    p = max((k for k in snapshots if 1 <= k <= first and k <= M + 1), default=1)
    if p <= 1 or any(reuse[seq[k - 1]] is None for k in range(1, p)):
        return 1
    state = copy.deepcopy(snapshots[p])
    for i in changed:
        fresh = it.bnds[i]
        P, dP = fresh.P, fresh.dP
        for k in range(1, p):
            cm = reuse[seq[k - 1]]
            assert cm is not None
            fz, dfz = cm.evaluate(P, derivative=True)
            assert dfz is not None
            P, dP = fz, dP * dfz
        fresh.P, fresh.dP = np.asarray(P), np.asarray(dP)
        state.bnds[i] = fresh
    for k in range(1, p):
        cm = reuse[seq[k - 1]]
        assert cm is not None
        tally.first(seq[k - 1], cm)
    it.bnds, it.c, it.a, it.D = state.bnds, state.c, state.a, state.D
    return p


@dataclass
class _Before:
    """What a sweep's change is measured against: the parameters u, the passive node images
    (only where positions are compared) and the centres before the sweep."""

    u: list[FloatArray | None]
    p: list[ComplexArray]
    c: ComplexArray
    by_position: bool

    @classmethod
    def of(cls, it: _Iterate, by_position: bool) -> _Before:
        u = [None if b.u is None else b.u.copy() for b in it.bnds]
        p = [b.passive()[0] for b in it.bnds] if by_position else []
        return cls(u, p, it.c.copy(), by_position)


def _circle_radii(it: _Iterate) -> FloatArray:
    """Radius of every boundary's circle, the outer one's (1) first."""
    return np.array([1.0] + [_radius(it.bnds[j], it.c[j - 1]) for j in range(1, len(it.bnds))])


def _sweep_change(it: _Iterate, before: _Before, radii: FloatArray) -> float:
    """The convergence measure of a sweep (module docstring): the change of the boundary
    correspondence (arc length moved on each circle, ``|du| r``) away from the vertices, or of
    the passive node positions after a sweep that kept its grids, and of the centres."""
    if before.by_position:
        change = max(
            float(np.max(np.abs(b.passive()[0][b.mask] - po[b.mask])))
            for b, po in zip(it.bnds, before.p, strict=True)
        )
    else:
        change = max(
            (float(np.max(np.abs(b.u[b.mask] - uo[b.mask]))) * r if uo is not None else 1.0)
            for b, uo, r in zip(it.bnds, before.u, radii, strict=True)
            if b.u is not None
        )
    if it.c.size:
        change = max(change, float(np.max(np.abs(it.c - before.c))))
    return change


def _check_crowding(radii: FloatArray) -> None:
    """A hole circle below :data:`CROWDING_RADIUS` cannot be resolved (docs/METHOD.md sec. 6)."""
    if radii.size and radii.min() < CROWDING_RADIUS:
        j = int(np.argmin(radii))
        raise CrowdingError(
            f"obstacle {j}'s circle has radius {radii[j]:.1e}: too small to resolve in double "
            "precision (crowding: a long, narrow passage leads to it)"
        )


def _extrapolate_iterate(
    it: _Iterate,
    grids_before: list[tuple[ComplexArray, ComplexArray]],
    D_before: complex,
    rho: float,
) -> None:
    """Move the whole domain along the geometric tail of the sweep map G:
    ``z -> z + (w - 1)(G(z) - z)``, w = 1/(1 - rho) (Aitken's delta^2 on the slowest mode,
    :func:`confnav.conformal.acceleration.extrapolate_curve`); D follows as H'(anchor) of
    H = (1 - w) id + w G."""
    w_ext = 1.0 / (1.0 - rho)
    for b, (S0, dS0) in zip(it.bnds, grids_before, strict=True):
        assert b.S is not None and b.dS is not None
        b.S, b.dS = extrapolate_curve(S0, dS0, b.S, b.dS, w_ext)
    it.D = D_before * ((1.0 - w_ext) + w_ext * it.D / D_before)


#: Geometric modes an extrapolation removes (1: the slowest, with the contraction observed
#: on the changes, one sweep keeping its grids, :func:`_extrapolate_iterate`; k > 1:
#: minimal polynomial extrapolation of degree k from k + 1 sweeps keeping their grids,
#: :func:`_extrapolate_modes`).
EXTRAPOLATE_MODES = 2
#: Largest weight |gamma_j| a multi-mode extrapolation may put on one state (beyond it the
#: fitted polynomial has a root near 1: the one-mode tail is used instead).
GAMMA_MAX = 40.0


def _plain_sweeps_left(remaining: float, rho: float, tol: float) -> float:
    """Plain sweeps that would take a remaining error down to ``tol`` at contraction rho.
    A multi-mode extrapolation is started only if more than its cycle (k + 1 sweeps keeping
    their grids, the confirming one and the two plain ones that certify) would be needed."""
    if remaining <= tol:
        return 0.0
    return float(np.log(tol / remaining) / np.log(rho))


def _stack_states(
    trail: list[tuple[list[tuple[ComplexArray, ComplexArray]], complex]], last: list[_Boundary]
) -> list[list[tuple[ComplexArray, ComplexArray]]] | None:
    """The grids of every state of ``trail`` and of the current one (``last``), each
    boundary's upsampled to its current size (exact FFT interpolation); None if a grid
    shrank."""
    now = [(b.S, b.dS) for b in last if b.S is not None and b.dS is not None]
    states: list[list[tuple[ComplexArray, ComplexArray]]] = []
    for grids, _D in trail:
        if len(grids) != len(now):
            return None
        row = []
        for (S, dS), (S1, _dS1) in zip(grids, now, strict=True):
            if S.size > S1.size:
                return None
            if S.size < S1.size:
                S, dS = upsample(np.stack([S, dS]), S1.size)
            row.append((S, dS))
        states.append(row)
    states.append(now)  # type: ignore[arg-type]
    return states


def _mpe_weights(x: list[ComplexArray]) -> FloatArray | None:
    """MPE weights gamma_0 .. gamma_k (sum 1) of the states x_1 .. x_(k+1) from the states
    x_0 .. x_(k+1) (:func:`_extrapolate_modes`); None if not usable."""
    k = len(x) - 2
    u = [x[j + 1] - x[j] for j in range(k + 1)]
    A = np.stack([np.concatenate([v.real, v.imag]) for v in u[:k]], axis=1)
    rhs = -np.concatenate([u[k].real, u[k].imag])
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(rhs))):
        return None
    c = np.append(np.linalg.lstsq(A, rhs, rcond=None)[0], 1.0)
    total = float(np.sum(c))
    if not np.isfinite(total) or abs(total) < 1.0 / GAMMA_MAX:
        return None
    gamma = c / total
    if float(np.max(np.abs(gamma))) > GAMMA_MAX:
        return None
    return np.asarray(gamma)


def _extrapolate_modes(
    it: _Iterate, trail: list[tuple[list[tuple[ComplexArray, ComplexArray]], complex]]
) -> bool:
    """Minimal polynomial extrapolation (MPE; A. Sidi, "Vector Extrapolation Methods with
    Applications", SIAM 2017, ch. 1-2) of the states x_0 .. x_k (the trail, k of them) and
    x_{k+1} (now), every grid point the image of the same point under the sweep map G: with
    the differences u_j = x_{j+1} - x_j, real c_0 .. c_{k-1} minimise
    ``|| sum_j c_j u_j + u_k ||`` (real least squares over the grid points: the linearised
    sweep is real-linear, its modes real or conjugate pairs), ``gamma_j = c_j / sum c``
    (c_k = 1), and the domain moves to ``H = sum_j gamma_j G^(j+1)`` applied to x_0: exact
    for an error in k geometric modes, whatever their ratios. An affine combination of the
    maps with real weights, so H is analytic wherever the G^j are (the iterate stays a
    conformal image of the polygon domain, as for the one-mode tail), with derivative along
    the curves ``sum gamma_j dS_(j+1)`` and ``D = sum gamma_j D_(j+1)``. False (nothing moved)
    if the grids changed size or the weights are not usable (``sum c`` near 0, a mode at 1,
    or some |gamma_j| above :data:`GAMMA_MAX`)."""
    states = _stack_states(trail, it.bnds)
    if states is None:
        return False
    gamma = _mpe_weights([np.concatenate([S for S, _ in st]) for st in states])
    if gamma is None:
        return False
    Ds = [D for _g, D in trail[1:]] + [it.D]
    for i, b in enumerate(b for b in it.bnds if b.S is not None and b.dS is not None):
        b.S = np.asarray(sum(g * st[i][0] for g, st in zip(gamma, states[1:], strict=True)))
        b.dS = np.asarray(sum(g * st[i][1] for g, st in zip(gamma, states[1:], strict=True)))
    it.D = complex(sum(g * D for g, D in zip(gamma, Ds, strict=True)))
    return True


@dataclass
class _Schedule:
    """Which kind of sweep comes next, and when the iteration stops.

    Phases: ``"plain"`` sweeps (all of them with ``accel="none"``); ``"relaxed"``: hole maps
    over-relaxed by omega (``"sor"``); ``"material"``: a plain sweep keeping every grid, then
    extrapolated, and ``"confirm"``: the plain sweep that accepts or rejects that
    (``"extrapolate"``); ``"final"``: plain sweeps after the relaxed ones, whose own history
    certifies the result. Stopping uses the geometric tail of the changes (module docstring).
    """

    accel: str
    tol: float
    phase: str = "plain"
    omega: float = 1.0
    history: list[float] = field(default_factory=list)
    #: changes since the phase began (the contraction the stopping test trusts)
    phase_history: list[float] = field(default_factory=list)
    relaxed_sweeps: int = 0
    extrapolations: int = 0
    rejected: int = 0
    hold: int = 0  # no extrapolation before this sweep (after a rejected one)
    rho_ext: float = 0.0
    prev_change: float = 0.0
    grids_before: list[tuple[ComplexArray, ComplexArray]] = field(default_factory=list)
    D_before: complex = 1.0 + 0j
    #: The states before each material sweep of the current run (:data:`EXTRAPOLATE_MODES`
    #: > 1): the grids (with their s-derivatives) and D.
    trail: list[tuple[list[tuple[ComplexArray, ComplexArray]], complex]] = field(
        default_factory=list
    )
    #: Extrapolations that fell back to the one-mode tail (the fitted polynomial unusable).
    single_mode: int = 0
    snapshot: tuple[list[_Boundary], ComplexArray, complex] | None = None
    remaining: float = float("inf")
    converged: bool = False
    #: Smallest contraction assumed: after a transplant (:func:`_transplant`), the one the
    #: previous levels observed (:attr:`LevelCarry.rho`).
    rho_floor: float = 0.0
    #: The next sweep follows a transplant: the passive nodes moved with their curves while
    #: keeping their parameters u, so its change is measured on their positions.
    after_transplant: bool = False

    def before_sweep(self, it: _Iterate) -> _Before:
        """Prepare a sweep: an extrapolating one keeps its start (grids, D) to extrapolate
        from. After a sweep that kept its grids a change of u is no change of position (the
        holes kept their parameters u while their curves moved): such sweeps and the plain
        sweep after them measure the change on the passive node images themselves; every
        other sweep measures it as plain sweeps do (a run no acceleration acts on is the
        plain run)."""
        if self.phase == "material":
            self.omega = 1.0
            self.grids_before = [
                (b.S.copy(), b.dS.copy()) for b in it.bnds if b.S is not None and b.dS is not None
            ]
            self.D_before = it.D
            self.trail.append((self.grids_before, it.D))
        by_position = (
            self.relaxing
            or self.phase == "confirm"
            or (self.phase == "final" and not self.phase_history)
            or self.after_transplant
        )
        self.after_transplant = False
        return _Before.of(it, by_position)

    @property
    def relaxing(self) -> bool:
        """This sweep moves the holes by relaxed maps on their grids (no regrid)."""
        return self.phase in ("relaxed", "material")

    def record(self, change: float) -> None:
        if self.relaxing:
            self.relaxed_sweeps += 1
        self.history.append(change)
        self.phase_history.append(change)

    def after_sweep(self, it: _Iterate, sweep: int, change: float) -> bool:
        """Choose the next sweep's phase; True when the iteration stops."""
        if self.phase == "material":
            if EXTRAPOLATE_MODES > 1 and len(self.trail) <= EXTRAPOLATE_MODES:
                return False  # k modes need k + 1 sweeps keeping their grids
            self._extrapolate(it, change)
            return False
        if self.phase == "confirm":
            if not change < self.prev_change:
                self._reject(it, sweep)
                return False
            self.phase = "plain"
        if self._start_extrapolation(sweep) or self._start_relaxation(sweep):
            return False
        if self.phase == "relaxed":
            self._relaxation_step(change)
            return False
        if (self.phase == "final" or self.extrapolations) and len(
            self.phase_history
        ) < STALL_SWEEPS:
            return False  # at least three plain sweeps: two observed plain contractions
        return self._converged_or_stalled(change)

    def _extrapolate(self, it: _Iterate, change: float) -> None:
        """Extrapolate the sweep just done (:func:`_extrapolate_iterate`), keeping the state
        before it; the next plain sweep must confirm it."""
        self.snapshot = (copy.deepcopy(it.bnds), it.c.copy(), it.D)
        self.prev_change = change
        trail, self.trail = self.trail, []
        if len(trail) < 2 or not _extrapolate_modes(it, trail):
            if len(trail) >= 2:
                self.single_mode += 1
            _extrapolate_iterate(it, self.grids_before, self.D_before, self.rho_ext)
        self.extrapolations += 1
        self.phase, self.phase_history = "confirm", []

    def _reject(self, it: _Iterate, sweep: int) -> None:
        """The confirming sweep did not shrink the change: back to the state before the
        extrapolation, and no new one for :data:`EXTRAPOLATE_WAIT` sweeps."""
        assert self.snapshot is not None
        it.bnds, it.c, it.D = self.snapshot
        it.a = 0j
        self.rejected += 1
        self.phase, self.phase_history = "plain", []
        self.hold = sweep + EXTRAPOLATE_WAIT

    def _start_extrapolation(self, sweep: int) -> bool:
        """Extrapolate next when two successive plain contraction ratios agree, rho in
        (RHO_EXTRAPOLATE_MIN, RHO_MAX), and the tolerance is not met yet."""
        h = self.phase_history
        if not (
            self.accel == "extrapolate"
            and self.phase == "plain"
            and sweep >= max(4, self.hold)
            and len(h) >= 3
        ):
            return False
        r1 = h[-1] / max(h[-2], 1e-300)
        r0 = h[-2] / max(h[-3], 1e-300)
        rem, ok = _remaining_error(h)
        if EXTRAPOLATE_MODES > 1:  # the fit needs no agreeing ratios, but must pay
            agree = ok and _plain_sweeps_left(rem, r1, self.tol) > EXTRAPOLATE_MODES + 4
        else:
            agree = abs(r1 - r0) <= RATIO_AGREE * r1
        rho_min = RHO_EXTRAPOLATE_MIN if EXTRAPOLATE_MODES == 1 else RHO_EXTRAPOLATE_MIN_MODES
        if rho_min < r1 < RHO_MAX and agree and not (ok and rem <= self.tol):
            self.rho_ext = min(r1, RHO_EXTRAPOLATE)
            self.phase = "material"
            return True
        return False

    def _start_relaxation(self, sweep: int) -> bool:
        """Over-relax next once two successive plain contraction ratios agree (the slowest
        mode dominates): Young's omega from the observed contraction (``optimal_omega``)."""
        if not (self.accel == "sor" and self.phase == "plain" and sweep >= 4):
            return False
        h = self.history
        r1 = h[-1] / max(h[-2], 1e-300)
        r0 = h[-2] / max(h[-3], 1e-300)
        self.omega = optimal_omega(r1) if abs(r1 - r0) <= RATIO_AGREE * r1 else 1.0
        if self.omega > 1.0:
            self.phase, self.phase_history = "relaxed", []
            return True
        return False

    def _relaxation_step(self, change: float) -> None:
        """Halve the over-relaxation when the change grows (it overshoots); end it with plain
        sweeps once the tolerance is met or omega is nearly 1."""
        rem, ok = _remaining_error(self.phase_history)
        grew = len(self.phase_history) > 1 and change > self.phase_history[-2]
        if grew:
            self.omega = 1.0 + 0.5 * (self.omega - 1.0)
        if (ok and rem <= self.tol) or self.omega < 1.05 or not np.isfinite(change):
            self.phase, self.phase_history = "final", []  # plain sweeps certify the result

    def _converged_or_stalled(self, change: float) -> bool:
        """Stop when the extrapolated remaining error is below ``tol``, or when the change has
        not decreased for :data:`STALL_SWEEPS` sweeps (rounding floor or a true stall)."""
        h = self.phase_history
        self.remaining, self.converged = _remaining_error(h, self.rho_floor)
        if self.converged and self.remaining <= self.tol:
            return True
        if len(h) > STALL_SWEEPS and change >= min(h[-STALL_SWEEPS - 1 : -1]):
            self.converged = False  # no progress: rounding floor or a true stall -- reported
            return True
        return False

    def certify(self) -> tuple[float, bool]:
        """The reported iteration error and whether it meets ``tol``: a run stopped before the
        final plain sweeps could certify anything counts as unfinished (infinite remaining
        error); an unconverged run reports :func:`_stalled_error`."""
        if self.phase in ("relaxed", "material", "confirm") or (
            (self.extrapolations or self.relaxed_sweeps) and len(self.phase_history) < STALL_SWEEPS
        ):
            self.remaining, self.converged = float("inf"), False
        h = (
            self.phase_history
            if len(self.phase_history) >= 2
            else self.history[-STALL_SWEEPS - 1 :]
        )
        if self.converged and self.remaining <= self.tol:
            error = self.remaining
        else:
            error = _stalled_error(h)
        return error, bool(self.converged and error <= self.tol)


def _count_final_tails(bnds: list[_Boundary]) -> None:
    """The final passive nodes are interpolated from each smooth grid as the last sweep left
    it (moved by the maps after its own): its Fourier tail there is a resolution error too,
    whether or not a sweep solved on it."""
    for b in bnds:
        if b.S is not None:
            tail = _tail(b.S)
            if tail > b.tail:
                b.capped_tail = max(b.capped_tail, tail)


def _circle_domain(
    it: _Iterate, tally: _Tally, sched: _Schedule, sweeps: int, t0: float
) -> CircleDomainResult:
    """The result: the passive nodes as the boundary images W, the centres and radii, all
    rotated by ``e^{-i arg D}`` so that T'(anchor) > 0 (docs/METHOD.md sec. 2, "Final
    rotation"), and the circularity of W (its distance from the circles)."""
    iteration_error, converged = sched.certify()
    _count_final_tails(it.bnds)
    M = len(it.bnds) - 1
    rot = complex(np.exp(-1j * np.angle(it.D)))
    passive = [b.passive() for b in it.bnds]
    W = [p[0] * rot for p in passive]
    dW = [p[1] * rot for p in passive]
    c = it.c * rot
    radii = np.array([_radius(it.bnds[j], c[j - 1] / rot) for j in range(1, M + 1)])
    circ = float(np.max(np.abs(np.abs(W[0]) - 1.0)))
    for j in range(1, M + 1):
        circ = max(circ, float(np.max(np.abs(np.abs(W[j] - c[j - 1]) - radii[j - 1]))))
    return CircleDomainResult(
        W=W,
        dW=dW,
        centers=c,
        radii=radii,
        derivative_at_anchor=float(abs(it.D)),
        sweeps=sweeps,
        history=sched.history,
        circularity=circ,
        gmres_iterations=tally.iterations,
        smooth_nodes=[b.m for b in it.bnds],
        wall_time=time.perf_counter() - t0,
        iteration_error=iteration_error,
        converged=converged,
        resolution_error=max(b.capped_tail for b in it.bnds),
        first_mu=tally.first_mu,
        first_maps=tally.first_maps,
        reused_first_maps=tally.reused,
        first_snapshots=tally.snapshots or {},
        gmres_residual=tally.residual,
        relaxed_sweeps=sched.relaxed_sweeps,
        omega=sched.omega,
        extrapolations=sched.extrapolations,
        rejected_extrapolations=sched.rejected,
    )


#: Taylor order of the transplant's evaluation of a trigonometric interpolant off the real
#: parameter axis (:func:`_transplant`), and its Newton steps per expansion point.
TRANSPLANT_ORDER = 8
TRANSPLANT_NEWTON = 4
#: A transplant is used only if every point is found on the previous level's curve to this
#: (relative to the curve's size) and the Taylor term dropped is below it.
TRANSPLANT_RTOL = 1e-14
#: The transplant's Cauchy integral for the anchor's image needs the anchor this many local
#: grid spacings from every curve: ln(1/eps)/pi with eps = 1e-16 (the rule of
#: :func:`_local_grid_size`: the trapezoid rule's error decays like exp(-pi d/h)).
ANCHOR_SPACINGS = float(np.log(1e16) / np.pi)
#: Tracers per smooth-grid point (the interpolant of Phi on a curve needs more modes than the
#: curve: Phi's singularities lie nearer than the curve's).
TRACER_FACTOR = 2


@dataclass
class LevelCarry:
    """A converged level's sweeps after its first as boundary data: the next mesh level's
    start (cross-level warm start, :func:`_transplant`).

    The sweeps after the first map the domain the first sweep left (each boundary a smooth
    analytic curve) conformally onto the circle domain; this map Phi is recorded on each
    boundary as the trigonometric interpolant of tracer points: ``curves[j]`` are the first
    sweep's smooth grid of boundary j (uniform in its parameter s, Moebius grading
    ``grading[j]``), ``images[j]`` the same points at convergence (before the final rotation).
    ``dscale`` is Phi'(0) (the anchor sits at 0 after every sweep, Phi(0) = 0) and ``centers``
    the converged hole centres (points inside the holes' images)."""

    curves: list[ComplexArray]
    grading: list[complex]
    images: list[ComplexArray]
    dscale: complex
    centers: ComplexArray
    #: The contraction per sweep observed (the larger of the last two ratios), never below
    #: the one carried into that level: the cold first level's, over its whole run.
    rho: float = 0.0


def _lay_tracers(it: _Iterate) -> tuple[list[ComplexArray], list[complex], complex]:
    """Tracers on every boundary's smooth grid after the first sweep (their u: the angle at
    which each grid point was laid); returns the grids, their gradings and D."""
    curves, grading = [], []
    for b in it.bnds:
        assert b.S is not None
        m = TRACER_FACTOR * b.S.size
        s_grid = 2 * np.pi * np.arange(m) / m
        b.tu = _mobius_grid(b.c, -1.0 if b.hole else 1.0, s_grid)[2]
        curves.append(upsample(b.S, m) if m > b.S.size else b.S.copy())
        grading.append(b.c)
    return curves, grading, it.D


def _tracer_images(it: _Iterate) -> list[ComplexArray]:
    """The tracers' positions: each smooth curve at their parameters (as :meth:`passive`)."""
    out = []
    for b in it.bnds:
        assert b.S is not None and b.tu is not None
        s_t = _mobius_param(b.c, -1.0 if b.hole else 1.0, b.tu)[0]
        out.append(trig_eval(np.stack([b.S]), s_t)[0])
    return out


def _derivative_rows(samples: ComplexArray, order: int) -> ComplexArray:
    """Samples of the trigonometric interpolant and its first ``order`` s-derivatives."""
    rows = [np.asarray(samples, np.complex128)]
    for _ in range(order):
        rows.append(spectral_derivative_complex(rows[-1]))
    return np.stack(rows)


def _taylor(at: ComplexArray, delta: ComplexArray) -> tuple[ComplexArray, ComplexArray]:
    """f(sigma + delta) and f'(sigma + delta) from f^(n)(sigma), n = 0..Q (rows of ``at``)."""
    q = at.shape[0] - 1
    val = at[q] / factorial(q)
    der = at[q] / factorial(q - 1)
    for n in range(q - 1, -1, -1):
        val = val * delta + at[n] / factorial(n)
        if n >= 1:
            der = der * delta + at[n] / factorial(n - 1)
    return val, der


def _transplant_curve(
    b: _Boundary, C: ComplexArray, c_old: complex, X: ComplexArray
) -> tuple[ComplexArray, ComplexArray] | None:
    """Phi on boundary b's smooth grid: each grid point z is found on the recorded curve C
    (the interpolant at a complex parameter sigma + delta, Newton's method on a Taylor
    expansion about a real sigma), and Phi(z) is X's interpolant there -- its analytic
    continuation off the curve (Henrici Vol. 3, sec. 13.3; the interpolant of an analytic
    periodic function is analytic in a strip). None if a point is not found to
    :data:`TRANSPLANT_RTOL` or the Taylor series does not converge to it."""
    assert b.S is not None and b.dS is not None
    sgn = -1.0 if b.hole else 1.0
    size = float(np.max(np.abs(C)))
    s_grid = 2 * np.pi * np.arange(b.S.size) / b.S.size
    # the same laid angle on the recorded grid: the first guess of the parameter
    sigma = _mobius_param(c_old, sgn, _mobius_grid(b.c, sgn, s_grid)[2])[0]
    s_of = 2 * np.pi * TRACER_FACTOR / C.size  # parameter spacing of the recorded grid
    rows_C = _derivative_rows(C, TRANSPLANT_ORDER)
    rows_X = _derivative_rows(X, TRANSPLANT_ORDER)
    z = b.S
    for _round in range(2):  # the second round re-centres the expansion on the real part
        at = trig_eval(rows_C, sigma)
        delta = np.zeros(z.size, np.complex128)
        for _ in range(TRANSPLANT_NEWTON):
            val, der = _taylor(at, delta)
            delta = delta - (val - z) / der
        if not np.all(np.isfinite(delta)) or np.max(np.abs(delta)) > s_of:
            return None
        sigma = sigma + delta.real
    at = trig_eval(rows_C, sigma)
    delta = np.zeros(z.size, np.complex128)
    for _ in range(TRANSPLANT_NEWTON):
        val, der = _taylor(at, delta)
        delta = delta - (val - z) / der
    val, der = _taylor(at, delta)
    q = TRANSPLANT_ORDER
    dropped = np.max(np.abs(at[q]) * np.abs(delta) ** q) / factorial(q)
    found = float(np.max(np.abs(val - z)))
    if not (found <= TRANSPLANT_RTOL * size and dropped <= TRANSPLANT_RTOL * size):
        return None
    atX = trig_eval(rows_X, sigma)
    if np.max(np.abs(atX[q]) * np.abs(delta) ** q) / factorial(q) > TRANSPLANT_RTOL * size:
        return None
    Xz, dXz = _taylor(atX, delta)
    return Xz, dXz / der * b.dS


def _anchor_resolved(it: _Iterate) -> bool:
    """Grids on which the anchor keeps :data:`ANCHOR_SPACINGS` local grid spacings from every
    curve, as :func:`_transplant`'s Cauchy formula needs: a grid too coarse for that is
    upsampled first (FFT interpolation of the analytic curve, exact to its resolved tail, as
    :meth:`_Boundary._resolve` refines a grid for near boundaries). With grid sizes rounded to
    powers of two the margin had come by chance; with sizes rounded to eighths of an octave
    (:data:`GRID_STEPS`) a hole 9.9 spacings from the anchor refused every transplant of the
    default workspace shrunk by 0.2 m. False if the size needed exceeds :data:`SMOOTH_MAX`."""
    for b in it.bnds:
        if b.S is None or b.dS is None:
            return False
        h = np.abs(b.dS) * 2 * np.pi / b.S.size
        ratio = float(np.min(np.abs(b.S - it.a) / np.maximum(h, 1e-300)))
        if ratio >= ANCHOR_SPACINGS:
            continue
        m = _round_size(b.S.size * ANCHOR_SPACINGS / max(ratio, 1e-300))
        if not ratio > 0 or m > SMOOTH_MAX or _tail(b.S) > b.tail:
            return False
        b.S, b.dS = upsample(np.stack([b.S, b.dS]), m)
    return True


def _transplant(it: _Iterate, carry: LevelCarry) -> bool:
    """Start the sweeps after the first from the previous mesh level's converged map.

    The first sweep of this level (on its own graded meshes) leaves a domain whose smooth
    boundary curves lie within the two levels' discretisation difference of the previous
    level's first-sweep curves; the previous level's map Phi of that domain onto its circle
    domain (:class:`LevelCarry`) is analytic across them, and applied here, continued by each
    boundary's interpolant (:func:`_transplant_curve`), it leaves a domain within about that
    difference of a circle domain, so the sweeps start there instead of ~1 away. Phi is one
    analytic map applied to the whole domain (grids, their derivatives, the passive nodes
    through their parameters u, D), so the fixed point -- this level's circle domain -- is
    unchanged, as for the accelerations (:mod:`confnav.conformal.acceleration`); the
    interpolants must resolve Phi to the smooth grids' own tail (else no transplant), and the
    passive nodes follow their curves. False (state untouched, but for grids upsampled by
    :func:`_anchor_resolved`: the same curves) if any boundary fails."""
    if len(carry.curves) != len(it.bnds):
        return False
    if not _anchor_resolved(it):
        return False
    new = []
    for b, C, c_old, X in zip(it.bnds, carry.curves, carry.grading, carry.images, strict=True):
        if b.S is None or _tail(C) > b.tail or _tail(X) > b.tail:
            return False
        moved = _transplant_curve(b, C, c_old, X)
        if moved is None:
            return False
        new.append(moved)
    for j in range(1, len(it.bnds)):
        if abs(_winding(new[j][0], complex(carry.centers[j - 1]))) < 0.5:
            return False
    # the anchor's image (it.a = 0 after every sweep) and Phi's derivative there from the same
    # boundary values, by the Cauchy formula over the whole boundary (positively oriented:
    # outer ccw, holes cw), as every map of a sweep carries the anchor: consistent with the
    # transplanted curves to their own resolution, not only with carry.dscale
    # (the trapezoid rule resolves the Cauchy integrand only where the anchor keeps
    # ANCHOR_SPACINGS local grid spacings from every curve: else no transplant -- measured on
    # a 0.2 m ring corridor with the anchor 0.1 from the hole, whose map then missed its
    # boundary residual by 4.7e-4 at every level)
    num = den = der = 0j
    for b in it.bnds:
        assert b.S is not None and b.dS is not None
        h = np.abs(b.dS) * 2 * np.pi / b.S.size
        if float(np.min(np.abs(b.S - it.a) / np.maximum(h, 1e-300))) < ANCHOR_SPACINGS:
            return False
    for b, (S, _dS) in zip(it.bnds, new, strict=True):
        assert b.S is not None and b.dS is not None
        w = b.dS / (b.S - it.a) / b.S.size  # (1/2 pi i) ∮ . dzeta / (zeta - a), trapezoid / i
        num += complex(np.sum(S * w))
        den += complex(np.sum(w))
        der += complex(np.sum(S * w / (b.S - it.a)))
    a_new, d_new = num / den, der / den
    if not (np.isfinite(a_new) and np.isfinite(d_new) and abs(d_new) > 0):
        return False
    for b, (S, dS) in zip(it.bnds, new, strict=True):
        b.S, b.dS = S, dS
    it.c = np.array(carry.centers, dtype=np.complex128)
    it.a = complex(a_new)
    it.D = it.D * complex(d_new)
    return True


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
    start: StartImage | None = None,
    carry: LevelCarry | None = None,
    trace: bool = False,
    reuse_first: list[CurveMap | None] | None = None,
    snapshots: bool = False,
    reuse_snapshots: dict[int, Any] | None = None,
    order: list[int] | None = None,
) -> CircleDomainResult:
    """Run the iteration on graded meshes (outer counter-clockwise, holes clockwise).

    Sweeps (:func:`_sweep`) until :class:`_Schedule` stops them, measuring each by
    :func:`_sweep_change`; then :func:`_circle_domain` (final rotation, result).

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
        ``"none"`` (plain sweeps), ``"sor"`` (over-relaxed hole maps) or ``"extrapolate"``
        (:mod:`confnav.conformal.acceleration`); None: :data:`KOEBE_ACCEL`. Accelerated runs
        end with plain sweeps whose own history (at least three sweeps) gives the reported
        iteration error, so the certificate never rests on accelerated sweeps.
    start
        Start from this conformal image of the domain (:class:`StartImage`) instead of the
        polygon domain (a warm re-solve); ``hole_points`` and ``anchor`` are then unused.
    carry
        The previous mesh level's converged map (its result's ``carry``): applied after the
        first sweep (:func:`_transplant`).
    trace
        Record this level's map for the next level (the result's ``carry``; not with
        ``start``); the same sweeps as an untraced run (the tracers only follow them).
    reuse_first
        A previous solve's first-sweep maps (its result's ``first_maps``, outer first): each
        boundary whose first-sweep equation is that solve's bit for bit (:func:`_reusable`:
        the same graded mesh, and every map before it in the sweep the same) takes its map
        instead of solving -- a re-solve of a level with some sides refined re-solves the
        graded equations from the first refined boundary on only.
    snapshots
        Keep snapshots of the first sweep's iterate (the result's ``first_snapshots``,
        :data:`SNAPSHOTS`; not with ``start``).
    reuse_snapshots
        A previous solve's ``first_snapshots`` (with its ``first_maps`` as ``reuse_first``):
        the first sweep starts at the last snapshot before the first changed mesh
        (:func:`_resume`) instead of applying the reused maps again.
    order
        The order in which every sweep maps the holes (:func:`_hole_order`).
    """
    accel = KOEBE_ACCEL if accel is None else accel
    if accel not in KOEBE_ACCELS:
        raise ValueError(f"accel must be one of {KOEBE_ACCELS}, got {accel!r}")
    t0 = time.perf_counter()
    M = len(meshes) - 1
    trace = trace and start is None and M > 0
    seq = _hole_order(order, M)
    it = _initial_iterate(meshes, hole_points, anchor, tol, start)
    guess: list[FloatArray | None] = (
        list(first_guess) if first_guess is not None else [None] * (M + 1)
    )
    tally = _Tally(
        first_mu=[None] * (M + 1),
        first_maps=[None] * (M + 1),
        reuse=list(reuse_first) if reuse_first is not None and len(reuse_first) == M + 1 else [],
        snapshots={0: tuple(seq)} if snapshots and start is None and M > 0 else None,
    )
    resumed = 1
    if reuse_snapshots and start is None and tally.reuse:
        resumed = _resume(it, reuse_snapshots, tally.reuse, meshes, tally, seq)
        if tally.snapshots is not None:  # the positions skipped: the same states (the
            # changed boundaries' nodes are replaced whenever a snapshot is resumed from)
            tally.snapshots.update({k: v for k, v in reuse_snapshots.items() if 0 < k < resumed})
    sched = _Schedule(accel, tol)
    sweeps, traced, transplanted = _run_sweeps(
        it, sched, meshes, guess, tally, gmres_tol, resumed, seq,
        max_sweeps=max_sweeps, progress=progress, start=start, trace=trace, carry=carry,
    )  # fmt: skip
    result = _circle_domain(it, tally, sched, sweeps, t0)
    result.transplanted, result.resumed_at, result.order = transplanted, resumed, seq
    if traced is not None and result.converged:
        result.carry = _level_carry(it, sched, traced)
    return result


def _hole_order(order: list[int] | None, M: int) -> list[int]:
    """The holes in the order every sweep maps them: a permutation of 1..M (default 1..M).
    The fixed point of the sweeps does not depend on it (each map is a conformal image of the
    domain); a level's first sweep does, to its discretisation error, which the certificate
    measures as before. A re-solve reusing first-sweep maps or snapshots must sweep in the
    order of the solve it reuses (its result's ``order``; :func:`_resume` checks it)."""
    seq = list(range(1, M + 1)) if order is None else [int(k) for k in order]
    if sorted(seq) != list(range(1, M + 1)):
        raise ValueError(f"order must be a permutation of the holes 1..{M}, got {order}")
    return seq


def _run_sweeps(
    it: _Iterate,
    sched: _Schedule,
    meshes: list[BoundaryMesh],
    guess: list[FloatArray | None],
    tally: _Tally,
    gmres_tol: float,
    resumed: int,
    order: list[int],
    *,
    max_sweeps: int,
    progress: Callable[[int, float], None] | None,
    start: StartImage | None,
    trace: bool,
    carry: LevelCarry | None,
) -> tuple[int, tuple[list[ComplexArray], list[complex], complex] | None, bool]:
    """:func:`koebe_iteration`'s sweeps until ``sched`` stops them: the number of sweeps, the
    tracers laid after the first (``trace``), and whether ``carry`` was transplanted."""
    M = len(meshes) - 1
    sweeps = 0
    traced: tuple[list[ComplexArray], list[complex], complex] | None = None
    transplanted = False
    for sweep in range(1, max_sweeps + 1):
        sweeps = sweep
        before = sched.before_sweep(it)
        _sweep(
            it,
            sweep,
            sched.phase,
            sched.omega,
            meshes,
            guess,
            tally,
            gmres_tol,
            resumed if sweep == 1 else 1,
            order,
        )
        radii = _circle_radii(it)
        change = _sweep_change(it, before, radii)
        sched.record(change)
        if progress is not None:
            progress(sweep, change)
        if not np.isfinite(change):
            raise ConvergenceError(f"Koebe iteration produced non-finite values in sweep {sweep}")
        if M == 0:  # the first sweep's interior map IS the Riemann map ([1], sec. 3)
            sched.remaining, sched.converged = 0.0, True
            break
        if sweep == 1 and start is None:
            _consistent_tangents(it)
        _check_crowding(radii[1:])
        if start is not None and sweep == 1:
            # the first sweep's change is no measurement (1 for a boundary without a previous
            # correspondence): from a warm start, whose second sweep may change by 1e-5 only,
            # its ratio to that 1 would stop the sweeps with an extrapolated error ~1e-10
            # while ~1e-8 are left (measured: boundary residual 1.0e-8 after 2 sweeps)
            sched.phase_history = []
            continue
        if sweep == 1 and trace:
            traced = _lay_tracers(it)
            if carry is not None and _transplant_after_first_sweep(it, sched, carry):
                transplanted = True
                continue
        if sched.after_sweep(it, sweep, change):
            break
    else:
        sched.converged = False  # sweep limit: the extrapolated remaining error is reported
    return sweeps, traced, transplanted


def _consistent_tangents(it: _Iterate) -> None:
    """Make every smooth grid's ``dS`` the derivative of its own curve after the first sweep.

    In the first sweep the maps are those of the polygons on their graded meshes, and a map's
    derivative at a point off its curve is the Cauchy integral of its boundary derivative
    (:meth:`~confnav.conformal.diskmap.CurveMap.evaluate`), not the derivative of the Cauchy
    integral giving the point: the two agree only to the mesh's discretisation error
    (measured on a 2 x 1 m room with a pillar: ``dS`` 5e-7 relative off the spectral
    derivative of ``S`` at 36 nodes per side, 2e-8 at 54; 1e-13 after the second sweep,
    whose maps are those of smooth grids). The sweeps after the first solve GNK equations on
    ``(S, dS)``, so with such a tangent the domain they map is not the one bounded by the
    curves ``S``, and the map they compose is not conformal on that domain to ~1e-9 --
    harmless within one level (its fixed point moves by its own discretisation error), but
    a carried level (:func:`_transplant`) continues that map off the curves and applies it
    to the next level's domain: the defect became a deformation no later sweep removes, and
    every carried level kept the coarsest level's boundary residual (9.2e-8 on that room,
    where the cold levels reach 8.6e-11). Here the curve ``S`` (resolved to its Fourier tail)
    defines the domain, and its tangent is its spectral derivative (Trefethen, "Spectral
    Methods in MATLAB", SIAM 2000, ch. 3)."""
    for b in it.bnds:
        if b.S is not None:
            b.dS = spectral_derivative_complex(b.S)


def _transplant_after_first_sweep(it: _Iterate, sched: _Schedule, carry: LevelCarry) -> bool:
    """Apply the previous level's map after this level's first sweep (:func:`_transplant`);
    False if it is refused. As from a warm start, the first sweep's change then says nothing
    about the sweeps after the transplant. The next one's is measured on the passive nodes'
    positions (their parameters u have not followed the transplant: u moves by Phi's
    correspondence in that sweep, ~0.3 measured), the contraction from there on, never taken
    below the one the cold first level observed over its whole run (``carry.rho``): the first
    changes after a transplant may shrink faster than the slowest mode does."""
    if not _transplant(it, carry):
        return False
    sched.phase_history = []
    sched.rho_floor = carry.rho
    sched.after_transplant = True
    return True


def _level_carry(
    it: _Iterate, sched: _Schedule, traced: tuple[list[ComplexArray], list[complex], complex]
) -> LevelCarry:
    """This converged level's map for the next level (:class:`LevelCarry`)."""
    curves, grading, D1 = traced
    return LevelCarry(
        curves=curves,
        grading=grading,
        images=_tracer_images(it),
        dscale=it.D / D1,
        centers=it.c.copy(),
        rho=max(_observed_rho(sched.phase_history), sched.rho_floor),
    )


def _remaining_error(history: list[float], rho_floor: float = 0.0) -> tuple[float, bool]:
    """Error left after the last sweep, from the observed linear contraction.

    With changes h_n shrinking by rho per sweep the iterate is h_n rho / (1 - rho) from the
    limit (geometric tail; Aitken's delta^2 estimate). rho is the larger of the last two
    observed ratios (the safe side; one after two sweeps) and ``rho_floor`` (after a
    transplant: the contraction the previous level observed over its longer run); a single
    sweep gives no estimate.
    """
    if len(history) < 2:
        return float("inf"), False
    h = history
    rho = max(h[i] / max(h[i - 1], 1e-300) for i in range(max(1, len(h) - 2), len(h)))
    rho = max(rho, rho_floor)
    if rho >= RHO_MAX:
        return float("inf"), False
    return h[-1] * rho / (1 - rho), True


def _observed_rho(history: list[float]) -> float:
    """The larger of the last two contraction ratios of a history (0: fewer than two)."""
    h = history
    if len(h) < 2:
        return 0.0
    return float(max(h[i] / max(h[i - 1], 1e-300) for i in range(max(1, len(h) - 2), len(h))))


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
    reuse: CurveMap | None = None,
) -> CurveMap:
    """``b.own_map`` with failures reported against the boundary and its sharpest corner."""
    try:
        corners = mesh.corner_blocks() if b.S is None and b.P.size == mesh.n else None
        return b.own_map(alpha, others, rtol, x0, corners, reuse)
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


__all__ = ["CROWDING_RADIUS", "CircleDomainResult", "StartImage", "koebe_iteration"]
