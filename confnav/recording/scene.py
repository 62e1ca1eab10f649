"""Foxglove ``foxglove.SceneUpdate`` visualisation channels for confnav recordings.

Two scenes per workspace ``ws`` (topics under the recording's key prefix, default ``confnav``):

- ``{prefix}/viz/{ws}/scene`` (frame ``workspace``): the outer polygon and the obstacles as
  line loops, each robot's goal (sphere), the robot itself (flat cube turned by its heading)
  and its trail (line strip).
- ``{prefix}/viz/{ws}/circle_domain`` (frame ``circle_domain``): the unit circle and the obstacle
  circles ``|w - c_j| = r_j`` of the solved map as line loops, and the images ``T(z)`` of the
  goals, robots and trails (needs the map's coefficients from the ``transform`` message).

Robots are updated every 0.1 s of log time; goals, polygons, circles and trails every second
(entities persist by id until replaced), trails are decimated to at most 256 points and mapped
once each: the recorder hook stays cheap (well under a millisecond per recorded message).

Messages are JSON (message encoding ``json``) conforming to the official Foxglove JSON Schema,
vendored unchanged in ``schemas/foxglove/SceneUpdate.json`` and written as the channel schema
(schema name ``foxglove.SceneUpdate``, schema encoding ``jsonschema``), so a recording opens in
Foxglove with a 2-D scene (3D panel, pick the display frame ``workspace`` or
``circle_domain``).

The builders (:func:`workspace_scene`, :func:`circle_domain_scene`, the primitive helpers) are
pure functions of plain data. :class:`SceneBuilder` keeps the state (workspaces, maps, goals,
poses, trails) and turns the stream of recorded confnav messages into scene messages;
:class:`FoxgloveSceneWriter` is the hook the recorder calls for every recorded message to write
those scene messages into the same :class:`mcap.writer.Writer`. All times are integer
nanoseconds on the recording's log-time clock (Unix epoch).
"""

from __future__ import annotations

import cmath
import json
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from typing import Any, NamedTuple

from mcap.writer import Writer

logger = logging.getLogger(__name__)

SCENE_SCHEMA_NAME = "foxglove.SceneUpdate"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
WORKSPACE_FRAME = "workspace"
CIRCLE_DOMAIN_FRAME = "circle_domain"
DEFAULT_PERIOD_NS = 100_000_000  # robots and goals: at most every 0.1 s of log time
DEFAULT_FULL_PERIOD_NS = 1_000_000_000  # polygons, circles and trails: every 1 s
DEFAULT_TRAIL_POINTS = 256  # maximum points per robot trail
DEFAULT_TRAIL_RESOLUTION = 0.002  # minimum trail spacing / workspace diameter
COORD_DECIMALS = 6  # coordinates in scene JSON are rounded to 1e-6 (workspace units)
CIRCLE_SEGMENTS = 96  # line-loop vertices per circle

Point = tuple[float, float]
Color = tuple[float, float, float, float]

OUTER_COLOR: Color = (0.1, 0.1, 0.1, 1.0)
OBSTACLE_COLOR: Color = (0.75, 0.2, 0.1, 1.0)
GOAL_COLOR: Color = (0.1, 0.7, 0.2, 1.0)
CELL_COLOR: Color = (0.3, 0.4, 0.9, 0.35)  # atlas cells (issue 15)
ROBOT_COLORS: tuple[Color, ...] = (
    (0.12, 0.47, 0.71, 1.0),
    (1.0, 0.5, 0.05, 1.0),
    (0.58, 0.4, 0.74, 1.0),
    (0.55, 0.34, 0.29, 1.0),
    (0.89, 0.47, 0.76, 1.0),
    (0.09, 0.75, 0.81, 1.0),
)


# --------------------------------------------------------------------------------------------
# schema and topics


@cache
def scene_update_schema_text() -> str:
    """The official ``foxglove.SceneUpdate`` JSON Schema text (vendored, unchanged)."""
    ref = resources.files("confnav.schemas").joinpath("foxglove/SceneUpdate.json")
    return ref.read_text(encoding="utf-8")


def scene_update_schema() -> dict[str, Any]:
    """The official ``foxglove.SceneUpdate`` JSON Schema as a dict (a fresh copy)."""
    schema: dict[str, Any] = json.loads(scene_update_schema_text())
    return schema


def scene_topic(ws: str, prefix: str = "confnav") -> str:
    """Topic of the workspace scene of ``ws``."""
    return f"{prefix}/viz/{ws}/scene"


