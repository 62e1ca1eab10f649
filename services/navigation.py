"""The one place services touch the navigation library: load a map from a
``TransformSolution`` and build the Theorem 2 controller for a ``Goal``. No math here."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from confnav.schemas import Goal, TransformSolution

# Status codes of confnav.control.Status (kept as ints so tests can fake the controller).
MOVING, ARRIVED, STALLED, ERROR = 0, 1, 2, 3


class ControlOutputLike(Protocol):
    @property
    def u(self) -> Any: ...

    @property
    def status(self) -> Any: ...


class ControllerLike(Protocol):
    """``confnav.control.Controller``: called on positions (complex array), returns u and
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
    """
    from confnav.cmap import ConformalMap
    from confnav.errors import MapMismatchError

    cmap = ConformalMap.from_dict(solution.coefficients)
    if cmap.workspace_hash != solution.workspace_hash:  # refuse a map of another workspace
        raise MapMismatchError(
            f"solution {solution.revision[:12]} declares workspace "
            f"{solution.workspace_hash[:12]} but its map was solved for "
            f"{cmap.workspace_hash[:12]}"
        )
    return cmap.for_navigation(accuracy=NAV_ACCURACY)


def make_controller(cmap: Any, goal: Goal) -> ControllerLike:
    """The feedback law for ``goal`` on ``cmap`` (raises ``NavigationError`` for a bad goal)."""
    from confnav.control import Controller

    return Controller(
        cmap,
        complex(goal.goal[0], goal.goal[1]),
        navfn=goal.navfn,
        k="auto" if goal.k is None else goal.k,
        gain=goal.gain,
        v_max=goal.v_max,
        goal_tol=goal.tolerance,
    )


def goal_key(goal: Goal) -> tuple[object, ...]:
    """What determines the controller of a goal on a given map (robots sharing it share one)."""
    return (goal.ws_id, goal.goal, goal.navfn, goal.k, goal.gain, goal.v_max, goal.tolerance)


#: Largest batch per control-law call. The core evaluates T by dense Cauchy sums for few
#: targets and switches to the FMM (about 15 ms fixed cost) above 64 targets; for the few
#: thousand boundary nodes of a typical map the dense path is faster up to this size.
MAX_BATCH = 32


def commands(ctrl: ControllerLike, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, status) for a batch of positions ``z`` (complex array), vectorized in blocks."""
    z = np.asarray(z, dtype=complex)
    us, codes = [], []
    for s in range(0, z.size, MAX_BATCH):
        out = ctrl(z[s : s + MAX_BATCH])
        us.append(np.asarray(out.u, dtype=complex).reshape(-1))
        codes.append(np.asarray(out.status, dtype=int).reshape(-1))
    return np.concatenate(us), np.concatenate(codes)


def command(ctrl: ControllerLike, x: float, y: float) -> tuple[complex, int]:
    """(u, status) for one robot at (x, y)."""
    out = ctrl(np.asarray(complex(x, y)))
    return complex(np.asarray(out.u).item()), int(np.asarray(out.status).item())
