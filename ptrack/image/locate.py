"""Detect and localise the particles of one frame (the step a notebook user calls).

Pixel coordinates follow trackpy: ``x`` along columns, ``y`` along rows, the
centre of pixel (0, 0) at (0, 0).
"""
from __future__ import annotations

import math
import time

import numba as nb
import numpy as np
import pandas as pd

from ..errors import UserError
from .fit import fit_spots
from .peaks import _default_separation, detect_raw, find_peaks
from .detect import FALSE_ALARM_RATE, detect, scratch
from .preprocess import fast_median, median3, noise_sigma
from .radial import has_dip, image_extent, profile_centres, radial_centres

__all__ = ["locate", "batch", "estimate_sigma", "sigma_to_diameter", "diameter_to_sigma", "repair_hot_pixels",
           "LOCATE_COLUMNS", "MULTISCALE_COLUMNS"]

LOCATE_COLUMNS = ("x_px", "y_px", "mass", "size", "ecc", "signal", "photons", "bg_photons",
                  "sigma_x_px", "sigma_y_px")
#: Extra columns of the multi-scale path: detection SNR (local noise units), localiser used
#: ("gauss": Gaussian fit; "radial": a centre-symmetric estimator, the free radial-profile fit of
#: :func:`ptrack.image.radial.profile_centres` or, where it fails, the radial-symmetry centre),
#: image polarity (+1 bright, -1 dark particles).
MULTISCALE_COLUMNS = ("snr", "method", "polarity")
_METHODS = ("gauss", "radial")
_METHOD_DTYPE = pd.CategoricalDtype(_METHODS)
# the multi-scale path's columns, in order, as one Index built once (a new string Index per frame costs ~0.1 ms)
_MULTISCALE_INDEX = pd.Index(("frame",) + LOCATE_COLUMNS + MULTISCALE_COLUMNS)


# place of the ``method`` column in _MULTISCALE_INDEX: int8 codes into _METHODS until the table is made
_METHOD_AT = len(LOCATE_COLUMNS) + 2


def _frame_table(arrays):
    """The multi-scale path's table from its columns (in :data:`_MULTISCALE_INDEX` order, equal lengths; the
    ``method`` column as int8 codes into ``_METHODS``).

    pandas' public constructor checks and converts every column of the dict (~0.4 ms for 14 columns, more than
    the fits of a sparse 256^2 frame); the arrays here are already final, so they are handed over as they are
    (``DataFrame._from_arrays``, ~0.13 ms), or through the public constructor where pandas lacks that.
    """
    arrays = list(arrays)
    # a categorical: building a string column costs more than the rest of the table
    arrays[_METHOD_AT] = pd.Categorical.from_codes(arrays[_METHOD_AT], dtype=_METHOD_DTYPE)
    n = len(arrays[0])
    make = getattr(pd.DataFrame, "_from_arrays", None)
    if make is not None:
        try:
            return make(arrays, columns=_MULTISCALE_INDEX, index=pd.RangeIndex(n), verify_integrity=False)
        except TypeError:       # a pandas whose private signature differs
            pass
    return pd.DataFrame(dict(zip(_MULTISCALE_INDEX, arrays)), copy=False)
#: Fitted Gaussian width (px) from which an image is not taken for a Gaussian spot: wider than the
#: coarsest default scale, it is a defocused image or a large particle, and its centre comes from the free
#: radial-profile fit (on a true Gaussian the profile fit is ~1.5x less precise than the Gaussian fit: it
#: refits the profile to the noise, so Gaussian-like images keep the Gaussian fit)
LARGE_IMAGE = 4.0


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



