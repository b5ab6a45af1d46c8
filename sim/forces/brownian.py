"""Brownian force with fluctuation-dissipation scaling.

For a time step dt each Cartesian component is an independent Gaussian with
zero mean and variance 2 gamma kB T / dt (gamma = 6 pi mu R), held constant
over the step. This is what makes an inertial integrator reproduce
D = kB T / gamma and m <v_i^2> = kB T; the seed's eq. 3.9 has no dt in it and
its eq. 3.32 patches that with a hand-tuned t* = 7 ns, which is wrong except
for one dt. Random numbers come from numba's per-thread generator, seeded by
:func:`seed_rng` (same seed, same numbers on the same thread).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def seed_rng(seed):
    """Seed numba's generator of the calling thread (np.random inside njit code)."""
    np.random.seed(seed)


def brownian_std(gamma, kT, dt) -> np.ndarray:
    """Standard deviation (N) of each Brownian force component: sqrt(2 gamma kB T / dt)."""
    return np.sqrt(2.0 * np.asarray(gamma, dtype=np.float64) * kT / dt)


@njit(cache=True, inline="always")
def brownian_sigma(gamma, kT, dt):
    """Standard deviation (N) of one Brownian force component, sqrt(2 gamma kB T / dt): the one
    implementation, used by every inertial integrator (gamma kg/s, kT J, dt s)."""
    return math.sqrt(2.0 * gamma * kT / dt)


@njit(cache=True)
def add_brownian(gamma, kT, dt, out):
    """Add a Brownian force (variance 2 gamma kT / dt per component) to ``out`` (N, 3).

    gamma (N,) kg/s, kT (J), dt (s). Does nothing (draws nothing) when kT == 0.
    """
    if kT <= 0.0:
        return
    for i in range(out.shape[0]):
        s = brownian_sigma(gamma[i], kT, dt)
        for k in range(3):
            out[i, k] += s * np.random.standard_normal()
