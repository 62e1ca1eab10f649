"""``confnav demo``: the whole system on the default workspace with the seed's four robots and a
differential-drive one.

Starts a router (unix socket in a temp dir) and the recorder, transform, controller and
simulator as separate processes, waits for the map, sends the four goals, shows progress,
stops when every robot has arrived or collided (or at the timeout), and writes
``OUT/demo.mcap`` and ``OUT/demo.png`` (a second run: ``demo.1.mcap`` and ``demo.1.png``);
prints a summary table. Exit code 0 only if every
robot arrived without collision.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from confnav.schemas import (
    CollisionEvent,
    DecodeError,
    Goal,
    Pose,
    RobotStatus,
    SpawnRequest,
    decode,
    encode,
)
from confnav.services.launcher import LaunchConfig, Launcher, ServiceSpec
from confnav.services.runtime import stop_on_signals

from confnav.navigation import defaults

log = logging.getLogger(__name__)

WS_ID = "default"
#: A differential-drive robot (id, start, heading, body radius, look-ahead) driven by body
#: twists on the map of the default workspace shrunk by radius + look-ahead.
UNICYCLE = ("u1", complex(1.6, -1.6), 3.0, 0.03, 0.05)


@dataclass
class Track:
    robot_id: str
    start: complex
    goal: complex
    path: list[complex] = field(default_factory=list)
    state: str = "waiting"
    reason: str = ""
    arrived_at: float | None = None
    collided: CollisionEvent | None = None
    radius: float = 0.0  # body radius (m): clearances are the body's, not the centre's

    @property
    def position(self) -> complex:
        return self.path[-1] if self.path else self.start

    @property
    def distance(self) -> float:
        return abs(self.position - self.goal)

    @property
    def length(self) -> float:
        return sum(abs(b - a) for a, b in zip(self.path, self.path[1:], strict=False))


class DemoMonitor:
    """Collects poses, statuses and collisions of the demo robots (bus handlers)."""

    def __init__(self, tracks: dict[str, Track]) -> None:
        self.tracks = tracks
        self.lock = threading.Lock()
        self.t0 = time.monotonic()

    def on_pose(self, key: str, payload: bytes) -> None:
        try:
            p = decode(Pose, payload)
        except DecodeError:
            return
        with self.lock:
            t = self.tracks.get(p.robot_id)
            if t is not None:
                t.path.append(complex(p.x, p.y))

    def on_status(self, key: str, payload: bytes) -> None:
        try:
            s = decode(RobotStatus, payload)
        except DecodeError:
            return
        with self.lock:
            t = self.tracks.get(s.robot_id)
            if t is None:
                return
            t.state, t.reason = s.state, s.reason
            if s.state == "arrived" and t.arrived_at is None:
                t.arrived_at = time.monotonic() - self.t0

    def on_collision(self, key: str, payload: bytes) -> None:
        try:
            c = decode(CollisionEvent, payload)
        except DecodeError:
            return
        with self.lock:
            t = self.tracks.get(c.robot_id)
            if t is not None and t.collided is None:
                t.collided = c

    def done(self) -> bool:
        with self.lock:
            return all(t.arrived_at is not None or t.collided for t in self.tracks.values())


def _state(t: Track) -> str:
    """``navigating``, or ``stopped (missing_map)``: the reason whenever it is not plain."""
    plain = {"navigating": "ok", "arrived": "arrived", "waiting": ""}
    if t.reason and t.reason != plain.get(t.state):
        return f"{t.state} ({t.reason})"
    return t.state


def figure_path(out: Path, new_recordings: list[Path]) -> Path:
    """The PNG named as this run's recording (``demo.1.mcap`` -> ``demo.1.png``: a second
    demo in the same folder keeps the first one's picture as it keeps its recording); without
    a recording the first free ``demo[.N].png``."""
    from confnav.services.recorder import free_path

    firsts = [p for p in new_recordings if ".part" not in p.name]
    if firsts:
        return firsts[0].with_suffix(".png")
    return free_path(out / "demo.png")


def demo_config(
    sock: str,
    out: Path,
    starts: dict[str, complex],
    time_scale: float,
    cache_dir: str | None,
    live_port: int | None = None,
) -> LaunchConfig:
    sim_args = ["--workspace", f"{WS_ID}=builtin:default", "--time-scale", str(time_scale)]
    for rid, z in starts.items():
        sim_args += ["--robot", f"{rid}={WS_ID}:{z.real!r},{z.imag!r}"]
    tr_args = ["--workspace", f"{WS_ID}=builtin:default"]
    if cache_dir:
        tr_args += ["--cache-dir", cache_dir]
    live = [] if live_port is None else [ServiceSpec("foxglove", ["--port", str(live_port)])]
    return LaunchConfig(
        listen=[sock],
        services=[
            *live,  # first: it sees every message, like the recorder
            ServiceSpec("recorder", ["--out", str(out / "demo.mcap"), "--foxglove"]),
            ServiceSpec("transform", tr_args),
            ServiceSpec("controller", []),
            ServiceSpec("simulator", sim_args),
        ],
        startup_timeout=60.0,
        log_dir=str(out / "logs"),
    )


def wait_for_map(launcher: Launcher, timeout: float, stop: threading.Event) -> str:
    """Query the transform queryable until it answers with a solution; return its revision."""
    assert launcher.bus is not None
    key = launcher.keys.ws(WS_ID, "transform")
    deadline = time.monotonic() + timeout
    last = ""
    while time.monotonic() < deadline and not stop.is_set():
        for rep in launcher.bus.query(key, timeout=5.0):
            if rep.ok and rep.payload is not None:
                from confnav.schemas import TransformSolution

                return decode(TransformSolution, rep.payload).revision
            last = rep.error or ""
            if " is invalid: " in last:  # solving failed: waiting will not help
                raise RuntimeError(f"the transform service cannot solve {WS_ID!r}: {last}")
        stop.wait(0.5)
    raise RuntimeError(f"no map for {WS_ID!r} after {timeout:g} s: {last}")


def plot_demo(tracks: dict[str, Track], path: Path) -> None:
    """Write :func:`demo_figure` to ``path``."""
    from confnav.plot.style import save

    save(demo_figure(tracks), path)


def demo_figure(tracks: dict[str, Track]) -> Any:
    """Workspace, start/goal and trajectory of every robot (matplotlib Agg), each robot in
    its colour of ``confnav inspect --plot`` and the Foxglove scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from confnav.recording.scene import robot_color
    from confnav.scenes.workspaces import default_workspace

    ws = default_workspace()
    # the colours of confnav inspect --plot and the Foxglove scene: by sorted robot id
    colors = {rid: robot_color(i) for i, rid in enumerate(sorted(tracks))}
    fig, ax = plt.subplots(figsize=(7, 6))
    outer = [*list(ws.outer), ws.outer[0]]
    ax.plot([z.real for z in outer], [z.imag for z in outer], "k-", lw=1.5)
    for ob in ws.obstacles:
        ax.fill([z.real for z in ob], [z.imag for z in ob], color="0.6", ec="k")
    for t in tracks.values():
        c = colors[t.robot_id]
        if t.path:
            ax.plot(
                [z.real for z in t.path],
                [z.imag for z in t.path],
                "-",
                color=c,
                lw=1.5,
                label=t.robot_id,
            )
        ax.plot(t.start.real, t.start.imag, "o", color=c)
        if t.collided is not None:
            ax.plot(*t.collided.position, "rx", ms=10)
    goals = {t.goal for t in tracks.values()}
    for g in goals:
        ax.plot(g.real, g.imag, "k*", ms=14)
    # marker key (proxy artists: the markers above are drawn once per robot / goal)
    ax.plot([], [], "o", color="0.3", label="start")
    ax.plot([], [], "k*", ms=10, label="goal")
    if any(t.collided is not None for t in tracks.values()):
        ax.plot([], [], "rx", label="collision")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"confnav demo: default workspace, {len(tracks)} robots")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return fig


