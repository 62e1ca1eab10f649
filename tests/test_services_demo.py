"""The demo's pieces that decide its exit code and outputs: tracking, summary, plot, config."""

from __future__ import annotations

from pathlib import Path

from confnav.schemas import CollisionEvent, Pose, RobotStatus, encode
from confnav.services.demo import DemoMonitor, Track, demo_config, plot_demo, summary


def tracks() -> dict[str, Track]:
    return {
        "r1": Track("r1", 1.5 + 1j, 0j),
        "r2": Track("r2", -1.5 + 1j, 0j),
    }


def feed(mon: DemoMonitor, rid: str, pts: list[complex]) -> None:
    for i, z in enumerate(pts):
        p = Pose(robot_id=rid, stamp_ns=i + 1, seq=i, x=z.real, y=z.imag)
        mon.on_pose(f"confnav/robot/{rid}/pose", encode(p))


def test_all_arrived_is_success(tmp_path: Path) -> None:
    t = tracks()
    mon = DemoMonitor(t)
    feed(mon, "r1", [1.5 + 1j, 0.5 + 0.5j, 0.01j])
    feed(mon, "r2", [-1.5 + 1j, -0.5 + 0.5j, 0.005 + 0j])
    for rid in t:
        st = RobotStatus(robot_id=rid, stamp_ns=5, state="arrived", reason="arrived")
        mon.on_status(f"confnav/robot/{rid}/status", encode(st))
    mon.on_pose("confnav/robot/r1/pose", b"{garbage")  # ignored, no crash
    assert mon.done()
    table, ok = summary(t)
    assert ok
    assert table.count("arrived") >= 2 and "FAILED" not in table
    assert t["r1"].length == abs(0.5 + 0.5j - (1.5 + 1j)) + abs(0.01j - (0.5 + 0.5j))
    plot_demo(t, tmp_path / "demo.png")
    assert (tmp_path / "demo.png").read_bytes()[:4] == b"\x89PNG"


def test_collision_or_timeout_is_failure() -> None:
    t = tracks()
    mon = DemoMonitor(t)
    feed(mon, "r1", [1.5 + 1j, 1.3 + 0.9j])
    ev = CollisionEvent(
        robot_id="r1", ws_id="default", stamp_ns=3, position=(1.3, 0.9), clearance=-0.01
    )
    mon.on_collision("confnav/robot/r1/collision", encode(ev))
    st = RobotStatus(robot_id="r2", stamp_ns=5, state="stopped", reason="stale_pose")
    mon.on_status("confnav/robot/r2/status", encode(st))
    assert not mon.done()  # r2 neither arrived nor collided
    table, ok = summary(t)
    assert not ok
    assert "COLLIDED" in table and "FAILED (stale_pose)" in table


def test_demo_config_runs_the_four_services_recorder_first(tmp_path: Path) -> None:
    cfg = demo_config("unixsock-stream//tmp/x.sock", tmp_path, {"r1": 1 + 1j}, 2.0, None)
    assert [s.name for s in cfg.services] == ["recorder", "transform", "controller", "simulator"]
    sim = cfg.services[3].args
    assert "r1=default:1.0,1.0" in sim and "--time-scale" in sim
    assert str(tmp_path / "demo.mcap") in cfg.services[0].args
