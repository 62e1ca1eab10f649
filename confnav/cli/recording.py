"""CLI of recordings: ``confnav replay``, ``confnav inspect``, ``confnav recover``, ``confnav viz``.

Registered by :mod:`confnav.cli.app` through :func:`register`. Every command exits 0 on success and
non-zero with a one-line message (no traceback) for a bad file; ``replay --check`` exits 1 when
a recomputed command differs from the recorded one.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from confnav.argtypes import output_path
from confnav.errors import ConfnavError

logger = logging.getLogger(__name__)


def register(subparsers: Any) -> None:
    """Add ``replay``, ``inspect``, ``recover`` and ``viz`` to the ``confnav`` parser."""
    _add_replay(subparsers)
    _add_inspect(subparsers)
    _add_recover(subparsers)
    _add_viz(subparsers)


def _add_replay(subparsers: Any) -> None:
    from confnav.recording.replay_check import DEFAULT_ATOL, DEFAULT_RTOL
    from confnav.services.runtime import add_zenoh_args

    p: argparse.ArgumentParser = subparsers.add_parser(
        "replay",
        help="republish a recording on Zenoh, or --check it against the controller code",
        description="Republish the messages of FILE.mcap on Zenoh with their recorded timing "
        "(or as fast as possible), under the prefix replay/PREFIX (never driving a live "
        "system), onto the recorded keys with --live, or under --prefix. With --check: "
        "recompute every recorded command from the recorded maps, goals and poses through the "
        "controller's code (no Zenoh) and exit 1 if any differs.",
    )
    p.add_argument("file", metavar="FILE.mcap")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument(
        "--speed", type=float, default=1.0, help="playback rate (default %(default)s)"
    )
    timing.add_argument("--max", action="store_true", help="as fast as possible")
    p.add_argument(
        "--include",
        action="append",
        default=[],
        metavar="KEYEXPR",
        help="replay only recorded keys matching (repeatable; default: all but alive/viz)",
    )
    p.add_argument(
        "--exclude", action="append", default=[], metavar="KEYEXPR", help="skip matching keys"
    )
    p.add_argument(
        "--inputs-only",
        action="store_true",
        help="replay only definitions, transforms, goals and poses (drive a live controller)",
    )
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=1.0,
        metavar="S",
        help="wait up to S seconds for subscribers on the replayed keys (default %(default)s)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="replay onto the recorded keys: drives a running system's controller and robots",
    )
    p.add_argument(
        "--no-serve-maps",
        action="store_true",
        help="do not answer transform/atlas/chart queries from the recording while replaying",
    )
    add_zenoh_args(p)
    p.set_defaults(prefix=None)  # replay: default replay/PREFIX, --prefix remaps, --live none
    for action in p._actions:
        if action.dest == "prefix":
            action.help = "replay under this key prefix (default: replay/ + the recorded one)"
    chk = p.add_argument_group("check")
    chk.add_argument(
        "--check", action="store_true", help="recompute and compare the commands (no Zenoh)"
    )
    chk.add_argument(
        "--atol", type=float, default=DEFAULT_ATOL, help="absolute tolerance, m/s (%(default)g)"
    )
    chk.add_argument(
        "--rtol",
        type=float,
        default=DEFAULT_RTOL,
        help="relative tolerance, dimensionless (%(default)g)",
    )
    chk.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        dest="overrides",
        help="recompute with a changed goal parameter (gain, v_max, k, navfn, tolerance)",
    )
    chk.add_argument(
        "--max-report", type=int, default=10, metavar="N", help="mismatches listed (10)"
    )
    p.set_defaults(func=cmd_replay)


def _add_inspect(subparsers: Any) -> None:
    i = subparsers.add_parser(
        "inspect",
        help="summarise a recording (channels, robots, arrival, clearance), --plot it",
    )
    i.add_argument("file", metavar="FILE.mcap")
    i.add_argument(
        "--plot", type=output_path, metavar="OUT.png", help="draw the trajectories on the workspace"
    )
    i.add_argument("--json", action="store_true", help="print the summary as JSON")
    i.set_defaults(func=cmd_inspect)


def _add_recover(subparsers: Any) -> None:
    r = subparsers.add_parser(
        "recover", help="rewrite a recording left without footer into a valid indexed MCAP"
    )
    r.add_argument("file", metavar="FILE.mcap")
    r.add_argument(
        "-o",
        "--output",
        type=output_path,
        metavar="OUT.mcap",
        help="default: FILE.recovered.mcap beside FILE",
    )
    r.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    r.set_defaults(func=cmd_recover)


def _add_viz(subparsers: Any) -> None:
    v = subparsers.add_parser(
        "viz", help="copy a recording adding the Foxglove scene channels (opens in Foxglove)"
    )
    v.add_argument("file", metavar="FILE.mcap")
    v.add_argument("-o", "--output", type=output_path, metavar="OUT.mcap", required=True)
    v.add_argument(
        "--period", type=float, default=0.1, metavar="S", help="scene period, s (%(default)s)"
    )
    v.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    v.set_defaults(func=cmd_viz)


def _exists_guard(path: str, force: bool) -> None:
    from pathlib import Path

    if Path(path).exists() and not force:
        raise ConfnavError(f"{path} exists (use --force to overwrite)")


def cmd_replay(args: argparse.Namespace) -> int:
    if args.check:
        from confnav.recording.replay_check import check_recording, parse_overrides

        check = check_recording(
            args.file,
            atol=args.atol,
            rtol=args.rtol,
            overrides=parse_overrides(args.overrides),
        )
        print(check.format(max_report=args.max_report))
        return 0 if check.ok else 1

    import zenoh

    from confnav.services.bus import zenoh_config
    from confnav.services.replay import replay
    from confnav.services.runtime import stop_on_signals

    speed = None if args.max else args.speed
    try:
        conf = zenoh_config(args.mode, args.listen, args.connect, args.zenoh_config)
        with stop_on_signals() as stop:
            report = replay(
                args.file,
                conf,
                speed=speed,
                include=args.include,
                exclude=args.exclude,
                prefix=args.prefix,
                wait_subscribers=args.wait_subscribers,
                stop=stop,
                inputs_only=args.inputs_only,
                live=args.live,
                serve_maps=not args.no_serve_maps,
            )
    except zenoh.ZError as exc:
        print(f"confnav replay: zenoh error: {exc}", file=sys.stderr)
        return 1
    print(report.summary())
    return 130 if report.interrupted else 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from confnav.plot.recording import plot_recording
    from confnav.recording.inspect import inspect_recording, report_json

    report = inspect_recording(args.file)
    print(report_json(report) if args.json else report.format())
    if args.plot:
        path = plot_recording(report, args.plot)
        if not args.json:
            print(f"\nplot: {path}")
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    from pathlib import Path

    from confnav.recording.recover import recover

    src = Path(args.file)
    out = args.output or str(src.with_name(src.stem + ".recovered.mcap"))
    _exists_guard(out, args.force)
    report = recover(src, out)
    print(report.summary())
    return 0


def cmd_viz(args: argparse.Namespace) -> int:
    from confnav.recording.scene_writer import add_scene_channels

    _exists_guard(args.output, args.force)
    if not args.period >= 0:
        raise ConfnavError("--period must be >= 0")
    report = add_scene_channels(args.file, args.output, period_ns=int(args.period * 1e9))
    scenes = ", ".join(f"{t}: {n}" for t, n in sorted(report.scene_messages.items()))
    print(
        f"{report.output}: {report.messages_copied} messages copied, scene messages: "
        f"{scenes or 'none (no workspace definition or transform recorded)'}"
    )
    if report.errors:
        print(f"messages not drawn (see the log): {dict(report.errors)}")
    return 0


__all__ = ["register"]
