"""Wire messages of confnav: strict, versioned pydantic v2 models.

Every message is JSON on the wire and in MCAP. Each carries ``type`` (``"confnav.<Model>"``)
and ``schema_version`` so that a payload names its own model. Timestamps are integer
nanoseconds since the Unix epoch (``time.time_ns()``); positions and velocities are in the
workspace frame, metres and metres per second; angles in radians.

Validate from bytes with ``Model.model_validate_json(data)`` (or :func:`confnav.schemas.decode`,
which also enforces the size limit). Models are strict (no coercion), reject unknown fields
and non-finite numbers, and are frozen.
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, JsonValue, StringConstraints, model_validator

from confnav.navigation import defaults

SCHEMA_VERSION: int = 1
"""Version of every model below; bump (and keep a reader for the old one) on breaking change."""

MAX_VERTICES = 4096
MAX_OBSTACLES = 256
MAX_ROBOTS_PER_CONFIG = 1024

MAX_ID_LENGTH = 64
ID_PATTERN = r"^[^*$#?/\s@][^*$#?/\s]*$"
"""The id rule (also :func:`confnav.services.keys.validate_id`): a Zenoh key chunk with no
``* $ # ? /``, no whitespace, not starting with ``@`` (verbatim chunks)."""

Id = Annotated[
    str,
    StringConstraints(min_length=1, max_length=MAX_ID_LENGTH, pattern=ID_PATTERN),
]
"""A key chunk: no ``* $ # ? /``, no whitespace, not starting with ``@``."""

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
TimeNs = Annotated[int, Field(ge=0)]
Point = tuple[Finite, Finite]
"""A point or planar vector ``[x, y]``."""
Polygon = Annotated[list[Point], Field(min_length=3, max_length=MAX_VERTICES)]


class Message(BaseModel):
    """Base of all wire messages (strict, frozen, no extra fields, finite numbers)."""

    model_config = ConfigDict(
        strict=True,
        extra="forbid",
        frozen=True,
        allow_inf_nan=False,
        json_schema_serialization_defaults_required=True,
    )
    TYPE: ClassVar[str] = ""


class WorkspaceDefinition(Message):
    """A polygonal workspace to be solved, put on ``{prefix}/ws/{ws}/definition``.

    ``outer`` is the outer polygon, ``obstacles`` the holes (any orientation, no repeated
    closing vertex); ``anchor`` the point mapped to 0 (None: maximal clearance); ``tol`` the
    solver tolerance.
    """

    TYPE: ClassVar[str] = "confnav.WorkspaceDefinition"
    type: Literal["confnav.WorkspaceDefinition"] = "confnav.WorkspaceDefinition"
    schema_version: Literal[1] = 1
    ws_id: Id
    outer: Polygon
    obstacles: Annotated[list[Polygon], Field(max_length=MAX_OBSTACLES)] = []
    anchor: Point | None = None
    tol: Annotated[float, Field(gt=0.0, le=1e-3)] = 1e-10
    stamp_ns: TimeNs = 0


class WorkspaceDelete(Message):
    """Remove a workspace from the transform service (and its saved definition), on
    ``{prefix}/ws/{ws}/delete``; controllers drop its map and stop its robots."""

    TYPE: ClassVar[str] = "confnav.WorkspaceDelete"
    type: Literal["confnav.WorkspaceDelete"] = "confnav.WorkspaceDelete"
    schema_version: Literal[1] = 1
    ws_id: Id
    stamp_ns: TimeNs = 0


class SolveDiagnostics(Message):
    """Solver diagnostics copied from :class:`confnav.ConformalMap.diagnostics`."""

    TYPE: ClassVar[str] = "confnav.SolveDiagnostics"
    type: Literal["confnav.SolveDiagnostics"] = "confnav.SolveDiagnostics"
    schema_version: Literal[1] = 1
    sweeps: Annotated[int, Field(ge=0)]
    error_estimate: Annotated[float, Field(ge=0.0)]
    wall_time: Annotated[float, Field(ge=0.0)]
    tol: Annotated[float, Field(ge=0.0)]
    nodes: list[Annotated[int, Field(ge=0)]] = []
    #: Largest distance of T from its circle at boundary points between the nodes (issue 8).
    boundary_residual: Annotated[float, Field(ge=0.0)]
    tol_met: bool