def circle_domain_topic(ws: str, prefix: str = "confnav") -> str:
    """Topic of the circle-domain scene of ``ws``."""
    return f"{prefix}/viz/{ws}/circle_domain"


def is_viz_topic(topic: str, prefix: str = "confnav") -> bool:
    """Whether ``topic`` is one of the visualisation channels (not a recorded Zenoh key)."""
    return topic.startswith(f"{prefix}/viz/")


# --------------------------------------------------------------------------------------------
# primitives (pure)


def time_msg(ns: int) -> dict[str, int]:
    """Foxglove ``time`` from integer nanoseconds since the epoch."""
    if ns < 0:
        raise ValueError(f"negative timestamp {ns} ns")
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _color(c: Color) -> dict[str, float]:
    return {"r": c[0], "g": c[1], "b": c[2], "a": c[3]}


def _pose(x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> dict[str, Any]:
    """Pose in the plane z = 0, turned by ``theta`` (rad) about +z."""
    return {
        "position": {
            "x": round(float(x), COORD_DECIMALS),
            "y": round(float(y), COORD_DECIMALS),
            "z": 0.0,
        },
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)},
    }


def _point(p: Point) -> dict[str, float]:
    return {
        "x": round(float(p[0]), COORD_DECIMALS),
        "y": round(float(p[1]), COORD_DECIMALS),
        "z": 0.0,
    }


def line_primitive(
    points: Sequence[Point], color: Color, *, loop: bool = False, thickness: float = 2.0
) -> dict[str, Any]:
    """A ``foxglove.LinePrimitive``: a line loop (``loop``) or strip, ``thickness`` in pixels."""
    return {
        "type": 1 if loop else 0,  # LINE_LOOP / LINE_STRIP
        "pose": _pose(),
        "thickness": float(thickness),
        "scale_invariant": True,
        "points": [_point(p) for p in points],
        "color": _color(color),
        "colors": [],
        "indices": [],
    }


def sphere_primitive(center: Point, diameter: float, color: Color) -> dict[str, Any]:
    """A ``foxglove.SpherePrimitive`` centred at ``center`` (flat in z)."""
    d = float(diameter)
    return {
        "pose": _pose(center[0], center[1]),
        "size": {"x": d, "y": d, "z": d / 4},
        "color": _color(color),
    }


def cube_primitive(center: Point, theta: float, size: float, color: Color) -> dict[str, Any]:
    """A flat ``foxglove.CubePrimitive`` at ``center`` turned by ``theta`` (rad), long along x."""
    s = float(size)
    return {
        "pose": _pose(center[0], center[1], theta),
        "size": {"x": 1.6 * s, "y": s, "z": s / 4},
        "color": _color(color),
    }


def text_primitive(at: Point, text: str, color: Color, font_size: float = 12.0) -> dict[str, Any]:
    """A billboard ``foxglove.TextPrimitive`` of fixed pixel size."""
    return {
        "pose": _pose(at[0], at[1]),
        "billboard": True,
        "font_size": float(font_size),
        "scale_invariant": True,
        "color": _color(color),
        "text": text,
    }


