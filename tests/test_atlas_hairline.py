"""Decomposition of free spaces with the features SLAM maps have and drawn scenes lack: a
hairline strip of free space along a wall with a pocket at its dead end (nav2's depot: a one-cell
strip along the image border), and an obstacle whose chamfered corner the cleaning's mitred
opening grows exactly onto the cut (nav2's warehouse). Both made the unshrunk map's atlas fail
(``PassageError``, ``WorkspaceError``), so a robot on it had no map at all."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon, box

from confnav.atlas import decompose
from confnav.atlas.decompose import _pieces, _pinched_holes, _unpinched
from confnav.geometry import Workspace


def _workspace(free: Polygon) -> Workspace:
    def ring(coords: object) -> list[tuple[float, float]]:
        return [(float(x), float(y)) for x, y in list(coords)[:-1]]  # type: ignore[call-overload]

    return Workspace(ring(free.exterior.coords), [ring(h.coords) for h in free.interiors])


def strip_room(pocket: float = 1.0, gap: float = 0.05) -> Workspace:
    """A 12 x 8 m room whose top 1.2 m is a wall block with a ``gap``-wide strip of free space
    above it (open at the left end, x < 0.5, closed at the right wall), and a ``pocket`` x
    ``pocket`` m room cut into the block at the strip's dead end: reached only through the
    strip, as the depot's border strip reaches its pocket."""
    top = 8.0 - gap
    block = box(0.5, top - 1.2, 12.0, top).difference(box(12.0 - pocket, top - pocket, 12.0, top))
    return _workspace(box(0, 0, 12.0, 8.0).difference(block))


@pytest.mark.parametrize("tile", [3.0, 4.0])
def test_a_pocket_behind_a_hairline_strip_is_left_out_not_fatal(tile: float) -> None:
    ws = strip_room()
    dec = decompose(ws, tile=tile)  # raised PassageError: "cells ... are cut off from the rest"
    assert dec.passage is not None  # every cell linked (it raises on a cut-off cell)
    # the pocket (1 m^2) and the strip's end, 5 cm wide, are what is left out
    pocket = box(11.0, 6.95, 12.0, 7.95)
    assert len(dec.dropped) == 1
    dropped = dec.dropped[0]
    assert dropped.contains(pocket.buffer(-1e-6))
    assert dropped.area < pocket.area + 0.05 * 12.0
    # nothing else is lost: outside the strip and the pocket every free point is covered
    strip = box(0.5, 7.95, 12.0, 8.0)
    lost = ws.polygon.difference(shapely.union_all([c.polygon for c in dec.cells]))
    assert lost.difference(strip.union(pocket)).area < 1e-6
    assert dropped.intersection(shapely.union_all([c.polygon for c in dec.cells])).area < 1e-9


@pytest.mark.parametrize("gap", [0.3, 0.4])
def test_a_strip_a_margin_fits_keeps_its_pocket(gap: float) -> None:
    """Only hairlines are left out: a strip some margin fits links the pocket's cells (the
    margin shrinks to the strip, as for a narrow door) and the cells cover everything."""
    dec = decompose(strip_room(gap=gap), tile=4.0)
    assert dec.dropped == ()
    assert dec.uncovered_area() < 1e-6  # of 96 m^2: the 1e-10 grid of the cleaning
    assert dec.passage is not None and dec.passage.depth >= dec.margin


# nav2 warehouse (3 cm cells): an obstacle with a 45-degree chamfer (its corner
# (-7.63, 7.88) -> (-7.66, 7.85)) 0.48 m below a cut; the mitred opening's chamfer reaches the
# cut exactly at the obstacle's other corner x = -7.15 (-7.66 + 0.51, 7.85 + 0.51 = 8.36)
CHAMFERED = [(-7.15, 7.49), (-7.18, 7.52), (-7.27, 7.52), (-7.27, 7.73), (-7.15, 7.73),
             (-7.15, 7.88), (-7.63, 7.88), (-7.66, 7.85), (-7.66, 7.73), (-7.54, 7.73),
             (-7.54, 7.49), (-7.66, 7.49), (-7.66, 7.34), (-7.15, 7.34)]  # fmt: skip
