"""The ``confnav`` command line: one subcommand per job, registered by the module that owns it.

Each module in :data:`SUBCOMMAND_MODULES` exposes ``register(subparsers)``, which adds its
subcommands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from confnav import __version__
from confnav.errors import ConfnavError

SUBCOMMAND_MODULES: tuple[str, ...] = (
    "confnav.cli.solve",
    "confnav.cli.simulate",
    "confnav.cli.import_map",
    "confnav.cli.atlas",
    "confnav.cli.services",
    "confnav.cli.recording",
    "confnav.cli.ops",
)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Every option's help shows its default; the epilog (examples) keeps its line breaks."""


EXAMPLES: dict[str, str] = {
    "solve": "confnav solve ws.json -o map.json --plot map.png",
    "simulate": 'confnav simulate ws.json --goal=-0.6,0 --starts="0.8,-0.6;0.8,0.7" --plot run.png',
    "figures": "confnav figures --out out/",
    "import-map": "confnav import-map map.yaml --robot-radius 0.2 -o ws.json --plot ws.png",
    "atlas": "confnav atlas ws.json --goal=1,1 --random 10 --json atlas.json",
    "launch": "confnav launch deploy/local.toml",
    "demo": "confnav demo --out out/",
    "schemas": "confnav schemas export schemas/json",
    "schemas export": "confnav schemas export schemas/json",
    "serve": "confnav serve controller --connect tcp/127.0.0.1:7447",
    "serve transform": "confnav serve transform --workspace room=room.json "
    "--connect tcp/127.0.0.1:7447",
    "serve controller": "confnav serve controller --connect tcp/127.0.0.1:7447",
    "serve simulator": "confnav serve simulator --workspace room=room.json "
    "--robot r1=room:0.8,-0.6 --connect tcp/127.0.0.1:7447",
    "serve recorder": "confnav serve recorder --out run.mcap --connect tcp/127.0.0.1:7447",
    "serve router": "confnav serve router --listen tcp/127.0.0.1:7447",
    "serve ros2": "confnav serve ros2 --robot r1=room --connect tcp/127.0.0.1:7447",
    "serve foxglove": "confnav serve foxglove --port 8765 --connect tcp/127.0.0.1:7447",
    "replay": "confnav replay run.mcap --speed 2\n         confnav replay --check run.mcap",
    "inspect": "confnav inspect run.mcap --plot run.png",
    "recover": "confnav recover run.mcap -o fixed.mcap",
    "viz": "confnav viz run.mcap -o scene.mcap",
}
"""One example per command, shown at the end of its ``--help`` unless the module gave one."""


def _polish(parser: argparse.ArgumentParser, path: str) -> None:
    """Give a (sub)command's help the shared look: defaults shown, an example, recursively."""
    if parser.formatter_class in (argparse.HelpFormatter, argparse.RawDescriptionHelpFormatter):
        parser.formatter_class = HelpFormatter
    if parser.epilog is None and path in EXAMPLES:
        parser.epilog = f"example: {EXAMPLES[path]}"
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                _polish(child, f"{path} {name}".strip())
        elif action.default == [] and action.help and "%(default" not in action.help:
            action.help += "%(default).0s"  # a repeatable option: "(default: [])" says nothing
        elif (
            action.help is None
            and action.option_strings
            and action.default not in (None, False, argparse.SUPPRESS, [])
        ):
            action.help = "default: %(default)s"


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
        importlib.import_module(name).register(sub)
    for name, child in sub.choices.items():
        _polish(child, name)
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
