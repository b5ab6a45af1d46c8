"""Ring detection: a centre vote from the rim, for images that are rings rather than blobs.

A defocused fluorescent bead is a disk with a bright rim; a defocused
brightfield particle is a bright centre in a dark ring (or the reverse). The
blob detector of :mod:`ptrack.image.detect` finds such a ring, if at all, as
a necklace of fine-scale maxima on the rim, or misses a faint centre whose
energy is mostly in its ring. Here every pixel of a candidate rim votes for
the point at the ring's radius ``R`` from it, in every direction: the
band-passed image ``B_s = G(s) - G(2 s)`` (the detector's own band) is
averaged around the circle of radius ``R`` about each pixel,

    ``S_R(c) = mean_theta B_s(c + R (cos theta, sin theta))``,

a linear, matched statistic of a thin ring (the circle's samples are
nearest pixels, one per px of arc). At a ring's centre the whole rim adds up
coherently, in noise units ``sqrt(2 pi R / correlation length)`` times more
than one piece of it; both signs are searched (a bright rim, ``S > 0``; a
ring darker than the surroundings, ``S < 0``, such as the dark ring around
a brightfield particle's bright centre). Radii form a ``2^(1/3)`` ladder
(:data:`RING_RADII`, 4-12.7 px).

Each map is divided by its own local noise (1.4826 MAD over tiles, as the
blob scales) and thresholded at a false-alarm rate from the Euler
characteristic density of its discrete kernel (:func:`ring_threshold`); the
map is evaluated on a 2-px grid, and its maxima refined on the full grid. A
candidate is kept only if the ring is there all round: each of 8 sectors of
the annulus at ``R``, in the background-subtracted frame, differs from the
level just outside the ring with the ring's sign, and the weakest sector
holds at least a quarter of the strongest (one bright spot, or a pair, at
distance ``R`` from a point covers one or two sectors; a Gaussian spot's
band-pass surround is not a ring of the frame).

The maps cost ~1 ms per 10^5 px per radius; :func:`ring_evidence` tells
from the blob candidates whether a frame needs them at all (rim pieces are
ridges, faint centres sit in rings of the opposite sign).
"""
from __future__ import annotations

import functools
import math

import numba as nb
import numpy as np

from .peaks import local_maxima
from .radial import _as_n

__all__ = ["RING_RADII", "ring_scale", "ring_threshold", "ring_maps_candidates", "ring_evidence",
           "ring_support"]

#: Ring radii searched (px): a 2^(1/3) ladder (a ring between two rungs keeps >= 80 % of its response).
RING_RADII = (4.0, 5.04, 6.35, 8.0, 10.08, 12.7)
# grid step (px) on which the maps are evaluated before the maxima are refined on the full grid
_STRIDE = 2


def ring_scale(R: float, scales) -> float:
    """Band-pass scale (px) used for rings of radius ``R``: the detector scale nearest ``R / 5``, at most 2 px.

    Rims are thin (a defocused disk's edge is about as sharp as the focused spot); a broad ring
    (brightfield J0 rings widen with the radius) is still matched within ~20 % at ``R / 5``.
    """
    sc = np.asarray(sorted(scales), float)
    sc = sc[sc <= 2.0] if np.any(sc <= 2.0) else sc[:1]
    return float(sc[np.argmin(np.abs(sc - R / 5.0))])


@functools.lru_cache(maxsize=64)
def _taps(R: float):
    # the circle of radius R as pixel offsets (dr, dc) and weights: one sample per px of arc, at the nearest
    # pixel (the bands are smooth on the scale of a pixel; a bilinear circle costs 2.2x the taps for the same
    # maps within 2 %); weights sum to 1
    n = max(16, int(math.ceil(2 * math.pi * R)))
    t = np.arange(n) * (2 * math.pi / n)
    off = np.unique(np.c_[np.round(R * np.sin(t)), np.round(R * np.cos(t))].astype(np.int64), axis=0, return_counts=True)
    (dr, dc), cnt = off[0].T, off[1]
    return (np.ascontiguousarray(dr), np.ascontiguousarray(dc), (cnt / cnt.sum()).astype(np.float32))


