"""Mean squared displacement (MSD) and diffusion-coefficient estimators.

Shared by the image pipeline (measured tracks) and the simulator's studies
(simulated tracks). Everything is in SI units: positions in m, times in s,
MSD in m^2, D in m^2/s.

What is here
------------
- :func:`ensemble_msd`, :func:`particle_msd`: time-averaged MSD per particle and
  over the ensemble (all particles, all start times), per axis (``x``, ``y``,
  ``z``) and combined (``xy``, ``xz``, ``yz``, ``xyz``). Tracks may have gaps
  (missing frames): a displacement is counted only where both ends exist.
- :func:`particle_diffusion`: CVE D of each track with its closed-form error.
- :func:`estimate_diffusion`: D per axis with standard errors, by

  * ``"cve"``: the covariance-based estimator of Vestergaard, Blainey and
    Flyvbjerg, Phys. Rev. E 89, 022726 (2014). Per axis
    ``D = <dx_n^2>/(2 dt) + <dx_n dx_n+1>/dt`` and the localisation variance
    ``sigma^2 = R <dx_n^2> + (2R - 1) <dx_n dx_n+1>``, with the motion-blur
    parameter ``R`` (1/6 for a shutter open the whole frame, 0 for
    instantaneous exposure). Unbiased whatever the localisation error; its
    variance is known in closed form (:func:`cve_variance`).
  * ``"ols"``: least squares of ``MSD(t) = 2 n D t + offset`` over the optimal
    number of lags (Michalet, Phys. Rev. E 82, 041914 (2010); Michalet and
    Berglund, Phys. Rev. E 85, 061916 (2012)). The offset absorbs localisation
    error and motion blur. The optimal number of lags depends on the reduced
    localisation error; it is found iteratively, by minimising the exact
    predicted variance of the fitted slope (computed from the covariance of
    the MSD points for Brownian motion with Gaussian localisation noise and
    blur), not taken as a fixed fraction of the curve.

  Standard errors come from a bootstrap over whole particles (particles are
  resampled with replacement; resampling single displacements would ignore
  their correlations and give errors about 2x too small). With fewer than
  :data:`MIN_PARTICLES_BOOTSTRAP` particles the model (closed-form) error is
  reported instead; both are kept in the result.
- :func:`drift`, :func:`subtract_drift`: common drift of the ensemble.
  Subtracting the mean displacement of the same M particles biases D by a
  factor (1 - 1/M); :func:`estimate_diffusion` with ``subtract_drift=True``
  corrects every step for its own M.
- :func:`powerlaw_flags`: per-track fit of ``MSD = A t^alpha`` and automatic
  flags for non-diffusive tracks (directed/advected, or confined/stuck/
  agglomerated), with alpha compared to bounds from Monte-Carlo tracks of the
  same length and localisation error (so the false-positive rate on Brownian
  tracks is the nominal one).
- :func:`stokes_einstein`, :func:`cve_variance`, :func:`crlb_diffusion`.
- Array fast paths for simulations: :func:`msd_from_positions`,
  :func:`cve_from_positions`.
- :func:`plot_msd`: log-log MSD per axis with the fitted model, as PNG.

Notes on the seed document: it fits a polynomial to the whole MSD curve
(eq. 3.30). Fitting a fixed fraction of the curve wastes most of the
information (bench/bench_msd.py: 25 % of the curve gives 2.3-10x the Cramer-Rao
bound, ~65-70 % error for a single track); the optimal-lag fit stays within
1.12x of the bound and the CVE is at the bound for small localisation error.
Table 4.1: D from an n-dimensional MSD is
``MSD / (2 n t)``. D_x, D_y (n = 1) and D_xy (n = 2, MSD = <dx^2 + dy^2>) must
agree within their errors on isotropic data; here D_xy is the mean (exactly, for the CVE) of
the 1D estimates taken on the same displacements.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numba import njit

from .constants import BOLTZMANN
from .errors import UserError

#: axis name -> the coordinate columns summed in its MSD
AXES = {
    "x": ("x",), "y": ("y",), "z": ("z",),
    "xy": ("x", "y"), "xz": ("x", "z"), "yz": ("y", "z"), "xyz": ("x", "y", "z"),
}
#: below this many particles the closed-form (model) standard error is reported
MIN_PARTICLES_BOOTSTRAP = 10
#: default longest lag (frames) of MSD tables
DEFAULT_MAX_LAG = 100
#: number of lags of the first least-squares fit of the iteration
START_POINTS = 5


# ---------------------------------------------------------------------------
# physics
# ---------------------------------------------------------------------------

def stokes_einstein(radius, viscosity, temperature=293.15):
    """Stokes-Einstein diffusion coefficient ``kB T / (6 pi mu r)``.

    Parameters
    ----------
    radius : float or array_like
        Particle radius, m.
    viscosity : float or array_like
        Dynamic viscosity of the fluid, Pa s.
    temperature : float or array_like
        Absolute temperature, K (default 293.15 K, room temperature).

    Returns
    -------
    float or ndarray
        D, m^2/s (broadcast over the inputs).
    """
    r = np.asarray(radius, dtype=float)
    mu = np.asarray(viscosity, dtype=float)
    T = np.asarray(temperature, dtype=float)
    for name, v in (("radius", r), ("viscosity", mu), ("temperature", T)):
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise UserError(f"{name} = {v.tolist()!r} must be finite and positive", f"give {name} in SI units")
    d = BOLTZMANN * T / (6.0 * np.pi * mu * r)
    return float(d) if d.ndim == 0 else d


def cve_variance(D, sigma2, dt, n, motion_blur=0.0):
    """Closed-form variance of the 1D CVE for one track of ``n`` displacements.

    Vestergaard et al. 2014, eq. (18)::

        var(D_hat) = D^2 [ (6 + 4 eps + 2 eps^2) / n + 4 (1 + eps)^2 / n^2 ],
        eps = sigma^2 / (D dt) - 2 R.

    Parameters
    ----------
    D : float or array_like
        Diffusion coefficient, m^2/s.
    sigma2 : float or array_like
        Localisation variance, m^2.
    dt : float
        Frame interval, s.
    n : int or array_like
        Number of displacements of the track.
    motion_blur : float
        R (1/6 full-frame exposure, 0 instantaneous).

    Returns
    -------
    ndarray or float
        Variance of D_hat, (m^2/s)^2.
    """
    D = np.asarray(D, dtype=float)
    n = np.asarray(n, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = np.asarray(sigma2, dtype=float) / (D * dt) - 2.0 * motion_blur
        v = D**2 * ((6 + 4 * eps + 2 * eps**2) / n + 4 * (1 + eps) ** 2 / n**2)
    return v


def _eps_eigen(n: int):
    k = np.arange(1, n + 1)
    return np.cos(k * np.pi / (n + 1))


def crlb_diffusion(D, sigma, dt, n, motion_blur=0.0, n_tracks=1, dims=1):
    """Cramer-Rao lower bound on the variance of an unbiased estimate of D.

    For Brownian motion observed with Gaussian localisation noise (standard
    deviation ``sigma``) and motion blur ``R``, the ``n`` displacements of a
    track are Gaussian with a tridiagonal Toeplitz covariance
    (Vestergaard et al. 2014): diagonal ``2 D dt (1 - 2R) + 2 sigma^2``,
    off-diagonal ``2 R D dt - sigma^2``. Its eigenvectors do not depend on the
    parameters, so the Fisher information of (D, sigma^2) is a sum over the
    eigenvalues ``l_k = c0 + 2 c1 cos(k pi / (n + 1))``:
    ``I_ij = 1/2 sum_k (d_i l_k)(d_j l_k) / l_k^2``. sigma^2 is treated as
    unknown (estimated jointly). Independent axes and tracks add information.

    Parameters
    ----------
    D : float
        m^2/s.
    sigma : float
        Localisation error (standard deviation), m.
    dt : float
        Frame interval, s.
    n : int
        Displacements per track.
    motion_blur : float
        R.
    n_tracks, dims : int
        Number of independent tracks and of axes pooled.

    Returns
    -------
    float
        Minimal variance of D_hat, (m^2/s)^2.
    """
    R = motion_blur
    c = _eps_eigen(int(n))
    s2 = sigma**2
    lam = 2 * D * dt * (1 - 2 * R) + 2 * s2 + 2 * (2 * R * D * dt - s2) * c
    dD = dt * (2 * (1 - 2 * R) + 4 * R * c)
    ds = 2 - 2 * c
    f = 0.5 * n_tracks * dims
    I = np.array([[np.sum(dD * dD / lam**2), np.sum(dD * ds / lam**2)],
                  [np.sum(dD * ds / lam**2), np.sum(ds * ds / lam**2)]]) * f
    return float(np.linalg.inv(I)[0, 0])


# ---------------------------------------------------------------------------
# numba kernels over ragged, dense-in-time arrays
#
# vals[k, off[p] + (frame - first_frame[p])] holds component k of particle p;
# NaN where the particle is missing (gaps).
# ---------------------------------------------------------------------------

@njit(cache=True)
def _msd_sums_ragged(vals, off, max_lag):
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
def _msd_sums_multi(vals, off, max_lag, fov, flen):
    """Per-component sums of squared displacements (n_p, max_lag, k) and counts (n_p, max_lag).

    A displacement counts where every component is finite at both ends. With
    a field of view (``fov``: the limited coordinates, ``flen``: their
    extents; empty for none) each displacement is weighted by
    :func:`_fov_weight` of the range the track covered from start to end.
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
                    w *= _fov_weight(mx[f] - mn[f], flen[f])
                for k in range(k_c):
                    d = vals[k, j] - vals[k, i]
                    sums[p, lag - 1, k] += w * d * d
                cnts[p, lag - 1] += w
    return sums, cnts


