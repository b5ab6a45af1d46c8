"""GDPT with calibration stacks as recorded: z error against the calibration step and the number of beads
averaged, and speed with large templates (512^2 frames, 20 particles).

Optics: an astigmatic Gaussian written here (widths s0 sqrt(1 + ((z -+ c) / d)^2), pixel-integrated, Poisson
noise; tests/test_gdpt.py's model), independent of the project's renderer, plus one renderer case.

command: .venv/bin/python bench/bench_gdpt.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_gdpt import _score, gaussian_frame  # noqa: E402  (the test's independent optics)

import test_gdpt  # noqa: E402
from ptrack.calibration import build_calibration, locate_frame_3d, prepare_gdpt  # noqa: E402

PX = 1e-7


def _movie_error(cal, half, n_frames, rng, photons=2e5, grid=4, spacing=120.0):
    found = n = n_det = 0
    errs, t = [], 0.0
    g = np.arange(grid) * spacing + 75.0
    for _ in range(n_frames):
        xs, ys = (a.ravel() + rng.uniform(-3, 3, grid * grid) for a in np.meshgrid(g, g))
        zs = rng.uniform(-0.95 * half, 0.95 * half, grid * grid)
        img = gaussian_frame((512, 512), xs, ys, zs, photons, 20.0, rng)
        t0 = time.perf_counter()
        df = locate_frame_3d(img, cal)
        t += time.perf_counter() - t0
        k, e, m = _score(df, xs, ys, zs)
        found, n, n_det = found + k, n + len(xs), n_det + m
        errs.extend(e)
    e = np.array(errs)
    return found / n, found / max(n_det, 1), float(np.sqrt(np.mean(e ** 2))), t / n_frames


def step_table(quick):
    print("\n## z error against the calibration step (one bead, 512^2 full frames, +-10 um, 2e5 photons)")
    print("command: .venv/bin/python bench/bench_gdpt.py")
    print(f"{'step um':>8} {'pages':>6} {'templates':>9} {'recall':>7} {'precis.':>7} {'z RMSE nm':>9} "
          f"{'% depth':>8} {'RMSE/step':>9} {'s/frame':>8}")
    half = 10e-6
    for step in (0.25e-6, 0.5e-6, 1e-6, 2e-6, 4e-6):
        rng = np.random.default_rng(11)
        z = np.arange(-half, half + 1e-12, step)
        stack = np.stack([gaussian_frame((512, 512), [255.3], [256.6], [zk], 2e5, 20.0, rng) for zk in z])
        cal = build_calibration(stack, z, PX)
        rec, prec, rm, t = _movie_error(cal, half, 2 if quick else 5, rng)
        print(f"{step * 1e6:8.2f} {len(z):6d} {len(cal.z):9d} {rec:7.3f} {prec:7.3f} {rm * 1e9:9.0f} "
              f"{100 * rm / cal.depth:8.2f} {rm / step:9.3f} {t:8.3f}")


def beads_table(quick):
    print("\n## z error against the number of beads averaged (512^2 full frames, +-10 um in 1 um steps, dim "
          "calibration beads: 2e4 photons; movie 2e5 photons)")
    print("command: .venv/bin/python bench/bench_gdpt.py")
    print(f"{'beads':>6} {'recall':>7} {'z RMSE nm':>9} {'% depth':>8} {'reported z_error nm':>19}")
    half = 10e-6
    spots = [(128.3, 128.6), (384.2, 128.1), (128.7, 384.4), (384.5, 384.9)]
    for nb in (1, 2, 4):
        rng = np.random.default_rng(5)
        z = np.arange(-half, half + 1e-12, 1e-6)
        stack = np.stack([gaussian_frame((512, 512), [s[0] for s in spots[:nb]], [s[1] for s in spots[:nb]],
                                         [zk] * nb, 2e4, 20.0, rng) for zk in z])
        cal = build_calibration(stack, z, PX)
        rec, prec, rm, t = _movie_error(cal, half, 2 if quick else 5, rng)
        ze = cal.info.get("z_error", float("nan"))
        print(f"{nb:6d} {rec:7.3f} {rm * 1e9:9.0f} {100 * rm / cal.depth:8.2f} {ze * 1e9:19.0f}")


def speed_table(quick):
    print("\n## Speed: 512^2 frames, 20 particles at random heights, +-30 um in 2 um steps (machine loaded: 2 cores "
          "shared with other jobs; wall times)")
    print("command: .venv/bin/python bench/bench_gdpt.py")
    print(f"{'layout':>6} {'d um':>5} {'largest template px':>19} {'templates':>9} {'scale':>5} {'recall':>7} {'z RMSE % depth':>14} "
          f"{'prepare ms':>10} {'locate ms':>9} {'frames/s':>8} {'CPU ms':>7} {'CPU frames/s':>12}")
    from ptrack.gdpt.fast import match_scale

    half = 30e-6
    stages = []
    for layout, d in [(lay, d) for lay in ("grid", "random") for d in (2e-6, 1.3e-6, 0.95e-6)]:
        test_gdpt.D = d             # image growth: templates up to ~100, ~150, ~220 px
        rng = np.random.default_rng(2)
        z = np.arange(-half, half + 1e-12, 2e-6)
        stack = np.stack([gaussian_frame((512, 512), [255.3], [256.6], [zk], 2e5, 20.0, rng) for zk in z])
        cal = build_calibration(stack, z, PX)
        frames, truth = [], []
        for f in range(3 if quick else 10):
            if layout == "grid":
                gx, gy = np.meshgrid(np.arange(5) * 100 + 56.0, np.arange(4) * 120 + 76.0)
                xs, ys = gx.ravel() + rng.uniform(-3, 3, 20), gy.ravel() + rng.uniform(-3, 3, 20)
            else:
                xs, ys = rng.uniform(40, 472, 20), rng.uniform(40, 472, 20)
            zs = rng.uniform(-0.95 * half, 0.95 * half, 20)
            frames.append(gaussian_frame((512, 512), xs, ys, zs, 2e5, 20.0, rng))
            truth.append((xs, ys, zs))
        locate_frame_3d(frames[0], cal)                 # warm-up (caches of reduced templates)
        cal.info["stage_times_s"] = {}                   # the stages of the timed frames only
        tp = tl = tc = 0.0
        found = n = 0
        errs = []
        for img, (xs, ys, zs) in zip(frames, truth):
            t0 = time.perf_counter()
            prepare_gdpt(img, cal)
            t1 = time.perf_counter()
            c1 = time.process_time()
            df = locate_frame_3d(img, cal)
            tc += time.process_time() - c1
            t2 = time.perf_counter()
            tp += t1 - t0
            tl += t2 - t1
            k, e, _ = _score(df, xs, ys, zs)
            found, n = found + k, n + 20
            errs.extend(e)
        rm = np.sqrt(np.mean(np.square(errs))) if errs else float("nan")
        nf = len(frames)
        print(f"{layout:>6} {d * 1e6:5.2f} {cal.size:19d} {len(cal.z):9d} {match_scale(cal):5d} {found / n:7.3f} "
              f"{100 * rm / cal.depth:14.2f} {1000 * tp / nf:10.1f} {1000 * tl / nf:9.1f} {nf / tl:8.2f} "
              f"{1000 * tc / nf:7.1f} {nf / tc:12.2f}")
        st = cal.info["stage_times_s"]
        stages.append((layout, d, {k: 1000 * v / nf for k, v in st.items()}))
    test_gdpt.D = 2e-6
    names = list(stages[0][2]) if stages else []
    print("\n    GDPT stages (locate_frame_3d's calib.info['stage_times_s'], wall ms per frame)")
    print(f"    {'layout':>6} {'d um':>5} " + " ".join(f"{n:>11}" for n in names))
    for layout, d, st in stages:
        print(f"    {layout:>6} {d * 1e6:5.2f} " + " ".join(f"{st.get(n, 0.0):11.1f}" for n in names))
    print("    (locate includes prepare; CPU: the process's CPU time in locate, all threads, which a busy machine "
          "inflates less than the wall time. grid: 5 x 4 particles 100-120 px apart, images overlap only at the largest "
          "defocus; random: uniform positions, many large images overlap: recall of a crowded frame)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--only", choices=("step", "beads", "speed"))
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    if a.only in (None, "step"):
        step_table(a.quick)
    if a.only in (None, "beads"):
        beads_table(a.quick)
    if a.only in (None, "speed"):
        speed_table(a.quick)


if __name__ == "__main__":
    main()
