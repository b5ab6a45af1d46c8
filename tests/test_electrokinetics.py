"""Tests of sim.electrokinetics against analytic limits, literature values and
an independent high-precision evaluation of Henry's function."""
import math
from decimal import Decimal, getcontext

import numpy as np
import pytest

from ptrack.constants import BOLTZMANN, VACUUM_PERMITTIVITY
from ptrack.errors import UserError
from sim import electrokinetics as ek


def henry_reference(x: float, digits: int = 60) -> float:
    """Henry's function from the closed form evaluated in 60-digit decimal arithmetic.

    e^x E1(x) from its continued fraction 1/(x + 1/(1 + 1/(x + 2/(1 + 2/(x + ...))))),
    evaluated backwards; with 60 digits the catastrophic cancellation of the
    closed form at large x is harmless. Independent of scipy and of the
    stable rearrangements used in the module.
    """
    getcontext().prec = digits
    X = Decimal(repr(x))
    t = Decimal(0)
    for k in range(6000, 0, -1):
        t = Decimal(k) / (1 + Decimal(k) / (X + t))
    s = 1 / (X + t)
    f = (96 + 6 * X ** 2 - 10 * X ** 3 - X ** 4 + X ** 5 + X ** 4 * (12 - X ** 2) * s) / 96
    return float(f)


# ---------------------------------------------------------------- Henry's function
def test_henry_limits_and_monotone():
    x = np.geomspace(1e-8, 1e9, 3000)
    f = ek.henry_function(x)
    assert f[0] == pytest.approx(1.0, abs=1e-12)
    assert f[-1] == pytest.approx(1.5, abs=1e-8)
    assert np.all(np.diff(f) >= 0)
    assert np.all(np.diff(f[x > 1e-6]) > 0)         # below, 1 + x^2/16 rounds to 1
    assert ek.henry_function(0.0) == 1.0


@pytest.mark.parametrize("x", [0.3, 1.0, 2.0, 4.0, 5.0, 5.5, 12.0, 60.0, 199.0, 250.0, 1000.0])
def test_henry_matches_high_precision_reference(x):
    assert ek.henry_function(x) == pytest.approx(henry_reference(x), rel=1e-13)


def test_henry_literature_values():
    # Ohshima (1994) tabulates Henry's function; in the [1, 3/2] convention f(ka=1) = 1.027
    assert round(ek.henry_function(1.0), 3) == 1.027
    # Ohshima's (1994) simple approximation 1 + 1/(2 (1 + 2.5/(ka (1 + 2 e^-ka)))^3), stated
    # to be within ~1 % of the exact function, is an independent check over the whole range
    x = np.geomspace(1e-3, 1e4, 500)
    ohshima = 1 + 1 / (2 * (1 + 2.5 / (x * (1 + 2 * np.exp(-x)))) ** 3)
    assert np.max(np.abs(ohshima / ek.henry_function(x) - 1)) < 0.01
    # large-ka expansion 3/2 - 9/(2 ka) + 75/(2 ka^2) - 330/ka^3
    assert ek.henry_function(1e4) == pytest.approx(1.5 - 4.5e-4 + 37.5e-8 - 330e-12, rel=1e-13)


def test_swan_furst_differs_by_0p15_percent_at_ka_2():
    rel = ek.henry_function_swan_furst(2.0) / ek.henry_function(2.0) - 1
    assert 0.0014 < rel < 0.0015
    assert ek.henry_function_swan_furst(2.0) == pytest.approx(64 / 60)
    x = np.geomspace(1e-4, 1e6, 2000)
    err = np.abs(ek.henry_function_swan_furst(x) / ek.henry_function(x) - 1)
    assert err.max() < 0.0015            # seed says 0.1 %; the true maximum is 0.147 % near ka = 2


# ---------------------------------------------------------------- Debye, charge, velocity
def test_debye_length_1mM_water():
    # textbook 0.304 nm / sqrt(I in mol/L) for water at 25 C -> 9.6 nm at 1 mM
    lam = ek.debye_length(1.0, eps_r=78.5, temperature=298.15)
    assert lam == pytest.approx(9.6e-9, rel=0.01)
    np.testing.assert_allclose(ek.debye_length(np.array([1.0, 100.0])), [lam, lam / 10], rtol=1e-12)
    with pytest.raises(UserError):
        ek.debye_length(-1.0)


