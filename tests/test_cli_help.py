"""Every subcommand's ``--help`` reads cleanly: a description, each default said once, no reST
markup; options that mean the same thing have the same name and default across commands;
negative points are arguments (issue 26, items 7 and 8)."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

import pytest

from confnav.cli.app import build_parser
from confnav.navigation import defaults


def _walk(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    yield " ".join(path), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _walk(child, (*path, name))


PARSERS = dict(_walk(build_parser()))
REST = re.compile(r"`|:(mod|class|func|meth|data|attr|obj|exc|ref):")


def _option_helps(parser: argparse.ArgumentParser) -> Iterator[tuple[str, str]]:
    """(option, help as printed with its default value shown as ``VALUE``) of every
    documented argument (a default value may itself be the word "default")."""
    fmt = parser._get_formatter()
    for action in parser._actions:
        if action.help in (None, argparse.SUPPRESS) or isinstance(
            action, argparse._SubParsersAction
        ):
            continue
        name = "/".join(action.option_strings) or action.dest
        template = fmt._get_help_string(action) or ""
        template = re.sub(r"%\(default\)\.0s", "", template)
        template = re.sub(r"%\(default\)[-#0 +]*\d*(\.\d+)?[sdrgf]", "VALUE", template)
        yield name, " ".join(template.split())


def test_every_command_is_walked() -> None:
    for cmd in ("launch", "goal", "status", "serve router", "atlas", "simulate", "import-map"):
        assert cmd in PARSERS


@pytest.mark.parametrize("path", sorted(p for p in PARSERS if p))
def test_help_reads_cleanly(path: str) -> None:
    parser = PARSERS[path]
    text = parser.format_help()
    assert parser.description and len(parser.description.split()) >= 2, path
    assert "description" not in text.splitlines()[0]
    assert not REST.search(text), REST.search(text)
    flat = " ".join(text.split())
    assert not re.search(r"\(default:[^)]*\) \(default:", flat)
    assert "(default: None)" not in flat
    for name, helptext in _option_helps(parser):
        said = re.findall(r"\bdefault\b", helptext)
        assert len(said) <= 1, f"{path} {name}: {helptext!r}"


def test_goal_has_the_goal_messages_unicycle_fields() -> None:
    args = PARSERS[""].parse_args(
        ["goal", "r1", "1,2", "--drive", "unicycle", "--lookahead", "0.2", "--omega-max", "1.5"]
    )
    assert (args.lookahead, args.omega_max) == (0.2, 1.5)
    # the defaults are the wire message's
    from confnav.schemas import Goal

    args = PARSERS[""].parse_args(["goal", "r1", "1,2"])
    goal = Goal(robot_id="r1", ws_id="w", goal=(1, 2))
    assert (args.lookahead, args.omega_max, args.speed_law) == (
        goal.lookahead,
        goal.omega_max,
        goal.speed_law,
    )


def test_speed_limit_is_one_option_across_commands() -> None:
    root = PARSERS[""]
    sim = root.parse_args(["simulate", "w.json", "--goal=0,0", "--random", "1"])
    atlas = root.parse_args(["atlas", "w.json", "--goal=0,0", "--random", "1"])
    assert sim.v_max == atlas.speed == defaults.V_MAX
    assert root.parse_args(["atlas", "w.json", "--goal=0,0", "--v-max", "0.3"]).speed == 0.3
    assert root.parse_args(["atlas", "w.json", "--goal=0,0", "--speed", "0.3"]).speed == 0.3


@pytest.mark.parametrize(
    "argv, dest, value",
    [
        (["goal", "r2", "-0.5,0.5"], "point", (-0.5, 0.5)),
        (["goal", "r2", "-.5,-1e-1", "--ws", "w"], "point", (-0.5, -0.1)),
        (["import-map", "m.yaml", "--keep", "-1,2", "-o", "ws.json"], "keep", None),
        (["simulate", "w.json", "--goal", "-1,0", "--starts", "-1,2;3,4"], "goal", -1 + 0j),
        (["atlas", "w.json", "--goal", "-1,-2", "--random", "2"], "goal", -1 - 2j),
    ],
)
def test_negative_points_are_arguments(argv: list[str], dest: str, value: object) -> None:
    args = PARSERS[""].parse_args(argv)
    got = getattr(args, dest)
    assert got is not None
    if value is not None:
        assert got == value


def test_options_are_still_options() -> None:
    """The widened negative-argument pattern does not swallow real options."""
    with pytest.raises(SystemExit):
        PARSERS[""].parse_args(["goal", "r2", "-v"])
    args = PARSERS[""].parse_args(["-v", "goal", "r2", "1,2"])
    assert args.verbose == 1


@pytest.mark.parametrize(
    "service", ["transform", "controller", "simulator", "recorder", "router", "ros2", "foxglove"]
)
def test_serve_runs_with_one_blas_thread(service: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A service started by hand gets one BLAS thread, as the launcher's children do; a
    count the user sets in the environment is left alone."""
    from threadpoolctl import threadpool_info

    from confnav.cli.services import _single_thread_blas

    def blas_threads(_: object = None) -> list[int]:
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    func = PARSERS[f"serve {service}"].get_default("func")
    assert func.__wrapped__ is not None  # the service's main runs inside the limit
    args = argparse.Namespace()
    seen: list[list[int]] = []
    probe = _single_thread_blas(lambda a: seen.append(blas_threads()) or 0)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    before = blas_threads()
    assert probe(args) == 0 and seen[-1] and set(seen[-1]) == {1}
    assert blas_threads() == before  # restored on return
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    assert probe(args) == 0 and seen[-1] == before  # the user's setting wins
