"""Stage drift from the frames themselves: phase correlation against a running reference.

The tracks-based drift (:func:`ptrack.motion.drift.drift`) is the mean
displacement of the linked particles; it needs linking, and linking breaks
when the stage jumps farther than the search range. The frames carry the
drift directly: a rigid shift of the field of view is a linear phase ramp in
their Fourier transforms. :func:`frame_drift` registers each frame with
scikit-image's ``phase_cross_correlation`` (the correlation peak; sub-pixel
by parabolas on shrinking stencils of the exact DFT correlation around it,
see ``upsample``) against a *running reference*: the mean of the
last few frames, each moved back by its own estimated drift. Against the
first frame alone, the particles' own motion blurs the correlation peak
until it is lost; the running reference keeps the lag short.

What a correlation of the images measures is the intensity-weighted mean
displacement of what is in them: the stage drift plus the mean random
displacement of the moving particles (as for the tracks-based estimate,
but weighted by the image and not exactly the mean: with diffusing
particles the tracks' mean is about 2x closer, see
bench/bench_image_models.py), and nothing of what does not move with the
stage. Patterns fixed
to the camera (uneven illumination, dust on the optics, the frame border)
pull the estimate towards zero, so each frame is band-passed first (its
smooth background removed, pixel noise smoothed) and tapered at the border.

Phase correlation needs content that persists from frame to frame. Sparse
particles that move farther than their own size between frames leave no
correlation peak, and the highest point of the map is then noise (on the
shipped ``diffusion2d`` movie, 26 particles stepping ~3 px a frame, it gave
drifts of 60-190 px on a still stage). Each frame's peak is therefore tested
for uniqueness: its height above the map's median over that of the highest
point more than 4 px from it (:data:`PEAK_RATIO_MIN`; measured: 1.01-1.72 on
that movie, 1.99-3.4 on drifting scenes whose drift is recovered). A frame
that fails is marked ``reliable = False``, takes its drift by interpolation
between reliable frames and is kept out of the running reference.

The table is in the trajectories table's units and sign convention: ``x``,
``y`` (m) is where the content of frame 0 has moved to in frame ``frame``;
:func:`subtract_frame_drift` removes it from a trajectories table.
"""
from __future__ import annotations

from collections import deque

import numpy as np
import pandas as pd

from ..errors import UserError, check_positive

__all__ = ["frame_drift", "subtract_frame_drift", "PEAK_RATIO_MIN"]

#: smallest ratio of the correlation peak (above the map's median) to the highest point more than
#: PEAK_EXCLUDE_PX from it for a frame's registration to count as reliable
PEAK_RATIO_MIN = 1.8
PEAK_EXCLUDE_PX = 4.0


