"""Large templates made cheap: match at reduced resolution, then place each particle at full resolution.

A defocused image 100-400 px across carries its height in its outline and
ring radii, tens of pixels, not in single pixels. Frame and templates are
reduced by an integer factor ``f`` (area averaging, so the photon noise is
averaged too, not aliased) until the largest template is about
``target`` px; the whole matcher (:func:`ptrack.calibration.locate_3d`:
candidates, residual subtraction, splitting of merged images) runs there at
~f^4 less cost; the small (near-focus) images, whose shape the reduction
blurs, are then matched again at full resolution (:func:`refine_full`).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["match_scale", "reduced_calibration", "reduce_frame", "refine_full"]


def _antialias(img, f: int):
    """Gaussian blur of f/2 px before an f-fold area reduction: a small (in-focus) image then looks the same
    whatever its sub-pixel phase on the reduced grid (a box average alone aliases it)."""
    import cv2

    return cv2.GaussianBlur(np.ascontiguousarray(img, np.float32), (0, 0), 0.5 * f)


def match_scale(calib, target: int = 48) -> int:
    """Integer reduction factor so that the largest template is about ``target`` px (1: match as is)."""
    # at most 3: beyond, the smallest (in-focus) images shrink to a pixel or two and a few particles per frame
    # come out at a wrong height that the full-resolution refinement (near the reduced match) cannot recover
    return max(1, min(3, int(calib.size // target)))


def reduced_calibration(calib, f: int):
    """The calibration with every template reduced by ``f`` (area average; cached in ``calib.info``)."""
    import cv2

    from ..calibration import Calibration

    cache = calib.info.setdefault("_reduced", {})
    if f in cache:
        return cache[f]
    tm, cen = [], np.zeros((len(calib.templates), 2))
    for k, t in enumerate(calib.templates):
        T = t.shape[0]
        Tr = int(math.ceil(T / f)) | 1
        o = (Tr * f - T) // 2
        big = np.zeros((Tr * f, Tr * f), np.float32)
        big[o:o + T, o:o + T] = t
        tm.append(cv2.resize(_antialias(big, f), (Tr, Tr), interpolation=cv2.INTER_AREA))
        # pixel i of the reduced image covers full-resolution pixels f i .. f i + f - 1
        cen[k] = (calib.centers[k] + o + 0.5) / f - 0.5
    info = {k: v for k, v in calib.info.items() if not k.startswith("_")}
    info["template_size"] = max(t.shape[0] for t in tm)
    px = calib.pixel_size * f if calib.pixel_size else None
    red = Calibration(tm, calib.z, cen, px, calib.source, info)
    cache[f] = red
    return red


def reduce_frame(img, f: int):
    """Frame reduced by ``f`` (area average), zero-padded (background) to a multiple of ``f``."""
    import cv2

    H, W = img.shape
    Hp, Wp = -(-H // f) * f, -(-W // f) * f
    if (Hp, Wp) != (H, W):
        img = cv2.copyMakeBorder(np.ascontiguousarray(img, np.float32), 0, Hp - H, 0, Wp - W,
                                 cv2.BORDER_CONSTANT, value=0.0)
    return cv2.resize(_antialias(img, f), (Wp // f, Hp // f), interpolation=cv2.INTER_AREA)


def refine_full(img, calib, df, f: int, smooth: float = 1.5, small: int = 64):
    """x, y, z and Cm of each small image again on the full-resolution frame, near the reduced-resolution match.

    Images of ``small`` px or more keep their reduced-resolution values.
    Per small image: its best template correlated over +-(f + 1) px gives the
    position; then the templates around its height (for images under
    ``small`` px, whose shape the reduction blurred, every template under
    ``small`` px and one recorded step beyond; 3 interpolated templates
    either way for larger ones) are correlated at
    +-1 px of it, and z is the vertex of the parabola through Cm(z)
    (:func:`ptrack.calibration._quadratic_peak`); with interpolated templates
    (``n_sub`` per recorded step) and more than 4 steps' worth of them, the
    recorded pages' templates are correlated first and then the
    interpolated ones within a step of the best. A particle whose windows
    leave the frame keeps its reduced-resolution values. ``mass``: the
    least-squares amplitude of the best full-resolution template times its
    signal.
    """
    import cv2

    from ..calibration import _gauss3, _quadratic_peak, _subpixel_peaks, smoothed_templates
    from .ncc import ncc, ncc_corners

    if len(df) == 0:
        return df
    H, W = img.shape
    img32 = np.ascontiguousarray(img, np.float32)
    sm = cv2.GaussianBlur(img32, (0, 0), smooth) if smooth else img32
    tm = smoothed_templates(calib, smooth)
    K = len(tm)
    sizes = tm.packed[2]
    cen = np.asarray(calib.centers, np.float64)
    n_sub = int(calib.info.get("n_sub", 1))
    out = df.copy()
    xs, ys, zs, cms, pages, mass = (out[c].to_numpy().copy() for c in ("x_px", "y_px", "z", "cm", "page", "mass"))
    for i in range(len(out)):
        k = int(pages[i])
        t = tm[k]
        T = t.shape[0]
        if T >= small:
            # a large image keeps its reduced-resolution match: its ring radii span many reduced pixels, and the
            # full-resolution search around it was measured worse (512^2, +-10 um stack: 3 px and 0.5 um off
            # for the particles at the ends of the range)
            continue
        cy, cx = calib.centers[k]
        m = f + 1
        top, left = int(round(ys[i] - cy)) - m, int(round(xs[i] - cx)) - m
        if top < 0 or left < 0 or top + T + 2 * m > H or left + T + 2 * m > W:
            continue
        R = ncc(sm[top:top + T + 2 * m, left:left + T + 2 * m], t)
        a, b = np.unravel_index(int(np.argmax(R)), R.shape)
        y0, x0 = top + a + cy, left + b + cx           # integer-placed centre
        if T < small:
            # a small image: its shape was blurred by the reduction, its reduced-resolution z may be pages off;
            # small templates are cheap: all of them near focus (one recorded step beyond)
            js = np.nonzero(sizes < small)[0]
            js = np.arange(max(0, js.min() - n_sub), min(K, js.max() + n_sub + 1))
        else:
            js = np.arange(max(0, k - 3), min(K, k + 4))
        maps = np.full((len(js), 3, 3), -1.0, np.float32)
        done = np.zeros(len(js), bool)

        def corr(qs):
            # each template at +-1 px of the integer-placed centre, all in one call (False: a window leaves the frame)
            j = js[qs]
            tp = np.round(y0 - cen[j, 0]).astype(np.int64) - 1      # round half to even, as round()
            lf = np.round(x0 - cen[j, 1]).astype(np.int64) - 1
            if np.any((tp < 0) | (lf < 0) | (tp + sizes[j] + 2 > H) | (lf + sizes[j] + 2 > W)):
                return False
            maps[qs] = ncc_corners(sm, tm, j, tp, lf, 3)
            done[qs] = True
            return True

        if n_sub > 1 and len(js) > 4 * n_sub:
            # coarse to fine, as the match itself (ptrack.calibration._match_one): the templates of the recorded
            # pages first, then the interpolated ones within a step of the best (+-30 um stack in 2 um steps,
            # 512^2: ~180 -> ~40 correlations per small image)
            first = np.nonzero(js % n_sub == 0)[0]
            ok = corr(first)
            if ok:
                np.copyto(maps, -1.0, where=np.isnan(maps))
                qb = int(first[np.argmax(_subpixel_peaks(maps[first]))])
                ok = corr(np.arange(max(0, qb - n_sub - 1), min(len(js), qb + n_sub + 2)))
        else:
            ok = corr(np.arange(len(js)))
        if not ok:
            continue
        np.copyto(maps, -1.0, where=np.isnan(maps))
        peak = np.full(K, -1.0)
        peak[js[done]] = _subpixel_peaks(maps[done])
        kb = int(np.argmax(peak))
        zs[i] = _quadratic_peak(calib.z, peak, kb, None, 0.15)
        cms[i] = min(float(peak[kb]), 1.0)
        mp = maps[kb - js[0]]
        a, b = np.unravel_index(int(np.argmax(mp)), mp.shape)
        di = _gauss3(mp[a - 1, b], mp[a, b], mp[a + 1, b]) if 0 < a < 2 else 0.0
        dj = _gauss3(mp[a, b - 1], mp[a, b], mp[a, b + 1]) if 0 < b < 2 else 0.0
        tp, lf = int(round(y0 - calib.centers[kb][0])) - 1 + a, int(round(x0 - calib.centers[kb][1])) - 1 + b
        ys[i] = tp + di + calib.centers[kb][0]
        xs[i] = lf + dj + calib.centers[kb][1]
        pages[i] = kb
        # brightness from the full-resolution image: least-squares amplitude of the best template (a template
        # of a few reduced pixels explains only part of a small image's light)
        tb = calib.templates[kb]
        win = img[tp:tp + tb.shape[0], lf:lf + tb.shape[1]]
        den = float((tb * tb).sum())
        if win.shape == tb.shape and den > 0:
            mass[i] = max(float((tb * win).sum()) / den, 0.0) * float(np.clip(tb, 0, None).sum())
    out["x_px"], out["y_px"], out["z"], out["cm"], out["page"] = xs, ys, zs, cms, pages
    out["mass"] = mass
    return out
