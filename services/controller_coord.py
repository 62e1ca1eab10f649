"""The controller service's fleet coordinator: the robots this controller serves move on a
roadmap as planned by PIBT (``confnav serve controller --fleet-coordinator roadmap``;
``local``: the local rules of ``services/neighbours.py`` only; the default ``auto``: per map
and footprint, ``roadmap`` where the free space has a single-lane passage, ``local`` in
open rooms, :func:`~confnav.navigation.fleet_coord.choose_coordinator`, decided once when
the fleet's roadmap is built and said in the log).

A thin shell over the core's :class:`~confnav.navigation.fleet_coord.FleetCoordinator`
(docs/NAVIGATION.md, "Coordination on a roadmap (PIBT)" and "The roadmap coordinator in the
controller service"):
the robots of one map (the free space shrunk by one footprint) with one speed limit are one
coordinated fleet; each pose block's fresh poses advance its plan, and a robot's sub-goal (its
next roadmap node) becomes the goal of the node's controller (Koditschek-Rimon on a single
conformal map; on an atlas the straight law along the roadmap's free edges,
:class:`~confnav.navigation.fleet_coord.LineLaw`; wrapped in the robot's look-ahead law for a
unicycle), whose command then goes through the same fleet filter
as any other (``services/neighbours.py``: pairwise rows, walls, the hold cap; side passing
and the yield rule are off for coordinated robots: the plan replaces them).  On the goal leg
the robot's own controller drives it, and its arrival is the published one; where its own
law has no value there (ERROR or NaN: an atlas chart's law may have none near the goal), the
straight law to its goal on an atlas (the segment from its goal node is free;
:meth:`~confnav.navigation.fleet_coord.RoadmapCoordinator.goal_law`,
``services/controller_poses.py``).

Not coordinated, and driven exactly as without this module: a robot alone on its map (one
robot with a goal seen within the coordinator's ``ttl``), a robot on the base map while its
footprint map is solved, any robot while its fleet's roadmap is being built
(in a background thread, the first time two robots share a map).  Robots of other shards, real
and replayed robots are never coordinated: they stay neighbours of the safety filter.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

from confnav.services import navigation
from confnav.services.controller_state import ControllerCore, PoseLike, _Robot
from confnav.services.roadmap_worker import build_in_child

from confnav.geometry import Workspace
from confnav.navigation.control import Controller
from confnav.navigation.fleet_coord import (
    ALONE,
    LANE_FACTOR,
    FleetCoordinator,
    FleetRoadmap,
    Plan,
    RoadmapCoordinator,
    plan_fleet_roadmap,
)
from confnav.navigation.unicycle import UnicycleController

log = logging.getLogger(__name__)

#: the coordinators the ``--fleet-coordinator`` option names
COORDINATORS = ("auto", "local", "roadmap")
#: the default of ``--fleet-coordinator``
DEFAULT_COORDINATOR = "auto"

_Key = tuple[str, float, float]  # (free space's content hash, filter radius, v_max)


class CoordMixin(ControllerCore):
    """The fleet coordinator of a controller service (module docstring)."""

    #: ``auto`` (default: ``roadmap`` on maps with a single-lane passage, else ``local``),
    #: ``local`` (the local rules) or ``roadmap``
    fleet_coordinator: str = DEFAULT_COORDINATOR

    def _coord_state(self) -> dict[str, Any]:
        st: dict[str, Any] | None = self.__dict__.get("_coord")
        if st is None:
            st = self.__dict__.setdefault(
                "_coord",
                {
                    "fleets": {},
                    "building": set(),
                    "of": {},
                    "laws": {},
                    "lock": threading.Lock(),
                    "local": set(),  # fleets ``auto`` leaves to the local rules
                },
            )
        return st

    def _coord_plans(
        self, rows: list[tuple[_Robot, PoseLike, navigation.ControllerLike]], now: float
    ) -> dict[str, Plan]:
        """The plan of each robot of a pose block that is coordinated (absent: not)."""
        if self.fleet_coordinator not in ("roadmap", "auto") or not rows:
            return {}
        st = self._coord_state()
        by_key: dict[_Key, list[tuple[_Robot, PoseLike, Any, float]]] = {}
        for r, pose, ctrl in rows:
            law = getattr(ctrl, "controller", ctrl)  # a unicycle's point law
            cmap: Any
            if isinstance(law, Controller):  # one conformal map: Koditschek-Rimon node laws
                cmap = law.cmap
            else:  # an atlas (AtlasController): straight node laws on its workspace
                cmap = getattr(getattr(law, "nav", None), "atlas", None)
            ws = getattr(cmap, "workspace", None)
            # isinstance, not hasattr(ws, "content_hash"): that evaluated the property (a
            # sha256 of the geometry's JSON) for every robot of every pose block, a quarter
            # of the pose step's CPU with 200 robots (bench_controller.py --step)
            if r.goal is None or r.base_ws or not isinstance(ws, Workspace):
                continue  # no goal, on the base map, or no polygonal workspace (a test's map)
            d = float(getattr(ctrl, "d", 0.0)) if getattr(ctrl, "frame", "") == "body" else 0.0
            # one fleet per free space (not per map object: a re-solved map or an atlas
            # whose charts come in one by one is a new object for the same robots' floor)
            key = (_space_of(cmap), navigation.footprint_radius(r.goal), float(r.goal.v_max))
            old = st["of"].get(r.robot_id)
            if old is not None and old != key and old in st["fleets"]:
                st["fleets"][old].forget(r.robot_id)  # another map or speed: another fleet
            st["of"][r.robot_id] = key
            by_key.setdefault(key, []).append((r, pose, cmap, d))
        out: dict[str, Plan] = {}
        for key, members in by_key.items():
            if key in st["local"]:  # auto chose the local rules for this map
                continue
            fleet = st["fleets"].get(key)
            if fleet is None:
                if len(members) > 1 or self._fleet_waits(key):
                    self._build_fleet(key, members[0][2], members[0][3])
                continue
            ids = [r.robot_id for r, _, _, _ in members]
            p = [complex(pz.x, pz.y) + d * _heading(pz.theta) for _, pz, _, d in members]
            goals = [complex(*r.goal.goal) for r, _, _, _ in members]  # type: ignore[union-attr]
            tokens = [(r.goal.goal, r.goal.stamp_ns, r.goal_t) for r, _, _, _ in members]  # type: ignore[union-attr]
            try:
                plans = fleet.plan(now, ids, p, goals, tokens)
            except Exception:  # a bug in the plan must not stop the fleet: local rules
                log.exception("fleet coordinator failed; its robots use the local rules")
                self.count("coordinator_errors")
                del st["fleets"][key]
                continue
            for rid, pl in zip(ids, plans, strict=True):
                if pl.coordinated:
                    out[rid] = pl
            self.count("coordinated_poses", sum(pl.coordinated for pl in plans))
        return out

    def _fleet_waits(self, key: _Key) -> bool:
        """Whether another robot of fleet ``key`` was seen lately (robots of one fleet may
        come in different pose blocks)."""
        st = self._coord_state()
        return sum(1 for k in st["of"].values() if k == key) > 1

    def _build_fleet(self, key: _Key, cmap: Any, d: float) -> None:
        """Build fleet ``key``'s roadmap and node controllers in a background thread (the pose
        path never waits for it: its robots use the local rules meanwhile)."""
        st = self._coord_state()
        with st["lock"]:
            if key in st["building"]:
                return
            st["building"].add(key)

        def build() -> None:
            try:
                single = hasattr(cmap, "T_and_dT")  # one map (else an atlas)
                auto = self.fleet_coordinator == "auto"
                fr = _roadmap_off_the_gil(cmap.workspace, key[1], auto)
                if auto:
                    choice, width, where = fr.choice, fr.width, fr.where
                    self.count(f"fleet_auto_{choice}")
                    if key[1] <= 0.0:
                        log.info("fleet coordinator auto for point robots: local (no passage "
                                 "is single-lane for them)")  # fmt: skip
                    elif not math.isfinite(width):  # no edge: nowhere to pass or wait aside
                        log.warning(
                            "fleet coordinator auto for radius %g m: %s (the roadmap has no "
                            "edge: the free space is nowhere wide enough for two robots; "
                            "robots whose routes meet head-on may block each other)",
                            key[1], choice,
                        )  # fmt: skip
                    else:
                        log.info(
                            "fleet coordinator auto for radius %g m: %s (narrowest passage "
                            "for the robots' centres %.2f m at (%.2f, %.2f); single-lane "
                            "below %.2f m)", key[1], choice, width, where.real, where.imag,
                            LANE_FACTOR * key[1],
                        )  # fmt: skip
                    if choice == "local":
                        st["local"].add(key)
                        return
                assert fr.roadmap is not None  # a roadmap choice comes with its roadmap
                coord = RoadmapCoordinator.on_roadmap(
                    fr.roadmap,
                    cmap if single else None,
                    0,
                    key[1],
                    v_max=key[2],
                    node_law="kr" if single else "line",
                    workspace=cmap.workspace,
                )
                st["fleets"] = {  # fleets of maps no robot uses any more are dropped
                    k: f for k, f in list(st["fleets"].items()) if k in set(st["of"].values())
                }
                st["fleets"][key] = FleetCoordinator(coord)
                self.count("roadmaps_built")
                log.info(
                    "fleet roadmap for radius %g m: %d nodes, %d edges",
                    key[1], coord.roadmap.size, len(coord.roadmap.edges),
                )  # fmt: skip
            except Exception as exc:  # no roadmap: the local rules stay (said in the log)
                log.warning("no fleet roadmap for radius %g m: %s", key[1], exc)
                self.count("roadmap_errors")
            finally:
                with st["lock"]:
                    st["building"].discard(key)

        threading.Thread(target=build, name="fleet-roadmap", daemon=True).start()

    def _coord_law(self, plan: Plan, ctrl: navigation.ControllerLike) -> navigation.ControllerLike:
        """The law that drives a coordinated robot now: its own (goal leg) or its node's
        controller, wrapped in the robot's look-ahead law for a unicycle (cached)."""
        if plan.ctrl is None:
            return ctrl
        if getattr(ctrl, "frame", "") != "body":
            node: navigation.ControllerLike = plan.ctrl
            return node
        u: Any = ctrl
        key = (id(plan.ctrl), u.d, u.v_max, u.omega_max)
        laws: dict[tuple[int, float, float, float], Any] = self._coord_state()["laws"]
        law = laws.get(key)
        if law is None:
            law = laws[key] = UnicycleController(
                plan.ctrl, u.d, v_max=u.v_max, omega_max=u.omega_max
            )
        return law  # type: ignore[no-any-return]

    def _coord_reached(self, rid: str) -> None:
        """Robot ``rid`` arrived on its goal leg: it parks on the roadmap."""
        st = self._coord_state()
        fleet = st["fleets"].get(st["of"].get(rid))
        if fleet is not None:
            fleet.reached(rid)

    def _coord_decision(self, plan: Plan, d: navigation.Decision, rid: str) -> navigation.Decision:
        """What a coordinated robot publishes: its node's command with the plan in the status
        message; a robot done with its goal stays ``arrived`` while it parks."""
        if d.state == "arrived" and plan.goal_leg:
            self._coord_reached(rid)
            return navigation.Decision(d.u, "arrived", "arrived", "arrived; parking on the roadmap")
        if d.state == "stopped":
            return d
        note = "; ".join(m for m in (plan.note, d.message) if m)
        if plan.parked:
            return navigation.Decision(d.u, "arrived", "arrived", note)
        return navigation.Decision(d.u, "navigating", d.reason, note)


