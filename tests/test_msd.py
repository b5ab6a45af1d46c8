"""Tests of ptrack.msd against analytic results and synthetic ground truth."""
import math

import numpy as np
import pandas as pd
import pytest

from ptrack import msd as M
from ptrack.errors import UserError
from ptrack.table import make_table

D0 = 1e-12      # m^2/s
DT = 0.1        # s


def _table(x, y, dt=DT, keep=None, z=None):
    """Tracks (n_p, n_f) arrays -> trajectories table, optionally dropping rows (gaps)."""
    n_p, n_f = x.shape
    fr = np.tile(np.arange(n_f), n_p)
    pa = np.repeat(np.arange(n_p), n_f)
    k = np.ones(n_p * n_f, bool) if keep is None else keep
    zz = None if z is None else z.ravel()[k]
    return make_table(fr[k], fr[k] * dt, pa[k], x.ravel()[k], y.ravel()[k], z=zz, meta={"frame_interval": dt})


# --------------------------------------------------------------------- Stokes-Einstein

def test_stokes_einstein_reproduces_seed_values():
    assert M.stokes_einstein(250e-9, 1e-3, 293.15) == pytest.approx(8.589e-13, rel=2e-4)
    assert M.stokes_einstein(330.1e-9, 1e-3, 293.15) == pytest.approx(6.504e-13, rel=2e-4)
    # seed Table 3.1, analytical column: T = 293 K, R = 1..1000 nm, mu = 1e-4..1e-2
    R = np.array([1e-9, 10e-9, 100e-9, 1000e-9])
    for mu, first in ((1e-4, 2.15e-9), (1e-3, 2.15e-10), (1e-2, 2.15e-11)):
        d = M.stokes_einstein(R, mu, 293.0)
        np.testing.assert_allclose(d, first * 10.0 ** -np.arange(4), rtol=3e-3)


def test_stokes_einstein_vectorised_and_rejects_bad_input():
    d = M.stokes_einstein(np.array([[1e-7], [2e-7]]), np.array([1e-3, 2e-3]), 300.0)
    assert d.shape == (2, 2) and d[0, 0] == pytest.approx(2 * d[1, 0]) == pytest.approx(2 * d[0, 1])
    for bad in (-1e-7, 0.0, np.nan):
        with pytest.raises(UserError):
            M.stokes_einstein(bad, 1e-3)


# --------------------------------------------------------------------- MSD tables

def _naive_msd(tracks, lag):
    """Brute force: tracks = {pid: {frame: (x, y)}} -> (sum dx^2, sum dy^2, count)."""
    sx = sy = n = 0
    for pts in tracks.values():
        for f, (x, y) in pts.items():
            if f + lag in pts:
                x2, y2 = pts[f + lag]
                sx += (x2 - x) ** 2
                sy += (y2 - y) ** 2
                n += 1
    return sx, sy, n


def test_ensemble_and_particle_msd_with_gaps_match_brute_force():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 30)).cumsum(1) * 1e-7
    y = rng.normal(size=(4, 30)).cumsum(1) * 1e-7
    keep = rng.random(120) > 0.25
    df = _table(x, y, keep=keep)
    tracks = {}
    for r in df.itertuples():
        tracks.setdefault(r.particle, {})[r.frame] = (r.x, r.y)
    ens = M.ensemble_msd(df, axes=("x", "y", "xy"), max_lag=10)
    assert list(ens["lag"]) == list(range(1, 11))
    np.testing.assert_allclose(ens["t"], ens["lag"] * DT)
    for lag in range(1, 11):
        sx, sy, n = _naive_msd(tracks, lag)
        row = ens.iloc[lag - 1]
        assert row["n_x"] == n == row["n_xy"]
        assert row["msd_x"] == pytest.approx(sx / n, rel=1e-12)
        assert row["msd_y"] == pytest.approx(sy / n, rel=1e-12)
        assert row["msd_xy"] == pytest.approx((sx + sy) / n, rel=1e-12)
    pm = M.particle_msd(df, axes=("x",), max_lag=5)
    one = pm[(pm.particle == 2) & (pm.lag == 3)].iloc[0]
    sx, _, n = _naive_msd({2: tracks[2]}, 3)
    assert one["n_x"] == n and one["msd_x"] == pytest.approx(sx / n)


