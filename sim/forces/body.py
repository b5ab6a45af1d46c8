"""Body forces: gravity with buoyancy (eq. 3.6) and the Lorentz force (eq. 3.7)."""
from __future__ import annotations

import numpy as np
from numba import njit


def gravity_buoyancy_force(mass, radius, rho_f, g) -> np.ndarray:
    """Gravity with buoyancy, F = (m - rho_f 4/3 pi R^3) g, shape (N, 3) in N.

    The seed's eq. 3.6 has m g only; for colloids the buoyancy of the
    displaced fluid is of the same order and is included (pass ``rho_f = 0``
    for no buoyancy). ``g`` is the gravity vector (m/s^2), e.g. (0, 0, -9.80665).
    """
    m_eff = np.asarray(mass, dtype=np.float64) - rho_f * 4.0 / 3.0 * np.pi * np.asarray(radius, dtype=np.float64) ** 3
    return np.ascontiguousarray(m_eff[:, None] * np.asarray(g, dtype=np.float64)[None, :])


@njit(cache=True)
def add_constant_force(fconst, out):
    """Add a precomputed per-particle constant force (N, 3) to ``out``."""
    for i in range(out.shape[0]):
        for k in range(3):
            out[i, k] += fconst[i, k]


@njit(cache=True, inline="always")
def magnetic_force(q, vx, vy, vz, bx, by, bz):
    """Magnetic part of the Lorentz force, q v x B (N): the one implementation, used by every integrator.

    q in C, v in m/s, B in T.
    """
    return q * (vy * bz - vz * by), q * (vz * bx - vx * bz), q * (vx * by - vy * bx)


@njit(cache=True)
def add_lorentz(charge, E, B, vel, out):
    """Add the Lorentz force q (E + v x B) (eq. 3.7) to ``out`` (N, 3).

    charge (N,) in C, E (3,) in V/m, B (3,) in T, vel (N, 3) in m/s.
    The electric part q E is constant and is folded into the engines' constant
    force (:func:`sim.state.constant_force`); the magnetic part is
    :func:`magnetic_force`.
    """
    for i in range(out.shape[0]):
        q = charge[i]
        mx, my, mz = magnetic_force(q, vel[i, 0], vel[i, 1], vel[i, 2], B[0], B[1], B[2])
        out[i, 0] += q * E[0] + mx
        out[i, 1] += q * E[1] + my
        out[i, 2] += q * E[2] + mz
