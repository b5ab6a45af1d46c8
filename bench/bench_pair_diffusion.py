"""D from linked tracks against the linking-free estimate, as particles get denser.

A. Point simulations (no images): free Brownian particles, uniform over a
   region wider than a square view of 150 units, steps of 4 units per axis
   (D = 80 units^2/s, dt = 0.1 s), localisation noise 0.1 units, 80 frames.
   Per density (link ambiguity = expected fraction of steps for which another
   particle is nearer than the partner) and over ``--seeds`` replicates:
   relative bias of D (mean +- its standard error), scatter over the
   replicates, mean stated standard error, run time, for
     - tracks linked by ptrack.link, CVE without the field-of-view correction,
     - the same with the field-of-view correction (msd.estimate_diffusion(field_of_view="auto")),
     - the true identities (perfect linking), with the correction,
     - msd.pair_diffusion (no linking).
B. Movies rendered like data/synthetic/diffusion2d (``--movies K`` seeds; 0
   skips): the whole pipeline (ptrack.analysis.analyze_movie), D reported,
   from the tracks and linking-free, against the rendered D.

Run: ``.venv/bin/python bench/bench_pair_diffusion.py [--seeds 20] [--movies 8]``
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptrack import msd as M  # noqa: E402
from ptrack.link import filter_short, link  # noqa: E402


def part_a(seeds: int):
    L, dt, D, sig, F = 150.0, 0.1, 80.0, 0.1, 80
    print("A. Points in a 150 x 150 view, steps 4 per axis, noise 0.1, 80 frames; "
          f"{seeds} replicates per density; D relative to the true D")
    print(f"{'particles/view':>14} {'ambiguity':>9}  {'estimator':<28}{'bias %':>14}{'scatter %':>10}"
          f"{'stated SE %':>12}{'time s':>8}")
    for dens in (0.0008, 0.0015, 0.0022, 0.004):
        rows = {k: [] for k in ("linked", "linked+fov", "true ids+fov", "pairs")}
        amb = []
        for k in range(seeds):
            df = M.brownian_field(F, L, dens, D, dt, sigma=sig, seed=1000 + k)
            feats = df.drop(columns=["particle", "x", "y"]).assign(x_px=df["x"], y_px=df["y"])
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lk = filter_short(link(feats), 5)
            lk = lk.assign(x=lk["x_px"], y=lk["y_px"])
            t_link = time.perf_counter() - t0
            for key, tab, fov in (("linked", lk, None), ("linked+fov", lk, "auto"), ("true ids+fov", df, "auto")):
                t0 = time.perf_counter()
                e = M.estimate_diffusion(tab, axes=("xy",), motion_blur=0.0, field_of_view=fov)
                extra = t_link if tab is lk else 0.0
                rows[key].append((e.D["xy"] / D - 1, e.D_err["xy"] / D, time.perf_counter() - t0 + extra))
            t0 = time.perf_counter()
            r = M.pair_diffusion(df.drop(columns="particle"), axes=("xy",), motion_blur=0.0)
            rows["pairs"].append((r.D["xy"] / D - 1, r.D_err["xy"] / D, time.perf_counter() - t0))
            amb.append(r.link_ambiguity)
        for key, v in rows.items():
            a = np.array(v)
            print(f"{dens * L * L:>14.0f} {np.mean(amb):>9.3f}  {key:<28}"
                  f"{a[:, 0].mean() * 100:>+7.2f} +- {a[:, 0].std(ddof=1) / math.sqrt(len(a)) * 100:4.2f}"
                  f"{a[:, 0].std(ddof=1) * 100:>10.2f}{a[:, 1].mean() * 100:>12.2f}{a[:, 2].mean():>8.2f}")
        sys.stdout.flush()


def part_b(movies: int):
    from ptrack.analysis import analyze_movie
    from sim.render import render_movie
    from sim.render.datasets import diffusion2d_scene

    print(f"\nB. {movies} movies rendered like data/synthetic/diffusion2d (new seeds), whole pipeline;"
          " D_xy relative to the rendered D")
    print(f"{'seed':>6} {'tracks':>7} {'ambiguity':>9} {'from tracks %':>15} {'linking-free %':>16} {'reported':>10}"
          f" {'time s':>7}")
    res = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(movies):
            sc = diffusion2d_scene(seed=30000 + 7 * k)
            out = Path(tmp) / f"m{k}"
            render_movie(sc["table"], out, sc["shape"], sc["optics"], sc["camera"], focal_plane=sc["focal_plane"],
                         brightfield=False, seed=sc["seed"], compression=None, extra_params=sc["extra"],
                         progress=False)
            cam = sc["camera"]
            D0 = sc["extra"]["D_true"]
            t0 = time.perf_counter()
            r = analyze_movie(out / "movie.tif", radius=sc["extra"]["radius"], viscosity=1e-3, temperature=293.15,
                              motion_blur=0.0, gain=cam.gain, offset=cam.offset, read_noise=cam.read_noise,
                              progress=False).summary
            wall = time.perf_counter() - t0
            pr = r["D_pairs"]
            row = (r["D_tracks"]["xy"] / D0 - 1, r["D_tracks_err"]["xy"] / D0, pr["D"]["xy"] / D0 - 1,
                   pr["D_err"]["xy"] / D0, r["D"]["xy"] / D0 - 1)
            res.append(row)
            print(f"{30000 + 7 * k:>6} {r['n_tracks']:>7} {pr['link_ambiguity']:>9.3f} {row[0] * 100:>+7.2f} +- {row[1] * 100:4.2f}"
                  f" {row[2] * 100:>+8.2f} +- {row[3] * 100:4.2f} {row[4] * 100:>+9.2f} {wall:>7.1f}", flush=True)
    a = np.array(res)
    n = len(a)
    for name, i in (("from tracks", 0), ("linking-free", 2), ("reported", 4)):
        print(f"   {name:<13} mean {a[:, i].mean() * 100:+.2f} +- {a[:, i].std(ddof=1) / math.sqrt(n) * 100:.2f} %,"
              f" scatter {a[:, i].std(ddof=1) * 100:.2f} %")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--movies", type=int, default=8)
    a = ap.parse_args(argv)
    if a.seeds > 1:
        part_a(a.seeds)
    if a.movies > 1:
        part_b(a.movies)
    return 0


if __name__ == "__main__":
    sys.exit(main())
