"""The controller's hot path, in process (issue 25 item 5): CPU per pose and where it goes.

    python bench/bench_controller.py [--robots 50 100 200 400] [--rate 20] [--seconds 5]
                                     [--wire single batch] [--profile] [--out FILE.json]
    python bench/bench_controller.py --step [--robots 200]   # the pose step alone, no Zenoh

One ``ControllerService`` runs in this process on its own session; a Zenoh router (``confnav
serve router``, as deployed: its routing is not the controller's CPU) and a transform service
(``confnav serve transform``, the default workspace) each in its own process; one child process
plays the robots exactly as ``bench services`` does (``play_robots``: poses at ``--rate`` Hz
per robot at independent phases, commands received, latency = command receipt - the answered
pose's stamp). Every robot has its own goal (``own`` mode). ``--wire batch``: the robots are
played as one simulator stepping them all at once, one ``PoseBatch`` per tick answered by one
``CommandBatch`` (optional messages, docs/SERVICES.md "Scale"); each row names its wire.

Per row: poses answered, latency p50/p99, and the controller process's CPU time divided by the
poses it took (``cpu_us_per_pose``) -- less sensitive to the machine's load than latency --
with the CPU of each Python thread that works on poses (the pose step, the fleet filter's
pose tracker, the publisher) measured with ``time.thread_time`` around its handler, and the
rest (Zenoh's own threads, health, watchdog) as the difference. ``--profile`` also runs
``cProfile`` (on each thread's CPU clock) inside those threads and prints the top functions
(inflated by the profiler; use its ratios). Writes bench/results/controller.json with the
commit and the load average before and after each row (after every row: a cut run keeps them).
``pose_path_cpu_us_per_pose`` is the process's CPU per pose without the threads of
:data:`BACKGROUND` (work that is not the poses': goals' critical-point searches, map installs).
``threads_cpu_us_per_pose`` is every thread of the process by name (``/proc/self/task``, 10 ms
ticks): ``latest`` the pose step, ``rx-*``/``tx-*``/``acc-*``/``app-*`` Zenoh's, the
``pyo3-closure`` threads Zenoh's callbacks into Python, ``critical-points`` the background
searches (services/critical_search.py), ``python`` native threads with no name of their own
(Zenoh's runtime), ``MainThread`` this harness's waiting.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as dt
import gc
import io
import json
import multiprocessing as mp
import os
import pstats
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from bench_services import (
    K,
    free_points,
    make_goal,
    play_robots,
    robot_id,
    spawn,
    wait,
)
from confnav.schemas import encode
from confnav.services.bus import ZenohBus, zenoh_config
from provenance import commit  # script mode: bench/ is on sys.path

RESULTS = Path(__file__).resolve().parent / "results" / "controller.json"
TARGET = {"robots": 200, "rate": 20.0, "p99_ms": 20.0}
POSE_THREADS = ("latest", "sub:confnav/sim/")
"""The pose step's threads: single poses (``latest``), pose batches (``sub:.../sim/*/poses``)."""
BACKGROUND = ("critical-points", "sub:", "controller:fetch", "controller:watchdog", "MainThread")
"""Threads whose work is not the poses' (``pose_path_cpu_us_per_pose`` leaves them out): the
background critical-point searches of new goals (services/critical_search.py), map installs
(``sub:``), map fetches, the watchdog and this harness's waiting."""
# Besides, per row: the pose threads' and the process's wait for a core (schedstat run delay),
# the machine's busy and stolen cores (/proc/stat), how late a 5 ms sleep wakes up in a process
# of its own (wake_probe), this process's GC pauses, and for pose batches each step's age,
# wall and CPU time (the slowest 2 %: wall far above CPU is waiting for a core).


