"""The transform service's side of atlases (issue 15 items 1 and 3).

A workspace too crowded for one map (:func:`confnav.atlas.needs_atlas`, or a
``CrowdingError`` of the single solve in a worker, :func:`single_or_atlas`) is solved as an
atlas by :class:`ChartShare` in a thread of the service: :func:`confnav.atlas.solve_atlas`
decomposes it there and hands the cells to a :class:`SharedExecutor`, which solves them on
the service's worker pool (``--workers`` at once) and splits them with the other transform
service instances on the bus:

- a cell's chart job has a content key (a hash of the cell workspace, ``tol``, the accepted
  error and the probe depth: :func:`job_key`); before solving it, an instance queries
  ``{prefix}/chart/{atlas}/{job}`` (answered by every instance that holds the result, solved
  or fetched) and skips a job another instance has claimed;
- a claim is a liveliness token ``{prefix}/claim/{atlas}/{job}/{zid}``, declared while the
  chart solves and undeclared after its result is served; a dead instance's tokens vanish
  with its session, so its jobs are free again and solved by the others;
- each instance starts with its own share (job ``j`` of ``n`` is instance ``j mod n``'s, by
  rank of the zids of the live transform services) and then takes whatever is left; two
  instances that claim one job at the same instant both solve it, harmless (the solve is a
  deterministic function of the job), so the result is that of one instance alone.

The service then publishes

- one ``TransformSolution`` per chart on ``{prefix}/ws/{ws}~c{i}/transform`` (the cell's own
  workspace id: queryable exactly like any transform),
- the ``AtlasIndex`` on ``{prefix}/ws/{ws}/atlas`` (after the charts, so a subscriber that
  sees the index can query them),
- ``TransformStatus`` ``solved`` with the atlas revision.

A transform query on the atlas workspace itself is answered with ``reply_err`` starting with
:data:`confnav.atlas.wire.ATLAS_MARKER` (the controller then fetches the atlas).
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import logging
import threading
import time
from collections import OrderedDict, defaultdict
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from confnav.schemas import AtlasCell, AtlasIndex, SolveDiagnostics, TransformSolution, encode
from confnav.services.bus import Closeable, QueryError, key_matches
from confnav.services.definitions import (
    COARSE_MAX_ERROR,
    LADDER,
    solution_result,
    workspace_of,
)

from confnav.atlas.charts import atlas_reason, solve_atlas
from confnav.atlas.wire import ATLAS_MARKER, atlas_revision, chart_ws_id, index_fields
from confnav.conformal.solver import crowding_reason, solve
from confnav.errors import CrowdingError, SolverError, fmt_point
from confnav.maps.footprint import parse_derived_ws_id

if TYPE_CHECKING:
    from confnav.services.transform import TransformService

log = logging.getLogger(__name__)

#: Atlases whose chart results an instance keeps serving to its peers (least recent dropped).
KEEP_ATLASES = 8

#: Seconds between checks of the claims while waiting for a peer's chart (a claim that
#: vanishes or a local solve that ends wakes the wait at once).
POLL = 0.5
#: s a background atlas's decomposition waits at most, per wait, for an atlas robots wait
#: for to publish its first revision (:meth:`ChartShare.hold`)
HOLD_MAX_S = 10.0


def single_or_atlas(
    ws: Any, tol: float, max_error: float | None = None, initial: Any = None
) -> dict[str, Any]:
    """Worker: one map's result dict, or ``{"needs_atlas": why}`` (the service then solves
    the atlas chart by chart, :meth:`ChartShare.solve`): when the a-priori test flags the
    workspace, when the single solve raises a crowding error mid-solve, and when the solved
    map measures crowding (:func:`confnav.conformal.solver.crowding_reason`: a boundary
    crowded by 10^6 or more, where the map's absolute accuracy says nothing of the positions
    it separates). ``max_error``:
    the largest estimated error accepted (``solve(max_error=...)``, a coarse revision);
    ``initial``: a previous map to re-solve from (``solve(initial=...)``)."""
    why = atlas_reason(ws)
    if why:
        return {"needs_atlas": why}
    try:
        kw: dict[str, Any] = {} if max_error is None else {"max_error": max_error}
        m = solve(ws, tol, initial=initial, **kw)
    except CrowdingError as exc:
        return {"needs_atlas": f"one map crowds: {exc}"}
    crowded = crowding_reason(m.diagnostics)  # accurate on the circles, useless where it crowds
    return {"needs_atlas": f"one map crowds: {crowded}"} if crowded else solution_result(m, tol)


def atlas_result(atlas: Any) -> dict[str, Any]:
    """The result dict of a solved :class:`confnav.atlas.Atlas` (or of a
    :class:`confnav.atlas.charts.PartialAtlas`, its pending charts ``None``): ``{"atlas":
    index fields, "charts": [result dicts]}`` (what :func:`messages_of` turns into
    messages)."""
    return {
        "atlas": index_fields(atlas),
        "charts": [None if m is None else solution_result(m, atlas.tol) for m in atlas.charts],
    }


def job_key(*args: Any) -> str:
    """Content key of a chart job (the arguments of the cell solve: cell workspace JSON,
    ``tol``, accepted error, probe depth): equal jobs give equal charts on every instance."""
    return hashlib.sha256(json.dumps([repr(a) for a in args]).encode()).hexdigest()[:32]


#: Route hints kept per workspace (the most recent robots' routes; older ones dropped).
MAX_HINTS = 256


class RouteBook:
    """The robots' routes the controllers sent with their map queries (``MapQuery``), per
    workspace id (thread-safe): a robot's newer route replaces its older one. Read by the
    atlas solves as ``solve_atlas(priority=...)`` (:meth:`ChartShare.solve`)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_ws: dict[str, OrderedDict[str, tuple[complex, complex]]] = {}

    def add(self, ws_id: str, routes: Iterable[Any]) -> int:
        """Keep the ``RouteHint`` s ``routes`` of ``ws_id``; returns how many were new."""
        new = 0
        with self._lock:
            book = self._by_ws.setdefault(ws_id, OrderedDict())
            for r in routes:
                pair = (complex(*r.start), complex(*r.goal))
                key = r.robot_id or f"{pair[0]}>{pair[1]}"
                if book.get(key) != pair:
                    new += 1
                book[key] = pair
                book.move_to_end(key)
            while len(book) > MAX_HINTS:
                book.popitem(last=False)
        return new

    def pairs(self, ws_ids: Iterable[str]) -> list[tuple[complex, complex]]:
        """Every kept (start, goal) pair of the workspaces ``ws_ids``, oldest first."""
        with self._lock:
            return [p for w in ws_ids for p in self._by_ws.get(w, {}).values()]

    def waited_for(self, ws_ids: Iterable[str]) -> bool:
        """Whether robots wait for the map of ``ws_ids`` (one definition's ids): a route of
        one of them, unless every such id is a base map ``{ws}`` whose footprint map
        ``{ws}~r{R}`` has routes too -- the robots with a body wait for their footprint map
        and ask for the base only to drive on it meanwhile, which the footprint atlas,
        solved first, makes moot (docs/SLAM.md "Background atlases")."""
        with self._lock:
            hinted = {w for w, book in self._by_ws.items() if book}
        footprint_bases = {p[0] for h in hinted if (p := parse_derived_ws_id(h)) is not None}
        return any(w in hinted and w not in footprint_bases for w in ws_ids)

    def forget(self, ws_id: str) -> None:
        with self._lock:
            self._by_ws.pop(ws_id, None)


