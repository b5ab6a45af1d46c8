"""DEM engine: conservation, determinism, resume, blow-up detection, automatic dt, scene parsing."""
import copy
import math

import numpy as np
import pytest

from ptrack.errors import UserError
from ptrack.table import read_table
from sim.dem import DEMSystem, auto_dt, counter_normal, run_dem
from sim.forces.contact import CONTACT_HOOKE, CONTACT_POWER, hooke_params, power_params
from sim.scene import scene_from_dict


def _lattice_gas(n, L, rad, seed):
    rng = np.random.default_rng(seed)
    k = int(math.ceil(n ** (1 / 3)))
    g = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    pos = (g + 0.5) * (L / k) + 0.01 * rad * rng.standard_normal((n, 3))
    return pos, rng


def test_momentum_conserved_in_periodic_box_without_external_force():
    L = 1.0
    rad = 0.06
    pos, rng = _lattice_gas(300, L, rad, 0)  # spacing 1/7 = 0.143 > 0.12: collisions start soon
    m = np.full(300, 0.9)
    vel = rng.standard_normal((300, 3))
    s = DEMSystem(pos, vel, np.full(300, rad), m, -m, model=CONTACT_HOOKE, cp=hooke_params(1e5, 0.6, mu=0.5),
                  rotation=True, nf_model=1, nfp=np.array([0.01, 0.001, 1.0, 2.0, 0.2]), cutoff=0.2,
                  box_length=(L, L, L), periodic=(1, 1, 1), dt=2e-5, skin=0.02)
    p0 = (m[:, None] * s.vel).sum(0)
    ke0 = s.kinetic_energy()
    s.run(20000)
    assert s.n_builds > 3
    p1 = (m[:, None] * s.vel).sum(0)
    scale = (m[:, None] * np.abs(s.vel)).sum()
    assert np.abs(p1 - p0).max() < 1e-12 * scale
    assert s.kinetic_energy() < ke0  # inelastic collisions happened


def test_counter_rng_is_keyed_and_normal():
    a = np.array([counter_normal(7, 3, i) for i in range(20000)])
    b = np.array([counter_normal(7, 3, i) for i in range(20000)])
    np.testing.assert_array_equal(a, b)
    assert abs(a.mean()) < 0.03 and abs(a.std() - 1) < 0.02
    assert counter_normal(7, 4, 0) != counter_normal(7, 3, 0)


def _brownian_system(kT):
    pos, rng = _lattice_gas(64, 1.0, 0.05, 1)
    m = np.full(64, 1.0)
    return DEMSystem(pos, np.zeros((64, 3)), np.full(64, 0.05), m, model=CONTACT_HOOKE,
                     cp=hooke_params(1e4, 0.5, mu=0.3), drag_mode=1, gamma=np.full(64, 2.0),
                     extp=np.array([0, 0, 0, 0, 0, kT, 0, 0, 0.0]), box_length=(1, 1, 1), periodic=(1, 1, 1),
                     dt=1e-3, seed=11)


def test_split_run_via_state_equals_single_run_with_brownian_forces():
    a = _brownian_system(0.05)
    a.run(3000)
    b = _brownian_system(0.05)
    b.run(1500, rebuild_at_end=True)
    st = b.get_state()
    c = _brownian_system(0.05)
    c.set_state(st)
    c.run(1500)
    # a was not rebuilt at step 1500, so compare c against an identically rebuilt a2
    a2 = _brownian_system(0.05)
    a2.run(1500, rebuild_at_end=True)
    a2.run(1500)
    np.testing.assert_array_equal(c.unwrapped, a2.unwrapped)
    np.testing.assert_array_equal(c.vel, a2.vel)
    np.testing.assert_allclose(a.unwrapped, a2.unwrapped, rtol=0, atol=1e-9)
    # equipartition with the FDT-scaled random force: m <v^2> = kT per component
    v2 = np.mean(a.vel**2)
    assert 0.6 * 0.05 < v2 < 1.4 * 0.05


def _scene(**over):
    raw = {
        "seed": 4,
        "particles": {"count": 60, "radius": 0.05, "density": 1540.0, "charge_per_mass": -1.0},
        "fluid": {"density": 1.2, "viscosity": 1.8e-5, "temperature": 0.0},
        "fields": {"E": [0.0, 0.0, 100.0]},
        "domain": {"size": [0.6, 0.6, 0.8]},
        "boundaries": {"x": "periodic", "y": "periodic", "bottom_wall": True},
        "time": {"dt": "auto", "final": 0.04, "output_interval": 0.004},
        "contact": {"model": "hooke", "kn": 1e6, "restitution": 0.4, "checkpoint_every": 3},
        "friction": {"mu": 0.4},
    }
    for k, v in over.items():
        if isinstance(v, dict):
            merged = {**raw.get(k, {}), **v}
            raw[k] = {a: b for a, b in merged.items() if b is not None}  # None removes a key
        else:
            raw[k] = v
    return scene_from_dict(raw)


