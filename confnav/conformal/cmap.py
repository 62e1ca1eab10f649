"""The solved conformal navigation transformation: T, T', T^-1 and lossless serialisation.

The map is stored as its boundary correspondence: for every boundary node ``eta_k`` (outer
counter-clockwise, holes clockwise, on the graded mesh) its image ``W_k = T(eta_k)`` and the
t-derivatives ``eta'_k`` and ``W'_k = T'(eta_k) eta'_k``. Evaluation is the barycentric Cauchy
formula over all boundary components (weights ``2pi/n_j``), accurate up to the boundary:

    T(z)   = N/D,  N = sum w W eta'/(eta - z),  D = sum w eta'/(eta - z),
    T'(z)  = (N'D - N D')/D^2  (the derivative of the barycentric formula),
    T^-1(w) = sum w eta W'/(W - w)  / sum w W'/(W - w)        (roles of eta and W swapped).

References
----------
.. [1] docs/METHOD.md sec. 2, "Cauchy evaluation in barycentric form".
.. [2] A. P. Austin, P. Kravanja, L. N. Trefethen, "Numerical algorithms based on analytic
   function values at roots of unity", SIAM J. Numer. Anal. 52 (2014) 1795-1821, sec. 4.
"""

from __future__ import annotations

import base64
import cmath
import hashlib
import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from confnav.conformal.cauchy import FMM_THRESHOLD, cauchy_sums, cauchy_sums2
from confnav.conformal.expansion import LocalExpansions
from confnav.errors import MapMismatchError, SerializationError
from confnav.geometry import Workspace, distance_to_boundary
from confnav.types import CArray as ComplexArray
from confnav.types import FArray as FloatArray

FORMAT = "confnav.map"
#: Points this close to the boundary (relative to the workspace size) count as on it.
BOUNDARY_RTOL = 1e-12
#: Version 2 added ``workspace_hash`` and the full error budget of the diagnostics (iteration
#: error, boundary residual). Version 1 maps are refused: their error estimate could not see an
#: iteration stopped early (issue 8), so loading them would pass on an unverified accuracy.
FORMAT_VERSION = 2
#: Where the boundary residual is checked besides the midpoints between nodes: fractions of
#: every side, graded geometrically towards both of its corners (and the side's midpoint).
CORNER_FRACTIONS = (0.5, 0.1, 1e-2, 1e-3, 1e-4)
#: The residual is certified down to this distance from every corner, relative to the shorter
#: side at the corner (1e-4: 50 um on a 0.5 m side). Closer to a corner of an obstacle (a
#: re-entrant corner of the free space) the node images carry rounding of ~1e-9 and T was
#: measured 2e-9 (at 1e-6) to 1e-6 (at 1e-11) off its circle on the seed's workspace -- far
#: inside any robot's clearance, but not within a tight tol, so it is not claimed.
CORNER_ZONE = 1e-4
#: Batches at least this large build the local expansions (confnav/conformal/expansion.py) of any
#: map.
EXPANSION_MIN_POINTS = 20_000
#: Up to this many boundary nodes a single point is evaluated directly (as fast, measured).
EXPANSION_SINGLE_NODES = 2_000


