"""Tests of ptrack.twin and `ptrack twin`: inference against known physics, the scene file, the whole chain."""
import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from ptrack.cli import main
from ptrack.constants import BOLTZMANN, STANDARD_GRAVITY
from ptrack.errors import UserError
from ptrack.twin import apply_overrides, build_scene, flag_stuck, infer_parameters, to_toml
from ptrack.velocity import drifting_tracks
from ptrack.wall import parallel_ratio

T, MU = 293.15, 1.0e-3
DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic"


def _d0(R, mu=MU):
    return BOLTZMANN * T / (6 * math.pi * mu * R)


def _table(D, n_p=60, n_f=80, dt=0.1, v=0.0, z=None, seed=0):
    t = drifting_tracks(n_p, n_f, D, dt, v, sigma=15e-9, seed=seed,
                        meta={"frame_interval": dt, "pixel_size": 1e-7, "frame_shape": [200, 200]})
    if z is None:
        t["z"] = np.nan
    else:
        t["z"] = t["z"] + z
    return t


def test_radius_from_D_with_the_wall_correction_of_a_given_height():
    R, h = 300e-9, 600e-9
    D = _d0(R) * float(parallel_ratio(h, R))          # what a particle at height h shows
    p = infer_parameters(_table(D, seed=1), T, MU, height=h, n_boot=100)
    assert p["wall_ratio"] == pytest.approx(float(parallel_ratio(h, p["radius_m"])), rel=1e-9)
    assert abs(p["radius_m"] - R) < 3 * p["radius_err_m"]
    assert p["radius_err_m"] / R < 0.05
    # without the wall correction the same data give a radius too large by ~1/ratio
    bulk = infer_parameters(_table(D, seed=1), T, MU, n_boot=100)
    assert bulk["radius_m"] > 1.25 * R
    # radius given: the viscosity is inferred instead
    q = infer_parameters(_table(D, seed=1), T, 2e-3, radius=R, height=h, n_boot=100)
    assert q["inferred"] == "viscosity" and abs(q["viscosity_Pa_s"] - MU) < 3 * q["viscosity_err_Pa_s"]


def test_zeta_and_charge_from_the_drift_with_sedimentation_subtracted():
    from sim.electrokinetics import colloid_charge, henry_velocity

    R, zeta, lam, E, rho = 400e-9, -0.040, 100e-9, 250.0, 1050.0
    v_h = float(henry_velocity(E, zeta, R, lam, 78.5, MU))
    v_sed = -2 / 9 * (rho - 998.2) * STANDARD_GRAVITY * R ** 2 / MU
    tab = _table(_d0(R), n_p=40, n_f=60, dt=1 / 30, v=(0.0, 0.0, v_h + v_sed), z=8e-6, seed=2)
    p = infer_parameters(tab, T, MU, radius=R, field=E, density=rho, debye_length=lam, wall_hydrodynamics=False,
                         motion_blur=0.0, n_boot=100)
    assert abs(p["zeta_V"] - zeta) < 3 * p["zeta_err_V"] and p["zeta_err_V"] < 0.1 * abs(zeta)
    # radius given: the viscosity is the one the mobility implies, and the settling uses it
    assert p["v_sedimentation_m_s"] == pytest.approx(v_sed * MU / p["viscosity_Pa_s"], rel=1e-12)
    assert p["charge_C"] == pytest.approx(float(colloid_charge(p["zeta_V"], R, lam, 78.5)), rel=1e-12)


def test_flag_stuck_marks_the_rows_after_the_particle_stops():
    tab = _table(_d0(400e-9), n_p=10, n_f=60, dt=1 / 30, z=5e-6, seed=3)
    stop = 30
    for c in ("x", "y", "z"):
        first = tab.groupby("particle")[c].transform(lambda s: s.iloc[stop])
        tab.loc[tab["frame"] >= stop, c] = first[tab["frame"] >= stop] + 5e-9 * np.random.default_rng(0).standard_normal((tab["frame"] >= stop).sum())
    f = flag_stuck(tab, 15e-9)
    dep = f.groupby("particle")["deposited"].apply(lambda s: int(np.argmax(s.to_numpy())))
    # the last free steps before the stop can be shorter than the threshold: a frame or three early at most
    assert (dep >= stop - 3).all() and (dep <= stop + 1).all()


