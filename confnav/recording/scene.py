"""Foxglove ``foxglove.SceneUpdate`` scenes of confnav workspaces: pure builders.

Two scenes per workspace ``ws`` (topics under the recording's key prefix, default ``confnav``):

- ``{prefix}/viz/{ws}/scene`` (frame ``workspace``): the outer polygon and the obstacles as
  line loops, each robot's goal (sphere), the robot itself (flat cube turned by its heading)
  and its trail (line strip).
- ``{prefix}/viz/{ws}/circle_domain`` (frame ``circle_domain``): the unit circle and the obstacle
  circles ``|w - c_j| = r_j`` of the solved map as line loops, and the images ``T(z)`` of the
  goals, robots and trails.

Messages are JSON (message encoding ``json``) conforming to the official Foxglove JSON Schema,
vendored unchanged in ``schemas/foxglove/SceneUpdate.json`` (schema name
``foxglove.SceneUpdate``, schema encoding ``jsonschema``), so a recording opens in Foxglove with
a 2-D scene (3D panel, display frame ``workspace`` or ``circle_domain``).

This module holds the pure functions of plain data (primitives, :func:`workspace_scene`,
:func:`circle_domain_scene`, topics, the schema text). The state that turns a stream of confnav
messages into scenes is :mod:`confnav.recording.scene_builder`; writing scene channels into an
MCAP file (recorder hook, ``confnav viz``) is :mod:`confnav.recording.scene_writer`. All times
are integer nanoseconds since the Unix epoch.
"""

from __future__ import annotations

import cmath
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

SCENE_SCHEMA_NAME = "foxglove.SceneUpdate"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
WORKSPACE_FRAME = "workspace"
CIRCLE_DOMAIN_FRAME = "circle_domain"
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


__all__ = [
    "CIRCLE_DOMAIN_FRAME",
    "SCENE_SCHEMA_NAME",
    "WORKSPACE_FRAME",
    "RobotView",
    "circle_domain_scene",
    "circle_domain_topic",
    "is_viz_topic",
    "line_primitive",
    "robot_color",
    "scene_entity",
    "scene_topic",
    "scene_update_schema",
    "scene_update_schema_text",
    "time_msg",
    "workspace_scene",
]
