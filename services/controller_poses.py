"""The controller service's hot path: the batched pose step. Poses arrive in batches (the newest
per robot), are decoded in blocks of ``POSE_BLOCK``, grouped by controller and evaluated with one
vectorized control-law call per group (``fleet_step`` for the world-frame robots of one map),
and their commands published in order. With ``--fleet-coordinator roadmap`` each block's fresh
poses first advance the fleet's roadmap plan, and a coordinated robot is driven by its next
node's law (``services/controller_coord.py``).

A simulator that steps all its robots at once may publish one :class:`~confnav.schemas.PoseBatch`
per step on ``{prefix}/sim/{sim}/poses`` instead of a ``Pose`` per robot: its poses are decoded
with one validation, go through the same step, and the commands to them go out as one
:class:`~confnav.schemas.CommandBatch` on ``{prefix}/sim/{sim}/cmd_vel`` (one message each way
per step instead of one per robot: docs/SERVICES.md, "Scale")."""

from __future__ import annotations

import logging
import time
from typing import Any, NamedTuple

import numpy as np
from confnav.schemas import DecodeError, Pose, PoseBatch, decode
from confnav.services import navigation
from confnav.services.controller_coord import CoordMixin
from confnav.services.controller_footprint import off_shrunk
from confnav.services.controller_state import POSE_BLOCK, PoseLike, _Robot
from confnav.services.keys import KeyError_

from confnav.navigation.control import Controller
from confnav.navigation.fleet import fleet_step
from confnav.navigation.fleet_coord import Plan

log = logging.getLogger(__name__)


class BatchPose(NamedTuple):
    """One entry of a :class:`~confnav.schemas.PoseBatch` (the fields of a ``Pose`` the step
    reads; a tuple, not a validated model: the batch was validated as a whole)."""

    robot_id: str
    stamp_ns: int
    seq: int
    x: float
    y: float
    theta: float


def _sub_goal_codes(results: list[Any], plans: dict[str, Any]) -> list[Any]:
    """``results`` with ARRIVED turned into MOVING for the coordinated robots off their goal
    leg (at a roadmap node: a sub-goal, not the goal)."""
    out: list[Any] = []
    for (ctrl, members), res in results:
        if not isinstance(res, Exception):
            sub = np.array(
                [(p := plans.get(r.robot_id)) is not None and not p.goal_leg for r, _ in members],
                dtype=bool,
            )
            if sub.any():
                codes = np.asarray(res[1]).copy()
                codes[sub & (codes == navigation.ARRIVED)] = navigation.MOVING
                res = (res[0], codes)
        out.append(((ctrl, members), res))
    return out


