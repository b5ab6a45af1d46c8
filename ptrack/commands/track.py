"""Track particles in microscope movies: TIFF series -> trajectories table (2D, or 3D with a calibration stack).

Per frame: invert (--brightfield), subtract the background, detect, localise
to the Cramer-Rao bound (Poisson maximum-likelihood Gaussian fit), or, with
--calib, measure x, y, z and the correlation Cm against the defocus
calibration stack (GDPT); then link with trackpy. The table is in SI units
(m, s) with pixel columns x_px, y_px. Several movies run as dask.distributed
tasks (a local cluster, or --scheduler ADDRESS), one table per movie in the
--out directory.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import UserError, atomic_output, check_writable


def add_track_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``track`` and ``analyze``."""
    g = p.add_argument_group("calibration (3D)")
    g.add_argument("--calib", metavar="CALIB", help="defocus calibration stack (TIFF): gives z by GDPT")
    g.add_argument("--calib-z", metavar="CSV", help="CSV with columns page, z (m) for the calibration pages")
    g.add_argument("--calib-step", metavar="DZ", type=float, help="z step between calibration pages (m)")
    g.add_argument("--calib-z0", metavar="Z0", type=float, default=0.0, help="z of page 0 (m, default 0; e.g. --calib-z0 -3e-6)")
    g.add_argument("--field-calib", action="store_true",
                   help="correct z across the field by the stack's beads (several beads at several places: field curvature, tilt)")
    g.add_argument("--cm-min", type=float, default=0.5, help="correlation threshold Cm for z (default 0.5)")
    g = p.add_argument_group("image")
    pol = g.add_mutually_exclusive_group()
    pol.add_argument("--brightfield", action="store_const", const=True, default=None,
                     help="dark particles on a bright field (default: polarity decided from the data and printed)")
    pol.add_argument("--fluorescence", dest="brightfield", action="store_const", const=False,
                     help="bright particles on a dark field")
    g.add_argument("--channel", metavar="N", type=_index, help="channel of a TCYX hyperstack (0-based)")
    g.add_argument("--plane", metavar="N", type=_index, help="focal plane of a TZYX hyperstack (0-based)")
    g.add_argument("--series", metavar="N", type=_index, help="image series of a multi-series (OME) file (0-based)")
    g.add_argument("--pixel-size", metavar="M", type=float, help="m per pixel in the sample (overrides metadata)")
    g.add_argument("--frame-interval", metavar="S", type=float, help="s between frames (overrides metadata)")
    g.add_argument("--diameter", metavar="PX", type=float,
                   help="particle image diameter in px (4 sigma of the spot); estimated from the movie if omitted")
    g.add_argument("--snr", type=float, default=None,
                   help="detection threshold in local noise units (default: set for 1 false detection per 10^6 px)")
    g.add_argument("--background", choices=("spatial", "temporal", "none"), default="spatial",
                   help="background subtraction (default spatial: per-frame opening; temporal: per-pixel median)")
    g.add_argument("--gain", type=float, default=1.0, help="camera ADU per photo-electron (default 1)")
    g.add_argument("--offset", type=float, default=0.0, help="camera baseline, ADU (default 0)")
    g.add_argument("--read-noise", type=float, default=0.0, help="camera read noise, e- rms (default 0)")
    g = p.add_argument_group("linking")
    g.add_argument("--search-range", metavar="PX", type=float, help="largest step between frames (px); estimated if omitted")
    g.add_argument("--memory", type=int, default=3, help="frames a particle may be missed (default 3)")
    g.add_argument("--min-length", type=int, default=5, help="shortest trajectory kept, frames (default 5)")
    g.add_argument("--stage-drift", action="store_true",
                   help="measure the stage drift of each frame by phase correlation and subtract it before linking "
                        "(for stage jumps or drift; x, y are then stage coordinates)")


def _index(text: str) -> int:  # argparse names it "index" in its message
    """A 0-based index option (--channel, --plane, --series): a whole number >= 0.

    (Parsed here rather than as ``type=int`` because ptrack.options has no entry for these yet; the
    lead may move them there as ``whole(0, ...)``.)
    """
    try:
        v = int(text)
    except ValueError:
        raise UserError(f"{text!r} is not a whole number", "give a 0-based index such as 0") from None
    if v < 0:
        raise UserError(f"index {v} is negative", "give a 0-based index such as 0")
    return v


