"""Fast Cauchy sums ``sum_k q_k / (z - zeta_k)``: expansions far away, FMM or direct near.

Every kernel sum of the integral equation and every evaluation of a map is a Cauchy sum. The
2-D Laplace FMM of pyfmmlib (``lfmm2dparttarg``) computes, for complex charges q_k at sources
zeta_k, the field ``E = -grad sum q_k log|z - zeta_k|``; its complex form ``E_x - i E_y`` equals
``sum_k q_k / (z - zeta_k)`` (checked against direct summation to 1e-15 in tests).

Sums from one curve to many targets (a disk map of one boundary applied to every other
boundary: the Koebe iteration's main cost) first take the targets that are far from the curve
as a whole, in one of two ways about the centre c of the sources' bounding box, with
R = max |zeta_k - c| and r = min |zeta_k - c| ([1] sec. 2, Lemmas 2.1-2.3):

* outside, ``|z - c| >= R / EXPANSION_RATIO`` (the multipole, or Laurent, expansion):
  ``sum_k q_k/(z - zeta_k) = sum_{m>=0} a_m / (z - c)^(m+1)``, ``a_m = sum_k q_k (zeta_k - c)^m``;
* inside, ``|z - c| <= EXPANSION_RATIO r`` (the local, or Taylor, expansion):
  ``sum_k q_k/(z - zeta_k) = -sum_{m>=0} b_m (z - c)^m``, ``b_m = sum_k q_k/(zeta_k - c)^(m+1)``.

With rho = R/|z - c| (resp. |z - c|/r) the truncation after degree p errs by at most
``(sum_k |q_k| / d) rho^(p+1) / (1 - rho)`` (d = |z - c| resp. r), and
``(sum_k |q_k| / d^2) rho^(p+1) ((p+2) - (p+1) rho) / (1 - rho)^2`` for the second-order sums;
the degree is chosen per band of rho so that both stay below :data:`EXPANSION_EPS` times
``sum |q_k| / d``, the rounding error of the direct sum itself. The targets left over (near the
curve) are summed by the FMM when that pays, else directly. A curve with n nodes and N far
targets thus costs O((n + N) p) instead of O(n N).

References
----------
.. [1] L. Greengard, V. Rokhlin, "A fast algorithm for particle simulations",
   J. Comput. Phys. 73 (1987) 325-348.
.. [2] M. M. S. Nasser, "Fast solution of boundary integral equations with the generalized
   Neumann kernel", ETNA 44 (2015) 189-229, sec. 4 (FMM for the GNK matrix-vector product).
"""

from __future__ import annotations

import numpy as np

from confnav.types import CArray as ComplexArray
from confnav.types import IArray as IntArray

#: Above this many source-target interactions the FMM is used.
FMM_THRESHOLD = 2_000_000
#: pyfmmlib precision flag: 3 gives ~1e-12 relative, 4 gives ~1e-15 (measured, 9000 points).
FMM_IPREC = 4

try:  # pragma: no cover - availability depends on the platform wheel
    from pyfmmlib import lfmm2dparttarg as _lfmm

    HAVE_FMM = True
except ImportError:  # pragma: no cover
    HAVE_FMM = False


def _fmm(
    sources: ComplexArray,
    charges: ComplexArray,
    targets: ComplexArray | None,
    second: bool = False,
) -> tuple[ComplexArray, ComplexArray | None]:
    """FMM Cauchy sums at the sources (self term excluded) or at the targets.

    Returns ``sum q/(z - zeta)`` and, with ``second``, ``sum q/(z - zeta)^2`` (from the
    Hessian: for the potential sum q log|z - zeta| it equals -(H_xx - i H_xy)).
    """
    src = np.ascontiguousarray(np.vstack([sources.real, sources.imag]))
    q = np.ascontiguousarray(charges, dtype=np.complex128)
    ns = sources.size
    if targets is None:
        tgt = np.zeros((2, 1))
        nt = 1
    else:
        tgt = np.ascontiguousarray(np.vstack([targets.real, targets.imag]))
        nt = targets.size
    on_src = targets is None
    ier, _pot, fld, hess, _pt, fldt, hesst = _lfmm(
        iprec=FMM_IPREC,
        source=src,
        ifcharge=1,
        charge=q,
        ifdipole=0,
        dipstr=np.zeros(ns, np.complex128),
        dipvec=np.zeros((2, ns)),
        ifpot=0,
        iffld=int(on_src),
        ifhess=int(on_src and second),
        ntarget=nt,
        target=tgt,
        ifpottarg=0,
        pottarg=np.zeros(nt, np.complex128),
        iffldtarg=int(not on_src),
        fldtarg=np.zeros((2, nt), np.complex128),
        ifhesstarg=int(second and not on_src),
        hesstarg=np.zeros((3, nt), np.complex128),
    )
    if ier != 0:
        raise RuntimeError(f"pyfmmlib lfmm2dparttarg failed with ier={ier}")
    f = fld if on_src else fldt
    h = hess if on_src else hesst
    first = np.asarray(f[0] - 1j * f[1], dtype=np.complex128)
    return first, (np.asarray(-(h[0] - 1j * h[1]), dtype=np.complex128) if second else None)


