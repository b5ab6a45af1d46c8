"""Benchmark of the diffusion-coefficient estimators in ptrack.msd: accuracy and speed.

Accuracy: synthetic free Brownian tracks with Gaussian localisation noise
(reduced error x = sigma^2 / (D dt)) and motion blur R (0 = instantaneous,
1/6 = full-frame exposure), drawn exactly (ptrack.msd.brownian_tracks). For
each case, `--reps` replicates of `--tracks` tracks of N displacements are
estimated with

- cve       covariance-based estimator (Vestergaard et al. 2014),
- ols-opt   least squares over the optimal number of lags (Michalet 2010),
- ols-25%   least squares over a fixed quarter of the MSD curve (for contrast),

and the table prints the bias (mean/D - 1, with its standard error), the
relative standard deviation over replicates, the Cramer-Rao bound on the
relative SD (same tracks, sigma unknown), their ratio, the CVE's closed-form
SD, and the run time.

Speed: MSD and CVE of 10^4 tracks x 10^3 frames (array fast paths, as the
simulator calls them), and the table path (gaps, bootstrap, flags) on
2000 tracks x 1000 frames.

Usage:  .venv/bin/python bench/bench_msd.py [--reps 1000] [--tracks 10] [--quick]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from ptrack import msd as M
from ptrack.table import make_table

D0, DT = 1e-12, 0.1


def accuracy(reps: int, n_tracks: int, xs, Ns, Rs, seed: int = 0):
    print(f"\n== accuracy: {reps} replicates x {n_tracks} tracks per case; D = {D0:g} m^2/s, dt = {DT:g} s ==")
    hdr = (f"{'x':>5s} {'R':>5s} {'N':>5s} {'estimator':>9s} {'bias %':>15s} {'rel SD':>8s} "
           f"{'CRLB':>8s} {'SD/CRLB':>8s} {'pred SD':>8s} {'lags':>6s} {'time s':>7s}")
    print(hdr)
    print("-" * len(hdr))
    rng = np.random.default_rng(seed)
    for N in Ns:
        for R in Rs:
            for x in xs:
                sigma = math.sqrt(x * D0 * DT)
                bound = math.sqrt(M.crlb_diffusion(D0, sigma, DT, N, R, n_tracks=n_tracks)) / D0
                pos_all = [M.brownian_tracks(n_tracks, N + 1, D0, DT, sigma, R, seed=rng) for _ in range(reps)]
                res = {}
                t0 = time.perf_counter()
                res["cve"] = (np.array([M.cve_from_positions(p, DT, R)[0].mean() for p in pos_all]), "-",
                              time.perf_counter() - t0)
                t0 = time.perf_counter()
                out = [M.ols_from_positions(p, DT) for p in pos_all]
                Ps = np.array([o[2] for o in out])
                res["ols-opt"] = (np.array([o[0] for o in out]), f"{int(np.median(Ps))}",
                                  time.perf_counter() - t0)
                t0 = time.perf_counter()
                q = max(2, N // 4)
                res["ols-25%"] = (np.array([M.ols_fit(M.msd_from_positions(p, q).mean(0), q)[1] / (2 * DT)
                                            for p in pos_all]), f"{q}", time.perf_counter() - t0)
                pred = math.sqrt(M.cve_variance(D0, sigma**2, DT, N, R) / n_tracks) / D0
                for name, (Ds, lags, tt) in res.items():
                    r = Ds / D0
                    bias = 100 * (r.mean() - 1)
                    se = 100 * r.std(ddof=1) / math.sqrt(reps)
                    sd = r.std(ddof=1)
                    ps = f"{pred:8.4f}" if name == "cve" else f"{'':8s}"
                    print(f"{x:5.1f} {R:5.3f} {N:5d} {name:>9s} {bias:+7.2f} +- {se:4.2f} {sd:8.4f} "
                          f"{bound:8.4f} {sd / bound:8.2f} {ps} {lags:>6s} {tt:7.2f}")


def speed(n_p: int, n_f: int, n_p_table: int, n_f_table: int, seed: int = 0):
    print(f"\n== speed (2-core machine; numba compiled beforehand) ==")
    print(f"{'what':<58s} {'time s':>8s}  result")
    rng = np.random.default_rng(seed)
    pos = M.brownian_tracks(n_p, n_f, D0, DT, 30e-9, 1 / 6, seed=rng)
    M.msd_from_positions(pos[:2, :20], 5)
    M.cve_from_positions(pos[:2, :20], DT)
    t0 = time.perf_counter()
    D, var = M.cve_from_positions(pos, DT, 1 / 6)
    t = time.perf_counter() - t0
    print(f"{f'cve_from_positions {n_p} x {n_f} (1 axis)':<58s} {t:8.2f}  mean D/D0 = {D.mean() / D0:.4f}")
    t0 = time.perf_counter()
    m = M.msd_from_positions(pos, 100)
    t = time.perf_counter() - t0
    print(f"{f'msd_from_positions {n_p} x {n_f}, 100 lags':<58s} {t:8.2f}  MSD(100 dt)/(200 D dt) = {m[:, -1].mean() / (200 * D0 * DT):.4f}")
    t0 = time.perf_counter()
    d, e, P = M.ols_from_positions(pos, DT)
    t = time.perf_counter() - t0
    print(f"{f'ols_from_positions {n_p} x {n_f}':<58s} {t:8.2f}  D/D0 = {d / D0:.4f} +- {e / D0:.4f}, {P} lags")
    del pos, m

    p = M.brownian_tracks(n_p_table, n_f_table, D0, DT, 30e-9, 1 / 6, n_dims=2, seed=rng)
    fr = np.tile(np.arange(n_f_table), n_p_table)
    pa = np.repeat(np.arange(n_p_table), n_f_table)
    keep = rng.random(len(fr)) > 0.05
    df = make_table(fr[keep], fr[keep] * DT, pa[keep], p[..., 0].ravel()[keep], p[..., 1].ravel()[keep])
    del p
    label = f"table {n_p_table} x {n_f_table} (5% gaps)"
    t0 = time.perf_counter()
    ens = M.ensemble_msd(df, axes=("x", "y", "xy"))
    t = time.perf_counter() - t0
    print(f"{'ensemble_msd ' + label + ', x,y,xy, 100 lags':<58s} {t:8.2f}  msd_xy(1)/(4 D dt) = {ens['msd_xy'].iloc[0] / (4 * D0 * DT):.4f}")
    for est in ("cve", "ols"):
        t0 = time.perf_counter()
        r = M.estimate_diffusion(df, axes=("x", "y", "xy"), estimator=est, n_boot=200)
        t = time.perf_counter() - t0
        print(f"{f'estimate_diffusion {est} ' + label + ', 200 boot':<58s} {t:8.2f}  "
              f"D_xy/D0 = {r.D['xy'] / D0:.4f} +- {r.D_err['xy'] / D0:.4f}")
    t0 = time.perf_counter()
    r = M.estimate_diffusion(df, axes=("xy",), subtract_drift=True, n_boot=0)
    t = time.perf_counter() - t0
    print(f"{'estimate_diffusion cve + drift ' + label:<58s} {t:8.2f}  D_xy/D0 = {r.D['xy'] / D0:.4f}")
    t0 = time.perf_counter()
    f = M.powerlaw_flags(df)
    t = time.perf_counter() - t0
    print(f"{'powerlaw_flags ' + label + ', level 0.01':<58s} {t:8.2f}  flagged {f['flagged'].mean() * 100:.2f} % (nominal 1 %)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=1000)
    ap.add_argument("--tracks", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="small run (200 replicates, smaller speed test)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    reps = 200 if a.quick else a.reps
    t0 = time.perf_counter()
    accuracy(reps, a.tracks, xs=(0.0, 0.1, 1.0, 10.0), Ns=(100, 1000), Rs=(0.0, 1 / 6), seed=a.seed)
    if a.quick:
        speed(2000, 1000, 500, 500, seed=a.seed)
    else:
        speed(10000, 1000, 2000, 1000, seed=a.seed)
    print(f"\ntotal {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
