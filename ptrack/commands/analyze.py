"""Track a movie and measure diffusion: MSD, D per axis, Stokes-Einstein, near-wall correction, plots.

Runs ``track`` on the movie, then estimates D per axis (covariance estimator
by default, bootstrap errors over particles), compares with Stokes-Einstein
for --radius, --viscosity and --temperature, corrects for hindered diffusion
near the wall from each particle's measured height (3D, with --calib; or an
assumed --height in 2D), and flags non-diffusive tracks. Writes PNG plots
and summary.json into --report DIR. Printed values are in um^2/s; files are SI.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import atomic_output
from .track import add_track_arguments, track_kwargs


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("movie", metavar="MOVIE", help="TIFF file, folder of frames, or glob")
    add_track_arguments(p)
    g = p.add_argument_group("physics")
    g.add_argument("--radius", metavar="R", type=float, required=True, help="particle radius (m)")
    g.add_argument("--viscosity", metavar="MU", type=float, required=True, help="fluid viscosity (Pa s)")
    g.add_argument("--temperature", metavar="T", type=float, required=True, help="temperature (K)")
    g.add_argument("--wall-z", metavar="Z", type=float, default=0.0, help="z of the wall in calibration coordinates (m, 3D; negative values as --wall-z=-3e-6)")
    g.add_argument("--height", metavar="H", type=float, help="assumed centre height above the wall (m, 2D)")
    g.add_argument("--subtract-drift", action="store_true", help="remove the ensemble drift before estimating D")
    g.add_argument("--estimator", choices=("cve", "ols"), default="cve", help="D estimator (default cve)")
    g.add_argument("--motion-blur", metavar="R", type=float, default=1 / 6,
                   help="motion-blur parameter: exposure / frame interval / 6 (default 1/6, shutter open the whole "
                        "frame; 0 for short exposures). D from tracks does not depend on it; the localisation error "
                        "and the precise linking-free estimate do (the summary says which R the data imply)")
    p.add_argument("--out", metavar="TRAJ", help="also write the trajectories table")
    p.add_argument("--report", metavar="DIR", help="directory for plots, per-particle CSV and summary.json")
    p.add_argument("--json", metavar="OUT", help="write the summary JSON here")


def run(args) -> int:
    from ..pipeline import analyze_movie

    s = analyze_movie(args.movie, radius=args.radius, viscosity=args.viscosity, temperature=args.temperature,
                      report_dir=args.report, out=args.out, wall_z=args.wall_z, height=args.height,
                      subtract_drift=args.subtract_drift, estimator=args.estimator, motion_blur=args.motion_blur,
                      **track_kwargs(args))
    um = 1e12
    print(f"{s['n_tracks']} tracks, {s['n_localisations']} localisations")
    for a in s["D"]:
        print(f"D_{a} = {s['D'][a] * um:.4f} +- {s['D_err'][a] * um:.4f} um^2/s")
    pr = s.get("D_pairs")
    print(f"  reported: {s['D_method']}; from tracks (field-of-view corrected) {s['D_tracks']['xy'] * um:.4f} +- "
          f"{s['D_tracks_err']['xy'] * um:.4f}" + (f", linking-free {pr['D']['xy'] * um:.4f} +- {pr['D_err']['xy'] * um:.4f}"
                                                    f" (link ambiguity {pr['link_ambiguity']:.3f})" if pr else ""))
    if pr and pr.get("motion_blur_implied") is not None and not pr["offset"].startswith("sigma"):
        print(f"  note: the data imply a motion-blur parameter R = {pr['motion_blur_implied']:.3f}, not the "
              f"{pr['motion_blur_assumed']:.3f} assumed (--motion-blur: 1/6 for a shutter open the whole frame, "
              "0 for short exposures)")
    print(f"Stokes-Einstein D = {s['D_stokes_einstein'] * um:.4f} um^2/s; D_xy / D_SE = {s['D_over_D_SE']:.3f}")
    if s.get("drift_velocity"):
        print("drift velocity (um/s): " + "  ".join(f"v_{a} = {v['v'] * 1e6:+.3f} +- {v['v_err'] * 1e6:.3f}"
                                                   for a, v in s["drift_velocity"].items()))
    h = s.get("hindered")
    if h:
        print(f"wall: mean D_par/D0 = {h.get('mean_ratio_parallel', h.get('ratio_parallel')):.3f}, "
              f"D corrected to bulk = {h['D_bulk_xy'] * um:.4f} um^2/s")
    nd = s["nondiffusive"]
    print(f"non-diffusive tracks: {nd['n_flagged']} of {nd['n_assessed']} assessed")
    if args.report:
        print(f"report -> {Path(args.report)}")
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(s, fh, indent=2)
    return 0
