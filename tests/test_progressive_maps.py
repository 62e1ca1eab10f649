"""Progressive maps (issue 23 item 2): the transform service publishes a coarse revision of a
workspace first and refined revisions up to its tol, each with its honest certificate; the
controller drives on the newest revision and swaps revisions without stopping the robot;
``confnav goal`` returns once the robot moves. Real Zenoh; waits for events."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from typing import Any

from confnav.schemas import TransformSolution, TransformStatus, decode, encode
from confnav.services.definitions import REFINING, revision_ladder
from confnav.services.keys import Keys
from confnav.services.transform import TransformService
from conftest import square_definition, wait_for

K = Keys()


def test_revision_ladder() -> None:
    assert revision_ladder(1e-8) == [1e-3, 1e-6, 1e-8]
    assert revision_ladder(1e-10) == [1e-3, 1e-6, 1e-10]
    assert revision_ladder(1e-4) == [1e-3, 1e-4]
    assert revision_ladder(1e-3) == [1e-3]
    assert revision_ladder(1e-2) == [1e-2]


class _Log:
    """Messages of a key expression, in arrival order, with an event per arrival."""

    def __init__(self, bus: Any, expr: str) -> None:
        self.msgs: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        bus.subscribe(expr, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.msgs.append((key, payload))

    def on(self, key: str) -> list[bytes]:
        with self.lock:
            return [p for k, p in self.msgs if k == key]


def test_transform_publishes_revisions_with_decreasing_error(
    make_bus: Callable[[], Any],
) -> None:
    """tol 1e-8: a coarse revision (status 'solved (coarse, refining)', state refining), then
    finer ones; each certificate honest (tol_met for its own tol), estimates decreasing, the
    last one meets 1e-8 and is what queries answer."""
    client = make_bus()
    log = _Log(client, "confnav/ws/**")
    svc = TransformService(make_bus(), K, executor="thread", health_period=0.2)
    assert svc.progressive  # the library's solver: revisions by default
    svc.start()
    try:
        defn = square_definition("sq", [(0.2, 0.0)]).model_copy(update={"tol": 1e-8})
        client.publish(K.ws("sq", "definition"), encode(defn))

        def solutions() -> list[TransformSolution]:
            return [decode(TransformSolution, p) for p in log.on(K.ws("sq", "transform"))]

        def final_status() -> bool:
            st = [decode(TransformStatus, p) for p in log.on(K.ws("sq", "status"))]
            return bool(st) and st[-1].state == "solved" and not st[-1].message

        wait_for(lambda: any(s.diagnostics.tol == 1e-8 for s in solutions()), timeout=240)
        wait_for(final_status)
        sols = solutions()
        assert len(sols) >= 2, [s.diagnostics for s in sols]
        est = [s.diagnostics.error_estimate for s in sols]
        assert all(b < a for a, b in itertools.pairwise(est)), est
        assert sols[0].diagnostics.tol == 1e-3 and sols[0].diagnostics.tol_met
        assert all(s.diagnostics.error_estimate <= s.diagnostics.tol for s in sols)
        assert sols[-1].diagnostics.tol == 1e-8 and sols[-1].diagnostics.tol_met
        assert len({s.revision for s in sols}) == len(sols)
        statuses = [decode(TransformStatus, p) for p in log.on(K.ws("sq", "status"))]
        coarse = [s for s in statuses if s.message.startswith(REFINING)]
        assert coarse and coarse[0].state == "solved" and coarse[0].revision == sols[0].revision
        assert statuses[-1].state == "solved" and statuses[-1].revision == sols[-1].revision
        assert not statuses[-1].message.startswith(REFINING)
        replies = client.query(K.ws("sq", "transform"))
        assert decode(TransformSolution, replies[0].payload or b"").revision == sols[-1].revision
    finally:
        svc.stop()
