"""Particle detection and sub-pixel localisation: moved to the :mod:`ptrack.image` package.

``ptrack.image.detect`` (knob-free multi-scale detection, noise maps, polarity),
``ptrack.image.peaks`` (single-size matched-filter maxima), ``ptrack.image.fit``
(maximum-likelihood Gaussian fits, Cramer-Rao bounds), ``ptrack.image.radial``
(radial-symmetry centres for rings) and ``ptrack.image.locate`` (one frame:
detect + localise). This module re-exports their public names so that
``ptrack.locate`` keeps working.
"""
from .image.fit import _fit_all, _moments, cramer_rao_bound, fit_spots, mortensen_sigma  # noqa: F401
from .image.locate import (LOCATE_COLUMNS, batch, diameter_to_sigma, estimate_sigma, locate,  # noqa: F401
                           repair_hot_pixels, sigma_to_diameter)
from .image.peaks import _default_separation, detect_raw, find_peaks  # noqa: F401

__all__ = ["find_peaks", "fit_spots", "locate", "batch", "estimate_sigma", "mortensen_sigma", "sigma_to_diameter",
           "diameter_to_sigma", "LOCATE_COLUMNS", "cramer_rao_bound", "detect_raw", "repair_hot_pixels"]
