"""Linking-free D: the positions of frame f + k explained by those of frame f (no particle assigned to another)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..errors import UserError
from .tracks import AXES, axis_components, check_motion_blur, frame_interval, parse_axes


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
        R in [0, 1/4) (:func:`ptrack.motion.tracks.check_motion_blur`; 1/6 full-frame exposure, 0 instantaneous); only the
        localisation error depends on it.
    frame_interval_s : float, optional
        s; default :func:`ptrack.motion.tracks.frame_interval` (the one rule).
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
    axes = parse_axes(axes)
    comps = axis_components(axes)
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
    dt = frame_interval(df) if frame_interval_s is None else float(frame_interval_s)
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
    n_loc = np.mean([len(v) for v in pos.values()])
    fits = _fit_all_lags(pos, comps, lo, hi, max_lag, window, n_loc / float(np.prod(span)))
    lags = pd.DataFrame([f.row for f in fits])
    kk = lags["lag"].to_numpy(float)
    offsets = _pair_offsets(df, comps, offset, R)
    var = {c: lags[f"s2_{c}_err"].to_numpy() ** 2 for c in comps}
    s2_all = {c: lags[f"s2_{c}"].to_numpy() for c in comps}
    fitted = _lag_estimates(kk, s2_all, var, None, dt, R)
    known = _lag_estimates(kk, s2_all, var, offsets, dt, R) if offsets is not None else None
    jack, n = _jackknife(sorted(pos), fits, comps, kk, var, offsets, dt, R, n_blocks, jackknife)

    # The localiser's sigma makes D far more precise, but the intercept it implies,
    # 2 sigma^2 - 4 R D dt, hangs on the motion-blur R: a wrong R (e.g. 1/6 for a movie without
    # blur) shifts D by 2R/(1-2R). Use it only where the fitted intercept agrees within 4
    # jackknife SE (the jackknife understates the intercept's error by ~1.5x on 80-frame movies:
    # at 2.5 SE one movie in six fell back to the imprecise fit for nothing).
    offset_used = "fit"
    if known is not None:
        agree = offset == "sigma" or all(abs(fitted[1][c] - known[1][c]) <= 4.0 * _jk_se(jack["c"][c]) for c in comps)
        offset_used = "sigma" if agree else "fit (the localiser's sigma with this motion blur R disagrees)"
    Dc, cc = known if offset_used == "sigma" else fitted
    Derr_c = {c: np.asarray(jack["known" if offset_used == "sigma" else "fit"][c]) for c in comps}

    res_D, res_err, res_sig = {}, {}, {}
    for a in axes:
        cs = AXES[a]
        res_D[a] = float(np.mean([Dc[c] for c in cs]))
        res_err[a] = _jk_se(np.mean([Derr_c[c] for c in cs], axis=0))
        # intercept = 2 sigma^2 - 4 R D dt per component
        res_sig[a] = float(math.sqrt(max(np.mean([(cc[c] + 4 * R * Dc[c] * dt) / 2 for c in cs]), 0.0)))
    # drift: mu_k = v k dt (no intercept: localisation noise has zero mean), weighted through the origin
    mu1 = {}
    for c in comps:
        tk, w = kk * dt, 1.0 / np.maximum(lags[f"mu_{c}_err"].to_numpy(), 1e-300) ** 2
        mu1[c] = float(np.sum(w * tk * lags[f"mu_{c}"].to_numpy()) / np.sum(w * tk * tk))
    # P(another particle nearer than the partner) for a Poisson field in the plane and Gaussian steps
    D_plane = float(np.mean([Dc[c] for c in comps[:2]]))
    x = 2 * math.pi * n_loc / float(np.prod(span[:2])) * 2 * max(D_plane, 0.0) * dt
    return PairDiffusionResult(D=res_D, D_err=res_err, sigma_loc=res_sig, drift_velocity=mu1, lags=lags,
                               window={c: float(w) for c, w in zip(comps, fits[0].win)}, link_ambiguity=float(x / (1 + x)),
                               frame_interval=dt, motion_blur=R, n_blocks=n, offset_used=offset_used,
                               intercept={c: float(fitted[1][c]) for c in comps},
                               intercept_err={c: _jk_se(jack["c"][c]) for c in comps})


@dataclass
class _LagFit:
    """One lag's maximum-likelihood fit: parameters, data, cut-off, inverse Hessian, rho fitted or held."""

    theta: np.ndarray
    data: _LagPairs
    win: np.ndarray
    h_inv: np.ndarray | None
    rho_free: bool
    row: dict


def _fit_lag(pos, k, cut, lo, hi, shift=None):
    """Maximum-likelihood parameters of lag ``k`` at cut-off ``cut`` (per component), and its pairs."""
    lp = _gather_pairs(pos, k, cut, lo, hi, shift)
    if lp.n_tgt < 20 or len(lp.u) < 20:
        raise UserError(f"lag {k}: only {lp.n_tgt} particles inside the field of view at one cut-off "
                        f"({cut.max() * 1e6:.3g} µm) from its edges",
                        "give a larger field of view, more frames, or a smaller window")
    d = len(cut)
    mu0 = np.zeros(d) if shift is None else np.asarray(shift) / cut
    theta0 = np.r_[math.log(0.95), math.log(0.05 * lp.n_tgt / (lp.area_per_frame * lp.n_frames)),
                   mu0, np.full(d, math.log(0.2))]
    return _fit_pairs(lp, theta0), lp