def scene_entity(
    entity_id: str,
    frame_id: str,
    timestamp_ns: int,
    *,
    lines: Sequence[dict[str, Any]] = (),
    spheres: Sequence[dict[str, Any]] = (),
    cubes: Sequence[dict[str, Any]] = (),
    texts: Sequence[dict[str, Any]] = (),
    metadata: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """A ``foxglove.SceneEntity`` (lifetime 0: kept until replaced by the same ``id``)."""
    return {
        "timestamp": time_msg(timestamp_ns),
        "frame_id": frame_id,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [{"key": k, "value": v} for k, v in (metadata or {}).items()],
        "arrows": [],
        "cubes": list(cubes),
        "spheres": list(spheres),
        "cylinders": [],
        "lines": list(lines),
        "triangles": [],
        "texts": list(texts),
        "models": [],
    }


def circle_points(center: complex, radius: float, n: int = CIRCLE_SEGMENTS) -> list[Point]:
    """``n`` points on the circle ``|w - center| = radius`` (for a line loop)."""
    pts = [center + radius * cmath.exp(2j * math.pi * k / n) for k in range(n)]
    return [(p.real, p.imag) for p in pts]


def robot_color(index: int) -> Color:
    """Colour of the ``index``-th robot (sorted by id)."""
    return ROBOT_COLORS[index % len(ROBOT_COLORS)]


# --------------------------------------------------------------------------------------------
# scenes (pure)


@dataclass(frozen=True)
class RobotView:
    """What a scene shows of one robot, in the scene's own coordinates."""

    position: Point | None = None
    theta: float = 0.0
    goal: Point | None = None
    trail: Sequence[Point] | None = ()  # None: leave the trail entity as it is (not sent)


def _robot_entities(
    robots: Mapping[str, RobotView], frame_id: str, timestamp_ns: int, size: float
) -> list[dict[str, Any]]:
    entities = []
    for i, rid in enumerate(sorted(robots)):
        view = robots[rid]
        color = robot_color(i)
        if view.goal is not None:
            entities.append(
                scene_entity(
                    f"goal/{rid}",
                    frame_id,
                    timestamp_ns,
                    spheres=[sphere_primitive(view.goal, size, GOAL_COLOR)],
                    texts=[text_primitive(view.goal, f"goal {rid}", GOAL_COLOR)],
                )
            )
        if view.position is not None:
            entities.append(
                scene_entity(
                    f"robot/{rid}",
                    frame_id,
                    timestamp_ns,
                    cubes=[cube_primitive(view.position, view.theta, size, color)],
                    texts=[text_primitive(view.position, rid, color)],
                )
            )
        if view.trail is not None and len(view.trail) >= 2:
            entities.append(
                scene_entity(
                    f"trail/{rid}",
                    frame_id,
                    timestamp_ns,
                    lines=[line_primitive(list(view.trail), color, thickness=2.0)],
                )
            )
    return entities


def workspace_scene(
    outer: Sequence[Point],
    obstacles: Sequence[Sequence[Point]],
    timestamp_ns: int,
    robots: Mapping[str, RobotView] | None = None,
    *,
    ws: str = "",
    frame_id: str = WORKSPACE_FRAME,
) -> dict[str, Any]:
    """``foxglove.SceneUpdate`` of a workspace: polygons as line loops, goals, robots, trails.

    Parameters
    ----------
    outer, obstacles : polygon vertices (x, y), any orientation, no repeated closing vertex.
    timestamp_ns : int
        Entity timestamp, nanoseconds since the epoch.
    robots : robot id -> :class:`RobotView` in workspace coordinates.
    """
    xs = [p[0] for p in outer] or [0.0, 1.0]
    ys = [p[1] for p in outer] or [0.0, 1.0]
    size = 0.03 * max(max(xs) - min(xs), max(ys) - min(ys), 1e-9)
    lines = [line_primitive(outer, OUTER_COLOR, loop=True, thickness=3.0)]
    lines += [line_primitive(ob, OBSTACLE_COLOR, loop=True, thickness=3.0) for ob in obstacles]
    entities = [
        scene_entity(
            "workspace",
            frame_id,
            timestamp_ns,
            lines=lines,
            metadata={"ws": ws, "obstacles": str(len(obstacles))},
        )
    ]
    entities += _robot_entities(robots or {}, frame_id, timestamp_ns, size)
    return {"deletions": [], "entities": entities}


def circle_domain_scene(
    centers: Sequence[complex],
    radii: Sequence[float],
    timestamp_ns: int,
    robots: Mapping[str, RobotView] | None = None,
    *,
    ws: str = "",
    frame_id: str = CIRCLE_DOMAIN_FRAME,
) -> dict[str, Any]:
    """``foxglove.SceneUpdate`` of the circle domain ``|w| < 1`` minus ``|w - c_j| <= r_j``.

    ``robots`` are given in circle-domain coordinates (images ``T(z)``).
    """
    if len(centers) != len(radii):
        raise ValueError(f"{len(centers)} centres but {len(radii)} radii")
    lines = [line_primitive(circle_points(0j, 1.0), OUTER_COLOR, loop=True, thickness=3.0)]
    lines += [
        line_primitive(
            circle_points(complex(c), float(r)), OBSTACLE_COLOR, loop=True, thickness=3.0
        )
        for c, r in zip(centers, radii, strict=True)
    ]
    entities = [
        scene_entity(
            "circle_domain",
            frame_id,
            timestamp_ns,
            lines=lines,
            metadata={"ws": ws, "circles": str(len(radii))},
        )
    ]
    entities += _robot_entities(robots or {}, frame_id, timestamp_ns, 0.03)
    return {"deletions": [], "entities": entities}


# --------------------------------------------------------------------------------------------
# reading confnav messages (tolerant of the field layout: plain dicts from JSON)


def parse_key(topic: str, prefix: str = "confnav") -> tuple[str, str, str] | None:
    """Split a confnav key into (kind, id, leaf): ``ws/{ws}/transform`` -> ("ws", ws, "transform").

    Returns None for keys outside ``{prefix}/ws/*/*`` and ``{prefix}/robot/*/*``.
    """
    head = prefix + "/"
    if not topic.startswith(head):
        return None
    parts = topic[len(head) :].split("/")
    if len(parts) != 3 or parts[0] not in ("ws", "robot"):
        return None
    return parts[0], parts[1], parts[2]


def _as_point(value: Any) -> Point | None:
    """(x, y) from ``[x, y]``, ``{"x":..,"y":..}`` or ``{"re":..,"im":..}``; None otherwise."""
    if isinstance(value, Mapping):
        if "x" in value and "y" in value:
            return float(value["x"]), float(value["y"])
        if "re" in value and "im" in value:
            return float(value["re"]), float(value["im"])
        return None
    if isinstance(value, Sequence) and not isinstance(value, str | bytes) and len(value) == 2:
        try:
            return float(value[0]), float(value[1])
        except (TypeError, ValueError):
            return None
    return None


def _polygon(value: Any) -> list[Point]:
    if not isinstance(value, Sequence) or isinstance(value, str | bytes):
        return []
    pts = [_as_point(v) for v in value]
    return [p for p in pts if p is not None]


def extract_position(payload: Mapping[str, Any]) -> tuple[Point, float] | None:
    """Position and heading (rad, 0 if absent) from a pose-like message."""
    for key in ("pose", "position", "point"):
        inner = payload.get(key)
        if isinstance(inner, Mapping):
            found = extract_position(inner)
            if found is not None:
                return found
        elif inner is not None:
            p = _as_point(inner)
            if p is not None:
                return p, _heading(payload)
    p = _as_point(payload)
    if p is None:
        return None
    return p, _heading(payload)


def _heading(payload: Mapping[str, Any]) -> float:
    for key in ("theta", "heading", "yaw"):
        v = payload.get(key)
        if isinstance(v, int | float):
            return float(v)
    return 0.0


def extract_goal(payload: Mapping[str, Any]) -> Point | None:
    """Goal position from a goal message (``goal``/``position``/``x,y`` fields)."""
    for key in ("goal", "target", "position", "point"):
        if key in payload:
            inner = payload[key]
            if isinstance(inner, Mapping):
                found = extract_goal(inner)
                if found is not None:
                    return found
            p = _as_point(inner)
            if p is not None:
                return p
    return _as_point(payload)


def extract_workspace(payload: Mapping[str, Any]) -> tuple[list[Point], list[list[Point]]] | None:
    """(outer, obstacles) from a workspace definition message (``Workspace.to_dict`` layout,
    possibly nested under ``workspace``)."""
    inner = payload.get("workspace")
    if isinstance(inner, Mapping):
        return extract_workspace(inner)
    outer = _polygon(payload.get("outer"))
    if len(outer) < 3:
        return None
    obstacles_raw = payload.get("obstacles") or []
    obstacles = [_polygon(o) for o in obstacles_raw] if isinstance(obstacles_raw, list) else []
    return outer, [o for o in obstacles if len(o) >= 3]


def extract_ws_id(payload: Mapping[str, Any]) -> str | None:
    """The workspace id a robot message names, if any."""
    for key in ("ws", "workspace", "workspace_id", "ws_id"):
        v = payload.get(key)
        if isinstance(v, str) and v:
            return v
    return None


# --------------------------------------------------------------------------------------------
# stateful builder


class SceneMessage(NamedTuple):
    """One scene message to write: topic, SceneUpdate dict, log time (ns)."""

    topic: str
    message: dict[str, Any]
    log_time_ns: int


@dataclass
class _Robot:
    position: Point | None = None
    theta: float = 0.0
    goal: Point | None = None
    ws: str | None = None
    trail: list[Point] = field(default_factory=list)  # decimated poses
    trail_step: float = 0.0  # current minimum distance between trail points
    trail_w: list[Point] = field(default_factory=list)  # images of trail[: len(trail_w)]
    trail_w_map: int = 0  # id() of the map trail_w was computed with
    chart: int | None = None  # active chart on an atlas (from cmd_vel)


@dataclass
class _Ws:
    outer: list[Point]
    obstacles: list[list[Point]]
    cmap: Any = None  # map with T (confnav.ConformalMap) once a transform was seen
    centers: list[complex] = field(default_factory=list)
    radii: list[float] = field(default_factory=list)
    last_emit_ns: int | None = None
    last_full_ns: int | None = None
    dirty: bool = True

    @property
    def diameter(self) -> float:
        xs = [p[0] for p in self.outer]
        ys = [p[1] for p in self.outer]
        return math.hypot(max(xs) - min(xs), max(ys) - min(ys))


def _load_cmap(payload: Mapping[str, Any]) -> Any:
    """A :class:`confnav.ConformalMap` from a transform message, or None (logged)."""
    try:
        from confnav.conformal.cmap import ConformalMap
    except ImportError:  # core not available: circles only
        return None
    candidates: list[Any] = [payload]
    for key in ("map", "cmap", "coefficients", "solution", "transform"):
        if isinstance(payload.get(key), Mapping):
            candidates.insert(0, payload[key])
    for cand in candidates:
        try:
            return ConformalMap.from_dict(dict(cand))
        except Exception:  # any malformed layout: try the next candidate
            continue
    logger.debug("transform message without loadable map coefficients")
    return None


def _circles(payload: Mapping[str, Any], cmap: Any) -> tuple[list[complex], list[float]]:
    if cmap is not None:
        try:
            return [complex(c) for c in cmap.centers], [float(r) for r in cmap.radii]
        except (AttributeError, TypeError):
            pass
    for holder in (payload, *(v for v in payload.values() if isinstance(v, Mapping))):
        centers_raw = holder.get("centers")
        radii_raw = holder.get("radii")
        if isinstance(centers_raw, list) and isinstance(radii_raw, list):
            pts = [_as_point(c) for c in centers_raw]
            if all(p is not None for p in pts) and len(pts) == len(radii_raw):
                return [complex(p[0], p[1]) for p in pts if p is not None], [
                    float(r) for r in radii_raw
                ]
    return [], []


MAP_BATCH = 8
"""Points per call of ``T`` when mapping into the circle domain: the core evaluates a few
points by direct sums in ~0.1 ms, larger batches switch to an FMM costing ~10 ms a call."""


def _image(cmap: Any, points: Sequence[Point]) -> list[Point | None]:
    """``T`` of each point in small batches; None where the map gives NaN (outside)."""
    import numpy as np

    out: list[Point | None] = []
    for i in range(0, len(points), MAP_BATCH):
        z = np.array([complex(p[0], p[1]) for p in points[i : i + MAP_BATCH]], dtype=complex)
        w = np.asarray(cmap.T(z), dtype=complex).reshape(-1)
        out += [(float(v.real), float(v.imag)) if np.isfinite(v) else None for v in w]
    return out


class SceneBuilder:
    """Turns the stream of recorded confnav messages into Foxglove scene messages.

    Feed every recorded message in log-time order to :meth:`observe`; it returns the scene
    messages to write now. Each workspace gets a *light* update (the robots) at most every
    ``period_ns`` of log time and a *full* one (also goals, polygons / circles and trails)
    every ``full_period_ns`` and as soon as a definition, transform or goal changes. Entities
    keep their ``id`` (lifetime 0), so the trails and polygons drawn by a full update stay
    until the next one. :meth:`flush` returns full scenes (call it before closing the file).

    Cost is bounded for the recorder's hot path: trails keep at most ``trail_points`` points
    (a new point only after moving ``trail_resolution`` times the workspace diameter; when
    full, every other point is dropped and the spacing doubled), and each point is mapped into
    the circle domain once, in batches of :data:`MAP_BATCH`.

    Parameters
    ----------
    prefix : key prefix of the recording (default ``confnav``).
    period_ns, full_period_ns : minimum log-time intervals (ns) between light / full updates.
    trail_points : maximum points per robot trail.
    trail_resolution : minimum trail spacing as a fraction of the workspace diameter.
    map_loader : transform message (dict) -> map with ``T`` (and ``centers``, ``radii``);
        default :class:`confnav.ConformalMap` from ``coefficients``; None result: circles only.
    """

    def __init__(
        self,
        prefix: str = "confnav",
        *,
        period_ns: int = DEFAULT_PERIOD_NS,
        full_period_ns: int = DEFAULT_FULL_PERIOD_NS,
        trail_points: int = DEFAULT_TRAIL_POINTS,
        trail_resolution: float = DEFAULT_TRAIL_RESOLUTION,
        map_loader: Callable[[Mapping[str, Any]], Any] | None = None,
    ) -> None:
        if period_ns < 0 or full_period_ns < 0:
            raise ValueError("periods must be >= 0")
        if trail_points < 2:
            raise ValueError("trail_points must be >= 2")
        self._load_map = map_loader or _load_cmap
        self.prefix = prefix
        self.period_ns = int(period_ns)
        self.full_period_ns = int(full_period_ns)
        self.trail_points = int(trail_points)
        self.trail_resolution = float(trail_resolution)
        self._ws: dict[str, _Ws] = {}
        self._robots: dict[str, _Robot] = {}
        self._cells: dict[str, list[list[Point]]] = {}  # atlas ws -> cell outlines

    def _robot(self, rid: str) -> _Robot:
        if rid not in self._robots:
            self._robots[rid] = _Robot()
        return self._robots[rid]

    def observe(
        self, topic: str, payload: Mapping[str, Any], log_time_ns: int
    ) -> list[SceneMessage]:
        """Update the state with one decoded message; return the scene messages due now."""
        parsed = parse_key(topic, self.prefix)
        if parsed is None:
            return []
        kind, ident, leaf = parsed
        if kind == "ws" and leaf == "definition":
            found = extract_workspace(payload)
            if found is None:
                logger.warning("%s: no polygons found in the definition message", topic)
                return []
            old = self._ws.get(ident)
            self._ws[ident] = _Ws(outer=found[0], obstacles=found[1])
            if old is not None:  # same workspace id re-defined: keep the map until re-solved
                self._ws[ident].cmap, self._ws[ident].centers = old.cmap, old.centers
                self._ws[ident].radii = old.radii
        elif kind == "ws" and leaf == "atlas":
            return self._observe_atlas(ident, payload, log_time_ns)
        elif kind == "ws" and leaf == "transform":
            from confnav.atlas.wire import is_chart_ws_id

            if is_chart_ws_id(ident):  # a chart: drawn as its atlas's cell
                return []
            ws = self._ws.get(ident)
            cmap = self._load_map(payload)
            if ws is None:
                # a transform before (or without) its definition: take polygons from the map
                if cmap is None or not hasattr(cmap, "workspace"):
                    return []
                outer = [(z.real, z.imag) for z in cmap.workspace.outer]
                obstacles = [[(z.real, z.imag) for z in ob] for ob in cmap.workspace.obstacles]
                ws = self._ws[ident] = _Ws(outer=outer, obstacles=obstacles)
            ws.cmap = cmap
            ws.centers, ws.radii = _circles(payload, cmap)
            ws.dirty = True
        elif kind == "robot":
            robot = self._robot(ident)
            ws_id = extract_ws_id(payload)
            if ws_id is not None:
                robot.ws = ws_id
            if leaf == "pose":
                found_pose = extract_position(payload)
                if found_pose is None:
                    return []
                robot.position, robot.theta = found_pose
                self._extend_trail(robot)
            elif leaf == "goal":
                robot.goal = extract_goal(payload)
                for ws in self._ws.values():
                    ws.dirty = True
            elif leaf == "cmd_vel" and isinstance(payload.get("chart"), int):
                robot.chart = int(payload["chart"])
                return []
            else:
                return []
        else:
            return []
        return self._due(log_time_ns, force=False)

    def _observe_atlas(
        self, ident: str, payload: Mapping[str, Any], log_time_ns: int
    ) -> list[SceneMessage]:
        """An ``AtlasIndex``: the cells' outlines (and the workspace, if not defined yet)."""
        cells = payload.get("cells")
        if not isinstance(cells, list):
            return []
        self._cells[ident] = [_polygon(c.get("outer")) for c in cells if isinstance(c, Mapping)]
        if ident not in self._ws:
            dec = payload.get("decomposition")
            found = extract_workspace(dec) if isinstance(dec, Mapping) else None
            if found is None:
                return []
            self._ws[ident] = _Ws(outer=found[0], obstacles=found[1])
        self._ws[ident].dirty = True
        return self._due(log_time_ns, force=False)

    def _atlas_entities(
        self, ws_id: str, robots: Mapping[str, _Robot], now_ns: int, full: bool
    ) -> list[dict[str, Any]]:
        """The cells (full updates) and each robot's active cell, in the robot's colour."""
        cells = self._cells.get(ws_id)
        if not cells:
            return []
        out = []
        if full:
            lines = [line_primitive(c, CELL_COLOR, loop=True, thickness=1.0) for c in cells if c]
            out.append(scene_entity("atlas/cells", WORKSPACE_FRAME, now_ns, lines=lines))
        for i, rid in enumerate(sorted(robots)):
            chart = robots[rid].chart
            if chart is None or not 0 <= chart < len(cells) or not cells[chart]:
                continue
            line = line_primitive(cells[chart], robot_color(i), loop=True, thickness=3.0)
            out.append(
                scene_entity(
                    f"chart/{rid}",
                    WORKSPACE_FRAME,
                    now_ns,
                    lines=[line],
                    metadata={"robot": rid, "chart": str(chart)},
                )
            )
        return out

    def _extend_trail(self, robot: _Robot) -> None:
        p = robot.position
        assert p is not None
        if robot.trail:
            q = robot.trail[-1]
            if math.hypot(p[0] - q[0], p[1] - q[1]) < robot.trail_step:
                return
        elif robot.trail_step == 0.0:
            ws = self._ws.get(robot.ws) if robot.ws else None
            if ws is None and len(self._ws) == 1:
                ws = next(iter(self._ws.values()))
            if ws is not None:
                robot.trail_step = self.trail_resolution * ws.diameter
        robot.trail.append(p)
        if len(robot.trail) > self.trail_points:
            keep = [*range(0, len(robot.trail) - 1, 2), len(robot.trail) - 1]
            robot.trail = [robot.trail[i] for i in keep]
            mapped = len(robot.trail_w)
            robot.trail_w = [robot.trail_w[i] for i in keep if i < mapped]
            robot.trail_step = max(2 * robot.trail_step, 1e-12)

    def flush(self, log_time_ns: int) -> list[SceneMessage]:
        """Full scenes of every workspace, regardless of the periods."""
        return self._due(log_time_ns, force=True)

    def _due(self, now_ns: int, force: bool) -> list[SceneMessage]:
        out: list[SceneMessage] = []
        for ws_id, ws in self._ws.items():
            full = (
                force
                or ws.dirty
                or ws.last_full_ns is None
                or now_ns - ws.last_full_ns >= self.full_period_ns
            )
            light = ws.last_emit_ns is None or now_ns - ws.last_emit_ns >= self.period_ns
            if not (full or light):
                continue
            out.extend(self.scenes(ws_id, now_ns, full=full))
            ws.last_emit_ns = now_ns
            if full:
                ws.last_full_ns = now_ns
                ws.dirty = False
        return out

    def _robots_of(self, ws_id: str) -> dict[str, _Robot]:
        single = len(self._ws) == 1
        return {
            rid: r for rid, r in self._robots.items() if r.ws == ws_id or (r.ws is None and single)
        }

    def scenes(self, ws_id: str, now_ns: int, *, full: bool = True) -> list[SceneMessage]:
        """The workspace scene and (once a transform is known) the circle-domain scene;
        ``full=False``: the robots only (goals, trails and polygons stay as last sent)."""
        ws = self._ws[ws_id]
        robots = self._robots_of(ws_id)
        views = {
            rid: RobotView(
                position=r.position,
                theta=r.theta,
                goal=r.goal if full else None,
                trail=list(r.trail) if full else None,
            )
            for rid, r in sorted(robots.items())
        }
        ws_msg = workspace_scene(ws.outer, ws.obstacles, now_ns, views, ws=ws_id)
        if not full:
            ws_msg["entities"] = ws_msg["entities"][1:]
        ws_msg["entities"] += self._atlas_entities(ws_id, robots, now_ns, full)
        out = [SceneMessage(scene_topic(ws_id, self.prefix), ws_msg, now_ns)]
        if ws.radii:
            w_views = {rid: self._map_view(ws.cmap, r, full) for rid, r in sorted(robots.items())}
            cd_msg = circle_domain_scene(ws.centers, ws.radii, now_ns, w_views, ws=ws_id)
            if not full:
                cd_msg["entities"] = cd_msg["entities"][1:]
            out.append(SceneMessage(circle_domain_topic(ws_id, self.prefix), cd_msg, now_ns))
        return out

    def _map_view(self, cmap: Any, robot: _Robot, full: bool) -> RobotView:
        """The robot in the circle domain (images under T; nothing without a map)."""
        if cmap is None or not hasattr(cmap, "T"):
            return RobotView(trail=() if full else None)
        if robot.trail_w_map != id(cmap):
            robot.trail_w, robot.trail_w_map = [], id(cmap)
        goal_z = robot.goal if full else None
        extra = [p for p in (robot.position, goal_z) if p is not None]
        pending = robot.trail[len(robot.trail_w) :] if full else []
        images = _image(cmap, [*extra, *pending])
        pos = images.pop(0) if robot.position is not None else None
        goal = images.pop(0) if goal_z is not None else None
        if full:
            robot.trail_w += [w if w is not None else (math.nan, math.nan) for w in images]
        trail = [w for w in robot.trail_w if math.isfinite(w[0])] if full else None
        return RobotView(position=pos, goal=goal, trail=trail)


# --------------------------------------------------------------------------------------------
# MCAP side


class SceneChannels:
    """Registers the ``foxglove.SceneUpdate`` schema and scene channels lazily on a Writer."""

    def __init__(self, writer: Writer) -> None:
        self._writer = writer
        self._schema_id: int | None = None
        self._channels: dict[str, int] = {}

    def channel_id(self, topic: str) -> int:
        if self._schema_id is None:
            self._schema_id = self._writer.register_schema(
                name=SCENE_SCHEMA_NAME,
                encoding=SCHEMA_ENCODING,
                data=scene_update_schema_text().encode("utf-8"),
            )
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=self._schema_id
            )
        return self._channels[topic]

    def write(self, msg: SceneMessage) -> None:
        data = json.dumps(msg.message, separators=(",", ":")).encode("utf-8")
        self._writer.add_message(
            channel_id=self.channel_id(msg.topic),
            log_time=msg.log_time_ns,
            publish_time=msg.log_time_ns,
            data=data,
        )


