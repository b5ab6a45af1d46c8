"""Accuracy and speed of the image pipeline on rendered movies with known truth.

Prints one table per question:

A. In-plane localisation of isolated in-focus particles (63x NA 0.75, 519 nm,
   103 nm pixels, point sources) against the exact Cramer-Rao bound of the
   rendered Airy PSF (Fisher information) and Mortensen's Gaussian-PSF
   formula, over a photon sweep; recall and precision.
B. z by GDPT on isolated particles at random heights (astigmatic optics,
   calibration stack +-3 um in 0.1 um steps): z RMSE as % of the calibrated
   depth, recall/precision at Cm >= 0.5, binned in z; the shipped crowded
   data/synthetic/diffusion3d movie (binned in z, and split into particles
   whose images overlap another's and those whose do not); and brightfield
   GDPT on the shipped data/synthetic/epd_brightfield movie.
C. D on data/synthetic/diffusion2d (reported, from the tracks and linking-free)
   against D of the ground-truth tracks (same estimator and field-of-view
   correction) and D_true.
D. Speed and peak memory: a 2560 x 2160 x 130-frame uint16 series with 50
   particles (rendered into /tmp), tracked by ``ptrack track`` in a
   subprocess.

Run: ``.venv/bin/python bench/bench_pipeline.py [--skip-speed] [--quick]``
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

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptrack.calibration import build_calibration, locate_3d, load_calibration  # noqa: E402
from ptrack.io import open_movie  # noqa: E402
from ptrack.locate import cramer_rao_bound, locate, mortensen_sigma  # noqa: E402
from ptrack.motion.truth import detection_scores, match_truth  # noqa: E402
from ptrack.preprocess import prepare  # noqa: E402
from ptrack.table import make_table  # noqa: E402
from sim import render  # noqa: E402


def grid_truth(n_frames, shape, spacing, rng, margin=12, px=1.0, z=None):
    """Isolated particles on a jittered grid (new jitter every frame): table + pixel truth."""
    rows = []
    for f in range(n_frames):
        gy, gx = np.meshgrid(np.arange(margin, shape[0] - margin + 1, spacing),
                             np.arange(margin, shape[1] - margin + 1, spacing), indexing="ij")
        xs = gx.ravel() + rng.uniform(-2, 2, gx.size)
        ys = gy.ravel() + rng.uniform(-2, 2, gx.size)
        zz = np.zeros(xs.size) if z is None else z(xs.size)
        rows.append(pd.DataFrame({"frame": f, "particle": np.arange(xs.size), "x_px": xs, "y_px": ys, "z": zz}))
    t = pd.concat(rows, ignore_index=True)
    table = make_table(t["frame"], t["frame"] * 0.1, t["particle"], t["x_px"] * px, t["y_px"] * px, t["z"],
                       meta={"frame_interval": 0.1, "pixel_size": px})
    return table, t


def match(found_xy, true_xy, r):
    """Indices of mutual nearest pairs closer than r in one frame: (found_idx, true_idx).

    The one truth-matching rule of the project, :func:`ptrack.motion.truth.match_truth` with
    ``mutual=True``, applied to two position arrays (px) of one frame (by
    :func:`ptrack.motion.truth.detection_scores`).
    """
    return detection_scores(found_xy, true_xy, max_px=r, mutual=True)["pairs"]


def section_a(quick):
    print("\n## A. In-plane localisation, isolated in-focus particles (rendered Airy PSF, 2 e- read noise model)")
    print("command: .venv/bin/python bench/bench_pipeline.py  (section A)")
    optics = render.Optics()
    rng = np.random.default_rng(1)
    n_frames = 6 if quick else 20
    print(f"{'photons':>8} {'n':>6} {'recall':>7} {'precis.':>7} {'RMSE x':>8} {'RMSE y':>8} {'CRB':>7} "
          f"{'RMSE/CRB':>8} {'Mortensen':>9} {'bias':>7} {'reported':>8} {'ms/frame':>8}   (px; 1 px = 103 nm)")
    out = {}
    for photons in (500, 1000, 2000, 5000, 10000):
        cam = render.Camera(photons=photons / 0.6, background=20.0)
        px = render.sample_pixel_size(optics, cam.pixel_pitch)
        table, t = grid_truth(n_frames, (256, 256), 20, rng, px=px)
        errs, nf, nm, nt, rep, sizes, tl = [], 0, 0, 0, [], [], 0.0
        for f, frame in enumerate(render.render_frames(table, shape=(256, 256), camera=cam, seed=photons)):
            tt = t[t["frame"] == f]
            t0 = time.perf_counter()
            df = locate(frame, sigma=1.3, gain=cam.gain, offset=cam.offset, read_noise=cam.read_noise)
            tl += time.perf_counter() - t0
            fi, ti = match(df[["x_px", "y_px"]].to_numpy(), tt[["x_px", "y_px"]].to_numpy(), 2.0)
            errs.append(df[["x_px", "y_px"]].to_numpy()[fi] - tt[["x_px", "y_px"]].to_numpy()[ti])
            rep.append(df["sigma_x_px"].to_numpy()[fi])
            sizes.append(df["size"].to_numpy()[fi])
            nf += len(df)
            nm += len(fi)
            nt += len(tt)
        e = np.concatenate(errs)
        rmse = np.sqrt((e ** 2).mean(0))
        psf = render.psf_image(optics, px, 0.0, size=32, oversample=8)
        crb = np.mean(cramer_rao_bound(psf, 8, photons, 20 * 0.6, cam.read_noise))
        mort = mortensen_sigma(photons, 20 * 0.6 + cam.read_noise ** 2, float(np.median(np.concatenate(sizes))))
        ratio = rmse.mean() / crb
        print(f"{photons:8d} {nm:6d} {nm / nt:7.4f} {nm / nf:7.4f} {rmse[0]:8.4f} {rmse[1]:8.4f} {crb:7.4f} "
              f"{ratio:8.3f} {mort:9.4f} {np.abs(e.mean(0)).max():7.4f} {np.median(np.concatenate(rep)):8.4f} "
              f"{1000 * tl / n_frames:8.1f}")
        out[photons] = {"rmse_px": rmse.tolist(), "crb_px": crb, "ratio": ratio, "recall": nm / nt, "precision": nm / nf}
    print("CRB: exact bound of the rendered PSF (Fisher information, background 12 photons/px + read noise);")
    print("Mortensen: eq. 5 of Mortensen et al. 2010 with the fitted Gaussian width (a Gaussian-PSF approximation,")
    print("lower than the true bound because an Airy PSF puts photons into its rings); reported: median per-spot sigma_x.")
    return out


def _calib(optics, z, photons=20000.0, seed=1):
    cam = render.Camera(photons=photons, background=15.0)
    stack = np.stack(list(render.calibration_images(z, shape=(72, 72), optics=optics, camera=cam, seed=seed)))
    return build_calibration(stack, z, render.sample_pixel_size(optics, cam.pixel_pitch), source="bench")


def _eval_3d(feats_by_frame, t, cm_min=0.5, r=3.0):
    rows = []
    for f, tt in t.groupby("frame"):
        df = feats_by_frame.get(f, pd.DataFrame(columns=["x_px", "y_px", "z", "cm"]))
        df = df[df["cm"] >= cm_min]
        fi, ti = match(df[["x_px", "y_px"]].to_numpy(float), tt[["x_px", "y_px"]].to_numpy(), r)
        matched_t = np.zeros(len(tt), bool)
        matched_t[ti] = True
        dz = np.full(len(tt), np.nan)
        dz[ti] = df["z"].to_numpy()[fi] - tt["z"].to_numpy()[ti]
        fz = df["z"].to_numpy()
        matched_f = np.zeros(len(df), bool)
        matched_f[fi] = True
        rows.append((tt["z"].to_numpy(), matched_t, dz, fz, matched_f))
    tz = np.concatenate([r[0] for r in rows])
    mt = np.concatenate([r[1] for r in rows])
    dz = np.concatenate([r[2] for r in rows])
    fz = np.concatenate([r[3] for r in rows])
    mf = np.concatenate([r[4] for r in rows])
    return tz, mt, dz, fz, mf


def _print_3d(label, tz, mt, dz, fz, mf, depth, bins):
    rm = np.sqrt(np.nanmean(dz[mt] ** 2))
    print(f"{label}: n_true {len(tz)}, recall {mt.mean():.4f}, precision {mf.mean() if len(mf) else float('nan'):.4f}, "
          f"z RMSE {rm * 1e6:.4f} um = {100 * rm / depth:.2f} % of the {depth * 1e6:.1f} um depth, "
          f"median |dz| {np.nanmedian(np.abs(dz[mt])) * 1e6:.4f} um")
    print(f"    {'z bin (um)':>14} {'n':>5} {'recall':>7} {'precis.':>7} {'z RMSE um':>9} {'bias um':>8}")
    for lo, hi in zip(bins[:-1], bins[1:]):
        s = (tz >= lo) & (tz < hi)
        sf = (fz >= lo) & (fz < hi)
        r = np.sqrt(np.nanmean(dz[s & mt] ** 2)) * 1e6 if (s & mt).any() else float("nan")
        b = np.nanmean(dz[s & mt]) * 1e6 if (s & mt).any() else float("nan")
        print(f"    {lo * 1e6:6.2f}..{hi * 1e6:5.2f} {s.sum():5d} {mt[s].mean() if s.any() else float('nan'):7.3f} "
              f"{mf[sf].mean() if sf.any() else float('nan'):7.3f} {r:9.4f} {b:8.4f}")
    return rm


def section_b(quick):
    print("\n## B. z by GDPT (astigmatic optics 120 nm, calibration +-3 um in 0.1 um steps at 20000 photons)")
    print("command: .venv/bin/python bench/bench_pipeline.py  (section B)")
    optics = render.Optics(astigmatism=1.2e-7)
    z = np.round(np.arange(-3e-6, 3.0001e-6, 0.1e-6), 12)
    cal = _calib(optics, z)
    depth = cal.depth
    bins = np.linspace(-3e-6, 3e-6, 7)
    out = {}
    rng = np.random.default_rng(2)
    for photons in (20000.0, 4000.0):
        cam = render.Camera(photons=photons, background=15.0)
        px = render.sample_pixel_size(optics, cam.pixel_pitch)
        table, t = grid_truth(4 if quick else 12, (256, 256), 60, rng, margin=40, px=px,
                              z=lambda n: rng.uniform(-2.95e-6, 2.95e-6, n))
        feats = {}
        t0 = time.perf_counter()
        for f, frame in enumerate(render.render_frames(table, shape=(256, 256), optics=optics, camera=cam, seed=3)):
            feats[f] = locate_3d(prepare(frame, bg_size=3 * cal.size), cal, cm_min=0.0)
        el = time.perf_counter() - t0
        res = _eval_3d(feats, t)
        rm = _print_3d(f"isolated particles, {photons:.0f} photons ({el / len(feats):.2f} s/frame incl. rendering)",
                       *res, depth, bins)
        out[photons] = {"z_rmse_m": rm, "z_rmse_pct_depth": 100 * rm / depth, "recall": float(res[1].mean())}
    # the shipped dataset (28 particles in 160 x 160 px: many overlapping defocused images)
    d = ROOT / "data" / "synthetic" / "diffusion3d"
    if (d / "movie.tif").exists():
        out["diffusion3d"] = _crowded(d, bins)
    else:
        print("    (data/synthetic/diffusion3d missing: run 'make data')")
    d = ROOT / "data" / "synthetic" / "epd_brightfield"
    if (d / "calib.tif").exists():
        out["epd_brightfield"] = _brightfield(d)
    else:
        print("    (data/synthetic/epd_brightfield with its calibration stack missing: run 'make data')")
    return out


def _image_radius(cal, z):
    """Half the side of the calibration template nearest to each height (px): how far a particle's image reaches."""
    sides = np.array([t.shape[0] for t in cal.templates], float)
    k = np.clip(np.searchsorted(cal.z, z), 0, len(cal.z) - 1)
    return sides[k] / 2