def _fit_all_lags(pos, comps, lo, hi, max_lag, window, density) -> list:
    """:class:`_LagFit` of every lag 1..max_lag.

    Each lag gets its own cut-off, 5 step standard deviations: beyond it a
    source's Gaussian is negligible. The step size of lag 1 comes from a
    first fit with a cut-off of 1.5 particle spacings; that of lag k from
    lag k - 1 (s^2 grows about as k). A cut-off is at most a third of the
    field, so that targets one cut-off inside it remain.
    """
    d = len(comps)
    span = hi - lo
    spacing = density ** (-1.0 / d)
    fits = []
    for k in range(1, max_lag + 1):
        if k == 1:
            # first pass (twice: the first cut-off is a guess from the spacing): where the peak is (drift), how wide
            w1 = np.minimum(np.full(d, 1.5 * spacing), span / 3.5) if window is None else \
                np.full(d, check_window(window, span))
            shift = None
            for _pass in range(2):
                th, _lp = _fit_lag(pos, k, w1, lo, hi, shift)
                shift = th[2:2 + d] * w1
                w1 = np.minimum(np.full(d, 5.0 * float(np.max(np.exp(th[2 + d:]) * w1))), span / 3.0)
            win = w1
        else:
            prev = fits[-1].row
            s_prev = max(math.sqrt(prev[f"s2_{c}"]) for c in comps)
            win = np.minimum(np.full(d, 5.0 * s_prev * math.sqrt(k / (k - 1))), span / 3.0)
            shift = np.array([prev[f"mu_{c}"] for c in comps]) * k / (k - 1)
        if window is not None:
            win = np.full(d, check_window(window, span))
        th, lp = _fit_lag(pos, k, win, lo, hi, shift)
        # Unmatched particles (rho) are kept only if the data ask for them (likelihood ratio above
        # the 5 % point of the boundary chi-bar^2, 2.71): with every particle detected, a free
        # rho >= 0 sits on its boundary, takes the far tail of the steps and biases s^2 low by up
        # to ~1 %.
        th0 = _fit_pairs(lp, th, rho_free=False)
        rho_free = 2 * (_pair_nll(th0, lp, prior=False)[0] - _pair_nll(th, lp, prior=False)[0]) > 2.71
        if not rho_free:
            th = th0
        cov, h_inv = _pair_cov(th, lp, rho_free)
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
        fits.append(_LagFit(th, lp, win, h_inv, rho_free, row))
    return fits


def _lag_estimates(kk, s2_by_comp, var, known, dt, R):
    """Per component (D, intercept) from the step variances of the lags ``kk``.

    ``known`` None: weighted line ``s2 = 2 D dt k + c``; else ``known[c]`` is
    the localisation term 2 sigma^2: ``s2_k - 2 sigma^2 = 2 D dt (k - 2R)``,
    a weighted mean over the lags.
    """
    Dc, cc = {}, {}
    for c, s2 in s2_by_comp.items():
        if known is None:
            Dc[c], cc[c] = _lag_line(kk, s2, var[c], dt)
        else:
            x = 2 * dt * (kk - 2 * R)
            w = x * x / var[c]
            Dc[c] = float(np.sum(w * (s2 - known[c]) / x) / np.sum(w))
            cc[c] = float(known[c] - 4 * R * Dc[c] * dt)
    return Dc, cc


def _jackknife(frames_all, fits, comps, kk, var, offsets, dt, R, n_blocks, method):
    """Block-deleted D (intercept fitted, and from the localiser's sigma) and intercepts, per component.

    Blocks are contiguous runs of source frames (displacements of nearby
    frames are correlated). ``method`` "one-step": each block-deleted fit is
    one Newton step from the full fit (the likelihood without the block has
    gradient -g_block there and Hessian ~ H (1 - share of the block));
    "refit": refitted from the full fit and its inverse Hessian.
    """
    frames_all = np.asarray(frames_all)
    n_blocks = int(min(max(n_blocks, 2), len(frames_all)))
    blocks = np.array_split(frames_all, n_blocks)
    d = len(comps)
    jack = {"fit": {c: [] for c in comps}, "known": {c: [] for c in comps}, "c": {c: [] for c in comps}}
    for blk in blocks:
        b0, b1 = blk[0], blk[-1]
        s2j = {c: np.empty(len(fits)) for c in comps}
        for j, f in enumerate(fits):
            th = f.theta
            if method == "refit" or f.h_inv is None:
                thj = _fit_pairs(f.data.subset(lambda fr: (fr < b0) | (fr > b1)), th, f.h_inv, rho_free=f.rho_free)
            else:
                inblk = f.data.subset(lambda fr: (fr >= b0) & (fr <= b1))
                idx = _free(th, f.rho_free)
                g_b = _pair_nll(th, inblk, prior=False)[1][idx]
                share = inblk.n_tgt / max(f.data.n_tgt, 1)
                thj = th.copy()
                thj[idx] = th[idx] + f.h_inv @ g_b / max(1.0 - share, 0.5)
            for i, c in enumerate(comps):
                s2j[c][j] = (math.exp(thj[2 + d + i]) * f.win[i]) ** 2
        Df, cf = _lag_estimates(kk, s2j, var, None, dt, R)
        Dk, _ = _lag_estimates(kk, s2j, var, offsets, dt, R) if offsets is not None else (Df, None)
        for c in comps:
            jack["fit"][c].append(Df[c])
            jack["known"][c].append(Dk[c])
            jack["c"][c].append(cf[c])
    return jack, len(blocks)


def _jk_se(vals) -> float:
    """Jackknife standard error of the block-deleted estimates ``vals``."""
    v = np.asarray(vals, float)
    n = len(v)
    return float(math.sqrt((n - 1) / n * np.sum((v - v.mean()) ** 2)))


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

