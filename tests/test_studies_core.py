"""Diffusion and electrophoresis studies at reduced size, the dask runner, and `ptrack simulate`."""
import json

import numpy as np
import pytest

from ptrack.cli import main
from ptrack.msd import stokes_einstein
from ptrack.table import read_table
from sim.studies import diffusion, electrophoresis
from sim.studies._dask import case_seed, run_cases


def test_diffusion_study_small(tmp_path):
    res = diffusion.run_study(replicates=2, particles=10, frames=400, seed=3, use_dask=False, progress=False,
                              radii=(1e-8, 1e-6), viscosities=(1e-3,))
    assert len(res["cases"]) == 2
    for c in res["cases"]:
        assert c["D_analytical"] == pytest.approx(stokes_einstein(c["radius"], c["viscosity"], 293.0))
        lo, hi = c["D_ci95"]
        assert lo < c["D_sim"] < hi
        flo, fhi = c["D_ci95_family"]
        assert flo < lo and fhi > hi  # simultaneous intervals are wider
        # 20 particles x 400 frames x 3 axes: the CVE's SE is ~1.4 %; 5 % is > 3.5 SE
        assert c["error_pct"] < 5.0
        assert (hi - lo) / 2 / c["D_sim"] < 0.05
    paths = diffusion.write_outputs(res, tmp_path, tmp_path / "d.json")
    assert all(p.exists() and p.stat().st_size > 0 for p in paths)
    doc = json.loads((tmp_path / "d.json").read_text())
    assert set(doc) >= {"cases", "max_error_pct", "wall_time_s"}
    assert set(doc["cases"][0]) >= {"radius", "viscosity", "D_analytical", "D_sim", "D_ci95", "error_pct"}


def test_diffusion_study_same_seed_same_result():
    kw = dict(replicates=1, particles=5, frames=50, use_dask=False, progress=False, radii=(1e-7,), viscosities=(1e-3,))
    a = diffusion.run_study(seed=1, **kw)["cases"][0]["D_sim"]
    b = diffusion.run_study(seed=1, **kw)["cases"][0]["D_sim"]
    c = diffusion.run_study(seed=2, **kw)["cases"][0]["D_sim"]
    assert a == b and a != c


def test_electrophoresis_study_small(tmp_path):
    res = electrophoresis.run_study(replicates=2, use_dask=False, progress=False, radii=(1e-6,),
                                    viscosities=(1e-4,), permittivities=(80.0,), fields=(1e3, 1e6))
    low, high = res["cases"]
    assert low["Re"] < 1 and not low["re_gt_1"]
    assert low["err_henry"] < 1e-4            # Stokes regime: terminal velocity = exact Henry velocity
    assert low["err_henry_sf"] == pytest.approx(1.46e-3, rel=0.05)  # Swan-Furst's approximation error
    assert high["re_gt_1"] and high["Re"] > 1  # the seed's 34.5 % outlier: piecewise drag at Re ~ 3.3
    assert high["err_henry"] == pytest.approx(0.345, abs=0.01)
    for c in res["cases"]:
        assert c["err_balance"] < 1e-6 and c["converged"]
        assert c["v_sim"] > 0  # zeta < 0 and E along -z: motion along +z
    tab = electrophoresis.pe_decade_table(res["cases"])
    assert list(tab.columns[:5]) == ["Pe_order", "n_cases", "err_vs_henry_exact_pct", "err_vs_swan_furst_pct",
                                     "err_vs_force_balance_pct"]
    paths = electrophoresis.write_outputs(res, tmp_path, tmp_path / "e.json")
    assert all(p.exists() for p in paths)
    doc = json.loads((tmp_path / "e.json").read_text())
    assert set(doc["cases"][0]) >= {"radius", "viscosity", "eps_r", "E", "v_sim", "v_henry_exact", "v_henry_sf",
                                    "v_balance", "Re", "Pe"}


def _square(c):
    return c["x"] ** 2


def test_dask_runner_keeps_order():
    cases = [{"x": i} for i in range(5)]
    assert run_cases(_square, cases, use_dask=True, workers=2, progress=False) == [0, 1, 4, 9, 16]
    assert run_cases(_square, cases, use_dask=False, progress=False) == [0, 1, 4, 9, 16]
    assert case_seed(0, 1) != case_seed(0, 2) and case_seed(0, 1) == case_seed(0, 1)


SCENE = """
seed = 4
[particles]
count = 6
radius = 1.0e-7
density = 2200.0
charge = -1.0e-17
[fluid]
viscosity = 1.0e-3
temperature = 0.0
[fields]
E = [0.0, 0.0, -1.0e3]
[domain]
size = [1.0e-5, 1.0e-5, 1.0e-5]
[time]
final = 1.0e-3
output_interval = 1.0e-4
"""


def test_simulate_cli(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    assert main(["simulate", str(scene), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    df = read_table(tmp_path / "o" / "trajectories.parquet")
    assert len(df) == 11 * 6
    assert {"vx", "vy", "vz", "radius"} <= set(df.columns)
    meta = json.loads((tmp_path / "o" / "scene.json").read_text())
    # output interval 1e-4 s = 2e4 m/gamma: auto picks overdamped BD
    assert meta["integrator"]["kind"] == "overdamped" and "m/gamma" in meta["integrator"]["reason"]
    # T = 0: z(t) = u t, u = (q E + buoyant weight) / gamma (the inertial lag tau = 5 ns is below the tolerance)
    import math
    R, m = 1e-7, 2200.0 * 4 / 3 * math.pi * 1e-21
    gamma = 6 * math.pi * 1e-3 * R
    u = (1e-14 - (2200.0 - 1000.0) * 4 / 3 * math.pi * R ** 3 * 9.80665) / gamma
    tau = m / gamma
    z = df.pivot(index="frame", columns="particle", values="z").to_numpy()
    np.testing.assert_allclose(z[-1] - z[0], u * 1e-3, rtol=1e-4)
    assert tau / 1e-3 < 1e-4

    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace("radius = 1.0e-7", "radius = -1.0e-7"))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "particles.radius" in err and "-1e-07" in err
    assert not (tmp_path / "b" / "trajectories.parquet").exists()


def test_study_commands(tmp_path, capsys):
    assert main(["study", "electrophoresis", "--quick", "--no-dask", "--out", str(tmp_path / "e"),
                 "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    assert "Re > 1" in out and "Pe decade" in out
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["summary"]["max_err_henry_re_le_1"] < 1e-4 and doc["summary"]["max_err_balance"] < 1e-6
    assert (tmp_path / "e" / "electrophoresis.png").exists()
    assert main(["study", "diffusion", "--no-dask", "--replicates", "1", "--particles", "5", "--frames", "60",
                 "--out", str(tmp_path / "d")]) == 0
    assert (tmp_path / "d" / "diffusion.csv").exists()
    assert main(["study", "diffusion", "--no-dask", "--frames", "2"]) == 2
    assert "--frames" in capsys.readouterr().err
