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

__all__ = ["ncc", "ncc_pages", "ncc_pages_strided", "DIRECT_MAX"]

DIRECT_MAX = 121     # shifts (rows x cols of the map) up to which the direct sum is used (11 x 11)


@njit(cache=True, fastmath=True)
def _setup(win, t):
    # what every correlation map needs besides the dot products: the zero-mean template and its sum of squares,
    # and the window's sums and sums of squares at every shift from double-precision integral images (the
    # variance is a difference of two large sums)
    T0, T1 = t.shape
    H, W = win.shape
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
    return tz, tn, S1, S2


@njit(cache=True, fastmath=True)
def _ncc_direct(win, t):
    # a contiguous copy of the window (a few thousand floats): with a slice's unknown strides the inner dot
    # product is not vectorised (a 49 px template at 9 x 9 shifts: 109 -> 24 us)
    win = np.ascontiguousarray(win)
    T0, T1 = t.shape
    H, W = win.shape
    ny, nx = H - T0 + 1, W - T1 + 1
    N = T0 * T1
    tz, tn, S1, S2 = _setup(win, t)
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


@njit(cache=True)
def _ncc_pages(img, ri, ci, m, flat, offs, sizes, pages, crop, a0, a1, b0, b1, out):
    # one match's correlations for many pages in one call (the per-call overhead of ~60 small maps per match)
    for q in range(len(pages)):
        k = pages[q]
        T = sizes[k]
        t = flat[offs[k]:offs[k] + T * T].reshape((T, T))
        Tc = crop if crop > 0 else T
        o = (T - Tc) // 2
        h = Tc // 2
        win = img[ri - h - m + a0: ri + h - m + a1, ci - h - m + b0: ci + h - m + b1]
        out[q, :, :] = -1.0
        out[q, a0:a1, b0:b1] = _ncc_direct(win, t[o:o + Tc, o:o + Tc])


@njit(cache=True, fastmath=True)
def _dot(a, b):
    # the dot product of two float32 rows (a function of its own: inlined, its loop is vectorised, which the same
    # loop written inside the shift loops is not when the shift has a stride)
    s = np.float32(0.0)
    for k in range(a.shape[0]):
        s += a[k] * b[k]
    return s


@njit(cache=True, fastmath=True)
def _ncc_strided(win, t, step):
    # _ncc_direct at every ``step``-th shift in each axis only (a coarse pass over the shifts): the same sums,
    # the integral images over the whole window
    win = np.ascontiguousarray(win)
    T0, T1 = t.shape
    H, W = win.shape
    ny, nx = (H - T0) // step + 1, (W - T1) // step + 1
    N = T0 * T1
    tz, tn, S1, S2 = _setup(win, t)
    out = np.empty((ny, nx), np.float32)
    acc = np.empty(nx, np.float32)
    for ii in range(ny):
        i = ii * step
        acc[:] = 0.0
        for a in range(T0):
            row = win[i + a]
            trow = tz[a]
            for jj in range(nx):
                j = jj * step
                acc[jj] += _dot(row[j:j + T1], trow)
        for jj in range(nx):
            j = jj * step
            s1 = S1[i + T0, j + T1] - S1[i, j + T1] - S1[i + T0, j] + S1[i, j]
            s2 = S2[i + T0, j + T1] - S2[i, j + T1] - S2[i + T0, j] + S2[i, j]
            d = np.sqrt(max(s2 - s1 * s1 / N, 0.0) * tn)
            out[ii, jj] = acc[jj] / d if d > 0 else -1.0
    return out


@njit(cache=True)
def _ncc_pages_strided(img, ri, ci, m, flat, offs, sizes, pages, step, out):
    for q in range(len(pages)):
        k = pages[q]
        T = sizes[k]
        t = flat[offs[k]:offs[k] + T * T].reshape((T, T))
        h = T // 2
        win = img[ri - h - m: ri + h + m + 1, ci - h - m: ci + h + m + 1]
        out[q, :, :] = _ncc_strided(win, t, step)


def ncc_pages_strided(img, ri, ci, m, tmpl: "Templates", pages, step: int) -> np.ndarray:
    """As :func:`ncc_pages` (no crop, all shifts) at every ``step``-th shift of each axis only: the maps'
    element (a, b) is the correlation at shift (a step, b step) from the corner, i.e. map index (a step, b step) of
    :func:`ncc_pages`.

    Returns
    -------
    (len(pages), 2 m // step + 1, 2 m // step + 1) float32 array
    """
    nc = (2 * m) // step + 1
    flat, offs, sizes = tmpl.packed
    pages = np.asarray(pages, np.int64)
    out = np.empty((len(pages), nc, nc), np.float32)
    _ncc_pages_strided(img, int(ri), int(ci), int(m), flat, offs, sizes, pages, int(step), out)
    return out


class Templates(list):
    """A list of square float32 templates that also holds them packed in one buffer (for :func:`ncc_pages`)."""

    _packed = None

    @property
    def packed(self):
        if self._packed is None:
            sizes = np.array([t.shape[0] for t in self], np.int64)
            offs = np.concatenate([[0], np.cumsum(sizes * sizes)[:-1]]).astype(np.int64)
            flat = np.concatenate([np.ascontiguousarray(t, np.float32).ravel() for t in self])
            self._packed = (flat, offs, sizes)
        return self._packed


def ncc_pages(img, ri, ci, m, tmpl: Templates, pages, crop=0, rows=None, cols=None) -> np.ndarray:
    """Maps of :func:`ncc` of each page's template (cropped about its centre to ``crop`` px if > 0) over the
    window of ``img`` centred on pixel (ri, ci), at the (2 m + 1)^2 shifts (only those in ``rows`` x ``cols``, a
    pair of (start, stop) map indices; -1 elsewhere), as ``ptrack.calibration._match_one`` places them.

    Returns
    -------
    (len(pages), 2 m + 1, 2 m + 1) float32 array
        Never NaN (a constant window or template gives -1).
    """
    n = 2 * m + 1
    a0, a1 = rows if rows is not None else (0, n)
    b0, b1 = cols if cols is not None else (0, n)
    flat, offs, sizes = tmpl.packed
    pages = np.asarray(pages, np.int64)
    out = np.empty((len(pages), n, n), np.float32)
    _ncc_pages(img, int(ri), int(ci), int(m), flat, offs, sizes, pages, int(crop), int(a0), int(a1), int(b0),
               int(b1), out)
    return out
