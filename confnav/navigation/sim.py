"""Simulation of kinematic robots ``x' = u(x)`` under a velocity field (batch, vectorized).

Every robot has its own adaptive step (Dormand-Prince 5(4) with an absolute error bound on the
position [1]_), and all active robots advance together, so one call of the velocity field
serves the whole batch.  A run ends at the goal tolerance (success), at a collision, at the
time limit or after too many steps.  Collisions are checked with the exact distance to the
polygons (``Workspace.clearance``) at every accepted point and along every chord between them:
a chord of length L between points of clearance c_a, c_b is certified free when
L < c_a + c_b (clearance is 1-Lipschitz); otherwise it is bisected.  A chord that hits an
obstacle although both its ends are free (a step that turns round a corner closer than the
chord is long: a robot sliding along a wall under the safety layer) is checked again along the
step's cubic Hermite interpolant, the path the integrator actually describes.

A robot is ``stalled`` only when it makes no progress: over a time window its image in the
circle domain moved less than a fraction of its local length scale (see :func:`simulate`), or
it stays put for many accepted steps.  A small ``|grad phi|`` alone never counts (flat is not
stalled); the reason names a critical point of phi when the robot is near one.

References
----------
.. [1] J. R. Dormand and P. J. Prince, "A family of embedded Runge-Kutta formulae",
   J. Comput. Appl. Math. 6 (1980) 19-26.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError, fmt_point
from confnav.types import CArray, FArray

__all__ = ["RunResult", "SimulationResult", "VelocityField", "simulate"]

Clearance = Callable[[CArray], Any]

STATUS_NAMES: tuple[str, ...] = ("arrived", "collided", "stalled", "timeout", "error")
ARRIVED, COLLIDED, STALLED, TIMEOUT, ERROR = range(5)

# Dormand-Prince 5(4) tableau
_A: tuple[tuple[float, ...], ...] = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
_E = np.array([71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40])


class VelocityField(Protocol):
    """A feedback law: ``velocity(z)`` (complex, NaN where undefined), ``goal``, ``goal_tol``.

    :class:`confnav.navigation.control.Controller` and
    :class:`confnav.navigation.baseline.PotentialField` are ones.
    """

    goal: complex
    goal_tol: float

    def velocity(self, z: ArrayLike) -> CArray: ...


@dataclass(frozen=True)
class RunResult:
    """One robot's run (workspace units; time in the field's time unit)."""

    start: complex
    success: bool
    collided: bool
    status: str
    time: float
    path_length: float
    min_clearance: float
    final_distance: float
    max_speed: float
    n_steps: int
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "reason": self.reason,
            "start": [self.start.real, self.start.imag],
            "success": self.success,
            "collided": self.collided,
            "status": self.status,
            "time": self.time,
            "path_length": self.path_length,
            "min_clearance": self.min_clearance,
            "final_distance": self.final_distance,
            "max_speed": self.max_speed,
            "n_steps": self.n_steps,
        }


class Outcomes:
    """Success rate and outcome counts of a batch whose ``success`` and ``status`` (codes
    indexing :data:`STATUS_NAMES`) are per-robot arrays; shared by the result types."""

    success: NDArray[np.bool_]
    status: NDArray[np.int8]

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.success)) if self.success.size else float("nan")

    @property
    def message(self) -> str:
        counts = np.bincount(self.status, minlength=len(STATUS_NAMES))
        return ", ".join(f"{n} {s}" for s, n in zip(STATUS_NAMES, counts, strict=False) if n)


@dataclass(frozen=True)
class SimulationResult(Outcomes):
    """A batch of runs: per-start arrays plus counters (scipy ``OdeResult`` style).

    status codes index :data:`STATUS_NAMES`; ``paths`` holds each robot's accepted points
    when ``record_paths`` was set; ``nfev`` counts batch evaluations of the velocity field.
    """

    starts: CArray
    goal: complex
    success: NDArray[np.bool_]
    collided: NDArray[np.bool_]
    status: NDArray[np.int8]
    time: FArray
    path_length: FArray
    min_clearance: FArray
    final_distance: FArray
    max_speed: FArray
    n_steps: NDArray[np.int64]
    final: CArray
    nfev: int
    wall_time: float
    paths: tuple[CArray, ...] | None = field(default=None, repr=False)
    reasons: tuple[str, ...] = ()

    def run(self, i: int) -> RunResult:
        return RunResult(
            start=complex(self.starts[i]),
            success=bool(self.success[i]),
            collided=bool(self.collided[i]),
            status=STATUS_NAMES[int(self.status[i])],
            time=float(self.time[i]),
            path_length=float(self.path_length[i]),
            min_clearance=float(self.min_clearance[i]),
            final_distance=float(self.final_distance[i]),
            max_speed=float(self.max_speed[i]),
            n_steps=int(self.n_steps[i]),
            reason=self.reasons[i] if self.reasons else "",
        )

    def runs(self) -> list[RunResult]:
        return [self.run(i) for i in range(self.starts.size)]


def _clearance_of(fld: Any) -> Clearance | None:
    for obj in (fld, getattr(fld, "cmap", None)):
        ws = getattr(obj, "workspace", None)
        if ws is not None and hasattr(ws, "clearance"):
            return ws.clearance  # type: ignore[no-any-return]
    return None


def _chord_check(
    a: CArray, b: CArray, ca: FArray, cb: FArray, clearance: Clearance, max_depth: int = 40
) -> tuple[NDArray[np.bool_], FArray]:
    """For chords a->b: (hits an obstacle, lower bound of the clearance along the chord)."""
    n = a.size
    hit = np.zeros(n, dtype=bool)
    low = np.minimum(ca, cb)
    idx = np.arange(n)
    for _ in range(max_depth):
        length = np.abs(b - a)
        bad = length >= ca + cb
        if not bad.any():
            break
        a, b, ca, cb, idx = a[bad], b[bad], ca[bad], cb[bad], idx[bad]
        m = 0.5 * (a + b)
        cm = np.asarray(clearance(m), dtype=np.float64)
        np.minimum.at(low, idx, cm)
        h = cm <= 0
        hit[idx[h]] = True
        keep = ~h
        a, b, ca, cb, m, cm, idx = (
            a[keep],
            b[keep],
            ca[keep],
            cb[keep],
            m[keep],
            cm[keep],
            idx[keep],
        )
        # split into the two halves
        a, b = np.concatenate([a, m]), np.concatenate([m, b])
        ca, cb = np.concatenate([ca, cm]), np.concatenate([cm, cb])
        idx = np.concatenate([idx, idx])
    return hit, low


def _curve_check(
    z0: CArray,
    z1: CArray,
    h: FArray,
    k0: CArray,
    k1: CArray,
    c0: FArray,
    c1: FArray,
    clearance: Clearance,
    pieces: int = 16,
) -> tuple[NDArray[np.bool_], FArray]:
    """:func:`_chord_check` along the cubic Hermite interpolant of steps (the integrator's
    dense output; Hairer, Norsett, Wanner, *Solving ODE I*, sec. II.6) instead of their chord:
    ``pieces`` sub-chords each.  (hits an obstacle, clearance lower bound) per step."""
    s = np.linspace(0.0, 1.0, pieces + 1)[1:-1]
    mid = _hermite(z0[:, None], z1[:, None], h[:, None], k0[:, None], k1[:, None], s[None, :])
    pts = np.concatenate([z0[:, None], mid, z1[:, None]], axis=1)
    cm = np.asarray(clearance(mid.ravel()), dtype=np.float64).reshape(mid.shape)
    cs = np.concatenate([c0[:, None], cm, c1[:, None]], axis=1)
    hit, low = _chord_check(
        pts[:, :-1].ravel(), pts[:, 1:].ravel(), cs[:, :-1].ravel(), cs[:, 1:].ravel(), clearance
    )
    n = z0.size
    hits = np.asarray(hit.reshape(n, pieces).any(axis=1), dtype=bool)
    return hits, np.asarray(low.reshape(n, pieces).min(axis=1), dtype=np.float64)


def _hermite(z0: CArray, z1: CArray, h: FArray, k0: CArray, k1: CArray, s: FArray) -> CArray:
    s2, s3 = s * s, s * s * s
    return (
        (2 * s3 - 3 * s2 + 1) * z0
        + (s3 - 2 * s2 + s) * h * k0
        + (-2 * s3 + 3 * s2) * z1
        + (s3 - s2) * h * k1
    )


def _goal_crossing(
    z0: CArray, z1: CArray, h: FArray, k0: CArray, k1: CArray, goal: complex, tol: float
) -> tuple[FArray, CArray]:
    """Fraction s of the step where the cubic Hermite interpolant enters the goal disk."""
    lo, hi = np.zeros(z0.size), np.ones(z0.size)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        inside = np.abs(_hermite(z0, z1, h, k0, k1, mid) - goal) <= tol
        hi = np.where(inside, mid, hi)
        lo = np.where(inside, lo, mid)
    return hi, _hermite(z0, z1, h, k0, k1, hi)


def simulate(
    fld: VelocityField,
    starts: ArrayLike,
    *,
    clearance: Clearance | None = None,
    t_max: float = 1e4,
    atol: float = 1e-5,
    max_step: float = 0.05,
    max_steps: int = 20000,
    stall_distance: float | None = None,
    stall_steps: int = 100,
    stall_window: float = 10.0,
    stall_progress: float = 0.05,
    record_paths: bool = False,
) -> SimulationResult:
    """Integrate ``x' = u(x)`` from every start until goal, collision, ``t_max`` or
    ``max_steps``.

    Parameters
    ----------
    fld : VelocityField (e.g. a Controller).
    starts : complex array (N,) or (N, 2) real array of start points.
    clearance : signed distance to the obstacles (> 0 in free space); default: the field's
        ``workspace.clearance`` (or its map's).
    t_max : time limit per robot.
    atol : local error bound on the position per step.
    max_step : largest chord per step (workspace units).
    max_steps : step limit per robot.
    stall_window, stall_progress : a robot whose progress over ``stall_window`` time units is
        below ``stall_progress`` is ``stalled``.  Progress is measured in the circle domain
        when the field has ``circle_domain_position`` (a :class:`Controller`): ``|w(t) -
        w(t - W)| / s``, ``w = T(x)``, ``s = min(clearance of w, |w - w_d|)`` at the window
        start.  Why this quantity and not phi itself: along the law's paths ``w`` follows an
        integral curve of ``-grad phi`` (a time change, see :mod:`confnav.navigation.control`),
        which
        never closes, so a robot that is not at a critical point moves ``w`` by a fair share
        of its local scale; the ratio does not vanish in pockets (there ``|T'|`` shrinks
        numerator and denominator alike), whereas ``1 - phi`` is 1e-11 in a pocket and below
        the accuracy of the harmonic fit (measured: ``1 - phi`` negative at 1e-11 in a
        charging-alcove scene), so neither phi nor ``log(1 - phi)`` can be trusted there.
        Near the goal ``s = |w - w_d|`` and the law's exponential approach gives a ratio
        near 1.  Other fields: the same test on the workspace position with
        ``s = min(clearance, |x - x_d|)``.
    stall_distance, stall_steps : a robot that stays within ``stall_distance`` (default 10
        goal tolerances) of one point for ``stall_steps`` accepted steps is ``stalled`` too
        (chattering at a critical point of a non-smooth field).
    record_paths : keep every accepted point of every robot.

    Raises
    ------
    NavigationError
        for non-finite starts, or starts outside the free space, or no clearance function.

    The steps, in order: :func:`_start` (checks, first velocity and step size), then while a
    robot runs: :func:`_dormand_prince` (one step of every running robot),
    :func:`_step_sizes` (accept or reject, next step size), :func:`_accept` (goal crossing,
    collision check, bookkeeping, stall and time limits); :func:`_finish` (the result).
    """
    import time as _time

    t0 = _time.perf_counter()
    clr = clearance if clearance is not None else _clearance_of(fld)
    if clr is None:
        raise NavigationError("simulate needs a clearance function (no workspace on the field)")
    opts = _Options(
        goal=complex(fld.goal),
        tol=float(fld.goal_tol),
        t_max=t_max,
        atol=atol,
        max_step=max_step,
        max_steps=max_steps,
        stall_distance=10.0 * float(fld.goal_tol) if stall_distance is None else stall_distance,
        stall_steps=stall_steps,
        stall_window=stall_window,
        stall_progress=stall_progress,
        record_paths=record_paths,
        clearance=clr,
        progress=_progress_measure(fld, clr, complex(fld.goal)),
    )
    run = _start(fld, starts, opts)
    while True:
        ai = np.flatnonzero(run.status < 0)
        if ai.size == 0:
            break
        znew, errv, ka = _dormand_prince(fld, run, ai)
        ok, hn, chord, speed = _step_sizes(run.z[ai], run.h[ai], znew, errv, ka[6], opts)
        _accept(run, ai, ok, znew, chord, speed, ka, opts)
        _next_step(run, ai, hn, opts)
    return _finish(fld, run, opts, _time.perf_counter() - t0)


@dataclass(frozen=True)
class _Options:
    """What :func:`simulate` was asked (and the field's goal, clearance and progress measure)."""

    goal: complex
    tol: float
    t_max: float
    atol: float
    max_step: float
    max_steps: int
    stall_distance: float
    stall_steps: int
    stall_window: float
    stall_progress: float
    record_paths: bool
    clearance: Clearance
    progress: Callable[[CArray], tuple[CArray, FArray]]


@dataclass
class _Run:
    """The state of a batch during :func:`simulate`: one entry per robot (status < 0: running);
    ``k1`` the velocity at ``z`` (the first stage of the next step, FSAL), ``h`` the next step,
    ``w_ref, s_ref, t_ref`` the progress window's start, ``z_anchor, n_anchor`` the point and
    step count the robot last moved ``stall_distance`` away from."""

    z0: CArray
    z: CArray
    t: FArray
    h: FArray
    k1: CArray
    status: NDArray[np.int8]
    cur_clr: FArray
    length: FArray
    minclr: FArray
    vmax: FArray
    nsteps: NDArray[np.int64]
    w_ref: CArray
    s_ref: FArray
    t_ref: FArray
    z_anchor: CArray
    n_anchor: NDArray[np.int64]
    nfev: int = 0
    path_chunks: list[tuple[NDArray[np.intp], CArray]] = field(default_factory=list)


def _progress_measure(
    fld: Any, clr: Clearance, goal: complex
) -> Callable[[CArray], tuple[CArray, FArray]]:
    """``(position, local scale)`` of the stall test: the circle-domain image and scale when the
    field has ``circle_domain_position`` (a Controller), else the workspace position and
    ``min(clearance, |x - x_d|)`` (:func:`simulate`, ``stall_window``)."""
    progress_of = getattr(fld, "circle_domain_position", None)

    def position_and_scale(zz: CArray) -> tuple[CArray, FArray]:
        if progress_of is not None:
            w, sc = progress_of(zz)
            return np.asarray(w, dtype=np.complex128), np.asarray(sc, dtype=np.float64)
        sc = np.minimum(np.asarray(clr(zz), dtype=np.float64), np.abs(zz - goal))
        return zz, sc

    return position_and_scale


def _start(fld: VelocityField, starts: ArrayLike, o: _Options) -> _Run:
    """Check the starts, mark those already at the goal, evaluate the first velocity and choose
    the first step (5 % of the clearance or ``max_step``, whichever is smaller)."""
    z = _as_points(starts).copy()
    c0 = np.asarray(o.clearance(z), dtype=np.float64)
    if np.any(~(c0 > 0)):
        i = int(np.flatnonzero(~(c0 > 0))[0])
        raise NavigationError(f"start {fmt_point(z[i])} is not in the free space")
    n = z.size
    w_ref, s_ref = o.progress(z)
    status = np.full(n, -1, dtype=np.int8)
    status[np.abs(z - o.goal) <= o.tol] = ARRIVED
    k1 = np.full(n, np.nan + 0j)
    act = status < 0
    nfev = 0
    if act.any():
        k1[act] = fld.velocity(z[act])
        nfev += 1
    speed0 = np.abs(k1)
    h = np.where(
        speed0 > 0,
        np.minimum(0.05 * np.maximum(c0, 1e-6), o.max_step) / np.maximum(speed0, 1e-300),
        o.t_max,
    )
    h = np.minimum(h, o.t_max)
    status[act & ~np.isfinite(k1)] = ERROR
    return _Run(
        z0=z.copy(),
        z=z,
        t=np.zeros(n),
        h=h,
        k1=k1,
        status=status,
        cur_clr=c0.copy(),
        length=np.zeros(n),
        minclr=c0.copy(),
        vmax=np.where(np.isfinite(speed0), speed0, 0.0),
        nsteps=np.zeros(n, dtype=np.int64),
        w_ref=w_ref,
        s_ref=s_ref,
        t_ref=np.zeros(n),
        z_anchor=z.copy(),
        n_anchor=np.zeros(n, dtype=np.int64),
        nfev=nfev,
    )


def _dormand_prince(
    fld: VelocityField, run: _Run, ai: NDArray[np.intp]
) -> tuple[CArray, CArray, list[CArray]]:
    """One Dormand-Prince 5(4) step of the running robots ``ai`` (one batch call of the field
    per stage): the new points, the error vectors and the seven stage velocities."""
    za, ha = run.z[ai], run.h[ai]
    ka = [run.k1[ai]]
    for s in range(1, 7):
        zs = za + ha * sum(c * kk for c, kk in zip(_A[s], ka, strict=False) if c != 0.0)
        ks = np.asarray(fld.velocity(zs), dtype=np.complex128)
        run.nfev += 1
        ka.append(ks)
    znew = za + ha * sum(c * kk for c, kk in zip(_A[6], ka, strict=False) if c != 0.0)
    errv = ha * sum(e * kk for e, kk in zip(_E, ka, strict=False) if e != 0.0)
    return znew, errv, ka


def _step_sizes(
    za: CArray, ha: FArray, znew: CArray, errv: CArray, k_end: CArray, o: _Options
) -> tuple[NDArray[np.bool_], FArray, FArray, FArray]:
    """Accept a step when its error is within ``atol`` and its chord within 1.5 ``max_step``;
    the next step from the usual ``0.9 err^(-1/5)`` factor (at most halved after a rejection,
    quartered after a non-finite error), its chord at most ``max_step``.  Returns (ok, next
    step, chord, speed at the end)."""
    err = np.abs(errv) / o.atol
    err = np.where(np.isfinite(err) & np.isfinite(znew), err, np.inf)
    chord = np.abs(znew - za)
    ok = (err <= 1.0) & (chord <= 1.5 * o.max_step)
    with np.errstate(divide="ignore"):
        fac = np.clip(0.9 * err ** (-0.2), 0.2, 5.0)
    fac = np.where(ok, fac, np.minimum(fac, 0.5))
    fac = np.where(np.isfinite(err), fac, 0.25)
    speed = np.abs(k_end)
    hn = ha * fac
    hn = np.where(
        np.isfinite(speed) & (speed > 0),
        np.minimum(hn, o.max_step / np.maximum(speed, 1e-300)),
        hn,
    )
    return ok, hn, chord, speed


def _accept(
    run: _Run,
    ai: NDArray[np.intp],
    ok: NDArray[np.bool_],
    znew: CArray,
    chord: FArray,
    speed: FArray,
    ka: list[CArray],
    o: _Options,
) -> None:
    """Move the robots whose step was accepted: cut a step that enters the goal disk at the
    first crossing, check the step for collisions, update the counters, then the statuses
    (collided, arrived, stalled, time or step limit)."""
    ia = ai[ok]
    if not ia.size:
        return
    zo, zn, hk, ck = run.z[ia], znew[ok], run.h[ai][ok], chord[ok]
    k0, k6 = ka[0][ok], ka[6][ok]
    arr = np.abs(zn - o.goal) <= o.tol
    if arr.any():  # first crossing of the goal circle on the cubic Hermite interpolant
        sa, za_ = _goal_crossing(zo[arr], zn[arr], hk[arr], k0[arr], k6[arr], o.goal, o.tol)
        zn[arr], hk[arr], ck[arr] = za_, hk[arr] * sa, np.abs(za_ - zo[arr])
    cn = np.asarray(o.clearance(zn), dtype=np.float64)
    hit = _collisions(run, ia, zo, zn, hk, k0, k6, cn, arr, o)
    run.z[ia] = zn
    run.t[ia] = run.t[ia] + hk
    run.length[ia] += ck
    run.cur_clr[ia] = cn
    run.nsteps[ia] += 1
    run.k1[ia] = k6
    sp = speed[ok]
    run.vmax[ia] = np.maximum(run.vmax[ia], np.where(np.isfinite(sp), sp, 0.0))
    if o.record_paths:
        run.path_chunks.append((ia, zn.copy()))
    collided = hit | (cn <= 0)
    run.status[ia[collided]] = COLLIDED
    arrived = ~collided & arr
    run.status[ia[arrived]] = ARRIVED
    _stalls_and_limits(run, ia, zn, ~collided & ~arrived, o)


def _collisions(
    run: _Run,
    ia: NDArray[np.intp],
    zo: CArray,
    zn: CArray,
    hk: FArray,
    k0: CArray,
    k6: CArray,
    cn: FArray,
    arr: NDArray[np.bool_],
    o: _Options,
) -> NDArray[np.bool_]:
    """Whether each accepted step hits an obstacle (its chord; a chord that cuts a corner
    between two free ends again along the step's Hermite interpolant); lowers ``minclr``."""
    hit, low = _chord_check(zo, zn, run.cur_clr[ia], cn, o.clearance)
    # a chord that cuts a corner the step's path goes round (both ends free): the path is
    # the step's cubic Hermite interpolant, checked on 16 sub-chords
    again = np.flatnonzero(hit & (cn > 0) & ~arr)
    if again.size:
        hit[again], low[again] = _curve_check(
            zo[again], zn[again], hk[again], k0[again], k6[again],
            run.cur_clr[ia][again], cn[again], o.clearance,
        )  # fmt: skip
    run.minclr[ia] = np.minimum(run.minclr[ia], low)
    return hit


def _stalls_and_limits(
    run: _Run, ia: NDArray[np.intp], zn: CArray, rest: NDArray[np.bool_], o: _Options
) -> None:
    """Statuses of the moved robots ``ia[rest]`` still running: chattering in place for
    ``stall_steps`` steps, no progress over a ``stall_window`` (:func:`simulate`), then the
    time and step limits."""
    moved = np.abs(zn - run.z_anchor[ia]) > o.stall_distance
    run.z_anchor[ia[moved]] = zn[moved]
    run.n_anchor[ia[moved]] = run.nsteps[ia[moved]]
    chatter = rest & (run.nsteps[ia] - run.n_anchor[ia] >= o.stall_steps)
    run.status[ia[chatter]] = STALLED
    rest &= ~chatter
    due = rest & (run.t[ia] - run.t_ref[ia] >= o.stall_window)
    if due.any():
        idx = ia[due]
        w_now, s_now = o.progress(zn[due])
        rel = np.abs(w_now - run.w_ref[idx]) / np.maximum(run.s_ref[idx], 1e-300)
        stuck = ~(rel >= o.stall_progress)
        run.status[idx[stuck]] = STALLED
        run.w_ref[idx], run.s_ref[idx], run.t_ref[idx] = w_now, s_now, run.t[idx]
        rest[np.flatnonzero(due)[stuck]] = False
    late = rest & (run.t[ia] >= o.t_max * (1 - 1e-12))
    run.status[ia[late]] = TIMEOUT
    run.status[ia[rest & ~late & (run.nsteps[ia] >= o.max_steps)]] = TIMEOUT


def _next_step(run: _Run, ai: NDArray[np.intp], hn: FArray, o: _Options) -> None:
    """The next step of the robots just stepped (within ``t_max``); a step that underflows
    (below 1e-13 of the time) ends the robot's run as ``error``."""
    run.h[ai] = np.minimum(hn, o.t_max - run.t[ai])
    run.h[ai] = np.where(run.h[ai] > 0, run.h[ai], 1e-300)
    tiny = run.h[ai] < 1e-13 * np.maximum(run.t[ai], 1.0)
    still = run.status[ai] < 0
    run.status[ai[tiny & still]] = ERROR


def _finish(fld: VelocityField, run: _Run, o: _Options, wall_time: float) -> SimulationResult:
    """The :class:`SimulationResult` of a finished batch (paths joined per robot, reasons)."""
    n = run.z.size
    path_tuple: tuple[CArray, ...] | None = None
    if o.record_paths:
        who = np.concatenate([np.arange(n)] + [c[0] for c in run.path_chunks])
        pts = np.concatenate([run.z0] + [c[1] for c in run.path_chunks])
        order = np.argsort(who, kind="stable")
        path_tuple = tuple(np.split(pts[order], np.cumsum(np.bincount(who, minlength=n))[:-1]))
    reasons = _reasons(
        run.status, run.z, run.t, run.nsteps, o.t_max, o.max_steps, o.stall_window,
        getattr(fld, "near_critical", None),
    )  # fmt: skip
    return SimulationResult(
        starts=run.z0,
        goal=o.goal,
        success=run.status == ARRIVED,
        collided=run.status == COLLIDED,
        status=run.status,
        time=run.t,
        path_length=run.length,
        min_clearance=run.minclr,
        final_distance=np.abs(run.z - o.goal),
        max_speed=run.vmax,
        n_steps=run.nsteps,
        final=run.z,
        nfev=run.nfev,
        wall_time=wall_time,
        paths=path_tuple,
        reasons=reasons,
    )


def _reasons(
    status: NDArray[np.int8],
    z: CArray,
    t: FArray,
    nsteps: NDArray[np.int64],
    t_max: float,
    max_steps: int,
    window: float,
    near_critical: Callable[[CArray], Any] | None,
) -> tuple[str, ...]:
    """One line per robot saying why its run ended."""
    out = [""] * status.size
    st = np.flatnonzero(status == STALLED)
    crit = np.zeros(st.size, dtype=bool)
    if st.size and near_critical is not None:
        crit = np.asarray(near_critical(z[st]), dtype=bool)
    for i, c in zip(st, crit, strict=True):
        out[i] = (
            f"at a critical point of phi near ({z[i].real:.3f}, {z[i].imag:.3f})"
            if c
            else f"no progress over {window:g} s near ({z[i].real:.3f}, {z[i].imag:.3f})"
        )
    for i in np.flatnonzero(status == COLLIDED):
        out[i] = f"hit an obstacle near ({z[i].real:.3f}, {z[i].imag:.3f})"
    for i in np.flatnonzero(status == TIMEOUT):
        out[i] = "step limit" if nsteps[i] >= max_steps else f"time limit {t_max:g} s"
    for i in np.flatnonzero(status == ERROR):
        out[i] = "velocity undefined (NaN) or step size underflow"
    for i in np.flatnonzero(status == ARRIVED):
        out[i] = "arrived"
    return tuple(out)


def _as_points(p: ArrayLike) -> CArray:
    a = np.asarray(p)
    if not np.iscomplexobj(a) and a.ndim == 2 and a.shape[1] == 2:
        a = a[:, 0] + 1j * a[:, 1]
    z = np.atleast_1d(np.asarray(a, dtype=np.complex128)).ravel()
    if not np.all(np.isfinite(z)):
        raise NavigationError("a start is not finite")
    return z
