"""The state behind the Foxglove scenes: confnav messages in, ``foxglove.SceneUpdate`` out.

:class:`SceneBuilder` keeps the workspaces, maps, goals, poses and trails it has seen in the
decoded confnav messages (:mod:`confnav.schemas` models, so every field it reads is one the
wire defines) and returns the scene messages due, built by :mod:`confnav.recording.scene`.
Robots are updated every 0.1 s of log time; goals, polygons, circles and trails every second
(entities persist by id until replaced), trails are decimated to at most 256 points and mapped
once each: the recorder hook stays cheap (well under a millisecond per recorded message).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

from confnav.recording.scene import (
    CELL_COLOR,
    WORKSPACE_FRAME,
    RobotView,
    circle_domain_scene,
    circle_domain_topic,
    circle_points,
    line_primitive,
    robot_color,
    scene_entity,
    scene_topic,
    text_primitive,
    workspace_scene,
)
from confnav.schemas import (
    AtlasIndex,
    CommandBatch,
    Goal,
    Message,
    Movers,
    Pose,
    PoseBatch,
    RobotStatus,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    model_for_key_parts,
)
from confnav.services.keys import KeyError_, Keys

DEFAULT_PERIOD_NS = 100_000_000  # robots and goals: at most every 0.1 s of log time
DEFAULT_FULL_PERIOD_NS = 1_000_000_000  # polygons, circles and trails: every 1 s
DEFAULT_TRAIL_POINTS = 256  # maximum points per robot trail
DEFAULT_TRAIL_RESOLUTION = 0.002  # minimum trail spacing / workspace diameter

Point = tuple[float, float]
MOVER_COLOR = (0.95, 0.55, 0.0, 1.0)  # movers (people, forklifts): orange


class MapLike(Protocol):
    """What the builder needs of a conformal map: ``T`` on an array of complex points."""

    def T(self, z: Any) -> Any: ...


def decode_on_key(keys: Keys, key: str, data: bytes) -> Message | None:
    """The message on ``key`` decoded with that key's schema; None if ``key`` carries no
    confnav message (outside the layout, e.g. a scene topic). Raises
    :class:`confnav.schemas.DecodeError` for a payload that is not a valid message."""
    try:
        parsed = keys.parse(key)
    except KeyError_:
        return None
    model = model_for_key_parts(parsed.group, parsed.kind)
    return None if model is None else decode(model, data)


def load_scene_map(solution: TransformSolution) -> MapLike:
    """The :class:`confnav.ConformalMap` of a solution (T only: no navigation precompute).

    Raises :class:`confnav.errors.ConfnavError` (or ``ValueError``) if the coefficients do not
    load or belong to another workspace."""
    from confnav.conformal.cmap import ConformalMap
    from confnav.errors import MapMismatchError

    cmap = ConformalMap.from_dict(solution.coefficients)
    if cmap.workspace_hash != solution.workspace_hash:
        raise MapMismatchError(
            f"solution {solution.revision[:12]} declares workspace "
            f"{solution.workspace_hash[:12]} but its map was solved for {cmap.workspace_hash[:12]}"
        )
    return cmap


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
    map_ws: str | None = None  # the workspace whose map drives it ({ws}~r{R} with a footprint)
    lookahead: float = 0.0  # a unicycle's steered point is this far ahead of the axle


@dataclass
class _Ws:
    outer: list[Point]
    obstacles: list[list[Point]]
    cmap: MapLike | None = None  # the map once a transform was seen
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


MAP_BATCH = 8
"""Points per call of ``T`` when mapping into the circle domain: the core evaluates a few
points by direct sums in ~0.1 ms, larger batches switch to an FMM costing ~10 ms a call."""


def _image(cmap: MapLike, points: Sequence[Point]) -> list[Point | None]:
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
    map_loader : solution -> map with ``T`` (default :func:`load_scene_map`).
    """

    def __init__(
        self,
        prefix: str = "confnav",
        *,
        period_ns: int = DEFAULT_PERIOD_NS,
        full_period_ns: int = DEFAULT_FULL_PERIOD_NS,
        trail_points: int = DEFAULT_TRAIL_POINTS,
        trail_resolution: float = DEFAULT_TRAIL_RESOLUTION,
        map_loader: Callable[[TransformSolution], MapLike] | None = None,
    ) -> None:
        if period_ns < 0 or full_period_ns < 0:
            raise ValueError("periods must be >= 0")
        if trail_points < 2:
            raise ValueError("trail_points must be >= 2")
        self._load_map = map_loader or load_scene_map
        self.prefix = prefix
        self.period_ns = int(period_ns)
        self.full_period_ns = int(full_period_ns)
        self.trail_points = int(trail_points)
        self.trail_resolution = float(trail_resolution)
        self._ws: dict[str, _Ws] = {}
        self._robots: dict[str, _Robot] = {}
        self._cells: dict[str, list[list[Point]]] = {}  # atlas ws -> cell outlines
        self._movers: dict[str, Movers] = {}  # floor (base ws id) -> latest movers

    def _robot(self, rid: str) -> _Robot:
        if rid not in self._robots:
            self._robots[rid] = _Robot()
        return self._robots[rid]

    def observe(self, message: Message, log_time_ns: int) -> list[SceneMessage]:
        """Update the state with one decoded message; return the scene messages due now.

        Messages other than workspace definitions, transforms, goals, poses and robot statuses
        change nothing. A transform whose map does not load raises (its circles are kept and
        drawn; the caller logs and counts the error)."""
        if isinstance(message, WorkspaceDefinition):
            old = self._ws.get(message.ws_id)
            ws = self._ws[message.ws_id] = _Ws(outer=message.outer, obstacles=message.obstacles)
            if old is not None:  # same workspace id re-defined: keep the map until re-solved
                ws.cmap, ws.centers, ws.radii = old.cmap, old.centers, old.radii
        elif isinstance(message, AtlasIndex):
            self._on_atlas(message)
        elif isinstance(message, TransformSolution):
            from confnav.atlas.wire import is_chart_ws_id

            if is_chart_ws_id(message.ws_id):  # a chart: drawn as its atlas's cell
                return []
            self._on_transform(message)
        elif isinstance(message, Goal):
            from confnav.maps.footprint import derived_ws_id

            robot = self._robot(message.robot_id)
            robot.ws, robot.goal = message.ws_id, message.goal
            # the map it drives on: its workspace shrunk by its footprint (docs/NAVIGATION.md)
            unicycle = message.drive == "unicycle"
            robot.lookahead = message.lookahead if unicycle else 0.0
            robot.map_ws = derived_ws_id(message.ws_id, message.robot_radius + robot.lookahead)
            for ws in self._ws.values():
                ws.dirty = True
        elif isinstance(message, Pose | PoseBatch):  # a batch: a simulator's poses of one step
            for pose in message.poses() if isinstance(message, PoseBatch) else (message,):
                robot = self._robot(pose.robot_id)
                robot.position, robot.theta = (pose.x, pose.y), pose.theta
                self._extend_trail(robot)
        elif isinstance(message, RobotStatus) and message.ws_id is not None:
            self._robot(message.robot_id).ws = message.ws_id
        elif isinstance(message, Movers):
            self._movers[message.ws_id.split("~", 1)[0]] = message
        elif isinstance(message, VelocityCommand) and message.chart is not None:
            self._robot(message.robot_id).chart = message.chart
            return []
        elif isinstance(message, CommandBatch):  # a controller's answers to a PoseBatch
            for rid, chart in zip(message.robot_ids, message.chart, strict=True):
                if chart is not None:
                    self._robot(rid).chart = chart
            return []
        else:
            return []
        return self._due(log_time_ns, force=False)

    def _on_transform(self, solution: TransformSolution) -> None:
        ws = self._ws.get(solution.ws_id)
        if ws is None:
            # a transform before (or without) its definition (the live view fetches the maps
            # at start): the polygons come from the map's own workspace
            cmap = self._load_map(solution)
            core = getattr(cmap, "workspace", None)  # None: a stand-in map without polygons
            if core is None:
                return
            outer = [(z.real, z.imag) for z in core.outer]
            obstacles = [[(z.real, z.imag) for z in ob] for ob in core.obstacles]
            ws = self._ws[solution.ws_id] = _Ws(outer=outer, obstacles=obstacles, cmap=cmap)
        else:
            ws.cmap = None  # the old map is not this solution's
        ws.centers = [complex(x, y) for x, y in solution.centers]
        ws.radii = list(solution.radii)
        ws.dirty = True
        if ws.cmap is None:
            ws.cmap = self._load_map(solution)  # raises on a bad map: circles still drawn

    def _on_atlas(self, index: AtlasIndex) -> None:
        """The cells' outlines (and the whole workspace, if not defined yet)."""
        self._cells[index.ws_id] = [list(c.outer) for c in index.cells]
        if index.ws_id not in self._ws:
            from confnav.geometry import Workspace

            ws = Workspace.from_dict(index.decomposition["workspace"])
            self._ws[index.ws_id] = _Ws(
                outer=[(z.real, z.imag) for z in ws.outer],
                obstacles=[[(z.real, z.imag) for z in ob] for ob in ws.obstacles],
            )
        self._ws[index.ws_id].dirty = True

    def _atlas_entities(
        self, ws_id: str, robots: dict[str, _Robot], now_ns: int, full: bool
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
            if chart is None or not 0 <= chart < len(cells):
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
        ws_msg["entities"] += self._mover_entities(ws_id, now_ns)
        out = [SceneMessage(scene_topic(ws_id, self.prefix), ws_msg, now_ns)]
        if ws.radii:
            # in a circle domain only the robots that drive on its map (a robot with a footprint
            # drives on the map of {ws}~r{R}, drawn in that workspace's circle domain)
            single = len(self._ws) == 1
            on_map = {
                rid: r
                for rid, r in self._robots.items()
                if (r.map_ws or r.ws) == ws_id or (r.ws is None and single)
            }
            w_views = {rid: self._map_view(ws.cmap, r, full) for rid, r in sorted(on_map.items())}
            cd_msg = circle_domain_scene(ws.centers, ws.radii, now_ns, w_views, ws=ws_id)
            if not full:
                cd_msg["entities"] = cd_msg["entities"][1:]
            out.append(SceneMessage(circle_domain_topic(ws_id, self.prefix), cd_msg, now_ns))
        return out

    def _mover_entities(self, ws_id: str, now_ns: int) -> list[dict[str, Any]]:
        """One entity ``movers`` (replaced each time, so a mover that is gone disappears):
        each mover's disk, its velocity as a line to where it will be in 1 s, its id."""
        m = self._movers.get(ws_id.split("~", 1)[0])
        if m is None:
            return []
        lines, texts = [], []
        for d in m.movers:
            c = complex(*d.position)
            lines.append(line_primitive(circle_points(c, d.radius), MOVER_COLOR, loop=True))
            v = complex(*d.velocity)
            if v != 0:
                ahead = (c + v).real, (c + v).imag  # where it will be in 1 s
                lines.append(line_primitive([d.position, ahead], MOVER_COLOR))
            texts.append(text_primitive(d.position, d.mover_id, MOVER_COLOR, font_size=10.0))
        return [
            scene_entity(
                "movers",
                WORKSPACE_FRAME,
                now_ns,
                lines=lines,
                texts=texts,
                metadata={"movers": str(len(m.movers))},
            )
        ]

    def _map_view(self, cmap: MapLike | None, robot: _Robot, full: bool) -> RobotView:
        """The robot in the circle domain (images under T; nothing without a map)."""
        if cmap is None:
            return RobotView(trail=() if full else None)
        if robot.trail_w_map != id(cmap):
            robot.trail_w, robot.trail_w_map = [], id(cmap)
        goal_z = robot.goal if full else None
        steered = robot.position
        if steered is not None and robot.lookahead:  # a unicycle: the map steers the point ahead
            d, th = robot.lookahead, robot.theta
            steered = (steered[0] + d * math.cos(th), steered[1] + d * math.sin(th))
        extra = [p for p in (steered, goal_z) if p is not None]
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
