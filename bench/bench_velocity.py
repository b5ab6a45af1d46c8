"""Benchmark of ptrack.velocity: accuracy of the GLS drift and its standard error, speed, and the EPD dataset.

Run:  .venv/bin/python bench/bench_velocity.py [--movie]

A. Drifting Brownian tracks with localisation noise, motion blur and gaps
   (ptrack.velocity.drifting_tracks, exact in distribution): bias of the
   per-track drift in units of its standard error of the mean, the ratio of
   the stated error to the true scatter (1 = honest), with per-track and
   pooled noise estimates; and the variance of the GLS against the
   end-to-end displacement and the least-squares slope, empirical and exact.
B. Speed of particle_velocity on many tracks.
C. data/synthetic/epd_brightfield: the true tracks before contact give back
   the rendered drift (Henry + settling); with --movie, the same from the
   movie through ptrack.pipeline.track_movie with the brightfield
   calibration stack (GDPT).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptrack import velocity as V  # noqa: E402
from ptrack.table import read_table  # noqa: E402

D0 = 5.37e-13
DT = 1 / 30
VEL = (1.5e-6, 0.0, -5.2e-6)


def _lin_var(w, n, s2, R):
    S = np.diag(np.full(n, 2 * D0 * DT * (1 - 2 * R) + 2 * s2)) + (2 * R * D0 * DT - s2) * (np.eye(n, k=1) + np.eye(n, k=-1))
    return float(w @ S @ w), S


def section_a(n_tracks: int):
    print("A. per-track drift: bias and honesty of the stated error (axis z, v = -5.2 um/s, D = 0.537 um^2/s, 30 fps)")
    print(f"   {n_tracks} tracks per row; bias in units of the standard error of the mean; ratio = RMS stated error / true SD")
    print(f"   {'frames':>6s} {'sigma nm':>8s} {'R':>5s} {'gaps':>5s} {'bias/SEM':>9s} {'ratio track':>11s} {'ratio pooled':>12s}"
          f" {'var GLS':>8s} {'var e2e':>8s} {'var OLS':>8s} {'(um/s)^2 emp | exact GLS e2e OLS':>34s}")
    for nf, sigma, R, gaps in [(30, 0, 0, 0), (30, 60e-9, 1 / 6, 0.25), (30, 250e-9, 0, 0), (30, 250e-9, 0, 0.1),
                               (100, 250e-9, 0, 0), (100, 100e-9, 1 / 6, 0), (300, 30e-9, 1 / 6, 0)]:
        df = V.drifting_tracks(n_tracks, nf, D0, DT, VEL, sigma=sigma, motion_blur=R, gap_fraction=gaps, seed=7)
        tr = V.particle_velocity(df, axes="z", motion_blur=R, noise="track")
        po = V.particle_velocity(df, axes="z", motion_blur=R, noise="pooled")
        e = tr["vz"].to_numpy() - VEL[2]
        bias = e.mean() / (e.std(ddof=1) / math.sqrt(len(e)))
        r_tr = math.sqrt(np.mean(tr["vz_err"] ** 2)) / e.std(ddof=1)
        r_po = math.sqrt(np.mean(po["vz_err"] ** 2)) / (po["vz"] - VEL[2]).std(ddof=1)
        cols = ["", "", "", "", "", ""]
        if gaps == 0:
            z = df["z"].to_numpy().reshape(n_tracks, nf)
            t = np.arange(nf) * DT
            e2e = (z[:, -1] - z[:, 0]) / t[-1]
            ols = np.polyfit(t, z.T, 1)[0]
            tc = t - t.mean()
            w_ols = np.cumsum(tc[::-1])[::-1][1:] / np.sum(tc**2)
            w_e2e = np.full(nf - 1, 1 / t[-1])
            v_e2e, S = _lin_var(w_e2e, nf - 1, sigma**2, R)
            v_ols, _ = _lin_var(w_ols, nf - 1, sigma**2, R)
            tau = np.full(nf - 1, DT)
            v_gls = 1 / (tau @ np.linalg.solve(S, tau))
            cols = [f"{po['vz'].var() * 1e12:.3f}", f"{e2e.var() * 1e12:.3f}", f"{ols.var() * 1e12:.3f}",
                    f"{v_gls * 1e12:.3f}", f"{v_e2e * 1e12:.3f}", f"{v_ols * 1e12:.3f}"]
        print(f"   {nf:>6d} {sigma * 1e9:>8.0f} {R:>5.3f} {gaps:>5.2f} {bias:>+9.2f} {r_tr:>11.3f} {r_po:>12.3f}"
              f" {cols[0]:>8s} {cols[1]:>8s} {cols[2]:>8s}   exact {cols[3]:>6s} {cols[4]:>6s} {cols[5]:>6s}")


def section_b():
    print("\nB. speed of particle_velocity (x, y, z; defaults: per-track noise estimates with 2 GLS iterations, then a pooled GLS pass)")
    V.particle_velocity(V.drifting_tracks(10, 20, D0, DT, VEL, seed=0))       # compile
    print(f"   {'tracks':>7s} {'frames':>6s} {'rows':>9s} {'wall s':>7s} {'rows/s':>10s}")
    for n_p, n_f in [(1000, 100), (10000, 100), (2000, 1000)]:
        df = V.drifting_tracks(n_p, n_f, D0, DT, VEL, sigma=50e-9, gap_fraction=0.05, seed=1)
        t0 = time.perf_counter()
        V.particle_velocity(df)
        w = time.perf_counter() - t0
        print(f"   {n_p:>7d} {n_f:>6d} {len(df):>9d} {w:>7.3f} {len(df) / w:>10.3g}")


def _report_epd(label, table, p, tol=None, noise="pooled"):
    moving = V.trim_deposited(table, p["radius"], tol) if tol is not None else table
    vel = V.particle_velocity(moving, axes="xyz", motion_blur=0.0, noise=noise)
    ens = V.ensemble_velocity(vel, n_boot=2000, seed=0).set_index("axis")
    vz, ez = ens.loc["z", "v"], ens.loc["z", "v_err"]
    print(f"   {label:<58s} v_z = {vz * 1e6:+.3f} +- {ez * 1e6:.3f} um/s ({(vz - p['vz_drift']) / ez:+.1f} SE from truth, "
          f"chi2/dof {ens.loc['z', 'chi2_dof']:.2f}); v_x = {ens.loc['x', 'v'] * 1e6:+.3f} +- {ens.loc['x', 'v_err'] * 1e6:.3f}, "
          f"v_y = {ens.loc['y', 'v'] * 1e6:+.3f} +- {ens.loc['y', 'v_err'] * 1e6:.3f}; {int(ens.loc['z', 'n_particles'])} tracks")


def section_c(movie: bool):
    d = ROOT / "data" / "synthetic" / "epd_brightfield"
    p = json.loads((d / "params.json").read_text())
    truth = read_table(d / "truth.parquet")
    print(f"\nC. data/synthetic/epd_brightfield: rendered drift v_z = {p['vz_drift'] * 1e6:.3f} um/s "
          f"(Henry {p['v_henry'] * 1e6:.3f} + settling {p['v_sedimentation'] * 1e6:.3f}), D = {p['D_true'] * 1e12:.3f} um^2/s")
    moving = truth[~truth["deposited"].astype(bool)]
    _report_epd("true tracks before contact (truth 'deposited'), pooled noise:", moving, p)
    _report_epd("true tracks before contact (truth 'deposited'), per-track noise:", moving, p, noise="track")
    _report_epd("true tracks, trim_deposited(tolerance 0.5 um):", truth, p, 0.5e-6)
    if not movie:
        print("   (run with --movie for the same from the movie through the pipeline)")
        return
    from ptrack.mainjob import camera_kwargs
    from ptrack.motion import match_truth
    from ptrack.pipeline import track_movie

    t0 = time.perf_counter()
    table, summ = track_movie(d / "movie.tif", calib=d / "calib.tif", calib_z=d / "calib_z.csv", brightfield=True,
                              progress=False, **camera_kwargs(p))
    wall = time.perf_counter() - t0
    found = table.reset_index(drop=True)
    fi, ti = match_truth(found, truth)
    err = found.loc[fi, "z"].to_numpy() - truth.loc[ti, "z"].to_numpy()
    zt = truth.loc[ti, "z"].to_numpy()
    print(f"   pipeline (track_movie, brightfield calibration): {wall:.1f} s, {summ['n_localisations']} localisations, "
          f"{summ['n_tracks']} tracks; recall {len(np.unique(ti)) / len(truth):.3f}, precision {len(fi) / len(found):.3f}")
    for lo, hi in [(0, 1), (1, 5), (5, 10), (10, 15)]:
        s = (zt >= lo * 1e-6) & (zt < hi * 1e-6)
        nt = int(((truth["z"] >= lo * 1e-6) & (truth["z"] < hi * 1e-6)).sum())
        if nt:
            rm = math.sqrt(np.nanmean(err[s] ** 2)) * 1e6 if s.any() else float("nan")
            print(f"     true z {lo:>2d}-{hi:<2d} um: {nt:4d} true rows, recall {s.sum() / nt:.3f}, z RMSE {rm:.3f} um, "
                  f"bias {np.nanmean(err[s]) * 1e6 if s.any() else float('nan'):+.3f} um")
    _report_epd("measured tracks, all rows (deposited particles included):", table, p)
    for tol in (0.5e-6, 1e-6):
        _report_epd(f"measured tracks, trim_deposited(tolerance {tol * 1e6:.1f} um):", table, p, tol)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracks", type=int, default=4000, help="tracks per accuracy row (default 4000)")
    ap.add_argument("--movie", action="store_true", help="also run the image pipeline on the EPD movie (~20 s)")
    a = ap.parse_args(argv)
    section_a(a.tracks)
    section_b()
    section_c(a.movie)


if __name__ == "__main__":
    main()
