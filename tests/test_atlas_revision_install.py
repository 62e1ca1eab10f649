"""The controller service installs a progressive atlas's next revision by extending its
robots' laws (issue 23, round 4; docs/ATLAS.md "Revisions of a progressive atlas"), over real
Zenoh sessions: a test-side atlas server (the transform's ``AtlasStore`` behind a queryable)
publishes a partial revision without the robot's start chart, then revisions of the same
cells with more charts, then a revision of other cells. The robot holds (zero command) on
the first, moves once a revision brings its chart, keeps the same law object through every
revision of the round (counted ``atlas_laws_extended``), gets a new law for the other
cells, and arrives without touching a wall."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from confnav.schemas import AtlasIndex, Goal, RobotStatus, decode, encode
from confnav.services.atlas_transform import AtlasStore, messages_of
from confnav.services.bus import QueryError
from confnav.services.controller import ControllerService
from confnav.services.keys import Keys
from confnav.services.transform import solution_result
from conftest import HolonomicRobot, wait_for
from test_atlas import GOAL, TOL, pillar_corridor
from test_atlas_wire import _bent, _partial

from confnav.atlas import solve_atlas
from confnav.atlas.wire import atlas_revision, index_fields

K = Keys(prefix="cnr")
START = (0.3, 0.4)


@pytest.mark.timeout(300)
def test_revisions_of_a_round_extend_the_robots_law(make_bus: Callable[[], Any]) -> None:
    ws = pillar_corridor()
    atlas = solve_atlas(ws, TOL, workers=1)
    result = {
        "atlas": index_fields(atlas),
        "charts": [solution_result(m, TOL) for m in atlas.charts],
    }
    index, charts = messages_of("pc", "h" * 64, result)
    by_rev = {c.revision: c for c in charts}
    n = len(index.cells)
    z0 = complex(*START)
    start_cells = {c.index for c in atlas.decomposition.cells if c.depth(np.array([z0]))[0] > 0}
    assert n >= 3 and len(start_cells) < n
    others = [i for i in range(n) if i not in start_cells]
    # revision 1: one chart, none of them holding the start; 2: the start's; 3: all
    first = _partial(index, set(range(n)) - {others[0]})
    second = _partial(index, set(others[1:]))
    # other cells (a cell polygon moved by 1e-12: still its chart's cell, another cells key)
    bent = _bent(index, 1e-12)
    bent = bent.model_copy(update={"revision": atlas_revision(["bent", index.revision])})
    store = AtlasStore()

    def serve(idx: AtlasIndex) -> None:
        ids = {c.chart_ws_id: by_rev[c.chart_revision] for c in idx.cells if not c.pending}
        store.put("pc", encode(idx), {w: encode(s) for w, s in ids.items()})

    def on_query(keyexpr: str, _payload: bytes | None) -> list[tuple[str, bytes]]:
        p = K.parse(keyexpr)
        hit = store.answer(keyexpr, p.ident, p.kind)
        if hit is None:
            raise QueryError(f"no map for {p.ident!r}")
        return hit

    server = make_bus()
    server.queryable(K.any_ws("transform"), on_query)
    server.queryable(K.any_ws("atlas"), on_query)
    server.declare_token(K.alive("transform", server.zid))  # a transform service to the controller
    lock = threading.Lock()
    statuses: list[RobotStatus] = []

    def on_status(_key: str, payload: bytes) -> None:
        with lock:
            statuses.append(decode(RobotStatus, payload))

    server.subscribe(K.robot("r1", "status"), on_status)
    serve(first)
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    ctl.start()
    robot = HolonomicRobot(make_bus(), "r1", START, keys=K)
    try:
        g = Goal(robot_id="r1", ws_id="pc", goal=(GOAL.real, GOAL.imag), v_max=0.5,
                 tolerance=0.05)  # fmt: skip
        server.publish(K.robot("r1", "goal"), encode(g))

        def installed(rev: str) -> Any:
            m = ctl._maps.get("pc")
            r = ctl._robots.get("r1")
            return r is not None and m is not None and m.revision == rev and r.ctrl_revision == rev

        wait_for(lambda: installed(first.revision), timeout=60)
        law = ctl._robots["r1"].ctrl
        assert law is not None
        assert robot.moving_commands() == []  # holding: its start chart is not there
        for idx in (second, index):  # the round's next revisions, announced on the bus
            serve(idx)
            server.publish(K.ws("pc", "atlas"), encode(idx))
            wait_for(lambda idx=idx: installed(idx.revision), timeout=60)  # type: ignore[misc]
            new = ctl._robots["r1"].ctrl
            assert new is not law and new.nav.atlas is ctl._maps["pc"].cmap.atlas  # type: ignore[union-attr]
            assert new.nav.plan is law.nav.plan  # type: ignore[union-attr]  # made from it
            law = new
        assert ctl.counters["atlas_laws_extended"] == 2
        wait_for(lambda: robot.moving_commands(), timeout=30)  # it moves on the start chart
        # other cells: a new law
        serve(bent)
        server.publish(K.ws("pc", "atlas"), encode(bent))
        wait_for(lambda: installed(bent.revision), timeout=60)
        assert ctl._robots["r1"].ctrl.nav.plan is not law.nav.plan  # type: ignore[union-attr]
        assert ctl.counters["atlas_laws_extended"] == 2

        def arrived() -> bool:
            with lock:
                return any(s.state == "arrived" for s in statuses)

        wait_for(arrived, timeout=120, interval=0.1)
        with robot.lock:
            path = np.array(robot.path)
        assert float(np.min(ws.clearance(path))) > 0
        assert abs(path[-1] - GOAL) < 0.05 + 0.05
    finally:
        robot.stop.set()
        ctl.stop()