def test_resume_equals_uninterrupted_run(tmp_path, monkeypatch):
    sc = _scene()
    full = run_dem(sc, tmp_path / "full", progress=False)
    ref = read_table(tmp_path / "full" / "trajectories.parquet")
    assert full["steps"] > 100 and full["n_frames"] == 11

    import sim.checkpoint as ck

    calls = {"n": 0}
    real = ck.save_checkpoint

    def crash_after_second(*a, **k):
        real(*a, **k)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("simulated crash")

    monkeypatch.setattr(ck, "save_checkpoint", crash_after_second)
    with pytest.raises(KeyboardInterrupt):
        run_dem(sc, tmp_path / "cut", progress=False)
    monkeypatch.setattr(ck, "save_checkpoint", real)
    part = read_table(tmp_path / "cut" / "trajectories.parquet", validate_table=False)
    assert part["frame"].max() == 6
    res = run_dem(sc, tmp_path / "cut", resume=True, progress=False)
    assert res["resumed_from_step"] > 0
    got = read_table(tmp_path / "cut" / "trajectories.parquet")
    assert len(got) == len(ref)
    for c in ("frame", "t", "particle", "x", "y", "z", "vx", "vy", "vz"):
        np.testing.assert_array_equal(got[c].to_numpy(), ref[c].to_numpy(), err_msg=c)


def test_resume_rejects_other_scene(tmp_path):
    run_dem(_scene(), tmp_path, progress=False)
    with pytest.raises(UserError, match="different scene"):
        run_dem(_scene(seed=5), tmp_path, resume=True, progress=False)


def test_blow_up_is_caught_with_step_particle_and_suggested_dt(tmp_path):
    sc = _scene(time={"dt": 2e-3}, contact={"kn": 1e9})
    with pytest.raises(UserError) as ei:
        run_dem(sc, tmp_path, progress=False)
    msg = str(ei.value)
    assert "blow-up at step" in msg and "particle" in msg and "reduce time.dt" in msg
    assert (tmp_path / "last_good_state.npz").exists()
    meta = read_table(tmp_path / "trajectories.parquet", validate_table=False).attrs["ptrack"]
    assert "incomplete" in meta


def test_auto_dt_is_stable_and_deposits(tmp_path):
    sc = _scene(contact={"kn": 1e8})
    res = run_dem(sc, tmp_path, progress=False)
    s = res.system
    assert np.all(s.pos[:, 2] > 0) and np.all(np.isfinite(s.vel))
    assert res["max_overlap_ratio"] < 0.1
    dt, why = auto_dt(sc.interactions, s.radius, s.mass, s.fconst)
    assert dt <= 0.2 * why["pair_critical_dt"] + 1e-18


def test_power_law_auto_dt_uses_representative_overlap():
    sc = _scene(contact={"model": "power", "K": 1e9, "exponent": 2.0, "damping": 1e8, "kn": None,
                                 "restitution": None}, friction={"mu": None})
    s = run_dem.__globals__["system_from_scene"](sc)[0]
    dt, why = auto_dt(sc.interactions, s.radius, s.mass, s.fconst, height=0.8)
    assert 0 < why["pair_overlap_rep"] < 0.05 and 1e-8 < dt < 1e-4


def test_phi_scheme_trapezoidal_conserves_energy_of_elastic_bounce():
    kn, m, r, v0 = 1e6, 0.5, 0.05, 1.0
    tc = math.pi / math.sqrt(kn / m)
    dt = tc / 40
    for phi, n_iter, tol in ((0.5, 30, 1e-3),):
        s = DEMSystem([[0, 0, r + 0.01]], [[0, 0, -v0]], [r], [m], model=CONTACT_HOOKE, cp=hooke_params(kn, 1.0),
                      rotation=False, walls=[[0, 0, 0, 0, 0, 1]], dt=dt, integrator=1, phi=phi, n_iter=n_iter)
        s.run(int((0.02 / v0 + 2 * tc) / dt))
        assert abs(s.vel[0, 2] - v0) < tol * v0 * 50


def test_trapezoidal_scene_uses_phi_scheme(tmp_path):
    sc = _scene(integrator={"kind": "trapezoidal", "phi": 0.5, "max_iterations": 20, "tolerance": 1e-9},
                time={"final": 0.012})
    res = run_dem(sc, tmp_path, progress=False)
    assert res.system.integrator == 1 and res.system.phi == 0.5
    assert np.all(np.isfinite(res.system.pos)) and np.all(res.system.pos[:, 2] > 0)


