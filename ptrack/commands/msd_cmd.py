"""MSD and diffusion coefficients of a trajectories table (Parquet or CSV, SI units).

Prints D ± standard error per axis in m^2/s and µm²/s (the seed's Table 4.1
layout: D_x, D_y, D_xy side by side), the localisation error, the number of
tracks, the tracks flagged as non-diffusive (power-law exponent alpha outside
the range expected for Brownian tracks of the same length), and, when a
radius and a viscosity are given (or the table has a 'radius' column), the
Stokes-Einstein value kB T / (6 pi mu r) and the ratio D / D_SE. The
temperature defaults to 293.15 K (room temperature, as in the seed). Writes
the log-log MSD plot with the fitted model (default: <TRAJ>_msd.png in the
working folder) and, with --json, a machine-readable summary.

Defaults that depend on the table, each said in the output: the
field-of-view correction is on for tables from a camera (with ``x_px``
columns: measured or rendered movies), off for simulated positions; the
motion blur R comes from the metadata or the localisation errors, else 1/6.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from ..errors import UserError, atomic_output, check_positive


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("traj", metavar="TRAJ", help="trajectories table (.parquet or .csv; frame, t, particle, x, y, z in SI units)")
    p.add_argument("--dims", default="x,y,xy", help="comma-separated axes: x, y, z, xy, xz, yz, xyz (default: x,y,xy)")
    p.add_argument("--estimator", default="cve", choices=("cve", "ols"),
                   help="cve: covariance-based estimator (Vestergaard et al. 2014, default); "
                        "ols: least squares over the optimal number of lags (Michalet 2010)")
    p.add_argument("--motion-blur", type=float, default=None,
                   help="motion-blur parameter R = exposure / frame interval / 6: 1/6 full-frame exposure, 0 "
                        "instantaneous (simulations); default: from the table's metadata or its localisation errors, "
                        "else 1/6 (the output says which)")
    p.add_argument("--radius", type=float, help="particle radius, m (for Stokes-Einstein; default: median of the table's 'radius' column if any)")
    p.add_argument("--viscosity", type=float, help="fluid viscosity, Pa s (for Stokes-Einstein)")
    p.add_argument("--temperature", type=float, default=293.15, help="temperature, K (default 293.15)")
    p.add_argument("--max-lag", type=int, default=None, help="longest lag of the MSD curve, frames (default min(100, longest track - 1))")
    p.add_argument("--subtract-drift", action="store_true", help="remove the common drift first (with the (1 - 1/M) bias correction)")
    p.add_argument("--exclude-flagged", action="store_true", help="leave out the tracks flagged as non-diffusive")
    p.add_argument("--flag-level", type=float, default=0.01, help="false-positive rate of the non-diffusive flag on Brownian tracks (default 0.01)")
    p.add_argument("--n-boot", type=int, default=200, help="bootstrap resamples over whole particles (default 200)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the bootstrap and flag bounds")
    p.add_argument("--field-of-view", default=None, metavar="none|auto|x,y[,z]",
                   help="correct the loss of long steps at the edges of the field of view: 'auto' = the range of x "
                        "and y, or the components whose range limits what is seen, e.g. x,y,z; 'none' for positions "
                        "not cut by a field (default: auto for tables from a camera, with x_px columns; else none)")
    p.add_argument("--linking-free", action="store_true",
                   help="also estimate D without the links (ptrack.motion.pair_diffusion: unbiased when particles "
                        "move a fair fraction of their spacing per frame)")
    p.add_argument("--json", metavar="OUT", help="write a JSON summary")
    p.add_argument("--plot", metavar="OUT.png", help="MSD plot path (default <TRAJ>_msd.png in the working folder)")
    p.add_argument("--no-plot", action="store_true", help="do not write the plot")
    p.add_argument("--tracks-out", metavar="OUT.csv",
                   help="write one row per track: CVE D per axis with its error, alpha, flag and reason")


def _fmt(v, e):
    if v is None or not math.isfinite(v):
        return "n/a"
    return f"{v:.4g} ± {e:.2g}" if e is not None and math.isfinite(e) else f"{v:.4g}"


def _check_args(args):
    """Every option checked before the table is read: (axes, plot path or None)."""
    from .. import msd as M

    axes = M.parse_axes(args.dims)
    # the numeric options (--radius, --viscosity, --temperature, --motion-blur, --n-boot, --flag-level,
    # --max-lag, ...) were checked against their ranges by ptrack.cli (ptrack.options, the one table)
    if args.radius is not None and args.viscosity is None:
        raise UserError("--radius given without --viscosity", "give --viscosity (Pa s) for the Stokes-Einstein value")
    if args.tracks_out is not None and Path(args.tracks_out).suffix.lower() != ".csv":
        raise UserError(f"--tracks-out {args.tracks_out} is not a .csv file", "give a path ending in .csv")
    # outputs go where the user points, else into the working folder (never beside the input)
    plot_path = None if args.no_plot else Path(args.plot) if args.plot else Path.cwd() / (Path(args.traj).stem + "_msd.png")
    if plot_path is not None and plot_path.suffix.lower() != ".png":
        raise UserError(f"plot path {plot_path} is not a .png file", "give a path ending in .png")
    return axes, plot_path


def _field_of_view(fov_arg, df):
    """The ``field_of_view`` argument of the estimators from ``--field-of-view``, and where it came from."""
    fov_source = "given"
    if fov_arg is None:
        # a camera sees a field: its edges cut tracks (-4.5 % on D for measured tracks if not corrected)
        fov_arg = "auto" if "x_px" in df.columns else "none"
        fov_source = ("default for a table from a camera (x_px columns)" if fov_arg == "auto"
                      else "default for positions without image columns (simulations)")
    fov = {"none": None, "auto": "auto"}.get(fov_arg.strip().lower())
    if fov is None and fov_arg.strip().lower() != "none":
        fov = tuple(c.strip() for c in fov_arg.split(",") if c.strip())
    return fov, fov_source


def run(args) -> int:
    from .. import msd as M
    from ..table import read_table

    from ..motion.stokes import implausible_D_note
    from ..motion.tracks import axis_components, resolve_motion_blur

    axes, plot_path = _check_args(args)
    df = read_table(args.traj)
    M_R, R_source = resolve_motion_blur(df, args.motion_blur)
    radius = args.radius
    if radius is None and args.viscosity is not None and "radius" in df.columns:
        r = df["radius"].to_numpy(dtype=float)
        r = r[np.isfinite(r)]
        if len(r):
            radius = float(np.median(r))
            check_positive("median 'radius' of the table", radius)
    if args.viscosity is not None and radius is None:
        raise UserError("--viscosity given without --radius (and the table has no 'radius' column)",
                        "give --radius (m) for the Stokes-Einstein value")

    # the flags' axes: x, y and (if the MSD axes use it; ptrack.motion.tracks.axis_components) z
    flag_axis = "xyz" if "z" in axis_components(axes) else "xy"
    flags = M.powerlaw_flags(df, axes=flag_axis, level=args.flag_level, seed=args.seed,
                             subtract_drift=args.subtract_drift)
    flagged = flags[flags["flagged"]]
    used = df
    if args.exclude_flagged and len(flagged):
        used = df[~df["particle"].isin(flagged["particle"])]
        used.attrs.update(df.attrs)
        if used.empty:
            raise UserError("every track is flagged as non-diffusive", "run without --exclude-flagged")
    fov, fov_source = _field_of_view(args.field_of_view, df)
    res = M.estimate_diffusion(used, axes=axes, estimator=args.estimator, motion_blur=M_R, n_boot=args.n_boot,
                               seed=args.seed, subtract_drift=args.subtract_drift, max_lag=args.max_lag,
                               field_of_view=fov)
    pair = M.pair_diffusion(used, axes=axes, motion_blur=M_R) if args.linking_free else None
    d_se = M.stokes_einstein(radius, args.viscosity, args.temperature) if radius is not None else None

    # ---- report
    print(f"{args.traj}: {res.n_particles} tracks, {res.n_displacements} frame-to-frame displacements, "
          f"frame interval {res.frame_interval:.6g} s")
    est = "CVE (Vestergaard 2014)" if res.estimator == "cve" else "least squares over the optimal number of lags (Michalet 2010)"
    print(f"estimator: {est}; motion blur R = {res.motion_blur:.4g} ({R_source}); errors: {res.se_method}"
          + (f" over {args.n_boot} particle resamples" if res.se_method == "bootstrap" else " (closed form)")
          + ("; drift subtracted" if res.drift_corrected else ""))
    print(f"{'axis':<5s} {'D (m^2/s)':>26s} {'D (µm²/s)':>22s} {'sigma_loc (nm)':>15s} {'lags':>5s}" + ("   D/D_SE" if d_se else ""))
    for a in axes:
        D, e = res.D[a], res.D_err[a]
        line = f"{a:<5s} {_fmt(D, e):>26s} {_fmt(D * 1e12, e * 1e12):>22s} {res.sigma_loc[a] * 1e9:>15.3g} {str(res.n_lags[a] or '-'):>5s}"
        if d_se:
            line += f"   {D / d_se:.3f} ± {e / d_se:.2g}"
        print(line)
    print("side by side (µm²/s): " + " | ".join(f"D_{a} = {_fmt(res.D[a] * 1e12, res.D_err[a] * 1e12)}" for a in axes)
          + (f"; field of view corrected ({', '.join(M.resolve_fov(used, fov))}; {fov_source})" if fov
             else f"; no field-of-view correction ({fov_source})"))
    notes = {implausible_D_note(res.D[a]) for a in axes} - {None}
    for note in notes:
        print(f"warning: {note}")
    nonfinite = [a for a in axes if not math.isfinite(res.D[a])]
    if nonfinite:
        raise UserError(f"D_{nonfinite[0]} is not finite", "check the table's positions (m) and times (s)")
    if pair is not None:
        print("linking-free (µm²/s): " + " | ".join(f"D_{a} = {_fmt(pair.D[a] * 1e12, pair.D_err[a] * 1e12)}"
                                                    for a in axes)
              + f"; link ambiguity {pair.link_ambiguity:.3f} (above ~0.05 D from tracks is biased low)")
    if d_se:
        print(f"Stokes-Einstein: D_SE = {d_se:.4g} m^2/s = {d_se * 1e12:.4g} µm²/s "
              f"(r = {radius:.4g} m, mu = {args.viscosity:.4g} Pa s, T = {args.temperature:.5g} K)")
    n_assessed = int(np.isfinite(flags["alpha"]).sum())
    print(f"non-diffusive tracks: {len(flagged)} of {n_assessed} assessed (alpha test at a {args.flag_level:g} false-positive rate)"
          + ("; excluded" if args.exclude_flagged and len(flagged) else ""))
    for _, row in flagged.head(20).iterrows():
        print(f"  particle {int(row['particle'])}: {row['reason']}")
    if len(flagged) > 20:
        print(f"  ... and {len(flagged) - 20} more")

    if plot_path is not None:
        from ..plot import plot_msd

        plot_msd(res, plot_path, title=f"{Path(args.traj).name}: {res.estimator.upper()}")
        print(f"wrote {plot_path}")
    if args.tracks_out:
        per = M.particle_diffusion(df, axes=axes, motion_blur=M_R, subtract_drift=args.subtract_drift)
        per = per.merge(flags[["particle", "alpha", "A", "alpha_lo", "alpha_hi", "flagged", "reason"]], on="particle", how="left")
        with atomic_output(args.tracks_out, "w") as fh:
            fh.write("# units: D m^2/s, sigma m, A m^2/s^alpha; D by the CVE per track\n")
            per.to_csv(fh, index=False)
        print(f"wrote {args.tracks_out}")
    if args.json:
        out = res.to_dict()
        out["D_stokes_einstein"] = d_se
        out["ratio_D_over_D_SE"] = {a: res.D[a] / d_se for a in axes} if d_se else None
        out["stokes_einstein_inputs"] = ({"radius": radius, "viscosity": args.viscosity, "temperature": args.temperature}
                                         if d_se else None)
        out["flagged"] = [{"particle": int(r["particle"]), "alpha": float(r["alpha"]), "reason": r["reason"]}
                          for _, r in flagged.iterrows()]
        out["excluded_flagged"] = bool(args.exclude_flagged)
        out["field_of_view"] = M.resolve_fov(used, fov) if fov else None
        out["field_of_view_source"] = fov_source
        out["motion_blur_source"] = R_source
        out["warnings"] = sorted(notes)
        if pair is not None:
            out["linking_free"] = {"D": pair.D, "D_err": pair.D_err, "link_ambiguity": pair.link_ambiguity,
                                   "drift_velocity": pair.drift_velocity}
        out["source"] = str(args.traj)
        with atomic_output(args.json, "w") as fh:
            json.dump(out, fh, indent=2)
        print(f"wrote {args.json}")
    return 0