@njit(cache=True, inline="always")
def _fov_weight(extent, length):
    """Inverse probability that a path segment of this extent lies inside a field of this length.

    For particles spread uniformly over the field, a segment spanning
    ``extent`` along an axis is seen whole (and so linked and counted) for a
    fraction ``1 - extent/length`` of its possible positions: long steps are
    lost at the edges more often than short ones, which biases the MSD low
    by about ``1.6 s / L`` (s the step standard deviation). Weighting each
    displacement by the inverse (Horvitz-Thompson) removes that bias. Clamped
    at 10 for segments nearly as long as the field.
    """
    q = 1.0 - extent / length
    return 1.0 / q if q > 0.1 else 10.0


@njit(cache=True)
def _cve_sums_ragged(vals, off, fov, flen):
    """Per particle and component: sum w dx^2, sum w, sum w' dx_n dx_n+1, sum w'.

    Unit weights without a field of view (``fov`` with no rows); else w is
    :func:`_fov_weight` of the extent of the step and w' of the three
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
                        w1 *= _fov_weight(abs(fov[f, i + 1] - fov[f, i]), flen[f])
                    s2 += w1 * d * d
                    n2 += w1
                    if prev == prev:
                        w2 = 1.0
                        for f in range(n_f):
                            u0 = fov[f, i - 1]
                            u1 = fov[f, i]
                            u2 = fov[f, i + 1]
                            w2 *= _fov_weight(max(u0, max(u1, u2)) - min(u0, min(u1, u2)), flen[f])
                        s11 += w2 * d * prev
                        n11 += w2
                prev = d
            out[p, k, 0] = s2
            out[p, k, 1] = n2
            out[p, k, 2] = s11
            out[p, k, 3] = n11
    return out


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


@njit(cache=True)
def _msd_dense(pos, max_lag):
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


# ---------------------------------------------------------------------------
# preparation of a trajectories table
# ---------------------------------------------------------------------------

@dataclass
class _Tracks:
    particles: np.ndarray      # particle ids (n_p,)
    first: np.ndarray          # first frame of each particle (n_p,)
    off: np.ndarray            # offsets into the dense arrays (n_p + 1,)
    comps: dict                # component name -> dense float64 array (total,)
    dt: float                  # frame interval, s
    n_rows: np.ndarray         # rows (positions) per particle

    def stack(self, names):
        return np.ascontiguousarray(np.vstack([self.comps[c] for c in names]))


def _parse_axes(axes) -> tuple:
    if isinstance(axes, str):
        axes = [a.strip() for a in axes.split(",") if a.strip()]
    axes = tuple(axes)
    if not axes:
        raise UserError("no axes given", f"choose from {', '.join(AXES)}")
    for a in axes:
        if a not in AXES:
            raise UserError(f"unknown axis '{a}'", f"choose from {', '.join(AXES)}")
    return axes


def frame_interval(df: pd.DataFrame) -> float:
    """Frame interval (s) of a trajectories table.

    Taken from the ``t`` column (median of dt/dframe between consecutive rows
    of the same particle); from the metadata ``frame_interval`` when no
    particle has two rows.
    """
    f = df["frame"].to_numpy()
    t = df["t"].to_numpy(dtype=float)
    p = df["particle"].to_numpy()
    same = (p[1:] == p[:-1]) & (f[1:] != f[:-1])
    if same.any():
        r = (t[1:] - t[:-1])[same] / (f[1:] - f[:-1])[same]
        dt = float(np.median(r))
    else:
        meta = df.attrs.get("ptrack", {}) or {}
        dt = meta.get("frame_interval")
        if dt is None:
            raise UserError("cannot find the frame interval: no particle has two positions and no 'frame_interval' metadata",
                            "give tracks of at least two frames")
        dt = float(dt)
    if not (math.isfinite(dt) and dt > 0):
        raise UserError(f"frame interval from the 't' column is {dt!r} s", "'t' must increase with 'frame'")
    return dt


def _prepare(df: pd.DataFrame, components, min_rows: int = 2) -> _Tracks:
    for c in ("frame", "particle", "t", *components):
        if c not in df.columns:
            raise UserError(f"trajectories table lacks column '{c}'", "a trajectories table needs frame, t, particle, x, y, z")
    if "z" in components and not np.isfinite(df["z"].to_numpy(dtype=float)).any():
        raise UserError("z axis requested but the table is 2D (z is NaN everywhere)", "use the axes x, y, xy")
    part = df["particle"].to_numpy().astype(np.int64)
    frame = df["frame"].to_numpy().astype(np.int64)
    order = np.lexsort((frame, part))
    if not np.all(order == np.arange(len(order))):
        df = df.iloc[order]
        part = part[order]
        frame = frame[order]
    if len(part) == 0:
        raise UserError("the trajectories table is empty", "track some particles first")
    dt = frame_interval(df)
    starts = np.flatnonzero(np.r_[True, part[1:] != part[:-1]])
    ends = np.r_[starts[1:], len(part)]
    n_rows = ends - starts
    keep = n_rows >= min_rows
    if not keep.any():
        raise UserError(f"every track is shorter than {min_rows} frames (longest: {int(n_rows.max())})",
                        f"give tracks of at least {min_rows} frames")
    first = frame[starts]
    last = frame[ends - 1]
    span = (last - first + 1)
    span = np.where(keep, span, 0)
    off = np.zeros(len(starts) + 1, dtype=np.int64)
    np.cumsum(span, out=off[1:])
    row_p = np.repeat(np.arange(len(starts)), n_rows)
    rows_kept = keep[row_p]
    idx = off[row_p] + frame - first[row_p]
    comps = {}
    for c in components:
        v = np.full(off[-1], np.nan)
        v[idx[rows_kept]] = df[c].to_numpy(dtype=float)[rows_kept]
        comps[c] = v
    sel = np.flatnonzero(keep)
    off_k = np.r_[off[sel], off[-1]].astype(np.int64)
    return _Tracks(particles=part[starts][sel], first=first[sel].astype(np.int64), off=off_k,
                   comps=comps, dt=dt, n_rows=n_rows[sel])


def _components(axes) -> tuple:
    comps = []
    for a in axes:
        for c in AXES[a]:
            if c not in comps:
                comps.append(c)
    return tuple(comps)


# ---------------------------------------------------------------------------
# drift
# ---------------------------------------------------------------------------

def check_motion_blur(motion_blur) -> float:
    """The motion-blur parameter R as a float in [0, 1/4], or a UserError."""
    R = float(motion_blur)
    if not (0.0 <= R <= 0.25):
        raise UserError(f"motion_blur = {motion_blur!r} outside [0, 1/4]", "use 1/6 for full-frame exposure, 0 for instantaneous")
    return R


def _resolve_fov(df: pd.DataFrame, field_of_view) -> dict:
    """Field of view as ``{component: extent (m)}``; empty for none.

    ``field_of_view``: None (no correction), ``"auto"`` (the image: the
    range of the positions in x and y), a sequence of component names (their
    ranges, e.g. ``("x", "y", "z")`` when z is limited by the calibrated
    range and particles leave it), or a dict component -> extent (m) or
    (lo, hi).
    """
    if field_of_view is None:
        return {}
    if isinstance(field_of_view, str) and field_of_view != "auto":
        raise UserError(f"field_of_view = {field_of_view!r}", "give None, 'auto', component names or a dict component -> extent in m")
    if isinstance(field_of_view, str) or (isinstance(field_of_view, (tuple, list))
                                          and all(isinstance(c, str) for c in field_of_view)):
        names = ("x", "y") if isinstance(field_of_view, str) else tuple(field_of_view)
        out = {}
        for c in names:
            if c not in ("x", "y", "z") or c not in df.columns:
                raise UserError(f"field_of_view names {c!r}, not a position column of the table", "use x, y or z")
            v = df[c].to_numpy(dtype=float)
            v = v[np.isfinite(v)]
            if v.size and v.max() > v.min():
                out[c] = float(v.max() - v.min())
        return out
    out = {}
    for c, v in dict(field_of_view).items():
        if c not in ("x", "y", "z"):
            raise UserError(f"field_of_view has component {c!r}", "use x, y or z")
        ext = float(v[1]) - float(v[0]) if isinstance(v, (tuple, list, np.ndarray)) else float(v)
        if not (math.isfinite(ext) and ext > 0):
            raise UserError(f"field_of_view[{c!r}] = {v!r} is not a positive extent", "give the field's size in m")
        out[c] = ext
    return out


def _fov_arrays(tr: _Tracks, fov: dict):
    """(limited coordinates (n_f, total), their extents (n_f,)) for the numba kernels."""
    if not fov:
        return np.empty((0, tr.off[-1])), np.empty(0)
    return tr.stack(list(fov)), np.array(list(fov.values()), dtype=float)


def _step_drift(tr: _Tracks, comps):
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
    comps = _components(_parse_axes(axes))
    tr = _prepare(df, comps)
    f0, M, means = _step_drift(tr, comps)
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


def _drift_corrected(tr: _Tracks, comps) -> _Tracks:
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
    f0, M, means = _step_drift(tr, comps)
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
    return _Tracks(particles=tr.particles, first=tr.first, off=tr.off, comps=new, dt=tr.dt, n_rows=tr.n_rows)


# ---------------------------------------------------------------------------
# MSD tables
# ---------------------------------------------------------------------------

def _default_max_lag(tr: _Tracks, max_lag):
    longest = int(np.diff(tr.off).max()) - 1
    if max_lag is None:
        return max(1, min(DEFAULT_MAX_LAG, longest))
    max_lag = int(max_lag)
    if max_lag < 1:
        raise UserError(f"max_lag = {max_lag} must be at least 1 frame", "give a positive number of frames")
    return max(1, min(max_lag, longest))


def _msd_sums(tr: _Tracks, axes, max_lag, fov=None):
    """axis -> (sums (n_p, L), counts (n_p, L)), weighted for the field of view ``fov`` (:func:`_fov_arrays`).

    One pass over all components when they share their missing values (the
    usual case: a row has x and y, and z if any); else one pass per axis.
    """
    comps = _components(axes)
    fv, fl = fov if fov is not None else _fov_arrays(tr, {})
    nan0 = np.isnan(tr.comps[comps[0]])
    if all(np.array_equal(nan0, np.isnan(tr.comps[c])) for c in comps[1:]):
        sums, cnts = _msd_sums_multi(tr.stack(comps), tr.off, int(max_lag), fv, fl)
        ci = {c: i for i, c in enumerate(comps)}
        return {a: (sums[:, :, [ci[c] for c in AXES[a]]].sum(axis=2), cnts) for a in axes}
    res = {}
    for a in axes:
        sums, cnts = _msd_sums_multi(tr.stack(AXES[a]), tr.off, int(max_lag), fv, fl)
        res[a] = (sums.sum(axis=2), cnts)
    return res


def _lag_sums(df: pd.DataFrame, axes, max_lag, field_of_view=None):
    """Parse ``axes``, prepare the tracks, resolve ``max_lag`` and sum the squared displacements.

    Returns (axes, tracks, L, {axis: (sums (n_p, L), counts (n_p, L))}): the common start of
    :func:`particle_msd` and :func:`ensemble_msd`.
    """
    axes = _parse_axes(axes)
    fov = _resolve_fov(df, field_of_view)
    comps = _components(axes)
    tr = _prepare(df, tuple(dict.fromkeys(comps + tuple(fov))))
    L = _default_max_lag(tr, max_lag)
    return axes, tr, L, _msd_sums(tr, axes, L, _fov_arrays(tr, fov))


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
    axes, tr, L, sums = _lag_sums(df, axes, max_lag)
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


def _ensemble_from_sums(sums, axes, dt, L):
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
    axes, tr, L, sums = _lag_sums(df, axes, max_lag, field_of_view)
    res = _ensemble_from_sums(sums, axes, tr.dt, L)
    res.attrs["frame_interval"] = tr.dt
    return res


# ---------------------------------------------------------------------------
# array fast paths
# ---------------------------------------------------------------------------

def _as_pos3(pos) -> np.ndarray:
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
    p = _as_pos3(pos)
    L = int(max_lag)
    if not 1 <= L <= p.shape[1] - 1:
        raise UserError(f"max_lag = {max_lag} outside 1..{p.shape[1] - 1}", "tracks need more frames than the longest lag")
    return _msd_dense(p, L)


def _cve_from_sums(S2, N2, S11, N11, dt, R):
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
    p = _as_pos3(pos)
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


# ---------------------------------------------------------------------------
# optimal number of lags for the least-squares fit
# ---------------------------------------------------------------------------

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


def _ols_fit(msd, P):
    """Fit msd[lag-1] = a + b lag over lags 1..P; msd may be (..., L)."""
    n = np.arange(1, P + 1, dtype=float)
    y = msd[..., :P]
    nc = n - n.mean()
    b = (y * nc).sum(axis=-1) / np.sum(nc * nc)
    a = y.mean(axis=-1) - b * n.mean()
    return a, b


def _ols_core(msd, n_disp, max_points: int = DEFAULT_MAX_LAG):
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
        a_, b_ = _ols_fit(msd, P)
        eps = float(a_ / b_) if b_ > 0 else 0.0
        P_new, _ = optimal_lags(eps, lengths, weights, Pmax)
        if P_new == P or P_new in seen:
            P = P_new
            break
        seen.add(P)
        P = P_new
    a_, b_ = _ols_fit(msd, P)
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
    p = _as_pos3(pos)
    n_p, n_f, k = p.shape
    L = int(min(max_points, n_f - 1))
    msd = _msd_dense(p, L).mean(axis=0)
    a_, b_, P, rv = _ols_core(msd, np.full(n_p, n_f - 1))
    D = b_ / (2 * k * dt)
    return float(D), float(abs(D) * math.sqrt(rv / k)), int(P)


# ---------------------------------------------------------------------------
# estimate_diffusion
# ---------------------------------------------------------------------------

@dataclass
class DiffusionResult:
    """Diffusion coefficients per axis with errors (all SI).

    Attributes
    ----------
    D, D_err : dict axis -> float
        D (m^2/s) and its standard error; ``se_method`` says which error.
    D_err_model, D_err_boot : dict axis -> float
        Closed-form (model) and bootstrap-over-particles errors (NaN if not
        computed).
    sigma_loc : dict axis -> float
        Localisation error (m, standard deviation per component).
    n_particles, n_displacements : int
        Tracks used and frame-to-frame displacements.
    estimator : str
        ``"cve"`` or ``"ols"``.
    n_lags : dict axis -> int or None
        Lags used by the OLS fit.
    frame_interval, motion_blur : float
    se_method : str
        ``"bootstrap"`` or ``"model"``.
    drift_corrected : bool
    msd : DataFrame
        The ensemble MSD (:func:`ensemble_msd` layout) for plots.
    fit : dict axis -> dict
        ``slope`` (m^2/s), ``offset`` (m^2), ``n_dims``, ``t_max`` (s, end of
        the fitted range) of the model ``MSD = offset + slope t``.
    """

    D: dict
    D_err: dict
    D_err_model: dict
    D_err_boot: dict
    sigma_loc: dict
    n_particles: int
    n_displacements: int
    estimator: str
    n_lags: dict
    frame_interval: float
    motion_blur: float
    se_method: str
    drift_corrected: bool = False
    msd: pd.DataFrame | None = None
    fit: dict = field(default_factory=dict)

    def table(self) -> pd.DataFrame:
        """The seed's Table 4.1 layout, one row: D_<axis> and D_<axis>_err side by side (m^2/s)."""
        row = {}
        for a in self.D:
            row[f"D_{a}"] = self.D[a]
            row[f"D_{a}_err"] = self.D_err[a]
        return pd.DataFrame([row])

    def to_dict(self) -> dict:
        """JSON-ready summary (no MSD table)."""
        f = lambda d: {k: (None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v) for k, v in d.items()}
        return {
            "D": f(self.D), "D_err": f(self.D_err), "D_err_model": f(self.D_err_model),
            "D_err_boot": f(self.D_err_boot), "sigma_loc": f(self.sigma_loc),
            "n_particles": int(self.n_particles), "n_displacements": int(self.n_displacements),
            "estimator": self.estimator, "n_lags": dict(self.n_lags), "frame_interval": self.frame_interval,
            "motion_blur": self.motion_blur, "se_method": self.se_method, "drift_corrected": self.drift_corrected,
            "fit": {a: f(v) for a, v in self.fit.items()},
            "units": {"D": "m^2/s", "sigma_loc": "m", "frame_interval": "s"},
        }


