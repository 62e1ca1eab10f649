"""``confnav inspect``: what a person wants to know about a recorded run.

:func:`inspect_recording` reads a recording (:mod:`confnav.recording.reader`) and summarises
it: channels, counts, duration, robots, whether and when each arrived, minimum clearance per
robot, and the closest approach of any two robots' disks (:func:`closest_approach`).
:meth:`InspectReport.format` and :func:`report_json` print it; the figure is
:func:`confnav.plot.recording.plot_recording`.

Time origin: every time in a report (``t = ...``, ``arrival_time_s``) is seconds after the log
time of the recording's first message (``start_ns``).
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from confnav.errors import ConfnavError
from confnav.recording.layout import METADATA_NAME
from confnav.recording.reader import NS_PER_S, ChannelInfo, Recording, decode_message
from confnav.recording.scene import SCENE_SCHEMA_NAME
from confnav.schemas import (
    MODELS_BY_TYPE,
    AtlasIndex,
    CollisionEvent,
    CommandBatch,
    Goal,
    Pose,
    PoseBatch,
    RobotStatus,
    SpawnRequest,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
)
from confnav.services.navigation import map_ws_id

logger = logging.getLogger(__name__)


@dataclass
class RobotSummary:
    """What happened to one robot in a recording (times: s after the recording start)."""

    robot_id: str
    ws_id: str | None = None
    poses: int = 0
    commands: int = 0
    start: tuple[float, float] | None = None
    end: tuple[float, float] | None = None
    goal: tuple[float, float] | None = None
    tolerance: float | None = None
    path_length: float = 0.0
    arrived: bool = False
    arrival_time_s: float | None = None
    goal_time_s: float | None = None  # when the (last) goal was recorded
    arrival_source: str = ""
    final_state: str | None = None
    final_reason: str | None = None
    min_clearance: float | None = None
    min_clearance_at: tuple[float, float] | None = None
    collision_time_s: float | None = None
    collision_at: tuple[float, float] | None = None
    trajectory: list[tuple[float, float]] = field(default_factory=list)
    charts: list[int] = field(default_factory=list)  # active charts in order (atlas only)
    map_ws_id: str | None = None  # the workspace whose map drove it ({ws}~r{R} with a radius)
    map_revision: str | None = None  # of the last command or status that named one
    atlas: str | None = None  # ws_id of the atlas it was driven on (None: a single map)
    chart: int | None = None  # its active chart at the end (atlas only)
    radius: float = 0.0  # body radius (m) from its spawn request or goal
    pose_stamps: list[int] = field(default_factory=list)  # stamp_ns of each trajectory point
    robot_contacts: list[str] = field(default_factory=list)  # robots it touched (simulator)


@dataclass
class AtlasHistory:
    """The revisions of one workspace's atlas in a recording (a progressive atlas publishes
    partial revisions, cells ``pending``, then complete ones: docs/SLAM.md "Progressive
    atlas"); times: s after the recording start."""

    revisions: int = 0  # distinct revisions recorded
    partial: int = 0  # of them, with pending cells
    first_charts: int = 0  # charts solved in the first revision recorded
    first_cells: int = 0  # its cells
    first_time_s: float | None = None  # log time of the first revision
    complete_time_s: float | None = None  # log time of the first revision with no pending cell
    _seen: set[str] = field(default_factory=set, repr=False)

    def add(self, index: AtlasIndex, t_s: float) -> None:
        """File a recorded index (a revision recorded twice, e.g. latched into a later
        segment, counts once)."""
        if index.revision in self._seen:
            return
        self._seen.add(index.revision)
        pending = sum(bool(c.pending) for c in index.cells)
        if self.revisions == 0:
            self.first_charts, self.first_cells = len(index.cells) - pending, len(index.cells)
            self.first_time_s = t_s
        self.revisions += 1
        self.partial += pending > 0
        if pending == 0 and self.complete_time_s is None:
            self.complete_time_s = t_s

    def format(self) -> str:
        """E.g. "first published after 2 of 11 charts (5 revisions, 3 partial)"."""
        if self.partial == 0:
            return f"{self.revisions} revision{'s' if self.revisions != 1 else ''}, complete"
        when = ""
        if self.first_time_s is not None and self.complete_time_s is not None:
            when = f"; complete {self.complete_time_s - self.first_time_s:.2f} s after the first"
        return (
            f"first published after {self.first_charts} of {self.first_cells} charts "
            f"({self.revisions} revisions, {self.partial} partial{when})"
        )


