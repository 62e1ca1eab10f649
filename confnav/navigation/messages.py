"""The one place services touch the navigation library: load a map from a
``TransformSolution`` (with the per-map precompute of the harmonic function), build the
controller for a ``Goal`` and turn its output into what is published (:func:`decide`).
The controller service, ``replay --check`` and ``confnav demo`` all go through here. No math.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from confnav.schemas import Goal, TransformSolution

log = logging.getLogger(__name__)

# Status codes of confnav.navigation.control.Status (kept as ints so tests can fake the controller).
MOVING, ARRIVED, STALLED, ERROR = 0, 1, 2, 3


class ControlOutputLike(Protocol):
    @property
    def u(self) -> Any: ...

    @property
    def status(self) -> Any: ...


class ControllerLike(Protocol):
    """``confnav.navigation.control.Controller``: called on positions (complex array), returns u and
    status codes (MOVING, ARRIVED, STALLED, ERROR)."""

    def __call__(self, z: Any) -> ControlOutputLike: ...


#: Accuracy of T and T' the controller needs from the map (relative for T'); a command's
#: direction error is of this order.
NAV_ACCURACY = 1e-7


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
    precompute(nav)
    return nav


def precompute(cmap: Any) -> None:
    """Per-map work of the harmonic navigation function (shared by every later goal)."""
    from confnav.navigation.harmonic import GreenBasis
    from confnav.navigation.navfn import CircleDomain

    try:
        GreenBasis.for_domain(CircleDomain.of(cmap)).precompute()
    except Exception as exc:  # a goal needing more terms reports it when it is built
        log.info("harmonic precompute: %s", exc)


def make_controller(cmap: Any, goal: Goal) -> ControllerLike:
    """The feedback law for ``goal`` on ``cmap`` (raises ``NavigationError`` for a bad goal).

    ``cmap`` is the map of :func:`map_ws_id` (the free space shrunk by the footprint); a
    unicycle goal gets the look-ahead law (:class:`confnav.navigation.unicycle.UnicycleController`),
    which answers body-frame twists ``v + i omega``.
    """
    from confnav.errors import NavigationError
    from confnav.maps.footprint import UnreachableGoalError
    from confnav.navigation.control import Controller

    if getattr(cmap, "is_atlas", False):  # confnav.atlas.wire.AtlasMap: per-robot switching
        return cmap.controller(goal)  # type: ignore[no-any-return]
    try:
        ctrl = Controller(
            cmap,
            complex(goal.goal[0], goal.goal[1]),
            navfn=goal.navfn,
            k="auto" if goal.k is None else goal.k,
            speed_law=goal.speed_law,
            gain=goal.gain,
            v_max=goal.v_max,
            goal_tol=goal.tolerance,
        )
    except NavigationError as exc:
        if map_ws_id(goal) == goal.ws_id or "not in the free space" not in str(exc):
            raise
        raise UnreachableGoalError(
            f"goal {goal.goal} of robot {goal.robot_id!r} is unreachable: it is not in "
            f"{map_ws_id(goal)!r}, the largest component of {goal.ws_id!r} shrunk by the "
            f"footprint {footprint_radius(goal):g} m (within that distance of an obstacle, or "
            "cut off by a passage narrower than twice it)"
        ) from exc
    if goal.drive == "unicycle":
        from confnav.navigation.unicycle import UnicycleController

        return UnicycleController(ctrl, goal.lookahead, v_max=goal.v_max, omega_max=goal.omega_max)
    return ctrl


def footprint_radius(goal: Goal) -> float:
    """How far the free space is shrunk for this robot: radius (+ look-ahead for unicycles)."""
    return goal.robot_radius + (goal.lookahead if goal.drive == "unicycle" else 0.0)


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


@dataclass(frozen=True)
class Decision:
    """What the controller publishes for one pose: the command and the status fields."""

    u: complex
    state: str  # RobotStatus.state: "navigating", "arrived" or "stopped"
    reason: str  # RobotStatus.reason
    message: str


def decide(ctrl: ControllerLike, u: complex, code: int) -> Decision:
    """The published command and status for the control law's ``(u, code)`` of one pose.

    The live controller service and ``replay --check`` both call this (never a copy): zero
    and ``stopped`` outside the free space (ERROR or NaN), zero at the goal, else ``u``; a
    navigation-function fallback (``Controller.fallback``) is said in the message.
    """
    if code == ERROR or u != u:  # NaN guard
        why = getattr(ctrl, "stop_reason", None)  # e.g. an atlas cell cut off from the goal
        if why:
            return Decision(0j, "stopped", why[0], why[1])
        return Decision(0j, "stopped", "outside_workspace", "pose outside the mapped free space")
    if code == ARRIVED:
        return Decision(0j, "arrived", "arrived", "")
    note = getattr(ctrl, "fallback", "")
    msg = "stalled at a critical point of phi (saddle)" if code == STALLED else ""
    return Decision(u, "navigating", "ok", "; ".join(m for m in (msg, note) if m))


#: Largest batch per control-law call. The core evaluates T by dense Cauchy sums for few
#: targets and switches to the FMM (about 15 ms fixed cost) above 64 targets; for the few
#: thousand boundary nodes of a typical map the dense path is faster up to this size.
MAX_BATCH = 32


def commands(
    ctrl: ControllerLike, z: np.ndarray, theta: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(u, status) for a batch of positions ``z`` (complex array), vectorized in blocks.

    For a body-frame controller (``ctrl.frame == "body"``, unicycles) the headings ``theta``
    are passed too and ``u`` is the twist ``v + i omega``.
    """
    z = np.asarray(z, dtype=complex)
    body = getattr(ctrl, "frame", "world") == "body"
    th = np.zeros(z.shape) if theta is None else np.asarray(theta, dtype=float)
    us, codes = [], []
    for s in range(0, z.size, MAX_BATCH):
        blk = slice(s, s + MAX_BATCH)
        out = ctrl(z[blk], th[blk]) if body else ctrl(z[blk])  # type: ignore[call-arg]
        us.append(np.asarray(out.u, dtype=complex).reshape(-1))
        codes.append(np.asarray(out.status, dtype=int).reshape(-1))
    return np.concatenate(us), np.concatenate(codes)


def command(ctrl: ControllerLike, x: float, y: float, theta: float = 0.0) -> tuple[complex, int]:
    """(u, status) for one robot at (x, y) heading ``theta`` (read by body-frame controllers
    only: :func:`commands`, as the controller service calls them)."""
    u, codes = commands(ctrl, np.array([complex(x, y)]), np.array([float(theta)]))
    return complex(u[0]), int(codes[0])
