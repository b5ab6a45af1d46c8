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


def test_inner_list_keeps_order_and_forces_bit_for_bit():
    """The sub-list of sim.neighbors.inner_list: exactly the pairs within max(R_i + R_j, cut-off) +
    margin, in the whole list's order, history carried (and zeroed for the pairs left out); the pair
    kernel with a cut-off law over it gives the whole list's forces bit for bit, also after the particles
    moved by less than margin / 2."""
    from sim.forces.contact import CONTACT_HOOKE, hooke_params, pair_forces
    from sim.forces.nearfield import NF_YUKAWA, law_row, law_table
    from sim.neighbors import inner_list, scatter_history

    rng = np.random.default_rng(3)
    n, a = 400, 1e-7
    L = np.array([4e-6, 4e-6, 4e-6])
    pos = rng.uniform(0, 4e-6, (n, 3))
    rad = np.full(n, a)
    per = np.array([1, 1, 0], dtype=np.int64)
    cut, skin, margin = 3.6 * a, 0.5 * a, 0.2 * a
    start, nbj, shift = build_neighbor_list(pos, rad, cut, skin, np.zeros(3), L, per)
    hist = rng.normal(size=(len(nbj), 3)) * (rng.uniform(size=(len(nbj), 1)) < 0.2)
    ii = np.repeat(np.arange(n), np.diff(start))
    r = np.linalg.norm(pos[ii] - pos[nbj] + shift, axis=1)
    want = r < np.maximum(cut, 2 * a) + margin
    h_all = hist.copy()
    istart, inbj, ishift, ihist, kmap = inner_list(pos, rad, cut, margin, start, nbj, shift, h_all)
    np.testing.assert_array_equal(kmap, np.flatnonzero(want))
    np.testing.assert_array_equal(inbj, nbj[want])
    np.testing.assert_array_equal(istart, np.concatenate([[0], np.cumsum(np.bincount(ii[want], minlength=n))]))
    np.testing.assert_array_equal(ihist, hist[want])
    assert not np.any(h_all[~want]) and np.array_equal(h_all[want], hist[want])
    assert 0 < want.sum() < len(nbj)
    laws = law_table(law_row(NF_YUKAWA, [1e-2, 1.0 / (0.2 * a), cut]))
    cp = hooke_params(1e-3, 1.0, mu=0.0)
    step = rng.normal(size=(n, 3))
    moved = pos + 0.4 * margin * step / np.linalg.norm(step, axis=1)[:, None]
    for p in (pos, moved):
        out = []
        for st, nj, sh, h in ((start, nbj, shift, h_all.copy()), (istart, inbj, ishift, ihist.copy())):
            f, t, d = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(5)
            pair_forces(p, np.zeros((n, 3)), np.zeros((n, 3)), rad, np.ones(n), np.zeros(n), st, nj, sh, h, f, t,
                        CONTACT_HOOKE, cp, laws, False, 1e-9, d)
            out.append((f, d, h))
        assert np.any(out[0][0] != 0.0)
        np.testing.assert_array_equal(out[1][0], out[0][0])
        np.testing.assert_array_equal(out[1][1], out[0][1])
        back = h_all.copy()
        scatter_history(back, out[1][2], kmap)
        np.testing.assert_array_equal(back, out[0][2])
