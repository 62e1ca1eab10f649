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
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError
from confnav.geometry import Workspace

__all__ = ["PotentialField"]

CArray = NDArray[np.complex128]


class PotentialField:
    """Khatib-style potential field on a polygonal workspace (a ``VelocityField`` for
    :func:`confnav.sim.simulate`).

    Parameters
    ----------
    workspace : Workspace
    goal : complex in the free space.
    k_att, k_rep : attractive and repulsive gains.
    d0 : influence distance of the obstacles.
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
        d0: float = 0.3,
        v_max: float = 1.0,
        goal_tol: float = 1e-3,
    ) -> None:
        self.workspace = workspace
        self.goal = complex(goal)
        if not np.isfinite(self.goal) or not bool(workspace.contains(self.goal)):
            raise NavigationError(f"goal {self.goal:.6g} is not in the free space")
        if min(k_att, k_rep, d0, v_max, goal_tol) <= 0:
            raise NavigationError("potential field parameters must be positive")
        self.k_att, self.k_rep, self.d0 = float(k_att), float(k_rep), float(d0)
        self.v_max, self.goal_tol = float(v_max), float(goal_tol)
        segs_a, segs_b, owner = [], [], []
        for j, p in enumerate(workspace.boundaries):
            segs_a.append(p)
            segs_b.append(np.roll(p, -1))
            owner.append(np.full(p.size, j))
        self._a = np.concatenate(segs_a)
        self._d = np.concatenate(segs_b) - self._a
        self._owner = np.concatenate(owner)
        self._nb = len(workspace.boundaries)

    def velocity(self, z: ArrayLike) -> CArray:
        """``-grad U`` saturated to ``v_max`` (NaN outside the free space)."""
        z = np.asarray(z, dtype=np.complex128)
        flat = z.ravel()
        rel = flat[:, None] - self._a[None, :]
        t = np.clip((rel * np.conj(self._d)).real / np.abs(self._d) ** 2, 0.0, 1.0)
        vec = rel - t * self._d  # from the nearest point of each segment to z
        dist = np.abs(vec)
        u = -self.k_att * (flat - self.goal)
        for j in range(self._nb):  # a handful of boundaries; vectorized over robots
            cols = self._owner == j
            dj = dist[:, cols]
            k = np.argmin(dj, axis=1)
            d = dj[np.arange(flat.size), k]
            v = vec[:, cols][np.arange(flat.size), k]
            with np.errstate(divide="ignore", invalid="ignore"):
                mag = np.where(d < self.d0, self.k_rep * (1 / d - 1 / self.d0) / d**2, 0.0)
                u = u + mag * v / d
        s = np.abs(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(s > self.v_max, u * (self.v_max / s), u)
        u = np.where(self.workspace.contains(flat), u, np.nan + 0j)
        return np.asarray(u.reshape(z.shape), dtype=np.complex128)
