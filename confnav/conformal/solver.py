"""``solve(workspace, tol)``: the conformal navigation transformation with an error estimate.

The node count is chosen by refinement, not by a magic constant: the Koebe-type iteration is run
on graded meshes of increasing size (nodes per side from :data:`LEVELS`), and the change of the
circle domain (centres and radii) between consecutive levels gives the discretisation error of
the finer one. With grading exponent p the error decays like n^-p (docs/METHOD.md sec. 2), so each
step of ``LEVELS`` (x1.5) cuts it by about 7x.

The error estimate covers every error source (issues 8, 26), each measured on its own:

* discretisation: the level differences above, extrapolated with the slower of the assumed
  order and the contraction observed over three levels; an estimate with no observed
  contraction (two levels: ``nodes_per_side`` with a failed coarse level) or from differences
  that stopped shrinking is listed in ``unverified`` and never gives ``tol_met``;
* iteration: the Koebe iteration runs until its remaining error, extrapolated from the
  observed contraction, is below ``tol / 10``; a stalled or unfinished iteration is reported
  (``iteration_converged = False``), never taken as converged;
* a-posteriori: :meth:`ConformalMap.boundary_residual` -- T at points between the nodes on
  every side (midpoints, and points graded towards every corner) must land on its circle;
  not checked within ``CORNER_ZONE`` (1e-4 of the shorter side) of a corner, as the
  diagnostics' table states;
* size caps: a smooth grid held at its cap (in any sweep, the last one's regrid included) or
  left above its target tail by the last sweep adds its Fourier tail; a level that would need
  more nodes than the mesh allows (a gap too narrow) ends the refinement and is listed in
  ``caps``;
* linear solves: the largest residual any GMRES solve left (``gmres_residual``; a run accepted
  at up to ``GMRES_ACCEPT`` times its target counts with its measured residual);
* evaluation: once the map evaluates through local expansions, their truncation bound
  (``evaluation_error``).

Refining where the error is (issue 24): a level whose discretisation estimate is within
``tol / 2`` but whose boundary residual is not refines only the sides the residual names (and
their neighbours) to the next level's nodes (:func:`_refine_sides`); its estimate is the base
level's plus the change this causes (triangle inequality, no order assumed). Measured in
``bench/results/local_refinement.json`` and ``core_certificate.json`` (see bench/README.md):
two squares 0.01 apart to 1e-8 take four level solves instead of five (8 sides at 120 nodes
after 36, 54, 80; residual 1.17e-9 as with the full 180-node level; 114 s CPU against 141 s in
one process, the same map to 4e-14 in asymmetry). On 10 mixed obstacles the base estimate
(8.0e-9) left too little of 1e-8 for the change (2.4e-9), hence :data:`LOCAL_HEADROOM`.

Carried levels (issue 24 items 1-2, :data:`LEVEL_CARRY`): a level's sweeps after its first
start from the previous level's converged map (:class:`~confnav.conformal.circledomain.
LevelCarry`). Where the time went before (``bench/bench_core.py --profile``,
``bench/results/core_profile.json``; bench/README.md "Where the time goes"): every level
repeated the same sweeps from scratch -- the history of the changes was the same to two
digits at every level (default shrunk by 0.2 m: 15 sweeps at each of 5 level solves; two
squares 0.01 apart: 61 at each of 4), as only the first sweep's polygon GNK solves depend on
the mesh -- and the outer boundary's 2048-point smooth grid built a dense GNK matrix in every
sweep for ~3 GMRES iterations (7.5 of 21 s CPU on the shrunk workspace; now FMM products,
:data:`confnav.conformal.gnk.SMOOTH_DENSE_MAX_NODES`). Now each level's first sweep is its
own (its discretisation, hence its fixed point, level difference and estimate are as
before), and the rest start within the level difference of the circle domain. The first
sweep's curves define the domain that the later sweeps map, so their tangents are reset to
the curves' derivatives (:func:`confnav.conformal.circledomain._consistent_tangents`): with
the graded maps' own derivatives (which differ by the level's discretisation error) the
carried map was not conformal on that domain, and each carried level kept its predecessor's
boundary error (a 9.2e-8 residual on a 2 x 1 m room with a pillar at every level, 8.6e-11
cold; tests/test_level_carry.py). Measured side by side, cold against carried, in one run
(``bench/bench_koebe.py --gaps 0.01 --scenes room default shrunk mixed50 --case-tol
default=1e-10 --designs fmm_smooth carry``, ``bench/results/koebe_carry_fixed.json`` at
30b19d7, load 6.1 -> 3.8, CPU seconds; tol 1e-8, the default workspace 1e-10): two squares
0.01 apart 122.9 -> 38.1 s (sweeps per level 61/61/61/61 -> 61/7/3/3, asymmetry 2.5e-12 ->
1.1e-12 under the estimate 1.2e-9); default shrunk by 0.2 m 14.3 -> 7.7 s (15 x 5 ->
15/7/4/3/3); 50 obstacles 81.9 -> 45.4 s (5 x 6 -> 5/3/3/3/3/3); default workspace 3.6 ->
3.1 s; the room 0.5 = 0.5 s (residual 8.6e-11 cold, 2.6e-11 carried). Every map tol_met with
the cold estimate, the carried maps within 6.3e-11 of the cold ones. The first (cold) level's
sweeps are now most of what is left on the near-touching and shrunk cases.

Designs of the iteration measured side by side (issue 24 item 1; CPU seconds of one run each,
the machine shared, so compare within a file): the plain sweeps against over-relaxed
(``koebe_accel="sor"``) and extrapolated (``"extrapolate"``) sweeps
(``bench/results/koebe_gap001.json``, ``koebe.json``): two squares 0.01 apart to 1e-8, 61 / 45
/ 34 sweeps per level, 123.5 / 96.4 / 83.0 s, all honest; where the plain contraction is fast
nothing triggers. Newton on the whole circle domain after 6 sweeps (``method="nasser"``,
``bench/results/koebe_methods.json``): slower on every case measured and never certified (see
``method`` below). The carried levels (above) remove the sweeps of every level after the
first; of the cold first level's, ``"extrapolate"`` (now the default, from plain contractions
above 0.5 only) removes about half where the contraction is slow: two squares 0.01 apart 36.5
-> 25.9 s CPU, 74 -> 46 sweeps, the same sweeps wherever it does not trigger
(``bench/results/koebe_extrapolate_default.json``; :mod:`confnav.conformal.circledomain`).

Warm re-solve (issue 24 item 3, ``initial=``, :func:`_warm_solve`): the sweeps start from the
previous map carried over to the changed workspace (:mod:`confnav.conformal.warm`: the
previous graded meshes, the Cauchy terms of the previous boundary values moved with their
obstacles) and run at the previous map's finest level only; the certificate keeps this
solve's own iteration error and boundary residual and inherits the discretisation estimate.
A change the warm start does not apply to (another outer boundary, a gap the previous mesh
does not resolve) or whose map misses ``tol`` is solved over the levels from two below the
previous map's (:func:`_warm_start_level`). Measured (``bench/results/core_resolve.json`` at
939ec99, 10 mixed obstacles at 1e-8, warm and cold in one run, load 6.3-7.7, CPU seconds):
one obstacle moved by 0.2 m 3.88 s warm (one level, 256 nodes per side) against 19.25 s cold
(five levels), one removed 3.85 against 18.82 s, one added back 4.74 against 20.41 s; every
warm map tol_met and within the two estimates of the cold one (7.5e-10, 1.5e-9, 9.8e-10). The
levels path it replaces took 13.4 s against 21.4 s. The 1 s target is missed: the first
sweep's GNK solves on the graded meshes (dense, ~14,700 nodes) cost most of it.

The issue-24 target rows at one commit: ``bench/results/core_targets.json``
(``python bench/bench_core.py --targets``).

Corner preconditioner and one BLAS thread (issue 24): each level's first sweep solves its GNK
equations on the graded polygon meshes with GMRES right-preconditioned by the corner blocks
(:mod:`confnav.conformal.gnk`), and a solve runs with one BLAS thread
(:data:`SOLVE_BLAS_THREADS`). Side by side in one run (``python bench/bench_koebe.py --gaps
0.01 --scenes default shrunk mixed50 --case-tol default=1e-10 --accels extrapolate --designs
carry corner carry_blas1 corner_blas1``, ``bench/results/koebe_corner_blas1.json`` at
4ebf245, load 4.8-9.8, CPU s, before / preconditioner / one thread / both): 50 obstacles 63.4
/ 61.1 / 21.2 / 19.9 (GMRES iterations 10136 -> 5238), the default workspace to 1e-10 4.3 /
3.0 / 1.4 / 1.4 (831 -> 446), shrunk by 0.2 m 7.7 / 7.9 / 3.1 / 3.0, two squares 0.01 apart
22.6 / 24.3 / 17.5 / 17.9; every map tol_met, the maps within 9.3e-12 of each other, the
asymmetry 1.5e-12 under the estimate 1.2e-9. The targets at 8791729
(``bench/results/core_targets_blas1.json``, one process, load 3.0-3.1, CPU s): default to
1e-10 1.61 s, shrunk 2.95 s (3.5x the unshrunk 0.83 s), 50 obstacles 19.97 s (27.7x the
4-obstacle scene's 0.72 s), two squares 0.01 apart 17.39 s. With the map evaluations'
power tables built per degree and the grid-size look-up limited to points within reach
(``koebe_lean.json`` at 41d0c98: 50 obstacles 20.9 -> 17.2 s, the same maps) the targets at
bf195f9 (``bench/results/core_targets_lean.json``, load 4.7-7.4), in the same order: 1.09,
3.38, 18.02 and 17.42 s. Then each map's boundary residuals evaluated once (the certificate
and the per-side refinement read one evaluation, :meth:`ConformalMap.boundary_residuals`;
the same maps bitwise) and the dense GNK matrices kept complex
(:data:`confnav.conformal.gnk.DENSE_INTERLEAVED`; maps within 4.9e-12), side by side
(``koebe_once.json`` at 3f25606 and ``koebe_interleaved.json`` at cf69531, CPU s, lean / once
| once / interleaved): 50 obstacles 17.6 / 15.9 | 16.1 / 15.5, the default workspace to 1e-10
1.4 / 1.1 | 1.3 / 0.9, two squares 0.01 apart 17.2 / 17.0 | 17.0 / 16.6, shrunk 2.8 / 2.8 |
2.8 / 2.9; the targets at 1d8599a (``core_targets_interleaved.json``, load 2.6-6.8): 1.43
(first solve of the process), 2.95, 17.30 and 17.19 s. Then the sweeps' map derivatives from
the second-order sums of two charges (:data:`confnav.conformal.diskmap.DERIVATIVE_FROM_SECOND_SUMS`:
two FMM calls per evaluation instead of three; ``koebe_second_sums.json`` at 8c92cc1, CPU s,
before / after): two squares 0.01 apart 16.9 / 14.9 (FMM sums 905 / 771), 50 obstacles 15.5 /
15.3, shrunk 2.9 / 2.8, the default workspace 1.1 / 0.9; the maps within 6.8e-12; off by
default (its docstring: the harmonic fleet step then leaves its rounding bound). What is left
is FMM sums (two squares: 771 per solve) and, on 50 obstacles, the expansions' O(holes x
points) per sweep.

Round 3 (issue 24; bench/README.md "Round 3"). Profiled first (cProfile and
``bench_core.py --profile``, ``cauchy._fmm`` counted by size): on two squares 0.01 apart the
FMM took 13.0 of 16.4 s CPU, 771 calls, most on the holes' smooth grids of 4096 points where
2235 were needed (sizes were rounded up to powers of two). Three changes, each measured side
by side: the second-sums derivatives on by default (their blocker was one robot's harmonic
gradient formed with Python's complex operations, not the map:
:data:`confnav.conformal.diskmap.DERIVATIVE_FROM_SECOND_SUMS`); smooth grids sized to eighths
of an octave from the rule for the band the tail check reads
(:data:`~confnav.conformal.circledomain.GRID_STEPS`,
:data:`~confnav.conformal.circledomain.TAIL_BAND`), a grid too coarse for the carried level's
anchor upsampled first; the Moebius grading strength searched between the listed ones
(:data:`~confnav.conformal.circledomain.GRADING_REFINE`). Side by side
(``bench/results/koebe_fine_grids.json``, ``koebe_graded.json``; CPU s at load 7-18): two
squares 15.4 -> 11.5 (grids) -> 11.0 (grading), 50 obstacles 17.3 -> 14.9 -> 13.7, shrunk
3.0 -> 2.5, the default workspace unchanged; the committed code against the second sums
alone in one run (``koebe_round3.json`` at bac1a98, load 11.5-17.6): two squares 15.3 ->
10.4, 50 obstacles 17.0 -> 14.7, shrunk 3.0 -> 2.8, the default workspace 1.2 = 1.2; the
same sweeps and estimates, every map tol_met, the maps within 3.8e-14 of each other, the
asymmetry 1.5e-12 under 1.2e-9.
The targets before and after: bench/README.md, "Round 3" (``core_targets_interleaved.json``
against ``core_targets_round3.json``).

Round 4 (issue 24; bench/README.md "Round 4"). Profiled first at 85476d2
(``bench/results/core_profile_round4_before.json``, load 1.0, CPU s; split by boundary kind in
``core_profile_round4_split.json``): 50 obstacles 13.7 s, spread over six level solves (the
per-side refinement's re-solve of all 51 boundaries 3.0 of it); the holes' maps evaluated on
every other boundary 2.0 s, the outer map on the holes 1.1, the holes' graded GNK solves 2.8,
the outer boundary's GNK solves 2.8, the certificate 1.5 -- so the quadratic term alone is not
what keeps it above 10 s. Two squares 0.01 apart 10.5 s, the cold first level 7.2 of it (34
sweeps). Built: the sweeps' extrapolation removes two geometric modes instead of one
(:data:`~confnav.conformal.circledomain.EXTRAPOLATE_MODES`, minimal polynomial extrapolation
from three grid-keeping sweeps). Side by side (``koebe_round4_modes2.json`` at e765f88, load
5.5-9.2, CPU s): two squares 0.01 apart 10.6 -> 8.6 (sweeps 46 -> 39), 0.03 apart 1.4 -> 1.2;
the other cases the same runs bit for bit. From plain contractions above 0.2 instead of 0.5
(``koebe_round4_rho.json`` at ec05683, load 2.0-2.7): the default workspace shrunk by 0.2 m 2.8
-> 2.3 s (sweeps 32 -> 27), two squares 0.01 apart 8.7 s either way. The targets:
``core_targets_round4b.json`` at ae1e0e7 (two squares 0.01 apart 8.83 s, met; 50 obstacles 13.84
s, missed).

Round 5 (issue 24; bench/README.md "Round 5"). A per-side refinement's re-solve takes the base
level's first-sweep maps of the boundaries whose first-sweep equations are unchanged bit for
bit -- those before the first refined boundary in the sweep's order (:data:`REFINE_REUSE`,
``reuse_first`` of :func:`~confnav.conformal.circledomain.koebe_iteration`); the refined
boundaries and those after them are solved anew, and the estimate (base + change), iteration
error and residual are computed on the map that comes out, as before. A workspace with an
obstacle tip sharper than 60 degrees starts the ladder at 80 nodes per side to 1e-8 and at 120
to 1e-10 (:data:`START_BY_CORNERS`): the certificate rests on the same three levels. Side by
side (``core_profile_round5.json`` at a28254b, one run, load 2.8-4.2, CPU s, round 4 / reuse /
both): 50 obstacles 14.39 / 13.77 / 10.45 (28 of 51 graded solves of the refinement reused:
its re-solve 3.27 -> 2.92 s; levels 36 and 54 no longer solved), the default workspace to 1e-8
0.69 / 0.64 / 0.49 and to 1e-10 1.01 / 0.89 / 0.81; two squares 0.01 apart and the shrunk
workspace the same levels (8.88 / 8.67 / 8.65 and 2.50 / 2.40 / 2.41); every map tol_met with
the same estimate. The re-solve's first sweep also starts from the base level's snapshot
before the first refined boundary (:data:`REFINE_SNAPSHOTS`; ``core_profile_round5_snapshots.json``
at eb65774, load 5.4-5.6: 50 obstacles 11.22 -> 10.94 s, the re-solve's map evaluations 0.57 ->
0.41 s). The targets: ``core_targets_round5.json`` at b225c32 (load 1.8-2.8; 50 obstacles 10.30
s, 10 s missed by 3 %) and ``core_targets_round5b.json`` at 61624a2 (load 5.5-6.6; 10.76 s).

Round 6 (issue 24; bench/README.md "Round 6"): two exact cuts below this module, the same maps
bit for bit -- the mesh planner's feature distances only to the features whose bounding boxes
can be nearest (:func:`confnav.conformal.meshing._nearest_features`; 50 obstacles' meshing 0.42
-> 0.11 s) and the dense GNK matrices assembled by blocks of rows, scanned for coincident
nodes only where some coincide (:func:`confnav.conformal.gnk._assemble`). Side by side
(``core_profile_round6.json`` at 1a7fe58, load 6.5-9.6): 50 obstacles 10.94 -> 10.59 s; the
targets (``core_targets_round6.json`` at b755288, load 3.4-4.5): 50 obstacles 10.39 s (10 s
missed), the default workspace to 1e-10 0.95 s (0.5 s missed). The certificates are unchanged:
each is the boundary residual's two FMM sums at full precision (0.75 of its 0.79 s on 50
obstacles); a lower FMM precision there moved the residual by 1.8e-11 and was not built.

Round 7 (issue 24; bench/README.md "Round 7"). Four changes, the certificate unchanged: the
holes are swept bluntest tip first, sharpest last, at every level (:func:`_sweep_order`), so
that a per-side refinement, which the residual asks for at the sharpest tips, re-solves the
first sweep from late in the order (50 obstacles: 46 of 51 first-sweep maps reused instead of
28, the maps 1.0e-11 apart; ``core_probes_round7.json``); the dense GNK matrices' real and
imaginary parts are written into two contiguous real matrices during the assembly
(:data:`confnav.conformal.gnk.DENSE_SPLIT_ASSEMBLY`: a GMRES product reads one part); smooth
grids of up to 2048 nodes are solved densely
(:data:`confnav.conformal.gnk.SMOOTH_DENSE_MAX_NODES`: grids of 1117-1414 nodes had fallen to
matrix-free direct sums); a refined map's residual takes the denominator sums of the map it
refines where its nodes are the same (:data:`REUSE_DENOMINATORS`). Side by side
(``core_profile_round7.json`` at a21ddac, load 3.2-3.8, CPU s, round 6 / the order / and the
split): 50 obstacles 10.43 / 10.01 / 9.29, the default workspace to 1e-10 0.96 / 0.86 / 0.67;
round 6 against all four (``core_profile_round7_final.json`` at 360a629, load 2.9-4.1): 50
obstacles 10.09 -> 8.95 (the refined map's certificate 0.77 -> 0.43), the default workspace
to 1e-10 0.91 -> 0.67, shrunk by 0.2 m 2.40 -> 1.65, two squares 0.01 apart 8.90 -> 7.99. Every
map tol_met with the same estimate. Measured and not built: fewer check points -- the
certificate's FMM sums are dominated by their 46,480 sources (one sum to a hundredth of the
39,684 check points costs 0.23 s against 0.36 s; ``core_probes_round7.json``).

``tol_met`` is true only if all are within ``tol`` and nothing is ``unverified``. A map that
misses ``tol`` is returned with ``tol_met = False`` and an :class:`AccuracyWarning`; one whose
estimate exceeds :data:`UNUSABLE_ERROR` (or the caller's ``max_error``) raises
:class:`~confnav.errors.SolverError` -- a silently wrong map is never returned.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from confnav.conformal.boundary import BoundaryMesh, graded_polygon, resample
from confnav.conformal.circledomain import (
    SMOOTH_PER_TOL,
    SMOOTH_TAIL,
    CircleDomainResult,
    LevelCarry,
    koebe_iteration,
)
from confnav.conformal.circular_map import METHODS, nasser_iteration
from confnav.conformal.cmap import ConformalMap, SolveReport
from confnav.conformal.diskmap import CurveMap
from confnav.conformal.gnk import gmres_rtol
from confnav.conformal.meshing import NODE_MULTIPLE, PanelPlan, plan_boundaries
from confnav.errors import (
    ConvergenceError,
    CrowdingError,
    GapError,
    SolverError,
    UnresolvedCrowdingError,
    fmt_point,
)
from confnav.geometry import Workspace, interior_point, signed_area
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

log = logging.getLogger(__name__)

#: Mesh levels: nodes per side at the workspace's sharpest corner, coarse to fine (x1.5 steps).
#: Above 256 the nodes next to the vertices of the p = 7 mesh fall within rounding of them; they
#: are dropped as sources (confnav.conformal.gnk.alive_nodes), and the finer levels are needed by
#: needle-like tips: a 10-degree tip reaches 1e-6 only at 576 (measured: 3.4e-8, residual
#: 6.8e-9, mirror asymmetry 2e-15; at 256 the residual is 1.1e-4).
LEVELS: tuple[int, ...] = (24, 36, 54, 80, 120, 180, 256, 384, 576)
#: Error decay assumed between two levels (n^-5 .. n^-11 measured on the default workspace);
#: the estimate uses the slower of this and the contraction observed over the last three
#: levels, so it errs on the safe side. A two-level estimate was measured to under-estimate a
#: thin triangle's error 5x (pre-asymptotic convergence at its 14-degree tip; hypothesis
#: test), hence three levels at least.
ASSUMED_ORDER = 5.0
#: Levels solved before an estimate may stop the refinement.
MIN_LEVELS = 3
#: A level difference that shrank by less than this factor from the previous one has stopped
#: converging geometrically: the tail extrapolation ``diff rho / (1 - rho)`` does not hold,
#: and the estimate is reported as unverified (``SolveReport.unverified``; no ``tol_met``)
#: unless the difference is at the rounding floor (:data:`ROUNDING_DIFFERENCE`).
RHO_LEVELS_MAX = 0.9
#: Level differences below ``ROUNDING_DIFFERENCE * tol``, or within the sum of the two
#: levels' iteration errors, are rounding and iteration noise, not discretisation: whether they
#: shrink says nothing (measured: two squares 0.1 apart at tol 1e-8, differences 2.52e-10 and
#: 2.55e-10 at 80 and 120 nodes per side, iteration errors 3.9e-10 each; 7.0e-11 at 180).
ROUNDING_DIFFERENCE = 1e-3
#: An estimated error above this makes the map useless for navigation: raise instead.
UNUSABLE_ERROR = 1e-4
#: Share of ``tol`` left to the Koebe iteration's remaining error (the rest: discretisation).
ITERATION_SHARE = 0.1
#: Start the first sweep's GNK solves of a level from the previous level's solutions, resampled
#: onto the new graded meshes (issue 12: "reuse of the previous level's solution as the GMRES
#: start"). Measured on the default workspace, 180 -> 256 nodes per side: 185 -> 144 GMRES
#: iterations of those solves (the spline transfer errs by 1e-6..5e-5 relative, limited by
#: the corners, and GMRES on the second-kind operator gains about a digit per 4-5 iterations);
#: the map is the same to the GMRES tolerance (tests/test_solver_warm_start.py).
WARM_START = True
#: Start each mesh level's sweeps after the first from the previous level's converged map
#: (:class:`confnav.conformal.circledomain.LevelCarry`, issue 24 item 2: "start each mesh
#: level from the previous level's circle domain and boundary correspondence"). The first
#: sweep stays this level's own (its polygon GNK solves on its graded meshes carry the whole
#: discretisation), so each level's fixed point, its level difference and the estimate are as
#: before; only the sweeps that follow start near the circle domain. Measured: module
#: docstring. It was off while a carried level kept its predecessor's boundary error (on a
#: 2 x 1 m room with a square pillar to 1e-8: a 9.2e-8 residual at every level against 8.6e-11
#: cold); the cause, the first sweep's tangents not those of its curves, is fixed
#: (:func:`confnav.conformal.circledomain._consistent_tangents`), and every carried level
#: ends within its iteration error of the cold one (tests/test_level_carry.py).
LEVEL_CARRY = True


class AccuracyWarning(UserWarning):
    """The map's estimated error is above the requested tolerance."""


