"""The one small interface services talk through: publish, subscribe, query, queryable,
liveliness. :class:`ZenohBus` is the real one; :class:`InMemoryBus` (on a shared
:class:`InMemoryNetwork`) runs service logic in one process for fast tests.

Threading contract (both implementations): handlers never run on a Zenoh thread. The Zenoh
callbacks only append to a queue (never block); one dispatcher thread per subscription /
queryable calls the handler in arrival order. Handlers may publish and query. A handler that
raises is logged and the subscription carries on. ``subscribe``/``subscribe_batch`` queues
never drop; ``subscribe_latest`` keeps only the newest sample per concrete key (bounded by
the number of keys; the superseded ones are reported, never silently lost).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

log = logging.getLogger(__name__)

Handler = Callable[[str, bytes], None]
"""Called with (concrete key, payload bytes)."""
QueryHandler = Callable[[str, bytes | None], list[tuple[str, bytes]]]
"""Called with (queried key expression, query payload); returns the replies as (concrete key,
payload) pairs, or raises :class:`QueryError` whose message goes back as ``reply_err``."""
BatchHandler = Callable[[list[tuple[str, bytes]]], None]
"""Called with every (key, payload) that is waiting, in arrival order (at least one)."""
LivelinessHandler = Callable[[str, bool], None]
"""Called with (token key, alive)."""


class QueryError(Exception):
    """Raised by a query handler: the message is sent back with ``reply_err``."""


@dataclass(frozen=True)
class Reply:
    """One reply to a query: ``payload`` on success, else ``error`` (the ``reply_err`` text)."""

    key: str
    payload: bytes | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class Closeable(Protocol):
    def close(self) -> None: ...


class Bus(Protocol):
    """What a service needs from the middleware."""

    @property
    def zid(self) -> str: ...

    def publish(self, key: str, payload: bytes) -> None: ...

    def subscribe(self, keyexpr: str, handler: Handler) -> Closeable: ...

    def subscribe_batch(
        self, keyexpr: str, handler: BatchHandler, max_batch: int = 1024, linger: float = 0.0
    ) -> Closeable: ...

    def subscribe_latest(
        self,
        keyexpr: str,
        handler: BatchHandler,
        on_dropped: Callable[[int], None] | None = None,
        max_keys: int = 100_000,
        linger: float = 0.0,
    ) -> Closeable: ...

    def query(
        self, selector: str, timeout: float = 2.0, payload: bytes | None = None
    ) -> list[Reply]: ...

    def queryable(
        self, keyexpr: str, handler: QueryHandler, complete: bool = True
    ) -> Closeable: ...

    def declare_token(self, key: str) -> Closeable: ...

    def subscribe_liveliness(self, keyexpr: str, handler: LivelinessHandler) -> Closeable: ...

    def alive(self, keyexpr: str, timeout: float = 1.0) -> list[str]: ...

    def close(self) -> None: ...


# ------------------------------------------------------------------------------------------
# dispatching
# ------------------------------------------------------------------------------------------
_STOP = object()


class _Dispatcher:
    """Unbounded FIFO + one daemon thread calling ``fn(item)`` for each item."""

    def __init__(
        self, name: str, fn: Callable[[Any], None], batch: int = 0, linger: float = 0.0
    ) -> None:
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._fn = fn
        self._batch = batch  # > 0: call fn with a list of up to this many waiting items
        self._linger = linger  # s to wait for more items after the first of a batch
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: Any) -> None:
        self._q.put(item)

    def pending(self) -> int:
        """Items waiting (approximate: the queue keeps changing)."""
        return self._q.qsize()

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is _STOP:
                return
            stop = False
            if self._batch:
                items = [item]
                until = time.monotonic() + self._linger
                while len(items) < self._batch:
                    try:
                        left = until - time.monotonic()
                        nxt = self._q.get(timeout=left) if left > 0 else self._q.get_nowait()
                    except queue.Empty:
                        break
                    if nxt is _STOP:
                        stop = True
                        break
                    items.append(nxt)
                item = items
            try:
                self._fn(item)
            except Exception:
                log.exception("handler failed in %s", self._thread.name)
            if stop:
                return

    def stop(self, timeout: float = 10.0) -> None:
        self._q.put(_STOP)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


class _LatestDispatcher:
    """Newest sample per key + one daemon thread calling ``fn(items)`` with every waiting
    (key, payload), in order of last arrival, ``linger`` s after the first one arrived. A
    sample that replaces a waiting one of the same key, or arrives while ``max_keys`` keys
    wait, is counted through ``on_dropped``."""

    def __init__(
        self,
        name: str,
        fn: Callable[[list[tuple[str, bytes]]], None],
        on_dropped: Callable[[int], None] | None,
        max_keys: int,
        linger: float = 0.0,
    ) -> None:
        self._fn = fn
        self._linger = linger
        self._on_dropped = on_dropped
        self._max_keys = max_keys
        self._waiting: dict[str, bytes] = {}
        self._cond = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: tuple[str, bytes]) -> None:
        key, payload = item
        with self._cond:
            dropped = self._waiting.pop(key, None) is not None
            if dropped or len(self._waiting) < self._max_keys:
                self._waiting[key] = payload  # re-inserted: ordered by last arrival
            else:
                dropped = True
            self._cond.notify()
        if dropped and self._on_dropped is not None:
            self._on_dropped(1)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._waiting and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
            if self._linger > 0:
                time.sleep(self._linger)
            with self._cond:
                items, self._waiting = list(self._waiting.items()), {}
            try:
                self._fn(items)
            except Exception:
                log.exception("handler failed in %s", self._thread.name)

    def stop(self, timeout: float = 10.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def pending(self) -> int:
        """Keys waiting."""
        return len(self._waiting)


class _Handle:
    def __init__(self, close: Callable[[], None], pending: Callable[[], int] | None = None) -> None:
        self._close = close
        #: Samples received and not yet handled, for a subscription's handle (else 0).
        self.pending: Callable[[], int] = pending or (lambda: 0)
        self._closed = False
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._close()


# ------------------------------------------------------------------------------------------
# Zenoh
# ------------------------------------------------------------------------------------------
def zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | None = None,
    multicast: bool = False,
) -> zenoh.Config:
    """A Zenoh config: explicit endpoints, multicast scouting off unless asked for."""
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


class _Subscriptions:
    """``subscribe``/``subscribe_batch`` for both buses, on top of their ``_subscribe``."""

    def _subscribe(self, keyexpr: str, disp: _Dispatcher | _LatestDispatcher) -> Closeable:
        raise NotImplementedError

    def subscribe(self, keyexpr: str, handler: Handler) -> Closeable:
        fn: Callable[[Any], None] = lambda item: handler(item[0], item[1])  # noqa: E731
        return self._subscribe(keyexpr, _Dispatcher(f"sub:{keyexpr}", fn))

    def subscribe_batch(
        self, keyexpr: str, handler: BatchHandler, max_batch: int = 1024, linger: float = 0.0
    ) -> Closeable:
        """Like :meth:`subscribe`, but the handler gets every waiting sample at once (at most
        ``max_batch``), waiting up to ``linger`` s after the first one for more."""
        return self._subscribe(keyexpr, _Dispatcher(f"sub:{keyexpr}", handler, max_batch, linger))

    def subscribe_latest(
        self,
        keyexpr: str,
        handler: BatchHandler,
        on_dropped: Callable[[int], None] | None = None,
        max_keys: int = 100_000,
        linger: float = 0.0,
    ) -> Closeable:
        """Like :meth:`subscribe_batch`, but only the newest waiting sample of each concrete
        key is delivered (a bounded queue: at most ``max_keys`` keys wait); every sample not
        delivered is counted through ``on_dropped``."""
        disp = _LatestDispatcher(f"latest:{keyexpr}", handler, on_dropped, max_keys, linger)
        return self._subscribe(keyexpr, disp)


FLUSH_KEY = "confnav_flush_barrier"
"""Key of the flush barrier's query; nothing answers it (see :func:`flush`)."""


