"""The ``confnav`` command line: one subcommand per job, registered by the module that owns it.

Each module in :data:`SUBCOMMAND_MODULES` exposes ``register(subparsers)``, which adds its
subcommands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from confnav import __version__
from confnav.errors import ConfnavError

SUBCOMMAND_MODULES: tuple[str, ...] = (
    "confnav.cli_solve",
    "confnav.cli_simulate",
    "confnav.cli_import_map",
    "confnav.cli_atlas",
    "confnav.services.cli",
    "confnav.services.cli_replay",
    "confnav.cli_ops",
)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Every option's help shows its default; the epilog (examples) keeps its line breaks."""


def output_path(text: str) -> str:
    """An argparse ``type=`` for files a command writes: the directory must exist, checked at
    parse time so a mistake costs one line, not the whole computation."""
    parent = os.path.dirname(os.path.abspath(text))
    if not os.path.isdir(parent):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: no directory {parent!r}")
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: it is a directory")
    if not os.access(parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: {parent!r} is not writable")
    return text


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="confnav",
        description="Conformal navigation in polygonal workspaces: solve maps, simulate, "
        "run the Zenoh services, record and replay.",
    )
    parser.add_argument("--version", action="version", version=f"confnav {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a module still being written; real errors surface
            if exc.name != name:
                raise
            continue
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except ConfnavError as exc:
        print(f"confnav {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