def _boot_weights(n_p, n_boot, rng):
    return rng.multinomial(n_p, np.full(n_p, 1.0 / n_p), size=n_boot).astype(float)


def estimate_diffusion(df: pd.DataFrame, axes=("x", "y", "xy"), estimator: str = "cve", motion_blur: float = 1 / 6,
                       n_boot: int = 200, seed=0, subtract_drift: bool = False, max_lag=None,
                       field_of_view=None) -> DiffusionResult:
    """Diffusion coefficient per axis with standard errors.

    Parameters
    ----------
    df : DataFrame
        Trajectories table (gaps allowed). Tracks need at least 3 frames.
    axes : sequence of str
        Any of ``x, y, z, xy, xz, yz, xyz``; an n-component axis uses
        ``MSD = 2 n D t``.
    estimator : {"cve", "ols"}
        Covariance-based estimator, or least squares over the optimal number
        of lags.
    motion_blur : float
        R in [0, 1/4]: 1/6 for a camera shutter open the whole frame
        (default, measured data), 0 for instantaneous positions (simulations).
        Only the localisation error (and the CVE's error model) depend on it;
        D does not.
    n_boot : int
        Bootstrap resamples of whole particles (0: model errors only).
    seed : int or numpy.random.Generator
        For the bootstrap.
    subtract_drift : bool
        Remove the common drift (per frame step) first, with the (1 - 1/M)
        bias correction.
    max_lag : int, optional
        Longest lag of the stored MSD table (frames).
    field_of_view : None, "auto", component names, or dict component -> extent (m) or (lo, hi)
        The region in which particles can be seen (the image, and in 3D the
        calibrated z range if particles leave it). A particle is tracked only while it stays
        inside, so long displacements near the edges are lost more often
        than short ones and the measured MSD is biased low by about
        ``1.6 s / L`` per limited axis (s the step standard deviation, L the
        extent: -3.4 % for 4 px steps in a 192 px field). With the field
        given, every displacement is weighted by the inverse probability
        that a segment of its extent fits in the field (uniformly spread
        particles), which removes the bias. ``"auto"`` takes the range of the
        positions in x and y (the image); names such as ``("x", "y", "z")``
        take the range of those components. None: no correction
        (simulations without a field).

    Returns
    -------
    DiffusionResult
    """
    axes = _parse_axes(axes)
    estimator = str(estimator).lower()
    if estimator not in ("cve", "ols"):
        raise UserError(f"unknown estimator '{estimator}'", "choose 'cve' or 'ols'")
    R = check_motion_blur(motion_blur)
    n_boot = int(n_boot)
    if n_boot < 0:
        raise UserError(f"n_boot = {n_boot} is negative", "give 0 or a positive number of resamples")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    comps = _components(axes)
    fov = _resolve_fov(df, field_of_view)
    tr = _prepare(df, tuple(dict.fromkeys(comps + tuple(fov))), min_rows=3)
    fv, fl = _fov_arrays(tr, fov)               # positions in the field: before any drift correction
    if subtract_drift:
        tr = _drift_corrected(tr, comps)
    dt = tr.dt
    n_p = len(tr.particles)
    L = _default_max_lag(tr, max_lag)
    cs = _cve_sums_ragged(tr.stack(comps), tr.off, fv, fl)            # (n_p, k, 4)
    ci = {c: i for i, c in enumerate(comps)}
    if np.any(cs[:, :, 3].sum(axis=0) == 0):
        raise UserError("no track has three consecutive frames", "give tracks with at least 3 consecutive positions")
    use_boot = n_boot > 0 and n_p >= MIN_PARTICLES_BOOTSTRAP
    W = _boot_weights(n_p, n_boot, rng) if n_boot > 0 and n_p >= 2 else None
    n_disp = int(cs[:, 0, 1].sum())

    # per-component CVE (used for sigma, eps and the CVE itself)
    comp_D, comp_s2, comp_var, comp_m11 = {}, {}, {}, {}
    for c, i in ci.items():
        S2, N2, S11, N11 = (cs[:, i, j] for j in range(4))
        D, s2 = _cve_from_sums(S2.sum(), N2.sum(), S11.sum(), N11.sum(), dt, R)
        comp_D[c], comp_s2[c] = float(D), float(s2)
        comp_m11[c] = float(S11.sum() / N11.sum())
        v_p = cve_variance(abs(D), max(s2, 0.0), dt, np.maximum(N2, 1), R)
        comp_var[c] = float(np.sum(np.where(N2 > 0, N2**2 * v_p, 0.0)) / N2.sum() ** 2)

    sums = _msd_sums(tr, axes, L, (fv, fl))
    msd_table = _ensemble_from_sums(sums, axes, dt, L)
    res = dict(D={}, D_err={}, D_err_model={}, D_err_boot={}, sigma_loc={}, n_lags={}, fit={})
    for a in axes:
        cc = AXES[a]
        k = len(cc)
        idx = [ci[c] for c in cc]
        res["sigma_loc"][a] = float(math.sqrt(max(np.mean([comp_s2[c] for c in cc]), 0.0)))
        if estimator == "cve":
            D = float(np.mean([comp_D[c] for c in cc]))
            err_model = math.sqrt(sum(comp_var[c] for c in cc)) / k
            boot = np.nan
            if W is not None:
                sub = cs[:, idx, :]                                      # (n_p, k, 4)
                Sb = np.einsum("bp,pkj->bkj", W, sub)
                Db, _ = _cve_from_sums(Sb[..., 0], Sb[..., 1], Sb[..., 2], Sb[..., 3], dt, R)
                boot = float(np.std(Db.mean(axis=1), ddof=1))
            offset = float(-2.0 * sum(comp_m11[c] for c in cc))
            res["n_lags"][a] = None
            res["fit"][a] = {"slope": 2 * k * D, "offset": offset, "n_dims": k, "t_max": None}
        else:
            s, c = sums[a]
            S, C = s.sum(axis=0), c.sum(axis=0)
            with np.errstate(invalid="ignore", divide="ignore"):
                msd = S / C
            avail = int(np.max(np.flatnonzero(C > 0))) + 1 if np.any(C > 0) else 0
            if avail < 2:
                raise UserError(f"axis {a}: fewer than 2 lags available for the least-squares fit",
                                "give longer tracks or use --estimator cve")
            n_d = np.maximum(np.diff(tr.off) - 1, 1)
            a_, b_, P, rv = _ols_core(msd[:avail], n_d)
            D = float(b_ / (2 * k * dt))
            err_model = abs(D) * math.sqrt(rv / k)
            boot = np.nan
            if W is not None:
                Sb = W @ s[:, :P]
                Cb = W @ c[:, :P]
                with np.errstate(invalid="ignore", divide="ignore"):
                    mb = Sb / Cb
                _, bb = _ols_fit(mb, P)
                boot = float(np.nanstd(bb / (2 * k * dt), ddof=1))
            res["n_lags"][a] = int(P)
            res["fit"][a] = {"slope": float(b_ / dt), "offset": float(a_), "n_dims": k, "t_max": float(P * dt)}
            # localisation error from the offset: offset/(2k) = sigma^2 - 2 R D dt
            res["sigma_loc"][a] = float(math.sqrt(max(a_ / (2 * k) + 2 * R * D * dt, 0.0)))
        res["D"][a] = D
        res["D_err_model"][a] = float(err_model)
        res["D_err_boot"][a] = float(boot)
        res["D_err"][a] = float(boot) if use_boot and np.isfinite(boot) else float(err_model)
    out = DiffusionResult(n_particles=n_p, n_displacements=n_disp, estimator=estimator, frame_interval=dt,
                          motion_blur=R, se_method="bootstrap" if use_boot else "model",
                          drift_corrected=bool(subtract_drift), msd=msd_table, **res)
    return out


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
    axes = _parse_axes(axes)
    R = check_motion_blur(motion_blur)
    comps = _components(axes)
    tr = _prepare(df, comps, min_rows=3)
    if subtract_drift:
        tr = _drift_corrected(tr, comps)
    cs = _cve_sums_ragged(tr.stack(comps), tr.off, *_fov_arrays(tr, {}))
    ci = {c: i for i, c in enumerate(comps)}
    out = {"particle": tr.particles, "n_frames": tr.n_rows.astype(np.int64)}
    Dc, vc, sc = {}, {}, {}
    for c, i in ci.items():
        S2, N2, S11, N11 = (cs[:, i, j] for j in range(4))
        D, s2 = _cve_from_sums(S2, N2, S11, N11, tr.dt, R)
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


