"""What every service process shares: Zenoh command-line options, the liveliness token,
periodic health, counters, and running until SIGINT/SIGTERM with the session always closed."""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import select
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from types import FrameType
from typing import TypeVar

from confnav.schemas import DecodeError, Message, ServiceHealth, WorkspaceDelete, decode, encode
from confnav.services.bus import Bus, Closeable, ZenohBus, zenoh_config
from confnav.services.keys import DEFAULT_PREFIX, KeyError_, Keys

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """``--mode --listen --connect --zenoh-config --prefix`` (the same for every service)."""
    g = parser.add_argument_group("zenoh")
    g.add_argument(
        "--mode", default="client", choices=("client", "peer", "router"), help="zenoh session mode"
    )
    g.add_argument(
        "--listen", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on"
    )
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="router endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument("--zenoh-config", default=None, metavar="FILE", help="zenoh JSON5 config")
    g.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix (default %(default)s)")


def bus_from_args(args: argparse.Namespace, retry_for: float = 30.0) -> ZenohBus:
    """Open the session; a client retries for ``retry_for`` s while the router comes up."""
    deadline = time.monotonic() + retry_for
    while True:
        conf = zenoh_config(args.mode, args.listen, args.connect, args.zenoh_config)
        try:
            return ZenohBus(conf)
        except Exception as exc:
            if time.monotonic() > deadline:
                raise
            log.info("cannot open the Zenoh session yet (%s): retrying", exc)
            time.sleep(0.3)


class Service:
    """Base of the services: liveliness token ``{prefix}/alive/{name}/{zid}``, counters, and a
    health message on ``{prefix}/health/{name}/{zid}`` every ``health_period`` seconds.

    Subclasses implement :meth:`_start` (declare subscriptions etc.) and may extend
    :meth:`stop` and :meth:`health_detail`.
    """

    name = "service"

    def __init__(self, bus: Bus, keys: Keys | None = None, health_period: float = 1.0) -> None:
        self.bus = bus
        self.keys = keys or Keys()
        self.counters: Counter[str] = Counter()
        self._counter_lock = threading.Lock()
        self._handles: list[Closeable] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._health_period = health_period
        self._t0 = time.monotonic()

    # lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        self._start()
        self._handles.append(self.bus.declare_token(self.keys.alive(self.name, self.bus.zid)))
        if self._health_period > 0:
            self.spawn(self._health_loop, "health")
        log.info("%s service started (zid %s)", self.name, self.bus.zid)

    def _start(self) -> None:
        raise NotImplementedError

    def spawn(self, fn: Callable[[], None], what: str) -> threading.Thread:
        t = threading.Thread(target=fn, name=f"{self.name}:{what}", daemon=True)
        t.start()
        self._threads.append(t)
        return t

    def stop(self) -> None:
        self._stop.set()
        for h in reversed(self._handles):
            try:
                h.close()
            except Exception:
                log.debug("closing handle failed", exc_info=True)
        self._handles.clear()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def __enter__(self) -> Service:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # counters and health ----------------------------------------------------------------
    def count(self, what: str, n: int = 1) -> None:
        with self._counter_lock:
            self.counters[what] += n

    def decode_keyed(
        self, model: type[M], key: str, payload: bytes, id_field: str, what: str
    ) -> tuple[str, M] | None:
        """``(id, message)`` of a ``model`` message on ``key``, whose ``id_field`` must equal
        the key's id; None (counted as ``rejected`` and logged) if the key or the message is
        malformed or they disagree."""
        try:
            ident = self.keys.parse(key).ident
            msg = decode(model, payload)
            if getattr(msg, id_field) != ident:
                named = getattr(msg, id_field)
                raise DecodeError("invalid_input", f"{what} on {key} names {named!r}")
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected %s on %s: %s", what, key, exc)
            return None
        return ident, msg

    def workspace_to_delete(self, key: str, payload: bytes) -> str | None:
        """The workspace id of a ``WorkspaceDelete`` on ``{prefix}/ws/{ws}/delete``, or None."""
        self.count("deletes_received")
        got = self.decode_keyed(WorkspaceDelete, key, payload, "ws_id", "delete")
        return None if got is None else got[0]

    def health_detail(self) -> tuple[str, str]:
        """(state, detail) for the health message; override to report degradation."""
        return "ok", ""

    def health_gauges(self) -> dict[str, int]:
        """Current values for the health message (queue depths...); override to add some."""
        return {}

    def health(self) -> ServiceHealth:
        state, detail = self.health_detail()
        with self._counter_lock:
            counters = dict(self.counters)
        return ServiceHealth(
            service=self.name,
            zid=self.bus.zid,
            stamp_ns=time.time_ns(),
            state="ok" if state == "ok" else "degraded",
            uptime_s=time.monotonic() - self._t0,
            counters=counters,
            detail=detail[:4000],
            gauges=self.health_gauges(),
        )

    def _health_loop(self) -> None:
        key = self.keys.health(self.name, self.bus.zid)
        while not self._stop.wait(self._health_period):
            try:
                self.bus.publish(key, encode(self.health()))
            except Exception:
                log.exception("publishing health failed")


