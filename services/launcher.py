"""``confnav launch``: a router and the services as separate processes, from a TOML manifest.

Starts the router (a Python Zenoh session in router mode) unless the manifest points at an
existing one, then each service in order (``python -m confnav serve NAME ...``, connected
as a client to the router), waiting for its liveliness token ``{prefix}/alive/{name}/*``.

Before starting anything it refuses (:class:`LaunchError`, one line, exit 1) when a router
endpoint is already taken, so that its services never join another system's router; its own
router gets a fresh Zenoh id, and the launcher waits for that router's liveliness token before
starting a service. A process that exits while running (the router included) is restarted
after a backoff (0.5 s, doubling, at most 10 s), at most ``max_restarts`` times; a router
that is given up on (or whose endpoint was taken meanwhile) stops the launch with exit 1.
Ctrl-C / SIGTERM stops the services in reverse order with SIGTERM (the recorder finishes its
file), then the router. Manifest format: see ``deploy/local.toml``.
"""

from __future__ import annotations

import argparse
import errno
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import DEFAULT_PREFIX, Keys
from confnav.services.runtime import Lifeline, stop_on_signals

from confnav.errors import ConfnavError

log = logging.getLogger(__name__)

SERVICES = ("transform", "controller", "simulator", "recorder", "ros2", "foxglove")

#: Environment of the service processes unless set already: one BLAS thread each. The
#: services get their parallelism from processes; a multi-threaded OpenBLAS waking its
#: threads for the tiny products of one control step stalls ~15 ms on a busy machine.
SINGLE_THREAD_BLAS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class LaunchError(ConfnavError, RuntimeError):
    """The system cannot be launched or kept running (endpoint taken, a process not coming
    up, the router given up on)."""


def endpoint_in_use(endpoint: str) -> bool:
    """Whether something already listens on a Zenoh ``tcp``/``tls``/``ws``/``udp``/``quic``
    endpoint (a bind test with ``SO_REUSEADDR``, as Zenoh binds) or ``unixsock-stream``
    endpoint (the socket file accepts a connection). Other kinds: False (Zenoh reports)."""
    proto, _, addr = endpoint.split("#", 1)[0].split("?", 1)[0].partition("/")
    if proto == "unixsock-stream":
        if not os.path.exists(addr):
            return False
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            try:
                sock.connect(addr)
            except OSError:
                return False  # a stale file: nobody listens
            return True
    if proto not in ("tcp", "tls", "ws", "udp", "quic"):
        return False
    host, _, port = addr.rpartition(":")
    kind = socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(host.strip("[]"), int(port), type=kind)
    except (OSError, ValueError):
        return False  # not resolvable: the router reports it
    for family, stype, _proto, _name, sockaddr in infos:
        with socket.socket(family, stype) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(sockaddr)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    return True
    return False


def backoff_s(restarts: int) -> float:
    """Wait before restart number ``restarts + 1``: 0.5 s, doubling, at most 10 s."""
    return float(min(0.5 * 2**restarts, 10.0))


@dataclass
class ServiceSpec:
    name: str  # service kind: transform | controller | simulator | recorder
    args: list[str] = field(default_factory=list)
    instance: str = ""  # label for logs (default: name)
    restart: bool = True
    wait: bool = True  # wait for its liveliness before starting the next one

    @property
    def label(self) -> str:
        return self.instance or self.name


