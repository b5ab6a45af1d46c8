"""Knob-free detection: noise and background maps, a false-alarm threshold, polarity, scale space.

Real frames are not flat: illumination is uneven, out-of-focus particles and
dirt add structure, and the noise changes across the frame (shot noise
follows the light; sCMOS pixels differ). One global noise figure then either
drowns the faint particles or lets the bright regions through. Here:

1. A 3x3 median removes hot pixels; the frame is band-passed at each scale
   ``s`` of a geometric ladder by a difference of Gaussians
   ``G(s) - G(3 s)`` (the matched filter of a spot of width ``s`` minus its
   local surround, so slow illumination and large dust vanish).
2. Each band-passed image gets a local *background* and *noise* map: the
   median and 1.4826 x the median absolute deviation over tiles (32 px, at
   least 4 s), bilinearly interpolated. The response in noise units is the
   detection statistic; it is comparable between scales and across the frame.
3. The threshold ``u`` is set from a false-alarm rate (default 1 per 10^6 px):
   for a smooth Gaussian field the density of local maxima above a high
   level ``u`` is the Euler-characteristic density
   ``lambda u exp(-u^2/2) / (2 pi)^(3/2)`` (Adler 1981; Worsley et al. 1996),
   with ``lambda`` the variance of the field's gradient over its variance,
   computed exactly for the discrete filter; the number of scales multiplies
   the rate (a Bonferroni bound). ``snr`` overrides it.
4. Polarity (bright particles on dark, or dark on bright) is decided from the
   data when not given: the side whose significant maxima carry more
   (summed SNR above threshold) wins.
5. Scale selection: the SNR maps are maximised over scale; local maxima of
   that map above ``u`` are candidates, each with the scale of its best
   response; weaker candidates inside a stronger one's image (2 s of its
   scale) are dropped, so a ring or a defocused image gives one detection,
   not a necklace.
6. Rings: when the candidates say the frame holds rings (rim pieces are
   ridges; faint centres sit in rings of the opposite sign), the rim votes
   for its centre (:mod:`ptrack.image.rings`: circle means of the band at
   radii 4-12.7 px, both signs, their own noise maps and false-alarm
   threshold, an all-round sector test). A ring so found holds every other
   candidate within its radius + 2.5 px.

Pixel coordinates follow trackpy (``x`` columns, ``y`` rows, pixel centres
at integers).
"""
from __future__ import annotations

import functools
import math
import sys
import threading

import numba as nb
import numpy as np

from ..errors import UserError
from .peaks import local_maxima
from .preprocess import fast_median
from .rings import RING_RADII, ring_evidence, ring_maps_candidates, ring_scale

__all__ = ["DEFAULT_SCALES", "FALSE_ALARM_RATE", "MAP_REFRESH", "bandpass", "noise_maps", "false_alarm_threshold",
           "detect"]

#: Default scale ladder (Gaussian sigma of the spot, px): sqrt(2) steps from 1 to 4 px. Larger images (rings,
#: strong defocus) are found at 4 px: a matched filter too small by 1.4-2x loses little SNR, and a sixth scale
#: cost 10-20 % of the frame time. The steps are exact (not 1.41 and 2.83): the surround of each scale is then
#: the scale two rungs up (_SURROUND), so the ladder is n + 2 = 7 blurs (rounded values make 2 x 1.41 = 2.82 and
#: 2.83 two blurs, one of them a full-size interpolation).
DEFAULT_SCALES = (1.0, math.sqrt(2.0), 2.0, 2.0 * math.sqrt(2.0), 4.0)
#: Frames that share one measurement of the noise and background maps when :func:`detect` is given a cache
#: (the maps follow the camera and the illumination, not the particles; measuring them costs ~40 % of a frame).
MAP_REFRESH = 16
#: Default false-alarm rate: expected false detections per pixel of an empty frame.
FALSE_ALARM_RATE = 1e-6
#: Share of the false-alarm rate given to the ring maps (:mod:`ptrack.image.rings`), on top of the blob scales'.
RING_RATE_SHARE = 0.5
#: Scale (px) reported for a ring of radius R found by the ring maps: R x this
RING_SCALE_PER_RADIUS = 0.4
# largest full-size inverse-noise maps (bytes, all scales, float32) kept in the cache (640 x 424: 5.4 MB; 1024^2:
# 21 MB, 11 % of the frame time faster than blocks; 2048^2: 84 MB, no faster); larger frames interpolate them in
# blocks of rows for each frame (interpolating inside the best-over-scales pass instead was no faster)
_FULL_IVS_BYTES = 32 << 20
#: full-size inverse-noise maps in float32 by cv2.resize (False: float64 by :func:`_inverse_noise_rows`, 4x the
#: time to make and 1.33x the bytes the best-over-scales pass reads per pixel and scale)
_IVS32 = True
# ... in blocks of rows of this many bytes (all scales: a block stays in the processor's cache)
_IVS_BLOCK_BYTES = 1 << 20
# the full-size inverse-noise maps of a cache are written into the previous map's array (kept in the blur pool):
# a fresh 11 MB array per map measurement costs its page faults (~4 ms per 640 x 424 map against ~1 ms to fill)
_POOL_IVS = True
# the work arrays a cache owns (the blur ladder's outputs, the full-size inverse-noise maps) go to a free list when
# the cache is dropped, and the next cache takes its arrays from there: a movie's first frame otherwise touches
# ~14 MB of fresh memory at 640 x 424, whose page faults (~3 us per 4 kB page on a VM) cost ~10 ms. At most this
# many bytes are kept on the free list (0: no recycling)
_RECYCLE_BYTES = 64 << 20
_FREE = []
_FREE_LOCK = threading.RLock()
# reach of the blur ladder's Gaussian kernels (sigmas; None: cv2's 4)
_BLUR_TRUNC = 3.0
# the median of the frame's noise map is taken over every this many pixels of each axis (1: all)
_RN_MEDIAN_STEP = 4
# surround of the band-pass, in units of the scale: 2 = two rungs of the sqrt(2) ladder, so the
# ladder's blurs serve as each other's surrounds (n + 2 blurs for n scales)
_SURROUND = 2.0
#: Blurs of the ladder wider than this (Gaussian sigma, px) are made on a 2x area-reduced copy (see _blur_ladder)
_HALF_ABOVE = 2.5
#: Sampling stride of a scale's noise map, in units of the scale (at least the ~256-samples-per-tile stride): the
#: band-passed noise is correlated over ~ s, so samples closer than ~1.5 s add little to the MAD (0: that rule off)
_MAP_STRIDE_S = 1.5


def _list_only_refcount():
    # sys.getrefcount of an array that only a list refers to, read as take() reads it (2 on CPython <= 3.13:
    # the list's and the argument's; an interpreter that borrows the argument's reference reports fewer)
    probe = [np.empty(0)]
    return sys.getrefcount(probe[0])


_LIST_ONLY = _list_only_refcount()


def _to_free_list(arrays):
    # the arrays onto the free list, the oldest dropped beyond _RECYCLE_BYTES
    with _FREE_LOCK:
        _FREE.extend(arrays)
        total = sum(a.nbytes for a in _FREE)
        while _FREE and total > _RECYCLE_BYTES:
            total -= _FREE.pop(0).nbytes


