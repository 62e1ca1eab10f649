"""Fast Cauchy sums ``sum_k q_k / (z - zeta_k)``: direct for small problems, FMM for large.

Every kernel sum of the integral equation and every evaluation of a map is a Cauchy sum. The
2-D Laplace FMM of pyfmmlib (``lfmm2dparttarg``) computes, for complex charges q_k at sources
zeta_k, the field ``E = -grad sum q_k log|z - zeta_k|``; its complex form ``E_x - i E_y`` equals
``sum_k q_k / (z - zeta_k)`` (checked against direct summation to 1e-15 in tests).

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

    Dense for small problems (one kernel matrix shared by all charge vectors, built in chunks
    with an in-place reciprocal), FMM above :data:`FMM_THRESHOLD` interactions.
    """
    return cauchy_sums2(sources, charges, targets, second=False)[0]


def cauchy_sums2(
    sources: ComplexArray,
    charges: list[ComplexArray],
    targets: ComplexArray,
    second: bool = True,
) -> tuple[list[ComplexArray], list[ComplexArray]]:
    """First- and second-order sums ``sum q/(x - z)`` and ``sum q/(x - z)^2`` per charge."""
    if HAVE_FMM and sources.size * targets.size > FMM_THRESHOLD and targets.size > 64:
        res = [_fmm(sources, q, targets, second) for q in charges]
        return [r[0] for r in res], [r[1] for r in res if r[1] is not None]
    Q = np.column_stack(charges)
    one = np.empty((targets.size, len(charges)), np.complex128)
    two = np.empty((targets.size, len(charges)), np.complex128) if second else None
    step = max(1, 2_000_000 // max(sources.size, 1))  # bound the temporary's memory
    for s in range(0, targets.size, step):
        R = np.subtract.outer(targets[s : s + step], sources)
        np.reciprocal(R, out=R)
        one[s : s + step] = R @ Q
        if two is not None:
            np.multiply(R, R, out=R)
            two[s : s + step] = R @ Q
    firsts = [one[:, j] for j in range(len(charges))]
    seconds = [two[:, j] for j in range(len(charges))] if two is not None else []
    return firsts, seconds


__all__ = ["HAVE_FMM", "cauchy_self", "cauchy_sums", "cauchy_sums2"]
