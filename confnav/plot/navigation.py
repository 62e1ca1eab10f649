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
from matplotlib.figure import Figure
from numpy.typing import NDArray

from confnav.navigation.control import Controller
from confnav.plot.style import save
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


def plot_workspace(
    ax: Axes,
    ctl: Controller,
    paths: Sequence[CArray] = (),
    n_grid: int = 260,
    outcomes: Sequence[str] = (),
) -> None:
    """Level sets of V = phi(T(x)), the obstacles, the goal and the trajectories (axes in
    metres; with ``outcomes`` a marker per path end and a legend)."""
    ws = getattr(ctl.cmap, "workspace", None)
    if ws is None:
        raise ValueError("the map has no workspace to plot")
    x0, y0, x1, y1 = ws.bounds
    x = np.linspace(x0, x1, n_grid)
    y = np.linspace(y0, y1, n_grid)
    z = x[None, :] + 1j * y[:, None]
    v = np.full(z.shape, np.nan)
    inside = ws.contains(z)
    v[inside] = ctl.lyapunov(z[inside])
    ax.contour(x, y, v, levels=_levels(v), linewidths=0.6, cmap="viridis")
    for j, p in enumerate(ws.boundaries):
        q = np.r_[p, p[:1]]
        if j == 0:
            ax.plot(q.real, q.imag, "k-", lw=1.2)
        else:
            ax.fill(q.real, q.imag, color="0.55", ec="k", lw=1.0)
    _trajectories(ax, paths, outcomes)
    ax.plot(ctl.goal.real, ctl.goal.imag, "k*", ms=12, mfc="gold", ls="none", label="goal")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"workspace: level sets of {ctl.navfn.name} phi(T(x))")
    ax.legend(loc="best", fontsize=8, framealpha=0.8)


def plot_circle_domain(
    ax: Axes, ctl: Controller, paths: Sequence[CArray] = (), n_grid: int = 260
) -> None:
    """Level sets of phi in the circle domain, the circles and the mapped trajectories."""
    t = np.linspace(-1, 1, n_grid)
    w = t[None, :] + 1j * t[:, None]
    v = np.full(w.shape, np.nan)
    inside = ctl.domain.contains(w)
    v[inside] = ctl.navfn.value(w[inside])
    ax.contour(t, t, v, levels=_levels(v), linewidths=0.6, cmap="viridis")
    e = np.exp(2j * np.pi * np.linspace(0, 1, 361))
    ax.plot(e.real, e.imag, "k-", lw=1.2)
    for c, r in zip(ctl.domain.centers, ctl.domain.radii, strict=True):
        q = c + r * e
        ax.fill(q.real, q.imag, color="0.55", ec="k", lw=1.0)
    mapped = [np.asarray(ctl.cmap.T_and_dT(p)[0]) for p in paths]
    _trajectories(ax, mapped)
    ax.plot(ctl.goal_w.real, ctl.goal_w.imag, "k*", ms=12, mfc="gold")
    ax.set_aspect("equal")
    ax.set_xlabel("Re w (dimensionless)")
    ax.set_ylabel("Im w")
    ax.set_title(f"circle domain: level sets of {ctl.navfn.name} phi(w)")


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
    ctl: Controller, paths: Sequence[CArray], title: str = "", outcomes: Sequence[str] = ()
) -> Figure:
    """Two panels: workspace (seed Fig. 2) and circle domain (seed Fig. 3)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 6), constrained_layout=True)
    plot_workspace(a, ctl, paths, outcomes=outcomes)
    plot_circle_domain(b, ctl, paths)
    if title:
        fig.suptitle(title)
    return fig


def save_navigation_figure(
    ctl: Controller, paths: Sequence[CArray], path: str | Path, title: str = "", **kw: Any
) -> Path:
    """Write :func:`navigation_figure` to ``path`` (PNG/PDF/SVG by extension)."""
    fig = navigation_figure(ctl, paths, title, outcomes=kw.get("outcomes", ()))
    return save(fig, path, dpi=kw.get("dpi", 120))
