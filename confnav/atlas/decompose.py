"""Decomposition of a free space into overlapping, well-conditioned cells (quadtree of tiles).

A single conformal map of a long corridor crowds like ``exp(-pi L / w)`` (DESIGN.md section 6):
beyond ``L/w ~ 11`` its far end is below double precision.  An atlas covers the free space
with small cells, each mapped on its own.  The cells come from overlapping tiles:

1. a square grid of tiles of side ``tile`` covers the bounding box;
2. each tile is enlarged by ``overlap * side`` (at least ``2 margin``) on every side, each
   enlarged edge snapped inwards onto a boundary vertex just inside it, and intersected with
   the free space (shapely); obstacles cut by the edge become notches of the outer boundary;
3. each piece is cleaned (:func:`_pieces`): channels and slivers along the cut, thinner than
   3/4 of the overlap, are removed, and so is a piece that does not reach into its tile's
   core; the connected components left are the cells;
4. a tile whose pieces are too crowded a priori -- the elongation ``area / (2 r)^2``, with
   ``r`` the largest inscribed radius, above ``max_ratio`` (``max_ratio_holes`` for a piece
   with obstacles; it is ``L/w`` for an L x w rectangle), or more than ``max_obstacles``
   holes -- is split into four, down to ``min_tile``.

Why it covers: a free point lies in the core (un-enlarged) square of some tile, at least 3/4 of
that tile's overlap from its cut edges; cleaning removes nothing of the core except where the
free space itself is thinner than the opening (:func:`Decomposition.uncovered_area` measures
it; the tests require 0).

Why tiles rather than medial-axis cuts: tiles need no skeleton (fragile on polygons with
hundreds of vertices), bound every cell's size, hence its elongation and obstacle count, by
construction, and give overlaps of a known width (at least ``3 margin`` across a tile edge).
See docs/ATLAS.md.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.ops import polylabel

from confnav.errors import WorkspaceError
from confnav.geometry import Workspace

__all__ = ["Cell", "Decomposition", "Tile", "decompose", "elongation"]

Tile = tuple[float, float, float, float]  # (x0, y0, x1, y1) of the core square


def _polygons(g: BaseGeometry) -> list[Polygon]:
    """The polygonal parts of a shapely geometry (any collection)."""
    if isinstance(g, Polygon):
        return [g] if not g.is_empty else []
    if isinstance(g, MultiPolygon):
        return [p for p in g.geoms if not p.is_empty]
    return [p for p in getattr(g, "geoms", []) if isinstance(p, Polygon) and not p.is_empty]


def inscribed(poly: Polygon, rel_tol: float = 1e-3) -> tuple[complex, float]:
    """Pole of inaccessibility of ``poly`` and its distance to the boundary (shapely polylabel)."""
    x0, y0, x1, y1 = poly.bounds
    p = polylabel(poly, tolerance=rel_tol * max(x1 - x0, y1 - y0))
    return complex(p.x, p.y), float(poly.boundary.distance(p))


def elongation(poly: Polygon) -> float:
    """A-priori crowding indicator ``area / (2 r)^2`` (``r``: largest inscribed radius).

    It is ``L/w`` for an ``L x w`` rectangle, about 1 for a square or a disk; the map of a
    channel of this elongation contracts like ``exp(-pi L/w)`` (DESIGN.md section 6).
    """
    r = inscribed(poly)[1]
    return float(poly.area / (2 * r) ** 2) if r > 0 else float("inf")


@dataclass(frozen=True)
class Cell:
    """One cell of the atlas: a polygonal domain cut from the free space.

    polygon: the cell's free space (shapely); workspace: the same as a validated
    :class:`Workspace` (outer boundary = tile cut + walls, holes = whole obstacles inside);
    cut: the part of the boundary that is not a wall of the original workspace (the tile
    edges); tile: the core square it came from; ratio: :func:`elongation`.
    """

    index: int
    polygon: Polygon
    workspace: Workspace
    cut: BaseGeometry
    tile: Tile
    ratio: float

    def depth(self, z: np.ndarray) -> np.ndarray:
        """Distance of the points ``z`` to the cut edges where they lie inside the cell,
        ``-inf`` outside (vectorized).  Walls do not count: a robot near a wall is still
        well inside the cell's domain as far as switching charts goes."""
        z = np.asarray(z, dtype=np.complex128)
        pts = shapely.points(z.real, z.imag)
        inside = np.asarray(shapely.contains(self.polygon, pts), dtype=bool)
        if self.cut.is_empty:
            d = np.full(z.shape, np.inf)
        else:
            d = np.asarray(shapely.distance(self.cut, pts), dtype=np.float64)
        return np.where(inside, d, -np.inf)


