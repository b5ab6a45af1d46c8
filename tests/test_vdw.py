"""DLVO van der Waals (Hamaker) law: analytic force-distance curves and the law inside the engine."""
import numpy as np
import pytest

from sim.forces import vdw

A = 1.0e-20  # J, polystyrene in water order of magnitude


def _fd(energy, x, eps):
    return -(energy(x + eps) - energy(x - eps)) / (2 * eps)


@pytest.mark.parametrize("a1,a2", [(1e-6, 1e-6), (1e-6, 0.3e-6)])
def test_sphere_sphere_force_is_minus_the_derivative_of_hamakers_energy(a1, a2):
    p = vdw.params(A, min_gap=1e-12)
    for h in np.geomspace(1e-3, 3.0, 25) * min(a1, a2):
        r = a1 + a2 + h
        want = _fd(lambda x: vdw.pair_energy(A, x, a1, a2), r, 1e-5 * h)
        assert vdw.pair_force(p, r, a1, a2) == pytest.approx(want, rel=1e-6)
    # limits: Derjaguin at a small gap, London's r^-7 tail far away
    aeff = a1 * a2 / (a1 + a2)
    h = 1e-5 * aeff
    assert vdw.pair_force(p, a1 + a2 + h, a1, a2) == pytest.approx(-A * aeff / (6 * h * h), rel=1e-4)
    r = 1e3 * (a1 + a2)
    assert vdw.pair_force(p, r, a1, a2) == pytest.approx(-32 / 3 * A * a1**3 * a2**3 / r**7, rel=1e-4)


def test_sphere_plate_force_is_minus_the_derivative_of_hamakers_energy():
    a = 1e-6
    p = vdw.params(A, wall_A=2 * A, min_gap=1e-12)
    for h in np.geomspace(1e-3, 3.0, 25) * a:
        want = _fd(lambda x: vdw.wall_energy(2 * A, x, a), h, 1e-5 * h)
        assert vdw.wall_force(p, a + h, a) == pytest.approx(want, rel=1e-6)
    h = 1e-5 * a
    assert vdw.wall_force(p, a + h, a) == pytest.approx(-2 * A * a / (6 * h * h), rel=1e-4)


def test_retarded_force_follows_gregory_at_small_gaps_and_weakens():
    a, lam = 1e-6, 1e-7
    p = vdw.params(A, min_gap=1e-12, wavelength=lam)
    p0 = vdw.params(A, min_gap=1e-12)
    aeff = a / 2
    for h in (1e-9, 5e-9, 2e-8, 1e-7):
        want = _fd(lambda x: vdw.gregory_energy(A, x, aeff, lam), h, 1e-5 * h)
        # Gregory's is a Derjaguin (h << a) form: agreement to O(h / a)
        assert vdw.pair_force(p, 2 * a + h, a, a) == pytest.approx(want, rel=3 * h / a + 1e-6)
        assert abs(vdw.pair_force(p, 2 * a + h, a, a)) < abs(vdw.pair_force(p0, 2 * a + h, a, a))


def test_min_gap_and_cutoff():
    a = 1e-6
    p = vdw.params(A, min_gap=1e-9, cutoff_gap=0.5e-6)
    f_min = vdw.pair_force(p, 2 * a + 1e-9, a, a)
    assert vdw.pair_force(p, 2 * a - 1e-8, a, a) == f_min  # overlapping: held at the minimum gap
    assert vdw.pair_force(p, 2 * a + 0.501e-6, a, a) == 0.0
    assert vdw.wall_force(p, a + 0.6e-6, a) == 0.0
    assert vdw.pair_force(p, 2 * a + 0.4e-6, a, a) < 0.0


def _scene(**vdw_keys):
    from sim.scene import scene_from_dict

    return scene_from_dict({
        "seed": 1,
        "particles": {"count": 2, "radius": 1e-6, "density": 1050.0},
        "fluid": {"temperature": 0.0},
        "gravity": {"enabled": False},
        "domain": {"size": [2e-5, 2e-5, 2e-5]},
        "boundaries": {"bottom_wall": True},
        "time": {"final": 1e-3, "output_interval": 1e-4, "dt": 1e-6},
        "contact": {"model": "hooke", "kn": 1e-3, "restitution": 0.5},
        "vdw": vdw_keys,
    })


def test_scene_vdw_section_reaches_the_engine_for_pairs_and_the_wall():
    """A [vdw] section acts in the DEM engine with the analytic forces (no integrator knows about it)."""
    from sim.dem import system_from_scene
    from sim.state import build_state

    sc = _scene(hamaker=A, wall_hamaker=3 * A, cutoff_gap=2e-6)
    a = 1e-6
    st = build_state(sc)
    h_pair, h_wall = 0.2e-6, 0.5e-6
    st.pos = np.array([[5e-6, 5e-6, a + h_wall], [5e-6 + 2 * a + h_pair, 5e-6, a + h_wall]])
    st.vel = np.zeros((2, 3))
    system, _ = system_from_scene(sc, state=st, dt=1e-6)
    p = vdw.params(A, 3 * A, cutoff_gap=2e-6)
    fp = vdw.pair_force(p, 2 * a + h_pair, a, a)  # on particle 0 along n (from 1 to 0), i.e. -x
    fw = vdw.wall_force(p, a + h_wall, a)
    np.testing.assert_allclose(system.force[0], [-fp, 0.0, fw], rtol=1e-12)
    np.testing.assert_allclose(system.force[1], [fp, 0.0, fw], rtol=1e-12)
    assert system.force[0, 0] > 0 and system.force[0, 2] < 0  # attraction toward the partner and the wall


def test_scene_vdw_section_is_validated():
    from ptrack.errors import UserError

    with pytest.raises(UserError, match="vdw.hamaker"):
        _scene(cutoff_gap=1e-6)
    with pytest.raises(UserError, match="vdw.wavelength"):
        _scene(hamaker=A, wavelength=-1.0)
    with pytest.raises(UserError, match="vdw.colour"):
        _scene(hamaker=A, colour=1)
