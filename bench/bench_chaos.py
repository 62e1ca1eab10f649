"""Chaos, fuzz and soak of the distributed system (issue 10), real processes over Zenoh.

``fuzz``: a router and the four services (``confnav launch`` machinery; the simulator without
robots so that the fuzzed kinds carry no other traffic); ``--n`` malformed messages (default
10,000) on every key a service subscribes to (random bytes, truncated JSON, wrong types, huge
payloads, NaN, wildcard / verbatim / odd ids), and ``--queries`` bad queries on the transform
queryable. Targets: no process dies or restarts; each service's health counters account for
every message that reached it (a ``*_received`` counter per subscription, or the recording's
per-topic count for the recorder); every query gets an answer.

``kill``: the four services and the router with four robots on the default workspace; for each
of router, transform, controller, simulator and recorder, ``--repeats`` times (default 5): the
robots are sent back to their starts (``SimControl reset``), and once they move the victim is
killed with SIGKILL (the launcher restarts it). Targets: 0 collisions; every robot arrives after
every kill; every recording file is complete (has its footer) or ``confnav recover`` restores
it; robots stop within one watchdog period of losing the controller, measured from the kill to
the stamp of the last pose that moved. The budget, by design: the simulator applies a command
at most ``max_cmd_age`` sim seconds after the pose it answers (published before the kill), and
at most ``cmd_timeout`` wall seconds after it arrived, so the robot stops within
``min(cmd_timeout, max_cmd_age / time_scale)`` plus one simulation step.

``soak``: ``--robots`` robots (default 100) driving to the goal and sent back when they
arrive, for ``--minutes``; the resident memory (VmRSS) of every process is sampled every 10 s,
with the recorder's message count and queue depth (its health: a growing queue means it falls
behind); target: growth <= 10 % from the end of the first minute (warm-up) to the end.
``--soak-split-duration S`` passes ``--split-duration S`` to the recorder (rotation: a short
S checks that the recorder's memory stops growing with the file length).

Writes ``bench/results/chaos.json`` (commit, date, load) and prints a table. The shared 2-core
machine is loaded: timings are not idle figures.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from confnav.schemas import (
    CollisionEvent,
    DecodeError,
    Goal,
    GoalCancel,
    Pose,
    RobotStatus,
    ServiceHealth,
    SimControl,
    SpawnRequest,
    TransformSolution,
    VelocityCommand,
    WorkspaceDefinition,
    WorkspaceDelete,
    decode,
    encode,
)
from confnav.services.bus import Bus, ZenohBus, zenoh_config
from confnav.services.keys import Keys
from confnav.services.launcher import LaunchConfig, Launcher, ServiceSpec

HERE = Path(__file__).resolve().parent
K = Keys()
SIM_ID = "sim"

# ------------------------------------------------------------------------------------------
# malformed messages
# ------------------------------------------------------------------------------------------
_SQUARE = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]


def _samples() -> dict[tuple[str, str], bytes]:
    """A valid message of every subscribed (group, kind): the base the mutations start from."""
    t = time.time_ns()
    return {
        ("ws", "definition"): encode(WorkspaceDefinition(ws_id="fz", outer=_SQUARE)),
        ("ws", "delete"): encode(WorkspaceDelete(ws_id="fz")),
        ("ws", "transform"): json.dumps(  # only the base of the mutations: never valid
            {
                "type": TransformSolution.TYPE,
                "schema_version": 1,
                "ws_id": "fz",
                "revision": "r",
                "definition_hash": "h",
                "stamp_ns": t,
                "anchor": [0.0, 0.0],
                "centers": [[0.1, 0.2]],
                "radii": [0.1],
                "diagnostics": {"sweeps": 1, "error_estimate": 0.0, "wall_time": 0.0},
                "coefficients": {"x": [1, 2]},
            }
        ).encode(),
        ("robot", "goal"): encode(Goal(robot_id="fz", ws_id="fz", goal=(0.0, 0.0))),
        ("robot", "cancel"): encode(GoalCancel(robot_id="fz")),
        ("robot", "pose"): encode(Pose(robot_id="fz", stamp_ns=t, seq=1, x=0.1, y=0.2)),
        ("robot", "cmd_vel"): encode(VelocityCommand(robot_id="fz", stamp_ns=t, linear=(0, 0))),
        ("sim", "spawn"): encode(SpawnRequest(robot_id="fz", ws_id="fz", position=(0.0, 0.0))),
        ("sim", "control"): encode(SimControl(action="pause")),
    }


FUZZ_KINDS: tuple[tuple[str, str], ...] = tuple(_samples())
HUGE_BYTES = 3 * 1024 * 1024


def _wrong_types(obj: Any, rng: random.Random) -> Any:
    """Every value replaced by one of another JSON type (the keys kept)."""
    if isinstance(obj, dict):
        return {k: _wrong_types(v, rng) for k, v in obj.items()}
    choices: list[Any] = [None, True, "x", 7, [1], {"a": 1}, -1.5]
    bad = [c for c in choices if type(c) is not type(obj)]
    return rng.choice(bad)


def _with_nan(text: str, rng: random.Random) -> bytes:
    """A numeric value replaced by NaN / Infinity (Python's json writes them bare)."""
    obj = json.loads(text)
    nums = [k for k, v in obj.items() if isinstance(v, int | float) and not isinstance(v, bool)]
    lists = [k for k, v in obj.items() if isinstance(v, list) and v and isinstance(v[0], float)]
    bad = rng.choice([float("nan"), float("inf"), -float("inf")])
    if nums:
        obj[rng.choice(nums)] = bad
    elif lists:
        key = rng.choice(lists)
        obj[key] = [bad, *obj[key][1:]]
    else:
        obj["x"] = bad
    return json.dumps(obj).encode()


def malformed(
    group: str, kind: str, n: int, seed: int = 0, verbatim: bool = True
) -> Iterator[tuple[str, bytes, str]]:
    """``n`` (key, payload, what) malformed messages for a subscribed key kind.

    Payload classes in turn: random bytes, truncated JSON, wrong types, NaN / Infinity, a
    wildcard id inside the payload, and (one in 500) a huge payload of 3 MiB. Keys: mostly
    the concrete fuzz key, one in 10 with a ``*`` chunk, one in 20 with an odd id (``..``, a
    500-character chunk...), and with ``verbatim`` one in 20 with a verbatim ``@`` chunk (a
    wildcard subscriber never receives those: Zenoh matches ``@`` chunks only literally).
    """
    rng = random.Random(f"{seed}:{group}:{kind}")
    sample = _samples()[(group, kind)].decode()
    ident = SIM_ID if group == "sim" else "fz"
    odd = ["..", ".", "~", "x" * 500, "ünï", "a-b_c"]
    for i in range(n):
        r = rng.random()
        if verbatim and r < 0.05:
            key_id = "@v"
        elif r < 0.15:
            key_id = "*"
        elif r < 0.20:
            key_id = rng.choice(odd)
        else:
            key_id = ident
        key = f"{K.prefix}/{group}/{key_id}/{kind}"
        what = ("random", "truncated", "wrong_types", "nan", "wild_id")[i % 5]
        if rng.random() < 0.002:
            what = "huge"
        if what == "random":
            payload = rng.randbytes(rng.randrange(0, 2000))
        elif what == "truncated":
            payload = sample.encode()[: rng.randrange(0, len(sample))]
        elif what == "wrong_types":
            payload = json.dumps(_wrong_types(json.loads(sample), rng)).encode()
        elif what == "nan":
            payload = _with_nan(sample, rng)
        elif what == "wild_id":
            obj = json.loads(sample)
            for field in ("robot_id", "ws_id"):
                if field in obj:
                    obj[field] = rng.choice(["*", "**", "$*", "@x", "a/b", ""])
            if "robot_id" not in obj and "ws_id" not in obj:  # SimControl: a bad action
                obj["action"] = "*"
            payload = json.dumps(obj).encode()
        else:
            payload = b'{"pad":"' + b"x" * HUGE_BYTES + b'"}'
        yield key, payload, what


#: (group, kind) -> (service, counter counting every message that reached it, subscription)
RECEIVED_COUNTERS: dict[tuple[str, str], list[tuple[str, str, str]]] = {
    ("ws", "definition"): [
        ("transform", "definitions_received", K.any_ws("definition")),
        ("controller", "definitions_received", K.any_ws("definition")),
        ("simulator", "definitions_received", K.any_ws("definition")),
    ],
    ("ws", "delete"): [
        ("transform", "deletes_received", K.any_ws("delete")),
        ("controller", "deletes_received", K.any_ws("delete")),
    ],
    ("ws", "transform"): [("controller", "transforms_received", K.any_ws("transform"))],
    ("robot", "goal"): [("controller", "goals_received", K.any_robot("goal"))],
    ("robot", "cancel"): [("controller", "cancels_received", K.any_robot("cancel"))],
    ("robot", "pose"): [("controller", "poses", K.any_robot("pose"))],
    ("robot", "cmd_vel"): [("simulator", "commands_received", K.any_robot("cmd_vel"))],
    ("sim", "spawn"): [("simulator", "spawns_received", K.sim(SIM_ID, "spawn"))],
    ("sim", "control"): [("simulator", "controls_received", K.sim(SIM_ID, "control"))],
}


def delivered_zenoh(key: str, sub: str) -> bool:
    """Whether a put on ``key`` reaches a subscriber of ``sub`` (``*`` chunks on either side
    match one chunk, ``**`` any; a verbatim ``@`` chunk only matches itself, as in Zenoh)."""
    k, e = key.split("/"), sub.split("/")
    if e[-1] == "**":
        e = e[:-1]
        if len(k) < len(e):
            return False
        k, rest = k[: len(e)], k[len(e) :]
        if any(c.startswith("@") for c in rest):
            return False
    if len(k) != len(e):
        return False
    for a, b in zip(k, e, strict=True):
        if a == b:
            continue
        if a.startswith("@") or b.startswith("@"):
            return False
        if a != "*" and b != "*":
            return False
    return True


def fuzz_traffic(
    n: int,
    seed: int = 0,
    verbatim: bool = True,
    delivered: Callable[[str, str], bool] = delivered_zenoh,
) -> tuple[list[tuple[str, bytes]], dict[tuple[str, str], int], Counter[str]]:
    """Every malformed message of every kind; the number delivered per (service, counter)
    and per topic (what the recorder must hold); ``delivered(key, subscription)`` says
    whether a put reaches a subscriber (Zenoh's rules by default)."""
    msgs: list[tuple[str, bytes]] = []
    expect: dict[tuple[str, str], int] = Counter()
    topics: Counter[str] = Counter()
    for group, kind in FUZZ_KINDS:
        for key, payload, _what in malformed(group, kind, n, seed, verbatim):
            msgs.append((key, payload))
            if delivered(key, K.prefix + "/**"):
                topics[key] += 1
            for service, counter, sub in RECEIVED_COUNTERS[(group, kind)]:
                if delivered(key, sub):
                    expect[(service, counter)] += 1
    return msgs, expect, topics


def bad_queries(n: int, seed: int = 0) -> list[str]:
    """Selectors the transform queryable receives and cannot answer with a solution."""
    rng = random.Random(seed)
    out = []
    for i in range(n):
        ident = ("x" * rng.randrange(65, 600), "nope", "ü" * 40, "..", f"q{i}")[i % 5]
        out.append(f"{K.prefix}/ws/{ident}/transform")
    return out


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
def commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=HERE, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def loadavg() -> str:
    return Path("/proc/loadavg").read_text().strip()


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


class HealthWatch:
    """The latest health counters of every service (by service name; one process each)."""

    def __init__(self, bus: Bus) -> None:
        self.latest: dict[str, ServiceHealth] = {}
        self.lock = threading.Lock()
        bus.subscribe(K.prefix + "/health/**", self._on)

    def _on(self, key: str, payload: bytes) -> None:
        try:
            h = decode(ServiceHealth, payload)
        except DecodeError:
            return
        with self.lock:
            self.latest[h.service] = h

    def counters(self) -> dict[str, dict[str, int]]:
        with self.lock:
            return {s: dict(h.counters) for s, h in self.latest.items()}


def wait(pred: Callable[[], Any], timeout: float, what: str, period: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(period)
    raise TimeoutError(what)


CMD_TIMEOUT_S = 0.25  # simulator: wall s without a command -> stop
MAX_CMD_AGE_S = 0.25  # simulator: sim s after the pose a command answers -> stop


def system_config(
    sock: str,
    out: Path,
    cache: Path,
    robots: dict[str, complex],
    time_scale: float,
    rate: float,
    recorder: bool = True,
    cmd_timeout: float = CMD_TIMEOUT_S,
    max_cmd_age: float = MAX_CMD_AGE_S,
    recorder_args: tuple[str, ...] = (),
) -> LaunchConfig:
    """Router + recorder (with ``recorder_args``), transform, controller, simulator on the
    default workspace."""
    sim_args = ["--workspace", "default=builtin:default", "--time-scale", str(time_scale)]
    sim_args += ["--rate", str(rate), "--cmd-timeout", str(cmd_timeout)]
    sim_args += ["--max-cmd-age", str(max_cmd_age)]
    for rid, z in robots.items():
        sim_args += ["--robot", f"{rid}=default:{z.real!r},{z.imag!r}"]
    services = [
        ServiceSpec(
            "transform", ["--workspace", "default=builtin:default", "--cache-dir", str(cache)]
        ),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", sim_args),
    ]
    if recorder:
        rec_args = ["--out", str(out / "chaos.mcap"), *recorder_args]
        services.insert(0, ServiceSpec("recorder", rec_args))
    return LaunchConfig(
        listen=[sock], services=services, max_restarts=20, log_dir=str(out / "logs")
    )


def check_recordings(out: Path) -> list[dict[str, Any]]:
    """Every recording file: complete (footer) or restored by recover (messages)."""
    from confnav.recording.recover import has_footer, recover

    rows: list[dict[str, Any]] = []
    for path in sorted(out.glob("chaos*.mcap")):
        if ".recovered" in path.name:
            continue
        if has_footer(path):
            rows.append({"file": path.name, "state": "complete"})
            continue
        try:
            rep = recover(path, path.with_name(path.stem + ".recovered.mcap"))
            rows.append({"file": path.name, "state": "recovered", "messages": rep.messages})
        except Exception as exc:
            rows.append({"file": path.name, "state": f"LOST: {exc}"})
    return rows


# ------------------------------------------------------------------------------------------
# fuzz
# ------------------------------------------------------------------------------------------
def run_fuzz(n: int, queries: int, work: Path) -> dict[str, Any]:
    sockdir = Path(tempfile.mkdtemp(prefix="cnf", dir="/tmp"))
    out = work / "fuzz"
    out.mkdir(parents=True, exist_ok=True)
    config = system_config(f"unixsock-stream/{sockdir}/r.sock", out, work / "cache", {}, 1.0, 50.0)
    config.stop_timeout = 120.0  # the recorder finishes a large file
    launcher = Launcher(config)
    result: dict[str, Any] = {"n_per_kind": n}
    try:
        launcher.start()
        assert launcher.bus is not None
        pids = {label: p.popen.pid for label, p in launcher.procs.items()}
        health = HealthWatch(launcher.bus)
        wait(lambda: len(health.counters()) == 4, 30, "health of the four services")
        bus = launcher.bus
        wait(
            lambda: any(r.ok for r in bus.query(K.ws("default", "transform"), timeout=5.0)),
            300,
            "the default workspace solved",
            0.5,
        )
        time.sleep(3.0)  # start-up traffic (definitions, solutions) settles
        before = health.counters()
        msgs, expect, topics = fuzz_traffic(n)
        pub = ZenohBus(zenoh_config("client", connect=launcher.config.listen))
        t0 = time.monotonic()
        try:
            for key, payload in msgs:
                pub.publish(key, payload)
            t_pub = time.monotonic() - t0
            answered = 0
            for sel in bad_queries(queries):
                replies = pub.query(sel, timeout=5.0)
                answered += bool(replies) and all(not r.ok for r in replies)
        finally:
            pub.close()

        def settled() -> dict[str, dict[str, int]] | None:
            now = health.counters()
            done = all(
                now.get(s, {}).get(c, 0) - before.get(s, {}).get(c, 0) >= v
                for (s, c), v in expect.items()
            )
            return now if done else None

        try:
            wait(settled, 300, "counters account for the messages", 1.0)
            n_rec = before.get("recorder", {}).get("recorded", 0) + sum(topics.values())
            wait(
                lambda: health.counters().get("recorder", {}).get("recorded", 0) >= n_rec,
                300,
                "the recorder has every message",
                1.0,
            )
        except TimeoutError:
            pass
        time.sleep(2.0)
        after = health.counters()
        rows = []
        for (service, counter), want in sorted(expect.items()):
            got = after.get(service, {}).get(counter, 0) - before.get(service, {}).get(counter, 0)
            rows.append({"service": service, "counter": counter, "sent": want, "counted": got})
        alive = {
            label: p.popen.poll() is None and p.popen.pid == pids[label]
            for label, p in launcher.procs.items()
        }
        result.update(
            messages=len(msgs),
            publish_s=t_pub,
            counters=rows,
            processes_alive_unrestarted=alive,
            restarts=launcher.restarts,
            queries=queries,
            queries_answered_with_error=answered,
        )
    finally:
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)
    # the recorder holds every delivered fuzz message, per topic
    from confnav.recording.reader import Recording

    got_topics: Counter[str] = Counter()
    files = sorted(p for p in out.glob("chaos*.mcap") if ".recovered" not in p.name)
    result["recordings"] = check_recordings(out)
    for path in files:
        fixed = path.with_name(path.stem + ".recovered.mcap")
        with Recording(fixed if fixed.exists() else path) as rec:
            for m in rec.iter_messages():
                if m.topic in topics:
                    got_topics[m.topic] += 1
    result["recorder_files"] = [p.name for p in files]
    result["recorder_topics_exact"] = got_topics == topics
    result["recorder_missing"] = sum((topics - got_topics).values())
    return result


# ------------------------------------------------------------------------------------------
# kill -9 during a 4-robot run
# ------------------------------------------------------------------------------------------
class Robots:
    """Poses (receive time, position), statuses and collisions of the robots."""

    def __init__(self, bus: Bus, ids: list[str]) -> None:
        self.lock = threading.Lock()
        # receive time (monotonic), position, publication time (the simulator's stamp_ns)
        self.poses: dict[str, list[tuple[float, complex, int]]] = {r: [] for r in ids}
        self.arrived_at: dict[str, float] = {}
        self.collisions: list[CollisionEvent] = []
        bus.subscribe(K.any_robot("pose"), self._pose)
        bus.subscribe(K.any_robot("status"), self._status)
        bus.subscribe(K.any_robot("collision"), self._collision)

    def _pose(self, key: str, payload: bytes) -> None:
        try:
            p = decode(Pose, payload)
        except DecodeError:
            return
        with self.lock:
            if p.robot_id in self.poses:
                self.poses[p.robot_id].append((time.monotonic(), complex(p.x, p.y), p.stamp_ns))

    def _status(self, key: str, payload: bytes) -> None:
        try:
            s = decode(RobotStatus, payload)
        except DecodeError:
            return
        if s.state == "arrived":
            with self.lock:
                self.arrived_at.setdefault(s.robot_id, time.monotonic())

    def _collision(self, key: str, payload: bytes) -> None:
        try:
            c = decode(CollisionEvent, payload)
        except DecodeError:
            return
        with self.lock:
            self.collisions.append(c)

    def position(self, rid: str) -> complex | None:
        with self.lock:
            return self.poses[rid][-1][1] if self.poses[rid] else None

    def started_over(self, rid: str, t_reset: float, start: complex) -> bool:
        """Whether, after ``t_reset``, the robot was back at ``start`` and then moved away."""
        with self.lock:
            seq = [z for t, z, _s in self.poses[rid] if t >= t_reset]
        back = next((i for i, z in enumerate(seq) if abs(z - start) < 0.05), None)
        return back is not None and any(abs(z - start) > 0.15 for z in seq[back:])

    def moving(self, rid: str, within_ns: int = 200_000_000) -> bool:
        """Whether the robot's last two poses differ and the last is stamped within
        ``within_ns`` of now (it is moving at this moment)."""
        with self.lock:
            last = self.poses[rid][-2:]
        if len(last) < 2:
            return False
        (_t0, z0, _s0), (_t1, z1, s1) = last
        return abs(z1 - z0) > 1e-12 and time.time_ns() - s1 <= within_ns

    def stop_time(self, rid: str, from_ns: int, to_ns: int) -> int | None:
        """Publication time (the simulator's stamp, ns) of the last pose stamped in
        [from_ns, to_ns] that differs from the one before (None: it never moved there); the
        robot stands still after it. Stamps, not receive times: what the plant did, not how
        late this process heard of it."""
        with self.lock:
            seq = [(s, z) for _t, z, s in self.poses[rid] if from_ns - 500_000_000 <= s <= to_ns]
        last = None
        for (_s0, z0), (s1, z1) in itertools.pairwise(seq):
            if abs(z1 - z0) > 1e-12 and s1 >= from_ns:
                last = s1
        return last


def _kill_victim(
    victim: str,
    repeats: int,
    work: Path,
    starts: dict[str, complex],
    time_scale: float,
    rate: float,
    cmd_timeout: float,
    runs: list[dict[str, Any]],
    stops: list[float],
) -> list[dict[str, Any]]:
    """One system; ``repeats`` kills of ``victim``; rows appended to ``runs`` and stop
    latencies to ``stops``; returns the state of its recording files."""
    from confnav.scenes.workspaces import DEFAULT_GOAL

    out = work / f"kill-{victim}"
    out.mkdir(parents=True, exist_ok=True)
    sockdir = Path(tempfile.mkdtemp(prefix="cnk", dir="/tmp"))
    launcher = Launcher(
        system_config(
            f"unixsock-stream/{sockdir}/r.sock",
            out,
            work / "cache",
            starts,
            time_scale,
            rate,
            cmd_timeout=cmd_timeout,
        )
    )
    stop_goals = threading.Event()
    try:
        launcher.start()
        assert launcher.bus is not None
        bus = launcher.bus
        robots = Robots(bus, list(starts))
        goals = [
            encode(
                Goal(
                    robot_id=r,
                    ws_id="default",
                    goal=(DEFAULT_GOAL.real, DEFAULT_GOAL.imag),
                    gain=100.0,
                )
            )
            for r in starts
        ]

        def send_goals() -> None:  # goals are state: republished at 1 Hz (idempotent)
            while not stop_goals.is_set():
                for rid, g in zip(starts, goals, strict=True):
                    with contextlib.suppress(Exception):  # the router may be down
                        bus.publish(K.robot(rid, "goal"), g)
                stop_goals.wait(1.0)

        threading.Thread(target=send_goals, daemon=True).start()
        monitor = threading.Thread(target=launcher.monitor, args=(stop_goals, 0.1), daemon=True)
        monitor.start()
        for rep in range(repeats):
            t_reset = time.monotonic()
            bus.publish(K.sim(SIM_ID, "control"), encode(SimControl(action="reset")))
            with robots.lock:
                robots.arrived_at.clear()
                n_coll = len(robots.collisions)

            # wait until every robot moves away from its start
            def started_over(t: float = t_reset) -> bool:
                return all(robots.started_over(r, t, z) for r, z in starts.items())

            wait(started_over, 120, "robots back at their starts and moving")

            def victim_up() -> Any:  # restarted after the previous kill (backoff grows)
                p = launcher.router if victim == "router" else launcher.procs[victim]
                return p if p is not None and p.popen.poll() is None else None

            proc = wait(victim_up, 120, f"{victim} restarted")
            # a stop latency needs a robot moving at the kill (in a full test run all four
            # stood still by then, e.g. arrived while the restarted victim came up: 0.0 s)
            wait(lambda: any(robots.moving(r) for r in starts), 60, "a robot moving")
            t_kill, t_kill_ns = time.monotonic(), time.time_ns()
            os.kill(proc.popen.pid, signal.SIGKILL)
            row: dict[str, Any] = {"victim": victim, "repeat": rep}
            if victim == "controller":
                time.sleep(max(1.0, 3 * cmd_timeout))
                lat = []
                for r in starts:
                    t_stop = robots.stop_time(r, t_kill_ns, time.time_ns())
                    lat.append(0.0 if t_stop is None else (t_stop - t_kill_ns) / 1e9)
                row["stop_latency_s"] = max(lat)
                stops.extend(lat)
            with robots.lock:
                robots.arrived_at.clear()
            try:
                wait(
                    lambda: (
                        all(r in robots.arrived_at for r in starts)
                        and all(
                            abs((robots.position(r) or 9) - DEFAULT_GOAL) < 0.05 for r in starts
                        )
                    ),
                    180,
                    "every robot arrives",
                    0.2,
                )
                row["all_arrived"] = True
            except TimeoutError:
                row["all_arrived"] = False
            with robots.lock:
                row["collisions"] = len(robots.collisions) - n_coll
            row["arrival_s_after_kill"] = time.monotonic() - t_kill
            row["cycle_s"] = time.monotonic() - t_reset
            row["restarts"] = launcher.restarts
            print(f"  kill {victim} #{rep + 1}: {row}", flush=True)
            runs.append(row)
    finally:
        stop_goals.set()
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)
    return check_recordings(out)