@dataclass
class LaunchConfig:
    prefix: str = DEFAULT_PREFIX
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    router_config: str | None = None
    external_router: list[str] = field(default_factory=list)  # connect here, start none
    services: list[ServiceSpec] = field(default_factory=list)
    startup_timeout: float = 60.0
    stop_timeout: float = 10.0
    max_restarts: int = 5
    log_dir: str | None = None

    @property
    def connect(self) -> list[str]:
        return self.external_router or self.listen

    @classmethod
    def load(cls, path: str | Path) -> LaunchConfig:
        """Read a TOML manifest; a missing, unreadable or invalid one is a :class:`LaunchError`."""
        try:
            data = tomllib.loads(Path(path).read_text())
        except OSError as exc:
            raise LaunchError(f"cannot read manifest {path}: {exc.strerror or exc}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise LaunchError(f"manifest {path} is not valid TOML: {exc}") from None
        try:
            return cls.from_dict(data, base=Path(path).parent)
        except (KeyError, TypeError, ValueError) as exc:
            raise LaunchError(f"manifest {path}: {exc}") from None

    @classmethod
    def from_dict(cls, data: dict[str, Any], base: Path | None = None) -> LaunchConfig:
        router = data.get("router", {})
        services = []
        for s in data.get("service", []):
            if s.get("name") not in SERVICES:
                raise ValueError(f"unknown service {s.get('name')!r}; choose from {SERVICES}")
            if not s.get("enabled", True):  # kept in the manifest, not started
                continue
            services.append(
                ServiceSpec(
                    name=s["name"],
                    args=[str(a) for a in s.get("args", [])],
                    instance=str(s.get("instance", "")),
                    restart=bool(s.get("restart", True)),
                    wait=bool(s.get("wait", True)),
                )
            )
        rc = router.get("config")
        if rc and base is not None and not Path(rc).is_absolute() and not Path(rc).exists():
            rc = str(base / rc)
        return cls(
            prefix=data.get("prefix", DEFAULT_PREFIX),
            listen=list(router.get("listen", ["tcp/127.0.0.1:7447"])),
            router_config=rc,
            external_router=list(router.get("connect", [])),
            services=services,
            startup_timeout=float(data.get("startup_timeout", 60.0)),
            stop_timeout=float(data.get("stop_timeout", 10.0)),
            max_restarts=int(data.get("max_restarts", 5)),
            log_dir=data.get("log_dir"),
        )


def confnav_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "confnav", *args]


@dataclass
class _Proc:
    spec: ServiceSpec
    popen: subprocess.Popen[bytes]
    log: IO[bytes] | None
    restarts: int = 0
    started: float = 0.0
    restart_at: float | None = None  # exited: restart at this monotonic time


