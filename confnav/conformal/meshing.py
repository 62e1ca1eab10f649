"""Mesh planning: nodes per polygon side from the corners, the gaps and a tolerance.

Two error sources decide how many graded-mesh nodes a panel needs:

* **corners.** At a corner with free-space angle ``a pi`` the map behaves like ``r^(1/a)``; on
  Kress's graded mesh that is ``tau^(p/a)`` and the trapezoidal rule converges like
  ``n^-(p/a + 1)`` [1]. Panels ending at a polygon corner get ``level^(e_ref/e)`` nodes, where
  ``e = p/a + 1`` of the polygon's worst corner; ``level`` is the refinement knob of
  :func:`confnav.conformal.solver.solve`.
* **proximity.** The Cauchy sums across a gap of width d between a panel and another boundary
  (or the anchor, or a non-adjacent side of the same polygon: the two faces of a thin wall)
  converge like ``e^(-2 pi d/h)`` for local mesh spacing h [2, 3], so
  ``h(x) <= 2 pi d(x) / ln(10/tol)`` is required at every point x of a side, with d(x) the
  distance of x to the nearest such feature and h(x) = len sigma'(tau) / n the local spacing
  of Kress's sigma mesh (checked at :data:`PROXIMITY_SAMPLES` points per side). Kress's
  grading already makes the spacing small towards the corners, so a close approach at a
  corner (two squares facing each other: the sides meeting the facing ones) costs few nodes,
  while a gap along a whole side (the facing sides, a thin wall's faces) is resolved all
  along. (Splitting long sides into shorter panels near close features
  was tried and measured worse: the grading at the split points wastes nodes, and on the
  default workspace 48 nodes on an unsplit outer side beat ~60 on split panels by 70x in the
  centres. The exception: a side that would need more than :data:`SPLIT_NODES` nodes for a gap
  along only part of it, a table near a long wall, is split around that stretch when this at
  least halves its nodes; see :func:`_split_close_stretches`.)

References
----------
.. [1] R. Kress, Numer. Math. 58 (1990) 145-161 (graded meshes, convergence order).
.. [2] J. Helsing, R. Ojala, "On the evaluation of layer potentials close to their sources",
   J. Comput. Phys. 227 (2008) 2899-2921 (near-singular quadrature error ~ e^(-2 pi d/h)).
.. [3] A. H. Barnett, "Evaluation of layer potentials close to the boundary for Laplace and
   Helmholtz problems on analytic planar domains", SIAM J. Sci. Comput. 36 (2014) A427-A451,
   its error analysis of the periodic trapezoid rule (error ~ e^(-n Im t*) for a target whose
   complexified parameter is t*).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from confnav.conformal.boundary import GRADING_P, kress_sigma
from confnav.errors import GapError
from confnav.geometry import Workspace
from confnav.types import CArray as ComplexArray

#: Free-space corner angle (units of pi) taken as the reference for ``level``.
REF_ANGLE = 1.75
#: Kress's grading narrows the strip of analyticity of the integrands (sigma has complex poles
#: near the middle of each side), so the e^(-2 pi d/h) rate is reached only for about half
#: the spacing: measured on the 4x2 rectangle, factor 1 leaves 3e-10 error at tol 1e-12,
#: factor 2 gives 1.3e-12 (the exact f'(0) of docs/METHOD.md sec. 4).
GRADING_STRIP = 2.0
#: Level at which the proximity rule is applied as derived (it scales like a straight corner).
LEVEL_BASE = 80
#: Every boundary's node total is a multiple of this, so that every 2nd/4th/8th node is again
#: an equispaced trapezoidal rule on the same parametrisation (fast evaluation of the map).
NODE_MULTIPLE = 8
#: Fewest nodes on any panel.
MIN_NODES = 12
#: Sides at a corner of angle theta (see module docstring) get at least this times
#: ``p / sin(theta)`` nodes.
SHARP_NODES_FACTOR = 2.0

#: Most nodes a side may get from the proximity rule; a gap needing more raises GapError
#: (a silently capped mesh would under-resolve the gap at every level alike, invisible to the
#: level-difference estimate).
MAX_NODES_PER_PANEL = 4000
#: A side whose gap would need more than this many nodes is split (collinear panel ends)
#: around its close stretch, if that at least halves the polygon's proximity nodes
#: (SPLIT_GAIN) ...
SPLIT_NODES = 1000
SPLIT_GAIN = 0.5
#: ... the stretch being the samples within this factor of the side's smallest distance ...
SPLIT_CLOSE = 2.0
#: ... widened by this many smallest distances on each side (beyond it d(x) has grown enough
#: that the rest of the side needs only ordinary spacing).
SPLIT_MARGIN = 4.0
#: Samples per side at which the proximity rule is checked (uniform in the mesh parameter tau,
#: so they follow the node density: the rule's ratio h/d is smooth in tau).
PROXIMITY_SAMPLES = 128


@dataclass(frozen=True)
class PanelPlan:
    """Sides of one boundary: its vertices and the graded-mesh node count of each side."""

    vertices: ComplexArray
    nodes: np.ndarray

    @property
    def total(self) -> int:
        return int(self.nodes.sum())


def corner_exponent(polygon: ComplexArray, hole: bool, p: int = GRADING_P) -> float:
    """Convergence exponent ``p/a + 1`` of the polygon's worst corner seen from the free space."""
    e_in = polygon - np.roll(polygon, 1)
    e_out = np.roll(polygon, -1) - polygon
    interior = np.pi - np.angle(e_out / e_in)  # interior angle of the (ccw) polygon
    a = (2 * np.pi - interior) / np.pi if hole else interior / np.pi
    return p / max(float(a.max()), 0.75) + 1.0