def cauchy_self(z: ComplexArray, q: ComplexArray) -> ComplexArray:
    """``c_i = sum_{k != i} q_k / (z_i - z_k)`` for distinct nodes z."""
    n = z.size
    if HAVE_FMM and n * n > FMM_THRESHOLD:
        return _fmm(z, q, None)[0]
    d = z[:, None] - z[None, :]
    np.fill_diagonal(d, 1.0)
    m = q[None, :] / d
    np.fill_diagonal(m, 0.0)
    return np.asarray(m.sum(axis=1))


def cauchy_sums(
    sources: ComplexArray, charges: list[ComplexArray], targets: ComplexArray
) -> list[ComplexArray]:
    """``c_j = sum_k q_k / (x_j - z_k)`` for each charge vector q, at targets off the sources.

    Far targets by expansions (module docstring), the others directly (one kernel matrix
    shared by all charge vectors, built in chunks with an in-place reciprocal) or, above
    :data:`FMM_THRESHOLD` interactions, by the FMM.
    """
    return cauchy_sums2(sources, charges, targets, second=False)[0]


def cauchy_sums2(
    sources: ComplexArray,
    charges: list[ComplexArray],
    targets: ComplexArray,
    second: bool = True,
) -> tuple[list[ComplexArray], list[ComplexArray]]:
    """First- and second-order sums ``sum q/(x - z)`` and ``sum q/(x - z)^2`` per charge."""
    Q = np.column_stack(charges).astype(np.complex128, copy=False)
    one = np.empty((targets.size, Q.shape[1]), np.complex128)
    two = np.empty_like(one) if second else None
    near = _expanded(sources, Q, targets, one, two)
    if near.size:
        _near_sums(sources, charges, Q, targets[near], near, one, two)
    firsts = [one[:, j] for j in range(Q.shape[1])]
    seconds = [two[:, j] for j in range(Q.shape[1])] if two is not None else []
    return firsts, seconds


