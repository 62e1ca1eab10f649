"""A roadmap of the free space for fleet coordination: nodes a robot's disk apart, edges along
free straight segments, all-pairs path lengths.

The nodes live in the space the controllers steer in: the workspace shrunk by the robots'
filter radius ``rho`` (a unicycle: ``r + d`` around its look-ahead point), so a node is a
place where a robot's disk fits.  Two robots standing on two different nodes do not touch
when the nodes are at least ``2 rho`` apart: :func:`build_roadmap` picks nodes greedily from a
fine grid, the points of largest clearance first (so the centre lines of aisles are taken
before their sides), keeping each new node at least ``spacing`` from the ones taken -- a
Poisson-disk sample (Bridson, "Fast Poisson disk sampling in arbitrary dimensions", SIGGRAPH
2007 sketches, for the spacing rule; the clearance order is the medial-axis preference of
probabilistic roadmaps on the medial axis, Wilmarth, Amato and Stiller, "MAPRM: a
probabilistic roadmap planner with sampling on the medial axis of the free space", ICRA
1999).  Edges are the Delaunay edges of the nodes (planar: no two edges cross) whose segment
keeps ``min_clearance`` from the walls (exact distances, sampled every ``step`` m: the
clearance is 1-Lipschitz, so it is at least the sampled minimum less ``step / 2``) and no
longer than ``max_edge``; an edge that passes nearer than ``pass_gap`` to a third node is
dropped (a robot on it would brush a robot standing there).

All geometry is exact (the workspace's polygons); the conformal map is not involved here.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra, shortest_path
from scipy.spatial import Delaunay, cKDTree

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.types import CArray, FArray

__all__ = ["Roadmap", "build_roadmap", "free_path", "passage_widths", "segment_segment_distance"]

#: the sampling step (m) of :func:`segment_clearance`
SEGMENT_STEP = 0.02
#: the edge clearance (m) of :func:`_tight_core`, for mazes whose pinch points are nearer the
#: walls than the default comfort margin (at least the sampling bound of segment_clearance)
TIGHT_EDGE_CLEARANCE = 0.01
#: its candidate grid step (m): pinch points and short lanes need candidates on their axes
TIGHT_GRID = 0.02
#: the most candidates of that grid (bounding box / step^2); beyond, the caller's grid
TIGHT_MAX_CANDIDATES = 400_000


@dataclass(frozen=True)
class Roadmap:
    """Nodes (complex, m), undirected edges ``edges[e] = (u, v)`` with ``u < v``, neighbour
    lists, the all-pairs shortest path lengths ``dist`` (m, ``inf`` between components) and
    the parameters it was built with."""

    nodes: CArray
    edges: NDArray[np.intp]
    neighbours: tuple[NDArray[np.intp], ...]
    dist: FArray
    spacing: float
    min_clearance: float

    @property
    def size(self) -> int:
        return int(self.nodes.size)

    def edge_index(self) -> dict[tuple[int, int], int]:
        """``(u, v) -> e`` for both orders."""
        out: dict[tuple[int, int], int] = {}
        for e, (u, v) in enumerate(self.edges.tolist()):
            out[(u, v)] = out[(v, u)] = e
        return out

    def components(self) -> NDArray[np.intp]:
        """Connected component label of every node."""
        return np.asarray(_components(self.nodes.size, self.edges)[1])


def _components(n: int, edges: NDArray[np.intp]) -> tuple[int, NDArray[np.intp]]:
    g = csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    k, lab = connected_components(g, directed=False)
    return int(k), np.asarray(lab, dtype=np.intp)


def segment_segment_distance(a0: ArrayLike, a1: ArrayLike, b0: ArrayLike, b1: ArrayLike) -> FArray:
    """Distance between segments ``a0..a1`` and ``b0..b1`` (complex, broadcast): 0 where they
    cross, else the least of the four endpoint-to-segment distances (two segments in the
    plane that do not cross are closest at an endpoint of one of them)."""
    p0, p1 = np.broadcast_arrays(np.asarray(a0, np.complex128), np.asarray(a1, np.complex128))
    q0, q1 = np.broadcast_arrays(np.asarray(b0, np.complex128), np.asarray(b1, np.complex128))
    p0, p1, q0, q1 = np.broadcast_arrays(p0, p1, q0, q1)

    def pt_seg(z: CArray, a: CArray, b: CArray) -> FArray:
        d = b - a
        dd = np.abs(d) ** 2
        t = np.where(dd > 0, ((z - a) * np.conj(d)).real / np.where(dd > 0, dd, 1.0), 0.0)
        return np.asarray(np.abs(z - (a + np.clip(t, 0.0, 1.0) * d)))

    def cross(u: CArray, v: CArray) -> FArray:
        return np.asarray((np.conj(u) * v).imag)

    r, s = p1 - p0, q1 - q0
    o1 = cross(r, q0 - p0)
    o2 = cross(r, q1 - p0)
    o3 = cross(s, p0 - q0)
    o4 = cross(s, p1 - q0)
    hit = (o1 * o2 < 0) & (o3 * o4 < 0)
    m = np.minimum(
        np.minimum(pt_seg(p0, q0, q1), pt_seg(p1, q0, q1)),
        np.minimum(pt_seg(q0, p0, p1), pt_seg(q1, p0, p1)),
    )
    return np.asarray(np.where(hit, 0.0, m))


def segment_clearance(
    ws: Workspace, a: ArrayLike, b: ArrayLike, step: float = SEGMENT_STEP
) -> FArray:
    """A lower bound of the wall clearance along each segment ``a[i]..b[i]``: the least exact
    clearance at points ``step`` apart less ``step / 2`` (the clearance is 1-Lipschitz)."""
    aa = np.atleast_1d(np.asarray(a, dtype=np.complex128))
    bb = np.atleast_1d(np.asarray(b, dtype=np.complex128))
    k = max(int(np.ceil(float(np.abs(bb - aa).max(initial=0.0)) / step)), 1)
    t = np.linspace(0.0, 1.0, k + 1)
    pts = aa[:, None] + (bb - aa)[:, None] * t[None, :]
    inside = np.asarray(ws.contains(pts.ravel())).reshape(pts.shape)
    c = np.asarray(ws.clearance(pts.ravel()), dtype=np.float64).reshape(pts.shape)
    c = np.where(inside, c, -1.0)
    seg_len = np.abs(bb - aa)
    return np.asarray(c.min(axis=1) - 0.5 * seg_len / k)


def build_roadmap(
    workspace: Workspace,
    spacing: float,
    *,
    min_clearance: float = 0.09,
    edge_clearance: float | None = None,
    max_edge: float | None = None,
    pass_gap: float | None = None,
    grid: float = 0.05,
    prune_leaves: bool = False,
) -> Roadmap:
    """The roadmap of ``workspace`` (the free space of the robots' centres, i.e. already
    shrunk by their filter radius) with nodes ``spacing`` m apart (module docstring).

    ``edge_clearance``: least wall clearance along an edge (default ``min_clearance``);
    ``max_edge``: longest edge (default ``1.6 spacing``); ``pass_gap``: least distance from
    an edge to a third node (default ``0.75 spacing``); ``grid``: the candidate grid's step;
    ``prune_leaves``: nodes of degree 0 or 1 are removed, repeatedly (the graph's 2-core:
    no dead-end branches, where robots could only pass each other by backing out); where that
    keeps less than half of the nodes, the core of a tighter roadmap if it keeps more
    (:func:`_tight_core`).
    Raises :class:`~confnav.errors.NavigationError` when no point has ``min_clearance``.
    """
    if not (spacing > 0 and grid > 0 and min_clearance >= 0):
        raise NavigationError(
            f"spacing > 0, grid > 0, min_clearance >= 0 needed, got {spacing}, {grid}, "
            f"{min_clearance}"
        )
    max_edge = 1.6 * spacing if max_edge is None else float(max_edge)
    pass_gap = 0.75 * spacing if pass_gap is None else float(pass_gap)
    nodes = _sample_nodes(workspace, spacing, min_clearance, grid)
    ec = min_clearance if edge_clearance is None else float(edge_clearance)
    edges = _free_edges(workspace, nodes, max_edge, ec, pass_gap)
    n = nodes.size
    if prune_leaves:
        nodes, edges = _two_core(nodes, edges)
        if 2 * nodes.size < n and ec > TIGHT_EDGE_CLEARANCE:
            nodes, edges = _tight_core(workspace, spacing, min_clearance, grid, max_edge,
                                       pass_gap, (nodes, edges))  # fmt: skip
        n = nodes.size
    nb: list[list[int]] = [[] for _ in range(n)]
    for u, v in edges.tolist():
        nb[u].append(v)
        nb[v].append(u)
    w = np.abs(nodes[edges[:, 1]] - nodes[edges[:, 0]]) if len(edges) else np.zeros(0)
    g = csr_matrix((w, (edges[:, 0], edges[:, 1])), shape=(n, n))
    dist = np.asarray(shortest_path(g, method="D", directed=False), dtype=np.float64)
    return Roadmap(
        nodes=nodes,
        edges=edges,
        neighbours=tuple(np.array(x, dtype=np.intp) for x in nb),
        dist=dist,
        spacing=float(spacing),
        min_clearance=float(min_clearance),
    )


def _sample_nodes(ws: Workspace, spacing: float, min_clearance: float, grid: float) -> CArray:
    """Grid points with ``min_clearance``, largest clearance first, kept ``spacing`` apart."""
    x0, y0, x1, y1 = ws.bounds
    # the grid anchored at the bounds' corner: axis-aligned passages of a width that is a
    # multiple of the step get candidates on their centre lines
    xs = np.arange(x0, x1 + 0.5 * grid, grid)
    ys = np.arange(y0, y1 + 0.5 * grid, grid)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = (gx + 1j * gy).ravel()
    inside = np.asarray(ws.contains(z), dtype=bool)
    z = z[inside]
    c = np.asarray(ws.clearance(z), dtype=np.float64)
    keep = c >= min_clearance - 1e-9
    z, c = z[keep], c[keep]
    if z.size == 0:
        raise NavigationError(f"no point of the ws has clearance {min_clearance} m")
    # largest clearance first; ties by position (deterministic)
    order = np.lexsort((z.imag, z.real, -np.round(c, 9)))
    cell = spacing / np.sqrt(2.0)  # at most one node per bucket
    buckets: dict[tuple[int, int], complex] = {}
    chosen: list[complex] = []
    for q in z[order].tolist():
        bx, by = int(np.floor(q.real / cell)), int(np.floor(q.imag / cell))
        ok = True
        for dx in (-2, -1, 0, 1, 2):
            for dy in (-2, -1, 0, 1, 2):
                o = buckets.get((bx + dx, by + dy))
                if o is not None and abs(o - q) < spacing - 1e-9:
                    ok = False
                    break
            if not ok:
                break
        if ok:
            buckets[(bx, by)] = q
            chosen.append(q)
    nodes = np.array(chosen, dtype=np.complex128)
    return nodes


def _free_edges(
    ws: Workspace, nodes: CArray, max_edge: float, ec: float, pass_gap: float
) -> NDArray[np.intp]:
    """Delaunay edges of ``nodes`` no longer than ``max_edge``, ``ec`` from the walls and
    ``pass_gap`` from every other node."""
    n = nodes.size
    if n >= 3:
        tri = Delaunay(np.column_stack([nodes.real, nodes.imag]))
        s = tri.simplices
        cand = np.concatenate([s[:, [0, 1]], s[:, [1, 2]], s[:, [0, 2]]])
        cand = np.unique(np.sort(cand, axis=1), axis=0)
    elif n == 2:
        cand = np.array([[0, 1]], dtype=np.intp)
    else:
        cand = np.zeros((0, 2), dtype=np.intp)
    if cand.size:
        a, b = nodes[cand[:, 0]], nodes[cand[:, 1]]
        ok_len = np.abs(b - a) <= max_edge + 1e-9
        cand, a, b = cand[ok_len], a[ok_len], b[ok_len]
        ok_c = segment_clearance(ws, a, b) >= ec
        cand, a, b = cand[ok_c], a[ok_c], b[ok_c]
        # no third node near the edge
        tree = cKDTree(np.column_stack([nodes.real, nodes.imag]))
        mid = 0.5 * (a + b)
        near = tree.query_ball_point(
            np.column_stack([mid.real, mid.imag]), 0.5 * max_edge + pass_gap
        )
        # every (edge, node near it) pair at once: a node is a segment of length 0
        counts = np.fromiter(map(len, near), dtype=np.intp, count=len(near))
        pe = np.repeat(np.arange(len(cand)), counts)
        pw = np.fromiter(itertools.chain.from_iterable(near), dtype=np.intp, count=pe.size)
        third = (pw != cand[pe, 0]) & (pw != cand[pe, 1])
        pe, pw = pe[third], pw[third]
        dd = segment_segment_distance(nodes[pw], nodes[pw], a[pe], b[pe])
        least = np.full(len(cand), np.inf)
        np.minimum.at(least, pe, dd)
        cand = cand[least >= pass_gap - 1e-9]
    edges = np.asarray(cand, dtype=np.intp).reshape(-1, 2)
    return edges


def _tight_core(
    ws: Workspace,
    spacing: float,
    min_clearance: float,
    grid: float,
    max_edge: float,
    pass_gap: float,
    core: tuple[CArray, NDArray[np.intp]],
) -> tuple[CArray, NDArray[np.intp]]:
    """The 2-core again with edges only :data:`TIGHT_EDGE_CLEARANCE` from the walls and
    candidates on a :data:`TIGHT_GRID` grid (where the free space allows so many), if it
    keeps more nodes than ``core`` (the default core), else ``core``.

    :func:`build_roadmap` asks for it where the default edge clearance leaves less than half
    of the nodes in the core: a maze of single-lane passages with pinch points nearer the
    walls than that comfort margin (the TurtleBot3 sandbox for a 0.32 m filter radius: 13
    nodes, 10 edges, an empty core, so the fleet had no roadmap and two robots met head-on
    in a lane for good).  An edge that clear of the walls is still free: the sampled
    clearance bounds the true one to ``step / 2`` (:func:`segment_clearance`), and the
    controller's safety filter keeps the robots off the walls whatever the law."""
    x0, y0, x1, y1 = ws.bounds
    g = TIGHT_GRID if (x1 - x0) * (y1 - y0) / TIGHT_GRID**2 <= TIGHT_MAX_CANDIDATES else grid
    nodes = _sample_nodes(ws, spacing, min_clearance, min(g, grid))
    edges = _free_edges(ws, nodes, max_edge, TIGHT_EDGE_CLEARANCE, pass_gap)
    tight = _two_core(nodes, edges)
    return tight if tight[0].size > core[0].size else core