def flush(session: zenoh.Session, timeout: float = 2.0) -> None:
    """Wait until the messages put so far on ``session`` have left this process.

    Zenoh queues puts in a transmission pipeline; closing the session right after the last put
    can drop the queued tail (measured: 100-200 of 20,000 back-to-back puts lost under load, both
    from a client of a router and from a peer). A query travels on the same link and priority
    behind those puts and the router answers it only after it has routed them, so a finished
    ``get`` is a barrier. Nothing answers :data:`FLUSH_KEY`; the reply is the router's final
    one, returned after one round trip.
    """
    try:
        for _ in session.get(FLUSH_KEY, timeout=timeout):
            pass
    except Exception:  # pragma: no cover - a closed or dead session has nothing to flush
        log.debug("flush failed", exc_info=True)


class ZenohBus(_Subscriptions):
    """:class:`Bus` over a Zenoh session that this object opens and closes.

    Use as a context manager (``with ZenohBus(conf) as bus``) so the session is always closed.
    Puts use congestion control BLOCK (reliable, no silent drops); never publish from a Zenoh
    callback (this class never does: handlers run on dispatcher threads).
    """

    def __init__(self, conf: zenoh.Config) -> None:
        self._session = zenoh.open(conf)
        self._zid = str(self._session.zid())
        self._lock = threading.Lock()
        self._handles: list[_Handle] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._closed = False

    @property
    def zid(self) -> str:
        return self._zid

    @property
    def session(self) -> zenoh.Session:
        return self._session

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _track(self, handle: _Handle) -> _Handle:
        with self._lock:
            self._handles.append(handle)
        return handle

    def publish(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            with self._lock:
                if self._closed:
                    return
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self._session.declare_publisher(
                        key,
                        encoding=zenoh.Encoding.APPLICATION_JSON,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                    if len(self._publishers) > 4096:  # bound the cache (many robots)
                        old = self._publishers.pop(next(iter(self._publishers)))
                        old.undeclare()  # type: ignore[no-untyped-call]
                    self._publishers[key] = pub
        pub.put(payload)

    def _subscribe(self, keyexpr: str, disp: _Dispatcher | _LatestDispatcher) -> Closeable:
        def on_sample(sample: zenoh.Sample) -> None:  # Zenoh thread: enqueue only
            disp.put((str(sample.key_expr), sample.payload.to_bytes()))

        sub = self._session.declare_subscriber(keyexpr, on_sample)

        def close() -> None:
            sub.undeclare()  # type: ignore[no-untyped-call]
            disp.stop()

        return self._track(_Handle(close, disp.pending))

    def query(
        self, selector: str, timeout: float = 2.0, payload: bytes | None = None
    ) -> list[Reply]:
        out: list[Reply] = []
        replies = self._session.get(selector, timeout=timeout, payload=payload)
        for rep in replies:
            if rep.ok is not None:
                out.append(Reply(str(rep.ok.key_expr), rep.ok.payload.to_bytes()))
            elif rep.err is not None:
                text = rep.err.payload.to_bytes().decode("utf-8", "replace")
                out.append(Reply(selector, None, text))
        return out

    def queryable(self, keyexpr: str, handler: QueryHandler, complete: bool = True) -> Closeable:
        """``complete``: this queryable answers for all of ``keyexpr`` (a query then reaches
        the nearest such one only); False for one holding a part (queries reach them all)."""

        def answer(q: zenoh.Query) -> None:
            key = str(q.key_expr)
            try:
                body = q.payload.to_bytes() if q.payload is not None else None
                replies = handler(key, body)
            except QueryError as exc:
                q.reply_err(str(exc).encode())
            except Exception as exc:  # a queryable that raises sends nothing: answer anyway
                log.exception("query handler failed for %s", key)
                q.reply_err(f"internal error: {exc}".encode())
            else:
                for rkey, data in replies:  # always concrete keys
                    q.reply(rkey, data, encoding=zenoh.Encoding.APPLICATION_JSON)
            finally:
                q.drop()  # type: ignore[no-untyped-call]

        disp = _Dispatcher(f"qbl:{keyexpr}", answer)
        qbl = self._session.declare_queryable(keyexpr, disp.put, complete=complete)

        def close() -> None:
            qbl.undeclare()  # type: ignore[no-untyped-call]
            disp.stop()

        return self._track(_Handle(close))

    def declare_token(self, key: str) -> Closeable:
        token = self._session.liveliness().declare_token(key)
        return self._track(_Handle(token.undeclare))

    def subscribe_liveliness(self, keyexpr: str, handler: LivelinessHandler) -> Closeable:
        disp = _Dispatcher(f"live:{keyexpr}", lambda item: handler(item[0], item[1]))

        def on_sample(sample: zenoh.Sample) -> None:
            disp.put((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        sub = self._session.liveliness().declare_subscriber(keyexpr, on_sample, history=True)

        def close() -> None:
            sub.undeclare()  # type: ignore[no-untyped-call]
            disp.stop()

        return self._track(_Handle(close))

    def alive(self, keyexpr: str, timeout: float = 1.0) -> list[str]:
        return sorted(
            str(r.ok.key_expr)
            for r in self._session.liveliness().get(keyexpr, timeout=timeout)
            if r.ok is not None
        )

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles = list(self._handles)
            pubs = list(self._publishers.values())
            self._publishers.clear()
        flush(self._session)  # the last puts (a final status, a stop command) reach the router
        for h in handles:
            try:
                h.close()
            except Exception:  # pragma: no cover - closing twice after session death
                log.debug("close failed", exc_info=True)
        for p in pubs:
            try:
                p.undeclare()  # type: ignore[no-untyped-call]
            except Exception:  # pragma: no cover
                log.debug("undeclare failed", exc_info=True)
        self._session.close()  # type: ignore[no-untyped-call]


# ------------------------------------------------------------------------------------------
# in memory
# ------------------------------------------------------------------------------------------
def key_matches(expr: str, key: str) -> bool:
    """Whether concrete ``key`` matches the key expression ``expr``: Zenoh's own rule
    (:meth:`zenoh.KeyExpr.intersects`; ``*`` one chunk, ``**`` any number, ``$*`` any run of
    characters within a chunk), so the in-memory bus routes exactly as a Zenoh session."""
    return bool(zenoh.KeyExpr.autocanonize(expr).intersects(zenoh.KeyExpr(key)))


@dataclass
class InMemoryNetwork:
    """A shared in-process 'network' for :class:`InMemoryBus` instances."""

    lock: threading.RLock = field(default_factory=threading.RLock)
    subs: list[tuple[str, _Dispatcher | _LatestDispatcher]] = field(default_factory=list)
    queryables: list[tuple[str, QueryHandler]] = field(default_factory=list)
    tokens: dict[str, int] = field(default_factory=dict)
    live_subs: list[tuple[str, _Dispatcher]] = field(default_factory=list)
    published: list[tuple[str, bytes]] = field(default_factory=list)

    def bus(self, name: str = "mem") -> InMemoryBus:
        return InMemoryBus(self, name)


class InMemoryBus(_Subscriptions):
    """:class:`Bus` on an :class:`InMemoryNetwork`: same threading contract, no sockets."""

    _count = 0

    def __init__(self, net: InMemoryNetwork, name: str = "mem") -> None:
        InMemoryBus._count += 1
        self._net = net
        self._zid = f"{name}{InMemoryBus._count}"
        self._handles: list[_Handle] = []

    @property
    def zid(self) -> str:
        return self._zid

    def __enter__(self) -> InMemoryBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def publish(self, key: str, payload: bytes) -> None:
        with self._net.lock:
            self._net.published.append((key, bytes(payload)))
            targets = [d for e, d in self._net.subs if key_matches(e, key)]
        for d in targets:
            d.put((key, bytes(payload)))

    def _subscribe(self, keyexpr: str, disp: _Dispatcher | _LatestDispatcher) -> Closeable:
        entry = (keyexpr, disp)
        with self._net.lock:
            self._net.subs.append(entry)

        def close() -> None:
            with self._net.lock:
                self._net.subs.remove(entry)
            disp.stop()

        h = _Handle(close, disp.pending)
        self._handles.append(h)
        return h

    def query(
        self, selector: str, timeout: float = 2.0, payload: bytes | None = None
    ) -> list[Reply]:
        with self._net.lock:
            targets = [(e, h) for e, h in self._net.queryables if key_matches(e, selector)]
        out: list[Reply] = []
        for _e, h in targets:
            try:
                out.extend(Reply(k, data) for k, data in h(selector, payload))
            except QueryError as exc:
                out.append(Reply(selector, None, str(exc)))
            except Exception as exc:
                out.append(Reply(selector, None, f"internal error: {exc}"))
        return out

    def queryable(self, keyexpr: str, handler: QueryHandler, complete: bool = True) -> Closeable:
        entry = (keyexpr, handler)  # every matching queryable answers here
        with self._net.lock:
            self._net.queryables.append(entry)

        def close() -> None:
            with self._net.lock:
                self._net.queryables.remove(entry)

        h = _Handle(close)
        self._handles.append(h)
        return h

    def declare_token(self, key: str) -> Closeable:
        self._token_change(key, +1)
        h = _Handle(lambda: self._token_change(key, -1))
        self._handles.append(h)
        return h

    def _token_change(self, key: str, delta: int) -> None:
        with self._net.lock:
            n = self._net.tokens.get(key, 0) + delta
            if n > 0:
                self._net.tokens[key] = n
            else:
                self._net.tokens.pop(key, None)
            changed = (delta > 0 and n == 1) or (delta < 0 and n <= 0)
            targets = [d for e, d in self._net.live_subs if key_matches(e, key)] if changed else []
        for d in targets:
            d.put((key, delta > 0))

    def subscribe_liveliness(self, keyexpr: str, handler: LivelinessHandler) -> Closeable:
        disp = _Dispatcher(f"memlive:{keyexpr}", lambda item: handler(item[0], item[1]))
        entry = (keyexpr, disp)
        with self._net.lock:
            self._net.live_subs.append(entry)
            current = [k for k in self._net.tokens if key_matches(keyexpr, k)]
        for k in current:
            disp.put((k, True))

        def close() -> None:
            with self._net.lock:
                self._net.live_subs.remove(entry)
            disp.stop()

        h = _Handle(close)
        self._handles.append(h)
        return h

    def alive(self, keyexpr: str, timeout: float = 1.0) -> list[str]:
        with self._net.lock:
            return sorted(k for k in self._net.tokens if key_matches(keyexpr, k))

    def close(self) -> None:
        handles, self._handles = self._handles, []
        for h in handles:
            h.close()
