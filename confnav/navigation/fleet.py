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

Robots that avoid each other (second half of this module): :func:`pairwise_rows` turns the
neighbours' disks into half-plane rows ``Re(conj(a) u_i) >= b`` on each robot's command,
:func:`project_rows` solves ``min |u - u_nom|^2`` subject to them and a speed cap, and
:func:`side_pass` with :class:`DeadlockMonitor` keeps symmetric encounters from freezing
(docs/NAVIGATION.md, "Fleets").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from confnav.navigation import defaults
from confnav.navigation.control import SLOW_FLOOR, Controller, ControlOutput, Status, speed_law
from confnav.navigation.navfn import value_and_gradient_stacked
from confnav.types import CArray, FArray

__all__ = [
    "DeadlockMonitor",
    "Rows",
    "deadlock_step",
    "fleet_step",
    "goal_yielders",
    "pairwise_rows",
    "project_rows",
    "project_with_walls",
    "side_pass",
    "swept_min_distance",
    "yield_way",
]


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


# ------------------------------------------------------------------------------------------
# Robots that avoid each other: pairwise rows, their projection, side passing.
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rows:
    """Half-plane rows on the commands of N robots: ``Re(conj(a[i, k]) u_i) >= b[i, k]``.

    ``a`` are unit vectors (complex, pointing from the neighbour to the robot), ``b`` in m/s;
    padding rows have ``a = 0``, ``b = 0`` (always met).  ``who[i, k]`` names the neighbour:
    ``j < N`` robot j of the batch, ``N + m`` the m-th other disk, -1 padding; ``gap`` is the
    surface gap (m) between the two disks (``inf`` on padding).  This is the row format the
    safety layer's projection takes (walls add rows of the same kind).
    """

    a: CArray
    b: FArray
    who: NDArray[np.intp]
    gap: FArray

    @property
    def count(self) -> NDArray[np.intp]:
        """Rows per robot."""
        return np.asarray((self.who >= 0).sum(axis=1), dtype=np.intp)

    @staticmethod
    def empty(n: int) -> Rows:
        return Rows(
            a=np.zeros((n, 0), dtype=np.complex128),
            b=np.zeros((n, 0)),
            who=np.zeros((n, 0), dtype=np.intp),
            gap=np.zeros((n, 0)),
        )


def _as_c(x: ArrayLike | None, n: int, fill: complex = 0j) -> CArray:
    if x is None:
        return np.full(n, fill, dtype=np.complex128)
    return np.broadcast_to(np.asarray(x, dtype=np.complex128).reshape(-1), (n,)).copy()


def _as_f(x: ArrayLike | None, n: int, fill: float = 0.0) -> FArray:
    if x is None:
        return np.full(n, fill, dtype=np.float64)
    return np.broadcast_to(np.asarray(x, dtype=np.float64).reshape(-1), (n,)).copy()


