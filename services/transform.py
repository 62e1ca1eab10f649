"""Transformation service: workspace definitions in, solved conformal maps out.

- loads workspaces from files (or the built-in ``default``) at start and publishes their
  definitions on ``{prefix}/ws/{ws}/definition`` so that recordings hold them;
- subscribes to ``{prefix}/ws/*/definition`` for new or changed workspaces;
- solves off the Zenoh threads, several workspaces at once (process pool by default),
  cached by the definition's content hash (optionally on disk, so a restart is instant);
- publishes ``TransformStatus`` and, when the solution changes, ``TransformSolution`` on
  ``{prefix}/ws/{ws}/transform``; serves the current solution from a complete queryable on
  ``{prefix}/ws/*/transform`` (``reply_err`` for unknown, invalid or not yet solved ones).

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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from confnav.schemas import (
    DecodeError,
    SolveDiagnostics,
    TransformSolution,
    TransformStatus,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.bus import Bus, QueryError
from confnav.services.keys import KeyError_, Keys
from confnav.services.runtime import Service, add_zenoh_args, run_until_signal

log = logging.getLogger(__name__)

SolveFn = Callable[[str], dict[str, Any]]
"""Takes a WorkspaceDefinition as JSON text, returns the solve result dict of
:func:`solve_definition` (must be picklable for the process pool)."""


def definition_hash(defn: WorkspaceDefinition) -> str:
    """Content hash of what determines the solution: the workspace geometry and ``tol``
    (not the ws id, not the time stamp). Validates the workspace with the core."""
    ws = workspace_of(defn)
    return hashlib.sha256(f"{ws.content_hash()}|tol={defn.tol!r}".encode()).hexdigest()


def workspace_of(defn: WorkspaceDefinition) -> Any:
    """The core :class:`confnav.Workspace` of a definition (raises WorkspaceError)."""
    from confnav.geometry import Workspace

    return Workspace(
        [tuple(p) for p in defn.outer],
        [[tuple(p) for p in o] for o in defn.obstacles],
        anchor=None if defn.anchor is None else complex(*defn.anchor),
    )


def definition_of(ws_id: str, workspace: Any, tol: float = 1e-10) -> WorkspaceDefinition:
    """A WorkspaceDefinition message for a core Workspace."""
    d = workspace.to_dict()
    return WorkspaceDefinition(
        ws_id=ws_id,
        outer=[(float(x), float(y)) for x, y in d["outer"]],
        obstacles=[[(float(x), float(y)) for x, y in o] for o in d["obstacles"]],
        anchor=None if d.get("anchor") is None else (float(d["anchor"][0]), float(d["anchor"][1])),
        tol=tol,
        stamp_ns=time.time_ns(),
    )


def derived_definition(ws_id: str, base: WorkspaceDefinition) -> WorkspaceDefinition:
    """The definition of ``{base}~r{R}``: ``base`` shrunk by a robot footprint of radius R
    (:func:`confnav.footprint.inflate`, largest component; raises WorkspaceError)."""
    from confnav.footprint import inflate, parse_derived_ws_id

    parsed = parse_derived_ws_id(ws_id)
    assert parsed is not None and parsed[0] == base.ws_id
    return definition_of(ws_id, inflate(workspace_of(base), parsed[1]), tol=base.tol)


def load_definition(ws_id: str, source: str) -> WorkspaceDefinition:
    """``builtin:default`` or a workspace file (JSON / GeoJSON, see ``Workspace.load``)."""
    if source == "builtin:default":
        from confnav.workspaces import default_workspace

        return definition_of(ws_id, default_workspace())
    from confnav.geometry import Workspace

    return definition_of(ws_id, Workspace.load(source))


def _xy(z: complex) -> tuple[float, float]:
    return (float(z.real), float(z.imag))


def solve_definition(defn_json: str) -> dict[str, Any]:
    """Solve one workspace (runs in a worker process): the map's coefficients and summary."""
    from confnav.solver import solve

    defn = WorkspaceDefinition.model_validate_json(defn_json)
    cmap = solve(workspace_of(defn), tol=defn.tol)
    diag = cmap.diagnostics
    nodes = getattr(diag, "nodes", None) or getattr(diag, "nodes_per_boundary", None) or []
    return {
        "revision": str(cmap.revision),
        "anchor": _xy(complex(cmap.anchor)),
        "centers": [_xy(complex(c)) for c in cmap.centers],
        "radii": [float(r) for r in cmap.radii],
        "diagnostics": {
            "sweeps": int(getattr(diag, "sweeps", 0)),
            "error_estimate": float(getattr(diag, "error_estimate", 0.0)),
            "wall_time": float(getattr(diag, "wall_time", 0.0)),
            "tol": float(getattr(diag, "tol", defn.tol)),
            "nodes": [int(n) for n in nodes],
        },
        # through JSON so that the result is plain JSON values (lists, not tuples/arrays)
        "coefficients": json.loads(cmap.to_json()),
    }


