"""Decomposition of a free space into overlapping, well-conditioned cells (quadtree of tiles).

A single conformal map of a long corridor crowds like ``exp(-pi L / w)`` (docs/METHOD.md section 6):
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
   holes -- is split into four, down to ``min_tile``; a tile whose chart failed
   (``split``) is split further, down to a side of ``FORCED_MIN_MARGINS`` margins.

Why it covers: a free point lies in the core (un-enlarged) square of some tile, at least 3/4 of
that tile's overlap from its cut edges; cleaning removes nothing of the core except where the
free space itself is thinner than the opening (:func:`Decomposition.uncovered_area` measures
it; the tests require 0).  A region reached only through such a hairline gives cells linked
to no other: their tiles are split, and what stays cut off is left out
(:attr:`Decomposition.dropped`, :func:`_connected`); a cleaned piece whose obstacle touches
its outer ring is repaired (:func:`_unpinched`).

The margin (the depth a local goal needs inside an overlap, :mod:`confnav.atlas.compose`) is
derived from the cells unless given: the cell graph links two cells through an overlap holding
a disk of radius ``margin``, and an overlap across a passage of width ``w`` holds no disk wider
than ``w / 2``.  :attr:`Decomposition.passage` is the thinnest overlap the graph cannot do
without (the bottleneck of a maximum spanning tree of the overlaps by depth); the automatic
margin is ``min(r / 10, depth / 2)`` of it, and a margin above its depth raises
:class:`PassageError` naming the passage.

Why tiles rather than medial-axis cuts: tiles need no skeleton (fragile on polygons with
hundreds of vertices), bound every cell's size, hence its elongation and obstacle count, by
construction, and give overlaps of a known width (at least ``3 margin`` across a tile edge).
See docs/ATLAS.md.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import LineString, MultiPolygon, Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.ops import nearest_points, polylabel

from confnav.errors import WorkspaceError, fmt_point
from confnav.geometry import Workspace

__all__ = [
    "AUTO_MARGIN_FRACTION",
    "Cell",
    "Decomposition",
    "Overlap",
    "PassageError",
    "Tile",
    "decompose",
    "elongation",
]

#: The automatic margin is this fraction of the depth of the thinnest overlap the cell graph
#: needs (:attr:`Decomposition.passage`): local goals then lie twice as deep as required,
#: slack for the redone decomposition and the inscribed-disk tolerance (1e-3 relative).
AUTO_MARGIN_FRACTION = 0.5

#: A tile whose chart failed is split down to a side of this many margins (below ``min_tile``).
FORCED_MIN_MARGINS = 2.0


class PassageError(WorkspaceError):
    """The atlas margin does not fit a passage the decomposition cuts through.

    ``point``: where (the deepest point of the thinnest overlap the cell graph needs, or the
    middle of the gap between cells that do not overlap at all); ``width``: the free space's
    width there (twice its clearance); ``depth``: the radius of the largest disk in the
    overlap (0 for no overlap); ``cells``: the two cells; ``margin``: the margin that failed.
    """

    def __init__(
        self,
        message: str,
        *,
        point: complex,
        width: float,
        depth: float,
        cells: tuple[int, int],
        margin: float,
    ) -> None:
        super().__init__(message)
        self.point, self.width, self.depth = point, width, depth
        self.cells, self.margin = cells, margin


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


#: Grid nodes of :func:`outer_depth`'s finite-difference Green's function (about 0.02 s).
DEPTH_CELLS = 10_000


def outer_depth(ws: Workspace, cells: int = DEPTH_CELLS) -> tuple[float, complex]:
    """How close the first Koebe sweep maps an obstacle to the unit circle: ``(g, where)``,
    the smallest value over the obstacles' boundaries of the Green's function ``g(z, a)`` of
    the outer boundary's interior (the obstacles filled in) with its pole at the anchor
    ``a``, and the point where it is smallest (``inf`` without obstacles).

    The map ``f`` of a simply connected domain onto the unit disk with ``f(a) = 0`` has
    ``|f(z)| = exp(-g(z, a))`` (Ahlfors, "Complex Analysis", 3rd ed., ch. 6.1; Henrici,
    "Applied and Computational Complex Analysis" vol. 3, ch. 16.1), so ``1 - |f(z)| ~ g``:
    an obstacle where ``g`` is tiny is sent next to the circle by the sweep that maps the
    outer boundary, and a room behind a door with furniture near its walls is crowded this
    way with no long channel anywhere (what :func:`bottleneck` and :func:`elongation` look
    for). ``g`` comes from the five-point Laplacian on a grid of about ``cells`` nodes over
    the outer boundary's box (LeVeque, "Finite Difference Methods for Ordinary and Partial
    Differential Equations", SIAM 2007, ch. 3), the pole a unit source ``2 pi`` at the node
    nearest the anchor, zero outside the outer boundary, read by bilinear interpolation at
    points along the obstacles' boundaries (half a grid step apart). A coarse grid reads
    ``g`` high near corners (at 10,000 nodes 1.0-3.0 times the 160,000-node value on the
    workspaces of bench/results/outer_depth.json), so the test errs towards one map.
    The threshold is :data:`confnav.atlas.charts.OUTER_DEPTH_MIN`."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    from scipy.interpolate import RegularGridInterpolator

    holes = list(ws.polygon.interiors)
    if not holes:
        return float("inf"), complex("nan")
    outer = Polygon(ws.polygon.exterior)
    x0, y0, x1, y1 = outer.bounds
    h = float(np.sqrt((x1 - x0) * (y1 - y0) / cells))
    nx, ny = int(np.ceil((x1 - x0) / h)) + 1, int(np.ceil((y1 - y0) / h)) + 1
    xs, ys = x0 + h * np.arange(nx), y0 + h * np.arange(ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    shapely.prepare(outer)
    inside = np.asarray(shapely.contains_xy(outer, gx, gy), dtype=bool)
    n = int(inside.sum())
    z = complex(ws.anchor)
    if n == 0:
        return float("inf"), complex("nan")
    idx = np.full(inside.shape, -1, dtype=np.int64)
    idx[inside] = np.arange(n)
    ii, jj = np.nonzero(inside)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], [np.full(n, 4.0)]
    for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        a, b = ii + di, jj + dj
        ok = (a >= 0) & (a < nx) & (b >= 0) & (b < ny)
        ok[ok] = inside[a[ok], b[ok]]
        rows.append(idx[ii[ok], jj[ok]])
        cols.append(idx[a[ok], b[ok]])
        vals.append(np.full(int(ok.sum()), -1.0))
    lap = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    k = int(np.argmin(np.abs(gx[inside] + 1j * gy[inside] - z)))  # the node nearest the anchor
    rhs = np.zeros(n)
    rhs[k] = 2 * np.pi  # -Laplacian(g) = 2 pi delta: g ~ log(1 / |z - a|) at the pole
    grid = np.zeros(inside.shape)
    grid[inside] = spla.spsolve(lap, rhs)
    g = RegularGridInterpolator((xs, ys), grid, bounds_error=False, fill_value=0.0)
    pts = []
    for hole in holes:
        line = LineString(hole.coords)
        s = np.linspace(0.0, line.length, max(8, int(line.length / (h / 2))))
        pts.append(shapely.get_coordinates(shapely.line_interpolate_point(line, s)))
    p = np.concatenate(pts)
    vals_at = g(p)
    m = int(np.argmin(vals_at))
    return float(vals_at[m]), complex(p[m, 0], p[m, 1])


