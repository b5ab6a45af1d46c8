"""ptrack's localiser against trackpy.batch on the same rendered movies, side by side.

1. Accuracy: isolated in-focus particles at 2000 detected photons (63x NA 0.75,
   519 nm, 103 nm pixels), 256 x 256 frames. trackpy is given its best case:
   diameter and minmass are scanned and the most accurate setting with
   recall >= 0.98 is reported (ptrack needs no such tuning: the spot size is
   estimated from the movie).
2. Speed: 2048 x 2048 frames with ~400 particles; per-frame time of
   trackpy.batch and of ptrack.locate, both on one core (cv2 threads = 1,
   trackpy processes = 1), and accuracy on these frames too.

Run: ``.venv/bin/python bench/bench_vs_trackpy.py [--quick]``
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_pipeline import grid_truth, match  # noqa: E402
from ptrack.locate import cramer_rao_bound, estimate_sigma, locate  # noqa: E402
from sim import render  # noqa: E402


def score(found_xy, t, n_frames, frames_of_found):
    errs, nm, nf, nt = [], 0, 0, 0
    for f in range(n_frames):
        tt = t[t["frame"] == f][["x_px", "y_px"]].to_numpy()
        ff = np.asarray(found_xy, float).reshape(-1, 2)[frames_of_found == f]
        fi, ti = match(ff, tt, 2.0)
        errs.append(ff[fi].reshape(-1, 2) - tt[ti].reshape(-1, 2))
        nm += len(fi)
        nf += len(ff)
        nt += len(tt)
    e = np.concatenate(errs) if errs else np.zeros((0, 2))
    rmse = np.sqrt((e ** 2).mean(0)) if len(e) else np.array([np.nan, np.nan])
    return rmse, np.abs(e.mean(0)) if len(e) else np.array([np.nan] * 2), nm / max(nt, 1), nm / max(nf, 1)


def run_ours(frames, cam, sigma=None):
    if sigma is None:
        sigma = estimate_sigma(frames[:2], gain=cam.gain, offset=cam.offset)
    xy, fr = [], []
    t0 = time.perf_counter()
    for i, f in enumerate(frames):
        df = locate(f, sigma=sigma, gain=cam.gain, offset=cam.offset, read_noise=cam.read_noise)
        xy.append(df[["x_px", "y_px"]].to_numpy())
        fr.append(np.full(len(df), i))
    el = time.perf_counter() - t0
    return np.concatenate(xy), np.concatenate(fr), el / len(frames), sigma


def run_trackpy(frames, diameter, minmass, processes=1):
    import trackpy

    trackpy.quiet()
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = trackpy.batch(list(frames), diameter, minmass=minmass, processes=processes)
    el = time.perf_counter() - t0
    return f[["x", "y"]].to_numpy(), f["frame"].to_numpy(), el / len(frames)


def main():
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    optics = render.Optics()
    cam = render.Camera(photons=2000 / 0.6, background=20.0)
    px = render.sample_pixel_size(optics, cam.pixel_pitch)
    rng = np.random.default_rng(5)
    crb = np.mean(cramer_rao_bound(render.psf_image(optics, px, 0.0, size=32, oversample=8), 8, 2000.0, 12.0,
                                   cam.read_noise))

    print("## 1. Accuracy at 2000 photons, isolated in-focus particles, 256 x 256 px")
    print("command: .venv/bin/python bench/bench_vs_trackpy.py")
    n = 8 if args.quick else 20
    table, t = grid_truth(n, (256, 256), 20, rng, px=px)
    frames = list(render.render_frames(table, shape=(256, 256), camera=cam, seed=6))
    cv2.setNumThreads(1)
    run_ours(frames[:1], cam, sigma=1.3)   # compile / warm up
    xy, fr, tpf, sigma = run_ours(frames, cam)
    rm, bias, rec, prec = score(xy, t, n, fr)
    print(f"{'method':>34} {'RMSE x':>7} {'RMSE y':>7} {'/CRB':>5} {'bias':>6} {'recall':>6} {'precis.':>7} {'ms/frame':>8}")
    print(f"{'ptrack (sigma %.2f px estimated)' % sigma:>34} {rm[0]:7.4f} {rm[1]:7.4f} {rm.mean() / crb:5.2f} "
          f"{bias.max():6.4f} {rec:6.3f} {prec:7.3f} {1000 * tpf:8.1f}")
    best = None
    for diameter in (5, 7, 9, 11):
        for minmass in (0, 50, 100, 200, 400, 800, 1600):
            txy, tfr, ttpf = run_trackpy(frames, diameter, minmass)
            trm, tb, trec, tprec = score(txy, t, n, tfr)
            if trec >= 0.98 and tprec >= 0.98 and (best is None or trm.mean() < best[0].mean()):
                best = (trm, tb, trec, tprec, ttpf, diameter, minmass)
    if best is None:
        print("    trackpy: no setting reached recall and precision >= 0.98")
    else:
        trm, tb, trec, tprec, ttpf, diameter, minmass = best
        print(f"{'trackpy.batch (best: d=%d, minmass=%d)' % (diameter, minmass):>34} {trm[0]:7.4f} {trm[1]:7.4f} "
              f"{trm.mean() / crb:5.2f} {tb.max():6.4f} {trec:6.3f} {tprec:7.3f} {1000 * ttpf:8.1f}")
    print(f"    (px; CRB = exact Cramer-Rao bound of the rendered Airy PSF = {crb:.4f} px; one core each)")

    print("\n## 2. Speed on 2048 x 2048 frames, ~400 particles, 2000 photons")
    n2 = 4 if args.quick else 10
    table, t = grid_truth(n2, (2048, 2048), 100, rng, margin=24, px=px)
    frames = list(render.render_frames(table, shape=(2048, 2048), camera=cam, seed=7))
    d, mm = (best[5], best[6]) if best else (7, 200)
    print(f"{'method':>34} {'ms/frame':>9} {'speed-up':>8} {'RMSE':>7} {'recall':>6} {'precis.':>7}")
    rows = []
    for threads, procs in ((1, 1), (0, "auto")):
        cv2.setNumThreads(threads if threads else cv2.getNumberOfCPUs())
        xy, fr, tpf, _ = run_ours(frames, cam, sigma=sigma)
        rm, _, rec, prec = score(xy, t, n2, fr)
        txy, tfr, ttpf = run_trackpy(frames, d, mm, processes=procs)
        trm, _, trec, tprec = score(txy, t, n2, tfr)
        label = "one core" if threads == 1 else "all cores"
        print(f"{'ptrack.locate, ' + label:>34} {1000 * tpf:9.1f} {ttpf / tpf:8.2f} {rm.mean():7.4f} {rec:6.3f} {prec:7.3f}")
        print(f"{'trackpy.batch d=%d, ' % d + label:>34} {1000 * ttpf:9.1f} {1.0:8.2f} {trm.mean():7.4f} {trec:6.3f} "
              f"{tprec:7.3f}")
        rows.append((tpf, ttpf))
    print("    (speed-up = trackpy time / ptrack time per frame; frames already in memory for both)")


if __name__ == "__main__":
    main()