def sharp_corner_nodes(polygon: ComplexArray, p: int = GRADING_P) -> np.ndarray:
    """Fewest nodes on each side so that the tips of sharp corners stay stable (module docstring).

    ``theta`` is the angle between the two sides at a vertex, the smaller of interior and
    exterior; each side takes the larger requirement of its two end vertices.
    """
    e_in = polygon - np.roll(polygon, 1)
    e_out = np.roll(polygon, -1) - polygon
    interior = np.abs(np.pi - np.abs(np.angle(e_out / e_in)))  # in [0, pi]: smaller angle
    need = np.ceil(SHARP_NODES_FACTOR * p / np.maximum(np.sin(interior), 1e-3))
    need = np.where(interior < np.pi / 2, need, 0)  # right and obtuse corners: no requirement
    return np.maximum(need, np.roll(need, -1)).astype(np.intp)  # side k: vertices k and k+1


def _lines(a: ComplexArray, b: ComplexArray) -> np.ndarray:
    xy = np.stack([np.column_stack([a.real, a.imag]), np.column_stack([b.real, b.imag])], axis=1)
    return np.asarray(shapely.linestrings(xy))


def _sample_taus() -> tuple[np.ndarray, np.ndarray]:
    """Sample positions tau in (0, 2pi) along a side and the Kress mesh's sigma'(tau) there."""
    tau = 2 * np.pi * (np.arange(PROXIMITY_SAMPLES) + 0.5) / PROXIMITY_SAMPLES
    sig, dsig = kress_sigma(tau)
    return sig / (2 * np.pi), dsig


def _proximity_nodes(length: np.ndarray, dsig: np.ndarray, d: np.ndarray, tol: float) -> np.ndarray:
    """Nodes per side so that the local spacing meets the proximity rule at every sample.

    Side k with n_k nodes has local spacing ``h = len_k sigma'(tau) / n_k`` at ``tau``
    (boundary module: d eta/d tau = edge sigma'/(2pi), tau step 2pi/n_k). The trapezoidal rule
    for a target at distance d from the boundary point x errs like ``e^(-2 pi d / h(x))``,
    h(x) the local spacing at x: the periodic trapezoid rule's error decays like
    ``e^(-n Im t*)``, t* the complex preimage of the target under the parametrisation, which
    lies ~ d/|eta'(t)| off the real axis [3] (and [2] for the e^(-2 pi d/h) form), so
    ``h(x) <= 2 pi d(x) / (GRADING_STRIP ln(10/tol))`` at every
    sample x of the side, ``d(x)`` its distance to the nearest feature. Because sigma' vanishes
    to order p - 1 at the side's ends, a close approach at a corner (two squares facing each
    other: the sides meeting the facing one) needs few nodes, while a gap along the whole side
    (the facing sides, the two faces of a thin wall) is resolved all along.
    ``length`` (L,), ``dsig`` (M,), ``d`` (L, M).
    """
    # sigma' over a sample's cell: the larger of its own and its neighbours' values
    cell = np.maximum(dsig, np.maximum(np.roll(dsig, 1), np.roll(dsig, -1)))
    ratio = length[:, None] * cell[None, :] / np.maximum(d, 1e-12)
    return np.asarray(np.ceil(GRADING_STRIP * np.log(10 / tol) / (2 * np.pi) * ratio.max(axis=1)))


