"""Benchmark of the services over real Zenoh on loopback (separate processes).

Measures, with a router, a transform service and a controller service each in their own
process and this process playing the robots:

- pose -> command latency (p50, p99; pose publish to cmd_vel receipt, same clock) and the
  CPU of the controller and the router, for 1, 10, 100 and 200 robots at 50 Hz (all robots
  share one goal, so the controller evaluates their poses in vectorized blocks);
- messages lost (poses sent after the warm-up without a matching command);
- coefficient query latency (``{prefix}/ws/default/transform``, the full solution);
- solve-to-first-command time after a workspace update (re-solve + publish + hot swap).

Target (issue 4): 100 robots at 50 Hz with p99 <= 5 ms on loopback, zero messages lost.
Prints a table and writes bench/results/services.json.  ``--quick``: shorter runs, 1/10/100.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from confnav.schemas import Goal, TransformSolution, WorkspaceDefinition, decode, encode
from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import Keys
from confnav.services.launcher import SINGLE_THREAD_BLAS

HERE = Path(__file__).resolve().parent
K = Keys()
CLK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def spawn(*args: str, log: Path) -> subprocess.Popen[bytes]:
    f = open(log, "wb")  # noqa: SIM115 - lives as long as the process
    env = dict(os.environ)
    env.update({k: v for k, v in SINGLE_THREAD_BLAS.items() if k not in os.environ})
    return subprocess.Popen(
        [sys.executable, "-m", "confnav.cli", *args], stdout=f, stderr=subprocess.STDOUT, env=env
    )


def wait(pred: Any, timeout: float, what: str) -> Any:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    raise RuntimeError(f"timed out waiting for {what}")


def connect(ep: str) -> ZenohBus:
    deadline = time.monotonic() + 30
    while True:
        try:
            return ZenohBus(zenoh_config("client", connect=[ep]))
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def free_points(n: int, seed: int = 1) -> list[complex]:
    from confnav.workspaces import default_workspace

    ws = default_workspace()
    rng = np.random.default_rng(seed)
    pts: list[complex] = []
    while len(pts) < n:
        z = complex(*rng.uniform(-1.9, 1.9, 2))
        if float(ws.clearance(np.asarray(z))) > 0.1 and abs(z) > 0.3:
            pts.append(z)
    return pts


def publish_poses(ep: str, n: int, rate: float, ticks: int, out: Any) -> None:
    """Child process: N robots publish poses at ``rate`` Hz for ``ticks`` ticks, each robot
    at its own phase (robot i at i/N of the period: independent robots, not one burst)."""
    ids = [f"b{i:03d}" for i in range(n)]
    pts = free_points(n)
    keys = [K.robot(r, "pose") for r in ids]
    period = 1.0 / rate
    late = 0
    with connect(ep) as bus:
        time.sleep(0.5)
        t0 = time.monotonic() + 0.1
        for seq in range(ticks):
            for i, (rid, key, z) in enumerate(zip(ids, keys, pts, strict=True)):
                due = t0 + (seq + i / n) * period
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -period:
                    late += 1
                payload = (
                    f'{{"type":"confnav.Pose","schema_version":1,"robot_id":"{rid}",'
                    f'"stamp_ns":{time.time_ns()},"seq":{seq},"x":{z.real!r},"y":{z.imag!r},'
                    f'"theta":0.0}}'
                ).encode()
                bus.publish(key, payload)
        out.put({"late": late})


class Commands:
    """Receives the commands: latency = receipt - the answered pose's own stamp (one clock)."""

    def __init__(self, bus: ZenohBus, first_seq: int) -> None:
        self.first_seq = first_seq
        self.lock = threading.Lock()
        self.lat_ns: list[int] = []
        self.seen: set[tuple[str, int]] = set()
        self.sub = bus.subscribe_batch(K.any_robot("cmd_vel"), self._on_cmds)

    def _on_cmds(self, items: list[tuple[str, bytes]]) -> None:
        now = time.time_ns()
        with self.lock:
            for _key, payload in items:
                c = json.loads(payload)
                if c["pose_seq"] >= self.first_seq and c["robot_id"].startswith("b"):
                    self.lat_ns.append(now - c["pose_stamp_ns"])
                    self.seen.add((c["robot_id"], c["pose_seq"]))


class Health:
    """Latest counters of every controller process (from their ServiceHealth messages)."""

    def __init__(self, bus: ZenohBus) -> None:
        self.lock = threading.Lock()
        self.counters: dict[str, dict[str, int]] = {}
        bus.subscribe(f"{K.prefix}/health/controller/*", self._on)

    def _on(self, key: str, payload: bytes) -> None:
        h = json.loads(payload)
        with self.lock:
            self.counters[h["zid"]] = dict(h["counters"])

    def total(self, name: str) -> int:
        with self.lock:
            return sum(c.get(name, 0) for c in self.counters.values())


HEALTH: Health | None = None


