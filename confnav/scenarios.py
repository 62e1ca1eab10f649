"""Benchmark scenarios: workspaces with a goal, and uniform random starts in free space.

- :func:`default_scenario`: the seed's Sec. VI workspace, goal (0, 0).
- :func:`cup_trap`: a U-shaped cup opening towards the robots with the goal behind it; depth d
  (a potential field's classic trap).
- :func:`l_room`: an L-shaped room with non-convex obstacles (U, L, star).
- :func:`mixed`: ``confnav.workspaces.mixed_obstacles(n)``, goal at the anchor.
- :func:`spiral_corridor`: a rectangular spiral corridor of length/width ratio L/w (the free
  space itself; no obstacles), goal at the inner end: crowding grows like exp(-pi L/w).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.workspaces import DEFAULT_GOAL, default_workspace, mixed_obstacles, star

__all__ = [
    "Scenario",
    "cup_trap",
    "default_scenario",
    "l_room",
    "mixed",
    "random_starts",
    "spiral_corridor",
]

CArray = NDArray[np.complex128]


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
