"""Non-diffusive tracks: per-track ``MSD = A t^alpha`` against Monte-Carlo bounds for Brownian tracks."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from ..errors import UserError
from .cve import cve_sums_ragged
from .drift import drift_corrected
from .fov import fov_arrays
from .msd import msd_dense, msd_sums_ragged
from .tracks import AXES, parse_axes, prepare_tracks


def _alpha_fit(msd, offset, lags, dt):
    """Log-log slope of (MSD - offset) over the given lags; msd (n, L)."""
    y = msd - offset
    y = np.log(np.maximum(y, 0.05 * np.abs(msd) + 1e-300))
    x = np.log(lags * dt)
    xc = x - x.mean()
    alpha = (y * xc).sum(axis=-1) / np.sum(xc * xc)
    logA = y.mean(axis=-1) - alpha * x.mean()
    return alpha, np.exp(logA)


def _n_alpha_lags(n_frames):
    return np.clip(np.asarray(n_frames) // 4, 3, 20).astype(int)


def powerlaw_flags(df: pd.DataFrame, axes="xy", level: float = 0.01, min_frames: int = 12, n_null: int = 1000,
                   seed=0, subtract_drift: bool = False) -> pd.DataFrame:
    """Fit ``MSD = A t^alpha`` per track and flag non-diffusive tracks.

    Each track's time-averaged MSD (over lags 1..clip(n/4, 3, 20)), minus the
    ensemble's localisation offset (from the lag-1 covariance, which needs no
    assumption on the blur), is fitted in log-log. alpha is compared with the
    ``level/2`` and ``1 - level/2`` quantiles of alpha for simulated Brownian
    tracks with the same length, localisation error and fitting procedure
    (``n_null`` Monte-Carlo tracks per length class), so that a Brownian track
    is flagged with probability ``level``.

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    axes : str
        Axis whose MSD is fitted (``"xy"`` default; any of :data:`AXES`).
    level : float
        False-positive rate on Brownian tracks (two-sided).
    min_frames : int
        Shorter tracks are not assessed (alpha NaN, not flagged).
    n_null : int
        Monte-Carlo tracks per length class.
    seed : int or Generator
    subtract_drift : bool
        Remove the common drift first (as in :func:`estimate_diffusion`);
        otherwise a drifting stage makes every track look directed.

    Returns
    -------
    DataFrame
        ``particle``, ``n_frames``, ``alpha``, ``A`` (m^2/s^alpha),
        ``alpha_lo``, ``alpha_hi``, ``flagged`` (bool), ``reason`` (str).
    """
    axis = parse_axes(axes)[0]
    if not (0 < level < 1):
        raise UserError(f"level = {level!r} outside (0, 1)", "give a false-positive rate such as 0.01")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    cc = AXES[axis]
    k = len(cc)
    tr = prepare_tracks(df, cc, min_rows=3)
    if subtract_drift:
        tr = drift_corrected(tr, cc)
    dt = tr.dt
    cs = cve_sums_ragged(tr.stack(cc), tr.off, *fov_arrays(tr, {}))
    tot = cs.sum(axis=0)                                   # (k, 4)
    m2 = tot[:, 0] / tot[:, 1]
    m11 = tot[:, 2] / np.maximum(tot[:, 3], 1)
    Ddt = np.mean(m2 / 2 + m11)                            # D dt per component
    eps = float(np.clip(np.mean(-m11) / Ddt, -0.45, 1e6)) if Ddt > 0 else 0.0
    offset = float(-2.0 * np.sum(m11))
    spans = np.diff(tr.off)
    n_frames = tr.n_rows
    Lmax = int(_n_alpha_lags(spans.max()))
    s, c = msd_sums_ragged(tr.stack(cc), tr.off, Lmax)
    with np.errstate(invalid="ignore", divide="ignore"):
        msd = s / c
    n_l = _n_alpha_lags(spans)
    alpha = np.full(len(spans), np.nan)
    A = np.full(len(spans), np.nan)
    lo = np.full(len(spans), np.nan)
    hi = np.full(len(spans), np.nan)
    ok = (n_frames >= min_frames)
    # null distribution per (span class, number of lags)
    a_ma = (math.sqrt(2.0) + math.sqrt(2.0 + 4.0 * eps)) / 2.0
    b_ma = (math.sqrt(2.0) - math.sqrt(2.0 + 4.0 * eps)) / 2.0
    cls = np.floor(np.log(np.maximum(spans, 1)) / np.log(1.15)).astype(int)
    for key in np.unique(cls[ok]):
        sel = ok & (cls == key)
        N = int(spans[sel].min())                          # shortest in the class: conservative bounds
        nl = int(_n_alpha_lags(N))
        z = rng.standard_normal((n_null, N, k))
        d = a_ma * z[:, 1:, :] + b_ma * z[:, :-1, :]
        pos = np.concatenate([np.zeros((n_null, 1, k)), np.cumsum(d, axis=1)], axis=1)
        mn = msd_dense(np.ascontiguousarray(pos), nl)      # units D dt = 1
        al, _ = _alpha_fit(mn, 2.0 * k * eps, np.arange(1, nl + 1), 1.0)
        q_lo, q_hi = np.quantile(al, [level / 2, 1 - level / 2])
        lo[sel], hi[sel] = q_lo, q_hi
        for nlp in np.unique(n_l[sel]):
            s2 = sel & (n_l == nlp)
            al_p, A_p = _alpha_fit(msd[s2][:, :nlp], offset, np.arange(1, nlp + 1), dt)
            alpha[s2], A[s2] = al_p, A_p
    flagged = ok & ((alpha > hi) | (alpha < lo))
    reason = np.full(len(spans), "", dtype=object)
    for i in np.flatnonzero(flagged):
        if alpha[i] > hi[i]:
            reason[i] = (f"alpha = {alpha[i]:.2f} above {hi[i]:.2f} (the {100 * (1 - level / 2):.1f}% bound for a Brownian "
                         f"track of {int(spans[i])} frames): directed motion (drift, advection, e.g. toward an evaporating edge)")
        else:
            reason[i] = (f"alpha = {alpha[i]:.2f} below {lo[i]:.2f} (the {100 * level / 2:.1f}% bound for a Brownian "
                         f"track of {int(spans[i])} frames): confined, stuck or agglomerated")
    return pd.DataFrame({"particle": tr.particles, "n_frames": n_frames.astype(np.int64), "alpha": alpha, "A": A,
                         "alpha_lo": lo, "alpha_hi": hi, "flagged": flagged, "reason": reason})

