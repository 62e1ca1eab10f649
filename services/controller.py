"""Controller service: per robot, goal + map + pose -> velocity command and status.

Subscribes ``{prefix}/robot/*/goal``, ``.../cancel``, ``.../pose``, ``{prefix}/ws/*/transform``,
``{prefix}/ws/*/definition`` and the liveliness of ``{prefix}/alive/transform/*``; fetches
missing maps with a query on ``{prefix}/ws/{ws}/transform``; publishes ``cmd_vel`` and
``status`` per robot. A re-solved map is loaded and the robots' controllers rebuilt off the
pose path, then swapped in atomically. A workspace solved as an atlas (``{prefix}/ws/{ws}/atlas``)
is fetched by ``services/atlas_client.py`` and each of its robots gets its own chart-switching
controller (docs/ATLAS.md section 5).

A workspace definition that differs from the one the installed map was solved from makes
that map outdated: until a map of the new definition is installed, every robot of the
workspace closer than ``margin`` to the new geometry (or inside a new obstacle) is stopped
(reason ``map_outdated``) at once, and at each of its poses; the others keep moving on the old
map (a robot moves at most ``v_max`` per control period, so with ``margin`` above that it is
stopped before it can reach the new geometry).

Watchdog (zero velocity and a status saying why): stale pose (none for ``stale_after`` s since
the last pose or the goal; a pose only counts when its ``(stamp_ns, seq)`` is newer than the
last one, so replayed or reordered poses are not fresh), missing map, NaN or invalid pose,
position outside the map, no live transform service. Malformed goals (and goals above the
``max_gain``/``max_speed`` caps) clear the robot's goal and are answered with a status
(``idle``, ``invalid_input``); a ``GoalCancel`` and ``idle_ttl`` s without a pose or goal
forget a robot. Poses go through a bounded latest-per-robot queue; commands and statuses are
published by one publisher thread (never under a lock), in the order they were decided.
Many robots per process; ``robots`` restricts which ones this process drives.

The service is split by job, one module each: ``controller_state`` (robot records, publisher
thread, commands, statuses, stop reasons), ``controller_cache`` (controllers per map revision
and goal), ``controller_maps`` (fetching, installing and hot-swapping maps and atlases,
definition changes), ``controller_goals`` (goals and cancels), ``controller_poses`` (the batched
pose step), ``controller_coord`` (the fleet coordinator), ``controller_watchdog``; this module
puts them together and holds the CLI.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from confnav.services.controller_cache import CTRL_CACHE_SIZE
from confnav.services.controller_coord import COORDINATORS, DEFAULT_COORDINATOR
from confnav.services.controller_goals import GoalsMixin
from confnav.services.controller_maps import MapsMixin
from confnav.services.controller_poses import PosesMixin
from confnav.services.controller_state import (
    MAX_BACKLOG,
    POSE_BLOCK,
    ControllerFactory,
    MapLoader,
)
from confnav.services.controller_watchdog import WatchdogMixin
from confnav.services.keys import KeyError_
from confnav.services.neighbours import attach as attach_neighbours
from confnav.services.runtime import add_zenoh_args, run_until_signal
from confnav.services.shard import RobotSelector, robot_key_exprs, serialized

log = logging.getLogger(__name__)


class ControllerService(MapsMixin, GoalsMixin, PosesMixin, WatchdogMixin):
    """See the module docstring."""

    def _start(self) -> None:
        k = self.keys
        self._handles.append(self.bus.subscribe_liveliness(k.alive_of("transform"), self._on_live))
        self.spawn(self._publish_loop, "publish")
        self._handles.append(self.bus.subscribe(k.any_ws("transform"), self._on_transform))
        self._handles.append(self.bus.subscribe(k.any_ws("definition"), self._on_definition))
        self._handles.append(self.bus.subscribe(k.any_ws("delete"), self._on_ws_delete))
        self._handles.append(self.bus.subscribe(k.any_ws("atlas"), self._on_atlas))
        self._handles.append(self.bus.subscribe(k.any_ws("status"), self._on_ws_status))
        # this process's robots only (scale-out: services/shard.py, docs/SERVICES.md)
        exprs = robot_key_exprs(k, "goal", self.only)
        on_goals = serialized(self._on_goals) if len(exprs) > 1 else self._on_goals
        for expr in exprs:
            self._handles.append(self.bus.subscribe_latest(expr, on_goals, self._goals_dropped))
        for expr in robot_key_exprs(k, "cancel", self.only):
            self._handles.append(self.bus.subscribe(expr, self._on_cancel))
        exprs = robot_key_exprs(k, "pose", self.only)
        on_poses = serialized(self._on_poses) if len(exprs) > 1 else self._on_poses
        for expr in exprs:
            self._handles.append(  # bounded: the newest waiting pose of each robot wins
                self.bus.subscribe_latest(
                    expr,
                    on_poses,
                    self._poses_dropped,
                    max_keys=MAX_BACKLOG,
                    linger=self.linger,
                )
            )
        # a simulator's poses all at once (optional PoseBatch; answered with a CommandBatch)
        self._handles.append(self.bus.subscribe_batch(k.any_sim("poses"), self._on_pose_batches))
        self.neighbours = attach_neighbours(self)  # fleet hook: every robot's pose, movers
        self.spawn(self._fetch_loop, "fetch")
        self.spawn(self._watchdog_loop, "watchdog")


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("controller", help="run the controller service")
    add_zenoh_args(p)
    p.add_argument(
        "--robots",
        default=None,
        help="robots this process drives: comma-separated ids and Zenoh chunk patterns such "
        "as 'a$*' (ids starting with a) or '$*7'; others' poses are not even delivered "
        "(default: all; see docs/SERVICES.md, scale-out)",
    )
    p.add_argument("--stale-after", type=float, default=0.5, help="pose timeout, s")
    p.add_argument(
        "--linger-ms",
        type=float,
        default=0.0,
        help="ms to wait for more poses before a control step (larger batches, less CPU)",
    )
    p.add_argument(
        "--margin",
        type=float,
        default=0.25,
        help="m: on a definition change, robots this close to the new geometry stop until "
        "its map is installed (default %(default)s)",
    )
    p.add_argument("--max-gain", type=float, default=1000.0, help="largest goal gain, 1/s")
    p.add_argument("--max-speed", type=float, default=2.0, help="largest goal v_max, m/s")
    p.add_argument(
        "--idle-ttl", type=float, default=60.0, help="s without pose or goal: robot forgotten"
    )
    p.add_argument(
        "--atlas-warmup",
        choices=("background", "first-use"),
        default="background",
        help="an atlas's charts: 'background' (default): installed cold, a robot's chart "
        "evaluates directly until a background thread has built its local expansions, "
        "nearest the robots first; 'first-use': each chart builds them when a robot first "
        "uses it, in its goal or pose step (less memory for charts no robot visits; a "
        "robot's first move then waits about a second per chart, more under load)",
    )
    p.add_argument(
        "--fleet-coordinator",
        choices=COORDINATORS,
        default=DEFAULT_COORDINATOR,
        help="how the robots this process drives get past each other: 'local': side "
        "passing, yielding and the deadlock step; 'roadmap': two or more robots on one map "
        "move on a roadmap of its free space as planned by PIBT (a robot alone drives as "
        "without it): every robot arrives through single-lane aisles and doors where the "
        "local rules gridlock, but open rooms take longer; 'auto' (default): per map and "
        "robot footprint, 'roadmap' when the free space has a single-lane passage "
        "(narrower than two robots' look-ahead disks side by side plus half a disk), "
        "'local' otherwise, decided when a second robot comes and said once in the log "
        "(docs/NAVIGATION.md, 'The roadmap coordinator in the controller service')",
    )
    p.add_argument(
        "--route-hints",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="send the waiting robots' start and goal with map queries, so that a transform "
        "service solving a progressive atlas solves their charts first (docs/SLAM.md, "
        "'Progressive atlas'; the default); --no-route-hints: queries without payload",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    try:
        robots = RobotSelector.parse(args.robots) if args.robots else None
    except KeyError_ as exc:
        print(f"confnav serve controller: --robots: {exc}", file=sys.stderr)
        return 2

    def make(bus: Any, keys: Any) -> ControllerService:
        svc = ControllerService(
            bus,
            keys,
            robots,
            stale_after=args.stale_after,
            linger=args.linger_ms / 1e3,
            margin=args.margin,
            max_gain=args.max_gain,
            max_speed=args.max_speed,
            idle_ttl=args.idle_ttl,
        )
        svc.atlas_warmup = getattr(args, "atlas_warmup", "background")
        svc.fleet_coordinator = getattr(args, "fleet_coordinator", DEFAULT_COORDINATOR)
        svc.route_hints = bool(getattr(args, "route_hints", True))
        return svc

    return run_until_signal(make, args)


__all__ = [
    "CTRL_CACHE_SIZE",
    "MAX_BACKLOG",
    "POSE_BLOCK",
    "ControllerFactory",
    "ControllerService",
    "MapLoader",
    "add_parser",
    "main",
]
