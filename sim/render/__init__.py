"""Synthetic microscope: Fourier-optics PSF (defocus, astigmatism), camera
noise, TIFF movies and defocus calibration stacks with exact ground truth.

Main entry points (SI units throughout)::

    from sim.render import Optics, Camera, render_frames, render_movie, render_calibration

See :mod:`sim.render.optics`, :mod:`sim.render.camera`,
:mod:`sim.render.movie`, :mod:`sim.render.calibration` and
:mod:`sim.render.datasets` (the shipped data in ``data/synthetic``).
"""
from .camera import Camera, expose
from .calibration import calibration_heights, calibration_images, render_calibration
from .movie import expected_frames, frame_interval_of, localisation_crlb, render_frames, render_movie
from .optics import Optics, build_psf_stack, otf_planes, psf_image, sample_pixel_size

__all__ = [
    "Optics", "Camera", "expose", "render_frames", "expected_frames", "render_movie", "render_calibration",
    "calibration_heights", "calibration_images", "frame_interval_of", "psf_image", "otf_planes",
    "build_psf_stack", "sample_pixel_size", "localisation_crlb",
]
