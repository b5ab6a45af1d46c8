"""Image preprocessing before detection: invert, background, threshold, 3x3 median.

Each step is a plain function on one frame (2D array) and can be used alone.
:func:`prepare` chains the steps a movie needs: inversion only for
brightfield images, then background subtraction. The background is removed
*before* any centroiding: a centroid taken on an image that keeps its
background is pulled towards the ROI centre (0.04-0.13 px pixel locking).

Backgrounds
-----------
``"spatial"`` (default)
    Per frame, a morphological opening (grey-level erosion then dilation) of
    a 4x down-sampled copy with a window larger than a particle image,
    smoothed and up-sampled; particles of any brightness are removed, slow
    illumination gradients are kept, and particles that never move (deposited
    ones) are *not* subtracted. A constant offset is then removed so that the
    residual background has zero median.
``"temporal"``
    A per-pixel median over a bounded sample of frames
    (:func:`temporal_background`); best for fixed-pattern backgrounds with
    moving particles, wrong for particles that stay put.
``"none"``
    Only the global median is removed.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..errors import UserError

__all__ = [
    "fast_median", "to_float", "invert", "spatial_background", "temporal_background", "subtract_background",
    "noise_sigma", "threshold", "median3", "prepare",
]


def to_float(frame) -> np.ndarray:
    """Frame as contiguous float32."""
    return np.ascontiguousarray(frame, dtype=np.float32)


def invert(frame, max_value: float | None = None) -> np.ndarray:
    """Invert a brightfield frame so particles are bright on a dark background.

    Parameters
    ----------
    frame : 2D array
    max_value : float, optional
        Value mapped to 0; default the frame's maximum.

    Returns
    -------
    numpy.ndarray of float32
    """
    f = to_float(frame)
    m = float(f.max()) if max_value is None else float(max_value)
    return m - f


def spatial_background(img: np.ndarray, size: float = 25.0, downsample: int = 4, signed: bool = False) -> np.ndarray:
    """Smooth background under the particles, from a grey-level opening (or a median for signed images).

    Parameters
    ----------
    img : 2D float32 array
        Particles bright.
    size : float
        Opening window (px, full-resolution), larger than a particle image
        (e.g. 4x its diameter).
    downsample : int
        Work on a copy reduced by this factor (area averaging) for speed.
    signed : bool
        The particles' images have parts above *and* below the background
        (defocused brightfield images: dark and bright rings). An opening
        follows the lower envelope, so the dark-side lobes would pull the
        background down under every particle; a running median (window
        ``size``) ignores excursions of either sign covering less than half
        of the window.

    Returns
    -------
    numpy.ndarray of float32, same shape as ``img``
    """
    import cv2

    img = to_float(img)
    h, w = img.shape
    ds = max(1, int(downsample))
    if min(h, w) // ds < 8:
        ds = 1
    small = cv2.resize(img, (max(1, w // ds), max(1, h // ds)), interpolation=cv2.INTER_AREA) if ds > 1 else img
    k = max(3, int(round(size / ds)) | 1)
    if signed:
        from scipy.ndimage import median_filter

        # on the down-sampled copy (a few thousand pixels): cheap even for large windows
        opened = median_filter(small, size=min(k, 2 * max(small.shape) + 1), mode="nearest").astype(np.float32)
    else:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
        opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)
    opened = cv2.blur(opened, (k, k), borderType=cv2.BORDER_REPLICATE)
    if ds > 1:
        opened = cv2.resize(opened, (w, h), interpolation=cv2.INTER_LINEAR)
    return opened


def temporal_background(movie, n_sample: int = 21, percentile: float = 50.0) -> np.ndarray:
    """Per-pixel temporal percentile over ``n_sample`` evenly spaced frames (float32).

    Memory: ``n_sample`` frames in the movie's dtype.
    """
    n = len(movie)
    idx = np.unique(np.linspace(0, n - 1, min(n, int(n_sample))).astype(int))
    stack = np.stack([np.asarray(movie[i]) for i in idx])
    return np.percentile(stack, percentile, axis=0).astype(np.float32) if percentile != 50 else \
        np.median(stack, axis=0).astype(np.float32)


def noise_sigma(img: np.ndarray, step: int = 5) -> float:
    """Robust standard deviation of the background (1.4826 x MAD over a pixel subsample)."""
    sub = np.asarray(img[::step, ::step], dtype=np.float32).ravel()
    med = np.median(sub)
    return float(1.4826 * np.median(np.abs(sub - med)))


def subtract_background(img: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """``img - background`` minus the residual's median (so background pixels sit at 0), float32."""
    out = to_float(img) - background if background is not None else to_float(img).copy()
    out -= np.median(out[::4, ::4])
    return out