@pytest.mark.parametrize("henry", ["exact", "swan_furst"])
def test_stokes_terminal_velocity_equals_henry_velocity(henry):
    R = np.array([10e-9, 100e-9, 1e-6])
    lam = R / np.array([0.05, 2.0, 300.0])
    mu, eps, zeta, E = 1e-3, 80.0, -0.05, 1e4
    q = ek.colloid_charge(zeta, R, lam, eps, henry=henry)
    v_stokes = q * E / (6 * math.pi * mu * R)
    np.testing.assert_allclose(v_stokes, ek.henry_velocity(E, zeta, R, lam, eps, mu, henry=henry), rtol=1e-14)
    # the charge is 4 pi eps eps0 zeta R f (Giera's eq. 3.33 is that, written out)
    f = ek.henry_function(R / lam) if henry == "exact" else ek.henry_function_swan_furst(R / lam)
    np.testing.assert_allclose(q, 4 * math.pi * eps * VACUUM_PERMITTIVITY * zeta * R * f, rtol=1e-14)
    assert np.all(q < 0)


def test_peclet_number():
    R, lam, eps, zeta, E, T, mu = 100e-9, 50e-9, 80.0, -0.05, 1e4, 293.15, 1e-3
    vh = ek.henry_velocity(E, zeta, R, lam, eps, mu)
    d_se = BOLTZMANN * T / (6 * math.pi * mu * R)
    pe = ek.peclet_number(E, zeta, R, lam, eps, T)
    assert pe == pytest.approx(abs(vh) * R / d_se, rel=1e-13)
    # the seed's eq. 3.37 (6 pi) is 1.5x this
    seed = 6 * math.pi * R ** 2 * abs(E * zeta) * eps * VACUUM_PERMITTIVITY * ek.henry_function(R / lam) / (BOLTZMANN * T)
    assert seed / pe == pytest.approx(1.5)


def test_reynolds_number():
    assert ek.reynolds_number(-0.1, 1e-6, 1000.0, 1e-3) == pytest.approx(0.2)
    np.testing.assert_allclose(ek.reynolds_number([1, 2], 1e-6, 1000.0, 1e-3), [2.0, 4.0])


# ---------------------------------------------------------------- drag law
def test_drag_coefficient_branches():
    re = np.array([1e-3, 0.5, 1.0, 10.0, 100.0, 1e3, 1e5, 5e5, 1e6, 1e7])
    cd = ek.drag_coefficient(re)
    np.testing.assert_allclose(cd[:3], 24 / re[:3], rtol=1e-15)
    np.testing.assert_allclose(cd[3:5], 24 / re[3:5] ** 0.646, rtol=1e-15)
    np.testing.assert_allclose(cd[5:7], 0.5, rtol=1e-3)        # seed plateau 0.5 (here 0.50036, continuous)
    np.testing.assert_allclose(cd[7:9], 0.000366 * re[7:9] ** 0.4275, rtol=1e-15)
    assert cd[9] == pytest.approx(0.18, rel=5e-3)             # seed 0.18 (here 0.1808, continuous)
    for r in re:
        assert ek.drag_coefficient_nb(r) == ek.drag_coefficient(r)


@pytest.mark.parametrize("re0", [1.0, 400.0, 2e5, 3e5, 2e6])
def test_drag_law_is_continuous(re0):
    lo, hi = re0 * (1 - 1e-12), re0 * (1 + 1e-12)
    assert ek.drag_coefficient(hi) * hi == pytest.approx(ek.drag_coefficient(lo) * lo, rel=1e-9)


def test_drag_force_is_stokes_at_low_re():
    R, rho, mu = 1e-6, 1000.0, 1e-3
    v = 1e-4
    assert ek.drag_force_nb(v, R, rho, mu) == pytest.approx(6 * math.pi * mu * R * v, rel=1e-14)
    assert ek.drag_force_nb(0.0, R, rho, mu) == 0.0
    # 1/2 C_D pi R^2 rho v^2 above Re = 1
    v = 5.0
    re = 2 * R * rho * v / mu
    assert ek.drag_force(v, R, rho, mu) == pytest.approx(0.5 * 24 / re ** 0.646 * math.pi * R ** 2 * rho * v ** 2)


