"""Fast evaluation of trigonometric interpolants of uniform periodic samples.

The Koebe iteration (:mod:`confnav.conformal.circledomain`) evaluates the trigonometric
interpolant of a boundary function sampled on m uniform points (m up to 2^14) at n arbitrary
parameters (the passive nodes). The direct sum costs O(m n); here it costs O(m log m + n q):

1. the Fourier coefficients are zero-padded to an oversampled uniform grid of M = SIGMA m
   points and transformed back (exact: the interpolant's values on the fine grid, as in
   :func:`upsample`);
2. at each point x the fine-grid values are interpolated by the degree q-1 polynomial through
   the q nearest fine-grid nodes (x in the central interval of its stencil), in the modified
   Lagrange ("first barycentric") form, which is backward stable (Higham, IMA J. Numer. Anal.
   24 (2004) 547-556); the basis l_j(t) = w_j prod_{i != j}(t - i) is formed by prefix and
   suffix products, so no division and a point on a node is exact.

Error of step 2 (Dutt & Rokhlin, SIAM J. Sci. Comput. 14 (1993) 1368-1393, sec. 3: the same
oversample-then-interpolate idea with polynomial interpolation replaced by Gaussians): a mode
e^{ikx} with |k| <= m/2 is seen on the fine grid with spacing h = 2 pi / M at k h <= pi/SIGMA,
and polynomial interpolation on q equispaced nodes around x has error
|e^{ikx} - p(x)| <= (k h)^q max_t |prod_i (t - i)| / q! for t in the central interval
(Davis, "Interpolation and Approximation", Dover 1975, thm 3.1.1). With SIGMA = 8, q = 20 the
maximum of |prod_i (t - i)| / q! is 1.7e-7 and (pi/8)^20 = 7.6e-9: at most 1.3e-15 per unit
coefficient (only the top modes reach it). Measured (tests/test_triginterp.py) against an
extended-precision direct sum, the error is at the rounding floor of the evaluation itself
(the phase of mode k at x is only known to ~ k |x| eps, for the direct sum as well).
"""

from __future__ import annotations

from math import factorial

import numpy as np

from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Oversampling factor of the fine grid (power of 2, so the fine grid stays FFT-friendly).
SIGMA = 8
#: Points of the local polynomial interpolation (even: x lies in the central interval).
STENCIL = 20
#: Points per block of the local interpolation (bounds its temporaries to a few tens of MB).
BLOCK = 16384

_J = np.arange(STENCIL)
#: Lagrange weights of the equispaced nodes 0..q-1: w_j = 1 / prod_{i != j} (j - i).
_W = np.array(
    [(-1.0) ** (STENCIL - 1 - j) / (factorial(j) * factorial(STENCIL - 1 - j)) for j in _J]
)


def _padded_coefficients(samples: ComplexArray, size: int) -> ComplexArray:
    """Fourier coefficients of uniform samples (last axis, m points) zero-padded to ``size``
    (FFT ordering), the Nyquist mode of an even m split symmetrically between -m/2 and m/2."""
    m = samples.shape[-1]
    c = np.fft.fft(samples, axis=-1)
    pad = np.zeros((*samples.shape[:-1], size), np.complex128)
    h = (m + 1) // 2  # modes 0 .. h-1 first, then -(m - h) .. -1 (FFT ordering)
    pad[..., :h] = c[..., :h]
    pad[..., size - (m - h) :] = c[..., h:]
    if m % 2 == 0:
        pad[..., h] = 0.5 * c[..., h]
        pad[..., size - h] = 0.5 * c[..., h]
    return np.asarray(pad * (size / m))


def upsample(samples: ComplexArray, size: int) -> ComplexArray:
    """Values of the trigonometric interpolant of uniform periodic samples on ``size`` points."""
    return np.asarray(np.fft.ifft(_padded_coefficients(samples, size), axis=-1))


def trig_eval(
    rows: ComplexArray | FloatArray, x: FloatArray, derivative: bool = False
) -> ComplexArray:
    """Trigonometric interpolants of the rows of ``rows`` (r, m: uniform periodic samples at
    2 pi j / m) at the points ``x``: shape (r, n), or (2 r, n) with the x-derivatives of the
    rows appended when ``derivative``.

    Modes -m/2..m/2 (Nyquist split symmetrically, as in :func:`upsample`); O(m log m + n q).
    """
    samples = np.atleast_2d(np.asarray(rows, np.complex128))
    m = samples.shape[-1]
    big = SIGMA * m
    pad = _padded_coefficients(samples, big)
    if derivative:  # d/dx e^{ikx} = ik e^{ikx}, k the integer wavenumber of each padded slot
        k = np.fft.fftfreq(big, 1.0 / big)
        pad = np.concatenate([pad, pad * (1j * k)])
    fine = np.fft.ifft(pad, axis=-1)
    x = np.asarray(x, np.float64)
    out = np.empty((fine.shape[0], x.size), np.complex128)
    for s in range(0, x.size, BLOCK):
        t = np.mod(x[s : s + BLOCK] * (big / (2 * np.pi)), big)  # position in fine-grid units
        base = np.floor(t).astype(np.int64) - (STENCIL // 2 - 1)
        d = (t - base)[:, None] - _J  # t - node, nodes base .. base + q - 1
        pre = np.ones_like(d)
        np.cumprod(d[:, :-1], axis=1, out=pre[:, 1:])
        suf = np.ones_like(d)
        suf[:, :-1] = np.cumprod(d[:, :0:-1], axis=1)[:, ::-1]
        basis = _W * pre * suf  # l_j(t) = w_j prod_{i<j}(t - i) prod_{i>j}(t - i)
        idx = (base[:, None] + _J) % big
        out[:, s : s + BLOCK] = np.einsum("nq,rnq->rn", basis, fine[:, idx])
    return out
