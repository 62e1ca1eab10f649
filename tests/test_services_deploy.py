"""deploy/: zenoh configs parse (zenoh rejects unknown keys), manifests load, and
``confnav launch`` starts everything, restarts a crashed service and stops cleanly on Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import zenoh
from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import Keys
from confnav.services.launcher import LaunchConfig
from conftest import REPO, confnav_cmd, subprocess_env, wait_for
from mcap.reader import make_reader

from confnav.geometry import Workspace

DEPLOY = REPO / "deploy"


@pytest.mark.parametrize("path", sorted(DEPLOY.rglob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_are_valid(path: Path) -> None:
    conf = zenoh.Config.from_file(str(path))
    assert '"enabled":false' in conf.get_json("scouting/multicast").replace(" ", "")


@pytest.mark.parametrize("path", sorted(DEPLOY.rglob("*.toml")), ids=lambda p: p.name)
def test_manifests_load(path: Path) -> None:
    cfg = LaunchConfig.load(path)
    assert cfg.services and cfg.connect
    if cfg.router_config:
        assert Path(cfg.router_config).exists()


def test_manifest_rejects_unknown_service() -> None:
    with pytest.raises(ValueError, match="unknown service"):
        LaunchConfig.from_dict({"service": [{"name": "teleporter"}]})


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_launch_restarts_a_crashed_service_and_stops_on_ctrl_c(
    tmp_path: Path, sockdir: Path
) -> None:
    room = tmp_path / "room.json"
    Workspace([(-1, -1), (1, -1), (1, 1), (-1, 1)], [[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2)]]).save(
        room
    )
    sock = f"unixsock-stream/{sockdir}/r.sock"
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        f"""
log_dir = "{tmp_path / "logs"}"
[router]
listen = ["{sock}"]
[[service]]
name = "recorder"
args = ["--out", "{tmp_path / "launch.mcap"}"]
[[service]]
name = "transform"
args = ["--workspace", "room={room}"]
[[service]]
name = "controller"
[[service]]
name = "simulator"
args = ["--workspace", "room={room}", "--robot", "r1=room:0.8,0.8"]
"""
    )
    proc = subprocess.Popen(
        confnav_cmd("-v", "launch", str(manifest)),
        env=subprocess_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    keys = Keys()
    try:
        time.sleep(1.0)
        bus = wait_for(lambda: _try_bus(sock), timeout=30, interval=0.3)
        with bus:
            for name in ("recorder", "transform", "controller", "simulator"):
                wait_for(lambda name=name: bus.alive(keys.alive_of(name)), timeout=60, interval=0.2)
            [old] = bus.alive(keys.alive_of("controller"))
            pid = _pid_of(proc.pid, "controller")
            os.kill(pid, signal.SIGKILL)
            # restarted: a new controller session comes alive
            wait_for(
                lambda: bus.alive(keys.alive_of("controller")) not in ([], [old]),
                timeout=60,
                interval=0.2,
            )
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in the launcher's terminal
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, out.decode()[-3000:]
    assert b"restarting" in out
    with open(tmp_path / "launch.mcap", "rb") as f:
        assert make_reader(f).get_summary() is not None  # recorder finished its file


def _try_bus(sock: str) -> ZenohBus | None:
    try:
        return ZenohBus(zenoh_config("client", connect=[sock]))
    except Exception:
        return None


def _pid_of(parent: int, label: str) -> int:
    """The pid of the launcher's child running ``serve <label>`` (from /proc)."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent and b"serve" in cmd and label.encode() in cmd:
            return int(d.name)
    raise AssertionError(f"no {label} child of {parent}")


def test_cli_registers_the_service_commands() -> None:
    from confnav.cli.app import build_parser

    parser = build_parser()
    for argv in (
        ["launch", "deploy/local.toml"],
        ["demo", "--out", "x", "--time-scale", "2"],
        ["schemas", "export", "d"],
        ["serve", "transform", "--workspace", "a=builtin:default", "--cache-dir", "c"],
        ["serve", "controller", "--robots", "r1,r2", "--linger-ms", "1"],
        ["serve", "simulator", "--robot", "r1=w:0,0", "--time-scale", "4"],
        ["serve", "recorder", "--out", "f.mcap", "--foxglove"],
        ["serve", "router", "--listen", "tcp/127.0.0.1:7447"],
    ):
        args = parser.parse_args(argv)
        assert callable(args.func), argv


def test_endpoint_in_use_sees_tcp_and_unix_listeners(sockdir: Path) -> None:
    import socket

    from confnav.services.launcher import endpoint_in_use

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.listen()
        assert endpoint_in_use(f"tcp/127.0.0.1:{port}")
        assert endpoint_in_use(f"tls/127.0.0.1:{port}")
    assert not endpoint_in_use(f"tcp/127.0.0.1:{port}")
    path = sockdir / "u.sock"
    assert not endpoint_in_use(f"unixsock-stream/{path}")
    with socket.socket(socket.AF_UNIX) as u:
        u.bind(str(path))
        u.listen()
        assert endpoint_in_use(f"unixsock-stream/{path}")
    assert not endpoint_in_use(f"unixsock-stream/{path}")  # a stale file: nobody listens