def summary(tracks: dict[str, Track]) -> tuple[str, bool]:
    from confnav.scenes.workspaces import default_workspace

    ws = default_workspace()
    rows = [("robot", "start", "final", "dist", "arrived (s)", "path (m)", "body clear", "result")]
    ok = True
    for t in tracks.values():
        import numpy as np

        clear = (
            float(np.min(ws.clearance(np.asarray(t.path)))) - t.radius if t.path else float("nan")
        )
        good = t.arrived_at is not None and t.collided is None
        ok &= good
        result = (
            "COLLIDED" if t.collided else ("arrived" if good else f"FAILED ({t.reason or t.state})")
        )
        rows.append(
            (
                t.robot_id,
                f"({t.start.real:+.2f},{t.start.imag:+.2f})",
                f"({t.position.real:+.3f},{t.position.imag:+.3f})",
                f"{t.distance:.3f}",
                "-" if t.arrived_at is None else f"{t.arrived_at:.1f}",
                f"{t.length:.2f}",
                f"{clear:.3f}",
                result,
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines), ok


def run_demo(
    out: Path,
    timeout: float = 120.0,
    time_scale: float = 1.0,
    navfn: str = defaults.NAVFN,
    gain: float = defaults.GAIN,
    v_max: float = defaults.V_MAX,
    tolerance: float = defaults.GOAL_TOL,
    speed_law: str = defaults.SPEED_LAW,
    cache_dir: str | None = None,
    verbose: int = 0,
    live_port: int | None = None,
) -> int:
    from confnav.scenes.workspaces import DEFAULT_GOAL, DEFAULT_STARTS

    out.mkdir(parents=True, exist_ok=True)
    old_recordings = set(out.glob("demo*.mcap"))  # never overwritten: demo.1.mcap... follow
    starts = {f"r{i + 1}": z for i, z in enumerate(DEFAULT_STARTS)}
    tracks = {rid: Track(rid, z, DEFAULT_GOAL) for rid, z in starts.items()}
    tracks[UNICYCLE[0]] = Track(UNICYCLE[0], UNICYCLE[1], DEFAULT_GOAL, radius=UNICYCLE[3])
    sockdir = tempfile.mkdtemp(prefix="confnav-demo-")
    sock = f"unixsock-stream/{sockdir}/router.sock"
    launcher = Launcher(
        demo_config(sock, out, starts, time_scale, cache_dir, live_port), verbose=max(verbose, 1)
    )
    mon = DemoMonitor(tracks)
    t_start = time.monotonic()
    try:
        with stop_on_signals() as stop:
            print(
                f"confnav demo: starting router and 4 services (logs in {out / 'logs'})", flush=True
            )
            launcher.start()
            if live_port is not None:
                print(f"confnav demo: live view in Foxglove at ws://127.0.0.1:{live_port}")
            assert launcher.bus is not None
            bus, keys = launcher.bus, launcher.keys
            bus.subscribe(keys.any_robot("pose"), mon.on_pose)
            bus.subscribe(keys.any_robot("status"), mon.on_status)
            bus.subscribe(keys.any_robot("collision"), mon.on_collision)
            _spawn_unicycle(launcher)
            print(
                "confnav demo: waiting for the conformal map of the default workspace...",
                flush=True,
            )
            rev = wait_for_map(launcher, timeout, stop)
            print(
                f"confnav demo: map {rev[:12]} ready after {time.monotonic() - t_start:.1f} s;"
                " sending goals",
                flush=True,
            )
            mon.t0 = time.monotonic()
            base = Goal(
                robot_id=next(iter(starts)),
                ws_id=WS_ID,
                goal=(DEFAULT_GOAL.real, DEFAULT_GOAL.imag),
                navfn=navfn,  # type: ignore[arg-type]
                speed_law=speed_law,  # type: ignore[arg-type]
                gain=gain,
                v_max=v_max,
                tolerance=tolerance,
            )
            _send_goals(launcher, list(starts), base)
            _watch(launcher, mon, tracks, mon.t0 + timeout, stop)
            if stop.is_set():
                print("confnav demo: interrupted", flush=True)
    finally:
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)
    recordings = sorted(
        set(out.glob("demo*.mcap")) - old_recordings, key=lambda p: p.stat().st_mtime
    )
    return _report(out, recordings, mon, tracks)