class _Owned:
    """The work arrays of one cache (:func:`detect`): taken from the free list or new, given back to it when
    the cache (so this object) is dropped, or by :meth:`give`. An array of the free list is handed out again
    only once the list holds its only reference (a caller may still hold a returned map, a view of one, or an
    array read from the cache); every array is overwritten in full before it is read."""

    __slots__ = ("arrays",)

    def __init__(self):
        self.arrays = []

    def take(self, shape, dtype):
        """An array of this shape and dtype (contents undefined), owned from now on."""
        shape, dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        a = None
        with _FREE_LOCK:
            for k in range(len(_FREE) - 1, -1, -1):
                # only the list refers to it (a view holds a reference to its base)
                if _FREE[k].shape == shape and _FREE[k].dtype == dtype and sys.getrefcount(_FREE[k]) == _LIST_ONLY:
                    a = _FREE.pop(k)
                    break
        if a is None:
            a = np.empty(shape, dtype)
        self.arrays.append(a)
        return a

    def give(self, *arrays):
        """These arrays no longer owned: onto the free list (handed out again once nothing refers to them)."""
        gone = [a for a in self.arrays if any(a is b for b in arrays)]
        self.arrays = [a for a in self.arrays if not any(a is b for b in arrays)]
        _to_free_list(gone)

    def __del__(self):
        try:
            _to_free_list(self.arrays)
        except Exception:       # interpreter shutdown
            pass
        self.arrays = []


def scratch(cache, name, shape, dtype):
    """A work array of a movie's cache (:func:`detect`'s), kept from frame to frame under ``name``: overwritten
    in full by every use and read only within one call (not returned), so a movie's frames allocate no fresh
    full-size temporaries (on a VM each 4 kB page of a fresh array costs ~3 us of page fault; a 640 x 424 frame
    had ~4 such arrays, ~1000 faults per 5 frames). A fresh array without a cache (or before :func:`detect` made
    its pool)."""
    pool = cache.get("blur_pool") if cache is not None else None
    owned = pool.get("owned") if pool is not None else None
    if owned is None:
        return np.empty(shape, dtype)
    shape, dtype = tuple(int(n) for n in shape), np.dtype(dtype)
    arrays = pool.setdefault("scratch", {})
    a = arrays.get(name)
    if a is None or a.shape != shape or a.dtype != dtype:
        a = owned.take(shape, dtype)
        arrays[name] = a
    return a


def bandpass(work, s: float):
    """Difference of Gaussians ``G(s) - G(2 s)`` of a float32 frame (cv2, reflected border)."""
    import cv2

    s = max(0.5, float(s))
    return cv2.GaussianBlur(work, (0, 0), s, borderType=cv2.BORDER_REFLECT) - \
        cv2.GaussianBlur(work, (0, 0), _SURROUND * s, borderType=cv2.BORDER_REFLECT)


def _ksize(s):
    # the ladder's Gaussian kernels reach _BLUR_TRUNC sigmas (cv2's own choice for float images is 4)
    if _BLUR_TRUNC is None:
        return (0, 0)
    k = 2 * int(math.ceil(_BLUR_TRUNC * s)) + 1
    return (k, k)