def _near_sums(
    sources: ComplexArray,
    charges: list[ComplexArray],
    Q: ComplexArray,
    targets: ComplexArray,
    where: IntArray,
    one: ComplexArray,
    two: ComplexArray | None,
) -> None:
    """The sums at ``targets`` (rows ``where`` of one/two) by the FMM or directly."""
    second = two is not None
    if HAVE_FMM and sources.size * targets.size > FMM_THRESHOLD and targets.size > 64:
        for j, q in enumerate(charges):
            f, s = _fmm(sources, np.asarray(q, np.complex128), targets, second)
            one[where, j] = f
            if two is not None and s is not None:
                two[where, j] = s
        return
    step = max(1, 2_000_000 // max(sources.size, 1))  # bound the temporary's memory
    for s0 in range(0, targets.size, step):
        R = np.subtract.outer(targets[s0 : s0 + step], sources)
        np.reciprocal(R, out=R)
        rows = where[s0 : s0 + step]
        one[rows] = R @ Q
        if two is not None:
            np.multiply(R, R, out=R)
            two[rows] = R @ Q


def _tail_bound(rho: float, p: int) -> float:
    """Truncation bound after degree p (module docstring), relative to sum|q|/d: the larger
    of the first-order and (the local expansion's, the larger) second-order tails."""
    first = rho ** (p + 1) / (1 - rho)
    second = rho**p * ((p + 1) - p * rho) / (1 - rho) ** 2
    return float(max(first, second))


def _degree(rho: float) -> int:
    """Smallest degree whose truncation bound at ratio rho is below EXPANSION_EPS."""
    p = 1
    while _tail_bound(rho, p) > EXPANSION_EPS:
        p += 1
    return p


#: Targets at ratio rho <= this from a curve's centre (R/|z - c| outside, |z - c|/r inside)
#: take an expansion instead of the direct sum.
EXPANSION_RATIO = 0.5
#: Truncation error allowed, relative to sum|q|/d: the rounding of the direct sum.
EXPANSION_EPS = 2.0**-53
#: Upper edges of the bands of rho that share one degree (the last is EXPANSION_RATIO).
EXPANSION_BANDS = (0.0625, 0.125, 0.25, EXPANSION_RATIO)
_BAND_DEGREES = tuple(_degree(b) for b in EXPANSION_BANDS)
#: Expansions only for at least this many sources and targets (else the direct sum is cheaper).
EXPANSION_MIN = 32
#: Targets per block of the expansion's evaluation (bounds its Vandermonde temporary).
EXPANSION_BLOCK = 8192


def _expanded(
    sources: ComplexArray,
    Q: ComplexArray,
    targets: ComplexArray,
    one: ComplexArray,
    two: ComplexArray | None,
) -> IntArray:
    """Fill the rows of one/two of the targets far from the sources by the multipole (outside)
    or local (inside) expansion about the sources' bounding-box centre; return the indices of
    the targets left (module docstring)."""
    if sources.size < EXPANSION_MIN or targets.size < EXPANSION_MIN:
        return np.arange(targets.size)
    c = 0.5 * complex(
        sources.real.min() + sources.real.max(), sources.imag.min() + sources.imag.max()
    )
    d_src = np.abs(sources - c)
    R, r = float(d_src.max()), float(d_src.min())
    d = np.abs(targets - c)
    with np.errstate(divide="ignore"):
        rho_out = R / d
    rho_in = d / r if r > 0 else np.full(d.size, np.inf)
    outside = rho_out <= EXPANSION_RATIO
    inside = rho_in <= EXPANSION_RATIO
    for far, rho, multipole in ((outside, rho_out, True), (inside, rho_in, False)):
        if not far.any():
            continue
        band = np.searchsorted(EXPANSION_BANDS, rho[far])
        idx = np.flatnonzero(far)
        p_max = _BAND_DEGREES[int(band.max())]
        # moments in the scaled variable (|terms| <= |q_k|: no over- or underflow), degrees
        # 0..p_max + 1 (the local second-order sums need one more): a_m / R^m outside,
        # b_m r^(m+1) inside
        u = (sources - c) / R if multipole else r / (sources - c)
        V = _powers(u, p_max + 2)  # (degree, source): u^0 .. u^(p_max + 2)
        A = (V[:-1] if multipole else V[1:]) @ Q
        m = np.arange(p_max + 2)[:, None]
        for b, p in enumerate(_BAND_DEGREES):
            sel = idx[band == b]
            for s0 in range(0, sel.size, EXPANSION_BLOCK):
                rows = sel[s0 : s0 + EXPANSION_BLOCK]
                _evaluate(
                    targets[rows] - c,
                    R if multipole else r,
                    A[: p + 2],
                    p,
                    multipole,
                    rows,
                    one,
                    two,
                    m,
                )
    return np.flatnonzero(~(outside | inside))


def _powers(w: ComplexArray, p: int) -> ComplexArray:
    """``P[m] = w^m`` for m = 0..p, one row per degree (each row contiguous): built row by row
    with the products ``cumprod`` would take (equal to rounding), and faster than ``cumprod``
    along the short axis of a (points, degrees) array, which loops per point (bench/README.md,
    "Corner-block preconditioner and one BLAS thread")."""
    P = np.empty((p + 1, w.size), np.complex128)
    P[0] = 1.0
    if p >= 1:
        P[1] = w
    for m in range(2, p + 1):
        np.multiply(P[m - 1], w, out=P[m])
    return P


def _evaluate(
    x: ComplexArray,
    scale: float,
    A: ComplexArray,
    p: int,
    multipole: bool,
    rows: IntArray,
    one: ComplexArray,
    two: ComplexArray | None,
    m: IntArray,
) -> None:
    """One block of targets (x = z - c) of one band: the expansions to degree p."""
    if not rows.size:
        return
    w = scale / x if multipole else x / scale
    W = _powers(w, p).T  # (target, degree), a view
    if multipole:  # sum a_m/x^(m+1) and sum (m+1) a_m/x^(m+2)
        one[rows] = (W @ A[: p + 1]) / x[:, None]
        if two is not None:
            two[rows] = (W @ (A[: p + 1] * (m[: p + 1] + 1))) / (x * x)[:, None]
    else:  # -sum b_m x^m and sum m b_m x^(m-1)
        one[rows] = (W @ A[: p + 1]) * (-1.0 / scale)
        if two is not None:
            two[rows] = (W @ (A[1 : p + 2] * (m[1 : p + 2]))) * (1.0 / scale**2)


__all__ = ["HAVE_FMM", "cauchy_self", "cauchy_sums", "cauchy_sums2"]