def _two_core(nodes: CArray, edges: NDArray[np.intp]) -> tuple[CArray, NDArray[np.intp]]:
    """Nodes of degree <= 1 removed repeatedly; edges renumbered."""
    n = nodes.size
    alive = np.ones(n, dtype=bool)
    while True:
        deg = np.bincount(edges.ravel(), minlength=n)
        leaf = alive & (deg <= 1)
        if not leaf.any():
            break
        alive &= ~leaf
        edges = edges[alive[edges[:, 0]] & alive[edges[:, 1]]]
    new = np.cumsum(alive) - 1
    return nodes[alive], new[edges].astype(np.intp).reshape(-1, 2)


def passage_widths(
    ws: Workspace, roadmap: Roadmap, *, cap: float = 4.0, tol: float = 1e-3, iters: int = 64
) -> FArray:
    """The width of the free space across each roadmap edge: along the line through the
    edge's midpoint perpendicular to it, the free extent on both sides summed (m, at most
    ``2 cap``).  Each side is found by sphere tracing on the exact signed clearance (Hart,
    "Sphere tracing: a geometric method for the antialiased ray tracing of implicit
    surfaces", The Visual Computer 12, 1996): from a point of clearance ``c`` the ray is
    free for ``c`` more, so it steps ``c`` until the clearance is below ``tol``.  In a
    single-lane passage (the edges follow its centre line) this is the passage's width; an
    edge along a wall of a room sees the room across it."""
    e = roadmap.edges
    if not len(e):
        return np.zeros(0)
    a, b = roadmap.nodes[e[:, 0]], roadmap.nodes[e[:, 1]]
    m = 0.5 * (a + b)
    n = 1j * (b - a) / np.maximum(np.abs(b - a), 1e-300)
    width = np.zeros(len(e))
    for sgn in (1.0, -1.0):
        t = np.zeros(len(e))
        live = np.ones(len(e), dtype=bool)
        for _ in range(iters):
            if not live.any():
                break
            c = np.asarray(ws.clearance(m[live] + sgn * n[live] * t[live]), dtype=np.float64)
            t[live] += np.maximum(c, 0.0)
            stop = (c < tol) | (t[live] >= cap)
            live[np.flatnonzero(live)[stop]] = False
        width += np.minimum(t, cap)
    return width


