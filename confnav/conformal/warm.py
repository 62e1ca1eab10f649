"""Warm re-solve (issue 24 item 3): the previous map of a workspace that changed a little as
the start of the Koebe iteration at the previous map's finest mesh level.

A map ``T`` of a domain with boundaries ``Gamma_i`` (outer counter-clockwise, holes clockwise)
is the sum of the Cauchy integrals of its boundary values over each boundary,

    T(z) = sum_i C_i(z),    C_i(z) = (1/2 pi i) oint_{Gamma_i} T(zeta)/(zeta - z) dzeta,

and ``C_i`` is analytic everywhere off ``Gamma_i`` (Henrici, "Applied and Computational
Complex Analysis", Vol. 3, Wiley 1986, sec. 14.1: Cauchy integrals; the Laurent decomposition
of a function on a multiply connected domain). When an obstacle moves by ``d``, its term moves
with it: ``G(z) = sum_i C_i(z - d_i)`` (``d_i = 0`` for the boundaries that stayed, the terms
of removed obstacles dropped) is analytic on the *new* domain, and on a boundary ``b`` its
values follow from the old ones by the jump relation (Plemelj): the term of ``b`` itself tends
to ``T(eta) - sum_{i != b} C_i(eta)`` at its own (old) node ``eta``, so at the new node
``eta + d_b``

    G = W_b + sum_{i != b, kept} C_i(eta + d_b - d_i) - sum_{i != b} C_i(eta),

only the terms of boundaries that moved relative to ``b`` (or were removed) contributing. An
added obstacle's nodes get ``sum_{kept} C_i(z - d_i)``. ``G`` maps the new domain onto a domain
whose boundaries are the previous circles moved by the change's influence (a small, analytic
perturbation away from the changed obstacle), so the sweeps start next to their fixed point.
The trapezoidal sums are exact rational functions of ``z``: ``G`` is analytic whatever their
quadrature error; what that error changes is only how close to circles the start is.

Meshes: a boundary that stayed keeps the previous map's graded mesh (moved with its obstacle),
so its corner singularities are resolved by the previous solve's boundary correspondence; only
a boundary whose previous mesh no longer meets the new geometry's mesh plan (a gap that
narrowed) makes the warm start decline (:func:`warm_state` returns None), as does another
outer boundary or anchor.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from confnav.conformal.boundary import BoundaryMesh, graded_polygon
from confnav.conformal.cauchy import cauchy_sums2
from confnav.conformal.circledomain import StartImage
from confnav.conformal.cmap import ConformalMap
from confnav.conformal.gnk import alive_nodes
from confnav.conformal.meshing import NODE_MULTIPLE, PanelPlan, plan_boundaries
from confnav.errors import GapError
from confnav.geometry import Workspace, interior_point, signed_area
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

#: Largest deviation of the start's boundaries from the previous circles (relative to each
#: radius) for which the warm start is used: beyond it the change is not small.
MAX_DEVIATION = 0.25
#: Largest share of the obstacles that may be new (unmatched) for a warm start (one is
#: always allowed): a workspace shrunk by another radius changes every boundary.
MAX_ADDED_SHARE = 0.25
#: Two polygons are the same one moved when their vertices differ by one translation to this
#: (relative to the workspace's diameter).
MATCH_RTOL = 1e-12


@dataclass
class WarmStart(StartImage):
    """The start of the sweeps on the new workspace (boundary order of the new workspace):
    its graded meshes and the image G of the nodes (:class:`StartImage`)."""

    meshes: list[BoundaryMesh] = field(default_factory=list)
    #: Largest distance of a start boundary from a circle (the previous one moved by the mean
    #: displacement of its nodes), relative to its radius (at least 1 with an added obstacle:
    #: it has no circle to be near).
    deviation: float = 0.0
    #: per new boundary: index of the previous boundary it continues (-1: added)
    source: list[int] = field(default_factory=list)


def _match(old: Workspace, new: Workspace) -> tuple[list[int], list[complex]] | None:
    """For each boundary of ``new``, the boundary of ``old`` it is (possibly moved: the
    translation), -1 if new; None if the outer boundary or the anchor differ."""
    scale = max(old.diameter, new.diameter)
    ob, nb = old.boundaries, new.boundaries
    if (
        ob[0].shape != nb[0].shape
        or np.max(np.abs(ob[0] - nb[0])) > MATCH_RTOL * scale
        or abs(old.anchor - new.anchor) > MATCH_RTOL * scale
    ):
        return None
    source, shift = [0], [0j]
    used = {0}
    for v in nb[1:]:
        hit, dd = -1, 0j
        for i, u in enumerate(ob):
            if i in used or u.shape != v.shape:
                continue
            d = complex(np.mean(v - u))
            if np.max(np.abs(v - u - d)) <= MATCH_RTOL * scale and (hit < 0 or abs(d) < abs(dd)):
                hit, dd = i, d  # the nearest copy (congruent obstacles: the one that moved least)
        if hit >= 0:
            used.add(hit)
        source.append(hit)
        shift.append(dd if hit >= 0 else 0j)
    return source, shift


def _actual_plan(plan: PanelPlan, eta: ComplexArray, hole: bool) -> PanelPlan | None:
    """The plan whose graded mesh is the previous mesh ``eta``: ``plan`` itself, or its sides
    with the node counts ``eta`` actually has on them (a level refined on some sides only,
    :func:`confnav.conformal.solver._refine_sides`), read off the nodes on the vertices --
    graded meshes put one on every vertex, and the nodes next to it that round onto the vertex
    too are tried from both ends. None if no such plan reproduces ``eta`` exactly."""
    n = eta.size
    atol = 1e-12 * float(np.max(np.abs(eta - eta.mean())))

    def same(p: PanelPlan) -> bool:
        m = _mesh(p, hole)
        return m.eta.shape == eta.shape and bool(np.allclose(m.eta, eta, rtol=0, atol=atol))

    if same(plan):
        return plan
    e = eta[(-np.arange(n)) % n] if hole else eta  # back to the plan's vertex order
    v = np.asarray(plan.vertices)
    L = v.size
    dist = np.abs(e[:, None] - v[None, :])
    ties = [np.flatnonzero(dist[:, k] <= dist[:, k].min()) for k in range(L)] + [np.array([n])]
    if ties[0][0] != 0:
        return None

    def side_ok(k: int, i0: int, i1: int) -> bool:
        counts = np.full(L, 4)
        counts[k] = i1 - i0
        if counts[k] < 4:
            return False
        nodes = graded_polygon(plan.vertices, counts).eta
        at = int(counts[:k].sum())
        return bool(np.allclose(nodes[at : at + counts[k]], e[i0:i1], rtol=0, atol=atol))

    # the vertex node of each vertex among the nodes that round onto it: the one whose sides'
    # graded nodes match (each side's nodes depend on its own count only)
    reach: list[dict[int, int]] = [{0: -1}]
    for k in range(L):
        nxt: dict[int, int] = {}
        for i0 in reach[-1]:
            for i1 in ties[k + 1]:
                if int(i1) > i0 and int(i1) not in nxt and side_ok(k, i0, int(i1)):
                    nxt[int(i1)] = i0
        if not nxt:
            return None
        reach.append(nxt)
    at = [n]
    for k in range(L, 0, -1):
        at.append(reach[k][at[-1]])
    cand = PanelPlan(vertices=plan.vertices, nodes=np.diff(np.array(at[::-1])))
    return cand if same(cand) else None


def _mesh(plan: PanelPlan, hole: bool) -> BoundaryMesh:
    m = graded_polygon(plan.vertices, plan.nodes)
    return m.reversed() if hole else m


def _components(
    eta: list[ComplexArray], deta: list[ComplexArray], W: list[ComplexArray], dW: list[ComplexArray]
) -> list[tuple[ComplexArray, ComplexArray, ComplexArray]]:
    """(sources, charges of C_i, charges of C_i') of each previous boundary's Cauchy term:
    ``C_i(z) = -(1/2 pi i) sum q/(z - eta)`` (trapezoidal rule, weight 2 pi/n)."""
    out = []
    for e, de, w, dw in zip(eta, deta, W, dW, strict=True):
        h = 2 * np.pi / e.size / (2j * np.pi)
        out.append((e, h * w * de, h * dw))
    return out


#: Graded nodes whose previous images lie closer than this (relative to the boundary's
#: size) to the previous kept node, or weigh less, are no sources of the start's sums.
CROWDED_RTOL = 1e-11


def _crowded_nodes(W: ComplexArray, dW: ComplexArray) -> np.ndarray:
    """Nodes next to corners the previous map compressed: their images lie within
    :data:`CROWDED_RTOL` of the previous kept one (or their quadrature weight is below it).
    As sources of a GNK solve on the start's curve they make the system singular to rounding
    (measured: GMRES stalled at a residual of 1e-1 on the previous map's own images of a
    12-pointed star's nodes, spacings down to 4.6e-15; the polygon's nodes themselves are
    well apart); dropped, they change the quadrature sums by their weights, below
    ``CROWDED_RTOL``."""
    size = float(np.max(np.abs(W - W.mean())))
    weight = np.abs(dW) * (2 * np.pi / W.size)
    out = ~alive_nodes(W, dW) | (weight < CROWDED_RTOL * size)
    last = None
    for i in np.flatnonzero(~out):  # sequential: each gap to the previous kept node
        if last is not None and abs(W[i] - W[last]) < CROWDED_RTOL * size:
            out[i] = True
        else:
            last = i
    return np.asarray(out)


#: One Cauchy term to evaluate: (boundary, points, sign).
_Request = tuple[int, ComplexArray, float]


def _requests(
    kept: dict[int, complex], n: int, src: int, d: complex, z: ComplexArray, atol: float
) -> list[_Request]:
    """The terms of ``G - T`` at points ``z`` of previous boundary ``src``, which moved by
    ``d`` (module docstring): the terms of the boundaries that moved relative to it at their
    new place (+) and at their old one (-; removed ones: - only)."""
    out: list[_Request] = []
    for i in range(n):
        if i == src:
            continue
        di = kept.get(i)
        if di is not None and abs(di - d) <= atol:
            continue  # moved together (or both stayed): the two terms cancel
        out.append((i, z, -1.0))
        if di is not None:
            out.append((i, z + d - di, 1.0))
    return out


def _evaluate(
    comps: list[tuple[ComplexArray, ComplexArray, ComplexArray]], groups: list[list[_Request]]
) -> list[tuple[ComplexArray, ComplexArray]]:
    """The signed sums of each group of terms and their derivatives, one Cauchy sum per
    boundary over all the points asked of it (the expansions are set up once)."""
    out = []
    for g in groups:
        size = g[0][1].size if g else 0
        out.append((np.zeros(size, np.complex128), np.zeros(size, np.complex128)))
    for i in range(len(comps)):
        asks = [(k, z, sg) for k, g in enumerate(groups) for (ii, z, sg) in g if ii == i]
        if not asks:
            continue
        t, dt = _term(comps[i], np.concatenate([z for _, z, _ in asks]))
        off = 0
        for k, z, sg in asks:
            out[k][0][:] += sg * t[off : off + z.size]
            out[k][1][:] += sg * dt[off : off + z.size]
            off += z.size
    return out


def _perturbation(
    comps: list[tuple[ComplexArray, ComplexArray, ComplexArray]],
    kept: dict[int, complex],
    src: int,
    d: complex,
    z: ComplexArray,
    atol: float,
) -> tuple[ComplexArray, ComplexArray]:
    """``G - T`` (and its derivative) at points ``z`` of previous boundary ``src``, which moved
    by ``d`` (:func:`_requests`)."""
    g = _requests(kept, len(comps), src, d, z, atol)
    if not g:
        return np.zeros(z.size, np.complex128), np.zeros(z.size, np.complex128)
    return _evaluate(comps, [g])[0]


def _smooth_image(
    initial: ConformalMap,
    comps: list[tuple[ComplexArray, ComplexArray, ComplexArray]],
    kept: dict[int, complex],
    src: int,
    d: complex,
    poles: ComplexArray,
    beta: ComplexArray,
    atol: float,
    tail: float,
) -> tuple[ComplexArray, ComplexArray, FloatArray, FloatArray]:
    """The start's image of previous boundary ``src`` as a smooth grid: uniform in the angle
    ``theta`` on its previous circle, ``S(s) = w(theta) + (G - T - L)(T^-1(w(theta)))``
    (``w(theta)`` the circle point, ``T^-1`` the previous map's inverse on its boundary), with
    ``theta = sgn s``; and the parameter ``u = sgn theta_i`` of each graded node (its previous
    image's angle) with ``du/dt``. The grid doubles from :data:`GRID_START` until its Fourier
    tail is below ``tail`` or it reaches :data:`GRID_MAX` (the iteration then reports the tail
    it solved on as a resolution error, never hides it)."""
    from confnav.conformal.circledomain import _tail
    from confnav.conformal.gnk import spectral_derivative_complex

    W, dW = initial._parts[2], initial._parts[3]
    hole = src > 0
    sgn = -1.0 if hole else 1.0
    cc = complex(initial.centers[src - 1]) if hole else 0j
    r = float(initial.radii[src - 1]) if hole else 1.0
    m = GRID_START
    while True:
        s = 2 * np.pi * np.arange(m) / m
        w = cc + r * np.exp(1j * sgn * s)
        z = initial.inverse(w, check=False)
        g = _perturbation(comps, kept, src, d, z, atol)[0]
        S = w + g - _rational(poles, beta, z + d)[0]
        if _tail(S) <= tail or m >= GRID_MAX:
            break
        m *= 2
    dS = spectral_derivative_complex(S)
    u = sgn * np.unwrap(np.angle(W[src] - cc))
    u = u - 2 * np.pi * np.floor(u[0] / (2 * np.pi))
    du = sgn * (dW[src] / (W[src] - cc)).imag
    return S, dS, np.asarray(u), np.asarray(du)


def _term(
    comp: tuple[ComplexArray, ComplexArray, ComplexArray], z: ComplexArray
) -> tuple[ComplexArray, ComplexArray]:
    """C_i and C_i' at points z off Gamma_i: the trapezoidal sum and its exact derivative (the
    derivative of the same rational function, so that the start's t-derivatives are those of
    its values even where the sum errs, next to another boundary)."""
    if z.size == 0:
        return np.zeros(0, np.complex128), np.zeros(0, np.complex128)
    first, second = cauchy_sums2(comp[0], [comp[1]], z, second=True)
    assert second is not None
    return -first[0], np.asarray(second[0])


#: Start the matched boundaries from smooth grids (:func:`_smooth_image`) rather than their
#: graded nodes. Measured and not used: the start's curve is singular at the corner images
#: (the moved terms are analytic in z, the previous map in (z - v)^(1/alpha)), so the grids
#: needed 8192 points and still missed 1e-8 (room of 3 convex obstacles: 14.6 s instead of
#: 0.23 s from the graded nodes; 10 mixed obstacles: boundary residual 1.2e-6).
SMOOTH_START_GRIDS = False
#: Smooth start grids: first size and cap (points per boundary).
GRID_START = 1024
GRID_MAX = 8192
#: Distance of a corner's pole from its corner, as a share of the shorter adjacent side.
POLE_SHARE = 0.2


def _rational(
    poles: ComplexArray, beta: ComplexArray, z: ComplexArray
) -> tuple[ComplexArray, ComplexArray]:
    """L(z) = sum beta/(z - p) and L'(z) at points z."""
    if poles.size == 0:
        return np.zeros(z.size, np.complex128), np.zeros(z.size, np.complex128)
    r = 1.0 / (z[:, None] - poles[None, :])
    return r @ beta, -(r * r) @ beta


def _corner_correction(
    ws: Workspace,
    source: list[int],
    shift: list[complex],
    comps: list[tuple[ComplexArray, ComplexArray, ComplexArray]],
    kept: dict[int, complex],
) -> tuple[ComplexArray, ComplexArray]:
    """Poles and residues of the rational L that makes the start compatible with the corners
    the map compresses.

    At a corner of free-space angle ``alpha pi < pi`` every conformal map of the domain is an
    analytic function of ``(z - v)^(1/alpha)`` (Schwarz reflection across the two straight
    sides; Henrici, Vol. 1, sec. 5.11), and so is the previous map, whose boundary values the
    start keeps. The Cauchy terms moved with an obstacle are analytic in ``z`` instead: their
    linear part ``q (z - v)`` dominates ``(z - v)^(1/alpha)`` next to the corner, a tiny copy
    of the corner on the start's curve that no graded mesh resolves (measured: GMRES stalled at
    2e-8 on a star's image; a boundary residual of 1e-7 at a room corner). ``L = sum beta_c /
    (z - p_c)``, one pole per compressing corner just outside the free space on its bisector,
    with ``L'(v_c) = q_c`` at every such corner, is analytic on the new domain; the start minus
    ``L`` has no linear part there (its next term, ``(z - v)^2``, is dominated by
    ``(z - v)^(1/alpha)`` for every ``alpha > 1/2``)."""
    verts, targets, poles = [], [], []
    scale = ws.diameter
    for j, (src, db) in enumerate(zip(source, shift, strict=True)):
        if src < 0:
            continue  # an added polygon: its own corners at full strength, as in a cold sweep
        v = np.asarray(ws.boundaries[j])
        if (signed_area(v) > 0) == (j > 0):
            v = v[::-1]  # free space on the left: outer counter-clockwise, holes clockwise
        prev, nxt = np.roll(v, 1), np.roll(v, -1)
        e1, e2 = (v - prev) / np.abs(v - prev), (nxt - v) / np.abs(nxt - v)
        turn = np.angle(e2 / e1)
        for k in np.flatnonzero(turn > 1e-6):  # a left turn: free-space angle below pi
            u = 1j * (e1[k] + e2[k])
            u /= abs(u)  # bisector into the free space
            side = min(abs(v[k] - prev[k]), abs(nxt[k] - v[k]))
            p = v[k] - POLE_SHARE * side * u
            q = 0j
            for i, comp in enumerate(comps):
                if i == src:
                    continue
                di = kept.get(i)
                if di is not None and abs(di - db) <= MATCH_RTOL * scale:
                    continue
                q -= complex(_term(comp, np.array([v[k] - db]))[1][0])
                if di is not None:
                    q += complex(_term(comp, np.array([v[k] - di]))[1][0])
            verts.append(v[k])
            targets.append(q)
            poles.append(p)
    if not verts:
        return np.zeros(0, np.complex128), np.zeros(0, np.complex128)
    vv, pp = np.array(verts), np.array(poles)
    A = -1.0 / (vv[:, None] - pp[None, :]) ** 2
    beta = np.linalg.solve(A, np.array(targets))
    return pp, np.asarray(beta)


def warm_state(
    initial: ConformalMap, ws: Workspace, tol: float, tail: float = 1e-12
) -> WarmStart | None:
    """The start of the sweeps on ``ws`` from ``initial`` (module docstring), at the finest
    level ``initial`` solved; None where it does not apply (another outer boundary or anchor,
    a previous mesh too coarse for the new geometry, a level that cannot be planned, a change
    that is not small: deviation above :data:`MAX_DEVIATION`)."""
    d0 = initial.diagnostics
    matched = _match(initial.workspace, ws)
    if matched is None or not d0.tol_met or d0.tol > tol:
        return None
    source, shift = matched
    if sum(1 for src in source if src < 0) > max(1, MAX_ADDED_SHARE * (len(source) - 1)):
        return None  # mostly new obstacles: not a small change
    meshes = _reused_meshes(initial, ws, tol, source, shift)
    if meshes is None:
        return None
    eta, deta, W, dW = initial._parts
    comps = _components(eta, deta, W, dW)
    kept = {src: d for src, d in zip(source, shift, strict=True) if src >= 0}
    boundary = _start_boundaries(initial, ws, source, shift, comps, kept, meshes)
    if boundary is None:
        return None
    P, dP, poles, beta = boundary
    a, D = _anchor_start(ws, comps, kept, poles, beta)
    c, dev = _start_centers(initial, ws, source, comps, kept, poles, beta, P)
    if not (np.all(np.isfinite(np.concatenate(P))) and np.isfinite(a) and np.isfinite(D)):
        return None
    if dev > MAX_DEVIATION:
        return None
    smooth = [
        None
        if src < 0 or not SMOOTH_START_GRIDS
        else _smooth_image(
            initial, comps, kept, src, d, poles, beta, MATCH_RTOL * ws.diameter, tail
        )
        for src, d in zip(source, shift, strict=True)
    ]
    return WarmStart(
        smooth=smooth,
        P=P,
        dP=dP,
        c=c,
        a=a,
        D=D,
        meshes=meshes,
        deviation=max(dev, 1.0) if -1 in source else dev,
        source=source,
    )


def _reused_meshes(
    initial: ConformalMap, ws: Workspace, tol: float, source: Any, shift: Any
) -> list[BoundaryMesh] | None:
    """The meshes of the warm level: each kept boundary's previous mesh moved with it (sides
    refined locally included), an added obstacle's planned anew; None where a previous mesh
    does not fit (sides split differently, a gap narrowed beyond what it resolves)."""
    d0 = initial.diagnostics
    ns = d0.nodes_per_side
    try:
        old_plans = plan_boundaries(initial.workspace, ns, d0.tol)
        new_plans = plan_boundaries(ws, ns, tol)
    except GapError:
        return None
    eta, deta, _, _ = initial._parts
    meshes: list[BoundaryMesh] = []
    for j, (src, d) in enumerate(zip(source, shift, strict=True)):
        if src < 0:
            meshes.append(_mesh(new_plans[j], j > 0))
            continue
        op, np_ = old_plans[src], new_plans[j]
        actual = _actual_plan(op, eta[src], src > 0)  # sides refined locally, if any
        if actual is None:
            return None  # the previous map's mesh is not on its plan's sides
        op = actual
        old_mesh = _mesh(op, src > 0)
        if op.vertices.shape != np_.vertices.shape or not np.allclose(
            op.vertices + d, np_.vertices, rtol=0, atol=MATCH_RTOL * ws.diameter
        ):
            return None  # sides split differently
        need = np_.nodes.copy()
        # the first side carries the plan's rounding of the total up to a multiple of
        # NODE_MULTIPLE (meshing.plan_boundaries), no requirement of the geometry
        need[0] = max(1, need[0] - (NODE_MULTIPLE - 1))
        if np.any(need > op.nodes):
            return None  # a gap narrowed: the previous mesh does not resolve it
        meshes.append(BoundaryMesh(eta[src] + d, deta[src].copy(), old_mesh.side, old_mesh.tau))
    return meshes


def _start_boundaries(
    initial: ConformalMap,
    ws: Workspace,
    source: Any,
    shift: Any,
    comps: Any,
    kept: dict[int, complex],
    meshes: list[BoundaryMesh],
) -> tuple[list[ComplexArray], list[ComplexArray], Any, Any] | None:
    """The start's boundary values and derivatives on ``meshes`` (previous values plus the
    moved Cauchy terms, an added obstacle the sum of the kept terms), less the rational
    corner correction, with the poles and weights of that correction; None where the
    correction's poles are too close to separate the corners' conditions."""
    eta, deta, W, dW = initial._parts
    groups: list[list[_Request]] = []
    for j, (src, d) in enumerate(zip(source, shift, strict=True)):
        if src < 0:  # an added obstacle: the sum of the kept terms
            z = meshes[j].eta
            groups.append([(i, z - di, 1.0) for i, di in kept.items()])
        else:
            groups.append(_requests(kept, len(comps), src, d, eta[src], MATCH_RTOL * ws.diameter))
    P: list[ComplexArray] = []
    dP: list[ComplexArray] = []
    for j, (src, (g, dg)) in enumerate(zip(source, _evaluate(comps, groups), strict=True)):
        if src < 0:
            P.append(g)
            dP.append(dg * meshes[j].deta)
        else:
            if g.size == 0:  # nothing moved relative to it
                g = dg = np.zeros(eta[src].size, np.complex128)
            P.append(W[src] + g)
            dP.append(dW[src] + dg * deta[src])
    try:
        poles, beta = _corner_correction(ws, source, shift, comps, kept)
    except np.linalg.LinAlgError:
        return None
    for j in range(len(P)):
        lz, dlz = _rational(poles, beta, meshes[j].eta)
        P[j] = P[j] - lz
        dP[j] = dP[j] - dlz * meshes[j].deta
        if source[j] >= 0:
            dP[j][_crowded_nodes(W[source[j]], dW[source[j]])] = 0.0
    return P, dP, poles, beta


def _anchor_start(
    ws: Workspace, comps: Any, kept: dict[int, complex], poles: Any, beta: Any
) -> tuple[complex, complex]:
    """The start's value and derivative at the anchor (the same sum as on the boundaries)."""
    anchor = np.array([ws.anchor])
    la, dla = _rational(poles, beta, anchor)
    a, D = -complex(la[0]), -complex(dla[0])
    for i, di in kept.items():
        t, dt = _term(comps[i], anchor - di)
        a += complex(t[0])
        D += complex(dt[0])
    return a, D


def _start_centers(
    initial: ConformalMap,
    ws: Workspace,
    source: Any,
    comps: Any,
    kept: dict[int, complex],
    poles: Any,
    beta: Any,
    P: list[ComplexArray],
) -> tuple[ComplexArray, float]:
    """The start's hole centres and its largest relative deviation from circles."""
    _, _, W, _ = initial._parts
    c = np.zeros(len(P) - 1, np.complex128)
    dev = 0.0
    for j, src in enumerate(source):
        if src < 0:
            if j > 0:
                pt = np.array([interior_point(ws.obstacles[j - 1])])
                c[j - 1] = sum(
                    complex(_term(comps[i], pt - di)[0][0]) for i, di in kept.items()
                ) - complex(_rational(poles, beta, pt)[0][0])
            continue
        # the previous circle moved by the mean displacement of its nodes (a moved obstacle's
        # image moves by about T' d): the start's hole lies around it
        cc = (0j if src == 0 else complex(initial.centers[src - 1])) + complex(
            np.mean(P[j] - W[src])
        )
        r = float(np.mean(np.abs(P[j] - cc)))
        if j > 0:
            c[j - 1] = cc
        dev = max(dev, float(np.max(np.abs(np.abs(P[j] - cc) - r))) / r)
    return c, dev


__all__ = ["MAX_DEVIATION", "WarmStart", "warm_state"]