def _gdpt_movie(path, cal, brightfield=False):
    """GDPT on every frame of a movie (no Cm cut): ({frame: features}, seconds per frame)."""
    from ptrack.calibration import prepare_gdpt

    feats = {}
    t0 = time.perf_counter()
    with open_movie(path) as mv:
        for f in range(len(mv)):
            feats[f] = locate_3d(prepare_gdpt(mv[f], cal, brightfield=brightfield), cal, cm_min=0.0)
    return feats, (time.perf_counter() - t0) / max(len(feats), 1)


def _crowded(d, bins):
    """GDPT on the shipped crowded movie: all particles, binned in z, and split by overlap of their images."""
    params = json.loads((d / "params.json").read_text())
    cal = load_calibration(d / "calib.tif", z_csv=d / "calib_z.csv")
    truth_all = pd.read_parquet(d / "truth.parquet")
    truth = truth_all[truth_all["in_frame"]] if "in_frame" in truth_all else truth_all
    feats, el = _gdpt_movie(d / "movie.tif", cal)
    res = _eval_3d(feats, truth)
    rm = _print_3d(f"data/synthetic/diffusion3d ({params['n_particles']} particles, {params['camera']['photons']:.0f} "
                   f"photons, 160 x 160 px, images up to 65 px wide: most overlap; {1000 * el:.0f} ms/frame)",
                   *res, cal.depth, bins)
    # overlap: another particle (in the frame or just outside) closer than the sum of the two image radii
    over, nn = [], []
    for f, tt in truth.groupby("frame"):
        allp = truth_all[truth_all["frame"] == f]
        xy, rad = allp[["x_px", "y_px"]].to_numpy(), _image_radius(cal, allp["z"].to_numpy())
        dd = np.hypot(tt["x_px"].to_numpy()[:, None] - xy[:, 0], tt["y_px"].to_numpy()[:, None] - xy[:, 1])
        dd[dd == 0] = np.inf
        over.append((dd < _image_radius(cal, tt["z"].to_numpy())[:, None] + rad).any(1))
        nn.append(dd.min(1))
    over, nn = np.concatenate(over), np.concatenate(nn)
    tz, mt, dz = res[0], res[1], res[2]
    print(f"    {'subset':>34} {'n':>5} {'recall':>7} {'z RMSE um':>9} {'% depth':>8} {'median|dz| um':>13} {'|dz|>0.3um':>10}")
    rows = [("images overlap another", over), ("images do not overlap", ~over)]
    rows += [(f"nearest neighbour {lo}-{hi} px", (nn >= lo) & (nn < hi)) for lo, hi in ((0, 10), (10, 20), (20, 40))]
    rows += [("nearest neighbour >= 40 px", nn >= 40)]
    sub = {}
    for name, m in rows:
        a = np.abs(dz[m & mt])
        r = np.sqrt(np.mean(a ** 2)) if a.size else float("nan")
        print(f"    {name:>34} {m.sum():5d} {mt[m].mean() if m.any() else float('nan'):7.3f} {r * 1e6:9.4f} "
              f"{100 * r / cal.depth:8.2f} {np.median(a) * 1e6 if a.size else float('nan'):13.4f} "
              f"{np.mean(a > 3e-7) if a.size else float('nan'):10.3f}")
        sub[name] = {"n": int(m.sum()), "recall": float(mt[m].mean()) if m.any() else None,
                     "z_rmse_pct_depth": float(100 * r / cal.depth)}
    print("    (match: mutual nearest neighbours within 3 px = 0.31 um; a particle found > 3 px off counts as missed and"
          " as a false detection)")
    r9 = _eval_3d(feats, truth, cm_min=0.9)
    a9 = np.abs(r9[2][r9[1]])
    print(f"    at Cm >= 0.9 instead of 0.5: recall {r9[1].mean():.4f}, precision {r9[4].mean():.4f}, z RMSE "
          f"{100 * np.sqrt(np.mean(a9 ** 2)) / cal.depth:.2f} % of depth, |dz| > 1 um: {int((a9 > 1e-6).sum())} "
          f"(at 0.5: {int((np.abs(dz[mt]) > 1e-6).sum())})")
    r5 = _eval_3d(feats, truth, r=5.0)
    a5 = np.abs(r5[2][r5[1]])
    print(f"    the same with a 5 px (0.52 um) match radius: recall {r5[1].mean():.4f}, precision {r5[4].mean():.4f}, "
          f"z RMSE {100 * np.sqrt(np.mean(a5 ** 2)) / cal.depth:.2f} % of depth (the extra matches: particles in "
          f"clusters found 3-5 px off, most with a poor z)")
    return {"recall": float(mt.mean()), "precision": float(res[4].mean()), "z_rmse_pct_depth": 100 * rm / cal.depth,
            "ms_per_frame": 1000 * el, "subsets": sub}


