"""Which robots a controller process drives: horizontal scale-out by robot key ranges.

Several controller processes share a fleet by each subscribing to its own part of the robot
key space, ``{prefix}/robot/{selector}/pose|goal``: Zenoh routes each robot's poses to the
one process whose key expression matches, so a process never decodes the others' traffic.
A selector (``--robots``) is a comma-separated list of items, each either

* a robot id (exact), or
* a Zenoh 1.x key-expression chunk: ``*`` (every robot) or a chunk with ``$*`` wildcards,
  which match any run of characters, possibly empty, inside one chunk (``a$*``: ids starting
  with ``a``; ``$*7``: ending in 7; ``b$*-x$*``). A bare ``*`` inside a chunk (``a*``) is not
  a Zenoh key expression and is rejected.

Robot ids never contain ``*`` or ``$`` (``confnav.services.keys.validate_id``), so a pattern
never matches by accident. Items must not overlap between processes (each robot driven by
one); the selectors of the benchmark and the documentation are disjoint by construction.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from typing import Any

from confnav.services.keys import KeyError_, Keys, validate_id

#: Up to this many exact ids get one subscription each; more share the ``*`` subscription and
#: are filtered in the process (a long id list is not a key range).
MAX_ID_SUBSCRIPTIONS = 8
_WILD = "$*"


def _is_pattern(item: str) -> bool:
    return item == "*" or _WILD in item


def _check_pattern(item: str) -> None:
    """A Zenoh chunk with ``$*`` wildcards whose literal parts are valid id characters."""
    literal = item.replace(_WILD, "")
    if _WILD + _WILD in item or item == _WILD:
        raise KeyError_(f"robot selector {item!r}: repeated or lone '$*' (use '*' for all)")
    if literal:
        try:
            validate_id(literal, "robot selector")
        except KeyError_:
            raise KeyError_(
                f"robot selector {item!r}: only '$*' wildcards and robot-id characters are "
                "allowed inside a chunk (a lone '*' selects every robot)"
            ) from None


def chunk_matches(pattern: str, chunk: str) -> bool:
    """Whether one key chunk matches a chunk pattern with ``$*`` wildcards (Zenoh 1.x
    semantics: ``$*`` matches any run of characters, possibly empty, within the chunk)."""
    return re.fullmatch(".*".join(re.escape(s) for s in pattern.split(_WILD)), chunk) is not None


class RobotSelector:
    """The robots of one controller process (see the module docstring).

    ``rid in selector`` says whether a robot belongs to it; :meth:`key_exprs` gives the key
    expressions to subscribe to for a key kind (``pose``, ``goal``).
    """

    def __init__(self, items: list[str]) -> None:
        if not items:
            raise KeyError_("empty robot selector")
        ids: set[str] = set()
        patterns: list[str] = []
        for raw in items:
            item = raw.strip()
            if not item:
                raise KeyError_("robot selector has an empty item")
            if _is_pattern(item):
                if item != "*":
                    _check_pattern(item)
                patterns.append(item)
            else:
                ids.add(validate_id(item, "robot id"))
        self.ids = frozenset(ids)
        self.patterns = tuple(dict.fromkeys(patterns))
        self._regex = (
            re.compile(
                "|".join(
                    ".+" if p == "*" else ".*".join(re.escape(s) for s in p.split(_WILD))
                    for p in self.patterns
                )
            )
            if self.patterns
            else None
        )

    @classmethod
    def parse(cls, text: str) -> RobotSelector:
        """From the ``--robots`` option: comma-separated ids and ``$*`` patterns."""
        return cls(text.split(","))

    def __contains__(self, rid: object) -> bool:
        if not isinstance(rid, str):
            return False
        if rid in self.ids:
            return True
        return self._regex is not None and self._regex.fullmatch(rid) is not None

    def key_exprs(self, keys: Keys, kind: str) -> list[str]:
        """Key expressions covering the selected robots' ``kind`` keys (no overlap)."""
        if "*" in self.patterns or len(self.ids) > MAX_ID_SUBSCRIPTIONS:
            return [keys.any_robot(kind)]  # filtered in the process by ``in``
        exprs = [f"{keys.prefix}/robot/{p}/{kind}" for p in self.patterns]
        return exprs + [keys.robot(r, kind) for r in sorted(self.ids)]

    def __repr__(self) -> str:
        return f"RobotSelector({','.join([*self.patterns, *sorted(self.ids)])!r})"


def robot_key_exprs(keys: Keys, kind: str, robots: Any) -> list[str]:
    """Subscriptions for a controller's ``robots`` (None: all; a set: all, filtered later)."""
    if isinstance(robots, RobotSelector):
        return robots.key_exprs(keys, kind)
    return [keys.any_robot(kind)]


def serialized(fn: Callable[..., None]) -> Callable[..., None]:
    """``fn`` behind one lock: handlers of several subscriptions run one at a time, as with
    a single subscription (each subscription has its own dispatcher thread)."""
    lock = threading.Lock()

    def call(*args: Any) -> None:
        with lock:
            fn(*args)

    return call


__all__ = [
    "MAX_ID_SUBSCRIPTIONS",
    "RobotSelector",
    "chunk_matches",
    "robot_key_exprs",
    "serialized",
]