def run_kill(
    victims: list[str], repeats: int, work: Path, time_scale: float, cmd_timeout: float
) -> dict[str, Any]:
    from confnav.scenes.workspaces import DEFAULT_STARTS

    starts = {f"r{i + 1}": z for i, z in enumerate(DEFAULT_STARTS)}
    rate = 50.0
    runs: list[dict[str, Any]] = []
    stops: list[float] = []
    recordings: dict[str, Any] = {}
    for victim in victims:
        recordings[victim] = _kill_victim(
            victim, repeats, work, starts, time_scale, rate, cmd_timeout, runs, stops
        )
    return {
        "time_scale": time_scale,
        "cmd_timeout_s": cmd_timeout,
        "max_cmd_age_s": MAX_CMD_AGE_S,
        "sim_step_s": 1.0 / rate / time_scale,
        "runs": runs,
        "stop_latency_s": {
            "max": max(stops) if stops else None,
            "p50": float(np.median(stops)) if stops else None,
            "n": len(stops),
        },
        "recordings": recordings,
    }


# ------------------------------------------------------------------------------------------
# soak
# ------------------------------------------------------------------------------------------
def free_points(n: int, seed: int = 1) -> list[complex]:
    from confnav.scenes.workspaces import default_workspace

    ws = default_workspace()
    rng = np.random.default_rng(seed)
    pts: list[complex] = []
    while len(pts) < n:
        z = complex(*rng.uniform(-1.9, 1.9, 2))
        if float(ws.clearance(np.asarray(z))) > 0.1 and abs(z) > 0.5:
            pts.append(z)
    return pts


