"""Differential-drive (unicycle) robots driven by the conformal law through a look-ahead point.

State ``(x, theta)`` with ``x`` complex, commands ``v`` (forward speed) and ``omega`` (yaw
rate): ``x' = v e^{i theta}``, ``theta' = omega``. The point ``p = x + d e^{i theta}`` a
distance ``d`` ahead of the axle moves by ``p' = (v + i d omega) e^{i theta}``, so

    v = Re(u e^{-i theta}),   omega = Im(u e^{-i theta}) / d

gives ``p' = u`` exactly (input-output feedback linearisation of the unicycle about a point
off the wheel axis [1]_ (sec. 11.5.3 on the kinematic model, "input/output linearization"),
[2]_; docs/METHOD.md sec. 3). The point ``p`` therefore follows the
Theorem 2 field of :class:`confnav.navigation.control.Controller` with all its guarantees, and a
body of
radius ``r`` around the axle stays within ``r + d`` of ``p``: navigate ``p`` in the free space
shrunk by ``r + d`` (:func:`confnav.maps.footprint.inflate`) and the body never touches an obstacle.

Limits: ``|v| <= v_max`` and ``|omega| <= omega_max`` are met by scaling ``u`` by
``s = min(1, v_max/|v|, omega_max/|omega|)``; the direction of ``u`` is kept, so ``p``
follows the same path, only slower (a time change of the field).

References
----------
.. [1] B. Siciliano, L. Sciavicco, L. Villani, G. Oriolo, *Robotics: Modelling, Planning and
   Control*, Springer 2009, sec. 11.5 (motion control of wheeled mobile robots,
   input/output linearization).
.. [2] G. Oriolo, A. De Luca, M. Vendittelli, "WMR control via dynamic feedback
   linearization", IEEE Trans. Control Syst. Technol. 10(6) (2002) 835-852.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError
from confnav.navigation.control import Controller, ControlOutput, Status
from confnav.navigation.sim import SimulationResult, _chord_check, simulate
from confnav.types import CArray, FArray

__all__ = [
    "UnicycleController",
    "UnicycleOutput",
    "UnicycleResult",
    "look_ahead_point",
    "simulate_robots",
    "simulate_unicycle",
    "step_exact",
    "twist_from_velocity",
]

ARRIVED, COLLIDED, STALLED, TIMEOUT, ERROR = range(5)


def look_ahead_point(z: ArrayLike, theta: ArrayLike, d: float) -> CArray:
    """``p = x + d e^{i theta}`` (vectorized)."""
    return np.asarray(z, dtype=np.complex128) + d * np.exp(1j * np.asarray(theta, dtype=float))


def twist_from_velocity(
    u: ArrayLike, theta: ArrayLike, d: float, v_max: float = np.inf, omega_max: float = np.inf
) -> tuple[FArray, FArray]:
    """``(v, omega)`` making ``p' = s u`` with the largest ``s <= 1`` meeting both limits.

    ``v + i d omega = s u e^{-i theta}`` (module docstring; Siciliano et al. sec. 11.5).
    """
    b = np.asarray(u, dtype=np.complex128) * np.exp(-1j * np.asarray(theta, dtype=float))
    v, omega = b.real, b.imag / d
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.minimum(1.0, np.minimum(v_max / np.abs(v), omega_max / np.abs(omega)))
    s = np.where(np.isfinite(s), s, 1.0)
    return np.asarray(v * s, dtype=float), np.asarray(omega * s, dtype=float)


def step_exact(
    z: ArrayLike, theta: ArrayLike, v: ArrayLike, omega: ArrayLike, dt: ArrayLike
) -> tuple[CArray, FArray]:
    """Exact unicycle motion for ``dt`` under constant ``(v, omega)`` (an arc).

    ``x(dt) = x + v dt e^{i(theta + omega dt/2)} sinc(omega dt / 2)`` (chord of the arc),
    ``theta(dt) = theta + omega dt``.
    """
    th = np.asarray(theta, dtype=float)
    half = 0.5 * np.asarray(omega, dtype=float) * np.asarray(dt, dtype=float)
    chord = np.asarray(v) * np.asarray(dt) * np.sinc(half / np.pi) * np.exp(1j * (th + half))
    return np.asarray(z, dtype=np.complex128) + chord, th + 2 * half


class PointLaw(Protocol):
    """What drives the look-ahead point: :class:`confnav.navigation.control.Controller` or an
    atlas's per-robot :class:`confnav.atlas.wire.AtlasController`."""

    goal: complex
    goal_tol: float

    def __call__(self, z: ArrayLike) -> ControlOutput: ...


@dataclass(frozen=True)
class UnicycleOutput:
    """One control step: ``u`` the body twist ``v + i omega`` (real part linear.x, m/s;
    imaginary part angular.z, rad/s), ``status`` :class:`confnav.navigation.control.Status` codes
    of the
    look-ahead point, ``point`` that point."""

    u: CArray
    status: NDArray[np.int8]
    point: CArray


