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
            self._latest.pop(key, None)  # re-inserted last: arrival order
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
        """The latched messages, oldest arrival first."""
        return list(self._latest.values())


__all__ = ["FORGETTING_KINDS", "LATCHED_KINDS", "MAX_ENTRIES", "Latched", "LatchedState"]