def locate(frame, img=None, sigma: float | None = None, snr: float | None = None, separation: float | None = None,
           gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0, brightfield: bool | None = None,
           median: bool = True, min_photons: float = 0.0, split: bool = True, scales=None,
           rate: float = FALSE_ALARM_RATE, centre: str = "auto", frame_no: int = 0,
           cache: dict | None = None) -> pd.DataFrame:
    """Detect and localise the particles of one frame.

    With the defaults (``sigma=None``) nothing needs tuning: detection is
    multi-scale with a false-alarm threshold and the polarity decided from
    the data (:func:`ptrack.image.detect.detect`); each particle is
    localised at its own size, by the Gaussian fit (blobs) or by radial
    symmetry (rings, :mod:`ptrack.image.radial`), see ``centre``. Giving
    ``sigma`` selects the single-size matched filter of issue 5 (one spot
    width for the frame, ``snr`` default 7).

    Parameters
    ----------
    frame : 2D array
        Raw camera frame (counts).
    img : 2D float32 array, optional
        Single-size path only: the preprocessed frame
        (:func:`ptrack.preprocess.prepare`) to detect on. If not given,
        fluorescence frames take the fast path (:func:`detect_raw`: spatial
        background at block resolution) and brightfield frames are prepared
        with the spatial background.
    sigma : float, optional
        Spot width (px) for the single-size path; see :func:`estimate_sigma`.
    snr : float, optional
        Detection threshold in local noise units (overrides the false-alarm
        rate; single-size path: default 7).
    separation, median
        Detection settings (:func:`find_peaks`).
    scales : sequence of float, optional
        Spot widths searched (px), default
        :data:`ptrack.image.detect.DEFAULT_SCALES`.
    rate : float
        False detections per pixel on an empty frame (default 1e-6).
    centre : {"auto", "gauss", "radial"}
        Localiser: ``auto`` fits a Gaussian to blobs and takes the radial-
        symmetry centre of rings (a dip in the centre, or a ring of the
        opposite sign around it); the ``method`` column says which.
    frame_no : int
        Value of the ``frame`` column.
    cache : dict, optional
        Multi-scale path: one dict passed with every frame of a movie lets the
        frames share their noise and background maps (see
        :func:`ptrack.image.detect.detect`); its ``stage_times_s`` then sums the
        wall seconds of the stages over those frames: ``detect``, ``fit``
        (hot-pixel repair, ring tests, Gaussian fits) and ``centres`` (radial
        centres and profile fits).
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
        ``frame`` and the columns :data:`LOCATE_COLUMNS`: ``x_px``, ``y_px`` (px), ``mass``
        (counts above background), ``size`` (fitted Gaussian width, px),
        ``ecc``, ``signal`` (matched-filter peak, counts), ``photons``,
        ``bg_photons`` (per px), ``sigma_x_px``, ``sigma_y_px`` (px, Cramer-Rao
        uncertainty at the estimate).
    """
    from .preprocess import prepare

    if sigma is None:
        return _frame_table(_locate_columns(frame, snr=snr, gain=gain, offset=offset, read_noise=read_noise,
                                            brightfield=brightfield, median=median, min_photons=min_photons,
                                            scales=scales, rate=rate, centre=centre, frame_no=frame_no, cache=cache))
    snr = 7.0 if snr is None else float(snr)
    brightfield = bool(brightfield)
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
        "frame": np.full(int(keep.sum()), int(frame_no), np.int64), "x_px": fit["x"][keep], "y_px": fit["y"][keep], "mass": mass[keep], "size": fit["s"][keep],
        "ecc": fit["ecc"][keep], "signal": vals[keep], "photons": fit["photons"][keep],
        "bg_photons": fit["bg"][keep], "sigma_x_px": np.sqrt(np.abs(fit["var_x"][keep])),
        "sigma_y_px": np.sqrt(np.abs(fit["var_y"][keep])),
    })
    return df


def _concat_columns(chunks):
    """One movie's columns from its frames' (lists from :func:`_locate_columns`, in frame order)."""
    if not chunks:
        cols = [np.zeros(0, np.int64)] + [np.zeros(0) for _ in range(len(LOCATE_COLUMNS) + 1)]
        return cols + [np.zeros(0, np.int8), np.zeros(0, np.int8)]
    return [np.concatenate(c) for c in zip(*chunks)]


