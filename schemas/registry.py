"""Which model belongs to which key, size limits, decoding from bytes and JSON Schema export."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

from confnav.schemas.messages import (
    AtlasIndex,
    CollisionEvent,
    CommandBatch,
    Goal,
    GoalCancel,
    MapQuery,
    Message,
    Movers,
    Pose,
    PoseBatch,
    RobotStatus,
    ServiceHealth,
    SimControl,
    SpawnRequest,
    TransformSolution,
    TransformStatus,
    VelocityCommand,
    WorkspaceDefinition,
    WorkspaceDelete,
)
from pydantic import ValidationError

M = TypeVar("M", bound=Message)

MESSAGE_MODELS: tuple[type[Message], ...] = (
    WorkspaceDefinition,
    WorkspaceDelete,
    TransformSolution,
    TransformStatus,
    Goal,
    GoalCancel,
    Pose,
    VelocityCommand,
    RobotStatus,
    CollisionEvent,
    SpawnRequest,
    SimControl,
    ServiceHealth,
    AtlasIndex,
    Movers,
    PoseBatch,
    CommandBatch,
    MapQuery,
)
MODELS_BY_TYPE: dict[str, type[Message]] = {m.TYPE: m for m in MESSAGE_MODELS}

#: (key group, key kind) -> model; groups and kinds as in :mod:`confnav.services.keys`.
MODEL_BY_KEY_KIND: dict[tuple[str, str], type[Message]] = {
    ("ws", "definition"): WorkspaceDefinition,
    ("ws", "delete"): WorkspaceDelete,
    ("ws", "transform"): TransformSolution,
    ("ws", "status"): TransformStatus,
    ("ws", "atlas"): AtlasIndex,
    ("ws", "movers"): Movers,
    ("robot", "goal"): Goal,
    ("robot", "cancel"): GoalCancel,
    ("robot", "pose"): Pose,
    ("robot", "cmd_vel"): VelocityCommand,
    ("robot", "status"): RobotStatus,
    ("robot", "collision"): CollisionEvent,
    ("sim", "spawn"): SpawnRequest,
    ("sim", "control"): SimControl,
    ("sim", "poses"): PoseBatch,
    ("sim", "cmd_vel"): CommandBatch,
    ("health", "*"): ServiceHealth,
}

#: (key group, key kind) -> the model of a query's optional payload on that key (a query
#: without payload is valid too; replies are the key's model above).
QUERY_MODEL_BY_KEY_KIND: dict[tuple[str, str], type[Message]] = {
    ("ws", "transform"): MapQuery,
    ("ws", "atlas"): MapQuery,
}

DEFAULT_MAX_BYTES = 64 * 1024
#: Largest accepted payload per model, in bytes; anything bigger is rejected unparsed.
MAX_BYTES: dict[type[Message], int] = {
    WorkspaceDefinition: 2 * 1024 * 1024,
    TransformSolution: 64 * 1024 * 1024,
    AtlasIndex: 16 * 1024 * 1024,
    PoseBatch: 2 * 1024 * 1024,  # MAX_BATCH entries of about 150 bytes
    CommandBatch: 2 * 1024 * 1024,
}


def max_bytes(model: type[Message]) -> int:
    return MAX_BYTES.get(model, DEFAULT_MAX_BYTES)


def model_for_key_parts(group: str, kind: str) -> type[Message] | None:
    """The model carried on a key with this group and kind, or None."""
    if group == "health":
        return ServiceHealth
    return MODEL_BY_KEY_KIND.get((group, kind))


class DecodeError(ValueError):
    """A payload that is not a valid message. ``reason`` is one of ``too_large``,
    ``invalid_json``, ``nan_input``, ``schema_version``, ``invalid_input``."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def decode(model: type[M], payload: bytes | bytearray | memoryview, limit: int | None = None) -> M:
    """Validate ``payload`` (JSON bytes) as ``model``; raise :class:`DecodeError` saying why not.

    The size limit (default :func:`max_bytes`) is checked before parsing.
    """
    limit = max_bytes(model) if limit is None else limit
    if len(payload) > limit:
        raise DecodeError("too_large", f"{model.TYPE}: payload of {len(payload)} bytes > {limit}")
    try:
        return model.model_validate_json(bytes(payload))
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_context=False, include_input=False)
        types = {e["type"] for e in errors}
        locs = {str(e["loc"][0]) if e["loc"] else "" for e in errors}
        if "json_invalid" in types:
            reason = "invalid_json"
        elif "finite_number" in types:
            reason = "nan_input"
        elif "schema_version" in locs or "type" in locs:
            reason = "schema_version"
        else:
            reason = "invalid_input"
        short = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in errors[:3])
        raise DecodeError(reason, f"{model.TYPE}: {short}") from None


def encode(message: Message) -> bytes:
    """The wire form of ``message`` (compact JSON, UTF-8)."""
    return message.model_dump_json().encode()


def schema_name(model: type[Message]) -> str:
    """MCAP schema name: ``confnav.<Model>``."""
    return model.TYPE


def json_schema(model: type[Message]) -> dict[str, Any]:
    """JSON Schema of the wire contract: what :func:`decode` accepts. A field with a default
    (``type`` and ``schema_version`` included) may be omitted, exactly as the services accept
    it; :func:`encode` always writes every field, which the schema accepts too."""
    schema = model.model_json_schema(mode="validation")
    schema["$id"] = model.TYPE
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return schema


def schema_bytes(model: type[Message]) -> bytes:
    """Canonical JSON Schema bytes (sorted keys): the MCAP schema data and the exported file."""
    return json.dumps(json_schema(model), sort_keys=True, indent=1).encode()


def export_schemas(directory: str | Path) -> list[Path]:
    """Write ``<dir>/confnav.<Model>.schema.json`` for every message model; return the paths."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for model in MESSAGE_MODELS:
        path = out / f"{model.TYPE}.schema.json"
        path.write_bytes(schema_bytes(model))
        paths.append(path)
    return paths
