"""Experiment against simulation: compare trajectories tables with statistics over whole particles.

:func:`compare_tables` compares two (or more, each against the first)
trajectories tables, measured, simulated or the truth of a rendered movie,
quantity by quantity and axis by axis:

``msd``
    Ensemble MSD (:func:`ptrack.msd.particle_msd`) at common lag times in
    seconds, with 95 % particle-bootstrap bands. Test: the mean over lags of
    log(MSD_A / MSD_B), each lag weighted by its inverse bootstrap variance;
    effect: its exponential minus 1.
``D``
    D per axis with its particle-bootstrap error (:func:`ptrack.msd.estimate_diffusion`).
    Test: Wald t on log(D_A / D_B) (Student's t with the smaller table's
    particles - 1 degrees of freedom, as for every Wald test here); effect: D_A / D_B - 1.
``D_distribution``
    Per-particle CVE D (:func:`ptrack.msd.particle_diffusion`, tracks of at
    least ``min_frames``). Test: two-sample Kolmogorov-Smirnov over
    particles (independent units); effect: ratio of medians - 1.
``van_hove``
    Step distributions at several lags (s). Test: Kolmogorov-Smirnov
    distance of the pooled steps, p-value by permutation of whole particles
    between the tables; effect: ratio of RMS steps - 1.
``alpha2``
    Non-Gaussian parameter ``<dx^4> / (3 <dx^2>^2) - 1`` at the same lags.
    Test: particle-bootstrap Wald z on the difference; effect: the difference.
``drift``
    Ensemble drift per axis (:func:`ptrack.velocity.particle_velocity`,
    :func:`ptrack.velocity.ensemble_velocity`, bootstrap over particles).
    Test: Wald z; effect: v_A - v_B (m/s).
``v_vs_height``
    (both 3D) drift against height (:func:`ptrack.velocity.velocity_profile`)
    in common bins. Test: chi-square of the bin differences over the number of
    bins, against F(bins, particles - 1); effect: the
    error-weighted mean difference (m/s).
``height``
    (both 3D) distribution of z. Test: Kolmogorov-Smirnov distance, p by
    permutation of whole particles; effect: difference of medians (m).
``deposition``
    (both with a ``deposited`` or ``contact`` column) fraction of particles
    deposited against time. Test: log-rank on the particles' deposition
    times (censored at their last frame); effect: difference of the final
    fractions.

Why whole particles: the steps of one track are correlated (shared D,
height, size, localisation noise), so resampling single steps makes errors
about 2x too small. Every interval and every p-value here resamples or
permutes particles. The p-values of one comparison are corrected together by
Holm's step-down method; a quantity is "differs" when its corrected p-value
is below ``level``, "consistent" otherwise, and "insufficient" (never
"consistent") when either table has fewer than ``min_particles`` particles
(or too few steps) for it.
"""
from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from .errors import UserError, atomic_output

from .motion.tracks import COMPONENTS  # noqa: F401  (re-exported: the coordinate columns, one definition)

__all__ = ["compare_tables", "holm", "write_report", "plot_comparison", "COMPONENTS"]

MIN_PARTICLES = 5          # fewer particles than this in a table: "insufficient"
MIN_STEPS = 50             # fewer steps (per table) at a lag: "insufficient"
Z95 = 1.959963984540054


# --------------------------------------------------------------------------- small statistics
def holm(p) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error control), NaN left as NaN."""
    p = np.asarray(p, dtype=float)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    if ok.size == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    m = order.size
    adj = np.maximum.accumulate((m - np.arange(m)) * p[order])
    out[order] = np.minimum(adj, 1.0)
    return out


def _df(n_a: int, n_b: int) -> int:
    """Degrees of freedom of a particle-bootstrap Wald statistic: the smaller table's particles - 1.

    A bootstrap standard error from n particles is itself uncertain; referring z to Student's t with
    n - 1 degrees of freedom (as a Welch test with the smaller sample would) keeps the false-positive
    rate near the level for the 15-30 tracks of a small movie, where the normal reference was liberal
    (bench/bench_compare.py).
    """
    return max(int(min(n_a, n_b)) - 1, 1)


def _tq(df: int) -> float:
    """Two-sided 95 % quantile of Student's t."""
    return float(stats.t.ppf(0.975, df))


def _wald_p(diff: float, se: float, df: int | None = None) -> float:
    if not (np.isfinite(diff) and np.isfinite(se)) or se <= 0:
        return float("nan")
    z = abs(diff) / se
    return float(2 * (stats.t.sf(z, df) if df else stats.norm.sf(z)))


def _boot_weights(n: int, n_boot: int, rng) -> np.ndarray:
    """(n_boot, n) multinomial counts: resamples of whole particles."""
    return rng.multinomial(n, np.full(n, 1.0 / n), size=n_boot).astype(float)


def _perm_masks(n_a: int, n_b: int, n_perm: int, rng) -> np.ndarray:
    """(n_perm, n_a + n_b) booleans: True = particle assigned to A in a random relabelling."""
    lab = np.r_[np.ones(n_a, bool), np.zeros(n_b, bool)]
    return rng.permuted(np.tile(lab, (n_perm, 1)), axis=1)


