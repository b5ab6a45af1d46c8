"""Synthetic microscope movies from a trajectories table, with exact ground truth.

:func:`render_frames` turns a trajectories table (simulated or hand-made,
SI units, see :mod:`ptrack.table`) into 2D uint16 camera frames, one per
unique ``frame`` of the table, in order. :func:`render_movie` writes them to a
multi-page TIFF frame by frame (bounded memory), with ImageJ metadata (pixel
size, frame interval) plus the same numbers as JSON, the ground-truth table
(``truth.parquet``, with ``x_px``, ``y_px``, ``photons``, ``signal``,
``defocus``) and the rendering parameters (``params.json``).

Geometry: ``x_px = x / pixel_size`` along columns, ``y_px = y / pixel_size``
along rows, the centre of pixel (0, 0) at (0, 0) (trackpy's convention);
``pixel_size = camera.pixel_pitch / optics.magnification``. The defocus of a
particle is ``z - focal_plane`` (z NaN, i.e. 2D data, renders in focus).

Each particle is rendered into a small square patch (see
:func:`sim.render.optics.patch_size`) from an OTF stack precomputed once per
movie, shifted by an exact Fourier phase ramp, blurred by its projected size
and integrated over the pixel area, then added to the frame; the camera model
(:mod:`sim.render.camera`) adds shot and read noise. Optional motion blur
averages ``motion_blur_substeps`` sub-positions spread over the exposure
(centred on the frame time, positions interpolated linearly between the
table's frames). Brightfield: ``"absorption"`` (dark PSF-shaped dips in a
bright field) or ``"coherent"`` (the amplitude PSF interfering with the
illumination: rings and contrast inversion across focus).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.fft as sfft
from numba import njit

from ptrack.errors import UserError, atomic_output, check_positive, output_dir
from ptrack.motion.tracks import check_coordinates, frame_interval
from ptrack.table import make_table, metadata, to_jsonable, validate, write_table

from .camera import Camera, Workspace, expose
from .optics import Optics, PSFStack, build_psf_stack, check_sampling, patch_size, sample_pixel_size, size_transfer

__all__ = ["render_frames", "expected_frames", "render_movie", "frame_interval_of", "localisation_crlb"]

_CHUNK_BYTES = 48e6
# Largest patch side rendered with wave optics (pixels). Particles that would need
# more (defocus beyond ~35 um at NA 0.75) are drawn in the geometric-optics limit:
# their light spread uniformly over the blur ellipse (flux conserved).
MAX_PATCH = 1024


def _fast_even(n: int) -> int:
    n = sfft.next_fast_len(max(int(n), 2), real=True)
    while n % 2:
        n = sfft.next_fast_len(n + 1, real=True)
    return n


@njit(cache=True)
def _add_ellipses(frame, xc, yc, rx, ry, photons, sign, peaks):
    """Add uniform ellipses (centres xc, yc; semi-axes rx, ry in px; total ``photons`` each) to ``frame``."""
    H, W = frame.shape
    for k in range(xc.size):
        a = max(rx[k], 0.5)
        b = max(ry[k], 0.5)
        v = photons[k] / (np.pi * a * b)
        peaks[k] = v
        y0 = max(0, int(math.floor(yc[k] - b)))
        y1 = min(H - 1, int(math.ceil(yc[k] + b)))
        x0 = max(0, int(math.floor(xc[k] - a)))
        x1 = min(W - 1, int(math.ceil(xc[k] + a)))
        for r in range(y0, y1 + 1):
            dy = (r - yc[k]) / b
            for c in range(x0, x1 + 1):
                dx = (c - xc[k]) / a
                if dx * dx + dy * dy <= 1.0:
                    frame[r, c] += sign * v


@njit(cache=True)
def _add_patches(frame, patches, iy0, ix0, sign):
    """Add ``sign * patches[k]`` to ``frame`` with patch pixel (0, 0) at frame (iy0[k], ix0[k]); clipped at the edges."""
    H, W = frame.shape
    K, n, _ = patches.shape
    for k in range(K):
        y0 = iy0[k]
        x0 = ix0[k]
        r0 = max(0, -y0)
        r1 = min(n, H - y0)
        c0 = max(0, -x0)
        c1 = min(n, W - x0)
        for r in range(r0, r1):
            for c in range(c0, c1):
                frame[y0 + r, x0 + c] += sign * patches[k, r, c]


@njit(cache=True)
def _otf_accumulate(stack, i0, w, ey, ex, amp, out):
    """out[k] += amp[k] * ((1 - w[k]) stack[i0[k]] + w[k] stack[i0[k] + 1]) * ey[k][:, None] * ex[k][None, :]."""
    K, n, q = out.shape
    last = stack.shape[0] - 1
    for k in range(K):
        i = i0[k]
        j = min(i + 1, last)
        a0 = np.float32(amp[k] * (1.0 - w[k]))
        a1 = np.float32(amp[k] * w[k])
        for r in range(n):
            e = ey[k, r]
            for c in range(q):
                out[k, r, c] += (a0 * stack[i, r, c] + a1 * stack[j, r, c]) * (e * ex[k, c])


class _Renderer:
    """Expected photon images of point-like / spherical emitters from a PSF stack."""

    def __init__(self, stack: PSFStack):
        self.stack = stack
        n = stack.n
        self.n = n
        self.fy = np.fft.fftfreq(n)
        self.fx = np.fft.rfftfreq(n)
        self._size_cache: dict[float, np.ndarray] = {}

    def _size(self, radius: float) -> np.ndarray:
        t = self._size_cache.get(radius)
        if t is None:
            t = size_transfer(self.stack.kr, radius)
            if len(self._size_cache) < 64:
                self._size_cache[radius] = t
        return t

    def plane_weights(self, defocus: np.ndarray):
        """Index of the PSF plane below each defocus and the linear weight of the one above."""
        st = self.stack
        zi = (np.asarray(defocus, dtype=np.float64) - st.z0) / st.dz
        i0 = np.clip(np.floor(zi).astype(np.int64), 0, max(st.nz - 2, 0))
        w = np.clip(zi - i0, 0.0, 1.0) if st.nz > 1 else np.zeros(len(zi))
        return np.ascontiguousarray(i0), np.ascontiguousarray(w)

    def ramps(self, dy: np.ndarray, dx: np.ndarray):
        """1D Fourier phase ramps placing each source at patch position (c + dy, c + dx), c = n // 2."""
        c = self.n // 2
        ey = np.exp(-2j * np.pi * self.fy[None, :] * (c + dy)[:, None]).astype(np.complex64)
        ex = np.exp(-2j * np.pi * self.fx[None, :] * (c + dx)[:, None]).astype(np.complex64)
        return ey, ex

    def patches(self, x_px, y_px, defocus, radius, photons, sub=None, field_amp=None):
        """Patches (K, n, n) of expected photons and their top-left frame indices.

        ``sub``: optional list of (weight, x_px, y_px, defocus) sub-positions for
        motion blur (weights sum to 1); the patch is anchored at the rounded
        (x_px, y_px). ``field_amp``: (c_re, c_im) per particle, the weights of
        the real and imaginary parts of the amplitude PSF (coherent
        brightfield's interference term), added to ``photons`` x intensity PSF.
        """
        ix = np.rint(x_px).astype(np.int64)
        iy = np.rint(y_px).astype(np.int64)
        c = self.n // 2
        # single precision: ~1e-7 relative, far below shot noise, twice the speed of double
        otf = np.zeros((len(x_px), self.n, self.n // 2 + 1), dtype=np.complex64)
        photons = np.ascontiguousarray(photons, dtype=np.float64)
        if sub is None:
            sub = [(1.0, x_px, y_px, defocus)]
        for w, xs, ys, zs in sub:
            i0, wz = self.plane_weights(zs)
            ey, ex = self.ramps(ys - iy, xs - ix)
            _otf_accumulate(self.stack.otf, i0, wz, ey, ex, photons * w, otf)
            if field_amp is not None:
                _otf_accumulate(self.stack.field_re, i0, wz, ey, ex, field_amp[0] * w, otf)
                _otf_accumulate(self.stack.field_im, i0, wz, ey, ex, field_amp[1] * w, otf)
        for r in np.unique(radius):
            if r > 0:
                sel = radius == r
                otf[sel] *= self._size(float(r)).astype(np.float32)
        pat = sfft.irfft2(otf, s=(self.n, self.n), workers=1)
        return pat, iy - c, ix - c


def frame_interval_of(table: pd.DataFrame) -> float:
    """Frame interval (s) of a table to render: :func:`ptrack.motion.frame_interval`, the toolkit's one rule.

    That rule reads ``t`` first (metadata ``frame_interval`` only for a single frame; a disagreement of more
    than 1 % is warned about). When ``t`` and the metadata agree to 1e-9 the metadata value is returned, so the
    number written into the movie is the exact one given, not ``t``'s rounding. Raises UserError when several
    frames do not tell it (t not increasing); a single-frame table without metadata gets the TIFF's nominal
    1 s, with a warning."""
    meta = metadata(table)
    fi = meta.get("frame_interval")
    f = table["frame"].to_numpy()
    if (f.size and f.max() > f.min()) or fi:
        dt = frame_interval(table)
        if fi and math.isfinite(float(fi)) and abs(float(fi) / dt - 1) < 1e-9:
            return float(fi)
        return dt
    # one frame: no interval to tell; 1 s is only the TIFF's nominal one (said, not silent)
    import warnings

    warnings.warn("a single-frame table has no frame interval: the movie is written with 1 s", stacklevel=2)
    return 1.0


class _Scene:
    """Per-row arrays prepared once for a table."""

    def __init__(self, table, shape, optics, camera, focal_plane, motion_blur_substeps, radius,
                 brightfield=False, scatter_phase: float = 2.5):
        table = validate(table.copy())
        for c in ("x", "y", "z"):  # the estimators' rule for a position in m (ptrack.motion.tracks)
            check_coordinates(c, table[c])
        self.table = table
        try:
            H, W = (int(v) for v in shape)
        except (TypeError, ValueError):
            raise UserError(f"shape = {shape!r} is not two integers", "give the frame shape as (height, width) in pixels")
        if H < 1 or W < 1 or H * W > 2 ** 28:
            raise UserError(f"shape = {shape!r} is out of range", "give a frame height and width of 1..16384 pixels")
        self.shape = (H, W)
        self.optics = optics or Optics()
        self.camera = camera or Camera()
        self.focal_plane = float(focal_plane)
        if not math.isfinite(self.focal_plane):
            raise UserError(f"focal_plane = {focal_plane!r} is not finite", "give the focal-plane height in m")
        self.pixel = sample_pixel_size(self.optics, self.camera.pixel_pitch)
        check_sampling(self.optics, self.pixel)
        self.mode = _brightfield_mode(brightfield)
        if self.mode == "coherent":
            if not self.camera.background > 0:
                raise UserError("coherent brightfield needs a bright field: camera.background = 0",
                                "give the illumination as background photons per pixel (> 0)")
            if not math.isfinite(float(scatter_phase)):
                raise UserError(f"scatter_phase = {scatter_phase!r} is not finite", "give the phase in radians")
        self.scatter_phase = float(scatter_phase)
        S = int(motion_blur_substeps)
        if S < 0:
            raise UserError(f"motion_blur_substeps = {motion_blur_substeps!r} is negative", "give 0 (no blur) or a positive number")
        self.substeps = S
        self.frame_interval = frame_interval_of(table)
        self.exposure = float(self.camera.exposure) if self.camera.exposure else self.frame_interval
        if len(np.unique(table["frame"])) > 1:   # (one frame has only the nominal 1 s interval)
            from ptrack.motion.tracks import motion_blur_from_exposure

            motion_blur_from_exposure(self.exposure, self.frame_interval)   # the one rule: 0 <= exposure <= interval

        self.x_px = table["x"].to_numpy() / self.pixel
        self.y_px = table["y"].to_numpy() / self.pixel
        z = table["z"].to_numpy()
        self.defocus = np.where(np.isfinite(z), z - self.focal_plane, 0.0)
        if self.optics.field_dependent:  # a curved / tilted focal surface (Optics.focal_shift) about the frame centre
            zf = self.optics.focal_shift(table["x"].to_numpy(), table["y"].to_numpy(),
                                         ((W - 1) / 2 * self.pixel, (H - 1) / 2 * self.pixel))
            self.defocus = np.where(np.isfinite(z), self.defocus - zf, 0.0)
        if radius is not None:
            r = np.full(len(table), check_positive("radius", radius, allow_zero=True))
        elif "radius" in table.columns:
            r = pd.to_numeric(table["radius"], errors="coerce").to_numpy(dtype=float)
            r = np.where(np.isfinite(r) & (r > 0), r, 0.0)
        else:
            r = np.zeros(len(table))
        self.radius = r
        if "photons" in table.columns:
            ph = pd.to_numeric(table["photons"], errors="coerce").to_numpy(dtype=float)
            if not np.all(np.isfinite(ph)) or (ph < 0).any():
                raise UserError("table column 'photons' has negative or non-finite values", "give photons per particle per exposure >= 0")
        else:
            ph = np.full(len(table), float(self.camera.photons))
        self.photons = ph

        frames = table["frame"].to_numpy()
        order = np.argsort(frames, kind="stable")
        self.frames, starts = np.unique(frames[order], return_index=True)
        self.groups = np.split(order, starts[1:]) if len(order) else []

        # Sub-positions for motion blur: linear interpolation to the neighbouring rows of the same particle.
        if S > 0 and len(table):
            p = table["particle"].to_numpy()
            t = table["t"].to_numpy()
            same_next = np.r_[p[1:] == p[:-1], False]
            same_prev = np.r_[False, p[1:] == p[:-1]]
            vel = []
            for arr in (self.x_px, self.y_px, self.defocus):
                nxt = np.r_[arr[1:], arr[-1:]]
                prv = np.r_[arr[:1], arr[:-1]]
                tn = np.r_[t[1:], t[-1:]]
                tp = np.r_[t[:1], t[:-1]]
                with np.errstate(divide="ignore", invalid="ignore"):
                    vf = np.where(same_next, (nxt - arr) / (tn - t), np.nan)
                    vb = np.where(same_prev, (arr - prv) / (t - tp), np.nan)
                vf = np.where(np.isfinite(vf), vf, np.where(np.isfinite(vb), vb, 0.0))
                vb = np.where(np.isfinite(vb), vb, vf)
                vel.append((vf, vb))
            self.vel = vel
            taus = ((np.arange(S) + 0.5) / S - 0.5) * self.exposure
            self.taus = taus
            vmax = max(float(np.max(np.abs(np.concatenate(v)))) if len(table) else 0.0 for v in vel[:2])
            self.blur_px = vmax * self.exposure / 2
            vz = max(float(np.max(np.abs(np.concatenate(vel[2])))), 0.0)
            self.blur_z = vz * self.exposure / 2
        else:
            self.blur_px = 0.0
            self.blur_z = 0.0

        # Patch classes: each row gets the patch its defocus needs (the defocus blur grows
        # 0.68 um per um at NA 0.75), rounded up a ladder of FFT-friendly sizes ~25 % apart;
        # one PSF stack per (size, side of focus). A particle far from focus then does not
        # make every in-focus particle pay for a huge patch.
        o = self.optics
        lo_z = self.defocus - self.blur_z
        hi_z = self.defocus + self.blur_z
        need = ((np.maximum(np.abs(lo_z), np.abs(hi_z)) + o.line_focus_offset) * o.half_angle_tan
                + o.psf_margin * o.airy_radius + 2.0 * self.radius) * 2.0 / self.pixel + 2 + 4 * self.blur_px
        ladder = [patch_size(o, self.pixel, 0.0, 0.0)]
        top = min(float(need.max()), MAX_PATCH) if len(need) else 0.0
        while ladder[-1] < top:
            ladder.append(_fast_even(int(math.ceil(ladder[-1] * 1.25))))
        ladder = np.array(ladder)
        size_idx = np.searchsorted(ladder, need, side="left") if len(need) else np.zeros(0, np.int64)
        side = (self.defocus >= 0).astype(np.int64)
        key = size_idx * 2 + side
        far = need > MAX_PATCH
        key[far] = -1
        self.row_class = np.full(len(table), -1, dtype=np.int64)
        self.renderers: list[_Renderer] = []
        # geometric blur ellipse of far rows (semi-axes in px; the astigmatic line foci sit at -/+ lf)
        lf = 2.0 * o.medium_index * o.astigmatism / o.na ** 2
        self.far_rx = np.abs(self.defocus - lf) * o.half_angle_tan / self.pixel
        self.far_ry = np.abs(self.defocus + lf) * o.half_angle_tan / self.pixel
        keys = np.unique(key[~far])
        for ci, k in enumerate(keys):
            sel = key == k
            self.row_class[sel] = ci
            n = int(ladder[k // 2])
            # all stacks together stay within ~512 MB (plane spacing coarsened if needed)
            st = build_psf_stack(o, self.pixel, float(lo_z[sel].min()), float(hi_z[sel].max()),
                                 float(self.radius[sel].max()), n=n, max_bytes=512e6 / len(keys),
                                 with_field=self.mode == "coherent")
            self.renderers.append(_Renderer(st))
        if not self.renderers:  # empty table: one in-focus class so that frames can still be drawn
            self.renderers.append(_Renderer(build_psf_stack(o, self.pixel, 0.0, 0.0, 0.0)))

    @property
    def stack(self) -> PSFStack:
        """The PSF stack with the largest patch (for reporting)."""
        return max((r.stack for r in self.renderers), key=lambda st: st.n)

    def sub_positions(self, idx):
        if self.substeps <= 0:
            return None
        out = []
        w = 1.0 / self.substeps
        (vxf, vxb), (vyf, vyb), (vzf, vzb) = self.vel
        for tau in self.taus:
            if tau >= 0:
                vx, vy, vz = vxf[idx], vyf[idx], vzf[idx]
            else:
                vx, vy, vz = vxb[idx], vyb[idx], vzb[idx]
            out.append((w, self.x_px[idx] + vx * tau, self.y_px[idx] + vy * tau, self.defocus[idx] + vz * tau))
        return out

    def field_amplitudes(self, rows):
        """Weights of Re a and Im a in 2 B Re(sigma a), sigma = sqrt(photons / B) exp(i phase)."""
        B = float(self.camera.background)
        mag = 2.0 * np.sqrt(B * self.photons[rows])
        return (np.ascontiguousarray(mag * math.cos(self.scatter_phase)),
                np.ascontiguousarray(-mag * math.sin(self.scatter_phase)))

    def expected(self, idx, brightfield=None, out=None):
        """Expected photons per pixel (H, W) for the rows ``idx`` of one frame, and each row's peak photons.

        ``out``: an (H, W) float64 array to fill (reused frame after frame), else a new one.
        """
        H, W = self.shape
        if out is None:
            img = np.full((H, W), float(self.camera.background))
        else:
            img = out
            img.fill(float(self.camera.background))
        peaks = np.zeros(len(idx))
        mode = self.mode if brightfield is None else _brightfield_mode(brightfield)
        coherent = mode == "coherent"
        sign = -1.0 if mode == "absorption" else 1.0
        cls = self.row_class[idx]
        far = np.nonzero(cls < 0)[0]
        if far.size:
            rows = idx[far]
            pk = np.zeros(far.size)
            _add_ellipses(img, self.x_px[rows], self.y_px[rows], self.far_rx[rows], self.far_ry[rows],
                          self.photons[rows], sign, pk)
            peaks[far] = pk
        for ci in np.unique(cls[cls >= 0]):
            renderer = self.renderers[ci]
            n = renderer.n
            c = n // 2
            cidx = np.nonzero(cls == ci)[0]
            rows_c = idx[cidx]
            # cull particles whose patch misses the frame entirely
            ix = np.rint(self.x_px[rows_c]).astype(np.int64)
            iy = np.rint(self.y_px[rows_c]).astype(np.int64)
            keep = (ix + n - c > 0) & (ix - c < W) & (iy + n - c > 0) & (iy - c < H) & (self.photons[rows_c] > 0)
            kidx = cidx[keep]
            per = max(1, int(_CHUNK_BYTES // (n * (n // 2 + 1) * 8 * 3)))
            for s in range(0, len(kidx), per):
                loc = kidx[s:s + per]
                rows = idx[loc]
                pat, y0, x0 = renderer.patches(self.x_px[rows], self.y_px[rows], self.defocus[rows],
                                               self.radius[rows], self.photons[rows], self.sub_positions(rows),
                                               self.field_amplitudes(rows) if coherent else None)
                flat = pat.reshape(len(rows), -1)
                peaks[loc] = np.abs(flat).max(axis=1) if coherent else flat.max(axis=1)
                _add_patches(img, pat, y0, x0, sign)
        if mode != "fluorescence":
            np.maximum(img, 0.0, out=img)
        return img, peaks


def _brightfield_mode(brightfield) -> str:
    """False -> 'fluorescence'; True or 'absorption' -> 'absorption'; 'coherent' -> 'coherent'."""
    if brightfield is False or brightfield is None:
        return "fluorescence"
    if brightfield is True:
        return "absorption"
    if isinstance(brightfield, str) and brightfield in ("absorption", "coherent"):
        return brightfield
    raise UserError(f"brightfield = {brightfield!r} is not understood",
                    "give False (fluorescence), True / 'absorption' or 'coherent'")


def _iter_frames(scene: _Scene, seed):
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    work = Workspace()
    buf = np.empty(scene.shape)
    for f, idx in zip(scene.frames, scene.groups):
        img, peaks = scene.expected(idx, out=buf)
        yield int(f), idx, expose(img, scene.camera, rng, work), peaks


def render_frames(table: pd.DataFrame, shape=(256, 256), optics: Optics | None = None, camera: Camera | None = None,
                  focal_plane: float = 0.0, brightfield=False, motion_blur_substeps: int = 0, seed=0,
                  radius: float | None = None, scatter_phase: float = 2.5):
    """Render a trajectories table as camera frames.

    Parameters
    ----------
    table : DataFrame
        Trajectories table (frame, t, particle, x, y, z in m). Optional columns
        ``radius`` (m, projected-size blur) and ``photons`` (per exposure)
        override the defaults per row.
    shape : (int, int)
        Frame height and width, pixels.
    optics : Optics, optional
    camera : Camera, optional
    focal_plane : float
        Height of the focal plane, m; a particle's defocus is ``z - focal_plane``.
    brightfield : bool or str
        False: fluorescence (``photons`` per particle on ``camera.background``).
        True or ``"absorption"``: dark particles on a bright field
        (``camera.background`` photons per pixel minus ``photons`` per
        particle spread as the intensity PSF). ``"coherent"``: coherent
        brightfield, ``B |1 + sigma a|^2`` with ``a`` the amplitude PSF
        (``sum |a|^2 = 1``), ``B = camera.background`` and
        ``sigma = sqrt(photons / B) exp(i scatter_phase)``: the scattered light
        interferes with the illumination, so the contrast changes with defocus
        (dark in focus for phases near pi, bright/dark centres on the two
        sides of focus) as in real brightfield images of colloids.
    motion_blur_substeps : int
        0: instantaneous positions; S > 0: average of S sub-positions over the exposure.
    seed : int or numpy.random.Generator
        Noise seed: same seed, same frames.
    radius : float, optional
        Particle radius for all rows, m (overrides a ``radius`` column; default 0 = point source).
    scatter_phase : float
        Phase of the scattered field relative to the illumination, rad
        (coherent brightfield only; pi = pure extinction, pi/2 = weak phase object).

    Yields
    ------
    ndarray (H, W), uint16
        One frame per sorted unique ``frame`` of the table.
    """
    scene = _Scene(table, shape, optics, camera, focal_plane, motion_blur_substeps, radius, brightfield, scatter_phase)
    for _, _, img, _ in _iter_frames(scene, seed):
        yield img


def expected_frames(table: pd.DataFrame, shape=(256, 256), optics: Optics | None = None, camera: Camera | None = None,
                    focal_plane: float = 0.0, brightfield=False, motion_blur_substeps: int = 0,
                    radius: float | None = None, scatter_phase: float = 2.5):
    """Noise-free expected photons per pixel (float64 frames), same geometry as :func:`render_frames`.

    Yields
    ------
    ndarray (H, W), float64
        Expected photons reaching each pixel (background included), one per
        sorted unique ``frame`` of the table; the camera turns them into ADU
        with mean ``gain * QE * photons + offset``.
    """
    scene = _Scene(table, shape, optics, camera, focal_plane, motion_blur_substeps, radius, brightfield, scatter_phase)
    for idx in scene.groups:
        yield scene.expected(idx)[0]


def localisation_crlb(camera: Camera, x_px: float, y_px: float, shape=(40, 40), optics: Optics | None = None,
                      step: float = 1e-3) -> float:
    """Cramer-Rao bound on x (px) of one in-focus particle rendered at (x_px, y_px), px.

    Exact for the renderer's own expected image: the Fisher information of
    (x, y, amplitude, background) under Poisson photo-electrons plus Gaussian
    read noise (variance ``mu + read_noise^2`` per pixel), with the image's
    derivatives by central differences of ``step`` px.
    """
    optics = optics or Optics()
    px = sample_pixel_size(optics, camera.pixel_pitch)

    def mu_e(x, y):
        tt = make_table([0], [0.0], [0], [x * px], [y * px], [0.0], meta={"frame_interval": 0.1})
        return next(expected_frames(tt, shape, optics, camera)) * camera.quantum_efficiency

    m = mu_e(x_px, y_px)
    J = np.stack([((mu_e(x_px + step, y_px) - mu_e(x_px - step, y_px)) / (2 * step)).ravel(),
                  ((mu_e(x_px, y_px + step) - mu_e(x_px, y_px - step)) / (2 * step)).ravel(),
                  (m - camera.background * camera.quantum_efficiency).ravel(), np.ones(m.size)], 1)
    fisher = J.T @ (J / (m + camera.read_noise ** 2).ravel()[:, None])
    return float(np.sqrt(np.linalg.inv(fisher)[0, 0]))


def _tiff_metadata(pixel: float, frame_interval: float, info: dict) -> dict:
    return {"axes": "TYX", "unit": "um", "finterval": float(frame_interval), "Info": json.dumps(info)}


def render_movie(table: pd.DataFrame, out_dir, shape=(256, 256), optics: Optics | None = None,
                 camera: Camera | None = None, focal_plane: float = 0.0, brightfield=False,
                 motion_blur_substeps: int = 0, seed=0, radius: float | None = None, scatter_phase: float = 2.5,
                 compression: str | None = None, extra_params: dict | None = None, progress: bool = True) -> dict:
    """Render a table to ``out_dir/movie.tif`` (+ ``truth.parquet``, ``params.json``).

    Every frame from the table's first to its last frame becomes one TIFF
    page (frames absent from the table are background only), so page index =
    ``frame - first_frame``; the truth table's ``frame`` column is that page
    index (``params.json`` records ``frame_offset``). Frames are written one at
    a time (memory bounded by one frame plus the PSF stack). Parameters as in
    :func:`render_frames`; ``compression`` e.g. ``"zlib"`` (lossless);
    ``extra_params`` are merged into ``params.json``.

    The truth table is the input table (all rows, SI units, metadata
    ``pixel_size``, ``frame_interval``, ``focal_plane``) plus:

    ``x_px``, ``y_px``
        Exact image position, pixels (trackpy convention).
    ``photons``
        Photons per exposure of the particle (brightfield: removed from the field).
    ``signal``
        Expected peak of the particle's image above the background, ADU
        (gain x QE x brightest pixel of its noise-free image; brightfield: the
        depth of its dip).
    ``defocus``
        ``z - focal_plane``, m (0 for 2D rows).
    ``radius``
        Particle radius used for the size blur, m.
    ``in_frame``
        True if the centre lies inside the image (rows outside are kept: their
        light may still reach the frame).

    The TIFF carries ImageJ metadata (``unit`` um, X/Y resolution in pixels
    per um, ``finterval`` in s) and the same numbers, SI, as JSON in the
    ImageJ ``Info`` property: ``json.loads(TiffFile(p).imagej_metadata["Info"])``
    gives ``pixel_size`` (m), ``frame_interval`` (s), ``focal_plane``, ``shape``...

    Returns
    -------
    dict with paths ``movie``, ``truth``, ``params``.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"output path {out_dir} exists and is not a directory", "give a directory for --out")
    if len(table) == 0:
        raise UserError("trajectories table is empty", "give a table with at least one row")
    scene = _Scene(table, shape, optics, camera, focal_plane, motion_blur_substeps, radius, brightfield, scatter_phase)
    tbl = scene.table
    f0 = int(scene.frames[0])
    nf = int(scene.frames[-1]) - f0 + 1
    H, W = scene.shape
    fi = scene.frame_interval
    pixel = scene.pixel

    signal = np.zeros(len(tbl))
    gain_qe = scene.camera.gain * scene.camera.quantum_efficiency
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    by_frame = dict(zip((int(f) for f in scene.frames), scene.groups))

    work = Workspace()
    buf = np.empty((H, W))

    def pages():
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=nf, desc="render", unit="frame", leave=False)
        try:
            for f in range(f0, f0 + nf):
                idx = by_frame.get(f)
                if idx is None:
                    idx = np.zeros(0, dtype=np.int64)
                img, peaks = scene.expected(idx, out=buf)
                signal[idx] = peaks * gain_qe
                yield expose(img, scene.camera, rng, work)
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()

    info = {
        "pixel_size": pixel, "pixel_size_unit": "m", "frame_interval": fi, "frame_interval_unit": "s",
        "shape": [H, W], "n_frames": nf, "focal_plane": scene.focal_plane, "brightfield": scene.mode != "fluorescence",
        "source": "sim.render.render_movie",
    }
    params = {
        **info,
        "frame_offset": f0,
        "exposure": scene.exposure,
        "motion_blur_substeps": scene.substeps,
        "mode": scene.mode,
        "scatter_phase": scene.scatter_phase if scene.mode == "coherent" else None,
        "seed": seed if not isinstance(seed, np.random.Generator) else None,
        "optics": scene.optics.to_dict(),
        "camera": scene.camera.to_dict(),
        "psf_patch_px": sorted({r.n for r in scene.renderers}),
        "psf_z_step_used": max(r.stack.dz for r in scene.renderers),
        "n_particles": int(tbl["particle"].nunique()),
        "table_meta": metadata(tbl),
        "compression": compression,
    }
    if extra_params:
        params.update(extra_params)
    # a folder made here is removed again, with what was written into it, if any write fails (a full disk)
    with output_dir(out_dir, "--out", all_or_nothing=True):
        return _write_movie(out_dir, pages, nf, H, W, pixel, fi, info, compression, tbl, scene, signal, f0, radius,
                            params)


def _write_movie(out_dir, pages, nf, H, W, pixel, fi, info, compression, tbl, scene, signal, f0, radius, params):
    """The files of :func:`render_movie`: movie.tif, truth.parquet, params.json (each atomic)."""
    import tifffile

    movie = out_dir / "movie.tif"
    px_um = pixel * 1e6
    with atomic_output(movie, None) as tmp:
        tifffile.imwrite(
            tmp, pages(), shape=(nf, H, W), dtype=np.uint16, imagej=True, compression=compression,
            resolution=(1.0 / px_um, 1.0 / px_um), metadata=_tiff_metadata(pixel, fi, info),
        )

    truth = tbl.copy()
    truth["frame"] = truth["frame"] - f0
    truth["x_px"] = scene.x_px
    truth["y_px"] = scene.y_px
    truth["photons"] = scene.photons
    truth["signal"] = signal
    truth["defocus"] = scene.defocus
    truth["in_frame"] = (scene.x_px > -0.5) & (scene.x_px < W - 0.5) & (scene.y_px > -0.5) & (scene.y_px < H - 0.5)
    if "radius" not in truth.columns or radius is not None:
        truth["radius"] = scene.radius
    meta = dict(metadata(tbl))
    meta.update({"pixel_size": pixel, "frame_interval": fi, "source": "sim.render ground truth",
                 "focal_plane": scene.focal_plane, "movie": movie.name})
    truth.attrs["ptrack"] = meta
    truth_path = write_table(truth, out_dir / "truth.parquet")
    params_path = out_dir / "params.json"
    with atomic_output(params_path, "w") as fh:
        json.dump(to_jsonable(params), fh, indent=2, sort_keys=True)
        fh.write("\n")
    return {"movie": movie, "truth": truth_path, "params": params_path}
