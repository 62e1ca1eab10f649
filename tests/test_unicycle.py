"""Unicycle robots: the look-ahead feedback linearisation is exact (p' = u), limits keep the
direction, and from random starts and headings every robot arrives without the body touching
an obstacle (exact circle domain, T = identity, so the clearance is known in closed form)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from conftest import IdentityMap, identity_loader, square_definition, wait_for

from confnav.errors import NavigationError
from confnav.navigation.control import Controller
from confnav.navigation.unicycle import (
    UnicycleController,
    look_ahead_point,
    simulate_unicycle,
    step_exact,
    twist_from_velocity,
)

CENTERS = [0.45 + 0.1j, -0.4 + 0.35j, -0.2 - 0.45j]
RADII = [0.15, 0.12, 0.14]


def clearance(z: np.ndarray) -> np.ndarray:
    """Exact signed distance to the circle domain's boundary (unit disk minus disks)."""
    z = np.asarray(z, dtype=complex)
    d = 1.0 - np.abs(z)
    for c, r in zip(CENTERS, RADII, strict=True):
        d = np.minimum(d, np.abs(z - c) - r)
    return d


def test_linearisation_is_exact() -> None:
    rng = np.random.default_rng(1)
    z = rng.normal(size=50) + 1j * rng.normal(size=50)
    th = rng.uniform(-np.pi, np.pi, 50)
    u = rng.normal(size=50) + 1j * rng.normal(size=50)
    d = 0.2
    v, om = twist_from_velocity(u, th, d)
    # p' = x' + i d theta' e^{i theta} = (v + i d omega) e^{i theta} must equal u
    np.testing.assert_allclose((v + 1j * d * om) * np.exp(1j * th), u, rtol=1e-14, atol=1e-14)
    # and along a short exact arc the finite difference of p matches u to O(dt)
    dt = 1e-6
    z1, th1 = step_exact(z, th, v, om, dt)
    dp = (look_ahead_point(z1, th1, d) - look_ahead_point(z, th, d)) / dt
    np.testing.assert_allclose(dp, u, atol=1e-5 * np.abs(u).max())


def test_limits_scale_keeping_direction() -> None:
    rng = np.random.default_rng(2)
    u = 3 * (rng.normal(size=200) + 1j * rng.normal(size=200))
    th = rng.uniform(-np.pi, np.pi, 200)
    d, vmax, wmax = 0.1, 0.5, 1.0
    v, om = twist_from_velocity(u, th, d, vmax, wmax)
    assert np.all(np.abs(v) <= vmax * (1 + 1e-12)) and np.all(np.abs(om) <= wmax * (1 + 1e-12))
    us = (v + 1j * d * om) * np.exp(1j * th)  # the p velocity actually commanded
    # same direction as u (a positive multiple), one limit active
    np.testing.assert_allclose(np.angle(us / u), 0.0, atol=1e-12)
    active = np.isclose(np.abs(v), vmax) | np.isclose(np.abs(om), wmax)
    assert np.all(active | np.isclose(np.abs(us), np.abs(u)))


def test_exact_arc() -> None:
    # a full turn at omega = 1, v = 1 returns to the start; a quarter turn ends at (1, 1)
    z, th = step_exact(0j, 0.0, 1.0, 1.0, 2 * np.pi)
    assert abs(z) < 1e-14 and th == pytest.approx(2 * np.pi)
    z, _ = step_exact(0j, 0.0, 1.0, 1.0, np.pi / 2)
    assert abs(z - (1 + 1j)) < 1e-14


