"""MSD and diffusion-coefficient estimators: the public API, now in :mod:`ptrack.motion` (one concern per module).

Kept so that ``from ptrack.msd import estimate_diffusion`` and
``ptrack.msd.pair_diffusion`` keep working; new code may import from
:mod:`ptrack.motion` directly.
"""
from .motion.anomalous import powerlaw_flags
from .motion.bounds import crlb_diffusion, cve_variance
from .motion.cve import cve_from_positions, particle_diffusion
from .motion.diffusion import MIN_PARTICLES_BOOTSTRAP, DiffusionResult, estimate_diffusion
from .motion.drift import drift, subtract_drift
from .motion.fov import resolve_fov
from .motion.msd import ensemble_msd, msd_from_positions, particle_msd
from .motion.ols import START_POINTS, ols_fit, ols_from_positions, optimal_lags
from .motion.pairs import LOG_RHO_OFF, PairDiffusionResult, check_window, pair_diffusion
from .motion.stokes import stokes_einstein
from .motion.synthetic import brownian_field, brownian_tracks
from .motion.tracks import (AXES, DEFAULT_MAX_LAG, axis_components, check_motion_blur, frame_interval, parse_axes,
                            prepare_tracks, resolve_motion_blur)
from .plot import plot_msd

__all__ = ["AXES", "DEFAULT_MAX_LAG", "LOG_RHO_OFF", "MIN_PARTICLES_BOOTSTRAP", "START_POINTS", "DiffusionResult",
           "PairDiffusionResult", "axis_components", "brownian_field", "brownian_tracks", "check_motion_blur",
           "check_window", "crlb_diffusion", "cve_from_positions", "cve_variance", "drift", "ensemble_msd",
           "estimate_diffusion", "frame_interval", "msd_from_positions", "ols_fit", "ols_from_positions",
           "optimal_lags", "pair_diffusion", "parse_axes", "particle_diffusion", "particle_msd", "plot_msd",
           "powerlaw_flags", "prepare_tracks", "resolve_fov", "resolve_motion_blur", "stokes_einstein",
           "subtract_drift"]
