"""The controller service's side of atlases (issue 15 item 3): fetch an atlas over Zenoh.

:func:`fetch_atlas` queries ``{prefix}/ws/{ws}/atlas`` (the ``AtlasIndex``), then each chart's
``TransformSolution`` on ``{prefix}/ws/{ws}~c{i}/transform`` (checking that it is the revision
the index names), loads the charts with :func:`confnav.services.navigation.load_map` and
returns the :class:`confnav.atlas.wire.AtlasMap` the controller installs like a map.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from confnav.schemas import AtlasIndex, TransformSolution, decode
from confnav.services.bus import Bus
from confnav.services.keys import Keys
from confnav.services.navigation import load_map

from confnav.atlas.wire import AtlasMap, atlas_map_of, is_pending
from confnav.errors import ConfnavError

log = logging.getLogger(__name__)

#: Chart queries of one fetch in flight at once.
QUERIES = 8


class AtlasFetchError(ConfnavError):
    """An atlas that could not be fetched (no answer, an error reply, a stale chart)."""


def _query_one(bus: Bus, key: str, timeout: float) -> bytes:
    replies = bus.query(key, timeout=timeout)
    errors = [r.error or "error" for r in replies if not r.ok or r.payload is None]
    for r in replies:
        if r.ok and r.payload is not None:
            return bytes(r.payload)
    raise AtlasFetchError(f"{key}: " + ("; ".join(errors) or "no transform service answered"))


def fetch_index(bus: Bus, keys: Keys, ws_id: str, timeout: float = 2.0) -> AtlasIndex:
    """The ``AtlasIndex`` of ``ws_id`` (raises AtlasFetchError)."""
    index = decode(AtlasIndex, _query_one(bus, keys.ws(ws_id, "atlas"), timeout))
    if index.ws_id != ws_id:
        raise AtlasFetchError(f"atlas index for {ws_id!r} names {index.ws_id!r}")
    return index


def fetch_atlas(
    bus: Bus,
    keys: Keys,
    ws_id: str,
    index: AtlasIndex | None = None,
    timeout: float = 5.0,
    known: Mapping[str, Any] | None = None,
    previous: AtlasMap | None = None,
) -> AtlasMap:
    """Every chart of ``ws_id``'s atlas, loaded for control (raises AtlasFetchError).

    A partial revision of a progressive atlas (cells ``pending``) gives an atlas whose
    pending cells have no chart; ``known``: charts already loaded (by revision, e.g. those
    of the installed revision), not fetched again; ``previous``: the installed revision,
    whose cells (polygons, overlaps, centres) the new one reuses when they are the same
    (:func:`confnav.atlas.wire.atlas_map_of`). The new charts are queried at once."""
    index = index if index is not None else fetch_index(bus, keys, ws_id, timeout)
    maps = {}
    todo = []
    for cell in index.cells:
        if is_pending(cell):  # a progressive atlas's partial revision: no chart yet
            continue
        if known is not None and cell.chart_revision in known:  # loaded for an earlier revision
            maps[cell.chart_revision] = known[cell.chart_revision]
            continue
        todo.append(cell)
    t0 = time.perf_counter()
    # the new charts' queries at once (one round trip each, 2-60 ms under load, sequential
    # before: a revision of 8 new charts waited for 8 round trips)
    if todo:
        with ThreadPoolExecutor(max(1, min(QUERIES, len(todo)))) as pool:
            payloads = list(
                pool.map(
                    lambda c: _query_one(bus, keys.ws(c.chart_ws_id, "transform"), timeout), todo
                )
            )
    else:
        payloads = []
    t1 = time.perf_counter()
    for cell, payload in zip(todo, payloads, strict=True):
        sol = decode(TransformSolution, payload)
        if sol.revision != cell.chart_revision:
            raise AtlasFetchError(
                f"chart {cell.chart_ws_id!r}: revision {sol.revision[:12]} is not the index's "
                f"{cell.chart_revision[:12]} (re-solved meanwhile)"
            )
        maps[sol.revision] = load_map(sol)
    t2 = time.perf_counter()
    am = atlas_map_of(index, maps, previous=previous)
    log.debug(
        "atlas %r: %d new charts queried in %.3f s, loaded in %.3f s, atlas built in %.3f s",
        ws_id, len(todo), t1 - t0, t2 - t1, time.perf_counter() - t2,
    )  # fmt: skip
    return am
