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
import shutil
import tempfile
import threading
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from confnav.schemas import (
    AtlasIndex,
    Goal,
    TransformSolution,
    VelocityCommand,
    decode,
    encode,
)
from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.launcher import LaunchConfig, Launcher, ServiceSpec
from conftest import RobotWatch, wait_for
from mcap.reader import make_reader

from confnav.atlas import plan
from confnav.atlas.scenes import corridor
from confnav.atlas.wire import ATLAS_MARKER, atlas_from_index, chart_ws_id
from confnav.conformal.cmap import ConformalMap
from confnav.recording.inspect import inspect_recording
from confnav.recording.replay_check import check_recording
from confnav.recording.scene import scene_topic
from confnav.recording.scene_writer import add_scene_channels

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCENE = corridor(12.0)
STARTS = {"a1": (0.5, 0.5), "a2": (1.2, 0.3)}


@pytest.mark.timeout(400)
def test_corridor_atlas_through_the_services(tmp_path: Path) -> None:
    ws_file = tmp_path / "corr.json"
    SCENE.workspace.save(ws_file)
    sockdir = tempfile.mkdtemp(prefix="cna", dir="/tmp")
    sock = f"unixsock-stream/{sockdir}/router.sock"
    sim_args = ["--workspace", f"corr={ws_file}", "--time-scale", "2"]
    for rid, (x, y) in STARTS.items():
        sim_args += ["--robot", f"{rid}=corr:{x},{y}"]
    mcap_path = tmp_path / "atlas.mcap"
    cfg = LaunchConfig(
        listen=[sock],
        services=[
            ServiceSpec("recorder", ["--out", str(mcap_path)]),
            ServiceSpec("transform", ["--workspace", f"corr={ws_file}"]),
            ServiceSpec("controller", []),
            ServiceSpec("simulator", sim_args),
        ],
        startup_timeout=60,
        log_dir=str(tmp_path / "logs"),
    )
    launcher = Launcher(cfg, verbose=1)
    stop = threading.Event()
    monitor = threading.Thread(target=launcher.monitor, args=(stop,), daemon=True)
    bus = None
    watch = RobotWatch()
    lock, status, collisions = watch.lock, watch.status, watch.collisions
    try:
        launcher.start()
        monitor.start()
        bus = ZenohBus(zenoh_config("client", connect=[sock]))
        k = launcher.keys
        watch.attach(bus, k)

        # the atlas is served: index, every chart, and the workspace's own transform says so
        replies = wait_for(
            lambda: [r for r in bus.query(k.ws("corr", "atlas")) if r.ok],  # type: ignore[union-attr]
            timeout=180,
            interval=0.5,
        )
        index = decode(AtlasIndex, replies[0].payload)
        assert index.ws_id == "corr" and len(index.cells) >= 4
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
        bus.close()
        bus = None
        codes = launcher.shutdown()
        assert codes.get("recorder") == 0, codes
    finally:
        stop.set()
        if bus is not None:
            bus.close()
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)

    # the recording: the index, the charts, and each robot's active chart per command
    seen: dict[str, list[int]] = defaultdict(list)
    n_index = 0
    chart_topics: set[str] = set()
    with open(mcap_path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == k.ws("corr", "atlas"):
                rec = decode(AtlasIndex, message.data)
                assert rec.revision == index.revision
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
