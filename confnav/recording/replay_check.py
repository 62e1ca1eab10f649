"""``confnav replay --check FILE.mcap``: recompute every recorded command, deterministically.

The recorded inputs of the controller (transform solutions, goals, poses) are fed in log-time
order, without Zenoh, through the same code the live controller service runs
(:mod:`confnav.services.navigation`: ``load_map``, ``make_controller``, ``command``); each
recorded ``cmd_vel`` that answers a pose (``pose_seq``/``pose_stamp_ns``; each entry of a
``CommandBatch`` answering a ``PoseBatch`` counts as one) is recomputed from
that pose, the goal in force at the command's log time and the map it names
(``map_revision``), and compared with the recorded one.

Tolerance: a command matches when ``|u_recorded - u_recomputed| <= atol + rtol * |u_recorded|``
(complex velocities, m/s; a unicycle's body-frame twist as ``v + i omega``, recomputed from
the pose's heading) with defaults ``atol = 1e-9`` m/s and ``rtol = 1e-9``: the same code
on the same map coefficients and the same (JSON round-tripped, exact) inputs is expected to
agree to rounding; any change of gains, navigation function or code shows up far above it.

What the controller decides from state outside the recording cannot be recomputed and is not
compared: watchdog stops (``pose_seq = -1``, stale poses) are counted as skipped. Commands the
live controller zeroed because no transform service was alive are recognised from the
recorded ``status`` messages (reason ``transform_service_dead``) and also skipped.

Use ``overrides`` (``--set gain=2``) to recompute with changed goal parameters: the check then
reports where the new parameters would have commanded something else.
"""

from __future__ import annotations

import cmath
import json
import logging
import math
import os
from collections import OrderedDict, defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from confnav.atlas.wire import atlas_map_of
from confnav.errors import ConfnavError
from confnav.recording.reader import Recording, RecordingError, decode_message
from confnav.schemas import (
    AtlasIndex,
    CommandBatch,
    Goal,
    Pose,
    PoseBatch,
    RobotStatus,
    TransformSolution,
    VelocityCommand,
)
from confnav.services import navigation

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
DEFAULT_ATOL = 1e-9  # m/s
DEFAULT_RTOL = 1e-9
GOAL_OVERRIDABLE = ("gain", "v_max", "k", "navfn", "speed_law", "tolerance")
_POSE_MEMORY = 4096  # poses kept per robot to match commands to (pose_seq, pose_stamp_ns)


class CheckError(ConfnavError):
    """Bad check options (unknown override field, bad value)."""


@dataclass(frozen=True)
class Mismatch:
    """A recorded command the recomputation does not reproduce."""

    robot_id: str
    log_time_ns: int
    t_s: float  # seconds after the recording start
    pose: tuple[float, float]
    pose_seq: int
    recorded: complex
    recomputed: complex
    reason: str

    @property
    def error(self) -> float:
        return abs(self.recorded - self.recomputed)

    def format(self) -> str:
        return (
            f"t={self.t_s:9.4f} s  robot {self.robot_id}  pose #{self.pose_seq} "
            f"({self.pose[0]:.6f}, {self.pose[1]:.6f}): recorded ({self.recorded.real:.9g}, "
            f"{self.recorded.imag:.9g}) recomputed ({self.recomputed.real:.9g}, "
            f"{self.recomputed.imag:.9g}) |diff| {self.error:.3g} m/s  [{self.reason}]"
        )


@dataclass
class CheckReport:
    """Outcome of :func:`check_recording`."""

    path: str
    atol: float
    rtol: float
    checked: int = 0
    matched: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)
    mismatch_count: int = 0
    skipped: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    max_error: float = 0.0
    per_robot: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    overrides: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.checked > 0 and self.mismatch_count == 0

    def format(self, max_report: int = 10) -> str:
        lines = [
            f"{self.path}: checked {self.checked} commands "
            f"({', '.join(f'{r}: {n}' for r, n in sorted(self.per_robot.items())) or 'none'}), "
            f"tolerance |du| <= {self.atol:g} + {self.rtol:g}*|u| m/s"
        ]
        if self.overrides:
            lines.append(f"goal overrides: {json.dumps(self.overrides, sort_keys=True)}")
        if self.skipped:
            skipped = ", ".join(f"{k}: {v}" for k, v in sorted(self.skipped.items()))
            lines.append(f"not comparable (skipped): {skipped}")
        lines.append(f"largest difference: {self.max_error:.3g} m/s")
        if self.checked == 0:
            hint = ""
            if self.skipped.get("map revision not recorded"):
                hint = (
                    " (the maps the commands name are not in the recording: start the recorder"
                    " before the transform service publishes)"
                )
            lines.append(f"FAIL: no command could be checked{hint}")
        elif self.mismatch_count == 0:
            lines.append(f"OK: all {self.checked} recomputed commands match")
        else:
            lines.append(
                f"FAIL: {self.mismatch_count} of {self.checked} commands differ; first "
                f"{min(max_report, len(self.mismatches))}:"
            )
            lines += ["  " + m.format() for m in self.mismatches[:max_report]]
        return "\n".join(lines)


