"""A fleet's roadmap built in a child process (``python -m confnav.services.roadmap_worker``).

The controller service builds a fleet's roadmap the first time two robots share a map
(``services/controller_coord.py``).  The build is Python and numpy (the candidate grid,
Delaunay edges checked against the walls and the other nodes, all-pairs shortest paths; its
CPU per workspace and radius: ``bench/bench_roadmap.py``); in a thread of the controller it
holds the GIL in turns with the pose step, and each time the pose step gives the GIL up (a
Zenoh call, a lock) it waits a switch interval (5 ms) to get it back: with 200 point robots at
20 Hz, the default workspace's roadmap built in the window, the p99 was 233-658 ms with 3800-6200
of 16000 poses superseded (``bench/bench_controller.py``,
bench/results/controller_200_s19_before.json).  In a process of its own, at a
lower priority, the build shares nothing with the pose path but the machine's cores.

A fresh interpreter runs this module (not ``multiprocessing``'s spawn, which imports the
parent's ``__main__`` again: a user's script without a ``__main__`` guard would start a second
controller).  The arguments and the result go as pickles over stdin / stdout (our own child:
trusted); anything the build prints goes to stderr.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
from typing import Any

from confnav.navigation.fleet_coord import FleetRoadmap, plan_fleet_roadmap

#: the child's nice increment: the pose path's process gets the core first
BUILD_NICE = 10
#: s a build may take (a roadmap of 20,000 nodes takes about a minute)
BUILD_TIMEOUT = 300.0


class RoadmapBuildError(RuntimeError):
    """The child process failed to build the roadmap (its message, or its stderr's tail)."""


def build_in_child(
    ws: Any, rho: float, decide: bool, timeout: float = BUILD_TIMEOUT
) -> FleetRoadmap:
    """:func:`~confnav.navigation.fleet_coord.plan_fleet_roadmap` of ``(ws, rho, decide)`` in
    a child process; the caller's thread waits without the GIL.  Raises
    :class:`RoadmapBuildError` with the child's error when the build fails there (e.g. no
    point of the free space is clear enough: ``NavigationError``), ``OSError`` when no child
    can be started."""
    proc = subprocess.run(
        [sys.executable, "-m", __name__],
        input=pickle.dumps((ws, float(rho), bool(decide))),
        capture_output=True,
        timeout=timeout,
        check=False,
    )
    if proc.returncode != 0 or not proc.stdout:
        tail = proc.stderr.decode(errors="replace").strip().splitlines()[-3:]
        raise RoadmapBuildError(
            f"roadmap child exited with {proc.returncode}: {' | '.join(tail) or 'no output'}"
        )
    ok, value = pickle.loads(proc.stdout)
    if not ok:
        raise RoadmapBuildError(str(value))
    if not isinstance(value, FleetRoadmap):
        raise RoadmapBuildError(f"roadmap child sent a {type(value).__name__}")
    return value


def main() -> int:
    """The child: read ``(ws, rho, decide)``, write ``(True, FleetRoadmap)`` or ``(False,
    message)``."""
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # stray prints must not corrupt the pickle
    with contextlib.suppress(OSError):  # not allowed here: the default priority
        os.nice(BUILD_NICE)
    ws, rho, decide = pickle.load(sys.stdin.buffer)
    try:
        result: tuple[bool, Any] = (True, plan_fleet_roadmap(ws, rho, decide))
    except Exception as exc:  # said to the parent, which logs it and keeps the local rules
        result = (False, f"{type(exc).__name__}: {exc}")
    out.write(pickle.dumps(result))
    out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