# ---------------------------------------------------------------------------
# anomalous tracks
# ---------------------------------------------------------------------------

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
    axis = _parse_axes(axes)[0]
    if not (0 < level < 1):
        raise UserError(f"level = {level!r} outside (0, 1)", "give a false-positive rate such as 0.01")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    cc = AXES[axis]
    k = len(cc)
    tr = _prepare(df, cc, min_rows=3)
    if subtract_drift:
        tr = _drift_corrected(tr, cc)
    dt = tr.dt
    cs = _cve_sums_ragged(tr.stack(cc), tr.off, *_fov_arrays(tr, {}))
    tot = cs.sum(axis=0)                                   # (k, 4)
    m2 = tot[:, 0] / tot[:, 1]
    m11 = tot[:, 2] / np.maximum(tot[:, 3], 1)
    Ddt = np.mean(m2 / 2 + m11)                            # D dt per component
    eps = float(np.clip(np.mean(-m11) / Ddt, -0.45, 1e6)) if Ddt > 0 else 0.0
    offset = float(-2.0 * np.sum(m11))
    spans = np.diff(tr.off)
    n_frames = tr.n_rows
    Lmax = int(_n_alpha_lags(spans.max()))
    s, c = _msd_sums_ragged(tr.stack(cc), tr.off, Lmax)
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
        mn = _msd_dense(np.ascontiguousarray(pos), nl)      # units D dt = 1
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


# ---------------------------------------------------------------------------
# synthetic tracks (for validation and benchmarks)
# ---------------------------------------------------------------------------

