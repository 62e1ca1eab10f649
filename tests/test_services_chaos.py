"""Chaos and fuzz, short versions of ``bench/bench_chaos.py`` (figures in bench/results):
malformed messages on every subscribed key never crash a service and every one is counted;
a controller killed with SIGKILL mid-run: its robots stop, every robot still arrives, no
collision, the recording is complete."""

from __future__ import annotations

import importlib.util
import logging
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from confnav.services.bus import InMemoryNetwork, key_matches
from confnav.services.controller import ControllerService
from confnav.services.keys import Keys
from confnav.services.recorder import Recorder
from confnav.services.simulator import SimulatorService
from confnav.services.transform import TransformService
from conftest import REPO, fake_solve, identity_loader, wait_for

from confnav.recording.reader import Recording

K = Keys()


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_chaos", REPO / "bench" / "bench_chaos.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bench_command_line_defaults_to_every_mode() -> None:
    """``python -m bench chaos`` passes no mode: all three run (it used to exit 2, Python
    3.11's argparse checking the empty positional against its choices); a wrong mode is a
    usage error."""
    bench = _bench()
    assert bench.parse_args([]).modes == ["fuzz", "kill", "soak"]
    assert bench.parse_args(["fuzz", "--n", "5"]).modes == ["fuzz"]
    with pytest.raises(SystemExit) as exc:
        bench.parse_args(["fuzz", "bogus"])
    assert exc.value.code == 2


def test_malformed_messages_never_crash_and_are_all_counted(
    mem_net: InMemoryNetwork, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """300 malformed messages per subscribed key kind (random bytes, truncated JSON, wrong
    types, NaN, wildcard ids, huge payloads) into the four services: no handler raises, the
    health counters of each subscription count every message that reached it, and the
    recording holds every one of them."""
    bench = _bench()
    msgs, expect, topics = bench.fuzz_traffic(
        300, seed=1, verbatim=False, delivered=lambda key, sub: key_matches(sub, key)
    )
    assert {w for g, k in bench.FUZZ_KINDS for _k, _p, w in bench.malformed(g, k, 300, 1)} == {
        "random",
        "truncated",
        "wrong_types",
        "nan",
        "wild_id",
        "huge",
    }
    services: list[Any] = [
        Recorder(mem_net.bus("rec"), K, tmp_path / "fuzz.mcap", health_period=0),
        TransformService(
            mem_net.bus("tr"), K, executor="thread", solve_fn=fake_solve, health_period=0
        ),
        ControllerService(
            mem_net.bus("ctl"),
            K,
            map_loader=identity_loader,
            require_transform=False,
            health_period=0,
        ),
        SimulatorService(mem_net.bus("sim"), K, sim_id=bench.SIM_ID, robots=[], health_period=0),
    ]
    by_name = {s.name: s for s in services}
    caplog.set_level(logging.ERROR)
    for s in services:
        s.start()
    try:
        pub = mem_net.bus("fuzzer")
        for key, payload in msgs:
            pub.publish(key, payload)

        def counted() -> bool:
            return all(by_name[s].counters[c] >= n for (s, c), n in expect.items())

        wait_for(counted, timeout=60, interval=0.1)
        time.sleep(0.3)
        for (service, counter), n in expect.items():
            assert by_name[service].counters[counter] == n, (service, counter)
        wait_for(lambda: by_name["recorder"].recorded >= sum(topics.values()), timeout=30)
    finally:
        for s in reversed(services):
            s.stop()
    assert not [r for r in caplog.records if "handler failed" in r.getMessage()]
    got: dict[str, int] = {}
    with Recording(tmp_path / "fuzz.mcap") as rec:
        for m in rec.iter_messages():
            if m.topic in topics:
                got[m.topic] = got.get(m.topic, 0) + 1
    assert got == dict(topics)


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(240)
def test_controller_killed_mid_run_robots_stop_and_all_arrive(tmp_path: Path) -> None:
    """Four robots on the default workspace (real processes); the controller is killed with
    SIGKILL while they move: they stop (the simulator's command timeout), the launcher
    restarts the controller, every robot arrives, no collision, the recording is complete."""
    bench = _bench()
    result = bench.run_kill(["controller"], 1, tmp_path, time_scale=2.0, cmd_timeout=0.25)
    [run] = result["runs"]
    assert run["all_arrived"] and run["collisions"] == 0, run
    # robots stop: the last pose that moved came within 1 s of the kill (the figure against
    # the one-watchdog-period target is in bench/results/chaos.json)
    assert 0.0 < run["stop_latency_s"] < 1.0, run
    assert [r["state"] for r in result["recordings"]["controller"]] == ["complete"]
