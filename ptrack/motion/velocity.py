"""Drift velocities of tracked particles: per particle, ensemble, against height, instantaneous.

Electrophoretic deposition (EPD) experiments film particles drifting in a field
towards an electrode; the quantity of interest is the drift velocity (and
from it the mobility and zeta potential), measured in the presence of
Brownian motion and localisation noise. Everything here is in SI units
(positions m, times s, velocities m/s, D m^2/s) and works on the shared
trajectories table (:mod:`ptrack.table`), measured or simulated.

Model and estimator
-------------------
Per axis, the observed positions of a track are ``y_j = X(t_j) + n_j``, with
``X`` a Brownian motion of diffusion coefficient ``D`` and drift ``v``
(averaged over the exposure: motion-blur parameter ``R``, 1/6 for a shutter
open the whole frame, 0 for instantaneous exposure) and ``n_j`` independent
localisation noise of variance ``sigma^2``. An increment spanning ``k`` frames
(gaps in the ``frame`` column are allowed) is ``d_i = v k_i dt + xi_i`` with::

    Var(xi_i)            = 2 D dt (k_i - 2R) + 2 sigma^2
    Cov(xi_i, xi_{i+1})  = 2 R D dt - sigma^2          (consecutive increments)
    Cov(xi_i, xi_j)      = 0                           (|i - j| > 1)

(the blur terms do not depend on the spans: the exposure windows of two
non-adjacent increments never overlap). This covariance ``S`` is tridiagonal,
so the best linear unbiased estimate of ``v`` is the generalised least squares
(GLS) estimate ``v = tau' S^-1 d / tau' S^-1 tau`` (``tau_i = k_i dt``), with
variance ``1 / tau' S^-1 tau``, computed in O(n) per track by a tridiagonal
(Thomas) solve. For ``sigma = 0, R = 0`` it is the end-to-end displacement over
the time span; with localisation noise it down-weights the noisy ends and beats
both the end-to-end estimate and the least-squares slope of position against
time (see ``bench/bench_velocity.py``).

``D`` and ``sigma^2`` are not known in advance: they are estimated per track
and axis from the drift-corrected increments ``r = d - v tau`` by the two
moments ``Q1 = sum r_i^2`` and ``Q2 = sum r_i r_i+1`` (the covariance-based
estimator of Vestergaard, Blainey and Flyvbjerg, Phys. Rev. E 89, 022726
(2014), extended to gaps), with their expectations computed exactly for the
projection ``r = (I - tau w') d`` that removes the fitted drift (so the
estimate is unbiased whatever the track length; the naive CVE on residuals is
biased low by about 3/n). Estimation alternates: end-to-end drift ->
(D, sigma^2) -> GLS drift -> (D, sigma^2) -> GLS drift. Because the weights are
even functions of the noise, the drift estimate stays exactly unbiased. The
weights need a positive-definite S, so negative estimates of D or sigma^2
(common for short tracks) are clipped for them; the stated variance
``w' S w`` is linear in (D, sigma^2) and is evaluated with the unclipped,
unbiased estimates (clipping would overstate it by ~10 % for 30-frame tracks
with sigma^2 > D dt), falling back to the clipped ones if it comes out
negative.

What is here
------------
- :func:`particle_velocity`: per particle ``vx, vy, vz`` with standard errors,
  ``D`` and localisation error per axis, number of frames, mean position.
- :func:`ensemble_velocity`: weighted mean drift with a bootstrap standard
  error over whole particles (seeded) and a heterogeneity chi^2.
- :func:`velocity_profile`: drift velocity against height ``z`` in bins (the
  EPD velocity against distance from the electrode).
- :func:`trim_deposited`: drop each track's rows from its contact with the
  substrate on (drift before deposition only).
- :func:`instantaneous_velocity`: centred finite-difference ``vx, vy, vz``
  columns added to the table (noisy: see its docstring).
- :func:`plot_velocity`: PNG with the tracks coloured by speed and the
  velocity profile against z with error bars.
- :func:`drifting_tracks`: seeded test tracks (drift + Brownian + noise + blur
  + gaps) with exactly the covariance above.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
from numba import njit

from ..errors import UserError
from .tracks import COMPONENTS, axis_components, check_motion_blur, sort_tracks

#: fewest positions per track (and axis) for a velocity with a standard error:
#: the two noise parameters need at least 3 increments after the drift is removed
MIN_FRAMES = 4


# ---------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _thomas(a, e, rhs, n, c_scr, u):
    """Solve the symmetric tridiagonal system (diag a, constant off-diagonal e) S u = rhs (first n entries)."""
    beta = a[0]
    u[0] = rhs[0] / beta
    for i in range(1, n):
        c_scr[i] = e / beta
        beta = a[i] - e * c_scr[i]
        u[i] = (rhs[i] - e * u[i - 1]) / beta
    for i in range(n - 2, -1, -1):
        u[i] -= c_scr[i + 1] * u[i + 1]


@njit(cache=True)
def _noise_moments(d, tau, kk, w, n, dt, R, scr):
    """Unbiased (D, sigma^2) from the residuals of the drift estimate v = w.d (w.tau = 1).

    E[Q] = tr(M'AM S) with M = I - tau w', S = D S_D + sigma^2 S_s;
    tr(M'AMS) = tr(AS) - 2 tau'A S w + (tau'A tau)(w'S w), for A = I (Q1) and
    A = the half-off-diagonal matrix B (Q2 = sum r_i r_i+1).
    """
    v = 0.0
    for i in range(n):
        v += w[i] * d[i]
    Q1 = 0.0
    Q2 = 0.0
    prev = 0.0
    for i in range(n):
        r = d[i] - v * tau[i]
        Q1 += r * r
        if i > 0:
            Q2 += r * prev
        prev = r
    # S_D: diag 2 dt (k - 2R), off 2 R dt;  S_s: diag 2, off -1
    coef = np.zeros((2, 2))
    for which in range(2):
        off = 2.0 * R * dt if which == 0 else -1.0
        # Sw
        for i in range(n):
            di = 2.0 * dt * (kk[i] - 2.0 * R) if which == 0 else 2.0
            s = di * w[i]
            if i > 0:
                s += off * w[i - 1]
            if i < n - 1:
                s += off * w[i + 1]
            scr[i] = s
        trS = 0.0
        tSw = 0.0
        wSw = 0.0
        tt = 0.0
        tBSw = 0.0
        tBt = 0.0
        for i in range(n):
            di = 2.0 * dt * (kk[i] - 2.0 * R) if which == 0 else 2.0
            trS += di
            tSw += tau[i] * scr[i]
            wSw += w[i] * scr[i]
            tt += tau[i] * tau[i]
            bt = 0.0
            if i > 0:
                bt += 0.5 * tau[i - 1]
            if i < n - 1:
                bt += 0.5 * tau[i + 1]
                tBt += tau[i] * tau[i + 1]
            tBSw += bt * scr[i]
        trBS = (n - 1) * off
        coef[0, which] = trS - 2.0 * tSw + tt * wSw
        coef[1, which] = trBS - 2.0 * tBSw + tBt * wSw
    det = coef[0, 0] * coef[1, 1] - coef[0, 1] * coef[1, 0]
    D = (Q1 * coef[1, 1] - Q2 * coef[0, 1]) / det
    s2 = (coef[0, 0] * Q2 - coef[1, 0] * Q1) / det
    D_raw = D
    s2_raw = s2
    if not (s2 >= 0.0):
        # sigma^2 estimated negative: set it to 0 and use the combination Q1 + 2 Q2
        s2 = 0.0
        D = (Q1 + 2.0 * Q2) / (coef[0, 0] + 2.0 * coef[1, 0])
    if not (D > 0.0):
        D = 0.0
        s2 = Q1 / coef[0, 1] if coef[0, 1] > 0 else 0.0
        if not (s2 > 0.0):
            # no fluctuation at all (e.g. exact straight line): tiny floor keeps S invertible
            s2 = 1e-300
    return D, s2, D_raw, s2_raw


@njit(cache=True)
def _quad_var(w, kk, n, dt, R, D, s2):
    """w' S(D, sigma^2) w for the tridiagonal increment covariance (linear in D and sigma^2)."""
    e = 2.0 * R * D * dt - s2
    acc = 0.0
    for i in range(n):
        acc += (2.0 * D * dt * (kk[i] - 2.0 * R) + 2.0 * s2) * w[i] * w[i]
        if i > 0:
            acc += 2.0 * e * w[i] * w[i - 1]
    return acc


@njit(cache=True)
def _gls(d, tau, kk, n, dt, R, D, s2, a_scr, c_scr, u):
    """GLS drift (v, var) for increments d with spans tau, noise (D, sigma^2); leaves w = S^-1 tau / tau'S^-1 tau in u."""
    for i in range(n):
        a_scr[i] = 2.0 * D * dt * (kk[i] - 2.0 * R) + 2.0 * s2
    e = 2.0 * R * D * dt - s2
    _thomas(a_scr, e, tau, n, c_scr, u)
    ut = 0.0
    ud = 0.0
    for i in range(n):
        ut += u[i] * tau[i]
        ud += u[i] * d[i]
    for i in range(n):
        u[i] /= ut
    return ud / ut, 1.0 / ut


@njit(cache=True)
def _velocity_kernel(vals, frames, off, dt, R, D_in, s2_in, min_obs, n_iter):
    """Per track (off) and component (rows of vals): v, var(v), D, sigma^2, n positions, time span, raw D, raw sigma^2.

    ``vals`` (k, N) in track order, NaN where a component is missing; ``frames``
    (N,) int; ``D_in``/``s2_in`` (k, n_p): given noise parameters (NaN:
    estimate from the track).
    """
    k_c = vals.shape[0]
    n_p = off.shape[0] - 1
    out = np.full((k_c, n_p, 8), np.nan)
    maxlen = 1
    for p in range(n_p):
        if off[p + 1] - off[p] > maxlen:
            maxlen = off[p + 1] - off[p]
    d = np.empty(maxlen)
    tau = np.empty(maxlen)
    kk = np.empty(maxlen)
    w = np.empty(maxlen)
    a_scr = np.empty(maxlen)
    c_scr = np.empty(maxlen)
    scr = np.empty(maxlen)
    for k in range(k_c):
        for p in range(n_p):
            n = 0
            last = np.nan
            last_f = 0
            first_f = -1
            m = 0
            for i in range(off[p], off[p + 1]):
                y = vals[k, i]
                if y != y:
                    continue
                if m > 0:
                    d[n] = y - last
                    kk[n] = frames[i] - last_f
                    tau[n] = kk[n] * dt
                    n += 1
                else:
                    first_f = frames[i]
                last = y
                last_f = frames[i]
                m += 1
            out[k, p, 4] = m
            out[k, p, 5] = (last_f - first_f) * dt if m > 0 else 0.0
            given = D_in[k, p] == D_in[k, p] and s2_in[k, p] == s2_in[k, p]
            if n < 1 or (not given and m < min_obs):
                continue
            if given:
                D = D_in[k, p]
                s2 = s2_in[k, p]
                if not (D > 0.0 or s2 > 0.0):
                    s2 = 1e-300
            else:
                span = 0.0
                for i in range(n):
                    span += tau[i]
                for i in range(n):
                    w[i] = 1.0 / span          # end-to-end: the GLS for sigma = 0, R = 0
                D, s2, D_raw, s2_raw = _noise_moments(d, tau, kk, w, n, dt, R, scr)
            v, var = _gls(d, tau, kk, n, dt, R, D, s2, a_scr, c_scr, w)
            if not given:
                for _ in range(n_iter - 1):
                    D, s2, D_raw, s2_raw = _noise_moments(d, tau, kk, w, n, dt, R, scr)
                    v, var = _gls(d, tau, kk, n, dt, R, D, s2, a_scr, c_scr, w)
                # stated variance w'S w with the unclipped (unbiased) D, sigma^2: linear in them, so
                # unbiased; the clipped values (needed for positive-definite weights) overstate it
                var_u = _quad_var(w, kk, n, dt, R, D_raw, s2_raw)
                if var_u > 0.0:
                    var = var_u
            out[k, p, 0] = v
            out[k, p, 1] = var
            out[k, p, 2] = D
            out[k, p, 3] = s2
            if not given:
                out[k, p, 6] = D_raw
                out[k, p, 7] = s2_raw
    return out


# ---------------------------------------------------------------------------
# preparation
# ---------------------------------------------------------------------------

def default_axes(df: pd.DataFrame) -> tuple:
    """The coordinate columns analysed when none are given: the one rule.

    x, y and z when the table has finite heights that change; x and y for a 2D
    table (z NaN) and for one whose z is the same in every row (no motion along
    z to measure).

    Examples
    --------
    >>> import pandas as pd
    >>> default_axes(pd.DataFrame({"z": [1e-6, 1e-6]})), default_axes(pd.DataFrame({"z": [0.0, 1e-7]}))
    (('x', 'y'), ('x', 'y', 'z'))
    """
    z = df["z"].to_numpy(dtype=float) if "z" in df.columns else np.zeros(0)
    z = z[np.isfinite(z)]
    return ("x", "y", "z") if len(z) and float(z.max()) > float(z.min()) else ("x", "y")


def _components(df: pd.DataFrame, axes) -> tuple:
    """Coordinate columns analysed: the components of ``axes`` (:func:`ptrack.motion.tracks.axis_components`),
    or x, y and (if the table has finite z) z."""
    return default_axes(df) if axes is None else axis_components(axes)


def _sorted_tracks(df: pd.DataFrame, comps):
    """Rows sorted by (particle, frame) (:func:`ptrack.motion.tracks.sort_tracks`) as the kernel's arrays."""
    st = sort_tracks(df, comps)
    return st.particles, st.off, st.frames, st.vals, st.dt, st.order


# ---------------------------------------------------------------------------
# per particle
# ---------------------------------------------------------------------------

def particle_velocity(df: pd.DataFrame, axes=None, motion_blur: float = 1 / 6, min_frames: int = MIN_FRAMES,
                      noise: str = "pooled", n_iter: int = 2) -> pd.DataFrame:
    """Drift velocity of each track by generalised least squares, with its standard error.

    Parameters
    ----------
    df : DataFrame
        Trajectories table (frame, t, particle, x, y, z in m). Gaps in
        ``frame`` are allowed (an increment then spans several frames); a NaN
        in one coordinate drops that position for that axis only.
    axes : str or sequence, optional
        Components to analyse, e.g. ``"xyz"``, ``"xy"``, ``("x", "z")``.
        Default: x, y and, if the table has finite z, z.
    motion_blur : float
        R in [0, 1/4) (:func:`ptrack.motion.tracks.check_motion_blur`): 1/6 for a shutter open the whole frame (default), 0 for
        instantaneous exposure (simulated truth tables).
    min_frames : int
        Fewest positions of a track (per axis) for a velocity; shorter tracks
        get NaN (at least :data:`MIN_FRAMES`).
    noise : {"pooled", "track"}
        Where the GLS weights and the stated error get (D, sigma^2) from: the
        ensemble's pooled estimate per axis (default: monodisperse particles
        under one localisation error; exact errors even for short,
        noise-dominated tracks), or each track's own drift-corrected
        increments (particles that differ in size or mobility). Per-track
        estimates from short tracks are noisy: their errors are unbiased in
        the mean square (~5-10 % conservative for 30 frames with
        sigma^2 = 2 D dt) but a track whose D happens to come out small gets
        a small error and dominates an inverse-variance mean (on the shipped
        EPD truth, 16 tracks of 10-90 frames: chi^2/dof up to 4 with "track",
        about 1 with "pooled"). The ``D{a}`` and ``sigma_{a}`` columns are per
        track either way.
    n_iter : int
        GLS / noise-estimate alternations (2 is converged in practice).

    Returns
    -------
    DataFrame, one row per particle
        ``particle``, ``n_frames`` (positions), ``t_start``, ``t_span`` (s),
        ``x_mean``, ``y_mean``, ``z_mean`` (m), then for each of x, y, z:
        ``v{a}`` (m/s), ``v{a}_err`` (standard error, m/s), ``n_{a}`` (positions with a finite {a}), ``D{a}`` (m^2/s,
        from the drift-corrected increments), ``sigma_{a}`` (localisation
        error, m). Axes not analysed are NaN. ``speed`` = |v| over the
        analysed axes (m/s). Metadata: the table's, plus ``attrs["velocity"]``
        with ``motion_blur``, ``frame_interval``, ``axes``, ``noise`` and the
        pooled ``D_pooled`` / ``sigma_pooled`` per axis.
    """
    comps = _components(df, axes)
    R = check_motion_blur(motion_blur)
    min_frames = int(min_frames)
    if min_frames < MIN_FRAMES:
        raise UserError(f"min_frames = {min_frames} is below {MIN_FRAMES}",
                        f"a velocity with a standard error needs at least {MIN_FRAMES} positions per track")
    if int(n_iter) < 1:
        raise UserError(f"n_iter = {n_iter} must be at least 1", "use 2")
    if noise not in ("pooled", "track"):
        raise UserError(f"noise = {noise!r} is not understood", "give 'pooled' or 'track'")
    parts, off, frames, vals, dt, order = _sorted_tracks(df, comps)
    nan_in = np.full((len(comps), len(parts)), np.nan)
    res = _velocity_kernel(vals, frames, off, dt, R, nan_in, nan_in, min_frames, int(n_iter))
    # unclipped per-track estimates are unbiased: pool them weighted by the number of increments
    n_inc = np.maximum(res[:, :, 4] - 1, 0)
    ok = np.isfinite(res[:, :, 6]) & np.isfinite(res[:, :, 7])
    wsum = np.where(ok, n_inc, 0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        D_p = np.maximum(np.where(ok, res[:, :, 6] * n_inc, 0).sum(axis=1) / wsum, 0.0)
        s2_p = np.maximum(np.where(ok, res[:, :, 7] * n_inc, 0).sum(axis=1) / wsum, 0.0)
    if noise == "pooled" and ok.any():
        D_in = np.repeat(D_p[:, None], len(parts), axis=1)
        s2_in = np.repeat(s2_p[:, None], len(parts), axis=1)
        D_in[~ok] = np.nan                                     # tracks too short: still no velocity
        pooled = _velocity_kernel(vals, frames, off, dt, R, D_in, s2_in, min_frames, 1)
        res[:, :, 0] = np.where(ok, pooled[:, :, 0], np.nan)
        res[:, :, 1] = np.where(ok, pooled[:, :, 1], np.nan)
    vel = _per_particle_frame(df, parts, off, frames, order, comps, res, dt, R)
    vel.attrs["velocity"].update({"noise": noise, "D_pooled": {c: float(D_p[j]) for j, c in enumerate(comps)},
                                  "sigma_pooled": {c: float(np.sqrt(s2_p[j])) for j, c in enumerate(comps)}})
    return vel


def _per_particle_frame(df, parts, off, frames, order, comps, res, dt, R):
    n_rows = np.diff(off)
    seg = np.repeat(np.arange(len(parts)), n_rows)
    out = {"particle": parts, "n_frames": n_rows, "t_start": frames[off[:-1]] * dt,
           "t_span": (frames[off[1:] - 1] - frames[off[:-1]]) * dt}
    for c in COMPONENTS:
        if c in df.columns:
            v = df[c].to_numpy(dtype=float)[order]
            ok = np.isfinite(v)
            cnt = np.bincount(seg, weights=ok, minlength=len(parts))
            with np.errstate(invalid="ignore", divide="ignore"):
                out[f"{c}_mean"] = np.bincount(seg, weights=np.where(ok, v, 0.0), minlength=len(parts)) / cnt
        else:
            out[f"{c}_mean"] = np.full(len(parts), np.nan)
    speed2 = np.zeros(len(parts))
    for c in COMPONENTS:
        if c in comps:
            j = comps.index(c)
            v, var, D, s2 = res[j, :, 0], res[j, :, 1], res[j, :, 2], res[j, :, 3]
            speed2 = speed2 + v * v
        else:
            v = var = D = s2 = np.full(len(parts), np.nan)
        out[f"v{c}"] = v
        out[f"v{c}_err"] = np.sqrt(var)
        # positions with this component finite (fewer than n_frames where the coordinate is NaN)
        out[f"n_{c}"] = res[j, :, 4].astype(np.int64) if c in comps else np.zeros(len(parts), np.int64)
        out[f"D{c}"] = D
        out[f"sigma_{c}"] = np.sqrt(s2)
    out["speed"] = np.sqrt(speed2)
    vel = pd.DataFrame(out)
    vel.attrs.update({k: v for k, v in df.attrs.items()})
    vel.attrs["velocity"] = {"motion_blur": R, "frame_interval": dt, "axes": "".join(comps)}
    return vel


# ---------------------------------------------------------------------------
# ensemble
# ---------------------------------------------------------------------------

def _boot_counts(n: int, n_boot: int, rng) -> np.ndarray:
    """(n_boot, n) resampling counts of n particles drawn with replacement."""
    return rng.multinomial(n, np.full(n, 1.0 / n), size=n_boot).astype(float)


def ensemble_velocity(vel: pd.DataFrame, axes=None, weights: str = "inverse_variance", n_boot: int = 1000,
                      seed=0) -> pd.DataFrame:
    """Mean drift velocity of the ensemble with a bootstrap standard error over particles.

    Parameters
    ----------
    vel : DataFrame
        Output of :func:`particle_velocity`.
    axes : str or sequence, optional
        Default: the axes that have finite velocities.
    weights : {"inverse_variance", "equal"}
        Inverse-variance (each particle weighted by 1 / v_err^2: the best
        estimate of a common drift) or equal weights (the plain mean of the
        particles' velocities, better when the particles truly differ).
    n_boot : int
        Bootstrap resamples of whole particles (0: model error only).
    seed : int or Generator

    Returns
    -------
    DataFrame, one row per axis
        ``axis``, ``v`` (m/s), ``v_err`` (bootstrap standard error over
        particles; the model error when fewer than 3 particles or n_boot = 0),
        ``v_err_model`` (from the particles' stated errors alone), ``chi2_dof``
        (scatter of the particles about the mean relative to their errors: about
        1 when they share one drift, above 1 when they differ), ``n_particles``.
    """
    if weights not in ("inverse_variance", "equal"):
        raise UserError(f"weights = {weights!r} is not understood", "give 'inverse_variance' or 'equal'")
    if int(n_boot) < 0:
        raise UserError(f"n_boot = {n_boot} is negative", "give 0 or a positive number")
    if axes is None:
        comps = tuple(c for c in COMPONENTS if f"v{c}" in vel.columns and np.isfinite(vel[f"v{c}"].to_numpy(float)).any())
    else:
        comps = axis_components(axes)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    rows = []
    for c in comps:
        v = vel[f"v{c}"].to_numpy(dtype=float)
        e = vel[f"v{c}_err"].to_numpy(dtype=float)
        ok = np.isfinite(v) & np.isfinite(e) & (e > 0)
        v, e = v[ok], e[ok]
        n = len(v)
        if n == 0:
            rows.append({"axis": c, "v": np.nan, "v_err": np.nan, "v_err_model": np.nan, "chi2_dof": np.nan,
                         "n_particles": 0})
            continue
        # inverse variances scaled by the smallest variance (the same weighted mean and error; no overflow
        # when an error is tiny, e.g. v_z of a table whose z never changes)
        w = (e.min() / e) ** 2 if weights == "inverse_variance" else np.ones(n)
        mean = float(np.sum(w * v) / np.sum(w))
        err_model = float(math.sqrt(np.sum(w**2 * e**2)) / np.sum(w))
        chi2 = float(np.sum((v - mean) ** 2 / e**2) / (n - 1)) if n > 1 else np.nan
        err = err_model
        if n >= 3 and n_boot > 0:
            C = _boot_counts(n, int(n_boot), rng)
            boot = (C @ (w * v)) / (C @ w)
            err = float(np.std(boot, ddof=1))
        rows.append({"axis": c, "v": mean, "v_err": err, "v_err_model": err_model, "chi2_dof": chi2,
                     "n_particles": n})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------
# profile against height
# ---------------------------------------------------------------------------

def velocity_profile(df: pd.DataFrame, bins=10, z_range=None, axes=None, motion_blur: float = 1 / 6,
                     vel: pd.DataFrame | None = None, min_frames: int = MIN_FRAMES, noise: str = "pooled",
                     n_boot: int = 1000, seed=0) -> pd.DataFrame:
    """Drift velocity against height z, in bins (EPD: velocity against distance from the electrode).

    Each increment is assigned to the bin of its *starting* height. For a
    Markov process the increment that follows a position does not depend on
    how the particle got there, so this assignment does not bias the drift
    (assigning increments by where they end, or keeping only increments that
    stay inside a bin, would select small or large steps at the bin edges and
    bias v_z by several %). With localisation noise sigma_z the starting
    height is itself noisy, which biases a bin's v_z by about sigma_z^2 /
    (bin width x frame interval) where the velocity changes with z; keep bins
    much wider than sigma_z.

    Within a bin, each particle's runs of consecutive increments are pieces;
    the bin's drift is their summed displacement over their summed duration
    (uniform weights: weighting increments by their place in a piece, as the
    GLS does, would again select the bin-leaving steps and bias v). Its model
    error uses each particle's (D, sigma^2) from its whole track
    (:func:`particle_velocity`: piece variance ``2 D T - 4 R D dt + 2
    sigma^2``); ``v_err`` is a bootstrap over whole particles.

    Parameters
    ----------
    df : DataFrame
        Trajectories table with finite z.
    bins : int or array_like
        Number of equal-width bins over ``z_range`` or the bin edges (m).
    z_range : (float, float), optional
        Default: the finite z range of the table.
    axes, motion_blur, min_frames, noise
        As in :func:`particle_velocity`.
    vel : DataFrame, optional
        Per-particle result of :func:`particle_velocity` (computed if not
        given); its (D, sigma^2), pooled or per track, set the model errors.
    n_boot : int
    seed : int or Generator

    Returns
    -------
    DataFrame, one row per bin
        ``z_lo``, ``z_hi``, ``z_mid``, ``z_mean`` (mean starting height of its
        increments), m; ``n_particles``, ``n_increments``; per axis ``v{a}``,
        ``v{a}_err`` (bootstrap over particles, or the model error with
        fewer than 3 particles), ``v{a}_err_model``, m/s.
    """
    if "z" not in default_axes(df):       # the one axes rule: heights that change
        raise UserError("velocity profile against z needs heights, but z is NaN or one value everywhere",
                        "track with a calibration stack (3D) or use particle_velocity for 2D tables")
    comps = _components(df, axes)
    R = check_motion_blur(motion_blur)
    if vel is None:
        vel = particle_velocity(df, axes=comps, motion_blur=R, min_frames=min_frames, noise=noise)
    z_all = df["z"].to_numpy(dtype=float)
    zf = z_all[np.isfinite(z_all)]
    if np.ndim(bins) == 0:
        nb = int(bins)
        if nb < 1:
            raise UserError(f"bins = {bins} must be at least 1", "give a number of bins or their edges")
        lo, hi = (float(zf.min()), float(zf.max())) if z_range is None else map(float, z_range)
        if not hi > lo:
            raise UserError(f"z range [{lo}, {hi}] is empty", "give z_range with z_min < z_max")
        edges = np.linspace(lo, hi, nb + 1)
    else:
        edges = np.asarray(bins, dtype=float)
        if edges.ndim != 1 or len(edges) < 2 or not np.all(np.diff(edges) > 0) or not np.all(np.isfinite(edges)):
            raise UserError("bin edges must be finite and increasing", "give at least two increasing heights, m")
    nb = len(edges) - 1
    parts, off, frames, vals, dt, order = _sorted_tracks(df, comps)
    z = z_all[order]
    b = np.searchsorted(edges, z, side="right") - 1
    b[z == edges[-1]] = nb - 1
    b[~np.isfinite(z) | (b < 0) | (b >= nb)] = -1
    N = len(z)
    seg = np.repeat(np.arange(len(parts)), np.diff(off))
    # a piece: a run of rows of one particle in one bin, extended by the row that follows it in the track
    new = np.r_[True, (seg[1:] != seg[:-1]) | (b[1:] != b[:-1])]
    run_start = np.flatnonzero(new)
    run_end = np.r_[run_start[1:], N]
    track_end = off[1:][seg[run_start]]
    ext_end = np.minimum(run_end + 1, track_end)
    keep = (b[run_start] >= 0) & (ext_end - run_start >= 2)
    rs, re_ = run_start[keep], ext_end[keep]
    lens = re_ - rs
    p_bin = b[rs]
    p_par = seg[rs]
    first, last = rs, re_ - 1
    span = (frames[last] - frames[first]) * dt                 # piece durations, s
    n_inc = lens - 1
    # noise parameters of the parent tracks
    pos_in_vel = pd.Index(vel["particle"].to_numpy()).get_indexer(parts)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    has_next = np.r_[seg[1:] == seg[:-1], False]
    rows = []
    disp, pvar = {}, {}
    vmeta = vel.attrs.get("velocity", {})
    pooled = vmeta.get("noise") == "pooled"
    for j, c in enumerate(comps):
        Dv = np.where(pos_in_vel >= 0, vel[f"D{c}"].to_numpy(float)[pos_in_vel], np.nan)[p_par]
        sv = np.where(pos_in_vel >= 0, vel[f"sigma_{c}"].to_numpy(float)[pos_in_vel], np.nan)[p_par] ** 2
        if pooled and c in vmeta.get("D_pooled", {}):
            Dv = np.where(np.isfinite(Dv), vmeta["D_pooled"][c], np.nan)
            sv = np.where(np.isfinite(sv), vmeta["sigma_pooled"][c] ** 2, np.nan)
        disp[c] = vals[j, last] - vals[j, first]
        # variance of a piece's end-to-end displacement: 1' S 1 = 2 D T - 4 R D dt + 2 sigma^2
        pvar[c] = 2 * Dv * span - 4 * R * Dv * dt + 2 * sv
    for k in range(nb):
        sel = p_bin == k
        inb = (b == k) & has_next                                   # increments starting in the bin
        row = {"z_lo": edges[k], "z_hi": edges[k + 1], "z_mid": 0.5 * (edges[k] + edges[k + 1]),
               "z_mean": float(np.mean(z[inb])) if inb.any() else np.nan,
               "n_particles": int(len(np.unique(p_par[sel]))), "n_increments": int(n_inc[sel].sum())}
        for c in comps:
            ok = sel & np.isfinite(disp[c]) & np.isfinite(pvar[c]) & (span > 0)
            if not ok.any():
                row.update({f"v{c}": np.nan, f"v{c}_err": np.nan, f"v{c}_err_model": np.nan})
                continue
            uniq, inv = np.unique(p_par[ok], return_inverse=True)
            S = np.bincount(inv, weights=disp[c][ok])
            T = np.bincount(inv, weights=span[ok])
            mean = float(S.sum() / T.sum())
            err_model = float(math.sqrt(max(pvar[c][ok].sum(), 0.0)) / T.sum())
            err = err_model
            if len(uniq) >= 3 and n_boot > 0:
                C = _boot_counts(len(uniq), int(n_boot), rng)
                err = float(np.std((C @ S) / (C @ T), ddof=1))
            row.update({f"v{c}": mean, f"v{c}_err": err, f"v{c}_err_model": err_model})
        rows.append(row)
    prof = pd.DataFrame(rows)
    for c in COMPONENTS:
        if c not in comps:
            prof[f"v{c}"] = np.nan
            prof[f"v{c}_err"] = np.nan
            prof[f"v{c}_err_model"] = np.nan
    return prof


# ---------------------------------------------------------------------------
# deposition: drop what follows contact
# ---------------------------------------------------------------------------

@njit(cache=True)
def _contact_index(z, off, level, window):
    """Per track: the first row whose centred running median of z (``window`` rows, clipped at the track's ends)
    is <= level (or the end of the track).

    The median of rows j - window//2 .. j + window//2 describes row j, so a track that moves freely until row k
    and then sits at the contact height is cut exactly at k. (Cutting at the first row of the first low window,
    as before, dropped window//2 free rows before every contact, and with them the descent's last part.)"""
    n_p = off.shape[0] - 1
    out = np.empty(n_p, dtype=np.int64)
    buf = np.empty(window)
    h = window // 2
    for p in range(n_p):
        a = off[p]
        b = off[p + 1]
        out[p] = b
        for i in range(a, b):
            m = 0
            for j in range(max(a, i - h), min(b, i + h + 1)):
                if z[j] == z[j]:
                    buf[m] = z[j]
                    m += 1
            if m == 0:
                continue
            med = np.median(buf[:m])
            if med <= level:
                out[p] = i
                break
    return out


def trim_deposited(df: pd.DataFrame, z_contact: float, tolerance: float = 0.5e-6, window: int = 5) -> pd.DataFrame:
    """Drop each track's rows from its contact with the substrate on (EPD: drift before deposition only).

    A track is taken to touch down at the first row whose running median of
    measured heights (``window`` rows centred on it, clipped at the track's
    ends) is at or below ``z_contact + tolerance``; that row and all later rows of the track are
    dropped (a deposited particle stays put, and its rows would pull the
    drift towards zero). A running median rather than single heights keeps
    one noisy z from cutting a track early; tracks that never come down keep
    all their rows. Rows of a deposited particle that the tracker linked into
    a separate track (e.g. after a gap) are dropped as well when they sit at
    the substrate.

    Parameters
    ----------
    df : DataFrame
        Trajectories table with z (m).
    z_contact : float
        Height of a particle's centre at contact, m (its radius when z = 0 is
        the substrate surface).
    tolerance : float
        m; a few times the z localisation error (default 0.5 um).
    window : int
        Rows in the running median (default 5).

    Returns
    -------
    DataFrame
        The rows before contact, sorted by (particle, frame), metadata kept.
    """
    if "z" not in df.columns or not np.isfinite(df["z"].to_numpy(dtype=float)).any():
        raise UserError("trim_deposited needs heights, but z is NaN everywhere", "track with a calibration stack (3D)")
    for name, val in (("z_contact", z_contact), ("tolerance", tolerance)):
        if not math.isfinite(float(val)):
            raise UserError(f"{name} = {val!r} is not finite", f"give {name} in m")
    w = int(window)
    if w < 1:
        raise UserError(f"window = {window} must be at least 1", "give a number of rows, e.g. 5")
    srt = df.sort_values(["particle", "frame"], kind="stable").reset_index(drop=True)
    srt.attrs.update(df.attrs)
    if len(srt) == 0:
        return srt
    part = srt["particle"].to_numpy()
    starts = np.flatnonzero(np.r_[True, part[1:] != part[:-1]])
    off = np.r_[starts, len(part)].astype(np.int64)
    cut = _contact_index(np.ascontiguousarray(srt["z"].to_numpy(dtype=float)), off,
                         float(z_contact) + float(tolerance), w)
    seg = np.repeat(np.arange(len(starts)), np.diff(off))
    keep = np.arange(len(srt)) < cut[seg]
    out = srt[keep].reset_index(drop=True)
    out.attrs.update(df.attrs)
    return out


# ---------------------------------------------------------------------------
# instantaneous velocities
# ---------------------------------------------------------------------------

def instantaneous_velocity(df: pd.DataFrame, window: int = 1) -> pd.DataFrame:
    """Add centred finite-difference velocity columns ``vx, vy, vz`` (m/s) to a copy of the table.

    ``v(t_j) = (x_{j+w} - x_{j-w}) / (t_{j+w} - t_{j-w})`` over the positions
    of the same track (``w = window`` positions either side; one-sided at the
    ends of a track, NaN for single-position tracks; gaps in ``frame`` are
    handled by the actual time difference).

    These are noisy: for Brownian motion each component carries noise of
    standard deviation ``sqrt(2 D / T + 2 sigma^2 / T^2)`` with
    ``T = 2 w dt`` (about ``sqrt(D / (w dt))``, e.g. 3.3 um/s for a 0.8 um
    sphere in water at 30 fps and w = 1, comparable to EPD velocities), so use
    :func:`particle_velocity` or :func:`velocity_profile` for drift
    velocities and these only to colour or smooth tracks.

    Parameters
    ----------
    df : DataFrame
        Trajectories table.
    window : int
        Half-window w, positions (>= 1).

    Returns
    -------
    DataFrame
        The table sorted by (particle, frame) with ``vx``, ``vy``, ``vz``
        (vz NaN where z is NaN).
    """
    w = int(window)
    if w < 1:
        raise UserError(f"window = {window} must be at least 1", "give a half-window of 1 or more positions")
    for c in ("frame", "t", "particle", "x", "y"):
        if c not in df.columns:
            raise UserError(f"trajectories table lacks column '{c}'", "a trajectories table needs frame, t, particle, x, y, z")
    out = df.sort_values(["particle", "frame"], kind="stable").reset_index(drop=True)
    out.attrs.update(df.attrs)
    part = out["particle"].to_numpy()
    N = len(out)
    if N == 0:
        return out.assign(vx=np.zeros(0), vy=np.zeros(0), vz=np.zeros(0))
    starts = np.flatnonzero(np.r_[True, part[1:] != part[:-1]])
    ends = np.r_[starts[1:], N]
    seg = np.repeat(np.arange(len(starts)), ends - starts)
    j = np.arange(N)
    lo = np.maximum(j - w, starts[seg])
    hi = np.minimum(j + w, ends[seg] - 1)
    t = out["t"].to_numpy(dtype=float)
    dtt = t[hi] - t[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        for c in COMPONENTS:
            if c in out.columns:
                x = out[c].to_numpy(dtype=float)
                v = np.where(hi > lo, (x[hi] - x[lo]) / dtt, np.nan)
            else:
                v = np.full(N, np.nan)
            out[f"v{c}"] = v
    return out
