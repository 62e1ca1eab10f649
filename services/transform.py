"""Transformation service: workspace definitions in, solved conformal maps out.

- loads workspaces from files (or the built-in ``default``) at start and publishes their
  definitions on ``{prefix}/ws/{ws}/definition`` so that recordings hold them;
- subscribes to ``{prefix}/ws/*/definition`` for new or changed workspaces;
- solves off the Zenoh threads, several workspaces at once (process pool by default),
  cached by the definition's content hash (optionally on disk, so a restart is instant);
- publishes ``TransformStatus`` and, when the solution changes, ``TransformSolution`` on
  ``{prefix}/ws/{ws}/transform``; serves the current solution from a complete queryable on
  ``{prefix}/ws/*/transform`` (``reply_err`` for every query it cannot answer: unknown,
  invalid, not yet solved, malformed key, no match);
- a solver worker that dies (killed, out of memory) breaks the process pool: the pool is
  rebuilt and the solve retried, and after ``max_attempts`` attempts the workspace is marked
  failed with the reason; a solve running longer than ``solve_timeout`` s fails the
  workspace (its worker is killed, the other solves retried on a new pool);
- results are kept in memory in an LRU of ``max_cached`` entries (and on disk by content
  hash with ``--cache-dir``); only valid definitions are persisted, in files named from an
  encoding of the id (never a path component such as ``..``);
- ``WorkspaceDelete`` on ``{prefix}/ws/{ws}/delete`` forgets a workspace (status
  ``deleted``; its saved definition removed).

The math is :func:`confnav.solve`; this module only parses, caches and publishes.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import hashlib
import json
import logging
import multiprocessing
import os
import threading
import time
import urllib.parse
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from confnav.schemas import (
    DecodeError,
    Goal,
    MapQuery,
    SolveDiagnostics,
    SpawnRequest,
    TransformSolution,
    TransformStatus,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.atlas_transform import (
    AtlasStore,
    ChartShare,
    RouteBook,
    finish_atlas,
    single_or_atlas,
)
from confnav.services.bus import Bus, QueryError, key_matches
from confnav.services.definitions import (
    COARSE_MAX_ERROR,
    REFINING,
    definition_hash,
    definition_of,
    derived_definition,
    footprint_of,
    load_definition,
    parse_sources,
    revision_ladder,
    solution_result,
    workspace_of,
)
from confnav.services.keys import KeyError_, Keys
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal

from confnav.atlas.wire import atlas_ws_id, parse_atlas_ws_id
from confnav.conformal.cmap import ConformalMap
from confnav.maps.footprint import derived_ws_id, parse_derived_ws_id

log = logging.getLogger(__name__)

SolveFn = Callable[[str], dict[str, Any]]
"""Takes a WorkspaceDefinition as JSON text, returns the solve result dict of
:func:`solve_definition` (must be picklable for the process pool)."""


def solve_definition(
    defn_json: str,
    tol: float | None = None,
    max_error: float | None = None,
    previous: str | None = None,
) -> dict[str, Any]:
    """Solve one workspace (runs in a worker process): the map's coefficients and summary,
    or ``{"needs_atlas": why}`` for a workspace too crowded for one map (the service then
    solves its charts, :class:`confnav.services.atlas_transform.ChartShare`). ``tol`` and
    ``max_error`` (a revision of a progressive solve): solved to ``tol`` instead of the
    definition's, a coarse map accepted up to ``max_error`` (:func:`confnav.solve`).
    ``previous``: the map JSON of the workspace's previous definition, the start of a warm
    re-solve (``solve(initial=...)``, docs/METHOD.md: a moved, added or removed obstacle)."""
    defn = WorkspaceDefinition.model_validate_json(defn_json)
    initial = ConformalMap.from_json(previous) if previous else None
    return single_or_atlas(
        workspace_of(defn), defn.tol if tol is None else tol, max_error=max_error, initial=initial
    )


def atlas_hash(h: str) -> str:
    """The key of the atlas solve of the geometry whose definition hash is ``h`` (the
    ``{ws}~atlas`` id): not the single map's key, so neither is served for the other."""
    return hashlib.sha256(f"{h}|atlas".encode()).hexdigest()


#: Niceness of the background solver processes: the charts of atlases no robot waits for
#: (:meth:`TransformService.submit_job`). Linux's scheduler weights a nice-0 process ~9x a
#: nice-10 one [sched(7), "The nice value"], so the charts robots wait for are solved at
#: nearly full speed while a base atlas nobody drives on yet keeps the rest of the CPU
#: (docs/SLAM.md "Background atlases").
BACKGROUND_NICE = 10


