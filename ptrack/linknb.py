"""trackpy's linking rules in one numba pass over the movie (the fast path of :func:`ptrack.link.link`).

``trackpy.link`` spends its time on Python objects (a ``Point`` per
localisation, sets per subnetwork, a list of candidates per point): ~2.3 ms
per frame of 600 localisations, whatever its ``link_strategy``. This module
applies the same rules to arrays:

1. Candidates: each localisation of frame t+1 (a *destination*) takes its up
   to ``MAX_NEIGHBORS`` = 10 nearest *sources* (the localisations of frame t
   and the remembered ones, see 4) closer than ``search_range`` + 1e-7; a
   source's candidates are sorted by distance (ties: by destination order).
2. Subnetworks: the connected components of that bipartite graph. One source
   and one destination: linked. Otherwise the assignment of each source to
   one of its candidates (distinct destinations) or to nothing (cost
   ``search_range^2``) that minimises the summed squared distances, by the
   same branch-and-bound search as trackpy's; unclaimed destinations start
   new trajectories.
3. Adaptive search (``adaptive_stop``): a subnetwork too large for trackpy's
   solver (more than 15 sources unless it has one source or one destination
   or at most 3 of each; or, when larger than that, a source with more than 8
   candidates) is split: the range is multiplied by ``adaptive_step``, each
   source keeps its candidates within the new range (a source left without
   any is unlinked: trackpy counts it among the lost), and the components
   of what is left are solved the same way, recursively. When the range
   would fall to ``adaptive_stop`` or below, trackpy raises
   ``SubnetOversizeException``: here :func:`link_ids` returns None and the
   caller runs ``trackpy.link`` (which raises it).
4. Memory: a source left unlinked is a source again for the next ``memory``
   steps (at its last position; counted from the first step it was left
   unlinked), unless it is linked meanwhile.

Anisotropic ranges (3D: z has its own) are handled as trackpy does: positions
divided by the range per axis, range 1. The results are trackpy's up to the
numbering of the trajectories and up to exact ties of summed squared
distances (which real positions do not have).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["link_ids", "MAX_NEIGHBORS", "MAX_SUBNET"]

#: Largest number of source candidates of one destination (trackpy's Linker.MAX_NEIGHBORS)
MAX_NEIGHBORS = 10
#: Largest subnetwork trackpy's solvers take with adaptive search (Linker.MAX_SUB_NET_SIZE_ADAPTIVE) ...
MAX_SUBNET = 15
#: ... and without (Linker.MAX_SUB_NET_SIZE)
MAX_SUBNET_FIXED = 30
# trackpy's numba solver holds at most this many candidates per source, the null link included
_MAX_CANDIDATES = 9


@nb.njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@nb.njit(cache=True)
def _nearest(src, order, xs, dst, out):
    """Index of the nearest point of ``src`` (n, 2: x, y) to each point of ``dst`` (exact: a sweep outwards
    from its place in x, ``xs`` = src's x sorted by ``order``, stopped once the x distance alone exceeds the
    best; ties: the first found). ``out``: int64, one per dst point (-1 when src is empty)."""
    n = xs.shape[0]
    for i in range(dst.shape[0]):
        qx = dst[i, 0]
        qy = dst[i, 1]
        best = np.inf
        bj = -1
        lo = 0
        hi = n
        while lo < hi:      # first sorted place with xs >= qx
            mid = (lo + hi) >> 1
            if xs[mid] < qx:
                lo = mid + 1
            else:
                hi = mid
        r = lo
        l_ = lo - 1
        while r < n or l_ >= 0:
            if r < n:
                tx = xs[r] - qx
                if tx * tx >= best:
                    r = n
                else:
                    j = order[r]
                    ty = src[j, 1] - qy
                    d2 = tx * tx + ty * ty
                    if d2 < best:
                        best = d2
                        bj = j
                    r += 1
            if l_ >= 0:
                tx = xs[l_] - qx
                if tx * tx >= best:
                    l_ = -1
                else:
                    j = order[l_]
                    ty = src[j, 1] - qy
                    d2 = tx * tx + ty * ty
                    if d2 < best:
                        best = d2
                        bj = j
                    l_ -= 1
        out[i] = bj


@nb.njit(cache=True)
def _kth(a, k):
    # the k-th smallest of a (a copy is partitioned)
    return np.partition(a, k)[k]


@nb.njit(cache=True)
def _median(a):
    # np.median of a 1-D float array without NaN: the middle order statistic, or the mean (a + b) / 2 of the
    # two middle ones
    n = a.shape[0]
    h = n // 2
    p = np.partition(a, h)
    if n % 2:
        return p[h]
    lo = p[0]
    for i in range(1, h):
        lo = max(lo, p[i])
    return (lo + p[h]) / 2.0


@nb.njit(cache=True)
def _percentile(a, q):
    # np.percentile(a, q) (method "linear") of a 1-D float array without NaN, with numpy's arithmetic: virtual
    # index (n - 1) q / 100, and its lerp between the two order statistics around it
    n = a.shape[0]
    v = (n - 1) * (q / 100.0)
    if v >= n - 1:
        return _kth(a, n - 1)
    i = int(math.floor(v))
    p = np.partition(a, i)
    lo = p[i]
    hi = p[i + 1]
    for k in range(i + 2, n):
        hi = min(hi, p[k])
    t = v - i
    diff = hi - lo
    if t >= 0.5:
        return hi - diff * (1.0 - t)
    return lo + diff * t


@nb.njit(cache=True)
def robust_step(d):
    """Range statistic of per-axis steps (px, 1-D float array without NaN): 5 robust standard deviations
    (1.4826 x the median absolute deviation), or 1.5 x the 99th percentile of |d| when that is larger (a
    minority that moves much more than the rest), to the bit as numpy's median and percentile give them."""
    m = _median(d)
    return max(5.0 * 1.4826 * _median(np.abs(d - m)), 1.5 * _percentile(np.abs(d), 99.0))


