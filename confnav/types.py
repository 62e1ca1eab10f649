"""numpy array aliases shared by the numerics (one definition, imported everywhere).

Points of the plane are complex numbers ``z = x + iy`` throughout confnav, so a batch of points
is a :data:`CArray`."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import ConfnavError, fmt_point

CArray = NDArray[np.complex128]
"""Complex points or values."""
FArray = NDArray[np.float64]
IArray = NDArray[np.int64]
BArray = NDArray[np.bool_]


def as_point(p: complex | ArrayLike, what: str, error: type[ConfnavError]) -> complex:
    """A finite complex point from a number or an ``(x, y)`` pair; raise ``error`` (naming
    ``what``) for anything else."""
    a = np.asarray(p)
    try:
        if a.shape == (2,) and not np.iscomplexobj(a):
            z = complex(float(a[0]), float(a[1]))
        elif a.shape == () and a.dtype != np.bool_:
            z = complex(a.item())
        else:
            raise TypeError
    except (TypeError, ValueError):
        raise error(f"{what} must be a complex number or an (x, y) pair") from None
    if not np.isfinite(z):
        raise error(f"{what} must be finite: {fmt_point(z)} is not finite")
    return z


__all__ = ["BArray", "CArray", "FArray", "IArray", "as_point"]
