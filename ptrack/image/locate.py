"""Detect and localise the particles of one frame (the step a notebook user calls).

Pixel coordinates follow trackpy: ``x`` along columns, ``y`` along rows, the
centre of pixel (0, 0) at (0, 0).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import pandas as pd

from ..errors import UserError
from .fit import fit_spots
from .peaks import _default_separation, detect_raw, find_peaks
from .preprocess import median3, noise_sigma

__all__ = ["locate", "estimate_sigma", "sigma_to_diameter", "diameter_to_sigma", "repair_hot_pixels",
           "LOCATE_COLUMNS"]

LOCATE_COLUMNS = ("x_px", "y_px", "mass", "size", "ecc", "signal", "photons", "bg_photons",
                  "sigma_x_px", "sigma_y_px")


def diameter_to_sigma(diameter: float) -> float:
    """Gaussian width (px) of a spot of the given diameter (px): the 1/e^2 diameter is 4 sigma."""
    return float(diameter) / 4.0


def sigma_to_diameter(sigma: float) -> float:
    """Spot diameter (px, 4 sigma) for a Gaussian width sigma (px)."""
    return 4.0 * float(sigma)



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
