"""Load: peak memory against input size for a long movie and a large DEM run.

1. Movie: a movie of N frames (48 x 48 px, 4 diffusing particles) is written
   by ``sim.render.render_movie`` into a temporary folder and tracked, in a
   fresh process, with ``ptrack.pipeline.track_movie``, and side by side
   with trackpy (``batch`` over the pages as a generator, then ``link``);
   N up to 10^4 frames. Peak memory should not grow with the movie beyond
   the localisations (frames are read and located one at a time).
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


def child_render(n_frames: int, folder: str) -> dict:
    """Render the movie of ``n_frames`` into ``folder`` (a process of its own)."""
    import numpy as np

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
    return {"frames": n_frames, "movie_MB": os.path.getsize(info["movie"]) / 1e6, "render_s": time.perf_counter() - t0}


def child_track(n_frames: int, folder: str) -> dict:
    """ptrack.pipeline.track_movie on the rendered movie."""
    from ptrack.pipeline import track_movie

    t0 = time.perf_counter()
    table, _ = track_movie(Path(folder) / "movie.tif", out=Path(folder) / "t.parquet", diameter=4.0,
                           search_range=3.0, progress=False)
    return {"rows": len(table), "tracks": int(table["particle"].nunique()), "track_s": time.perf_counter() - t0}


def child_trackpy(n_frames: int, folder: str) -> dict:
    """The peer: trackpy.batch over the TIFF pages (a generator: one frame at a time) + trackpy.link."""
    import logging

    import tifffile
    import trackpy as tp

    tp.quiet()
    logging.getLogger("trackpy").setLevel(logging.ERROR)
    t0 = time.perf_counter()
    class Pages:  # a lazy sequence of frames: one page read at a time
        def __init__(self, tf):
            self.tf = tf

        def __len__(self):
            return len(self.tf.pages)

        def __getitem__(self, i):
            return self.tf.pages[i].asarray()

        def __iter__(self):
            return (self[i] for i in range(len(self)))

    with tifffile.TiffFile(Path(folder) / "movie.tif") as tf:
        f = tp.batch(Pages(tf), 5, minmass=200, processes=1)
    t = tp.link(f, 3, memory=3)
    t = tp.filter_stubs(t, 5)
    return {"rows": len(t), "tracks": int(t["particle"].nunique()), "track_s": time.perf_counter() - t0}


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
    if kind == "track":
        import ptrack.pipeline  # noqa: F401
    elif kind == "trackpy":
        import tifffile  # noqa: F401
        import trackpy  # noqa: F401
    else:
        import sim.run  # noqa: F401
        import sim.scene  # noqa: F401
    return {}


def _child(kind: str, size: int, tmp: str | None = None) -> dict:
    if tmp is None:
        with tempfile.TemporaryDirectory(prefix="bench_load_") as tmp:
            return _child(kind, size, tmp)
    if True:
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
        bases = {k: _child(k, 0).get("peak_MB", float("nan")) for k in ("track", "trackpy")}
        print("movie (48 x 48 px, 4 particles) rendered by sim.render.render_movie, then tracked in a fresh process "
              "by ptrack.pipeline.track_movie and, side by side, by trackpy (batch over the pages + link); "
              f"baselines (imports only): ptrack {bases['track']:.0f} MB, trackpy {bases['trackpy']:.0f} MB")
        print(f"{'frames':>7} {'movie MB':>9} {'render s':>9} {'tracker':>8} {'rows':>7} {'tracks':>6} {'s':>7} "
              f"{'frames/s':>9} {'peak MB':>8} {'peak - base':>11} {'vs first':>9}")
        first: dict = {}
        for n in frames:
            with tempfile.TemporaryDirectory(prefix="bench_load_") as tmp:
                r0 = _child("render", n, tmp)
                if "error" in r0:
                    print(f"{n:>7} render error: {r0['error']}")
                    continue
                for kind, label in (("track", "ptrack"), ("trackpy", "trackpy")):
                    r = _child(kind, n, tmp)
                    if "error" in r:
                        print(f"{n:>7} {label} error: {r['error']}")
                        continue
                    print(f"{n:>7} {r0['movie_MB']:>9.1f} {r0['render_s']:>9.1f} {label:>8} {r['rows']:>7} "
                          f"{r['tracks']:>6} {r['track_s']:>7.1f} {n / r['track_s']:>9.0f} {r['peak_MB']:>8.0f} "
                          f"{r['peak_MB'] - bases[kind]:>11.0f} {r['peak_MB'] - first.setdefault(kind, r['peak_MB']):>+9.0f}")
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