#: A level's graded meshes and its first sweep's GNK solutions (the next level's first guess).
_Warm = tuple[list[BoundaryMesh], list[FloatArray | None]]


def _solve_level(
    ws: Workspace,
    nodes_per_side: int,
    tol: float,
    progress: Callable[[str], None] | None,
    warm: _Warm | None = None,
    plans: list[PanelPlan] | None = None,
    accel: str | None = None,
    method: str = "koebe",
    carry: LevelCarry | None = None,
    reuse_first: list[CurveMap | None] | None = None,
    reuse_snapshots: dict[int, Any] | None = None,
    order: list[int] | None = None,
) -> tuple[CircleDomainResult, list[BoundaryMesh]]:
    if plans is None:
        plans = plan_boundaries(ws, nodes_per_side, tol)
    meshes = [graded_polygon(plans[0].vertices, plans[0].nodes)] + [
        graded_polygon(p.vertices, p.nodes).reversed() for p in plans[1:]
    ]
    holes = [interior_point(o) for o in ws.obstacles]
    guess: list[FloatArray | None] | None = None
    if warm is not None and WARM_START:
        guess = [
            None if mu is None else resample(old, mu, new)
            for old, mu, new in zip(warm[0], warm[1], meshes, strict=True)
        ]

    def _p(sweep: int, change: float) -> None:
        if progress is not None:
            progress(f"  {nodes_per_side} nodes/side: sweep {sweep}, change {change:.1e}")

    common: dict[str, Any] = {
        "tol": ITERATION_SHARE * tol,
        "progress": _p,
        "gmres_tol": gmres_rtol(tol),
        "first_guess": guess,
        "accel": accel,
    }
    res: CircleDomainResult
    if method == "nasser":
        res = nasser_iteration(meshes, holes, ws.anchor, **common)
    else:
        carried = carry if LEVEL_CARRY else None
        res = koebe_iteration(
            meshes,
            holes,
            ws.anchor,
            **common,
            carry=carried,
            trace=LEVEL_CARRY,
            reuse_first=reuse_first if REFINE_REUSE else None,
            snapshots=REFINE_REUSE and REFINE_SNAPSHOTS,
            reuse_snapshots=reuse_snapshots if REFINE_REUSE and REFINE_SNAPSHOTS else None,
            order=order,
        )
    return res, meshes


