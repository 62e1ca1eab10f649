"""Ordinary command-line mistakes: one error line, a non-zero exit, no traceback, and before
any long computation (output paths are checked at parse time)."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import pytest
from conftest import confnav_cmd, subprocess_env

from confnav.cli.app import build_parser
from confnav.errors import fmt_point


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        confnav_cmd(*args), capture_output=True, text=True, timeout=60, env=subprocess_env()
    )


def workspace(tmp: Path) -> str:
    from confnav.geometry import Workspace

    path = tmp / "room.json"
    Workspace([(-1, -1), (1, -1), (1, 1), (-1, 1)], [], anchor=0j).save(path)
    return str(path)


@pytest.mark.parametrize(
    "make_args",
    [
        lambda ws: ("solve", ws, "-o", "/nonexistent-dir/map.json"),
        lambda ws: ("solve", ws, "--plot", "/nonexistent-dir/map.png"),
        lambda ws: ("simulate", ws, "--goal=0,0", "--random", "2", "--json", "/nonexistent-dir/x"),
        lambda ws: ("simulate", ws, "--goal=0,0", "--random", "2", "--plot", "/nonexistent-dir/x"),
        lambda ws: ("import-map", "m.yaml", "-o", "/nonexistent-dir/ws.json"),
        lambda ws: ("atlas", ws, "--goal=0,0", "--random", "2", "--json", "/nonexistent-dir/x"),
        lambda ws: ("inspect", "x.mcap", "--plot", "/nonexistent-dir/x.png"),
        lambda ws: ("recover", "x.mcap", "-o", "/nonexistent-dir/x.mcap"),
        lambda ws: ("viz", "x.mcap", "-o", "/nonexistent-dir/x.mcap"),
        lambda ws: ("serve", "recorder", "--out", "/nonexistent-dir/x.mcap"),
    ],
)
def test_output_in_missing_directory_fails_at_parse_time(make_args, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    res = run(*make_args(workspace(tmp_path)))
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert "no directory '/nonexistent-dir'" in last
    assert time.monotonic() - t0 < 30  # nothing was solved or simulated


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--random", "-3"), "argument --random: '-3' must be at least 1"),
        (("--random", "2", "--gain", "-1"), "argument --gain: '-1' must be a finite number > 0"),
        (("--random", "2", "--v-max", "nan"), "argument --v-max: 'nan' must be a finite"),
        (("--random", "2", "--tol", "0"), "argument --tol: '0' must be a finite number > 0"),
        (("--random", "2", "--tolerance", "0"), "argument --tolerance: '0' must be a finite"),
        (("--random", "2", "--unicycle", "0.1", "--omega-max", "0"), "--omega-max: '0' must be"),
    ],
)
def test_bad_numbers_fail_before_solving(
    extra: tuple[str, ...], message: str, tmp_path: Path
) -> None:
    t0 = time.monotonic()
    res = run("simulate", workspace(tmp_path), "--goal=0,0", *extra)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert message in res.stderr.strip().splitlines()[-1]
    assert time.monotonic() - t0 < 30


def test_output_path_that_is_a_directory(tmp_path: Path) -> None:
    res = run("solve", workspace(tmp_path), "-o", str(tmp_path))
    assert res.returncode == 2
    assert "it is a directory" in res.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "cannot read manifest"),
        ("x = [", "is not valid TOML"),
        ('{"json": true}', "is not valid TOML"),
        ('[[service]]\nname = "nope"\n', "unknown service 'nope'"),
    ],
)
def test_launch_manifest_errors(content: str | None, message: str, tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    if content is not None:
        path.write_text(content)
    res = run("launch", str(path))
    assert res.returncode == 1
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert message in res.stderr


def test_points_in_errors_read_as_pairs(tmp_path: Path) -> None:
    assert fmt_point(3 + 2j) == "(3, 2)"
    assert fmt_point(complex(-0.25, 1e-7)) == "(-0.25, 1e-07)"
    res = run("simulate", workspace(tmp_path), "--goal=3,2", "--starts=0,0")
    assert res.returncode != 0
    assert "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert "(3, 2)" in last and "3+2j" not in last


def test_vmax_alias_kept_hidden() -> None:
    parser = build_parser()
    a = parser.parse_args(["simulate", "ws.json", "--goal=0,0", "--random", "1", "--vmax", "0.3"])
    b = parser.parse_args(["simulate", "ws.json", "--goal=0,0", "--random", "1", "--v-max", "0.3"])
    assert a.v_max == b.v_max == 0.3
    assert "--vmax" not in run("simulate", "--help").stdout


def _commands(parser, path: str = ""):  # type: ignore[no-untyped-def]
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                sub = f"{path} {name}".strip()
                yield sub, child
                yield from _commands(child, sub)


def test_every_command_has_an_example_and_shows_defaults() -> None:
    import argparse

    for path, p in _commands(build_parser()):
        assert p.epilog and "example" in p.epilog, path
        for action in p._actions:
            if (
                action.option_strings
                and action.help is not argparse.SUPPRESS
                and action.default not in (None, False, argparse.SUPPRESS, [])
            ):
                shown = p.formatter_class(prog=p.prog)._get_help_string(action) or ""
                assert "%(default)" in shown or "default" in shown, (path, action.dest)


UNIT = re.compile(r"(\b(m|s|m/s|rad/s|1/s|Hz|seconds|dimensionless|cells?|K|ms)\b|0\.\.1|>1:)")


def _numeric_options() -> list[tuple[str, str, str]]:
    """(command, option, help) of every visible option taking a number."""
    import argparse

    out: list[tuple[str, str, str]] = []

    def walk(parser: argparse.ArgumentParser, path: str) -> None:
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, child in a.choices.items():
                    walk(child, f"{path} {name}".strip())
            elif (
                a.option_strings
                and a.help != argparse.SUPPRESS
                and getattr(a.type, "__name__", "") in ("float", "positive_float", "_k")
            ):
                out.append((path, a.option_strings[-1], a.help or ""))

    walk(build_parser(), "")
    return out


def test_every_numeric_option_says_its_unit() -> None:
    """Help of each option taking a real number names its unit (or says it has none)."""
    missing = [(c, o, h) for c, o, h in _numeric_options() if not UNIT.search(h)]
    assert not missing, missing


@pytest.mark.parametrize(
    "make_args",
    [
        lambda ws, tmp: (
            "simulate",
            ws,
            "--map",
            f"{tmp}/missing.json",
            "--goal=0.5,0.5",
            "--starts=-0.5,-0.5",
        ),
        lambda ws, tmp: ("solve", f"{tmp}/missing.json"),
        lambda ws, tmp: ("inspect", f"{tmp}/missing.mcap"),
    ],
)
def test_missing_input_file_is_one_line(make_args, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """An OS error (here: a missing file) is caught once, at the CLI's top: one line naming
    the file and the reason, exit 1, no traceback (issue 26, item 6)."""
    res = run(*make_args(workspace(tmp_path), tmp_path))
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "missing." in lines[0] and "error:" in lines[0]
    assert "no such file" in lines[0].lower()


def test_os_error_is_caught_at_the_top(monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """Any command's OSError (not only a missing file) ends in one line and exit 1."""
    from confnav.cli import app

    def boom(args: object) -> int:
        raise PermissionError(13, "Permission denied", "/root/x.json")

    parser = app.build_parser
    monkeypatch.setattr(app, "build_parser", lambda: _with_func(parser(), boom))
    assert app.main(["schemas", "export", "out"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "confnav schemas: error: /root/x.json: Permission denied"


def _with_func(parser, func):  # type: ignore[no-untyped-def]
    parser.set_defaults(func=func)
    for action in parser._actions:
        if hasattr(action, "choices") and isinstance(action.choices, dict):
            for child in action.choices.values():
                _with_func(child, func)
    return parser
