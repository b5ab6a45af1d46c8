"""Near-field (non-contact) pair forces: the seed's power-law attraction/repulsion
and a screened-Coulomb (Yukawa / DLVO double-layer) repulsion.

Both return the *magnitude along n*, where ``n`` is the unit vector from
particle j to particle i: a positive value pushes i away from j (repulsion),
a negative one pulls it toward j (attraction).  Forces are in newtons,
distances in metres.

Laws are composed as a *law table*: a float64 array (L, LAW_WIDTH), one row
per active law, ``row = [code, p0, p1, ...]`` (the law's own parameters,
each law checking its own cut-off). :func:`pair_law_force` and
:func:`wall_law_force` sum the rows; the pair kernel of
:mod:`sim.forces.contact` and the engine call only these two, so a new
non-contact law is one file (its formulas, parameters and scene section,
e.g. :mod:`sim.forces.vdw`) plus one branch per dispatcher below and one
entry in ``sim.interactions.LAW_SECTIONS``; no kernel signature changes.

Codes:

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
3. DLVO van der Waals (Hamaker) attraction, see :mod:`sim.forces.vdw`
   (pairs and the particle-wall plane).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim.forces import vdw

NF_NONE = 0
NF_SEED = 1
NF_YUKAWA = 2
NF_VDW = vdw.CODE
LAW_WIDTH = 8  # code + up to 7 parameters per law row


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
    if model == NF_SEED:
        if r >= p[4]:
            return 0.0
        qq = qi * qj
        attraction = p[0] * qq * fast_pow(r, -p[2])
        repulsion = p[1] * qq * fast_pow(r, -p[3])
        # seed: F_i = (attraction - repulsion) n_ij, n_ij = -n
        return repulsion - attraction
    elif model == NF_YUKAWA:
        if r >= p[2]:
            return 0.0
        u = p[0] * ri * rj * math.exp(-p[1] * (r - ri - rj)) / r
        return u * (p[1] + 1.0 / r)
    elif model == NF_VDW:
        return vdw.pair_force(p, r, ri, rj)
    return 0.0


@njit(cache=True, inline="always")
def pair_law_force(laws, r, ri, rj, qi, qj):
    """Sum over the law table's rows of the pair force on i along n (N); positive = repulsive."""
    f = 0.0
    for k in range(laws.shape[0]):
        f += nearfield_magnitude(int(laws[k, 0]), laws[k, 1:], r, ri, rj, qi, qj)
    return f


MAX_TUPLE_LAWS = 4  # law rows the pair kernel takes as tuples (more rows: the array form)


@njit(cache=True, inline="always")
def _row(laws, k):
    if k >= laws.shape[0]:
        return 0, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return int(laws[k, 0]), (laws[k, 1], laws[k, 2], laws[k, 3], laws[k, 4], laws[k, 5], laws[k, 6], laws[k, 7])


@njit(cache=True, inline="always")
def law_tuples(laws):
    """The first :data:`MAX_TUPLE_LAWS` rows of a law table as ``(codes, params)`` tuples (zero rows
    padded), for :func:`pair_law_force_t`."""
    c0, p0 = _row(laws, 0)
    c1, p1 = _row(laws, 1)
    c2, p2 = _row(laws, 2)
    c3, p3 = _row(laws, 3)
    return (c0, c1, c2, c3), (p0, p1, p2, p3)


@njit(cache=True, inline="always")
def pair_law_force_t(nl, codes, params, r, ri, rj, qi, qj):
    """:func:`pair_law_force` of a table of ``nl <= MAX_TUPLE_LAWS`` rows given by :func:`law_tuples`: the
    same sum in the same order, without array arguments per pair (their reference counting cost more
    than the laws)."""
    f = 0.0
    # a loop over the (homogeneous) tuples: one inlined copy of the laws, not one per row (compile time)
    for k in range(nl):
        f += nearfield_magnitude(codes[k], params[k], r, ri, rj, qi, qj)
    return f


