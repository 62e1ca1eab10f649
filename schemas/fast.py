"""Fast paths of the hot messages: a ``VelocityCommand`` and a ``RobotStatus`` written straight
to their wire bytes.

The controller answers every pose with a command; building the pydantic model and dumping it
costs about 20 us (``model_construct`` + ``model_dump_json``), most of the per-command cost
once the control law is vectorized (docs/SERVICES.md, "Scale").  :func:`velocity_command_json`
writes the same bytes (every field, in the model's order, each value through pydantic-core's
own serializer ``pydantic_core.to_json``), so readers, the recorder and ``replay --check`` see
no difference: tests/test_schemas_fast.py checks byte equality with
``encode(VelocityCommand(...))`` and validity against the model.  The same for the robots'
statuses (:func:`robot_status_json`): 200 robots repeat theirs every 0.25 s, 40 a pose step
at 20 Hz, 6 % of the step's CPU as models (bench/bench_controller.py).  Decoding stays with
pydantic (``decode``): a ``Pose`` validates in about 5 us, less than a fast path that builds
the model (``model_construct`` alone costs more).
"""

from __future__ import annotations

from confnav.schemas.messages import RobotStatus, VelocityCommand
from pydantic_core import to_json

__all__ = ["robot_status_json", "velocity_command_json"]

_HEAD = (
    b'{"type":"' + VelocityCommand.TYPE.encode() + b'","schema_version":'
    + str(VelocityCommand.model_fields["schema_version"].default).encode() + b',"robot_id":'
)  # fmt: skip
_CACHE_MAX = 100_000
_strings: dict[str | None, bytes] = {None: b"null"}


def _str(s: str | None) -> bytes:
    """``s`` as pydantic writes it (cached: robot ids and map revisions repeat)."""
    b = _strings.get(s)
    if b is None:
        b = to_json(s)
        if len(_strings) < _CACHE_MAX:
            _strings[s] = b
    return b


def velocity_command_json(
    robot_id: str,
    stamp_ns: int,
    linear: tuple[float, float],
    angular: float,
    pose_seq: int,
    pose_stamp_ns: int,
    map_revision: str | None,
    frame: str,
    chart: int | None,
) -> bytes:
    """``encode(VelocityCommand(...))`` of these fields, byte for byte, without the model.

    The caller passes valid values (the controller's own: finite floats, a valid id); nothing
    is validated here, exactly as with ``VelocityCommand.model_construct``.
    """
    return b"".join(
        (
            _HEAD,
            _str(robot_id),
            b',"stamp_ns":',
            str(int(stamp_ns)).encode(),
            b',"linear":',
            to_json((float(linear[0]), float(linear[1]))),
            b',"angular":',
            to_json(float(angular)),
            b',"pose_seq":',
            str(int(pose_seq)).encode(),
            b',"pose_stamp_ns":',
            str(int(pose_stamp_ns)).encode(),
            b',"map_revision":',
            _str(map_revision),
            b',"frame":',
            _str(frame),
            b',"chart":',
            b"null" if chart is None else str(int(chart)).encode(),
            b"}",
        )
    )


_STATUS_HEAD = (
    b'{"type":"' + RobotStatus.TYPE.encode() + b'","schema_version":'
    + str(RobotStatus.model_fields["schema_version"].default).encode() + b',"robot_id":'
)  # fmt: skip


def robot_status_json(
    robot_id: str,
    stamp_ns: int,
    state: str,
    reason: str,
    message: str,
    ws_id: str | None,
    map_revision: str | None,
    position: tuple[float, float] | None,
    distance_to_goal: float | None,
    chart: int | None,
) -> bytes:
    """``encode(RobotStatus(...))`` of these fields, byte for byte, without the model.

    As :func:`velocity_command_json`: the caller passes valid values (a state and reason of
    the schema's, a message of at most 4096 characters, finite numbers); not validated here.
    """
    return b"".join(
        (
            _STATUS_HEAD,
            _str(robot_id),
            b',"stamp_ns":',
            str(int(stamp_ns)).encode(),
            b',"state":',
            _str(state),
            b',"reason":',
            _str(reason),
            b',"message":',
            _str(message) if not message else to_json(message),
            b',"ws_id":',
            _str(ws_id),
            b',"map_revision":',
            _str(map_revision),
            b',"position":',
            b"null" if position is None else to_json((float(position[0]), float(position[1]))),
            b',"distance_to_goal":',
            b"null" if distance_to_goal is None else to_json(float(distance_to_goal)),
            b',"chart":',
            b"null" if chart is None else str(int(chart)).encode(),
            b"}",
        )
    )