def decide(
    ctrl: navigation.ControllerLike | None, x: float, y: float, theta: float = 0.0
) -> tuple[complex, str]:
    """The command the live controller publishes for a pose: zero without a controller, else
    what :func:`confnav.services.navigation.decide` (the controller service's own decision)
    makes of the control law's output from :func:`confnav.services.navigation.command`
    (a unicycle's body twist ``v + i omega`` from the pose's heading)."""
    if ctrl is None:
        return 0j, "no controller"
    u, code = navigation.command(ctrl, x, y, theta)
    u, code, _ = navigation.reenter(ctrl, x, y, theta, u, code)  # as the service does
    d = navigation.decide(ctrl, u, code)
    return d.u, d.message or d.reason


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["gain=2", "navfn=kr"]`` -> ``{"gain": 2.0, "navfn": "kr"}`` (goal fields only)."""
    out: dict[str, Any] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in GOAL_OVERRIDABLE:
            raise CheckError(
                f"bad override {item!r}: use FIELD=VALUE, FIELD one of "
                f"{', '.join(GOAL_OVERRIDABLE)}"
            )
        if name in ("navfn", "speed_law"):
            out[name] = value.strip()
        elif name == "k" and value.strip().lower() in ("auto", "none"):
            out[name] = None
        else:
            try:
                out[name] = float(value)
            except ValueError:
                raise CheckError(f"bad override {item!r}: {value!r} is not a number") from None
    return out


def _apply(goal: Goal, overrides: Mapping[str, Any]) -> Goal:
    if not overrides:
        return goal
    data = goal.model_dump()
    data.update(overrides)
    try:
        return Goal.model_validate(data)
    except ValueError as exc:
        raise CheckError(f"override makes the goal invalid: {exc}") from None


class _Controllers:
    """Controllers built with the live controller's factory, cached per (goal, map revision)."""

    def __init__(
        self,
        load_map: Callable[[TransformSolution], Any],
        make_controller: Callable[[Any, Goal], navigation.ControllerLike],
    ) -> None:
        self._load_map = load_map
        self._make = make_controller
        self.maps: dict[str, Any] = {}  # revision -> cmap
        self._ctrls: OrderedDict[tuple[str, str], navigation.ControllerLike | None] = OrderedDict()

    def add_solution(self, sol: TransformSolution) -> None:
        if sol.revision not in self.maps:
            try:
                self.maps[sol.revision] = self._load_map(sol)
            except Exception as exc:  # e.g. coefficients of an older serialisation format
                raise RecordingError(
                    f"the recorded map {sol.revision[:12]} of workspace {sol.ws_id!r} cannot be "
                    f"loaded by this version: {type(exc).__name__}: {exc}"
                ) from exc

    def add_atlas(self, index: AtlasIndex) -> None:
        """An atlas from its recorded index and charts (confnav.atlas.wire.atlas_map_of)."""
        if index.revision not in self.maps:
            try:
                self.maps[index.revision] = atlas_map_of(index, self.maps)
            except ConfnavError as exc:  # its commands count as "map revision not recorded"
                logger.warning("%s", exc)

    def get(self, goal: Goal, revision: str) -> navigation.ControllerLike | None:
        key = (goal.model_dump_json(), revision)
        if key in self._ctrls:
            self._ctrls.move_to_end(key)
            return self._ctrls[key]
        try:
            ctrl: navigation.ControllerLike | None = self._make(self.maps[revision], goal)
        except Exception as exc:  # like the live controller: the robot is stopped (zero)
            logger.info("controller for %s cannot be built: %s", goal.robot_id, exc)
            ctrl = None
        self._ctrls[key] = ctrl
        if len(self._ctrls) > 64:
            self._ctrls.popitem(last=False)
        return ctrl