def bottleneck(poly: Polygon, levels: int = 28) -> tuple[float, complex]:
    """A-priori crowding of regions reached only through narrow passages: ``(q, where)``.

    A region of the free space joined to the rest only through a passage of width ``w`` and
    length ``L`` has harmonic measure about ``exp(-pi L / w)`` seen from the other side (Ahlfors'
    distortion theorem; Garnett & Marshall, "Harmonic Measure", CUP 2005, ch. IV.6), so one
    conformal map crowds it like a channel of that ``L / w`` -- a SLAM speck 6 cm from a sofa
    cut 7.9 m^2 of a studio off this way, and its single map failed after 7.5 minutes.  Such
    passages are what an opening removes: for half-widths ``d = r 2^(-k/4)`` (``r``: the largest
    inscribed radius) the free space is eroded by ``d``; where that splits it into regions at
    least ``2 d`` wide, the pieces of ``poly`` outside the regions dilated back are passages
    narrower than ``2 d``.  A region's way out is its shortest one: over the pieces it
    touches, the distance from its contact to another region's contact, ``L``; ``q = L / (2 d)``
    bounds ``L / w`` from below.  Returns the largest ``q`` over the regions but the largest
    one (0 if nothing splits) and the middle of that way.  A long corridor with doors all
    along it gives short ways (its rooms are not behind it), and a narrow gap *between* two
    regions that stay connected elsewhere (two near-touching obstacles) gives none.
    """
    r = inscribed(poly)[1]
    best, where = 0.0, complex(np.nan, np.nan)
    for k in range(1, levels + 1):
        d = r * 2.0 ** (-k / 4)
        # regions at least twice as wide as the passage (narrower ones are part of it)
        regions = [p for p in _polygons(poly.buffer(-d)) if p.area >= (2 * d) ** 2]
        if len(regions) < 2:
            continue
        grown = [p.buffer(d * (1 + 1e-6)) for p in regions]
        rest = poly.difference(shapely.union_all(grown))
        way = np.full(len(regions), np.inf)  # each region's shortest way to another
        mid = np.full(len(regions), complex(np.nan, np.nan))
        for piece in _polygons(rest):
            edge = piece.boundary
            touch = {i: edge.intersection(g) for i, g in enumerate(grown) if edge.intersects(g)}
            for a, ca in touch.items():
                for b, cb in touch.items():
                    if a != b and not ca.is_empty and not cb.is_empty:
                        length = float(ca.distance(cb))
                        if length < way[a]:
                            pa, pb = nearest_points(ca, cb)
                            way[a], mid[a] = length, complex(pa.x + pb.x, pa.y + pb.y) / 2
        main = int(np.argmax([p.area for p in regions]))
        way[main] = 0.0  # crowding is of the regions behind, seen from the main one
        finite = np.isfinite(way)
        if finite.any():
            i = int(np.argmax(np.where(finite, way, -1.0)))
            q = way[i] / (2 * d)
            if q > best:
                best, where = float(q), complex(mid[i])
    return float(best), where