def brownian_tracks(n_particles: int, n_frames: int, D: float, dt: float, sigma: float = 0.0,
                    motion_blur: float = 0.0, n_dims: int = 1, seed=0) -> np.ndarray:
    """Observed positions of free Brownian particles with localisation noise and motion blur.

    Exact in distribution: the observed displacements of Brownian motion
    averaged over the exposure (blur R) plus independent Gaussian noise
    (standard deviation ``sigma``) form a Gaussian moving-average process of
    order 1 with variance ``2 D dt (1 - 2R) + 2 sigma^2`` and lag-1 covariance
    ``2 R D dt - sigma^2`` (Vestergaard et al. 2014); they are drawn as such.

    Parameters
    ----------
    n_particles, n_frames : int
    D : float
        m^2/s.
    dt : float
        Frame interval, s.
    sigma : float
        Localisation error, m.
    motion_blur : float
        R in [0, 1/6] (1/6: shutter open the whole frame).
    n_dims : int
        Independent components.
    seed : int or Generator

    Returns
    -------
    ndarray
        ``(n_particles, n_frames)`` if ``n_dims == 1`` else
        ``(n_particles, n_frames, n_dims)``, m; tracks start near 0.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    R = float(motion_blur)
    if not 0 <= R <= 1 / 6 + 1e-12:
        raise UserError(f"motion_blur = {motion_blur!r} outside [0, 1/6]", "use 0 (instantaneous) .. 1/6 (full-frame exposure)")
    c0 = 2 * D * dt * (1 - 2 * R) + 2 * sigma**2
    c1 = 2 * R * D * dt - sigma**2
    p_ = math.sqrt(max(c0 + 2 * c1, 0.0))
    m_ = math.sqrt(max(c0 - 2 * c1, 0.0))
    a, b = (p_ + m_) / 2, (p_ - m_) / 2
    z = rng.standard_normal((n_particles, n_frames, n_dims))
    d = a * z[:, 1:, :] + b * z[:, :-1, :]
    pos = np.empty((n_particles, n_frames, n_dims))
    # first observation: a (blurred) position plus its noise: offset b z_0 keeps the MA structure exact
    pos[:, 0, :] = b * z[:, 0, :]
    np.cumsum(d, axis=1, out=pos[:, 1:, :])
    pos[:, 1:, :] += pos[:, :1, :]
    return pos[:, :, 0] if n_dims == 1 else pos


# ---------------------------------------------------------------------------
# plot
# ---------------------------------------------------------------------------

def brownian_field(n_frames: int, size: float, density: float, D: float, dt: float, sigma: float = 0.0,
                   drift=(0.0, 0.0), seed=0) -> pd.DataFrame:
    """What a camera sees of free Brownian particles: a trajectories table of those inside a square view.

    Particles start uniformly over a periodic box wider than the view by six
    step lengths on each side (so the density in view stays uniform) and
    enter and leave the view as in a real experiment; a particle keeps its id
    when it comes back. Positions carry Gaussian localisation noise.

    Parameters
    ----------
    n_frames : int
    size : float
        Side of the view [0, size)^2, m.
    density : float
        Particles per m^2.
    D : float
        m^2/s.
    dt : float
        Frame interval, s.
    sigma : float
        Localisation error per axis, m (also written as ``sigma_x``, ``sigma_y``).
    drift : (vx, vy)
        m/s.
    seed : int or numpy.random.Generator

    Returns
    -------
    DataFrame
        Trajectories table (``frame``, ``t``, ``particle``, ``x``, ``y``, ``sigma_x``, ``sigma_y``).
    """
    from .table import make_table

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    s = math.sqrt(2 * D * dt)
    margin = 6 * s
    Lb = size + 2 * margin
    X = rng.uniform(0, Lb, (rng.poisson(density * Lb * Lb), 2))
    fr, pa, xs, ys = [], [], [], []
    for f in range(n_frames):
        if f:
            X = np.mod(X + s * rng.standard_normal(X.shape) + np.asarray(drift, float) * dt, Lb)
        Y = X - margin
        ok = np.flatnonzero(np.all((Y >= 0) & (Y < size), axis=1))
        fr.append(np.full(ok.size, f))
        pa.append(ok)
        xs.append(Y[ok, 0] + sigma * rng.standard_normal(ok.size))
        ys.append(Y[ok, 1] + sigma * rng.standard_normal(ok.size))
    fr, pa = np.concatenate(fr), np.concatenate(pa)
    n = len(fr)
    return make_table(fr, fr * dt, pa, np.concatenate(xs), np.concatenate(ys), meta={"frame_interval": dt},
                      sigma_x=np.full(n, float(sigma)), sigma_y=np.full(n, float(sigma)))


def plot_msd(result, path, title: str | None = None):
    """Log-log ensemble MSD per axis with the fitted model, written as PNG.

    Parameters
    ----------
    result : DiffusionResult or DataFrame
        A result (MSD and fit drawn) or an :func:`ensemble_msd` table.
    path : path-like
        Output PNG (written atomically).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .errors import atomic_output

    if isinstance(result, DiffusionResult):
        msd, fit = result.msd, result.fit
    else:
        msd, fit = result, {}
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=120)
    t = msd["t"].to_numpy()
    for i, col in enumerate(c for c in msd.columns if c.startswith("msd_")):
        a = col[4:]
        y = msd[col].to_numpy()
        good = np.isfinite(y) & (y > 0)
        color = f"C{i}"
        se = msd[f"se_{a}"].to_numpy() if f"se_{a}" in msd.columns else np.full(len(y), np.nan)
        if np.isfinite(se[good]).any():
            ax.errorbar(t[good], y[good] * 1e12, yerr=np.nan_to_num(se[good]) * 1e12, fmt="o", ms=3,
                        color=color, elinewidth=0.7, label=f"MSD {a} (+- SE)")
            ax.set_xscale("log")
            ax.set_yscale("log")
        else:
            ax.loglog(t[good], y[good] * 1e12, "o", ms=3, color=color, label=f"MSD {a}")
        if a in fit:
            f = fit[a]
            tt = np.geomspace(t[0], t[-1], 100)
            model = f["offset"] + f["slope"] * tt
            D = f["slope"] / (2 * f["n_dims"])
            lab = f"fit {a}: D = {D * 1e12:.4g} um^2/s"
            ax.loglog(tt[model > 0], model[model > 0] * 1e12, "-", color=color, lw=1, label=lab)
            if f.get("t_max"):
                ax.axvline(f["t_max"], color=color, ls=":", lw=0.8)
    ax.set_xlabel("lag time t (s)")
    ax.set_ylabel("MSD (um^2)")
    if title:
        ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_output(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------
# linking-free D: the self part of the displacement distribution of all pairs
# ---------------------------------------------------------------------------

@dataclass
class PairDiffusionResult:
    """Linking-free diffusion coefficients (all SI), from :func:`pair_diffusion`.

    Attributes
    ----------
    D, D_err : dict axis -> float
        D (m^2/s) and its jackknife standard error (over blocks of frames).
    sigma_loc : dict axis -> float
        Localisation error (m per component) from the offset of the
        displacement variance against lag, with the motion-blur term removed.
    drift_velocity : dict component -> float
        Common drift (m/s): the mean displacement per lag, fitted through the origin.
    lags : DataFrame
        One row per lag: ``lag`` (frames), ``s2_<c>`` and ``s2_<c>_err``
        (variance of the one-particle displacement along component c, m^2),
        ``mu_<c>``, ``mu_<c>_err`` (mean, m), ``window_<c>`` (cut-off, m),
        ``alpha`` (fraction of particles found again), ``unmatched_density``
        (particles not explained by any of the previous frame, per m^d),
        ``n_targets``, ``n_pairs``.
    window : dict component -> float
        Cut-off at lag 1 (m); every lag's is in ``lags``.
    link_ambiguity : float
        Expected fraction of frame-to-frame steps for which another particle
        lies closer to a particle's old position than the particle itself
        (from the measured density and D): when this is more than a few
        percent, D from linked tracks is biased low and this estimate is the
        one to use.
    frame_interval, motion_blur : float
    n_blocks : int
        Jackknife blocks.
    offset_used : str
        ``"sigma"`` (intercept from the localiser's sigma and R: the precise
        estimate) or ``"fit"`` (intercept fitted; also when the two disagree,
        which points to a wrong motion-blur R or sigma).
    intercept, intercept_err : dict component -> float
        Fitted intercept of the step variance against lag,
        ``2 sigma^2 - 4 R D dt`` (m^2), and its jackknife error: a check on R.
    """

    D: dict
    D_err: dict
    sigma_loc: dict
    drift_velocity: dict
    lags: pd.DataFrame
    window: dict
    link_ambiguity: float
    frame_interval: float
    motion_blur: float
    n_blocks: int
    offset_used: str = "fit"
    intercept: dict = field(default_factory=dict)
    intercept_err: dict = field(default_factory=dict)


class _LagPairs:
    """Everything one lag's likelihood needs, positions scaled by the cut-off ``c`` (per component).

    ``u``: displacement target - source of every (target, source) pair closer
    than the cut-off along every axis; ``tgt``: the pair's target index;
    ``n_tgt``: targets (inside the inner box); ``src``: every source position
    relative to its frame's inner box (lo, hi per source, scaled);
    ``area``: total inner-box area over the frame pairs (scaled);
    ``tgt_frame``, ``src_frame``, ``pair_frame``: source frame of each, for the jackknife.
    """

    def __init__(self, u, tgt, n_tgt, src_lo, src_hi, area_per_frame, tgt_frame, src_frame):
        self.u, self.tgt, self.n_tgt = u, tgt, n_tgt
        self.src_lo, self.src_hi = src_lo, src_hi
        self.area_per_frame = area_per_frame
        self.tgt_frame, self.src_frame = tgt_frame, src_frame
        self.n_frames = len(np.unique(tgt_frame)) if len(tgt_frame) else 0
        self.log_rho0 = math.log(0.01 * max(n_tgt, 1) / max(area_per_frame * max(self.n_frames, 1), 1e-300))

    def subset(self, keep_frame):
        """The same lag without the frame pairs whose source frame fails ``keep_frame`` (a function of frames)."""
        kt = keep_frame(self.tgt_frame)
        new_idx = np.cumsum(kt) - 1
        kp = kt[self.tgt]
        ks = keep_frame(self.src_frame)
        out = _LagPairs(self.u[kp], new_idx[self.tgt[kp]], int(kt.sum()), self.src_lo[ks], self.src_hi[ks],
                        self.area_per_frame, self.tgt_frame[kt], self.src_frame[ks])
        out.n_frames = len(np.unique(self.src_frame[ks]))
        out.log_rho0 = self.log_rho0
        return out


#: log rho (scaled units) standing for "no unmatched particles": exp(-40) ~ 4e-18 per box
LOG_RHO_OFF = -40.0


def _pair_nll(theta, lp: _LagPairs, prior: bool = True):
    """Negative log-likelihood of one lag's targets given its sources, and its gradient.

    The particles of frame f + k inside the inner box are a Poisson process
    with intensity ``alpha sum_j N(y - x_j - mu; s^2) + rho`` over the
    particles x_j of frame f: each particle is found again (probability
    alpha) displaced by a Gaussian step, and rho collects particles not seen
    in frame f. No particle is assigned to another: every source within the
    cut-off contributes, weighted by its Gaussian. The intensity is the exact
    expected density for independent particles, so the estimate is
    consistent (a composite likelihood: the one-to-one nature of the real
    assignment only changes the error, which is taken from a jackknife).
    ``theta = (log alpha, log rho, mu_1..d, log s_1..d)`` in scaled units.
    """
    from scipy.special import ndtr

    d = lp.u.shape[1]
    alpha, rho = math.exp(theta[0]), math.exp(theta[1])
    mu, s = theta[2:2 + d], np.exp(theta[2 + d:])
    z = (lp.u - mu) / s
    g = alpha * np.exp(-0.5 * np.sum(z * z, axis=1)) / np.prod(s * math.sqrt(2 * math.pi))
    lam = np.bincount(lp.tgt, weights=g, minlength=lp.n_tgt) + rho
    # expected number of targets: sources' Gaussians inside the inner box, plus rho times its area
    hi, lo = (lp.src_hi - mu) / s, (lp.src_lo - mu) / s
    Pa = np.maximum(ndtr(hi) - ndtr(lo), 1e-300)
    P = np.prod(Pa, axis=1)
    area = lp.area_per_frame * lp.n_frames
    # a weak prior on log rho (sd 5 around 1 % of the target density): when every target has a
    # source, rho -> 0 is otherwise a flat direction of the likelihood
    pr = (theta[1] - lp.log_rho0) / 5.0 if prior else 0.0
    nll = -float(np.sum(np.log(lam))) + alpha * float(P.sum()) + rho * area + 0.5 * pr * pr
    r = g / lam[lp.tgt]                                     # responsibility of each pair
    phi = lambda x: np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi)  # noqa: E731
    grad = np.empty_like(theta)
    grad[0] = -float(r.sum()) + alpha * float(P.sum())
    grad[1] = -float(np.sum(rho / lam)) + rho * area + pr / 5.0
    w = alpha * P[:, None] / Pa
    grad[2:2 + d] = -(r @ (z / s)) + np.sum(w * (phi(lo) - phi(hi)) / s, axis=0)
    grad[2 + d:] = -(r @ (z * z - 1)) + np.sum(w * (phi(lo) * lo - phi(hi) * hi), axis=0)
    return nll, grad


