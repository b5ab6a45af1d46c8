"""Near-field (non-contact) pair forces: the seed's power-law attraction/repulsion
and a screened-Coulomb (Yukawa / DLVO double-layer) repulsion.

Both return the *magnitude along n*, where ``n`` is the unit vector from
particle j to particle i: a positive value pushes i away from j (repulsion),
a negative one pulls it toward j (attraction).  Forces are in newtons,
distances in metres.

Models (``model`` codes used by :mod:`sim.forces.contact`):

0. none.
1. Seed eq. 3.24-3.25 (Zohdi): ``F_i = (a1 r^-b1 - a2 r^-b2) n_ij`` with
   ``n_ij`` pointing from i to j and ``a_k = abar_k q_i q_j`` (charge-based
   decomposition).  Parameters ``p = [abar1, abar2, b1, b2, cutoff]``.
   Units: abar_k in N m^b_k / C^2.
2. Screened Coulomb between spheres in the linear-superposition form
   ``U(r) = A a_i a_j exp(-kappa (r - a_i - a_j)) / r`` with
   ``A = 4 pi eps eps0 psi^2`` (psi = surface potential, V); the force is
   ``-dU/dr = U (kappa + 1/r)``.  Parameters ``p = [A, kappa, cutoff]``
   (A in N/m = J/m^2, kappa in 1/m).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

NF_NONE = 0
NF_SEED = 1
NF_YUKAWA = 2


@njit(cache=True, inline="always")
def fast_pow(x, p):
    """x**p with the common small integer exponents done by multiplication."""
    if p == 1.0:
        return x
    if p == 2.0:
        return x * x
    if p == 3.0:
        return x * x * x
    if p == -1.0:
        return 1.0 / x
    if p == -2.0:
        return 1.0 / (x * x)
    return x ** p


@njit(cache=True, inline="always")
def nearfield_magnitude(model, p, r, ri, rj, qi, qj):
    """Force on i along n (from j to i); positive = repulsive.  Zero beyond the cutoff."""
    if model == 1:
        if r >= p[4]:
            return 0.0
        qq = qi * qj
        attraction = p[0] * qq * fast_pow(r, -p[2])
        repulsion = p[1] * qq * fast_pow(r, -p[3])
        # seed: F_i = (attraction - repulsion) n_ij, n_ij = -n
        return repulsion - attraction
    elif model == 2:
        if r >= p[2]:
            return 0.0
        u = p[0] * ri * rj * math.exp(-p[1] * (r - ri - rj)) / r
        return u * (p[1] + 1.0 / r)
    return 0.0


def yukawa_prefactor(eps_r, zeta):
    """``A = 4 pi eps_r eps0 zeta^2`` (N/m) of the screened-Coulomb model 2."""
    from ptrack.constants import VACUUM_PERMITTIVITY

    return 4.0 * np.pi * eps_r * VACUUM_PERMITTIVITY * zeta**2


def nearfield_pair(model, p, r, ri, rj, qi, qj):
    """Python-callable wrapper of :func:`nearfield_magnitude` (for tests)."""
    return nearfield_magnitude(int(model), np.asarray(p, dtype=np.float64), float(r), float(ri),
                               float(rj), float(qi), float(qj))