def pairwise_rows(
    z: ArrayLike,
    radius: ArrayLike,
    v_max: ArrayLike,
    *,
    others: ArrayLike | None = None,
    others_radius: ArrayLike | None = None,
    others_velocity: ArrayLike | None = None,
    others_cooperative: ArrayLike | None = None,
    others_mover: ArrayLike | None = None,
    hold_time: float = defaults.HOLD_TIME,
    fraction: float = defaults.HOLD_FRACTION,
    active: ArrayLike | None = None,
    horizon: float = 0.0,
) -> Rows:
    """Rows keeping the disks of N controlled robots off each other and off other disks.

    Robot i at ``z[i]`` (its disk's centre: a unicycle's look-ahead point with radius ``r +
    d``) with radius ``radius[i]`` and speed limit ``v_max[i]``; ``others`` are disks not
    controlled here (robots of another controller, real or replayed ones, movers) with their
    velocity (m/s; 0 if unknown) and whether they run this same filter (``cooperative``).
    ``active`` (default all): robots that take rows; the others are still obstacles.
    ``horizon`` (s): a non-cooperative disk with velocity ``v_j`` counts as the capsule it
    sweeps over the next ``horizon`` seconds (segment ``z_j .. z_j + v_j horizon`` widened by
    its radius): a robot then keeps out of a mover's path ahead of it and leaves it sideways,
    instead of only backing away from a person who walks faster than the robot can drive.
    The capsule is convex and translates with ``v_j``, so the argument below holds with the
    normal at its nearest point, and it contains the disk.

    For a pair at distance ``D = |z_i - z_j|``, unit normal ``n = (z_i - z_j) / D`` and gap
    ``h = D - r_i - r_j`` the barrier is ``h`` itself (the distance form of Wang, Ames,
    Egerstedt, "Safety barrier certificates for collisions-free multirobot systems", IEEE
    T-RO 33(3) 2017, sec. IV), with rate ``alpha = fraction / hold_time``:

    * both controlled (or ``cooperative``), reciprocal, each takes half (ibid., eq. (13)):
      ``Re(conj(n) u_i) >= -alpha h / 2``;
    * the other is not controlled and moves with ``v_j``: full responsibility,
      ``Re(conj(n) u_i) >= -alpha h + Re(conj(n) v_j)``.

    Held commands.  Velocities constant over ``t <= hold_time`` give ``|d(t)| >= Re(conj(n)
    d(t)) = D + t Re(conj(n)(u_i - u_j))`` (Cauchy-Schwarz), and the rows of the pair add up
    to ``Re(conj(n)(u_i - u_j)) >= -alpha h``: so ``h(t) >= (1 - fraction) h(0) > 0`` for
    every ``t`` in the hold.  This is the pairwise twin of the wall hold cap and needs no
    separate speed cap; it holds exactly for commands held at most ``hold_time`` that start
    together and for neighbours that keep their velocity (movers) over the hold.

    A robot without a radius is a point, not a body: pairs of robots get rows only when both
    radii are positive (a point robot drives as before the fleet filter, and a disk robot
    does not make room for points); ``others_mover`` marks the other disks that are movers,
    which every robot avoids, a point robot included.

    A row can bind only if ``b > -v_max[i]`` (``|u_i| <= v_max`` meets it otherwise), i.e. for
    ``h < 2 v_max / alpha`` (controlled) or ``h < (v_max + |v_j|) / alpha``: neighbours are
    searched within that reach (``scipy.spatial.cKDTree``), farther ones give no rows, so
    leaving them out is exact.
    """
    z = np.asarray(z, dtype=np.complex128).reshape(-1)
    n = z.size
    r = _as_f(radius, n)
    vm = _as_f(v_max, n)
    act = np.ones(n, dtype=bool) if active is None else _as_f(active, n).astype(bool)
    if not (hold_time > 0 and 0 < fraction <= 1):
        raise ValueError(f"hold_time > 0 and 0 < fraction <= 1 needed, got {hold_time}, {fraction}")
    alpha = fraction / hold_time
    oz = np.zeros(0, dtype=np.complex128) if others is None else np.asarray(others, np.complex128)
    oz = oz.reshape(-1)
    m = oz.size
    orad, ovel = _as_f(others_radius, m), _as_c(others_velocity, m)
    ocoop = _as_f(others_cooperative, m).astype(bool)
    omover = _as_f(others_mover, m).astype(bool)
    if n == 0:
        return Rows.empty(0)
    pts = np.column_stack([z.real, z.imag])
    vtop = float(vm.max(initial=0.0))
    ii: list[NDArray[np.intp]] = []
    jj: list[NDArray[np.intp]] = []
    if n > 1:
        reach = 2 * float(r.max()) + 2 * vtop / alpha
        pr = cKDTree(pts).query_pairs(reach, output_type="ndarray")
        if pr.size:
            ii += [pr[:, 0], pr[:, 1]]
            jj += [pr[:, 1], pr[:, 0]]
    if m:
        fast = max(vtop, float(np.abs(ovel).max()))  # cooperative rows bind up to 2 v_max
        reach = float(r.max()) + float(orad.max()) + (vtop + fast) / alpha
        reach += float(np.abs(ovel).max()) * horizon
        sm = cKDTree(pts).sparse_distance_matrix(
            cKDTree(np.column_stack([oz.real, oz.imag])), reach, output_type="ndarray"
        )
        if sm.size:
            ii.append(sm["i"].astype(np.intp))
            jj.append(sm["j"].astype(np.intp) + n)
    if not ii:
        return Rows.empty(n)
    i = np.concatenate(ii)
    j = np.concatenate(jj)
    keep = act[i]
    i, j = i[keep], j[keep]
    allz = np.concatenate([z, oz])
    allr = np.concatenate([r, orad])
    allv = np.concatenate([np.zeros(n, np.complex128), ovel])
    coop = np.concatenate([np.ones(n, bool), ocoop])
    sweep = np.where(coop[j], 0j, allv[j] * horizon)  # capsule axis (0: a disk)
    ss = np.abs(sweep) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        s_near = np.clip(np.real(np.conj(sweep) * (z[i] - allz[j])) / ss, 0.0, 1.0)
    near = allz[j] + np.where(ss > 0, s_near, 0.0) * sweep
    d = z[i] - near
    dist = np.abs(d)
    # on a capsule's axis (in a mover's way): leave to the right of its motion; coincident
    # centres of two disks: an arbitrary unit normal
    sw = np.abs(sweep)
    side = np.where(sw > 0, -1j * sweep / np.where(sw > 0, sw, 1.0), 1.0 + 0j)
    nrm = np.where(dist > 0, d / np.where(dist > 0, dist, 1.0), side)
    gap = dist - r[i] - allr[j]
    b = np.where(coop[j], -0.5 * alpha * gap, -alpha * gap + np.real(np.conj(nrm) * allv[j]))
    mover = np.concatenate([np.zeros(n, bool), omover])
    bodies = np.where(mover[j], r[i] + allr[j] > 0, (r[i] > 0) & (allr[j] > 0))
    bind = (b > -vm[i]) & bodies
    i, j, nrm, b, gap = i[bind], j[bind], nrm[bind], b[bind], gap[bind]
    if i.size == 0:
        return Rows.empty(n)
    order = np.lexsort((-b, i))  # by robot, the tightest row first
    i, j, nrm, b, gap = i[order], j[order], nrm[order], b[order], gap[order]
    cnt = np.bincount(i, minlength=n)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    col = np.arange(i.size) - start[i]
    k = int(cnt.max())
    a_out = np.zeros((n, k), dtype=np.complex128)
    b_out = np.zeros((n, k))
    w_out = np.full((n, k), -1, dtype=np.intp)
    g_out = np.full((n, k), np.inf)
    a_out[i, col], b_out[i, col], w_out[i, col], g_out[i, col] = nrm, b, j, gap
    return Rows(a=a_out, b=b_out, who=w_out, gap=g_out)


