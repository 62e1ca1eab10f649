"""The generalized Neumann kernel (GNK) boundary integral equation on one closed curve.

For a curve ``eta(t)``, a complex function ``A`` on it and a real ``gamma``, there are a unique
real function ``mu`` and a real constant ``h`` such that ``A f = gamma + h + i mu`` are the
boundary values of a function ``f`` analytic in the domain; they solve

    (I - N) mu = -M gamma,        h = [M mu - (I - N) gamma] / 2,

with the kernels (``s, t`` parameters on the curve)

    N(s, t) = (1/pi) Im( A(s) eta'(t) / (A(t) (eta(t) - eta(s))) ),
    M(s, t) = (1/pi) Re( A(s) eta'(t) / (A(t) (eta(t) - eta(s))) ).

Discretisation: Nystrom with the trapezoidal rule (weight 2pi/n) on the graded mesh. The
singularities are removed with ``N 1 = -1`` and ``M 1 = 0``:

    [(I - N) x]_i = 2 x_i - sum_{k != i} N_ik (x_k - x_i),
    [M x]_i       = sum_{k != i} M_ik (x_k - x_i) + (2/n) x'(t_i),

where ``x'`` is the spectral (FFT) derivative. The system is solved by GMRES; a matrix-vector
product is one Cauchy sum (direct or FMM, see :mod:`confnav.conformal.cauchy`), so a solve costs
O(n^2) dense or O(n) with the FMM. (The seed's eqs. (integral equation) and (c) swap the known
and unknown functions -- docs/METHOD.md sec. 6 errata; this module follows docs/METHOD.md sec. 2.)

On a graded polygon mesh (a level's first sweep) GMRES is right-preconditioned by the inverse
of the operator's diagonal blocks at the vertices (:class:`_CornerBlocks`): the corners make
``I - N`` non-compact, and these blocks carry that part. Measured (bench/README.md,
"Corner-block preconditioner and one BLAS thread"; ``bench/results/koebe_corner_blas1.json``):
GMRES iterations over a whole solve 10136 -> 5238 on 50 mixed obstacles, 831 -> 446 on the
default workspace to 1e-10, the same maps within 9.1e-12.

References
----------
.. [1] R. Wegmann, M. M. S. Nasser, "The Riemann-Hilbert problem and the generalized Neumann
   kernel on multiply connected regions", J. Comput. Appl. Math. 214 (2008) 36-57, Thm. 5.
.. [2] M. M. S. Nasser, "Fast solution of boundary integral equations with the generalized
   Neumann kernel", ETNA 44 (2015) 189-229, secs. 2-4 (Nystrom, singularity removal, FMM).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.linalg import LinearOperator, gmres

import confnav.conformal.cauchy as _cauchy
from confnav.conformal.cauchy import cauchy_self
from confnav.errors import ConvergenceError
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Default relative GMRES residual (for a map tolerance of 1e-11 and below); callers tie it to
#: their tolerance with :func:`gmres_rtol`.
GMRES_RTOL = 1e-14
#: GMRES residual per unit of the requested map tolerance. The GNK operator I - N is a
#: second-kind operator with a bounded inverse (Wegmann & Nasser 2008, Thm. 5), so the error
#: of mu is of the order of the residual; 1e-3 keeps it far below the tolerance.
GMRES_PER_TOL = 1e-3
#: A GMRES run that stops at its iteration limit is accepted only if its true residual is
#: within this factor of the residual asked for (never at a fixed threshold).
GMRES_ACCEPT = 10.0
GMRES_RESTART = 80
GMRES_MAXITER = 20


def spectral_derivative(x: FloatArray) -> FloatArray:
    """d x / d t for samples of a smooth 2pi-periodic function at t_i = 2pi i/n (FFT)."""
    n = x.size
    k = np.fft.rfftfreq(n, d=1.0 / n)
    xh = np.fft.rfft(x) * 1j * k
    if n % 2 == 0:
        xh[-1] = 0.0  # the Nyquist mode has no derivative in a real expansion
    return np.fft.irfft(xh, n)


def spectral_derivative_complex(x: ComplexArray) -> ComplexArray:
    """d x / d t for complex samples of a smooth 2pi-periodic function (FFT)."""
    return spectral_derivative(x.real) + 1j * spectral_derivative(x.imag)


@dataclass(frozen=True)
class GNKSolution:
    """Solution of one GNK equation: ``mu`` at the nodes, ``h``, and diagnostics."""

    mu: FloatArray
    h: float
    h_spread: float  # max - min of the pointwise h: a residual check (0 in exact arithmetic)
    iterations: int
    #: Absolute 2-norm of the residual left, ``|(I - N) mu + M gamma|``: ``rtol`` times the
    #: right-hand side's norm when GMRES met its target, the measured residual when a run
    #: stopped at its limit was accepted within :data:`GMRES_ACCEPT` of it.
    residual: float = 0.0


#: Up to this many nodes the GNK matrix is built densely (O(n^2) memory, fast BLAS matvecs);
#: above it every matrix-vector product is an FMM Cauchy sum (O(n)).
DENSE_MAX_NODES = 3200
#: The same limit for a *smooth* curve (a Koebe sweep's smooth grid, uniform in an analytic
#: parameter): GMRES needs ~3 iterations there (a second-kind operator on an analytic curve),
#: so a solve costs ~6 products, and building the n x n matrix (~10 passes over n^2 complex
#: entries) costs more than the products it serves. Profiled on the default workspace shrunk
#: by 0.2 m (bench/README.md, "Where the time goes"; bench/results/core_profile.json): the
#: assembly of the GNK matrices, mostly the outer boundary's 2048-point grid rebuilt in every
#: sweep, took 7.8 of 21.8 s CPU for 225-270 GMRES iterations per level over 60 solves.
#: Below ~1400 nodes the matrix-free product is a direct sum
#: (:func:`confnav.conformal.cauchy.cauchy_self`), which rebuilds the kernel per product: the
#: dense build wins there, hence the limit.
#: Round 7: 1024 -> 2048. Since round 3 the smooth grids take sizes in eighths of an octave
#: (1117, 1218, 1328, ...: circledomain.GRID_STEPS), not only powers of two, and those between
#: 1024 and ~1414 fell to the matrix-free *direct* sums (below cauchy.FMM_THRESHOLD) that
#: rebuild the n^2 kernel at every product. Measured (bench/results/core_probes_round7.json,
#: an interior map of a smooth curve, one BLAS thread, 9 GMRES iterations, ms, matrix-free /
#: dense with the split assembly, :data:`DENSE_SPLIT_ASSEMBLY`): 1117 nodes 125 / 13, 1280
#: 165 / 17, 1579 (FMM) 94 / 27, 2048 112 / 48, 2580 152 / 83, 3584 193 / 192; the default
#: workspace shrunk by 0.2 m solves its outer boundary's 1280-point grid in every sweep:
#: 2.40 -> 1.65 s CPU with the other round-7 changes (bench/README.md "Round 7").
SMOOTH_DENSE_MAX_NODES = 2048

#: Keep a dense GNK matrix complex and take its real and imaginary parts' products through
#: its float view (the other part's slots multiplied by exact zeros) instead of copying the
#: parts into two real matrices. The copies (strided reads into freshly faulted-in pages)
#: cost more than the products they served, ~5 GMRES products per graded solve (a cProfile
#: of 50 obstacles). A product reads twice the memory of one part, so this
#: pays only while products per matrix stay few. Measured side by side (bench/README.md,
#: "Residuals evaluated once; dense GNK matrices kept complex", koebe_interleaved.json, CPU s):
#: the default workspace to 1e-10 1.3 -> 0.9, 50 obstacles 16.1 -> 15.5, two squares 0.01
#: apart 17.0 -> 16.6, the default shrunk by 0.2 m 2.8 -> 2.9 (noise); the same sweeps, maps
#: within 4.9e-12. The products equal the copies' to rounding (the summation order of the
#: BLAS kernels differs). False: two real copies (before).
DENSE_INTERLEAVED = True

#: Write a dense GNK matrix's real and imaginary parts into two contiguous real matrices block
#: by block of its assembly, while each block is in cache (:func:`_assemble_parts`; round 7),
#: instead of keeping it complex (:data:`DENSE_INTERLEAVED`) or copying the parts afterwards
#: (the strided whole-matrix copies that made the interleaved layout win). A GMRES product of
#: ``I - N`` then reads one part (8 n^2 bytes) instead of the complex matrix with zeros in the
#: other part's slots (16 n^2 bytes, twice the flops). The same entries bit for bit; the
#: products equal the interleaved ones to rounding (BLAS summation order). Measured
#: (bench/results/core_probes_round7.json, one BLAS thread, load 2.1-2.7, construction + 8
#: products of ``I - N`` + 2 of ``M``, as a graded solve does, ms): 0.90 -> 0.82 at 300 nodes,
#: 7.7 -> 6.9 at 900, 31.6 -> 20.6 at 1500, 134.1 -> 92.6 at 2968; in the solves:
#: bench/README.md "Round 7".
DENSE_SPLIT_ASSEMBLY = True

#: Rows of a dense GNK matrix per block of its assembly (:func:`_assemble`), in bytes of the
#: block; 0: whole-matrix passes (before round 6).
ASSEMBLY_BLOCK_BYTES = 1 << 22

#: Scan every dense GNK matrix for exactly coincident nodes (True: before round 6). False: only
#: a curve whose nodes are not all distinct (``np.unique``, O(n log n)) is scanned -- the same
#: matrices bit for bit (bench/README.md, "Round 6").
ZERO_SCAN_ALWAYS = False

#: A node whose quadrature weight |eta'| 2pi/n is below this fraction of the curve's size lies
#: within rounding of its neighbours (graded nodes next to a corner, and their images under maps
#: that compress the corner); it carries no information as a source and is dropped as one.
DEAD_NODE_RTOL = 1e-15


#: Two live nodes closer than this many units in the last place of the coordinates are one
#: point in floating point: 1/(eta_k - eta_i) has a rounding error above 1/16 there. Graded nodes
#: on the two sides of a corner reach this at 384 nodes per side (p = 7: both within 1e-14 of the
#: vertex), and an inversion (exterior maps) can merge them exactly: the Cauchy sum was then
#: inf, GMRES ran to its iteration limit on NaN (50 s) and the level failed.
MERGED_NODE_ULPS = 16.0


def alive_nodes(eta: ComplexArray, deta: ComplexArray) -> np.ndarray:
    """Nodes that are sources: quadrature weight above rounding (:data:`DEAD_NODE_RTOL`) and
    not within rounding of the previous such node along the curve (:data:`MERGED_NODE_ULPS`;
    one node of a merged group stays; the others carry a weight below 1e-12 of the curve's)."""
    size = float(np.max(np.abs(eta - eta.mean())))
    alive = np.abs(deta) * (2 * np.pi / eta.size) > DEAD_NODE_RTOL * size
    idx = np.flatnonzero(alive)
    if idx.size > 1:
        ulp = np.finfo(np.float64).eps * float(np.max(np.abs(eta)))
        gap = np.abs(eta[idx] - eta[np.roll(idx, 1)])  # to the previous one, cyclically
        alive[idx[gap <= MERGED_NODE_ULPS * ulp]] = False
    return np.asarray(alive)


def _assemble(eta: ComplexArray, a: ComplexArray, q0: ComplexArray) -> ComplexArray:
    """The dense GNK matrix ``K_ik = a_i q0_k / (eta_i - eta_k)`` (0 on the diagonal and for
    coincident nodes), built in place (in-place reciprocal and products: 3-5x faster than a
    complex division over n^2 entries, measured).

    By blocks of :data:`ASSEMBLY_BLOCK_BYTES` of rows (round 6): each pass (difference,
    reciprocal, row and column scaling) runs over a block while it is in cache instead of over
    the whole matrix, the same operations on every entry in the same order -- the same matrix
    bit for bit (``tests/test_gnk_interleaved.py``). With the coincident-node scan skipped,
    one operator's construction took 20-22 % less time at 2088 and 2968 nodes (the default
    workspace's graded meshes at 180-256 nodes per side) and 12 % at 900 (a hole of 50
    obstacles): bench/README.md, "Round 6"; bench/results/core_probes_round6.json.
    """
    n = eta.size
    K = np.empty((n, n), np.complex128)
    for r0, r1 in _blocks(eta):
        _fill_block(eta, a, q0, r0, r1, K[r0:r1], _scan(eta))
    return K


def _assemble_parts(
    eta: ComplexArray, a: ComplexArray, q0: ComplexArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`_assemble`'s matrix as its real and imaginary parts, two contiguous real
    matrices written block by block from one block buffer (:data:`DENSE_SPLIT_ASSEMBLY`):
    the same entries bit for bit."""
    n = eta.size
    Kr, Ki = np.empty((n, n)), np.empty((n, n))
    blocks = _blocks(eta)
    buf = np.empty((max(r1 - r0 for r0, r1 in blocks), n), np.complex128) if n else None
    scan = _scan(eta)
    for r0, r1 in blocks:
        assert buf is not None
        B = buf[: r1 - r0]
        _fill_block(eta, a, q0, r0, r1, B, scan)
        Kr[r0:r1] = B.real
        Ki[r0:r1] = B.imag
    return Kr, Ki


def _scan(eta: ComplexArray) -> bool:
    """Whether a matrix must be scanned for coincident nodes: eta_i - eta_k is exactly 0
    only for equal nodes (a difference of distinct doubles is never 0, subnormals included),
    so only where np.unique finds some (coincident image nodes, both dead, have no mutual
    term)."""
    return bool(ZERO_SCAN_ALWAYS or np.unique(eta).size < eta.size)


def _blocks(eta: ComplexArray) -> list[tuple[int, int]]:
    """Row ranges of the assembly's blocks (:data:`ASSEMBLY_BLOCK_BYTES`)."""
    n = eta.size
    rows = n if ASSEMBLY_BLOCK_BYTES <= 0 else max(8, ASSEMBLY_BLOCK_BYTES // (16 * max(n, 1)))
    return [(r0, min(n, r0 + max(rows, 1))) for r0 in range(0, n, max(rows, 1))]


def _fill_block(
    eta: ComplexArray,
    a: ComplexArray,
    q0: ComplexArray,
    r0: int,
    r1: int,
    B: ComplexArray,
    scan: bool,
) -> None:
    """Rows ``r0:r1`` of the GNK matrix into ``B``, in place."""
    np.subtract.outer(eta[r0:r1], eta, out=B)  # eta_i - eta_k
    B[np.arange(r1 - r0), np.arange(r0, r1)] = np.inf
    if scan:
        B[B == 0] = np.inf
    np.reciprocal(B, out=B)
    B *= a[r0:r1, None]
    B *= q0[None, :]


class _Operator:
    """Discrete GNK operators for one curve: S(x) = sum_{k!=i} K_ik (x_k - x_i) etc."""

    def __init__(
        self, eta: ComplexArray, deta: ComplexArray, A: ComplexArray, smooth: bool = False
    ) -> None:
        self.n = n = eta.size
        self.eta, self.A = eta, A
        self.alive = alive_nodes(eta, deta)
        self.q0 = np.where(self.alive, deta / A, 0.0)
        limit = min(DENSE_MAX_NODES, SMOOTH_DENSE_MAX_NODES) if smooth else DENSE_MAX_NODES
        self.dense = not (_cauchy.HAVE_FMM and n > limit)
        self.K: ComplexArray | None = None  # the dense matrix, complex (DENSE_INTERLEAVED)
        if self.dense:
            # K_ik = (2/n) A_i q0_k / (eta_k - eta_i), built in place (in-place reciprocal and
            # products: 3-5x faster than a complex division over n^2 entries, measured)
            if DENSE_SPLIT_ASSEMBLY:
                self.Kr, self.Ki = _assemble_parts(eta, (-2.0 / n) * A, self.q0)
            elif DENSE_INTERLEAVED:
                K = _assemble(eta, (-2.0 / n) * A, self.q0)
                # kept complex; products through its float view (DENSE_INTERLEAVED)
                self.K = K
                self._Kf = K.view(np.float64)  # (n, 2n): Re K_ik, Im K_ik interleaved
                self.Kr, self.Ki = K.real, K.imag  # strided views (blocks, row sums)
            else:
                K = _assemble(eta, (-2.0 / n) * A, self.q0)
                self.Kr = K.real.copy()
                self.Ki = K.imag.copy()
            self.rowr = self.Kr.sum(axis=1)
            self.rowi = self.Ki.sum(axis=1)
        else:
            self.c0 = self._cauchy(self.q0)
        self._last: tuple[FloatArray, ComplexArray] | None = None

    def _cauchy(self, q: ComplexArray) -> ComplexArray:
        """sum over alive k != i of q_k/(eta_i - eta_k), at every node i (FMM)."""
        a = self.alive
        out = np.empty(self.n, np.complex128)
        out[a] = cauchy_self(self.eta[a], q[a])
        if not a.all():
            # The few dead nodes directly: one may coincide with a live node in floating point
            # (node images merged next to a corner), and that pair has no mutual term.
            d = np.subtract.outer(self.eta[~a], self.eta[a])
            d[d == 0] = np.inf
            out[~a] = (q[a][None, :] / d).sum(axis=1)
        return out

    def _real(self, x: FloatArray, part: int) -> FloatArray:
        """``Kr @ x`` (part 0) or ``Ki @ x`` (part 1) of the dense matrix."""
        if self.K is None:
            return np.asarray((self.Kr if part == 0 else self.Ki) @ x)
        # x in the slots of one part of the interleaved row, zeros in the other's: one
        # contiguous product over the complex matrix's memory (exact zeros add nothing)
        xx = np.zeros(2 * self.n)
        xx[part::2] = x
        return np.asarray(self._Kf @ xx)

    def S(self, x: FloatArray) -> ComplexArray:
        """sum_{k != i} K_ik (x_k - x_i), complex (Re -> M part, Im -> N part)."""
        if self.dense:
            if self.K is not None:  # both parts in one pass over the complex matrix
                kx = self.K @ x.astype(np.complex128)
                kr, ki = kx.real, kx.imag
            else:
                kr, ki = self._real(x, 0), self._real(x, 1)
            return np.asarray((kr - self.rowr * x) + 1j * (ki - self.rowi * x))
        # one-entry memo: GMRES's last product is (I - N) mu of the solution, whose M mu (h)
        # needs the same FMM sum
        if self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1]
        cx = self._cauchy(self.q0 * x.astype(np.complex128))
        sx = np.asarray(-(2.0 / self.n) * self.A * (cx - x * self.c0))
        self._last = (x.copy(), sx)
        return sx

    def I_minus_N(self, x: FloatArray) -> FloatArray:
        if self.dense:
            return np.asarray(2 * x - (self._real(x, 1) - self.rowi * x))
        return np.asarray(2 * x - self.S(x).imag)

    def M(self, x: FloatArray) -> FloatArray:
        mx = self._real(x, 0) - self.rowr * x if self.dense else self.S(x).real
        return np.asarray(mx + (2.0 / self.n) * spectral_derivative(x))


#: Right-precondition the GNK solves on graded polygon meshes by the inverse of their corner
#: blocks (:class:`_CornerBlocks`); False: plain GMRES (the bench's "before").
CORNER_PRECONDITIONER = True


class _CornerBlocks:
    """Right preconditioner of ``I - N`` on a graded polygon mesh: the inverse of its
    diagonal blocks, one per vertex (the nodes near it on its two sides,
    :meth:`confnav.conformal.boundary.BoundaryMesh.corner_blocks`), the identity's diagonal
    scaling elsewhere.

    At a corner the GNK operator is not compact: the double-layer-type kernel of two sides
    meeting at an angle is homogeneous of degree -1 in the distance to the vertex, so it
    contributes an interval of essential spectrum whose width grows with the turn of the
    corner, and GMRES needs a number of iterations that grows with it (J. Helsing, R. Ojala,
    "Corner singularities for elliptic problems: integral equations, graded meshes,
    quadrature, and compressed inverse preconditioning", J. Comput. Phys. 227 (2008)
    8820-8840, who precondition by the inverse of the corner interactions, compressed). The
    graded nodes next to a vertex interact mostly with each other, so the block of ``I - N``
    on them carries that non-compact part; off these blocks the kernel is smooth (zero
    between collinear nodes of one side), a compact perturbation. ``A P^-1`` with P = the
    block diagonal thus clusters near 1 (Y. Saad, "Iterative Methods for Sparse Linear
    Systems", 2nd ed., SIAM 2003, sec. 9.3.2: right preconditioning leaves the residual that
    GMRES minimises the true residual ``b - A x``, so the solver's tolerance keeps its
    meaning). A singular block or a failed preconditioned run falls back to plain GMRES."""

    def __init__(self, op: _Operator, labels: np.ndarray) -> None:
        # a label < 0: the node is its own block (a diagonal, Jacobi, entry)
        lab = np.asarray(labels)
        self.groups = [np.flatnonzero(lab == v) for v in np.unique(lab[lab >= 0])]
        self.single = np.flatnonzero(lab < 0)
        rowi = op.rowi if op.dense else (-(2.0 / op.n) * op.A * op.c0).imag
        self.diag = 2.0 + rowi[self.single]  # (I - N)_ii (the diagonal of Ki is 0)
        self.blocks: list[FloatArray] = []
        self.inverses: list[FloatArray] = []
        for idx in self.groups:
            if op.dense:
                ki = op.Ki[np.ix_(idx, idx)]  # a copy (fancy index), also of a view
            else:
                d = np.subtract.outer(op.eta[idx], op.eta[idx])
                np.fill_diagonal(d, np.inf)
                d[d == 0] = np.inf
                np.reciprocal(d, out=d)
                d *= (-2.0 / op.n) * op.A[idx][:, None]
                d *= op.q0[idx][None, :]
                ki = d.imag
            B = -ki
            B[np.diag_indices_from(B)] += 2.0 + rowi[idx]
            self.blocks.append(np.ascontiguousarray(B))
            self.inverses.append(np.asarray(np.linalg.inv(B), dtype=np.float64))

    @classmethod
    def build(cls, op: _Operator, labels: np.ndarray) -> _CornerBlocks | None:
        """The preconditioner, or None if a block is singular or its inverse not finite
        (GMRES then runs unpreconditioned)."""
        try:
            pc = cls(op, labels)
        except np.linalg.LinAlgError:
            return None
        finite = np.all(np.isfinite(pc.diag)) and np.all(pc.diag != 0)
        if not (finite and all(np.all(np.isfinite(v)) for v in pc.inverses)):
            return None
        return pc

    def solve(self, y: FloatArray) -> FloatArray:
        """P^-1 y."""
        out = np.empty_like(y)
        out[self.single] = y[self.single] / self.diag
        for idx, inv in zip(self.groups, self.inverses, strict=True):
            out[idx] = inv @ y[idx]
        return out

    def apply(self, x: FloatArray) -> FloatArray:
        """P x (a first guess x0 of mu is the start P x0 of the preconditioned unknown)."""
        out = np.empty_like(x)
        out[self.single] = x[self.single] * self.diag
        for idx, B in zip(self.groups, self.blocks, strict=True):
            out[idx] = B @ x[idx]
        return out


def gmres_rtol(tol: float) -> float:
    """Relative GMRES residual for a map tolerance ``tol``: ``GMRES_PER_TOL * tol``, not below
    :data:`GMRES_RTOL` (rounding) nor above 1e-8."""
    return float(min(max(GMRES_PER_TOL * tol, GMRES_RTOL), 1e-8))


def solve_gnk(
    eta: ComplexArray,
    deta: ComplexArray,
    A: ComplexArray,
    gamma: FloatArray,
    rtol: float = GMRES_RTOL,
    x0: FloatArray | None = None,
    smooth: bool = False,
    corners: np.ndarray | None = None,
) -> GNKSolution:
    """Solve ``(I - N) mu = -M gamma`` and return ``mu`` and ``h`` (see module docstring).

    ``rtol`` is the relative GMRES residual asked for (see :func:`gmres_rtol`); a run stopped at
    its iteration limit is accepted only within :data:`GMRES_ACCEPT` of it. ``x0``: a first
    guess of ``mu`` (e.g. the previous mesh level's solution); the residual asked for is
    relative to the right-hand side either way, so it changes the work, not the accuracy.
    ``smooth``: the curve is a smooth grid (few GMRES iterations): matrix-free products above
    :data:`SMOOTH_DENSE_MAX_NODES` instead of a dense matrix (the same operator either way).
    ``corners``: on a graded polygon mesh, the vertex block of each node
    (:meth:`confnav.conformal.boundary.BoundaryMesh.corner_blocks`): GMRES is then right
    preconditioned by the blocks' inverse (:class:`_CornerBlocks`, with
    :data:`CORNER_PRECONDITIONER`); the residual asked for is the true one either way.
    """
    op = _Operator(eta, deta, A, smooth)
    n = eta.size
    rhs = -op.M(gamma)
    imn_gamma = op.I_minus_N(gamma)  # for h; the same FMM sum as M gamma (memo in S)
    if not np.all(np.isfinite(rhs)):
        raise ConvergenceError(
            f"the GNK right-hand side is not finite (n={n}): coincident or non-finite nodes"
        )
    prec = (
        _CornerBlocks.build(op, corners)
        if CORNER_PRECONDITIONER and corners is not None and corners.shape == (n,)
        else None
    )
    count = [0]
    try:
        mu, info, res = _gmres(op, rhs, rtol, x0, prec, count)
    except ConvergenceError:
        if prec is None:
            raise
        # the preconditioned run failed: the plain one decides (the same equation)
        mu, info, res = _gmres(op, rhs, rtol, x0, None, count)
    hpt = 0.5 * (op.M(mu) - imn_gamma)  # M mu: the memo of GMRES's last product
    bnorm = max(float(np.linalg.norm(rhs)), 1e-300)
    return GNKSolution(
        mu=np.asarray(mu),
        h=float(np.mean(hpt)),
        h_spread=float(np.ptp(hpt)),
        iterations=count[0],
        residual=(rtol if info == 0 else res) * bnorm,
    )


def _gmres(
    op: _Operator,
    rhs: FloatArray,
    rtol: float,
    x0: FloatArray | None,
    prec: _CornerBlocks | None,
    count: list[int],
) -> tuple[FloatArray, int, float]:
    """GMRES on ``(I - N) mu = rhs``, right-preconditioned by ``prec`` if given: returns mu,
    GMRES's info and the measured relative residual of a run stopped at its limit (inf when
    it met ``rtol``); raises :class:`ConvergenceError` if that residual is not accepted."""
    n = rhs.size

    def _mu(y: FloatArray) -> FloatArray:
        return y if prec is None else prec.solve(y)

    def _product(y: FloatArray) -> FloatArray:
        return op.I_minus_N(_mu(y))

    lin = LinearOperator((n, n), matvec=_product, dtype=np.float64)

    def _cb(_: object) -> None:
        count[0] += 1

    # restarted GMRES, one cycle of GMRES_RESTART iterations at a time: a cycle that does not
    # halve the true residual has stagnated (at the rounding floor of the operator, e.g. a
    # crowded boundary of 10^4 nodes stuck at 9e-12 for 1e-13 asked), and the remaining
    # cycles would not help: 20 of them took 147 s on an imported floor plan before failing
    bnorm = max(float(np.linalg.norm(rhs)), 1e-300)
    y = np.zeros(n)  # the unknown GMRES iterates on: mu = P^-1 y (y = mu unpreconditioned)
    if x0 is not None and x0.shape == (n,) and np.all(np.isfinite(x0)):
        y = np.array(x0, dtype=np.float64) if prec is None else prec.apply(x0)
    res = np.inf
    info = -1
    for _cycle in range(GMRES_MAXITER):
        y, info = gmres(
            lin,
            rhs,
            x0=y,
            rtol=rtol,
            atol=0.0,
            restart=GMRES_RESTART,
            maxiter=1,
            callback=_cb,
            callback_type="pr_norm",
        )
        if info == 0:
            break
        last, res = res, float(np.linalg.norm(_product(y) - rhs)) / bnorm
        if not res < 0.5 * last:  # stagnated (or NaN)
            break
    if info != 0 and not res <= GMRES_ACCEPT * rtol:  # NaN is not accepted either
        raise ConvergenceError(
            f"GMRES did not converge for the GNK equation (n={n}, residual {res:.2e} > "
            f"{GMRES_ACCEPT * rtol:.1e} after {count[0]} iterations)"
        )
    return _mu(y), int(info), float(res)


__all__ = [
    "GNKSolution",
    "alive_nodes",
    "gmres_rtol",
    "solve_gnk",
    "spectral_derivative",
    "spectral_derivative_complex",
]
