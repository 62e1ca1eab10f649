"""Atlases of conformal charts for large or corridor-rich workspaces (issue 15).

- :mod:`confnav.atlas.decompose`: overlapping, well-conditioned cells (quadtree of tiles);
- :mod:`confnav.atlas.charts`: one conformal map per cell, solved in a process pool;
  :func:`solve_auto` picks one map or an atlas;
- :mod:`confnav.atlas.compose`: sequential composition of the cells' navigation laws
  (Burridge, Rizzi, Koditschek 1999) with hysteresis switching;
- :mod:`confnav.atlas.scenes`: office floor, warehouse, spiral corridors.
"""

from confnav.atlas.charts import (
    Atlas,
    ChartRecord,
    atlas_reason,
    needs_atlas,
    solve_atlas,
    solve_auto,
)
from confnav.atlas.compose import AtlasNavigator, AtlasRun, CellPlan, overlaps, plan
from confnav.atlas.decompose import (
    Cell,
    Decomposition,
    Overlap,
    PassageError,
    bottleneck,
    decompose,
    elongation,
)

__all__ = [
    "Atlas",
    "AtlasNavigator",
    "AtlasRun",
    "Cell",
    "CellPlan",
    "ChartRecord",
    "Decomposition",
    "Overlap",
    "PassageError",
    "atlas_reason",
    "bottleneck",
    "decompose",
    "elongation",
    "needs_atlas",
    "overlaps",
    "plan",
    "solve_atlas",
    "solve_auto",
]
