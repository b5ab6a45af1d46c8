"""Compile the simulator's kernels into numba's on-disk cache, so that the first real run starts warm.

Numba compiles a kernel on its first call and caches the machine code on disk
(``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``); a later process
loads it in milliseconds. This command makes those first calls: it runs every
shipped scene (``scenes/*.toml``) for a few steps with a few particles, so
that each integrator, contact law and wall kernel a shipped scene uses is
compiled once, at install time (``make venv`` runs it) rather than inside a
user's first simulation or in every new dask worker. Nothing it writes is
kept (the runs go to a temporary folder). Running it again with a warm cache
takes a few seconds.

Why not ahead-of-time compilation: numba's AOT module is deprecated, and the
cache already holds exactly the specialisations a run needs.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

N_PARTICLES = 24  # enough for pairs in contact and a neighbour list; the kernels' types do not depend on N
STEPS = 3


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def shipped_scenes() -> list[Path]:
    """The shipped scene files (source tree or installed package data)."""
    from sim.studies.deposition import SCENES

    return sorted(Path(SCENES).glob("*.toml"))


def short_scene(raw: dict):
    """The scene of ``raw`` cut to :data:`N_PARTICLES` particles and :data:`STEPS` steps (or 3 ns with dt = auto)."""
    from sim.scene import scene_from_dict

    raw = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    parts = raw.setdefault("particles", {})
    parts["count"] = min(int(parts.get("count", N_PARTICLES)), N_PARTICLES)
    t = raw.setdefault("time", {})
    dt = t.get("dt", "auto")
    final = STEPS * float(dt) if not isinstance(dt, str) else 3e-9
    t["final"] = final
    t["output_interval"] = final
    return scene_from_dict(raw, source="warmup")


def run(args) -> int:
    from sim.run import run_scene

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ptrack-warmup-") as tmp:
        for path in shipped_scenes():
            t1 = time.perf_counter()
            with open(path, "rb") as fh:
                scene = short_scene(tomllib.load(fh))
            run_scene(scene, Path(tmp) / path.stem, progress=False)
            if not args.quiet:
                print(f"warmup: {path.name} compiled / loaded in {time.perf_counter() - t1:.1f} s", file=sys.stderr)
    if not args.quiet:
        print(f"warmup: numba cache ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
