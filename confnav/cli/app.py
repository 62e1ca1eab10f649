"""The ``confnav`` command line: one subcommand per job, registered by the module that owns it.

Each module in :data:`SUBCOMMAND_MODULES` exposes ``register(subparsers)``, which adds its
subcommands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import re
import sys
from collections.abc import Sequence

from confnav import __version__
from confnav.errors import ConfnavError

SUPERVISOR_ENV = "CONFNAV_SUPERVISOR"
"""Set for the children of ``confnav launch`` and ``confnav demo``
(:data:`confnav.services.runtime.SUPERVISOR_ENV`)."""

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


#: A negative point or number list (``-0.5,0.5``, ``-1,2;3,4``, ``-1e-3``): an argument, not an
#: option (argparse's own pattern knows only plain negative numbers; no confnav option looks
#: like a number, so nothing else is shadowed).
NEGATIVE_ARG = re.compile(r"^-\d+$|^-\d*\.\d+$|^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?[,;]")

_REST_ROLE = re.compile(r":(?:mod|class|func|meth|data|attr|obj|exc|ref|doc):`~?([^`]*)`")
_REST_LITERAL = re.compile(r"``([^`]*)``")
_REST_INTERPRETED = re.compile(r"`([^`]+)`")


def plain(text: str) -> str:
    """Help text without reST markup: ``:mod:`x```, double-backquoted ``x`` and
    single-backquoted `x` become x."""
    text = _REST_LITERAL.sub(r"\1", _REST_ROLE.sub(r"\1", text))
    return _REST_INTERPRETED.sub(r"\1", text)


def _sentence(text: str) -> str:
    text = text.strip()
    return (text[:1].upper() + text[1:]).rstrip(".") + "."


def _polish_action(action: argparse.Action) -> None:
    """One option's help: plain text, and its default shown once (by the formatter unless the
    text states it: ``(default: ...)``, ``default 0: ...``), never ``(default: None)``."""
    if action.help == argparse.SUPPRESS:
        return
    if action.help is None:
        if action.option_strings and action.default not in (None, False, argparse.SUPPRESS, []):
            action.help = "default: %(default)s"
        return
    action.help = plain(action.help)
    if "%(default" in action.help:
        return
    says_default = re.search(r"\bdefault\b", action.help) is not None
    empty = action.default is None or (isinstance(action.default, list) and not action.default)
    if says_default or empty or isinstance(action.default, bool):
        action.help += "%(default).0s"  # the formatter would repeat or say nothing useful


def _polish(parser: argparse.ArgumentParser, path: str, summary: str | None = None) -> None:
    """Give a (sub)command's help the shared look, recursively: defaults shown once, no reST,
    a description (the one-line summary its parent lists if it has none), an example, and
    negative points accepted as arguments (``confnav goal r1 -0.5,0.5``)."""
    if parser.formatter_class in (argparse.HelpFormatter, argparse.RawDescriptionHelpFormatter):
        parser.formatter_class = HelpFormatter
    parser._negative_number_matcher = NEGATIVE_ARG
    if parser.description is None and summary:
        parser.description = _sentence(summary)
    if parser.description is not None:
        parser.description = plain(parser.description)
    if parser.epilog is None and path in EXAMPLES:
        parser.epilog = f"example: {EXAMPLES[path]}"
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, child in action.choices.items():
                _polish(child, f"{path} {name}".strip(), helps.get(name))
        else:
            _polish_action(action)


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
    parser._negative_number_matcher = NEGATIVE_ARG
    helps = {a.dest: a.help for a in sub._choices_actions}
    for name, child in sub.choices.items():
        _polish(child, name, helps.get(name))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    if SUPERVISOR_ENV in os.environ:  # a child of confnav launch / demo: die with it
        from confnav.services.runtime import watch_supervisor

        watch_supervisor()
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
    except OSError as exc:  # a missing or unreadable file, a full disk...: one line
        print(f"confnav {args.command}: error: {_os_error(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"confnav {args.command}: interrupted", file=sys.stderr)
        return 130


def _os_error(exc: OSError) -> str:
    """``cannot open missing.json: No such file or directory`` (what, where, why)."""
    why = exc.strerror or (errno.errorcode.get(exc.errno, "") if exc.errno else "") or str(exc)
    if exc.filename is None:
        return why
    where = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 is not None else "")
    return f"{where}: {why}"


if __name__ == "__main__":
    sys.exit(main())
