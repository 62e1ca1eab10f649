"""One control step for a fleet on one map, each robot with its own goal and controller.

A host of many robots (the controller service) keeps one :class:`Controller` per goal.  The
map ``T`` does not depend on the goal, so ``T``, ``T'`` and the clearance are evaluated once
for every robot; this module evaluates the rest in one vectorized pass as well: each goal's
navigation function stacked (:func:`~confnav.navigation.navfn.value_and_gradient_stacked`:
Koditschek-Rimon with a goal and k per robot, the harmonic series with each goal's
coefficients) and the speed law with each controller's parameters as arrays.  Before this, a
fleet with its own goals cost one scalar control step per robot (40-150 us each: 100 robots
at 50 Hz took 0.75 s of CPU per second and the commands fell 100 ms behind, measured in
bench/bench_services.py).

The result is each robot's ``Controller.from_map_values`` (tests/test_fleet_step.py: equal to
rounding), so everything said there (the speed law, the hold cap, the safety layer of
:mod:`confnav.navigation.safety`, stall reports) holds here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from confnav.navigation import defaults
from confnav.navigation.control import SLOW_FLOOR, Controller, ControlOutput, Status, speed_law
from confnav.navigation.navfn import value_and_gradient_stacked
from confnav.types import CArray, FArray

__all__ = ["fleet_step"]


def fleet_step(
    ctrls: Sequence[Controller],
    z: ArrayLike,
    w: ArrayLike,
    dw: ArrayLike,
    clearance: ArrayLike | None = None,
) -> ControlOutput:
    """``ctrls[i].from_map_values(z[i], w[i], dw[i], clearance[i])`` for every i, at once.

    ``ctrls`` share one map (``cmap``); ``(w, dw) = cmap.T_and_dT(z)`` and, optionally,
    ``clearance = ctrls[0].clearance(z)`` are 1-D arrays of ``len(ctrls)``.  A controller may
    appear any number of times (robots sharing a goal).
    """
    z = np.asarray(z, dtype=np.complex128).reshape(-1)
    w = np.asarray(w, dtype=np.complex128).reshape(-1)
    dw = np.asarray(dw, dtype=np.complex128).reshape(-1)
    if not (len(ctrls) == z.size == w.size == dw.size):
        raise ValueError(
            f"{len(ctrls)} controllers for {z.size} poses and {w.size}, {dw.size} values"
        )
    if len({id(c.cmap) for c in ctrls}) > 1:
        raise ValueError("fleet_step needs controllers on one map")
    first: dict[int, int] = {}
    inv = np.array([first.setdefault(id(c), len(first)) for c in ctrls], dtype=np.intp)
    us = list({id(c): c for c in ctrls}.values())  # the distinct controllers, in `first` order

    def per_robot(values: list[object], dtype: type) -> np.ndarray:
        return np.asarray(values, dtype=dtype)[inv]

    goal = per_robot([c.goal for c in us], np.complex128)
    goal_w = per_robot([c.goal_w for c in us], np.complex128)
    bad = ~np.isfinite(z) | ~np.isfinite(w) | ~np.isfinite(dw)
    w = np.where(bad, goal_w, w)
    dw = np.where(bad, 1.0, dw)
    phi, g = value_and_gradient_stacked([c.navfn for c in ctrls], w)
    zc = np.where(bad, goal, z)  # the bad poses are evaluated at the goal (then u = 0)

    uses = per_robot([c.uses_clearance for c in us], bool)
    slow = v_cap = None
    if uses.any():
        user = us[int(inv[np.argmax(uses)])]
        if clearance is None:
            c = user.clearance(zc)
        else:
            c = np.array(clearance, dtype=np.float64).reshape(-1)
            if bad.any():
                c[bad] = user.clearance(goal[bad])
        sd = np.where(uses, per_robot([c_.slow_distance for c_ in us], np.float64), 0.0)
        ht = np.where(uses, per_robot([c_.hold_time for c_ in us], np.float64), 0.0)
        if (sd > 0).any():  # factor 1 where off: the same u as Controller._command
            slow = np.where(sd > 0, np.clip(c / np.where(sd > 0, sd, 1.0), SLOW_FLOOR, 1.0), 1.0)
        if (ht > 0).any():  # a command held hold_time s moves <= HOLD_FRACTION * c
            cap = defaults.HOLD_FRACTION * np.maximum(c, 0.0) / np.where(ht > 0, ht, 1.0)
            v_cap = np.where(ht > 0, cap, np.inf)

    field = -np.conj(dw) * g
    dist = np.abs(zc - goal)
    gain = per_robot([c.gain for c in us], np.float64)
    v_max = per_robot([c.v_max for c in us], np.float64)
    laws = per_robot([c.speed_law for c in us], object)
    u = np.empty(z.size, dtype=np.complex128)
    sat = np.empty(z.size, dtype=bool)
    for law in set(laws.tolist()):
        m = laws == law
        u[m], sat[m] = speed_law(
            field[m],
            dist[m],
            law=law,
            gain=gain[m],  # per robot: numpy broadcasts
            v_max=v_max[m],
            slow=None if slow is None else slow[m],
            v_cap=None if v_cap is None else v_cap[m],
        )
    filt = _safety_layer(us, inv, zc, u, sat)
    goal_tol = per_robot([c.goal_tol for c in us], np.float64)
    arrived = ~bad & (np.abs(z - goal) <= goal_tol)
    stalled = ~bad & ~arrived & _near_critical(us, inv, w, dw)
    status = np.full(z.shape, Status.MOVING, dtype=np.int8)
    status[stalled] = Status.STALLED
    status[arrived] = Status.ARRIVED
    status[bad] = Status.ERROR
    return ControlOutput(
        u=np.where(arrived | bad, 0j, u),
        status=status,
        phi=np.where(bad, np.nan, phi),
        w=np.where(bad, np.nan + 0j, w),
        saturated=sat & ~arrived & ~bad,
        filtered=None if filt is None else filt & ~arrived & ~bad,
    )


def _safety_layer(
    us: list[Controller], inv: np.ndarray, z: CArray, u: CArray, sat: np.ndarray
) -> np.ndarray | None:
    """``Controller._command``'s safety layer for every robot, in place on ``u``/``sat``
    (one call per distinct filter: controllers of one workspace share it); the changed mask,
    or None when no controller has one."""
    flts = [c.safety for c in us]
    if all(f is None for f in flts):
        return None
    changed = np.zeros(z.size, dtype=bool)
    key = np.array([id(f) for f in flts], dtype=np.int64)[inv]
    for f in {id(f): f for f in flts if f is not None}.values():
        m = np.flatnonzero(key == id(f))
        pr = f(z[m], u[m])
        u[m], changed[m] = pr.u, pr.changed
        sat[m] &= ~pr.changed
        n_ch = np.bincount(inv[m], weights=pr.changed, minlength=len(us))
        n_in = np.bincount(inv[m], weights=pr.infeasible, minlength=len(us))
        n_all = np.bincount(inv[m], minlength=len(us))
        for j in np.flatnonzero(n_all):  # per distinct controller (stats only)
            us[j].safety_counts.add(int(n_all[j]), int(n_ch[j]), int(n_in[j]))
    return changed


def _near_critical(us: list[Controller], inv: np.ndarray, w: CArray, dw: CArray) -> np.ndarray:
    """``Controller._near_critical`` per robot: its controller's stall points, padded."""
    pts = [c._stall_points() for c in us]
    width = max(p.size for p in pts)
    if width == 0:
        return np.zeros(w.shape, dtype=bool)
    table = np.full((len(us), width), np.inf + 0j, dtype=np.complex128)
    for i, p in enumerate(pts):
        table[i, : p.size] = p
    d: FArray = np.min(np.abs(w[:, None] - table[inv]), axis=1)
    radius = np.array([c.stall_radius for c in us], dtype=np.float64)[inv]
    return np.asarray(d <= radius * np.abs(dw))
