"""The main job (``make run``): the shipped synthetic data analysed end to end.

1. ``data/synthetic/diffusion2d``: movie -> preprocessing -> sub-pixel
   localisation -> linking -> MSD -> D per axis, compared with the ground truth
   (the D the movie was rendered with, and the D of its true tracks by the same
   estimator) and with Stokes-Einstein.
2. ``data/synthetic/diffusion3d``: the same with z from the defocus calibration
   stack (GDPT); z error against the ground truth; D in x, y and z.
3. ``data/synthetic/epd_brightfield``: a brightfield movie (inverted) of
   particles drifting to the substrate, z from its brightfield calibration
   stack; the measured drift velocity towards the electrode (before contact)
   against the Henry velocity the movie was rendered with.

Results (tables, PNG plots, ``summary.json``) go to ``out/mainjob/`` in the
working folder (or the folder given as the first argument). The data are
``data/synthetic/`` of a source checkout, or the copy installed with the
package (``ptrack/datasets/``).
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from .errors import UserError
from .motion import estimate_diffusion, match_truth, stokes_einstein
from .table import read_table

ROOT = Path(__file__).resolve().parent.parent


def _data_dir() -> Path:
    """The shipped datasets: ``data/synthetic`` of a source checkout, else the installed ``ptrack/datasets``."""
    src = ROOT / "data" / "synthetic"
    return src if src.is_dir() else Path(__file__).resolve().parent / "datasets"


DATA = _data_dir()
UM2 = 1e12  # m^2/s -> µm²/s


def _params(name: str) -> dict:
    path = DATA / name / "params.json"
    if not path.exists():
        raise UserError(f"shipped dataset missing: {path}", "regenerate it with 'make data'")
    return json.loads(path.read_text())


def verdict(value: float, ref: float, err: float, what: str, limit: float = 3.0) -> str:
    """One line: how many standard errors ``value`` is from ``ref``, and ok / CHECK at ``limit`` SE.

    Examples
    --------
    >>> verdict(1.02, 1.0, 0.02, "D_xy against the true tracks")
    'D_xy against the true tracks: +2.0 %, 1.0 SE: ok'
    """
    z = abs(value - ref) / err if err > 0 else float("inf")
    return f"{what}: {100 * (value / ref - 1):+.1f} %, {z:.1f} SE: {'ok' if z <= limit else 'CHECK'}"


def camera_kwargs(p: dict) -> dict:
    """The camera calibration a user would pass (--gain, --offset, --read-noise), from the dataset's parameters."""
    cam = p.get("camera", {})
    return {k: float(cam[k]) for k in ("gain", "offset", "read_noise") if k in cam}


def job_2d(out: Path) -> dict:
    from .analysis import analyze_movie

    p = _params("diffusion2d")
    # The shipped movies have no motion blur (short exposure): R = 0 for the CVE's localisation variance.
    res = analyze_movie(DATA / "diffusion2d" / "movie.tif", radius=p["radius"], viscosity=p["viscosity"],
                        temperature=p["temperature"], report_dir=out / "diffusion2d",
                        out=out / "diffusion2d" / "trajectories.parquet", motion_blur=0.0,
                        **camera_kwargs(p)).summary
    truth = read_table(DATA / "diffusion2d" / "truth.parquet")
    if "in_frame" in truth.columns:
        truth = truth[truth["in_frame"].astype(bool)]
    # the true tracks as the camera sees them, with the same estimator and field-of-view correction
    ref = estimate_diffusion(truth, axes=("x", "y", "xy"), estimator="cve", motion_blur=0.0, field_of_view="auto")
    d_se = float(stokes_einstein(p["radius"], p["viscosity"], p["temperature"]))
    pr = res["D_pairs"] or {"D": {a: float("nan") for a in ("x", "y", "xy")},
                            "D_err": {a: float("nan") for a in ("x", "y", "xy")}, "link_ambiguity": float("nan")}
    print("\n== 2D diffusion movie (data/synthetic/diffusion2d: 130 frames, 10 fps, R = 250 nm in water)")
    print(f"   tracks: {res['n_tracks']}   D in µm²/s (± standard error); field-of-view corrected;"
          f" link ambiguity {pr['link_ambiguity']:.3f}")
    print(f"   {'axis':<5}{'from tracks':>18}{'linking-free':>18}{'true tracks':>18}{'rendered D':>12}"
          f"{'Stokes-Einstein':>17}")
    for a in ("x", "y", "xy"):
        print(f"   {a:<5}{res['D_tracks'][a] * UM2:>10.4f} ± {res['D_tracks_err'][a] * UM2:.4f}"
              f"{pr['D'][a] * UM2:>10.4f} ± {pr['D_err'][a] * UM2:.4f}"
              f"{ref.D[a] * UM2:>10.4f} ± {ref.D_err[a] * UM2:.4f}{p['D_true'] * UM2:>12.4f}{d_se * UM2:>17.4f}")
    err_true = res["D"]["xy"] / p["D_true"] - 1
    err_tracks = res["D"]["xy"] / ref.D["xy"] - 1
    print(f"   reported D_xy ({res['D_method']}) = {res['D']['xy'] * UM2:.4f} ± {res['D_err']['xy'] * UM2:.4f} µm²/s:"
          f" {100 * err_true:+.2f} % from the rendered D, {100 * err_tracks:+.2f} % from the true tracks"
          f" (standard error {100 * res['D_err']['xy'] / res['D']['xy']:.1f} %)")
    print("   verdict: " + verdict(res["D"]["xy"], ref.D["xy"], math.hypot(res["D_err"]["xy"], ref.D_err["xy"]),
                                   f"reported D_xy against the true tracks ({res['n_tracks']} tracks of "
                                   f"{truth['particle'].nunique()} true particles: one leaving and re-entering the "
                                   "view starts a new track)"))
    return {"D": res["D"], "D_err": res["D_err"], "D_method": res["D_method"], "D_tracks": res["D_tracks"],
            "D_pairs": res["D_pairs"], "D_true": p["D_true"], "D_truth_tracks": ref.D,
            "D_stokes_einstein": d_se, "n_tracks": res["n_tracks"], "rel_err_vs_true": err_true,
            "rel_err_vs_truth_tracks": err_tracks}