#: One solved level: result, nodes, their derivatives, nodes per side, discretisation
#: estimate, and why that estimate is unverified (empty: verified).
_Level = tuple[CircleDomainResult, list[ComplexArray], list[ComplexArray], int, float, list[str]]


def _make_map(
    ws: Workspace,
    level: _Level,
    tol: float,
    caps: list[str],
    refinements: list[dict[str, float]],
    t0: float,
    denominators_from: ConformalMap | None = None,
) -> ConformalMap:
    """The map of one solved level with its full error budget (residual computed here);
    ``denominators_from``: the map of the same level this one refines, whose residual's
    denominator sums it may take where its nodes are the same
    (:meth:`ConformalMap.reuse_denominators`, :data:`REUSE_DENOMINATORS`)."""
    res, eta, deta, ns, disc, unverified = level
    diag = SolveReport(
        tol=tol,
        error_estimate=float("inf"),
        tol_met=False,
        sweeps=res.sweeps,
        history=res.history,
        nodes=[e.size for e in eta],
        nodes_per_side=ns,
        circularity=res.circularity,
        gmres_iterations=res.gmres_iterations,
        wall_time=0.0,
        discretisation_error=disc,
        iteration_error=res.iteration_error,
        iteration_converged=res.converged,
        boundary_residual=float("inf"),
        resolution_error=res.resolution_error,
        caps=list(caps),
        refinements=list(refinements),
        gmres_residual=res.gmres_residual,
        unverified=list(unverified),
        min_radius=float(np.min(res.radii)) if res.radii.size else 1.0,
    )
    m = ConformalMap(ws, eta, deta, res.W, res.dW, res.centers, res.radii, diag)
    if denominators_from is not None and REUSE_DENOMINATORS:
        m.reuse_denominators(denominators_from)
    diag.crowding = crowding(m)
    m.diagnostics = diag.with_residual(m.boundary_residual())
    m.diagnostics.wall_time = time.perf_counter() - t0
    return m