class TransformSolution(Message):
    """A solved map, put on ``{prefix}/ws/{ws}/transform`` and served by its queryable.

    ``revision`` is the content hash of the coefficients (:attr:`ConformalMap.revision`),
    ``definition_hash`` that of the workspace definition it was solved from, ``workspace_hash``
    the :attr:`Workspace.content_hash` the map is bound to. ``coefficients``
    is :meth:`ConformalMap.to_dict` (lossless); ``centers``/``radii`` the circle domain.
    """

    TYPE: ClassVar[str] = "confnav.TransformSolution"
    type: Literal["confnav.TransformSolution"] = "confnav.TransformSolution"
    schema_version: Literal[1] = 1
    ws_id: Id
    revision: Annotated[str, Field(min_length=1, max_length=128)]
    definition_hash: Annotated[str, Field(min_length=1, max_length=128)]
    #: ``Workspace.content_hash`` of the workspace the map was solved for (issue 8).
    workspace_hash: Annotated[str, Field(min_length=1, max_length=128)]
    stamp_ns: TimeNs
    anchor: Point
    centers: list[Point]
    radii: list[Annotated[float, Field(gt=0.0, allow_inf_nan=False)]]
    diagnostics: SolveDiagnostics
    coefficients: dict[str, JsonValue]


class TransformStatus(Message):
    """State of one workspace in the transform service, on ``{prefix}/ws/{ws}/status``."""

    TYPE: ClassVar[str] = "confnav.TransformStatus"
    type: Literal["confnav.TransformStatus"] = "confnav.TransformStatus"
    schema_version: Literal[1] = 1
    ws_id: Id
    stamp_ns: TimeNs
    state: Literal["solving", "solved", "failed", "deleted"]
    definition_hash: str
    revision: str | None = None
    message: Annotated[str, Field(max_length=4096)] = ""


NavFnName = Literal["harmonic", "kr"]
SpeedLawName = Literal["normalized", "theorem2"]
DriveName = Literal["holonomic", "unicycle"]


class Goal(Message):
    """Navigation goal of one robot, on ``{prefix}/robot/{r}/goal``.

    ``navfn`` names the navigation function (``harmonic``: tuning free; ``kr``:
    Koditschek-Rimon with exponent ``k``, None for the library's certified default);
    ``speed_law`` ``normalized`` commands the unit direction of the Theorem 2 field times
    ``min(v_max, gain * distance to goal)``, ``theorem2`` the plain law (``gain`` = K)
    saturated at ``v_max``; ``v_max`` is the speed limit (m/s), ``tolerance`` the arrival
    radius (m).  Every default is the library's (``confnav.navigation.defaults``).
    ``robot_radius`` (m, 0: a point) navigates the robot's centre in the free space shrunk by
    it (the map of the derived workspace ``{ws_id}~r{radius}``); ``drive`` ``unicycle`` steers
    the point ``lookahead`` (m) ahead of the axle with ``v`` and ``omega`` limited by ``v_max``
    and ``omega_max`` (rad/s), and the free space is shrunk by ``robot_radius + lookahead``.
    """

    TYPE: ClassVar[str] = "confnav.Goal"
    type: Literal["confnav.Goal"] = "confnav.Goal"
    schema_version: Literal[1] = 1
    robot_id: Id
    ws_id: Id
    goal: Point
    navfn: NavFnName = defaults.NAVFN
    k: Annotated[float, Field(ge=1.0, le=1000.0)] | None = None
    speed_law: SpeedLawName = defaults.SPEED_LAW
    gain: Positive = defaults.GAIN
    v_max: Positive = defaults.V_MAX
    tolerance: Positive = defaults.GOAL_TOL
    stamp_ns: TimeNs = 0
    robot_radius: Annotated[float, Field(ge=0.0, le=1000.0, allow_inf_nan=False)] = 0.0
    drive: DriveName = "holonomic"
    lookahead: Positive = 0.1
    omega_max: Positive = 2.0


