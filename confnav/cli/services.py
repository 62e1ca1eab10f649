"""Service subcommands of ``confnav``: ``launch``, ``demo``, ``schemas export DIR`` and
``serve transform|controller|simulator|recorder|router|ros2|foxglove``."""

from __future__ import annotations

import argparse
import functools
import os
from collections.abc import Callable
from typing import Any

from threadpoolctl import threadpool_limits

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
    for sub in serve_sub.choices.values():
        sub.set_defaults(func=_single_thread_blas(sub.get_default("func")))


def _single_thread_blas(func: Callable[[argparse.Namespace], int]) -> Callable[..., int]:
    """Run a service with one BLAS thread unless the environment sets a count, as
    ``confnav launch`` and ``demo`` do for their children (``launcher.SINGLE_THREAD_BLAS``):
    a service gets its parallelism from processes, and a multi-threaded OpenBLAS waking its
    threads for the small products of one control step stalls a busy machine (docs/SLAM.md: a
    controller's sample evaluation took a quarter of a second instead of milliseconds)."""

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        if any(v in os.environ for v in launcher.SINGLE_THREAD_BLAS):
            return func(args)
        with threadpool_limits(limits=1, user_api="blas"):
            return func(args)

    return run
