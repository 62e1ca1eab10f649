"""``confnav atlas``: solve a corridor as an atlas and navigate it from the command line."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest

from confnav.atlas.scenes import corridor
from confnav.cli.app import main


def test_atlas_command_navigates_a_corridor(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sc = corridor(8)
    ws_path = tmp_path / "corridor.json"
    sc.workspace.save(ws_path)
    out = tmp_path / "runs.json"
    code = main(
        ["atlas", str(ws_path), f"--goal={sc.goal.real},{sc.goal.imag}",
         "--starts=0.5,0.5;3,0.2;6,0.8", "--tol=1e-6", "--workers=1", "--json", str(out)]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0, text
    assert "3 arrived" in text
    doc = json.loads(out.read_text())
    assert len(doc["cells"]) >= 2
    assert [r["status"] for r in doc["runs"]] == ["arrived"] * 3
    # every robot's cells go down the plan's order
    ranks = [c["rank"] for c in doc["cells"]]
    for r in doc["runs"]:
        seq = [ranks[i] for i in r["cells"]]
        assert all(a > b for a, b in itertools.pairwise(seq))


def test_atlas_command_rejects_a_goal_outside(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ws_path = tmp_path / "corridor.json"
    corridor(4).workspace.save(ws_path)
    code = main(["atlas", str(ws_path), "--goal=20,20", "--tol=1e-6", "--workers=1"])
    err = capsys.readouterr().err
    assert code == 1
    assert "goal" in err and len(err.strip().splitlines()) == 1
