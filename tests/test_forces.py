"""External force kernels against hand calculations."""
import math

import numpy as np
import pytest

from ptrack.constants import BOLTZMANN
from sim.forces import (add_brownian, add_drag, add_lorentz, add_stokes_drag, drag_force_scalar,
                        gravity_buoyancy_force, max_reynolds, seed_rng, stokes_gamma)

MU, RHO = 1.0e-3, 1000.0


def test_stokes_drag_hand():
    R = 1e-6
    vel = np.array([[1e-6, -2e-6, 0.5e-6]])
    vf = np.array([0.0, 1e-6, 0.0])
    out = np.zeros((1, 3))
    add_stokes_drag(vel, vf, stokes_gamma([R], MU), out)
    g = 6 * math.pi * 1e-3 * 1e-6
    np.testing.assert_allclose(out[0], g * (vf - vel[0]), rtol=1e-14)
    # the piecewise law equals Stokes below Re = 1
    out2 = np.zeros((1, 3))
    add_drag(vel, vf, np.array([R]), RHO, MU, out2)
    np.testing.assert_allclose(out2, out, rtol=1e-14)


def test_piecewise_drag_hand_re10_and_re1000():
    R = 1e-3
    from sim.electrokinetics import drag_coefficient_nb
    # the plateau is 0.5 in eq. 3.5; sim.electrokinetics nudges it (< 0.1 %) to make C_D continuous at Re = 400
    assert drag_coefficient_nb(1000.0) == pytest.approx(0.5, rel=1e-3)
    for re, cd in ((10.0, 24.0 / 10.0 ** 0.646), (1000.0, drag_coefficient_nb(1000.0))):
        speed = re * MU / (2 * R * RHO)
        fx, fy, fz = drag_force_scalar(-speed, 0.0, 0.0, R, RHO, MU)  # particle moving +x at `speed` in still fluid
        expected = 0.5 * cd * math.pi * R ** 2 * RHO * speed ** 2  # eq. 3.2
        assert fy == 0 and fz == 0
        assert fx == pytest.approx(-expected, rel=1e-9)


@pytest.mark.parametrize("re0", [1.0, 400.0])
def test_drag_continuous_across_branches(re0):
    R = 1e-4
    f = []
    for re in (re0 * (1 - 1e-9), re0 * (1 + 1e-9)):
        speed = re * MU / (2 * R * RHO)
        f.append(abs(drag_force_scalar(speed, 0.0, 0.0, R, RHO, MU)[0]))
    assert f[1] == pytest.approx(f[0], rel=1e-6)


def test_max_reynolds():
    vel = np.array([[0.0, 0.0, 1e-3], [0.0, 2e-3, 0.0]])
    re = max_reynolds(vel, np.zeros(3), np.array([1e-6, 1e-6]), RHO, MU)
    assert re == pytest.approx(2 * 1e-6 * RHO * 2e-3 / MU)


def test_gravity_with_buoyancy_hand():
    R, rho_p = 1e-6, 2200.0
    m = rho_p * 4 / 3 * math.pi * R ** 3
    f = gravity_buoyancy_force(np.array([m]), np.array([R]), RHO, (0.0, 0.0, -9.80665))
    expected = (rho_p - RHO) * 4 / 3 * math.pi * R ** 3 * -9.80665
    np.testing.assert_allclose(f[0], [0.0, 0.0, expected], rtol=1e-14)


def test_lorentz_hand():
    q = np.array([-2e-17])
    E = np.array([0.0, 0.0, -1e4])
    B = np.array([0.0, 0.5, 0.0])
    v = np.array([[1e-3, 0.0, 2e-3]])
    out = np.zeros((1, 3))
    add_lorentz(q, E, B, v, out)
    # v x B = (vy Bz - vz By, vz Bx - vx Bz, vx By - vy Bx) = (-1e-3, 0, 5e-4)
    np.testing.assert_allclose(out[0], q[0] * np.array([-1e-3, 0.0, -1e4 + 5e-4]), rtol=1e-14)


def test_brownian_variance_and_seed():
    n, dt, T = 200_000, 1e-6, 293.0
    gamma = stokes_gamma(np.full(n, 1e-7), MU)
    kT = BOLTZMANN * T
    seed_rng(5)
    out = np.zeros((n, 3))
    add_brownian(gamma, kT, dt, out)
    var = out.var(axis=0)
    expected = 2 * gamma[0] * kT / dt
    np.testing.assert_allclose(var, expected, rtol=0.02)  # 3 sigma of the sample variance is ~1 %
    assert abs(out.mean()) < 4 * math.sqrt(expected / (3 * n))
    seed_rng(5)
    again = np.zeros((n, 3))
    add_brownian(gamma, kT, dt, again)
    np.testing.assert_array_equal(out, again)


def test_brownian_draws_nothing_at_zero_temperature():
    gamma = stokes_gamma(np.full(10, 1e-7), MU)
    out = np.zeros((10, 3))
    seed_rng(9)
    add_brownian(gamma, 0.0, 1e-6, out)
    assert not out.any()
    # the generator was not advanced: the next draws equal those right after seeding
    a = np.zeros((10, 3))
    add_brownian(gamma, 1e-21, 1e-6, a)
    seed_rng(9)
    b = np.zeros((10, 3))
    add_brownian(gamma, 1e-21, 1e-6, b)
    np.testing.assert_array_equal(a, b)
