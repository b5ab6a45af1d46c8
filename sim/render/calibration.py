"""Defocus calibration stacks: one particle stepped through z, as for GDPT.

The seed (chapter 4) made its stacks by hand: a particle near the slide,
the stage moved in 2 um steps from where the Airy disk just disappears above
focus to where it disappears below (about 60 images). :func:`render_calibration`
renders the same thing with exact z: a particle at the centre of the frame at
heights ``z_min, z_min + z_step, ... <= z_max`` (defocus ``z - focal_plane``),
one TIFF page per height, each page exact in z (no interpolation between PSF
planes), with the camera noise of :mod:`sim.render.camera`.

Note that with the default NA 0.75 objective the geometric blur grows by
``tan(asin(NA / n))`` = 0.68 um per um of defocus, so at 60 um from focus the
light of the particle is spread over a disk about 800 pixels across and
practically vanishes in a 64 x 64 crop: the useful range of a high-NA
objective is a few um, not the +-60 um of the seed's stage scan. The defaults
(:data:`DEFAULT_Z_RANGE`, :data:`DEFAULT_Z_STEP`; ``ptrack render-calibration``
adds :data:`DEFAULT_ASTIGMATISM`) give a stack in which every page shows the
bead with the default optics and camera and z is read to tens of nm between
pages. For the z range of a real measurement choose ``z_min, z_max, z_step``
accordingly (see data/synthetic/diffusion3d).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ptrack.errors import UserError, atomic_output, check_positive, output_dir
from ptrack.table import to_jsonable

from .camera import Camera, expose
from .movie import _add_patches
from .optics import Optics, check_sampling, otf_planes, patch_size, sample_pixel_size, size_transfer

__all__ = ["render_calibration", "calibration_heights", "page_shape_for", "image_diameter_px", "DEFAULT_Z_RANGE",
           "DEFAULT_Z_STEP", "DEFAULT_ASTIGMATISM", "DEFAULT_PHOTONS"]

# Defaults of a calibration stack (m). +-3 um: at NA 0.75 the image of a 5000-photon particle spreads into the noise
# beyond about +-5 um of defocus (0.68 um of blur radius per um); 0.1 um steps: z between pages to a few tens of nm
# (2 um steps, interpolated: errors of 0.45 um). DEFAULT_ASTIGMATISM, the wavefront at the pupil edge (about 0.23
# waves at 519 nm) of ``ptrack render-calibration``: without astigmatism +z and -z pages look alike and the sign of
# z is undefined (the movie must be rendered with the same value). DEFAULT_PHOTONS, per page: 4x a default movie
# frame's (Camera().photons), a few frames averaged per height as a careful calibration does (the noise of a
# 5000-photon template biased z by 0.16 um and x by 0.45 px at 2.6 um of defocus; 20000: 10 nm, 0.1 px).
DEFAULT_Z_RANGE = (-3e-6, 3e-6)
DEFAULT_Z_STEP = 1e-7
DEFAULT_ASTIGMATISM = 1.2e-7
DEFAULT_PHOTONS = 20000.0


def calibration_heights(z_min: float, z_max: float, z_step: float) -> np.ndarray:
    """Heights ``z_min + k z_step`` for k = 0, 1, ... up to ``z_max`` (inclusive within 1e-9 of a step), m."""
    for name, v in (("z_min", z_min), ("z_max", z_max)):
        if not math.isfinite(float(v)):
            raise UserError(f"{name} = {v!r} is not finite", "give heights in m")
    check_positive("z_step", z_step)
    if z_max < z_min:
        raise UserError(f"z_max = {z_max} is below z_min = {z_min}", "give z_min <= z_max")
    n = int(math.floor((z_max - z_min) / z_step + 1e-9)) + 1
    if n > 100000:
        raise UserError(f"{n} calibration planes from z_step = {z_step}", "use a larger z_step")
    return z_min + z_step * np.arange(n)


def calibration_images(z, shape=(64, 64), optics: Optics | None = None, camera: Camera | None = None,
                       focal_plane: float = 0.0, radius: float = 0.0, position=None, brightfield=False,
                       noise: bool = True, seed=0, scatter_phase: float = 2.5):
    """Yield one calibration image per height in ``z`` (uint16 if ``noise``, else expected photons as float64).

    ``position``: (x_px, y_px) of the particle; default the frame centre
    ``((W - 1) / 2, (H - 1) / 2)`` rounded down to a whole pixel.
    ``brightfield``, ``scatter_phase``: as in :func:`sim.render.render_frames`.
    """
    from .movie import _brightfield_mode

    mode = _brightfield_mode(brightfield)
    optics = optics or Optics()
    camera = camera or Camera()
    H, W = (int(v) for v in shape)
    if H < 1 or W < 1:
        raise UserError(f"shape = {shape!r} is out of range", "give positive height and width in pixels")
    pixel = sample_pixel_size(optics, camera.pixel_pitch)
    check_sampling(optics, pixel)
    x_px, y_px = position if position is not None else (float((W - 1) // 2), float((H - 1) // 2))
    z = np.asarray(z, dtype=float)
    dz = z - float(focal_plane)
    if optics.field_dependent:  # the bead's place on a curved / tilted focal surface (Optics.focal_shift)
        dz = dz - optics.focal_shift(x_px * pixel, y_px * pixel, ((W - 1) / 2 * pixel, (H - 1) / 2 * pixel))
    n = patch_size(optics, pixel, float(np.max(np.abs(dz))) if dz.size else 0.0, radius)
    # a patch far larger than the frame is only needed to keep the PSF from wrapping onto itself;
    # the frame sees the central H x W part.
    c = n // 2
    ix, iy = int(round(x_px)), int(round(y_px))
    fy = np.fft.fftfreq(n)
    fx = np.fft.rfftfreq(n)
    ramp = np.exp(-2j * np.pi * fy[:, None] * (c + y_px - iy)) * np.exp(-2j * np.pi * fx[None, :] * (c + x_px - ix))
    if radius > 0:
        f = np.fft.fftfreq(n, d=pixel)
        r = np.fft.rfftfreq(n, d=pixel)
        ramp = ramp * size_transfer(np.sqrt(f[:, None] ** 2 + r[None, :] ** 2), radius)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    import scipy.fft as sfft

    if mode == "coherent" and not camera.background > 0:
        raise UserError("coherent brightfield needs a bright field: camera.background = 0",
                        "give the illumination as background photons per pixel (> 0)")
    for d in dz:
        if mode == "coherent":
            o, re, im = otf_planes(optics, pixel, n, [d], field=True)
            mag = 2.0 * np.sqrt(camera.background * camera.photons)
            otf = (o[0] * camera.photons + re[0] * mag * np.cos(scatter_phase) - im[0] * mag * np.sin(scatter_phase)) * ramp
        else:
            otf = otf_planes(optics, pixel, n, [d])[0] * ramp * camera.photons
        pat = sfft.irfft2(otf, s=(n, n), workers=1)
        img = np.full((H, W), float(camera.background))
        _add_patches(img, pat[None], np.array([iy - c]), np.array([ix - c]), -1.0 if mode == "absorption" else 1.0)
        if mode != "fluorescence":
            np.maximum(img, 0.0, out=img)
        yield expose(img, camera, rng) if noise else img


def _with_bar(gen, total):
    from tqdm import tqdm

    with tqdm(total=total, desc="calibration", unit="plane", leave=False) as bar:
        for item in gen:
            yield item
            bar.update(1)


MAX_AUTO_PAGE = 512     # px: default pages are sized to the image at the largest defocus, up to this


def image_diameter_px(optics: Optics, pixel: float, defocus: float, radius: float = 0.0) -> float:
    """Diameter (px) holding the particle image at ``defocus`` (m): geometric blur, line foci, 3 Airy radii."""
    r = (abs(defocus) + optics.line_focus_offset) * optics.half_angle_tan + 3.0 * optics.airy_radius + radius
    return 2.0 * r / pixel


def page_shape_for(z, optics: Optics, camera: Camera, focal_plane: float = 0.0, radius: float = 0.0, shape=None):
    """Page shape for a calibration stack: ``shape`` if given, else one that holds the image at the largest
    defocus (even, at most :data:`MAX_AUTO_PAGE` px). Warns naming the heights whose image the page cuts."""
    import warnings

    pixel = sample_pixel_size(optics, camera.pixel_pitch)
    dz = np.abs(np.asarray(z, float) - float(focal_plane))
    need = image_diameter_px(optics, pixel, float(dz.max()), radius)
    if shape is None:
        n = int(min(MAX_AUTO_PAGE, max(32, 2 * math.ceil(need / 2 + 4))))
        shape = (n, n)
    H, W = (int(v) for v in shape)
    fits = np.array([image_diameter_px(optics, pixel, d, radius) <= min(H, W) for d in dz])
    if not fits.all():
        lim = float(dz[fits].max()) if fits.any() else 0.0
        warnings.warn(f"calibration pages of {H} x {W} px cut the particle image beyond {lim * 1e6:.3g} µm of "
                      f"defocus ({int((~fits).sum())} of {len(dz)} pages; the image is {need:.0f} px across at "
                      f"{dz.max() * 1e6:.3g} µm): those pages will be rejected by the calibration",
                      stacklevel=3)
    return H, W


def render_calibration(out_dir, z_min: float = DEFAULT_Z_RANGE[0], z_max: float = DEFAULT_Z_RANGE[1],
                       z_step: float = DEFAULT_Z_STEP, shape=None,
                       optics: Optics | None = None, camera: Camera | None = None, focal_plane: float = 0.0,
                       radius: float = 0.0, position=None, brightfield=False, seed=0,
                       compression: str | None = None, progress: bool = True, scatter_phase: float = 2.5) -> dict:
    """Write a defocus calibration stack: ``out_dir/calib.tif`` and ``out_dir/calib_z.csv``.

    Parameters
    ----------
    out_dir : path
    z_min, z_max, z_step : float
        Particle heights, m (defocus = z - focal_plane). Defaults: +-3 um in
        0.1 um steps (every page shows the bead at the default optics and
        camera; the seed's stage scan was +-60 um in 2 um steps).
    shape : (int, int), optional
        Page height and width, pixels; default: the image at the largest
        defocus fits (:func:`page_shape_for`, up to 512 px; a warning names
        the heights a page cuts).
    optics, camera : Optics, Camera
        Default ``Optics(astigmatism=DEFAULT_ASTIGMATISM)`` (1.2e-7 m: the
        sign of z is defined; render the movie with the same) and
        ``Camera(photons=DEFAULT_PHOTONS)`` (20000 per page).
    focal_plane : float
        m.
    radius : float
        Particle radius, m.
    position : (x_px, y_px), optional
        Particle position in the page (default: the centre pixel).
    brightfield : bool or str
        As in :func:`sim.render.render_frames` (False, True/'absorption', 'coherent').
    scatter_phase : float
        rad, coherent brightfield only.
    seed : int or Generator
    compression : str, optional
        e.g. ``"zlib"``.

    Returns
    -------
    dict with paths ``stack`` (calib.tif), ``z`` (calib_z.csv: columns page, z in m),
    ``params`` (calib_params.json).
    """
    import tifffile

    z = calibration_heights(z_min, z_max, z_step)
    optics = optics or Optics(astigmatism=DEFAULT_ASTIGMATISM)
    camera = camera or Camera(photons=DEFAULT_PHOTONS)
    check_positive("radius", radius, allow_zero=True)
    H, W = page_shape_for(z, optics, camera, focal_plane, radius, shape)
    pixel = sample_pixel_size(optics, camera.pixel_pitch)
    if position is None:
        position = (float((W - 1) // 2), float((H - 1) // 2))
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"output path {out_dir} exists and is not a directory", "give a directory for --out")
    info = {
        "pixel_size": pixel, "pixel_size_unit": "m", "z_step": float(z_step), "z_min": float(z[0]),
        "z_max": float(z[-1]), "z_unit": "m", "focal_plane": float(focal_plane), "x_px": position[0],
        "y_px": position[1], "source": "sim.render.render_calibration",
    }
    gen = calibration_images(z, (H, W), optics, camera, focal_plane, radius, position, brightfield, True, seed,
                             scatter_phase)
    if progress:
        gen = _with_bar(gen, len(z))
    # a folder made here is removed again, with what was written into it, if any write fails (a full disk)
    with output_dir(out_dir, "--out", all_or_nothing=True):
        px_um = pixel * 1e6
        stack = out_dir / "calib.tif"
        with atomic_output(stack, None) as tmp:
            tifffile.imwrite(
                tmp, gen, shape=(len(z), H, W), dtype=np.uint16, imagej=True, compression=compression,
                resolution=(1.0 / px_um, 1.0 / px_um),
                metadata={"axes": "ZYX", "unit": "um", "spacing": float(z_step) * 1e6, "Info": json.dumps(info)},
            )
        zpath = out_dir / "calib_z.csv"
        with atomic_output(zpath, "w") as fh:
            fh.write("page,z\n")
            for i, zi in enumerate(z):
                fh.write(f"{i},{float(zi)!r}\n")
        params = {**info, "n_planes": len(z), "shape": [H, W], "radius": radius, "brightfield": str(brightfield) if brightfield else False,
                  "scatter_phase": scatter_phase if brightfield == "coherent" else None,
                  "seed": seed if not isinstance(seed, np.random.Generator) else None,
                  "optics": optics.to_dict(), "camera": camera.to_dict(), "compression": compression}
        ppath = out_dir / "calib_params.json"
        with atomic_output(ppath, "w") as fh:
            json.dump(to_jsonable(params), fh, indent=2, sort_keys=True)
            fh.write("\n")
        return {"stack": stack, "z": zpath, "params": ppath}