@dataclass
class InspectReport:
    """Summary of a recording (see :func:`inspect_recording`)."""

    path: Path
    prefix: str
    message_count: int
    start_ns: int
    end_ns: int
    channels: list[ChannelInfo]
    metadata: dict[str, dict[str, str]]
    workspaces: dict[str, WorkspaceDefinition]
    transforms: dict[str, TransformSolution]
    robots: dict[str, RobotSummary]
    unknown_schemas: list[str]
    invalid_messages: int
    atlases: dict[str, AtlasIndex] = field(default_factory=dict)
    #: per atlas workspace, its recorded revisions (partial ones of a progressive atlas)
    atlas_history: dict[str, AtlasHistory] = field(default_factory=dict)
    #: the closest approach of two robots (:func:`closest_approach`), None: fewer than two
    closest: dict[str, Any] | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS_PER_S if self.message_count else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "prefix": self.prefix,
            "messages": self.message_count,
            "duration_s": self.duration_s,
            "time_origin": "first recorded message (start_ns)",
            "start_ns": self.start_ns,
            "channels": [
                {
                    "topic": c.topic,
                    "schema": c.schema_name,
                    "encoding": c.message_encoding,
                    "count": c.count,
                }
                for c in self.channels
            ],
            "workspaces": sorted(self.workspaces),
            "atlases": {
                w: {
                    "revision": a.revision,
                    "cells": len(a.cells),
                    "robots": self.atlas_robots(w),
                    "cells_used": self.cells_used(w),
                    **(
                        {
                            "revisions": h.revisions,
                            "partial_revisions": h.partial,
                            "first_charts": h.first_charts,
                            "first_time_s": h.first_time_s,
                            "complete_time_s": h.complete_time_s,
                        }
                        if (h := self.atlas_history.get(w)) is not None
                        else {}
                    ),
                }
                for w, a in sorted(self.atlases.items())
            },
            "robots": {
                rid: {
                    "ws_id": r.ws_id,
                    "poses": r.poses,
                    "commands": r.commands,
                    "goal": r.goal,
                    "arrived": r.arrived,
                    "arrival_time_s": r.arrival_time_s,
                    "goal_time_s": r.goal_time_s,
                    "final_state": r.final_state,
                    "path_length": r.path_length,
                    "min_clearance": r.min_clearance,
                    "collision_time_s": r.collision_time_s,
                    "charts": r.charts,
                    "map_ws_id": r.map_ws_id,
                    "atlas": r.atlas,
                    "active_chart": r.chart,
                }
                for rid, r in sorted(self.robots.items())
            },
            "unknown_schemas": self.unknown_schemas,
            "invalid_messages": self.invalid_messages,
            "closest_robot_approach": self.closest,
            "robot_contacts": sorted(
                {
                    tuple(sorted((rid, o)))
                    for rid, r in self.robots.items()
                    for o in r.robot_contacts
                }
            ),
        }

    def atlas_robots(self, ws_id: str) -> list[str]:
        """The robots driven on the atlas ``ws_id``."""
        return sorted(rid for rid, r in self.robots.items() if r.atlas == ws_id)

    def cells_used(self, ws_id: str) -> list[int]:
        """The cells of atlas ``ws_id`` that some robot had as its active chart."""
        return sorted({c for rid in self.atlas_robots(ws_id) for c in self.robots[rid].charts})

    def format(self) -> str:
        """Human-readable report."""
        out = [
            f"file:      {self.path}",
            f"prefix:    {self.prefix}",
            f"messages:  {self.message_count}",
            f"duration:  {self.duration_s:.3f} s",
            "times:     t = 0 at the first recorded message",
        ]
        meta = self.metadata.get(METADATA_NAME)
        if meta:
            versions = ", ".join(
                f"{k.removesuffix('_version')} {v}"
                for k, v in meta.items()
                if k.endswith("_version")
            )
            out.append(f"versions:  {versions}")
        out.append("")
        width = max([len(c.topic) for c in self.channels] + [5])
        out.append(f"{'topic':<{width}}  {'count':>7}  schema")
        for c in self.channels:
            note = "  (invalid payloads)" if c.invalid else ""
            out.append(f"{c.topic:<{width}}  {c.count:>7}  {c.schema_name or '-'}{note}")
        if self.unknown_schemas:
            out.append(f"\nunknown schemas (not decoded): {', '.join(self.unknown_schemas)}")
        if self.invalid_messages:
            out.append(f"invalid payloads recorded: {self.invalid_messages}")
        for ws_id, wd in sorted(self.workspaces.items()):
            tr = self.transforms.get(ws_id)
            atlas = self.atlases.get(ws_id)
            solved = (
                f"solved as an atlas of {len(atlas.cells)} charts (revision {atlas.revision[:12]})"
                if atlas
                else f"solved (revision {tr.revision[:12]}, {len(tr.radii)} circles)"
                if tr
                else "no transform recorded"
            )
            out.append(f"\nworkspace {ws_id}: {len(wd.obstacles)} obstacles, {solved}")
        for ws_id, atlas in sorted(self.atlases.items()):  # what each atlas was used for
            robots = self.atlas_robots(ws_id)
            used = (
                f"used by {', '.join(robots)}: cells {_ranges(self.cells_used(ws_id))} active"
                if robots
                else "used by no robot"
            )
            out.append(f"atlas {ws_id}: {len(atlas.cells)} cells, {used}")
            hist = self.atlas_history.get(ws_id)
            if hist is not None and hist.partial:  # a progressive atlas
                out.append(f"atlas {ws_id}: {len(atlas.cells)} charts, {hist.format()}")
        if not self.robots:
            out.append("\nno robots recorded")
        if self.closest is not None:
            near = self.closest
            out.append(
                f"\nclosest robot-robot approach: {near['robots'][0]} and {near['robots'][1]}, "
                f"centres {near['distance']:.4f} m apart, "
                f"gap {near['gap']:.4f} m between their disks "
                f"(radii {near['radii'][0]:g}, {near['radii'][1]:g}) at t = {near['time_s']:.3f} s"
                + ("  CONTACT" if near["gap"] <= 0 else "")
            )
        for rid, r in sorted(self.robots.items()):
            out += self._robot_lines(rid, r)
        return "\n".join(out)

    def _robot_lines(self, rid: str, r: RobotSummary) -> list[str]:
        """The report's lines on one robot: path, map, arrival, collisions, clearance."""
        out: list[str] = []
        out.append(f"\nrobot {rid}" + (f" (workspace {r.ws_id})" if r.ws_id else ""))
        out.append(f"  poses {r.poses}, commands {r.commands}, path {r.path_length:.3f} m")
        if r.start is not None and r.end is not None:
            out.append(f"  start {_fmt_pt(r.start)} -> end {_fmt_pt(r.end)}")
        if r.goal is not None:
            out.append(f"  goal {_fmt_pt(r.goal)}")
        if r.atlas is not None:
            a = self.atlases[r.atlas]
            out.append(
                f"  map: atlas {r.atlas} ({len(a.cells)} cells, revision {a.revision[:12]})"
                + (f", active chart {r.chart}" if r.chart is not None else "")
            )
        elif r.map_ws_id is not None and r.map_ws_id != r.ws_id:
            out.append(f"  map: {r.map_ws_id}")
        if r.charts:
            path = " -> ".join(map(str, r.charts))
            out.append(f"  charts {path} ({len(r.charts) - 1} switches)")
        if r.arrived and r.arrival_time_s is not None:
            after = (
                f", {r.arrival_time_s - r.goal_time_s:.3f} s after its goal"
                if r.goal_time_s is not None and r.goal_time_s <= r.arrival_time_s
                else ""
            )
            out.append(f"  arrived at t = {r.arrival_time_s:.3f} s{after} ({r.arrival_source})")
        else:
            state = f" (last state {r.final_state}/{r.final_reason})" if r.final_state else ""
            out.append(f"  did not arrive{state}")
        if r.collision_at is not None and r.collision_time_s is not None:
            out.append(
                f"  COLLISION at t = {r.collision_time_s:.3f} s at {_fmt_pt(r.collision_at)}"
            )
        if r.robot_contacts:
            out.append(f"  touched robot(s) {', '.join(sorted(set(r.robot_contacts)))}")
        if r.min_clearance is not None and r.min_clearance_at is not None:
            out.append(
                f"  minimum clearance {r.min_clearance:.4f} m at {_fmt_pt(r.min_clearance_at)}"
            )
        else:
            out.append("  minimum clearance: n/a (no workspace definition recorded)")
        return out