def test_interaction_sections_are_validated():
    with pytest.raises(UserError, match="contact.stiffness"):
        _scene(contact={"stiffness": 3})
    with pytest.raises(UserError, match="restitution"):
        _scene(contact={"restitution": 1.5})
    with pytest.raises(UserError, match="bonding"):
        _scene(bonding={"K_nb": 1.0})
    with pytest.raises(UserError, match="mu_d"):
        _scene(contact={"model": "power", "K": 1e9, "kn": None, "restitution": None}, friction={"mu": None, "mu_s": 0.2, "mu_d": 0.3})
    sc = _scene()
    assert sc.interactions.any_pair_force and sc.interactions.rotation


def _sheared_pile(sort):
    """Frictional spheres (Hooke/Coulomb, rotation) falling onto the substrate in a periodic box: many
    contacts with tangential springs, particle rebuilds and re-orderings."""
    pos, rng = _lattice_gas(216, 1.0, 0.06, 3)
    pos[:, 2] = 0.1 + 0.8 * pos[:, 2]
    m = np.full(216, 0.5)
    vel = 0.5 * rng.standard_normal((216, 3))
    s = DEMSystem(pos, vel, np.full(216, 0.06), m, model=CONTACT_HOOKE, cp=hooke_params(1e6, 0.5, mu=0.5),
                  rotation=True, walls=[[0, 0, 0, 0, 0, 1]], box_length=(1, 1, 1), periodic=(1, 1, 0),
                  fconst=np.tile([0.0, 0.0, -25.0], (216, 1)), dt=5e-5, skin=0.02, sort=sort)
    return s


def test_cell_ordered_memory_is_the_same_dynamics_and_resumes_bit_identically():
    a = _sheared_pile(False)
    b = _sheared_pile(True)
    assert np.array_equal(b.by_id(b.pos), a.pos)  # same start, in id order
    a.run(3000)
    b.run(3000)
    assert b.n_builds > 3 and not np.array_equal(b.particle_order, np.arange(216))
    assert np.array_equal(np.sort(b.particle_order), np.arange(216))
    # the pile formed: particles on the wall and many frictional contacts with springs carried
    assert b.diag[4] > 100
    # the re-ordering changes the summation order only: round-off, not physics (the sign rule of a pair
    # that changes its storing particle: tests/test_neighbors.py)
    np.testing.assert_allclose(b.by_id(b.unwrapped), a.unwrapped, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.by_id(b.vel), a.vel, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.by_id(b.omega), a.omega, rtol=0, atol=1e-4)
    ga, gb = a.get_state(), b.get_state()
    ka = {(i, j): v for i, j, v in zip(ga["hist_i"], ga["hist_j"], ga["hist_v"])}
    kb = {(i, j): v for i, j, v in zip(gb["hist_i"], gb["hist_j"], gb["hist_v"])}
    assert set(ka) == set(kb) and len(ka) > 100
    assert max(np.abs(ka[p] - kb[p]).max() for p in ka) < 1e-9 * max(np.abs(v).max() for v in ka.values()) + 1e-15
    # resume from a snapshot (id order) equals the uninterrupted sorted run bit for bit
    c = _sheared_pile(True)
    c.run(600, rebuild_at_end=True)
    snap = c.get_state()
    c.run(600)
    d = _sheared_pile(True)
    d.set_state(snap)
    d.run(600)
    for k in ("pos", "vel", "omega", "image", "whist"):
        np.testing.assert_array_equal(c.by_id(getattr(c, k)), d.by_id(getattr(d, k)))


def _falling_bed(n=200, sort=True, v_max=np.inf, dt=1e-5, seed=3):
    """Spheres at rest above a wall, pulled down hard (g = 500 m/s^2), friction on: contacts, wall and
    rebuilds within a few thousand steps."""
    rng = np.random.default_rng(seed)
    L = 0.5
    k = int(math.ceil(n ** 0.5))
    g = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2)[:n]
    pos = np.column_stack([(g + 0.5) * (L / k), 0.03 + 0.2 * rng.random(n)])
    m = np.full(n, 1e-3)
    fconst = np.zeros((n, 3))
    fconst[:, 2] = -500.0 * m
    return DEMSystem(pos, np.zeros((n, 3)), np.full(n, 0.01), m, model=CONTACT_HOOKE,
                     cp=hooke_params(1e5, 0.4, mu=0.4), rotation=True, walls=[[0, 0, 0, 0, 0, 1]],
                     box_length=(L, L, 1.0), periodic=(1, 1, 0), fconst=fconst, dt=dt, skin=0.002, sort=sort,
                     v_max=v_max)


def _plain(system):
    from sim.dem import G_PLAIN

    system.guards[G_PLAIN] = 1.0  # every second half kick in a pass of its own
    return system


