"""The figure of a recorded run (``confnav inspect --plot``): every workspace with the recorded
trajectories, starts, goals, closest approaches and collisions and, when the map is recorded,
the circle domain with the images ``T(z)`` of the trajectories."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from confnav.plot.style import save
from confnav.recording.inspect import InspectReport
from confnav.recording.scene import robot_color
from confnav.schemas import TransformSolution

logger = logging.getLogger(__name__)

MARKERS: dict[str, dict[str, Any]] = {
    "start": {"marker": "o", "color": "0.4", "ms": 6},
    "goal": {"marker": "*", "color": "green", "ms": 12, "mec": "black"},
    "closest approach to an obstacle": {"marker": "x", "color": "0.4", "ms": 8, "mew": 2},
    "collision": {"marker": "X", "color": "red", "ms": 10, "mec": "black"},
}
"""Legend entries of the markers (drawn in each robot's colour on the trajectories)."""


def _decimate(points: list[tuple[float, float]], n: int) -> list[tuple[float, float]]:
    if len(points) <= n:
        return points
    step = len(points) / n
    return [points[int(i * step)] for i in range(n)] + [points[-1]]


def _circle_domain_images(
    tr: TransformSolution, paths: dict[str, list[tuple[float, float]]]
) -> tuple[Any, dict[str, list[complex]]] | None:
    """(map, robot -> images T(z) of its decimated trajectory), None if the map won't load."""
    import numpy as np

    from confnav.services.navigation import load_map

    try:
        cmap = load_map(tr)
    except Exception as exc:  # e.g. a stand-in map in tests, an old format
        logger.info("circle domain not drawn: cannot load the map: %s", exc)
        return None
    out = {}
    for rid, pts in paths.items():
        z = np.array([complex(x, y) for x, y in _decimate(pts, 1000)], dtype=complex)
        w = np.asarray(cmap.T(z), dtype=complex).reshape(-1) if z.size else z
        out[rid] = [complex(v) for v in w if np.isfinite(v)]
    return cmap, out


def plot_recording(report: InspectReport, out: str | os.PathLike[str]) -> Path:
    """Write :func:`recording_figure` of ``report`` to ``out`` (PNG)."""
    return save(recording_figure(report), out, dpi=110)


def recording_figure(report: InspectReport) -> Figure:
    """Every workspace with the recorded trajectories, starts, goals and the closest approach
    to an obstacle and, when its map is recorded, the circle domain with the images of the
    trajectories (one row per workspace)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    from matplotlib.patches import Polygon as MplPolygon

    ws_ids = sorted(report.workspaces) or [""]
    mapped = {}
    for ws_id in ws_ids:
        tr = report.transforms.get(ws_id)
        if tr is not None:
            paths = {
                rid: r.trajectory
                for rid, r in report.robots.items()
                if r.ws_id in (ws_id, None) and r.trajectory
            }
            found = _circle_domain_images(tr, paths)
            if found is not None:
                mapped[ws_id] = found
    cols = 2 if mapped else 1
    fig, axes = plt.subplots(
        len(ws_ids), cols, figsize=(6.5 * cols, 6.5 * len(ws_ids)), squeeze=False,
        layout="constrained",
    )  # fmt: skip
    colors = {rid: robot_color(i) for i, rid in enumerate(sorted(report.robots))}
    for row, ws_id in enumerate(ws_ids):
        ax = axes[row][0]
        wd = report.workspaces.get(ws_id)
        if wd is not None:
            ax.add_patch(MplPolygon(wd.outer, closed=True, fill=False, lw=2, ec="black"))
            for ob in wd.obstacles:
                ax.add_patch(MplPolygon(ob, closed=True, fc="#d9a89b", ec="#a0301a", lw=1.5))
        for rid, r in sorted(report.robots.items()):
            if wd is not None and r.ws_id not in (ws_id, None):
                continue
            color = colors[rid]
            if r.trajectory:
                xs, ys = zip(*r.trajectory, strict=True)
                ax.plot(xs, ys, "-", color=color, lw=1.6, label=f"{rid}")
                ax.plot(xs[0], ys[0], "o", color=color, ms=6)
            if r.goal is not None:
                ax.plot(*r.goal, "*", color="green", ms=14, mec="black")
            if r.min_clearance_at is not None:
                ax.plot(*r.min_clearance_at, "x", color=color, ms=9, mew=2)
            if r.collision_at is not None:
                ax.plot(*r.collision_at, "X", color="red", ms=12, mec="black")
        for label, style in MARKERS.items():  # what the markers mean, once each
            ax.plot([], [], ls="none", label=label, **style)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.autoscale_view()
        title = f"workspace {ws_id}" if ws_id else "recorded trajectories"
        ax.set_title(f"{report.path.name}: {title}", fontsize=10)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0)
        if cols == 2:
            cax = axes[row][1]
            if ws_id in mapped:
                cmap, images = mapped[ws_id]
                cax.add_patch(Circle((0, 0), 1.0, fill=False, lw=2, ec="black"))
                for c, rad in zip(cmap.centers, cmap.radii, strict=True):
                    cax.add_patch(Circle((c.real, c.imag), rad, fc="#d9a89b", ec="#a0301a", lw=1.5))
                for rid, w in sorted(images.items()):
                    if w:
                        cax.plot([v.real for v in w], [v.imag for v in w], "-", color=colors[rid])
                        cax.plot(w[0].real, w[0].imag, "o", color=colors[rid], ms=6)
                cax.set_xlim(-1.05, 1.05)
                cax.set_ylim(-1.05, 1.05)
                cax.set_title(f"circle domain of {ws_id}: images T(z)", fontsize=10)
                cax.set_xlabel("Re w (dimensionless)")
                cax.set_ylabel("Im w")
            else:
                cax.set_axis_off()
            cax.set_aspect("equal")
    return fig


__all__ = ["plot_recording", "recording_figure"]
