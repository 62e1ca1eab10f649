"""``confnav replay FILE.mcap``: republish a recording onto Zenoh with its original timing.

Messages are sent in log-time order, by default under the separate prefix
``replay/{recorded prefix}`` (:data:`REPLAY_PREFIX`), so that a replay next to a running system
never drives its robots; ``live=True`` sends each to its recorded key (the channel topic), and
``prefix`` to the same key under another prefix. Message ``i`` goes out at
``t_start + (log_time_i - log_time_0) / speed`` on the monotonic clock (``speed=None``: as fast
as possible); payloads are the recorded bytes, unchanged. Puts use congestion control BLOCK
(no silent drops) and encoding ``application/json``.

Not replayed by default: liveliness keys (``{prefix}/alive/**``, tokens, not puts) and the
Foxglove visualisation channels (``{prefix}/viz/**``, made by the recorder, not Zenoh traffic).
``include``/``exclude`` take key expressions (``*`` one chunk, ``**`` any), matched against the
recorded topics; an explicit ``include`` overrides the default exclusions.

Before sending, replay waits up to ``wait_subscribers`` seconds until every replayed key has a
matching subscriber (Zenoh matching status), so a recorder or controller started just before
does not miss the first messages; keys nobody listens to are reported.

While it runs, replay also answers what a transform service answers (``serve_maps``, on by
default; :class:`RecordedMaps`): queries on ``ws/*/transform`` (a workspace's or an atlas
chart's ``TransformSolution``) and ``ws/*/atlas`` (``AtlasIndex``) under the replay prefix,
with the latest one the replay has sent (before it sends the first one: the first recorded),
and ``reply_err`` ``atlas: ...`` for a transform query on a workspace recorded as an atlas.
It declares the liveliness token of a transform service meanwhile, so a live controller
driven by the replay fetches its maps and atlases by query as from the real service (an
atlas recording needs that: the controller fetches charts by query only).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh
from confnav.services.bus import flush, key_matches
from confnav.services.keys import KeyError_, Keys

from confnav.errors import ConfnavError
from confnav.recording.reader import Recording, RecordingError
from confnav.recording.scene import is_viz_topic

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000


class ReplayError(ConfnavError):
    """Bad replay options (no topic selected, bad prefix, ...)."""


@dataclass
class ReplayReport:
    """Outcome of a replay: messages sent per key (after remapping), keys without subscribers,
    wall-clock duration and the largest lateness against the schedule (s)."""

    published: Counter[str] = field(default_factory=Counter)
    unmatched_keys: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0
    max_lateness_s: float = 0.0
    recorded_duration_s: float = 0.0
    interrupted: bool = False

    @property
    def total(self) -> int:
        return sum(self.published.values())

    def summary(self) -> str:
        lines = [
            f"replayed {self.total} messages on {len(self.published)} keys in "
            f"{self.wall_time_s:.3f} s (recorded span {self.recorded_duration_s:.3f} s, "
            f"max lateness {1e3 * self.max_lateness_s:.1f} ms)"
            + (" - interrupted" if self.interrupted else "")
        ]
        for key, n in sorted(self.published.items()):
            lines.append(f"  {n:>7}  {key}")
        if self.unmatched_keys:
            lines.append(f"no subscriber for: {', '.join(sorted(self.unmatched_keys))}")
        return "\n".join(lines)


INPUT_KINDS = (
    "ws/*/definition",
    "ws/*/transform",
    "ws/*/atlas",
    "robot/*/goal",
    "robot/*/pose",
    "sim/*/poses",  # PoseBatch (a simulator's poses all at once)
)
"""What drives a controller: with ``inputs_only`` a live controller recomputes the rest."""


def input_keyexprs(prefix: str) -> list[str]:
    """Key expressions of the controller's inputs under ``prefix`` (see :data:`INPUT_KINDS`)."""
    return [f"{prefix}/{kind}" for kind in INPUT_KINDS]


