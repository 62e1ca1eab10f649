"""``confnav launch``: a router and the services as separate processes, from a TOML manifest.

Starts the router (a Python Zenoh session in router mode) unless the manifest points at an
existing one, then each service in order (``python -m confnav.cli serve NAME ...``, connected
as a client to the router), waiting for its liveliness token ``{prefix}/alive/{name}/*``.
A service that exits while running is restarted (with backoff, at most ``max_restarts``
times). Ctrl-C / SIGTERM stops the services in reverse order with SIGTERM (the recorder
finishes its file), then the router. Manifest format: see ``deploy/local.toml``.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import DEFAULT_PREFIX, Keys
from confnav.services.runtime import stop_on_signals

log = logging.getLogger(__name__)

SERVICES = ("transform", "controller", "simulator", "recorder", "ros2", "foxglove")

#: Environment of the service processes unless set already: one BLAS thread each. The
#: services get their parallelism from processes; a multi-threaded OpenBLAS waking its
#: threads for the tiny products of one control step stalls ~15 ms on a busy machine.
SINGLE_THREAD_BLAS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


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
        data = tomllib.loads(Path(path).read_text())
        return cls.from_dict(data, base=Path(path).parent)

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
    return [sys.executable, "-m", "confnav.cli", *args]


@dataclass
class _Proc:
    spec: ServiceSpec
    popen: subprocess.Popen[bytes]
    log: IO[bytes] | None
    restarts: int = 0
    started: float = 0.0


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
        popen = subprocess.Popen(
            argv,
            stdout=logf if logf else None,
            stderr=subprocess.STDOUT if logf else None,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,  # Ctrl-C reaches the launcher only: it stops them in order
        )
        log.info("started %s (pid %d)", label, popen.pid)
        return popen, logf

    def _verbosity(self) -> list[str]:
        return ["-" + "v" * self.verbose] if self.verbose else []

    def _service_argv(self, spec: ServiceSpec) -> list[str]:
        argv = confnav_command(*self._verbosity(), "serve", spec.name, "--mode", "client")
        for ep in self.config.connect:
            argv += ["--connect", ep]
        return [*argv, "--prefix", self.config.prefix, *spec.args]

    def start_router(self) -> None:
        if self.config.external_router:
            return
        argv = confnav_command(
            *self._verbosity(), "serve", "router", "--prefix", self.config.prefix
        )
        for ep in self.config.listen:
            argv += ["--listen", ep]
        if self.config.router_config:
            argv += ["--zenoh-config", self.config.router_config]
        popen, logf = self._spawn(argv, "router")
        self.router = _Proc(ServiceSpec("router"), popen, logf, started=time.monotonic())

    def connect(self) -> ZenohBus:
        """The launcher's own client session (retried until the router accepts it)."""
        deadline = time.monotonic() + self.config.startup_timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            if self.router is not None and self.router.popen.poll() is not None:
                raise RuntimeError(f"router exited with code {self.router.popen.returncode}")
            try:
                self.bus = ZenohBus(zenoh_config("client", connect=self.config.connect))
                return self.bus
            except Exception as exc:  # router not listening yet
                last = exc
                time.sleep(0.2)
        raise RuntimeError(f"cannot connect to the router at {self.config.connect}: {last}")

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
            raise RuntimeError(
                f"service {spec.label} did not come alive (exit code {popen.poll()}); "
                f"see {self.config.log_dir or 'its output'}"
            )
        log.info("%s is alive", spec.label)
        return proc

    def start(self) -> None:
        """Router, launcher session, then each service in order (waiting for liveliness)."""
        self.start_router()
        self.connect()
        for spec in self.config.services:
            self.start_service(spec)

    def check(self) -> None:
        """Restart services that exited (called periodically by :meth:`monitor`)."""
        if self._stopping:
            return
        if self.router is not None and self.router.popen.poll() is not None:
            log.error("router exited (code %s): restarting it", self.router.popen.returncode)
            self.start_router()
        for label, proc in list(self.procs.items()):
            code = proc.popen.poll()
            if code is None or self._stopping:
                continue
            if not proc.spec.restart or proc.restarts >= self.config.max_restarts:
                log.error("%s exited with code %s; not restarting", label, code)
                with self._lock:
                    self.procs.pop(label, None)
                continue
            log.warning("%s exited with code %s: restarting (%d)", label, code, proc.restarts + 1)
            if proc.log is not None:
                proc.log.close()
            time.sleep(min(0.2 * 2**proc.restarts, 5.0))
            self.restarts += 1
            spec = ServiceSpec(
                proc.spec.name, proc.spec.args, proc.spec.instance, proc.spec.restart, False
            )
            self.start_service(spec, proc.restarts + 1)

    def monitor(self, stop: threading.Event, period: float = 0.2) -> None:
        while not stop.wait(period):
            try:
                self.check()
            except Exception:
                log.exception("monitor failed")

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
        "launch", help="start a router and the services of a TOML manifest (deploy/local.toml)"
    )
    p.add_argument("config", help="TOML manifest")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    config = LaunchConfig.load(args.config)
    launcher = Launcher(config, verbose=getattr(args, "verbose", 0))
    with stop_on_signals() as ev:
        try:
            launcher.start()
            print(f"confnav launch: {len(launcher.procs)} services up; Ctrl-C to stop", flush=True)
            launcher.monitor(ev)
        finally:
            launcher.shutdown()
    return 0