def batch(frames, brightfield: bool | None = None, snr: float | None = None, gain: float = 1.0,
          offset: float = 0.0, read_noise: float = 0.0, median: bool = True, min_photons: float = 0.0,
          scales=None, rate: float = FALSE_ALARM_RATE, centre: str = "auto", cache: dict | None = None,
          frame_numbers=None) -> pd.DataFrame:
    """Locate every frame of a movie with the knob-free path of :func:`locate`, as ``trackpy.batch`` does.

    The frames share one cache (their noise and background maps, see :func:`ptrack.image.detect.detect`), the
    polarity is decided on the first frame with particles (unless ``brightfield`` is given) and kept for the
    rest, and the table is made once for the movie.

    Parameters
    ----------
    frames : iterable of 2D arrays
        Raw camera frames (counts), in time order.
    frame_numbers : iterable of int, optional
        The ``frame`` column's value of each frame (default 0, 1, 2, ...).
    cache : dict, optional
        A dict to share (and to read ``stage_times_s`` from afterwards); a new one by default.
    Others : see :func:`locate`.

    Returns
    -------
    pandas.DataFrame
        The rows of every frame, in frame order, with :func:`locate`'s columns: the same table as
        ``pandas.concat`` of :func:`locate` on each frame with the same cache and polarity.

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[:64, :64]
    >>> frames = [np.random.default_rng(i).poisson(10 + 300 * np.exp(-((xx - 30.3 - i) ** 2 + (yy - 33.6) ** 2)
    ...           / 4.5)).astype(np.uint16) for i in range(3)]
    >>> t = batch(frames)
    >>> t[["frame", "x_px", "y_px"]].round(0).astype(int).values.tolist()
    [[0, 30, 34], [1, 31, 34], [2, 32, 34]]
    """
    cache = {} if cache is None else cache
    numbers = None if frame_numbers is None else iter(frame_numbers)
    pol = brightfield
    chunks = []
    for i, f in enumerate(frames):
        cols = _locate_columns(f, snr=snr, gain=gain, offset=offset, read_noise=read_noise, brightfield=pol,
                               median=median, min_photons=min_photons, scales=scales, rate=rate, centre=centre,
                               frame_no=i if numbers is None else int(next(numbers)), cache=cache)
        if pol is None and len(cols[0]):
            pol = bool(cols[-1][0] < 0)         # the polarity column
        chunks.append(cols)
    return _frame_table(_concat_columns(chunks))


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


@nb.njit(cache=True)
def _ring_like(sub, rows, cols, scale, noise, out):
    # per spot, on the polarity-corrected, background-subtracted image: ring-like when the centre is
    # fainter than the annulus around it (a hole: a ring) or when an annulus of the opposite sign
    # surrounds it beyond 4 noise standard errors (a bright centre in a dark ring, or the reverse)
    h, w = sub.shape
    # the distance of every integer offset, computed once per call (the same formula as per pixel)
    hmax = 0
    for k in range(rows.shape[0]):
        hmax = max(hmax, int(math.ceil(3.0 * scale[k])) + 1)
    m = 2 * hmax + 1
    dist = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            dist[i, j] = math.sqrt((i - hmax) ** 2 + (j - hmax) ** 2)
    for k in range(rows.shape[0]):
        s = scale[k]
        rc = max(1.0, 0.6 * s)
        half = int(math.ceil(3.0 * s)) + 1
        core = 0.0
        nc = 0
        mid = 0.0
        nm = 0
        outer = 0.0
        no = 0
        for r in range(max(0, rows[k] - half), min(h, rows[k] + half + 1)):
            for c in range(max(0, cols[k] - half), min(w, cols[k] + half + 1)):
                d = dist[r - rows[k] + hmax, c - cols[k] + hmax]
                v = sub[r, c]
                if d <= rc:
                    core += v
                    nc += 1
                elif s <= d <= 2.0 * s:
                    mid += v
                    nm += 1
                elif 2.0 * s < d <= 3.0 * s:
                    outer += v
                    no += 1
        core /= max(nc, 1)
        mid /= max(nm, 1)
        neg = min(mid, outer / max(no, 1))
        nn = nm if mid < outer / max(no, 1) else no
        out[k] = core < mid or neg < -4.0 * noise / math.sqrt(max(nn, 1))


