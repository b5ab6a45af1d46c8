"""Command-line options shared by ``ptrack render`` and ``ptrack render-calibration``, and their preview plots."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from ptrack.errors import UserError

from .camera import Camera
from .optics import Optics

_OPT = Optics()
_CAM = Camera()


def _number(group, flag: str, default, what: str, fmt: str = "", kind=float) -> None:
    """A numeric option whose help ends with its default, formatted with ``fmt``."""
    group.add_argument(flag, type=kind, default=default, help=f"{what} (default {default:{fmt}})")


def add_optics_camera_arguments(p: argparse.ArgumentParser, astigmatism: float | None = None,
                                photons: float | None = None) -> None:
    """Optics and camera options (SI units; defaults: the seed's 63x / NA 0.75 objective and Zyla 5.5 camera).

    ``astigmatism``, ``photons``: the defaults of ``--astigmatism`` (m) and ``--photons``, if not the optics' and
    camera's own (``ptrack render-calibration`` gives both: its default stack tells +z from -z, and its pages
    are as bright as a few movie frames averaged)."""
    # let negative numbers in scientific notation (e.g. --focal-plane -2e-6) be values, not options
    p._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
    g = p.add_argument_group("optics (SI units)")
    _number(g, "--na", _OPT.na, "numerical aperture")
    _number(g, "--wavelength", _OPT.wavelength, "emission wavelength, m", "g")
    _number(g, "--medium-index", _OPT.medium_index, "refractive index of the sample medium")
    _number(g, "--immersion-index", _OPT.immersion_index, "refractive index of the immersion medium")
    _number(g, "--magnification", _OPT.magnification, "magnification", "g")
    ast = _OPT.astigmatism if astigmatism is None else float(astigmatism)
    g.add_argument("--astigmatism", type=float, default=ast,
                   help="astigmatic wavefront amplitude at the pupil edge, m (cylindrical lens; 0 = none; e.g. 1.2e-7; "
                        f"default {ast:g}; a movie and its calibration stack need the same value: "
                        "render-calibration's default is 1.2e-7)")
    g.add_argument("--radius", type=float, default=None, help="particle radius, m (default: the table's 'radius' column, else a point source)")
    c = p.add_argument_group("camera and light")
    _number(c, "--pixel-pitch", _CAM.pixel_pitch, "camera pixel pitch, m", "g")
    _number(c, "--photons", _CAM.photons if photons is None else float(photons), "photons per particle per exposure (brightfield: removed from the background)", "g")
    _number(c, "--background", _CAM.background, "background photons per pixel per exposure", "g")
    _number(c, "--qe", _CAM.quantum_efficiency, "quantum efficiency")
    _number(c, "--read-noise", _CAM.read_noise, "read noise, e- rms")
    _number(c, "--gain", _CAM.gain, "gain, ADU per e-")
    _number(c, "--offset", _CAM.offset, "offset, ADU", "g")
    _number(c, "--bit-depth", _CAM.bit_depth, "bit depth", kind=int)
    c.add_argument("--brightfield", action="store_true",
                   help="brightfield instead of fluorescence (--background is the illumination, photons per pixel)")
    c.add_argument("--brightfield-model", choices=["absorption", "coherent"], default="absorption",
                   help="'absorption': dark PSF-shaped dips (default); 'coherent': scattered light interfering "
                        "with the illumination (rings, contrast inverts across focus)")
    c.add_argument("--scatter-phase", type=float, default=2.5,
                   help="coherent brightfield: phase of the scattered field, rad (pi: extinction, pi/2: phase object; default 2.5)")
    c.add_argument("--compress", action="store_true", help="lossless zlib compression of the TIFF")
    c.add_argument("--seed", type=int, default=0, help="noise seed (same seed, byte-identical output; default 0)")


def optics_camera_from_args(a, exposure=None) -> tuple[Optics, Camera]:
    optics = Optics(na=a.na, wavelength=a.wavelength, medium_index=a.medium_index, immersion_index=a.immersion_index,
                    magnification=a.magnification, astigmatism=a.astigmatism)
    camera = Camera(pixel_pitch=a.pixel_pitch, quantum_efficiency=a.qe, read_noise=a.read_noise, gain=a.gain,
                    offset=a.offset, bit_depth=a.bit_depth, photons=a.photons, background=a.background, exposure=exposure)
    return optics, camera


def brightfield_from_args(a):
    """False (fluorescence), 'absorption' or 'coherent'."""
    return a.brightfield_model if a.brightfield else False


def check_out_dir(out) -> Path:
    """The --out folder, checked before any rendering: a directory (or creatable) and writable."""
    from ptrack.errors import check_writable

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory", "give a directory path")
    return check_writable(out, "--out", directory=True)


def save_montage(images, titles, path, ncols: int = 6, overlay=None, title: str | None = None,
                 smooth: bool = False) -> Path:
    """Grey-scale montage PNG of a few images; ``overlay``: list of (x_px, y_px) arrays to circle.

    Each image is stretched between its 1st and 99.9th percentiles; ``smooth``: Gaussian-smoothed first (faint
    defocused images on large pages)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    ncols = min(ncols, n)
    nrows = (n + ncols - 1) // ncols
    # room for one title line above each row
    fig, axes = plt.subplots(nrows, ncols, figsize=(2.6 * ncols, 2.9 * nrows + (0.4 if title else 0)), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for i, (img, t) in enumerate(zip(images, titles)):
        ax = axes.ravel()[i]
        img = np.asarray(img, np.float64)
        if smooth:
            # a faint defocused image spread over a large page is invisible under the pixel noise at the montage's
            # scale: smoothed over ~1 displayed pixel and stretched between percentiles it shows
            from scipy.ndimage import gaussian_filter

            img = gaussian_filter(img, max(1.0, max(img.shape) / 200.0))
        lo, hi = np.percentile(img, [1.0, 99.9])
        ax.imshow(img, cmap="gray", interpolation="nearest", vmin=lo, vmax=hi if hi > lo else lo + 1)
        if overlay is not None and overlay[i] is not None:
            x, y = overlay[i]
            ax.scatter(x, y, s=40, facecolors="none", edgecolors="r", linewidths=0.7)
            ax.set_xlim(-0.5, img.shape[1] - 0.5)
            ax.set_ylim(img.shape[0] - 0.5, -0.5)
        ax.set_title(t, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def preview_pages(tiff_path, pages):
    """Read a few pages of a TIFF (one page at a time)."""
    import tifffile

    with tifffile.TiffFile(tiff_path) as tf:
        return [tf.pages[int(k)].asarray() for k in pages]


def spread_indices(n: int, k: int = 6, include=None):
    """About ``k`` indices spread over 0..n-1, always with ``include`` (e.g. the page nearest focus) among them."""
    idx = set(np.linspace(0, n - 1, min(k, n)).round().astype(int).tolist())
    if include is not None and 0 <= int(include) < n and int(include) not in idx:
        idx.discard(min(idx, key=lambda i: abs(i - int(include))))
        idx.add(int(include))
    return sorted(idx)


def crop_box(xs, ys, shape, margin: int = 40, min_gain: float = 0.5):
    """(r0, r1, c0, c1) around the points (px) plus ``margin``, or the whole frame if that box is not at least
    ``min_gain`` smaller in area (a preview of particles in one corner of a large frame)."""
    H, W = shape
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        return 0, H, 0, W
    r0, r1 = max(int(ys[ok].min()) - margin, 0), min(int(ys[ok].max()) + margin + 1, H)
    c0, c1 = max(int(xs[ok].min()) - margin, 0), min(int(xs[ok].max()) + margin + 1, W)
    if (r1 - r0) * (c1 - c0) > (1 - min_gain) * H * W:
        return 0, H, 0, W
    return r0, r1, c0, c1
