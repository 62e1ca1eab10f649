"""Regenerate a benchmark's JSON at HEAD: ``python -m bench NAME [--quick] [-- extra args]``.

Runs ``bench/bench_*.py`` of that benchmark as a child process (under ``nice``), then stamps the
JSON it wrote with its provenance: the commit (and whether the tree had uncommitted changes),
the UTC date, the machine's load average (``os.getloadavg()``) before and after, the CPU count
and the exact command. ``python -m bench --list`` lists the benchmarks with the commit their
stored results were made at ("stale" when that is not HEAD); ``--table KIND FILE [--at
COMMIT]`` prints a results file's markdown table for the docs (:mod:`bench.tables`) and
``--refresh-docs`` rewrites the docs' generated blocks from the JSON. ``--quick`` runs the
benchmark's short mode and writes ``results/NAME.quick.json``, never over the full results;
``--dry-run`` prints the command without running it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.provenance import git

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"


#: What every benchmark measures unless it says otherwise: with its own script, a change here
#: makes its results stale.
CODE_PATHS = ("confnav", "services", "schemas")
#: The conformal solver and what it reads: the code whose cost and accuracy the solver
#: benchmarks report (they import ``confnav``, whose ``__init__`` loads navigation and atlas
#: modules too, but run none of them).
SOLVER_PATHS = (
    "confnav/conformal",
    "confnav/geometry.py",
    "confnav/errors.py",
    "confnav/types.py",
    "confnav/scenes",
)
#: The solver plus the navigation functions, control law and simulation (no services, no
#: atlas): what the navigation and map-evaluation benchmarks run.
NAVIGATION_PATHS = (*SOLVER_PATHS, "confnav/navigation", "confnav/maps")


@dataclass(frozen=True)
class Bench:
    script: str
    results: str
    about: str
    args: tuple[str, ...] = ()
    quick: tuple[str, ...] = ("--quick",)
    #: Code whose change makes the results stale (besides the script itself).
    measures: tuple[str, ...] = CODE_PATHS


BENCHMARKS: dict[str, Bench] = {
    "core": Bench(
        "bench_core.py", "core.json", "solver accuracy and cost, scaling", measures=SOLVER_PATHS
    ),
    "certificate": Bench(
        "bench_core.py",
        "core_certificate.json",
        "near-touching / mirror-symmetric accuracy certificate",
        args=("--certificate",),
        quick=("--limit", "60"),
        measures=SOLVER_PATHS,
    ),
    "resolve": Bench(
        "bench_core.py",
        "core_resolve.json",
        "warm re-solves: an obstacle moved, removed, added (issue 24 item 3)",
        args=("--resolve",),
        measures=SOLVER_PATHS,
    ),
    "coarse": Bench(
        "bench_coarse.py",
        "coarse.json",
        "first (coarse, 1e-3) revision of footprint maps: CPU time and honesty (issue 23 item 2)",
        measures=(*SOLVER_PATHS, "confnav/maps", "services/definitions.py"),
    ),
    "koebe": Bench(
        "bench_koebe.py",
        "koebe.json",
        "Koebe-sweep accelerations side by side on near-touching squares (issue 24 item 1)",
        measures=SOLVER_PATHS,
    ),
    "eval": Bench(
        "bench_eval.py",
        "eval.json",
        "map evaluation and control-step costs",
        measures=NAVIGATION_PATHS,
    ),
    "scale": Bench(
        "bench_scale.py",
        "scale.json",
        "solver cost at scale: obstacles 10..100, fast vs dense sums",
        quick=("--obstacles", "5", "10"),
        measures=SOLVER_PATHS,
    ),
    "navigation": Bench(
        "bench_navigation.py",
        "navigation_defaults.json",
        "success / path ratio with the library defaults on realistic scenes",
        quick=("--starts", "20", "--only", "default", "--no-cost"),
        measures=NAVIGATION_PATHS,
    ),
    "safety": Bench(
        "bench_safety.py",
        "safety.json",
        "safety layer: wrong and coarse maps, activity on an accurate map, cost per robot",
        measures=NAVIGATION_PATHS,
    ),
    "services": Bench("bench_services.py", "services.json", "latency and CPU over real Zenoh"),
    "controller": Bench(
        "bench_controller.py",
        "controller.json",
        "controller hot path: CPU per pose and latency, 50..400 robots at 20 Hz (issue 25)",
        quick=("--robots", "100", "--seconds", "3"),
    ),
    "roadmap": Bench(
        "bench_roadmap.py",
        "roadmap_sizes.json",
        "fleet roadmap sizes and build CPU per workspace and radius (issue 25)",
    ),
    "firstmove": Bench(
        "bench_firstmove.py",
        "firstmove.json",
        "goal to first command of a robot with a body (progressive maps), services",
    ),
    "mapimport": Bench(
        "bench_mapimport.py",
        "mapimport.json",
        "occupancy-grid import of 400x400 grids",
        quick=("--runs", "1"),
        measures=("confnav/maps", "confnav/geometry.py", "confnav/errors.py", "confnav/scenes"),
    ),
    "slam": Bench(
        "bench_slam.py",
        "slam.json",
        "real SLAM maps (ROS map_server): import, first map, TurtleBot pairs (issue 23)",
    ),
    "slam_services": Bench(
        "bench_slam.py",
        "slam_services.json",
        "real SLAM maps through the service processes: goal to first command (issue 23)",
        args=("--services",),
    ),
    "atlas": Bench(
        "bench_atlas.py",
        "atlas.json",
        "atlas solve and navigation on floor plans",
        quick=("--starts", "10", "--scenario", "office"),
    ),
    "fleet": Bench(
        "bench_fleet.py",
        "fleet.json",
        "fleets: robot-robot contacts, arrival, filter cost (swaps, door, person)",
        measures=NAVIGATION_PATHS,
    ),
    "goal_leg": Bench(
        "bench_goal_leg.py",
        "fleet_goal_leg.json",
        "a goal leg on a crowded atlas chart: own law against the stalled-leg rule",
        quick=(),
    ),
    "chaos": Bench(
        "bench_chaos.py",
        "chaos.json",
        "fuzz, kill -9 and soak of the running system",
        quick=("fuzz", "--n", "100", "--queries", "20"),
    ),
}


def head() -> tuple[str, bool]:
    """(commit of HEAD, whether tracked files other than results differ from it: a result
    written by an earlier benchmark of the same session does not make the code dirty)."""
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!bench/results")
    return git("rev-parse", "HEAD"), bool(changed)


def recorded_commit(doc: Any) -> str | None:
    """The commit a results file says it was made at (its provenance, else older layouts)."""
    if not isinstance(doc, dict):
        return None
    for holder in (doc.get("provenance"), doc, doc.get("code"), doc.get("machine")):
        if isinstance(holder, dict) and isinstance(holder.get("commit"), str):
            return str(holder["commit"])
    return None


def out_path(name: str, quick: bool, out: Path | None) -> Path:
    if out is not None:
        return out
    results = BENCHMARKS[name].results
    return RESULTS / (results.replace(".json", ".quick.json") if quick else results)


def command(name: str, out: Path, quick: bool, extra: list[str]) -> list[str]:
    b = BENCHMARKS[name]
    return [
        sys.executable,
        str(HERE / b.script),
        *b.args,
        *(b.quick if quick else ()),
        "--out",
        str(out),
        *extra,
    ]


def stamp(path: Path, provenance: dict[str, Any]) -> None:
    """Add ``provenance`` to the JSON object the benchmark wrote at ``path``."""
    doc = json.loads(path.read_text())
    if not isinstance(doc, dict):
        doc = {"results": doc}
    doc["provenance"] = provenance
    path.write_text(json.dumps(doc, indent=1) + "\n")


def run(name: str, quick: bool, out: Path | None, extra: list[str], nice: int) -> int:
    target = out_path(name, quick, out)
    cmd = command(name, target, quick, extra)
    commit, dirty = head()
    load0 = list(os.getloadavg())
    t0 = time.perf_counter()
    started = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    print(
        f"bench {name}: {' '.join(cmd)}\n  commit {commit[:12]}{' (dirty)' if dirty else ''}, "
        f"load {' '.join(f'{x:.2f}' for x in load0)}",
        flush=True,
    )
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    )
    rc = subprocess.run(
        cmd, cwd=ROOT, env=env, preexec_fn=(lambda: os.nice(nice)) if nice else None
    ).returncode
    if rc != 0:
        print(f"bench {name}: exited {rc}; {target} not stamped", file=sys.stderr)
        return rc
    if not target.exists():
        print(f"bench {name}: {target} was not written", file=sys.stderr)
        return 1
    stamp(
        target,
        {
            "benchmark": name,
            "commit": commit,
            "dirty": dirty,
            "date": started,
            "loadavg_start": load0,
            "loadavg_end": list(os.getloadavg()),
            "cpu_count": os.cpu_count(),
            "wall_time_s": round(time.perf_counter() - t0, 3),
            "quick": quick,
            "command": [Path(cmd[0]).name, *cmd[1:]],
        },
    )
    print(f"bench {name}: wrote {target}")
    from bench import tables

    quoting = [
        str(p.relative_to(ROOT))
        for p in tables.doc_files()
        for _k, files, at, _b in tables.blocks(p.read_text())
        if at is None and target.name in files
    ]
    if quoting and target.resolve().parent == RESULTS:
        print(
            f"bench {name}: the docs quote {target.name} ({', '.join(sorted(set(quoting)))}): "
            "run `python -m bench --refresh-docs`"
        )
    return 0


def freshness(name: str, recorded: str, commit: str) -> str:
    """ "" if the results were made at HEAD or nothing they measure changed since, else
    " (stale: N files changed)" / " (stale: commit unknown)"."""
    if commit.startswith(recorded):
        return ""
    if not git("rev-parse", "--verify", "--quiet", f"{recorded}^{{commit}}"):
        return " (stale: commit unknown)"
    paths = [f"bench/{BENCHMARKS[name].script}", *BENCHMARKS[name].measures]
    changed = git("diff", "--name-only", recorded, commit, "--", *paths).splitlines()
    return f" (stale: {len(changed)} files changed)" if changed else " (current)"


def list_benchmarks() -> None:
    commit, _ = head()
    print(f"{'name':<12} {'results':<28} {'made at':<40} {'date':<26} about")
    for name, b in BENCHMARKS.items():
        path = RESULTS / b.results
        made, date = "-", "-"
        if path.exists():
            try:
                doc = json.loads(path.read_text())
            except ValueError:
                doc = None
            c = recorded_commit(doc)
            made = "unrecorded" if c is None else c[:12] + freshness(name, c, commit)
            prov = doc.get("provenance") if isinstance(doc, dict) else None
            date = str((prov or doc or {}).get("date", "-")) if isinstance(doc, dict) else "-"
        else:
            made = "missing"
        print(f"{name:<12} {b.results:<28} {made:<40} {date:<26} {b.about}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m bench",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        epilog="example: python -m bench mapimport --quick; python -m bench core -- --runs 1",
    )
    ap.add_argument("name", nargs="?", choices=sorted(BENCHMARKS), help="benchmark to run")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and their results")
    ap.add_argument("--quick", action="store_true", help="short mode, to NAME.quick.json")
    ap.add_argument("--out", type=Path, default=None, help="results file (default: results/)")
    ap.add_argument("--dry-run", action="store_true", help="print the command only")
    ap.add_argument("--nice", type=int, default=10, help="niceness of the benchmark process")
    ap.add_argument(
        "--table",
        nargs="+",
        metavar=("KIND", "FILE"),
        help="print the markdown table KIND (services, atlas) from bench/results/FILE ...",
    )
    ap.add_argument("--at", default=None, help="with --table: read the files at this git commit")
    ap.add_argument(
        "--refresh-docs",
        action="store_true",
        help="rewrite the generated blocks (<!-- bench:... -->) of README.md, docs/, bench/",
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []  # passed on to the benchmark
    args = ap.parse_args(argv[: len(argv) - len(extra) - (1 if "--" in argv else 0)])
    if args.list:
        list_benchmarks()
        return 0
    if args.table or args.refresh_docs:
        from bench import tables

        try:
            if args.table:
                if len(args.table) < 2:
                    ap.error("--table needs a KIND and at least one results FILE")
                print(tables.render(args.table[0], args.table[1:], args.at), end="")
            else:
                for path in tables.doc_files():
                    if tables.refresh(path):
                        print(f"refreshed {path.relative_to(ROOT)}")
        except tables.TableError as exc:
            print(f"python -m bench: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.name is None:
        ap.error("a benchmark NAME or --list is needed")
    if args.out is not None and not args.out.resolve().parent.is_dir():
        ap.error(f"no directory {str(args.out.resolve().parent)!r} for --out")
    if args.dry_run:
        target = out_path(args.name, args.quick, args.out)
        print(" ".join(command(args.name, target, args.quick, extra)))
        return 0
    return run(args.name, args.quick, args.out, extra, args.nice)


if __name__ == "__main__":
    sys.exit(main())
