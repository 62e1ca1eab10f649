"""``confnav goal`` / ``cancel`` / ``status`` against a running system: real router, real
transform + controller + simulator processes under the launcher, the CLI as a subprocess."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from confnav.schemas import WAITING_FOR_MAP, RobotStatus
from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.launcher import LaunchConfig, Launcher, ServiceSpec
from conftest import confnav_cmd, subprocess_env, wait_for

from confnav.cli.ops import goal_verdict
from confnav.geometry import Workspace

ROOM = Workspace(
    [(-1, -1), (1, -1), (1, 1), (-1, 1)],
    [[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2), (0.2, 0.2)]],
    anchor=0j,
)


def run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        confnav_cmd(*args), capture_output=True, text=True, timeout=timeout, env=subprocess_env()
    )


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A launched system with robot r1 idle at (0.8, -0.6) in workspace ``room``; yields the
    router endpoint."""
    out = tmp_path_factory.mktemp("ops")
    room = out / "room.json"
    ROOM.save(room)
    sockdir = tempfile.mkdtemp(prefix="cno", dir="/tmp")
    sock = f"unixsock-stream/{sockdir}/router.sock"
    cfg = LaunchConfig(
        listen=[sock],
        services=[
            ServiceSpec(
                "transform", ["--workspace", f"room={room}", "--cache-dir", str(out / "cache")]
            ),
            ServiceSpec("controller", []),
            ServiceSpec(
                "simulator",
                ["--workspace", f"room={room}", "--time-scale", "2", "--robot", "r1=room:0.8,-0.6"],
            ),
        ],
        startup_timeout=60,
        log_dir=str(out / "logs"),
    )
    launcher = Launcher(cfg)
    stop = threading.Event()
    monitor = threading.Thread(target=launcher.monitor, args=(stop,), daemon=True)
    try:
        launcher.start()
        monitor.start()
        with ZenohBus(zenoh_config("client", connect=[sock])) as bus:
            wait_for(
                lambda: any(r.ok for r in bus.query(launcher.keys.ws("room", "transform"))),
                timeout=90,
                interval=0.5,
            )
        yield sock
    finally:
        stop.set()
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(180)
def test_goal_makes_robot_arrive_and_status_lists_it(system: str) -> None:
    sent = run("goal", "r1", "--ws", "room", "--gain", "5", "--connect", system, "--", "-0.6,0")
    assert sent.returncode == 0, sent.stderr
    assert "sent to robot r1" in sent.stdout
    assert "robot r1" in sent.stdout and "navigating" in sent.stdout

    def arrived() -> str | None:
        st = run("status", "--window", "1.0", "--connect", system)
        assert st.returncode == 0, st.stderr
        line = next(ln for ln in st.stdout.splitlines() if "robot r1" in ln)
        return st.stdout if " arrived " in line else None

    text = wait_for(arrived, timeout=60, interval=0.5)
    # the arrival point is the goal within the tolerance
    line = next(ln for ln in text.splitlines() if "robot r1" in ln)
    pos = line.split(" at (")[1].split(")")[0]
    x, y = (float(v) for v in pos.split(","))
    assert abs(complex(x, y) - complex(-0.6, 0.0)) <= 0.02 + 1e-3
    # workspaces and live services are listed with their state
    assert "room" in text and "solved" in text
    for service in ("router", "transform", "controller", "simulator"):
        assert service in text
    assert "services alive: 4" in text  # the three services and the router

    cancel = run("cancel", "r1", "--connect", system)
    assert cancel.returncode == 0, cancel.stderr


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_status_lists_robots_by_their_poses_and_the_routers_health(system: str) -> None:
    """A robot the simulator moves is listed although no controller reports on it (before any
    goal, or after a cancel, when the controller forgets it); the router has health like the
    other services (issue 26 item 9)."""
    cancel = run("cancel", "r1", "--connect", system)
    assert cancel.returncode == 0, cancel.stderr

    def seen() -> str | None:
        st = run("status", "--window", "1.5", "--connect", system)
        assert st.returncode == 0, st.stderr
        return (
            st.stdout if "robot r1" in st.stdout and " ok " in _line(st.stdout, "router") else None
        )

    text = wait_for(seen, timeout=60, interval=0.5)
    assert "robots: 1" in text
    line = _line(text, "robot r1")
    assert " idle " in line
    pos = line.split(" at (")[1].split(")")[0]
    x, y = (float(v) for v in pos.split(","))
    assert -1 < x < 1 and -1 < y < 1  # a position from the robot's poses, inside the room
    assert "no health message" not in text


def _line(text: str, what: str) -> str:
    return next((ln for ln in text.splitlines() if what in ln), "")


@pytest.mark.integration
def test_goal_outside_free_space_is_rejected(system: str) -> None:
    res = run("goal", "r1", "0.3,0", "--ws", "room", "--connect", system)  # inside the obstacle
    assert res.returncode == 1
    assert "goal rejected" in res.stderr.strip().splitlines()[-1]
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (("goal", "r/1", "1,2"), "robot id 'r/1'"),
        (("goal", "r*", "1,2"), "robot id 'r*'"),
        (("goal", "r1", "3,x"), "point '3,x' is not X,Y"),
        (("goal", "r1", "1,2,3"), "is not X,Y"),
        (("goal", "r1", "nan,2"), "not finite"),
        (("cancel", "a b"), "robot id 'a b'"),
        (("status", "--prefix", "a/*"), "prefix chunk"),
    ],
)
def test_bad_input_one_line_and_nonzero_exit(args: tuple[str, ...], message: str) -> None:
    res = run(*args)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert message in res.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize("cmd", [("goal", "r1", "1,2"), ("cancel", "r1"), ("status",)])
def test_no_router_reachable(cmd: tuple[str, ...], sockdir: Path) -> None:
    t0 = time.monotonic()
    res = run(
        *cmd, "--connect", f"unixsock-stream/{sockdir}/nobody.sock", "--connect-timeout", "0.3"
    )
    assert res.returncode == 1
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert "cannot reach a Zenoh router" in res.stderr
    assert time.monotonic() - t0 < 30


@pytest.mark.parametrize(
    ("state", "reason", "message", "verdict"),
    [
        (
            "navigating",
            "ok",
            f"{WAITING_FOR_MAP} 'ws~r0.2' (being solved; ...)",
            "map_being_solved",
        ),
        ("stopped", "missing_map", "workspace 'ws' is being solved; retry", "map_being_solved"),
        ("stopped", "missing_map", "unknown workspace 'ws'", "pending"),
        ("navigating", "ok", "holding for chart 3 of the atlas (being solved; ...)", "done"),
        ("navigating", "ok", "", "done"),
        ("arrived", "arrived", "", "done"),
        ("stopped", "outside_workspace", "start inside an obstacle", "done"),
    ],
)
def test_goal_waits_while_the_map_is_being_solved_and_not_longer(
    state: str, reason: str, message: str, verdict: str
) -> None:
    s = RobotStatus(robot_id="r", stamp_ns=1, state=state, reason=reason, message=message)  # type: ignore[arg-type]
    assert goal_verdict(s) == verdict