#: Crowding (decades, :func:`crowding`) from which one map is not advised: a side compressed
#: 10^6 times below its boundary's average keeps ~10 of double precision's 16 digits for T
#: there, against map tolerances of 1e-8..1e-10 (the solver's choice, not a measured limit).
CROWDING_ATLAS_DECADES = 6.0
#: Smallest circle radius below which one map is not advised (a circle of radius 1e-6 is
#: 10^5 above :data:`~confnav.conformal.circledomain.CROWDING_RADIUS`, where the solve fails).
MIN_RADIUS_ATLAS = 1e-6


def crowding(m: ConformalMap) -> list[float]:
    """Conformal crowding of each boundary of ``m`` (outer first), in decades.

    For every side of a boundary: its share of the boundary's length against the share of
    the image circle its images cover (chord sums over the nodes between its two corners);
    the boundary's crowding is ``log10`` of the largest such quotient, at least 0 (a side
    that maps to 10^-k of the circle it would get in proportion to its length: k). Crowding
    of a region reached through a narrow passage grows like exp(-pi L / w) (Driscoll &
    Trefethen, "Schwarz-Christoffel Mapping", Cambridge 2002, sec. 2.6), so the measured
    decades say how close a map is to the end of double precision.
    """
    out: list[float] = []
    eta, _, W, _ = m._parts
    for e, w, v in zip(eta, W, m.workspace.boundaries, strict=True):
        vv = np.asarray(v)
        # the node at each corner (graded meshes put a node on every vertex); a k-d tree, not
        # an n x L distance matrix: imported floor plans have thousands of vertices
        nearest = cKDTree(np.column_stack([e.real, e.imag])).query(
            np.column_stack([vv.real, vv.imag])
        )[1]
        idx = np.sort(np.unique(nearest))
        seg_len = np.abs(np.roll(e, -1) - e)
        seg_arc = np.abs(np.roll(w, -1) - w)
        side = np.searchsorted(idx, np.arange(e.size), side="right") - 1  # side of each segment
        side[side < 0] = idx.size - 1  # segments before the first corner close the last side
        L = np.bincount(side, seg_len, idx.size)
        A = np.bincount(side, seg_arc, idx.size)
        q = (L / L.sum()) / np.maximum(A / A.sum(), 1e-300)
        out.append(float(max(0.0, np.log10(np.max(q)))))
    return out


def crowding_reason(diag: SolveReport) -> str:
    """Why a solved map says an atlas would serve better ("" if nothing does): its smallest
    circle below :data:`MIN_RADIUS_ATLAS` or a boundary crowded by
    :data:`CROWDING_ATLAS_DECADES` or more (measured by the solve, :func:`crowding`)."""
    why = []
    if diag.min_radius < MIN_RADIUS_ATLAS:
        why.append(f"smallest circle radius {diag.min_radius:.1e} < {MIN_RADIUS_ATLAS:.0e}")
    worst = max(diag.crowding, default=0.0)
    if worst >= CROWDING_ATLAS_DECADES:
        j = diag.crowding.index(worst)
        name = "the outer boundary" if j == 0 else f"obstacle {j - 1}"
        why.append(f"{name} crowded by 10^{worst:.1f}")
    return "; ".join(why)


def _check_resolvable(
    res: CircleDomainResult, ns: int, prev_resolution: float, max_error: float
) -> None:
    """Stop refining when a finer mesh cannot make the map usable: a boundary image's smooth
    grid held at its size cap (:data:`~confnav.conformal.circledomain.SMOOTH_MAX`, which does
    not grow with the nodes per side) leaves a Fourier tail above ``max_error`` at two levels
    in a row, the second not halving it. That tail comes from a boundary image crowded
    against its nearest singularity (docs/METHOD.md, crowding), which an atlas resolves.
    Measured on a 12 x 8 m lab with a 1 m alcove and a 0.3 m footprint: tail 1.3e-1 at every
    level from 36 to 576 nodes per side (105 s of levels that could not help)."""
    tail = res.resolution_error
    if tail > max_error and prev_resolution > max_error and tail > 0.5 * prev_resolution:
        radius = float(np.min(res.radii)) if res.radii.size else 1.0
        raise CrowdingError(
            f"a boundary image is crowded beyond what one map resolves: its smooth grid is at "
            f"its size cap with a Fourier tail of {tail:.1e} at {ns} nodes per side (previous "
            f"level {prev_resolution:.1e}; finer meshes do not lower it; smallest circle "
            f"radius {radius:.1e}): an atlas resolves it"
        )


#: Refine only the sides whose a-posteriori residual asks (issue 24 item 2) when a level's
#: discretisation estimate is within ``tol`` but its boundary residual is not, before solving
#: the next level everywhere; at most this many rounds (each moves the sides still above
#: ``tol`` one level finer).
LOCAL_ROUNDS = 2
LOCAL_REFINEMENT = True
#: Per-side refinement is tried only while the base level's estimate leaves this share of
#: ``tol`` to the change it causes (its estimate is base + change). Measured on 10 mixed
#: obstacles at 1e-8: base 8.0e-9, change 2.4e-9 -- the partial level met the residual
#: (6.5e-9) but not the estimate (1.04e-8), and the full level had to follow (4.2 s lost).
LOCAL_HEADROOM = 0.5
#: A per-side refinement's re-solve takes the base level's first-sweep maps of every boundary
#: whose first-sweep equation is unchanged (bit for bit: its graded mesh not refined, and every
#: map before it in the sweep taken too; circledomain._reusable) instead of solving it again:
#: the boundaries before the first refined one in the sweep's order keep the base level's
#: solution, the refined ones and those after them are solved anew (their equations differ).
#: The map is the same to the GMRES tolerance; its estimate, iteration error and residual are
#: computed on it as before.
REFINE_REUSE = True
#: And the re-solve's first sweep starts from a snapshot of the base level's iterate before the
#: first refined boundary (circledomain.SNAPSHOTS, ``_resume``) instead of applying the reused
#: maps to every other boundary again.
REFINE_SNAPSHOTS = True


