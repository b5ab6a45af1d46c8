"""Height (z) from a defocus calibration stack: General Defocusing Particle Tracking.

The method of Barnkob, Kaehler and Rossi (GDPT; the seed's chapter 4): a
calibration stack holds images of one particle at known heights z_k (page k).
Each particle image in a movie is compared with every calibration image by
zero-normalised cross-correlation (OpenCV ``matchTemplate`` with
``TM_CCOEFF_NORMED``); the best page gives z and its correlation is the
particle's ``cm``. Between calibration steps z is refined by a parabola
through Cm(z) at the best page and its two neighbours, and x, y by a parabola
through the correlation peak (the defocused image's own centre, not a spot
fit). Matches below a correlation threshold are dropped (GDPT's Cm_min).

In a movie (:func:`locate_3d`) candidates come from correlating a few
representative templates over the whole frame, and each accepted particle's
fitted template is subtracted before the next is matched, so that one
defocused (ring-shaped, astigmatic) image is reported once and overlapping
images are matched each with its neighbour removed.

Templates: each page is background-subtracted (median of its border), the
particle centre is found per page (thresholded centroid; a stack that drifts
sideways is fine), and a square window of the same size for every page is cut
around it; the sub-pixel position of the particle inside each template is
kept, so the reported x, y is the particle centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numba import njit

from .errors import UserError, check_positive, require_file
from .gdpt.ncc import (FrameSpectrum, Templates, _ncc_map, _ncc_pages, _ncc_pages_strided, _window_sums,
                       layouts_upto, ncc, ncc_pages, ncc_pages_strided)

_COMMON_WINDOW = True     # compare the pages around the best one on one window (see _match_one)
_COMMON_PAGES = 2         # pages either side of the best one (4: diffusion3d a little better, a close pair worse)
_WIDE_MASK = 1 / 8         # second candidate-mask smoothing, x the largest template side (see locate_3d)
_REFINE_SCALE = 1 / 1.2    # refine only particles whose 95 % light discs overlap (see build_calibration)
_PAIR_SEEDS = True         # _split also tries parts seeded at the window's best correlation maxima
_PAIR_LAST = True          # ... only when the grown attempts found no split (see _split)
_PAIR_SEP = 8.0            # px between those seeds (5: recall 0.944, overlapping-image z RMSE 2.15 %)
_SWEEP_MARGIN = 2          # shift range (px) of _split's re-matches of its parts after the first sweep
_JOINT_FIT = False         # _split places each part by a joint least-squares fit of all parts (_joint_place), for
                           # the attempts its plain sweeps leave unaccepted (_JOINT_RESCUE): bench_pipeline B
                           # diffusion3d recall 0.950 -> 0.960, precision 0.966 -> 0.968, but z RMSE of overlapping
                           # images 2.11 -> 2.86 % (pairs < 5 px apart at opposite heights, now found, both at one
                           # height) and 2.1x the CPU time (0.114 -> 0.244 s/frame); at every sweep end (not only
                           # rescue): 0.963 / 0.974 / 2.86 %, 2.9x: off
_JOINT_SWEEPS = 2          # sweeps of joint placement at the end of each _split attempt
_JOINT_RESCUE = True       # joint placement only for attempts that the plain sweeps leave unaccepted
_NEIGHBOUR_WEIGHT = None   # re-matches in locate_3d's refine passes weight each pixel by 1 / (1 + (b N / noise)^2),
                           # N the sum of |model| of the other particles there (see _weighted_ncc); None: off.
                           # b = 0.5: bench_pipeline B diffusion3d recall 0.937 -> 0.948, precision 0.960 -> 0.965,
                           # z RMSE of overlapping images 2.09 -> 1.61 % of the depth (b 0.1 / 0.25 / 1 / 2: 3.29 /
                           # 2.02 / 1.83 / 2.70 %); but make run: diffusion3d z RMSE 81 -> 88 nm (recall 0.917 ->
                           # 0.932), EPD v_z -4.98 +- 0.24 -> -4.97 +- 0.20 (1.2 -> 1.5 SE), and 1.5-2.5x the CPU
                           # time on crowded frames: off until that is understood
_SHIFT_STRIDE = 2          # _match_one's coarse pages at every 2nd shift (see there; 1: every shift): diffusion3d
                           # CPU 140 -> 125 ms/frame, bench_pipeline B figures within 0.01 %; bench_gdpt speed
                           # frames 11-25 % less CPU except the largest random images (0.95 um), recall there 0.59 -> 0.57
_SWEEP_TOL = 0.1          # _split's sweeps end after one that moved no part by more than this (px) nor changed its page
                           # (the refine passes' rule; -1: exactly unchanged placements, which sub-pixel offsets
                           # hardly ever are, so nearly every attempt ran all 3 sweeps): bench_pipeline B the same
                           # recall / precision, overlapping-image z RMSE 1.58 -> 1.56 %; ~6 % fewer matches
_FLIP_SWEEP_TOL = 0.1     # the same for _flip_branches' sweeps
_MODEL_SUMS = True         # _Residual.model's sums in one numba pass (_model_sums; False: NumPy, the same numbers)
_COARSE_EVERY = 2         # _match_one's coarse stage first scores every 2nd of its pages (and the last one), then the
                           # pages between those scoring within _COARSE_DELTA of the best (1: every page at once; 1 or
                           # 2 only: with 2 both neighbours of the coarse best are always scored)
_COARSE_DELTA = 0.1       # (correlation units)
_MATCH_CORE = True        # _match_one's plain coarse-to-fine path in one numba call (_match_core; False: step by step)
_STILL_CORE = True        # _still_there in one numba call (_still_core; False: NumPy step by step, the same answers)
_BOUND_FFT = True         # _snr_bound's sums of t w from _candidates' FFT correlations of the same residual (zero-mean
                           # template's, plus mean(t) x the window sum) instead of one whole-frame OpenCV TM_CCORR per
                           # page (~3 % of a random frame): the bound only skips candidates that _still_there refuses
                           # anyway (below 0.9 x its threshold; both sums within ~1e-6 of exact), so the same answers
_PER_AMP_CACHE = True     # locate_3d's per-page template signal (sum of max(t, 0), 301 pages) cached on the templates
                           # (~1.7 % of a random frame when made per frame; the same numbers)
_CAND_ARRAYS = True       # locate_3d's candidate loop: the distance to the nearest hit and the skip by _snr_bound (at
                           # the round's starting overlaps; touched windows) kept as arrays over the candidates, updated
                           # once per accepted hit, instead of per-candidate calls (~900 candidates a random frame; the
                           # same float64 values and integer tests: the same candidates skipped)
_SHARED_VAR = True        # _candidates' window variances made once per template size for the whole frame
                           # (FrameSpectrum.box_var, branch-free) and read by the pages of that size (the 7 pages
                           # have ~4 sizes), instead of per page and pixel inside _ncc_region_max; the same values
_REFINE_LISTS = True      # locate_3d's refine passes: the overlap tests against the other hits on their window
                           # centres and sides held in a list per pass (no dict copy per pair and test), and the
                           # 2 px test's np.hypot only for hits within 2 px in both axes (the same exact arithmetic
                           # and hypot values: the same decisions; ~4 % of a random frame at d = 0.95 um in py-spy)
_WINDOW_LEAN = True       # _best_in_window: its representative pages and their rounded centres cached, divmod for
                           # np.unravel_index (~4 us each); the same pages, centres and maxima
_WINDOW_ADD = True        # _Residual.add / subtract of a model by one numba call (_add_window; ~580 a random frame
                           # at d = 0.95 um, ~1.5 us less each than NumPy's in-place slice op; the same float32 sums)
_MASK_ROWS = True         # locate_3d's candidate mask grown by OpenCV's elliptic structuring element through its rows
                           # (_dilate_rows: each kernel row a symmetric run, tested against each frame row's distance
                           # to its nearest signal pixel; the same mask, ~1 % of a random frame)
_FLIP = True               # locate_3d tries the other side of focus for badly explained overlapping images
                           # (_flip_branches): bench_pipeline B diffusion3d recall 0.952 -> 0.955, precision 0.970
                           # -> 0.972, overlapping-image z RMSE 2.06 -> 1.59 % of the depth
_FLIP_CHI2 = 1.2           # ... whose window's chi^2 per pixel is above this x the frame's typical one
_FLIP_CM = 0.98            # ... and whose Cm is below this (a better match is one image explained by its template)
_FLIP_SCALE = 1 / 1.2       # windows (x this about their centres) that overlap make a cluster
_FLIP_MAX = 2              # at most this many images of a cluster flipped at once
__all__ = ["Calibration", "read_calib_z", "build_calibration", "load_calibration", "prepare_gdpt", "check_pixel_size",
           "detect_blobs", "match_templates", "locate_3d", "locate_frame_3d"]


@dataclass
class Calibration:
    """Templates of one particle at known heights.

    Attributes
    ----------
    templates : list of K ndarrays (T_k, T_k), float32
        Background-subtracted calibration images, T_k odd, sized per page.
    z : ndarray, shape (K,)
        Height of each template (m), strictly increasing.
    centers : ndarray, shape (K, 2)
        (row, col) of the particle centre inside each template (px).
    pixel_size : float or None
        m per pixel of the stack.
    source : str
    """

    templates: np.ndarray
    z: np.ndarray
    centers: np.ndarray
    pixel_size: float | None = None
    source: str = ""
    info: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        """Largest template side (px)."""
        return int(max(t.shape[0] for t in self.templates))

    @property
    def depth(self) -> float:
        """Calibrated depth range z_max - z_min (m)."""
        return float(self.z[-1] - self.z[0])

    @property
    def step(self) -> float:
        """Median calibration step (m)."""
        return float(np.median(np.diff(self.z))) if len(self.z) > 1 else float("nan")


def read_calib_z(path, n_pages: int) -> np.ndarray:
    """Heights (m) of the pages of a calibration stack from a CSV with columns ``page``, ``z``.

    Raises
    ------
    UserError
        Missing columns, pages not covering 0..n_pages-1, non-finite z.
    """
    path = require_file(path, "calibration z file")
    try:
        df = pd.read_csv(path, comment="#")
    except Exception as exc:
        raise UserError(f"cannot read {path} as CSV: {exc}", "give a CSV with columns page, z (m)") from None
    cols = {c.strip().lower(): c for c in df.columns}
    if "page" not in cols or "z" not in cols:
        raise UserError(f"{path} lacks columns page, z (has {', '.join(map(str, df.columns))})",
                        "give a CSV with columns page (0-based) and z (m)")
    page = pd.to_numeric(df[cols["page"]], errors="coerce").to_numpy()
    z = pd.to_numeric(df[cols["z"]], errors="coerce").to_numpy(dtype=float)
    if not np.all(np.isfinite(z)) or not np.all(np.isfinite(page)):
        raise UserError(f"{path} has non-numeric page or z values", "give numbers (z in m)")
    page = page.astype(int)
    if sorted(page.tolist()) != list(range(n_pages)):
        raise UserError(f"{path} lists {len(page)} pages ({page.min()}..{page.max()}), the stack has {n_pages}",
                        f"give one row per page 0..{n_pages - 1}")
    out = np.empty(n_pages)
    out[page] = z
    if np.abs(out).max() > 0.01:
        raise UserError(f"{path}: z values up to {np.abs(out).max():g} look like micrometres, not metres",
                        "give z in metres (e.g. 2e-6 for 2 µm)")
    return out


def _page_centre(img, noise, signed: bool = False):
    """(row, col) centre and the radius holding 95 % of the image's light, of one background-subtracted page.

    ``signed``: brightfield pages, whose defocused images are rings both
    darker and brighter than the field; their centre and extent are taken on
    the magnitude of the (1 px smoothed) signal, so the bright lobes count
    as much as the dark ones.
    """
    if signed:
        import cv2

        img = np.abs(cv2.GaussianBlur(np.ascontiguousarray(img, np.float32), (0, 0), 1.0))
        border = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
        # noise of |smoothed noise|: its median and spread over the border
        base = float(np.median(border))
        noise = 1.4826 * float(np.median(np.abs(border - base))) + 1e-6
        img = img - base
    thr = max(3 * noise, 0.2 * float(img.max()))
    w = np.clip(img - thr, 0, None)
    s = w.sum()
    if s <= 0:
        return None
    r = np.arange(img.shape[0])
    c = np.arange(img.shape[1])
    cy = float((w.sum(1) * r).sum() / s)
    cx = float((w.sum(0) * c).sum() / s)
    # radius holding 95 % of the excess intensity
    pos = np.clip(img - 2.0 * noise, 0, None)   # noise-free support: positive noise would fill the page
    rr, cc = np.indices(img.shape)
    d = np.hypot(rr - cy, cc - cx).ravel()
    order = np.argsort(d)
    cum = np.cumsum(pos.ravel()[order])
    r95 = float(d[order][np.searchsorted(cum, 0.95 * cum[-1])]) if cum[-1] > 0 else 3.0
    return cy, cx, r95


def build_calibration(stack, z, pixel_size=None, template_size: int | None = None, brightfield: bool = False,
                      source: str = "", max_beads: int | None = None, fine_step="auto") -> Calibration:
    """Templates from a calibration stack held in memory (:mod:`ptrack.gdpt`).

    Each page's background is estimated from its bead-free pixels, the
    bead(s) are found and followed from page to page, each page's template
    is cut to the extent of that page's image, several beads are registered
    on their centres and averaged, pages where no bead is whole are rejected
    (named in a warning and in ``info["rejected"]``), and coarse steps are
    filled with templates interpolated between pages (``fine_step``).

    Parameters
    ----------
    stack : array (K, H, W)
        One image of the calibration bead(s) per height (crops or full frames).
    z : array (K,)
        Heights (m); pages are sorted by z.
    pixel_size : float, optional
        m per pixel.
    template_size : int, optional
        Template side (px, made odd); default from each page's image.
    brightfield : bool or None
        Invert the pages first (dark particles); templates are signed.
        None: decided from the stack (:func:`ptrack.gdpt.stack.stack_polarity`);
        a setting the stack clearly contradicts is a UserError.
    max_beads : int, optional
        Use at most this many beads (the brightest).
    fine_step : float, "auto" or None
        Spacing (m) of the interpolated templates; "auto": steps over
        0.2 um are divided into parts of 0.2 um or less; None: pages only.

    Returns
    -------
    Calibration
        ``info`` holds ``n_beads``, ``bead_xy`` (px), ``rejected``
        ({page: reason}), ``page_z`` (heights of the pages used), ``n_sub``
        (templates per page step) and, with several beads, ``bead_dz``
        (each bead's pages read on the average, minus their height, m) and
        ``z_error`` (m: the z error of one image read on this calibration,
        from each page read on the calibration built without it,
        ``z_error_loo``, and the spread between beads, ``z_error_beads``, in
        quadrature; within 0.85-1.6x of the z RMSE measured against truth).
    """
    from .gdpt.build import build_templates

    stack = np.asarray(stack, dtype=np.float32)
    z = np.asarray(z, dtype=float)
    if stack.ndim != 3 or len(stack) != len(z):
        raise UserError(f"calibration stack of shape {stack.shape} with {len(z)} heights",
                        "give one height per page")
    if len(z) < 3:
        raise UserError(f"calibration stack has {len(z)} pages", "a calibration needs at least 3 heights")
    order = np.argsort(z)
    stack, z = stack[order], z[order]
    if np.any(np.diff(z) <= 0):
        raise UserError("calibration heights are not distinct", "give one distinct z per page")
    from .gdpt.stack import stack_polarity

    pol, ratio = stack_polarity(stack)
    if brightfield is None:
        brightfield = pol == "dark"         # from the stack itself (unambiguous near focus)
    elif ratio > 5 and (pol == "dark") != bool(brightfield):
        raise UserError(f"calibration stack {source or ''} shows {pol} particles (strongest excursion {ratio:.0f}x the "
                        f"opposite one) but {'brightfield' if brightfield else 'fluorescence'} was asked for "
                        "(given, or detected from the movie)",
                        f"give {'--fluorescence' if pol == 'bright' else '--brightfield'}")
    if brightfield:
        stack = stack.max() - stack
    templates, zz, centers, info = build_templates(stack, z, bool(brightfield), template_size, max_beads, fine_step)
    T = max(t.shape[0] for t in templates)
    info.update(template_size=T, signed=bool(brightfield))
    return Calibration(templates, zz, centers, pixel_size, source, info)


def load_calibration(path, z_csv=None, z_step: float | None = None, z0: float = 0.0, pixel_size=None,
                     template_size: int | None = None, brightfield: bool = False, max_beads: int | None = None,
                     fine_step="auto") -> Calibration:
    """Read a calibration stack (any movie format of :func:`ptrack.io.open_movie`) and build its templates.

    Heights, first found of: ``z_csv`` (CSV with columns page, z in m);
    ``z_step`` (page k at ``z0 + k z_step``); a CSV beside the stack
    (``<stem>_z.csv``, ``<stem>.z.csv`` or ``calib_z.csv``); the stack's
    own metadata (Micro-Manager stage positions, OME PositionZ or
    PhysicalSizeZ, ImageJ spacing; a spacing starts at ``z0``). Heights no
    stack can have (beyond 1 mm, or a step far too small for how fast the
    particle image grows) are refused. ``info["z_source"]`` says where the
    heights came from. Other parameters as :func:`build_calibration`.
    """
    from pathlib import Path

    from .gdpt.heights import check_heights, heights_from_metadata, z_csv_beside
    from .io import open_movie

    no_heights = UserError("the heights of the calibration pages are not given",
                           "give --calib-z CSV (columns page, z in m) or --calib-step DZ (m) [--calib-z0 Z0], "
                           "or put calib_z.csv beside the stack")
    if z_csv is None and z_step is None and not Path(str(path)).is_file():
        raise no_heights
    with open_movie(path, pixel_size=pixel_size) as mv:
        K = len(mv)
        if K < 3:
            raise UserError(f"calibration stack {path} has {K} page(s)", "a calibration needs at least 3 heights")
        px = mv.pixel_size
        if z_csv is None and z_step is None:
            z_csv = z_csv_beside(path)
            meta = None if z_csv is not None else heights_from_metadata(path, K, float(z0))
            if z_csv is None and meta is None:
                raise no_heights
        stack = np.stack([mv[i] for i in range(K)])
    if z_csv is not None:
        z = read_calib_z(z_csv, K)
        what = str(z_csv)
    elif z_step is not None:
        dz = check_positive("calibration step", z_step)
        z = float(z0) + dz * np.arange(K)
        what = "--calib-step/--calib-z0"
    else:
        z, what = meta
        what = f"the stack's metadata ({what})"
    check_heights(z, what)
    cal = build_calibration(stack, z, px, template_size, brightfield, source=str(path), max_beads=max_beads,
                            fine_step=fine_step)
    check_heights(z, what, cal)
    cal.info["z_source"] = what
    return cal


def prepare_gdpt(raw, calib: Calibration, brightfield: bool = False, background="spatial") -> np.ndarray:
    """One movie frame made ready for :func:`locate_3d` the way the calibration's templates were made.

    Brightfield is inverted (dark particles positive) and kept *signed*:
    defocused brightfield images are rings with lobes both darker and
    brighter than the field, and the normalised cross-correlation needs both;
    nothing is thresholded. The spatial background is then a running median
    (an opening follows the lower envelope and would dip under every ring), window 3x
    the largest template. Fluorescence: the usual opening.

    Parameters
    ----------
    raw : 2D array
        Camera frame.
    calib : Calibration
        From :func:`build_calibration` / :func:`load_calibration` with the
        same ``brightfield`` setting.
    brightfield : bool
    background : "spatial", "none" or 2D array
        As :func:`ptrack.preprocess.prepare` (an array: already inverted for
        brightfield).

    Returns
    -------
    numpy.ndarray of float32
    """
    from .preprocess import prepare

    signed = bool(calib.info.get("signed", False))
    if signed != bool(brightfield):
        raise UserError(f"the calibration stack was built {'with' if signed else 'without'} --brightfield, "
                        f"the movie is {'brightfield' if brightfield else 'fluorescence'}",
                        "build the calibration with the same --brightfield setting as the movie")
    return prepare(raw, brightfield=brightfield, background=background, bg_size=3.0 * calib.size, signed=signed)


def check_pixel_size(calib: Calibration, pixel_size: float | None, rtol: float = 0.01) -> None:
    """Raise UserError if the stack's pixel size differs from the movie's by more than ``rtol``."""
    if calib.pixel_size is None or pixel_size is None:
        return
    if abs(calib.pixel_size - pixel_size) > rtol * pixel_size:
        raise UserError(
            f"calibration stack {calib.source} has pixel size {calib.pixel_size * 1e9:.1f} nm, "
            f"the movie {pixel_size * 1e9:.1f} nm",
            "record the calibration with the same objective, camera and binning as the movie")


def detect_blobs(img, sigma: float = 2.0, snr: float = 6.0, min_area: int = 4, close: int = 3):
    """Candidate particle centres for defocused images: connected regions above threshold.

    Parameters
    ----------
    img : 2D float32
        Background-subtracted frame.
    sigma : float
        Smoothing (px) before thresholding.
    snr : float
        Threshold in units of the smoothed image's noise.
    min_area : int
        Smallest region (px).
    close : int
        Dilation (px) joining the pieces of a ring.

    Returns
    -------
    rows, cols : ndarray of float
        Intensity-weighted centroids (px).
    area : ndarray of int
    """
    import cv2

    from .preprocess import median3, noise_sigma

    sm = cv2.GaussianBlur(median3(img), (0, 0), sigmaX=float(sigma))
    thr = float(np.median(sm[::5, ::5])) + snr * max(noise_sigma(sm), 1e-6)
    mask = (sm > thr).astype(np.uint8)
    if close > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * close + 1, 2 * close + 1)))
    n, labels, stats, cent = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area)[0] + 1
    if keep.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, int)
    w = np.clip(sm - thr, 0, None).ravel()
    lab = labels.ravel()
    rr, cc = np.divmod(np.arange(lab.size), sm.shape[1])
    sw = np.bincount(lab, w, minlength=n)
    sr = np.bincount(lab, w * rr, minlength=n)
    sc = np.bincount(lab, w * cc, minlength=n)
    ok = keep[sw[keep] > 0]
    return sr[ok] / sw[ok], sc[ok] / sw[ok], stats[ok, cv2.CC_STAT_AREA]


def _pixel_noise(img) -> float:
    """Robust per-pixel noise (same units as ``img``) from differences of horizontal neighbours (smooth signal
    cancels; 1.4826 x MAD / sqrt 2)."""
    d = np.diff(np.asarray(img, np.float32)[::2], axis=1).ravel()
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


_SMOOTH_NOISE: dict = {}


def _smoothed_noise(sigma: float) -> float:
    """Standard deviation of white unit noise after the 3 x 3 median and a Gaussian blur of ``sigma`` px
    (measured once on a seeded 256^2 field)."""
    key = round(float(sigma), 3)
    if key not in _SMOOTH_NOISE:
        import cv2

        from .preprocess import median3

        n = np.random.default_rng(0).standard_normal((256, 256)).astype(np.float32)
        _SMOOTH_NOISE[key] = float(cv2.GaussianBlur(median3(n), (0, 0), sigmaX=key)[32:-32, 32:-32].std())
    return _SMOOTH_NOISE[key]


def _gauss3(y0, y1, y2):
    """Sub-pixel offset of a peak from three samples by a Gaussian (log-parabola) fit.

    Less biased towards the sample than a plain parabola for the bell-shaped
    peak of a correlation map; falls back to the parabola when a sample is
    not positive.  One rule with :func:`_match_core`'s: this calls its kernel, :func:`_gauss3_nb`.
    """
    return float(_gauss3_nb(y0, y1, y2))


def _subpixel_peaks(maps):
    """Height of each correlation map's maximum, refined by a parabola through it and its neighbours per axis.

    A particle sits between pixels while a template is centred on one: the
    correlation at the nearest integer shift is lower than at the true
    shift, more so for sharp (in-focus) templates than for blurred ones, which
    would bias z towards defocus. The sub-pixel peak height removes that bias.
    (Until now the column neighbours of square maps were read transposed, so
    the x part of the correction was noise; corrected: isolated particles
    0.53 -> 0.32 % of the depth at 20000 photons, 1.11 -> 0.97 % at 4000.)
    """
    maps = np.asarray(maps, np.float32)
    out = np.empty(maps.shape[0])
    _subpixel_peaks_kernel(maps, out)
    return out


@njit(cache=True)
def _subpixel_peaks_kernel(maps, out):
    # one loop over the maps instead of ~20 numpy calls on arrays of a few pages (~180 us per call); the same
    # float32 differences and float64 correction as the array code it replaces (bit-identical)
    K, ny, nx = maps.shape
    two = np.float32(2.0)
    for k in range(K):
        best = 0
        for q in range(1, ny * nx):
            if maps[k, q // nx, q % nx] > maps[k, best // nx, best % nx]:
                best = q
        i, j = best // nx, best % nx
        c = maps[k, i, j]
        o = np.float64(c)
        for ax in range(2):
            if ax == 0:
                if not (0 < i < ny - 1):
                    continue
                y0, y2 = maps[k, i - 1, j], maps[k, i + 1, j]
            else:
                if not (0 < j < nx - 1):
                    continue
                y0, y2 = maps[k, i, j - 1], maps[k, i, j + 1]
            curv = np.float64(y0 + y2 - two * c)
            if curv < 0:
                d = np.float64(y2 - y0)
                o -= d ** 2 / (8 * curv)
        out[k] = o


@njit(cache=True)
def _gauss3_nb(y0, y1, y2):
    # _gauss3's rule (the one copy of it): the log-parabola in double precision, the parabola fallback in the
    # samples' precision (float32 for correlation maps)
    if y0 > 0 and y1 > 0 and y2 > 0:
        l0, l1, l2 = math.log(np.float64(y0)), math.log(np.float64(y1)), math.log(np.float64(y2))
        den = l0 - 2 * l1 + l2
        if den < 0:
            return min(max(0.5 * (l0 - l2) / den, -1.0), 1.0)
    e0 = y0 - y1
    e2 = y2 - y1
    two = np.float32(2.0)
    a = (e0 + e2) / two
    b = (e2 - e0) / two
    if a >= 0:
        return 0.0
    t = -b / (two * a)
    if t < -1.0:
        return -1.0
    if t > 1.0:
        return 1.0
    return np.float64(t)


@njit(cache=True)
def _quadratic_peak_nb(z, c, k, n_points, drop):
    # the window rule of _quadratic_peak (n_points < 0: None), on float64 arrays; the one copy of it
    K = len(z)
    if n_points < 0:
        miss = 1.0 - c[k]
        w = 1 if miss < 0.002 else (2 if miss < 0.006 else 4)
        while w > 1 and c[max(0, k - w):min(K, k + w + 1)].min() < c[k] - drop:
            w -= 1
    else:
        w = max(1, n_points // 2)
    lo, hi = max(0, k - w), min(K, k + w + 1)
    if hi - lo < 3:
        return z[k]
    return _parabola_fit_vertex(z, c, k, lo, hi)


@njit(cache=True)
def _argmax2(mp):
    # flat index of the first maximum of a 2-D map
    ny, nx = mp.shape
    best = 0
    v = mp[0, 0]
    for q in range(1, ny * nx):
        if mp[q // nx, q % nx] > v:
            v = mp[q // nx, q % nx]
            best = q
    return best


@njit(cache=True)
def _peaks_of(maps, pages):
    # _subpixel_peaks of maps[pages]
    sub = np.empty((len(pages), maps.shape[1], maps.shape[2]), np.float32)
    for q in range(len(pages)):
        sub[q] = maps[pages[q]]
    out = np.empty(len(pages))
    _subpixel_peaks_kernel(sub, out)
    return out


@njit(cache=True)
def _coarse_first(P, every):
    # indices of the coarse pages scored first: every ``every``-th one and the last one
    ev = np.zeros(P, np.bool_)
    for q in range(0, P, max(every, 1)):
        ev[q] = True
    if P:
        ev[P - 1] = True
    return np.flatnonzero(ev)


@njit(cache=True)
def _coarse_fill(s, every, delta):
    # the coarse pages not scored yet (s = -inf) within every - 1 of a scored one that scores within delta of the
    # best: where the coarse best may lie between the samples
    P = len(s)
    b = -np.inf
    for q in range(P):
        if s[q] > b:
            b = s[q]
    add = np.zeros(P, np.bool_)
    for q in range(P):
        if s[q] != -np.inf and s[q] >= b - delta:
            for d in range(1 - every, every):
                if 0 <= q + d < P and s[q + d] == -np.inf:
                    add[q + d] = True
    return np.flatnonzero(add)


@njit(cache=True)
def _match_core(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs, K, plo, phi, coarse, stride, fine_margin,
                common, cpages, zc, z_points, cm_drop, every, delta):
    # _match_one's batch coarse-to-fine path in one call, the same correlations (gdpt.ncc kernels, same windows and
    # shift ranges) and the same selection: (page, cm, z, i, j, di, dj). fine_margin, z_points < 0: None. The
    # coarse pages scored in two steps (_coarse_first, _coarse_fill; every, delta: _COARSE_EVERY, _COARSE_DELTA)
    n = 2 * m + 1
    maps = np.full((K, n, n), -1.0, np.float32)
    f0 = -(-plo // coarse) * coarse
    first = np.arange(f0, phi, coarse)
    P = len(first)
    if stride > 1:
        nc = (2 * m) // stride + 1
        cmaps = np.empty((P, nc, nc), np.float32)
        pk = np.full(P, -np.inf)
        qs = _coarse_first(P, every)
        for step_ in range(2):
            if step_:
                qs = _coarse_fill(pk, every, delta)
            if len(qs) == 0:
                continue
            tmp = np.empty((len(qs), nc, nc), np.float32)
            _ncc_pages_strided(img, ri, ci, m, offs, sizes, zflat, tns, lflat, loffs[2 * m], first[qs], stride, tmp)
            pq = np.empty(len(qs))
            _subpixel_peaks_kernel(tmp, pq)
            for u in range(len(qs)):
                cmaps[qs[u]] = tmp[u]
                pk[qs[u]] = pq[u]
        q = int(np.argmax(pk))
        best = first[q]
        ab = _argmax2(cmaps[q])
        i0, j0 = (ab // nc) * stride, (ab % nc) * stride
        lo, hi = max(plo, best - coarse - 1), min(phi, best + coarse + 2)
        fw = m if fine_margin < 0 else max(stride, fine_margin)
        done = np.arange(lo, hi)
        a0, a1 = max(i0 - fw, 0), min(i0 + fw, n - 1) + 1
        b0, b1 = max(j0 - fw, 0), min(j0 + fw, n - 1) + 1
        tmp = np.empty((len(done), n, n), np.float32)
        _ncc_pages(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs[b1 - b0 - 1], done, 0, a0, a1, b0, b1,
                   tmp)
        for q in range(len(done)):
            maps[done[q]] = tmp[q]
    else:
        sc = np.full(P, -np.inf)
        qs = _coarse_first(P, every)
        for step_ in range(2):
            if step_:
                qs = _coarse_fill(sc, every, delta)
            if len(qs) == 0:
                continue
            fm = np.empty((len(qs), n, n), np.float32)
            _ncc_pages(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs[n - 1], first[qs], 0, 0, n, 0, n,
                       fm)
            for u in range(len(qs)):
                maps[first[qs[u]]] = fm[u]
                sc[qs[u]] = fm[u].max()
        bq = 0
        bv = -np.inf
        for q in range(P):      # the first of the best (as np.argmax of the maps' maxima)
            if sc[q] > bv:
                bv = sc[q]
                bq = q
        best = first[bq]
        lo, hi = max(plo, best - coarse - 1), min(phi, best + coarse + 2)
        ab = _argmax2(maps[best])
        i0, j0 = ab // n, ab % n
        near = fine_margin >= 0 and m > fine_margin
        nks = 0
        for k in range(lo, hi):
            if k % coarse:
                nks += 1
        if nks:
            ks = np.empty(nks, np.int64)
            nks = 0
            for k in range(lo, hi):
                if k % coarse:
                    ks[nks] = k
                    nks += 1
            if near:
                a0, a1 = max(i0 - fine_margin, 0), min(i0 + fine_margin, n - 1) + 1
                b0, b1 = max(j0 - fine_margin, 0), min(j0 + fine_margin, n - 1) + 1
            else:
                a0, a1, b0, b1 = 0, n, 0, n
            tmp = np.empty((nks, n, n), np.float32)
            _ncc_pages(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs[b1 - b0 - 1], ks, 0, a0, a1, b0,
                       b1, tmp)
            for q in range(nks):
                maps[ks[q]] = tmp[q]
        sel = np.zeros(K, np.bool_)
        for q in range(P):
            if sc[q] != -np.inf:
                sel[first[q]] = True
        sel[lo:hi] = True
        done = np.flatnonzero(sel)
    peak = np.full(K, -1.0)
    pd_ = _peaks_of(maps, done)
    for q in range(len(done)):
        peak[done[q]] = pd_[q]
    k = int(np.argmax(peak))
    cm = peak[k]
    have_z = False
    z = 0.0
    if common:
        lo2, hi2 = max(plo, k - cpages), min(phi, k + cpages + 1)
        Tc = sizes[lo2:hi2].min()
        if sizes[lo2:hi2].max() > Tc:
            ab = _argmax2(maps[k])
            i0, j0 = ab // n, ab % n
            if m > 2:
                a0, a1 = max(i0 - 2, 0), min(i0 + 2, n - 1) + 1
                b0, b1 = max(j0 - 2, 0), min(j0 + 2, n - 1) + 1
            else:
                a0, a1, b0, b1 = 0, n, 0, n
            pg = np.arange(lo2, hi2)
            tmp = np.empty((hi2 - lo2, n, n), np.float32)
            _ncc_pages(img, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs[b1 - b0 - 1], pg, Tc, a0, a1, b0,
                       b1, tmp)
            for q in range(hi2 - lo2):
                maps[lo2 + q] = tmp[q]
            pk2 = np.empty(hi2 - lo2)
            _subpixel_peaks_kernel(tmp, pk2)
            kk = int(np.argmax(pk2))
            k, cm = lo2 + kk, pk2[kk]
            z = _quadratic_peak_nb(zc[lo2:hi2], pk2, kk, z_points, cm_drop)
            have_z = True
    if not have_z:
        z = _quadratic_peak_nb(zc, peak, k, z_points, cm_drop)
    mp = maps[k]
    ab = _argmax2(mp)
    i, j = ab // n, ab % n
    di = dj = 0.0
    if 0 < i < n - 1:
        di = _gauss3_nb(mp[i - 1, j], mp[i, j], mp[i + 1, j])
    if 0 < j < n - 1:
        dj = _gauss3_nb(mp[i, j - 1], mp[i, j], mp[i, j + 1])
    return k, cm, z, i, j, di, dj


def _quadratic_peak(z, c, k, n_points=None, drop: float = 0.15):
    """z of the maximum of a least-squares parabola through Cm(z) around page k.

    By default 3, 5 or 9 pages as the best Cm is above 0.998, above 0.994 or
    lower (a noisy match needs more pages to average over; a clean one has a
    sharp peak that a wide parabola would bias), narrowed while any page's
    Cm falls more than ``drop`` below the best (coarse calibration steps get
    the classic three-point vertex).
    ``n_points`` fixes the window instead.  One rule with :func:`_match_core`'s: this calls its kernel,
    :func:`_quadratic_peak_nb`, on float64 arrays.
    """
    return float(_quadratic_peak_nb(np.asarray(z, np.float64), np.asarray(c, np.float64), int(k),
                                    -1 if n_points is None else int(n_points), float(drop)))


@njit(cache=True)
def _parabola_fit_vertex(z, c, k, lo, hi):
    # least-squares parabola c = a u^2 + b u + e through (z[lo:hi], c[lo:hi]), u = (z - z[k]) / s scaled to
    # about 1 (well-conditioned normal equations, solved by Cramer's rule: ~15x less than np.linalg.solve of
    # the 3 x 3 system per call); its vertex, clipped to the window, or z[k] if the fit opens upwards
    s = max(abs(z[lo] - z[k]), abs(z[hi - 1] - z[k]))
    if s == 0.0:
        return z[k]
    S0 = S1 = S2 = S3 = S4 = T0 = T1 = T2 = 0.0
    for q in range(lo, hi):
        u = (z[q] - z[k]) / s
        u2 = u * u
        S0 += 1.0
        S1 += u
        S2 += u2
        S3 += u2 * u
        S4 += u2 * u2
        T0 += c[q]
        T1 += c[q] * u
        T2 += c[q] * u2
    # [S4 S3 S2; S3 S2 S1; S2 S1 S0] (a, b, e) = (T2, T1, T0)
    det = S4 * (S2 * S0 - S1 * S1) - S3 * (S3 * S0 - S1 * S2) + S2 * (S3 * S1 - S2 * S2)
    if det == 0.0:
        return z[k]
    a = (T2 * (S2 * S0 - S1 * S1) - S3 * (T1 * S0 - S1 * T0) + S2 * (T1 * S1 - S2 * T0)) / det
    b = (S4 * (T1 * S0 - S1 * T0) - T2 * (S3 * S0 - S1 * S2) + S2 * (S3 * T0 - T1 * S2)) / det
    if a >= 0.0:
        return z[k]
    t = -b / (2.0 * a) * s
    return z[k] + min(max(t, z[lo] - z[k]), z[hi - 1] - z[k])


def smoothed_templates(calib: Calibration, smooth: float) -> Templates:
    """The calibration's templates blurred by a Gaussian of ``smooth`` px (0: as they are), packed for
    :func:`ptrack.gdpt.ncc.ncc_pages`.

    Cached in ``calib.info["_smoothed"]`` per ``smooth`` (and per templates
    object: a calibration whose templates are replaced is smoothed again):
    the same for every frame, and ~10 ms per frame for 31 templates of up
    to 220 px.
    """
    import cv2

    key = float(smooth) if smooth and smooth > 0 else 0.0
    cache = calib.info.setdefault("_smoothed", {})
    hit = cache.get(key)
    if hit is not None and hit[0] is calib.templates:
        return hit[1]
    if key > 0:
        tmpl = Templates(cv2.GaussianBlur(t, (0, 0), sigmaX=key) for t in calib.templates)
    else:
        tmpl = Templates(calib.templates)
    cache[key] = (calib.templates, tmpl)
    return tmpl


def _prepare_matching(img, calib: Calibration, smooth: float, margin: int):
    """Smoothed, zero-padded frame and smoothed templates (the frame is background-subtracted: 0 = background)."""
    import cv2

    m = int(margin)
    pad = calib.size // 2 + m + 1
    img = np.ascontiguousarray(img, np.float32)
    tmpl = smoothed_templates(calib, smooth)
    if smooth and smooth > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=float(smooth))
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    return padded, pad, tmpl


def _masked_ncc(win, t, r0, r1, c0, c1):
    """Zero-normalised cross-correlation of template ``t`` over ``win`` using only the template's rows r0:r1,
    cols c0:c1 (what OpenCV's masked TM_CCOEFF_NORMED computes, from three unmasked correlations, ~10x faster)."""
    import cv2

    sub = t[r0:r1, c0:c1].astype(np.float64)
    N = sub.size
    tp = np.zeros_like(t)
    tp[r0:r1, c0:c1] = (sub - sub.mean()).astype(np.float32)
    num = cv2.matchTemplate(win, tp, cv2.TM_CCORR)
    ny, nx = num.shape
    # window sums of win and win^2 over the mask rectangle at every shift, from an integral image
    w = win.astype(np.float64)
    S1 = cv2.integral(w)
    S2 = cv2.integral(w * w)
    h, wd = r1 - r0, c1 - c0

    def box(S):
        return (S[r0 + h:r0 + h + ny, c0 + wd:c0 + wd + nx] - S[r0:r0 + ny, c0 + wd:c0 + wd + nx]
                - S[r0 + h:r0 + h + ny, c0:c0 + nx] + S[r0:r0 + ny, c0:c0 + nx])

    s1, s2 = box(S1), box(S2)
    var_w = np.maximum(s2 - s1 * s1 / N, 0.0)
    den = np.sqrt(var_w * float((tp.astype(np.float64) ** 2).sum()))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den > 0, num / den, np.nan)
    return out.astype(np.float32)


def _weighted_ncc(win, wts, t):
    """Weighted zero-normalised cross-correlation of template ``t`` over ``win`` (the TM_CCOEFF_NORMED map shape).

    ``wts`` (the shape of ``win``, frame pixels) weights every pixel of the
    window in the means, covariance and variances at each shift: pixels
    dominated by a neighbour's subtracted model, whose leftovers would pull
    the match, count less. Six whole-window correlations (sums of w t I,
    w t, w t^2, w, w I, w I^2 at every shift).
    """
    import cv2

    t = np.ascontiguousarray(t, np.float32)
    w = np.ascontiguousarray(wts, np.float32)
    if float(w.min()) >= 0.999:
        return ncc(win, t)     # no neighbour's light here: the plain NCC
    wi = w * win
    A = cv2.matchTemplate(wi, t, cv2.TM_CCORR).astype(np.float64)
    B = cv2.matchTemplate(w, t, cv2.TM_CCORR).astype(np.float64)
    C = cv2.matchTemplate(w, t * t, cv2.TM_CCORR).astype(np.float64)
    ny, nx = A.shape
    T0, T1 = t.shape

    def box(x):         # sums over the template's footprint at every shift, from an integral image
        Si = cv2.integral(x.astype(np.float64))
        return Si[T0:T0 + ny, T1:T1 + nx] - Si[:ny, T1:T1 + nx] - Si[T0:T0 + ny, :nx] + Si[:ny, :nx]

    S, SI, SI2 = box(w), box(wi), box(wi * win)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = A - B * SI / S
        vt = C - B * B / S
        vi = SI2 - SI * SI / S
        den = np.sqrt(np.maximum(vt, 0.0) * np.maximum(vi, 0.0))
        out = np.where((S > 0) & (den > 0), cov / den, np.nan)
    return out.astype(np.float32)


def _outside_fraction(t, r0, r1, c0, c1) -> float:
    """Fraction of a template's signal (sum of |t|) outside rows r0:r1, cols c0:c1."""
    a = np.abs(t)
    tot = float(a.sum())
    return 1.0 - float(a[r0:r1, c0:c1].sum()) / tot if tot > 0 else 0.0


def _match_one(padded, pad, r, c, tmpl, calib: Calibration, m: int, z_points, cm_drop, coarse: int = 0,
               masked: bool = False, fine_margin: int | None = None, common: bool | None = None, weight=None,
               pages=None):
    """Best template, z, sub-pixel x, y and Cm of the particle image near frame pixel (r, c).

    ``masked``: for an image cut by the frame edge, correlate only the
    template pixels inside the frame (slower; see :func:`_masked_ncc`).
    ``common`` (default ``_COMMON_WINDOW``): the pages within 2 of the best
    are correlated again, each cropped to the smallest of their sizes, so
    that Cm(z) compares them on one window.

    ``weight``: (N, b, noise), N an array the shape of ``padded`` (the
    summed |model| of the neighbours): the correlations are weighted by
    1 / (1 + (b N / noise)^2) (:func:`_weighted_ncc`).

    ``pages``: (lo, hi), match only against pages lo..hi-1 (a seed of
    :func:`_split` on one side of a merged match's height).

    Returns a dict with ``x_px``, ``y_px``, ``z``, ``cm``, ``page`` and the
    placement of the best template in ``padded`` (``top``, ``left`` integer
    corner, ``di``, ``dj`` sub-pixel shift).
    """
    import cv2

    K = len(tmpl)
    plo, phi = (0, K) if pages is None else (max(int(pages[0]), 0), min(int(pages[1]), K))
    n = 2 * m + 1
    if common is None:
        common = _COMMON_WINDOW
    if fine_margin is None and int(calib.info.get("n_sub", 1)) > 1:
        fine_margin = 2         # interpolated templates: near the recorded page's best shift (see locate_3d)
        coarse = max(int(coarse or 0), int(calib.info["n_sub"]))
    Hf, Wf = padded.shape[0] - 2 * pad, padded.shape[1] - 2 * pad
    # centres within 1 px of the frame (the padding holds the windows of those)
    # (Python floats: round() of a NumPy scalar costs 3x as much; both round half to even)
    ri = int(round(min(max(float(r), -1.0), Hf))) + pad
    ci = int(round(min(max(float(c), -1.0), Wf))) + pad

    def corr(k, t=None):
        t = tmpl[k] if t is None else t
        T = t.shape[0]
        h = T // 2
        win = padded[ri - h - m: ri + h + m + 1, ci - h - m: ci + h + m + 1]
        # an image cut by the frame edge: correlate only the template pixels that stay inside the frame at every
        # shift tried (the zero padding is no measurement: counted, it pulls the match towards templates and
        # positions with less light there, i.e. a wrong z and a centre pulled inwards)
        r0, r1 = max(pad + m - (ri - h), 0), min(pad + Hf - m - (ri - h), T)
        c0, c1 = max(pad + m - (ci - h), 0), min(pad + Wf - m - (ci - h), T)
        if (masked and (r0 > 0 or c0 > 0 or r1 < T or c1 < T) and r1 > r0 and c1 > c0
                and (r1 - r0) * (c1 - c0) >= 0.25 * T * T and win.shape == (T + 2 * m, T + 2 * m)
                and _outside_fraction(t, r0, r1, c0, c1) > 0.05):    # (masked matching is slow: when it matters)
            return _masked_ncc(win, t, r0, r1, c0, c1)
        if weight is not None:
            return _weighted_ncc(win, wts(ri - h - m, ri + h + m + 1, ci - h - m, ci + h + m + 1), t)
        return ncc(win, t)

    def wts(a0, a1, b0, b1):
        N, b, noise = weight
        return 1.0 / (1.0 + (b / noise * N[a0:a1, b0:b1]) ** 2)

    def corr_near(k, i0, j0, mf, t=None):
        # the shifts within mf of (i0, j0) only (the fine stage: the position is known from the coarse one)
        t = tmpl[k] if t is None else t
        h = t.shape[0] // 2
        a0, a1 = max(i0 - mf, 0), min(i0 + mf, n - 1) + 1
        b0, b1 = max(j0 - mf, 0), min(j0 + mf, n - 1) + 1
        win = padded[ri - h - m + a0: ri + h - m + a1, ci - h - m + b0: ci + h - m + b1]
        out = np.full((n, n), -1.0, np.float32)
        if weight is not None:
            out[a0:a1, b0:b1] = _weighted_ncc(win, wts(ri - h - m + a0, ri + h - m + a1, ci - h - m + b0,
                                                       ci + h - m + b1), t)
        else:
            out[a0:a1, b0:b1] = ncc(win, t)
        return out

    # the plain correlations of many pages in one call (not for cut images or weighted matching, page by page)
    batch = weight is None and not masked and isinstance(tmpl, Templates)
    if batch and _MATCH_CORE and coarse and K > 4 * coarse and phi - plo > 2 * coarse:
        # the whole coarse-to-fine match in one numba call (_match_core: the same steps as below)
        stride = _SHIFT_STRIDE if _SHIFT_STRIDE > 1 and m >= 2 * _SHIFT_STRIDE else 1
        flat, offs, sizes = tmpl.packed
        zflat, tns = tmpl.zero_mean
        lflat, loffs = layouts_upto(tmpl, 2 * m)
        zc = calib.info.get("_z64")
        if zc is None or zc[0] is not calib.z:
            zc = calib.info["_z64"] = (calib.z, np.ascontiguousarray(calib.z, np.float64))
        k, cm, z, i, j, di, dj = _match_core(padded, ri, ci, m, flat, offs, sizes, zflat, tns, lflat, loffs, K, plo,
                                             phi, int(coarse), stride, -1 if fine_margin is None else int(fine_margin),
                                             bool(common), _COMMON_PAGES, zc[1],
                                             -1 if z_points is None else int(z_points), float(cm_drop),
                                             int(_COARSE_EVERY), float(_COARSE_DELTA))
        h = int(sizes[k]) // 2
        top, left = ri - h - m + i, ci - h - m + j
        return {"x_px": left - pad + dj + calib.centers[k, 1], "y_px": top - pad + di + calib.centers[k, 0],
                "z": z, "cm": min(cm, 1.0), "page": k, "top": int(top), "left": int(left), "di": di, "dj": dj}
    maps = np.full((K, n, n), -1.0, np.float32)
    if coarse and K > 4 * coarse and phi - plo > 2 * coarse:
        # coarse to fine: every ``coarse``-th page first, then every page within a coarse step + 1 of the best
        # (templates interpolated between recorded pages: at the +-2 shifts around the coarse stage's best only,
        # unless the image is cut by the frame edge and needs the masked correlation)
        first = np.arange(-(-plo // coarse) * coarse, phi, coarse)
        stride = _SHIFT_STRIDE if batch and _SHIFT_STRIDE > 1 and m >= 2 * _SHIFT_STRIDE else 1
        if stride > 1:
            # the coarse pages at every ``stride``-th shift only (1/stride^2 of the work; at +-4 px the coarse pages
            # were 3/4 of a match's correlations): best page by the sub-pixel peak height of those maps (a parabola
            # through samples ``stride`` px apart, so that a sharp peak between samples is not lost), then every
            # page within a coarse step + 1 of it, at every shift (or, interpolated templates, within
            # ``fine_margin`` of that page's best sample, and at least ``stride``); only those pages compete for the
            # best page (recorded pages at +-2 px of the best sample instead of every shift: diffusion3d
            # overlapping-image z RMSE 1.59 -> 2.62 %)
            nc = (2 * m) // stride + 1
            cmaps = np.empty((len(first), nc, nc), np.float32)
            pk = np.full(len(first), -np.inf)
            qs = _coarse_first(len(first), _COARSE_EVERY)
            for step_ in range(2):
                if step_:
                    qs = _coarse_fill(pk, _COARSE_EVERY, _COARSE_DELTA)
                if len(qs):
                    cmaps[qs] = ncc_pages_strided(padded, ri, ci, m, tmpl, first[qs], stride)
                    pk[qs] = _subpixel_peaks(cmaps[qs])
            q = int(np.argmax(pk))
            best = int(first[q])
            a, b = divmod(int(np.argmax(cmaps[q])), cmaps.shape[2])      # (divmod: np.unravel_index ~4 us)
            i0, j0 = a * stride, b * stride
            lo, hi = max(plo, best - coarse - 1), min(phi, best + coarse + 2)
            fw = m if fine_margin is None else max(stride, fine_margin)
            done = np.arange(lo, hi)
            maps[done] = ncc_pages(padded, ri, ci, m, tmpl, done, rows=(max(i0 - fw, 0), min(i0 + fw, n - 1) + 1),
                                   cols=(max(j0 - fw, 0), min(j0 + fw, n - 1) + 1))
        else:
            # (the coarse pages scored in two steps, as _match_core: _coarse_first, then _coarse_fill)
            sc = np.full(len(first), -np.inf)
            qs = _coarse_first(len(first), _COARSE_EVERY)
            for step_ in range(2):
                if step_:
                    qs = _coarse_fill(sc, _COARSE_EVERY, _COARSE_DELTA)
                if not len(qs):
                    continue
                if batch:
                    maps[first[qs]] = ncc_pages(padded, ri, ci, m, tmpl, first[qs])
                else:
                    for k in first[qs]:
                        maps[k] = corr(k)
                    np.copyto(maps, -1.0, where=np.isnan(maps))    # a constant window (padding) gives NaN (OpenCV)
                sc[qs] = maps[first[qs]].reshape(len(qs), -1).max(1)
            best = int(first[np.argmax(sc)])
            lo, hi = max(plo, best - coarse - 1), min(phi, best + coarse + 2)
            i0, j0 = divmod(int(np.argmax(maps[best])), n)
            near = fine_margin is not None and not masked and m > fine_margin
            ks = [k for k in range(lo, hi) if k % coarse]
            if batch and ks:
                rows = (max(i0 - fine_margin, 0), min(i0 + fine_margin, n - 1) + 1) if near else None
                cols = (max(j0 - fine_margin, 0), min(j0 + fine_margin, n - 1) + 1) if near else None
                maps[ks] = ncc_pages(padded, ri, ci, m, tmpl, ks, rows=rows, cols=cols)
            else:
                for k in ks:
                    maps[k] = corr_near(k, i0, j0, fine_margin) if near else corr(k)
                np.copyto(maps, -1.0, where=np.isnan(maps))
            # the pages correlated (sorted; np.union1d costs ~100 us a match)
            sel = np.zeros(K, bool)
            sel[first[sc != -np.inf]] = True
            sel[lo:hi] = True
            done = np.flatnonzero(sel)
    else:
        for k in range(plo, phi):
            maps[k] = corr(k)
        np.copyto(maps, -1.0, where=np.isnan(maps))    # a constant window (padding) gives NaN
        done = np.arange(plo, phi)
    peak = np.full(K, -1.0)
    peak[done] = _subpixel_peaks(maps[done])
    k = int(np.argmax(peak))
    cm = float(peak[k])
    z = None
    if common and not masked:
        # the pages around the best one compared on one window: each template cropped to the smallest of them.
        # Templates grow with defocus; compared each on its own window, a smaller one sees less of a neighbour's
        # light in a crowded frame, correlates better and pulls z towards focus (diffusion3d, images that
        # overlap another: z RMSE 3.25 -> 2.31 % of the depth; moving the window along while the best page lands
        # on its edge: 2.91 %)
        lo2, hi2 = max(plo, k - _COMMON_PAGES), min(phi, k + _COMMON_PAGES + 1)
        sizes = [tmpl[q].shape[0] for q in range(lo2, hi2)]
        Tc = min(sizes)
        if max(sizes) > Tc:
            i0, j0 = divmod(int(np.argmax(maps[k])), n)
            if batch:
                near2 = m > 2
                maps[lo2:hi2] = ncc_pages(padded, ri, ci, m, tmpl, np.arange(lo2, hi2), crop=Tc,
                                          rows=(max(i0 - 2, 0), min(i0 + 2, n - 1) + 1) if near2 else None,
                                          cols=(max(j0 - 2, 0), min(j0 + 2, n - 1) + 1) if near2 else None)
            else:
                for q in range(lo2, hi2):
                    t = tmpl[q]
                    o = (t.shape[0] - Tc) // 2
                    tc = t[o:o + Tc, o:o + Tc] if o else t
                    maps[q] = corr_near(q, i0, j0, min(2, m), tc) if m > 2 else corr(q, tc)
                np.copyto(maps, -1.0, where=np.isnan(maps))
            pk = _subpixel_peaks(maps[lo2:hi2])
            kk = int(np.argmax(pk))
            k, cm = lo2 + kk, float(pk[kk])
            z = _quadratic_peak(calib.z[lo2:hi2], pk, kk, z_points, cm_drop)
    if z is None:
        z = _quadratic_peak(calib.z, peak, k, z_points, cm_drop)
    mp = maps[k]
    i, j = divmod(int(np.argmax(mp)), n)
    di = dj = 0.0
    # float(): the parabola fallback gives a float32 scalar, which added to a Python int (i, j) would stay float32
    if 0 < i < mp.shape[0] - 1:
        di = float(_gauss3(mp[i - 1, j], mp[i, j], mp[i + 1, j]))
    if 0 < j < mp.shape[1] - 1:
        dj = float(_gauss3(mp[i, j - 1], mp[i, j], mp[i, j + 1]))
    h = tmpl[k].shape[0] // 2
    top, left = ri - h - m + i, ci - h - m + j       # template corner in padded coordinates
    return {"x_px": left - pad + dj + calib.centers[k, 1], "y_px": top - pad + di + calib.centers[k, 0],
            "z": z, "cm": min(cm, 1.0), "page": k, "top": int(top), "left": int(left), "di": float(di),
            "dj": float(dj)}


def _mass(padded, hit, tmpl):
    T = tmpl[hit["page"]].shape[0]
    sub = padded[hit["top"]:hit["top"] + T, hit["left"]:hit["left"] + T]
    return float(np.clip(sub, 0, None).sum())


def match_templates(img, rows, cols, calib: Calibration, margin: int = 4, cm_min: float = 0.5,
                    smooth: float = 1.5, z_points: int | None = None, cm_drop: float = 0.15):
    """z, refined x, y and Cm of particles near (rows, cols) by normalised cross-correlation.

    Each candidate is matched independently against the frame as it is (no
    removal of neighbouring images; :func:`locate_3d` does that).

    Parameters
    ----------
    img : 2D float32
        Background-subtracted frame (particles bright).
    rows, cols : array_like
        Approximate particle centres (px).
    calib : Calibration
    margin : int
        Search +- margin px around each centre.
    cm_min : float
        Drop matches with a lower correlation.
    z_points : int, optional
        Pages around the best one fitted by a parabola Cm(z); by default the
        widest window of up to 9 pages whose Cm stay within ``cm_drop`` of
        the best.
    cm_drop : float
        See ``z_points``.
    smooth : float
        Gaussian smoothing (px) of frame and templates before correlating
        (0: none). Defocused images spread their photons over many pixels;
        smoothing both sides raises Cm of dim images without moving the peak.

    Returns
    -------
    pandas.DataFrame
        ``x_px``, ``y_px`` (px), ``z`` (m), ``cm``, ``page`` (best template), ``mass``.
    """
    m = int(margin)
    padded, pad, tmpl = _prepare_matching(img, calib, smooth, m)
    out = {k: [] for k in ("x_px", "y_px", "z", "cm", "page", "mass")}
    for r, c in zip(np.asarray(rows, float), np.asarray(cols, float)):
        hit = _match_one(padded, pad, r, c, tmpl, calib, m, z_points, cm_drop)
        if hit["cm"] < cm_min:
            continue
        hit["mass"] = _mass(padded, hit, tmpl)
        for key in out:
            out[key].append(hit[key])
    df = pd.DataFrame(out)
    if len(df) > 1:
        # one particle found twice (ring split in pieces): keep the better correlation
        df = df.sort_values("cm", ascending=False).reset_index(drop=True)
        from scipy.spatial import cKDTree

        pairs = cKDTree(df[["x_px", "y_px"]].to_numpy()).query_pairs(2.0)
        drop = {max(a, b) for a, b in pairs}
        if drop:
            df = df.drop(index=sorted(drop)).reset_index(drop=True)
    return df


def _shifted(t, di, dj):
    """Template ``t`` moved by a sub-pixel (di, dj) (bilinear, zeros outside)."""
    import cv2

    if di == 0.0 and dj == 0.0:
        return t
    M = np.float32([[1, 0, dj], [0, 1, di]])
    return cv2.warpAffine(t, M, (t.shape[1], t.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0.0)


@njit(cache=True)
def _pairwise_leaf32(a, lo, n):
    # numpy's pairwise sum of a block of at most 128 float32s (8 accumulators)
    if n < 8:
        res = np.float32(0.0)
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum32(a, n):
    # numpy's pairwise summation of the float32 a[:n] (numpy/_core/src/umath/loops_utils.h.src: blocks of 128,
    # larger runs split at half rounded down to a multiple of 8, left + right): the same additions in the same
    # order, so the same float32 as ndarray.sum() of a contiguous float32 array. Its recursion by an explicit
    # stack (a cached self-recursive numba function crashes when loaded from the cache)
    los = np.empty(128, np.int64)
    ns = np.empty(128, np.int64)
    flags = np.empty(128, np.int64)
    vals = np.empty(128, np.float32)
    nv = 0
    los[0], ns[0], flags[0] = 0, n, 0
    top = 1
    while top > 0:
        top -= 1
        lo, m, fl = los[top], ns[top], flags[top]
        if m <= 128:
            vals[nv] = _pairwise_leaf32(a, lo, m)
            nv += 1
        elif fl == 1:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]     # left + right
            nv -= 1
        else:
            m2 = m // 2
            m2 -= m2 % 8
            los[top], ns[top], flags[top] = lo, m, 1            # combine after both halves
            los[top + 1], ns[top + 1], flags[top + 1] = lo + m2, m - m2, 0
            los[top + 2], ns[top + 2], flags[top + 2] = lo, m2, 0   # left first
            top += 3
    return vals[0]


@njit(cache=True)
def _model_sums(t, img, top, left):
    """(sum t^2, sum t w, sum max(t, 0)) of a float32 template ``t`` and the window ``w`` of ``img`` at (top, left),
    each in float32 exactly as NumPy sums the float32 products ``(t * t).sum()`` etc. (pairwise, C order)."""
    T0, T1 = t.shape
    n = T0 * T1
    tt = np.empty(n, np.float32)
    tw = np.empty(n, np.float32)
    tp = np.empty(n, np.float32)
    q = 0
    for i in range(T0):
        for j in range(T1):
            v = t[i, j]
            tt[q] = v * v
            tw[q] = v * img[top + i, left + j]
            tp[q] = v if (v >= 0 or v != v) else np.float32(0.0)       # np.maximum(v, 0.0): NaN kept
            q += 1
    z = np.float32(0.0)
    return z + _pairwise_sum32(tt, n), z + _pairwise_sum32(tw, n), z + _pairwise_sum32(tp, n)


class _Residual:
    """The smoothed, padded frame minus the template models of the particles accepted so far.

    The padding (outside the frame) stays 0: a model is fitted and removed
    only over the pixels inside the frame, so a particle cut by the edge is
    scaled by its visible part.
    """

    def __init__(self, padded, pad, tmpl, noise):
        self.noise = max(float(noise), 1e-6)
        self.img = padded
        self.pad = pad
        self.tmpl = tmpl
        self.inside = np.zeros(padded.shape, bool)
        self.inside[pad:padded.shape[0] - pad, pad:padded.shape[1] - pad] = True

    def model(self, hit, cap: float | None = None):
        """(slices, model image) of one hit, amplitude fitted by least squares to the current residual.

        ``cap``: largest amplitude subtracted. Two overlapping images matched
        as one are fitted about twice as bright as one particle; subtracting
        at most one particle's worth leaves the other's light in the residual,
        where a later round finds it.
        """
        t = _shifted(self.tmpl[hit["page"]], hit["di"], hit["dj"])
        T = t.shape[0]
        sl = (slice(hit["top"], hit["top"] + T), slice(hit["left"], hit["left"] + T))
        win = self.img[sl]
        Hp, Wp = self.img.shape
        p = self.pad
        inside = hit["top"] >= p and hit["left"] >= p and hit["top"] + T <= Hp - p and hit["left"] + T <= Wp - p
        # wholly inside the frame (most hits): no masked copy
        tt = t if inside else np.where(self.inside[sl], t, 0.0)
        if inside and _MODEL_SUMS and t.dtype == np.float32 and self.img.dtype == np.float32:
            # the three sums below in one numba pass (numpy's float32 pairwise sums, the same numbers)
            d32, n32, p32 = _model_sums(np.ascontiguousarray(t), self.img, int(hit["top"]), int(hit["left"]))
            den, num, tpos = float(d32), float(n32), float(p32)
        else:
            den, num, tpos = float((tt * tt).sum()), float((tt * win).sum()), float(np.maximum(t, 0.0).sum())
        a = max(num / den, 0.0) if den > 0 else 0.0
        hit["snr"] = a * math.sqrt(den) / self.noise
        hit["amp"] = a          # brightness relative to the calibration particle (whole image, also outside the frame)
        hit["mass"] = a * tpos  # whole image, also the part outside the frame
        if cap is not None and a > cap:
            a = cap
        return sl, (a * tt).astype(np.float32, copy=False)

    def _fast(self, sl, mod) -> bool:
        # a model window of model(): float32, C-contiguous, wholly inside the padded frame
        rs, cs = sl
        return (_WINDOW_ADD and mod.dtype == np.float32 and self.img.dtype == np.float32 and mod.ndim == 2
                and mod.flags.c_contiguous and rs.step is None and cs.step is None and 0 <= rs.start
                and 0 <= cs.start and rs.stop - rs.start == mod.shape[0] and cs.stop - cs.start == mod.shape[1]
                and rs.stop <= self.img.shape[0] and cs.stop <= self.img.shape[1])

    def subtract(self, sl, mod):
        if self._fast(sl, mod):
            _add_window(self.img, sl[0].start, sl[1].start, mod, True)
        else:
            self.img[sl] -= mod

    def add(self, sl, mod):
        if self._fast(sl, mod):
            _add_window(self.img, sl[0].start, sl[1].start, mod, False)
        else:
            self.img[sl] += mod


@njit(cache=True)
def _add_window(img, top, left, mod, neg):
    # img[top:top + T0, left:left + T1] -= mod (neg) or += mod, in place: the float32 differences / sums of NumPy's
    # in-place slice operation, element by element
    T0, T1 = mod.shape
    if neg:
        for i in range(T0):
            for j in range(T1):
                img[top + i, left + j] = img[top + i, left + j] - mod[i, j]
    else:
        for i in range(T0):
            for j in range(T1):
                img[top + i, left + j] = img[top + i, left + j] + mod[i, j]


def _candidates(padded, pad, tmpl, calib: Calibration, shape, mask, n_templates: int, c_min: float,
                exclude=None, exclude_r: float = 3.0, with_page: bool = False, spectra: dict | None = None):
    """Candidate centres (row, col) by correlating a few representative templates over the whole frame.

    The GDPTlab way: the frame is correlated with ``n_templates`` pages spread
    over the calibrated range; each map is shifted so that its value sits at
    the particle centre of its template; the maximum over templates is
    searched for local maxima (3 x 3) above ``c_min`` inside ``mask`` (pixels
    near signal). Returned in decreasing correlation.

    ``spectra``: a dict that receives the frame's :class:`FrameSpectrum` (``"fs"``) and the pages' whole-frame
    zero-mean correlations (``"C"``, by page; Templates only), for :func:`_snr_bound` on the same frame.
    """
    import cv2

    H, W = shape
    K = len(tmpl)
    pages = np.unique(np.round(np.linspace(0, K - 1, min(n_templates, K))).astype(int))
    cmap = np.full((H, W), -1.0, np.float32)
    which = np.zeros((H, W), np.int32)
    if isinstance(tmpl, Templates):
        # one forward FFT of the frame for all the templates (cached spectra), normalised from integral images;
        # correlations below c_min left out (no candidate there, and lower than any candidate they neighbour)
        fs = FrameSpectrum(padded)
        keep = None
        if spectra is not None:
            keep = spectra["C"] = {}
            spectra["fs"] = fs
        for k in pages:
            oy, ox = int(round(calib.centers[k, 0])), int(round(calib.centers[k, 1]))
            fs.ncc_max(tmpl, int(k), pad - oy, pad - ox, cmap, which, c_min, keep=keep, shared_var=_SHARED_VAR)
    else:
        for k in pages:
            t = tmpl[k]
            R = cv2.matchTemplate(padded, t, cv2.TM_CCOEFF_NORMED)
            oy, ox = int(round(calib.centers[k, 0])), int(round(calib.centers[k, 1]))
            R = np.nan_to_num(R[pad - oy: pad - oy + H, pad - ox: pad - ox + W], nan=-1.0)
            better = R > cmap
            which[better] = k
            np.maximum(cmap, R, out=cmap)
    local = cmap >= cv2.dilate(cmap, np.ones((3, 3), np.uint8))
    ok = local & mask & (cmap >= c_min)
    r, c = np.nonzero(ok)
    v = cmap[r, c]
    order = np.argsort(-v, kind="stable")
    r, c, v = r[order], c[order], v[order]
    if exclude is not None and len(exclude) and len(r):
        from scipy.spatial import cKDTree

        d, _ = cKDTree(exclude).query(np.column_stack([r, c]).astype(float))
        keep = d > exclude_r
        r, c, v = r[keep], c[keep], v[keep]
    if with_page:
        return r, c, v, which[r, c]
    return r, c, v


def _still_there(resimg, pad, tmpl, calib: Calibration, r, c, k, c_min: float, snr_min: float, noise: float) -> bool:
    """Whether a candidate found at the start of a round still has an image on the current residual.

    Later candidates of a round were found before the particles accepted
    since were subtracted: most of them were pieces of those images. One
    correlation with the representative template ``k`` that found it (at
    the found position, 3 x 3 shifts) and its least-squares amplitude
    decide, instead of a full match against every page.
    """
    if _STILL_CORE and isinstance(tmpl, Templates) and resimg.dtype == np.float32 and tmpl[k].dtype == np.float32:
        flat, offs, sizes = tmpl.packed
        zflat, tns = tmpl.zero_mean
        lflat, loffs = tmpl.layout(2)
        v = _still_core(resimg, int(pad), int(r), int(c), int(k), _center_px(calib), flat, offs, sizes, zflat, tns,
                        lflat, loffs, _template_dots(tmpl), float(c_min), float(snr_min), float(noise))
        if v < 2:
            return v == 1
    return _still_steps(resimg, pad, tmpl, calib, r, c, k, c_min, snr_min, noise)


def _center_px(calib: Calibration) -> np.ndarray:
    """(K, 2) int64: each page's particle centre inside its template rounded to a pixel (row, col), as
    ``int(round(calib.centers[k, i]))``; cached in ``calib.info``."""
    hit = calib.info.get("_center_px")
    if hit is None or hit[0] is not calib.centers:
        px = np.array([[int(round(float(y))), int(round(float(x)))] for y, x in calib.centers], np.int64).reshape(-1, 2)
        hit = calib.info["_center_px"] = (calib.centers, px)
    return hit[1]


def _template_dots(tmpl: Templates) -> np.ndarray:
    """Each template's sum of squares as :func:`_still_steps` forms it (``float(np.dot(t.ravel(), t.ravel()))``, a
    float32 BLAS dot); cached on ``tmpl``."""
    d = tmpl.__dict__.get("_still_dots")
    if d is None:
        d = tmpl.__dict__["_still_dots"] = np.array([float(np.dot(t.ravel(), t.ravel())) for t in tmpl], np.float64)
    return d


@njit(cache=True)
def _still_core(img, pad, r, c, k, cpx, flat, offs, sizes, zflat, tns, lflat, loffs, dens, c_min, snr_min, noise):
    # _still_steps' answer in one call: 1 yes, 0 no, 2 undecided (the caller then takes _still_steps). The same
    # correlations (ncc's direct kernels on the same window, the cached zero-mean template) and maximum (first in
    # row-major order). The amplitude there is a float32 BLAS dot in _still_steps, whose summation order is
    # unknown: here it is summed in double precision with its error bound, |fl(sum t w) - sum t w| <= gamma_n
    # sum |t w| (gamma_n = n u / (1 - n u), u = 2^-24, any order, with or without FMA), and the answer is given
    # only when every float32 sum within that bound gives it (the SNR is a non-decreasing function of that sum)
    T = sizes[k]
    top = r + pad - cpx[k, 0] - 1
    left = c + pad - cpx[k, 1] - 1
    if top < 0 or left < 0 or top + T + 2 > img.shape[0] or left + T + 2 > img.shape[1]:
        return 1
    wc = np.ascontiguousarray(img[top:top + T + 2, left:left + T + 2])
    R = _ncc_map(wc, _window_sums(wc, T, T), zflat[offs[k]:offs[k] + T * T].reshape((T, T)), tns[k], 1,
                 lflat[loffs[k]:loffs[k + 1]])
    bi, bj = 0, 0
    mx = R[0, 0]
    for i in range(3):
        for j in range(3):
            if R[i, j] > mx:
                mx, bi, bj = R[i, j], i, j
    if mx != mx:
        return 2
    if np.float64(mx) < c_min:
        return 0
    den = dens[k]
    if not (noise > 0.0) or not (den > 0.0):
        return 2
    t = flat[offs[k]:offs[k] + T * T]
    s = 0.0
    sa = 0.0
    for a in range(T):
        row = wc[bi + a]
        for b in range(T):
            p = np.float64(t[a * T + b]) * np.float64(row[bj + b])
            s += p
            sa += abs(p)
    n = T * T
    g = n * 2.0 ** -24
    e = (g / (1.0 - g)) * sa * 1.001 + 1e-300 if g < 0.5 else np.inf
    lo = s - e
    hi = s + e
    q = math.sqrt(den)
    if (lo / den) * q / noise >= snr_min:
        return 1
    if (hi / den) * q / noise < snr_min:
        return 0
    return 2


def _still_steps(resimg, pad, tmpl, calib: Calibration, r, c, k, c_min: float, snr_min: float, noise: float) -> bool:
    # _still_there step by step (NumPy; any templates)
    import cv2

    t = tmpl[k]
    T = t.shape[0]
    oy, ox = int(round(calib.centers[k, 0])), int(round(calib.centers[k, 1]))
    top, left = int(r) + pad - oy - 1, int(c) + pad - ox - 1
    if top < 0 or left < 0 or top + T + 2 > resimg.shape[0] or left + T + 2 > resimg.shape[1]:
        return True
    win = resimg[top:top + T + 2, left:left + T + 2]
    R = ncc(win, t)
    mx = float(R.max())
    if mx != mx:                        # a constant window (padding) gives NaN
        R = np.nan_to_num(R, nan=-1.0)
        mx = float(R.max())
    if mx < c_min:
        return False
    i, j = divmod(int(np.argmax(R)), 3)
    tv = t.ravel()
    den = float(np.dot(tv, tv))
    a = float(np.vdot(t, np.ascontiguousarray(win[i:i + T, j:j + T]))) / den if den > 0 else 0.0
    return a * math.sqrt(den) / noise >= snr_min


def _snr_bound(resimg, pad, tmpl, calib: Calibration, rr, cc, kk, noise: float, spectra: dict | None = None
               ) -> np.ndarray:
    """Per candidate, an upper bound of the amplitude SNR :func:`_still_there` would find on ``resimg`` as it is.

    That SNR is the least-squares amplitude of template ``k`` at one of the
    3 x 3 shifts about the candidate, times sqrt(sum t^2) / noise: at most the
    largest (sum t w) / (sqrt(sum t^2) noise) over the 3 x 3 shifts, read here
    from one whole-frame correlation per representative template (instead of
    one small correlation per candidate: a later round on a 512^2 frame of 20
    bright, large images meets ~700 candidates, nearly all leftovers).
    Candidates whose window leaves the padded frame get +inf (never skipped).

    ``spectra``: :func:`_candidates`' correlations of this same ``resimg`` (its ``spectra`` dict): with
    ``_BOUND_FFT``, sum t w = (zero-mean t's correlation) + mean(t) (window sum) from those instead of an OpenCV
    correlation per page (float64 FFT and integral image: as close to the exact sum as OpenCV's float32 one;
    a bound used with a 10 % margin).
    """
    import cv2

    out = np.full(len(rr), np.inf)
    Hp, Wp = resimg.shape
    pages = np.unique(kk)
    fft = (_BOUND_FFT and spectra is not None and "C" in spectra and spectra["fs"].img.shape == resimg.shape
           and all(int(k) in spectra["C"] for k in pages))
    if fft:
        S, _ = spectra["fs"].integral
    for k in pages:
        sel = np.nonzero(kk == k)[0]
        t = tmpl[k]
        T = t.shape[0]
        t64 = t.astype(np.float64)
        den = float((t64 ** 2).sum())
        if den <= 0:
            continue
        oy, ox = int(round(calib.centers[k, 0])), int(round(calib.centers[k, 1]))
        top = rr[sel] + pad - oy - 1
        left = cc[sel] + pad - ox - 1
        ok = (top >= 0) & (left >= 0) & (top + T + 2 <= Hp) & (left + T + 2 <= Wp)
        if not ok.any():
            continue
        tp, lf = top[ok], left[ok]
        if fft:
            # sum t w at corner (y, x): the zero-mean template's correlation plus mean(t) x the window sum
            C = spectra["C"][int(k)]
            tmean = float(t64.mean())

            def tw(y, x):
                return C[y, x] + tmean * (S[y + T, x + T] - S[y, x + T] - S[y + T, x] + S[y, x])
        else:
            R = cv2.matchTemplate(resimg, t, cv2.TM_CCORR)          # R[top, left] = sum t * window

            def tw(y, x):
                return R[y, x]
        best = np.full(len(tp), -np.inf)
        for a in range(3):
            for b in range(3):
                best = np.maximum(best, tw(tp + a, lf + b))
        out[sel[ok]] = best / (math.sqrt(den) * noise)
    return out


def _touches(hit, tmpl, slices) -> bool:
    """Whether the 3 x 3-shift window of ``hit``'s template (its ``page``, ``top``, ``left``) meets any of the
    (row slice, col slice) windows."""
    T = tmpl[hit["page"]].shape[0]
    r0, c0 = hit["top"] - 1, hit["left"] - 1
    for rs, cs in slices:
        if rs.start < r0 + T + 2 and r0 < rs.stop and cs.start < c0 + T + 2 and c0 < cs.stop:
            return True
    return False


# maps of up to this many shifts in _best_in_window by the direct sum (with its large templates, 2x faster than
# OpenCV's up to 15 x 15 shifts, about even to 20 x 20, slower beyond)
_WINDOW_DIRECT_MAX = 225


def _best_in_window(resimg, pad, tmpl, calib: Calibration, r0, r1, c0, c1, n_templates: int,
                    n_peaks: int = 0, sep: float = 4.0):
    """(row, col, correlation) of the best candidate centre inside frame rows r0..r1, cols c0..c1 of the residual,
    from the maximum over ``n_templates`` representative templates (as :func:`_candidates`, on a crop).

    ``n_peaks`` > 0: instead a list of up to that many (row, col, correlation) local maxima of that map, best
    first, each more than ``sep`` px from the better ones (the seeds of a joint fit, see :func:`_split`).
    """
    import cv2

    K = len(tmpl)
    lean = _WINDOW_LEAN and isinstance(tmpl, Templates)
    if lean:
        cache = tmpl.__dict__.setdefault("_window_pages", {})       # (string attribute keys only: dir() sorts them)
        pages = cache.get((int(n_templates), K))
        if pages is None:
            pages = cache[(int(n_templates), K)] = [
                int(k) for k in np.unique(np.round(np.linspace(0, K - 1, min(n_templates, K))).astype(int))]
        cpx = _center_px(calib)
    else:
        pages = np.unique(np.round(np.linspace(0, K - 1, min(n_templates, K))).astype(int))
    best = (None, None, -2.0)
    Hp, Wp = resimg.shape
    # centres inside the frame only (a matching window around them stays inside the padding)
    r0, r1 = max(int(r0), 0), min(int(r1), Hp - 2 * pad - 1)
    c0, c1 = max(int(c0), 0), min(int(c1), Wp - 2 * pad - 1)
    cmap = np.full((max(r1 - r0 + 1, 1), max(c1 - c0 + 1, 1)), -2.0, np.float32) if n_peaks else None
    for k in pages:
        t = tmpl[k]
        T = t.shape[0]
        if lean:
            oy, ox = int(cpx[k, 0]), int(cpx[k, 1])
        else:
            oy, ox = int(round(calib.centers[k, 0])), int(round(calib.centers[k, 1]))
        # template corners whose centre falls in the window
        tr0, tr1 = max(r0 + pad - oy, 0), min(r1 + pad - oy, Hp - T)
        tc0, tc1 = max(c0 + pad - ox, 0), min(c1 + pad - ox, Wp - T)
        if tr1 < tr0 or tc1 < tc0:
            continue
        if (tr1 - tr0 + 1) * (tc1 - tc0 + 1) <= _WINDOW_DIRECT_MAX:
            R = ncc(resimg[tr0:tr1 + T, tc0:tc1 + T], t, _WINDOW_DIRECT_MAX)     # never NaN
        else:
            R = cv2.matchTemplate(resimg[tr0:tr1 + T, tc0:tc1 + T], t, cv2.TM_CCOEFF_NORMED)
            if not np.isfinite(R).all():        # a constant window (padding) gives NaN
                R = np.nan_to_num(R, nan=-1.0)
        if cmap is not None:
            a, b = tr0 + oy - pad - r0, tc0 + ox - pad - c0          # R[0, 0] is the centre (a, b) of cmap
            sub = cmap[a:a + R.shape[0], b:b + R.shape[1]]
            np.maximum(sub, R[:sub.shape[0], :sub.shape[1]], out=sub)
            continue
        if lean:
            i, j = divmod(int(np.argmax(R)), R.shape[1])
        else:
            i, j = np.unravel_index(int(np.argmax(R)), R.shape)
        if R[i, j] > best[2]:
            best = (tr0 + i + oy - pad, tc0 + j + ox - pad, float(R[i, j]))
    if cmap is None:
        return best
    local = (cmap >= cv2.dilate(cmap, np.ones((3, 3), np.uint8))) & (cmap > -1.0)
    ii, jj = np.nonzero(local)
    order = np.argsort(-cmap[ii, jj], kind="stable")
    out = []
    for i, j in zip(ii[order], jj[order]):
        if all(math.hypot(i + r0 - p[0], j + c0 - p[1]) > sep for p in out):
            out.append((int(i + r0), int(j + c0), float(cmap[i, j])))
            if len(out) == n_peaks:
                break
    return out


def _window_rss(res, slices):
    """Sum of squared residuals over the union of the given (row slice, col slice) windows, inside the frame."""
    r0 = min(s[0].start for s in slices)
    r1 = max(s[0].stop for s in slices)
    c0 = min(s[1].start for s in slices)
    c1 = max(s[1].stop for s in slices)
    w = res.img[r0:r1, c0:c1]
    return float((w[res.inside[r0:r1, c0:c1]] ** 2).sum())


def _joint_place(res, pad, tmpl, calib: Calibration, parts, pm, j: int, m: int, coarse: int):
    """Where part ``j`` of a split sits in a joint least-squares fit of all the parts' templates.

    The window is fitted as the sum of every part's template with free
    amplitudes (linear least squares; the other parts kept at their page and
    sub-pixel position, part ``j`` tried at every page, coarse to fine, and
    every integer shift within ``m`` px of its centre). Re-matching a part by
    its normalised correlation on the residual, with the others' models
    subtracted at their own (single-image) amplitudes, can stay at a
    compromise: a neighbour's model that took some of this part's light
    leaves it too little to move to (diffusion3d frame 70: two images 2.8 px
    apart at z = -1.65 and +1.0 um, the fainter one held 3.5 px off). With
    the amplitudes fitted jointly the light is shared as the templates say.

    Parameters
    ----------
    res : _Residual
        The residual with part ``j``'s model added back, the others' (``pm``) subtracted.
    parts, pm : lists
        The parts (hits) and their (slices, model) as subtracted.
    j : int
    m : int
        Shift range (px).
    coarse : int
        Page step of the first stage (0: every page).

    Returns
    -------
    (row, col, page) or None
        The centre (frame px, integer shift from the current one) and page of
        the best fit with positive amplitudes; None if no window fits (edge).
    """
    import cv2

    Hp, Wp = res.img.shape
    P = parts[j]
    yc = P["y_px"] + pad
    xc = P["x_px"] + pad
    K = len(tmpl)
    corner = np.rint(np.column_stack([yc - calib.centers[:, 0], xc - calib.centers[:, 1]])).astype(int) - m
    sides = np.array([t.shape[0] for t in tmpl]) + 2 * m
    others = [i for i in range(len(parts)) if i != j]
    rows = [corner[:, 0].min(), (corner[:, 0] + sides).max()]
    cols = [corner[:, 1].min(), (corner[:, 1] + sides).max()]
    for i in others:
        rows = [min(rows[0], pm[i][0][0].start), max(rows[1], pm[i][0][0].stop)]
        cols = [min(cols[0], pm[i][0][1].start), max(cols[1], pm[i][0][1].stop)]
    R0, R1 = max(rows[0], 0), min(rows[1], Hp)
    C0, C1 = max(cols[0], 0), min(cols[1], Wp)
    ins = res.inside[R0:R1, C0:C1]
    # the data the parts explain: the residual with the others' models put back; the others as unit templates
    W = res.img[R0:R1, C0:C1].copy()
    O = []
    for i in others:
        (rs, cs), mod = pm[i]
        W[rs.start - R0:rs.stop - R0, cs.start - C0:cs.stop - C0] += mod
        h = parts[i]
        t = _shifted(tmpl[h["page"]], h["di"], h["dj"])
        o = np.zeros(W.shape, np.float32)
        o[rs.start - R0:rs.stop - R0, cs.start - C0:cs.stop - C0] = t
        O.append(np.where(ins, o, 0.0).astype(np.float32))
    Mk = ins.astype(np.float32)
    G = np.array([[float((a * b).sum()) for b in O] for a in O])
    bo = np.array([float((a * W).sum()) for a in O])
    try:
        Gi = np.linalg.inv(G)
    except np.linalg.LinAlgError:
        return None
    u = Gi @ bo                                 # the others' amplitudes without part j

    def score(k):
        t = tmpl[k]
        a0, b0 = corner[k, 0] - R0, corner[k, 1] - C0
        S = sides[k]
        if a0 < 0 or b0 < 0 or a0 + S > W.shape[0] or b0 + S > W.shape[1]:
            return None
        sub = (slice(a0, a0 + S), slice(b0, b0 + S))
        bj = cv2.matchTemplate(W[sub], t, cv2.TM_CCORR).astype(np.float64)
        tt = cv2.matchTemplate(Mk[sub], t * t, cv2.TM_CCORR).astype(np.float64)
        c = np.stack([cv2.matchTemplate(o[sub], t, cv2.TM_CCORR).astype(np.float64) for o in O], -1)
        # Schur complement of the others' Gram matrix: part j's amplitude and its reduction of the RSS
        num = bj - c @ u
        den = tt - np.einsum("...i,ij,...j->...", c, Gi, c)
        with np.errstate(invalid="ignore", divide="ignore"):
            aj = np.where(den > 0, num / den, -1.0)
            ao = u - aj[..., None] * (c @ Gi)
            q = np.where((aj > 0) & (ao > 0).all(-1), num * num / den, -np.inf)
        return q

    step = max(int(coarse or 1), 1)
    best = (-np.inf, None, None)

    def run(ks):
        nonlocal best
        for k in ks:
            q = score(k)
            if q is None:
                continue
            i = int(np.argmax(q))
            if q.flat[i] > best[0]:
                best = (float(q.flat[i]), int(k), divmod(i, q.shape[1]))

    run(range(0, K, step))
    if best[1] is None:
        return None
    if step > 1:
        k0 = best[1]
        run([k for k in range(max(0, k0 - step + 1), min(K, k0 + step)) if k % step])
    k = best[1]
    si, sj = best[2]
    return (corner[k, 0] + si + calib.centers[k, 0] - pad, corner[k, 1] + sj + calib.centers[k, 1] - pad, k)


def _unmoved(a, b, tol=None) -> bool:
    """Whether a re-match ``a`` of hit ``b`` left it where it was: the same page and, with ``tol`` (px; default
    ``_SWEEP_TOL``) None, the same placement exactly, else x and y within ``tol``."""
    tol = _SWEEP_TOL if tol is None else tol
    if tol is None or tol < 0:
        return all(a[key] == b[key] for key in ("page", "top", "left", "di", "dj"))
    return a["page"] == b["page"] and abs(a["x_px"] - b["x_px"]) <= tol and abs(a["y_px"] - b["y_px"]) <= tol


def _split(res, pad, tmpl, calib, hit, model, cap, n_parts, m, z_points, cm_drop, coarse, n_templates, gain,
           part_ok):
    """Fit one (over-bright or badly explained) match as ``n_parts`` particles of capped brightness.

    The match's model is taken out of the residual; the first part starts at
    the match, each further one at the best representative-template
    correlation inside the match's window on what is left; then each part is
    re-matched with the others subtracted (3 sweeps). Accepted (models
    subtracted, returned) when the residual sum of squares over the window
    drops by more than ``gain`` noise variances against the single match with
    a free amplitude, the parts are more than 1 px apart and each passes
    ``part_ok``. A second attempt starts from the second part found (the
    merged match sits at a compromise between the images, and the first part
    can stay stuck there); of the accepted attempts the one with the lower
    residual is kept. If neither is accepted the residual is left as it was
    and (None, None) is returned.
    """
    joint = _JOINT_FIT and not calib.info.get("signed", False)
    res.add(*model)
    single = dict(hit)
    sl_s, mod_s = res.model(single)
    T = tmpl[hit["page"]].shape[0]
    r0, c0 = hit["top"] - pad, hit["left"] - pad

    def attempt(seeds):
        """Parts grown from ``seeds`` (the first parts), swept; returns (parts, models), models subtracted."""
        parts, pm = list(seeds), [res.model(sd, cap(sd)) for sd in seeds]
        for p_ in pm:
            res.subtract(*p_)
        for _ in range(len(parts), n_parts):
            r, c, _v = _best_in_window(res.img, pad, tmpl, calib, r0, r0 + T - 1, c0, c0 + T - 1, n_templates)
            if r is None:
                break
            hj = _match_one(res.img, pad, r, c, tmpl, calib, m, z_points, cm_drop, coarse)
            pm.append(res.model(hj, cap(hj)))
            res.subtract(*pm[-1])
            parts.append(hj)
        sweep(parts, pm)
        bad = [j for j, p_ in enumerate(parts) if not part_ok(p_)]
        if bad and len(parts) - len(bad) >= 2:
            # a part that fails its checks (a third part grown on the leftovers of two images): dropped, its light
            # given back, and the others swept again (diffusion3d: pairs of a 3-part attempt were lost with it)
            for j in bad:
                res.add(*pm[j])
            parts = [p_ for j, p_ in enumerate(parts) if j not in bad]
            pm = [p_ for j, p_ in enumerate(pm) if j not in bad]
            sweep(parts, pm)
        if joint and len(parts) >= 2 and not (accepted(parts, pm) and _JOINT_RESCUE):
            sweep(parts, pm, True, _JOINT_SWEEPS)
        return parts, pm

    def accepted(parts, pm):
        """Whether the parts (models subtracted) pass the split's tests against the single match."""
        union = [sl_s] + [p[0] for p in pm]
        rss_n = _window_rss(res, union)
        for p in pm:
            res.add(*p)
        res.subtract(sl_s, mod_s)
        rss_1 = _window_rss(res, union)
        res.add(sl_s, mod_s)
        for p in pm:
            res.subtract(*p)
        close = any(math.hypot(a["x_px"] - b["x_px"], a["y_px"] - b["y_px"]) < 1.0
                    for i, a in enumerate(parts) for b in parts[i + 1:])
        return (len(parts) >= 2 and not close and rss_1 - rss_n >= gain * res.noise ** 2
                and all(map(part_ok, parts)))

    def sweep(parts, pm, by_joint=False, n_sweeps=3):
        """Each part re-matched with the others subtracted (at most ``n_sweeps`` sweeps; in place); ``by_joint``:
        each matched (+-1 px) where :func:`_joint_place` puts it."""
        for it in range(n_sweeps):
            same = True
            for j in range(len(parts)):
                res.add(*pm[j])
                y, x, mj, pg = parts[j]["y_px"], parts[j]["x_px"], m if it == 0 else min(m, _SWEEP_MARGIN), None
                if by_joint:
                    jp = _joint_place(res, pad, tmpl, calib, parts, pm, j, m, coarse)
                    if jp is not None:
                        # matched where the joint fit puts it: +-1 px, pages within a coarse step + 1 of its page
                        y, x, mj = jp[0], jp[1], 1
                        g = max(int(coarse or 0), 2) + 1
                        pg = (jp[2] - g, jp[2] + g + 1)
                hj = _match_one(res.img, pad, y, x, tmpl, calib, mj, z_points, cm_drop, coarse, pages=pg)
                pm[j] = res.model(hj, cap(hj))
                res.subtract(*pm[j])
                same &= _unmoved(hj, parts[j])
                parts[j] = hj
            if same:
                break       # a sweep that changed no part: the next one would see the same residual

    seeds = [[dict(hit)], None]
    # not in brightfield: a defocused ring correlates with itself at offsets of its radius, so the window's side
    # maxima there are ring lobes, not second particles (seeded there, the shipped epd_brightfield drift moved
    # -5.09 -> -5.02 um/s against the rendered -5.26, 0.8 -> 1.1 SE)
    pair = _PAIR_SEEDS and n_parts >= 2 and not calib.info.get("signed", False)

    def pair_seeds():
        # two images 10-16 px apart at opposite heights are matched as one image between them, and growing the parts
        # from that compromise leaves the second one too little light to be found: seed the parts instead at the
        # best local maxima of the window's correlation map (on the window with the merged model put back), each
        # matched on that window (both images still in it; its shift search keeps it near its own maximum)
        pk = _best_in_window(res.img, pad, tmpl, calib, r0, r0 + T - 1, c0, c0 + T - 1, n_templates,
                             n_peaks=n_parts, sep=_PAIR_SEP)
        if len(pk) < 2:
            return None
        return [_match_one(res.img, pad, r, c, tmpl, calib, m, z_points, cm_drop, coarse) for r, c, _v in pk]

    if pair:
        seeds.append("pair" if _PAIR_LAST else pair_seeds())
    best = None
    for _try, seed in enumerate(seeds):
        if isinstance(seed, str):
            # the seeded attempt only when growing found no split: it exists for the pair that growing misses.
            # Where a grown attempt was accepted the seeded one won 1 of 30 splits of bench_gdpt's random frames
            # and 3 of 90 of diffusion3d's (not told apart by the seeds' distance to the accepted parts; diffusion3d
            # recall 0.9550 -> 0.9537 without those; _PAIR_LAST = False runs it always). The window is as at the
            # start (every attempt gives its light back)
            if best is not None:
                break
            seed = pair_seeds()
        if seed is None:
            continue
        parts, pm = attempt(seed)
        union = [sl_s] + [p[0] for p in pm]
        rss_n = _window_rss(res, union)
        for p in pm:
            res.add(*p)
        res.subtract(sl_s, mod_s)
        rss_1 = _window_rss(res, union)
        res.add(sl_s, mod_s)
        close = any(math.hypot(a["x_px"] - b["x_px"], a["y_px"] - b["y_px"]) < 1.0
                    for i, a in enumerate(parts) for b in parts[i + 1:])
        if (len(parts) >= 2 and not close and rss_1 - rss_n >= gain * res.noise ** 2 and all(map(part_ok, parts))
                and (best is None or rss_n < best[0])):
            best = (rss_n, parts, pm)
        if _try == 0 and len(parts) >= 2:
            seeds[1] = [dict(parts[1])]
    if best is None:
        res.subtract(*model)
        return None, None
    for p in best[2]:
        res.subtract(*p)
    return best[1], best[2]


def _focus_page(calib: Calibration) -> int:
    """Page of the most compact template (smallest radius of gyration of |t| about the particle centre): the focus,
    which separates the branches of images above and below it. Cached per templates object in ``calib.info``."""
    hit = calib.info.get("_focus")
    if hit is not None and hit[0] is calib.templates:
        return hit[1]
    rg = np.empty(len(calib.templates))
    for k, t in enumerate(calib.templates):
        a = np.abs(np.asarray(t, np.float64))
        yy, xx = np.ogrid[:t.shape[0], :t.shape[1]]
        d2 = (yy - calib.centers[k, 0]) ** 2 + (xx - calib.centers[k, 1]) ** 2
        tot = a.sum()
        rg[k] = (a * d2).sum() / tot if tot > 0 else np.inf
    kf = int(np.argmin(rg))
    calib.info["_focus"] = (calib.templates, kf)
    return kf


def _flip_branches(res, pad, tmpl, calib: Calibration, hits, models, chis, cap, m, z_points, cm_drop, coarse, fm,
                   gain: float, hit_ok, chi_min: float, cm_max: float = 1.0, max_flip: int = 2) -> int:
    """Re-match badly explained overlapping images on the other side of focus, jointly with their neighbours.

    Above and below focus, a defocused image grows alike; an astigmatic one
    differs in the axis of its elongation, but an image that overlaps
    others, whose light its match shares, can match the wrong side better
    (diffusion3d frame 70: a particle at z = +2.1 um matched at -2.3 um 3.5 px
    off, on the light of a neighbour 16 px away, itself matched at +1.1
    instead of -1.6 um; each flipped alone explains the window worse, both
    together far better). So, per cluster of overlapping images (windows
    shrunk by ``_FLIP_SCALE``) that keep a chi^2 per pixel above ``chi_min``
    and a Cm below ``cm_max``, every overlapping subset of up to
    ``max_flip`` of them is matched only against the pages across focus
    (:func:`_focus_page`), then swept with every image overlapping it as in
    :func:`_split` (3 sweeps at most), the flipped ones kept on their new
    side. The cluster swept with nothing flipped is the reference: a flip
    is kept if it lowers the residual sum of squares by ``gain`` noise
    variances more than that sweep alone (and than any other flip), its
    images stay more than 2 px from every other one and each flipped one
    passes ``hit_ok``. Nothing is tried when the focus is within 3 pages of
    an end of the stack (one side only, as the shipped brightfield one).

    Parameters
    ----------
    res : _Residual
        All models subtracted.
    hits, models : lists
        Accepted hits and their (slices, model); changed in place.
    chis : sequence of float
        Each hit's window chi^2 per pixel relative to the frame's typical one.
    cap : callable
        Brightness cap of a hit's model (see :func:`locate_3d`).
    m : int
        Shift range (px) of the first re-match; later sweeps +-``_SWEEP_MARGIN``.

    Returns
    -------
    int
        Number of images whose height moved to the other side of focus.
    """
    import itertools

    K = len(tmpl)
    kf = _focus_page(calib)
    if kf < 3 or kf > K - 4:
        return 0            # focus at an end of the stack: one branch only
    sus = [i for i in range(len(hits))
           if chis[i] > chi_min and hits[i]["cm"] < cm_max and abs(hits[i]["page"] - kf) > 2]
    if not sus:
        return 0
    box = [dict(h, snr=1.0) for h in hits]

    def overlap(i, j):
        return _overlap_snr(box[i], [box[j]], tmpl, _FLIP_SCALE) > 0

    # clusters: connected groups of suspect images whose windows overlap
    left, groups = set(sus), []
    while left:
        g, todo = [], [left.pop()]
        while todo:
            i = todo.pop()
            g.append(i)
            near = [j for j in left if overlap(i, j)]
            left.difference_update(near)
            todo.extend(near)
        groups.append(sorted(g))
    n_flipped = 0
    for g in groups:
        if len(g) < 2 and not any(overlap(g[0], j) for j in range(len(hits)) if j != g[0]):
            continue        # alone: its match saw no neighbour's light
        best = (gain * res.noise ** 2, None)
        # the empty flip first: the group swept as it is, how much of any flip's gain the sweep alone would give
        for nf in range(0, min(max_flip, len(g)) + 1):
            for flip in itertools.combinations(g, nf):
                if nf > 1 and not all(any(overlap(a, b) for b in flip if b != a) for a in flip):
                    continue        # images whose windows do not meet: each decides alone
                side = {i: (kf + 1, K) if hits[i]["page"] < kf else (0, kf) for i in flip}
                # swept: the flipped images, then every image whose window meets theirs
                src = flip if nf else g
                cl = list(src) + [j for j in range(len(hits)) if j not in src and any(overlap(i, j) for i in src)]
                slices = [models[j][0] for j in cl]
                base = {j: (hits[j], models[j]) for j in cl}
                order = cl
                cur = dict(base)
                for it in range(3):
                    same = True
                    for j in order:
                        h0, mo = cur[j]
                        res.add(*mo)
                        hj = _match_one(res.img, pad, h0["y_px"], h0["x_px"], tmpl, calib,
                                        m if it == 0 else min(m, _SWEEP_MARGIN), z_points, cm_drop, coarse,
                                        fine_margin=fm, pages=side.get(j))
                        mj = res.model(hj, cap(hj))
                        res.subtract(*mj)
                        same &= _unmoved(hj, h0, _FLIP_SWEEP_TOL)
                        cur[j] = (hj, mj)
                    if same:
                        break
                # both configurations compared on one region: the windows of both
                union = slices + [cur[j][1][0] for j in cl]
                rss = _window_rss(res, union)
                for j in cl:         # back to the current configuration
                    res.add(*cur[j][1])
                    res.subtract(*base[j][1])
                # (pixels outside the union are the same in both: drops of different clusters compare)
                drop = _window_rss(res, union) - rss
                if not nf:
                    best = (max(drop, 0.0) + gain * res.noise ** 2, None)
                    continue
                pts = np.array([(cur[j][0]["y_px"], cur[j][0]["x_px"]) if j in cur else (h["y_px"], h["x_px"])
                                for j, h in enumerate(hits)])
                dd = np.hypot(pts[:, None, 0] - pts[None, :, 0], pts[:, None, 1] - pts[None, :, 1])
                np.fill_diagonal(dd, np.inf)
                if drop > best[0] and dd[cl].min() > 2.0 and all(hit_ok(cur[i][0]) for i in flip):
                    best = (drop, cur, flip, base)
        if best[1] is not None:
            for j in best[1]:
                res.add(*best[3][j][1])
                res.subtract(*best[1][j][1])
                hits[j], models[j] = best[1][j]
                box[j] = dict(hits[j], snr=1.0)
            n_flipped += len(best[2])
    return n_flipped


class _HitIndex:
    """The accepted hits' centres, template windows and SNRs as arrays, grown as hits are accepted: the distance
    to the nearest hit and :func:`_overlap_snr` without a Python loop over the hits (a 512^2 frame of 20 large
    images meets ~1000 candidates)."""

    def __init__(self, hits, tmpl):
        self.tmpl = tmpl
        self.n = 0
        self.a = np.zeros((max(2 * len(hits), 16), 6))     # y_px, x_px, window centre row, col, side, snr
        for h in hits:
            self.add(h)

    def add(self, h):
        if self.n == len(self.a):
            self.a = np.concatenate([self.a, np.zeros_like(self.a)])
        T = self.tmpl[h["page"]].shape[0]
        self.a[self.n] = (h["y_px"], h["x_px"], h["top"] + T / 2, h["left"] + T / 2, T, h["snr"])
        self.n += 1

    def prepare(self, rr, cc, tops=None, lefts=None, sides=None):
        """Precompute, for every candidate q (frame row rr[q], col cc[q]; with ``tops``, ``lefts``, ``sides`` its
        template window), the distance to the nearest hit held now and the overlap SNR against them, so that
        :meth:`nearest_q` and :meth:`overlap_q` only add the hits accepted since (the same values as
        :meth:`nearest` and :meth:`overlap_snr`: a min or max over all hits is that over both groups)."""
        self.n0 = self.n
        a = self.a[:self.n0]
        nq = len(rr)
        if self.n0:
            self.d0 = np.hypot(a[None, :, 0] - np.asarray(rr)[:, None], a[None, :, 1] - np.asarray(cc)[:, None]).min(1)
        else:
            self.d0 = np.full(nq, np.inf)
        self.ov0 = None
        if tops is not None:
            self.ov0 = np.zeros(nq)
            if self.n0:
                T = np.asarray(sides)[:, None]
                lim = 1.0 * (T + a[None, :, 4]) / 2
                ov = ((np.abs(a[None, :, 2] - np.asarray(tops)[:, None] - T / 2) < lim)
                      & (np.abs(a[None, :, 3] - np.asarray(lefts)[:, None] - T / 2) < lim))
                self.ov0 = np.maximum(np.where(ov, a[None, :, 5], -np.inf).max(1), 0.0)

    def nearest_q(self, q, y, x) -> float:
        """:meth:`nearest` of candidate q of :meth:`prepare` (at y, x)."""
        d = float(self.d0[q])
        if self.n > self.n0:
            a = self.a[self.n0:self.n]
            d = min(d, float(np.hypot(a[:, 0] - y, a[:, 1] - x).min()))
        return d

    def overlap_q(self, q, hit) -> float:
        """:meth:`overlap_snr` (scale 1) of candidate q of :meth:`prepare` (its window ``hit``)."""
        v = float(self.ov0[q])
        if self.n > self.n0:
            a = self.a[self.n0:self.n]
            T = self.tmpl[hit["page"]].shape[0]
            lim = 1.0 * (T + a[:, 4]) / 2
            ov = (np.abs(a[:, 2] - hit["top"] - T / 2) < lim) & (np.abs(a[:, 3] - hit["left"] - T / 2) < lim)
            if ov.any():
                v = max(v, float(max(a[ov, 5].max(), 0.0)))
        return v

    def nearest(self, y, x) -> float:
        a = self.a[:self.n]
        return float(np.hypot(a[:, 0] - y, a[:, 1] - x).min()) if self.n else float("inf")

    def overlap_snr(self, hit, scale: float = 1.0) -> float:
        """As :func:`_overlap_snr` (hit against all accepted ones)."""
        if not self.n:
            return 0.0
        a = self.a[:self.n]
        T = self.tmpl[hit["page"]].shape[0]
        lim = scale * (T + a[:, 4]) / 2
        ov = (np.abs(a[:, 2] - hit["top"] - T / 2) < lim) & (np.abs(a[:, 3] - hit["left"] - T / 2) < lim)
        return float(max(a[ov, 5].max(), 0.0)) if ov.any() else 0.0


def _overlap_snr(hit, hits, tmpl, scale: float = 1.0) -> float:
    """Largest amplitude SNR of the accepted particles whose template windows overlap ``hit``'s (0 if none).

    ``scale`` < 1 shrinks both windows about their centres first (1/1.2: the
    discs holding 95 % of the light, see :func:`build_calibration`).
    """
    best = 0.0
    T = tmpl[hit["page"]].shape[0]
    for h in hits:
        Th = tmpl[h["page"]].shape[0]
        if (abs(h["top"] + Th / 2 - hit["top"] - T / 2) < scale * (T + Th) / 2
                and abs(h["left"] + Th / 2 - hit["left"] - T / 2) < scale * (T + Th) / 2):
            best = max(best, h["snr"])
    return best


def _grow_mask(signal, rad: int) -> np.ndarray:
    """``cv2.dilate(signal, <elliptic element of side 2 rad + 1>) > 0`` (signal uint8 0 / 1); with ``_MASK_ROWS``
    by :func:`_dilate_rows` when every row of the element is one run centred on the anchor (OpenCV's ellipses)."""
    import cv2

    if _MASK_ROWS and signal.dtype == np.uint8 and signal.ndim == 2:
        half = _ellipse_rows(int(rad))
        if half is not None:
            out = np.empty(signal.shape, np.bool_)
            _dilate_rows(np.ascontiguousarray(signal), half, out)
            return out
    return cv2.dilate(signal, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))) > 0


_ELLIPSE_ROWS: dict = {}


def _ellipse_rows(rad: int):
    """Half-widths (int64, -1: empty row) of the rows of OpenCV's elliptic element of side 2 rad + 1, or None if a
    row is not one run centred on the anchor; cached per rad."""
    if rad not in _ELLIPSE_ROWS:
        import cv2

        kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
        half = np.full(len(kern), -1, np.int64)
        runs = True
        for i, row in enumerate(kern):
            nz = np.flatnonzero(row)
            if len(nz):
                runs &= bool(nz[-1] - nz[0] + 1 == len(nz) and nz[0] + nz[-1] == 2 * rad)
                half[i] = (nz[-1] - nz[0]) // 2
        _ELLIPSE_ROWS[rad] = half if runs else None
    return _ELLIPSE_ROWS[rad]


@njit(cache=True)
def _dilate_rows(src, half, out):
    # out[y, x] = any src[y + ky - R, x + dx] != 0 with |dx| <= half[ky] (half < 0: an empty kernel row), pixels
    # outside the frame not counted (OpenCV's dilation border): per kernel row, each frame row's distance to its
    # nearest nonzero pixel compared with the row's half-width
    H, W = src.shape
    R = (len(half) - 1) // 2
    big = W + 1
    dist = np.empty((H, W), np.int64)
    for y in range(H):
        d = big
        for x in range(W):
            d = 0 if src[y, x] != 0 else min(d + 1, big)
            dist[y, x] = d
        d = big
        for x in range(W - 1, -1, -1):
            d = 0 if src[y, x] != 0 else min(d + 1, big)
            if d < dist[y, x]:
                dist[y, x] = d
    for y in range(H):
        for x in range(W):
            out[y, x] = False
        for ky in range(len(half)):
            r = y + ky - R
            w = half[ky]
            if r < 0 or r >= H or w < 0:
                continue
            for x in range(W):
                if dist[r, x] <= w:
                    out[y, x] = True


def locate_3d(img, calib: Calibration, sigma: float = 2.0, snr: float = 6.0, margin: int = 4,
              cm_min: float = 0.5, min_area: int = 4, smooth: float = 1.5, n_templates: int = 7,
              c_candidate: float = 0.3, rounds: int = 2, refine: int = 4, z_points: int | None = None,
              cm_drop: float = 0.15, snr_fit: float = 40.0, snr_rel: float = 0.15,
              min_mass: float = 0.5, max_mass: float | None = 1.8, coarse: int = 4,
              amp_cap: float | None = 1.15, split_at: float | None = 1.3, split_gain: float = 100.0,
              split_chi2: float = 3.0, max_chi2: float | None = None, ghost_mass: float = 0.7,
              ghost_px: float = 6.0, merged_cm: float | None = 0.99, split_cm: float | None = 0.995,
              times: dict | None = None) -> pd.DataFrame:
    """Detect defocused particles in a background-subtracted frame and measure x, y, z, Cm.

    Built for realistic (crowded) frames, where defocused images overlap and
    are cut by the frame edge, and for brightfield (a calibration built with
    ``brightfield=True``: signed images, see :func:`prepare_gdpt`):

    1. Candidates: local maxima of the frame's correlation with
       ``n_templates`` representative templates (the GDPTlab way,
       :func:`_candidates`), above ``c_candidate`` and near pixels whose
       (brightfield: absolute) signal is above ``snr`` noise units after a
       ``sigma`` px blur or after a blur of 1/8 of the largest template
       (wide, faint defocused images; its noise is the frame's pixel noise
       carried through the blur).
    2. In decreasing order of that correlation, each candidate is matched
       against the templates (coarse to fine: every ``coarse``-th page, then
       every page near the best; sub-pixel x, y, parabolic z, Cm) on the
       *residual* frame, from which the template models of the particles
       already accepted were subtracted (amplitude by least squares over the
       pixels inside the frame). A ring-shaped or astigmatic image found at
       several points is explained by its first (best) match; two
       overlapping images are each matched with the other removed, so Cm
       keeps its meaning (the correlation of one particle's own image with
       its template). A candidate found before other particles were
       subtracted is first checked on the current residual (one correlation
       and amplitude) before a full match.
    3. Brightness cap: once the frame's typical particle brightness is known
       (median of the first round, 3 particles or more), at most ``amp_cap``
       times it is subtracted for any match, so the light of a second image
       hidden under a merged match stays in the residual.
    4. Split: a match brighter than ``split_at`` times the typical particle,
       or whose window is left with a residual chi^2 above ``split_chi2``
       times the frame's typical one, is refitted as 2-3 particles
       (:func:`_split`, its parts grown from the match or seeded at the
       window's best correlation maxima; kept when the window's residual sum
       of squares drops by more than ``split_gain`` noise variances). Matches with Cm of
       ``split_cm`` or more are not split (None: no such limit).
    5. ``refine`` passes re-match the accepted particles with all the others
       removed (only those next to a particle that changed; they stop when
       nothing moves); a particle that converges within 2 px of another is
       dropped (one image found twice). ``rounds`` repeats the candidate
       search on the residual (images hidden under brighter ones).
    6. Sides of focus: overlapping images whose windows stay badly
       explained (chi^2 above ``_FLIP_CHI2`` times the frame's typical one,
       Cm below ``_FLIP_CM``) are re-matched, alone and in overlapping
       pairs, against the pages across focus, with their neighbours swept;
       kept where the residual drops by ``split_gain`` noise variances more
       than a sweep alone gives (:func:`_flip_branches`).
    7. Checks against matches of what is left over: Cm is blind to
       amplitude, and the residue of an imperfectly subtracted image can
       correlate well with a small template. A match is kept only if its
       fitted amplitude is ``snr_fit`` times its standard error and
       ``snr_rel`` times that of any accepted image it overlaps, its
       brightness is at least ``min_mass`` times the frame's median (with 3
       or more particles), and it is not a faint (< ``ghost_mass``) match
       within ``ghost_px`` of a brighter one at the same height (a piece of
       an elongated image). Matches brighter than ``max_mass`` times the
       median (two images merged into one match, whose z is wrong) are
       dropped too, unless their Cm is at least ``merged_cm`` (two images at
       one height, nearly on top of each other: the merged match's z is
       right, and reporting it keeps the track; epd_brightfield's pair of
       particles 1-3 px apart was lost for 9 frames and its tracks broken);
       give ``max_mass=None`` (and ``split_at=None``) for
       samples with aggregates or very different particle brightnesses.
       ``max_chi2`` drops matches whose window stays badly explained.
    8. Images cut by the frame edge are matched once more on their visible
       part only (:func:`_masked_ncc`); particles whose centre lies more
       than 1 px outside the frame are not reported.

    ``times``: a dict to which the wall seconds of the stages are added
    (``mask``, ``candidates``, ``match``, ``split``, ``refine``, ``flip``, ``edge``;
    default ``calib.info["stage_times_s"]``, summed over the frames).

    Brightness: fluorescence, the fitted model's photons (``mass``);
    brightfield, the fitted amplitude relative to the calibration particle.

    Measured on ``data/synthetic/diffusion3d`` (28 particles, 160 x 160 px,
    images up to 65 px wide, most of them overlapping;
    ``bench/bench_pipeline.py --only B``): recall 0.84 -> 0.94, precision
    0.96 -> 0.97 with steps 3-7, median |dz| 54 nm (0.9 % of the 6 um
    depth), particles whose images overlap no other 1.1-1.3 % of the depth;
    the z RMSE of all (3 %) is set by a few particles in clusters of images
    less than ~1 um apart, matched at the wrong height.

    Returns
    -------
    pandas.DataFrame
        ``x_px``, ``y_px`` (px), ``z`` (m), ``cm``, ``page`` (best template),
        ``snr`` (amplitude / its standard error), ``mass`` (the fitted
        model's signal, smoothed ADU, including any part outside the
        frame), ``chi2`` (residual sum of squares per pixel of the particle's
        window after all models are subtracted, in units of the smoothed
        noise variance: about 1 when the frame is explained, high for a match
        at a compromise between overlapping images), ``edge`` (True when the
        best template's window leaves the frame: a cut image, matched and
        fitted on its visible part).
    """
    import time

    import cv2

    from .preprocess import median3, noise_sigma

    if times is None:
        times = calib.info.setdefault("stage_times_s", {})
    clock = [time.perf_counter()]

    def tick(stage):
        # wall seconds since the last tick added to the stage (for the pipeline's JSON summary)
        t = time.perf_counter()
        times[stage] = times.get(stage, 0.0) + t - clock[0]
        clock[0] = t

    img = np.ascontiguousarray(img, np.float32)
    H, W = img.shape
    m = int(margin)
    # templates interpolated between the recorded pages (n_sub per step): the coarse stage runs over the
    # recorded pages, the fine one over the interpolated ones near the best at +-2 px shifts only
    n_sub = int(calib.info.get("n_sub", 1))
    fm = 2 if n_sub > 1 else None
    if n_sub > 1 and coarse:
        coarse = max(int(coarse), n_sub)
    padded, pad, tmpl = _prepare_matching(img, calib, smooth, m)
    # brightfield (signed) calibrations: a defocused image has lobes darker and brighter than the field.
    # Two smoothing scales: ``sigma`` and one matched to the largest images (a wide, faint defocused ring is
    # below the threshold at 2 px: epd_brightfield's isolated particles above 9 um were not even candidates)
    med = median3(img)
    signal = np.zeros(img.shape, np.uint8)
    wide = max(float(sigma), _WIDE_MASK * calib.size)
    for sg in ((float(sigma), wide) if wide > 1.5 * sigma else (float(sigma),)):
        sm = cv2.GaussianBlur(med, (0, 0), sigmaX=sg)
        base = float(np.median(sm[::5, ::5]))
        # the wide scale: the frame's pixel noise carried through the smoothing (the spread of a heavily smoothed
        # crowded frame is its signal, not its noise)
        ns = noise_sigma(sm) if sg == sigma else min(noise_sigma(sm), _pixel_noise(img) * _smoothed_noise(sg))
        thr = snr * max(ns, 1e-6)
        signal |= ((np.abs(sm - base) if calib.info.get("signed") else sm - base) > thr).astype(np.uint8)
    if min_area > 1:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(signal, connectivity=8)
        small = np.nonzero(stats[:, cv2.CC_STAT_AREA] < min_area)[0]
        small = small[small > 0]
        if small.size:
            signal[np.isin(labels, small)] = 0
    if not signal.any():
        tick("mask")
        return pd.DataFrame({k: [] for k in ("x_px", "y_px", "z", "cm", "page", "snr", "mass", "chi2", "edge")})
    # a ring's dark centre is still a candidate: grow the signal mask by the largest image radius
    rad = max(3, int(0.5 * max(t.shape[0] for t in calib.templates) * 0.6))
    mask = _grow_mask(signal, rad)
    res = _Residual(padded, pad, tmpl, noise_sigma(padded[pad:pad + H, pad:pad + W]))
    hits, models = [], []
    # brightness: fluorescence, the fitted model's photons (conserved whatever z); brightfield, the fitted
    # amplitude relative to the calibration particle's image at the same height (the contrast changes with
    # defocus, so a sum over the image would not be comparable between heights)
    signed = bool(calib.info.get("signed"))
    bkey = "amp" if signed else "mass"
    if signed:
        per_amp = np.ones(len(tmpl))
    elif _PER_AMP_CACHE and isinstance(tmpl, Templates):
        per_amp = tmpl.__dict__.get("_per_amp")
        if per_amp is None:
            per_amp = tmpl.__dict__["_per_amp"] = np.array([float(np.clip(t, 0, None).sum()) for t in tmpl])
    else:
        per_amp = np.array([float(np.clip(t, 0, None).sum()) for t in tmpl])
    ref = [0.0]          # the frame's typical particle brightness, once known

    def cap(h):
        return amp_cap * ref[0] / per_amp[h["page"]] if (amp_cap and ref[0] > 0) else None

    def xy():
        return np.array([(h["y_px"], h["x_px"]) for h in hits], float).reshape(-1, 2)

    tick("mask")
    for rnd in range(max(1, int(rounds))):
        spectra = {} if rnd > 0 and hits else None     # (for _snr_bound on the same residual)
        rr, cc, _, kk = _candidates(res.img, pad, tmpl, calib, (H, W), mask, n_templates, c_candidate,
                                    exclude=xy() if hits else None, with_page=True, spectra=spectra)
        tick("candidates")
        new = 0
        n_at_start = len(hits)
        idx = _HitIndex(hits, tmpl)     # positions and windows of the hits, for the checks below (no loop over hits)
        bound = _snr_bound(res.img, pad, tmpl, calib, rr, cc, kk, res.noise, spectra) if rnd > 0 and hits else None
        touched = []                    # windows of the models subtracted in this round (the bound is stale there)
        if rnd > 0 and hits:
            c_tops = rr + pad - np.round(calib.centers[kk, 0]).astype(np.int64)
            c_lefts = cc + pad - np.round(calib.centers[kk, 1]).astype(np.int64)
            idx.prepare(rr, cc, c_tops, c_lefts, tmpl.packed[2][kk] if isinstance(tmpl, Templates)
                        else np.array([tmpl[k].shape[0] for k in kk], np.int64))
        else:
            idx.prepare(rr, cc)
        pre = None
        if _CAND_ARRAYS:
            # idx.nearest_q of every candidate, as hits are accepted; and the candidates that the bound check
            # below skips already at the round's starting overlaps (idx.ov0: lim only grows as hits are added)
            # unless a window subtracted since meets theirs (as _touches)
            dmin = idx.d0.copy()
            if bound is not None and idx.ov0 is not None:
                pre = bound < 0.9 * (0.5 * np.maximum(snr_fit, snr_rel * idx.ov0))
                c_sides = (tmpl.packed[2][kk] if isinstance(tmpl, Templates)
                           else np.array([tmpl[k].shape[0] for k in kk], np.int64))
                c_r0, c_c0 = c_tops - 1, c_lefts - 1
                touch = np.zeros(len(rr), bool)
        for q, (r, c, k0) in enumerate(zip(rr, cc, kk)):
            if _CAND_ARRAYS:
                if dmin[q] <= 3.0 or (pre is not None and pre[q] and not touch[q]):
                    continue
            elif hits and idx.nearest_q(q, r, c) <= 3.0:
                continue
            if rnd > 0 and hits:
                # later rounds search the residual, where the leftovers of bright particles' imperfect models
                # give dozens of candidates that the full match would reject (their amplitude is a small
                # fraction of the image they sit on): the cheap check first, at half the final thresholds
                # (a full-frame 512^2 frame of five 1e6-photon particles: 92 -> a few full matches). (Its
                # threshold is at least the one below, so that check is not repeated.)
                near = {"page": int(k0), "top": r + pad - int(round(calib.centers[k0, 0])),
                        "left": c + pad - int(round(calib.centers[k0, 1]))}
                lim = 0.5 * max(snr_fit, snr_rel * idx.overlap_q(q, near))
                if bound[q] < 0.9 * lim and not _touches(near, tmpl, touched):
                    continue        # _still_there would say no: its SNR is at most the bound, unchanged since
                if not _still_there(res.img, pad, tmpl, calib, r, c, k0, c_candidate, lim, res.noise):
                    continue
            elif len(hits) > n_at_start and not _still_there(res.img, pad, tmpl, calib, r, c, k0, c_candidate,
                                                             0.5 * snr_fit, res.noise):
                continue
            hit = _match_one(res.img, pad, r, c, tmpl, calib, m, z_points, cm_drop, coarse, fine_margin=fm)
            if hit["cm"] < cm_min:
                continue
            if hits and idx.nearest(hit["y_px"], hit["x_px"]) <= 2.0:
                continue
            sl, mod = res.model(hit, cap(hit))
            if hit["snr"] < max(snr_fit, snr_rel * idx.overlap_snr(hit)):
                continue
            res.subtract(sl, mod)
            hits.append(hit)
            idx.add(hit)
            touched.append(sl)
            models.append((sl, mod))
            new += 1
            if _CAND_ARRAYS:
                dmin = np.minimum(dmin, np.hypot(hit["y_px"] - rr, hit["x_px"] - cc))
                if pre is not None:
                    rs, cs = sl
                    touch |= ((rs.start < c_r0 + c_sides + 2) & (c_r0 < rs.stop)
                              & (cs.start < c_c0 + c_sides + 2) & (c_c0 < cs.stop))
        if rnd == 0 and amp_cap and len(hits) >= 3:
            # two overlapping images matched as one were fitted (and subtracted) about twice as bright as a
            # particle: subtract at most amp_cap x the typical brightness, so the other one's light stays in the
            # residual for the next round
            ref[0] = float(np.median([h[bkey] for h in hits]))
            for i, h in enumerate(hits):
                if h[bkey] > amp_cap * ref[0]:
                    res.add(*models[i])
                    models[i] = res.model(h, cap(h))
                    res.subtract(*models[i])
                    new += 1
        tick("match")
        if split_at:
            # images of 2-3 particles closer than their image size, matched as one brighter particle at a compromise
            # z (even with the amplitude cap, the residual keeps looking like the merged image): fit them as 2 or 3
            # particles of the typical brightness and keep the split if it explains the window far better.
            # Tried for matches brighter than split_at x the frame's typical particle or, in frames too sparse
            # to know it, whose window is left with a residual chi^2 per pixel above split_chi2
            n0 = len(hits)
            chis = [_window_rss(res, [mo[0]]) / max(int(res.inside[mo[0]].sum()), 1) / res.noise ** 2
                    for mo in models]
            # very bright images are never explained to the noise level (the templates are images too): chi2
            # relative to the frame's typical one when there are enough particles to tell
            chi_ref = max(1.0, float(np.median(chis))) if len(chis) >= 3 else 1.0
            for i in range(n0):
                h = hits[i]
                if h.get("split_tried"):
                    continue
                if split_cm is not None and h["cm"] >= split_cm:
                    # a match this good is one image explained by one template (or two images on top of each other
                    # at one height, whose merged z is right): a bright isolated near-focus image, whose residual
                    # is the template's own imperfection, was split for nothing (512^2, 20 particles: 8 attempts of
                    # ~14 matches each per frame, 72 % of all matches; diffusion3d: none of its 128 accepted splits)
                    continue
                chi2 = chis[i] / chi_ref
                if ref[0] > 0:
                    if h[bkey] < split_at * ref[0] and chi2 < split_chi2:
                        continue
                    n_parts = int(min(3, max(2, round(h[bkey] / ref[0]))))
                    part_cap = cap
                else:
                    if chi2 < split_chi2:
                        continue
                    n_parts = 2
                    b_part = h[bkey] / n_parts

                    def part_cap(p, b_part=b_part):
                        return amp_cap * b_part / per_amp[p["page"]] if amp_cap else None
                h["split_tried"] = True
                b_min = min_mass * (ref[0] if ref[0] > 0 else h[bkey] / n_parts)

                def part_ok(p, b_min=b_min):
                    return p["cm"] >= cm_min and p["snr"] >= snr_fit and p[bkey] >= b_min

                parts, pm = _split(res, pad, tmpl, calib, h, models[i], part_cap, n_parts, m, z_points, cm_drop,
                                   coarse, n_templates, split_gain, part_ok)
                if parts is None:
                    continue
                for p_ in parts:
                    p_["split_tried"] = True        # no split of a split: two halves of one elongated image
                hits[i], models[i] = parts[0], pm[0]
                hits.extend(parts[1:])
                new += len(parts) - 1
                models.extend(pm[1:])
        tick("split")
        if new == 0 and rnd > 0:
            break
        # which hits changed since their neighbours were last matched: new ones (no "settled" key) and those
        # whose re-match moved them; a pass re-matches only hits next to a changed one
        nb = None
        if _NEIGHBOUR_WEIGHT and refine:
            nb = np.zeros(res.img.shape, np.float32)       # summed |model| of the accepted particles
            for sl_, mod_ in models:
                nb[sl_] += np.abs(mod_)
        for _ in range(int(refine)):
            alive, moved, dropped = [], set(), False
            if _REFINE_LISTS:
                # (window centre row, col, side) of hits[j], kept as hits[j] is replaced: _overlap_snr's test
                geo = []
                for o in hits:
                    To = tmpl[o["page"]].shape[0]
                    geo.append((o["top"] + To / 2, o["left"] + To / 2, To))
            for i, h in enumerate(hits):
                if _REFINE_LISTS:
                    Th = tmpl[h["page"]].shape[0]
                    cy, cx = h["top"] + Th / 2, h["left"] + Th / 2
                    ovl = []
                    for j, (gy, gx, Tj) in enumerate(geo):
                        if j != i:
                            lim_ = _REFINE_SCALE * (Th + Tj) / 2
                            if abs(gy - cy) < lim_ and abs(gx - cx) < lim_:
                                ovl.append(j)
                    if not any(hits[j]["snr"] > 0 for j in ovl):
                        alive.append(i)     # alone (_overlap_snr(h, others) == 0)
                        h["settled"] = True
                        continue
                    if h.get("settled") and not any(not hits[j].get("settled") or id(hits[j]) in moved
                                                    for j in ovl):
                        alive.append(i)     # its neighbourhood did not change since its last re-match
                        continue
                else:
                    others = hits[:i] + hits[i + 1:]
                    if _overlap_snr(h, others, tmpl, _REFINE_SCALE) == 0:
                        alive.append(i)         # alone: its first match saw no neighbour, nothing to refine
                        h["settled"] = True
                        continue
                    if h.get("settled") and not any(not o.get("settled") or id(o) in moved
                                                    for o in others
                                                    if _overlap_snr(h, [dict(o, snr=1.0)], tmpl, _REFINE_SCALE) > 0):
                        alive.append(i)         # its neighbourhood did not change since its last re-match
                        continue
                res.add(*models[i])
                if nb is not None:
                    nb[models[i][0]] -= np.abs(models[i][1])
                h2 = _match_one(res.img, pad, h["y_px"], h["x_px"], tmpl, calib, min(m, 2), z_points, cm_drop, coarse,
                                fine_margin=fm, weight=None if nb is None else (nb, _NEIGHBOUR_WEIGHT, res.noise))
                if h2["cm"] >= h["cm"] - 0.02:
                    if (h2["page"] != h["page"] or abs(h2["x_px"] - h["x_px"]) > 0.1
                            or abs(h2["y_px"] - h["y_px"]) > 0.1):
                        moved.add(id(h2))
                    h = h2
                others = [hits[j] for j in alive] + hits[i + 1:]
                if _REFINE_LISTS:
                    # np.hypot(dy, dx) >= max(|dy|, |dx|): only hits within 2 px (+ 1e-9) in both axes can be
                    # within 2 px (NaN: the plain test)
                    y0, x0 = h["y_px"], h["x_px"]
                    close = False
                    for o in others:
                        dy, dx = o["y_px"] - y0, o["x_px"] - x0
                        if not (abs(dy) > 2.000000001 or abs(dx) > 2.000000001) and np.hypot(dy, dx) <= 2.0:
                            close = True
                            break
                    if not (y0 == y0 and x0 == x0) or any(o["y_px"] != o["y_px"] or o["x_px"] != o["x_px"]
                                                          for o in others):
                        close = bool(others) and min(np.hypot(o["y_px"] - h["y_px"], o["x_px"] - h["x_px"])
                                                     for o in others) <= 2.0
                else:
                    close = bool(others) and min(np.hypot(o["y_px"] - h["y_px"], o["x_px"] - h["x_px"])
                                                 for o in others) <= 2.0
                if close:
                    dropped = True
                    continue        # converged onto another particle: one image, found twice
                sl, mod = res.model(h, cap(h))
                res.subtract(sl, mod)
                if nb is not None:
                    nb[sl] += np.abs(mod)
                hits[i], models[i] = h, (sl, mod)
                alive.append(i)
                if _REFINE_LISTS:
                    Th = tmpl[h["page"]].shape[0]
                    geo[i] = (h["top"] + Th / 2, h["left"] + Th / 2, Th)
            hits = [hits[i] for i in alive]
            models = [models[i] for i in alive]
            for h in hits:
                h["settled"] = not dropped and id(h) not in moved
            if not moved and not dropped:
                break
        tick("refine")
        if new == 0:
            break
    if _FLIP and len(hits) >= 2:
        # overlapping images matched on the wrong side of focus (see _flip_branches), in units of the frame's
        # typical window chi^2 (bright images are never explained to the noise level)
        chis = [_window_rss(res, [mo[0]]) / max(int(res.inside[mo[0]].sum()), 1) / res.noise ** 2 for mo in models]
        chi_ref = max(1.0, float(np.median(chis))) if len(chis) >= 3 else 1.0

        def hit_ok(p):
            return p["cm"] >= cm_min and p["snr"] >= snr_fit and p[bkey] >= min_mass * ref[0]

        _flip_branches(res, pad, tmpl, calib, hits, models, [c / chi_ref for c in chis], cap, m, z_points, cm_drop,
                       coarse, fm, split_gain, hit_ok, _FLIP_CHI2, _FLIP_CM, _FLIP_MAX)
        tick("flip")
    # images cut by the frame edge (> 15 % of the template's signal outside): matched again with only their
    # visible part (the zero padding counted as "no light" pulls the match towards a wrong z and the centre
    # inwards; diffusion3d: z RMSE of the cut, non-overlapping images 3.7 -> 1.3 % of the depth)
    for i, h in enumerate(hits):
        T = tmpl[h["page"]].shape[0]
        r0, c0 = max(pad - h["top"], 0), max(pad - h["left"], 0)
        r1, c1 = min(pad + H - h["top"], T), min(pad + W - h["left"], T)
        if r1 <= r0 or c1 <= c0 or _outside_fraction(tmpl[h["page"]], r0, r1, c0, c1) <= 0.15:
            continue
        res.add(*models[i])
        h2 = _match_one(res.img, pad, h["y_px"], h["x_px"], tmpl, calib, m, z_points, cm_drop, coarse, masked=True)
        hits[i] = h2
        models[i] = res.model(h2, cap(h2))
        res.subtract(*models[i])
    # the leftovers of an imperfectly subtracted neighbour can correlate well (Cm is blind to amplitude) but
    # carry a fraction of a particle's light: drop images much fainter than the frame's typical particle
    mass_ref = float(np.median([h[bkey] for h in hits])) if len(hits) >= 3 else 0.0
    out = {k: [] for k in ("x_px", "y_px", "z", "cm", "page", "snr", "mass", "chi2", "edge")}
    for i, (h, (sl, mod)) in enumerate(zip(hits, models)):
        if (h["cm"] < cm_min or h["snr"] < snr_fit or h[bkey] < min_mass * mass_ref
                or (max_mass and mass_ref > 0 and h[bkey] > max_mass * mass_ref
                    and not (merged_cm is not None and h["cm"] >= merged_cm))):
            continue
        if not (-1.0 <= h["x_px"] <= W and -1.0 <= h["y_px"] <= H):
            continue        # centre outside the frame (by more than 1 px, the error of a cut image): not reported
        if mass_ref > 0 and h[bkey] < ghost_mass * mass_ref and any(
                o[bkey] > h[bkey] and abs(o["z"] - h["z"]) < 0.1 * calib.depth
                and math.hypot(o["x_px"] - h["x_px"], o["y_px"] - h["y_px"]) < ghost_px
                for j, o in enumerate(hits) if j != i):
            # a second, faint match a few px along a brighter particle's image at the same height: a piece of
            # that (elongated, astigmatic) image left over by its imperfect model, not a particle
            continue
        # what the models of all particles leave unexplained in this one's window, per pixel, in units of the
        # (smoothed) noise variance: ~1 for a well-explained image; high for an image matched at a compromise
        # between two overlapping particles (Cm alone cannot tell)
        chi2 = _window_rss(res, [sl]) / max(int(res.inside[sl].sum()), 1) / res.noise ** 2
        if max_chi2 is not None and chi2 > max_chi2:
            continue
        for key in ("x_px", "y_px", "z", "cm", "page", "snr"):
            out[key].append(h[key])
        out["mass"].append(h["mass"])
        out["chi2"].append(chi2)
        T = tmpl[h["page"]].shape[0]
        out["edge"].append(bool(h["top"] < pad or h["left"] < pad or h["top"] + T > pad + H or h["left"] + T > pad + W))
    tick("edge")
    return pd.DataFrame(out)


def locate_frame_3d(raw, calib: Calibration, brightfield: bool = False, background="spatial", snr: float = 6.0,
                    cm_min: float = 0.5, gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0,
                    **options) -> pd.DataFrame:
    """Particles and their heights in one raw camera frame: the whole GDPT front end behind one call.

    Prepares the frame as the calibration's templates were made
    (:func:`prepare_gdpt`) and matches the templates (:func:`locate_3d`).

    Parameters
    ----------
    raw : 2D array
        Camera frame (ADU).
    calib : Calibration
    brightfield : bool
        Dark particles on a bright field (must match the calibration).
    background : "spatial", "none" or 2D array
        Background handling; an array is a precomputed background (for
        brightfield already inverted, as :func:`ptrack.preprocess.prepare`).
    snr : float
        Detection threshold (units of the smoothed noise).
    cm_min : float
        Smallest accepted correlation (GDPT's Cm_min).
    gain, offset, read_noise : float
        Camera model (ADU per photon, ADU, photons rms); accepted for the
        pipeline's uniform call; template matching is normalised, so they
        do not change z.
    **options
        Passed to :func:`locate_3d`; ``scale`` (int): match at 1/scale
        resolution (default :func:`ptrack.gdpt.fast.match_scale`: large
        templates reduced to about 48 px; 1: full resolution).

    Returns
    -------
    pandas.DataFrame
        ``x_px``, ``y_px`` (px), ``z`` (m), ``cm``, ``mass`` and the
        diagnostic columns of :func:`locate_3d` (``chi2``, ``edge``...).
    """
    import time

    from .gdpt.fast import match_scale, reduce_frame, reduced_calibration, refine_full

    t0 = time.perf_counter()
    times = calib.info.setdefault("stage_times_s", {})
    img = prepare_gdpt(raw, calib, brightfield=brightfield, background=background)
    times["prepare"] = times.get("prepare", 0.0) + time.perf_counter() - t0
    f = options.pop("scale", None) or match_scale(calib)
    if f <= 1:
        return locate_3d(img, calib, snr=snr, cm_min=cm_min, times=times, **options)
    # large templates: matched at 1/f resolution (ptrack.gdpt.fast), x, y, z refined at full resolution
    # (the brightness cut on faint leftovers, min_mass x the frame's median, after the full-resolution brightness)
    min_mass = options.pop("min_mass", 0.5)
    df = locate_3d(reduce_frame(img, f), reduced_calibration(calib, f), snr=snr, cm_min=cm_min, min_mass=0.0,
                   times=times, **options)
    df["x_px"] = (df["x_px"] + 0.5) * f - 0.5
    df["y_px"] = (df["y_px"] + 0.5) * f - 0.5
    df["mass"] = df["mass"] * (f * f)
    t0 = time.perf_counter()
    df = refine_full(img, calib, df, f)
    times["refine_full"] = times.get("refine_full", 0.0) + time.perf_counter() - t0
    if len(df) >= 3 and min_mass:
        df = df[df["mass"] >= min_mass * float(df["mass"].median())].reset_index(drop=True)
    return df
