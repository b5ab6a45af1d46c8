"""Fluid drag on a sphere: Stokes drag and the seed's piecewise drag law (eq. 3.2-3.5).

Eq. 3.2 writes F = 1/2 C_D pi R^2 rho_f |u| u with u = v_f - v_p and
Re = 2 R rho_f |u| / mu (eq. 3.4). With C_D = 24 / Re (Re <= 1) this is
exactly Stokes drag F = 6 pi mu R u, so the kernels write the force as

    F = gamma * phi(Re) * u,   gamma = 6 pi mu R,   phi(Re) = C_D(Re) Re / 24,

which is the same law without the 0/0 at u = 0 (phi = 1 for Re <= 1). The
piecewise C_D(Re) for Re > 1 comes from :func:`sim.electrokinetics.drag_coefficient_nb`
(one implementation of the seed's table). Callers that know Re stays <= 1
use :func:`add_stokes_drag` and skip the branching altogether.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim.electrokinetics import drag_coefficient_nb as _cd  # the seed's piecewise C_D (eq. 3.5), one implementation


def stokes_gamma(radius, viscosity) -> np.ndarray:
    """Stokes drag coefficient gamma = 6 pi mu R (kg/s) as a contiguous float64 array."""
    return np.ascontiguousarray(6.0 * np.pi * float(viscosity) * np.asarray(radius, dtype=np.float64))


@njit(cache=True)
def drag_factor(re):
    """phi(Re) = C_D(Re) Re / 24: the drag relative to Stokes drag (1 for Re <= 1)."""
    if re <= 1.0:
        return 1.0
    return _cd(re) * re / 24.0


@njit(cache=True)
def reynolds(speed, radius, rho_f, mu):
    """Particle Reynolds number Re = 2 R rho_f |v_f - v_p| / mu (eq. 3.4)."""
    return 2.0 * radius * rho_f * speed / mu


@njit(cache=True)
def drag_force_scalar(ux, uy, uz, radius, rho_f, mu):
    """Drag force (N) of eq. 3.2-3.5 on one sphere for the relative velocity u = v_f - v_p (m/s).

    Returns (fx, fy, fz) = 6 pi mu R phi(Re) u.
    """
    s = math.sqrt(ux * ux + uy * uy + uz * uz)
    g = 6.0 * math.pi * mu * radius * drag_factor(2.0 * radius * rho_f * s / mu)
    return g * ux, g * uy, g * uz


@njit(cache=True)
def add_drag(vel, vf, radius, rho_f, mu, out):
    """Add the piecewise drag (eq. 3.2-3.5) to ``out`` (N, 3).

    Parameters
    ----------
    vel : (N, 3) particle velocities (m/s)
    vf : (3,) uniform fluid velocity (m/s)
    radius : (N,) radii (m)
    rho_f, mu : fluid density (kg/m^3) and viscosity (Pa s)
    out : (N, 3) force array (N), modified in place
    """
    for i in range(vel.shape[0]):
        fx, fy, fz = drag_force_scalar(vf[0] - vel[i, 0], vf[1] - vel[i, 1], vf[2] - vel[i, 2], radius[i], rho_f, mu)
        out[i, 0] += fx
        out[i, 1] += fy
        out[i, 2] += fz


@njit(cache=True)
def add_stokes_drag(vel, vf, gamma, out):
    """Add Stokes drag gamma (v_f - v_p) to ``out`` (N, 3); gamma (N,) in kg/s."""
    for i in range(vel.shape[0]):
        for k in range(3):
            out[i, k] += gamma[i] * (vf[k] - vel[i, k])


@njit(cache=True)
def max_reynolds(vel, vf, radius, rho_f, mu):
    """Largest particle Reynolds number over all particles (uses |v_f - v_p|)."""
    m = 0.0
    for i in range(vel.shape[0]):
        ux = vf[0] - vel[i, 0]
        uy = vf[1] - vel[i, 1]
        uz = vf[2] - vel[i, 2]
        re = 2.0 * radius[i] * rho_f * math.sqrt(ux * ux + uy * uy + uz * uz) / mu
        if re > m:
            m = re
    return m