def project_rows(
    u_nom: ArrayLike, a: ArrayLike, b: ArrayLike, cap: ArrayLike
) -> tuple[CArray, NDArray[np.bool_]]:
    """``argmin |u - u_nom|^2`` s.t. ``Re(conj(a_k) u) >= b_k`` and ``|u| <= cap``, per robot.

    Exact for this 2-D convex QP by enumeration of its possible active sets (an optimum of a
    strictly convex QP in the plane has at most two active constraints: Boyd and
    Vandenberghe, *Convex Optimization*, 2004, sec. 5.5.3, KKT): ``u_nom`` (clipped to the
    cap), its projection on each line, each pair of lines' intersection, each line's two
    points on the circle ``|u| = cap``; the feasible candidate nearest ``u_nom`` wins.
    Vectorized over robots; ``a``, ``b`` of shape (N, K).  Returns ``(u, feasible)``; where
    the rows and the cap leave no command, ``u`` is the candidate of least largest violation
    (``feasible`` False) within the cap.
    """
    un = np.asarray(u_nom, dtype=np.complex128).reshape(-1)
    n = un.size
    A = np.asarray(a, dtype=np.complex128).reshape(n, -1)
    B = np.asarray(b, dtype=np.float64).reshape(n, -1)
    cp = _as_f(cap, n)
    k = A.shape[1]
    mag = np.abs(un)
    c0 = np.where(mag > cp, un * (cp / np.where(mag > 0, mag, 1.0)), un)
    cands = [c0[:, None], np.zeros((n, 1), np.complex128)]
    if k:
        a2 = np.abs(A) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            cands.append(un[:, None] + (B - np.real(np.conj(A) * un[:, None])) / a2 * A)
            an = np.abs(A)
            ah = A / an
            beta = B / an
            s = np.sqrt(cp[:, None] ** 2 - beta**2)
            cands += [ah * (beta + 1j * s), ah * (beta - 1j * s)]
        if k > 1:
            p, q = np.triu_indices(k, 1)
            ar, ai = A.real, A.imag
            det = ar[:, p] * ai[:, q] - ai[:, p] * ar[:, q]
            with np.errstate(divide="ignore", invalid="ignore"):
                x = (B[:, p] * ai[:, q] - ai[:, p] * B[:, q]) / det
                y = (ar[:, p] * B[:, q] - B[:, p] * ar[:, q]) / det
            cands.append(x + 1j * y)
    C = np.concatenate(cands, axis=1)
    scale = np.maximum(np.maximum(cp, mag), 1e-300)[:, None]
    tol = 1e-9 * scale
    finite = np.isfinite(C)
    Cf = np.where(finite, C, 0j)
    viol = np.maximum(np.abs(Cf) - cp[:, None], 0.0)
    if k:
        slack = np.real(np.conj(A)[:, None, :] * Cf[:, :, None]) - B[:, None, :]
        viol = np.maximum(viol, np.max(np.maximum(-slack, 0.0), axis=2))
    viol = np.where(finite, viol, np.inf)
    feas = viol <= tol
    cost = np.where(feas, np.abs(Cf - un[:, None]) ** 2, np.inf)
    best = np.argmin(cost, axis=1)
    ok = np.isfinite(cost[np.arange(n), best])
    # no feasible command: the candidate (scaled into the cap) of least largest row violation,
    # among them each row's own best, cap times its unit normal
    m = np.abs(Cf)
    Cc = np.where(m > cp[:, None], Cf * (cp[:, None] / np.where(m > 0, m, 1.0)), Cf)
    if k:
        an = np.abs(A)
        Cc = np.concatenate([Cc, cp[:, None] * A / np.where(an > 0, an, 1.0)], axis=1)
        finite = np.concatenate([finite, an > 0], axis=1)
    rv = np.zeros(Cc.shape)
    if k:
        sl = np.real(np.conj(A)[:, None, :] * Cc[:, :, None]) - B[:, None, :]
        rv = np.max(np.maximum(-sl, 0.0), axis=2)
    least = np.argmin(np.where(finite, rv, np.inf), axis=1)
    rows_ = np.arange(n)
    return np.where(ok, Cf[rows_, best], Cc[rows_, least]), ok