def _ks_from_hist(ha: np.ndarray, hb: np.ndarray) -> np.ndarray:
    """KS distance between the distributions given by histograms (..., bins)."""
    ca = np.cumsum(ha, axis=-1)
    cb = np.cumsum(hb, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.max(np.abs(ca / ca[..., -1:] - cb / cb[..., -1:]), axis=-1)


def _perm_ks(HA: np.ndarray, HB: np.ndarray, n_perm: int, rng) -> tuple[float, float]:
    """KS distance of pooled per-particle histograms and its p-value by permuting particles.

    HA, HB: (n_particles, bins) counts of each particle's values in common bins.
    """
    obs = float(_ks_from_hist(HA.sum(0), HB.sum(0)))
    H = np.vstack([HA, HB])
    M = _perm_masks(len(HA), len(HB), n_perm, rng).astype(float)
    tot = H.sum(0)
    pa = M @ H
    perm = _ks_from_hist(pa, tot[None, :] - pa)
    p = (1.0 + np.sum(perm >= obs - 1e-12)) / (1.0 + n_perm)
    return obs, float(p)


def _hist_per_particle(values: np.ndarray, pid: np.ndarray, n_p: int, edges: np.ndarray) -> np.ndarray:
    """(n_p, bins) counts; values outside the edges go to the end bins (the tails still count)."""
    b = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    H = np.zeros((n_p, len(edges) - 1))
    np.add.at(H, (pid, b), 1.0)
    return H


# --------------------------------------------------------------------------- table preparation
class _Table:
    """A trajectories table with what every quantity needs (sorted, particle index, frame interval)."""

    def __init__(self, df: pd.DataFrame, name: str, motion_blur: float):
        from .motion.velocity import default_axes
        from .msd import frame_interval
        from .table import validate

        df = validate(df, source=name)
        self.name = name
        self.df = df.sort_values(["particle", "frame"], kind="stable").reset_index(drop=True)
        self.dt = frame_interval(self.df)
        self.motion_blur = motion_blur
        # x, y and z when z changes: the one rule of the analysed axes (ptrack.motion.velocity.default_axes), so a
        # 2D table with z = 0 in every row is compared as 2D
        self.comps = default_axes(self.df)
        self.n_particles = int(self.df["particle"].nunique())
        self.dep_col = next((c for c in ("deposited", "contact") if c in self.df.columns), None)

    def steps(self, k: int, comp: str):
        """Displacements of ``comp`` over exactly ``k`` frames: (values, particle index 0..n-1, n_particles)."""
        a = self.df[["particle", "frame", comp]].dropna()
        b = a.assign(frame=a["frame"] - k)
        m = a.merge(b, on=["particle", "frame"], suffixes=("", "_end"))
        d = (m[f"{comp}_end"] - m[comp]).to_numpy(float)
        codes, uniq = pd.factorize(m["particle"])
        return d, codes.astype(np.int64), len(uniq)

    def summary(self) -> dict:
        f = self.df["frame"].to_numpy()
        return {"name": self.name, "n_particles": self.n_particles, "n_rows": int(len(self.df)),
                "frame_interval_s": self.dt, "n_frames": int(f.max() - f.min() + 1) if len(f) else 0,
                "components": list(self.comps), "deposited_column": self.dep_col}


def _lag_times(A: _Table, B: _Table, n_lags: int = 12) -> np.ndarray:
    """Common lag times (s): multiples of the coarser frame interval, log-spaced, up to half a typical track."""
    dt = max(A.dt, B.dt)
    dur = []
    for T in (A, B):
        g = T.df.groupby("particle")["t"]
        dur.append(float(np.percentile(g.max() - g.min(), 75)) if T.n_particles else 0.0)
    t_max = 0.5 * min(dur)
    k_max = max(int(t_max / dt), 1)
    ks = np.unique(np.round(np.geomspace(1, k_max, min(n_lags, k_max))).astype(int))
    return ks * dt


def _msd_arrays(T: _Table, axis: str, taus: np.ndarray):
    """Per-particle MSD sums S (n_p, n_tau) and counts C at lag times ``taus`` (linear in lag between frames)."""
    from .msd import particle_msd

    kf = taus / T.dt
    L = int(np.ceil(kf.max() - 1e-9))
    pm = particle_msd(T.df, axes=(axis,), max_lag=L)
    parts = np.unique(T.df["particle"].to_numpy())
    pi = np.searchsorted(parts, pm["particle"].to_numpy())
    lag = pm["lag"].to_numpy()
    s = np.zeros((len(parts), L + 1))
    c = np.zeros((len(parts), L + 1))
    n = pm[f"n_{axis}"].to_numpy(float)
    s[pi, lag] = pm[f"msd_{axis}"].to_numpy(float) * n
    c[pi, lag] = n
    lo = np.clip(np.floor(kf + 1e-9).astype(int), 1, L)
    hi = np.clip(lo + 1, 1, L)
    w = np.clip(kf - lo, 0.0, 1.0)
    S = s[:, lo] * (1 - w) + s[:, hi] * w
    C = c[:, lo] * (1 - w) + c[:, hi] * w
    keep = C.sum(1) > 0
    return S[keep], C[keep]


# --------------------------------------------------------------------------- result records
def _record(quantity, axis, test, values_a, values_b, effect_name, effect, ci, p, unit_effect, lag_s=None,
            statistic=None, reason=None, extra=None) -> dict:
    r = {"quantity": quantity, "axis": axis, "lag_s": lag_s, "test": test, "a": values_a, "b": values_b,
         "effect": {"name": effect_name, "value": effect, "ci_low": ci[0], "ci_high": ci[1], "unit": unit_effect},
         "statistic": statistic, "p_value": p, "p_holm": None, "verdict": "insufficient" if reason else None,
         "reason": reason}
    if extra:
        r.update(extra)
    return r


def _insufficient(quantity, axis, test, reason, lag_s=None, unit="1", effect_name="") -> dict:
    return _record(quantity, axis, test, None, None, effect_name, None, (None, None), None, unit, lag_s=lag_s,
                   reason=reason)


def _few(A: _Table, B: _Table, n_a: int, n_b: int, what: str, min_particles: int):
    if n_a < min_particles or n_b < min_particles:
        return (f"{what}: {n_a} particles in {A.name} and {n_b} in {B.name}; "
                f"at least {min_particles} each are needed")
    return None


# --------------------------------------------------------------------------- the quantities
def _q_msd(A, B, axis, taus, n_boot, rng, min_particles, curves):
    test = "particle bootstrap, Wald t on the inverse-variance weighted mean log MSD ratio over lags"
    SA, CA = _msd_arrays(A, axis, taus)
    SB, CB = _msd_arrays(B, axis, taus)
    why = _few(A, B, len(SA), len(SB), "MSD", min_particles)
    if why:
        return _insufficient("msd", axis, test, why, effect_name="MSD_A/MSD_B - 1")
    with np.errstate(invalid="ignore", divide="ignore"):
        ma = SA.sum(0) / CA.sum(0)
        mb = SB.sum(0) / CB.sum(0)
        WA = _boot_weights(len(SA), n_boot, rng)
        WB = _boot_weights(len(SB), n_boot, rng)
        ba = (WA @ SA) / (WA @ CA)
        bb = (WB @ SB) / (WB @ CB)
    ok = np.isfinite(ma) & np.isfinite(mb) & (ma > 0) & (mb > 0) & np.all(ba > 0, 0) & np.all(bb > 0, 0)
    if ok.sum() < 1:
        return _insufficient("msd", axis, test, "no lag with a positive MSD in both tables",
                             effect_name="MSD_A/MSD_B - 1")
    # the lags' log ratios are strongly correlated: weight each by its inverse bootstrap variance (the
    # short lags, which carry most of the information), then take the bootstrap error of the weighted mean
    lr_boot = np.log(ba[:, ok]) - np.log(bb[:, ok])
    w = 1.0 / np.maximum(np.var(lr_boot, axis=0, ddof=1), 1e-300)
    w /= w.sum()
    stat = float(np.log(ma[ok] / mb[ok]) @ w)
    se = float(np.std(lr_boot @ w, ddof=1))
    curves[f"msd_{axis}"] = {
        "t_s": taus.tolist(), "a": ma.tolist(), "b": mb.tolist(),
        "a_lo": np.percentile(ba, 2.5, 0).tolist(), "a_hi": np.percentile(ba, 97.5, 0).tolist(),
        "b_lo": np.percentile(bb, 2.5, 0).tolist(), "b_hi": np.percentile(bb, 97.5, 0).tolist(), "unit": "m^2"}
    df = _df(len(SA), len(SB))
    q = _tq(df)
    return _record("msd", axis, test, {"msd_first_lag": float(ma[0]), "n_particles": len(SA)},
                   {"msd_first_lag": float(mb[0]), "n_particles": len(SB)}, "MSD_A/MSD_B - 1",
                   math.expm1(stat), (math.expm1(stat - q * se), math.expm1(stat + q * se)), _wald_p(stat, se, df), "1",
                   statistic=stat, extra={"lags_s": taus[ok].tolist()})


def _q_D(A, B, axis, resA, resB, min_particles):
    test = "Wald t on log(D_A/D_B) (dof: particles - 1), errors by particle bootstrap"
    why = _few(A, B, resA.n_particles if resA else 0, resB.n_particles if resB else 0, "D", min_particles)
    if why:
        return _insufficient("D", axis, test, why, unit="1", effect_name="D_A/D_B - 1")
    da, ea, db, eb = resA.D[axis], resA.D_err[axis], resB.D[axis], resB.D_err[axis]
    if not (da > 0 and db > 0 and np.isfinite(ea) and np.isfinite(eb)):
        return _insufficient("D", axis, test, f"D not positive or without error (A {da:.3g}, B {db:.3g} m^2/s)",
                             effect_name="D_A/D_B - 1")
    lr = math.log(da / db)
    se = math.hypot(ea / da, eb / db)
    df = _df(resA.n_particles, resB.n_particles)
    q = _tq(df)
    return _record("D", axis, test, {"D": da, "D_err": ea, "n_particles": resA.n_particles},
                   {"D": db, "D_err": eb, "n_particles": resB.n_particles}, "D_A/D_B - 1", math.expm1(lr),
                   (math.expm1(lr - q * se), math.expm1(lr + q * se)), _wald_p(lr, se, df), "1", statistic=lr / se)


def _q_D_distribution(A, B, axis, perA, perB, n_boot, rng, min_particles, curves):
    test = "two-sample Kolmogorov-Smirnov over particles (per-particle CVE D)"
    da = perA[f"D_{axis}"].to_numpy(float) if perA is not None else np.zeros(0)
    db = perB[f"D_{axis}"].to_numpy(float) if perB is not None else np.zeros(0)
    da, db = da[np.isfinite(da)], db[np.isfinite(db)]
    why = _few(A, B, len(da), len(db), "per-particle D", min_particles)
    if why:
        return _insufficient("D_distribution", axis, test, why, effect_name="median ratio - 1")
    ks = stats.ks_2samp(da, db)
    ma, mb = float(np.median(da)), float(np.median(db))
    ia = rng.integers(0, len(da), (n_boot, len(da)))
    ib = rng.integers(0, len(db), (n_boot, len(db)))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.median(da[ia], 1) / np.median(db[ib], 1) - 1
    eff = ma / mb - 1 if mb > 0 else float("nan")
    curves[f"D_distribution_{axis}"] = {"a": da.tolist(), "b": db.tolist(), "unit": "m^2/s"}
    return _record("D_distribution", axis, test, {"median": ma, "iqr": float(np.subtract(*np.percentile(da, [75, 25]))),
                                                  "n_particles": len(da)},
                   {"median": mb, "iqr": float(np.subtract(*np.percentile(db, [75, 25]))), "n_particles": len(db)},
                   "median ratio - 1", eff, tuple(float(v) for v in np.nanpercentile(r, [2.5, 97.5])),
                   float(ks.pvalue), "1", statistic=float(ks.statistic))


def _q_van_hove(A, B, comp, tau, n_boot, n_perm, rng, min_particles, curves):
    ka, kb = int(round(tau / A.dt)), int(round(tau / B.dt))
    test_vh = "Kolmogorov-Smirnov distance of the step distributions, permutation of whole particles"
    test_a2 = "particle bootstrap, Wald t on the difference of alpha_2"
    out = []
    if abs(ka * A.dt - tau) > 0.01 * tau or abs(kb * B.dt - tau) > 0.01 * tau:
        why = f"lag {tau:.4g} s is not a whole number of frames in both tables"
        return [_insufficient("van_hove", comp, test_vh, why, lag_s=tau),
                _insufficient("alpha2", comp, test_a2, why, lag_s=tau)]
    sa, pa, na = A.steps(ka, comp)
    sb, pb, nb = B.steps(kb, comp)
    why = _few(A, B, na, nb, "van Hove", min_particles)
    if not why and (len(sa) < MIN_STEPS or len(sb) < MIN_STEPS):
        why = f"van Hove: {len(sa)} and {len(sb)} steps; at least {MIN_STEPS} each are needed"
    if why:
        return [_insufficient("van_hove", comp, test_vh, why, lag_s=tau, effect_name="RMS ratio - 1"),
                _insufficient("alpha2", comp, test_a2, why, lag_s=tau, effect_name="alpha2_A - alpha2_B")]
    # van Hove: common bins over the pooled steps (tails go to the end bins)
    pooled = np.r_[sa, sb]
    s = float(np.sqrt(np.mean(pooled ** 2)))
    edges = np.linspace(-5 * s, 5 * s, 61)
    HA = _hist_per_particle(sa, pa, na, edges)
    HB = _hist_per_particle(sb, pb, nb, edges)
    ks, p = _perm_ks(HA, HB, n_perm, rng)
    # per-particle moments for the RMS ratio and alpha_2
    m2a, m4a, ca = (np.bincount(pa, w, na) for w in (sa ** 2, sa ** 4, np.ones_like(sa)))
    m2b, m4b, cb = (np.bincount(pb, w, nb) for w in (sb ** 2, sb ** 4, np.ones_like(sb)))
    WA, WB = _boot_weights(na, n_boot, rng), _boot_weights(nb, n_boot, rng)

    def rms_a2(m2, m4, c, W=None):
        if W is None:
            M2, M4, C = m2.sum(), m4.sum(), c.sum()
        else:
            M2, M4, C = W @ m2, W @ m4, W @ c
        return np.sqrt(M2 / C), C * M4 / (3 * M2 ** 2) - 1

    ra, a2a = rms_a2(m2a, m4a, ca)
    rb, a2b = rms_a2(m2b, m4b, cb)
    rba, a2ba = rms_a2(m2a, m4a, ca, WA)
    rbb, a2bb = rms_a2(m2b, m4b, cb, WB)
    rr = rba / rbb - 1
    centres = 0.5 * (edges[1:] + edges[:-1])
    width = edges[1] - edges[0]
    curves[f"van_hove_{comp}_{tau:.4g}"] = {"lag_s": tau, "step_centres": centres.tolist(),
                                            "a_density": (HA.sum(0) / len(sa) / width).tolist(),
                                            "b_density": (HB.sum(0) / len(sb) / width).tolist(), "unit": "1/m"}
    out.append(_record("van_hove", comp, test_vh, {"rms_step": float(ra), "n_steps": len(sa), "n_particles": na},
                       {"rms_step": float(rb), "n_steps": len(sb), "n_particles": nb}, "RMS ratio - 1",
                       float(ra / rb - 1), tuple(float(v) for v in np.percentile(rr, [2.5, 97.5])), p, "1",
                       lag_s=tau, statistic=ks))
    d = float(a2a - a2b)
    se = float(np.std(a2ba - a2bb, ddof=1))
    out.append(_record("alpha2", comp, test_a2, {"alpha2": float(a2a), "alpha2_se": float(np.std(a2ba, ddof=1))},
                       {"alpha2": float(a2b), "alpha2_se": float(np.std(a2bb, ddof=1))}, "alpha2_A - alpha2_B", d,
                       (d - _tq(_df(na, nb)) * se, d + _tq(_df(na, nb)) * se), _wald_p(d, se, _df(na, nb)), "1",
                       lag_s=tau,
                       statistic=d / se if se > 0 else None))
    return out


def _velocities(T: _Table, comps, n_boot, seed):
    from .velocity import ensemble_velocity, particle_velocity

    try:
        vel = particle_velocity(T.df, axes=comps, motion_blur=T.motion_blur)
        ens = ensemble_velocity(vel, axes=comps, n_boot=n_boot, seed=seed)
    except UserError:
        return None
    return {r.axis: r for r in ens.itertuples()}


def _q_drift(A, B, comp, ea, eb, min_particles):
    test = "Wald t on v_A - v_B, errors by particle bootstrap (GLS per track)"
    na = int(ea[comp].n_particles) if ea and comp in ea else 0
    nb = int(eb[comp].n_particles) if eb and comp in eb else 0
    why = _few(A, B, na, nb, "drift", min_particles)
    if why:
        return _insufficient("drift", comp, test, why, unit="m/s", effect_name="v_A - v_B")
    ra, rb = ea[comp], eb[comp]
    d = float(ra.v - rb.v)
    se = math.hypot(ra.v_err, rb.v_err)
    return _record("drift", comp, test, {"v": float(ra.v), "v_err": float(ra.v_err), "n_particles": na},
                   {"v": float(rb.v), "v_err": float(rb.v_err), "n_particles": nb}, "v_A - v_B", d,
                   (d - _tq(_df(na, nb)) * se, d + _tq(_df(na, nb)) * se), _wald_p(d, se, _df(na, nb)), "m/s",
                   statistic=d / se if se > 0 else None)


def _q_v_height(A, B, comp, n_bins, n_boot, seed, min_particles, curves):
    from .velocity import velocity_profile

    test = "chi-square of the per-bin differences of v(z) / bins against F(bins, particles - 1), errors by particle bootstrap"
    za, zb = A.df["z"].to_numpy(float), B.df["z"].to_numpy(float)
    za, zb = za[np.isfinite(za)], zb[np.isfinite(zb)]
    lo, hi = max(np.percentile(za, 1), np.percentile(zb, 1)), min(np.percentile(za, 99), np.percentile(zb, 99))
    if not hi > lo:
        return _insufficient("v_vs_height", comp, test, "the tables' height ranges do not overlap", unit="m/s")
    edges = np.linspace(lo, hi, n_bins + 1)
    try:
        pa = velocity_profile(A.df, bins=edges, axes=comp, motion_blur=A.motion_blur, n_boot=n_boot, seed=seed)
        pb = velocity_profile(B.df, bins=edges, axes=comp, motion_blur=B.motion_blur, n_boot=n_boot, seed=seed + 1)
    except UserError as exc:
        return _insufficient("v_vs_height", comp, test, f"velocity profile: {exc.cause}", unit="m/s")
    va, ea_, vb, eb_ = (p[k].to_numpy(float) for p, k in ((pa, f"v{comp}"), (pa, f"v{comp}_err"),
                                                        (pb, f"v{comp}"), (pb, f"v{comp}_err")))
    # a bin's bootstrap error from fewer than 5 particles is too uncertain for a chi-square (liberal)
    ok = (np.isfinite(va) & np.isfinite(vb) & (ea_ > 0) & (eb_ > 0) & (pa["n_particles"].to_numpy() >= 5)
          & (pb["n_particles"].to_numpy() >= 5))
    if ok.sum() < 2:
        return _insufficient("v_vs_height", comp, test, "fewer than 2 height bins with 5 particles in both tables",
                             unit="m/s", effect_name="weighted mean v_A - v_B")
    d = va[ok] - vb[ok]
    var = ea_[ok] ** 2 + eb_[ok] ** 2
    chi2 = float(np.sum(d ** 2 / var))
    # each bin's variance is a bootstrap estimate from few particles: chi2 / k is referred to
    # F(k, n - 1) (n: fewest particles in a used bin) rather than chi2(k), which was liberal (bench_compare)
    n_min = int(min(pa["n_particles"].to_numpy()[ok].min(), pb["n_particles"].to_numpy()[ok].min()))
    k_bins = int(ok.sum())
    w = 1 / var
    md = float(np.sum(w * d) / w.sum())
    se = float(1 / math.sqrt(w.sum()))
    curves[f"v_vs_height_{comp}"] = {"z_mid": pa["z_mid"].tolist(), "a": va.tolist(), "a_err": ea_.tolist(),
                                     "b": vb.tolist(), "b_err": eb_.tolist(), "unit": "m/s"}
    return _record("v_vs_height", comp, test, {"n_bins": int(ok.sum())}, {"n_bins": int(ok.sum())},
                   "weighted mean v_A - v_B", md, (md - Z95 * se, md + Z95 * se),
                   float(stats.f.sf(chi2 / k_bins, k_bins, max(n_min - 1, 1))), "m/s", statistic=chi2)


def _q_height(A, B, n_boot, n_perm, rng, min_particles, curves):
    test = "Kolmogorov-Smirnov distance of the height distributions, permutation of whole particles"
    da = A.df[["particle", "z"]].dropna()
    db = B.df[["particle", "z"]].dropna()
    pa, ua = pd.factorize(da["particle"])
    pb, ub = pd.factorize(db["particle"])
    why = _few(A, B, len(ua), len(ub), "heights", min_particles)
    if why:
        return _insufficient("height", "z", test, why, unit="m", effect_name="median z_A - median z_B")
    za, zb = da["z"].to_numpy(float), db["z"].to_numpy(float)
    pooled = np.r_[za, zb]
    edges = np.linspace(pooled.min(), pooled.max() + 1e-12, 41)
    HA = _hist_per_particle(za, pa, len(ua), edges)
    HB = _hist_per_particle(zb, pb, len(ub), edges)
    ks, p = _perm_ks(HA, HB, n_perm, rng)
    centres = 0.5 * (edges[1:] + edges[:-1])

    def med(H):   # median height of a (resampled) histogram, by the bin centres
        c = np.cumsum(H, axis=-1)
        return centres[np.argmax(c >= 0.5 * c[..., -1:], axis=-1)]

    WA, WB = _boot_weights(len(ua), n_boot, rng), _boot_weights(len(ub), n_boot, rng)
    d_boot = med(WA @ HA) - med(WB @ HB)
    d = float(np.median(za) - np.median(zb))
    curves["height"] = {"z_centres": centres.tolist(), "a": (HA.sum(0) / len(za)).tolist(),
                        "b": (HB.sum(0) / len(zb)).tolist(), "unit": "fraction per bin"}
    return _record("height", "z", test, {"median_z": float(np.median(za)), "n_particles": len(ua)},
                   {"median_z": float(np.median(zb)), "n_particles": len(ub)}, "median z_A - median z_B", d,
                   tuple(float(v) for v in np.percentile(d_boot, [2.5, 97.5])), p, "m", statistic=ks)


def _deposition_times(T: _Table):
    """Per particle: first time deposited (s, relative to the table start) and whether it deposited."""
    df = T.df
    t0 = float(df["t"].min())
    dep = df[T.dep_col].astype(bool).to_numpy()
    g = pd.DataFrame({"particle": df["particle"].to_numpy(), "t": df["t"].to_numpy(float) - t0, "dep": dep})
    last = g.groupby("particle")["t"].max()
    first = g[g["dep"]].groupby("particle")["t"].min()
    times = last.copy()
    times.loc[first.index] = first
    event = np.isin(last.index.to_numpy(), first.index.to_numpy())
    return times.to_numpy(float), event


def _q_deposition(A, B, n_boot, rng, min_particles, curves):
    test = "log-rank test on the particles' deposition times (censored at their last frame)"
    if A.dep_col is None or B.dep_col is None:
        has = [T.name for T in (A, B) if T.dep_col is not None]
        why = (f"only {has[0]} has a deposited/contact column" if has
               else "neither table has a deposited/contact column")
        return _insufficient("deposition", "", test, why, effect_name="final fraction A - B")
    ta, ea = _deposition_times(A)
    tb, eb = _deposition_times(B)
    why = _few(A, B, len(ta), len(tb), "deposition", min_particles)
    if not why and ea.sum() + eb.sum() < 3:
        why = f"deposition: {int(ea.sum())} and {int(eb.sum())} particles deposited; at least 3 in all are needed"
    if why:
        return _insufficient("deposition", "", test, why, effect_name="final fraction A - B")
    t_end = min(ta.max(), tb.max())
    res = stats.logrank(stats.CensoredData(uncensored=ta[ea], right=ta[~ea]),
                        stats.CensoredData(uncensored=tb[eb], right=tb[~eb]))
    fa = (ea & (ta <= t_end)).astype(float)
    fb = (eb & (tb <= t_end)).astype(float)
    d = float(fa.mean() - fb.mean())
    WA, WB = _boot_weights(len(fa), n_boot, rng), _boot_weights(len(fb), n_boot, rng)
    db = (WA @ fa) / len(fa) - (WB @ fb) / len(fb)
    grid = np.linspace(0, t_end, 50)
    curves["deposition"] = {"t_s": grid.tolist(),
                            "a": [(ea & (ta <= g)).mean() for g in grid], "b": [(eb & (tb <= g)).mean() for g in grid],
                            "unit": "fraction of particles deposited"}
    return _record("deposition", "", test, {"fraction_deposited": float(fa.mean()), "n_particles": len(fa)},
                   {"fraction_deposited": float(fb.mean()), "n_particles": len(fb)}, "final fraction A - B", d,
                   tuple(float(v) for v in np.percentile(db, [2.5, 97.5])), float(res.pvalue), "1",
                   statistic=float(res.statistic))


# --------------------------------------------------------------------------- driver
def _compare_pair(A: _Table, B: _Table, lags, n_boot, n_perm, level, seed, min_particles, min_frames,
                  field_of_view, velocity_bins):
    from .msd import estimate_diffusion, particle_diffusion

    rng = np.random.default_rng(seed)
    comps = tuple(c for c in A.comps if c in B.comps)
    if not comps:
        raise UserError(f"{A.name} and {B.name} share no coordinate with finite values", "give trajectories tables")
    taus = _lag_times(A, B)
    curves: dict = {}
    recs = []
    axes = comps
    res = []
    for T, s in ((A, seed), (B, seed + 1)):
        try:
            res.append(estimate_diffusion(T.df, axes=axes, motion_blur=T.motion_blur, n_boot=n_boot, seed=s,
                                          field_of_view=field_of_view))
        except UserError:
            res.append(None)
    pers = []
    for T in (A, B):
        try:
            per = particle_diffusion(T.df, axes=axes, motion_blur=T.motion_blur)
            pers.append(per[per["n_frames"] >= min_frames])
        except UserError:
            pers.append(None)
    for c in comps:
        recs.append(_q_msd(A, B, c, taus, n_boot, rng, min_particles, curves))
        recs.append(_q_D(A, B, c, res[0], res[1], min_particles))
        recs.append(_q_D_distribution(A, B, c, pers[0], pers[1], n_boot, rng, min_particles, curves))
    vh_lags = lags if lags is not None else _van_hove_lags(taus)
    for c in comps:
        for tau in vh_lags:
            recs.extend(_q_van_hove(A, B, c, float(tau), n_boot, n_perm, rng, min_particles, curves))
    ea, eb = _velocities(A, comps, n_boot, seed), _velocities(B, comps, n_boot, seed + 1)
    for c in comps:
        recs.append(_q_drift(A, B, c, ea, eb, min_particles))
    if "z" in comps:
        for c in comps:
            recs.append(_q_v_height(A, B, c, velocity_bins, n_boot, seed, min_particles, curves))
        recs.append(_q_height(A, B, n_boot, n_perm, rng, min_particles, curves))
    recs.append(_q_deposition(A, B, n_boot, rng, min_particles, curves))
    # Holm over every test of this comparison
    p = np.array([r["p_value"] if r["verdict"] is None and r["p_value"] is not None else np.nan for r in recs])
    ph = holm(p)
    for r, q in zip(recs, ph):
        if r["verdict"] is None:
            if np.isfinite(q):
                r["p_holm"] = float(q)
                r["verdict"] = "differs" if q < level else "consistent"
            else:
                r["verdict"] = "insufficient"
                r["reason"] = r["reason"] or "no p-value (degenerate data)"
    out = {}
    for r in recs:
        key = r["quantity"] + (f"_{r['axis']}" if r["axis"] else "") + (f"_{r['lag_s']:.4g}s" if r["lag_s"] else "")
        out[key] = r
    verdicts = {k: r["verdict"] for k, r in out.items()}
    decided = [v for v in verdicts.values() if v != "insufficient"]
    return {"a": A.name, "b": B.name, "level": level, "correction": "Holm (family-wise, over this comparison)",
            "n_tests": int(np.isfinite(ph).sum()), "lags_s": taus.tolist(), "van_hove_lags_s": [float(t) for t in vh_lags],
            "quantities": out, "verdicts": verdicts,
            "n_differs": sum(v == "differs" for v in decided), "n_consistent": sum(v == "consistent" for v in decided),
            "n_insufficient": sum(v == "insufficient" for v in verdicts.values()),
            "all_consistent": bool(decided) and all(v == "consistent" for v in decided), "curves": curves}


def _van_hove_lags(taus: np.ndarray) -> list:
    """Three lags for the van Hove functions: the first, a middle and the longest common lag."""
    t = np.unique([taus[0], taus[len(taus) // 2], taus[-1]])
    return [float(v) for v in t]


def compare_tables(tables, names=None, lags=None, n_boot: int = 400, n_perm: int = 2000, level: float = 0.05,
                   seed: int = 0, motion_blur=1 / 6, min_particles: int = MIN_PARTICLES, min_frames: int = 10,
                   field_of_view=None, velocity_bins: int = 6) -> dict:
    """Compare trajectories tables, each against the first, quantity by quantity.

    Parameters
    ----------
    tables : sequence of DataFrame
        Trajectories tables (:mod:`ptrack.table`), at least two. Frame
        intervals may differ (lags are compared in seconds); z is compared
        only where both tables have it.
    names : sequence of str, optional
        Labels (default A, B, C...).
    lags : sequence of float, optional
        Lag times of the van Hove functions and alpha_2, s (default: the
        first, a middle and the longest of the common MSD lags).
    n_boot, n_perm : int
        Particle bootstrap resamples and particle permutations (a permutation
        p-value is at least 1 / (n_perm + 1), and Holm multiplies it by up to
        the number of tests: keep n_perm well above that number / level).
    level : float
        Family-wise error rate of each comparison (Holm).
    seed : int
        Seed of every resampling (same seed, same numbers).
    motion_blur : float or sequence of float
        R per table (1/6 full-frame exposure, 0 instantaneous: simulated truth).
        Only the drift's error model uses it; D does not depend on it.
    min_particles : int
        Fewer particles than this in a table make a quantity "insufficient".
    min_frames : int
        Shortest track in the per-particle D distribution.
    field_of_view : None or "auto"
        Passed to :func:`ptrack.msd.estimate_diffusion` (edge-loss correction of D).
    velocity_bins : int
        Height bins of v(z) (3D).

    Returns
    -------
    dict
        ``tables`` (summaries) and ``comparisons``: one dict per table after
        the first, with ``quantities`` (key -> record: ``quantity``, ``axis``,
        ``lag_s``, ``test``, values ``a`` and ``b``, ``effect`` with ``value``,
        ``ci_low``, ``ci_high``, ``unit``, ``p_value``, ``p_holm``,
        ``verdict``, ``reason``), ``verdicts`` (key -> "consistent" /
        "differs" / "insufficient"), ``curves`` (arrays for the plots).
    """
    tables = list(tables)
    if len(tables) < 2:
        raise UserError("compare needs at least two tables", "give two or more trajectories tables")
    names = list(names) if names is not None else [chr(65 + i) for i in range(len(tables))]
    if len(names) != len(tables):
        raise UserError(f"{len(names)} names for {len(tables)} tables", "give one name per table")
    if not 0 < level < 1:
        raise UserError(f"level = {level!r} is outside (0, 1)", "give a rate such as 0.05")
    if int(n_boot) < 20 or int(n_perm) < 20:
        raise UserError(f"n_boot = {n_boot}, n_perm = {n_perm}: too few resamples", "give at least 20 (default 400)")
    if lags is not None:
        lags = [float(v) for v in lags]
        if not lags or not all(math.isfinite(v) and v > 0 for v in lags):
            raise UserError(f"lags = {lags!r} must be positive times in s", "give e.g. 0.1,0.4")
    blur = list(motion_blur) if np.ndim(motion_blur) else [float(motion_blur)] * len(tables)
    T = [_Table(df, n, b) for df, n, b in zip(tables, names, blur)]
    comps = [_compare_pair(T[0], t, lags, int(n_boot), int(n_perm), level, seed + 7 * i, min_particles, min_frames,
                           field_of_view, velocity_bins) for i, t in enumerate(T[1:])]
    return {"tables": [t.summary() for t in T], "comparisons": comps, "level": level,
            "units": "SI (m, s, m^2/s, m/s); effect units per record"}


# --------------------------------------------------------------------------- figures and report
_COL = ("C0", "C3")


def plot_comparison(comp: dict, out_dir) -> dict:
    """One PNG overlay per quantity of a comparison (``compare_tables(...)["comparisons"][i]``); returns name -> path."""
    from .plot import new_figure     # Figure objects, no pyplot: a notebook's backend and figures are left alone

    def subplots(nrows=1, ncols=1, figsize=(4.5, 3.4), **kw):
        return new_figure(figsize=figsize, dpi=100, nrows=nrows, ncols=ncols, **kw)

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    a, b = comp["a"], comp["b"]
    cv = comp["curves"]
    q = comp["quantities"]
    paths = {}

    def save(fig, name):
        p = out_dir / f"{name}.png"
        fig.tight_layout()
        with atomic_output(p, "wb") as fh:
            fig.savefig(fh, format="png", dpi=90)
        paths[name] = p

    def verdict(key):
        r = q.get(key)
        return f" [{r['verdict']}]" if r else ""

    msd_keys = [k for k in cv if k.startswith("msd_")]
    if msd_keys:
        fig, axs = subplots(1, len(msd_keys), figsize=(4.2 * len(msd_keys), 3.6), squeeze=False)
        for ax, k in zip(axs[0], msd_keys):
            c = cv[k]
            t = np.asarray(c["t_s"])
            for lab, s, col in ((a, "a", _COL[0]), (b, "b", _COL[1])):
                ax.fill_between(t, np.asarray(c[f"{s}_lo"]) * 1e12, np.asarray(c[f"{s}_hi"]) * 1e12, color=col, alpha=0.25)
                ax.plot(t, np.asarray(c[s]) * 1e12, "o-", color=col, ms=3, label=lab)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("lag (s)")
            ax.set_ylabel("MSD (µm²)")
            ax.set_title(f"MSD {k[4:]}{verdict(k)}", fontsize=9)
            ax.legend(fontsize=8)
        save(fig, "msd")
    dk = [k for k in q if q[k]["quantity"] == "D" and q[k]["a"]]
    if dk:
        fig, ax = subplots(figsize=(4.5, 3.4))
        x = np.arange(len(dk))
        for j, (s, col, lab) in enumerate((("a", _COL[0], a), ("b", _COL[1], b))):
            ax.errorbar(x + (j - 0.5) * 0.2, [q[k][s]["D"] * 1e12 for k in dk],
                        [Z95 * q[k][s]["D_err"] * 1e12 for k in dk], fmt="o", color=col, capsize=3, label=lab)
        ax.set_xticks(x, [f"{q[k]['axis']}{verdict(k)}" for k in dk], fontsize=8)
        ax.set_ylabel("D (µm²/s), 95 % interval")
        ax.set_title("diffusion coefficient", fontsize=9)
        ax.legend(fontsize=8)
        save(fig, "D")
    dd = [k for k in cv if k.startswith("D_distribution_")]
    if dd:
        fig, axs = subplots(1, len(dd), figsize=(4.2 * len(dd), 3.4), squeeze=False)
        for ax, k in zip(axs[0], dd):
            for s, col, lab in (("a", _COL[0], a), ("b", _COL[1], b)):
                v = np.sort(np.asarray(cv[k][s])) * 1e12
                ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", color=col, label=f"{lab} ({len(v)})")
            ax.set_xlabel("per-particle D (µm²/s)")
            ax.set_ylabel("cumulative fraction")
            ax.set_title(f"D per particle, {k.rsplit('_', 1)[1]}{verdict(k)}", fontsize=9)
            ax.legend(fontsize=8)
        save(fig, "D_distribution")
    vh = [k for k in cv if k.startswith("van_hove_")]
    if vh:
        comps_ = sorted({k.split("_")[2] for k in vh})
        fig, axs = subplots(1, len(comps_), figsize=(4.4 * len(comps_), 3.6), squeeze=False)
        for ax, c in zip(axs[0], comps_):
            for j, k in enumerate(k for k in vh if k.split("_")[2] == c):
                d = cv[k]
                x = np.asarray(d["step_centres"]) * 1e6
                key = f"van_hove_{c}_{d['lag_s']:.4g}s"
                key2 = f"alpha2_{c}_{d['lag_s']:.4g}s"
                ax.semilogy(x, np.asarray(d["a_density"]) * 1e-6 + 1e-9, "-", color=f"C{2 * j}",
                            label=f"{a} {d['lag_s']:.3g} s{verdict(key)}")
                ax.semilogy(x, np.asarray(d["b_density"]) * 1e-6 + 1e-9, "--", color=f"C{2 * j}",
                            label=f"{b}; alpha2{verdict(key2)}")
            ax.set_ylim(bottom=1e-4)
            ax.set_xlabel(f"step d{c} (µm)")
            ax.set_ylabel("density (1/µm)")
            ax.set_title(f"van Hove {c} (solid {a}, dashed {b})", fontsize=9)
            ax.legend(fontsize=6)
        save(fig, "van_hove")
    a2 = [k for k in q if q[k]["quantity"] == "alpha2" and q[k]["a"]]
    if a2:
        fig, ax = subplots(figsize=(4.5, 3.4))
        for c in sorted({q[k]["axis"] for k in a2}):
            ks = [k for k in a2 if q[k]["axis"] == c]
            t = [q[k]["lag_s"] for k in ks]
            for s, col, mk in (("a", _COL[0], "o"), ("b", _COL[1], "s")):
                ax.errorbar(t, [q[k][s]["alpha2"] for k in ks], [Z95 * q[k][s]["alpha2_se"] for k in ks], fmt=mk + "-",
                            color=col, capsize=2, label=f"{a if s == 'a' else b} {c}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xscale("log")
        ax.set_xlabel("lag (s)")
        ax.set_ylabel("alpha_2 (0 = Gaussian)")
        ax.set_title("non-Gaussian parameter", fontsize=9)
        ax.legend(fontsize=7)
        save(fig, "alpha2")
    dr = [k for k in q if q[k]["quantity"] == "drift" and q[k]["a"]]
    if dr:
        fig, ax = subplots(figsize=(4.5, 3.4))
        x = np.arange(len(dr))
        for j, (s, col, lab) in enumerate((("a", _COL[0], a), ("b", _COL[1], b))):
            ax.errorbar(x + (j - 0.5) * 0.2, [q[k][s]["v"] * 1e6 for k in dr], [Z95 * q[k][s]["v_err"] * 1e6 for k in dr],
                        fmt="o", color=col, capsize=3, label=lab)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xticks(x, [f"v{q[k]['axis']}{verdict(k)}" for k in dr], fontsize=8)
        ax.set_ylabel("drift velocity (µm/s), 95 %")
        ax.set_title("ensemble drift", fontsize=9)
        ax.legend(fontsize=8)
        save(fig, "drift")
    vz = [k for k in cv if k.startswith("v_vs_height_")]
    if vz:
        fig, ax = subplots(figsize=(4.8, 3.6))
        for j, k in enumerate(vz):
            d = cv[k]
            z = np.asarray(d["z_mid"]) * 1e6
            c = k.rsplit("_", 1)[1]
            ax.errorbar(z, np.asarray(d["a"]) * 1e6, Z95 * np.asarray(d["a_err"]) * 1e6, fmt="o-", color=f"C{2 * j}",
                        capsize=2, label=f"{a} v{c}{verdict(k)}")
            ax.errorbar(z + 0.05, np.asarray(d["b"]) * 1e6, Z95 * np.asarray(d["b_err"]) * 1e6, fmt="s--",
                        color=f"C{2 * j}", capsize=2, label=f"{b} v{c}")
        ax.set_xlabel("height z (µm)")
        ax.set_ylabel("v (µm/s), 95 %")
        ax.set_title("drift against height", fontsize=9)
        ax.legend(fontsize=6)
        save(fig, "v_vs_height")
    if "height" in cv:
        d = cv["height"]
        fig, ax = subplots(figsize=(4.5, 3.4))
        z = np.asarray(d["z_centres"]) * 1e6
        ax.step(z, d["a"], where="mid", color=_COL[0], label=a)
        ax.step(z, d["b"], where="mid", color=_COL[1], label=b)
        ax.set_xlabel("z (µm)")
        ax.set_ylabel("fraction of rows")
        ax.set_title(f"height distribution{verdict('height_z')}", fontsize=9)
        ax.legend(fontsize=8)
        save(fig, "height")
    if "deposition" in cv:
        d = cv["deposition"]
        fig, ax = subplots(figsize=(4.5, 3.4))
        ax.plot(d["t_s"], d["a"], color=_COL[0], label=a)
        ax.plot(d["t_s"], d["b"], color=_COL[1], label=b)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("fraction deposited")
        ax.set_title(f"deposition{verdict('deposition')}", fontsize=9)
        ax.legend(fontsize=8)
        save(fig, "deposition")
    return paths


def _fmt(v, unit=""):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if unit == "m^2/s":
        return f"{v * 1e12:.4g} µm²/s"
    if unit == "m/s":
        return f"{v * 1e6:.3g} µm/s"
    if unit == "m":
        return f"{v * 1e6:.3g} µm"
    return f"{v:.3g}"


def _main_value(r: dict, s: str) -> str:
    v = r.get(s)
    if not v:
        return "-"
    q = r["quantity"]
    if q == "D":
        return f"{v['D'] * 1e12:.4g} &plusmn; {v['D_err'] * 1e12:.2g} µm²/s"
    if q == "msd":
        return f"{v['msd_first_lag'] * 1e12:.3g} µm² (first lag)"
    if q == "D_distribution":
        return f"median {v['median'] * 1e12:.3g} µm²/s (n={v['n_particles']})"
    if q == "van_hove":
        return f"rms {v['rms_step'] * 1e6:.3g} µm ({v['n_steps']} steps)"
    if q == "alpha2":
        return f"{v['alpha2']:.3f} &plusmn; {v['alpha2_se']:.2g}"
    if q == "drift":
        return f"{v['v'] * 1e6:.3g} &plusmn; {v['v_err'] * 1e6:.2g} µm/s"
    if q == "height":
        return f"median {v['median_z'] * 1e6:.3g} µm"
    if q == "deposition":
        return f"{v['fraction_deposited']:.2f} deposited"
    return html.escape(", ".join(f"{k}={_fmt(x)}" for k, x in v.items()))


def verdict_rows(comp: dict) -> list[dict]:
    """The headline table of a comparison as plain rows (also printed by the CLI and the twin report)."""
    rows = []
    for k, r in comp["quantities"].items():
        e = r["effect"]
        rows.append({"key": k, "quantity": r["quantity"], "axis": r["axis"], "lag_s": r["lag_s"],
                     "effect": e["name"], "value": e["value"], "ci": (e["ci_low"], e["ci_high"]), "unit": e["unit"],
                     "p": r["p_value"], "p_holm": r["p_holm"], "verdict": r["verdict"], "reason": r["reason"],
                     "test": r["test"]})
    return rows


def format_table(comp: dict) -> str:
    """Plain-text verdict table of one comparison."""
    lines = [f"{comp['a']} vs {comp['b']}: {comp['n_consistent']} consistent, {comp['n_differs']} differ, "
             f"{comp['n_insufficient']} insufficient ({comp['correction']}, level {comp['level']:g})",
             f"  {'quantity':<26s} {'effect':>10s} {'95% interval':>22s} {'p':>9s} {'p_holm':>9s}  verdict"]
    for r in verdict_rows(comp):
        u = r["unit"]
        ci = r["ci"]
        cis = "-" if ci[0] is None else f"[{_fmt(ci[0], u)}, {_fmt(ci[1], u)}]"
        p = "-" if r["p"] is None else f"{r['p']:.3g}"
        ph = "-" if r["p_holm"] is None else f"{r['p_holm']:.3g}"
        lines.append(f"  {r['key']:<26s} {_fmt(r['value'], u):>10s} {cis:>22s} {p:>9s} {ph:>9s}  {r['verdict']}"
                     + (f" ({r['reason']})" if r["verdict"] == "insufficient" else ""))
    return "\n".join(lines)


_CSS = """body{font-family:sans-serif;margin:1.5em;max-width:1200px}table{border-collapse:collapse;font-size:13px}
td,th{border:1px solid #bbb;padding:3px 6px}th{background:#eee}.differs{background:#f8c8c8}
.consistent{background:#c8f0c8}.insufficient{background:#eee;color:#666}img{max-width:100%;margin:4px;border:1px solid #ddd}
.small{font-size:12px;color:#444}"""


def _img_tag(path: Path) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return f'<figure style="display:inline-block"><img alt="{path.stem}" src="data:image/png;base64,{data}"><figcaption class="small">{path.stem}</figcaption></figure>'


def comparison_html(comp: dict, figures: dict, title: str | None = None) -> str:
    """HTML fragment: verdict table (always visible first) and the figures, embedded as base64 PNG."""
    h = [f"<h2>{html.escape(title or comp['a'] + ' vs ' + comp['b'])}</h2>",
         f"<p>{comp['n_consistent']} consistent, <b>{comp['n_differs']} differ</b>, {comp['n_insufficient']} "
         f"insufficient. p-values corrected by {html.escape(comp['correction'])} at level {comp['level']:g}; every "
         f"interval and p-value resamples or permutes whole particles. Effects are A = {html.escape(comp['a'])} "
         f"relative to B = {html.escape(comp['b'])}.</p>",
         "<table><tr><th>quantity</th><th>axis</th><th>lag (s)</th><th>A</th><th>B</th><th>effect</th>"
         "<th>95 % interval</th><th>p</th><th>p (Holm)</th><th>verdict</th><th>test</th></tr>"]
    for k, r in comp["quantities"].items():
        e = r["effect"]
        u = e["unit"]
        ci = "-" if e["ci_low"] is None else f"[{_fmt(e['ci_low'], u)}, {_fmt(e['ci_high'], u)}]"
        p = "-" if r["p_value"] is None else f"{r['p_value']:.3g}"
        ph = "-" if r["p_holm"] is None else f"{r['p_holm']:.3g}"
        lag = "" if r["lag_s"] is None else f"{r['lag_s']:.3g}"
        test = html.escape(r["test"]) + (f"<br><i>{html.escape(r['reason'])}</i>" if r["reason"] else "")
        h.append(f"<tr class='{r['verdict']}'><td>{r['quantity']}</td><td>{r['axis']}</td><td>{lag}</td>"
                 f"<td>{_main_value(r, 'a')}</td><td>{_main_value(r, 'b')}</td>"
                 f"<td>{html.escape(e['name'])} = {_fmt(e['value'], u)}</td><td>{ci}</td><td>{p}</td><td>{ph}</td>"
                 f"<td><b>{r['verdict']}</b></td><td class='small'>{test}</td></tr>")
    h.append("</table>")
    h.append("<div>" + "".join(_img_tag(p) for p in figures.values()) + "</div>")
    return "\n".join(h)


def write_report(result: dict, report_dir, title: str = "ptrack compare", preamble: str = "") -> Path:
    """Figures (PNG per quantity, one folder per comparison) and one self-contained ``report.html``."""
    rd = Path(report_dir)
    if rd.exists() and not rd.is_dir():
        raise UserError(f"--report {rd} exists and is not a directory", "give a directory")
    rd.mkdir(parents=True, exist_ok=True)
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>", preamble]
    tabs = "".join(f"<tr><td>{html.escape(t['name'])}</td><td>{t['n_particles']}</td><td>{t['n_rows']}</td>"
                   f"<td>{t['frame_interval_s']:.4g}</td><td>{','.join(t['components'])}</td></tr>"
                   for t in result["tables"])
    parts.append("<table><tr><th>table</th><th>particles</th><th>rows</th><th>frame interval (s)</th>"
                 f"<th>coordinates</th></tr>{tabs}</table>")
    for i, comp in enumerate(result["comparisons"]):
        figs = plot_comparison(comp, rd / f"figures_{i + 1}_{_slug(comp['b'])}")
        parts.append(comparison_html(comp, figs))
    parts.append("</body></html>")
    path = rd / "report.html"
    with atomic_output(path, "w") as fh:
        fh.write("\n".join(parts))
    return path


def _slug(s: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in str(s))[:40]


def to_json(result: dict, path) -> Path:
    """Write a comparison result as JSON (NaN as null)."""
    with atomic_output(path, "w") as fh:
        json.dump(_clean(result), fh, indent=1)
    return Path(path)


def _clean(obj):
    from .table import to_jsonable

    return to_jsonable(obj, finite=True)