@dataclass
class SolveReport:
    """How the map was obtained and how accurate it is believed to be.

    ``error_estimate`` is the largest of every error source, each measured independently:

    * ``discretisation_error``: extrapolated change of the centres and radii between mesh
      levels (:mod:`confnav.conformal.solver`);
    * ``iteration_error``: the Koebe iteration's remaining error, extrapolated from its
      observed contraction (``iteration_converged`` is False if it stalled or hit its limit);
    * ``boundary_residual``: the largest distance of T(z) from its circle over points *between*
      the nodes on every side (midpoints and points graded towards every corner), an
      a-posteriori check of the map actually returned (:meth:`ConformalMap.boundary_residual`);
    * ``resolution_error``: the Fourier tail of any smooth grid solved on above its target
      (held at its size cap, or laid too small in an early sweep).

    ``tol_met`` is true only if all of them are within ``tol`` and no size cap was hit
    (``caps`` lists any that were).
    """

    tol: float
    error_estimate: float
    tol_met: bool
    sweeps: int
    history: list[float]
    nodes: list[int]
    nodes_per_side: int
    circularity: float
    gmres_iterations: int
    wall_time: float
    discretisation_error: float
    iteration_error: float
    iteration_converged: bool
    boundary_residual: float
    resolution_error: float
    caps: list[str] = field(default_factory=list)
    refinements: list[dict[str, float]] = field(default_factory=list)
    #: Largest GMRES residual left by any GNK solve of the final level (absolute 2-norm of
    #: ``(I - N) mu + M gamma``; a run stopped at its iteration limit is accepted up to
    #: ``GMRES_ACCEPT`` times its target, and that residual is what is counted here). The GNK
    #: operator has a bounded inverse (Wegmann & Nasser 2008, Thm. 5), so the error it leaves in
    #: mu is of this order: it is part of ``error_estimate``.
    gmres_residual: float = 0.0
    #: Truncation bound of the local expansions this map evaluates through, once built
    #: (:meth:`confnav.conformal.expansion.LocalExpansions.error_bound` / pi, T and T'); part
    #: of ``error_estimate`` (0 while the map evaluates by the direct sums only).
    evaluation_error: float = 0.0
    #: Reasons why the estimate cannot be trusted for ``tol_met`` although its figure may be
    #: small: a discretisation estimate from two mesh levels on an assumed order, level
    #: differences that stopped shrinking. Any entry makes ``tol_met`` False.
    unverified: list[str] = field(default_factory=list)
    #: Smallest circle radius of the circle domain (1 with no obstacles).
    min_radius: float = 1.0
    #: Conformal crowding of each boundary (outer first): -log10 of the share of the image
    #: circle's circumference per unit of the boundary's length (circumference / (2 pi r) over
    #: arc-length share); 0 when the boundary maps uniformly, k when it is compressed 10^k
    #: times below average (:func:`confnav.conformal.solver.crowding`).
    crowding: list[float] = field(default_factory=list)

    def _budget(self, *extra: float) -> tuple[float, bool]:
        """(error_estimate, tol_met) from every error source (see the class docstring)."""
        est = max(
            self.discretisation_error,
            self.iteration_error,
            self.boundary_residual,
            self.resolution_error,
            self.gmres_residual,
            self.evaluation_error,
            *extra,
        )
        return est, self._meets(est, self.tol)

    def _meets(self, est: float, level: float) -> bool:
        return bool(
            est <= level and self.iteration_converged and not self.caps and not self.unverified
        )

    def meets(self, level: float) -> bool:
        """``tol_met``'s criterion at another tolerance ``level``: the estimate of every
        source within ``level``, the iteration converged and no size cap hit. (An atlas keeps a
        chart that misses its ``tol`` only if it meets the accuracy the controller evaluates
        to in this sense, never on the error estimate alone.)"""
        return self._meets(self.error_estimate, level)

    def with_residual(self, residual: float) -> SolveReport:
        """These diagnostics for the same solution evaluated from other nodes (its residual)."""
        d = replace(self, boundary_residual=residual)
        d.error_estimate, d.tol_met = d._budget()
        return d

    def with_evaluation(self, bound: float) -> SolveReport:
        """These diagnostics with the truncation bound of the local expansions folded in."""
        d = replace(self, evaluation_error=max(self.evaluation_error, bound))
        est, d.tol_met = d._budget()
        d.error_estimate = max(est, self.error_estimate)
        d.tol_met = d._meets(d.error_estimate, d.tol)
        return d

    def with_deviation(self, deviation: float) -> SolveReport:
        """Fold a measured deviation from the full map (coarsened evaluation) into the budget."""
        d = replace(self)
        d.error_estimate, d.tol_met = d._budget(self.error_estimate, deviation)
        return d

    def table(self) -> str:
        rows = [
            ("requested tolerance", f"{self.tol:.1e}"),
            ("estimated error (all sources)", f"{self.error_estimate:.1e}"),
            ("tolerance met", "yes" if self.tol_met else "NO"),
            ("  discretisation (mesh levels)", f"{self.discretisation_error:.1e}"),
            (
                "  Koebe iteration (extrapolated)",
                f"{self.iteration_error:.1e}"
                + ("" if self.iteration_converged else "  NOT CONVERGED (stalled or sweep limit)"),
            ),
            ("  boundary residual (between nodes)", f"{self.boundary_residual:.1e}"),
            ("  smooth-grid resolution", f"{self.resolution_error:.1e}"),
            ("  GMRES residual (largest, absolute)", f"{self.gmres_residual:.1e}"),
            ("  local expansions (truncation bound)", f"{self.evaluation_error:.1e}"),
            ("size caps hit", "; ".join(self.caps) if self.caps else "none"),
            ("estimate not verified", "; ".join(self.unverified) if self.unverified else "no"),
            (
                "not covered",
                f"boundary residual not checked within {CORNER_ZONE:.0e} of the shorter side of "
                "each corner (node images there carry ~1e-9 rounding)",
            ),
            ("smallest circle radius", f"{self.min_radius:.2e}"),
            (
                "crowding per boundary (log10, outer first)",
                ", ".join(f"{c:.1f}" for c in self.crowding) if self.crowding else "-",
            ),
            ("Koebe sweeps (final solve)", str(self.sweeps)),
            ("last sweep change", f"{self.history[-1]:.1e}" if self.history else "-"),
            ("boundary circularity residual", f"{self.circularity:.1e}"),
            ("nodes per side", str(self.nodes_per_side)),
            ("nodes per boundary", ", ".join(str(n) for n in self.nodes)),
            ("GMRES iterations (total)", str(self.gmres_iterations)),
            ("wall time", f"{self.wall_time:.2f} s"),
        ]
        w = max(len(r[0]) for r in rows)
        return "\n".join(f"{a:<{w}}  {b}" for a, b in rows)


