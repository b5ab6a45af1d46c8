"""Load: peak memory against input size for a long movie and a large DEM run.

1. Movie: a movie of N frames (48 x 48 px, 4 diffusing particles) is written
   by ``sim.render.render_movie`` into a temporary folder and tracked with
   ``ptrack.pipeline.track_movie``; N up to 10^4 frames. Peak memory should
   not grow with the movie (frames are read and located one at a time; only
   the localisations are kept).
2. DEM: a scene of M spheres (dilute, DEM contacts on) is set up with
   ``sim.scene.scene_from_dict`` and stepped a few output frames with
   ``sim.run.run_scene``; M up to 10^6.

Each case runs in a child process of its own, so its peak resident memory
(``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss``) is its own; the Python +
numba + library baseline (an empty child that imports the same modules) is
printed beside it.

Usage::

    .venv/bin/python bench/bench_load.py                 # movie 1e3, 1e4 frames; DEM 1e4, 1e5, 1e6 spheres
    .venv/bin/python bench/bench_load.py --quick         # movie 1e3 frames; DEM 1e4 spheres
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def child_movie(n_frames: int, folder: str) -> dict:
    import numpy as np

    from ptrack.pipeline import track_movie
    from ptrack.table import make_table
    from sim import render

    rng = np.random.default_rng(1)
    cam = render.Camera(photons=3000)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    n = 4
    steps = rng.normal(0, 3e-8, (2, n, n_frames))
    x = (rng.uniform(12, 36, n) * px)[:, None] + steps[0].cumsum(1)
    y = (rng.uniform(12, 36, n) * px)[:, None] + steps[1].cumsum(1)
    # keep the particles in the view: reflect at the borders (5 px margin)
    lo, hi = 5 * px, 43 * px
    x = lo + np.abs((x - lo) % (2 * (hi - lo)) - (hi - lo))
    y = lo + np.abs((y - lo) % (2 * (hi - lo)) - (hi - lo))
    fr = np.tile(np.arange(n_frames), n)
    tab = make_table(fr, fr * 0.01, np.repeat(np.arange(n), n_frames), x.ravel(), y.ravel(), np.zeros(n * n_frames),
                     meta={"frame_interval": 0.01})
    t0 = time.perf_counter()
    info = render.render_movie(tab, folder, shape=(48, 48), camera=cam, seed=2, progress=False)
    t_render = time.perf_counter() - t0
    rss_render = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    del tab, x, y, steps, fr
    t0 = time.perf_counter()
    table, summary = track_movie(info["movie"], out=Path(folder) / "t.parquet", diameter=4.0, search_range=3.0,
                                 progress=False)
    t_track = time.perf_counter() - t0
    return {"frames": n_frames, "movie_MB": os.path.getsize(info["movie"]) / 1e6, "rows": len(table),
            "tracks": int(table["particle"].nunique()), "render_s": t_render, "track_s": t_track,
            "rss_after_render_MB": rss_render / 1024}


def child_dem(n_particles: int, folder: str) -> dict:
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    radius = 1e-6
    # dilute (volume fraction ~2 %): random placement stays cheap, contacts still searched every step
    side = (n_particles * 4.19 * radius**3 / 0.02 / 0.2) ** (1 / 3)
    raw = {
        "seed": 1,
        "particles": {"count": n_particles, "radius": radius, "density": 2200.0, "charge_per_mass": -1e-3},
        "fluid": {"density": 1000.0, "viscosity": 1e-3, "temperature": 0.0},
        "fields": {"E": [0.0, 0.0, 1e3]},
        "gravity": {"enabled": True},
        "domain": {"size": [side, side, 0.2 * side]},
        "boundaries": {"x": "periodic", "y": "periodic", "bottom_wall": True},
        "time": {"dt": 1e-7, "final": 3e-7, "output_interval": 1e-7},
        "contact": {"model": "power", "K": 1e9, "exponent": 2.0, "damping": 1e2, "checkpoint_every": 0},
    }
    t0 = time.perf_counter()
    scene = scene_from_dict(raw, source="bench_load")
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_scene(scene, folder, progress=False)
    t_run = time.perf_counter() - t0
    out = Path(folder) / "trajectories.parquet"
    return {"particles": n_particles, "setup_s": t_setup, "run_s": t_run, "steps": 3,
            "table_MB": out.stat().st_size / 1e6 if out.exists() else None}


def child_baseline(kind: str) -> dict:
    if kind == "movie":
        import ptrack.pipeline  # noqa: F401
        import sim.render  # noqa: F401
    else:
        import sim.run  # noqa: F401
        import sim.scene  # noqa: F401
    return {}


def _child(kind: str, size: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_load_") as tmp:
        code = ("import json, resource, sys; sys.path.insert(0, %r); import bench_load as b; "
                "r = b.child_%s(%d, %r) if %d else b.child_baseline(%r); "
                "r['peak_MB'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024; print(json.dumps(r))"
                % (str(Path(__file__).parent), kind, size, tmp, size, kind))
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           cwd=Path(__file__).resolve().parents[1])
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            return {"error": (p.stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall}
        r = json.loads(p.stdout.strip().splitlines()[-1])
        r["wall_s"] = wall
        return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--frames", type=int, nargs="*", default=None, help="movie lengths (default 1000 10000)")
    ap.add_argument("--particles", type=int, nargs="*", default=None, help="DEM sizes (default 1e4 1e5 1e6)")
    a = ap.parse_args()
    frames = a.frames if a.frames is not None else ([1000] if a.quick else [1000, 10000])
    parts = a.particles if a.particles is not None else ([10000] if a.quick else [10000, 100000, 1000000])
    print(f"bench_load: each case in its own process, peak RSS; machine: {os.cpu_count()} cores, shared and loaded "
          f"(load average {os.getloadavg()[0]:.1f})\n")
    if frames:
        base = _child("movie", 0)
        print(f"movie: render (sim.render.render_movie) + track (ptrack.pipeline.track_movie), 48 x 48 px, "
              f"4 particles; baseline (imports only) {base.get('peak_MB', float('nan')):.0f} MB")
        print(f"{'frames':>7} {'movie MB':>9} {'rows':>7} {'tracks':>6} {'render s':>9} {'track s':>8} "
              f"{'frames/s':>9} {'peak MB':>8} {'peak - base':>11}")
        for n in frames:
            r = _child("movie", n)
            if "error" in r:
                print(f"{n:>7} error: {r['error']}")
                continue
            print(f"{n:>7} {r['movie_MB']:>9.1f} {r['rows']:>7} {r['tracks']:>6} {r['render_s']:>9.1f} "
                  f"{r['track_s']:>8.1f} {n / r['track_s']:>9.0f} {r['peak_MB']:>8.0f} "
                  f"{r['peak_MB'] - base.get('peak_MB', 0):>11.0f}")
    if parts:
        base = _child("dem", 0)
        print(f"\nDEM: sim.scene.scene_from_dict + sim.run.run_scene, 3 steps (3 output frames), volume fraction 2 %, "
              f"periodic sides; baseline (imports only) {base.get('peak_MB', float('nan')):.0f} MB")
        print(f"{'spheres':>8} {'setup s':>8} {'run s':>7} {'table MB':>9} {'peak MB':>8} {'peak - base':>11} "
              f"{'bytes/sphere':>12}")
        for n in parts:
            r = _child("dem", n)
            if "error" in r:
                print(f"{n:>8} error: {r['error']}")
                continue
            extra = r["peak_MB"] - base.get("peak_MB", 0)
            print(f"{n:>8} {r['setup_s']:>8.1f} {r['run_s']:>7.1f} {r['table_MB'] or float('nan'):>9.1f} "
                  f"{r['peak_MB']:>8.0f} {extra:>11.0f} {extra * 1048576 / n:>12.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
