"""Contact laws against hand calculations; restitution; Newton's third law; periodic images."""
import math

import numpy as np
import pytest

from sim.dem import DEMSystem
from sim.forces.contact import (CONTACT_HOOKE, CONTACT_POWER, contact_force_pair, hooke_params, power_params,
                                restitution_beta)
from sim.forces.nearfield import NF_SEED, NF_YUKAWA, nearfield_pair


def test_hooke_normal_hand_calculation():
    kn, e = 1e5, 0.5
    cp = hooke_params(kn, e, mu=0.0)
    ri, rj, mi, mj = 0.1, 0.2, 2.0, 3.0
    delta = 0.01
    vi, vj = (0.0, 0.0, -1.0), (0.0, 0.0, 0.5)   # approaching along z
    fi, fj, ti, tj, _ = contact_force_pair(CONTACT_HOOKE, cp, (0, 0, 0.29), (0, 0, 0), ri, rj, mi, mj, vi, vj)
    meff = mi * mj / (mi + mj)
    le = math.log(e)
    eta = 2 * (-le / math.sqrt(math.pi**2 + le**2)) * math.sqrt(kn * meff)
    vn = -1.5  # (v_i - v_j) . n, n = +z from j to i
    want = kn * delta - eta * vn
    np.testing.assert_allclose(fi, [0, 0, want], rtol=1e-12)
    np.testing.assert_allclose(fj, -fi, rtol=0, atol=0)
    assert not ti.any() and not tj.any()


def test_hooke_tangential_spring_and_coulomb_limit():
    kn, kt, mu = 1e5, 2e4, 0.3
    cp = hooke_params(kn, 1.0, kt=kt, mu=mu, damp_t_ratio=0.0)  # e = 1: no damping
    r = 0.1
    xi, xj = (0, 0, 0.19), (0, 0, 0)  # delta = 0.01 -> F_n = 1000 N
    dt = 1e-4
    # small tangential velocity: stick, F_t = -kt * v dt
    fi, _, ti, tj, h = contact_force_pair(CONTACT_HOOKE, cp, xi, xj, r, r, 1.0, 1.0, vi=(0.1, 0, 0), dt=dt)
    np.testing.assert_allclose(fi, [-kt * 0.1 * dt, 0, 1000.0], rtol=1e-12)
    np.testing.assert_allclose(h, [0.1 * dt, 0, 0], rtol=1e-12)
    # torque on i = (-R n) x F_t with n = +z: (-R z) x (Ft x) = -R Ft y
    np.testing.assert_allclose(ti, [0, -r * fi[0], 0], rtol=1e-12)
    np.testing.assert_allclose(tj, ti, rtol=1e-12)
    # large stored spring: slip at mu F_n, spring reset to the slip limit
    fi, _, _, _, h = contact_force_pair(CONTACT_HOOKE, cp, xi, xj, r, r, 1.0, 1.0, vi=(1.0, 0, 0), dt=dt,
                                        hist=(1.0, 0, 0))
    np.testing.assert_allclose(fi, [-mu * 1000.0, 0, 1000.0], rtol=1e-12)
    np.testing.assert_allclose(h, [mu * 1000.0 / kt, 0, 0], rtol=1e-12)
    # rolling without sliding: v_i = w x (R n) cancels the contact-point velocity -> no tangential force
    w = 0.5
    fi, _, _, _, h = contact_force_pair(CONTACT_HOOKE, cp, xi, xj, r, r, 1.0, 1.0, vi=(w * r, 0, 0),
                                        wi=(0, w, 0), dt=dt)
    np.testing.assert_allclose(fi[:2], 0, atol=1e-12)


