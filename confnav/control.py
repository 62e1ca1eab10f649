"""Feedback law of the seed paper's Theorem 2 for kinematic robots ``x' = u``.

``u(x) = -K conj(T'(x)) grad phi(T(x))`` (complex form of ``-K J_T^T grad phi``, DESIGN.md
section 3): the negative workspace gradient of the Lyapunov function ``V = phi o T``, whose
image in the circle domain is ``w' = -K |T'|^2 grad phi``.  Because ``|T'|`` is unbounded at
obstacle corners that point into free space, ``u`` is scaled to at most ``v_max`` keeping its
direction; ``dV/dt = -K s |T'|^2 |grad phi|^2 <= 0`` with the scale ``s in (0, 1]``, so the
saturated law still decreases V.

The law depends on the map only through :class:`ConformalLike` (``T_and_dT``, ``centers``,
``radii``), so exact maps can stand in for the solver in tests.  A new goal reuses the map
(:meth:`Controller.with_goal`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import MapMismatchError, NavigationError
from confnav.navfn import CircleDomain, NavigationFunction, make_navfn

if TYPE_CHECKING:
    from confnav.critical import CriticalPoints
    from confnav.geometry import Workspace

__all__ = ["ConformalLike", "ControlOutput", "Controller", "Status"]

CArray = NDArray[np.complex128]
FArray = NDArray[np.float64]


class ConformalLike(Protocol):
    """What the control law needs from a conformal map (``confnav.ConformalMap`` has it).

    ``T_and_dT(z)`` returns ``(T(z), T'(z))`` for a complex array of any shape, NaN outside
    the closed free space; ``centers``/``radii`` describe the circle domain.
    """

    @property
    def centers(self) -> Any: ...

    @property
    def radii(self) -> Any: ...

    def T_and_dT(self, z: Any) -> tuple[Any, Any]: ...


class Status(enum.IntEnum):
    """Per-robot status of the control law."""

    MOVING = 0
    ARRIVED = 1  # within goal_tol of the goal (u = 0)
    STALLED = 2  # |grad phi| below stall_tol away from the goal: at/near a saddle
    ERROR = 3  # NaN pose or pose outside the free space (u = 0)


@dataclass(frozen=True)
class ControlOutput:
    """Result of one control step for a batch of robots (arrays of the pose's shape).

    u: commanded velocity (complex, workspace units per time unit); status: :class:`Status`
    codes (int8); phi: ``V = phi(T(x))``; w: ``T(x)``; saturated: True where ``|u|`` was
    scaled down to ``v_max``.
    """

    u: CArray
    status: NDArray[np.int8]
    phi: FArray
    w: CArray
    saturated: NDArray[np.bool_]


def _workspace_contains(cmap: ConformalLike, z: complex) -> bool | None:
    ws = getattr(cmap, "workspace", None)
    if ws is None or not hasattr(ws, "contains"):
        return None
    return bool(np.asarray(ws.contains(np.asarray(z))))


class Controller:
    """The Theorem 2 feedback law for one goal on one conformal map.

    Parameters
    ----------
    cmap : ConformalLike, e.g. a ``confnav.ConformalMap``.
    goal : complex (or (x, y)), in the free space.
    navfn : ``"harmonic"`` (default: tuning-free) or ``"kr"``; or a ready
        :class:`NavigationFunction` on the map's circle domain with goal ``T(goal)``.
    k : for ``"kr"``: a number (the seed uses 6) or ``"auto"`` (default, checked k).
    gain : K > 0.
    v_max : speed limit (> 0, may be ``inf``).
    goal_tol : distance to the goal (workspace units) counted as arrived.
    stall_tol : ``|grad phi|`` (circle domain) below which a robot away from the goal is
        reported STALLED.
    v_min : optional speed floor (0 = off, the plain Theorem 2 law): ``u`` is scaled up,
        keeping its direction, to at least ``v_min * min(1, |x - x_d| / floor_radius)``.
        A positive scaling keeps the paths and dV/dt < 0; it removes the crawl where
        ``|T'|`` is tiny (crowded corridors, deep pockets: ``|T'| ~ exp(-pi L/w)``).
    workspace : the workspace in use; if given, a map whose ``workspace_hash`` differs from
        its ``content_hash`` is refused with :class:`~confnav.errors.MapMismatchError`.
    """

    def __init__(
        self,
        cmap: ConformalLike,
        goal: complex | tuple[float, float] | ArrayLike,
        *,
        navfn: Literal["kr", "harmonic"] | str | NavigationFunction = "harmonic",
        k: float | Literal["auto"] = "auto",
        gain: float = 1.0,
        v_max: float = np.inf,
        goal_tol: float = 1e-3,
        stall_tol: float = 1e-9,
        v_min: float = 0.0,
        floor_radius: float = 0.1,
        workspace: Workspace | None = None,
    ) -> None:
        bound = getattr(cmap, "workspace_hash", None)
        if workspace is not None and bound != workspace.content_hash:  # issue 8
            raise MapMismatchError(
                f"the map was solved for workspace {str(bound)[:12]}, not for the one in use "
                f"{workspace.content_hash[:12]}"
            )
        self.cmap = cmap
        self.goal = _as_point(goal, "goal")
        if not float(gain) > 0 or not np.isfinite(gain):
            raise NavigationError(f"gain must be positive and finite, got {gain!r}")
        if not float(v_max) > 0:
            raise NavigationError(f"v_max must be positive, got {v_max!r}")
        if not float(goal_tol) > 0:
            raise NavigationError(f"goal_tol must be positive, got {goal_tol!r}")
        self.gain = float(gain)
        self.v_max = float(v_max)
        self.goal_tol = float(goal_tol)
        self.stall_tol = float(stall_tol)
        if not (0 <= float(v_min) <= float(v_max)) or not float(floor_radius) > 0:
            raise NavigationError("need 0 <= v_min <= v_max and floor_radius > 0")
        self.v_min = float(v_min)
        self.floor_radius = float(floor_radius)
        if _workspace_contains(cmap, self.goal) is False:
            raise NavigationError(f"goal {self.goal:.6g} is not in the free space")
        wd = complex(np.asarray(cmap.T_and_dT(np.asarray(self.goal))[0]))
        if not np.isfinite(wd):
            raise NavigationError(f"goal {self.goal:.6g} is not in the free space (T is NaN)")
        if isinstance(navfn, NavigationFunction):
            self.domain = navfn.domain
            if abs(navfn.goal - wd) > 1e-9:
                raise NavigationError("navigation function goal differs from T(goal)")
            self.navfn = navfn
        else:
            self.domain = CircleDomain.of(cmap)
            self.navfn = make_navfn(navfn, self.domain, wd, k=k)
        self.goal_w = wd

    def with_goal(self, goal: complex | tuple[float, float] | ArrayLike) -> Controller:
        """A controller for a new goal on the same map (no new solve); same parameters."""
        z = _as_point(goal, "goal")
        wd = complex(np.asarray(self.cmap.T_and_dT(np.asarray(z))[0]))
        if not np.isfinite(wd) or _workspace_contains(self.cmap, z) is False:
            raise NavigationError(f"goal {z:.6g} is not in the free space")
        nf = self.navfn.with_goal(wd)
        return Controller(
            self.cmap,
            z,
            navfn=nf,
            gain=self.gain,
            v_max=self.v_max,
            goal_tol=self.goal_tol,
            stall_tol=self.stall_tol,
            v_min=self.v_min,
            floor_radius=self.floor_radius,
        )

    def velocity(self, z: ArrayLike) -> CArray:
        """The saturated command ``u`` only (hot path; NaN outside the free space)."""
        w, dw = self.cmap.T_and_dT(z)
        g = self.navfn.gradient(w)
        u = -self.gain * np.conj(dw) * g
        if self.v_max < np.inf or self.v_min > 0:
            u = self._scale(u, z)[0]
        return np.asarray(u, dtype=np.complex128)

    def _scale(self, u: CArray, z: ArrayLike) -> tuple[CArray, NDArray[np.bool_]]:
        """Saturate to v_max and lift to the floor, keeping the direction."""
        s = np.abs(u)
        target = np.minimum(s, self.v_max)
        if self.v_min > 0:
            dist = np.abs(np.asarray(z) - self.goal)
            target = np.maximum(target, self.v_min * np.minimum(1.0, dist / self.floor_radius))
        # no division by zero (u = 0 stays 0); NaN propagates silently
        scaled = u * (target / np.maximum(s, 1e-300))
        return scaled, s > self.v_max

    def __call__(self, z: ArrayLike) -> ControlOutput:
        """Command and status for a batch of robot positions (complex array, any shape)."""
        z = np.asarray(z, dtype=np.complex128)
        bad = ~np.isfinite(z)
        w, dw = self.cmap.T_and_dT(np.where(bad, self.goal, z))
        w = np.asarray(w, dtype=np.complex128)
        dw = np.asarray(dw, dtype=np.complex128)
        bad |= ~np.isfinite(w) | ~np.isfinite(dw)
        w = np.where(bad, self.goal_w, w)
        phi, g = self.navfn.value_and_gradient(w)
        u = -self.gain * np.conj(dw) * g
        u, sat = self._scale(u, z)
        arrived = ~bad & (np.abs(z - self.goal) <= self.goal_tol)
        stalled = ~bad & ~arrived & (np.abs(g) < self.stall_tol)
        status = np.full(z.shape, Status.MOVING, dtype=np.int8)
        status[stalled] = Status.STALLED
        status[arrived] = Status.ARRIVED
        status[bad] = Status.ERROR
        u = np.where(arrived | bad, 0j, u)
        return ControlOutput(
            u=u,
            status=status,
            phi=np.where(bad, np.nan, phi),
            w=np.where(bad, np.nan + 0j, w),
            saturated=sat & ~arrived & ~bad,
        )

    def check(self) -> CriticalPoints:
        """Critical points of the navigation function in the circle domain (one minimum and
        M saddles expected; ``.ok`` False means e.g. k too small for this geometry)."""
        from confnav.critical import find_critical_points

        return find_critical_points(self.navfn)

    def lyapunov(self, z: ArrayLike) -> FArray:
        """``V(x) = phi(T(x))`` (NaN outside the free space)."""
        w = np.asarray(self.cmap.T_and_dT(z)[0], dtype=np.complex128)
        return self.navfn.value(w)

    def __repr__(self) -> str:
        return (
            f"Controller(goal={self.goal:.6g}, navfn={self.navfn!r}, gain={self.gain:g}, "
            f"v_max={self.v_max:g}, goal_tol={self.goal_tol:g})"
        )


def _as_point(p: complex | tuple[float, float] | ArrayLike, what: str) -> complex:
    """A finite complex point from a complex number or an (x, y) pair."""
    a = np.asarray(p)
    try:
        if a.shape == (2,) and not np.iscomplexobj(a):
            z = complex(float(a[0]), float(a[1]))
        elif a.shape == ():
            z = complex(a.item())
        else:
            raise TypeError
    except (TypeError, ValueError):
        raise NavigationError(f"{what} must be a complex number or an (x, y) pair") from None
    if not np.isfinite(z):
        raise NavigationError(f"{what} {z} is not finite")
    return z
