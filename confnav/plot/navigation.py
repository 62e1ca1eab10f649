"""Figures like the seed's Fig. 2 and Fig. 3: level sets of phi(T(x)) in the workspace and of
phi in the circle domain, with robot trajectories (matplotlib, Agg backend; an I/O edge)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.contour import ContourSet
from matplotlib.figure import Figure
from numpy.typing import NDArray

from confnav.geometry import Workspace
from confnav.navigation.control import Controller
from confnav.plot.style import SMALL_CIRCLE, label_circles, label_polygons, save
from confnav.types import CArray

__all__ = ["navigation_figure", "plot_circle_domain", "plot_workspace", "save_navigation_figure"]

_COLORS = ("tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown")


def _levels(v: NDArray[np.float64], n: int = 24) -> NDArray[np.float64]:
    """Contour levels at quantiles of the sampled values (phi_k crowds near 1)."""
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return np.linspace(0, 1, n)
    q = np.unique(np.quantile(finite, np.linspace(0.01, 0.99, n)))
    return q if q.size >= 2 else np.linspace(0, 1, n)


#: Marker of each run outcome at the end of its path (names of confnav.navigation.sim.STATUS_NAMES).
OUTCOME_MARKERS: dict[str, tuple[str, str]] = {
    "arrived": ("o", "tab:green"),
    "collided": ("X", "red"),
    "stalled": ("s", "darkorange"),
    "timeout": ("v", "purple"),
    "error": ("D", "black"),
}


def draw_walls(ax: Axes, ws: Workspace, walls: Workspace | None, shrink: float) -> None:
    """The walls and obstacles of ``walls`` (the real workspace; ``ws`` if None) and, for a
    robot with a body, the free space ``ws`` of its centre (shrunk by ``shrink``) dashed."""
    for j, p in enumerate((walls or ws).boundaries):
        q = np.r_[p, p[:1]]
        if j == 0:
            ax.plot(q.real, q.imag, "k-", lw=1.2)
        else:
            ax.fill(q.real, q.imag, color="0.55", ec="k", lw=1.0)
    if walls is not None:
        label = f"free space of the centre (walls grown by {shrink:g} m)"
        for p in ws.boundaries:
            q = np.r_[p, p[:1]]
            ax.plot(q.real, q.imag, "--", color="tab:blue", lw=0.8, label=label)
            label = "_"  # one legend entry


def plot_workspace(
    ax: Axes,
    ctl: Controller,
    paths: Sequence[CArray] = (),
    n_grid: int = 260,
    outcomes: Sequence[str] = (),
    walls: Workspace | None = None,
    shrink: float = 0.0,
    legend: bool = True,
) -> ContourSet:
    """Level sets of V = phi(T(x)), the obstacles, the goal and the trajectories (axes in
    metres; with ``outcomes`` a marker per path end and, if ``legend``, a legend); returns the
    level sets (for a colour bar: phi is 0 at the goal and 1 on the boundary).

    For a robot with a body the map is of the free space shrunk by ``shrink``: then ``walls``
    (the real workspace) are drawn as the walls and obstacles, and the shrunk free space that
    the robot's centre keeps to as a dashed outline."""
    ws = getattr(ctl.cmap, "workspace", None)
    if ws is None:
        raise ValueError("the map has no workspace to plot")
    x0, y0, x1, y1 = (walls or ws).bounds
    x = np.linspace(x0, x1, n_grid)
    y = np.linspace(y0, y1, n_grid)
    z = x[None, :] + 1j * y[:, None]
    v = np.full(z.shape, np.nan)
    inside = ws.contains(z)
    v[inside] = ctl.lyapunov(z[inside])
    levels = ax.contour(x, y, v, levels=_levels(v), linewidths=0.6, cmap="viridis", vmin=0, vmax=1)
    draw_walls(ax, ws, walls, shrink)
    label_polygons(ax, ws.obstacles)  # the obstacles of the map (circle i <-> obstacle i)
    _trajectories(ax, paths, outcomes)
    ax.plot(ctl.goal.real, ctl.goal.imag, "k*", ms=12, mfc="gold", ls="none", label="goal")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"workspace: level sets of {ctl.navfn.name} phi(T(x))")
    if legend:
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    return levels


#: Smallest magnification worth an inset (below it the main view shows the small disks).
MIN_ZOOM = 3.0