def _ranges(xs: list[int]) -> str:
    """``0-3, 7, 9-10`` for sorted integers."""
    out: list[str] = []
    for x in xs:
        if out and out[-1].rpartition("-")[2] == str(x - 1):
            head = out[-1].partition("-")[0]
            out[-1] = f"{head}-{x}"
        else:
            out.append(str(x))
    return ", ".join(out)


def _fmt_pt(p: tuple[float, float]) -> str:
    return f"({p[0]:.3f}, {p[1]:.3f})"


def _core_workspace(wd: WorkspaceDefinition) -> Any:
    """The core :class:`confnav.geometry.Workspace` of a definition (for clearances)."""
    from confnav.geometry import Workspace

    return Workspace(wd.outer, wd.obstacles, anchor=wd.anchor)


def _unknown_schemas(channels: list[ChannelInfo]) -> list[str]:
    """Schemas of valid channels that are neither wire models nor the scene schema."""
    return sorted(
        {
            c.schema_name or f"(none, encoding {c.message_encoding})"
            for c in channels
            if not c.invalid
            and c.schema_name not in MODELS_BY_TYPE
            and c.schema_name != SCENE_SCHEMA_NAME
        }
    )


@dataclass
class _Scan:
    """What one pass over a recording's messages collects (the latest definition, solution
    and atlas index per workspace; per robot, :class:`RobotSummary`)."""

    workspaces: dict[str, WorkspaceDefinition] = field(default_factory=dict)
    transforms: dict[str, TransformSolution] = field(default_factory=dict)
    atlases: dict[str, AtlasIndex] = field(default_factory=dict)
    #: every recorded atlas revision -> its ws_id
    atlas_of_revision: dict[str, str] = field(default_factory=dict)
    atlas_history: dict[str, AtlasHistory] = field(default_factory=dict)
    robots: dict[str, RobotSummary] = field(default_factory=dict)
    status_arrival: dict[str, int] = field(default_factory=dict)
    pose_times: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    #: messages per channel, counted here: the statistics record is optional
    counts: Counter[int] = field(default_factory=Counter)
    first_ns: int | None = None
    last_ns: int = 0

    def robot(self, rid: str) -> RobotSummary:
        if rid not in self.robots:
            self.robots[rid] = RobotSummary(robot_id=rid)
        return self.robots[rid]

    def add(self, channel_id: int, log_time_ns: int, model: Any) -> None:
        """Count a message and file its decoded ``model`` (None: not a wire model)."""
        self.counts[channel_id] += 1
        self.first_ns = log_time_ns if self.first_ns is None else self.first_ns
        self.last_ns = max(self.last_ns, log_time_ns)
        if isinstance(model, WorkspaceDefinition):
            self.workspaces[model.ws_id] = model
        elif isinstance(model, TransformSolution):
            self.transforms[model.ws_id] = model
        elif isinstance(model, Pose):
            self._pose(model, log_time_ns)
        elif isinstance(model, PoseBatch):  # a simulator's poses of one step: each is a Pose
            for pose in model.poses():
                self._pose(pose, log_time_ns)
        elif isinstance(model, CommandBatch):  # a controller's answers to a PoseBatch
            for command in model.commands():
                self._command(command)
        elif isinstance(model, Goal):
            self._goal(model, log_time_ns)
        elif isinstance(model, SpawnRequest):
            r = self.robot(model.robot_id)
            r.radius = max(r.radius, model.robot_radius)
        elif isinstance(model, AtlasIndex):
            self.atlases[model.ws_id] = model
            self.atlas_of_revision[model.revision] = model.ws_id
            t0 = self.first_ns if self.first_ns is not None else log_time_ns
            hist = self.atlas_history.setdefault(model.ws_id, AtlasHistory())
            hist.add(model, (log_time_ns - t0) / NS_PER_S)
        elif isinstance(model, VelocityCommand):
            self._command(model)
        elif isinstance(model, CollisionEvent):
            self._collision(model, log_time_ns)
        elif isinstance(model, RobotStatus):
            self._status(model, log_time_ns)

    def _pose(self, model: Pose, log_time_ns: int) -> None:
        r = self.robot(model.robot_id)
        p = (model.x, model.y)
        if r.trajectory:
            q = r.trajectory[-1]
            r.path_length += math.hypot(p[0] - q[0], p[1] - q[1])
        r.trajectory.append(p)
        self.pose_times[model.robot_id].append(log_time_ns)
        r.pose_stamps.append(model.stamp_ns or log_time_ns)
        r.poses += 1

    def _goal(self, model: Goal, log_time_ns: int) -> None:
        assert self.first_ns is not None
        r = self.robot(model.robot_id)
        r.goal = (model.goal[0], model.goal[1])
        r.tolerance = model.tolerance
        r.ws_id = model.ws_id
        r.map_ws_id = map_ws_id(model)
        r.goal_time_s = (log_time_ns - self.first_ns) / NS_PER_S
        r.radius = max(r.radius, model.robot_radius)

    def _command(self, model: VelocityCommand) -> None:
        r = self.robot(model.robot_id)
        r.commands += 1
        if model.chart is not None and (not r.charts or r.charts[-1] != model.chart):
            r.charts.append(model.chart)
        r.chart = model.chart
        r.map_revision = model.map_revision or r.map_revision

    def _collision(self, model: CollisionEvent, log_time_ns: int) -> None:
        r = self.robot(model.robot_id)
        if model.other_robot_id is not None:
            r.robot_contacts.append(model.other_robot_id)
        if r.collision_at is None:
            r.collision_at = (model.position[0], model.position[1])
            r.collision_time_s = (log_time_ns - (self.first_ns or 0)) / NS_PER_S

    def _status(self, model: RobotStatus, log_time_ns: int) -> None:
        r = self.robot(model.robot_id)
        r.final_state, r.final_reason = model.state, model.reason
        r.map_revision = model.map_revision or r.map_revision
        if model.chart is not None:
            r.chart = model.chart
        if model.ws_id and r.ws_id is None:
            r.ws_id = model.ws_id
        if model.state == "arrived" and model.robot_id not in self.status_arrival:
            self.status_arrival[model.robot_id] = log_time_ns

    def finish_robot(self, rid: str, r: RobotSummary, start: int) -> None:
        """After the pass: start and end, arrival, the atlas driven on, the workspace and the
        smallest clearance of robot ``rid``."""
        if r.trajectory:
            r.start, r.end = r.trajectory[0], r.trajectory[-1]
        self._arrival(rid, r, start)
        # the atlas it was driven on: the one its commands name, else its goal's map
        used = self.atlas_of_revision.get(r.map_revision or "") or r.map_ws_id
        r.atlas = used if used in self.atlases and (r.charts or r.chart is not None) else None
        if r.ws_id is None and len(self.workspaces) == 1:
            r.ws_id = next(iter(self.workspaces))
        wd = self.workspaces.get(r.ws_id) if r.ws_id else None
        if wd is not None and r.trajectory:
            _min_clearance(r, wd)

    def _arrival(self, rid: str, r: RobotSummary, start: int) -> None:
        """Arrival from the controller's status, else the first pose within the goal's
        tolerance."""
        if rid in self.status_arrival:
            r.arrived = True
            r.arrival_time_s = (self.status_arrival[rid] - start) / NS_PER_S
            r.arrival_source = "controller status"
        elif r.goal is not None and r.tolerance is not None and r.trajectory:
            for p, t in zip(r.trajectory, self.pose_times[rid], strict=True):
                if math.hypot(p[0] - r.goal[0], p[1] - r.goal[1]) <= r.tolerance:
                    r.arrived = True
                    r.arrival_time_s = (t - start) / NS_PER_S
                    r.arrival_source = "pose within goal tolerance"
                    break


