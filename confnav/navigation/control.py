"""Feedback law of the seed paper's Theorem 2 for kinematic robots ``x' = u``, with a speed law.

The Theorem 2 field is ``f(x) = -conj(T'(x)) grad phi(T(x))`` (complex form of
``-J_T^T grad phi``, DESIGN.md section 3): the negative workspace gradient of the Lyapunov
function ``V = phi o T``, whose image in the circle domain is ``w' = -|T'|^2 grad phi``.
Two speed laws drive the robot along it (:data:`confnav.navigation.defaults.SPEED_LAWS`):

``"normalized"`` (default)
    ``u = f / |f| * v(x)`` with ``v = min(v_max, gain |x - x_d|)``, optionally times
    ``clip(clearance / slow_distance, 0.2, 1)`` near walls.  ``|f| = |T'| |grad phi|`` is
    exponentially small in pockets, behind obstacles and far from the goal (3e-11 m/s
    measured with the goal in a charging alcove); the speed of this law does not depend on it.
``"theorem2"``
    the plain law ``u = gain f``, scaled down to ``v_max`` keeping its direction.

**Why the paths and the guarantees are the same.**  Both laws are ``u = s(x) f(x)`` with a
scalar ``s > 0`` wherever ``f != 0`` (``s = v/|f|`` resp. ``gain * min(1, v_max/|gain f|)``).
On the set where ``f != 0`` (the free space minus the critical points of V) the solutions of
``x' = s f`` are those of ``x' = f`` under the time change ``dtau/dt = s(x(t)) > 0``, so both
fields have the same integral curves, traversed in the same direction [1]_ (time changes of
flows; e.g. Chicone, *Ordinary Differential Equations with Applications*, Prop. 1.14).  Every
property of Theorem 2 that is a property of the curves carries over: the free space is
positively invariant (no collision), and every curve not on the stable manifold of a saddle
(a set of measure zero) ends at the goal (almost-global convergence; Koditschek-Rimon
1990 [2]_, Prop. 2.4, and DESIGN.md section 3).  ``dV/dt = s <grad V, f> = -s |f|^2 < 0``
off the critical points.  Convergence in *finite-looking* time is what changes: with
``v >= min(v_max, gain d)`` the robot reaches the goal disk of radius ``goal_tol`` after at
most ``L / v_max + log(v_max / (gain goal_tol)) / gain`` seconds along a path of length L.
Where ``f = 0`` (the goal and the M saddles) the direction is undefined and ``u = 0``.

**Held commands.**  A robot applies a command until ``hold_time`` after the pose it answers
(the simulator's ``max_cmd_age``, :data:`~confnav.navigation.defaults.HOLD_TIME`), i.e. up to
``|u| hold_time`` away from that pose.  Both laws cap the speed at
``HOLD_FRACTION * c(x) / hold_time`` with ``c`` the clearance of the map's workspace (shrunk by
the footprint): the held command ends inside the disk of radius ``c`` about ``x``, which lies in
the free space.  The cap is one more factor ``s > 0`` off the walls: same curves as above;
the time bound holds where it does not bind (``c >= v_max hold_time / HOLD_FRACTION``).

**Safety layer.**  After the speed law every command passes the filter of
:mod:`confnav.navigation.safety` (on by default when the map has a workspace): the nearest
command that keeps the robot out of every wall by the exact polygon distance (control barrier
function rows per nearby side, and the held-command cap above with the exact clearance), so
no contact depends on the map's accuracy; where no row binds the command is the law's, bitwise
(docs/NAVIGATION.md, "Safety layer").

The law depends on the map only through :class:`ConformalLike` (``T_and_dT``, ``centers``,
``radii``), so exact maps can stand in for the solver in tests.  A new goal reuses the map
(:meth:`Controller.with_goal`) and, for the harmonic function, the map's factorization.
The speed law itself is :func:`speed_law`, the ONE implementation that the controller
service, ``confnav simulate``, ``confnav demo`` and ``replay --check`` all run.

References
----------
.. [1] C. Chicone, Ordinary Differential Equations with Applications, 2nd ed., Springer
   (2006), section 1.3 (reparametrization of time).
.. [2] D. E. Koditschek and E. Rimon, "Robot navigation functions on manifolds with
   boundary", Advances in Applied Mathematics 11 (1990) 412-442.
"""

from __future__ import annotations

