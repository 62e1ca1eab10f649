"""schemas/fast.py: the controller's command bytes equal the pydantic model's, field for field."""

from __future__ import annotations

import json
from typing import get_args

import numpy as np
import pytest
from confnav.schemas import RobotStatus, VelocityCommand, decode, encode
from confnav.schemas.fast import robot_status_json, velocity_command_json
from confnav.schemas.messages import RobotState, StatusReason

FLOATS = [0.0, -0.0, 1.0, -1.5, 0.1, 1e-7, -1e-300, 5e-324, 1e16, 1e17, 1.7976931348623157e308,
          123456.789, 2.0 / 3.0, 1e-5, 1e-4, 1e15, 1e21, 1e22]  # fmt: skip


def _both(**kw: object) -> tuple[bytes, bytes]:
    fast = velocity_command_json(
        kw["robot_id"], kw["stamp_ns"], kw["linear"], kw["angular"], kw["pose_seq"],  # type: ignore[arg-type]
        kw["pose_stamp_ns"], kw["map_revision"], kw["frame"], kw["chart"],  # type: ignore[arg-type]
    )  # fmt: skip
    return fast, encode(VelocityCommand(**kw))  # type: ignore[arg-type]


@pytest.mark.parametrize("x", FLOATS)
def test_floats_are_written_as_pydantic_writes_them(x: float) -> None:
    fast, ref = _both(robot_id="z01r001", stamp_ns=1, linear=(x, -x), angular=x, pose_seq=3,
                      pose_stamp_ns=7, map_revision="abc", frame="world", chart=None)  # fmt: skip
    assert fast == ref


def test_random_commands_are_byte_identical_and_valid() -> None:
    rng = np.random.default_rng(5)
    ids = ["a", "z00r000", "robot-7_x.y", "R" * 64, "é~ü"]
    for i in range(2000):
        x, y, w = (float(v) for v in rng.standard_normal(3) * 10.0 ** rng.integers(-12, 12, 3))
        kw = dict(
            robot_id=ids[i % len(ids)],
            stamp_ns=int(rng.integers(0, 2**63 - 1)),
            linear=(x, 0.0) if i % 2 else (x, y),
            angular=w,
            pose_seq=int(rng.integers(-1, 2**40)),
            pose_stamp_ns=int(rng.integers(0, 2**62)),
            map_revision=None if i % 3 == 0 else f"rev{i}",
            frame="body" if i % 2 else "world",
            chart=None if i % 4 else int(rng.integers(0, 100)),
        )
        fast, ref = _both(**kw)
        assert fast == ref, (fast, ref)
        back = decode(VelocityCommand, fast)  # valid against the model, the same values
        assert back.model_dump() == VelocityCommand(**kw).model_dump()  # type: ignore[arg-type]
        assert json.loads(fast)["linear"] == list(kw["linear"])  # type: ignore[call-overload]


def test_stop_command_without_a_pose() -> None:
    fast, ref = _both(robot_id="r", stamp_ns=0, linear=(0.0, 0.0), angular=0.0, pose_seq=-1,
                      pose_stamp_ns=0, map_revision=None, frame="world", chart=None)  # fmt: skip
    assert fast == ref


def _status_both(**kw: object) -> tuple[bytes, bytes]:
    fast = robot_status_json(
        kw["robot_id"], kw["stamp_ns"], kw["state"], kw["reason"], kw["message"],  # type: ignore[arg-type]
        kw["ws_id"], kw["map_revision"], kw["position"], kw["distance_to_goal"],  # type: ignore[arg-type]
        kw["chart"],  # type: ignore[arg-type]
    )  # fmt: skip
    return fast, encode(RobotStatus(**kw))  # type: ignore[arg-type]


def test_random_statuses_are_byte_identical_and_valid() -> None:
    """The controller's statuses (schemas/fast.py ``robot_status_json``): the model's bytes for
    every state and reason, messages with quotes, escapes, newlines and non-ASCII text, and
    every optional field absent or present."""
    rng = np.random.default_rng(11)
    states = list(get_args(RobotState))
    reasons = list(get_args(StatusReason))
    messages = ["", "navigating", 'a "quoted" word', "back\\slash", "two\nlines\ttab",
                "0.88 m off it; élan → ü", "\x00\x1f\x7f", "\u2028 \ud7ff", "x" * 4000]  # fmt: skip
    for i in range(1500):
        x, y, dd = (float(v) for v in rng.standard_normal(3) * 10.0 ** rng.integers(-12, 12, 3))
        kw = dict(
            robot_id=["a", "z00r000", "robot-7_x.y", "é~ü"][i % 4],
            stamp_ns=int(rng.integers(0, 2**63 - 1)),
            state=states[i % len(states)],
            reason=reasons[i % len(reasons)],
            message=messages[i % len(messages)],
            ws_id=None if i % 5 == 0 else f"ws{i % 7}",
            map_revision=None if i % 3 == 0 else f"rev{i}",
            position=None if i % 6 == 0 else (x, y),
            distance_to_goal=None if i % 4 == 0 else abs(dd),
            chart=None if i % 2 else int(rng.integers(0, 100)),
        )
        fast, ref = _status_both(**kw)
        assert fast == ref, (fast, ref)
        back = decode(RobotStatus, fast)
        assert back.model_dump() == RobotStatus(**kw).model_dump()  # type: ignore[arg-type]