# ------------------------------------------------------------------------------------------
# children die with their supervisor
# ------------------------------------------------------------------------------------------
SUPERVISOR_ENV = "CONFNAV_SUPERVISOR"
"""Set by a supervisor (``confnav launch``, ``confnav demo``) for its children:
``PID:FD[:d]``: the supervisor's pid, the read end of its lifeline pipe, and ``d`` when the
child was started by the supervisor's main thread (then the kernel's parent-death signal is
safe to use: it fires when the thread that forked the child ends, not only the process)."""

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


class Lifeline:
    """The supervisor's side: a pipe whose write end only the supervisor holds.

    Every child gets the read end (``pass_fds``) and :data:`SUPERVISOR_ENV`. When the
    supervisor's process ends, however it ends (``kill -9`` included), the kernel closes the
    write end and each child's read sees end-of-file: :func:`watch_supervisor` then stops the
    child as SIGTERM does (a recorder still finishes its file)."""

    def __init__(self) -> None:
        self.read_fd, self.write_fd = os.pipe()  # both close on exec: passed explicitly
        self.pid = os.getpid()

    def child_env(self) -> dict[str, str]:
        main = threading.current_thread() is threading.main_thread()
        return {SUPERVISOR_ENV: f"{self.pid}:{self.read_fd}" + (":d" if main else "")}

    def close(self) -> None:
        for fd in (self.read_fd, self.write_fd):
            with suppress(OSError):
                os.close(fd)
        self.read_fd = self.write_fd = -1


def _set_parent_death_signal(sig: int) -> bool:
    """Linux ``prctl(PR_SET_PDEATHSIG, sig)`` (True if set); elsewhere nothing (False)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def watch_supervisor(
    environ: dict[str, str] | os._Environ[str] | None = None, grace: float = 20.0
) -> threading.Thread | None:
    """In a child of a supervisor (:data:`SUPERVISOR_ENV` set): stop when the supervisor dies.

    Three ways, each enough alone: the kernel's parent-death signal (Linux ``prctl``, SIGTERM,
    when the supervisor's main thread started this child), end-of-file on the lifeline pipe,
    and the parent pid changing (polled every 0.5 s: portable, and covers a lifeline whose
    write end leaked into another process). On either of the last two this process sends
    itself SIGTERM (the services stop cleanly on it) and exits hard after ``grace`` s if that
    did not end it. The variable is removed, so grandchildren do not inherit it. Returns the
    watching thread (None when not supervised)."""
    env = os.environ if environ is None else environ
    spec = env.pop(SUPERVISOR_ENV, None)
    if not spec:
        return None
    try:
        pid_s, fd_s, *flags = spec.split(":")
        pid, fd = int(pid_s), int(fd_s)
    except ValueError:
        log.warning("ignoring malformed %s=%r", SUPERVISOR_ENV, spec)
        return None
    if "d" in flags:
        _set_parent_death_signal(signal.SIGTERM)

    def gone(why: str) -> None:
        log.warning("supervisor (pid %d) %s: stopping", pid, why)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace)
        log.error("still running %g s after the supervisor ended: exiting", grace)
        os._exit(1)

    def watch() -> None:
        while True:
            if os.getppid() != pid:
                return gone("is gone")
            try:
                ready, _, _ = select.select([fd], [], [], 0.5)
                if ready and os.read(fd, 1) == b"":
                    return gone("closed the lifeline")
            except (OSError, ValueError):  # no such fd (not a pipe from a supervisor)
                time.sleep(0.5)

    t = threading.Thread(target=watch, name="supervisor-watch", daemon=True)
    t.start()
    return t


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM (previous handlers restored afterwards)."""
    ev = threading.Event()

    def handler(signum: int, frame: FrameType | None) -> None:
        log.info("signal %d: stopping", signum)
        ev.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield ev
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def run_until_signal(make: Callable[[Bus, Keys], Service], args: argparse.Namespace) -> int:
    """Open the session, start the service, wait for SIGINT/SIGTERM, stop, close. Exit code."""
    keys = Keys(args.prefix)
    with stop_on_signals() as ev, bus_from_args(args) as bus:
        service = make(bus, keys)
        service.start()
        try:
            while not ev.wait(0.5):
                pass
        finally:
            service.stop()
    return 0
