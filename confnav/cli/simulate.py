"""``confnav simulate`` and ``confnav figures``: drive robots with the Theorem 2 law.

``confnav simulate WS.json --goal=X,Y (--starts="X,Y;X,Y" | --random N --seed S)
[--navfn harmonic|kr] [--k auto|6] [--speed-law normalized|theorem2] [--gain G] [--v-max V]
[--json OUT.json] [--plot OUT.png] [--require RATE]``

Defaults are the library's (:mod:`confnav.navigation.defaults`): navigation succeeds without tuning
flags.  Prints a per-robot table (start, outcome, reason, time, path ratio, min clearance)
for up to 20 robots and the failures beyond; ``--require RATE`` exits 1 when the success rate
is below RATE.

``confnav figures [--out DIR]``: the seed's Fig. 2/3 (default workspace, four starts) for both
navigation functions.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from confnav.argtypes import output_path, positive_float, positive_int
from confnav.cli.jsonout import finite, write_json
from confnav.errors import ConfnavError, CrowdingError, NavigationError, fmt_point

log = logging.getLogger(__name__)

#: Time limit per robot when ``--t-max`` is not given (s): a unicycle's zero-order-hold
#: integration takes many more steps per simulated second than the adaptive point robot's.
T_MAX_POINT, T_MAX_UNICYCLE = 1e4, 1e3


def _point(text: str) -> complex:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y, got {text!r}") from None
    return complex(x, y)


def _points(text: str) -> list[complex]:
    parts = [p for p in text.replace(" ", "").split(";") if p]
    if not parts:
        raise argparse.ArgumentTypeError("expected X,Y;X,Y;...")
    return [_point(p) for p in parts]


def _k(text: str) -> float | str:
    if text == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--k must be a number or 'auto', got {text!r}") from None


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate kinematic robots under the conformal navigation law",
        description="Solve (or load) the map of a workspace and simulate x' = u(x) from "
        "given or random starts; report success, collisions and path-length ratios.",
    )
    p.add_argument("workspace", type=Path, help="workspace JSON/GeoJSON")
    p.add_argument("--goal", type=_point, required=True, help="goal X,Y (use --goal=X,Y)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--starts", type=_points, help='starts "X,Y;X,Y;..." (one argument)')
    g.add_argument("--random", type=positive_int, metavar="N", help="N random starts in free space")
    p.add_argument("--seed", type=int, default=0, help="seed for --random")
    p.add_argument("--map", type=Path, help="a solved map (JSON) instead of solving")
    p.add_argument(
        "--single-map",
        action="store_true",
        help="solve one map even where it would crowd (default: such a workspace, too "
        "elongated or with a region behind a long narrow passage, runs as `confnav atlas`)",
    )
    p.add_argument("--robot-radius", type=float, default=0.0, help="disk robot radius (m)")
    p.add_argument(
        "--unicycle",
        type=float,
        metavar="D",
        help="differential drive with look-ahead distance D, m",
    )
    p.add_argument(
        "--omega-max", type=positive_float, default=2.0, help="unicycle yaw-rate limit, rad/s"
    )
    _law_options(p)
    p.add_argument(
        "--t-max",
        type=positive_float,
        default=None,
        help=f"time limit per robot, s (default: {T_MAX_POINT:g} s, {T_MAX_UNICYCLE:g} s for "
        "unicycles)",
    )
    p.add_argument(
        "--require",
        type=float,
        metavar="RATE",
        help="exit 1 if the success rate (0..1) is below RATE",
    )
    p.add_argument("--json", type=output_path, help="write runs and summary here")
    p.add_argument("--plot", type=output_path, help="write a figure with the trajectories here")
    p.set_defaults(func=run_simulate)

    f = subparsers.add_parser(
        "figures",
        help="the seed's Fig. 2/3: level sets and trajectories, KR and harmonic",
        description="Level sets of phi(T(x)) in the workspace and of phi in the circle "
        "domain with the trajectories from the seed's four starts, for both navigation "
        "functions, on the default workspace (or WS.json with --goal/--starts).",
    )
    f.add_argument("workspace", type=Path, nargs="?", help="workspace (default: the seed's)")
    f.add_argument("--goal", type=_point, help="goal X,Y")
    f.add_argument("--starts", type=_points, help='starts "X,Y;X,Y;..."')
    f.add_argument("--k", type=_k, default=6.0, help="k for KR (default 6, the seed's)")
    f.add_argument("--gain", type=positive_float, default=1.0, help="control gain, 1/s")
    f.add_argument("--out", type=Path, default=Path("."), help="output directory")
    f.set_defaults(func=run_figures)


def _law_options(p: argparse.ArgumentParser) -> None:
    from confnav.navigation import defaults

    p.add_argument(
        "--navfn",
        choices=("harmonic", "kr"),
        default=defaults.NAVFN,
        help="navigation function (default %(default)s: tuning-free)",
    )
    p.add_argument(
        "--k",
        type=_k,
        default="auto",
        help="k of KR, dimensionless: a number (seed: 6) or auto (default)",
    )
    p.add_argument(
        "--speed-law",
        choices=defaults.SPEED_LAWS,
        default=defaults.SPEED_LAW,
        help="normalized: unit direction times min(v_max, gain*distance) (default); "
        "theorem2: the plain law -gain conj(T') grad phi saturated at v_max",
    )
    p.add_argument(
        "--gain",
        type=positive_float,
        default=defaults.GAIN,
        help="1/s for normalized, K for theorem2 (default %(default)s)",
    )
    p.add_argument(
        "--v-max",
        type=positive_float,
        default=defaults.V_MAX,
        help="speed limit, m/s (default %(default)s)",
    )
    p.add_argument("--vmax", dest="v_max", type=positive_float, help=argparse.SUPPRESS)  # old name
    p.add_argument(
        "--tolerance",
        type=positive_float,
        default=defaults.GOAL_TOL,
        help="arrival radius around the goal, m (default %(default)s)",
    )
    # old name (--tol means the map's accuracy in solve and atlas)
    p.add_argument("--tol", dest="tolerance", type=positive_float, help=argparse.SUPPRESS)


def _load_map(args: argparse.Namespace, ws: Any) -> Any:
    import confnav
    from confnav.conformal.solver import crowding_reason

    if getattr(args, "map", None):
        cmap = confnav.ConformalMap.from_json(Path(args.map).read_text())
        cmap.check_workspace(ws)  # a map of another workspace: MapMismatchError, exit != 0
        return cmap.for_navigation()
    t0 = time.perf_counter()
    print(f"solving the conformal map of {ws.n_obstacles} obstacles...", file=sys.stderr)

    def progress(msg: str) -> None:
        print(f"  [{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    solved = confnav.solve(ws, progress=progress)
    print(f"map solved in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    crowded = crowding_reason(solved.diagnostics)
    if crowded and not args.single_map:  # accurate on the circles, useless where it crowds
        raise CrowdingError(f"the solved map crowds ({crowded})")
    return solved.for_navigation()


#: Tolerance of the probe map :func:`_coarse_verdict` solves before the full map (the first
#: revision the transform service publishes, services/definitions.py ``LADDER``).
PROBE_TOL = 1e-3


def _coarse_verdict(args: argparse.Namespace, nav_ws: Any) -> str:
    """Why one map will not do, read off a coarse map (tol :data:`PROBE_TOL`, about a second)
    before the full solve ("" when the coarse map sees no reason or cannot be had).

    Real SLAM maps (docs/SLAM.md) were solved to 1e-10 for minutes, only for the finished map
    to show a navigation function flat at the starts; crowding and that flatness are
    properties of the circle domain's geometry (a decay by 10^12 along corridors), which a
    1e-3 map already shows. The full map is still checked for both afterwards."""
    import warnings

    import confnav
    from confnav.conformal.solver import AccuracyWarning, crowding_reason

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AccuracyWarning)
            probe = confnav.solve(nav_ws, PROBE_TOL, max_error=10 * PROBE_TOL)
    except CrowdingError as exc:
        return f"one map crowds ({exc})"
    except ConfnavError:
        return ""  # no usable coarse map: the full solve decides, as before
    crowded = crowding_reason(probe.diagnostics)
    if crowded:
        return f"a coarse map crowds ({crowded})"
    starts, _ = _starts(args, nav_ws)
    return _flat_starts(_controller(args, probe.for_navigation()), starts)


def _as_atlas(args: argparse.Namespace, nav_ws: Any) -> int:
    """Run ``confnav atlas`` with this command's options (robots, body, speed limit, JSON)."""
    from confnav.cli.atlas import run_atlas
    from confnav.navigation import defaults

    unused = [
        name
        for name, given, default in (
            ("--navfn", args.navfn, defaults.NAVFN),
            ("--k", args.k, "auto"),
            ("--speed-law", args.speed_law, defaults.SPEED_LAW),
            ("--gain", args.gain, defaults.GAIN),
            ("--tolerance", args.tolerance, defaults.GOAL_TOL),
        )
        if given != default
    ]
    if unused:
        print(f"note: {', '.join(unused)} not used by the atlas run", file=sys.stderr)
    atlas_args = argparse.Namespace(
        workspace=args.workspace, goal=args.goal, starts=args.starts, random=args.random,
        seed=args.seed, tol=1e-8, workers=2, tile=None, margin=None, hysteresis=None,
        speed=args.v_max, robot_radius=args.robot_radius, unicycle=args.unicycle,
        omega_max=args.omega_max, json=args.json, shrunk=nav_ws, plot=args.plot,
    )  # fmt: skip
    return int(run_atlas(atlas_args))