@nb.njit(cache=True)
def nn_steps(pts, start, end, follows, max_pairs):
    """Per-axis steps (px) of mutual nearest neighbours between consecutive frames (the first look at the
    step distribution of :func:`ptrack.link._nn_steps`).

    Parameters
    ----------
    pts : (n, 2) float64 array
        x, y (px) of the localisations, frame after frame.
    start, end : int64 arrays
        Each frame's rows of ``pts``.
    follows : bool array
        Frame k + 1 is the frame after frame k (the pair k, k + 1 is measured).
    max_pairs : int
        Stop after the pair of frames that brings the count to this.

    Returns
    -------
    dx, dy : float64 arrays (px)
        Each mutual pair's step, frame pair after frame pair, in the order of the earlier frame's points.
    """
    n = pts.shape[0]
    dx = np.empty(n)
    dy = np.empty(n)
    m = 0
    for k in range(start.shape[0] - 1):
        if not follows[k]:
            continue
        a = pts[start[k]:end[k]]
        b = pts[start[k + 1]:end[k + 1]]
        na = a.shape[0]
        nb_ = b.shape[0]
        if na < 1 or nb_ < 1:
            continue
        oa = np.argsort(a[:, 0])
        ob = np.argsort(b[:, 0])
        ib = np.empty(nb_, np.int64)
        ia = np.empty(na, np.int64)
        _nearest(a, oa, a[:, 0][oa], b, ib)
        _nearest(b, ob, b[:, 0][ob], a, ia)
        for i in range(na):
            if ia[i] >= 0 and ib[ia[i]] == i:
                dx[m] = b[ia[i], 0] - a[i, 0]
                dy[m] = b[ia[i], 1] - a[i, 1]
                m += 1
        if m >= max_pairs:
            break
    return dx[:m], dy[:m]


