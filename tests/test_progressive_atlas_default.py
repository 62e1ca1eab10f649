"""The progressive atlas is the services' default (issue 23 item 2, docs/SLAM.md "Progressive
atlas"): a goal in a workspace that needs an atlas (a 12 x 1 m corridor) gets its first
non-zero command while the atlas is still partial, with a transform service built with its
defaults; the remaining charts' solves are gated until that command is seen, so "before the
whole atlas is solved" is an event, not a race. The run is recorded; ``replay --check``
recomputes every command against the atlas revision installed when it was computed (partial
ones included), and ``inspect`` says when the atlas was first published. Real Zenoh (unix
socket, multicast off); waits for events."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import shapely
from confnav.schemas import AtlasIndex, Goal, RobotStatus, VelocityCommand, decode, encode
from confnav.services.controller import ControllerService
from confnav.services.keys import Keys
from confnav.services.recorder import Recorder
from confnav.services.transform import TransformService, definition_of
from conftest import HolonomicRobot, wait_for

from confnav.atlas.scenes import corridor
from confnav.recording.inspect import inspect_recording
from confnav.recording.replay_check import check_recording

K = Keys()
SCENE = corridor(12.0)


@pytest.mark.parametrize(
    ("flags", "on"),
    [([], True), (["--progressive-atlas"], True), (["--no-progressive-atlas"], False)],
)
def test_serve_transform_progressive_atlas_flags(flags: list[str], on: bool) -> None:
    """On by default; both spellings of the option stay accepted (a contract)."""
    from confnav.cli.app import build_parser

    args = build_parser().parse_args(["serve", "transform", *flags])
    assert args.progressive_atlas is on and args.progressive is True


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_first_command_before_the_atlas_is_solved_and_the_recording_replays(
    make_bus: Callable[[], Any], tmp_path: Path
) -> None:
    client = make_bus()
    lock = threading.Lock()
    indexes: list[AtlasIndex] = []
    statuses: list[RobotStatus] = []
    moved = threading.Event()  # the robot's first non-zero command
    first_move: list[VelocityCommand] = []

    tr = TransformService(make_bus(), K, executor="thread", workers=2, health_period=0.2)
    assert tr.charts.progressive  # the default: nothing asked for it
    allowed = 0
    submit = tr.submit_job

    def gated(fn: Callable[..., Any], *args: Any, **kw: Any) -> Any:
        """The first two chart jobs (one partial revision: a batch of ``workers`` charts)
        run at once; every other chart waits until the robot has moved."""
        nonlocal allowed
        if fn is tr._solve_fn:  # the workspace's single solve (it says: an atlas)
            return submit(fn, *args, **kw)
        with lock:
            free = allowed < 2
            allowed += 1
        if free:
            return submit(fn, *args, **kw)

        def later(*a: Any) -> Any:
            moved.wait(timeout=300)
            return fn(*a)

        return submit(later, *args, **kw)

    tr.submit_job = gated  # type: ignore[method-assign]

    def on_index(_key: str, payload: bytes) -> None:
        with lock:
            indexes.append(decode(AtlasIndex, payload))

    def on_cmd(_key: str, payload: bytes) -> None:
        c = decode(VelocityCommand, payload)
        if abs(complex(*c.linear)) > 0 and not moved.is_set():
            with lock:
                first_move.append(c)
            moved.set()

    def on_status(_key: str, payload: bytes) -> None:
        with lock:
            statuses.append(decode(RobotStatus, payload))

    client.subscribe(K.ws("corr", "atlas"), on_index)
    client.subscribe(K.robot("d1", "cmd_vel"), on_cmd)
    client.subscribe(K.robot("d1", "status"), on_status)
    mcap = tmp_path / "progressive.mcap"
    rec = Recorder(make_bus(), K, mcap, health_period=0)
    ctl = ControllerService(make_bus(), K, stale_after=5.0, health_period=0.2)
    rec.start()
    tr.start()
    ctl.start()
    robot: HolonomicRobot | None = None
    try:
        client.publish(K.ws("corr", "definition"), encode(definition_of("corr", SCENE.workspace)))

        def first_partial() -> AtlasIndex | None:
            with lock:
                return next((i for i in indexes if any(c.pending for c in i.cells)), None)

        partial = wait_for(first_partial, timeout=180, interval=0.1)
        solved = [c for c in partial.cells if not c.pending]
        assert solved and len(solved) < len(partial.cells)
        # the robot starts deep inside a solved cell (no other chart is coming until it moves)
        cell = shapely.Polygon(solved[0].outer)
        for o in solved[0].obstacles:
            cell = cell.difference(shapely.Polygon(o))
        core = cell.buffer(-0.15)
        p = (core if not core.is_empty else cell).representative_point()
        robot = HolonomicRobot(make_bus(), "d1", (p.x, p.y), K)
        goal = Goal(robot_id="d1", ws_id="corr", goal=(SCENE.goal.real, SCENE.goal.imag),
                    v_max=1.0, tolerance=0.05)  # fmt: skip
        client.publish(K.robot("d1", "goal"), encode(goal))

        wait_for(moved.is_set, timeout=120, interval=0.05)
        with lock:
            cmd = first_move[0]
            seen = {i.revision: i for i in indexes}
        # the first move was computed on a partial revision: the atlas was not solved then
        assert cmd.map_revision in seen and any(c.pending for c in seen[cmd.map_revision].cells)

        def arrived() -> bool:
            with lock:
                return bool(statuses) and statuses[-1].state == "arrived"

        wait_for(arrived, timeout=300, interval=0.2)
        wait_for(lambda: tr.state_of("corr") == "solved", timeout=300, interval=0.2)
        wait_for(lambda: rec.recorded > 0, timeout=10)
    finally:
        if robot is not None:
            robot.stop.set()
        ctl.stop()
        tr.stop()
        rec.stop()
    assert robot is not None
    free = SCENE.workspace.polygon
    assert all(free.contains(shapely.Point(z.real, z.imag)) for z in robot.path)

    # every published revision is recorded; replay --check recomputes the commands, each on
    # the revision (partial, coarse or final) it names
    with lock:
        published = [i.revision for i in indexes]
    summary = inspect_recording(mcap)
    hist = summary.atlas_history["corr"]
    assert hist.revisions == len(set(published)) and hist.partial >= 1
    assert hist.first_charts == len(solved) and hist.first_cells == len(partial.cells)
    assert (
        f"atlas corr: {len(summary.atlases['corr'].cells)} charts, first published after "
        f"{len(solved)} of {len(partial.cells)} charts"
    ) in summary.format()
    report = check_recording(mcap)
    assert report.ok, report.format()
    assert report.per_robot["d1"] > 20
    print(report.format())