def run_simulate(args: argparse.Namespace) -> int:
    """``confnav simulate``: the steps below, in order (each a function of this module)."""
    from confnav.geometry import Workspace

    _check_options(args)
    ws = Workspace.load(args.workspace)
    body = args.robot_radius + (args.unicycle or 0.0)  # the footprint shrinks the free space
    nav_ws = _navigable_space(args, ws, body)
    if not args.map and _crowds_one_map(args, nav_ws):
        return _as_atlas(args, nav_ws)
    if not (args.map or args.single_map):
        why = _coarse_verdict(args, nav_ws)
        if why:
            print(f"note: {why}: navigating it as an atlas (confnav atlas; --single-map "
                  "forces one map)", file=sys.stderr)  # fmt: skip
            return _as_atlas(args, nav_ws)
    try:
        cmap = _load_map(args, nav_ws)
    except CrowdingError as exc:  # found mid-solve, not by the a-priori test
        if args.map or args.single_map:
            raise
        print(f"note: one map crowds ({exc}): navigating it as an atlas (confnav atlas; "
              "--single-map forces one map)", file=sys.stderr)  # fmt: skip
        return _as_atlas(args, nav_ws)
    ctl = _controller(args, cmap)
    starts, headings = _starts(args, nav_ws)
    flat = _flat_starts(ctl, starts)
    if flat and not (args.map or args.single_map):
        print(f"note: {flat}: navigating it as an atlas (confnav atlas; --single-map forces "
              "one map)", file=sys.stderr)  # fmt: skip
        return _as_atlas(args, nav_ws)
    res = _drive(args, ctl, ws, starts, headings)
    runs, ratios = _runs(args, ctl, nav_ws, res)
    summary, params = _summary(res, ratios, runs), _params(args, ctl)
    _print_report(runs, summary, params, ctl)
    if args.json:
        doc = {"workspace": str(args.workspace), "params": params, "summary": summary,
               "runs": runs}  # fmt: skip
        write_json(Path(args.json), doc)
    if args.plot:
        _plot(args, ctl, ws, res, runs, summary, body)
    if args.require is not None and res.success_rate < args.require:
        print(
            f"FAIL: success rate {res.success_rate:.4f} is below --require {args.require:g}",
            file=sys.stderr,
        )
        return 1
    return 0