def test_power_law_hand_calculation():
    K, p, ccd = 1e9, 2.0, 1e8
    ri, rj = 0.05, 0.07
    d = 0.115
    cp = power_params(K, p, ccd)
    vi, vj = (0, 0, -0.2), (0, 0, 0.1)
    fi, fj, _, _, _ = contact_force_pair(CONTACT_POWER, cp, (0, 0, d), (0, 0, 0), ri, rj, 1.0, 1.0, vi, vj)
    delta = ri + rj - d
    eps = delta / (ri + rj)
    li = 0.5 * (d - (rj**2 - ri**2) / d)          # eq. 3.16
    area = math.pi * (ri**2 - li**2)               # eq. 3.15
    contact = K * eps**p * area                    # eq. 3.12 (repulsive, along n = +z on i)
    dissip = ccd * (vj[2] - vi[2]) * area          # eq. 3.17 on i, along +z
    np.testing.assert_allclose(fi, [0, 0, contact + dissip], rtol=1e-12)
    np.testing.assert_array_equal(fj, -fi)
    # the contact circle is the same seen from j
    lj = 0.5 * (d - (ri**2 - rj**2) / d)
    assert math.isclose(rj**2 - lj**2, ri**2 - li**2, rel_tol=1e-12)


def test_power_law_bonding_switches_on_at_critical_strain():
    K, Knb, eps_star = 1e9, 1e8, 0.02
    r = 0.05
    cp = power_params(K, 2.0, 0.0, K_nb=Knb, p_b=2.0, eps_star=eps_star, bonding=True)
    for eps in (0.015, 0.025):
        d = 2 * r * (1 - eps)
        fi, _, _, _, _ = contact_force_pair(CONTACT_POWER, cp, (0, 0, d), (0, 0, 0), r, r, 1.0, 1.0)
        area = math.pi * (r**2 - (d / 2) ** 2)
        want = K * eps**2 * area - (Knb * eps**2 * area if eps >= eps_star else 0.0)  # eq. 3.19 attractive
        np.testing.assert_allclose(fi[2], want, rtol=1e-12)


def test_power_law_wall_uses_particle_strain():
    K, r, z = 1e11, 0.05, 0.049
    cp = power_params(K, 2.0, 0.0)
    s = DEMSystem([[0.3, 0.3, z]], [[0, 0, 0]], [r], [1.0], model=CONTACT_POWER, cp=cp, cpw=cp, rotation=False,
                  walls=[[0, 0, 0, 0, 0, 1]])
    delta = r - z
    want = K * (delta / r) ** 2 * math.pi * (r**2 - z**2)
    np.testing.assert_allclose(s.force[0], [0, 0, want], rtol=1e-12)


def test_nearfield_laws():
    # seed eq. 3.24-3.25: (a1 r^-b1 - a2 r^-b2) along n_ij (toward j); a = abar qi qj
    p = [0.5, 0.05, 1.0, 2.0, 0.3]
    qi, qj, r = -0.8, -0.6, 0.12
    toward_j = 0.5 * qi * qj / r - 0.05 * qi * qj / r**2
    assert math.isclose(nearfield_pair(NF_SEED, p, r, 0.05, 0.05, qi, qj), -toward_j, rel_tol=1e-12)
    assert nearfield_pair(NF_SEED, p, 0.31, 0.05, 0.05, qi, qj) == 0.0
    # screened Coulomb: F = U (kappa + 1/r), U = A a_i a_j exp(-kappa (r - a_i - a_j)) / r
    A, kappa, ai, aj, r = 2e-3, 1e8, 1e-7, 2e-7, 3.2e-7
    U = A * ai * aj * math.exp(-kappa * (r - ai - aj)) / r
    got = nearfield_pair(NF_YUKAWA, [A, kappa, 1e-6, 0, 0], r, ai, aj, 0, 0)
    assert math.isclose(got, U * (kappa + 1 / r), rel_tol=1e-12)
    # and it is minus the derivative of U (numerically)
    h = 1e-13
    Uf = lambda x: A * ai * aj * math.exp(-kappa * (x - ai - aj)) / x  # noqa: E731
    assert math.isclose(got, -(Uf(r + h) - Uf(r - h)) / (2 * h), rel_tol=1e-5)


