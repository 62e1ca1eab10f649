"""Benchmark scenarios: workspaces with a goal, and uniform random starts in free space.

- :func:`default_scenario`: the seed's Sec. VI workspace, goal (0, 0).
- :func:`cup_trap`: a U-shaped cup opening towards the robots with the goal behind it; depth d
  (a potential field's classic trap).
- :func:`l_room`: an L-shaped room with non-convex obstacles (U, L, star).
- :func:`mixed`: ``confnav.scenes.workspaces.mixed_obstacles(n)``, goal at the anchor.
- :func:`spiral_corridor`: a rectangular spiral corridor of length/width ratio L/w (the free
  space itself; no obstacles), goal at the inner end: crowding grows like exp(-pi L/w).
- Rooms like real ones (metres), for the defaults of issue 9: :func:`cup_room` (an 8 x 6 m
  clutter with the goal inside a U-shaped obstacle's cup), :func:`alcove_room` (goal at the end
  of a 1.0 x 2.0 m alcove in a wall), :func:`door_rooms` (goal behind a 0.8 m door in a
  0.15 m wall), :func:`office` (12 x 8 m: two desks, an L-shaped counter, a pillar and a thin
  partition).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.scenes.workspaces import DEFAULT_GOAL, default_workspace, mixed_obstacles, star
from confnav.types import CArray

__all__ = [
    "Scenario",
    "alcove_room",
    "cup_room",
    "cup_trap",
    "default_scenario",
    "door_rooms",
    "l_room",
    "mixed",
    "office",
    "random_starts",
    "spiral_corridor",
]


@dataclass(frozen=True)
class Scenario:
    """A named workspace with a goal."""

    name: str
    workspace: Workspace
    goal: complex
    description: str = ""


def default_scenario() -> Scenario:
    return Scenario("default", default_workspace(), DEFAULT_GOAL, "seed Sec. VI workspace")


def cup_trap(depth: float, width: float = 0.8, wall: float = 0.1) -> Scenario:
    """A cup of inner ``width`` and ``depth`` in the room [-2, 2]^2, opening to -x, goal
    at (1.6, 0) behind it."""
    if not 0 < depth <= 2.8:
        raise NavigationError("cup depth must be in (0, 2.8]")
    x0 = -(depth + wall) / 2
    hw = width / 2
    cup = [
        (x0, hw + wall),
        (x0, hw),
        (x0 + depth, hw),
        (x0 + depth, -hw),
        (x0, -hw),
        (x0, -hw - wall),
        (x0 + depth + wall, -hw - wall),
        (x0 + depth + wall, hw + wall),
    ]
    ws = Workspace([(-2, -2), (2, -2), (2, 2), (-2, 2)], [cup])
    return Scenario(f"cup d={depth:g}", ws, 1.6 + 0j, f"cup trap, depth {depth:g}, width {width:g}")


def l_room() -> Scenario:
    """L-shaped room (arms of width 2) with a U, an L-shaped block and a 5-pointed star."""
    outer = [(-2, -2), (2, -2), (2, 0), (0, 0), (0, 2), (-2, 2)]
    u = [(0.4, -1.5), (0.6, -1.5), (0.6, -0.8), (1.2, -0.8), (1.2, -1.5), (1.4, -1.5),
         (1.4, -0.6), (0.4, -0.6)]  # fmt: skip
    ell = [(-1.5, -1.4), (-0.7, -1.4), (-0.7, -1.2), (-1.3, -1.2), (-1.3, -0.5), (-1.5, -0.5)]
    st = star(-1.0 + 1.0j, 0.45, 0.2, 5, np.pi / 2)
    ws = Workspace(outer, [u, ell, st])
    return Scenario("L-room", ws, -1.0 + 0.0j, "L-shaped room, non-convex obstacles")


def mixed(n: int, seed: int = 0) -> Scenario:
    ws = mixed_obstacles(n, seed)
    return Scenario(f"mixed {n}", ws, ws.anchor, f"{n} mixed obstacles, seed {seed}")


def spiral_corridor(ratio: float, width: float = 0.4) -> Scenario:
    """A rectangular spiral corridor with centreline length/width ``ratio``; the goal is half
    a width from the inner end."""
    if not 1 <= ratio <= 40:
        raise NavigationError("corridor ratio must be in [1, 40]")
    total = ratio * width
    pitch = 2 * width
    first = 4 * width
    pts = [0j]
    heading = 1 + 0j
    seg, remaining, i = first, total, 0
    while remaining > 1e-12:
        step = min(seg, remaining)
        pts.append(pts[-1] + heading * step)
        remaining -= step
        heading *= 1j
        i += 1
        if i % 2 == 0:
            seg -= pitch
            if seg <= 0:
                raise NavigationError("corridor ratio too long for this spiral")
    line = shapely.LineString([(p.real, p.imag) for p in pts])
    poly = line.buffer(width / 2, cap_style="flat", join_style="mitre")
    xy = np.asarray(poly.exterior.coords)[:-1]
    outer = xy[:, 0] + 1j * xy[:, 1]
    end, before = pts[-1], pts[-2]
    goal = end - (end - before) / abs(end - before) * (width / 2)
    ws = Workspace(outer)
    return Scenario(
        f"spiral L/w={ratio:g}", ws, complex(goal), f"spiral corridor, length/width {ratio:g}"
    )


def _rect(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float]]:
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def cup_room() -> Scenario:
    """8 x 6 m clutter; a U-shaped shelf (1.2 m wide, 1.4 m deep cup, 0.1 m walls) opening to
    +x with the goal 0.3 m from the bottom of its cup; a table, a cabinet and a round bin."""
    u = [(3.0, 2.0), (4.5, 2.0), (4.5, 2.1), (3.1, 2.1), (3.1, 3.3), (4.5, 3.3), (4.5, 3.4),
         (3.0, 3.4)]  # fmt: skip
    bin_ = 6.5 + 1.0j + 0.25 * np.exp(2j * np.pi * np.arange(12) / 12)
    ws = Workspace(
        _rect(0, 0, 8, 6), [u, _rect(5.5, 3.8, 7.0, 4.6), _rect(0.8, 4.5, 1.6, 5.4), bin_]
    )
    return Scenario("U cup room", ws, 3.4 + 2.7j, "goal inside the cup of a U-shaped shelf")


def alcove_room() -> Scenario:
    """7 x 5 m room with a 1.0 m wide, 2.0 m deep alcove in the top wall, the goal 0.3 m from
    its end; a sofa and a table in the room."""
    outer = [(0, 0), (7, 0), (7, 5), (5.5, 5), (5.5, 7), (4.5, 7), (4.5, 5), (0, 5)]
    ws = Workspace(outer, [_rect(0.5, 3.8, 2.5, 4.6), _rect(3.0, 1.5, 4.2, 2.3)])
    return Scenario("alcove", ws, 5.0 + 6.7j, "goal at the end of a 1.0 x 2.0 m alcove")


def door_rooms() -> Scenario:
    """Two 5 x 4 m rooms joined by a 0.8 m door in a 0.15 m wall; furniture in both; the goal
    in the second room behind the wall."""
    outer = [(0, 0), (5, 0), (5, 1.6), (5.15, 1.6), (5.15, 0), (10.15, 0), (10.15, 4),
             (5.15, 4), (5.15, 2.4), (5, 2.4), (5, 4), (0, 4)]  # fmt: skip
    ws = Workspace(
        outer,
        [
            _rect(1.0, 1.2, 2.6, 2.0),
            _rect(3.8, 3.2, 4.6, 3.8),
            _rect(7.0, 1.8, 8.4, 2.6),
            _rect(9.4, 0.3, 9.9, 1.3),
        ],
    )
    return Scenario("door", ws, 6.0 + 3.2j, "goal behind a 0.8 m door in a 0.15 m wall")


def office() -> Scenario:
    """12 x 8 m office: two desks, an L-shaped counter, a 0.4 m pillar and a thin (0.1 m)
    partition; the goal behind the partition."""
    counter = [(8.5, 5.0), (11.4, 5.0), (11.4, 7.4), (10.8, 7.4), (10.8, 5.6), (8.5, 5.6)]
    ws = Workspace(
        _rect(0, 0, 12, 8),
        [
            _rect(1.5, 1.5, 3.1, 2.3),
            _rect(1.5, 4.5, 3.1, 5.3),
            counter,
            _rect(6.0, 3.8, 6.4, 4.2),
            _rect(8.0, 1.0, 8.1, 4.0),
        ],
    )
    return Scenario("office", ws, 9.5 + 2.0j, "office: desks, counter, pillar, partition")


def random_starts(ws: Workspace, n: int, seed: int = 0, margin: float = 0.05) -> CArray:
    """``n`` points uniform in the free space at least ``margin`` from every boundary."""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = ws.bounds
    out: list[CArray] = []
    have = 0
    for _ in range(1000):
        z = rng.uniform(x0, x1, 4 * n) + 1j * rng.uniform(y0, y1, 4 * n)
        z = z[ws.clearance(z) >= margin]
        out.append(z)
        have += z.size
        if have >= n:
            break
    if have < n:
        raise NavigationError("free space too small for the requested random starts")
    return np.concatenate(out)[:n]
