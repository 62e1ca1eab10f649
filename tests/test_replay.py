"""``confnav replay``: recorded messages go back onto Zenoh with their timing, to the recorded
keys or under a new prefix; replaying through a live recorder reproduces every channel."""

from __future__ import annotations

import importlib.util
import subprocess
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from confnav.schemas import Pose, encode
from confnav.services.bus import zenoh_config
from confnav.services.keys import Keys
from confnav.services.recorder import Recorder
from confnav.services.replay import ReplayError, remap, replay, select_topics
from conftest import confnav_cmd, subprocess_env, wait_for
from mcap.writer import Writer

from confnav.recording import layout as L
from confnav.recording.reader import Recording
from confnav.recording.scene import is_viz_topic

DATA = Path(__file__).resolve().parent / "data"
GOLDEN = sorted(DATA.glob("golden_*.mcap"))
T0 = 1_700_000_000_000_000_000


def _make_golden() -> ModuleType:
    spec = importlib.util.spec_from_file_location("confnav_make_golden", DATA / "make_golden.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _per_channel(path: Path) -> dict[str, list[bytes]]:
    """Payloads per topic (log-time order), Foxglove scene channels left out."""
    out: dict[str, list[bytes]] = defaultdict(list)
    with Recording(path) as rec:
        for m in rec.iter_messages():
            if not is_viz_topic(m.topic):
                out[m.topic].append(m.data)
    return dict(out)


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "run.mcap"
    _make_golden().run_pipeline(path, solver="fake", time_scale=4.0)
    return path


def _timed(path: Path, n: int = 26, step_ns: int = 20_000_000) -> list[bytes]:
    """n poses, ``step_ns`` apart in log time (0.5 s in all by default)."""
    payloads = []
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(L.PROFILE, "test")
        sid = w.register_schema(L.schema_name(Pose), L.SCHEMA_ENCODING, L.schema_data(Pose))
        cid = w.register_channel("confnav/robot/r1/pose", L.MESSAGE_ENCODING, sid)
        aid = w.register_channel("confnav/alive/recorder/abc", L.MESSAGE_ENCODING, sid)
        for i in range(n):
            t = T0 + step_ns * i
            data = encode(Pose(robot_id="r1", stamp_ns=t, seq=i, x=0.01 * i, y=0.0))
            w.add_message(cid, t, data, t)
            payloads.append(data)
        w.add_message(aid, T0, b"{}", T0)
        w.finish()
    return payloads


def test_select_and_remap() -> None:
    topics = [
        "confnav/alive/controller/z1",
        "confnav/robot/r1/cmd_vel",
        "confnav/robot/r1/pose",
        "confnav/robot/r2/pose",
        "confnav/viz/w1/scene",
        "confnav/ws/w1/transform",
    ]
    assert select_topics(topics, "confnav") == [
        "confnav/robot/r1/cmd_vel",
        "confnav/robot/r1/pose",
        "confnav/robot/r2/pose",
        "confnav/ws/w1/transform",
    ]
    assert select_topics(topics, "confnav", include=["confnav/robot/*/pose"]) == [
        "confnav/robot/r1/pose",
        "confnav/robot/r2/pose",
    ]
    assert select_topics(topics, "confnav", exclude=["**/cmd_vel", "confnav/ws/**"]) == [
        "confnav/robot/r1/pose",
        "confnav/robot/r2/pose",
    ]
    assert select_topics(topics, "confnav", include=["confnav/viz/**"]) == ["confnav/viz/w1/scene"]
    assert select_topics(topics, "confnav", inputs_only=True) == [
        "confnav/robot/r1/pose",
        "confnav/robot/r2/pose",
        "confnav/ws/w1/transform",
    ]
    assert select_topics(topics, "confnav", include=["confnav/robot/r2/**"], inputs_only=True) == [
        "confnav/robot/r2/pose"
    ]
    assert remap("confnav/robot/r1/pose", "confnav", "lab/a") == "lab/a/robot/r1/pose"
    assert remap("confnav/robot/r1/pose", "confnav", None) == "confnav/robot/r1/pose"


def _collect(make_bus: Any, keyexpr: str) -> tuple[list[tuple[float, str, bytes]], Any]:
    got: list[tuple[float, str, bytes]] = []
    lock = threading.Lock()
    bus = make_bus()

    def on(key: str, payload: bytes) -> None:
        with lock:
            got.append((time.monotonic(), key, payload))

    bus.subscribe(keyexpr, on)
    return got, bus


@pytest.mark.parametrize("speed", [1.0, 2.5, None], ids=["x1", "x2.5", "max"])
def test_timing_follows_the_recording(
    tmp_path: Path, zenoh_router: str, make_bus: Any, speed: float | None
) -> None:
    path = tmp_path / "timed.mcap"
    payloads = _timed(path)
    got, _bus = _collect(make_bus, "confnav/**")
    report = replay(
        path,
        zenoh_config("client", connect=[zenoh_router]),
        speed=speed,
        wait_subscribers=5.0,
        live=True,
    )
    wait_for(lambda: len(got) >= len(payloads), timeout=10)
    assert report.unmatched_keys == [] and report.total == len(payloads)
    assert [p for _t, _k, p in got] == payloads  # alive keys are not replayed
    assert {k for _t, k, _p in got} == {"confnav/robot/r1/pose"}
    t = np.array([t for t, _k, _p in got])
    if speed is None:
        assert t[-1] - t[0] < 0.2
    else:
        # Each pose i is due at offset 0.02 i / speed. Compare the arrival times with that
        # schedule after removing the common delay (median): the bulk must be on time, and a
        # replay that ignored `speed` would be off by up to 0.25-0.5 s. (Endpoints alone made
        # this test flaky: one descheduled first or last message on a busy 2-core machine.)
        due = 0.02 * np.arange(len(t)) / speed
        err = np.abs(t - due - np.median(t - due))
        assert np.median(err) < 0.02, err
        assert np.quantile(err, 0.8) < 0.05, err
        assert report.wall_time_s >= 0.5 / speed * 0.95


def test_prefix_and_include(tmp_path: Path, zenoh_router: str, make_bus: Any) -> None:
    path = tmp_path / "timed.mcap"
    payloads = _timed(path, n=10, step_ns=1_000_000)
    got, _bus = _collect(make_bus, "lab/**")
    report = replay(
        path,
        zenoh_config("client", connect=[zenoh_router]),
        speed=None,
        prefix="lab",
        include=["confnav/robot/**"],
        wait_subscribers=5.0,
    )
    wait_for(lambda: len(got) >= 10, timeout=10)
    assert dict(report.published) == {"lab/robot/r1/pose": 10}
    assert [p for _t, _k, p in got] == payloads
    with pytest.raises(ReplayError, match="no recorded topic selected"):
        replay(path, zenoh_config("client", connect=[zenoh_router]), include=["nothing/**"])
    with pytest.raises(ReplayError, match="speed"):
        replay(path, zenoh_config("client", connect=[zenoh_router]), speed=0.0)
    with pytest.raises(ReplayError, match="exclude each other"):
        replay(path, zenoh_config("client", connect=[zenoh_router]), prefix="lab", live=True)


def test_replay_defaults_to_a_separate_prefix(
    tmp_path: Path, zenoh_router: str, make_bus: Any
) -> None:
    """Without --live nothing reaches the live keys: a running system is never driven."""
    path = tmp_path / "timed.mcap"
    payloads = _timed(path, n=10, step_ns=1_000_000)
    live, _b1 = _collect(make_bus, "confnav/**")
    moved, _b2 = _collect(make_bus, "replay/confnav/**")
    res = subprocess.run(
        confnav_cmd(
            "replay", str(path), "--max", "--connect", zenoh_router, "--wait-subscribers", "5"
        ),
        capture_output=True,
        text=True,
        timeout=60,
        env=subprocess_env(),
    )
    assert res.returncode == 0, res.stderr
    wait_for(lambda: len(moved) >= 10, timeout=10)
    assert {k for _t, k, _p in moved} == {"replay/confnav/robot/r1/pose"}
    assert [p for _t, _k, p in moved] == payloads
    time.sleep(0.3)
    assert live == []


def _round_trip(source: Path, again: Path, zenoh_router: str, make_bus: Any) -> None:
    """``confnav replay --max`` (a real process) into a live recorder on Zenoh; the new
    recording has the same channels, counts and byte-identical payloads in the same order."""
    rec = Recorder(make_bus(), Keys(), again, {}, foxglove=True, health_period=0)
    seen: Counter[str] = Counter()  # a second subscriber: a loss on the bus or a stalled recorder
    lock = threading.Lock()

    def on(key: str, _payload: bytes) -> None:
        with lock:
            seen[key] += 1

    make_bus().subscribe("confnav/**", on)
    rec.start()
    try:
        res = subprocess.run(
            confnav_cmd(
                "replay",
                str(source),
                "--max",
                "--mode",
                "client",
                "--connect",
                zenoh_router,
                "--wait-subscribers",
                "5",
                "--live",
            ),
            capture_output=True,
            text=True,
            timeout=60,
            env=subprocess_env(),
        )
        assert res.returncode == 0, res.stderr
        # every replayed key had its subscriber before the first put (else the replay's
        # report says which keys had none: a late subscription, not a lost message)
        assert "no subscriber for" not in res.stdout, res.stdout
        original = _per_channel(source)
        total = sum(len(v) for v in original.values())
        try:
            wait_for(lambda: rec.recorded >= total, timeout=20)
        except AssertionError:  # say what is missing, to tell a stall from a loss
            with lock:
                missing = {t: len(v) - seen[t] for t, v in original.items() if seen[t] < len(v)}
            raise AssertionError(
                f"recorded {rec.recorded} of {total} within 20 s; not received by a second "
                f"subscriber either: {missing}; replay said:\n{res.stdout}{res.stderr}"
            ) from None
    finally:
        rec.stop()
    assert _per_channel(again) == original
    with Recording(again) as r:  # and the recorder drew the scenes again from replayed data
        assert {c.topic for c in r.channels.values() if is_viz_topic(c.topic)} == {
            "confnav/viz/w1/scene",
            "confnav/viz/w1/circle_domain",
        }


def test_replay_through_a_live_recorder_reproduces_every_channel(
    run_file: Path, tmp_path: Path, zenoh_router: str, make_bus: Any
) -> None:
    _round_trip(run_file, tmp_path / "again.mcap", zenoh_router, make_bus)


@pytest.mark.skipif(not GOLDEN, reason="no golden recording in tests/data")
@pytest.mark.parametrize("golden", GOLDEN, ids=lambda p: p.name)
def test_golden_recording_round_trip(
    golden: Path, tmp_path: Path, zenoh_router: str, make_bus: Any
) -> None:
    _round_trip(golden, tmp_path / "again.mcap", zenoh_router, make_bus)


def test_replay_at_recorded_speed_keeps_relative_timing(
    run_file: Path, tmp_path: Path, zenoh_router: str, make_bus: Any
) -> None:
    """At speed 1 the re-recorded log times follow the original ones (within scheduling)."""
    again = tmp_path / "again1.mcap"
    rec = Recorder(make_bus(), Keys(), again, {}, health_period=0)
    rec.start()
    try:
        report = replay(
            run_file,
            zenoh_config("client", connect=[zenoh_router]),
            wait_subscribers=5.0,
            live=True,
        )
        wait_for(lambda: rec.recorded >= report.total, timeout=20)
    finally:
        rec.stop()

    def times(path: Path) -> list[int]:
        with Recording(path) as r:
            return [m.log_time_ns for m in r.iter_messages() if not is_viz_topic(m.topic)]

    a, b = times(run_file), times(again)
    assert len(a) == len(b)
    lag = (np.array(b) - np.array(a)) / 1e9  # s; a common delay is not a timing error
    err = np.abs(lag - np.median(lag))  # (relative to the first message, one late first
    # message shifted every other one: the test failed that way at load 17)
    # The replayer schedules every message at t_start + offset on the monotonic clock, so its
    # errors do not accumulate; what remains is per-message scheduling in the replayer, Zenoh
    # and the recorder thread, where one descheduling on a busy 2-core machine was measured
    # at 0.17 s. The bulk must be tight, the tail bounded; a replay that ignored the recorded
    # timing (as fast as possible) would miss every bound by seconds.
    assert np.median(err) < 0.02, np.median(err)
    assert np.quantile(err, 0.95) < 0.1, np.quantile(err, 0.95)
    assert err.max() < 0.5, err.max()


def test_recorded_inputs_drive_a_live_controller_to_the_recorded_commands(
    run_file: Path, zenoh_router: str, make_bus: Any
) -> None:
    """``inputs_only``: definitions, transforms, goals and poses replayed at recorded speed
    into a live controller service; it answers each pose with the recorded command."""
    from confnav.schemas import VelocityCommand, decode
    from confnav.services.controller import ControllerService
    from conftest import identity_loader

    recorded: dict[tuple[str, int], complex] = {}
    with Recording(run_file) as rec:
        for m in rec.iter_messages():
            if m.topic.endswith("/cmd_vel"):
                c = decode(VelocityCommand, m.data)
                if c.pose_seq >= 0 and c.map_revision is not None:
                    recorded[(c.robot_id, c.pose_seq)] = complex(*c.linear)
    live: dict[tuple[str, int], VelocityCommand] = {}
    lock = threading.Lock()

    def on_cmd(key: str, payload: bytes) -> None:
        c = decode(VelocityCommand, payload)
        with lock:
            live[(c.robot_id, c.pose_seq)] = c

    listener = make_bus()
    listener.subscribe("confnav/robot/*/cmd_vel", on_cmd)
    listener.subscribe("confnav/ws/*/definition", lambda k, p: None)  # nobody else listens
    ctl = ControllerService(
        make_bus(), Keys(), map_loader=identity_loader, require_transform=False, health_period=0
    )
    ctl.start()
    try:
        report = replay(
            run_file,
            zenoh_config("client", connect=[zenoh_router]),
            inputs_only=True,
            wait_subscribers=5.0,
            live=True,
        )
        assert report.unmatched_keys == []
        kinds = {k.rsplit("/", 1)[-1] for k in report.published}
        assert kinds == {"definition", "transform", "goal", "pose"}
        poses = sum(n for k, n in report.published.items() if k.endswith("/pose"))
        # Every pose is accounted for: answered with a command, or superseded by a newer pose
        # of its robot that was already waiting (by design: the latest pose wins when the
        # controller is behind, e.g. on a loaded machine). How many are superseded depends on
        # CPU load, so the count of answers is not a correctness criterion; their values are.
        c = ctl.counters
        wait_for(lambda: c["commands"] + c["poses_superseded"] >= poses, timeout=30)
        time.sleep(0.5)
    finally:
        ctl.stop()
    with lock:
        answered = {k: c for k, c in live.items() if c.map_revision is not None and k[1] >= 0}
    common = set(answered) & set(recorded)
    assert c["poses"] == poses, c
    # answered poses are those not superseded (minus the first ones, before the map)
    assert len(common) >= 0.9 * (len(recorded) - c["poses_superseded"]), (len(common), c)
    assert len(common) >= 0.5 * len(recorded), (len(common), c)
    for key in common:
        assert abs(complex(*answered[key].linear) - recorded[key]) <= 1e-9, key


def test_recorded_maps_answer_like_a_transform_service(tmp_path: Path) -> None:
    """``RecordedMaps`` (what ``replay`` serves to queries): per key the latest message the
    replay has sent (before any, the first recorded), under the replay's prefix; the atlas
    marker for a transform query on a workspace recorded as an atlas; clear errors else."""
    from confnav.schemas import AtlasIndex, TransformSolution
    from confnav.services.replay import RecordedMaps

    from confnav.atlas.wire import ATLAS_MARKER

    path = tmp_path / "maps.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(L.PROFILE, "test")
        sid = w.register_schema(
            L.schema_name(TransformSolution), L.SCHEMA_ENCODING, L.schema_data(TransformSolution)
        )
        aid = w.register_schema(
            L.schema_name(AtlasIndex), L.SCHEMA_ENCODING, L.schema_data(AtlasIndex)
        )
        ws = w.register_channel("confnav/ws/w1/transform", L.MESSAGE_ENCODING, sid)
        chart = w.register_channel("confnav/ws/at~c0/transform", L.MESSAGE_ENCODING, sid)
        index = w.register_channel("confnav/ws/at/atlas", L.MESSAGE_ENCODING, aid)
        pose = w.register_channel("confnav/robot/r1/pose", L.MESSAGE_ENCODING, sid)
        for t, (cid, data) in enumerate(
            [(ws, b"w1-a"), (chart, b"c0"), (index, b"idx"), (pose, b"p"), (ws, b"w1-b")]
        ):
            w.add_message(cid, T0 + t, data, T0 + t)
        w.finish()
    with Recording(path) as rec:
        maps = RecordedMaps(rec, "replay/confnav")
    k = "replay/confnav/ws"
    assert maps.answer(f"{k}/w1/transform") == [(f"{k}/w1/transform", b"w1-a")]  # first
    maps.sent(f"{k}/w1/transform")
    assert maps.answer(f"{k}/w1/transform") == [(f"{k}/w1/transform", b"w1-a")]
    maps.sent(f"{k}/w1/transform")
    assert maps.answer(f"{k}/w1/transform") == [(f"{k}/w1/transform", b"w1-b")]  # latest sent
    maps.sent(f"{k}/w1/transform")  # nothing more recorded: stays the last one
    assert maps.answer(f"{k}/w1/transform") == [(f"{k}/w1/transform", b"w1-b")]
    assert maps.answer(f"{k}/at~c0/transform") == [(f"{k}/at~c0/transform", b"c0")]
    assert maps.answer(f"{k}/at/atlas") == [(f"{k}/at/atlas", b"idx")]
    assert maps.answer(f"{k}/*/atlas") == [(f"{k}/at/atlas", b"idx")]
    assert [key for key, _ in maps.answer(f"{k}/*/transform")] == [
        f"{k}/at~c0/transform",
        f"{k}/w1/transform",
    ]
    with pytest.raises(ReplayError, match=f"^{ATLAS_MARKER}"):
        maps.answer(f"{k}/at/transform")
    with pytest.raises(ReplayError, match="'w2': no recorded transform"):
        maps.answer(f"{k}/w2/transform")
    with pytest.raises(ReplayError, match="no recorded map matches"):
        maps.answer(f"{k}/*/status")
    with pytest.raises(ReplayError, match="bad key"):
        maps.answer("elsewhere/ws/w1/transform")
