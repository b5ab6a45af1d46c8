"""External (single-particle) forces as numba kernels that ADD into a force array.

Every kernel takes contiguous float64 arrays (structure of arrays) and adds
its contribution to ``out`` of shape (N, 3), in newtons, so a caller composes
forces by calling the kernels it needs.

- :mod:`sim.forces.drag`: Stokes drag and the seed's piecewise drag law (eq. 3.2-3.5).
- :mod:`sim.forces.body`: gravity with buoyancy (eq. 3.6), Lorentz force (eq. 3.7).
- :mod:`sim.forces.brownian`: Brownian force with fluctuation-dissipation scaling.
- :mod:`sim.forces.contact`: contact laws (Hooke/Coulomb, the seed's power law with bonding and
  friction) and the pair and wall kernels.
- :mod:`sim.forces.nearfield`: law tables of the non-contact laws (seed near-field, screened
  Coulomb, van der Waals) and their dispatch.
- :mod:`sim.forces.vdw`: DLVO van der Waals (Hamaker, optionally retarded), one file.

The per-particle laws (``drag_force_scalar``, ``magnetic_force``, ``brownian_sigma``) are the
functions the engines call; the ``add_*`` kernels loop them over particles.
"""
from .body import add_constant_force, add_lorentz, gravity_buoyancy_force, magnetic_force  # noqa: F401
from .brownian import add_brownian, brownian_sigma, brownian_std, seed_rng  # noqa: F401
from .drag import (add_drag, add_stokes_drag, drag_factor, drag_force_scalar, max_reynolds,  # noqa: F401
                   reynolds, stokes_gamma)