class _Timed:
    """CPU seconds (``time.thread_time``) and calls of one handler; optionally profiled."""

    def __init__(self, profile: bool) -> None:
        self.cpu = 0.0
        self.calls = 0
        # thread CPU time, not wall time: a function that releases the GIL (shapely, numpy)
        # would otherwise be charged the wait for the GIL after it (other threads' work)
        self.prof = cProfile.Profile(time.thread_time) if profile else None
        self.lock = threading.Lock()

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def run(*a: Any) -> Any:
            t = time.thread_time()
            if self.prof is not None:
                self.prof.enable()
            try:
                return fn(*a)
            finally:
                if self.prof is not None:
                    self.prof.disable()
                with self.lock:
                    self.cpu += time.thread_time() - t
                    self.calls += 1

        return run


def _timed_loop(timer: _Timed, loop: Callable[[], None]) -> Callable[[], None]:
    """A thread's whole loop (the publisher): its CPU at the end, profiled throughout."""

    def run() -> None:
        t = time.thread_time()
        if timer.prof is not None:
            timer.prof.enable()
        try:
            loop()
        finally:
            if timer.prof is not None:
                timer.prof.disable()
            timer.cpu += time.thread_time() - t

    return run


def _tasks() -> dict[str, float]:
    """CPU seconds of every thread of this process by name (Python threads by their
    ``threading`` name, native ones -- Zenoh's -- by their kernel name; same names summed)."""
    clk = os.sysconf("SC_CLK_TCK")
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        f = stat.rsplit(")", 1)[1].split()
        name = names.get(int(task.name), comm)
        if name.startswith(("latest", "qbl", "live")):  # one per key expression: summed
            name = name.split(":", 1)[0]
        out[name] = out.get(name, 0.0) + (int(f[11]) + int(f[12])) / clk
    return out


