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

__all__ = ["ncc", "ncc_pages", "ncc_pages_strided", "ncc_corners", "FrameSpectrum", "DIRECT_MAX"]

DIRECT_MAX = 121     # shifts (rows x cols of the map) up to which the direct sum is used (11 x 11)
FLAT_MAX = 8192      # template span (px, see _ncc_map) up to which a shift's sum is one flat dot product


@njit(cache=True, fastmath=True)
def _zero_mean(t):
    # the zero-mean template and its sum of squares
    T0, T1 = t.shape
    tm = 0.0
    for a in range(T0):
        for b in range(T1):
            tm += t[a, b]
    tm /= T0 * T1
    tz = np.empty((T0, T1), np.float32)
    tn = 0.0
    for a in range(T0):
        for b in range(T1):
            v = t[a, b] - tm
            tz[a, b] = v
            tn += v * v
    return tz, tn


@njit(cache=True, fastmath=True)
def _window_sums(win, T0, T1):
    # the (contiguous) window's sum and sum of squares over the template's footprint at every shift, (2, ny, nx), in
    # double precision (the variance is a difference of two large sums): each column's T0-row sum, slid down the
    # rows, then T1-column sums of those, slid along; vectorised over the columns (two whole-window integral
    # images, added serially, cost 2-4x as much)
    H, W = win.shape
    ny, nx = H - T0 + 1, W - T1 + 1
    c1 = np.zeros(W)
    c2 = np.zeros(W)
    out = np.empty((2, ny, nx))
    for a in range(T0):
        r = win[a]
        for b in range(W):
            w = np.float64(r[b])
            c1[b] += w
            c2[b] += w * w
    for i in range(ny):
        if i > 0:
            r0 = win[i - 1]
            r1 = win[i + T0 - 1]
            for b in range(W):
                w0 = np.float64(r0[b])
                w1 = np.float64(r1[b])
                c1[b] += w1 - w0
                c2[b] += w1 * w1 - w0 * w0
        s1 = 0.0
        s2 = 0.0
        for b in range(T1):
            s1 += c1[b]
            s2 += c2[b]
        out[0, i, 0] = s1
        out[1, i, 0] = s2
        for j in range(1, nx):
            s1 += c1[j + T1 - 1] - c1[j - 1]
            s2 += c2[j + T1 - 1] - c2[j - 1]
            out[0, i, j] = s1
            out[1, i, j] = s2
    return out


@njit(cache=True, fastmath=True)
def _dot(a, b):
    # the dot product of two float32 rows (a function of its own: inlined, its loop is vectorised, which the same
    # loop written inside the shift loops is not when the shift has a stride)
    s = np.float32(0.0)
    for k in range(a.shape[0]):
        s += a[k] * b[k]
    return s


@njit(cache=True, fastmath=True)
def _dot4(w0, w1, w2, w3, t):
    # four dot products with one vector t in one pass (t loaded once for four sums). Each sum is formed the same
    # way whichever of the four it is: a shift's correlation does not depend on the shifts computed beside it
    s0 = np.float32(0.0)
    s1 = np.float32(0.0)
    s2 = np.float32(0.0)
    s3 = np.float32(0.0)
    for k in range(t.shape[0]):
        v = t[k]
        s0 += w0[k] * v
        s1 += w1[k] * v
        s2 += w2[k] * v
        s3 += w3[k] * v
    return s0, s1, s2, s3


