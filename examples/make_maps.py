"""Write the example occupancy maps (ROS map_server YAML + PGM): an office and a small warehouse.

    python examples/make_maps.py [OUT_DIR]      # default: the folder of this script

Cell values follow ``map_saver``: 254 free, 0 occupied, 205 unknown (outside the walls);
resolution 0.05 m. The office has a few sensor specks next to walls (merged into them on
import) and one free-standing speck (kept as a small obstacle: an obstacle never shrinks).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

RES = 0.05
FREE, OCC, UNKNOWN = 254, 0, 205


class Canvas:
    """An occupancy image in map coordinates (metres; origin = lower-left image corner)."""

    def __init__(self, width: float, height: float, origin: tuple[float, float]) -> None:
        self.w, self.h = round(width / RES), round(height / RES)
        self.origin = origin
        self.img = np.full((self.h, self.w), UNKNOWN, dtype=np.uint8)
        jj, ii = np.meshgrid(np.arange(self.w), np.arange(self.h))
        self.x = origin[0] + (jj + 0.5) * RES
        self.y = origin[1] + (self.h - ii - 0.5) * RES

    def rect(self, x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        self.img[(self.x >= x0) & (self.x <= x1) & (self.y >= y0) & (self.y <= y1)] = value

    def disk(self, cx: float, cy: float, r: float, value: int) -> None:
        self.img[(self.x - cx) ** 2 + (self.y - cy) ** 2 <= r * r] = value

    def save(self, out: Path, name: str) -> None:
        Image.fromarray(self.img, mode="L").save(out / f"{name}.pgm")
        (out / f"{name}.yaml").write_text(
            f"image: {name}.pgm\n"
            f"resolution: {RES}\n"
            f"origin: [{self.origin[0]}, {self.origin[1]}, 0.0]\n"
            "negate: 0\n"
            "occupied_thresh: 0.65\n"
            "free_thresh: 0.196\n"
            "mode: trinary\n"
        )


def walls(c: Canvas, x0: float, y0: float, x1: float, y1: float, t: float = 0.15) -> None:
    """A walled room: occupied frame of thickness t, free inside."""
    c.rect(x0 - t, y0 - t, x1 + t, y1 + t, OCC)
    c.rect(x0, y0, x1, y1, FREE)


def office(out: Path) -> None:
    """12 x 8 m: an open-plan area with desks, two offices behind doors, a meeting table."""
    c = Canvas(12.8, 8.8, (-0.4, -0.4))
    walls(c, 0.0, 0.0, 12.0, 8.0)
    c.rect(0.0, 5.0, 12.0, 5.15, OCC)  # wall between the open area and the offices
    c.rect(2.0, 5.0, 3.2, 5.15, FREE)  # door 1
    c.rect(8.0, 5.0, 9.2, 5.15, FREE)  # door 2
    c.rect(5.9, 5.15, 6.05, 8.0, OCC)  # wall between the two offices
    for x in (1.5, 4.5, 7.5):  # desks in the open area
        c.rect(x, 2.2, x + 1.6, 3.0, OCC)
    c.rect(10.3, 0.8, 11.2, 3.8, OCC)  # cabinets along the right wall, 0.8 m off it
    c.disk(3.0, 6.8, 0.5, OCC)  # meeting table in office 1
    c.rect(9.8, 7.2, 11.6, 7.7, OCC)  # desk in office 2, 0.3 m from the wall
    for x, y in ((0.0, 1.0), (6.0, 0.0), (11.95, 6.0)):  # sensor specks touching walls
        c.rect(x, y, x + 0.05, y + 0.05, OCC)
    c.rect(6.5, 4.0, 6.55, 4.05, OCC)  # a free-standing speck (kept: never dropped by default)
    c.save(out, "office")


def warehouse(out: Path) -> None:
    """10 x 8 m: three shelf rows with 1.6 m aisles, two pillars, a loading bay."""
    c = Canvas(10.8, 8.8, (-0.4, -0.4))
    walls(c, 0.0, 0.0, 10.0, 8.0)
    for y in (1.6, 3.8, 6.0):  # shelf rows, 6 m long, 0.6 m deep
        c.rect(2.0, y, 8.0, y + 0.6, OCC)
    c.rect(0.0, 7.2, 1.0, 8.0, OCC)  # loading-bay block attached to the wall
    for x, y in ((9.0, 3.0), (9.0, 5.2)):  # pillars
        c.rect(x - 0.2, y - 0.2, x + 0.2, y + 0.2, OCC)
    c.save(out, "warehouse")


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    office(out)
    warehouse(out)
    print(f"wrote office.yaml/pgm and warehouse.yaml/pgm to {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent)
