"""``confnav import-map MAP.yaml [--robot-radius R] [--keep X,Y] -o WS.json [--plot OUT.png]``.

Reads a ROS map_server map (YAML + PGM/PNG), keeps one free component, traces and simplifies it
conservatively (see :mod:`confnav.maps.occupancy`) and writes a validated workspace in metres in the
map frame that ``confnav solve`` and ``confnav simulate`` accept. With ``--robot-radius`` the
workspace is the free space shrunk by the radius (for the robot's centre).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from confnav.argtypes import output_path
from confnav.cli.simulate import _point


def register(sub: Any) -> None:
    p = sub.add_parser(
        "import-map",
        help="import a ROS occupancy-grid map (YAML + PGM/PNG) as a workspace",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("map", type=Path, help="map_server YAML file")
    p.add_argument(
        "-o", "--output", type=output_path, required=True, help="workspace JSON to write"
    )
    p.add_argument(
        "--robot-radius",
        type=float,
        default=0.0,
        metavar="R",
        help="shrink the free space by this radius (m); default 0: a point robot",
    )
    p.add_argument(
        "--keep",
        type=_point,
        metavar="X,Y",
        help="keep the free component holding this point (default: the largest)",
    )
    p.add_argument(
        "--min-obstacle-cells",
        type=int,
        default=0,
        metavar="N",
        help="drop obstacles of at most N cells (non-conservative; default 0: keep all)",
    )
    p.add_argument(
        "--merge-cells",
        type=int,
        default=0,
        metavar="N",
        help="merge obstacles closer than 2N cells (closing; default: the robot radius in cells)",
    )
    p.add_argument(
        "--max-error",
        type=float,
        default=1.0,
        metavar="CELLS",
        help="Hausdorff bound of the simplification in cells (default 1; larger: fewer vertices)",
    )
    p.add_argument(
        "--plot", type=output_path, help="write a picture of the map and workspace (PNG)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from confnav.maps.occupancy import import_map

    res = import_map(
        args.map,
        robot_radius=args.robot_radius,
        keep=args.keep,
        min_obstacle_cells=args.min_obstacle_cells,
        merge_cells=args.merge_cells,
        max_error=args.max_error,
    )
    args.output.write_text(res.workspace.to_json(indent=1) + "\n")
    for line in res.report.lines():  # warnings (e.g. the border taken as a wall) on stderr
        print(line, file=sys.stderr if line.startswith("warning:") else sys.stdout)
    print(f"workspace written to {args.output}")
    if args.plot:
        _plot(args.map, res, args.plot)
        print(f"plot written to {args.plot}")
    return 0


def _plot(map_path: Path, res: Any, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from confnav.maps.occupancy import load_occupancy, read_map_yaml
    from confnav.plot.style import label_polygons, save

    meta = read_map_yaml(map_path)
    free = load_occupancy(meta)
    h, w = free.shape
    x0, y0 = meta.origin[0], meta.origin[1]
    fig, ax = plt.subplots(figsize=(8, 8 * h / max(w, 1)))
    ax.imshow(
        np.where(free, 1.0, 0.35),
        cmap="gray",
        vmin=0,
        vmax=1,
        origin="upper",
        extent=(x0, x0 + w * meta.resolution, y0, y0 + h * meta.resolution),
    )
    ws = res.workspace
    for k, b in enumerate(ws.boundaries):
        z = np.concatenate([b, b[:1]])
        ax.plot(z.real, z.imag, "r-" if k == 0 else "b-", lw=1.0,
                label=("outer boundary" if k == 0 else "obstacle") if k < 2 else None)  # fmt: skip
    label_polygons(ax, ws.obstacles)
    ax.plot([ws.anchor.real], [ws.anchor.imag], "g+", ms=12, mew=2, ls="none", label="anchor")
    ax.plot([], [], "s", color="0.35", ls="none", label="occupied / unknown cells")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m]")
    ax.set_title(
        f"{map_path.name}: {ws.n_obstacles} obstacles, one-sided simplification error "
        f"(Hausdorff) {res.report.hausdorff_cells:.2f} cell = "
        f"{res.report.hausdorff_cells * meta.resolution:.3g} m",
        fontsize=10,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    save(fig, out)