import cmath
import enum
import logging
import threading
import weakref
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import MapMismatchError, NavigationError, fmt_point
from confnav.navigation import defaults
from confnav.navigation.factory import make_navfn
from confnav.navigation.navfn import CircleDomain, NavigationFunction
from confnav.navigation.safety import SafetyFilter, safety_filter
from confnav.types import CArray, FArray, as_point

if TYPE_CHECKING:
    from confnav.geometry import Workspace
    from confnav.navigation.critical import CriticalPoints

log = logging.getLogger(__name__)

__all__ = [
    "ConformalLike",
    "ControlOutput",
    "Controller",
    "SafetyCounts",
    "SearchExecutor",
    "Status",
    "speed_law",
]


#: Lowest factor of the optional slow-down near walls (keeps the speed positive: same paths).
SLOW_FLOOR = 0.2
_NO_POINTS: CArray = np.zeros(0, dtype=np.complex128)


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


class SearchExecutor(Protocol):
    """Runs critical-point searches in the background for
    :meth:`Controller.search_critical_points`: ``submit_search(ref, future)`` must eventually
    complete ``future`` with ``ref().critical_points()`` (or its exception), or cancel it when
    ``ref()`` is None (nobody holds the controller any more)."""

    def submit_search(
        self, controller: weakref.ref[Controller], future: Future[CriticalPoints]
    ) -> None: ...


class Status(enum.IntEnum):
    """Per-robot status of the control law."""

    MOVING = 0
    ARRIVED = 1  # within goal_tol of the goal (u = 0)
    STALLED = 2  # within stall_radius of a critical point of phi other than the goal
    ERROR = 3  # NaN pose or pose outside the free space (u = 0)


@dataclass(frozen=True)
class ControlOutput:
    """Result of one control step for a batch of robots (arrays of the pose's shape).

    u: commanded velocity (complex, m/s); status: :class:`Status` codes (int8);
    phi: ``V = phi(T(x))``; w: ``T(x)``; saturated: True where the speed is ``v_max``;
    filtered: True where the safety layer (:mod:`confnav.navigation.safety`) changed the
    law's command (None: no safety layer).
    """

    u: CArray
    status: NDArray[np.int8]
    phi: FArray
    w: CArray
    saturated: NDArray[np.bool_]
    filtered: NDArray[np.bool_] | None = None


def speed_law(
    field: CArray,
    dist: FArray,
    *,
    law: str = defaults.SPEED_LAW,
    gain: float | FArray = defaults.GAIN,
    v_max: float | FArray = defaults.V_MAX,
    slow: FArray | None = None,
    v_cap: FArray | None = None,
) -> tuple[CArray, NDArray[np.bool_]]:
    """The command ``u = s f`` (``s > 0``) from the Theorem 2 field ``f`` (module docstring).

    ``dist``: distance to the goal (m); ``slow``: optional factor in ``[SLOW_FLOOR, 1]``
    (normalized law only); ``v_cap``: optional per-point speed limit (m/s, >= 0, either
    law: ``u`` is scaled down to it keeping its direction).  Where ``f`` is 0 (goal,
    critical points) ``u = 0``; NaN stays NaN.  Returns ``(u, saturated)``.
    """
    u, sat = _speed_law(field, dist, law=law, gain=gain, v_max=v_max, slow=slow)
    if v_cap is None:
        return u, sat
    cap = np.asarray(v_cap, dtype=np.float64)
    speed = np.abs(u)
    capped = speed > cap
    scale = np.where(capped, cap / np.where(capped, speed, 1.0), 1.0)
    return np.asarray(u * scale, dtype=np.complex128), np.asarray(sat & ~capped)


def _speed_law(
    field: CArray,
    dist: FArray,
    *,
    law: str,
    gain: float | FArray,
    v_max: float | FArray,
    slow: FArray | None,
) -> tuple[CArray, NDArray[np.bool_]]:
    """:func:`speed_law` without the per-point cap."""
    f = np.asarray(field, dtype=np.complex128)
    size = np.abs(f)
    if law == "theorem2":
        u = gain * f
        s = gain * size
        sat = s > v_max
        scale = np.where(sat, v_max / np.where(sat, s, 1.0), 1.0)
        return np.asarray(u * scale, dtype=np.complex128), np.asarray(sat)
    if law != "normalized":
        raise NavigationError(f"unknown speed law {law!r}; choose from {defaults.SPEED_LAWS}")
    v = np.minimum(v_max, gain * np.asarray(dist, dtype=np.float64))
    sat = gain * np.asarray(dist) >= v_max
    if slow is not None:
        v = v * slow
    # unit direction; |f| = 0 (direction undefined) gives u = 0, never NaN
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.where(size > 0, f / np.where(size > 0, size, 1.0), np.where(size == 0, 0j, f))
    return np.asarray(unit * v, dtype=np.complex128), np.asarray(sat & (size > 0))


