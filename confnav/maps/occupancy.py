"""Occupancy-grid import: ROS ``map_server`` maps (YAML + PGM/PNG) to a validated Workspace.

Pipeline (every step conservative: the free space never grows, an obstacle never shrinks):

1. **Classify** each cell as map_server does [1]_: ``p = (255 - v) / 255`` (``v / 255`` with
   ``negate: 1``; ``v / 100`` in ``raw`` mode); occupied if ``p > occupied_thresh``, free if
   ``p < free_thresh``, otherwise unknown. Unknown cells count as occupied, and so does
   everything outside the image.
2. **Merge** (the speck rule): occupied cells that touch, also diagonally, are one obstacle
   (8-connectivity), so a speck touching a wall is part of the wall. Then the occupied set is
   closed morphologically with a disk of ``rho`` cells,
   ``rho = max(merge_cells, floor(robot_radius / resolution))`` (default 0 for a point robot:
   no closing). Closing only adds occupied cells, and it merges obstacles (and walls) less than
   ``2 rho`` cells apart into one; with a robot radius the cells it fills are (up to the raster)
   those the robot's body can never cover (the opening of the free space by the body's disk is
   the set the body sweeps). Obstacles of at most ``min_obstacle_cells`` cells are then
   **dropped** only on request (default 0: none): the one non-conservative step, counted in
   the report. Free-standing specks are otherwise kept: an obstacle never shrinks.
3. **Keep** the 4-connected free component holding ``keep`` (default: the largest). Where it
   runs into the image border (maps saved from SLAM often do), the border is a wall: the map's
   extent is the robot's world (said in the report's warnings; nothing outside the image is
   known, so this is the conservative reading).
4. **Trace** its boundary with marching squares [2]_ (scikit-image ``find_contours``, level 0.5:
   free cells face-connected, occupied cells fully connected) and put back the cell corners the
   marching squares cut, so the traced rings are the exact cell-edge staircase (a free cell
   touching the rest only diagonally is occupied first, so the boundary is simple).
5. **Simplify one-sidedly** (:func:`_simplify_ring`, tolerance ``max_error`` = 1 cell), a
   cone-intersection scheme [3]_ made one-sided: every chord cuts off free space only and passes
   within the tolerance of the corners it skips, so no obstacle shrinks. The result is checked
   to lie inside the exact union of the free cells (shapely) and its Hausdorff distance to their
   boundary is measured (densified) and reported in cells; above the tolerance it is halved and
   the step repeated (at worst down to the unsimplified staircase, error 0). A conservative
   straight edge along a slanted digital line is up to the staircase's band width (1 to 1.41
   cells) from some corners, so at one cell slanted edges keep more vertices; a larger
   ``max_error`` trades accuracy for fewer vertices (and a faster solve).
6. **Write** metres in the map frame: cell ``(row i, col j)`` of an image of height ``H``
   covers ``[j, j+1] x [H-1-i, H-i]`` cells from the map origin (lower-left corner of the
   lower-left pixel), rotated by the origin's yaw. With ``robot_radius`` the result is the free
   space shrunk by it (:func:`confnav.maps.footprint.inflate`), for the robot's centre.

References
----------
.. [1] ROS ``map_server`` documentation, "Map format" (YAML keys image, resolution, origin,
   negate, occupied_thresh, free_thresh, mode), http://wiki.ros.org/map_server.
.. [2] W. E. Lorensen, H. E. Cline, "Marching cubes", SIGGRAPH 1987 (marching squares in 2-D,
   as in ``skimage.measure.find_contours``).
.. [3] J. Sklansky, V. Gonzalez, "Fast polygonal approximation of digitized curves", Pattern
   Recognition 12 (1980) 327-331 (cone intersection).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from confnav.errors import ConfnavError, fmt_point
from confnav.geometry import Workspace, signed_area
from confnav.maps.footprint import inflate

__all__ = [
    "ImportReport",
    "ImportResult",
    "MapError",
    "MapMeta",
    "import_map",
    "load_occupancy",
    "rasterize",
    "read_map_yaml",
    "workspace_from_grid",
]

BoolGrid = NDArray[np.bool_]


class MapError(ConfnavError, ValueError):
    """The occupancy map cannot be read or does not describe a closed free space."""


@dataclass(frozen=True)
class MapMeta:
    """The keys of a map_server YAML file (``image`` resolved against the YAML's folder)."""

    image: Path
    resolution: float
    origin: tuple[float, float, float]
    negate: bool = False
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    mode: str = "trinary"


def read_map_yaml(path: str | Path) -> MapMeta:
    """Parse and check a map_server YAML file (:class:`MapError` naming the bad key)."""
    import yaml

    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise MapError(f"cannot read map file {p}: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise MapError(f"{p}: not valid YAML ({exc})") from exc
    if not isinstance(doc, dict):
        raise MapError(f"{p}: a map YAML must be a mapping with image, resolution, origin")
    for key in ("image", "resolution", "origin"):
        if key not in doc:
            raise MapError(f"{p}: missing key {key!r}")
    try:
        res = float(doc["resolution"])
        origin = tuple(float(v) for v in doc["origin"])
        occ = float(doc.get("occupied_thresh", 0.65))
        free = float(doc.get("free_thresh", 0.196))
        negate = int(doc.get("negate", 0))
    except (TypeError, ValueError) as exc:
        raise MapError(f"{p}: resolution, origin, thresholds and negate must be numbers") from exc
    if not (math.isfinite(res) and res > 0):
        raise MapError(f"{p}: resolution must be positive, got {doc['resolution']!r}")
    if len(origin) == 2:
        origin = (*origin, 0.0)
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise MapError(f"{p}: origin must be [x, y, yaw] (finite), got {doc['origin']!r}")
    if not (0.0 <= free < occ <= 1.0):
        raise MapError(
            f"{p}: thresholds must satisfy 0 <= free_thresh < occupied_thresh <= 1, got "
            f"free_thresh={free:g}, occupied_thresh={occ:g}"
        )
    if negate not in (0, 1):
        raise MapError(f"{p}: negate must be 0 or 1, got {doc['negate']!r}")
    mode = str(doc.get("mode", "trinary"))
    if mode not in ("trinary", "scale", "raw"):
        raise MapError(f"{p}: mode must be trinary, scale or raw, got {mode!r}")
    image = Path(str(doc["image"]))
    if not image.is_absolute():
        image = p.parent / image
    return MapMeta(image, res, (origin[0], origin[1], origin[2]), bool(negate), occ, free, mode)


def load_occupancy(meta: MapMeta) -> BoolGrid:
    """Free-cell mask of the map's image (row 0 = top); unknown cells are not free."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(meta.image) as im:
            v = np.asarray(im.convert("L") if im.mode in ("P", "1") else im, dtype=np.float64)
    except FileNotFoundError as exc:
        raise MapError(f"map image {meta.image} does not exist") from exc
    except (OSError, UnidentifiedImageError) as exc:
        raise MapError(f"cannot read map image {meta.image}: {exc}") from exc
    if v.ndim == 3:  # colour: map_server averages the colour channels (alpha ignored)
        v = v[..., :3].mean(axis=2)
    if v.size and v.max() > 255:
        raise MapError(f"map image {meta.image}: only 8-bit images are supported")
    if v.ndim != 2 or v.size == 0:
        raise MapError(f"map image {meta.image} is empty")
    if meta.mode == "raw":
        p = v / 100.0
        unknown = v > 100
    else:
        p = v / 255.0 if meta.negate else (255.0 - v) / 255.0
        unknown = np.zeros(v.shape, dtype=bool)
    free: BoolGrid = (p < meta.free_thresh) & ~unknown
    return free


@dataclass(frozen=True)
class ImportReport:
    """What the import did: cell counts, components, obstacles, specks, the measured error."""

    shape: tuple[int, int]
    resolution: float
    free_cells: int
    components: int
    kept_cells: int
    obstacles: int
    merged_cells: int
    dropped_specks: int
    simplify_cells: float
    hausdorff_cells: float
    vertices: int
    robot_radius: float
    seconds: float
    warnings: tuple[str, ...] = field(default=())

    def lines(self) -> list[str]:
        h, w = self.shape
        return [
            f"grid {w}x{h} at {self.resolution:g} m: {self.free_cells} free cells in "
            f"{self.components} component(s), kept {self.kept_cells}",
            f"closing filled {self.merged_cells} cells; dropped {self.dropped_specks} speck(s)",
            f"{self.obstacles} obstacle(s), {self.vertices} vertices (one-sided simplification "
            f"at {self.simplify_cells:g} cell)",
            f"Hausdorff error {self.hausdorff_cells:.3f} cell "
            f"({self.hausdorff_cells * self.resolution:.4g} m)"
            + (f"; robot radius {self.robot_radius:g} m" if self.robot_radius else ""),
            f"import took {self.seconds:.3f} s",
            *(f"warning: {w}" for w in self.warnings),
        ]


@dataclass(frozen=True)
class ImportResult:
    workspace: Workspace
    report: ImportReport
    free: BoolGrid = field(repr=False)  # the kept free cells after closing (row 0 = top)


def _cells_to_world(
    u: NDArray[np.float64], v: NDArray[np.float64], res: float, origin: tuple[float, float, float]
) -> NDArray[np.complex128]:
    z = complex(origin[0], origin[1]) + np.exp(1j * origin[2]) * res * (u + 1j * v)
    return np.asarray(z, dtype=np.complex128)


def _world_to_cell(
    z: complex, h: int, res: float, origin: tuple[float, float, float]
) -> tuple[int, int]:
    q = (z - complex(origin[0], origin[1])) * np.exp(-1j * origin[2]) / res
    return h - 1 - math.floor(q.imag), math.floor(q.real)


def _exact_union(mask: BoolGrid) -> Any:
    """The union of the True cells as a shapely geometry in cell units (row runs -> boxes)."""
    h, w = mask.shape
    pad = np.zeros((h, w + 2), dtype=np.int8)
    pad[:, 1:-1] = mask
    d = np.diff(pad, axis=1)
    r0, c0 = np.nonzero(d == 1)
    c1 = np.nonzero(d == -1)[1]  # run ends: same rows, same order (row-major scan)
    boxes = shapely.box(c0, h - 1 - r0, c1, h - r0)
    return shapely.union_all(boxes)


def _merge_gaps(free: BoolGrid, rho: int) -> BoolGrid:
    """Step 2: close the occupied set with a disk of ``rho`` cells (outside the image is
    occupied); returns the free cells left."""
    from scipy import ndimage
    from skimage import morphology

    if rho <= 0:
        return free
    occ = np.pad(~free, rho + 1, constant_values=True)
    occ = ndimage.binary_closing(occ, morphology.disk(rho))  # type: ignore[no-untyped-call]
    return np.asarray(~occ[rho + 1 : -rho - 1, rho + 1 : -rho - 1])


def _keep_component(
    closed_free: BoolGrid,
    keep: complex | None,
    rho: int,
    resolution: float,
    origin: tuple[float, float, float],
) -> tuple[BoolGrid, int, int]:
    """Step 3: the 4-connected free component holding ``keep`` (default: the largest), made
    a simple polygon's cells (:func:`_unpinch`). Returns it, the number of components and the
    cells that unpinching occupied."""
    from scipy import ndimage

    h, w = closed_free.shape
    labels, n_comp = ndimage.label(closed_free)  # default structure: 4-connectivity
    if n_comp == 0:
        raise MapError(f"no free space is left after merging gaps narrower than {2 * rho} cells")
    cell: tuple[int, int] | None = None
    if keep is not None:
        i, j = _world_to_cell(complex(keep), h, resolution, origin)
        if not (0 <= i < h and 0 <= j < w):
            raise MapError(f"--keep point {fmt_point(keep)} is outside the map")
        if not closed_free[i, j]:
            raise MapError(
                f"--keep point ({keep.real:g}, {keep.imag:g}) is in an occupied or unknown cell "
                f"(row {i}, col {j})"
            )
        k = int(labels[i, j])
        cell = (i, j)
    else:
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        k = int(np.argmax(sizes))
    kept, pinched = _unpinch(labels == k, cell)
    return kept, int(n_comp), pinched


def _border_warning(
    kept: BoolGrid, resolution: float, origin: tuple[float, float, float]
) -> list[str]:
    """Step 3: where the kept free space runs into the image border, the border is a wall
    (the map's extent is the robot's world); said once, with the first such cell."""
    h, w = kept.shape
    border = np.concatenate([kept[0], kept[-1], kept[:, 0], kept[:, -1]])
    if not border.any():
        return []
    rows, cols = np.nonzero(kept)
    on = (rows == 0) | (rows == h - 1) | (cols == 0) | (cols == w - 1)
    k0 = int(np.flatnonzero(on)[0])
    zc = complex(
        _cells_to_world(
            np.asarray(cols[k0 : k0 + 1] + 0.5, dtype=np.float64),
            np.asarray(h - rows[k0 : k0 + 1] - 0.5, dtype=np.float64),
            resolution,
            origin,
        )[0]
    )
    return [
        f"the free space runs into the image border ({int(on.sum())} border cells, first "
        f"at row {rows[k0]}, col {cols[k0]}, x={zc.real:.4g}, y={zc.imag:.4g}): the "
        "border is taken as a wall (the map's extent is the robot's world)"
    ]


def _specks(
    kept: BoolGrid, min_obstacle_cells: int, resolution: float
) -> tuple[BoolGrid, int, list[str]]:
    """Step 2's optional drop: obstacles (8-connected blocked components inside the kept free
    space) of at most ``min_obstacle_cells`` cells are freed; with 0 one-cell obstacles are
    kept (conservative) but named. Returns the mask, the obstacles dropped and warnings."""
    from scipy import ndimage

    # the image is padded with blocked cells so that everything outside it is one component
    holes, n_holes = ndimage.label(np.pad(~kept, 1, constant_values=True), np.ones((3, 3)))
    outside = holes[0, 0]
    holes = holes[1:-1, 1:-1]
    sizes = np.bincount(holes.ravel(), minlength=n_holes + 1)
    if min_obstacle_cells <= 0:
        ones = np.flatnonzero(sizes == 1)
        ones = ones[(ones != 0) & (ones != outside)]
        if ones.size:  # kept (conservative), but said: grown by a robot each blocks a square
            return (
                kept,
                0,
                [
                    f"kept {ones.size} one-cell obstacle(s), SLAM specks perhaps: grown by a "
                    f"robot of radius R each blocks a square of side 2 R + {resolution:g} m and "
                    "can cut rooms off; --min-obstacle-cells 1 drops them (non-conservative)"
                ],
            )
        return kept, 0, []
    small = np.flatnonzero(sizes <= min_obstacle_cells)
    small = small[(small != 0) & (small != outside)]
    if not small.size:
        return kept, 0, []
    return (
        kept | np.isin(holes, small),
        int(small.size),
        [
            f"dropped {int(small.size)} obstacle(s) of <= {min_obstacle_cells} cells "
            "(non-conservative: they are gone from the workspace)"
        ],
    )


def _polygon_workspace(
    poly: Polygon, resolution: float, origin: tuple[float, float, float]
) -> Workspace:
    """Step 6: the traced polygon (cell units) as a workspace in metres in the map frame."""

    def world(coords: Any) -> NDArray[np.complex128]:
        xy = np.asarray(coords, dtype=np.float64)[:-1]
        return _cells_to_world(xy[:, 0], xy[:, 1], resolution, origin)

    return Workspace(world(poly.exterior.coords), [world(h.coords) for h in poly.interiors])


def workspace_from_grid(
    free: BoolGrid,
    resolution: float,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    robot_radius: float = 0.0,
    keep: complex | None = None,
    min_obstacle_cells: int = 0,
    merge_cells: int = 0,
    max_error: float = 1.0,
) -> ImportResult:
    """Steps 2-6 of the module docstring on a free-cell mask (row 0 = top): merge
    (:func:`_merge_gaps`), keep (:func:`_keep_component`, :func:`_border_warning`), drop
    specks on request (:func:`_specks`), trace and simplify (:func:`_trace`), write
    (:func:`_polygon_workspace`, shrunk by ``robot_radius``)."""
    t0 = time.perf_counter()
    free = np.asarray(free, dtype=bool)
    if free.ndim != 2 or free.size == 0:
        raise MapError("the occupancy grid must be a non-empty 2-D array")
    h, w = free.shape
    n_free = int(free.sum())
    if n_free == 0:
        raise MapError("the map has no free cell (check negate and the thresholds)")
    rho = max(merge_cells, math.floor(robot_radius / resolution + 1e-9))
    closed_free = _merge_gaps(free, rho)
    kept, n_comp, pinched = _keep_component(closed_free, keep, rho, resolution, origin)
    merged = int(n_free - closed_free.sum()) + pinched
    warnings = _border_warning(kept, resolution, origin)
    kept, dropped, speck_warnings = _specks(kept, min_obstacle_cells, resolution)
    warnings += speck_warnings
    poly, hd = _trace(kept, _exact_union(kept), max_error)
    if hd > max_error + 1e-9:
        warnings.append(f"Hausdorff error {hd:.3f} cell exceeds {max_error:g} cell")
    ws = _polygon_workspace(poly, resolution, origin)
    if robot_radius > 0:
        ws = inflate(ws, robot_radius, keep=keep)
    report = ImportReport(
        shape=(h, w),
        resolution=resolution,
        free_cells=n_free,
        components=n_comp,
        kept_cells=int(kept.sum()),
        obstacles=ws.n_obstacles,
        merged_cells=merged,
        dropped_specks=dropped,
        simplify_cells=max_error,
        hausdorff_cells=hd,
        vertices=int(sum(len(b) for b in ws.boundaries)),
        robot_radius=robot_radius,
        seconds=time.perf_counter() - t0,
        warnings=tuple(warnings),
    )
    return ImportResult(ws, report, kept)


def _unpinch(kept: BoolGrid, cell: tuple[int, int] | None) -> tuple[BoolGrid, int]:
    """Occupy one free cell of every diagonal-only contact (a 2x2 checkerboard), so that the
    boundary is a simple polygon, and keep the component of ``cell`` (default: largest).
    Only removes free cells (conservative); returns the mask and the number removed."""
    from scipy import ndimage

    kept = kept.copy()
    n0 = int(kept.sum())
    while True:
        a, b, c, d = kept[:-1, :-1], kept[:-1, 1:], kept[1:, :-1], kept[1:, 1:]
        main = a & d & ~b & ~c
        anti = b & c & ~a & ~d
        if not (main.any() or anti.any()):
            break
        kept[:-1, :-1] &= ~main
        kept[:-1, 1:] &= ~anti
    labels, n = ndimage.label(kept)
    if n > 1:
        if cell is not None and labels[cell]:
            k = int(labels[cell])
        else:
            sizes = np.bincount(labels.ravel())
            sizes[0] = 0
            k = int(np.argmax(sizes))
        kept = labels == k
    return kept, n0 - int(kept.sum())


def _staircase_rings(kept: BoolGrid) -> list[NDArray[np.complex128]]:
    """Exact cell-edge boundary of ``kept`` (cell units, free on the left: outer ring
    counter-clockwise first, holes clockwise), traced by marching squares.

    ``find_contours`` at level 0.5 puts vertices at the midpoints of the edges between free and
    occupied cells and cuts each cell corner by a diagonal step; the corner (the endpoint pair's
    mixed point whose both coordinates are half-integers) is put back and the collinear
    midpoints are dropped, so every vertex is a cell corner.
    """
    from skimage import measure

    h = kept.shape[0]
    padded = np.pad(kept, 1).astype(np.float64)
    contours = measure.find_contours(padded, 0.5, fully_connected="low")  # type: ignore[no-untyped-call]
    rings: list[NDArray[np.complex128]] = []
    for c in contours:
        r, q = c[:, 0], c[:, 1]
        r0, q0, r1, q1 = r[:-1], q[:-1], r[1:], q[1:]
        diag = (r0 != r1) & (q0 != q1)
        half = np.isclose(np.mod(r0, 1.0), 0.5)
        corner = np.where(half, r0 + 1j * q1, r1 + 1j * q0)
        seq = np.column_stack([r0 + 1j * q0, corner]).ravel()
        seq = seq[np.column_stack([np.ones_like(diag), diag]).ravel()]
        z = (seq.imag - 0.5) + 1j * (h + 0.5 - seq.real)  # cell units, y up
        z = np.round(z * 2) / 2
        d_in, d_out = z - np.roll(z, 1), np.roll(z, -1) - z
        z = z[(np.conj(d_in) * d_out).imag != 0]  # keep the corners only
        if z.size >= 4:
            rings.append(z)
    rings.sort(key=lambda z: -abs(signed_area(z)))
    out = []
    for k, z in enumerate(rings):
        ccw = signed_area(z) > 0
        out.append(z if ccw == (k == 0) else z[::-1])
    return out


def _simplify_ring(z: NDArray[np.complex128], tol: float) -> BoolGrid:
    """One-sided simplification of a closed ring with the free space on its left: the mask of
    the vertices kept.

    From each kept vertex ``a`` the chord goes to the farthest vertex such that every skipped
    vertex lies on the right of the chord (the obstacle side: the chord only cuts off free
    space, so no obstacle shrinks) within ``tol`` of it. The feasible chord directions form a
    cone narrowed by each skipped vertex (the cone intersection of [3]_, made one-sided), so the
    whole pass is linear in the vertices.
    """
    n = z.size
    mask = np.ones(n, dtype=bool)
    if tol <= 0 or n <= 4:
        return mask
    s = int(np.lexsort((z.imag, z.real))[0])  # an extreme vertex: a corner every result keeps
    zc = np.append(np.roll(z, -s), z[s])
    keep = [0]
    i = 0
    while i < n:
        a = zc[i]
        ref = (zc[i + 1] - a) / abs(zc[i + 1] - a)
        lo, hi, far = -math.inf, math.inf, 0.0
        best = i + 1
        for j in range(i + 1, n + 1):
            p = (zc[j] - a) / ref
            ang, dist = math.atan2(p.imag, p.real), abs(p)
            if lo <= ang <= hi and dist >= far:
                best = j
            # v_j on the right of the chord (direction >= ang) and within tol of it
            lo = max(lo, ang)
            hi = min(hi, ang + (math.asin(tol / dist) if dist > tol else 0.5 * math.pi))
            far = max(far, dist)
            if lo > hi:
                break
        keep.append(best)
        i = best
    mask[:] = False
    mask[(np.asarray(keep[:-1]) + s) % n] = True
    return mask


def _trace(kept: BoolGrid, exact: Any, tol: float) -> tuple[Polygon, float]:
    """Steps 4-5: the exact staircase, simplified one-sidedly, repaired chord by chord.

    Every ring is simplified at ``tol`` (:func:`_simplify_ring`); then each chord is checked
    exactly (shapely): it lies in the free cells (so no obstacle shrinks), and it meets no
    other chord of any ring except its two neighbours at their common vertices (so the rings
    stay simple and apart). A chord that fails is replaced by the staircase it skipped, and
    the check repeats until none fails (the staircase itself always passes). A failed check
    used to halve the tolerance of *every* ring, so one SLAM speck a cell from a wall left a
    whole map unsimplified (a 30 x 15 m depot: 2738 vertices, 62-68 % of the edges one cell,
    "Hausdorff error 0.000 cell"). Returns the polygon, checked valid and inside the free
    cells, and an exact bound of its Hausdorff distance to their boundary in cells
    (:func:`_chord_error`; the boundaries' distance is at most the largest ring's).
    """
    rings = _staircase_rings(kept)
    masks = [_simplify_ring(z, tol) for z in rings]
    guard = exact.buffer(1e-9)
    shapely.prepare(guard)
    while True:
        bad = _bad_chords(rings, masks, guard)
        if not bad:
            break
        for k, (i, j) in bad:  # put back the staircase between vertices i and j of ring k
            n = rings[k].size
            masks[k][(i + np.arange((j - i) % n)) % n] = True
    simple = [z[m] for z, m in zip(rings, masks, strict=True)]
    poly = Polygon(_xy(simple[0]), [_xy(z) for z in simple[1:]])
    if not (poly.is_valid and guard.contains(poly)):
        raise MapError("could not fit a valid polygon inside the free cells")
    return poly, max((_chord_error(z, m) for z, m in zip(rings, masks, strict=True)), default=0.0)


def _chord_error(z: NDArray[np.complex128], mask: BoolGrid) -> float:
    """Hausdorff distance between a ring ``z`` and its simplification ``z[mask]``, bounded
    exactly: the largest distance of a skipped vertex from its chord (segment).

    Staircase to chords: the distance to a segment is convex, so on each staircase edge it
    peaks at a vertex. Chords to staircase: the staircase between a chord's ends projects onto
    the whole chord (it is connected and starts and ends there), so every chord point has a
    staircase point on its perpendicular, no farther than the staircase's largest distance
    from the chord's line, which a vertex attains (again by convexity).
    """
    v = np.flatnonzero(mask)
    skipped = np.flatnonzero(~mask)
    if skipped.size == 0:
        return 0.0
    pos = np.searchsorted(v, skipped)
    a, b = z[v[pos - 1]], z[v[pos % v.size]]  # pos 0: the chord wrapping past the end
    t = np.clip(((z[skipped] - a) * np.conj(b - a)).real / np.abs(b - a) ** 2, 0.0, 1.0)
    return float(np.max(np.abs(z[skipped] - (a + t * (b - a)))))


def _xy(z: NDArray[np.complex128]) -> NDArray[np.float64]:
    return np.column_stack([z.real, z.imag])


def _bad_chords(
    rings: list[NDArray[np.complex128]], masks: list[BoolGrid], guard: Any
) -> list[tuple[int, tuple[int, int]]]:
    """The chords (ring, (first vertex, last vertex)) that skip vertices and leave the free
    cells or meet a chord other than their neighbours (all checks vectorised in shapely)."""
    ring_of, first, last, a, b = [], [], [], [], []
    for k, (z, m) in enumerate(zip(rings, masks, strict=True)):
        v = np.flatnonzero(m)
        w = np.roll(v, -1)
        ring_of.append(np.full(v.size, k))
        first.append(v)
        last.append(w)
        a.append(z[v])
        b.append(z[w])
    ring = np.concatenate(ring_of)
    i0, i1 = np.concatenate(first), np.concatenate(last)
    za, zb = np.concatenate(a), np.concatenate(b)
    sizes = np.array([z.size for z in rings])[ring]
    skips = (i1 - i0) % sizes > 1  # a chord, not a staircase edge
    seg = shapely.linestrings(np.stack([_xy(za), _xy(zb)], axis=1))
    bad = skips & ~shapely.within(seg, guard)
    p, q = shapely.STRtree(seg).query(seg, predicate="intersects")
    nb = (ring[p] == ring[q]) & ((i1[p] == i0[q]) | (i0[p] == i1[q]))  # neighbours
    cross = (p != q) & ~nb
    bad[p[cross]] |= skips[p[cross]]
    return [(int(ring[c]), (int(i0[c]), int(i1[c]))) for c in np.flatnonzero(bad)]


def import_map(
    path: str | Path,
    *,
    robot_radius: float = 0.0,
    keep: complex | None = None,
    min_obstacle_cells: int = 0,
    merge_cells: int = 0,
    max_error: float = 1.0,
) -> ImportResult:
    """Read a map_server YAML map and return the validated workspace with a report."""
    if not (math.isfinite(robot_radius) and robot_radius >= 0):
        raise MapError(f"robot radius must be >= 0, got {robot_radius!r}")
    meta = read_map_yaml(path)
    free = load_occupancy(meta)
    return workspace_from_grid(
        free,
        meta.resolution,
        meta.origin,
        robot_radius=robot_radius,
        keep=keep,
        min_obstacle_cells=min_obstacle_cells,
        merge_cells=merge_cells,
        max_error=max_error,
    )


def rasterize(
    ws: Workspace, resolution: float, origin: tuple[float, float], shape: tuple[int, int]
) -> BoolGrid:
    """Free-cell mask (row 0 = top) of a workspace: a cell is free iff its centre is free."""
    h, w = shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    z = complex(origin[0], origin[1]) + resolution * ((jj + 0.5) + 1j * (h - ii - 0.5))
    return np.asarray(ws.contains(z), dtype=bool)
