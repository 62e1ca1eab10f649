"""Shared fixtures for the service tests: Zenoh over unix sockets in short temp dirs (multicast
off, sessions always closed), a fake solver and an exact stand-in map (a circle domain maps to
itself by the identity), and polling helpers."""

from __future__ import annotations

import os

# One BLAS thread: the suite's processes share 2 cores, and a threaded BLAS stalls small
# products for milliseconds under oversubscription (measured 20x slower tests); and the
# service processes the tests start run one BLAS thread (services/launcher.py), so a test
# that compares their maps bit for bit with one solved here needs the same (a threaded
# product rounds differently). Set before numpy is imported: nothing in the pytest
# configuration may import confnav (the AccuracyWarning filter is added per test below,
# not in pyproject.toml, whose filterwarnings imported the solver, and numpy, before this).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import shutil
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from confnav.schemas import (
    CollisionEvent,
    Pose,
    RobotStatus,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.keys import Keys

REPO = Path(__file__).resolve().parents[1]


def wait_for(pred: Callable[[], Any], timeout: float = 5.0, interval: float = 0.02) -> Any:
    """Poll ``pred`` until truthy; return its value or fail the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(interval)


# ------------------------------------------------------------------------------------------
# an exact map for fast tests: the circle domain itself, T = identity
# ------------------------------------------------------------------------------------------
class IdentityMap:
    """The identity of a circle domain (|w|<1 minus disks): an exact conformal map of the
    domain onto itself, with the ConformalMap surface the controller uses."""

    def __init__(self, centers: list[complex], radii: list[float]) -> None:
        self.centers = np.asarray(centers, dtype=complex)
        self.radii = np.asarray(radii, dtype=float)

    def _inside(self, z: np.ndarray) -> np.ndarray:
        ok = np.abs(z) < 1
        for c, r in zip(self.centers, self.radii, strict=True):
            ok &= np.abs(z - c) > r
        return ok

    def T_and_dT(self, z: Any) -> tuple[np.ndarray, np.ndarray]:
        z = np.asarray(z, dtype=complex)
        ok = self._inside(z)
        return np.where(ok, z, np.nan), np.where(ok, 1.0 + 0j, np.nan)

    def T(self, z: Any) -> np.ndarray:
        return self.T_and_dT(z)[0]


def fake_solve(defn_json: str) -> dict[str, Any]:
    """Stand-in for ``solve_definition``: the 'map' of a workspace whose obstacles are given
    by their first vertex as a circle centre (radius 0.1); revision = content of the input."""
    import hashlib

    d = WorkspaceDefinition.model_validate_json(defn_json)
    centers = [(o[0][0], o[0][1]) for o in d.obstacles]
    radii = [0.1] * len(centers)
    rev = hashlib.sha256(repr((centers, radii)).encode()).hexdigest()
    return {
        "revision": rev,
        "anchor": (0.0, 0.0),
        "centers": centers,
        "radii": radii,
        "diagnostics": {
            "sweeps": 1,
            "error_estimate": 0.0,
            "wall_time": 0.0,
            "tol": d.tol,
            "boundary_residual": 0.0,
            "tol_met": True,
        },
        "workspace_hash": "fake-" + rev,
        "coefficients": {"centers": [list(c) for c in centers], "radii": radii},
    }


def identity_loader(sol: Any) -> IdentityMap:
    c = sol.coefficients
    return IdentityMap([complex(x, y) for x, y in c["centers"]], list(c["radii"]))


def square_definition(ws_id: str, holes: list[tuple[float, float]] = ()) -> WorkspaceDefinition:  # type: ignore[assignment]
    """A square room [-0.7, 0.7]^2 with small square holes at the given points."""
    obstacles = [[(x, y), (x + 0.05, y), (x + 0.05, y + 0.05), (x, y + 0.05)] for x, y in holes]
    return WorkspaceDefinition(
        ws_id=ws_id,
        outer=[(-0.7, -0.7), (0.7, -0.7), (0.7, 0.7), (-0.7, 0.7)],
        obstacles=obstacles,
    )


# ------------------------------------------------------------------------------------------
# Zenoh
# ------------------------------------------------------------------------------------------
@pytest.fixture
def sockdir() -> Iterator[Path]:
    """A short temp dir for unix sockets (paths must stay under ~100 characters)."""
    d = Path(tempfile.mkdtemp(prefix="cnz", dir="/tmp"))
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def zenoh_endpoint(sockdir: Path) -> str:
    return f"unixsock-stream/{sockdir}/router.sock"


@pytest.fixture
def zenoh_router(zenoh_endpoint: str) -> Iterator[str]:
    """An in-process Zenoh router listening on a unix socket; yields its endpoint."""
    import zenoh
    from confnav.services.bus import zenoh_config

    with zenoh.open(zenoh_config("router", listen=[zenoh_endpoint])):
        yield zenoh_endpoint


@pytest.fixture
def make_bus(zenoh_router: str) -> Iterator[Callable[[], Any]]:
    """Factory of ZenohBus clients of the router; all closed at teardown."""
    from confnav.services.bus import ZenohBus, zenoh_config

    buses: list[ZenohBus] = []

    def make() -> ZenohBus:
        bus = ZenohBus(zenoh_config("client", connect=[zenoh_router]))
        buses.append(bus)
        return bus

    yield make
    for b in reversed(buses):
        b.close()


@pytest.fixture
def mem_net() -> Any:
    from confnav.services.bus import InMemoryNetwork

    return InMemoryNetwork()


def confnav_cmd(*args: str) -> list[str]:
    """Command line running the confnav CLI with this interpreter."""
    return [sys.executable, "-m", "confnav", *args]


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


class HolonomicRobot:
    """A holonomic robot integrated on the test's side, as a simulator or a real robot would be:
    it publishes its pose at 20 Hz on real Zenoh and follows the newest command, keeping every
    position it passed through and every command it received."""

    def __init__(
        self, bus: Any, rid: str, start: tuple[float, float], keys: Keys | None = None
    ) -> None:
        self.keys = keys if keys is not None else Keys()
        self.bus, self.rid, self.z = bus, rid, complex(*start)
        self.v = 0j
        self.seq = 0
        self.period = 0.05
        self.path: list[complex] = [self.z]
        self.cmds: list[VelocityCommand] = []
        self.stop = threading.Event()
        self.lock = threading.Lock()
        bus.subscribe(self.keys.robot(rid, "cmd_vel"), self._on_cmd)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _on_cmd(self, key: str, payload: bytes) -> None:
        c = decode(VelocityCommand, payload)
        with self.lock:
            self.v = complex(*c.linear)
            self.cmds.append(c)

    def moving_commands(self) -> list[VelocityCommand]:
        with self.lock:
            return [c for c in self.cmds if abs(complex(*c.linear)) > 0]

    def _run(self) -> None:
        while not self.stop.wait(self.period):
            with self.lock:
                self.z += self.v * self.period
                self.path.append(self.z)
                self.seq += 1
                p = Pose(robot_id=self.rid, stamp_ns=time.time_ns(), seq=self.seq,
                         x=self.z.real, y=self.z.imag)  # fmt: skip
            self.bus.publish(self.keys.robot(self.rid, "pose"), encode(p))


class RobotWatch:
    """Every robot's statuses and the collision events seen on a bus (an end-to-end test's
    observer); ``lock`` guards both (they are appended from subscriber threads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.status: dict[str, list[RobotStatus]] = defaultdict(list)
        self.collisions: list[CollisionEvent] = []

    def attach(self, bus: Any, keys: Any) -> None:
        """Subscribe to ``{prefix}/robot/*/status`` and ``.../collision`` on ``bus``."""
        bus.subscribe(keys.any_robot("status"), self._on_status)
        bus.subscribe(keys.any_robot("collision"), self._on_collision)

    def _on_status(self, key: str, payload: bytes) -> None:
        s = decode(RobotStatus, payload)
        with self.lock:
            self.status[s.robot_id].append(s)

    def _on_collision(self, key: str, payload: bytes) -> None:
        c = decode(CollisionEvent, payload)
        with self.lock:
            self.collisions.append(c)


@dataclass
class LaunchedSystem:
    """Services started by :func:`launched_system` and a client bus on their router."""

    launcher: Any  # confnav.services.launcher.Launcher
    bus: Any  # confnav.services.bus.ZenohBus

    @property
    def keys(self) -> Any:
        return self.launcher.keys

    def shutdown(self) -> dict[str, int | None]:
        """Close the test's bus, then stop every service: exit codes by service name (a
        recorder that exits 0 finished its file). Safe to call again."""
        self.bus.close()
        return dict(self.launcher.shutdown())


@contextmanager
def launched_system(
    services: list[Any], tmp: Path, prefix: str = "cn", startup_timeout: float = 60
) -> Iterator[LaunchedSystem]:
    """Real service processes (``ServiceSpec`` list) behind a router on a unix socket, the
    launcher's restart monitor running, and a client bus connected to it.

    On exit (also on failure) the monitor stops, the bus closes, every service is stopped
    and the socket directory removed. Logs go to ``tmp/logs``.
    """
    from confnav.services.bus import ZenohBus, zenoh_config
    from confnav.services.launcher import LaunchConfig, Launcher

    sockdir = tempfile.mkdtemp(prefix=prefix, dir="/tmp")  # short: unix socket paths are
    sock = f"unixsock-stream/{sockdir}/router.sock"  # limited to 108 bytes
    cfg = LaunchConfig(
        listen=[sock],
        services=services,
        startup_timeout=startup_timeout,
        log_dir=str(tmp / "logs"),
    )
    launcher = Launcher(cfg, verbose=1)
    stop = threading.Event()
    monitor = threading.Thread(target=launcher.monitor, args=(stop,), daemon=True)
    bus = None
    try:
        launcher.start()
        monitor.start()
        bus = ZenohBus(zenoh_config("client", connect=[sock]))
        yield LaunchedSystem(launcher, bus)
    finally:
        stop.set()
        if bus is not None:
            bus.close()
        launcher.shutdown()
        shutil.rmtree(sockdir, ignore_errors=True)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A solve that misses its tol where a test did not expect it is a failure, not a
    warning (a carried-levels regression once showed only as this warning in a passing
    run). Added per test, after this module set the BLAS threads (see the top)."""
    mark = pytest.mark.filterwarnings("error::confnav.conformal.solver.AccuracyWarning")
    for item in items:
        item.add_marker(mark)
