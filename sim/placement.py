"""Initial particle positions: sequential random non-overlapping placement (seed section 3.3.3).

Radii follow eq. 3.39, R_i = R (1 + alpha c_i) with c_i uniform in [-1, 1].
Particles are placed one after the other at uniformly random positions inside
the box, a candidate being rejected if it overlaps one already placed. The
overlap test looks only at the neighbouring cells of a uniform cell hash
(cell size >= the largest diameter), so placing 10^5 particles costs O(N)
tests per attempt, not O(N^2).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ptrack.errors import UserError


@njit(cache=True)
def _place_kernel(seed, radius, lo, hi, ncell, cell, max_attempts):
    """Place particles sequentially with numba's generator seeded by ``seed``.

    Returns (pos, n_placed). Cell linked lists: head per cell, next per particle.
    """
    np.random.seed(seed)
    n = radius.shape[0]
    pos = np.empty((n, 3))
    head = -np.ones(ncell[0] * ncell[1] * ncell[2], dtype=np.int64)
    nxt = -np.ones(n, dtype=np.int64)
    rmax = 0.0
    for i in range(n):
        if radius[i] > rmax:
            rmax = radius[i]
    reach = np.empty(3, dtype=np.int64)
    for i in range(n):
        r = radius[i]
        placed = False
        for a in range(max_attempts):
            p0 = lo[0] + r + np.random.random() * (hi[0] - lo[0] - 2 * r)
            p1 = lo[1] + r + np.random.random() * (hi[1] - lo[1] - 2 * r)
            p2 = lo[2] + r + np.random.random() * (hi[2] - lo[2] - 2 * r)
            c0 = min(int((p0 - lo[0]) / cell[0]), ncell[0] - 1)
            c1 = min(int((p1 - lo[1]) / cell[1]), ncell[1] - 1)
            c2 = min(int((p2 - lo[2]) / cell[2]), ncell[2] - 1)
            for d in range(3):
                reach[d] = int(np.ceil((r + rmax) / cell[d]))
            ok = True
            for a0 in range(max(c0 - reach[0], 0), min(c0 + reach[0], ncell[0] - 1) + 1):
                if not ok:
                    break
                for a1 in range(max(c1 - reach[1], 0), min(c1 + reach[1], ncell[1] - 1) + 1):
                    if not ok:
                        break
                    for a2 in range(max(c2 - reach[2], 0), min(c2 + reach[2], ncell[2] - 1) + 1):
                        j = head[(a0 * ncell[1] + a1) * ncell[2] + a2]
                        while j >= 0:
                            dx = p0 - pos[j, 0]
                            dy = p1 - pos[j, 1]
                            dz = p2 - pos[j, 2]
                            s = r + radius[j]
                            if dx * dx + dy * dy + dz * dz < s * s:
                                ok = False
                                break
                            j = nxt[j]
                        if not ok:
                            break
            if ok:
                pos[i, 0] = p0
                pos[i, 1] = p1
                pos[i, 2] = p2
                c = (c0 * ncell[1] + c1) * ncell[2] + c2
                nxt[i] = head[c]
                head[c] = i
                placed = True
                break
        if not placed:
            return pos, i
    return pos, n


def particle_radii(n: int, mean_radius: float, alpha: float, seed=None) -> np.ndarray:
    """Radii of eq. 3.39: R_i = R (1 + alpha c_i), c_i uniform in [-1, 1] (m)."""
    rng = np.random.default_rng(seed)
    if alpha == 0:
        return np.full(n, float(mean_radius))
    return np.ascontiguousarray(mean_radius * (1.0 + alpha * rng.uniform(-1.0, 1.0, n)))


def place_particles(n: int, mean_radius: float, alpha: float, lo, hi, seed=None, max_attempts: int = 100_000):
    """Sequential random non-overlapping placement of n spheres in the box [lo, hi].

    Parameters
    ----------
    n : int
        Number of particles.
    mean_radius : float
        Mean radius R (m).
    alpha : float
        Radius variation alpha_Rad of eq. 3.39 (0 = monodisperse).
    lo, hi : sequence of 3 floats
        Box corners (m); every sphere lies entirely inside.
    seed : int or numpy.random.Generator, optional
        Same seed, same positions.
    max_attempts : int
        Random candidates tried per particle before giving up (the acceptance
        rate falls towards the random-sequential-addition limit, ~0.38).

    Returns
    -------
    pos : (n, 3) float64 array (m)
    radius : (n,) float64 array (m)

    Raises
    ------
    UserError
        The box is too small or too crowded to place all particles.
    """
    rng = np.random.default_rng(seed)
    radius = particle_radii(n, mean_radius, alpha, rng)
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    rmax = float(radius.max())
    if np.any(hi - lo < 2 * rmax):
        raise UserError(f"placement box {list(hi - lo)} m is smaller than a particle diameter {2 * rmax:g} m",
                        "enlarge the domain or the placement range")
    phi = float(np.sum(4 / 3 * np.pi * radius ** 3) / np.prod(hi - lo))
    if phi > 0.34:
        raise UserError(f"cannot place {n} particles at random: packing fraction {phi:.3f} in the placement box "
                        "exceeds what random sequential addition reaches (jamming at 0.38; in practice ~0.3 in a walled box)",
                        "enlarge the domain (or placement_z range) or reduce particles.count")
    # cells: at least one diameter wide, and about one particle per cell (bounded memory)
    span = hi - lo
    target = max(2 * rmax, float((np.prod(span) / max(n, 1)) ** (1 / 3)))
    ncell = np.maximum(1, np.floor(span / target)).astype(np.int64)
    while np.prod(ncell) > 8 * n + 64:
        ncell = np.maximum(1, ncell // 2)
    cell = span / ncell
    seed_int = int(rng.integers(0, 2**31 - 1))
    pos, done = _place_kernel(seed_int, radius, lo, hi, ncell, cell, max_attempts)
    if done < n:
        raise UserError(f"placed only {done} of {n} particles without overlap (packing fraction {phi:.3f})",
                        "enlarge the domain or reduce particles.count")
    return np.ascontiguousarray(pos), radius