def _free(theta, rho_free: bool) -> np.ndarray:
    """Indices of the fitted parameters: all, or all but log rho (held at :data:`LOG_RHO_OFF`)."""
    return np.arange(theta.size) if rho_free else np.r_[0, 2:theta.size]


def _fit_pairs(lp: _LagPairs, theta0, hess_inv=None, rho_free: bool = True):
    """Maximum-likelihood parameters of one lag (BFGS from ``theta0``; ``hess_inv``: a starting inverse Hessian
    of the fitted parameters). With ``rho_free=False`` there are no unmatched particles (rho held at ~0)."""
    from scipy.optimize import minimize

    idx = _free(theta0, rho_free)
    base = np.array(theta0, float)
    if not rho_free:
        base[1] = LOG_RHO_OFF

    def fun(t):
        full = base.copy()
        full[idx] = t
        v, g = _pair_nll(full, lp, prior=rho_free)
        return v, g[idx]

    # BFGS: L-BFGS-B's Fortran step costs milliseconds per call here, more than the likelihood
    opts = {"maxiter": 400, "gtol": 1e-6}
    if hess_inv is not None:
        opts["hess_inv0"] = hess_inv
    try:
        r = minimize(fun, base[idx], jac=True, method="BFGS", options=opts)
    except ValueError:              # starting inverse Hessian not positive definite
        opts.pop("hess_inv0", None)
        r = minimize(fun, base[idx], jac=True, method="BFGS", options=opts)
    out = base.copy()
    out[idx] = r.x
    return out


def _pair_cov(theta, lp: _LagPairs, rho_free: bool = True):
    """(Covariance of all parameters (zero rows for a held rho), inverse Hessian of the fitted ones or None)."""
    idx = _free(theta, rho_free)
    h = 1e-5
    H = np.empty((idx.size, idx.size))
    for a, k in enumerate(idx):
        e = np.zeros_like(theta)
        e[k] = h
        H[a] = (_pair_nll(theta + e, lp, prior=rho_free)[1] - _pair_nll(theta - e, lp, prior=rho_free)[1])[idx] / (2 * h)
    inv = np.linalg.pinv(0.5 * (H + H.T))
    inv = 0.5 * (inv + inv.T)
    cov = np.zeros((theta.size, theta.size))
    cov[np.ix_(idx, idx)] = inv
    return cov, (inv if np.all(np.linalg.eigvalsh(inv) > 0) else None)


def _frame_positions(df, comps):
    f = df["frame"].to_numpy().astype(np.int64)
    order = np.argsort(f, kind="stable")
    f = f[order]
    X = np.column_stack([df[c].to_numpy(dtype=float)[order] for c in comps])
    ok = np.all(np.isfinite(X), axis=1)
    f, X = f[ok], X[ok]
    frames = np.unique(f)
    starts = np.searchsorted(f, frames)
    ends = np.r_[starts[1:], len(f)]
    return {int(fr): X[a:b] for fr, a, b in zip(frames, starts, ends)}


def _gather_pairs(pos, lag, cutoff, lo, hi, shift=None) -> _LagPairs:
    """(target, source) pairs whose displacement is within ``cutoff`` of ``shift`` per axis, frames f -> f + lag.

    Targets are the particles of f + lag whose whole source region (target
    minus shift, plus or minus the cut-off) lies inside the field, so every
    particle that can have moved to them was in the field; sources are all
    particles of f. ``shift`` (m): the expected drift over the lag, so that
    the cut-off is centred on the peak of the displacements.
    """
    from scipy.spatial import cKDTree

    c = np.asarray(cutoff, float)
    sh = np.zeros_like(c) if shift is None else np.asarray(shift, float)
    # targets whose whole source region (target - shift +- cut-off) lies inside the field
    t_lo, t_hi = np.maximum(lo + c + sh, lo), np.minimum(hi - c + sh, hi)
    ilo, ihi = t_lo / c, t_hi / c
    us, tg, slo, shi, tfr, sfr = [], [], [], [], [], []
    n_t = 0
    for f, S in pos.items():
        T = pos.get(f + lag)
        if T is None or len(S) == 0:
            continue
        T = T[np.all((T >= t_lo) & (T <= t_hi), axis=1)] / c
        S = S / c
        Sq = S if shift is None else S + np.asarray(shift, float) / c
        slo.append(ilo - S)
        shi.append(ihi - S)
        sfr.append(np.full(len(S), f, np.int64))
        tfr.append(np.full(len(T), f, np.int64))
        if len(T):
            m = cKDTree(T).sparse_distance_matrix(cKDTree(Sq), 1.0, p=np.inf, output_type="coo_matrix")
            us.append(T[m.row] - S[m.col])
            tg.append(m.row + n_t)
        n_t += len(T)
    d = len(c)
    cat = lambda a, shape: np.concatenate(a) if a else np.empty(shape)  # noqa: E731
    return _LagPairs(cat(us, (0, d)), cat(tg, (0,)).astype(np.int64), n_t, cat(slo, (0, d)), cat(shi, (0, d)),
                     float(np.prod(ihi - ilo)), cat(tfr, (0,)).astype(np.int64), cat(sfr, (0,)).astype(np.int64))


