"""Naive attractive/repulsive potential field: the baseline the conformal method is compared to.

``U = (k_att/2) |x - x_d|^2 + sum_j (k_rep/2) (1/d_j - 1/d_0)^2`` for ``d_j < d_0``, with
``d_j`` the exact distance to boundary j (outer polygon or obstacle j) [1]_; the robot follows
``u = -grad U = -k_att (x - x_d) + sum_j k_rep (1/d_j - 1/d_0) d_j^-2 (x - p_j)/d_j``
(p_j the nearest point of boundary j), saturated to ``v_max`` keeping the direction.  It has
spurious local minima behind obstacles and inside concave ones: robots stall there.

References
----------
.. [1] O. Khatib, "Real-time obstacle avoidance for manipulators and mobile robots",
   Int. J. Robotics Research 5 (1986) 90-98.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from confnav.errors import NavigationError, fmt_point
from confnav.geometry import Workspace
from confnav.types import CArray

__all__ = ["PotentialField"]


class PotentialField:
    """Khatib-style potential field on a polygonal workspace (a ``VelocityField`` for
    :func:`confnav.navigation.sim.simulate`).

    Parameters
    ----------
    workspace : Workspace
    goal : complex in the free space.
    k_att, k_rep : attractive and repulsive gains.
    d0 : influence distance of the obstacles; default ``min(0.075 diameter,
        clearance(goal) / 2)`` so that the goal is an equilibrium.
    v_max : speed limit.
    goal_tol : arrival distance.
    """

    def __init__(
        self,
        workspace: Workspace,
        goal: complex,
        *,
        k_att: float = 1.0,
        k_rep: float = 0.01,
        d0: float | None = None,
        v_max: float = 1.0,
        goal_tol: float = 1e-3,
    ) -> None:
        self.workspace = workspace
        self.goal = complex(goal)
        if not np.isfinite(self.goal) or not bool(workspace.contains(self.goal)):
            raise NavigationError(f"goal {fmt_point(self.goal)} is not in the free space")
        if d0 is None:
            # influence distance: 7.5% of the workspace size, and no obstacle pushes at the
            # goal (otherwise the goal is not an equilibrium: Ge & Cui's GNRON problem)
            d0 = min(0.075 * workspace.diameter, 0.5 * float(workspace.clearance(self.goal)))
        if min(k_att, k_rep, d0, v_max, goal_tol) <= 0:
            raise NavigationError("potential field parameters must be positive")
        self.k_att, self.k_rep, self.d0 = float(k_att), float(k_rep), float(d0)
        self.v_max, self.goal_tol = float(v_max), float(goal_tol)
        # boundaries padded to a common number of segments (padding repeats the boundary's
        # first segment, which changes no nearest point)
        bounds = workspace.boundaries
        lmax = max(p.size for p in bounds)
        a = np.empty((len(bounds), lmax), dtype=np.complex128)
        b = np.empty_like(a)
        for j, p in enumerate(bounds):
            a[j, : p.size], b[j, : p.size] = p, np.roll(p, -1)
            a[j, p.size :], b[j, p.size :] = p[0], p[1 % p.size]
        self._a = a
        self._d = b - a
        self._dd = np.abs(self._d) ** 2

    def velocity(self, z: ArrayLike) -> CArray:
        """``-grad U`` saturated to ``v_max`` (NaN outside the free space)."""
        z = np.asarray(z, dtype=np.complex128)
        flat = z.ravel()
        rel = flat[:, None, None] - self._a[None]  # (N, boundaries, segments)
        t = np.clip((rel * np.conj(self._d)).real / self._dd, 0.0, 1.0)
        vec = rel - t * self._d  # from the nearest point of each segment to z
        dist = np.abs(vec)
        k = np.argmin(dist, axis=2)[..., None]
        d = np.take_along_axis(dist, k, axis=2)[..., 0]  # (N, boundaries)
        v = np.take_along_axis(vec, k, axis=2)[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            mag = np.where(d < self.d0, self.k_rep * (1 / d - 1 / self.d0) / d**3, 0.0)
            u = -self.k_att * (flat - self.goal) + np.sum(mag * v, axis=1)
        s = np.abs(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(s > self.v_max, u * (self.v_max / s), u)
        u = np.where(self.workspace.contains(flat), u, np.nan + 0j)
        return np.asarray(u.reshape(z.shape), dtype=np.complex128)