_index.__name__ = "0-based index"


def track_kwargs(args) -> dict:
    # the numeric ranges (--snr nan, --search-range=-5, --gain 0 ...) are checked once for every command
    # by ptrack.options before this runs
    return dict(pixel_size=args.pixel_size, frame_interval=args.frame_interval, calib=args.calib,
                calib_z=args.calib_z, calib_step=args.calib_step, calib_z0=args.calib_z0,
                brightfield=args.brightfield, diameter=args.diameter, search_range=args.search_range,
                memory=args.memory, min_length=args.min_length, snr=args.snr, gain=args.gain, offset=args.offset,
                read_noise=args.read_noise, background=args.background, cm_min=args.cm_min,
                channel=args.channel, plane=args.plane, series=args.series, field_calib=args.field_calib,
                stage_drift=args.stage_drift)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("movies", nargs="+", metavar="MOVIE", help="TIFF file, folder of frames, or glob")
    add_track_arguments(p)
    p.add_argument("--out", metavar="PATH",
                   help="output table (.parquet or .csv); a directory when several movies (default: ./<stem>.traj.parquet)")
    p.add_argument("--json", metavar="OUT", help="write a JSON summary (n_frames, n_localisations, n_tracks, wall_time_s, frames_per_s)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask scheduler address for several movies (default: local cluster)")
    p.add_argument("--workers", type=int, help="local worker processes for several movies (default: one per core)")


def run(args) -> int:
    from ..pipeline import default_output, track_many, track_movie

    kw = track_kwargs(args)
    if len(args.movies) == 1:
        out = Path(args.out) if args.out else default_output(args.movies[0])
        if out.is_dir():
            out = default_output(args.movies[0], out)
        check_writable(out, "--out")
        if args.json:
            check_writable(args.json, "--json")
        _, summary = track_movie(args.movies[0], out=out, **kw)
        if summary.get("polarity_from") == "data":
            print(f"image polarity from the data: {summary['polarity']} "
                  f"(override with --brightfield or --fluorescence)")
        print(f"{summary['n_frames']} frames, {summary['n_localisations']} localisations, {summary['n_tracks']} tracks "
              f"in {summary['wall_time_s']:.1f} s ({summary['frames_per_s']:.1f} frames/s) -> {out}")
        result = summary
    else:
        if args.out and Path(args.out).suffix.lower() in (".parquet", ".csv"):
            raise UserError(f"--out {args.out} is a file but {len(args.movies)} movies were given",
                            "give a directory for --out (one <stem>.traj.parquet per movie)")
        if args.out:
            check_writable(args.out, "--out", directory=True)
        if args.json:
            check_writable(args.json, "--json")
        results = track_many(args.movies, out_dir=args.out, scheduler=args.scheduler, n_workers=args.workers, **kw)
        for r in results:
            if "error" in r:
                print(f"{r['movie']}: error: {r['error']}", file=sys.stderr)
            else:
                print(f"{r['movie']}: {r['n_frames']} frames, {r['n_localisations']} localisations, "
                      f"{r['n_tracks']} tracks -> {r['output']}")
        ok = [r for r in results if "error" not in r]
        result = {"n_frames": sum(r["n_frames"] for r in ok), "n_localisations": sum(r["n_localisations"] for r in ok),
                  "n_tracks": sum(r["n_tracks"] for r in ok), "wall_time_s": sum(r["wall_time_s"] for r in ok),
                  "movies": results}
        result["frames_per_s"] = round(result["n_frames"] / result["wall_time_s"], 2) if result["wall_time_s"] else None
        if len(ok) < len(results):
            if args.json:
                with atomic_output(args.json, "w") as fh:
                    json.dump(result, fh, indent=2)
            raise UserError(f"{len(results) - len(ok)} of {len(results)} movies failed (see above)",
                            "fix those inputs and rerun them")
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0