class GoalCancel(Message):
    """Cancel the goal of one robot, on ``{prefix}/robot/{r}/cancel``: the controller sends a
    zero command, reports ``idle`` and forgets the robot."""

    TYPE: ClassVar[str] = "confnav.GoalCancel"
    type: Literal["confnav.GoalCancel"] = "confnav.GoalCancel"
    schema_version: Literal[1] = 1
    robot_id: Id
    stamp_ns: TimeNs = 0


class Pose(Message):
    """Timestamped robot pose, on ``{prefix}/robot/{r}/pose``; ``seq`` counts poses."""

    TYPE: ClassVar[str] = "confnav.Pose"
    type: Literal["confnav.Pose"] = "confnav.Pose"
    schema_version: Literal[1] = 1
    robot_id: Id
    stamp_ns: TimeNs
    seq: Annotated[int, Field(ge=0)] = 0
    x: Finite
    y: Finite
    theta: Finite = 0.0


class VelocityCommand(Message):
    """Twist-like command, on ``{prefix}/robot/{r}/cmd_vel``.

    ``frame`` ``world`` (default): ``linear`` is ``[vx, vy]`` in the workspace frame (m/s),
    ``angular`` the yaw rate (rad/s). ``frame`` ``body`` (unicycles): a twist in the robot's
    body frame, ``linear = [v, 0]`` (linear.x, forward speed, m/s) and ``angular`` = angular.z
    (rad/s). ``pose_seq``/``pose_stamp_ns`` identify the pose it answers (-1/0: none, e.g.
    watchdog stop).
    """

    TYPE: ClassVar[str] = "confnav.VelocityCommand"
    type: Literal["confnav.VelocityCommand"] = "confnav.VelocityCommand"
    schema_version: Literal[1] = 1
    robot_id: Id
    stamp_ns: TimeNs
    linear: Point
    angular: Finite = 0.0
    pose_seq: Annotated[int, Field(ge=-1)] = -1
    pose_stamp_ns: TimeNs = 0
    map_revision: str | None = None
    frame: Literal["world", "body"] = "world"
    chart: Annotated[int, Field(ge=0)] | None = None
    """Active chart (cell index) of a robot driven on an atlas (None: a single map)."""


RobotState = Literal["idle", "navigating", "arrived", "stopped"]
StatusReason = Literal[
    "ok",
    "no_goal",
    "arrived",
    "stale_pose",
    "missing_map",
    "nan_input",
    "invalid_input",
    "transform_service_dead",
    "outside_workspace",
    "solve_failed",
    "navigation_error",
    "map_outdated",
    "unreachable",
]


#: How a ``navigating`` status's message starts while the robot holds (zero command) for the
#: first revision of a map that is being solved (progressive maps, docs/SERVICES.md).
WAITING_FOR_MAP = "waiting for the first revision of map"


class RobotStatus(Message):
    """Controller's view of one robot, on ``{prefix}/robot/{r}/status``.

    ``state`` ``stopped`` always comes with a ``reason`` saying why the command is zero; a
    ``navigating`` robot may hold (zero command) while its map's first revision is being
    solved, its message then starting with :data:`WAITING_FOR_MAP`.
    """

    TYPE: ClassVar[str] = "confnav.RobotStatus"
    type: Literal["confnav.RobotStatus"] = "confnav.RobotStatus"
    schema_version: Literal[1] = 1
    robot_id: Id
    stamp_ns: TimeNs
    state: RobotState
    reason: StatusReason
    message: Annotated[str, Field(max_length=4096)] = ""
    ws_id: str | None = None
    map_revision: str | None = None
    position: Point | None = None
    distance_to_goal: Finite | None = None
    chart: Annotated[int, Field(ge=0)] | None = None
    """Active chart (cell index) of a robot driven on an atlas (None: a single map)."""


class CollisionEvent(Message):
    """Simulator report: the robot left the free space (``clearance`` <= 0, metres), or its
    disk touched another robot's (``other_robot_id`` names it; ``clearance`` is then the gap
    between the two disks at their closest approach along the step, <= 0, and ``position``
    this robot's centre there)."""

    TYPE: ClassVar[str] = "confnav.CollisionEvent"
    type: Literal["confnav.CollisionEvent"] = "confnav.CollisionEvent"
    schema_version: Literal[1] = 1
    robot_id: Id
    ws_id: Id
    stamp_ns: TimeNs
    position: Point
    clearance: Finite
    other_robot_id: Id | None = None
    """The other robot of a robot-robot contact (None: a wall)."""


