"""Tests of the `ptrack msd` command."""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ptrack import msd as M
from ptrack.cli import main
from ptrack.table import make_table, write_table

D_SE = 8.589e-13   # r = 250 nm, water, 293.15 K (seed)
DT = 0.05


def _write(path, n_p=25, n_f=200, D=D_SE, seed=0, radius=None, z=False):
    p = M.brownian_tracks(n_p, n_f, D, DT, 25e-9, 1 / 6, n_dims=3 if z else 2, seed=seed)
    fr = np.tile(np.arange(n_f), n_p)
    pa = np.repeat(np.arange(n_p), n_f)
    opt = {} if radius is None else {"radius": np.full(n_p * n_f, radius)}
    df = make_table(fr, fr * DT, pa, p[..., 0].ravel(), p[..., 1].ravel(), z=p[..., 2].ravel() if z else None,
                    meta={"frame_interval": DT}, **opt)
    write_table(df, path)
    return path


def test_msd_command_reports_d_stokes_einstein_json_and_plot(tmp_path, capsys):
    traj = _write(tmp_path / "tr.parquet")
    out, png = tmp_path / "o.json", tmp_path / "m.png"
    rc = main(["msd", str(traj), "--radius", "250e-9", "--viscosity", "1e-3", "--json", str(out), "--plot", str(png)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "µm²/s" in text and "m^2/s" in text and "D/D_SE" in text and "25 tracks" in text
    res = json.loads(out.read_text())
    assert res["D_stokes_einstein"] == pytest.approx(8.589e-13, rel=2e-4)
    assert res["n_particles"] == 25 and res["estimator"] == "cve"
    assert set(res["D"]) == {"x", "y", "xy"} == set(res["D_err"])
    for a in ("x", "y", "xy"):
        assert abs(res["D"][a] - D_SE) < 4 * res["D_err"][a]
        assert res["ratio_D_over_D_SE"][a] == pytest.approx(res["D"][a] / D_SE, rel=1e-3)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_msd_command_ols_3d_and_radius_from_table(tmp_path, capsys):
    traj = _write(tmp_path / "tr3.csv", z=True, radius=250e-9)
    out = tmp_path / "o.json"
    rc = main(["msd", str(traj), "--dims", "x,y,z,xyz", "--estimator", "ols", "--viscosity", "1e-3",
               "--json", str(out), "--no-plot"])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["estimator"] == "ols" and all(res["n_lags"][a] >= 2 for a in ("x", "y", "z", "xyz"))
    assert res["D_stokes_einstein"] == pytest.approx(8.589e-13, rel=2e-4)
    assert abs(res["D"]["xyz"] - D_SE) < 4 * res["D_err"]["xyz"]
    assert not (tmp_path / "tr3_msd.png").exists()


def test_msd_command_default_plot_and_flags(tmp_path, capsys, monkeypatch):
    """The default plot goes into the working folder, not beside the input (issue 13)."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    p = M.brownian_tracks(30, 150, D_SE, DT, 20e-9, 1 / 6, n_dims=2, seed=3)
    p[0, :, 0] += 2.0 * math.sqrt(2 * D_SE * DT) * np.arange(150)     # advected track
    fr = np.tile(np.arange(150), 30)
    pa = np.repeat(np.arange(30), 150)
    traj = write_table(make_table(fr, fr * DT, pa, p[..., 0].ravel(), p[..., 1].ravel()), tmp_path / "adv.parquet")
    out = tmp_path / "o.json"
    per = tmp_path / "tracks.csv"
    assert main(["msd", str(traj), "--json", str(out), "--exclude-flagged", "--tracks-out", str(per)]) == 0
    res = json.loads(out.read_text())
    import pandas as pd
    tab = pd.read_csv(per, comment="#")
    assert len(tab) == 30 and bool(tab.set_index("particle").loc[0, "flagged"])
    assert {"D_x", "D_x_err", "D_xy", "alpha", "reason"} <= set(tab.columns)
    assert 0 in [f["particle"] for f in res["flagged"]]
    assert res["n_particles"] <= 29 and res["excluded_flagged"]
    assert "directed" in capsys.readouterr().out
    assert (work / "adv_msd.png").exists() and not (tmp_path / "adv_msd.png").exists()


@pytest.mark.parametrize("args,needle", [
    (["{missing}"], "not found"),
    (["{corrupt}"], "cannot read"),
    (["{traj}", "--radius", "nan", "--viscosity", "1e-3"], "--radius"),
    (["{traj}", "--radius=-2e-7", "--viscosity", "1e-3"], "--radius"),
    (["{traj}", "--radius", "2e-7"], "--viscosity"),
    (["{traj}", "--dims", "x,w"], "unknown axis 'w'"),
    (["{traj}", "--dims", "z"], "2D"),
    (["{short}"], "shorter than 3"),
    (["{traj}", "--plot", "{dir}/m.jpg"], ".png"),
    (["{traj}", "--tracks-out", "{dir}/t.txt"], ".csv"),
])
def test_msd_command_bad_input_one_line_exit_2_no_output(tmp_path, capsys, args, needle):
    traj = _write(tmp_path / "tr.parquet", n_p=3, n_f=30)
    (tmp_path / "bad.parquet").write_bytes(b"not a parquet file at all")
    short = write_table(make_table([0, 1, 0, 1], [0, .1, 0, .1], [0, 0, 1, 1], [0, 1e-7, 0, 2e-7], [0, 0, 0, 0]),
                        tmp_path / "short.csv")
    sub = {"missing": str(tmp_path / "nope.parquet"), "corrupt": str(tmp_path / "bad.parquet"),
           "traj": str(traj), "short": str(short), "dir": str(tmp_path)}
    argv = [a.format(**sub) for a in args]
    out = tmp_path / "o.json"
    before = set(tmp_path.iterdir())
    rc = main(["msd", *argv, "--json", str(out)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err
    assert set(tmp_path.iterdir()) == before       # no JSON, no plot, no temporary files


def test_msd_console_script_exit_status(tmp_path):
    r = subprocess.run([sys.executable, "-m", "ptrack", "msd", str(tmp_path / "none.parquet")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "not found" in r.stderr


def test_msd_command_field_of_view_and_linking_free(tmp_path, capsys):
    # Brownian tracks spread over a wide area: the linking-free estimate (identities ignored) and the
    # field-of-view-corrected one both recover D; the JSON says what was done
    n_p, n_f, D = 60, 120, D_SE
    rng = np.random.default_rng(3)
    start = rng.uniform(0, 40e-6, (n_p, 1, 2))
    p = start + M.brownian_tracks(n_p, n_f, D, DT, 10e-9, 0.0, n_dims=2, seed=4)
    fr = np.tile(np.arange(n_f), n_p)
    pa = np.repeat(np.arange(n_p), n_f)
    df = make_table(fr, fr * DT, pa, p[..., 0].ravel(), p[..., 1].ravel(), meta={"frame_interval": DT},
                    sigma_x=np.full(n_p * n_f, 10e-9), sigma_y=np.full(n_p * n_f, 10e-9))
    traj = tmp_path / "tr.parquet"
    write_table(df, traj)
    out = tmp_path / "o.json"
    rc = main(["msd", str(traj), "--motion-blur", "0", "--field-of-view", "x,y", "--linking-free", "--no-plot",
               "--json", str(out)])
    assert rc == 0
    assert "linking-free" in capsys.readouterr().out
    res = json.loads(out.read_text())
    assert set(res["field_of_view"]) == {"x", "y"}
    lf = res["linking_free"]
    assert abs(lf["D"]["xy"] - D) < 4 * lf["D_err"]["xy"]
    assert lf["link_ambiguity"] < 0.05
    assert main(["msd", str(traj), "--field-of-view", "q"]) == 2


def _camera_table(tmp_path, name="cam.parquet", scale=1.0, **kw):
    """Brownian tracks cut by a square field as a camera sees them (x_px columns), positions times ``scale``."""
    df = M.brownian_field(n_frames=80, size=25e-6, density=0.08e12, D=D_SE, dt=DT, sigma=20e-9, seed=5)
    px = 1e-7
    df["x_px"], df["y_px"] = df["x"] / px, df["y"] / px
    df["x"], df["y"] = df["x"] * scale, df["y"] * scale
    return write_table(df, tmp_path / name)


def test_msd_command_corrects_the_field_of_view_by_default_for_camera_tables(tmp_path, capsys):
    """Measured tables (x_px columns) get the field-of-view correction without a flag; --field-of-view none
    gives the biased-low D the issue measured (-4.5 % for its tracks; here a few per cent)."""
    traj = _camera_table(tmp_path)
    js_def, js_none = tmp_path / "d.json", tmp_path / "n.json"
    assert main(["msd", str(traj), "--motion-blur", "0", "--dims", "xy", "--no-plot", "--json", str(js_def)]) == 0
    out = capsys.readouterr().out
    assert "field of view corrected (x, y; default for a table from a camera" in out
    assert main(["msd", str(traj), "--motion-blur", "0", "--dims", "xy", "--no-plot", "--field-of-view", "none",
                 "--json", str(js_none)]) == 0
    d, n = json.loads(js_def.read_text()), json.loads(js_none.read_text())
    assert d["field_of_view"] is not None and n["field_of_view"] is None
    assert abs(d["D"]["xy"] / D_SE - 1) < 3 * d["D_err"]["xy"] / D_SE
    assert n["D"]["xy"] < d["D"]["xy"]


def test_msd_command_says_where_the_motion_blur_comes_from(tmp_path, capsys):
    traj = _write(tmp_path / "tr.parquet")
    assert main(["msd", str(traj), "--no-plot"]) == 0
    assert "R = 0.1667 (default: R = 1/6" in capsys.readouterr().out
    assert main(["msd", str(traj), "--no-plot", "--motion-blur", "0"]) == 0
    assert "R = 0 (given)" in capsys.readouterr().out


def test_msd_command_warns_when_a_pixel_table_is_read_as_metres(tmp_path, capsys):
    traj = _camera_table(tmp_path, "px.parquet", scale=1e7)          # positions in px, labelled m
    assert main(["msd", str(traj), "--motion-blur", "0", "--no-plot"]) == 0
    assert "warning: D = " in capsys.readouterr().out


def test_msd_command_refuses_coordinates_that_overflow(tmp_path, capsys):
    traj = _camera_table(tmp_path, "big.parquet", scale=1e300 / 25e-6)
    assert main(["msd", str(traj), "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert "not a position in m" in err and "Traceback" not in err
