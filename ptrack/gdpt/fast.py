"""Large templates made cheap: match at reduced resolution, then place each particle at full resolution.

A defocused image 100-400 px across carries its height in its outline and
ring radii, tens of pixels, not in single pixels. Frame and templates are
reduced by an integer factor ``f`` (area averaging, so the photon noise is
averaged too, not aliased) until the largest template is about
``target`` px; the whole matcher (:func:`ptrack.calibration.locate_3d`:
candidates, residual subtraction, splitting of merged images) runs there at
~f^4 less cost, and x, y of each particle are then refined on the full
resolution frame with its best template alone (one correlation over
+-(f + 1) px).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["match_scale", "reduced_calibration", "reduce_frame", "refine_xy"]


def _antialias(img, f: int):
    """Gaussian blur of f/2 px before an f-fold area reduction: a small (in-focus) image then looks the same
    whatever its sub-pixel phase on the reduced grid (a box average alone aliases it)."""
    import cv2

    return cv2.GaussianBlur(np.ascontiguousarray(img, np.float32), (0, 0), 0.5 * f)


def match_scale(calib, target: int = 48) -> int:
    """Integer reduction factor so that the largest template is about ``target`` px (1: match as is)."""
    return max(1, int(calib.size // target))


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


def refine_xy(img, calib, df, f: int, smooth: float = 1.5):
    """x, y of each particle on the full-resolution frame: its best template correlated over +-(f + 1) px.

    Kept only where the correlation peak lies inside the search window and
    the template inside the frame (else the reduced-resolution position
    stays).
    """
    import cv2

    from ..calibration import _gauss3

    if len(df) == 0:
        return df
    H, W = img.shape
    sm = cv2.GaussianBlur(np.ascontiguousarray(img, np.float32), (0, 0), smooth) if smooth else img
    m = f + 1
    xs, ys = df["x_px"].to_numpy().copy(), df["y_px"].to_numpy().copy()
    for i, k in enumerate(df["page"].to_numpy()):
        t = calib.templates[int(k)]
        T = t.shape[0]
        cy, cx = calib.centers[int(k)]
        top, left = int(round(ys[i] - cy)) - m, int(round(xs[i] - cx)) - m
        if top < 0 or left < 0 or top + T + 2 * m > H or left + T + 2 * m > W:
            continue
        tt = cv2.GaussianBlur(t, (0, 0), smooth) if smooth else t
        R = cv2.matchTemplate(sm[top:top + T + 2 * m, left:left + T + 2 * m], tt, cv2.TM_CCOEFF_NORMED)
        a, b = np.unravel_index(int(np.argmax(R)), R.shape)
        if not (0 < a < R.shape[0] - 1 and 0 < b < R.shape[1] - 1):
            continue
        ys[i] = top + a + _gauss3(R[a - 1, b], R[a, b], R[a + 1, b]) + cy
        xs[i] = left + b + _gauss3(R[a, b - 1], R[a, b], R[a, b + 1]) + cx
    out = df.copy()
    out["x_px"], out["y_px"] = xs, ys
    return out