def _segment_distance(z: ComplexArray, a: ComplexArray, b: ComplexArray) -> np.ndarray:
    """Distance of points ``z`` (..., 1) to segments ``[a, b]`` (broadcast), complex algebra."""
    e = b - a
    t = np.clip(((z - a) * np.conj(e)).real / np.maximum(np.abs(e) ** 2, 1e-300), 0.0, 1.0)
    return np.asarray(np.abs(z - a - t * e))


#: :func:`_nearest_features` computes the exact distances to this many features (those whose
#: bounding boxes are nearest) before it bounds the others away.
NEAR_FEATURES_FIRST = 8


def _nearest_features(
    z: ComplexArray, pts: np.ndarray, segs: np.ndarray, features: list[shapely.Geometry]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance of every sample ``pts`` and every side ``segs`` of the polygon ``z`` to its
    nearest feature, and the index (into ``features``) of each side's nearest one.

    The same values as the distances to every feature (bit for bit: a minimum is exact), from
    fewer of them: a feature whose bounding box is farther from the polygon's bounding box
    (which holds every sample and side) than ``U`` -- the largest of the nearest distances
    over the :data:`NEAR_FEATURES_FIRST` features with the nearest boxes -- is farther than
    ``U`` from every sample and side, so it is nobody's nearest (ties keep the first index, as
    ``argmin`` over all features did: a feature left out is strictly farther). On 50 obstacles
    the 51 x 51 shapely distances were 0.42 s of a cold solve, now 0.11 s (bench/README.md,
    "Round 6"; bench/results/core_profile_round6.json).
    """
    n = len(features)
    x0, y0, x1, y1 = (
        float(z.real.min()),
        float(z.imag.min()),
        float(z.real.max()),
        float(z.imag.max()),
    )
    fb = np.asarray(shapely.bounds(np.asarray(features, dtype=object)), dtype=float).reshape(n, 4)
    gx = np.maximum(0.0, np.maximum(fb[:, 0] - x1, x0 - fb[:, 2]))
    gy = np.maximum(0.0, np.maximum(fb[:, 1] - y1, y0 - fb[:, 3]))
    lower = np.hypot(gx, gy)  # box-to-box distance: at most any sample's or side's distance
    order = np.argsort(lower, kind="stable")

    def exact(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        P = np.stack([np.asarray(shapely.distance(pts, features[i]), float) for i in idx], 1)
        S = np.stack([np.asarray(shapely.distance(segs, features[i]), float) for i in idx], 1)
        return P, S

    first = order[: min(n, NEAR_FEATURES_FIRST)]
    P, S = exact(first)
    bound = max(float(P.min(axis=1).max()), float(S.min(axis=1).max()))
    rest = order[first.size :]
    more = rest[lower[rest] <= bound]
    if more.size:
        P2, S2 = exact(more)
        P, S = np.concatenate([P, P2], axis=1), np.concatenate([S, S2], axis=1)
    kept = np.concatenate([first, more])
    cols = np.argsort(kept, kind="stable")  # the features' own order: argmin's ties as before
    P, S, kept = P[:, cols], S[:, cols], kept[cols]
    return P.min(axis=1), S.min(axis=1), kept[np.argmin(S, axis=1)]


def _feature_distance(
    z: ComplexArray, features: list[shapely.Geometry], frac: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Lower bound of the distance to the nearest feature over the cell of each sample of each
    side, (L, M), and which feature is nearest to each side (index into ``features``, or -1 for
    a non-adjacent side of the same polygon: the arms of a U, the two faces of a thin wall).

    The distance is 1-Lipschitz along the side, so over the part of the side nearer to sample i
    than to its neighbours it is at least ``d_i - r_i`` (r_i that part's reach from the
    sample), and never below the side's exact distance to the features: a close approach
    narrower than the sample spacing is not missed (it falls back to the side's minimum).
    """
    L = z.size
    edge = np.roll(z, -1) - z
    x = z[:, None] + edge[:, None] * frac[None, :]  # (L, M) sample points
    pts = shapely.points(x.real.ravel(), x.imag.ravel())
    segs = _lines(z, np.roll(z, -1))
    d, side_min, which = _nearest_features(z, pts, segs, features)
    d = d.reshape(L, frac.size)
    if L > 3:  # self-proximity: distance of side k's samples to the sides k+2 .. k-2
        k = np.arange(L)
        others = (k[:, None] + np.arange(2, L - 1)[None, :]) % L  # (L, L-3)
        a, b = z[others], np.roll(z, -1)[others]
        own = _segment_distance(x[:, :, None], a[:, None, :], b[:, None, :]).min(axis=2)
        # non-adjacent sides of a simple polygon do not cross: their distance is attained at
        # an endpoint of one of them
        own_side = np.minimum(
            np.minimum(
                _segment_distance(z[:, None], a, b),
                _segment_distance(z[others], z[:, None], z[(k + 1) % L][:, None]),
            ),
            np.minimum(
                _segment_distance(np.roll(z, -1)[:, None], a, b),
                _segment_distance(b, z[:, None], z[(k + 1) % L][:, None]),
            ),
        ).min(axis=1)
        which = np.where(own_side < side_min, -1, which)
        d = np.minimum(d, own)
        side_min = np.minimum(side_min, own_side)
    cells = np.concatenate([[0.0], 0.5 * (frac[1:] + frac[:-1]), [1.0]])
    reach = np.maximum(frac - cells[:-1], cells[1:] - frac)  # (M,), fraction of the side
    d_low = np.maximum(d - np.abs(edge)[:, None] * reach[None, :], side_min[:, None])
    return d_low, which


