"""Structure of deposits: coordination number, height profile, packing fraction,
Steinhardt q6 and the ten Wolde solid-like fraction, deposited count.

All functions take plain arrays (positions in m, radii in m) and an optional
periodic box, so they work on simulated frames (``df[df.frame == k]``) and on
measured 3D positions alike.  Neighbour search uses :mod:`sim.neighbors`
(O(N) cell lists, minimum image on periodic axes).

Definitions
-----------
* Coordination number (seed Fig. 3.16): the number of particles whose centre
  is closer than ``R_CN``; by default ``R_CN = cn_factor (R_i + R_j)`` with
  ``cn_factor = 1.1`` (a surface gap below 10 % of the two radii), or a fixed
  distance ``r_cn`` (m).
* Steinhardt ``q6(i) = sqrt(4 pi / 13 sum_m |q6m(i)|^2)`` with
  ``q6m(i) = <Y6m(r_ij)>`` over the neighbours of i.  Perfect crystals:
  fcc 0.575, hcp 0.485, bcc 0.511 (14 neighbours; 0.628 with 8), sc 0.354; a gas gives
  ~ 0.3-0.4 for the averaged value but no coherent bonds.
* ten Wolde, Ruiz-Montero and Frenkel (1996) solid-like particles: bond i-j is
  "connected" when ``Re(sum_m q6m(i) q6m(j)^*) / (|q6(i)| |q6(j)|) > 0.7``; a
  particle with at least 7 connected bonds is solid-like.  The solid-like
  fraction is the "relative order" ``N_ordered / N`` of Giera et al. (seed
  Fig. 3.24).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim.neighbors import build_neighbor_list

__all__ = ["pair_list", "coordination_numbers", "steinhardt_q6", "solid_like", "height_profile",
           "packing_fraction", "deposited_mask", "deposit_height"]


def _box(length, periodic):
    if periodic is None or length is None:
        return np.zeros(3), np.ones(3), np.zeros(3, dtype=np.int64)
    per = np.zeros(3, dtype=np.int64)
    per[: len(periodic)] = np.asarray(periodic, dtype=np.int64)
    L = np.ones(3)
    L[: len(length)] = np.asarray(length, dtype=float)
    return np.zeros(3), L, per


def pair_list(pos, radius=None, r_cut=None, cn_factor=1.1, length=None, periodic=None):
    """Pairs (i, j, dx, dy, dz, r) closer than ``r_cut`` or ``cn_factor (R_i+R_j)``.

    ``dx = x_i - x_j`` (minimum image on periodic axes).  Returns arrays
    ``i, j, d (M, 3), r``; each pair once.
    """
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    n = len(pos)
    if n == 0:
        e = np.empty(0, dtype=np.int64)
        return e, e, np.empty((0, 3)), np.empty(0)
    lo, L, per = _box(length, periodic)
    if per.any():
        pos = pos.copy()
        for a in range(3):
            if per[a]:
                pos[:, a] = np.mod(pos[:, a], L[a])
    if r_cut is not None:
        rad = np.zeros(n)
        cut = float(r_cut)
    else:
        rad = np.ascontiguousarray(radius, dtype=np.float64) * cn_factor
        cut = 0.0
    start, nbj, shift = build_neighbor_list(pos, rad, cut, 0.0, lo, L, per)
    ii = np.repeat(np.arange(n), np.diff(start))
    d = pos[ii] - pos[nbj] + shift
    r = np.sqrt((d**2).sum(1))
    lim = cut if r_cut is not None else rad[ii] + rad[nbj]
    keep = r < lim
    return ii[keep], nbj[keep], d[keep], r[keep]


def coordination_numbers(pos, radius, r_cn=None, cn_factor=1.1, length=None, periodic=None):
    """Coordination number of every particle (int array).

    Parameters
    ----------
    pos : (N, 3) array, m
    radius : (N,) array, m
    r_cn : float, optional
        Fixed neighbour distance (m); default ``cn_factor (R_i + R_j)``.
    length, periodic : optional
        Box edge lengths (m) and periodic flags for the minimum image.
    """
    i, j, _, _ = pair_list(pos, radius, r_cn, cn_factor, length, periodic)
    n = len(pos)
    return (np.bincount(i, minlength=n) + np.bincount(j, minlength=n)).astype(np.int64)


@njit(cache=True)
def _q6m(n, ii, jj, d, r):
    """Complex q6m (m = 0..6) per particle, averaged over its bonds."""
    re = np.zeros((n, 7))
    im = np.zeros((n, 7))
    cnt = np.zeros(n)
    # normalisation sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)
    norm = np.empty(7)
    for m in range(7):
        f = 1.0
        for k in range(6 - m + 1, 6 + m + 1):
            f *= k
        norm[m] = math.sqrt(13.0 / (4.0 * math.pi) / f)
    plm = np.empty(7)
    for b in range(ii.shape[0]):
        x = d[b, 2] / r[b]
        phi = math.atan2(d[b, 1], d[b, 0])
        s = math.sqrt(max(0.0, 1.0 - x * x))
        for m in range(7):
            # P_m^m
            pmm = 1.0
            for k in range(1, m + 1):
                pmm *= -(2 * k - 1) * s
            if m == 6:
                plm[m] = pmm
                continue
            pm1 = x * (2 * m + 1) * pmm
            if m == 5:
                plm[m] = pm1
                continue
            p2 = pmm
            p1 = pm1
            for l in range(m + 2, 7):
                pl = ((2 * l - 1) * x * p1 - (l + m - 1) * p2) / (l - m)
                p2 = p1
                p1 = pl
            plm[m] = p1
        for end in range(2):
            # the bond seen from j is -d: theta -> pi - theta, phi -> phi + pi,
            # i.e. Y6m(-r) = (-1)^6 Y6m(r) = Y6m(r) (even l): same contribution
            p = ii[b] if end == 0 else jj[b]
            cnt[p] += 1.0
            for m in range(7):
                a = norm[m] * plm[m]
                re[p, m] += a * math.cos(m * phi)
                im[p, m] += a * math.sin(m * phi)
    for p in range(n):
        if cnt[p] > 0:
            for m in range(7):
                re[p, m] /= cnt[p]
                im[p, m] /= cnt[p]
    return re, im, cnt


def _q6_vectors(pos, radius, r_cut, cn_factor, length, periodic):
    i, j, d, r = pair_list(pos, radius, r_cut, cn_factor, length, periodic)
    re, im, cnt = _q6m(len(pos), i, j, np.ascontiguousarray(d), r)
    return i, j, re, im, cnt


def _q6_from(re, im):
    w = np.array([1.0] + [2.0] * 6)  # m and -m contribute equally
    return np.sqrt(4.0 * np.pi / 13.0 * ((re**2 + im**2) * w).sum(1))


def steinhardt_q6(pos, radius=None, r_cut=None, cn_factor=1.2, length=None, periodic=None):
    """Steinhardt bond-orientational order q6 of every particle (NaN without neighbours).

    Neighbours: centres closer than ``r_cut`` (m) or ``cn_factor (R_i+R_j)``.
    """
    i, j, re, im, cnt = _q6_vectors(pos, radius, r_cut, cn_factor, length, periodic)
    q = _q6_from(re, im)
    q[cnt == 0] = np.nan
    return q


def solid_like(pos, radius=None, r_cut=None, cn_factor=1.2, length=None, periodic=None, threshold=0.7,
               min_bonds=7):
    """ten Wolde solid-like particles (bool array) and the per-particle connection count.

    Returns ``(solid (N,) bool, n_connected (N,) int)``.
    """
    n = len(pos)
    i, j, re, im, cnt = _q6_vectors(pos, radius, r_cut, cn_factor, length, periodic)
    w = np.array([1.0] + [2.0] * 6)
    mag = np.sqrt(((re**2 + im**2) * w).sum(1))
    mag[mag == 0] = np.inf
    dot = ((re[i] * re[j] + im[i] * im[j]) * w).sum(1) / (mag[i] * mag[j])
    conn = dot > threshold
    nconn = np.bincount(i[conn], minlength=n) + np.bincount(j[conn], minlength=n)
    return nconn >= min_bonds, nconn


def _cap_volume(r, h):
    """Volume of a spherical cap of height h (0 <= h <= 2r)."""
    h = np.clip(h, 0.0, 2 * r)
    return np.pi * h * h * (3 * r - h) / 3.0


def _slab_volume(z, r, z0, z1):
    """Volume of the sphere (centre height z, radius r) between the planes z0 < z1."""
    below1 = _cap_volume(r, z1 - (z - r))   # part below z1
    below0 = _cap_volume(r, z0 - (z - r))   # part below z0
    return below1 - below0


def height_profile(pos, radius, area, bins=50, z_max=None):
    """Solid volume fraction against height: ``(z_centres, phi)``.

    Each sphere's volume is split exactly between the slabs it crosses.
    ``area`` is the substrate area (m^2) the deposit covers (the periodic box
    area, or e.g. the footprint of an open pile).
    """
    z = np.asarray(pos, dtype=float)[:, 2]
    r = np.asarray(radius, dtype=float)
    top = float((z + r).max()) if z_max is None else float(z_max)
    edges = np.linspace(0.0, top, bins + 1)
    phi = np.empty(bins)
    for k in range(bins):
        phi[k] = _slab_volume(z, r, edges[k], edges[k + 1]).sum() / (area * (edges[k + 1] - edges[k]))
    return 0.5 * (edges[1:] + edges[:-1]), phi


def packing_fraction(pos, radius, area, z0, z1):
    """Solid volume fraction of the slab ``z0 < z < z1`` (m) over ``area`` (m^2)."""
    z = np.asarray(pos, dtype=float)[:, 2]
    r = np.asarray(radius, dtype=float)
    return float(_slab_volume(z, r, z0, z1).sum() / (area * (z1 - z0)))


def deposited_mask(pos, radius, tol=0.05, length=None, periodic=None):
    """Particles connected to the substrate (z = 0) through touching particles.

    A particle touches the substrate when ``z - R < tol R`` and touches
    another when ``r_ij < (1 + tol)(R_i + R_j)``.  Returns a bool array.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pos = np.asarray(pos, dtype=float)
    r = np.asarray(radius, dtype=float)
    n = len(pos)
    if n == 0:
        return np.zeros(0, dtype=bool)
    i, j, _, _ = pair_list(pos, r, None, 1.0 + tol, length, periodic)
    ground = np.nonzero(pos[:, 2] - r < tol * r)[0]
    rows = np.concatenate([i, ground])
    cols = np.concatenate([j, np.full(len(ground), n)])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n + 1, n + 1))
    _, lab = connected_components(g, directed=False)
    return lab[:n] == lab[n]


def deposit_height(pos, radius, quantile=0.95):
    """Height (m) of the deposit surface: a quantile of ``z + R``."""
    z = np.asarray(pos, dtype=float)[:, 2] + np.asarray(radius, dtype=float)
    return float(np.quantile(z, quantile)) if len(z) else 0.0
