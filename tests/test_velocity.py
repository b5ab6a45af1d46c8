"""Tests of ptrack.velocity (drift velocities) against analytic results and ground truth."""
import argparse
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ptrack import velocity as V
from ptrack.cli import main
from ptrack.errors import UserError
from ptrack.table import make_table, read_table, write_table

D0 = 5.37e-13            # m^2/s, 0.8 um sphere in water at 20 C
DT = 1 / 30              # s
VEL = (1.5e-6, 0.0, -5.2e-6)


def _theory_var(weights, tau, kk, D, s2, R, dt):
    """Exact variance w' S w of a linear drift estimate sum w_i d_i (sum w_i tau_i = 1)."""
    n = len(tau)
    S = np.diag(2 * D * dt * (kk - 2 * R) + 2 * s2) + (2 * R * D * dt - s2) * (np.eye(n, k=1) + np.eye(n, k=-1))
    return float(weights @ S @ weights)


@pytest.mark.parametrize("sigma, R, gaps, noise", [(0.0, 0.0, 0.0, "track"), (60e-9, 1 / 6, 0.25, "track"),
                                                   (250e-9, 0.0, 0.1, "pooled")])
def test_gls_is_unbiased_and_its_standard_error_matches_the_scatter(sigma, R, gaps, noise):
    # 2400 tracks = 200 replicates of 12 particles; 30 frames each
    df = V.drifting_tracks(2400, 30, D0, DT, VEL, sigma=sigma, motion_blur=R, gap_fraction=gaps, seed=11)
    vel = V.particle_velocity(df, motion_blur=R, noise=noise)
    assert len(vel) == 2400 and vel["n_frames"].min() >= 4
    for c, vt in zip("xyz", VEL):
        err = vel[f"v{c}"].to_numpy() - vt
        sd = err.std(ddof=1)
        assert abs(err.mean()) < 4 * sd / math.sqrt(len(err)), c                  # unbiased
        stated = math.sqrt(np.mean(vel[f"v{c}_err"].to_numpy() ** 2))
        assert stated / sd == pytest.approx(1.0, abs=0.05), c                     # SE matches the scatter
        assert vel[f"D{c}"].mean() == pytest.approx(D0, rel=0.04), c              # D from drift-corrected steps
    if sigma > 100e-9:    # clipped at 0, the per-track sigma is biased up when sigma^2 << 2 D dt
        s_est = math.sqrt(np.mean(vel["sigma_z"].to_numpy() ** 2))
        assert s_est == pytest.approx(sigma, rel=0.1)
        # per-track noise estimates on short noise-dominated tracks: unbiased v, error a little conservative
        tr = V.particle_velocity(df, motion_blur=R, noise="track")
        ratio = math.sqrt(np.mean(tr["vz_err"] ** 2)) / (tr["vz"] - VEL[2]).std()
        assert 0.97 < ratio < 1.15


def test_without_noise_the_gls_is_the_end_to_end_displacement_even_with_gaps():
    df = V.drifting_tracks(5, 40, D0, DT, VEL, gap_fraction=0.3, seed=3)
    from ptrack.motion.tracks import sort_tracks
    from ptrack.motion.velocity import _velocity_kernel

    st = sort_tracks(df, ("x", "y", "z"))
    parts, off, frames, vals, dt = st.particles, st.off, st.frames, st.vals, st.dt
    D_in = np.full((3, len(parts)), D0)
    s2_in = np.zeros((3, len(parts)))
    res = _velocity_kernel(vals, frames, off, dt, 0.0, D_in, s2_in, 4, 1)
    for p in range(len(parts)):
        a, b = off[p], off[p + 1] - 1
        span = (frames[b] - frames[a]) * dt
        np.testing.assert_allclose(res[:, p, 0], (vals[:, b] - vals[:, a]) / span, rtol=1e-10)
        np.testing.assert_allclose(res[:, p, 1], 2 * D0 / span, rtol=1e-10)    # Var = 2 D / T


