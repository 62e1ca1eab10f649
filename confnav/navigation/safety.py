"""Safety layer on exact geometry: a filter that keeps every command out of the walls.

The conformal map only *steers*; the guarantee that no robot touches a wall comes from this
filter, which uses the exact polygon distance of the workspace in use (the free space shrunk by
the robot's footprint when a radius is used, so the robot is a point in it; see
:mod:`confnav.maps.footprint`).  Every command ``u_nom`` the controller produces is replaced by

.. math::  u^* = \\arg\\min_u |u - u_{nom}|^2 \\quad \\text{s.t.}\\quad
           \\mathrm{Re}(\\bar a_j u) \\ge b_j \\ (j = 1..m), \\qquad |u| \\le \\mathrm{cap},

a quadratic program in two variables per robot (the safety filter of control barrier functions,
Ames et al. 2017 [1]_, 2019 [2]_).  docs/NAVIGATION.md ("Safety layer") gives the argument.

Two layers
----------
:func:`project` is the generic, vectorized core: ``n`` robots, ``m`` half-plane rows each
(padded: a row with bound ``-inf`` is absent) and a per-robot speed cap.  It knows nothing of
walls; callers append their own rows (robot-robot, moving disks) through ``extra_normals`` /
``extra_bounds``.  The solution is exact: in two dimensions the minimiser of a strictly convex
quadratic over an intersection of half-planes and a disk is either the unconstrained point, the
projection onto one constraint's boundary, or an intersection point of two constraint
boundaries (KKT: at most two independent active constraints in R^2).  All these candidates are
enumerated at once (array ops over robots x candidates; no loop over robots) and the nearest
feasible one is taken.  Robots whose nominal command is already feasible keep it *bitwise*.

:class:`SafetyFilter` builds the wall rows from exact geometry and calls :func:`project`.
With ``d_j`` the distance from ``x`` to boundary segment ``j`` (exact, as
:func:`confnav.geometry.distance_to_boundary`), ``p_j`` its closest point and
``n_j = (x - p_j) / d_j``, each nearby segment gives the control-barrier-function row

.. math::  n_j \\cdot u \\ge -\\alpha\\, \\max(d_j - \\mathrm{margin}, 0),

i.e. ``dd_j/dt >= -alpha h_j`` for the barrier ``h_j = d_j - margin``; the clearance
``h = min_j d_j`` is non-smooth on the medial axis, so there is one row per nearby segment
(a minimum of barrier functions: Glotfelter, Cortes, Egerstedt 2017 [3]_).  The speed cap is
the held-command bound of :mod:`confnav.navigation.control`:
``|u| <= hold_fraction * c(x) / hold_time`` with ``c`` the exact clearance.

Which rows are needed (exactly, not heuristically): a row ``j`` can only be violated if
``alpha d_j < |u|``, and ``|u| <= cap = kappa alpha c`` with ``kappa = hold_fraction /
(alpha hold_time)``, so only segments with ``d_j < kappa c`` matter; further ones are implied
by the cap.  Rows beyond the ``lookahead`` distance ``L`` (or beyond the ``max_rows`` nearest)
are dropped and the cap is lowered to ``alpha`` times the distance of the nearest dropped
segment, which implies them.  Candidate segments come from a uniform grid built once per
workspace (each cell lists every segment that can be relevant anywhere in the cell, and a lower
bound of the clearance over the cell, which lets robots far from every wall skip the filter).

References
----------
.. [1] A. D. Ames, X. Xu, J. W. Grizzle, P. Tabuada, "Control barrier function based quadratic
   programs for safety critical systems", IEEE Trans. Automatic Control 62(8) (2017)
   3861-3876.
.. [2] A. D. Ames, S. Coogan, M. Egerstedt, G. Notomista, K. Sreenath, P. Tabuada, "Control
   Barrier Functions: Theory and Applications", European Control Conference (2019) 3420-3431.
.. [3] P. Glotfelter, J. Cortes, M. Egerstedt, "Nonsmooth barrier functions with applications
   to multi-robot systems", IEEE Control Systems Letters 1(2) (2017) 310-315.
"""

from __future__ import annotations