def _check_options(args: argparse.Namespace) -> None:
    """Option values argparse cannot check alone; resolves the default ``--t-max``."""
    if args.require is not None and not 0 <= args.require <= 1:
        raise NavigationError("--require needs a rate in [0, 1]")
    if args.random is not None and args.random < 1:
        raise NavigationError("--random needs N >= 1")
    if args.unicycle is not None and not (np.isfinite(args.unicycle) and args.unicycle > 0):
        raise NavigationError(f"--unicycle needs a look-ahead distance > 0, got {args.unicycle!r}")
    if args.t_max is None:
        args.t_max = T_MAX_UNICYCLE if args.unicycle else T_MAX_POINT


def _navigable_space(args: argparse.Namespace, ws: Any, body: float) -> Any:
    """The workspace of the steered point: ``ws`` shrunk by radius + look-ahead, keeping the
    goal's component; every given start must lie in it (``UnreachableGoalError`` otherwise)."""
    from confnav.maps.footprint import inflate

    if not body:
        return ws
    named = {f"start {k}": z for k, z in enumerate(args.starts or [])}
    return inflate(ws, body, keep=args.goal, require=named)


def _crowds_one_map(args: argparse.Namespace, nav_ws: Any) -> bool:
    """The a-priori test (under a second): True if the workspace should run as an atlas."""
    from confnav.atlas.charts import atlas_reason

    # a loop around an obstacle is no channel: such a room keeps its single map
    why = atlas_reason(nav_ws, loops=True)
    if why and not args.single_map:
        print(f"note: {why}: navigating it as an atlas (confnav atlas; "
              "--single-map forces one map)", file=sys.stderr)  # fmt: skip
        return True
    if why:
        print(f"warning: {why}; the single map may fail", file=sys.stderr)
    elif atlas_reason(nav_ws):
        print("note: elongated, but around obstacles: solving one map", file=sys.stderr)
    return False


