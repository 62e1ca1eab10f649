"""Occupancy-grid import: round trips (rasterise a known workspace, write YAML + PGM, import,
compare within one cell), conservativeness (the imported free space lies in the free cells),
the speck rule, the map frame (origin and yaw), and clear errors for bad maps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from PIL import Image

from confnav.cli.app import main
from confnav.geometry import Workspace
from confnav.maps.occupancy import MapError, import_map, rasterize, workspace_from_grid

RES = 0.05
# axis-aligned, vertices on cell edges: the raster is exact, so the import must be within a cell
ROOM = Workspace(
    [(0, 0), (4, 0), (4, 3), (2.5, 3), (2.5, 2.2), (1.5, 2.2), (1.5, 3), (0, 3)],
    [
        [(0.5, 0.5), (1.5, 0.5), (1.5, 1.2), (0.5, 1.2)],
        [(2.8, 0.8), (3.3, 0.8), (3.3, 1.8), (2.8, 1.8)],
    ],
)
# slanted edges and a sharp tip
SLANT = Workspace(
    [(0, 0), (4, 0), (4, 3), (0, 3)],
    [[(0.6, 0.3), (1.9, 0.5), (1.0, 1.9)], [(2.6, 1.2), (3.4, 1.0), (3.2, 2.5)]],
)


def write_map(
    tmp: Path,
    free: np.ndarray,
    origin: tuple[float, float, float] = (-0.2, -0.2, 0.0),
    name: str = "m",
    **keys: object,
) -> Path:
    img = np.where(free, 254, 0).astype(np.uint8)
    Image.fromarray(img, mode="L").save(tmp / f"{name}.pgm")
    doc = {
        "image": f"{name}.pgm",
        "resolution": RES,
        "origin": list(origin),
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        **keys,
    }
    text = "".join(f"{k}: {v}\n" for k, v in doc.items())
    (tmp / f"{name}.yaml").write_text(text)
    return tmp / f"{name}.yaml"


def raster(ws: Workspace) -> np.ndarray:
    x0, y0, x1, y1 = ws.bounds
    shape = (round((y1 - y0 + 0.4) / RES), round((x1 - x0 + 0.4) / RES))
    return rasterize(ws, RES, (x0 - 0.2, y0 - 0.2), shape)


def hausdorff(a: Workspace, b: Workspace) -> float:
    return float(shapely.hausdorff_distance(a.polygon.boundary, b.polygon.boundary, densify=0.02))


def test_round_trip_axis_aligned(tmp_path: Path) -> None:
    res = import_map(write_map(tmp_path, raster(ROOM)))
    ws = res.workspace
    assert ws.n_obstacles == 2
    assert hausdorff(ws, ROOM) <= RES  # within one cell
    assert res.report.hausdorff_cells <= 1.0
    # conservative: the imported free space lies inside the original one
    assert ROOM.polygon.buffer(1e-9).contains(ws.polygon)
    # and loses little: area within one cell's width times the perimeter
    assert ROOM.polygon.area - ws.polygon.area <= RES * ROOM.polygon.length


def test_round_trip_slanted(tmp_path: Path) -> None:
    free = raster(SLANT)
    res = import_map(write_map(tmp_path, free))
    ws = res.workspace
    assert ws.n_obstacles == 2
    assert res.report.hausdorff_cells <= 1.0
    # the raster itself is within half a cell diagonal of the polygons; the import within a
    # cell of the raster
    assert hausdorff(ws, SLANT) <= RES * (1 + math.sqrt(0.5))
    # conservative w.r.t. the free cells: the imported free space lies in their union
    cells = [
        shapely.box(
            -0.2 + j * RES,
            -0.2 + (free.shape[0] - 1 - i) * RES,
            -0.2 + (j + 1) * RES,
            -0.2 + (free.shape[0] - i) * RES,
        )
        for i, j in zip(*np.nonzero(free), strict=True)
    ]
    assert shapely.union_all(cells).buffer(1e-9).contains(ws.polygon)


def test_origin_and_yaw(tmp_path: Path) -> None:
    free = raster(ROOM)
    a = workspace_from_grid(free, RES, (-0.2, -0.2, 0.0)).workspace
    b = workspace_from_grid(free, RES, (1.0, 2.0, math.pi / 2)).workspace
    # b is a turned by 90 degrees about its origin (-0.2, -0.2) -> moved to (1, 2)
    moved = Workspace(
        1 + 2j + 1j * (a.outer + 0.2 + 0.2j), [1 + 2j + 1j * (o + 0.2 + 0.2j) for o in a.obstacles]
    )
    assert hausdorff(b, moved) < 1e-9


def test_speck_rule(tmp_path: Path) -> None:
    free = raster(ROOM)
    h = free.shape[0]

    # a speck touching the left wall (merged into it) and a free-standing one (kept)
    def cell(x: float, y: float) -> tuple[int, int]:  # origin (-0.2, -0.2)
        return h - 1 - int((y + 0.2) / RES), int((x + 0.2) / RES)

    free[cell(0.01, 1.8)] = False  # first free cell next to the left wall (x = 0)
    free[cell(3.6, 2.0)] = False
    res = import_map(write_map(tmp_path, free))
    assert res.workspace.n_obstacles == 3  # two rectangles and the free-standing speck
    assert res.report.dropped_specks == 0
    # the kept one is said: grown by a robot it may cut rooms off (the wall-merged one is wall)
    assert [w for w in res.report.warnings if "one-cell" in w] == [
        next(w for w in res.report.warnings if w.startswith("kept 1 one-cell obstacle(s)"))
    ]
    dropped = import_map(write_map(tmp_path, free), min_obstacle_cells=2)
    assert not any("one-cell" in w for w in dropped.report.warnings)
    assert dropped.workspace.n_obstacles == 2 and dropped.report.dropped_specks == 1
    assert any("non-conservative" in w for w in dropped.report.warnings)


def test_keep_component(tmp_path: Path) -> None:
    free = raster(ROOM)
    free[:, int(3.8 / RES)] = False  # a wall cutting off a strip on the right
    path = write_map(tmp_path, free)
    big = import_map(path).workspace
    small = import_map(path, keep=3.9 + 1.5j).workspace
    assert big.polygon.area > 5 * small.polygon.area
    assert small.contains(3.9 + 1.5j) and not big.contains(3.9 + 1.5j)
    with pytest.raises(MapError, match="occupied or unknown"):
        import_map(path, keep=1.0 + 0.8j)  # inside the rectangle


def test_robot_radius(tmp_path: Path) -> None:
    res = import_map(write_map(tmp_path, raster(ROOM)), robot_radius=0.1)
    plain = import_map(write_map(tmp_path, raster(ROOM))).workspace
    assert shapely.distance(res.workspace.polygon.boundary, plain.polygon.boundary) >= 0.1 - 1e-9


def test_bad_maps(tmp_path: Path) -> None:
    free = raster(ROOM)
    path = write_map(tmp_path, free)
    (tmp_path / "m.pgm").rename(tmp_path / "gone.pgm")
    with pytest.raises(MapError, match="does not exist"):
        import_map(path)
    with pytest.raises(MapError, match="free_thresh < occupied_thresh"):
        import_map(write_map(tmp_path, free, occupied_thresh=0.1, free_thresh=0.5))
    with pytest.raises(MapError, match="no free cell"):
        import_map(write_map(tmp_path, np.zeros_like(free)))
    open_map = free.copy()
    open_map[:, :5] = True  # free space runs into the image border
    with pytest.raises(MapError, match="touches the image border"):
        import_map(write_map(tmp_path, open_map))
    with pytest.raises(MapError, match="missing key 'resolution'"):
        (tmp_path / "x.yaml").write_text("image: m.pgm\norigin: [0, 0, 0]\n")
        import_map(tmp_path / "x.yaml")
    with pytest.raises(MapError, match="resolution must be positive"):
        import_map(write_map(tmp_path, free, resolution=-1))
    (tmp_path / "junk.pgm").write_bytes(b"not an image")
    (tmp_path / "j.yaml").write_text("image: junk.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapError, match="cannot read map image"):
        import_map(tmp_path / "j.yaml")


def test_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_map(tmp_path, raster(ROOM))
    out = tmp_path / "ws.json"
    assert main(["import-map", str(path), "-o", str(out), "--plot", str(tmp_path / "p.png")]) == 0
    assert Workspace.load(out).n_obstacles == 2
    assert (tmp_path / "p.png").stat().st_size > 1000
    assert "Hausdorff error" in capsys.readouterr().out
    assert main(["import-map", str(tmp_path / "nope.yaml"), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cannot read map file" in err