class SpawnRequest(Message):
    """Ask the simulator ``{prefix}/sim/{sim}/spawn`` to add (or move) a robot.

    ``robot_radius`` (m): the simulator checks collisions of the disk of this radius;
    ``drive`` ``unicycle``: the robot moves only by body-frame twists (``VelocityCommand``
    with ``frame="body"``).
    """

    TYPE: ClassVar[str] = "confnav.SpawnRequest"
    type: Literal["confnav.SpawnRequest"] = "confnav.SpawnRequest"
    schema_version: Literal[1] = 1
    robot_id: Id
    ws_id: Id
    position: Point
    theta: Finite = 0.0
    stamp_ns: TimeNs = 0
    robot_radius: Annotated[float, Field(ge=0.0, le=1000.0, allow_inf_nan=False)] = 0.0
    drive: DriveName = "holonomic"


class SimControl(Message):
    """Pause, resume or reset the simulator (``robot_id`` None: all robots)."""

    TYPE: ClassVar[str] = "confnav.SimControl"
    type: Literal["confnav.SimControl"] = "confnav.SimControl"
    schema_version: Literal[1] = 1
    action: Literal["pause", "resume", "reset", "remove"]
    robot_id: Id | None = None
    stamp_ns: TimeNs = 0


class ServiceHealth(Message):
    """Periodic health of a service process, on ``{prefix}/health/{service}/{zid}``."""

    TYPE: ClassVar[str] = "confnav.ServiceHealth"
    type: Literal["confnav.ServiceHealth"] = "confnav.ServiceHealth"
    schema_version: Literal[1] = 1
    service: Id
    zid: Id
    stamp_ns: TimeNs
    state: Literal["ok", "degraded"]
    uptime_s: Annotated[float, Field(ge=0.0)]
    counters: dict[str, int] = {}
    detail: Annotated[str, Field(max_length=4096)] = ""
    #: Current values (queue depths, memory), unlike the cumulative ``counters``.
    gauges: dict[str, int] = {}


class AtlasCell(Message):
    """One cell of an atlas: its free space exactly (``outer`` with ``obstacles`` as holes; the
    chart's workspace is this polygon without collinear vertices), the cut
    edges (polylines of the boundary that are no walls), its core tile ``(x0, y0, x1, y1)``,
    and the chart: the ``TransformSolution`` of workspace ``chart_ws_id`` (``{ws}~c{i}``)."""

    TYPE: ClassVar[str] = "confnav.AtlasCell"
    type: Literal["confnav.AtlasCell"] = "confnav.AtlasCell"
    schema_version: Literal[1] = 1
    index: Annotated[int, Field(ge=0)]
    chart_ws_id: Id
    chart_revision: Annotated[str, Field(min_length=1, max_length=128)]
    outer: Polygon
    obstacles: Annotated[list[Polygon], Field(max_length=MAX_OBSTACLES)] = []
    cut: list[Annotated[list[Point], Field(min_length=2, max_length=MAX_VERTICES)]] = []
    tile: tuple[Finite, Finite, Finite, Finite]
    solve_time: Annotated[float, Field(ge=0.0)] = 0.0
    #: the chart is not solved yet (a progressive atlas's partial revision): no
    #: ``TransformSolution`` to fetch for it; ``chart_revision`` is a placeholder
    pending: bool = False


class AtlasIndex(Message):
    """A workspace solved as an atlas of charts, on ``{prefix}/ws/{ws}/atlas`` (put on change
    + queryable); each cell's chart is a ``TransformSolution`` on
    ``{prefix}/ws/{ws}~c{i}/transform``.  ``margin`` is the decomposition's overlap depth
    (local goals lie at least that deep in the next cell); ``revision`` changes with any chart;
    ``decomposition`` the whole workspace and the parameters that made the cells;
    ``wall_time``/``cpu_time`` the elapsed and summed per-chart solve times.
    """

    TYPE: ClassVar[str] = "confnav.AtlasIndex"
    type: Literal["confnav.AtlasIndex"] = "confnav.AtlasIndex"
    schema_version: Literal[1] = 1
    ws_id: Id
    revision: Annotated[str, Field(min_length=1, max_length=128)]
    definition_hash: Annotated[str, Field(min_length=1, max_length=128)]
    stamp_ns: TimeNs
    margin: Positive
    tol: Positive
    cells: Annotated[list[AtlasCell], Field(min_length=1, max_length=4096)]
    decomposition: dict[str, JsonValue]
    wall_time: Annotated[float, Field(ge=0.0)] = 0.0
    cpu_time: Annotated[float, Field(ge=0.0)] = 0.0