def test_gls_beats_end_to_end_and_least_squares_slope_as_theory_says():
    """With localisation noise the GLS beats the OLS slope and the end-to-end estimate (30 frames, sigma^2 = 10 D dt)."""
    n_f, s = 30, math.sqrt(10 * D0 * DT)
    df = V.drifting_tracks(4000, n_f, D0, DT, (0.0, 0.0, -5e-6), sigma=s, seed=5)
    vel = V.particle_velocity(df, axes="z", motion_blur=0.0, noise="pooled")
    z = df["z"].to_numpy().reshape(4000, n_f)
    t = np.arange(n_f) * DT
    e2e = (z[:, -1] - z[:, 0]) / t[-1]
    ols = np.polyfit(t, z.T, 1)[0]
    tau, kk = np.full(n_f - 1, DT), np.ones(n_f - 1)
    w_e2e = np.full(n_f - 1, 1 / t[-1])
    # OLS slope as a linear function of the increments: w_i = sum_{j>i} (t_j - tbar) / Sxx
    tc = t - t.mean()
    w_ols = np.cumsum(tc[::-1])[::-1][1:] / np.sum(tc**2)
    S = np.diag(2 * D0 * DT * kk + 2 * s**2) - s**2 * (np.eye(n_f - 1, k=1) + np.eye(n_f - 1, k=-1))
    u = np.linalg.solve(S, tau)
    th = {"gls": 1 / (u @ tau), "e2e": _theory_var(w_e2e, tau, kk, D0, s**2, 0, DT),
          "ols": _theory_var(w_ols, tau, kk, D0, s**2, 0, DT)}
    emp = {"gls": vel["vz"].var(), "e2e": e2e.var(), "ols": ols.var()}
    assert th["gls"] < 0.96 * th["ols"] < 0.96 * th["e2e"]
    for k in th:
        assert emp[k] / th[k] == pytest.approx(1.0, abs=0.08), k
    assert emp["gls"] < 0.97 * emp["ols"] and emp["gls"] < 0.9 * emp["e2e"]


def test_ensemble_velocity_bootstrap_and_heterogeneity():
    df = V.drifting_tracks(60, 50, D0, DT, VEL, sigma=40e-9, seed=8)
    vel = V.particle_velocity(df, motion_blur=0.0, noise="pooled")
    ens = V.ensemble_velocity(vel, n_boot=2000, seed=1).set_index("axis")
    for c, vt in zip("xyz", VEL):
        r = ens.loc[c]
        assert abs(r["v"] - vt) < 4 * r["v_err"]
        assert r["v_err"] == pytest.approx(r["v_err_model"], rel=0.3)     # one common drift: errors agree
        assert 0.5 < r["chi2_dof"] < 1.6
    again = V.ensemble_velocity(vel, n_boot=2000, seed=1)
    pd.testing.assert_frame_equal(ens.reset_index(), again)                 # same seed, same numbers
    # particles with truly different drifts: chi2 >> 1 and the bootstrap error exceeds the model error
    het = vel.copy()
    het["vz"] = het["vz"] + np.random.default_rng(0).normal(0, 2e-6, len(het))
    h = V.ensemble_velocity(het, axes="z", n_boot=2000, seed=2).iloc[0]
    assert h["chi2_dof"] > 3 and h["v_err"] > 1.5 * h["v_err_model"]


def _height_dependent_tracks(n_p, n_f, seed):
    """Overdamped drift v_z(z) = -v0 (1 + z / L) + Brownian, 10 substeps per frame (no noise)."""
    rng = np.random.default_rng(seed)
    v0, L, sub = 3e-6, 10e-6, 10
    z = rng.uniform(5e-6, 15e-6, n_p)
    x = np.zeros(n_p)
    h = DT / sub
    Z = np.empty((n_p, n_f))
    X = np.empty((n_p, n_f))
    Z[:, 0], X[:, 0] = z, x
    for f in range(1, n_f):
        for _ in range(sub):
            z = z - v0 * (1 + z / L) * h + math.sqrt(2 * D0 * h) * rng.standard_normal(n_p)
            x = x + math.sqrt(2 * D0 * h) * rng.standard_normal(n_p)
        Z[:, f], X[:, f] = z, x
    fr = np.tile(np.arange(n_f), n_p)
    pa = np.repeat(np.arange(n_p), n_f)
    df = make_table(fr, fr * DT, pa, X.ravel(), np.zeros(n_p * n_f), Z.ravel(), meta={"frame_interval": DT})
    return df, (lambda zz: -v0 * (1 + zz / L))