import math
import threading
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from confnav.errors import NavigationError
from confnav.navigation import defaults
from confnav.types import CArray, FArray

if TYPE_CHECKING:
    from confnav.geometry import Workspace

__all__ = [
    "ALPHA",
    "FEAS_RTOL",
    "MARGIN",
    "MAX_ROWS",
    "Projection",
    "SafetyFilter",
    "project",
    "safety_filter",
]

#: Default CBF rate (1/s).  Must stay below ``HOLD_FRACTION / HOLD_TIME`` (2/s) or the rows
#: are implied by the speed cap (module docstring).
ALPHA = 1.5
#: Default lookahead (m): wall rows come from segments at most this far away.
LOOKAHEAD = 1.0
#: Default margin (m) the rows keep from the walls: the rows forbid any approach closer than
#: it, so integration error (a simulator's tolerance, a real robot's tracking) cannot eat up
#: the last exponentially small distance the continuous-time condition would allow.
MARGIN = 1e-3
#: Most wall rows per robot (the nearest ones; the cap implies the rest).
MAX_ROWS = 8
#: Relative tolerance of the feasibility test (a nominal command within it is kept as is).
FEAS_RTOL = 1e-12
#: Largest robots x candidates x rows block of one vectorized pass of :func:`project`.
_BLOCK = 1 << 21


@dataclass(frozen=True)
class Projection:
    """Result of :func:`project` / :class:`SafetyFilter` for ``n`` robots.

    u: the filtered commands (complex, shape of ``u_nom``); changed: True where ``u`` differs
    from ``u_nom`` (the filter acted); infeasible: True where no command meets every row and
    the cap (``u`` is then 0, or the robot is outside the free space).
    """

    u: CArray
    changed: NDArray[np.bool_]
    infeasible: NDArray[np.bool_]