class UnicycleController:
    """The Theorem 2 law for the look-ahead point of unicycle robots.

    Parameters
    ----------
    controller : the point law (:class:`PointLaw`: a
        :class:`confnav.navigation.control.Controller` or an atlas's
        :class:`confnav.atlas.wire.AtlasController`) on the map of the free space shrunk by
        ``r + d`` (body radius plus look-ahead); its goal is the goal of ``p``.
    d : look-ahead distance (> 0, workspace units).
    v_max, omega_max : limits on ``|v|`` (m/s) and ``|omega|`` (rad/s), > 0.
    """

    frame = "body"

    def __init__(
        self,
        controller: PointLaw,
        d: float,
        *,
        v_max: float = np.inf,
        omega_max: float = np.inf,
    ) -> None:
        if not (np.isfinite(d) and d > 0):
            raise NavigationError(f"look-ahead distance d must be positive, got {d!r}")
        if not (v_max > 0 and omega_max > 0):
            raise NavigationError("v_max and omega_max must be positive")
        self.controller = controller
        self.d = float(d)
        self.v_max = float(v_max)
        self.omega_max = float(omega_max)
        self.goal = controller.goal
        self.goal_tol = controller.goal_tol

    @property
    def active_chart(self) -> int | None:
        """The point law's active chart on an atlas (None on a single map)."""
        return getattr(self.controller, "active_chart", None)

    @property
    def stop_reason(self) -> tuple[str, str] | None:
        """The point law's (reason, message) of a stop other than a bare ERROR, if any."""
        return getattr(self.controller, "stop_reason", None)

    def __call__(self, z: ArrayLike, theta: ArrayLike | None = None) -> UnicycleOutput:
        """Body twists and statuses for axle positions ``z`` and headings ``theta``."""
        if theta is None:
            raise NavigationError("a unicycle controller needs the headings of the robots")
        th = np.asarray(theta, dtype=float)
        p = look_ahead_point(z, th, self.d)
        out = self.controller(p)
        v, omega = twist_from_velocity(out.u, th, self.d, self.v_max, self.omega_max)
        return UnicycleOutput(u=v + 1j * omega, status=out.status, point=p)


@dataclass(frozen=True, kw_only=True)
class UnicycleResult(SimulationResult):
    """Runs of unicycle robots: a :class:`confnav.navigation.sim.SimulationResult` whose ``final``
    are axle
    positions, plus the start and final ``headings`` (rad). ``min_clearance`` is the *body's*
    (axle clearance minus the radius) along the whole path; ``final_distance`` is that of the
    look-ahead point, and so is ``point_length``, the length of the path of the point that
    is steered to the goal (``path_length`` is the axle's)."""

    headings: FArray
    final_theta: FArray
    point_length: FArray


def _lowered(clearance: Any, margin: float) -> Any:
    """``clearance`` minus a constant margin."""

    def f(z: CArray) -> FArray:
        return np.asarray(clearance(z), dtype=float) - margin

    return f


def _held_step(
    h: FArray, c: FArray, v: FArray, om: FArray, point: CArray, uc: UnicycleController
) -> FArray:
    """Step lengths (at most ``h``) over which the command ``(v, om)`` may be held: at most
    half the body's clearance ``c`` travelled, 0.2 rad turned, and a quarter of the
    look-ahead point's distance to the goal (no overshoot of the goal by a held command)."""
    h = np.minimum(h, 0.5 * c / np.maximum(np.abs(v), 1e-300))
    h = np.minimum(h, 0.2 / np.maximum(np.abs(om), 1e-300))
    gap = np.abs(point - uc.goal)
    return np.asarray(np.minimum(h, 0.25 * gap / np.maximum(np.abs(v + 1j * uc.d * om), 1e-300)))


def _gather_paths(z0: CArray, chunks: list[tuple[NDArray[np.intp], CArray]]) -> tuple[CArray, ...]:
    """Each robot's path (its start, then its positions step by step) from the per-step
    chunks ``(robots moved, their new positions)``."""
    n = z0.size
    who = np.concatenate([np.arange(n)] + [ch[0] for ch in chunks])
    pts = np.concatenate([z0] + [ch[1] for ch in chunks])
    order = np.argsort(who, kind="stable")
    return tuple(np.split(pts[order], np.cumsum(np.bincount(who, minlength=n))[:-1]))


