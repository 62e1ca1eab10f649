"""``confnav inspect``: channels, counts, duration, robots, arrival and minimum clearance of a
recording, ``--plot`` and ``--json``; clear errors for bad files."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import pytest
import shapely
from confnav.schemas import (
    CollisionEvent,
    Goal,
    Message,
    Pose,
    RobotStatus,
    VelocityCommand,
    WorkspaceDefinition,
    encode,
)
from conftest import confnav_cmd, subprocess_env
from mcap.writer import Writer

from confnav.recording import layout as L
from confnav.recording.inspect import inspect_recording
from confnav.recording.reader import Recording, RecordingError

T0 = 1_700_000_000_000_000_000
OUTER = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
HOLE = [(0.2, -0.2), (0.4, -0.2), (0.4, 0.2), (0.2, 0.2)]


class _Rec:
    """Writes a recording with the recorder's layout (mcap_layout) from model instances."""

    def __init__(self, path: Path) -> None:
        self.f = open(path, "wb")  # noqa: SIM115 - closed in finish()
        self.w = Writer(self.f)
        self.w.start(L.PROFILE, "test")
        self.w.add_metadata(L.METADATA_NAME, L.metadata_record("confnav", {"test": True}))
        self.schemas: dict[type[Message], int] = {}
        self.channels: dict[str, int] = {}

    def put(self, key: str, m: Message, t: int) -> None:
        model = type(m)
        if model not in self.schemas:
            self.schemas[model] = self.w.register_schema(
                L.schema_name(model), L.SCHEMA_ENCODING, L.schema_data(model)
            )
        if key not in self.channels:
            self.channels[key] = self.w.register_channel(
                key, L.MESSAGE_ENCODING, self.schemas[model]
            )
        self.w.add_message(self.channels[key], t, encode(m), L.publish_time_ns(m, t))

    def raw(self, key: str, data: bytes, t: int) -> None:
        cid = self.w.register_channel(
            key, L.RAW_MESSAGE_ENCODING, 0, dict(L.INVALID_CHANNEL_METADATA)
        )
        self.w.add_message(cid, t, data, t)

    def finish(self) -> None:
        self.w.finish()
        self.f.close()


def _path(k: int) -> tuple[float, float]:
    """r1 passes below the hole: closest approach 0.05 to its bottom edge at x in [0.2, 0.4]."""
    x = 0.9 - 0.02 * k
    return x, -0.25 if 0.1 < x < 0.5 else -0.5


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    p = tmp_path / "r.mcap"
    r = _Rec(p)
    r.put(
        "confnav/ws/w1/definition",
        WorkspaceDefinition(ws_id="w1", outer=OUTER, obstacles=[HOLE]),
        T0,
    )
    r.put("confnav/robot/r1/goal", Goal(robot_id="r1", ws_id="w1", goal=(-0.5, -0.5)), T0 + 10)
    r.put("confnav/robot/r2/goal", Goal(robot_id="r2", ws_id="w1", goal=(0.5, 0.5)), T0 + 20)
    for k in range(71):  # r1: 70 steps of 0.02 m along x, 10 ms apart
        t = T0 + 10_000_000 * (k + 1)
        x, y = _path(k)
        r.put("confnav/robot/r1/pose", Pose(robot_id="r1", stamp_ns=t, seq=k, x=x, y=y), t)
        r.put(
            "confnav/robot/r1/cmd_vel",
            VelocityCommand(robot_id="r1", stamp_ns=t, linear=(-2.0, 0.0), pose_seq=k),
            t + 1,
        )
        # r2 never moves (stopped: missing map)
        r.put("confnav/robot/r2/pose", Pose(robot_id="r2", stamp_ns=t, seq=k, x=-0.6, y=0.6), t)
    arrive = T0 + 10_000_000 * 71 + 5
    r.put(
        "confnav/robot/r1/status",
        RobotStatus(robot_id="r1", stamp_ns=arrive, state="arrived", reason="arrived"),
        arrive,
    )
    r.put(
        "confnav/robot/r2/status",
        RobotStatus(robot_id="r2", stamp_ns=arrive, state="stopped", reason="missing_map"),
        arrive + 1,
    )
    r.raw("confnav/robot/r2/goal", b'{"garbage": 1}', arrive + 2)
    hit = CollisionEvent(
        robot_id="r2", ws_id="w1", stamp_ns=arrive, position=(-0.6, 0.6), clearance=-0.01
    )
    r.put("confnav/robot/r2/collision", hit, arrive + 3)
    r.finish()
    return p