CORE = (-11.035272475740207, 3.7900908252467347, -7.3551816504934715, 7.47018165049347)
BAND = 0.9200227063116839


def test_a_chamfer_grown_onto_the_cut_leaves_no_hole_touching_the_cell_boundary() -> None:
    # the block whose side the enlarged tile's top (8.39) snaps onto: the cut y = 8.36
    block = [(-10.5, 8.36), (-10.06, 8.36), (-10.06, 8.7), (-10.5, 8.7)]
    ws = Workspace([(-12.5, 2.0), (-5.5, 2.0), (-5.5, 9.5), (-12.5, 9.5)], [CHAMFERED, block])
    free = ws.polygon
    walls = free.boundary.buffer(1e-9 * ws.diameter)
    vertices = np.concatenate([ws.outer, *ws.obstacles])
    pieces = _pieces(free, walls, vertices, CORE, BAND, 1e-3, 1e-10 * ws.diameter)
    assert pieces
    for p in pieces:
        assert _pinched_holes(p) == []
        assert p.bounds[3] == pytest.approx(8.36, abs=1e-6)  # cut where the test says
        _workspace(p)  # a cell's workspace: raised "must lie strictly inside the outer polygon"
    # the obstacle is still a hole of its piece, strictly inside it
    held = [p for p in pieces if any(Polygon(h).contains(Polygon(CHAMFERED).buffer(-1e-6))
                                     for h in p.interiors)]  # fmt: skip
    assert len(held) == 1


# nav2 warehouse, a split tile's piece: the cleaning's cut ran through the corner (-6.85, 23.42)
# of a one-cell obstacle (3 cm), which then touched the piece's outer ring there
SPECK = shapely.from_wkt(
    "POLYGON ((-6.85 23.63, -6.82 23.63, -6.82 23.45, -6.85 23.42, -6.94 23.33, -6.91 23.54, "
    "-6.91 23.63, -6.88 23.63, -6.88 23.48, -6.85 23.48, -6.85 23.63), "
    "(-6.85 23.45, -6.88 23.45, -6.88 23.42, -6.85 23.42, -6.85 23.45))"
)
SPECK_COMP = shapely.from_wkt(
    "POLYGON ((-6.82 23.42, -6.79 23.3, -6.64 23.3, -6.61 23.27, -6.79 23.27, -6.81125 23.1, "
    "-6.94 23.1, -6.94 23.15, -6.91 23.24, -6.91 23.3, -6.97 23.3, -6.94 23.33, -6.91 23.54, "
    "-6.91 23.63, -6.88 23.63, -6.88 23.48, -6.85 23.48, -6.85 23.63, -6.82 23.63, "
    "-6.82 23.45, -6.82 23.42), (-6.88 23.42, -6.85 23.42, -6.85 23.45, -6.88 23.45, "
    "-6.88 23.42))"
)


@pytest.mark.parametrize("notch", [0.23, 0.01])
def test_an_obstacle_corner_on_the_cleaned_boundary_gets_a_notch(notch: float) -> None:
    """Giving back cannot help (the hole is the obstacle alone): a notch at the contact joins
    the obstacle to the boundary; a piece the notch swallows whole (the warehouse's, with its
    notch of 0.23 m) is dropped ("max() arg is an empty sequence" before)."""
    assert _pinched_holes(SPECK) == [0]
    out = _unpinched(SPECK, SPECK_COMP, 1e-9, notch)
    pieces = [p for p in getattr(out, "geoms", [out]) if not p.is_empty]
    for p in pieces:
        assert isinstance(p, Polygon) and _pinched_holes(p) == []
        _workspace(p)
        assert p.within(SPECK.buffer(1e-9))
    if notch < 0.1:  # a small notch keeps most of the piece
        assert sum(p.area for p in pieces) > 0.5 * SPECK.area