@pytest.mark.parametrize("sort", [True, False])
def test_verlet_fused_second_half_kick_is_bit_identical_to_the_plain_stepper(sort):
    # the fused stepper (a step's second half kick inside the next step's pass) against the plain one:
    # the whole state equal bit for bit after calls of several lengths and a run 'until' a time
    a, b = _falling_bed(sort=sort), _plain(_falling_bed(sort=sort))
    for k in (1, 7, 1500, 2500):
        assert a.run(k) == b.run(k) == 0
        st_a, st_b = a.get_state(), b.get_state()
        for key in st_a:
            assert np.array_equal(st_a[key], st_b[key]), key
    assert a.n_builds == b.n_builds and a.n_builds > 3
    t_stop = a.t + 123.5 * a.dt
    assert a.run(1000, until=t_stop) == b.run(1000, until=t_stop) == 0
    assert a.step == b.step and a.t == b.t
    for key, v in a.get_state().items():
        assert np.array_equal(v, b.get_state()[key]), key


@pytest.mark.parametrize("case", ["speed", "overlap"])
def test_verlet_fused_blow_up_ends_where_the_plain_stepper_ends(case):
    # a blow-up found one pass late (speed) makes DEMSystem.run repeat the call without the fusion; an
    # overlap ends the call at once: the status, step, particle and the state left are those of the plain
    # stepper
    kw = dict(v_max=1.2) if case == "speed" else dict(dt=2e-4)
    a, b = _falling_bed(**kw), _plain(_falling_bed(**kw))
    a.run(3)
    b.run(3)
    sa, sb = a.run(5000), b.run(5000)
    assert sa == sb != 0
    assert a.step == b.step and a.fail_particle == b.fail_particle and a.step < 5003
    for key, v in a.get_state().items():
        assert np.array_equal(v, b.get_state()[key]), key


@pytest.mark.parametrize("sort", [True, False])
@pytest.mark.parametrize("frac", [0.05, 0.3])
def test_verlet_near_sub_list_is_bit_identical_to_the_whole_list(sort, frac):
    # the velocity-Verlet stepper's near sub-list (pairs within max(R_i + R_j, cutoff) + margin, re-filtered
    # when a distance may have shrunk by 0.9 margin): the same state bit for bit as the whole list, with
    # contacts forming and breaking, rebuilds and re-orderings, and fewer pairs visited per step
    from sim.dem import P_NEAR_FILTERS, P_NEAR_PAIRS

    a = _sheared_pile(sort)
    a.guards[9] = frac * a.skin  # G_NEAR
    b = _sheared_pile(sort)
    b.guards[9] = 0.0  # off: the whole list
    refilter = 0
    for k in (1, 7, 1500, 2500, 3000):
        assert a.run(k) == b.run(k) == 0
        st_a, st_b = a.get_state(), b.get_state()
        for key in st_a:
            assert np.array_equal(st_a[key], st_b[key]), key
        assert b.chunk_peaks[P_NEAR_FILTERS] == 0
        refilter += a.chunk_peaks[P_NEAR_FILTERS]
        assert a.chunk_peaks[P_NEAR_PAIRS] <= len(a.nbj)
    assert a.n_builds == b.n_builds > 3 and a.diag[4] > 100 and 50 < a.chunk_peaks[P_NEAR_PAIRS] < len(a.nbj)
    assert refilter > a.n_builds + 5  # filtered far more often than the list was rebuilt


def test_verlet_near_sub_list_is_not_refiltered_while_the_bed_moves_as_one():
    # the bound on how much a distance shrank uses the velocities relative to the mean: spheres falling
    # together (no contacts) keep their sub-list; one sphere moving against the others re-filters it
    from sim.dem import DEMSystem, P_NEAR_FILTERS

    pos, _ = _lattice_gas(64, 1.0, 0.05, 1)
    pos[:, 2] += 2.0
    s = DEMSystem(pos, np.tile([0.3, 0.0, -2.0], (64, 1)), np.full(64, 0.05), np.full(64, 1.0),
                  model=CONTACT_HOOKE, cp=hooke_params(1e5, 0.5), rotation=True, box_length=(1, 1, 4),
                  periodic=(1, 1, 0), dt=1e-4, skin=0.02, near_margin=0.002)
    assert s.run(2000) == 0
    assert s.chunk_peaks[P_NEAR_FILTERS] == 1 + s.n_builds - 1  # the call's start and each rebuild
    vel = s.vel.copy()
    vel[0, 0] += 0.5
    s.vel[:] = vel
    b0 = s.n_builds
    assert s.run(2000) == 0
    assert s.chunk_peaks[P_NEAR_FILTERS] > 1 + (s.n_builds - b0) + 5