def project_with_walls(
    u_nom: ArrayLike,
    z: ArrayLike,
    rows: Rows,
    cap: ArrayLike,
    walls: Sequence[object | None],
) -> tuple[CArray, NDArray[np.bool_]]:
    """The pairwise rows and each robot's wall rows in one projection.

    ``walls[i]``: robot i's wall filter (a :class:`confnav.navigation.safety.SafetyFilter`
    on the workspace its point ``z[i]`` navigates in, e.g. ``Controller.safety``; robots
    sharing one are projected together), or None (pairwise rows and ``cap`` only:
    :func:`project_rows`).  The filter adds its wall rows and its held-command cap and solves
    the joint QP (its ``extra_normals``/``extra_bounds``); where that has no solution (robots
    pressing a robot against a wall) the walls come first: the robot gets
    :func:`project_rows`' least-violation command on the pairwise rows and cap, filtered by
    its walls alone (a robot inside the free space can always stop, so that filter has a
    solution; the other robot's own row keeps the pair apart while this one does not close
    in). A robot outside the free space keeps the least-violation command (it re-enters:
    :func:`confnav.navigation.messages.reenter`). Returns ``(u, feasible)``; ``feasible`` is
    False where the joint QP had no solution.
    """
    un = np.asarray(u_nom, dtype=np.complex128).reshape(-1)
    zz = np.asarray(z, dtype=np.complex128).reshape(-1)
    cp = _as_f(cap, un.size)
    u, ok = project_rows(un, rows.a, rows.b, cp)
    groups: dict[int, tuple[object, list[int]]] = {}
    for i, f in enumerate(walls):
        if f is not None:
            groups.setdefault(id(f), (f, []))[1].append(i)
    for f, idx in groups.values():
        m = np.array(idx, dtype=np.intp)
        pr = f(zz[m], un[m], cap=cp[m], extra_normals=rows.a[m], extra_bounds=rows.b[m])  # type: ignore[operator]
        good = ~np.asarray(pr.infeasible, dtype=bool)
        u[m[good]] = np.asarray(pr.u)[good]
        ok[m] = good
        bad = m[~good]
        if bad.size:  # walls first: a wall never moves, the other robot filters too
            pw = f(zz[bad], u[bad], cap=cp[bad])  # type: ignore[operator]
            inside = ~np.asarray(pw.infeasible, dtype=bool)
            u[bad[inside]] = np.asarray(pw.u)[inside]
    return u, ok