def plot_circle_domain(
    ax: Axes, ctl: Controller, paths: Sequence[CArray] = (), n_grid: int = 260
) -> None:
    """Level sets of phi in the circle domain, the circles and the mapped trajectories."""
    mapped = [np.asarray(ctl.cmap.T_and_dT(p)[0]) for p in paths]
    _draw_domain(ax, ctl, mapped, -1.0 - 1.0j, 2.0, n_grid)
    label_circles(ax, list(ctl.domain.centers), list(ctl.domain.radii))
    radii = np.asarray(ctl.domain.radii, dtype=float)
    small = np.flatnonzero(radii < SMALL_CIRCLE)
    if small.size:  # crowded disks (radii down to 1e-4): magnify them in an inset
        c = np.asarray(ctl.domain.centers)[small]
        lo = complex(c.real.min(), c.imag.min())
        hi = complex(c.real.max(), c.imag.max())
        side = max(hi.real - lo.real, hi.imag - lo.imag, 20 * float(radii[small].max()), 0.01)
        side = min(side * 1.6, 2.0)
        if 2.0 / side >= MIN_ZOOM:  # else the main view shows them well enough
            # the window inside the view [-1, 1]^2 (a zoom box never sticks out of the axes)
            mid = (lo + hi) / 2
            half = side / 2
            mid = complex(
                min(max(mid.real, -1 + half), 1 - half), min(max(mid.imag, -1 + half), 1 - half)
            )
            # the inset in the corner of the axes farthest from the window it magnifies
            x0 = 0.61 if mid.real < 0 else 0.03
            y0 = 0.61 if mid.imag < 0 else 0.03
            inset = ax.inset_axes((x0, y0, 0.36, 0.36))
            _draw_domain(inset, ctl, mapped, mid - half * (1 + 1j), side, n_grid // 2)
            inset.set_xticks([])
            inset.set_yticks([])
            inset.set_title(f"x{2 / side:.0f}", fontsize=7, pad=2)
            ax.indicate_inset_zoom(inset, edgecolor="0.3")
    ax.set_aspect("equal")
    ax.set_xlabel("Re w (dimensionless)")
    ax.set_ylabel("Im w")
    ax.set_title(f"circle domain: level sets of {ctl.navfn.name} phi(w)")


def _draw_domain(
    ax: Axes, ctl: Controller, mapped: Sequence[CArray], corner: complex, side: float, n: int
) -> None:
    """Level sets of phi, the circles, the mapped paths and the goal in the square window
    ``[corner, corner + side (1 + i)]`` of the circle domain."""
    x = corner.real + side * np.linspace(0, 1, n)
    y = corner.imag + side * np.linspace(0, 1, n)
    w = x[None, :] + 1j * y[:, None]
    v = np.full(w.shape, np.nan)
    inside = ctl.domain.contains(w)
    v[inside] = ctl.navfn.value(w[inside])
    ax.contour(x, y, v, levels=_levels(v), linewidths=0.6, cmap="viridis")
    e = np.exp(2j * np.pi * np.linspace(0, 1, 721))
    ax.plot(e.real, e.imag, "k-", lw=1.2)
    for c, r in zip(ctl.domain.centers, ctl.domain.radii, strict=True):
        q = c + r * e
        ax.fill(q.real, q.imag, color="0.55", ec="k", lw=0.8)
    _trajectories(ax, mapped)
    ax.plot(ctl.goal_w.real, ctl.goal_w.imag, "k*", ms=12, mfc="gold")
    ax.set_xlim(x[0], x[-1])
    ax.set_ylim(y[0], y[-1])
    ax.set_aspect("equal")


def _trajectories(ax: Axes, paths: Sequence[CArray], outcomes: Sequence[str] = ()) -> None:
    many = len(paths) > len(_COLORS)
    seen: set[str] = set()
    for i, p in enumerate(paths):
        col = "tab:blue" if many else _COLORS[i % len(_COLORS)]
        ax.plot(p.real, p.imag, "-", color=col, lw=0.8 if many else 1.6, alpha=0.7)
        first = i == 0
        ax.plot(p[0].real, p[0].imag, "o", color="0.3", ms=3, mfc="none",
                label="start" if first and outcomes else None)  # fmt: skip
        if i < len(outcomes):
            mk, mc = OUTCOME_MARKERS.get(outcomes[i], ("o", "k"))
            lab = outcomes[i] if outcomes[i] not in seen else None
            seen.add(outcomes[i])
            ax.plot(p[-1].real, p[-1].imag, mk, color=mc, ms=6, ls="none", label=lab)


def navigation_figure(
    ctl: Controller,
    paths: Sequence[CArray],
    title: str = "",
    outcomes: Sequence[str] = (),
    walls: Workspace | None = None,
    shrink: float = 0.0,
) -> Figure:
    """Two panels: workspace (seed Fig. 2) and circle domain (seed Fig. 3); ``walls`` and
    ``shrink`` as in :func:`plot_workspace`."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 6.2), layout="constrained")
    levels = plot_workspace(
        a, ctl, paths, outcomes=outcomes, walls=walls, shrink=shrink, legend=False
    )
    plot_circle_domain(b, ctl, paths)
    # one colour bar for both panels: the level sets are the same function, phi(T(x)) = phi(w)
    bar = fig.colorbar(
        ScalarMappable(norm=levels.norm, cmap=levels.cmap), ax=[a, b], shrink=0.85, pad=0.02
    )
    bar.set_label(f"{ctl.navfn.name} phi (0 at the goal, 1 on every boundary)")
    bar.ax.hlines(np.asarray(levels.levels), 0, 1, colors="k", lw=0.4)  # the drawn levels
    # the legend below the panels, where it hides nothing (the goal sits anywhere)
    fig.legend(
        *a.get_legend_handles_labels(), loc="outside lower center", ncols=6, fontsize=9,
        frameon=False,
    )  # fmt: skip
    if title:
        fig.suptitle(title)
    return fig


def save_navigation_figure(
    ctl: Controller, paths: Sequence[CArray], path: str | Path, title: str = "", **kw: Any
) -> Path:
    """Write :func:`navigation_figure` to ``path`` (PNG/PDF/SVG by extension)."""
    fig = navigation_figure(
        ctl,
        paths,
        title,
        outcomes=kw.get("outcomes", ()),
        walls=kw.get("walls"),
        shrink=kw.get("shrink", 0.0),
    )
    return save(fig, path, dpi=kw.get("dpi", 120))