def test_scene_toml_round_trip_and_overrides():
    from sim.scene import scene_from_dict

    p = {"radius_m": 2.5e-7, "viscosity_Pa_s": MU, "temperature_K": T, "number_density_per_m2": 0.05e12,
         "three_d": False}
    scene, view = build_scene(p, (100, 120), 1e-7, 0.1, 50, depth_of_field=1.2e-6)
    render = {"view": view, "optics": {"na": 0.75}, "camera": {"photons": 3000.0}}
    keys = apply_overrides(scene, render, ["particles.radius=3.25e-7", "camera.photons=2000", "fields.E=[0, 0, 10.0]"])
    assert keys == ["particles.radius", "camera.photons", "fields.E"]
    text = to_toml(scene, {"particles.radius": "m"}, "header line")
    back = tomllib.loads(text)
    assert back == scene
    sc = scene_from_dict(back)
    assert sc.particles.radius == 3.25e-7 and render["camera"]["photons"] == 2000 and sc.fields.E == (0, 0, 10.0)
    # the box holds the view plus margins; the count is the measured density times the box area
    Lx, Ly, _ = scene["domain"]["size"]
    assert Lx > 120e-7 and scene["particles"]["count"] == round(0.05e12 * Lx * Ly)
    with pytest.raises(UserError):
        apply_overrides(scene, render, ["radius 3e-7"])
    with pytest.raises(UserError):
        apply_overrides(scene, render, ["radius=3e-7"])


@pytest.fixture(scope="module")
def measured_2d(tmp_path_factory):
    from ptrack.pipeline import track_movie

    p = json.loads((DATA / "diffusion2d" / "params.json").read_text())
    kw = {k: p["camera"][k] for k in ("gain", "offset", "read_noise")}
    table, _ = track_movie(DATA / "diffusion2d" / "movie.tif", progress=False, **kw)
    return table, kw, p


@pytest.mark.slow       # ~30 s each on 2 loaded cores (render + track + two comparisons + report)
@pytest.mark.parametrize("factor", [1.0, 1.3])
def test_twin_of_the_shipped_2d_movie(measured_2d, tmp_path, factor):
    from ptrack.twin import run_twin

    table, kw, p = measured_2d
    R_true = p["radius"]
    over = [] if factor == 1.0 else [f"particles.radius={factor * R_true!r}"]
    res = run_twin(DATA / "diffusion2d" / "movie.tif", tmp_path, kw, T, MU, overrides=over, seed=3, n_boot=150,
                   n_perm=1000, measured_table=table)
    # the inferred radius is within its stated error (2 SE) of the truth
    assert abs(res["radius_m"] - R_true) < 2 * res["radius_err_m"]
    v = res["verdicts"]
    if factor == 1.0:
        decided = [k for k, x in v.items() if x != "insufficient"]
        assert len(decided) >= 15 and all(v[k] == "consistent" for k in decided), v
    else:
        assert res["twin_radius_m"] == pytest.approx(1.3 * R_true)
        assert v["D_x"] == v["D_y"] == "differs" and "differs" in (v["msd_x"], v["msd_y"])
        assert any(m.startswith("D (") for m in res["meaning"])
    page = Path(res["files"]["report"]).read_text()
    assert "data:image/png;base64," in page and "Inferred parameters" in page
    assert tomllib.loads(Path(res["files"]["scene"]).read_text())["particles"]["radius"] == pytest.approx(
        res["twin_radius_m"])


def test_twin_command_user_errors(tmp_path, capsys):
    movie = str(DATA / "diffusion2d" / "movie.tif")
    assert main(["twin", movie, "--temperature", "293", "--viscosity", "-1", "--out", str(tmp_path / "o")]) == 2
    assert main(["twin", movie, "--temperature", "293", "--viscosity", "1e-3", "--field", "0",
                 "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.count("error:") == 2
