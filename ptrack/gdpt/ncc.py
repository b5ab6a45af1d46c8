"""Zero-normalised cross-correlation at a few shifts: the inner loop of template matching.

A match correlates a window with dozens of templates at 3 x 3 to 9 x 9
shifts each. OpenCV's ``matchTemplate`` computes such small maps through a
DFT whose set-up dominates (a 51 px template: ~100 us for 5 x 5 shifts, more
than for 9 x 9); the direct sum here costs (shifts x template pixels) and
is 1.3-5x faster for maps of up to :data:`DIRECT_MAX` shifts. Larger maps
(a whole frame) stay with OpenCV.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["ncc", "DIRECT_MAX"]

DIRECT_MAX = 121     # shifts (rows x cols of the map) up to which the direct sum is used (11 x 11)


@njit(cache=True, fastmath=True)
def _ncc_direct(win, t):
    T0, T1 = t.shape
    H, W = win.shape
    ny, nx = H - T0 + 1, W - T1 + 1
    N = T0 * T1
    tm = 0.0
    for a in range(T0):
        for b in range(T1):
            tm += t[a, b]
    tm /= N
    tz = np.empty((T0, T1), np.float32)
    tn = 0.0
    for a in range(T0):
        for b in range(T1):
            v = t[a, b] - tm
            tz[a, b] = v
            tn += v * v
    # window sums and sums of squares at every shift from double-precision integral images (the variance is
    # a difference of two large sums)
    S1 = np.zeros((H + 1, W + 1))
    S2 = np.zeros((H + 1, W + 1))
    for a in range(H):
        r1 = 0.0
        r2 = 0.0
        for b in range(W):
            w = np.float64(win[a, b])
            r1 += w
            r2 += w * w
            S1[a + 1, b + 1] = S1[a, b + 1] + r1
            S2[a + 1, b + 1] = S2[a, b + 1] + r2
    out = np.empty((ny, nx), np.float32)
    acc = np.empty(nx, np.float32)
    for i in range(ny):
        acc[:] = 0.0
        for a in range(T0):
            row = win[i + a]
            trow = tz[a]
            for j in range(nx):
                s = np.float32(0.0)
                for b in range(T1):
                    s += row[j + b] * trow[b]
                acc[j] += s
        for j in range(nx):
            s1 = S1[i + T0, j + T1] - S1[i, j + T1] - S1[i + T0, j] + S1[i, j]
            s2 = S2[i + T0, j + T1] - S2[i, j + T1] - S2[i + T0, j] + S2[i, j]
            d = np.sqrt(max(s2 - s1 * s1 / N, 0.0) * tn)
            # a constant window (zero padding) or template: no correlation (OpenCV gives NaN there, which the
            # callers turn into -1)
            out[i, j] = acc[j] / d if d > 0 else -1.0
    return out


def ncc(win, t) -> np.ndarray:
    """``cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)`` (float32 map of shape win - t + 1).

    Parameters
    ----------
    win : (H, W) float32 array
        Image window (any strides).
    t : (T0, T1) float32 array
        Template, T0 <= H, T1 <= W.

    Returns
    -------
    (H - T0 + 1, W - T1 + 1) float32 array
        Correlation at each shift, in [-1, 1]; -1 where the window or the
        template is constant (OpenCV: NaN). Maps of up to
        :data:`DIRECT_MAX` shifts by a direct sum (agrees with OpenCV to
        ~2e-7), larger ones by OpenCV.
    """
    ny, nx = win.shape[0] - t.shape[0] + 1, win.shape[1] - t.shape[1] + 1
    if ny * nx <= DIRECT_MAX and win.dtype == np.float32 and t.dtype == np.float32:
        return _ncc_direct(win, t)
    import cv2

    return cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)
