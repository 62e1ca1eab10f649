"""JSON output of the CLI: strict JSON (RFC 8259 has no inf or NaN).

A value that is not a finite number (a clearance never measured, a path ratio with no path) is
written as ``null``: the one sentinel, documented with each output. Writers build their
documents with :func:`finite` where such a value can arise; :func:`write_json` replaces any that
remains (numpy scalars and arrays included) and writes with ``allow_nan=False``, so a JSON
writer never fails on one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["finite", "json_safe", "write_json"]


def finite(x: Any) -> float | None:
    """``float(x)``, or None where it is inf or NaN (or None)."""
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def json_safe(obj: Any) -> Any:
    """``obj`` with numpy scalars/arrays as Python values and non-finite floats as None."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def write_json(path: Path, doc: Any, *, indent: int = 1) -> None:
    """Write ``doc`` as strict JSON (non-finite numbers as null)."""
    path.write_text(json.dumps(json_safe(doc), indent=indent, allow_nan=False))
