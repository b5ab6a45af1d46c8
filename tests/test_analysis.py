"""ptrack.analysis: the analysis defaults a new user meets (issue 13) and the all-or-nothing report (issue 15)."""
import json

import numpy as np
import pytest

from ptrack.analysis import analyze_movie, analyze_table, choose_D, write_report
from ptrack.errors import UserError
from ptrack.motion import brownian_field, brownian_tracks, resolve_motion_blur
from ptrack.motion.tracks import check_motion_blur
from ptrack.table import make_table

D0, DT, RADIUS = 8.6e-13, 0.1, 250e-9


def _table_3d(z_low=-2.5e-6, z_high=2.5e-6, n_p=30, n_f=60, seed=4):
    """Brownian tracks in x, y with heights spread between z_low and z_high (m)."""
    rng = np.random.default_rng(seed)
    p = brownian_tracks(n_p, n_f, D0, DT, 20e-9, 0.0, n_dims=2, seed=seed)
    p += rng.uniform(0, 30e-6, (n_p, 1, 2))
    # heights: a particle near each level, with 50 nm of localisation noise in z
    z = np.linspace(z_low, z_high, n_p)[:, None] + 50e-9 * rng.standard_normal((n_p, n_f))
    fr = np.tile(np.arange(n_f), n_p)
    return make_table(fr, fr * DT, np.repeat(np.arange(n_p), n_f), p[..., 0].ravel(), p[..., 1].ravel(),
                      z.ravel(), meta={"frame_interval": DT})


def test_3d_wall_comes_from_the_data_not_the_focal_plane():
    a = analyze_table(_table_3d(), RADIUS, 1e-3, 293.15, motion_blur=0.0, n_boot=0)
    h = a.summary["hindered"]
    assert h["wall_z_source"].startswith("from the data")
    # lowest centre heights (-2.5 um) minus the radius: the wall, to within the 0.5 % quantile's resolution
    assert h["wall_z_m"] == pytest.approx(-2.5e-6 - RADIUS, abs=0.15e-6)
    assert h["n_particles_below_contact"] == 0 and 0 < h["mean_ratio_parallel"] < 1
    # D is the same at every height here (no hydrodynamic wall): the data say so and D is not "corrected"
    assert h["applied"] is False and h["evidence"]["favours"] == "no wall" and "D_bulk_xy" not in h
    assert h["D_bulk_xy_if_applied"] > a.summary["D"]["xy"]
    assert any("wall correction not applied" in n and "--wall-z" in n for n in a.notes)


def test_shipped_3d_truth_is_not_wall_corrected_and_gives_the_free_D():
    """diffusion3d: free diffusion between reflecting planes at +-2.5 um (sim.render.datasets), no hydrodynamic wall.

    The old default put a wall at the lowest heights and reported D 10 % above the rendered free D."""
    import json as _json
    from pathlib import Path

    from ptrack.table import read_table

    root = Path(__file__).resolve().parents[1] / "data" / "synthetic" / "diffusion3d"
    truth = read_table(root / "truth.parquet")
    truth = truth[truth["in_frame"]].copy()
    rng = np.random.default_rng(0)
    for c, s in (("x", 20e-9), ("y", 20e-9), ("z", 60e-9)):     # the movie's localisation errors
        truth[c] = truth[c] + s * rng.standard_normal(len(truth))
    D_true = _json.loads((root / "params.json").read_text())["D_true"]
    s = analyze_table(truth, RADIUS, 1e-3, 293.15, n_boot=100).summary
    h = s["hindered"]
    assert h["applied"] is False and h["evidence"]["favours"] != "wall"
    assert abs(s["D"]["xy"] - D_true) < 2 * s["D_err"]["xy"]


def test_particles_below_a_given_wall_stop_the_correction_with_a_message():
    # the old default: the wall at the focal plane z = 0, half the particles below it
    a = analyze_table(_table_3d(), RADIUS, 1e-3, 293.15, wall_z=0.0, motion_blur=0.0, n_boot=0)
    h = a.summary["hindered"]
    assert h["applied"] is False and "D_bulk_xy" not in h and h["n_particles_below_contact"] >= 14
    assert any("wall correction not applied" in n and "--wall-z" in n for n in a.notes)