@njit(cache=True, fastmath=True)
def _ncc_map(wc, S, tz, tn, step, tp):
    # the correlation map of zero-mean template tz (sum of squares tn) at every ``step``-th shift in each axis (1:
    # all). A shift's sum over the template is one dot product of the flattened window from the shift's corner with
    # the template laid out on the window's row length (zeros between its rows): long vectorised loops instead of
    # a short dot per template row, whose scalar tail (T1 mod 32 terms) took a third of the time at T1 = 51; four
    # shifts per pass share the template's loads. Templates spanning more than FLAT_MAX px (refine_full's at full
    # resolution, whose flat layout leaves the cache): row by row. wc: the window, contiguous (with a slice's
    # unknown strides the loops over a row are not vectorised); S: its _window_sums for tz's shape; tp: tz laid out
    # on the window's row length (Templates.layout) or any other length (made here)
    T0, T1 = tz.shape
    H, W = wc.shape
    ny, nx = (H - T0) // step + 1, (W - T1) // step + 1
    N = T0 * T1
    acc = np.zeros((ny, nx), np.float32)
    L = (T0 - 1) * W + T1
    if L <= FLAT_MAX:
        wf = wc.ravel()
        if tp.shape[0] != L:
            tp = np.zeros(L, np.float32)
            for a in range(T0):
                tp[a * W:a * W + T1] = tz[a]
        # the shifts in row-major order, four at a time (the last group repeats the last shift: computed, not stored)
        nsh = ny * nx
        o = np.empty(4, np.int64)
        for g in range(0, nsh, 4):
            for q in range(4):
                k = min(g + q, nsh - 1)
                o[q] = (k // nx) * step * W + (k % nx) * step
            s = _dot4(wf[o[0]:o[0] + L], wf[o[1]:o[1] + L], wf[o[2]:o[2] + L], wf[o[3]:o[3] + L], tp)
            for q in range(min(4, nsh - g)):
                acc[(g + q) // nx, (g + q) % nx] = s[q]
    else:
        for ii in range(ny):
            for a in range(T0):
                row = wc[ii * step + a]
                trow = tz[a]
                for jj in range(nx):
                    acc[ii, jj] += _dot(row[jj * step:jj * step + T1], trow)
    out = np.empty((ny, nx), np.float32)
    for ii in range(ny):
        for jj in range(nx):
            s1 = S[0, ii * step, jj * step]
            d = np.sqrt(max(S[1, ii * step, jj * step] - s1 * s1 / N, 0.0) * tn)
            # a constant window (zero padding) or template: no correlation (OpenCV gives NaN there, which the
            # callers turn into -1)
            out[ii, jj] = acc[ii, jj] / d if d > 0 else -1.0
    return out


@njit(cache=True)
def _ncc_direct(win, t):
    tz, tn = _zero_mean(t)
    wc = np.ascontiguousarray(win)
    return _ncc_map(wc, _window_sums(wc, t.shape[0], t.shape[1]), tz, tn, 1, np.empty(0, np.float32))


def ncc(win, t, direct_max: int = DIRECT_MAX) -> np.ndarray:
    """``cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)`` (float32 map of shape win - t + 1).

    Parameters
    ----------
    win : (H, W) float32 array
        Image window (any strides).
    t : (T0, T1) float32 array
        Template, T0 <= H, T1 <= W.
    direct_max : int
        Largest map (shifts) computed by the direct sum.

    Returns
    -------
    (H - T0 + 1, W - T1 + 1) float32 array
        Correlation at each shift, in [-1, 1]; -1 where the window or the
        template is constant (OpenCV: NaN). Maps of up to
        :data:`DIRECT_MAX` shifts by a direct sum (agrees with OpenCV to
        ~2e-7), larger ones by OpenCV.
    """
    ny, nx = win.shape[0] - t.shape[0] + 1, win.shape[1] - t.shape[1] + 1
    if ny * nx <= direct_max and win.dtype == np.float32 and t.dtype == np.float32:
        return _ncc_direct(win, t)
    import cv2

    return cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)


@njit(cache=True)
def _ncc_pages(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs, pages, crop, a0, a1, b0, b1, out):
    # one match's correlations for many pages in one call (the per-call overhead of ~60 small maps per match); whole
    # templates from their cached zero-mean copies, cropped ones made zero-mean here. Pages of one size (runs of
    # 3-7 among interpolated templates) share the window and its sums
    Tw = -1
    wc = np.empty((1, 1), np.float32)
    S = np.empty((2, 1, 1))
    for q in range(len(pages)):
        k = pages[q]
        T = sizes[k]
        Tc = crop if crop > 0 and crop < T else T
        if Tc != Tw:
            h = Tc // 2
            wc = np.ascontiguousarray(img[ri - h - m + a0: ri + h - m + a1, ci - h - m + b0: ci + h - m + b1])
            S = _window_sums(wc, Tc, Tc)
            Tw = Tc
        out[q, :, :] = -1.0
        if Tc == T:
            out[q, a0:a1, b0:b1] = _ncc_map(wc, S, zflat[offs[k]:offs[k] + T * T].reshape((T, T)), tns[k], 1,
                                            lflat[loffs[k]:loffs[k + 1]])
        else:
            o = (T - Tc) // 2
            t = flat[offs[k]:offs[k] + T * T].reshape((T, T))
            tz, tn = _zero_mean(t[o:o + Tc, o:o + Tc])
            out[q, a0:a1, b0:b1] = _ncc_map(wc, S, tz, tn, 1, np.empty(0, np.float32))


@njit(cache=True)
def _ncc_pages_strided(img, ri, ci, m, offs, sizes, zflat, tns, lflat, loffs, pages, step, out):
    Tw = -1
    wc = np.empty((1, 1), np.float32)
    S = np.empty((2, 1, 1))
    for q in range(len(pages)):
        k = pages[q]
        T = sizes[k]
        if T != Tw:
            h = T // 2
            wc = np.ascontiguousarray(img[ri - h - m: ri + h + m + 1, ci - h - m: ci + h + m + 1])
            S = _window_sums(wc, T, T)
            Tw = T
        out[q, :, :] = _ncc_map(wc, S, zflat[offs[k]:offs[k] + T * T].reshape((T, T)), tns[k], step,
                                lflat[loffs[k]:loffs[k + 1]])


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
    zflat, tns = tmpl.zero_mean
    lflat, loffs = tmpl.layout(2 * int(m))
    pages = np.asarray(pages, np.int64)
    out = np.empty((len(pages), nc, nc), np.float32)
    _ncc_pages_strided(img, int(ri), int(ci), int(m), offs, sizes, zflat, tns, lflat, loffs, pages, int(step), out)
    return out


@njit(cache=True)
def _ncc_corners(img, offs, sizes, zflat, tns, lflat, loffs, pages, tops, lefts, n, out):
    for q in range(len(pages)):
        k = pages[q]
        T = sizes[k]
        wc = np.ascontiguousarray(img[tops[q]:tops[q] + T + n - 1, lefts[q]:lefts[q] + T + n - 1])
        out[q, :, :] = _ncc_map(wc, _window_sums(wc, T, T), zflat[offs[k]:offs[k] + T * T].reshape((T, T)), tns[k],
                                1, lflat[loffs[k]:loffs[k + 1]])


def ncc_corners(img, tmpl: "Templates", pages, tops, lefts, n: int) -> np.ndarray:
    """Maps of :func:`ncc` of each page's template over the window of ``img`` whose corner is (tops[q], lefts[q])
    (px, integer) and side the template's + n - 1: its correlation at the n x n shifts from that corner, each page
    placed on its own corner, in one call (``ptrack.gdpt.fast.refine_full``: ~40 small maps per image). The
    windows must lie inside ``img`` (a contiguous float32 array).

    Returns
    -------
    (len(pages), n, n) float32 array, equal to ``ncc(img[top:top + T + n - 1, left:left + T + n - 1], tmpl[k])``
    """
    flat, offs, sizes = tmpl.packed
    zflat, tns = tmpl.zero_mean
    lflat, loffs = tmpl.layout(int(n) - 1)
    pages = np.asarray(pages, np.int64)
    out = np.empty((len(pages), n, n), np.float32)
    _ncc_corners(img, offs, sizes, zflat, tns, lflat, loffs, pages, np.asarray(tops, np.int64),
                 np.asarray(lefts, np.int64), int(n), out)
    return out


@njit(cache=True, inline="always")
def _window_var(S, SQ, T, N, a, b):
    # the sum of squared deviations from the mean of the T x T window with corner (a, b), N = T^2 pixels, from the
    # frame's integral images S, SQ (float64)
    s1 = S[a + T, b + T] - S[a, b + T] - S[a + T, b] + S[a, b]
    s2 = SQ[a + T, b + T] - SQ[a, b + T] - SQ[a + T, b] + SQ[a, b]
    return max(s2 - s1 * s1 / N, 0.0)


@njit(cache=True, inline="always")
def _keep_max(c, var, tn, k, cmap, which, i, j):
    # the normalised correlation c / sqrt(var tn) (clipped to [-1, 1], -1 without variance) as float32 into the
    # running maximum cmap[i, j] and its template which[i, j]
    d = np.sqrt(var * tn)
    r = min(max(c / d, -1.0), 1.0) if d > 0 else -1.0
    v = np.float32(r)
    if v > cmap[i, j]:
        cmap[i, j] = v
        which[i, j] = k


@njit(cache=True)
def _region_max(C, S, SQ, V, from_v, T, tn, top, left, k, floor, cmap, which):
    # the normalised correlation of one zero-mean template (side T, sum of squares tn) at the template corners
    # (top + i, left + j) of cmap's shape, from its whole-frame correlation C (FFT) and the windows' variances: read
    # from V (from_v: _box_var of the template's size) or made here from the frame's integral images S, SQ
    # (cv2.integral2, float64), the same values; cmap, which: the running maximum over templates and its template
    # (in place). Values below ``floor`` (> 0) may be left out: a correlation r >= floor needs C > 0 and
    # C^2 >= floor^2 var tn, tested (with 1 % to spare) before the square root and division
    H, W = cmap.shape
    N = T * T
    lim = (0.99 * floor) ** 2 * tn if floor > 0 else -1.0
    for i in range(H):
        a = top + i
        for j in range(W):
            b = left + j
            c = C[a, b]
            if lim >= 0 and c <= 0:
                continue
            var = V[a, b] if from_v else _window_var(S, SQ, T, N, a, b)
            if c * c < lim * var:
                continue
            _keep_max(c, var, tn, k, cmap, which, i, j)


def _ncc_region_max(C, S, SQ, T, tn, top, left, k, floor, cmap, which):
    """:func:`_region_max` with the variances from the integral images."""
    _region_max(C, S, SQ, _NO_V, False, T, tn, top, left, k, floor, cmap, which)


def _ncc_region_max_var(C, V, tn, top, left, k, floor, cmap, which):
    """:func:`_region_max` with the variances read from ``V`` (:func:`_box_var` of the template's size)."""
    _region_max(C, _NO_S, _NO_S, V, True, 0, tn, top, left, k, floor, cmap, which)


_NO_V = np.zeros((1, 1))
_NO_S = np.zeros((1, 1))


@njit(cache=True)
def _box_var(S, SQ, T, out):
    # _window_var at every template corner (a, b) of out's shape: the region maximum's ``var`` for all the pages of
    # one size at once
    H, W = out.shape
    N = T * T
    for a in range(H):
        for b in range(W):
            out[a, b] = _window_var(S, SQ, T, N, a, b)


class FrameSpectrum:
    """One frame's 2-D FFT, its integral images and the templates' spectra: whole-frame correlations with several
    templates for one forward transform (OpenCV's ``matchTemplate`` transforms frame and template again for
    every template).

    Parameters
    ----------
    img : (H, W) float32 array
        The (zero-padded) frame.
    """

    def __init__(self, img):
        import scipy.fft as sf

        self.img = np.ascontiguousarray(img, np.float32)
        H, W = self.img.shape
        # (no wrap-around: a template corner inside the frame reads frame rows < H <= the transform's length)
        self.shape = (sf.next_fast_len(H, True), sf.next_fast_len(W, True))
        self.F = sf.rfft2(self.img.astype(np.float64), self.shape, workers=1)
        self._integral = None
        self._vars = {}

    @property
    def integral(self):
        """(S, SQ): the frame's integral image and integral of squares (float64, one row and column more)."""
        if self._integral is None:
            import cv2

            self._integral = cv2.integral2(self.img, sdepth=cv2.CV_64F)
        return self._integral

    def correlate(self, tmpl: "Templates", k: int, zero_mean: bool = True) -> np.ndarray:
        """sum_uv img[a + u, b + v] t[u, v] at every template corner (a, b) (rows and columns up to the
        transform's length; those with the template inside the frame are OpenCV's ``TM_CCORR`` map),
        float64; ``zero_mean``: of the template minus its mean (``TM_CCOEFF``)."""
        import scipy.fft as sf

        return sf.irfft2(self.F * tmpl.spectrum(k, self.shape, zero_mean), self.shape, workers=1)

    def box_var(self, T: int) -> np.ndarray:
        """The frame's sum of squared deviations from the mean over the T x T window at every template corner
        inside it ((H - T + 1, W - T + 1), float64, from :attr:`integral`; cached per T)."""
        V = self._vars.get(int(T))
        if V is None:
            S, SQ = self.integral
            H, W = self.img.shape
            V = np.empty((H - T + 1, W - T + 1))
            _box_var(S, SQ, int(T), V)
            self._vars[int(T)] = V
        return V

    def ncc_max(self, tmpl: "Templates", k: int, top: int, left: int, cmap, which, floor: float = -1.0,
                keep: dict | None = None, shared_var: bool = False) -> None:
        """Page ``k``'s normalised correlation (OpenCV's ``TM_CCOEFF_NORMED``; -1 on a constant window) at the
        template corners (top + i, left + j), i, j over cmap's shape, folded into the running maximum ``cmap``
        (float32) and its page ``which`` (int32), in place. The corners' windows must lie inside the frame.
        ``floor`` > 0: correlations below it may be left out (cmap and which then hold the maximum over the
        pages only where it is at least ``floor``). ``keep``: a dict in which the page's whole-frame correlation
        (:meth:`correlate`, zero-mean) is stored under ``k``, for other sums over the same frame. ``shared_var``:
        the windows' variances from :meth:`box_var` (made once per template size, shared by the pages of that
        size; the same values)."""
        T = int(tmpl.packed[2][k])
        if top < 0 or left < 0 or top + cmap.shape[0] + T - 1 > self.img.shape[0] \
                or left + cmap.shape[1] + T - 1 > self.img.shape[1]:
            raise ValueError("template windows leave the frame")
        S, SQ = self.integral
        C = self.correlate(tmpl, k)
        if keep is not None:
            keep[int(k)] = C
        if shared_var:
            _ncc_region_max_var(C, self.box_var(T), tmpl.norm64(k), int(top), int(left), int(k), float(floor), cmap,
                                which)
            return
        _ncc_region_max(C, S, SQ, T, tmpl.norm64(k), int(top), int(left), int(k), float(floor), cmap, which)


class Templates(list):
    """A list of square float32 templates that also holds them packed in one buffer (for :func:`ncc_pages`)."""

    _packed = None
    _zero_mean = None
    _layouts = None
    _spectra = None

    def _zm64(self, k):
        t = np.asarray(self[k], np.float64)
        return t - t.mean()

    def norm64(self, k: int) -> float:
        """Sum of squares of template k minus its mean, in double precision (the spectra's template; cached)."""
        if self._spectra is None:
            self._spectra = {}
        v = self._spectra.get(("norm", int(k)))
        if v is None:
            v = self._spectra[("norm", int(k))] = float((self._zm64(k) ** 2).sum())
        return v

    def spectrum(self, k: int, shape, zero_mean: bool = True):
        """Conjugate 2-D FFT (``scipy.fft.rfft2`` at ``shape``, float64) of template k (minus its mean if
        ``zero_mean``): multiplied with a frame's transform, its correlation at every corner. Cached per page,
        shape and kind (the same for every frame)."""
        import scipy.fft as sf

        if self._spectra is None:
            self._spectra = {}
        key = (int(k), tuple(int(a) for a in shape), bool(zero_mean))
        sp = self._spectra.get(key)
        if sp is None:
            t = self._zm64(k) if zero_mean else np.asarray(self[k], np.float64)
            sp = np.conj(sf.rfft2(t, key[1], workers=1))
            self._spectra[key] = sp
        return sp

    @property
    def packed(self):
        if self._packed is None:
            sizes = np.array([t.shape[0] for t in self], np.int64)
            offs = np.concatenate([[0], np.cumsum(sizes * sizes)[:-1]]).astype(np.int64)
            flat = np.concatenate([np.ascontiguousarray(t, np.float32).ravel() for t in self])
            self._packed = (flat, offs, sizes)
        return self._packed

    @property
    def zero_mean(self):
        """(zflat, tn): every template minus its mean, packed as :attr:`packed`, and its sum of squares (the
        same for every window it is correlated with)."""
        if self._zero_mean is None:
            flat, offs, sizes = self.packed
            zflat = np.empty_like(flat)
            tns = np.empty(len(sizes))
            for k, (o, T) in enumerate(zip(offs, sizes)):
                tz, tns[k] = _zero_mean(flat[o:o + T * T].reshape(T, T))
                zflat[o:o + T * T] = tz.ravel()
            self._zero_mean = (zflat, tns)
        return self._zero_mean

    def layout(self, p: int):
        """(lflat, loffs): every zero-mean template laid out on a row length of T + p px (p zeros after each row
        but the last), as _ncc_map dots it with a window T + p px wide; page k's is lflat[loffs[k]:loffs[k + 1]]
        (empty where it would span more than FLAT_MAX px: that page is correlated row by row). Cached per p: the
        same for every match (making it per map cost a sixth of the correlation time)."""
        if self._layouts is None:
            self._layouts = {}
        p = int(p)
        if p not in self._layouts:
            zflat, _ = self.zero_mean
            flat, offs, sizes = self.packed
            parts, loffs = [], np.zeros(len(sizes) + 1, np.int64)
            for k, (o, T) in enumerate(zip(offs, sizes)):
                L = (T - 1) * (T + p) + T
                if L <= FLAT_MAX:
                    lay = np.zeros((T, T + p), np.float32)
                    lay[:, :T] = zflat[o:o + T * T].reshape(T, T)
                    parts.append(lay.ravel()[:L])
                    loffs[k + 1] = loffs[k] + L
                else:
                    loffs[k + 1] = loffs[k]
            self._layouts[p] = (np.concatenate(parts) if parts else np.zeros(0, np.float32), loffs)
        return self._layouts[p]


def layouts_upto(tmpl: Templates, P: int):
    """(lflat, loffs): the layouts :meth:`Templates.layout` of every p = 0..P in one buffer, page k's for p at
    lflat[loffs[p, k]:loffs[p, k + 1]] (for one numba call that correlates at several window widths). Cached per
    Templates object and P."""
    cache = tmpl.__dict__.setdefault("_layouts_upto", {})
    P = int(P)
    if P not in cache:
        parts, rows, base = [], [], 0
        for p in range(P + 1):
            lf, lo = tmpl.layout(p)
            parts.append(lf)
            rows.append(lo + base)
            base += len(lf)
        cache[P] = (np.concatenate(parts), np.stack(rows).astype(np.int64))
    return cache[P]


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
    zflat, tns = tmpl.zero_mean
    lflat, loffs = tmpl.layout(int(b1) - int(b0) - 1)     # the window is T - 1 + (b1 - b0) px wide
    pages = np.asarray(pages, np.int64)
    out = np.empty((len(pages), n, n), np.float32)
    _ncc_pages(img, int(ri), int(ci), int(m), flat, offs, sizes, zflat, tns, lflat, loffs, pages, int(crop), int(a0),
               int(a1), int(b0), int(b1), out)
    return out
