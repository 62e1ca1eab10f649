"""The controller service's watchdog: stops a robot whose pose is stale or whose map is missing
or outdated, and forgets robots silent for ``idle_ttl`` s."""

from __future__ import annotations

import logging
import time

from confnav.services.controller_state import ControllerCore

log = logging.getLogger(__name__)


class WatchdogMixin(ControllerCore):
    """Stale poses, blockers and the idle TTL, checked on a timer."""

    # watchdog -------------------------------------------------------------------------------
    def _watchdog_loop(self) -> None:
        period = min(0.05, self.stale_after / 4)
        next_ttl = time.monotonic() + 1.0
        while not self._stop.wait(period):
            now = time.monotonic()
            with self._lock:
                robots = list(self._robots.values())
            if now >= next_ttl:  # forget robots silent for idle_ttl s
                next_ttl = now + 1.0
                for r in robots:
                    if now - r.seen_t > self.idle_ttl:
                        self._forget(r.robot_id, f"forgotten after {self.idle_ttl:g} s silent")
            for r in robots:  # a law not yet checked for a flat navigation function
                if r.goal is not None and r.ctrl is not None and r.flat_checked is not r.ctrl:
                    self._check_flat(r)  # type: ignore[attr-defined]
            for r in robots:
                with r.lock:
                    if r.goal is None:
                        continue
                    last = r.goal_t if r.last_pose_t is None else max(r.last_pose_t, r.goal_t)
                    if now - last > self.stale_after:
                        if not r.stale_reported:
                            r.stale_reported = True
                            self._stop_robot(
                                r, "stale_pose", f"no pose for {self.stale_after:g} s", now
                            )
                        else:
                            self._status(r, "stopped", "stale_pose", "", now)
                        continue
                    blocker = self._blocker(r)
                    if blocker is not None:  # stop now; the pose path keeps it stopped
                        state = self._blocked_status(r, blocker)
                        if r.status_key[:2] != state[:2]:
                            self._block(r, blocker, now)
                        else:
                            self._status(r, *state, now)