def _peak_ratio(R, sy: float, sx: float) -> float:
    """Uniqueness of the correlation peak at integer shift (sy, sx) of the cross-power spectrum ``R``."""
    cc = np.fft.ifft2(R).real
    H, W = cc.shape
    iy, ix = int(round(sy)) % H, int(round(sx)) % W
    med = float(np.median(cc))
    yy = (np.arange(H)[:, None] - iy + H // 2) % H - H // 2
    xx = (np.arange(W)[None, :] - ix + W // 2) % W - W // 2
    far = yy * yy + xx * xx > PEAK_EXCLUDE_PX ** 2
    second = float(cc[far].max()) - med if far.any() else 0.0
    top = float(cc[iy, ix]) - med
    return top / second if second > 0 else np.inf


def _taper(shape, width):
    # separable Tukey window: 1 inside, a cosine ramp over `width` px at each border
    out = []
    for n in shape:
        w = np.ones(n)
        k = int(min(width, n // 4))
        if k > 0:
            ramp = 0.5 * (1 - np.cos(np.pi * (np.arange(k) + 0.5) / k))
            w[:k] = ramp
            w[n - k:] = ramp[::-1]
        out.append(w)
    return np.outer(out[0], out[1])


def _band(shape, sigma_low, sigma_high):
    # Fourier-domain band-pass: a Gaussian smoothing of sigma_low px minus the background of sigma_high px
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.fftfreq(shape[1])[None, :]
    k2 = (2 * np.pi) ** 2 * (kx ** 2 + ky ** 2)
    return np.exp(-0.5 * k2 * sigma_low ** 2) - np.exp(-0.5 * k2 * sigma_high ** 2)


def _shift_spectrum(F, dy, dx):
    # the spectrum of the image moved by (dy, dx) px (rows, columns); separable phase ramp
    ey = np.exp(-2j * np.pi * np.fft.fftfreq(F.shape[0]) * dy)
    ex = np.exp(-2j * np.pi * np.fft.fftfreq(F.shape[1]) * dx)
    return F * ey[:, None] * ex[None, :]


def _stencil(P, dy, dx, h):
    # cross-correlation c(d) = Re sum_k P(k) exp(2 pi i k.d) at the 3x3 points (dy + {-h, 0, h}, dx + {-h, 0, h}):
    # three DFT rows and columns, 3 H W operations (einsum: no BLAS call, whose threads stall on a busy machine)
    o = np.array([-h, 0.0, h])
    Ey = np.exp(2j * np.pi * np.outer(dy + o, np.fft.fftfreq(P.shape[0])))
    Ex = np.exp(2j * np.pi * np.outer(np.fft.fftfreq(P.shape[1]), dx + o))
    return np.real(np.einsum("ij,jk->ik", np.einsum("ij,jk->ik", Ey, P), Ex))


def _refine(P, dy, dx, steps=(0.5, 0.125, 1 / 32, 1 / 128)):
    # sub-pixel peak of the cross-correlation from its integer peak: a parabola through the stencil in each
    # axis, on stencils shrinking 4x per round (the parabola's own bias falls as h^2: < 1e-3 px at h = 1/32)
    for h in steps:
        c = _stencil(P, dy, dx, h)
        new = []
        for m, z in ((c[:, 1], dy), (c[1, :], dx)):
            den = m[0] - 2 * m[1] + m[2]
            new.append(z + (float(np.clip(0.5 * h * (m[0] - m[2]) / den, -h, h)) if den < 0 else 0.0))
        dy, dx = new
    return dy, dx


def frame_drift(frames, pixel_size: float, frame_interval: float | None = None, upsample: int = 1,
                window: int = 5, reference: str = "running", bandpass=(1.0, 10.0), taper: float = 16.0,
                first_frame: int = 0) -> pd.DataFrame:
    """Per-frame rigid stage drift by phase correlation, sub-pixel.

    Parameters
    ----------
    frames : iterable of 2D arrays
        The movie, frame by frame (read lazily: only ``window`` spectra are
        kept). All frames the same shape, any polarity.
    pixel_size : float
        Sample-plane pixel size (m per px).
    frame_interval : float, optional
        s per frame, for the ``t`` column (NaN if not given).
    upsample : int
        ``phase_cross_correlation`` locates the peak on a grid of
        1/``upsample`` px (1: the integer peak of its FFT correlation; more:
        its upsampled DFT); parabolas through the correlation at stencils
        shrinking from half that grid to 1/128 of it then refine it. The
        grid alone leaves a uniform error of +-1/(2 upsample) px, which a
        running reference accumulates; the refinement is more accurate
        and much cheaper (clean periodic 256^2 frames: < 1e-4 px RMS with 1
        or 10, against 6e-4 px for skimage's grid at 10 and a parabola;
        skimage's upsampled DFT takes 25-75 ms per 256 x 320 frame on a
        busy 2-core machine, where its BLAS threads stall, the parabolas
        ~2 ms).
    window : int
        Frames in the running reference (the last ``window`` frames, each
        moved back by its estimated drift, averaged).
    reference : {"running", "first"}
        Register against the running reference, or against frame 0 alone
        (exact for a static scene: no accumulation of errors; wrong when
        the particles move by more than their size over the movie).
    bandpass : (float, float)
        Gaussian widths (px) of the band-pass applied before correlating:
        pixel-noise smoothing and the background (illumination) scale.
    taper : float
        Width (px) of the cosine taper at the frame border.
    first_frame : int
        Frame number of the first frame.

    Returns
    -------
    DataFrame
        One row per frame: ``frame``, ``t`` (s), ``x``, ``y`` (m: the
        displacement of the content of frame 0, along columns and rows),
        ``x_px``, ``y_px`` (the same in px), ``error`` (scikit-image's
        translation-invariant normalised RMS error of the registration, 0 for
        a perfect match), ``peak_ratio`` (uniqueness of the correlation peak,
        see the module notes) and ``reliable`` (``peak_ratio >=``
        :data:`PEAK_RATIO_MIN`; frame 0 is the origin and reliable; the
        others' drift is interpolated between reliable frames). Columns ``frame``, ``x``, ``y`` are those of
        :func:`ptrack.motion.drift.drift`'s table, so
        :func:`ptrack.motion.drift.subtract_drift` takes it too.

    Raises
    ------
    UserError
        No frame, frames that are not 2D or differ in shape, bad parameters.
    """
    from skimage.registration import phase_cross_correlation

    px = check_positive("pixel_size", pixel_size)
    dt = np.nan if frame_interval is None else check_positive("frame_interval", frame_interval)
    upsample = int(upsample)
    window = int(window)
    if upsample < 1 or window < 1:
        raise UserError(f"upsample = {upsample} and window = {window} must be at least 1",
                        "give positive integers (defaults 1 and 5)")
    if reference not in ("running", "first"):
        raise UserError(f"reference = {reference!r} is not known", "use 'running' or 'first'")
    s_lo, s_hi = (float(v) for v in bandpass)
    if not (0 <= s_lo < s_hi):
        raise UserError(f"bandpass = {bandpass} must be (low, high) px with 0 <= low < high",
                        "give e.g. (1, 10): noise smoothing and background widths")
    shape = None
    band = taper_w = None
    past = deque(maxlen=window)      # spectra of past frames, already moved back to frame 0
    rows = []
    for k, f in enumerate(frames):
        f = np.asarray(f, np.float64)
        if f.ndim != 2:
            raise UserError(f"frame {k} has shape {f.shape}, not 2D", "give the movie as a sequence of 2D frames")
        if shape is None:
            shape = f.shape
            band = _band(shape, s_lo, s_hi)
            taper_w = _taper(shape, taper)
        elif f.shape != shape:
            raise UserError(f"frame {k} has shape {f.shape}, frame 0 {shape}", "give frames of one size")
        F = np.fft.fft2((f - f.mean()) * taper_w) * band
        if k == 0:
            dy = dx = err = 0.0
            ratio = np.inf
            ref0 = F
        else:
            ref = ref0 if reference == "first" else sum(past) / len(past)
            # the shift that registers this frame with the reference is minus its drift
            shift, err, _ = phase_cross_correlation(ref, F, space="fourier", upsample_factor=upsample,
                                                    normalization=None)
            R = ref * np.conj(F)
            ratio = _peak_ratio(R, float(shift[0]), float(shift[1]))
            sy, sx = _refine(R, float(shift[0]), float(shift[1]),
                             steps=tuple(h / upsample for h in (0.5, 0.125, 1 / 32, 1 / 128)))
            dy, dx = -sy, -sx
        if ratio >= PEAK_RATIO_MIN:      # a noise peak would poison the running reference
            past.append(_shift_spectrum(F, -dy, -dx))
        rows.append((first_frame + k, dx, dy, float(err), ratio))
    if not rows:
        raise UserError("no frame to estimate the drift from", "give a movie with at least one frame")
    fr = np.array([r[0] for r in rows], np.int64)
    dx = np.array([r[1] for r in rows])
    dy = np.array([r[2] for r in rows])
    ratio = np.array([r[4] for r in rows])
    ok = ratio >= PEAK_RATIO_MIN
    if not ok.all():      # frame 0 is always reliable: interpolate the others from the reliable ones
        dx = np.interp(fr, fr[ok], dx[ok])
        dy = np.interp(fr, fr[ok], dy[ok])
    return pd.DataFrame({"frame": fr, "t": fr * dt, "x": dx * px, "y": dy * px, "x_px": dx, "y_px": dy,
                         "error": np.array([r[3] for r in rows]), "peak_ratio": ratio, "reliable": ok})


def subtract_frame_drift(df: pd.DataFrame, drift_table: pd.DataFrame) -> pd.DataFrame:
    """Remove the drift of :func:`frame_drift` from a trajectories (or feature) table.

    ``x``, ``y`` (m) go through :func:`ptrack.motion.drift.subtract_drift`
    (frames outside the drift table take its first/last value); ``x_px``,
    ``y_px``, when present, are corrected by the same amounts in px.

    Parameters
    ----------
    df : DataFrame
        Trajectories table (``frame``, ``x``, ``y`` in m), or a feature table
        with only ``frame``, ``x_px``, ``y_px``.
    drift_table : DataFrame
        Output of :func:`frame_drift`.

    Returns
    -------
    DataFrame
        A corrected copy of ``df``.
    """
    from ..motion.drift import subtract_drift

    need = {"frame", "x", "y", "x_px", "y_px"}
    if not need <= set(drift_table.columns):
        raise UserError(f"the drift table lacks {sorted(need - set(drift_table.columns))}",
                        "give the output of ptrack.image.drift.frame_drift")
    if "frame" not in df.columns or not ({"x", "y"} <= set(df.columns) or {"x_px", "y_px"} <= set(df.columns)):
        raise UserError("the table has no frame and x, y (m) or x_px, y_px (px) columns",
                        "give a trajectories table (ptrack.link.to_trajectories) or a feature table")
    out = subtract_drift(df, drift_table[["frame", "x", "y"]]) if {"x", "y"} <= set(df.columns) else df.copy()
    fd = drift_table["frame"].to_numpy(float)
    fr = df["frame"].to_numpy(float)
    for c in ("x_px", "y_px"):
        if c in df.columns:
            out[c] = df[c].to_numpy(float) - np.interp(fr, fd, drift_table[c].to_numpy(float))
    out.attrs.update(df.attrs)
    return out
