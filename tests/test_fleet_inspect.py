"""``confnav inspect`` reports the closest robot-robot approach of a recording (exact between
poses) and the robot-robot contacts the simulator reported."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from confnav.schemas import CollisionEvent, Pose, SpawnRequest
from test_foxglove_scene import validator  # noqa: F401  (the SceneUpdate schema fixture)
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


def test_movers_in_the_foxglove_scene(validator: Any) -> None:  # noqa: F811
    """A Movers message shows in the workspace scene as one ``movers`` entity: each disk, a
    velocity line to where it will be in 1 s, its id; the next message replaces it."""
    import math

    from confnav.schemas import MoverDisk, Movers, WorkspaceDefinition

    from confnav.recording import scene_builder as sb

    b = sb.SceneBuilder(period_ns=0)
    b.observe(WorkspaceDefinition(ws_id="w1", outer=[(0, 0), (4, 0), (4, 3), (0, 3)]), T0)
    person = MoverDisk(mover_id="p1", position=(1.0, 1.0), radius=0.3, velocity=(1.2, 0.0))
    msgs = b.observe(Movers(ws_id="w1", stamp_ns=T0, movers=[person]), T0 + 1)
    scene = next(m for m in msgs if m.topic == "confnav/viz/w1/scene").message
    ent = next(e for e in scene["entities"] if e["id"] == "movers")
    disk, vel = ent["lines"]
    radii = [math.hypot(p["x"] - 1.0, p["y"] - 1.0) for p in disk["points"]]
    validator.validate(scene)
    # coordinates are written to 1e-6 m (confnav.recording.scene.COORD_DECIMALS)
    assert max(abs(r - 0.3) for r in radii) < 2e-6 and disk["type"] == 1  # a closed loop
    assert vel["points"][1]["x"] == pytest.approx(2.2) and ent["texts"][0]["text"] == "p1"
    msgs = b.observe(Movers(ws_id="w1", stamp_ns=T0 + 2), T0 + 2)  # gone
    scene = next(m for m in msgs if m.topic == "confnav/viz/w1/scene").message
    ent = next(e for e in scene["entities"] if e["id"] == "movers")
    assert ent["lines"] == [] and ent["texts"] == []