def _manifest(tmp_path: Path, sock: str, body: str, max_restarts: int = 5) -> Path:
    m = tmp_path / "m.toml"
    m.write_text(
        f'log_dir = "{tmp_path / "logs"}"\nmax_restarts = {max_restarts}\n'
        f'[router]\nlisten = ["{sock}"]\n{body}'
    )
    return m


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_launch_refuses_a_taken_router_endpoint(tmp_path: Path, zenoh_router: str) -> None:
    """Another system's router holds the endpoint: one-line error, exit 1, nothing started."""
    manifest = _manifest(tmp_path, zenoh_router, '[[service]]\nname = "controller"\n')
    res = subprocess.run(
        confnav_cmd("launch", str(manifest)),
        env=subprocess_env(),
        capture_output=True,
        text=True,
        timeout=50,
    )
    assert res.returncode == 1
    assert res.stderr.strip().count("\n") == 0, res.stderr
    assert "already in use" in res.stderr and zenoh_router in res.stderr
    assert not (tmp_path / "logs").exists()  # no process was started


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_launch_honours_max_restarts_with_backoff(tmp_path: Path, sockdir: Path) -> None:
    """A service that always crashes is restarted max_restarts times, with growing waits, and
    the status line says it is down; a router killed more than max_restarts times stops the
    launch with exit 1 (instead of being restarted forever)."""
    sock = f"unixsock-stream/{sockdir}/r.sock"
    body = '[[service]]\nname = "controller"\nargs = ["--no-such-flag"]\nwait = false\n'
    manifest = _manifest(tmp_path, sock, body, max_restarts=2)
    proc = subprocess.Popen(
        confnav_cmd("launch", str(manifest)),
        env=subprocess_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None
        lines: list[str] = []
        while "not restarting" not in "".join(lines):
            line = proc.stdout.readline().decode()
            assert line, "".join(lines)
            lines.append(line)
        text = "".join(lines)
        assert "0/1 services alive (down: controller)" in text
        assert "restarting in 0.5 s (1/2)" in text and "restarting in 1.0 s (2/2)" in text
        assert "(3/2)" not in text
        for kill in range(3):  # the router: killed 3 times with max_restarts = 2
            pid = _pid_of(proc.pid, "router")
            os.kill(pid, signal.SIGKILL)
            if kill < 2:  # restarted after its backoff
                wait_for(lambda pid=pid: _router_pid(proc.pid) not in (None, pid), 30, 0.1)
        out, _err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text += out.decode()
    assert proc.returncode == 1, text[-3000:]
    assert "router exited with code -9 after 2 restarts" in text


def _router_pid(parent: int) -> int | None:
    try:
        return _pid_of(parent, "router")
    except AssertionError:
        return None


def _children(parent: int) -> dict[int, str]:
    """pid -> command line of the processes whose parent is ``parent`` (from /proc)."""
    out: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent:
            out[int(d.name)] = cmd
    return out


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie awaiting its reaper does not count)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


@pytest.mark.integration
@pytest.mark.timeout(120)
@pytest.mark.parametrize("how", ["main-thread", "monitor-thread"])
def test_children_die_with_a_killed_launcher(tmp_path: Path, sockdir: Path, how: str) -> None:
    """``kill -9`` of ``confnav launch``: router, recorder, transform, controller and simulator
    all exit by themselves (issue 26 item 14), the recorder with a finished file (they stop as
    on SIGTERM). ``monitor-thread``: the same for a service the launcher restarted (started by
    a thread, where the kernel's parent-death signal does not apply: the lifeline does)."""
    room = tmp_path / "room.json"
    Workspace([(-1, -1), (1, -1), (1, 1), (-1, 1)], [[(0.2, -0.2), (0.5, -0.2), (0.5, 0.2)]]).save(
        room
    )
    sock = f"unixsock-stream/{sockdir}/r.sock"
    body = f"""
[[service]]
name = "recorder"
args = ["--out", "{tmp_path / "launch.mcap"}"]
[[service]]
name = "transform"
args = ["--workspace", "room={room}"]
[[service]]
name = "controller"
[[service]]
name = "simulator"
args = ["--workspace", "room={room}", "--robot", "r1=room:0.8,0.8"]
"""
    manifest = _manifest(tmp_path, sock, body)
    proc = subprocess.Popen(
        confnav_cmd("launch", str(manifest)),
        env=subprocess_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    kids: dict[int, str] = {}
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().decode()  # "confnav launch: ... 4/4 services alive"
        assert "4/4 services alive" in line, line + proc.stdout.read().decode()
        if how == "monitor-thread":
            pid = _pid_of(proc.pid, "controller")
            os.kill(pid, signal.SIGKILL)  # restarted by the launcher's monitor
            wait_for(lambda: _has_child(proc.pid, "controller", pid), timeout=30, interval=0.1)
        kids = _children(proc.pid)
        names = " ".join(kids.values())
        for name in ("router", "recorder", "transform", "controller", "simulator"):
            assert f"serve {name}" in names, names
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        wait_for(lambda: not any(_running(p) for p in kids), timeout=30, interval=0.1)
    finally:
        for p in kids:  # never leave them behind, whatever failed
            if _running(p):
                os.kill(p, signal.SIGKILL)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    log = (tmp_path / "logs" / "recorder.log").read_text()
    assert "signal 15: stopping" in log or "supervisor" in log, log[-2000:]
    # launched without -v, the log files still say what happened (INFO), not only warnings
    for name in ("router", "transform", "controller", "simulator"):
        assert " INFO " in (tmp_path / "logs" / f"{name}.log").read_text(), name
    if how == "monitor-thread":  # no parent-death signal: the lifeline stopped it, and it says so
        log = (tmp_path / "logs" / "controller.log").read_text()
        assert f"supervisor (pid {proc.pid})" in log, log[-2000:]
    with open(tmp_path / "launch.mcap", "rb") as f:
        assert make_reader(f).get_summary() is not None  # stopped cleanly: file finished


def _has_child(parent: int, label: str, not_pid: int) -> bool:
    try:
        return _pid_of(parent, label) != not_pid
    except AssertionError:
        return False
