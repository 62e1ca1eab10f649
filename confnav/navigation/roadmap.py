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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, shortest_path
from scipy.spatial import Delaunay, cKDTree

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.types import CArray, FArray

__all__ = ["Roadmap", "build_roadmap", "passage_widths", "segment_segment_distance"]


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


def segment_clearance(ws: Workspace, a: ArrayLike, b: ArrayLike, step: float = 0.02) -> FArray:
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
    no dead-end branches, where robots could only pass each other by backing out).
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
        good = np.ones(len(cand), dtype=bool)
        mid = 0.5 * (a + b)
        for e, near in enumerate(
            tree.query_ball_point(np.column_stack([mid.real, mid.imag]), 0.5 * max_edge + pass_gap)
        ):
            others = [w for w in near if w != cand[e, 0] and w != cand[e, 1]]
            if others:
                dd = segment_segment_distance(nodes[others], nodes[others], a[e], b[e])
                good[e] = bool(dd.min() >= pass_gap - 1e-9)
        cand = cand[good]
    edges = np.asarray(cand, dtype=np.intp).reshape(-1, 2)
    return edges


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