def free_path(
    ws: Workspace,
    a: complex,
    b: complex,
    *,
    step: float = 0.02,
    margin: float = 0.005,
    pad: float = 1.0,
    max_cells: int = 250_000,
) -> CArray | None:
    """The corners of a free polyline from ``a`` to ``b`` (``a`` not included, ``b`` last;
    ``[b]`` where the segment is free), each leg at least ``margin`` from the walls (sampled:
    :func:`segment_clearance`); None if there is none within the grid's reach.

    A shortest path on the 8-neighbour grid of step ``step`` over the points of clearance at
    least ``margin + step / sqrt 2`` (so the straight step between two neighbours is
    ``margin`` clear: the clearance is 1-Lipschitz), Dijkstra (scipy.sparse.csgraph), in the
    box round ``a`` and ``b`` grown by ``pad`` (doubled until a path is found, the box
    covers the workspace, or it would hold more than ``max_cells`` points), then pulled
    tight: from each corner, the farthest grid point of the path in free straight sight
    (string pulling; a polyline no longer than the grid path).  For the fleet's return leg
    round a wall (:meth:`~confnav.navigation.fleet_coord.RoadmapCoordinator.return_way`)."""
    a, b = complex(a), complex(b)
    if segment_clearance(ws, np.array([a]), np.array([b]))[0] >= margin:
        return np.array([b])
    x0, y0, x1, y1 = ws.bounds
    reach = float(pad)
    while True:
        lo = complex(max(min(a.real, b.real) - reach, x0), max(min(a.imag, b.imag) - reach, y0))
        hi = complex(min(max(a.real, b.real) + reach, x1), min(max(a.imag, b.imag) + reach, y1))
        nx = int(np.floor((hi.real - lo.real) / step)) + 1
        ny = int(np.floor((hi.imag - lo.imag) / step)) + 1
        if nx * ny > max_cells:
            return None
        path = _grid_path(ws, a, b, lo, nx, ny, step, margin)
        whole = lo.real <= x0 and lo.imag <= y0 and hi.real >= x1 and hi.imag >= y1
        if path is not None or whole:
            break
        reach *= 2.0
    if path is None:
        return None
    return _pull_tight(ws, a, np.concatenate([path, [b]]), margin)


