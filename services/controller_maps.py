"""The controller service's maps: fetched with a query, received on the bus, installed with a
hot swap of the robots' controllers; atlases; definition changes and deletes (see
services/controller.py)."""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from confnav.schemas import (
    AtlasIndex,
    DecodeError,
    Goal,
    MapQuery,
    RouteHint,
    TransformSolution,
    TransformStatus,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.schemas.messages import MAX_ROUTES
from confnav.services import navigation
from confnav.services.atlas_client import fetch_atlas
from confnav.services.controller_flat import FlatMixin
from confnav.services.controller_footprint import (
    FootprintMixin,
    base_of,
    base_workspace,
    shrunk_workspace,
)
from confnav.services.controller_state import _Map, _Pending, _Robot
from confnav.services.controller_warm import prime
from confnav.services.definitions import REFINING, definition_hash, workspace_of
from confnav.services.keys import KeyError_

from confnav.atlas.wire import ATLAS_MARKER, AtlasMap, is_chart_ws_id, shared_workspace
from confnav.geometry import Workspace
from confnav.navigation import defaults
from confnav.navigation.safety import safety_filter

log = logging.getLogger(__name__)

#: Footprint maps whose shrunk workspace (and safety grid) the controller keeps built ahead.
PREBUILT = 16


def _warm(cmap: object) -> None:
    """Build a map's lazy evaluation structures (the forward map's expansions, built on the
    first evaluation of ``T``: 1-3 s on the default workspace under load; not for an atlas,
    whose charts are built when a robot enters them) here, on the map thread, so that the
    first goal on the map (e.g. a robot driving on the base map while its footprint map is
    solved) does not wait for them before its first command."""
    f = getattr(cmap, "T_and_dT", None)
    anchor = getattr(cmap, "anchor", None)
    if f is None or anchor is None or getattr(cmap, "is_atlas", False):
        return  # an atlas: warming its every chart here delayed the office's install by 15 s
    try:
        f(np.asarray(complex(anchor)))
    except Exception:  # a map that cannot evaluate its anchor fails the same way for goals
        log.debug("map warm-up", exc_info=True)


class MapsMixin(FootprintMixin, FlatMixin):
    """Maps: liveliness of the transform services, solutions and atlases received or fetched,
    hot swaps, definition changes and deletes."""

    # liveliness and maps -----------------------------------------------------------------
    def _on_live(self, key: str, alive: bool) -> None:
        if alive:
            self._transform_alive.add(key)
        else:
            self._transform_alive.discard(key)
        log.info("transform service %s %s", key, "alive" if alive else "gone")
        self._wake_fetch.set()

    def _on_transform(self, key: str, payload: bytes) -> None:
        self.count("transforms_received")
        try:
            ws_id = self.keys.parse(key).ident
            sol = decode(TransformSolution, payload)
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected transform on %s: %s", key, exc)
            return
        if sol.ws_id != ws_id:
            self.count("rejected")
            return
        if is_chart_ws_id(ws_id):  # a chart of an atlas: installed with its atlas
            return
        self._install(sol)

    def _install(self, sol: TransformSolution | AtlasMap) -> None:
        """Load a solution (or take a fetched atlas) and rebuild the controllers of its
        robots, then swap (hot)."""
        ws_id = sol.ws_id
        cur = self._maps.get(ws_id)
        if cur is not None and cur.revision == sol.revision:
            return
        try:
            cmap = sol if isinstance(sol, AtlasMap) else self._load_map(sol)
            _warm(cmap)
        except Exception as exc:
            self.count("map_load_errors")
            self._map_errors[ws_id] = f"cannot load map: {exc}"
            log.error("workspace %r: cannot load map %s: %s", ws_id, sol.revision[:12], exc)
            return
        est = None if isinstance(sol, AtlasMap) else sol.diagnostics.error_estimate
        new = _Map(sol.revision, cmap, sol.definition_hash, est)
        with self._lock:
            goals = {
                r.robot_id: r.goal
                for r in self._robots.values()
                if r.goal and r.goal.ws_id == ws_id
            }
            # a progressive atlas's next revision (same cells, more charts): the robots' laws
            # on it are made from their laws on the installed one (plan and chart laws shared)
            laws = {
                r.robot_id: r.ctrl
                for r in self._robots.values()
                if cur is not None and r.ctrl is not None and r.ctrl_revision == cur.revision
            }
        with self._goal_building():  # the robots' swap first, the atlas warm-up after
            built = {
                rid: self._extended(cur, new, g, laws.get(rid)) or self._build(new, g)
                for rid, g in goals.items()
                if g
            }
            for rid, (ctrl, _) in built.items():
                prime(ctrl, self._robots[rid].position if rid in self._robots else None)
        with self._build_lock:
            live = {m.revision for w, m in self._maps.items() if w != ws_id} | {new.revision}
            self._ctrl_cache = OrderedDict(
                (k, c) for k, c in self._ctrl_cache.items() if k[0] in live
            )
        late: list[_Robot] = []  # goals that changed or came while the map was being built
        with self._lock:
            self._maps[ws_id] = new
            if est is not None:
                live_revs = {m.revision for m in self._maps.values()}
                self._estimates = {k: v for k, v in self._estimates.items() if k in live_revs}
                self._estimates[new.revision] = est
            self._map_errors.pop(ws_id, None)
            pending = self._pending.get(ws_id)
            if pending is not None and pending.definition_hash == sol.definition_hash:
                del self._pending[ws_id]  # the map of the current geometry: robots go on
            for r in self._robots.values():
                with r.lock:
                    if r.goal is None or r.goal.ws_id != ws_id:
                        continue
                    if r.atlas_ws in self._maps:  # on the atlas its flat start asked for
                        continue
                    if r.goal is not goals.get(r.robot_id):
                        late.append(r)
                        continue
                    ctrl, err = built[r.robot_id]
                    r.ctrl, r.ctrl_revision, r.ctrl_error = ctrl, new.revision, err
                    r.base_ws, r.shrunk = "", None
        for r in late:
            self._adopt(r, ws_id, new)
        self._footprint_installed(ws_id, new)
        self._base_installed(ws_id, new)  # robots whose footprint map {ws_id}~r{R} is unsolved
        self._atlas_installed(ws_id, new)  # robots whose single map is flat where they stood
        if isinstance(cmap, AtlasMap):  # its charts are warmed in the background
            self._warm_atlas(cmap)
        self.count("maps_installed")
        log.info("workspace %r: map %s installed (%d robots)", ws_id, sol.revision[:12], len(goals))
        self.swapped.set()

    def _extended(
        self,
        cur: _Map | None,
        new: _Map,
        goal: Goal,
        ctrl: navigation.ControllerLike | None,
    ) -> tuple[navigation.ControllerLike, str] | None:
        """The law of ``goal`` on ``new`` made from ``ctrl``, the robot's law on the installed
        atlas revision ``cur`` (:meth:`confnav.atlas.wire.AtlasMap.extend`: a new law that
        shares ``ctrl``'s plan and chart laws), cached like a built one; None when ``new``
        does not just add charts to ``cur`` (a new round, a refined atlas, a single map):
        then a law is built."""
        old, am = None if cur is None else cur.cmap, new.cmap
        if ctrl is None or not isinstance(old, AtlasMap) or not isinstance(am, AtlasMap):
            return None
        with self._build_lock:
            assert cur is not None
            key = (cur.revision, *navigation.goal_key(goal), goal.robot_id)
            if self._ctrl_cache.get(key) is not ctrl:  # not this goal's law on ``cur``
                return None
            law: navigation.ControllerLike | None = am.extend(ctrl, old)
            if law is None:
                return None
            self._ctrl_cache[(new.revision, *navigation.goal_key(goal), goal.robot_id)] = law
        self.count("atlas_laws_extended")
        return law, ""

    def _on_ws_status(self, key: str, payload: bytes) -> None:
        """A transform status: remember which revision is a coarse one being refined
        (``REFINING``), for the robots' statuses (progressive maps, docs/SERVICES.md)."""
        try:
            self.keys.parse(key)
            st = decode(TransformStatus, payload)
        except (KeyError_, DecodeError):
            self.count("rejected")
            return
        if st.state == "solved" and st.revision and st.message.startswith(REFINING):
            with self._lock:
                self._refining[st.revision] = None
                while len(self._refining) > 4096:
                    self._refining.popitem(last=False)

    # definition changes -----------------------------------------------------------------
    def _on_definition(self, key: str, payload: bytes) -> None:
        """A definition unlike the installed map's: stop the robots near the new geometry."""
        self.count("definitions_received")
        try:
            ws_id = self.keys.parse(key).ident
            defn = decode(WorkspaceDefinition, payload)
            if defn.ws_id != ws_id:
                raise DecodeError("invalid_input", f"definition on {key} names {defn.ws_id!r}")
            h = definition_hash(defn)
            workspace = workspace_of(defn)
        except (KeyError_, DecodeError, ValueError) as exc:  # WorkspaceError is a ValueError
            self.count("rejected")
            log.warning("rejected definition on %s: %s", key, exc)
            return
        self.count("definitions")
        now = time.monotonic()
        with self._lock:
            cur = self._maps.get(ws_id)
            if cur is not None and cur.definition_hash == h:
                self._pending.pop(ws_id, None)  # back to the geometry of the installed map
                return
            old = self._pending.get(ws_id)
            if old is not None and old.definition_hash == h:
                return  # announced again
            self._pending[ws_id] = _Pending(h, workspace)
            robots = [r for r in self._robots.values() if r.goal and r.goal.ws_id == ws_id]
        self.count("definitions_changed")
        log.warning("workspace %r: definition changed; robots near it stop until its map", ws_id)
        for r in robots:
            with r.lock:
                if r.goal is None or r.goal.ws_id != ws_id or r.position is None:
                    continue
                blocker = self._outdated(r)
                if blocker is not None:
                    self._stop_robot(r, "map_outdated", blocker, now)
        self._wake_fetch.set()

    def _on_ws_delete(self, key: str, payload: bytes) -> None:
        """A deleted workspace: its map is dropped, its robots stop (missing_map)."""
        ws_id = self.workspace_to_delete(key, payload)
        if ws_id is None:
            return
        now = time.monotonic()
        with self._lock:
            self._maps.pop(ws_id, None)
            self._pending.pop(ws_id, None)
            self._map_errors[ws_id] = f"workspace {ws_id!r} was deleted"
            robots = [r for r in self._robots.values() if r.goal and r.goal.ws_id == ws_id]
        self.count("workspaces_deleted")
        for r in robots:
            with r.lock:
                if r.goal is None or r.goal.ws_id != ws_id:
                    continue
                r.ctrl, r.ctrl_revision, r.ctrl_error = None, None, ""
                r.base_ws, r.shrunk = "", None
                self._stop_robot(r, "missing_map", self._map_errors[ws_id], now)

    def _fetch_loop(self) -> None:
        while not self._stop.is_set():
            self._wake_fetch.wait(self.fetch_period)
            self._wake_fetch.clear()
            if self._stop.is_set():
                return
            with self._lock:
                missing = {
                    r.goal.ws_id
                    for r in self._robots.values()
                    if r.goal is not None and r.goal.ws_id not in self._maps
                } | {  # atlases asked for by robots whose single map is flat where they stood
                    r.atlas_ws for r in self._robots.values() if r.atlas_ws not in ("", *self._maps)
                }
                # a footprint map being solved: its base map too (robots drive on it meanwhile)
                bases = {b for w in missing if (b := base_of(w)) is not None}
                needed = missing | {b for b in bases if b not in self._maps} | set(self._pending)
            # the safety grids first: a fetch may wait for a query and an atlas (measured on
            # the SLAM warehouse, first use: the grid started 1.8 s after the goals, behind
            # the fetches, and the first revision's install waited 0.86 s for it)
            for ws_id in sorted(missing):
                self._prebuild_safety(ws_id)
            for ws_id in sorted(needed):
                self._fetch(ws_id)
            self._send_hints()

    def _prebuild_safety(self, ws_id: str) -> None:
        """A footprint map ``{base}~r{R}`` nobody has yet: build the safety layer's grid of its
        exact shrunk workspace now, in a thread, from the base geometry the controller knows
        (its installed map, or the definition announced on the bus), so that the first
        revision's first command does not wait for it (0.44 s on the depot shrunk by 0.32 m,
        idle; the grid is shared by workspace object, :func:`confnav.atlas.wire.
        shared_workspace`, and the atlas's revisions rebuild theirs from the same
        geometry). A geometry that differs (another anchor) just builds its own grid."""
        base = base_of(ws_id)
        if base is None or ws_id in self._prebuilt or not self._on_base_available():
            return
        with self._lock:
            m = self._maps.get(base)
            pend = self._pending.get(base)
        if m is not None and self._on_base_available(m):
            base_ws = base_workspace(m.cmap)
        elif pend is not None:
            base_ws = pend.workspace
        else:
            return
        self._prebuild(ws_id, lambda: shrunk_workspace(base_ws, ws_id))

    def _prebuild(self, ws_id: str, geometry: Callable[[], Any]) -> None:
        """Build the safety grid of ``geometry()`` (the exact workspace of ``ws_id``'s map)
        in a thread, once per map id (:meth:`_prebuild_safety`; also from the first atlas
        index of a map not installed yet, beside the fetch of its charts)."""
        with self._lock:  # from the fetch thread and the atlas subscriber
            if ws_id in self._prebuilt:
                return
            self._prebuilt[ws_id] = None  # one attempt per map
            while len(self._prebuilt) > PREBUILT:
                self._prebuilt.popitem(last=False)

        def build() -> None:
            try:
                shrunk = shared_workspace(geometry())
                with self._lock:
                    if ws_id in self._prebuilt:  # held: the registry keeps it while used
                        self._prebuilt[ws_id] = shrunk
                t0 = time.perf_counter()
                _ = safety_filter(shrunk, hold_time=defaults.HOLD_TIME).grid
                self.count("safety_grids_prebuilt")
                log.info(
                    "workspace %r: safety grid built ahead of its map in %.2f s",
                    ws_id, time.perf_counter() - t0,
                )  # fmt: skip
            except Exception as exc:  # the map's own revision builds it then
                log.info("workspace %r: no safety grid ahead (%s)", ws_id, exc)

        self.spawn(build, "prebuild")

    def _route_hints(self, ws_id: str, only_new: bool = False) -> bytes | None:
        """The ``MapQuery`` payload of a query for ``ws_id``'s map: the routes (start, goal)
        of the robots waiting for it (their goal's map, the atlas they asked for, or the base
        map of their footprint map), the start being the point the law steers (a unicycle's
        look-ahead point); None if there is none. ``only_new``: only routes not sent for
        ``ws_id`` yet. The transform service solves those routes' charts first
        (docs/SLAM.md, "Progressive atlas")."""
        if not self.route_hints:
            return None
        with self._lock:
            robots = list(self._robots.values())
        routes: list[RouteHint] = []
        sent = self._hinted.setdefault(ws_id, {})
        for r in robots:
            with r.lock:
                goal, pos, theta = r.goal, r.position, r.theta
                wanted = goal is not None and ws_id in (goal.ws_id, r.atlas_ws, base_of(goal.ws_id))
            if not wanted or goal is None or pos is None:
                continue
            z = navigation.steered_point(goal, pos[0], pos[1], theta)
            key = (goal.goal, goal.ws_id)
            if only_new and sent.get(r.robot_id) == key:
                continue
            if not (math.isfinite(z.real) and math.isfinite(z.imag)):
                continue
            routes.append(RouteHint(robot_id=r.robot_id, start=(z.real, z.imag), goal=goal.goal))
            sent[r.robot_id] = key
            if len(routes) >= MAX_ROUTES:
                break
        if not routes:
            return None
        self.count("route_hints_sent", len(routes))
        payload: bytes = encode(MapQuery(stamp_ns=time.time_ns(), routes=routes))
        return payload

    def _send_hints(self) -> None:
        """New robots' routes on a progressive atlas still being solved (an installed
        revision with pending cells): sent with a query of its index, whose reply is not
        needed (the revisions come on ``ws/{ws}/atlas``)."""
        with self._lock:
            partial = [w for w, m in self._maps.items() if getattr(m.cmap, "pending", None)]
        for ws_id in partial:
            payload = self._route_hints(ws_id, only_new=True)
            if payload is None:
                continue
            try:
                self.bus.query(self.keys.ws(ws_id, "atlas"), timeout=2.0, payload=payload)
            except Exception as exc:
                log.debug("workspace %r: route hints not sent: %s", ws_id, exc)

    def _fetch(self, ws_id: str) -> None:
        """Query ``ws_id``'s map (every ``fetch_period`` while it is missing). The route
        hints go with the first query and again when the transform's answer changes (a
        new failure, a definition being solved); a query retried on the same answer (a
        base map that failed, one still being solved) carries only robots' new routes:
        the transform has the others (measured before: 510 hints to the warehouse's
        failed base map in 98 s, the same 3 routes every 0.5 s)."""
        self.count("queries")
        err = self._map_errors.get(ws_id)
        same = err is not None and self._hint_error.get(ws_id) == err
        try:
            replies = self.bus.query(
                self.keys.ws(ws_id, "transform"),
                timeout=2.0,
                payload=self._route_hints(ws_id, only_new=same),
            )
        except Exception as exc:
            self._map_errors[ws_id] = f"query failed: {exc}"
            return
        finally:
            self._hint_error.pop(ws_id, None)
        if not replies:
            self._map_errors[ws_id] = "no transform service answered"
            return
        for rep in replies:
            if not rep.ok or rep.payload is None:
                self._map_errors[ws_id] = rep.error or "error"
                if (rep.error or "").startswith(ATLAS_MARKER):  # solved as an atlas
                    self._hinted_on(ws_id, err, same)
                    self._fetch_atlas(ws_id)
                    return
                continue
            try:
                sol = decode(TransformSolution, rep.payload)
            except DecodeError as exc:
                self._map_errors[ws_id] = str(exc)
                continue
            self._install(sol)
            return
        self._hinted_on(ws_id, err, same)

    def _hinted_on(self, ws_id: str, before: str | None, same: bool) -> None:
        """After a map query answered with an error: the answer the transform has every
        route under (:meth:`_fetch`). A query with every route (``same`` False) gives it
        its answer; a retry with new routes only keeps it while the answer stays
        ``before``, a changed answer (a new failure, a new definition) drops it: the next
        retry sends every route again."""
        now = self._map_errors.get(ws_id)
        if now is not None and (not same or now == before):
            self._hint_error[ws_id] = now

    def _fetch_atlas(self, ws_id: str, index: AtlasIndex | None = None) -> None:
        """Fetch and install the atlas of ``ws_id`` (services/atlas_client.py), one fetch per
        workspace at a time: an index that comes meanwhile is fetched after it (the newest
        one; a progressive atlas's revisions only add charts), a fetch without an index
        (the transform query said "atlas") is left to the running one. Concurrent fetches
        of one atlas competed for the interpreter with the install of the first revision
        (measured on the depot: a revision's fetch took 0.49-0.73 s, each partial revision
        fetched twice)."""
        busy = self._atlas_busy
        with self._lock:
            if ws_id in busy:
                if index is not None:
                    busy[ws_id] = index  # the newest index waits for the running fetch
                return
            busy[ws_id] = None
        try:
            while True:
                self._fetch_atlas_once(ws_id, index)
                with self._lock:
                    index = busy.get(ws_id)
                    if index is None:
                        busy.pop(ws_id, None)
                        return
                    busy[ws_id] = None
        except BaseException:
            with self._lock:
                busy.pop(ws_id, None)
            raise

    def _fetch_atlas_once(self, ws_id: str, index: AtlasIndex | None) -> None:
        cur = self._maps.get(ws_id)
        if index is not None and cur is not None and cur.revision == index.revision:
            return  # installed already
        try:
            # a progressive atlas: its charts loaded already
            known = getattr(cur.cmap, "known_charts", None) if cur is not None else None
            t0 = time.perf_counter()
            prev = cur.cmap if cur is not None and isinstance(cur.cmap, AtlasMap) else None
            am = fetch_atlas(
                self.bus,
                self.keys,
                ws_id,
                index,
                known=known() if known else None,
                previous=prev,
            )
            t1 = time.perf_counter()
            self._install(am)
            log.debug(
                "workspace %r: atlas revision %s fetched in %.3f s, installed in %.3f s",
                ws_id, am.revision[:12], t1 - t0, time.perf_counter() - t1,
            )  # fmt: skip
        except Exception as exc:
            self._map_errors[ws_id] = f"cannot fetch atlas: {exc}"
            log.warning("workspace %r: cannot fetch atlas: %s", ws_id, exc)

    def _on_atlas(self, key: str, payload: bytes) -> None:
        """A (re)solved atlas: fetched and installed off the subscriber thread."""
        try:
            index = decode(AtlasIndex, payload)
            if index.ws_id != self.keys.parse(key).ident:
                raise DecodeError("invalid_input", f"atlas on {key} names {index.ws_id!r}")
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected atlas on %s: %s", key, exc)
            return
        cur = self._maps.get(index.ws_id)
        if cur is None and base_of(index.ws_id) is not None and self._on_base_available():
            # the first revision of a footprint atlas: its safety grid beside the fetch
            ws = dict(index.decomposition).get("workspace")
            self._prebuild(index.ws_id, lambda: Workspace.from_dict(ws))  # type: ignore[arg-type]
        if cur is None or cur.revision != index.revision:
            self.spawn(lambda: self._fetch_atlas(index.ws_id, index), "atlas-fetch")