class PosesMixin(CoordMixin):
    """The batched pose step (hot path)."""

    # poses (hot path) -------------------------------------------------------------------------
    def _on_poses(self, items: list[tuple[str, bytes]]) -> None:
        """Every waiting pose: the newest per robot, in blocks of :data:`POSE_BLOCK`."""
        self.count("poses", len(items))
        if len(items) > 1:
            newest = {key: i for i, (key, _) in enumerate(items)}
            if len(newest) < len(items):
                self.count("poses_superseded", len(items) - len(newest))
                items = [items[i] for i in sorted(newest.values())]
        for s in range(0, len(items), POSE_BLOCK):
            with self._step_lock:  # one step at a time (pose batches: another thread)
                self._hold()  # the block's messages go to the publisher in one piece
                try:
                    self._pose_block(items[s : s + POSE_BLOCK])
                finally:
                    self._release()

    def _on_pose_batches(self, items: list[tuple[str, bytes]]) -> None:
        """Waiting :class:`~confnav.schemas.PoseBatch` messages: the newest of each simulator
        is answered (one step, one ``CommandBatch``), older ones are superseded."""
        newest = {key: i for i, (key, _) in enumerate(items)}
        for i, (key, payload) in enumerate(items):
            try:
                sim = self.keys.parse(key).ident
                batch = decode(PoseBatch, payload)
                if batch.sim_id != sim:
                    raise DecodeError("invalid_input", f"batch on {key} names {batch.sim_id!r}")
            except (KeyError_, DecodeError) as exc:
                self.count("rejected")
                log.debug("rejected pose batch on %s: %s", key, exc)
                continue
            only = self.only
            idx = [j for j, rid in enumerate(batch.robot_ids) if only is None or rid in only]
            self.count("pose_batches")
            self.count("poses", len(idx))
            if newest[key] != i:  # a newer batch of this simulator waits: it is answered
                self.count("poses_superseded", len(idx))
                continue
            b = batch
            entries = [BatchPose(*e) for e in zip(b.robot_ids, b.stamps_ns, b.seq, b.x, b.y,
                                                  b.theta, strict=True)]  # fmt: skip
            rows = [entries[j] for j in idx]
            nb = self.neighbours
            if nb is not None:  # every robot of the batch is a neighbour (other shards' too);
                # a fed tracker gets the driven robots' poses from the step
                now = time.monotonic()
                driven = set(idx) if nb.fed else set()
                for j, e in enumerate(entries):
                    if j not in driven:
                        nb.note_pose(e.robot_id, e, now)  # type: ignore[arg-type]
            for s in range(0, len(rows), POSE_BLOCK):
                with self._step_lock:
                    self._hold(self.keys.sim(sim, "cmd_vel"), sim)
                    try:
                        self._pose_rows(rows[s : s + POSE_BLOCK])
                    finally:
                        self._release()

    def _pose_rows(self, poses: list[BatchPose]) -> None:
        """The step of a pose batch's entries (decoded already)."""
        now = time.monotonic()
        rows: list[tuple[_Robot, PoseLike]] = []
        robots = self._robots
        for pose in poses:
            r = robots.get(pose.robot_id)
            if r is None:
                r = self._robot(pose.robot_id)
                if r is None:
                    continue
            rows.append((r, pose))
        self._step(rows, now)

    def _rid_of(self, key: str) -> str | None:
        """Robot id of a pose key (cached: the hot path parses each key once)."""
        rid = self._rids.get(key)
        if rid is None:
            try:
                rid = self.keys.parse(key).ident
            except KeyError_:
                return None
            if len(self._rids) < 100_000:
                self._rids[key] = rid
        return rid

    def _pose_block(self, items: list[tuple[str, bytes]]) -> None:
        """Decode, one vectorized control-law call per shared controller, publish."""
        now = time.monotonic()
        rows: list[tuple[_Robot, PoseLike]] = []
        robots = self._robots
        for key, payload in items:
            rid = self._rid_of(key)
            if rid is None:
                self.count("rejected")
                continue
            r = robots.get(rid)  # one dict read: atomic, no lock per pose
            if r is None:  # remembered before its goal (the watchdog must not miss it)
                r = self._robot(rid)
                if r is None:
                    continue
            try:
                pose = decode(Pose, payload)
                if pose.robot_id != rid:
                    raise DecodeError("invalid_input", f"pose on {key} names {pose.robot_id!r}")
            except DecodeError as exc:
                self.count("rejected")
                reason = "nan_input" if exc.reason == "nan_input" else "invalid_input"
                with r.lock:
                    r.seen_t = now
                    if r.goal is not None:
                        r.last_pose_t = now  # the robot is alive, but its input is unusable
                        self._stop_robot(r, reason, str(exc), now)
                continue
            rows.append((r, pose))
        self._step(rows, now)

    def _step(self, rows: list[tuple[_Robot, PoseLike]], now: float) -> None:
        """The decoded poses of a block: fresh ones of robots with a goal get one vectorized
        control-law call per shared controller; every command is published."""
        groups: dict[int, tuple[navigation.ControllerLike, list[tuple[_Robot, PoseLike]]]] = {}
        nb = self.neighbours
        nb_fed = nb is not None and nb.fed
        drive: list[tuple[_Robot, PoseLike, navigation.ControllerLike]] = []
        for r, pose in rows:
            if nb_fed:  # the fleet filter's view of every robot (services/neighbours.py)
                nb.note_pose(r.robot_id, pose, now)  # type: ignore[union-attr,arg-type]
            with r.lock:
                r.seen_t = now
                stamp = (pose.stamp_ns, pose.seq)
                if stamp <= r.last_stamp:  # replayed or reordered: not fresh, not answered
                    self.count("poses_out_of_order")
                    continue
                r.last_stamp = stamp
                r.last_pose_t = now
                r.position = (pose.x, pose.y)
                r.theta = pose.theta
                r.stale_reported = False
                if r.goal is None:
                    continue
                blocker = self._blocker(r)
                if blocker is not None:
                    self._block(r, blocker, now, pose)
                    continue
                ctrl = r.ctrl
            assert ctrl is not None
            drive.append((r, pose, ctrl))
        # the fleet coordinator (services/controller_coord.py): a coordinated robot is driven
        # by its next roadmap node's controller, or by its own on the goal leg
        plans = self._coord_plans(drive, now)
        own: dict[str, navigation.ControllerLike] = {}
        for r, pose, ctrl in drive:
            pl = plans.get(r.robot_id)
            if pl is not None:
                own[r.robot_id] = ctrl
                ctrl = self._coord_law(pl, ctrl)
            groups.setdefault(id(ctrl), (ctrl, []))[1].append((r, pose))
        members_of = list(groups.values())
        results = list(zip(members_of, self._control(members_of), strict=True))
        if plans:  # a node controller's arrival is a sub-goal's: the robot keeps moving
            results = _sub_goal_codes(results, plans)
        results = self._reentered(results)
        if plans:  # a goal leg whose own law has no value: the plan's fallback law
            results = self._coord_fallback(results, plans, own)
        # --- fleet hook (services/neighbours.py): keep robots off each other and movers ---
        if self.neighbours is not None:
            results = self.neighbours.filter_block(
                results, now, coordinated=plans, reentering=self._reentry_notes
            )
        # --- end fleet hook ---
        batched = getattr(self._held, "batch", None) is not None
        if batched:  # a pose batch: its CommandBatch goes out before the robots' statuses
            self._defer_statuses(True)
        try:
            self._answer(results, plans, own, now)
        finally:
            if batched:
                kept = self._defer_statuses(False)
                self._send_commands()
                for r, *args in kept:
                    with r.lock:
                        self._status(r, *args)

    def _answer(
        self,
        results: list[Any],
        plans: dict[str, Plan],
        own: dict[str, navigation.ControllerLike],
        now: float,
    ) -> None:
        """Each robot's command (or stop) of the step's results, and its status."""
        for (ctrl, members), res in results:
            if isinstance(res, Exception):
                self.count("navigation_errors")
                for r, pose in members:
                    with r.lock:
                        self._stop_robot(
                            r, "navigation_error", f"{type(res).__name__}: {res}", now, pose
                        )
                continue
            u, codes = res
            for (r, pose), ui, code in zip(members, u.tolist(), codes.tolist(), strict=True):
                with r.lock:
                    if r.ctrl is not own.get(r.robot_id, ctrl):  # swapped to another map
                        # revision meanwhile: the answer is not the current revision's, and
                        # replay --check recomputes each command from the revision it names;
                        # the next pose gets one
                        self.count("answers_dropped_on_swap")
                        continue
                    d = navigation.decide(ctrl, complex(ui), int(code))
                    pl = plans.get(r.robot_id)
                    if pl is not None:
                        d = self._coord_decision(pl, d, r.robot_id)
                    self._act(r, pose, d, now)

    def _control(
        self, groups: list[tuple[navigation.ControllerLike, list[tuple[_Robot, PoseLike]]]]
    ) -> list[tuple[np.ndarray, np.ndarray] | Exception]:
        """``(u, codes)`` (or the error) of each controller group of a pose block, in order.

        The map does not depend on the goal: the groups of world-frame controllers on one map
        (robots with their own goals) get ``T``, ``T'`` and the clearance from one evaluation
        for all their poses and each group's law from ``Controller.from_map_values``; the others one
        control-law call per group (:func:`navigation.commands`).
        """
        zs = [np.array([complex(p.x, p.y) for _, p in members]) for _, members in groups]
        out: list[tuple[np.ndarray, np.ndarray] | Exception | None] = [None] * len(groups)
        laws: list[Any] = [ctrl for ctrl, _ in groups]
        by_map: dict[int, list[int]] = {}
        for i, law in enumerate(laws):
            if hasattr(law, "from_map_values") and hasattr(law, "cmap"):
                by_map.setdefault(id(law.cmap), []).append(i)
        for idx in by_map.values():
            if len(idx) < 2:  # one goal on this map: the plain call below
                continue
            try:
                zall = np.concatenate([zs[i] for i in idx])
                w, dw = laws[idx[0]].cmap.T_and_dT(zall)
                use = [i for i in idx if getattr(laws[i], "uses_clearance", False)]
                c = laws[use[0]].clearance(zall) if use else None
            except Exception as exc:
                for i in idx:
                    out[i] = exc
                continue
            if all(isinstance(laws[i], Controller) for i in idx):
                try:  # every goal's law in one vectorized pass (navigation.fleet)
                    fleet = [laws[i] for i in idx for _ in range(zs[i].size)]
                    o = fleet_step(fleet, zall, w, dw, c)
                    self.count("fleet_steps")
                except Exception:  # a bug there must not stop the fleet: one by one below
                    log.exception("fleet step failed; evaluating each goal on its own")
                else:
                    s = 0
                    for i in idx:
                        n = zs[i].size
                        out[i] = (np.asarray(o.u[s : s + n]), np.asarray(o.status[s : s + n]))
                        s += n
                    continue
            s = 0
            for i in idx:
                n = zs[i].size
                try:
                    ci = None if c is None else c[s : s + n]
                    o = laws[i].from_map_values(zs[i], w[s : s + n], dw[s : s + n], ci)
                    out[i] = (np.asarray(o.u, dtype=complex), np.asarray(o.status, dtype=int))
                except Exception as exc:
                    out[i] = exc
                s += n
        for i, (ctrl, members) in enumerate(groups):
            if out[i] is not None:
                continue
            th = np.array([p.theta for _, p in members])
            try:
                out[i] = navigation.commands(ctrl, zs[i], th)
            except Exception as exc:
                out[i] = exc
        return [o for o in out if o is not None]

    def _reentered(self, results: list[Any]) -> list[Any]:
        """``results`` with the robots just outside their law's free space steered back in
        (:func:`navigation.reenter`; confnav/navigation/reentry.py): their re-entry command
        and MOVING, before the fleet filter sees them. Robots outside their map are rare, so
        only the ERROR entries of a group are visited."""
        self._reentry_notes.clear()  # this step's (steps run one at a time)
        codes_all = [np.ravel(res[1]) for _, res in results if not isinstance(res, Exception)]
        if not codes_all or not (np.concatenate(codes_all) == navigation.ERROR).any():
            return results  # nobody outside its map (one check, not one per goal's group)
        out: list[Any] = []
        for (ctrl, members), res in results:
            if isinstance(res, Exception):
                out.append(((ctrl, members), res))
                continue
            u, codes = res
            bad = np.flatnonzero(np.asarray(codes) == navigation.ERROR)
            if bad.size:
                u, codes = np.array(u, dtype=complex), np.array(codes)
                for k in bad.tolist():
                    r, pose = members[k]
                    uk, ck, note = navigation.reenter(
                        ctrl, pose.x, pose.y, pose.theta, complex(u[k]), int(codes[k])
                    )
                    if note:
                        u[k], codes[k] = uk, ck
                        self._reentry_notes[r.robot_id] = note
                        self.count("reentry_commands")
            out.append(((ctrl, members), (u, codes)))
        return out

    def _coord_fallback(
        self,
        results: list[Any],
        plans: dict[str, Any],
        own: dict[str, navigation.ControllerLike],
    ) -> list[Any]:
        """``results`` with the coordinated robots whose own law has no value on their goal
        leg (ERROR or a NaN command) driven by their plan's fallback law (the straight law
        to the goal on an atlas, :meth:`~confnav.navigation.fleet_coord.RoadmapCoordinator
        .goal_law`; wrapped in the robot's look-ahead law for a unicycle), and for the rest
        of that leg once it was (latched per robot and fallback law)."""
        latched: dict[str, Any] = self._coord_state().setdefault("fallback", {})
        out: list[Any] = []
        for (ctrl, members), res in results:
            if isinstance(res, Exception):
                out.append(((ctrl, members), res))
                continue
            u, codes = res
            bad = (np.asarray(codes) == navigation.ERROR) | ~np.isfinite(np.asarray(u))
            for k, (r, _) in enumerate(members):
                pl = plans.get(r.robot_id)
                fb = None if pl is None else pl.fallback
                if latched.get(r.robot_id, fb) is not fb or fb is None:
                    latched.pop(r.robot_id, None)  # off that goal leg: its own law again
                elif bad[k]:
                    latched[r.robot_id] = fb
                # once its own law had no value on this leg, the fallback drives the rest of
                # it: in the services warehouse (seed 0) the own law, NaN in a patch near the
                # goal, drove the robot back into the patch, and it stayed between the two
                bad[k] = bad[k] or r.robot_id in latched
            for k in np.flatnonzero(bad).tolist():
                r, pose = members[k]
                pl = plans.get(r.robot_id)
                if pl is None or pl.fallback is None or r.robot_id not in own:
                    continue
                law = self._coord_law(
                    Plan(pl.fallback, pl.goal_leg, pl.parked, pl.note, True), own[r.robot_id]
                )
                uk, ck = navigation.commands(
                    law, np.array([complex(pose.x, pose.y)]), np.array([pose.theta])
                )
                u, codes = np.array(u, dtype=complex), np.array(codes)
                u[k], codes[k] = uk[0], ck[0]
                self.count("goal_leg_fallbacks")
            out.append(((ctrl, members), (u, codes)))
        return out

    def _act(self, r: _Robot, pose: PoseLike, d: navigation.Decision, now: float) -> None:
        """Publish what :func:`navigation.decide` made of the control law's output."""
        if r.goal is None or r.last_stamp != (pose.stamp_ns, pose.seq):
            return  # cancelled, or a newer pose came meanwhile: it gets the answer
        blocker = self._blocker(r)  # again: the geometry may have changed meanwhile
        if blocker is not None:
            self._block(r, blocker, now, pose)
        elif d.state == "stopped":
            self._stop_robot(r, d.reason, d.message, now, pose)
        elif r.shrunk is not None and (off := off_shrunk(r, pose.theta)):
            # on the base map (footprint map being solved) outside the footprint's free space:
            # what the footprint map would answer (services/controller_footprint.py)
            self._stop_robot(r, "outside_workspace", off, now, pose)
        else:
            self._publish_cmd(r, d.u, pose)
            message = d.message
            holding = getattr(r.ctrl, "waiting", None) is not None  # a pending atlas chart
            if (self._refining or r.base_ws or r.atlas_ws or holding) and d.state == "navigating":
                note = self._map_note(r)
                message = "; ".join(m for m in (note, message) if m)
            reentry = self._reentry_notes.pop(r.robot_id, "")
            if reentry and d.state == "navigating":
                message = "; ".join(m for m in (reentry, message) if m)
            if self.neighbours is not None and d.state == "navigating":
                stuck = self.neighbours.stuck_note(r.robot_id, now)
                message = "; ".join(m for m in (message, stuck) if m)
            self._status(r, d.state, d.reason, message, now)