def _pack(z: np.ndarray) -> dict[str, str]:
    arr = np.ascontiguousarray(z)
    dtype = "<c16" if arr.dtype.kind == "c" else "<f8"
    return {"dtype": dtype, "data": base64.b64encode(arr.astype(dtype).tobytes()).decode()}


def _unpack(d: Any, name: str) -> np.ndarray:
    try:
        dtype = np.dtype(d["dtype"])
        if dtype.str not in ("<c16", "<f8"):
            raise ValueError(f"unsupported dtype {dtype}")
        arr = np.frombuffer(base64.b64decode(d["data"], validate=True), dtype=dtype)
    except (KeyError, TypeError, ValueError) as exc:
        raise SerializationError(f"map field {name!r} is not a packed array: {exc}") from exc
    if not np.all(np.isfinite(arr)):
        raise SerializationError(f"map field {name!r} contains NaN or inf")
    return arr.astype(np.complex128 if dtype.kind == "c" else np.float64)


class ConformalMap:
    """The conformal map T of a workspace's free space onto a circle domain.

    The outer boundary goes to the unit circle, obstacle j to the circle
    ``|w - centers[j]| = radii[j]``; ``T(anchor) = 0`` and ``T'(anchor) > 0``.
    All evaluation methods are vectorized over complex arrays of any shape; points outside the
    closed free space (resp. the closed circle domain) give NaN.
    """

    def __init__(
        self,
        workspace: Workspace,
        eta: list[ComplexArray],
        deta: list[ComplexArray],
        W: list[ComplexArray],
        dW: list[ComplexArray],
        centers: ComplexArray,
        radii: FloatArray,
        diagnostics: SolveReport,
    ) -> None:
        self.workspace = workspace
        self.anchor = workspace.anchor
        self.centers = np.asarray(centers, dtype=np.complex128)
        self.radii = np.asarray(radii, dtype=np.float64)
        self.diagnostics = diagnostics
        self._parts = (eta, deta, W, dW)
        wts = np.concatenate([np.full(e.size, 2 * np.pi / e.size) for e in eta])
        self._eta, self._W = np.concatenate(eta), np.concatenate(W)
        # charges of the barycentric sums (weights folded in)
        self._q_deta = wts * np.concatenate(deta)
        self._q_W = self._q_deta * self._W
        self._q_dW = wts * np.concatenate(dW)
        self._Q_fwd = np.column_stack([self._q_W, self._q_deta])
        # The inverse sums run over the images W; nodes next to a corner that the map
        # compresses coincide there in floating point and are merged into one source.
        _, first = np.unique(self._W, return_index=True)
        keep = np.zeros(self._W.size, bool)
        keep[first] = True
        self._inv_W, self._inv_eta = self._W[keep], self._eta[keep]
        self._inv_q_dW = self._q_dW[keep]
        self._inv_q_etadW = self._inv_q_dW * self._inv_eta
        self._revision: str | None = None
        self._expansion: LocalExpansions | None = None
        self._fast = False  # build the expansions on first use (set by for_navigation)
        # :meth:`boundary_residuals`, computed once (the map's data do not change after
        # construction; the solver asks twice: the certificate, then the sides to refine)
        self._residuals: tuple[ComplexArray, FloatArray, NDArray[np.int_]] | None = None
        # the residual's denominator sums by boundary (its check points and the raw sums), kept
        # for a refined map of the same level (:meth:`reuse_denominators`), and that base
        self._denominators: tuple[list[ComplexArray], list[ComplexArray]] | None = None
        self._denominator_base: ConformalMap | None = None

    # ------------------------------------------------------------------ evaluation
    @property
    def n_obstacles(self) -> int:
        return int(self.centers.size)

    @staticmethod
    def _bary(
        nodes: ComplexArray, z: ComplexArray, charges: list[ComplexArray]
    ) -> list[ComplexArray]:
        """sum_k q_k/(nodes_k - z) for each charge vector."""
        return [-c for c in cauchy_sums(nodes, charges, z)]

    def _forward(
        self, z: ArrayLike, derivative: bool, check: bool, expand: bool = True
    ) -> tuple[ComplexArray, ComplexArray | None]:
        zz = np.asarray(z, dtype=np.complex128)
        shape = zz.shape
        if zz.size == 1:  # one robot: the scalar path (same values, no per-array overhead)
            w1, dw1 = self._forward1(complex(zz.reshape(-1)[0]), derivative, check, expand)
            return np.full(shape, w1), (np.full(shape, dw1) if derivative else None)
        flat = zz.ravel()
        w = np.full(flat.size, np.nan + 0j)
        dw = np.full(flat.size, np.nan + 0j) if derivative else None
        ok = np.isfinite(flat)
        if check:
            inside = np.asarray(
                shapely.intersects_xy(self.workspace.polygon, flat.real, flat.imag), dtype=bool
            )
            near = ok & ~inside  # boundary points rounded to just outside still count
            if near.any():
                d = distance_to_boundary(self.workspace, flat[near])
                inside[near] = d <= BOUNDARY_RTOL * self.workspace.diameter
            ok &= inside
        idx = np.flatnonzero(ok)
        if idx.size:
            pts = flat[idx]
            ex = self._expansions(pts.size) if expand else None
            if (
                ex is not None
            ):  # O(1) per point away from the walls (confnav/conformal/expansion.py)
                far, S, dS = ex.sums(pts)
                (Nf, Df), (dNf, dDf) = S[far].T, dS[far].T
                w[idx[far]] = Nf / Df
                if dw is not None:
                    dw[idx[far]] = (dNf * Df - Nf * dDf) / Df**2
                idx, pts = idx[~far], pts[~far]  # near a wall: the direct formula below
                if not idx.size:
                    return w.reshape(shape), (dw.reshape(shape) if dw is not None else None)
            with np.errstate(divide="ignore", invalid="ignore"):
                # N = sum q_W/(eta - z), D = sum q_eta/(eta - z), T = N/D and
                # T' = (N'D - N D')/D^2 with N' = sum q_W/(eta - z)^2 (likewise D'): the exact
                # derivative of the barycentric formula. It needs no W' and beats the Cauchy
                # integral of W' near the boundary (measured against finite differences: 8e-9
                # vs 1.2e-7 relative at clearance 0.002), where W' is least accurate.
                if pts.size == 1:  # one robot near a wall in a batch: 1-D dots
                    N, D, dN, dD = self._direct1(complex(pts[0]), derivative)
                elif pts.size * self._eta.size <= FMM_THRESHOLD:
                    R = np.subtract.outer(self._eta, pts)
                    np.reciprocal(R, out=R)
                    # einsum's own loop for a few points: a threaded BLAS gemv can stall for
                    # milliseconds on a busy machine (measured), a single robot's step cannot
                    few = pts.size <= 4
                    N, D = np.einsum("nk,np->kp", self._Q_fwd, R) if few else self._Q_fwd.T @ R
                    if derivative:
                        np.multiply(R, R, out=R)
                        dN, dD = (
                            np.einsum("nk,np->kp", self._Q_fwd, R) if few else self._Q_fwd.T @ R
                        )
                else:
                    first, second = cauchy_sums2(
                        self._eta, [self._q_W, self._q_deta], pts, derivative
                    )
                    N, D = -first[0], -first[1]
                    if derivative:
                        dN, dD = second
                w[idx] = N / D
                if dw is not None:
                    dw[idx] = (dN * D - N * dD) / D**2
            self._fix_nodes(pts, idx, w, dw)
        return w.reshape(shape), (dw.reshape(shape) if dw is not None else None)

    def _forward1(
        self, z: complex, derivative: bool, check: bool, expand: bool = True
    ) -> tuple[complex, complex]:
        """:meth:`_forward` of one point in Python scalars: ``(T(z), T'(z))`` (NaN outside).

        The same formulas: the local expansion's row is bitwise that of a batch
        (:meth:`LocalExpansions.sums1`); the quotients ``N/D`` and ``(N'D - N D')/D^2`` and
        the direct 1-D dots (near a wall) are rounded in scalars, within a few ulp of a batch.
        """
        nan = complex(np.nan, 0.0)
        if not cmath.isfinite(z):
            return nan, nan
        if check and not self._inside1(z):
            return nan, nan
        ex = self._expansions(1) if expand else None
        s = ex.sums1(z) if ex is not None else None
        if s is not None:  # O(1) away from the walls (confnav/conformal/expansion.py)
            N, D, dN, dD = s.tolist()
        else:  # near a wall (or a small map): the direct formula of _forward
            N, D, dN, dD = (complex(x) for x in self._direct1(z, derivative))
        try:
            w = N / D
            dw = (dN * D - N * dD) / (D * D) if derivative else nan
        except ZeroDivisionError:
            w = dw = nan
        if not cmath.isfinite(w):  # exactly on a node: the node's value (as _fix_nodes)
            wa, dwa = np.array([w]), np.array([dw])
            self._fix_nodes(np.array([z]), np.zeros(1, np.intp), wa, dwa if derivative else None)
            w, dw = complex(wa[0]), complex(dwa[0])
        return w, dw

    def _direct1(self, z: complex, derivative: bool) -> tuple[Any, Any, Any, Any]:
        """``(N, D, N', D')`` of the barycentric formula at one point by 1-D dots over the
        nodes (no kernel matrix: 4x faster than the batch kernels for one point); N', D' are
        NaN without ``derivative``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            r = 1.0 / (self._eta - z)
            N, D = np.dot(self._q_W, r), np.dot(self._q_deta, r)
            if not derivative:
                return N, D, np.nan, np.nan
            r *= r
            return N, D, np.dot(self._q_W, r), np.dot(self._q_deta, r)

    def _inside1(self, z: complex) -> bool:
        """The closed free space test of :meth:`_forward` for one point."""
        if shapely.intersects_xy(self.workspace.polygon, z.real, z.imag):
            return True
        d = distance_to_boundary(self.workspace, np.array([z]))
        return bool(d[0] <= BOUNDARY_RTOL * self.workspace.diameter)

    def _expansions(self, n_points: int) -> LocalExpansions | None:
        """The local-expansion evaluator if built, or worth building for ``n_points``.

        Built on first use by maps from :meth:`for_navigation` (evaluated again and again), or
        for a batch of at least :data:`EXPANSION_MIN_POINTS` (whose direct cost already
        exceeds the build's); once built it serves every evaluation of two or more points (T and
        T' within 1e-12 of the exact sums, see tests/test_expansion.py).
        """
        if self._expansion is None and (self._fast or n_points >= EXPANSION_MIN_POINTS):
            self._expansion = LocalExpansions(self._eta, self._Q_fwd, region=self.workspace.polygon)
            # from now on T and T' may come from the expansions: their truncation bound (sums;
            # T = N/D with |D| ~ 2 pi in the free space, so T errs by about bound / pi, and T'
            # likewise -- confnav/conformal/expansion.py) joins the map's error estimate
            self.diagnostics = self.diagnostics.with_evaluation(
                max(self._expansion.error_bound()) / np.pi
            )
        # one point on a small map: the direct 1-D dots cost less than the look-up's numpy
        # overhead (the build happens anyway, e.g. in a Controller's constructor)
        small = n_points == 1 and self.n_nodes <= EXPANSION_SINGLE_NODES
        return None if small else self._expansion

    def _fix_nodes(
        self, pts: ComplexArray, idx: np.ndarray, w: ComplexArray, dw: ComplexArray | None
    ) -> None:
        """Points that coincide with a boundary node take the node's value (0/0 otherwise)."""
        bad = ~np.isfinite(w[idx])
        if not bad.any():
            return
        for j in np.flatnonzero(bad):  # rare: exact hits of nodes only
            k = int(np.argmin(np.abs(self._eta - pts[j])))
            w[idx[j]] = self._W[k]
            if dw is not None:
                dk = self._q_deta[k]
                dw[idx[j]] = self._q_dW[k] / dk if dk != 0 else np.nan

    def T(self, z: ArrayLike, check: bool = True) -> ComplexArray:
        """T(z). With ``check=False`` the free-space test is skipped (caller guarantees it)."""
        return self._forward(z, False, check)[0]

    def dT(self, z: ArrayLike, check: bool = True) -> ComplexArray:
        """The complex derivative T'(z)."""
        d = self._forward(z, True, check)[1]
        assert d is not None
        return d

    def T_and_dT(self, z: ArrayLike, check: bool = True) -> tuple[ComplexArray, ComplexArray]:
        """T(z) and T'(z) from one pass over the boundary nodes."""
        w, d = self._forward(z, True, check)
        assert d is not None
        return w, d

    def T_and_dT1(self, z: complex, check: bool = True) -> tuple[complex, complex]:
        """:meth:`T_and_dT` of one point as Python complex numbers (the one-robot control
        step: no arrays in or out)."""
        return self._forward1(complex(z), True, check)

    def in_circle_domain(self, w: ArrayLike) -> np.ndarray:
        """True for points of the closed circle domain."""
        ww = np.asarray(w, dtype=np.complex128)
        ok = np.isfinite(ww) & (np.abs(ww) <= 1.0 + 1e-12)
        for c, r in zip(self.centers, self.radii, strict=True):
            ok &= np.abs(ww - c) >= r - 1e-12
        return np.asarray(ok)

    def inverse(self, w: ArrayLike, check: bool = True) -> ComplexArray:
        """T^-1(w) for points of the circle domain."""
        ww = np.asarray(w, dtype=np.complex128)
        shape = ww.shape
        flat = ww.ravel()
        out = np.full(flat.size, np.nan + 0j)
        ok = self.in_circle_domain(flat) if check else np.isfinite(flat)
        idx = np.flatnonzero(ok)
        if idx.size:
            pts = flat[idx]
            with np.errstate(divide="ignore", invalid="ignore"):
                num, den = self._bary(self._inv_W, pts, [self._inv_q_etadW, self._inv_q_dW])
                out[idx] = num / den
            bad = ~np.isfinite(out[idx])
            for j in np.flatnonzero(bad):
                out[idx[j]] = self._inv_eta[int(np.argmin(np.abs(self._inv_W - pts[j])))]
        return out.reshape(shape)

    # ------------------------------------------------------------------ fast evaluation
    def coarsened(self, stride: int) -> ConformalMap:
        """The same map evaluated from every ``stride``-th boundary node.

        The nodes are equispaced in the mesh parameter t, so every stride-th node is again a
        trapezoidal rule on the same parametrisation (boundaries whose node count ``stride``
        does not divide keep all their nodes). The solve needs its node density at the
        corners; evaluation away from them needs far fewer, and its cost is linear in the nodes.
        """
        eta, deta, W, dW = self._parts
        pick = [slice(None, None, stride if e.size % stride == 0 else 1) for e in eta]
        coarse = ConformalMap(
            self.workspace,
            [e[s] for e, s in zip(eta, pick, strict=True)],
            [d[s] for d, s in zip(deta, pick, strict=True)],
            [w[s] for w, s in zip(W, pick, strict=True)],
            [d[s] for d, s in zip(dW, pick, strict=True)],
            self.centers,
            self.radii,
            self.diagnostics,
        )
        coarse._revision = self.revision  # the same solution, evaluated from fewer nodes
        # its own a-posteriori check: fewer nodes are least accurate right at the walls
        coarse.diagnostics = self.diagnostics.with_residual(coarse.boundary_residual())
        return coarse

    def for_navigation(
        self, accuracy: float = 1e-7, strides: tuple[int, ...] = (8, 4, 2), seed: int = 0
    ) -> ConformalMap:
        """The cheapest coarsened map whose T and T' stay within ``accuracy`` of this one.

        Checked (T absolute, T' relative) at up to 400 random free-space points, preferring
        those at least 1% of the workspace size from the boundary but taking the ones with the
        most clearance where the domain is narrower than that, and at the walls themselves
        through the coarsened map's own :meth:`boundary_residual` (it must be within
        ``accuracy`` too). The result carries its own diagnostics (its residual, and the
        deviation measured here folded into its error estimate); returns ``self`` if no
        coarsening qualifies.
        The result evaluates through local expansions (built on first use, ~0.5 s).
        """
        z = self._check_points(seed)
        w, dw = self.T_and_dT(z, check=False)
        for s in strides:
            c = self.coarsened(s)
            wc, dwc = c.T_and_dT(z, check=False)
            dev = (
                max(float(np.max(np.abs(wc - w))), float(np.max(np.abs(dwc - dw) / np.abs(dw))))
                if z.size
                else 0.0
            )
            if dev <= accuracy and c.diagnostics.boundary_residual <= accuracy:
                c.diagnostics = c.diagnostics.with_deviation(dev)
                c._fast = True
                return c
        self._fast = True
        return self

    def _check_points(self, seed: int, count: int = 400) -> ComplexArray:
        """Random free-space points, those farther than 1% of the workspace size from the
        boundary first, then (narrow domains) the ones with the largest clearance."""
        ws = self.workspace
        x0, y0, x1, y1 = ws.bounds
        rng = np.random.default_rng(seed)
        z = rng.uniform(x0, x1, 10 * count) + 1j * rng.uniform(y0, y1, 10 * count)
        d = ws.clearance(z)
        inside = d > 0
        z, d = z[inside], d[inside]
        far = d > 0.01 * ws.diameter
        if int(far.sum()) >= count:
            return np.asarray(z[far][:count])
        return np.asarray(z[np.argsort(-d)][:count])

    def boundary_residual(self) -> float:
        """Largest distance of T(z) from its circle over boundary points between the nodes
        (:meth:`boundary_residuals`; inf if some is not finite)."""
        res = self.boundary_residuals()[1]
        return float(np.max(res)) if np.all(np.isfinite(res)) else float("inf")

    def worst_boundary_point(self) -> tuple[complex, str]:
        """Where the boundary residual is largest: the point and the boundary's name."""
        z, res, owner = self.boundary_residuals()
        i = int(np.argmax(np.where(np.isfinite(res), res, np.inf)))
        j = int(owner[i])
        return complex(z[i]), "the outer boundary" if j == 0 else f"obstacle {j - 1}"

    def boundary_residuals(self) -> tuple[ComplexArray, FloatArray, NDArray[np.int_]]:
        """Boundary points between the nodes, the distance of T there from its circle, and the
        boundary of each (0 outer, j + 1 obstacle j).

        An a-posteriori check of the map as evaluated (independent of the solver's own
        estimates): the midpoint between every two consecutive nodes (on the polygon, since
        consecutive nodes share a side) and, on every side, the points at the fractions
        :data:`CORNER_FRACTIONS` from each of its corners -- all but within
        :data:`CORNER_ZONE` of a corner. T maps the outer polygon onto
        ``|w| = 1`` and obstacle j onto ``|w - c_j| = r_j`` (docs/METHOD.md sec. 2).

        Computed on the first call and kept (read-only arrays): the solver's certificate and
        its choice of sides to refine read the same evaluation. On 50 obstacles that second
        evaluation was two FMM sums from every node to ~40,000 points (side by side 17.6 ->
        15.9 s CPU, the same maps bitwise; bench/README.md, "Residuals evaluated once").
        """
        if self._residuals is None:
            z, res, which = self._boundary_residuals()
            for a in (z, res, which):
                a.flags.writeable = False
            self._residuals = (z, res, which)
        return self._residuals

    def reuse_denominators(self, base: ConformalMap) -> None:
        """Let :meth:`boundary_residuals` take the denominator sums of ``base`` (a map of the
        same workspace and level whose residual was evaluated) on the boundaries whose nodes
        are ``base``'s bit for bit (:meth:`_denominators_from`): a per-side refinement's
        map. Call before the residual is first evaluated."""
        self._denominator_base = base

    def _boundary_residuals(self) -> tuple[ComplexArray, FloatArray, NDArray[np.int_]]:
        """:meth:`boundary_residuals`, evaluated.

        T = N/D with N = sum q_W/(eta - z) and D = sum q_eta/(eta - z) over every node. D
        depends on the nodes alone: above the FMM threshold its sums are kept by boundary,
        and a map whose nodes differ from a ``base`` map's (:meth:`reuse_denominators`) on a
        few boundaries only takes ``base``'s D at the other boundaries' check points (the same
        points) corrected by the changed boundaries' terms, and sums D afresh only at the
        changed boundaries' points, boundary by boundary (:meth:`_denominators_from`) -- the
        same sums, another order of their rounding. Round 7 (bench/README.md "Round 7"): on
        the refined 50-obstacle map the FMM sum of D (0.36 s CPU, dominated by its 46,480
        sources, not by its 39,684 points; 0.03 s boundary by boundary at the refined hole's
        points, bench/results/core_probes_round7.json) -- its certificate 0.77 -> 0.43 s."""
        eta = self._parts[0]
        targets, owner = [], []
        frac = np.array(CORNER_FRACTIONS)
        frac = np.concatenate([frac, 1.0 - frac[1:]])
        for j, (e, v) in enumerate(zip(eta, self.workspace.boundaries, strict=True)):
            mid = 0.5 * (e + np.roll(e, -1))
            lens = np.abs(np.roll(v, -1) - v)
            at = np.minimum(lens, np.roll(lens, 1))  # shorter side at each vertex
            rel = np.min(np.abs(mid[:, None] - v[None, :]) / at[None, :], axis=1)
            mid = mid[rel >= CORNER_ZONE]
            side = (v[:, None] + np.outer(np.roll(v, -1) - v, frac)).ravel()
            pts = np.concatenate([mid, side])
            targets.append(pts)
            owner.append(np.full(pts.size, j))
        z = np.concatenate(targets)
        which = np.concatenate(owner)
        if z.size * self._eta.size <= FMM_THRESHOLD:
            # points on the walls: no expansion covers them, so none is built for them (a build
            # for a map of 50 obstacles costs more than the direct/FMM sums at these points)
            w = self._forward(z, False, False, expand=False)[0]
        else:  # the sums _forward takes here, D kept by boundary
            # a check point on a node (a side's midpoint can be one) gives 0/0 there, which
            # _fix_nodes replaces by the node's value, as in _forward
            with np.errstate(divide="ignore", invalid="ignore"):
                D = self._denominators_from(targets)
                if D is None:
                    first = cauchy_sums2(self._eta, [self._q_W, self._q_deta], z, False)[0]
                    N, D = first
                else:
                    N = cauchy_sums(self._eta, [self._q_W], z)[0]
                w = N / D  # (-N) / (-D): cauchy_sums has the target first
            ends = np.cumsum([t.size for t in targets])[:-1]
            self._denominators = (targets, np.split(D, ends))
            self._fix_nodes(z, np.arange(z.size), w, None)
        c = np.concatenate([[0j], self.centers])[which]
        r = np.concatenate([[1.0], self.radii])[which]
        return z, np.abs(np.abs(w - c) - r), which

    def _denominators_from(self, targets: list[ComplexArray]) -> ComplexArray | None:
        """The denominator sums at ``targets`` (by boundary) from the base map's
        (:meth:`reuse_denominators`), or None if they do not apply: no base or no kept sums,
        another boundary count, or half the nodes or more changed. For an unchanged boundary
        (nodes and t-derivatives bit for bit the base's, hence its check points too) the
        base's sums plus, for each changed boundary, its new terms minus its old ones; at a
        changed boundary's points the sums over every boundary, one at a time (the
        expansions of :func:`~confnav.conformal.cauchy.cauchy_sums` for the far ones)."""
        base, self._denominator_base = self._denominator_base, None
        if base is None or base._denominators is None:
            return None
        old_t, old_D = base._denominators
        eta, deta = self._parts[0], self._parts[1]
        beta, bdeta = base._parts[0], base._parts[1]
        if len(beta) != len(eta) or len(old_t) != len(eta):
            return None
        changed = [
            j
            for j in range(len(eta))
            if not (
                eta[j].shape == beta[j].shape
                and np.array_equal(eta[j], beta[j])
                and np.array_equal(deta[j], bdeta[j])
                and np.array_equal(targets[j], old_t[j])
            )
        ]
        if not changed or 2 * sum(eta[j].size for j in changed) >= self._eta.size:
            return None

        def terms(e: ComplexArray, de: ComplexArray, pts: ComplexArray) -> ComplexArray:
            return cauchy_sums(e, [(2 * np.pi / e.size) * de], pts)[0]

        kept = [j for j in range(len(eta)) if j not in changed]
        zk = np.concatenate([targets[j] for j in kept])
        Dk = np.concatenate([old_D[j] for j in kept])
        for c in changed:  # the changed boundaries' terms at the kept points: new minus old
            Dk += terms(eta[c], deta[c], zk) - terms(beta[c], bdeta[c], zk)
        zc = np.concatenate([targets[j] for j in changed])
        Dc = np.zeros(zc.size, np.complex128)
        for e, de in zip(eta, deta, strict=True):
            Dc += terms(e, de, zc)
        out: list[ComplexArray] = [np.empty(0, np.complex128)] * len(eta)
        for group, values in ((kept, Dk), (changed, Dc)):
            ends = np.cumsum([0] + [targets[j].size for j in group])
            for i, j in enumerate(group):
                out[j] = values[ends[i] : ends[i + 1]]
        return np.concatenate(out)

    @property
    def n_nodes(self) -> int:
        """Boundary nodes the map is evaluated from (its cost per point is linear in this)."""
        return int(self._eta.size)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-able, lossless: arrays are base64 little-endian float64/complex128."""
        eta, deta, W, dW = self._parts
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "workspace": self.workspace.to_dict(),
            "workspace_hash": self.workspace_hash,
            "centers": _pack(self.centers),
            "radii": _pack(self.radii),
            "boundaries": [
                {"eta": _pack(e), "deta": _pack(d), "W": _pack(w), "dW": _pack(dw)}
                for e, d, w, dw in zip(eta, deta, W, dW, strict=True)
            ],
            "diagnostics": asdict(self.diagnostics),
        }

    @classmethod
    def from_dict(cls, d: Any) -> ConformalMap:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise SerializationError(f"not a confnav map (expected format {FORMAT!r})")
        if d.get("version") == 1:
            raise SerializationError(
                "map format version 1 is no longer accepted: its error estimate could not see "
                "an iteration stopped early and it carries no workspace hash; re-solve the "
                "workspace (confnav solve WS.json --out MAP.json)"
            )
        if d.get("version") != FORMAT_VERSION:
            raise SerializationError(
                f"map format version {d.get('version')!r} is not supported "
                f"(this confnav reads version {FORMAT_VERSION})"
            )
        try:
            ws = Workspace.from_dict(d["workspace"])
            if d["workspace_hash"] != ws.content_hash:
                raise SerializationError(
                    "map's workspace_hash does not match the workspace stored with it "
                    "(the file was altered or written by an incompatible program)"
                )
            bnd = d["boundaries"]
            parts = [[_unpack(b[k], k) for b in bnd] for k in ("eta", "deta", "W", "dW")]
            centers = _unpack(d["centers"], "centers")
            radii = _unpack(d["radii"], "radii")
            diag = SolveReport(**d["diagnostics"])
        except (KeyError, TypeError) as exc:
            raise SerializationError(f"map is missing or has a malformed field: {exc}") from exc
        if len(bnd) != ws.n_obstacles + 1 or centers.size != ws.n_obstacles:
            raise SerializationError("map boundaries do not match its workspace")
        for e, de, w, dw in zip(*parts, strict=True):
            if not (e.size == de.size == w.size == dw.size):
                raise SerializationError("map boundary arrays have inconsistent sizes")
        return cls(ws, parts[0], parts[1], parts[2], parts[3], centers, radii, diag)

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str | bytes) -> ConformalMap:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SerializationError(f"map is not valid JSON: {exc}") from exc
        return cls.from_dict(d)

    @property
    def workspace_hash(self) -> str:
        """:attr:`Workspace.content_hash` of the workspace this map was solved for."""
        return self.workspace.content_hash

    def check_workspace(self, workspace: Workspace) -> None:
        """Raise :class:`MapMismatchError` unless this map was solved for ``workspace``."""
        if workspace.content_hash != self.workspace_hash:
            raise MapMismatchError(
                f"the map was solved for workspace {self.workspace_hash[:12]} "
                f"({self.n_obstacles} obstacles), not for the one in use "
                f"{workspace.content_hash[:12]} ({workspace.n_obstacles} obstacles): "
                "solve this workspace or load its own map"
            )

    @property
    def revision(self) -> str:
        """sha256 of the workspace and coefficients (not of the diagnostics)."""
        if self._revision is None:
            h = hashlib.sha256(self.workspace.content_hash.encode())
            for arr in (*self._parts[2], *self._parts[3], self.centers, self.radii):
                h.update(np.ascontiguousarray(arr).tobytes())
            self._revision = h.hexdigest()
        return self._revision

    def __repr__(self) -> str:
        return (
            f"ConformalMap(obstacles={self.n_obstacles}, anchor={self.anchor:.6g}, "
            f"error_estimate={self.diagnostics.error_estimate:.1e})"
        )


__all__ = ["ConformalMap", "SolveReport"]