def inspect_recording(path: str | os.PathLike[str]) -> InspectReport:
    """Read a recording and summarise it (channels, robots, arrival, clearance): one pass
    over the messages (:class:`_Scan`), then each robot's summary is completed."""
    with Recording(path) as rec:
        channels = sorted(rec.channels.values(), key=lambda c: (c.topic, c.id))
        unknown = _unknown_schemas(channels)
        scan = _Scan()
        for msg in rec.iter_messages():
            scan.add(msg.channel_id, msg.log_time_ns, decode_message(msg))
        start = scan.first_ns if scan.first_ns is not None else 0
        channels = [replace(c, count=scan.counts[c.id]) for c in channels]
        invalid = sum(c.count for c in channels if c.invalid)
        for rid, r in scan.robots.items():
            scan.finish_robot(rid, r, start)
        return InspectReport(
            closest=closest_approach(scan.robots, start),
            path=rec.path,
            prefix=rec.prefix,
            message_count=sum(scan.counts.values()),
            start_ns=start,
            end_ns=scan.last_ns,
            channels=channels,
            metadata=rec.metadata,
            workspaces=scan.workspaces,
            transforms=scan.transforms,
            robots=scan.robots,
            unknown_schemas=unknown,
            invalid_messages=invalid,
            atlases=scan.atlases,
            atlas_history=scan.atlas_history,
        )


