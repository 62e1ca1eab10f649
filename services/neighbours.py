"""Neighbours of a controller's robots: every robot's latest pose and every mover, and the
fleet filter applied to a whole pose block at once.

The controller service serves some robots (its shard); the others on the bus are obstacles
too: robots of another controller shard, real robots, replayed ones.  :class:`Neighbours`
subscribes to every robot's pose (``{prefix}/robot/*/pose``), goal and spawn request (for
their disks: ``robot_radius``, a unicycle's look-ahead) and to ``{prefix}/ws/*/movers``
(:class:`~confnav.schemas.Movers`), and :meth:`Neighbours.filter_block` keeps the commands of
one pose block off each other (reciprocal rows), off every other robot (full responsibility,
with its velocity estimated from its last two poses) and off the movers (with their
velocities), with the rules of the fleet simulation, shared from
:mod:`confnav.navigation.fleet` (docs/NAVIGATION.md, "Fleets"): side passing with its wall
fade, the deadlock monitor (``deadlock_step``, its state kept per robot id), the yield rule
(``yield_way``: a robot that arrived at its goal, until it gets a new one, steps out of a
moving robot's way, also of a robot of another pose block of this controller, whose last
nominal command is kept), optionally the goal-conflict rule (``goal_yielders``), and the
contact margin of the rows.  The gates' mutex (:mod:`confnav.navigation.traffic`) is not
applied here (it is off in the fleet simulation too: measured worse on the warehouse).

A robot with no neighbour within reach of a row keeps the control law's command bitwise, so
a robot alone drives exactly as without this module; so does a robot without a radius (a
point), except near a mover.  A robot whose floor is unknown (no goal
or spawn request seen) counts as a neighbour on every floor, and a robot whose body is unknown
as a disk of the largest radius known on the floor (both conservative).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Container
from dataclasses import dataclass
from typing import Any

import numpy as np
from confnav.schemas import DecodeError, Goal, Movers, Pose, SpawnRequest, decode
from confnav.services.bus import Bus, Closeable
from confnav.services.keys import KeyError_, Keys

from confnav.navigation import defaults
from confnav.navigation.control import Status
from confnav.navigation.fleet import (
    Rows,
    deadlock_step,
    goal_yielders,
    pairwise_rows,
    project_with_walls,
    side_pass,
    yield_way,
)
from confnav.navigation.unicycle import twist_from_velocity

log = logging.getLogger(__name__)

#: A pose older than this (s, receive time) is forgotten: the robot is gone or stopped sending.
POSE_TTL = 2.0
#: Movers older than this (s after their stamp) are forgotten.
MOVERS_TTL = 1.0
#: Movers count as the capsule they sweep in this many seconds (fleet.pairwise_rows).
MOVER_HORIZON = 2.0


@dataclass
class _Seen:
    z: complex
    theta: float
    t: float  # monotonic receive time
    stamp_ns: int
    v: complex = 0j  # estimated from the last two poses (m/s)


@dataclass
class _Body:
    ws: str | None = None  # floor (the base workspace id), None: unknown
    radius: float = 0.0


def _floor(ws_id: str) -> str:
    return ws_id.split("~", 1)[0]


class Neighbours:
    """Tracks the robots and movers on the bus; filters a controller's pose blocks."""

    def __init__(
        self,
        keys: Keys,
        *,
        default_radius: float = 0.0,
        hold_time: float = defaults.HOLD_TIME,
        fraction: float = defaults.HOLD_FRACTION,
        contact_margin: float = 1e-3,
        side_passing: bool = True,
        yielding: bool = True,
        goal_yield: bool = False,
        window: float = 1.0,
        progress: float = 0.1,
    ) -> None:
        self.keys = keys
        self.default_radius = float(default_radius)
        self.hold_time = float(hold_time)
        self.fraction = float(fraction)
        self.contact_margin = float(contact_margin)
        self.side_passing = side_passing
        self.yielding = yielding
        self.goal_yield = goal_yield
        self.window = float(window)
        self.progress = float(progress)
        self._lock = threading.Lock()
        # every robot's latest pose in one slot of these arrays (the filter of each pose block
        # selects its neighbours with vectorized masks, no Python loop over the fleet)
        self._slot: dict[str, int] = {}
        self._rids: list[str] = []
        self._z = np.zeros(0, dtype=np.complex128)
        self._th = np.zeros(0)
        self._t = np.zeros(0)  # monotonic receive time; -inf: free slot
        self._stamp = np.zeros(0, dtype=np.int64)
        self._v = np.zeros(0, dtype=np.complex128)  # estimated from the last two poses (m/s)
        self._rad = np.zeros(0)  # body radius, NaN: unknown (_select: the largest known)
        self._fl = np.zeros(0, dtype=np.int64)  # floor number (_floors), -1: unknown
        self._un = np.zeros(0, dtype=np.complex128)  # a served robot's last nominal command
        self._floors: dict[str, int] = {}
        self._body: dict[str, _Body] = {}
        self._movers: dict[str, tuple[Movers, float]] = {}
        # deadlock monitor per robot: best distance to goal, its time, blocked until
        self._dl: dict[str, tuple[float, float, float]] = {}
        # robot id -> (first, last) time the deadlock monitor held it blocked, in one spell
        self._stuck: dict[str, tuple[float, float]] = {}
        # robot id -> the goal it arrived at (it counts as idle, and yields, while it keeps it)
        self._done: dict[str, Goal] = {}
        self.counters: dict[str, int] = {}
        #: robot id -> whether this controller serves it (set by :func:`attach`)
        self.served: Callable[[str], bool] | None = None
        #: the same for many robots at once (faster; set by :func:`attach`)
        self.served_many: Callable[[list[str]], list[bool]] | None = None
        #: True: no pose subscription of its own; the host calls :meth:`note_pose` with every
        #: pose it decodes (a controller that takes every robot's poses anyway: each pose is
        #: then received and decoded once, not twice -- docs/SERVICES.md, "Scale")
        self.fed = False

    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    # inputs ------------------------------------------------------------------------------
    def subscribe(self, bus: Bus, poses: bool = True) -> list[Closeable]:
        """Goals, spawn requests, movers and (``poses``) every robot's poses."""
        k = self.keys
        self.fed = not poses
        return [
            *([bus.subscribe_latest(k.any_robot("pose"), self._on_poses)] if poses else []),
            bus.subscribe(k.any_robot("goal"), self._on_goal),
            bus.subscribe(k.any_sim("spawn"), self._on_spawn),
            bus.subscribe(k.any_ws("movers"), self._on_movers),
        ]

    def _on_poses(self, items: list[tuple[str, bytes]]) -> None:
        now = time.monotonic()
        for key, payload in items:
            try:
                rid = self.keys.parse(key).ident
                pose = decode(Pose, payload)
            except (KeyError_, DecodeError):
                self._count("rejected")
                continue
            self.note_pose(rid, pose, now)

    def note_pose(self, rid: str, pose: Pose, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        z = complex(pose.x, pose.y)
        with self._lock:
            i = self._slot.get(rid)
            if i is None or self._t[i] == -np.inf:
                i = self._new_slot(rid) if i is None else i
                v = 0j
            else:
                old_stamp = int(self._stamp[i])
                if pose.stamp_ns <= old_stamp:
                    return  # replayed or reordered
                dt = (pose.stamp_ns - old_stamp) * 1e-9
                v = (z - complex(self._z[i])) / dt if dt > 1e-3 else complex(self._v[i])
            self._z[i], self._th[i], self._t[i] = z, pose.theta, now
            self._stamp[i], self._v[i] = pose.stamp_ns, v

    def _new_slot(self, rid: str) -> int:
        """A slot for ``rid`` (the arrays doubled when full), its body filled in."""
        i = len(self._rids)
        if i == self._t.size:
            n = max(64, 2 * i)
            for name in ("_z", "_th", "_t", "_stamp", "_v", "_rad", "_fl", "_un"):
                a = getattr(self, name)
                b = np.zeros(n, dtype=a.dtype)
                b[:i] = a
                setattr(self, name, b)
            self._t[i:] = -np.inf
        self._slot[rid] = i
        self._rids.append(rid)
        self._set_body(rid, i)
        return i

    def _set_body(self, rid: str, i: int) -> None:
        b = self._body.get(rid)
        self._rad[i] = np.nan if b is None else b.radius
        self._fl[i] = -1 if b is None or b.ws is None else self._floor_no(b.ws)

    def _floor_no(self, floor: str) -> int:
        n = self._floors.get(floor)
        if n is None:
            n = self._floors[floor] = len(self._floors)
        return n

    def _expire(self, now: float) -> None:
        """Forget poses older than :data:`POSE_TTL`; compact the slots when most are free."""
        self._t[(now - self._t > POSE_TTL)] = -np.inf
        n = len(self._rids)
        free = int(np.count_nonzero(self._t[:n] == -np.inf))
        if n >= 256 and 2 * free > n:
            keep = np.flatnonzero(self._t[:n] > -np.inf)
            for name in ("_z", "_th", "_t", "_stamp", "_v", "_rad", "_fl", "_un"):
                a = getattr(self, name)
                b = np.zeros(a.size, dtype=a.dtype)
                b[: keep.size] = a[keep]
                setattr(self, name, b)
            self._t[keep.size :] = -np.inf
            self._rids = [self._rids[k] for k in keep]
            self._slot = {rid: k for k, rid in enumerate(self._rids)}

    @property
    def _seen(self) -> dict[str, _Seen]:
        """The robots seen within :data:`POSE_TTL` (a copy: inspection and tests)."""
        with self._lock:
            return {
                rid: _Seen(
                    complex(self._z[i]),
                    float(self._th[i]),
                    float(self._t[i]),
                    int(self._stamp[i]),
                    complex(self._v[i]),
                )
                for i, rid in enumerate(self._rids)
                if self._t[i] > -np.inf
            }

    def _on_goal(self, key: str, payload: bytes) -> None:
        try:
            g = decode(Goal, payload)
        except DecodeError:
            return
        with self._lock:  # the body disk around the pose (a unicycle's axle)
            b = self._body.setdefault(g.robot_id, _Body())
            b.ws = _floor(g.ws_id)
            b.radius = max(b.radius, g.robot_radius)
            i = self._slot.get(g.robot_id)
            if i is not None:
                self._set_body(g.robot_id, i)

    def _on_spawn(self, key: str, payload: bytes) -> None:
        try:
            s = decode(SpawnRequest, payload)
        except DecodeError:
            return
        with self._lock:
            b = self._body.setdefault(s.robot_id, _Body())
            b.ws = _floor(s.ws_id)
            b.radius = max(b.radius, s.robot_radius)
            i = self._slot.get(s.robot_id)
            if i is not None:
                self._set_body(s.robot_id, i)

    def _on_movers(self, key: str, payload: bytes) -> None:
        try:
            ws = self.keys.parse(key).ident
            m = decode(Movers, payload)
            if m.ws_id != ws:
                raise DecodeError("invalid_input", "ws id differs from key")
        except (KeyError_, DecodeError):
            self._count("rejected")
            return
        with self._lock:
            old = self._movers.get(_floor(ws))
            if old is None or m.stamp_ns >= old[0].stamp_ns:
                self._movers[_floor(ws)] = (m, time.monotonic())

    # the filter --------------------------------------------------------------------------
    def _others(
        self, floor: str | None, exclude: set[str], now: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Other robots' and the movers on ``floor``: (positions, radii, velocities,
        cooperative, mover); a robot this controller serves (``served``) is cooperative: it
        runs this filter with its own poses."""
        return self._select(floor, exclude, now)[:5]

    def _select(
        self, floor: str | None, exclude: set[str], now: float, at_least: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_others` and each one's heading: a robot this controller serves, its last
        nominal command (the yield rule across pose blocks); another robot, its velocity; a
        mover, none."""
        zs: list[complex] = []
        rs: list[float] = []
        vs: list[complex] = []
        co: list[bool] = []
        mv: list[bool] = []
        wall = time.time_ns()
        with self._lock:
            self._expire(now)
            n = len(self._rids)
            sel = self._t[:n] > -np.inf
            if floor is not None:
                fno = self._floors.get(floor, -2)
                sel &= (self._fl[:n] == -1) | (self._fl[:n] == fno)
            # a robot whose body nobody announced (no Goal, no SpawnRequest: e.g. a
            # simulator's config robot before its goal, or a real robot's bridge without a
            # radius) is taken as large as the largest body known on this floor, the robots
            # being filtered included (``at_least``: their goals' radii), and at least
            # default_radius: as a point it let a robot drive into a standing one (the studio
            # outside check, fleet_studio_auto.json)
            known = self._rad[:n][sel & ~np.isnan(self._rad[:n])]
            unknown_r = max(
                self.default_radius, at_least, float(known.max()) if known.size else 0.0
            )
            for rid in exclude:
                i = self._slot.get(rid)
                if i is not None:
                    sel[i] = False
            idx = np.flatnonzero(sel)
            rids = [self._rids[i] for i in idx]
            if self.served_many is not None:
                mine = np.array(self.served_many(rids), dtype=bool)
            elif self.served is not None:
                mine = np.array([self.served(r) for r in rids], dtype=bool)
            else:
                mine = np.zeros(idx.size, dtype=bool)
            rad = self._rad[idx]
            r_z = self._z[idx]
            r_r = np.where(np.isnan(rad), unknown_r, rad)
            r_v = np.where(mine, 0j, self._v[idx])
            r_h = np.where(mine, self._un[idx], self._v[idx])
            for fl, (m, _) in list(self._movers.items()):
                age = (wall - m.stamp_ns) * 1e-9
                if age > MOVERS_TTL:
                    del self._movers[fl]
                    continue
                if floor is not None and fl != floor:
                    continue
                for d in m.movers:
                    v = complex(*d.velocity)
                    zs.append(complex(*d.position) + v * max(age, 0.0))
                    rs.append(d.radius)
                    vs.append(v)
                    co.append(False)
                    mv.append(True)
        return (
            np.concatenate([r_z, np.array(zs, dtype=np.complex128)]),
            np.concatenate([r_r, np.array(rs, dtype=np.float64)]),
            np.concatenate([r_v, np.array(vs, dtype=np.complex128)]),
            np.concatenate([mine, np.array(co, dtype=bool)]),
            np.concatenate([np.zeros(idx.size, dtype=bool), np.array(mv, dtype=bool)]),
            np.concatenate([r_h, np.zeros(len(zs), dtype=np.complex128)]),
        )

    def filter_block(
        self,
        results: list[Any],
        now: float | None = None,
        coordinated: Container[str] = frozenset(),
        reentering: Container[str] = frozenset(),
    ) -> list[Any]:
        """The controller's results of one pose block, ``[((ctrl, [(robot, pose), ...]),
        (u, codes) or an exception), ...]``, with every robot's command filtered against the
        others (module docstring).  Robots without rows keep their command bitwise.  The
        ``coordinated`` robots (ids; the fleet coordinator plans their way,
        ``services/controller_coord.py``) get the filter without side passing and the yield
        rule, as the fleet simulation with a coordinator. The ``reentering`` robots (ids) steer
        back into their map's free space (confnav/navigation/reentry.py): filtered against the
        others only, at most at their re-entry speed, never yielding nor side passing (their
        wall filter would hold them: it stops a point outside its workspace)."""
        now = time.monotonic() if now is None else now
        entries: list[tuple[int, int, Any, Any, Any]] = []  # (group, k, robot, pose, ctrl)
        for gi, ((ctrl, members), res) in enumerate(results):
            if isinstance(res, BaseException):
                continue
            for k, (r, pose) in enumerate(members):
                if r.goal is not None:
                    entries.append((gi, k, r, pose, ctrl))
        if not entries:
            return results
        by_floor: dict[str, list[int]] = {}
        for i, e in enumerate(entries):
            by_floor.setdefault(_floor(e[2].goal.ws_id), []).append(i)
        out: list[Any] = [
            (
                g,
                res
                if isinstance(res, BaseException)
                else (np.array(res[0], complex), np.array(res[1])),
            )
            for g, res in results
        ]
        own = {e[2].robot_id for e in entries}
        for floor, idx in by_floor.items():
            self._filter_floor(
                floor, [entries[i] for i in idx], out, own, now, coordinated, reentering
            )
        return out

    def _filter_floor(
        self,
        floor: str,
        entries: list[tuple[int, int, Any, Any, Any]],
        out: list[Any],
        own: set[str],
        now: float,
        coordinated: Container[str] = frozenset(),
        reentering: Container[str] = frozenset(),
    ) -> None:
        goals = [e[2].goal for e in entries]
        reent = np.array([e[2].robot_id in reentering for e in entries], dtype=bool)
        local = np.array([e[2].robot_id not in coordinated for e in entries], dtype=bool)
        local &= ~reent
        z = np.array([complex(e[3].x, e[3].y) for e in entries])
        th = np.array([e[3].theta for e in entries])
        body = np.array([getattr(e[4], "frame", "world") == "body" for e in entries])
        d = np.array(
            [
                float(getattr(e[4], "d", g.lookahead)) if b else 0.0
                for e, g, b in zip(entries, goals, body, strict=True)
            ]
        )
        p = z + d * np.exp(1j * th)
        rad = np.array([g.robot_radius for g in goals]) + d
        vmax = np.array([g.v_max for g in goals])
        u_law = np.array([out[e[0]][1][0][e[1]] for e in entries], dtype=complex)
        codes = np.array([int(out[e[0]][1][1][e[1]]) for e in entries])
        # the velocity of the steered point: a unicycle's twist v + i omega moves p by
        # (v + i d omega) e^{i theta} (confnav.navigation.unicycle)
        u_nom = np.where(body, (u_law.real + 1j * d * u_law.imag) * np.exp(1j * th), u_law)
        live = np.isfinite(u_nom) & (codes != Status.ERROR)
        body_max = max((float(g.robot_radius) for g in goals), default=0.0)
        oz, orad, ov, oco, omv, ohead = self._select(floor, own, now, at_least=body_max)
        rows = pairwise_rows(
            p,
            # as the fleet simulation: no round-off contact (points stay points: no rows)
            np.where(rad > 0, rad + 0.5 * self.contact_margin, rad),
            vmax,
            others=oz,
            others_radius=orad,
            others_velocity=ov,
            others_cooperative=oco,
            others_mover=omv,
            hold_time=self.hold_time,
            fraction=self.fraction,
            active=live,
            horizon=MOVER_HORIZON,
        )
        has = (rows.who >= 0).any(axis=1) & live
        arrived = codes == Status.ARRIVED
        u0 = np.where(live & ~arrived, u_nom, 0j)
        with self._lock:  # the heading other pose blocks yield to
            for e, u_i in zip(entries, u0, strict=True):
                k = self._slot.get(e[2].robot_id)
                if k is not None:
                    self._un[k] = u_i
        if not has.any():
            return  # nobody near: the law's commands, bitwise
        # the body's clearance where the robot's law uses one (inf: no wall fade, no cap)
        cb, hold = _body_clearance(entries, has, p)
        # the fleet simulation's rules (confnav.navigation.fleet_sim): a robot parked at its
        # goal (or, with goal_yield, one on a nearer neighbour's goal) steps out of a moving
        # robot's way, also one of another pose block (its last nominal command); side passing
        # with the wall fade; the deadlock monitor (shared code, per robot id here)
        if self.yielding:
            u_y, yl = self._yield_rule(entries, p, rad, rows, vmax, live, arrived, u0, cb, oz,
                                       orad, ohead)  # fmt: skip
            yl &= local  # (re-entering robots are not local)
        if self.side_passing and local.any():
            blocked = self._blocked([e[2].robot_id for e in entries], p, goals, rows, now)
            u0 = np.where(local, side_pass(u0, rows, blocked=blocked, clearance=cb), u0)
        if self.yielding:
            u0 = np.where(yl, u_y, u0)
        # the wall hold cap of the robot's own law
        cap = np.minimum(vmax, defaults.HOLD_FRACTION * np.maximum(cb, 0.0) / hold)
        cap = np.where(reent, np.minimum(vmax, np.abs(u_nom)), cap)
        walls = [
            None if re else getattr(getattr(e[4], "controller", e[4]), "safety", None)
            for e, re in zip(entries, reent.tolist(), strict=True)
        ]
        u, ok = project_with_walls(u0, p, rows, cap, walls)
        self._count("filtered", int(has.sum()))
        self._count("infeasible", int((~ok & has).sum()))
        _write_back(entries, out, u, has, arrived, body, th, d, vmax)

    def _yield_rule(
        self,
        entries: list[tuple[int, int, Any, Any, Any]],
        p: np.ndarray,
        rad: np.ndarray,
        rows: Rows,
        vmax: np.ndarray,
        live: np.ndarray,
        arrived: np.ndarray,
        u0: np.ndarray,
        cb: np.ndarray,
        oz: np.ndarray,
        orad: np.ndarray,
        ohead: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fleet simulation's yield rule (:func:`confnav.navigation.fleet.yield_way`): a
        robot parked at its goal (or, with ``goal_yield``, one on a nearer neighbour's goal)
        steps out of a moving robot's way; the commands and which robots yield."""
        goals = [e[2].goal for e in entries]
        gz = np.array([complex(*g.goal) for g in goals])
        rids = [e[2].robot_id for e in entries]
        for k in np.flatnonzero(arrived).tolist():  # done with this goal until a new one
            self._done[rids[k]] = goals[k]
        done = np.array([self._done.get(r) == g for r, g in zip(rids, goals, strict=True)])
        idle = live & (arrived | done)
        if self.goal_yield:  # off by default, as in the fleet simulation
            idle |= goal_yielders(p, gz, rad, rows, live & ~arrived)
        u_y, yl = yield_way(
            u0,
            p,
            rad,
            idle,
            rows,
            vmax,
            clearance=cb,
            others=oz,
            others_radius=orad,
            others_heading=ohead,
        )
        self._count("yields", int(yl.sum()))
        return u_y, yl

    def _blocked(
        self, rids: list[str], p: np.ndarray, goals: list[Goal], rows: Rows, now: float
    ) -> np.ndarray:
        """:class:`confnav.navigation.fleet.DeadlockMonitor`'s rule, kept per robot id."""
        dist = np.abs(p - np.array([complex(*g.goal) for g in goals]))
        state = np.array([self._dl.get(rid, (np.inf, now, -np.inf)) for rid in rids])
        best, t_best, until, new = deadlock_step(
            state[:, 0],
            state[:, 1],
            state[:, 2],
            now,
            dist,
            rows,
            window=self.window,
            progress=self.progress,
        )
        self._count("deadlocks", int(new.sum()))
        blocked = np.asarray(until >= now)
        for i, rid in enumerate(rids):
            self._dl[rid] = (float(best[i]), float(t_best[i]), float(until[i]))
            self._note_stuck(rid, bool(blocked[i]), now)
        return blocked

    def _note_stuck(self, rid: str, blocked: bool, now: float) -> None:
        """Keep the spell of a robot the deadlock monitor holds blocked again and again: the
        monitor releases a robot after ``release`` s and may block it again ``window`` s
        later, so a spell ends only after twice that long unblocked."""
        first, last = self._stuck.get(rid, (now, -np.inf))
        if blocked:
            gap = 2.0 * (self.window + 1.0)  # 1.0: deadlock_step's release (s)
            self._stuck[rid] = (first if now - last <= gap else now, now)
        elif now - last > 2.0 * (self.window + 1.0):
            self._stuck.pop(rid, None)

    def stuck_note(self, rid: str, now: float, after: float = 5.0) -> str:
        """A status note for a robot the local fleet rules have held blocked by other robots
        for ``after`` s or more (a deadlock they do not resolve, e.g. two robots meeting in
        a single-lane passage), else ''."""
        spell = self._stuck.get(rid)
        if spell is None or spell[1] - spell[0] < after:
            return ""
        return (
            f"blocked by other robots for {spell[1] - spell[0]:.0f} s (local fleet rules: "
            "side passing, yielding; single-lane passages need --fleet-coordinator roadmap)"
        )


def attach(service: Any, **kw: Any) -> Neighbours:
    """A :class:`Neighbours` subscribed on ``service``'s bus (its handles closed with it). A
    controller that drives every robot (no ``robots`` selection) receives every pose anyway
    and feeds them in (:attr:`Neighbours.fed`); a shard subscribes to all poses itself."""
    nb = Neighbours(service.keys, **kw)

    def served(rid: str) -> bool:
        r = service._robots.get(rid)
        return r is not None and r.goal is not None and r.ctrl is not None

    robots = service._robots

    def served_many(rids: list[str]) -> list[bool]:
        out = []
        for rid in rids:
            r = robots.get(rid)
            out.append(r is not None and r.goal is not None and r.ctrl is not None)
        return out

    nb.served = served
    nb.served_many = served_many
    service._handles.extend(nb.subscribe(service.bus, poses=service.only is not None))
    return nb


def _body_clearance(
    entries: list[tuple[int, int, Any, Any, Any]], has: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The body's clearance and the law's hold time for each robot with neighbours whose law
    uses a clearance (inf and 1 otherwise: no wall fade, no cap)."""
    cb = np.full(len(entries), np.inf)
    hold = np.ones(len(entries))
    for i, e in enumerate(entries):
        ctrl = getattr(e[4], "controller", e[4])
        if has[i] and getattr(ctrl, "uses_clearance", False) and ctrl.hold_time > 0:
            cb[i] = float(np.asarray(ctrl.clearance(np.array([p[i]])))[0])
            hold[i] = ctrl.hold_time
    return cb, hold


def _write_back(
    entries: list[tuple[int, int, Any, Any, Any]],
    out: list[Any],
    u: np.ndarray,
    has: np.ndarray,
    arrived: np.ndarray,
    body: np.ndarray,
    th: np.ndarray,
    d: np.ndarray,
    vmax: np.ndarray,
) -> None:
    """The filtered velocities into the answers (unicycles as twists of their look-ahead)."""
    for i, e in enumerate(entries):
        if not has[i] or (arrived[i] and u[i] == 0):
            continue
        if body[i]:
            v, om = twist_from_velocity(
                u[i], th[i], d[i], vmax[i], getattr(e[4], "omega_max", np.inf)
            )
            new = complex(float(v), float(om))
        else:
            new = complex(u[i])
        out[e[0]][1][0][e[1]] = new
        if arrived[i] and new != 0:  # pushed off its goal by a mover: keep moving
            out[e[0]][1][1][e[1]] = Status.MOVING
