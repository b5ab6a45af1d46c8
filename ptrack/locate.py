"""Particle detection and sub-pixel localisation at the Cramer-Rao bound.

Detection: a Gaussian matched filter (after a 3x3 median against hot pixels)
of the background-subtracted frame, local maxima above ``snr`` times the
filtered noise, at least ``separation`` px apart. :func:`find_peaks` does this
on a whole preprocessed frame; :func:`detect_raw` (the default for
fluorescence movies) gives the same peaks from the raw frame while filtering
only small tiles around candidates found on a block-averaged copy, so a
2560 x 2160 frame costs one block average plus work proportional to the
number of particles.

Localisation: a maximum-likelihood fit of a pixel-integrated 2D Gaussian
(position, photons, background, width) to the raw counts of each spot,
converted to photons with the camera gain and offset, with sCMOS/CCD read
noise folded in (Poisson + read-noise variance, the "+ sigma^2" shift of
Huang et al. 2013). The likelihood is maximised by Levenberg-Marquardt
damped Fisher scoring in a numba kernel, started from the local centroid.
The MLE reaches the Cramer-Rao lower bound (Mortensen et al. 2010, Smith et
al. 2010), whereas least squares loses a factor 16/9 in variance; the
inverse Fisher information at the estimate is each particle's uncertainty
(``sigma_x``, ``sigma_y``). For brightfield images (no Poisson model after
inversion) a least-squares fit of the same model is used.

Pixel coordinates follow trackpy: ``x`` along columns, ``y`` along rows, the
centre of pixel (0, 0) at (0, 0).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import pandas as pd

from .errors import UserError
from .preprocess import median3, noise_sigma

__all__ = [
    "find_peaks", "fit_spots", "locate", "estimate_sigma", "mortensen_sigma", "sigma_to_diameter",
    "diameter_to_sigma", "LOCATE_COLUMNS",
]

LOCATE_COLUMNS = ("x_px", "y_px", "mass", "size", "ecc", "signal", "photons", "bg_photons",
                  "sigma_x_px", "sigma_y_px")
_SQRT2 = math.sqrt(2.0)
_SQRT2PI = math.sqrt(2.0 * math.pi)


def diameter_to_sigma(diameter: float) -> float:
    """Gaussian width (px) of a spot of the given diameter (px): the 1/e^2 diameter is 4 sigma."""
    return float(diameter) / 4.0


def sigma_to_diameter(sigma: float) -> float:
    """Spot diameter (px, 4 sigma) for a Gaussian width sigma (px)."""
    return 4.0 * float(sigma)


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


@nb.njit(cache=True)
def _median9(buf):
    # insertion sort of 9 values, return the middle one
    for i in range(1, 9):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    return buf[4]


@nb.njit(cache=True)
def _hot_in_rois(raw, bg, ds, rows, cols, half, thr):
    # pixels of the fit windows that stand alone: more than thr above their brightest neighbour and
    # more than 3x that neighbour's height above background. A diffraction-limited spot (sigma >= 0.8 px)
    # never does (its brightest neighbour holds >= 45 % of its peak); a hot pixel or cosmic ray does.
    # Returns their coordinates and 3x3 medians (the replacement values).
    h, w = raw.shape
    bh, bw = bg.shape
    hr = []
    hc = []
    hv = []
    buf = np.empty(9)
    for k in range(rows.shape[0]):
        for r in range(max(1, rows[k] - half), min(h - 2, rows[k] + half) + 1):
            for c in range(max(1, cols[k] - half), min(w - 2, cols[k] + half) + 1):
                v = float(raw[r, c])
                mx = -1e300
                n = 0
                for dr in range(-1, 2):
                    for dc in range(-1, 2):
                        u = float(raw[r + dr, c + dc])
                        buf[n] = u
                        n += 1
                        if (dr != 0 or dc != 0) and u > mx:
                            mx = u
                b = bg[min(r // ds, bh - 1), min(c // ds, bw - 1)]
                if v - mx > thr and v - b > 3.0 * (mx - b):
                    hr.append(r)
                    hc.append(c)
                    hv.append(_median9(buf))
    return hr, hc, hv


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


@nb.njit(cache=True)
def _erf_profile(n0, n, x, s, e, de_dx, de_ds):
    # pixel-integrated unit Gaussian over pixels n0..n0+n-1 centred at x, width s
    inv = 1.0 / (_SQRT2 * s)
    for i in range(n):
        p = n0 + i
        a = (p - x + 0.5)
        b = (p - x - 0.5)
        ga = math.exp(-a * a / (2 * s * s))
        gb = math.exp(-b * b / (2 * s * s))
        e[i] = 0.5 * (math.erf(a * inv) - math.erf(b * inv))
        de_dx[i] = -(ga - gb) / (_SQRT2PI * s)
        de_ds[i] = -(a * ga - b * gb) / (_SQRT2PI * s * s)


@nb.njit(cache=True, inline="always")
def _pixel_loglik(d, mu, rvar, poisson):
    # one pixel's term of the fit objective, shared by the single and the joint fit: d = measured photons,
    # mu = model photons. Poisson log-likelihood with the read-noise variance rvar added to both (sCMOS
    # approximation; mu floored at 1e-9), or -(d - mu)^2 / 2 for least squares.
    if poisson:
        mu += rvar
        d += rvar
        if mu < 1e-9:
            mu = 1e-9
        if d > 0:
            return d * math.log(mu) - mu
        return -mu
    return -0.5 * (d - mu) ** 2


@nb.njit(cache=True)
def _objective(img, r0, r1, c0, c1, th, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys):
    x, y, N, b, s = th[0], th[1], th[2], th[3], th[4]
    _erf_profile(c0, c1 - c0 + 1, x, s, ex, dxx, dxs)
    _erf_profile(r0, r1 - r0 + 1, y, s, ey, dyy, dys)
    f = 0.0
    for i in range(r1 - r0 + 1):
        for j in range(c1 - c0 + 1):
            mu = b + N * ex[j] * ey[i]
            f += _pixel_loglik((img[r0 + i, c0 + j] - offset) / gain, mu, rvar, poisson)
    return f


@nb.njit(cache=True, inline="always")
def _border_mean(img, r0, nr, c0, nc, gain, offset):
    # mean photons on the border pixels of the window rows r0..r0+nr-1, cols c0..c0+nc-1: the starting
    # background of the single and the joint fit
    bsum = 0.0
    nb_ = 0
    for i in range(nr):
        for j in range(nc):
            if i == 0 or j == 0 or i == nr - 1 or j == nc - 1:
                bsum += (img[r0 + i, c0 + j] - offset) / gain
                nb_ += 1
    return bsum / max(nb_, 1)


@nb.njit(cache=True, inline="always")
def _spot_model(th, ex, ey, dxx, dxs, dyy, dys, i, j, dm):
    # single-spot model photons at window pixel (i, j) for th = (x, y, N, b, s) from the current erf
    # profiles; its derivatives d mu / d th go to dm. Shared by the Levenberg-Marquardt step and the
    # covariance of _fit_one.
    N = th[2]
    mu = th[3] + N * ex[j] * ey[i]
    dm[0] = N * dxx[j] * ey[i]
    dm[1] = N * ex[j] * dyy[i]
    dm[2] = ex[j] * ey[i]
    dm[3] = 1.0
    dm[4] = N * (dxs[j] * ey[i] + ex[j] * dys[i])
    return mu


@nb.njit(cache=True)
def _fit_one(img, r, c, half, sigma0, gain, offset, rvar, poisson, max_iter, out, cov):
    h, w = img.shape
    r0 = max(0, r - half)
    r1 = min(h - 1, r + half)
    c0 = max(0, c - half)
    c1 = min(w - 1, c + half)
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    # initial guess: border mean as background, centroid of the excess
    b0 = _border_mean(img, r0, nr, c0, nc, gain, offset)
    sw = 0.0
    sx = 0.0
    sy = 0.0
    for i in range(nr):
        for j in range(nc):
            v = (img[r0 + i, c0 + j] - offset) / gain - b0
            if v > 0:
                sw += v
                sx += v * (c0 + j)
                sy += v * (r0 + i)
    if sw <= 0:
        return False, 0
    th = np.empty(5)
    th[0] = sx / sw
    th[1] = sy / sw
    th[2] = sw
    th[3] = max(b0, 0.0) if poisson else b0
    th[4] = sigma0
    ex = np.empty(nc)
    ey = np.empty(nr)
    dxx = np.empty(nc)
    dxs = np.empty(nc)
    dyy = np.empty(nr)
    dys = np.empty(nr)
    J = np.zeros((5, 5))
    g = np.zeros(5)
    dm = np.zeros(5)
    lam = 1e-3
    f = _objective(img, r0, r1, c0, c1, th, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys)
    it = 0
    converged = False
    trial = np.empty(5)
    while it < max_iter:
        it += 1
        # gradient and Fisher information at th (profiles are current from the last objective call)
        _erf_profile(c0, nc, th[0], th[4], ex, dxx, dxs)
        _erf_profile(r0, nr, th[1], th[4], ey, dyy, dys)
        J[:, :] = 0.0
        g[:] = 0.0
        for i in range(nr):
            for j in range(nc):
                mu = _spot_model(th, ex, ey, dxx, dxs, dyy, dys, i, j, dm)
                d = (img[r0 + i, c0 + j] - offset) / gain
                if poisson:
                    mu += rvar
                    d += rvar
                    if mu < 1e-9:
                        mu = 1e-9
                    wgt = 1.0 / mu
                    res = d / mu - 1.0
                else:
                    wgt = 1.0
                    res = d - mu
                for a in range(5):
                    g[a] += res * dm[a]
                    for bb in range(a, 5):
                        J[a, bb] += wgt * dm[a] * dm[bb]
        for a in range(5):
            for bb in range(a):
                J[a, bb] = J[bb, a]
        improved = False
        for _ in range(12):
            A = J.copy()
            for a in range(5):
                A[a, a] += lam * J[a, a] + 1e-12
            step = np.linalg.solve(A, g)
            for a in range(5):
                trial[a] = th[a] + step[a]
            if trial[2] <= 0 or trial[4] < 0.25 * sigma0 or trial[4] > 4.0 * sigma0 or (poisson and trial[3] < -rvar):
                lam *= 10.0
                continue
            ft = _objective(img, r0, r1, c0, c1, trial, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys)
            if ft >= f:
                th[:] = trial
                f = ft
                lam = max(lam * 0.1, 1e-7)
                improved = True
                break
            lam *= 10.0
        if not improved or (abs(step[0]) < 1e-5 and abs(step[1]) < 1e-5):
            converged = True
            break
    # covariance: inverse Fisher information (Poisson), scaled by the residual variance (least squares)
    _erf_profile(c0, nc, th[0], th[4], ex, dxx, dxs)
    _erf_profile(r0, nr, th[1], th[4], ey, dyy, dys)
    J[:, :] = 0.0
    rss = 0.0
    for i in range(nr):
        for j in range(nc):
            mu = _spot_model(th, ex, ey, dxx, dxs, dyy, dys, i, j, dm)
            d = (img[r0 + i, c0 + j] - offset) / gain
            rss += (d - mu) ** 2
            wgt = 1.0 / max(mu + rvar, 1e-9) if poisson else 1.0
            for a in range(5):
                for bb in range(5):
                    J[a, bb] += wgt * dm[a] * dm[bb]
    for a in range(5):
        J[a, a] += 1e-12
    C = np.linalg.inv(J)
    scale = 1.0 if poisson else rss / max(nr * nc - 5, 1)
    for a in range(5):
        cov[a] = C[a, a] * scale
    out[:] = th
    ok = converged and abs(th[0] - c) <= half and abs(th[1] - r) <= half and th[2] > 0
    return ok, it


@nb.njit(cache=True)
def _moments(img, r, c, half, x, y, bg):
    # eccentricity from the second moments of the background-subtracted spot
    h, w = img.shape
    sw = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for rr in range(max(0, r - half), min(h - 1, r + half) + 1):
        for cc in range(max(0, c - half), min(w - 1, c + half) + 1):
            v = img[rr, cc] - bg
            if v > 0:
                sw += v
                sxx += v * (cc - x) ** 2
                syy += v * (rr - y) ** 2
                sxy += v * (cc - x) * (rr - y)
    if sw <= 0:
        return 0.0
    a = sxx / sw
    b = syy / sw
    d = sxy / sw
    tr = a + b
    det = math.sqrt(max((a - b) ** 2 + 4 * d * d, 0.0))
    l1 = 0.5 * (tr + det)
    l2 = 0.5 * (tr - det)
    if l1 <= 0:
        return 0.0
    return math.sqrt(max(1.0 - max(l2, 0.0) / l1, 0.0))


@nb.njit(cache=True)
def _fit_all(img, rows, cols, half, sigma0, gain, offset, rvar, poisson, max_iter):
    n = rows.shape[0]
    params = np.zeros((n, 5))
    var = np.zeros((n, 5))
    ok = np.zeros(n, np.bool_)
    ecc = np.zeros(n)
    out = np.empty(5)
    cv = np.empty(5)
    for k in range(n):
        good, it = _fit_one(img, rows[k], cols[k], half, sigma0, gain, offset, rvar, poisson, max_iter, out, cv)
        params[k] = out
        var[k] = cv
        ok[k] = good
        if good:
            ecc[k] = _moments(img, rows[k], cols[k], half, out[0], out[1], out[3] * gain + offset
                              if not poisson else (out[3]) * gain + offset)
    return params, var, ok, ecc


@nb.njit(cache=True)
def _group_objective(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys):
    # log-likelihood (Poisson) or -RSS/2 of K Gaussians (x, y, N each) on a shared background and width
    b = th[3 * K]
    s = th[3 * K + 1]
    for k in range(K):
        _erf_profile(c0, nc, th[3 * k], s, ex[k], dxx[k], dxs[k])
        _erf_profile(r0, nr, th[3 * k + 1], s, ey[k], dyy[k], dys[k])
    f = 0.0
    for i in range(nr):
        for j in range(nc):
            mu = b
            for k in range(K):
                mu += th[3 * k + 2] * ex[k, j] * ey[k, i]
            f += _pixel_loglik((img[r0 + i, c0 + j] - offset) / gain, mu, rvar, poisson)
    return f


@nb.njit(cache=True)
def _group_fisher(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys, J, g, dm):
    # Fisher information (or Gauss-Newton matrix) J and score g at th; returns the residual sum of squares
    P = 3 * K + 2
    s = th[3 * K + 1]
    for k in range(K):
        _erf_profile(c0, nc, th[3 * k], s, ex[k], dxx[k], dxs[k])
        _erf_profile(r0, nr, th[3 * k + 1], s, ey[k], dyy[k], dys[k])
    J[:, :] = 0.0
    g[:] = 0.0
    rss = 0.0
    for i in range(nr):
        for j in range(nc):
            mu = th[3 * K]
            ds_ = 0.0
            for k in range(K):
                N = th[3 * k + 2]
                e = ex[k, j] * ey[k, i]
                mu += N * e
                dm[3 * k] = N * dxx[k, j] * ey[k, i]
                dm[3 * k + 1] = N * ex[k, j] * dyy[k, i]
                dm[3 * k + 2] = e
                ds_ += N * (dxs[k, j] * ey[k, i] + ex[k, j] * dys[k, i])
            dm[3 * K] = 1.0
            dm[3 * K + 1] = ds_
            d = (img[r0 + i, c0 + j] - offset) / gain
            rss += (d - mu) ** 2
            if poisson:
                m = max(mu + rvar, 1e-9)
                wgt = 1.0 / m
                res = (d + rvar) / m - 1.0
            else:
                wgt = 1.0
                res = d - mu
            for a in range(P):
                g[a] += res * dm[a]
                for bb in range(a, P):
                    J[a, bb] += wgt * dm[a] * dm[bb]
    for a in range(P):
        for bb in range(a):
            J[a, bb] = J[bb, a]
    return rss


@nb.njit(cache=True)
def _fit_group(img, r0, r1, c0, c1, x0, y0, amp, sigma0, gain, offset, rvar, poisson, max_iter, th, var):
    # joint maximum-likelihood fit of K = len(x0) overlapping spots in the window rows r0..r1, cols c0..c1:
    # parameters th = (x_1, y_1, N_1, ..., x_K, y_K, N_K, background, width); var = diagonal of the
    # inverse Fisher information (scaled by the residual variance for least squares).
    # Returns (converged, log-likelihood).
    K = x0.shape[0]
    P = 3 * K + 2
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    b0 = _border_mean(img, r0, nr, c0, nc, gain, offset)
    sw = 0.0
    for i in range(nr):
        for j in range(nc):
            v = (img[r0 + i, c0 + j] - offset) / gain - b0
            if v > 0:
                sw += v
    asum = 0.0
    for k in range(K):
        asum += max(amp[k], 1e-12)
    for k in range(K):
        th[3 * k] = x0[k]
        th[3 * k + 1] = y0[k]
        th[3 * k + 2] = max(sw * max(amp[k], 1e-12) / asum, 1.0)
    th[3 * K] = max(b0, 0.0) if poisson else b0
    th[3 * K + 1] = sigma0
    ex = np.empty((K, nc))
    ey = np.empty((K, nr))
    dxx = np.empty((K, nc))
    dxs = np.empty((K, nc))
    dyy = np.empty((K, nr))
    dys = np.empty((K, nr))
    J = np.zeros((P, P))
    g = np.zeros(P)
    dm = np.zeros(P)
    trial = np.empty(P)
    step = np.zeros(P)
    lam = 1e-3
    f = _group_objective(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys)
    converged = False
    for it in range(max_iter):
        _group_fisher(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys, J, g, dm)
        improved = False
        for _ in range(12):
            A = J.copy()
            for a in range(P):
                A[a, a] += lam * J[a, a] + 1e-12
            step = np.linalg.solve(A, g)
            bad = False
            for a in range(P):
                trial[a] = th[a] + step[a]
            for k in range(K):
                if (trial[3 * k + 2] <= 0 or trial[3 * k] < c0 - 1 or trial[3 * k] > c1 + 1
                        or trial[3 * k + 1] < r0 - 1 or trial[3 * k + 1] > r1 + 1):
                    bad = True
            s = trial[3 * K + 1]
            if bad or s < 0.25 * sigma0 or s > 4.0 * sigma0 or (poisson and trial[3 * K] < -rvar):
                lam *= 10.0
                continue
            ft = _group_objective(img, r0, nr, c0, nc, trial, K, gain, offset, rvar, poisson,
                                  ex, ey, dxx, dxs, dyy, dys)
            if ft >= f:
                th[:] = trial
                f = ft
                lam = max(lam * 0.1, 1e-7)
                improved = True
                break
            lam *= 10.0
        small = True
        for k in range(K):
            if abs(step[3 * k]) >= 1e-5 or abs(step[3 * k + 1]) >= 1e-5:
                small = False
        if not improved or small:
            converged = True
            break
    rss = _group_fisher(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys,
                        J, g, dm)
    for a in range(P):
        J[a, a] += 1e-12
    C = np.linalg.inv(J)
    scale = 1.0 if poisson else rss / max(nr * nc - P, 1)
    for a in range(P):
        var[a] = C[a, a] * scale
    return converged, f


@nb.njit(cache=True)
def _fit_tasks(img, rows, cols, amps, ptr, members, report, half, sigma0, gain, offset, rvar, poisson, max_iter,
               params, var, ok, ecc):
    # joint fits of groups of neighbouring spots: task t fits members[ptr[t]:ptr[t+1]] together in the union
    # of their (2 half + 1)^2 windows and writes the results of the members flagged in report
    h, w = img.shape
    for t in range(ptr.shape[0] - 1):
        m = members[ptr[t]:ptr[t + 1]]
        K = m.shape[0]
        r0 = h
        r1 = 0
        c0 = w
        c1 = 0
        x0 = np.empty(K)
        y0 = np.empty(K)
        a0 = np.empty(K)
        for k in range(K):
            q = m[k]
            r0 = min(r0, max(0, rows[q] - half))
            r1 = max(r1, min(h - 1, rows[q] + half))
            c0 = min(c0, max(0, cols[q] - half))
            c1 = max(c1, min(w - 1, cols[q] + half))
            x0[k] = cols[q]
            y0[k] = rows[q]
            a0[k] = amps[q]
        th = np.empty(3 * K + 2)
        vv = np.empty(3 * K + 2)
        conv, _ = _fit_group(img, r0, r1, c0, c1, x0, y0, a0, sigma0, gain, offset, rvar, poisson, max_iter, th, vv)
        for k in range(K):
            if not report[ptr[t] + k]:
                continue
            q = m[k]
            params[q, 0] = th[3 * k]
            params[q, 1] = th[3 * k + 1]
            params[q, 2] = th[3 * k + 2]
            params[q, 3] = th[3 * K]
            params[q, 4] = th[3 * K + 1]
            var[q, 0] = vv[3 * k]
            var[q, 1] = vv[3 * k + 1]
            var[q, 2] = vv[3 * k + 2]
            var[q, 3] = vv[3 * K]
            var[q, 4] = vv[3 * K + 1]
            good = (conv and abs(th[3 * k] - cols[q]) <= half and abs(th[3 * k + 1] - rows[q]) <= half
                    and th[3 * k + 2] > 0)
            ok[q] = good
            if good:
                ecc[q] = _moments(img, rows[q], cols[q], half, th[3 * k], th[3 * k + 1], th[3 * K] * gain + offset)


@nb.njit(cache=True)
def _split_spots(img, rows, cols, params, cand, half, sigma0, gain, offset, rvar, poisson, max_iter, min_llr,
                 out, var, accepted, llr):
    # For each candidate spot q = cand[k] (fitted alone, suspiciously wide or elongated), fit two spots
    # started on either side of the centre along the major axis of the spot's second moments, in the
    # same window. Accept when the likelihood gains more than min_llr (log units), both parts carry
    # >= 15 % of the photons and they are >= sigma0 apart: two spots closer than ~2.8 sigma merge into
    # one maximum of the matched filter, so detection alone cannot separate them.
    h, w = img.shape
    K1 = np.empty(5)
    ex = np.empty((2, 2 * half + 1))
    ey = np.empty((2, 2 * half + 1))
    dxx = np.empty((2, 2 * half + 1))
    dxs = np.empty((2, 2 * half + 1))
    dyy = np.empty((2, 2 * half + 1))
    dys = np.empty((2, 2 * half + 1))
    th = np.empty(8)
    vv = np.empty(8)
    x0 = np.empty(2)
    y0 = np.empty(2)
    a0 = np.ones(2)
    for k in range(cand.shape[0]):
        q = cand[k]
        r = rows[q]
        c = cols[q]
        r0 = max(0, r - half)
        r1 = min(h - 1, r + half)
        c0 = max(0, c - half)
        c1 = min(w - 1, c + half)
        nr = r1 - r0 + 1
        nc = c1 - c0 + 1
        xc = params[q, 0]
        yc = params[q, 1]
        bgc = params[q, 3]
        # single-spot likelihood in this window
        K1[0] = xc
        K1[1] = yc
        K1[2] = params[q, 2]
        K1[3] = bgc
        K1[4] = params[q, 4]
        f1 = _group_objective(img, r0, nr, c0, nc, K1, 1, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys)
        # major axis of the excess
        sw = 0.0
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for i in range(nr):
            for j in range(nc):
                v = (img[r0 + i, c0 + j] - offset) / gain - bgc
                if v > 0:
                    dx = c0 + j - xc
                    dy = r0 + i - yc
                    sw += v
                    sxx += v * dx * dx
                    syy += v * dy * dy
                    sxy += v * dx * dy
        if sw <= 0:
            continue
        a = sxx / sw
        b = syy / sw
        d_ = sxy / sw
        ang = 0.5 * math.atan2(2 * d_, a - b)
        det = math.sqrt(max((a - b) ** 2 + 4 * d_ * d_, 0.0))
        sep = 2.0 * math.sqrt(max(det, 0.25))
        sep = min(max(sep, 1.0 * sigma0), 3.0 * sigma0)
        ca = math.cos(ang) * 0.5 * sep
        sa = math.sin(ang) * 0.5 * sep
        x0[0] = xc + ca
        y0[0] = yc + sa
        x0[1] = xc - ca
        y0[1] = yc - sa
        conv, f2 = _fit_group(img, r0, r1, c0, c1, x0, y0, a0, sigma0, gain, offset, rvar, poisson, max_iter, th, vv)
        gain_ll = f2 - f1
        if not poisson:
            # least squares: f = -RSS/2 in image units; in log-likelihood units divide by the noise
            # variance, estimated from the two-spot residual
            s2 = -2.0 * f2 / max(nr * nc - 8, 1)
            gain_ll = gain_ll / max(s2, 1e-300)
        llr[k] = gain_ll
        if not conv or gain_ll < min_llr:
            continue
        N1 = th[2]
        N2 = th[5]
        dd = math.hypot(th[0] - th[3], th[1] - th[4])
        if min(N1, N2) < 0.15 * (N1 + N2) or dd < sigma0:
            continue
        ok2 = True
        for m in range(2):
            if abs(th[3 * m] - c) > half or abs(th[3 * m + 1] - r) > half:
                ok2 = False
        if not ok2:
            continue
        accepted[k] = True
        for m in range(2):
            out[k, m, 0] = th[3 * m]
            out[k, m, 1] = th[3 * m + 1]
            out[k, m, 2] = th[3 * m + 2]
            out[k, m, 3] = th[6]
            out[k, m, 4] = th[7]
            var[k, m, 0] = vv[3 * m]
            var[k, m, 1] = vv[3 * m + 1]
            var[k, m, 2] = vv[3 * m + 2]
            var[k, m, 3] = vv[6]
            var[k, m, 4] = vv[7]


def _neighbour_tasks(rows, cols, radius: float, max_group: int):
    """Groups for joint fitting: each spot with neighbours closer than ``radius`` (px) is fitted together
    with its nearest ``max_group - 1`` of them; identical groups are fitted once.

    Returns (grouped mask, ptr, members, report) in the layout of :func:`_fit_tasks`.
    """
    from scipy.spatial import cKDTree

    n = len(rows)
    grouped = np.zeros(n, bool)
    empty = (grouped, np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.bool_))
    if n < 2 or max_group < 2:
        return empty
    pts = np.c_[cols, rows].astype(float)
    d, idx = cKDTree(pts).query(pts, k=min(max_group, n), distance_upper_bound=radius)
    has = np.isfinite(d[:, 1])
    if not has.any():
        return empty
    grouped[has] = True
    idx = np.where(np.isfinite(d), idx, n)[has]            # missing neighbours -> n (sorted last)
    keys = np.sort(idx, axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = np.asarray(inv).ravel()
    counts = (uniq < n).sum(axis=1)
    ptr = np.zeros(len(uniq) + 1, np.int64)
    ptr[1:] = np.cumsum(counts)
    members = uniq[uniq < n].astype(np.int64)               # row-major: each task's members in order
    report = np.zeros(len(members), np.bool_)
    owners = np.nonzero(has)[0]
    # each grouped spot is reported from its own task (members are sorted, so its place is a count)
    report[ptr[inv] + (keys < owners[:, None]).sum(axis=1)] = True
    return grouped, ptr, members, report


def fit_spots(img, rows, cols, sigma: float, gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0,
              poisson: bool = True, half: int | None = None, max_iter: int = 40, amps=None,
              group_radius: float | None = None, max_group: int = 5, split: bool = False,
              split_width: float = 1.1, split_ecc: float = 0.6, split_llr: float = 12.0):
    """Fit a pixel-integrated Gaussian to each spot by maximum likelihood.

    Parameters
    ----------
    img : 2D array
        Raw frame in camera counts (``poisson=True``), or any background-
        subtracted image (``poisson=False``: least squares).
    rows, cols : array_like of int
        Starting pixels (from :func:`find_peaks`).
    sigma : float
        Starting spot width (px); the width is fitted within [sigma/4, 4 sigma].
    gain : float
        Camera counts per photon (ADU per detected photo-electron).
    offset : float
        Camera baseline (counts at zero light).
    read_noise : float
        RMS read noise (photo-electrons).
    poisson : bool
        Maximum likelihood with Poisson (+ read noise) statistics; else least squares.
    half : int, optional
        Half-width of the fitting window (px), default ceil(3 sigma), at least 3.
    amps : array_like, optional
        Relative brightness of each spot (e.g. the detection signal), used to
        share the photons between jointly fitted spots at the start.
    group_radius : float, optional
        Spots closer than this (px; default ``half + 2 sigma``, where a
        neighbour's light reaches into the fit window) are fitted jointly:
        each with its nearest ``max_group - 1`` neighbours, as a sum of
        Gaussians (own position and photons, shared background and width) over
        the union of their windows. Fitting them one by one would pull each
        centre towards its neighbour (or lose the fit), which drops or biases
        exactly the displacements where particles approach each other. 0
        disables joint fitting.
    max_group : int
        Largest number of spots in one joint fit.
    split : bool
        Test each spot fitted alone whose width exceeds ``split_width *
        sigma`` or whose eccentricity exceeds ``split_ecc`` for being two
        unresolved spots (closer than ~2.8 sigma, one maximum of the matched
        filter): a two-spot fit replaces it when the log-likelihood gains more
        than ``split_llr``, both parts carry >= 15 % of the photons and they
        are >= sigma apart. The output then has more rows than the input;
        ``index`` maps each row to its input spot.

    Returns
    -------
    dict of ndarrays
        ``x``, ``y`` (px), ``photons``, ``bg`` (photons/px), ``s`` (px),
        ``var_x``, ``var_y`` (px^2), ``ok`` (bool), ``ecc``, ``index`` (input
        spot of each row: ``arange(len(rows))`` unless spots were split).
    """
    rows = np.ascontiguousarray(rows, np.int64)
    cols = np.ascontiguousarray(cols, np.int64)
    half = max(3, int(math.ceil(3 * sigma))) if half is None else int(half)
    img = np.ascontiguousarray(img)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        img = img.astype(np.float32)
    p, v, ok, ecc = _fit_all(img, rows, cols, half, float(sigma), float(gain), float(offset),
                             float(read_noise) ** 2, bool(poisson), int(max_iter))
    radius = half + 2.0 * float(sigma) if group_radius is None else float(group_radius)
    if radius > 0 and len(rows) > 1:
        grouped, ptr, members, report = _neighbour_tasks(rows, cols, radius, int(max_group))
        if grouped.any():
            a = np.ones(len(rows)) if amps is None else np.ascontiguousarray(amps, np.float64)
            _fit_tasks(img, rows, cols, a, ptr, members, report, half, float(sigma), float(gain), float(offset),
                       float(read_noise) ** 2, bool(poisson), int(max_iter), p, v, ok, ecc)
    else:
        grouped = np.zeros(len(rows), bool)
    index = np.arange(len(rows))
    if split and len(rows):
        cand = np.nonzero(ok & ~grouped & ((p[:, 4] > split_width * sigma) | (ecc > split_ecc)))[0]
        if len(cand):
            out = np.zeros((len(cand), 2, 5))
            vout = np.zeros((len(cand), 2, 5))
            acc = np.zeros(len(cand), np.bool_)
            llr = np.full(len(cand), np.nan)
            _split_spots(img, rows, cols, p, cand.astype(np.int64), half, float(sigma), float(gain), float(offset),
                         float(read_noise) ** 2, bool(poisson), int(max_iter), float(split_llr), out, vout, acc, llr)
            if acc.any():
                q = cand[acc]
                p[q], v[q] = out[acc, 0], vout[acc, 0]
                p = np.concatenate([p, out[acc, 1]])
                v = np.concatenate([v, vout[acc, 1]])
                ok = np.concatenate([ok, np.ones(len(q), bool)])
                index = np.concatenate([index, q])
                ecc = np.concatenate([ecc, np.zeros(len(q))])
                for i in np.r_[q, np.arange(len(rows), len(p))]:   # split spots only: a few per frame
                    x, y, b = p[i, 0], p[i, 1], p[i, 3]
                    ecc[i] = _moments(img, int(round(y)), int(round(x)), half, x, y, b * gain + offset)
    return {"x": p[:, 0], "y": p[:, 1], "photons": p[:, 2], "bg": p[:, 3], "s": p[:, 4],
            "var_x": v[:, 0], "var_y": v[:, 1], "ok": ok, "ecc": ecc, "index": index}


def mortensen_sigma(photons, bg, s, a: float = 1.0):
    """Cramer-Rao localisation precision of a maximum-likelihood Gaussian fit (Mortensen et al. 2010, eq. 5).

    Parameters
    ----------
    photons : float or array
        Detected photons per spot.
    bg : float or array
        Background photons per pixel.
    s : float or array
        Gaussian width of the PSF (px, without pixelation).
    a : float
        Pixel size (same unit as ``s``; 1 for px).

    Returns
    -------
    float or ndarray
        Standard deviation per axis, in the unit of ``s``.
    """
    from scipy.special import spence

    N = np.asarray(photons, float)
    b = np.asarray(bg, float)
    sa2 = np.asarray(s, float) ** 2 + a * a / 12.0
    tau = 2 * np.pi * sa2 * b / (N * a * a)
    with np.errstate(divide="ignore", invalid="ignore"):
        # int_0^1 ln t / (1 + t/tau) dt = tau * Li2(-1/tau), Li2(z) = spence(1 - z)
        integral = np.where(tau > 1e-12, tau * spence(1.0 + 1.0 / np.maximum(tau, 1e-300)), 0.0)
    return np.sqrt(sa2 / N / (1.0 + integral))


def cramer_rao_bound(psf, oversample: int, photons: float, background: float, read_noise: float = 0.0):
    """Exact Cramer-Rao bound on x and y (px) for a sampled PSF, from its Fisher information.

    Mortensen's formula (:func:`mortensen_sigma`) assumes a Gaussian PSF; a
    real (Airy) PSF puts photons into its rings, so its bound differs. This
    computes the bound of the true pixelated PSF with Poisson photons and
    Gaussian read noise (as extra Poisson-like variance).

    Parameters
    ----------
    psf : 2D array
        Pixel-integrated PSF sampled every 1/``oversample`` px, centred on a
        sample whose indices are multiples of ``oversample`` (the layout of
        ``sim.render.psf_image(..., oversample=k)``).
    oversample : int
    photons : float
        Detected photons per spot.
    background : float
        Background photons per pixel.
    read_noise : float
        e- rms.

    Returns
    -------
    (float, float)
        Standard deviation bound for x (columns) and y (rows), px, for a
        spot centred on a pixel.
    """
    ov = int(oversample)
    P = np.asarray(psf, float)
    c = np.unravel_index(int(np.argmax(P)), P.shape)
    P = np.roll(P, (-(c[0] % ov), -(c[1] % ov)), axis=(0, 1))   # put the peak on the pixel grid
    I0 = P[0::ov, 0::ov]
    norm = I0.sum()
    mu = photons * I0 / norm + background + read_noise ** 2
    out = []
    for axis in (1, 0):
        if axis == 1:
            plus, minus = P[0::ov, 1::ov], np.roll(P[0::ov, ov - 1::ov], 1, axis=1)
        else:
            plus, minus = P[1::ov, 0::ov], np.roll(P[ov - 1::ov, 0::ov], 1, axis=0)
        d = photons * (plus - minus) / (2.0 / ov) / norm
        out.append(1.0 / np.sqrt(np.sum(d * d / mu)))
    return out[0], out[1]


def locate(frame, img=None, sigma: float = 1.5, snr: float = 7.0, separation: float | None = None,
           gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0, brightfield: bool = False,
           median: bool = True, min_photons: float = 0.0, split: bool = True) -> pd.DataFrame:
    """Detect and localise the particles of one frame.

    Parameters
    ----------
    frame : 2D array
        Raw camera frame (counts).
    img : 2D float32 array, optional
        The preprocessed frame (:func:`ptrack.preprocess.prepare`) to detect
        on. If not given, fluorescence frames take the fast path
        (:func:`detect_raw`: spatial background at block resolution) and
        brightfield frames are prepared with the spatial background.
    sigma : float
        Spot width (px); see :func:`estimate_sigma`.
    snr, separation, median
        Detection settings (:func:`find_peaks`).
    gain, offset, read_noise
        Camera model (counts per photon, baseline counts, read noise e-).
    brightfield : bool
        Inverted brightfield: least-squares fit on ``img`` instead of the
        Poisson likelihood of the raw counts.
    min_photons : float
        Drop fits with fewer photons.
    split : bool
        Split wide or elongated spots into two when a two-spot fit is much
        more likely (particles closer than the matched filter resolves); see
        :func:`fit_spots`. Spots with neighbours are always fitted jointly.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`LOCATE_COLUMNS`: ``x_px``, ``y_px`` (px), ``mass``
        (counts above background), ``size`` (fitted Gaussian width, px),
        ``ecc``, ``signal`` (matched-filter peak, counts), ``photons``,
        ``bg_photons`` (per px), ``sigma_x_px``, ``sigma_y_px`` (px, Cramer-Rao
        uncertainty at the estimate).
    """
    from .preprocess import prepare

    if img is None and not brightfield:
        # fast path: detection on the raw frame, background only at block resolution
        rows, cols, vals, aux = detect_raw(frame, sigma, snr=snr, separation=separation, median=median)
        if median and len(rows):
            half = max(3, int(math.ceil(3 * sigma)))
            noise_raw = aux["noise"] * 2.0 * math.sqrt(math.pi) * max(0.5, sigma)   # per-pixel noise (approx.)
            hr, hc, hv = _hot_in_rois(np.ascontiguousarray(frame), aux["bg"], aux["ds"], rows, cols, half,
                                      8.0 * noise_raw)
            if len(hr):
                frame = np.array(frame, copy=True)
                frame[np.asarray(hr), np.asarray(hc)] = np.asarray(hv)
    else:
        if img is None:
            img = prepare(frame, brightfield=brightfield, bg_size=max(15.0, 12 * sigma))
        m3 = median3(img) if median else None
        rows, cols, vals = find_peaks(img, sigma, snr=snr, separation=separation, median=median, filtered=m3)
        if not brightfield and median and len(rows):
            frame = repair_hot_pixels(frame, img, m3)
    if brightfield:
        fit = fit_spots(img, rows, cols, sigma, poisson=False, amps=vals, split=split)
        mass = fit["photons"]
    else:
        fit = fit_spots(frame, rows, cols, sigma, gain=gain, offset=offset, read_noise=read_noise, poisson=True,
                        amps=vals, split=split)
        mass = fit["photons"] * gain
    vals = np.asarray(vals)[fit["index"]]
    keep = fit["ok"] & (fit["photons"] > min_photons) & np.isfinite(fit["x"])
    df = pd.DataFrame({
        "x_px": fit["x"][keep], "y_px": fit["y"][keep], "mass": mass[keep], "size": fit["s"][keep],
        "ecc": fit["ecc"][keep], "signal": vals[keep], "photons": fit["photons"][keep],
        "bg_photons": fit["bg"][keep], "sigma_x_px": np.sqrt(np.abs(fit["var_x"][keep])),
        "sigma_y_px": np.sqrt(np.abs(fit["var_y"][keep])),
    })
    return df


def repair_hot_pixels(frame, img, m3, k: float = 8.0):
    """Replace isolated hot pixels of a raw frame by their 3x3 median, for the fit.

    A pixel is hot when it exceeds its brightest 8-neighbour by more than
    ``k`` noise sigmas and stands more than 3x that neighbour's height above
    the background (in the background-subtracted image ``img``): a
    diffraction-limited spot (sigma >= 0.8 px) never does, a single-pixel spike
    does. Returns ``frame`` itself when there is none.
    """
    import cv2

    nb_max = cv2.dilate(img, np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8))
    hot = (img - nb_max > k * noise_sigma(img)) & (img > 3.0 * np.maximum(nb_max, 0))
    if not hot.any():
        return frame
    out = np.array(frame, copy=True)
    H, W = out.shape
    for r, c in zip(*np.nonzero(hot)):
        nb_ = frame[max(r - 1, 0):min(r + 2, H), max(c - 1, 0):min(c + 2, W)]
        out[r, c] = np.median(nb_)
    return out


def estimate_sigma(frames, brightfield: bool = False, gain: float = 1.0, offset: float = 0.0,
                   sigma0: float = 1.5, snr: float = 10.0, max_spots: int = 300) -> float:
    """Estimate the spot width (px) from a few frames: fit the brightest isolated spots, take the median width.

    Two rounds: detect with ``sigma0``, fit, re-detect with the fitted width.

    Raises
    ------
    UserError
        No spot found in the frames.
    """
    from .preprocess import prepare

    s = float(sigma0)
    for _ in range(2):
        widths = []
        for f in frames:
            img = prepare(f, brightfield=brightfield, bg_size=max(15.0, 12 * s))
            rows, cols, vals = find_peaks(img, s, snr=snr, separation=4 * s)
            if len(rows) == 0:
                continue
            order = np.argsort(vals)[::-1][:max_spots]
            src = img if brightfield else f
            fit = fit_spots(src, rows[order], cols[order], s, gain=gain, offset=offset, poisson=not brightfield,
                            half=max(3, int(math.ceil(4 * s))))
            widths.extend(fit["s"][fit["ok"]].tolist())
        if not widths:
            raise UserError("no particle found to estimate the particle image size",
                            "check the movie (is it dark? brightfield needs --brightfield) or give --diameter")
        s_new = float(np.median(widths))
        if abs(s_new - s) < 0.05 * s:
            s = s_new
            break
        s = s_new
    return s