def valid_routes(
    ws: Any, pairs: list[tuple[complex, complex]], seen: dict[tuple[complex, complex], bool]
) -> list[tuple[complex, complex]]:
    """The pairs whose start and goal lie in the free space of ``ws`` (vectorized
    ``Workspace.contains``); each pair not seen before is checked once (``seen``, updated)
    and an ignored one says so in the log."""
    todo = [p for p in pairs if p not in seen]
    if todo:
        z = np.array([[a, b] for a, b in todo], dtype=np.complex128)
        inside = np.asarray(ws.contains(z.ravel()), dtype=bool).reshape(z.shape)
        ok: list[bool] = [bool(v) for v in np.all(inside, axis=1).tolist()]
        for p, good in zip(todo, ok, strict=True):
            seen[p] = good
            if not good:
                log.info(
                    "route hint %s -> %s is outside the workspace: ignored",
                    fmt_point(p[0]), fmt_point(p[1]),
                )  # fmt: skip
    return [p for p in pairs if seen[p]]


class AtlasAbandoned(Exception):
    """The atlas solve was abandoned (timed out, superseded or the service stopped)."""


def _pt(p: Any) -> tuple[float, float]:
    return (float(p[0]), float(p[1]))


#: ``chart_revision`` of a pending cell of a partial revision (``AtlasCell.pending``)
PENDING = "pending"


