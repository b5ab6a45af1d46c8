"""Integrators: relaxation, equipartition, diffusion, stability refusal, seeds, NaN handling, wall drift."""
import math

import numpy as np
import pytest

from ptrack.constants import BOLTZMANN
from ptrack.errors import UserError
from ptrack.table import read_table
from sim.integrate import choose_integrator, ou_coefficients
from sim.run import Stepper, run_scene
from sim.scene import build_state, constant_force, scene_from_dict

R, RHO_P, MU, T = 1e-7, 2200.0, 1e-3, 293.0
MASS = RHO_P * 4 / 3 * math.pi * R ** 3
GAMMA = 6 * math.pi * MU * R
TAU = MASS / GAMMA
KT = BOLTZMANN * T


def make(kind="ou_exact", n=100, T=T, dt=None, out=None, final=None, E=(0.0, 0.0, 0.0), phi=0.0, seed=1,
         init="zero", charge=None, walls=False, **extra):
    out = out or 10 * TAU
    raw = {
        "seed": seed,
        "particles": {"count": n, "radius": R, "density": RHO_P, "initial_velocity": init},
        "fluid": {"viscosity": MU, "temperature": T, "density": 1000.0},
        "fields": {"E": list(E)},
        "gravity": {"enabled": False},
        "domain": {"size": [1e-4, 1e-4, 1e-4]},
        "boundaries": {"bottom_wall": walls},
        "time": {"final": final or 100 * out, "output_interval": out, "dt": dt if dt is not None else "auto"},
        "integrator": {"kind": kind, "phi": phi},
    }
    if charge is not None:
        raw["particles"]["charge"] = charge
    for k, v in extra.items():
        raw.setdefault(k, {}).update(v)
    sc = scene_from_dict(raw)
    st = build_state(sc)
    fc = constant_force(sc, st)
    ch = choose_integrator(sc, st, fc)
    return sc, st, fc, ch


def test_ou_coefficients_series_matches_closed_form():
    # the small-a series and the closed form agree where they meet
    for a in (0.0199999, 0.0200001):
        e, em, gvv, gxx, gxv, gc = ou_coefficients(a)
        assert gxx == pytest.approx(2 * a - 3 + 4 * math.exp(-a) - math.exp(-2 * a), rel=1e-7)
        assert gc == pytest.approx(gxx - gxv ** 2 / gvv, rel=1e-6)
    e, em, gvv, gxx, gxv, gc = ou_coefficients(1e-6)
    assert gxx == pytest.approx(2 / 3 * 1e-18, rel=1e-5) and gc == pytest.approx(1e-18 / 6, rel=1e-5)


@pytest.mark.parametrize("kind,phi,dt_tau,tol", [("ou_exact", 0.0, 1.0, 1e-12), ("trapezoidal", 0.0, 0.01, 2e-2),
                                                  ("trapezoidal", 0.5, 0.05, 1e-3), ("trapezoidal", 1.0, 0.01, 2e-2)])
def test_momentum_relaxation_under_constant_force(kind, phi, dt_tau, tol):
    q, E = -1e-17, 1e3
    sc, st, fc, ch = make(kind, n=3, T=0.0, dt=dt_tau * TAU, out=TAU, final=5 * TAU, E=(0, 0, E), phi=phi, charge=q)
    u = q * E / GAMMA
    step = Stepper(sc, st, fc, ch)
    z0 = st.pos[0, 2]
    pos, vel = step.advance(5)
    t = np.arange(1, 6) * TAU
    v_exact = u * (1 - np.exp(-t / TAU))
    z_exact = u * (t - TAU * (1 - np.exp(-t / TAU)))
    np.testing.assert_allclose(vel[:, 0, 2], v_exact, rtol=tol)
    # positions ~1e-5 m, displacements ~1e-13 m: allow the float64 rounding of the absolute position
    np.testing.assert_allclose(pos[:, 0, 2] - z0, z_exact, rtol=max(tol, 1e-9) * 2, atol=1e-19)


def test_overdamped_drifts_at_terminal_velocity():
    q, E = -1e-17, 1e3
    sc, st, fc, ch = make("overdamped", n=2, T=0.0, out=1e-4, E=(0, 0, E), charge=q)
    z0 = st.pos[:, 2].copy()
    pos, vel = Stepper(sc, st, fc, ch).advance(3)
    np.testing.assert_allclose(pos[-1, :, 2] - z0, 3e-4 * q * E / GAMMA, rtol=1e-9)
    np.testing.assert_allclose(vel[-1, :, 2], q * E / GAMMA, rtol=1e-12)