def _warm_worker() -> None:
    """A no-op job that starts a worker and imports the chart solver in it (the foreground
    workers are started with the service, not when the first robot waits)."""
    import confnav.atlas.charts  # noqa: F401


def _worker_init(parent: int, nice: int = 0) -> None:
    """In each solver process: exit when the service process dies (even by SIGKILL); a
    background worker lowers its priority by ``nice``."""
    if nice > 0 and hasattr(os, "nice"):  # lowering one's own priority is always allowed
        os.nice(nice)
    try:  # Linux: the kernel sends SIGTERM when the parent exits
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

    def watch() -> None:  # portable fallback
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(0)


@dataclass
class _WsState:
    definition: WorkspaceDefinition
    definition_hash: str
    state: str  # solving | refining (a coarse revision published) | solved | failed
    error: str = ""
    solution: bytes | None = None  # last good solution (kept while a new one solves)
    revision: str | None = None


class TransformService(Service):
    """See the module docstring. ``sources`` maps ws id -> file path or ``builtin:default``."""

    name = "transform"

    def __init__(
        self,
        bus: Bus,
        keys: Keys | None = None,
        sources: dict[str, str] | None = None,
        workers: int = 2,
        executor: str = "process",
        solve_fn: SolveFn = solve_definition,
        cache_dir: str | Path | None = None,
        health_period: float = 1.0,
        max_attempts: int = 3,
        solve_timeout: float = 900.0,
        max_cached: int = 32,
        progressive: bool | None = None,
        robot_radii: tuple[float, ...] = (),
    ) -> None:
        super().__init__(bus, keys, health_period)
        # revisions coarse to fine (docs/SERVICES.md); None: with the library's solver (a
        # custom solve_fn takes the definition only and is called once per definition)
        self.progressive = (solve_fn is solve_definition) if progressive is None else progressive
        self.robot_radii = tuple(r for r in robot_radii if r > 0)  # {ws}~r{R} solved ahead
        self._rung: dict[str, int] = {}  # hash -> rung of the ladder its running solve is at
        # ws id -> (definition hash, map coefficients) of its last final single map
        self._last_map: dict[str, tuple[str, Any]] = {}
        self.sources = dict(sources or {})
        self._solve_fn = solve_fn
        self._workers = workers
        self._executor_kind = executor
        self._pool: cf.Executor | None = None
        #: the background pool (niced workers): charts of atlases no robot waits for
        self._bg_pool: cf.Executor | None = None
        self._lock = threading.RLock()  # submit_job is called with it held
        self._ws: dict[str, _WsState] = {}
        self.max_attempts = max_attempts
        self.solve_timeout = solve_timeout
        self.max_cached = max_cached
        # definition hash -> solve result, least recently used first
        self._results: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self._inflight: dict[str, cf.Future[dict[str, Any]]] = {}
        self._started: dict[str, float] = {}  # hash -> monotonic start of its current solve
        self._attempts: dict[str, int] = {}  # hash -> solves started (worker deaths retry)
        self._abandoned: set[cf.Future[dict[str, Any]]] = set()  # timed out: result ignored
        self._cache_dir = Path(cache_dir) if cache_dir else None
        self.solved = threading.Event()  # set each time a solution is published (tests)
        self.atlases = AtlasStore()  # workspaces solved as atlases (index + charts)
        self.charts = ChartShare(self)  # atlas charts solved with the peer instances
        self.routes = RouteBook()  # the robots' routes sent with map queries (MapQuery)
        self._atlas_threads = cf.ThreadPoolExecutor(4, thread_name_prefix="atlas")

    @property
    def workers(self) -> int:
        """Solves run at once (the pool's size; an atlas's charts use as many)."""
        return self._workers

    # lifecycle -------------------------------------------------------------------------
    def _new_pool(self, background: bool = False) -> cf.Executor:
        if self._executor_kind == "process":
            ctx = multiprocessing.get_context("spawn")  # never fork a process holding Zenoh
            nice = BACKGROUND_NICE if background else 0
            return cf.ProcessPoolExecutor(
                self._workers,
                mp_context=ctx,
                initializer=_worker_init,
                initargs=(os.getpid(), nice),
            )
        return cf.ThreadPoolExecutor(self._workers, thread_name_prefix="solve")

    def _start(self) -> None:
        self._pool = self._new_pool()
        self._bg_pool = self._new_pool(background=True)
        if self._executor_kind == "process":  # the workers start (and import) now: a chart
            for pool in (self._pool, self._bg_pool):  # never waits for a worker's start
                for _ in range(self._workers):
                    pool.submit(_warm_worker).add_done_callback(self._warmed)
        self.spawn(self._timeout_loop, "timeouts")
        if self._cache_dir:
            self._cache_dir.mkdir(parents=True, exist_ok=True)
        self._handles.append(
            self.bus.subscribe(self.keys.any_ws("definition"), self._on_definition)
        )
        self._handles.append(self.bus.subscribe(self.keys.any_ws("delete"), self._on_delete))
        # robots spawned in a simulator: their {ws}~r{R} maps are solved ahead of their goals
        self._handles.append(self.bus.subscribe(f"{self.keys.prefix}/sim/*/spawn", self._on_spawn))
        self._handles.append(self.bus.queryable(self.keys.any_ws("transform"), self._on_query))
        self._handles.append(self.bus.queryable(self.keys.any_ws("atlas"), self._on_query))
        self._handles.extend(self.charts.start())
        defs: dict[str, WorkspaceDefinition] = {}
        for ws_id, source in self.sources.items():
            try:
                defs[ws_id] = load_definition(ws_id, source)
            except Exception as exc:
                log.error("cannot load workspace %r from %s: %s", ws_id, source, exc)
                self.count("load_errors")
        defs.update(self._load_saved_definitions())  # later puts override the files
        for defn in defs.values():
            if self.submit(defn):
                self.bus.publish(self.keys.ws(defn.ws_id, "definition"), encode(defn))
                self._derive_ahead(defn.ws_id, self.robot_radii)

    def stop(self) -> None:
        super().stop()
        self._atlas_threads.shutdown(wait=False, cancel_futures=True)
        for pool in (self._pool, self._bg_pool):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)

    def _warmed(self, fut: cf.Future[None]) -> None:
        """A worker started and imported the solver (health counter ``workers_warmed``: both
        pools are ready at ``2 workers``)."""
        if not fut.cancelled() and fut.exception() is None:
            self.count("workers_warmed")

    def health_detail(self) -> tuple[str, str]:
        with self._lock:
            failed = sorted(w for w, s in self._ws.items() if s.state == "failed")
            solving = sorted(w for w, s in self._ws.items() if s.state == "solving")
            refining = sorted(w for w, s in self._ws.items() if s.state == "refining")
        detail = json.dumps({"failed": failed, "solving": solving, "refining": refining})
        return ("degraded" if failed else "ok"), detail

    # inputs ----------------------------------------------------------------------------
    def _on_definition(self, key: str, payload: bytes) -> None:
        self.count("definitions_received")
        try:
            ws_id = self.keys.parse(key).ident
            defn = decode(WorkspaceDefinition, payload)
        except (KeyError_, DecodeError) as exc:
            self.count("rejected")
            log.warning("rejected definition on %s: %s", key, exc)
            return
        if defn.ws_id != ws_id:
            self.count("rejected")
            log.warning("definition on %s names workspace %r: ignored", key, defn.ws_id)
            return
        if not self.submit(defn):
            return
        self._save_definition(defn)
        with self._lock:  # re-derive the footprint workspaces and atlases of this one
            derived = sorted(  # a footprint workspace before its atlas ({ws}~r{R}~atlas)
                (w for w in self._ws if w.startswith(ws_id + "~r") or w == atlas_ws_id(ws_id)),
                key=len,
            )
        for w in derived:
            err = self._derive(w)
            if err:
                log.warning("%s", err)
        self._derive_ahead(ws_id, self.robot_radii)

    def _derive_ahead(self, ws_id: str, radii: tuple[float, ...]) -> None:
        """Solve ``{ws_id}~r{R}`` for footprint radii the system already knows (spawned
        robots, ``--robot-radius``) before any goal asks for them."""
        for radius in radii:
            w = derived_ws_id(ws_id, radius)
            with self._lock:
                known = w in self._ws or w == ws_id
            if not known:
                err = self._derive(w)
                if err:
                    log.warning("%s", err)

    def _on_spawn(self, key: str, payload: bytes) -> None:
        """A robot spawned with a body: the map of its footprint is solved ahead of use."""
        try:
            req = decode(SpawnRequest, payload)
        except DecodeError:
            return  # the simulator answers bad requests; nothing to solve here
        radius = footprint_of(
            req.robot_radius, req.drive, float(Goal.model_fields["lookahead"].default)
        )
        if radius > 0:
            self.count("spawn_radii")
            self._derive_ahead(req.ws_id, (radius,))

    def _derive(self, ws_id: str) -> str:
        """Solve ``{base}~r{R}`` (a footprint workspace) from the known base definition, or
        ``{base}~atlas`` (the base's geometry as an atlas, whatever one map of it would be:
        asked for by a controller whose robot's navigation function is flat on the single
        map, docs/SERVICES.md); returns why it cannot be derived ("" if it was submitted or
        is not a derived id)."""
        atlas_of = parse_atlas_ws_id(ws_id)
        if atlas_of is not None:
            with self._lock:
                known = atlas_of in self._ws
            err = "" if known else self._derive(atlas_of)  # e.g. {ws}~r{R}~atlas
            with self._lock:
                base = self._ws.get(atlas_of)
            if base is None:
                return err
            self.submit(base.definition.model_copy(update={"ws_id": ws_id}))
            return ""
        parsed = parse_derived_ws_id(ws_id)
        with self._lock:
            base = self._ws.get(parsed[0]) if parsed else None
        if base is None:
            return ""
        try:
            defn = derived_definition(ws_id, base.definition)
        except Exception as exc:
            return f"workspace {ws_id!r}: {exc}"
        self.submit(defn)
        return ""

    def _on_delete(self, key: str, payload: bytes) -> None:
        """Forget a workspace: state, saved definition; status ``deleted``."""
        ws_id = self.workspace_to_delete(key, payload)
        if ws_id is None:
            return
        with self._lock:
            st = self._ws.pop(ws_id, None)
        self.atlases.forget(ws_id)
        self.routes.forget(ws_id)
        path = self._definition_path(ws_id)
        if path is not None:
            path.unlink(missing_ok=True)
        if st is None:
            self.count("deletes_unknown")
            return
        self.count("deletes")
        log.info("workspace %r deleted", ws_id)
        self._publish_status(ws_id, "deleted", st.definition_hash, None, "deleted")

    def submit(self, defn: WorkspaceDefinition) -> bool:
        """Validate and (re)solve ``defn`` unless its solution is current or cached; False
        if the definition is invalid (the workspace is then marked failed)."""
        ws_id = defn.ws_id
        try:
            h = definition_hash(defn)
        except Exception as exc:  # WorkspaceError and anything the validation raises
            self._fail(defn, "invalid:" + ws_id, f"invalid workspace: {exc}")
            return False
        if parse_atlas_ws_id(ws_id) is not None:  # the geometry's atlas: its own result
            h = atlas_hash(h)
        with self._lock:
            cur = self._ws.get(ws_id)
            if cur is not None and cur.definition_hash == h and cur.state != "failed":
                return True  # unchanged: nothing to do
            old_solution = cur.solution if cur else None
            old_rev = cur.revision if cur else None
            self._ws[ws_id] = _WsState(defn, h, "solving", "", old_solution, old_rev)
            result = self._cached(h)
            if result is None and h not in self._inflight:
                self._attempts.pop(h, None)  # a new request: a fresh budget of attempts
                self._rung.pop(h, None)
        if result is not None:
            self.count("cache_hits")
            self._finish(ws_id, h, result, None)
            return True
        self._publish_status(ws_id, "solving", h, old_rev, "")
        log.info("workspace %r: solving (%d obstacles)", ws_id, len(defn.obstacles))
        self._solve(ws_id, h, defn)
        return True

    def _cached(self, h: str) -> dict[str, Any] | None:
        """The result for hash ``h`` from the LRU or the disk cache (lock held)."""
        result = self._results.get(h)
        if result is not None:
            self._results.move_to_end(h)
            return result
        return self._load_cached(h)

    def _remember(self, h: str, result: dict[str, Any]) -> None:
        """Put a result into the LRU, dropping the least recently used (lock held)."""
        self._results[h] = result
        self._results.move_to_end(h)
        while len(self._results) > self.max_cached:
            self._results.popitem(last=False)
            self.count("cache_evictions")

    def submit_job(
        self, fn: Callable[..., Any], *args: Any, background: bool = False
    ) -> cf.Future[Any]:
        """Run ``fn(*args)`` on the solver pool (a new pool if the current one is broken);
        ``background``: on the background pool, whose workers run at :data:`BACKGROUND_NICE`
        (the charts of an atlas no robot waits for, :meth:`ChartShare.run`)."""
        with self._lock:
            assert self._pool is not None, "service not started"
            if background and self._bg_pool is not None:
                try:
                    return self._bg_pool.submit(fn, *args)
                except (cf.BrokenExecutor, RuntimeError):  # a worker died: new pool
                    self._rebuild_pool(background=True)
                    return self._bg_pool.submit(fn, *args)
            try:
                return self._pool.submit(fn, *args)
            except (cf.BrokenExecutor, RuntimeError):  # a worker died: new pool
                self._rebuild_pool()
                return self._pool.submit(fn, *args)

    def _ladder(self, defn: WorkspaceDefinition) -> list[float]:
        """The tolerances of the revisions of ``defn`` (one: its ``tol``, unless progressive)."""
        return revision_ladder(defn.tol) if self.progressive else [defn.tol]

    def _solve(
        self, ws_id: str, h: str, defn: WorkspaceDefinition, atlas: bool = False, rung: int = 0
    ) -> None:
        """Attach ``ws_id`` to the running solve of ``h``, starting one if there is none:
        the worker's solve of revision ``rung`` of the ladder (:func:`revision_ladder`), or
        with ``atlas`` the chart by chart solve of an atlas (a thread handing the charts to
        the pool and the peers, :meth:`ChartShare.solve`)."""
        atlas = atlas or parse_atlas_ws_id(ws_id) is not None  # {ws}~atlas: never one map
        with self._lock:
            fut = self._inflight.get(h)
            if fut is None:
                ladder = self._ladder(defn)
                rung = min(rung, len(ladder) - 1)
                if atlas:
                    rung = len(ladder) - 1  # an atlas is solved to the definition's tol
                    box: list[cf.Future[dict[str, Any]]] = []
                    fut = self._atlas_threads.submit(
                        self.charts.solve,
                        h,
                        defn,
                        lambda: self.stopped or (bool(box) and box[0] in self._abandoned),
                    )
                    box.append(fut)
                elif not self.progressive:
                    prev = self._previous_map(ws_id, h)
                    args = (None, None, prev) if prev else ()
                    fut = self.submit_job(self._solve_fn, defn.model_dump_json(), *args)
                else:
                    max_error = COARSE_MAX_ERROR if rung == 0 and len(ladder) > 1 else None
                    # the last rung starts from the previous definition's map, if any
                    prev = self._previous_map(ws_id, h) if rung == len(ladder) - 1 else None
                    fut = self.submit_job(
                        self._solve_fn,
                        defn.model_dump_json(),
                        ladder[rung],
                        max_error,
                        *((prev,) if prev else ()),
                    )
                self._inflight[h] = fut
                self._rung[h] = rung
                self._started[h] = time.monotonic()
                self._attempts[h] = self._attempts.get(h, 0) + 1
                self.count("solves_started")
            rung = self._rung.get(h, 0)
        fut.add_done_callback(lambda f: self._done(ws_id, h, defn, f, rung))

    def _rebuild_pool(self, background: bool = False) -> None:
        """Replace a broken pool (lock held)."""
        if background:
            old, self._bg_pool = self._bg_pool, self._new_pool(background=True)
        else:
            old, self._pool = self._pool, self._new_pool()
        self.count("pool_rebuilds")
        log.warning("solver pool broken: rebuilt")
        if old is not None:
            old.shutdown(wait=False, cancel_futures=True)

    def _done(
        self,
        ws_id: str,
        h: str,
        defn: WorkspaceDefinition,
        fut: cf.Future[dict[str, Any]],
        rung: int = 0,
    ) -> None:
        if self.stopped:
            return  # the service stopped (its workers terminated): nothing to retry or publish
        with self._lock:
            if self._inflight.get(h) is fut:
                del self._inflight[h]
                self._started.pop(h, None)
            if fut in self._abandoned:
                return  # timed out: the workspace was failed already
            attempts = self._attempts.get(h, 0)
        try:
            result = fut.result()
        except cf.CancelledError:
            return
        except cf.BrokenExecutor as exc:  # the worker died (or was killed for a timeout)
            with self._lock:
                st = self._ws.get(ws_id)
                wanted = (
                    st is not None
                    and st.definition_hash == h
                    and st.state in ("solving", "refining")
                )
            if not wanted:
                return
            if attempts < self.max_attempts:
                self.count("solve_retries")
                log.warning("workspace %r: solver worker died (%s): retrying", ws_id, exc)
                self._solve(ws_id, h, defn, rung=rung)
                return
            reason = f"solver worker died {attempts} times ({type(exc).__name__}: {exc})"
            self._finish(ws_id, h, None, reason)
            return
        except Exception as exc:
            if self._more_rungs(ws_id, h, defn, rung):  # a coarse revision failed: refine
                log.info("workspace %r: revision %d failed (%s): refining", ws_id, rung, exc)
                return
            self._finish(ws_id, h, None, f"{type(exc).__name__}: {exc}")
            return
        if "needs_atlas" in result:  # too crowded for one map: solve its charts
            log.info("workspace %r: an atlas (%s)", ws_id, result["needs_atlas"])
            self._solve(ws_id, h, defn, atlas=True)
            return
        ladder = self._ladder(defn)
        final = rung >= len(ladder) - 1 or self._meets(result, defn.tol)
        if not final:
            self._finish(ws_id, h, result, None, final=False)  # a coarse revision
            nxt = rung + 1  # the next rung the estimate does not meet already
            while nxt < len(ladder) - 1 and self._meets(result, ladder[nxt]):
                nxt += 1
            self._more_rungs(ws_id, h, defn, nxt - 1)
            return
        with self._lock:
            self._remember(h, result)
            if "coefficients" in result:
                self._last_map[ws_id] = (h, result["coefficients"])
        self._store_cached(h, result)
        self._finish(ws_id, h, result, None)

    def _previous_map(self, ws_id: str, h: str) -> str | None:
        """The map JSON of ``ws_id``'s last solved definition if it is another than ``h``
        and the library's solver runs (a warm re-solve's start), else None."""
        if self._solve_fn is not solve_definition:
            return None  # a custom solve_fn takes the definition (and rung) only
        with self._lock:
            last = self._last_map.get(ws_id)
        if last is None or last[0] == h:
            return None
        return json.dumps(last[1])

    @staticmethod
    def _meets(result: dict[str, Any], tol: float) -> bool:
        """A revision's result meets ``tol`` already (its certificate: tol_met and estimate)."""
        d = result.get("diagnostics", {})
        return bool(d.get("tol_met")) and float(d.get("error_estimate", 1.0)) <= tol

    def _more_rungs(self, ws_id: str, h: str, defn: WorkspaceDefinition, rung: int) -> bool:
        """Start the revision after ``rung`` if there is one and ``ws_id`` still wants it."""
        if rung + 1 >= len(self._ladder(defn)) or self.stopped:
            return False
        with self._lock:
            st = self._ws.get(ws_id)
            if st is None or st.definition_hash != h or st.state not in ("solving", "refining"):
                return True  # superseded or deleted: nothing more to do, and nothing to fail
        self._solve(ws_id, h, defn, rung=rung + 1)
        return True

    def _timeout_loop(self) -> None:
        """Fail the solves running longer than ``solve_timeout`` s and kill their workers."""
        while not self._stop.wait(min(1.0, self.solve_timeout / 4)):
            now = time.monotonic()
            with self._lock:
                late = [h for h, t in self._started.items() if now - t > self.solve_timeout]
                futs = {h: self._inflight.pop(h) for h in late if h in self._inflight}
                for h in late:
                    self._started.pop(h, None)
                self._abandoned.update(futs.values())
                victims = [
                    (w, st.definition_hash)
                    for w, st in self._ws.items()
                    if st.definition_hash in futs and st.state in ("solving", "refining")
                ]
            if not futs:
                continue
            self.count("solve_timeouts", len(futs))
            for ws_id, h in victims:
                self._finish(ws_id, h, None, f"solve timed out after {self.solve_timeout:g} s")
            if self._executor_kind == "process":  # the only way to stop a running solve
                for child in multiprocessing.active_children():
                    child.terminate()  # the pool breaks: other solves are retried

    def _finish(
        self,
        ws_id: str,
        h: str,
        result: dict[str, Any] | None,
        error: str | None,
        final: bool = True,
    ) -> None:
        """Publish a solve's outcome: a failure, an atlas, or a map (with ``final`` False a
        coarse revision that a finer one follows: state ``refining``, status message
        :data:`REFINING`)."""
        if self.stopped:
            return
        if error is None and result is not None and "atlas" in result:
            error = finish_atlas(self, ws_id, h, result)  # publishes index and charts
            if error is None:
                return
            result = None
        msg: TransformSolution | None = None
        if error is None and result is not None:
            try:
                msg = TransformSolution(
                    ws_id=ws_id,
                    revision=result["revision"],
                    definition_hash=h,
                    workspace_hash=result["workspace_hash"],
                    stamp_ns=time.time_ns(),
                    anchor=tuple(result["anchor"]),
                    centers=[tuple(c) for c in result["centers"]],
                    radii=result["radii"],
                    diagnostics=SolveDiagnostics(**result["diagnostics"]),
                    coefficients=result["coefficients"],
                )
            except Exception as exc:
                error = f"bad solve result: {exc}"
        error = error or ("no result" if msg is None else None)
        data: bytes | None = None
        with self._lock:
            st = self._ws.get(ws_id)
            if st is None or st.definition_hash != h:
                return  # superseded by a newer definition
            if msg is None:
                st.state, st.error = "failed", error or ""
            else:
                self.atlases.forget(ws_id)  # solved as one map (again)
                if st.solution is None or st.revision != msg.revision:
                    data = encode(msg)
                    st.solution = data
                state = "solved" if final else "refining"
                st.state, st.error, st.revision = state, "", msg.revision
            rev = st.revision
        if msg is None:
            self.count("solves_failed")
            log.error("workspace %r failed: %s", ws_id, error)
            self._publish_status(ws_id, "failed", h, rev, error or "")
            return
        assert msg is not None
        d = msg.diagnostics
        accuracy = f"estimated error {d.error_estimate:.1e} (tol {d.tol:.0e})"
        if data is not None:
            self.bus.publish(self.keys.ws(ws_id, "transform"), data)
            self.count("solutions_published" if final else "revisions_published")
            log.info(
                "workspace %r %s: revision %s, %s",
                ws_id,
                "solved" if final else "coarse revision, refining",
                str(rev)[:12],
                accuracy,
            )
        note = "" if final else f"{REFINING}: {accuracy}; refining to {st.definition.tol:.0e}"
        self._publish_status(ws_id, "solved", h, rev, note)
        self.solved.set()

    def _fail(self, defn: WorkspaceDefinition, h: str, error: str) -> None:
        with self._lock:
            cur = self._ws.get(defn.ws_id)
            self._ws[defn.ws_id] = _WsState(
                defn,
                h,
                "failed",
                error,
                cur.solution if cur else None,
                cur.revision if cur else None,
            )
        self.count("rejected")
        log.warning("workspace %r: %s", defn.ws_id, error)
        self._publish_status(defn.ws_id, "failed", h, None, error)

    def _publish_status(self, ws_id: str, state: str, h: str, rev: str | None, msg: str) -> None:
        status = TransformStatus(
            ws_id=ws_id,
            stamp_ns=time.time_ns(),
            state=state,  # type: ignore[arg-type]
            definition_hash=h,
            revision=rev,
            message=msg[:4000],
        )
        self.bus.publish(self.keys.ws(ws_id, "status"), encode(status))

    # queries ---------------------------------------------------------------------------
    def _on_query(self, keyexpr: str, payload: bytes | None) -> list[tuple[str, bytes]]:
        self.count("queries")
        try:
            parsed = self.keys.parse(keyexpr)
        except KeyError_ as exc:
            if "*" not in keyexpr:  # not a wildcard: a malformed key (e.g. a 500-char id)
                self.count("bad_queries")
                raise QueryError(f"bad key {keyexpr[:80]!r}: {exc}") from None
            parsed = None
        if payload and parsed is not None:  # before a derive: its solve reads them
            self._take_hints(parsed.ident, payload)
        if parsed is not None:
            hit = self.atlases.answer(keyexpr, parsed.ident, parsed.kind)
            if hit is not None:
                return hit
        elif keyexpr.endswith("/atlas"):
            return self.atlases.answer_wildcard(keyexpr)
        if parsed is not None and parsed.ident not in self._ws:
            err = self._derive(parsed.ident)  # a footprint workspace {ws}~r{R} of a known one
            if err:
                raise QueryError(err)
        with self._lock:
            if parsed is None:  # a wildcard query: every solved workspace that matches
                found = [
                    (self.keys.ws(w, "transform"), s.solution)
                    for w, s in sorted(self._ws.items())
                    if s.solution is not None and key_matches(keyexpr, self.keys.ws(w, "transform"))
                ]
                if not found:
                    raise QueryError(f"no solved workspace matches {keyexpr[:80]!r}")
                return found
            st = self._ws.get(parsed.ident)
            if st is None:
                raise QueryError(f"unknown workspace {parsed.ident!r}")
            if st.state == "failed" and st.solution is None:
                raise QueryError(f"workspace {parsed.ident!r} is invalid: {st.error}")
            if st.solution is None:
                raise QueryError(f"workspace {parsed.ident!r} is being solved; retry")
            return [(keyexpr, st.solution)]

    def _take_hints(self, ws_id: str, payload: bytes) -> None:
        """Keep the route hints of a query's ``MapQuery`` payload for ``ws_id``'s atlas solve
        (docs/SLAM.md, "Progressive atlas"); a malformed payload is logged and ignored, the
        query answered as without it (routes outside the workspace are dropped by the
        solve, :func:`~confnav.services.atlas_transform.valid_routes`)."""
        try:
            q = decode(MapQuery, payload)
        except DecodeError as exc:
            self.count("bad_route_hints")
            log.warning("workspace %r: query payload ignored (%s)", ws_id, exc)
            return
        if q.routes:
            new = self.routes.add(ws_id, q.routes)
            self.count("route_hints", len(q.routes))
            if new:
                log.debug("workspace %r: %d new route hints", ws_id, new)

    def state_of(self, ws_id: str) -> str | None:
        with self._lock:
            st = self._ws.get(ws_id)
            return st.state if st else None

    # disk cache ------------------------------------------------------------------------
    def _definition_path(self, ws_id: str) -> Path | None:
        """``definitions/ws-<id, percent-encoded>.json``: never ``..`` or a path separator."""
        if self._cache_dir is None:
            return None
        return self._cache_dir / "definitions" / f"ws-{urllib.parse.quote(ws_id, safe='')}.json"

    def _save_definition(self, defn: WorkspaceDefinition) -> None:
        """Remember valid definitions put on the bus, so that a restarted service serves them."""
        path = self._definition_path(defn.ws_id)
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(encode(defn))
            tmp.replace(path)
        except OSError:
            log.warning("cannot save definition of %r", defn.ws_id, exc_info=True)

    def _load_saved_definitions(self) -> dict[str, WorkspaceDefinition]:
        out: dict[str, WorkspaceDefinition] = {}
        if self._cache_dir is None or not (self._cache_dir / "definitions").is_dir():
            return out
        for path in sorted((self._cache_dir / "definitions").glob("*.json")):
            try:
                defn = decode(WorkspaceDefinition, path.read_bytes())
                definition_hash(defn)  # valid geometry
            except Exception as exc:  # OSError, DecodeError, WorkspaceError
                log.warning("ignoring saved definition %s: %s", path, exc)
                continue
            out[defn.ws_id] = defn
        return out

    def _cache_path(self, h: str) -> Path | None:
        return self._cache_dir / f"{h}.json" if self._cache_dir else None

    def _load_cached(self, h: str) -> dict[str, Any] | None:
        path = self._cache_path(h)
        if path is None or not path.exists():
            return None
        try:
            result: dict[str, Any] = json.loads(path.read_text())
        except (OSError, ValueError):
            log.warning("unreadable cache entry %s", path)
            return None
        self._remember(h, result)
        return result

    def _store_cached(self, h: str, result: dict[str, Any]) -> None:
        path = self._cache_path(h)
        if path is None:
            return
        tmp = path.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(result))
            tmp.replace(path)
        except OSError:
            log.warning("cannot write cache entry %s", path, exc_info=True)


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("transform", help="run the transformation service")
    add_zenoh_args(p)
    p.add_argument(
        "--workspace",
        action="append",
        default=[],
        metavar="ID=PATH",
        help="workspace to load at start (PATH may be builtin:default)",
    )
    p.add_argument("--workers", type=int, default=2, help="concurrent solves")
    p.add_argument("--cache-dir", default=None, help="persist solutions by content hash here")
    p.add_argument(
        "--solve-timeout", type=float, default=900.0, help="s before a solve fails (killed)"
    )
    p.add_argument(
        "--max-attempts", type=int, default=3, help="solves per definition when workers die"
    )
    p.add_argument("--max-cached", type=int, default=32, help="solutions kept in memory (LRU)")
    p.add_argument(
        "--robot-radius",
        type=float,
        action="append",
        default=[],
        metavar="R",
        help="footprint radius (m; a unicycle's radius + look-ahead) whose shrunk maps "
        "{ws}~r{R} are solved ahead of use for every workspace (repeatable; robots spawned "
        "in a simulator add theirs)",
    )
    p.add_argument(
        "--progressive",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="publish a coarse revision of each map first, then refined ones up to the "
        "workspace's tol (docs/SERVICES.md); --no-progressive: the final map only",
    )
    p.add_argument(
        "--progressive-atlas",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --progressive: publish an atlas's charts as they are solved (partial "
        "revisions, a coarse atlas first; docs/SLAM.md; the default); "
        "--no-progressive-atlas: the complete atlas only",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    sources = parse_sources(args.workspace)

    def make(svc: TransformService) -> TransformService:
        svc.charts.progressive = bool(getattr(args, "progressive_atlas", True))
        return svc

    return run_until_signal(
        lambda bus, keys: make(
            TransformService(
                bus,
                keys,
                sources,
                workers=args.workers,
                cache_dir=args.cache_dir,
                solve_timeout=args.solve_timeout,
                max_attempts=args.max_attempts,
                max_cached=args.max_cached,
                progressive=args.progressive,
                robot_radii=tuple(args.robot_radius),
            )
        ),
        args,
    )


__all__ = [  # the shared helpers stay importable from here (services/definitions.py)
    "TransformService",
    "add_parser",
    "definition_hash",
    "definition_of",
    "derived_definition",
    "load_definition",
    "main",
    "parse_sources",
    "solution_result",
    "solve_definition",
    "workspace_of",
]