def test_msd_of_uniform_motion_is_v2_t2_and_array_path_agrees():
    f = np.arange(50.0)
    pos = np.stack([2e-8 * f, -1e-8 * f])                       # two particles, constant velocity
    m = M.msd_from_positions(pos, 10)
    np.testing.assert_allclose(m[0], (2e-8 * np.arange(1, 11)) ** 2)
    np.testing.assert_allclose(m[1], (1e-8 * np.arange(1, 11)) ** 2)
    df = _table(pos, np.zeros_like(pos))
    ens = M.ensemble_msd(df, axes=("x",), max_lag=10)
    np.testing.assert_allclose(ens["msd_x"], m.mean(0))
    m3 = M.msd_from_positions(np.stack([pos, pos], axis=2), 4)   # (n_p, n_f, 2): summed over dims
    np.testing.assert_allclose(m3, 2 * m[:, :4])


# --------------------------------------------------------------------- CVE: bias and closed-form variance

@pytest.mark.parametrize("x", [0.0, 1.0, 10.0])
@pytest.mark.parametrize("R", [0.0, 1 / 6])
def test_cve_unbiased_and_scatter_matches_closed_form(x, R):
    n_tr, n_f = 20000, 201
    sigma = math.sqrt(x * D0 * DT)
    pos = M.brownian_tracks(n_tr, n_f, D0, DT, sigma, R, seed=int(10 * x + 60 * R))
    D, var = M.cve_from_positions(pos, DT, motion_blur=R)
    sd = D.std(ddof=1)
    se_mean = sd / math.sqrt(n_tr)
    bias = D.mean() / D0 - 1
    assert abs(bias) < max(0.01, 3.5 * se_mean / D0), (bias, se_mean / D0)
    exact_sd = math.sqrt(M.cve_variance(D0, sigma**2, DT, n_f - 1, R))
    assert sd == pytest.approx(exact_sd, rel=0.10)
    # the per-track error estimate (closed form at the estimates) is right on average
    assert math.sqrt(np.mean(var)) == pytest.approx(exact_sd, rel=0.10)


def test_cve_with_explicitly_blurred_exposure():
    """Independent of the MA(1) model: average fine Brownian sub-steps over a full-frame exposure."""
    rng = np.random.default_rng(11)
    n_tr, n_f, sub = 3000, 60, 24
    h = DT / sub
    steps = rng.normal(scale=math.sqrt(2 * D0 * h), size=(n_tr, n_f * sub))
    fine = np.cumsum(steps, axis=1)
    blurred = fine.reshape(n_tr, n_f, sub).mean(axis=2)      # shutter open the whole frame
    sigma = 20e-9
    obs = blurred + rng.normal(scale=sigma, size=blurred.shape)
    D, _, s2 = M.cve_from_positions(obs, DT, motion_blur=1 / 6, return_sigma=True)
    assert D.mean() == pytest.approx(D0, rel=0.02)
    assert math.sqrt(max(s2.mean(), 0)) == pytest.approx(sigma, rel=0.1)
    # ignoring the blur (R = 0) gets sigma wrong, D stays right
    D0b, _, s2b = M.cve_from_positions(obs, DT, motion_blur=0.0, return_sigma=True)
    assert D0b.mean() == pytest.approx(D.mean(), rel=1e-12)
    assert s2b.mean() < 0.5 * s2.mean()


# --------------------------------------------------------------------- CRLB and OLS efficiency