def project(
    u_nom: ArrayLike,
    normals: ArrayLike,
    bounds: ArrayLike,
    cap: ArrayLike | None = None,
    *,
    extra_normals: ArrayLike | None = None,
    extra_bounds: ArrayLike | None = None,
    rtol: float = FEAS_RTOL,
) -> Projection:
    """Per-robot projection of commands onto half-planes and a speed disk (vectorized, exact).

    For every robot ``i`` solves ``min |u - u_nom[i]|^2`` subject to
    ``Re(conj(a_ij) u) >= b_ij`` for every row ``j`` and ``|u| <= cap[i]``.

    Parameters (stable API: the fleet layer appends its rows through ``extra_*``)
    ----------
    u_nom : complex (n,)  nominal commands.
    normals : complex (n, m)  row normals ``a_ij`` (any length; normalised here).  ``m`` may
        be 0.
    bounds : float (n, m)  row bounds ``b_ij``.  Padding: ``b_ij = -inf`` (row absent).
    cap : float (n,) or scalar, optional  speed limits (``inf``/None: none).
    extra_normals, extra_bounds : complex (n, k), float (n, k), optional  further rows
        appended to ``normals``/``bounds`` (same conventions), e.g. robot-robot or moving-disk
        barrier rows.
    rtol : a nominal command that violates a row by at most ``rtol * scale`` (scale: the
        largest of ``|u_nom|`` and the finite normalised bounds) or the cap by ``rtol * cap``
        counts as feasible and is returned unchanged (bitwise).

    Returns
    -------
    :class:`Projection`.  ``infeasible[i]``: the rows and the cap have no common point (or a
    row is NaN); then ``u[i] = 0``, the safest command for static constraints with
    ``b <= 0``, which the caller may replace.  A NaN ``u_nom[i]`` is returned unchanged
    (NaN, not flagged).

    Method: the minimiser is ``u_nom``, a projection onto one constraint boundary (a line or
    the circle) or an intersection of two boundaries (line-line, line-circle); every such
    candidate is formed for the robots whose ``u_nom`` is infeasible, and the nearest
    feasible candidate is taken (module docstring).  Cost: ``O(m^2)`` candidates times ``m``
    rows per filtered robot.
    """
    u = np.asarray(u_nom, dtype=np.complex128)
    shape = u.shape
    u = u.reshape(-1)
    n = u.size
    a = np.asarray(normals, dtype=np.complex128).reshape(n, -1)
    b = np.asarray(bounds, dtype=np.float64).reshape(n, -1)
    if extra_normals is not None or extra_bounds is not None:
        if extra_normals is None or extra_bounds is None:
            raise NavigationError("extra_normals and extra_bounds go together")
        a = np.concatenate([a, np.asarray(extra_normals, np.complex128).reshape(n, -1)], axis=1)
        b = np.concatenate([b, np.asarray(extra_bounds, np.float64).reshape(n, -1)], axis=1)
    if a.shape != b.shape:
        raise NavigationError(f"normals {a.shape} and bounds {b.shape} differ in shape")
    c = np.full(n, np.inf) if cap is None else np.broadcast_to(np.asarray(cap, np.float64), (n,))
    a, b, bad = _normalised(a, b)
    live = np.isfinite(b).any(axis=0)
    if not live.all():  # columns that are padding for every robot cost nothing
        a, b = a[:, live], b[:, live]
    bad |= np.isnan(c)
    speed = np.abs(u)
    finite_b = np.where(np.isfinite(b), np.abs(b), 0.0)
    scale = np.maximum(speed, finite_b.max(axis=1, initial=0.0))
    slack = (np.conj(a) * u[:, None]).real - b
    ok = (slack >= -rtol * scale[:, None]).all(axis=1) & (speed <= c * (1.0 + rtol)) & ~bad
    keep = ok | np.isnan(u)
    out = u.copy()
    changed = np.zeros(n, dtype=bool)
    infeasible = bad & ~np.isnan(u)
    todo = np.flatnonzero(~keep & ~bad)
    out[bad & ~np.isnan(u)] = 0j
    changed[bad & ~np.isnan(u)] = True
    if todo.size:
        # each robot's live rows first; robots grouped by their number of live rows (the
        # candidates grow as m^2: most robots near a wall have one or two)
        pad = ~np.isfinite(b[todo])
        order = np.argsort(pad, axis=1, kind="stable")
        at = np.take_along_axis(a[todo], order, axis=1)
        bt = np.take_along_axis(b[todo], order, axis=1)
        count = (~pad).sum(axis=1)
        for m in np.unique(count).tolist():  # at most m + 1 groups
            grp = np.flatnonzero(count == m)
            n_cand = 1 + 3 * m + m * (m - 1) // 2
            step = max(1, _BLOCK // max(1, n_cand * max(m, 1)))
            for s in range(0, grp.size, step):  # blocks bound the memory
                g = grp[s : s + step]
                idx = todo[g]
                best, found = _nearest_feasible(u[idx], at[g, :m], bt[g, :m], c[idx], rtol)
                out[idx] = np.where(found, best, 0j)
                infeasible[idx] = ~found
        changed[todo] = out[todo] != u[todo]
    return Projection(
        u=out.reshape(shape), changed=changed.reshape(shape), infeasible=infeasible.reshape(shape)
    )


def _normalised(a: CArray, b: FArray) -> tuple[CArray, FArray, NDArray[np.bool_]]:
    """Unit normals and scaled bounds; padding rows become ``(0, -inf)``; ``bad`` marks robots
    with a NaN row or an impossible zero row (``0 >= b > 0``)."""
    size = np.abs(a)
    nan_row = np.isnan(b) | np.isnan(size)
    pad = (b == -np.inf) | ((size == 0) & (b <= 0))
    impossible = (size == 0) & (b > 0)
    live = ~pad & ~nan_row & ~impossible
    with np.errstate(invalid="ignore", divide="ignore"):
        an = np.where(live, a / np.where(live, size, 1.0), 0j)
        bn = np.where(live, b / np.where(live, size, 1.0), -np.inf)
    bad = (nan_row & ~pad).any(axis=1) | impossible.any(axis=1)
    return an, bn, bad


def _nearest_feasible(
    u: CArray, a: CArray, b: FArray, cap: FArray, rtol: float
) -> tuple[CArray, NDArray[np.bool_]]:
    """The exact minimiser for robots whose ``u`` is infeasible: every KKT candidate, then the
    nearest feasible one.  Returns (u*, found)."""
    k, m = a.shape
    finite_cap = np.isfinite(cap)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        sp = np.abs(u)
        disk = np.where(
            finite_cap, np.where(sp > 0, u * (cap / np.where(sp > 0, sp, 1.0)), 0j), np.nan
        )
        cands = [disk[:, None]]
        if m:
            # projection of u onto each row's line
            au = (np.conj(a) * u[:, None]).real
            cands.append(u[:, None] + (b - au) * a)
            # line-line intersections: Re(conj(a_j) p) = b_j, Re(conj(a_k) p) = b_k
            if m > 1:
                j, k2 = np.triu_indices(m, 1)
                aj, al, bj, bl = a[:, j], a[:, k2], b[:, j], b[:, k2]
                det = (np.conj(aj) * al).imag
                p = 1j * (bl * aj - bj * al) / det
                cands.append(np.where(np.abs(det) > 1e-12, p, np.nan))
            # line-circle intersections: p = b a +- i a sqrt(cap^2 - b^2)
            disc = cap[:, None] ** 2 - b**2
            root = np.sqrt(np.where(disc >= 0, disc, np.nan))
            root = np.where(finite_cap[:, None], root, np.nan)
            cands.append(b * a + 1j * a * root)
            cands.append(b * a - 1j * a * root)
        p = np.concatenate(cands, axis=1)  # (k, C)
        valid = np.isfinite(p)
        p = np.where(valid, p, 0j)
        finite_b = np.where(np.isfinite(b), np.abs(b), 0.0)
        scale = np.maximum(
            np.maximum(np.abs(p), sp[:, None]), finite_b.max(axis=1, initial=0.0)[:, None]
        )
        feas = valid & (np.abs(p) <= np.where(finite_cap, cap, np.inf)[:, None] * (1 + rtol))
        if m:
            slack = (np.conj(a)[:, None, :] * p[:, :, None]).real - b[:, None, :]
            feas &= (slack >= -rtol * scale[:, :, None]).all(axis=2)
        dist = np.where(feas, np.abs(p - u[:, None]), np.inf)
    best = np.argmin(dist, axis=1)
    rows = np.arange(k)
    found = np.isfinite(dist[rows, best])
    return p[rows, best], found


# --------------------------------------------------------------------------- wall rows


@dataclass(frozen=True)
class WallRows:
    """Wall constraints of a batch: ``normals``/``bounds`` (n, m) for :func:`project` (padding
    ``-inf``), the exact signed ``clearance`` (n,), the ``distance`` (n, m) of each row's
    segment (inf for padding) and the speed ``cap`` (n,) (held-command bound, lowered where
    rows were dropped)."""

    normals: CArray
    bounds: FArray
    distance: FArray
    clearance: FArray
    cap: FArray


class SafetyFilter:
    """The wall filter of one workspace (the workspace in use; module docstring).

    Parameters
    ----------
    workspace : the free space the robot's reference point must stay in (shrunk by the
        footprint when the robot has a radius).
    alpha : CBF rate (1/s): ``n_j . u >= -alpha (d_j - margin)``; 0 forbids any approach.
    hold_time : s a command may be held (the simulator's ``max_cmd_age``): the speed cap
        ``hold_fraction * c / hold_time`` (0: no cap; then the continuous-time guarantee only).
    hold_fraction : share of the clearance a held command may use (< 1).
    lookahead : m; segments further away give no row (the cap is lowered to imply them).
    margin : m kept from the walls by the rows (within it the robot may not approach).
    max_rows : most rows per robot.
    """

    def __init__(
        self,
        workspace: Workspace,
        *,
        alpha: float = ALPHA,
        hold_time: float = defaults.HOLD_TIME,
        hold_fraction: float = defaults.HOLD_FRACTION,
        lookahead: float = LOOKAHEAD,
        margin: float = MARGIN,
        max_rows: int = MAX_ROWS,
    ) -> None:
        for name, v in (
            ("alpha", alpha),
            ("hold_time", hold_time),
            ("lookahead", lookahead),
            ("margin", margin),
        ):
            if not (float(v) >= 0 and math.isfinite(v)):
                raise NavigationError(f"safety filter: {name} must be >= 0 and finite, got {v!r}")
        if not 0 < hold_fraction < 1:
            raise NavigationError(f"hold_fraction must be in (0, 1), got {hold_fraction!r}")
        if not (lookahead > 0 and int(max_rows) >= 1):
            raise NavigationError("safety filter: lookahead > 0 and max_rows >= 1 needed")
        self.workspace = workspace
        self.alpha = float(alpha)
        self.hold_time = float(hold_time)
        self.hold_fraction = float(hold_fraction)
        self.lookahead = float(lookahead)
        self.margin = float(margin)
        self.max_rows = int(max_rows)
        #: cap slope: cap = slope * c (inf without a hold time)
        self.slope = self.hold_fraction / self.hold_time if self.hold_time > 0 else math.inf
        #: rows matter only within kappa * c (module docstring)
        self.kappa = self.slope / self.alpha if self.alpha > 0 else math.inf
        self._grid: _Grid | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ grid
    @property
    def grid(self) -> _Grid:
        g = self._grid
        if g is None:
            with self._lock:
                if self._grid is None:
                    self._grid = _Grid.build(self)
                g = self._grid
        return g

    def free_speed(self, z: ArrayLike) -> FArray:
        """A speed below which every command is feasible for the wall rows and the cap at
        ``z`` (from the grid's clearance lower bound; 0 near walls)."""
        g = self.grid
        return g.free_speed[g.cell(np.asarray(z, dtype=np.complex128))]

    def rows(self, z: ArrayLike) -> WallRows:
        """Wall rows, exact clearance and speed cap at the points ``z`` (complex, (n,))."""
        zz = np.asarray(z, dtype=np.complex128).reshape(-1)
        g = self.grid
        cell = g.cell(zz)
        seg = g.candidates[cell]  # (n, K) segment indices, -1 = none
        has = seg >= 0
        si = np.where(has, seg, 0)
        a, d, dd = g.a[si], g.d[si], g.dd[si]
        with np.errstate(invalid="ignore"):
            t = np.minimum(np.maximum(((zz[:, None] - a) * np.conj(d)).real / dd, 0.0), 1.0)
        p = a + t * d
        diff = zz[:, None] - p
        dist = np.where(has, np.abs(diff), np.inf)
        c_abs = dist.min(axis=1, initial=np.inf)
        inside = g.inside(zz, cell)
        clearance = np.where(inside, c_abs, -c_abs)
        # a vertex that is the closest point of a side's end and of the next side's start
        # gives one row (the next side's)
        nx = g.next[si]
        with np.errstate(invalid="ignore"):
            t_next = ((zz[:, None] - g.a[nx]) * np.conj(g.d[nx])).real / g.dd[nx]
        dup = (t >= 1.0) & (t_next <= 0.0)
        dist_row = np.where(has & ~dup, dist, np.inf)
        reach = np.minimum(_times(self.kappa, c_abs), self.lookahead)  # further rows: implied
        dist_row = np.where(dist_row <= reach[:, None], dist_row, np.inf)
        cap = np.full(zz.size, np.inf)
        if self.hold_time > 0:
            cap = self.slope * np.maximum(clearance, 0.0)
        trunc = _times(self.kappa, c_abs) > self.lookahead  # rows beyond the lookahead dropped
        # the nearest rows first, as many columns as the robot with the most rows needs
        order = np.argsort(dist_row, axis=1, kind="stable")
        width = int(np.isfinite(dist_row).sum(axis=1).max(initial=0))
        if width > self.max_rows:
            dropped = np.take_along_axis(
                dist_row, order[:, self.max_rows : self.max_rows + 1], axis=1
            )[:, 0]
            cap = np.minimum(cap, np.where(np.isfinite(dropped), self.alpha * dropped, np.inf))
        order = order[:, : min(width, self.max_rows)]
        dist_row = np.take_along_axis(dist_row, order, axis=1)
        diff = np.take_along_axis(diff, order, axis=1)
        cap = np.where(trunc, np.minimum(cap, self.alpha * self.lookahead), cap)
        live = np.isfinite(dist_row)
        with np.errstate(invalid="ignore", divide="ignore"):
            normals = np.where(live & (dist_row > 0), diff / np.where(live, dist_row, 1.0), 0j)
        h = np.maximum(dist_row - self.margin, 0.0)
        bounds = np.where(live, -self.alpha * h, -np.inf)
        return WallRows(
            normals=normals, bounds=bounds, distance=dist_row, clearance=clearance, cap=cap
        )

    # ------------------------------------------------------------------ filter
    def __call__(
        self,
        z: ArrayLike,
        u_nom: ArrayLike,
        *,
        cap: ArrayLike | None = None,
        extra_normals: ArrayLike | None = None,
        extra_bounds: ArrayLike | None = None,
    ) -> Projection:
        """Filter the commands ``u_nom`` of robots at ``z`` (complex arrays of one shape).

        ``cap``: a further per-robot speed limit (e.g. the robot's own).  ``extra_*``:
        further rows (n, k) as in :func:`project` (robot-robot, moving disks).  A robot
        outside the free space (clearance <= 0) gets ``u = 0`` and ``infeasible``; a NaN
        command or pose stays NaN.  Robots whose command is feasible keep it bitwise; robots
        far from every wall (``|u| <=`` :meth:`free_speed`) with no extra rows skip the rows.
        """
        zz = np.asarray(z, dtype=np.complex128)
        shape = zz.shape
        zz = zz.reshape(-1)
        u = np.asarray(u_nom, dtype=np.complex128).reshape(-1)
        if u.shape != zz.shape:
            raise NavigationError(f"poses {shape} and commands {np.shape(u_nom)} differ in shape")
        n = zz.size
        extra = extra_normals is not None or extra_bounds is not None
        ecap = None if cap is None else np.broadcast_to(np.asarray(cap, np.float64), (n,))
        fine = np.isfinite(zz) & np.isfinite(u)
        free = fine & (np.abs(u) <= self.free_speed(np.where(fine, zz, 0j)))
        if ecap is not None:
            free &= np.abs(u) <= ecap
        if extra:
            en = np.asarray(extra_normals, np.complex128).reshape(n, -1)
            eb = np.asarray(extra_bounds, np.float64).reshape(n, -1)
            free &= (eb == -np.inf).all(axis=1)
        todo = np.flatnonzero(fine & ~free)
        out = u.copy()
        changed = np.zeros(n, dtype=bool)
        infeasible = np.zeros(n, dtype=bool)
        if todo.size:
            r = self.rows(zz[todo])
            c = r.cap if ecap is None else np.minimum(r.cap, ecap[todo])
            pr = project(
                u[todo],
                r.normals,
                r.bounds,
                c,
                extra_normals=en[todo] if extra else None,
                extra_bounds=eb[todo] if extra else None,
            )
            outside = ~(r.clearance > 0)
            out[todo] = np.where(outside, 0j, pr.u)
            changed[todo] = pr.changed | (outside & (u[todo] != 0))
            infeasible[todo] = pr.infeasible | outside
        return Projection(
            u=out.reshape(shape),
            changed=changed.reshape(shape),
            infeasible=infeasible.reshape(shape),
        )

    def filter1(self, z: complex, u: complex) -> tuple[complex, bool, bool]:
        """:meth:`__call__` of one robot: ``(u, changed, infeasible)``.

        Far from the walls a Python-scalar test; near them a sufficient test of ``u`` against
        every candidate side of the robot's cell (:meth:`_feasible1`); only a command that
        fails it goes through the batch code on one robot, so the result is the batch's
        bitwise whenever the command is kept, and the batch's own result otherwise."""
        if not (
            math.isfinite(z.real)
            and math.isfinite(z.imag)
            and math.isfinite(u.real)
            and math.isfinite(u.imag)
        ):
            return u, False, False
        g = self.grid
        cell = g.cell1(z)
        if abs(u) <= g.free_speed[cell] or self._feasible1(z, u, cell):
            return u, False, False
        pr = self(np.array([z]), np.array([u]))
        return complex(pr.u[0]), bool(pr.changed[0]), bool(pr.infeasible[0])

    def _feasible1(self, z: complex, u: complex, cell: int) -> bool:
        """Whether ``u`` certainly meets the rows and the cap of :meth:`rows` at ``z``: inside
        the free space, ``|u|`` within the cap (and within ``alpha * lookahead`` where rows
        were cut off there), no more rows than ``max_rows``, and every candidate side of the
        cell within reach met exactly (duplicate vertex rows are the same row).  A sufficient
        test: :func:`project` keeps such a ``u`` unchanged (its tolerance only widens it)."""
        g = self.grid
        seg = g.candidates[cell]
        seg = seg[seg >= 0]
        if seg.size == 0:
            return False
        a, d = g.a[seg], g.d[seg]
        t = np.minimum(np.maximum(((z - a) * np.conj(d)).real / g.dd[seg], 0.0), 1.0)
        diff = z - (a + t * d)
        dist = np.abs(diff)
        c = float(dist.min())
        side = int(g.side[cell])
        inside = side == 1 or (side == 0 and bool(g.inside(np.array([z]), np.array([cell]))[0]))
        if not (inside and c > 0):
            return False
        speed = abs(u)
        if self.hold_time > 0 and not speed <= self.slope * c:
            return False
        reach = min(self.kappa * c, self.lookahead)
        if self.kappa * c > self.lookahead and not speed <= self.alpha * self.lookahead:
            return False
        near = dist <= reach
        if int(near.sum()) > self.max_rows:
            return False
        dn, diffn = dist[near], diff[near]
        pos = dn > 0
        slack = (np.conj(diffn[pos]) * u).real / dn[pos] + self.alpha * np.maximum(
            dn[pos] - self.margin, 0.0
        )
        return bool(np.all(slack >= 0.0))


def _times(k: float, x: FArray) -> FArray:
    """``k * x`` for ``x >= 0`` with ``inf * 0 = 0`` (``k`` may be inf)."""
    return np.where(x > 0, k * np.where(x > 0, x, 1.0), 0.0)


class _Grid:
    """Uniform grid over the workspace: per cell the candidate segments (every segment that
    can give a row or be nearest anywhere in the cell), the cell's clearance lower bound and
    whether the whole cell is inside the free space."""

    def __init__(self, **kw: object) -> None:
        self.__dict__.update(kw)

    x0: float
    y0: float
    h: float
    nx: int
    ny: int
    candidates: NDArray[np.intp]
    free_speed: FArray
    side: NDArray[np.int8]  # 1 inside, -1 outside, 0 near the boundary (test per point)
    a: CArray
    d: CArray
    dd: FArray
    next: NDArray[np.intp]  # the side that starts where side k ends (same ring)
    polygon: object

    @staticmethod
    def build(flt: SafetyFilter, max_cells: int = 128) -> _Grid:
        ws = flt.workspace
        a, bnd = ws._segments  # type: ignore[attr-defined]
        d = bnd - a
        x0, y0, x1, y1 = ws.bounds
        size = max(x1 - x0, y1 - y0)
        h = size / max_cells
        nx = max(1, math.ceil((x1 - x0) / h))
        ny = max(1, math.ceil((y1 - y0) / h))
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        q = (x0 + (ix.ravel() + 0.5) * h) + 1j * (y0 + (iy.ravel() + 0.5) * h)
        r = h * math.sqrt(0.5)  # half diagonal
        # the exact distance of every cell centre to every segment, once, in blocks that
        # bound the memory (cells x segments), in real arithmetic: the centre's clearance
        # ``dq`` (its minimum) and the candidate segments (those within ``reach``)
        ax, ay, dx, dy = a.real, a.imag, d.real, d.imag
        dd = dx * dx + dy * dy
        inv = np.divide(1.0, dd, out=np.zeros_like(dd), where=dd > 0)
        dq = np.empty(q.size)
        hits_i: list[NDArray[np.intp]] = []
        hits_j: list[NDArray[np.intp]] = []
        step = max(1, (1 << 21) // max(1, a.size))
        for s in range(0, q.size, step):
            qx, qy = q.real[s : s + step, None] - ax, q.imag[s : s + step, None] - ay
            t = np.clip((qx * dx + qy * dy) * inv, 0.0, 1.0)
            ex, ey = qx - t * dx, qy - t * dy
            dist = np.sqrt(ex * ex + ey * ey)
            dqs = dist.min(axis=1)
            dq[s : s + step] = dqs
            reach = np.minimum(flt.kappa * (dqs + r), flt.lookahead) + r
            reach = np.maximum(reach, dqs + 2 * r)  # the nearest segment of every point
            i, j = np.nonzero(dist <= reach[:, None])
            hits_i.append(i + s)
            hits_j.append(j)
        ci, cj = np.concatenate(hits_i), np.concatenate(hits_j)  # row-major: by cell, segment
        count = np.bincount(ci, minlength=q.size)
        width = max(1, int(count.max(initial=0)))
        cand = np.full((q.size, width), -1, dtype=np.intp)
        first = np.concatenate([[0], np.cumsum(count)[:-1]])
        cand[ci, np.arange(ci.size) - first[ci]] = cj
        low = np.maximum(dq - r, 0.0)
        inside = np.asarray(ws.contains(q), dtype=bool)
        side = np.where(dq > r, np.where(inside, 1, -1), 0).astype(np.int8)
        speed = np.minimum(flt.alpha * np.minimum(low, flt.lookahead), _times(flt.slope, low))
        speed = np.where(side == 1, speed, 0.0)
        sizes = [len(ring) for ring in ws.boundaries]
        starts = np.cumsum([0, *sizes[:-1]])
        nxt = np.concatenate(
            [s + (np.arange(k) + 1) % k for s, k in zip(starts, sizes, strict=True)]
        )
        return _Grid(
            x0=x0,
            y0=y0,
            h=h,
            nx=nx,
            ny=ny,
            candidates=cand,
            free_speed=speed,
            side=side,
            a=a,
            d=d,
            dd=np.abs(d) ** 2,
            next=nxt,
            polygon=ws.polygon,
        )

    def cell(self, z: CArray) -> NDArray[np.intp]:
        with np.errstate(invalid="ignore"):
            ix = np.clip(np.floor((z.real - self.x0) / self.h), 0, self.nx - 1)
            iy = np.clip(np.floor((z.imag - self.y0) / self.h), 0, self.ny - 1)
        ix = np.where(np.isfinite(ix), ix, 0).astype(np.intp)
        iy = np.where(np.isfinite(iy), iy, 0).astype(np.intp)
        return np.asarray(ix * self.ny + iy)

    def cell1(self, z: complex) -> int:
        ix = min(max(math.floor((z.real - self.x0) / self.h), 0), self.nx - 1)
        iy = min(max(math.floor((z.imag - self.y0) / self.h), 0), self.ny - 1)
        return int(ix * self.ny + iy)

    def inside(self, z: CArray, cell: NDArray[np.intp]) -> NDArray[np.bool_]:
        import shapely

        side = self.side[cell]
        out = side == 1
        near = np.flatnonzero(side == 0)
        if near.size:
            zz = z[near]
            out[near] = shapely.contains_xy(self.polygon, zz.real, zz.imag)
        return np.asarray(out, dtype=bool)


_Key = tuple[int, tuple[tuple[str, float], ...]]
_FILTERS: dict[_Key, tuple[weakref.ref[Workspace], SafetyFilter]] = {}
_FILTERS_LOCK = threading.Lock()


def safety_filter(workspace: Workspace, **params: float) -> SafetyFilter:
    """The :class:`SafetyFilter` of ``workspace`` with ``params``, shared by every controller
    of that workspace object (its grid is built once)."""
    key: _Key = (id(workspace), tuple(sorted((k, float(v)) for k, v in params.items())))
    with _FILTERS_LOCK:
        hit = _FILTERS.get(key)
        if hit is not None and hit[0]() is workspace:
            return hit[1]
        flt = SafetyFilter(workspace, **params)  # type: ignore[arg-type]

        def forget(
            _ref: weakref.ref[Workspace], k: _Key = key, filters: dict[_Key, Any] = _FILTERS
        ) -> None:  # the dict bound here: at interpreter exit the module global is None
            filters.pop(k, None)

        _FILTERS[key] = (weakref.ref(workspace, forget), flt)
        return flt