def _worker_init(parent: int) -> None:
    """In each solver process: exit when the service process dies (even by SIGKILL)."""
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
    state: str  # solving | solved | failed
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
    ) -> None:
        super().__init__(bus, keys, health_period)
        self.sources = dict(sources or {})
        self._solve_fn = solve_fn
        self._workers = workers
        self._executor_kind = executor
        self._pool: cf.Executor | None = None
        self._lock = threading.Lock()
        self._ws: dict[str, _WsState] = {}
        self._results: dict[str, dict[str, Any]] = {}  # definition hash -> solve result
        self._inflight: dict[str, cf.Future[dict[str, Any]]] = {}
        self._cache_dir = Path(cache_dir) if cache_dir else None
        self.solved = threading.Event()  # set each time a solution is published (tests)

    # lifecycle -------------------------------------------------------------------------
    def _start(self) -> None:
        if self._executor_kind == "process":
            ctx = multiprocessing.get_context("spawn")  # never fork a process holding Zenoh
            self._pool = cf.ProcessPoolExecutor(
                self._workers, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
            )
        else:
            self._pool = cf.ThreadPoolExecutor(self._workers, thread_name_prefix="solve")
        if self._cache_dir:
            self._cache_dir.mkdir(parents=True, exist_ok=True)
        self._handles.append(
            self.bus.subscribe(self.keys.any_ws("definition"), self._on_definition)
        )
        self._handles.append(self.bus.queryable(self.keys.any_ws("transform"), self._on_query))
        defs: dict[str, WorkspaceDefinition] = {}
        for ws_id, source in self.sources.items():
            try:
                defs[ws_id] = load_definition(ws_id, source)
            except Exception as exc:
                log.error("cannot load workspace %r from %s: %s", ws_id, source, exc)
                self.count("load_errors")
        defs.update(self._load_saved_definitions())  # later puts override the files
        for defn in defs.values():
            self.submit(defn)
            self.bus.publish(self.keys.ws(defn.ws_id, "definition"), encode(defn))

    def stop(self) -> None:
        super().stop()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)

    def health_detail(self) -> tuple[str, str]:
        with self._lock:
            failed = sorted(w for w, s in self._ws.items() if s.state == "failed")
            solving = sorted(w for w, s in self._ws.items() if s.state == "solving")
        detail = json.dumps({"failed": failed, "solving": solving})
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
        self.submit(defn)
        self._save_definition(defn)
        with self._lock:  # re-derive the footprint workspaces of this one ({ws}~r{R})
            derived = [w for w in self._ws if w.startswith(ws_id + "~r")]
        for w in derived:
            err = self._derive(w)
            if err:
                log.warning("%s", err)

    def _derive(self, ws_id: str) -> str:
        """Solve ``{base}~r{R}`` (a footprint workspace) from the known base definition;
        returns why it cannot be derived ("" if it was submitted or is not a derived id)."""
        from confnav.footprint import parse_derived_ws_id

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

    def submit(self, defn: WorkspaceDefinition) -> None:
        """Validate and (re)solve ``defn`` unless its solution is current or cached."""
        ws_id = defn.ws_id
        try:
            h = definition_hash(defn)
        except Exception as exc:  # WorkspaceError and anything the validation raises
            self._fail(defn, "invalid:" + ws_id, f"invalid workspace: {exc}")
            return
        with self._lock:
            cur = self._ws.get(ws_id)
            if cur is not None and cur.definition_hash == h and cur.state != "failed":
                return  # unchanged: nothing to do
            old_solution = cur.solution if cur else None
            old_rev = cur.revision if cur else None
            self._ws[ws_id] = _WsState(defn, h, "solving", "", old_solution, old_rev)
            result = self._results.get(h) or self._load_cached(h)
            fut = None
            if result is None:
                fut = self._inflight.get(h)
                if fut is None:
                    assert self._pool is not None, "service not started"
                    fut = self._pool.submit(self._solve_fn, defn.model_dump_json())
                    self._inflight[h] = fut
                    self.count("solves_started")
        if result is not None:
            self.count("cache_hits")
            self._finish(ws_id, h, result, None)
            return
        self._publish_status(ws_id, "solving", h, old_rev, "")
        assert fut is not None
        fut.add_done_callback(lambda f: self._done(ws_id, h, f))

    def _done(self, ws_id: str, h: str, fut: cf.Future[dict[str, Any]]) -> None:
        with self._lock:
            self._inflight.pop(h, None)
        try:
            result = fut.result()
        except cf.CancelledError:
            return
        except Exception as exc:
            self._finish(ws_id, h, None, f"{type(exc).__name__}: {exc}")
            return
        with self._lock:
            self._results[h] = result
        self._store_cached(h, result)
        self._finish(ws_id, h, result, None)

    def _finish(self, ws_id: str, h: str, result: dict[str, Any] | None, error: str | None) -> None:
        if self.stopped:
            return
        msg: TransformSolution | None = None
        if error is None and result is not None:
            try:
                msg = TransformSolution(
                    ws_id=ws_id,
                    revision=result["revision"],
                    definition_hash=h,
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
                if st.solution is None or st.revision != msg.revision:
                    data = encode(msg)
                    st.solution = data
                st.state, st.error, st.revision = "solved", "", msg.revision
            rev = st.revision
        if msg is None:
            self.count("solves_failed")
            log.error("workspace %r failed: %s", ws_id, error)
            self._publish_status(ws_id, "failed", h, rev, error or "")
            return
        if data is not None:
            self.bus.publish(self.keys.ws(ws_id, "transform"), data)
            self.count("solutions_published")
            log.info("workspace %r solved: revision %s", ws_id, str(rev)[:12])
        self._publish_status(ws_id, "solved", h, rev, "")
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
        except KeyError_:
            parsed = None
        if parsed is not None and parsed.ident not in self._ws:
            err = self._derive(parsed.ident)  # a footprint workspace {ws}~r{R} of a known one
            if err:
                raise QueryError(err)
        with self._lock:
            if parsed is None:  # a wildcard query: every solved workspace that matches
                from confnav.services.bus import key_matches

                return [
                    (self.keys.ws(w, "transform"), s.solution)
                    for w, s in sorted(self._ws.items())
                    if s.solution is not None and key_matches(keyexpr, self.keys.ws(w, "transform"))
                ]
            st = self._ws.get(parsed.ident)
            if st is None:
                raise QueryError(f"unknown workspace {parsed.ident!r}")
            if st.state == "failed" and st.solution is None:
                raise QueryError(f"workspace {parsed.ident!r} is invalid: {st.error}")
            if st.solution is None:
                raise QueryError(f"workspace {parsed.ident!r} is being solved; retry")
            return [(keyexpr, st.solution)]

    def state_of(self, ws_id: str) -> str | None:
        with self._lock:
            st = self._ws.get(ws_id)
            return st.state if st else None

    # disk cache ------------------------------------------------------------------------
    def _save_definition(self, defn: WorkspaceDefinition) -> None:
        """Remember definitions put on the bus, so that a restarted service serves them."""
        if self._cache_dir is None:
            return
        d = self._cache_dir / "definitions"
        try:
            d.mkdir(parents=True, exist_ok=True)
            tmp = d / f"{defn.ws_id}.tmp"
            tmp.write_bytes(encode(defn))
            tmp.replace(d / f"{defn.ws_id}.json")
        except OSError:
            log.warning("cannot save definition of %r", defn.ws_id, exc_info=True)

    def _load_saved_definitions(self) -> dict[str, WorkspaceDefinition]:
        out: dict[str, WorkspaceDefinition] = {}
        if self._cache_dir is None or not (self._cache_dir / "definitions").is_dir():
            return out
        for path in sorted((self._cache_dir / "definitions").glob("*.json")):
            try:
                defn = decode(WorkspaceDefinition, path.read_bytes())
            except (OSError, DecodeError) as exc:
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
        self._results[h] = result
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


def parse_sources(items: list[str]) -> dict[str, str]:
    """``ID=PATH`` items (PATH may be ``builtin:default``)."""
    out = {}
    for item in items:
        ws_id, sep, path = item.partition("=")
        if not sep:
            raise SystemExit(f"--workspace expects ID=PATH, got {item!r}")
        out[ws_id] = path
    return out


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
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    sources = parse_sources(args.workspace)
    return run_until_signal(
        lambda bus, keys: TransformService(
            bus, keys, sources, workers=args.workers, cache_dir=args.cache_dir
        ),
        args,
    )
