"""Scene parsing/validation, placement and build_state."""
import copy
import math
from pathlib import Path

import numpy as np
import pytest

from ptrack.errors import UserError
from sim.placement import place_particles
from sim.scene import OPEN, PERIODIC, WALL, build_state, constant_force, load_scene, scene_from_dict

ROOT = Path(__file__).resolve().parents[1]

BASE = {
    "seed": 3,
    "particles": {"count": 20, "radius": 1e-7, "density": 2200.0},
    "fluid": {"viscosity": 1e-3, "temperature": 293.0},
    "domain": {"size": [1e-5, 1e-5, 1e-5]},
    "time": {"final": 1e-3, "output_interval": 1e-4},
}


def with_(path, value):
    raw = copy.deepcopy(BASE)
    d = raw
    keys = path.split(".")
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = value
    return raw


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "scenes").glob("*.toml")))
def test_example_scenes_parse(name):
    sc = load_scene(ROOT / "scenes" / name)
    assert sc.particles.count > 0


def test_defaults_gravity_on_with_buoyancy():
    sc = scene_from_dict(BASE)
    assert sc.gravity.enabled and sc.gravity.buoyancy
    assert sc.time.dt is None and sc.integrator.kind == "auto"
    assert sc.boundaries.modes.tolist() == [[OPEN, OPEN, WALL], [OPEN, OPEN, OPEN]]


@pytest.mark.parametrize("path,value,words", [
    ("particles.radius", -1e-7, ["particles.radius", "-1e-07", "positive"]),
    ("particles.radius", float("nan"), ["particles.radius", "nan", "finite"]),
    ("particles.count", "ten", ["particles.count", "'ten'", "whole number"]),
    ("particles.count", 2.5, ["particles.count", "2.5"]),
    ("particles.colour", "red", ["particles.colour", "allowed keys"]),
    ("fluid.viscosity", 0.0, ["fluid.viscosity", "positive"]),
    ("fields.E", [0, 1], ["fields.E", "3-vector"]),
    ("boundaries.x", "sticky", ["boundaries.x", "'sticky'", "'periodic'"]),
    ("integrator.kind", "rk4", ["integrator.kind", "'rk4'", "'ou_exact'"]),
    ("integrator.phi", 1.5, ["integrator.phi", "1.5", "[0.0, 1.0]"]),
    ("time.dt", "fast", ["time.dt", "'fast'", "auto"]),
    ("time.dt", 1e-3, ["time.dt", "output_interval"]),
    ("time.output_interval", 1.0, ["output_interval", "time.final"]),
    ("gravity.enabled", "yes", ["gravity.enabled", "true or false"]),
    ("domain.placement_z", [0.0, 1.0], ["placement_z", "Lz"]),
    ("particles.charge_per_mass", -1.0, None),
])
def test_validation_errors(path, value, words):
    raw = with_(path, value)
    if words is None:  # two charge definitions
        raw["particles"]["charge"] = 1e-18
        words = ["particles.charge", "particles.charge_per_mass", "once"]
    with pytest.raises(UserError) as exc:
        scene_from_dict(raw)
    msg = str(exc.value)
    for w in words:
        assert w in msg, (w, msg)


def test_unknown_section_and_zeta_without_debye():
    raw = copy.deepcopy(BASE)
    raw["physics"] = {}
    with pytest.raises(UserError, match="physics"):
        scene_from_dict(raw)
    with pytest.raises(UserError, match="Debye"):
        scene_from_dict(with_("particles.zeta_potential", -0.05))