def simulate_unicycle(
    uc: UnicycleController,
    starts: ArrayLike,
    headings: ArrayLike,
    *,
    clearance: Any,
    radius: float = 0.0,
    dt: float = 0.02,
    t_max: float = 200.0,
    record_paths: bool = False,
) -> UnicycleResult:
    """Drive unicycles with the controller held constant over each step (zero-order hold,
    as a real robot and the simulator service do), moving exactly along arcs.

    ``clearance(z)`` is the signed distance of the axle to the *original* obstacles; the body
    of ``radius`` collides when it drops to ``radius``. Each step is shortened to at most half
    the body's clearance, a turn of 0.2 rad and a quarter of the look-ahead point's distance to
    the goal (so that the held command cannot overshoot it: the continuous law is simulated).
    The arc between steps is certified by bisection of its chord with the clearance lowered by
    the arc's sagitta bound ``L |omega| dt / 8`` (the largest of the batch inside the bisection).
    """
    t0 = time.perf_counter()
    z = np.atleast_1d(np.asarray(starts, dtype=np.complex128)).copy()
    th = np.broadcast_to(np.asarray(headings, dtype=float), z.shape).copy()
    z0, th0 = z.copy(), th.copy()
    n = z.size

    def body(zz: CArray) -> FArray:
        return np.asarray(clearance(zz), dtype=float) - radius

    c = body(z)
    if np.any(~(c > 0)):
        i = int(np.flatnonzero(~(c > 0))[0])
        raise NavigationError(f"start {z[i]:.6g}: the body of radius {radius:g} hits an obstacle")
    status = np.full(n, -1, dtype=np.int8)
    t = np.zeros(n)
    length = np.zeros(n)
    plength = np.zeros(n)
    minclr = c.copy()
    nsteps = np.zeros(n, dtype=np.int64)
    vmax = np.zeros(n)
    chunks: list[tuple[NDArray[np.intp], CArray]] = []
    max_steps = int(20 * t_max / dt) + 1
    nfev = 0
    while True:
        a = np.flatnonzero(status < 0)
        if a.size == 0:
            break
        out = uc(z[a], th[a])
        nfev += 1
        code = np.asarray(out.status)
        status[a[code == Status.ARRIVED]] = ARRIVED
        status[a[code == Status.ERROR]] = ERROR
        go = code == Status.MOVING
        go |= code == Status.STALLED
        a, v, om = a[go], out.u.real[go], out.u.imag[go]
        if a.size == 0:
            continue
        h = _held_step(np.minimum(dt, t_max - t[a]), c[a], v, om, out.point[go], uc)
        zn, thn = step_exact(z[a], th[a], v, om, h)
        sag = np.abs(v) * h * np.abs(om) * h / 8.0
        cn = body(zn)
        hit, low = _chord_check(z[a], zn, c[a] - sag, cn - sag, _lowered(body, float(sag.max())))
        minclr[a] = np.minimum(minclr[a], low)
        length[a] += np.abs(v) * h
        # the look-ahead point p = z + d e^{i theta} moves at |v + i d omega| along the arc
        plength[a] += np.abs(v + 1j * uc.d * om) * h
        vmax[a] = np.maximum(vmax[a], np.abs(v))
        z[a], th[a], c[a], t[a] = zn, thn, cn, t[a] + h
        nsteps[a] += 1
        if record_paths:
            chunks.append((a, zn.copy()))
        status[a[hit | (cn <= 0)]] = COLLIDED
        late = (status[a] < 0) & ((t[a] >= t_max * (1 - 1e-12)) | (nsteps[a] >= max_steps))
        status[a[late]] = TIMEOUT
    paths = _gather_paths(z0, chunks) if record_paths else None
    return UnicycleResult(
        starts=z0,
        goal=uc.goal,
        success=np.asarray(status == ARRIVED, dtype=bool),
        collided=np.asarray(status == COLLIDED, dtype=bool),
        status=status,
        time=t,
        path_length=length,
        min_clearance=minclr,
        final=z,
        final_distance=np.abs(look_ahead_point(z, th, uc.d) - uc.goal),
        n_steps=nsteps,
        max_speed=vmax,
        nfev=nfev,
        wall_time=time.perf_counter() - t0,
        paths=paths,
        headings=th0,
        final_theta=th,
        point_length=plength,
    )


def simulate_robots(
    ctl: Controller,
    starts: ArrayLike,
    *,
    workspace: Any,
    radius: float = 0.0,
    lookahead: float | None = None,
    omega_max: float = np.inf,
    seed: int = 0,
    t_max: float = 1e4,
    record_paths: bool = False,
) -> SimulationResult | UnicycleResult:
    """Drive disk robots of ``radius`` (points if 0) or, with ``lookahead`` d, unicycles
    (random headings from ``seed``) with ``ctl``, whose map must be that of ``workspace``
    shrunk by ``radius`` (+ d). Collisions and clearances are the body's in ``workspace``."""
    if lookahead is None:
        return simulate(
            ctl,
            starts,
            clearance=lambda z: workspace.clearance(z) - radius,
            t_max=t_max,
            record_paths=record_paths,
        )
    z = np.atleast_1d(np.asarray(starts, dtype=np.complex128))
    heads = np.random.default_rng(seed).uniform(-np.pi, np.pi, z.size)
    uc = UnicycleController(ctl, lookahead, v_max=ctl.v_max, omega_max=omega_max)
    return simulate_unicycle(
        uc,
        z,
        heads,
        clearance=workspace.clearance,
        radius=radius,
        dt=0.02,
        t_max=min(t_max, 1e3),
        record_paths=record_paths,
    )
