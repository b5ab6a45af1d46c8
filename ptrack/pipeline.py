"""The track and analyze chains as Python functions.

``track``: movie -> (preprocess -> detect -> localise [-> z by GDPT]) per frame
-> link -> trajectories table (SI units + pixel columns), written atomically.

``analyze`` (track -> MSD / D -> Stokes-Einstein -> wall correction -> report)
is :mod:`ptrack.analysis`.

Every step is also usable alone (:mod:`ptrack.io`, :mod:`ptrack.preprocess`,
:mod:`ptrack.locate`, :mod:`ptrack.calibration`, :mod:`ptrack.link`).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import UserError, check_positive

__all__ = ["locate_movie", "track_movie", "track_many", "default_output"]


def _progress(total, desc, enabled):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled, leave=False, dynamic_ncols=True)


def locate_movie(movie, brightfield: bool | None = None, diameter: float | None = None, calib=None,
                 snr: float | None = None, gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0,
                 background: str = "spatial", cm_min: float = 0.5, frames=None,
                 progress: bool = True) -> tuple[pd.DataFrame, dict]:
    """Localise the particles of every frame of an open movie.

    Parameters
    ----------
    movie : ptrack.io.Movie
    brightfield : bool, optional
        Dark particles on a bright field (True) or bright particles (False);
        None: decided from the data and reported in ``info['polarity_from']``
        (the knob-free path: by :func:`ptrack.image.locate.batch`, on the first
        frame with particles; the others: :func:`ptrack.image.detect.detect` on
        the first frame).
    diameter : float, optional
        Particle image diameter (px, = 4 sigma of the spot): selects the
        single-size detector. None (default, 2D): multi-scale detection, each
        particle localised at its own size.
    calib : ptrack.calibration.Calibration, optional
        Defocus calibration: z by GDPT; without it the data are 2D.
    snr : float, optional
        Detection threshold in local noise units; default from a false-alarm
        rate of 1 per 10^6 px (2D), 7 (3D and single-size 2D).
    gain, offset, read_noise : float
        Camera: ADU per photo-electron, baseline ADU, read noise (e- rms).
    background : {"spatial", "temporal", "none"}
    cm_min : float
        Correlation threshold for z (3D).
    frames : iterable of int, optional
        Subset of frames.
    progress : bool
        tqdm bar on stderr.

    Returns
    -------
    features : DataFrame
        ``frame``, ``x_px``, ``y_px`` and the localiser's columns (``z`` in m
        and ``cm`` in 3D).
    info : dict
        Settings used (``sigma_px``, ``background``, ``polarity``...) and
        ``stage_times_s`` (read, locate, z, and the parts of locate and z
        as ``locate.*`` and ``z.*``).
    """
    from . import calibration as cal_mod
    from .image.detect import detect
    from .io import check_not_blank
    from .locate import batch, diameter_to_sigma, locate, sigma_to_diameter
    from .preprocess import prepare, temporal_background

    if min(movie.shape) < 8:
        raise UserError(f"{movie.source}: frames of {movie.shape[0]}x{movie.shape[1]} px are too small to hold a "
                        "particle image", "give the movie itself (frames of at least 8x8 px)")
    check_not_blank(movie)
    n = len(movie)
    frames = range(n) if frames is None else list(frames)
    if snr is not None and not (math.isfinite(float(snr)) and float(snr) > 0):
        raise UserError(f"snr = {snr} is not a positive number", "give a threshold such as 5 (noise units)")
    times = {"read": 0.0, "locate": 0.0, "z": 0.0}
    info = {"background": background, "snr": None if snr is None else float(snr),
            "gain": float(gain), "offset": float(offset), "read_noise": float(read_noise)}
    # the frames of the movie share their noise and background maps (measured again every
    # ptrack.image.detect.MAP_REFRESH frames, or when the background level moves)
    maps = {}
    multiscale = diameter is None and calib is None
    # the knob-free path with the spatial background: the frames through ptrack.image.locate.batch (its polarity
    # rule, its shared maps, one table for the movie); the other paths need the polarity before the first frame
    columns = multiscale and background == "spatial"
    if brightfield is None and columns:
        info["polarity_from"] = "data"
    elif brightfield is None:
        # polarity from the data (first frame), fixed for the movie
        t = time.perf_counter()
        first = movie[frames[0] if len(frames) else 0]
        times["read"] += time.perf_counter() - t
        t = time.perf_counter()
        pol = detect(first, offset=offset, cache=maps)["polarity"]
        times["locate"] += time.perf_counter() - t
        brightfield = bool(pol < 0)
        info["polarity_from"] = "data"
    else:
        info["polarity_from"] = "--brightfield" if brightfield else "option (fluorescence)"
    sigma = None
    if diameter is not None:
        sigma = diameter_to_sigma(check_positive("diameter", diameter))
    elif calib is not None:
        sigma = 2.0
    info["detector"] = "multi-scale (false-alarm rate 1e-6 per px)" if multiscale else "single size"
    info["sigma_px"] = None if sigma is None else float(sigma)
    info["diameter_px"] = None if sigma is None else sigma_to_diameter(sigma)
    bg_size = max(15.0, 12.0 * (sigma or 1.5)) if calib is None else 3.0 * calib.size
    bg = background
    if background == "temporal":
        bg = temporal_background(movie)
        if brightfield:
            bg = float(np.iinfo(movie.dtype).max if movie.dtype.kind in "ui" else bg.max()) - bg
    elif background not in ("spatial", "none"):
        raise UserError(f"background = {background!r} is not known", "use spatial, temporal or none")
    has_3d = hasattr(cal_mod, "locate_frame_3d")
    chunks = []
    # GDPT sums its own stage times into calib.info (over every call): this movie's share is the difference
    z_before = dict(calib.info.get("stage_times_s", {})) if calib is not None else {}
    with _progress(len(frames), Path(movie.source).name, progress) as bar:
        if columns:
            def reading():
                # the frames as batch takes them, the read time apart and the bar moved once a frame is located
                for i in frames:
                    t = time.perf_counter()
                    raw = movie[i]
                    times["read"] += time.perf_counter() - t
                    yield raw
                    bar.update(1)
            t = time.perf_counter()
            read_before = times["read"]
            feats = batch(reading(), brightfield=brightfield, snr=snr, gain=gain, offset=offset,
                          read_noise=read_noise, cache=maps, frame_numbers=frames)
            times["locate"] += time.perf_counter() - t - (times["read"] - read_before)
            if brightfield is None:
                brightfield = bool(len(feats) and feats["polarity"].iloc[0] < 0)
        else:
            for i in frames:
                t = time.perf_counter()
                raw = movie[i]
                times["read"] += time.perf_counter() - t
                t = time.perf_counter()
                if calib is not None:
                    if has_3d:
                        df = cal_mod.locate_frame_3d(raw, calib, brightfield=brightfield, background=bg,
                                                     snr=7.0 if snr is None else snr, cm_min=cm_min, gain=gain,
                                                     offset=offset, read_noise=read_noise)
                    else:
                        img = cal_mod.prepare_gdpt(raw, calib, brightfield=brightfield, background=bg)
                        df = cal_mod.locate_3d(img, calib, snr=7.0 if snr is None else snr, cm_min=cm_min)
                    times["z"] += time.perf_counter() - t
                    df.insert(0, "frame", np.full(len(df), i, np.int64))
                else:
                    img = None
                    if brightfield or not (isinstance(bg, str) and bg == "spatial"):
                        img = prepare(raw, brightfield=brightfield, background=bg, bg_size=bg_size)
                    df = locate(raw, img, sigma=sigma or 1.5, snr=7.0 if snr is None else snr, gain=gain,
                                offset=offset, read_noise=read_noise, brightfield=brightfield, frame_no=i)
                    times["locate"] += time.perf_counter() - t
                chunks.append(df)
                bar.update(1)
            feats = pd.concat(chunks, ignore_index=True) if chunks else pd.DataFrame()
    brightfield = bool(brightfield)
    info["brightfield"] = brightfield
    info["polarity"] = "dark particles on a bright field" if brightfield else "bright particles on a dark field"
    if len(feats) == 0:
        raise UserError(f"no particle found in {movie.source}",
                        "check the movie (is it empty or out of focus?), lower --snr or give --diameter")
    if multiscale and "size" in feats:
        # the typical particle image, for the summary (each particle was localised at its own size)
        info["sigma_px"] = float(np.median(feats["size"]))
        info["diameter_px"] = sigma_to_diameter(info["sigma_px"])
    # the multi-scale locator's own split of "locate" (detect, fit, centres), summed over frames
    times.update({"locate." + k: v for k, v in maps.get("stage_times_s", {}).items()})
    if calib is not None:
        times.update({"z." + k: v - z_before.get(k, 0.0) for k, v in calib.info.get("stage_times_s", {}).items()})
    info["stage_times_s"] = {k: round(v, 4) for k, v in times.items()}
    return feats, info


def default_output(movie_path, out_dir=None) -> Path:
    """``<out_dir or .>/<movie stem>.traj.parquet``."""
    p = Path(str(movie_path).rstrip("/*"))
    stem = p.name
    for suf in (".ome.tiff", ".ome.tif", ".tiff", ".tif", ".png"):
        if stem.lower().endswith(suf):
            stem = stem[: -len(suf)]
            break
    return Path(out_dir or ".") / f"{stem}.traj.parquet"


#: largest fraction of frames whose stage drift has no unique correlation peak for --stage-drift to go on
STAGE_DRIFT_UNRELIABLE_MAX = 0.2


def track_movie(movie, out=None, pixel_size: float | None = None, frame_interval: float | None = None,
                calib=None, calib_z=None, calib_step: float | None = None, calib_z0: float = 0.0,
                brightfield: bool | None = None, diameter: float | None = None, search_range: float | None = None,
                memory: int = 3, min_length: int = 5, snr: float | None = None, gain: float = 1.0, offset: float = 0.0,
                read_noise: float = 0.0, background: str = "spatial", cm_min: float = 0.5,
                channel: int | None = None, plane: int | None = None, series: int | None = None,
                field_calib: bool = False, stage_drift: bool = False,
                progress: bool = True) -> tuple[pd.DataFrame, dict]:
    """Movie -> trajectories table.

    Parameters
    ----------
    movie : path-like
        Movie file, folder or glob (:func:`ptrack.io.open_movie`).
    out : path-like, optional
        Write the table here (Parquet, or CSV by suffix), atomically.
    pixel_size, frame_interval : float, optional
        m per px and s per frame; override the metadata (required if absent).
    calib : path-like or Calibration, optional
        Defocus calibration stack for z; heights from ``calib_z`` (CSV page, z)
        or ``calib_step`` (+ ``calib_z0``), m.
    search_range : float, optional
        Linking range (px); estimated if None.
    memory : int
        Frames a particle may be missed.
    min_length : int
        Shortest trajectory kept (frames).
    channel, plane, series : int, optional
        Hyperstack channel, focal plane and image series (:func:`ptrack.io.open_movie`).
    field_calib : bool
        With ``calib`` holding several beads across the field: correct z for
        field-dependent aberration (field curvature, tilt) by the beads' own
        readings (:func:`ptrack.gdpt.field.load_field_calibration`).
    stage_drift : bool
        Measure the rigid stage drift of every frame by phase correlation
        (:func:`ptrack.image.drift.frame_drift`) and subtract it from the
        positions before linking: ``x_px``, ``y_px`` are then stage
        coordinates. Use it when the stage jumps or drifts by more than a
        fraction of the particle spacing per frame (linking then holds).
    Others : see :func:`locate_movie`.

    Returns
    -------
    table : DataFrame
        Trajectories table (:mod:`ptrack.table`) with x_px, y_px, mass, size,
        ecc, signal, sigma_x, sigma_y (2D) or cm and edge (3D; edge: the
        particle image is cut by the frame border).
    summary : dict
        ``n_frames``, ``n_localisations``, ``n_tracks``, ``wall_time_s``,
        ``frames_per_s`` and the settings used.
    """
    from .calibration import Calibration, check_pixel_size, load_calibration
    from .io import open_movie
    from .link import filter_short, link, to_trajectories
    from .table import UNITS, write_table

    t0 = time.perf_counter()
    with open_movie(movie, pixel_size=pixel_size, frame_interval=frame_interval, channel=channel, plane=plane,
                    series=series) as mv:
        mv.require_calibration()
        px, dt = mv.pixel_size, mv.frame_interval
        cal = None
        polarity_from = None
        if calib is not None:
            # with a calibration the polarity is the stack's own (unambiguous near focus; a full-frame
            # fluorescence movie of a few defocused beads can look dark to the movie detector)
            cal = calib if isinstance(calib, Calibration) else load_calibration(
                calib, z_csv=calib_z, z_step=calib_step, z0=calib_z0, brightfield=brightfield)
            check_pixel_size(cal, px)
            if brightfield is None:
                brightfield = bool(cal.info.get("signed", False))
                polarity_from = "calibration stack"
        elif calib_z is not None or calib_step is not None:
            raise UserError("--calib-z/--calib-step given without --calib", "give the calibration stack with --calib")
        fcal = None
        if field_calib:
            if cal is None or isinstance(calib, Calibration):
                raise UserError("--field-calib needs the calibration stack file", "give it with --calib STACK")
            from .gdpt.field import load_field_calibration

            t_f = time.perf_counter()
            fcal = load_field_calibration(calib, calib=cal, locate_options={"snr": 7.0 if snr is None else snr,
                                                                            "cm_min": cm_min},
                                          z_csv=calib_z, z_step=calib_step, z0=calib_z0)
            t_f = time.perf_counter() - t_f
        sd = None
        if stage_drift:     # first, so that a movie whose drift cannot be measured is refused before the work
            from .image.drift import PEAK_RATIO_MIN, frame_drift

            t_sd = time.perf_counter()
            sd = frame_drift(iter(mv), px, dt)        # a lazy pass over the frames
            t_sd = time.perf_counter() - t_sd
            bad = int((~sd["reliable"]).sum())
            if bad > STAGE_DRIFT_UNRELIABLE_MAX * len(sd):
                raise UserError(f"the stage drift cannot be measured in {bad} of {len(sd)} frames of {mv.source}: "
                                f"no unique correlation peak (ratio < {PEAK_RATIO_MIN}; the particles change too much "
                                "between frames for phase correlation)",
                                "omit --stage-drift (the tracks' own drift is in ptrack analyze / ptrack.msd)")
        feats, info = locate_movie(mv, brightfield=brightfield, diameter=diameter, calib=cal, snr=snr, gain=gain,
                                   offset=offset, read_noise=read_noise, background=background, cm_min=cm_min,
                                   progress=progress)
        if fcal is not None:
            from .gdpt.field import correct_z

            t_c = time.perf_counter()
            feats = correct_z(feats, fcal)
            info.setdefault("stage_times_s", {})["field_calibration"] = round(t_f + time.perf_counter() - t_c, 4)
        if sd is not None:
            from .image.drift import subtract_frame_drift

            t0_sd = time.perf_counter()
            feats = subtract_frame_drift(feats, sd)   # x_px, y_px in stage coordinates, before linking
            info.setdefault("stage_times_s", {})["stage_drift"] = round(t_sd + time.perf_counter() - t0_sd, 4)
            info["stage_drift_max_px"] = float(np.hypot(sd["x_px"], sd["y_px"]).max())
            info["stage_drift_reliable_frames"] = int(sd["reliable"].sum())
        n_frames = len(mv)
        source = mv.source
        shape = mv.shape
    if polarity_from:
        info["polarity_from"] = polarity_from
    n_loc = len(feats)
    t_link = time.perf_counter()
    linked = link(feats, search_range=search_range, memory=memory, pixel_size=px)
    link_info = dict(linked.attrs.get("link", {}))
    linked = filter_short(linked, min_length)
    t_link = time.perf_counter() - t_link
    t_table = time.perf_counter()
    if len(linked) == 0:
        raise UserError(f"no trajectory of {min_length} or more frames in {source}",
                        "lower --min-length, raise --memory or give a larger --search-range")
    meta = {
        "source": str(source), "n_frames": n_frames,
        "frame_shape": list(shape), "kind": "measured", "tracker": "ptrack", **info, "link": link_info,
        "units": {**UNITS, "size": "px", "mass": "ADU", "signal": "ADU", "ecc": "1"},
    }
    if cal is not None:
        meta.update(calibration=str(cal.source), calib_depth=cal.depth, calib_step=cal.step,
                    calib_template_px=cal.size, cm_min=float(cm_min))
    keep = ["frame", "particle", "x_px", "y_px", "mass"]
    keep += ["size", "ecc", "signal", "sigma_x_px", "sigma_y_px"] if cal is None else \
        ["z", "cm"] + [c for c in ("chi2", "edge") if c in linked]
    # the public step from linked features (px) to the SI table; it renumbers the particles 0..n-1 by
    # first appearance (trackpy's own ids depend on set iteration order)
    table = to_trajectories(linked[keep], px, dt, meta=meta)
    stages = dict(info.get("stage_times_s", {}))
    stages["link"] = round(t_link, 4)
    stages["table"] = round(time.perf_counter() - t_table, 4)
    wall = time.perf_counter() - t0
    summary = {"movie": str(source), "n_frames": int(n_frames), "n_localisations": int(n_loc),
               "n_tracks": int(table["particle"].nunique()), "wall_time_s": round(wall, 3),
               "frames_per_s": round(n_frames / wall, 2) if wall > 0 else None,
               "pixel_size_m": px, "frame_interval_s": dt, "diameter_px": info["diameter_px"],
               "search_range_px": link_info.get("search_range_px"), "three_d": cal is not None,
               "polarity": info.get("polarity"), "polarity_from": info.get("polarity_from"),
               "detector": info.get("detector"), "stage_times_s": stages}
    if cal is not None:  # what the calibration stack gave: beads used, pages rejected, the beads' own z spread
        ci = cal.info
        summary["calibration"] = {"n_beads": ci.get("n_beads"), "rejected_pages": ci.get("rejected"),
                                  "z_error_m": ci.get("z_error"), "z_source": ci.get("z_source")}
        if fcal is not None:
            summary["calibration"]["field"] = {"basis": fcal.basis, "n_beads": fcal.info.get("n_beads"),
                                               "loo_rms_m": fcal.info.get("loo_rms")}
    if stage_drift:
        summary["stage_drift_max_px"] = info.get("stage_drift_max_px")
        summary["stage_drift_reliable_frames"] = info.get("stage_drift_reliable_frames")
    if out is not None:
        t = time.perf_counter()
        write_table(table, out)
        stages["write"] = round(time.perf_counter() - t, 4)
        summary["output"] = str(out)
    return table, summary


def _track_worker(movie, out, kwargs):
    _, summary = track_movie(movie, out=out, progress=False, **kwargs)
    return summary


def track_many(movies, out_dir=None, scheduler: str | None = None, n_workers: int | None = None,
               **kwargs) -> list[dict]:
    """Track several movies as dask.distributed tasks, one output table per movie.

    Parameters
    ----------
    movies : sequence of path-like
    out_dir : path-like, optional
        Directory for ``<stem>.traj.parquet`` files (default: current directory);
        movies of one name in several folders give ``<folder>_<stem>.traj.parquet``.
    scheduler : str, optional
        Address of a running dask scheduler; default a LocalCluster of
        ``n_workers`` single-threaded processes.
    **kwargs
        As :func:`track_movie`.

    Returns
    -------
    list of dict
        One summary per movie (in the given order). A movie that failed has
        ``error`` set; the others' outputs are complete.
    """
    import os

    outs = [default_output(m, out_dir) for m in movies]
    if len(set(outs)) < len(outs):
        # movies of one name in several folders (run1/movie.tif, run2/movie.tif): name each by its folder too
        outs = [o.with_name(f"{Path(os.path.abspath(str(m).rstrip('/*'))).parent.name}_{o.name}")
                if outs.count(o) > 1 else o for m, o in zip(movies, outs)]
    dup = {str(o) for o in outs if outs.count(o) > 1}
    if dup:
        raise UserError(f"several movies would write the same output {sorted(dup)[0]}",
                        "rename the movies or track them separately with --out")
    import glob

    # a movie that is not there is said here, once, before any worker starts (not as worker tracebacks)
    missing = [str(m) for m in movies if not Path(m).exists() and not glob.glob(str(m))]
    if missing:
        raise UserError(f"{len(missing)} of {len(movies)} movies not found: {', '.join(missing[:3])}"
                        f"{' ...' if len(missing) > 3 else ''}", "check the paths (a file, a folder of frames or a glob)")
    from dask.distributed import Client, LocalCluster

    # workers may run elsewhere or in another folder: paths are resolved here, on the client
    movies = [os.path.abspath(str(m)) for m in movies]
    outs = [Path(os.path.abspath(str(o))) for o in outs]
    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="2s")     # a refused connection is retried until then
        except (OSError, TimeoutError) as exc:
            raise UserError(f"cannot reach the dask scheduler at {scheduler} ({type(exc).__name__})",
                            "start it (dask scheduler) or omit --scheduler for a local cluster") from None
    else:
        nw = n_workers or max(1, min(len(movies), os.cpu_count() or 1))
        cluster = LocalCluster(n_workers=nw, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    try:
        futs = [client.submit(_track_worker, str(m), str(o), kwargs, pure=False) for m, o in zip(movies, outs)]
        from tqdm import tqdm

        results = []
        for m, f in zip(movies, tqdm(futs, desc="movies", unit="movie", disable=not kwargs.get("progress", True))):
            try:
                results.append(f.result())
            except UserError as exc:
                results.append({"movie": str(m), "error": str(exc)})
            except Exception as exc:     # a worker's failure: one line per movie, not a traceback block
                results.append({"movie": str(m), "error": f"{type(exc).__name__}: {exc}".splitlines()[0]})
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return results
