"""confnav: provably correct navigation in polygonal workspaces by conformal maps.

The conformal navigation transformation ``T`` maps the free space of a polygonal workspace onto
a circle domain (unit disk minus disjoint disks); navigation functions on the circle domain are
pulled back through ``T`` to drive robots.
"""

from confnav.atlas import Atlas, AtlasNavigator, solve_atlas, solve_auto
from confnav.conformal.cmap import ConformalMap, SolveReport
from confnav.conformal.solver import AccuracyWarning, solve
from confnav.errors import (
    ConfnavError,
    ConvergenceError,
    CrowdingError,
    GapError,
    MapMismatchError,
    NavigationError,
    SerializationError,
    SolverError,
    UnresolvedCrowdingError,
    WorkspaceError,
)
from confnav.geometry import Workspace
from confnav.maps.footprint import UnreachableGoalError, inflate
from confnav.maps.occupancy import MapError, import_map
from confnav.navigation.control import Controller
from confnav.navigation.critical import choose_k, find_critical_points
from confnav.navigation.factory import make_navfn
from confnav.navigation.sim import simulate
from confnav.navigation.unicycle import UnicycleController, simulate_unicycle
from confnav.scenes.workspaces import default_workspace

__version__ = "0.1.0"

__all__ = [
    "AccuracyWarning",
    "Atlas",
    "AtlasNavigator",
    "ConfnavError",
    "ConformalMap",
    "Controller",
    "ConvergenceError",
    "CrowdingError",
    "GapError",
    "MapError",
    "MapMismatchError",
    "NavigationError",
    "SerializationError",
    "SolveReport",
    "SolverError",
    "UnicycleController",
    "UnreachableGoalError",
    "UnresolvedCrowdingError",
    "Workspace",
    "WorkspaceError",
    "__version__",
    "choose_k",
    "default_workspace",
    "find_critical_points",
    "import_map",
    "inflate",
    "make_navfn",
    "simulate",
    "simulate_unicycle",
    "solve",
    "solve_atlas",
    "solve_auto",
]
