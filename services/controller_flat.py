"""The controller service's way out of a flat navigation function: a robot whose harmonic
navigation function is 1 to rounding where it stands drives on an atlas of its workspace.

Far along corridors from the goal the goal's Green's function decays below double precision
(``1 - phi < FLAT_PHI``, :mod:`confnav.cli.simulate`; or the map itself crowds there and phi
is not even finite): the gradient the law follows is rounding noise and the robot crawls or
wanders. ``confnav simulate`` runs such starts on an atlas; here, when a robot's law on a
single map is built (or swapped) and its position is known, :func:`flat_here` checks that
position; where it is flat the controller asks the transform service for the workspace's
atlas (``{ws}~atlas``, :func:`confnav.atlas.wire.atlas_ws_id`: the same geometry solved chart
by chart, whose charts are short enough for their Green's functions to stay well above
rounding), keeps the robot on its single map meanwhile with a status saying why, and swaps it
to the atlas when that is installed (until its next goal: a new goal is checked afresh).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from confnav.services.controller_cache import ControllerCacheMixin
from confnav.services.controller_state import _Map, _Robot
from confnav.services.controller_warm import prime

from confnav.atlas.wire import atlas_ws_id

log = logging.getLogger(__name__)


def flat_phi() -> float:
    """``1 - phi`` below which the harmonic navigation function is flat (``confnav simulate``'s
    threshold, one source)."""
    from confnav.cli.simulate import FLAT_PHI

    return float(FLAT_PHI)


def flat_here(ctrl: Any, position: tuple[float, float] | None) -> str:
    """Why ``ctrl``'s harmonic navigation function cannot steer from ``position`` ("" if it
    can, or if this is no single-map harmonic law, or the position is unknown or outside the
    map's free space): ``1 - phi`` below :func:`flat_phi`, or phi not finite, there."""
    law = getattr(ctrl, "controller", ctrl)
    navfn = getattr(law, "navfn", None)
    if (
        navfn is None
        or position is None
        or getattr(navfn, "name", "") != "harmonic"
        or not hasattr(law, "cmap")
    ):
        return ""
    ws = getattr(getattr(law, "cmap", None), "workspace", None)
    z = complex(position[0], position[1])
    if ws is None or not bool(ws.contains(z)):
        return ""
    cmap = law.cmap  # phi = navfn(T(z)): T alone (no T'), one point, off the pose path
    T = getattr(cmap, "T", None)
    w = T(np.array([z])) if T is not None else cmap.T_and_dT(np.array([z]))[0]
    phi = float(np.asarray(navfn.value(np.asarray(w)), dtype=np.float64)[0])
    flat = flat_phi()
    if 1.0 - phi >= flat:  # False for NaN: not finite counts as flat
        return ""
    value = f"1 - phi = {1.0 - phi:.1e}" if np.isfinite(phi) else "phi not finite"
    return (
        f"the navigation function is flat at ({z.real:.3g}, {z.imag:.3g}) ({value}, below "
        f"{flat:.0e}: the goal's Green's function decays below double precision along the "
        "corridors between)"
    )


class FlatMixin(ControllerCacheMixin):
    """Robots whose navigation function is flat where they stand (module docstring)."""

    def _check_flat(self, r: _Robot) -> None:
        """Check ``r``'s law at its position once per law (off the pose path); where it is
        flat, ask for the atlas of its workspace (and drive on it if installed)."""
        with r.lock:
            goal, ctrl, pos = r.goal, r.ctrl, r.position
            if (
                goal is None
                or ctrl is None
                or pos is None
                or r.base_ws
                or r.atlas_ws
                or r.flat_checked is ctrl
            ):
                return
            r.flat_checked = ctrl
        try:
            why = flat_here(ctrl, pos)
        except Exception:  # the pose path meets the same error and reports it
            log.debug("flat check", exc_info=True)
            return
        if not why:
            return
        aid = atlas_ws_id(goal.ws_id)
        with r.lock:
            if r.goal is not goal:
                return
            r.atlas_ws, r.flat_note = aid, why
        self.count("flat_starts")
        log.info("robot %r: %s; asking for the atlas %r", r.robot_id, why, aid)
        m = self._maps.get(aid)
        if m is not None:
            self._adopt_atlas(r, aid, m)
        else:
            self._wake_fetch.set()

    def _adopt_atlas(self, r: _Robot, aid: str, m: _Map) -> None:
        """Drive ``r`` on the atlas ``m`` (id ``aid``) it asked for, with its goal."""
        with r.lock:
            goal = r.goal
            if goal is None or r.atlas_ws != aid or r.ctrl_revision == m.revision:
                return
        ctrl, err = self._build(m, goal)
        prime(ctrl, r.position)
        with r.lock:
            if r.goal is goal and r.atlas_ws == aid and ctrl is not None:
                r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, m.revision, err
                log.info("robot %r: driving on the atlas %r", r.robot_id, aid)

    def _atlas_installed(self, ws_id: str, m: _Map) -> None:
        """An atlas ``{ws}~atlas`` was installed: the robots that asked for it drive on it."""
        with self._lock:
            robots = [r for r in self._robots.values() if r.atlas_ws == ws_id]
        for r in robots:
            self._adopt_atlas(r, ws_id, m)

    def _flat_note(self, r: _Robot) -> str:
        """The status note of a robot that asked for an atlas ("" otherwise)."""
        if not r.atlas_ws:
            return ""
        if r.atlas_ws in self._maps and r.ctrl_revision == self._maps[r.atlas_ws].revision:
            return f"navigating on the atlas {r.atlas_ws!r} ({r.flat_note})"
        err = self._map_errors.get(r.atlas_ws, "")
        tail = f" ({err})" if err and "being solved" not in err else ""
        return f"{r.flat_note}; atlas {r.atlas_ws!r} being solved{tail}"