@dataclass(frozen=True)
class Decomposition:
    """Cells covering a workspace's free space, with the parameters that made them."""

    workspace: Workspace
    cells: tuple[Cell, ...]
    tile: float
    overlap: float
    margin: float
    max_ratio: float
    max_ratio_holes: float
    max_obstacles: int
    split: frozenset[Tile] = field(default_factory=frozenset)

    def uncovered_area(self) -> float:
        """Area of the free space outside every cell (0 up to rounding when covered)."""
        union = shapely.union_all([c.polygon for c in self.cells])
        return float(self.workspace.polygon.difference(union).area)


def _cell_workspace(poly: Polygon, scale: float) -> Workspace:
    """A validated workspace from a shapely polygon (collinear and near-duplicate vertices
    removed, which only add corners to the mesh)."""
    p = poly.simplify(1e-9 * scale, preserve_topology=True)
    if not isinstance(p, Polygon) or p.is_empty:
        raise WorkspaceError("cell polygon degenerates on simplification")

    def ring(coords: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
        return [(float(x), float(y)) for x, y in list(coords)[:-1]]

    # anchor: the centroid when it is nearly as deep as the deepest point.  The pole of
    # inaccessibility of a strip is anywhere on its midline (polylabel may put it near one
    # end), and the map then contracts like exp(-pi d/w) towards the far end; measured on a
    # 0.4 x 2.1 m cell anchored 0.2 m from its end: the error estimate grew with refinement,
    # 3.8e-8 -> 2.6e-6, against 1e-8 at the centre.
    pole, r = inscribed(p)
    c = p.centroid
    anchor = pole
    if p.contains(c) and p.boundary.distance(c) >= 0.75 * r:
        anchor = complex(c.x, c.y)
    return Workspace(ring(p.exterior.coords), [ring(h.coords) for h in p.interiors], anchor=anchor)


def _snapped_box(core: Tile, overlap: float, vertices: np.ndarray) -> Polygon:
    """The core enlarged by ``overlap``, each edge moved inwards (by less than ``overlap/4``)
    onto the innermost boundary vertex lying just inside it.

    A cut passing a hair inside an obstacle's side would leave a bump of that height on the
    cell's boundary: a side of length 1e-3 beside sides of metres, which the graded mesh
    resolves only at great cost (measured: tol 1e-8 missed even after four splits).  On the
    snapped edge the obstacle's side lies on the cut instead.
    """
    eps = overlap / 4
    x0, y0 = core[0] - overlap, core[1] - overlap
    x1, y1 = core[2] + overlap, core[3] + overlap
    vx, vy = vertices.real, vertices.imag
    in_y = (vy > y0 - eps) & (vy < y1 + eps)
    in_x = (vx > x0 - eps) & (vx < x1 + eps)
    near = in_y & (vx > x0) & (vx < x0 + eps)
    x0n = float(vx[near].max()) if near.any() else x0
    near = in_y & (vx < x1) & (vx > x1 - eps)
    x1n = float(vx[near].min()) if near.any() else x1
    near = in_x & (vy > y0) & (vy < y0 + eps)
    y0n = float(vy[near].max()) if near.any() else y0
    near = in_x & (vy < y1) & (vy > y1 - eps)
    y1n = float(vy[near].min()) if near.any() else y1
    return box(x0n, y0n, x1n, y1n)


def _pieces(
    free: Polygon,
    walls: BaseGeometry,
    vertices: np.ndarray,
    core: Tile,
    overlap: float,
    min_area: float,
) -> list[Polygon]:
    """Cleaned connected components of (tile enlarged by ``overlap``) intersected with free.

    The enlarged tile is snapped to nearby vertices (:func:`_snapped_box`, which keeps at
    least ``3/4`` of the overlap).  Each component is opened by ``3/8`` of the overlap
    (mitre joins); of what the opening removes, only the part within ``3/4`` of the overlap
    from the cut edges is dropped: channels narrower than that between the tile edge and an
    obstacle (a hole almost touching the outer boundary crowds the map), and slivers.
    Genuine narrow passages of the free space away from the cut stay.  What is dropped lies
    outside this tile's core, hence in a neighbouring core, far from that tile's cut edges;
    so is a whole piece that does not reach into the core, which is dropped too.
    """
    raw = free.intersection(_snapped_box(core, overlap, vertices))
    core_box = box(*core)
    rho = 3 * overlap / 8
    out: list[Polygon] = []
    for comp in _polygons(raw):
        cut = comp.boundary.difference(walls)
        # erosion by the boundary's mitred buffer: square-ish everywhere (a negative buffer
        # rounds the convex corners of obstacles), then a mitred dilation
        eroded = comp.difference(comp.boundary.buffer(rho, join_style="mitre", cap_style="square"))
        opened = eroded.buffer(rho, join_style="mitre")
        opened = opened.intersection(comp)  # never outside the component
        if not cut.is_empty:
            near = cut.buffer(2 * rho, join_style="mitre", cap_style="square")
            thin = comp.difference(opened).difference(near)
            opened = opened.union(thin)
        # a piece that does not reach into the core lies in the neighbours' cores, which
        # cover it deeply: drop it (measured: a 4.4 x 18 cm sliver along a corridor wall whose
        # solve missed 1e-6)
        out.extend(
            p
            for p in _polygons(opened)
            if p.area >= min_area and p.intersection(core_box).area >= min_area
        )
    return out


def decompose(
    ws: Workspace,
    *,
    tile: float | None = None,
    overlap: float = 0.25,
    margin: float | None = None,
    max_ratio: float = 6.0,
    max_ratio_holes: float = 2.5,
    max_obstacles: int = 12,
    min_tile: float | None = None,
    split: Iterable[Tile] = (),
) -> Decomposition:
    """Overlapping cells covering the free space of ``ws`` (module docstring).

    Parameters
    ----------
    tile : side of the initial tiles (default ``6 r``, ``r`` the free space's largest
        inscribed radius).
    overlap : enlargement of a tile on each side as a fraction of its side (at least
        ``2 margin``; snapping keeps 3/4 of it): neighbouring cells overlap in a band at
        least ``3 margin`` wide.
    margin : the depth a local goal needs inside an overlap (robot radius plus goal
        neighbourhood; default ``r / 10``).  ``overlap`` must exceed it.
    max_ratio, max_ratio_holes, max_obstacles : a tile whose pieces exceed either is split
        into four.  Cells with obstacles get the tighter elongation bound: an obstacle at the
        far end of a cell of elongation q, seen from the anchor in the middle, maps to a
        circle within ~exp(-pi q / 2) of the unit circle (q = 3.75: 3e-3, too close for the
        harmonic navigation function's series; measured in tests/test_atlas.py's corridor).
    min_tile : smallest tile side (default ``tile / 16``).
    split : core tiles to split regardless (used when a cell's solve failed).
    """
    free = ws.polygon
    r = inscribed(free)[1]
    tile = float(tile) if tile is not None else 6.0 * r
    margin = float(margin) if margin is not None else 0.1 * r
    min_tile = float(min_tile) if min_tile is not None else tile / 16
    if not (tile > 0 and margin > 0 and 0 < overlap <= 1 and min_tile > 0):
        raise WorkspaceError(
            f"atlas needs tile > 0, margin > 0 and overlap in (0, 1] "
            f"(tile {tile:g}, overlap {overlap:g}, margin {margin:g})"
        )
    min_area = 0.5 * margin**2
    forced = frozenset(split)
    scale = ws.diameter
    walls = free.boundary.buffer(1e-9 * scale)
    vertices = np.concatenate([ws.outer, *ws.obstacles])
    x0, y0, x1, y1 = ws.bounds
    nx = max(1, int(np.ceil((x1 - x0) / tile - 1e-9)))
    ny = max(1, int(np.ceil((y1 - y0) / tile - 1e-9)))
    # centre the grid on the bounding box
    ox = x0 - (nx * tile - (x1 - x0)) / 2
    oy = y0 - (ny * tile - (y1 - y0)) / 2
    todo: list[Tile] = [
        (ox + i * tile, oy + j * tile, ox + (i + 1) * tile, oy + (j + 1) * tile)
        for j in range(ny)
        for i in range(nx)
    ]
    polys: list[tuple[Polygon, Tile, float]] = []
    while todo:
        core = todo.pop(0)
        side = core[2] - core[0]
        pieces = _pieces(free, walls, vertices, core, max(overlap * side, 2 * margin), min_area)
        ratios = [elongation(p) for p in pieces]
        bad = any(
            q > (max_ratio if not p.interiors else max_ratio_holes)
            or len(p.interiors) > max_obstacles
            for p, q in zip(pieces, ratios, strict=True)
        )
        if (bad or core in forced) and side / 2 >= min_tile - 1e-12:
            cx, cy = (core[0] + core[2]) / 2, (core[1] + core[3]) / 2
            todo += [
                (core[0], core[1], cx, cy),
                (cx, core[1], core[2], cy),
                (core[0], cy, cx, core[3]),
                (cx, cy, core[2], core[3]),
            ]
            continue
        polys += [(p, core, q) for p, q in zip(pieces, ratios, strict=True)]
    cells: list[Cell] = []
    for poly, core, q in polys:
        cut = poly.boundary.difference(walls)
        cells.append(Cell(len(cells), poly, _cell_workspace(poly, scale), cut, core, q))
    return Decomposition(
        ws, tuple(cells), tile, overlap, margin, max_ratio, max_ratio_holes, max_obstacles, forced
    )
