"""Reading confnav recordings: ``confnav inspect`` (summary, ``--plot``) and ``confnav viz``.

:class:`Recording` opens an MCAP file written by the recorder (layout in
:mod:`confnav.recording.layout`) with the indexed reader and turns format problems into
:class:`RecordingError` with a message that says what to do (not an MCAP file, no footer: run
``confnav recover``, ...). :func:`inspect_recording` computes what a person wants to know about a
run: channels, counts, duration, robots, whether and when each arrived, minimum clearance per
robot. :func:`plot_recording` draws the trajectories on the workspace and
:func:`add_scene_channels` copies a recording adding the Foxglove scene channels
(:mod:`confnav.recording.scene`).

Times: MCAP ``log_time``/``publish_time`` are integer nanoseconds since the Unix epoch;
durations in reports are seconds relative to the first message's log time.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections import Counter, defaultdict
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.reader import McapReader, make_reader
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from confnav.errors import ConfnavError
from confnav.recording import scene as foxglove
from confnav.recording.layout import METADATA_NAME, RAW_MESSAGE_ENCODING
from confnav.recording.recover import MCAP_MAGIC, has_footer
from confnav.schemas import (
    MODELS_BY_TYPE,
    AtlasIndex,
    CollisionEvent,
    DecodeError,
    Goal,
    Message,
    Pose,
    RobotStatus,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
)

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000


class RecordingError(ConfnavError):
    """A recording that cannot be read or lacks what a command needs."""


# --------------------------------------------------------------------------------------------
# reading


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded message: ``topic`` (the Zenoh key), raw ``data``, times in ns."""

    topic: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    schema_name: str
    message_encoding: str
    channel_id: int


@dataclass(frozen=True)
class ChannelInfo:
    """A channel of a recording with its message count and log-time range (ns)."""

    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    metadata: Mapping[str, str]
    count: int

    @property
    def invalid(self) -> bool:
        """The recorder's channel for payloads that were not valid messages."""
        return self.message_encoding == RAW_MESSAGE_ENCODING


