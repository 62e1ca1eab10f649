"""The one place services touch the navigation library: load a map from a
``TransformSolution`` (with the per-map precompute of the harmonic function), build the
controller for a ``Goal`` and turn its output into what is published (:func:`decide`).
The controller service, ``replay --check`` and ``confnav demo`` all go through here. No math.

The wire-free part lives in the core (:mod:`confnav.navigation.messages`) and is re-exported
here, so a host imports one module; :data:`CRITICAL_SEARCH` is the background executor of the
controllers' critical-point searches (:mod:`confnav.services.critical_search`).
"""

from __future__ import annotations

import cmath
import logging
from typing import Any

from confnav.schemas import Goal, TransformSolution
from confnav.services.critical_search import CRITICAL_SEARCH

from confnav.navigation.messages import (
    ARRIVED,
    ERROR,
    MAX_BATCH,
    MOVING,
    NAV_ACCURACY,
    STALLED,
    ControllerLike,
    ControlOutputLike,
    Decision,
    command,
    commands,
    decide,
    precompute,
    reenter,
)

log = logging.getLogger(__name__)

__all__ = [
    "ARRIVED",
    "CRITICAL_SEARCH",
    "ERROR",
    "MAX_BATCH",
    "MOVING",
    "NAV_ACCURACY",
    "STALLED",
    "ControlOutputLike",
    "ControllerLike",
    "Decision",
    "command",
    "commands",
    "decide",
    "footprint_radius",
    "goal_key",
    "load_map",
    "make_controller",
    "map_ws_id",
    "point_law",
    "precompute",
    "reenter",
    "shrunk_workspace",
    "stands_in",
]


def load_map(solution: TransformSolution) -> Any:
    """The :class:`confnav.ConformalMap` of a solution message, prepared for control.

    The coefficients are bit-identical to the solver's; the controller evaluates them through
    ``for_navigation()`` (fewer boundary nodes, T and T' within 1e-7 of the full map, checked),
    which is deterministic, so ``replay --check`` recomputes exactly what the live controller
    commanded.

    Also factors the map's harmonic least-squares system once (:func:`precompute`): call this
    outside any lock; new goals on the map then cost one solve.
    """
    from confnav.conformal.cmap import ConformalMap
    from confnav.errors import MapMismatchError

    cmap = ConformalMap.from_dict(solution.coefficients)
    if cmap.workspace_hash != solution.workspace_hash:  # refuse a map of another workspace
        raise MapMismatchError(
            f"solution {solution.revision[:12]} declares workspace "
            f"{solution.workspace_hash[:12]} but its map was solved for "
            f"{cmap.workspace_hash[:12]}"
        )
    nav = cmap.for_navigation(accuracy=NAV_ACCURACY)
    setattr(nav, "ws_id", solution.ws_id)  # noqa: B010 (a base map can stand in, below)
    precompute(nav)
    return nav


def stands_in(cmap: Any, goal: Goal) -> bool:
    """True if ``cmap`` is the unshrunk map of the workspace of ``goal``, a goal whose robot
    has a footprint: it steers that robot until the footprint map ``{ws}~r{R}`` is solved,
    with the safety layer on the exact shrunk workspace keeping the body clear
    (:func:`make_controller`; docs/NAVIGATION.md, "Driving before the footprint map")."""
    from confnav.maps.footprint import parse_derived_ws_id

    ws = getattr(cmap, "ws_id", None)
    return (
        footprint_radius(goal) > 0
        and isinstance(ws, str)
        and parse_derived_ws_id(ws) is None
        and ws == (parse_derived_ws_id(goal.ws_id) or (goal.ws_id, 0.0))[0]
    )


def _footprint_id(cmap: Any, goal: Goal) -> str:
    """``{ws}~r{R}`` of ``goal``'s footprint on the workspace of the base map ``cmap``."""
    return map_ws_id(goal.model_copy(update={"ws_id": cmap.ws_id}))


def shrunk_workspace(cmap: Any, goal: Goal) -> Any:
    """The exact free space the safety layer keeps ``goal``'s robot in while the unshrunk map
    ``cmap`` stands in (:func:`stands_in`): the base workspace shrunk by the footprint, derived
    as the transform service derives ``{ws}~r{R}``
    (:func:`confnav.services.controller_footprint.shrunk_workspace`). Kept on the map, one per
    footprint (the safety filter's grid is cached per workspace object)."""
    from confnav.services.controller_footprint import base_workspace
    from confnav.services.controller_footprint import shrunk_workspace as derive

    ws_id = _footprint_id(cmap, goal)
    cache: dict[str, Any] = cmap.__dict__.setdefault("_shrunk_by", {})
    if ws_id not in cache:
        cache[ws_id] = derive(base_workspace(cmap), ws_id)
    return cache[ws_id]


