"""Make the golden recordings of tests/data (and the synthetic runs the replay tests use).

Run from the repository root::

    python tests/data/make_golden.py            # rewrites tests/data/*.mcap

``run_pipeline`` runs the real services (transform, controller, simulator, recorder) of
``confnav.services`` in one process on an in-memory bus (the same service code the demo runs
over Zenoh), drives robots to their goals and records everything, Foxglove scene channels
included, into an MCAP file:

- ``solver="real"``: the transform service solves the workspace with the core solver
  (``confnav.conformal.solver.solve``), the controller loads it with ``ConformalMap.from_dict``;
- ``solver="fake"``: a stand-in map for fast tests (tests/conftest.py ``fake_solve`` and
  ``identity_loader``: the workspace's obstacles become small disks of a circle domain and the
  map is the identity), so no solve is needed.

Golden files (keep them small, < 1 MB in total):

- ``golden_square.mcap``: square room [-0.7, 0.7]^2 with one square hole, two robots, the
  real solver and the default harmonic navigation function, gain 1, v_max 0.3 m/s;
- ``golden_square_kr.mcap``: the same with the Koditschek-Rimon function (automatic k),
  gain 0.5.

The recordings are time-dependent (wall-clock log times, thread scheduling), so a regenerated
file differs byte-wise from the committed one; what the tests check (``replay --check`` passes,
message structure, arrival) holds for any run.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

DEFAULT_ROBOTS: tuple[tuple[str, float, float], ...] = (("r1", 0.5, -0.4), ("r2", -0.5, 0.45))


def run_pipeline(
    path: str | Path,
    *,
    solver: str = "fake",
    robots: Sequence[tuple[str, float, float]] = DEFAULT_ROBOTS,
    goal: tuple[float, float] = (0.0, 0.0),
    holes: Sequence[tuple[float, float]] = ((0.3, 0.3),),
    gain: float = 1.0,
    v_max: float = 0.3,
    navfn: str = "harmonic",
    time_scale: float = 4.0,
    rate_hz: float = 50.0,
    timeout: float = 60.0,
    foxglove: bool = True,
    pose_batch: bool = False,
) -> dict[str, Any]:
    """Run the services on an in-memory bus until every robot arrived; record to ``path``.

    Returns ``{"robots": {id: (state, reason)}, "wall_time": s}``. Raises ``TimeoutError``
    if some robot has not arrived within ``timeout`` seconds.
    """
    from confnav.schemas import Goal, encode
    from confnav.services import navigation
    from confnav.services.bus import InMemoryNetwork
    from confnav.services.controller import ControllerService
    from confnav.services.keys import Keys
    from confnav.services.recorder import Recorder
    from confnav.services.simulator import SimulatorService
    from confnav.services.transform import TransformService, solve_definition
    from conftest import fake_solve, identity_loader, square_definition  # tests/conftest.py

    if solver not in ("fake", "real"):
        raise ValueError("solver must be 'fake' or 'real'")
    net = InMemoryNetwork()
    keys = Keys()
    t0 = time.monotonic()
    rec = Recorder(
        net.bus("recorder"),
        keys,
        path,
        {"pipeline": "tests/data/make_golden.py", "solver": solver},
        foxglove=foxglove,
        health_period=0,
    )
    transform = TransformService(
        net.bus("transform"),
        keys,
        executor="thread",
        workers=1,
        solve_fn=fake_solve if solver == "fake" else solve_definition,
        health_period=0,
    )
    controller = ControllerService(
        net.bus("controller"),
        keys,
        map_loader=identity_loader if solver == "fake" else navigation.load_map,
        health_period=0,
    )
    sim = SimulatorService(
        net.bus("simulator"),
        keys,
        robots=[(rid, "w1", x, y) for rid, x, y in robots],
        rate_hz=rate_hz,
        time_scale=time_scale,
        health_period=0,
        pose_batch=pose_batch,  # one PoseBatch per step, answered with a CommandBatch
    )
    services = [rec, transform, controller]
    try:
        for s in services:
            s.start()
        pub = net.bus("operator")
        pub.publish(keys.ws("w1", "definition"), encode(square_definition("w1", list(holes))))
        deadline = time.monotonic() + timeout
        while not transform.solved.is_set():
            if time.monotonic() > deadline:
                raise TimeoutError("the transform service did not solve the workspace")
            time.sleep(0.01)
        # wait until the controller has the map before the robots start moving
        while "w1" not in getattr(controller, "_maps", {"w1": None}):
            if time.monotonic() > deadline:
                raise TimeoutError("the controller did not install the map")
            time.sleep(0.01)
        for rid, _x, _y in robots:
            g = Goal(robot_id=rid, ws_id="w1", goal=goal, gain=gain, v_max=v_max, navfn=navfn)
            pub.publish(keys.robot(rid, "goal"), encode(g))
        sim.start()
        services.append(sim)
        while True:
            states = {rid: controller.robot_state(rid) for rid, _x, _y in robots}
            if all(s == ("arrived", "arrived") for s in states.values()):
                break
            if time.monotonic() > deadline:
                raise TimeoutError(f"robots did not arrive: {states}")
            time.sleep(0.01)
    finally:
        for s in reversed(services):
            s.stop()
    return {"robots": states, "wall_time": time.monotonic() - t0}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", default=str(HERE))
    args = parser.parse_args(argv)
    out = Path(args.out_dir)
    # regenerating replaces the goldens on purpose (the recorder itself never overwrites)
    for name in ("golden_square.mcap", "golden_square_kr.mcap"):
        (out / name).unlink(missing_ok=True)
    result = run_pipeline(out / "golden_square.mcap", solver="real")
    print(f"golden_square.mcap: {result}")
    result = run_pipeline(out / "golden_square_kr.mcap", solver="real", navfn="kr", gain=0.5)
    print(f"golden_square_kr.mcap: {result}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