def _roadmap_off_the_gil(ws: Workspace, rho: float, decide: bool) -> FleetRoadmap:
    """The fleet's roadmap (and ``auto``'s choice) built in a child process
    (``services/roadmap_worker.py``: the pose path never waits for the GIL behind it); in
    this thread only if no child can be started (said in the log).  Point robots under
    ``auto`` need no roadmap (:func:`plan_fleet_roadmap`): decided here, no child."""
    if decide and not rho > 0.0:
        return plan_fleet_roadmap(ws, rho, decide)
    try:
        return build_in_child(ws, rho, decide)
    except OSError as exc:
        log.warning("no roadmap child process (%s): building it in the controller", exc)
        return plan_fleet_roadmap(ws, rho, decide)


def _space_of(cmap: Any) -> str:
    """The identity of a map's free space: its workspace's content hash (cached on the
    workspace object)."""
    ws = cmap.workspace
    h = ws.__dict__.get("_fleet_key")
    if h is None:
        h = ws.__dict__.setdefault("_fleet_key", str(ws.content_hash))
    return str(h)


def _heading(theta: float) -> complex:
    import cmath

    return cmath.exp(1j * theta)


__all__ = ["ALONE", "COORDINATORS", "DEFAULT_COORDINATOR", "CoordMixin"]
