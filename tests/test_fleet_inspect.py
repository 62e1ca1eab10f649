"""``confnav inspect`` reports the closest robot-robot approach of a recording (exact between
poses) and the robot-robot contacts the simulator reported."""

from __future__ import annotations

from pathlib import Path

import pytest
from confnav.schemas import CollisionEvent, Pose, SpawnRequest
from test_inspect import T0, _Rec

from confnav.recording.inspect import inspect_recording

S = 1_000_000_000


def test_closest_approach_between_poses(tmp_path: Path) -> None:
    """r1 drives from (-1, 0) to (1, 0) between two poses 1 s apart, r2 stands at (0, 0.3):
    at the poses they are 1.04 m apart, the closest approach is 0.3 m at t = 0.5 s; radii
    0.1 (spawn requests): gap 0.1 m."""
    p = tmp_path / "pair.mcap"
    r = _Rec(p)
    for rid, (x, y) in (("r1", (-1.0, 0.0)), ("r2", (0.0, 0.3))):
        r.put(
            "confnav/sim/sim/spawn",
            SpawnRequest(robot_id=rid, ws_id="w1", position=(x, y), robot_radius=0.1),
            T0,
        )
    for k, x in enumerate((-1.0, 1.0)):
        t = T0 + k * S
        r.put("confnav/robot/r1/pose", Pose(robot_id="r1", stamp_ns=t, seq=k, x=x, y=0.0), t)
        r.put("confnav/robot/r2/pose", Pose(robot_id="r2", stamp_ns=t, seq=k, x=0.0, y=0.3), t)
    r.put(
        "confnav/robot/r1/collision",
        CollisionEvent(
            robot_id="r1",
            ws_id="w1",
            stamp_ns=T0 + S,
            position=(0.0, 0.0),
            clearance=-0.01,
            other_robot_id="r2",
        ),
        T0 + S + 1,
    )
    r.finish()
    rep = inspect_recording(p)
    c = rep.closest
    assert c is not None and c["robots"] == ["r1", "r2"]
    assert c["distance"] == pytest.approx(0.3, abs=1e-12)
    assert c["gap"] == pytest.approx(0.1, abs=1e-12)
    assert c["time_s"] == pytest.approx(0.5, abs=1e-9)
    text = rep.format()
    assert "closest robot-robot approach: r1 and r2" in text and "gap 0.1000 m" in text
    assert "touched robot(s) r2" in text
    assert rep.to_dict()["robot_contacts"] == [("r1", "r2")]


def test_one_robot_has_no_closest_pair(tmp_path: Path) -> None:
    p = tmp_path / "one.mcap"
    r = _Rec(p)
    r.put("confnav/robot/r1/pose", Pose(robot_id="r1", stamp_ns=T0, seq=0, x=0.0, y=0.0), T0)
    r.finish()
    rep = inspect_recording(p)
    assert rep.closest is None and "closest robot-robot" not in rep.format()