def test_crlb_matches_dense_fisher_information():
    D, sigma, N, R = 1e-12, 40e-9, 40, 1 / 6
    c0 = lambda D, s2: 2 * D * DT * (1 - 2 * R) + 2 * s2
    c1 = lambda D, s2: 2 * R * D * DT - s2
    cov = lambda D, s2: (np.diag(np.full(N, c0(D, s2))) + np.diag(np.full(N - 1, c1(D, s2)), 1)
                         + np.diag(np.full(N - 1, c1(D, s2)), -1))
    S = cov(D, sigma**2)
    Si = np.linalg.inv(S)
    dS = [(cov(D * 1.001, sigma**2) - cov(D * 0.999, sigma**2)) / (0.002 * D),
          (cov(D, sigma**2 * 1.001) - cov(D, sigma**2 * 0.999)) / (0.002 * sigma**2)]
    I = np.array([[0.5 * np.trace(Si @ a @ Si @ b) for b in dS] for a in dS])
    assert M.crlb_diffusion(D, sigma, DT, N, R) == pytest.approx(np.linalg.inv(I)[0, 0], rel=1e-6)
    assert M.crlb_diffusion(D, sigma, DT, N, R, n_tracks=5, dims=2) == pytest.approx(np.linalg.inv(I)[0, 0] / 10, rel=1e-6)


def test_optimal_lags_grow_with_localisation_error():
    P = [M.optimal_lags(eps, [200])[0] for eps in (0.0, 1.0, 10.0, 100.0)]
    assert P[0] == 2 and P == sorted(P) and P[-1] > P[1]


@pytest.mark.parametrize("x,R", [(0.0, 0.0), (1.0, 1 / 6), (10.0, 0.0)])
def test_ols_optimal_lags_near_cramer_rao_bound(x, R):
    n_rep, n_p, n_f = 200, 20, 101
    sigma = math.sqrt(x * D0 * DT)
    rng = np.random.default_rng(int(100 * x + 7))
    Ds = np.array([M.ols_from_positions(M.brownian_tracks(n_p, n_f, D0, DT, sigma, R, seed=rng), DT)[0]
                   for _ in range(n_rep)])
    bound = math.sqrt(M.crlb_diffusion(D0, sigma, DT, n_f - 1, R, n_tracks=n_p))
    sd = Ds.std(ddof=1)
    assert abs(Ds.mean() / D0 - 1) < 3.5 * sd / math.sqrt(n_rep) / D0
    assert sd / bound < 1.2, sd / bound
    # a fixed fraction of the curve (here half of it) is much worse
    Df = []
    rng = np.random.default_rng(5)
    for _ in range(60):
        m = M.msd_from_positions(M.brownian_tracks(n_p, n_f, D0, DT, sigma, R, seed=rng), 50).mean(0)
        Df.append(M.ols_fit(m, 50)[1] / (2 * DT))
    assert np.std(Df) > 1.5 * sd


# --------------------------------------------------------------------- table-level estimates

def _iso_table(n_p=40, n_f=150, sigma=30e-9, R=1 / 6, seed=0, gaps=0.1):
    rng = np.random.default_rng(seed)
    p = M.brownian_tracks(n_p, n_f, D0, DT, sigma, R, n_dims=2, seed=rng)
    keep = rng.random(n_p * n_f) > gaps
    return _table(p[..., 0], p[..., 1], keep=keep)