@nb.njit(cache=True)
def _candidates(src, dst, ub, max_nb):
    """Each destination's up to ``max_nb`` nearest sources closer than ``ub``, as per-source candidate lists.

    Returns ``start`` (ns + 1), ``cdst`` (destination index) and ``cdist`` (distance, the sum of squared
    per-axis differences in axis order, square-rooted, as scipy's cKDTree), each source's run sorted by
    distance, ties by destination index."""
    ns, d = src.shape
    nd = dst.shape[0]
    start = np.zeros(ns + 1, np.int64)
    if ns == 0 or nd == 0:
        return start, np.zeros(0, np.int64), np.zeros(0)
    # cell list on the last two axes (x, y), cells of side ub (at most ~4e6 cells)
    ay = d - 2 if d >= 2 else 0
    ax = d - 1
    y0 = src[0, ay]
    x0 = src[0, ax]
    y1 = y0
    x1 = x0
    for j in range(ns):
        y0 = min(y0, src[j, ay])
        y1 = max(y1, src[j, ay])
        x0 = min(x0, src[j, ax])
        x1 = max(x1, src[j, ax])
    cs = max(ub, (y1 - y0) / 2000.0, (x1 - x0) / 2000.0, 1e-12)
    gh = int((y1 - y0) / cs) + 1
    gw = int((x1 - x0) / cs) + 1
    head = np.full(gh * gw, -1, np.int64)
    nxt = np.empty(ns, np.int64)
    for j in range(ns - 1, -1, -1):
        cy = int((src[j, ay] - y0) / cs)
        cx = int((src[j, ax] - x0) / cs)
        k = cy * gw + cx
        nxt[j] = head[k]
        head[k] = j
    # per destination: the sources within ub, the nearest max_nb kept
    pd_ = np.empty(nd * max_nb, np.int64)      # (destination, source) pairs
    ps_ = np.empty(nd * max_nb, np.int64)
    pdist = np.empty(nd * max_nb)
    npair = 0
    cand = np.empty(64, np.int64)
    cdd = np.empty(64)
    for i in range(nd):
        yy = dst[i, ay]
        xx = dst[i, ax]
        cy = int(np.floor((yy - y0) / cs))
        cx = int(np.floor((xx - x0) / cs))
        m = 0
        for gy in range(max(cy - 1, 0), min(cy + 2, gh)):
            for gx in range(max(cx - 1, 0), min(cx + 2, gw)):
                j = head[gy * gw + gx]
                while j >= 0:
                    s2 = 0.0
                    for a in range(d):
                        t = dst[i, a] - src[j, a]
                        s2 += t * t
                    dist = np.sqrt(s2)
                    if dist < ub:
                        if m == cand.shape[0]:
                            c2 = np.empty(2 * m, np.int64)
                            d2 = np.empty(2 * m)
                            c2[:m] = cand
                            d2[:m] = cdd
                            cand = c2
                            cdd = d2
                        cand[m] = j
                        cdd[m] = dist
                        m += 1
                    j = nxt[j]
        # insertion sort by distance (then source index), keep the first max_nb
        for a in range(1, m):
            cj = cand[a]
            cv = cdd[a]
            b = a - 1
            while b >= 0 and (cdd[b] > cv or (cdd[b] == cv and cand[b] > cj)):
                cand[b + 1] = cand[b]
                cdd[b + 1] = cdd[b]
                b -= 1
            cand[b + 1] = cj
            cdd[b + 1] = cv
        for a in range(min(m, max_nb)):
            pd_[npair] = i
            ps_[npair] = cand[a]
            pdist[npair] = cdd[a]
            npair += 1
    # per source, sorted by distance, ties by destination (trackpy's stable sort of a list built in
    # destination order)
    for p in range(npair):
        start[ps_[p] + 1] += 1
    for j in range(ns):
        start[j + 1] += start[j]
    fill = start[:-1].copy()
    cdst = np.empty(npair, np.int64)
    cdist = np.empty(npair)
    for p in range(npair):
        j = ps_[p]
        cdst[fill[j]] = pd_[p]
        cdist[fill[j]] = pdist[p]
        fill[j] += 1
    for j in range(ns):
        for a in range(start[j] + 1, start[j + 1]):
            cj = cdst[a]
            cv = cdist[a]
            b = a - 1
            while b >= start[j] and cdist[b] > cv:
                cdst[b + 1] = cdst[b]
                cdist[b + 1] = cdist[b]
                b -= 1
            cdst[b + 1] = cj
            cdist[b + 1] = cv
    return start, cdst, cdist


