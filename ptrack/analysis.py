"""Diffusion analysis of a trajectories table, and the report writer (``ptrack analyze``).

:func:`analyze_table` is pure: a table in, an :class:`Analysis` out (D per
axis from the tracks and without links, the one reported and why,
Stokes-Einstein, the wall correction, the drift velocity, non-diffusive
tracks, D per particle). :func:`write_report` writes it as a folder, all or
nothing. :func:`analyze_movie` checks every parameter, tracks the movie and
does both.

Defaults that depend on the data, each recorded in the summary with its
source:

- the motion-blur parameter R (:func:`ptrack.motion.tracks.resolve_motion_blur`);
- in 3D, the wall correction: with ``wall_z`` given it is applied (the
  user's word); else the wall is put at the lowest heights the particles
  reach (0.5 % quantile of z) minus the radius and the correction is
  applied only when the data show a hydrodynamic wall there: D parallel to
  the wall falling with height as Brenner / Faxen predict
  (:func:`ptrack.motion.wall.wall_evidence`, delta chi^2 >=
  :data:`ptrack.motion.wall.WALL_EVIDENCE_DCHI2` against flat D). Otherwise
  D is reported as measured, with a note (a sample confined by planes
  without hydrodynamic hindrance, as the shipped 3D movie, is not
  corrected). ``hindered["decision"]`` and ``hindered["evidence"]`` say
  what and why. A wall placed above particles stops the correction with a
  message (``hindered["applied"] = False``).

Examples
--------
>>> from ptrack.motion import brownian_field
>>> df = brownian_field(n_frames=60, size=30e-6, density=0.06e12, D=8.6e-13, dt=0.1, sigma=20e-9, seed=2)
>>> a = analyze_table(df, radius=250e-9, viscosity=1e-3, temperature=293.15, motion_blur=0.0)
>>> a.summary["D_method"], round(a.summary["D_over_D_SE"], 1)
('linking-free (pairs)', 1.0)
>>> a.summary["D_method_reason"].startswith("the estimates agree")
True
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import UserError, atomic_output, check_positive, check_writable, missing_dirs, remove_empty_dirs
from .motion import wall
from .motion.anomalous import powerlaw_flags
from .motion.cve import particle_diffusion
from .motion.diffusion import DiffusionResult, estimate_diffusion
from .motion.pairs import pair_diffusion
from .motion.stokes import implausible_D_note, stokes_einstein
from .motion.tracks import check_motion_blur, frame_interval, resolve_motion_blur
from .motion.velocity import default_axes

#: quantile of the measured heights taken as the lowest centre height reached (3D wall from the data)
WALL_QUANTILE = 0.005
#: difference (in the larger standard error) beyond which the tracks and the linking-free D disagree
AGREE_Z = 2.0
#: link ambiguity above which linked tracks are biased low (swapped identities)
AMBIGUOUS_LINKS = 0.05


@dataclass
class Analysis:
    """Result of :func:`analyze_table` (SI units).

    Attributes
    ----------
    summary : dict
        JSON-ready summary (what ``summary.json`` holds).
    diffusion : DiffusionResult
        D from the tracks (:func:`ptrack.motion.estimate_diffusion`).
    per_particle : DataFrame
        CVE D of each track with its error, mean height, wall ratio.
    flags : DataFrame
        :func:`ptrack.motion.powerlaw_flags`.
    table : DataFrame
        The trajectories analysed.
    notes : list of str
        Warnings for the user (a correction not applied, an implausible D).
    """

    summary: dict
    diffusion: DiffusionResult
    per_particle: pd.DataFrame
    flags: pd.DataFrame
    table: pd.DataFrame
    notes: list = field(default_factory=list)


def check_parameters(radius, viscosity, temperature, wall_z=None, height=None, estimator="cve", motion_blur=None,
                     n_boot=200) -> dict:
    """Every analysis parameter checked at once, before any work (tracking a movie can take minutes).

    Returns the checked values as keyword arguments of :func:`analyze_table`.
    """
    radius = check_positive("radius", radius)
    out = {"radius": radius, "viscosity": check_positive("viscosity", viscosity),
           "temperature": check_positive("temperature", temperature)}
    if wall_z is not None:
        wz = float(wall_z)
        if not math.isfinite(wz):
            raise UserError(f"wall_z = {wall_z!r} is not finite", "give the wall's z in m")
        out["wall_z"] = wz
    if height is not None:
        h = check_positive("height", height)
        if h <= radius:
            raise UserError(f"height = {h:g} m is not above the radius {radius:g} m",
                            "give the centre height above the wall (more than the radius)")
        out["height"] = h
    est = str(estimator).lower()
    if est not in ("cve", "ols"):
        raise UserError(f"unknown estimator '{estimator}'", "choose 'cve' or 'ols'")
    out["estimator"] = est
    if motion_blur is not None:
        out["motion_blur"] = check_motion_blur(motion_blur)
    if int(n_boot) < 0:
        raise UserError(f"n_boot = {n_boot} is negative", "give 0 or a positive number of resamples")
    out["n_boot"] = int(n_boot)
    return out


def linking_free_check(table: pd.DataFrame, axes, motion_blur: float) -> dict | None:
    """Linking-free D (:func:`ptrack.motion.pair_diffusion`) and the motion blur its intercept implies.

    Returns None when the field of view is too small for it.
    """
    try:
        pr = pair_diffusion(table, axes=axes, motion_blur=motion_blur)
    except UserError:
        return None
    D = {k: float(v) for k, v in pr.D.items()}
    # the fitted intercept 2 sigma^2 - 4 R D dt with the localiser's sigma gives the R the data imply
    implied = None
    if all(f"sigma_{c}" in table.columns for c in ("x", "y")) and D["xy"] > 0:
        s2 = np.mean([np.nanmean(table[f"sigma_{c}"].to_numpy(float) ** 2) for c in ("x", "y")])
        c_fit = np.mean([pr.intercept[c] for c in ("x", "y")])
        implied = float((2 * s2 - c_fit) / (4 * D["xy"] * pr.frame_interval))
    return {"D": D, "D_err": {k: float(v) for k, v in pr.D_err.items()}, "link_ambiguity": float(pr.link_ambiguity),
            "lags": int(len(pr.lags)), "offset": pr.offset_used, "motion_blur_assumed": float(motion_blur),
            "motion_blur_implied": implied}


def choose_D(D_tracks: dict, err_tracks: dict, pairs: dict | None, axis: str = "xy") -> tuple[str, str]:
    """Which D to report, ``"tracks"`` or ``"linking-free (pairs)"``, and why (one sentence).

    D from tracks is biased low when particles move a fair fraction of their
    spacing per frame (swapped identities shorten the steps); the pair
    estimate has no links to get wrong but assumes independent particles.
    When the two agree (difference within :data:`AGREE_Z` times the larger
    error: they share their data, so the quadrature sum would be too wide)
    the more precise is reported; when they disagree, the pair estimate if
    links are ambiguous (:data:`AMBIGUOUS_LINKS`), else the tracks (a
    disagreement with unambiguous links points to correlated particles,
    which the pair model ignores).

    Examples
    --------
    >>> choose_D({"xy": 1.0}, {"xy": 0.02}, None)
    ('tracks', 'no linking-free estimate (field of view too small for it)')
    >>> choose_D({"xy": 1.0}, {"xy": 0.05}, {"D": {"xy": 1.01}, "D_err": {"xy": 0.02}, "link_ambiguity": 0.01})[0]
    'linking-free (pairs)'
    """
    if pairs is None:
        return "tracks", "no linking-free estimate (field of view too small for it)"
    e = max(pairs["D_err"][axis], err_tracks[axis])
    z = abs(pairs["D"][axis] - D_tracks[axis]) / e if e > 0 else math.inf
    amb = pairs["link_ambiguity"]
    if z > AGREE_Z:
        if amb > AMBIGUOUS_LINKS:
            return "linking-free (pairs)", (f"the estimates differ by {z:.1f} SE and links are ambiguous "
                                            f"({amb:.3f} > {AMBIGUOUS_LINKS}): D from tracks is biased low")
        return "tracks", (f"the estimates differ by {z:.1f} SE with unambiguous links ({amb:.3f}): "
                          "correlated particles, which the pair model ignores")
    if pairs["D_err"][axis] < err_tracks[axis]:
        return "linking-free (pairs)", f"the estimates agree ({z:.1f} SE) and the linking-free one is more precise"
    return "tracks", f"the estimates agree ({z:.1f} SE) and the tracks' is more precise"


def wall_from_data(table: pd.DataFrame, radius: float) -> float:
    """z of the wall (m): the lowest centre heights reached (:data:`WALL_QUANTILE` of z) minus the radius."""
    z = table["z"].to_numpy(float)
    z = z[np.isfinite(z)]
    return float(np.quantile(z, WALL_QUANTILE) - radius)


def _hindered(per: pd.DataFrame, table: pd.DataFrame, three_d: bool, radius: float, D: float, D_err: float,
              D_se: float, wall_z, height, seed: int = 0):
    """The wall correction (dict) and a note when it is not applied.

    3D: the correction is applied when the wall is given (``wall_z[1] == "given"``: the user's word) or when
    the data show it (:func:`ptrack.motion.wall.wall_evidence`: D parallel to the wall falls with height as
    Brenner / Faxen predict, delta chi^2 >= :data:`ptrack.motion.wall.WALL_EVIDENCE_DCHI2`); else D is
    reported uncorrected and the note says why and how to force it. A wall above particles' mean heights
    stops the correction either way.
    """
    if three_d:
        h = per["z_mean"].to_numpy() - wall_z[0]
        below = np.isfinite(h) & (h < radius)
        per["height"] = h
        if below.any():
            note = (f"wall correction not applied: {int(below.sum())} particles have a mean centre height "
                    f"below contact ({radius:g} m) over the wall at z = {wall_z[0]:g} m ({wall_z[1]}); give --wall-z "
                    "below the lowest particles (m, calibration coordinates)")
            return {"applied": False, "reason": note, "wall_z_m": wall_z[0], "wall_z_source": wall_z[1],
                    "n_particles_below_contact": int(below.sum())}, note
        ok = np.isfinite(h)
        ratio = np.full(len(per), np.nan)
        ratio[ok] = wall.parallel_ratio(h[ok], radius)
        per["ratio_parallel"] = ratio
        if not ok.any():
            return None, None
        ev = wall.wall_evidence(table, radius, wall_z[0], seed=seed)
        # the D over the tracks is D0 times the mean ratio over the points (heights) it was measured at
        mean_ratio = ev["mean_ratio"] if ev else float(np.average(ratio[ok], weights=per["n_frames"].to_numpy()[ok]))
        out = {"wall_z_m": wall_z[0], "wall_z_source": wall_z[1],
               "mean_height_m": float(np.nanmean(table["z"].to_numpy(float)) - wall_z[0]),
               "mean_ratio_parallel": mean_ratio, "n_particles_below_contact": 0, "evidence": ev}
        corrected = {"D_bulk_xy": D / mean_ratio, "D_bulk_xy_err": D_err / mean_ratio,
                     "D_SE_hindered_xy": D_se * mean_ratio}
        if wall_z[1] == "given":
            out.update(applied=True, decision="applied: the wall height was given (--wall-z)", **corrected)
            return out, None
        if ev is not None and ev["favours"] == "wall":
            out.update(applied=True, decision=(f"applied: D parallel to the wall falls with height as a wall at "
                                               f"z = {wall_z[0]:g} m predicts (delta chi2 = {ev['delta_chi2']:.1f} "
                                               f">= {ev['threshold']:g})"), **corrected)
            return out, None
        verdict = {"no wall": "the data favour no wall", "undecided": "the data cannot tell",
                   "neither": (f"a wall fits better than a flat D but does not fit either (chi2 = {ev['chi2_wall']:.0f} "
                               f"for {ev['dof']} dof: stuck particles or drift?)") if ev else ""}
        why = ("too few points to test for a wall" if ev is None else
               f"{verdict[ev['favours']]} (D_par vs height: delta chi2 = {ev['delta_chi2']:.1f}, a wall needs >= "
               f"{ev['threshold']:g})")
        note = (f"wall correction not applied: {why}; D is reported as measured. A wall at z = "
                f"{wall_z[0] * 1e6:.3g} µm ({wall_z[1]}) would give D corrected to bulk = {D / mean_ratio * 1e12:.4f} "
                "µm²/s; give --wall-z (m) to apply it")
        out.update(applied=False, reason=note, decision=f"not applied: {why}",
                   D_bulk_xy_if_applied=D / mean_ratio)
        return out, note
    if height is not None:
        r = float(wall.parallel_ratio(height, radius))
        return {"applied": True, "decision": "applied: the height was given (--height)", "assumed_height_m": height,
                "ratio_parallel": r, "D_bulk_xy": D / r, "D_bulk_xy_err": D_err / r, "D_SE_hindered_xy": D_se * r}, None
    return None, None


def analyze_table(table: pd.DataFrame, radius: float, viscosity: float, temperature: float, wall_z=None,
                  height=None, subtract_drift: bool = False, estimator: str = "cve", motion_blur=None,
                  n_boot: int = 200, seed: int = 0) -> Analysis:
    """Diffusion against Stokes-Einstein, with the wall correction, drift velocity and flags (no file written).

    Parameters
    ----------
    table : DataFrame
        Trajectories table (SI units).
    radius, viscosity, temperature : float
        m, Pa s, K.
    wall_z : float, optional
        z of the wall (m, 3D; the calibration's coordinates): heights are
        ``z - wall_z``; the correction is then applied. Default: from the
        data (:func:`wall_from_data`), the correction applied only when the
        data show the wall (see the module docstring).
    height : float, optional
        Assumed centre height above the wall (m) for 2D data.
    subtract_drift : bool
        Remove the ensemble drift before estimating D.
    estimator : {"cve", "ols"}
    motion_blur : float, optional
        R; default from the metadata or the data
        (:func:`ptrack.motion.tracks.resolve_motion_blur`).
    n_boot, seed
        Bootstrap over particles.

    Returns
    -------
    Analysis
    """
    p = check_parameters(radius, viscosity, temperature, wall_z, height, estimator, motion_blur, n_boot)
    radius = p["radius"]
    R, R_source = resolve_motion_blur(table, p.get("motion_blur"))
    dt = frame_interval(table)
    # 3D by the one axes rule: z that changes (a 2D table with z = 0 in every row is 2D)
    three_d = "z" in default_axes(table)
    axes = ("x", "y", "xy")
    notes = []
    # The image edges cut tracks: correct the loss of long steps there (x and y only: in z the
    # calibrated range need not cut tracks).
    res = estimate_diffusion(table, axes=axes, estimator=p["estimator"], motion_blur=R, n_boot=p["n_boot"],
                             seed=seed, subtract_drift=subtract_drift, field_of_view="auto")
    D_se = float(stokes_einstein(radius, p["viscosity"], p["temperature"]))
    D_tracks = {k: float(v) for k, v in res.D.items()}
    err_tracks = {k: float(v) for k, v in res.D_err.items()}
    pair = linking_free_check(table, axes, R)
    method, why = choose_D(D_tracks, err_tracks, pair)
    D_best, err_best = (pair["D"], pair["D_err"]) if method.startswith("linking") else (D_tracks, err_tracks)
    note = implausible_D_note(D_best["xy"])
    if note:
        notes.append(note)
    summary = {
        "D": D_best, "D_err": err_best, "D_method": method, "D_method_reason": why,
        "D_tracks": D_tracks, "D_tracks_err": err_tracks, "D_pairs": pair,
        "D_stokes_einstein": D_se, "D_over_D_SE": float(D_best["xy"] / D_se),
        "n_tracks": int(table["particle"].nunique()), "n_localisations": int(len(table)),
        "sigma_loc": {k: float(v) for k, v in res.sigma_loc.items()}, "estimator": res.estimator,
        "motion_blur": R, "motion_blur_source": R_source,
        "drift_corrected": bool(res.drift_corrected), "radius_m": radius, "viscosity_Pa_s": p["viscosity"],
        "temperature_K": p["temperature"], "frame_interval_s": dt,
        "units": {"D": "m^2/s", "D_err": "m^2/s", "D_stokes_einstein": "m^2/s", "sigma_loc": "m"},
    }
    per = particle_diffusion(table, axes=axes, motion_blur=R, subtract_drift=subtract_drift)
    zm = table.groupby("particle")["z"].mean()
    per["z_mean"] = zm.reindex(per["particle"]).to_numpy(float)
    wz = None
    if three_d:
        wz = (p["wall_z"], "given") if "wall_z" in p else (
            wall_from_data(table, radius), f"from the data: the {100 * WALL_QUANTILE:g} % quantile of z minus the radius")
    hind, note = _hindered(per, table, three_d, radius, D_best["xy"], err_best["xy"], D_se, wz, p.get("height"),
                           seed=seed)
    if note:
        notes.append(note)
    summary["hindered"] = hind
    # the common drift (EPD: electrophoretic or sedimentation drift), per particle by GLS, then the ensemble
    from .motion.velocity import ensemble_velocity, particle_velocity

    try:
        ens = ensemble_velocity(particle_velocity(table, axes=default_axes(table), motion_blur=R), seed=seed)
        summary["drift_velocity"] = {r.axis: {"v": float(r.v), "v_err": float(r.v_err), "chi2_dof": float(r.chi2_dof)}
                                     for r in ens.itertuples()}
        summary["units"]["drift_velocity"] = "m/s"
    except UserError as exc:          # e.g. tracks too short for a velocity with an error: said, not hidden
        summary["drift_velocity"] = None
        summary["drift_velocity_note"] = str(exc)
        notes.append(f"no drift velocity: {exc}")
    flags = powerlaw_flags(table, seed=seed)
    flagged = flags[flags["flagged"]]
    summary["nondiffusive"] = {"n_flagged": int(len(flagged)), "n_assessed": int(np.isfinite(flags["alpha"]).sum()),
                               "tracks": [{"particle": int(r.particle), "alpha": float(r.alpha), "reason": str(r.reason)}
                                          for r in flagged.itertuples()]}
    summary["notes"] = list(notes)
    return Analysis(summary=jsonable(summary), diffusion=res, per_particle=per, flags=flags, table=table, notes=notes)


def check_writable_dir(path, what: str = "--report") -> Path:
    """UserError now, not after the work, when a report folder cannot be created at ``path``
    (:func:`ptrack.errors.check_writable`, the one rule)."""
    return check_writable(path, what, directory=True)


@contextlib.contextmanager
def atomic_dir(path, last: str = "summary.json"):
    """Build a folder's files under a temporary name beside ``path``; they reach ``path`` only when all are written.

    A new folder is renamed into place in one step. Into an existing folder
    (which may hold other files, e.g. the trajectories table) the files are
    moved one by one, ``last`` at the end, so a report is complete once its
    ``last`` file is new. An interrupt (Ctrl-C) or an error while writing
    leaves ``path`` as it was and no temporary folder behind.
    """
    path = Path(path)
    created = missing_dirs(path.parent)  # removed again, if empty, when the report fails (a full disk)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    except BaseException:
        remove_empty_dirs(created)
        raise
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o777 & ~umask)             # mkdtemp makes 0700: honour the umask like mkdir
        yield tmp
        if not path.exists():
            os.replace(tmp, path)
            return
        for f in sorted(tmp.iterdir(), key=lambda f: f.name == last):
            os.replace(f, path / f.name)
        tmp.rmdir()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_empty_dirs(created)
        raise


def write_report(analysis: Analysis, report_dir, movie=None) -> Path:
    """Write ``summary.json``, the CSV tables and the figures into ``report_dir``, all or nothing.

    Files: ``summary.json``, ``per_particle.csv``, ``nondiffusive.csv``,
    ``msd.png``, ``D_per_particle.png``, ``tracks.png`` (with the movie),
    ``cm_vs_z.png`` (3D).
    """
    from . import plot

    s = analysis.summary
    with atomic_dir(report_dir) as rd:
        table = analysis.table
        if movie is not None and "x_px" in table.columns:
            from .io import open_movie

            f0 = int(table["frame"].min())
            with open_movie(movie) as mv:
                img = np.asarray(mv[min(f0, len(mv) - 1)], float)
            plot.plot_tracks(img, table, rd / "tracks.png", frame=f0)
        reported = None
        if s["D_method"].startswith("linking"):
            reported = {a: (s["D"][a], s["D_err"][a], "linking-free") for a in s["D"]}
        name = Path(str(movie)).name if movie is not None else "trajectories"
        plot.plot_msd(analysis.diffusion, rd / "msd.png", title=f"{name}: ensemble MSD", reported=reported)
        hind = s.get("hindered") or {}
        if len(analysis.per_particle):
            plot.plot_D_per_particle(analysis.per_particle, "xy", rd / "D_per_particle.png", D_ensemble=s["D"]["xy"],
                                     D_stokes_einstein=s["D_stokes_einstein"],
                                     D_hindered=hind.get("D_SE_hindered_xy") if hind.get("applied") else None,
                                     label_ensemble=f"ensemble ({s['D_method']})")
        if "z" in default_axes(table) and "cm" in table:
            plot.plot_cm_vs_z(table, rd / "cm_vs_z.png")
        analysis.per_particle.to_csv(rd / "per_particle.csv", index=False)
        analysis.flags.to_csv(rd / "nondiffusive.csv", index=False)
        with atomic_output(rd / "summary.json", "w") as fh:
            json.dump(s, fh, indent=2)
    return Path(report_dir)


def analyze_movie(movie, radius: float, viscosity: float, temperature: float, report_dir=None, out=None,
                  wall_z=None, height=None, subtract_drift: bool = False, estimator: str = "cve", motion_blur=None,
                  n_boot: int = 200, seed: int = 0, table: pd.DataFrame | None = None, **track_kwargs) -> Analysis:
    """Check every parameter, track the movie (unless ``table`` is given), analyse, and write the report.

    Parameters
    ----------
    movie : path-like or None
    radius, viscosity, temperature, wall_z, height, subtract_drift, estimator, motion_blur, n_boot, seed
        As :func:`analyze_table`.
    report_dir : path-like, optional
        Folder for the report (:func:`write_report`), written all or nothing.
    out : path-like, optional
        Also write the trajectories table.
    table : DataFrame, optional
        Skip tracking and analyse this table.
    **track_kwargs
        As :func:`ptrack.pipeline.track_movie`.

    Returns
    -------
    Analysis
        ``summary["track"]`` holds the tracking summary.
    """
    kw = check_parameters(radius, viscosity, temperature, wall_z, height, estimator, motion_blur, n_boot)
    if report_dir is not None:
        check_writable_dir(report_dir)
    if out is not None:
        if Path(out).is_dir():
            raise UserError(f"--out {out} is a folder", "give a file name for the trajectories table")
        check_writable_dir(Path(out).parent, "--out")
    track_summary = {}
    if table is None:
        from .pipeline import track_movie

        table, track_summary = track_movie(movie, out=out, **track_kwargs)
    a = analyze_table(table, subtract_drift=subtract_drift, seed=seed, **kw)
    a.summary["track"] = jsonable(track_summary)
    if report_dir is not None:
        write_report(a, report_dir, movie=movie)
    return a


def jsonable(obj):
    """Nested dicts/lists with numpy scalars made plain and non-finite floats made None (valid JSON)."""
    from .table import to_jsonable

    return to_jsonable(obj, finite=True)