def elongation(poly: Polygon) -> float:
    """A-priori crowding indicator ``area / (2 r)^2`` (``r``: largest inscribed radius).

    It is ``L/w`` for an ``L x w`` rectangle, about 1 for a square or a disk; the map of a
    channel of this elongation contracts like ``exp(-pi L/w)`` (docs/METHOD.md section 6).
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
class Overlap:
    """Two cells' common region: its deepest point ``point`` (pole of inaccessibility of the
    intersection, walls included) and that depth."""

    a: int
    b: int
    point: complex
    depth: float


def _links(cells: tuple[Cell, ...]) -> tuple[Overlap, ...]:
    """Every pair of intersecting cells (``a < b``) with its overlap's deepest point."""
    tree = shapely.STRtree([c.polygon for c in cells])
    a, b = tree.query([c.polygon for c in cells], predicate="intersects")
    out: list[Overlap] = []
    for i, j in zip(a.tolist(), b.tolist(), strict=True):
        if i >= j:
            continue
        parts = _polygons(cells[i].polygon.intersection(cells[j].polygon))
        best = max((inscribed(p) for p in parts), key=lambda t: t[1], default=None)
        if best is not None and best[1] > 0:
            out.append(Overlap(i, j, best[0], best[1]))
    return tuple(out)