@nb.njit(cache=True)
def _solve(srcs, start, ncand, cdst, cdist, rng, dlocal, nd_sub, assign):
    """Branch-and-bound minimum of the summed squared distances over the assignments of the sources ``srcs``
    to their first ``ncand`` candidates or to nothing (cost ``rng^2``), distinct destinations; ``dlocal``
    maps a destination to 0..nd_sub-1. Writes each source's destination (-1: none) to ``assign``."""
    n = srcs.shape[0]
    # trackpy's recursive solver takes the sources with fewer candidates first
    order = np.argsort(ncand[srcs], kind="mergesort")
    s = srcs[order]
    nc = ncand[s] + 1                   # + the null link
    null2 = rng * rng
    taken = np.zeros(nd_sub, np.bool_)
    cur = np.full(n, -1, np.int64)      # destination (global index) chosen at each level
    k = np.zeros(n, np.int64)           # candidate tried next at each level
    sums = np.zeros(n + 1)
    best = np.full(n, -1, np.int64)
    best_sum = np.inf
    j = 0
    while j >= 0:
        up = k[j] >= nc[j]          # level exhausted
        if not up:
            i = k[j]
            if i < nc[j] - 1:
                dd = cdist[start[s[j]] + i]
                dest = cdst[start[s[j]] + i]
                t = sums[j] + dd * dd
            else:
                dest = -1
                t = sums[j] + null2
            # the candidates are sorted (the null link last): nothing further on this level is better
            up = t > best_sum
        if up:
            j -= 1
            if j >= 0:
                if cur[j] >= 0:
                    taken[dlocal[cur[j]]] = False
                    cur[j] = -1
                k[j] += 1
            continue
        if dest >= 0 and taken[dlocal[dest]]:
            k[j] += 1
            continue
        if j + 1 == n:
            if t < best_sum:
                best_sum = t
                for a in range(n - 1):
                    best[a] = cur[a]
                best[n - 1] = dest
            k[j] += 1
            continue
        cur[j] = dest
        if dest >= 0:
            taken[dlocal[dest]] = True
        sums[j + 1] = t
        j += 1
        k[j] = 0
    for a in range(n):
        assign[a] = best[a]
    return order


@nb.njit(cache=True)
def _oversize(ns_sub, nd_sub, max_nc, max_size):
    # trackpy's "hybrid" solver: its recursive solver for one source, one destination or at most 3 of each
    # (too large beyond max_size sources), its numba solver otherwise (also too large when a source has
    # more than 8 candidates + the null link)
    if nd_sub == 1 or ns_sub == 1 or (nd_sub <= 3 and ns_sub <= 3):
        return ns_sub > max_size
    return ns_sub > max_size or max_nc + 1 > _MAX_CANDIDATES