#: A per-side refinement's map takes the denominator sums of its residual from the map it
#: refines where its nodes are that map's (:meth:`ConformalMap.reuse_denominators`; round 7):
#: on 50 obstacles one FMM sum over 46,480 nodes (0.36 s CPU) becomes sums from and to the
#: one refined boundary (0.03 s at its points, ``core_probes_round7.json``), the certificate
#: 0.77 -> 0.43 s (bench/README.md "Round 7"); the same sums to rounding.
REUSE_DENOMINATORS = True

#: Sweep the holes in the order of their sharpest tips, bluntest first (:func:`_sweep_order`;
#: round 7, issue 24); False: 1..M.
SWEEP_ORDER = True
#: Free-space angles within this many degrees count as equal (the natural order is kept among
#: them, e.g. for the holes of a mirror-symmetric workspace, whose angles agree to rounding).
SWEEP_ORDER_DEGREES = 1.0


def _sweep_order(ws: Workspace) -> list[int] | None:
    """The order in which every level's sweeps map the holes (:func:`koebe_iteration`'s
    ``order``): by the largest free-space angle at a corner of each hole (360 degrees minus
    its sharpest tip), smallest first, so that the holes with the sharpest tips come last;
    None (1..M) with :data:`SWEEP_ORDER` off or fewer than two holes.

    Why: a per-side refinement (:func:`_refine_sides`) re-solves the graded first-sweep
    equations from its first refined boundary on in the sweep's order (those before it are
    reused bit for bit, :data:`REFINE_REUSE`), and the sides its boundary residual names are
    where the discretisation is worst: at the sharpest tips, where the map's leading
    singularity ``(z - v)^(1/alpha)`` is strongest (Henrici, "Applied and Computational
    Complex Analysis", Vol. 1, sec. 5.11; :data:`START_BY_CORNERS`). Measured on 50 mixed
    obstacles to 1e-8 (bench/README.md "Round 7"): the eight boundaries with the largest
    residual at 180 nodes per side were eight of the ten sharpest tips, the one refined (hole
    28) the fourth sharpest (``core_probes_round7.json``). The order is the workspace's, the
    same at every level: a carried level (:data:`LEVEL_CARRY`) continues the previous level's
    map after its own first sweep, which needs the first sweeps to compose the same maps in
    the same order (an order taken from the level differences, known only from the third
    level on, cost the 180 level extra sweeps on 50 obstacles: bench/README.md "Round 7").
    The order changes the first sweep's discretisation path, not the fixed point the sweeps
    converge to for it (each map of a sweep is a conformal image of the domain): the circle
    domain moves by an amount of the level's discretisation error, which the three-level
    estimate and the boundary residual measure as before (measured: 1.0e-11 on 50 obstacles
    under an estimate of 9.1e-9, ``core_probes_round7.json``)."""
    if not SWEEP_ORDER or ws.n_obstacles < 2:
        return None
    angles = free_angles(ws)[1:]
    key = np.round(np.asarray(angles) / SWEEP_ORDER_DEGREES)
    return [int(k) + 1 for k in np.argsort(key, kind="stable")]


def _bad_sides(m: ConformalMap, plans: list[PanelPlan], tol: float) -> list[tuple[int, int]]:
    """(boundary, side of its plan) of every residual check point above ``tol``: the side
    nearest to the point (a point at a corner belongs to both its sides: both are returned)."""
    z, res, owner = m.boundary_residuals()
    bad = ~(res <= tol)
    out: set[tuple[int, int]] = set()
    for j in np.unique(owner[bad]):
        pts = z[bad & (owner == j)]
        v = np.asarray(plans[int(j)].vertices)
        a, e = v[None, :], (np.roll(v, -1) - v)[None, :]
        t = np.clip(((pts[:, None] - a) * np.conj(e)).real / np.abs(e) ** 2, 0.0, 1.0)
        d = np.abs(pts[:, None] - (a + t * e))
        near = d <= d.min(axis=1, keepdims=True) * (1 + 1e-9) + 1e-15
        for k in np.flatnonzero(near.any(axis=0)):
            out.add((int(j), int(k)))
    return sorted(out)


def _refine_sides(
    ws: Workspace,
    ns: int,
    finer: list[int],
    base: _Level,
    bad_map: ConformalMap,
    tol: float,
    progress: Callable[[str], None] | None,
    warm: _Warm | None,
    caps: list[str],
    refinements: list[dict[str, float]],
    t0: float,
    accel: str | None = None,
) -> tuple[ConformalMap, _Level] | None:
    """Refine only the sides whose boundary residual is above ``tol`` (and their neighbours),
    each to the next level's nodes, up to :data:`LOCAL_ROUNDS` times; None if that does not
    give a map meeting ``tol`` (the caller then solves the next level everywhere).

    The discretisation estimate of a partly refined mesh is the base level's (observed over
    three levels) plus the change of the circle domain from it: the error of the refined
    solution is at most the base's plus their difference (triangle inequality), so no order
    is assumed.
    """
    res0, est0 = base[0], base[4]
    try:
        plans0 = plan_boundaries(ws, ns, tol)
        finer_plans = [plan_boundaries(ws, f, tol) for f in finer[:LOCAL_ROUNDS]]
    except GapError:
        return None
    if not finer_plans:
        return None
    level = [np.zeros(p.nodes.size, np.intp) for p in plans0]
    m = bad_map
    last = res0  # the latest solve of this level: its first-sweep maps are reused
    for _round in range(LOCAL_ROUNDS):
        bad = _bad_sides(m, plans0, tol)
        if not bad:
            return None
        for j, k in bad:
            L = level[j].size
            for kk in (k - 1, k, k + 1):
                level[j][kk % L] = min(level[j][kk % L] + 1, len(finer_plans))
        plans = []
        for j, p0 in enumerate(plans0):
            nodes = p0.nodes.copy()
            for lv in range(1, len(finer_plans) + 1):
                pf = finer_plans[lv - 1][j]
                if pf.nodes.size != nodes.size or not np.array_equal(pf.vertices, p0.vertices):
                    if np.any(level[j] >= lv):  # sides split differently: the whole boundary
                        nodes = pf.nodes.copy()
                        p0 = pf
                        break
                    continue
                nodes = np.where(level[j] >= lv, np.maximum(nodes, pf.nodes), nodes)
            nodes[0] += (-int(nodes.sum())) % NODE_MULTIPLE
            plans.append(PanelPlan(vertices=p0.vertices, nodes=nodes))
        n_ref = int(sum(int(np.count_nonzero(lv)) for lv in level))
        if progress is not None:
            progress(f"refining {n_ref} sides where the boundary residual asks")
        try:
            res, meshes = _solve_level(
                ws,
                ns,
                tol,
                progress,
                warm,
                plans,
                accel,
                carry=base[0].carry,
                reuse_first=last.first_maps,
                reuse_snapshots=last.first_snapshots,
                order=res0.order or None,
            )
        except ConvergenceError as exc:
            log.warning("local refinement failed (%s)", exc)
            return None
        last = res
        diff = _difference(res, res0)
        est = est0 + diff
        eta, deta = [mm.eta for mm in meshes], [mm.deta for mm in meshes]
        lvl: _Level = (res, eta, deta, ns, est, list(base[5]))
        refinements.append(
            {
                "nodes_per_side": ns,
                "refined_sides": n_ref,
                "difference": diff,
                "error_estimate": est,
                "iteration_error": res.iteration_error,
                "wall_time": res.wall_time,
                "reused_first_maps": res.reused_first_maps,
                "resumed_at": res.resumed_at,
            }
        )
        m = _make_map(ws, lvl, tol, caps, refinements, t0, denominators_from=m)
        refinements[-1]["boundary_residual"] = m.diagnostics.boundary_residual
        if m.diagnostics.tol_met:
            return m, lvl
    return None