@pytest.mark.parametrize("e", [0.3, 0.7, 0.95])
def test_restitution_of_wall_impact_matches_damped_oscillator(e):
    kn, m, r, v0 = 1e6, 0.5, 0.05, 2.0
    cp = hooke_params(kn, e, mu=0.0)
    omega = math.sqrt(kn / m)
    beta = restitution_beta(e)
    # contact time of the damped linear oscillator: pi / (omega sqrt(1 - beta^2))
    tc = math.pi / (omega * math.sqrt(1 - beta**2))
    dt = tc / 2000
    s = DEMSystem([[0.0, 0.0, r + 0.5 * v0 * dt]], [[0, 0, -v0]], [r], [m], model=CONTACT_HOOKE, cp=cp, cpw=cp,
                  rotation=False, walls=[[0, 0, 0, 0, 0, 1]], dt=dt)
    s.run(int(1.5 * tc / dt))
    assert s.pos[0, 2] > r  # left the wall
    e_sim = s.vel[0, 2] / v0
    assert abs(e_sim - e) < 2e-3 * max(e, 0.3), (e_sim, e)
    # analytic: e = exp(-beta pi / sqrt(1 - beta^2))
    assert math.isclose(math.exp(-beta * math.pi / math.sqrt(1 - beta**2)), e, rel_tol=1e-12)


def _dense_random(n, L, seed, rad=0.05):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(k) for k in (L / (1.9 * rad)).astype(int)], indexing="ij"), -1)
    g = g.reshape(-1, 3)[:n] * 1.9 * rad + rad
    return g + 0.003 * rng.standard_normal(g.shape), rng


@pytest.mark.parametrize("model", [CONTACT_HOOKE, CONTACT_POWER])
def test_newton_third_law_to_round_off(model):
    L = np.array([1.0, 1.0, 1.0])
    pos, rng = _dense_random(500, L, 1)
    rad = 0.05 * (1 + 0.1 * rng.uniform(-1, 1, len(pos)))
    m = 1540 * 4 / 3 * np.pi * rad**3
    cp = hooke_params(1e7, 0.4, mu=0.5) if model == CONTACT_HOOKE else \
        power_params(1e9, 2.0, 1e6, K_nb=1e8, K_rb=1e5, eps_star=0.01, K_f=1e9, mu_s=0.4, mu_d=0.3,
                     bonding=True, friction=True)
    q = -m
    s = DEMSystem(pos, rng.standard_normal(pos.shape), rad, m, q, model=model, cp=cp, cpw=cp, rotation=True,
                  nf_model=NF_SEED, nfp=np.array([0.5, 0.05, 1.0, 2.0, 0.15]), cutoff=0.15,
                  box_length=L, periodic=(1, 1, 1), dt=1e-6)
    s.omega[:] = rng.standard_normal(pos.shape)
    s.compute_forces()
    assert s.diag[4] > 200  # many contacts
    scale = np.abs(s.force).sum()
    assert np.abs(s.force.sum(0)).max() < 1e-12 * scale
    # same pair once: each tangential force gives torques -R_i n x F_t and -R_j n x F_t
    # (angular momentum is conserved only up to O(overlap/R), as in every soft-sphere DEM code)
    assert np.isfinite(s.torque).all()


def test_same_forces_across_periodic_boundary_and_in_interior():
    L = np.array([2.0, 2.0, 2.0])
    cp = hooke_params(1e6, 0.5, mu=0.4)
    nfp = np.array([0.5, 0.05, 1.0, 2.0, 0.3])
    base = np.array([[0.0, 0.0, 0.0], [0.08, 0.03, -0.04], [-0.2, 0.1, 0.05]])
    vel = np.array([[0.1, -0.2, 0.3], [-0.3, 0.1, 0.0], [0.0, 0.2, -0.1]])
    out = []
    for centre in ([1.0, 1.0, 1.0], [1.97, 0.02, 1.0]):  # interior / straddling the x and y faces
        pos = np.mod(base + np.array(centre), L)
        s = DEMSystem(pos, vel, [0.05, 0.06, 0.05], [1.0, 1.2, 0.9], [-1, -1.2, -0.9], model=CONTACT_HOOKE, cp=cp,
                      cpw=cp, nf_model=NF_SEED, nfp=nfp, cutoff=0.3, box_length=L, periodic=(1, 1, 1), dt=1e-5)
        s.omega[:] = [[1, 0, 0], [0, 2, 0], [0, 0, 3]]
        x0 = s.unwrapped
        s.run(50)
        out.append((s.force.copy(), s.torque.copy(), s.unwrapped - x0))
    np.testing.assert_allclose(out[1][0], out[0][0], rtol=1e-9, atol=1e-9 * np.abs(out[0][0]).max())
    np.testing.assert_allclose(out[1][1], out[0][1], rtol=1e-9, atol=1e-9 * np.abs(out[0][1]).max())
    np.testing.assert_allclose(out[1][2], out[0][2], atol=1e-12)