def threshold(img: np.ndarray, level: float) -> np.ndarray:
    """Copy of ``img`` with values below ``level`` set to 0 (the ImageJ-style threshold step)."""
    out = to_float(img).copy()
    out[out < level] = 0.0
    return out


def median3(img: np.ndarray) -> np.ndarray:
    """3x3 median filter (OpenCV; removes hot pixels and salt noise)."""
    import cv2

    return cv2.medianBlur(to_float(img), 3)


def prepare(frame, brightfield: bool = False, background="spatial", bg_size: float = 25.0,
            max_value: float | None = None, signed: bool = False) -> np.ndarray:
    """Invert (brightfield only) and subtract the background of one frame.

    Parameters
    ----------
    frame : 2D array
        Raw camera frame.
    brightfield : bool
        Dark particles on a bright field: invert first.
    background : {"spatial", "none"} or 2D array
        A background image (e.g. from :func:`temporal_background`, already
        inverted for brightfield) is subtracted as given.
    bg_size : float
        Opening window for the spatial background (px).
    max_value : float, optional
        Inversion reference (default: the camera's full scale for integer
        frames).
    signed : bool
        The particle images have parts on both sides of the background
        (defocused brightfield): the spatial background is a running median
        instead of an opening (see :func:`spatial_background`). Nothing is
        thresholded here in either case.

    Returns
    -------
    numpy.ndarray of float32
        Background-subtracted image, particles positive (brightfield: their
        dark parts), background ~0.
    """
    if brightfield:
        if max_value is None and np.issubdtype(np.asarray(frame).dtype, np.integer):
            max_value = float(np.iinfo(np.asarray(frame).dtype).max)
        img = invert(frame, max_value)
    else:
        img = to_float(frame)
    if isinstance(background, np.ndarray):
        if background.shape != img.shape:
            raise UserError(f"background image shape {background.shape} differs from the frame's {img.shape}",
                            "compute the background from the same movie")
        return subtract_background(img, background)
    if background in (None, "none", False):
        return subtract_background(img, None)
    if background == "spatial":
        return subtract_background(img, spatial_background(img, bg_size, signed=signed))
    raise UserError(f"background = {background!r} is not known", "use 'spatial', 'temporal' or 'none'")


@nb.njit(cache=True, inline="always")
def _select(a, k, n):
    # the k-th smallest of a[:n], in place (quickselect, Hoare partition about a median-of-3 pivot); afterwards
    # a[:k] holds values <= it
    lo = 0
    hi = n - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        p = a[mid]
        i = lo
        j = hi
        while i <= j:
            while a[i] < p:
                i += 1
            while a[j] > p:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


@nb.njit(cache=True)
def _middle_values(a):
    # the two middle values of the sorted 1-D array a (the same one twice for an odd count), selected in place;
    # NaN if a holds one
    n = a.shape[0]
    for k in range(n):
        if math.isnan(a[k]):
            return a[k], a[k]
    h = n >> 1
    upper = _select(a, h, n)
    if n & 1:
        return upper, upper
    lower = a[0]
    for k in range(1, h):
        if a[k] > lower:
            lower = a[k]
    return lower, upper


def fast_median(a) -> float:
    """``float(np.median(a))`` of a float32/float64 array without numpy's per-call overhead (~25 us, which
    matters for the few small medians of every frame): the same value (the mean of the two middle values in
    the array's own precision, as numpy)."""
    a = np.asarray(a)
    if a.size == 0 or a.dtype not in (np.float32, np.float64):
        return float(np.median(a))
    lo, hi = _middle_values(np.array(a, copy=True).ravel())
    t = a.dtype.type
    return float((t(lo) + t(hi)) / t(2))
