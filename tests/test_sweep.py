"""ptrack sweep: the grid, the summary table, resuming, and refusals before any work."""
from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ptrack.cli import main
from sim.sweep import build_cases, parse_set, run_sweep

KB = 1.380649e-23

SCENE = """
seed = 3
[particles]
count = 30
radius = 1.0e-7
density = 2200.0
[fluid]
temperature = 293.0
viscosity = 1.0e-3
[gravity]
enabled = false
[domain]
size = [2.0e-5, 2.0e-5, 2.0e-5]
[boundaries]
x = "periodic"
y = "periodic"
bottom_wall = false
[time]
final = 0.06
output_interval = 1.0e-3
"""


@pytest.fixture()
def scene(tmp_path) -> Path:
    p = tmp_path / "brownian.toml"
    p.write_text(SCENE)
    return p


def test_parse_set_values():
    assert parse_set("particles.count=10,20") == ("particles.count", [10, 20])
    assert parse_set("fields.E=[0,0,-1e4],[0,0,-2e4]") == ("fields.E", [[0, 0, -1e4], [0, 0, -2e4]])
    assert parse_set("integrator.kind=overdamped,ou_exact") == ("integrator.kind", ["overdamped", "ou_exact"])
    assert parse_set('integrator.kind="auto"') == ("integrator.kind", ["auto"])


def test_grid_table_values_and_seeds(scene, tmp_path):
    out = tmp_path / "sw"
    t = run_sweep(scene, ["particles.radius=1e-7,2e-7"], out, replicates=2, workers=1, progress=False)
    assert len(t) == 4 and (t["status"] == "ok").all()
    assert sorted(t["particles.radius"]) == [1e-7, 1e-7, 2e-7, 2e-7]
    # replicate 0 keeps the scene's seed; replicates differ; the same seeds at every grid point
    seeds = t.pivot(index="replicate", columns="point", values="seed")
    assert (seeds[0] == seeds[1]).all() and seeds.loc[0, 0] == 3 and seeds.loc[1, 0] != 3
    # replicates with distinct seeds give distinct trajectories
    assert t.loc[(t.point == 0) & (t.replicate == 0), "z_mean"].item() != t.loc[
        (t.point == 0) & (t.replicate == 1), "z_mean"].item()
    # the observable against the analytic value: D = kT / (6 pi eta R) (Stokes-Einstein)
    for _, r in t.iterrows():
        d_se = KB * 293.0 / (6 * math.pi * 1e-3 * r["particles.radius"])
        assert abs(r["D_xy"] - d_se) < 5 * r["D_xy_err"], (r["D_xy"], d_se, r["D_xy_err"])
        assert math.isnan(r["deposited_fraction"])  # no bottom wall
        assert r["n_frames"] == 61
    # both tables hold the same rows; every run has its folder with a done marker
    pq = pd.read_parquet(out / "summary.parquet")
    csv = pd.read_csv(out / "summary.csv")
    assert len(pq) == len(csv) == 4
    np.testing.assert_allclose(pq["D_xy"], t["D_xy"])
    for f in t["folder"]:
        d = json.loads((out / f / "case.json").read_text())
        assert d["status"] == "ok" and (out / f / "run" / "trajectories.parquet").exists()


def test_resume_skips_finished_cases(scene, tmp_path):
    out = tmp_path / "sw"
    sets = ["fluid.viscosity=1e-3,2e-3"]
    first = run_sweep(scene, sets, out, use_dask=False, progress=False)
    assert not first["skipped"].any()
    again = run_sweep(scene, sets, out, use_dask=False, progress=False)
    assert again["skipped"].all()
    np.testing.assert_array_equal(again["z_mean"], first["z_mean"])
    # a done marker that does not match its case (another scene) is not trusted: that case alone reruns
    marker = out / first["folder"][1] / "case.json"
    d = json.loads(marker.read_text())
    d["fingerprint"] = "0" * 64
    marker.write_text(json.dumps(d))
    third = run_sweep(scene, sets, out, use_dask=False, progress=False)
    assert list(third["skipped"]) == [True, False]
    np.testing.assert_array_equal(third["z_mean"], first["z_mean"])  # same seed, same result
    # a changed grid value is a new case, not a finished one
    fourth = run_sweep(scene, ["fluid.viscosity=1e-3,3e-3"], out, use_dask=False, progress=False)
    assert list(fourth["skipped"]) == [True, False]


@pytest.mark.parametrize("spec", ["particles.radiuz=1e-7", "particles.radius=-1e-7", "fields.E=[0,1]", "foo=1",
                                  "particles.count"])
def test_bad_key_or_value_refused_before_work(scene, tmp_path, capsys, spec):
    out = tmp_path / "sw"
    assert main(["sweep", str(scene), "--set", spec, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    assert not out.exists()


def test_unreachable_scheduler_refused(scene, tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", str(scene), "--set", "particles.count=5", "--scheduler", "tcp://127.0.0.1:9",
                 "--out", str(out), "--quiet"]) == 2
    assert "cannot reach the dask scheduler" in capsys.readouterr().err
    assert not out.exists()


def test_quick_shortens_runs(scene, tmp_path):
    cases = build_cases(tomllib.loads(SCENE), [], 1, tmp_path, quick=True)
    assert cases[0].raw["time"]["final"] == pytest.approx(0.006)


DEM_SCENE = """
seed = 1
[particles]
count = 20
radius = 0.05
density = 1540.0
[fluid]
density = 0.0
viscosity = 1.0e-12
temperature = 0.0
[gravity]
enabled = true
g = [0.0, 0.0, -1000.0]
buoyancy = false
[domain]
size = [1.0, 1.0, 0.5]
placement_z = [0.0, 0.3]
[boundaries]
x = "periodic"
y = "periodic"
bottom_wall = true
[time]
dt = 1.0e-6
final = 0.1
output_interval = 0.01
[contact]
model = "hooke"
kn = 1.0e9
restitution = 0.3
checkpoint_every = 5
[friction]
mu = 0.4
"""


def test_dem_sweep_deposit(tmp_path):
    # 20 spheres (R = 0.05 m) dropped into a 1 m^2 periodic box settle as a monolayer: all deposited,
    # centres at z = R (less the static overlap m g / kn ~ 1e-6 m)
    p = tmp_path / "dem.toml"
    p.write_text(DEM_SCENE)
    t = run_sweep(p, ["contact.restitution=0.3"], tmp_path / "sw", use_dask=False, progress=False)
    r = t.iloc[0]
    assert r["status"] == "ok" and r["deposited_fraction"] == 1.0
    assert abs(r["z_mean"] - 0.05) < 1e-3 * 0.05
    assert math.isnan(r["D_xy"])  # T = 0 and contacts: no diffusion coefficient