def _controller(args: argparse.Namespace, cmap: Any) -> Any:
    from confnav.navigation.control import Controller

    ctl = Controller(
        cmap,
        args.goal,
        navfn=args.navfn,
        k=args.k,
        speed_law=args.speed_law,
        gain=args.gain,
        v_max=args.v_max,
        goal_tol=args.tolerance,
    )
    if ctl.fallback:
        print(f"note: {ctl.fallback}", file=sys.stderr)
    if args.navfn == "kr" and args.k != "auto":
        cp = ctl.check()
        if not cp.ok:
            print(
                f"warning: k={args.k:g} is too small for this geometry ({cp.message}); "
                "use --k auto or --navfn harmonic",
                file=sys.stderr,
            )
    return ctl


#: ``1 - phi`` of the harmonic navigation function below which its gradient is rounding noise:
#: phi = exp(2 G), 1 - phi ~ 2 |G|, with the Green's function G of the goal, which decays
#: exponentially along corridors (like exp(-pi L / w) for a corridor of length L and width w;
#: docs/METHOD.md on crowding), so far from the goal G falls below double precision. Seen on a
#: warehouse whose shelf rows a 0.3 m footprint merges into long aisles: the starts with
#: 1 - phi at rounding level crawled until the time limit, the others arrived.
FLAT_PHI = 1e-12


def _flat_starts(ctl: Any, starts: np.ndarray) -> str:
    """Why the navigation function cannot steer from some of ``starts`` ("" if it can): the
    harmonic phi = exp(2 G) within :data:`FLAT_PHI` of 1 there (an atlas's charts are short,
    so their Green's functions stay well above rounding)."""
    law = getattr(ctl, "controller", ctl)
    if getattr(getattr(law, "navfn", None), "name", "") != "harmonic":
        return ""
    phi = np.asarray(law(np.asarray(starts, dtype=complex)).phi, dtype=float)
    flat = np.flatnonzero(1.0 - phi < FLAT_PHI)
    if flat.size == 0:
        return ""
    z = complex(starts[flat[0]])
    return (
        f"the navigation function is flat at {flat.size} of {len(starts)} starts (1 - phi < "
        f"{FLAT_PHI:.0e}, e.g. at {fmt_point(z)}: the goal's Green's function decays below "
        "double precision along the corridors between)"
    )


