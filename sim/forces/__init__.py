"""External (single-particle) forces as numba kernels that ADD into a force array.

Every kernel takes contiguous float64 arrays (structure of arrays) and adds
its contribution to ``out`` of shape (N, 3), in newtons, so a caller (the
free-particle integrators of :mod:`sim.integrate`, or the DEM engine) composes
forces by calling the kernels it needs; a new force never touches the
integrator.

- :mod:`sim.forces.drag`: Stokes drag and the seed's piecewise drag law (eq. 3.2-3.5).
- :mod:`sim.forces.body`: gravity with buoyancy (eq. 3.6), Lorentz force (eq. 3.7).
- :mod:`sim.forces.brownian`: Brownian force with fluctuation-dissipation scaling.
"""
from .body import add_constant_force, add_lorentz, gravity_buoyancy_force  # noqa: F401
from .brownian import add_brownian, brownian_std, seed_rng  # noqa: F401
from .drag import (add_drag, add_stokes_drag, drag_factor, drag_force_scalar, max_reynolds,  # noqa: F401
                   reynolds, stokes_gamma)
