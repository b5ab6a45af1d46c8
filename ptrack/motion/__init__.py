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
# Submodules load on first use (PEP 562): `import ptrack.motion.wall` (the simulator's import) stays light.
_WHERE = {
    "powerlaw_flags": "anomalous",
    "crlb_diffusion": "bounds",
    "cve_variance": "bounds",
    "cve_from_positions": "cve",
    "particle_diffusion": "cve",
    "MIN_PARTICLES_BOOTSTRAP": "diffusion",
    "DiffusionResult": "diffusion",
    "estimate_diffusion": "diffusion",
    "ensemble_msd": "msd",
    "msd_from_positions": "msd",
    "particle_msd": "msd",
    "ols_from_positions": "ols",
    "optimal_lags": "ols",
    "PairDiffusionResult": "pairs",
    "pair_diffusion": "pairs",
    "stokes_einstein": "stokes",
    "brownian_field": "synthetic",
    "brownian_tracks": "synthetic",
    "drifting_tracks": "synthetic",
    "AXES": "tracks",
    "axis_components": "tracks",
    "check_motion_blur": "tracks",
    "frame_interval": "tracks",
    "parse_axes": "tracks",
    "resolve_motion_blur": "tracks",
    "motion_blur_from_data": "tracks",
    "match_truth": "truth",
    "detection_scores": "truth",
    "ensemble_velocity": "velocity",
    "particle_velocity": "velocity",
    "default_axes": "velocity",
    "trim_deposited": "velocity",
    "velocity_profile": "velocity",
    "height_from_ratio": "wall",
    "hindered_D": "wall",
    "parallel_ratio": "wall",
    "wall_evidence": "wall",
    "perpendicular_ratio": "wall",
    "unhindered_D": "wall",
}


def __getattr__(name):
    if name in _WHERE:
        import importlib

        value = getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_WHERE))


__all__ = ["AXES", "MIN_PARTICLES_BOOTSTRAP", "DiffusionResult", "PairDiffusionResult", "axis_components",
           "brownian_field", "brownian_tracks", "check_motion_blur", "crlb_diffusion", "cve_from_positions",
           "cve_variance", "drifting_tracks", "ensemble_msd", "estimate_diffusion", "frame_interval",
           "msd_from_positions", "ols_from_positions", "optimal_lags", "pair_diffusion", "parse_axes",
           "particle_diffusion", "particle_msd", "powerlaw_flags", "resolve_motion_blur", "motion_blur_from_data", "stokes_einstein",
           "match_truth", "detection_scores", "ensemble_velocity", "particle_velocity", "default_axes", "trim_deposited", "velocity_profile",
           "height_from_ratio", "hindered_D", "parallel_ratio", "wall_evidence", "perpendicular_ratio", "unhindered_D"]