@pytest.mark.parametrize("kind,phi,dt_tau,expected", [
    ("ou_exact", 0.0, 0.3, 1.0),
    ("ou_exact", 0.0, 50.0, 1.0),
    ("trapezoidal", 0.5, 0.2, 1.0),                    # exact equipartition for the trapezoidal rule
    ("trapezoidal", 0.0, 0.2, 1.0 / (1 - 0.2 / 2)),    # forward Euler: kT / (1 - dt / 2 tau), 11 % too hot
])
def test_equipartition(kind, phi, dt_tau, expected):
    n = 4000
    sc, st, fc, ch = make(kind, n=n, dt=dt_tau * TAU, out=max(dt_tau, 1.0) * TAU * 2, phi=phi, init="thermal", seed=7)
    step = Stepper(sc, st, fc, ch)
    step.advance(10)  # equilibrate
    _, vel = step.advance(40)
    ratio = MASS * np.mean(vel ** 2) / KT
    # 4000 x 3 x 40 strongly correlated samples: statistical error well below 1 %
    assert ratio == pytest.approx(expected, rel=0.015)


@pytest.mark.parametrize("kind,phi,dt_tau", [("ou_exact", 0.0, 0.1), ("ou_exact", 0.0, 1000.0),
                                             ("overdamped", 0.0, 1000.0), ("trapezoidal", 0.5, 0.5)])
def test_diffusion_coefficient(kind, phi, dt_tau):
    """MSD at lag Delta: 2 D (Delta - tau (1 - e^-Delta/tau)) per component, D = kT / gamma."""
    n, frames = 600, 60
    delta = 1000 * TAU if dt_tau >= 1000 else 20 * TAU
    sc, st, fc, ch = make(kind, n=n, dt=dt_tau * TAU, out=delta, phi=phi, init="thermal", seed=11)
    step = Stepper(sc, st, fc, ch)
    p0 = st.pos.copy()
    pos, _ = step.advance(frames)
    pos = np.concatenate([p0[None], pos])
    d = np.diff(pos, axis=0)
    D = np.mean(d ** 2) / (2 * delta)
    D0 = KT / GAMMA
    inertial = 1 - (TAU / delta) * (1 - math.exp(-delta / TAU)) if kind != "overdamped" else 1.0
    se = math.sqrt(2 / d.size)
    assert D / (D0 * inertial) == pytest.approx(1.0, abs=4 * se)


def test_unstable_dt_refused_with_largest_stable_dt():
    with pytest.raises(UserError) as exc:
        make("trapezoidal", dt=3 * TAU, out=30 * TAU, phi=0.0)
    msg = str(exc.value)
    assert "unstable" in msg and f"{2 * TAU:.3g}" in msg
    with pytest.raises(UserError, match=f"{2 * TAU / (1 - 0.5):.3g}"):
        make("trapezoidal", dt=5 * TAU, out=30 * TAU, phi=0.25)
    make("trapezoidal", dt=1.9 * TAU, out=30 * TAU, phi=0.0)      # just stable: accepted
    make("trapezoidal", dt=100 * TAU, out=300 * TAU, phi=0.5)     # implicit: accepted
    make("ou_exact", dt=1e6 * TAU, out=1e6 * TAU)                 # exact: any dt


def test_auto_choice_by_physics():
    *_, ch = make("auto")
    assert ch.kind == "ou_exact" and "exact" in ch.reason
    *_, ch = make("auto", out=2e4 * TAU)
    assert ch.kind == "overdamped" and "m/gamma" in ch.reason
    *_, ch = make("auto", fields={"B": [0.0, 0.0, 1.0]})
    assert ch.kind == "trapezoidal" and "magnetic" in ch.reason
    # Re > 1: 1 um sphere driven hard in a thin fluid
    raw_E = (0.0, 0.0, -1e6)
    *_, ch = make("auto", E=raw_E, charge=-1e-12, fluid={"viscosity": 1e-4})
    assert ch.kind == "trapezoidal" and "Reynolds" in ch.reason
    with pytest.raises(UserError, match="Stokes drag"):
        make("ou_exact", E=raw_E, charge=-1e-12, fluid={"viscosity": 1e-4})


def _tiny_scene(seed=1, final=2e-3):
    return scene_from_dict({
        "seed": seed,
        "particles": {"count": 5, "radius": 1e-7, "density": 2200.0},
        "fluid": {"viscosity": 1e-3, "temperature": 293.0},
        "domain": {"size": [1e-5, 1e-5, 1e-5]},
        "boundaries": {"x": "periodic", "y": "wall"},
        "time": {"final": final, "output_interval": 1e-4},
    })


def test_same_seed_same_trajectories(tmp_path):
    a = read_table(run_scene(_tiny_scene(1), tmp_path / "a", progress=False).trajectories)
    b = read_table(run_scene(_tiny_scene(1), tmp_path / "b", progress=False).trajectories)
    c = read_table(run_scene(_tiny_scene(2), tmp_path / "c", progress=False).trajectories)
    assert len(a) == 21 * 5
    np.testing.assert_array_equal(a[["x", "y", "z", "vx"]].to_numpy(), b[["x", "y", "z", "vx"]].to_numpy())
    assert not np.allclose(a["x"].to_numpy(), c["x"].to_numpy())
    # periodic x stays in [0, L); y and z walls keep the sphere inside
    assert a["x"].between(0, 1e-5).all() and a["y"].between(1e-7, 1e-5 - 1e-7).all() and (a["z"] >= 1e-7).all()
    assert (tmp_path / "a" / "scene.json").exists()