@nb.njit(cache=True)
def _link_step(src, dst, rng0, adaptive_stop, adaptive_step, max_size, max_nb, has_adaptive):
    """One frame step. Returns ``(dest_of_source, ok)``: each source's destination (-1: none), and False
    where trackpy would raise."""
    ns = src.shape[0]
    nd = dst.shape[0]
    dest_of = np.full(ns, -1, np.int64)
    if ns == 0 or nd == 0:
        return dest_of, True
    start, cdst, cdist = _candidates(src, dst, rng0 + 1e-7, max_nb)
    ncand = (start[1:] - start[:-1]).copy()
    # components: nodes 0..ns-1 sources, ns..ns+nd-1 destinations
    parent = np.arange(ns + nd)
    for j in range(ns):
        for a in range(start[j], start[j + 1]):
            r1 = _find(parent, j)
            r2 = _find(parent, ns + cdst[a])
            if r1 != r2:
                parent[r1] = r2
    # work items: a list of sources and of destinations with a range; flat buffers with offsets
    root = np.empty(ns + nd, np.int64)
    for v in range(ns + nd):
        root[v] = _find(parent, v)
    # group the sources with candidates and the destinations by component (sources without any are lost)
    key = np.empty(ns + nd, np.int64)
    for v in range(ns + nd):
        key[v] = root[v] if (v >= ns or ncand[v] > 0) else -1
    order = np.argsort(key, kind="mergesort")
    # stack of items: (offset into items_nodes, count, range)
    items_nodes = np.empty(2 * (ns + nd) + 16, np.int64)
    it_off = []
    it_cnt = []
    it_rng = []
    pos = 0
    a = 0
    while a < ns + nd:
        v = order[a]
        if key[v] < 0:
            a += 1
            continue
        b = a
        while b < ns + nd and key[order[b]] == key[v]:
            b += 1
        for c in range(a, b):
            items_nodes[pos + c - a] = order[c]
        it_off.append(pos)
        it_cnt.append(b - a)
        it_rng.append(rng0)
        pos += b - a
        a = b
    dlocal = np.full(nd, -1, np.int64)
    assign = np.empty(max(ns, 1), np.int64)
    while len(it_off):
        off = it_off.pop()
        cnt = it_cnt.pop()
        rng = it_rng.pop()
        nodes = items_nodes[off:off + cnt].copy()
        ns_sub = 0
        max_nc = 0
        for v in nodes:
            if v < ns:
                ns_sub += 1
                max_nc = max(max_nc, ncand[v])
        nd_sub = cnt - ns_sub
        if ns_sub == 0:
            continue                            # a lone destination: a new trajectory
        if ns_sub == 1 and nd_sub == 1:
            j = -1
            i = -1
            for v in nodes:
                if v < ns:
                    j = v
                else:
                    i = v - ns
            dest_of[j] = i
            continue
        if not _oversize(ns_sub, nd_sub, max_nc, max_size):
            srcs = np.empty(ns_sub, np.int64)
            q = 0
            r = 0
            for v in nodes:
                if v < ns:
                    srcs[q] = v
                    q += 1
                else:
                    dlocal[v - ns] = r
                    r += 1
            o = _solve(srcs, start, ncand, cdst, cdist, rng, dlocal, nd_sub, assign)
            for q in range(ns_sub):
                dest_of[srcs[o[q]]] = assign[q]
            continue
        # too large: split with a smaller range (trackpy's adaptive_link_wrap / split_subnet)
        if not has_adaptive or rng <= adaptive_stop:
            return dest_of, False
        new_rng = rng * adaptive_step
        for v in nodes:
            if v < ns:
                c = 0
                while c < ncand[v] and cdist[start[v] + c] <= new_rng:
                    c += 1
                ncand[v] = c
                parent[v] = v
            else:
                parent[v] = v
        for v in nodes:
            if v < ns:
                for c in range(start[v], start[v] + ncand[v]):
                    r1 = _find(parent, v)
                    r2 = _find(parent, ns + cdst[c])
                    if r1 != r2:
                        parent[r1] = r2
        keys = np.empty(cnt, np.int64)
        for c in range(cnt):
            v = nodes[c]
            keys[c] = _find(parent, v) if (v >= ns or ncand[v] > 0) else -1
        oo = np.argsort(keys, kind="mergesort")
        if pos + cnt > items_nodes.shape[0]:
            grown = np.empty(2 * (pos + cnt), np.int64)
            grown[:pos] = items_nodes[:pos]
            items_nodes = grown
        a = 0
        while a < cnt:
            kk = keys[oo[a]]
            if kk < 0:
                a += 1
                continue
            b = a
            while b < cnt and keys[oo[b]] == kk:
                b += 1
            for c in range(a, b):
                items_nodes[pos + c - a] = nodes[oo[c]]
            it_off.append(pos)
            it_cnt.append(b - a)
            it_rng.append(new_rng)
            pos += b - a
            a = b
    return dest_of, True


