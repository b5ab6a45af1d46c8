"""Tests of ptrack.compare and `ptrack compare`: verdicts on tables of known physics."""
import base64
import json
import re

import numpy as np
import pytest

from ptrack.cli import main
from ptrack.compare import compare_tables, holm
from ptrack.table import write_table
from ptrack.velocity import drifting_tracks

D0 = 8.589e-13     # m^2/s: R = 250 nm in water at 293.15 K
DT = 0.1


def _tracks(n_p=40, n_f=60, D=D0, dt=DT, seed=0, z=False, v=0.0, sigma=20e-9):
    t = drifting_tracks(n_p, n_f, D, dt, v, sigma=sigma, seed=seed)
    if not z:
        t["z"] = np.nan
    return t


def test_holm_matches_hand_computed_step_down():
    p = [0.01, 0.04, 0.03, np.nan, 0.005]
    # sorted 0.005, 0.01, 0.03, 0.04 (m = 4): 0.02, 0.03, 0.06, 0.06 (monotone)
    assert np.allclose(holm(p), [0.03, 0.06, 0.06, np.nan, 0.02], equal_nan=True)
    assert holm([0.5, 0.9])[1] == 1.0


def test_identical_parameters_are_consistent_and_30_percent_D_differs():
    a, b, c = _tracks(seed=1), _tracks(seed=2), _tracks(D=1.3 * D0, seed=3)
    res = compare_tables([a, b, c], ["A", "B", "C"], seed=0, n_boot=200, n_perm=1000)
    same, diff = res["comparisons"]
    decided = {k: v for k, v in same["verdicts"].items() if v != "insufficient"}
    assert len(decided) >= 18 and set(decided.values()) == {"consistent"}, same["verdicts"]
    # no deposited column in either table: said so, not "consistent"
    assert same["verdicts"]["deposition"] == "insufficient"
    for k in ("D_x", "D_y", "msd_x", "msd_y"):
        assert diff["verdicts"][k] == "differs", (k, diff["quantities"][k])
    e = diff["quantities"]["D_x"]["effect"]
    assert e["ci_low"] < 1 / 1.3 - 1 < e["ci_high"]         # the interval covers the true effect, -23 %
    assert diff["quantities"]["D_x"]["p_holm"] >= diff["quantities"]["D_x"]["p_value"]
    assert 0 < diff["quantities"]["D_x"]["p_holm"] < 0.05


def test_too_little_data_is_insufficient_not_consistent():
    res = compare_tables([_tracks(n_p=3, seed=1), _tracks(n_p=40, seed=2)], seed=0, n_boot=50, n_perm=100)
    v = res["comparisons"][0]["verdicts"]
    assert set(v.values()) == {"insufficient"}
    r = res["comparisons"][0]["quantities"]["D_x"]
    assert "3 particles" in r["reason"] and r["p_value"] is None


def test_lags_compared_in_seconds_across_frame_intervals():
    # the same physics filmed at 10 and 20 fps: consistent; the lags are whole frames of both
    a = _tracks(n_p=40, n_f=60, dt=0.1, seed=4)
    b = _tracks(n_p=40, n_f=120, dt=0.05, seed=5)
    comp = compare_tables([a, b], seed=1, n_boot=200, n_perm=1000)["comparisons"][0]
    assert np.allclose(np.array(comp["lags_s"]) / 0.1, np.round(np.array(comp["lags_s"]) / 0.1))
    assert comp["verdicts"]["D_x"] == comp["verdicts"]["msd_y"] == "consistent"
    assert comp["verdicts"]["van_hove_x_0.1s"] == "consistent"


def test_3d_drift_heights_and_deposition():
    # 3D tables with a drift in z: the same drift is consistent, a doubled drift differs;
    # deposition: half of B's particles deposit early, none of A's
    a = _tracks(z=True, v=(0, 0, -1e-6), seed=6)
    b = _tracks(z=True, v=(0, 0, -2e-6), seed=7)
    for t, frac in ((a, 0.0), (b, 0.5)):
        t["deposited"] = (t["particle"] < frac * 40) & (t["frame"] >= 10)
    comp = compare_tables([a, b], seed=2, n_boot=200, n_perm=1000)["comparisons"][0]
    q = comp["quantities"]
    assert comp["verdicts"]["drift_z"] == "differs"
    assert q["drift_z"]["effect"]["ci_low"] < 1e-6 < q["drift_z"]["effect"]["ci_high"]
    assert comp["verdicts"]["drift_x"] == "consistent"
    assert comp["verdicts"]["D_x"] == "consistent"
    assert "height_z" in q and "v_vs_height_z" in q
    assert comp["verdicts"]["deposition"] == "differs"
    assert q["deposition"]["effect"]["value"] == pytest.approx(-0.5)


def test_a_2d_table_with_constant_z_is_compared_as_2d():
    # z = 0 in every row (a 2D table written with a z column): no motion along z, so no z quantity
    # (the one rule of the analysed axes, ptrack.motion.velocity.default_axes; finite z alone made it 3D)
    a, b = _tracks(seed=1), _tracks(seed=2)
    a["z"] = b["z"] = 0.0
    res = compare_tables([a, b], seed=0, n_boot=50, n_perm=100)
    assert [t["components"] for t in res["tables"]] == [["x", "y"], ["x", "y"]]
    assert not [k for k in res["comparisons"][0]["verdicts"] if k.endswith("_z")]
    assert "D_x" in res["comparisons"][0]["verdicts"]


def test_compare_command_json_and_self_contained_report(tmp_path, capsys):
    pa, pb = tmp_path / "a.parquet", tmp_path / "b.parquet"
    write_table(_tracks(n_p=60, n_f=100, seed=8), pa)
    write_table(_tracks(n_p=60, n_f=100, D=1.3 * D0, seed=9), pb)
    out, rep = tmp_path / "c.json", tmp_path / "rep"
    assert main(["compare", str(pa), str(pb), "--json", str(out), "--report", str(rep), "--n-perm", "500"]) == 0
    text = capsys.readouterr().out
    assert "D_x" in text and "differs" in text
    res = json.loads(out.read_text())
    assert res["comparisons"][0]["verdicts"]["D_x"] == "differs"
    assert res["comparisons"][0]["quantities"]["D_x"]["a"]["D"] > 0
    page = (rep / "report.html").read_text()
    imgs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(imgs) >= 5 and all(base64.b64decode(s)[:8] == b"\x89PNG\r\n\x1a\n" for s in imgs)
    assert "src=\"http" not in page and "<table>" in page and "differs" in page


def test_compare_command_user_errors(tmp_path, capsys):
    pa = tmp_path / "a.parquet"
    write_table(_tracks(seed=1), pa)
    assert main(["compare", str(pa)]) == 2
    assert main(["compare", str(pa), str(tmp_path / "missing.parquet")]) == 2
    assert main(["compare", str(pa), str(pa), "--motion-blur", "0.5"]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 3