def _lag_line(k, s2, var, dt):
    """Weighted least squares of ``s2 = 2 D dt k + c`` over the lags k; returns (D, c)."""
    w = 1.0 / var
    A = np.column_stack([2 * dt * k, np.ones_like(k, dtype=float)])
    coef = np.linalg.solve(A.T @ (A * w[:, None]), A.T @ (w * s2))
    return float(coef[0]), float(coef[1])


def pair_diffusion(df: pd.DataFrame, axes=("x", "y", "xy"), max_lag: int = 3, motion_blur: float = 1 / 6,
                   frame_interval_s: float | None = None, window: float | None = None, n_blocks: int = 20,
                   bounds: dict | None = None, offset="auto", jackknife: str = "one-step") -> PairDiffusionResult:
    """Diffusion coefficients without linking: the positions of frame f + k explained by those of frame f.

    For every lag k = 1..``max_lag`` (frames), the particles found in frame
    f + k are modelled as a Poisson process whose intensity is a sum of
    Gaussians, one on every particle of frame f (shifted by the drift, width
    ``2 D k dt + 2 sigma^2 - 4 R D dt`` per axis), weighted by the fraction
    alpha of particles found again, plus a small uniform density of particles
    not seen in frame f. That intensity is the exact expected density for
    independently moving particles, so its maximum-likelihood fit gives the
    step variance and drift per lag with no particle assigned to another:
    near neighbours share a target according to their Gaussians instead of
    one of them taking it. D is then the slope of the variance against lag
    (localisation error and motion blur in the intercept, or the intercept
    taken from the localiser's sigma: see ``offset``). The idea is the
    pair-correlation analysis of Semrau & Schmidt (Biophys. J. 92, 613 (2007),
    "PICS"); conditioning on the actual particles of frame f instead of
    assuming a uniform background removes the bias from the clustering of one
    slowly changing configuration and makes the estimate nearly as precise
    as from perfectly linked tracks (bench/bench_pair_diffusion.py).

    Why: when particles move a fair fraction of their spacing per frame,
    linking (even the optimal assignment) swaps the identities of close
    particles and shortens the steps, which biases D from tracks low (see
    ``link_ambiguity``); this estimate has no links to get wrong. Only
    targets whose possible sources all lie in the field are used, so it has
    no field-of-view bias either. Assumes the particles move independently
    (dilute suspension); the standard error is a jackknife over blocks of
    frames.

    Parameters
    ----------
    df : DataFrame
        Localisations with ``frame`` and positions (m) ``x``, ``y`` (and
        ``z``); the ``particle`` column, if any, is ignored. A trajectories
        table or the localiser's output (converted to m) both work.
    axes : sequence of str
        Any of ``x, y, z, xy, xz, yz, xyz``.
    max_lag : int
        Longest lag (frames) in the fit; at least 2.
    motion_blur : float
        R in [0, 1/4] (1/6 full-frame exposure, 0 instantaneous); only the
        localisation error depends on it.
    frame_interval_s : float, optional
        s; default from the ``t`` column or the ``frame_interval`` metadata.
    window : float, optional
        Cut-off (m, every component): sources farther than this from a
        target (after the drift) are ignored; default 5 step standard
        deviations of each lag (found by a first pass).
    n_blocks : int
        Contiguous blocks of frames for the jackknife standard error.
    bounds : dict component -> (lo, hi), optional
        Field of view (m); default the range of the positions. Only
        particles at least one cut-off inside it are explained, so that every
        particle that can have moved to them was in the field.
    offset : {"auto", "fit", "sigma"}
        The localisation variance in ``s2 = 2 D dt (k - 2R) + 2 sigma^2``:
        ``"fit"`` fits the intercept (no assumption; needs the slope over
        lags, so the error is larger); ``"sigma"`` takes sigma^2 per
        component as the mean of the localiser's per-particle variance
        (columns ``sigma_x``, ``sigma_y``, ``sigma_z`` in m) and the given R,
        and fits D alone from every lag (far more precise; a wrong sigma
        shifts D by ``delta(sigma^2) / ((1 - 2R) dt)``, a wrong R by
        ``2 delta(R) / (1 - 2R)``); ``"auto"``: ``"sigma"`` when the columns
        are there and the intercept they imply agrees with the fitted one
        within 4 standard errors, else ``"fit"`` (``offset_used`` says
        which).

    jackknife : {"one-step", "refit"}
        Each block-deleted fit as one Newton step from the full fit (fast;
        same errors within a few per cent in bench/bench_pair_diffusion.py)
        or refitted.

    Returns
    -------
    PairDiffusionResult
    """
    axes = _parse_axes(axes)
    comps = _components(axes)
    if jackknife not in ("one-step", "refit"):
        raise UserError(f"jackknife = {jackknife!r}", "choose one-step or refit")
    for c in ("frame", *comps):
        if c not in df.columns:
            raise UserError(f"localisation table lacks column '{c}'", "give frame and the position columns (m)")
    if "z" in comps and not np.isfinite(df["z"].to_numpy(dtype=float)).any():
        raise UserError("z axis requested but the table is 2D (z is NaN everywhere)", "use the axes x, y, xy")
    R = check_motion_blur(motion_blur)
    max_lag = int(max_lag)
    if max_lag < 2:
        raise UserError(f"max_lag = {max_lag}", "give at least 2 lags (the slope of variance against lag is D)")
    if frame_interval_s is None:
        if "t" in df.columns and df["frame"].nunique() > 1:
            ft = df.groupby("frame")["t"].first()
            dt = float(np.median(np.diff(ft.to_numpy(float)) / np.diff(ft.index.to_numpy())))
        else:
            meta = df.attrs.get("ptrack", {}) or {}
            if meta.get("frame_interval") is None:
                raise UserError("no frame interval: the table has no t column and no 'frame_interval' metadata",
                                "pass frame_interval_s")
            dt = float(meta["frame_interval"])
    else:
        dt = float(frame_interval_s)
    if not (math.isfinite(dt) and dt > 0):
        raise UserError(f"frame interval = {dt!r} s", "give a positive frame interval")
    pos = _frame_positions(df, comps)
    if len(pos) < max_lag + 2:
        raise UserError(f"{len(pos)} frames with localisations", f"give at least {max_lag + 2} frames")
    allX = np.concatenate(list(pos.values()))
    lo, hi = allX.min(axis=0), allX.max(axis=0)
    if bounds is not None:
        lo = np.array([bounds[c][0] if c in bounds else lo[i] for i, c in enumerate(comps)], float)
        hi = np.array([bounds[c][1] if c in bounds else hi[i] for i, c in enumerate(comps)], float)
    span = hi - lo
    if np.any(span <= 0):
        raise UserError("the localisations do not span the field of view in every axis", "check the positions")
    d = len(comps)
    n_loc = np.mean([len(v) for v in pos.values()])
    density = n_loc / float(np.prod(span))

    def fit_lag(k, cut, shift=None, theta0=None):
        lp = _gather_pairs(pos, k, cut, lo, hi, shift)
        if lp.n_tgt < 20 or len(lp.u) < 20:
            raise UserError(f"lag {k}: only {lp.n_tgt} particles inside the field of view at one cut-off "
                            f"({cut.max() * 1e6:.3g} um) from its edges",
                            "give a larger field of view, more frames, or a smaller window")
        if theta0 is None:
            mu0 = np.zeros(d) if shift is None else np.asarray(shift) / cut
            theta0 = np.r_[math.log(0.95), math.log(0.05 * lp.n_tgt / (lp.area_per_frame * lp.n_frames)),
                           mu0, np.full(d, math.log(0.2))]
        return _fit_pairs(lp, theta0), lp

    # Each lag gets its own cut-off, 5 step standard deviations: beyond it a source's Gaussian is
    # negligible. The step size of lag 1 comes from a first fit with a cut-off of 1.5 particle
    # spacings; that of lag k from lag k - 1 (s^2 grows about as k).
    spacing = density ** (-1.0 / d)
    rows, thetas, data, wins, covs, free = [], [], [], [], [], []
    for k in range(1, max_lag + 1):
        if k == 1:
            # first pass: where the peak is (drift) and how wide
            w1 = np.minimum(np.full(d, 1.5 * spacing), span / 3.5) if window is None else \
                np.full(d, check_window(window, span))
            # (twice: the first cut-off is a guess from the spacing; a cut-off is at most a third of
            # the field, so that targets one cut-off inside it remain)
            shift = None
            for _pass in range(2):
                th, _lp = fit_lag(k, w1, shift)
                shift = th[2:2 + d] * w1
                w1 = np.minimum(np.full(d, 5.0 * float(np.max(np.exp(th[2 + d:]) * w1))), span / 3.0)
            win = w1
        else:
            s_prev = max(math.sqrt(rows[-1][f"s2_{c}"]) for c in comps)
            win = np.minimum(np.full(d, 5.0 * s_prev * math.sqrt(k / (k - 1))), span / 3.0)
            shift = np.array([rows[-1][f"mu_{c}"] for c in comps]) * k / (k - 1)
        if window is not None:
            win = np.full(d, check_window(window, span))
        th, lp = fit_lag(k, win, shift)
        # Unmatched particles (rho) are kept only if the data ask for them (likelihood ratio above
        # the 5 % point of the boundary chi-bar^2, 2.71): with every particle detected, a free
        # rho >= 0 sits on its boundary, takes the far tail of the steps and biases s^2 low by up
        # to ~1 %.
        th0 = _fit_pairs(lp, th, rho_free=False)
        rho_free = 2 * (_pair_nll(th0, lp, prior=False)[0] - _pair_nll(th, lp, prior=False)[0]) > 2.71
        if not rho_free:
            th = th0
        cov, h_inv = _pair_cov(th, lp, rho_free)
        covs.append(h_inv)
        free.append(rho_free)
        sd = np.exp(th[2 + d:]) * win
        row = {"lag": k, "alpha": math.exp(th[0]),
               "unmatched_density": math.exp(th[1]) / float(np.prod(win)) if rho_free else 0.0,
               "n_targets": lp.n_tgt, "n_pairs": len(lp.u)}
        for i, c in enumerate(comps):
            row[f"s2_{c}"] = sd[i] ** 2
            row[f"s2_{c}_err"] = 2 * sd[i] ** 2 * math.sqrt(max(cov[2 + d + i, 2 + d + i], 0.0))
            row[f"mu_{c}"] = th[2 + i] * win[i]
            row[f"mu_{c}_err"] = win[i] * math.sqrt(max(cov[2 + i, 2 + i], 0.0))
            row[f"window_{c}"] = win[i]
        rows.append(row)
        thetas.append(th)
        data.append(lp)
        wins.append(win)
    lags = pd.DataFrame(rows)
    kk = lags["lag"].to_numpy(float)
    offsets = _pair_offsets(df, comps, offset, R)
    var = {c: lags[f"s2_{c}_err"].to_numpy() ** 2 for c in comps}

    def estimates(s2_by_comp, known):
        """Per component (D, intercept): the intercept fitted, or taken from the localiser's sigma and R."""
        Dc, cc = {}, {}
        for c in comps:
            if known is None:
                Dc[c], cc[c] = _lag_line(kk, s2_by_comp[c], var[c], dt)
            else:
                # known localisation variance: s2_k - 2 sigma^2 = 2 D dt (k - 2R); weighted mean over lags
                x = 2 * dt * (kk - 2 * R)
                w = x * x / var[c]
                Dc[c] = float(np.sum(w * (s2_by_comp[c] - known[c]) / x) / np.sum(w))
                cc[c] = float(known[c] - 4 * R * Dc[c] * dt)
        return Dc, cc

    s2_all = {c: lags[f"s2_{c}"].to_numpy() for c in comps}
    fitted = estimates(s2_all, None)
    known = estimates(s2_all, offsets) if offsets is not None else None

    # jackknife over contiguous blocks of source frames (displacements of nearby frames are correlated)
    frames_all = np.array(sorted(pos))
    n_blocks = int(min(max(n_blocks, 2), len(frames_all)))
    blocks = np.array_split(frames_all, n_blocks)
    jack = {"fit": {c: [] for c in comps}, "known": {c: [] for c in comps}, "c": {c: [] for c in comps}}
    for blk in blocks:
        b0, b1 = blk[0], blk[-1]
        s2j = {c: np.empty(max_lag) for c in comps}
        for j, (th, lp) in enumerate(zip(thetas, data)):
            if jackknife == "refit" or covs[j] is None:
                # warm start: the full fit and its inverse Hessian
                thj = _fit_pairs(lp.subset(lambda f: (f < b0) | (f > b1)), th, covs[j], rho_free=free[j])
            else:
                # one Newton step from the full fit: the likelihood without the block has gradient
                # -g_block there and Hessian ~ H (1 - share of the block)
                inblk = lp.subset(lambda f: (f >= b0) & (f <= b1))
                idx = _free(th, free[j])
                g_b = _pair_nll(th, inblk, prior=False)[1][idx]
                share = inblk.n_tgt / max(lp.n_tgt, 1)
                thj = th.copy()
                thj[idx] = th[idx] + covs[j] @ g_b / max(1.0 - share, 0.5)
            for i, c in enumerate(comps):
                s2j[c][j] = (math.exp(thj[2 + d + i]) * wins[j][i]) ** 2
        Df, cf = estimates(s2j, None)
        Dk, _ = estimates(s2j, offsets) if offsets is not None else (Df, None)
        for c in comps:
            jack["fit"][c].append(Df[c])
            jack["known"][c].append(Dk[c])
            jack["c"][c].append(cf[c])
    n = len(blocks)

    def jk_se(vals):
        v = np.asarray(vals)
        return float(math.sqrt((n - 1) / n * np.sum((v - v.mean()) ** 2)))

    # The localiser's sigma makes D far more precise, but the intercept it implies,
    # 2 sigma^2 - 4 R D dt, hangs on the motion-blur R: a wrong R (e.g. 1/6 for a movie without
    # blur) shifts D by 2R/(1-2R). Use it only where the fitted intercept agrees within 4
    # jackknife SE (the jackknife understates the intercept's error by ~1.5x on 80-frame movies:
    # at 2.5 SE one movie in six fell back to the imprecise fit for nothing).
    offset_used = "fit"
    if known is not None:
        agree = offset == "sigma" or all(abs(fitted[1][c] - known[1][c]) <= 4.0 * jk_se(jack["c"][c]) for c in comps)
        offset_used = "sigma" if agree else "fit (the localiser's sigma with this motion blur R disagrees)"
    Dc, cc = known if offset_used == "sigma" else fitted
    Derr_c = {c: np.asarray(jack["known" if offset_used == "sigma" else "fit"][c]) for c in comps}

    res_D, res_err, res_sig = {}, {}, {}
    for a in axes:
        cs = AXES[a]
        res_D[a] = float(np.mean([Dc[c] for c in cs]))
        jj = np.mean([Derr_c[c] for c in cs], axis=0)
        res_err[a] = float(math.sqrt((n - 1) / n * np.sum((jj - jj.mean()) ** 2)))
        # intercept = 2 sigma^2 - 4 R D dt per component
        res_sig[a] = float(math.sqrt(max(np.mean([(cc[c] + 4 * R * Dc[c] * dt) / 2 for c in cs]), 0.0)))
    # drift: mu_k = v k dt (no intercept: localisation noise has zero mean), weighted through the origin
    mu1 = {}
    for c in comps:
        tk, w = kk * dt, 1.0 / np.maximum(lags[f"mu_{c}_err"].to_numpy(), 1e-300) ** 2
        mu1[c] = float(np.sum(w * tk * lags[f"mu_{c}"].to_numpy()) / np.sum(w * tk * tk))
    D_plane = float(np.mean([Dc[c] for c in comps[:2]]))
    # P(another particle nearer than the partner) for a Poisson field in the plane and Gaussian steps
    plane_density = n_loc / float(np.prod(span[:2]))
    x = 2 * math.pi * plane_density * 2 * max(D_plane, 0.0) * dt
    ambiguity = x / (1 + x)
    return PairDiffusionResult(D=res_D, D_err=res_err, sigma_loc=res_sig, drift_velocity=mu1, lags=lags,
                               window={c: float(w) for c, w in zip(comps, wins[0])}, link_ambiguity=float(ambiguity),
                               frame_interval=dt, motion_blur=R, n_blocks=n, offset_used=offset_used,
                               intercept={c: float(fitted[1][c]) for c in comps},
                               intercept_err={c: jk_se(jack["c"][c]) for c in comps})


