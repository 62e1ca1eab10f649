"""Figure of an atlas run: walls, the cells of the decomposition, robot paths and the goal
(matplotlib, Agg backend; an I/O edge)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from confnav.atlas import Atlas, AtlasRun
from confnav.geometry import Workspace
from confnav.navigation.sim import STATUS_NAMES
from confnav.plot.navigation import _trajectories, draw_walls
from confnav.plot.style import save

__all__ = ["atlas_figure", "save_atlas_figure"]


def atlas_figure(
    atlas: Atlas,
    run: AtlasRun,
    goal: complex,
    *,
    walls: Workspace | None = None,
    shrink: float = 0.0,
    title: str = "",
) -> Figure:
    """One panel in metres: the walls and obstacles (``walls``, the real workspace, when the
    atlas is of the free space shrunk by ``shrink`` for a robot's body, drawn dashed then),
    every cell's outline, each robot's path with its outcome, and the goal."""
    if run.paths is None:
        raise ValueError("the run has no paths: run it with record_paths=True")
    ws = atlas.workspace
    x0, y0, x1, y1 = (walls or ws).bounds
    aspect = (y1 - y0) / max(x1 - x0, 1e-12)
    fig, ax = plt.subplots(figsize=(10, float(np.clip(10 * aspect, 4, 14))), layout="constrained")
    draw_walls(ax, ws, walls, shrink)
    label = f"cells ({len(atlas.decomposition.cells)})"
    for c in atlas.decomposition.cells:
        xs, ys = c.polygon.exterior.xy
        ax.plot(xs, ys, "-", color="tab:gray", lw=0.5, alpha=0.6, label=label)
        label = "_"
    outcomes = [STATUS_NAMES[int(s)] for s in run.status]
    _trajectories(ax, run.paths, outcomes)
    ax.plot(goal.real, goal.imag, "k*", ms=12, mfc="gold", ls="none", label="goal")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    arrived = int(run.success.sum())
    ax.set_title(
        title
        or f"atlas: {len(atlas.charts)} charts; {arrived}/{run.success.size} arrived, "
        f"{int(run.collided.sum())} collisions"
    )
    # beside the map, never on it (a legend "best" placed still covers walls and starts)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0, fontsize=8)
    return fig


def save_atlas_figure(
    atlas: Atlas,
    run: AtlasRun,
    goal: complex,
    path: str | Path,
    *,
    walls: Workspace | None = None,
    shrink: float = 0.0,
    dpi: int = 120,
) -> Path:
    """Write :func:`atlas_figure` to ``path`` (PNG/PDF/SVG by extension)."""
    return save(atlas_figure(atlas, run, goal, walls=walls, shrink=shrink), path, dpi=dpi)
