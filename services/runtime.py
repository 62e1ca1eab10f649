"""What every service process shares: Zenoh command-line options, the liveliness token,
periodic health, counters, and running until SIGINT/SIGTERM with the session always closed."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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
