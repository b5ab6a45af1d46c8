"""Drift velocities of a trajectories table (Parquet or CSV, SI units): per particle, ensemble, against height.

Each track's drift velocity is the generalised least squares estimate for
Brownian motion with localisation noise and motion blur (the best linear
unbiased estimate; gaps in the frame numbers allowed), with its standard
error; D and the localisation error per axis come from the drift-corrected
increments. Prints the ensemble drift (inverse-variance weighted mean,
bootstrap standard error over particles) and, for 3D tables, the velocity
against height z in bins (EPD: velocity against distance from the electrode),
in µm/s. With --contact Z (the particle centre's height at contact), each
track's rows from its touch-down on the substrate are dropped first, so the
drift is that before deposition. Writes the per-particle table (CSV, SI units: m/s, m^2/s, m), a PNG
(tracks coloured by drift speed, velocity against z with error bars) and,
with --json, a summary.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from ..errors import UserError, atomic_output


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("traj", metavar="TRAJ", help="trajectories table (.parquet or .csv; frame, t, particle, x, y, z in SI units)")
    p.add_argument("--axes", default=None,
                   help="components to analyse, e.g. xyz, xy, z (default: xyz if the table has heights, else xy)")
    p.add_argument("--motion-blur", type=float, default=None,
                   help="motion-blur parameter R = exposure / frame interval / 6: 1/6 full-frame exposure, 0 "
                        "instantaneous (simulations); default: from the table's metadata or its localisation errors, "
                        "else 1/6 (the output says which)")
    p.add_argument("--bins", type=int, default=8, help="height bins of the velocity profile against z (default 8; 0: none)")
    p.add_argument("--noise", choices=("pooled", "track"), default="pooled",
                   help="D and localisation error for the weights and errors: pooled over the tracks (default; "
                        "monodisperse particles, one localisation error) or each track's own (particles that differ)")
    p.add_argument("--contact", type=float, default=None, metavar="Z",
                   help="EPD: height of a particle's centre at contact with the substrate, m (e.g. its radius); "
                        "each track's rows from its touch-down on are dropped (running median of z within "
                        "--contact-tolerance of Z)")
    p.add_argument("--contact-tolerance", type=float, default=0.5e-6,
                   help="m, a few times the z localisation error (default 0.5e-6)")
    p.add_argument("--min-frames", type=int, default=5, help="shortest track (positions) given a velocity (default 5, at least 4)")
    p.add_argument("--weights", choices=("inverse_variance", "equal"), default="inverse_variance",
                   help="ensemble mean weights (default inverse_variance; 'equal' when the particles truly differ)")
    p.add_argument("--n-boot", type=int, default=1000, help="bootstrap resamples over whole particles (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--reference", type=float, default=None,
                   help="reference velocity along z, m/s, e.g. the Henry velocity (drawn on the plot, compared in the output)")
    p.add_argument("--out", metavar="VEL.csv", help="per-particle velocities (default <TRAJ>_velocity.csv in --report, "
                                                 "else in the working folder)")
    p.add_argument("--report", metavar="DIR", help="directory for the plot and the profile table (default: the working folder)")
    p.add_argument("--no-plot", action="store_true", help="do not write the plot")
    p.add_argument("--json", metavar="OUT", help="write a JSON summary")


def _um(v, e=None):
    if v is None or not math.isfinite(v):
        return "n/a"
    s = f"{v * 1e6:+.4g}"
    if e is not None and math.isfinite(e):
        s += f" ± {e * 1e6:.2g}"
    return s


def _clean(v):
    from ..table import to_jsonable

    return to_jsonable(v, finite=True)


def run(args) -> int:
    from .. import velocity as V
    from ..motion.velocity import default_axes
    from ..table import read_table

    from ..motion.tracks import axis_components, resolve_motion_blur

    # the numeric options (--motion-blur, --bins, --min-frames, --n-boot, --reference, --contact-tolerance...)
    # were checked against their ranges by ptrack.cli (ptrack.options, the one table)
    traj = Path(args.traj)
    # outputs go where the user points, else into the working folder (never beside the input)
    report = Path(args.report) if args.report else Path.cwd()
    out_csv = Path(args.out) if args.out else report / (traj.stem + "_velocity.csv")
    if out_csv.suffix.lower() != ".csv":
        raise UserError(f"--out {out_csv} is not a .csv file", "give a path ending in .csv")
    if report.exists() and not report.is_dir():
        raise UserError(f"--report {report} exists and is not a directory", "give a directory")

    df = read_table(traj)
    n_rows_all = len(df)
    if args.contact is not None:
        df = V.trim_deposited(df, args.contact, args.contact_tolerance)
        if df.empty:
            raise UserError(f"every row is within {args.contact_tolerance} m of contact (z <= {args.contact + args.contact_tolerance} m)",
                            "check --contact (m, the particle centre at contact) and the table's z")
    z = df["z"].to_numpy(dtype=float)
    z = z[np.isfinite(z)]
    z_flat = len(z) > 0 and float(z.max()) == float(z.min())  # heights given, but one value: no motion along z
    if args.axes:
        axes = axis_components(args.axes)
        if "z" in axes and z_flat:
            raise UserError(f"z is {z[0]:.6g} m in every row of {traj}: there is no motion along z to measure",
                            "give --axes without z (e.g. xy)")
    else:
        axes = default_axes(df)
    R, R_source = resolve_motion_blur(df, args.motion_blur)
    vel = V.particle_velocity(df, axes=axes, motion_blur=R, min_frames=args.min_frames, noise=args.noise)
    n_ok = int(np.isfinite(vel[f"v{axes[0]}"].to_numpy(float)).sum())
    if n_ok == 0:
        # positions along the axis, not rows: a row with a NaN coordinate is no position of that axis
        n_ax = vel[f"n_{axes[0]}"].to_numpy()
        raise UserError(f"no track gave a velocity along {axes[0]}: the most positions with a finite {axes[0]} in one "
                        f"track is {int(n_ax.max())} (of {int(vel['n_frames'].max())} rows), and "
                        f"{int((n_ax >= args.min_frames).sum())} tracks have {args.min_frames} or more",
                        "give longer tracks, a smaller --min-frames, or other --axes")
    ens = V.ensemble_velocity(vel, axes=axes, weights=args.weights, n_boot=args.n_boot, seed=args.seed)
    prof = None
    if args.bins > 0 and "z" in axes:
        prof = V.velocity_profile(df, bins=args.bins, axes=axes, motion_blur=R, vel=vel, n_boot=args.n_boot,
                                  seed=args.seed)

    # ---- report
    print(f"{traj}: {len(vel)} tracks, {n_ok} with >= {args.min_frames} positions; frame interval "
          f"{vel.attrs['velocity']['frame_interval']:.6g} s; motion blur R = {R:.4g} ({R_source}); noise parameters: "
          f"{args.noise}")
    if z_flat and not args.axes:
        print(f"note: z is {z[0] * 1e6:.4g} µm in every row (a 2D table): no velocity along z and no profile "
              "against height; x and y analysed")
    if args.contact is not None:
        print(f"deposition: {n_rows_all - len(df)} of {n_rows_all} rows dropped from touch-down on "
              f"(z within {args.contact_tolerance * 1e6:.3g} µm of contact at {args.contact * 1e6:.3g} µm)")
    elif "z" in axes:
        z = df["z"].to_numpy(dtype=float)
        z = z[np.isfinite(z)]
        low = z[z < np.percentile(z, 1) + 0.3e-6]
        if len(low) > 0.2 * len(z):
            print(f"hint: {len(low) / len(z):.0%} of the rows sit within 0.3 µm of the lowest height "
                  f"({np.median(low) * 1e6:.3g} µm): deposited particles pull the drift towards 0; "
                  f"for the drift before deposition give --contact {np.median(low):.3g}")
    print("ensemble drift velocity (µm/s; " + ("inverse-variance" if args.weights == "inverse_variance" else "equal")
          + f" weights; error: bootstrap over particles, {args.n_boot} resamples):")
    print(f"{'axis':<5s} {'v (µm/s)':>20s} {'model SE':>9s} {'chi2/dof':>9s} {'tracks':>7s}")
    for _, r in ens.iterrows():
        print(f"{r['axis']:<5s} {_um(r['v'], r['v_err']):>20s} {r['v_err_model'] * 1e6:>9.2g} {r['chi2_dof']:>9.3g} "
              f"{int(r['n_particles']):>7d}")
    if args.reference is not None and "z" in axes:
        rz = ens[ens["axis"] == "z"].iloc[0]
        dev = (rz["v"] - args.reference) / rz["v_err"] if rz["v_err"] > 0 else float("nan")
        print(f"reference v_z = {_um(args.reference)} µm/s: measured - reference = {dev:+.2f} standard errors")
    if prof is not None:
        print("velocity against height (µm, µm/s; error: bootstrap over particles):")
        print(f"{'z range (µm)':>17s} {'tracks':>6s} {'steps':>6s} " + " ".join(f"{'v_' + a:>18s}" for a in axes))
        for _, r in prof.iterrows():
            print(f"{r['z_lo'] * 1e6:7.2f} - {r['z_hi'] * 1e6:7.2f} {int(r['n_particles']):>6d} {int(r['n_increments']):>6d} "
                  + " ".join(f"{_um(r['v' + a], r['v' + a + '_err']):>18s}" for a in axes))
    show = vel[np.isfinite(vel[f"v{axes[0]}"])].sort_values("n_frames", ascending=False).head(10)
    print(f"per particle (µm/s, longest {len(show)} of {n_ok} tracks):")
    print(f"{'particle':>8s} {'frames':>6s} " + " ".join(f"{'v_' + a:>16s}" for a in axes)
          + (f" {'z_mean (µm)':>11s}" if "z" in axes else ""))
    for _, r in show.iterrows():
        print(f"{int(r['particle']):>8d} {int(r['n_frames']):>6d} " + " ".join(f"{_um(r['v' + a], r['v' + a + '_err']):>16s}" for a in axes)
              + (f" {r['z_mean'] * 1e6:>11.3f}" if "z" in axes else ""))

    with atomic_output(out_csv, "w") as fh:
        fh.write("# units: v m/s, D m^2/s, sigma/x/y/z m, t s; drift by GLS per track (ptrack.velocity)\n")
        vel.to_csv(fh, index=False)
    print(f"wrote {out_csv}")
    prof_path = None
    if prof is not None:
        prof_path = report / (traj.stem + "_velocity_profile.csv")
        with atomic_output(prof_path, "w") as fh:
            fh.write("# units: z m, v m/s; increments binned by their starting height\n")
            prof.to_csv(fh, index=False)
        print(f"wrote {prof_path}")
    png = None
    if not args.no_plot:
        png = report / (traj.stem + "_velocity.png")
        V.plot_velocity(df, vel, png, profile=prof, title=f"{traj.name}: drift velocities", v_ref=args.reference)
        print(f"wrote {png}")
    if args.json:
        summary = {
            "source": str(traj), "axes": "".join(axes), "motion_blur": R, "motion_blur_source": R_source,
            "frame_interval": vel.attrs["velocity"]["frame_interval"], "n_tracks": len(vel), "n_tracks_used": n_ok,
            "weights": args.weights, "noise": args.noise, "contact": args.contact,
            "contact_tolerance": args.contact_tolerance if args.contact is not None else None,
            "rows_used": len(df), "rows_read": n_rows_all, "n_boot": args.n_boot, "seed": args.seed,
            "v": {r["axis"]: _clean(r["v"]) for _, r in ens.iterrows()},
            "v_err": {r["axis"]: _clean(r["v_err"]) for _, r in ens.iterrows()},
            "v_err_model": {r["axis"]: _clean(r["v_err_model"]) for _, r in ens.iterrows()},
            "chi2_dof": {r["axis"]: _clean(r["chi2_dof"]) for _, r in ens.iterrows()},
            "reference_vz": args.reference,
            "profile": None if prof is None else [{k: _clean(v) for k, v in row.items()} for row in prof.to_dict("records")],
            "velocities_csv": str(out_csv), "profile_csv": None if prof_path is None else str(prof_path),
            "plot": None if png is None else str(png), "units": "SI (m/s, m)",
        }
        with atomic_output(args.json, "w") as fh:
            json.dump(summary, fh, indent=2)
        print(f"wrote {args.json}")
    return 0
