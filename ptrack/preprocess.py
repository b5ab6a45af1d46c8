"""Image preprocessing (invert, background, threshold, 3x3 median): moved to :mod:`ptrack.image.preprocess`.

This module re-exports it so that ``ptrack.preprocess`` keeps working.
"""
from .image.preprocess import *  # noqa: F401,F403
from .image.preprocess import __all__  # noqa: F401
