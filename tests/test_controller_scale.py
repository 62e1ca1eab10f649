"""The optional batched wire path (issue 25 item 5): a ``PoseBatch`` per simulator step is
answered with one ``CommandBatch`` whose entries are exactly the commands single poses get."""

from __future__ import annotations

import json
import time
from typing import Any

import pytest
from confnav.schemas import (
    CommandBatch,
    DecodeError,
    Pose,
    PoseBatch,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from conftest import wait_for
from test_services_controller import expected_u, same, setup

K = Keys()


class BatchClient:
    """A simulator stand-in publishing pose batches and collecting the command batches."""

    def __init__(self, bus: Any, sim: str = "s1") -> None:
        self.bus = bus
        self.sim = sim
        self.batches: list[CommandBatch] = []
        bus.subscribe(K.sim(sim, "cmd_vel"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        self.batches.append(decode(CommandBatch, payload))

    def poses(self, rows: list[tuple[str, int, float, float]], stamp: int | None = None) -> int:
        t = time.time_ns() if stamp is None else stamp
        b = PoseBatch(
            sim_id=self.sim,
            stamp_ns=t,
            robot_ids=[r[0] for r in rows],
            stamps_ns=[t] * len(rows),
            seq=[r[1] for r in rows],
            x=[r[2] for r in rows],
            y=[r[3] for r in rows],
            theta=[0.0] * len(rows),
        )
        self.bus.publish(K.sim(self.sim, "poses"), encode(b))
        return t

    def answering(self, seq: int) -> CommandBatch | None:
        hits = [b for b in self.batches if seq in b.pose_seq]
        return hits[-1] if hits else None


def test_pose_batch_gets_the_commands_single_poses_get(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    sim = BatchClient(mem_net.bus("sim"))
    try:
        rids = [f"r{i}" for i in range(12)]
        goals = {r: cl.goal(r) for r in rids}
        wait_for(lambda: ctl.counters["goals"] == 12 and ctl.counters["maps_installed"])
        wait_for(lambda: all(ctl.robot_state(r) is not None for r in rids))
        pts = {r: (0.1 * (i % 4) - 0.2, 0.15 * (i // 4) - 0.5) for i, r in enumerate(rids)}
        # "idle" has no goal: remembered, not answered (as a single pose of it would be)
        rows = [(r, 3, *pts[r]) for r in rids] + [("idle", 3, 0.0, 0.6)]
        t = sim.poses(rows)
        b = wait_for(lambda: sim.answering(3))
        assert b.sim_id == "s1" and set(b.robot_ids) == set(rids)
        cmds = {c.robot_id: c for c in b.commands()}
        for r in rids:
            c = cmds[r]
            assert (c.pose_seq, c.pose_stamp_ns, c.map_revision) == (3, t, "rev1")
            assert c.frame == "world" and c.chart is None
            assert same(complex(*c.linear), expected_u(goals[r], complex(*pts[r])))
        # the same poses one by one: the same commands (one control law, one map)
        for r in rids[:3]:
            p = Pose(robot_id=r, stamp_ns=time.time_ns(), seq=4, x=pts[r][0], y=pts[r][1])
            cl.bus.publish(K.robot(r, "pose"), encode(p))

        def single(r: str) -> VelocityCommand | None:
            c = [m for m in cl.cmds if m.robot_id == r and m.pose_seq == 4]
            return c[-1] if c else None

        for r in rids[:3]:
            assert same(complex(*wait_for(lambda r=r: single(r)).linear), complex(*cmds[r].linear))
        # statuses stay per robot
        wait_for(lambda: cl.last_status("r0") and cl.last_status("r0").state == "navigating")
        # an older pose of a robot (stamp and seq of its first batch) is not fresh: not answered
        sim.poses([("r0", 3, 0.0, 0.0), ("r5", 5, *pts["r5"])], stamp=t)
        b5 = wait_for(lambda: sim.answering(5))
        assert b5.robot_ids == ["r5"]
        assert ctl.counters["poses_out_of_order"] >= 1
    finally:
        ctl.stop()


def test_a_shard_answers_only_its_robots(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, robots={"a1", "a2"})
    sim = BatchClient(mem_net.bus("sim"))
    try:
        for r in ("a1", "a2", "b1"):
            cl.goal(r)
        wait_for(lambda: ctl.counters["maps_installed"] and ctl.robot_state("a2") is not None)
        sim.poses([("a1", 1, 0.1, 0.5), ("b1", 1, 0.2, 0.5), ("a2", 1, -0.1, 0.5)])
        b = wait_for(lambda: sim.answering(1))
        assert b.robot_ids == ["a1", "a2"]
        assert ctl.robot_state("b1") is None
    finally:
        ctl.stop()


def test_bad_pose_batches_are_rejected_and_the_controller_goes_on(
    mem_net: InMemoryNetwork,
) -> None:
    ctl, _tr, cl = setup(mem_net)
    sim = BatchClient(mem_net.bus("sim"))
    try:
        cl.goal("r1")
        wait_for(lambda: ctl.counters["maps_installed"] and ctl.robot_state("r1") is not None)
        bus = sim.bus
        ok = encode(
            PoseBatch(sim_id="s1", stamp_ns=1, robot_ids=["r1"], stamps_ns=[1], seq=[1],
                      x=[0.1], y=[0.5], theta=[0.0])
        )  # fmt: skip
        bad = [
            ok.replace(b'"x":[0.1]', b'"x":[NaN]'),  # not finite
            ok.replace(b'"seq":[1]', b'"seq":[1,2]'),  # columns of different lengths
            ok.replace(b'"robot_ids":["r1"]', b'"robot_ids":["r1","r1"]').replace(
                b'"seq":[1]', b'"seq":[1,1]'
            ),  # a robot twice (other columns too short as well)
            b"{garbage",
        ]
        for payload in bad:
            bus.publish(K.sim("s1", "poses"), payload)
        bus.publish(K.sim("s2", "poses"), ok)  # names simulator s1 on s2's key
        wait_for(lambda: ctl.counters["rejected"] >= len(bad) + 1)
        assert not sim.batches
        sim.poses([("r1", 7, 0.1, 0.5)])
        assert wait_for(lambda: sim.answering(7)).robot_ids == ["r1"]
    finally:
        ctl.stop()


@pytest.mark.parametrize(
    "change",
    [
        {"seq": [1]},  # one entry, two robots
        {"robot_ids": ["r1", "r1"], "seq": [1, 2], "stamps_ns": [1, 1], "x": [0.0, 0.0],
         "y": [0.0, 0.0], "theta": [0.0, 0.0]},  # a robot twice
    ],
)  # fmt: skip
def test_pose_batch_columns_must_match(change: dict[str, Any]) -> None:
    base = dict(sim_id="s", stamp_ns=1, robot_ids=["r1", "r2"], stamps_ns=[1, 1], seq=[1, 2],
                x=[0.0, 1.0], y=[0.0, 1.0], theta=[0.0, 0.0])  # fmt: skip
    good = PoseBatch.model_validate(base)
    assert [p.robot_id for p in good.poses()] == ["r1", "r2"]
    payload = json.dumps({"type": "confnav.PoseBatch", "schema_version": 1, **base, **change})
    with pytest.raises(DecodeError) as exc:
        decode(PoseBatch, payload.encode())
    assert exc.value.reason == "invalid_input"


def test_simulator_pose_batches_drive_robots_like_single_poses(mem_net: InMemoryNetwork) -> None:
    """A simulator in ``pose_batch`` mode publishes one PoseBatch per step (no Pose), the
    controller answers with one CommandBatch, and the simulator holds exactly those commands."""
    from confnav.services.simulator import SimulatorService

    ctl, _tr, cl = setup(mem_net)
    robots = [("r1", "cd", 0.2, 0.5), ("r2", "cd", -0.1, -0.6)]
    sim = SimulatorService(mem_net.bus("sim"), K, "s1", robots, pose_batch=True)
    batches: list[PoseBatch] = []
    singles: list[bytes] = []
    watch = mem_net.bus("watch")
    watch.subscribe(K.sim("s1", "poses"), lambda k, p: batches.append(decode(PoseBatch, p)))
    watch.subscribe(K.any_robot("pose"), lambda k, p: singles.append(p))
    sim._stop.set()  # no background loop: the test steps by hand
    sim.start()
    try:
        goals = {r: cl.goal(r) for r, *_ in robots}
        wait_for(lambda: ctl.counters["maps_installed"] and ctl.robot_state("r2") is not None)
        sim.step(0.0)  # poses seq 0 at the spawn points
        wait_for(lambda: sim.counters["commands"] == 2)
        assert ctl.counters["pose_batches"] == 1 and ctl.counters["commands"] >= 2
        with sim._lock:
            held = {r: sim._robots[r].u for r, *_ in robots}
        for rid, _ws, x, y in robots:
            assert same(held[rid], expected_u(goals[rid], complex(x, y)))
        sim.step(0.1)  # moves by u * dt
        for rid, _ws, x, y in robots:
            assert abs(sim.positions()[rid] - (complex(x, y) + 0.1 * held[rid])) < 1e-12
        wait_for(lambda: len(batches) == 2)
        assert batches[1].seq == [1, 1] and batches[1].robot_ids == ["r1", "r2"]
        assert not singles
    finally:
        sim.stop()
        ctl.stop()


def test_every_robot_of_a_batch_is_a_neighbour_of_a_shard(mem_net: InMemoryNetwork) -> None:
    """A shard answers its own robots, but the fleet filter sees every robot of the batch."""
    ctl, _tr, cl = setup(mem_net, robots={"a1"})
    sim = BatchClient(mem_net.bus("sim"))
    try:
        cl.goal("a1")
        wait_for(lambda: ctl.counters["maps_installed"] and ctl.robot_state("a1") is not None)
        assert ctl.neighbours is not None and not ctl.neighbours.fed
        sim.poses([("a1", 1, 0.1, 0.5), ("b7", 1, 0.2, -0.4)])
        assert wait_for(lambda: sim.answering(1)).robot_ids == ["a1"]
        nb = ctl.neighbours
        with nb._lock:
            seen = {rid: complex(nb._z[i]) for rid, i in nb._slot.items()}
        assert seen == {"a1": 0.1 + 0.5j, "b7": 0.2 - 0.4j}
    finally:
        ctl.stop()


def test_batches_are_recorded_with_their_schemas(mem_net: InMemoryNetwork, tmp_path: Any) -> None:
    from confnav.schemas import schema_bytes
    from confnav.services.recorder import Recorder
    from test_services_recorder import read_all

    path = tmp_path / "rec.mcap"
    rec = Recorder(mem_net.bus("rec"), K, path, health_period=0)
    rec.start()
    pub = mem_net.bus("pub")
    pb = PoseBatch(sim_id="s1", stamp_ns=10, robot_ids=["r1", "r2"], stamps_ns=[10, 10],
                   seq=[3, 3], x=[0.1, 0.2], y=[0.0, 0.5], theta=[0.0, 1.0])  # fmt: skip
    cb = CommandBatch(sim_id="s1", stamp_ns=11, robot_ids=["r2"], linear=[(0.1, 0.0)],
                      angular=[0.0], pose_seq=[3], pose_stamp_ns=[10], map_revision=["x"],
                      frame=["world"], chart=[None])  # fmt: skip
    try:
        pub.publish(K.sim("s1", "poses"), encode(pb))
        pub.publish(K.sim("s1", "cmd_vel"), encode(cb))
        wait_for(lambda: rec.recorded == 2)
    finally:
        rec.stop()
    counts, msgs, _meta = read_all(path)
    assert counts == {K.sim("s1", "poses"): 1, K.sim("s1", "cmd_vel"): 1}
    got = {ch.topic: (schema, m.data) for schema, ch, m in msgs}
    for key, msg in ((K.sim("s1", "poses"), pb), (K.sim("s1", "cmd_vel"), cb)):
        schema, data = got[key]
        assert schema.name == type(msg).TYPE and schema.data == schema_bytes(type(msg))
        assert decode(type(msg), data) == msg


def test_a_recording_of_pose_batches_replays_exactly(tmp_path: Any) -> None:
    """The services with the simulator in ``pose_batch`` mode, recorded: every entry of every
    recorded CommandBatch is recomputed by ``replay --check`` from its PoseBatch entry."""
    from conftest import identity_loader
    from test_replay_check import _make_golden

    from confnav.recording.reader import Recording
    from confnav.recording.replay_check import check_recording, parse_overrides

    path = tmp_path / "batch.mcap"
    _make_golden().run_pipeline(path, solver="fake", time_scale=4.0, pose_batch=True)
    with Recording(path) as rec:
        topics = {c.topic for c in rec.channels.values()}
    assert K.sim("sim", "poses") in topics and K.sim("sim", "cmd_vel") in topics
    assert not any(t.endswith("/pose") for t in topics)  # no single poses at all
    report = check_recording(path, load_map=identity_loader)
    assert report.ok, report.format()
    assert report.checked >= 50 and set(report.per_robot) == {"r1", "r2"}
    assert report.max_error <= 1e-12
    changed = check_recording(path, load_map=identity_loader,
                              overrides=parse_overrides(["gain=1.2"]))  # fmt: skip
    assert not changed.ok and changed.mismatch_count > 0


def test_inspect_and_the_scene_read_pose_batches(tmp_path: Any) -> None:
    """A recording with PoseBatch / CommandBatch instead of single poses and commands: ``confnav
    inspect`` counts every batch entry as that robot's pose or command (trajectory, path,
    arrival), and the Foxglove scene builder places each robot at its last batch entry."""
    from confnav.schemas import TransformSolution
    from test_replay_check import _make_golden

    from confnav.recording.inspect import inspect_recording
    from confnav.recording.reader import Recording, decode_message
    from confnav.recording.scene_builder import SceneBuilder

    path = tmp_path / "batch.mcap"
    _make_golden().run_pipeline(path, solver="fake", time_scale=4.0, pose_batch=True)
    entries: dict[str, list[tuple[float, float]]] = {}
    commands: dict[str, int] = {}
    builder = SceneBuilder(K.prefix)
    with Recording(path) as rec:
        for msg in rec.iter_messages():
            model = decode_message(msg)
            if isinstance(model, PoseBatch):
                for p in model.poses():
                    entries.setdefault(p.robot_id, []).append((p.x, p.y))
            elif isinstance(model, CommandBatch):
                for rid in model.robot_ids:
                    commands[rid] = commands.get(rid, 0) + 1
            if model is not None and not isinstance(model, TransformSolution):
                builder.observe(model, msg.log_time_ns)  # the fake solver's maps do not load
    assert set(entries) == {"r1", "r2"} and all(len(v) >= 20 for v in entries.values())

    report = inspect_recording(path)
    for rid, points in entries.items():
        r = report.robots[rid]
        assert r.poses == len(points) and r.trajectory == points
        assert r.start == points[0] and r.end == points[-1]
        assert r.commands == commands[rid] > 0
        assert r.path_length > 0.1
        robot = builder._robots[rid]
        assert robot.position == points[-1]
    assert report.closest is not None and set(report.closest["robots"]) == {"r1", "r2"}
