"""Differential-drive (unicycle) robots on an atlas: the look-ahead law
(:class:`confnav.navigation.unicycle.UnicycleController`) around a robot's switching
controller (:class:`confnav.atlas.wire.AtlasController`) on the atlas of the free space shrunk
by radius + look-ahead.

In process: the controller the services build (``make_controller`` on an :class:`AtlasMap`)
drives a unicycle down a 12 x 1 m corridor under the exact unicycle integrator, switching
charts of strictly decreasing rank, and it is the look-ahead point, not the axle, that the
atlas sees.  Through the services (real processes, real Zenoh over a unix socket): a unicycle
robot with a radius gets body-frame twists, switches charts down the plan, arrives with its
body clear of the walls, and ``replay --check`` recomputes its commands from the recording.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from confnav.schemas import (
    AtlasIndex,
    Goal,
    Pose,
    SpawnRequest,
    TransformSolution,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.atlas_transform import messages_of
from confnav.services.launcher import ServiceSpec
from confnav.services.navigation import commands, footprint_radius, make_controller, map_ws_id
from confnav.services.transform import solution_result
from conftest import RobotWatch, launched_system, wait_for
from mcap.reader import make_reader

from confnav.atlas import solve_atlas
from confnav.atlas.scenes import corridor
from confnav.atlas.wire import AtlasController, AtlasMap, atlas_map_of, index_fields
from confnav.conformal.cmap import ConformalMap
from confnav.maps.footprint import derived_ws_id, inflate
from confnav.navigation.control import Status
from confnav.navigation.unicycle import (
    ARRIVED,
    UnicycleController,
    look_ahead_point,
    simulate_unicycle,
)
from confnav.recording.inspect import inspect_recording
from confnav.recording.replay_check import check_recording

SCENE = corridor(12.0)  # L/w = 12: one map of it crowds (test_atlas_services.py)
ROOM = corridor(3.0, 1.5)  # 4.5 x 1.5 m: one map (a unicycle there checks single-map replay)
RADIUS, LOOKAHEAD = 0.1, 0.1  # the free space is shrunk by 0.2 m: 11.6 x 0.6 m, L/w = 19
GOAL = (SCENE.goal.real, SCENE.goal.imag)


def unicycle_goal(rid: str = "u1", ws_id: str = "corr") -> Goal:
    return Goal(
        robot_id=rid, ws_id=ws_id, goal=GOAL, v_max=1.0, tolerance=0.05,
        robot_radius=RADIUS, drive="unicycle", lookahead=LOOKAHEAD, omega_max=3.0,
    )  # fmt: skip


@pytest.fixture(scope="module")
def shrunk_atlas() -> AtlasMap:
    """The atlas of the corridor shrunk by radius + look-ahead, through the wire messages (as
    the controller service and ``replay --check`` get it)."""
    ws = inflate(SCENE.workspace, RADIUS + LOOKAHEAD)
    atlas = solve_atlas(ws, 1e-8, workers=1)
    result = {
        "atlas": index_fields(atlas),
        "charts": [solution_result(m, 1e-8) for m in atlas.charts],
    }
    index, charts = messages_of("corr~r0.2", "h" * 64, result)
    return atlas_map_of(index, {c.revision: ConformalMap.from_dict(c.coefficients) for c in charts})


def test_a_unicycle_drives_down_the_atlas_of_its_shrunk_corridor(shrunk_atlas: AtlasMap) -> None:
    g = unicycle_goal()
    assert footprint_radius(g) == RADIUS + LOOKAHEAD and map_ws_id(g) == "corr~r0.2"
    uc = make_controller(shrunk_atlas, g)
    assert isinstance(uc, UnicycleController) and uc.frame == "body"
    inner = uc.controller
    assert isinstance(inner, AtlasController)
    assert uc.goal == complex(*GOAL) and uc.goal_tol == 0.05 and uc.active_chart is None
    # the axle 0.15 m from the end wall lies outside the shrunk corridor (x >= 0.2), its
    # look-ahead point 0.25 m from it inside: the atlas sees the point (the axle: ERROR)
    z0, th0 = 0.15 + 0.5j, 0.0
    assert int(AtlasController(inner.nav)(np.array([z0])).status[0]) == Status.ERROR
    run = simulate_unicycle(
        uc, [z0], [th0], clearance=SCENE.workspace.clearance, radius=RADIUS, t_max=60.0
    )
    assert run.status[0] == ARRIVED, run.status
    assert not run.collided[0] and run.min_clearance[0] > 0  # the body's clearance
    assert run.final_distance[0] <= 0.05  # the look-ahead point at the goal
    hist = inner.history
    rank = inner.nav.plan.rank
    assert len(hist) >= 4 and hist[-1] in inner.nav.plan.goal_cells, hist
    assert all(rank[b] < rank[a] for a, b in itertools.pairwise(hist)), hist
    assert uc.active_chart == hist[-1]  # the passthrough the controller service reads
    # the switch is decided at the look-ahead point: a fresh controller put where axle and
    # point lie in different cells picks the point's cell
    nav = inner.nav
    for x in np.linspace(1.0, 11.0, 41):
        z = complex(x, 0.5)
        p = complex(look_ahead_point(z, 0.0, LOOKAHEAD))
        cz, cp = nav.initial_cells(np.array([z, p]))
        if cz != cp:
            fresh = make_controller(shrunk_atlas, g)
            commands(fresh, np.array([z]), np.array([0.0]))
            assert fresh.active_chart == cp != cz  # type: ignore[attr-defined]
            break
    else:
        pytest.fail("no pose with the axle and its look-ahead point in different cells")


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_unicycle_on_an_atlas_through_the_services(tmp_path: Path) -> None:
    ws_file, room_file = tmp_path / "corr.json", tmp_path / "room.json"
    SCENE.workspace.save(ws_file)
    ROOM.workspace.save(room_file)
    spaces = ["--workspace", f"corr={ws_file}", "--workspace", f"room={room_file}"]
    mcap_path = tmp_path / "uni.mcap"
    services = [
        ServiceSpec("recorder", ["--out", str(mcap_path)]),
        ServiceSpec("transform", spaces),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", [*spaces, "--time-scale", "2"]),
    ]
    watch = RobotWatch()
    lock, status, collisions = watch.lock, watch.status, watch.collisions
    rid = "u1"
    shrunk = derived_ws_id("corr", RADIUS + LOOKAHEAD)
    with launched_system(services, tmp_path, prefix="cnu") as system:
        bus, k = system.bus, system.keys
        watch.attach(bus, k)
        # the axle where a point robot could not start (0.15 m from the end wall), turned
        # 0.5 rad off the corridor's axis: its look-ahead point at (0.24, 0.50)
        spawn = SpawnRequest(
            robot_id=rid, ws_id="corr", position=(0.15, 0.45), theta=0.5,
            robot_radius=RADIUS, drive="unicycle",
        )  # fmt: skip
        bus.publish(k.sim("sim", "spawn"), encode(spawn))
        bus.publish(k.robot(rid, "goal"), encode(unicycle_goal(rid)))
        other = SpawnRequest(
            robot_id="u2", ws_id="room", position=(0.5, 0.4), theta=2.0,
            robot_radius=RADIUS, drive="unicycle",
        )  # fmt: skip
        bus.publish(k.sim("sim", "spawn"), encode(other))
        room_goal = unicycle_goal("u2", "room").model_copy(
            update={"goal": (ROOM.goal.real, ROOM.goal.imag)}
        )
        bus.publish(k.robot("u2", "goal"), encode(room_goal))

        def arrived() -> bool:
            with lock:
                return all(status[r] and status[r][-1].state == "arrived" for r in ("u1", "u2"))

        wait_for(arrived, timeout=200, interval=0.2)
        with lock:
            assert collisions == []
            assert {s.ws_id for s in status[rid]} == {shrunk}
            assert {s.chart for s in status["u2"]} == {None}  # one map, no atlas
        codes = system.shutdown()
        assert codes.get("recorder") == 0, codes

    index = None
    charts: dict[str, ConformalMap] = {}
    seq: list[int] = []
    frames: list[tuple[str, complex]] = []
    poses: list[complex] = []
    with open(mcap_path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == k.ws(shrunk, "atlas"):
                index = decode(AtlasIndex, message.data)
            elif channel.topic.endswith("/transform") and "~c" in channel.topic:
                sol = decode(TransformSolution, message.data)
                charts[sol.revision] = ConformalMap.from_dict(sol.coefficients)
            elif channel.topic == k.robot(rid, "pose"):
                p = decode(Pose, message.data)
                poses.append(complex(p.x, p.y))
            elif channel.topic == k.robot(rid, "cmd_vel"):
                cmd = decode(VelocityCommand, message.data)
                if cmd.pose_seq >= 0:
                    frames.append((cmd.frame, complex(cmd.linear[0], cmd.angular)))
                    if cmd.chart is not None and (not seq or seq[-1] != cmd.chart):
                        seq.append(cmd.chart)
    # the atlas is that of the shrunk corridor; its charts are the shrunk cells' maps
    assert index is not None and index.ws_id == shrunk
    am = atlas_map_of(index, charts)
    ws = am.atlas.workspace
    assert ws.polygon.symmetric_difference(inflate(SCENE.workspace, 0.2).polygon).area < 1e-12
    assert ws.polygon.area < 0.6 * 11.6 + 1e-9  # (the original is 12 x 1)
    # twists v + i omega only, once the map is in (before it: zero commands, holding for it)
    first = [f for f, _ in frames].index("body")
    assert all(f == "world" and u == 0 for f, u in frames[:first])
    assert all(f == "body" for f, _ in frames[first:]) and len(frames) - first > 100
    assert max(abs(u.imag) for _, u in frames) > 0.1  # it turned
    rank = am.controller(unicycle_goal(rid).model_copy(update={"ws_id": shrunk}))
    order = rank.controller.nav.plan.rank  # type: ignore[union-attr]
    assert len(seq) >= 4, seq  # it switched charts down the corridor ...
    assert all(order[b] < order[a] for a, b in itertools.pairwise(seq)), seq  # ... downwards
    # the body (radius RADIUS around the axle) never touched a wall
    body = np.asarray(SCENE.workspace.clearance(np.array(poses)), dtype=float) - RADIUS
    assert len(poses) > 100 and float(body.min()) > 0, float(body.min())
    # replay --check recomputes every body-frame twist, switching included (and those of
    # the unicycle on a single map)
    report = check_recording(mcap_path)
    assert report.ok and report.per_robot[rid] > 100, report.format()
    assert report.per_robot["u2"] > 50, report.format()
    assert not report.skipped.get("body-frame twist (unicycle)")
    summary = inspect_recording(mcap_path)
    assert summary.atlases[shrunk].revision == index.revision
    assert summary.robots[rid].charts == seq and summary.robots[rid].arrived
    # what was used, not the base workspace's map: the shrunk corridor's atlas, the cells the
    # robot had active and its last chart
    r = summary.robots[rid]
    assert (r.map_ws_id, r.atlas, r.chart) == (shrunk, shrunk, seq[-1])
    assert summary.robots["u2"].atlas is None  # a single map
    assert summary.cells_used(shrunk) == sorted(set(seq))
    text = summary.format()
    n = len(index.cells)
    assert f"map: atlas {shrunk} ({n} cells, revision {index.revision[:12]}), active chart" in text
    assert f"atlas {shrunk}: {n} cells, used by {rid}: cells " in text


def test_the_atlas_command_drives_unicycles_with_a_radius(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from confnav.cli.app import main

    sc = corridor(8)
    ws_path, out = tmp_path / "corridor.json", tmp_path / "runs.json"
    sc.workspace.save(ws_path)
    argv = [
        "atlas", str(ws_path), f"--goal={sc.goal.real},{sc.goal.imag}",
        "--starts=0.5,0.5;3,0.4", "--tol=1e-6", "--workers=1", "--json", str(out),
        "--robot-radius=0.1", "--unicycle=0.1",
    ]  # fmt: skip
    code = main(argv)
    text = capsys.readouterr().out
    assert code == 0, text
    assert "2 arrived; collisions 0" in text and "(the body's)" in text
    clearance = float(text.split("min clearance ")[1].split()[0])
    assert 0 < clearance <= 0.3 + 1e-9  # the body's: at most the half-width minus the radius
    doc = json.loads(out.read_text())
    # the cells are those of the corridor shrunk by 0.2 m: none reaches within 0.2 of a wall
    outer = [np.array(c["workspace"]["outer"]) for c in doc["cells"]]
    assert min(float(o[:, 1].min()) for o in outer) >= 0.2 - 1e-9
    assert max(float(o[:, 1].max()) for o in outer) <= 0.8 + 1e-9
    ranks = [c["rank"] for c in doc["cells"]]
    for r in doc["runs"]:
        assert r["status"] == "arrived" and len(r["cells"]) >= 2
        assert all(ranks[a] > ranks[b] for a, b in itertools.pairwise(r["cells"]))
    assert main([*argv[:-2], "--robot-radius=-1"]) == 1
    assert "--robot-radius" in capsys.readouterr().err
