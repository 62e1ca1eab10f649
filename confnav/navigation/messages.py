"""What a host publishes from the control law: the decision for one pose (:func:`decide`),
commands in blocks (:func:`commands`), the per-map precompute of the harmonic function. No
wire models and no math: the wire side (a map from a ``TransformSolution``, the controller for
a ``Goal``) is :mod:`confnav.services.navigation`, which re-exports this module.  The controller
service, ``replay --check`` and ``confnav demo`` all go through there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

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


def precompute(cmap: Any) -> None:
    """Per-map work of the harmonic navigation function (shared by every later goal)."""
    from confnav.navigation.harmonic import GreenBasis
    from confnav.navigation.navfn import CircleDomain

    try:
        GreenBasis.for_domain(CircleDomain.of(cmap)).precompute()
    except Exception as exc:  # a goal needing more terms reports it when it is built
        log.info("harmonic precompute: %s", exc)


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


def law_workspace(ctrl: Any) -> Any:
    """The free space a controller's law is defined on (its reference point's), or None: the
    safety layer's workspace, an atlas's whole workspace, or the map's; through a unicycle's
    look-ahead law to the point law it wraps."""
    inner = getattr(ctrl, "controller", ctrl)
    for path in (("safety", "workspace"), ("nav", "atlas", "workspace"), ("cmap", "workspace")):
        obj: Any = inner
        for name in path:
            obj = getattr(obj, name, None)
            if obj is None:
                break
        if obj is not None and hasattr(obj, "clearance1") and hasattr(obj, "polygon"):
            return obj
    return None


def reenter(
    ctrl: Any, x: float, y: float, theta: float, u: complex, code: int
) -> tuple[complex, int, str]:
    """``(u, code, note)`` of one robot's law output, with a reference point just outside the
    law's free space (ERROR with no other stop reason) steered back in
    (:mod:`confnav.navigation.reentry`): the re-entry command (a unicycle's twist), MOVING and
    a status note; any other output unchanged with an empty note. The controller service
    applies it before its fleet filter and ``replay --check`` after :func:`command`, so both
    compute the same command."""
    if code != ERROR or getattr(ctrl, "stop_reason", None):
        return u, code, ""
    from confnav.navigation.reentry import reentry_velocity

    ws = law_workspace(ctrl)
    if ws is None:
        return u, code, ""
    body = getattr(ctrl, "frame", "world") == "body"
    d = float(getattr(ctrl, "d", 0.0)) if body else 0.0
    p = complex(x, y) + d * complex(np.cos(theta), np.sin(theta))
    got = reentry_velocity(ws, p)
    if got is None:
        return u, code, ""
    up, depth = got
    note = f"re-entering the map's free space ({depth:.3g} m outside it)"
    if not body:
        return up, MOVING, note
    from confnav.navigation.unicycle import twist_from_velocity

    v, omega = twist_from_velocity(
        up, theta, d, getattr(ctrl, "v_max", np.inf), getattr(ctrl, "omega_max", np.inf)
    )
    return complex(float(v), float(omega)), MOVING, note


def command(ctrl: ControllerLike, x: float, y: float, theta: float = 0.0) -> tuple[complex, int]:
    """(u, status) for one robot at (x, y) heading ``theta`` (read by body-frame controllers
    only: :func:`commands`, as the controller service calls them)."""
    u, codes = commands(ctrl, np.array([complex(x, y)]), np.array([float(theta)]))
    return complex(u[0]), int(codes[0])
