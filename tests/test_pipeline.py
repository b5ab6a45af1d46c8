"""End to end: rendered diffusion movie -> track -> table -> analyze, from Python and the command line."""
import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from ptrack.errors import UserError
from ptrack.motion import match_truth
from ptrack.msd import estimate_diffusion, stokes_einstein
from ptrack.analysis import analyze_movie
from ptrack.pipeline import track_movie
from ptrack.table import make_table, read_table, validate

render = pytest.importorskip("sim.render")

D_TRUE = 0.86e-12
DT = 0.1


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """12 particles diffusing in 2D in a 140 x 140 px view, 60 frames, 2000 detected photons each."""
    rng = np.random.default_rng(11)
    cam = render.Camera(photons=2000 / 0.6)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    n, T = 12, 60
    x0 = rng.uniform(25, 115, n) * px
    y0 = rng.uniform(25, 115, n) * px
    steps = rng.normal(0, np.sqrt(2 * D_TRUE * DT), (2, n, T))
    steps[:, :, 0] = 0
    x = x0[:, None] + steps[0].cumsum(1)
    y = y0[:, None] + steps[1].cumsum(1)
    fr = np.tile(np.arange(T), n)
    table = make_table(fr, fr * DT, np.repeat(np.arange(n), T), x.ravel(), y.ravel(), np.zeros(n * T),
                       meta={"frame_interval": DT})
    d = tmp_path_factory.mktemp("movie")
    info = render.render_movie(table, d, shape=(140, 140), camera=cam, seed=12, progress=False)
    truth = pd.read_parquet(info["truth"])
    return {"path": info["movie"], "truth": truth, "px": px, "cam": cam, "dir": d}


def _camera(m):
    return dict(gain=m["cam"].gain, offset=m["cam"].offset, read_noise=m["cam"].read_noise)


def test_match_truth_pairs_within_each_frame_and_one_to_one_when_mutual():
    """The one truth-matching rule: nearest true particle of the same frame, closer than max_px; mutual=True keeps
    one localisation per true particle (the nearer one)."""
    truth = pd.DataFrame({"frame": [0, 0, 1], "x_px": [10.0, 20.0, 10.0], "y_px": [10.0, 10.0, 30.0]},
                         index=[7, 8, 9])
    found = pd.DataFrame({"frame": [0, 0, 0, 1, 1], "x_px": [10.3, 10.9, 30.0, 10.0, 10.0],
                          "y_px": [10.0, 10.0, 10.0, 10.0, 30.5]}, index=[100, 101, 102, 103, 104])
    fi, ti = match_truth(found, truth)
    # 100 and 101 both on 7; 102 is 10 px from 8; 103 sits on frame 0's particle 7 but is in frame 1 (20 px from 9)
    assert fi.tolist() == [100, 101, 104] and ti.tolist() == [7, 7, 9]
    fi, ti = match_truth(found, truth, mutual=True)
    assert fi.tolist() == [100, 104] and ti.tolist() == [7, 9]
    fi, ti = match_truth(found, truth, max_px=0.4)
    assert fi.tolist() == [100] and ti.tolist() == [7]
    fi, ti = match_truth(found.iloc[:0], truth)
    assert len(fi) == 0 and len(ti) == 0


