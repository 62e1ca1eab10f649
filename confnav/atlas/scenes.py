"""Floor plans for atlases: an office floor (rooms off a corridor) and a shelf warehouse.

Units are metres.  Both are :class:`confnav.scenes.scenarios.Scenario` objects (workspace + goal);
the spiral corridors of :func:`confnav.scenes.scenarios.spiral_corridor` complete the benchmark set.
"""

from __future__ import annotations

import shapely
from shapely.geometry import Polygon, box

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.scenes.scenarios import Scenario

__all__ = ["corridor", "office", "spiral", "warehouse"]


def _workspace(poly: Polygon, obstacles: list[Polygon] | None = None) -> Workspace:
    ring = [(float(x), float(y)) for x, y in list(poly.exterior.coords)[:-1]]
    holes = [
        [(float(x), float(y)) for x, y in list(o.exterior.coords)[:-1]] for o in obstacles or []
    ]
    return Workspace(ring, holes)


def corridor(ratio: float, width: float = 1.0) -> Scenario:
    """A straight corridor ``ratio * width`` long, goal half a width from its right end."""
    if not ratio >= 1:
        raise NavigationError("corridor ratio must be >= 1")
    length = ratio * width
    ws = _workspace(box(0, 0, length, width))
    return Scenario(
        f"corridor L/w={ratio:g}", ws, complex(length - width / 2, width / 2),
        f"straight corridor {length:g} x {width:g}",
    )  # fmt: skip


def office(
    length: float = 30.0,
    width: float = 2.0,
    rooms: int = 10,
    room_depth: float = 5.0,
    door: float = 0.9,
    wall: float = 0.2,
) -> Scenario:
    """A corridor ``length x width`` with ``rooms`` rooms (half above, half below), each
    behind a door ``door`` wide in a wall ``wall`` thick; goal in the middle of the last
    upper room (the far end of the corridor)."""
    per_side = (rooms + 1) // 2
    room_w = length / per_side
    parts = [box(0, 0, length, width)]
    for i in range(rooms):
        side = i % 2
        k = i // 2
        xa, xb = k * room_w + wall / 2, (k + 1) * room_w - wall / 2
        xc = (xa + xb) / 2
        if side == 0:
            parts.append(box(xa, width + wall, xb, width + wall + room_depth))
            parts.append(box(xc - door / 2, width, xc + door / 2, width + wall))
        else:
            parts.append(box(xa, -wall - room_depth, xb, -wall))
            parts.append(box(xc - door / 2, -wall, xc + door / 2, 0))
    poly = shapely.union_all(parts)
    if not isinstance(poly, Polygon):
        raise NavigationError("office floor is not one polygon")
    ws = _workspace(shapely.normalize(poly).simplify(0))
    k_last = (rooms - 1 - (rooms - 1) % 2) // 2
    goal = complex((k_last + 0.5) * room_w, width + wall + room_depth / 2)
    return Scenario(
        "office", ws, goal,
        f"{length:g} x {width:g} m corridor, {rooms} rooms behind {door:g} m doors",
    )  # fmt: skip


def warehouse(
    cols: int = 10,
    rows: int = 10,
    shelf: tuple[float, float] = (4.0, 1.0),
    aisle: float = 2.0,
) -> Scenario:
    """``rows x cols`` shelves (``shelf`` = x and y size) on a grid with ``aisle`` wide aisles
    between them and around them; goal in the aisle at the far corner.

    The floor is ``cols (sx + aisle) + aisle`` by ``rows (sy + aisle) + aisle``: 62 x 32 m for
    100 shelves of 4 x 1 m.  (100 such shelves do not fit a 40 x 20 m floor with 2 m aisles:
    each needs its own 18 m^2 with half the aisles around it, 1800 m^2 in all.)
    """
    sx, sy = shelf
    wx, wy = cols * (sx + aisle) + aisle, rows * (sy + aisle) + aisle
    obstacles = [
        box(aisle + i * (sx + aisle), aisle + j * (sy + aisle),
            aisle + i * (sx + aisle) + sx, aisle + j * (sy + aisle) + sy)
        for j in range(rows)
        for i in range(cols)
    ]  # fmt: skip
    ws = _workspace(box(0, 0, wx, wy), obstacles)
    goal = complex(wx - aisle / 2, wy - aisle / 2)
    return Scenario(
        "warehouse", ws, goal,
        f"{wx:g} x {wy:g} m, {rows * cols} shelves {sx:g} x {sy:g} m, {aisle:g} m aisles",
    )  # fmt: skip


def spiral(ratio: float, width: float = 0.4) -> Scenario:
    """A rectangular spiral corridor of centreline length ``ratio * width`` (walls 1 width
    thick between the turns), goal half a width from the inner end.

    Unlike :func:`confnav.scenes.scenarios.spiral_corridor` (first leg 4 widths, so at most
    L/w ~ 14), the first leg grows with the ratio so that any ratio fits.
    """
    if not ratio >= 1:
        raise NavigationError("spiral ratio must be >= 1")
    pitch = 2 * width
    legs: list[float] = []
    first = 4 * width
    while True:  # smallest first leg whose inward spiral holds the whole length
        legs, seg, total, i = [], first, 0.0, 0
        while seg >= 2 * width and total < ratio * width:  # inner legs long enough to turn
            legs.append(min(seg, ratio * width - total))
            total += legs[-1]
            i += 1
            if i % 2 == 0:
                seg -= pitch
        if total >= ratio * width - 1e-12:
            break
        first += width
    pts = [0j]
    heading = 1 + 0j
    for leg in legs:
        pts.append(pts[-1] + heading * leg)
        heading *= 1j
    line = shapely.LineString([(p.real, p.imag) for p in pts])
    poly = line.buffer(width / 2, cap_style="flat", join_style="mitre")
    if not isinstance(poly, Polygon):
        raise NavigationError("spiral is not one polygon")
    end, before = pts[-1], pts[-2]
    goal = end - (end - before) / abs(end - before) * (width / 2)
    return Scenario(
        f"spiral L/w={ratio:g}", _workspace(poly), complex(goal),
        f"spiral corridor, length/width {ratio:g}",
    )  # fmt: skip
