"""Covariance-based estimator (CVE) of D: Vestergaard, Blainey and Flyvbjerg, Phys. Rev. E 89, 022726 (2014).

Per axis ``D = <dx_n^2>/(2 dt) + <dx_n dx_n+1>/dt`` and the localisation
variance ``sigma^2 = R <dx_n^2> + (2R - 1) <dx_n dx_n+1>``; unbiased whatever
the localisation error, with the closed-form variance of
:func:`ptrack.motion.bounds.cve_variance`.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
from numba import njit

from ..errors import UserError
from .bounds import cve_variance
from .drift import drift_corrected
from .fov import fov_arrays, fov_weight
from .msd import as_pos3
from .tracks import AXES, axis_components, check_motion_blur, parse_axes, prepare_tracks


@njit(cache=True)
def cve_sums_ragged(vals, off, fov, flen):
    """Per particle and component: sum w dx^2, sum w, sum w' dx_n dx_n+1, sum w'.

    Unit weights without a field of view (``fov`` with no rows); else w is
    :func:`fov_weight` of the extent of the step and w' of the three
    positions of the pair of steps.
    """
    n_p = off.shape[0] - 1
    k_c = vals.shape[0]
    n_f = fov.shape[0]
    out = np.zeros((n_p, k_c, 4))
    for p in range(n_p):
        a = off[p]
        b = off[p + 1]
        for k in range(k_c):
            s2 = 0.0
            n2 = 0.0
            s11 = 0.0
            n11 = 0.0
            prev = np.nan
            for i in range(a, b - 1):
                d = vals[k, i + 1] - vals[k, i]
                if d == d:
                    w1 = 1.0
                    for f in range(n_f):
                        w1 *= fov_weight(abs(fov[f, i + 1] - fov[f, i]), flen[f])
                    s2 += w1 * d * d
                    n2 += w1
                    if prev == prev:
                        w2 = 1.0
                        for f in range(n_f):
                            u0 = fov[f, i - 1]
                            u1 = fov[f, i]
                            u2 = fov[f, i + 1]
                            w2 *= fov_weight(max(u0, max(u1, u2)) - min(u0, min(u1, u2)), flen[f])
                        s11 += w2 * d * prev
                        n11 += w2
                prev = d
            out[p, k, 0] = s2
            out[p, k, 1] = n2
            out[p, k, 2] = s11
            out[p, k, 3] = n11
    return out


def cve_from_sums(S2, N2, S11, N11, dt, R):
    with np.errstate(invalid="ignore", divide="ignore"):
        m2 = S2 / N2
        m11 = S11 / N11
        D = m2 / (2 * dt) + m11 / dt
        s2 = R * m2 + (2 * R - 1) * m11
    return D, s2


def cve_from_positions(pos, dt: float, motion_blur: float = 0.0, return_sigma: bool = False):
    """Covariance-based estimator (CVE) per gap-free track.

    Parameters
    ----------
    pos : ndarray
        ``(n_particles, n_frames)`` one coordinate, or
        ``(n_particles, n_frames, n_dims)`` (the per-axis estimates are
        averaged), m. At least 3 frames.
    dt : float
        Frame interval, s.
    motion_blur : float
        R: 1/6 for full-frame exposure, 0 for instantaneous (simulations).
    return_sigma : bool
        Also return the localisation variance (m^2, per particle, averaged
        over dims).

    Returns
    -------
    D : ndarray (n_particles,)
        m^2/s.
    D_var : ndarray (n_particles,)
        Closed-form variance of each D (Vestergaard et al. 2014, eq. 18,
        evaluated at the estimates; averaged over the independent dims).
    sigma2 : ndarray, only if ``return_sigma``
    """
    p = as_pos3(pos)
    if p.shape[1] < 3:
        raise UserError(f"tracks have {p.shape[1]} frames", "the CVE needs at least 3 frames per track")
    dt = float(dt)
    d = np.diff(p, axis=1)
    N = d.shape[1]
    m2 = np.mean(d * d, axis=1)                         # (n_p, k)
    m11 = np.mean(d[:, 1:] * d[:, :-1], axis=1)
    D_k = m2 / (2 * dt) + m11 / dt
    s2_k = motion_blur * m2 + (2 * motion_blur - 1) * m11
    var_k = cve_variance(np.abs(D_k), np.maximum(s2_k, 0.0), dt, N, motion_blur)
    k = p.shape[2]
    D = D_k.mean(axis=1)
    var = var_k.sum(axis=1) / k**2
    if return_sigma:
        return D, var, s2_k.mean(axis=1)
    return D, var


def particle_diffusion(df: pd.DataFrame, axes=("x", "y", "xy"), motion_blur: float = 1 / 6,
                       subtract_drift: bool = False) -> pd.DataFrame:
    """CVE diffusion coefficient of each track, with its closed-form error.

    For distributions of D over particles (polydispersity, agglomerates,
    particles at different heights above a wall, to be corrected one by one).

    Parameters
    ----------
    df : DataFrame
        Trajectories table (gaps allowed; tracks need 3 consecutive frames).
    axes : sequence of str
        Any of :data:`AXES`.
    motion_blur : float
        R (1/6 full-frame exposure, 0 instantaneous).
    subtract_drift : bool
        Remove the common drift first (with the (1 - 1/M) correction).

    Returns
    -------
    DataFrame
        ``particle``, ``n_frames``, and per axis ``D_<axis>`` (m^2/s),
        ``D_<axis>_err`` (closed form, Vestergaard et al. 2014 eq. 18, at the
        track's own estimates) and ``sigma_<axis>`` (m, NaN if the estimate of
        sigma^2 is negative). Tracks without two consecutive displacements
        get NaN.
    """
    axes = parse_axes(axes)
    R = check_motion_blur(motion_blur)
    comps = axis_components(axes)
    tr = prepare_tracks(df, comps, min_rows=3)
    if subtract_drift:
        tr = drift_corrected(tr, comps)
    cs = cve_sums_ragged(tr.stack(comps), tr.off, *fov_arrays(tr, {}))
    ci = {c: i for i, c in enumerate(comps)}
    out = {"particle": tr.particles, "n_frames": tr.n_rows.astype(np.int64)}
    Dc, vc, sc = {}, {}, {}
    for c, i in ci.items():
        S2, N2, S11, N11 = (cs[:, i, j] for j in range(4))
        D, s2 = cve_from_sums(S2, N2, S11, N11, tr.dt, R)
        D = np.where(N11 > 0, D, np.nan)
        Dc[c], sc[c] = D, s2
        vc[c] = cve_variance(np.abs(D), np.maximum(s2, 0.0), tr.dt, np.maximum(N2, 1), R)
    for a in axes:
        cc = AXES[a]
        k = len(cc)
        out[f"D_{a}"] = sum(Dc[c] for c in cc) / k
        out[f"D_{a}_err"] = np.sqrt(sum(vc[c] for c in cc)) / k
        s2 = sum(sc[c] for c in cc) / k
        with np.errstate(invalid="ignore"):
            out[f"sigma_{a}"] = np.where(s2 >= 0, np.sqrt(np.abs(s2)), np.nan)
    return pd.DataFrame(out)



def component_cve(cs, comps, dt, R) -> dict:
    """Pooled CVE of each component from the per-particle sums ``cs`` (n_p, k, 4) of :func:`cve_sums_ragged`.

    Returns component -> dict ``D`` (m^2/s), ``s2`` (localisation variance,
    m^2), ``var`` (closed-form variance of D) and ``m11`` (mean product of
    consecutive displacements, m^2).
    """
    out = {}
    for i, c in enumerate(comps):
        S2, N2, S11, N11 = (cs[:, i, j] for j in range(4))
        D, s2 = cve_from_sums(S2.sum(), N2.sum(), S11.sum(), N11.sum(), dt, R)
        v_p = cve_variance(abs(D), max(s2, 0.0), dt, np.maximum(N2, 1), R)
        out[c] = {"D": float(D), "s2": float(s2), "m11": float(S11.sum() / N11.sum()),
                  "var": float(np.sum(np.where(N2 > 0, N2**2 * v_p, 0.0)) / N2.sum() ** 2)}
    return out


def cve_axis(cs, comp, idx, names, dt, R, W) -> dict:
    """CVE of one MSD axis: the mean of its components' estimates, with model and bootstrap errors.

    Parameters
    ----------
    cs : ndarray (n_p, k, 4)
        Per-particle sums (:func:`cve_sums_ragged`).
    comp : dict
        :func:`component_cve` of the same sums.
    idx, names : sequence
        Columns of ``cs`` and names of the axis's components.
    dt, R : float
        Frame interval (s) and motion blur.
    W : ndarray (n_boot, n_p) or None
        Bootstrap counts of whole particles.

    Returns
    -------
    dict
        ``D``, ``D_err_model``, ``D_err_boot`` (m^2/s; NaN without ``W``),
        ``sigma_loc`` (m), ``n_lags`` (None), ``fit``: the line through the
        MSD at lags 1 and 2 (the CVE is exactly its slope over 2 n).
    """
    k = len(names)
    D = float(np.mean([comp[c]["D"] for c in names]))
    boot = np.nan
    if W is not None:
        Sb = np.einsum("bp,pkj->bkj", W, cs[:, list(idx), :])
        Db, _ = cve_from_sums(Sb[..., 0], Sb[..., 1], Sb[..., 2], Sb[..., 3], dt, R)
        boot = float(np.std(Db.mean(axis=1), ddof=1))
    offset = float(-2.0 * sum(comp[c]["m11"] for c in names))
    return {"D": D, "D_err_model": float(math.sqrt(sum(comp[c]["var"] for c in names)) / k), "D_err_boot": boot,
            "sigma_loc": float(math.sqrt(max(np.mean([comp[c]["s2"] for c in names]), 0.0))), "n_lags": None,
            "fit": {"slope": 2 * k * D, "offset": offset, "n_dims": k, "t_min": float(dt), "t_max": float(2 * dt)}}
