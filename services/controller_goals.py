"""The controller service's goals: a robot's goal (state, not an event: a repeated one changes
nothing), its controller from the cache, malformed goals and cancels."""

from __future__ import annotations

import logging
import time

from confnav.schemas import (
    DecodeError,
    Goal,
    GoalCancel,
    decode,
)
from confnav.services import navigation
from confnav.services.controller_flat import FlatMixin
from confnav.services.controller_footprint import FootprintMixin, base_charts_start, base_of
from confnav.services.controller_warm import prime
from confnav.services.keys import KeyError_

log = logging.getLogger(__name__)


class GoalsMixin(FootprintMixin, FlatMixin):
    """Goals and cancels: each robot's goal, its controller, and rejected input."""

    # goals (records from ControllerCore._robot) ------------------------------------------
    def _on_goals(self, items: list[tuple[str, bytes]]) -> None:
        self.count("goals_received", len(items))
        for key, payload in items:
            self._on_goal(key, payload)

    def _on_goal(self, key: str, payload: bytes) -> None:
        try:
            rid = self.keys.parse(key).ident
        except KeyError_ as exc:
            self.count("rejected")
            log.warning("rejected goal on %s: %s", key, exc)
            return
        try:
            goal = decode(Goal, payload)
            if goal.robot_id != rid:
                raise DecodeError("invalid_input", f"goal on {key} names robot {goal.robot_id!r}")
            if goal.gain > self.max_gain or goal.v_max > self.max_speed:
                raise DecodeError(
                    "invalid_input",
                    f"gain {goal.gain:g} / v_max {goal.v_max:g} above the caps "
                    f"{self.max_gain:g} / {self.max_speed:g}",
                )
        except DecodeError as exc:
            self.count("rejected")
            log.warning("rejected goal on %s: %s", key, exc)
            self._reject_goal(rid, str(exc))
            return
        # a robot with a footprint drives on the map of the shrunk workspace ({ws}~r{radius})
        goal = goal.model_copy(update={"ws_id": navigation.map_ws_id(goal)})
        r = self._robot(rid)
        if r is None:
            return
        with r.lock:
            r.seen_t = time.monotonic()
            same = r.goal is not None and navigation.goal_key(r.goal) == navigation.goal_key(goal)
        if same:  # goals are state: a repeated one (e.g. republished at 1 Hz) changes nothing
            self.count("goals_repeated")
            return
        self.count("goals")
        with self._goal_building():  # the atlas warm-up waits (services/controller_warm.py)
            m = self._maps.get(goal.ws_id)
            ctrl, err = self._build(m, goal) if m is not None else (None, "")
            base = base_of(goal.ws_id)  # a footprint map being solved: drive on the base map
            bm = self._maps.get(base) if base is not None and m is None else None
            shrunk = None
            if (
                bm is not None
                and self._on_base_available(bm)
                and base_charts_start(bm.cmap, self._reference_of(r, goal))
            ):  # built before the goal is set, so no pose meets it without
                ctrl, err, shrunk = self._build_on_base(bm, goal)
            else:
                bm = None
            prime(ctrl, r.position)  # an atlas: its starting chart's law and safety grid
        with r.lock:
            r.goal, r.ctrl, r.ctrl_error = goal, ctrl, err
            r.ctrl_revision = m.revision if m is not None else None
            r.base_ws, r.shrunk = "", None
            r.atlas_ws, r.flat_note, r.flat_checked = "", "", None
            if bm is not None and base is not None:
                r.ctrl_revision, r.base_ws, r.shrunk = bm.revision, base, shrunk
            r.stale_reported = False
            r.status_key = ("", "", None, "")
            r.goal_t = r.seen_t = time.monotonic()
        current = self._maps.get(goal.ws_id)
        if current is not None and current is not m:  # a map landed while this goal was set
            self._adopt(r, goal.ws_id, current)
        elif m is None:
            latest = self._maps.get(base) if base is not None else None
            if base is not None and latest is not None and self._on_base_available(latest):
                self._adopt_base(r, base, latest)  # a base revision that landed meanwhile
            self._wake_fetch.set()
        self._check_flat(r)  # a single map flat where it stands: ask for the atlas
        if current is not None and getattr(current.cmap, "pending", None):
            self._wake_fetch.set()  # a progressive atlas being solved: send the route hint
        log.info("robot %r: goal %s on %r", rid, goal.goal, goal.ws_id)

    def _reject_goal(self, rid: str, message: str) -> None:
        """A malformed goal: the robot's goal is cleared (zero command) and the sender told."""
        r = self._robot(rid)
        if r is None:
            return
        now = time.monotonic()
        with r.lock:
            if r.goal is not None:
                self._publish_cmd(r, 0j, None)
            r.goal, r.ctrl, r.ctrl_error, r.ctrl_revision = None, None, "", None
            r.base_ws, r.shrunk = "", None
            r.atlas_ws, r.flat_note, r.flat_checked = "", "", None
            r.seen_t = now
            r.status_key = ("", "", None, "")
            self._status(r, "idle", "invalid_input", f"goal rejected: {message}", now)

    def _on_cancel(self, key: str, payload: bytes) -> None:
        """Cancel: zero command, ``idle`` status, and the robot is forgotten."""
        self.count("cancels_received")
        got = self.decode_keyed(GoalCancel, key, payload, "robot_id", "cancel")
        if got is None:
            return
        rid = got[0]
        self.count("cancels")
        self._forget(rid, "cancelled")
