"""Peak detection: matched-filter maxima (single size) on a whole or a raw frame.

:func:`find_peaks` finds local maxima of the Gaussian matched filter of a
preprocessed frame above ``snr`` times the filtered noise;
:func:`detect_raw` gives the same peaks from a raw fluorescence frame while
filtering only small tiles around candidates found on a block-averaged copy.
The knob-free, multi-scale detector with a stated false-alarm rate is
:mod:`ptrack.image.detect` ``detect``.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .preprocess import median3, noise_sigma

__all__ = ["find_peaks", "detect_raw", "local_maxima"]


#: local_maxima scans a row this many pixels at a time and skips a run in which no |z| exceeds the threshold
_SCAN_RUN = 32


@nb.njit(cache=True)
def local_maxima(z, thr, edge, signed):
    """Rows and columns (int64 arrays) of the 8-neighbour local maxima of ``z`` above ``thr``, at least ``edge``
    px (and at least 1 px) from the border, in raster order; ties go to the first in raster order. ``signed``:
    maxima of ``|z|``, each pixel compared with its neighbours times its own sign (bright and dark extrema in one
    pass). A pixel that is not at or below ``thr`` (NaN included) is tested against its neighbours."""
    h, w = z.shape
    edge = max(edge, 1)         # the 8-neighbour test reads one pixel beyond each tested one
    cap = 256
    n = 0
    rows = np.empty(cap, np.int64)
    cols = np.empty(cap, np.int64)
    for r in range(edge, h - edge):
        zr = z[r]
        zu = z[r - 1]
        zd = z[r + 1]
        c_end = w - edge
        for c0 in range(edge, c_end, _SCAN_RUN):
            c1 = min(c0 + _SCAN_RUN, c_end)
            # a run is skipped when no |z| in it is above thr (for signed = False a superset of the pixels
            # tested below, so the same maxima): one count over a slice, whose indices are provably >= 0, with no
            # branch on signed inside, vectorises (4x faster than the per-pixel tests of an empty run)
            seg = zr[c0:c1]
            above = 0
            for k in range(seg.shape[0]):
                above += not (abs(seg[k]) <= thr)
            if above == 0:
                continue
            for c in range(c0, c1):
                v = abs(zr[c]) if signed else zr[c]
                if v <= thr:
                    continue
                sg = (1.0 if zr[c] > 0 else -1.0) if signed else 1.0
                # the 8 neighbours, the pixel's own row first (most candidates above thr fail there), each test
                # ending at the first neighbour that wins (2x faster on a dense frame than testing all 8): a
                # neighbour wins when it is larger, or equal and before the pixel in raster order (ties go to
                # the first); a NaN neighbour never wins
                if sg * zr[c - 1] >= v or sg * zr[c + 1] > v:
                    continue
                if sg * zu[c - 1] >= v or sg * zu[c] >= v or sg * zu[c + 1] >= v:
                    continue
                if sg * zd[c - 1] > v or sg * zd[c] > v or sg * zd[c + 1] > v:
                    continue
                if n == cap:
                    cap *= 2
                    rows2 = np.empty(cap, np.int64)
                    cols2 = np.empty(cap, np.int64)
                    rows2[:n] = rows[:n]
                    cols2[:n] = cols[:n]
                    rows, cols = rows2, cols2
                rows[n] = r
                cols[n] = c
                n += 1
    return rows[:n], cols[:n]


def _default_separation(sigma: float) -> float:
    """Default peak separation (px): half the spot FWHM (1.18 sigma), at least 2 px.

    The local-maximum window then accepts two spots about one FWHM apart; in
    the matched-filtered image (width sqrt(2) sigma) two equal spots stay
    separate maxima down to ~2.8 sigma. A larger separation (the former
    2.5 sigma) silently drops one of every pair that comes within ~2 FWHM,
    and the lost rows are exactly the displacements where particles approach
    each other, which biases D low. Overlapping spots are then fitted jointly
    (:func:`fit_spots`).
    """
    return max(2.0, 0.5 * 2.3548 * float(sigma))


@nb.njit(cache=True)
def _local_maxima(img, thr, half, edge):
    h, w = img.shape
    n = 0
    cap = 1024
    rows = np.empty(cap, np.int64)
    cols = np.empty(cap, np.int64)
    vals = np.empty(cap, np.float64)
    for r in range(edge, h - edge):
        for c in range(edge, w - edge):
            v = img[r, c]
            if v <= thr:
                continue
            ok = True
            r0 = max(0, r - half)
            r1 = min(h - 1, r + half)
            c0 = max(0, c - half)
            c1 = min(w - 1, c + half)
            for rr in range(r0, r1 + 1):
                for cc in range(c0, c1 + 1):
                    u = img[rr, cc]
                    if u > v or (u == v and (rr < r or (rr == r and cc < c))):
                        ok = False
                        break
                if not ok:
                    break
            if ok:
                if n == cap:
                    cap *= 2
                    rows2 = np.empty(cap, np.int64)
                    cols2 = np.empty(cap, np.int64)
                    vals2 = np.empty(cap, np.float64)
                    rows2[:n] = rows[:n]
                    cols2[:n] = cols[:n]
                    vals2[:n] = vals[:n]
                    rows, cols, vals = rows2, cols2, vals2
                rows[n] = r
                cols[n] = c
                vals[n] = v
                n += 1
    return rows[:n], cols[:n], vals[:n]




@nb.njit(cache=True, inline="always")
def _med9(p0, p1, p2, p3, p4, p5, p6, p7, p8):
    # median of 9 by the classic 19-exchange sorting network (Paeth / Devillard)
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p0, p1 = min(p0, p1), max(p0, p1)
    p3, p4 = min(p3, p4), max(p3, p4)
    p6, p7 = min(p6, p7), max(p6, p7)
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p3 = max(p0, p3)
    p5 = min(p5, p8)
    p4, p7 = min(p4, p7), max(p4, p7)
    p6 = max(p3, p6)
    p4 = max(p1, p4)
    p2 = min(p2, p5)
    p4 = min(p4, p7)
    p4, p2 = min(p4, p2), max(p4, p2)
    p4 = max(p6, p4)
    return min(p4, p2)


@nb.njit(cache=True)
def _smooth_tile(raw, r0, r1, c0, c1, kern, median, med, tmp, sm):
    # Gaussian(kern)-filtered 3x3-median of raw over rows r0..r1, cols c0..c1 (inclusive) -> sm;
    # indices outside the frame are clamped (replicated border)
    h, w = raw.shape
    kh = kern.shape[0] // 2
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    for i in range(nr + 2 * kh):
        r = min(max(r0 - kh + i, 0), h - 1)
        ra = max(r - 1, 0)
        rb = min(r + 1, h - 1)
        for j in range(nc + 2 * kh):
            c = min(max(c0 - kh + j, 0), w - 1)
            if median:
                ca = max(c - 1, 0)
                cb = min(c + 1, w - 1)
                med[i, j] = _med9(float(raw[ra, ca]), float(raw[ra, c]), float(raw[ra, cb]),
                                  float(raw[r, ca]), float(raw[r, c]), float(raw[r, cb]),
                                  float(raw[rb, ca]), float(raw[rb, c]), float(raw[rb, cb]))
            else:
                med[i, j] = raw[r, c]
    for i in range(nr + 2 * kh):
        for j in range(nc):
            acc = 0.0
            for k in range(kern.shape[0]):
                acc += kern[k] * med[i, j + k]
            tmp[i, j] = acc
    for i in range(nr):
        for j in range(nc):
            acc = 0.0
            for k in range(kern.shape[0]):
                acc += kern[k] * tmp[i + k, j]
            sm[i, j] = acc


@nb.njit(cache=True)
def _tile_peaks(raw, boxes, kern, median, bg, ds, thr, half, edge):
    # local maxima of the filtered frame inside each box (r0, r1, c0, c1, inclusive), tile by tile;
    # a peak must exceed its block background by thr and be the maximum of its (2 half + 1)^2 window
    h, w = raw.shape
    bh, bw = bg.shape
    kh = kern.shape[0] // 2
    rows = []
    cols = []
    vals = []
    for k in range(boxes.shape[0]):
        br0, br1, bc0, bc1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        r0 = br0 - half
        c0 = bc0 - half
        nr = br1 - br0 + 1 + 2 * half
        nc = bc1 - bc0 + 1 + 2 * half
        med = np.empty((nr + 2 * kh, nc + 2 * kh))
        tmp = np.empty((nr + 2 * kh, nc))
        sm = np.empty((nr, nc))
        _smooth_tile(raw, r0, r0 + nr - 1, c0, c0 + nc - 1, kern, median, med, tmp, sm)
        for i in range(half, nr - half):
            r = r0 + i
            if r < edge or r >= h - edge:
                continue
            for j in range(half, nc - half):
                c = c0 + j
                if c < edge or c >= w - edge:
                    continue
                v = sm[i, j]
                b = bg[min(r // ds, bh - 1), min(c // ds, bw - 1)]
                if v - b <= thr:
                    continue
                ok = True
                for ii in range(i - half, i + half + 1):
                    rr = r0 + ii
                    if rr < 0 or rr >= h:
                        continue
                    for jj in range(j - half, j + half + 1):
                        c2 = c0 + jj
                        if c2 < 0 or c2 >= w:
                            continue
                        u = sm[ii, jj]
                        if u > v or (u == v and (rr < r or (rr == r and c2 < c))):
                            ok = False
                            break
                    if not ok:
                        break
                if ok:
                    rows.append(r)
                    cols.append(c)
                    vals.append(v - b)
    return rows, cols, vals


@nb.njit(cache=True)
def _tile_values(raw, cr, cc, kern, median, bg, ds, n_side):
    # filtered values minus block background at n_side x n_side pixels around each (cr, cc): noise samples
    h, w = raw.shape
    bh, bw = bg.shape
    kh = kern.shape[0] // 2
    med = np.empty((n_side + 2 * kh, n_side + 2 * kh))
    tmp = np.empty((n_side + 2 * kh, n_side))
    sm = np.empty((n_side, n_side))
    out = np.empty(cr.shape[0] * n_side * n_side)
    n = 0
    for k in range(cr.shape[0]):
        _smooth_tile(raw, cr[k], cr[k] + n_side - 1, cc[k], cc[k] + n_side - 1, kern, median, med, tmp, sm)
        for i in range(n_side):
            for j in range(n_side):
                r = min(cr[k] + i, h - 1)
                c = min(cc[k] + j, w - 1)
                out[n] = sm[i, j] - bg[min(r // ds, bh - 1), min(c // ds, bw - 1)]
                n += 1
    return out


def detect_raw(frame, sigma: float, snr: float = 7.0, separation: float | None = None, bg_size: float | None = None,
               median: bool = True, edge: int | None = None, downsample: int = 4, coarse_snr: float = 4.0):
    """Fast detection on a raw fluorescence frame: coarse candidates, then exact peaks in small tiles.

    1. The frame is reduced ``downsample`` times by block averaging (one pass
       over the full frame); the background (grey-level opening, as
       :func:`ptrack.preprocess.spatial_background`) and the block noise are
       measured there, and blocks above ``coarse_snr`` noise (after a 2x2
       block smoothing) become candidates: a spot's photons are
       concentrated in a few blocks, so the coarse test is about as sensitive
       as the final one.
    2. Around each candidate block (with its 8 neighbours), a numba kernel
       computes the 3x3 median and the
       Gaussian matched filter of the raw counts on a small tile and keeps
       its local maxima more than ``snr`` noise sigmas above the background,
       exactly as :func:`find_peaks` would on the whole frame. The filtered
       image's noise is measured the same way on a grid of sample tiles.

    Full-resolution work is thus one block average plus tiles around the
    particles, instead of four full-frame filters.

    Returns
    -------
    rows, cols : ndarray of int
    signal : ndarray
        Filtered height above background (counts).
    aux : dict
        ``bg`` (block background, filtered-image units), ``ds``, ``noise``
        (filtered-image noise, counts), ``n_candidates``.
    """
    import cv2

    raw = np.ascontiguousarray(frame)
    if raw.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raw = raw.astype(np.float32)
    H, W = raw.shape
    ds = max(1, int(downsample)) if min(H, W) >= 64 else 1
    small = cv2.resize(raw, (max(1, W // ds), max(1, H // ds)), interpolation=cv2.INTER_AREA).astype(np.float32) \
        if ds > 1 else raw.astype(np.float32)
    bg_size = max(15.0, 12.0 * sigma) if bg_size is None else float(bg_size)
    k = max(3, int(round(bg_size / ds)) | 1)
    rect = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    opened = cv2.blur(cv2.morphologyEx(small, cv2.MORPH_OPEN, rect, borderType=cv2.BORDER_REPLICATE), (k, k),
                      borderType=cv2.BORDER_REPLICATE)
    # the opening sits below the background by a few noise sigmas: lift it to the residual's median
    resid = small - opened
    off = float(np.median(resid[::2, ::2]))
    bg = opened + np.float32(off)
    resid -= off
    coarse = cv2.blur(resid, (2, 2)) if ds > 1 else resid
    cnoise = max(float(1.4826 * np.median(np.abs(coarse[::2, ::2]))), 1e-6)
    cthr = coarse_snr * cnoise
    # candidates: blocks above threshold; each is searched at full resolution together with its 8
    # neighbour blocks (a spot's peak may sit in the block next to its brightest coarse value)
    above = coarse > cthr
    cr, cc = np.nonzero(above)
    nbh, nbw = coarse.shape
    if len(cr) <= 256:
        boxes = np.empty((len(cr), 4), np.int64)
        boxes[:, 0] = np.maximum(cr - 1, 0) * ds
        boxes[:, 1] = np.where(cr + 2 >= nbh, H, (cr + 2) * ds) - 1
        boxes[:, 2] = np.maximum(cc - 1, 0) * ds
        boxes[:, 3] = np.where(cc + 2 >= nbw, W, (cc + 2) * ds) - 1
    else:
        # many candidates: merge the grown candidate blocks into connected regions (one labelling
        # pass) so overlapping neighbourhoods are not filtered several times
        mask = cv2.dilate(above.astype(np.uint8), np.ones((3, 3), np.uint8))
        _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        st = stats[1:].astype(np.int64)
        top, left = st[:, cv2.CC_STAT_TOP], st[:, cv2.CC_STAT_LEFT]
        bottom, right = top + st[:, cv2.CC_STAT_HEIGHT], left + st[:, cv2.CC_STAT_WIDTH]
        boxes = np.stack([top * ds, np.where(bottom >= nbh, H, bottom * ds) - 1,
                          left * ds, np.where(right >= nbw, W, right * ds) - 1], axis=1).astype(np.int64)
    ks = int(2 * math.ceil(2.5 * max(0.5, sigma)) + 1)
    kern = cv2.getGaussianKernel(ks, max(0.5, float(sigma)), cv2.CV_64F).ravel()
    # noise of the filtered image, from a grid of sample tiles
    step = max(16, int(math.sqrt(H * W / 96)))
    gr, gc = np.meshgrid(np.arange(step // 2, H - 8, step), np.arange(step // 2, W - 8, step), indexing="ij")
    samples = _tile_values(raw, gr.ravel().astype(np.int64), gc.ravel().astype(np.int64), kern, bool(median),
                           bg, ds, 8)
    noise = max(float(1.4826 * np.median(np.abs(samples - np.median(samples)))), 1e-6)
    thr = snr * noise
    half = max(1, int(round(separation if separation is not None else _default_separation(sigma))))
    edge = max(2, int(round(sigma))) if edge is None else int(edge)
    rows, cols, vals = _tile_peaks(raw, boxes, kern, bool(median), bg, ds, float(thr), half, edge)
    rows, cols, vals = np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(vals, np.float64)
    _, first = np.unique(rows * W + cols, return_index=True)     # bounding boxes of two regions may overlap
    rows, cols, vals = rows[first], cols[first], vals[first]
    return (rows, cols, vals,
            {"bg": bg, "ds": ds, "noise": noise, "n_candidates": int(len(boxes))})


def find_peaks(img: np.ndarray, sigma: float, snr: float = 7.0, separation: float | None = None,
               median: bool = True, threshold: float | None = None, edge: int | None = None, filtered=None):
    """Local maxima of the matched-filtered image.

    Parameters
    ----------
    img : 2D array
        Background-subtracted frame (particles bright, background ~0).
    sigma : float
        Spot width (px) of the Gaussian matched filter.
    snr : float
        Detection threshold in units of the filtered image's noise.
    separation : float, optional
        Minimum distance between maxima (px, half-width of the local-maximum
        window); default :func:`_default_separation` (half the FWHM, min 2).
    median : bool
        3x3 median filter before the Gaussian (hot pixels).
    threshold : float, optional
        Absolute threshold on the filtered image (overrides ``snr``).
    edge : int, optional
        Ignore maxima closer than this to the border (default max(2, sigma)).
    filtered : 2D float32 array, optional
        ``median3(img)`` if already computed.

    Returns
    -------
    rows, cols : ndarray of int
    values : ndarray of float
        Filtered-image value at each maximum (the ``signal`` column).
    """
    import cv2

    if filtered is not None:
        work = filtered
    else:
        work = median3(img) if median else np.ascontiguousarray(img, np.float32)
    smooth = cv2.GaussianBlur(work, (0, 0), sigmaX=max(0.5, float(sigma)), borderType=cv2.BORDER_REFLECT)
    if threshold is None:
        threshold = float(np.median(smooth[::5, ::5])) + snr * max(noise_sigma(smooth), 1e-6)
    half = max(1, int(round(separation if separation is not None else _default_separation(sigma))))
    edge = max(2, int(round(sigma))) if edge is None else int(edge)
    return _local_maxima(smooth, float(threshold), half, edge)