@nb.njit(cache=True)
def _link_all(pos, fstart, memory, rng0, adaptive_stop, adaptive_step, max_size, max_nb, has_adaptive):
    """All frame steps; ``fstart`` (n_frames + 1) delimits the rows of each frame number (empty frames
    included). Returns the trajectory id of each row and ok."""
    n, d = pos.shape
    pid = np.full(n, -1, np.int64)
    nf = fstart.shape[0] - 1
    next_id = 0
    mem_row = np.empty(0, np.int64)     # remembered rows and the step after which they are forgotten
    mem_exp = np.empty(0, np.int64)
    for r in range(fstart[0], fstart[1]):
        pid[r] = next_id
        next_id += 1
    for t in range(1, nf):
        p0, p1 = fstart[t - 1], fstart[t]
        q0, q1 = fstart[t], fstart[t + 1]
        nprev = p1 - p0
        nm = mem_row.shape[0]
        ns = nprev + nm
        src_rows = np.empty(ns, np.int64)
        for a in range(nprev):
            src_rows[a] = p0 + a
        for a in range(nm):
            src_rows[nprev + a] = mem_row[a]
        src = np.empty((ns, d))
        for a in range(ns):
            src[a] = pos[src_rows[a]]
        dst = pos[q0:q1]
        dest_of, ok = _link_step(src, dst, rng0, adaptive_stop, adaptive_step, max_size, max_nb,
                                          has_adaptive)
        if not ok:
            return pid, False
        claimed = np.zeros(q1 - q0, np.bool_)
        for a in range(ns):
            if dest_of[a] >= 0:
                pid[q0 + dest_of[a]] = pid[src_rows[a]]
                claimed[dest_of[a]] = True
        for i in range(q1 - q0):
            if not claimed[i]:
                pid[q0 + i] = next_id
                next_id += 1
        if memory > 0:
            # remembered rows stay until their expiry unless linked now; the previous frame's unlinked
            # rows join for `memory` steps
            keep = 0
            for a in range(nm):
                if dest_of[nprev + a] < 0 and mem_exp[a] > t:
                    keep += 1
            new = 0
            for a in range(nprev):
                if dest_of[a] < 0:
                    new += 1
            mr = np.empty(keep + new, np.int64)
            me = np.empty(keep + new, np.int64)
            c = 0
            for a in range(nm):
                if dest_of[nprev + a] < 0 and mem_exp[a] > t:
                    mr[c] = mem_row[a]
                    me[c] = mem_exp[a]
                    c += 1
            for a in range(nprev):
                if dest_of[a] < 0:
                    mr[c] = p0 + a
                    me[c] = t + memory
                    c += 1
            mem_row, mem_exp = mr, me
    return pid, True


def link_ids(frames, pos, search_range, memory: int = 0, adaptive_stop: float | None = None,
             adaptive_step: float = 0.95):
    """trackpy.link's trajectory ids, computed by numba (see the module docstring for the rules).

    Parameters
    ----------
    frames : 1D int array
        Frame number of each row, non-decreasing.
    pos : 2D float array, shape (n, ndim)
        Positions (px), in trackpy's ``pos_columns`` order (e.g. y, x or z, y, x).
    search_range : float or sequence of float
        Largest step between frames (px), one per axis or one for all.
    memory : int
        Frames a particle may vanish and keep its id.
    adaptive_stop, adaptive_step : float
        trackpy's adaptive search (None: none).

    Returns
    -------
    1D int64 array or None
        The trajectory id of each row (numbered by first appearance within the first frame, then by
        frame: not trackpy's numbers, the same partition), or None where trackpy would raise
        (``SubnetOversizeException``: a subnetwork still too large at ``adaptive_stop``).
    """
    frames = np.asarray(frames, np.int64)
    pos = np.ascontiguousarray(pos, np.float64)
    if len(frames) == 0:
        return np.zeros(0, np.int64)
    if len(frames) > 1 and not (frames[1:] >= frames[:-1]).all():
        raise ValueError("frames must be non-decreasing")
    rng = np.atleast_1d(np.asarray(search_range, np.float64))
    if rng.size > 1 and not np.all(rng[1:] == rng[:-1]):
        # trackpy: positions in units of the per-axis range, range 1, adaptive_stop rescaled likewise
        pos = np.ascontiguousarray(pos / np.atleast_2d(rng))
        stop = None if adaptive_stop is None else float(np.max(adaptive_stop / np.atleast_2d(rng)))
        r0 = 1.0
    else:
        stop = adaptive_stop
        r0 = float(rng[0])
    fr = np.arange(frames[0], frames[-1] + 2)
    fstart = np.searchsorted(frames, fr).astype(np.int64)
    max_size = MAX_SUBNET if stop is not None else MAX_SUBNET_FIXED
    pid, ok = _link_all(pos, fstart, int(memory), r0, float(stop) if stop is not None else 0.0,
                        float(adaptive_step), max_size, MAX_NEIGHBORS, stop is not None)
    return pid if ok else None