def messages_of(
    ws_id: str, h: str, result: dict[str, Any]
) -> tuple[AtlasIndex, list[TransformSolution]]:
    """The index and chart messages of an atlas result (tuples restored after JSON); a
    partial revision's pending cells are marked ``pending`` and have no chart message."""
    now = time.time_ns()
    charts = [
        None
        if c is None  # a partial revision's pending chart
        else TransformSolution(
            ws_id=chart_ws_id(ws_id, i),
            revision=c["revision"],
            definition_hash=h,
            workspace_hash=c["workspace_hash"],
            stamp_ns=now,
            anchor=_pt(c["anchor"]),
            centers=[_pt(p) for p in c["centers"]],
            radii=[float(r) for r in c["radii"]],
            diagnostics=SolveDiagnostics(**c["diagnostics"]),
            coefficients=c["coefficients"],
        )
        for i, c in enumerate(result["charts"])
    ]
    a = result["atlas"]

    def rev(i: int) -> str:
        m = charts[i]
        return PENDING if m is None else m.revision

    cells = [
        AtlasCell(
            index=int(c["index"]),
            chart_ws_id=chart_ws_id(ws_id, int(c["index"])),
            chart_revision=rev(int(c["index"])),
            pending=charts[int(c["index"])] is None,
            outer=[_pt(p) for p in c["outer"]],
            obstacles=[[_pt(p) for p in o] for o in c["obstacles"]],
            cut=[[_pt(p) for p in line] for line in c["cut"]],
            tile=tuple(float(v) for v in c["tile"]),  # type: ignore[arg-type]
            solve_time=float(c["solve_time"]),
        )
        for c in a["cells"]
    ]
    index = AtlasIndex(
        ws_id=ws_id,
        revision=atlas_revision([rev(i) for i in range(len(charts))]),
        definition_hash=h,
        stamp_ns=now,
        margin=float(a["margin"]),
        tol=float(a["tol"]),
        cells=cells,
        decomposition=a["decomposition"],
        wall_time=float(a["wall_time"]),
        cpu_time=float(a["cpu_time"]),
    )
    return index, [c for c in charts if c is not None]


