"""The external-robot recipe of the docs arrives with the defaults: real transform and
controller services (processes under the launcher, unix-socket Zenoh), and a robot that is a
separate process speaking raw Zenoh + JSON only (examples/external_robot.py)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from confnav.services.launcher import LaunchConfig, Launcher, ServiceSpec
from conftest import subprocess_env

from confnav.geometry import Workspace

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "external_robot.py"
# a 5 x 4 m room with a 1.2 x 1.2 m cabinet between the start and the goal
ROOM = Workspace([(0, 0), (5, 0), (5, 4), (0, 4)], [[(2, 1.4), (3.2, 1.4), (3.2, 2.6), (2, 2.6)]])


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_external_robot_recipe_arrives_with_the_defaults(tmp_path: Path) -> None:
    room = tmp_path / "room.json"
    ROOM.save(room)
    sockdir = tempfile.mkdtemp(prefix="cnx", dir="/tmp")
    sock = f"unixsock-stream/{sockdir}/router.sock"
    cfg = LaunchConfig(
        listen=[sock],
        services=[
            ServiceSpec("transform", ["--workspace", f"room={room}"]),
            ServiceSpec("controller", []),
        ],
        startup_timeout=60,
        log_dir=str(tmp_path / "logs"),
    )
    launcher = Launcher(cfg, verbose=1)
    try:
        launcher.start()
        proc = subprocess.run(
            [sys.executable, str(SCRIPT), sock, "r1", "room", "0.5,2.0", "4.5,2.0", "150"],
            env=subprocess_env(),
            capture_output=True,
            text=True,
            timeout=200,
        )
    finally:
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("arrived")
    travelled = float(proc.stdout.split("travelled ")[1].split(" m")[0])
    assert 4.0 < travelled < 6.0  # around the cabinet: more than the 4 m straight line
