"""Compare trajectories tables (experiment against simulation) with statistics over whole particles.

Each table after the first is compared with the first, per axis: the
ensemble MSD with bands, D with its error, the per-particle D distribution,
the van Hove step distributions and their non-Gaussian parameter alpha_2 at
several lags (compared in seconds, so frame intervals may differ), the drift
velocity, and where both tables are 3D the drift against height and the
height distribution; the number deposited against time where both tables
have a ``deposited`` or ``contact`` column. Every interval and p-value
resamples or permutes whole particles (steps within a track are
correlated); the p-values of a comparison are Holm-corrected. Each quantity
gets a verdict: consistent, differs, or insufficient (too little data: never
reported as consistent). Prints the verdict table; --json writes every
number, --report DIR writes one PNG per quantity and a self-contained
report.html (figures embedded; opens offline).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import UserError, check_positive


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("tables", nargs="+", metavar="TABLE", help="trajectories tables (.parquet or .csv, SI units); "
                   "the first is the reference")
    p.add_argument("--names", help="comma-separated labels, one per table (default: the file names)")
    p.add_argument("--json", metavar="OUT", help="write every number (and the verdicts under 'verdicts') as JSON")
    p.add_argument("--report", metavar="DIR", help="write PNG overlays and a self-contained report.html here")
    p.add_argument("--lags", help="comma-separated lag times of the van Hove functions and alpha_2, s "
                   "(default: the first, a middle and the longest common MSD lag)")
    p.add_argument("--level", type=float, default=0.05, help="family-wise error rate per comparison (Holm; default 0.05)")
    p.add_argument("--n-boot", type=int, default=400, help="particle bootstrap resamples (default 400)")
    p.add_argument("--n-perm", type=int, default=2000, help="particle permutations (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    p.add_argument("--motion-blur", default="1/6",
                   help="motion-blur R per table, comma-separated or one for all: 1/6 full-frame exposure (default), "
                        "0 instantaneous (simulated truth); used by the drift's error model only")
    p.add_argument("--min-particles", type=int, default=5,
                   help="fewer particles than this in a table make a quantity 'insufficient' (default 5)")
    p.add_argument("--field-of-view", choices=("none", "auto"), default="none",
                   help="'auto': correct D for the loss of long steps at the image edges (measured tracks)")


def _blur(text: str, n: int) -> list:
    from ..motion.tracks import check_motion_blur

    vals = []
    for s in text.split(","):
        s = s.strip()
        try:
            v = float(s.split("/")[0]) / float(s.split("/")[1]) if "/" in s else float(s)
        except (ValueError, ZeroDivisionError):
            raise UserError(f"--motion-blur {text!r} is not understood", "give numbers such as 1/6 or 0, comma-separated")
        # the one rule of R (and message), as for the numeric --motion-blur of the other commands
        vals.append(check_motion_blur(v, f"--motion-blur {s}" if "/" in s else "--motion-blur"))
    if len(vals) == 1:
        vals = vals * n
    if len(vals) != n:
        raise UserError(f"--motion-blur gives {len(vals)} values for {n} tables", "give one value or one per table")
    return vals


def run(args) -> int:
    from ..compare import compare_tables, format_table, to_json, write_report
    from ..table import read_table

    if len(args.tables) < 2:
        raise UserError("compare needs at least two tables", "give two or more trajectories tables")
    names = [s.strip() for s in args.names.split(",")] if args.names else [Path(t).name for t in args.tables]
    if len(names) != len(args.tables):
        raise UserError(f"--names gives {len(names)} labels for {len(args.tables)} tables", "give one label per table")
    if len(set(names)) != len(names):
        names = [f"{i + 1}:{n}" for i, n in enumerate(names)]
    lags = None
    if args.lags:
        try:
            lags = [check_positive("--lags", float(v)) for v in args.lags.split(",")]
        except ValueError:
            raise UserError(f"--lags {args.lags!r} is not a list of numbers", "give lag times in s, e.g. 0.1,0.4")
    # --level, --n-boot, --n-perm, --seed, --min-particles: checked by ptrack.cli against ptrack.options
    if args.report and Path(args.report).exists() and not Path(args.report).is_dir():
        raise UserError(f"--report {args.report} exists and is not a directory", "give a directory")
    blur = _blur(args.motion_blur, len(args.tables))
    tables = [read_table(t) for t in args.tables]
    res = compare_tables(tables, names, lags=lags, n_boot=args.n_boot, n_perm=args.n_perm, level=args.level,
                         seed=args.seed, motion_blur=blur, min_particles=args.min_particles,
                         field_of_view=None if args.field_of_view == "none" else "auto")
    for comp in res["comparisons"]:
        print(format_table(comp))
    if args.report:
        path = write_report(res, args.report, title="ptrack compare: " + ", ".join(names))
        print(f"wrote {path}")
    if args.json:
        to_json(res, args.json)
        print(f"wrote {args.json}")
    return 0