def _grid_path(
    ws: Workspace, a: complex, b: complex, lo: complex, nx: int, ny: int, step: float,
    margin: float,
) -> CArray | None:  # fmt: skip
    """:func:`free_path`'s grid path from the free grid point nearest ``a`` that ``a`` sees
    to the one nearest ``b`` that ``b`` sees (both ends excluded), or None."""
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    z = (lo.real + step * ix + 1j * (lo.imag + step * iy)).ravel()
    inside = np.asarray(ws.contains(z), dtype=bool)
    ok = np.zeros(z.size, dtype=bool)
    ok[inside] = np.asarray(ws.clearance(z[inside])) >= margin + step / np.sqrt(2.0)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return None
    ends = [_seen_from(ws, e, z, idx, margin) for e in (a, b)]
    if ends[0] is None or ends[1] is None:
        return None
    rows, cols, w = [], [], []
    grid = ok.reshape(nx, ny)
    flat = np.arange(nx * ny).reshape(nx, ny)
    for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
        sx = slice(0, nx - dx)
        sy = slice(max(0, -dy), ny - max(0, dy))
        tx = slice(dx, nx)
        ty = slice(max(0, dy), ny - max(0, -dy))
        both = grid[sx, sy] & grid[tx, ty]
        rows.append(flat[sx, sy][both])
        cols.append(flat[tx, ty][both])
        w.append(np.full(int(both.sum()), step * np.hypot(dx, dy)))
    r, c, ww = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    g = csr_matrix((ww, (r, c)), shape=(nx * ny, nx * ny))
    dist, pred = dijkstra(g, directed=False, indices=ends[0], return_predecessors=True)
    if not np.isfinite(dist[ends[1]]):
        return None
    out = [ends[1]]
    while out[-1] != ends[0]:
        out.append(int(pred[out[-1]]))
    return np.asarray(z[np.array(out[::-1])], dtype=np.complex128)


