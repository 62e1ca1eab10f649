"""A fleet driven together: N robots, each with its own :class:`Controller` and goal on one
workspace, filtered against each other, the walls and moving disks, integrated step-wise.

Every ``dt`` (the control period, at most the hold time) all robots get a new command at
once, computed from the same snapshot: the nominal command of each robot's controller
(:func:`~confnav.navigation.fleet.fleet_step`, batched per map), turned by the side-passing
rule (:func:`~confnav.navigation.fleet.side_pass`), then projected onto the pairwise rows
(:func:`~confnav.navigation.fleet.pairwise_rows`), the wall rows of the robot's safety layer
(``Controller.safety``, :mod:`confnav.navigation.safety`) in the same projection
(:func:`~confnav.navigation.fleet.project_with_walls`) and the wall cap ``|u| <= fraction *
c_body / hold_time`` (the hold cap of :mod:`confnav.navigation.control`: ``c_body`` is the
exact clearance of the robot's disk, 1-Lipschitz, so a command held ``hold_time`` keeps the
disk off every wall, with or without the safety layer).  Commands are held exactly (points:
straight lines; unicycles: exact arcs, :func:`~confnav.navigation.unicycle.step_exact`).

Contacts are checked along every step, not at its ends: robot-robot and robot-mover with the
exact closest approach of linearly moving centres
(:func:`~confnav.navigation.fleet.swept_min_distance`; a unicycle's axle is taken along its
chord), walls with the core's chord check (:func:`confnav.navigation.sim._chord_check`).
See docs/NAVIGATION.md, "Fleets".
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from confnav.geometry import Workspace
from confnav.navigation import defaults
from confnav.navigation.control import Controller, Status
from confnav.navigation.fleet import (
    DeadlockMonitor,
    Rows,
    fleet_step,
    goal_yielders,
    pairwise_rows,
    project_with_walls,
    side_pass,
    swept_min_distance,
    yield_way,
)
from confnav.navigation.fleet_coord import RoadmapCoordinator
from confnav.navigation.sim import _chord_check
from confnav.navigation.traffic import Gates, Traffic, find_gates
from confnav.navigation.unicycle import step_exact, twist_from_velocity
from confnav.types import CArray, FArray

__all__ = ["FleetResult", "Mover", "simulate_fleet"]


@dataclass(frozen=True)
class Mover:
    """A disk (a person, a forklift) moving from ``start`` to ``end`` at ``speed`` from time
    ``t_start`` on, then standing at ``end``; its velocity is known to the filter."""

    start: complex
    end: complex
    radius: float
    speed: float
    t_start: float = 0.0

    def state(self, t: float) -> tuple[complex, complex]:
        """Position and velocity at time ``t``."""
        d = self.end - self.start
        length = abs(d)
        if length == 0 or t < self.t_start:
            return self.start, 0j
        s = (t - self.t_start) * self.speed
        if s >= length:
            return self.end, 0j
        return self.start + d * (s / length), d / length * self.speed


@dataclass
class FleetResult:
    """Outcome of :func:`simulate_fleet` (times in s, distances in m)."""

    arrived: NDArray[np.bool_]
    arrival_time: FArray
    robot_contacts: int
    mover_contacts: int
    wall_contacts: int
    min_gap: float
    min_mover_gap: float
    min_wall_clearance: float
    t_end: float
    steps: int
    filter_time: float
    errors: int
    infeasible: int
    deadlocks: int
    contact_pairs: list[tuple[int, int, float]] = field(default_factory=list)
    paths: CArray | None = None
    final: CArray | None = None  # positions at the end (axles for unicycles)
    final_theta: FArray | None = None
    reached: NDArray[np.intp] | None = None  # goals reached per robot (with ``next_goals``)
    goals: int = 0  # goals given in all (first goals and ``next_goals``)
    yields: int = 0  # robot-steps an idle robot spent yielding
    gates: int = 0  # single-lane passages used as mutexes
    waits: int = 0  # robot-steps spent waiting for a gate
    goal_yields: int = 0  # robot-steps a robot on a neighbour's goal counted as idle

    @property
    def arrival_rate(self) -> float:
        return float(self.arrived.mean()) if self.arrived.size else float("nan")

    @property
    def last_arrival(self) -> float:
        return float(np.nanmax(self.arrival_time)) if self.arrived.all() else float("inf")

    @property
    def filter_us_per_robot_step(self) -> float:
        n = self.arrived.size
        return 1e6 * self.filter_time / max(self.steps * n, 1)


def _lowered(clear: Callable[[CArray], FArray], by: float) -> Callable[[CArray], FArray]:
    def f(q: CArray) -> FArray:
        return np.asarray(clear(q), dtype=np.float64) - by

    return f


def simulate_fleet(
    controllers: Sequence[Controller],
    starts: ArrayLike,
    workspace: Workspace,
    *,
    radius: ArrayLike = 0.0,
    lookahead: ArrayLike | None = None,
    theta: ArrayLike | None = None,
    omega_max: float = 2.0,
    movers: Sequence[Mover] = (),
    dt: float = 0.05,
    hold_time: float = defaults.HOLD_TIME,
    fraction: float = defaults.HOLD_FRACTION,
    t_max: float = 120.0,
    avoid: bool = True,
    side_passing: bool = True,
    record_paths: bool = False,
    mover_horizon: float = 2.0,
    pass_angle: float = np.pi / 4,
    deadlock_window: float = 1.0,
    next_goals: Sequence[Sequence[Controller]] | None = None,
    yielding: bool = True,
    yield_gap: float = 0.6,
    contact_margin: float = 1e-3,
    wall_fade: bool = True,
    traffic: bool = False,
    gates: Gates | None = None,
    trace_every: int = 5,
    trace_step: float = 0.1,
    trace_points: int = 15,
    goal_yield: bool = False,
    backoff: float = 0.15,
    coordinator: RoadmapCoordinator | None = None,
) -> FleetResult:
    """Drive robot i from ``starts[i]`` with ``controllers[i]`` until all arrive or ``t_max``.

    ``radius``: body radii; ``lookahead``: per robot 0 (a point robot, the default) or the
    look-ahead distance d of a unicycle (its controller steers the point d ahead of the axle,
    on the map of the free space shrunk by ``r + d``; its disk in the filter is ``r + d``
    around that point); ``theta``: initial headings.  ``avoid`` False: no pairwise rows (the
    robots are ghosts to each other, the state before the fleet filter); the wall cap stays.
    ``mover_horizon``: movers count as the capsule they sweep in that many seconds
    (:func:`~confnav.navigation.fleet.pairwise_rows`).  ``pass_angle``, ``deadlock_window``:
    the side-passing rule's largest turn and the deadlock monitor's window
    (:func:`~confnav.navigation.fleet.side_pass`,
    :class:`~confnav.navigation.fleet.DeadlockMonitor`).

    ``next_goals[i]``: the controllers of robot i's later goals, taken in order when it
    reaches the current one (a new goal is issued on arrival); a robot is done, and its
    ``arrival_time`` is set, when it reaches its last goal.  ``yielding``: done robots step
    out of the way of a robot whose path they block (:func:`~confnav.navigation.fleet.
    yield_way`, within ``yield_gap`` m) and return to their goal afterwards.
    ``wall_fade``: the side-passing turn fades out within 0.25 m of a wall
    (:func:`~confnav.navigation.fleet.side_pass`' ``clearance``).  ``contact_margin``: the
    pairwise rows see each disk ``contact_margin / 2`` larger than it
    is (the walls do not: a lone robot drives exactly as without it), so the barrier's
    geometric decay in a standoff (``h`` may shrink by ``1 - fraction`` per hold, down to
    rounding) ends ``contact_margin`` m short of contact, not at a round-off "contact".

    ``traffic``: the single-lane passages of ``workspace`` for the largest filter disk
    (``gates``, default :func:`~confnav.navigation.traffic.find_gates`) are mutexes
    (:class:`~confnav.navigation.traffic.Traffic`): every ``trace_every`` steps each robot's
    path is traced ``trace_points`` points of ``trace_step`` m ahead along its nominal
    command; a robot whose path enters a gate held the other way waits (nominal command 0
    within the mutex's ``stop`` distance; nearer than ``stop - backoff`` it backs away from
    the gate at half speed) and steps aside like an idle robot.  ``goal_yield``:
    a robot whose disk covers the goal of a neighbour that is nearer its goal than the robot
    is to its own steps aside like an idle robot (:func:`~confnav.navigation.fleet.
    goal_yielders`).  Both are off by default: on the warehouse bench they reached fewer
    goals than without them (bench/README.md, docs/NAVIGATION.md "Fleets").

    ``coordinator``: the robots move on a roadmap as planned by a
    :class:`~confnav.navigation.fleet_coord.RoadmapCoordinator` (PIBT steps between nodes,
    excursions to the goals): each step a robot is driven by its current node's controller,
    or by its goal's controller on the goal leg (arrival counts only there); side passing,
    yielding and the gates are off (the plan replaces them); the fleet filter stays on.
    """
    ctrls = list(controllers)
    queue = [list(q) for q in next_goals] if next_goals is not None else [[] for _ in ctrls]
    x = np.asarray(starts, dtype=np.complex128).reshape(-1).copy()
    n = x.size
    if len(ctrls) != n:
        raise ValueError(f"{len(ctrls)} controllers for {n} starts")
    if len(queue) != n:
        raise ValueError(f"next_goals for {len(queue)} robots, {n} starts")
    n_goals = n + sum(len(q) for q in queue)
    reached = np.zeros(n, dtype=np.intp)
    yields = 0
    if not 0 < dt <= hold_time:
        raise ValueError(f"the control period dt must be in (0, hold_time], got {dt}")
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,)).copy()
    d = np.zeros(n) if lookahead is None else np.broadcast_to(np.asarray(lookahead, float), (n,))
    th = np.zeros(n) if theta is None else np.broadcast_to(np.asarray(theta, float), (n,)).copy()
    uni = d > 0
    rf = r + d  # the filter's disk: around the look-ahead point for a unicycle
    goal = np.array([c.goal for c in ctrls], dtype=np.complex128)
    v_max = np.array([c.v_max for c in ctrls], dtype=np.float64)
    gidx = _map_groups(ctrls)
    radii_groups = [(rv, np.flatnonzero(r == rv)) for rv in np.unique(r)]
    clear = workspace.clearance
    # each robot's wall filter (the safety layer on its map's workspace), joined with the rows
    walls = [getattr(c, "safety", None) for c in ctrls]

    c_now = np.asarray(clear(x), dtype=np.float64) - r
    if np.any(~(c_now > 0)):
        i = int(np.flatnonzero(~(c_now > 0))[0])
        raise ValueError(f"robot {i} starts in contact with a wall (clearance {c_now[i]:.3g})")
    arrival = np.full(n, np.nan)
    frozen = np.zeros(n, dtype=bool)  # hit a wall or error: stays put
    monitor = DeadlockMonitor(n, window=deadlock_window)
    if gates is None:
        use = traffic and avoid and float(rf.max(initial=0.0)) > 0
        gates = find_gates(workspace, float(rf.max())) if use else Gates.none()
    mutex = Traffic(gates, n)
    path_ahead = np.full((n, trace_points + 1), np.nan + 0j)
    waiting = np.zeros(n, dtype=bool)
    goal_yields = 0
    in_contact: set[tuple[int, int]] = set()
    mover_touch = np.zeros((len(movers), n), dtype=bool)
    pairs_out: list[tuple[int, int, float]] = []
    robot_contacts = mover_contacts = wall_contacts = errors = infeasible = 0
    min_gap = min_mover_gap = np.inf
    min_wall = float(c_now.min())
    filter_time = 0.0
    paths = [x.copy()] if record_paths else None
    t = 0.0
    steps = 0
    coord = coordinator
    if coord is not None:
        coord.start(x + d * np.exp(1j * th))
        side_passing = yielding = False
        gates = Gates.none()
    while t < t_max - 1e-12:
        p = x + d * np.exp(1j * th)
        u_nom = np.zeros(n, dtype=np.complex128)
        status = np.full(n, Status.MOVING, dtype=np.int8)
        driving: Sequence[Controller] = ctrls
        groups = gidx
        leg = None
        if coord is not None:
            drv, leg = coord.update(t, p, goal, ~np.isnan(arrival))
            driving = [ctrls[i] if c is None else c for i, c in enumerate(drv)]
            groups = _map_groups(driving)
        for g in groups:
            cm = getattr(driving[int(g[0])], "cmap", None)
            if cm is None:  # a law without a map (fleet_coord.LineLaw): called directly
                o = driving[int(g[0])](p[g])
                u_nom[g], status[g] = o.u, o.status
                continue
            w, dw = cm.T_and_dT(p[g])
            out = fleet_step([driving[i] for i in g], p[g], w, dw)
            u_nom[g], status[g] = out.u, out.status
        if leg is not None:  # arrival counts on the goal leg only
            status = np.where(leg | (status == Status.ERROR), status, Status.MOVING)
        now_arr = (status == Status.ARRIVED) & np.isnan(arrival)
        if coord is not None:  # a done robot gone back to its goal arrives there again
            again = (
                leg & (status == Status.ARRIVED) & ~np.isnan(arrival)
                if leg is not None
                else now_arr
            )
            for i_ in np.flatnonzero(now_arr | again):
                coord.reached(int(i_))
        reached += now_arr
        nxt = now_arr & np.array([len(q) > 0 for q in queue], dtype=bool)
        for i_ in np.flatnonzero(nxt):  # a new goal on arrival (rare: per goal, not per step)
            i = int(i_)
            ctrls[i] = queue[i].pop(0)
            goal[i], v_max[i] = ctrls[i].goal, ctrls[i].v_max
            walls[i] = getattr(ctrls[i], "safety", None)
            monitor.best[i], monitor.t_best[i] = np.inf, t
            u_nom[i] = 0j  # it starts toward the new goal at the next step
            status[i] = Status.MOVING
        if nxt.any():
            gidx = _map_groups(ctrls)
        arrival[now_arr & ~nxt] = t
        bad = (status == Status.ERROR) & ~frozen
        errors += int(bad.sum())
        frozen |= bad
        if np.all(~np.isnan(arrival) | frozen):
            break
        u_nom = np.where(frozen | ~np.isfinite(u_nom), 0j, u_nom)
        mz = np.array([m.state(t)[0] for m in movers], dtype=np.complex128)
        mv = np.array([m.state(t)[1] for m in movers], dtype=np.complex128)
        mr = np.array([m.radius for m in movers], dtype=np.float64)

        t0 = time.perf_counter()
        cb = np.asarray(clear(p), dtype=np.float64) - rf
        cap = np.minimum(v_max, fraction * np.maximum(cb, 0.0) / hold_time)
        if avoid:
            rows = pairwise_rows(
                p,
                np.where(rf > 0, rf + 0.5 * contact_margin, rf),  # points stay points
                v_max,
                others=mz,
                others_radius=mr,
                others_velocity=mv,
                others_mover=np.ones(mz.size, dtype=bool),
                hold_time=hold_time,
                fraction=fraction,
                active=~frozen,
                horizon=mover_horizon,
            )
        else:
            rows = Rows.empty(n)
        moving = np.isnan(arrival) & ~frozen
        if gates.count:
            if steps % trace_every == 0:
                path_ahead = _trace(ctrls, gidx, p, trace_points, trace_step)
            path_ahead[:, 0] = p
            waiting, _ = mutex.update(p, path_ahead, moving)
            # a waiting robot stands still, or backs off to the stop distance if nearer
            e_away, d_gate = mutex.away(p)
            back = waiting & (d_gate < mutex.stop - backoff)
            u_nom = np.where(waiting, np.where(back, 0.5 * v_max * e_away, 0j), u_nom)
        blocked = monitor.update(t, np.abs(p - goal), rows) if side_passing else None
        if waiting.any():  # a waiting robot is not blocked: its clock restarts
            monitor.t_best[waiting] = t
            if blocked is not None:
                blocked = blocked & ~waiting
        if yielding and avoid:  # toward the goals, before side passing turns them
            idle = ~np.isnan(arrival) & ~frozen
            idle |= waiting
            if goal_yield:
                gy = goal_yielders(p, goal, rf, rows, moving)
                goal_yields += int(gy.sum())
                idle |= gy
            u_yield, yl = yield_way(
                u_nom, p, rf, idle, rows, v_max, clearance=cb, yield_gap=yield_gap
            )
            yields += int(yl.sum())
        if side_passing:
            u_nom = side_pass(
                u_nom,
                rows,
                blocked=blocked,
                angle=pass_angle,
                clearance=cb if wall_fade else None,
            )
        if yielding and avoid:
            u_nom = np.where(yl, u_yield, u_nom)
            if waiting.any():  # a waiting robot steps aside, never into its gate
                u_nom = np.where(waiting & mutex.toward(p, u_nom), 0j, u_nom)
        u, ok = project_with_walls(u_nom, p, rows, cap, walls)
        filter_time += time.perf_counter() - t0
        infeasible += int((~ok).sum())
        u = np.where(frozen, 0j, u)

        x0 = x.copy()
        if (~uni).any():
            x[~uni] = x[~uni] + u[~uni] * dt
        if uni.any():
            v, om = twist_from_velocity(u[uni], th[uni], d[uni], v_max[uni], omega_max)  # type: ignore[arg-type]
            x[uni], th[uni] = step_exact(x[uni], th[uni], v, om, dt)
        t += dt
        steps += 1
        if record_paths and paths is not None:
            paths.append(x.copy())

        # contacts along the step: walls (chord check), robots and movers (swept disks)
        c_new = np.empty(n)
        for rv, idx in radii_groups:
            c_new[idx] = np.asarray(clear(x[idx]), dtype=np.float64) - rv
            hit, low = _chord_check(x0[idx], x[idx], c_now[idx], c_new[idx], _lowered(clear, rv))
            min_wall = min(min_wall, float(low.min(initial=np.inf)))
            newly = hit | (c_new[idx] <= 0)
            newly &= ~frozen[idx]
            wall_contacts += int(newly.sum())
            frozen[idx[newly]] = True
        c_now = c_new
        if n > 1:
            reach = 2 * float(r.max()) + float(np.abs(x - x0).max(initial=0.0)) + 1.0
            mid = 0.5 * (x + x0)
            pr = cKDTree(np.column_stack([mid.real, mid.imag])).query_pairs(
                reach, output_type="ndarray"
            )
            if pr.size:
                a_, b_ = pr[:, 0], pr[:, 1]
                dmin, _ = swept_min_distance(x0[a_], x[a_], x0[b_], x[b_])
                gap = dmin - r[a_] - r[b_]
                min_gap = min(min_gap, float(gap.min()))
                touching = {(int(i), int(j)) for i, j, g in zip(a_, b_, gap, strict=True) if g <= 0}
                for pair in touching - in_contact:
                    robot_contacts += 1
                    pairs_out.append((pair[0], pair[1], t))
                in_contact = touching
        for mi, m in enumerate(movers):
            m0 = mz[mi]
            m1 = m.state(t)[0]
            dmin, _ = swept_min_distance(x0, x, np.full(n, m0), np.full(n, m1))
            gap = dmin - r - m.radius
            min_mover_gap = min(min_mover_gap, float(gap.min()))
            touch = gap <= 0
            mover_contacts += int((touch & ~mover_touch[mi]).sum())  # contact onsets
            mover_touch[mi] = touch
    return FleetResult(
        arrived=~np.isnan(arrival),
        arrival_time=arrival,
        robot_contacts=robot_contacts,
        mover_contacts=mover_contacts,
        wall_contacts=wall_contacts,
        min_gap=float(min_gap),
        min_mover_gap=float(min_mover_gap),
        min_wall_clearance=float(min_wall),
        t_end=t,
        steps=steps,
        filter_time=filter_time,
        errors=errors,
        infeasible=infeasible,
        deadlocks=monitor.detections,
        contact_pairs=pairs_out,
        paths=np.array(paths) if paths is not None else None,
        final=x.copy(),
        final_theta=th.copy(),
        reached=reached,
        goals=n_goals,
        yields=yields,
        gates=gates.count,
        waits=mutex.waits,
        goal_yields=goal_yields,
    )


def _trace(
    ctrls: Sequence[Controller], gidx: list[NDArray[np.intp]], p: CArray, k: int, h: float
) -> CArray:
    """Each robot's path ahead: ``k`` steps of ``h`` m along its nominal command (the
    batched fleet step per map, safety layer included), NaN after it arrives or stops."""
    out = np.full((p.size, k + 1), np.nan + 0j)
    out[:, 0] = p
    q = p.copy()
    alive = np.ones(p.size, dtype=bool)
    for s in range(1, k + 1):
        for g in gidx:
            cm = ctrls[int(g[0])].cmap
            w, dw = cm.T_and_dT(q[g])
            res = fleet_step([ctrls[i] for i in g], q[g], w, dw)
            mag = np.abs(res.u)
            st = res.status
            go = (st != Status.ARRIVED) & (st != Status.ERROR) & (mag > 0) & np.isfinite(mag)
            step = np.where(go, res.u / np.where(go, mag, 1.0) * h, 0j)
            alive[g] &= go
            q[g] = q[g] + step
        out[:, s] = np.where(alive, q, np.nan + 0j)
    return out


def _map_groups(ctrls: Sequence[Controller]) -> list[NDArray[np.intp]]:
    """Robots grouped by their controller's map (one batched fleet step per map)."""
    groups: dict[int, list[int]] = {}
    for i, c in enumerate(ctrls):  # a law without a map (LineLaw): a group of its own
        groups.setdefault(id(getattr(c, "cmap", c)), []).append(i)
    return [np.array(g, dtype=np.intp) for g in groups.values()]