class FoxgloveSceneWriter:
    """Recorder hook: adds the Foxglove scene channels to a recording as it is written.

    Usage in the recorder (on the thread that owns the writer, never in a Zenoh callback)::

        viz = FoxgloveSceneWriter(writer, prefix)
        ...                                   # for every recorded message:
        writer.add_message(channel_id, log_time_ns, data, publish_time_ns)
        viz.on_message(topic, data, log_time_ns)
        ...
        viz.close(last_log_time_ns)           # before writer.finish()

    Errors in a message never propagate (a bad message is logged and skipped), so the hook
    cannot break a recording.
    """

    def __init__(
        self,
        writer: Writer,
        prefix: str = "confnav",
        *,
        period_ns: int = DEFAULT_PERIOD_NS,
        full_period_ns: int = DEFAULT_FULL_PERIOD_NS,
        trail_points: int = DEFAULT_TRAIL_POINTS,
        map_loader: Callable[[Mapping[str, Any]], Any] | None = None,
    ) -> None:
        self.builder = SceneBuilder(
            prefix,
            period_ns=period_ns,
            full_period_ns=full_period_ns,
            trail_points=trail_points,
            map_loader=map_loader,
        )
        self.channels = SceneChannels(writer)
        self._last_ns = 0

    def on_message(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Observe one recorded message (raw JSON bytes) and write the scenes due."""
        self._last_ns = max(self._last_ns, int(log_time_ns))
        if parse_key(topic, self.builder.prefix) is None:
            return
        try:
            payload = json.loads(data)
            if not isinstance(payload, Mapping):
                return
            for msg in self.builder.observe(topic, payload, int(log_time_ns)):
                self.channels.write(msg)
        except Exception:  # visualisation must never break the recording
            logger.exception("foxglove scene: skipping message on %s", topic)

    def close(self, log_time_ns: int | None = None) -> None:
        """Write the final scenes (at ``log_time_ns``, default the last message's log time)."""
        now = self._last_ns if log_time_ns is None else int(log_time_ns)
        try:
            for msg in self.builder.flush(now):
                self.channels.write(msg)
        except Exception:  # visualisation must never break the recording
            logger.exception("foxglove scene: final scene failed")


__all__ = [
    "CIRCLE_DOMAIN_FRAME",
    "SCENE_SCHEMA_NAME",
    "WORKSPACE_FRAME",
    "FoxgloveSceneWriter",
    "RobotView",
    "SceneBuilder",
    "SceneChannels",
    "SceneMessage",
    "circle_domain_scene",
    "circle_domain_topic",
    "is_viz_topic",
    "line_primitive",
    "scene_entity",
    "scene_topic",
    "scene_update_schema",
    "scene_update_schema_text",
    "time_msg",
    "workspace_scene",
]