def select_topics(
    topics: Sequence[str],
    prefix: str,
    include: Sequence[str] = (),
    exclude: Sequence[str] = (),
    inputs_only: bool = False,
) -> list[str]:
    """Recorded topics to replay: ``include`` (default: all but alive/viz) minus ``exclude``;
    with ``inputs_only`` only the controller's inputs among them."""
    if inputs_only:
        inputs = input_keyexprs(prefix)
        chosen_inputs = select_topics(topics, prefix, inputs, exclude)
        if include:
            chosen_inputs = [t for t in chosen_inputs if any(key_matches(e, t) for e in include)]
        return chosen_inputs
    chosen = []
    for topic in topics:
        if include:
            if not any(key_matches(expr, topic) for expr in include):
                continue
        elif topic.startswith(f"{prefix}/alive/") or is_viz_topic(topic, prefix):
            continue
        if any(key_matches(expr, topic) for expr in exclude):
            continue
        chosen.append(topic)
    return chosen


def remap(topic: str, old_prefix: str, new_prefix: str | None) -> str:
    """``topic`` with its leading ``old_prefix`` replaced by ``new_prefix`` (None: unchanged)."""
    if new_prefix is None or new_prefix == old_prefix:
        return topic
    if topic.startswith(old_prefix + "/"):
        return new_prefix + topic[len(old_prefix) :]
    return f"{new_prefix}/{topic}"