class Launcher:
    """Runs a :class:`LaunchConfig`: ``start()``, ``monitor(stop_event)``, ``shutdown()``."""

    def __init__(self, config: LaunchConfig, verbose: int = 0) -> None:
        self.config = config
        self.keys = Keys(config.prefix)
        self.verbose = verbose
        self.router: _Proc | None = None
        self.procs: dict[str, _Proc] = {}
        self.bus: ZenohBus | None = None
        self._stopping = False
        self.restarts = 0
        self._lock = threading.Lock()
        #: Zenoh id given to the router this launcher starts (its services must reach it)
        self.router_id = "a" + secrets.token_hex(7)
        self.failed: str | None = None  # why the launch cannot go on (set by check())
        #: children stop by themselves when this process ends, even by kill -9
        self.lifeline = Lifeline()

    # processes ---------------------------------------------------------------------------
    def _open_log(self, label: str) -> IO[bytes] | None:
        if not self.config.log_dir:
            return None
        d = Path(self.config.log_dir)
        d.mkdir(parents=True, exist_ok=True)
        return open(d / f"{label}.log", "ab")

    def _spawn(
        self, argv: list[str], label: str
    ) -> tuple[subprocess.Popen[bytes], IO[bytes] | None]:
        logf = self._open_log(label)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.update({k: v for k, v in SINGLE_THREAD_BLAS.items() if k not in os.environ})
        env.update(self.lifeline.child_env())
        popen = subprocess.Popen(
            argv,
            stdout=logf if logf else None,
            stderr=subprocess.STDOUT if logf else None,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,  # Ctrl-C reaches the launcher only: it stops them in order
            pass_fds=(self.lifeline.read_fd,),
        )
        log.info("started %s (pid %d)", label, popen.pid)
        return popen, logf

    def _verbosity(self) -> list[str]:
        """``-v`` (INFO) at least when the output goes to log files: they are for reading
        afterwards; on the launcher's terminal only warnings unless asked."""
        level = max(self.verbose, 1) if self.config.log_dir else self.verbose
        return ["-" + "v" * level] if level else []

    def _service_argv(self, spec: ServiceSpec) -> list[str]:
        argv = confnav_command(*self._verbosity(), "serve", spec.name, "--mode", "client")
        for ep in self.config.connect:
            argv += ["--connect", ep]
        return [*argv, "--prefix", self.config.prefix, *spec.args]

    def check_endpoints(self) -> None:
        """Raise :class:`LaunchError` if a router endpoint of the manifest is taken."""
        if self.config.external_router:
            return
        for ep in self.config.listen:
            if endpoint_in_use(ep):
                raise LaunchError(
                    f"router endpoint {ep} is already in use (another confnav launch or "
                    "Zenoh router?): stop it or change [router] listen"
                )

    def start_router(self, restarts: int = 0) -> None:
        if self.config.external_router:
            return
        argv = confnav_command(
            *self._verbosity(), "serve", "router", "--prefix", self.config.prefix
        )
        for ep in self.config.listen:
            argv += ["--listen", ep]
        if self.config.router_config:
            argv += ["--zenoh-config", self.config.router_config]
        argv += ["--id", self.router_id]
        popen, logf = self._spawn(argv, "router")
        self.router = _Proc(ServiceSpec("router"), popen, logf, restarts, time.monotonic())

    def connect(self) -> ZenohBus:
        """The launcher's own client session (retried until the router accepts it); with a
        router of its own, waits for that router's liveliness token (never another's)."""
        deadline = time.monotonic() + self.config.startup_timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            if self.router is not None and self.router.popen.poll() is not None:
                raise LaunchError(
                    f"router exited with code {self.router.popen.returncode}"
                    + (f"; see {self.config.log_dir}/router.log" if self.config.log_dir else "")
                )
            try:
                if self.bus is None:
                    self.bus = ZenohBus(zenoh_config("client", connect=self.config.connect))
                if self.router is None or self._own_router_alive():
                    return self.bus
            except Exception as exc:  # router not listening yet
                last = exc
            time.sleep(0.2)
        raise LaunchError(f"cannot connect to the router at {self.config.connect}: {last}")

    def _own_router_alive(self) -> bool:
        assert self.bus is not None
        return bool(self.bus.alive(self.keys.alive("router", self.router_id), 1.0))

    def alive_zids(self, name: str) -> set[str]:
        assert self.bus is not None
        return {k.rsplit("/", 1)[-1] for k in self.bus.alive(self.keys.alive_of(name), 1.0)}

    def wait_alive(self, proc: _Proc, before: set[str], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if proc.popen.poll() is not None:
                return False
            if self.alive_zids(proc.spec.name) - before:
                return True
            time.sleep(0.1)
        return False

    def start_service(self, spec: ServiceSpec, restarts: int = 0) -> _Proc:
        before = self.alive_zids(spec.name) if self.bus else set()
        popen, logf = self._spawn(self._service_argv(spec), spec.label)
        proc = _Proc(spec, popen, logf, restarts, time.monotonic())
        with self._lock:
            self.procs[spec.label] = proc
        if spec.wait and not self.wait_alive(proc, before, self.config.startup_timeout):
            raise LaunchError(
                f"service {spec.label} did not come alive (exit code {popen.poll()}); "
                f"see {self.config.log_dir or 'its output'}"
            )
        log.info("%s is alive", spec.label)
        return proc

    def start(self) -> None:
        """Endpoint check, router, launcher session (on the own router), then each service in
        order (waiting for liveliness). Raises :class:`LaunchError`."""
        self.check_endpoints()
        self.start_router()
        self.connect()
        for spec in self.config.services:
            self.start_service(spec)

    def _exited(self, label: str, proc: _Proc, code: int, now: float) -> bool:
        """Handle an exited process; True when it is due for a restart now."""
        if proc.restart_at is None:
            wait = backoff_s(proc.restarts)
            proc.restart_at = now + wait
            log.warning(
                "%s exited with code %s: restarting in %.1f s (%d/%d)",
                label,
                code,
                wait,
                proc.restarts + 1,
                self.config.max_restarts,
            )
            if proc.log is not None:
                proc.log.close()
                proc.log = None
        return now >= proc.restart_at

    def check(self) -> None:
        """Restart processes that exited, after their backoff, at most ``max_restarts`` times
        each (called periodically by :meth:`monitor`; never blocks on a backoff). Sets
        :attr:`failed` when the router is given up on."""
        if self._stopping or self.failed:
            return
        now = time.monotonic()
        router = self.router
        if router is not None and (code := router.popen.poll()) is not None:
            if router.restarts >= self.config.max_restarts:
                self.failed = f"router exited with code {code} after {router.restarts} restarts"
            elif self._exited("router", router, code, now):
                if any(endpoint_in_use(ep) for ep in self.config.listen):
                    self.failed = (
                        f"router endpoint {self.config.listen} was taken by another process "
                        "while the router was down"
                    )
                else:
                    self.restarts += 1
                    self.start_router(router.restarts + 1)
            if self.failed:
                log.error("%s: stopping", self.failed)
                return
        for label, proc in list(self.procs.items()):
            code = proc.popen.poll()
            if code is None or self._stopping:
                continue
            if not proc.spec.restart or proc.restarts >= self.config.max_restarts:
                log.error("%s exited with code %s; not restarting", label, code)
                with self._lock:
                    self.procs.pop(label, None)
                continue
            if not self._exited(label, proc, code, now):
                continue
            self.restarts += 1
            spec = ServiceSpec(
                proc.spec.name, proc.spec.args, proc.spec.instance, proc.spec.restart, False
            )
            self.start_service(spec, proc.restarts + 1)

    def status(self) -> str:
        """The real state: the router (own process and its liveliness token) and, per
        service, whether its process runs and its liveliness token is there."""
        if self.router is None:
            router = f"external router {','.join(self.config.connect)}"
        else:
            up = self.router.popen.poll() is None and self.bus is not None
            up = up and self._own_router_alive()
            router = f"router {','.join(self.config.listen)} {'up' if up else 'DOWN'}"
        with self._lock:
            procs = list(self.procs.values())
        running: Counter[str] = Counter(p.spec.name for p in procs if p.popen.poll() is None)
        alive = {n: min(c, len(self.alive_zids(n))) for n, c in running.items()}
        down = [
            p.spec.label
            for p in procs
            if p.popen.poll() is not None or alive.get(p.spec.name, 0) == 0
        ]
        total = len(self.config.services)
        text = f"{router}; {sum(alive.values())}/{total} services alive"
        return text + (f" (down: {', '.join(down)})" if down else "")

    def monitor(self, stop: threading.Event, period: float = 0.2) -> None:
        """Call :meth:`check` every ``period`` s until ``stop`` is set or the launch failed."""
        while not stop.wait(period):
            try:
                self.check()
            except Exception:
                log.exception("monitor failed")
            if self.failed:
                return

    def shutdown(self) -> dict[str, int | None]:
        """SIGTERM the services in reverse order, then the router; return the exit codes."""
        self._stopping = True
        codes: dict[str, int | None] = {}
        for label, proc in reversed(list(self.procs.items())):
            codes[label] = _terminate(proc.popen, self.config.stop_timeout)
            if proc.log is not None:
                proc.log.close()
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        if self.router is not None:
            codes["router"] = _terminate(self.router.popen, self.config.stop_timeout)
            if self.router.log is not None:
                self.router.log.close()
        self.lifeline.close()
        log.info("all stopped: %s", codes)
        return codes


def _terminate(popen: subprocess.Popen[bytes], timeout: float) -> int | None:
    if popen.poll() is None:
        popen.send_signal(signal.SIGTERM)
        try:
            popen.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("pid %d did not stop in %g s: killing it", popen.pid, timeout)
            popen.kill()
            popen.wait(5.0)
    return popen.returncode


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "launch",
        help="start a router and the services of a TOML manifest (deploy/local.toml)",
        description="Start a Zenoh router (unless the manifest names one) and each service of "
        "the manifest as its own process, in order, each waiting for the previous one's "
        "liveliness; restart a process that exits (with a backoff); Ctrl-C or SIGTERM stops "
        "them in reverse order. Each process logs at INFO to LOG_DIR/NAME.log when the "
        "manifest sets log_dir (-v: DEBUG). The processes stop by themselves if the launcher "
        "dies (even by kill -9).",
    )
    p.add_argument("config", help="TOML manifest")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    config = LaunchConfig.load(args.config)
    launcher = Launcher(config, verbose=getattr(args, "verbose", 0))
    with stop_on_signals() as ev:
        try:
            launcher.start()
            print(f"confnav launch: {launcher.status()}; Ctrl-C to stop", flush=True)
            launcher.monitor(ev)
        finally:
            launcher.shutdown()
    if launcher.failed:
        raise LaunchError(launcher.failed)
    return 0
