"""Drive and watch a running confnav system from the shell: ``confnav goal``, ``confnav cancel``
and ``confnav status``.

Each command opens one Zenoh client session (the same ``--connect``/``--prefix`` flags as the
services), publishes or listens for a short window, prints what it saw and exits. Messages are
the wire schemas (:mod:`confnav.schemas`); keys come from :class:`confnav.services.keys.Keys`.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, get_args

from pydantic import ValidationError

from confnav.argtypes import positive_float
from confnav.cli.app import HelpFormatter
from confnav.errors import ConfnavError
from confnav.navigation import defaults
from confnav.schemas import (
    WAITING_FOR_MAP,
    Goal,
    GoalCancel,
    Pose,
    RobotStatus,
    ServiceHealth,
    TransformSolution,
    TransformStatus,
    decode,
    encode,
)
from confnav.schemas.messages import DriveName, NavFnName, SpeedLawName
from confnav.services.bus import ZenohBus
from confnav.services.keys import KeyError_, Keys, validate_id
from confnav.services.runtime import add_zenoh_args, bus_from_args

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
"""Where ``confnav launch`` puts its router by default; used when no ``--connect`` is given."""


REJECTED = ("invalid_input", "navigation_error", "outside_workspace")
"""Status reasons that answer a goal with a refusal (the goal is dropped)."""


class OpsError(ConfnavError):
    """A command driving a running system failed (no router, no answer, goal rejected)."""


# ------------------------------------------------------------------------------------------
# argument types (checked at parse time: one line, exit 2)
# ------------------------------------------------------------------------------------------
def robot_id(text: str) -> str:
    """An id valid as a key chunk (no ``/ * $ # ?`` nor whitespace)."""
    try:
        return validate_id(text, "robot id")
    except KeyError_ as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def ws_id(text: str) -> str:
    try:
        return validate_id(text, "workspace id")
    except KeyError_ as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def prefix(text: str) -> str:
    try:
        return Keys(text).prefix
    except KeyError_ as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def point(text: str) -> tuple[float, float]:
    """``X,Y`` in metres, both finite."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        x, y = float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"point {text!r} is not X,Y (two numbers)") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"point {text!r} is not finite")
    return x, y


# ------------------------------------------------------------------------------------------
# session
# ------------------------------------------------------------------------------------------
def _open(args: argparse.Namespace) -> ZenohBus:
    if not args.connect and not args.listen and not args.zenoh_config and args.mode == "client":
        args.connect = [DEFAULT_ROUTER]
    try:
        return bus_from_args(args, retry_for=args.connect_timeout)
    except Exception as exc:
        where = ", ".join(args.connect) or "(config)"
        first = str(exc).split("\n")[0].split("  at ")[0].strip()
        raise OpsError(f"cannot reach a Zenoh router at {where}: {first}") from None


@dataclass
class _Latest:
    """The newest decoded message per id, filled by subscription handlers."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    items: dict[str, Any] = field(default_factory=dict)
    bad: int = 0

    def handler(
        self, model: type[Any], ident: Callable[[Any], str]
    ) -> Callable[[str, bytes], None]:
        def on(key: str, payload: bytes) -> None:
            try:
                msg = decode(model, payload)
            except (ValidationError, ValueError):
                with self.lock:
                    self.bad += 1
                return
            with self.lock:
                self.items[ident(msg)] = msg

        return on

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            return dict(self.items)


# ------------------------------------------------------------------------------------------
# goal / cancel
# ------------------------------------------------------------------------------------------
def _goal(args: argparse.Namespace) -> int:
    keys = Keys(args.prefix)
    try:
        goal = Goal(
            robot_id=args.robot,
            ws_id=args.ws,
            goal=args.point,
            navfn=args.navfn,
            k=args.k,
            gain=args.gain,
            v_max=args.v_max,
            tolerance=args.tolerance,
            robot_radius=args.robot_radius,
            drive=args.drive,
            lookahead=args.lookahead,
            omega_max=args.omega_max,
            speed_law=args.speed_law,
            stamp_ns=time.time_ns(),
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise OpsError(f"invalid goal: {where}: {err['msg']}") from None
    with _open(args) as bus:
        seen = _Latest()
        bus.subscribe(keys.robot(args.robot, "status"), seen.handler(RobotStatus, lambda s: "s"))
        time.sleep(0.2)  # let the subscription reach the router before the goal goes out
        t_sent = time.time_ns()
        bus.publish(keys.robot(args.robot, "goal"), encode(goal))
        x, y = args.point
        print(f"goal ({x:g}, {y:g}) in workspace {args.ws} sent to robot {args.robot}")
        deadline = time.monotonic() + args.timeout
        last: RobotStatus | None = None  # newest status since the goal went out
        solving = False
        while time.monotonic() < deadline:
            s = seen.snapshot().get("s")
            if s is not None and s.stamp_ns >= t_sent:
                last = s
                verdict = goal_verdict(s)
                if verdict == "done":
                    break
                if verdict == "map_being_solved":
                    # its map is being solved (progressive maps: the robot moves on the first
                    # revision): the timeout counts from the newest such status
                    if not solving:
                        print(f"waiting for the map: {s.message}")
                        solving = True
                    deadline = max(deadline, time.monotonic() + args.timeout)
            time.sleep(0.05)
    if last is None:
        raise OpsError(
            f"no status from robot {args.robot} within {args.timeout:g} s "
            "(is a controller running under this prefix?)"
        )
    print(_robot_line(last))
    if last.reason in REJECTED:
        raise OpsError(f"goal rejected: {last.message}")
    if last.state not in ("navigating", "arrived"):
        raise OpsError(
            f"robot {args.robot} is {last.state} ({last.reason}) {args.timeout:g} s after the goal"
        )
    return 0


def goal_verdict(s: RobotStatus) -> str:
    """What a status after ``confnav goal`` means: ``done`` (the robot navigates, arrived, or
    its goal was rejected), ``map_being_solved`` (it holds for the first revision of its map:
    keep waiting) or ``pending`` (any other state, e.g. a stop that may clear)."""
    if s.reason in REJECTED:
        return "done"
    holding = s.state == "navigating" and s.message.startswith(WAITING_FOR_MAP)
    if holding or (s.reason == "missing_map" and "being solved" in s.message):
        return "map_being_solved"  # (the second: a controller older than this one)
    return "done" if s.state in ("navigating", "arrived") else "pending"


def _cancel(args: argparse.Namespace) -> int:
    keys = Keys(args.prefix)
    with _open(args) as bus:
        time.sleep(0.2)
        bus.publish(
            keys.robot(args.robot, "cancel"),
            encode(GoalCancel(robot_id=args.robot, stamp_ns=time.time_ns())),
        )
        time.sleep(0.1)  # let the sample leave before the session closes
    print(f"cancel sent to robot {args.robot}")
    return 0


# ------------------------------------------------------------------------------------------
# status
# ------------------------------------------------------------------------------------------
def _robot_line(s: RobotStatus) -> str:
    pos = f"({s.position[0]:.3f}, {s.position[1]:.3f})" if s.position is not None else "-"
    dist = f"{s.distance_to_goal:.3f} m" if s.distance_to_goal is not None else "-"
    msg = f"  {s.message}" if s.message else ""
    return (
        f"robot {s.robot_id:<16} {s.state:<10} {s.reason:<18} ws {s.ws_id or '-':<12} "
        f"at {pos:<18} to goal {dist}{msg}"
    )


def collect_status(bus: ZenohBus, keys: Keys, window: float) -> dict[str, Any]:
    """Listen ``window`` s to robot statuses and poses, workspace statuses and health, query
    the served transforms and the liveliness tokens; return what was seen, grouped.

    A robot is listed if it publishes poses (the simulator's, a real robot's) or a controller
    reports on it: the controller reports only on robots it drives (a goal) and forgets a
    cancelled robot, which still stands somewhere."""
    robots, ws_status, health, poses = _Latest(), _Latest(), _Latest(), _Latest()
    handles = [
        bus.subscribe(keys.any_robot("status"), robots.handler(RobotStatus, lambda s: s.robot_id)),
        bus.subscribe(keys.any_robot("pose"), poses.handler(Pose, lambda p: p.robot_id)),
        bus.subscribe(keys.any_ws("status"), ws_status.handler(TransformStatus, lambda s: s.ws_id)),
        bus.subscribe(
            f"{keys.prefix}/health/**",
            health.handler(ServiceHealth, lambda h: f"{h.service}/{h.zid}"),
        ),
    ]
    alive = bus.alive(f"{keys.prefix}/alive/**", timeout=min(window, 1.0))
    solved: dict[str, str] = {}
    for rep in bus.query(keys.any_ws("transform"), timeout=min(window, 2.0)):
        if rep.ok and rep.payload is not None:
            try:
                sol = decode(TransformSolution, rep.payload)
            except (ValidationError, ValueError):
                continue
            solved[sol.ws_id] = sol.revision
    time.sleep(window)
    for h in handles:
        h.close()
    services = []
    for key in alive:
        try:
            p = keys.parse(key)
        except KeyError_:
            continue
        services.append((p.ident, p.kind))
    return {
        "robots": robots.snapshot(),
        "poses": poses.snapshot(),
        "workspaces": ws_status.snapshot(),
        "solved": solved,
        "health": health.snapshot(),
        "alive": sorted(services),
    }


def format_status(seen: dict[str, Any]) -> str:
    lines = [f"services alive: {len(seen['alive'])}"]
    health: dict[str, ServiceHealth] = seen["health"]
    for name, zid in seen["alive"]:
        h = health.get(f"{name}/{zid}")
        if h is None:
            lines.append(f"  {name:<12} {zid}  (no health message yet)")
            continue
        counters = " ".join(f"{k}={v}" for k, v in sorted(h.counters.items()))
        lines.append(f"  {name:<12} {zid}  {h.state:<8} up {h.uptime_s:.0f} s  {counters}")
    ws_ids = sorted(set(seen["workspaces"]) | set(seen["solved"]))
    lines.append(f"workspaces: {len(ws_ids)}")
    for w in ws_ids:
        st: TransformStatus | None = seen["workspaces"].get(w)
        if st is not None:
            extra = f"  {st.message}" if st.message else ""
            lines.append(f"  {w:<16} {st.state:<8} revision {st.revision or '-'}{extra}")
        else:
            lines.append(f"  {w:<16} {'solved':<8} revision {seen['solved'][w]}")
    robots: dict[str, RobotStatus] = dict(seen["robots"])
    poses: dict[str, Pose] = seen.get("poses", {})
    for rid, pose in poses.items():  # the newest position; a robot no controller reports on
        known = robots.get(rid)
        if known is None:
            robots[rid] = RobotStatus(
                robot_id=rid,
                stamp_ns=time.time_ns(),
                state="idle",
                reason="no_goal",
                message="(poses only: no controller drives it)",
                position=(pose.x, pose.y),
            )
        else:  # a pose of this window is newer than the controller's last word
            robots[rid] = known.model_copy(update={"position": (pose.x, pose.y)})
    lines.append(f"robots: {len(robots)}")
    lines += ["  " + _robot_line(robots[r]) for r in sorted(robots)]
    return "\n".join(lines)


def _status(args: argparse.Namespace) -> int:
    keys = Keys(args.prefix)
    with _open(args) as bus:
        while True:
            text = format_status(collect_status(bus, keys, args.window))
            if args.watch:
                sys.stdout.write("\x1b[H\x1b[2J")
            print(text, flush=True)
            if not args.watch:
                return 0


# ------------------------------------------------------------------------------------------
# parser
# ------------------------------------------------------------------------------------------
def _common(p: argparse.ArgumentParser) -> None:
    add_zenoh_args(p)
    for action in p._actions:  # the shared flags, with a checked prefix
        if action.dest == "prefix":
            action.type = prefix
        if action.dest == "connect":
            action.help = f"router endpoint; none: {DEFAULT_ROUTER} (launch's)%(default).0s"
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=2.0,
        metavar="S",
        help="seconds to keep trying to reach the router",
    )


def register(subparsers: Any) -> None:
    fmt = HelpFormatter
    g = subparsers.add_parser(
        "goal",
        help="send a goal to a robot of a running system",
        formatter_class=fmt,
        epilog="example: confnav goal r1 0.6,0.2 --ws room --connect tcp/127.0.0.1:7447\n"
        "         confnav goal r1 -0.6,-0.2 --ws room (a negative point as it is)",
    )
    g.add_argument("robot", type=robot_id, metavar="ROBOT", help="robot id")
    g.add_argument("point", type=point, metavar="X,Y", help="goal position, m")
    g.add_argument("--ws", type=ws_id, default="default", help="workspace id")
    g.add_argument(
        "--navfn", default=defaults.NAVFN, choices=get_args(NavFnName), help="navigation function"
    )
    g.add_argument(
        "--k",
        type=float,
        default=None,
        help="navigation-function exponent, dimensionless (default: auto)",
    )
    g.add_argument("--gain", type=positive_float, default=defaults.GAIN, help="control gain, 1/s")
    g.add_argument("--v-max", type=positive_float, default=defaults.V_MAX, help="speed limit, m/s")
    g.add_argument("--vmax", dest="v_max", type=positive_float, help=argparse.SUPPRESS)
    g.add_argument(
        "--tolerance", type=positive_float, default=defaults.GOAL_TOL, help="arrival radius, m"
    )
    g.add_argument("--robot-radius", type=float, default=0.0, help="robot disc radius, m")
    g.add_argument("--drive", default="holonomic", choices=get_args(DriveName))
    g.add_argument(
        "--lookahead",
        type=positive_float,
        default=Goal.model_fields["lookahead"].default,
        help="unicycle look-ahead distance, m (the point that reaches the goal)",
    )
    g.add_argument(
        "--omega-max",
        type=positive_float,
        default=Goal.model_fields["omega_max"].default,
        help="unicycle yaw-rate limit, rad/s",
    )
    g.add_argument(
        "--speed-law",
        default=defaults.SPEED_LAW,
        choices=get_args(SpeedLawName),
        help="normalized or theorem2 (as confnav simulate)",
    )
    g.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds to wait for the robot to start navigating (while its map is being "
        "solved, counted from the newest status saying so)",
    )
    _common(g)
    g.set_defaults(func=_goal)

    c = subparsers.add_parser(
        "cancel",
        help="cancel a robot's goal (it stops and goes idle)",
        formatter_class=fmt,
        epilog="example: confnav cancel r1 --connect tcp/127.0.0.1:7447",
    )
    c.add_argument("robot", type=robot_id, metavar="ROBOT", help="robot id")
    _common(c)
    c.set_defaults(func=_cancel)

    s = subparsers.add_parser(
        "status",
        help="robots, workspaces, live services and their health counters",
        formatter_class=fmt,
        epilog="example: confnav status --watch --connect tcp/127.0.0.1:7447",
    )
    s.add_argument(
        "--window", type=float, default=1.5, metavar="S", help="seconds to listen per refresh"
    )
    s.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    _common(s)
    s.set_defaults(func=_status)