def _starts(args: argparse.Namespace, nav_ws: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The starts and, for unicycles, their headings (uniform, from ``--seed``). A unicycle
    whose look-ahead point lies outside the navigable space cannot be steered: refused here,
    naming the start, why, and the nearest start that works with every heading."""
    from confnav.scenes.scenarios import random_starts

    d = args.unicycle
    if args.random is not None:
        # margin d + 5 cm: the look-ahead point is inside whatever the heading
        starts = random_starts(nav_ws, args.random, args.seed, margin=0.05 + (d or 0))
    else:
        starts = np.array(args.starts, dtype=np.complex128)
    if d is None:
        return starts, None
    headings = np.random.default_rng(args.seed).uniform(-np.pi, np.pi, starts.size)
    _check_look_ahead(nav_ws, starts, headings, float(d), args.robot_radius)
    return starts, headings


def _check_look_ahead(
    nav_ws: Any, starts: np.ndarray, headings: np.ndarray, d: float, radius: float
) -> None:
    """``NavigationError`` for the first start whose look-ahead point is not strictly inside
    the navigable space (the free space shrunk by radius + d)."""
    from confnav.maps.footprint import EDGE_RTOL, shrink_free_space
    from confnav.navigation.unicycle import look_ahead_point

    p = look_ahead_point(starts, headings, d)
    depth = np.asarray(nav_ws.clearance(p), dtype=float)
    bad = np.flatnonzero(~(depth > EDGE_RTOL * nav_ws.diameter))
    if bad.size == 0:
        return
    k = int(bad[0])
    here = float(np.asarray(nav_ws.clearance(starts[k : k + 1]))[0])
    try:  # every heading works from a start more than d inside the navigable space
        near, _ = shrink_free_space(nav_ws, 1.001 * d).nearest(complex(starts[k]))
        hint = f"; the nearest start that works with any heading is {fmt_point(near)}"
    except ConfnavError:
        hint = ""
    raise NavigationError(
        f"start {k} {fmt_point(complex(starts[k]))}: its look-ahead point "
        f"{fmt_point(complex(p[k]))} (heading {np.degrees(headings[k]):.0f} deg, {d:g} m "
        f"ahead) is outside the navigable space (the free space shrunk by the radius "
        f"{radius:g} m plus the look-ahead {d:g} m), so it cannot be steered; the start is "
        f"{here:.3g} m inside that space and needs more than {d:g} m"
        + f" ({len(bad)} of {starts.size} starts)" * (len(bad) > 1)
        + hint
    )


def _drive(
    args: argparse.Namespace, ctl: Any, ws: Any, starts: np.ndarray, headings: np.ndarray | None
) -> Any:
    """Integrate the robots for at most ``--t-max`` each; collisions are the body's in ``ws``."""
    from confnav.navigation.sim import simulate
    from confnav.navigation.unicycle import UnicycleController, simulate_unicycle

    if headings is None:
        return simulate(
            ctl,
            starts,
            clearance=lambda z: ws.clearance(z) - args.robot_radius,
            t_max=args.t_max,
            record_paths=args.plot is not None,
        )
    uc = UnicycleController(ctl, float(args.unicycle), v_max=ctl.v_max, omega_max=args.omega_max)
    return simulate_unicycle(
        uc,
        starts,
        headings,
        clearance=ws.clearance,
        radius=args.robot_radius,
        dt=0.02,
        t_max=args.t_max,
        record_paths=args.plot is not None,
    )


def _runs(
    args: argparse.Namespace, ctl: Any, nav_ws: Any, res: Any
) -> tuple[list[dict[str, Any]], np.ndarray]:
    """Per-robot dicts (JSON-ready: None where a value is undefined) and the path ratios."""
    from confnav.navigation.shortest_path import ShortestPaths, path_ratio
    from confnav.navigation.unicycle import UnicycleResult, look_ahead_point

    runs = [r.to_dict() for r in res.runs()]
    if isinstance(res, UnicycleResult):
        # the look-ahead point is what is steered to the goal: its path against the shortest
        # from where it starts (the axle's path ends d short of the goal: ratios below 1)
        origin = look_ahead_point(res.starts, res.headings, float(args.unicycle))
        length = res.point_length
        for r, q in zip(runs, length, strict=True):
            r["point_path_length"] = float(q)
    else:
        origin, length = res.starts, res.path_length
    shortest = ShortestPaths(nav_ws, ctl.goal).lengths(origin)
    ratios = path_ratio(length, shortest, ctl.goal_tol)
    for i, (r, s, q) in enumerate(zip(runs, shortest, ratios, strict=True)):
        r["shortest_path"] = finite(s)  # None: no path (another component)
        r["path_ratio"] = finite(q) if r["success"] else None
        for key in ("min_clearance", "final_distance", "time", "path_length", "max_speed"):
            r[key] = finite(r[key])  # None: undefined (e.g. a robot that never moved)
        if not r["success"] and not r.get("reason"):
            r["reason"] = _reason(args, ctl, res, i)
    return runs, np.asarray(ratios, dtype=float)


def _reason(args: argparse.Namespace, ctl: Any, res: Any, i: int) -> str:
    """A reason for a failed run whose integrator gave none (never an empty reason)."""
    from confnav.navigation.sim import STATUS_NAMES
    from confnav.navigation.unicycle import look_ahead_point

    status = STATUS_NAMES[int(res.status[i])]
    if status == "timeout":
        return f"time limit {args.t_max:g} s reached (--t-max), {res.final_distance[i]:.3g} m short"
    if status == "collided":
        return "the body touched an obstacle or wall"
    if status == "stalled":
        return "no progress (a critical point of the navigation function or a held command)"
    if not (np.isfinite(res.final[i]) and np.isfinite(res.time[i])):
        return (
            f"the robot's state became non-finite after {int(res.n_steps[i])} steps (a "
            "non-finite command; the integrator stopped it)"
        )
    if args.unicycle:
        theta = res.final_theta[i : i + 1]
        p = complex(look_ahead_point(res.final[i : i + 1], theta, float(args.unicycle))[0])
        return (
            f"the controller refused the look-ahead point {fmt_point(p)} (outside the map's "
            f"domain or a non-finite command) at t = {res.time[i]:.3g} s"
        )
    return (
        f"the controller refused the position {fmt_point(complex(res.final[i]))} (outside "
        f"the map's domain or a non-finite command) at t = {res.time[i]:.3g} s"
    )


def _summary(res: Any, ratios: np.ndarray, runs: list[dict[str, Any]]) -> dict[str, Any]:
    ratio = ratios[res.success & np.isfinite(ratios)]
    clear = [r["min_clearance"] for r in runs if r["min_clearance"] is not None]
    return {
        "n": int(res.starts.size),
        "success_rate": finite(res.success_rate),
        "collisions": int(res.collided.sum()),
        "stalled": int((res.status == 2).sum()),
        "timeouts": int((res.status == 3).sum()),
        "errors": int((res.status == 4).sum()),
        "median_path_ratio": float(np.median(ratio)) if ratio.size else None,
        "median_time": float(np.median(res.time[res.success])) if res.success.any() else None,
        "min_clearance": min(clear) if clear else None,
        "wall_time": res.wall_time,
    }


def _params(args: argparse.Namespace, ctl: Any) -> dict[str, Any]:
    return {
        "navfn": ctl.navfn.name,
        "k": getattr(ctl.navfn, "k", None),
        "fallback": ctl.fallback or None,
        "speed_law": ctl.speed_law,
        "gain": ctl.gain,
        "v_max": finite(ctl.v_max),  # None: no speed limit
        "goal": [ctl.goal.real, ctl.goal.imag],
        "goal_tol": ctl.goal_tol,
        "t_max": args.t_max,
    }


def _print_report(
    runs: list[dict[str, Any]], summary: dict[str, Any], params: dict[str, Any], ctl: Any
) -> None:
    print(run_table(runs))
    rate = summary["success_rate"]
    print(
        f"{summary['n']} robots, {params['navfn']}"
        + (f" k={params['k']:g}" if params["k"] is not None else "")
        + f", {ctl.speed_law} law: success "
        + ("n/a" if rate is None else f"{100 * rate:.1f}%")
        + f", collisions {summary['collisions']}, stalled {summary['stalled']}, timeouts "
        f"{summary['timeouts']}, errors {summary['errors']}, median path ratio "
        + (f"{summary['median_path_ratio']:.3f}" if summary["median_path_ratio"] else "n/a")
    )


def _plot(
    args: argparse.Namespace,
    ctl: Any,
    ws: Any,
    res: Any,
    runs: list[dict[str, Any]],
    summary: dict[str, Any],
    body: float,
) -> None:
    from confnav.plot.navigation import save_navigation_figure

    save_navigation_figure(
        ctl,
        res.paths or (),
        args.plot,
        title=f"{args.workspace}: {100 * res.success_rate:.1f}% of {summary['n']} arrived",
        outcomes=[r["status"] for r in runs],
        walls=ws if body else None,
        shrink=body,
    )


TABLE_ROWS = 20


def run_table(runs: list[dict[str, Any]], max_rows: int = TABLE_ROWS) -> str:
    """Per-robot table (start, outcome, reason, time, path ratio, min clearance) for the first
    ``max_rows`` robots, then one line per failure beyond them."""
    head = ("#", "start [m]", "outcome", "time [s]", "path ratio", "min clear [m]", "reason")
    rows: list[tuple[str, ...]] = [head]
    for i, r in enumerate(runs[:max_rows]):
        rows.append(_row(i, r))
    widths = [max(len(row[c]) for row in rows) for c in range(len(head) - 1)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row[:-1], widths, strict=True)) + "  " + row[-1]
             for row in rows]  # fmt: skip
    lines.insert(1, "-" * len(lines[0]))
    failed = [(i, r) for i, r in enumerate(runs) if i >= max_rows and not r["success"]]
    if len(runs) > max_rows:
        lines.append(
            f"... {len(runs) - max_rows} more robots, {len(failed)} of them failed"
            + (":" if failed else "")
        )
        lines += ["  " + "  ".join(_row(i, r)) for i, r in failed]
    return "\n".join(lines)