def _full(shape: tuple[int, ...], value: Any, dtype: type) -> Any:
    """``np.full(shape, value, dtype)``; a 0-d array by ``np.array`` (one C call instead of
    numpy's Python-level ``full``: the one-robot step builds five of them)."""
    return np.array(value, dtype=dtype) if shape == () else np.full(shape, value, dtype=dtype)


#: Least depth of a goal's image inside the circle domain (unit-disk scale): below it the goal
#: is on a boundary circle to rounding.
MIN_GOAL_DEPTH = 1e-12


def _workspace_contains(cmap: ConformalLike, z: complex) -> bool | None:
    ws = getattr(cmap, "workspace", None)
    if ws is None or not hasattr(ws, "contains"):
        return None
    return bool(np.asarray(ws.contains(np.asarray(z))))


@dataclass
class SafetyCounts:
    """How often a controller's safety layer ran (``commands``: robot commands filtered),
    changed the law's command (``changed``) and found no safe command but 0
    (``infeasible``: e.g. a pose outside the free space)."""

    commands: int = 0
    changed: int = 0
    infeasible: int = 0

    def add(self, commands: int, changed: int, infeasible: int) -> None:
        self.commands += commands
        self.changed += changed
        self.infeasible += infeasible

    @property
    def fraction_changed(self) -> float:
        return self.changed / self.commands if self.commands else 0.0


def _safety_layer(
    safety: bool | Workspace | SafetyFilter | None, ws: Any, hold_time: float
) -> SafetyFilter | None:
    """The controller's :class:`SafetyFilter` (``Controller(safety=...)``)."""
    from confnav.geometry import Workspace

    if safety is False:
        return None
    if isinstance(safety, SafetyFilter):
        return safety
    if isinstance(safety, Workspace):
        return safety_filter(safety, hold_time=hold_time)
    if isinstance(ws, Workspace):
        return safety_filter(ws, hold_time=hold_time)
    if safety is None:
        return None
    if safety is True:
        raise NavigationError("safety=True needs a map with a workspace (exact geometry)")
    raise NavigationError(
        f"safety must be a bool, a Workspace or a SafetyFilter, got {type(safety).__name__}"
    )


