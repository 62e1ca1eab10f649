"""Route hints on retried map queries (issue 23): a controller re-queries a missing map every
``fetch_period``; its robots' routes go with the first query and again when the transform's
answer changes, not with every retry of the same answer (measured before: 510 hints sent to
the warehouse's failed base map in 98 s, the same 3 routes every 0.5 s). A recording stand-in
for the bus: this is the controller's query logic, no transport."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from confnav.schemas import Goal, MapQuery, decode
from confnav.services.controller import ControllerService
from confnav.services.controller_state import _Robot


@dataclass
class _Reply:
    ok: bool
    payload: bytes | None
    error: str


class _Bus:
    """Answers every map query with the error in ``error``; records the queries' payloads."""

    def __init__(self) -> None:
        self.error = "workspace 'depot' is being solved; retry"
        self.payloads: list[bytes | None] = []

    def query(self, key: str, timeout: float = 0.0, payload: bytes | None = None) -> list[Any]:
        self.payloads.append(payload)
        return [_Reply(False, None, self.error)]


def _routes(payload: bytes | None) -> list[str]:
    return [] if payload is None else [h.robot_id for h in decode(MapQuery, payload).routes]


def _robot(svc: ControllerService, rid: str, x: float) -> None:
    r = _Robot(rid)
    r.goal = Goal(robot_id=rid, ws_id="depot", goal=(5.0, 5.0))
    r.position = (x, 1.0)
    svc._robots[rid] = r


def test_a_retried_query_sends_only_new_routes_until_the_answer_changes() -> None:
    bus = _Bus()
    svc = ControllerService(bus)  # type: ignore[arg-type]
    _robot(svc, "r0", 1.0)
    _robot(svc, "r1", 2.0)
    svc._fetch("depot")
    assert sorted(_routes(bus.payloads[-1])) == ["r0", "r1"]
    for _ in range(3):  # the same answer: the transform has these routes
        svc._fetch("depot")
        assert _routes(bus.payloads[-1]) == []
    _robot(svc, "r2", 3.0)  # a new robot's route goes with the next retry, once
    svc._fetch("depot")
    assert _routes(bus.payloads[-1]) == ["r2"]
    svc._fetch("depot")
    assert _routes(bus.payloads[-1]) == []
    bus.error = "workspace 'depot': atlas failed: cell of tile ... still fails"  # a new answer
    svc._fetch("depot")  # sent with the old hints: this answer is the first of its kind
    assert _routes(bus.payloads[-1]) == []
    svc._fetch("depot")  # the retry on the new answer sends every route again, once
    assert sorted(_routes(bus.payloads[-1])) == ["r0", "r1", "r2"]
    svc._fetch("depot")
    assert _routes(bus.payloads[-1]) == []
