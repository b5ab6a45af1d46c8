"""A movie's simulated twin: track it, infer its physics, simulate, render, track again, compare.

:func:`run_twin` does the seven steps of ``ptrack twin``:

1. track the movie (:func:`ptrack.pipeline.track_movie`; 2D, or 3D with a calibration);
2. infer the parameters, each with an error (:func:`infer_parameters`):
   the radius from D (or the viscosity when the radius is given), with the
   wall correction of each particle's measured height (3D) or of a given
   height (2D) (:mod:`ptrack.wall`); from the drift along z and the field E
   the electrophoretic velocity (sedimentation subtracted when the particle
   density is known), the zeta potential (Henry's exact function,
   :mod:`sim.electrokinetics`) and the charge; the number density and the
   heights; the camera (background, noise, photons per particle, spot size)
   and the motion blur the data imply (:func:`measure_camera`);
3. write them as ``scene.toml`` (a :mod:`sim.scene` file, valid for
   ``ptrack simulate``) and ``render.toml`` (view, optics, camera), both
   readable and editable;
4. simulate on the engine (:func:`sim.run.run_scene`: overdamped Brownian
   dynamics, wall mobility, field, gravity and buoyancy) in a box larger than
   the field of view with periodic sides, so that particles enter and leave
   the view as in the movie;
5. render it with the same optics and camera (:func:`sim.render.render_movie`)
   and track it with the same settings;
6. compare (:func:`ptrack.compare.compare_tables`) measured tracks against twin
   tracks (both went through the pipeline) and twin tracks against the twin's
   truth (what the pipeline does, apart from the physics);
7. report the parameters, the verdicts and what each disagreement most
   likely means (``twin.json``, ``report.html``).

``overrides`` (``--set KEY=VALUE``) replace any inferred value: scene keys
(``particles.radius``, ``fluid.viscosity``, ``fields.E`` ...) or render keys
(``optics.na``, ``camera.photons``, ``view.focal_plane`` ...), for what-if
twins.
"""
from __future__ import annotations

import json
import math
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from .constants import BOLTZMANN, STANDARD_GRAVITY, VACUUM_PERMITTIVITY
from .errors import UserError, atomic_output, check_positive
from .motion.tracks import exposure_from_motion_blur, motion_blur_from_data, motion_blur_from_exposure
from .motion.velocity import default_axes

__all__ = ["infer_parameters", "measure_camera", "build_scene", "to_toml", "apply_overrides", "run_twin",
           "interpret"]


