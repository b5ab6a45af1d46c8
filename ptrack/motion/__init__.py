"""Motion analysis of trajectories tables: MSD, diffusion coefficients, drift, velocities, wall-hindered diffusion.

Shared by the image pipeline (measured tracks) and the simulator (simulated
tracks); SI units everywhere (m, s, m^2/s). One concern per module:

=============  ==============================================================
tracks         axes, frame interval, motion blur, sorting a table (one rule each)
msd            MSD tables (per particle, ensemble) and array fast paths
cve            covariance-based estimator (Vestergaard et al. 2014)
ols            least squares over the optimal number of lags (Michalet 2010)
diffusion      :func:`estimate_diffusion`: D per axis with standard errors
bounds         closed-form CVE variance, Cramer-Rao bound
fov            field-of-view correction
drift          ensemble drift and its (1 - 1/M) bias correction
anomalous      flags for non-diffusive tracks
pairs          linking-free D (:func:`pair_diffusion`)
velocity       drift velocities (GLS per track, ensemble, profile in z)
wall           hindered diffusion near a wall (shared with the simulator)
stokes         Stokes-Einstein
synthetic      tracks with known statistics for tests and benchmarks
truth          matching found particles to a ground truth
=============  ==============================================================

Examples
--------
>>> from ptrack.motion import brownian_field, estimate_diffusion
>>> df = brownian_field(n_frames=60, size=40e-6, density=0.05e12, D=1e-12, dt=0.1, seed=1)
>>> res = estimate_diffusion(df, axes="xy", motion_blur=0.0, field_of_view="auto")
>>> abs(res.D["xy"] / 1e-12 - 1) < 4 * res.D_err["xy"] / 1e-12
True
"""
from .anomalous import powerlaw_flags
from .bounds import crlb_diffusion, cve_variance
from .cve import cve_from_positions, particle_diffusion
from .diffusion import MIN_PARTICLES_BOOTSTRAP, DiffusionResult, estimate_diffusion
from .msd import ensemble_msd, msd_from_positions, particle_msd
from .ols import ols_from_positions, optimal_lags
from .pairs import PairDiffusionResult, pair_diffusion
from .stokes import stokes_einstein
from .synthetic import brownian_field, brownian_tracks, drifting_tracks
from .tracks import AXES, axis_components, check_motion_blur, frame_interval, parse_axes, resolve_motion_blur
from .truth import match_truth
from .velocity import ensemble_velocity, particle_velocity, trim_deposited, velocity_profile
from .wall import height_from_ratio, hindered_D, parallel_ratio, perpendicular_ratio, unhindered_D

__all__ = ["AXES", "MIN_PARTICLES_BOOTSTRAP", "DiffusionResult", "PairDiffusionResult", "axis_components",
           "brownian_field", "brownian_tracks", "check_motion_blur", "crlb_diffusion", "cve_from_positions",
           "cve_variance", "drifting_tracks", "ensemble_msd", "estimate_diffusion", "frame_interval",
           "msd_from_positions", "ols_from_positions", "optimal_lags", "pair_diffusion", "parse_axes",
           "particle_diffusion", "particle_msd", "powerlaw_flags", "resolve_motion_blur", "stokes_einstein",
           "match_truth", "ensemble_velocity", "particle_velocity", "trim_deposited", "velocity_profile",
           "height_from_ratio", "hindered_D", "parallel_ratio", "perpendicular_ratio", "unhindered_D"]
