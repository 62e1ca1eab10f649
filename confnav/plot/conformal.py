"""Pictures of a solved map: the workspace and its circle domain side by side.

A polar grid of the circle domain (circles |w| = rho and rays arg w = theta) and its preimage
in the workspace show at a glance that the map is conformal (the grid stays orthogonal) and
that every boundary goes to its circle.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from confnav.conformal.cmap import ConformalMap
from confnav.plot.style import OBSTACLE_FILL, label_circles, label_polygons, save
from confnav.types import CArray as ComplexArray


def _closed(z: ComplexArray) -> ComplexArray:
    return np.concatenate([z, z[:1]])


def draw_workspace(ax: Axes, m: ConformalMap) -> None:
    """Outer polygon and filled obstacles."""
    ws = m.workspace
    o = _closed(ws.outer)
    ax.plot(o.real, o.imag, "k-", lw=1.5)
    for p in ws.obstacles:
        q = _closed(p)
        ax.fill(q.real, q.imag, color=OBSTACLE_FILL, zorder=3)
    label_polygons(ax, ws.obstacles)
    ax.plot(ws.anchor.real, ws.anchor.imag, "r+", ms=12, mew=2, zorder=5, ls="none",
            label="anchor a (T(a) = 0, the centre of the circle domain)")  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def draw_circle_domain(ax: Axes, m: ConformalMap) -> None:
    """Unit circle and the obstacle disks."""
    t = np.linspace(0, 2 * np.pi, 400)
    ax.plot(np.cos(t), np.sin(t), "k-", lw=1.5)
    for c, r in zip(m.centers, m.radii, strict=True):
        ax.fill(c.real + r * np.cos(t), c.imag + r * np.sin(t), color=OBSTACLE_FILL, zorder=3)
    label_circles(ax, m.centers, m.radii)
    ax.plot(0, 0, "r+", ms=12, mew=2, zorder=5, ls="none")
    ax.set_aspect("equal")
    ax.set_xlabel("Re w (dimensionless)")
    ax.set_ylabel("Im w")


def polar_grid(
    m: ConformalMap, n_rho: int = 12, n_theta: int = 24, samples: int = 600
) -> list[ComplexArray]:
    """Curves of a polar grid in the circle domain, NaN where they cross an obstacle disk."""
    curves = []
    t = np.linspace(0, 2 * np.pi, samples)
    for rho in np.linspace(0, 1, n_rho + 1)[1:-1]:
        curves.append(rho * np.exp(1j * t))
    s = np.linspace(0, 1, samples)
    for th in np.linspace(0, 2 * np.pi, n_theta, endpoint=False):
        curves.append(s * np.exp(1j * th))
    out = []
    for w in curves:
        w = w.astype(np.complex128)
        w[~m.in_circle_domain(w)] = np.nan
        out.append(w)
    return out


def map_figure(m: ConformalMap, title: str = "") -> Figure:
    """Workspace with the preimage of a polar grid | circle domain with the grid."""
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 6), layout="constrained")
    grid = polar_grid(m)
    for w in grid:
        z = m.inverse(w)
        ax0.plot(z.real, z.imag, "-", color="tab:blue", lw=0.6)
        ax1.plot(w.real, w.imag, "-", color="tab:blue", lw=0.6)
    draw_workspace(ax0, m)
    draw_circle_domain(ax1, m)
    # one-line panel titles: the figure's title sits above them in the layout (a two-line
    # panel title grew into the suptitle's space)
    ax0.set_title("workspace: preimage of the polar grid", fontsize=11)
    ax1.set_title("circle domain T(workspace): polar grid", fontsize=11)
    handles, labels = ax0.get_legend_handles_labels()
    handles.append(Line2D([], [], ls="none"))
    labels.append("obstacle j maps to circle j")
    fig.legend(handles, labels, loc="outside lower center", ncols=2, fontsize=9, frameon=False)
    d = m.diagnostics
    fig.suptitle(
        (title + ": " if title else "")
        + f"estimated error {d.error_estimate:.1e} (tol {d.tol:.0e}), {sum(d.nodes)} nodes, "
        f"{d.sweeps} sweeps, {d.wall_time:.2f} s",
        fontsize=12,
    )
    return fig


def save_map_figure(m: ConformalMap, path: str | Path, title: str = "") -> None:
    save(map_figure(m, title), path)


__all__ = ["draw_circle_domain", "draw_workspace", "map_figure", "polar_grid", "save_map_figure"]
