"""A progressive atlas through the real services (issue 23, docs/SLAM.md "Progressive atlas"):
the transform service with ``--progressive-atlas`` publishes a 12 x 1 m corridor's atlas (tol
1e-10, a definition's default) as its
charts come (partial revisions whose cells without a chart are ``pending``, then the complete
coarse atlas, then the atlas at the workspace's tol); the controller drives two robots on the
partial and coarse revisions and swaps them to the final one without stopping; both arrive
without a collision."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from confnav.schemas import (
    AtlasIndex,
    Goal,
    TransformStatus,
    VelocityCommand,
    WorkspaceDefinition,
    decode,
    encode,
)
from confnav.services.launcher import ServiceSpec
from conftest import RobotWatch, launched_system, wait_for
from test_atlas_services import corridor_files

from confnav.atlas.scenes import corridor

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCENE = corridor(12.0)
STARTS = {"p1": (0.5, 0.5), "p2": (1.2, 0.3)}


@pytest.mark.timeout(700)
def test_robots_drive_on_partial_atlas_revisions_and_arrive(tmp_path: Path) -> None:
    _, sim_args = corridor_files(tmp_path, STARTS)
    services = [
        # the workspace comes over the bus once the test's subscriptions are in place (a
        # file loaded at start is solved before they are routed, and Zenoh drops puts to
        # subscribers it does not know yet)
        ServiceSpec("transform", ["--progressive-atlas"]),
        ServiceSpec("controller", []),
        ServiceSpec("simulator", sim_args),
    ]
    lock = threading.Lock()
    indexes: list[AtlasIndex] = []  # in the order published
    moving: list[VelocityCommand] = []  # non-zero commands
    statuses: list[TransformStatus] = []

    def on_index(_key: str, payload: bytes) -> None:
        with lock:
            indexes.append(decode(AtlasIndex, payload))

    def on_cmd(_key: str, payload: bytes) -> None:
        cmd = decode(VelocityCommand, payload)
        if abs(cmd.linear[0]) + abs(cmd.linear[1]) > 0:
            with lock:
                moving.append(cmd)

    def on_status(_key: str, payload: bytes) -> None:
        with lock:
            statuses.append(decode(TransformStatus, payload))

    watch = RobotWatch()
    with launched_system(services, tmp_path, prefix="cnp") as system:
        bus, k = system.bus, system.keys
        watch.attach(bus, k)
        bus.subscribe(k.ws("corr", "atlas"), on_index)
        bus.subscribe(k.any_robot("cmd_vel"), on_cmd)
        bus.subscribe(k.ws("corr", "status"), on_status)
        d = SCENE.workspace.to_dict()
        defn = WorkspaceDefinition(
            ws_id="corr",
            outer=[(float(x), float(y)) for x, y in d["outer"]],
            obstacles=[[(float(x), float(y)) for x, y in o] for o in d["obstacles"]],
        )

        def solving() -> bool:  # put again until the service has it (idempotent)
            bus.publish(k.ws("corr", "definition"), encode(defn))
            with lock:
                return bool(statuses)

        wait_for(solving, timeout=30, interval=0.5)
        goal = (SCENE.goal.real, SCENE.goal.imag)
        for rid in STARTS:
            g = Goal(robot_id=rid, ws_id="corr", goal=goal, v_max=1.0, tolerance=0.05)
            bus.publish(k.robot(rid, "goal"), encode(g))

        def arrived() -> bool:
            with watch.lock:
                return all(
                    watch.status[r] and watch.status[r][-1].state == "arrived" for r in STARTS
                )

        wait_for(arrived, timeout=240, interval=0.2)

        def final() -> bool:  # the atlas at the workspace's tol (1e-10), complete
            with lock:
                return any(i.tol < 1e-3 and not any(c.pending for c in i.cells) for i in indexes)

        wait_for(final, timeout=480, interval=0.5)

        def solved() -> bool:
            with lock:
                return any(s.state == "solved" for s in statuses)

        wait_for(solved, timeout=30, interval=0.2)
        with watch.lock:
            assert watch.collisions == []
    with lock:
        revs = [i.revision for i in indexes]
        partial = [i for i in indexes if any(c.pending for c in i.cells)]
        final = indexes[-1]
        cmds = list(moving)
    # partial revisions came first: some cells pending, each with fewer pending than before
    # within one decomposition; the last revision is complete and is the solved one
    assert partial, "no partial revision was published"
    assert not any(c.pending for c in final.cells)
    assert revs.index(partial[0].revision) < revs.index(final.revision)
    assert final.tol < partial[0].tol  # the coarse rung first, then the workspace's tol
    solved_rev = next(s.revision for s in statuses if s.state == "solved")
    assert solved_rev == final.revision
    # a status said how many charts robots drive on while the atlas was solving
    said = [s.message for s in statuses if s.state == "solving"]
    assert any("charts solved" in m for m in said), said
    # robots moved on revisions before the final one (partial or coarse)
    early = {i.revision for i in indexes if i.revision != final.revision}
    assert any(c.map_revision in early for c in cmds), "no robot moved before the final atlas"
