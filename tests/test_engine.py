"""The engine's overdamped stepper (sim.dem OVERDAMPED): Brownian dynamics that takes pair forces."""
import math

import numpy as np
import pytest

from sim.dem import OVERDAMPED, DEMSystem
from sim.forces.contact import CONTACT_HOOKE, CONTACT_NONE, hooke_params
from sim.forces.nearfield import NF_YUKAWA, law_row, law_table, nearfield_pair

KT = 4.0e-21
A = 1.0e-7
GAMMA = 6 * math.pi * 1e-3 * A
D = KT / GAMMA


def _system(pos, kT=KT, fconst=None, laws=None, model=CONTACT_NONE, cp=None, **kw):
    n = len(pos)
    return DEMSystem(pos, np.zeros((n, 3)), np.full(n, A), np.full(n, 1e-18), None, model=model, cp=cp,
                     pair_laws=laws, rotation=False, box_length=(1e-4, 1e-4, 1e-4), periodic=(0, 0, 0),
                     fconst=fconst, gamma=np.full(n, GAMMA), extp=np.array([0, 0, 0, 0, 0, kT, 0, 0, 0.0]),
                     cutoff=6 * A, skin=0.5 * A, seed=7, integrator=OVERDAMPED, max_overlap=np.inf, **kw)


def test_free_diffusion_coefficient():
    rng = np.random.default_rng(0)
    pos = 5e-5 + rng.uniform(-2e-5, 2e-5, (3000, 3))
    s = _system(pos, dt=1e-5)
    x0 = s.unwrapped.copy()
    s.run(40)
    msd = np.mean(np.sum((s.unwrapped - x0) ** 2, axis=1))
    # 3 N = 9000 squared Gaussian increments: relative SE sqrt(2 / 9000) = 1.5 %
    assert msd / (6 * D * s.t) == pytest.approx(1.0, abs=0.06)
    assert s.t == pytest.approx(40 * 1e-5)


def test_pair_force_drift_at_zero_temperature():
    laws = law_table(law_row(NF_YUKAWA, [1e-11, 1e8, 6 * A]))
    r = 2 * A + 2e-8
    s = _system(np.array([[5e-5, 5e-5, 5e-5], [5e-5 + r, 5e-5, 5e-5]]), kT=0.0, laws=laws, dt=1e-9)
    f = nearfield_pair(NF_YUKAWA, [1e-11, 1e8, 6 * A], r, A, A, 0.0, 0.0)  # repulsive, > 0
    assert f > 0
    s.run(1)
    np.testing.assert_allclose(s.pos[0] - [5e-5, 5e-5, 5e-5], [-f / GAMMA * 1e-9, 0, 0], rtol=1e-9)
    np.testing.assert_allclose(s.vel[1], [f / GAMMA, 0, 0], rtol=1e-12)


def test_step_is_shortened_so_no_drift_step_exceeds_the_limit():
    f = np.array([0.0, 0.0, -1e-12])
    s = _system(np.array([[5e-5, 5e-5, 5e-5]]), kT=0.0, fconst=f, dt=1.0, max_step=0.01 * A)
    s.run(3)
    assert s.pos[0, 2] == pytest.approx(5e-5 - 0.03 * A, rel=1e-12)
    assert s.t == pytest.approx(3 * 0.01 * A * GAMMA / 1e-12, rel=1e-12)


@pytest.mark.parametrize("substrate", ["stick", "reflect"])
def test_substrate_sticks_or_reflects(substrate):
    rng = np.random.default_rng(1)
    pos = np.column_stack([rng.uniform(1e-5, 9e-5, (200, 2)), rng.uniform(2 * A, 6 * A, 200)])
    fz = -20 * KT / A  # Pe = 20: crosses the 6 a of the start in 0.3 a^2 / D = 1.4 ms
    s = _system(pos, fconst=np.array([0.0, 0.0, fz]), dt=1e-6, substrate=substrate, max_step=0.05 * A)
    s.run(20000, until=5e-3)
    assert s.t == pytest.approx(5e-3, rel=1e-3) and s.step < 20000
    if substrate == "stick":
        assert s.frozen.all() and np.all(s.pos[:, 2] == A)
    else:
        assert not s.frozen.any() and np.all(s.pos[:, 2] >= A)
        assert np.mean(s.pos[:, 2] - A) < 0.2 * A  # the drift holds them near the substrate


def test_split_run_with_pair_forces_is_bit_identical():
    rng = np.random.default_rng(2)
    pos = np.column_stack([rng.uniform(3e-5, 7e-5, (300, 2)), rng.uniform(2 * A, 2e-5, 300)])
    kw = dict(fconst=np.array([0.0, 0.0, -5 * KT / A]), laws=law_table(law_row(NF_YUKAWA, [1e-12, 3e7, 4 * A])),
              model=CONTACT_HOOKE, cp=hooke_params(5e3 * KT / A**2, 1.0), dt=2e-5, substrate="reflect",
              max_step=0.01 * A)
    a = _system(pos, **kw)
    b = _system(pos, **kw)
    a.run(600)
    for k in (250, 1, 349):
        b.run(k)
    np.testing.assert_array_equal(a.pos, b.pos)
    assert a.t == b.t  # the clock counts absolute time step by step, whatever the split


def test_run_until_a_time_ends_at_the_same_step_however_it_is_split():
    # the study stops each deposit at t_end, in kernel calls sized by wall time: the stop step must not
    # depend on where the calls were cut (the clock used to be the sum of per-call sums)
    rng = np.random.default_rng(3)
    pos = np.column_stack([rng.uniform(3e-5, 7e-5, (200, 2)), rng.uniform(2 * A, 1e-5, 200)])
    kw = dict(fconst=np.array([0.0, 0.0, -5 * KT / A]), laws=law_table(law_row(NF_YUKAWA, [1e-12, 3e7, 4 * A])),
              dt=2e-5, substrate="reflect", max_step=0.01 * A)
    a, b = _system(pos, **kw), _system(pos, **kw)
    a.run(400)
    t_end = a.t * 0.999  # the clock as the split run will reach it, within the last step
    a = _system(pos, **kw)
    a.run(10**6, until=t_end)
    for k in (37, 101, 5):
        b.run(k, until=t_end)
    b.run(10**6, until=t_end)
    assert (a.step, a.t) == (b.step, b.t)
    np.testing.assert_array_equal(a.pos, b.pos)