def _run_delay() -> dict[str, float]:
    """Seconds each thread of this process spent runnable but waiting for a core (kernel
    schedstat ``run_delay``), by name as in :func:`_tasks`: the machine's contention (other
    processes, or this process's threads exceeding the cores), not GIL waits (those sleep)."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            fields = (task / "schedstat").read_text().split()
            comm = (task / "comm").read_text().strip()
        except OSError:
            continue
        name = names.get(int(task.name), comm)
        if name.startswith(("latest", "qbl", "live")):
            name = name.split(":", 1)[0]
        out[name] = out.get(name, 0.0) + int(fields[1]) / 1e9
    return out


def _cpu_ticks() -> tuple[int, int]:
    """(busy, steal) clock ticks of the whole machine so far (``/proc/stat``, all cores):
    busy = user + nice + system + irq + softirq; steal = time the hypervisor ran others."""
    f = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return f[0] + f[1] + f[2] + f[5] + f[6], f[7]


class _BatchSteps:
    """Each pose-batch step: how old the batch was when the step began (its ``stamp_ns`` to the
    handler: Zenoh, the router, waiting for the thread), the step's wall time and its thread
    CPU time (ms). Wall minus CPU is the step's wait for a core or the GIL."""

    def __init__(self, fn: Callable[[list[tuple[str, bytes]]], None]) -> None:
        self.fn = fn
        self.rows: list[tuple[float, float, float]] = []
        self.on = False

    def __call__(self, items: list[tuple[str, bytes]]) -> None:
        t_ns, w0, c0 = time.time_ns(), time.perf_counter(), time.thread_time()
        self.fn(items)
        if self.on and items:
            payload = items[-1][1]
            i = payload.index(b'"stamp_ns":') + 11
            stamp = int(payload[i : payload.index(b",", i)])
            self.rows.append(((t_ns - stamp) / 1e6, (time.perf_counter() - w0) * 1e3,
                              (time.thread_time() - c0) * 1e3))  # fmt: skip

    def summary(self) -> dict[str, Any]:
        """Percentiles of each part, and the parts of the slowest 2 % of the steps (by age
        plus wall time: the latency of their commands up to the publisher)."""
        if not self.rows:
            return {}
        a = np.asarray(self.rows)
        tot = a[:, 0] + a[:, 1]
        worst = a[np.argsort(tot)[-max(1, len(tot) // 50) :]]
        out: dict[str, Any] = {"steps": len(a)}
        for j, name in enumerate(("age_ms", "wall_ms", "cpu_ms")):
            out[name] = {"p50": float(np.percentile(a[:, j], 50)),
                         "p99": float(np.percentile(a[:, j], 99)),
                         "worst_2pct_mean": float(worst[:, j].mean())}  # fmt: skip
        return out


class _GcPauses:
    """Every garbage collection of this process while installed: generation and pause (s);
    a full (generation 2) collection stops every Python thread, the pose step included."""

    def __init__(self) -> None:
        self.pauses: list[tuple[int, float]] = []
        self._t = 0.0

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t = time.perf_counter()
        else:
            self.pauses.append((int(info["generation"]), time.perf_counter() - self._t))

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for g in (0, 1, 2):
            d = [p for gen, p in self.pauses if gen == g]
            out[f"gen{g}"] = {"count": len(d), "max_ms": max(d, default=0.0) * 1e3,
                              "total_ms": sum(d) * 1e3}  # fmt: skip
        return out


def wake_probe(seconds: float, period: float, out: Any) -> None:
    """Child process: sleep ``period`` s again and again for ``seconds`` s and put how late
    each wake-up came (ms): the scheduling delay every waking thread on this machine sees
    (a pose arriving at the controller, a command at the robots), from the machine's load."""
    late = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        t0 = time.monotonic()
        time.sleep(period)
        late.append((time.monotonic() - t0 - period) * 1e3)
    out.put(late)


def _settle(
    svc: Any, quiet: float = 3.0, timeout: float = 30.0, search_timeout: float = 240.0
) -> None:
    """Wait until the controller is idle: the final revision of the progressive map installed,
    no controller built for ``quiet`` s (every goal rebuilt on it) and under 40% of a core, then
    until the critical-point searches of the goals are done (their worker idle for 1 s, at most
    ``search_timeout`` s more: services/critical_search.py)."""
    t_end = time.monotonic() + timeout
    built, since = svc.counters["controllers_built"], time.monotonic()
    c0, t0 = time.process_time(), time.monotonic()
    while time.monotonic() < t_end:
        time.sleep(0.5)
        now = time.monotonic()
        if svc.counters["controllers_built"] != built:
            built, since = svc.counters["controllers_built"], now
        cpu = (time.process_time() - c0) / (now - t0)
        c0, t0 = time.process_time(), now
        m = svc._maps.get("default")
        refining = m is None or m.revision in svc._refining  # a coarse revision installed
        if now - since >= quiet and cpu < 0.4 and not refining:
            break
    # the goals' background critical-point searches (services/critical_search.py) hold the
    # GIL in turns with the pose step: done before the window (a fleet with fixed goals)
    from confnav.services.critical_search import CRITICAL_SEARCH

    busy = None
    while time.monotonic() < t_end + search_timeout:
        cpu_s = _tasks().get(CRITICAL_SEARCH.name, 0.0)
        if CRITICAL_SEARCH._jobs.empty() and cpu_s == busy:
            return
        busy = cpu_s
        time.sleep(1.0)
    log_line = "critical-point searches still running after the settle timeout"
    print(log_line, flush=True)


def row(
    ep: str,
    ctl_bus: ZenohBus,
    n: int,
    rate: float,
    seconds: float,
    profile: bool,
    linger_ms: float = 0.0,
    gc_freeze: bool = False,
    batch: bool = False,
) -> dict[str, Any]:
    from confnav.services.controller import ControllerService
    from confnav.services.neighbours import Neighbours

    timers = {k: _Timed(profile) for k in ("pose_step", "fleet_tracker", "publisher")}
    svc = ControllerService(ctl_bus, K, stale_after=2.0, idle_ttl=600.0, linger=linger_ms / 1e3)
    svc._on_poses = timers["pose_step"].wrap(svc._on_poses)  # type: ignore[method-assign]
    steps = _BatchSteps(timers["pose_step"].wrap(svc._on_pose_batches))
    svc._on_pose_batches = steps  # type: ignore[method-assign]
    svc._publish_loop = _timed_loop(timers["publisher"], svc._publish_loop)  # type: ignore[method-assign]
    orig = Neighbours._on_poses
    wrapped = timers["fleet_tracker"].wrap(orig)
    Neighbours._on_poses = lambda self, items: wrapped(self, items)  # type: ignore[method-assign]
    try:
        svc.start()
    finally:
        Neighbours._on_poses = orig  # type: ignore[method-assign]
    try:
        with ZenohBus(zenoh_config("client", connect=[ep])) as bus:
            goals = free_points(n, seed=7)
            for i in range(n):
                xy = (goals[i].real, goals[i].imag)
                bus.publish(K.robot(robot_id(i), "goal"), encode(make_goal(i, xy, "harmonic")))
            wait(lambda: svc.counters["controllers_built"] >= n, 300, "controllers")
            _settle(svc)
            if gc_freeze:  # everything built so far out of the collector's way
                gc.collect()
                gc.freeze()
            warm = int(rate)
            ticks = warm + int(seconds * rate)
            ctx = mp.get_context("spawn")
            q: Any = ctx.Queue()
            q_probe: Any = ctx.Queue()
            done = ctx.Event()
            child = ctx.Process(
                target=play_robots, args=(ep, n, rate, ticks, warm, q, done, 0, 1, batch)
            )
            child.start()
            poses0 = svc.counters["poses"]
            time.sleep(0.6 + warm / rate)  # the child's session and the warm-up second
            load0 = os.getloadavg()
            c0 = {k: (t.cpu, t.calls) for k, t in timers.items()}
            p0 = os.times()
            k0 = _tasks()
            d0 = _run_delay()
            m0 = _cpu_ticks()
            gcp = _GcPauses()
            gc.callbacks.append(gcp)
            steps.on = True
            probe = ctx.Process(target=wake_probe, args=(seconds, 0.005, q_probe))
            probe.start()
            poses_w0, sup0 = svc.counters["poses"], svc.counters["poses_superseded"]
            cmds0 = svc.counters["commands"]
            t0 = time.monotonic()
            late = q.get(timeout=seconds + 120)["late"]
            wait(lambda: svc.counters["poses"] - poses0 >= n * ticks, 120, "drain")
            time.sleep(0.3)
            wall = time.monotonic() - t0
            p1 = os.times()
            k1 = _tasks()
            d1 = _run_delay()
            m1 = _cpu_ticks()
            gc.callbacks.remove(gcp)
            steps.on = False
            wakes = np.asarray(q_probe.get(timeout=60))
            probe.join(10)
            load1 = os.getloadavg()
            taken = svc.counters["poses"] - poses_w0
            superseded = svc.counters["poses_superseded"] - sup0
            commands = svc.counters["commands"] - cmds0
            done.set()
            res = q.get(timeout=60)
            child.join(30)
    finally:
        svc.stop()
    proc_cpu = (p1.user + p1.system) - (p0.user + p0.system)
    lat = np.asarray(res["lat_ns"], dtype=float) / 1e6
    per = {k: (t.cpu - c0[k][0]) / max(commands, 1) * 1e6 for k, t in timers.items()}
    calls = {k: t.calls - c0[k][1] for k, t in timers.items()}
    out: dict[str, Any] = {
        "robots": n,
        "rate_hz": rate,
        # single: a Pose per robot at its own phase, a VelocityCommand each; batch: one
        # PoseBatch per tick, answered with one CommandBatch (bench_services.play_robots)
        "wire": "batch" if batch else "single",
        "seconds": seconds,
        # from sequence numbers (bench_services.account_poses): answered + superseded + lost
        # == sent exactly, never clamped
        "sent": int(res["sent"]),
        "answered": int(res["answered"]),
        "superseded": int(res["superseded"]),
        "lost": int(res["lost"]),
        "poses_taken": taken,
        "superseded_counted": superseded,  # the controller's counter over its own window
        "commands": commands,
        "late_publishes": late,
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "max_ms": float(lat.max()) if lat.size else float("nan"),
        "process_cpu_pct": 100 * proc_cpu / wall,
        "cpu_us_per_pose": proc_cpu / max(commands, 1) * 1e6,
        "thread_cpu_us_per_pose": per,
        "other_cpu_us_per_pose": proc_cpu / max(commands, 1) * 1e6 - sum(per.values()),
        "threads_cpu_us_per_pose": {
            k: round((v - k0.get(k, 0.0)) / max(commands, 1) * 1e6, 1)
            for k, v in sorted(k1.items(), key=lambda kv: -(kv[1] - k0.get(kv[0], 0.0)))
            if v - k0.get(k, 0.0) > 0
        },
        "pose_path_cpu_us_per_pose": sum(
            (v - k0.get(k, 0.0)) / max(commands, 1) * 1e6
            for k, v in k1.items()
            if k.startswith(POSE_THREADS) or not k.startswith(BACKGROUND)
        ),
        # the pose thread's wait for a core, per s of the window (0.1: runnable but not running
        # 10 % of the time), and every thread's together: evidence of the machine's load
        "pose_thread_run_delay_frac": sum(
            d1[k] - d0.get(k, 0.0) for k in d1 if k.startswith(POSE_THREADS)
        )
        / wall,
        # the whole machine's busy cores (every process, this bench's included) and stolen ones
        "machine_busy_cores": (m1[0] - m0[0]) / os.sysconf("SC_CLK_TCK") / wall,
        "machine_steal_cores": (m1[1] - m0[1]) / os.sysconf("SC_CLK_TCK") / wall,
        "gc_pauses": gcp.summary(),  # this process's collections in the window
        "batch_steps": steps.summary(),  # pose batches only
        # how late a 5 ms sleep wakes up in a process of its own, during the window (ms)
        "wake_late_max_ms": float(wakes.max()),
        "wake_late_p50_ms": float(np.percentile(wakes, 50)),
        "wake_late_p99_ms": float(np.percentile(wakes, 99)),
        "process_run_delay_frac": (sum(d1.values()) - sum(d0.get(k, 0.0) for k in d1)) / wall,
        "pose_step_calls": calls["pose_step"],
        "poses_per_step": commands / max(calls["pose_step"], 1),
        "counters": {k: v for k, v in svc.counters.items() if k.startswith(("stops_", "def"))},
        "fleet": {k: v for k, v in svc.neighbours.counters.items()} if svc.neighbours else {},
        "profiled": profile,
        "linger_ms": linger_ms,
        "gc_freeze": gc_freeze,
        "switch_interval_ms": sys.getswitchinterval() * 1e3,
        "loadavg_start": list(load0),
        "loadavg_end": list(load1),
    }
    if profile:
        out["profile"] = {}
        for k, t in timers.items():
            assert t.prof is not None
            if not t.calls and k != "publisher":  # not called (the tracker, fed)
                continue
            s = io.StringIO()
            st = pstats.Stats(t.prof, stream=s)
            st.sort_stats("tottime").print_stats(18)
            st.sort_stats("cumulative").print_stats(30)
            out["profile"][k] = s.getvalue()
    return out


def _write(out: str, rows: list[dict[str, Any]]) -> None:
    doc = {
        "about": "controller hot path in process: CPU per pose, latency (bench_controller.py)",
        "commit": commit(),
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "cpus": os.cpu_count(),
        "command": " ".join(sys.argv),
        "target": TARGET,
        "rows": rows,
    }
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(doc, indent=1) + "\n")


def codec(n: int = 50_000) -> dict[str, float]:
    """us per call of the pose decode and the command encode, and of the alternatives."""
    import timeit

    from confnav.schemas import Pose, VelocityCommand, decode
    from confnav.schemas.fast import velocity_command_json

    pose = (
        b'{"type":"confnav.Pose","schema_version":1,"robot_id":"z01r001",'
        b'"stamp_ns":1764180000000000000,"seq":12,"x":0.123456789,"y":-1.23456789,"theta":0.0}'
    )
    d = json.loads(pose)
    header = {k: VelocityCommand.model_fields[k].default for k in ("type", "schema_version")}
    fields = dict(robot_id="z01r001", stamp_ns=1764180000000000000, linear=(0.31, -0.12),
                  angular=0.0, pose_seq=12, pose_stamp_ns=1764180000000000000,
                  map_revision="5f1c9a0b2e", frame="world", chart=None)  # fmt: skip
    args = tuple(fields.values())
    cases: dict[str, Callable[[], object]] = {
        "decode_pose_pydantic": lambda: decode(Pose, pose),
        "json_loads_pose": lambda: json.loads(pose),
        "pose_model_construct": lambda: Pose.model_construct(**d),
        "encode_command_model_construct": lambda: encode(
            VelocityCommand.model_construct(**header, **fields)
        ),
        "encode_command_fast": lambda: velocity_command_json(*args),  # type: ignore[arg-type]
    }
    return {k: min(timeit.repeat(f, number=n, repeat=3)) / n * 1e6 for k, f in cases.items()}


def step(
    n: int = 200, blocks: tuple[int, ...] = (5, 20, 50), rounds: int = 20
) -> list[dict[str, Any]]:
    """The pose step alone, in process, without Zenoh: a transform service and the controller
    on an in-memory bus (the real default map, ``n`` robots with their own goals, as in the
    rows), then ``rounds`` poses of every robot handed to the pose step in blocks of each size
    of ``blocks``: thread CPU per pose (repeatable; old and new code compare alternately)."""
    from confnav.schemas import Pose, PoseBatch, decode
    from confnav.services.bus import InMemoryNetwork
    from confnav.services.controller import ControllerService
    from confnav.services.transform import TransformService

    net = InMemoryNetwork()
    with tempfile.TemporaryDirectory(prefix="cnbs") as tmp:
        tr = TransformService(net.bus("tr"), K, {"default": "builtin:default"}, workers=1,
                              executor="thread", cache_dir=tmp, progressive=False)  # fmt: skip
        tr.start()
        svc = ControllerService(net.bus("ctl"), K, stale_after=600.0, idle_ttl=600.0)
        svc.start()
        try:
            cl = net.bus("cl")
            goals, starts = free_points(n, seed=7), free_points(n, seed=3)
            for i in range(n):
                g = make_goal(i, (goals[i].real, goals[i].imag), "harmonic")
                cl.publish(K.robot(robot_id(i), "goal"), encode(g))
            wait(lambda: svc.counters["controllers_built"] >= n, 600, "controllers")
            _settle(svc)
            seq = 0

            def poses() -> list[tuple[str, bytes]]:
                nonlocal seq
                seq += 1
                t = time.time_ns()
                return [
                    (K.robot(robot_id(i), "pose"),
                     encode(Pose(robot_id=robot_id(i), stamp_ns=t, seq=seq,
                                 x=starts[i].real, y=starts[i].imag)))
                    for i in range(n)
                ]  # fmt: skip

            out = []
            for b in blocks:
                todo = [(ps[s : s + b]) for _ in range(rounds) for ps in [poses()]
                        for s in range(0, n, b)]  # fmt: skip
                c0, load0 = svc.counters["commands"], os.getloadavg()
                t0 = time.thread_time()
                for items in todo:
                    svc._on_poses(items)
                cpu = time.thread_time() - t0
                done = svc.counters["commands"] - c0
                out.append({"robots": n, "block": b, "poses": n * rounds, "commands": done,
                            "step_cpu_us_per_pose": cpu / max(n * rounds, 1) * 1e6,
                            "loadavg_start": list(load0),
                            "loadavg_end": list(os.getloadavg())})  # fmt: skip
                print(f"{n} robots, blocks of {b:3d}: pose step "
                      f"{out[-1]['step_cpu_us_per_pose']:.1f} us CPU per pose ({done} "
                      f"commands) | load {load0[0]:.1f}", flush=True)  # fmt: skip
            # the same poses as one PoseBatch per round (decode included)
            batches = []
            for _ in range(rounds):
                ps = [decode(Pose, p) for _k, p in poses()]
                batches.append(
                    (
                        K.sim("bench", "poses"),
                        encode(
                            PoseBatch(
                                sim_id="bench",
                                stamp_ns=ps[0].stamp_ns,
                                robot_ids=[p.robot_id for p in ps],
                                stamps_ns=[p.stamp_ns for p in ps],
                                seq=[p.seq for p in ps],
                                x=[p.x for p in ps],
                                y=[p.y for p in ps],
                                theta=[p.theta for p in ps],
                            )
                        ),
                    )
                )
            c0, load0 = svc.counters["commands"], os.getloadavg()
            per_step = []
            for item in batches:  # at 20 Hz: the statuses' periodic repeats fall due
                t1 = time.thread_time()
                svc._on_pose_batches([item])
                per_step.append(time.thread_time() - t1)
                time.sleep(0.05)
            cpu = sum(per_step)
            done = svc.counters["commands"] - c0
            out.append(
                {
                    "robots": n,
                    "block": "batch",
                    "poses": n * rounds,
                    "commands": done,
                    "step_cpu_us_per_pose": cpu / max(n * rounds, 1) * 1e6,
                    "step_cpu_ms": [round(t * 1e3, 2) for t in per_step],
                    "loadavg_start": list(load0),
                    "loadavg_end": list(os.getloadavg()),
                }
            )
            print(
                f"{n} robots, one PoseBatch: pose step "
                f"{out[-1]['step_cpu_us_per_pose']:.1f} us CPU per pose ({done} "
                f"commands), ms per step {out[-1]['step_cpu_ms']} | load {load0[0]:.1f}",
                flush=True,
            )
            return out
        finally:
            svc.stop()
            tr.stop()


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--robots", type=int, nargs="*", default=[50, 100, 200, 400])
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--profile", action="store_true", help="cProfile the pose threads")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--linger-ms", type=float, default=0.0, help="controller linger, ms")
    ap.add_argument("--gc-freeze", action="store_true", help="gc.freeze() once set up")
    ap.add_argument("--blocks", type=int, nargs="*", default=[5, 20, 50],
                    help="--step: block sizes of single poses (then one PoseBatch)")  # fmt: skip
    ap.add_argument(
        "--wire", nargs="*", default=["single"], choices=["single", "batch"],
        help="single: a Pose per robot; batch: one PoseBatch per tick (both: each row twice)",
    )  # fmt: skip
    ap.add_argument("--switch-ms", type=float, default=None, help="sys.setswitchinterval, ms")
    ap.add_argument(
        "--codec", action="store_true", help="only decode/encode costs: controller_codec.json"
    )
    ap.add_argument(
        "--step", action="store_true",
        help="only the pose step in process, no Zenoh (blocks of 5, 20, 50): controller_step.json",
    )  # fmt: skip
    args = ap.parse_args()
    if args.step:
        out = RESULTS.with_name("controller_step.json") if args.out == str(RESULTS) else args.out
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        rows = step(args.robots[0] if len(args.robots) == 1 else 200, tuple(args.blocks))
        doc = {"about": "the pose step alone, in process (bench_controller.py --step)",
               "commit": commit(), "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
               "command": " ".join(sys.argv), "rows": rows}  # fmt: skip
        Path(out).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {out}")
        return 0
    if args.codec:
        out = RESULTS.with_name("controller_codec.json") if args.out == str(RESULTS) else args.out
        doc = {"about": "pose decode and command encode, us per call (bench_controller.py --codec)",
               "commit": commit(), "loadavg": list(os.getloadavg()), "us": codec()}  # fmt: skip
        Path(out).write_text(json.dumps(doc, indent=1) + "\n")
        print(json.dumps(doc["us"], indent=1))
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if args.switch_ms is not None:  # how long a thread holds the GIL when others wait
        sys.setswitchinterval(args.switch_ms / 1e3)
    rows = []
    with tempfile.TemporaryDirectory(prefix="cnb") as tmp:
        ep = f"unixsock-stream/{tmp}/r.sock"
        # the router in its own process (as deployed): this process's CPU is the controller's
        router = spawn("serve", "router", "--listen", ep, log=Path(tmp) / "router.log")
        try:
            wait(lambda: Path(ep.split("/", 1)[1]).exists(), 30, "router socket")
            tr = spawn("serve", "transform", "--mode", "client", "--connect", ep,
                       "--workspace", "default=builtin:default",
                       log=Path(tmp) / "transform.log")  # fmt: skip
            ctl_bus = ZenohBus(zenoh_config("client", connect=[ep]))
            try:
                for n, wire in [(n, w) for n in args.robots for w in args.wire]:
                    r = row(ep, ctl_bus, n, args.rate, args.seconds, args.profile,
                            args.linger_ms, args.gc_freeze, wire == "batch")  # fmt: skip
                    rows.append(r)
                    _write(args.out, rows)  # after every row: a cut run keeps its rows
                    th = r["thread_cpu_us_per_pose"]
                    print(
                        f"{n:4d} robots @ {args.rate:g} Hz ({wire}): answered "
                        f"{r['answered']}/{r['sent']}"
                        f" superseded {r['superseded']} lost {r['lost']}"
                        f" p50 {r['p50_ms']:.1f} ms p99 "
                        f"{r['p99_ms']:.1f} ms | CPU {r['process_cpu_pct']:.0f}% "
                        f"{r['cpu_us_per_pose']:.0f} us/pose, pose path "
                        f"{r['pose_path_cpu_us_per_pose']:.0f} (step {th['pose_step']:.0f}, "
                        f"tracker {th['fleet_tracker']:.0f}, publisher {th['publisher']:.0f}, "
                        f"other {r['other_cpu_us_per_pose']:.0f}) {r['poses_per_step']:.1f} "
                        f"poses/step | run delay: pose thread "
                        f"{r['pose_thread_run_delay_frac']:.0%}, process "
                        f"{r['process_run_delay_frac']:.2f} cores; a 5 ms sleep wakes "
                        f"{r['wake_late_p50_ms']:.1f}/{r['wake_late_p99_ms']:.1f} ms late "
                        f"(p50/p99); machine {r['machine_busy_cores']:.2f} cores busy | load "
                        f"{r['loadavg_start'][0]:.1f}",
                        flush=True,
                    )
                    print("  threads (us/pose):", r["threads_cpu_us_per_pose"], flush=True)
                    if r["batch_steps"]:
                        print("  batch steps (ms):", json.dumps(r["batch_steps"]), flush=True)
                    print("  gc:", r["gc_pauses"], "| 5 ms sleep late max",
                          f"{r['wake_late_max_ms']:.1f} ms", flush=True)  # fmt: skip
                    if args.profile:
                        for k, text in r["profile"].items():
                            print(f"--- {k} ---\n{text}")
            finally:
                ctl_bus.close()
                tr.terminate()
                tr.wait(20)
        finally:
            router.terminate()
            router.wait(20)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
