"""Track a movie and measure diffusion: MSD, D per axis, Stokes-Einstein, near-wall correction, plots.

Runs ``track`` on the movie, then estimates D per axis (covariance estimator
by default, bootstrap errors over particles), compares with Stokes-Einstein
for --radius, --viscosity and --temperature, corrects for hindered diffusion
near the wall from each particle's measured height (3D, with --calib; or an
assumed --height in 2D), and flags non-diffusive tracks. Writes PNG plots
and summary.json into --report DIR. Printed values are in µm²/s; files are SI. Every parameter is checked before the
movie is tracked.
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
    g.add_argument("--wall-z", metavar="Z", type=float, default=None,
                   help="z of the wall in calibration coordinates (m, 3D): the near-wall correction is then applied. "
                        "Default: the wall at the lowest heights the particles reach minus the radius, and the "
                        "correction applied only if D parallel to the wall falls with height as that wall makes it "
                        "(delta chi2 >= 6 against a flat D); else D is reported as measured, said in the output")
    g.add_argument("--height", metavar="H", type=float, help="assumed centre height above the wall (m, 2D)")
    g.add_argument("--subtract-drift", action="store_true", help="remove the ensemble drift before estimating D")
    g.add_argument("--estimator", choices=("cve", "ols"), default="cve", help="D estimator (default cve)")
    g.add_argument("--motion-blur", metavar="R", type=float, default=None,
                   help="motion-blur parameter: exposure / frame interval / 6 (1/6: shutter open the whole frame; 0 "
                        "for short exposures); default: from the metadata or the localisation errors, else 1/6 (the "
                        "output says which). D from tracks does not depend on it; the localisation error and the "
                        "precise linking-free estimate do")
    p.add_argument("--out", metavar="TRAJ", help="also write the trajectories table")
    p.add_argument("--report", metavar="DIR", help="directory for plots, per-particle CSV and summary.json (written "
                                                  "all or nothing)")
    p.add_argument("--json", metavar="OUT", help="write the summary JSON here")


def run(args) -> int:
    from ..analysis import analyze_movie

    a = analyze_movie(args.movie, radius=args.radius, viscosity=args.viscosity, temperature=args.temperature,
                      report_dir=args.report, out=args.out, wall_z=args.wall_z, height=args.height,
                      subtract_drift=args.subtract_drift, estimator=args.estimator, motion_blur=args.motion_blur,
                      **track_kwargs(args))
    print_summary(a.summary)
    if args.report:
        print(f"report -> {Path(args.report)}")
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(a.summary, fh, indent=2)
    return 0


def print_summary(s: dict) -> None:
    """The analysis summary as the terminal shows it (µm²/s)."""
    um = 1e12
    print(f"{s['n_tracks']} tracks, {s['n_localisations']} localisations; motion blur R = {s['motion_blur']:.3g} "
          f"({s['motion_blur_source']})")
    for a in s["D"]:
        print(f"D_{a} = {s['D'][a] * um:.4f} ± {s['D_err'][a] * um:.4f} µm²/s")
    pr = s.get("D_pairs")
    print(f"  reported: {s['D_method']} ({s['D_method_reason']}); from tracks (field-of-view corrected) "
          f"{s['D_tracks']['xy'] * um:.4f} ± {s['D_tracks_err']['xy'] * um:.4f}"
          + (f", linking-free {pr['D']['xy'] * um:.4f} ± {pr['D_err']['xy'] * um:.4f}"
             f" (link ambiguity {pr['link_ambiguity']:.3f})" if pr else ""))
    if pr and pr.get("motion_blur_implied") is not None and not pr["offset"].startswith("sigma"):
        print(f"  note: the data imply a motion-blur parameter R = {pr['motion_blur_implied']:.3f}, not the "
              f"{pr['motion_blur_assumed']:.3f} used (--motion-blur: 1/6 for a shutter open the whole frame, "
              "0 for short exposures)")
    print(f"Stokes-Einstein D = {s['D_stokes_einstein'] * um:.4f} µm²/s; D_xy / D_SE = {s['D_over_D_SE']:.3f}")
    if s.get("drift_velocity"):
        print("drift velocity (µm/s): " + "  ".join(f"v_{a} = {v['v'] * 1e6:+.3f} ± {v['v_err'] * 1e6:.3f}"
                                                   for a, v in s["drift_velocity"].items()))
    h = s.get("hindered")
    ev = (h or {}).get("evidence")
    if ev:
        print(f"wall test (D parallel to the wall vs height, {ev['n_points']} points in {len(ev['bins'])} height bins): "
              f"chi2 {ev['chi2_flat']:.1f} flat, {ev['chi2_wall']:.1f} with a wall at z = {ev['wall_z_m'] * 1e6:.3g} µm "
              f"({ev['dof']} dof); delta chi2 = {ev['delta_chi2']:+.1f} (a wall needs >= {ev['threshold']:g}): "
              f"{ev['favours']}")
    if h and h.get("decision"):
        print(f"wall correction {h['decision']}")
    if h and h.get("applied"):
        where = (f"wall at z = {h['wall_z_m'] * 1e6:.3g} µm ({h['wall_z_source']}), mean centre height "
                 f"{h['mean_height_m'] * 1e6:.3g} µm" if "wall_z_m" in h
                 else f"assumed centre height {h['assumed_height_m'] * 1e6:.3g} µm")
        print(f"wall: {where}; mean D_par/D0 = {h.get('mean_ratio_parallel', h.get('ratio_parallel')):.3f}, "
              f"D corrected to bulk = {h['D_bulk_xy'] * um:.4f} ± {h['D_bulk_xy_err'] * um:.4f} µm²/s")
    nd = s["nondiffusive"]
    print(f"non-diffusive tracks: {nd['n_flagged']} of {nd['n_assessed']} assessed")
    for note in s.get("notes", []):
        print(f"warning: {note}")