def check_recording(
    path: str | os.PathLike[str],
    *,
    atol: float = DEFAULT_ATOL,
    rtol: float = DEFAULT_RTOL,
    overrides: Mapping[str, Any] | None = None,
    max_mismatches: int = 100,
    load_map: Callable[[TransformSolution], Any] = navigation.load_map,
    make_controller: Callable[[Any, Goal], navigation.ControllerLike] = navigation.make_controller,
) -> CheckReport:
    """Recompute every recorded command of ``path`` and compare (see the module docstring).

    Raises :class:`RecordingError` if the recording has no commands, or commands whose map or
    goal was not recorded.
    """
    if not (atol >= 0 and rtol >= 0 and math.isfinite(atol) and math.isfinite(rtol)):
        raise CheckError("tolerances must be finite and >= 0")
    overrides = dict(overrides or {})
    report = CheckReport(path=str(path), atol=atol, rtol=rtol, overrides=overrides)
    ctrls = _Controllers(load_map, make_controller)
    goals: dict[str, Goal] = {}
    poses: dict[str, OrderedDict[tuple[int, int], Pose]] = defaultdict(OrderedDict)
    dead_since: dict[str, int] = {}  # robot -> log time of a transform_service_dead status
    with Recording(path) as rec:
        kinds = {c.topic.rsplit("/", 1)[-1] for c in rec.channels.values()}
        if "cmd_vel" not in kinds:
            raise RecordingError(f"{rec.path}: no cmd_vel channel recorded: nothing to check")
        if "transform" not in kinds:
            raise RecordingError(
                f"{rec.path}: no transform channel recorded: the maps the controller used are "
                "missing, commands cannot be recomputed"
            )
        if not {"pose", "poses"} & kinds or "goal" not in kinds:
            raise RecordingError(f"{rec.path}: no pose or goal channel recorded")
        start = rec.start_ns
        for msg in rec.iter_messages():
            model = decode_message(msg)
            if isinstance(model, TransformSolution):
                ctrls.add_solution(model)
            elif isinstance(model, AtlasIndex):  # after its charts (published first)
                ctrls.add_atlas(model)
            elif isinstance(model, Goal):
                goals[model.robot_id] = _apply(model, overrides)
            elif isinstance(model, Pose | PoseBatch):  # a batch: each entry is one Pose
                for pose in model.poses() if isinstance(model, PoseBatch) else (model,):
                    memo = poses[pose.robot_id]
                    memo[(pose.seq, pose.stamp_ns)] = pose
                    if len(memo) > _POSE_MEMORY:
                        memo.popitem(last=False)
            elif isinstance(model, RobotStatus):
                if model.reason == "transform_service_dead":
                    dead_since.setdefault(model.robot_id, msg.log_time_ns)
                else:
                    dead_since.pop(model.robot_id, None)
            elif isinstance(model, VelocityCommand | CommandBatch):  # a batch: each entry
                cmds = model.commands() if isinstance(model, CommandBatch) else (model,)
                for cmd in cmds:
                    t = msg.log_time_ns
                    _check_one(report, cmd, t, start, goals, poses, ctrls, dead_since)
                    if len(report.mismatches) > max_mismatches:
                        report.mismatches.pop()
    return report


def _check_one(
    report: CheckReport,
    cmd: VelocityCommand,
    log_time_ns: int,
    start_ns: int,
    goals: Mapping[str, Goal],
    poses: Mapping[str, OrderedDict[tuple[int, int], Pose]],
    ctrls: _Controllers,
    dead_since: Mapping[str, int],
) -> None:
    rid = cmd.robot_id
    body = cmd.frame == "body"  # a unicycle's twist: u = v + i omega
    recorded = complex(cmd.linear[0], cmd.angular if body else cmd.linear[1])
    if cmd.pose_seq < 0:
        report.skipped["watchdog stop (no pose)"] += 1
        return
    pose = poses.get(rid, OrderedDict()).get((cmd.pose_seq, cmd.pose_stamp_ns))
    if pose is None:
        report.skipped["pose not recorded"] += 1
        return
    goal = goals.get(rid)
    if goal is None:
        report.skipped["goal not recorded"] += 1
        return
    if rid in dead_since and recorded == 0:
        report.skipped["stop: transform service dead"] += 1
        return
    if cmd.map_revision is None:
        expected, why = 0j, "no map"
    elif cmd.map_revision not in ctrls.maps:
        report.skipped["map revision not recorded"] += 1
        return
    else:
        expected, why = decide(ctrls.get(goal, cmd.map_revision), pose.x, pose.y, pose.theta)
    report.checked += 1
    report.per_robot[rid] += 1
    err = abs(recorded - expected) if cmath.isfinite(expected) else math.inf
    report.max_error = max(report.max_error, err)
    if err <= report.atol + report.rtol * abs(recorded):
        report.matched += 1
        return
    report.mismatch_count += 1
    report.mismatches.append(
        Mismatch(
            robot_id=rid,
            log_time_ns=log_time_ns,
            t_s=(log_time_ns - start_ns) / NS_PER_S,
            pose=(pose.x, pose.y),
            pose_seq=pose.seq,
            recorded=recorded,
            recomputed=expected,
            reason=why,
        )
    )


__all__ = [
    "DEFAULT_ATOL",
    "DEFAULT_RTOL",
    "CheckError",
    "CheckReport",
    "Mismatch",
    "check_recording",
    "decide",
    "parse_overrides",
]