def side_pass(
    u_nom: ArrayLike,
    rows: Rows,
    *,
    blocked: ArrayLike | None = None,
    pass_gap: float = 1.0,
    angle: float = np.pi / 4,
    blocked_angle: float = np.pi / 2,
    clearance: ArrayLike | None = None,
    wall_band: tuple[float, float] = (0.1, 0.25),
) -> CArray:
    """The nominal commands turned to the right near a neighbour ahead: the side-passing rule.

    Every robot applies the same rule (traffic keeps right): its command is rotated clockwise
    by ``angle * e`` with ``e = max_k clip(1 - gap_k / pass_gap, 0, 1) * max(0, cos)`` over the
    neighbours of its rows (``cos`` the cosine between the command and the direction to the
    neighbour), and by ``blocked_angle`` when :class:`DeadlockMonitor` says it is blocked
    (counter-clockwise instead when its nearest neighbour is clearly on its right, the sine
    of its bearing below -0.3: a robot stuck behind another that hugs the right-hand wall
    goes round it on the free side).
    Two robots meeting head-on both turn right and pass each other on their left (the
    symmetry that freezes a pure safety filter is broken the same way for both; Wang, Ames,
    Egerstedt, IEEE T-RO 2017, sec. VI, use a perturbation for the same purpose).  Only the
    nominal command turns: the rows still bound the filtered one, so safety is unaffected.
    ``clearance`` (optional, m): each robot's body clearance to the walls; the turn then
    fades to 0 from ``wall_band[1]`` down to ``wall_band[0]`` (the wall hold cap ``|u| <=
    fraction c / hold_time`` all but freezes a robot turned into a wall, and the navigation
    law's own command keeps it off the walls).
    """
    un = np.asarray(u_nom, dtype=np.complex128).reshape(-1)
    n = un.size
    side = np.ones(n)  # +1: a blocked robot turns right, -1: left
    if rows.a.shape[1] == 0:
        e = np.zeros(n)
    else:
        mag = np.abs(un)
        dirn = np.where(mag > 0, un / np.where(mag > 0, mag, 1.0), 0j)
        ahead = np.maximum(np.real(np.conj(-rows.a) * dirn[:, None]), 0.0)
        near = np.clip(1.0 - rows.gap / pass_gap, 0.0, 1.0)
        e = np.max(np.where(rows.who >= 0, near * ahead, 0.0), axis=1)
        # the nearest neighbour clearly to the right (sine of its bearing < -0.3): pass it on
        # its left (a pair meeting this way both see the other on their right: consistent)
        k = np.argmin(np.where(rows.who >= 0, rows.gap, np.inf), axis=1)
        bearing = np.imag(np.conj(dirn) * -rows.a[np.arange(n), k])
        side = np.where((rows.who[np.arange(n), k] >= 0) & (bearing < -0.3), -1.0, 1.0)
    theta = angle * e
    if blocked is not None:
        theta = np.where(np.asarray(blocked, dtype=bool).reshape(-1), side * blocked_angle, theta)
    if clearance is not None:
        lo, hi = wall_band
        theta = theta * np.clip((_as_f(clearance, n) - lo) / (hi - lo), 0.0, 1.0)
    return np.asarray(un * np.exp(-1j * theta), dtype=np.complex128)