def test_track_movie_table_and_links(movie, tmp_path):
    out = tmp_path / "t.parquet"
    table, summary = track_movie(movie["path"], out=out, progress=False, **_camera(movie))
    t = read_table(out)
    meta = t.attrs["ptrack"]
    assert meta["pixel_size"] == pytest.approx(movie["px"]) and meta["frame_interval"] == pytest.approx(DT)
    np.testing.assert_allclose(t["x"], t["x_px"] * movie["px"])
    assert np.isnan(t["z"]).all() and (t["sigma_x"] > 0).all()
    assert summary["n_frames"] == 60 and summary["n_tracks"] == t["particle"].nunique()
    # per-stage times, with the multi-scale locator's own split of "locate" (its parts cannot exceed it)
    st = summary["stage_times_s"]
    parts = [st[k] for k in ("locate.detect", "locate.fit", "locate.centres")]
    assert all(v >= 0 for v in parts) and 0 < sum(parts) <= st["locate"] * 1.01 + 1e-3
    # every localisation sits on a true particle, and links follow one true particle (ptrack.motion.match_truth:
    # the one truth-matching rule)
    truth = movie["truth"]
    fi, _ = match_truth(t, truth, max_px=1.0)
    assert len(fi) / len(t) > 0.95                  # the rest: two particles overlapping
    fi, ti = match_truth(t, truth, max_px=0.5)      # not merged with a neighbour
    m = pd.DataFrame({"particle": t.loc[fi, "particle"].to_numpy(), "frame": t.loc[fi, "frame"].to_numpy(),
                      "true": truth.loc[ti, "particle"].to_numpy()}).sort_values(["particle", "frame"])
    same_track = m["particle"].to_numpy()[1:] == m["particle"].to_numpy()[:-1]
    same_true = m["true"].to_numpy()[1:] == m["true"].to_numpy()[:-1]
    assert same_true[same_track].mean() > 0.97      # links join the same true particle
    in_view = truth[(truth["x_px"] > 3) & (truth["x_px"] < 136) & (truth["y_px"] > 3) & (truth["y_px"] < 136)]
    assert len(t) / len(in_view) > 0.95


def test_diffusion_matches_truth_tracks(movie):
    table, _ = track_movie(movie["path"], progress=False, **_camera(movie))
    truth = movie["truth"]
    truth = truth[truth["in_frame"]] if "in_frame" in truth else truth
    tt = validate(make_table(truth["frame"], truth["t"], truth["particle"], truth["x"], truth["y"],
                             meta={"frame_interval": DT}))
    d_ours = estimate_diffusion(table, axes=("xy",), n_boot=0).D["xy"]
    d_truth = estimate_diffusion(tt, axes=("xy",), n_boot=0).D["xy"]
    assert d_ours == pytest.approx(d_truth, rel=0.06)


def test_analyze_movie_report(movie, tmp_path):
    rep = tmp_path / "rep"
    s = analyze_movie(movie["path"], radius=250e-9, viscosity=1e-3, temperature=293.15, report_dir=rep,
                      height=2e-6, progress=False, n_boot=50, **_camera(movie)).summary
    assert s["D_stokes_einstein"] == pytest.approx(stokes_einstein(250e-9, 1e-3, 293.15))
    assert set(s["D"]) == {"x", "y", "xy"} and all(v > 0 for v in s["D_err"].values())
    assert s["D"]["xy"] == pytest.approx(D_TRUE, rel=0.3)
    assert s["n_tracks"] >= 10
    assert 0.6 < s["hindered"]["ratio_parallel"] < 1.0
    assert s["hindered"]["D_bulk_xy"] > s["D"]["xy"]
    for f in ("tracks.png", "msd.png", "D_per_particle.png", "summary.json"):
        assert (rep / f).stat().st_size > 1000 or f == "summary.json"
    assert json.loads((rep / "summary.json").read_text())["n_tracks"] == s["n_tracks"]
    with pytest.raises(UserError, match="radius"):
        analyze_movie(movie["path"], radius=-1, viscosity=1e-3, temperature=293.15)