class Recording:
    """An open, finished (indexed) MCAP recording.

    Raises :class:`RecordingError` if the file is missing, not an MCAP file, has no footer
    (writer killed: ``confnav recover`` fixes it) or its summary cannot be read.
    Use as a context manager.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: no such file")
        with open(self.path, "rb") as probe:
            if probe.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise RecordingError(f"{self.path}: not an MCAP file")
        if not has_footer(self.path):
            raise RecordingError(
                f"{self.path}: the MCAP file has no footer (the writer was killed before it "
                f"finished); run `confnav recover {self.path} -o FIXED.mcap` and use FIXED.mcap"
            )
        self._file: IO[bytes] = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        try:
            self._reader: McapReader = make_reader(self._file)
            summary = self._reader.get_summary()
            self.metadata: dict[str, dict[str, str]] = {
                m.name: dict(m.metadata) for m in self._reader.iter_metadata()
            }
        except (McapError, ValueError, OSError, EOFError) as exc:
            self._file.close()
            raise RecordingError(f"{self.path}: unreadable MCAP file: {exc}") from exc
        if summary is None:
            self._file.close()
            raise RecordingError(f"{self.path}: MCAP file without a summary section")
        self._schemas: dict[int, Schema] = dict(summary.schemas)
        self._channels: dict[int, Channel] = dict(summary.channels)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        self.message_count = summary.statistics.message_count if summary.statistics else 0
        self.start_ns = summary.statistics.message_start_time if summary.statistics else 0
        self.end_ns = summary.statistics.message_end_time if summary.statistics else 0
        self.channels: dict[int, ChannelInfo] = {}
        for cid, ch in sorted(self._channels.items()):
            schema = self._schemas.get(ch.schema_id)
            self.channels[cid] = ChannelInfo(
                id=cid,
                topic=ch.topic,
                message_encoding=ch.message_encoding,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                metadata=dict(ch.metadata),
                count=int(counts.get(cid, 0)),
            )

    def __enter__(self) -> Recording:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    @property
    def prefix(self) -> str:
        """Key prefix recorded in the ``confnav`` metadata (default ``confnav``)."""
        return self.metadata.get(METADATA_NAME, {}).get("prefix", "confnav")

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS_PER_S if self.message_count else 0.0

    def topics(self) -> list[str]:
        return sorted({c.topic for c in self.channels.values()})

    def raw_schemas(self) -> dict[int, Schema]:
        return dict(self._schemas)

    def raw_channels(self) -> dict[int, Channel]:
        return dict(self._channels)

    def iter_messages(self, topics: Iterable[str] | None = None) -> Iterator[RecordedMessage]:
        """Messages in log-time order (ties in file order), optionally only on ``topics``."""
        wanted = None if topics is None else list(topics)
        try:
            for schema, channel, msg in self._reader.iter_messages(
                topics=wanted, log_time_order=True
            ):
                yield RecordedMessage(
                    topic=channel.topic,
                    data=bytes(msg.data),
                    log_time_ns=int(msg.log_time),
                    publish_time_ns=int(msg.publish_time),
                    sequence=int(msg.sequence),
                    schema_name=schema.name if schema else "",
                    message_encoding=channel.message_encoding,
                    channel_id=channel.id,
                )
        except (McapError, ValueError, OSError, EOFError) as exc:
            raise RecordingError(f"{self.path}: corrupt data while reading: {exc}") from exc

    def iter_attachments(self) -> Iterator[Any]:
        return self._reader.iter_attachments()


def decode_message(msg: RecordedMessage) -> Message | None:
    """The confnav model instance of a recorded message, or None (not a confnav schema,
    recorded as invalid, or no longer valid: logged)."""
    if msg.message_encoding != "json":
        return None
    model = MODELS_BY_TYPE.get(msg.schema_name)
    if model is None:
        return None
    try:
        return decode(model, msg.data, limit=len(msg.data))
    except DecodeError as exc:
        logger.warning("%s at %d ns: %s", msg.topic, msg.log_time_ns, exc)
        return None


# --------------------------------------------------------------------------------------------
# inspect


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
    arrival_source: str = ""
    final_state: str | None = None
    final_reason: str | None = None
    min_clearance: float | None = None
    min_clearance_at: tuple[float, float] | None = None
    collision_time_s: float | None = None
    collision_at: tuple[float, float] | None = None
    trajectory: list[tuple[float, float]] = field(default_factory=list)
    charts: list[int] = field(default_factory=list)  # active charts in order (atlas only)


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

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS_PER_S if self.message_count else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "prefix": self.prefix,
            "messages": self.message_count,
            "duration_s": self.duration_s,
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
                w: {"revision": a.revision, "cells": len(a.cells)}
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
                    "final_state": r.final_state,
                    "path_length": r.path_length,
                    "min_clearance": r.min_clearance,
                    "collision_time_s": r.collision_time_s,
                    "charts": r.charts,
                }
                for rid, r in sorted(self.robots.items())
            },
            "unknown_schemas": self.unknown_schemas,
            "invalid_messages": self.invalid_messages,
        }

    def format(self) -> str:
        """Human-readable report."""
        out = [
            f"file:      {self.path}",
            f"prefix:    {self.prefix}",
            f"messages:  {self.message_count}",
            f"duration:  {self.duration_s:.3f} s",
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
        if not self.robots:
            out.append("\nno robots recorded")
        for rid, r in sorted(self.robots.items()):
            out.append(f"\nrobot {rid}" + (f" (workspace {r.ws_id})" if r.ws_id else ""))
            out.append(f"  poses {r.poses}, commands {r.commands}, path {r.path_length:.3f} m")
            if r.start is not None and r.end is not None:
                out.append(f"  start {_fmt_pt(r.start)} -> end {_fmt_pt(r.end)}")
            if r.goal is not None:
                out.append(f"  goal {_fmt_pt(r.goal)}")
            if r.charts:
                path = " -> ".join(map(str, r.charts))
                out.append(f"  charts {path} ({len(r.charts) - 1} switches)")
            if r.arrived:
                out.append(f"  arrived at t = {r.arrival_time_s:.3f} s ({r.arrival_source})")
            else:
                state = f" (last state {r.final_state}/{r.final_reason})" if r.final_state else ""
                out.append(f"  did not arrive{state}")
            if r.collision_at is not None and r.collision_time_s is not None:
                out.append(
                    f"  COLLISION at t = {r.collision_time_s:.3f} s at {_fmt_pt(r.collision_at)}"
                )
            if r.min_clearance is not None and r.min_clearance_at is not None:
                out.append(
                    f"  minimum clearance {r.min_clearance:.4f} m at {_fmt_pt(r.min_clearance_at)}"
                )
            else:
                out.append("  minimum clearance: n/a (no workspace definition recorded)")
        return "\n".join(out)


def _fmt_pt(p: tuple[float, float]) -> str:
    return f"({p[0]:.3f}, {p[1]:.3f})"


def _core_workspace(wd: WorkspaceDefinition) -> Any:
    """The core :class:`confnav.geometry.Workspace` of a definition (for clearances)."""
    from confnav.geometry import Workspace

    return Workspace(wd.outer, wd.obstacles, anchor=wd.anchor)


def inspect_recording(path: str | os.PathLike[str]) -> InspectReport:
    """Read a recording and summarise it (channels, robots, arrival, clearance)."""
    with Recording(path) as rec:
        channels = sorted(rec.channels.values(), key=lambda c: (c.topic, c.id))
        unknown = sorted(
            {
                c.schema_name or f"(none, encoding {c.message_encoding})"
                for c in channels
                if not c.invalid
                and c.schema_name not in MODELS_BY_TYPE
                and c.schema_name != foxglove.SCENE_SCHEMA_NAME
            }
        )
        workspaces: dict[str, WorkspaceDefinition] = {}
        transforms: dict[str, TransformSolution] = {}
        atlases: dict[str, AtlasIndex] = {}
        robots: dict[str, RobotSummary] = {}
        status_arrival: dict[str, int] = {}
        pose_times: dict[str, list[int]] = defaultdict(list)

        def robot(rid: str) -> RobotSummary:
            if rid not in robots:
                robots[rid] = RobotSummary(robot_id=rid)
            return robots[rid]

        counts: Counter[int] = Counter()  # counted here: the statistics record is optional
        first_ns: int | None = None
        last_ns = 0
        for msg in rec.iter_messages():
            counts[msg.channel_id] += 1
            first_ns = msg.log_time_ns if first_ns is None else first_ns
            last_ns = max(last_ns, msg.log_time_ns)
            model = decode_message(msg)
            if model is None:
                continue
            if isinstance(model, WorkspaceDefinition):
                workspaces[model.ws_id] = model
            elif isinstance(model, TransformSolution):
                transforms[model.ws_id] = model
            elif isinstance(model, Pose):
                r = robot(model.robot_id)
                p = (model.x, model.y)
                if r.trajectory:
                    q = r.trajectory[-1]
                    r.path_length += math.hypot(p[0] - q[0], p[1] - q[1])
                r.trajectory.append(p)
                pose_times[model.robot_id].append(msg.log_time_ns)
                r.poses += 1
            elif isinstance(model, Goal):
                r = robot(model.robot_id)
                r.goal = (model.goal[0], model.goal[1])
                r.tolerance = model.tolerance
                r.ws_id = model.ws_id
            elif isinstance(model, AtlasIndex):
                atlases[model.ws_id] = model
            elif isinstance(model, VelocityCommand):
                r = robot(model.robot_id)
                r.commands += 1
                if model.chart is not None and (not r.charts or r.charts[-1] != model.chart):
                    r.charts.append(model.chart)
            elif isinstance(model, CollisionEvent):
                r = robot(model.robot_id)
                if r.collision_at is None:
                    r.collision_at = (model.position[0], model.position[1])
                    r.collision_time_s = (msg.log_time_ns - (first_ns or 0)) / NS_PER_S
            elif isinstance(model, RobotStatus):
                r = robot(model.robot_id)
                r.final_state, r.final_reason = model.state, model.reason
                if model.ws_id and r.ws_id is None:
                    r.ws_id = model.ws_id
                if model.state == "arrived" and model.robot_id not in status_arrival:
                    status_arrival[model.robot_id] = msg.log_time_ns
        start = first_ns if first_ns is not None else 0
        channels = [replace(c, count=counts[c.id]) for c in channels]
        invalid = sum(c.count for c in channels if c.invalid)
        for rid, r in robots.items():
            if r.trajectory:
                r.start, r.end = r.trajectory[0], r.trajectory[-1]
            if rid in status_arrival:
                r.arrived = True
                r.arrival_time_s = (status_arrival[rid] - start) / NS_PER_S
                r.arrival_source = "controller status"
            elif r.goal is not None and r.tolerance is not None and r.trajectory:
                for p, t in zip(r.trajectory, pose_times[rid], strict=True):
                    if math.hypot(p[0] - r.goal[0], p[1] - r.goal[1]) <= r.tolerance:
                        r.arrived = True
                        r.arrival_time_s = (t - start) / NS_PER_S
                        r.arrival_source = "pose within goal tolerance"
                        break
            if r.ws_id is None and len(workspaces) == 1:
                r.ws_id = next(iter(workspaces))
            wd = workspaces.get(r.ws_id) if r.ws_id else None
            if wd is not None and r.trajectory:
                _min_clearance(r, wd)
        return InspectReport(
            path=rec.path,
            prefix=rec.prefix,
            message_count=sum(counts.values()),
            start_ns=start,
            end_ns=last_ns,
            channels=channels,
            metadata=rec.metadata,
            workspaces=workspaces,
            transforms=transforms,
            robots=robots,
            unknown_schemas=unknown,
            invalid_messages=invalid,
            atlases=atlases,
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


# --------------------------------------------------------------------------------------------
# plot


def _decimate(points: list[tuple[float, float]], n: int) -> list[tuple[float, float]]:
    if len(points) <= n:
        return points
    step = len(points) / n
    return [points[int(i * step)] for i in range(n)] + [points[-1]]


def _circle_domain_images(
    tr: TransformSolution, paths: dict[str, list[tuple[float, float]]]
) -> tuple[Any, dict[str, list[complex]]] | None:
    """(map, robot -> images T(z) of its decimated trajectory), None if the map won't load."""
    import numpy as np

    from confnav.navigation.messages import load_map

    try:
        cmap = load_map(tr)
    except Exception as exc:  # e.g. a stand-in map in tests, an old format
        logger.info("circle domain not drawn: cannot load the map: %s", exc)
        return None
    out = {}
    for rid, pts in paths.items():
        z = np.array([complex(x, y) for x, y in _decimate(pts, 1000)], dtype=complex)
        w = np.asarray(cmap.T(z), dtype=complex).reshape(-1) if z.size else z
        out[rid] = [complex(v) for v in w if np.isfinite(v)]
    return cmap, out


