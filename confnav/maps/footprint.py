"""Robot footprints: the free space shrunk by a disk of radius r (configuration space).

A disk robot of radius ``r`` centred at ``x`` is collision free iff ``x`` lies in the free space
minus the Minkowski sum of the obstacles (and of the walls) with the closed disk ``D_r``
[1]_ (ch. 4). Navigating the centre in the *shrunk* free space therefore keeps the body clear,
with every guarantee of the point robot.

Polygonisation (why the result contains the true Minkowski sum)
---------------------------------------------------------------
The exact shrunk free space is bounded by straight offsets and circular arcs. GEOS (shapely's
``buffer``) approximates an arc of total angle A by ``n = round(A / q)`` chords with vertices
*on* the circle (``q = pi / (2 quad_segs)``, see GEOS ``OffsetSegmentGenerator::
addDirectedFillet``), so one chord spans at most ``1.5 q`` and sags inside the arc by up to
``r (1 - cos(0.75 q))``: a bevel-like cut into the Minkowski sum, i.e. not conservative.
We therefore buffer by the radius of the *circumscribed* polygon,
``r' = r / cos(0.75 q)``: every chord of a circle of radius ``r'`` spanning at most ``1.5 q``
stays at distance ``>= r`` from the centre, so the polygonal result contains the true
Minkowski sum (the round approximation is outward). The straight offsets move out by ``r'``
too; the excess ``r' - r`` is the polygonisation bound (``r * 0.0027`` at ``quad_segs = 16``,
``r * 0.044`` at 4). With ``join="mitre"`` the offset edges meet at their intersection (capped
at ``mitre_limit * r`` from the vertex, which still contains the disk) and no excess is needed.
Bevel joins cut inside the sum and are refused. A mitre is capped at ``mitre_limit * r``
(:data:`MITRE_LIMIT`) from its vertex by a cut tangent to or beyond the disk: still conservative,
and sharp corners no longer grow spikes that nearly touch other obstacles (a near-touch the
solver must resolve with many nodes, and a topology the true sum does not have).
The default is mitre: it adds no vertices (the solver's graded mesh pays for every vertex:
round joins with 8 segments per quadrant made the default workspace fail to converge), at the
price of a wider margin at sharp corners. That
margin must not change the topology: two facing corners of imported walls (about 50 degrees)
grew by about 0.45 m each for a 0.32 m disk and closed a 0.78 m passage the disk passes. So
wherever the round-join shrink (circumscribed, hence also inside the exact one) connects what
the mitred one separates, or keeps a region the mitre lost, those pieces of it are added
(:func:`_reopen_passages`): the topology changes only where the true Minkowski sum changes it
(up to the round join's excess ``r' - r``, ``0.011 r`` at 8 segments per quadrant), and round
vertices appear only in such passages.
Each result is checked exactly: the distance from the shrunk boundary to the original boundary
(segment-to-segment, shapely) must be >= r.

Topology: inflated obstacles that meet merge into one obstacle; an obstacle whose inflation
reaches a wall becomes part of the outer boundary (shapely's polygon buffer does both); a
passage narrower than 2r splits the free space into components (:class:`Inflation` lists them,
largest first, and :class:`UnreachableGoalError` names the component of a point that is not in
the kept one).

References
----------
.. [1] J.-C. Latombe, *Robot Motion Planning*, Kluwer 1991, ch. 4 (configuration space of a
   disk: Minkowski sum of the obstacles with the disk).
.. [2] T. Lozano-Perez, "Spatial planning: a configuration space approach", IEEE Trans.
   Computers C-32 (1983) 108-120.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Point, Polygon

from confnav.errors import NavigationError, WorkspaceError
from confnav.geometry import Workspace

log = logging.getLogger(__name__)

__all__ = [
    "Inflation",
    "UnreachableGoalError",
    "derived_ws_id",
    "inflate",
    "parse_derived_ws_id",
    "quantize_radius",
    "shrink_free_space",
]

JoinStyle = Literal["round", "mitre"]

#: Radii are rounded *up* to this quantum (workspace units) so that close radii share one solve
#: (cache key) and the rounding is conservative.
RADIUS_QUANTUM = 1e-4

#: Mitre joins are cut (bevelled perpendicular to the corner's bisector) at this multiple of the
#: radius from the vertex; the cut is tangent to or beyond the disk, so the result still contains
#: the Minkowski sum (checked exactly in :func:`shrink_free_space`). 1.5 keeps right angles mitred
#: (ratio sqrt 2: a square grows to a square) and cuts only corners sharper than about 84
#: degrees. A far-reaching spike costs the solver: on the default workspace shrunk by 0.2 m the
#: star's 40-degree tips reached 0.5 m at limit 5 and left a 4.3 mm gap to the square (55 polygon
#: sides); at 1.5 the narrowest gap is 0.10 m (33 sides), and the coarse revision (tol 1e-3)
#: took 1.8 s CPU instead of 4.4 s in the same run (medians of 3, load 5-7;
#: bench/results/coarse.json, ``python -m bench coarse``).
MITRE_LIMIT = 1.5

#: Round-join polygonisations (segments per quadrant) tried, coarse first, for the passages
#: :func:`_reopen_passages` puts back: each is circumscribed (still inside the exact shrink) and
#: is used only if it has the same topology as the ``quad_segs`` one (every passage that one
#: opens stays open). Every arc vertex is a polygon corner the solver's graded mesh pays for
#: (each side gets at least the nodes of the polygon's worst corner), so fewer, longer arc
#: sides mean fewer nodes; the price is a larger excess ``r' - r``: 0.044 r at 4 segments,
#: 0.20 r at 2, in the reopened passages only.
REOPEN_QUAD_SEGS: tuple[int, ...] = (2, 4)

#: Components of the shrunk free space smaller than this fraction of the largest are reported
#: but never kept by default (slivers left by a buffer between two nearly touching obstacles).
MIN_COMPONENT_FRACTION = 1e-6


#: Points closer than this (relative to the workspace size) to the shrunk free space's
#: boundary are not in it (:meth:`Inflation.component_of`): far above rounding, far below any
#: clearance that matters to a robot (0.1 mm in a 10 m room), and below the 1e-4 step inwards
#: of the points :meth:`Inflation.nearest` suggests.
EDGE_RTOL = 1e-5


class UnreachableGoalError(NavigationError):
    """A point (goal or start) is not in the kept component of the shrunk free space."""


def quantize_radius(radius: float) -> float:
    """``radius`` rounded up to :data:`RADIUS_QUANTUM` (conservative, a stable cache key)."""
    if not (math.isfinite(radius) and radius >= 0):
        raise NavigationError(f"robot radius must be finite and >= 0, got {radius!r}")
    q = math.ceil(radius / RADIUS_QUANTUM - 1e-9) * RADIUS_QUANTUM
    return round(q, 10)


def derived_ws_id(ws_id: str, radius: float) -> str:
    """Key of the workspace ``ws_id`` shrunk by ``radius``: ``"{ws_id}~r{radius}"``.

    ``radius`` is quantised up (:func:`quantize_radius`); radius 0 is ``ws_id`` itself.
    """
    r = quantize_radius(radius)
    return ws_id if r == 0 else f"{ws_id}~r{r:g}"


def parse_derived_ws_id(ws_id: str) -> tuple[str, float] | None:
    """``(base id, radius)`` of a derived id from :func:`derived_ws_id`, else None."""
    base, sep, tail = ws_id.rpartition("~r")
    if not sep or not base:
        return None
    try:
        r = float(tail)
    except ValueError:
        return None
    return (base, r) if math.isfinite(r) and r > 0 and derived_ws_id(base, r) == ws_id else None


def _effective_radius(radius: float, join: JoinStyle, quad_segs: int) -> float:
    """The buffer distance whose polygon contains the true Minkowski sum (module docstring)."""
    if join == "mitre":
        return radius
    q = math.pi / (2 * quad_segs)
    return radius / math.cos(0.75 * q)


@dataclass(frozen=True)
class Inflation:
    """The free space of ``workspace`` shrunk by ``radius``: its connected components.

    ``components`` are shapely polygons, largest area first; ``effective_radius`` is the
    buffer distance used (>= radius, see the module docstring); ``excess`` = its difference.
    """

    workspace: Workspace
    radius: float
    join: JoinStyle
    quad_segs: int
    effective_radius: float
    components: tuple[Polygon, ...]
    #: passages the mitre joins closed and the round joins reopened (:func:`shrink_free_space`)
    reopened: int = 0

    @property
    def excess(self) -> float:
        return self.effective_radius - self.radius

    def component_of(self, z: complex) -> int | None:
        """Index of the component holding ``z`` (None: within ``radius`` of the boundary).

        A point on the shrunk boundary to within :data:`EDGE_RTOL` of the workspace size
        counts as outside: there the robot's footprint touches a wall, and the map sends the
        point onto a circle of the circle domain, where no navigation function has its goal
        (found from the CLI: a goal exactly ``radius`` from a wall was "inside" to rounding,
        and the run failed after a 77 s solve with "not inside the circle domain").
        """
        p = Point(z.real, z.imag)
        edge = EDGE_RTOL * self.workspace.diameter
        for j, c in enumerate(self.components):
            if c.contains(p):
                return j if c.boundary.distance(p) > edge else None
        return None

    def nearest(self, z: complex) -> tuple[complex, int]:
        """The point of the shrunk free space nearest ``z`` (just inside it) and its component."""
        p = Point(z.real, z.imag)
        j = min(range(len(self.components)), key=lambda i: self.components[i].distance(p))
        c = self.components[j]
        q = c.exterior.interpolate(c.exterior.project(p))
        for ring in c.interiors:  # the nearest boundary point may lie on a hole
            r = ring.interpolate(ring.project(p))
            if r.distance(p) < q.distance(p):
                q = r
        w = complex(q.x, q.y)
        # a step of 1e-4 of the size inwards: on the boundary is not inside, and the point
        # printed to 6 digits must still be
        d = 1e-4 * self.workspace.diameter
        away = (w - z) / abs(w - z) if w != z else 1.0  # on, away from z: the inward normal
        # of 8 directions, the one deepest inside (the first inside may run almost along the
        # wall, closer to it than component_of accepts)
        best, depth = w, 0.0
        for k in range(8):
            u = w + d * away * np.exp(2j * np.pi * k / 8)
            pu = Point(u.real, u.imag)
            inside = c.boundary.distance(pu) if c.contains(pu) else 0.0
            if inside > depth:
                best, depth = complex(u), inside
        return best, j

    def describe(self, j: int) -> str:
        c = self.components[j]
        rp = c.representative_point()
        return (
            f"component {j} of {len(self.components)} "
            f"(area {c.area:.4g}, around ({rp.x:.4g}, {rp.y:.4g}))"
        )

    def check_reachable(self, keep: int, points: dict[str, complex]) -> None:
        """Raise :class:`UnreachableGoalError` for the first named point not in ``keep``."""
        for name, z in points.items():
            j = self.component_of(z)
            if j == keep:
                continue
            where = (
                f"within r={self.radius:g} of an obstacle or wall"
                if j is None
                else f"in {self.describe(j)}"
            )
            raise UnreachableGoalError(
                f"{name} ({z.real:.6g}, {z.imag:.6g}) is unreachable for a robot of radius "
                f"{self.radius:g}: it is {where}, but the navigable space is "
                f"{self.describe(keep)}; a passage narrower than {2 * self.radius:g} separates "
                "them" + ("" if j is not None else " or the point itself is too close")
            )

    def workspace_of(self, j: int, anchor: complex | None = None) -> Workspace:
        """Component ``j`` as a validated :class:`Workspace` (obstacles = its holes)."""
        return _to_workspace(self.components[j], anchor)


def shrink_free_space(
    ws: Workspace,
    radius: float,
    *,
    join: JoinStyle = "mitre",
    quad_segs: int = 8,
    mitre_limit: float = MITRE_LIMIT,
) -> Inflation:
    """The components of the free space of ``ws`` shrunk by a disk of ``radius``.

    Raises :class:`WorkspaceError` for a bevel join, a bad radius, no free space left, or a
    result that fails the exact containment check.
    """
    if join not in ("round", "mitre"):
        raise WorkspaceError(
            f"join style {join!r} not allowed: use 'round' or 'mitre' (a bevel join cuts "
            "inside the Minkowski sum, so the robot could touch an obstacle)"
        )
    if quad_segs < 1 or mitre_limit < 1:
        raise WorkspaceError("need quad_segs >= 1 and mitre_limit >= 1")
    r = quantize_radius(radius)
    free = ws.polygon
    if r == 0:
        return Inflation(ws, 0.0, join, quad_segs, 0.0, (free,))
    reff = _effective_radius(r, join, quad_segs)
    shrunk = free.buffer(-reff, quad_segs=quad_segs, join_style=join, mitre_limit=mitre_limit)
    reopened = 0
    if join == "mitre":
        shrunk, reopened = _reopen_passages(free, shrunk, r, quad_segs, ws.diameter)
    parts = [shrunk] if isinstance(shrunk, Polygon) else list(getattr(shrunk, "geoms", []))
    parts = [p for p in parts if isinstance(p, Polygon) and not p.is_empty and p.area > 0]
    if not parts:
        raise WorkspaceError(
            f"no free space is left for a robot of radius {r:g} (the widest clearance is "
            f"{ws.clearance(np.asarray(ws.anchor)).item():.4g})"
        )
    # drop the near-repeated and collinear vertices GEOS leaves (moves edges by <= 1e-10 of
    # the workspace size; the containment check below runs on the cleaned polygons)
    parts = [shapely.simplify(p, 1e-10 * ws.diameter, preserve_topology=True) for p in parts]
    parts.sort(key=lambda p: -p.area)
    big = parts[0].area
    parts = [p for p in parts if p.area >= MIN_COMPONENT_FRACTION * big]
    # exact check: the shrunk region stays inside and >= r away from every original edge
    union = MultiPolygon(parts)
    gap = float(shapely.distance(union.boundary, free.boundary))
    if not (free.buffer(1e-9 * ws.diameter).contains(union) and gap >= r * (1 - 1e-9)):
        raise WorkspaceError(
            f"inflation by {r:g} failed its containment check (gap {gap:.6g} < {r:g})"
        )
    return Inflation(ws, r, join, quad_segs, reff, tuple(parts), reopened)


def _reopen_passages(
    free: Polygon, mitred: shapely.Geometry, r: float, quad_segs: int, size: float
) -> tuple[shapely.Geometry, int]:
    """``mitred`` (the free space shrunk with mitre joins) with the passages the mitre closed
    but the true Minkowski sum leaves open put back, from the round-join shrink.

    Both shrinks lie inside the exact one (the round join by the circumscribed radius,
    module docstring), so their union does too. The round shrink minus the mitred one is
    a sliver at every convex corner (the mitre's tip beyond the arc), touching the mitred
    region along one curve, plus, where a mitre tip closed a passage, a piece touching it
    on both sides of the passage (or not at all: a region the mitre lost). Only where the two
    shrinks differ in topology (components and their holes) are those pieces added: the
    topology is the round shrink's, and the vertices stay the mitre's except in the passages.
    Returns the region and the number of pieces added.
    """
    rounded = free.buffer(-_effective_radius(r, "round", quad_segs), quad_segs=quad_segs)
    if _topology(rounded) == _topology(mitred):
        return mitred, 0  # the same components and holes: the mitre's vertices only
    for coarse_segs in REOPEN_QUAD_SEGS:  # fewer arc vertices, if the topology is kept
        if coarse_segs < quad_segs:
            coarse = free.buffer(-_effective_radius(r, "round", coarse_segs), quad_segs=coarse_segs)
            if _topology(coarse) == _topology(rounded):
                rounded = coarse
                break
    extra = shapely.difference(rounded, mitred)
    pieces = [g for g in getattr(extra, "geoms", [extra]) if isinstance(g, Polygon) and g.area > 0]
    if not pieces:
        return mitred, 0
    eps = 1e-7 * size
    touch = shapely.intersection(shapely.buffer(pieces, eps), mitred)
    n_touch = np.array([len(getattr(t, "geoms", [t])) if not t.is_empty else 0 for t in touch])
    add = [g for g, k in zip(pieces, n_touch, strict=True) if k != 1]
    if not add:
        return mitred, 0
    # grown by eps within the round shrink: rounding leaves no gap along the seams
    grown = shapely.intersection(shapely.buffer(add, eps), rounded)
    return shapely.union_all([mitred, *grown]), len(add)


def _topology(region: shapely.Geometry) -> tuple[int, ...]:
    """Hole counts of the components of ``region`` that are not slivers, largest first."""
    parts = [g for g in getattr(region, "geoms", [region]) if isinstance(g, Polygon)]
    big = max((g.area for g in parts), default=0.0)
    keep = sorted((g for g in parts if g.area >= MIN_COMPONENT_FRACTION * big),
                  key=lambda g: -g.area)  # fmt: skip
    return tuple(len(g.interiors) for g in keep)


def inflate(
    ws: Workspace,
    radius: float,
    *,
    keep: complex | None = None,
    require: dict[str, complex] | None = None,
    join: JoinStyle = "mitre",
    quad_segs: int = 8,
    mitre_limit: float = MITRE_LIMIT,
) -> Workspace:
    """The workspace for the centre of a disk robot of ``radius``: ``ws`` shrunk by it.

    Keeps the component holding ``keep`` (default: the largest), checks every point of
    ``require`` (e.g. ``{"goal": g}``) lies in it (:class:`UnreachableGoalError` naming the
    point and its component otherwise). The anchor is the original one if it is still free,
    else the new maximal-clearance point. ``mitre_limit``: see :data:`MITRE_LIMIT`.
    """
    inf = shrink_free_space(ws, radius, join=join, quad_segs=quad_segs, mitre_limit=mitre_limit)
    if inf.radius == 0:
        return ws
    if keep is None:
        j = 0
    else:
        found = inf.component_of(complex(keep))
        if found is None:
            near, k = inf.nearest(complex(keep))
            raise UnreachableGoalError(
                f"point ({keep.real:.6g}, {keep.imag:.6g}) is within r={inf.radius:g} of an "
                "obstacle or wall: no component of the shrunk free space holds it; the nearest "
                f"point that does is ({near.real:.6g}, {near.imag:.6g}), "
                f"{abs(near - keep):.3g} m away, in {inf.describe(k)}"
            )
        j = found
        if j != 0:  # components are sorted by area: the goal's is not the largest
            log.warning(
                "the point (%.6g, %.6g) kept lies in %s, not in the largest, %s: a passage "
                "narrower than %g (twice the radius) cuts it off, and robots elsewhere "
                "cannot reach it",
                keep.real, keep.imag, inf.describe(j), inf.describe(0), 2 * inf.radius,
            )  # fmt: skip
    inf.check_reachable(j, dict(require or {}))
    anchor = (
        ws.anchor
        if ws.anchor_given and inf.components[j].contains(Point(ws.anchor.real, ws.anchor.imag))
        else None
    )
    return inf.workspace_of(j, anchor)


def _to_workspace(poly: Polygon, anchor: complex | None) -> Workspace:
    """A validated Workspace from a shapely polygon (exterior = outer, holes = obstacles)."""

    def ring(coords: object) -> np.ndarray:
        xy = np.asarray(coords, dtype=np.float64)[:-1]
        return xy[:, 0] + 1j * xy[:, 1]

    try:
        return Workspace(
            ring(poly.exterior.coords), [ring(h.coords) for h in poly.interiors], anchor
        )
    except WorkspaceError as exc:
        raise WorkspaceError(f"the shrunk free space is not a valid workspace: {exc}") from exc
