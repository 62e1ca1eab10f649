"""Map evaluation and control-step costs: direct Cauchy sums, local expansions, pyfmmlib.

Measures on the default workspace (seed Sec. VI, docs/METHOD.md sec. 5), for the navigation map
the controller service uses (``for_navigation()``) and for the full solver map:

* T and T' per point for a batch of 1000 robots and for one robot: the direct barycentric
  formula (linear in the boundary nodes), the local expansions of confnav/conformal/expansion.py
  (one
  polynomial per point away from the walls, direct near them) and the pyfmmlib FMM;
* the build of the expansions (time, leaves, recorded truncation bound, coverage);
* their accuracy against the barycentric sums in extended precision;
* the control step through the public ``confnav.Controller`` API (KR k = 6 and harmonic,
  v_max saturation on, the held-command cap on) on both evaluation paths;
* 1000 robots each with its own goal: the fleet step of the controller service
  (confnav/navigation/fleet.py) against one control step per robot;
* one robot (the scalar path of ``Controller._step1``): one pose, 50 poses in turn, a pose
  next to a wall (barycentric fallback), without the hold cap, and the stages of the step.

Targets (issue 12, item 2): batch of 1000 robots <= 5 us per robot, single robot <= 50 us,
with either navigation function; met/missed is stated for wall clock and for CPU time
(``time.process_time``: leaves out waiting for a core on the shared machine). Timings are the
best of several repetitions under whatever load the machine has (/proc/loadavg recorded).

Usage: ``python bench/bench_eval.py [--quick] [--out bench/results/eval.json]``
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import datetime as dt  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import provenance  # noqa: E402  (script mode: bench/ is on sys.path)

import confnav  # noqa: E402
from confnav.conformal.cauchy import HAVE_FMM, _fmm  # noqa: E402
from confnav.conformal.cmap import ConformalMap  # noqa: E402
from confnav.navigation.control import Controller  # noqa: E402
from confnav.navigation.fleet import fleet_step  # noqa: E402
from confnav.scenes.scenarios import default_scenario, random_starts  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "eval.json"
V_MAX = 1.0
BATCH_TARGET_US = 5.0
SINGLE_TARGET_US = 50.0


def commit() -> str:
    """HEAD, with ``+dirty`` when confnav/ or bench/ have uncommitted changes."""
    dirty = provenance.git("status", "--porcelain", "--", "confnav", "bench")
    return provenance.commit() + ("+dirty" if dirty else "")


def timed(fn: Callable[[], Any], reps: int, rounds: int = 5) -> tuple[float, float]:
    """Best mean seconds per call over ``rounds`` rounds of ``reps`` calls (after a warm-up):
    (wall clock, CPU time of this process). On a loaded machine the CPU time, which leaves out
    the time spent waiting for a core, is the closer estimate of the idle figure."""
    fn()
    wall = cpu = np.inf
    for _ in range(rounds):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(reps):
            fn()
        wall = min(wall, (time.perf_counter() - t0) / reps)
        cpu = min(cpu, (time.process_time() - c0) / reps)
    return float(wall), float(cpu)


def best_time(fn: Callable[[], Any], reps: int, rounds: int = 5) -> float:
    """Wall-clock part of :func:`timed`."""
    return timed(fn, reps, rounds)[0]


def longdouble_T(m: ConformalMap, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The barycentric T and T' summed in extended precision (reference)."""
    eta = m._eta.astype(np.clongdouble)
    q = m._Q_fwd.astype(np.clongdouble)
    R = 1 / (eta[None, :] - z.astype(np.clongdouble)[:, None])
    S, S2 = R @ q, (R * R) @ q
    T = S[:, 0] / S[:, 1]
    dT = (S2[:, 0] * S[:, 1] - S[:, 0] * S2[:, 1]) / S[:, 1] ** 2
    return T.astype(np.complex128), dT.astype(np.complex128)