def _seen_from(ws: Workspace, e: complex, z: CArray, idx: NDArray[np.intp], margin: float
               ) -> int | None:  # fmt: skip
    """The free grid point (of ``z[idx]``) nearest ``e`` whose segment from ``e`` is
    ``margin`` clear (among the 16 nearest), or None."""
    near = idx[np.argsort(np.abs(z[idx] - e))[:16]]
    seen = segment_clearance(ws, np.full(near.size, e), z[near]) >= margin
    return int(near[np.flatnonzero(seen)[0]]) if seen.any() else None


def _pull_tight(ws: Workspace, a: complex, pts: CArray, margin: float) -> CArray:
    """String pulling of the polyline ``a, pts...``: from each corner on, the farthest
    point of ``pts`` in ``margin``-clear straight sight (:func:`segment_clearance`'s lower
    bound); the next point always is (the grid's steps are, by construction)."""
    out: list[complex] = []
    cur, k = a, 0
    while k < pts.size:
        seen = segment_clearance(ws, np.full(pts.size - k, cur), pts[k:]) >= margin
        j = k + (int(np.flatnonzero(seen)[-1]) if seen.any() else 0)
        cur, k = complex(pts[j]), j + 1
        out.append(cur)
    return np.array(out, dtype=np.complex128)