@njit(cache=True, inline="always")
def wall_law_force(laws, d, ri, qi):
    """Sum over the wall-law table of the force (N) along the wall's inward normal on a particle
    of radius ``ri`` whose centre is ``d`` from the plane; positive = away from the wall."""
    f = 0.0
    for k in range(laws.shape[0]):
        if int(laws[k, 0]) == NF_VDW:
            f += vdw.wall_force(laws[k, 1:], d, ri)
    return f


@njit(cache=True)
def wall_law_forces(pos, radius, charge, walls, laws, force):
    """Add the non-contact wall laws of ``laws`` for every particle and wall plane to ``force``.

    ``walls`` (W, 6): a point on the plane and its inward unit normal (as
    :func:`sim.forces.contact.wall_forces`).
    """
    for w in range(walls.shape[0]):
        for i in range(pos.shape[0]):
            d = ((pos[i, 0] - walls[w, 0]) * walls[w, 3] + (pos[i, 1] - walls[w, 1]) * walls[w, 4]
                 + (pos[i, 2] - walls[w, 2]) * walls[w, 5])
            fm = wall_law_force(laws, d, radius[i], charge[i])
            force[i, 0] += fm * walls[w, 3]
            force[i, 1] += fm * walls[w, 4]
            force[i, 2] += fm * walls[w, 5]


def law_row(code, params) -> np.ndarray:
    """One row of a law table: ``[code, *params]`` padded with zeros to LAW_WIDTH."""
    params = np.asarray(params, dtype=np.float64).ravel()
    if params.size > LAW_WIDTH - 1:
        raise ValueError(f"a law has at most {LAW_WIDTH - 1} parameters")
    row = np.zeros(LAW_WIDTH)
    row[0] = code
    row[1:1 + params.size] = params
    return row


def law_table(*rows) -> np.ndarray:
    """Stack law rows into a contiguous (L, LAW_WIDTH) table (L may be 0)."""
    if not rows:
        return np.zeros((0, LAW_WIDTH))
    return np.ascontiguousarray(np.vstack(rows), dtype=np.float64)


def yukawa_prefactor(eps_r, zeta):
    """``A = 4 pi eps_r eps0 zeta^2`` (N/m) of the screened-Coulomb model 2."""
    from ptrack.constants import VACUUM_PERMITTIVITY

    return 4.0 * np.pi * eps_r * VACUUM_PERMITTIVITY * zeta**2


def nearfield_pair(model, p, r, ri, rj, qi, qj):
    """Python-callable wrapper of :func:`nearfield_magnitude` (for tests)."""
    return nearfield_magnitude(int(model), np.asarray(p, dtype=np.float64), float(r), float(ri),
                               float(rj), float(qi), float(qj))


def law_scales(pair_laws, wall_laws, radius, charge, reach=0.2):
    """Largest force (N) and stiffness |dF/dr| (N/m) of the non-contact laws near contact.

    Sampled over gaps from 1e-12 m to ``reach`` radii (log-spaced) for the
    smallest and largest particle radius and the largest charge magnitude,
    pairs and walls; what the engine needs to bound the speed a law can
    drive and the time step it needs, without knowing the law.
    """
    radius = np.asarray(radius, dtype=float)
    q = float(np.max(np.abs(charge), initial=0.0))
    fmax = 0.0
    kmax = 0.0
    for a in {float(radius.min()), float(radius.max())}:
        gaps = np.geomspace(1e-12, reach * a, 600)
        for laws, wall in ((pair_laws, False), (wall_laws, True)):
            if len(laws) == 0:
                continue
            laws = np.ascontiguousarray(laws, dtype=np.float64)
            if wall:
                f = np.array([wall_law_force(laws, a + h, a, q) for h in gaps])
            else:
                f = np.array([pair_law_force(laws, 2 * a + h, a, a, q, q) for h in gaps])
            fmax = max(fmax, float(np.max(np.abs(f))))
            kmax = max(kmax, float(np.max(np.abs(np.diff(f) / np.diff(gaps)))))
    return fmax, kmax