MAX_ROUTES = 256
"""Most route hints in one :class:`MapQuery`."""


class RouteHint(Message):
    """One robot's route for :class:`MapQuery`: where it starts (the point its law steers: the
    position, or a unicycle's look-ahead point) and its goal, workspace frame (m)."""

    TYPE: ClassVar[str] = "confnav.RouteHint"
    type: Literal["confnav.RouteHint"] = "confnav.RouteHint"
    schema_version: Literal[1] = 1
    robot_id: Id | None = None
    start: Point
    goal: Point


class MapQuery(Message):
    """The optional payload of a query on ``{prefix}/ws/{ws}/transform`` or
    ``{prefix}/ws/{ws}/atlas`` (a query without payload is answered the same way): the routes
    of the robots waiting for that map. A transform service solving the workspace as a
    progressive atlas solves the charts these routes need first (docs/SLAM.md, "Progressive
    atlas"); routes outside the workspace are ignored. Hints only order the solve: the
    answer, the atlas and its charts do not depend on them."""

    TYPE: ClassVar[str] = "confnav.MapQuery"
    type: Literal["confnav.MapQuery"] = "confnav.MapQuery"
    schema_version: Literal[1] = 1
    stamp_ns: TimeNs = 0
    routes: Annotated[list[RouteHint], Field(max_length=MAX_ROUTES)] = []


MAX_MOVERS = 1024


class MoverDisk(Message):
    """One moving obstacle that is not a robot (a person, a forklift): a disk of ``radius``
    (m) at ``position`` moving with ``velocity`` (m/s, workspace frame; [0, 0] if unknown)."""

    TYPE: ClassVar[str] = "confnav.MoverDisk"
    type: Literal["confnav.MoverDisk"] = "confnav.MoverDisk"
    schema_version: Literal[1] = 1
    mover_id: Id
    position: Point
    radius: Positive
    velocity: Point = (0.0, 0.0)


class Movers(Message):
    """The moving obstacles of a workspace at ``stamp_ns``, on ``{prefix}/ws/{ws}/movers``
    (from a tracker, a person detector or a simulation).  Each message is the complete list:
    a mover missing from it is gone.  Controllers keep every robot's disk off the movers'
    disks (docs/NAVIGATION.md, "Fleets"), using their velocities."""

    TYPE: ClassVar[str] = "confnav.Movers"
    type: Literal["confnav.Movers"] = "confnav.Movers"
    schema_version: Literal[1] = 1
    ws_id: Id
    stamp_ns: TimeNs
    movers: Annotated[list[MoverDisk], Field(max_length=MAX_MOVERS)] = []


MAX_BATCH = 4096
"""Most robots in one :class:`PoseBatch` or :class:`CommandBatch`."""
Seq = Annotated[int, Field(ge=0)]


def _same_lengths(m: BaseModel, columns: tuple[str, ...]) -> None:
    n = len(getattr(m, columns[0]))
    bad = [c for c in columns[1:] if len(getattr(m, c)) != n]
    if bad:
        raise ValueError(f"columns {', '.join(bad)} do not have {n} entries as {columns[0]}")
    ids = getattr(m, columns[0])
    if len(set(ids)) != n:
        raise ValueError(f"{columns[0]}: a robot appears more than once")


