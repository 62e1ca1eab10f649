"""Single-lane passages ("gates") of a workspace and a mutex per gate: one direction at a time.

Two robots with filter disks of radius ``rho`` (a unicycle: ``r + d``) can pass each other
only where the free space of their centres, the workspace shrunk by ``rho``, is at least
``2 rho`` wide.  :func:`find_gates` finds the places where it is narrower (plus a margin),
from the exact polygons: on a grid over the workspace, each point's exact distance to every
boundary component (the outer polygon, each obstacle) is computed; the points where the two
nearest components are equally far (the generalized Voronoi diagram of the components, i.e.
the medial axis between two different components; Aurenhammer, "Voronoi diagrams - a survey
of a fundamental geometric data structure", ACM Computing Surveys 23(3), 1991, sec. 5.1)
and that distance ``c`` satisfies ``rho < c < 2 rho + margin / 2`` lie on a passage whose
centre space is narrower than ``2 rho + margin`` (its width there is ``2 (c - rho)``).  Each
connected run of such points between one pair of components is a gate: its centre line is
the segment spanned by the run (principal axis), its axis the segment's direction.

A narrow corridor inside one component's concavity (between two sides of one polygon) is not
found: the diagram is between components.  That is a stated limitation, not a guarantee.

:class:`Traffic` is the mutex: a robot whose path (traced ahead by the caller along its
nominal field) enters a gate *requests* it with the direction it will cross it in; a request
is *granted* when no robot holds the gate in the other direction and no robot waits for it
in the other direction since an earlier step (first come, first served between directions;
ties to the robot nearer the gate, then the lower index: deterministic).  A granted robot
holds the gate until it is out on the far side (or its path no longer enters it).  A robot
that is not granted *waits*, also one already inside the gate (pushed in, or its goal is
there): the caller stops its nominal command once it is within ``stop`` m of the gate's
centre line, and lets it step aside as an idle robot
(:func:`confnav.navigation.fleet.yield_way`) for the robots coming out, never toward the
gate (:meth:`Traffic.toward`).  Guaranteed: granted robots of one gate all cross it in one
direction.  Not guaranteed: that no robot is in a gate against its holders (an ungranted one
inside is not removed, only stopped), nor any arrival.  Measured worse than without it on
the warehouse bench, so :func:`~confnav.navigation.fleet_sim.simulate_fleet` has it off by
default.  Only nominal
commands change: the fleet filter's rows bound the filtered command, so the rule never costs
safety (docs/NAVIGATION.md, "Fleets").  It is a liveness heuristic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from confnav.errors import NavigationError
from confnav.geometry import Workspace
from confnav.types import CArray, FArray

__all__ = ["Gates", "Traffic", "find_gates", "segment_distance"]


@dataclass(frozen=True)
class Gates:
    """Single-lane passages: centre-line segments ``a[g] .. b[g]`` (complex), the narrowest
    width of the centres' free space ``width[g]`` (m), the boundary components ``pair[g]``
    (indices into ``Workspace.boundaries``) and the lane ``2 rho`` they were found for."""

    a: CArray
    b: CArray
    width: FArray
    pair: NDArray[np.intp]
    lane: float

    @property
    def count(self) -> int:
        return int(self.a.size)

    @property
    def axis(self) -> CArray:
        d = self.b - self.a
        m = np.abs(d)
        return np.asarray(np.where(m > 0, d / np.where(m > 0, m, 1.0), 1.0 + 0j))

    @property
    def centre(self) -> CArray:
        return np.asarray(0.5 * (self.a + self.b))

    @staticmethod
    def none(lane: float = 0.0) -> Gates:
        z = np.zeros(0, dtype=np.complex128)
        return Gates(z, z.copy(), np.zeros(0), np.zeros((0, 2), dtype=np.intp), lane)


def _component_distance(z: CArray, poly: CArray) -> FArray:
    """Exact distance from each point to the closed polygon ``poly`` (its sides)."""
    a = np.asarray(poly, dtype=np.complex128)
    b = np.roll(a, -1)
    d = b - a
    dd = np.abs(d) ** 2
    t = np.clip(((z[:, None] - a[None, :]) * np.conj(d)[None, :]).real / dd[None, :], 0.0, 1.0)
    return np.asarray(np.abs(z[:, None] - (a[None, :] + t * d[None, :])).min(axis=1))


def segment_distance(z: ArrayLike, a: ArrayLike, b: ArrayLike) -> FArray:
    """Distance from points ``z`` (any shape S) to segments ``a[g] .. b[g]``: shape S + (G,)."""
    zz = np.asarray(z, dtype=np.complex128)[..., None]
    aa = np.asarray(a, dtype=np.complex128)
    d = np.asarray(b, dtype=np.complex128) - aa
    dd = np.abs(d) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dd > 0, ((zz - aa) * np.conj(d)).real / np.where(dd > 0, dd, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.asarray(np.abs(zz - (aa + t * d)))


def find_gates(
    workspace: Workspace, rho: float, *, margin: float = 0.1, spacing: float = 0.05
) -> Gates:
    """The passages of ``workspace`` where disks of radius ``rho`` cannot pass each other.

    Grid points at ``spacing`` m; a point is on the diagram between its two nearest
    components when their distances differ by at most ``spacing`` (the distances are
    1-Lipschitz, so every diagram point has a grid point within ``spacing / 2`` that passes);
    it is narrow when the nearer distance ``c`` has ``rho < c < 2 rho + margin / 2``.  Runs
    of such points (8-connected on the grid, one pair of components each) with at least two
    points are the gates.  Exact distances to the polygons; the grid only samples where the
    diagram lies, so a gate's ends are known to ``spacing``.
    """
    if not (rho > 0 and spacing > 0 and margin >= 0):
        raise NavigationError(
            f"rho > 0, spacing > 0, margin >= 0 needed, got {rho}, {spacing}, {margin}"
        )
    comps = workspace.boundaries
    lane = 2.0 * rho
    if len(comps) < 2:
        return Gates.none(lane)
    x0, y0, x1, y1 = workspace.bounds
    xs = np.arange(x0, x1 + 0.5 * spacing, spacing)
    ys = np.arange(y0, y1 + 0.5 * spacing, spacing)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = (gx + 1j * gy).ravel()
    dist = np.stack([_component_distance(z, np.asarray(c)) for c in comps], axis=1)
    order = np.argsort(dist, axis=1, kind="stable")[:, :2]
    d1 = np.take_along_axis(dist, order[:, :1], axis=1)[:, 0]
    d2 = np.take_along_axis(dist, order[:, 1:2], axis=1)[:, 0]
    k1, k2 = np.minimum(order[:, 0], order[:, 1]), np.maximum(order[:, 0], order[:, 1])
    inside = workspace.contains(z)
    narrow = inside & (d2 - d1 <= spacing) & (d1 > rho) & (d1 < lane + 0.5 * margin)
    if not narrow.any():
        return Gates.none(lane)
    pair_id = np.where(narrow, k1 * len(comps) + k2, -1).reshape(gx.shape)
    a_out: list[complex] = []
    b_out: list[complex] = []
    w_out: list[float] = []
    p_out: list[tuple[int, int]] = []
    zg = z.reshape(gx.shape)
    dg = d1.reshape(gx.shape)
    for pid in np.unique(pair_id[pair_id >= 0]):
        lab, nlab = ndimage.label(pair_id == pid, structure=np.ones((3, 3), dtype=bool))
        for k in range(1, nlab + 1):
            m = lab == k
            if m.sum() < 2:
                continue
            pts = zg[m]
            c = pts.mean()
            q = np.column_stack([(pts - c).real, (pts - c).imag])
            _, _, vt = np.linalg.svd(q, full_matrices=False)
            ax = complex(vt[0, 0], vt[0, 1])
            s = ((pts - c) * np.conj(ax)).real
            a_out.append(c + s.min() * ax)
            b_out.append(c + s.max() * ax)
            w_out.append(2.0 * (float(dg[m].min()) - rho))
            p_out.append((int(pid) // len(comps), int(pid) % len(comps)))
    return Gates(
        a=np.array(a_out, dtype=np.complex128),
        b=np.array(b_out, dtype=np.complex128),
        width=np.array(w_out, dtype=np.float64),
        pair=np.array(p_out, dtype=np.intp).reshape(-1, 2),
        lane=lane,
    )


class Traffic:
    """The gates' mutex for N robots (see the module docstring).

    ``occupy``: a robot's centre within ``occupy`` m of a gate's centre line is *in* it
    (default ``lane / 2 + margin``: anywhere a second disk could not pass it); ``stop``: a
    waiting robot's nominal command is zeroed within ``stop`` m of the centre line (default
    ``occupy + 0.5``: room for the robot coming out to pass it).

    State per robot: ``gate`` (requested or held, -1 none), ``dirn`` (+1: crossing along the
    gate's axis, -1 against it), ``granted``, ``since`` (the step its request began).
    """

    def __init__(
        self,
        gates: Gates,
        n: int,
        *,
        occupy: float | None = None,
        stop: float | None = None,
        margin: float = 0.05,
    ) -> None:
        self.gates = gates
        self.occupy = float(0.5 * gates.lane + margin if occupy is None else occupy)
        self.stop = float(self.occupy + 0.5 if stop is None else stop)
        self.gate = np.full(n, -1, dtype=np.intp)
        self.dirn = np.zeros(n, dtype=np.int8)
        self.granted = np.zeros(n, dtype=bool)
        self.since = np.zeros(n, dtype=np.int64)
        self.step = 0
        self.waits = 0  # robot-steps spent waiting (not granted, within ``stop``)
        self.grants = 0

    def _side(self, p: CArray, g: NDArray[np.intp]) -> FArray:
        """Signed coordinate of each point along its gate's axis, from the gate's centre."""
        gt = self.gates
        return np.asarray(((p - gt.centre[g]) * np.conj(gt.axis[g])).real)

    def update(
        self, p: ArrayLike, path: ArrayLike, active: ArrayLike
    ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """One control step: positions ``p`` (N), each robot's path ahead ``path`` (N, K:
        points along its nominal field, ``p`` first; NaN where it ends) and which robots take
        part (``active``: moving, not done).  Returns ``(wait, hold)``: robots to stop (not
        granted and within ``stop`` of their gate) and robots holding a gate."""
        pp = np.asarray(p, dtype=np.complex128).reshape(-1)
        n = pp.size
        act = np.asarray(active, dtype=bool).reshape(-1)
        gt = self.gates
        self.step += 1
        if gt.count == 0 or n == 0:
            return np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        P = np.asarray(path, dtype=np.complex128).reshape(n, -1)
        dpath = segment_distance(P, gt.a, gt.b)  # (N, K, G)
        dpath = np.where(np.isfinite(dpath), dpath, np.inf)
        hit: NDArray[np.bool_] = np.asarray(dpath < self.occupy)
        inside: NDArray[np.bool_] = hit[:, 0, :]  # (N, G): in a gate now
        any_hit: NDArray[np.bool_] = np.asarray(hit.any(axis=1))
        first_k = np.where(any_hit, np.argmax(hit, axis=1), hit.shape[1])  # (N, G)
        nxt = np.argmin(first_k, axis=1)  # the gate the path enters first
        has = any_hit[np.arange(n), nxt] & act
        # keep a held gate while inside it or its path still enters it; else take the next
        cur = self.gate
        keep = (cur >= 0) & act
        ci = np.where(cur >= 0, cur, 0)
        still = keep & (inside[np.arange(n), ci] | any_hit[np.arange(n), ci])
        new_gate = np.where(still, cur, np.where(has, nxt, -1))
        changed = new_gate != cur
        side = np.where(new_gate >= 0, self._side(pp, np.where(new_gate >= 0, new_gate, 0)), 0.0)
        # a new request crosses toward the far side; a robot inside with no side yet: its path
        self.dirn = np.where(changed, np.where(side > 0, -1, 1), self.dirn).astype(np.int8)
        self.granted = np.where(changed, False, self.granted)
        self.since = np.where(changed, self.step, self.since)
        self.gate = new_gate
        g = self.gate
        on = g >= 0
        gi = np.where(on, g, 0)
        in_own = on & inside[np.arange(n), gi]
        # grants: per gate and direction, the holders and the earliest waiting request
        G = gt.count
        pend = on & ~self.granted
        if pend.any():
            idx = np.flatnonzero(on)
            dcol = (self.dirn[idx] > 0).astype(np.intp)  # 0: -1, 1: +1
            held = np.zeros((G, 2), dtype=bool)
            hsel = self.granted[idx]
            held[g[idx][hsel], dcol[hsel]] = True
            # rank of each pending request: (since, distance to the gate, index)
            dist = segment_distance(pp[idx], gt.a, gt.b)[np.arange(idx.size), g[idx]]
            psel = ~hsel
            pi, pg, pd = idx[psel], g[idx][psel], dcol[psel]
            key = np.lexsort((pi, dist[psel], self.since[pi]))
            first = np.full((G, 2), -1, dtype=np.intp)  # the earliest request per gate/dirn
            for_rank = np.empty(key.size, dtype=np.intp)
            for_rank[key] = np.arange(key.size)
            best = np.full((G, 2), np.iinfo(np.intp).max, dtype=np.intp)
            np.minimum.at(best, (pg, pd), for_rank)
            has_first = best < np.iinfo(np.intp).max
            first[has_first] = key[best[has_first]]
            opp = 1 - pd
            opp_held = held[pg, opp]
            opp_first = first[pg, opp]
            my_rank = for_rank
            opp_rank = np.where(opp_first >= 0, best[pg, opp], np.iinfo(np.intp).max)
            ok = ~opp_held & (my_rank < opp_rank)
            # robots of one direction are granted together only if none holds the other way
            self.granted[pi[ok]] = True
            self.grants += int(ok.sum())
        d_now = segment_distance(pp, gt.a, gt.b)[np.arange(n), gi]
        wait = on & ~self.granted & (d_now < self.stop)
        # release: out of the gate on its far side (crossed), or the path left it
        crossed = on & self.granted & ~in_own & (np.sign(self._side(pp, gi)) == self.dirn)
        crossed &= ~any_hit[np.arange(n), gi]
        self.gate = np.where(crossed | ~act, -1, self.gate)
        self.granted &= self.gate >= 0
        self.waits += int(wait.sum())
        return wait, self.granted & (self.gate >= 0)

    def away(self, p: ArrayLike) -> tuple[CArray, FArray]:
        """For robots with a gate: the unit vector from the nearest point of its centre line
        to ``p`` and the distance (0j and inf for robots without a gate)."""
        pp = np.asarray(p, dtype=np.complex128).reshape(-1)
        on = self.gate >= 0
        if not on.any():
            return np.zeros(pp.size, dtype=np.complex128), np.full(pp.size, np.inf)
        gt = self.gates
        g = np.where(on, self.gate, 0)
        a, d = gt.a[g], gt.b[g] - gt.a[g]
        dd = np.abs(d) ** 2
        t = ((pp - a) * np.conj(d)).real / np.where(dd > 0, dd, 1.0)
        s = np.clip(np.where(dd > 0, t, 0.0), 0.0, 1.0)
        v = pp - (a + s * d)
        m = np.abs(v)
        e = np.where(on & (m > 0), v / np.where(m > 0, m, 1.0), 0j)
        return np.asarray(e), np.asarray(np.where(on, m, np.inf))

    def toward(self, p: ArrayLike, u: ArrayLike) -> NDArray[np.bool_]:
        """Robots with a gate whose command ``u`` brings them closer to its centre line (a
        waiting robot that steps aside must not step into the gate)."""
        e, _ = self.away(p)
        uu = np.asarray(u, dtype=np.complex128).reshape(-1)
        return np.asarray((self.gate >= 0) & (np.real(np.conj(e) * uu) < 0))
