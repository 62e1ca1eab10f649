"""Service subcommands of ``confnav``: ``launch``, ``demo``, ``schemas export DIR`` and
``serve transform|controller|simulator|recorder|router|ros2|foxglove``."""

from __future__ import annotations

import argparse
from typing import Any

from confnav.services import (
    controller,
    demo,
    foxglove_live,
    launcher,
    recorder,
    router,
    simulator,
    transform,
)
from confnav.services.ros2 import bridge as ros2_bridge


def _schemas_export(args: argparse.Namespace) -> int:
    from confnav.schemas import export_schemas

    paths = export_schemas(args.dir)
    for p in paths:
        print(p)
    return 0


def register(subparsers: Any) -> None:
    """Add the service subcommands to the ``confnav`` parser."""
    launcher.add_parser(subparsers)
    demo.add_parser(subparsers)

    sch = subparsers.add_parser("schemas", help="message schemas")
    sch_sub = sch.add_subparsers(dest="schemas_command", metavar="ACTION", required=True)
    exp = sch_sub.add_parser("export", help="write the JSON Schema of every message to DIR")
    exp.add_argument("dir", metavar="DIR")
    exp.set_defaults(func=_schemas_export)

    serve = subparsers.add_parser("serve", help="run one service process")
    serve_sub = serve.add_subparsers(dest="service", metavar="SERVICE", required=True)
    for mod in (transform, controller, simulator, recorder, router, ros2_bridge, foxglove_live):
        mod.add_parser(serve_sub)
