"""Fleet coordination on a roadmap: PIBT steps on the roadmap's nodes, sub-goals for the
robots' conformal controllers, excursions from a node to a goal off the roadmap.

Why: a fleet driven by its navigation functions plus a safety filter and local rules (side
passing, yielding, single-lane mutexes) deadlocks in a warehouse's narrow aisles and at the
junctions between its pillars (bench/README.md, "Fleets").  Here the robots move on a
:class:`~confnav.navigation.roadmap.Roadmap` whose nodes are a robot's disk apart, one node at
a time and all at once (a *tick*), as planned by Priority Inheritance with Backtracking
(PIBT; Okumura, Machida, Defago and Tamura, "Priority inheritance with backtracking for
iterative multi-agent path finding", Artificial Intelligence 310, 2022, Algorithm 1): each
tick, the robots in order of priority pick the neighbouring node (or their own) nearest their
goal node that no robot has taken for the next tick; a robot whose pick is occupied by a robot
that has not picked yet hands its priority down to it, which must then move away (or the pick
fails and the next candidate is tried: backtracking); no two robots swap.  The priority of a
robot grows by one every tick it is not at its goal node and drops to zero on a new goal, so
the robot waiting longest leads (ties by a fixed random order).  A robot done with its goals
is an agent with its current node as goal and priority zero: robots that need its node push
it aside -- off the pusher's shortest path first (a pocket or a branch of a single-lane
passage rather than the lane ahead of the pusher, :func:`pibt_step`) -- and it goes back to
its goal once every robot is done (``come_back = "clear"``: once no active robot's shortest
path runs through its goal's nodes and none is within ``3 gap`` of them); going back it is
*meek*: it pushes no robot (two done robots pushing each other back and forth along a lane
is what this rules out).

The nodes are the sub-goals: a robot drives to its next node with a conformal controller of
that node (Koditschek-Rimon on the same map, :class:`~confnav.navigation.control.Controller`),
and every command still goes through the fleet filter (pairwise barrier rows, walls, the hold
cap: :func:`~confnav.navigation.fleet.project_with_walls`), so the plan costs no safety:
robots on different nodes are ``spacing >= 2 rho`` apart, and where the continuous motion
between nodes brings two robots nearer, the filter keeps them apart.  The next tick starts
when every robot on the roadmap is within ``node_tol`` of its node, when a robot has just
come within ``node_tol`` of its node (``eager``, at most every ``min_tick`` s: a robot need
not wait for the slowest one), or ``settle_timeout`` s after the last tick, whichever comes
first: a robot not there yet is fixed for that tick
(it keeps its node) and the node it comes from stays closed to the others until it is
there, so it holds up only the robots that need one of its two nodes, not the fleet (a
robot on an edge along a wall is slow: the wall hold cap limits it to ``HOLD_FRACTION c /
HOLD_TIME``).

Goals are off the roadmap.  A robot whose goal node (the node nearest the goal with a free
straight segment to it) is reached asks for an *excursion*: the nodes within ``gap`` of the
segment node-goal and the edges within ``gap`` of it are closed to the other robots; robots
standing on them are pushed out first (they plan with those nodes closed, staying not
allowed), and once they are empty the robot drives to its goal with its own controller and
back to its node (the *goal leg* and the *return leg*), while the others keep ticking around
the closed part.  Excursions are granted in order of priority and only when their closed
parts keep ``gap`` from the other excursions'.  A request still waiting for its nodes to
empty after ``patience`` s is dropped for ``patience`` s (the robot may then be pushed off
its goal node, and comes back): a robot that cannot leave a closed node does not hold the
requester forever.

What PIBT guarantees (op. cit., Theorem 1; Theorem 2 for goals given again on arrival): on a
graph where every two adjacent nodes lie on a simple cycle, the robot of highest priority
reaches its goal node within ``diam(G)`` ticks, so every robot reaches every goal node.  The
excursions and the timeout change the graph from tick to tick (closed nodes), so the theorem
is not claimed for this module: it is the design's rationale, not a guarantee; arrival is
measured (bench/bench_fleet.py).  What is guaranteed is what the fleet filter guarantees (no
contact), and that the plan never gives a node to two robots in one tick
(:meth:`RoadmapCoordinator.tick`).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from confnav.errors import NavigationError
from confnav.navigation.control import Controller, Status
from confnav.navigation.defaults import GOAL_TOL, V_MAX
from confnav.navigation.navfn import CircleDomain, KoditschekRimon
from confnav.navigation.roadmap import (
    Roadmap,
    build_roadmap,
    free_path,
    passage_widths,
    segment_clearance,
    segment_segment_distance,
)
from confnav.navigation.safety import SafetyFilter, safety_filter
from confnav.types import CArray

__all__ = [
    "ALONE",
    "GOAL_LEG",
    "LANE_FACTOR",
    "PARKED",
    "RETURN_LEG",
    "ROAD",
    "FleetCoordinator",
    "FleetRoadmap",
    "LineLaw",
    "NodeLaws",
    "Plan",
    "RoadmapCoordinator",
    "choose_coordinator",
    "choose_on_roadmap",
    "fleet_roadmap",
    "main_component",
    "pibt_step",
    "plan_fleet_roadmap",
]

#: modes of a robot; PARKED: at the goal it reached, its excursion still closed to the others,
#: until a robot's shortest way needs one of those nodes (then the return leg) or a new goal
ROAD, GOAL_LEG, RETURN_LEG, PARKED = 0, 1, 2, 3

#: the least default node spacing of a fleet roadmap (m): small robots' roadmaps would have
#: nodes a few cm apart (``2 rho + margin``), tens of thousands in a warehouse
MIN_SPACING = 0.25

#: m a robot on its goal leg must come nearer its goal within ``leg_patience`` s to count as
#: progressing (:meth:`RoadmapCoordinator._stalled_legs`)
LEG_PROGRESS = 0.02
#: a corner of a return way round the walls (:meth:`RoadmapCoordinator.return_way`) counts
#: as passed this near (m): the leg after it starts at the corner, where it is free
WAY_TOL = 0.05
#: how a robot drives the rest of its goal leg (:meth:`RoadmapCoordinator._stalled_legs`)
OWN_LAW, STRAIGHT, VIA_NODE = 0, 1, 2


def pibt_step(
    roadmap: Roadmap,
    at: Sequence[int],
    goal: Sequence[int],
    priority: Sequence[float],
    *,
    fixed: Sequence[bool] | None = None,
    closed_nodes: set[int] | frozenset[int] = frozenset(),
    closed_edges: set[tuple[int, int]] | frozenset[tuple[int, int]] = frozenset(),
    blocked: set[int] | frozenset[int] = frozenset(),
    meek: Sequence[bool] | None = None,
    aside: Sequence[bool] | None = None,
    rng: np.random.Generator | None = None,
) -> list[int]:
    """One PIBT step (Okumura et al. 2022, Algorithm 1): the node of every robot at the next
    tick.  ``at``: current nodes (distinct); ``goal``: goal nodes; ``priority``: larger
    first.  ``fixed`` robots stay.  No robot enters a ``closed_nodes`` node or moves along a
    ``closed_edges`` edge (either order); a robot standing on a closed node must leave it
    (staying is its last resort); no robot enters a ``blocked`` node (one standing on it may
    stay).  The result never gives one node to two robots, and no two
    robots swap nodes.

    Two rules for lanes (a pushed robot steps aside, not ahead): a robot pushed by another
    (directly or down a chain started by robot ``h``) tries the candidates off every
    shortest path of ``h`` to its goal first (``dist[at_h, v] + dist[v, goal_h] >
    dist[at_h, goal_h]``: a pocket or a branch rather than the next node of the lane ahead of
    ``h``), then the others, each group nearest its own goal first (only the ``aside``
    robots, default all; the others nearest their goal first); and a chain started by a
    ``meek`` robot (a robot done with its goals, going back to it) pushes no one: it moves
    only to nodes that are free or already left -- unless it stands on a closed node: it
    must leave that, and may push to (a meek robot boxed in on an excursion's node held the
    excursion for good, bench/results/fleet_services_latch_seed0_3rounds.json)."""
    n = len(at)
    cur = [int(a) for a in at]
    if len(set(cur)) != n:
        raise NavigationError("pibt_step: two robots on one node")
    fix = [False] * n if fixed is None else [bool(f) for f in fixed]
    mk = [False] * n if meek is None else [bool(f) for f in meek]
    asd = [True] * n if aside is None else [bool(f) for f in aside]
    occupant: dict[int, int] = {v: i for i, v in enumerate(cur)}
    nxt: list[int | None] = [None] * n
    taken: dict[int, int] = {}
    for i in range(n):
        if fix[i]:
            nxt[i] = cur[i]
            taken[cur[i]] = i
    tie = (rng or np.random.default_rng(0)).random(roadmap.size)
    dist = roadmap.dist

    def closed_edge(u: int, v: int) -> bool:
        return (u, v) in closed_edges or (v, u) in closed_edges

    def plan(i: int, parent: int | None, root: int) -> bool:
        u = cur[i]
        cands = [int(v) for v in roadmap.neighbours[u]]
        cands = [
            v for v in cands if v not in closed_nodes and v not in blocked and not closed_edge(u, v)
        ]
        if u not in closed_nodes:
            cands.append(u)
        g = goal[i]
        if parent is None or not asd[i]:
            cands.sort(key=lambda v: (dist[v, g], tie[v]))
        else:  # pushed: off the chain's starter's shortest paths first (step aside)
            a0, g0 = cur[root], goal[root]
            d0 = dist[a0, g0]
            on = {v: bool(np.isfinite(d0) and dist[a0, v] + dist[v, g0] <= d0 + 1e-9)
                  for v in cands}  # fmt: skip
            cands.sort(key=lambda v: (on[v], dist[v, g], tie[v]))
        for v in cands:
            if v in taken:
                continue
            if parent is not None and v == cur[parent]:
                continue  # no swap with the robot that pushed
            k = occupant.get(v)
            if mk[root] and k is not None and k != i and nxt[k] is None:
                continue  # a meek chain pushes no one
            nxt[i] = v
            taken[v] = i
            if k is not None and k != i and nxt[k] is None and not plan(k, i, root):
                continue  # k stays on v (it took v itself): try the next candidate
            return True
        nxt[i] = u
        taken[u] = i
        return False

    must_leave = [i for i in range(n) if not fix[i] and cur[i] in closed_nodes]
    for i in must_leave:  # leaving a closed node is no going back: it may push
        mk[i] = False
    order = sorted(range(n), key=lambda i: -priority[i])
    for i in must_leave + order:
        if nxt[i] is None:
            plan(i, None, i)
    out = [int(v) if v is not None else cur[i] for i, v in enumerate(nxt)]
    return out


@dataclass(frozen=True)
class LineOutput:
    """Commands (complex, m/s) and :class:`~confnav.navigation.control.Status` codes."""

    u: CArray
    status: NDArray[np.int8]


class LineLaw:
    """A point driven straight to ``goal``: ``u = gain (goal - z)`` at most ``v_max`` fast,
    zero within ``goal_tol`` (ARRIVED), then the wall safety filter on the exact workspace
    (:class:`~confnav.navigation.safety.SafetyFilter`: barrier rows and the hold cap), so it
    never leaves the free space.  The node law of a fleet on a map that is not one conformal
    map (an atlas, docs/ATLAS.md): a robot on the roadmap moves along its edges, which are
    free straight segments (:func:`~confnav.navigation.roadmap.build_roadmap`), so the
    straight law from a node to the next, or from a goal back to its node (a free segment,
    :meth:`RoadmapCoordinator.goal_node_of`), needs no navigation function; off a free
    segment (pushed aside by the fleet filter) it may stop at a wall, which the filter's
    rows then hold (no contact; arrival is what the bench measures)."""

    frame = "world"

    def __init__(
        self,
        goal: complex,
        safety: SafetyFilter,
        *,
        v_max: float = V_MAX,
        gain: float = 4.0,
        goal_tol: float = GOAL_TOL,
    ) -> None:
        self.goal = complex(goal)
        self.safety = safety
        self.v_max = float(v_max)
        self.gain = float(gain)
        self.goal_tol = float(goal_tol)

    def __call__(self, z: ArrayLike) -> LineOutput:
        zz = np.asarray(z, dtype=np.complex128)
        e = self.goal - zz
        u = self.gain * e
        speed = np.abs(u)
        u = np.where(speed > self.v_max, u * (self.v_max / np.maximum(speed, 1e-300)), u)
        arrived = np.abs(e) <= self.goal_tol
        u = np.where(arrived, 0j, u)
        pr = self.safety(zz, u)
        status = np.where(arrived, Status.ARRIVED, Status.MOVING).astype(np.int8)
        return LineOutput(u=np.asarray(pr.u).reshape(zz.shape), status=status.reshape(zz.shape))


def fleet_roadmap(
    ws: Any,
    rho: float,
    *,
    spacing: float | None = None,
    margin: float = 0.05,
    edge_clearance: float = 0.03,
    max_edge: float = 2.2,
) -> Roadmap:
    """The roadmap of a fleet of filter radius ``rho`` on ``ws`` (the free space shrunk by
    ``rho``): nodes ``spacing`` apart (default ``gap / sin 60deg``, ``gap = 2 rho + margin``:
    :meth:`RoadmapCoordinator.build`; at least :data:`MIN_SPACING`), edges at most
    ``max_edge`` spacings long, no edge nearer than ``gap`` to a third node, its 2-core
    (:func:`build_roadmap`).  Pure geometry: no map, so it can be built in another
    process."""
    gap = 2.0 * rho + margin
    sp = max(gap / np.sqrt(0.75), MIN_SPACING) if spacing is None else float(spacing)
    return build_roadmap(ws, sp, pass_gap=gap, edge_clearance=edge_clearance,
                         max_edge=max_edge * sp, prune_leaves=True)  # fmt: skip


class NodeLaws(Sequence[Any]):
    """The node laws of a roadmap, each made by ``make(v, node)`` when first asked for and
    kept (a robot drives to few of a large roadmap's nodes; the same law object each time)."""

    def __init__(self, nodes: NDArray[np.complex128], make: Any) -> None:
        self._nodes = nodes
        self._make = make
        self._laws: dict[int, Any] = {}

    def __len__(self) -> int:
        return int(self._nodes.size)

    def __getitem__(self, v: Any) -> Any:
        if isinstance(v, slice):
            return [self[i] for i in range(len(self))[v]]
        i = int(v)
        if not -len(self) <= i < len(self):
            raise IndexError(f"node {i} of {len(self)}")
        i %= len(self)
        law = self._laws.get(i)
        if law is None:
            law = self._laws[i] = self._make(i, complex(self._nodes[i]))
        return law


def _line_laws(ws: Any, v_max: float, gain: float) -> Any:
    """``make`` of :class:`NodeLaws`: the straight law to a node on ``ws``'s safety filter
    (built with the first law)."""
    flt: list[Any] = []

    def make(_: int, z: complex) -> LineLaw:
        if not flt:
            flt.append(safety_filter(ws))
        return LineLaw(z, flt[0], v_max=v_max, gain=gain)

    return make


def _kr_laws(cmap: Any, k: float, v_max: float, gain: float) -> Any:
    """``make`` of :class:`NodeLaws`: Koditschek-Rimon to a node on the conformal map
    ``cmap`` (one ``k`` for all nodes: for k at or above the goal's threshold the function
    is a navigation function, Koditschek and Rimon, "Robot navigation functions on manifolds
    with boundary", Adv. Appl. Math. 11, 1990)."""
    dom: list[CircleDomain] = []

    def make(_: int, z: complex) -> Controller:
        if not dom:
            dom.append(CircleDomain.of(cmap))
        w = complex(np.asarray(cmap.T_and_dT(np.array([z]))[0]).reshape(-1)[0])
        return Controller(cmap, z, navfn=KoditschekRimon(dom[0], w, k), gain=gain, v_max=v_max)

    return make


@dataclass
class _Excursion:
    nodes: frozenset[int]
    edges: frozenset[tuple[int, int]]
    a: complex
    b: complex


@dataclass
class RoadmapCoordinator:
    """Sub-goals for ``n`` robots on ``roadmap`` (module docstring).

    ``node_ctrls[v]``: the controller that drives a robot to node v; ``gap``: the least
    distance kept between an excursion and the other robots' nodes and edges (``2 rho`` plus
    a margin).  Use :meth:`build`, then :meth:`start` with the robots' positions, then call
    :meth:`update` every control step and :meth:`reached` when a robot reaches its goal."""

    roadmap: Roadmap
    node_ctrls: Sequence[Any]  # Controller (one conformal map) or LineLaw; NodeLaws: lazily
    n: int
    gap: float
    workspace: Any = None  # the exact free space (None: the node controllers' map's)
    node_tol: float = 0.12
    settle_timeout: float = 1.0
    seed: int = 0
    patience: float = 4.0
    eager: bool = True
    min_tick: float = 0.1
    late_limit: float = 3.0
    #: s on the goal leg without coming ``LEG_PROGRESS`` m nearer the goal after which a
    #: robot with a straight fallback (:meth:`goal_law`) drives the rest of the leg on it
    leg_patience: float = 5.0
    #: which pushed robots step aside first (:func:`pibt_step`'s ``aside``): ``"done"``
    #: (robots done with their goals: parked robots leave a lane into a pocket) or ``"all"``
    #: (every pushed robot: measured slower, bench/results/fleet_node_laws_aside.json)
    aside: str = "done"
    #: when a done robot pushed off its goal goes back (:meth:`_may_return`): ``"idle"`` (no
    #: robot of the fleet has a goal left) or ``"clear"`` (no active robot needs its goal's
    #: nodes: sooner, but measured to cost arrivals in the warehouse,
    #: bench/results/fleet_node_laws_comeback.json)
    come_back: str = "idle"
    at: NDArray[np.intp] = field(init=False)
    nxt: NDArray[np.intp] = field(init=False)
    mode: NDArray[np.int8] = field(init=False)
    eta: NDArray[np.float64] = field(init=False)
    goal_node: NDArray[np.intp] = field(init=False)
    goal_pt: CArray = field(init=False)
    pend_since: NDArray[np.float64] = field(init=False)
    suspend_until: NDArray[np.float64] = field(init=False)
    origin: NDArray[np.intp] = field(init=False)  # the node a robot on its way comes from
    excursions: dict[int, _Excursion] = field(init=False)
    #: robots on a return leg round the walls: the corners still ahead (the node last)
    return_ways: dict[int, list[complex]] = field(init=False)
    ticks: int = 0
    reverts: int = 0
    excursions_done: int = 0
    timeouts: int = 0
    idle_ticks: int = 0
    made_way: int = 0  # robot-ticks of done robots leading the way out of a lane
    t_tick: float = 0.0
    main: NDArray[np.intp] = field(init=False)  # nodes of the largest component

    def __post_init__(self) -> None:
        n = self.n
        self.at = np.zeros(n, dtype=np.intp)
        self.nxt = np.zeros(n, dtype=np.intp)
        self.mode = np.full(n, RETURN_LEG, dtype=np.int8)
        self.eta = np.zeros(n)
        self.goal_node = np.zeros(n, dtype=np.intp)
        self.goal_pt = np.full(n, np.nan + 0j)
        self.pend_since = np.full(n, np.nan)
        self.suspend_until = np.full(n, -np.inf)
        self._settled = np.zeros(n, dtype=bool)
        self._best = np.full(n, np.inf)  # a robot's least distance to its next node so far
        self._t_best = np.zeros(n)  # and when it came 0.05 m nearer than before
        self._leg_best = np.full(n, np.inf)  # on the goal leg: least distance to the goal
        self._leg_t = np.zeros(n)  # and when it came LEG_PROGRESS m nearer than before
        self._leg_way = np.zeros(n, dtype=np.int8)  # OWN_LAW, STRAIGHT or VIA_NODE
        self.origin = np.zeros(n, dtype=np.intp)
        self.excursions = {}
        self.return_ways = {}
        self._ways: dict[tuple[int, complex], list[complex] | None] = {}  # return_way cache
        self._rng = np.random.default_rng(self.seed)
        self._tie = self._rng.random(n) * 1e-3  # fixed random order between equal priorities
        self.main = main_component(self.roadmap)
        self._goal_cache: dict[complex, int] = {}
        self._goal_nodes_cache: dict[tuple[int, complex], NDArray[np.intp]] = {}
        self._goal_laws: dict[complex, LineLaw] = {}  # straight goal-leg laws (goal_law)

    @classmethod
    def build(
        cls,
        cmap: object,
        n: int,
        rho: float,
        *,
        spacing: float | None = None,
        k: float = 40.0,
        node_gain: float = 4.0,
        margin: float = 0.05,
        edge_clearance: float = 0.03,
        max_edge: float = 2.2,
        v_max: float = V_MAX,
        node_law: str = "kr",
        workspace: Any = None,
        **kw: float,
    ) -> RoadmapCoordinator:
        """The roadmap of ``cmap.workspace`` (the free space shrunk by the filter radius
        ``rho``), nodes ``spacing`` apart (default ``gap / sin 60deg`` with ``gap = 2 rho +
        margin``: an equilateral triangle of that side has its heights ``gap`` long, so its
        edges pass ``gap`` from the third node) and no edge nearer than ``gap`` to a node
        other than its ends (a robot moving along an edge keeps clear of the robots standing
        on nodes), and a controller per
        node: Koditschek-Rimon with the given ``k`` (one k for all nodes: for k at or above
        the goal's threshold the function is a navigation function, Koditschek and Rimon,
        "Robot navigation functions on manifolds with boundary", Adv. Appl. Math. 11, 1990)
        and gain ``node_gain`` (speed limit ``v_max``); ``node_law`` ``line``: a
        :class:`LineLaw` per node instead, on ``workspace`` (default ``cmap.workspace``; no
        conformal map is evaluated, ``cmap`` may be None).  ``node_tol`` defaults to
        ``spacing - 2 rho`` (a robot that near its node clears a robot standing on any other
        node)."""
        ws = getattr(cmap, "workspace", None) if workspace is None else workspace
        if ws is None:
            raise NavigationError("the coordinator needs a map with its workspace")
        rm = fleet_roadmap(ws, rho, spacing=spacing, margin=margin,
                           edge_clearance=edge_clearance, max_edge=max_edge)  # fmt: skip
        return cls.on_roadmap(rm, cmap, n, rho, k=k, node_gain=node_gain, margin=margin,
                              v_max=v_max, node_law=node_law, workspace=ws, **kw)  # fmt: skip

    @classmethod
    def on_roadmap(
        cls,
        rm: Roadmap,
        cmap: object,
        n: int,
        rho: float,
        *,
        k: float = 40.0,
        node_gain: float = 4.0,
        margin: float = 0.05,
        v_max: float = V_MAX,
        node_law: str = "kr",
        workspace: Any = None,
        **kw: float,
    ) -> RoadmapCoordinator:
        """The coordinator of :meth:`build` on a roadmap built already (:func:`fleet_roadmap`,
        e.g. in another process: the controller service builds it in a child process so that
        its pose path never shares the GIL with the build, ``services/roadmap_worker.py``).
        The node laws are made when a robot first drives to their node
        (:class:`NodeLaws`): a roadmap of 2,407 nodes (point robots in the default
        workspace) cost a conformal-map evaluation and a hash per node otherwise (about 1 s
        under a profiler)."""
        ws = getattr(cmap, "workspace", None) if workspace is None else workspace
        if ws is None:
            raise NavigationError("the coordinator needs a map with its workspace")
        if node_law not in ("kr", "line"):
            raise NavigationError(f"node_law must be 'kr' or 'line', got {node_law!r}")
        gap = 2.0 * rho + margin
        kw.setdefault("node_tol", rm.spacing - 2.0 * rho)
        laws = NodeLaws(rm.nodes, _line_laws(ws, v_max, node_gain) if node_law == "line"
                        else _kr_laws(cmap, k, v_max, node_gain))  # fmt: skip
        return cls(roadmap=rm, node_ctrls=laws, n=n, gap=gap, workspace=ws, **kw)  # type: ignore[arg-type]

    # -- set-up -----------------------------------------------------------------------------
    def start(self, p: ArrayLike) -> None:
        """Assign each robot (positions ``p``) a distinct node of the main component, nearest
        in sum (Hungarian method: Kuhn, "The Hungarian method for the assignment problem",
        Naval Res. Logist. Q. 2, 1955); the robots drive there first (return leg)."""
        pp = np.asarray(p, dtype=np.complex128).reshape(-1)
        if pp.size != self.n:
            raise NavigationError(f"{pp.size} positions for {self.n} robots")
        if self.main.size < self.n:
            raise NavigationError(f"{self.n} robots for {self.main.size} roadmap nodes")
        cost = np.abs(pp[:, None] - self.roadmap.nodes[self.main][None, :])
        r, c = linear_sum_assignment(cost)
        self.at[r] = self.main[c]
        self.nxt[:] = self.at
        self.origin[:] = self.at
        self.goal_node[:] = self.at
        self.mode[:] = RETURN_LEG

    def _workspace(self) -> Any:
        if self.workspace is not None:
            return self.workspace
        return getattr(self.node_ctrls[0].cmap, "workspace")  # noqa: B009 (typed Any)

    _ARRAYS = ("at", "nxt", "mode", "eta", "goal_node", "goal_pt", "pend_since",
               "suspend_until", "_settled", "origin", "_tie", "_best", "_t_best", "_leg_best",
               "_leg_t", "_leg_way")  # fmt: skip

    def add(self, p: complex) -> int:
        """A new robot at ``p`` (its controlled point): it gets the free main-component node
        nearest ``p`` among those with a free straight segment to ``p`` (the nearest if none
        of the eight nearest has, with conformal node laws; with straight ones
        (:class:`LineLaw`) a ``NavigationError``; free: no robot is on it, bound for it or
        coming from it, and no excursion closes it) and drives there first (return leg); its
        index.  For a host whose robots come and go (:class:`FleetCoordinator`)."""
        used = {int(v) for v in np.concatenate([self.at, self.nxt, self.origin])}
        for ex in self.excursions.values():
            used |= ex.nodes
        free = np.array([v for v in self.main.tolist() if v not in used], dtype=np.intp)
        if free.size == 0:
            raise NavigationError(f"no free roadmap node for robot {self.n}")
        near = free[np.argsort(np.abs(self.roadmap.nodes[free] - complex(p)))[:8]]
        seen = segment_clearance(self._workspace(), self.roadmap.nodes[near], complex(p)) > 0
        if not seen.any() and isinstance(self.node_ctrls[0], LineLaw):
            # a straight node law cannot go round a wall: on tb3_world through the services a
            # robot stayed "joining the roadmap" at a node behind one for 180 s
            # (bench/results/slam_services_final.json); it drives on its own law (the local
            # rules) until a node is in sight, then joins
            raise NavigationError(f"no free roadmap node in straight sight of {complex(p)}")
        v = int(near[np.flatnonzero(seen)[0]] if seen.any() else near[0])
        fill = {"at": v, "nxt": v, "mode": RETURN_LEG, "eta": 0.0, "goal_node": v,
                "goal_pt": np.nan + 0j, "pend_since": np.nan, "suspend_until": -np.inf,
                "_settled": False, "origin": v, "_tie": self._rng.random() * 1e-3,
                "_best": np.inf, "_t_best": 0.0, "_leg_best": np.inf, "_leg_t": 0.0,
                "_leg_way": OWN_LAW}  # fmt: skip
        for name in self._ARRAYS:
            a = getattr(self, name)
            setattr(self, name, np.append(a, np.array([fill[name]], dtype=a.dtype)))
        self.n += 1
        return self.n - 1

    def remove(self, i: int) -> None:
        """Forget robot ``i`` (its nodes and its excursion are freed); the robots after it
        move down one index."""
        if not 0 <= i < self.n:
            raise NavigationError(f"no robot {i} of {self.n}")
        for name in self._ARRAYS:
            setattr(self, name, np.delete(getattr(self, name), i))
        self.excursions = {
            (j if j < i else j - 1): ex for j, ex in self.excursions.items() if j != i
        }
        self.return_ways = {
            (j if j < i else j - 1): w for j, w in self.return_ways.items() if j != i
        }
        self.n -= 1

    def goal_node_of(self, goal: complex) -> int:
        """The main-component node nearest ``goal`` whose straight segment to it is free."""
        g = complex(goal)
        if g in self._goal_cache:
            return self._goal_cache[g]
        nodes = self.roadmap.nodes[self.main]
        order = np.argsort(np.abs(nodes - g))[:8]
        ws = self._workspace()
        free = segment_clearance(ws, nodes[order], np.full(order.size, g))
        ok = np.flatnonzero(free > 0.0)
        best = int(self.main[order[ok[0]] if ok.size else order[0]])
        self._goal_cache[g] = best
        return best

    # -- per control step -------------------------------------------------------------------
    def reached(self, i: int) -> None:
        """Robot ``i`` reached its goal: it stays there (``PARKED``) until a robot needs its
        way or it gets a new goal, then returns to its node."""
        if self.mode[i] == GOAL_LEG:
            self.mode[i] = PARKED
            self.excursions_done += 1

    def update(
        self, t: float, p: ArrayLike, goals: ArrayLike, done: ArrayLike
    ) -> tuple[list[Any], NDArray[np.bool_]]:
        """Each robot's controller for this step (None: its own goal controller, on the goal
        leg and parked; :meth:`goal_law` is the host's fallback there) and the goal-leg
        mask.  ``p``: controlled points; ``goals``: current goals; ``done``: robots with no
        goal left (they park on the roadmap)."""
        pp = np.asarray(p, dtype=np.complex128).reshape(-1)
        gg = np.asarray(goals, dtype=np.complex128).reshape(-1)
        dn = np.asarray(done, dtype=bool).reshape(-1)
        nodes = self.roadmap.nodes
        for i in range(self.n):
            if dn[i]:
                continue
            if self.mode[i] == PARKED:  # given its goal again: arrival counts again
                if gg[i] == self.goal_pt[i]:
                    self.mode[i] = GOAL_LEG
                else:
                    self._leave_goal(i)
                self._start_leg(i, t)
            if gg[i] != self.goal_pt[i]:
                self.goal_pt[i] = gg[i]
                self.goal_node[i] = self.goal_node_of(gg[i])
                self.eta[i] = 0.0
                self.pend_since[i] = np.nan
                self.suspend_until[i] = -np.inf
        back = (self.mode == RETURN_LEG) & (np.abs(pp - nodes[self.at]) <= self.node_tol)
        for i in np.flatnonzero(back).tolist():
            self.mode[i] = ROAD
            self.excursions.pop(i, None)
            self.return_ways.pop(i, None)
        road = self.mode == ROAD
        gap = np.abs(pp - nodes[self.nxt])
        settled = gap <= self.node_tol
        nearer = gap < self._best - 0.05  # progress toward the next node
        self._t_best = np.where(nearer, t, self._t_best)
        self._best = np.where(nearer, gap, self._best)
        newly = road & settled & ~self._settled
        self._settled = road & settled
        eager = self.eager and bool(newly.any()) and t - self.t_tick >= self.min_tick
        if np.all(settled | ~road) or t - self.t_tick >= self.settle_timeout or eager:
            if not (np.all(settled | ~road) or eager):
                self.timeouts += 1
            self.tick(t, settled, dn)
        way = self._stalled_legs(t, pp)
        drive: list[Any] = []
        for i in range(self.n):
            m = self.mode[i]
            if m == GOAL_LEG and way[i] == STRAIGHT:
                drive.append(self.goal_law(i))
            elif m == GOAL_LEG and way[i] == VIA_NODE:
                drive.append(self.node_ctrls[int(self.at[i])])
            elif m in (GOAL_LEG, PARKED):
                drive.append(None)
            elif m == RETURN_LEG:
                drive.append(self._return_law(i, complex(pp[i])))
            else:
                drive.append(self.node_ctrls[int(self.nxt[i])])
        return drive, self.mode == GOAL_LEG

    def _start_leg(self, i: int, t: float) -> None:
        """Robot ``i`` starts a goal leg at ``t``: a new progress clock, its own law."""
        self._leg_best[i], self._leg_t[i], self._leg_way[i] = np.inf, t, OWN_LAW

    def _stalled_legs(self, t: float, p: CArray) -> NDArray[np.int8]:
        """How each robot drives the rest of its goal leg: ``OWN_LAW``; ``STRAIGHT``, the
        straight fallback (:meth:`goal_law`) to the goal; ``VIA_NODE``, straight back to its
        goal node (whose segment to the goal is free by construction), then ``STRAIGHT``.  A
        robot on the leg that came no ``LEG_PROGRESS`` m nearer its goal for ``leg_patience``
        s takes ``STRAIGHT`` where the segment to its goal is free, else ``VIA_NODE`` where
        the segment to its goal node is, else keeps its own law and is looked at again
        ``leg_patience`` s later; latched until the leg ends.  Only with straight node laws
        (an atlas: :meth:`goal_law` exists).  Why: through the services (warehouse, seed 0) a
        unicycle's own atlas law near its goal, 0.06 m off the top aisle's wall, was
        rounding noise (the chart's map derivative 4.6e-7 there: the chart crowds, the goal
        and the robot 2.5e-9 apart in its disk, bench/results/fleet_goal_leg.json); the
        command's direction flipped from step to
        step, the robot turned on the spot 0.27 m from its goal from 311 s on and 10 robots
        queued behind it (bench/results/fleet_services_final_seed0.json); its own law had a
        value, so the NaN/ERROR fallback of the controller service never took over.  In seed
        1 (round 3) a robot's own law took it round a pillar, off the free segment, where a
        parked robot held it 1.27 m from its goal: ``VIA_NODE``.  A robot held by a neighbour
        meanwhile loses nothing: the straight laws pass the same fleet filter."""
        leg = self.mode == GOAL_LEG
        d = np.abs(p - self.goal_pt)
        nearer = leg & (d < self._leg_best - LEG_PROGRESS)
        self._leg_t = np.where(nearer, t, self._leg_t)
        self._leg_best = np.where(nearer, d, self._leg_best)
        self._leg_way[~leg] = OWN_LAW
        home = self.roadmap.nodes[self.at]
        # within node_tol, and within the node law's own arrival radius (its ARRIVED must
        # never reach the goal leg, where arrival counts)
        tol = max(self.node_tol, float(getattr(self.node_ctrls[0], "goal_tol", 0.0)))
        back = (self._leg_way == VIA_NODE) & (np.abs(p - home) <= tol)
        self._leg_way[back] = STRAIGHT  # at its goal node: the free segment to the goal
        late = leg & (self._leg_way == OWN_LAW) & (t - self._leg_t >= self.leg_patience)
        stalled = np.flatnonzero(late)
        if stalled.size and isinstance(self.node_ctrls[0], LineLaw):  # goal_law exists
            ws = self._workspace()
            to_goal = segment_clearance(ws, p[stalled], self.goal_pt[stalled]) > 0
            to_node = segment_clearance(ws, p[stalled], home[stalled]) > 0
            self._leg_way[stalled[to_goal]] = STRAIGHT
            self._leg_way[stalled[~to_goal & to_node]] = VIA_NODE
            self._leg_t[stalled[~to_goal & ~to_node]] = t  # look again in leg_patience s
        return self._leg_way

    def goal_law(self, i: int) -> Any:
        """The fallback law of robot ``i`` on its goal leg and parked at its goal, where its
        own controller (which drives it there) has no value: None with conformal node laws;
        with straight ones (:class:`LineLaw`, an atlas) the straight law to its goal point
        (same safety filter, speed and gain as the node laws, arrival within ``GOAL_TOL``),
        cached per goal point.  The segment from the goal node to the goal is free
        (:meth:`goal_node_of`), so the straight law needs no navigation function there, as
        from a node to the next.  Why: in the services warehouse (seed 0) a robot's own atlas
        law was NaN at points 0.3-0.4 m from its goal in the top aisle (the chart flat to
        rounding there); it stopped on its goal leg ``outside the mapped free space`` for
        good and 12 robots queued behind it (bench/results/fleet_services_diag_seed0.json).
        Only a fallback: driving every goal leg straight cost goals in the core warehouse
        (off the free segment, a robot that starts its leg off its node can be held at a
        wall)."""
        law0 = self.node_ctrls[0] if self.node_ctrls else None
        if not isinstance(law0, LineLaw):
            return None
        return self._line_law(complex(self.goal_pt[i]))

    def _line_law(self, point: complex) -> LineLaw:
        """The straight law to ``point`` with the node laws' safety filter, speed and gain
        (cached per point: goals and the corners of return ways)."""
        law = self._goal_laws.get(point)
        if law is None:
            law0 = self.node_ctrls[0]
            law = LineLaw(point, law0.safety, v_max=law0.v_max, gain=law0.gain)
            self._goal_laws[point] = law
        return law

    def _unpark(self, active: NDArray[np.bool_]) -> None:
        """Parked robots whose goal's nodes (its excursion's nodes and closed edges' ends, its
        goal node) lie on a shortest roadmap path of an ``active`` robot to its goal node, or
        within ``3 gap`` of an active robot along the roadmap, take the return leg: they
        leave the way, and become robots done with their goals (pushed aside)."""
        parked = [i for i in np.flatnonzero(self.mode == PARKED).tolist() if i in self.excursions]
        if not parked or not active.any():
            return
        chain = self._push_chains(active)
        for i in parked:
            ex = self.excursions[i]
            ends = {int(v) for e in ex.edges for v in e}  # a closed edge's ends
            nodes = ex.nodes | ends | {int(self.at[i])}
            nn = np.fromiter(nodes, dtype=np.intp)
            if nodes & chain or self._in_the_way(nn, active):
                self._leave_goal(i)

    def _leave_goal(self, i: int) -> None:
        """Parked robot ``i`` takes the return leg to its node, round the walls where the
        straight way from its goal is not free (:meth:`return_way`)."""
        self.mode[i] = RETURN_LEG
        way = self.return_way(int(self.at[i]), complex(self.goal_pt[i]))
        if way is not None and len(way) > 1:
            self.return_ways[i] = list(way)
        else:
            self.return_ways.pop(i, None)

    def return_way(self, v: int, goal: complex) -> list[complex] | None:
        """The corners of the way back from ``goal`` to node ``v`` (the node last; cached):
        with straight node laws (:class:`LineLaw`, an atlas) a free polyline round the walls
        (:func:`~confnav.navigation.roadmap.free_path`) where the straight segment is not
        free; None where it is, with conformal node laws (they go round walls themselves),
        or where no way is found (the straight law then, as before).  A goal that no node
        of the main component sees (:meth:`goal_node_of` then takes the nearest node) is
        reached on the robot's own law round the walls; the straight law back held it at
        the wall for good.  Why: on the TurtleBot3 sandbox (services, three unicycles,
        filter radius 0.32 m) a done robot parked in the outer ring, called back to its
        node across a pillar, stood at the pillar's wall while another robot waited for
        that node until the end of the run."""
        if not isinstance(self.node_ctrls[0], LineLaw) or np.isnan(goal.real):
            return None
        key = (int(v), complex(goal))
        if key not in self._ways:
            node = complex(self.roadmap.nodes[key[0]])
            if segment_clearance(self._workspace(), np.array([goal]), np.array([node]))[0] > 0:
                self._ways[key] = None
            else:
                w = free_path(self._workspace(), goal, node)
                self._ways[key] = None if w is None else [complex(z) for z in w.tolist()]
        return self._ways[key]

    def _return_law(self, i: int, p: complex) -> Any:
        """The law of robot ``i`` on its return leg at ``p``: the node's law, or the straight
        law to the next corner of its way round the walls (passed within ``WAY_TOL``)."""
        way = self.return_ways.get(i)
        while way and len(way) > 1 and abs(p - way[0]) <= WAY_TOL:
            way.pop(0)
        if not way or len(way) <= 1:
            return self.node_ctrls[int(self.at[i])]
        return self._line_law(complex(way[0]))

    def _push_chains(self, active: NDArray[np.bool_]) -> set[int]:
        """The nodes an ``active`` robot's next move needs cleared: where its next node on a
        shortest path to its goal node holds a robot done with its goals (on the roadmap),
        that robot's node and every node of done robots joined to it by edges (the chain its
        push runs down), with their neighbours (where the chain's last robot must go), when
        none of those neighbours is free (no robot on or bound for it, no excursion closing
        it).  A robot parked at its goal holding one of them blocks the push however far it
        is from the active robot: in the services warehouse (seed 1) two done robots stood in a
        lane between an active robot and its goal node, and a robot parked at the lane's
        far node held it: the push failed for good (bench/results/
        fleet_services_diag_seed1.json)."""
        done_on = {int(v) for v in self.at[(self.mode == ROAD) & ~active]}
        if not done_on:
            return set()
        dist, nb = self.roadmap.dist, self.roadmap.neighbours
        taken = {int(v) for v in np.concatenate([self.at, self.nxt])}
        for ex in self.excursions.values():
            taken |= ex.nodes
        out: set[int] = set()
        for j in np.flatnonzero(active).tolist():
            a, g = int(self.at[j]), int(self.goal_node[j])
            if a == g or not np.isfinite(dist[a, g]):
                continue
            nxt = [int(v) for v in nb[a] if int(v) in done_on
                   and dist[a, v] + dist[v, g] <= dist[a, g] + 1e-9]  # fmt: skip
            todo = list(nxt)
            seen = set(nxt)
            while todo:  # the done robots joined to them
                v = todo.pop()
                for w in nb[v].tolist():
                    if w in done_on and w not in seen:
                        seen.add(w)
                        todo.append(w)
            ends = {int(w) for v in seen for w in nb[v].tolist()} - seen - {a}
            if ends - taken:
                continue  # the chain can end on a free node: nothing to unpark
            out |= seen | ends
        return out

    def _in_the_way(self, nn: NDArray[np.intp], active: NDArray[np.bool_]) -> bool:
        """Whether nodes ``nn`` lie on a shortest roadmap path of an ``active`` robot to its
        goal node, or within ``3 gap`` of an active robot along the roadmap."""
        if not active.any():
            return False
        dist = self.roadmap.dist
        a, g = self.at[active], self.goal_node[active]
        direct = dist[a, g]
        via = dist[np.ix_(a, nn)] + dist[np.ix_(nn, g)].T  # (robots, nodes)
        on_way = np.isfinite(direct)[:, None] & (via <= direct[:, None] + 1e-9)
        near = dist[np.ix_(a, nn)] <= 3.0 * self.gap  # a robot coming near
        return bool(on_way.any() or near.any())

    def _goal_nodes(self, i: int) -> NDArray[np.intp]:
        """Robot ``i``'s goal's nodes: its goal node, the nodes its excursion from there
        closes and its closed edges' ends (cached per goal node and point)."""
        key = (int(self.goal_node[i]), complex(self.goal_pt[i]))
        nn = self._goal_nodes_cache.get(key)
        if nn is None:
            ex = self._excursion(i, key[0])
            ends = {int(v) for e in ex.edges for v in e}
            nn = np.fromiter(ex.nodes | ends | {key[0]}, dtype=np.intp)
            self._goal_nodes_cache[key] = nn
        return nn

    def _may_return(self, done: NDArray[np.bool_], active: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Robots done with their goals, on the roadmap (pushed off their goal or parked
        there), that go back to their goal, as meek robots (:func:`pibt_step`: pushing no
        one): with ``come_back = "idle"`` (the default) all of them once every robot is
        done; with ``"clear"`` those whose goal's nodes no active robot needs
        (:meth:`_in_the_way`)."""
        out = np.zeros(self.n, dtype=bool)
        cand = done & (self.mode == ROAD) & ~np.isnan(self.goal_pt.real)
        if self.come_back == "idle":  # only once no robot of the fleet has a goal left
            return cand if done.all() else out
        for i in np.flatnonzero(cand).tolist():
            out[i] = not self._in_the_way(self._goal_nodes(i), active)
        return out

    def tick(self, t: float, settled: NDArray[np.bool_], done: NDArray[np.bool_]) -> None:
        """One PIBT step for the robots on the roadmap; excursions granted and started."""
        self.ticks += 1
        self.t_tick = t
        road = self.mode == ROAD
        late = road & ~settled  # still between two nodes: keeps both until it is there
        self.origin = np.where(road & settled, self.nxt, self.origin)
        self._revert(t, late)
        blocked = {int(v) for v in self.origin[late & (self.origin != self.nxt)]}
        self.at = np.where(road, self.nxt, self.at)
        fixed = ~road | late
        for i in [j for j in self.excursions if self.mode[j] == ROAD]:
            self.excursions.pop(i)  # a request not started last tick is asked again
        self._unpark(road & ~done)
        back = self._may_return(done, road & ~done)  # done, its goal clear: goes back
        goal = np.where(done & ~back, self.at, self.goal_node)
        at_goal = road & (self.at == goal)
        self.eta = np.where(at_goal | done, 0.0, self.eta + 1.0)
        closed_nodes: set[int] = set()
        closed_edges: set[tuple[int, int]] = set()
        for ex in self.excursions.values():
            closed_nodes |= ex.nodes
            closed_edges |= ex.edges
        # excursion requests: settled robots on their goal node, goal not yet reached, not
        # suspended (a request pending ``patience`` s is dropped for ``patience`` s:
        # the robot is then an ordinary agent that may be pushed off its goal node)
        req = np.flatnonzero(
            road
            & settled
            & (~done | back)
            & (self.at == self.goal_node)
            & (t >= self.suspend_until)
        )
        req = req[np.argsort(-(self.eta[req] + self._tie[req]), kind="stable")]
        holders = {int(self.at[j]) for j in np.flatnonzero(~road)}
        starting: list[int] = []
        asked: list[int] = []
        for i in req.tolist():
            ex = self._excursion(i)
            if int(self.at[i]) in closed_nodes or ex.nodes & holders:
                continue
            if any(
                float(segment_segment_distance(ex.a, ex.b, o.a, o.b)) < self.gap
                for o in self.excursions.values()
            ):
                continue
            others = {int(self.at[j]) for j in range(self.n) if j != i}
            if done[i] and ex.nodes & (others | {int(v) for v in self.nxt}):
                continue  # a done robot going back does not empty its way: it waits
            if ex.nodes & others:  # pending: its nodes are emptied first, its edges stay open
                if np.isnan(self.pend_since[i]):
                    self.pend_since[i] = t
                closed_nodes |= ex.nodes
            else:
                starting.append(i)
                self.pend_since[i] = np.nan  # started: no longer pending (never dropped)
                closed_nodes |= ex.nodes
                closed_edges |= ex.edges
            self.excursions[i] = ex
            fixed[i] = True
            asked.append(i)
        self._drop_overdue(t, road, late, fixed, asked)
        closed_nodes, closed_edges = self._closed(starting)
        prio = self.eta + self._tie
        prio = np.where(np.isin(np.arange(self.n), asked), prio + 1e6, prio)  # at goal: hold
        meek = done.copy()
        way = self._make_way(road & done & ~back & ~fixed, road & ~done, prio,
                             closed_nodes | blocked, closed_edges)  # fmt: skip
        for i, (w, pr) in way.items():  # cornered in a lane: leads the way out, pushing
            goal[i], prio[i], meek[i] = w, pr, False
        self.made_way += len(way)
        nxt = pibt_step(
            self.roadmap,
            self.at.tolist(),
            goal.tolist(),
            prio.tolist(),
            fixed=fixed.tolist(),
            closed_nodes=closed_nodes,
            closed_edges=closed_edges,
            blocked=blocked,
            meek=meek.tolist(),
            aside=None if self.aside == "all" else done.tolist(),
            rng=self._rng,
        )
        self.origin = np.where(road & ~late, self.at, self.origin)
        moved = np.array(nxt, dtype=np.intp) != self.nxt
        self.nxt = np.array(nxt, dtype=np.intp)
        self._best = np.where(moved, np.inf, self._best)  # a new next node: a new clock
        self._t_best = np.where(moved, t, self._t_best)
        if np.unique(self.nxt).size != self.n:  # pibt_step's invariant, kept cheaply checked
            raise NavigationError("roadmap plan gave one node to two robots")
        if np.all(self.nxt == self.at) and not starting:
            self.idle_ticks += 1
        for i in starting:
            self.mode[i] = GOAL_LEG
            self.pend_since[i] = np.nan
            self._start_leg(i, t)

    def _make_way(
        self,
        cand: NDArray[np.bool_],
        active: NDArray[np.bool_],
        prio: NDArray[np.float64],
        closed_nodes: set[int],
        closed_edges: set[tuple[int, int]],
    ) -> dict[int, tuple[int, float]]:
        """Done robots (``cand``) cornered in an active robot's way: a robot ``i`` on the
        shortest roadmap path of an active robot ``j`` to its goal node (``j`` within ``3
        gap`` of it along the roadmap) such that no node off that path from which ``i`` can
        come back to its goal node without passing ``j``'s goal node lies ahead of it (in
        the roadmap as built, reachable from ``i`` without passing ``j``'s node): a
        pocketless lane that is a bridge of the roadmap.  Pushed, ``i`` could only go on
        ahead of ``j``, past ``j``'s goal, and stay behind it there: the studio's robot a,
        parked 3.09 m off its goal, bench/results/fleet_studio_auto.json.  Each gets a
        *waiting node* -- the open node off every such path, from which it can come back,
        nearest it along the roadmap (behind ``j``) -- and a priority above those robots', so
        that it leads the way out (pushing them aside at the junction behind them, then
        stepping off their way) instead of being pushed on ahead of them; ``{i: (node,
        priority)}``.  In the warehouse, whose aisles join at both ends, no robot is
        cornered.  The pushing and the priorities are PIBT's (Okumura et al. 2022,
        Algorithm 1); the waiting node is this module's rule."""
        out: dict[int, tuple[int, float]] = {}
        if not cand.any() or not active.any():
            return out
        dist = self.roadmap.dist
        js = np.flatnonzero(active)
        a, g = self.at[js], self.goal_node[js]
        direct = dist[a, g]
        # way[k, v]: node v lies on a shortest path of active robot js[k] to its goal node
        way = np.isfinite(direct)[:, None] & (dist[a, :] + dist[:, g].T <= direct[:, None] + 1e-9)
        way &= (a != g)[:, None]
        shut = np.zeros(self.roadmap.size, dtype=bool)
        shut[list(closed_nodes)] = True
        for i in np.flatnonzero(cand).tolist():
            u = int(self.at[i])
            mine = way[:, u] & (dist[a, u] <= 3.0 * self.gap)
            if not mine.any():
                continue
            home = int(self.goal_node[i])  # it comes back there: not from behind their goals
            cornered = False
            for k in np.flatnonzero(mine).tolist():  # each robot whose way it is in, alone
                ok = ~way[k] & np.isfinite(dist[u]) & self._reach(u, {int(a[k])})
                ok[u] = False
                if home != int(g[k]):
                    ok &= self._reach(home, {int(g[k])})
                if not ok.any():  # no way out ahead of it in the roadmap as built
                    cornered = True
                    break
            if not cornered:
                continue  # a way out ahead: PIBT's aside rule takes it there
            gone = {int(x) for x in g[mine]}
            off = ~way[mine].any(axis=0) & np.isfinite(dist[u]) & ~shut
            off[u] = False
            if home not in gone:
                off &= self._reach(home, gone)
            if not off.any():
                continue
            cands = np.flatnonzero(off)
            w = int(cands[np.argmin(dist[u, cands])])
            out[i] = (w, float(prio[js[mine]].max()) + 1.0)
        return out

    def _reach(self, src: int, gone: set[int]) -> NDArray[np.bool_]:
        """The nodes connected to ``src`` on the roadmap without the nodes ``gone``."""
        e = self.roadmap.edges
        n = self.roadmap.size
        keep = ~np.isin(e, list(gone)).any(axis=1) if gone else np.ones(len(e), dtype=bool)
        _, lab = connected_components(
            csr_matrix((np.ones(int(keep.sum())), (e[keep, 0], e[keep, 1])), shape=(n, n)),
            directed=False,
        )
        ok = lab == lab[src]
        ok[list(gone - {src})] = False
        return np.asarray(ok)

    def _drop_overdue(
        self,
        t: float,
        road: NDArray[np.bool_],
        late: NDArray[np.bool_],
        fixed: NDArray[np.bool_],
        asked: list[int],
    ) -> None:
        """Excursion requests pending ``patience`` s are dropped and suspended for as long
        (the robot is then an ordinary agent); ``fixed`` and ``asked`` updated in place."""
        over = road & (t - self.pend_since >= self.patience)  # NaN (not pending): False
        self.suspend_until[over] = t + self.patience
        self.pend_since[over] = np.nan
        for i in np.flatnonzero(over).tolist():
            self.excursions.pop(i, None)
            self.eta[i] = 0.0
            fixed[i] = bool(late[i])  # a robot still on its way stays fixed regardless
            if i in asked:
                asked.remove(i)

    def _closed(self, starting: list[int]) -> tuple[set[int], set[tuple[int, int]]]:
        """The roadmap nodes every excursion closes, and the edges of those under way or
        starting this tick (a pending one keeps its edges open)."""
        closed_nodes: set[int] = set()
        closed_edges: set[tuple[int, int]] = set()
        for ex in self.excursions.values():
            closed_nodes |= ex.nodes
        for j, ex in self.excursions.items():
            if self.mode[j] != ROAD or j in starting:
                closed_edges |= ex.edges
        return closed_nodes, closed_edges

    def _revert(self, t: float, late: NDArray[np.bool_]) -> None:
        """A robot on its way that has not come 0.05 m nearer its next node for
        ``late_limit`` s (held off it: by the fleet filter, by a robot pushed onto the edge,
        by a wall) goes back to the node it comes from, if no other robot is on, bound for or
        coming from that node: its move is undone (it would otherwise stay fixed, and the
        robots around it with it)."""
        stuck = late & (t - self._t_best >= self.late_limit) & (self.origin != self.nxt)
        for i in np.flatnonzero(stuck).tolist():
            u = int(self.origin[i])
            others = np.arange(self.n) != i
            taken = np.concatenate([self.at[others], self.nxt[others], self.origin[others]])
            if u in taken.tolist() or any(u in ex.nodes for ex in self.excursions.values()):
                continue
            self.origin[i], self.nxt[i] = self.nxt[i], u
            self._best[i], self._t_best[i] = np.inf, t
            self.reverts += 1

    def _excursion(self, i: int, node: int | None = None) -> _Excursion:
        """Robot ``i``'s excursion from ``node`` (default: its node) to its goal point."""
        s = int(self.at[i]) if node is None else int(node)
        a = complex(self.roadmap.nodes[s])
        b = complex(self.goal_pt[i])
        rm = self.roadmap
        dn = segment_segment_distance(rm.nodes, rm.nodes, a, b)
        nodes = frozenset(int(v) for v in np.flatnonzero(dn < self.gap)) - {s}
        de = segment_segment_distance(rm.nodes[rm.edges[:, 0]], rm.nodes[rm.edges[:, 1]], a, b)
        edges = frozenset(
            (int(u), int(v)) for u, v in rm.edges[de < self.gap].tolist() if s not in (u, v)
        )
        return _Excursion(nodes=nodes, edges=edges, a=a, b=b)


#: ``auto``'s threshold: a passage is single-lane when the free space of the robots' centres
#: across it (the workspace shrunk by the filter radius ``rho``) is narrower than
#: ``LANE_FACTOR rho``, i.e. the passage itself narrower than ``(LANE_FACTOR + 2) rho``: two
#: disks side by side (``4 rho``) and half a disk of room for side passing.  Measured: under
#: the local rules 4 robots of radius 0.2 m do not get through a 0.9 m door (``4.5 rho``,
#: tests/test_fleet_coord_async.py), 8 get through a 1.2 m one (``6 rho``) in 1.45 times the
#: slowest lone run (bench/results/fleet_roadmap_scenarios.json)
LANE_FACTOR = 3.0


def choose_coordinator(
    coord: RoadmapCoordinator, rho: float, factor: float = LANE_FACTOR
) -> tuple[str, float, complex]:
    """``auto``: ``"roadmap"`` when the free space (of centres, for filter radius ``rho``)
    that ``coord``'s roadmap covers has a single-lane passage -- an edge of its main component
    across which the free space is narrower than ``factor rho`` (:data:`LANE_FACTOR`;
    :func:`~confnav.navigation.roadmap.passage_widths`) -- else ``"local"``; with the
    narrowest width across an edge (m; ``inf``: no edge) and where (the edge's midpoint)."""
    return choose_on_roadmap(coord.roadmap, coord._workspace(), rho, factor)


def main_component(rm: Roadmap) -> NDArray[np.intp]:
    """The nodes of the roadmap's largest connected component (the coordinator's ``main``)."""
    lab = rm.components()
    big = np.bincount(lab).argmax() if lab.size else 0
    return np.flatnonzero(lab == big).astype(np.intp)


def choose_on_roadmap(
    rm: Roadmap, ws: Any, rho: float, factor: float = LANE_FACTOR
) -> tuple[str, float, complex]:
    """:func:`choose_coordinator` on a roadmap with no coordinator (no node laws): the same
    decision from the roadmap's main component and the free space ``ws``."""
    main = np.zeros(rm.size, dtype=bool)
    main[main_component(rm)] = True
    keep = main[rm.edges[:, 0]] & main[rm.edges[:, 1]] if len(rm.edges) else np.zeros(0, bool)
    if not keep.any():
        return "local", float("inf"), complex(np.nan, np.nan)
    e = rm.edges[keep]
    sub = Roadmap(rm.nodes, e, rm.neighbours, rm.dist, rm.spacing, rm.min_clearance)
    w = passage_widths(ws, sub)
    k = int(np.argmin(w))
    where = complex(0.5 * (rm.nodes[e[k, 0]] + rm.nodes[e[k, 1]]))
    return ("roadmap" if w[k] < factor * rho else "local"), float(w[k]), where


@dataclass(frozen=True)
class FleetRoadmap:
    """A fleet's roadmap and, for ``auto``, the coordinator chosen on it
    (:func:`plan_fleet_roadmap`): ``roadmap`` None when the choice is ``"local"`` (nothing
    to coordinate on: not sent back from a child process); ``width`` and ``where`` as
    :func:`choose_coordinator` gives them (NaN when not chosen)."""

    roadmap: Roadmap | None
    choice: str
    width: float
    where: complex


def plan_fleet_roadmap(ws: Any, rho: float, decide: bool) -> FleetRoadmap:
    """The roadmap of a fleet of filter radius ``rho`` on ``ws`` (:func:`fleet_roadmap`) and,
    if ``decide`` (``auto``), the coordinator for it (:func:`choose_on_roadmap`).  Point
    robots (``rho`` 0) are left to the local rules without a roadmap: no passage is
    single-lane for them, and their roadmap would have nodes 6 cm apart (2,407 in the
    default workspace, 21,455 and an all-pairs distance matrix of 3.7 GB in a small
    warehouse)."""
    if decide and not rho > 0.0:  # point robots: no passage is narrower than LANE_FACTOR 0
        return FleetRoadmap(None, "local", float("nan"), complex(np.nan, np.nan))
    rm = fleet_roadmap(ws, rho)
    if not decide:
        return FleetRoadmap(rm, "roadmap", float("nan"), complex(np.nan, np.nan))
    choice, width, where = choose_on_roadmap(rm, ws, rho)
    return FleetRoadmap(rm if choice == "roadmap" else None, choice, width, where)


@dataclass(frozen=True)
class Plan:
    """What a coordinated robot does now: ``ctrl`` drives it (None: its own goal controller,
    on the goal leg or uncoordinated); ``goal_leg``: its own controller's arrival counts;
    ``parked``: it reached its goal and waits on the roadmap; ``note``: what it does, in
    words (a status message)."""

    ctrl: Any  # the node's law (Controller or LineLaw); None: its own goal controller
    goal_leg: bool
    parked: bool
    note: str
    coordinated: bool
    #: on the goal leg and parked: the law for where its own has no value (NaN or ERROR;
    #: :meth:`RoadmapCoordinator.goal_law`), None: none
    fallback: Any = None


#: the plan of a robot that is not coordinated: its own controller, exactly as alone
ALONE = Plan(ctrl=None, goal_leg=True, parked=False, note="", coordinated=False)


class FleetCoordinator:
    """A :class:`RoadmapCoordinator` for a host that gets its robots' poses asynchronously,
    in batches, and whose robots come and go (the controller service,
    ``services/controller_coord.py``): robots are named by id, and each call of :meth:`plan`
    with the poses of some of them (the others keep their last position) advances the plan
    (:meth:`RoadmapCoordinator.update`: a tick when the robots on the roadmap have settled,
    eagerly at most every ``min_tick`` s, or after ``settle_timeout`` s) and returns each
    given robot's :class:`Plan`.

    Coordination engages only with two robots or more seen within ``ttl`` s: a robot alone
    is not coordinated (:data:`ALONE`: its own controller, exactly as without this class),
    and when the fleet drops to one robot, that robot is let go.  A robot not seen for
    ``ttl`` s is forgotten (its nodes freed).  Goals are named by a ``token`` (any hashable
    that changes when a goal is given again, e.g. its stamp): a robot that reached the goal
    of its current token is done (it parks on the roadmap, :class:`RoadmapCoordinator`)
    until its token changes."""

    def __init__(self, coordinator: RoadmapCoordinator, ttl: float = 2.0) -> None:
        if coordinator.n:
            raise NavigationError("FleetCoordinator takes a coordinator with no robots yet")
        self.coord = coordinator
        self.ttl = float(ttl)
        self.ids: list[str] = []  # coordinator index -> robot id
        self._index: dict[str, int] = {}  # robot id -> coordinator index
        self._p = np.zeros(0, dtype=np.complex128)  # last controlled point of each member
        self._goal = np.zeros(0, dtype=np.complex128)
        self._token: list[Hashable] = []
        self._done: list[Hashable] = []  # the token whose goal was reached (None: none)
        self._seen: dict[str, float] = {}  # robot id -> last time it was planned

    @property
    def size(self) -> int:
        """Robots being coordinated."""
        return len(self.ids)

    def plan(
        self,
        t: float,
        ids: Sequence[str],
        p: ArrayLike,
        goals: ArrayLike,
        tokens: Sequence[Hashable],
    ) -> list[Plan]:
        """The plans of robots ``ids`` (controlled points ``p``, goals ``goals`` named by
        ``tokens``) at time ``t`` (s, any monotonic clock)."""
        pp = np.asarray(p, dtype=np.complex128).reshape(-1)
        gg = np.asarray(goals, dtype=np.complex128).reshape(-1)
        for rid in ids:
            self._seen[rid] = t
        for rid in [r for r, s in self._seen.items() if t - s > self.ttl]:
            del self._seen[rid]
            if rid in self._index:
                self._remove(self._index[rid])
        if len(self._seen) < 2:  # alone: not coordinated (let go if it was)
            while self.ids:
                self._remove(len(self.ids) - 1)
            return [ALONE] * len(ids)
        idx: list[int] = []
        for k, rid in enumerate(ids):
            if rid not in self._index:
                try:
                    self.coord.add(complex(pp[k]))
                except NavigationError:
                    idx.append(-1)  # no free node: not coordinated
                    continue
                self._index[rid] = len(self.ids)
                self.ids.append(rid)
                self._p = np.append(self._p, pp[k])
                self._goal = np.append(self._goal, gg[k])
                self._token.append(tokens[k])
                self._done.append(None)
            i = self._index[rid]
            idx.append(i)
            self._p[i], self._goal[i] = pp[k], gg[k]
            if tokens[k] != self._token[i]:
                self._token[i] = tokens[k]
                self._done[i] = None
        done = np.array([d is not None and d == tk for d, tk in zip(self._done, self._token,
                                                                     strict=True)])  # fmt: skip
        drive, leg = self.coord.update(t, self._p, self._goal, done)
        out: list[Plan] = []
        for i in idx:
            if i < 0:
                out.append(ALONE)
                continue
            out.append(
                Plan(
                    ctrl=drive[i],
                    goal_leg=bool(leg[i]),
                    parked=bool(done[i]),
                    note=self.describe(i, bool(done[i])),
                    coordinated=True,
                    fallback=None if drive[i] is not None else self.coord.goal_law(i),
                )
            )
        return out

    def reached(self, rid: str) -> None:
        """Robot ``rid`` reached its goal (its own controller said so on the goal leg): it
        returns to its roadmap node and parks there until it gets a new goal."""
        if rid in self._index:
            i = self._index[rid]
            self.coord.reached(i)
            self._done[i] = self._token[i]

    def forget(self, rid: str) -> None:
        """Robot ``rid`` is gone (goal cancelled, served elsewhere): its nodes are freed."""
        self._seen.pop(rid, None)
        if rid in self._index:
            self._remove(self._index[rid])

    def _remove(self, i: int) -> None:
        self.coord.remove(i)
        del self.ids[i], self._token[i], self._done[i]
        self._index = {r: k for k, r in enumerate(self.ids)}
        self._p = np.delete(self._p, i)
        self._goal = np.delete(self._goal, i)

    def describe(self, i: int, parked: bool = False) -> str:
        """What robot ``i`` does, in words: the roadmap nodes it is at or bound for, and the
        robot it waits for (the one on or bound for its next node toward its goal)."""
        c = self.coord
        at, nxt, m = int(c.at[i]), int(c.nxt[i]), int(c.mode[i])
        if m == GOAL_LEG:
            how = {STRAIGHT: " straight (its own law made no progress)",
                   VIA_NODE: " by way of its goal node (its own law made no progress)"}.get(
                       int(c._leg_way[i]), "")  # fmt: skip
            return f"driving off the roadmap from node {at} to its goal{how}"
        if m == PARKED:
            return f"arrived; at its goal (off node {at}; leaves it when a robot needs the way)"
        if m == RETURN_LEG:
            way = c.return_ways.get(i)
            how = f" round the walls ({len(way) - 1} corners ahead)" if way else ""
            if parked:
                return f"arrived; returning to roadmap node {at}{how} to park off the goal"
            return f"joining the roadmap at node {at}{how}"
        if parked:
            return f"arrived; parked on roadmap node {nxt}"
        g = int(c.goal_node[i])
        if nxt == g and at == g:
            if i in c.excursions:
                who = self._on(c.excursions[i].nodes, i)
                return f"at node {g}, waiting for {who or 'its way to the goal'} to clear"
            if c.suspend_until[i] > c.t_tick:
                return f"at node {g}, its way to the goal blocked: waiting to try again"
            return f"at node {g}, next to its goal"
        togo = float(c.roadmap.dist[nxt, g])
        off = abs(complex(self._p[i]) - complex(c.roadmap.nodes[nxt])) if i < self._p.size else 0.0
        if nxt == at and off > c.node_tol:  # fixed until it is there (held off by the filter)
            who = self._on(frozenset({nxt}), i)
            near = f" ({who} near)" if who else ""
            return f"getting to node {nxt}, {off:.2f} m off it{near}"
        if nxt != at:
            return f"following roadmap to goal: node {at} -> {nxt}, {togo:.1f} m to go"
        nb = c.roadmap.neighbours[at]
        if nb.size:
            best = int(nb[np.argmin(c.roadmap.dist[nb, g])])
            who = self._on(frozenset({best}), i)
            if who:
                return f"waiting for {who} at node {at} (next node {best})"
        return f"waiting at node {at} ({togo:.1f} m to go along the roadmap)"

    def _on(self, nodes: frozenset[int], me: int) -> str:
        """The robots (ids) on, bound for or coming from ``nodes``, other than ``me``."""
        c = self.coord
        nn = np.fromiter(nodes, dtype=np.intp, count=len(nodes))
        hit = np.isin(c.at, nn) | np.isin(c.nxt, nn) | np.isin(c.origin, nn)
        hit[me] = False
        who = [self.ids[j] for j in np.flatnonzero(hit)[:4].tolist()]
        return ", ".join(who[:3]) + (" ..." if len(who) > 3 else "")