@pytest.mark.parametrize("R", [0.0, 1 / 6])
def test_motion_blur_from_the_data_when_the_table_has_the_localisers_sigma(R):
    sigma = 30e-9
    p = brownian_tracks(60, 100, D0, DT, sigma, R, n_dims=2, seed=7)
    fr = np.tile(np.arange(100), 60)
    n = fr.size
    df = make_table(fr, fr * DT, np.repeat(np.arange(60), 100), p[..., 0].ravel(), p[..., 1].ravel(),
                    meta={"frame_interval": DT}, sigma_x=np.full(n, sigma), sigma_y=np.full(n, sigma))
    got, source = resolve_motion_blur(df)
    assert source.startswith("data") and got == pytest.approx(R, abs=0.03)
    # given beats data; metadata beats data; nothing at all: 1/6, said
    assert resolve_motion_blur(df, 0.1) == (0.1, "given")
    df.attrs["ptrack"]["exposure"] = 0.05
    got, source = resolve_motion_blur(df)
    assert got == pytest.approx(0.05 / DT / 6) and source.startswith("metadata: exposure 0.05 s / frame interval")
    bare = df.drop(columns=["sigma_x", "sigma_y"])
    bare.attrs = {}
    assert resolve_motion_blur(bare)[1].startswith("default")
    # simulated positions (and the ground truth of a rendered movie) are instantaneous: R = 0, not 1/6
    bare.attrs = {"ptrack": {"source": "sim.render ground truth", "frame_interval": DT}}
    assert resolve_motion_blur(bare) == (0.0, "metadata: simulated positions are instantaneous")


def test_one_motion_blur_range_for_every_estimator():
    from ptrack.motion import estimate_diffusion, particle_velocity

    df = brownian_field(20, 20e-6, 0.05e12, D0, DT, seed=1)
    for f in (lambda R: estimate_diffusion(df, motion_blur=R, n_boot=0),
              lambda R: particle_velocity(df, motion_blur=R),
              lambda R: brownian_tracks(2, 10, D0, DT, motion_blur=R)):
        f(0.2)                                                   # inside [0, 1/4) everywhere
        with pytest.raises(UserError, match=r"outside \[0, 1/4\)"):
            f(0.25)
    assert check_motion_blur(0.0) == 0.0


@pytest.mark.parametrize("argv", [["msd", "t.parquet", "--motion-blur", "0.3"],
                                  ["velocity", "t.parquet", "--motion-blur", "0.3"],
                                  ["compare", "a.parquet", "b.parquet", "--motion-blur", "0.3"]])
def test_the_command_line_refuses_R_with_the_library_rule_and_message(argv, capsys):
    from ptrack.cli import main

    with pytest.raises(UserError) as api:
        check_motion_blur(0.3, "--motion-blur")
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == f"error: {api.value}"


@pytest.mark.parametrize("pairs, expected, why", [
    (None, "tracks", "no linking-free"),
    ({"D": {"xy": 1.01}, "D_err": {"xy": 0.02}, "link_ambiguity": 0.01}, "linking-free (pairs)", "agree"),
    ({"D": {"xy": 1.01}, "D_err": {"xy": 0.08}, "link_ambiguity": 0.01}, "tracks", "agree"),
    ({"D": {"xy": 1.30}, "D_err": {"xy": 0.05}, "link_ambiguity": 0.20}, "linking-free (pairs)", "ambiguous"),
    ({"D": {"xy": 1.30}, "D_err": {"xy": 0.05}, "link_ambiguity": 0.01}, "tracks", "correlated"),
])
def test_which_D_is_reported_and_why(pairs, expected, why):
    method, reason = choose_D({"xy": 1.0}, {"xy": 0.05}, pairs)
    assert method == expected and why in reason


def test_analyze_checks_every_parameter_before_tracking(tmp_path):
    # the movie does not exist: a parameter error must come first, before any file is touched
    with pytest.raises(UserError, match="height"):
        analyze_movie(tmp_path / "none.tif", radius=1e-6, viscosity=1e-3, temperature=293.15, height=0.5e-6)
    with pytest.raises(UserError, match="motion_blur"):
        analyze_movie(tmp_path / "none.tif", radius=1e-6, viscosity=1e-3, temperature=293.15, motion_blur=0.3)
    with pytest.raises(UserError, match="not a folder"):
        (tmp_path / "file").write_text("x")
        analyze_movie(tmp_path / "none.tif", radius=1e-6, viscosity=1e-3, temperature=293.15,
                      report_dir=tmp_path / "file")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    import os

    if not os.access(ro, os.W_OK):              # (root may write anywhere)
        with pytest.raises(UserError, match="cannot write"):
            analyze_movie(tmp_path / "none.tif", radius=1e-6, viscosity=1e-3, temperature=293.15, out=ro / "t.parquet")
    with pytest.raises(UserError, match="is a folder"):
        analyze_movie(tmp_path / "none.tif", radius=1e-6, viscosity=1e-3, temperature=293.15, out=tmp_path)