@pytest.mark.parametrize("estimator", ["cve", "ols"])
def test_dx_dy_dxy_agree_within_errors_on_isotropic_data(estimator):
    df = _iso_table(seed=1)
    r = M.estimate_diffusion(df, axes=("x", "y", "xy"), estimator=estimator, n_boot=200, seed=1)
    assert r.se_method == "bootstrap" and r.n_particles == 40
    for a in ("x", "y", "xy"):
        assert abs(r.D[a] - D0) < 3.5 * r.D_err[a], (a, r.D[a], r.D_err[a])
    assert abs(r.D["x"] - r.D["y"]) < 3.5 * math.hypot(r.D_err["x"], r.D_err["y"])
    # the factor 2n: D_xy (n = 2) is the mean of the 1D values, not half or double
    assert r.D["xy"] == pytest.approx(0.5 * (r.D["x"] + r.D["y"]), rel=0.05)
    assert r.D_err["xy"] < min(r.D_err["x"], r.D_err["y"])
    tab = r.table()
    assert list(tab.columns) == ["D_x", "D_x_err", "D_y", "D_y_err", "D_xy", "D_xy_err"]
    if estimator == "cve":
        assert r.D["xy"] == pytest.approx(0.5 * (r.D["x"] + r.D["y"]), rel=1e-12)
        assert r.sigma_loc["xy"] == pytest.approx(30e-9, rel=0.3)
    else:
        assert all(P >= 2 for P in r.n_lags.values())


@pytest.mark.parametrize("estimator", ["cve", "ols"])
def test_bootstrap_se_matches_replicate_scatter(estimator):
    Ds, boots, models = [], [], []
    for rep in range(80):
        df = _iso_table(n_p=30, n_f=80, sigma=50e-9, seed=100 + rep, gaps=0.05)
        r = M.estimate_diffusion(df, axes=("x",), estimator=estimator, n_boot=150, seed=rep)
        Ds.append(r.D["x"])
        boots.append(r.D_err_boot["x"])
        models.append(r.D_err_model["x"])
    sd = np.std(Ds, ddof=1)
    assert np.mean(boots) == pytest.approx(sd, rel=0.2)
    assert np.mean(models) == pytest.approx(sd, rel=0.2)
    assert abs(np.mean(Ds) / D0 - 1) < 3.5 * sd / math.sqrt(80) / D0


def test_bootstrap_is_reproducible_with_seed():
    df = _iso_table(seed=4)
    a = M.estimate_diffusion(df, seed=7).D_err
    b = M.estimate_diffusion(df, seed=7).D_err
    c = M.estimate_diffusion(df, seed=8).D_err
    assert a == b and a != c


def test_drift_subtraction_with_bias_correction_is_unbiased():
    n_p, n_f, n_rep = 4, 200, 60                           # few particles: (1 - 1/M) = 0.75
    ratios_corr, ratios_naive = [], []
    for rep in range(n_rep):
        rng = np.random.default_rng(500 + rep)
        p = M.brownian_tracks(n_p, n_f, D0, DT, 20e-9, 0.0, n_dims=2, seed=rng)
        common = np.cumsum(rng.normal(5e-7, 3e-7, size=(n_f, 2)), axis=0)   # drifting stage: mean + wander
        p = p + common[None]
        df = _table(p[..., 0], p[..., 1])
        r = M.estimate_diffusion(df, axes=("xy",), subtract_drift=True, motion_blur=0.0, n_boot=0)
        ratios_corr.append(r.D["xy"] / D0)
        naive = M.estimate_diffusion(M.subtract_drift(df), axes=("xy",), motion_blur=0.0, n_boot=0)
        ratios_naive.append(naive.D["xy"] / D0)
    se = np.std(ratios_corr, ddof=1) / math.sqrt(n_rep)
    assert abs(np.mean(ratios_corr) - 1) < max(0.02, 3.5 * se)
    assert np.mean(ratios_naive) == pytest.approx(0.75, abs=max(0.02, 3.5 * se))
    # without any drift removal, D is far too large
    raw = M.estimate_diffusion(df, axes=("xy",), motion_blur=0.0, n_boot=0).D["xy"]
    assert raw > 2 * D0


