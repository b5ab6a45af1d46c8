"""Brownian force with fluctuation-dissipation scaling.

For a time step dt each Cartesian component is an independent Gaussian with
zero mean and variance 2 gamma kB T / dt (gamma = 6 pi mu R), held constant
over the step. This is what makes an inertial integrator reproduce
D = kB T / gamma and m <v_i^2> = kB T; the seed's eq. 3.9 has no dt in it and
its eq. 3.32 patches that with a hand-tuned t* = 7 ns, which is wrong except
for one dt.

Random numbers: :func:`counter_normal`, a counter-based generator keyed by
(seed, step, index) - the one scheme of every integrator (free-particle
kernels, DEM, overdamped with pair forces). Same key, same number, whatever
the order of evaluation, the threads or the split of a run into kernel calls,
so a resumed run draws exactly the numbers of the uninterrupted one (numba's
global generator state cannot be saved). :func:`seed_rng` and
:func:`add_brownian` (numba's generator) remain for the hand tests of
:mod:`sim.forces`.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _mix64(z):
    # splitmix64 finaliser on uint64
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def counter_normal(seed, step, index):
    """Standard normal number keyed by (seed, step, index): same key, same number (Box-Muller on two
    splitmix64 outputs)."""
    key = np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(step) * np.uint64(0xD1B54A32D192ED03) \
        + np.uint64(index) * np.uint64(0x8CB92BA72F3D8DD7)
    a = _mix64(key)
    b = _mix64(a + np.uint64(0x9E3779B97F4A7C15))
    u1 = ((a >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740993.0)  # (0, 1]
    u2 = (b >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


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
