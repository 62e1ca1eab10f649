"""Workspace definitions and solve results: the helpers the services share.

The transform service (services/transform.py), its atlas side (services/atlas_transform.py), the
controller (services/controller.py), the simulator and the ROS 2 bridge all turn
``WorkspaceDefinition`` messages into core workspaces and solved maps into result dicts; those
conversions live here, so that no service imports another one for them.
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

from confnav.schemas import WorkspaceDefinition


def definition_hash(defn: WorkspaceDefinition) -> str:
    """Content hash of what determines the solution: the workspace geometry and ``tol``
    (not the ws id, not the time stamp). Validates the workspace with the core."""
    ws = workspace_of(defn)
    return hashlib.sha256(f"{ws.content_hash}|tol={defn.tol!r}".encode()).hexdigest()


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
    (:func:`confnav.maps.footprint.inflate`, largest component; raises WorkspaceError)."""
    from confnav.maps.footprint import inflate, parse_derived_ws_id

    parsed = parse_derived_ws_id(ws_id)
    assert parsed is not None and parsed[0] == base.ws_id
    return definition_of(ws_id, inflate(workspace_of(base), parsed[1]), tol=base.tol)


def load_definition(ws_id: str, source: str) -> WorkspaceDefinition:
    """``builtin:default`` or a workspace file (JSON / GeoJSON, see ``Workspace.load``)."""
    if source == "builtin:default":
        from confnav.scenes.workspaces import default_workspace

        return definition_of(ws_id, default_workspace())
    from confnav.geometry import Workspace

    return definition_of(ws_id, Workspace.load(source))


def _xy(z: complex) -> tuple[float, float]:
    return (float(z.real), float(z.imag))


def solution_result(cmap: Any, tol: float) -> dict[str, Any]:
    """The solve result dict of one map (what :class:`TransformSolution` is built from)."""
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
            "tol": float(getattr(diag, "tol", tol)),
            "nodes": [int(n) for n in nodes],
            "boundary_residual": float(diag.boundary_residual),
            "tol_met": bool(diag.tol_met),
        },
        "workspace_hash": str(cmap.workspace_hash),
        # through JSON so that the result is plain JSON values (lists, not tuples/arrays)
        "coefficients": json.loads(cmap.to_json()),
    }


def parse_sources(items: list[str]) -> dict[str, str]:
    """``ID=PATH`` items (PATH may be ``builtin:default``)."""
    out = {}
    for item in items:
        ws_id, sep, path = item.partition("=")
        if not sep:
            raise SystemExit(f"--workspace expects ID=PATH, got {item!r}")
        out[ws_id] = path
    return out


#: Progressive maps (docs/SERVICES.md): the tolerances of the revisions a workspace is solved
#: to before its own ``tol``, coarse first. The first revision is accepted up to
#: :data:`COARSE_MAX_ERROR` (``solve(max_error=...)``): the controller keeps robots out of the
#: walls on the exact geometry, so a coarse map costs path quality, not safety.
LADDER: tuple[float, ...] = (1e-3, 1e-6)
#: Largest estimated error of the first (coarse) revision that is published.
COARSE_MAX_ERROR = 1e-2
#: ``TransformStatus.message`` of a revision that a finer one follows (state ``solved``).
REFINING = "solved (coarse, refining)"


def revision_ladder(tol: float) -> list[float]:
    """The tolerances a workspace of tolerance ``tol`` is solved to, one revision each: the
    rungs of :data:`LADDER` above ``tol``, then ``tol`` itself (``tol`` 1e-8: 1e-3, 1e-6,
    1e-8; ``tol`` 1e-4: 1e-3, 1e-4; ``tol`` 1e-3 or coarser: ``tol`` alone)."""
    return [t for t in LADDER if t > tol] + [tol]


def footprint_of(robot_radius: float, drive: str, lookahead: float) -> float:
    """The footprint a robot's map is shrunk by (``confnav.navigation.messages
    .footprint_radius``): its radius, plus the look-ahead for a unicycle."""
    return robot_radius + (lookahead if drive == "unicycle" else 0.0)


def ask_for_maps(
    bus: Any,
    keys: Any,
    ws_ids: list[str],
    stopped: Any,
    give_up_s: float = 300.0,
    payloads: dict[str, bytes] | None = None,
) -> list[str]:
    """Query the transform service for the maps ``ws_ids`` once, so that they are solved
    before the first goal needs them (a query for a footprint map ``{ws}~r{R}`` makes the
    service derive and solve it: docs/SERVICES.md, "ahead of use"); a map no transform
    service knows yet is asked again every 2 s (at most ``give_up_s``). ``stopped`` is a
    ``threading.Event`` that ends the wait; ``payloads``: a query's ``MapQuery`` per id (the
    robots' starts, whose charts an atlas then solves first). Returns the ids never
    answered."""
    todo = sorted(set(ws_ids))
    deadline = time.monotonic() + give_up_s
    while todo and not stopped.is_set() and time.monotonic() < deadline:
        for ws in list(todo):
            try:
                payload = (payloads or {}).get(ws)
                replies = bus.query(keys.ws(ws, "transform"), timeout=2.0, payload=payload)
            except Exception:
                continue
            if any(r.ok or "unknown workspace" not in (r.error or "") for r in replies):
                todo.remove(ws)  # solved, or being solved
        stopped.wait(2.0)
    return todo