def test_velocity_profile_follows_a_height_dependent_drift():
    df, vz_of = _height_dependent_tracks(300, 40, seed=4)
    prof = V.velocity_profile(df, bins=np.arange(2e-6, 16e-6, 2e-6), axes="xz", motion_blur=0.0, n_boot=500, seed=0)
    used = prof[prof["n_particles"] >= 10]
    assert len(used) >= 5
    for _, r in used.iterrows():
        # increments are binned by their starting height: v(z_mean) is the truth to first order
        assert abs(r["vz"] - vz_of(r["z_mean"])) < 4 * r["vz_err"] + 0.02e-6, r.to_dict()
        assert abs(r["vx"]) < 4 * r["vx_err"]
    assert np.all(np.isnan(prof["vy"]))
    # errors are honest: chi^2 of the bins against the truth is near its dof
    chi2 = np.mean(((used["vz"] - vz_of(used["z_mean"])) / used["vz_err"]) ** 2)
    assert chi2 < 3


def test_instantaneous_velocity_exact_on_straight_lines_and_noise_as_documented():
    n_f = 20
    fr = np.r_[np.arange(8), np.arange(10, n_f)]                            # a gap: frames 8, 9 missing
    t = fr * DT
    df = make_table(fr, t, np.zeros(len(fr), int), 2e-6 * t, -1e-6 * t + 3e-6, 4e-6 - 5e-6 * t,
                    meta={"frame_interval": DT})
    out = V.instantaneous_velocity(df, window=2)
    np.testing.assert_allclose(out["vx"], 2e-6, rtol=1e-9)
    np.testing.assert_allclose(out["vy"], -1e-6, rtol=1e-9)
    np.testing.assert_allclose(out["vz"], -5e-6, rtol=1e-9)
    bt = V.drifting_tracks(400, 60, D0, DT, VEL, seed=2)
    iv = V.instantaneous_velocity(bt, window=1)
    inner = iv[(iv["frame"] > 0) & (iv["frame"] < 59)]
    assert inner["vz"].std() == pytest.approx(math.sqrt(2 * D0 / (2 * DT)), rel=0.05)
    assert inner["vz"].mean() == pytest.approx(VEL[2], abs=0.15e-6)
    two_d = make_table([0], [0.0], [1], [0.0], [0.0])
    assert np.isnan(V.instantaneous_velocity(two_d)["vx"]).all()          # a single position has no velocity


def test_trim_deposited_drops_rows_from_touch_down_on():
    rng = np.random.default_rng(3)
    n_f, R = 60, 0.4e-6
    z = np.maximum(8e-6 - 5e-6 * np.arange(n_f) * DT * 3, R)               # reaches contact at frame 31
    zn = z + rng.normal(0, 0.1e-6, n_f)
    zn[10] = R                                                               # one outlier near contact: no cut
    fr = np.r_[np.arange(n_f), np.arange(n_f)]
    pa = np.r_[np.zeros(n_f, int), np.ones(n_f, int)]
    zz = np.r_[zn, np.full(n_f, 5e-6)]                                       # particle 1 never comes down
    df = make_table(fr, fr * DT, pa, np.zeros(2 * n_f), np.zeros(2 * n_f), zz, meta={"frame_interval": DT})
    out = V.trim_deposited(df, R, tolerance=0.3e-6, window=5)
    f0 = out[out["particle"] == 0]["frame"]
    touch = int(np.argmax(z <= R + 1e-12))
    assert touch - 3 <= f0.max() + 1 <= touch and f0.min() == 0 and len(f0) == f0.max() + 1
    assert (out["particle"] == 1).sum() == n_f
    with pytest.raises(UserError, match="heights"):
        V.trim_deposited(df.assign(z=np.nan), R)


