"""Real SLAM maps (ROS map_server occupancy grids from nav2 and TurtleBot3, Apache-2.0,
tests/data/slam/NOTICE) through ``confnav import-map``'s code and a TurtleBot-sized footprint
(issue 23, "Real SLAM maps"; bench/bench_slam.py drives robots on them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from confnav.maps.footprint import inflate
from confnav.maps.occupancy import import_map, load_occupancy, read_map_yaml

DATA = Path(__file__).resolve().parent / "data" / "slam"
#: every map with whether its kept free space runs into the image border
MAPS = {"tb3_world": False, "tb3_sandbox": False, "empty_room": True, "depot": True}
#: radius + unicycle look-ahead of a TurtleBot-sized body (README: --robot-radius 0.22
#: --unicycle 0.1)
FOOTPRINT = 0.32


@pytest.mark.parametrize("name", sorted(MAPS))
def test_a_real_map_imports_conservatively(name: str) -> None:
    """No part of a cell that is not free (occupied or unknown) lies in the imported free
    space: the centre and four points 0.45 cell from it of every such cell are outside it
    (the simplification only removes free space, obstacles never shrink)."""
    yaml = DATA / f"{name}.yaml"
    res = import_map(yaml)
    meta = read_map_yaml(yaml)
    free = load_occupancy(meta)
    h = free.shape[0]
    ii, jj = np.nonzero(~free)
    r = meta.resolution
    centre = complex(meta.origin[0], meta.origin[1]) + r * ((jj + 0.5) + 1j * (h - ii - 0.5))
    for d in (0, 0.45 + 0.45j, 0.45 - 0.45j, -0.45 + 0.45j, -0.45 - 0.45j):
        inside = res.workspace.contains(centre + r * d)
        assert not inside.any(), f"{name}: a non-free cell at {centre[inside][0]} is free"
    # and the free space kept is the bulk of the map's free cells
    assert res.report.kept_cells >= 0.7 * res.report.free_cells
    border = any("image border" in m for m in res.report.warnings)
    assert border == MAPS[name]


@pytest.mark.parametrize("name", sorted(MAPS))
def test_a_turtlebot_footprint_shrinks_every_real_map_to_one_drivable_space(name: str) -> None:
    """The free space shrunk by 0.32 m is a workspace whose every point is at least 0.32 m
    (less the polygonisation bound of the joins, 1 %) from every imported wall and obstacle."""
    ws = import_map(DATA / f"{name}.yaml").workspace
    shrunk = inflate(ws, FOOTPRINT)
    d = shrunk.to_dict()
    pts = np.concatenate([np.asarray(p, dtype=float) for p in [d["outer"], *d["obstacles"]]])
    z = pts[:, 0] + 1j * pts[:, 1]
    assert np.min(ws.clearance(z)) >= 0.99 * FOOTPRINT
    assert shrunk.polygon.area > 0.2 * ws.polygon.area
