"""Run a grid of scene variants (--set KEY=V1,V2 ...) as dask tasks and write one summary table.

Every combination of the --set values (times --replicates seeds) is one run of
``ptrack simulate`` in its own sub-folder of --out; DIR/summary.csv and
DIR/summary.parquet hold the swept values beside the observables (SI): final
mean height, deposited fraction, mean speed, in-plane D (free Brownian scenes)
and wall time. A second sweep into the same folder skips the runs already
complete (checked against their scene and seed). See sim/sweep.py.
"""
from __future__ import annotations

import argparse
import logging
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="scene TOML file (see scenes/*.toml)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="swept scene key (section.key as in the TOML, or seed) and its values, comma-separated "
                        "TOML values (vectors as [x,y,z]); repeat for a grid")
    p.add_argument("--replicates", type=int, default=1, help="runs per grid point with distinct seeds (default 1)")
    p.add_argument("--out", default="sweep", help="sweep folder (default ./sweep)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of a running dask scheduler, tcp://HOST:PORT (default: a local cluster)")
    p.add_argument("--workers", type=int, default=None, help="threads of the local cluster (default: all cores)")
    p.add_argument("--quick", action="store_true", help="each run cut to a tenth of time.final (a fast check)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from sim.sweep import run_sweep

    # --workers, --replicates: checked by ptrack.cli against ptrack.options
    if not args.quiet:
        logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stderr)
    table = run_sweep(args.scene, args.sets, args.out, replicates=args.replicates, scheduler=args.scheduler,
                      workers=args.workers, quick=args.quick, progress=not args.quiet)
    n_skip = int(table["skipped"].sum()) if "skipped" in table else 0
    n_fail = int((table["status"] != "ok").sum())
    if not args.quiet:
        print(table.drop(columns=["folder", "skipped"], errors="ignore").to_string(index=False))
    print(f"wrote {args.out}/summary.csv and summary.parquet: {len(table)} runs ({n_skip} already done, "
          f"{n_fail} failed)", file=sys.stderr)
    return 1 if n_fail else 0