# --------------------------------------------------------------------------- camera and optics from the movie
def measure_camera(movie, table: pd.DataFrame, brightfield: bool, gain: float, offset: float, qe: float,
                   box_px: int, n_sample: int = 12) -> dict:
    """Background, noise, photons per particle and spot size measured on the movie's own frames.

    Parameters
    ----------
    movie : path-like
        The movie (:func:`ptrack.io.open_movie`).
    table : DataFrame
        Its trajectories (``x_px``, ``y_px``, ``frame``).
    brightfield : bool
        Dark particles on a bright field: the photons a particle removes.
    gain, offset, qe : float
        Camera gain (ADU per e-), offset (ADU) and quantum efficiency.
    box_px : int
        Half-size of the square around each particle whose light is summed, px.
    n_sample : int
        Frames sampled.

    Returns
    -------
    dict
        ``background_photons`` (per pixel), ``read_noise_e`` (from the
        variance of the difference of two frames minus the shot noise),
        ``photons`` (median per particle per exposure, and its interquartile
        range), ``noise_adu`` (frame-difference noise per pixel).
    """
    from .io import open_movie

    with open_movie(movie) as mv:
        n = len(mv)
        idx = np.unique(np.linspace(0, n - 2, min(n_sample, n - 1)).astype(int))
        flux, bg, var = [], [], []
        for i in idx:
            f = mv[int(i)].astype(float)
            g = mv[int(i) + 1].astype(float)
            med = float(np.median(f))
            bg.append(med)
            d = (f - g).ravel()
            var.append((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2 / 2)   # robust: particles move
            rows = table[table["frame"] == i]
            H, W = f.shape
            for x, y in zip(rows["x_px"].to_numpy(), rows["y_px"].to_numpy()):
                xi, yi = int(round(x)), int(round(y))
                if box_px <= xi < W - box_px and box_px <= yi < H - box_px:
                    patch = f[yi - box_px:yi + box_px + 1, xi - box_px:xi + box_px + 1]
                    ring = np.r_[patch[0], patch[-1], patch[:, 0], patch[:, -1]]
                    s = float(np.sum(patch - np.median(ring)))
                    flux.append(-s if brightfield else s)
    bg_adu = float(np.median(bg))
    scale = gain * qe
    bg_ph = max((bg_adu - offset) / scale, 0.0)
    var_adu = float(np.median(var))
    # ADU variance = gain^2 (qe B + read_noise^2): the read noise that remains after the shot noise
    rn2 = var_adu / gain ** 2 - qe * bg_ph
    flux = np.asarray(flux) / scale
    return {"background_adu": bg_adu, "background_photons": bg_ph, "noise_adu": math.sqrt(var_adu),
            "read_noise_e": math.sqrt(rn2) if rn2 > 0 else 0.0,
            "photons": float(np.median(flux)) if len(flux) else float("nan"),
            "photons_iqr": float(np.subtract(*np.percentile(flux, [75, 25]))) if len(flux) else float("nan"),
            "n_particles_measured": int(len(flux)), "box_px": int(box_px),
            "method": "median frame (background), MAD of frame differences (noise), background-subtracted sum "
                      f"over {2 * box_px + 1} px squares (photons), converted with gain {gain:g} ADU/e-, "
                      f"offset {offset:g} ADU, QE {qe:g}"}


def twin_exposure(motion_blur: dict | None, frame_interval: float) -> tuple[float | None, float, int]:
    """Camera exposure of the twin's movie from the blur the measured data imply.

    A uniform exposure of length ``e`` in a frame of ``dt`` gives R = (e / dt) / 6, so the twin is rendered
    with ``e = min(6 R, 1) dt`` (:func:`ptrack.motion.tracks.exposure_from_motion_blur`) when R is significant
    (above 2 of its errors and 0.03), else instantaneously; its R is that of ``e``
    (:func:`ptrack.motion.tracks.motion_blur_from_exposure`: R capped at 1/6).

    Parameters
    ----------
    motion_blur : dict or None
        ``{"R": ..., "R_err": ...}`` from :func:`infer_parameters` (None: not measurable).
    frame_interval : float
        s.

    Returns
    -------
    (exposure, R, substeps)
        Exposure in s (None: instantaneous), the R the twin's movie has (what its tracks are analysed
        with; at most 1/6), and the motion-blur sub-positions per frame for the renderer (0: none).

    Examples
    --------
    >>> e, R, n = twin_exposure({"R": 0.1, "R_err": 0.01}, 0.1)
    >>> round(e, 12), round(R, 12), n
    (0.06, 0.1, 8)
    >>> twin_exposure({"R": 0.02, "R_err": 0.01}, 0.1)
    (None, 0.0, 0)
    """
    mb = motion_blur
    if not (mb and mb["R"] > 2 * mb["R_err"] and mb["R"] > 0.03):
        return None, 0.0, 0
    exposure = exposure_from_motion_blur(mb["R"], frame_interval)
    return exposure, motion_blur_from_exposure(exposure, frame_interval), 8


def _implied_motion_blur(table: pd.DataFrame) -> dict | None:
    """The blur the data imply, given the localiser's sigma (2D): :func:`ptrack.motion.tracks.motion_blur_from_data`
    (the one rule), its error a bootstrap over particles; None without the localiser's sigma_x, sigma_y."""
    if not {"sigma_x", "sigma_y"} <= set(table.columns):
        return None
    R, R_err = motion_blur_from_data(table, n_boot=300, seed=0)
    if R is None:
        return None
    sig2 = float(np.nanmean(np.r_[table["sigma_x"].to_numpy(float) ** 2, table["sigma_y"].to_numpy(float) ** 2]))
    return {"R": float(R), "R_err": float(R_err), "sigma_loc_m": math.sqrt(sig2),
            "note": "R = 0: instantaneous exposure; 1/6: shutter open the whole frame"}


def flag_stuck(df: pd.DataFrame, sigma: float, window: int = 5, floor: float = 0.15e-6) -> pd.DataFrame:
    """Mark each track's rows from the moment it stops moving sideways for good (deposited, stuck).

    A particle that sticks on the substrate stops in x and y as well as z; a free one diffuses sideways
    (0.4 um in 5 frames at 30 fps for 0.8 um particles). A row is ``deposited`` when every later row of
    its track stays within ``max(8 sigma, floor)`` of it in x and in y (the suffix range of the track),
    and at least ``window`` rows follow. Unlike a height threshold this needs no correct z near the wall
    (brightfield GDPT may read a particle sitting on the substrate 2 um too high).

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    sigma : float
        Localisation error in x, y, m.
    window : int
        Fewest rows of a stationary end of a track.
    floor : float
        Smallest allowed spread of a stuck particle's positions, m.

    Returns
    -------
    DataFrame
        A copy with a boolean column ``deposited``.
    """
    thr = max(8 * float(sigma), floor)
    d = df.sort_values(["particle", "frame"], kind="stable").reset_index(drop=True)
    rev = d.iloc[::-1]
    g = rev.groupby("particle", sort=False)
    ok = np.ones(len(d), bool)
    for c in ("x", "y"):
        rng_ = (g[c].cummax() - g[c].cummin()).iloc[::-1].to_numpy()
        ok &= rng_ <= thr
    after = rev.groupby("particle", sort=False).cumcount().iloc[::-1].to_numpy()   # rows after this one
    # a row is stuck if it and all later rows are within thr; the suffix must be long enough
    stuck = ok & (after + 1 >= window)
    # once stuck, the rest of the track is stuck (suffix property), so the flag is monotone in frame
    d["deposited"] = stuck
    return d


# --------------------------------------------------------------------------- physical parameters
def infer_parameters(table: pd.DataFrame, temperature: float, viscosity: float, radius: float | None = None,
                     height: float | None = None, wall_z: float = 0.0, wall_hydrodynamics: bool = True,
                     field: float | None = None, density: float | None = None, fluid_density: float = 998.2,
                     debye_length: float = 100e-9, permittivity: float = 78.5, motion_blur: float = 1 / 6,
                     n_boot: int = 200, seed: int = 0, pipeline_bias: dict | None = None) -> dict:
    """Radius (or viscosity), zeta potential, charge, number density and heights from a trajectories table.

    Parameters
    ----------
    table : DataFrame
        Measured trajectories (2D, or 3D with z in the calibration's frame).
    temperature : float
        K.
    viscosity : float
        Pa s (inferred instead when ``radius`` is given).
    radius : float, optional
        m; given, the viscosity is inferred from D.
    height : float, optional
        Centre height above the wall for 2D data, m (wall correction); None: bulk.
    wall_z : float
        z of the wall (substrate, electrode) in the table's coordinates, m (3D).
    wall_hydrodynamics : bool
        Correct D for the hindered mobility near the wall (False: free-space
        mobility, as in a movie rendered without wall hydrodynamics).
        (:func:`run_twin` also takes ``wall=False``: no substrate near the particles at all.)
    field : float, optional
        E_z, V/m (+z away from the wall): infer the electrophoretic mobility, zeta and charge from v_z.
    density, fluid_density : float
        kg/m^3; the particle density sets the sedimentation subtracted from v_z.
    debye_length, permittivity : float
        m and relative permittivity, for Henry's function and the charge.
    motion_blur : float
        R of the movie (for the velocity error model).
    pipeline_bias : dict, optional
        ``{"D": (factor, rel_err), "v_z": (factor, rel_err)}``: what the pipeline does to D_xy and v_z,
        as truth / tracks of a twin (:func:`pipeline_bias_of`); the measured values are multiplied by
        the factors (errors added in quadrature) before the radius and zeta are derived.

    Returns
    -------
    dict with plain keys (SI): ``radius_m``, ``radius_err_m``, ``viscosity_Pa_s`` ...,
    ``D``, ``D_err`` (x, y, xy), ``wall_ratio``, ``drift`` (per axis), ``zeta_V``,
    ``zeta_err_V``, ``charge_C``, ``number_density_per_m2``, ``heights`` (3D).
    """
    from . import msd, wall
    from .velocity import ensemble_velocity, particle_velocity, trim_deposited

    check_positive("temperature", temperature)
    check_positive("viscosity", viscosity)
    three_d = "z" in default_axes(table)   # heights that change (the one rule; z = 0 in every row is a 2D table)
    kT = BOLTZMANN * temperature
    out: dict = {"three_d": three_d, "temperature_K": temperature, "notes": []}

    def estimate(df):
        res = msd.estimate_diffusion(df, axes=("x", "y", "xy"), motion_blur=motion_blur, n_boot=n_boot, seed=seed,
                                     field_of_view="auto")
        return res

    def ratio_of(df, R):
        """Mean parallel hindrance of the rows (each particle at its own height), weighted by displacements."""
        if not wall_hydrodynamics:
            return 1.0
        if three_d:
            h = df.groupby("particle")["z"].mean().to_numpy(float) - wall_z
            w = df.groupby("particle").size().to_numpy(float) - 1
            ok = np.isfinite(h) & (h > R)
            if not ok.any():
                return 1.0
            return float(np.sum(wall.parallel_ratio(h[ok], R) * w[ok]) / np.sum(w[ok]))
        if height is not None:
            if height <= R:
                raise UserError(f"--height {height} m is not above the radius {R:.3g} m", "give the centre height")
            return float(wall.parallel_ratio(height, R))
        return 1.0

    used = table
    res = estimate(used)
    D, De = res.D["xy"], res.D_err["xy"]
    if not D > 0:
        raise UserError(f"the measured D_xy = {D:.3g} m^2/s is not positive", "check the tracks (too short or too noisy?)")

    def solve_R(D, used):
        R = kT / (6 * math.pi * viscosity * D)
        for _ in range(30):     # D = ratio(h, R) kT / (6 pi mu R): fixed point in R
            R = kT * ratio_of(used, R) / (6 * math.pi * viscosity * D)
        return R

    R_est = radius if radius is not None else solve_R(D, used)
    if three_d and (field is not None or density is not None):
        # deposited particles sit still at the wall: their rows would pull D and the drift towards zero.
        # Dropped where the height says so (trim_deposited) or where the particle has stopped sideways
        # (flag_stuck: robust to a wrong z near the wall)
        flagged = flag_stuck(table, res.sigma_loc["xy"])
        moving = flagged[~flagged["deposited"]].drop(columns="deposited")
        moving.attrs.update(table.attrs)
        trimmed = trim_deposited(moving, z_contact=wall_z + R_est)
        if trimmed["particle"].nunique() >= 3:
            used = trimmed
            res = estimate(used)
            D, De = res.D["xy"], res.D_err["xy"]
            R_est = radius if radius is not None else solve_R(D, used)
            out["notes"].append(f"rows from contact with the wall on dropped ({len(table) - len(used)} rows; "
                                f"{int(flagged['deposited'].sum())} of them stationary sideways)")
            out["n_deposited_tracks"] = int(flagged.groupby("particle")["deposited"].any().sum())
    Dd, Dde = dict(res.D), dict(res.D_err)
    if pipeline_bias and "D" in pipeline_bias:
        fD, eD = pipeline_bias["D"]
        for a in Dd:
            Dde[a] = math.hypot(Dde[a] * fD, Dd[a] * fD * eD)
            Dd[a] = Dd[a] * fD
        D, De = Dd["xy"], Dde["xy"]
        R_est = radius if radius is not None else solve_R(D, used)
        out["notes"].append(f"D corrected for the pipeline by x{fD:.4g} +- {eD * fD:.2g} (twin truth / twin tracks)")
    ratio = ratio_of(used, R_est)
    out["sigma_loc_xy_m"] = float(res.sigma_loc["xy"])
    out.update({"D_measured": dict(res.D), "D": Dd, "D_err": Dde, "D_method": "CVE over tracks, field-of-view corrected",
                "n_tracks": int(table["particle"].nunique()), "wall_ratio": ratio,
                "wall_hydrodynamics": bool(wall_hydrodynamics), "wall_z_m": wall_z, "assumed_height_m": height})
    D0 = D / ratio
    if radius is None:
        out["radius_m"] = R_est
        out["radius_err_m"] = R_est * De / D          # the wall ratio's own dependence on R is second order
        out["viscosity_Pa_s"] = viscosity
        out["viscosity_err_Pa_s"] = None
        out["inferred"] = "radius"
    else:
        out["radius_m"] = radius
        out["radius_err_m"] = None
        out["viscosity_Pa_s"] = kT / (6 * math.pi * radius * D0)
        out["viscosity_err_Pa_s"] = out["viscosity_Pa_s"] * De / D
        out["inferred"] = "viscosity"
    R = out["radius_m"]
    mu = out["viscosity_Pa_s"]
    out["D_bulk_m2_s"] = D0
    out["D_stokes_einstein_m2_s"] = kT / (6 * math.pi * mu * R)
    mb = _implied_motion_blur(table)
    out["motion_blur"] = mb
    # drift
    try:
        ens = ensemble_velocity(particle_velocity(used, axes=None, motion_blur=motion_blur), n_boot=500, seed=seed)
        out["drift"] = {r.axis: {"v": float(r.v), "v_err": float(r.v_err), "chi2_dof": float(r.chi2_dof),
                                 "n_particles": int(r.n_particles)} for r in ens.itertuples()}
    except UserError as exc:
        out["drift"] = None
        out["notes"].append(f"no drift: {exc.cause}")
    if pipeline_bias and "v_z" in pipeline_bias and out["drift"] and "z" in out["drift"]:
        fv, ev = pipeline_bias["v_z"]
        d = out["drift"]["z"]
        d["v_measured"] = d["v"]
        d["v_err"] = math.hypot(d["v_err"] * fv, d["v"] * fv * ev)
        d["v"] = d["v"] * fv
        out["notes"].append(f"v_z corrected for the pipeline by x{fv:.4g} +- {ev * fv:.2g} (twin truth / twin tracks)")
    # sedimentation and electrophoresis
    v_sed = None
    if density is not None:
        v_sed = -2.0 / 9.0 * (density - fluid_density) * STANDARD_GRAVITY * R ** 2 / mu
    out["v_sedimentation_m_s"] = v_sed
    out.update({"zeta_V": None, "zeta_err_V": None, "charge_C": None, "charge_err_C": None, "henry_f": None,
                "v_electrophoretic_m_s": None, "field_V_m": field, "debye_length_m": debye_length,
                "relative_permittivity": permittivity})
    if field is not None and out["drift"] and "z" in out["drift"]:
        from sim.electrokinetics import colloid_charge, henry_function

        vz, vze = out["drift"]["z"]["v"], out["drift"]["z"]["v_err"]
        v_ep = vz - (v_sed or 0.0)
        f = float(henry_function(R / debye_length))
        zeta = 3 * mu * v_ep / (2 * permittivity * VACUUM_PERMITTIVITY * field * f)
        # error: the drift's, and R's through f (and mu's when inferred), added in quadrature
        dlnf = (float(henry_function(1.01 * R / debye_length)) / f - 1) / 0.01
        rel_R = (out["radius_err_m"] or 0.0) / R
        rel_mu = (out["viscosity_err_Pa_s"] or 0.0) / mu
        zeta_err = abs(zeta) * math.sqrt((vze / v_ep) ** 2 + (dlnf * rel_R) ** 2 + rel_mu ** 2)
        q = float(colloid_charge(zeta, R, debye_length, permittivity))
        out.update({"zeta_V": zeta, "zeta_err_V": zeta_err, "henry_f": f, "v_electrophoretic_m_s": v_ep,
                    "charge_C": q, "charge_err_C": abs(q) * math.sqrt((zeta_err / zeta) ** 2 + rel_R ** 2)})
    elif field is not None:
        out["notes"].append("a field was given but the table has no z drift (2D): zeta not inferred")
    # number density (particles seen per frame per area of the view) and heights
    meta = table.attrs.get("ptrack", {})
    shape = meta.get("frame_shape")
    px = float(meta.get("pixel_size") or 0)
    counts = table.groupby("frame").size()
    if shape and px:
        area = shape[0] * shape[1] * px * px
        out["number_density_per_m2"] = float(counts.median() / area)
        out["view_area_m2"] = area
    out["particles_per_frame"] = float(counts.median())
    if three_d:
        z = table["z"].to_numpy(float) - wall_z
        rows0 = table.loc[table.groupby("particle")["frame"].idxmin()]
        first = rows0["z"].to_numpy(float) - wall_z
        dz = (out.get("drift") or {}).get("z")
        if dz and abs(dz["v"]) > 3 * dz["v_err"]:
            # a track that starts late came into the measurable range by drifting: its particle started
            # where the drift puts it at the movie's first frame (above the calibrated range if it drifts down)
            first = first - dz["v"] * (rows0["t"].to_numpy(float) - float(table["t"].min()))
            out["notes"].append("start heights of late tracks extrapolated back to the first frame along the drift")
        out["heights"] = {"z_min": float(np.nanmin(z)), "z_max": float(np.nanmax(z)),
                          "median": float(np.nanmedian(z)),
                          "start_p05": float(np.nanpercentile(first, 5)), "start_p95": float(np.nanpercentile(first, 95)),
                          # uniform start heights: unbiased ends of the range from n samples, min/max -+ range/(n-1)
                          "start_lo": float(np.nanmin(first) - np.ptp(first[np.isfinite(first)]) / max(len(first) - 1, 1)),
                          "start_hi": float(np.nanmax(first) + np.ptp(first[np.isfinite(first)]) / max(len(first) - 1, 1)),
                          "unit": "m above the wall (wall_z subtracted)"}
    return out


def pipeline_bias_of(twin_tracks: pd.DataFrame, twin_truth: pd.DataFrame, infer_kwargs: dict) -> dict:
    """What the pipeline does to D_xy and v_z, measured on a twin: (truth / tracks, relative error) each.

    Both tables go through :func:`infer_parameters` with the same settings (deposited rows dropped the
    same way), so the factors carry only what tracking and localisation change. Their errors are the two
    estimates' errors in quadrature (the truth and its tracks share the same particles, so this is
    conservative).
    """
    kw = dict(infer_kwargs)
    kw.pop("pipeline_bias", None)
    a = infer_parameters(twin_tracks, **kw)
    b = infer_parameters(twin_truth, **{**kw, "motion_blur": 0.0})
    out = {"D": (b["D"]["xy"] / a["D"]["xy"],
                 math.hypot(a["D_err"]["xy"] / a["D"]["xy"], b["D_err"]["xy"] / b["D"]["xy"]))}
    if a.get("drift") and b.get("drift") and "z" in a["drift"] and "z" in b["drift"]:
        va, vb = a["drift"]["z"], b["drift"]["z"]
        if abs(va["v"]) > 3 * va["v_err"] and abs(vb["v"]) > 3 * vb["v_err"]:
            out["v_z"] = (vb["v"] / va["v"], math.hypot(va["v_err"] / va["v"], vb["v_err"] / vb["v"]))
    return out


# --------------------------------------------------------------------------- scene and render settings
def build_scene(params: dict, shape, pixel_size: float, frame_interval: float, n_frames: int, *, density=None,
                fluid_density: float = 998.2, wall: bool = True, wall_hydrodynamics: bool = True,
                depth_of_field: float = 1e-6, height=None, seed: int = 1) -> tuple[dict, dict]:
    """The twin's scene (a :mod:`sim.scene` dict) and its view (where the camera looks in the box).

    The box is the field of view plus a margin of three RMS excursions of a
    particle over the movie (and at least a few particle diameters) on each
    side, with periodic sides: particles enter and leave the view as in the
    movie. 2D without a height: a slab of the depth of field between two
    reflecting planes, the focal plane in its middle (no wall correction);
    2D with a height: the substrate at z = 0, particles placed around the
    height; 3D: heights as measured, the substrate at z = 0 (the table's
    wall_z). The number of particles is the measured number per area of the
    view times the box area.
    """
    R = params["radius_m"]
    mu = params["viscosity_Pa_s"]
    T = params["temperature_K"]
    D0 = BOLTZMANN * T / (6 * math.pi * mu * R)
    duration = (n_frames - 1) * frame_interval
    H, W = shape
    margin = max(3 * math.sqrt(4 * D0 * duration), 6 * R, 10 * pixel_size)
    Lx, Ly = W * pixel_size + 2 * margin, H * pixel_size + 2 * margin
    n = max(int(round(params.get("number_density_per_m2", 0) * Lx * Ly)), 1)
    three_d = params["three_d"]
    focal = None
    if three_d:
        h = params["heights"]
        lo = max(h.get("start_lo", h["start_p05"]), 1.05 * R)
        hi = max(h.get("start_hi", h["start_p95"]), lo + R)
        Lz = max(h["z_max"], hi) + 2e-6
        placement = [lo, hi]
    elif height is not None:
        lo = max(height - depth_of_field / 2, 1.05 * R)
        placement = [lo, height + depth_of_field / 2]
        Lz = placement[1] + 2 * R
        focal = height
    else:
        Lz = depth_of_field + 2 * R
        placement = [R, Lz - R]
        focal = Lz / 2
    scene = {
        "seed": int(seed),
        "particles": {"count": n, "radius": R, "density": float(density) if density is not None else 1050.0},
        "fluid": {"viscosity": mu, "temperature": T, "density": fluid_density,
                  "relative_permittivity": params.get("relative_permittivity", 78.5)},
        "gravity": {"enabled": density is not None, "buoyancy": True},
        "domain": {"size": [Lx, Ly, Lz], "placement_z": placement},
        "boundaries": {"x": "periodic", "y": "periodic", "bottom_wall": True, "top": "wall"},
        "time": {"dt": frame_interval / 10, "final": duration, "output_interval": frame_interval},
        "integrator": {"kind": "overdamped",
                       "hindered_mobility": bool(wall_hydrodynamics and (three_d or height is not None) and wall)},
    }
    if params.get("zeta_V") is not None and params.get("field_V_m"):
        scene["particles"]["zeta_potential"] = params["zeta_V"]
        scene["fluid"]["debye_length"] = params["debye_length_m"]
        scene["fields"] = {"E": [0.0, 0.0, float(params["field_V_m"])]}
    view = {"origin_x": margin, "origin_y": margin, "shape": [int(H), int(W)], "pixel_size": pixel_size,
            "focal_plane": focal, "z_offset": params.get("wall_z_m", 0.0) if three_d else 0.0,
            "sticking": bool(params.get("zeta_V") is not None or density is not None) and three_d}
    return scene, view


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if v is None:
        raise UserError("a None value cannot be written to TOML", "internal: drop the key")
    raise UserError(f"cannot write {v!r} to TOML", "internal")


def to_toml(doc: dict, comments: dict | None = None, header: str = "") -> str:
    """A dict of sections (one level, as scene files are) as TOML text, with a comment per key where given."""
    comments = comments or {}
    lines = [f"# {ln}" for ln in header.splitlines()]
    top = {k: v for k, v in doc.items() if not isinstance(v, dict)}
    for k, v in top.items():
        lines.append(f"{k} = {_toml_value(v)}" + (f"    # {comments[k]}" if k in comments else ""))
    for sec, d in doc.items():
        if not isinstance(d, dict):
            continue
        lines.append("")
        lines.append(f"[{sec}]")
        for k, v in d.items():
            if v is None:
                continue
            c = comments.get(f"{sec}.{k}")
            lines.append(f"{k} = {_toml_value(v)}" + (f"    # {c}" if c else ""))
    return "\n".join(lines) + "\n"


def apply_overrides(scene: dict, render: dict, overrides) -> list[str]:
    """Apply ``KEY=VALUE`` overrides (TOML values) to the scene or render dicts; returns the keys set."""
    done = []
    for item in overrides or []:
        if "=" not in item:
            raise UserError(f"--set {item!r} is not KEY=VALUE", "e.g. --set particles.radius=3.25e-7")
        key, val = (s.strip() for s in item.split("=", 1))
        try:
            value = tomllib.loads(f"v = {val}")["v"]
        except tomllib.TOMLDecodeError:
            value = val
        parts = key.split(".")
        if len(parts) != 2:
            raise UserError(f"--set key {key!r} is not SECTION.KEY", "e.g. particles.radius, optics.na, camera.photons")
        sec, k = parts
        target = render if sec in ("optics", "camera", "view") else scene
        if sec not in target and target is render:
            raise UserError(f"--set section {sec!r} is unknown", "use a scene section, optics, camera or view")
        target.setdefault(sec, {})[k] = value
        done.append(key)
    return done


# --------------------------------------------------------------------------- interpretation
_MEANING = {
    "msd": "the mobility differs: radius, viscosity or temperature (D = kB T / (6 pi mu R)), or the wall hindrance "
           "(heights); at the first lags alone: localisation noise or motion blur",
    "D": "the mobility differs: radius, viscosity or temperature, or the particles' heights above the wall",
    "D_distribution": "the spread of mobilities differs: polydisperse sizes, agglomerates, or a spread of heights",
    "van_hove": "the step distributions differ: if D agrees, heavier tails mean heterogeneous sizes or agglomerates, "
                "or a mixture of moving and stuck particles",
    "alpha2": "non-Gaussian steps: heterogeneous sizes or agglomerates, stuck particles, or drift that varies",
    "drift": "the drift differs: the charge (zeta), the field, or sedimentation (density) is off, or a flow",
    "v_vs_height": "the drift changes with height differently: a field gradient or electro-osmotic flow near the "
                   "electrode",
    "height": "the heights differ: the starting heights, sedimentation or the deposition",
    "deposition": "the deposition rate differs: sticking is not perfect (the twin sticks on every contact), "
                  "or the drift towards the wall is off",
}


def interpret(measured_vs_twin: dict, twin_vs_truth: dict | None) -> list[str]:
    """One line per disagreement: what it most likely means (physics vs pipeline)."""
    lines = []
    mv = measured_vs_twin["quantities"]
    tt = twin_vs_truth["quantities"] if twin_vs_truth else {}
    differs = [k for k, r in mv.items() if r["verdict"] == "differs"]
    kinds = {mv[k]["quantity"] for k in differs}
    for q in dict.fromkeys(mv[k]["quantity"] for k in differs):
        keys = [k for k in differs if mv[k]["quantity"] == q]
        pipe = [k for k in keys if tt.get(k, {}).get("verdict") == "differs"]
        txt = f"{q} ({', '.join(keys)}): {_MEANING.get(q, 'differs')}"
        if q in ("van_hove", "alpha2") and not kinds & {"D", "msd"}:
            txt += " (D agrees, so the shape, not the scale, differs)"
        if pipe:
            txt += (f"; the twin's own tracks also differ from its truth on {', '.join(pipe)}, so the pipeline "
                    "shapes this quantity too")
        lines.append(txt)
    if not differs:
        lines.append("no disagreement between the movie and its twin at the stated level")
    bad_pipe = [k for k, r in tt.items() if r["verdict"] == "differs"]
    if bad_pipe:
        lines.append("pipeline (twin tracks vs twin truth) differs on " + ", ".join(bad_pipe)
                     + ": tracking/localisation biases these quantities, independently of the physics")
    return lines


# --------------------------------------------------------------------------- the whole chain
def _stick(sim: pd.DataFrame, R: float, z_offset: float, tol: float) -> pd.DataFrame:
    """Perfect sticking: from a particle's first contact with the wall on, it stays where it touched down.

    The free-particle engine reflects at the substrate; the EPD physics of the seed (and the shipped EPD
    movie) has particles stick on contact, so the positions after the first contact are frozen here and
    the column ``deposited`` marks them.
    """
    sim = sim.sort_values(["particle", "frame"]).reset_index(drop=True)
    z = sim["z"].to_numpy()
    touch = z - z_offset <= R + tol
    p = sim["particle"].to_numpy()
    first = pd.Series(np.where(touch, sim["frame"].to_numpy(), np.iinfo(np.int64).max)).groupby(p).transform("min")
    dep = sim["frame"].to_numpy() >= first.to_numpy()
    idx0 = pd.Series(np.where(touch, np.arange(len(sim)), len(sim))).groupby(p).transform("min").to_numpy()
    for c in ("x", "y"):
        v = sim[c].to_numpy().copy()
        v[dep] = v[idx0[dep]]
        sim[c] = v
    zz = z.copy()
    zz[dep] = z_offset + R
    sim["z"] = zz
    sim["deposited"] = dep
    return sim


def _render_objects(render: dict):
    from sim.render import Camera, Optics

    return Optics(**render["optics"]), Camera(**render["camera"])


def run_twin(movie, out_dir, track_kwargs: dict, temperature: float, viscosity: float, radius=None, field=None,
             density=None, fluid_density: float = 998.2, height=None, wall_z: float = 0.0,
             wall: bool = True, wall_hydrodynamics: bool = True, debye_length: float = 100e-9, permittivity: float = 78.5,
             optics: dict | None = None, camera: dict | None = None, focal_plane=None, overrides=None,
             seed: int = 1, n_boot: int = 200, n_perm: int = 2000, level: float = 0.05, progress: bool = False,
             measured_table: pd.DataFrame | None = None, calibrate: int = 0) -> dict:
    """Movie -> inferred parameters -> scene -> simulate -> render -> track -> compare -> report.

    Parameters
    ----------
    movie : path-like
    out_dir : path-like
        Receives ``measured.parquet``, ``scene.toml``, ``render.toml``,
        ``sim/`` (engine output), ``twin/`` (rendered movie, truth),
        ``twin_tracks.parquet``, ``twin.json`` and ``report.html``.
    track_kwargs : dict
        Settings of :func:`ptrack.pipeline.track_movie` (used for the movie and its twin).
    temperature, viscosity, radius, field, density, fluid_density, height, wall_z, wall_hydrodynamics,
    debye_length, permittivity
        As :func:`infer_parameters` (SI).
    optics, camera : dict
        :class:`sim.render.Optics` / :class:`sim.render.Camera` fields (camera photons, background and read
        noise are measured on the movie unless given here).
    focal_plane : float, optional
        Focal plane in the table's z coordinates, m (3D; default: ``focal_plane`` of the calibration's
        ``calib_params.json`` if present, else 0).
    overrides : list of "KEY=VALUE"
        Applied after inference (``particles.radius=3.25e-7``, ``camera.photons=2000``...).
    seed : int
        Simulation and rendering seed.
    calibrate : int
        Rounds of pipeline calibration: make a twin, measure what tracking does to D and v_z on it (its
        truth against its tracks, :func:`pipeline_bias_of`), correct the measured values by that, and
        make the twin again (0: none).
    """
    from sim.render import render_movie
    from sim.run import run_scene
    from sim.scene import scene_from_dict

    from .compare import compare_tables, comparison_html, format_table, plot_comparison
    from .motion import frame_interval
    from .pipeline import track_movie
    from .table import metadata, read_table, write_table

    t0 = time.perf_counter()
    timings = {}
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory", "give a directory")
    out.mkdir(parents=True, exist_ok=True)
    # 1. track
    if measured_table is None:
        measured, tsum = track_movie(movie, out=out / "measured.parquet", progress=progress, **track_kwargs)
    else:
        measured, tsum = measured_table, {}
    timings["track_movie_s"] = time.perf_counter() - t0
    meta = metadata(measured)
    px, dt = float(meta["pixel_size"]), frame_interval(measured)       # the one frame-interval rule
    shape = meta.get("frame_shape")
    n_frames = int(meta.get("n_frames") or measured["frame"].max() + 1)
    three_d = "z" in default_axes(measured)   # the one rule of a 3D table (ptrack.motion.velocity.default_axes)
    brightfield = bool(track_kwargs.get("brightfield"))
    if three_d and not wall:
        # no substrate near the particles (e.g. a movie around focus in the bulk): the twin's box floor is
        # put 1 um below the lowest measured height, a reflecting plane without hindrance
        wall_z = float(np.nanmin(measured["z"].to_numpy(float))) - 1e-6
        wall_hydrodynamics = False
    # 2. infer
    t1 = time.perf_counter()
    params = infer_parameters(measured, temperature, viscosity, radius=radius, height=height, wall_z=wall_z,
                              wall_hydrodynamics=wall_hydrodynamics, field=field, density=density,
                              fluid_density=fluid_density, debye_length=debye_length, permittivity=permittivity,
                              motion_blur=0.0, n_boot=n_boot, seed=seed)
    notes0 = params["notes"]
    from sim.render import Camera, Optics

    opt = {**Optics().to_dict(), **(optics or {})}
    if "magnification" not in (optics or {}):
        cam_pitch = (camera or {}).get("pixel_pitch", Camera().pixel_pitch)
        opt["magnification"] = cam_pitch / px      # from the movie's pixel size
    cam = {**Camera().to_dict(), **(camera or {})}
    cam["gain"] = float(track_kwargs.get("gain") or cam["gain"])
    cam["offset"] = float(track_kwargs.get("offset") if track_kwargs.get("offset") is not None else cam["offset"])
    box = int(meta.get("calib_template_px", 0) // 2) or int(math.ceil(4 * float(meta.get("sigma_px", 2.0)))) + 2
    camm = measure_camera(movie, measured, brightfield, cam["gain"], cam["offset"], cam["quantum_efficiency"], box)
    for k_cam, k_meas in (("background", "background_photons"), ("photons", "photons"), ("read_noise", "read_noise_e")):
        if k_cam not in (camera or {}) and math.isfinite(camm[k_meas]):
            cam[k_cam] = float(camm[k_meas])
    exposure, blur, substeps = twin_exposure(params.get("motion_blur"), dt)
    if exposure is not None:
        cam["exposure"] = exposure
    params["camera_measured"] = camm
    dof = opt["wavelength"] * opt["medium_index"] / opt["na"] ** 2
    sigma_model = 0.21 * opt["wavelength"] / opt["na"]
    params["spot"] = {"sigma_px_measured": meta.get("sigma_px"), "sigma_px_model_in_focus": sigma_model / px,
                      "depth_of_field_m": dof}
    if focal_plane is None and track_kwargs.get("calib"):
        cp = Path(track_kwargs["calib"]).with_name("calib_params.json")
        if cp.exists():
            focal_plane = float(json.loads(cp.read_text()).get("focal_plane", 0.0))
            params["notes"].append(f"focal plane {focal_plane:.3g} m from {cp}")
    timings["infer_s"] = time.perf_counter() - t1

    def make_twin(params):
        """Steps 3-6 for one set of parameters: scene, simulate, render, track."""
        # 3. scene and render settings
        scene, view = build_scene(params, shape, px, dt, n_frames, density=density, fluid_density=fluid_density,
                                  wall_hydrodynamics=wall_hydrodynamics, depth_of_field=dof, height=height, seed=seed)
        if three_d:
            view["focal_plane"] = (focal_plane or 0.0) - wall_z
        view.update({"brightfield": brightfield, "motion_blur_substeps": substeps, "render_seed": seed + 1})
        render = {"view": view, "optics": opt, "camera": {k: v for k, v in cam.items() if v is not None}}
        set_keys = apply_overrides(scene, render, overrides)
        sc = scene_from_dict(scene, source=str(out / "scene.toml"))
        header = (f"Simulated twin of {movie} (ptrack twin). SI units. Inferred from the movie's tracks: radius "
                  f"{params['radius_m']:.4g} m, viscosity {params['viscosity_Pa_s']:.4g} Pa s"
                  + (f", zeta {params['zeta_V']:.4g} V" if params.get("zeta_V") is not None else "")
                  + (f"\nOverridden (--set): {', '.join(set_keys)}" if set_keys else "")
                  + "\nRun alone with: ptrack simulate scene.toml")
        comments = {"particles.count": "measured particles per frame per view area x box area",
                    "particles.radius": "m, from D (Stokes-Einstein, wall-corrected)",
                    "particles.zeta_potential": "V, from the drift along z and E (Henry's exact function)",
                    "domain.size": "m: the view plus a margin on each side (periodic sides: particles enter and leave)",
                    "domain.placement_z": "m: measured starting heights (3D) or the depth of field (2D)",
                    "time.dt": "s: a tenth of the frame interval"}
        with atomic_output(out / "scene.toml", "w") as fh:
            fh.write(to_toml(scene, comments, header))
        with atomic_output(out / "render.toml", "w") as fh:
            fh.write(to_toml({k: {kk: vv for kk, vv in v.items() if vv is not None} for k, v in render.items()},
                             {}, "View, optics and camera of the twin (sim.render); measured on the movie where possible"))
        # 4. simulate
        t2 = time.perf_counter()
        runres = run_scene(sc, out / "sim", seed=seed, progress=progress)
        sim = read_table(runres.trajectories)
        timings["simulate_s"] = time.perf_counter() - t2
        R_sim = float(sc.particles.radius)
        if view.get("sticking"):
            D_sim = BOLTZMANN * sc.fluid.temperature / (6 * math.pi * sc.fluid.viscosity * R_sim)
            sim = _stick(sim, R_sim, 0.0, tol=max(0.02 * R_sim, math.sqrt(2 * D_sim * sc.time.dt or dt / 10)))
        # 5. render (view coordinates: the box shifted so that the view starts at 0; z in the table's frame)
        t3 = time.perf_counter()
        tab = sim.copy()
        tab["x"] = tab["x"] - view["origin_x"]
        tab["y"] = tab["y"] - view["origin_y"]
        tab["z"] = tab["z"] + view["z_offset"]
        Hh, Ww = view["shape"]
        pad = 30 * px
        keep = (tab["x"] > -pad) & (tab["x"] < Ww * px + pad) & (tab["y"] > -pad) & (tab["y"] < Hh * px + pad)
        tab = tab[keep].drop(columns=[c for c in ("vx", "vy", "vz") if c in tab.columns])
        tab.attrs["ptrack"] = {"frame_interval": dt, "pixel_size": px, "source": "ptrack twin simulation"}
        optics_o, camera_o = _render_objects(render)
        fp = view["focal_plane"] + (view["z_offset"] if three_d else 0.0)
        paths = render_movie(tab, out / "twin", (Hh, Ww), optics_o, camera_o, focal_plane=fp,
                             brightfield=view["brightfield"], motion_blur_substeps=int(view["motion_blur_substeps"]),
                             seed=int(view["render_seed"]), compression="zlib", progress=progress)
        timings["render_s"] = time.perf_counter() - t3
        # 6. track the twin with the same settings, compare
        t4 = time.perf_counter()
        twin_tracks, _ = track_movie(paths["movie"], out=out / "twin_tracks.parquet", progress=progress, **track_kwargs)
        timings["track_twin_s"] = time.perf_counter() - t4
        truth = read_table(paths["truth"])
        truth = truth[truth["in_frame"].astype(bool)].copy()
        if not three_d:
            truth["z"] = np.nan
        return sc, scene, render, set_keys, paths, twin_tracks, truth, R_sim

    infer_kw = dict(temperature=temperature, viscosity=viscosity, radius=radius, height=height, wall_z=wall_z,
                    wall_hydrodynamics=wall_hydrodynamics, field=field, density=density, fluid_density=fluid_density,
                    debye_length=debye_length, permittivity=permittivity, motion_blur=0.0, n_boot=n_boot, seed=seed)
    history = []
    for it in range(int(calibrate) + 1):
        sc, scene, render, set_keys, paths, twin_tracks, truth, R_sim = make_twin(params)
        if it == int(calibrate):
            break
        # the twin's truth and its tracks went through the same estimators: their ratio is what the pipeline
        # does to D and v_z; the measured values are corrected by it and the twin made again
        bias = pipeline_bias_of(twin_tracks, truth, infer_kw)
        keep = {k: params[k] for k in ("camera_measured", "spot") if k in params}
        history.append({"iteration": it + 1, "radius_m": params["radius_m"], "zeta_V": params.get("zeta_V"),
                        "bias": {k: list(v) for k, v in bias.items()}})
        params = infer_parameters(measured, **infer_kw, pipeline_bias=bias)
        params.update(keep)
        params["notes"] += [n for n in notes0 if n not in params["notes"]]
    params["calibration_history"] = history
    t5 = time.perf_counter()
    if render["view"].get("sticking"):
        # deposition compared like with like: the tracks' deposited rows found the same way (flag_stuck)
        # in the movie's and the twin's tracks; the truth has its own column
        sig = params.get("sigma_loc_xy_m") or 0.0
        measured = flag_stuck(measured, sig)
        twin_tracks = flag_stuck(twin_tracks, sig)
    cmp1 = compare_tables([measured, twin_tracks], ["measured", "twin"], n_boot=n_boot, n_perm=n_perm, level=level,
                          seed=seed, motion_blur=[blur, blur], field_of_view="auto")["comparisons"][0]
    cmp2 = compare_tables([twin_tracks, truth], ["twin tracks", "twin truth"], n_boot=n_boot, n_perm=n_perm,
                          level=level, seed=seed + 1, motion_blur=[blur, 0.0], field_of_view="auto")["comparisons"][0]
    timings["compare_s"] = time.perf_counter() - t5
    meaning = interpret(cmp1, cmp2)
    # 7. report
    t6 = time.perf_counter()
    figs1 = plot_comparison(cmp1, out / "figures_measured_vs_twin")
    figs2 = plot_comparison(cmp2, out / "figures_twin_vs_truth")
    timings["report_s"] = time.perf_counter() - t6
    timings["total_s"] = time.perf_counter() - t0
    result = {
        "movie": str(movie), "out": str(out),
        "radius_m": params["radius_m"], "radius_err_m": params["radius_err_m"],
        "viscosity_Pa_s": params["viscosity_Pa_s"], "viscosity_err_Pa_s": params["viscosity_err_Pa_s"],
        "zeta_V": params["zeta_V"], "zeta_err_V": params["zeta_err_V"], "charge_C": params["charge_C"],
        "charge_err_C": params["charge_err_C"],
        "verdicts": cmp1["verdicts"], "verdicts_twin_vs_truth": cmp2["verdicts"],
        "all_consistent": cmp1["all_consistent"], "meaning": meaning, "overrides": set_keys,
        "parameters": params, "scene": scene, "render": render,
        "twin_radius_m": R_sim, "n_simulated": int(sc.particles.count),
        "calibration_history": params["calibration_history"],
        "measured_vs_twin": cmp1, "twin_vs_truth": cmp2, "timings_s": timings,
        "files": {"scene": str(out / "scene.toml"), "render": str(out / "render.toml"),
                  "twin_movie": str(paths["movie"]), "twin_truth": str(paths["truth"]),
                  "twin_tracks": str(out / "twin_tracks.parquet"), "report": str(out / "report.html")},
        "track_summary": tsum,
    }
    _write_report(result, cmp1, cmp2, figs1, figs2, out / "report.html", comparison_html, format_table)
    return result


def _fmt_pm(v, e, scale=1.0, unit=""):
    if v is None:
        return "-"
    return f"{v * scale:.4g}" + (f" &plusmn; {e * scale:.2g}" if e is not None else "") + (f" {unit}" if unit else "")


def headline_rows(result: dict) -> list[tuple[str, str]]:
    """The inferred parameters as (name, value with error) rows (HTML entities allowed)."""
    p = result["parameters"]
    rows = [("radius", _fmt_pm(result["radius_m"], result["radius_err_m"], 1e9, "nm")),
            ("viscosity", _fmt_pm(result["viscosity_Pa_s"], result["viscosity_err_Pa_s"], 1e3, "mPa s")),
            ("D_xy (measured)", _fmt_pm(p["D"]["xy"], p["D_err"]["xy"], 1e12, "µm²/s")),
            ("wall ratio D/D0", f"{p['wall_ratio']:.4g}")]
    if p.get("drift"):
        for c, d in p["drift"].items():
            rows.append((f"drift v{c}", _fmt_pm(d["v"], d["v_err"], 1e6, "µm/s")))
    if result.get("zeta_V") is not None:
        rows += [("zeta potential", _fmt_pm(result["zeta_V"], result["zeta_err_V"], 1e3, "mV")),
                 ("charge", _fmt_pm(result["charge_C"], result["charge_err_C"], 1 / 1.602176634e-19, "e")),
                 ("Henry f(R/lambda_D)", f"{p['henry_f']:.4f}")]
    if p.get("number_density_per_m2"):
        rows.append(("number density", f"{p['number_density_per_m2'] * 1e-12:.4g} per µm² "
                                       f"({p['particles_per_frame']:.3g} per frame)"))
    if p.get("heights"):
        h = p["heights"]
        rows.append(("start heights (uniform range)", f"{h['start_lo'] * 1e6:.3g} - {h['start_hi'] * 1e6:.3g} µm"))
    c = p["camera_measured"]
    rows += [("background", f"{c['background_photons']:.4g} photons/px"),
             ("photons per particle", f"{c['photons']:.4g} (IQR {c['photons_iqr']:.3g})"),
             ("read noise (from the data)", f"{c['read_noise_e']:.3g} e-"),
             ("spot sigma", f"{p['spot']['sigma_px_measured'] or float('nan'):.3g} px measured, "
                            f"{p['spot']['sigma_px_model_in_focus']:.3g} px model in focus")]
    if p.get("motion_blur"):
        m = p["motion_blur"]
        rows.append(("motion blur R", f"{m['R']:.3g} &plusmn; {m['R_err']:.2g}"))
    rows.append(("twin radius used", f"{result['twin_radius_m'] * 1e9:.4g} nm"
                 + (f" (--set {', '.join(result['overrides'])})" if result["overrides"] else "")))
    return rows


def _write_report(result, cmp1, cmp2, figs1, figs2, path, comparison_html, format_table):
    import html as H

    from .compare import _CSS

    rows = "".join(f"<tr><td>{n}</td><td>{v}</td></tr>" for n, v in headline_rows(result))
    mean = "".join(f"<li>{H.escape(m)}</li>" for m in result["meaning"])
    tm = ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in result["timings_s"].items())
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>ptrack twin</title><style>{_CSS}</style>"
           f"</head><body><h1>Simulated twin of {H.escape(result['movie'])}</h1>"
           f"<h2>Inferred parameters</h2><table><tr><th>parameter</th><th>value &plusmn; standard error</th></tr>{rows}"
           f"</table><h2>What the disagreements most likely mean</h2><ul>{mean}</ul>"
           + comparison_html(cmp1, figs1, "measured tracks vs twin tracks (both through the pipeline)")
           + comparison_html(cmp2, figs2, "twin tracks vs twin truth (what the pipeline does)")
           + f"<p class='small'>Timings: {H.escape(tm)}. Files: scene.toml, render.toml, twin/movie.tif, "
             f"twin.json.</p></body></html>")
    with atomic_output(path, "w") as fh:
        fh.write(doc)