def test_trim_deposited_cuts_a_clean_descent_exactly_at_contact():
    # noise-free: free descent to the wall at frame k, then at rest. The running median describes its centre row,
    # so the cut is row k itself (the first row of the first low window would drop window // 2 free rows)
    R, k, n_f = 0.4e-6, 23, 40
    for window in (3, 5, 7):
        z = np.maximum(6e-6 - (6e-6 - R) * np.arange(n_f) / k, R)
        df = make_table(np.arange(n_f), np.arange(n_f) * DT, np.zeros(n_f, int), np.zeros(n_f), np.zeros(n_f), z,
                        meta={"frame_interval": DT})
        out = V.trim_deposited(df, R, tolerance=1e-9, window=window)
        assert out["frame"].max() == k - 1, window
        # a track that starts on the wall has no free rows; a level crossing mid-descent cuts at its first low row
        start = V.trim_deposited(df.assign(z=np.full(n_f, R)), R, tolerance=1e-9, window=window)
        assert len(start) == 0
        mid = V.trim_deposited(df, R, tolerance=3e-6, window=window)
        assert mid["frame"].max() + 1 == int(np.argmax(z <= R + 3e-6))


def test_bad_input_is_a_user_error():
    df2 = make_table(np.arange(10), np.arange(10) * DT, np.zeros(10, int), np.arange(10) * 1e-7, np.zeros(10))
    with pytest.raises(UserError, match="2D"):
        V.particle_velocity(df2, axes="xyz")
    with pytest.raises(UserError, match="unknown axis"):
        V.particle_velocity(df2, axes="xw")
    with pytest.raises(UserError, match="min_frames"):
        V.particle_velocity(df2, min_frames=2)
    with pytest.raises(UserError, match="motion_blur"):
        V.particle_velocity(df2, motion_blur=0.3)
    with pytest.raises(UserError, match="noise"):
        V.particle_velocity(df2, noise="global")
    with pytest.raises(UserError, match="twice"):
        V.particle_velocity(pd.concat([df2, df2.iloc[:1]]))
    with pytest.raises(UserError, match="heights"):
        V.velocity_profile(df2)
    short = V.particle_velocity(df2.iloc[:3])                                # too short: NaN, not a crash
    assert np.isnan(short["vx"]).all()
    vel = V.particle_velocity(df2)
    assert vel["vx"].iloc[0] == pytest.approx(1e-7 / DT, rel=1e-6)          # exact straight line


# ---------------------------------------------------------------- command

def _run_cmd(argv):
    from ptrack.commands import velocity_cmd as C

    p = argparse.ArgumentParser()
    C.add_arguments(p)
    return C.run(p.parse_args(argv))


def test_velocity_command_writes_table_profile_plot_and_json(tmp_path, capsys):
    df = V.drifting_tracks(30, 60, D0, DT, VEL, sigma=30e-9, gap_fraction=0.1, seed=2)
    df["z"] += 20e-6
    traj = write_table(df, tmp_path / "tr.parquet")
    out, js, rep = tmp_path / "v.csv", tmp_path / "s.json", tmp_path / "rep"
    assert _run_cmd([str(traj), "--motion-blur", "0", "--noise", "pooled", "--out", str(out), "--report", str(rep), "--json", str(js),
                     "--bins", "4", "--reference=-5.2e-6", "--contact", "1e-6"]) == 0
    text = capsys.readouterr().out
    assert "µm/s" in text and "bootstrap" in text and "standard errors" in text
    vel = pd.read_csv(out, comment="#")
    assert len(vel) == 30 and {"vx", "vx_err", "vz", "vz_err", "Dz", "z_mean", "n_frames"} <= set(vel.columns)
    s = json.loads(js.read_text())
    assert abs(s["v"]["z"] - VEL[2]) < 4 * s["v_err"]["z"] and len(s["profile"]) == 4
    assert (rep / "tr_velocity.png").stat().st_size > 10000 and (rep / "tr_velocity_profile.csv").is_file()


