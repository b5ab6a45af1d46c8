"""Least-squares D over the optimal number of MSD lags (Michalet 2010; Michalet and Berglund 2012).

The optimal number of lags is found iteratively by minimising the exact
predicted variance of the fitted slope (the covariance of the MSD points for
Brownian motion with Gaussian localisation noise and blur), not taken as a
fixed fraction of the curve.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .msd import as_pos3, msd_dense
from .tracks import DEFAULT_MAX_LAG

#: number of lags of the first least-squares fit of the iteration
START_POINTS = 5


@njit(cache=True)
def _msd_cov_unit(N, P, eps):
    """Covariance of the un-normalised MSD sums U_n (n = 1..P) of one 1D track.

    Units D dt = 1. Displacements are Gaussian with covariance c0 = 2 (1 + eps)
    on the diagonal and c1 = -eps next to it (Brownian motion, localisation
    noise and motion blur all enter through eps = sigma^2/(D dt) - 2R).
    U_n = sum_i (y_{i+n} - y_i)^2, i = 0..N-n;
    Cov(U_n, U_m) = 2 sum_{i,j} Cov(y_{i+n}-y_i, y_{j+m}-y_j)^2 (Isserlis).
    The inner covariance depends on the offset d = j - i only, so the double
    sum is a sum over d weighted by its multiplicity. Intervals of
    displacement indices: I = [0, n), J = [d, d + m).
    """
    c0 = 2.0 * (1.0 + eps)
    c1 = -eps
    out = np.zeros((P, P))
    for n in range(1, P + 1):
        for m in range(n, P + 1):
            s = 0.0
            for d in range(-m - 1, n + 2):
                cnt = min(N - n, N - m - d) - max(0, -d) + 1
                if cnt <= 0:
                    continue
                o0 = min(n, d + m) - max(0, d)
                o1 = min(n, d + m - 1) - max(0, d - 1)
                o2 = min(n, d + m + 1) - max(0, d + 1)
                g = c0 * max(o0, 0) + c1 * (max(o1, 0) + max(o2, 0))
                s += cnt * g * g
            out[n - 1, m - 1] = 2.0 * s
            out[m - 1, n - 1] = 2.0 * s
    return out


def _ols_weights(P: int) -> np.ndarray:
    n = np.arange(1, P + 1, dtype=float)
    nc = n - n.mean()
    return nc / np.sum(nc * nc)


def _predicted_rel_var(lengths, weights, eps, Pmax):
    """Relative variance of the OLS slope for P = 2..Pmax (index P-2), 1D."""
    eps = float(np.clip(eps, -0.45, 1e6))
    cov = np.zeros((Pmax, Pmax))
    T = np.zeros(Pmax)
    lag = np.arange(1, Pmax + 1)
    for N, w in zip(lengths, weights):
        N = int(N)
        if N < 2:
            continue
        Pn = min(Pmax, N)
        cov[:Pn, :Pn] += w * _msd_cov_unit(N, Pn, eps)
        T += w * np.maximum(N + 1 - lag, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        C = cov / np.outer(T, T)
    out = np.full(Pmax - 1, np.inf)
    for P in range(2, Pmax + 1):
        if T[P - 1] <= 0:
            break
        w = _ols_weights(P)
        out[P - 2] = w @ C[:P, :P] @ w / 4.0     # slope of the unit model is 2
    return out


def _length_groups(n_disp: np.ndarray, max_groups: int = 12):
    """Representative track lengths (displacements) and their multiplicities."""
    u, c = np.unique(n_disp, return_counts=True)
    if len(u) <= max_groups:
        return u, c.astype(float)
    edges = np.unique(np.quantile(n_disp, np.linspace(0, 1, max_groups + 1)).astype(int))
    idx = np.clip(np.searchsorted(edges, n_disp, side="right") - 1, 0, len(edges) - 2)
    reps, ws = [], []
    for g in range(len(edges) - 1):
        sel = n_disp[idx == g]
        if len(sel):
            reps.append(int(np.median(sel)))
            ws.append(float(len(sel)))
    return np.array(reps), np.array(ws)


def optimal_lags(eps: float, lengths, weights=None, max_lags: int = 100) -> tuple[int, float]:
    """Number of MSD points minimising the variance of the least-squares D.

    Parameters
    ----------
    eps : float
        Reduced localisation error ``sigma^2/(D dt) - 2R`` (= the fitted
        offset over the fitted slope of MSD(lag)).
    lengths : array_like of int
        Displacements per track (or representative lengths).
    weights : array_like, optional
        Number of tracks of each length.
    max_lags : int
        Largest number of points considered.

    Returns
    -------
    (P, rel_var)
        Optimal number of lags and the predicted relative variance of D
        for a 1D fit (divide by the number of pooled axes).
    """
    lengths = np.asarray(lengths, dtype=int)
    weights = np.ones(len(lengths)) if weights is None else np.asarray(weights, dtype=float)
    Pmax = int(max(2, min(max_lags, lengths.max())))
    # search a window well beyond Michalet's estimate 2 + 2.3 eps^0.52, widened while the
    # minimum sits at its edge (the O(P^3) covariance makes a full search costly)
    cap = int(min(Pmax, 8 + 4 * math.sqrt(max(eps, 0.0))))
    while True:
        rv = _predicted_rel_var(lengths, weights, eps, max(cap, 2))
        i = int(np.argmin(rv))
        if i + 2 < cap or cap >= Pmax:
            return i + 2, float(rv[i])
        cap = min(Pmax, 2 * cap)


def ols_fit(msd, P):
    """Fit msd[lag-1] = a + b lag over lags 1..P; msd may be (..., L)."""
    n = np.arange(1, P + 1, dtype=float)
    y = msd[..., :P]
    nc = n - n.mean()
    b = (y * nc).sum(axis=-1) / np.sum(nc * nc)
    a = y.mean(axis=-1) - b * n.mean()
    return a, b


def ols_core(msd, n_disp, max_points: int = DEFAULT_MAX_LAG):
    """Least squares over the optimal number of lags, found iteratively.

    Start with 2 points; from the fitted offset a and slope b the reduced
    error eps = a/b gives the optimal number of points P (minimum predicted
    variance, :func:`optimal_lags`); refit and repeat until P repeats.

    Parameters
    ----------
    msd : ndarray (L,)
        Ensemble MSD at lags 1..L (any unit).
    n_disp : array_like of int
        Displacements per track (for the predicted variance).

    Returns
    -------
    a, b, P, rel_var
        Offset and slope per lag (units of msd), points used, predicted
        relative variance of b for one component.
    """
    lengths, weights = _length_groups(np.asarray(n_disp, dtype=int))
    Pmax = int(min(len(msd), max_points))
    P = int(min(Pmax, START_POINTS))
    seen = set()
    for _ in range(30):
        a_, b_ = ols_fit(msd, P)
        eps = float(a_ / b_) if b_ > 0 else 0.0
        P_new, _ = optimal_lags(eps, lengths, weights, Pmax)
        if P_new == P or P_new in seen:
            P = P_new
            break
        seen.add(P)
        P = P_new
    a_, b_ = ols_fit(msd, P)
    eps = float(a_ / b_) if b_ > 0 else 0.0
    rv = _predicted_rel_var(lengths, weights, eps, P)[P - 2]
    return float(a_), float(b_), int(P), float(rv)


def ols_from_positions(pos, dt: float, max_points: int = DEFAULT_MAX_LAG):
    """Least-squares D over the optimal number of lags, for gap-free tracks (ensemble fit).

    Parameters
    ----------
    pos : ndarray
        ``(n_particles, n_frames)`` or ``(n_particles, n_frames, n_dims)``, m.
    dt : float
        Frame interval, s.
    max_points : int
        Largest number of lags considered.

    Returns
    -------
    D : float
        m^2/s (per dimension: the MSD summed over dims is divided by 2 n_dims).
    D_err : float
        Model standard error (from the exact covariance of the MSD points).
    P : int
        Lags used.
    """
    p = as_pos3(pos)
    n_p, n_f, k = p.shape
    L = int(min(max_points, n_f - 1))
    msd = msd_dense(p, L).mean(axis=0)
    a_, b_, P, rv = ols_core(msd, np.full(n_p, n_f - 1))
    D = b_ / (2 * k * dt)
    return float(D), float(abs(D) * math.sqrt(rv / k)), int(P)



def ols_axis(s, c, n_disp, k, dt, R, W, name: str = "") -> dict:
    """Least squares of one MSD axis over the optimal number of lags, with model and bootstrap errors.

    Parameters
    ----------
    s, c : ndarray (n_p, L)
        Per-particle sums of squared displacements (m^2, summed over the
        axis's ``k`` components) and their counts, lags 1..L.
    n_disp : ndarray (n_p,)
        Displacements per track (for the predicted variance).
    k : int
        Components of the axis (``MSD = 2 k D t``).
    dt, R : float
        Frame interval (s) and motion blur.
    W : ndarray (n_boot, n_p) or None
        Bootstrap counts of whole particles.

    Returns
    -------
    dict
        As :func:`ptrack.motion.cve.cve_axis`, with ``n_lags`` the lags fitted.
    """
    from ..errors import UserError

    S, C = s.sum(axis=0), c.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        msd = S / C
    avail = int(np.max(np.flatnonzero(C > 0))) + 1 if np.any(C > 0) else 0
    if avail < 2:
        raise UserError(f"axis {name}: fewer than 2 lags available for the least-squares fit",
                        "give longer tracks or use --estimator cve")
    a_, b_, P, rv = ols_core(msd[:avail], n_disp)
    D = float(b_ / (2 * k * dt))
    boot = np.nan
    if W is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            mb = (W @ s[:, :P]) / (W @ c[:, :P])
        _, bb = ols_fit(mb, P)
        boot = float(np.nanstd(bb / (2 * k * dt), ddof=1))
    # localisation error from the offset: offset/(2k) = sigma^2 - 2 R D dt
    return {"D": D, "D_err_model": float(abs(D) * math.sqrt(rv / k)), "D_err_boot": boot,
            "sigma_loc": float(math.sqrt(max(a_ / (2 * k) + 2 * R * D * dt, 0.0))), "n_lags": int(P),
            "fit": {"slope": float(b_ / dt), "offset": float(a_), "n_dims": k, "t_min": float(dt),
                    "t_max": float(P * dt)}}
