"""Linking localisations into trajectories (trackpy) and drift removal.

:func:`link` links by ``trackpy.link``'s rules on pixel coordinates (computed by
:mod:`ptrack.linknb`, ``trackpy.link`` itself where that gives up). The search range
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

    # numpy only: a per-frame .loc on the table costs ~50 ms a frame once it holds string/categorical columns
    fr = features["frame"].to_numpy()
    x = features["x_px"].to_numpy(float)
    y = features["y_px"].to_numpy(float)
    frames = np.unique(fr)
    frames = frames[np.linspace(0, len(frames) - 1, min(n_frames, len(frames))).astype(int)] if len(frames) else frames
    d = []
    for f in frames:
        m = fr == f
        pts = np.c_[x[m], y[m]]
        if len(pts) > 1:
            dd, _ = cKDTree(pts).query(pts, k=2)
            d.append(dd[:, 1])
    return float(np.median(np.concatenate(d))) if d else float("inf")


#: trackpy's adaptive search as ptrack uses it: a subnetwork too large is split at 0.8x the range, until 0.3 px
ADAPTIVE_STOP = 0.3
ADAPTIVE_STEP = 0.8


def _trackpy_link(frames, positions, search_range, memory, pos_columns):
    """Trajectory ids (int64, aligned with the rows, which are in frame order) by trackpy's rules.

    ``frames``: each row's frame number; ``positions``: (n, d) float64, the columns ``pos_columns`` (px) in
    that order (the arrays once, not the table: each column read from a table costs ~10-30 us).

    The fast path is :func:`ptrack.linknb.link_ids` (numba; the same partition into trajectories as
    ``trackpy.link`` with ``adaptive_stop`` = :data:`ADAPTIVE_STOP`, ``adaptive_step`` =
    :data:`ADAPTIVE_STEP`: checked on the rendered and real movies of the benches and on random dense
    movies with memory, gaps, 3D ranges and adaptive splits, ~25x faster). ``trackpy.link`` itself runs only
    where the fast path gives up: a subnetwork still too large at ``adaptive_stop``, where trackpy raises
    (reported as a UserError). trackpy then gets a minimal copy of the table (frame + positions) with the
    garbage collector paused (its many small objects made Python's cyclic collector run passes of 19 to
    125 ms).
    """
    import gc

    from .linknb import link_ids

    pid = link_ids(frames, positions, search_range, memory, ADAPTIVE_STOP, ADAPTIVE_STEP)
    if pid is not None:
        return pid
    import trackpy

    trackpy.quiet()
    cols = ["frame", *pos_columns]
    small = pd.DataFrame(dict(zip(cols, (frames, *positions.T))))
    was = gc.isenabled()
    gc.disable()
    try:
        out = trackpy.link(small, search_range, memory=memory, pos_columns=list(pos_columns), t_column="frame",
                           adaptive_stop=ADAPTIVE_STOP, adaptive_step=ADAPTIVE_STEP)
    except Exception as exc:  # SubnetOversize etc.
        raise UserError(f"linking failed with search range {search_range}: {type(exc).__name__}: {exc}",
                        "give a smaller --search-range (px) or reduce the particle density") from None
    finally:
        if was:
            gc.enable()
    # trackpy keeps the index of the table it was given (0..n-1 here), possibly reordered
    pid = np.empty(len(small), np.int64)
    pid[out.index.to_numpy()] = out["particle"].to_numpy(np.int64)
    return pid


def _robust_step(d):
    """Range statistic of per-axis steps (px): 5 robust standard deviations, or 1.5x the 99th percentile of
    |step| when a minority moves much more than the rest (stuck and drifting particles in one movie).

    Computed by :func:`ptrack.linknb.robust_step` (numba: numpy's median and percentile to the bit, in one call
    instead of four numpy reductions); by numpy itself where a step is not finite."""
    from .linknb import robust_step

    d = np.ascontiguousarray(d, np.float64)
    if len(d) and np.isfinite(d).all():
        return float(robust_step(d))
    return max(5.0 * 1.4826 * np.median(np.abs(d - np.median(d))), 1.5 * np.percentile(np.abs(d), 99))


def _nn_steps(frames, x, y, max_pairs: int = 20000):
    """Per-axis steps (px) of mutual nearest neighbours between consecutive frames: a first look at the
    step distribution without a search range (no link); empty when there are too few. ``frames`` in frame
    order (:func:`link`'s table, sorted there).

    The pairs come from :func:`ptrack.linknb.nn_steps` (numba, exact nearest neighbours; two cKDTree queries
    per pair of frames cost ~0.1 ms each, mostly call overhead, more than the rest of a sparse frame's link).
    """
    from .linknb import nn_steps

    pts = np.column_stack((x, y)).astype(np.float64)
    ufr, start = np.unique(frames, return_index=True)
    end = np.r_[start[1:], len(frames)]
    follows = ufr[1:] == ufr[:-1] + 1
    dx, dy = nn_steps(pts, start.astype(np.int64), end.astype(np.int64), follows, int(max_pairs))
    if len(dx) < 10:
        return np.zeros(0), np.zeros(0)
    return dx, dy


#: Frames (from the start) on which the search range is estimated before the whole movie is linked once
#: (at least; more when they hold fewer than RANGE_MIN_FEATURES localisations)
RANGE_FRAMES = 20
RANGE_MIN_FEATURES = 2000


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
    # in frame order (as trackpy returns it), ties in their given order; one copy of the table (the caller's
    # is not changed), none more: a table from locate is already in frame order
    fr0 = features["frame"].to_numpy()
    if len(fr0) > 1 and not (fr0[1:] >= fr0[:-1]).all():
        feats = features.sort_values("frame", kind="stable").reset_index(drop=True)
    else:
        feats = features.reset_index(drop=True)
    three_d = "z" in feats.columns and np.isfinite(feats["z"].to_numpy()).any()
    if three_d:
        if pixel_size is None:
            raise UserError("3D linking needs the pixel size", "give --pixel-size")
        feats = feats[np.isfinite(feats["z"].to_numpy())].reset_index(drop=True)
    # the columns once, as arrays: frame, and the positions y, x (px) (and z / pixel size first in 3D)
    fr = feats["frame"].to_numpy()
    xy = np.column_stack([feats["y_px"].to_numpy(float), feats["x_px"].to_numpy(float)])
    # The refined range is NOT capped by the particle spacing: a range shorter than the longest
    # steps drops exactly those steps and biases D low (in 2D the steps beyond 2.5 step standard
    # deviations carry 18 % of the MSD); trackpy's adaptive search shrinks the range only inside
    # the subnetworks that would otherwise be too large.
    cap = 80.0
    sr = float(search_range) if search_range is not None else None
    if search_range is None:
        # first range from the steps of mutual nearest neighbours between consecutive frames (no range
        # needed): the refinement below then usually confirms it after one link instead of growing it
        # over several; without such steps, from the typical nearest-neighbour distance
        ndx, ndy = _nn_steps(fr, xy[:, 1], xy[:, 0])
        if len(ndx):
            sr = float(np.clip(max(_robust_step(ndx), _robust_step(ndy)) + 1.0, 3.0, cap))
        else:
            sr = min(max(0.45 * nearest_neighbour_distance(feats), 5.0), 50.0)
    pos = ["y_px", "x_px"]
    rng_ = (sr, sr)
    if three_d:
        zsr = z_search_range / pixel_size if z_search_range is not None else max(4.0 * sr, 1.0)
        pos = ["z_px", "y_px", "x_px"]
        rng_ = (zsr, sr, sr)
        xy = np.column_stack([feats["z"].to_numpy(float) / pixel_size, xy])
    # the search range is estimated on the first RANGE_FRAMES frames (more when they hold few
    # localisations), then the whole movie is linked once with it
    ufr = np.unique(fr)
    estimate = search_range is None or (three_d and z_search_range is None)
    fr_s, xy_s = fr, xy
    if estimate and len(ufr) > RANGE_FRAMES:
        counts = np.cumsum(np.bincount(np.searchsorted(ufr, fr), minlength=len(ufr)))
        n_est = max(RANGE_FRAMES, int(np.searchsorted(counts, RANGE_MIN_FEATURES)) + 1)
        if n_est < len(ufr):
            m = fr <= ufr[min(n_est, len(ufr)) - 1]
            fr_s, xy_s = fr[m], xy[m]
    pid = _trackpy_link(fr_s, xy_s, rng_, memory, pos)
    # refine (a few rounds): 5 robust standard deviations of the measured steps per axis, +1 px
    # for localisation error; a range cut short by the first guess under-estimates the steps, so
    # repeat until the range stops growing.
    for _ in range(4):
        if not estimate:
            break
        order = np.lexsort((fr_s, pid))
        p_s = pid[order]
        f_s = fr_s[order]
        same = p_s[1:] == p_s[:-1]
        step = (f_s[1:] - f_s[:-1])[same]
        if same.sum() < 10:
            break

        def robust(col):
            return _robust_step(np.diff(xy_s[:, pos.index(col)][order])[same] / np.sqrt(step))
        s = max(robust("x_px"), robust("y_px"))
        new_sr = float(np.clip(s + 1.0, 3.0, cap)) if search_range is None else sr
        new_rng = (new_sr, new_sr)
        if three_d:
            zsr = z_search_range / pixel_size if z_search_range is not None else float(max(robust("z_px") + 1.0, 2.0))
            new_rng = (zsr, new_sr, new_sr)
        # (np.allclose's rule, |new - old| <= 1e-8 + 0.05 |old| on every axis, without its overhead)
        if all(abs(a - b) <= 1e-8 + 0.05 * abs(b) for a, b in zip(new_rng, rng_)):
            break
        pid = _trackpy_link(fr_s, xy_s, new_rng, memory, pos)
        rng_ = new_rng
    if len(fr_s) < len(fr):
        pid = _trackpy_link(fr, xy, rng_, memory, pos)
    linked = feats
    linked["particle"] = pid
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