def test_random_starts_converge_without_collision() -> None:
    r, d = 0.04, 0.05
    # the map of the free space shrunk by r + d: exact for a circle domain
    scale = 1 / (1 - r - d)  # rescale so that the outer circle is the unit circle
    cmap = IdentityMap([c * scale for c in CENTERS], [(rr + r + d) * scale for rr in RADII])

    class Scaled:
        centers, radii = cmap.centers, cmap.radii

        def T_and_dT(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            w, dw = cmap.T_and_dT(np.asarray(z) * scale)
            return w, dw * scale

    goal = 0.05 + 0.55j
    ctl = Controller(Scaled(), goal, v_max=0.5, goal_tol=0.01)
    uc = UnicycleController(ctl, d, v_max=0.5, omega_max=2.0)
    rng = np.random.default_rng(7)
    z = rng.uniform(-1, 1, 400) + 1j * rng.uniform(-1, 1, 400)
    z = z[clearance(z) > r + 2 * d][:40]  # then p = z + d e^{i theta} has clearance > r + d
    th = rng.uniform(-np.pi, np.pi, z.size)
    res = simulate_unicycle(uc, z, th, clearance=clearance, radius=r, t_max=60.0)
    assert z.size == 40
    assert res.collided.sum() == 0, res.message
    assert res.success.all(), res.message
    assert np.all(res.final_distance <= 0.01 + 1e-12)
    assert res.min_clearance.min() > 0


def test_bad_parameters() -> None:
    ctl = Controller(IdentityMap([0.5 + 0j], [0.1]), -0.5 + 0j)
    with pytest.raises(NavigationError):
        UnicycleController(ctl, 0.0)
    with pytest.raises(NavigationError):
        UnicycleController(ctl, 0.1, omega_max=0.0)
    uc = UnicycleController(ctl, 0.1)
    with pytest.raises(NavigationError, match="body"):
        simulate_unicycle(uc, [0.45 + 0j], [0.0], clearance=clearance, radius=0.05)


# --------------------------------------------------------------------------------------------
# services: the controller answers unicycle goals with body twists on the footprint map, the
# simulator moves unicycles along exact arcs and collides disks (in memory)
# --------------------------------------------------------------------------------------------
def test_controller_service_sends_body_twists(mem_net: Any) -> None:
    import time

    from confnav.schemas import (
        Goal,
        Pose,
        SolveDiagnostics,
        TransformSolution,
        VelocityCommand,
        decode,
        encode,
    )
    from confnav.services.bus import QueryError
    from confnav.services.controller import ControllerService
    from confnav.services.keys import Keys

    K = Keys()
    served: list[str] = []
    sol = TransformSolution(
        ws_id="cd~r0.1",
        revision="rev1",
        definition_hash="h",
        workspace_hash="ws-cd~r0.1",
        stamp_ns=1,
        anchor=(0.0, 0.0),
        centers=[(0.4, 0.0)],
        radii=[0.15],
        diagnostics=SolveDiagnostics(
            sweeps=1, error_estimate=0, wall_time=0, tol=1e-10, boundary_residual=0, tol_met=True
        ),
        coefficients={"centers": [[0.4, 0.0]], "radii": [0.15]},
    )

    def answer(key: str, payload: bytes | None) -> list[tuple[str, bytes]]:
        ws = K.parse(key).ident
        served.append(ws)
        if ws != "cd~r0.1":
            raise QueryError(f"unknown workspace {ws!r}")
        return [(key, encode(sol))]

    tr = mem_net.bus("tr")
    tr.queryable("confnav/ws/*/transform", answer)
    tr.declare_token(K.alive("transform", tr.zid))
    ctl = ControllerService(mem_net.bus("ctl"), K, map_loader=identity_loader)
    ctl.start()
    client = mem_net.bus("client")
    cmds: list[VelocityCommand] = []
    client.subscribe(K.any_robot("cmd_vel"), lambda k, p: cmds.append(decode(VelocityCommand, p)))
    try:
        goal = Goal(
            robot_id="u1",
            ws_id="cd",
            goal=(-0.5, 0.0),
            v_max=0.5,
            robot_radius=0.05,
            drive="unicycle",
            lookahead=0.05,
            omega_max=1.5,
        )
        client.publish(K.robot("u1", "goal"), encode(goal))
        wait_for(lambda: ctl.counters["maps_installed"])
        assert "cd~r0.1" in served  # radius 0.05 + look-ahead 0.05 (and the base "cd")
        z, th = 0.2 + 0.5j, 2.0
        client.publish(
            K.robot("u1", "pose"),
            encode(
                Pose(robot_id="u1", stamp_ns=time.time_ns(), seq=1, x=z.real, y=z.imag, theta=th)
            ),
        )
        cmd = wait_for(lambda: [c for c in cmds if c.pose_seq == 1])[-1]
        assert cmd.frame == "body" and cmd.linear[1] == 0.0
        ref = UnicycleController(
            Controller(IdentityMap([0.4 + 0j], [0.15]), -0.5 + 0j, v_max=0.5, goal_tol=0.02),
            0.05,
            v_max=0.5,
            omega_max=1.5,
        )(np.array([z]), np.array([th])).u[0]
        assert abs(complex(cmd.linear[0], cmd.angular) - ref) <= 1e-12 * abs(ref)
        assert abs(cmd.angular) <= 1.5 + 1e-12 and abs(cmd.linear[0]) <= 0.5 + 1e-12
    finally:
        ctl.stop()


def test_simulator_unicycle_arcs_and_disk_collisions(mem_net: Any) -> None:
    import time

    from confnav.schemas import CollisionEvent, SpawnRequest, VelocityCommand, decode, encode
    from confnav.services.keys import Keys
    from confnav.services.simulator import SimulatorService

    K = Keys()
    sim = SimulatorService(mem_net.bus("sim"), K)
    client = mem_net.bus("client")
    hits: list[CollisionEvent] = []
    client.subscribe(K.any_robot("collision"), lambda k, p: hits.append(decode(CollisionEvent, p)))
    sim._stop.set()  # steps driven by the test
    sim.start()
    try:
        client.publish(K.ws("sq", "definition"), encode(square_definition("sq")))  # [-0.7, 0.7]^2
        for rid, x, r in (("u1", 0.0, 0.05), ("u2", 0.5, 0.15)):
            client.publish(
                K.sim("sim", "spawn"),
                encode(
                    SpawnRequest(
                        robot_id=rid,
                        ws_id="sq",
                        position=(x, 0.0),
                        theta=0.0,
                        robot_radius=r,
                        drive="unicycle",
                    )
                ),
            )
        wait_for(lambda: len(sim.positions()) == 2 and sim.health_detail()[0] == "ok")

        def send(rid: str, frame: str, lin: tuple[float, float], ang: float) -> None:
            client.publish(
                K.robot(rid, "cmd_vel"),
                encode(
                    VelocityCommand(
                        robot_id=rid, stamp_ns=time.time_ns(), linear=lin, angular=ang, frame=frame
                    )
                ),
            )

        send("u1", "world", (0.3, 0.3), 0.0)  # sideways motion: refused for a unicycle
        wait_for(lambda: sim.counters["rejected"] == 1)
        send("u1", "body", (0.5, 0.0), 1.0)
        send("u2", "body", (0.5, 0.0), 0.0)
        wait_for(lambda: sim.counters["commands"] == 2)
        for _ in range(10):
            sim.step(0.02)
        # v = 0.5, omega = 1 for 0.2 s: an arc of radius 0.5 turning by 0.2 rad
        z = sim.positions()["u1"]
        assert abs(z - 0.5 * (np.sin(0.2) + 1j * (1 - np.cos(0.2)))) < 1e-12
        # u2 (radius 0.15) at x = 0.5 moving +x: the body touches the wall x = 0.7 when the
        # axle passes 0.55, although the axle itself is still 0.15 from the wall
        wait_for(lambda: hits)
        assert [h.robot_id for h in hits] == ["u2"]
        assert -0.01 - 1e-12 <= hits[0].clearance <= 0 and hits[0].position[0] < 0.7 - 0.14
    finally:
        sim.stop()
