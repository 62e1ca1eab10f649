"""The controller service's chart warm-up: the local expansions of an installed atlas's charts
are built by one background thread, the charts the robots need first first, and never in a
goal's way.

An atlas is installed cold (:meth:`confnav.atlas.wire.AtlasMap.warm`): every chart evaluates
by the direct formula, so a goal costs its plan and its first chart's law (built when the
goal arrives, :func:`prime`), not the second or so per chart its expansions take (3-4 s under
load on the README's office map, which was most of a robot's first move). This thread then
builds the expansions, one chart at a time:

1. the cold charts on the cell paths of the robots driving on the atlas (their active or
   starting chart, then the next cells of their plans, in order);
2. the cold charts within :data:`WARM_RADIUS` of a robot the controller knows (a pose
   received, with or without a goal), nearest first.

Charts no robot is near stay on the direct formula (a robot's step costs about the same on
either, measured in process on the office; the expansions pay off for many robots on one
chart), and the thread keeps to a quarter of a core (:data:`WARM_DUTY`): building every
chart of two atlases back to back (the office and its footprint atlas, 81 charts) kept one
core busy for minutes and, holding the interpreter lock in its Python loops, starved the
pose thread (a robot was stopped for stale poses and never swapped to its footprint atlas in
``bench_firstmove``).

While a goal's controller is being built (:meth:`WarmMixin._goal_building`) the thread does
not start a chart: a goal for a cold chart never waits for the warm queue (a chart already
being built finishes; the goal does not need it, since a cold chart evaluates directly).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from confnav.services.controller_state import ControllerCore, _Robot

log = logging.getLogger(__name__)

#: Seconds between checks of the warm queue when nothing woke the thread (new robots and
#: poses do not wake it; a newly installed atlas does).
WARM_PERIOD = 1.0

#: Metres: the cold charts whose cells are this close to a known robot are warmed.
WARM_RADIUS = 1.0

#: Share of one core the warm-up thread may use (it sleeps (1 - duty) / duty times each
#: chart's build time after it).
WARM_DUTY = 0.25


def _law(ctrl: Any) -> Any:
    """The point law inside a unicycle's look-ahead law (the law itself otherwise)."""
    return getattr(ctrl, "controller", ctrl)


def prime(ctrl: Any, position: tuple[float, float] | None) -> list[int]:
    """Build what an atlas controller's first command at ``position`` needs (its starting
    chart's law and safety grid: :meth:`confnav.atlas.wire.AtlasController.prepare`), off
    the pose path; nothing for other laws or an unknown position. Returns the charts."""
    prepare = getattr(_law(ctrl), "prepare", None)
    if prepare is None or position is None:
        return []
    try:
        return list(prepare(complex(position[0], position[1])))
    except Exception:  # the first pose meets the same error and reports it
        log.debug("priming an atlas controller", exc_info=True)
        return []


def _chain(ctrl: Any, position: tuple[float, float] | None) -> list[int]:
    """The charts an atlas controller's robot will use, in order: its active chart (or the
    one it would start on at ``position``), then the next cells of its plan."""
    nav = getattr(_law(ctrl), "nav", None)
    if nav is None:
        return []
    a = getattr(_law(ctrl), "active_chart", None)
    if a is None:
        if position is None:
            return []
        a = int(nav.initial_cells(np.array([complex(position[0], position[1])]))[0])
    out: list[int] = []
    while a is not None and a >= 0 and a not in out and len(out) < len(nav.cells):
        out.append(int(a))
        a = int(nav.plan.next[a])
    return out


class WarmMixin(ControllerCore):
    """The warm-up thread of atlas charts (module docstring)."""

    #: ``background`` (module docstring) or ``first-use``: an atlas's charts build their
    #: expansions when a robot first evaluates them (``serve controller --atlas-warmup``)
    atlas_warmup: str = "background"

    def _init_warm(self) -> None:
        if not hasattr(self, "_warm_wake"):
            self._warm_wake = threading.Event()
            self._warm_guard = threading.Lock()
            self._warm_started = False
            self._building = 0  # goal builds in progress (the thread waits for them)

    @contextlib.contextmanager
    def _goal_building(self) -> Iterator[None]:
        """Around a goal's controller build: no chart warm-up starts meanwhile."""
        self._init_warm()
        with self._warm_guard:
            self._building += 1
        try:
            yield
        finally:
            with self._warm_guard:
                self._building -= 1

    def _warm_atlas(self, cmap: Any) -> None:
        """An atlas was installed: (start and) wake the warm-up thread (``first-use``: its
        charts build their expansions when first evaluated instead)."""
        if self.atlas_warmup == "first-use":
            cmap.build_on_first_use()
            return
        self._init_warm()
        with self._warm_guard:
            start = not self._warm_started
            self._warm_started = True
        if start:
            self.spawn(self._warm_loop, "warm")
        self._warm_wake.set()

    def _next_chart(self) -> tuple[Any, int] | None:
        """The next ``(atlas map, chart)`` to warm (module docstring), None if all are warm."""
        with self._lock:
            atlases = [m.cmap for m in self._maps.values() if getattr(m.cmap, "is_atlas", False)]
            robots: list[_Robot] = list(self._robots.values())
        atlases = [a for a in atlases if hasattr(a, "warm")]
        if not atlases:
            return None
        by_atlas = {id(a.atlas): a for a in atlases}
        points = []
        for r in robots:
            ctrl, pos = r.ctrl, r.position
            if pos is not None:
                points.append(complex(pos[0], pos[1]))
            nav = getattr(_law(ctrl), "nav", None)
            am = by_atlas.get(id(getattr(nav, "atlas", None)))
            if am is None:
                continue
            for i in _chain(ctrl, pos):
                if not am.is_warm(i):
                    return am, i
        best: tuple[float, Any, int] | None = None
        for am in atlases:
            near = [(i, d) for i, d in am.cold_by_distance(points) if d <= WARM_RADIUS]
            if near and (best is None or near[0][1] < best[0]):
                best = (near[0][1], am, near[0][0])
        return None if best is None else (best[1], best[2])

    def _warm_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._next_chart()
            except Exception:
                log.debug("warm queue", exc_info=True)
                job = None
            if job is None:
                self._warm_wake.wait(WARM_PERIOD)
                self._warm_wake.clear()
                continue
            while self._building > 0 and not self._stop.is_set():
                self._stop.wait(0.02)  # a goal is being built: it goes first
            if self._stop.is_set():
                return
            am, i = job
            t0 = time.perf_counter()
            try:
                built = am.warm(i)
            except Exception as exc:  # such a chart stays on the direct formula
                self.count("chart_warm_errors")
                log.warning("atlas %r: chart %d not warmed: %s", am.ws_id, i, exc)
                am.warm_failed(i)
                continue
            if built:
                took = time.perf_counter() - t0
                self.count("charts_warmed")
                log.debug("atlas %r: chart %d warmed in %.2f s", am.ws_id, i, took)
                self._stop.wait(took * (1.0 - WARM_DUTY) / WARM_DUTY)
