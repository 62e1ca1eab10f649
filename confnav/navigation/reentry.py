"""Re-entry: steer a reference point that lies just outside the mapped free space back in.

A robot's law is defined on the free space its map was solved for; outside it the law has no
value and the robot is stopped (``outside_workspace``). A robot can end up just outside without
any fault of its own law: its map is the footprint map ``{ws}~r{R}``, whose free space is the
workspace shrunk by ``R`` with *mitred* corners (:mod:`confnav.maps.footprint`), a subset of the
exact shrink (all points at distance >= R from every wall). Anything that moves the robot other
than that map's law -- a neighbour's yielding under the fleet rules, a roadmap node law, the
first move on the base map, a person pushing it -- can leave its reference point in the sliver
between the two, up to ``(mitre_limit - 1) R`` deep, with the body clear of every wall. Stopping
there for good is what the services did (measured: a TurtleBot-sized robot that yielded to a
neighbour after arriving stayed ``stopped (outside_workspace)`` 0.038 m outside its map, body
0.043 m clear, for the rest of the run).

The re-entry law: ``u = s (q - p) / |q - p|`` with ``q`` the nearest point of the free space's
closure to ``p`` and ``s`` a small speed. The distance ``delta(p)`` to a closed set is
1-Lipschitz and ``delta(p + t e) <= |p + t e - q| = delta(p) - t`` along ``e = (q - p)/|q - p|``
for ``0 <= t <= delta(p)`` [Federer 1959, "Curvature measures", Thm. 4.8; any nearest point],
so a reference point that follows ``u`` (a holonomic robot; a unicycle's look-ahead point
follows ``sigma u`` with ``0 < sigma <= 1`` under the twist limits,
:func:`confnav.navigation.unicycle.twist_from_velocity`) is back in within ``delta / (sigma s)``
seconds, moving straight away from the walls that define that part of the boundary. Only
points at most ``max_depth`` outside are steered: deeper is not a mitre's sliver but a map that
does not fit the robot (or a collision), and stays a stop.
"""

from __future__ import annotations

import math

import shapely
from shapely.geometry import Point

from confnav.geometry import Workspace

__all__ = ["REENTRY_DEPTH", "REENTRY_SPEED", "reentry_velocity"]

#: m: the deepest a reference point is steered back from (a mitre's sliver is at most
#: ``(mitre_limit - 1) R`` = 0.5 R deep at the default limit 1.5: 0.15 m covers R <= 0.3 m).
REENTRY_DEPTH = 0.15

#: m/s: the re-entry speed (a walking-pace fraction; re-entry is a recovery, not travel).
REENTRY_SPEED = 0.1


def reentry_velocity(
    ws: Workspace,
    p: complex,
    *,
    speed: float = REENTRY_SPEED,
    max_depth: float = REENTRY_DEPTH,
) -> tuple[complex, float] | None:
    """``(u, depth)``: the velocity steering ``p`` into ``ws`` at ``speed`` (module docstring)
    and how far outside ``p`` is; None when ``p`` is inside (or on the boundary), deeper than
    ``max_depth``, or not finite."""
    if not (math.isfinite(p.real) and math.isfinite(p.imag)):
        return None
    depth = -float(ws.clearance1(p))
    if not (0.0 < depth <= max_depth):
        return None
    poly = ws.polygon
    pt = Point(p.real, p.imag)
    q = shapely.shortest_line(pt, poly).coords[-1]  # the nearest point of the closure
    d = complex(q[0] - p.real, q[1] - p.imag)
    if abs(d) == 0.0:
        return None
    return speed * d / abs(d), depth