def _spawn_unicycle(launcher: Launcher) -> None:
    """Ask the simulator for the demo's unicycle (:data:`UNICYCLE`: id, pose, body)."""
    assert launcher.bus is not None
    uid, uz, uth, urad, _ud = UNICYCLE
    spawn = SpawnRequest(
        robot_id=uid,
        ws_id=WS_ID,
        position=(uz.real, uz.imag),
        theta=uth,
        robot_radius=urad,
        drive="unicycle",
    )
    launcher.bus.publish(launcher.keys.sim("sim", "spawn"), encode(spawn))


def _send_goals(launcher: Launcher, robots: list[str], base: Goal) -> None:
    """The goal ``base`` to every point robot (stamped now), then to the unicycle with its
    body and look-ahead."""
    assert launcher.bus is not None
    bus, keys = launcher.bus, launcher.keys
    for rid in robots:
        goal = base.model_copy(update={"robot_id": rid, "stamp_ns": time.time_ns()})
        bus.publish(keys.robot(rid, "goal"), encode(goal))
    uid, _uz, _uth, urad, ud = UNICYCLE
    ugoal = goal.model_copy(
        update={"robot_id": uid, "robot_radius": urad, "drive": "unicycle", "lookahead": ud}
    )
    bus.publish(keys.robot(uid, "goal"), encode(ugoal))


