"""The controller service's background worker for critical-point searches.

:meth:`confnav.navigation.control.Controller.search_critical_points` takes an executor (the
pure core starts no thread); this is the one the services pass.  One daemon worker per process
runs every controller's search in turn (a burst of new goals queues up instead of taking every
core, and an exiting process never waits for a search), takes at most :data:`SEARCH_DUTY` of a
core (it sleeps ``(1/SEARCH_DUTY - 1)`` times each search's CPU time, at most 2 s, afterwards,
so the control steps are not starved), and skips controllers nobody holds any more (a robot
that got a new goal before its old goal's search began): their futures are cancelled.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import weakref
from concurrent.futures import Future
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from confnav.navigation.control import Controller
    from confnav.navigation.critical import CriticalPoints

log = logging.getLogger(__name__)

__all__ = ["CRITICAL_SEARCH", "SEARCH_DUTY", "CriticalSearchWorker"]

#: Share of a core the background critical-point searches of a process may take.
SEARCH_DUTY = 0.25

_Job = tuple["weakref.ref[Controller]", "Future[CriticalPoints]"]


class CriticalSearchWorker:
    """A :class:`confnav.navigation.control.SearchExecutor` with one daemon thread, started
    on the first search."""

    def __init__(self, duty: float = SEARCH_DUTY, name: str = "critical-points") -> None:
        self.duty = float(duty)
        self.name = name
        self._jobs: queue.SimpleQueue[_Job] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def submit_search(
        self, controller: weakref.ref[Controller], future: Future[CriticalPoints]
    ) -> None:
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
                self._thread.start()
        self._jobs.put((controller, future))

    def _loop(self) -> None:
        while True:
            ref, fut = self._jobs.get()
            ctl = ref()
            if ctl is None:  # dropped by every holder before its turn: cancelled, not run
                fut.cancel()
                continue
            if not fut.set_running_or_notify_cancel():
                continue
            t0 = time.process_time()
            try:
                fut.set_result(ctl.critical_points())
            except Exception as exc:  # reported through the future, never kills the worker
                log.warning("critical-point search failed for %r: %s", ctl, exc)
                fut.set_exception(exc)
            del ctl  # not kept alive by the idle worker
            busy = time.process_time() - t0  # the process's CPU: includes others' work, so
            time.sleep(min(busy * (1.0 / self.duty - 1.0), 2.0))  # this errs on the idle side


#: The process's worker (what the controller service passes).
CRITICAL_SEARCH = CriticalSearchWorker()
