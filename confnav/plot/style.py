"""What every confnav figure shares: obstacle labels that stay readable, the anchor / goal
markers, and saving without clipped labels."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import shapely
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from confnav.types import CArray

OBSTACLE_FILL = "0.55"
SMALL_CIRCLE = 0.06  # circle-domain radius under which a label goes outside its disk
LABEL_GAP = 0.07  # minimum distance between two such labels (circle-domain units)


def label_point(polygon: CArray) -> complex:
    """A point inside ``polygon`` to write its label on (the vertex mean of an L-shaped or
    concave obstacle can lie outside it, where a white label is invisible)."""
    p = shapely.Polygon(np.column_stack([polygon.real, polygon.imag])).representative_point()
    return complex(p.x, p.y)


def label_polygons(ax: Axes, polygons: Sequence[CArray]) -> None:
    """Number each obstacle polygon ``0, 1, ...`` at a point inside it; a speck (a quarter of
    the median obstacle size or less) gets a black number beside it instead."""
    pts = [np.asarray(p, dtype=np.complex128) for p in polygons]
    sizes = [float(np.ptp(p.real) + np.ptp(p.imag)) for p in pts]
    small = 0.25 * float(np.median(sizes)) if sizes else 0.0
    for j, (p, size) in enumerate(zip(pts, sizes, strict=True)):
        c = label_point(p)
        if size > small:
            ax.annotate(str(j), (c.real, c.imag), ha="center", va="center", color="w",
                        zorder=6, fontsize=8, fontweight="bold")  # fmt: skip
        else:
            ax.annotate(str(j), (c.real, c.imag), xytext=(6, 6), textcoords="offset points",
                        fontsize=8, fontweight="bold", zorder=6)  # fmt: skip


def label_circles(ax: Axes, centers: Iterable[complex], radii: Iterable[float]) -> None:
    """Number each obstacle disk; a small disk gets its number outside, towards the centre of
    the unit disk, with a leader line, fanned out where disks crowd, so it stays readable."""
    placed: list[complex] = []
    for j, (c, r) in enumerate(zip(centers, radii, strict=True)):
        c = complex(c)
        if r >= SMALL_CIRCLE:
            ax.annotate(str(j), (c.real, c.imag), ha="center", va="center", color="w",
                        zorder=6, fontsize=8, fontweight="bold")  # fmt: skip
            continue
        inward = -c / abs(c) if abs(c) > 1e-9 else 1j
        at = c + inward * (r + 0.12)
        while any(abs(at - q) < LABEL_GAP for q in placed):  # crowded disks: fan out
            at += 1j * inward * LABEL_GAP
        placed.append(at)
        ax.annotate(str(j), (c.real, c.imag), xytext=(at.real, at.imag), ha="center",
                    va="center", fontsize=8, fontweight="bold", zorder=6,
                    arrowprops={"arrowstyle": "-", "lw": 0.6, "color": "k"})  # fmt: skip


def save(fig: Figure, path: str | os.PathLike[str], dpi: int = 120) -> Path:
    """Write ``fig`` (format by extension) with nothing clipped (tight bounding box)."""
    import matplotlib.pyplot as plt

    out = Path(path)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


__all__ = ["label_circles", "label_point", "label_polygons", "save"]