@nb.njit(cache=True)
def _nn_sweep(x, y, order):
    # distance to the nearest other point: the points sorted by y (order), each searched up and down the sorted
    # list until the y gap alone exceeds the best distance so far (exact; ~20 us for 600 points, where a
    # cKDTree build and query costs ~100 us of fixed overhead)
    n = x.shape[0]
    out = np.empty(n)
    for a in range(n):
        ia = order[a]
        best2 = np.inf
        for step in (1, -1):
            b = a + step
            while 0 <= b < n:
                ib = order[b]
                dy = y[ib] - y[ia]
                if dy * dy >= best2:
                    break
                dx = x[ib] - x[ia]
                d2 = dx * dx + dy * dy
                if d2 < best2:
                    best2 = d2
                b += step
        out[ia] = math.sqrt(best2)
    return out


def _nearest_other(rows, cols):
    """Distance (px) from each detection to the nearest other one (inf when alone)."""
    if len(rows) < 2:
        return np.full(len(rows), np.inf)
    y = np.asarray(rows, np.float64)
    return _nn_sweep(np.asarray(cols, np.float64), y, np.argsort(y, kind="stable"))


def _locate_columns(frame, snr=None, gain=1.0, offset=0.0, read_noise=0.0, brightfield=None, median=True,
                    min_photons=0.0, scales=None, rate=FALSE_ALARM_RATE, centre="auto", frame_no=0, cache=None):
    """The knob-free path of :func:`locate` (see there): the table's columns, as :func:`_frame_table` takes them
    (a movie's frames are made one table at the end, :func:`batch`: a table per frame and their concat cost
    ~0.1-0.2 ms a frame)."""
    if centre not in ("auto", "gauss", "radial"):
        raise UserError(f"centre = {centre!r} is not known", "use 'auto', 'gauss' or 'radial'")
    raw = np.ascontiguousarray(frame)
    if raw.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raw = raw.astype(np.float32)
    pol = None if brightfield is None else (-1 if brightfield else 1)
    # wall seconds per stage summed over the frames that share the cache (cache["stage_times_s"]: detect,
    # fit, centres), kept across detect's refresh of the maps (which clears the cache)
    tm = cache.get("stage_times_s", {"detect": 0.0, "fit": 0.0, "centres": 0.0}) if cache is not None else None
    t0 = time.perf_counter()
    det = detect(raw, scales=scales, polarity=pol, snr=snr, rate=rate, median=median, offset=offset, cache=cache)
    t1 = time.perf_counter()
    if tm is not None:
        cache["stage_times_s"] = tm
        tm["detect"] += t1 - t0
    rows, cols, scale, polarity = det["rows"], det["cols"], det["scale"], det["polarity"]
    n = len(rows)
    # background-subtracted image, particles positive (dark particles: the background minus the frame)
    bgmap, nzmap = det["background_map"], det["noise_map"]
    # (with a cache, into its scratch array: see ptrack.image.detect.scratch)
    buf = scratch(cache, "sub", raw.shape, np.float32)
    sub = np.subtract(raw, bgmap, dtype=np.float32, out=buf) if polarity > 0 else \
        np.subtract(bgmap, raw, dtype=np.float32, out=buf)
    # the frame's noise (counts): the median of its noise map, measured by detect once per map (frames that
    # share the maps through the cache share it; a full-frame median costs as much as the fits of a sparse frame)
    noise = det["noise_map_median"]
    if polarity > 0 and median and n:
        # isolated hot pixels would pull the likelihood fit of the raw counts: replaced by their 3x3 median
        # (the rule of repair_hot_pixels, 8 noise sigmas, tested only inside the fit windows)
        half_max = int(max(3, math.ceil(3 * float(np.max(scale))))) + 1
        hr, hc, hv = _hot_in_rois(raw, bgmap, 1, rows, cols, half_max, 8.0 * noise)
        if len(hr):
            raw = np.array(raw, copy=True)
            raw[np.asarray(hr), np.asarray(hc)] = np.asarray(hv)
    ring = np.zeros(n, np.bool_)
    if n:
        _ring_like(np.ascontiguousarray(sub, np.float32), rows, cols, scale.astype(np.float64), noise, ring)
    ring |= det["ring"]
    if centre == "gauss":
        ring[:] = False
    elif centre == "radial":
        ring[:] = True
    x = np.full(n, np.nan)
    y = np.full(n, np.nan)
    vx = np.full(n, np.nan)
    vy = np.full(n, np.nan)
    photons = np.full(n, np.nan)
    bgp = np.full(n, np.nan)
    size = scale.astype(float).copy()
    ecc = np.zeros(n)
    ok = np.zeros(n, bool)
    poisson = polarity > 0
    # Gaussian fits at each particle's own scale: spots are fitted in size classes spanning at most 2x
    # (the width is a fitted parameter, so the start needs only the right window); spots with a
    # neighbour whose light reaches into the window are fitted jointly, and a wide or elongated spot
    # is tested for being two unresolved ones (both only where images overlap)
    blob = ~ring
    uniq = np.unique(scale[blob])
    classes = []
    for s in uniq:
        if classes and s <= 2.05 * classes[-1][0]:
            classes[-1].append(s)
        else:
            classes.append([s])
    for cl in classes:
        # (a class is a run of consecutive values of the sorted uniq: membership is its range, cheaper than isin)
        q = np.nonzero(blob & (scale >= cl[0]) & (scale <= cl[-1]))[0]
        s0 = fast_median(scale[q])
        src = raw if poisson else sub
        fit = fit_spots(src, rows[q], cols[q], s0, gain=gain if poisson else 1.0,
                        offset=offset if poisson else 0.0, read_noise=read_noise, poisson=poisson,
                        amps=det["snr"][q], split=poisson)   # brightfield blobs with halos are not Gaussian: no split
        idx = q[fit["index"]]
        first = slice(0, len(q))        # the fits of the class's own spots (split halves follow them)
        x[q], y[q], vx[q], vy[q] = fit["x"][first], fit["y"][first], fit["var_x"][first], fit["var_y"][first]
        photons[q], bgp[q], size[q] = fit["photons"][first], fit["bg"][first], fit["s"][first]
        ecc[q], ok[q] = fit["ecc"][first], fit["ok"][first]
        extra = np.arange(len(q), len(fit["x"]))
        if len(extra):      # the second halves of split spots: new rows, detection values of their parent
            src_i = idx[extra]
            rows, cols, scale = np.r_[rows, rows[src_i]], np.r_[cols, cols[src_i]], np.r_[scale, scale[src_i]]
            ring, blob = np.r_[ring, np.zeros(len(extra), bool)], np.r_[blob, np.zeros(len(extra), bool)]
            det = dict(det, snr=np.r_[det["snr"], det["snr"][src_i]], signal=np.r_[det["signal"], det["signal"][src_i]])
            x, y = np.r_[x, fit["x"][extra]], np.r_[y, fit["y"][extra]]
            vx, vy = np.r_[vx, fit["var_x"][extra]], np.r_[vy, fit["var_y"][extra]]
            photons, bgp = np.r_[photons, fit["photons"][extra]], np.r_[bgp, fit["bg"][extra]]
            size, ecc, ok = np.r_[size, fit["s"][extra]], np.r_[ecc, fit["ecc"][extra]], np.r_[ok, fit["ok"][extra]]
    t2 = time.perf_counter()
    if tm is not None:
        tm["fit"] += t2 - t1
    # images a Gaussian does not describe, fitted with a free radial profile about a free centre
    # (radial.profile_centres) over the image's extent measured from the data: rings, and blobs that are
    # not diffraction-limited spots (Gaussian width >= LARGE_IMAGE px: defocused) or that sit in a ring of
    # the opposite sign (a bright centre in a dark ring)
    blob_ok = blob & ok & np.isfinite(x) & np.isfinite(y)
    nn_d = _nearest_other(rows, cols)
    H_, W_ = sub.shape
    edge_d = np.minimum.reduce([rows, cols, H_ - 1 - rows, W_ - 1 - cols]) - 1 if len(rows) else np.zeros(0)
    rmax_all = np.clip(np.minimum(np.floor(0.6 * nn_d), edge_d), 4, 24)
    sym = blob_ok & (size >= LARGE_IMAGE)
    rest = np.nonzero(blob_ok & ~sym)[0]
    if len(rest):
        # a ring of the opposite sign lies within a few scales of a blob's centre
        r_dip = np.minimum(rmax_all[rest], np.ceil(4.0 * scale[rest]) + 3)
        sym[rest] = has_dip(sub, x[rest], y[rest], nzmap[rows[rest], cols[rest]], r_dip)
    q = np.nonzero(ring)[0]
    if len(q):
        half = np.maximum(4, np.ceil(3.0 * scale[q])).astype(np.int64)
        rc = radial_centres(sub, rows[q], cols[q], half)
        x[q], y[q], vx[q], vy[q], ok[q] = rc["x"], rc["y"], rc["var_x"], rc["var_y"], rc["ok"]
        # photons of a ring: the background-subtracted sum over its window (counts / gain)
        photons[q] = [float(np.clip(sub[max(0, r - h):r + h + 1, max(0, c - h):c + h + 1], 0, None).sum()) / gain
                      for r, c, h in zip(rows[q], cols[q], half)] if len(q) < 5000 else np.nan
        bgp[q] = (bgmap[rows[q], cols[q]] - (offset if poisson else 0.0)) / (gain if poisson else 1.0)
    q = np.nonzero((ring & ok) | sym)[0]
    if len(q):
        rmax = rmax_all[q]
        ext = image_extent(sub, x[q], y[q], nzmap[rows[q], cols[q]], np.minimum(np.maximum(4, np.ceil(3.0 * scale[q])), rmax), rmax)
        pf = profile_centres(sub, rows[q], cols[q], np.minimum(np.ceil(ext) + 2, rmax).astype(np.int64), x[q], y[q],
                             noise=nzmap[rows[q], cols[q]], shot=gain if poisson else 0.0)
        use = pf["ok"]
        for a, b_ in ((x, "x"), (y, "y"), (vx, "var_x"), (vy, "var_y")):
            a[q] = np.where(use, pf[b_], a[q])
        ring[q] |= use
    if tm is not None:
        tm["centres"] += time.perf_counter() - t2
    mass = photons * (gain if poisson else 1.0)
    keep = ok & np.isfinite(x) & np.isfinite(y) & (np.nan_to_num(photons, nan=np.inf) > min_photons)
    k = np.nonzero(keep)[0]
    return [
        np.full(len(k), int(frame_no), np.int64), x[k], y[k], mass[k], size[k], ecc[k], det["signal"][k], photons[k],
        bgp[k], np.sqrt(np.abs(vx[k])), np.sqrt(np.abs(vy[k])), det["snr"][k], ring[k].astype(np.int8),
        np.full(len(k), polarity, np.int8),
    ]