def _watch(
    launcher: Launcher,
    mon: DemoMonitor,
    tracks: dict[str, Track],
    deadline: float,
    stop: threading.Event,
) -> None:
    """Until every robot is done, the deadline or a stop: check the services and print each
    robot's distance to the goal and state once a second."""
    next_print = 0.0
    while not stop.is_set() and time.monotonic() < deadline and not mon.done():
        launcher.check()
        now = time.monotonic()
        if now >= next_print:
            next_print = now + 1.0
            with mon.lock:
                parts = [f"{t.robot_id}: {t.distance:5.2f} m {_state(t)}" for t in tracks.values()]
            print(f"[{now - mon.t0:5.1f} s] " + " | ".join(parts), flush=True)
        stop.wait(0.1)


def _report(out: Path, recordings: list[Path], mon: DemoMonitor, tracks: dict[str, Track]) -> int:
    """The figure, the summary table and the verdict; 0 if every robot arrived without a
    collision."""
    png = figure_path(out, recordings)
    with mon.lock:
        plot_demo(tracks, png)
        table, ok = summary(tracks)
    print()
    print(table)
    print("arrived (s): seconds after the goals were sent (`confnav inspect` counts from the")
    print("first recorded message and also gives the time after each robot's goal)")
    print()
    print(f"recording: {', '.join(map(str, recordings)) or '-'}   plot: {png}")
    print("result:", "all robots arrived without collision" if ok else "FAILED")
    return 0 if ok else 1


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "demo", help="run the whole system on the default workspace with five robots"
    )
    p.add_argument("--out", default="out", help="output folder (default %(default)s)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds (default %(default)s)")
    p.add_argument("--time-scale", type=float, default=1.0, help=">1: faster than real time")
    p.add_argument("--navfn", default=defaults.NAVFN, choices=("harmonic", "kr"))
    p.add_argument("--speed-law", default=defaults.SPEED_LAW, choices=defaults.SPEED_LAWS)
    p.add_argument(
        "--gain",
        type=float,
        default=defaults.GAIN,
        help="1/s of the normalized law, K of theorem2 (default %(default)s)",
    )
    p.add_argument("--v-max", type=float, default=defaults.V_MAX, help="m/s")
    p.add_argument("--tolerance", type=float, default=defaults.GOAL_TOL, help="m")
    p.add_argument("--cache-dir", default=None, help="transform solution cache")
    p.add_argument(
        "--live",
        nargs="?",
        type=int,
        const=8765,
        default=None,
        metavar="PORT",
        help="serve the live scene to Foxglove on ws://127.0.0.1:PORT (default 8765)",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    return run_demo(
        Path(args.out),
        timeout=args.timeout,
        time_scale=args.time_scale,
        navfn=args.navfn,
        speed_law=args.speed_law,
        gain=args.gain,
        v_max=args.v_max,
        tolerance=args.tolerance,
        cache_dir=args.cache_dir,
        verbose=getattr(args, "verbose", 0),
        live_port=args.live,
    )
