"""Run a simulation scene (TOML) and stream its trajectories to DIR/trajectories.parquet.

Writes DIR/trajectories.parquet (frame, t, particle, x, y, z, vx, vy, vz,
radius; SI units) and DIR/scene.json (the resolved scene, the chosen
integrator, dt and why). Free particles use the exact OU, overdamped or
trapezoidal integrator; scenes with pair forces run on the DEM engine.
Every run checkpoints (the table is committed in segments with each
checkpoint), so after a kill ``--resume`` continues and ends with every frame
of an uninterrupted run; Ctrl-C or SIGTERM stop within about a second (exit
130) keeping the frames done. A folder holding an earlier run has it moved
into ``previous/`` (one generation).
"""
from __future__ import annotations

import argparse
import logging
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="scene TOML file (see scenes/*.toml)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=None, help="override the scene's seed")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its checkpoint (same scene and seed); the table ends "
                        "with every frame of an uninterrupted run (a finished run is left as it is)")
    p.add_argument("--max-hours", type=float, default=None, metavar="H",
                   help="free particles: refuse a run estimated to take longer than H hours on one core (default "
                        "4); the estimate is said when a run is refused")
    p.add_argument("--threads", type=int, default=None,
                   help="threads of the DEM pair kernel (default: PTRACK_THREADS, else 1: serial and bit-reproducible)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or log lines")


def run(args) -> int:
    from sim.run import MAX_RUN_HOURS, run_scene
    from sim.scene import load_scene

    if not args.quiet:
        logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    scene = load_scene(args.scene)
    res = run_scene(scene, args.out, seed=args.seed, progress=not args.quiet, resume=args.resume,
                    max_hours=MAX_RUN_HOURS if args.max_hours is None else args.max_hours, threads=args.threads)
    if res.already_complete:
        # said even with --quiet: the user asked for work that was not done
        print(f"run already complete: {res.trajectories} has all {res.n_frames} frames; nothing to resume",
              file=sys.stderr)
        return 0
    if not args.quiet:
        ch = getattr(res, "choice", None)
        if ch is not None:
            print(f"integrator: {ch.kind} ({ch.reason})", file=sys.stderr)
        print(f"wrote {res.trajectories} ({res.n_frames} frames) and {res.scene_json} in {res.wall_time_s:.2f} s",
              file=sys.stderr)
    return 0