def job_3d(out: Path) -> dict:
    from .pipeline import track_movie

    p = _params("diffusion3d")
    d = DATA / "diffusion3d"
    table, summary = track_movie(d / "movie.tif", out=out / "diffusion3d" / "trajectories.parquet",
                                 calib=d / "calib.tif", calib_z=d / "calib_z.csv", **camera_kwargs(p))
    truth = read_table(d / "truth.parquet")
    if "in_frame" in truth.columns:
        truth = truth[truth["in_frame"].astype(bool)].reset_index(drop=True)
    found = table.reset_index(drop=True)
    fi, ti = match_truth(found, truth)
    z_err = found.loc[fi, "z"].to_numpy() - truth.loc[ti, "z"].to_numpy()
    ok = np.isfinite(z_err)
    z_rmse = float(np.sqrt(np.mean(z_err[ok] ** 2))) if ok.any() else float("nan")
    recall = len(np.unique(ti)) / max(len(truth), 1)
    z_span = float(truth["z"].max() - truth["z"].min())
    res = estimate_diffusion(table, axes=("x", "y", "z"), estimator="cve", motion_blur=0.0, field_of_view="auto")
    _plot_3d(found.loc[fi], truth.loc[ti], out / "diffusion3d" / "z_vs_truth.png")
    print("\n== 3D diffusion movie with its calibration stack (data/synthetic/diffusion3d, GDPT z)")
    print(f"   localisations matched to truth: recall {recall:.3f}; z RMSE {z_rmse * 1e9:.1f} nm "
          f"over a {z_span * 1e6:.2f} µm span of true heights, median |dz| {np.nanmedian(np.abs(z_err)) * 1e9:.0f} nm")
    if "chi2" in found.columns:
        # chi2: light the fitted templates leave unexplained; high where overlapping images compromise the match
        good = ok & (found.loc[fi, "chi2"].to_numpy() <= 2.0)
        print(f"   matches the templates explain (chi2 <= 2, {good.mean():.0%} of them): z RMSE "
              f"{np.sqrt(np.mean(z_err[good] ** 2)) * 1e9:.0f} nm; the rest are overlapping images")
    # the true tracks through the same estimator: in z the particles are confined between walls
    # 5 um apart, which lowers the frame-to-frame MSD below 2 D dt
    ref = estimate_diffusion(truth, axes=("x", "y", "z"), estimator="cve", motion_blur=0.0, field_of_view="auto")
    print("   D (µm²/s): " + "  ".join(f"{a} {res.D[a] * UM2:.3f} ± {res.D_err[a] * UM2:.3f}" for a in ("x", "y", "z"))
          + f"   rendered D {p['D_true'] * UM2:.3f}")
    print("   true tracks: " + "  ".join(f"{a} {ref.D[a] * UM2:.3f}" for a in ("x", "y", "z"))
          + "   (z confined between walls 5 µm apart: D_z of the true tracks is the reference, not the free D)")
    for a in ("z", "x", "y"):
        print("   verdict: " + verdict(res.D[a], ref.D[a], math.hypot(res.D_err[a], ref.D_err[a]),
                                       f"D_{a} against the true tracks" + (" (confined)" if a == "z" else "")))
    return {"recall": recall, "z_rmse": z_rmse, "D": res.D, "D_err": res.D_err, "D_true": p["D_true"],
            "D_truth_tracks": ref.D, "n_tracks": summary["n_tracks"]}


