"""Near-wall hindered diffusion: the public API, now in :mod:`ptrack.motion.wall` (shared with the simulator).

Kept so that ``from ptrack.wall import parallel_ratio_nb`` (sim.integrate) keeps working.
"""
from .motion.wall import (  # noqa: F401
    BLEND_GAP_HIGH,
    BLEND_GAP_LOW,
    BRENNER_ASYMPTOTE_GAP,
    PARALLEL_METHODS,
    PERPENDICULAR_METHODS,
    faxen_ratio_derivative_nb,
    faxen_ratio_nb,
    height_from_ratio,
    hindered_D,
    lubrication_ratio_derivative_nb,
    lubrication_ratio_nb,
    parallel_ratio,
    parallel_ratio_and_derivative_nb,
    parallel_ratio_derivative,
    parallel_ratio_derivative_nb,
    parallel_ratio_nb,
    perpendicular_ratio,
    perpendicular_ratio_and_derivative_nb,
    perpendicular_ratio_bp_derivative_nb,
    perpendicular_ratio_bp_nb,
    perpendicular_ratio_derivative,
    perpendicular_ratio_derivative_nb,
    perpendicular_ratio_fast_and_derivative_nb,
    perpendicular_ratio_fast_derivative_nb,
    perpendicular_ratio_fast_nb,
    perpendicular_ratio_nb,
    perpendicular_ratio_series_and_derivative_nb,
    perpendicular_ratio_series_derivative_nb,
    perpendicular_ratio_series_nb,
    unhindered_D,
)

__all__ = ["BLEND_GAP_HIGH", "BLEND_GAP_LOW", "BRENNER_ASYMPTOTE_GAP", "PARALLEL_METHODS", "PERPENDICULAR_METHODS", "faxen_ratio_derivative_nb", "faxen_ratio_nb", "height_from_ratio", "hindered_D", "lubrication_ratio_derivative_nb", "lubrication_ratio_nb", "parallel_ratio", "parallel_ratio_and_derivative_nb", "parallel_ratio_derivative", "parallel_ratio_derivative_nb", "parallel_ratio_nb", "perpendicular_ratio", "perpendicular_ratio_and_derivative_nb", "perpendicular_ratio_bp_derivative_nb", "perpendicular_ratio_bp_nb", "perpendicular_ratio_derivative", "perpendicular_ratio_derivative_nb", "perpendicular_ratio_fast_and_derivative_nb", "perpendicular_ratio_fast_derivative_nb", "perpendicular_ratio_fast_nb", "perpendicular_ratio_nb", "perpendicular_ratio_series_and_derivative_nb", "perpendicular_ratio_series_derivative_nb", "perpendicular_ratio_series_nb", "unhindered_D"]
