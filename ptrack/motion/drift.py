"""Common drift of the ensemble, and its subtraction with the (1 - 1/M) bias correction."""
from __future__ import annotations

import numpy as np
import pandas as pd
from numba import njit

from ..errors import UserError
from .tracks import Tracks, axis_components, parse_axes, prepare_tracks


@njit(cache=True)
def _rebuild_scaled(vals, off, first, scale):
    """Rebuild tracks from increments, the increment f -> f+1 multiplied by scale[f].

    Increments across gaps are kept unscaled.
    """
    out = np.empty_like(vals)
    n_p = off.shape[0] - 1
    for k in range(vals.shape[0]):
        for p in range(n_p):
            a = off[p]
            b = off[p + 1]
            last_orig = np.nan
            last_new = np.nan
            prev_present = False
            for i in range(a, b):
                v = vals[k, i]
                if v != v:
                    out[k, i] = np.nan
                    prev_present = False
                    continue
                if last_orig != last_orig:
                    out[k, i] = v
                elif prev_present:
                    f = first[p] + (i - 1 - a)
                    out[k, i] = last_new + scale[f] * (v - last_orig)
                else:
                    out[k, i] = last_new + (v - last_orig)
                last_orig = v
                last_new = out[k, i]
                prev_present = True
    return out


def step_drift(tr: Tracks, comps):
    """Mean displacement per frame step f -> f+1 and the number M of particles in it."""
    if len(tr.first) == 0:
        return 0, np.zeros(0), {c: np.zeros(0) for c in comps}
    f0 = int(tr.first.min())
    spans = np.diff(tr.off)
    f1 = int((tr.first + spans - 1).max())
    n_steps = max(f1 - f0, 0)
    p_of = np.repeat(np.arange(len(tr.first)), spans)
    fr = tr.first[p_of] + (np.arange(tr.off[-1]) - tr.off[p_of])   # frame of each dense slot
    same_next = np.r_[p_of[1:] == p_of[:-1], False]
    M = None
    means = {}
    for c in comps:
        v = tr.comps[c]
        d = np.full(len(v), np.nan)
        d[:-1] = v[1:] - v[:-1]
        d[~same_next] = np.nan
        ok = np.isfinite(d)
        step = fr[ok] - f0
        s = np.bincount(step, weights=d[ok], minlength=n_steps)[:n_steps]
        m = np.bincount(step, minlength=n_steps)[:n_steps].astype(float)
        if M is None:
            M = m
        with np.errstate(invalid="ignore", divide="ignore"):
            means[c] = np.where(m > 0, s / np.maximum(m, 1), np.nan)
    return f0, M, means


def drift(df: pd.DataFrame, axes=("x", "y"), smoothing: int = 1) -> pd.DataFrame:
    """Common drift of the ensemble: cumulative mean displacement per frame.

    The drift step from frame f to f+1 is the mean displacement of the
    particles present in both frames; steps with no particle take the average
    step. The cumulative sum gives the drift position relative to the first
    frame.

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    axes : sequence of {"x", "y", "z"}
        Components to estimate.
    smoothing : int
        Width (frames) of a centred moving average applied to the steps
        (1 = none). Note: :func:`estimate_diffusion` uses the unsmoothed drift,
        for which the (1 - 1/M) bias correction is exact.

    Returns
    -------
    DataFrame
        Columns ``frame``, ``t`` (s), one column per component (drift
        position, m) and ``n`` (particles in the step ending at that frame).
    """
    comps = axis_components(parse_axes(axes))
    tr = prepare_tracks(df, comps)
    f0, M, means = step_drift(tr, comps)
    smoothing = int(smoothing)
    if smoothing < 1:
        raise UserError(f"smoothing = {smoothing} must be at least 1 frame", "give a window width in frames")
    out = {"frame": np.arange(f0, f0 + len(M) + 1)}
    out["t"] = out["frame"] * tr.dt
    for c in comps:
        st = means[c].copy()
        w = np.where(M > 0, M, 0.0)
        avg = np.nansum(st * w) / w.sum() if w.sum() > 0 else 0.0
        st[~np.isfinite(st)] = avg
        if smoothing > 1 and len(st):
            st = pd.Series(st).rolling(smoothing, center=True, min_periods=1).mean().to_numpy()
        out[c] = np.r_[0.0, np.cumsum(st)]
    out["n"] = np.r_[0, M].astype(np.int64)
    return pd.DataFrame(out)


def subtract_drift(df: pd.DataFrame, drift_table: pd.DataFrame | None = None, axes=("x", "y")) -> pd.DataFrame:
    """Return a copy of ``df`` with the drift position subtracted from each row.

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    drift_table : DataFrame, optional
        Output of :func:`drift`; computed (unsmoothed) if omitted.
    axes : sequence of {"x", "y", "z"}
        Components to correct (ignored when ``drift_table`` is given: its
        component columns are used).
    """
    if drift_table is None:
        drift_table = drift(df, axes=axes)
    comps = [c for c in ("x", "y", "z") if c in drift_table.columns]
    out = df.copy()
    fd = drift_table["frame"].to_numpy(dtype=float)
    fr = df["frame"].to_numpy(dtype=float)
    for c in comps:
        # frames outside the drift table take its first/last value
        m = np.interp(fr, fd, drift_table[c].to_numpy(dtype=float))
        out[c] = df[c].to_numpy(dtype=float) - m
    out.attrs.update(df.attrs)
    return out


def drift_corrected(tr: Tracks, comps) -> Tracks:
    """Subtract the per-step ensemble drift and undo its (1 - 1/M) bias.

    Subtracting from a displacement the mean displacement of the M particles
    that include it scales every displacement (co)variance by (1 - 1/M)
    (exactly, for independent particles, also for the localisation-noise
    correlation between consecutive steps when M does not change). We
    therefore multiply each drift-corrected step f -> f+1 by sqrt(M/(M-1))
    and rebuild the tracks, which makes D unbiased step by step. Steps seen by
    a single particle carry no information on the drift; they get the average
    drift step (M taken as infinite: no scaling). Steps across gaps are not
    part of any M and are only shifted.
    """
    f0, M, means = step_drift(tr, comps)
    scale_f = np.ones(len(M) + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        sc = np.where(M >= 2, np.sqrt(M / (M - 1.0)), 1.0)
    scale_f[:len(M)] = sc
    spans = np.diff(tr.off)
    p_of = np.repeat(np.arange(len(tr.first)), spans)
    fr = tr.first[p_of] + (np.arange(tr.off[-1]) - tr.off[p_of])
    new = {}
    for c in comps:
        st = means[c].copy()
        good = M >= 2
        w = np.where(good, M, 0.0)
        avg = np.sum(np.where(good, st, 0.0) * w) / w.sum() if w.sum() > 0 else 0.0
        st[~good] = avg
        cum = np.r_[0.0, np.cumsum(st)]
        v = tr.comps[c] - cum[fr - f0]
        new[c] = _rebuild_scaled(v[None, :].copy(), tr.off, (tr.first - f0).astype(np.int64), scale_f)[0]
    return Tracks(particles=tr.particles, first=tr.first, off=tr.off, comps=new, dt=tr.dt, n_rows=tr.n_rows)