def yield_way(
    u_nom: ArrayLike,
    z: ArrayLike,
    radius: ArrayLike,
    idle: ArrayLike,
    rows: Rows,
    speed: ArrayLike,
    *,
    clearance: ArrayLike | None = None,
    yield_gap: float = 0.6,
    angle: float = np.pi / 4,
    wall_band: tuple[float, float] = (0.1, 0.25),
    others: ArrayLike | None = None,
    others_radius: ArrayLike | None = None,
    others_heading: ArrayLike | None = None,
) -> tuple[CArray, NDArray[np.bool_]]:
    """Idle robots step out of the way of a moving robot whose path they block: the yield rule.

    An idle robot i (done with its goals, parked at the last one) *blocks* a robot j of its
    rows that is not idle when j is within ``yield_gap`` m (surface gap), i lies ahead of j
    (``s = Re(conj(e_j)(z_i - z_j)) > 0`` with ``e_j`` the direction of j's nominal command)
    and within j's swept width (``|l| < r_i + r_j``, ``l = Im(conj(e_j)(z_i - z_j))``).  Its
    nominal command becomes ``speed_i e_j exp(+-1j angle) / cos(angle)``: forward along j's
    motion and to j's left (the side j's keep-right rule of :func:`side_pass` leaves free)
    unless i is clearly to j's right (``l < -(r_i + r_j) / 2``), then to the right.  The
    factor ``1 / cos(angle)`` lets the projection keep the full forward speed where a wall
    stops the sideways part (an aisle); ``|u| <= cap`` still bounds it.

    ``clearance`` (optional, m): each robot's body clearance to the walls; the sideways turn
    then fades from ``angle`` at ``wall_band[1]`` to 0 at ``wall_band[0]`` (the wall hold cap
    ``|u| <= fraction c / hold_time`` freezes a robot that hugs a wall, so a yielding robot
    keeps ``wall_band[0]`` off it and goes on forward, e.g. out of a door, instead of pressing
    sideways).  Among several blocked robots the nearest one decides.

    Only nominal commands change (the filtered command still obeys every row and wall), and
    a robot with no neighbour never yields, so a lone robot drives as without the rule.
    ``others``, ``others_radius``, ``others_heading``: the other disks of the rows (index
    ``N + m`` in ``rows.who``) with the direction they are heading in (e.g. the last nominal
    command of a robot served in another pose block; 0: none, e.g. a mover): an idle robot
    yields to them as to the robots of the batch.
    Returns ``(u_nom', yielding)``.  This is a rule chosen on the warehouse bench
    (docs/NAVIGATION.md, "Fleets"), not a derived one; the literature's counterpart is the
    perturbations that leave symmetric deadlocks in Wang, Ames, Egerstedt, "Safety barrier
    certificates for collisions-free multirobot systems", IEEE T-RO 33(3) 2017, sec. VI.
    """
    un = np.asarray(u_nom, dtype=np.complex128).reshape(-1)
    n = un.size
    zz = np.asarray(z, dtype=np.complex128).reshape(-1)
    r = _as_f(radius, n)
    idl = _as_f(idle, n).astype(bool)
    sp = _as_f(speed, n)
    out = un.copy()
    if rows.a.shape[1] == 0 or not idl.any():
        return out, np.zeros(n, dtype=bool)
    who = rows.who
    oz = np.zeros(0, np.complex128) if others is None else np.asarray(others, np.complex128)
    oz = oz.reshape(-1)
    n_all = n + oz.size
    z_all = np.concatenate([zz, oz])
    r_all = np.concatenate([r, _as_f(others_radius, oz.size)])
    u_all = np.concatenate([un, _as_c(others_heading, oz.size)])
    i_all = np.concatenate([idl, np.zeros(oz.size, dtype=bool)])
    j = np.where((who >= 0) & (who < n_all), who, 0)
    valid = (who >= 0) & (who < n_all) & idl[:, None] & ~i_all[j] & (rows.gap < yield_gap)
    mag = np.abs(u_all[j])
    e = np.where(mag > 0, u_all[j] / np.where(mag > 0, mag, 1.0), 0j)
    rel = np.conj(e) * (zz[:, None] - z_all[j])
    s, lat = rel.real, rel.imag
    width = r[:, None] + r_all[j]
    block = valid & (mag > 0) & (s > 0) & (np.abs(lat) < width)
    gap = np.where(block, rows.gap, np.inf)
    k = np.argmin(gap, axis=1)
    yielding = np.isfinite(gap[np.arange(n), k])
    if not yielding.any():
        return out, yielding
    idx = np.flatnonzero(yielding)
    kk = k[idx]
    ek = e[idx, kk]
    sgn = np.where(lat[idx, kk] < -0.5 * width[idx, kk], -1.0, 1.0)
    turn = np.full(idx.size, angle)
    if clearance is not None:
        lo, hi = wall_band
        turn = angle * np.clip((_as_f(clearance, n)[idx] - lo) / (hi - lo), 0.0, 1.0)
    out[idx] = sp[idx] * ek * np.exp(1j * sgn * turn) / np.cos(turn)
    return out, yielding