class PoseBatch(Message):
    """The poses of many robots at one instant, on ``{prefix}/sim/{sim}/poses`` (optional: a
    simulator that steps all its robots at once publishes one message per step instead of one
    :class:`Pose` per robot; docs/SERVICES.md, "Scale"). Columns of equal length: entry ``i``
    is ``Pose(robot_id=robot_ids[i], stamp_ns=stamps_ns[i], seq=seq[i], x=x[i], y=y[i],
    theta=theta[i])``; a robot appears at most once. A controller answers the robots it drives
    with one :class:`CommandBatch` on ``{prefix}/sim/{sim}/cmd_vel``."""

    TYPE: ClassVar[str] = "confnav.PoseBatch"
    type: Literal["confnav.PoseBatch"] = "confnav.PoseBatch"
    schema_version: Literal[1] = 1
    sim_id: Id
    stamp_ns: TimeNs
    robot_ids: Annotated[list[Id], Field(max_length=MAX_BATCH)]
    stamps_ns: Annotated[list[TimeNs], Field(max_length=MAX_BATCH)]
    seq: Annotated[list[Seq], Field(max_length=MAX_BATCH)]
    x: Annotated[list[Finite], Field(max_length=MAX_BATCH)]
    y: Annotated[list[Finite], Field(max_length=MAX_BATCH)]
    theta: Annotated[list[Finite], Field(max_length=MAX_BATCH)]

    @model_validator(mode="after")
    def _columns(self) -> PoseBatch:
        _same_lengths(self, ("robot_ids", "stamps_ns", "seq", "x", "y", "theta"))
        return self

    def poses(self) -> list[Pose]:
        """The batch's entries as :class:`Pose` messages, in order."""
        return [
            Pose(robot_id=r, stamp_ns=t, seq=q, x=x, y=y, theta=th)
            for r, t, q, x, y, th in zip(
                self.robot_ids, self.stamps_ns, self.seq, self.x, self.y, self.theta, strict=True
            )
        ]


class CommandBatch(Message):
    """A controller's answers to one :class:`PoseBatch`, on ``{prefix}/sim/{sim}/cmd_vel``
    (optional, see :class:`PoseBatch`). Columns of equal length: entry ``i`` is
    ``VelocityCommand(robot_id=robot_ids[i], stamp_ns=stamp_ns, linear=linear[i],
    angular=angular[i], pose_seq=pose_seq[i], pose_stamp_ns=pose_stamp_ns[i],
    map_revision=map_revision[i], frame=frame[i], chart=chart[i])``; a robot appears at most
    once. Several controllers (shards) each answer their own robots."""

    TYPE: ClassVar[str] = "confnav.CommandBatch"
    type: Literal["confnav.CommandBatch"] = "confnav.CommandBatch"
    schema_version: Literal[1] = 1
    sim_id: Id
    stamp_ns: TimeNs
    robot_ids: Annotated[list[Id], Field(max_length=MAX_BATCH)]
    linear: Annotated[list[Point], Field(max_length=MAX_BATCH)]
    angular: Annotated[list[Finite], Field(max_length=MAX_BATCH)]
    pose_seq: Annotated[list[Annotated[int, Field(ge=-1)]], Field(max_length=MAX_BATCH)]
    pose_stamp_ns: Annotated[list[TimeNs], Field(max_length=MAX_BATCH)]
    map_revision: Annotated[list[str | None], Field(max_length=MAX_BATCH)]
    frame: Annotated[list[Literal["world", "body"]], Field(max_length=MAX_BATCH)]
    chart: Annotated[list[Annotated[int, Field(ge=0)] | None], Field(max_length=MAX_BATCH)]

    @model_validator(mode="after")
    def _columns(self) -> CommandBatch:
        cols = ("robot_ids", "linear", "angular", "pose_seq", "pose_stamp_ns", "map_revision",
                "frame", "chart")  # fmt: skip
        _same_lengths(self, cols)
        return self

    def commands(self) -> list[VelocityCommand]:
        """The batch's entries as :class:`VelocityCommand` messages, in order."""
        return [
            VelocityCommand(robot_id=r, stamp_ns=self.stamp_ns, linear=lin, angular=a,
                            pose_seq=q, pose_stamp_ns=t, map_revision=rev, frame=f, chart=c)
            for r, lin, a, q, t, rev, f, c in zip(
                self.robot_ids, self.linear, self.angular, self.pose_seq, self.pose_stamp_ns,
                self.map_revision, self.frame, self.chart, strict=True,
            )
        ]  # fmt: skip
