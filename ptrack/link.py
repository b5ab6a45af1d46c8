"""Linking localisations into trajectories (trackpy) and drift removal.

:func:`link` wraps ``trackpy.link`` on pixel coordinates. The search range
is estimated from the data when not given (trackpy makes every user guess
it): a first pass with a range set by the typical nearest-neighbour distance,
then up to four more with 5 robust standard deviations of the measured
per-axis step (or 1.5x its 99th percentile if larger: a few drifting particles
among stuck ones) plus 1 px, at least 3 px, at most 80 px. It is not capped
by the particle spacing: that would cut off the longest steps and bias D
low; where particles are dense, trackpy's adaptive search shrinks the range
only in the subnetworks that need it. In 3D the
z axis gets its own search range: it carries the z step and the (larger) z
uncertainty, so z is scaled by its uncertainty rather than mixed in with the
lateral pixels.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from .errors import UserError

__all__ = ["nearest_neighbour_distance", "link", "filter_short", "to_trajectories",
           "from_trackpy", "to_trackpy"]


def nearest_neighbour_distance(features: pd.DataFrame, n_frames: int = 10) -> float:
    """Median distance (px) from each localisation to its nearest neighbour in the same frame (inf if alone)."""
    from scipy.spatial import cKDTree

    frames = np.unique(features["frame"].to_numpy())
    frames = frames[np.linspace(0, len(frames) - 1, min(n_frames, len(frames))).astype(int)] if len(frames) else frames
    d = []
    for f in frames:
        pts = features.loc[features["frame"] == f, ["x_px", "y_px"]].to_numpy()
        if len(pts) > 1:
            dd, _ = cKDTree(pts).query(pts, k=2)
            d.append(dd[:, 1])
    return float(np.median(np.concatenate(d))) if d else float("inf")


def _trackpy_link(features, search_range, memory, pos_columns):
    import trackpy

    trackpy.quiet()
    try:
        return trackpy.link(features, search_range, memory=memory, pos_columns=list(pos_columns), t_column="frame",
                            adaptive_stop=0.3, adaptive_step=0.8)
    except Exception as exc:  # SubnetOversize etc.
        raise UserError(f"linking failed with search range {search_range}: {type(exc).__name__}: {exc}",
                        "give a smaller --search-range (px) or reduce the particle density") from None


def link(features: pd.DataFrame, search_range: float | None = None, memory: int = 3, pixel_size: float | None = None,
         z_search_range: float | None = None) -> pd.DataFrame:
    """Link per-frame localisations into trajectories.

    Parameters
    ----------
    features : DataFrame
        Columns ``frame``, ``x_px``, ``y_px`` (px) and optionally ``z`` (m)
        and ``sigma_x_px`` (px).
    search_range : float, optional
        Largest lateral displacement between frames (px); estimated if None.
    memory : int
        Frames a particle may vanish (blink, leave focus) and keep its id.
    pixel_size : float, optional
        m per px (needed for 3D linking).
    z_search_range : float, optional
        Largest z displacement between frames (m); estimated if None.

    Returns
    -------
    DataFrame
        ``features`` with an integer ``particle`` column; ``attrs['link']``
        records the search ranges used.
    """
    if len(features) == 0:
        out = features.assign(particle=np.zeros(0, np.int64))
        out.attrs["link"] = {"search_range_px": search_range}
        return out
    feats = features.reset_index(drop=True).copy()
    three_d = "z" in feats.columns and np.isfinite(feats["z"].to_numpy()).any()
    if three_d:
        if pixel_size is None:
            raise UserError("3D linking needs the pixel size", "give --pixel-size")
        feats = feats[np.isfinite(feats["z"].to_numpy())].reset_index(drop=True)
        feats["z_px"] = feats["z"] / pixel_size
    nn = nearest_neighbour_distance(feats)
    # The refined range is NOT capped by the particle spacing: a range shorter than the longest
    # steps drops exactly those steps and biases D low (in 2D the steps beyond 2.5 step standard
    # deviations carry 18 % of the MSD); trackpy's adaptive search shrinks the range only inside
    # the subnetworks that would otherwise be too large.
    cap = 80.0
    sr = float(search_range) if search_range is not None else min(max(0.45 * nn, 5.0), 50.0)
    pos = ["y_px", "x_px"]
    rng_ = (sr, sr)
    if three_d:
        zsr = z_search_range / pixel_size if z_search_range is not None else max(4.0 * sr, 1.0)
        pos = ["z_px", "y_px", "x_px"]
        rng_ = (zsr, sr, sr)
    linked = _trackpy_link(feats, rng_, memory, pos)
    # refine (a few rounds): 5 robust standard deviations of the measured steps per axis, +1 px
    # for localisation error, capped by the nearest-neighbour distance; a range cut short by
    # the first guess under-estimates the steps, so repeat until the range stops growing.
    for _ in range(4):
        if search_range is not None and (not three_d or z_search_range is not None):
            break
        lk = linked.sort_values(["particle", "frame"])
        same = lk["particle"].to_numpy()[1:] == lk["particle"].to_numpy()[:-1]
        step = (lk["frame"].to_numpy()[1:] - lk["frame"].to_numpy()[:-1])[same]
        if same.sum() < 10:
            break
        def robust(col):
            # 5 robust sigmas of the steps, or 1.5x their 99th percentile when a minority moves much
            # more than the rest (stuck and drifting particles in one movie)
            d = np.diff(lk[col].to_numpy())[same] / np.sqrt(step)
            return max(5.0 * 1.4826 * np.median(np.abs(d - np.median(d))), 1.5 * np.percentile(np.abs(d), 99))
        s = max(robust("x_px"), robust("y_px"))
        new_sr = float(np.clip(s + 1.0, 3.0, cap)) if search_range is None else sr
        new_rng = (new_sr, new_sr)
        if three_d:
            zsr = z_search_range / pixel_size if z_search_range is not None else float(max(robust("z_px") + 1.0, 2.0))
            new_rng = (zsr, new_sr, new_sr)
        if np.allclose(new_rng, rng_, rtol=0.05):
            break
        linked = _trackpy_link(feats, new_rng, memory, pos)
        rng_ = new_rng
    linked = linked.drop(columns=[c for c in ("z_px",) if c in linked.columns and c not in features.columns])
    linked["particle"] = linked["particle"].astype(np.int64)
    linked = linked.reset_index(drop=True)
    linked.attrs["link"] = {"search_range_px": float(rng_[-1]), "memory": int(memory)}
    if three_d:
        linked.attrs["link"]["z_search_range_m"] = float(rng_[0] * pixel_size)
    return linked


def filter_short(linked: pd.DataFrame, min_length: int = 5) -> pd.DataFrame:
    """Drop trajectories with fewer than ``min_length`` localisations."""
    n = linked.groupby("particle")["frame"].transform("size")
    out = linked[n.to_numpy() >= int(min_length)].reset_index(drop=True)
    out.attrs.update(linked.attrs)
    return out


def to_trajectories(linked: pd.DataFrame, pixel_size: float, frame_interval: float, meta: dict | None = None,
                    renumber: bool = True) -> pd.DataFrame:
    """Linked features in pixels -> the SI trajectories table (:mod:`ptrack.table`).

    The step after :func:`ptrack.locate.locate` + :func:`link` (or
    ``trackpy.batch`` + ``trackpy.link`` via :func:`from_trackpy`), so a
    notebook user gets the table ``ptrack track`` writes.

    Parameters
    ----------
    linked : DataFrame
        ``frame``, ``particle``, ``x_px``, ``y_px`` (px) and optionally ``z``
        (m) and the localiser's columns (``mass``, ``size``, ``ecc``,
        ``signal``, ``sigma_x_px``, ``sigma_y_px``; ``cm``, ``chi2``, ``edge``
        in 3D).
    pixel_size : float
        m per px in the sample plane.
    frame_interval : float
        s per frame.
    meta : dict, optional
        Extra metadata (``pixel_size`` and ``frame_interval`` are set here).
    renumber : bool
        Particles numbered 0..n-1 by first appearance, ties by position
        (trackpy's own ids depend on set iteration order).

    Returns
    -------
    DataFrame
        Trajectories table: ``frame``, ``t`` (s), ``particle``, ``x``, ``y``,
        ``z`` (m; NaN in 2D), ``x_px``, ``y_px`` and the optional columns,
        ``sigma_x``/``sigma_y`` in m.
    """
    from .errors import check_positive
    from .table import UNITS, make_table

    px = check_positive("pixel_size", pixel_size)
    dt = check_positive("frame_interval", frame_interval)
    missing = [c for c in ("frame", "particle", "x_px", "y_px") if c not in linked.columns]
    if missing:
        raise UserError(f"the feature table lacks the column(s) {missing}",
                        "give linked features with frame, particle, x_px, y_px (see ptrack.link.link)")
    linked = linked.reset_index(drop=True).copy()
    if renumber and len(linked):
        firsts = linked.sort_values(["frame", "y_px", "x_px"], kind="stable").drop_duplicates("particle")
        order = firsts["particle"].to_numpy()
        linked["particle"] = linked["particle"].map({p: i for i, p in enumerate(order)}).astype(np.int64)
    opt = {c: linked[c] for c in ("x_px", "y_px", "mass", "size", "ecc", "signal", "cm", "chi2") if c in linked}
    if "edge" in linked:
        opt["edge"] = linked["edge"].astype(bool)
    for c in ("x", "y"):
        if f"sigma_{c}_px" in linked:
            opt[f"sigma_{c}"] = linked[f"sigma_{c}_px"] * px
    z = linked["z"].to_numpy(float) if "z" in linked else None
    m = {"pixel_size": px, "frame_interval": dt, "units": {**UNITS, "size": "px", "mass": "ADU", "signal": "ADU",
                                                           "ecc": "1"}}
    m.update(meta or {})
    m["pixel_size"], m["frame_interval"] = px, dt
    frame = linked["frame"].to_numpy(np.int64)
    return make_table(frame, frame * dt, linked["particle"].to_numpy(np.int64), linked["x_px"].to_numpy(float) * px,
                      linked["y_px"].to_numpy(float) * px, z, meta=m, **opt)


def from_trackpy(features: pd.DataFrame, pixel_size: float, frame_interval: float,
                 z_column: str | None = None) -> pd.DataFrame:
    """A trackpy table (``x``, ``y`` in px, ``frame``, ``particle``) -> the SI trajectories table.

    trackpy's ``x``/``y`` are pixels; read as metres they give D ~ 10^12 times
    too large. This renames them to ``x_px``/``y_px`` and scales by
    ``pixel_size`` (:func:`to_trajectories`). ``z_column`` (m) is kept as z.
    """
    if not {"x", "y", "frame"} <= set(features.columns):
        raise UserError("the trackpy table lacks x, y or frame", "give trackpy.batch/link output (x, y in px)")
    f = features.rename(columns={"x": "x_px", "y": "y_px"}).reset_index(drop=True)
    if "particle" not in f:
        raise UserError("the trackpy table has no particle column", "link it first (trackpy.link)")
    if z_column is not None:
        f["z"] = f[z_column].astype(float)
    f = f.drop(columns=[c for c in ("z",) if c in f and z_column is None])
    return to_trajectories(f, pixel_size, frame_interval, meta={"tracker": "trackpy"})


def to_trackpy(table: pd.DataFrame, pixel_size: float | None = None) -> pd.DataFrame:
    """The SI trajectories table -> a trackpy table (``frame``, ``particle``, ``x``, ``y`` in px).

    The pixel size comes from the table's metadata unless given.
    """
    from .table import metadata

    px = pixel_size if pixel_size is not None else metadata(table).get("pixel_size")
    if not px:
        raise UserError("the table has no pixel size", "pass pixel_size= (m per px)")
    out = pd.DataFrame({"frame": table["frame"].to_numpy(np.int64), "particle": table["particle"].to_numpy(np.int64),
                        "x": table["x"].to_numpy(float) / px, "y": table["y"].to_numpy(float) / px})
    for c in ("mass", "size", "ecc", "signal"):
        if c in table:
            out[c] = table[c].to_numpy()
    return out
