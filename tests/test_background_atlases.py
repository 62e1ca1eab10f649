"""Background atlases (docs/SLAM.md "Background atlases", issue 23): the charts of an atlas no
robot waits for run on niced workers, a base map whose footprint map robots wait for is not
waited for, its decomposition holds while a waited-for atlas starts, the simulator asks for
its robots' footprint maps at start with their starts, and the transform's "atlas:" answer
holds a robot instead of stopping it."""

from __future__ import annotations

import os
import threading
from typing import Any

import pytest
from confnav.schemas import MapQuery, RouteHint, decode
from confnav.services.atlas_transform import RouteBook
from confnav.services.bus import InMemoryNetwork
from confnav.services.controller_state import map_being_solved
from confnav.services.keys import Keys
from confnav.services.simulator import SimulatorService
from confnav.services.transform import BACKGROUND_NICE, TransformService
from conftest import wait_for

K = Keys()


def _niceness() -> int:
    return os.nice(0)


def _hint(rid: str, z: complex = 0.5 + 0.5j) -> RouteHint:
    return RouteHint(robot_id=rid, start=(z.real, z.imag), goal=(z.real, z.imag))


@pytest.mark.timeout(120)
def test_background_jobs_run_on_niced_workers(mem_net: InMemoryNetwork) -> None:
    """Two real process pools: the background one's workers run at BACKGROUND_NICE above the
    service's priority, the normal one's at it."""
    svc = TransformService(mem_net.bus("t"), K, workers=1)
    svc.start()
    try:
        mine = os.nice(0)
        fg = svc.submit_job(_niceness).result(timeout=60)
        bg = svc.submit_job(_niceness, background=True).result(timeout=60)
        assert fg == mine
        assert bg == min(19, mine + BACKGROUND_NICE)
    finally:
        svc.stop()


def test_a_base_map_is_not_waited_for_when_its_footprint_map_is() -> None:
    book = RouteBook()
    assert not book.waited_for(["wh"])  # no route: nobody waits
    book.add("wh", [_hint("r1")])  # a point robot (or a body's fallback) on the base map
    assert book.waited_for(["wh"])
    book.add("wh~r0.32", [_hint("r1")])  # the body's footprint map: that is what it waits for
    assert book.waited_for(["wh~r0.32"])
    assert not book.waited_for(["wh"])
    assert book.waited_for(["other", "wh~r0.32"])  # one definition's ids: any waited for
    assert not book.waited_for(["wh~r0.5"])  # another radius nobody asked for


def test_a_background_decomposition_holds_while_a_waited_for_atlas_starts() -> None:
    svc = TransformService(InMemoryNetwork().bus("t"), K, executor="thread", workers=1)
    share = svc.charts
    share._started("urgent", True)
    done = threading.Event()
    background = [True]

    def decompose_step() -> None:
        share.hold("base", lambda: background[0], lambda: False)
        done.set()

    t = threading.Thread(target=decompose_step)
    t.start()
    assert not done.wait(0.3)  # held: the waited-for atlas has no revision out
    share._started("urgent", False)  # its first revision is out
    assert done.wait(5)
    t.join()
    # an atlas robots wait for never holds (nor does one once it becomes waited for)
    share._started("urgent", True)
    done.clear()
    background[0] = False
    share.hold("base", lambda: background[0], lambda: False)
    share.hold("urgent", lambda: True, lambda: False)  # nor for itself
    share._started("urgent", False)
    assert svc.counters.get("atlas_holds", 0) == 1


@pytest.mark.parametrize("ahead", [True, False])
def test_simulator_asks_for_its_robots_footprint_maps_with_their_starts(
    mem_net: InMemoryNetwork, ahead: bool
) -> None:
    asked: list[tuple[str, MapQuery | None]] = []

    def on_query(key: str, payload: bytes | None) -> list[tuple[str, bytes]]:
        asked.append((key, decode(MapQuery, payload) if payload else None))
        return []  # nobody knows the map yet: asked again later

    mem_net.bus("transform").queryable(K.any_ws("transform"), on_query)
    robots: list[Any] = [
        ("u1", "room", 1.0, 2.0, 0.0, 0.2, "unicycle"),  # 0.2 + the look-ahead 0.1
        ("h1", "room", 3.0, 1.0, 0.0, 0.25, "holonomic"),
        ("p1", "room", 2.0, 2.0),  # a point: no footprint map
    ]
    sim = SimulatorService(mem_net.bus("sim"), K, robots=robots, maps_ahead=ahead)
    sim.start()
    try:
        if not ahead:
            sim._stop.wait(0.5)
            assert asked == []
            return
        wait_for(lambda: {k for k, _ in asked} >= {K.ws("room~r0.3", "transform")}, timeout=10)
        wait_for(lambda: {k for k, _ in asked} >= {K.ws("room~r0.25", "transform")}, timeout=10)
        got = {k: q for k, q in asked}
        q = got[K.ws("room~r0.3", "transform")]
        assert q is not None and [r.robot_id for r in q.routes] == ["u1"]
        assert q.routes[0].start == pytest.approx((1.1, 2.0))  # the look-ahead point
        q = got[K.ws("room~r0.25", "transform")]
        assert q is not None and q.routes[0].start == pytest.approx((3.0, 1.0))
        assert not any("~r" not in k for k, _ in asked)
    finally:
        sim.stop()


def test_the_atlas_answer_holds_the_robot() -> None:
    assert map_being_solved("atlas: workspace 'wh~r0.32' is solved as an atlas of 2 charts")
    assert map_being_solved("workspace 'wh' is being solved; retry")
    assert not map_being_solved("unknown workspace 'wh'")


def test_a_base_atlas_steers_only_where_it_has_a_chart() -> None:
    """First move on the base map (docs/NAVIGATION.md): a partial base atlas is adopted only
    where a chart of a cell holding the robot's reference point is out."""
    from types import SimpleNamespace

    from confnav.services.controller_footprint import base_charts_start
    from shapely.geometry import box

    cells = [SimpleNamespace(polygon=box(0, 0, 2, 1)), SimpleNamespace(polygon=box(1.5, 0, 4, 1))]
    atlas = SimpleNamespace(
        is_atlas=True,
        pending=[1],  # the right cell's chart is still being solved
        atlas=SimpleNamespace(decomposition=SimpleNamespace(cells=cells)),
    )
    assert base_charts_start(atlas, 0.5 + 0.5j)
    assert base_charts_start(atlas, 1.8 + 0.5j)  # in both cells: the left one is charted
    assert not base_charts_start(atlas, 3.0 + 0.5j)
    assert base_charts_start(atlas, None)  # no pose yet: as before
    assert base_charts_start(SimpleNamespace(is_atlas=False), 3.0 + 0.5j)  # one map
    atlas.pending = []
    assert base_charts_start(atlas, 3.0 + 0.5j)
