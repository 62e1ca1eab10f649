"""What ``confnav demo`` shows and writes: robot colours as ``confnav inspect --plot`` (and the
Foxglove scene), the picture named as the run's recording, a stop's reason in the progress
(issue 26, items 10 and 11)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
from confnav.services.demo import Track, _state, demo_figure, figure_path
from matplotlib.colors import to_rgba

from confnav.recording.scene import robot_color


def test_robots_have_the_colours_of_inspect_and_the_scene() -> None:
    # given out of id order: colours follow the sorted ids, as inspect assigns them
    tracks = {
        rid: Track(rid, z, 0j, path=[z, z / 2, 0j])
        for rid, z in (("u1", 1 + 1j), ("r2", -1 + 1j), ("r1", 1 - 1j))
    }
    fig = demo_figure(tracks)
    try:
        lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
        for i, rid in enumerate(sorted(tracks)):
            assert to_rgba(lines[rid].get_color()) == to_rgba(robot_color(i)), rid
    finally:
        plt.close(fig)


def test_the_picture_follows_the_recordings_name(tmp_path: Path) -> None:
    (tmp_path / "demo.mcap").write_bytes(b"")
    (tmp_path / "demo.png").write_bytes(b"")  # the first run's picture
    second = [tmp_path / "demo.1.mcap", tmp_path / "demo.1.part001.mcap"]
    assert figure_path(tmp_path, second) == tmp_path / "demo.1.png"
    assert figure_path(tmp_path, [tmp_path / "demo.mcap"]) == tmp_path / "demo.png"
    # no recording (the recorder failed): a free name, never the first run's picture
    assert figure_path(tmp_path, []) == tmp_path / "demo.1.png"


def test_progress_says_why_a_robot_stopped() -> None:
    t = Track("r1", 0j, 1j, state="stopped", reason="missing_map")
    assert _state(t) == "stopped (missing_map)"
    assert _state(Track("r1", 0j, 1j, state="navigating", reason="ok")) == "navigating"
    assert _state(Track("r1", 0j, 1j, state="arrived", reason="arrived")) == "arrived"
    assert _state(Track("r1", 0j, 1j, state="idle", reason="invalid_input")) == (
        "idle (invalid_input)"
    )
