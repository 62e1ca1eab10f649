"""The controller service's controller cache: one control law per (map revision, goal), built
off the pose path and handed to the robots that drive on it."""

from __future__ import annotations

import logging

from confnav.schemas import Goal
from confnav.services import navigation
from confnav.services.controller_state import (
    ControllerCore,
    _Map,
    _Robot,
)

log = logging.getLogger(__name__)

CTRL_CACHE_SIZE = 4096
"""Most controllers kept for reuse (a new goal with the parameters of a cached one costs no
harmonic solve); robots hold the ones they use, so eviction only forgets old goals."""


class ControllerCacheMixin(ControllerCore):
    """Controllers by (map revision, goal and law parameters), shared by the robots with one
    goal; least recently used first, at most ``CTRL_CACHE_SIZE``."""

    def _build(self, m: _Map, goal: Goal) -> tuple[navigation.ControllerLike | None, str]:
        key = (m.revision, *navigation.goal_key(goal))
        if getattr(m.cmap, "per_robot", False):  # an atlas: the controller holds the chart
            key = (*key, goal.robot_id)
        with self._build_lock:
            ctrl = self._ctrl_cache.get(key)
            if ctrl is not None:
                self._ctrl_cache.move_to_end(key)
                return ctrl, ""
            try:
                ctrl = self._make_ctrl(m.cmap, goal)
            except Exception as exc:
                self.count("navigation_errors")
                return None, f"{type(exc).__name__}: {exc}"
            self.count("controllers_built")
            self._ctrl_cache[key] = ctrl
            while len(self._ctrl_cache) > CTRL_CACHE_SIZE:  # robots keep what they use
                self._ctrl_cache.popitem(last=False)
            flt = getattr(getattr(ctrl, "controller", ctrl), "safety", None)
            try:  # the wall safety layer's grid: built here (0.3-0.5 s once per map, on the
                getattr(flt, "grid", None)  # map thread), not in the first pose step after it
            except Exception:  # the pose step meets the same error and reports it
                log.debug("safety grid", exc_info=True)
            search = getattr(getattr(ctrl, "controller", ctrl), "search_critical_points", None)
            if search is not None:  # in the background: STALLED near a saddle once they land
                search(navigation.CRITICAL_SEARCH)
            return ctrl, ""

    def _adopt(self, r: _Robot, ws_id: str, m: _Map) -> None:
        """Give ``r`` the controller of workspace ``ws_id``'s map ``m`` for its current goal,
        unless it has one of ``m`` already or its goal moved elsewhere meanwhile.

        A goal and a map installation race: the installation builds for the goals it saw, the
        goal handler for the map it saw; whichever comes second catches the robot the first
        one missed (a lost race left a robot without a controller until the next map)."""
        with r.lock:
            goal = r.goal
            if goal is None or goal.ws_id != ws_id or r.ctrl_revision == m.revision:
                return
            if r.atlas_ws in self._maps:  # on the atlas its flat start asked for
                return
        ctrl, err = self._build(m, goal)
        with r.lock:
            if r.goal is goal and r.ctrl_revision != m.revision:
                r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, m.revision, err
                r.base_ws, r.shrunk = "", None
