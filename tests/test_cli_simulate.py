"""``confnav simulate`` / ``confnav figures`` end to end (real solver, small workspaces)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from confnav.cli.app import main
from confnav.geometry import Workspace

ROOM = {
    "outer": [[-2, -2], [2, -2], [2, 2], [-2, 2]],
    "obstacles": [[[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]],
}


@pytest.fixture
def room(tmp_path: Path) -> Path:
    p = tmp_path / "room.json"
    p.write_text(json.dumps(ROOM))
    return p


def test_simulate_starts_with_negative_coordinates(room: Path, tmp_path: Path) -> None:
    out = tmp_path / "o.json"
    rc = main(
        [
            "simulate",
            str(room),
            "--goal=-1,0",
            "--starts=1.2,0.1;-1.5,-1.5;0,-1.2",
            "--navfn",
            "kr",
            "--k",
            "6",
            "--gain",
            "2",
            "--vmax",
            "0.8",
            f"--json={out}",
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    runs, summary = doc["runs"], doc["summary"]
    assert [r["start"] for r in runs] == [[1.2, 0.1], [-1.5, -1.5], [0.0, -1.2]]
    for r in runs:
        assert {"start", "success", "collided", "time", "path_length", "min_clearance",
                "final_distance"} <= set(r)  # fmt: skip
        assert r["success"] and not r["collided"] and r["min_clearance"] > 0
        assert r["final_distance"] <= 0.02 + 1e-12  # the default goal tolerance
        assert r["path_length"] >= r["shortest_path"] - 0.02 - 1e-9  # stops at 0.02 m
        # the ratio is against the shortest path into the 0.02 m goal disk: never below 1
        assert r["path_ratio"] == pytest.approx(r["path_length"] / (r["shortest_path"] - 0.02))
        assert r["path_ratio"] >= 1.0 - 1e-9
    assert summary["success_rate"] == 1.0 and summary["collisions"] == 0
    assert summary["median_path_ratio"] >= 1.0
    # from (1.2, 0.1) around the square to (-1, 0): via two corners, exact length
    a, b = np.array([1.2, 0.1]), np.array([-1.0, 0.0])
    c1, c2 = np.array([0.5, 0.5]), np.array([-0.5, 0.5])
    exact = np.linalg.norm(a - c1) + 1.0 + np.linalg.norm(c2 - b)
    assert runs[0]["shortest_path"] == pytest.approx(exact, rel=1e-12)
    assert doc["params"]["k"] == 6.0 and doc["params"]["v_max"] == 0.8


def test_simulate_random_starts_and_plot(room: Path, tmp_path: Path) -> None:
    outs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.json"
        args = ["simulate", str(room), "--goal=1.5,-1.5", "--random", "25", "--seed", "7"]
        rc = main([*args, f"--json={out}", f"--plot={tmp_path / 'p.png'}"])
        assert rc == 0
        outs.append(json.loads(out.read_text()))
    starts = np.array([r["start"] for r in outs[0]["runs"]])
    assert starts.shape == (25, 2)
    assert starts.tolist() == [r["start"] for r in outs[1]["runs"]]  # seeded
    ws = Workspace.from_dict(ROOM)
    assert np.all(ws.clearance(starts[:, 0] + 1j * starts[:, 1]) >= 0.05)
    assert outs[0]["summary"]["success_rate"] == 1.0
    assert outs[0]["params"]["navfn"] == "harmonic"  # the safe default
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_table_require_and_failures_beyond_twenty(
    room: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["simulate", str(room), "--goal=1.5,-1.5", "--random", "24", "--seed", "3"]
    # 5 s at 0.5 m/s: robots near the goal arrive, the rest time out
    slow = [*args, "--t-max", "5"]
    assert main([*slow, "--require", "0.999", f"--json={tmp_path / 's.json'}"]) == 1
    out, err = capsys.readouterr()
    doc = json.loads((tmp_path / "s.json").read_text())
    rate = doc["summary"]["success_rate"]
    assert 0 < rate < 1 and "below --require 0.999" in err
    lines = out.splitlines()
    assert lines[0].split()[:4] == ["#", "start", "[m]", "outcome"]
    assert len([ln for ln in lines if ln[:3].strip().isdigit()]) >= 20
    failed_late = [i for i, r in enumerate(doc["runs"]) if i >= 20 and not r["success"]]
    assert f"4 more robots, {len(failed_late)} of them failed" in out
    assert "time limit 5 s" in out and "timeout" in out
    assert main([*slow, "--require", repr(rate)]) == 0  # exactly at the rate: passes
    # the defaults: every robot arrives, --require 1 passes
    assert main([*args, "--require", "1"]) == 0
    assert "24 robots, harmonic" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*args, "--require", "x"])


def test_bad_input_is_a_clean_error(room: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", str(room), "--goal=0,0", "--starts=1.5,1.5"]) == 1
    assert "free space" in capsys.readouterr().err
    assert main(["simulate", str(room), "--goal=1,1.5", "--starts=0.1,0.1"]) == 1
    assert "start" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", str(room), "--goal=1,x", "--starts=1,1"])
    with pytest.raises(SystemExit):
        main(["simulate", str(room), "--goal=1,1"])  # no starts


def test_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["figures", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    for name in ("kr", "harmonic"):
        assert (tmp_path / f"navigation_{name}.png").stat().st_size > 50_000
    assert text.count("4 arrived") == 2


def test_explicit_k_that_fails_the_check_is_reported(
    room: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from confnav.navigation.control import Controller
    from confnav.navigation.critical import CriticalPoints

    spurious = CriticalPoints(
        minima=np.array([0j, 0.5 + 0.5j]),
        saddles=np.array([0.1j, 0.2j]),
        maxima=np.zeros(0, complex),
        degenerate=np.zeros(0, complex),
        n_obstacles=1,
        goal=0j,
        n_candidates=10,
    )
    monkeypatch.setattr(Controller, "check", lambda self: spurious)
    args = ["simulate", str(room), "--goal=-1,0", "--starts=1.5,0", "--navfn", "kr"]
    assert main([*args, "--k", "3"]) == 0
    err = capsys.readouterr().err
    assert "k=3 is too small" in err and "1 spurious" in err
    assert main([*args, "--k", "auto"]) == 0  # auto k is checked already: no extra check
    assert "too small" not in capsys.readouterr().err


def test_unicycle_path_ratios_are_those_of_the_steered_point(room: Path, tmp_path: Path) -> None:
    """A unicycle steers its look-ahead point to the goal; its path ratio compares that point's
    path with the shortest path from where that point starts (the axle's path ends d short
    of the goal, and its ratio was reported below 1 on an imported floor plan: 0.936)."""
    out = tmp_path / "u.json"
    args = ["simulate", str(room), "--goal=1.5,-1.5", "--random", "12", "--seed", "3"]
    assert main([*args, "--robot-radius", "0.1", "--unicycle", "0.3", f"--json={out}"]) == 0
    doc = json.loads(out.read_text())
    assert doc["summary"]["success_rate"] == 1.0
    tol = doc["params"]["goal_tol"]
    for r in doc["runs"]:
        # no path is shorter than the shortest one, up to the goal tolerance
        assert r["point_path_length"] >= r["shortest_path"] - tol - 1e-9
        assert r["path_ratio"] == pytest.approx(r["point_path_length"] / (r["shortest_path"] - tol))
        assert r["path_ratio"] >= 1.0 - 1e-9


def test_a_workspace_one_map_would_crowd_runs_as_an_atlas(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 12 m x 1 m corridor (L/w = 12, past what one map resolves) is navigated as an atlas,
    said on stderr, with the options that do not apply named."""
    from confnav.atlas.scenes import corridor

    ws_path = tmp_path / "corridor.json"
    corridor(12).workspace.save(ws_path)
    out = tmp_path / "runs.json"
    args = ["simulate", str(ws_path), "--goal=11.5,0.5", "--random", "3", f"--json={out}"]
    assert main([*args, "--plot", str(tmp_path / "p.png")]) == 0
    cap = capsys.readouterr()
    assert "too elongated for one map" in cap.err and "navigating it as an atlas" in cap.err
    assert "not used by the atlas run" not in cap.err  # --plot draws the atlas run
    assert "3 robots: 3 arrived; collisions 0" in cap.out
    assert (tmp_path / "p.png").stat().st_size > 10_000
    doc = json.loads(out.read_text())
    assert len(doc["cells"]) > 1 and [r["status"] for r in doc["runs"]] == ["arrived"] * 3


