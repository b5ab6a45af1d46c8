"""DLVO van der Waals attraction (Hamaker), between spheres and between a sphere and a plane wall.

The whole law in one file: the formulas (numba), the parameter row and the
``[vdw]`` scene section. The engine reaches it only through the law tables
of :mod:`sim.forces.nearfield` (code ``NF_VDW``).

Non-retarded (Hamaker 1937), exact for any gap, in the closed form of
``F = -dU/dr``:

* sphere-sphere, radii a1, a2, centre distance r, s = r^2::

      U = -A/6 [2 a1 a2 / (s - (a1+a2)^2) + 2 a1 a2 / (s - (a1-a2)^2)
                + ln((s - (a1+a2)^2) / (s - (a1-a2)^2))]
      F = -(32/3) A a1^3 a2^3 r / ((s - (a1+a2)^2)^2 (s - (a1-a2)^2)^2)

  (negative = attraction along n from j to i); at a small gap h it tends to
  the Derjaguin force -A a_eff / (6 h^2), a_eff = a1 a2 / (a1 + a2), at a
  large distance to the London tail -(32/3) A a1^3 a2^3 / r^7;
* sphere-plate, radius a, gap h = d - a (d: centre-to-plane distance)::

      U = -A/6 [a/h + a/(h + 2a) + ln(h / (h + 2a))]
      F = -2 A a^3 / (3 h^2 (h + 2a)^2).

Retarded (optional, ``wavelength`` lambda > 0): Gregory's (1981) form of
the Derjaguin energy, U = -A a_eff / (6 h) [1 - (b h / lambda) ln(1 + lambda / (b h))],
b = 5.32, whose force is the Derjaguin force times lambda / (lambda + b h).
It is written here as the exact non-retarded force times that factor, which
is Gregory's force for h << a (where retardation matters) and tends to the
exact Hamaker force as lambda -> infinity. (Gregory's expression is a
small-gap approximation; no closed form covers a retarded sphere at any gap.)

The force diverges at contact; below ``min_gap`` (default 0.4 nm, about the
Born-repulsion distance) the gap is held at ``min_gap``, so overlapping
spheres (the contact law acts there) feel a finite, constant attraction.
Beyond the cut-off gap ``cutoff_gap`` the law is zero (scene default: two
particle radii, where the pair force is ~0.3 % of its value at a gap of a
tenth of a radius).

Parameter row (after the code): ``[A, wall_A, min_gap, cutoff_gap, wavelength]``
with A the particle-particle and wall_A the particle-wall Hamaker constant (J).
"""
from __future__ import annotations

import numpy as np
from numba import njit

SECTION = "vdw"
CODE = 3      # law code in the tables of sim.forces.nearfield
WALL = True   # also acts between a particle and the wall planes
KEYS = ("hamaker", "wall_hamaker", "min_gap", "cutoff_gap", "wavelength")
GREGORY_B = 5.32  # Gregory (1981), J. Colloid Interface Sci. 83, 138
I_A, I_WALL_A, I_MIN_GAP, I_CUTOFF_GAP, I_WAVELENGTH = 0, 1, 2, 3, 4


@njit(cache=True, inline="always")
def _retardation(p, h):
    lam = p[I_WAVELENGTH]
    if lam > 0.0:
        return lam / (lam + GREGORY_B * h)
    return 1.0


@njit(cache=True)
def pair_force(p, r, ri, rj):
    """Hamaker force (N) on sphere i along n (from j to i) at centre distance r (m); negative = attractive."""
    h = r - ri - rj
    if h >= p[I_CUTOFF_GAP] or p[I_A] == 0.0:
        return 0.0
    if h < p[I_MIN_GAP]:
        h = p[I_MIN_GAP]
        r = ri + rj + h
    s = r * r
    dp = s - (ri + rj) * (ri + rj)
    dm = s - (ri - rj) * (ri - rj)
    f = -(32.0 / 3.0) * p[I_A] * (ri * rj) ** 3 * r / (dp * dp * dm * dm)
    return f * _retardation(p, h)


@njit(cache=True)
def wall_force(p, d, ri):
    """Hamaker force (N) on a sphere of radius ri whose centre is d (m) from a plane, along the
    plane's inward normal; negative = toward the wall."""
    h = d - ri
    if h >= p[I_CUTOFF_GAP] or p[I_WALL_A] == 0.0:
        return 0.0
    if h < p[I_MIN_GAP]:
        h = p[I_MIN_GAP]
    q = h + 2.0 * ri
    return -2.0 * p[I_WALL_A] * ri ** 3 / (3.0 * h * h * q * q) * _retardation(p, h)


def pair_energy(A, r, a1, a2):
    """Non-retarded Hamaker energy (J) of two spheres at centre distance r (vectorised; for tests)."""
    s = np.asarray(r, dtype=float) ** 2
    dp = s - (a1 + a2) ** 2
    dm = s - (a1 - a2) ** 2
    return -A / 6.0 * (2 * a1 * a2 / dp + 2 * a1 * a2 / dm + np.log(dp / dm))


def wall_energy(A, h, a):
    """Non-retarded Hamaker energy (J) of a sphere at gap h from a plane (vectorised; for tests)."""
    h = np.asarray(h, dtype=float)
    return -A / 6.0 * (a / h + a / (h + 2 * a) + np.log(h / (h + 2 * a)))


def gregory_energy(A, h, a_eff, wavelength):
    """Gregory's retarded Derjaguin energy (J) at gap h (vectorised; for tests)."""
    h = np.asarray(h, dtype=float)
    x = GREGORY_B * h / wavelength
    return -A * a_eff / (6.0 * h) * (1.0 - x * np.log(1.0 + 1.0 / x))


def params(A, wall_A=None, min_gap=4e-10, cutoff_gap=np.inf, wavelength=0.0) -> np.ndarray:
    """Parameter row (without the code) of :func:`pair_force`/:func:`wall_force`."""
    return np.array([A, A if wall_A is None else wall_A, min_gap, cutoff_gap, wavelength], dtype=np.float64)


def parse_section(sec: dict, scene=None):
    """Validate the ``[vdw]`` scene section.

    Keys (SI): ``hamaker`` A (J, required, e.g. 1e-20 for polystyrene in
    water), ``wall_hamaker`` (J, default A), ``min_gap`` (m, default 4e-10),
    ``cutoff_gap`` (m, surface-to-surface; default 2 largest particle radii),
    ``wavelength`` (m, 0 = non-retarded; ~1e-7 m for Gregory's retardation).

    Returns
    -------
    params : ndarray
        The law's parameter row.
    reach : float
        Largest centre-to-centre distance (m) at which the law acts (for the
        neighbour list).
    """
    from sim.validate import missing, number

    A = number(SECTION, "hamaker", sec["hamaker"] if "hamaker" in sec else missing(SECTION, "hamaker"), nonneg=True)
    wall_A = number(SECTION, "wall_hamaker", sec.get("wall_hamaker", A), nonneg=True)
    min_gap = number(SECTION, "min_gap", sec.get("min_gap", 4e-10), positive=True)
    rmax = 1.0
    if scene is not None:
        rmax = scene.particles.radius * (1 + scene.particles.radius_variation)
    cut = number(SECTION, "cutoff_gap", sec.get("cutoff_gap", 2.0 * rmax), positive=True)
    lam = number(SECTION, "wavelength", sec.get("wavelength", 0.0), nonneg=True)
    return params(A, wall_A, min_gap, cut, lam), 2.0 * rmax + cut
