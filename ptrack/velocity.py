"""Drift velocities of tracked particles: the public API, now in :mod:`ptrack.motion.velocity`.

Kept so that ``from ptrack.velocity import particle_velocity`` keeps working.
"""
from .motion.synthetic import drifting_tracks
from .motion.tracks import COMPONENTS
from .motion.velocity import (MIN_FRAMES, ensemble_velocity, instantaneous_velocity, particle_velocity,
                              trim_deposited, velocity_profile)
from .plot import plot_velocity

__all__ = ["COMPONENTS", "MIN_FRAMES", "drifting_tracks", "ensemble_velocity", "instantaneous_velocity",
           "particle_velocity", "plot_velocity", "trim_deposited", "velocity_profile"]