def _plot_3d(found, truth, path: Path) -> None:
    """GDPT check: measured against true z, and the correlation Cm against z."""
    from .plot import new_figure, save_figure

    fig, (a1, a2) = new_figure(figsize=(10, 4.2), dpi=110, ncols=2)
    zt, zm = truth["z"].to_numpy() * 1e6, found["z"].to_numpy() * 1e6
    a1.plot(zt, zm, ".", ms=2, alpha=0.5)
    lim = [np.nanmin(zt), np.nanmax(zt)]
    a1.plot(lim, lim, "k-", lw=0.8, label="measured = true")
    a1.set(xlabel="true z (µm)", ylabel="measured z (µm)", title="z from the calibration stack")
    a1.legend()
    a2.plot(zm, found["cm"].to_numpy(), ".", ms=2, alpha=0.5)
    a2.set(xlabel="measured z (µm)", ylabel="correlation Cm", title="GDPT correlation against z", ylim=(0, 1.02))
    fig.tight_layout()
    save_figure(fig, path)


def job_brightfield(out: Path) -> dict:
    from .pipeline import track_movie
    from .velocity import ensemble_velocity, particle_velocity, plot_velocity, trim_deposited, velocity_profile

    p = _params("epd_brightfield")
    d = DATA / "epd_brightfield"
    od = out / "epd_brightfield"
    table, summary = track_movie(d / "movie.tif", out=od / "trajectories.parquet", calib=d / "calib.tif",
                                 calib_z=d / "calib_z.csv", brightfield=True, **camera_kwargs(p))
    truth = read_table(d / "truth.parquet")
    found = table.reset_index(drop=True)
    fi, ti = match_truth(found, truth.reset_index(drop=True))
    z_err = found.loc[fi, "z"].to_numpy() - truth.reset_index(drop=True).loc[ti, "z"].to_numpy()
    z_rmse = float(np.sqrt(np.nanmean(z_err ** 2)))
    recall = len(np.unique(ti)) / max(len(truth), 1)
    # drift before deposition: each track's rows from touch-down on are dropped (they would pull v to 0)
    moving = trim_deposited(table, p["radius"], 0.5e-6)
    vel = particle_velocity(moving, axes="xyz", motion_blur=0.0)
    ens = ensemble_velocity(vel, seed=0).set_index("axis")
    prof = velocity_profile(moving, bins=6, motion_blur=0.0, vel=vel)
    plot_velocity(moving, vel, od / "velocity.png", profile=prof, v_ref=p["vz_drift"])
    vz, vz_err = float(ens.loc["z", "v"]), float(ens.loc["z", "v_err"])
    deposited = int(truth.groupby("particle")["deposited"].any().sum()) if "deposited" in truth else 0
    print("\n== Brightfield EPD movie (data/synthetic/epd_brightfield: 20x NA 0.4, dark particles, inverted; "
          "z from its brightfield calibration stack)")
    n_true = truth["particle"].nunique()
    print(f"   {summary['n_localisations']} localisations in {summary['n_frames']} frames; {summary['n_tracks']} tracks"
          f" found for {n_true} true particles (a track broken by a missed frame counts twice);"
          f" recall {recall:.3f}; z RMSE {z_rmse * 1e9:.0f} nm over {p['start_heights'][1] * 1e6:.0f} µm of travel")
    print(f"   drift towards the electrode before contact: v_z = {vz * 1e6:.2f} ± {vz_err * 1e6:.2f} µm/s"
          f" ({len(vel)} tracks); rendered {p['vz_drift'] * 1e6:.2f} µm/s (Henry {-p['v_henry'] * 1e6:.2f}"
          f" + settling); {(vz / p['vz_drift'] - 1) * 100:+.1f} %, {abs(vz - p['vz_drift']) / vz_err:.1f} SE")
    print(f"   {deposited} of the {n_true} true particles deposited by the last frame")
    print("   verdict: " + verdict(vz, p["vz_drift"], vz_err, "v_z against the rendered drift"))
    return {"n_localisations": summary["n_localisations"], "n_tracks": summary["n_tracks"], "recall": recall,
            "z_rmse": z_rmse, "vz": vz, "vz_err": vz_err, "vz_rendered": p["vz_drift"], "v_henry": p["v_henry"],
            "deposited": deposited}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path.cwd() / "out" / "mainjob"      # the working folder, never the install
    t0 = time.perf_counter()
    try:
        summary = {"diffusion2d": job_2d(out), "diffusion3d": job_3d(out), "epd_brightfield": job_brightfield(out)}
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary["wall_time_s"] = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    print(f"\nDone in {summary['wall_time_s']:.1f} s. Plots, tables and summary.json in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