def test_report_counts_robots_arrival_and_clearance(recording: Path) -> None:
    rep = inspect_recording(recording)
    assert rep.message_count == 1 + 2 + 71 * 3 + 2 + 1 + 1
    assert math.isclose(rep.duration_s, (10_000_000 * 71 + 8) / 1e9)
    counts = {c.topic: c.count for c in rep.channels if not c.invalid}
    assert counts["confnav/robot/r1/pose"] == 71 and counts["confnav/robot/r1/cmd_vel"] == 71
    assert rep.invalid_messages == 1 and rep.unknown_schemas == []
    assert set(rep.robots) == {"r1", "r2"}
    r1, r2 = rep.robots["r1"], rep.robots["r2"]
    assert r1.arrived and r1.arrival_source == "controller status"
    assert math.isclose(r1.arrival_time_s, (10_000_000 * 71 + 5) / 1e9)
    assert not r2.arrived and (r2.final_state, r2.final_reason) == ("stopped", "missing_map")
    # minimum clearance against an independent shapely computation over the same poses
    free = shapely.Polygon(OUTER, [HOLE])
    expected = min(free.exterior.distance(shapely.Point(_path(k))) for k in range(71))
    expected = min(
        expected,
        *(free.interiors[0].distance(shapely.Point(_path(k))) for k in range(71)),
    )
    assert math.isclose(r1.min_clearance, expected, abs_tol=1e-12)
    assert math.isclose(r1.min_clearance, 0.05, abs_tol=1e-9)
    assert 0.2 <= r1.min_clearance_at[0] <= 0.4
    assert math.isclose(r2.min_clearance, 0.4, abs_tol=1e-9)
    # 68 steps along x and two diagonal steps where y jumps by 0.25
    assert math.isclose(r1.path_length, 68 * 0.02 + 2 * math.hypot(0.02, 0.25), rel_tol=1e-9)
    text = rep.format()
    assert (
        "arrived at t = 0.710 s" in text
        and "did not arrive (last state stopped/missing_map)" in text
    )
    assert "minimum clearance 0.0500 m" in text
    assert r1.collision_at is None and r2.collision_at == (-0.6, 0.6)
    assert "COLLISION at t = 0.710 s at (-0.600, 0.600)" in text


def test_arrival_from_poses_without_status(tmp_path: Path) -> None:
    p = tmp_path / "nostatus.mcap"
    r = _Rec(p)
    r.put(
        "confnav/robot/r1/goal",
        Goal(robot_id="r1", ws_id="w1", goal=(0.0, 0.0), tolerance=0.05),
        T0,
    )
    for k in range(10):
        t = T0 + 100_000_000 * (k + 1)
        r.put(
            "confnav/robot/r1/pose",
            Pose(robot_id="r1", stamp_ns=t, seq=k, x=0.5 - 0.05 * k, y=0.0),
            t,
        )
    r.finish()
    rep = inspect_recording(p)
    r1 = rep.robots["r1"]
    # x = 0.5 - 0.05 k <= 0.05 first at k = 9 (x = 0.05): t = 1.0 s after the first message
    assert r1.arrived and r1.arrival_source == "pose within goal tolerance"
    assert math.isclose(r1.arrival_time_s, 1.0)
    assert r1.min_clearance is None  # no workspace definition recorded
    assert "n/a" in rep.format()