@pytest.mark.slow          # a local dask cluster in a subprocess: ~1 min on 2 loaded cores
def test_cli_track_json_and_several_movies_with_dask(movie, tmp_path):
    import shutil

    cam = ["--gain", str(movie["cam"].gain), "--offset", str(movie["cam"].offset)]
    js = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "ptrack", "track", str(movie["path"]), "--out", str(tmp_path / "one.parquet"),
                        "--json", str(js)] + cam, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    s = json.loads(js.read_text())
    assert {"n_frames", "n_localisations", "n_tracks", "wall_time_s", "frames_per_s"} <= set(s)
    # one movie name in two folders (as microscopes save them): each output is named by its folder too
    a, b = tmp_path / "run1" / "movie.tif", tmp_path / "run2" / "movie.tif"
    for m in (a, b):
        m.parent.mkdir()
        shutil.copy(movie["path"], m)
    outdir = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "ptrack", "track", str(a), str(b), "--out", str(outdir), "--workers", "1",
                        "--json", str(js)] + cam, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in outdir.iterdir()) == ["run1_movie.traj.parquet", "run2_movie.traj.parquet"]
    ta, tb = read_table(outdir / "run1_movie.traj.parquet"), read_table(outdir / "run2_movie.traj.parquet")
    cols = ["frame", "x_px", "y_px", "mass", "sigma_x"]       # same localisations from both workers' runs
    pd.testing.assert_frame_equal(ta[cols].sort_values(cols[:3]).reset_index(drop=True),
                                  tb[cols].sort_values(cols[:3]).reset_index(drop=True))
    assert ta["particle"].nunique() == tb["particle"].nunique()
    assert json.loads(js.read_text())["n_frames"] == 120


def test_cli_analyze_and_missing_calibration(movie, tmp_path):
    import tifffile

    with tifffile.TiffFile(movie["path"]) as tf:
        frames = tf.asarray()
    bare = tmp_path / "bare.tif"
    tifffile.imwrite(bare, frames)                          # no pixel size, no frame interval
    r = subprocess.run([sys.executable, "-m", "ptrack", "analyze", str(bare), "--radius", "250e-9", "--viscosity", "1e-3",
                        "--temperature", "293.15"], capture_output=True, text=True)
    assert r.returncode == 2 and "--pixel-size" in r.stderr
    rep = tmp_path / "rep"
    r = subprocess.run([sys.executable, "-m", "ptrack", "analyze", str(bare), "--pixel-size", str(movie["px"]),
                        "--frame-interval", "0.1", "--radius", "250e-9", "--viscosity", "1e-3", "--temperature", "293.15",
                        "--report", str(rep), "--json", str(tmp_path / "a.json")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "µm²/s" in r.stdout
    s = json.loads((tmp_path / "a.json").read_text())
    assert {"D", "D_err", "D_stokes_einstein", "n_tracks"} <= set(s)
    # both D estimates, which one is reported and why (the rule of ptrack.analysis.choose_D, whose every branch
    # tests/test_analysis.py covers): agreeing estimates -> the more precise; else the pairs only if links are
    # ambiguous
    assert set(s["D_tracks"]) == {"x", "y", "xy"} and s["D_pairs"] is not None
    pr = s["D_pairs"]
    z = abs(pr["D"]["xy"] - s["D_tracks"]["xy"]) / max(pr["D_err"]["xy"], s["D_tracks_err"]["xy"])
    if z <= 2:
        assert s["D_method_reason"].startswith("the estimates agree")
        pairs_chosen = pr["D_err"]["xy"] < s["D_tracks_err"]["xy"]
    else:
        pairs_chosen = pr["link_ambiguity"] > 0.05
        assert ("ambiguous" in s["D_method_reason"]) == pairs_chosen
    assert s["D_method"] == ("linking-free (pairs)" if pairs_chosen else "tracks")
    assert s["D"]["xy"] == (pr["D"]["xy"] if pairs_chosen else s["D_tracks"]["xy"])
    assert s["D_method_reason"] in r.stdout
    # the rendered movie has no motion blur, and R comes from the data, said
    assert s["motion_blur_source"].startswith("data") and s["motion_blur"] < 0.05
    assert "motion blur R = " in r.stdout
    # no drift in this movie: the ensemble drift is 0 within errors
    assert set(s["drift_velocity"]) == {"x", "y"}
    for v in s["drift_velocity"].values():
        assert abs(v["v"]) < 4 * v["v_err"]
