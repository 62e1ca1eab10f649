"""A Zenoh router as a Python session in router mode (``confnav serve router``)."""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

from confnav.services.bus import ZenohBus, zenoh_config
from confnav.services.keys import DEFAULT_PREFIX, Keys
from confnav.services.runtime import Service, stop_on_signals

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


class RouterService(Service):
    """The router's own session as a service: liveliness token ``{prefix}/alive/router/{zid}``
    and health on ``{prefix}/health/router/{zid}`` every second (``confnav status`` shows it
    with the others' instead of waiting for a health message forever)."""

    name = "router"

    def _start(self) -> None:
        pass


def main(args: argparse.Namespace) -> int:
    conf = zenoh_config("router", args.listen, args.connect, args.zenoh_config)
    if args.id:
        conf.insert_json5("id", json.dumps(args.id))
    keys = Keys(args.prefix)
    with stop_on_signals() as ev, ZenohBus(conf) as bus:
        service = RouterService(bus, keys)
        service.start()
        log.info("router %s listening on %s", bus.zid, args.listen or "(config)")
        try:
            while not ev.wait(0.5):
                pass
        finally:
            service.stop()
    return 0