def test_velocity_command_bad_input_leaves_no_output(tmp_path):
    df = V.drifting_tracks(3, 10, D0, DT, VEL, seed=2)
    df["z"] = np.nan
    traj = write_table(df, tmp_path / "tr2d.parquet")
    with pytest.raises(UserError, match="2D"):
        _run_cmd([str(traj), "--axes", "xyz", "--out", str(tmp_path / "o.csv")])
    # the range of --min-frames is checked once, by ptrack.cli (ptrack.options)
    assert main(["velocity", str(traj), "--min-frames", "2"]) == 2
    with pytest.raises(UserError):
        _run_cmd([str(tmp_path / "missing.parquet")])
    with pytest.raises(UserError, match="heights"):
        _run_cmd([str(traj), "--contact", "4e-7", "--out", str(tmp_path / "o.csv")])
    assert not (tmp_path / "o.csv").exists() and not list(tmp_path.glob("*.png"))


def test_velocity_cli_registered():
    from ptrack.cli import COMMANDS, main

    if "velocity" not in COMMANDS:
        pytest.skip("'ptrack velocity' not registered in ptrack/cli.py yet (the lead wires it)")
    assert main(["velocity", "/nonexistent.parquet"]) == 2


# ---------------------------------------------------------------- shipped EPD dataset

DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic" / "epd_brightfield"


def test_velocity_of_the_true_epd_tracks_recovers_the_henry_velocity():
    params = json.loads((DATA / "params.json").read_text())
    truth = read_table(DATA / "truth.parquet")
    moving = truth[~truth["deposited"].astype(bool)]                     # before contact with the substrate
    vel = V.particle_velocity(moving, axes="xyz", motion_blur=0.0)
    ens = V.ensemble_velocity(vel, n_boot=2000, seed=0).set_index("axis")
    vz = params["vz_drift"]
    assert vz == pytest.approx(-(params["v_henry"] + params["v_sedimentation"]))
    assert abs(ens.loc["z", "v"] - vz) < 3 * ens.loc["z", "v_err"]
    assert ens.loc["z", "v_err"] < 0.1 * abs(vz)
    for c in "xy":
        assert abs(ens.loc[c, "v"]) < 3 * ens.loc[c, "v_err"]
    assert vel["Dz"].median() == pytest.approx(params["D_true"], rel=0.3)
    # the deposited rows found from z alone (as for measured tracks): the true ones plus the last 2-3 frames of the approach
    trimmed = V.trim_deposited(truth, params["radius"], tolerance=0.3e-6, window=3)
    assert 0.9 < len(trimmed) / len(moving) <= 1.0
    ens2 = V.ensemble_velocity(V.particle_velocity(trimmed, motion_blur=0.0), n_boot=2000, seed=0).set_index("axis")
    assert abs(ens2.loc["z", "v"] - vz) < 3 * ens2.loc["z", "v_err"]


def test_velocity_command_writes_into_the_working_folder_not_beside_the_input(tmp_path, monkeypatch, capsys):
    from ptrack.table import write_table

    data, work = tmp_path / "data", tmp_path / "work"
    data.mkdir()
    work.mkdir()
    traj = write_table(V.drifting_tracks(10, 30, D0, DT, VEL, seed=5), data / "tr.parquet")
    monkeypatch.chdir(work)
    assert _run_cmd([str(traj), "--motion-blur", "0", "--bins", "0"]) == 0
    assert (work / "tr_velocity.csv").exists() and (work / "tr_velocity.png").exists()
    assert sorted(p.name for p in data.iterdir()) == ["tr.parquet"]


def test_velocity_command_no_velocity_message_counts_positions_not_rows(tmp_path, capsys):
    """Issue 15: 'no track has 5 or more positions (longest: 30)' contradicted itself: rows are not positions
    when a coordinate is NaN."""
    from ptrack.table import write_table

    df = V.drifting_tracks(6, 30, D0, DT, VEL, seed=6)
    z = df["z"].to_numpy().copy()
    z[df["frame"].to_numpy() % 10 != 0] = np.nan        # z found in 3 of 30 frames
    df["z"] = z
    traj = write_table(df, tmp_path / "tr.parquet")
    from ptrack.errors import UserError

    with pytest.raises(UserError, match=r"the most positions with a finite z in one track is 3 \(of 30 rows\)"):
        _run_cmd([str(traj), "--axes", "z", "--report", str(tmp_path / "r")])