class Controller:
    """The navigation law for one goal on one conformal map.

    Parameters
    ----------
    cmap : ConformalLike, e.g. a ``confnav.ConformalMap``.
    goal : complex (or (x, y)), in the free space.
    navfn : ``"harmonic"`` (default: tuning-free) or ``"kr"``; or a ready
        :class:`NavigationFunction` on the map's circle domain with goal ``T(goal)``.  A
        harmonic fit that does not converge falls back to ``"kr"`` with automatic k;
        ``fallback`` then says why (never silent).
    k : for ``"kr"``: a number (the seed uses 6) or ``"auto"`` (default, checked k).
    speed_law : ``"normalized"`` (default) or ``"theorem2"`` (module docstring).
    gain : 1/s for the normalized law (``v = min(v_max, gain |x - x_d|)``), K for theorem2.
    v_max : speed limit (m/s, > 0, may be ``inf`` for theorem2 only).
    goal_tol : distance to the goal (m) counted as arrived.
    slow_distance : normalized law: clearance (m) below which the speed is scaled by
        ``clip(clearance / slow_distance, 0.2, 1)`` (0 = off; needs ``cmap.workspace``).
    hold_time : s a robot may keep applying a command after the pose it answers (the
        simulator's ``max_cmd_age``): the speed is capped at ``HOLD_FRACTION * clearance /
        hold_time``, so the held command stays inside the free space (module docstring).
        None: :data:`~confnav.navigation.defaults.HOLD_TIME` when the map has a workspace
        (clearance), off otherwise; 0: off.
    stall_radius : distance (m) to a critical point of phi other than the goal (found by
        :meth:`critical_points`, or in the background by :meth:`search_critical_points`)
        within which a robot is reported STALLED; default goal_tol.

    All defaults come from :mod:`confnav.navigation.defaults` (equal to the ``Goal`` message's).
    ``x``
    may be any point the robot steers, e.g. a point ahead of a unicycle's axle.
    workspace : the workspace in use; if given, a map whose ``workspace_hash`` differs from
        its ``content_hash`` is refused with :class:`~confnav.errors.MapMismatchError`.
    safety : the safety layer on exact geometry (:mod:`confnav.navigation.safety`) every
        command passes after the speed law.  None (default): on when the map has a
        :class:`~confnav.geometry.Workspace` (filtered against it, with this ``hold_time``);
        False: off; True: on (needs the map's workspace); a ``Workspace``: filter against that
        one (the workspace in use, e.g. the true one when the map is coarse or wrong); a
        :class:`~confnav.navigation.safety.SafetyFilter`: that filter.  Where no constraint
        is active the command is the law's, bitwise.  :attr:`safety_counts` counts how often
        it acts; ``ControlOutput.filtered`` says where.
    """

    def __init__(
        self,
        cmap: ConformalLike,
        goal: complex | tuple[float, float] | ArrayLike,
        *,
        navfn: Literal["kr", "harmonic"] | str | NavigationFunction = defaults.NAVFN,
        k: float | Literal["auto"] = "auto",
        speed_law: str = defaults.SPEED_LAW,
        gain: float = defaults.GAIN,
        v_max: float = defaults.V_MAX,
        goal_tol: float = defaults.GOAL_TOL,
        slow_distance: float = defaults.SLOW_DISTANCE,
        stall_radius: float | None = None,
        workspace: Workspace | None = None,
        hold_time: float | None = None,
        safety: bool | Workspace | SafetyFilter | None = None,
    ) -> None:
        bound = getattr(cmap, "workspace_hash", None)
        if workspace is not None and bound != workspace.content_hash:  # issue 8
            raise MapMismatchError(
                f"the map was solved for workspace {str(bound)[:12]}, not for the one in use "
                f"{workspace.content_hash[:12]}"
            )
        self.cmap = cmap
        self.goal = as_point(goal, "goal", NavigationError)
        if speed_law not in defaults.SPEED_LAWS:
            raise NavigationError(
                f"unknown speed law {speed_law!r}; choose from {defaults.SPEED_LAWS}"
            )
        if not float(gain) > 0 or not np.isfinite(gain):
            raise NavigationError(f"gain must be positive and finite, got {gain!r}")
        if not float(v_max) > 0 or (speed_law == "normalized" and not np.isfinite(v_max)):
            raise NavigationError(f"v_max must be positive (finite for {speed_law}), got {v_max!r}")
        if not float(goal_tol) > 0:
            raise NavigationError(f"goal_tol must be positive, got {goal_tol!r}")
        if not float(slow_distance) >= 0:
            raise NavigationError(f"slow_distance must be >= 0, got {slow_distance!r}")
        self.speed_law = speed_law
        self.gain = float(gain)
        self.v_max = float(v_max)
        self.goal_tol = float(goal_tol)
        self.slow_distance = float(slow_distance)
        self.stall_radius = self.goal_tol if stall_radius is None else float(stall_radius)
        ws = getattr(cmap, "workspace", None)
        self._clearance = getattr(ws, "clearance", None)
        if hold_time is None:
            hold_time = defaults.HOLD_TIME if self._clearance is not None else 0.0
        if not (float(hold_time) >= 0 and np.isfinite(hold_time)):
            raise NavigationError(f"hold_time must be >= 0 and finite, got {hold_time!r}")
        self.hold_time = float(hold_time)
        for name, on in (("slow_distance", self.slow_distance), ("hold_time", self.hold_time)):
            if on > 0 and self._clearance is None:
                raise NavigationError(f"{name} needs a map with a workspace (clearance)")
        self.safety: SafetyFilter | None = _safety_layer(safety, ws, self.hold_time)
        #: how often the safety layer ran and acted (commands, changed, infeasible)
        self.safety_counts = SafetyCounts()
        if _workspace_contains(cmap, self.goal) is False:
            raise NavigationError(f"goal {fmt_point(self.goal)} is not in the free space")
        wd = complex(np.asarray(cmap.T_and_dT(np.asarray(self.goal))[0]))
        if not np.isfinite(wd):
            raise NavigationError(
                f"goal {fmt_point(self.goal)} is not in the free space (T is NaN)"
            )
        # a goal whose image is not inside the circle domain by more than rounding is on a
        # wall as far as the map can tell (the navigation functions would fail on it with
        # circle-domain figures: "not inside the circle domain", a series that does not
        # converge, no valid k). Not the map's error estimate: an atlas chart's local goal
        # 3.2e-7 deep in a chart of estimate 3.5e-7 navigates well (tests/test_atlas_margin.py)
        domain = CircleDomain.of(cmap)
        depth = float(domain.clearance1(wd))
        if not depth > MIN_GOAL_DEPTH:
            raise NavigationError(
                f"goal {fmt_point(self.goal)} is too close to a wall to navigate to: the map "
                f"sends it within {max(depth, 0.0):.1e} of a boundary circle of the circle "
                "domain; move it further from the walls"
            )
        self.fallback = ""
        if isinstance(navfn, NavigationFunction):
            self.domain = navfn.domain
            if abs(navfn.goal - wd) > 1e-9:
                raise NavigationError("navigation function goal differs from T(goal)")
            self.navfn = navfn
        else:
            self.domain = domain
            try:
                self.navfn = make_navfn(navfn, self.domain, wd, k=k, samples=_samples(cmap))
            except NavigationError as exc:
                if navfn != "harmonic" or "did not converge" not in str(exc):
                    raise
                self.navfn = make_navfn("kr", self.domain, wd, k="auto")
                self.fallback = (
                    f"harmonic fit failed ({exc}); using Koditschek-Rimon "
                    f"k={self.navfn.k:g}"  # type: ignore[attr-defined]
                )
        self.goal_w = wd
        self._critical: CriticalPoints | None = None
        self._stall_cache: tuple[CriticalPoints, CArray] | None = None
        self._critical_lock = threading.Lock()
        self._search: Future[CriticalPoints] | None = None
        self._search_lock = threading.Lock()


    def _params(self) -> dict[str, Any]:
        return {
            "speed_law": self.speed_law,
            "gain": self.gain,
            "v_max": self.v_max,
            "goal_tol": self.goal_tol,
            "slow_distance": self.slow_distance,
            "stall_radius": self.stall_radius,
            "hold_time": self.hold_time,
            "safety": self.safety if self.safety is not None else False,
        }

    def with_goal(self, goal: complex | tuple[float, float] | ArrayLike) -> Controller:
        """A controller for a new goal on the same map (no new solve); same parameters."""
        z = as_point(goal, "goal", NavigationError)
        wd = complex(np.asarray(self.cmap.T_and_dT(np.asarray(z))[0]))
        if not np.isfinite(wd) or _workspace_contains(self.cmap, z) is False:
            raise NavigationError(f"goal {fmt_point(z)} is not in the free space")
        return Controller(self.cmap, z, navfn=self.navfn.with_goal(wd), **self._params())

    @property
    def uses_clearance(self) -> bool:
        """Whether the law needs the workspace clearance (wall slow-down or hold cap)."""
        return self._clearance is not None and (self.slow_distance > 0 or self.hold_time > 0)

    def clearance(self, z: ArrayLike) -> FArray:
        """Clearance of ``z`` in the map's workspace (what :meth:`from_map_values` takes)."""
        if self._clearance is None:
            raise NavigationError("the map has no workspace (clearance)")
        return np.asarray(self._clearance(np.asarray(z, dtype=np.complex128)), dtype=np.float64)

    def _command(
        self, z: CArray, dw: CArray, g: CArray, clearance: FArray | None = None
    ) -> tuple[CArray, NDArray[np.bool_], NDArray[np.bool_] | None]:
        """The law's command, then the safety layer: ``(u, saturated, filtered)``."""
        u, sat = self._law(z, dw, g, clearance)
        if self.safety is None:
            return u, sat, None
        pr = self.safety(z, u)
        self.safety_counts.add(pr.u.size, int(pr.changed.sum()), int(pr.infeasible.sum()))
        return pr.u, sat & ~pr.changed, pr.changed

    def _law(
        self, z: CArray, dw: CArray, g: CArray, clearance: FArray | None = None
    ) -> tuple[CArray, NDArray[np.bool_]]:
        """The speed law's command (before the safety layer)."""
        slow = v_cap = None
        if self.uses_clearance:
            c = self.clearance(z) if clearance is None else clearance
            if self.slow_distance > 0:
                slow = np.clip(c / self.slow_distance, SLOW_FLOOR, 1.0)
            if self.hold_time > 0:  # a command held hold_time s moves <= HOLD_FRACTION * c
                v_cap = defaults.HOLD_FRACTION * np.maximum(c, 0.0) / self.hold_time
        return speed_law(
            -np.conj(dw) * g,
            np.abs(z - self.goal),
            law=self.speed_law,
            gain=self.gain,
            v_max=self.v_max,
            slow=slow,
            v_cap=v_cap,
        )

    def velocity(self, z: ArrayLike) -> CArray:
        """The command ``u`` only (hot path; NaN outside the free space)."""
        z = np.asarray(z, dtype=np.complex128)
        w, dw = self.cmap.T_and_dT(z)
        g = self.navfn.gradient(w)
        return self._command(z, np.asarray(dw), g)[0]

    def law_velocity(self, z: ArrayLike) -> CArray:
        """The speed law's command without the safety layer (for comparisons)."""
        z = np.asarray(z, dtype=np.complex128)
        w, dw = self.cmap.T_and_dT(z)
        return self._law(z, np.asarray(dw), self.navfn.gradient(w))[0]

    def __call__(self, z: ArrayLike) -> ControlOutput:
        """Command and status for a batch of robot positions (complex array, any shape)."""
        z = np.asarray(z, dtype=np.complex128)
        if z.size == 1:  # one robot: the scalar path (_step1)
            z1 = complex(z.reshape(-1)[0])
            w1, dw1 = self._map1(z1 if cmath.isfinite(z1) else self.goal)
            return self._step1(z1, w1, dw1, None, z.shape)
        w, dw = self.cmap.T_and_dT(np.where(np.isfinite(z), z, self.goal))
        return self.from_map_values(z, w, dw)

    def _map1(self, z: complex) -> tuple[complex, complex]:
        """``T(z), T'(z)`` of one point (the map's scalar path if it has one)."""
        one = getattr(self.cmap, "T_and_dT1", None)
        if one is not None:
            w, dw = one(z)
        else:
            w, dw = self.cmap.T_and_dT(np.asarray(z))
        return complex(w), complex(dw)

    def _step1(
        self, z: complex, w: complex, dw: complex, clearance: float | None, shape: tuple[int, ...]
    ) -> ControlOutput:
        """:meth:`from_map_values` of one robot in Python scalars (arrays of ``shape`` out).

        Statement for statement the batch path: the same formulas in the same order, so the
        results agree with a batch to rounding (tests/test_single_robot_path.py: 1e-14
        relative); a single robot's step costs tens of microseconds instead of the ~60 numpy
        calls on 1-element arrays of the batch path.
        """
        bad = not (cmath.isfinite(z) and cmath.isfinite(w) and cmath.isfinite(dw))
        if bad:  # evaluated at the goal, then u = 0 (as the batch path)
            z_eval, w, dw = self.goal, self.goal_w, 1 + 0j
        else:
            z_eval = z
        phi, g = self.navfn.value_and_gradient1(w)
        c = None
        if self.uses_clearance:
            c = self._clearance1(z_eval) if clearance is None or bad else float(clearance)
        u, sat, filt = self._command1(z_eval, dw, g, c)
        arrived = not bad and abs(z - self.goal) <= self.goal_tol
        if bad:
            status = Status.ERROR
        elif arrived:
            status = Status.ARRIVED
        elif self._near_critical1(w, dw):
            status = Status.STALLED
        else:
            status = Status.MOVING
        if arrived or bad:
            u = 0j
        return ControlOutput(
            u=_full(shape, u, np.complex128),
            status=_full(shape, status, np.int8),
            phi=_full(shape, np.nan if bad else phi, np.float64),
            w=_full(shape, complex(np.nan, 0.0) if bad else w, np.complex128),
            saturated=_full(shape, sat and not arrived and not bad, np.bool_),
            filtered=None
            if filt is None
            else _full(shape, filt and not arrived and not bad, np.bool_),
        )

    def _clearance1(self, z: complex) -> float:
        """:meth:`clearance` of one point (the workspace's scalar path if it has one)."""
        one = getattr(getattr(self.cmap, "workspace", None), "clearance1", None)
        return float(one(z)) if one is not None else float(self.clearance(z))

    def _command1(
        self, z: complex, dw: complex, g: complex, c: float | None
    ) -> tuple[complex, bool, bool | None]:
        """:meth:`_command` of one point: the law (:meth:`_law1`), then the safety layer."""
        u, sat = self._law1(z, dw, g, c)
        if self.safety is None:
            return u, sat, None
        u, changed, infeasible = self.safety.filter1(z, u)
        self.safety_counts.add(1, int(changed), int(infeasible))
        return u, sat and not changed, changed

    def _law1(
        self, z: complex, dw: complex, g: complex, c: float | None
    ) -> tuple[complex, bool]:
        """:meth:`_law` and :func:`speed_law` of one point (same formulas, scalars)."""
        f = -dw.conjugate() * g
        size = abs(f)
        if self.speed_law == "theorem2":
            u = self.gain * f
            s = self.gain * size
            sat = s > self.v_max
            if sat:
                u = u * (self.v_max / s)
        else:
            dist = abs(z - self.goal)
            v = min(self.v_max, self.gain * dist)
            sat = self.gain * dist >= self.v_max
            if c is not None and self.slow_distance > 0:
                v = v * min(max(c / self.slow_distance, SLOW_FLOOR), 1.0)
            # unit direction; |f| = 0 gives u = 0; NaN stays NaN (as _speed_law)
            if size > 0:
                scl = 1.0 / size  # numpy's complex / real: times the reciprocal
                unit = complex(f.real * scl, f.imag * scl)
            else:
                unit = 0j if size == 0 else f
            u = unit * v
            sat = sat and size > 0
        if c is not None and self.hold_time > 0:
            cap = defaults.HOLD_FRACTION * max(c, 0.0) / self.hold_time
            speed = abs(u)
            if speed > cap:
                u = u * (cap / speed)
                sat = False
        return u, bool(sat)

    def _near_critical1(self, w: complex, dw: complex) -> bool:
        """:meth:`_near_critical` of one point."""
        pts = self._stall_points()
        if pts.size == 0:
            return False
        return bool(np.minimum.reduce(np.abs(w - pts)) <= self.stall_radius * abs(dw))

    def from_map_values(
        self, z: ArrayLike, w: ArrayLike, dw: ArrayLike, clearance: ArrayLike | None = None
    ) -> ControlOutput:
        """:meth:`__call__` from precomputed ``(w, dw) = cmap.T_and_dT(z)`` (same shapes) and,
        optionally, ``clearance = self.clearance(z)``.

        The map does not depend on the goal, so a host with many robots on one map (each with
        its own goal and controller) evaluates ``T``, ``T'`` and the clearance once for all of
        them and hands each controller its robots' values: the result is exactly ``self(z)``
        for those values.
        """
        z = np.asarray(z, dtype=np.complex128)
        w = np.asarray(w, dtype=np.complex128)
        dw = np.asarray(dw, dtype=np.complex128)
        if z.size == 1 and w.size == 1 and dw.size == 1:  # one robot: the scalar path
            c1 = None
            if clearance is not None:
                c1 = float(np.asarray(clearance, dtype=np.float64).reshape(-1)[0])
            z1, w1, dw1 = (complex(a.reshape(-1)[0]) for a in (z, w, dw))
            return self._step1(z1, w1, dw1, c1, z.shape)
        bad = ~np.isfinite(z) | ~np.isfinite(w) | ~np.isfinite(dw)
        w = np.where(bad, self.goal_w, w)
        dw = np.where(bad, 1.0, dw)
        phi, g = self.navfn.value_and_gradient(w)
        c = None
        if clearance is not None and self.uses_clearance:
            c = np.asarray(clearance, dtype=np.float64)
            if bad.any():  # the bad poses are evaluated at the goal (then set to u = 0)
                c = np.where(bad, self.clearance(self.goal), c)
        u, sat, filt = self._command(np.where(bad, self.goal, z), dw, g, c)
        arrived = ~bad & (np.abs(z - self.goal) <= self.goal_tol)
        stalled = ~bad & ~arrived & self._near_critical(w, dw)
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
            filtered=None if filt is None else filt & ~arrived & ~bad,
        )

    def critical_points(self) -> CriticalPoints:
        """Critical points of the navigation function (computed once, cached; thread-safe).

        One minimum and M saddles expected; ``.ok`` False means e.g. k too small for this
        geometry, or a search that missed points where phi is flat to rounding.
        """
        with self._critical_lock:
            if self._critical is None:
                from confnav.navigation.critical import search_critical_points

                self._critical = search_critical_points(self.navfn)
            return self._critical

    check = critical_points

    def search_critical_points(self, executor: SearchExecutor) -> Future[CriticalPoints]:
        """Have ``executor`` run :meth:`critical_points` in the background (once per
        controller) and return its future.

        ``__call__`` never waits for the search: it reports STALLED near a critical point as
        soon as the points have landed (a few seconds for 20 obstacles), MOVING before.  Long
        running hosts (the controller service) call this when they build a controller, so
        stall detection works without anyone asking for the points first.  The core starts no
        thread: the host passes its executor (the controller service's is
        ``confnav.services.critical_search.CriticalSearchWorker``: one duty-cycled worker per
        process, which skips controllers nobody holds any more).  ``executor.submit_search``
        gets a weak reference to this controller and the future to complete
        (:class:`SearchExecutor`).
        """
        with self._search_lock:
            if self._search is None:
                self._search = Future()
                executor.submit_search(weakref.ref(self), self._search)
            return self._search

    def _stall_points(self) -> CArray:
        cp = self._critical  # never computed here: __call__ must not block on the search
        if cp is None:
            return _NO_POINTS
        cached = self._stall_cache
        if cached is None or cached[0] is not cp:  # once per search result (hot path)
            pts = np.concatenate([cp.saddles, cp.spurious_minima, cp.maxima, cp.degenerate])
            cached = self._stall_cache = (cp, pts)
        return cached[1]

    def _near_critical(self, w: CArray, dw: CArray) -> NDArray[np.bool_]:
        """Within ``stall_radius`` (workspace metres, via ``|dw| ~ |T'|``) of a critical point
        other than the goal; only once :meth:`critical_points` has been computed."""
        pts = self._stall_points()
        if pts.size == 0:
            return np.zeros(w.shape, dtype=bool)
        d = np.min(np.abs(w[..., None] - pts), axis=-1)
        return np.asarray(d <= self.stall_radius * np.abs(dw))

    def near_critical(self, z: ArrayLike) -> NDArray[np.bool_]:
        """True within ``stall_radius`` of a critical point other than the goal (computes the
        critical points on first use)."""
        self.critical_points()
        z = np.asarray(z, dtype=np.complex128)
        w, dw = self.cmap.T_and_dT(z)
        w, dw = np.asarray(w, dtype=np.complex128), np.asarray(dw, dtype=np.complex128)
        return np.asarray(self._near_critical(w, dw) & np.isfinite(w), dtype=bool)

    def circle_domain_position(self, z: ArrayLike) -> tuple[CArray, FArray]:
        """``(T(z), scale)``: the image in the circle domain and its local length scale
        ``min(clearance in the circle domain, |T(z) - T(goal)|)`` (for progress checks)."""
        w = np.asarray(self.cmap.T_and_dT(np.asarray(z, dtype=np.complex128))[0])
        scale = np.minimum(self.domain.clearance(w), np.abs(w - self.goal_w))
        return w.astype(np.complex128), np.asarray(scale, dtype=np.float64)

    def lyapunov(self, z: ArrayLike) -> FArray:
        """``V(x) = phi(T(x))`` (NaN outside the free space)."""
        w = np.asarray(self.cmap.T_and_dT(z)[0], dtype=np.complex128)
        return self.navfn.value(w)

    def __repr__(self) -> str:
        return (
            f"Controller(goal={self.goal:.6g}, navfn={self.navfn!r}, "
            f"speed_law={self.speed_law}, gain={self.gain:g}, v_max={self.v_max:g}, "
            f"goal_tol={self.goal_tol:g})"
        )


#: Free-space points (per map) where the harmonic fit must be accurate relative to |G|.
N_SAMPLES = 256
SAMPLE_MARGIN = 0.05  # m from the walls, like the benchmark's random starts


def _samples(cmap: ConformalLike) -> CArray | None:
    """Images ``T(x)`` of free-space points at ``SAMPLE_MARGIN`` from the walls (None without
    a workspace); fixed seed, so every controller of a map asks the same accuracy."""
    ws = getattr(cmap, "workspace", None)
    if ws is None or not hasattr(ws, "bounds"):
        return None
    from confnav.scenes.scenarios import random_starts

    try:
        z = random_starts(ws, N_SAMPLES, seed=0, margin=SAMPLE_MARGIN)
    except NavigationError:
        return None
    w = np.asarray(cmap.T_and_dT(z)[0], dtype=np.complex128)
    return w[np.isfinite(w)]