class AtlasStore:
    """The encoded index and charts of every workspace served as an atlas (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._index: dict[str, bytes] = {}  # ws id -> AtlasIndex
        self._charts: dict[str, bytes] = {}  # chart ws id -> TransformSolution
        self._owned: dict[str, list[str]] = {}  # ws id -> its chart ids

    def put(self, ws_id: str, index: bytes, charts: dict[str, bytes]) -> None:
        with self._lock:
            self._forget(ws_id)
            self._index[ws_id] = index
            self._charts.update(charts)
            self._owned[ws_id] = list(charts)

    def forget(self, ws_id: str) -> None:
        with self._lock:
            self._forget(ws_id)

    def _forget(self, ws_id: str) -> None:
        self._index.pop(ws_id, None)
        for c in self._owned.pop(ws_id, []):
            self._charts.pop(c, None)

    def answer(self, keyexpr: str, ident: str, kind: str) -> list[tuple[str, bytes]] | None:
        """Replies to a concrete query, or None if it is not about an atlas."""
        with self._lock:
            if kind == "atlas":
                data = self._index.get(ident)
                if data is None:
                    raise QueryError(f"workspace {ident!r} is not solved as an atlas")
                return [(keyexpr, data)]
            if kind == "transform":
                chart = self._charts.get(ident)
                if chart is not None:
                    return [(keyexpr, chart)]
                if ident in self._index:
                    raise QueryError(
                        f"{ATLAS_MARKER} workspace {ident!r} is solved as an atlas of "
                        f"{len(self._owned[ident])} charts: query ws/{ident}/atlas"
                    )
        return None

    def answer_wildcard(self, keyexpr: str) -> list[tuple[str, bytes]]:
        """Every atlas index whose key matches a wildcard ``.../ws/*/atlas`` query."""
        prefix = keyexpr.split("/ws/")[0]
        with self._lock:
            found = [
                (f"{prefix}/ws/{w}/atlas", d)
                for w, d in sorted(self._index.items())
                if key_matches(keyexpr, f"{prefix}/ws/{w}/atlas")
            ]
        if not found:
            raise QueryError(f"no atlas matches {keyexpr[:80]!r}")
        return found


def finish_atlas(svc: TransformService, ws_id: str, h: str, result: dict[str, Any]) -> str | None:
    """Install and publish an atlas result of ``ws_id``; the error if the result is bad."""
    try:
        index, charts = messages_of(ws_id, h, result)
    except Exception as exc:
        return f"bad atlas result: {exc}"
    encoded = {c.ws_id: encode(c) for c in charts}
    with svc._lock:
        st = svc._ws.get(ws_id)
        if st is None or st.definition_hash != h:
            return None  # superseded by a newer definition
        new = st.revision != index.revision
        st.state, st.error, st.revision, st.solution = "solved", "", index.revision, None
        svc.atlases.put(ws_id, encode(index), encoded)
    if new:
        for cid, data in encoded.items():
            svc.bus.publish(svc.keys.ws(cid, "transform"), data)
        svc.bus.publish(svc.keys.ws(ws_id, "atlas"), encode(index))
        svc.count("atlases_published")
        svc.count("solutions_published")
    svc._publish_status(ws_id, "solved", h, index.revision, f"atlas of {len(charts)} charts")
    svc.solved.set()
    return None


def publish_partial(svc: TransformService, h: str, atlas: Any, sent: set[str]) -> None:
    """Publish a revision of an atlas being solved (a :class:`PartialAtlas`, or a complete
    coarse atlas a finer one follows) for every workspace waiting for definition ``h``: its
    new charts, then its index (cells without a chart ``pending``), and a ``solving`` status
    saying how many charts robots can drive on. ``sent``: the chart revisions published
    already (updated). The state stays ``solving`` until :func:`finish_atlas`."""
    n = len(atlas.charts)
    k = sum(m is not None for m in atlas.charts)
    if k == 0:
        return
    with svc._lock:
        targets = [
            w
            for w, st in svc._ws.items()
            if st.definition_hash == h and st.state in ("solving", "refining")
        ]
    if not targets:
        return
    result = atlas_result(atlas)
    for ws_id in targets:
        try:
            index, charts = messages_of(ws_id, h, result)
        except Exception as exc:  # a bad revision is skipped; the final atlas follows
            log.warning("workspace %r: partial atlas not published: %s", ws_id, exc)
            continue
        encoded = {c.ws_id: encode(c) for c in charts}
        with svc._lock:
            st = svc._ws.get(ws_id)
            if st is None or st.definition_hash != h or st.state not in ("solving", "refining"):
                continue
            svc.atlases.put(ws_id, encode(index), encoded)
        for c in charts:
            key = f"{ws_id}|{c.revision}"
            if key not in sent:
                svc.bus.publish(svc.keys.ws(c.ws_id, "transform"), encoded[c.ws_id])
                sent.add(key)
        svc.bus.publish(svc.keys.ws(ws_id, "atlas"), encode(index))
        svc.count("atlas_revisions_published")
        log.info("workspace %r: atlas revision with %d of %d charts published", ws_id, k, n)
        what = "complete, refining" if k == n else "robots drive on them, the rest follow"
        svc._publish_status(
            ws_id,
            "solving",
            h,
            None,
            f"atlas: {k} of {n} charts solved to {atlas.tol:g} ({what})",
        )


ChartResult = tuple[str, float, str]
"""What a cell solve returns (:func:`confnav.atlas.charts._solve_one`): the map's JSON (""
if it failed), the solve's wall time, the failure message."""


class ChartShare:
    """An instance's part in solving atlases with its peers (see the module docstring):
    serves the chart results it holds on ``{prefix}/chart/{atlas}/{job}`` and tracks the
    claims ``{prefix}/claim/{atlas}/{job}/{zid}`` of every instance."""

    def __init__(self, svc: TransformService) -> None:
        self.svc = svc
        self.prefix = svc.keys.prefix
        self._cond = threading.Condition()
        # atlas key -> job key -> encoded ChartResult (least recently used atlas first)
        self._results: OrderedDict[str, dict[str, bytes]] = OrderedDict()
        self._claims: defaultdict[tuple[str, str], set[str]] = defaultdict(set)
        #: publish an atlas's charts as they come (:meth:`solve`, docs/SLAM.md "Progressive
        #: atlas"); the default, ``serve transform --no-progressive-atlas`` turns it off (a
        #: consumer then sees one complete atlas revision per definition)
        self.progressive = True
        #: atlases robots wait for whose first revision is not out yet: the background
        #: atlases' decompositions hold meanwhile (:meth:`hold`)
        self._starting: set[str] = set()

    def start(self) -> list[Closeable]:
        """Declare the chart queryable and the claim subscriber (the handles to close)."""
        return [
            # not complete: each instance holds some results, a query must reach them all
            self.svc.bus.queryable(f"{self.prefix}/chart/*/*", self._on_query, complete=False),
            self.svc.bus.subscribe_liveliness(f"{self.prefix}/claim/*/*/*", self._on_claim),
        ]

    # bus side ------------------------------------------------------------------------
    def _on_query(self, keyexpr: str, payload: bytes | None) -> list[tuple[str, bytes]]:
        with self._cond:
            return [
                (key, data)
                for a, jobs in self._results.items()
                for j, data in jobs.items()
                if key_matches(keyexpr, key := f"{self.prefix}/chart/{a}/{j}")
            ]

    def _on_claim(self, key: str, alive: bool) -> None:
        parts = key[len(self.prefix) + 1 :].split("/")
        if len(parts) != 4 or parts[0] != "claim":
            return
        _, a, j, zid = parts
        with self._cond:
            if alive:
                self._claims[(a, j)].add(zid)
            else:
                self._claims[(a, j)].discard(zid)
                if not self._claims[(a, j)]:
                    del self._claims[(a, j)]
            self._cond.notify_all()

    def _claimed_by_peer(self, a: str, j: str) -> bool:
        with self._cond:
            return bool(self._claims.get((a, j), set()) - {self.svc.bus.zid})

    def _keep(self, a: str, j: str, result: ChartResult) -> None:
        with self._cond:
            self._results.setdefault(a, {})[j] = json.dumps(list(result)).encode()
            self._results.move_to_end(a)
            while len(self._results) > KEEP_ATLASES:
                self._results.popitem(last=False)

    def _fetch(self, a: str, j: str) -> ChartResult | None:
        """A peer's result of job ``j`` (None if nobody holds it)."""
        for r in self.svc.bus.query(f"{self.prefix}/chart/{a}/{j}", timeout=2.0):
            if not r.ok or r.payload is None:
                continue
            try:
                text, wall, err = json.loads(r.payload)
                result = (str(text), float(wall), str(err))
            except (ValueError, TypeError):
                log.warning("bad chart result on %s: ignored", r.key)
                continue
            self._keep(a, j, result)
            return result
        return None

    def _order(self, n: int) -> list[int]:
        """Job order for this instance: its share (``j mod size == rank``, by the live
        transform services' zids) first, then the others' from their ends (stealing)."""
        alive = self.svc.bus.alive(self.svc.keys.alive_of("transform"))
        zids = {k.rsplit("/", 1)[-1] for k in alive}
        ranked = sorted(zids | {self.svc.bus.zid})
        size, rank = len(ranked), ranked.index(self.svc.bus.zid)
        mine = [i for i in range(n) if i % size == rank]
        return mine + [i for i in reversed(range(n)) if i % size != rank]

    # solving -------------------------------------------------------------------------
    def solve(self, h: str, defn: Any, abandoned: Callable[[], bool]) -> dict[str, Any]:
        """Solve the atlas of definition ``defn`` (hash ``h``) with the peers (a thread of
        the service); raises :class:`AtlasAbandoned` or what ``solve_atlas`` raises.

        Progressive (:attr:`progressive` and the service's ``progressive``, docs/SLAM.md
        "Progressive atlas"): the cells the robots' routes need (the route hints of the
        controllers' queries, :class:`RouteBook`, read before every batch) are solved first;
        the charts are published as they come, a partial revision per ``workers`` charts
        (:func:`publish_partial`), first to the ladder's first tolerance (accepted up to
        ``COARSE_MAX_ERROR``) when the definition asks for a finer one, whose complete
        atlas is a revision too; then the atlas to the definition's ``tol``, returned (the
        final revision, :func:`finish_atlas`)."""
        svc = self.svc

        def ids() -> list[str]:
            with svc._lock:
                return [w for w, st in svc._ws.items() if st.definition_hash == h]

        def background() -> bool:
            """No robot waits for this atlas (:meth:`RouteBook.waited_for`): its charts go
            to the background pool and its decomposition holds for those robots wait for."""
            return not svc.routes.waited_for(ids())

        ex = SharedExecutor(self, h[:32], abandoned, background)
        ws = workspace_of(defn)
        workers = svc.workers
        kw: dict[str, Any] = {"pause": lambda: self.hold(h, background, abandoned)}
        if not (self.progressive and getattr(svc, "progressive", False)):
            return atlas_result(solve_atlas(ws, defn.tol, workers=workers, executor=ex, **kw))
        sent: set[str] = set()
        checked: dict[tuple[complex, complex], bool] = {}
        if not background():
            self._started(h, True)

        def routes() -> list[tuple[complex, complex]]:
            """The route hints of every workspace waiting for ``h``, those in ``ws``."""
            return valid_routes(ws, svc.routes.pairs(ids()), checked)

        def publish(pa: Any) -> None:
            self._started(h, False)
            if not abandoned():
                publish_partial(svc, h, pa, sent)

        try:
            return self._solve_progressive(ws, defn, ex, routes, publish, kw)
        finally:
            self._started(h, False)

    def _solve_progressive(
        self,
        ws: Any,
        defn: Any,
        ex: SharedExecutor,
        routes: Callable[[], list[tuple[complex, complex]]],
        publish: Callable[[Any], None],
        kw: dict[str, Any],
    ) -> dict[str, Any]:
        """:meth:`solve`'s progressive atlas: a coarse atlas first when the definition asks
        for a finer one, its charts published as they come, then the final atlas."""
        workers = self.svc.workers
        first = LADDER[0]
        if defn.tol < first:
            try:
                # its complete revision is the last partial one
                solve_atlas(
                    ws, first, workers=workers, executor=ex, on_partial=publish, batch=workers,
                    accept=max(first, COARSE_MAX_ERROR), priority=routes, **kw,
                )  # fmt: skip
            except SolverError as exc:  # the final atlas may still solve: go on to it
                log.info("atlas %s: no coarse revision (%s)", ex.atlas_key[:12], exc)
            atlas = solve_atlas(ws, defn.tol, workers=workers, executor=ex, **kw)
        else:
            atlas = solve_atlas(
                ws, defn.tol, workers=workers, executor=ex, on_partial=publish, batch=workers,
                priority=routes, **kw,
            )  # fmt: skip
        return atlas_result(atlas)

    def _started(self, h: str, starting: bool) -> None:
        """Mark the atlas ``h`` as one robots wait for whose first revision is not out yet
        (``starting``), or no longer."""
        with self._cond:
            if starting:
                self._starting.add(h)
            elif h in self._starting:
                self._starting.discard(h)
                self._cond.notify_all()

    def hold(self, h: str, background: Callable[[], bool], abandoned: Callable[[], bool]) -> None:
        """``decompose``'s pause hook (between two tiles, a few ms apart): a background
        atlas's decomposition waits while an atlas robots wait for has no revision out yet
        (at most :data:`HOLD_MAX_S` per wait). Threads of one interpreter share it: the
        footprint atlas's decomposition ran at half speed beside its base's (docs/SLAM.md
        "Background atlases"). The decomposition does not depend on the wait."""
        deadline = time.monotonic() + HOLD_MAX_S
        held = False
        while time.monotonic() < deadline and not abandoned() and background():
            # background() takes the service's lock: asked outside this one's condition
            with self._cond:
                if not self._starting - {h}:
                    break
                held = True
                self._cond.wait(0.05)
        if held:
            self.svc.count("atlas_holds")

    def run(
        self,
        a: str,
        fn: Callable[..., ChartResult],
        jobs: list[tuple[Any, ...]],
        abandoned: Callable[[], bool],
        background: Callable[[], bool] = lambda: False,
    ) -> list[ChartResult]:
        """Every job's result, in order: fetched from a peer, or solved on the service's
        pool (at most ``workers`` at once) under a claim token; on the background pool
        while ``background()`` (asked at each submission: no robot waits for the atlas)."""
        keys = [job_key(*args) for args in jobs]
        order = self._order(len(jobs))
        results: dict[int, ChartResult] = {}
        running: dict[cf.Future[ChartResult], int] = {}
        on_bg: dict[cf.Future[ChartResult], bool] = {}  # submitted to the background pool
        tokens: dict[int, Closeable] = {}
        failures: defaultdict[int, int] = defaultdict(int)
        bus, svc = self.svc.bus, self.svc

        def wake(_f: object) -> None:
            with self._cond:
                self._cond.notify_all()

        try:
            while len(results) < len(jobs):
                if abandoned():
                    raise AtlasAbandoned(f"atlas {a}: abandoned")
                # at most ``workers`` at once on the pool in use: an atlas robots came to
                # wait for starts its jobs on the normal pool beside those still running
                # on the background pool (a footprint map solved ahead, then a goal)
                bg = background()
                free = svc.workers - sum(on_bg[f] == bg for f in running)
                for i in order:
                    if free <= 0:
                        break
                    if i in results or i in tokens or self._claimed_by_peer(a, keys[i]):
                        continue
                    got = self._fetch(a, keys[i])
                    if got is not None:
                        results[i] = got
                        svc.count("charts_fetched")
                        continue
                    tokens[i] = bus.declare_token(f"{self.prefix}/claim/{a}/{keys[i]}/{bus.zid}")
                    fut = svc.submit_job(fn, *jobs[i], background=bg)
                    on_bg[fut] = bg
                    fut.add_done_callback(wake)
                    running[fut] = i
                    free -= 1
                if len(results) == len(jobs):
                    break
                with self._cond:
                    if not any(f.done() for f in running):
                        self._cond.wait(POLL)
                for fut in [f for f in running if f.done()]:
                    i = running.pop(fut)
                    on_bg.pop(fut, None)
                    try:
                        res = fut.result()
                    except (cf.BrokenExecutor, cf.CancelledError) as exc:
                        tokens.pop(i).close()  # free again: retried (here or by a peer)
                        failures[i] += 1
                        svc.count("chart_retries")
                        if failures[i] >= svc.max_attempts:
                            raise SolverError(
                                f"atlas {a}: chart job failed {failures[i]} times ({exc!r})"
                            ) from exc
                        continue
                    self._keep(a, keys[i], res)  # served before the claim goes
                    tokens.pop(i).close()
                    results[i] = res
                    svc.count("charts_solved")
        finally:
            for t in tokens.values():
                t.close()
            for f in running:
                f.cancel()
        return [results[i] for i in range(len(jobs))]


