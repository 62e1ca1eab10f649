"""``confnav solve WS.json [-o MAP.json] [--tol 1e-10] [--plot OUT.png]``.

Solves the conformal navigation transformation of a workspace (JSON or GeoJSON), prints the
circle domain and a diagnostics table, and optionally writes the map's coefficients (lossless
JSON that ``ConformalMap.from_json`` and the services load) and a picture.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from confnav.argtypes import output_path
from confnav.conformal.cmap import ConformalMap
from confnav.conformal.solver import AccuracyWarning, solve
from confnav.geometry import Workspace


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "solve",
        help="solve the conformal map of a workspace onto a circle domain",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("workspace", type=Path, help="workspace file (JSON or GeoJSON)")
    p.add_argument("-o", "--output", type=output_path, help="write the solved map (JSON) here")
    p.add_argument(
        "--tol",
        type=float,
        default=1e-10,
        help="accuracy of the circle domain (centres, radii; dimensionless; default 1e-10)",
    )
    p.add_argument("--plot", type=output_path, help="write a picture of the map (PNG)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _table(m: ConformalMap) -> str:
    lines = [f"{'boundary':<10} {'centre':>28} {'radius':>16}"]
    lines.append(f"{'outer':<10} {'0':>28} {1.0:>16.12f}")
    for j, (c, r) in enumerate(zip(m.centers, m.radii, strict=True)):
        lines.append(f"{'obst ' + str(j):<10} {c.real:>13.10f} {c.imag:+14.10f}i {r:>16.12f}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    ws = Workspace.load(args.workspace)

    def progress(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", AccuracyWarning)
        m = solve(ws, tol=args.tol, progress=progress)
    print(_table(m))
    print()
    print(m.diagnostics.table())
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if args.output:
        args.output.write_text(m.to_json())
        print(f"map written to {args.output} (revision {m.revision[:12]})")
    if args.plot:
        from confnav.plot.conformal import save_map_figure

        save_map_figure(m, args.plot, title=str(args.workspace))
        print(f"plot written to {args.plot}")
    return 0 if m.diagnostics.tol_met else 3