def test_threaded_pair_kernel_matches_serial():
    L = np.array([1.0, 1.0, 1.0])
    pos, rng = _dense_random(500, L, 2)
    rad = np.full(len(pos), 0.05)
    m = np.full(len(pos), 0.8)
    cp = hooke_params(1e7, 0.4, mu=0.5)
    out = []
    for threads in (1, 3):
        s = DEMSystem(pos, np.zeros_like(pos), rad, m, model=CONTACT_HOOKE, cp=cp, rotation=True, box_length=L,
                      periodic=(1, 1, 1), dt=1e-6, threads=threads)
        s.vel[:] = np.random.default_rng(9).standard_normal(pos.shape)
        s.run(200)
        out.append((s.force.copy(), s.torque.copy(), s.diag.copy()))
    scale = np.abs(out[0][0]).max()
    np.testing.assert_allclose(out[1][0], out[0][0], atol=1e-9 * scale)
    np.testing.assert_allclose(out[1][1], out[0][1], atol=1e-9 * np.abs(out[0][1]).max())
    assert out[1][2][4] == out[0][2][4] > 100


def _wall_bed(n=600, seed=4):
    """A loose random packing over a wall at z = 0 (periodic x, y), radii +-10 %, random spins."""
    L = np.array([0.6, 0.6, 1.2])
    pos, rng = _dense_random(n, L, seed)
    rad = 0.05 * (1 + 0.1 * rng.uniform(-1, 1, len(pos)))
    pos[:, 2] -= 0.012  # the lowest layer presses into the wall
    return L, pos, rad, 1540 * 4 / 3 * np.pi * rad**3, rng


