"""Mean squared displacement tables: per particle and over the ensemble, gaps allowed; array fast paths.

The numba kernels work on ragged, dense-in-time arrays:
``vals[k, off[p] + (frame - first_frame[p])]`` holds component k of particle
p, NaN where the particle is missing (gaps).
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from numba import njit

from ..errors import UserError
from .fov import fov_arrays, fov_weight, resolve_fov
from .tracks import AXES, DEFAULT_MAX_LAG, Tracks, axis_components, parse_axes, prepare_tracks


@njit(cache=True)
def msd_sums_ragged(vals, off, max_lag):
    """Sum of squared displacements (summed over components) and counts per particle and lag."""
    n_p = off.shape[0] - 1
    k_c = vals.shape[0]
    sums = np.zeros((n_p, max_lag))
    cnts = np.zeros((n_p, max_lag))
    for p in range(n_p):
        a = off[p]
        b = off[p + 1]
        span = b - a
        for lag in range(1, min(max_lag, span - 1) + 1):
            s = 0.0
            c = 0.0
            for i in range(a, b - lag):
                d2 = 0.0
                ok = True
                for k in range(k_c):
                    d = vals[k, i + lag] - vals[k, i]
                    if d != d:
                        ok = False
                        break
                    d2 += d * d
                if ok:
                    s += d2
                    c += 1.0
            sums[p, lag - 1] = s
            cnts[p, lag - 1] = c
    return sums, cnts


@njit(cache=True)
def msd_sums_multi(vals, off, max_lag, fov, flen):
    """Per-component sums of squared displacements (n_p, max_lag, k) and counts (n_p, max_lag).

    A displacement counts where every component is finite at both ends. With
    a field of view (``fov``: the limited coordinates, ``flen``: their
    extents; empty for none) each displacement is weighted by
    :func:`fov_weight` of the range the track covered from start to end.
    """
    n_p = off.shape[0] - 1
    k_c = vals.shape[0]
    n_f = fov.shape[0]
    sums = np.zeros((n_p, max_lag, k_c))
    cnts = np.zeros((n_p, max_lag))
    mn = np.empty(n_f)
    mx = np.empty(n_f)
    for p in range(n_p):
        a = off[p]
        b = off[p + 1]
        # start-major order: for each lag the displacements still arrive with increasing start
        for i in range(a, b - 1):
            ok0 = True
            for k in range(k_c):
                if vals[k, i] != vals[k, i]:
                    ok0 = False
            if not ok0:
                continue
            for f in range(n_f):
                mn[f] = fov[f, i]
                mx[f] = fov[f, i]
            for lag in range(1, min(max_lag, b - 1 - i) + 1):
                j = i + lag
                for f in range(n_f):
                    v = fov[f, j]
                    if v == v:
                        if v < mn[f]:
                            mn[f] = v
                        if v > mx[f]:
                            mx[f] = v
                ok = True
                for k in range(k_c):
                    if vals[k, j] != vals[k, j]:
                        ok = False
                        break
                if not ok:
                    continue
                w = 1.0
                for f in range(n_f):
                    w *= fov_weight(mx[f] - mn[f], flen[f])
                for k in range(k_c):
                    d = vals[k, j] - vals[k, i]
                    sums[p, lag - 1, k] += w * d * d
                cnts[p, lag - 1] += w
    return sums, cnts


@njit(cache=True)
def msd_dense(pos, max_lag):
    """pos (n_p, n_f, k) without gaps -> time-averaged MSD (n_p, max_lag) summed over k."""
    n_p, n_f, k_c = pos.shape
    out = np.zeros((n_p, max_lag))
    for p in range(n_p):
        for lag in range(1, max_lag + 1):
            s = 0.0
            for i in range(n_f - lag):
                for k in range(k_c):
                    d = pos[p, i + lag, k] - pos[p, i, k]
                    s += d * d
            out[p, lag - 1] = s / (n_f - lag)
    return out


def default_max_lag(tr: Tracks, max_lag):
    longest = int(np.diff(tr.off).max()) - 1
    if max_lag is None:
        return max(1, min(DEFAULT_MAX_LAG, longest))
    max_lag = int(max_lag)
    if max_lag < 1:
        raise UserError(f"max_lag = {max_lag} must be at least 1 frame", "give a positive number of frames")
    return max(1, min(max_lag, longest))


def msd_sums(tr: Tracks, axes, max_lag, fov=None):
    """axis -> (sums (n_p, L), counts (n_p, L)), weighted for the field of view ``fov`` (:func:`fov_arrays`).

    One pass over all components when they share their missing values (the
    usual case: a row has x and y, and z if any); else one pass per axis.
    """
    comps = axis_components(axes)
    fv, fl = fov if fov is not None else fov_arrays(tr, {})
    nan0 = np.isnan(tr.comps[comps[0]])
    if all(np.array_equal(nan0, np.isnan(tr.comps[c])) for c in comps[1:]):
        sums, cnts = msd_sums_multi(tr.stack(comps), tr.off, int(max_lag), fv, fl)
        ci = {c: i for i, c in enumerate(comps)}
        return {a: (sums[:, :, [ci[c] for c in AXES[a]]].sum(axis=2), cnts) for a in axes}
    res = {}
    for a in axes:
        sums, cnts = msd_sums_multi(tr.stack(AXES[a]), tr.off, int(max_lag), fv, fl)
        res[a] = (sums.sum(axis=2), cnts)
    return res


def lag_sums(df: pd.DataFrame, axes, max_lag, field_of_view=None):
    """Parse ``axes``, prepare the tracks, resolve ``max_lag`` and sum the squared displacements.

    Returns (axes, tracks, L, {axis: (sums (n_p, L), counts (n_p, L))}): the common start of
    :func:`particle_msd` and :func:`ensemble_msd`.
    """
    axes = parse_axes(axes)
    fov = resolve_fov(df, field_of_view)
    comps = axis_components(axes)
    tr = prepare_tracks(df, tuple(dict.fromkeys(comps + tuple(fov))))
    L = default_max_lag(tr, max_lag)
    return axes, tr, L, msd_sums(tr, axes, L, fov_arrays(tr, fov))


def particle_msd(df: pd.DataFrame, axes=("x", "y", "xy"), max_lag=None) -> pd.DataFrame:
    """Time-averaged MSD of each particle.

    Parameters
    ----------
    df : DataFrame
        Trajectories table (gaps allowed).
    axes : sequence of str
        Any of ``x, y, z, xy, xz, yz, xyz``.
    max_lag : int, optional
        Longest lag in frames (default: min(100, longest track - 1)).

    Returns
    -------
    DataFrame
        Columns ``particle``, ``lag`` (frames), ``t`` (s), ``msd_<axis>`` (m^2)
        and ``n_<axis>`` (displacements averaged). Rows with no displacement
        are dropped.
    """
    axes, tr, L, sums = lag_sums(df, axes, max_lag)
    n_p = len(tr.particles)
    out = {"particle": np.repeat(tr.particles, L), "lag": np.tile(np.arange(1, L + 1), n_p)}
    out["t"] = out["lag"] * tr.dt
    anyc = np.zeros(n_p * L, dtype=bool)
    for a in axes:
        s, c = sums[a]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[f"msd_{a}"] = (s / c).ravel()
        out[f"n_{a}"] = c.ravel().astype(np.int64)
        anyc |= c.ravel() > 0
    res = pd.DataFrame(out)[anyc].reset_index(drop=True)
    res.attrs["frame_interval"] = tr.dt
    return res


def ensemble_from_sums(sums, axes, dt, L):
    out = {"lag": np.arange(1, L + 1)}
    out["t"] = out["lag"] * dt
    for a in axes:
        s, c = sums[a]
        S = s.sum(axis=0)
        C = c.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(C > 0, S / np.maximum(C, 1), np.nan)
            # standard error over whole particles (delta method for the ratio
            # sum(s_p)/sum(c_p), the closed form of a particle bootstrap)
            m = (c > 0).sum(axis=0)
            se = np.sqrt(m / np.maximum(m - 1, 1) * ((s - r * c) ** 2).sum(axis=0)) / C
            se = np.where(m >= 2, se, np.nan)
        out[f"msd_{a}"] = r
        out[f"n_{a}"] = C.astype(np.int64)
        out[f"se_{a}"] = se
    return pd.DataFrame(out)


def ensemble_msd(df: pd.DataFrame, axes=("x", "y", "xy"), max_lag=None, field_of_view=None) -> pd.DataFrame:
    """Ensemble MSD: average over all particles and all start times.

    Each displacement counts once (a long track weighs more than a short one).
    ``msd_xy`` is ``<dx^2 + dy^2>`` (= 4 D t for free diffusion).

    Parameters
    ----------
    df : DataFrame
        Trajectories table (gaps allowed).
    axes : sequence of str
        Any of ``x, y, z, xy, xz, yz, xyz``.
    max_lag : int, optional
        Longest lag in frames (default: min(100, longest track - 1)).
    field_of_view : None, "auto" or dict
        Correct the loss of long displacements at the edges of the field
        (see :func:`estimate_diffusion`).

    Returns
    -------
    DataFrame
        Columns ``lag`` (frames), ``t`` (s), ``msd_<axis>`` (m^2),
        ``n_<axis>`` (number of displacements), ``se_<axis>`` (m^2, standard
        error over whole particles; NaN with fewer than 2 particles).
    """
    axes, tr, L, sums = lag_sums(df, axes, max_lag, field_of_view)
    res = ensemble_from_sums(sums, axes, tr.dt, L)
    res.attrs["frame_interval"] = tr.dt
    return res


def as_pos3(pos) -> np.ndarray:
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim == 1:
        pos = pos[None, :, None]
    elif pos.ndim == 2:
        pos = pos[:, :, None]
    elif pos.ndim != 3:
        raise UserError(f"positions have shape {pos.shape}", "give (n_particles, n_frames) or (n_particles, n_frames, n_dims)")
    if not np.all(np.isfinite(pos)):
        raise UserError("positions contain NaN or infinite values", "the array fast paths take gap-free tracks; use a trajectories table for gaps")
    return np.ascontiguousarray(pos)


def msd_from_positions(pos, max_lag: int) -> np.ndarray:
    """Time-averaged MSD of gap-free tracks (numba).

    Parameters
    ----------
    pos : ndarray
        ``(n_particles, n_frames)`` one coordinate, or
        ``(n_particles, n_frames, n_dims)`` (squared displacements summed over
        the dims), m.
    max_lag : int
        Longest lag, frames (at most n_frames - 1).

    Returns
    -------
    ndarray
        ``(n_particles, max_lag)`` MSD at lags 1..max_lag, m^2. The ensemble
        MSD of equal-length tracks is the mean over axis 0.
    """
    p = as_pos3(pos)
    L = int(max_lag)
    if not 1 <= L <= p.shape[1] - 1:
        raise UserError(f"max_lag = {max_lag} outside 1..{p.shape[1] - 1}", "tracks need more frames than the longest lag")
    return msd_dense(p, L)