def _brightfield(d):
    """Brightfield GDPT on the shipped epd_brightfield movie (dark particles, signed defocused images)."""
    cal = load_calibration(d / "calib.tif", z_csv=d / "calib_z.csv", brightfield=True)
    truth = pd.read_parquet(d / "truth.parquet")
    truth = truth[truth["in_frame"]] if "in_frame" in truth else truth
    feats, el = _gdpt_movie(d / "movie.tif", cal, brightfield=True)
    res = _eval_3d(feats, truth)
    bins = np.array([cal.z[0], 2e-6, 4e-6, 6e-6, 8e-6, 10e-6, 12e-6, cal.z[-1] + 1e-9])
    rm = _print_3d(f"data/synthetic/epd_brightfield (brightfield, 20x NA 0.4, calibration {cal.z[0] * 1e6:.2f}-"
                   f"{cal.z[-1] * 1e6:.2f} um; {1000 * el:.0f} ms/frame)", *res, cal.depth, bins)
    print("    (deposited particles sit at z = R = the first calibration page: their z can only err upwards)")
    return {"recall": float(res[1].mean()), "precision": float(res[4].mean()), "z_rmse_pct_depth": 100 * rm / cal.depth,
            "ms_per_frame": 1000 * el}


def section_c():
    print("\n## C. D on data/synthetic/diffusion2d (ptrack.analysis.analyze_movie)")
    print("command: .venv/bin/python bench/bench_pipeline.py  (section C)")
    from ptrack.msd import estimate_diffusion
    from ptrack.analysis import analyze_movie

    d = ROOT / "data" / "synthetic" / "diffusion2d"
    if not (d / "movie.tif").exists():
        print("    (data/synthetic/diffusion2d missing: run 'make data')")
        return {}
    params = json.loads((d / "params.json").read_text())
    cam = params["camera"]
    meta = params.get("table_meta", {})
    t0 = time.perf_counter()
    s = analyze_movie(d / "movie.tif", radius=params.get("radius", 2.5e-7), viscosity=meta.get("viscosity", 1e-3),
                      temperature=meta.get("temperature", 293.15), gain=cam["gain"], offset=cam["offset"],
                      read_noise=cam["read_noise"], motion_blur=0.0, progress=False).summary   # rendered without blur
    el = time.perf_counter() - t0
    truth = pd.read_parquet(d / "truth.parquet")
    truth = truth[truth["in_frame"]] if "in_frame" in truth else truth
    tt = make_table(truth["frame"], truth["t"], truth["particle"], truth["x"], truth["y"],
                    meta={"frame_interval": params["frame_interval"]})
    # the true tracks as the camera sees them, with the same field-of-view correction as ours
    d_truth = estimate_diffusion(tt, axes=("x", "y", "xy"), n_boot=200, field_of_view="auto").D
    d_true = params["D_true"]
    um = 1e12
    print(f"    {'axis':>4} {'D ours um2/s':>13} {'+-':>7} {'D truth tracks':>14} {'ours/truth-1':>12} {'D_true':>7} {'ours/D_true-1':>13}")
    for a in ("x", "y", "xy"):
        print(f"    {a:>4} {s['D'][a] * um:13.4f} {s['D_err'][a] * um:7.4f} {d_truth[a] * um:14.4f} "
              f"{100 * (s['D'][a] / d_truth[a] - 1):11.2f}% {d_true * um:7.4f} {100 * (s['D'][a] / d_true - 1):12.2f}%")
    pr = s["D_pairs"] or {}
    print(f"    reported: {s['D_method']}; from tracks (CVE, field-of-view corrected) "
          f"{s['D_tracks']['xy'] * um:.4f} +- {s['D_tracks_err']['xy'] * um:.4f}"
          + (f", linking-free {pr['D']['xy'] * um:.4f} +- {pr['D_err']['xy'] * um:.4f}"
             f" (link ambiguity {pr['link_ambiguity']:.3f})" if pr else ""))
    print(f"    n_tracks {s['n_tracks']}, Stokes-Einstein {s['D_stokes_einstein'] * um:.4f} um^2/s, "
          f"analysis wall time {el:.1f} s")
    # decomposition: the truth positions on exactly the rows (and links) we tracked
    from ptrack.pipeline import track_movie

    ours, _ = track_movie(d / "movie.tif", gain=cam["gain"], offset=cam["offset"], read_noise=cam["read_noise"],
                          progress=False)
    all_truth = pd.read_parquet(d / "truth.parquet")
    # each of our rows with its nearest true particle of the frame, at any range (the one rule, match_truth)
    ours_r, truth_r = ours.reset_index(drop=True), all_truth.reset_index(drop=True)
    fi, ti = match_truth(ours_r, truth_r, max_px=np.inf)
    q, g = truth_r.loc[ti], ours_r.loc[fi]
    m = pd.DataFrame({"frame": g["frame"].to_numpy(), "particle": g["particle"].to_numpy(), "x": q["x"].to_numpy(),
                      "y": q["y"].to_numpy(), "d": np.hypot(*(g[["x_px", "y_px"]].to_numpy()
                                                              - q[["x_px", "y_px"]].to_numpy()).T)})
    tm = make_table(m["frame"], m["frame"] * params["frame_interval"], m["particle"], m["x"], m["y"],
                    meta={"frame_interval": params["frame_interval"]})
    d_same = estimate_diffusion(tm, axes=("xy",), n_boot=0, field_of_view="auto").D["xy"]
    d_ours = estimate_diffusion(ours, axes=("xy",), n_boot=0, field_of_view="auto").D["xy"]
    print(f"    truth positions on the rows and links we tracked: D_xy {d_same * um:.4f} um^2/s; ours/that - 1 = "
          f"{100 * (d_ours / d_same - 1):.2f}% (localisation + linking error); that/truth tracks - 1 = "
          f"{100 * (d_same / d_truth['xy'] - 1):.2f}% (which rows are seen: edges, overlapping particles); "
          f"{100 * (m['d'] > 0.5).mean():.1f}% of our rows are > 0.5 px from a true particle (overlaps)")
    return {"D_xy": s["D"]["xy"], "D_truth_tracks": d_truth["xy"], "D_true": d_true}


