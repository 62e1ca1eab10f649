"""The latched state every recording segment starts with (recorder rotation, issue 10).

A recording split into segments must let a reader use any one segment alone: ``confnav replay``,
``inspect``, ``replay --check`` and the Foxglove scene need the workspace definitions, the
transform solutions (map coefficients), the atlas indexes and the goals in force, which were
published once, possibly hours before the segment began. :class:`LatchedState` keeps the latest
valid message of each such key (the kinds in :data:`LATCHED_KINDS`) as the recorder writes it,
and forgets what a later message withdraws (a workspace ``delete`` forgets that workspace's
keys, a robot ``cancel`` its goal). The recorder writes :meth:`LatchedState.entries` at the
start of each new segment, in the order they arrived (charts before the atlas index that names
them, a definition before its transform), on channels marked
:data:`~confnav.recording.layout.LATCHED_CHANNEL_METADATA` so that the copies are not counted
twice across segments. Pure bookkeeping: no Zenoh, no I/O.

An atlas's charts (``{ws}~c{i}``) are published before the index that names them, and a
progressive atlas publishes several revisions (docs/SLAM.md, "Progressive atlas"): a segment
that starts after a new revision's charts but before its index would latch the new charts
with the old index, whose charts it would no longer hold. So a chart replaced before its
atlas's next index keeps its previous message too (:meth:`LatchedState.entries` writes it
first), until that index arrives.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Final

from confnav.schemas import Message

#: (group, kind) of the keys whose latest message is state a reader needs, not an event.
LATCHED_KINDS: Final = frozenset(
    {
        ("ws", "definition"),
        ("ws", "transform"),
        ("ws", "atlas"),
        ("ws", "status"),
        ("robot", "goal"),
    }
)
#: (group, kind) of the messages that withdraw the latched state of their group and id.
FORGETTING_KINDS: Final = frozenset({("ws", "delete"), ("robot", "cancel")})
#: Entries kept at most (the oldest is dropped): bounds memory if ids churn without end.
MAX_ENTRIES: Final = 10_000


@dataclass(frozen=True)
class Latched:
    """The latest valid message on one key; times in integer ns since the Unix epoch."""

    key: str
    group: str
    ident: str
    model: type[Message]
    data: bytes
    log_time_ns: int
    publish_time_ns: int


class LatchedState:
    """Latest message per latched key, in arrival order (see the module docstring)."""

    def __init__(self, max_entries: int = MAX_ENTRIES) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be >= 1")
        self.max_entries = max_entries
        self._latest: OrderedDict[str, Latched] = OrderedDict()
        #: a chart's previous message, kept until its atlas's next index (module docstring)
        self._previous: OrderedDict[str, Latched] = OrderedDict()

    def __len__(self) -> int:
        return len(self._latest)

    def observe(
        self,
        key: str,
        group: str,
        ident: str,
        kind: str,
        model: type[Message],
        data: bytes,
        log_time_ns: int,
        publish_time_ns: int,
    ) -> None:
        """Take note of one valid message that was recorded on ``key`` (parsed into
        ``group``/``ident``/``kind``); anything not latched nor forgetting is ignored."""
        if (group, kind) in LATCHED_KINDS:
            old = self._latest.pop(key, None)  # re-inserted last: arrival order
            if group == "ws" and kind == "transform" and old is not None and _atlas_of(ident):
                self._previous.setdefault(key, old)  # the one the latched index may name
                if len(self._previous) > self.max_entries:
                    self._previous.popitem(last=False)
            elif group == "ws" and kind == "atlas":  # its charts are the latest ones now
                stale = [k for k, e in self._previous.items() if _atlas_of(e.ident) == ident]
                for k in stale:
                    del self._previous[k]
            self._latest[key] = Latched(
                key, group, ident, model, bytes(data), log_time_ns, publish_time_ns
            )
            if len(self._latest) > self.max_entries:
                self._latest.popitem(last=False)
        elif (group, kind) in FORGETTING_KINDS:  # a deleted workspace, a cancelled goal
            gone = [k for k, e in self._latest.items() if e.group == group and e.ident == ident]
            for k in gone:
                del self._latest[k]

    def entries(self) -> list[Latched]:
        """The latched messages, oldest arrival first (a replaced chart's previous message,
        kept for the index that names it, before all of them)."""
        return [*self._previous.values(), *self._latest.values()]


def _atlas_of(ident: str) -> str | None:
    """The atlas of a chart's workspace id ``{ws}~c{i}`` (:func:`confnav.atlas.wire.chart_ws_id`),
    None for any other id."""
    base, sep, i = ident.rpartition("~c")
    return base if sep and base and i.isdigit() else None


__all__ = ["FORGETTING_KINDS", "LATCHED_KINDS", "MAX_ENTRIES", "Latched", "LatchedState"]