def _warm_start_level(initial: ConformalMap, tol: float) -> int:
    """Index into :data:`LEVELS` at which a re-solve like ``initial`` starts: two levels
    below the finest full level ``initial`` solved (so that the estimate still rests on a
    contraction observed over three levels), 0 if ``initial`` says nothing usable (solved to
    a looser tolerance: its levels were too coarse for ``tol``)."""
    d = initial.diagnostics
    if d.tol > tol or d.nodes_per_side not in LEVELS:
        return 0
    return max(0, LEVELS.index(d.nodes_per_side) - 2)


#: Warm re-solves from the previous map's circle domain (issue 24 item 3, :func:`_warm_solve`);
#: False: ``initial`` only moves the first mesh level up (:func:`_warm_start_level`).
WARM_RESOLVE = True


def _warm_solve(
    ws: Workspace,
    tol: float,
    initial: ConformalMap,
    progress: Callable[[str], None] | None,
    accel: str | None,
    t0: float,
) -> ConformalMap | None:
    """A warm re-solve at the finest level of ``initial`` only (issue 24 item 3): the sweeps
    start from ``initial`` carried over to ``ws`` (:func:`confnav.conformal.warm.warm_state`:
    the previous meshes, the Cauchy terms of the previous boundary values moved with their
    obstacles), so that only the changed part of the map is left to the iteration. None if
    the warm start does not apply or its map does not meet ``tol`` (the caller then refines
    over the levels as a cold solve does, from :func:`_warm_start_level`).

    Its certificate: the iteration error and the boundary residual are this solve's own; the
    discretisation estimate is inherited. The boundaries kept the previous graded meshes and
    the corner singularities of the map are carried by the previous solve's boundary values,
    whose error the previous map's estimate bounds (its three observed mesh levels, residual
    and all); what this level's first sweep adds is the graded-mesh error of the disk maps of
    curves within ``deviation`` (relative) of circles -- zero for a circle (the trapezoidal
    rule on a smooth periodic integrand converges spectrally; Trefethen & Weideman, SIAM Rev.
    56 (2014) 385-458, sec. 3) and linear in the non-circular part, which carries the corner
    singularities at ``deviation`` times their strength in the polygon. So the estimate is the
    previous map's error estimate times ``1 + deviation`` (an added obstacle counts as
    deviation 1: its polygon is solved here at the previous level, whose error the previous
    estimate bounded for its other polygons).
    """
    from confnav.conformal.warm import warm_state

    if not WARM_RESOLVE:
        return None
    st = warm_state(initial, ws, tol, tail=max(SMOOTH_TAIL, SMOOTH_PER_TOL * ITERATION_SHARE * tol))
    if st is None:
        return None
    ns = initial.diagnostics.nodes_per_side
    if progress is not None:
        progress(f"warm re-solve at {ns} nodes per side (start {st.deviation:.1e} from circles)")

    def _p(sweep: int, change: float) -> None:
        if progress is not None:
            progress(f"  {ns} nodes/side (warm): sweep {sweep}, change {change:.1e}")

    try:
        res = koebe_iteration(
            st.meshes,
            [],
            ws.anchor,
            tol=ITERATION_SHARE * tol,
            progress=_p,
            gmres_tol=gmres_rtol(tol),
            accel=accel,
            start=st,
        )
    except ConvergenceError as exc:
        log.warning("warm re-solve failed (%s); refining over the levels", exc)
        return None
    inherited = float(initial.diagnostics.error_estimate)
    disc = inherited * (1.0 + st.deviation)
    eta, deta = [m.eta for m in st.meshes], [m.deta for m in st.meshes]
    refinements: list[dict[str, float]] = [
        {
            "nodes_per_side": ns,
            "warm_start": 1.0,
            "inherited_error": inherited,
            "deviation": st.deviation,
            "error_estimate": disc,
            "iteration_error": res.iteration_error,
            "sweeps": float(res.sweeps),
            "wall_time": res.wall_time,
        }
    ]
    m = _make_map(ws, (res, eta, deta, ns, disc, []), tol, [], refinements, t0)
    refinements[-1]["boundary_residual"] = m.diagnostics.boundary_residual
    if not m.diagnostics.tol_met:
        log.warning(
            "warm re-solve missed tol (estimate %.1e); refining over the levels",
            m.diagnostics.error_estimate,
        )
        return None
    return m


def _difference(a: CircleDomainResult, b: CircleDomainResult) -> float:
    if a.centers.size == 0:
        return float(abs(a.derivative_at_anchor - b.derivative_at_anchor))
    return float(max(np.max(np.abs(a.centers - b.centers)), np.max(np.abs(a.radii - b.radii))))


def _already_solved(
    workspace: Workspace, tol: float, nodes_per_side: int | None, initial: ConformalMap | None
) -> ConformalMap | None:
    """``initial`` if it is this very workspace solved to at least ``tol`` (nothing to do)."""
    if (
        initial is not None
        and nodes_per_side is None
        and initial.workspace.content_hash == workspace.content_hash
        and initial.diagnostics.tol_met
        and initial.diagnostics.tol <= tol
    ):
        return initial
    return None


#: Start the ladder higher for a workspace with a sharp obstacle tip (round 5, issue 24):
#: the levels a certificate at ``tol`` rests on are the last three solved, and on the scenes
#: measured so far (bench/README.md "Round 5") the workspaces whose largest free-space angle
#: exceeds :data:`SHARP_FREE_ANGLE` -- the default workspace (312 degrees) and 50 mixed
#: obstacles (330) -- were certified only at 180 nodes per side to 1e-8 and at 256 to 1e-10,
#: while those without (two squares, the default shrunk by 0.2 m: 270 at most) were certified
#: at 80 and 120 to 1e-8. The map's leading singularity at a corner of free-space angle
#: ``alpha pi`` is ``(z - v)^(1/alpha)`` (Henrici, "Applied and Computational Complex
#: Analysis", Vol. 1, sec. 5.11): the sharper the tip, the more nodes a given accuracy needs
#: at the same grading. Such a workspace starts at :data:`SHARP_START` instead (nodes per side
#: by the tolerance's band, as :func:`_mesh_levels`); the estimate at the level that certifies
#: rests on the same three levels as before, so the certificate is unchanged -- a sharp
#: workspace that would have been certified lower pays one or two finer levels instead.
START_BY_CORNERS = True
SHARP_FREE_ANGLE = 300.0
#: (smallest tol of the band, first level): tol >= 1e-7 keeps the default start.
SHARP_START: tuple[tuple[float, int], ...] = ((1e-7, 0), (1e-9, 80), (0.0, 120))


def free_angles(ws: Workspace) -> list[float]:
    """Per boundary (outer first), the largest free-space angle (degrees) at one of its
    corners: 360 minus an obstacle's sharpest tip, or a room corner's own angle."""
    out = []
    for j, b in enumerate(ws.boundaries):
        v = np.asarray(b)
        if (signed_area(v) > 0) == (j > 0):
            v = v[::-1]  # free space on the left: outer counter-clockwise, holes clockwise
        turn = np.angle((np.roll(v, -1) - v) / (v - np.roll(v, 1)))
        out.append(float(np.degrees(np.max(np.pi - turn))))
    return out


def largest_free_angle(ws: Workspace) -> float:
    """The largest free-space angle (degrees) at a corner of any boundary: 360 minus the
    sharpest obstacle tip, or a room corner's own angle."""
    return max(free_angles(ws), default=0.0)


def _sharp_start(ws: Workspace | None, tol: float) -> int:
    """Index into :data:`LEVELS` of :data:`SHARP_START` for a sharp workspace; 0 otherwise."""
    if ws is None or not START_BY_CORNERS or largest_free_angle(ws) <= SHARP_FREE_ANGLE:
        return 0
    for low, ns in SHARP_START:
        if tol >= low:
            return LEVELS.index(ns) if ns else 0
    return 0


def _mesh_levels(
    tol: float,
    nodes_per_side: int | None,
    initial: ConformalMap | None,
    workspace: Workspace | None = None,
) -> list[int]:
    """Nodes per side of the levels to solve, coarse to fine: :data:`LEVELS` from a start
    that the tolerance sets (a sharp obstacle tip raises, :data:`START_BY_CORNERS`, and a
    warm start, :func:`_warm_start_level`), or a fixed mesh and the two next coarser ones
    (x1.5 steps), so that an estimate still rests on an observed contraction."""
    if nodes_per_side is not None:
        if nodes_per_side < 8:
            raise SolverError("nodes_per_side must be at least 8")
        return sorted(
            {max(8, round(nodes_per_side / 2.25)), max(8, round(nodes_per_side / 1.5))}
            | {nodes_per_side}
        )
    start = 0 if tol >= 1e-7 else (1 if tol >= 1e-9 else 3)
    start = max(start, _sharp_start(workspace, tol))
    if initial is not None:
        start = max(start, _warm_start_level(initial, tol))
    return list(LEVELS[start:])