def test_bad_toml_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[particles\ncount = 3\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_scene(p)
    with pytest.raises(UserError, match="not found"):
        load_scene(tmp_path / "missing.toml")


def test_placement_no_overlap_polydisperse():
    n = 20_000
    pos, r = place_particles(n, 1e-7, 0.3, (0, 0, 0), (2.2e-5, 2.2e-5, 2.2e-5), seed=4)
    assert pos.shape == (n, 3) and pos.flags.c_contiguous
    assert r.min() >= 0.7e-7 * (1 - 1e-12) and r.max() <= 1.3e-7 * (1 + 1e-12)
    assert abs(r.mean() / 1e-7 - 1) < 0.01
    assert np.all(pos - r[:, None] >= 0) and np.all(pos + r[:, None] <= 2.2e-5)
    from scipy.spatial import cKDTree
    pairs = cKDTree(pos).query_pairs(2 * r.max(), output_type="ndarray")
    d = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    assert np.all(d >= r[pairs[:, 0]] + r[pairs[:, 1]])
    pos2, r2 = place_particles(n, 1e-7, 0.3, (0, 0, 0), (2.2e-5, 2.2e-5, 2.2e-5), seed=4)
    np.testing.assert_array_equal(pos, pos2)


def test_placement_too_crowded():
    with pytest.raises(UserError, match="packing fraction"):
        place_particles(1000, 1e-6, 0.0, (0, 0, 0), (1e-5, 1e-5, 1e-5), seed=1)


def test_build_state_charges_and_velocities():
    raw = with_("particles.charge_per_mass", -1.0)
    sc = scene_from_dict(raw)
    st = build_state(sc)
    np.testing.assert_allclose(st.charge, -st.mass)
    np.testing.assert_allclose(st.gamma, 6 * math.pi * 1e-3 * st.radius)
    for a in (st.radius, st.mass, st.charge, st.gamma, st.pos, st.vel):
        assert a.dtype == np.float64 and a.flags.c_contiguous

    raw = with_("particles.zeta_potential", -0.05)
    raw["fluid"]["debye_ratio"] = 2.0
    raw["fluid"]["relative_permittivity"] = 80.0
    raw["fields"] = {"E": [0.0, 0.0, -1e4]}
    raw["gravity"] = {"enabled": False}
    raw["particles"]["initial_velocity"] = "henry"
    sc = scene_from_dict(raw)
    st = build_state(sc)
    from sim.electrokinetics import colloid_charge, henry_velocity
    np.testing.assert_allclose(st.charge, colloid_charge(-0.05, 1e-7, 5e-8, 80.0), rtol=1e-12)
    # terminal initial velocity = Henry velocity (Stokes drag, eq. 3.33 charge)
    np.testing.assert_allclose(st.vel[:, 2], henry_velocity(-1e4, -0.05, 1e-7, 5e-8, 80.0, 1e-3), rtol=1e-12)

    raw = with_("particles.initial_velocity", "thermal")
    raw["particles"]["count"] = 4000
    raw["domain"]["size"] = [5e-5, 5e-5, 5e-5]
    st = build_state(scene_from_dict(raw))
    kT = 1.380649e-23 * 293.0
    assert np.mean(st.mass[:, None] * st.vel ** 2) / kT == pytest.approx(1.0, abs=0.05)


def test_constant_force_gravity_buoyancy_and_field():
    raw = with_("particles.charge", -1e-18)
    raw["fields"] = {"E": [1e3, 0.0, 0.0]}
    sc = scene_from_dict(raw)
    st = build_state(sc)
    f = constant_force(sc, st)
    V = 4 / 3 * math.pi * 1e-7 ** 3
    np.testing.assert_allclose(f[:, 0], -1e-15)
    np.testing.assert_allclose(f[:, 2], -(2200 - 1000) * V * 9.80665, rtol=1e-12)


def test_periodic_modes_and_interaction_sections():
    raw = with_("boundaries", {"x": "periodic", "y": "wall", "bottom_wall": True, "top": "wall"})
    sc = scene_from_dict(raw)
    assert sc.boundaries.modes.tolist() == [[PERIODIC, WALL, WALL], [PERIODIC, WALL, WALL]]
    assert sc.interactions is None


def test_interaction_sections_go_to_the_dem_engine(tmp_path, monkeypatch):
    raw = copy.deepcopy(BASE)
    raw["contact"] = {"model": "hooke", "kn": 1.0, "restitution": 0.5}
    sc = scene_from_dict(raw)
    assert sc.interactions is not None and sc.interactions.any_pair_force
    assert sc.to_dict()["interactions"] == {"contact": {"model": "hooke", "kn": 1.0, "restitution": 0.5}}
    import sim.dem
    from sim.run import run_scene
    seen = {}

    def fake_run_dem(scene, out_dir, resume=False, progress=True, threads=None):
        seen.update(scene=scene, out_dir=out_dir, resume=resume, threads=threads)
        return "dem"

    monkeypatch.setattr(sim.dem, "run_dem", fake_run_dem)
    assert run_scene(sc, tmp_path, progress=False) == "dem"
    assert seen["scene"].interactions is sc.interactions and seen["threads"] is None
    assert run_scene(sc, tmp_path, progress=False, threads=2) == "dem" and seen["threads"] == 2
    with pytest.raises(UserError, match="contact.colour"):
        raw["contact"] = {"colour": 1}
        scene_from_dict(raw)


def test_placement_dense_random_sequential_addition():
    n, R, phi = 20_000, 1e-7, 0.25
    L = (n * 4 / 3 * math.pi * R ** 3 / phi) ** (1 / 3)
    pos, r = place_particles(n, R, 0.0, (0, 0, 0), (L, L, L), seed=2)
    from scipy.spatial import cKDTree
    pairs = cKDTree(pos).query_pairs(2 * R * (1 - 1e-12))
    assert len(pairs) == 0