def goal_yielders(
    z: ArrayLike, goal: ArrayLike, radius: ArrayLike, rows: Rows, active: ArrayLike
) -> NDArray[np.bool_]:
    """Robots that sit on a neighbour's goal and should make room: the goal-conflict rule.

    Robot i yields (is treated as idle by :func:`yield_way`) when a robot j of its rows, both
    ``active`` (moving, not done), has its goal within ``radius[i] + radius[j]`` of ``z[i]``
    (j cannot arrive while i stays) and j is nearer its goal than i is to its own (ties: the
    lower index is nearer).  Of two robots whose goals lie within each other's disks, exactly
    the one farther from its goal yields, so the other arrives (and, with goals issued on
    arrival, leaves).  A rule chosen on the warehouse bench (docs/NAVIGATION.md, "Fleets"),
    not derived; only nominal commands change.
    """
    zz = np.asarray(z, dtype=np.complex128).reshape(-1)
    n = zz.size
    gl = _as_c(goal, n)
    r = _as_f(radius, n)
    act = _as_f(active, n).astype(bool)
    if rows.a.shape[1] == 0:
        return np.zeros(n, dtype=bool)
    who = rows.who
    own = (who >= 0) & (who < n)
    j = np.where(own, who, 0)
    dist = np.abs(zz - gl)
    on_goal = np.abs(zz[:, None] - gl[j]) < r[:, None] + r[j]
    nearer = (dist[j] < dist[:, None]) | ((dist[j] == dist[:, None]) & (j < np.arange(n)[:, None]))
    hit = own & act[:, None] & act[j] & on_goal & nearer
    return np.asarray(hit.any(axis=1))