def run_soak(
    minutes: float,
    n_robots: int,
    work: Path,
    rate: float,
    keep: bool = False,
    split_duration: float | None = None,
) -> dict[str, Any]:
    from confnav.scenes.workspaces import DEFAULT_GOAL

    starts = {f"s{i}": z for i, z in enumerate(free_points(n_robots))}
    out = work / "soak"
    out.mkdir(parents=True, exist_ok=True)
    sockdir = Path(tempfile.mkdtemp(prefix="cns", dir="/tmp"))
    rec_args = () if split_duration is None else ("--split-duration", str(split_duration))
    launcher = Launcher(
        system_config(
            f"unixsock-stream/{sockdir}/r.sock",
            out,
            work / "cache",
            starts,
            1.0,
            rate,
            recorder_args=rec_args,
        )
    )
    samples: list[dict[str, Any]] = []
    resets = 0
    try:
        launcher.start()
        assert launcher.bus is not None
        bus = launcher.bus
        robots = Robots(bus, list(starts))
        health = HealthWatch(bus)
        goal = (DEFAULT_GOAL.real, DEFAULT_GOAL.imag)
        t0 = time.monotonic()
        next_goal = next_sample = 0.0
        while (now := time.monotonic() - t0) < minutes * 60:
            if now >= next_goal:
                next_goal = now + 2.0
                for rid in starts:
                    bus.publish(
                        K.robot(rid, "goal"),
                        encode(Goal(robot_id=rid, ws_id="default", goal=goal, gain=100.0)),
                    )
                with robots.lock:
                    done = list(robots.arrived_at)
                    robots.arrived_at.clear()
                for rid in done:  # keep the traffic going: arrived robots start over
                    bus.publish(
                        K.sim(SIM_ID, "control"), encode(SimControl(action="reset", robot_id=rid))
                    )
                    resets += 1
            if now >= next_sample:
                next_sample = now + 10.0
                procs = {label: p.popen.pid for label, p in launcher.procs.items()}
                if launcher.router is not None:
                    procs["router"] = launcher.router.popen.pid
                row = {"t_s": round(now, 1), "load": loadavg()}
                row.update({label: rss_kib(pid) for label, pid in procs.items()})
                with health.lock:
                    rh = health.latest.get("recorder")
                row["recorded"] = rh.counters.get("recorded", 0) if rh else 0
                row["queued"] = rh.gauges.get("queued", 0) if rh else 0  # recorder backlog
                samples.append(row)
                print(f"  soak {row}", flush=True)
            time.sleep(0.2)
        with robots.lock:
            events = [
                c.model_dump(include={"robot_id", "stamp_ns", "position", "clearance"})
                for c in robots.collisions
            ]
        restarts = launcher.restarts
    finally:
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)
    warm = [s for s in samples if s["t_s"] >= 60.0] or samples
    growth = {}
    for label in [k for k in samples[0] if k not in ("t_s", "load", "recorded", "queued")]:
        first, last = warm[0][label], warm[-1][label]
        growth[label] = (last - first) / first if first else None
    segments = sorted(out.glob("chaos*.mcap"))
    recording_bytes = sum(p.stat().st_size for p in segments)
    if not (keep or events):  # a large recording: kept only to investigate
        shutil.rmtree(out, ignore_errors=True)
    return {
        "minutes": minutes,
        "robots": n_robots,
        "rate_hz": rate,
        "samples": samples,
        "rss_growth_after_warmup": growth,
        "resets": resets,
        "collisions": len(events),
        "collision_events": events,
        "recording": str(out) if out.exists() else None,
        "recorder_split_duration_s": split_duration,
        "recording_segments": len(segments),
        "recording_bytes": recording_bytes,
        "restarts": restarts,
    }