# ---------------------------------------------------------------- force balance
def test_steady_state_equals_stokes_and_henry_at_low_re():
    R = np.array([10e-9, 100e-9, 1e-6])
    lam = R / 2
    mu, eps, zeta, E = 1e-3, 80.0, -0.05, np.array([10.0, 1e3, 1e4])
    q = ek.colloid_charge(zeta, R, lam, eps)
    v, re, n = ek.steady_state_velocity(q * E, R, 1000.0, mu, return_info=True)
    assert np.all(re < 1)
    np.testing.assert_allclose(v, ek.henry_velocity(E, zeta, R, lam, eps, mu), rtol=1e-12)
    np.testing.assert_allclose(v, q * E / (6 * math.pi * mu * R), rtol=1e-12)
    assert np.all(v < 0)


def test_steady_state_reproduces_seed_outliers():
    # seed electrophoresis study: R = 1 um, mu = 1e-4 Pa s, E = 1e6 V/m, zeta = -0.05 V,
    # R/lambda = 2, water density; the seed reports 21.5 % (eps 40) and 34.5 % (eps 80)
    # below the Henry velocity: the piecewise drag law once Re > 1.
    R, mu, E, zeta = 1e-6, 1e-4, 1e6, -0.05
    deficits = []
    for eps in (40.0, 80.0):
        q = ek.colloid_charge(zeta, R, R / 2, eps)
        v, re, n = ek.steady_state_velocity(q * E, R, 1000.0, mu, return_info=True)
        assert 1 < re < 400 and n > 1
        # drag balances the force at the solution
        assert ek.drag_force(abs(v), R, 1000.0, mu) == pytest.approx(abs(q * E), rel=1e-11)
        deficits.append(1 - v / ek.henry_velocity(E, zeta, R, R / 2, eps, mu))
    assert deficits[0] == pytest.approx(0.215, abs=0.002)
    assert deficits[1] == pytest.approx(0.345, abs=0.002)


def test_steady_state_all_regimes_balance_force():
    F = np.geomspace(1e-18, 1e2, 25)
    R, rho, mu = 1e-3, 1.2, 1.8e-5         # millimetre grain in air: Re from 1e-9 to 1e7
    v, re, n = ek.steady_state_velocity(F, R, rho, mu, return_info=True)
    np.testing.assert_allclose(ek.drag_force(v, R, rho, mu), F, rtol=1e-10)
    assert re.min() < 1e-6 and re.max() > 1e6


def test_steady_state_lowest_root_across_drag_crisis():
    # in 2e5 < Re < 3e5 the drag falls with speed, so a force can balance at three speeds;
    # the solver returns the lowest (reached accelerating from rest), and drag balances there
    R, rho, mu = 0.1, 1.2, 1.8e-5
    re_true = np.array([1.9e5, 2.2e5, 2.6e5, 2.95e5, 3.5e5, 6e5])
    v_true = re_true * mu / (2 * R * rho)
    F = ek.drag_force(v_true, R, rho, mu)
    v, re, n = ek.steady_state_velocity(F, R, rho, mu, return_info=True)
    np.testing.assert_allclose(ek.drag_force(v, R, rho, mu), F, rtol=1e-10)
    assert np.all(re <= re_true * (1 + 1e-9))
    for vi, Fi in zip(v, F):        # no slower speed balances the force
        slower = np.linspace(0, vi, 2001)[1:-1]
        assert np.all(ek.drag_force(slower, R, rho, mu) < Fi)


def test_steady_state_nonconvergence_is_an_error():
    R, rho, mu = 1e-6, 1000.0, 1e-4
    with pytest.raises(UserError, match="did not converge"):
        ek.steady_state_velocity(2.4e-10, R, rho, mu, max_iter=2)
    assert ek.steady_state_velocity(0.0, R, rho, mu) == 0.0


def test_buoyant_weight():
    assert ek.buoyant_weight(1e-6, 2000.0, 1000.0) == pytest.approx(1000 * 4 / 3 * math.pi * 1e-18 * 9.80665)


def test_shape_mismatch_is_a_user_error():
    with pytest.raises(UserError, match="broadcast"):
        ek.colloid_charge(-0.05, np.array([1e-7, 2e-7]), np.array([1e-8, 2e-8, 3e-8]), 80.0)
    with pytest.raises(UserError, match="broadcast"):
        ek.steady_state_velocity(np.ones(3), np.ones(2) * 1e-6, 1000.0, 1e-3)