def _split_close_stretches(
    z: ComplexArray, d: np.ndarray, n_prox: np.ndarray, frac: np.ndarray
) -> ComplexArray:
    """``z`` with collinear vertices inserted around the close stretch of every side that would
    need more than :data:`SPLIT_NODES` nodes.

    A gap along part of a long side (a table 5 cm from a 6 m wall) otherwise forces the gap's
    spacing onto the whole side, the graded mesh being one panel per side; as its own panel the
    stretch gets it alone, and the two outer panels grade towards it as towards a straight
    corner (a = 1, no singularity), which costs few nodes. Only such sides are split, and only
    where it halves the nodes: elsewhere one panel per side was measured better (module
    docstring). Measured on
    near_touching (a 1.2 m table 0.05 from a 6 m wall, 2 cm cabinets): tol 1e-10 met (estimate
    5.4e-11, residual 2.7e-11) instead of the node cap at 256 nodes per side and 8.5e-9.
    """
    out: list[complex] = []
    L = z.size
    for k in range(L):
        a, b = complex(z[k]), complex(z[(k + 1) % L])
        out.append(a)
        if n_prox[k] <= SPLIT_NODES:
            continue
        length = abs(b - a)
        dmin = float(d[k].min())
        close = np.flatnonzero(d[k] <= SPLIT_CLOSE * dmin)
        pad = SPLIT_MARGIN * dmin / length
        t0, t1 = frac[close[0]] - pad, frac[close[-1]] + pad
        out += [a + t * (b - a) for t in (t0, t1) if pad < t < 1 - pad]
    return np.asarray(out, dtype=np.complex128)


def _name(j: int) -> str:
    return "the outer boundary" if j == 0 else f"obstacle {j - 1}"


