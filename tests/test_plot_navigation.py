"""The circle-domain panel magnifies crowded disks in an inset that stays inside the axes and
does not cover the disks it magnifies; disks the main view shows well get no inset."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import confnav
from confnav.navigation.control import Controller
from confnav.plot.navigation import MIN_ZOOM, plot_circle_domain
from confnav.plot.style import SMALL_CIRCLE


def _square(c: complex, h: float) -> list[tuple[float, float]]:
    return [(c.real - h, c.imag - h), (c.real + h, c.imag - h), (c.real + h, c.imag + h),
            (c.real - h, c.imag + h)]  # fmt: skip


def _panel(obstacles: list[list[tuple[float, float]]]) -> tuple[Controller, plt.Axes]:
    room = [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0)]
    ws = confnav.Workspace(room, obstacles, anchor=(1.0, 1.0))
    ctl = Controller(confnav.solve(ws, 1e-6), 1.0 + 1.0j, navfn="kr")
    _fig, ax = plt.subplots()
    plot_circle_domain(ax, ctl, n_grid=60)
    return ctl, ax


def test_a_crowded_disk_gets_an_inset_inside_the_axes_away_from_it() -> None:
    # a 4 cm box 0.1 m from the lower-left corner (where a fixed inset would cover it)
    ctl, ax = _panel([_square(-1.85 - 1.85j, 0.02)])
    r = float(ctl.domain.radii[0])
    c = complex(ctl.domain.centers[0])
    assert r < SMALL_CIRCLE
    insets = ax.child_axes
    assert len(insets) == 1
    ax.figure.canvas.draw()  # positions after the equal-aspect layout
    box = ax.get_window_extent()  # pixels
    x0, y0, w, h = insets[0].get_window_extent().bounds
    assert box.x0 - 0.5 <= x0 and x0 + w <= box.x1 + 0.5  # inside the axes
    assert box.y0 - 0.5 <= y0 and y0 + h <= box.y1 + 0.5
    # the inset's corner is opposite to the disk: its centre is on the other side in x and y
    cx = (x0 + w / 2 - box.x0) / box.width * 2 - 1  # axes centre -> data [-1, 1]
    cy = (y0 + h / 2 - box.y0) / box.height * 2 - 1
    assert cx * c.real < 0 and cy * c.imag < 0
    lo, hi = insets[0].get_xlim()
    assert -1.0 - 1e-12 <= lo < c.real < hi <= 1.0 + 1e-12  # the window holds the disk
    assert 2.0 / (hi - lo) >= MIN_ZOOM
    plt.close("all")


def test_no_inset_when_the_main_view_shows_the_disks() -> None:
    # two small boxes in opposite corners: small disks, but far apart (a window holding both
    # would magnify less than MIN_ZOOM)
    ctl, ax = _panel([_square(-1.5 + 1.5j, 0.05), _square(1.5 - 1.5j, 0.05)])
    assert np.all(np.asarray(ctl.domain.radii) < SMALL_CIRCLE)
    assert ax.child_axes == []
    plt.close("all")


def test_a_robot_with_a_body_sees_the_real_walls_and_its_shrunk_free_space() -> None:
    from confnav.maps.footprint import inflate
    from confnav.plot.navigation import plot_workspace

    room = [(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)]
    ws = confnav.Workspace(room, [_square(2.0 + 1.5j, 0.4)])
    shrunk = inflate(ws, 0.3)
    ctl = Controller(confnav.solve(shrunk, 1e-6), 0.6 + 0.6j, navfn="kr")
    _fig, ax = plt.subplots()
    plot_workspace(ax, ctl, n_grid=40, walls=ws, shrink=0.3)
    x0, x1 = ax.get_xlim()
    assert x0 <= 0.0 and x1 >= 4.0  # the real room, not only the shrunk one (0.3 .. 3.7)
    dashed = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    assert len(dashed) == 2  # the shrunk outer boundary and the grown obstacle
    xs = np.concatenate([ln.get_xdata() for ln in dashed])
    assert np.isclose(xs.min(), 0.3, atol=1e-6) and np.isclose(xs.max(), 3.7, atol=1e-6)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("grown by 0.3 m" in t for t in labels)
    plt.close("all")