def _min_clearance(r: RobotSummary, wd: WorkspaceDefinition) -> None:
    import numpy as np

    try:
        ws = _core_workspace(wd)
    except ConfnavError as exc:
        logger.warning("workspace %s cannot be rebuilt: %s", wd.ws_id, exc)
        return
    z = np.array([complex(x, y) for x, y in r.trajectory])
    c = np.asarray(ws.clearance(z), dtype=float)
    i = int(np.argmin(c))
    r.min_clearance = float(c[i])
    r.min_clearance_at = r.trajectory[i]


def closest_approach(robots: dict[str, RobotSummary], start_ns: int = 0) -> dict[str, Any] | None:
    """The closest approach of two robots' disks over a recording.

    Each robot's centre moves linearly between its recorded poses (by pose stamp); on the
    common refinement of all pose times every pair moves linearly, so the closest approach
    within each interval is the exact minimum of a convex quadratic
    (:func:`confnav.navigation.fleet.swept_min_distance`).  Only times where both robots have
    poses count.  Returns the pair, centre distance, gap between the disks (radii from the
    spawn requests or goals) and the time (s after ``start_ns``).
    """
    import numpy as np

    from confnav.navigation.fleet import swept_min_distance

    ids = sorted(rid for rid, r in robots.items() if len(r.trajectory) >= 1)
    if len(ids) < 2:
        return None
    tracks = []
    for rid in ids:
        r = robots[rid]
        t = np.asarray(r.pose_stamps, dtype=np.int64)
        order = np.argsort(t, kind="stable")
        xy = np.asarray(r.trajectory, dtype=np.float64)[order]
        tracks.append((t[order], xy[:, 0] + 1j * xy[:, 1]))
    grid = np.unique(np.concatenate([t for t, _ in tracks]))
    tg = (grid - grid[0]).astype(np.float64)
    pos = np.full((len(ids), grid.size), np.nan + 0j)
    for k, (t, z) in enumerate(tracks):
        tt = (t - grid[0]).astype(np.float64)
        inside = (tg >= tt[0]) & (tg <= tt[-1])
        pos[k, inside] = np.interp(tg[inside], tt, z.real) + 1j * np.interp(tg[inside], tt, z.imag)
    radii = np.array([robots[rid].radius for rid in ids])
    best: dict[str, Any] | None = None
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            a0, a1 = pos[i, :-1], pos[i, 1:]
            b0, b1 = pos[j, :-1], pos[j, 1:]
            ok = np.isfinite(a0) & np.isfinite(a1) & np.isfinite(b0) & np.isfinite(b1)
            if grid.size == 1 or not ok.any():
                both = np.isfinite(pos[i]) & np.isfinite(pos[j])
                if not both.any():
                    continue
                d = np.abs(pos[i] - pos[j])
                k = int(np.nanargmin(np.where(both, d, np.nan)))
                dist, when = float(d[k]), float(tg[k])
            else:
                dmin, s = swept_min_distance(a0[ok], a1[ok], b0[ok], b1[ok])
                k = int(np.argmin(dmin))
                seg = np.flatnonzero(ok)[k]
                dist = float(dmin[k])
                when = float(tg[seg] + s[k] * (tg[seg + 1] - tg[seg]))
            gap = dist - radii[i] - radii[j]
            if best is None or gap < best["gap"]:
                best = {
                    "robots": [ids[i], ids[j]],
                    "distance": dist,
                    "gap": float(gap),
                    "radii": [float(radii[i]), float(radii[j])],
                    "time_s": (when + float(grid[0] - start_ns)) / NS_PER_S,
                }
    return best


def report_json(report: InspectReport) -> str:
    return json.dumps(report.to_dict(), indent=2, sort_keys=True)


__all__ = [
    "AtlasHistory",
    "InspectReport",
    "RobotSummary",
    "closest_approach",
    "inspect_recording",
    "report_json",
]