#: :func:`_feature_distance` per boundary, keyed by the workspace's geometry: it does not
#: depend on the level, and plan_boundaries runs once per mesh level (six to eight times per
#: solve; on 50 obstacles its shapely distances took ~5 % of the solve, profiled).
_FEATURE_CACHE: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
FEATURE_CACHE_SIZE = 512


def _feature_distance_cached(
    key: bytes, z: ComplexArray, features: list[shapely.Geometry], frac: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_feature_distance`, remembered under ``key`` (the geometry it depends on)."""
    full = key + z.tobytes() + frac.tobytes()
    hit = _FEATURE_CACHE.get(full)
    if hit is None:
        if len(_FEATURE_CACHE) >= FEATURE_CACHE_SIZE:
            _FEATURE_CACHE.clear()
        hit = _feature_distance(z, features, frac)
        _FEATURE_CACHE[full] = hit
    return hit[0].copy(), hit[1].copy()


def plan_boundaries(ws: Workspace, level: int, tol: float) -> list[PanelPlan]:
    """Panels and nodes for every boundary (outer first) at one refinement level.

    Raises
    ------
    GapError
        A side is so close to another boundary (or to the anchor, or to another side of its
        own polygon) that resolving the gap at this level and ``tol`` needs more than
        :data:`MAX_NODES_PER_PANEL` nodes on it; the message names both and the gap.
    """
    e_ref = GRADING_P / REF_ANGLE + 1.0
    # The proximity requirement refines with the level too (like a straight corner, exponent
    # p + 1), so that every error source shrinks as the level grows.
    scale = (level / LEVEL_BASE) ** (e_ref / (GRADING_P + 1.0))
    polys = ws.boundaries
    rings = [shapely.LinearRing(np.column_stack([z.real, z.imag])) for z in polys]
    anchor = shapely.Point(ws.anchor.real, ws.anchor.imag)
    frac, dsig = _sample_taus()
    geometry = b"|".join(np.asarray(p, np.complex128).tobytes() for p in polys)
    geometry += np.complex128(ws.anchor).tobytes()
    plans = []
    for j, z in enumerate(polys):
        idx = [i for i in range(len(rings)) if i != j]
        n_corner = max(MIN_NODES, int(np.ceil(level ** (e_ref / corner_exponent(z, j > 0)))))
        features = [anchor, *(rings[i] for i in idx)]
        key = geometry + b"#" + str(j).encode()
        d, which = _feature_distance_cached(key, z, features, frac)
        n_prox = np.ceil(scale * _proximity_nodes(np.abs(np.roll(z, -1) - z), dsig, d, tol))
        if n_prox.max() > SPLIT_NODES:
            zs = _split_close_stretches(z, d, n_prox, frac)
            ds, wh = _feature_distance_cached(key, zs, features, frac)
            ns = np.ceil(scale * _proximity_nodes(np.abs(np.roll(zs, -1) - zs), dsig, ds, tol))
            if ns.sum() < SPLIT_GAIN * n_prox.sum():
                z, d, which, n_prox = zs, ds, wh, ns
        over = np.flatnonzero(n_prox > MAX_NODES_PER_PANEL)
        if over.size:
            k = int(over[np.argmin(d[over].min(axis=1))])
            w = int(which[k])
            other = (
                f"side {k} and another side of {_name(j)}"
                if w < 0
                else ("the anchor" if w == 0 else _name(idx[w - 1]))
            )
            raise GapError(
                f"{_name(j)} (side {k}) and {other} are {d[k].min():.3g} apart: resolving that gap "
                f"to tol {tol:.0e} needs {int(n_prox[k])} nodes on the side, more than the "
                f"{MAX_NODES_PER_PANEL} the mesh allows (widen the gap, merge the two, or "
                "ask for a looser tol)"
            )
        n = np.maximum(np.maximum(n_corner, n_prox), sharp_corner_nodes(z)).astype(np.intp)
        n[0] += (-int(n.sum())) % NODE_MULTIPLE  # totals divisible: see ConformalMap.coarsened
        plans.append(PanelPlan(vertices=z, nodes=n))
    return plans


__all__ = ["PanelPlan", "corner_exponent", "plan_boundaries", "sharp_corner_nodes"]