def test_a_crowding_error_raised_mid_solve_falls_back_to_the_atlas(
    room: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The a-priori test does not flag the room, the solve itself raises a crowding error (as
    the README's office with a 0.2 m unicycle did in sweep 2): simulate runs the atlas instead
    of exiting 1; ``--single-map`` keeps the error."""
    import confnav
    import confnav.cli.atlas as atlas_cli
    from confnav.errors import UnresolvedCrowdingError

    def crowded(*args: object, **kwargs: object) -> None:
        raise UnresolvedCrowdingError("points of other boundaries just outside the unit circle")

    ran: list[object] = []
    monkeypatch.setattr(confnav, "solve", crowded)
    monkeypatch.setattr(atlas_cli, "run_atlas", lambda a: ran.append(a) or 0)
    args = ["simulate", str(room), "--goal=1.5,-1.5", "--starts=-1.5,1.5"]
    assert main([*args, "--robot-radius", "0.1", "--unicycle", "0.1"]) == 0
    err = capsys.readouterr().err
    assert "one map crowds" in err and "navigating it as an atlas" in err
    assert len(ran) == 1 and ran[0].unicycle == 0.1 and ran[0].shrunk is not None  # type: ignore[attr-defined]
    assert main([*args, "--single-map"]) == 1
    assert "just outside the unit circle" in capsys.readouterr().err
    assert len(ran) == 1


def test_json_never_carries_inf_or_nan(
    room: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A value with no finite answer (no shortest path, a clearance never measured) is null in
    the JSON: the writer used to die on ``Out of range float values are not JSON compliant``."""
    from confnav.cli.jsonout import json_safe, write_json
    from confnav.navigation.shortest_path import ShortestPaths

    real = ShortestPaths.lengths

    def no_path_for_the_first(self: ShortestPaths, z: np.ndarray) -> np.ndarray:
        out = np.array(real(self, z), dtype=float)
        out[0] = np.inf
        return out

    monkeypatch.setattr(ShortestPaths, "lengths", no_path_for_the_first)
    out = tmp_path / "o.json"
    assert main(["simulate", str(room), "--goal=-1,0", "--starts=1.2,0.1;0,-1.2",
                 f"--json={out}"]) == 0  # fmt: skip
    text = out.read_text()
    assert "Infinity" not in text and "NaN" not in text
    runs = json.loads(text)["runs"]
    assert runs[0]["shortest_path"] is None and runs[0]["path_ratio"] is None
    assert runs[1]["shortest_path"] > 0 and runs[1]["path_ratio"] >= 1.0 - 1e-9
    doc = {"a": np.float64(np.inf), "b": [float("nan"), np.array([1.0, -np.inf])], "c": 2}
    assert json_safe(doc) == {"a": None, "b": [None, [1.0, None]], "c": 2}
    write_json(tmp_path / "x.json", doc)
    assert json.loads((tmp_path / "x.json").read_text())["b"] == [None, [1.0, None]]


def test_a_unicycle_whose_look_ahead_point_is_outside_is_refused_up_front(
    room: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Starts 0.055-0.074 m inside the shrunk free space (less than the look-ahead) ended as
    a robot ``error`` at t = 0 with an empty reason; now a clear error names the start, why,
    and the nearest start that works with any heading."""
    from confnav.maps.footprint import inflate

    r, d = 0.1, 0.1
    nav = inflate(Workspace.from_dict(ROOM), r + d)
    # starts 0.06 m inside the shrunk space, next to the outer wall, on all four sides
    starts = [complex(x, -2 + r + d + 0.06) for x in (-1.5, -1.0, 1.0, 1.5)]
    starts += [complex(-2 + r + d + 0.06, y) for y in (-1.0, 1.0)]
    assert np.allclose(nav.clearance(np.array(starts)), 0.06)
    text = ";".join(f"{z.real:g},{z.imag:g}" for z in starts)
    args = ["simulate", str(room), "--goal=1.5,1.5", f"--starts={text}",
            "--robot-radius", str(r), "--unicycle", str(d)]  # fmt: skip
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "look-ahead point" in err and "outside the navigable space" in err
    assert "0.06 m inside that space and needs more than 0.1 m" in err
    near = err.split("with any heading is (")[1].split(")")[0]
    zn = complex(*(float(v) for v in near.split(",")))
    assert 0.1 < float(nav.clearance(np.array([zn]))[0]) < 0.11  # just deep enough


def test_t_max_help_and_behaviour_agree(
    room: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--help`` named 10000 s while a unicycle run stopped at 1000 s."""
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "default: 10000 s, 1000 s for unicycles" in help_text
    out = tmp_path / "u.json"
    args = ["simulate", str(room), "--goal=1.5,-1.5", "--starts=-1.5,1.5",
            "--robot-radius", "0.1", "--unicycle", "0.1"]  # fmt: skip
    assert main([*args, f"--json={out}"]) == 0
    assert json.loads(out.read_text())["params"]["t_max"] == 1000.0
    assert main([*args, "--t-max", "1.5", f"--json={out}"]) == 0
    doc = json.loads(out.read_text())
    (run,) = doc["runs"]
    assert run["status"] == "timeout" and run["time"] == pytest.approx(1.5)
    assert run["reason"].startswith("time limit 1.5 s reached")


def test_a_solved_map_that_crowds_runs_as_an_atlas(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A room barred across but for a door that a 0.1 m body passes with 4 cm to spare: the
    shrunk free space solves to its tol, but the room behind the door lands on an arc of the
    unit circle 10^6.6 times shorter than its wall, where the map's absolute accuracy says
    nothing (a single map stalled the robot 0.42 m from its goal, 'at a critical point').
    ``simulate`` measures that crowding on the solved map and runs the atlas: it arrives."""
    ws_path = tmp_path / "bar.json"
    ws_path.write_text(
        json.dumps(
            {
                "outer": [[-0.7, -0.7], [0.7, -0.7], [0.7, 0.7], [-0.7, 0.7]],
                "obstacles": [[[-0.65, -0.025], [0.42, -0.025], [0.42, 0.025], [-0.65, 0.025]]],
            }
        )
    )
    args = ["simulate", str(ws_path), "--goal=0,0.45", "--starts=0,-0.45", "--robot-radius", "0.1"]
    assert main(args) == 0
    cap = capsys.readouterr()
    assert "the outer boundary crowded by 10^" in cap.err and "navigating it as an atlas" in cap.err
    assert "1 robots: 1 arrived; collisions 0" in cap.out


def test_starts_where_the_harmonic_function_is_flat_are_named() -> None:
    """Far along corridors the goal's Green's function falls below double precision: phi is 1
    to rounding and its gradient is noise (the small warehouse's far aisles: robots crawled to
    the time limit). ``_flat_starts`` names such starts (simulate then runs the atlas)."""
    from types import SimpleNamespace

    import numpy as np

    from confnav.cli.simulate import FLAT_PHI, _flat_starts

    class Law:
        def __init__(self, phi: list[float], name: str = "harmonic") -> None:
            self.navfn = SimpleNamespace(name=name)
            self.phi = np.array(phi)

        def __call__(self, z: np.ndarray) -> SimpleNamespace:
            assert z.shape == self.phi.shape
            return SimpleNamespace(phi=self.phi)

    starts = np.array([1 + 1j, 2 + 1j, 3 + 1j])
    assert _flat_starts(Law([0.5, 1 - 1e-5, 1 - 10 * FLAT_PHI]), starts) == ""
    why = _flat_starts(Law([0.5, 1.0 - 4e-16, 1.0]), starts)
    assert "flat at 2 of 3 starts" in why and "(2, 1)" in why
    # a unicycle's law wraps the point law; Koditschek-Rimon is not checked
    assert "flat at 2 of 3" in _flat_starts(
        SimpleNamespace(controller=Law([0.5, 1.0, 1.0])), starts
    )
    assert _flat_starts(Law([1.0, 1.0, 1.0], name="kr"), starts) == ""