class DeadlockMonitor:
    """Detects robots held up by other robots: no progress toward the goal for ``window`` s
    while a robot row is engaged (within ``engage_gap`` m).

    Progress is a decrease of the distance to the goal by ``progress`` m below the best so
    far, or by a quarter of it within ``4 progress`` m of the goal (where the speed law slows
    down in proportion to the distance, a robot closing in is not blocked); while no robot
    row is engaged the clock restarts (a stall without neighbours is the navigation law's
    business, not a deadlock).  A blocked robot stays blocked for
    ``release`` s after it is detected (a hysteresis: the side step must take it somewhere).
    """

    def __init__(
        self,
        n: int,
        *,
        window: float = 1.0,
        progress: float = 0.1,
        engage_gap: float = 0.5,
        release: float = 1.0,
    ) -> None:
        self.window = float(window)
        self.progress = float(progress)
        self.engage_gap = float(engage_gap)
        self.release = float(release)
        self.best = np.full(n, np.inf)
        self.t_best = np.zeros(n)
        self.until = np.full(n, -np.inf)
        self.detections = 0

    def update(self, t: float, dist_to_goal: ArrayLike, rows: Rows) -> NDArray[np.bool_]:
        """The robots blocked at time ``t`` (distances to the goal now, the rows in use)."""
        self.best, self.t_best, self.until, new = deadlock_step(
            self.best,
            self.t_best,
            self.until,
            t,
            dist_to_goal,
            rows,
            window=self.window,
            progress=self.progress,
            engage_gap=self.engage_gap,
            release=self.release,
        )
        self.detections += int(new.sum())
        return np.asarray(self.until >= t)


def deadlock_step(
    best: ArrayLike,
    t_best: ArrayLike,
    until: ArrayLike,
    t: float,
    dist_to_goal: ArrayLike,
    rows: Rows,
    *,
    window: float = 1.0,
    progress: float = 0.1,
    engage_gap: float = 0.5,
    release: float = 1.0,
) -> tuple[FArray, FArray, FArray, NDArray[np.bool_]]:
    """:class:`DeadlockMonitor`'s rule on explicit state (the services keep it per robot id):
    each robot's best distance to its goal, the time of it and the time it stays blocked
    until; returns the new state and the robots newly detected as blocked at time ``t``."""
    d = np.asarray(dist_to_goal, dtype=np.float64).reshape(-1)
    bst = np.asarray(best, dtype=np.float64).reshape(-1)
    tb = np.asarray(t_best, dtype=np.float64).reshape(-1)
    unt = np.asarray(until, dtype=np.float64).reshape(-1)
    engaged = np.any((rows.who >= 0) & (rows.gap < engage_gap), axis=1)
    # near the goal the law slows down (|u| ~ gain d): a quarter of the way left counts
    better = d < bst - np.minimum(progress, 0.25 * bst)
    reset = better | ~engaged
    bst = np.where(reset, d, bst)
    tb = np.where(reset, t, tb)
    new = engaged & (t - tb > window) & (unt < t)
    unt = np.where(new, t + release, unt)
    tb = np.where(new, t, tb)
    return bst, tb, unt, np.asarray(new)


def swept_min_distance(
    a0: ArrayLike, a1: ArrayLike, b0: ArrayLike, b1: ArrayLike
) -> tuple[FArray, FArray]:
    """Smallest distance of two points moving linearly ``a0 -> a1`` and ``b0 -> b1`` over one
    step, and the fraction of the step where it occurs (exact: the relative position ``d(s) =
    d0 + s (d1 - d0)`` is closest to 0 at ``s* = clip(-Re(conj(d0) e) / |e|^2, 0, 1)``, ``e =
    d1 - d0``, the minimum of a convex quadratic on [0, 1])."""
    d0 = np.asarray(a0, np.complex128) - np.asarray(b0, np.complex128)
    e = (np.asarray(a1, np.complex128) - np.asarray(b1, np.complex128)) - d0
    ee = np.abs(e) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(ee > 0, np.clip(-np.real(np.conj(d0) * e) / np.where(ee > 0, ee, 1), 0, 1), 0)
    return np.asarray(np.abs(d0 + s * e), dtype=np.float64), np.asarray(s, dtype=np.float64)