def test_drift_table_recovers_uniform_drift():
    p = M.brownian_tracks(50, 100, D0, DT, 0.0, 0.0, n_dims=2, seed=2)
    p[..., 0] += 1e-7 * np.arange(100)[None]
    df = _table(p[..., 0], p[..., 1])
    d = M.drift(df, axes=("x", "y"), smoothing=5)
    assert list(d.columns) == ["frame", "t", "x", "y", "n"]
    assert np.polyfit(d["frame"], d["x"], 1)[0] == pytest.approx(1e-7, rel=0.05)
    assert abs(np.polyfit(d["frame"], d["y"], 1)[0]) < 1e-8
    corrected = M.subtract_drift(df, d)
    assert abs(np.polyfit(corrected["frame"], corrected["x"], 1)[0]) < 1e-8


# --------------------------------------------------------------------- power-law flags

def test_powerlaw_false_positive_rate_on_brownian_tracks():
    df = _iso_table(n_p=600, n_f=100, sigma=math.sqrt(1.0 * D0 * DT), seed=9, gaps=0.05)
    f = M.powerlaw_flags(df, axes="xy", level=0.01, seed=0)
    assert len(f) == 600 and f["alpha"].notna().all()
    assert np.median(f["alpha"]) == pytest.approx(1.0, abs=0.05)
    assert f["flagged"].mean() < 0.025          # nominal 1 %; binomial SD 0.4 %


def test_powerlaw_flags_directed_and_confined_tracks():
    rng = np.random.default_rng(21)
    n_p, n_f = 60, 120
    p = M.brownian_tracks(n_p, n_f, D0, DT, 20e-9, 1 / 6, n_dims=2, seed=rng)
    step = math.sqrt(2 * D0 * DT)
    p[0, :, 0] += 1.5 * step * np.arange(n_f)                    # advected toward an edge
    p[1] = p[1, :1] + rng.normal(scale=0.3 * step, size=(n_f, 2))   # stuck: only jitter around a point
    df = _table(p[..., 0], p[..., 1])
    f = M.powerlaw_flags(df, level=0.01, seed=1).set_index("particle")
    assert f.loc[0, "flagged"] and "directed" in f.loc[0, "reason"] and f.loc[0, "alpha"] > 1.3
    assert f.loc[1, "flagged"] and "confined" in f.loc[1, "reason"] and f.loc[1, "alpha"] < 0.7
    assert f["flagged"].sum() <= 4


# --------------------------------------------------------------------- user errors

def test_library_rejects_bad_input():
    df = _iso_table(n_p=5, n_f=20, seed=3)
    with pytest.raises(UserError, match="unknown axis"):
        M.estimate_diffusion(df, axes=("w",))
    with pytest.raises(UserError, match="2D"):
        M.estimate_diffusion(df, axes=("z",))
    with pytest.raises(UserError, match="estimator"):
        M.estimate_diffusion(df, estimator="mle")
    short = make_table([0, 1, 0, 1], [0, .1, 0, .1], [0, 0, 1, 1], [0, 1e-7, 0, 1e-7], [0, 0, 0, 0])
    with pytest.raises(UserError, match="shorter than 3"):
        M.estimate_diffusion(short)
    gappy = make_table([0, 2, 4], [0, .2, .4], [0, 0, 0], [0, 1e-7, 2e-7], [0, 0, 0])
    with pytest.raises(UserError, match="three consecutive"):
        M.estimate_diffusion(gappy)
    with pytest.raises(UserError):
        M.cve_from_positions(np.array([[0.0, np.nan, 1.0]]), DT)


def test_powerlaw_flags_with_common_drift():
    rng = np.random.default_rng(31)
    n_p, n_f = 80, 100
    p = M.brownian_tracks(n_p, n_f, D0, DT, 20e-9, 0.0, n_dims=2, seed=rng)
    p[..., 0] += 2.0 * math.sqrt(2 * D0 * DT) * np.arange(n_f)[None]      # the whole field drifts
    df = _table(p[..., 0], p[..., 1])
    assert M.powerlaw_flags(df, seed=0)["flagged"].mean() > 0.8
    assert M.powerlaw_flags(df, seed=0, subtract_drift=True)["flagged"].mean() < 0.05


