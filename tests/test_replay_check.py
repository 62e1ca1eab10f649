"""``confnav replay --check``: recorded commands are recomputed through the controller's own
code, pass on unchanged code and fail when a gain (or the code) changes."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from confnav.schemas import Goal, Pose, VelocityCommand, encode
from confnav.services import navigation
from conftest import confnav_cmd, identity_loader, subprocess_env
from mcap.writer import Writer

from confnav.recording import layout as L
from confnav.recording.reader import RecordingError
from confnav.recording.replay_check import (
    CheckError,
    check_recording,
    decide,
    parse_overrides,
)

DATA = Path(__file__).resolve().parent / "data"
GOLDEN = sorted(DATA.glob("golden_*.mcap"))


def _make_golden() -> ModuleType:
    spec = importlib.util.spec_from_file_location("confnav_make_golden", DATA / "make_golden.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of the real services (fake map: identity of a circle domain)."""
    path = tmp_path_factory.mktemp("check") / "run.mcap"
    _make_golden().run_pipeline(path, solver="fake", time_scale=4.0)
    return path


def test_unchanged_code_reproduces_every_command(fake_run: Path) -> None:
    report = check_recording(fake_run, load_map=identity_loader)
    assert report.ok, report.format()
    assert report.checked >= 50 and set(report.per_robot) == {"r1", "r2"}
    assert report.max_error <= 1e-12  # same code, same inputs: identical to rounding


@pytest.mark.parametrize("override", ["gain=1.2", "gain=0.8", "navfn=kr", "v_max=0.25"])
def test_changed_parameters_are_detected(fake_run: Path, override: str) -> None:
    report = check_recording(
        fake_run, load_map=identity_loader, overrides=parse_overrides([override])
    )
    assert not report.ok
    assert report.mismatch_count > 0 and report.mismatches
    first = report.mismatches[0]
    assert first.error > report.atol
    text = report.format(max_report=3)
    assert "FAIL" in text and f"robot {first.robot_id}" in text


def test_changed_code_is_detected(fake_run: Path) -> None:
    """A 'code change' in the controller factory (here: the gain doubled inside it) fails."""

    def changed(cmap: Any, goal: Goal) -> navigation.ControllerLike:
        return navigation.make_controller(cmap, goal.model_copy(update={"gain": 2 * goal.gain}))

    report = check_recording(fake_run, load_map=identity_loader, make_controller=changed)
    assert not report.ok and report.mismatch_count > 0


def test_tolerance_is_what_decides(fake_run: Path) -> None:
    """With a tolerance larger than the change, a small gain change passes; at the stated
    tolerance it fails (the tolerance is applied, not ignored)."""
    changed = parse_overrides(["gain=1.000001"])
    tight = check_recording(fake_run, load_map=identity_loader, overrides=changed)
    loose = check_recording(fake_run, load_map=identity_loader, overrides=changed, atol=1e-3)
    assert not tight.ok and loose.ok


def test_decide_matches_the_controller_policy() -> None:
    class Fixed:
        def __init__(self, u: complex, status: int) -> None:
            self.u, self.status = u, status

        def __call__(self, z: Any) -> Any:
            return self

    # the same decision function as the live controller service (navigation.decide)
    outside = "pose outside the mapped free space"
    assert decide(None, 0.0, 0.0) == (0j, "no controller")
    assert decide(Fixed(1 + 1j, navigation.MOVING), 0, 0) == (1 + 1j, "ok")
    assert decide(Fixed(1 + 1j, navigation.ARRIVED), 0, 0) == (0j, "arrived")
    assert decide(Fixed(complex("nan"), navigation.MOVING), 0, 0) == (0j, outside)
    assert decide(Fixed(1j, navigation.ERROR), 0, 0) == (0j, outside)
    u, why = decide(Fixed(1j, navigation.STALLED), 0, 0)
    assert u == 1j and "stalled" in why
    d = navigation.decide(Fixed(1j, navigation.ERROR), 1j, navigation.ERROR)
    assert (d.state, d.reason) == ("stopped", "outside_workspace")


def test_bad_overrides() -> None:
    with pytest.raises(CheckError, match="FIELD"):
        parse_overrides(["robot_id=x"])
    with pytest.raises(CheckError, match="not a number"):
        parse_overrides(["gain=fast"])
    assert parse_overrides(["k=auto", "gain=2"]) == {"k": None, "gain": 2.0}


def test_missing_channels_are_reported(tmp_path: Path) -> None:
    path = tmp_path / "poses_only.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(L.PROFILE, "test")
        sid = w.register_schema(L.schema_name(Pose), L.SCHEMA_ENCODING, L.schema_data(Pose))
        cid = w.register_channel("confnav/robot/r1/pose", L.MESSAGE_ENCODING, sid)
        w.add_message(cid, 1, encode(Pose(robot_id="r1", stamp_ns=1, x=0.0, y=0.0)), 1)
        vs = w.register_schema(
            L.schema_name(VelocityCommand), L.SCHEMA_ENCODING, L.schema_data(VelocityCommand)
        )
        vid = w.register_channel("confnav/robot/r1/cmd_vel", L.MESSAGE_ENCODING, vs)
        cmd = VelocityCommand(robot_id="r1", stamp_ns=2, linear=(0.0, 0.0))
        w.add_message(vid, 2, encode(cmd), 2)
        w.finish()
    with pytest.raises(RecordingError, match="no transform channel"):
        check_recording(path)
    res = subprocess.run(
        confnav_cmd("replay", "--check", str(path)),
        capture_output=True,
        text=True,
        timeout=60,
        env=subprocess_env(),
    )
    assert res.returncode == 1 and "no transform channel" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.skipif(not GOLDEN, reason="no golden recording in tests/data")
@pytest.mark.parametrize("golden", GOLDEN, ids=lambda p: p.name)
def test_golden_recording_passes_and_fails_on_gain_change(golden: Path) -> None:
    """The committed golden recordings (real solver): the CLI passes, and fails (exit 1,
    mismatches listed) when a gain is changed."""
    assert sum(p.stat().st_size for p in DATA.iterdir() if p.is_file()) < 1_000_000
    ok = subprocess.run(
        confnav_cmd("replay", "--check", str(golden)),
        capture_output=True,
        text=True,
        timeout=120,
        env=subprocess_env(),
    )
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "OK: all" in ok.stdout
    bad = subprocess.run(
        confnav_cmd("replay", "--check", str(golden), "--set", "gain=1.5", "--max-report", "2"),
        capture_output=True,
        text=True,
        timeout=120,
        env=subprocess_env(),
    )
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert "FAIL" in bad.stdout and "recomputed" in bad.stdout


def test_unloadable_map_is_a_clear_error(fake_run: Path) -> None:
    def broken(sol: Any) -> Any:
        raise ValueError("unknown coefficient format")

    with pytest.raises(RecordingError, match="cannot be loaded by this version"):
        check_recording(fake_run, load_map=broken)