def plot_recording(report: InspectReport, out: str | os.PathLike[str]) -> Path:
    """Draw every workspace with the recorded trajectories, starts, goals and the closest
    approach to an obstacle and, when its map is recorded, the circle domain with the images
    of the trajectories; write a PNG to ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    from matplotlib.patches import Polygon as MplPolygon

    ws_ids = sorted(report.workspaces) or [""]
    mapped = {}
    for ws_id in ws_ids:
        tr = report.transforms.get(ws_id)
        if tr is not None:
            paths = {
                rid: r.trajectory
                for rid, r in report.robots.items()
                if r.ws_id in (ws_id, None) and r.trajectory
            }
            found = _circle_domain_images(tr, paths)
            if found is not None:
                mapped[ws_id] = found
    cols = 2 if mapped else 1
    fig, axes = plt.subplots(
        len(ws_ids), cols, figsize=(6.5 * cols, 6.5 * len(ws_ids)), squeeze=False
    )
    colors = {rid: foxglove.robot_color(i) for i, rid in enumerate(sorted(report.robots))}
    for row, ws_id in enumerate(ws_ids):
        ax = axes[row][0]
        wd = report.workspaces.get(ws_id)
        if wd is not None:
            ax.add_patch(MplPolygon(wd.outer, closed=True, fill=False, lw=2, ec="black"))
            for ob in wd.obstacles:
                ax.add_patch(MplPolygon(ob, closed=True, fc="#d9a89b", ec="#a0301a", lw=1.5))
        for rid, r in sorted(report.robots.items()):
            if wd is not None and r.ws_id not in (ws_id, None):
                continue
            color = colors[rid]
            if r.trajectory:
                xs, ys = zip(*r.trajectory, strict=True)
                ax.plot(xs, ys, "-", color=color, lw=1.6, label=f"{rid}")
                ax.plot(xs[0], ys[0], "o", color=color, ms=6)
            if r.goal is not None:
                ax.plot(*r.goal, "*", color="green", ms=14, mec="black")
            if r.min_clearance_at is not None:
                ax.plot(*r.min_clearance_at, "x", color=color, ms=9, mew=2)
            if r.collision_at is not None:
                ax.plot(*r.collision_at, "X", color="red", ms=12, mec="black")
        ax.set_aspect("equal")
        ax.autoscale_view()
        title = f"workspace {ws_id}" if ws_id else "recorded trajectories"
        ax.set_title(f"{report.path.name}: {title}", fontsize=10)
        if report.robots:
            ax.legend(loc="upper right", fontsize=8)
        if cols == 2:
            cax = axes[row][1]
            if ws_id in mapped:
                cmap, images = mapped[ws_id]
                cax.add_patch(Circle((0, 0), 1.0, fill=False, lw=2, ec="black"))
                for c, rad in zip(cmap.centers, cmap.radii, strict=True):
                    cax.add_patch(Circle((c.real, c.imag), rad, fc="#d9a89b", ec="#a0301a", lw=1.5))
                for rid, w in sorted(images.items()):
                    if w:
                        cax.plot([v.real for v in w], [v.imag for v in w], "-", color=colors[rid])
                        cax.plot(w[0].real, w[0].imag, "o", color=colors[rid], ms=6)
                cax.set_xlim(-1.05, 1.05)
                cax.set_ylim(-1.05, 1.05)
                cax.set_title(f"circle domain of {ws_id}: images T(z)", fontsize=10)
            else:
                cax.set_axis_off()
            cax.set_aspect("equal")
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# viz: add Foxglove scene channels to an existing recording


@dataclass
class VizReport:
    source: Path
    output: Path
    messages_copied: int = 0
    scene_messages: Counter[str] = field(default_factory=Counter)


def add_scene_channels(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    period_ns: int = foxglove.DEFAULT_PERIOD_NS,
) -> VizReport:
    """Copy ``source`` to ``output`` with the Foxglove scene channels added.

    Every schema, channel, message (times unchanged), metadata record and attachment is copied;
    scene channels already in ``source`` are dropped and regenerated.
    """
    src, dst = Path(source), Path(output)
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise RecordingError("the output must be a different file from the input")
    with Recording(src) as rec:
        prefix = rec.prefix
        report = VizReport(source=src, output=dst)
        tmp = dst.with_name(dst.name + ".part")
        with open(tmp, "wb") as f:
            writer = Writer(f, compression=CompressionType.ZSTD)
            writer.start(profile="confnav", library="confnav viz")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            schemas = rec.raw_schemas()
            for cid, ch in sorted(rec.raw_channels().items()):
                if foxglove.is_viz_topic(ch.topic, prefix):
                    continue
                if ch.schema_id and ch.schema_id not in schema_ids:
                    s = schemas[ch.schema_id]
                    schema_ids[ch.schema_id] = writer.register_schema(
                        name=s.name, encoding=s.encoding, data=bytes(s.data)
                    )
                channel_ids[cid] = writer.register_channel(
                    topic=ch.topic,
                    message_encoding=ch.message_encoding,
                    schema_id=schema_ids.get(ch.schema_id, 0),
                    metadata=dict(ch.metadata),
                )
            for name, data in rec.metadata.items():
                writer.add_metadata(name, data)
            for att in rec.iter_attachments():
                writer.add_attachment(
                    create_time=att.create_time,
                    log_time=att.log_time,
                    name=att.name,
                    media_type=att.media_type,
                    data=bytes(att.data),
                )
            scenes = foxglove.FoxgloveSceneWriter(writer, prefix, period_ns=period_ns)
            for msg in rec.iter_messages():
                if msg.channel_id not in channel_ids:
                    continue
                writer.add_message(
                    channel_id=channel_ids[msg.channel_id],
                    log_time=msg.log_time_ns,
                    data=msg.data,
                    publish_time=msg.publish_time_ns,
                    sequence=msg.sequence,
                )
                report.messages_copied += 1
                if msg.message_encoding == "json":
                    scenes.on_message(msg.topic, msg.data, msg.log_time_ns)
            scenes.close()
            writer.finish()  # type: ignore[no-untyped-call]
        os.replace(tmp, dst)
    with Recording(dst) as out:
        for c in out.channels.values():
            if c.schema_name == foxglove.SCENE_SCHEMA_NAME:
                report.scene_messages[c.topic] += c.count
    return report


def report_json(report: InspectReport) -> str:
    return json.dumps(report.to_dict(), indent=2, sort_keys=True)


__all__ = [
    "ChannelInfo",
    "InspectReport",
    "RecordedMessage",
    "Recording",
    "RecordingError",
    "RobotSummary",
    "VizReport",
    "add_scene_channels",
    "decode_message",
    "inspect_recording",
    "plot_recording",
    "report_json",
]