def _level_estimate(
    diff: float, prev_diff: float | None, ns: int, prev_ns: int, noise: float
) -> tuple[float, float, list[str]]:
    """Discretisation error of the finer of two levels from their difference ``diff``
    (docs/METHOD.md sec. 2): ``diff rho / (1 - rho)`` (geometric tail, Aitken), rho the error
    ratio per level, the slower of the assumed order n^-p and the contraction observed over
    three levels (``diff / prev_diff``). Returns the estimate, that observed ratio (nan: none)
    and why the estimate is unverified (no contraction observed; differences above ``noise``
    that stopped shrinking)."""
    rho = (prev_ns / ns) ** ASSUMED_ORDER
    unverified: list[str] = []
    ratio = float("nan")
    if prev_diff is not None and prev_diff > 0:
        ratio = diff / prev_diff
        rho = max(rho, ratio)
    else:
        unverified.append(
            f"discretisation estimate from two mesh levels ({prev_ns} and {ns} nodes per "
            f"side) on an assumed order n^-{ASSUMED_ORDER:g}, no contraction observed"
        )
    if rho >= RHO_LEVELS_MAX and diff > noise:
        unverified.append(
            f"level differences stopped shrinking ({prev_diff:.1e} -> {diff:.1e} at "
            f"{ns} nodes per side): the extrapolation does not hold"
        )
    rho = min(rho, RHO_LEVELS_MAX)  # the figure only; unverified says it is not one
    return diff * rho / (1 - rho), ratio, unverified


class _Refinement:
    """The refinement over mesh levels (module docstring): solve each level, estimate its
    discretisation error from the previous one, and stop at the first level whose estimate
    (over at least :data:`MIN_LEVELS` levels) and boundary residual meet ``tol`` -- refining
    only the sides the residual names first, where that may suffice."""

    def __init__(
        self,
        workspace: Workspace,
        tol: float,
        max_error: float,
        progress: Callable[[str], None] | None,
        accel: str | None,
        t0: float,
        method: str = "koebe",
    ) -> None:
        self.workspace, self.tol, self.max_error = workspace, tol, max_error
        self.progress, self.accel, self.t0 = progress, accel, t0
        self.method = method
        self.refinements: list[dict[str, float]] = []
        self.caps: list[str] = []
        self.prev: CircleDomainResult | None = None
        self.prev_ns = 0
        self.prev_diff: float | None = None
        self.prev_resolution = 0.0
        self.failed: ConvergenceError | None = None
        self.best: _Level | None = None
        self.cmap: ConformalMap | None = None
        self.solved = 0  # levels solved (a skipped level does not count)
        self.warm: _Warm | None = None
        self.carry: LevelCarry | None = None
        self.done = False
        self.order = _sweep_order(workspace) if method == "koebe" else None

    def run(self, levels: list[int]) -> ConformalMap:
        """Refine through ``levels`` until one is certified or none is left; the best map."""
        for ns in levels:
            self.level(ns, levels)
            if self.done:
                break
        return self.result()

    def level(self, ns: int, levels: list[int]) -> None:
        """Solve level ``ns``, estimate its error, and certify it if the estimate allows."""
        if self.progress is not None:
            self.progress(f"solving with {ns} nodes per side at the sharpest corners")
        solved = self._solve(ns)
        if solved is None:
            return
        res, meshes = solved
        self.warm = (meshes, res.first_mu)  # the next level's first guesses
        self.carry = res.carry  # and start of its later sweeps
        _check_resolvable(res, ns, self.prev_resolution, self.max_error)
        self.prev_resolution = res.resolution_error
        if self.prev is not None:
            est, unverified = self._estimate(res, meshes, ns)
            if est <= self.tol and self.solved + 1 >= MIN_LEVELS and not unverified:
                self.done = self._certify(ns, est, levels)
                if self.done:
                    return
        if self.prev is not None:  # no longer a refinement's base: its first sweep's record
            self.prev.first_maps, self.prev.first_snapshots = [], {}
        self.prev, self.prev_ns = res, ns
        self.solved += 1

    def _solve(self, ns: int) -> tuple[CircleDomainResult, list[BoundaryMesh]] | None:
        """One level's Koebe iteration; None if it gives nothing (``done`` then says whether
        the refinement ends): a level past the node limit (:class:`GapError`) or failing once
        a usable pair of levels exists ends it on the best level; a failing coarse level is
        skipped (e.g. a needle-like tip, see confnav.conformal.meshing); unresolved crowding
        at two levels is raised (refining does not resolve it)."""
        try:
            return _solve_level(
                self.workspace,
                ns,
                self.tol,
                self.progress,
                self.warm,
                accel=self.accel,
                method=self.method,
                carry=self.carry,
                order=self.order,
            )
        except GapError as exc:
            if self.best is None:
                raise
            self.caps.append(f"node limit at {ns} nodes per side: {exc}")
            log.warning(
                "refinement to level %d stopped (%s); keeping level %d", ns, exc, self.best[3]
            )
            self.done = True
            return None
        except ConvergenceError as exc:
            if isinstance(exc, UnresolvedCrowdingError) and isinstance(
                self.failed, UnresolvedCrowdingError
            ):
                raise  # two levels alike: refining does not resolve crowding
            if self.best is None:
                self.failed = exc
                log.warning("level %d failed (%s); refining", ns, exc)
                return None
            log.warning(
                "refinement to level %d failed (%s); keeping level %d", ns, exc, self.best[3]
            )
            self.done = True
            return None

    def _estimate(
        self, res: CircleDomainResult, meshes: list[BoundaryMesh], ns: int
    ) -> tuple[float, list[str]]:
        """The level's discretisation estimate (:func:`_level_estimate`), recorded in
        ``refinements``; the level becomes the best one."""
        assert self.prev is not None
        diff = _difference(res, self.prev)
        # a difference within the two levels' own iteration errors is iteration noise
        noise = max(ROUNDING_DIFFERENCE * self.tol, res.iteration_error + self.prev.iteration_error)
        est, ratio, unverified = _level_estimate(diff, self.prev_diff, ns, self.prev_ns, noise)
        self.refinements.append(
            {
                "nodes_per_side": ns,
                "difference": diff,
                "error_estimate": est,
                "iteration_error": res.iteration_error,
                "wall_time": res.wall_time,
            }
        )
        if np.isfinite(ratio):  # difference / previous difference (observed contraction)
            self.refinements[-1]["ratio"] = ratio
        eta, deta = [m.eta for m in meshes], [m.deta for m in meshes]
        self.best = (res, eta, deta, ns, est, unverified)
        self.cmap = None
        self.prev_diff = diff
        return est, unverified

    def _certify(self, ns: int, est: float, levels: list[int]) -> bool:
        """The discretisation is fine: the a-posteriori boundary residual must agree, else
        refine the sides it names (:func:`_refine_sides`, if the estimate leaves
        :data:`LOCAL_HEADROOM`). True if a map meeting ``tol`` came out."""
        assert self.best is not None
        cmap = _make_map(self.workspace, self.best, self.tol, self.caps, self.refinements, self.t0)
        # kept per level: a residual above tol at a level whose discretisation estimate is
        # below it says what forced the next (costlier) level
        self.refinements[-1]["boundary_residual"] = cmap.diagnostics.boundary_residual
        self.cmap = cmap
        if cmap.diagnostics.boundary_residual <= self.tol:
            return True
        finer = levels[levels.index(ns) + 1 :]
        if LOCAL_REFINEMENT and finer and est <= LOCAL_HEADROOM * self.tol:
            local = _refine_sides(
                self.workspace,
                ns,
                finer,
                self.best,
                cmap,
                self.tol,
                self.progress,
                self.warm,
                self.caps,
                self.refinements,
                self.t0,
                self.accel,
            )
            if local is not None:
                self.cmap, self.best = local
                return True
            self.cmap = None
        return False

    def result(self) -> ConformalMap:
        """The map of the best level (its full error budget); the first failure if no pair of
        levels was solved."""
        if self.best is None:
            if self.failed is not None:
                raise self.failed
            raise SolverError("refinement needs at least two mesh levels")
        if self.cmap is None:
            self.cmap = _make_map(
                self.workspace, self.best, self.tol, self.caps, self.refinements, self.t0
            )
        return self.cmap