def _pair_offsets(df, comps, offset, R):
    """2 sigma^2 per component from the localiser's ``sigma_<c>`` columns, or None to fit the intercept."""
    if offset not in ("auto", "fit", "sigma"):
        raise UserError(f"offset = {offset!r}", "choose auto, fit or sigma")
    have = all(f"sigma_{c}" in df.columns for c in comps)
    if offset == "fit" or (offset == "auto" and not have):
        return None
    if not have:
        missing = [f"sigma_{c}" for c in comps if f"sigma_{c}" not in df.columns]
        raise UserError(f"offset = 'sigma' but the table lacks {', '.join(missing)}", "use offset = 'fit'")
    out = {}
    for c in comps:
        v = df[f"sigma_{c}"].to_numpy(dtype=float)
        v = v[np.isfinite(v)]
        if v.size == 0:
            raise UserError(f"column sigma_{c} has no finite value", "use offset = 'fit'")
        out[c] = float(2 * np.mean(v * v))
    return out


def check_window(window, span) -> float:
    """Validate a pair-search window half-width (m) against the field of view."""
    w = float(window)
    if not (math.isfinite(w) and w > 0):
        raise UserError(f"window = {window!r}", "give a positive window half-width in m")
    if np.any(2 * w >= np.asarray(span)):
        raise UserError(f"window = {w:g} m is half the field of view or more", "give a smaller window")
    return w