def test_nan_stops_run_and_keeps_last_good_state(tmp_path, monkeypatch):
    import sim.run as run_mod

    orig = run_mod.Stepper.advance
    calls = {"n": 0}

    def bad_advance(self, nframes, out_pos=None, out_vel=None, **kw):
        res = orig(self, nframes, out_pos, out_vel, **kw)
        out_pos[3:] = np.nan  # the 4th frame of the first chunk goes bad
        return res

    monkeypatch.setattr(run_mod.Stepper, "advance", bad_advance)
    with pytest.raises(UserError) as exc:
        run_scene(_tiny_scene(), tmp_path, progress=False)
    msg = str(exc.value)
    assert "non-finite" in msg and "last good state" in msg and "4e-04" in msg.replace("0.0004", "4e-04")
    df = read_table(tmp_path / "trajectories.parquet")
    assert df["frame"].max() == 3 and df.attrs["ptrack"]["incomplete"]
    st = np.load(tmp_path / "last_good_state.npz")
    assert float(st["t"]) == pytest.approx(3e-4)
    np.testing.assert_allclose(st["pos"][:, 0], df[df.frame == 3]["x"].to_numpy())
    del calls


def test_wall_tables_match_direct_evaluation():
    from sim.integrate import _wall_lookup, wall_tables
    from ptrack.wall import parallel_ratio_nb, perpendicular_ratio_derivative_nb, perpendicular_ratio_nb
    tabs = wall_tables()
    for x in np.concatenate([1 + np.logspace(-6, 2, 57), [150.0, 1000.0]]):
        got = _wall_lookup(x, *tabs)
        want = (parallel_ratio_nb(x), perpendicular_ratio_nb(x), perpendicular_ratio_derivative_nb(x))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-12)


def test_hindered_overdamped_keeps_uniform_heights():
    """With the kT dM/dz drift, a uniform height distribution between wall and top stays uniform."""
    from scipy import stats

    a = 1e-6
    n = 6000
    top = 3 * a  # centre heights h in [a, 3a - a]... top wall at z = 3a: centres in [a, 2a]
    sc = scene_from_dict({
        "seed": 5,
        "particles": {"count": n, "radius": a, "density": 1000.0},
        "fluid": {"viscosity": 1e-3, "temperature": 293.0, "density": 1000.0},
        "domain": {"size": [1e-3, 1e-3, top]},
        "boundaries": {"x": "periodic", "y": "periodic", "bottom_wall": True, "top": "wall"},
        "time": {"final": 1.0, "output_interval": 0.05, "dt": 2e-4},
        "integrator": {"kind": "overdamped", "hindered_mobility": True},
    })
    st = build_state(sc)
    rng = np.random.default_rng(0)
    st.pos[:, 2] = rng.uniform(a, top - a, n)
    fc = constant_force(sc, st)
    ch = choose_integrator(sc, st, fc)
    pos, _ = Stepper(sc, st, fc, ch).advance(20)
    h = (pos[-1, :, 2] - a) / (top - 2 * a)
    assert h.min() >= 0 and h.max() <= 1
    assert stats.kstest(h, "uniform").pvalue > 1e-3
    # the layer next to the wall (gap < 5 % of a) is neither empty nor piled up
    near = np.mean(h < 0.05)
    assert near == pytest.approx(0.05, abs=4 * math.sqrt(0.05 * 0.95 / n))


def test_reflecting_walls_keep_uniform_density_with_large_steps():
    """Pure diffusion between two reflecting planes stays uniform even when a step is ~0.3 of the gap."""
    from scipy import stats

    n, a, L = 20000, 1e-7, 2e-6
    sc = scene_from_dict({
        "seed": 8,
        "particles": {"count": n, "radius": a, "density": 2200.0},
        "fluid": {"viscosity": 1e-3, "temperature": 293.0},
        "gravity": {"enabled": False},
        "domain": {"size": [1e-3, 1e-3, L]},
        "boundaries": {"x": "periodic", "y": "periodic", "bottom_wall": True, "top": "wall"},
        "time": {"final": 0.1, "output_interval": 0.01 * (0.3 * (L - 2 * a)) ** 2 / (2 * KT / GAMMA) / 0.01},
    })
    st = build_state(sc)
    st.pos[:, 2] = np.random.default_rng(1).uniform(a, L - a, n)
    fc = constant_force(sc, st)
    ch = choose_integrator(sc, st, fc)
    assert ch.steps_per_output == 1  # no drift: the walls do not shorten dt
    pos, _ = Stepper(sc, st, fc, ch).advance(10)
    h = (pos[-1, :, 2] - a) / (L - 2 * a)
    assert h.min() >= 0 and h.max() <= 1
    assert stats.kstest(h, "uniform").pvalue > 1e-3