def test_particle_diffusion_matches_array_path_and_closed_form():
    p = M.brownian_tracks(300, 120, D0, DT, 30e-9, 1 / 6, n_dims=2, seed=17)
    df = _table(p[..., 0], p[..., 1])
    pdf = M.particle_diffusion(df, axes=("x", "xy"), motion_blur=1 / 6)
    Dx, vx = M.cve_from_positions(p[..., 0], DT, 1 / 6)
    np.testing.assert_allclose(pdf["D_x"], Dx, rtol=1e-10)
    np.testing.assert_allclose(pdf["D_x_err"], np.sqrt(vx), rtol=1e-10)
    Dxy, vxy = M.cve_from_positions(p, DT, 1 / 6)
    np.testing.assert_allclose(pdf["D_xy"], Dxy, rtol=1e-10)
    # the per-track errors describe the scatter of the per-track D
    assert pdf["D_xy"].std() == pytest.approx(np.sqrt(np.mean(pdf["D_xy_err"] ** 2)), rel=0.15)
    assert pdf["D_xy"].mean() == pytest.approx(D0, rel=0.03)


def test_ensemble_msd_standard_error_matches_replicate_scatter():
    vals, ses = [], []
    for rep in range(150):
        p = M.brownian_tracks(20, 60, D0, DT, 20e-9, 0.0, n_dims=2, seed=900 + rep)
        e = M.ensemble_msd(_table(p[..., 0], p[..., 1]), axes=("xy",), max_lag=10)
        vals.append(e["msd_xy"].to_numpy())
        ses.append(e["se_xy"].to_numpy())
    sd = np.std(vals, axis=0, ddof=1)
    np.testing.assert_allclose(np.mean(ses, axis=0), sd, rtol=0.2)
    np.testing.assert_allclose(np.mean(vals, axis=0), 4 * D0 * DT * np.arange(1, 11) + 4 * (20e-9) ** 2, rtol=0.03)


# --------------------------------------------------------------------- field of view, linking-free D

def test_field_of_view_correction_removes_edge_bias():
    # steps of s = 4 units in a 100-unit view: tracks lose long steps at the edges, MSD low by ~1.6 s / L
    L, dt, D = 100.0, 0.1, 80.0
    s = math.sqrt(2 * D * dt)
    df = pd.concat([M.brownian_field(60, L, 0.01, D, dt, seed=k).assign(particle=lambda d, k=k: d["particle"] + 100000 * k)
                    for k in range(6)], ignore_index=True)
    raw = M.estimate_diffusion(df, axes=("xy",), motion_blur=0.0, n_boot=0)
    cor = M.estimate_diffusion(df, axes=("xy",), motion_blur=0.0, n_boot=0, field_of_view={"x": L, "y": L})
    auto = M.estimate_diffusion(df, axes=("xy",), motion_blur=0.0, n_boot=0, field_of_view="auto")
    se = cor.D_err_model["xy"]
    assert se / D < 0.012
    # uncorrected: low by E|d|^3 / (s^2 L) per axis = 2 sqrt(2/pi) s / L for Gaussian steps
    predicted = -2 * math.sqrt(2 / math.pi) * s / L
    assert raw.D["xy"] / D - 1 == pytest.approx(predicted, abs=2.5 * se / D)
    assert abs(cor.D["xy"] - D) < 3 * se
    assert abs(auto.D["xy"] - cor.D["xy"]) < 0.2 * se
    # the ensemble MSD takes the same correction at every lag
    m = M.ensemble_msd(df, axes=("xy",), max_lag=5, field_of_view={"x": L, "y": L})
    np.testing.assert_allclose(m["msd_xy"] / (4 * D * m["t"]), 1.0, atol=0.05)
    with pytest.raises(UserError, match="field_of_view"):
        M.estimate_diffusion(df, field_of_view={"x": -1.0})
    with pytest.raises(UserError, match="field_of_view"):
        M.estimate_diffusion(df, field_of_view=("q",))