@dataclass(frozen=True)
class Decomposition:
    """Cells covering a workspace's free space, with the parameters that made them.

    ``margin``: the depth a local goal needs inside an overlap (given, or derived from
    :attr:`passage`); the cell graph links two cells whose overlap is at least that deep.
    """

    workspace: Workspace
    cells: tuple[Cell, ...]
    tile: float
    overlap: float
    margin: float
    max_ratio: float
    max_ratio_holes: float
    max_obstacles: int
    split: frozenset[Tile] = field(default_factory=frozenset)
    #: Regions of the free space the cells leave out (:func:`decompose`): each reached from
    #: the rest only through a channel narrower than the cleaning's opening at the smallest
    #: tile (a SLAM map's one-cell strip along the image border), so no overlap links its
    #: cells to the others; the atlas does not cover them (:meth:`uncovered_area` counts them).
    dropped: tuple[Polygon, ...] = ()

    def uncovered_area(self) -> float:
        """Area of the free space outside every cell (0 up to rounding when covered)."""
        union = shapely.union_all([c.polygon for c in self.cells])
        return float(self.workspace.polygon.difference(union).area)

    @cached_property
    def centres(self) -> np.ndarray:
        """Each cell's deepest point (pole of inaccessibility; computed once: every goal's
        plan uses them)."""
        return np.array([inscribed(c.polygon)[0] for c in self.cells], dtype=np.complex128)

    @cached_property
    def keys(self) -> tuple[str, ...]:
        """The cells' workspaces' content hashes (computed once: every partial revision of a
        progressive atlas's round shares the decomposition, and hashing every cell per
        revision and robot took 0.7 s of the depot's first round)."""
        return tuple(c.workspace.content_hash for c in self.cells)

    @cached_property
    def touching(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Every ordered pair ``(i, j)`` of intersecting cells, ``i == j`` included (computed
        once: every goal's switching order is made from it)."""
        polys = [c.polygon for c in self.cells]
        a, b = shapely.STRtree(polys).query(polys, predicate="intersects")
        return np.asarray(a, dtype=np.intp), np.asarray(b, dtype=np.intp)

    @cached_property
    def _shapes(self) -> tuple[NDArray[np.object_], NDArray[np.object_], NDArray[np.bool_]]:
        polys = np.array([c.polygon for c in self.cells], dtype=object)
        cuts = np.array([c.cut for c in self.cells], dtype=object)
        shapely.prepare(polys)
        return polys, cuts, np.array([c.cut.is_empty for c in self.cells], dtype=bool)

    def depths(self, z: complex) -> NDArray[np.float64]:
        """:meth:`Cell.depth` of the point ``z`` in every cell at once (shape (cells,)):
        the distance to the cell's cut edges where ``z`` lies inside it, ``-inf`` outside."""
        polys, cuts, empty = self._shapes
        pt = shapely.points(complex(z).real, complex(z).imag)
        inside = np.asarray(shapely.contains(polys, pt), dtype=bool)
        d = np.full(len(self.cells), np.inf)
        if not empty.all():
            d[~empty] = shapely.distance(cuts[~empty], pt)
        return np.where(inside, d, -np.inf)

    @cached_property
    def links(self) -> tuple[Overlap, ...]:
        """Every pair of overlapping cells, however thin the overlap (computed once)."""
        return _links(self.cells)

    @cached_property
    def passage(self) -> Overlap | None:
        """The thinnest overlap the cell graph cannot do without (None for a single cell).

        The largest depth ``d`` such that the overlaps at least ``d`` deep connect every
        cell is the bottleneck of a maximum spanning tree (Kruskal on depths, descending);
        this is its overlap: the narrowest passage (or cut) every margin must fit.

        Raises
        ------
        PassageError
            if some cells share no overlap with the rest at all (names the gap between them).
        """
        n = len(self.cells)
        parent = list(range(n))

        def root(i: int) -> int:
            return _root(parent, i)

        groups, last = n, None
        for o in sorted(self.links, key=lambda o: -o.depth):
            ra, rb = root(o.a), root(o.b)
            if ra != rb:
                parent[ra] = rb
                groups, last = groups - 1, o
                if groups == 1:
                    return last
        if n <= 1:
            return None
        # disconnected: name the gap between the component of cell 0 and the rest
        first = [i for i in range(n) if root(i) == root(0)]
        rest = [i for i in range(n) if root(i) != root(0)]
        a = shapely.union_all([self.cells[i].polygon for i in first])
        b = shapely.union_all([self.cells[i].polygon for i in rest])
        line = shapely.shortest_line(a, b)
        mid = line.interpolate(0.5, normalized=True)
        z = complex(mid.x, mid.y)
        w = 2 * float(self.workspace.clearance(np.array([z]))[0])
        ia = min(first, key=lambda i: self.cells[i].polygon.distance(mid))
        ib = min(rest, key=lambda i: self.cells[i].polygon.distance(mid))
        raise PassageError(
            f"atlas cells {ia} and {ib} do not overlap near {fmt_point(z)}, where the free "
            f"space is {w:.3g} m wide: cells {sorted(rest)[:8]} are cut off from the rest "
            f"(tile {self.tile:.3g} m; a smaller --tile may help)",
            point=z, width=w, depth=0.0, cells=(ia, ib), margin=self.margin,
        )  # fmt: skip


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
    grid: float,
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
        if cut.is_empty:  # no cut (one tile holds it all): nothing to clean
            opened = comp
        else:
            near = cut.buffer(2 * rho, join_style="mitre", cap_style="square")
            thin = comp.difference(opened).difference(near)
            # on a grid far below the walls' tolerance (1e-9 of the size): copies of one edge
            # an ulp apart leave a slit in the union (measured: a cell's outer ring running up
            # a wall face and back, rejected by Workspace as doubling back on itself); the
            # grid is dropped after (later overlays would round to it: the cells rebuilt from
            # an index, without it, would give other overlaps)
            opened = shapely.set_precision(shapely.set_precision(opened.union(thin), grid), 0.0)
            opened = _unpinched(opened, comp, grid, overlap / 8)
        # a piece that does not reach into the core lies in the neighbours' cores, which
        # cover it deeply: drop it (measured: a 4.4 x 18 cm sliver along a corridor wall whose
        # solve missed 1e-6)
        out.extend(
            p
            for p in _polygons(opened)
            if p.area >= min_area and p.intersection(core_box).area >= min_area
        )
    return out


def _pinched_holes(poly: Polygon) -> list[int]:
    """The holes of ``poly`` that touch its outer ring or another hole (shapely allows a
    hole to touch a ring at one point; a :class:`Workspace` needs its obstacles strictly
    inside and pairwise disjoint)."""
    holes = [shapely.LinearRing(h.coords) for h in poly.interiors]
    if not holes:
        return []
    rings = np.array([shapely.LinearRing(poly.exterior.coords), *holes], dtype=object)
    tree = shapely.STRtree(rings)
    a, b = tree.query(rings[1:], predicate="intersects")
    return sorted({int(i) for i, j in zip(a.tolist(), b.tolist(), strict=True) if j != i + 1})


def _unpinched(opened: BaseGeometry, comp: Polygon, grid: float, notch: float) -> BaseGeometry:
    """``opened`` with what the cleaning dropped inside a pinched hole given back.

    The opening's boundary can meet the cut edge (or another obstacle's dropped sliver) at a
    single point: the sliver dropped between an obstacle and the cut then touches the cell's
    outer ring there, and the obstacle with it becomes a hole touching the outer boundary,
    which no :class:`Workspace` (hence no chart) accepts.  Measured on nav2's warehouse
    (occupancy grid of 3 cm cells): an obstacle's 45-degree chamfer, grown by the mitred
    dilation, reached the cut exactly at another of its corners (-7.15, 8.36), and the
    unshrunk map's atlas failed to decompose.  The part of the component ``comp`` inside such
    a hole's ring (the obstacle's dropped sliver; the obstacle itself is no part of ``comp``)
    is given back: the obstacle is then the component's hole, strictly inside it, with the
    channel to the cut the cleaning would have removed (it costs the chart accuracy, not its
    validity).  A contact giving back cannot remove (the snapped cut through an obstacle's
    lone vertex, the cleaned boundary through an obstacle's corner) gets a notch of
    half-side ``notch`` there instead.
    """
    out: list[Polygon] = []
    parts_in = _polygons(opened)
    if not any(_pinched_holes(p) for p in parts_in):
        return opened
    for p in parts_in:
        for _ in range(4):  # a given-back sliver may meet another; a few rounds settle it
            bad = _pinched_holes(p)
            if not bad:
                break
            back = shapely.union_all([Polygon(p.interiors[i].coords) for i in bad])
            grown = shapely.set_precision(p.union(back.intersection(comp)), grid)
            parts = _polygons(shapely.set_precision(grown, 0.0))
            p = max(parts, key=lambda q: q.area)  # one piece: the slivers adjoin it
        bad = _pinched_holes(p)
        if bad:
            # giving back did not help: the snapped cut runs through an obstacle's lone vertex,
            # or the boundary of what the cleaning dropped does (measured: a one-cell
            # obstacle's corner on the warehouse). The contact lies within 3/4 of the band from
            # the cut, in a neighbouring tile's core, which covers it: a notch of half-side
            # ``notch`` there joins the obstacle to the boundary (a piece it swallows goes)
            rings = [shapely.LinearRing(p.exterior.coords)]
            rings += [shapely.LinearRing(h.coords) for h in p.interiors]
            hit = shapely.union_all(
                [rings[i + 1].intersection(r) for i in bad for r in rings if r is not rings[i + 1]]
            )
            cut_out = shapely.union_all(
                [shapely.box(q.x - notch, q.y - notch, q.x + notch, q.y + notch)
                 for q in shapely.get_parts(shapely.points(shapely.get_coordinates(hit)))]
            )  # fmt: skip
            parts = _polygons(shapely.set_precision(p.difference(cut_out), grid))
            if not parts:  # a speck within the notch (measured: 12 x 30 cm on the warehouse)
                continue
            p = max(parts, key=lambda q: q.area)
            if _pinched_holes(p):
                raise WorkspaceError(
                    f"atlas cell near {fmt_point(complex(hit.centroid.x, hit.centroid.y))}: an "
                    "obstacle touches the cell's boundary at a point after cleaning"
                )
        out.append(shapely.set_precision(p, 0.0))
    return shapely.union_all(out) if len(out) != 1 else out[0]  # empty: no piece


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
    fine: Iterable[complex] = (),
    fine_vertices: int = 24,
    on_pass: Callable[[Decomposition, float], None] | None = None,
    pause: Callable[[], None] | None = None,
) -> Decomposition:
    """Overlapping cells covering the free space of ``ws`` (module docstring).

    Parameters
    ----------
    tile : side of the initial tiles (default ``6 r``, ``r`` the free space's largest
        inscribed radius).
    overlap : enlargement of a tile on each side as a fraction of its side (at least
        ``2 margin``; snapping keeps 3/4 of it): neighbouring cells overlap in a band at
        least ``3 margin`` wide.
    margin : the depth a local goal needs inside an overlap (the robot is a point here: a
        robot's radius is taken off the free space before, ``confnav.maps.footprint.inflate``).
        Default: derived from the passages, ``min(r / 10, AUTO_MARGIN_FRACTION * depth)`` with
        ``depth`` that of :attr:`Decomposition.passage`, the decomposition redone with it
        (the band floor ``2 margin`` and the smallest piece ``margin^2 / 2`` depend on it).
    max_ratio, max_ratio_holes, max_obstacles : a tile whose pieces exceed either is split
        into four.  Cells with obstacles get the tighter elongation bound: an obstacle at the
        far end of a cell of elongation q, seen from the anchor in the middle, maps to a
        circle within ~exp(-pi q / 2) of the unit circle (q = 3.75: 3e-3, too close for the
        harmonic navigation function's series; measured in tests/test_atlas.py's corridor).
    min_tile : smallest tile side (default ``tile / 16``).
    split : core tiles to split regardless (used when a cell's solve failed), even below
        ``min_tile`` (down to a side of ``FORCED_MIN_MARGINS * margin``).
    fine, fine_vertices : points (robots' starts) whose cells should be quick to solve: a
        tile whose core holds one and whose piece holding it has more than
        ``fine_vertices`` vertices is split, down to ``min_tile`` (a chart's solve time grows
        with its corners: measured on the nav2 warehouse shrunk by 0.32 m, cells of 55-129
        vertices took 3.5-10 s at tol 1e-2 against a median of 0.45 s; a progressive atlas
        solves the start cells first, docs/SLAM.md "Progressive atlas").
    on_pass : called with a pass's decomposition and the margin of the next pass when the
        derived margin is redone (``auto``); a progressive atlas starts its start cells'
        solves from it (a cell the next pass leaves unchanged has the same content hash).
    pause : called before each tile of the quadtree is cut (a few ms of work apart); the
        caller may block in it to yield the CPU to more urgent work (the transform service
        holds a base atlas's decomposition there while a footprint atlas that robots wait
        for is cut and solved, docs/SLAM.md "Round 5"). The result does not depend on it.

    Raises
    ------
    PassageError
        if the cells do not all connect through overlaps at least ``margin`` deep: a given
        margin too large for a passage, or a passage too thin for any (names its location,
        width and cells).
    """
    free = ws.polygon
    r = inscribed(free)[1]
    tile = float(tile) if tile is not None else 6.0 * r
    auto = margin is None
    margin = 0.1 * r if margin is None else float(margin)
    min_tile = float(min_tile) if min_tile is not None else tile / 16
    if not (tile > 0 and margin > 0 and 0 < overlap <= 1 and min_tile > 0):
        raise WorkspaceError(
            f"atlas needs tile > 0, margin > 0 and overlap in (0, 1] "
            f"(tile {tile:g}, overlap {overlap:g}, margin {margin:g})"
        )
    params = _Params(
        tile, overlap, max_ratio, max_ratio_holes, max_obstacles, min_tile,
        tuple(complex(z) for z in fine), int(fine_vertices), pause,
    )  # fmt: skip
    forced = frozenset(split)
    floor = 1e-3 * 0.1 * r  # below this an automatic margin is a hairline, not a passage
    for _ in range(4):
        dec = _connected(ws, params, margin, forced, floor / AUTO_MARGIN_FRACTION)
        thin = dec.passage
        if thin is None or thin.depth >= margin:
            return dec
        if not auto or AUTO_MARGIN_FRACTION * thin.depth < floor:
            break
        margin = AUTO_MARGIN_FRACTION * thin.depth
        if on_pass is not None:
            on_pass(dec, margin)
    assert thin is not None
    z = thin.point
    w = 2 * float(ws.clearance(np.array([z]))[0])
    hint = (
        f"give a margin below {thin.depth:.3g} m, or none (derived from the passages)"
        if not auto
        else "no margin fits it; widen the passage or give a smaller --tile"
    )
    raise PassageError(
        f"atlas margin {margin:.3g} m does not fit the passage at {fmt_point(z)}, {w:.3g} m "
        f"wide: cells {thin.a} and {thin.b} overlap there only {2 * thin.depth:.3g} m across "
        f"and a local goal needs a disk of radius margin inside the overlap; {hint}",
        point=z, width=w, depth=thin.depth, cells=(thin.a, thin.b), margin=margin,
    )  # fmt: skip


@dataclass(frozen=True)
class _Params:
    """The decomposition's parameters other than the margin (see :func:`decompose`)."""

    tile: float
    overlap: float
    max_ratio: float
    max_ratio_holes: float
    max_obstacles: int
    min_tile: float
    fine: tuple[complex, ...] = ()
    fine_vertices: int = 24
    pause: Callable[[], None] | None = None  # see decompose's ``pause``


def _too_many_corners(pieces: list[Polygon], core: Tile, p: _Params) -> bool:
    """A piece holding one of ``p.fine`` (in the tile's core) has more than
    ``p.fine_vertices`` vertices (:func:`decompose`'s ``fine``)."""
    pts = [z for z in p.fine if core[0] <= z.real < core[2] and core[1] <= z.imag < core[3]]
    if not pts:
        return False
    xy = shapely.points([z.real for z in pts], [z.imag for z in pts])
    for piece in pieces:
        if np.any(shapely.contains(piece, xy)):
            n = len(piece.exterior.coords) - 1 + sum(len(h.coords) - 1 for h in piece.interiors)
            if n > p.fine_vertices:
                return True
    return False


def _root(parent: list[int], i: int) -> int:
    """The root of ``i`` in the union-find forest ``parent`` (path halving; Tarjan and van
    Leeuwen, "Worst-case analysis of set union algorithms", J. ACM 31, 1984)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _components(dec: Decomposition, hairline: float = 0.0) -> list[list[int]]:
    """The cells of ``dec`` grouped by the overlaps linking them (:attr:`Decomposition.links`)
    at least ``hairline`` deep, the group of the largest area first."""
    n = len(dec.cells)
    parent = list(range(n))

    def root(i: int) -> int:
        return _root(parent, i)

    for o in dec.links:
        if o.depth >= hairline:
            parent[root(o.a)] = root(o.b)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    area = np.array([c.polygon.area for c in dec.cells])
    return sorted(groups.values(), key=lambda g: -float(area[g].sum()))


def _connected(
    ws: Workspace, p: _Params, margin: float, forced: frozenset[Tile], hairline: float = 0.0
) -> Decomposition:
    """:func:`_decompose` with every cell linked to the others through an overlap.

    A cell without any overlap with the rest (its group, :func:`_components`) is a piece of
    the free space reached only through a channel the cleaning of :func:`_pieces` removed
    where it crosses a cut: narrower than the opening, ``3/4`` of the band.  The band
    shrinks with the tile, so the tiles of the cut-off group and of the main group's cells
    nearest it are split (down to ``min_tile`` and ``FORCED_MIN_MARGINS`` margins) and the
    decomposition redone: a channel as
    wide as the opening at ``min_tile`` is kept.  What stays cut off at ``min_tile`` is a
    hairline channel (measured: nav2's depot, its one-cell strip of free space along the
    image border, 5 cm wide between the border and the outer wall, with a 0.11 m^2 pocket
    behind it, raised :class:`PassageError` and the unshrunk map had no atlas): its cells
    are left out (:attr:`Decomposition.dropped`) and the atlas covers the rest.

    An overlap less than ``hairline`` deep links nothing here (:func:`decompose` passes the
    depth below which the automatic margin, half of it, would be a hairline): a group of
    cells hanging on it alone is cut off too (measured: nav2's warehouse, unshrunk, after
    its failed charts' tiles were split: two cells linked only across a gap of 1.35 mm
    between two imported obstacles, and no margin fitted it).
    """
    grow: frozenset[Tile] = frozenset()
    while True:
        dec = _decompose(ws, p, margin, forced, grow)
        groups = _components(dec, hairline)
        if len(groups) <= 1:
            return dec
        main = shapely.union_all([dec.cells[i].polygon for i in groups[0]])
        main_tree = shapely.STRtree([dec.cells[i].polygon for i in groups[0]])
        more: set[Tile] = set()
        for g in groups[1:]:
            more |= {dec.cells[i].tile for i in g}
            near = main_tree.nearest(shapely.union_all([dec.cells[i].polygon for i in g]))
            more.add(dec.cells[groups[0][int(near)]].tile)
        # not below 2 margins either: a core smaller than the least piece (margin^2 / 2)
        # keeps no piece, and the cells there would vanish instead of linking
        floor = max(p.min_tile, FORCED_MIN_MARGINS * margin)
        more = {t for t in more if (t[2] - t[0]) / 2 >= floor - 1e-12} - grow
        if not more:
            break
        grow = grow | more
    keep = sorted(groups[0])
    new = {old: k for k, old in enumerate(keep)}
    cells = tuple(replace(dec.cells[i], index=new[i]) for i in keep)
    dropped = tuple(
        _polygons(shapely.union_all([dec.cells[i].polygon for i in g]).difference(main))
        for g in groups[1:]
    )
    out = replace(dec, cells=cells, dropped=tuple(q for parts in dropped for q in parts))
    # the links, re-indexed (computed once: the passage needs them)
    out.__dict__["links"] = tuple(
        Overlap(new[o.a], new[o.b], o.point, o.depth)
        for o in dec.links
        if o.a in new and o.b in new
    )
    return out


def _decompose(
    ws: Workspace,
    p: _Params,
    margin: float,
    forced: frozenset[Tile],
    grow: frozenset[Tile] = frozenset(),
) -> Decomposition:
    """The quadtree of :func:`decompose` for one margin (module docstring, steps 1-4);
    ``grow``: tiles split once more regardless (:func:`_connected` keeps them at least
    ``min_tile`` and ``FORCED_MIN_MARGINS`` margins wide)."""
    free = ws.polygon
    tile, overlap, min_tile = p.tile, p.overlap, p.min_tile
    min_area = 0.5 * margin**2
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
        if p.pause is not None:
            p.pause()
        core = todo.pop(0)
        side = core[2] - core[0]
        band = max(overlap * side, 2 * margin)
        pieces = _pieces(free, walls, vertices, core, band, min_area, 1e-10 * scale)
        ratios = [elongation(piece) for piece in pieces]
        bad = any(
            q > (p.max_ratio if not piece.interiors else p.max_ratio_holes)
            or len(piece.interiors) > p.max_obstacles
            for piece, q in zip(pieces, ratios, strict=True)
        )
        # a tile whose chart failed (``forced``) splits below ``min_tile``: the a-priori tests
        # miss a channel between two obstacles (a SLAM speck beside a sofa), which only a
        # cell cut across it maps well; down to a side of 2 margin, where the cell's extent
        # (side + 2 band, band >= 2 margin) is about 1.5 passage widths (margin <= w / 4)
        floor = FORCED_MIN_MARGINS * margin if core in forced else min_tile
        if not bad and p.fine and side / 2 >= min_tile - 1e-12:
            bad = _too_many_corners(pieces, core, p)
        bad = bad or core in grow
        if (bad or core in forced) and side / 2 >= floor - 1e-12:
            cx, cy = (core[0] + core[2]) / 2, (core[1] + core[3]) / 2
            todo += [
                (core[0], core[1], cx, cy),
                (cx, core[1], core[2], cy),
                (core[0], cy, cx, core[3]),
                (cx, cy, core[2], core[3]),
            ]
            continue
        polys += [(piece, core, q) for piece, q in zip(pieces, ratios, strict=True)]
    cells: list[Cell] = []
    for poly, core, q in polys:
        cut = poly.boundary.difference(walls)
        cells.append(Cell(len(cells), poly, _cell_workspace(poly, scale), cut, core, q))
    return Decomposition(
        ws, tuple(cells), tile, overlap, margin, p.max_ratio, p.max_ratio_holes, p.max_obstacles,
        forced,
    )  # fmt: skip
