"""Synthetic microscope: Fourier-optics PSF (defocus, astigmatism), camera
noise, TIFF movies and defocus calibration stacks with exact ground truth.

Main entry points (SI units throughout)::

    from sim.render import Optics, Camera, render_frames, render_movie, render_calibration

See :mod:`sim.render.optics`, :mod:`sim.render.camera`,
:mod:`sim.render.movie`, :mod:`sim.render.calibration` and
:mod:`sim.render.datasets` (the shipped data in ``data/synthetic``).
"""
import importlib

# name -> submodule; loaded on first use (PEP 562), so `sim.render.options` (the CLI's parsers) does not pull in
# the renderer, numba kernels and FFTs
_WHERE = {
    "Camera": "camera", "expose": "camera",
    "calibration_heights": "calibration", "calibration_images": "calibration", "render_calibration": "calibration",
    "expected_frames": "movie", "frame_interval_of": "movie", "localisation_crlb": "movie", "render_frames": "movie",
    "render_movie": "movie",
    "Optics": "optics", "build_psf_stack": "optics", "otf_planes": "optics", "psf_image": "optics",
    "sample_pixel_size": "optics",
}


def __getattr__(name):
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Optics", "Camera", "expose", "render_frames", "expected_frames", "render_movie", "render_calibration",
    "calibration_heights", "calibration_images", "frame_interval_of", "psf_image", "otf_planes",
    "build_psf_stack", "sample_pixel_size", "localisation_crlb",
]
