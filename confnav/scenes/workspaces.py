"""Ready-made workspaces: the seed paper's default scene and random mixed-obstacle rooms.

The default workspace is the seed's Sec. VI scene with the concrete coordinates of docs/METHOD.md
section 5 (outer square, triangle, rectangle, 6-pointed star, non-star-shaped U).
"""

from __future__ import annotations

import numpy as np

from confnav.geometry import Workspace
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: The seed's goal (also the default workspace's anchor).
DEFAULT_GOAL: complex = 0j
#: The seed's four starts (Sec. VI).
DEFAULT_STARTS: tuple[complex, ...] = (1.5 + 1j, -1.5 + 1j, -1 - 1.5j, 0.05 - 1.5j)


def star(center: complex, r_tip: float, r_notch: float, tips: int, phase: float) -> ComplexArray:
    """A star polygon with ``tips`` points, first tip at angle ``phase`` (radians)."""
    k = np.arange(2 * tips)
    r = np.where(k % 2 == 0, r_tip, r_notch)
    return np.asarray(center + r * np.exp(1j * (phase + np.pi * k / tips)), dtype=np.complex128)


def default_workspace() -> Workspace:
    """The seed's Sec. VI workspace (docs/METHOD.md sec. 5), anchor at the goal (0, 0)."""
    outer = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
    triangle = [[0.6, 0.3], [1.3, 0.4], [0.85, 1.0]]
    rectangle = [[-1.1, 0.3], [-0.6, 0.3], [-0.6, 1.0], [-1.1, 1.0]]
    star6 = star(-1.05 - 0.8j, 0.4, 0.2, 6, np.pi / 2)
    u_shape = [
        [-0.35, -1.2],
        [-0.15, -1.2],
        [-0.15, -0.6],
        [0.25, -0.6],
        [0.25, -1.2],
        [0.45, -1.2],
        [0.45, -0.4],
        [-0.35, -0.4],
    ]
    return Workspace(outer, [triangle, rectangle, star6, u_shape], anchor=DEFAULT_GOAL)


def _shape(kind: int, rng: np.random.Generator) -> ComplexArray:
    """A polygon of unit size around 0: triangle, rectangle, star or U (kind mod 4)."""
    if kind == 0:  # a triangle with every angle >= 30 degrees (no needles)
        while True:
            ang = np.sort(rng.uniform(0, 2 * np.pi, 3))
            arcs = np.diff(np.r_[ang, ang[0] + 2 * np.pi])  # inscribed angle = arc / 2
            if arcs.min() >= np.radians(60):
                return np.asarray(np.exp(1j * ang), dtype=np.complex128)
    if kind == 1:
        a, b = rng.uniform(0.35, 0.7, 2)
        return np.array([-a - 1j * b, a - 1j * b, a + 1j * b, -a + 1j * b])
    if kind == 2:
        return star(0j, 1.0, 0.5, int(rng.integers(4, 7)), rng.uniform(0, np.pi))
    u = (
        np.array(
            [-1 - 1j, -0.5 - 1j, -0.5 + 0.3j, 0.5 + 0.3j, 0.5 - 1j, 1 - 1j, 1 + 0.8j, -1 + 0.8j]
        )
        * 0.8
    )
    return np.asarray(u, dtype=np.complex128)


def mixed_obstacles(n: int, seed: int = 0) -> Workspace:
    """A square room with ``n`` pairwise-disjoint mixed obstacles on a jittered grid.

    Shapes cycle through triangles, rectangles, stars and U shapes with random size, rotation
    and position; each stays within 70% of its grid cell so gaps are at least ~15% of a cell.
    The anchor is left to the default (maximal clearance).
    """
    if n < 0:
        raise ValueError("n must be >= 0")
    rng = np.random.default_rng(seed)
    g = int(np.ceil(np.sqrt(n + 1)))
    cell = 2.0 / g
    cells = rng.permutation(g * g)[:n]
    obstacles = []
    for j, c in enumerate(cells):
        cx = -1 + cell * (c % g + 0.5)
        cy = -1 + cell * (c // g + 0.5)
        shape = _shape(j % 4, rng) * np.exp(1j * rng.uniform(0, 2 * np.pi))
        shape = shape / np.max(np.abs(shape))
        size = cell * rng.uniform(0.22, 0.35)
        jitter = (cell * 0.5 - size) * 0.5 * (rng.uniform(-1, 1) + 1j * rng.uniform(-1, 1))
        obstacles.append(complex(cx, cy) + jitter + size * shape)
    return Workspace([[-1, -1], [1, -1], [1, 1], [-1, 1]], obstacles)


#: The 4 x 4 room of :func:`mirror_squares`.
MIRROR_ROOM = [[-2, -2], [2, -2], [2, 2], [-2, 2]]


def mirror_squares(gap: float) -> Workspace:
    """Two unit squares ``gap`` apart, mirror images under x -> -x, anchor on the axis: its
    circle domain is mirror-symmetric (docs/METHOD.md section 4), so the
    :func:`mirror_asymmetry` of a computed map is a true lower bound of its error."""
    g = gap / 2
    left = [[-1 - g, -0.5], [-g, -0.5], [-g, 0.5], [-1 - g, 0.5]]
    right = [[g, -0.5], [1 + g, -0.5], [1 + g, 0.5], [g, 0.5]]
    return Workspace(MIRROR_ROOM, [left, right], anchor=[0, 1.5])


def mirror_asymmetry(centers: ComplexArray, radii: FloatArray) -> float:
    """Distance of the circle domain of :func:`mirror_squares` from its mirror image (0
    exactly): the radii differ and the centres fail ``c_0 = -conj(c_1)`` by at most this."""
    return float(max(abs(radii[0] - radii[1]), abs(centers[0] + np.conj(centers[1]))))


__all__ = [
    "DEFAULT_GOAL",
    "DEFAULT_STARTS",
    "MIRROR_ROOM",
    "default_workspace",
    "mirror_asymmetry",
    "mirror_squares",
    "mixed_obstacles",
    "star",
]
