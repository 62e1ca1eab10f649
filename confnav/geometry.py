"""Workspace polygons: validation, orientation, clearance, and (Geo)JSON load/save.

A workspace is an outer simple polygon with M simple obstacle polygons strictly inside it and
pairwise disjoint. Points are complex numbers ``x + iy`` in the core. Validation is strict and
every error names the polygon (``outer`` or ``obstacle j``) and the problem, because a map of a
wrong domain is silently wrong everywhere.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import shapely.ops
from numpy.typing import ArrayLike, NDArray
from shapely.geometry import LinearRing, Polygon
from shapely.validation import explain_validity

from confnav.errors import WorkspaceError
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray
from confnav.types import as_point

#: Relative size (to the workspace diameter) under which two vertices count as repeated and a
#: turn counts as a spike (collinear back-tracking).
DEGENERACY_RTOL = 1e-9


def _as_vertices(points: Any, name: str) -> ComplexArray:
    """Convert ``[[x, y], ...]`` or a complex array to a complex vertex array (no closing copy)."""
    try:
        arr = np.asarray(points)
    except (TypeError, ValueError) as exc:
        raise WorkspaceError(f"{name}: vertices are not a list of (x, y) pairs ({exc})") from exc
    if arr.dtype.kind == "c" and arr.ndim == 1:
        z = arr.astype(np.complex128)
    elif arr.ndim == 2 and arr.shape[1] == 2 and arr.dtype.kind in "iuf":
        xy = arr.astype(np.float64)
        z = xy[:, 0] + 1j * xy[:, 1]
    elif arr.ndim == 2 and arr.shape[0] == 0:
        z = np.zeros(0, np.complex128)
    else:
        raise WorkspaceError(
            f"{name}: vertices must be a list of (x, y) number pairs, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(z)):
        raise WorkspaceError(f"{name}: vertex coordinates must be finite (found NaN or inf)")
    if z.size >= 2 and z[0] == z[-1]:
        z = z[:-1]  # closed ring given with its closing vertex
    if z.size < 3:
        raise WorkspaceError(f"{name}: a polygon needs at least 3 vertices, got {z.size}")
    return z


def signed_area(z: ComplexArray) -> float:
    """Shoelace area, positive for counter-clockwise vertex order."""
    return 0.5 * float(np.sum((np.conj(z) * np.roll(z, -1)).imag))


def _check_simple(z: ComplexArray, name: str, scale: float) -> ComplexArray:
    """Reject repeated vertices, spikes and self-intersection; return counter-clockwise order."""
    edges = np.roll(z, -1) - z
    lengths = np.abs(edges)
    tiny = DEGENERACY_RTOL * scale
    bad = np.flatnonzero(lengths <= tiny)
    if bad.size:
        k = int(bad[0])
        raise WorkspaceError(
            f"{name}: vertices {k} and {(k + 1) % z.size} are repeated "
            f"(edge length {lengths[k]:.3g})"
        )
    # A spike: the boundary turns back on itself (interior angle 0 or 2*pi).
    prev = np.roll(edges, 1)
    cross = (np.conj(prev) * edges).imag
    dot = (np.conj(prev) * edges).real
    spikes = np.flatnonzero((np.abs(cross) <= tiny * (np.abs(prev) + lengths)) & (dot < 0))
    if spikes.size:
        raise WorkspaceError(
            f"{name}: vertex {int(spikes[0])} is collinear-degenerate "
            "(the boundary doubles back on itself)"
        )
    ring = LinearRing(np.column_stack([z.real, z.imag]))
    if not ring.is_simple:
        why = explain_validity(Polygon(ring))
        raise WorkspaceError(f"{name}: polygon is self-intersecting ({why})")
    area = signed_area(z)
    if abs(area) <= tiny * scale:
        raise WorkspaceError(f"{name}: polygon has zero area (all vertices collinear)")
    return z if area > 0 else z[::-1].copy()


def _polygon(z: ComplexArray) -> Polygon:
    return Polygon(np.column_stack([z.real, z.imag]))


@dataclass(frozen=True, eq=False)
class Workspace:
    """Outer polygon with obstacle polygons; validated and normalised on construction.

    Parameters
    ----------
    outer
        Outer boundary vertices, ``[[x, y], ...]`` or complex, any orientation.
    obstacles
        Obstacle polygons in the same form. Their order is the order of the circles of the map.
    anchor
        Point of the free space with ``T(anchor) = 0``, ``T'(anchor) > 0``. Default: a point of
        maximal clearance (pole of inaccessibility).

    Attributes
    ----------
    outer, obstacles
        Complex vertex arrays, all counter-clockwise.
    anchor
        The resolved anchor (complex).
    """

    outer: ComplexArray
    obstacles: tuple[ComplexArray, ...]
    anchor: complex
    anchor_given: bool = field(default=False, repr=False)

    def __init__(
        self,
        outer: Any,
        obstacles: Iterable[Any] = (),
        anchor: complex | Sequence[float] | None = None,
    ) -> None:
        out = _as_vertices(outer, "outer")
        obs_raw = [_as_vertices(p, f"obstacle {j}") for j, p in enumerate(obstacles)]
        allz = np.concatenate([out, *obs_raw])
        scale = float(np.max(np.abs(allz - allz.mean()))) or 1.0
        out = _check_simple(out, "outer", scale)
        obs = tuple(_check_simple(p, f"obstacle {j}", scale) for j, p in enumerate(obs_raw))
        outer_poly = _polygon(out)
        obs_polys = [_polygon(p) for p in obs]
        for j, poly in enumerate(obs_polys):
            if not outer_poly.contains(poly) or poly.intersects(outer_poly.exterior):
                raise WorkspaceError(
                    f"obstacle {j}: must lie strictly inside the outer polygon "
                    "(it leaves or touches the outer boundary)"
                )
        if len(obs_polys) > 1:
            tree = shapely.STRtree(obs_polys)
            pairs = tree.query(obs_polys, predicate="intersects")
            for a, b in zip(*pairs, strict=True):
                if a < b:
                    kind = (
                        "overlap"
                        if obs_polys[a].overlaps(obs_polys[b])
                        or obs_polys[a].contains(obs_polys[b])
                        or obs_polys[b].contains(obs_polys[a])
                        else "touch"
                    )
                    raise WorkspaceError(
                        f"obstacles {a} and {b} {kind}: obstacles must be pairwise disjoint"
                    )
        free = Polygon(outer_poly.exterior.coords, [p.exterior.coords for p in obs_polys])
        object.__setattr__(self, "outer", out)
        object.__setattr__(self, "obstacles", obs)
        object.__setattr__(self, "_free", free)
        shapely.prepare(free)
        object.__setattr__(self, "_segments", _segments(out, obs))
        if anchor is None:
            a = _max_clearance_point(free)
            object.__setattr__(self, "anchor_given", False)
        else:
            a = as_point(anchor, "anchor", WorkspaceError)
            if not self.contains(a):
                raise WorkspaceError(
                    f"anchor ({a.real:g}, {a.imag:g}) is not in the free space "
                    "(inside an obstacle, outside the outer polygon, or on a boundary)"
                )
            object.__setattr__(self, "anchor_given", True)
        object.__setattr__(self, "anchor", complex(a))

    # ------------------------------------------------------------------ queries
    @property
    def n_obstacles(self) -> int:
        return len(self.obstacles)

    @property
    def polygon(self) -> Polygon:
        """The free space as a shapely polygon with holes."""
        return self._free  # type: ignore[attr-defined,no-any-return]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.polygon.bounds)  # type: ignore[return-value]

    @property
    def diameter(self) -> float:
        """Largest extent of the outer polygon's bounding box (a length scale)."""
        x0, y0, x1, y1 = self.bounds
        return max(x1 - x0, y1 - y0)

    @property
    def boundaries(self) -> tuple[ComplexArray, ...]:
        """Outer polygon then obstacles, all counter-clockwise."""
        return (self.outer, *self.obstacles)

    def contains(self, z: ArrayLike) -> NDArray[np.bool_]:
        """True where ``z`` is strictly inside the free space (vectorized)."""
        zz = np.asarray(z, dtype=np.complex128)
        return np.asarray(shapely.contains_xy(self.polygon, zz.real, zz.imag), dtype=bool)

    def clearance(self, z: ArrayLike) -> FloatArray:
        """Signed distance to the nearest boundary: > 0 in free space, < 0 outside it."""
        zz = np.asarray(z, dtype=np.complex128)
        d = distance_to_boundary(self, zz)
        inside = self.contains(zz)
        return np.where(inside, d, -d)

    def clearance1(self, z: complex) -> float:
        """:meth:`clearance` of one point (a Python float; the one-robot control step): the
        same arithmetic on the segments as :func:`distance_to_boundary`, in fewer numpy calls."""
        seg = self.__dict__.get("_seg1")
        if seg is None:  # (a, d, conj(d), |d|^2) of every side, as _distance_to_segments
            a, b = self._segments  # type: ignore[attr-defined]
            seg = (a, b - a, np.conj(b - a), np.abs(b - a) ** 2)
            object.__setattr__(self, "_seg1", seg)
        a, d, cd, dd = seg
        t = np.minimum(np.maximum(((z - a) * cd).real / dd, 0.0), 1.0)
        dist = float(np.abs(z - (a + t * d)).min())
        return dist if shapely.contains_xy(self.polygon, z.real, z.imag) else -dist

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: ``{"outer": [[x, y], ...], "obstacles": [...], "anchor": [x, y]}``."""
        return {
            "outer": _xy_list(self.outer),
            "obstacles": [_xy_list(p) for p in self.obstacles],
            "anchor": [self.anchor.real, self.anchor.imag],
        }

    @classmethod
    def from_dict(cls, d: Any) -> Workspace:
        if not isinstance(d, dict):
            raise WorkspaceError("workspace JSON must be an object with 'outer' and 'obstacles'")
        if d.get("type") in {"Feature", "FeatureCollection", "Polygon", "MultiPolygon"}:
            return cls.from_geojson(d)
        unknown = set(d) - {"outer", "obstacles", "anchor", "name"}
        if unknown:
            raise WorkspaceError(f"workspace JSON has unknown keys: {sorted(unknown)}")
        if "outer" not in d:
            raise WorkspaceError("workspace JSON needs an 'outer' polygon")
        return cls(d["outer"], d.get("obstacles") or (), d.get("anchor"))

    def to_json(self, indent: int | None = None) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_json(cls, text: str | bytes) -> Workspace:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise WorkspaceError(f"workspace is not valid JSON: {exc}") from exc
        return cls.from_dict(d)

    @classmethod
    def from_geojson(cls, obj: Any) -> Workspace:
        """Read a GeoJSON Polygon (with holes), single-part MultiPolygon, or Feature thereof.

        The polygon's exterior ring is the outer boundary and its interior rings are the
        obstacles; a Feature may carry ``properties.anchor = [x, y]``.
        """
        anchor = None
        if obj.get("type") == "FeatureCollection":
            feats = obj.get("features") or []
            if len(feats) != 1:
                raise WorkspaceError(
                    f"GeoJSON FeatureCollection must hold exactly one feature, got {len(feats)}"
                )
            obj = feats[0]
        if obj.get("type") == "Feature":
            anchor = (obj.get("properties") or {}).get("anchor")
            obj = obj.get("geometry") or {}
        kind = obj.get("type")
        coords = obj.get("coordinates")
        if kind == "MultiPolygon":
            if not isinstance(coords, list) or len(coords) != 1:
                n = len(coords) if isinstance(coords, list) else 0
                raise WorkspaceError(
                    f"GeoJSON MultiPolygon must have exactly one part (the free space must be "
                    f"connected), got {n}"
                )
            coords = coords[0]
        elif kind != "Polygon":
            raise WorkspaceError(f"GeoJSON geometry must be Polygon or MultiPolygon, got {kind!r}")
        if not isinstance(coords, list) or not coords:
            raise WorkspaceError("GeoJSON Polygon has no rings")
        return cls(coords[0], coords[1:], anchor)

    def to_geojson(self) -> dict[str, Any]:
        """A GeoJSON Feature: Polygon with holes (RFC 7946 ring orientation), anchor property."""

        def ring(z: ComplexArray, ccw: bool) -> list[list[float]]:
            zz = z if ccw else z[::-1]
            pts = _xy_list(zz)
            return [*pts, pts[0]]

        return {
            "type": "Feature",
            "properties": {"anchor": [self.anchor.real, self.anchor.imag]},
            "geometry": {
                "type": "Polygon",
                "coordinates": [ring(self.outer, True)] + [ring(p, False) for p in self.obstacles],
            },
        }

    @classmethod
    def load(cls, path: str | Path) -> Workspace:
        """Load a workspace from a JSON or GeoJSON file."""
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise WorkspaceError(f"cannot read workspace file {p}: {exc.strerror}") from exc
        try:
            return cls.from_json(text)
        except WorkspaceError as exc:
            raise WorkspaceError(f"{p}: {exc}") from exc

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json(indent=2) + "\n")

    @property
    def content_hash(self) -> str:
        """sha256 (hex) of the canonical form: what a map solved for this workspace is bound to.

        Canonical form: :meth:`to_dict` after validation (every polygon counter-clockwise,
        closing vertex dropped, the default anchor resolved to its point), coordinates as
        float64 with -0.0 written as 0.0, serialised as JSON with sorted keys, no whitespace
        and Python's shortest round-trip float repr, UTF-8. Equal geometry and anchor give
        equal hashes; any change of a coordinate, of the obstacle order or of the anchor gives
        another hash (obstacle j is circle j of the map, and the anchor is sent to 0).
        """
        d = self.to_dict()
        canon = json.dumps(_zero_signs(d), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canon.encode()).hexdigest()

    def with_anchor(self, anchor: complex | Sequence[float] | None) -> Workspace:
        return Workspace(self.outer, self.obstacles, anchor)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Workspace) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(self.content_hash)


def _zero_signs(x: Any) -> Any:
    """The same nested lists/dicts with every float -0.0 replaced by 0.0 (canonical form)."""
    if isinstance(x, dict):
        return {k: _zero_signs(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_zero_signs(v) for v in x]
    return x + 0.0 if isinstance(x, float) else x


def _xy_list(z: ComplexArray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in z]


def _segments(
    outer: ComplexArray, obstacles: tuple[ComplexArray, ...]
) -> tuple[ComplexArray, ComplexArray]:
    starts = np.concatenate([outer, *obstacles])
    ends = np.concatenate([np.roll(p, -1) for p in (outer, *obstacles)])
    return starts, ends


def _distance_to_segments(z: ComplexArray, a: ComplexArray, b: ComplexArray) -> FloatArray:
    """Exact Euclidean distance from each point to the nearest segment [a_k, b_k]."""
    d = b - a
    # projection parameter of z onto each segment, clamped to [0, 1]
    t = ((z[:, None] - a[None, :]) * np.conj(d)[None, :]).real / (np.abs(d) ** 2)[None, :]
    t = np.clip(t, 0.0, 1.0)
    return np.asarray(np.min(np.abs(z[:, None] - (a[None, :] + t * d[None, :])), axis=1))


def distance_to_boundary(ws: Workspace, z: ArrayLike) -> FloatArray:
    """Unsigned distance from points to the workspace boundary (vectorized)."""
    zz = np.asarray(z, dtype=np.complex128)
    return _distance_to_segments(zz.ravel(), *ws._segments).reshape(zz.shape)  # type: ignore[attr-defined,no-any-return]


def _max_clearance_point(free: Polygon) -> complex:
    """Pole of inaccessibility of the free space (shapely's polylabel, holes respected)."""
    x0, y0, x1, y1 = free.bounds
    tol = 1e-4 * max(x1 - x0, y1 - y0)
    p = shapely.ops.polylabel(free, tolerance=tol)
    return complex(p.x, p.y)


def interior_point(polygon: ComplexArray) -> complex:
    """A point well inside a simple polygon (its pole of inaccessibility)."""
    return _max_clearance_point(_polygon(polygon))


__all__ = ["Workspace", "distance_to_boundary", "interior_point", "signed_area"]