def run_load(bus: ZenohBus, ep: str, n: int, rate: float, seconds: float) -> dict[str, Any]:
    import multiprocessing as mp

    for i in range(n):
        g = Goal(robot_id=f"b{i:03d}", ws_id="default", goal=(0.0, 0.0), gain=100.0, v_max=0.5)
        bus.publish(K.robot(f"b{i:03d}", "goal"), encode(g))
    time.sleep(2.5 if n > 10 else 1.0)  # controllers built (shared goal: once)
    warm = int(rate)  # first second: warm-up
    ticks = warm + int(seconds * rate)
    cmds = Commands(bus, warm)
    assert HEALTH is not None
    sup0 = HEALTH.total("poses_superseded")
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    child = ctx.Process(target=publish_poses, args=(ep, n, rate, ticks, q))
    child.start()
    time.sleep(0.6 + warm / rate)
    pid_cpu = {}
    return_cpu = _cpu_probe(pid_cpu)
    t0 = time.monotonic()
    child.join(seconds + 60)
    wall = time.monotonic() - t0
    time.sleep(1.5)  # answers and one health period
    cpu = return_cpu(wall)
    superseded = HEALTH.total("poses_superseded") - sup0
    late = q.get(timeout=5)["late"] if child.exitcode == 0 else -1
    cmds.sub.close()
    with cmds.lock:
        lat = np.array(cmds.lat_ns, dtype=float) / 1e6
        answered = len(cmds.seen)
    sent = n * (ticks - warm)
    return {
        "robots": n,
        "sent": sent,
        "answered": answered,
        "unanswered": sent - answered,
        "superseded": superseded,  # by a newer pose of the same robot (overload)
        # neither answered nor superseded (the superseded count covers the whole run,
        # warm-up included, so this is a lower bound; clamped at 0)
        "lost": max(0, sent - answered - superseded),
        "late_publishes": late,
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "max_ms": float(lat.max()) if lat.size else float("nan"),
        **cpu,
    }


PROCS: dict[str, subprocess.Popen[bytes]] = {}


