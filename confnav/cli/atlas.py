"""``confnav atlas``: solve a workspace as an atlas of charts and navigate by composition.

``confnav atlas WS.json --goal=X,Y (--starts="X,Y;X,Y" | --random N --seed S) [--tol 1e-8]
[--workers 2] [--tile T] [--margin M] [--hysteresis H] [--v-max V]
[--robot-radius R] [--unicycle D [--omega-max W]] [--json OUT.json]``

Prints the cells (tile, obstacles, nodes, solve time) and the runs' summary: success,
collisions, chart switches, path length over the shortest path.  Exit 0 only if every robot
arrived without collision.

A robot of radius R (a unicycle: R + its look-ahead D) navigates in the free space shrunk by
it, so the atlas is solved for that shrunk workspace (as the services do for ``{ws}~r{R}``).
Disk robots run :meth:`AtlasNavigator.run` (the centre in the shrunk space: the body's
clearance is at least the one reported); unicycles each get their own switching controller
(:class:`confnav.atlas.wire.AtlasController`, what the controller service runs) under the
look-ahead law, moved by the exact unicycle integrator
(:func:`confnav.navigation.unicycle.simulate_unicycle`) with random headings from ``--seed``,
collisions and clearances those of the body in the original workspace.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from confnav.argtypes import output_path, positive_float, positive_int
from confnav.cli.jsonout import write_json
from confnav.cli.simulate import _point, _points
from confnav.navigation import defaults

if TYPE_CHECKING:
    from confnav.atlas import AtlasNavigator, AtlasRun


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "atlas",
        help="solve a large or corridor-rich workspace as an atlas and navigate through it",
        description="Decompose the free space into overlapping cells, solve each cell's "
        "conformal map in parallel, and simulate robots under the sequentially composed "
        "navigation laws (docs/ATLAS.md).",
    )
    p.add_argument("workspace", type=Path, help="workspace JSON/GeoJSON")
    p.add_argument("--goal", type=_point, required=True, help="goal X,Y, m (negative: --goal -1,2)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--starts", type=_points, help='starts "X,Y;X,Y;..." (one argument)')
    g.add_argument("--random", type=positive_int, metavar="N", help="N random starts in free space")
    p.add_argument("--seed", type=int, default=0, help="seed for --random")
    p.add_argument(
        "--tol",
        type=float,
        default=1e-8,
        help="accuracy of each chart's circle domain (dimensionless)",
    )
    p.add_argument("--workers", type=int, default=2, help="solver processes")
    p.add_argument("--tile", type=float, help="initial tile side, m (default 6 x inradius)")
    p.add_argument(
        "--margin",
        type=float,
        help="local-goal depth in overlaps, m (default: derived from the narrowest passage "
        "the cells cut through; one it cannot hold is an error naming it)",
    )
    p.add_argument("--hysteresis", type=float, help="switching depth, m (default margin/2)")
    p.add_argument(
        "--v-max",
        "--speed",
        dest="speed",
        type=positive_float,
        default=defaults.V_MAX,
        help="speed limit, m/s (as confnav simulate; --speed: the old name)",
    )
    p.add_argument("--robot-radius", type=float, default=0.0, help="disk robot radius, m")
    p.add_argument(
        "--unicycle", type=positive_float, metavar="D",
        help="differential drive with look-ahead distance D, m",
    )  # fmt: skip
    p.add_argument(
        "--omega-max", type=positive_float, default=2.0, help="unicycle yaw-rate limit, rad/s"
    )
    p.add_argument("--json", type=output_path, help="write cells, plan and runs here")
    p.add_argument(
        "--plot", type=output_path, help="write a figure with the cells and the paths here"
    )
    p.set_defaults(func=run_atlas)


def _navigation_workspace(args: argparse.Namespace, ws: Any) -> tuple[Any, float]:
    """The free space the atlas is made for (shrunk by the body: ``--robot-radius`` plus the
    unicycle's look-ahead) and the body's size; the goal and the starts are checked first
    (before a solve of minutes)."""
    from confnav.errors import NavigationError, fmt_point
    from confnav.maps.footprint import inflate

    if not (np.isfinite(args.robot_radius) and args.robot_radius >= 0):
        raise NavigationError(f"--robot-radius must be >= 0, got {args.robot_radius!r}")
    body = args.robot_radius + (args.unicycle or 0.0)  # the footprint shrinks the free space
    named = {f"start {k}": z for k, z in enumerate(args.starts or [])}
    for name, z in {"goal": args.goal, **named}.items():
        if not bool(ws.contains(np.array([z]))[0]):
            raise NavigationError(f"{name} {fmt_point(z)} is not in the workspace's free space")
    shrunk = getattr(args, "shrunk", None)  # simulate's, already inflated (and warned about)
    nav_ws = (
        shrunk
        if shrunk is not None
        else inflate(ws, body, keep=args.goal, require=named)
        if body
        else ws
    )
    return nav_ws, body


def _print_atlas(atlas: Any, nav_ws: Any, args: argparse.Namespace) -> None:
    """The cells' table and the thinnest overlap the cells need (the margin's limit)."""
    from confnav.errors import fmt_point

    print(
        f"atlas: {len(atlas.charts)} cells, solved in {atlas.wall_time:.2f} s "
        f"(charts {atlas.cpu_time:.2f} s, speed-up x{atlas.speedup:.2f})"
    )
    print(f"{'cell':>4} {'obst':>4} {'nodes':>6} {'time s':>7} {'error':>8}")
    for i, r in enumerate(atlas.chart_records):
        n_obs = atlas.decomposition.cells[i].workspace.n_obstacles
        print(f"{i:>4} {n_obs:>4} {r.n_nodes:>6} {r.wall_time:>7.2f} {r.error_estimate:>8.1e}")
    dec = atlas.decomposition
    thin = dec.passage
    if thin is not None:
        how = "given" if args.margin is not None else "automatic"
        w = 2 * float(nav_ws.clearance(np.array([thin.point]))[0])
        # the thinnest overlap is a passage of the free space or a sliver of two split cells:
        # say what was measured (its depth) and how wide the free space is there
        print(
            f"margin {dec.margin:.3g} m ({how}); thinnest overlap the cells need: "
            f"{thin.depth:.3g} m deep at {fmt_point(thin.point)}, where the free space is "
            f"{w:.3g} m wide"
        )


def _run_robots(
    nav: Any,
    atlas: Any,
    ws: Any,
    nav_ws: Any,
    starts: NDArray[np.complex128],
    body: float,
    args: argparse.Namespace,
    doc: dict[str, Any],
) -> int:
    """Drive robots from ``starts`` on the atlas (points, or unicycles with ``--unicycle``),
    print the outcome against the shortest paths, record every run in ``doc`` and draw
    ``--plot``; exit code 0 if all arrive without a collision."""
    from confnav.errors import fmt_point
    from confnav.navigation.shortest_path import ShortestPaths, path_ratio
    from confnav.navigation.sim import STATUS_NAMES

    plot = getattr(args, "plot", None)
    run = (
        nav.run(starts, record_paths=plot is not None)
        if args.unicycle is None
        else run_unicycles(nav, ws, starts, args, record_paths=plot is not None)
    )
    short = ShortestPaths(nav_ws, nav.goal).lengths(starts)
    ratio = path_ratio(run.path_length, short, nav.controller(nav.plan.goal_cells[0]).goal_tol)
    ok = run.success & np.isfinite(ratio)
    med = float(np.median(ratio[ok])) if ok.any() else float("nan")
    print(
        f"{starts.size} robots: {run.message}; collisions {int(run.collided.sum())}; "
        f"switches <= {int(run.switches.max())}; median path x{med:.3f} of shortest; "
        f"min clearance {float(run.min_clearance.min()):.3g} m"
        + (
            ""
            if not body
            else " (the body's)"
            if args.unicycle
            else " (of the centre in the shrunk space: the body's is at least this)"
        )
    )
    for k in np.flatnonzero(~run.success)[:10]:
        print(f"  robot {k} at {fmt_point(starts[k])}: {STATUS_NAMES[run.status[k]]}: "
              f"{run.reasons[k]}")  # fmt: skip
    doc["runs"] = [
        {
            "start": [complex(s).real, complex(s).imag],
            "status": STATUS_NAMES[int(st)],
            "reason": why,
            "path_length": float(pl),
            "shortest": float(sh),
            "cells": list(cs),
        }
        for s, st, why, pl, sh, cs in zip(
            starts, run.status, run.reasons, run.path_length, short, run.cells, strict=True
        )
    ]
    if plot is not None:
        from confnav.plot.atlas import save_atlas_figure

        out = save_atlas_figure(atlas, run, nav.goal, plot, walls=ws if body else None, shrink=body)
        print(f"plot written to {out}")
    return 0 if bool(run.success.all()) and not run.collided.any() else 1


def run_atlas(args: argparse.Namespace) -> int:
    """``confnav atlas``: solve the atlas of the (shrunk) workspace, print its cells, drive
    the robots asked for and write ``--json``."""
    from confnav.atlas import AtlasNavigator, solve_atlas
    from confnav.geometry import Workspace
    from confnav.scenes.scenarios import random_starts

    ws = Workspace.load(args.workspace)
    nav_ws, body = _navigation_workspace(args, ws)
    kw = {k: getattr(args, k) for k in ("tile", "margin") if getattr(args, k) is not None}
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"  [{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    with interruptible_pool(args.workers) as pool:
        atlas = solve_atlas(
            nav_ws, args.tol, workers=args.workers, progress=progress, executor=pool, **kw
        )
    _print_atlas(atlas, nav_ws, args)
    nav = AtlasNavigator(atlas, args.goal, hysteresis=args.hysteresis, speed=args.speed)
    doc: dict[str, Any] = {
        "cells": [
            {"tile": c.tile, "workspace": c.workspace.to_dict(), "rank": float(nav.plan.rank[i])}
            for i, c in enumerate(atlas.decomposition.cells)
        ],
        "solve_wall_s": atlas.wall_time,
        "chart_s": [r.wall_time for r in atlas.chart_records],
    }
    starts = (
        np.asarray(args.starts, dtype=np.complex128)
        if args.starts
        else random_starts(nav_ws, args.random, seed=args.seed, margin=0.05 + (args.unicycle or 0))
        if args.random
        else None
    )
    code = 0
    if starts is not None:
        code = _run_robots(nav, atlas, ws, nav_ws, starts, body, args, doc)
    if args.json:
        write_json(Path(args.json), doc)  # inf/NaN (no path, never measured) as null
    return code


@contextmanager
def interruptible_pool(workers: int) -> Iterator[ProcessPoolExecutor | None]:
    """The chart solvers' process pool (None for one worker: solved in this process), whose
    workers ignore SIGINT: on Ctrl-C (KeyboardInterrupt here) the queued charts are cancelled
    and the running ones' processes terminated at once, instead of finishing the charts they
    had started (13-23 s on a warehouse at tol 1e-12) while the terminal shows nothing."""
    if workers <= 1:
        yield None
        return
    pool = ProcessPoolExecutor(max_workers=workers, initializer=_ignore_sigint)
    try:
        _start_workers(pool)
        yield pool
    except BaseException:
        procs = list((pool._processes or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            proc.terminate()
        for proc in procs:
            proc.join(timeout=5.0)
        raise
    else:
        pool.shutdown()


def _start_workers(pool: ProcessPoolExecutor) -> None:
    """Fork the pool's workers now, with SIGINT blocked in this thread while it forks.

    A Ctrl-C that lands while ``os.fork`` runs the parent's at-fork hooks (logging's lock
    release) raises inside the hook, where CPython reports it as unraisable and drops it: the
    command would then ignore the Ctrl-C and solve on.  Blocked, the signal stays pending and
    is delivered when the mask is restored, here, as a KeyboardInterrupt.  The workers (and
    the pool's manager thread) inherit the blocked mask, and ignore SIGINT anyway
    (:func:`_ignore_sigint`)."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        pool.submit(int).result()  # the fork start method spawns every worker on first submit
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the parent (which stops them)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_unicycles(
    nav: AtlasNavigator,
    ws: Any,
    starts: np.ndarray,
    args: argparse.Namespace,
    *,
    record_paths: bool = False,
) -> AtlasRun:
    """Unicycles from ``starts`` (random headings from ``--seed``), one switching controller
    each (it holds the robot's active chart), as an :class:`AtlasRun`: collisions and
    clearances those of the body of ``--robot-radius`` in the original workspace ``ws``."""
    import time

    from confnav.atlas import AtlasRun
    from confnav.atlas.wire import AtlasController
    from confnav.navigation.sim import STATUS_NAMES
    from confnav.navigation.unicycle import UnicycleController, simulate_unicycle

    t0 = time.perf_counter()
    heads = np.random.default_rng(args.seed).uniform(-np.pi, np.pi, starts.size)
    t_max = 20 * nav.atlas.workspace.diameter / nav.speed  # as AtlasNavigator.run
    ctrls = [AtlasController(nav) for _ in range(starts.size)]
    runs = [
        simulate_unicycle(
            UnicycleController(c, args.unicycle, v_max=nav.speed, omega_max=args.omega_max),
            [z],
            [h],
            clearance=ws.clearance,
            radius=args.robot_radius,
            t_max=t_max,
            record_paths=record_paths,
        )
        for c, z, h in zip(ctrls, starts, heads, strict=True)
    ]

    def cat(name: str) -> Any:
        return np.concatenate([getattr(r, name) for r in runs])

    status = cat("status")

    return AtlasRun(
        starts=starts,
        success=cat("success"),
        collided=cat("collided"),
        status=status,
        path_length=cat("path_length"),
        time=cat("time"),
        min_clearance=cat("min_clearance"),
        final=cat("final"),
        switches=np.array([max(len(c.history) - 1, 0) for c in ctrls], dtype=np.int64),
        cells=tuple(tuple(c.history) for c in ctrls),
        wall_time=time.perf_counter() - t0,
        reasons=tuple(
            c.stop_reason[1] if c.stop_reason else STATUS_NAMES[int(st)]
            for c, st in zip(ctrls, status, strict=True)
        ),
        paths=tuple(r.paths[0] for r in runs if r.paths) if record_paths else None,
    )
