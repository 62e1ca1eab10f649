"""A Zenoh router as a Python session in router mode (``confnav serve router``)."""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

import zenoh
from confnav.services.bus import zenoh_config
from confnav.services.keys import DEFAULT_PREFIX, Keys
from confnav.services.runtime import stop_on_signals

log = logging.getLogger(__name__)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("router", help="run a Zenoh router")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="other routers to peer with (multi-machine)",
    )
    p.add_argument("--zenoh-config", default=None, metavar="FILE", help="zenoh JSON5 config")
    p.add_argument("--prefix", default=DEFAULT_PREFIX)
    p.add_argument(
        "--id",
        default=None,
        metavar="HEX",
        help="Zenoh id of the router (the launcher sets one to recognise its own router)",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    conf = zenoh_config("router", args.listen, args.connect, args.zenoh_config)
    if args.id:
        conf.insert_json5("id", json.dumps(args.id))
    keys = Keys(args.prefix)
    with stop_on_signals() as ev, zenoh.open(conf) as session:
        zid = str(session.zid())
        token = session.liveliness().declare_token(keys.alive("router", zid))
        log.info("router %s listening on %s", zid, args.listen or "(config)")
        while not ev.wait(0.5):
            pass
        token.undeclare()  # type: ignore[no-untyped-call]
    return 0
