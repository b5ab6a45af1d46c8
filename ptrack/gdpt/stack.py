"""Calibration stacks as people record them: find the bead(s) on each page, cut and average their templates.

A real stack is a series of full camera frames (or crops) of one or several
beads stuck on the glass while the stage steps through z. Each page gets a
background estimated from its own bead-free pixels (a constant for small
crops, a quadratic surface for full frames with uneven illumination), the
beads are found as connected regions of the smoothed signal (ring pieces
joined, holes filled) and followed from page to page, and each bead's
template is cut to the extent of that page's image. Pages where a bead is
missing, cut by the page edge or merged with another bead's image are
rejected for that bead (and named); a page rejected for every bead is
dropped from the calibration.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import UserError

# template half-side / 95 % light radius. Fluorescence 1.35: the 95 % radius is measured on the bead's own region
# (the old whole-page rule, 1.2 x, counted positive noise far out and gave ~2 px larger in-focus templates, which
# the matching thresholds were tuned for). Brightfield (signed) 1.2: its radius, on the magnitude of the signal,
# comes out as before (1.35 made epd_brightfield's templates 2 px larger than the old ones, and z worse)
TEMPLATE_SCALE = 1.35
TEMPLATE_SCALE_SIGNED = 1.2
SYMMETRISE = True       # each page's template averaged with its point reflection about the bead (see symmetrised)

__all__ = ["stack_polarity", "page_background", "find_beads", "bead_tracks", "cut_templates"]


def _mad(x) -> float:
    x = np.asarray(x, np.float64).ravel()
    return 1.4826 * float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def stack_polarity(stack, sigma: float = 2.0):
    """("bright" or "dark", ratio): the sign of the strongest (smoothed) excursion from the median over all pages.

    A calibration bead near focus is unmistakable: fluorescence stacks have
    positive excursions hundreds of times the negative ones, brightfield the
    reverse (data/synthetic: ratios 58-2600). ``ratio`` is the larger over
    the smaller.
    """
    import cv2

    hi = lo = 0.0
    for p in np.asarray(stack, np.float32):
        sm = cv2.GaussianBlur(p - np.median(p), (0, 0), float(sigma))
        hi, lo = max(hi, float(sm.max())), max(lo, float(-sm.min()))
    return ("bright" if hi >= lo else "dark"), max(hi, lo) / max(min(hi, lo), 1e-9)


def page_background(page, mask=None):
    """Background of one page (ADU) and the noise of its bead-free pixels.

    Parameters
    ----------
    page : 2D float array
    mask : 2D bool array, optional
        Pixels holding signal (excluded).

    Returns
    -------
    bg : 2D float32 array (same shape)
        A constant (pages under 128 px a side) or a quadratic surface fitted
        to the medians of 16 x 16 px blocks free of signal (uneven
        illumination of a full frame).
    noise : float
        Robust standard deviation of the bead-free pixels around ``bg``.
    """
    p = np.asarray(page, np.float32)
    H, W = p.shape
    free = np.ones(p.shape, bool) if mask is None else ~mask
    if free.sum() < 0.05 * p.size:
        free = np.ones(p.shape, bool)
    if min(H, W) < 128:
        v = p[free]
        bg = np.full(p.shape, float(np.median(v)), np.float32)
    else:
        b = 16
        hb, wb = H // b, W // b
        blk = p[:hb * b, :wb * b].reshape(hb, b, wb, b)
        fr = free[:hb * b, :wb * b].reshape(hb, b, wb, b)
        vals, ys, xs = [], [], []
        for i in range(hb):            # a few hundred blocks, once per page: not a hot path
            for j in range(wb):
                f = fr[i, :, j, :]
                if f.mean() > 0.9:
                    vals.append(float(np.median(blk[i, :, j, :][f])))
                    ys.append((i + 0.5) * b / H - 0.5)
                    xs.append((j + 0.5) * b / W - 0.5)
        if len(vals) < 12:
            bg = np.full(p.shape, float(np.median(p[free])), np.float32)
        else:
            ys, xs, vals = np.array(ys), np.array(xs), np.array(vals)
            A = np.stack([np.ones_like(ys), ys, xs, ys * ys, ys * xs, xs * xs], 1)
            # robust: one refit without the blocks more than 3 MAD off (dirt, faint halo of a bead)
            coef = np.linalg.lstsq(A, vals, rcond=None)[0]
            r = vals - A @ coef
            ok = np.abs(r) <= 3 * max(_mad(r), 1e-6)
            if ok.sum() >= 12:
                coef = np.linalg.lstsq(A[ok], vals[ok], rcond=None)[0]
            yy = (np.arange(H) / H - 0.5)[:, None]
            xx = (np.arange(W) / W - 0.5)[None, :]
            bg = (coef[0] + coef[1] * yy + coef[2] * xx + coef[3] * yy * yy + coef[4] * yy * xx
                  + coef[5] * xx * xx).astype(np.float32)
    noise = _mad((p - bg)[free]) + 1e-6
    return bg, noise


def _signal_mask(p, noise, signed: bool, sigma: float, k: float):
    """Smoothed signal above ``k`` of its own noise, pieces of a ring joined and holes filled."""
    import cv2
    from scipy import ndimage as ndi

    s = cv2.GaussianBlur(np.ascontiguousarray(p, np.float32), (0, 0), float(sigma))
    if signed:
        s = np.abs(s)
        base = float(np.median(s))
        s = s - base
    ns = _mad(s[::2, ::2]) + 1e-6 if not signed else _mad(s) + 1e-6
    m = (s > k * ns).astype(np.uint8)
    r = max(2, int(round(2 * sigma)))
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return ndi.binary_fill_holes(m > 0), s, ns


def _regions(p, noise, signed: bool, sigma: float, k: float, min_frac: float, raw_extent: bool):
    """Bead regions of a background-subtracted page at one smoothing scale (see :func:`find_beads`)."""
    import cv2

    mask, s, ns = _signal_mask(p, noise, signed, sigma, k)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return []
    H, W = p.shape
    if not raw_extent:
        # faint, large images (a few photons per pixel over a wide ring): centre and extent on the smoothed page
        exc = np.clip(s - 2.0 * ns, 0, None)
    elif signed:
        # magnitude of the (1 px smoothed) signed signal: the bright lobes count as much as the dark ones
        mag = np.abs(cv2.GaussianBlur(p, (0, 0), 1.0))
        base = float(np.median(mag))
        exc = np.clip(mag - base - 2.0 * (_mad(mag) + 1e-6), 0, None)
    else:
        exc = np.clip(p - 2.0 * noise, 0, None)     # noise-free support: positive noise would fill the page
    flux = np.bincount(lab.ravel(), weights=exc.ravel(), minlength=n)
    flux[0] = 0.0
    out = []
    keep = [i for i in range(1, n) if flux[i] >= min_frac * flux.max() and stats[i, cv2.CC_STAT_AREA] >= 4]
    for i in keep:
        x0, y0, w, h = (int(stats[i, j]) for j in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH,
                                                   cv2.CC_STAT_HEIGHT))
        edge = x0 <= 0 or y0 <= 0 or x0 + w >= W or y0 + h >= H
        bbox = (y0, y0 + h, x0, x0 + w)
        # the region grown by half its radius (>= 6 px), without other regions: the faint outskirts
        # of the image below the threshold still count towards its 95 % radius
        g = max(6, int(round(0.5 * math.sqrt(stats[i, cv2.CC_STAT_AREA] / math.pi))))
        y0, x0, y1, x1 = max(y0 - g, 0), max(x0 - g, 0), min(y0 + h + g, H), min(x0 + w + g, W)
        li = lab[y0:y1, x0:x1]
        sub = cv2.dilate((li == i).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1,) * 2))
        sub = (sub > 0) & ((li == 0) | (li == i))
        e = np.where(sub, exc[y0:y1, x0:x1], 0.0)
        # centre: thresholded centroid (20 % of the peak), robust to a faint halo
        thr = 0.2 * float(e.max())
        wgt = np.clip(e - thr, 0, None)
        sw = float(wgt.sum())
        if sw <= 0:
            continue
        rr, cc = np.indices(e.shape)
        cy = float((wgt * rr).sum() / sw) + y0
        cx = float((wgt * cc).sum() / sw) + x0
        d = np.hypot(rr + y0 - cy, cc + x0 - cx).ravel()
        order = np.argsort(d)
        cum = np.cumsum(e.ravel()[order])
        r95 = float(d[order][np.searchsorted(cum, 0.95 * cum[-1])]) if cum[-1] > 0 else 3.0
        if not raw_extent:
            r95 = math.sqrt(max(r95 * r95 - (2.45 * sigma) ** 2, 0.0)) + sigma   # minus most of the blur's own
        # cut by the page edge: the disc holding 95 % of the light leaves the page (a region touching the edge
        # may be only the faint tail of a bright image, or the spread of a coarse smoothing)
        edge = bool(edge) and (cy < r95 or cx < r95 or cy > H - 1 - r95 or cx > W - 1 - r95)
        out.append({"y": cy, "x": cx, "r95": max(r95, 1.5), "bbox": bbox, "edge": bool(edge),
                    "flux": float(flux[i]), "sigma": float(sigma)})
    return out


def find_beads(page, signed: bool = False, sigmas=(2.0, 5.0, 12.0), k: float = 5.0, min_frac: float = 0.05):
    """Bead images on one calibration page.

    Regions of the smoothed page above ``k`` noise units, each bead at the
    finest of the smoothing scales ``sigmas`` that still sees it whole: the
    beads are the regions at the coarsest scale, and each is replaced by
    the region a finer scale finds in it while that is a single region on
    its centre (not a ring in pieces, nor a piece of a faint ring). In-focus images end at the finest scale, with
    the extent measured on the unsmoothed page.

    Parameters
    ----------
    page : 2D array
        The page (particles bright; brightfield already inverted).
    signed : bool
        Brightfield: images with lobes on both sides of the field.
    sigmas : tuple of float
        Smoothing scales (px), finest first.
    k : float
        Threshold, units of the smoothed image's noise.
    min_frac : float
        Regions with less than this fraction of the brightest region's
        excess signal are ignored (dirt, hot pixels).

    Returns
    -------
    beads : list of dict
        ``y``, ``x`` (centre, px), ``r95`` (radius holding 95 % of the
        excess light, px), ``bbox`` (r0, r1, c0, c1), ``edge`` (the region
        touches the page border), ``flux``.
    p : 2D float32
        The background-subtracted page.
    noise : float
    """
    import cv2

    raw = np.asarray(page, np.float32)
    bg, noise = page_background(raw)
    mask = np.zeros(raw.shape, bool)
    for sg in (sigmas[0], sigmas[-1]):
        mask |= _signal_mask(raw - bg, noise, signed, sg, k)[0]
    # background again without the beads' pixels (their halo would raise a median of the whole page)
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    bg, noise = page_background(raw, grown)
    p = raw - bg
    best = None
    for j in range(len(sigmas) - 1, -1, -1):
        reg = _regions(p, noise, signed, sigmas[j], k, min_frac, raw_extent=(j == 0))
        if best is None:
            best = reg or None
            continue
        # per bead: the finer scale replaces the coarser where exactly one finer region lies in the bead's
        # coarse region, on its centre (a ring in pieces, or only a piece of a faint ring, keeps the coarse one)
        for i, b in enumerate(best):
            r0, r1, c0, c1 = b["bbox"]
            inside = [q for q in reg if r0 <= q["y"] < r1 and c0 <= q["x"] < c1]
            if len(inside) == 1 and math.hypot(inside[0]["x"] - b["x"], inside[0]["y"] - b["y"]) <= max(
                    3.0, 0.3 * b["r95"]):
                best[i] = inside[0]
    return best or [], p, noise


def symmetric_centre(p, cy: float, cx: float, r: float, sigma: float = 1.5, iterations: int = 2):
    """Centre (row, col, px) of a point-symmetric particle image, from its correlation with its own 180-degree rotation.

    A defocused (and astigmatic) image of a bead is symmetric about the bead: I(c + d) = I(c - d) for pupil
    aberrations even in the pupil coordinate (defocus, astigmatism, spherical), in fluorescence and brightfield
    alike. Its convolution with itself then peaks at exactly 2 c (there it is the image's energy, by
    Cauchy-Schwarz the largest value), whatever the shape: a ring, two line foci or a spot, every pixel of the
    image counts. The thresholded centroid of :func:`_regions` uses the few pixels above 20 % of a noisy peak
    and was 2-4 px off on defocused pages (astigmatic, 6 um from focus: the matched x, y inherited it).

    Parameters
    ----------
    p : 2D array
        Background-subtracted page.
    cy, cx : float
        Start (px).
    r : float
        Radius holding the image's light (px); the window is 1.5 r + 4 px either side.
    sigma : float
        Gaussian smoothing (px) first (symmetric: no bias, less noise).
    iterations : int
        The window is re-centred on the result this many times.

    Returns
    -------
    (cy, cx) : float, px; the start if the window is empty or its peak lies on the window's edge.
    """
    import cv2
    import scipy.fft as sfft

    H, W = p.shape
    h = int(math.ceil(1.5 * r)) + 4
    y, x = float(cy), float(cx)
    for _ in range(int(iterations)):
        r0, r1 = max(int(round(y)) - h, 0), min(int(round(y)) + h + 1, H)
        c0, c1 = max(int(round(x)) - h, 0), min(int(round(x)) + h + 1, W)
        w = np.ascontiguousarray(p[r0:r1, c0:c1], np.float32)
        if w.shape[0] < 5 or w.shape[1] < 5 or not np.any(w):
            break
        if sigma > 0:
            w = cv2.GaussianBlur(w, (0, 0), float(sigma), borderType=cv2.BORDER_CONSTANT)
        a, b = w.shape
        sh = (sfft.next_fast_len(2 * a - 1), sfft.next_fast_len(2 * b - 1))
        f = sfft.rfft2(w.astype(np.float64), s=sh)
        cc = sfft.irfft2(f * f, s=sh)[:2 * a - 1, :2 * b - 1]      # full convolution of w with itself
        i, j = np.unravel_index(int(np.argmax(cc)), cc.shape)
        if not (0 < i < cc.shape[0] - 1 and 0 < j < cc.shape[1] - 1):
            break

        def vertex(m0, m1, m2):
            d = m0 - 2.0 * m1 + m2
            return 0.5 * (m0 - m2) / d if d < 0 else 0.0

        y = r0 + (i + vertex(cc[i - 1, j], cc[i, j], cc[i + 1, j])) / 2.0
        x = c0 + (j + vertex(cc[i, j - 1], cc[i, j], cc[i, j + 1])) / 2.0
    return y, x


def bead_tracks(found, max_beads: int | None = None):
    """Follow the beads from page to page.

    The beads are those of the page with the most compact bright image
    (near focus); on every page each bead takes the
    region nearest its last position within its image radius + 10 px, and a
    region claimed by two beads (their images merged) is given to neither.

    Parameters
    ----------
    found : list (one per page) of lists of bead dicts (:func:`find_beads`)

    Returns
    -------
    list (one per bead) of lists (one per page) of the bead dict or None
    """
    K = len(found)
    counts = [len(f) for f in found]
    if max(counts) == 0:
        return []
    # the reference page: the most compact bright image (near focus), where beads are most clearly apart;
    # its beads are the regions with at least 20 % of the brightest one's light (not dirt or noise)
    ref = max((k for k in range(K) if counts[k]), key=lambda k: max(b["flux"] / b["r95"] ** 2 for b in found[k]))
    fmax = max(b["flux"] for b in found[ref])
    beads = sorted((b for b in found[ref] if b["flux"] >= 0.2 * fmax), key=lambda b: -b["flux"])
    if max_beads:
        beads = beads[:max_beads]
    tracks = [[None] * K for _ in beads]
    for j, b in enumerate(beads):
        tracks[j][ref] = b
    for direction in (range(ref + 1, K), range(ref - 1, -1, -1)):
        last = [dict(b) for b in beads]
        for k in direction:
            claims = {}
            for j, b in enumerate(last):
                best, bd = None, np.inf
                for i, f in enumerate(found[k]):
                    d = math.hypot(f["x"] - b["x"], f["y"] - b["y"])
                    if d < bd:
                        best, bd = i, d
                if best is not None and bd <= max(b["r95"], found[k][best]["r95"]) * 0.5 + 10.0:
                    claims.setdefault(best, []).append(j)
            for i, js in claims.items():
                if len(js) == 1:
                    tracks[js[0]][k] = found[k][i]
                    last[js[0]] = found[k][i]
                else:
                    for j in js:
                        tracks[j][k] = {"merged": True}
    return tracks


def cut_templates(pages, tracks, z, signed: bool, template_size: int | None = None):
    """Per bead, its template on every page where it is whole, alone and inside the page.

    Parameters
    ----------
    pages : list of 2D float32
        Background-subtracted pages.
    tracks : from :func:`bead_tracks`
    z : array (K,)
    signed : bool
    template_size : int, optional
        Fixed template side (px).

    Returns
    -------
    per_bead : list of dict
        ``templates`` (K entries: array or None), ``centers`` (K, 2),
        ``xy`` (median page position, px), ``why`` (K entries: reason a page
        was rejected, or "").
    """
    from scipy.ndimage import median_filter

    K = len(pages)
    H, W = pages[0].shape
    out = []
    for tr in tracks:
        ok = np.array([t is not None and not t.get("merged") for t in tr])
        why = ["" if ok[k] else ("images of two beads merged" if tr[k] is not None else "no bead") for k in range(K)]
        if ok.sum() == 0:
            out.append({"templates": [None] * K, "centers": np.zeros((K, 2)), "xy": (np.nan, np.nan), "why": why})
            continue
        r95 = np.array([t["r95"] if ok[k] else np.nan for k, t in enumerate(tr)])
        # each page's centre from the image's point symmetry (the thresholded centroid is off on defocused pages)
        cyx = np.array([symmetric_centre(pages[k], t["y"], t["x"], t["r95"]) if ok[k] else (np.nan, np.nan)
                        for k, t in enumerate(tr)])
        idx = np.nonzero(ok)[0]
        if len(idx) >= 5:
            # the bead's lateral position drifts slowly but each page's centre is noisy: a quadratic trend in z,
            # each page weighted by 1 / its centre's error, which grows as the image's area (r95^2) for a
            # background-limited image (unweighted, the noisy far-defocus pages moved the in-focus centres by 0.3 px)
            zn = (z - z.mean()) / (np.ptp(z) or 1.0)
            wz = 1.0 / np.maximum(r95[idx], 1.5) ** 2
            for a in range(2):
                cyx[idx, a] = np.polyval(np.polyfit(zn[idx], cyx[idx, a], 2, w=wz), zn[idx])
        if signed and len(idx) >= 7:
            # brightfield: one page's 95 % radius is noisy (faint outer rings come and go): running median
            r95[idx] = median_filter(r95[idx], size=7, mode="nearest")
        templates, centers = [None] * K, np.zeros((K, 2))
        for k in idx:
            cy, cx = cyx[k]
            # each page its own square template sized to its image (TEMPLATE_SCALE x the 95 % radius, >= 7 px): a small
            # in-focus spot is not drowned in the noise of a window sized for the most defocused page
            T = int(template_size) | 1 if template_size is not None else int(2 * math.ceil(max((TEMPLATE_SCALE_SIGNED if signed else TEMPLATE_SCALE) * r95[k], 3.0)) + 1)
            h = T // 2
            r0, c0 = int(round(cy)) - h, int(round(cx)) - h
            if tr[k]["edge"]:
                why[k] = "bead cut by the page edge"
                continue
            # the window may leave the page where the image itself does not: the rest is background (zero)
            t = np.zeros((T, T), np.float32)
            rs, cs, re, ce = max(r0, 0), max(c0, 0), min(r0 + T, H), min(c0 + T, W)
            t[rs - r0:re - r0, cs - c0:ce - c0] = pages[k][rs:re, cs:ce]
            if t.std() == 0:
                why[k] = "constant page"
                continue
            if SYMMETRISE:
                t = symmetrised(t, cy - r0, cx - c0)
            templates[k] = t
            centers[k] = (cy - r0, cx - c0)
        xy = (float(np.nanmedian(cyx[:, 1])), float(np.nanmedian(cyx[:, 0])))
        out.append({"templates": templates, "centers": centers, "xy": xy, "why": why})
    return out


def symmetrised(t, cy: float, cx: float):
    """Template ``t`` averaged with its own point reflection about (cy, cx) (px, sub-pixel: a Fourier shift).

    A bead's image is point-symmetric about the bead (:func:`symmetric_centre`); one page's noise is not, and
    shifts the correlation peak of every match made with that template (a faint defocused page: by up to
    px). The average keeps the image, halves the noise variance, and its correlation with a symmetric image
    peaks exactly at (cy, cx)."""
    import scipy.fft as sfft

    t = np.asarray(t, np.float64)
    H, W = t.shape
    f = t[::-1, ::-1]           # f(i) = t(H - 1 - i); wanted t(2 c - i) = f(i - (2 c - H + 1))
    sy, sx = 2.0 * cy - (H - 1), 2.0 * cx - (W - 1)
    ky = np.fft.fftfreq(H)[:, None]
    kx = np.fft.rfftfreq(W)[None, :]
    g = sfft.irfft2(sfft.rfft2(f) * np.exp(-2j * np.pi * (ky * sy + kx * sx)), s=(H, W))
    return (0.5 * (t + g)).astype(np.float32)


def centred(t, cy, cx, T: int):
    """Template ``t`` moved so that its particle centre (cy, cx) sits on the centre pixel of a T x T array."""
    import cv2

    h = T // 2
    M = np.float32([[1, 0, h - cx], [0, 1, h - cy]])
    return cv2.warpAffine(np.ascontiguousarray(t, np.float32), M, (T, T), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def average_beads(per_bead, K: int):
    """One template per page from several beads: registered on their centres, flux-normalised, averaged.

    Returns
    -------
    templates : list (K) of array or None
    centers : ndarray (K, 2)
    n_used : ndarray (K,) int
    """
    templates, centers, n_used = [None] * K, np.zeros((K, 2)), np.zeros(K, int)
    for k in range(K):
        ts = [(b["templates"][k], b["centers"][k]) for b in per_bead if b["templates"][k] is not None]
        if not ts:
            continue
        if len(ts) == 1:
            templates[k], centers[k] = ts[0]
            n_used[k] = 1
            continue
        T = max(t.shape[0] for t, _ in ts)
        acc = np.zeros((T, T), np.float64)
        fl = []
        for t, c in ts:
            f = float(np.abs(t).sum()) or 1.0
            fl.append(f)
            acc += centred(t, c[0], c[1], T) / f
        templates[k] = (acc / len(ts) * float(np.mean(fl))).astype(np.float32)
        centers[k] = (T // 2, T // 2)
        n_used[k] = len(ts)
    return templates, centers, n_used


def rejected_summary(per_bead, z) -> dict:
    """{page: reason} for pages no bead could be used on; warns naming them."""
    K = len(z)
    bad = {}
    for k in range(K):
        if all(b["templates"][k] is None for b in per_bead):
            reasons = sorted({b["why"][k] for b in per_bead if b["why"][k]}) or ["no bead"]
            bad[k] = "; ".join(reasons)
    if bad:
        items = ", ".join(f"{k} (z = {z[k] * 1e6:+.2f} µm: {r})" for k, r in list(bad.items())[:8])
        more = f" and {len(bad) - 8} more" if len(bad) > 8 else ""
        warnings.warn(f"calibration pages rejected: {items}{more}", stacklevel=3)
    return bad


def require_pages(n_ok: int, bad: dict, z):
    if n_ok < 3:
        some = ", ".join(f"{k}: {r}" for k, r in list(bad.items())[:5])
        raise UserError(f"only {n_ok} calibration page(s) show a whole bead ({some})",
                        "give a stack whose pages show the bead inside the page, at least 3 heights")