def test_pair_diffusion_unbiased_where_linking_is_not():
    from ptrack.link import filter_short, link

    # dense: another particle is often nearer than the partner (link ambiguity ~ 0.2)
    L, dt, D, sig = 150.0, 0.1, 80.0, 0.1
    Ds, errs, Dl = [], [], []
    for k in range(4):
        df = M.brownian_field(80, L, 0.0022, D, dt, sigma=sig, seed=k)
        r = M.pair_diffusion(df.drop(columns="particle"), axes=("x", "y", "xy"), motion_blur=0.0)
        Ds.append(r.D["xy"])
        errs.append(r.D_err["xy"])
        feats = df.drop(columns="particle").rename(columns={"x": "x_px", "y": "y_px"})
        lk = filter_short(link(feats), 5)
        lk = lk.assign(x=lk["x_px"], y=lk["y_px"])
        Dl.append(M.estimate_diffusion(lk, axes=("xy",), motion_blur=0.0, n_boot=0, field_of_view="auto").D["xy"])
    assert r.link_ambiguity > 0.12
    mean, se = np.mean(Ds), math.sqrt(np.sum(np.square(errs))) / len(errs)
    assert se / D < 0.04
    assert abs(mean - D) < 3 * se
    assert np.mean(Dl) < D - 3 * se           # linked tracks: identity swaps shorten the steps
    assert set(r.lags.columns) >= {"lag", "s2_x", "s2_y", "alpha", "unmatched_density", "n_targets"}
    assert np.all(np.abs(r.lags["alpha"] - 1) < 0.1)    # every particle's partner is found


def test_pair_diffusion_fitted_offset_and_drift():
    L, dt, D, sig = 150.0, 0.1, 80.0, 1.0
    v = (30.0, -20.0)
    df = M.brownian_field(120, L, 0.001, D, dt, sigma=sig, drift=v, seed=7).drop(columns=["sigma_x", "sigma_y"])
    r = M.pair_diffusion(df, axes=("x", "y", "xy"), motion_blur=0.0, offset="fit", max_lag=5)
    assert abs(r.D["xy"] - D) < 3 * r.D_err["xy"]
    assert r.sigma_loc["xy"] == pytest.approx(sig, abs=0.5)
    assert r.drift_velocity["x"] == pytest.approx(v[0], abs=3.0)
    assert r.drift_velocity["y"] == pytest.approx(v[1], abs=3.0)
    with pytest.raises(UserError, match="max_lag"):
        M.pair_diffusion(df, max_lag=1)
    with pytest.raises(UserError, match="sigma_x"):
        M.pair_diffusion(df, offset="sigma")
    with pytest.raises(UserError, match="lacks column"):
        M.pair_diffusion(df.drop(columns="y"))


def test_pair_diffusion_checks_the_motion_blur_it_is_given():
    # no blur in the data: with R = 0 the localiser's sigma fixes the intercept (precise); told R = 1/6,
    # the intercept it implies (2 sigma^2 - 4 R D dt) disagrees with the fitted one and D falls back to the fit
    L, dt, D, sig = 150.0, 0.1, 80.0, 0.2
    df = M.brownian_field(100, L, 0.0015, D, dt, sigma=sig, seed=11)
    good = M.pair_diffusion(df, axes=("xy",), motion_blur=0.0)
    wrong = M.pair_diffusion(df, axes=("xy",), motion_blur=1 / 6)
    assert good.offset_used == "sigma" and wrong.offset_used.startswith("fit")
    assert abs(good.D["xy"] - D) < 3 * good.D_err["xy"]
    assert abs(wrong.D["xy"] - D) < 3 * wrong.D_err["xy"]
    assert good.D_err["xy"] < 0.8 * wrong.D_err["xy"]
    # the fitted intercept is 2 sigma^2 (R = 0) within its error
    for c in ("x", "y"):
        assert abs(good.intercept[c] - 2 * sig**2) < 3 * good.intercept_err[c]