class SharedExecutor(cf.Executor):
    """The executor :func:`confnav.atlas.solve_atlas` solves one atlas's cells with: its
    ``map`` runs :meth:`ChartShare.run`; its ``submit`` runs one job the same way in a
    thread (the robots' start cells, started while the decomposition's next pass is cut,
    and a revision after each of their charts: :func:`confnav.atlas.charts._solve_streaming`).
    """

    #: :func:`confnav.atlas.charts._submits`: single charts go through :meth:`submit`
    submits_charts = True

    def __init__(
        self,
        share: ChartShare,
        atlas_key: str,
        abandoned: Callable[[], bool],
        background: Callable[[], bool] = lambda: False,
    ) -> None:
        self.share, self.atlas_key, self.abandoned = share, atlas_key, abandoned
        self.background = background

    def map(  # type: ignore[override]
        self, fn: Callable[..., ChartResult], *iterables: Iterable[Any], **_kw: Any
    ) -> Iterator[ChartResult]:
        jobs = list(zip(*iterables, strict=True))
        return iter(self.share.run(self.atlas_key, fn, jobs, self.abandoned, self.background))

    def submit(  # type: ignore[override]
        self, fn: Callable[..., ChartResult], /, *args: Any, **_kw: Any
    ) -> cf.Future[ChartResult]:
        fut: cf.Future[ChartResult] = cf.Future()

        def work() -> None:
            if not fut.set_running_or_notify_cancel():
                return
            try:
                res = self.share.run(self.atlas_key, fn, [args], self.abandoned, self.background)
                fut.set_result(res[0])
            except BaseException as exc:  # the consumer's result() raises it
                fut.set_exception(exc)

        threading.Thread(target=work, name="chart-submit", daemon=True).start()
        return fut