def make_controller(cmap: Any, goal: Goal) -> ControllerLike:
    """The feedback law for ``goal`` on ``cmap`` (raises ``NavigationError`` for a bad goal).

    ``cmap`` is the map of :func:`map_ws_id` (the free space shrunk by the footprint); a
    unicycle goal gets the look-ahead law (:class:`confnav.navigation.unicycle.UnicycleController`),
    which answers body-frame twists ``v + i omega``.
    """
    from confnav.errors import NavigationError
    from confnav.maps.footprint import UnreachableGoalError

    if stands_in(cmap, goal):  # the unshrunk map steers, the exact shrunk geometry keeps safe
        from confnav.services.controller_footprint import make_controller_on_base

        fp = goal.model_copy(update={"ws_id": _footprint_id(cmap, goal)})
        return make_controller_on_base(cmap, fp, shrunk_workspace(cmap, goal))
    if getattr(cmap, "is_atlas", False):  # confnav.atlas.wire.AtlasMap: per-robot switching
        return cmap.controller(goal)  # type: ignore[no-any-return]
    try:
        return point_law(cmap, goal)
    except NavigationError as exc:
        if map_ws_id(goal) == goal.ws_id or "not in the free space" not in str(exc):
            raise
        raise UnreachableGoalError(
            f"goal {goal.goal} of robot {goal.robot_id!r} is unreachable: it is not in "
            f"{map_ws_id(goal)!r}, the largest component of {goal.ws_id!r} shrunk by the "
            f"footprint {footprint_radius(goal):g} m (within that distance of an obstacle, or "
            "cut off by a passage narrower than twice it)"
        ) from exc


def point_law(cmap: Any, goal: Goal, safety: Any = None) -> ControllerLike:
    """The goal's law on the single map ``cmap`` (:class:`confnav.navigation.control
    .Controller`, wrapped in the look-ahead law for a unicycle); ``safety``: the workspace the
    safety layer filters against (None: the map's own)."""
    from confnav.navigation.control import Controller

    ctrl = Controller(
        cmap,
        complex(goal.goal[0], goal.goal[1]),
        navfn=goal.navfn,
        k="auto" if goal.k is None else goal.k,
        speed_law=goal.speed_law,
        gain=goal.gain,
        v_max=goal.v_max,
        goal_tol=goal.tolerance,
        safety=safety,
    )
    if goal.drive == "unicycle":
        from confnav.navigation.unicycle import UnicycleController

        return UnicycleController(ctrl, goal.lookahead, v_max=goal.v_max, omega_max=goal.omega_max)
    return ctrl


def steered_point(goal: Goal, x: float, y: float, theta: float) -> complex:
    """The point a robot's law steers at pose ``(x, y, theta)``: the position, or a
    unicycle's look-ahead point ``x + d e^{i theta}`` (docs/NAVIGATION.md, unicycles)."""
    d = goal.lookahead if goal.drive == "unicycle" else 0.0
    return complex(x, y) + d * cmath.exp(1j * theta)


def footprint_radius(goal: Goal) -> float:
    """How far the free space is shrunk for this robot: radius (+ look-ahead for unicycles)."""
    return float(goal.robot_radius + (goal.lookahead if goal.drive == "unicycle" else 0.0))


def map_ws_id(goal: Goal) -> str:
    """The workspace whose map drives this robot: ``ws_id`` or ``{ws_id}~r{footprint}``."""
    from confnav.maps.footprint import derived_ws_id

    return derived_ws_id(goal.ws_id, footprint_radius(goal))


def goal_key(goal: Goal) -> tuple[object, ...]:
    """What determines the controller of a goal on a given map (robots sharing it share one)."""
    return (
        goal.ws_id, goal.goal, goal.navfn, goal.k, goal.speed_law, goal.gain, goal.v_max,
        goal.tolerance, goal.robot_radius, goal.drive, goal.lookahead, goal.omega_max,
    )  # fmt: skip