def _cpu_probe(store: dict[str, float]) -> Any:
    c0 = {k: cpu_seconds(p.pid) for k, p in PROCS.items()}

    def done(wall: float) -> dict[str, float]:
        return {f"cpu_{k}_pct": 100 * (cpu_seconds(p.pid) - c0[k]) / wall for k, p in PROCS.items()}

    return done


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="1/10/100 robots, 3 s each")
    ap.add_argument("--robots", type=int, nargs="*", default=None)
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--rate", type=float, default=50.0)
    ap.add_argument("--linger-ms", type=float, default=0.0, help="controller --linger-ms")
    ap.add_argument("--controllers", type=int, default=1, help="controller processes (shards)")
    ap.add_argument("--out", default=str(HERE / "results" / "services.json"))
    args = ap.parse_args()
    counts = args.robots or ([1, 10, 100] if args.quick else [1, 10, 100, 200])
    seconds = args.seconds or (3.0 if args.quick else 10.0)

    tmp = Path(tempfile.mkdtemp(prefix="confnav-bench-"))
    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--mode", "client", "--connect", ep]
    procs = PROCS
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "endpoint": "tcp loopback",
        "rate_hz": args.rate,
        "controllers": args.controllers,
        "linger_ms": args.linger_ms,
        "seconds": seconds,
        "runs": [],
    }
    try:
        procs["router"] = spawn("serve", "router", "--listen", ep, log=tmp / "router.log")
        time.sleep(1.0)
        cache = Path(tempfile.gettempdir()) / "confnav-bench-cache"  # outside the repo
        procs["transform"] = spawn(
            "serve",
            "transform",
            *common,
            "--workspace",
            "default=builtin:default",
            "--cache-dir",
            str(cache),
            log=tmp / "transform.log",
        )
        n_max = max(counts)
        for c in range(args.controllers):
            shard = [f"b{i:03d}" for i in range(n_max) if i % args.controllers == c]
            robots_arg = ["--robots", ",".join([*shard, "u1"])] if args.controllers > 1 else []
            procs["controller" if c == 0 else f"controller{c}"] = spawn(
                "serve",
                "controller",
                *common,
                "--stale-after",
                "2.0",
                "--linger-ms",
                str(args.linger_ms),
                *robots_arg,
                log=tmp / f"controller{c}.log",
            )
        with connect(ep) as bus:
            global HEALTH
            HEALTH = Health(bus)
            wait(
                lambda: (
                    len(bus.alive(K.alive_of("controller"))) == args.controllers
                    and bus.alive(K.alive_of("transform"))
                ),
                60,
                "services",
            )
            print("waiting for the default workspace's map...", flush=True)
            wait(
                lambda: any(r.ok for r in bus.query(K.ws("default", "transform"), timeout=5)),
                180,
                "map",
            )

            # coefficient query latency
            q = []
            size = 0
            for _ in range(30):
                t0 = time.perf_counter()
                [r] = bus.query(K.ws("default", "transform"), timeout=5)
                q.append((time.perf_counter() - t0) * 1e3)
                size = len(r.payload or b"")
            results["query"] = {
                "p50_ms": float(np.percentile(q, 50)),
                "p99_ms": float(np.percentile(q, 99)),
                "bytes": size,
            }

            for n in counts:
                r = run_load(bus, ep, n, args.rate, seconds)
                results["runs"].append(r)
                print(
                    f"{n:4d} robots: p50 {r['p50_ms']:.2f} ms  p99 {r['p99_ms']:.2f} ms  "
                    f"lost {r['lost']}/{r['sent']}  controller CPU "
                    f"{r['cpu_controller_pct']:.0f}%",
                    flush=True,
                )
                time.sleep(1.0)

            # solve-to-first-command after a workspace update (small room, one robot)
            room = WorkspaceDefinition(
                ws_id="benchroom",
                outer=[(-1, -1), (1, -1), (1, 1), (-1, 1)],
                obstacles=[[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2), (0.2, 0.2)]],
                anchor=(0, 0),
            )
            got: list[tuple[int, str]] = []
            bus.subscribe(
                K.robot("u1", "cmd_vel"),
                lambda k, p: got.append((time.time_ns(), json.loads(p).get("map_revision") or "")),
            )
            sols: list[TransformSolution] = []
            bus.subscribe(
                K.ws("benchroom", "transform"),
                lambda k, p: sols.append(decode(TransformSolution, p)),
            )
            bus.publish(K.ws("benchroom", "definition"), encode(room))
            wait(lambda: sols, 120, "room map")
            bus.publish(
                K.robot("u1", "goal"),
                encode(Goal(robot_id="u1", ws_id="benchroom", goal=(-0.6, 0.0), gain=100.0)),
            )
            stop = threading.Event()

            def poses() -> None:
                s = 0
                while not stop.is_set():
                    bus.publish(
                        K.robot("u1", "pose"),
                        (
                            f'{{"robot_id":"u1","stamp_ns":{time.time_ns()},"seq":{s},"x":0.8,'
                            f'"y":0.8}}'
                        ).encode(),
                    )
                    s += 1
                    time.sleep(0.02)

            th = threading.Thread(target=poses, daemon=True)
            th.start()
            wait(lambda: got and got[-1][1] == sols[0].revision, 30, "first command")
            dy = float(np.random.default_rng().uniform(0, 0.1))  # a new geometry: no cache hit
            moved = room.model_copy(
                update={"obstacles": [[(0.2, -0.5 - dy), (0.5, -0.5 - dy), (0.5, -0.1 - dy)]]}
            )
            t_put = time.time_ns()
            bus.publish(K.ws("benchroom", "definition"), encode(moved))
            wait(lambda: len(sols) >= 2, 120, "re-solve")
            t_first = wait(
                lambda: next((t for t, rev in got if rev == sols[-1].revision), None), 60, "swap"
            )
            stop.set()
            th.join()
            results["update"] = {
                "solve_to_first_command_s": (t_first - t_put) / 1e9,
                "solver_wall_time_s": sols[-1].diagnostics.wall_time,
                "publish_to_command_s": (t_first - sols[-1].stamp_ns) / 1e9,
            }
    finally:
        for name in [n for n in procs if n.startswith("controller")] + ["transform", "router"]:
            p = procs.get(name)
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()

    print()
    print(f"pose -> command over Zenoh (tcp loopback), {args.rate:g} Hz per robot, {seconds:g} s")
    hdr = (
        f"{'robots':>6} {'msgs/s':>7} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'lost':>5} "
        f"{'superseded':>13} {'ctl CPU':>8} {'rtr CPU':>8} {'target':>7}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in results["runs"]:
        ok = r["p99_ms"] <= 5.0 and r["lost"] == 0 and r["superseded"] == 0
        target = ("met" if ok else "MISSED") if r["robots"] == 100 else ""
        sup = f"{r['superseded']}/{r['sent']}"
        print(
            f"{r['robots']:>6} {r['robots'] * args.rate:>7.0f} {r['p50_ms']:>7.2f} "
            f"{r['p99_ms']:>7.2f} {r['max_ms']:>7.1f} {r['lost']:>5} {sup:>13}"
            f"{r['cpu_controller_pct']:>8.0f}% {r['cpu_router_pct']:>7.0f}% {target:>7}"
        )
    print(
        f"(controllers: {args.controllers}; the robots publish at independent phases from a "
        "separate process; latency = cmd_vel receipt - the pose's own stamp; superseded = "
        "poses replaced by a newer one of the same robot while the controller was busy)"
    )
    qr = results["query"]
    print(
        f"\ncoefficient query ({qr['bytes'] / 1024:.0f} KiB): p50 {qr['p50_ms']:.2f} ms, "
        f"p99 {qr['p99_ms']:.2f} ms"
    )
    up = results["update"]
    print(
        f"workspace update -> first command on the new map: {up['solve_to_first_command_s']:.2f} s"
        f" (solver {up['solver_wall_time_s']:.2f} s, publish -> command "
        f"{up['publish_to_command_s'] * 1e3:.0f} ms)"
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
