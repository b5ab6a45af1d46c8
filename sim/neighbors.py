"""Cell lists and Verlet (neighbour) lists with a skin, open or periodic sides.

The neighbour list is a *half* list in compressed-row form: for particle ``i``
the entries ``start[i] .. start[i+1]-1`` hold its partners ``j > i`` (each pair
appears exactly once, so a pair force is computed once and applied as +F / -F,
which keeps Newton's third law to round-off).  Each entry also stores the
periodic image ``shift`` (m) to add to ``x_i - x_j``: positions are wrapped into
the box only when the list is rebuilt, so between rebuilds the image of every
pair is fixed and the pair kernels need no minimum-image branch.

Per-entry contact history (the tangential spring of Hooke/Coulomb friction, a
bond flag, ...) lives in an ``(M, H)`` float64 array aligned with the list; on a
rebuild :func:`carry_history` copies it to the new entries of the same pairs,
so history survives rebuilds.

Building costs O(N): particles are binned into cells at least one cut-off wide
(counting sort) and each particle only looks at the 27 surrounding cells.  The
list is rebuilt when the largest displacement since the last build exceeds half
the skin (:func:`needs_rebuild`), which guarantees no pair inside the cut-off
is ever missing.

All lengths are in metres.  Boxes: ``lo`` (3,) lower corner, ``length`` (3,)
edge lengths, ``periodic`` (3,) int flags; only periodic axes use ``lo`` and
``length`` (open axes are binned over the particles' current extent).
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "build_neighbor_list",
    "carry_history",
    "carry_history_permuted",
    "cell_order",
    "permute_rows",
    "needs_rebuild",
    "inner_list",
    "scatter_history",
    "wrap_positions",
    "brute_force_pairs",
    "NeighborList",
]

_MAX_CELLS_PER_PARTICLE = 8


@njit(cache=True)
def wrap_positions(pos, image, lo, length, periodic):
    """Wrap positions into the periodic box in place, counting image crossings.

    ``unwrapped = pos + image * length`` is preserved.
    """
    n = pos.shape[0]
    for d in range(3):
        if periodic[d] == 0:
            continue
        L = length[d]
        for i in range(n):
            s = np.floor((pos[i, d] - lo[d]) / L)
            if s != 0.0:
                pos[i, d] -= s * L
                image[i, d] += s
                # guard against round-off putting a particle exactly at lo+L
                if pos[i, d] >= lo[d] + L:
                    pos[i, d] -= L
                    image[i, d] += 1.0


@njit(cache=True)
def _bin_particles(pos, cell_size, lo, length, periodic):
    """Counting sort of particles into cells; returns grid info and order."""
    n = pos.shape[0]
    origin = np.empty(3)
    ncell = np.empty(3, dtype=np.int64)
    csize = np.empty(3)
    for d in range(3):
        if periodic[d] != 0:
            origin[d] = lo[d]
            nc = int(np.floor(length[d] / cell_size))
            if nc < 1:
                nc = 1
            ncell[d] = nc
            csize[d] = length[d] / nc
        else:
            mn = pos[0, d]
            mx = pos[0, d]
            for i in range(n):
                v = pos[i, d]
                if v < mn:
                    mn = v
                if v > mx:
                    mx = v
            origin[d] = mn
            ncf = np.floor((mx - mn) / cell_size) + 1.0
            if ncf > 4.0e6:
                # cap before converting to int (far outliers); coarsened below
                csize[d] = (mx - mn) / 4.0e6 * 1.0000001
                ncf = 4.0e6
            ncell[d] = int(ncf)
            if ncf < 4.0e6:
                csize[d] = cell_size
    # keep memory O(N) when a few particles fly far away on an open axis
    limit = _MAX_CELLS_PER_PARTICLE * n + 64
    totf = float(ncell[0]) * float(ncell[1]) * float(ncell[2])
    while totf > limit:
        coarsened = False
        for d in range(3):
            if periodic[d] == 0 and ncell[d] > 1:
                csize[d] *= 2.0
                ncell[d] = (ncell[d] + 1) // 2
                coarsened = True
        totf = float(ncell[0]) * float(ncell[1]) * float(ncell[2])
        if not coarsened:
            break
    total = ncell[0] * ncell[1] * ncell[2]
    cell_of = np.empty(n, dtype=np.int64)
    counts = np.zeros(total + 1, dtype=np.int64)
    for i in range(n):
        c = 0
        for d in range(3):
            k = int(np.floor((pos[i, d] - origin[d]) / csize[d]))
            if periodic[d] != 0:
                k = k % ncell[d]
            else:
                if k < 0:
                    k = 0
                elif k >= ncell[d]:
                    k = ncell[d] - 1
            c = c * ncell[d] + k
        cell_of[i] = c
        counts[c + 1] += 1
    for c in range(total):
        counts[c + 1] += counts[c]
    fill = counts[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = cell_of[i]
        order[fill[c]] = i
        fill[c] += 1
    return ncell, cell_of, counts, order


@njit(cache=True)
def _scan(pos, radius, cutoff, skin, lo, length, periodic, ncell, cell_of, cell_start,
          order, start, nbj, shift, fill):
    """One pass over candidate pairs: count (fill=False) or store (fill=True)."""
    n = pos.shape[0]
    nx, ny, nz = ncell[0], ncell[1], ncell[2]
    # number of distinct neighbour-cell offsets per axis (avoid double visits)
    lohi = np.empty((3, 2), dtype=np.int64)
    for d in range(3):
        if ncell[d] >= 3 or periodic[d] == 0:
            lohi[d, 0] = -1
            lohi[d, 1] = 1
        elif ncell[d] == 2:
            lohi[d, 0] = 0
            lohi[d, 1] = 1
        else:
            lohi[d, 0] = 0
            lohi[d, 1] = 0
    count_total = 0
    for i in range(n):
        if fill:
            k = start[i]
        else:
            k = 0
        c = cell_of[i]
        cz = c % nz
        cy = (c // nz) % ny
        cx = c // (ny * nz)
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        ri = radius[i]
        for ox in range(lohi[0, 0], lohi[0, 1] + 1):
            ax = cx + ox
            if periodic[0] != 0:
                ax = ax % nx
            elif ax < 0 or ax >= nx:
                continue
            for oy in range(lohi[1, 0], lohi[1, 1] + 1):
                ay = cy + oy
                if periodic[1] != 0:
                    ay = ay % ny
                elif ay < 0 or ay >= ny:
                    continue
                for oz in range(lohi[2, 0], lohi[2, 1] + 1):
                    az = cz + oz
                    if periodic[2] != 0:
                        az = az % nz
                    elif az < 0 or az >= nz:
                        continue
                    cc = (ax * ny + ay) * nz + az
                    for q in range(cell_start[cc], cell_start[cc + 1]):
                        j = order[q]
                        if j <= i:
                            continue
                        dx = xi - pos[j, 0]
                        dy = yi - pos[j, 1]
                        dz = zi - pos[j, 2]
                        sx = 0.0
                        sy = 0.0
                        sz = 0.0
                        if periodic[0] != 0:
                            sx = -length[0] * np.rint(dx / length[0])
                            dx += sx
                        if periodic[1] != 0:
                            sy = -length[1] * np.rint(dy / length[1])
                            dy += sy
                        if periodic[2] != 0:
                            sz = -length[2] * np.rint(dz / length[2])
                            dz += sz
                        rc = ri + radius[j]
                        if cutoff > rc:
                            rc = cutoff
                        rc += skin
                        if dx * dx + dy * dy + dz * dz < rc * rc:
                            if fill:
                                nbj[k] = j
                                shift[k, 0] = sx
                                shift[k, 1] = sy
                                shift[k, 2] = sz
                                k += 1
                            else:
                                k += 1
        if not fill:
            start[i + 1] = k
            count_total += k
    return count_total


@njit(cache=True)
def _cell_size(radius, cutoff, skin):
    """Cell edge of the neighbour grid (m): the largest contact distance 2 max(radius) or the pair cut-off, plus the skin."""
    rmax = 0.0
    for i in range(radius.shape[0]):
        if radius[i] > rmax:
            rmax = radius[i]
    return max(2.0 * rmax, cutoff) + skin


@njit(cache=True)
def _build(pos, radius, cutoff, skin, lo, length, periodic):
    n = pos.shape[0]
    cell_size = _cell_size(radius, cutoff, skin)
    ncell, cell_of, cell_start, order = _bin_particles(pos, cell_size, lo, length, periodic)
    start = np.zeros(n + 1, dtype=np.int64)
    dummy_j = np.empty(0, dtype=np.int64)
    dummy_s = np.empty((0, 3))
    _scan(pos, radius, cutoff, skin, lo, length, periodic, ncell, cell_of, cell_start,
          order, start, dummy_j, dummy_s, np.bool_(False))  # np.bool_: one compiled _scan for both passes
    for i in range(n):
        start[i + 1] += start[i]
    m = start[n]
    nbj = np.empty(m, dtype=np.int64)
    shift = np.zeros((m, 3))
    _scan(pos, radius, cutoff, skin, lo, length, periodic, ncell, cell_of, cell_start,
          order, start, nbj, shift, np.bool_(True))
    return start, nbj, shift


def build_neighbor_list(pos, radius, cutoff=0.0, skin=0.0, lo=None, length=None, periodic=None):
    """Build a half Verlet list.

    Parameters
    ----------
    pos : (N, 3) float64 array
        Particle centres (m).  On periodic axes they should be wrapped into the
        box (:func:`wrap_positions`); they are binned modulo the box anyway.
    radius : (N,) float64 array
        Radii (m).  A pair is listed when its centre distance is below
        ``max(R_i + R_j, cutoff) + skin``.
    cutoff : float
        Centre-to-centre range of non-contact pair forces (m); 0 for contact only.
    skin : float
        Verlet skin (m).
    lo, length : (3,) arrays, optional
        Box lower corner and edge lengths (m); used on periodic axes only, which
        must be at least ``2 * (max(2 R_max, cutoff) + skin)`` long.
    periodic : (3,) int array, optional
        1 for a periodic axis.

    Returns
    -------
    start : (N+1,) int64, nbj : (M,) int64, shift : (M, 3) float64
        Compressed-row half list; add ``shift[k]`` to ``x_i - x_j``.
    """
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    radius = np.ascontiguousarray(radius, dtype=np.float64)
    lo = np.zeros(3) if lo is None else np.asarray(lo, dtype=np.float64)
    length = np.ones(3) if length is None else np.asarray(length, dtype=np.float64)
    periodic = np.zeros(3, dtype=np.int64) if periodic is None else np.asarray(periodic, dtype=np.int64)
    if len(pos) == 0:
        return np.zeros(1, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 3))
    rng = 2.0 * float(radius.max()) if len(radius) else 0.0
    reach = max(rng, float(cutoff)) + float(skin)
    for d in range(3):
        if periodic[d] and length[d] < 2.0 * reach:
            from ptrack.errors import UserError

            raise UserError(
                f"periodic box edge {length[d]:.4g} m along axis {'xyz'[d]} is shorter than twice the "
                f"interaction range {reach:.4g} m",
                "make the box larger or the cutoff/skin smaller",
            )
    return _build(pos, radius, float(cutoff), float(skin), lo, length, periodic)


@njit(cache=True)
def carry_history(old_start, old_nbj, old_hist, new_start, new_nbj):
    """Copy per-entry history from an old list to a new one (same pairs).

    Returns the new ``(M_new, H)`` history array; pairs absent from the old list
    start with zeros.
    """
    n = new_start.shape[0] - 1
    h = old_hist.shape[1]
    new_hist = np.zeros((new_nbj.shape[0], h))
    if old_hist.shape[0] == 0:
        return new_hist
    for i in range(n):
        a0 = old_start[i]
        a1 = old_start[i + 1]
        if a0 == a1:
            continue
        for k in range(new_start[i], new_start[i + 1]):
            j = new_nbj[k]
            for q in range(a0, a1):
                if old_nbj[q] == j:
                    nonzero = False
                    for c in range(h):
                        if old_hist[q, c] != 0.0:
                            nonzero = True
                    if nonzero:
                        for c in range(h):
                            new_hist[k, c] = old_hist[q, c]
                    break
    return new_hist


@njit(cache=True)
def cell_order(pos, radius, cutoff, skin, lo, length, periodic, ids):
    """Order of the particles by list cell, ties by particle id: ``perm`` (N,) with ``perm[s]`` the
    current slot of the particle that goes to slot ``s``.

    The cells are those :func:`_build` bins into; ``ids`` (N,) gives the particle id held in each
    slot.  The order depends only on the positions and the ids, not on the current slot order, so a
    run rebuilt from a checkpoint (slots in id order) gets the same layout as the uninterrupted run.
    """
    n = pos.shape[0]
    perm = np.empty(n, dtype=np.int64)
    if n == 0:
        return perm
    cell_size = _cell_size(radius, cutoff, skin)
    ncell, cell_of, counts, _ = _bin_particles(pos, cell_size, lo, length, periodic)
    slot_of = np.empty(n, dtype=np.int64)
    for q in range(n):
        slot_of[ids[q]] = q
    fill = counts[:-1].copy()
    for pid in range(n):
        q = slot_of[pid]
        c = cell_of[q]
        perm[fill[c]] = q
        fill[c] += 1
    return perm


@njit(cache=True)
def permute_rows(a, perm, block):
    """In place: rows ``[s*block, (s+1)*block)`` of ``a`` (2-D) become the old rows of slot ``perm[s]``."""
    tmp = a.copy()
    w = a.shape[1]
    for s in range(perm.shape[0]):
        o = perm[s]
        for b in range(block):
            for c in range(w):
                a[s * block + b, c] = tmp[o * block + b, c]


@njit(cache=True)
def carry_history_permuted(old_start, old_nbj, old_hist, new_start, new_nbj, perm):
    """:func:`carry_history` across a re-ordering of the particles: the new list is in the new slots,
    the old one in the old slots, ``perm[new slot] = old slot``.

    A pair stored under its other particle now (the half list keeps ``j > i``) swaps the roles of i
    and j, and its tangential spring, being i's relative displacement, changes sign.
    """
    n = new_start.shape[0] - 1
    h = old_hist.shape[1]
    new_hist = np.zeros((new_nbj.shape[0], h))
    if old_hist.shape[0] == 0:
        return new_hist
    for inew in range(n):
        a = perm[inew]
        for k in range(new_start[inew], new_start[inew + 1]):
            b = perm[new_nbj[k]]
            if a < b:
                row = a
                other = b
                sign = 1.0
            else:
                row = b
                other = a
                sign = -1.0
            for q in range(old_start[row], old_start[row + 1]):
                if old_nbj[q] == other:
                    nonzero = False
                    for c in range(h):
                        if old_hist[q, c] != 0.0:
                            nonzero = True
                    if nonzero:
                        for c in range(h):
                            new_hist[k, c] = sign * old_hist[q, c]
                    break
    return new_hist


@njit(cache=True)
def needs_rebuild(pos, ref_pos, skin):
    """True when some particle moved more than skin/2 since the last build."""
    lim = 0.25 * skin * skin
    for i in range(pos.shape[0]):
        dx = pos[i, 0] - ref_pos[i, 0]
        dy = pos[i, 1] - ref_pos[i, 1]
        dz = pos[i, 2] - ref_pos[i, 2]
        if dx * dx + dy * dy + dz * dz > lim:
            return True
    return False


@njit(cache=True)
def inner_list(pos, radius, cutoff, margin, start, nbj, shift, hist):
    """The order-preserving sub-list of the pairs of a half list closer than ``max(R_i + R_j, cutoff) +
    margin`` (m), with their history.

    While no particle moves more than (a little less than) ``margin / 2`` from ``pos``, every pair left
    out neither touches nor reaches the cut-off, so a pair kernel over the sub-list adds exactly what it
    adds over the whole list (a left-out pair adds +0.0, and the kept pairs come in the same order:
    the same sums bit for bit).  The history of the left-out pairs is set to zero where it is not (what
    the pair kernel does to a pair that does not touch).

    Returns
    -------
    istart, inbj, ishift, ihist : the sub-list (CSR, as :func:`build_neighbor_list`) and a copy of its
        history rows.
    kmap : (M',) int64, the entry of the whole list of each sub-list entry (:func:`scatter_history`).
    """
    n = pos.shape[0]
    h = hist.shape[1]
    kmap = np.empty(nbj.shape[0], dtype=np.int64)
    istart = np.zeros(n + 1, dtype=np.int64)
    c = 0
    for i in range(n):
        for k in range(start[i], start[i + 1]):
            j = nbj[k]
            dx = pos[i, 0] - pos[j, 0] + shift[k, 0]
            dy = pos[i, 1] - pos[j, 1] + shift[k, 1]
            dz = pos[i, 2] - pos[j, 2] + shift[k, 2]
            rc = radius[i] + radius[j]
            if cutoff > rc:
                rc = cutoff
            rc += margin
            if not dx * dx + dy * dy + dz * dz >= rc * rc:  # NaN distances are kept
                kmap[c] = k
                c += 1
            else:
                nonzero = False
                for q in range(h):
                    if hist[k, q] != 0.0:
                        nonzero = True
                if nonzero:
                    for q in range(h):
                        hist[k, q] = 0.0
        istart[i + 1] = c
    kmap = kmap[:c].copy()
    inbj = np.empty(c, dtype=np.int64)
    ishift = np.empty((c, 3))
    ihist = np.empty((c, h))
    for q in range(c):
        k = kmap[q]
        inbj[q] = nbj[k]
        for d in range(3):
            ishift[q, d] = shift[k, d]
        for d in range(h):
            ihist[q, d] = hist[k, d]
    return istart, inbj, ishift, ihist, kmap


@njit(cache=True)
def scatter_history(hist, ihist, kmap):
    """Write the history of a sub-list of :func:`inner_list` back into the whole list's, in place."""
    for q in range(kmap.shape[0]):
        for d in range(hist.shape[1]):
            hist[kmap[q], d] = ihist[q, d]


def brute_force_pairs(pos, radius, cutoff=0.0, skin=0.0, length=None, periodic=None):
    """All pairs ``(i, j)``, i < j, within ``max(R_i+R_j, cutoff) + skin`` (O(N^2), for tests)."""
    pos = np.asarray(pos, dtype=float)
    n = len(pos)
    d = pos[:, None, :] - pos[None, :, :]
    if periodic is not None:
        L = np.asarray(length, dtype=float)
        for a in range(3):
            if periodic[a]:
                d[..., a] -= L[a] * np.rint(d[..., a] / L[a])
    r = np.sqrt((d**2).sum(-1))
    rc = np.maximum(radius[:, None] + radius[None, :], cutoff) + skin
    ii, jj = np.nonzero((r < rc) & (np.arange(n)[:, None] < np.arange(n)[None, :]))
    return set(zip(ii.tolist(), jj.tolist()))


class NeighborList:
    """Convenience holder: a half list plus its history, rebuilt on demand.

    Parameters are those of :func:`build_neighbor_list`; ``n_history`` is the
    number of history values per entry (3 for a tangential spring).
    """

    def __init__(self, cutoff, skin, lo, length, periodic, n_history=0):
        self.cutoff = float(cutoff)
        self.skin = float(skin)
        self.lo = np.asarray(lo, dtype=float)
        self.length = np.asarray(length, dtype=float)
        self.periodic = np.asarray(periodic, dtype=np.int64)
        self.n_history = int(n_history)
        self.start = None
        self.nbj = None
        self.shift = None
        self.hist = None
        self.ref_pos = None
        self.builds = 0

    def build(self, pos, radius):
        start, nbj, shift = build_neighbor_list(pos, radius, self.cutoff, self.skin, self.lo,
                                                self.length, self.periodic)
        if self.hist is not None and self.n_history:
            self.hist = carry_history(self.start, self.nbj, self.hist, start, nbj)
        else:
            self.hist = np.zeros((len(nbj), self.n_history))
        self.start, self.nbj, self.shift = start, nbj, shift
        self.ref_pos = np.array(pos, dtype=float, copy=True)
        self.builds += 1

    def pairs(self):
        """Set of (i, j) pairs currently listed."""
        i = np.repeat(np.arange(len(self.start) - 1), np.diff(self.start))
        return set(zip(i.tolist(), self.nbj.tolist()))