def _blur_ladder(work, sigmas, pool=None):
    """G(s) * work for increasing ``sigmas``, each from the previous one (cheaper kernels); blurs wider
    than _HALF_ABOVE (2.5 px) are done on a 2x area-reduced copy and interpolated back (their content is smooth).

    ``pool``: a dict (a movie's cache) whose arrays, one per output, the blurs are written into, frame after
    frame (the same values; fresh full-size arrays every frame cost the kernel's page faults, ~1 ms per
    640 x 424 frame), taken from its ``owned`` (an :class:`_Owned`) when it has one. The outputs are then
    overwritten by the next call with that pool."""
    import cv2

    H, W = work.shape
    bufs = None
    if pool is not None:
        key = (H, W, tuple(sigmas))
        if pool.get("key") != key:
            kept = {k: pool[k] for k in ("owned", "scratch") if k in pool}
            pool.clear()
            pool.update(kept)
            pool["key"] = key
            pool["bufs"] = [[None, None] for _ in sigmas]
        bufs = pool["bufs"]
    owned = pool.get("owned") if pool is not None else None

    def into(i, j, fn, *args, **kw):
        # fn(*args, dst=<array i, j of the pool>, **kw), the array kept for the next frame (cv2 fills it)
        if bufs is None:
            return fn(*args, **kw)
        if bufs[i][j] is None and owned is not None:
            bufs[i][j] = owned.take((H, W), work.dtype)
        out = fn(*args, dst=bufs[i][j], **kw) if bufs[i][j] is not None else fn(*args, **kw)
        bufs[i][j] = out
        return out

    out = []
    prev, prev_s = work, 0.0
    half = None
    for i, s in enumerate(sigmas):
        if s > _HALF_ABOVE and min(H, W) >= 32:
            if half is None:
                # the half-size arrays alternate between two of the pool's (a blur's source is not its output);
                # without an owner cv2 allocates (dst None)
                hbuf = [None, None]
                if owned is not None:
                    if pool.get("half") is None:
                        pool["half"] = [owned.take((H // 2, W // 2), prev.dtype) for _ in range(2)]
                    hbuf = pool["half"]
                hi = 0
                half = cv2.resize(prev, (W // 2, H // 2), dst=hbuf[0], interpolation=cv2.INTER_AREA)
                half_s = math.sqrt(prev_s ** 2 + 0.25)      # area reduction ~ a 0.5 px blur at full scale
            ds = math.sqrt(max(s * s - half_s * half_s, 0.01)) / 2.0
            hi = 1 - hi
            half = cv2.GaussianBlur(half, _ksize(ds), ds, dst=hbuf[hi], borderType=cv2.BORDER_REFLECT)
            half_s = s
            out.append(into(i, 0, cv2.resize, half, (W, H), interpolation=cv2.INTER_LINEAR))
            continue
        ds = math.sqrt(max(s * s - prev_s * prev_s, 0.01))
        prev = into(i, 1, cv2.GaussianBlur, prev, _ksize(ds), ds, borderType=cv2.BORDER_REFLECT)
        prev_s = s
        out.append(prev)
    return out


@nb.njit(cache=True, inline="always")
def _sort_key(u):
    # the bits of a float32 as a uint32 whose unsigned order is the floats' order (negative: all bits flipped;
    # positive: the sign bit set)
    return u ^ np.uint32(0xFFFFFFFF) if u & np.uint32(0x80000000) else u | np.uint32(0x80000000)


@nb.njit(cache=True, inline="always")
def _sort_unkey(u):
    # the float32 bits of a _sort_key
    return u ^ np.uint32(0x80000000) if u & np.uint32(0x80000000) else u ^ np.uint32(0xFFFFFFFF)


@nb.njit(cache=True, inline="always")
def _dev_pair(s, n, p, m, k):
    # the k-th smallest (0-based) of the float32 deviations |s_i - m| of the sorted float32 array s[:n], and the
    # next one (inf if none), as float64; s[:p] <= m <= s[p:]. The deviations m - s[p - 1 - i] (i < p) and
    # s[p + i] - m are each non-decreasing in i (float32 subtraction rounds monotonically), so this is the k-th
    # of two sorted sequences: a binary search for how many of the k + 1 smallest come from below m
    a = p
    b = n - p
    lo = max(0, k + 1 - b)
    hi = min(k + 1, a)
    while lo < hi:
        t = (lo + hi) >> 1
        if m - s[p - 1 - t] >= s[p + k - t] - m:
            hi = t
        else:
            lo = t + 1
    t = lo
    x = -np.inf
    if t > 0:
        x = np.float64(m - s[p - t])
    if k - t >= 0:
        x = max(x, np.float64(s[p + k - t] - m))
    y = np.inf
    if t < a:
        y = np.float64(m - s[p - 1 - t])
    if k + 1 - t < b:
        y = min(y, np.float64(s[p + k + 1 - t] - m))
    return x, y


@nb.njit(cache=True, inline="always")
def _sorted_tile_med_mad(s, n):
    # the median and the MAD (x 1.4826, float32) of the ascending float32 tile s[:n]: the one rule of both
    # tile-statistics paths (the radix sort's and numpy's)
    h = n >> 1
    if n & 1:
        m = s[h]
        dev = _dev_pair(s, n, h, m, h)[0]
    else:
        m = np.float32((np.float64(s[h - 1]) + np.float64(s[h])) / 2)
        d0, d1 = _dev_pair(s, n, h, m, h - 1)
        dev = (d0 + d1) / 2
    return m, np.float32(1.4826 * dev)


@nb.njit(cache=True)
def _tile_med_mad(sub, nh, nw, th, tw):
    """Median and 1.4826 x median absolute deviation of each ``th x tw`` tile of ``sub``.

    Parameters
    ----------
    sub : 2D C-contiguous float32 array
        Image (any unit), at least ``nh th x nw tw``.
    nh, nw : int
        Tiles per column and per row.
    th, tw : int
        Tile shape (px).

    Returns
    -------
    med, mad : 2D float32 arrays, shape (nh, nw)
        numpy's values (unit of ``sub``): the median of an even count is the float64 mean of the two middle
        values, rounded to float32; the deviations are float32 ``|x - med|``. Each tile is sorted once (LSD
        radix sort of the floats' order-preserving bits, 4 byte passes, a pass whose byte all share skipped);
        the median is read off and the MAD found by a binary search over the deviations on either side of it
        (two quickselects per tile cost twice as much).
    """
    med = np.empty((nh, nw), np.float32)
    mad = np.empty((nh, nw), np.float32)
    n = th * tw
    bits = sub.view(np.uint32)
    ka = np.empty(n, np.uint32)
    kb = np.empty(n, np.uint32)
    cnt = np.empty((4, 256), np.int32)
    for a in range(nh):
        for b in range(nw):
            for d in range(4):
                for q in range(256):
                    cnt[d, q] = 0
            k = 0
            for i in range(a * th, (a + 1) * th):
                for j in range(b * tw, (b + 1) * tw):
                    u = _sort_key(bits[i, j])
                    ka[k] = u
                    cnt[0, u & np.uint32(255)] += 1
                    cnt[1, (u >> np.uint32(8)) & np.uint32(255)] += 1
                    cnt[2, (u >> np.uint32(16)) & np.uint32(255)] += 1
                    cnt[3, u >> np.uint32(24)] += 1
                    k += 1
            src = ka
            dst = kb
            for d in range(4):
                sh = np.uint32(8 * d)
                if cnt[d, (src[0] >> sh) & np.uint32(255)] == n:
                    continue
                tot = 0
                for q in range(256):
                    c = cnt[d, q]
                    cnt[d, q] = tot
                    tot += c
                for k in range(n):
                    u = src[k]
                    q = (u >> sh) & np.uint32(255)
                    dst[cnt[d, q]] = u
                    cnt[d, q] += 1
                src, dst = dst, src
            for k in range(n):
                src[k] = _sort_unkey(src[k])
            med[a, b], mad[a, b] = _sorted_tile_med_mad(src.view(np.float32), n)
    return med, mad


@nb.njit(cache=True)
def _gather_tiles(sub, nh, nw, th, tw, out, negz):
    # tile (a, b) of sub (th x tw px, raster order) into row a nw + b of out, shape (nh nw, th tw), and the
    # number of its -0.0 values into negz[a nw + b]
    for a in range(nh):
        for b in range(nw):
            o = out[a * nw + b]
            k = 0
            nz = 0
            for i in range(a * th, (a + 1) * th):
                for j in range(b * tw, (b + 1) * tw):
                    v = sub[i, j]
                    o[k] = v
                    if v == 0 and math.copysign(1.0, v) < 0:
                        nz += 1
                    k += 1
            negz[a * nw + b] = nz


@nb.njit(cache=True)
def _sorted_med_mad(tiles, negz, nh, nw, med, mad):
    """:func:`_tile_med_mad` from tiles already sorted in ascending order, one per row of ``tiles`` (shape
    (nh nw, n), float32; numpy's sort, which puts NaN last and may swap the signs of zeros: its vectorised
    min/max return either of -0.0 and +0.0), ``negz`` the number of -0.0 values of each tile before the sort.

    ``med``, ``mad`` (float32, shape (nh, nw), unit of the tiles) are filled with :func:`_tile_med_mad`'s
    values bit for bit: the run of zeros is rewritten in the radix sort's order (the tile's -0.0 first)
    before it is read.
    Returns False (and stops) at a tile holding a NaN: the radix sort orders NaNs by their sign bit, numpy's
    puts them last (the caller then uses :func:`_tile_med_mad`).
    """
    n = tiles.shape[1]
    for a in range(nh):
        for b in range(nw):
            s = tiles[a * nw + b]
            if math.isnan(s[n - 1]):
                return False
            # the zeros (a contiguous run: -0.0 == +0.0) in the radix order: the negative ones first
            lo = 0
            hi = n
            while lo < hi:
                t = (lo + hi) >> 1
                if s[t] < 0:
                    lo = t + 1
                else:
                    hi = t
            if lo < n and s[lo] == 0:
                e = lo
                while e < n and s[e] == 0:
                    e += 1
                neg = negz[a * nw + b]
                for t in range(lo, e):
                    s[t] = np.float32(-0.0) if t < lo + neg else np.float32(0.0)
            med[a, b], mad[a, b] = _sorted_tile_med_mad(s, n)
    return True


#: tile medians and MADs from numpy's (vectorised) sort of the gathered tiles (False: :func:`_tile_med_mad`'s
#: radix sort in numba, ~4x the time on AVX2); the same values bit for bit
_NP_SORT = True


def _tile_stats(sub, nh, nw, th, tw):
    """:func:`_tile_med_mad`'s median and 1.4826 MAD of each ``th x tw`` tile of the float32 ``sub``."""
    if _NP_SORT and th * tw > 1:
        tiles = np.empty((nh * nw, th * tw), np.float32)
        negz = np.empty(nh * nw, np.int64)
        _gather_tiles(sub, nh, nw, th, tw, tiles, negz)
        tiles.sort(axis=1)
        med = np.empty((nh, nw), np.float32)
        mad = np.empty((nh, nw), np.float32)
        if _sorted_med_mad(tiles, negz, nh, nw, med, mad):
            return med, mad
    return _tile_med_mad(sub, nh, nw, th, tw)


def noise_maps(img, tile: int = 64, step: int = 2, what: str = "both", shape=None, out=None):
    """Local background (median) and noise (1.4826 MAD) of an image over tiles, interpolated to full size.

    Parameters
    ----------
    img : 2D float32 array
    tile : int
        Tile side (px). Particles cover a minority of every tile, so the
        median and the MAD describe the background and its noise.
    step : int
        Sub-sampling inside each tile (speed; the MAD needs only a few
        hundred samples).
    what : {"both", "inverse noise", "grid"}
        ``"inverse noise"``: only 1 / noise (one interpolation, for the
        band-passed images whose background is zero by construction);
        ``"grid"``: 1 / noise on the tile grid, not interpolated.
    shape : (H, W), optional
        ``img`` is already sub-sampled by ``step`` from a frame of this shape
        (the maps are returned at full size).
    out : (background, noise), optional
        ``what="both"``: float32 arrays of the full shape that the interpolated
        maps are written into (and returned).

    Returns
    -------
    background, noise : 2D float32 arrays, shape of ``img``
    """
    import cv2

    H, W = img.shape if shape is None else shape
    t = int(max(8, min(tile, H, W)))
    nh, nw = max(1, H // t), max(1, W // t)
    # tiles cover the frame: the last row/column of tiles absorbs the remainder
    sub = img[::step, ::step] if shape is None else img
    # tiles of the sub-sampled image: the remainder rows/columns join the last tile's statistics by
    # the interpolation (they are within one tile of it)
    th, tw = max(1, (H // nh) // step), max(1, (W // nw) // step)
    med, mad = _tile_stats(np.ascontiguousarray(sub[:nh * th, :nw * tw], np.float32), nh, nw, th, tw)
    # a tile of constant values (saturated, padded) has MAD 0: borrow the frame's typical noise
    if nh >= 3 and nw >= 3:
        # neighbouring tiles share the noise level: a 3x3 mean over the tile grid cuts the MAD's
        # sampling scatter threefold (a noise map 3 % low doubles the false alarms at u = 5)
        import cv2 as _cv2

        mad = _cv2.blur(mad, (3, 3), borderType=_cv2.BORDER_REPLICATE)
    pos = mad[mad > 0]
    floor = fast_median(pos) * 0.25 if pos.size else 1e-6
    mad = np.maximum(mad, max(floor, 1e-6))
    if what == "grid":
        return np.ascontiguousarray(1.0 / mad, np.float32)
    if what == "inverse noise":
        inv = (1.0 / mad).astype(np.float32)
        if nh == 1 and nw == 1:
            return np.full((H, W), inv[0, 0], np.float32)
        return cv2.resize(inv, (W, H), interpolation=cv2.INTER_LINEAR)
    if nh == 1 and nw == 1:
        return np.full((H, W), med[0, 0], np.float32), np.full((H, W), mad[0, 0], np.float32)
    if out is not None:
        return (cv2.resize(med, (W, H), dst=out[0], interpolation=cv2.INTER_LINEAR),
                cv2.resize(mad, (W, H), dst=out[1], interpolation=cv2.INTER_LINEAR))
    return (cv2.resize(med, (W, H), interpolation=cv2.INTER_LINEAR),
            cv2.resize(mad, (W, H), interpolation=cv2.INTER_LINEAR))


def _kernel(s: float):
    n = int(2 * math.ceil(4 * _SURROUND * s) + 3)
    d = np.zeros((n, n), np.float32)
    d[n // 2, n // 2] = 1.0
    return bandpass(d, s).astype(np.float64)


@functools.lru_cache(maxsize=64)
def skew_factor(s: float) -> float:
    """Skewness of white noise after the band-pass of scale s, per unit pixel skewness: sum k^3 / (sum k^2)^1.5."""
    k = _kernel(s)
    return float((k ** 3).sum() / (k ** 2).sum() ** 1.5)


def _gradient_ratio(s: float) -> float:
    """lambda = Var(d f / d x) / Var(f) for white noise filtered by the discrete DoG of scale s (px^-2)."""
    k = _kernel(s)
    gx = np.diff(k, axis=1)
    return float((gx ** 2).sum() / (k ** 2).sum())


@functools.lru_cache(maxsize=64)
def false_alarm_threshold(scales, rate: float = FALSE_ALARM_RATE) -> float:
    """Threshold (noise units) giving ``rate`` false maxima per pixel over all ``scales``.

    The density of local maxima above ``u`` of a smooth 2D Gaussian field is,
    for high ``u``, its Euler-characteristic density
    ``lambda u exp(-u^2 / 2) / (2 pi)^(3/2)``; summed over the scales (the
    finest dominates) and solved for ``u`` by bisection.
    """
    return threshold_for(tuple(_gradient_ratio(s) for s in scales), rate)


def threshold_for(lambdas, rate: float) -> float:
    """Level ``u`` (noise units) above which smooth Gaussian fields with gradient ratios ``lambdas`` (px^-2)
    have ``rate`` local maxima per pixel together: ``sum(lambda) u exp(-u^2/2) / (2 pi)^(3/2) = rate``."""
    lam = np.asarray(lambdas, float)
    if not 0 < rate < 1:
        raise UserError(f"false-alarm rate {rate} is outside (0, 1)", "give a rate such as 1e-6 per px")

    def dens(u):
        return float(np.sum(lam) * u * math.exp(-u * u / 2) / (2 * math.pi) ** 1.5)

    lo, hi = 1.0, 12.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if dens(mid) > rate:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _inverse_noise_rows(invs, h, w, r0, r1, out=None):
    """1 / noise of every scale at full resolution, rows ``r0:r1`` of an ``h x w`` frame (see
    :func:`_inverse_noise_into`), written into ``out`` (float64, shape (len(invs), r1 - r0, w)) when given."""
    if out is None:
        out = np.empty((len(invs), r1 - r0, w))
    _inverse_noise_into(invs, h, w, r0, r1, out)
    return out


@nb.njit(cache=True)
def _inverse_noise_into(invs, h, w, r0, r1, out):
    """1 / noise of every scale at full resolution, rows ``r0:r1`` of an ``h x w`` frame, into ``out``.

    Parameters
    ----------
    invs : tuple of 2D float32 arrays
        Tile grid of 1 / noise (1 / counts) of each scale.
    h, w : int
        Frame shape (px).
    r0, r1 : int
        Rows (px) to fill.
    out : 3D float64 array, shape (len(invs), r1 - r0, w)
        Filled with the grids interpolated bilinearly between tile centres (as cv2.resize INTER_LINEAR),
        1 / counts.
    """
    ns = len(invs)
    gwmax = 1
    for i in range(ns):
        gwmax = max(gwmax, invs[i].shape[1])
    x0 = np.empty(w, np.int64)
    x1 = np.empty(w, np.int64)
    wx = np.empty(w)
    rowv = np.empty(gwmax)
    for i in range(ns):
        gh, gw = invs[i].shape
        g = invs[i]
        fx = gw / w
        for c in range(w):
            xx = min(max((c + 0.5) * fx - 0.5, 0.0), gw - 1.0)
            x0[c] = min(int(xx), gw - 1)
            x1[c] = min(x0[c] + 1, gw - 1)
            wx[c] = xx - x0[c]
        for r in range(r0, r1):
            yy = min(max((r + 0.5) * gh / h - 0.5, 0.0), gh - 1.0)
            y0 = min(int(yy), gh - 1)
            y1 = min(y0 + 1, gh - 1)
            wy = yy - y0
            for j in range(gw):
                rowv[j] = (1 - wy) * g[y0, j] + wy * g[y1, j]
            o = out[i, r - r0]
            for c in range(w):
                o[c] = (1 - wx[c]) * rowv[x0[c]] + wx[c] * rowv[x1[c]]


@nb.njit(cache=True)
def _best_over_scales(b1s, b2s, ivs, r0, sign, best, best_neg, both):
    # z_i = sign (b1_i - b2_i) / noise_i for every scale i in one pass over rows r0:r0 + ivs.shape[1] of the
    # frame, keeping the best (no full-frame band-passed or SNR image is stored); ivs[i] is 1 / noise of scale
    # i at full resolution over those rows (_inverse_noise_rows). With `both`, the same pass also fills
    # best_neg: the map of the other sign, max_i(-z_i) = -min_i z_i (exact: negation does not round), for the
    # polarity vote. The scale index of the best is not kept here (tracking it made the pass ~1.8x slower):
    # _scale_at recomputes it at the few pixels that need it
    ns, nr, w = ivs.shape
    # in the precision of the inverse-noise maps: with float32 ones (the default), float32 throughout, twice the
    # values per vector instruction, and the same maps bit for bit: b1 - b2 is a float32 difference either way,
    # its product with a float32 1/noise is exact in float64, so float64 then rounding to the float32 map gives
    # the float32 product, and rounding commutes with max, min and negation
    sg = ivs.dtype.type(sign)
    bz = np.empty(w, ivs.dtype)
    mz = np.empty(w, ivs.dtype)
    for r in range(r0, r0 + nr):
        # scale by scale along the row (contiguous, branch-free inner loops)
        for i in range(ns):
            iv = ivs[i, r - r0]
            b1 = b1s[i][r]
            b2 = b2s[i][r]
            if i == 0:
                for c in range(w):
                    z = sg * (b1[c] - b2[c]) * iv[c]
                    bz[c] = z
                    mz[c] = z
            elif both:
                for c in range(w):
                    z = sg * (b1[c] - b2[c]) * iv[c]
                    bz[c] = max(bz[c], z)
                    mz[c] = min(mz[c], z)
            else:
                for c in range(w):
                    z = sg * (b1[c] - b2[c]) * iv[c]
                    bz[c] = max(bz[c], z)
        bo = best[r]
        for c in range(w):
            bo[c] = bz[c]
        if both:
            bn = best_neg[r]
            for c in range(w):
                bn[c] = -mz[c]


@nb.njit(cache=True)
def _scale_at(b1s, b2s, invs, h, w, sign, rows, cols):
    """Index of the scale whose SNR is the best (ties: the finer) at each pixel, the value
    :func:`_best_over_scales` keeps there.

    Parameters
    ----------
    b1s, b2s : tuples of 2D float32 arrays
        ``G(s) * frame`` and ``G(2 s) * frame`` per scale (counts).
    invs : tuple of 2D float32 arrays
        Tile grids of 1 / noise per scale (1 / counts), interpolated here at each pixel with the arithmetic of
        :func:`_inverse_noise_rows` (bit-identical).
    h, w : int
        Frame shape (px).
    sign : float
        Polarity.
    rows, cols : 1D int64 arrays
        Pixels.

    Returns
    -------
    1D int64 array
    """
    n = rows.shape[0]
    out = np.zeros(n, np.int64)
    best = np.full(n, -np.inf)
    for i in range(len(invs)):
        g = invs[i]
        gh, gw = g.shape
        fx = gw / w
        b1 = b1s[i]
        b2 = b2s[i]
        for k in range(n):
            r = rows[k]
            c = cols[k]
            yy = min(max((r + 0.5) * gh / h - 0.5, 0.0), gh - 1.0)
            y0 = min(int(yy), gh - 1)
            y1 = min(y0 + 1, gh - 1)
            wy = yy - y0
            xx = min(max((c + 0.5) * fx - 0.5, 0.0), gw - 1.0)
            x0 = min(int(xx), gw - 1)
            x1 = min(x0 + 1, gw - 1)
            wx = xx - x0
            v0 = (1 - wy) * g[y0, x0] + wy * g[y1, x0]
            v1 = (1 - wy) * g[y0, x1] + wy * g[y1, x1]
            iv = (1 - wx) * v0 + wx * v1
            z = sign * (b1[r, c] - b2[r, c]) * iv
            if z > best[k]:
                best[k] = z
                out[k] = i
    return out


@nb.njit(cache=True)
def _scale_at_full(b1s, b2s, ivs, sign, rows, cols):
    """:func:`_scale_at` from the full-size inverse-noise maps ``ivs`` (shape (scales, h, w)) that
    :func:`_best_over_scales` read: the index of the best scale (ties: the finer) at each pixel."""
    n = rows.shape[0]
    out = np.zeros(n, np.int64)
    best = np.full(n, -np.inf)
    for i in range(ivs.shape[0]):
        b1 = b1s[i]
        b2 = b2s[i]
        for k in range(n):
            r = rows[k]
            c = cols[k]
            z = sign * (b1[r, c] - b2[r, c]) * ivs[i, r, c]
            if z > best[k]:
                best[k] = z
                out[k] = i
    return out


@nb.njit(cache=True)
def _amp_at(b1s, b2s, sign, rows, cols):
    """The band-passed height ``sign (b1 - b2)`` (float32, as the frame's blurs) of every scale (rows of the
    result) at each pixel (columns): what indexing each pair of blurs at the pixels gives, in one pass."""
    n = rows.shape[0]
    out = np.empty((len(b1s), n), np.float32)
    for i in range(len(b1s)):
        b1 = b1s[i]
        b2 = b2s[i]
        for k in range(n):
            out[i, k] = (b1[rows[k], cols[k]] - b2[rows[k], cols[k]]) * sign
    return out


@nb.njit(cache=True)
def _ring_test(frame, bgmap, noise, sign, rows, cols, scale, out):
    # an image with a hole: the annulus 0.7 s .. 2.2 s is brighter (polarity applied) than the core
    # (<= 0.5 s) in every one of 8 sectors, beyond 3 noise standard errors, and no sector is below 40 %
    # of the brightest. Two neighbouring spots seen together at a coarse scale have a dip between
    # them too, but only two bright sectors; a ring has all eight.
    h, w = frame.shape
    # distance and sector of every integer offset (the same formulas as per pixel, computed once per call: the
    # atan2 and sqrt of each window pixel cost more than the test)
    hmax = 0
    for k in range(rows.shape[0]):
        hmax = max(hmax, int(math.ceil(2.2 * scale[k])) + 1)
    m = 2 * hmax + 1
    dist = np.empty((m, m))
    sect = np.empty((m, m), np.int64)
    for i in range(m):
        for j in range(m):
            dist[i, j] = math.sqrt((i - hmax) ** 2 + (j - hmax) ** 2)
            sect[i, j] = int((math.atan2(i - hmax, j - hmax) + math.pi) / (2 * math.pi) * 8) % 8
    sec = np.zeros(8)
    nsec = np.zeros(8)
    for k in range(rows.shape[0]):
        s = scale[k]
        r0 = rows[k]
        c0 = cols[k]
        half = int(math.ceil(2.2 * s)) + 1
        sec[:] = 0.0
        nsec[:] = 0.0
        core = 0.0
        ncore = 0
        for r in range(max(0, r0 - half), min(h, r0 + half + 1)):
            for c in range(max(0, c0 - half), min(w, c0 + half + 1)):
                d = dist[r - r0 + hmax, c - c0 + hmax]
                v = sign * (np.float32(frame[r, c]) - bgmap[r, c])     # (the frame's float32 value)
                if d <= max(0.5 * s, 1.0):
                    core += v
                    ncore += 1
                elif 0.7 * s <= d <= 2.2 * s:
                    a = sect[r - r0 + hmax, c - c0 + hmax]
                    sec[a] += v
                    nsec[a] += 1
        if ncore == 0 or nsec.min() == 0:
            out[k] = False
            continue
        core /= ncore
        lo = 1e300
        hi = -1e300
        for a in range(8):
            m = sec[a] / nsec[a]
            lo = min(lo, m)
            hi = max(hi, m)
        se = noise[r0, c0] / math.sqrt(nsec.min())
        out[k] = lo > core + 3.0 * se and lo > 0.4 * hi and hi > 0


@nb.njit(cache=True)
def _suppress(rows, cols, scale, order, radius_factor, min_radius, ring, reach):
    # greedy non-maximum suppression in order of decreasing SNR. Candidates of clearly different scales
    # (more than 1.5x, i.e. beyond the next rung) within radius_factor x the larger scale are one image:
    # a finer one is a piece of a coarse image (a ring's necklace), a coarser one the blend of finer
    # images (two spots seen as one large blob). Of similar scales, both are kept unless closer than half
    # the FWHM (1.18 scale), where two spots merge into one maximum anyway (two spots 3-4 px apart must
    # both be kept, or D is biased low at close approach). A ring found by the rim's vote (reach > 0: its
    # radius + rim) holds everything within its reach, of any scale
    # (the kept ones are binned on a grid of cells no smaller than the largest radius any pair can get, so
    # only the 3 x 3 cells around a candidate are searched: same result as the search over all kept ones)
    n = rows.shape[0]
    keep = np.zeros(n, np.bool_)
    if n == 0:
        return keep
    smax = 0.0
    rmax = 0.0
    for i in range(n):
        smax = max(smax, scale[i])
        rmax = max(rmax, reach[i])
    big = max(rmax, 2.0 * rmax - 4.0, radius_factor * smax, 1.18 * smax, min_radius)
    cs = max(1, int(math.ceil(big)))
    gh = int(rows.max()) // cs + 1
    gw = int(cols.max()) // cs + 1
    head = np.full(gh * gw, -1, np.int64)
    nxt = np.empty(n, np.int64)
    for a in range(n):
        i = order[a]
        ok = True
        ci = rows[i] // cs
        cj = cols[i] // cs
        for gi in range(max(ci - 1, 0), min(ci + 2, gh)):
            for gj in range(max(cj - 1, 0), min(cj + 2, gw)):
                j = head[gi * gw + gj]
                while j >= 0 and ok:
                    lo = min(scale[i], scale[j])
                    hi = max(scale[i], scale[j])
                    if reach[j] > 0 and reach[i] > 0:
                        # two rings of the rim's vote whose circles overlap share the rim's votes: the weaker is
                        # dropped (reach = radius + 2.5 px: centres closer than the sum of the radii + 1 px)
                        rad = max(reach[j], reach[i] + reach[j] - 4.0)
                    elif reach[j] > 0:
                        rad = reach[j]                  # a ring found by the rim's vote: anything inside it is the ring
                    elif reach[i] > 0 and ring[j]:
                        rad = reach[i]                  # ... and it is the same image as a kept ring inside it
                    elif ring[j] and scale[i] <= scale[j]:
                        rad = max(radius_factor * scale[j], min_radius)     # anything inside a kept ring is the ring
                    elif hi > 1.5 * lo:
                        rad = max(radius_factor * hi, min_radius)
                    else:
                        rad = max(1.18 * hi, min_radius)
                    dr = rows[i] - rows[j]
                    dc = cols[i] - cols[j]
                    if dr * dr + dc * dc < rad * rad:
                        ok = False
                    j = nxt[j]
        if ok:
            keep[i] = True
            cell = ci * gw + cj
            nxt[i] = head[cell]
            head[cell] = i
    return keep


def detect(frame, scales=None, polarity: int | None = None, snr: float | None = None,
           rate: float = FALSE_ALARM_RATE, median: bool = True, tile: int = 32, edge: int = 2,
           suppress: float = 2.0, offset: float = 0.0, cache: dict | None = None, rings: bool = True):
    """Detect particles of several sizes without tuning knobs.

    Parameters
    ----------
    frame : 2D array
        Raw frame (any polarity, camera counts).
    scales : sequence of float, optional
        Spot widths (Gaussian sigma, px) searched; default :data:`DEFAULT_SCALES`.
    polarity : {+1, -1}, optional
        Bright (+1) or dark (-1) particles; decided from the data if None.
    snr : float, optional
        Threshold in local noise units; default from ``rate``
        (:func:`false_alarm_threshold`).
    rate : float
        False detections per pixel of an empty frame (default 1e-6).
    median : bool
        3x3 median first (hot pixels, salt noise).
    tile : int
        Noise-map tile (px, default 32); at least 12x the scale (and at most ~256 tiles
        per frame). Illumination varies slowly on this scale; a finer map
        only adds sampling scatter to the noise estimate.
    edge : int
        Ignore maxima closer than this to the border (px).
    suppress : float
        A weaker candidate of a clearly different scale (> 1.5x) within
        ``suppress`` x the larger scale is part of the same image.
    offset : float
        Camera baseline (counts): the skewness correction of the threshold
        needs the background above it.
    cache : dict, optional
        A movie's frames share their noise and background maps (camera and
        illumination): pass the same (initially empty) dict for every frame
        and the maps are measured on one frame and reused for the next
        :data:`MAP_REFRESH` - 1, and measured again sooner when the frame's
        background level (median of a 1/64 sub-sample) moves by more than 3
        of its standard errors + 1 %. The ring maps' noise grids and the blob scales' full-size
        inverse-noise maps (frames up to ~0.4 Mpx) are kept
        there too, with the same lifetime.
    rings : bool
        Also look for ring centres by the rim's vote (:mod:`ptrack.image.rings`)
        when the candidates say the frame holds rings (default; False: blobs only).

    Returns
    -------
    dict
        ``rows``, ``cols`` (int px), ``scale`` (px, the particle's size: scale of the largest band-passed response),
        ``snr`` (best response, noise units), ``signal`` (band-passed height,
        counts, polarity applied), ``polarity`` (+1/-1), ``threshold`` (u),
        ``noise`` (median local noise of the finest scale, counts),
        ``ring`` (bool: an image with a hole, e.g. a defocused ring, or a
        ring found by the rim's vote, whose ``scale`` is then 0.4 x its radius
        and ``snr``, ``signal`` those of its circle mean),
        ``scales``, ``background_map`` and ``noise_map`` (the frame's local
        median and noise, counts, full size), ``noise_map_median`` (the
        median of ``noise_map`` over every 4th pixel of each axis, counts).
    """
    import cv2

    scales = tuple(float(s) for s in (DEFAULT_SCALES if scales is None else scales))
    if not scales or min(scales) <= 0:
        raise UserError(f"scales {scales} must be positive", "give spot widths in px")
    u = false_alarm_threshold(scales, float(rate)) if snr is None else float(snr)
    frame = np.asarray(frame)
    if not frame.dtype.isnative:
        # (a big-endian frame, as a TIFF may hold it: the same values in the machine's byte order, which the
        # numba kernels and cv2 read)
        frame = frame.astype(frame.dtype.newbyteorder("="))
    pool = cache.setdefault("blur_pool", {}) if cache is not None else None
    if pool is not None and "owned" not in pool and _RECYCLE_BYTES > 0:
        pool["owned"] = _Owned()
    # the frame as float32, made when first needed (the maps and the ring maps read it): an 8/16-bit frame whose
    # maps come from the cache and that holds no rings never needs it (its copy cost ~40 us per 640 x 424 frame)
    # (with a cache, into its scratch array: the same values as ascontiguousarray's and astype's conversions)
    made = []

    def frame32():
        if not made:
            f = np.ascontiguousarray(frame) if frame.dtype == np.float32 else None
            if f is None or f is not frame:
                f = scratch(cache, "f32", np.shape(frame), np.float32)
                np.copyto(f, frame, casting="unsafe")
            made.append(f)
        return made[0]

    native = frame.dtype in (np.uint8, np.uint16) and frame.ndim == 2
    if median and native:
        # the 3x3 median of 8/16-bit frames by cv2's integer kernel (2x faster than its float32 one), then
        # float32: the same values (a median selects one of its nine, and the integers are exact in float32)
        m8 = cv2.medianBlur(np.ascontiguousarray(frame), 3, dst=scratch(cache, "median", frame.shape, frame.dtype))
        work = scratch(cache, "work", frame.shape, np.float32)
        np.copyto(work, m8)
    elif median:
        work = cv2.medianBlur(frame32(), 3, dst=scratch(cache, "work", np.shape(frame), np.float32))
    else:
        work = frame32()
    H, W = work.shape
    ladder = sorted(set(scales) | {_SURROUND * x for x in scales})
    # (with a cache, into the arrays of the previous frame: nothing keeps the blurs beyond this call)
    blurs = dict(zip(ladder, _blur_ladder(work, ladder, pool)))
    # the noise and background maps describe the camera and the illumination, which a movie keeps from
    # frame to frame: with a cache they are measured on one frame and reused for the next ones (see
    # MAP_REFRESH), unless the frame's background level has moved
    key = (H, W, scales, int(tile), bool(median))
    level = fast_median(work[::8, ::8])
    c = cache if cache is not None else {}
    fresh = (c.get("key") != key or c.get("age", MAP_REFRESH) >= MAP_REFRESH
             or abs(level - c["level"]) > 3.0 * c["level_noise"] + 0.01 * abs(c["level"]))
    if fresh:
        noise0 = None
        invs = []
        for s in scales:
            # tiles hold ~150 correlation areas of the band-passed noise (side 12 s): a MAD from fewer
            # independent samples scatters by several per cent, which multiplies the false-alarm rate
            # (and, on large frames, at most ~256 tiles); ~600-1000 samples per tile fix the MAD to ~3 %
            t_side = max(int(tile), int(12 * s), int(math.sqrt(H * W / 256.0)))
            # ~256 samples per tile and ~64k per scale (the 3x3 tile smoothing brings the MAD to ~2.5 %), and no
            # closer than _MAP_STRIDE_S x the scale (the band-passed noise's correlation length)
            st = max(1, t_side // 16, int(math.sqrt(H * W / 65536.0)), int(round(_MAP_STRIDE_S * s)))
            # the band-pass has no response to a constant: its background is zero, only the noise is
            # mapped, from the sub-sampled band-passed image
            bsub = blurs[s][::st, ::st] - blurs[_SURROUND * s][::st, ::st]
            inv = noise_maps(bsub, tile=t_side, step=st, what="grid", shape=(H, W))
            if noise0 is None:
                noise0 = float(1.0 / np.float32(fast_median(inv)))
            invs.append(inv)
        # background and noise of the frame itself (the skew correction; the localiser's background)
        # (with a cache, into arrays it owns; the previous maps go to the free list, taken again once no caller
        # holds them: a frame's detect result returns them)
        owned = pool.get("owned") if pool is not None else None
        if owned is not None and c.get("rb") is not None:
            owned.give(c["rb"], c["rn"])
        rb, rn = noise_maps(frame32(), tile=max(int(tile), int(math.sqrt(H * W / 256.0))), step=2,
                            out=None if owned is None else (owned.take((H, W), np.float32),
                                                            owned.take((H, W), np.float32)))
        # the median of the frame's noise map (a full-frame median: measured once per map, for the level test
        # below and the localiser, see the returned noise_map_median), over every _RN_MEDIAN_STEP-th pixel
        # of each axis: the map is bilinear between tile centres >= 32 px apart, so the sub-sample's median is
        # the full one's to ~1e-4 (a full-frame median costs 2.5 ms on 640 x 424, 40 ms on 2048^2)
        rn_median = fast_median(rn[::_RN_MEDIAN_STEP, ::_RN_MEDIAN_STEP])
        if cache is not None:
            cache.clear()
            cache.update(blur_pool=pool, key=key, age=0, level=level, level_noise=1.25 * rn_median / math.sqrt(work[::8, ::8].size),
                         invs=tuple(invs), noise0=noise0, rb=rb, rn=rn, rn_median=rn_median)
    else:
        invs, noise0, rb, rn, rn_median = c["invs"], c["noise0"], c["rb"], c["rn"], c["rn_median"]
    if cache is not None:
        cache["age"] = cache.get("age", 0) + 1

    b1s = tuple(np.ascontiguousarray(blurs[s], np.float32) for s in scales)
    b2s = tuple(np.ascontiguousarray(blurs[_SURROUND * s], np.float32) for s in scales)
    invs = tuple(invs)

    # the full-size inverse-noise maps change only with the tile grids: interpolated once per map
    # measurement and kept in the cache (float64, as the row-by-row interpolation gave them); on frames
    # too large for that (> _FULL_IVS_BYTES) they are interpolated in blocks of rows for each map
    ivs = c.get("ivs_full") if not fresh else None
    if ivs is None and len(scales) * H * W * 4 <= _FULL_IVS_BYTES:
        # with a cache, into the array of the previous map (kept across refreshes, see _POOL_IVS)
        dt = np.float32 if _IVS32 else np.float64
        buf = pool.get("ivs") if pool is not None and _POOL_IVS else None
        if buf is None or buf.shape != (len(scales), H, W) or buf.dtype != dt:
            owned = pool.get("owned") if pool is not None else None
            buf = owned.take((len(scales), H, W), dt) if owned is not None else np.empty((len(scales), H, W), dt)
        if _IVS32:
            # cv2's bilinear interpolation between tile centres (the geometry of _inverse_noise_rows), float32
            for i, g in enumerate(invs):
                cv2.resize(g, (W, H), dst=buf[i], interpolation=cv2.INTER_LINEAR)
            ivs = buf
        else:
            ivs = _inverse_noise_rows(invs, H, W, 0, H, buf)
        if cache is not None:
            cache["ivs_full"] = ivs
            if _POOL_IVS:
                pool["ivs"] = ivs
    def best_maps(sign, both):
        # the SNR map maximised over scale (and its scale index) of one sign, and with `both` of the other
        # sign too, from the same pass (the polarity vote)
        n = (H, W) if both else (1, 1)       # the other sign's map: unused without `both`
        out = [scratch(cache, "best", (H, W), np.float32), scratch(cache, "best_other", n, np.float32)]
        if ivs is not None:
            _best_over_scales(b1s, b2s, ivs, 0, float(sign), *out, both)
        else:
            block = max(1, _IVS_BLOCK_BYTES // (len(scales) * W * 8))
            for r0 in range(0, H, block):
                _best_over_scales(b1s, b2s, _inverse_noise_rows(invs, H, W, r0, min(H, r0 + block)), r0,
                                  float(sign), *out, both)
        return {sign: out[0], -sign: out[1]} if both else {sign: out[0]}

    maxima = {}
    if polarity is None:
        # the side whose significant maxima carry more summed excess SNR, sum(z - u), wins; both maps from
        # one pass, the winner's is the detection map
        maps = best_maps(1, True)
        score = []
        for sign in (1, -1):
            bm = maps[sign]
            r, c = local_maxima(bm, float(u), 1, False)
            maxima[sign] = r, c
            score.append(float(np.sum(bm[maxima[sign]] - u)) if len(r) else 0.0)
        polarity = 1 if score[0] >= score[1] else -1
    else:
        polarity = 1 if polarity >= 0 else -1
        maps = best_maps(polarity, False)
    best = maps[polarity]
    if polarity in maxima and int(edge) >= 1:
        # a pixel's maximum test reads only its 8 neighbours: the maxima away from a wider edge are those of
        # the vote (edge 1) inside it, in the same (raster) order
        rows, cols = maxima[polarity]
        e = int(edge)
        inside = (rows >= e) & (rows < H - e) & (cols >= e) & (cols < W - e)
        rows, cols = rows[inside], cols[inside]
    else:
        rows, cols = local_maxima(best, float(u), int(edge), False)
    # the scale index of each candidate's best SNR, from the inverse-noise values the best-over-scales pass used
    kk = _scale_at_full(b1s, b2s, ivs, float(polarity), rows, cols) if ivs is not None else \
        _scale_at(b1s, b2s, invs, H, W, float(polarity), rows, cols)
    z = best[rows, cols].astype(np.float64)
    if polarity > 0 and len(rows):
        # Poisson (and sCMOS) noise is skewed to the bright side: at a low background the Gaussian
        # threshold lets several times the stated rate through. A Cornish-Fisher shift u + g (u^2 - 1) / 6
        # with the band-passed skewness g = skew_factor(s) / sqrt(background photons); the photons
        # follow from the local mean and variance of the raw frame (mean / noise^2 = photons per count
        # for Poisson), so no camera calibration is needed. Read noise only lowers the estimate (safe side).
        lev = np.maximum(rb[rows, cols] - float(offset), 1e-6)
        g_pix = np.clip(rn[rows, cols] / lev, 0.0, 2.0)          # 1 / sqrt(photons)
        g = np.array([skew_factor(s) for s in scales])[kk] * g_pix
        z_ok = z > u + g * (u * u - 1.0) / 6.0
        rows, cols, kk, z = rows[z_ok], cols[z_ok], kk[z_ok], z[z_ok]
    # size of each particle: the scale of the largest band-passed response (the DoG with a fixed ratio
    # is scale-normalised, so its response to a Gaussian spot of width a peaks near s = a), not the
    # scale of the best SNR (which favours fine scales when the background has coarse structure)
    amp = _amp_at(b1s, b2s, np.float32(polarity), rows, cols) if len(rows) else np.zeros((len(scales), 0))
    size_k = np.argmax(amp, axis=0) if len(rows) else np.zeros(0, int)
    sc = np.asarray(scales)[size_k]
    ring = np.zeros(len(rows), np.bool_)
    coarse = np.nonzero(sc >= 2.0)[0]
    if len(coarse):
        rflag = np.zeros(len(coarse), np.bool_)
        # (an 8/16-bit frame as it is, read as float32 values; any other as its float32 copy)
        _ring_test(np.ascontiguousarray(frame) if native else frame32(), rb, rn, float(polarity), rows[coarse],
                   cols[coarse], sc[coarse].astype(np.float64), rflag)
        ring[coarse] = rflag
    sig = amp[kk, np.arange(len(rows))] if len(rows) else np.zeros(0)
    reach = np.zeros(len(rows))     # ring-map candidates: radius (px) within which anything is the ring (0: others)
    if rings and len(rows) >= 3:
        # rings: a centre vote from the rim (ptrack.image.rings), computed where the blob candidates say the
        # frame holds rings (rim pieces are ridges, faint centres sit in rings of the opposite sign)
        if ring_evidence(b1s, b2s, float(polarity), frame, rb, rn, rows, cols, kk):
            J = polarity * (frame32() - rb)
            need = sorted({ring_scale(R, scales) for R in RING_RADII})
            bands = {s: (blurs[s] - blurs[_SURROUND * s]) * np.float32(polarity) for s in need}
            rc = ring_maps_candidates(bands, J, rn, RING_RATE_SHARE * float(rate), scales, edge=int(edge),
                                      tile=int(tile), noise_cache=cache)
            m = len(rc["rows"])
            if m:
                rows, cols = np.r_[rows, rc["rows"]], np.r_[cols, rc["cols"]]
                # the ring's size as a blob scale (the localiser's windows are ~3 scales), and its reach: the
                # radius plus the rim's width
                sc = np.r_[sc, RING_SCALE_PER_RADIUS * rc["radius"]]
                reach = np.r_[reach, rc["radius"] + 2.5]
                z, sig = np.r_[z, rc["snr"]], np.r_[sig, np.abs(rc["signal"])]
                kk = np.r_[kk, np.zeros(m, kk.dtype)]
                ring = np.r_[ring, np.ones(m, np.bool_)]
    if len(rows) > 1:
        # rings first (their necklace of fine-scale maxima is often stronger than the ring's own response),
        # then by decreasing SNR
        order = np.lexsort((-z, ~ring)).astype(np.int64)
        keep = _suppress(rows, cols, sc.astype(np.float64), order, float(suppress), 1.5, ring, reach.astype(np.float64))
        rows, cols, sc, z, kk, sig, ring = rows[keep], cols[keep], sc[keep], z[keep], kk[keep], sig[keep], ring[keep]
    return {"rows": rows, "cols": cols, "scale": sc, "snr": z, "signal": np.asarray(sig, np.float64),
            "polarity": polarity, "threshold": float(u), "noise": float(noise0), "scales": scales,
            "background_map": rb, "noise_map": rn, "noise_map_median": rn_median, "ring": ring}