def test_cli_inspect_json_and_plot(recording: Path, tmp_path: Path) -> None:
    png = tmp_path / "plot.png"
    res = subprocess.run(
        confnav_cmd("inspect", str(recording), "--json", "--plot", str(png)),
        capture_output=True,
        text=True,
        timeout=60,
        env=subprocess_env(),
    )
    assert res.returncode == 0, res.stderr
    data = json.loads(res.stdout)
    assert data["robots"]["r1"]["arrived"] is True
    assert data["robots"]["r2"]["arrived"] is False
    assert math.isclose(data["robots"]["r1"]["min_clearance"], 0.05, abs_tol=1e-9)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_unknown_schema_is_listed_not_fatal(tmp_path: Path) -> None:
    p = tmp_path / "u.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("acme.Thing", "jsonschema", b"{}")
        cid = w.register_channel("acme/thing", "json", sid)
        w.add_message(cid, 5, b"{}", 5)
        w.finish()
    rep = inspect_recording(p)
    assert rep.unknown_schemas == ["acme.Thing"] and rep.robots == {}
    assert "unknown schemas (not decoded): acme.Thing" in rep.format()


def test_bad_files(tmp_path: Path, recording: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        Recording(tmp_path / "missing.mcap")
    notm = tmp_path / "n.mcap"
    notm.write_text("hello")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        Recording(notm)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:-100])
    with pytest.raises(RecordingError, match="no footer"):
        Recording(cut)
    res = subprocess.run(
        confnav_cmd("inspect", str(cut)),
        capture_output=True,
        text=True,
        timeout=60,
        env=subprocess_env(),
    )
    assert res.returncode == 1
    assert "confnav recover" in res.stderr and "Traceback" not in res.stderr


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


GOLDEN = sorted((Path(__file__).resolve().parent / "data").glob("golden_*.mcap"))


@pytest.mark.skipif(not GOLDEN, reason="no golden recording in tests/data")
def test_plot_adds_the_circle_domain_when_the_map_is_recorded(
    recording: Path, tmp_path: Path
) -> None:
    from confnav.plot.recording import plot_recording, recording_figure

    rep = inspect_recording(GOLDEN[0])
    assert all(r.arrived for r in rep.robots.values()) and len(rep.robots) == 2
    assert all(r.min_clearance is not None and r.min_clearance > 0 for r in rep.robots.values())
    assert _png_size(plot_recording(rep, tmp_path / "golden.png"))[0] > 0
    with_map = recording_figure(rep)
    plain = recording_figure(inspect_recording(recording))
    assert len(plain.axes) == 1 and len(with_map.axes) == 2  # + the circle-domain panel
    for fig in (with_map, plain):  # units on every axis, a legend explaining the markers
        assert fig.axes[0].get_xlabel() == "x [m]" and fig.axes[0].get_ylabel() == "y [m]"
        legend = fig.axes[0].get_legend()
        assert legend is not None
        assert {"start", "goal", "collision"} <= {t.get_text() for t in legend.get_texts()}
    assert with_map.axes[1].get_xlabel().startswith("Re w")


def test_counts_without_a_statistics_record(tmp_path: Path) -> None:
    p = tmp_path / "nostats.mcap"
    with open(p, "wb") as f:
        w = Writer(f, use_statistics=False)
        w.start()
        sid = w.register_schema(L.schema_name(Pose), L.SCHEMA_ENCODING, L.schema_data(Pose))
        cid = w.register_channel("confnav/robot/r1/pose", L.MESSAGE_ENCODING, sid)
        for k in range(7):
            t = T0 + 1_000_000 * k
            w.add_message(cid, t, encode(Pose(robot_id="r1", stamp_ns=t, seq=k, x=0.0, y=0.0)), t)
        w.finish()
    rep = inspect_recording(p)
    assert rep.message_count == 7 and [c.count for c in rep.channels] == [7]
    assert math.isclose(rep.duration_s, 0.006) and rep.robots["r1"].poses == 7


@pytest.mark.skipif(not GOLDEN, reason="no golden recording in tests/data")
def test_times_have_one_labelled_origin() -> None:
    """Every time is seconds after the first recorded message, and the report says so; the
    arrival is also given after the robot's goal (the origin ``confnav demo`` uses)."""
    rep = inspect_recording(GOLDEN[0])
    text = rep.format()
    assert "t = 0 at the first recorded message" in text
    assert rep.to_dict()["time_origin"].startswith("first recorded message")
    for r in rep.robots.values():
        assert r.goal_time_s is not None and r.arrival_time_s is not None
        assert 0.0 <= r.goal_time_s < r.arrival_time_s <= rep.duration_s
        assert f"{r.arrival_time_s - r.goal_time_s:.3f} s after its goal" in text