def make_big_movie(path: Path, n=50, n_frames=130, shape=(2160, 2560), seed=0):
    """Render the seed-sized series (2560 x 2160 uint16, 130 frames) with n diffusing particles."""
    if (path / "movie.tif").exists():
        return path / "movie.tif"
    rng = np.random.default_rng(seed)
    cam = render.Camera(photons=2000 / 0.6)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    H, W = shape
    D, dt = 0.86e-12, 0.1
    x0, y0 = rng.uniform(50, W - 50, n) * px, rng.uniform(50, H - 50, n) * px
    st = rng.normal(0, np.sqrt(2 * D * dt), (2, n, n_frames))
    st[:, :, 0] = 0
    x, y = x0[:, None] + st[0].cumsum(1), y0[:, None] + st[1].cumsum(1)
    fr = np.tile(np.arange(n_frames), n)
    tab = make_table(fr, fr * dt, np.repeat(np.arange(n), n_frames), x.ravel(), y.ravel(), np.zeros(n * n_frames),
                     meta={"frame_interval": dt})
    render.render_movie(tab, path, shape=shape, camera=cam, seed=1, progress=False)
    return path / "movie.tif"


def section_d(workdir: Path):
    print("\n## D. Speed: 2560 x 2160 x 130 frames uint16 (1.44 GB), 50 particles, 2D")
    movie = make_big_movie(workdir / "big")
    out = workdir / "big.traj.parquet"
    js = workdir / "big.json"
    cmd = [str(ROOT / ".venv" / "bin" / "ptrack"), "track", str(movie), "--out", str(out), "--json", str(js),
           "--gain", "2.17", "--offset", "100", "--read-noise", "1.2"]
    print("command: " + " ".join(cmd))
    subprocess.run(cmd, check=True, capture_output=True)   # warm-up (numba cache, page cache)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    total = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    s = json.loads(js.read_text())
    print(f"    pipeline wall time {s['wall_time_s']:.2f} s ({s['frames_per_s']:.1f} frames/s; recorded at 10 fps = 13 s), "
          f"process total {total:.2f} s incl. start-up, peak RSS {rss:.0f} MB, {s['n_localisations']} localisations, "
          f"{s['n_tracks']} tracks; load average at start {load:.1f} on {os.cpu_count()} cores")
    return {"wall_time_s": s["wall_time_s"], "total_s": total, "peak_rss_mb": rss}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-speed", action="store_true", help="skip section D (renders a 1.4 GB movie into /tmp)")
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "ptrack_bench"))
    ap.add_argument("--only", choices=("A", "B", "C", "D"), help="run one section")
    args = ap.parse_args()
    wd = Path(args.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    run = (lambda k: args.only in (None, k))
    if run("A"):
        section_a(args.quick)
    if run("B"):
        section_b(args.quick)
    if run("C"):
        section_c()
    if run("D") and not args.skip_speed:
        section_d(wd)


if __name__ == "__main__":
    main()