@pytest.mark.parametrize("nt", [2, 3])
def test_threaded_kernel_owner_writes_and_halo(nt):
    """The threaded pair + wall kernel gives the serial forces to round-off, writes each contact history
    row once, and leaves its halo buffers zero (they are reused across steps without clearing)."""
    from sim.forces.contact import D_SIZE, _pair_rows, pair_forces_parallel, thread_blocks, wall_forces
    from sim.neighbors import build_neighbor_list

    L, pos, rad, m, rng = _wall_bed()
    n = len(pos)
    vel = rng.standard_normal((n, 3))
    om = rng.standard_normal((n, 3))
    cp = hooke_params(1e6, 0.4, mu=0.5)
    walls = np.array([[0.0, 0, 0, 0, 0, 1]])
    start, nbj, shift = build_neighbor_list(pos, rad, 0.0, 0.01, np.zeros(3), L, np.array([1, 1, 0]))
    laws = np.zeros((0, 8))
    hist0 = 1e-4 * rng.standard_normal((len(nbj), 3))
    whist0 = 1e-4 * rng.standard_normal((n, 3))

    def serial():
        f, t, h, wh, d = np.zeros((n, 3)), np.zeros((n, 3)), hist0.copy(), whist0.copy(), np.zeros(D_SIZE)
        _pair_rows(0, n, pos, vel, om, rad, m, np.zeros(n), start, nbj, shift, h, f, t, CONTACT_HOOKE, cp, laws,
                   True, 1e-6, d, n, f, t)
        wall_forces(pos, vel, om, rad, m, walls, wh, f, t, CONTACT_HOOKE, cp, True, 1e-6, d)
        return f, t, h, wh, d

    f1, t1, h1, wh1, d1 = serial()
    rows, hs, hidx = thread_blocks(start, nbj, nt)
    assert rows[0] == 0 and rows[-1] == n and np.all(np.diff(rows) > 0)
    # every partner of a block's rows beyond the block is in its halo list, once
    for b in range(nt - 1):
        js = nbj[start[rows[b]]:start[rows[b + 1]]]
        want = np.unique(js[js >= rows[b + 1]])
        got = hidx[hs[b]:hs[b + 1]]
        assert len(got) == len(want) > 0 and np.array_equal(np.sort(got), want)
    fbuf, tbuf, dbuf = np.zeros((nt, n, 3)), np.zeros((nt, n, 3)), np.zeros((2 * nt, D_SIZE))
    for _ in range(2):  # the second pass reuses the buffers the first left
        f, t, h, wh, d = np.zeros((n, 3)), np.zeros((n, 3)), hist0.copy(), whist0.copy(), np.zeros(D_SIZE)
        pair_forces_parallel(rows, hs, hidx, pos, vel, om, rad, m, np.zeros(n), start, nbj, shift, h, f, t,
                             CONTACT_HOOKE, cp, laws, True, 1e-6, d, fbuf, tbuf, dbuf, True, walls, wh, cp, True)
        assert not fbuf.any() and not tbuf.any()
        scale = np.abs(f1).max()
        np.testing.assert_allclose(f, f1, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(t, t1, rtol=0, atol=1e-12 * np.abs(t1).max())
        np.testing.assert_array_equal(h, h1)  # history rows: the same arithmetic, one writer each
        np.testing.assert_array_equal(wh, wh1)
        assert d[4] == d1[4] > 100 and d[0] == d1[0] and d[1] == d1[1]


def test_threaded_verlet_stepper_matches_serial():
    """Whole velocity-Verlet runs (cell-sorted memory, near sub-list, wall, rotation, gravity) on 1, 2
    and 3 threads agree to round-off, and a threaded run repeats itself exactly."""
    L, pos, rad, m, _ = _wall_bed()
    cp = hooke_params(1e6, 0.4, mu=0.5)
    out = {}
    for threads in (1, 2, 3, 2):
        s = DEMSystem(pos, np.zeros_like(pos), rad, m, model=CONTACT_HOOKE, cp=cp, rotation=True, box_length=L,
                      periodic=(1, 1, 0), walls=[[0, 0, 0, 0, 0, 1]], fconst=m[:, None] * [0, 0, -9.81],
                      dt=2e-5, threads=threads, sort=True)
        s.run(400)
        s.run(400)
        got = (s.by_id(s.pos).copy(), s.by_id(s.vel).copy(), s.by_id(s.omega).copy())
        if threads in out:
            for a, b in zip(got, out[threads]):
                np.testing.assert_array_equal(a, b)
        out[threads] = got
    vscale = np.abs(out[1][1]).max()
    assert vscale > 0
    for threads in (2, 3):
        np.testing.assert_allclose(out[threads][0], out[1][0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(out[threads][1], out[1][1], rtol=0, atol=1e-9 * vscale)


@pytest.mark.parametrize("env, expect", [({}, "10000"), ({"GOMP_SPINCOUNT": "77"}, "77"),
                                         ({"OMP_WAIT_POLICY": "PASSIVE"}, None)])
def test_openmp_spin_default_is_set_before_libgomp_loads(env, expect):
    # a short OpenMP spin unless the user chose a policy; it only acts if set before sim.dem loads libgomp
    import os
    import subprocess
    import sys

    code = ("import os, sim.dem; maps = open('/proc/self/maps').read(); "
            "print(os.environ.get('GOMP_SPINCOUNT'), 'libgomp' in maps)")
    e = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    e.update(env)
    out = subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True, check=True).stdout
    spin, loaded = out.split()
    assert spin == str(expect)
    if loaded == "True":  # the variable must already be there when libgomp is loaded, i.e. by `import sim`
        code2 = ("import os, sys; import sim; "
                 "print('libgomp' in open('/proc/self/maps').read())")
        assert subprocess.run([sys.executable, "-c", code2], env=e, capture_output=True, text=True,
                              check=True).stdout.split() == ["False"]


def test_busy_cores_warning():
    from sim.dem import busy_cores_warning

    assert busy_cores_warning(1, load=8.0, ncpu=2) is None          # serial never waits for a thread
    assert busy_cores_warning(2, load=0.2, ncpu=2) is None          # a quiet machine
    assert busy_cores_warning(2, load=1.0, ncpu=4) is None          # two cores left free
    assert "load average 1.2 on 2 cores" in busy_cores_warning(2, load=1.2, ncpu=2)
    assert "use --threads 4" in busy_cores_warning(8, load=0.0, ncpu=4)
