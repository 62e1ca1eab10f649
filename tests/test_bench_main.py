"""``python -m bench``: the dispatcher lists every benchmark, builds its command, stamps the
JSON with its provenance (the benchmarks themselves are not run here: too long)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.__main__ import BENCHMARKS, head, out_path, recorded_commit, stamp  # noqa: E402


def bench(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True, timeout=60
    )


def test_list_names_every_benchmark_with_its_script() -> None:
    res = bench("--list")
    assert res.returncode == 0, res.stderr
    for name, b in BENCHMARKS.items():
        assert (ROOT / "bench" / b.script).exists(), name
        assert any(line.startswith(name + " ") for line in res.stdout.splitlines()), name


def test_dry_run_builds_the_command_and_quick_never_overwrites_full_results() -> None:
    res = bench("mapimport", "--quick", "--dry-run", "--", "--navigate")
    assert res.returncode == 0, res.stderr
    cmd = res.stdout.split()
    assert cmd[1].endswith("bench/bench_mapimport.py")
    assert cmd[2:] == ["--runs", "1", "--out", str(out_path("mapimport", True, None)), "--navigate"]
    assert out_path("core", True, None).name == "core.quick.json"
    assert out_path("core", False, None).name == "core.json"


@pytest.mark.parametrize("args", [("nope",), (), ("core", "--out", "/nonexistent-dir/x.json")])
def test_mistakes_are_one_line(args: tuple[str, ...]) -> None:
    res = bench(*args)
    assert res.returncode == 2 and "Traceback" not in res.stderr


def test_stamp_records_commit_date_and_load(tmp_path: Path) -> None:
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"rows": [1, 2], "commit": "old"}))
    commit, _dirty = head()
    stamp(path, {"commit": commit, "loadavg_start": [0.5, 0.4, 0.3]})
    doc = json.loads(path.read_text())
    assert doc["rows"] == [1, 2]
    assert recorded_commit(doc) == commit != "old"
    assert recorded_commit({"code": {"commit": "abc"}}) == "abc"
    assert recorded_commit({"rows": []}) is None


def test_results_are_stale_only_when_what_they_measure_changed() -> None:
    """A result made at an older commit is current if neither its script nor the package
    changed since, stale (with the count of changed files) otherwise."""
    import subprocess

    import bench.__main__ as bm

    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                          cwd=bm.ROOT, check=True).stdout.strip()  # fmt: skip
    assert bm.freshness("core", head, head) == ""
    assert bm.freshness("core", "0" * 40, head) == " (stale: commit unknown)"
    root = subprocess.run(["git", "rev-list", "--max-parents=0", "HEAD"], capture_output=True,
                          text=True, cwd=bm.ROOT, check=True).stdout.split()[0]  # fmt: skip
    assert bm.freshness("core", root, head).startswith(" (stale: ")


def test_solver_results_go_stale_only_with_the_solver(monkeypatch: pytest.MonkeyPatch) -> None:
    """The solver benchmarks measure the conformal solver: a change elsewhere in the package
    (navigation, services) leaves their results current, a change in the solver does not."""
    import bench.__main__ as bm

    changed = ["confnav/navigation/control.py", "services/controller.py"]

    def fake_git(*args: str) -> str:
        if args[0] == "diff":
            paths = args[args.index("--") + 1 :]
            return "\n".join(f for f in changed if any(f.startswith(p) for p in paths))
        return "x"  # rev-parse --verify: the recorded commit exists

    monkeypatch.setattr(bm, "git", fake_git)
    for name in ("core", "certificate", "scale"):
        assert bm.freshness(name, "a" * 40, "b" * 40) == " (current)"
    assert bm.freshness("services", "a" * 40, "b" * 40) == " (stale: 2 files changed)"
    changed.append("confnav/conformal/gnk.py")
    assert bm.freshness("core", "a" * 40, "b" * 40) == " (stale: 1 files changed)"


def test_a_result_written_earlier_does_not_make_the_code_dirty(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``dirty`` asks git about tracked files other than bench/results (a result of an earlier
    benchmark in the same session is not a code change)."""
    import bench.__main__ as bm

    seen: list[tuple[str, ...]] = []

    def fake_git(*args: str) -> str:
        seen.append(args)
        return "abc" if args[0] == "rev-parse" else ""

    monkeypatch.setattr(bm, "git", fake_git)
    assert bm.head() == ("abc", False)
    status = next(a for a in seen if a[0] == "status")
    assert ":!bench/results" in status


def test_pose_accounting_from_sequence_numbers() -> None:
    """bench services: every pose after the warm-up is answered, superseded (a newer pose of
    its robot was answered) or lost (no answer to it or anything newer), exactly, never
    clamped; answers in the warm-up (seq < first) do not count."""
    sys.path.insert(0, str(ROOT / "bench"))  # the benchmarks run as scripts from bench/
    from bench.bench_services import account_poses

    # robot a: 10..19 sent, answered 10, 12, 15 -> superseded 11, 13, 14; lost 16..19
    # robot b: answered 19 only -> superseded 10..18, lost none
    # robot c: nothing answered -> all 10 lost; an answer in the warm-up (seq 5) is ignored,
    # and so is a robot not played here (x)
    seen = {("a", 10), ("a", 12), ("a", 15), ("b", 19), ("c", 5), ("x", 12)}
    got = account_poses(seen, ["a", "b", "c"], 10, 20)
    assert got == {"sent": 30, "answered": 4, "superseded": 3 + 9, "lost": 4 + 0 + 10}
    assert got["answered"] + got["superseded"] + got["lost"] == got["sent"]
    # everything answered: nothing superseded or lost
    every = {(r, s) for r in "ab" for s in range(3, 8)}
    assert account_poses(every, ["a", "b"], 3, 8) == {
        "sent": 10, "answered": 10, "superseded": 0, "lost": 0
    }  # fmt: skip
