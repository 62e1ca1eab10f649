"""Multi-process integration over real Zenoh (unix socket, multicast off): the services run
as separate processes under the launcher; a workspace update re-solves and the controller
hot-swaps; killing the transform service mid-run loses no robot; bad inputs never crash a
service; the MCAP holds exactly the messages published and every payload validates."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from confnav.schemas import (
    CollisionEvent,
    Goal,
    Pose,
    RobotStatus,
    ServiceHealth,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.bus import ZenohBus
from confnav.services.launcher import Launcher, ServiceSpec
from confnav.services.transform import definition_of
from conftest import confnav_cmd, launched_system, subprocess_env, wait_for
from mcap.reader import make_reader

from confnav.geometry import Workspace
from confnav.recording import layout as L

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROOM = Workspace(
    [(-1, -1), (1, -1), (1, 1), (-1, 1)],
    [[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2), (0.2, 0.2)]],
    anchor=0j,
)
STARTS = {"r1": (0.8, -0.6), "r2": (0.8, 0.7), "r3": (-0.8, -0.8)}
GOALS = {"r1": (-0.6, 0.0), "r2": (-0.5, 0.6), "r3": (0.8, 0.0)}


@dataclass
class Observed:
    lock: threading.Lock = field(default_factory=threading.Lock)
    status: dict[str, list[RobotStatus]] = field(default_factory=lambda: defaultdict(list))
    cmds: dict[str, list[VelocityCommand]] = field(default_factory=lambda: defaultdict(list))
    collisions: list[CollisionEvent] = field(default_factory=list)
    transforms: list[TransformSolution] = field(default_factory=list)
    health: dict[str, float] = field(default_factory=dict)  # service -> last receive time

    def last(self, rid: str) -> RobotStatus | None:
        with self.lock:
            s = self.status.get(rid)
            return s[-1] if s else None


@dataclass
class System:
    launcher: Launcher
    bus: ZenohBus
    obs: Observed
    out: Path
    sent: Counter[str] = field(default_factory=Counter)
    stopped: bool = False

    def goal(self, rid: str, ws: str) -> None:
        g = Goal(robot_id=rid, ws_id=ws, goal=GOALS[rid], gain=100.0, v_max=0.5, tolerance=0.02)
        self.bus.publish(self.launcher.keys.robot(rid, "goal"), encode(g))

    def stop(self) -> dict[str, int | None]:
        if self.stopped:
            return {}
        self.stopped = True
        self.bus.close()
        return self.launcher.shutdown()


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:

    out = tmp_path_factory.mktemp("system")
    room = out / "room.json"
    ROOM.save(room)
    sim_args = ["--workspace", f"room={room}", "--time-scale", "2"]
    for rid, (x, y) in STARTS.items():
        sim_args += ["--robot", f"{rid}=room:{x},{y}"]
    services = [
        ServiceSpec("recorder", ["--out", str(out / "system.mcap")]),
        ServiceSpec(
            "transform",
            ["--workspace", f"room={room}", "--cache-dir", str(out / "cache"), "--no-progressive"],
        ),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", sim_args),
    ]
    with launched_system(services, out, prefix="cni") as launched:
        bus, k = launched.bus, launched.keys
        obs = Observed()

        def on(kind: str) -> Any:
            def handler(key: str, payload: bytes) -> None:
                with obs.lock:
                    if kind == "status":
                        s = decode(RobotStatus, payload)
                        obs.status[s.robot_id].append(s)
                    elif kind == "cmd_vel":
                        c = decode(VelocityCommand, payload)
                        obs.cmds[c.robot_id].append(c)
                    elif kind == "collision":
                        obs.collisions.append(decode(CollisionEvent, payload))
                    elif kind == "transform":
                        obs.transforms.append(decode(TransformSolution, payload))
                    elif kind == "health":
                        obs.health[decode(ServiceHealth, payload).service] = time.monotonic()

            return handler

        for kind in ("status", "cmd_vel", "collision"):
            bus.subscribe(k.any_robot(kind), on(kind))
        bus.subscribe(k.any_ws("transform"), on("transform"))
        bus.subscribe(f"{k.prefix}/health/**", on("health"))
        # the map of the file workspace is served
        wait_for(
            lambda: any(r.ok for r in bus.query(k.ws("room", "transform"))),
            timeout=90,
            interval=0.5,
        )
        system = System(launched.launcher, bus, obs, out)
        yield system
        system.stop()


def arrived(obs: Observed, rid: str) -> bool:
    s = obs.last(rid)
    return s is not None and s.state == "arrived"


@pytest.mark.timeout(150)
def test_workspace_update_resolves_and_controller_hot_swaps(system: System) -> None:
    k, obs, bus = system.launcher.keys, system.obs, system.bus
    defn = definition_of("room2", ROOM)
    bus.publish(k.ws("room2", "definition"), encode(defn))
    wait_for(lambda: any(t.ws_id == "room2" for t in obs.transforms), timeout=60, interval=0.1)
    rev1 = next(t.revision for t in obs.transforms if t.ws_id == "room2")
    system.goal("r1", "room2")
    wait_for(  # driving on rev1 (not holding for its map: navigating with no revision)
        lambda: (
            (s := obs.last("r1")) is not None and s.state == "navigating" and s.map_revision == rev1
        ),
        timeout=20,
    )
    # move the obstacle away from the robot's path: re-solved, hot-swapped while moving
    moved = WorkspaceDefinition(
        ws_id="room2",
        outer=defn.outer,
        obstacles=[[(-0.1, 0.5), (0.1, 0.5), (0.1, 0.8), (-0.1, 0.8)]],
        anchor=(0.0, 0.0),
    )
    bus.publish(k.ws("room2", "definition"), encode(moved))
    t_update = time.monotonic()
    wait_for(
        lambda: any(c.map_revision not in (None, rev1) for c in obs.cmds["r1"]),
        timeout=60,
        interval=0.05,
    )
    swap_latency = time.monotonic() - t_update
    rev2 = [t.revision for t in obs.transforms if t.ws_id == "room2"][-1]
    assert rev2 != rev1
    wait_for(lambda: arrived(obs, "r1"), timeout=60, interval=0.1)
    with obs.lock:
        revs = [c.map_revision for c in obs.cmds["r1"] if c.pose_seq >= 0 and c.map_revision]
        states = [(s.state, s.reason, s.map_revision) for s in obs.status["r1"]]
    # commands went rev1 -> rev2 once; the robot drove on the old map only while it was more
    # than the margin away from the new geometry: stopped (map_outdated) otherwise, on rev1
    assert revs[0] == rev1 and revs[-1] == rev2
    assert revs == [rev1] * revs.index(rev2) + [rev2] * (len(revs) - revs.index(rev2))
    first_nav = [s[:2] for s in states].index(("navigating", "ok"))
    allowed = {("navigating", "ok"), ("arrived", "arrived"), ("stopped", "map_outdated")}
    assert all(s[:2] in allowed for s in states[first_nav:]), states
    assert all(s[2] == rev1 for s in states if s[1] == "map_outdated")
    assert not [c for c in obs.collisions if c.robot_id == "r1"]
    print(f"solve-to-first-command after update: {swap_latency:.2f} s")


@pytest.mark.timeout(150)
def test_killing_the_transform_service_loses_no_robot(system: System) -> None:
    obs, launcher = system.obs, system.launcher
    for rid in ("r2", "r3"):
        system.goal(rid, "room")
    wait_for(
        lambda: all(
            obs.last(r) is not None and obs.last(r).state == "navigating" for r in ("r2", "r3")
        ),
        timeout=30,
    )
    proc = launcher.procs["transform"].popen
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    # robots stop and say why ...
    wait_for(
        lambda: all(
            any(s.reason == "transform_service_dead" for s in obs.status[r]) for r in ("r2", "r3")
        ),
        timeout=20,
    )
    # ... the launcher restarts the service, and every robot still arrives
    wait_for(lambda: launcher.procs["transform"].popen.pid != proc.pid, timeout=30)
    wait_for(lambda: arrived(obs, "r2") and arrived(obs, "r3"), timeout=90, interval=0.2)
    assert launcher.restarts >= 1
    assert not obs.collisions


@pytest.mark.timeout(120)
def test_bad_inputs_never_crash_a_service(system: System) -> None:
    k, bus, obs, launcher = system.launcher.keys, system.bus, system.obs, system.launcher
    pids = {name: p.popen.pid for name, p in launcher.procs.items()}
    nan_pose = (
        b'{"type":"confnav.Pose","schema_version":1,"robot_id":"r1","stamp_ns":1,"x":NaN,"y":0}'
    )
    garbage = [
        b"",
        b"{not json",
        b"\x00\xff" * 50,
        b"[1,2,3]",
        b'{"schema_version":99}',
        nan_pose,
        b"x" * (5 * 1024 * 1024),  # oversized
    ]
    keys = [
        k.ws("room", "definition"),
        k.ws("nowhere", "definition"),
        k.robot("r1", "goal"),
        k.robot("r1", "pose"),
        k.robot("r1", "cmd_vel"),
        k.sim("sim", "spawn"),
        k.sim("sim", "control"),
        k.ws("room", "transform"),
    ]
    for key in keys:
        for payload in garbage:
            bus.publish(key, payload)
    # a goal on an unknown workspace and a query for it: clear errors, no crash
    bus.publish(
        k.robot("ghost", "goal"), encode(Goal(robot_id="ghost", ws_id="nowhere", goal=(0, 0)))
    )
    [err] = bus.query(k.ws("nowhere", "transform"))
    assert not err.ok and "unknown workspace 'nowhere'" in (err.error or "")
    bad_ws = WorkspaceDefinition(ws_id="bow", outer=[(0, 0), (1, 1), (1, 0), (0, 1)])
    bus.publish(k.ws("bow", "definition"), encode(bad_ws))
    wait_for(
        lambda: any(
            not r.ok and "invalid" in (r.error or "") for r in bus.query(k.ws("bow", "transform"))
        ),
        timeout=10,
    )
    # NaN pose for a robot with a goal: zero velocity and the reason (a robot the simulator
    # does not drive, so that no newer good pose supersedes the NaN one)
    g = Goal(robot_id="r9", ws_id="room", goal=(0.0, 0.5))
    bus.publish(k.robot("r9", "goal"), encode(g))
    wait_for(lambda: obs.last("r9") is not None, timeout=10)  # stale_pose: the goal is in
    bus.publish(k.robot("r9", "pose"), nan_pose.replace(b'"r1"', b'"r9"'))
    wait_for(lambda: any(s.reason == "nan_input" for s in obs.status["r9"]), timeout=10)
    # cmd_vel and status arrive on two subscriber threads: the stop may trail its status
    wait_for(lambda: obs.cmds["r9"] and obs.cmds["r9"][-1].linear == (0.0, 0.0), timeout=10)
    # every service process is still the same process and still healthy afterwards
    t = time.monotonic()
    wait_for(
        lambda: all(
            obs.health.get(s, 0) > t for s in ("transform", "controller", "simulator", "recorder")
        ),
        timeout=10,
    )
    for name, p in launcher.procs.items():
        assert p.popen.poll() is None, f"{name} died"
        if name != "transform":  # restarted on purpose by the previous test
            assert p.popen.pid == pids[name]
    assert any(r.ok for r in bus.query(k.ws("room", "transform")))


@pytest.mark.timeout(120)
def test_mcap_holds_exactly_the_messages_published(system: System) -> None:
    k, bus = system.launcher.keys, system.bus
    # a commanded robot of its own (the module's other tests may run on another xdist worker)
    system.goal("r1", "room")
    wait_for(lambda: system.obs.cmds["r1"], timeout=60)
    sent: Counter[str] = Counter()
    for i in range(400):
        for rid in ("ghost1", "ghost2", "ghost3"):
            key = k.robot(rid, "pose")
            bus.publish(key, encode(Pose(robot_id=rid, stamp_ns=time.time_ns(), seq=i, x=0, y=0)))
            sent[key] += 1
    time.sleep(0.5)
    codes = system.stop()  # SIGTERM: the recorder drains and finishes the file
    assert codes.get("recorder") == 0, codes
    path = system.out / "system.mcap"
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        counts: Counter[str] = Counter()
        for cid, n in summary.statistics.channel_message_counts.items():
            ch = summary.channels[cid]
            if ch.message_encoding == L.MESSAGE_ENCODING:
                counts[ch.topic] += n
        validators: dict[int, Any] = {}
        n_checked = 0
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding != L.MESSAGE_ENCODING:
                assert channel.schema_id == 0
                continue
            v = validators.setdefault(
                schema.id, jsonschema.Draft202012Validator(json.loads(schema.data))
            )
            payload = json.loads(message.data)
            v.validate(payload)
            assert payload["type"] == schema.name
            n_checked += 1
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    for key, n in sent.items():
        assert counts[key] == n, key
    assert counts[k.ws("room", "definition")] >= 1  # definitions are recorded as messages
    assert counts[k.robot("r1", "cmd_vel")] > 0 and counts[k.robot("r2", "pose")] > 0
    assert n_checked == sum(counts.values())
    assert L.METADATA_NAME in meta


@pytest.mark.timeout(240)
def test_demo_all_robots_arrive(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.run(
        confnav_cmd("demo", "--out", str(out), "--time-scale", "2", "--timeout", "90"),
        env=subprocess_env(),
        capture_output=True,
        text=True,
        timeout=220,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "all robots arrived without collision" in proc.stdout
    assert (out / "demo.png").stat().st_size > 10_000
    with open(out / "demo.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = Counter()
    for cid, n in summary.statistics.channel_message_counts.items():
        topics[summary.channels[cid].topic] += n
    for rid in ("r1", "r2", "r3", "r4"):
        assert topics[f"confnav/robot/{rid}/goal"] == 1
        assert topics[f"confnav/robot/{rid}/cmd_vel"] > 50
    assert topics["confnav/ws/default/transform"] >= 1  # progressive maps: a revision ladder
