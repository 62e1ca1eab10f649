"""An atlas end to end through the real services (issue 15 items 3 and 5): a 12 x 1 m corridor
(L/w = 12, beyond one map) given to the transform service as a file is solved as an atlas;
its index and every chart are queryable under keys of their own; the controller drives two
robots (separate processes, real Zenoh over a unix socket, multicast off) down the corridor
switching charts; both arrive without a collision; the MCAP recording holds the index, the
charts and the active chart of every command, and the recorded switches follow the plan's
strictly decreasing rank (no chattering)."""

from __future__ import annotations

import itertools
import json
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from confnav.schemas import (
    AtlasIndex,
    Goal,
    ServiceHealth,
    TransformSolution,
    TransformStatus,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.launcher import ServiceSpec
from conftest import RobotWatch, confnav_cmd, launched_system, subprocess_env, wait_for
from mcap.reader import make_reader

from confnav.atlas import plan
from confnav.atlas.scenes import corridor
from confnav.atlas.wire import ATLAS_MARKER, atlas_from_index, chart_ws_id
from confnav.conformal.cmap import ConformalMap
from confnav.geometry import Workspace
from confnav.recording.inspect import inspect_recording
from confnav.recording.replay_check import check_recording
from confnav.recording.scene import scene_topic
from confnav.recording.scene_writer import add_scene_channels

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCENE = corridor(12.0)
STARTS = {"a1": (0.5, 0.5), "a2": (1.2, 0.3)}


def corridor_files(
    tmp_path: Path, starts: dict[str, tuple[float, float]]
) -> tuple[Path, list[str]]:
    """The 12 m corridor saved as workspace ``corr``, and the simulator's arguments for robots
    at ``starts`` in it (time scale 2)."""
    ws_file = tmp_path / "corr.json"
    SCENE.workspace.save(ws_file)
    sim_args = ["--workspace", f"corr={ws_file}", "--time-scale", "2"]
    for rid, (x, y) in starts.items():
        sim_args += ["--robot", f"{rid}=corr:{x},{y}"]
    return ws_file, sim_args


@pytest.mark.timeout(400)
def test_corridor_atlas_through_the_services(tmp_path: Path) -> None:
    ws_file, sim_args = corridor_files(tmp_path, STARTS)
    mcap_path = tmp_path / "atlas.mcap"
    services = [
        ServiceSpec("recorder", ["--out", str(mcap_path)]),
        ServiceSpec("transform", ["--workspace", f"corr={ws_file}"]),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", sim_args),
    ]
    watch = RobotWatch()
    lock, status, collisions = watch.lock, watch.status, watch.collisions
    with launched_system(services, tmp_path, prefix="cna") as system:
        bus, k = system.bus, system.keys
        watch.attach(bus, k)

        # the atlas is served: index, every chart, and the workspace's own transform says so.
        # The progressive atlas (the default) publishes partial revisions (cells pending) and
        # the complete coarse atlas (tol 1e-3) first: the final one is complete at the file's
        # tol (a status subscription made now could miss the "solved" of a file loaded at start)
        def final_index() -> list[object]:
            reps = [r for r in bus.query(k.ws("corr", "atlas")) if r.ok]
            found = [decode(AtlasIndex, r.payload) for r in reps]
            return [
                r
                for r, i in zip(reps, found, strict=True)
                if i.tol < 1e-3 and not any(c.pending for c in i.cells)
            ]

        replies = wait_for(final_index, timeout=180, interval=0.5)
        index = decode(AtlasIndex, replies[0].payload)
        assert index.ws_id == "corr" and len(index.cells) >= 4
        assert not any(c.pending for c in index.cells)
        charts = []
        for cell in index.cells:
            assert cell.chart_ws_id == chart_ws_id("corr", cell.index)
            (rep,) = bus.query(k.ws(cell.chart_ws_id, "transform"))
            assert rep.ok and rep.payload is not None
            sol = decode(TransformSolution, rep.payload)
            assert sol.revision == cell.chart_revision and sol.ws_id == cell.chart_ws_id
            charts.append(ConformalMap.from_dict(sol.coefficients))
        (rep,) = bus.query(k.ws("corr", "transform"))
        assert not rep.ok and (rep.error or "").startswith(ATLAS_MARKER)
        # the published charts are the cells' maps: the cell's outer edges land on |w| = 1
        for cell, m in zip(index.cells, charts, strict=True):
            v = np.array([complex(*p) for p in cell.outer])
            mid = (v + np.roll(v, -1)) / 2
            mid += 1e-9 * (m.workspace.anchor - mid)
            assert np.allclose(np.abs(m.T(mid)), 1.0, atol=1e-6)
        atlas = atlas_from_index(index, charts)
        goal = (SCENE.goal.real, SCENE.goal.imag)
        rank = plan(atlas, SCENE.goal).rank

        for rid in STARTS:
            g = Goal(robot_id=rid, ws_id="corr", goal=goal, v_max=1.0, tolerance=0.05)
            bus.publish(k.robot(rid, "goal"), encode(g))

        def done() -> bool:
            with lock:
                return all(status[r] and status[r][-1].state == "arrived" for r in STARTS)

        wait_for(done, timeout=150, interval=0.2)
        with lock:
            assert collisions == []
        codes = system.shutdown()
        assert codes.get("recorder") == 0, codes

    # the recording: the index, the charts, and each robot's active chart per command
    seen: dict[str, list[int]] = defaultdict(list)
    n_index = 0
    recorded_revisions: list[str] = []
    chart_topics: set[str] = set()
    with open(mcap_path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == k.ws("corr", "atlas"):
                rec = decode(AtlasIndex, message.data)
                recorded_revisions.append(rec.revision)
                n_index += 1
            elif channel.topic.endswith("/transform") and "~c" in channel.topic:
                chart_topics.add(channel.topic)
            elif channel.topic.endswith("/cmd_vel"):
                cmd = decode(VelocityCommand, message.data)
                if cmd.pose_seq >= 0 and cmd.chart is not None:
                    seq = seen[cmd.robot_id]
                    if not seq or seq[-1] != cmd.chart:
                        seq.append(cmd.chart)
    assert n_index >= 1
    # every published revision is recorded (partial ones first), the final one last
    assert recorded_revisions[-1] == index.revision
    # replay --check recomputes every command, switching included, from the recording alone
    report = check_recording(mcap_path)
    assert report.ok and report.checked > 50, report.format()
    assert set(report.per_robot) >= set(STARTS)
    # inspect: the atlas and each robot's charts; the Foxglove scene: cells and active chart
    summary = inspect_recording(mcap_path)
    assert summary.atlases["corr"].revision == index.revision
    assert "solved as an atlas of" in summary.format()
    for rid in STARTS:
        assert summary.robots[rid].charts == seen[rid] and summary.robots[rid].arrived
        assert summary.robots[rid].atlas == "corr"
        assert summary.robots[rid].chart == seen[rid][-1]
    assert summary.cells_used("corr") == sorted({c for rid in STARTS for c in seen[rid]})
    assert f"atlas corr: {len(index.cells)} cells, used by {', '.join(sorted(STARTS))}" in (
        summary.format()
    )
    viz = mcap_path.with_name("atlas_viz.mcap")
    add_scene_channels(mcap_path, viz)
    entities: dict[str, dict[str, object]] = {}
    with open(viz, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == scene_topic("corr"):
                for e in json.loads(message.data)["entities"]:
                    entities[e["id"]] = e
    assert len(entities["atlas/cells"]["lines"]) == len(index.cells)  # type: ignore[arg-type]
    for rid in STARTS:  # the last active chart shown is the robot's last chart
        assert entities[f"chart/{rid}"]["metadata"] == [  # type: ignore[comparison-overlap]
            {"key": "robot", "value": rid},
            {"key": "chart", "value": str(seen[rid][-1])},
        ]
    assert chart_topics == {k.ws(c.chart_ws_id, "transform") for c in index.cells}
    for rid in STARTS:
        charts_used = seen[rid]
        assert len(charts_used) >= 3, charts_used  # it switched charts down the corridor
        # no chattering: every switch goes to a cell of strictly lower rank
        assert all(rank[b] < rank[a] for a, b in itertools.pairwise(charts_used)), charts_used
        assert rank[charts_used[-1]] == min(rank[c] for c in charts_used)


def _pillar_corridor(length: float) -> Workspace:
    """A 1.2 m wide corridor with a 0.2 m pillar every 1.5 m (too elongated for one map):
    14 to 20 charts of 0.2 to 0.5 s each."""
    n = int((length - 0.5) // 1.5)
    pillars = [
        [(x - 0.1, 0.5), (x + 0.1, 0.5), (x + 0.1, 0.7), (x - 0.1, 0.7)]
        for x in [1.0 + 1.5 * i for i in range(n)]
    ]
    return Workspace([(0, 0), (length, 0), (length, 1.2), (0, 1.2)], pillars)


class _Claims:
    """Every claim token ``{prefix}/claim/{atlas}/{job}/{zid}`` seen on the bus: per zid the
    jobs claimed, released and the most held at once."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.held: dict[str, set[str]] = defaultdict(set)
        self.claimed: dict[str, set[str]] = defaultdict(set)
        self.released: dict[str, int] = defaultdict(int)
        self.most: dict[str, int] = defaultdict(int)

    def __call__(self, key: str, alive: bool) -> None:
        *_, job, zid = key.split("/")
        with self.lock:
            if alive:
                self.held[zid].add(job)
                self.claimed[zid].add(job)
                self.most[zid] = max(self.most[zid], len(self.held[zid]))
            elif job in self.held[zid]:
                self.held[zid].discard(job)
                self.released[zid] += 1


def _zid_of(log_file: Path) -> str:
    """The zid a service process logged at start (``... service started (zid Z)``)."""
    text = wait_for(lambda: "service started (zid" in log_file.read_text() and log_file.read_text())
    return str(text.split("service started (zid ", 1)[1].split(")", 1)[0])


@pytest.mark.timeout(120)
def test_two_transform_instances_share_an_atlas(tmp_path: Path) -> None:
    """Issue 15 item 1: two transform service processes (two workers each) on one router
    split one atlas's charts (each solves some, at most two at once, every job exactly under
    one claim) and both answer the atlas of one instance solving alone (same revision, so the
    same charts); then, with one killed while it holds claims, the other solves its charts
    too and completes the next atlas, again identical to a lone solve."""
    from confnav.services.transform import definition_of

    from confnav.atlas.charts import solve_atlas
    from confnav.atlas.wire import atlas_revision

    ws_a, ws_b = _pillar_corridor(12.0), _pillar_corridor(10.5)
    tol = 1e-10
    specs = [
        # one atlas per definition (no progressive revisions), so that the claims counted
        # are those of one lone solve_atlas at tol
        ServiceSpec(
            "transform", ["--workers", "2", "--no-progressive-atlas"], instance=t, restart=False
        )
        for t in ("t1", "t2")
    ]
    claims = _Claims()
    health: dict[str, ServiceHealth] = {}

    def on_health(key: str, payload: bytes) -> None:
        h = decode(ServiceHealth, payload)
        health[h.zid] = h

    solved: list[TransformStatus] = []  # every instance says "solved" with its revision

    def on_status(key: str, payload: bytes) -> None:
        st = decode(TransformStatus, payload)
        if st.state == "solved":
            solved.append(st)

    def answers(ws_id: str, n: int) -> list[AtlasIndex]:
        """The atlas answered (a query reaches one instance) once ``n`` instances solved it."""
        if sum(s.ws_id == ws_id for s in solved) < n:
            return []
        reps = [r for r in sys_.bus.query(sys_.keys.ws(ws_id, "atlas")) if r.ok]
        return [decode(AtlasIndex, r.payload) for r in reps]

    with launched_system(specs, tmp_path, prefix="cns") as sys_:
        zids = {t: _zid_of(tmp_path / "logs" / f"{t}.log") for t in ("t1", "t2")}
        sys_.bus.subscribe_liveliness(f"{sys_.keys.prefix}/claim/*/*/*", claims)
        sys_.bus.subscribe(f"{sys_.keys.prefix}/health/transform/*", on_health)
        sys_.bus.subscribe(sys_.keys.any_ws("status"), on_status)

        def warmed() -> bool:  # both instances' workers started (two pools of two each):
            # in a full run one instance's workers were still starting while the other
            # claimed most jobs (a 16 / 4 split)
            return all(
                z in health and health[z].counters.get("workers_warmed", 0) >= 4
                for z in zids.values()
            )

        wait_for(warmed, timeout=60, interval=0.1)
        sys_.bus.publish(sys_.keys.ws("pa", "definition"), encode(definition_of("pa", ws_a, tol)))
        ref_a = solve_atlas(ws_a, tol, workers=1)  # one instance alone (meanwhile)
        (index_a,) = wait_for(lambda: answers("pa", 2), timeout=60, interval=0.2)
        rev_a = atlas_revision([m.revision for m in ref_a.charts])
        assert [s.revision for s in solved if s.ws_id == "pa"] == [rev_a, rev_a]
        assert index_a.revision == rev_a and len(index_a.cells) == len(ref_a.charts)
        jobs_a = len(ref_a.records)  # cell solves, failed rounds included
        with claims.lock:
            assert sorted(claims.claimed) == sorted(zids.values())
            every = set().union(*claims.claimed.values())
            assert len(every) == jobs_a  # every job was claimed, nothing else
            assert all(claims.most[z] == 2 for z in zids.values()), dict(claims.most)
            both = claims.claimed[zids["t1"]] & claims.claimed[zids["t2"]]
            assert len(both) <= 2, both  # only a simultaneous first claim is solved twice

        def per_instance() -> list[int] | None:
            if not all(z in health for z in zids.values()):
                return None
            n = [health[z].counters.get("charts_solved", 0) for z in zids.values()]
            return n if sum(n) >= jobs_a else None

        n_solved = wait_for(per_instance, timeout=10, interval=0.2)
        assert min(n_solved) >= jobs_a // 4, n_solved  # split, not one instance doing it all
        print(f"{jobs_a} chart jobs; solved per instance {n_solved}; both claimed {len(both)}")

        # kill t1 while it holds claims on the next atlas: t2 solves them and completes it
        before = {z: set(c) for z, c in claims.claimed.items()}
        sys_.bus.publish(sys_.keys.ws("pb", "definition"), encode(definition_of("pb", ws_b, tol)))

        def t1_busy() -> set[str] | None:
            with claims.lock:
                new = claims.claimed[zids["t1"]] - before[zids["t1"]]
                held = set(claims.held[zids["t1"]]) & new
                return held if new - held and held else None  # solved one, holds others

        victims = wait_for(t1_busy, timeout=30, interval=0.005)
        sys_.launcher.procs["t1"].popen.kill()
        ref_b = solve_atlas(ws_b, tol, workers=1)
        (index_b,) = wait_for(lambda: answers("pb", 1), timeout=60, interval=0.2)
        assert index_b.revision == atlas_revision([m.revision for m in ref_b.charts])
        with claims.lock:
            assert victims <= claims.claimed[zids["t2"]]  # t2 took over the killed claims


@pytest.mark.timeout(200)
def test_replayed_atlas_recording_drives_a_fresh_controller(tmp_path: Path) -> None:
    """Issue 15: an atlas run is recorded (transform, controller, simulator, recorder
    processes), then ``confnav replay --live --inputs-only`` (a process) re-publishes it to a
    fresh controller process with no transform service on the bus: the replay answers the
    controller's transform, atlas and chart queries from the recording, and the controller
    answers the replayed poses with the recorded commands (same pose: same command)."""
    ws_file = tmp_path / "corr.json"
    SCENE.workspace.save(ws_file)
    mcap_path = tmp_path / "run.mcap"
    x, y = STARTS["a1"]
    sim = ["--workspace", f"corr={ws_file}", "--time-scale", "2", "--robot", f"a1=corr:{x},{y}"]
    record = [
        ServiceSpec("recorder", ["--out", str(mcap_path)]),
        ServiceSpec("transform", ["--workspace", f"corr={ws_file}"]),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", sim),
    ]
    goal = Goal(robot_id="a1", ws_id="corr", goal=(SCENE.goal.real, SCENE.goal.imag), v_max=1.0)
    with launched_system(record, tmp_path / "rec", prefix="cnr") as run:
        watch = RobotWatch()
        watch.attach(run.bus, run.keys)
        busy: list[bool] = []  # per transform health: something solving or refining

        def on_health(_key: str, payload: bytes) -> None:
            d = json.loads(decode(ServiceHealth, payload).detail)
            busy.append(bool(d.get("solving") or d.get("refining")))

        run.bus.subscribe(f"{run.keys.prefix}/health/transform/*", on_health)
        # the final atlas before the goal: a progressive atlas's partial revisions, installed
        # while the robot drives, reach the replaying controller at other poses than they
        # reached the recorded one (the replay republishes them at their recorded times),
        # so the same pose could meet another revision; this test is about the replay
        wait_for(lambda: busy and not busy[-1], timeout=120, interval=0.5)
        wait_for(
            lambda: [r for r in run.bus.query(run.keys.ws("corr", "atlas")) if r.ok],
            timeout=120,
            interval=0.5,
        )
        run.bus.publish(run.keys.robot("a1", "goal"), encode(goal))

        def arrived() -> bool:
            with watch.lock:
                return bool(watch.status["a1"]) and watch.status["a1"][-1].state == "arrived"

        wait_for(arrived, timeout=120, interval=0.2)
        assert run.shutdown().get("recorder") == 0
    recorded: dict[int, VelocityCommand] = {}
    with open(mcap_path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic.endswith("/cmd_vel"):
                cmd = decode(VelocityCommand, message.data)
                if cmd.pose_seq >= 0 and cmd.chart is not None:
                    recorded[cmd.pose_seq] = cmd
    assert len({c.chart for c in recorded.values()}) >= 3  # the run switched charts

    live: dict[int, VelocityCommand] = {}
    lock = threading.Lock()

    def on_cmd(key: str, payload: bytes) -> None:
        c = decode(VelocityCommand, payload)
        with lock:
            live[c.pose_seq] = c

    with launched_system([ServiceSpec("controller", [])], tmp_path / "rp", prefix="cnp") as rp:
        rp.bus.subscribe(rp.keys.any_robot("cmd_vel"), on_cmd)
        zenoh_args = ["--mode", "client", "--connect", rp.launcher.config.connect[0]]
        res = subprocess.run(
            [*confnav_cmd("replay", str(mcap_path), "--live", "--inputs-only"), *zenoh_args],
            capture_output=True,
            text=True,
            timeout=120,
            env=subprocess_env(),
        )
        assert res.returncode == 0, res.stdout + res.stderr
        assert "/ws/corr/atlas" in res.stdout  # the index went out too
        time.sleep(0.5)  # the last commands
        with lock:
            answered = {s: c for s, c in live.items() if s >= 0 and c.chart is not None}
    common = set(answered) & set(recorded)
    print(f"replayed atlas: {len(common)} of {len(recorded)} recorded commands recomputed live")
    # poses superseded in either run (a newer pose waiting) have no command there
    assert len(common) >= 0.5 * len(recorded), (len(common), len(recorded), len(answered))
    for seq in sorted(common):
        a, b = answered[seq], recorded[seq]
        assert a.chart == b.chart and a.map_revision == b.map_revision, seq
        assert abs(complex(*a.linear) - complex(*b.linear)) <= 1e-9, seq