def test_interrupted_report_leaves_no_half_report(tmp_path, monkeypatch):
    from ptrack import plot

    df = brownian_field(40, 30e-6, 0.06e12, D0, DT, sigma=20e-9, seed=3)
    a = analyze_table(df, RADIUS, 1e-3, 293.15, motion_blur=0.0, n_boot=0)
    rep = tmp_path / "rep"
    write_report(a, rep)
    before = sorted(p.name for p in rep.iterdir())
    assert {"summary.json", "msd.png", "D_per_particle.png", "per_particle.csv"} <= set(before)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plot, "plot_D_per_particle", interrupted)    # Ctrl-C after msd.png was written
    with pytest.raises(KeyboardInterrupt):
        write_report(a, tmp_path / "new")
    with pytest.raises(KeyboardInterrupt):
        write_report(a, rep)
    assert not (tmp_path / "new").exists()
    assert sorted(p.name for p in rep.iterdir()) == before             # the previous report, untouched
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert json.loads((rep / "summary.json").read_text())["n_tracks"] == a.summary["n_tracks"]
    # a report into a folder that holds other files (the trajectories table) keeps them
    (rep / "trajectories.parquet").write_bytes(b"table")
    monkeypatch.undo()
    write_report(a, rep)
    assert (rep / "trajectories.parquet").read_bytes() == b"table" and (rep / "msd.png").exists()


def test_motion_blur_of_a_rendered_movie_comes_from_its_params_json(tmp_path):
    """GDPT tables have no sigma_x/sigma_y: R comes from the movie's metadata, not the 1/6 default. The renderer's
    params.json holds exposure (s) and motion_blur_substeps (0: positions drawn at an instant, R = 0); the old text
    key "motion_blur": "none (short exposure)" is read as no number, not as an error."""
    movie = tmp_path / "movie.tif"
    movie.write_bytes(b"")
    params = {"source": "sim.render.render_movie", "exposure": 0.1, "frame_interval": 0.1, "motion_blur_substeps": 0,
              "motion_blur": "none (short exposure)"}
    (tmp_path / "params.json").write_text(json.dumps(params))
    df = _table_3d()
    df.attrs["ptrack"] = {"source": str(movie), "kind": "measured", "frame_interval": DT}
    R, source = resolve_motion_blur(df)
    assert R == 0.0 and source.startswith("movie metadata (params.json): rendered without motion blur")
    params["motion_blur_substeps"] = 8                 # blurred over an exposure of half the frame: R = 0.5 / 6
    params["exposure"] = 0.05
    (tmp_path / "params.json").write_text(json.dumps(params))
    assert resolve_motion_blur(df)[0] == pytest.approx(0.05 / 0.1 / 6)
    (tmp_path / "params.json").unlink()                # no metadata, no sigma columns: the default, said
    assert resolve_motion_blur(df)[1].startswith("default")


def test_motion_blur_from_data_is_the_one_rule_with_a_bootstrap_error():
    from ptrack.motion.tracks import motion_blur_from_data

    sigma = 30e-9
    for R_true in (0.0, 0.1):
        p = brownian_tracks(80, 100, D0, DT, sigma, R_true, n_dims=2, seed=11)
        fr = np.tile(np.arange(100), 80)
        df = make_table(fr, fr * DT, np.repeat(np.arange(80), 100), p[..., 0].ravel(), p[..., 1].ravel(),
                        meta={"frame_interval": DT}, sigma_x=np.full(fr.size, sigma), sigma_y=np.full(fr.size, sigma))
        R, err = motion_blur_from_data(df, n_boot=200, seed=1)
        assert 0 < err < 0.02 and abs(R - R_true) < 3 * err + 1e-3
        assert motion_blur_from_data(df)[1] != motion_blur_from_data(df)[1]      # NaN: no resamples, no error
    assert motion_blur_from_data(df.drop(columns=["sigma_x", "sigma_y"])) == (None, None)


def test_default_axes_one_rule_for_velocity_and_analysis():
    from ptrack.motion.velocity import default_axes

    t = _table_3d()
    assert default_axes(t) == ("x", "y", "z")
    t["z"] = 1e-6                               # heights given but the same everywhere: no motion along z
    assert default_axes(t) == ("x", "y")
    t["z"] = np.nan
    assert default_axes(t) == ("x", "y")


def test_a_2d_table_with_z_zero_is_analysed_as_2d():
    """z = 0 in every row (what many tools write for 2D) is 2D by the one axes rule: the given height is used,
    not every particle read at a wall at z = 0 (that raised 'height ... not above the particle radius')."""
    xy = brownian_tracks(20, 60, 0.5e-12, 0.1, n_dims=2, seed=3)
    n, T, _ = xy.shape
    fr = np.tile(np.arange(T), n)
    out = []
    for z in (np.zeros(n * T), np.full(n * T, np.nan)):
        t = make_table(fr, fr * 0.1, np.repeat(np.arange(n), T), xy[:, :, 0].ravel(), xy[:, :, 1].ravel(), z,
                       meta={"frame_interval": 0.1, "kind": "truth"})
        out.append(analyze_table(t, 4.3e-7, 1e-3, 293.15, height=600e-9, n_boot=20).summary)
    assert out[0]["D"] == out[1]["D"] and out[0]["hindered"] == out[1]["hindered"]
    assert out[0]["hindered"]["applied"]
