"""Zenoh key layout of confnav (docs/METHOD.md section 1).

Every key starts with a configurable prefix (default ``confnav``)::

    {prefix}/ws/{ws}/definition        WorkspaceDefinition (put; transform service subscribes)
    {prefix}/ws/{ws}/transform         TransformSolution (put on change + queryable)
    {prefix}/ws/{ws}/status            TransformStatus (solving / solved / failed)
    {prefix}/ws/{ws}/atlas             AtlasIndex (put on change + queryable; charts on
                                       {prefix}/ws/{ws}~c{i}/transform)
    {prefix}/ws/{ws}/movers            Movers (moving obstacles that are not robots)
    {prefix}/robot/{r}/goal            Goal
    {prefix}/robot/{r}/pose            Pose
    {prefix}/robot/{r}/cmd_vel         VelocityCommand
    {prefix}/robot/{r}/status          RobotStatus (controller)
    {prefix}/robot/{r}/collision       CollisionEvent (simulator)
    {prefix}/sim/{sim}/spawn           SpawnRequest
    {prefix}/sim/{sim}/control         SimControl (pause / resume / reset)
    {prefix}/sim/{sim}/poses           PoseBatch (optional: all of a simulator's poses at once)
    {prefix}/sim/{sim}/cmd_vel         CommandBatch (a controller's answers to a PoseBatch)
    {prefix}/health/{service}/{zid}    ServiceHealth
    {prefix}/alive/{service}/{zid}     liveliness token (no payload)

Ids are validated: non-empty, at most 64 characters, none of ``* $ # ? /`` nor whitespace,
and not starting with ``@`` (verbatim chunks are not matched by ``**``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

from confnav.schemas.messages import ID_PATTERN, MAX_ID_LENGTH

DEFAULT_PREFIX: Final = "confnav"
_ID_RE = re.compile(ID_PATTERN)

WS_KINDS: Final = ("definition", "delete", "transform", "status", "atlas", "movers")
ROBOT_KINDS: Final = ("goal", "cancel", "pose", "cmd_vel", "status", "collision")
SIM_KINDS: Final = ("spawn", "control", "poses", "cmd_vel")


class KeyError_(ValueError):
    """An id or key that does not fit the confnav key layout."""


def validate_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a valid key chunk for an id, else raise :class:`KeyError_`."""
    if not isinstance(value, str) or not value:
        raise KeyError_(f"{what} must be a non-empty string")
    if len(value) > MAX_ID_LENGTH:
        raise KeyError_(f"{what} {value[:20]!r}... longer than {MAX_ID_LENGTH} characters")
    if _ID_RE.match(value) is None:  # the schemas' rule; say which part is broken
        if value.startswith("@"):
            raise KeyError_(f"{what} {value!r} starts with '@'")
        raise KeyError_(f"{what} {value!r} contains one of '*$#?/' or whitespace")
    return value


def is_valid_id(value: str) -> bool:
    try:
        validate_id(value)
    except KeyError_:
        return False
    return True


def validate_prefix(prefix: str) -> str:
    parts = prefix.split("/")
    for part in parts:
        validate_id(part, "prefix chunk")
    return prefix


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key split into its parts: ``group`` is ``ws``, ``robot``, ``sim``, ``health``
    or ``alive``; ``ident`` the workspace / robot / simulator / service id; ``kind`` the last
    chunk (for health and alive: the session zid)."""

    group: str
    ident: str
    kind: str


@dataclass(frozen=True)
class Keys:
    """Builds and parses confnav keys under one prefix."""

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        validate_prefix(self.prefix)

    # concrete keys -----------------------------------------------------------------------
    def ws(self, ws: str, kind: str) -> str:
        if kind not in WS_KINDS:
            raise KeyError_(f"unknown workspace key kind {kind!r}")
        return f"{self.prefix}/ws/{validate_id(ws, 'workspace id')}/{kind}"

    def robot(self, robot: str, kind: str) -> str:
        if kind not in ROBOT_KINDS:
            raise KeyError_(f"unknown robot key kind {kind!r}")
        return f"{self.prefix}/robot/{validate_id(robot, 'robot id')}/{kind}"

    def sim(self, sim: str, kind: str) -> str:
        if kind not in SIM_KINDS:
            raise KeyError_(f"unknown simulator key kind {kind!r}")
        return f"{self.prefix}/sim/{validate_id(sim, 'simulator id')}/{kind}"

    def health(self, service: str, zid: str) -> str:
        return f"{self.prefix}/health/{validate_id(service, 'service')}/{validate_id(zid, 'zid')}"

    def alive(self, service: str, zid: str) -> str:
        return f"{self.prefix}/alive/{validate_id(service, 'service')}/{validate_id(zid, 'zid')}"

    # key expressions ---------------------------------------------------------------------
    def all(self) -> str:
        return f"{self.prefix}/**"

    def any_ws(self, kind: str) -> str:
        return f"{self.prefix}/ws/*/{kind}"

    def any_robot(self, kind: str) -> str:
        return f"{self.prefix}/robot/*/{kind}"

    def any_sim(self, kind: str) -> str:
        return f"{self.prefix}/sim/*/{kind}"

    def alive_of(self, service: str = "*") -> str:
        return f"{self.prefix}/alive/{service}/*"

    # parsing -----------------------------------------------------------------------------
    def parse(self, key: str) -> ParsedKey:
        """Split a concrete key; raise :class:`KeyError_` if it is not in the layout."""
        head = self.prefix + "/"
        if not key.startswith(head):
            raise KeyError_(f"key {key!r} is not under prefix {self.prefix!r}")
        parts = key[len(head) :].split("/")
        if len(parts) != 3:
            raise KeyError_(f"key {key!r} does not have the form group/id/kind")
        group, ident, kind = parts
        validate_id(ident)
        allowed = {
            "ws": WS_KINDS,
            "robot": ROBOT_KINDS,
            "sim": SIM_KINDS,
        }.get(group)
        if allowed is not None:
            if kind not in allowed:
                raise KeyError_(f"key {key!r}: unknown kind {kind!r} for group {group!r}")
        elif group in ("health", "alive"):
            validate_id(kind, "zid")
        else:
            raise KeyError_(f"key {key!r}: unknown group {group!r}")
        return ParsedKey(group, ident, kind)
