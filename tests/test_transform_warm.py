"""The transform service re-solves a changed definition from the workspace's previous map
(issue 24 item 3: ``solve(initial=...)``, confnav/conformal/warm.py): a moved obstacle's
final revision is a warm map, equal to a cold solve within the two certificates."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from confnav.schemas import TransformSolution, WorkspaceDefinition, decode, encode
from confnav.services.bus import InMemoryNetwork
from confnav.services.keys import Keys
from confnav.services.transform import TransformService, solve_definition
from conftest import wait_for

import confnav
from confnav import ConformalMap

K = Keys()
ROOM = [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0)]
L_SHAPE = [(-0.5, -0.5), (0.3, -0.5), (0.3, -0.2), (-0.2, -0.2), (-0.2, 0.3), (-0.5, 0.3)]


def box(x: float, y: float, s: float = 0.4) -> list[tuple[float, float]]:
    return [(x, y), (x + s, y), (x + s, y + s), (x, y + s)]


def room(dx: float) -> WorkspaceDefinition:
    """test_resolve_warm's room: two boxes and an L (a reflex corner), one box moved by dx."""
    ell = [(x + 1.0, y + 1.0) for x, y in L_SHAPE]
    return WorkspaceDefinition(
        ws_id="room",
        outer=ROOM,
        obstacles=[box(-1.5, -1.5), box(0.5 + dx, -1.0), ell],
        anchor=(0.0, 0.0),
        tol=1e-8,
    )


def _final(msgs: list[bytes], box_x: float) -> TransformSolution | None:
    """The last published solution whose map is of the room with its box at ``box_x``
    and meets its tol (the final revision)."""
    for p in reversed(msgs):
        sol = decode(TransformSolution, p)
        m = ConformalMap.from_json(json.dumps(sol.coefficients))
        if m.diagnostics.tol_met and m.diagnostics.tol <= 1e-8:
            x0 = float(np.min(np.real(m.workspace.obstacles[1])))
            if abs(x0 - box_x) < 1e-12:
                return sol
    return None


@pytest.mark.slow
def test_a_moved_obstacle_is_re_solved_warm_and_equals_a_cold_solve(
    mem_net: InMemoryNetwork,
) -> None:
    client = mem_net.bus("client")
    got: list[bytes] = []
    client.subscribe(K.ws("room", "transform"), lambda _k, p: got.append(p))
    svc = TransformService(
        mem_net.bus("tr"), K, executor="thread", solve_fn=solve_definition, health_period=0.2
    )
    svc.start()
    try:
        client.publish(K.ws("room", "definition"), encode(room(0.0)))
        wait_for(lambda: _final(got, 0.5), 120)
        client.publish(K.ws("room", "definition"), encode(room(0.1)))
        sol = wait_for(lambda: _final(got, 0.6), 120)
    finally:
        svc.stop()
    warm = ConformalMap.from_json(json.dumps(sol.coefficients))
    levels = warm.diagnostics.refinements
    assert levels[0].get("warm_start") == 1.0 and len(levels) == 1, levels  # one warm level
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", confnav.AccuracyWarning)
        cold = confnav.solve(warm.workspace, tol=1e-8)
    assert cold.diagnostics.refinements[0].get("warm_start") is None
    gap = max(
        float(np.max(np.abs(warm.centers - cold.centers))),
        float(np.max(np.abs(warm.radii - cold.radii))),
    )
    assert gap <= warm.diagnostics.error_estimate + cold.diagnostics.error_estimate
