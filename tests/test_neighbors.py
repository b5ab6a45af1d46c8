"""Neighbour lists against brute force; history carried across rebuilds; wrapping."""
import numpy as np
import pytest

from ptrack.errors import UserError
from sim.neighbors import (NeighborList, brute_force_pairs, build_neighbor_list, carry_history, needs_rebuild,
                           wrap_positions)


def _pairs(start, nbj):
    i = np.repeat(np.arange(len(start) - 1), np.diff(start))
    return set(zip(i.tolist(), nbj.tolist()))


@pytest.mark.parametrize("periodic", [(0, 0, 0), (1, 1, 0), (1, 1, 1)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_brute_force(periodic, seed):
    rng = np.random.default_rng(seed)
    n = 400
    L = np.array([3.0, 2.5, 2.0])
    pos = rng.random((n, 3)) * L
    rad = 0.05 + 0.05 * rng.random(n)
    cutoff, skin = (0.25 if seed == 1 else 0.0), 0.03
    start, nbj, shift = build_neighbor_list(pos, rad, cutoff, skin, np.zeros(3), L, np.array(periodic))
    got = _pairs(start, nbj)
    want = brute_force_pairs(pos, rad, cutoff, skin, L, periodic)
    assert got == want
    # each pair once, and the stored image shift is the minimum image
    assert len(got) == len(nbj)
    i = np.repeat(np.arange(n), np.diff(start))
    d = pos[i] - pos[nbj] + shift
    r = np.linalg.norm(d, axis=1)
    assert np.all(r < np.maximum(rad[i] + rad[nbj], cutoff) + skin + 1e-12)


def test_open_axes_with_far_outlier_stays_linear_memory():
    rng = np.random.default_rng(3)
    pos = rng.random((300, 3))
    pos[0] = [1e6, -1e6, 5e5]  # a particle that flew away must not allocate a huge grid
    rad = np.full(300, 0.02)
    start, nbj, _ = build_neighbor_list(pos, rad, 0.0, 0.01)
    assert _pairs(start, nbj) == brute_force_pairs(pos, rad, 0.0, 0.01)


def test_small_periodic_box_rejected():
    pos = np.zeros((2, 3))
    with pytest.raises(UserError, match="periodic box"):
        build_neighbor_list(pos, np.full(2, 0.5), 0.0, 0.1, np.zeros(3), np.array([1.5, 5, 5]), np.array([1, 0, 0]))


def test_history_carried_across_rebuild():
    rng = np.random.default_rng(4)
    L = np.array([2.0, 2.0, 2.0])
    pos = rng.random((200, 3)) * L
    rad = np.full(200, 0.08)
    nl = NeighborList(0.0, 0.05, np.zeros(3), L, np.array([1, 1, 0]), n_history=3)
    nl.build(pos, rad)
    nl.hist = rng.random(nl.hist.shape)
    i = np.repeat(np.arange(200), np.diff(nl.start))
    before = {(a, b): h.copy() for a, b, h in zip(i, nl.nbj, nl.hist)}
    pos2 = pos + 0.01 * rng.standard_normal(pos.shape)
    nl.build(pos2, rad)
    i2 = np.repeat(np.arange(200), np.diff(nl.start))
    kept = 0
    for a, b, h in zip(i2, nl.nbj, nl.hist):
        if (a, b) in before:
            np.testing.assert_array_equal(h, before[(a, b)])
            kept += 1
        else:
            assert not h.any()
    assert kept > 0


def test_wrap_keeps_unwrapped_and_rebuild_criterion():
    rng = np.random.default_rng(5)
    L = np.array([1.0, 2.0, 3.0])
    pos = rng.uniform(-5, 5, (50, 3))
    orig = pos.copy()
    image = np.zeros((50, 3))
    wrap_positions(pos, image, np.zeros(3), L, np.array([1, 1, 0]))
    np.testing.assert_allclose(pos + image * L, orig, atol=1e-12)
    assert np.all((pos[:, :2] >= 0) & (pos[:, :2] < L[:2]))
    np.testing.assert_array_equal(pos[:, 2], orig[:, 2])
    ref = pos.copy()
    moved = pos.copy()
    moved[7, 0] += 0.049
    assert not needs_rebuild(moved, ref, 0.1)
    moved[7, 0] += 0.002
    assert needs_rebuild(moved, ref, 0.1)


def test_history_carried_across_a_reordering_changes_sign_with_the_roles():
    """After a re-ordering a pair can be stored under its other particle (the half list keeps j > i);
    its tangential spring is the first particle's relative displacement, so it changes sign, and the
    contact law then gives the same forces (swapped) as before."""
    from sim.forces.contact import CONTACT_HOOKE, contact_force_pair, hooke_params
    from sim.neighbors import carry_history_permuted, cell_order

    h = np.array([[1.5e-4, -0.7e-4, 0.2e-4]])
    start = np.array([0, 1, 1, 1], dtype=np.int64)  # old slots: pair (0, 2), particle 1 alone
    nbj = np.array([2], dtype=np.int64)
    perm = np.array([2, 1, 0], dtype=np.int64)      # new slot 0 holds old slot 2, new 2 holds old 0
    new = carry_history_permuted(start, nbj, h, start, nbj, perm)  # new list: pair (0, 2) in new slots
    np.testing.assert_array_equal(new, -h)
    same = carry_history_permuted(start, nbj, h, start, nbj, np.array([0, 1, 2], dtype=np.int64))
    np.testing.assert_array_equal(same, h)
    # the law with the roles swapped and the spring negated: the same forces on the same bodies
    cp = hooke_params(1e6, 0.5, mu=0.4)
    xi, xj = [0.0, 0.0, 0.0], [0.099, 0.003, 0.0]
    vi, vj, wi, wj = [0.1, 0.3, -0.2], [-0.2, 0.0, 0.1], [1.0, -2.0, 0.5], [0.0, 3.0, 1.0]
    fi, fj, ti, tj, hij = contact_force_pair(CONTACT_HOOKE, cp, xi, xj, 0.05, 0.05, 1.0, 1.2, vi, vj, wi, wj,
                                             hist=h[0])
    gj, gi, uj, ui, hji = contact_force_pair(CONTACT_HOOKE, cp, xj, xi, 0.05, 0.05, 1.2, 1.0, vj, vi, wj, wi,
                                             hist=-h[0])
    np.testing.assert_allclose(gi, fi, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(gj, fj, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(ui, ti, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(hji, -hij, rtol=1e-12, atol=1e-18)
    # the cell order depends on the positions and the ids, not on the slots they are in
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 1, (50, 3))
    rad = np.full(50, 0.04)
    lo, L, per = np.zeros(3), np.ones(3), np.array([1, 1, 0], dtype=np.int64)
    p0 = cell_order(pos, rad, 0.0, 0.01, lo, L, per, np.arange(50, dtype=np.int64))
    shuffle = rng.permutation(50)
    p1 = cell_order(pos[shuffle], rad, 0.0, 0.01, lo, L, per, shuffle.astype(np.int64))
    np.testing.assert_array_equal(shuffle[p1], p0)