def _refuse_unusable(cmap: ConformalMap, max_error: float) -> None:
    """A map whose estimated error exceeds ``max_error`` is never returned: raise, naming the
    error terms, the worst boundary point and, when the solve measured crowding, the atlas
    (:class:`~confnav.errors.CrowdingError`)."""
    diag = cmap.diagnostics
    if diag.error_estimate <= max_error:
        return
    where = ""
    if diag.boundary_residual >= diag.error_estimate:  # name the place: a user can see it
        z, name = cmap.worst_boundary_point()
        where = f"; largest on {name} at {fmt_point(z)}"
    crowded = crowding_reason(diag)
    error = CrowdingError if crowded else SolverError  # an atlas resolves crowding
    raise error(
        f"the map's estimated error {diag.error_estimate:.1e} is too large to navigate "
        f"with (even at {diag.nodes_per_side} nodes per side; discretisation "
        f"{diag.discretisation_error:.1e}, iteration {diag.iteration_error:.1e}, "
        f"boundary residual {diag.boundary_residual:.1e}, smooth-grid resolution "
        f"{diag.resolution_error:.1e}{where})"
        + (f"; one map crowds here ({crowded}): an atlas resolves it" if crowded else "")
    )


def _warn_tol_missed(diag: SolveReport, tol: float) -> None:
    """An :class:`AccuracyWarning` naming every error term above ``tol`` (raised at the
    caller of :func:`solve`)."""
    why = [
        f"{name} {val:.1e}"
        for name, val in (
            ("discretisation", diag.discretisation_error),
            ("iteration", diag.iteration_error),
            ("boundary residual", diag.boundary_residual),
            ("smooth-grid resolution", diag.resolution_error),
        )
        if val > tol
    ]
    if not diag.iteration_converged:
        why.append("the Koebe iteration did not converge (stalled or sweep limit)")
    why += diag.caps + diag.unverified
    warnings.warn(
        f"conformal map: estimated error {diag.error_estimate:.1e}, tol {tol:.1e} not met "
        f"(finest mesh {diag.nodes_per_side} nodes per side): " + "; ".join(why),
        AccuracyWarning,
        stacklevel=3,
    )


#: BLAS threads during :func:`solve` (None: the BLAS library's own count). Every BLAS call of
#: a solve is a small, memory-bound product (GNK matrix-vector products of a few thousand
#: nodes, the Cauchy expansions' n x p x 3 products, block inverses of ~100 nodes), where a
#: second thread gains little and a multi-threaded OpenBLAS waking and spinning its threads
#: costs CPU time many times the product's on a busy machine; the services run with one BLAS
#: thread for the same reason (``confnav.cli.services``). Measured side by side in one run
#: (bench/results/koebe_corner_blas1.json, load 4.8-9.8, CPU s, the library's 2 threads
#: against 1, corner preconditioner on): 50 mixed obstacles 61.1 -> 19.9, the default
#: workspace to 1e-10 3.0 -> 1.4, it shrunk by 0.2 m 7.9 -> 3.0, two squares 0.01 apart 24.3
#: -> 17.9; the same maps. A count set in the environment (:data:`BLAS_THREAD_ENV`) is left
#: alone.
SOLVE_BLAS_THREADS: int | None = 1
BLAS_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _blas_threads() -> contextlib.AbstractContextManager[object]:
    """The BLAS thread limit of a solve (:data:`SOLVE_BLAS_THREADS`), restored on return."""
    if SOLVE_BLAS_THREADS is None or any(v in os.environ for v in BLAS_THREAD_ENV):
        return contextlib.nullcontext()
    limit: contextlib.AbstractContextManager[object] = threadpool_limits(
        limits=SOLVE_BLAS_THREADS, user_api="blas"
    )
    return limit


def solve(
    workspace: Workspace,
    tol: float = 1e-10,
    *,
    nodes_per_side: int | None = None,
    progress: Callable[[str], None] | None = None,
    initial: ConformalMap | None = None,
    max_error: float = UNUSABLE_ERROR,
    koebe_accel: str | None = None,
    method: str = "koebe",
) -> ConformalMap:
    """Compute the conformal map of ``workspace`` onto a circle domain.

    The steps: the mesh levels (:func:`_mesh_levels`); the refinement over them
    (:class:`_Refinement`: each level's Koebe iteration, its discretisation estimate
    :func:`_level_estimate`, the boundary residual and per-side refinement that certify it);
    a map too inaccurate to use is refused (:func:`_refuse_unusable`), one missing ``tol``
    is returned with a warning (:func:`_warn_tol_missed`).

    Parameters
    ----------
    workspace
        The validated workspace; its anchor is sent to 0.
    tol
        Target accuracy of the circle domain (centres and radii, absolute, unit-disk scale).
    nodes_per_side
        Fix the mesh instead of refining: three levels, ``nodes_per_side`` and the two next
        coarser ones (x1.5 steps), so that the discretisation estimate rests on an observed
        contraction, never on an assumed order alone.
    progress
        Called with one-line progress messages.
    initial
        A map of a workspace like this one (an obstacle moved, added or removed; the same
        workspace at another radius): a warm re-solve. The same workspace solved to at least
        ``tol`` is returned as is; a workspace with the same outer boundary and anchor whose
        obstacles moved, were added or removed is solved at ``initial``'s finest level only,
        starting from ``initial`` (:func:`_warm_solve`: its estimate is ``initial``'s times
        ``1 + deviation``, its iteration error and residual its own); otherwise, or if that
        misses ``tol``, the refinement starts two levels below the one ``initial`` needed
        (:func:`_warm_start_level`), skipping the coarse levels, and keeps the full
        certificate (three levels, residual). Anything that does not fit (another tolerance
        range, a fixed mesh) falls back to a cold solve's levels.
    max_error
        Largest estimated error of a map that is returned (with ``tol_met`` saying whether it
        meets ``tol``) rather than refused. The default, :data:`UNUSABLE_ERROR`, is for callers
        whose safety rests on the map; a caller that keeps its robots out of the walls on the
        exact geometry (the controller's safety filter, docs/NAVIGATION.md) may accept a
        coarse map (e.g. ``tol=1e-3, max_error=1e-2``): the certificate stays honest, the map
        then only costs path quality (docs/SERVICES.md, progressive maps).
    koebe_accel
        Acceleration of the Koebe sweeps: ``"none"``, ``"sor"`` or ``"extrapolate"``
        (:mod:`confnav.conformal.acceleration`); None: the default,
        :data:`confnav.conformal.circledomain.KOEBE_ACCEL`.
    method
        ``"koebe"`` (the sweeps, default) or ``"nasser"``: a few sweeps, then Newton steps on
        the whole circle domain (:mod:`confnav.conformal.circular_map`; experimental, its
        levels are never reported converged). Measured side by side (bench/bench_koebe.py,
        bench/results/koebe_methods.json, CPU s on the shared machine): two squares 0.1 apart
        to 1e-8 9.7 s sweeps / 21.6 s Newton (asymmetry 2.4e-11 / 1.6e-8); 0.01 apart at a
        fixed 80 nodes per side 83.7 / 190.9 s (Newton rejected, the sweeps redone); default
        workspace to 1e-10 5.0 / 24.2 s; shrunk by 0.2 m 26.1 s / refused; 50 obstacles
        76.0 / 129.6 s (Newton capped, the sweeps redone). The sweeps win
        everywhere measured, so they stay the default.

    Raises
    ------
    SolverError, CrowdingError, ConvergenceError
        The map cannot be computed to a usable accuracy.
    """
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise SolverError(f"tol must be in (0, 1), got {tol}")
    if method not in METHODS:
        raise SolverError(f"method must be one of {METHODS}, got {method!r}")
    done = _already_solved(workspace, tol, nodes_per_side, initial)
    if done is not None:
        return done
    if not (np.isfinite(max_error) and max_error > 0):
        raise SolverError(f"max_error must be positive and finite, got {max_error}")
    t0 = time.perf_counter()
    with _blas_threads():
        if initial is not None and nodes_per_side is None and method == "koebe":
            warm = _warm_solve(workspace, tol, initial, progress, koebe_accel, t0)
            if warm is not None:
                return warm
        levels = _mesh_levels(tol, nodes_per_side, initial, workspace)
        cmap = _Refinement(workspace, tol, max_error, progress, koebe_accel, t0, method).run(levels)
    _refuse_unusable(cmap, max_error)
    if not cmap.diagnostics.tol_met:
        _warn_tol_missed(cmap.diagnostics, tol)
    return cmap


__all__ = ["LEVELS", "AccuracyWarning", "crowding", "crowding_reason", "solve"]