def _row(i: int, r: dict[str, Any]) -> tuple[str, ...]:
    ratio = r.get("path_ratio")
    return (
        str(i),
        f"({r['start'][0]:.2f}, {r['start'][1]:.2f})",
        r["status"],
        "-" if r["time"] is None else f"{r['time']:.1f}",
        "-" if ratio is None else f"{ratio:.3f}",
        "-" if r["min_clearance"] is None else f"{r['min_clearance']:.3f}",
        r.get("reason", ""),
    )


def run_figures(args: argparse.Namespace) -> int:
    from confnav.geometry import Workspace
    from confnav.navigation.control import Controller
    from confnav.navigation.sim import simulate
    from confnav.plot.navigation import save_navigation_figure
    from confnav.scenes.workspaces import DEFAULT_GOAL, DEFAULT_STARTS, default_workspace

    ws = Workspace.load(args.workspace) if args.workspace else default_workspace()
    goal = args.goal if args.goal is not None else DEFAULT_GOAL
    starts = np.array(args.starts if args.starts else DEFAULT_STARTS, dtype=np.complex128)
    cmap = _load_map(args, ws)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in ("kr", "harmonic"):
        ctl = Controller(cmap, goal, navfn=name, k=args.k, gain=args.gain)
        res = simulate(ctl, starts, t_max=1e6, atol=1e-6, max_step=0.02, record_paths=True)
        label = f"{name}" + (f" k={ctl.navfn.k:g}" if name == "kr" else "")  # type: ignore[attr-defined]
        out = save_navigation_figure(
            ctl, res.paths or (), args.out / f"navigation_{name}.png", title=label
        )
        print(f"{out}: {res.message}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="confnav")
    register(parser.add_subparsers())
    a = parser.parse_args()
    sys.exit(a.func(a))