@nb.njit(cache=True)
def _circle_grid(P, h, w, dr, dc, wt, edge, out):
    # out[i, j] = sum_t wt[t] B[2 i + dr[t], 2 j + dc[t]]; 0 within `edge` px of the border. B is given by its
    # 4 polyphase components P[2 a + b] = B[a::2, b::2] (zero-padded), so that every tap reads one row of one
    # component contiguously (the inner loop vectorises)
    gh, gw = out.shape
    nt = dr.shape[0]
    j0 = (edge + 1) // 2
    j1 = (w - edge - 1) // 2               # last grid column with 2 j < w - edge
    for i in range(gh):
        r = 2 * i
        for j in range(gw):
            out[i, j] = 0.0
        if r < edge or r >= h - edge or j1 < j0:
            continue
        for t in range(nt):
            a = dr[t] & 1
            b = dc[t] & 1
            row = P[2 * a + b, i + (dr[t] >> 1)]
            sh = dc[t] >> 1
            wv = wt[t]
            for j in range(j0, j1 + 1):
                out[i, j] += wv * row[j + sh]


def _polyphase(B):
    """The 4 polyphase components of a frame, ``P[2 a + b] = B[a::2, b::2]``, zero-padded to one shape."""
    H, W = B.shape
    P = np.zeros((4, (H + 1) // 2, (W + 1) // 2), np.float32)
    for a in range(2):
        for b in range(2):
            c = B[a::2, b::2]
            P[2 * a + b, :c.shape[0], :c.shape[1]] = c
    return P


@nb.njit(cache=True)
def _circle_at(B, dr, dc, wt, r, c):
    s = 0.0
    for t in range(dr.shape[0]):
        s += wt[t] * B[r + dr[t], c + dc[t]]
    return s


@nb.njit(cache=True)
def _refine(B, dr, dc, wt, edge, stride, gi, gj, sgn, inv, rows, cols, snr, sig, idx):
    # per grid maximum m: the best (sign applied, noise units) of the circle means at the 3x3 full-grid pixels
    # around it; written to rows, cols, snr, sig at idx[m]
    h, w = B.shape
    for m in range(gi.shape[0]):
        bz = -np.inf
        for r in range(gi[m] * stride - 1, gi[m] * stride + 2):
            for c in range(gj[m] * stride - 1, gj[m] * stride + 2):
                if r < edge or c < edge or r >= h - edge or c >= w - edge:
                    continue
                v = _circle_at(B, dr, dc, wt, r, c)
                if sgn[m] * v * inv[m] > bz:
                    bz = sgn[m] * v * inv[m]
                    rows[idx[m]] = r
                    cols[idx[m]] = c
                    sig[idx[m]] = v
        snr[idx[m]] = bz


@nb.njit(cache=True)
def _sectors(J, rows, cols, radius, width, sign, noise, out):
    # the ring all round: 8 sectors of the annulus |d - R| <= width, in J (background-subtracted, particles
    # positive), each differ from the (median) level of the annulus just outside (R + width + 1 .. + 4 px) with the
    # ring's sign by more than half a standard error, the rim (the strongest 1 px annulus of the band) differs so
    # from the mean inside the ring (d < R - width - 1) by 3 standard errors (a ring is a ring around something,
    # not a circle through the gap between other images), and the weakest sector holds >= 1/4 of the strongest
    h, w = J.shape
    for k in range(rows.shape[0]):
        R = radius[k]
        wd = width[k]
        r0 = rows[k]
        c0 = cols[k]
        ro = R + wd + 4.0
        half = int(math.ceil(ro)) + 1
        sec = np.zeros(8)
        nsec = np.zeros(8)
        buf = np.empty((2 * half + 1) ** 2)
        nb_ = int(2 * wd) + 1
        asum = np.zeros(nb_)
        acnt = np.zeros(nb_)
        nref = 0
        inner = 0.0
        ninner = 0
        if r0 - half < 0 or c0 - half < 0 or r0 + half >= h or c0 + half >= w:
            out[k] = False
            continue
        for r in range(r0 - half, r0 + half + 1):
            for c in range(c0 - half, c0 + half + 1):
                d = math.sqrt((r - r0) ** 2 + (c - c0) ** 2)
                if abs(d - R) <= wd:
                    a = int((math.atan2(r - r0, c - c0) + math.pi) / (2 * math.pi) * 8) % 8
                    sec[a] += J[r, c]
                    nsec[a] += 1
                    b = min(int(d - (R - wd)), nb_ - 1)
                    asum[b] += J[r, c]
                    acnt[b] += 1
                elif R + wd + 1.0 < d <= ro:
                    buf[nref] = J[r, c]
                    nref += 1
                elif d < R - wd - 1.0:
                    inner += J[r, c]
                    ninner += 1
        if nref == 0 or nsec.min() == 0:
            out[k] = False
            continue
        # the outside level: a median, so that a neighbour's image in a part of the outer annulus does not set it
        ref = np.median(buf[:nref])
        if ninner > 0:
            inner /= ninner
        lo = 1e300
        hi = -1e300
        ok = True
        for a in range(8):
            m = sec[a] / nsec[a]
            v = sign[k] * (m - ref)
            if v <= 0.5 * noise[k] / math.sqrt(nsec[a]):
                ok = False
            lo = min(lo, v)
            hi = max(hi, v)
        # the rim (the strongest 1 px annulus of the band) against the inside
        if ninner > 0:
            best = -1e300
            for b in range(nb_):
                if acnt[b] > 0:
                    v = sign[k] * (asum[b] / acnt[b] - inner) / (noise[k] * math.sqrt(1.0 / acnt[b] + 1.0 / ninner))
                    best = max(best, v)
            if best <= 3.0:
                ok = False
        out[k] = ok and lo >= 0.25 * hi


def ring_support(J, rows, cols, radius, width, sign, noise):
    """Whether a ring of radius ``radius`` (px) and sign ``sign`` surrounds each pixel, all round.

    Parameters
    ----------
    J : 2D array
        Background-subtracted frame, particles positive (counts).
    rows, cols : array_like of int
        Candidate centres.
    radius, width : array_like of float
        Ring radius and the half-width of the annulus tested (px).
    sign : array_like of float
        +1: the ring is brighter (in ``J``) than the level just outside it; -1: darker.
    noise : array_like of float
        Per-pixel noise of ``J`` at each candidate (counts rms).

    Returns
    -------
    ndarray of bool
        Every one of 8 sectors differs from the outside level with the ring's
        sign by more than half a standard error, and the weakest holds at
        least a quarter of the strongest.
    """
    n = len(np.atleast_1d(rows))
    b = lambda v, t: _as_n(v, n, t)
    out = np.zeros(n, np.bool_)
    if n:
        _sectors(np.ascontiguousarray(J, np.float32), b(rows, np.int64), b(cols, np.int64), b(radius, np.float64),
                 b(width, np.float64), b(sign, np.float64), b(noise, np.float64), out)
    return out


@functools.lru_cache(maxsize=64)
def ring_lambda(R: float, s: float) -> float:
    """lambda = Var(d S / d x) / Var(S) of the ring map of radius ``R`` on the band of scale ``s``, white noise (px^-2)."""
    import cv2

    from .detect import _kernel

    k = _kernel(s).astype(np.float32)
    dr, dc, wt = _taps(float(R))
    h = int(math.ceil(R)) + 2
    circ = np.zeros((2 * h + 1, 2 * h + 1), np.float32)
    circ[dr + h, dc + h] = wt
    pad = np.pad(k, h)
    full = cv2.filter2D(pad, -1, circ[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT).astype(np.float64)
    gx = np.diff(full, axis=1)
    return float((gx ** 2).sum() / (full ** 2).sum())


@functools.lru_cache(maxsize=64)
def ring_threshold(pairs, rate: float) -> float:
    """Threshold (noise units) of the ring maps: ``rate`` false maxima per pixel over all (radius, scale) ``pairs``, both signs.

    The Euler-characteristic density of a smooth Gaussian field (see
    :func:`ptrack.image.detect.false_alarm_threshold`) with each map's own
    ``lambda`` (:func:`ring_lambda`); both signs double the density.
    """
    from .detect import threshold_for

    return threshold_for(tuple(2.0 * ring_lambda(R, s) for R, s in pairs), rate)


def ring_maps_candidates(bands, J, noise_pix, rate: float, scales, radii=RING_RADII, edge: int = 2,
                         tile: int = 32, noise_cache: dict | None = None):
    """Ring centres of a frame: maxima of the circle-averaged band-pass maps that pass the all-round test.

    Parameters
    ----------
    bands : dict
        Band-passed frames ``{s: G(s) - G(2 s)}`` (float32, counts, polarity
        applied: particles positive) for the scales in ``scales``.
    J : 2D array
        Background-subtracted frame, particles positive (counts).
    noise_pix : 2D array
        Per-pixel noise map of the frame (counts rms).
    rate : float
        False maxima per pixel allowed to the ring maps together.
    scales : tuple of float
        Scales of ``bands``.
    radii : sequence of float
        Ring radii (px), default :data:`RING_RADII`.
    edge : int
        Border (px) beyond a ring's radius where no centre is sought.
    tile : int
        Smallest noise-map tile (px).
    noise_cache : dict, optional
        The maps' noise grids follow the camera and the illumination, as the
        blob scales' do: given a dict (the detector's cache, cleared when its
        maps are measured again), they are stored in it on the first frame and
        reused on the next ones of the same shape, radii and scales.

    Returns
    -------
    dict
        ``rows``, ``cols`` (int px), ``radius`` (px), ``snr`` (noise units,
        positive), ``sign`` (+1 bright rim, -1 dark ring), ``signal`` (circle
        mean of the band, counts), ``threshold``.
    """
    import cv2

    from .detect import noise_maps

    H, W = J.shape
    pairs = tuple((float(R), ring_scale(R, scales)) for R in radii)
    u = ring_threshold(pairs, float(rate))
    gh, gw = (H + _STRIDE - 1) // _STRIDE, (W + _STRIDE - 1) // _STRIDE
    best = np.zeros((gh, gw), np.float32)
    arg = np.zeros((gh, gw), np.int8)
    ckey = ("ring_invs", H, W, pairs, int(tile))
    cached = noise_cache.get(ckey) if noise_cache is not None else None
    invs = [] if cached is None else list(cached)
    poly = {s: _polyphase(bands[s]) for s in {s for _, s in pairs}}
    for k, (R, s) in enumerate(pairs):
        dr, dc, wt = _taps(R)
        g = np.empty((gh, gw), np.float32)
        e = int(math.ceil(R)) + 1 + edge
        _circle_grid(poly[s], H, W, dr, dc, wt, e, g)
        if cached is None:
            # the map's noise over tiles holding ~100 of its correlation areas (side >= 12 R)
            t_side = max(int(tile), int(12 * R), int(math.sqrt(H * W / 64.0)))
            # (every other grid point: the map is smooth over a few px, ~1000 samples per tile remain)
            grid = noise_maps(np.ascontiguousarray(g[::2, ::2]), tile=t_side, step=2 * _STRIDE, what="grid",
                              shape=(H, W))
            invs.append(np.full((gh, gw), grid[0, 0], np.float32) if grid.size == 1
                        else cv2.resize(grid, (gw, gh), interpolation=cv2.INTER_LINEAR))
        inv = invs[k]
        z = g * inv
        better = np.abs(z) > np.abs(best)
        best[better] = z[better]
        arg[better] = k
    if noise_cache is not None and cached is None:
        noise_cache[ckey] = tuple(invs)
    gi, gj = local_maxima(best, float(0.8 * u), 1, True)  # bright and dark rings in one pass (int64 arrays)
    ka = arg[gi, gj].astype(np.int64)
    rows = np.zeros(len(gi), np.int64)
    cols = np.zeros(len(gi), np.int64)
    snr = np.full(len(gi), -np.inf)
    sig = np.zeros(len(gi))
    sgn = np.where(best[gi, gj] > 0, 1.0, -1.0)
    for k, (R, s) in enumerate(pairs):
        # refine on the full grid, radius by radius: the best of the 3x3 pixels around each grid maximum
        q = np.nonzero(ka == k)[0]
        if len(q):
            dr, dc, wt = _taps(R)
            _refine(bands[s], dr, dc, wt, int(math.ceil(R)) + 1 + edge, _STRIDE, gi[q], gj[q], sgn[q],
                    invs[k][gi[q], gj[q]].astype(np.float64), rows, cols, snr, sig, q)
    hit = snr > u
    rows, cols, snr, sig, sgn, ka = rows[hit], cols[hit], snr[hit], sig[hit], sgn[hit], ka[hit]
    rad = np.array([R for R, _ in pairs])[ka]
    # the annulus tested: the rim's width at its band's scale, plus half a rung of the radius ladder
    width = np.array([max(1.0, 1.2 * s) + 0.13 * R for R, s in pairs])[ka]
    ok = ring_support(J, rows, cols, rad, width, sgn, noise_pix[rows, cols]) if len(rows) else np.zeros(0, bool)
    return {"rows": rows[ok], "cols": cols[ok], "radius": rad[ok], "snr": snr[ok], "sign": sgn[ok],
            "signal": sig[ok], "threshold": float(u)}


@nb.njit(cache=True)
def _ridge(b1s, b2s, sign, rows, cols, kk, out):
    # Hessian of B = sign (b1 - b2) at each maximum (3x3 central differences), at the candidate's own scale kk
    # (b1s[kk], b2s[kk]): ridge-like when the weaker curvature is below half the stronger (a piece of a rim:
    # measured median 0.3-0.4 on 9 px rings); a spot's maximum is round (0.8-0.96 measured on Airy spots,
    # brightfield blobs and 6 px disks). Candidates on the frame's border are not tested (False)
    for k in range(rows.shape[0]):
        r = rows[k]
        c = cols[k]
        b1 = b1s[kk[k]]
        b2 = b2s[kk[k]]
        if r < 1 or c < 1 or r >= b1.shape[0] - 1 or c >= b1.shape[1] - 1:
            out[k] = False
            continue
        v00 = sign * (b1[r - 1, c - 1] - b2[r - 1, c - 1])
        v01 = sign * (b1[r - 1, c] - b2[r - 1, c])
        v02 = sign * (b1[r - 1, c + 1] - b2[r - 1, c + 1])
        v10 = sign * (b1[r, c - 1] - b2[r, c - 1])
        v11 = sign * (b1[r, c] - b2[r, c])
        v12 = sign * (b1[r, c + 1] - b2[r, c + 1])
        v20 = sign * (b1[r + 1, c - 1] - b2[r + 1, c - 1])
        v21 = sign * (b1[r + 1, c] - b2[r + 1, c])
        v22 = sign * (b1[r + 1, c + 1] - b2[r + 1, c + 1])
        hxx = v12 - 2.0 * v11 + v10
        hyy = v21 - 2.0 * v11 + v01
        hxy = 0.25 * (v22 - v20 - v02 + v00)
        tr = 0.5 * (hxx + hyy)
        dd = math.sqrt(0.25 * (hxx - hyy) ** 2 + hxy * hxy)
        l1 = tr - dd        # the stronger (most negative) curvature
        l2 = tr + dd
        out[k] = l1 < 0 and l2 > 0.5 * l1


@nb.njit(cache=True)
def _patch_mosaic(frame, background, rows, cols, h, sign, out):
    # the (2h + 1)^2 patches of sign * (frame - background) about each (row, col), side by side in `out`
    # (float32, as the frame's float32 copy minus the map; pixels beyond the border repeat the edge)
    H, W = frame.shape
    sg = np.float32(sign)
    n = 2 * h + 1
    for k in range(rows.shape[0]):
        for i in range(n):
            r = min(max(rows[k] + i - h, 0), H - 1)
            for j in range(n):
                c = min(max(cols[k] + j - h, 0), W - 1)
                out[i, k * n + j] = sg * (np.float32(frame[r, c]) - background[r, c])


#: ring_evidence's dip tests read the frame directly (:func:`_patch_dips`; False: through a mosaic of patches
#: and :func:`ptrack.image.radial.has_dip`, the same result)
_DIRECT_DIP = True


@nb.njit(cache=True)
def _patch_dips(frame, background, rows, cols, h, sign, noise, k_sig, out):
    # has_dip on each (2h + 1)^2 patch of sign * (frame - background) about (row, col), radius h, centre on the
    # pixel, pixels beyond the border repeating the edge: the mosaic's values (float32) summed in its order,
    # the same annuli and test as radial._dip_all, with no patch written out
    H, W = frame.shape
    sg = np.float32(sign)
    n = 2 * h + 1
    sums = np.zeros(h + 1)
    cnt = np.zeros(h + 1)
    # every patch is centred on its pixel: one table of the annulus of each offset
    ann = np.empty((n, n), np.int64)
    for i in range(n):
        for j in range(n):
            ann[i, j] = int(math.sqrt(float(j - h) ** 2 + float(i - h) ** 2) + 0.5)
    for k in range(rows.shape[0]):
        sums[:] = 0.0
        cnt[:] = 0.0
        for i in range(n):
            r = min(max(rows[k] + i - h, 0), H - 1)
            for j in range(n):
                b = ann[i, j]
                if b <= h:
                    c = min(max(cols[k] + j - h, 0), W - 1)
                    sums[b] += sg * (np.float32(frame[r, c]) - background[r, c])
                    cnt[b] += 1
        found = False
        for b in range(2, h - 1):
            if cnt[b] == 0 or cnt[b + 2] == 0:
                continue
            mm = sums[b] / cnt[b]
            se = noise[k] / math.sqrt(cnt[b])
            outside = max(sums[b + 1] / max(cnt[b + 1], 1.0), sums[b + 2] / cnt[b + 2])
            if mm < -k_sig * se and mm < outside - k_sig * se and mm < sums[0] / max(cnt[0], 1.0) - k_sig * se:
                found = True
                break
        out[k] = found


def ring_evidence(b1s, b2s, sign, frame, background, noise_pix, rows, cols, kk, min_count: int = 3,
                  min_fraction: float = 0.2, max_dip_tests: int = 64):
    """Whether the blob candidates of a frame say it holds rings (so the ring maps are worth their cost).

    Rim pieces are ridges (one curvature below half the other at the
    maximum of the band-passed image); a faint centre sits in a ring of the
    opposite sign (:func:`ptrack.image.radial.has_dip`, on at most
    ``max_dip_tests`` candidates spread over the list, each on its own
    21 x 21 px patch: no full-frame image is made). Either must hold for at
    least ``min_count`` candidates and ``min_fraction`` of those tested.

    Parameters
    ----------
    b1s, b2s : tuples of 2D arrays
        ``G(s) * frame`` and ``G(2 s) * frame`` per detector scale.
    sign : float
        Polarity (+1 bright particles, -1 dark).
    frame, background, noise_pix : 2D arrays
        The frame, its background map and its noise map (counts).
    rows, cols : ndarray of int
        Candidates (local maxima above the threshold).
    kk : ndarray of int
        Index of each candidate's best scale.

    Returns
    -------
    bool
    """
    from .radial import has_dip

    n = len(rows)
    if n < min_count:
        return False
    ridge = np.zeros(n, np.bool_)
    _ridge(tuple(b1s), tuple(b2s), float(sign), rows, cols, np.ascontiguousarray(kk, np.int64), ridge)
    if ridge.sum() >= max(min_count, min_fraction * n):
        return True
    m = min(n, int(max_dip_tests))
    sel = np.linspace(0, n - 1, m).astype(np.int64)
    h = 10
    if not _DIRECT_DIP:
        mosaic = np.empty((2 * h + 1, (2 * h + 1) * m), np.float32)
        _patch_mosaic(np.ascontiguousarray(frame), np.ascontiguousarray(background, np.float32), rows[sel],
                      cols[sel], h, float(sign), mosaic)
        dip = has_dip(mosaic, h + (2 * h + 1) * np.arange(m, dtype=float), np.full(m, float(h)),
                      noise_pix[rows[sel], cols[sel]], np.full(m, float(h)))
    else:
        dip = np.zeros(m, np.bool_)
        _patch_dips(np.ascontiguousarray(frame), np.ascontiguousarray(background, np.float32), rows[sel], cols[sel],
                    h, float(sign), np.ascontiguousarray(noise_pix[rows[sel], cols[sel]], np.float64), 4.0, dip)
    return bool(dip.sum() >= max(min_count, min_fraction * m))