def fmm_T(m: ConformalMap, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T and T' from the pyfmmlib FMM (both sums, first and second order)."""
    (n1, dn), (d1, dd) = (_fmm(m._eta, m._Q_fwd[:, j], z, True) for j in range(2))
    assert dn is not None and dd is not None
    N, D = -n1, -d1
    return N / D, (dn * D - N * dd) / D**2


def evaluation_rows(name: str, m: ConformalMap, zb: np.ndarray, quick: bool) -> dict[str, Any]:
    """Costs and accuracy of T and T' on one map, direct vs expansions vs FMM."""
    reps_b, reps_1 = (5, 100) if quick else (20, 1000)
    direct = ConformalMap.from_dict(m.to_dict())  # no expansions: the direct formula
    fast = ConformalMap.from_dict(m.to_dict())
    fast._fast = True  # what for_navigation() sets
    t0 = time.perf_counter()
    fast.T_and_dT(zb[:2])  # builds the expansions
    build = time.perf_counter() - t0
    ex = fast._expansion
    assert ex is not None
    covered = ex.sums(zb)[0]
    z1 = np.asarray(zb[0])
    row: dict[str, Any] = {
        "map": name,
        "nodes": m.n_nodes,
        "expansion": {
            "build_s": build,
            "leaves": ex.stats.leaves,
            "leaves_per_level": ex.stats.leaves_per_level,
            "degree": ex.stats.degree,
            "separation": ex.stats.separation,
            "bound_sums": ex.stats.max_bound,
            "bound_derivatives": ex.stats.max_bound_derivative,
            "covered_fraction": float(covered.mean()),
            "memory_mb": ex._coef.nbytes / 1e6,
        },
        "direct_batch_us": 1e6 * best_time(lambda: direct.T_and_dT(zb), reps_b) / zb.size,
        "expansion_batch_us": 1e6 * best_time(lambda: fast.T_and_dT(zb), reps_b) / zb.size,
        "expansion_batch_nocheck_us": 1e6
        * best_time(lambda: fast.T_and_dT(zb, check=False), reps_b)
        / zb.size,
        "single_us": 1e6 * best_time(lambda: fast.T_and_dT(z1), reps_1),
        "single_nocheck_us": 1e6 * best_time(lambda: fast.T_and_dT(z1, check=False), reps_1),
    }
    if HAVE_FMM:
        row["fmm_batch_us"] = 1e6 * best_time(lambda: fmm_T(m, zb), max(2, reps_b // 4)) / zb.size
    ref, dref = longdouble_T(m, zb)
    for label, (w, dw) in (
        ("direct", direct.T_and_dT(zb)),
        ("expansion", fast.T_and_dT(zb)),
        *((("fmm", fmm_T(m, zb)),) if HAVE_FMM else ()),
    ):
        c = covered
        row[f"{label}_err_T"] = float(np.max(np.abs(w[c] - ref[c])))
        row[f"{label}_err_dT_rel"] = float(np.max(np.abs(dw[c] - dref[c]) / np.abs(dref[c])))
    return row


def control_rows(
    m: ConformalMap, zb: np.ndarray, goal: complex, quick: bool
) -> list[dict[str, Any]]:
    """The control step through the public Controller API, on both evaluation paths."""
    reps_b, reps_1 = (5, 100) if quick else (20, 500)
    direct = ConformalMap.from_dict(m.to_dict())
    fast = ConformalMap.from_dict(m.to_dict())
    fast._fast = True
    fast.T_and_dT(zb[:2])
    z1 = np.asarray(zb[0])
    rows = []
    wb = fast.T_and_dT(zb)[0]
    for navfn in ("kr", "harmonic"):
        for label, cm in (("direct", direct), ("expansion", fast)):
            ctl = Controller(cm, goal, navfn=navfn, k=6, v_max=V_MAX)
            step_b = partial(ctl, zb)
            step_1 = partial(ctl, z1)
            eval_b = partial(cm.T_and_dT, zb)
            nav_b = partial(ctl.navfn.value_and_gradient, wb)
            tb, t1 = timed(step_b, reps_b), timed(step_1, reps_1)
            row: dict[str, Any] = {
                "navfn": navfn,
                "evaluation": label,
                "hold_time": ctl.hold_time,
                "batch1000_per_robot_us": 1e6 * tb[0] / zb.size,
                "batch1000_per_robot_cpu_us": 1e6 * tb[1] / zb.size,
                "single_us": 1e6 * t1[0],
                "single_cpu_us": 1e6 * t1[1],
                "T_and_dT_batch_per_robot_us": 1e6 * best_time(eval_b, reps_b) / zb.size,
                "navfn_batch_per_robot_us": 1e6 * best_time(nav_b, reps_b) / zb.size,
            }
            if label == "expansion":
                row.update(single_robot_rows(ctl, fast, zb, reps_1))
            rows.append(row)
    return rows


def single_robot_rows(
    ctl: Controller, m: ConformalMap, zb: np.ndarray, reps: int
) -> dict[str, Any]:
    """One robot: the step over 50 poses in turn (wall and CPU), a pose next to a wall (no
    expansion covers it: the barycentric formula), the step without the hold cap, and the
    stages of the step (CPU)."""
    ex = m._expansion
    assert ex is not None
    cov = ex.sums(zb)[0]
    poses = [np.asarray(z) for z in zb[:50]]
    it = iter(range(1 << 62))

    def cycle() -> Any:
        return ctl(poses[next(it) % len(poses)])

    wall_pose = np.asarray(zb[np.flatnonzero(~cov)[0]])
    no_hold = Controller(m, ctl.goal, navfn=ctl.navfn, v_max=V_MAX, hold_time=0.0)
    z1 = complex(zb[0])
    w1, dw1 = m.T_and_dT1(z1)
    stages = {
        "T_and_dT1": partial(m.T_and_dT1, z1),
        "navfn1": partial(ctl.navfn.value_and_gradient1, w1),
        "clearance1": partial(ctl._clearance1, z1),
        "step_from_map_values": partial(ctl._step1, z1, w1, dw1, None, ()),
    }
    out: dict[str, Any] = {}
    for key, fn in (
        ("single_50_poses", cycle),
        ("single_near_wall", partial(ctl, wall_pose)),
        ("single_no_hold", partial(no_hold, np.asarray(z1))),
    ):
        wall, cpu = timed(fn, reps)
        out[f"{key}_us"], out[f"{key}_cpu_us"] = 1e6 * wall, 1e6 * cpu
    out["single_stages_cpu_us"] = {k: 1e6 * timed(fn, reps)[1] for k, fn in stages.items()}
    return out


def fmt_table(headers: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    line = "  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))
    out = [line, "-" * len(line)]
    out += ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(out)


def fleet_rows(m: ConformalMap, zb: np.ndarray, quick: bool) -> list[dict[str, Any]]:
    """1000 robots, each with its own goal, on one map: the controller service's path (one
    ``T_and_dT`` and one clearance for all, then :func:`confnav.navigation.fleet.fleet_step`)
    against one control step per robot (``Controller.from_map_values`` in turn)."""
    reps = 3 if quick else 10
    goals = random_starts(m.workspace, zb.size, seed=17, margin=0.05)
    rows = []
    for navfn in ("kr", "harmonic"):
        base = Controller(m, goals[0], navfn=navfn, k=6, v_max=V_MAX)
        t0 = time.process_time()
        ctrls = [base] + [base.with_goal(g) for g in goals[1:]]
        build = (time.process_time() - t0) / len(ctrls)

        def fleet(ctrls: list[Controller] = ctrls) -> Any:
            w, dw = m.T_and_dT(zb)
            return fleet_step(ctrls, zb, w, dw, ctrls[0].clearance(zb))

        def one_by_one(ctrls: list[Controller] = ctrls) -> Any:
            w, dw = m.T_and_dT(zb)
            c = ctrls[0].clearance(zb)
            return [
                ct.from_map_values(zb[i : i + 1], w[i : i + 1], dw[i : i + 1], c[i : i + 1])
                for i, ct in enumerate(ctrls)
            ]

        tf, to = timed(fleet, reps, 3), timed(one_by_one, max(1, reps // 5), 3)
        rows.append(
            {
                "navfn": navfn,
                "goals": len(ctrls),
                "controller_build_cpu_ms": 1e3 * build,
                "fleet_per_robot_us": 1e6 * tf[0] / zb.size,
                "fleet_per_robot_cpu_us": 1e6 * tf[1] / zb.size,
                "one_by_one_per_robot_us": 1e6 * to[0] / zb.size,
                "one_by_one_per_robot_cpu_us": 1e6 * to[1] / zb.size,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--map", type=Path, default=None, help="a solved map JSON (else solve)")
    args = ap.parse_args(argv)
    load_start = list(os.getloadavg())
    proc_start = provenance.loadavg()
    sc = default_scenario()
    if args.map is not None:
        full = ConformalMap.from_json(args.map.read_text())
    else:
        full = confnav.solve(sc.workspace)
    nav = full.for_navigation()
    zb = random_starts(sc.workspace, 1000, seed=3, margin=0.01)
    ev = [evaluation_rows("navigation", nav, zb, args.quick)]
    ev.append(evaluation_rows("full", full, zb, args.quick))
    ctl = control_rows(nav, zb, sc.goal, args.quick)
    fl = fleet_rows(nav, zb, args.quick)

    print(f"load average at start: {load_start} (2 cores, shared; timings are not idle figures)")
    print("\nT and T' per point, default workspace, 1000 robots uniform at clearance >= 0.01:")
    print(
        fmt_table(
            [
                "map",
                "nodes",
                "direct us",
                "expans. us",
                "no-check",
                "fmm us",
                "single",
                "build s",
                "leaves",
                "covered",
                "bound T'",
                "err T'(exp)",
                "err T'(dir)",
            ],
            [
                [
                    r["map"],
                    str(r["nodes"]),
                    f"{r['direct_batch_us']:.2f}",
                    f"{r['expansion_batch_us']:.2f}",
                    f"{r['expansion_batch_nocheck_us']:.2f}",
                    f"{r.get('fmm_batch_us', float('nan')):.2f}",
                    f"{r['single_us']:.1f}",
                    f"{r['expansion']['build_s']:.2f}",
                    str(r["expansion"]["leaves"]),
                    f"{r['expansion']['covered_fraction']:.3f}",
                    f"{r['expansion']['bound_derivatives']:.1e}",
                    f"{r['expansion_err_dT_rel']:.1e}",
                    f"{r['direct_err_dT_rel']:.1e}",
                ]
                for r in ev
            ],
        )
    )
    print("\ncontrol step through confnav.Controller (navigation map, v_max = 1):")
    print(
        fmt_table(
            [
                "navfn",
                "T,T' by",
                "batch us/robot",
                "(cpu)",
                "single us",
                "(cpu)",
                "T,T' us/robot",
                "navfn us/robot",
            ],
            [
                [
                    r["navfn"],
                    r["evaluation"],
                    f"{r['batch1000_per_robot_us']:.2f}",
                    f"{r['batch1000_per_robot_cpu_us']:.2f}",
                    f"{r['single_us']:.1f}",
                    f"{r['single_cpu_us']:.1f}",
                    f"{r['T_and_dT_batch_per_robot_us']:.2f}",
                    f"{r['navfn_batch_per_robot_us']:.2f}",
                ]
                for r in ctl
            ],
        )
    )
    print("\none robot through confnav.Controller (navigation map, expansions; us):")
    print(
        fmt_table(
            [
                "navfn",
                "1 pose",
                "(cpu)",
                "50 poses",
                "(cpu)",
                "near wall",
                "(cpu)",
                "no hold cap",
                "(cpu)",
                "stages cpu: T,T'",
                "navfn",
                "clearance",
                "law",
            ],
            [
                [
                    r["navfn"],
                    f"{r['single_us']:.1f}",
                    f"{r['single_cpu_us']:.1f}",
                    f"{r['single_50_poses_us']:.1f}",
                    f"{r['single_50_poses_cpu_us']:.1f}",
                    f"{r['single_near_wall_us']:.1f}",
                    f"{r['single_near_wall_cpu_us']:.1f}",
                    f"{r['single_no_hold_us']:.1f}",
                    f"{r['single_no_hold_cpu_us']:.1f}",
                    f"{r['single_stages_cpu_us']['T_and_dT1']:.1f}",
                    f"{r['single_stages_cpu_us']['navfn1']:.1f}",
                    f"{r['single_stages_cpu_us']['clearance1']:.1f}",
                    f"{r['single_stages_cpu_us']['step_from_map_values']:.1f}",
                ]
                for r in ctl
                if r["evaluation"] == "expansion"
            ],
        )
    )
    print("\n1000 robots with 1000 different goals on the navigation map (us/robot, with T, T'):")
    print(
        fmt_table(
            ["navfn", "fleet step", "(cpu)", "one by one", "(cpu)", "build ms/goal (cpu)"],
            [
                [
                    r["navfn"],
                    f"{r['fleet_per_robot_us']:.2f}",
                    f"{r['fleet_per_robot_cpu_us']:.2f}",
                    f"{r['one_by_one_per_robot_us']:.1f}",
                    f"{r['one_by_one_per_robot_cpu_us']:.1f}",
                    f"{r['controller_build_cpu_ms']:.2f}",
                ]
                for r in fl
            ],
        )
    )
    targets = []
    for r in fl:
        targets.append(
            {
                "target": f"{r['navfn']}: batch of 1000, each its own goal, us/robot <= "
                f"{BATCH_TARGET_US:g} (wall clock)",
                "measured": r["fleet_per_robot_us"],
                "cpu_time": r["fleet_per_robot_cpu_us"],
                "met": r["fleet_per_robot_us"] <= BATCH_TARGET_US,
                "met_in_cpu_time": r["fleet_per_robot_cpu_us"] <= BATCH_TARGET_US,
            }
        )
    for r in ctl:
        if r["evaluation"] != "expansion":
            continue
        for what, val, cpu, lim in (
            (
                "batch of 1000, us/robot",
                r["batch1000_per_robot_us"],
                r["batch1000_per_robot_cpu_us"],
                BATCH_TARGET_US,
            ),
            (
                "single robot (mean over 50 poses, hold cap on), us",
                r["single_50_poses_us"],
                r["single_50_poses_cpu_us"],
                SINGLE_TARGET_US,
            ),
        ):
            targets.append(
                {
                    "target": f"{r['navfn']}: {what} <= {lim:g} (wall clock)",
                    "measured": val,
                    "cpu_time": cpu,
                    "met": val <= lim,
                    "met_in_cpu_time": cpu <= lim,
                }
            )
    acc = max(ev[0]["expansion_err_T"], ev[0]["expansion_err_dT_rel"])
    targets.append(
        {
            "target": "expansion vs exact sums <= 1e-12 (T abs, T' rel)",
            "measured": acc,
            "met": acc <= 1e-12,
        }
    )
    load_end = list(os.getloadavg())
    print("\ntargets:")
    for t in targets:
        cpu = f" (CPU time {t['cpu_time']:.3g})" if "cpu_time" in t else ""
        print(
            f"  {'met   ' if t['met'] else 'MISSED'}  {t['target']}: "
            f"measured {t['measured']:.3g}{cpu}"
        )
    print(f"load average at end: {load_end}")
    out = {
        "commit": commit(),
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "loadavg_start": load_start,
        "loadavg_end": load_end,
        "proc_loadavg_start": proc_start,
        "proc_loadavg_end": provenance.loadavg(),
        "cpu_count": os.cpu_count(),
        "quick": args.quick,
        "evaluation": ev,
        "control": ctl,
        "fleet": fl,
        "targets": targets,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