def _matching(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches (the stubs say bool, zenoh 1.x returns MatchingStatus)."""
    status: object = publisher.matching_status
    return bool(getattr(status, "matching", status))


def _wait_matching(
    publishers: dict[str, zenoh.Publisher], timeout: float, stop: threading.Event
) -> list[str]:
    """Wait until each publisher has a matching subscriber; return the keys still unmatched."""
    deadline = time.monotonic() + timeout
    pending = dict(publishers)
    while pending and not stop.is_set():
        pending = {k: p for k, p in pending.items() if not _matching(p)}
        if not pending or time.monotonic() >= deadline:
            break
        time.sleep(0.01)
    return sorted(pending)


class RecordedMaps:
    """The recorded ``TransformSolution`` and ``AtlasIndex`` messages of a recording, served
    to queries under the replay's prefix (see the module docstring).

    Each key's messages are kept in log-time order; :meth:`sent` moves a key's answer to the
    message the replay has just sent on it.  Thread-safe (queries arrive on Zenoh threads and
    are answered from memory, without blocking).
    """

    KINDS = ("transform", "atlas")

    def __init__(self, rec: Recording, prefix: str) -> None:
        self.keys = Keys(prefix)
        self._lock = threading.Lock()
        self._messages: dict[str, list[tuple[int, bytes]]] = {}  # key -> (log time, payload)
        self._current: dict[str, tuple[int, bytes]] = {}  # key -> its answer now
        mine = [
            t
            for t in rec.topics()
            if any(key_matches(f"{rec.prefix}/ws/*/{k}", t) for k in self.KINDS)
        ]
        for msg in rec.iter_messages(mine) if mine else ():
            key = remap(msg.topic, rec.prefix, prefix)
            self._messages.setdefault(key, []).append((msg.log_time_ns, msg.data))
        self._current = {k: v[0] for k, v in self._messages.items()}
        self._sent: dict[str, int] = {}  # key -> index of the message sent last

    def __bool__(self) -> bool:
        return bool(self._messages)

    def sent(self, key: str) -> None:
        """The replay sent the next recorded message on ``key``: it answers from now on."""
        with self._lock:
            msgs = self._messages.get(key)
            if msgs is None:
                return
            i = self._sent.get(key, -1) + 1
            if i < len(msgs):
                self._sent[key] = i
                self._current[key] = msgs[i]

    def answer(self, keyexpr: str) -> list[tuple[str, bytes]]:
        """Replies to a query (raises :class:`ReplayError` with the ``reply_err`` text)."""
        with self._lock:
            found = sorted((k, v[1]) for k, v in self._current.items() if key_matches(keyexpr, k))
            if found or "*" in keyexpr:
                if not found:
                    raise ReplayError(f"no recorded map matches {keyexpr[:80]!r}")
                return found
            try:
                parsed = self.keys.parse(keyexpr)
            except KeyError_ as exc:
                raise ReplayError(f"bad key {keyexpr[:80]!r}: {exc}") from None
            atlas = self._current.get(self.keys.ws(parsed.ident, "atlas"))
        if parsed.kind == "transform" and atlas is not None:
            from confnav.atlas.wire import ATLAS_MARKER

            raise ReplayError(
                f"{ATLAS_MARKER} workspace {parsed.ident!r} is recorded as an atlas: "
                f"query ws/{parsed.ident}/atlas"
            )
        raise ReplayError(f"workspace {parsed.ident!r}: no recorded {parsed.kind}")

    def on_query(self, q: zenoh.Query) -> None:
        """Zenoh queryable callback: answer from memory (never blocks)."""
        try:
            for key, data in self.answer(str(q.key_expr)):
                q.reply(key, data, encoding=zenoh.Encoding.APPLICATION_JSON)
        except ReplayError as exc:
            q.reply_err(str(exc).encode())
        finally:
            q.drop()  # type: ignore[no-untyped-call]


REPLAY_PREFIX = "replay"
"""Default: a recording of prefix ``P`` is replayed under ``replay/P``."""


def _check_arguments(speed: float | None, live: bool, prefix: str | None) -> None:
    if speed is not None and not (speed > 0 and speed < float("inf")):
        raise ReplayError(f"speed must be a positive finite number, got {speed}")
    if live and prefix is not None:
        raise ReplayError("live (the recorded keys) and a prefix exclude each other")
    if prefix is not None:
        from confnav.services.keys import KeyError_, validate_prefix

        try:
            validate_prefix(prefix)
        except KeyError_ as exc:
            raise ReplayError(f"bad prefix: {exc}") from exc


def _serve_maps(session: zenoh.Session, maps: RecordedMaps, served: list[Any]) -> None:
    """Answer transform and atlas queries from the recording, as a transform service does
    (its liveliness token too); what is declared goes into ``served`` (undeclared at the
    end, also after a failure half-way)."""
    mk = maps.keys
    for kind in RecordedMaps.KINDS:  # not complete: a live service answers too
        served.append(session.declare_queryable(mk.any_ws(kind), maps.on_query, complete=False))
    zid = str(session.zid())
    served.append(session.liveliness().declare_token(mk.alive("transform", zid)))


def _declare_publishers(session: zenoh.Session, keys: list[str]) -> dict[str, zenoh.Publisher]:
    publishers: dict[str, zenoh.Publisher] = {}
    for key in keys:
        try:
            publishers[key] = session.declare_publisher(
                key,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except zenoh.ZError as exc:
            for pub in publishers.values():
                pub.undeclare()  # type: ignore[no-untyped-call]
            raise RecordingError(f"recorded topic {key!r} is not a Zenoh key: {exc}") from None
    return publishers


def _play(
    rec: Recording,
    topics: Sequence[str],
    keys: dict[str, str],
    publishers: dict[str, zenoh.Publisher],
    maps: RecordedMaps | None,
    speed: float | None,
    stop: threading.Event,
    on_message: Callable[[str, int], None] | None,
    report: ReplayReport,
) -> None:
    """Put the recorded messages of ``topics`` in log-time order, paced by ``speed`` (None:
    as fast as possible) from the first one; ``stop`` ends it early (``interrupted``)."""
    t_start = time.monotonic()
    t0_ns: int | None = None
    for msg in rec.iter_messages(topics):
        if stop.is_set():
            report.interrupted = True
            break
        if t0_ns is None:
            t0_ns = msg.log_time_ns
        if speed is not None:
            due = t_start + (msg.log_time_ns - t0_ns) / NS_PER_S / speed
            delay = due - time.monotonic()
            if delay > 0:
                if stop.wait(delay):
                    report.interrupted = True
                    break
            else:
                report.max_lateness_s = max(report.max_lateness_s, -delay)
        key = keys[msg.topic]
        if maps:
            maps.sent(key)  # answered from now on (before subscribers query it)
        publishers[key].put(msg.data)
        report.published[key] += 1
        if on_message is not None:
            on_message(key, msg.log_time_ns)
    report.wall_time_s = time.monotonic() - t_start


def replay(
    path: str | os.PathLike[str],
    conf: zenoh.Config,
    *,
    speed: float | None = 1.0,
    include: Sequence[str] = (),
    exclude: Sequence[str] = (),
    prefix: str | None = None,
    wait_subscribers: float = 1.0,
    stop: threading.Event | None = None,
    on_message: Callable[[str, int], None] | None = None,
    inputs_only: bool = False,
    live: bool = False,
    serve_maps: bool = True,
) -> ReplayReport:
    """Republish the recording ``path`` on a Zenoh session opened from ``conf``.

    Parameters
    ----------
    speed : playback rate (2.0: twice as fast); None: as fast as possible.
    include, exclude : key expressions selecting recorded topics (see module docstring).
    prefix : new key prefix replacing the recorded one (None: ``replay/{recorded prefix}``,
        or the recorded keys with ``live``).
    live : replay onto the recorded keys (drives the live system listening there).
    wait_subscribers : seconds to wait for subscribers on the replayed keys before sending.
    stop : set it to end the replay early (the report says ``interrupted``).
    on_message : called with (key, log_time_ns) after each put (progress, tests).
    inputs_only : replay only the controller's inputs (definitions, transforms, goals, poses),
        to drive a live controller with recorded data; combined with ``include``.
    serve_maps : answer transform and atlas queries from the recording while replaying, as
        a transform service (:class:`RecordedMaps`; its liveliness token declared meanwhile).
    """
    _check_arguments(speed, live, prefix)
    stop = stop or threading.Event()
    report = ReplayReport()
    with Recording(path) as rec:
        topics = select_topics(rec.topics(), rec.prefix, include, exclude, inputs_only)
        if not topics:
            raise ReplayError(
                f"{rec.path}: no recorded topic selected (recorded: {', '.join(rec.topics())})"
            )
        if prefix is None and not live:
            prefix = f"{REPLAY_PREFIX}/{rec.prefix}"
        keys = {t: remap(t, rec.prefix, prefix) for t in topics}
        report.recorded_duration_s = rec.duration_s
        maps = RecordedMaps(rec, rec.prefix if prefix is None else prefix) if serve_maps else None
        with zenoh.open(conf) as session:
            publishers: dict[str, zenoh.Publisher] = {}
            served: list[Any] = []  # queryables and token, undeclared at the end
            try:
                if maps:
                    _serve_maps(session, maps, served)
                publishers = _declare_publishers(session, sorted(set(keys.values())))
                if wait_subscribers > 0:
                    report.unmatched_keys = _wait_matching(publishers, wait_subscribers, stop)
                    for key in report.unmatched_keys:
                        logger.warning("no subscriber for %s", key)
                _play(rec, topics, keys, publishers, maps, speed, stop, on_message, report)
                flush(session)  # closing right after the last put could drop the queued tail
            finally:
                for pub in publishers.values():
                    pub.undeclare()  # type: ignore[no-untyped-call]
                for handle in served:
                    handle.undeclare()
    logger.info("replayed %d messages from %s", report.total, path)
    return report


__all__ = [
    "INPUT_KINDS",
    "RecordedMaps",
    "ReplayError",
    "ReplayReport",
    "input_keyexprs",
    "remap",
    "replay",
    "select_topics",
]
