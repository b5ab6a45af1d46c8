"""ptrack: particle tracking of colloids from microscope TIFF series.

The package turns microscope movies into 3D trajectories and diffusion /
velocity measurements, and shares its trajectories table, MSD estimators and
near-wall hindered-diffusion functions with the simulator in :mod:`sim`.
All public APIs use SI units (m, s, kg, C, V/m, Pa s, K, m^2/s).
"""

__version__ = "0.1.0"

# numba's cache stamps a kernel with its own file only; ours also with the project files it imports
from ._numba_cache import install as _install_numba_cache  # noqa: E402

_install_numba_cache()
