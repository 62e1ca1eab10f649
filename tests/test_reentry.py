"""Re-entry of a reference point just outside its law's free space
(confnav/navigation/reentry.py; confnav.navigation.messages.reenter)."""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from confnav.schemas import Goal, encode
from confnav.services.definitions import workspace_of
from confnav.services.keys import Keys
from conftest import HolonomicRobot, square_definition, wait_for

from confnav.geometry import Workspace
from confnav.maps.footprint import inflate
from confnav.navigation.messages import ARRIVED, ERROR, MOVING, reenter
from confnav.navigation.reentry import REENTRY_DEPTH, REENTRY_SPEED, reentry_velocity
from confnav.navigation.unicycle import look_ahead_point, step_exact

K = Keys()
SQUARE = [(-2, -2), (2, -2), (2, 2), (-2, 2)]
BOX = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]


def room() -> Workspace:
    return Workspace(SQUARE, [BOX])


def test_points_inside_deep_or_not_finite_are_left_alone() -> None:
    ws = room()
    assert reentry_velocity(ws, 1.5 + 0j) is None  # inside
    assert reentry_velocity(ws, 0j) is None  # 0.5 m inside the box: deeper than the limit
    assert reentry_velocity(ws, complex(math.nan, 0)) is None


def test_steers_along_the_normal_of_a_side_and_to_a_corner() -> None:
    ws = room()
    u, depth = reentry_velocity(ws, 0.45 + 0.1j) or (None, None)  # 0.05 m into the box's side
    assert depth == pytest.approx(0.05, abs=1e-12)
    assert u == pytest.approx(REENTRY_SPEED + 0j, abs=1e-12)  # straight out of the side
    u, depth = reentry_velocity(ws, 2.05 + 2.05j, speed=0.2) or (None, None)  # outside a corner
    assert depth == pytest.approx(0.05 * math.sqrt(2), abs=1e-12)
    assert u == pytest.approx(0.2 * cmath.exp(-0.75j * math.pi), abs=1e-12)  # to the corner


def _mitre_sliver_point(radius: float) -> tuple[Workspace, Workspace, complex]:
    """A point on the box's diagonal, outside the mitred shrink by ``radius`` but at more
    than ``radius`` from every wall (the sliver between the mitred and the exact shrink)."""
    ws = room()
    shrunk = inflate(ws, radius)  # mitre joins (the footprint maps' default)
    t = 0.5 + 0.9 * radius / math.sqrt(2)  # distance 0.9 r from the corner... along x and y
    p = complex(t, t) + radius * 0.15 * (1 + 1j) / math.sqrt(2)
    assert float(ws.clearance1(p)) > radius  # the body is clear of the box
    assert float(shrunk.clearance1(p)) < 0  # but the footprint map has no value there
    return ws, shrunk, p


def test_a_unicycle_in_the_mitre_sliver_drives_back_in_within_depth_over_speed() -> None:
    r, d = 0.3, 0.1
    _, shrunk, p = _mitre_sliver_point(r)
    theta = 2.0  # any heading
    z = p - d * cmath.exp(1j * theta)  # the axle, so that the look-ahead point is p
    ctrl = SimpleNamespace(
        frame="body",
        d=d,
        v_max=0.5,
        omega_max=2.0,
        controller=SimpleNamespace(safety=SimpleNamespace(workspace=shrunk)),
        stop_reason=None,
    )
    depth0 = -float(shrunk.clearance1(p))
    dt, t = 0.05, 0.0
    while True:
        u, code, note = reenter(ctrl, z.real, z.imag, theta, 7 + 7j, ERROR)
        if code == ERROR:
            break
        assert code == MOVING and note.startswith("re-entering the map's free space")
        zz, th = step_exact(np.array([z]), np.array([theta]), u.real, u.imag, dt)
        z, theta, t = complex(zz[0]), float(th[0]), t + dt
        assert t < 10, "no progress"
    p_end = complex(look_ahead_point(z, theta, d))
    assert float(shrunk.clearance1(p_end)) >= -1e-9  # back in (then the map answers)
    assert t <= depth0 / REENTRY_SPEED + dt + 1e-9


def test_other_outputs_and_stops_with_a_reason_are_unchanged() -> None:
    _, shrunk, p = _mitre_sliver_point(0.3)
    ctrl = SimpleNamespace(safety=SimpleNamespace(workspace=shrunk), stop_reason=None)
    assert reenter(ctrl, p.real, p.imag, 0.0, 0.3j, MOVING) == (0.3j, MOVING, "")
    assert reenter(ctrl, p.real, p.imag, 0.0, 0j, ARRIVED) == (0j, ARRIVED, "")
    u, code, _ = reenter(ctrl, p.real, p.imag, 0.0, 0j, ERROR)  # a point robot: velocity
    assert code == MOVING and abs(u) == pytest.approx(REENTRY_SPEED)
    cut = SimpleNamespace(
        safety=SimpleNamespace(workspace=shrunk), stop_reason=("unreachable", "x")
    )
    assert reenter(cut, p.real, p.imag, 0.0, 0j, ERROR) == (0j, ERROR, "")
    deep = 0.0 + 0.0j  # inside the box: a collision, not a sliver
    assert reenter(ctrl, deep.real, deep.imag, 0.0, 0j, ERROR) == (0j, ERROR, "")
    assert REENTRY_DEPTH < 0.5


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_a_robot_in_the_mitre_sliver_of_its_footprint_map_re_enters_and_arrives(
    make_bus: Callable[[], Any],
) -> None:
    """Real services (transform and controller over Zenoh): a robot with a 0.1 m body starts
    on the diagonal of an obstacle's corner, 0.105 m from it (body clear) but outside the
    mitred footprint map ``sq~r0.1``. It is steered back in ("re-entering" in its status),
    never closer than its radius to a wall, and arrives; before re-entry it was stopped
    (``outside_workspace``) for good."""
    from test_firstmove import _Statuses, _system

    defn = square_definition("sq", [(0.0, 0.1)]).model_copy(update={"tol": 1e-6})
    corner = complex(0.05, 0.15)  # the hole's upper right corner
    start = corner + 0.105 * cmath.exp(0.25j * math.pi)
    exact = workspace_of(defn)
    assert float(exact.clearance1(start)) > 0.1
    assert float(inflate(exact, 0.1).clearance1(start)) < 0
    with _system(make_bus, defn) as (gated, tr, _ctl, client, _):
        gated.gate.set()  # the footprint map is solved at once
        statuses = _Statuses(client, "r9")
        robot = HolonomicRobot(make_bus(), "r9", (start.real, start.imag))
        try:
            goal = Goal(robot_id="r9", ws_id="sq", goal=(0.45, 0.45), robot_radius=0.1,
                        v_max=0.25, tolerance=0.03)  # fmt: skip
            client.publish(K.robot("r9", "goal"), encode(goal))
            wait_for(lambda: tr.state_of("sq~r0.1") == "solved", timeout=120)
            wait_for(lambda: statuses.all() and statuses.all()[-1].state == "arrived", timeout=120)
            seen = statuses.all()
            assert any("re-entering the map's free space" in s.message for s in seen)
            with robot.lock:
                path = np.array(robot.path)
            assert float(exact.clearance(path).min()) >= 0.1 - 1e-9
            assert abs(path[-1] - complex(0.45, 0.45)) <= 0.03 + 0.01
        finally:
            robot.stop.set()