# ------------------------------------------------------------------------------------------
MODES = ("fuzz", "kill", "soak")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; ``modes`` defaults to all of :data:`MODES`."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    # checked below, not by ``choices``: Python 3.11's argparse checks the value of an empty
    # nargs="*" positional (its default, or []) against ``choices`` as one value and rejects
    # it, so the bare ``python -m bench chaos`` exited 2
    ap.add_argument("modes", nargs="*", help=f"any of {', '.join(MODES)} (default: all)")
    ap.add_argument("--n", type=int, default=10_000, help="malformed messages per key kind")
    ap.add_argument("--queries", type=int, default=1000, help="bad queries")
    ap.add_argument("--repeats", type=int, default=5, help="kills per service")
    ap.add_argument(
        "--victims", default="router,transform,controller,simulator,recorder", help="kill order"
    )
    ap.add_argument("--time-scale", type=float, default=2.0, help="simulator speed-up (kill)")
    ap.add_argument("--minutes", type=float, default=30.0, help="soak duration")
    ap.add_argument("--robots", type=int, default=100, help="soak robots")
    ap.add_argument("--soak-rate", type=float, default=20.0, help="soak simulator rate, Hz")
    ap.add_argument(
        "--soak-split-duration",
        type=float,
        default=None,
        help="recorder --split-duration in the soak, s (default: the recorder's)",
    )
    ap.add_argument("--out", default=str(HERE / "results" / "chaos.json"))
    ap.add_argument("--keep", action="store_true", help="keep the work directory")
    args = ap.parse_args(argv)
    bad = sorted(set(args.modes) - set(MODES))
    if bad:
        ap.error(f"unknown mode(s) {', '.join(bad)}: choose from {', '.join(MODES)}")
    args.modes = args.modes or list(MODES)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="confnav-chaos-"))
    results: dict[str, Any] = {
        "commit": commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "load_start": loadavg(),
        "machine": f"{os.cpu_count()} cores (shared)",
    }
    prev = Path(args.out)
    if prev.exists():  # modes run separately at one commit accumulate in one file
        try:
            old = json.loads(prev.read_text())
        except ValueError:
            old = {}
        kept = {k: v for k, v in old.items() if k in ("fuzz", "kill", "soak")}
        if old.get("commit") == results["commit"]:
            results.update(kept)
        elif kept:  # never stamp another commit's figures with this one
            print(f"{prev.name}: dropping {', '.join(kept)} measured at {old.get('commit')}")
    targets: list[tuple[str, str, bool]] = []
    keep_work = args.keep
    try:
        if "fuzz" in args.modes:
            print(
                f"fuzz: {args.n} malformed messages per key kind, {args.queries} bad queries",
                flush=True,
            )
            fz = run_fuzz(args.n, args.queries, work)
            fz["load_end"] = loadavg()
            results["fuzz"] = fz
        if "kill" in args.modes:
            victims = args.victims.split(",")
            print(f"kill: {victims} x {args.repeats}", flush=True)
            kl = run_kill(victims, args.repeats, work, args.time_scale, CMD_TIMEOUT_S)
            kl["load_end"] = loadavg()
            results["kill"] = kl
        if "soak" in args.modes:
            print(f"soak: {args.robots} robots for {args.minutes} min", flush=True)
            sk = run_soak(
                args.minutes,
                args.robots,
                work,
                args.soak_rate,
                args.keep,
                split_duration=args.soak_split_duration,
            )
            keep_work = sk["recording"] is not None
            sk["load_end"] = loadavg()
            results["soak"] = sk
    finally:
        if not keep_work:
            shutil.rmtree(work, ignore_errors=True)

    if "fuzz" in results:
        fz = results["fuzz"]
        accounted = all(r["counted"] == r["sent"] for r in fz["counters"])
        alive = all(fz["processes_alive_unrestarted"].values()) and fz["restarts"] == 0
        print(f"\nfuzz ({fz['messages']} messages, published in {fz['publish_s']:.1f} s):")
        for r in fz["counters"]:
            print(
                f"  {r['service']:<11} {r['counter']:<22} sent {r['sent']:>6}  "
                f"counted {r['counted']:>6}"
            )
        print(
            f"  recorder: every delivered message in the file: {fz['recorder_topics_exact']} "
            f"(missing {fz['recorder_missing']})"
        )
        print(
            f"  bad queries answered with reply_err: {fz['queries_answered_with_error']}"
            f"/{fz['queries']}"
        )
        targets += [
            (
                "fuzz: 0 crashes / restarts",
                f"alive {fz['processes_alive_unrestarted']}, restarts {fz['restarts']}",
                alive,
            ),
            (
                "fuzz: counters account for every message",
                "exact" if accounted else "MISMATCH",
                accounted,
            ),
            (
                "fuzz: recorder holds every message",
                f"missing {fz['recorder_missing']}",
                fz["recorder_topics_exact"],
            ),
            (
                "fuzz: every bad query answered",
                f"{fz['queries_answered_with_error']}/{fz['queries']}",
                fz["queries_answered_with_error"] == fz["queries"],
            ),
        ]
    if "kill" in results:
        kl = results["kill"]
        runs = kl["runs"]
        coll = sum(r["collisions"] for r in runs)
        arrived = sum(r["all_arrived"] for r in runs)
        rec_ok = all(
            row["state"] in ("complete", "recovered")
            for rows in kl["recordings"].values()
            for row in rows
        )
        hold = min(kl["cmd_timeout_s"], kl.get("max_cmd_age_s", 1e9) / kl["time_scale"])
        limit = hold + kl["sim_step_s"]
        sl = kl["stop_latency_s"]
        print(f"\nkill -9 ({len(runs)} kills):")
        by: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for r in runs:
            by[r["victim"]].append(r)
        for v, rs in by.items():
            print(
                f"  {v:<11} kills {len(rs)}  all arrived "
                f"{sum(r['all_arrived'] for r in rs)}/{len(rs)}  "
                f"collisions {sum(r['collisions'] for r in rs)}  arrival after kill "
                f"{max(r['arrival_s_after_kill'] for r in rs):.1f} s max"
            )
        print(f"  recordings: {kl['recordings']}")
        targets += [
            ("kill: 0 collisions", str(coll), coll == 0),
            (
                "kill: every robot arrives after every kill",
                f"{arrived}/{len(runs)} runs",
                arrived == len(runs),
            ),
            ("kill: recordings complete or recoverable", "yes" if rec_ok else "NO", rec_ok),
        ]
        if sl["max"] is not None:
            targets.append(
                (
                    f"kill: robots stop <= command hold + 1 step ({limit * 1e3:.0f} ms) "
                    "after losing the controller",
                    f"max {sl['max'] * 1e3:.0f} ms, p50 {sl['p50'] * 1e3:.0f} ms (n={sl['n']})",
                    sl["max"] <= limit,
                )
            )
    if "soak" in results:
        sk = results["soak"]
        worst = max(
            (g for g in sk["rss_growth_after_warmup"].values() if g is not None), default=0.0
        )
        print(f"\nsoak ({sk['robots']} robots, {sk['minutes']} min, resets {sk['resets']}):")
        if "recording_segments" in sk:
            split = sk["recorder_split_duration_s"]
            print(
                f"  recording: {sk['recording_segments']} segment(s), "
                f"{sk['recording_bytes'] / 1e6:.0f} MB, recorder --split-duration "
                f"{'default' if split is None else split}"
            )
        for label, g in sk["rss_growth_after_warmup"].items():
            print(f"  {label:<11} RSS growth {g * 100:+.1f} %")
        queued = [s["queued"] for s in sk["samples"] if "queued" in s]
        if queued:
            print(f"  recorder queue: max {max(queued)}, last {queued[-1]} (samples every 10 s)")
        short = "" if sk["minutes"] >= 30 else ", short; target is 30 min"
        targets.append(
            (
                f"soak ({sk['minutes']:g} min{short}): RSS growth <= 10 %",
                f"worst {worst * 100:+.1f} %",
                worst <= 0.10,
            )
        )
        targets.append(("soak: 0 collisions", str(sk["collisions"]), sk["collisions"] == 0))
    print("\ntargets:")
    for name, value, ok in targets:
        print(f"  {'met   ' if ok else 'MISSED'} {name}: {value}")
    results["targets"] = [{"target": n, "value": v, "met": ok} for n, v, ok in targets]
    results["load_end"] = loadavg()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1, default=str))
    print(
        f"\nwrote {args.out} (load at start {results['load_start']}, at end {results['load_end']})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
