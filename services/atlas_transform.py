"""The transform service's side of atlases (issue 15 item 3).

A workspace too crowded for one map (:func:`confnav.atlas.needs_atlas`, or a
``CrowdingError`` of the single solve) is solved as an atlas (:func:`solve_or_atlas`, in the
service's worker).  The service then publishes

- one ``TransformSolution`` per chart on ``{prefix}/ws/{ws}~c{i}/transform`` (the cell's own
  workspace id: queryable exactly like any transform),
- the ``AtlasIndex`` on ``{prefix}/ws/{ws}/atlas`` (after the charts, so a subscriber that
  sees the index can query them),
- ``TransformStatus`` ``solved`` with the atlas revision.

A transform query on the atlas workspace itself is answered with ``reply_err`` starting with
:data:`confnav.atlas.wire.ATLAS_MARKER` (the controller then fetches the atlas).
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

from confnav.schemas import AtlasCell, AtlasIndex, SolveDiagnostics, TransformSolution, encode
from confnav.services.bus import QueryError, key_matches

from confnav.atlas.wire import ATLAS_MARKER, atlas_revision, chart_ws_id

if TYPE_CHECKING:
    from confnav.services.transform import TransformService

#: Chart solves of one atlas run one after the other inside the service's solver worker (the
#: service's pool already runs ``--workers`` workspaces at once); ``confnav atlas`` and
#: :func:`confnav.atlas.solve_atlas` solve charts in parallel.
ATLAS_WORKERS = 1


def solve_or_atlas(ws: Any, tol: float) -> dict[str, Any]:
    """One map's result dict, or ``{"atlas": index fields, "charts": [result dicts]}``."""
    from confnav.services.transform import solution_result

    from confnav.atlas.charts import needs_atlas, solve_atlas
    from confnav.atlas.wire import index_fields
    from confnav.conformal.solver import solve
    from confnav.errors import CrowdingError

    if not needs_atlas(ws):
        try:
            return solution_result(solve(ws, tol=tol), tol)
        except CrowdingError:
            pass
    atlas = solve_atlas(ws, tol, workers=ATLAS_WORKERS)
    return {
        "atlas": index_fields(atlas),
        "charts": [solution_result(m, tol) for m in atlas.charts],
    }


def _pt(p: Any) -> tuple[float, float]:
    return (float(p[0]), float(p[1]))


def messages_of(
    ws_id: str, h: str, result: dict[str, Any]
) -> tuple[AtlasIndex, list[TransformSolution]]:
    """The index and chart messages of an atlas result (tuples restored after JSON)."""
    now = time.time_ns()
    charts = [
        TransformSolution(
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
    cells = [
        AtlasCell(
            index=int(c["index"]),
            chart_ws_id=chart_ws_id(ws_id, int(c["index"])),
            chart_revision=charts[int(c["index"])].revision,
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
        revision=atlas_revision([c.revision for c in charts]),
        definition_hash=h,
        stamp_ns=now,
        margin=float(a["margin"]),
        tol=float(a["tol"]),
        cells=cells,
        decomposition=a["decomposition"],
        wall_time=float(a["wall_time"]),
        cpu_time=float(a["cpu_time"]),
    )
    return index, charts


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
