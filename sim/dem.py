"""The DEM engine: velocity-Verlet, the seed's phi-scheme or overdamped Brownian
dynamics of spheres with contact, bonding, friction, non-contact (near-field,
screened Coulomb, van der Waals) and wall forces, all through one force pass
(:func:`_forces`).

Layout (jax-md / HOOMD style: small pieces composed by the caller):

* :class:`DEMSystem` holds the state as contiguous float64 arrays (structure
  of arrays), the force-model parameters, the box and the neighbour list with
  per-entry contact history.  ``system.run(n)`` advances ``n`` steps inside one
  compiled kernel (the stepper of its integrator: :func:`_run_verlet`,
  :func:`_run_phi` or :func:`_run_overdamped`; only that one is compiled): no Python per step, no allocation per
  step (the list is rebuilt - and only then allocated - when some particle
  moved more than half the skin).
* :func:`run_dem` runs a :class:`sim.scene.Scene` that has pair interactions:
  automatic and adaptive dt, the table streamed as segments committed with
  atomic checkpoints (:class:`sim.driver.SegmentedTable`; unwrapped
  coordinates), ``resume`` that survives any kill, signals handled between
  kernel calls of bounded wall time, blow-up detection with the last good
  state saved.

External forces reuse the simulator core: the constant force ``q E + (m -
rho_f V) g`` from :func:`sim.scene.constant_force`, the drag law of
:mod:`sim.forces.drag` (Stokes or the seed's piecewise C_D) and the magnetic
part of the Lorentz force.  Brownian forces (variance ``2 gamma kB T / dt``)
are drawn from a counter-based generator keyed by (seed, step, particle,
component), so a run resumed from a checkpoint draws exactly the numbers the
uninterrupted run draws (numba's global generator state cannot be saved).

Determinism: every kernel is serial with a fixed summation order, and the
neighbour list is rebuilt at every checkpoint in both the uninterrupted and
the resumed run, so resume reproduces the uninterrupted run bit for bit.

Blow-up detection (status codes): overlap above ``max_overlap`` of a radius,
NaN/inf, a particle centre behind the substrate, a speed above ``v_max``.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from sim.forces.contact import (CONTACT_NONE, D_MAX_DAMP, D_MAX_OVERLAP, D_MAX_OVERLAP_I, D_MAX_W2, D_N_CONTACTS, D_SIZE,
                                _pair_rows, pair_forces_parallel, thread_blocks, wall_forces)
from sim.forces.body import magnetic_force
from sim.forces.brownian import brownian_sigma
from sim.forces.drag import drag_force_scalar
from sim.forces.nearfield import LAW_WIDTH, law_row, law_table, wall_law_forces
from sim.neighbors import (_build, carry_history, carry_history_permuted, cell_order, inner_list, needs_rebuild,
                           permute_rows, scatter_history,
                           wrap_positions)

# The cached kernels below call a parallel=True kernel; when they are loaded from
# numba's on-disk cache in a fresh process the threading layer must already be
# running, otherwise the first call can crash.  Start it once at import.
try:  # pragma: no cover - depends on numba internals
    from numba.np.ufunc.parallel import _launch_threads

    _launch_threads()
except Exception:  # noqa: BLE001
    pass

OK, BLOWUP_OVERLAP, BLOWUP_NAN, BLOWUP_WALL, BLOWUP_SPEED = 0, 1, 2, 3, 4
# the velocity-Verlet stepper's answer when a step's end state failed a check that it made only inside the
# next step's pass (DEMSystem.run then repeats the call from its start without that fusion: G_PLAIN)
REPLAY = -1
STATUS_TEXT = {
    BLOWUP_OVERLAP: "overlap beyond the allowed fraction of a radius",
    BLOWUP_NAN: "NaN or infinite position/velocity",
    BLOWUP_WALL: "particle centre went through the substrate",
    BLOWUP_SPEED: "runaway speed (kinetic energy)",
}

DRAG_NONE, DRAG_STOKES, DRAG_SEED = 0, 1, 2
VERLET, PHI_SCHEME, OVERDAMPED = 0, 1, 2  # integrator codes (STEPPERS: the kernel of each)

# the ``guards`` array of the kernels: blow-up limits, the fixed-point tolerance and the overdamped
# stepper's options (sticking substrate, largest drift step in m, time at which to stop in s, and the clock's
# value at the start of a call: the overdamped stepper counts absolute time from it, the fixed-step ones from 0;
# G_PLAIN 1: the velocity-Verlet stepper keeps every step's second half kick in a pass of its own; G_NEAR: the
# margin (m) of the velocity-Verlet stepper's near sub-list of the neighbour list, 0 = off: see _run_verlet)
G_MAX_OVERLAP, G_V_MAX, G_HAS_BOTTOM, G_TOL, G_STICK, G_MAX_STEP, G_T_STOP, G_T_START, G_PLAIN, G_NEAR = range(10)
# the near sub-list's default margin as a fraction of the skin (DEMSystem(near_margin=))
NEAR_FRACTION = 0.1
# the ``chunk_peaks`` array: largest values over a run() call, and two counts of the velocity-Verlet stepper's
# near sub-list: filterings of it in the call and its pairs at the last step (0 when the sub-list is off)
P_OVERLAP, P_W2, P_DAMP, P_NEAR_FILTERS, P_NEAR_PAIRS = range(5)

# random numbers: the counter-based generator of sim.forces.brownian (one scheme for every run)
from sim.forces.brownian import counter_normal  # noqa: E402,F401  (re-exported: sim.dem.counter_normal)


# --------------------------------------------------------------------------- force evaluation


@njit(cache=True, inline="always")
def _external_one(fx, fy, fz, vx, vy, vz, ri, qi, gi, drag_mode, ufx, ufy, ufz, rho_f, mu, bx, by, bz, magnetic, kT,
                  seed, step, dt, i):
    """Constant force ``f`` (N) + drag + magnetic Lorentz + Brownian on particle ``i`` of velocity
    ``v``, radius, charge and Stokes gamma ``ri``, ``qi``, ``gi``, fluid velocity ``uf``, density and
    viscosity ``rho_f``, ``mu``, magnetic field ``b``; see :func:`_forces`.  Everything comes in as
    scalars (array arguments of a function called per particle cost reference counting in the hot
    loop: 5-10x this function's time)."""
    if drag_mode == DRAG_STOKES:
        fx += gi * (ufx - vx)
        fy += gi * (ufy - vy)
        fz += gi * (ufz - vz)
    elif drag_mode == DRAG_SEED:
        if rho_f == 0.0:
            # fluid density 0: Re = 0, so phi(Re) = 1 and the seed's law is Stokes drag 6 pi mu R u
            # (sim.forces.drag.drag_force_scalar: the same products, without its square root and division)
            g = 6.0 * math.pi * mu * ri
            fx += g * (ufx - vx)
            fy += g * (ufy - vy)
            fz += g * (ufz - vz)
        else:
            dx, dy, dz = drag_force_scalar(ufx - vx, ufy - vy, ufz - vz, ri, rho_f, mu)
            fx += dx
            fy += dy
            fz += dz
    if magnetic:
        mx, my, mz = magnetic_force(qi, vx, vy, vz, bx, by, bz)
        fx += mx
        fy += my
        fz += mz
    if kT > 0.0:
        s = brownian_sigma(gi, kT, dt)
        fx += s * counter_normal(seed, step, 3 * i)
        fy += s * counter_normal(seed, step, 3 * i + 1)
        fz += s * counter_normal(seed, step, 3 * i + 2)
    return fx, fy, fz


@njit(cache=True)
def _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
            model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist, start, nbj, shift, hist,
            force, torque, diag, fbuf, tbuf, dbuf):
    """One whole force pass into ``force``, ``torque`` and ``diag``: the external forces
    (:func:`_begin_forces`: constant force + drag + magnetic Lorentz + Brownian, ``extp = [vf_x, vf_y,
    vf_z, rho_f, mu, kT, B_x, B_y, B_z]``; the overdamped stepper passes drag_mode = DRAG_NONE and kT = 0,
    its mobility and displacement noise carry drag and Brownian motion), then the pair and wall forces
    (:func:`_interaction_forces`)."""
    _begin_forces(vel, radius, charge, gamma, fconst, drag_mode, extp, seed, step, dt, rotation, force, torque,
                  diag)
    _interaction_forces(pos, vel, omega, radius, mass, charge, model, cp, cpw, pair_laws, wall_laws, rotation,
                        walls, whist, start, nbj, shift, hist, force, torque, dt, diag, fbuf, tbuf, dbuf,
                        model != CONTACT_NONE or pair_laws.shape[0] > 0)


@njit(cache=True)
def _interaction_forces(pos, vel, omega, radius, mass, charge, model, cp, cpw, pair_laws, wall_laws, rotation,
                        walls, whist, start, nbj, shift, hist, force, torque, dt, diag, fbuf, tbuf, dbuf, pairs,
                        blocks=None):
    """Add the pair forces (``pairs``: contact or non-contact laws on) and the wall contact and wall laws
    to ``force``, ``torque``.  Serial when ``fbuf`` is None; else threaded with the per-thread buffers
    ``fbuf``, ``tbuf``, ``dbuf`` (:func:`sim.forces.contact.pair_forces_parallel`) over ``blocks`` (the
    list's :func:`sim.forces.contact.thread_blocks`, computed here when not given).  The branches are
    pruned at compile time, so a serial run never compiles the threaded kernel."""
    wall_contacts = walls.shape[0] > 0 and model != CONTACT_NONE
    if fbuf is None:
        if pairs:
            # sim.forces.contact.pair_forces, without its wrapper (each wrapper level costs compile time)
            n = pos.shape[0]
            _pair_rows(0, n, pos, vel, omega, radius, mass, charge, start, nbj, shift, hist, force,
                       torque, model, cp, pair_laws, rotation, dt, diag, n, force, torque)
        if wall_contacts:
            wall_forces(pos, vel, omega, radius, mass, walls, whist, force, torque, model, cpw, rotation, dt, diag)
    else:
        if blocks is None:
            rows, halo_start, halo_idx = thread_blocks(start, nbj, fbuf.shape[0])
        else:
            rows, halo_start, halo_idx = blocks
        pair_forces_parallel(rows, halo_start, halo_idx, pos, vel, omega, radius, mass, charge, start, nbj,
                             shift, hist, force, torque, model, cp, pair_laws, rotation, dt, diag, fbuf, tbuf,
                             dbuf, pairs, walls, whist, cpw, wall_contacts)
    if walls.shape[0] > 0 and wall_laws.shape[0] > 0:
        wall_law_forces(pos, radius, charge, walls, wall_laws, force)


@njit(cache=True, inline="always")
def _check_one(x, y, z, vx, vy, vz, bottom, vmax2):
    # the blow-up status of one particle at (x, y, z) m with velocity (vx, vy, vz) m/s (OK if none)
    v2 = vx * vx + vy * vy + vz * vz
    # one finiteness test of the sum first (non-finite if any term is, or if the sum overflows: then the
    # terms are tested one by one): the same status, one branch per particle instead of four
    if not math.isfinite(x + y + z + v2):
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z) and math.isfinite(v2)):
            return BLOWUP_NAN
    if bottom and z < 0.0:
        return BLOWUP_WALL
    if v2 > vmax2:
        return BLOWUP_SPEED
    return OK


@njit(cache=True)
def _check(pos, vel, radius, guards):
    """Return (status, particle) for NaN, substrate crossing, runaway speed."""
    vmax2 = guards[G_V_MAX] * guards[G_V_MAX]
    bottom = guards[G_HAS_BOTTOM] != 0.0
    for i in range(pos.shape[0]):
        st = _check_one(pos[i, 0], pos[i, 1], pos[i, 2], vel[i, 0], vel[i, 1], vel[i, 2], bottom, vmax2)
        if st != OK:
            return st, i
    return OK, -1


@njit(cache=True)
def _kick_factors(mass, inertia, hdt, rotation, kick):
    """``kick[0] = hdt / mass`` (s/kg) and, with rotation, ``kick[1] = hdt / inertia`` (s/(kg m^2)): the
    half-kick factors of every particle, in place.  Computed once per stepper call and after every
    rebuild (which may re-order the particles) instead of twice per particle and step: the same
    divisions, so the same factors bit for bit, without four divisions per particle and step."""
    for i in range(mass.shape[0]):
        kick[0, i] = hdt / mass[i]
        if rotation:
            kick[1, i] = hdt / inertia[i]


@njit(cache=True)
def _kick_check(pos, vel, omega, force, torque, kick, rotation, guards):
    """The step's second velocity-Verlet half kick of the velocities (m/s) and, with rotation, the
    angular velocities (rad/s), in place, with the factors of :func:`_kick_factors`, and the blow-up
    checks of :func:`_check` on the kicked state in the same pass over the particles (one pass over
    ``pos`` and ``vel`` less per step).  Every particle is kicked; returns ``(status, particle)`` of the
    first particle :func:`_check` would report."""
    vmax2 = guards[G_V_MAX] * guards[G_V_MAX]
    bottom = guards[G_HAS_BOTTOM] != 0.0
    st = OK
    p = -1
    for i in range(vel.shape[0]):
        im = kick[0, i]
        vx = vel[i, 0] + im * force[i, 0]
        vy = vel[i, 1] + im * force[i, 1]
        vz = vel[i, 2] + im * force[i, 2]
        vel[i, 0] = vx
        vel[i, 1] = vy
        vel[i, 2] = vz
        if rotation:
            ii = kick[1, i]
            omega[i, 0] += ii * torque[i, 0]
            omega[i, 1] += ii * torque[i, 1]
            omega[i, 2] += ii * torque[i, 2]
        if p < 0:
            sti = _check_one(pos[i, 0], pos[i, 1], pos[i, 2], vx, vy, vz, bottom, vmax2)
            if sti != OK:
                st = sti
                p = i
    return st, p


@njit(cache=True)
def _kick_drift(pos, vel, omega, force, torque, kick, ref_pos, dt, rotation, skin, ext, fconst, radius, charge,
                gamma, drag_mode, extp, seed, step, pending, guards, near, ux, uy, uz):
    """First half of a velocity-Verlet step in one pass over the particles: half kick of ``vel`` (and
    ``omega``; factors of :func:`_kick_factors`), drift of ``pos``; returns True when some particle moved
    more than skin/2 since the list was built (:func:`sim.neighbors.needs_rebuild`, the same test).  The
    same arithmetic per particle as :func:`_kick_check`, the drift and ``needs_rebuild`` one after the
    other.

    With ``ext`` the same pass also starts the step's force pass (what :func:`_begin_forces` does per
    particle: ``force`` = the external forces at the kicked velocity, ``torque`` = 0), once the kick has
    read the old force: one pass over the per-particle arrays less per step.  Only without Brownian
    force (its numbers are keyed by the slot, which a re-ordering rebuild after this pass changes); the
    rebuild permutes ``force`` and ``torque`` with the particles, so the values are those of
    :func:`_begin_forces` after it bit for bit.

    With ``pending`` the pass first gives each particle the last step's second half kick (the force has
    not changed since) and makes the blow-up checks of :func:`_kick_check` on it, one pass less per step:
    the same operations in the same order per particle as :func:`_kick_check` followed by this pass.

    With ``near`` the pass also measures the drift velocities against ``u = (ux, uy, uz)`` (m/s, any
    velocity: the caller gives the last step's mean): ``w2`` = the largest ``|v_i - u|^2`` and the sum
    of the ``v_i``.  This step changes the distance of any two particles by at most ``2 dt sqrt(w2)``,
    the bound of the near sub-list of :func:`_run_verlet`.

    Returns ``(rebuild, status, particle, w2, sx, sy, sz)``: the skin test, the first particle failing a
    check of the last step's end state (the pass is not stopped: that state is gone for the particles
    before it, so the caller repeats the call without the fusion, :data:`REPLAY`), and with ``near`` the
    largest ``|v_i - u|^2`` (m^2/s^2) and the sum of the drift velocities (m/s; zeros without).
    """
    d2max = 0.0
    magnetic = extp[6] != 0.0 or extp[7] != 0.0 or extp[8] != 0.0
    kT = extp[5]
    # the fluid and field parameters in locals: read from ``extp`` inside the loop they are loaded again for
    # every particle (the compiler cannot rule out that the force stores alias them)
    ufx = extp[0]
    ufy = extp[1]
    ufz = extp[2]
    rho_f = extp[3]
    mu = extp[4]
    bx = extp[6]
    by = extp[7]
    bz = extp[8]
    vmax2 = guards[G_V_MAX] * guards[G_V_MAX]
    bottom = guards[G_HAS_BOTTOM] != 0.0
    st = OK
    p = -1
    w2 = 0.0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    # the half kick is written out here and in _kick_check on purpose: shared as one function
    # (_half_kick, inlined or not, with or without a return value) the whole Hooke reference run took 2x
    # as long (N = 1e3, 1e5 steps: 2.7 -> 5.5 s CPU, same results bit for bit; measured 2 Dec 2026)
    for i in range(pos.shape[0]):
        im = kick[0, i]
        vx = vel[i, 0]
        vy = vel[i, 1]
        vz = vel[i, 2]
        if pending:
            # _kick_check's half kick and checks
            vx = vx + im * force[i, 0]
            vy = vy + im * force[i, 1]
            vz = vz + im * force[i, 2]
            if rotation:
                ii = kick[1, i]
                omega[i, 0] += ii * torque[i, 0]
                omega[i, 1] += ii * torque[i, 1]
                omega[i, 2] += ii * torque[i, 2]
            if p < 0:
                sti = _check_one(pos[i, 0], pos[i, 1], pos[i, 2], vx, vy, vz, bottom, vmax2)
                if sti != OK:
                    st = sti
                    p = i
        vx = vx + im * force[i, 0]
        vy = vy + im * force[i, 1]
        vz = vz + im * force[i, 2]
        vel[i, 0] = vx
        vel[i, 1] = vy
        vel[i, 2] = vz
        if rotation:
            ii = kick[1, i]
            omega[i, 0] += ii * torque[i, 0]
            omega[i, 1] += ii * torque[i, 1]
            omega[i, 2] += ii * torque[i, 2]
        x = pos[i, 0] + dt * vx
        y = pos[i, 1] + dt * vy
        z = pos[i, 2] + dt * vz
        pos[i, 0] = x
        pos[i, 1] = y
        pos[i, 2] = z
        dx = x - ref_pos[i, 0]
        dy = y - ref_pos[i, 1]
        dz = z - ref_pos[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > d2max:
            d2max = d2
        if near:
            sx += vx
            sy += vy
            sz += vz
            wx = vx - ux
            wy = vy - uy
            wz = vz - uz
            q2 = wx * wx + wy * wy + wz * wz
            if q2 > w2:
                w2 = q2
        if ext:
            fx, fy, fz = _external_one(fconst[i, 0], fconst[i, 1], fconst[i, 2], vx, vy, vz, radius[i], charge[i],
                                       gamma[i], drag_mode, ufx, ufy, ufz, rho_f, mu, bx, by, bz, magnetic, kT, seed,
                                       step, dt, i)
            force[i, 0] = 0.0 + fx
            force[i, 1] = 0.0 + fy
            force[i, 2] = 0.0 + fz
            if rotation:
                torque[i, 0] = 0.0
                torque[i, 1] = 0.0
                torque[i, 2] = 0.0
    return d2max > 0.25 * skin * skin, st, p, w2, sx, sy, sz


@njit(cache=True, parallel=True)
def _kick_drift_parallel(nt, pos, vel, omega, force, torque, kick, ref_pos, dt, rotation, skin, ext, fconst, radius,
                         charge, gamma, drag_mode, extp, seed, step, pending, guards, near, ux, uy, uz, out):
    """:func:`_kick_drift` on ``nt`` threads, each over one block of equal particle count (row slices: the
    same arithmetic per particle).  ``out`` (nt, 7): per-block results, combined in block order: the skin
    test of any block, the first failing particle, the largest ``w2``, the sums block by block (they
    differ from the serial sums by round-off; they only set the near sub-list's travel bound).  The
    particle index inside a block is used only for Brownian numbers, which ``ext`` excludes."""
    n = pos.shape[0]
    for t in prange(nt):
        i0 = (t * n) // nt
        i1 = ((t + 1) * n) // nt
        if i1 > i0:
            rb, st, p, w2, sx, sy, sz = _kick_drift(pos[i0:i1], vel[i0:i1], omega[i0:i1], force[i0:i1],
                                                    torque[i0:i1], kick[:, i0:i1], ref_pos[i0:i1], dt, rotation,
                                                    skin, ext, fconst[i0:i1], radius[i0:i1], charge[i0:i1],
                                                    gamma[i0:i1], drag_mode, extp, seed, step, pending, guards,
                                                    near, ux, uy, uz)
            out[t, 0] = 1.0 if rb else 0.0
            out[t, 1] = st
            out[t, 2] = p + i0 if p >= 0 else -1
            out[t, 3] = w2
            out[t, 4] = sx
            out[t, 5] = sy
            out[t, 6] = sz
        else:
            out[t, 0] = 0.0
            out[t, 1] = OK
            out[t, 2] = -1
            out[t, 3] = 0.0
            out[t, 4] = 0.0
            out[t, 5] = 0.0
            out[t, 6] = 0.0
    rebuild = False
    st = OK
    p = -1
    w2 = 0.0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for t in range(nt):
        rebuild = rebuild or out[t, 0] != 0.0
        if p < 0 and out[t, 2] >= 0:
            st = int(out[t, 1])
            p = int(out[t, 2])
        if out[t, 3] > w2:
            w2 = out[t, 3]
        sx += out[t, 4]
        sy += out[t, 5]
        sz += out[t, 6]
    return rebuild, st, p, w2, sx, sy, sz


@njit(cache=True)
def _begin_forces(vel, radius, charge, gamma, fconst, drag_mode, extp, seed, step, dt, rotation, force,
                  torque, diag):
    """Start a force pass: ``force`` = the external forces (``0.0 +`` the sum of :func:`_external_one`,
    one pass), ``torque`` = 0, ``diag`` = 0."""
    magnetic = extp[6] != 0.0 or extp[7] != 0.0 or extp[8] != 0.0
    kT = extp[5]
    for k in range(D_SIZE):
        diag[k] = 0.0
    # extp in locals, as in _kick_drift (read inside the loop, it is loaded again for every particle)
    ufx = extp[0]
    ufy = extp[1]
    ufz = extp[2]
    rho_f = extp[3]
    mu = extp[4]
    bx = extp[6]
    by = extp[7]
    bz = extp[8]
    for i in range(vel.shape[0]):
        fx, fy, fz = _external_one(fconst[i, 0], fconst[i, 1], fconst[i, 2], vel[i, 0], vel[i, 1], vel[i, 2],
                                   radius[i], charge[i], gamma[i], drag_mode, ufx, ufy, ufz, rho_f, mu, bx, by, bz,
                                   magnetic, kT, seed, step, dt, i)
        force[i, 0] = 0.0 + fx
        force[i, 1] = 0.0 + fy
        force[i, 2] = 0.0 + fz
        if rotation:
            torque[i, 0] = 0.0
            torque[i, 1] = 0.0
            torque[i, 2] = 0.0


@njit(cache=True)
def _copy_rows(dst, src):
    """``dst[:, :] = src`` for two arrays of one shape, as a loop: the slice assignment's broadcasting check
    compiles an error-message formatter (about 3 s of compile time on first use)."""
    for i in range(src.shape[0]):
        for c in range(src.shape[1]):
            dst[i, c] = src[i, c]


@njit(cache=True)
def rebuild_neighbors(pos, image, radius, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
    """Wrap positions into the box and rebuild the neighbour list from them.

    The one rebuild step shared by every DEM kernel (integrators here, the
    quench in ``sim.studies.epd_order``): wraps ``pos`` into the periodic box
    (counting crossings in ``image``), builds the new list, carries the
    tangential-spring history of pairs present in both lists, and stores the
    positions the list was built from in ``ref_pos`` (all in place).

    Returns
    -------
    start, nbj, shift, hist : the new list (CSR row starts, neighbour indices,
        periodic image shifts in m) and the carried history (m), one row per pair.
    """
    wrap_positions(pos, image, lo, length, periodic)
    ns, nj, nsh = _build(pos, radius, cutoff, skin, lo, length, periodic)
    hist = carry_history(start, nbj, hist, ns, nj)
    _copy_rows(ref_pos, pos)
    return ns, nj, nsh, hist


@njit(cache=True)
def rebuild_sorted(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                   whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
    """:func:`rebuild_neighbors` with the particles re-ordered by cell first (cell-ordered memory:
    partners of a particle sit near it in every per-particle array).

    Every per-particle array (and ``whist``, ``W`` rows per particle) is permuted in place by
    :func:`sim.neighbors.cell_order` (cell, then particle id), ``order`` (slot -> particle id) with
    them, and the contact history is carried onto the new list by particle, sign-flipped where a pair
    changed which particle stores it (:func:`sim.neighbors.carry_history_permuted`).
    """
    wrap_positions(pos, image, lo, length, periodic)
    n = pos.shape[0]
    perm = cell_order(pos, radius, cutoff, skin, lo, length, periodic, order)
    permute_rows(pos, perm, 1)
    permute_rows(image, perm, 1)
    permute_rows(vel, perm, 1)
    permute_rows(omega, perm, 1)
    permute_rows(force, perm, 1)
    permute_rows(torque, perm, 1)
    permute_rows(fconst, perm, 1)
    if n > 0:
        permute_rows(whist, perm, whist.shape[0] // n)
    for a in (radius, mass, inertia, charge, gamma, frozen):
        tmp = a.copy()
        for q in range(n):
            a[q] = tmp[perm[q]]
    tmpo = order.copy()
    for q in range(n):
        order[q] = tmpo[perm[q]]
    ns, nj, nsh = _build(pos, radius, cutoff, skin, lo, length, periodic)
    hist = carry_history_permuted(start, nbj, hist, ns, nj, perm)
    _copy_rows(ref_pos, pos)
    return ns, nj, nsh, hist


def _rebuild_any(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                 whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
    """:func:`rebuild_sorted` when ``order`` (slot -> particle id) is given, :func:`rebuild_neighbors` when it is
    None (no cell ordering).  In a kernel the choice is made from the type of ``order`` when the caller is
    compiled (:func:`_ol_rebuild_any`), so only the rebuild a system uses is compiled."""
    if order is None:
        return rebuild_neighbors(pos, image, radius, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos)
    return rebuild_sorted(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst,
                          frozen, whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos)


@overload(_rebuild_any, inline="always")
def _ol_rebuild_any(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                    whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
    if isinstance(order, (types.NoneType, types.Omitted)):
        def impl(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                 whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
            return rebuild_neighbors(pos, image, radius, cutoff, skin, lo, length, periodic, start, nbj, hist,
                                     ref_pos)
    else:
        def impl(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                 whist, order, cutoff, skin, lo, length, periodic, start, nbj, hist, ref_pos):
            return rebuild_sorted(pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma,
                                  fconst, frozen, whist, order, cutoff, skin, lo, length, periodic, start, nbj,
                                  hist, ref_pos)
    return impl


@njit(cache=True)
def _end_step(pos, vel, radius, guards, diag, chunk_peaks, t_done):
    """After a step: the run's peaks of the diagnostics into ``chunk_peaks`` and the blow-up checks.

    Returns ``(status, particle, stop)``: a status code other than OK (with its particle) ends the chunk
    with that status; ``stop`` ends it with OK once the time ``t_done`` (s) reaches ``guards[G_T_STOP]``.
    """
    st, p = _check(pos, vel, radius, guards)
    return _end_step_checked(st, p, guards, diag, chunk_peaks, t_done)


@njit(cache=True)
def _end_step_checked(st, p, guards, diag, chunk_peaks, t_done):
    """:func:`_end_step` with the result ``(st, p)`` of :func:`_check` given (:func:`_kick_check`)."""
    if diag[D_MAX_OVERLAP] > chunk_peaks[P_OVERLAP]:
        chunk_peaks[P_OVERLAP] = diag[D_MAX_OVERLAP]
    if diag[D_MAX_W2] > chunk_peaks[P_W2]:
        chunk_peaks[P_W2] = diag[D_MAX_W2]
    if diag[D_MAX_DAMP] > chunk_peaks[P_DAMP]:
        chunk_peaks[P_DAMP] = diag[D_MAX_DAMP]
    if diag[D_MAX_OVERLAP] > guards[G_MAX_OVERLAP]:
        return BLOWUP_OVERLAP, int(diag[D_MAX_OVERLAP_I]), True
    if st != OK:
        return st, p, True
    # the overdamped stepper's variable steps reached the requested time
    return OK, -1, guards[G_T_STOP] > 0.0 and t_done >= guards[G_T_STOP]


# The three steppers below take the same arguments (DEMSystem.run calls the one of its integrator), so that
# only the stepper a system uses is compiled.  ``fbuf``, ``tbuf``, ``dbuf``: per-thread force, torque and
# diagnostics buffers of the threaded pair kernel, or None for the serial one (the threaded kernel is then
# not compiled); ``order`` None: no cell ordering (see _rebuild_any).  Each returns
# ``(status, steps_done, particle, start, nbj, shift, hist, ref_pos, n_builds, t_done)``.


@njit(cache=True)
def _run_verlet(nsteps, dt, step0, phi, n_iter,
                pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                drag_mode, extp, seed, model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist,
                start, nbj, shift, hist, ref_pos, cutoff, skin, lo, length, periodic, guards, diag,
                chunk_peaks, force_rebuild_at_end, fbuf, tbuf, dbuf, order):
    """Up to ``nsteps`` velocity-Verlet steps (kick-drift-kick; velocity-dependent forces use the
    half-step velocity, as in LAMMPS).

    Near sub-list (``guards[G_NEAR]`` = margin > 0): the pair forces are taken over
    the pairs of the list closer than ``max(R_i + R_j, cutoff) + margin`` (:func:`sim.neighbors.inner_list`,
    order kept), re-filtered from the whole list at every rebuild and once the distance of two particles
    may have shrunk by 0.9 margin since the last filtering: every step adds ``2 dt max_i |v_i - u|`` to
    that bound (:func:`_kick_drift`, ``u`` the last step's mean velocity, so a bed falling as one never
    re-filters).  A left-out pair touches no one meanwhile, and the whole list's kernel adds nothing for
    such a pair (and zeroes its history, as the filtering does), so the forces are the same bit for bit;
    in a settled Hooke bed about 40 % of the listed pairs are left out.  The sub-list's history is
    written back into ``hist`` before every rebuild and at every return.
    """
    n = pos.shape[0]
    nbuild = 0
    t_done = 0.0
    hdt = 0.5 * dt
    pairs = model != CONTACT_NONE or pair_laws.shape[0] > 0
    kick = np.empty((2, n))
    _kick_factors(mass, inertia, hdt, rotation, kick)
    # without Brownian force the external forces start the force pass inside the kick-drift pass
    ext = not extp[5] > 0.0
    # a step's second half kick and checks are made in the next step's kick-drift pass (and after the last
    # step of the call), unless guards[G_PLAIN]; ``pending``: the last step's second half kick is owed
    fuse = guards[G_PLAIN] == 0.0
    pending = False
    # the near sub-list (l*: the list the pair kernel is given)
    margin = guards[G_NEAR]
    near = pairs and margin > 0.0 and n > 0
    # threads: the pair kernel's row blocks and halos of the list it is given, recomputed when that
    # list changes (``stale``), and the kick-drift pass's per-block results
    # (``fbuf is not None`` in each test, not a flag: numba prunes those branches at compile time)
    nt = 1
    if fbuf is not None:
        nt = fbuf.shape[0]
    kd_out = np.empty((nt, 7))
    stale = True
    rows = np.empty(0, dtype=np.int64)
    halo_start = np.empty(0, dtype=np.int64)
    halo_idx = np.empty(0, dtype=np.int64)
    if near:
        lstart, lnbj, lshift, lhist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift, hist)
        chunk_peaks[P_NEAR_FILTERS] += 1.0
    else:
        lstart, lnbj, lshift, lhist, kmap = start, nbj, shift, hist, np.empty(0, dtype=np.int64)
    travel = 0.0  # bound (m) on how much any distance shrank since the sub-list was filtered
    ux = 0.0
    uy = 0.0
    uz = 0.0
    for s in range(nsteps):
        step = step0 + s + 1
        # (last step's second half kick and checks +) kick + drift + skin test (+ external forces and the
        # zeroing) in one pass: the arithmetic of the half kicks, the checks, the drift, needs_rebuild and
        # _forces in the same order per particle, so the results are those of the separate loops bit for bit
        if fbuf is not None:
            rebuild, cst, cpart, w2, sx, sy, sz = _kick_drift_parallel(nt, pos, vel, omega, force, torque, kick,
                                                                       ref_pos, dt, rotation, skin, ext, fconst,
                                                                       radius, charge, gamma, drag_mode, extp, seed,
                                                                       step, pending, guards, near, ux, uy, uz,
                                                                       kd_out)
        else:
            rebuild, cst, cpart, w2, sx, sy, sz = _kick_drift(pos, vel, omega, force, torque, kick, ref_pos, dt,
                                                              rotation, skin, ext, fconst, radius, charge, gamma,
                                                              drag_mode, extp, seed, step, pending, guards, near,
                                                              ux, uy, uz)
        if cst != OK:
            # the end state of step s failed a check; this pass has moved particles on past it
            if near:
                scatter_history(hist, lhist, kmap)
            return REPLAY, s, cpart, start, nbj, shift, hist, ref_pos, nbuild, t_done
        if near:
            travel += 2.0 * dt * math.sqrt(w2)
            ux = sx / n
            uy = sy / n
            uz = sz / n
        if rebuild:
            if near:
                scatter_history(hist, lhist, kmap)
            start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass,
                                                   inertia, charge, gamma, fconst, frozen, whist, order,
                                                   cutoff, skin, lo, length, periodic, start, nbj, hist,
                                                   ref_pos)
            if order is not None:  # the rebuild re-ordered the particles
                _kick_factors(mass, inertia, hdt, rotation, kick)
            nbuild += 1
            stale = True
            if near:
                lstart, lnbj, lshift, lhist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift,
                                                               hist)
                travel = 0.0
                chunk_peaks[P_NEAR_FILTERS] += 1.0
            else:
                lstart, lnbj, lshift, lhist = start, nbj, shift, hist
        elif near and not travel < 0.9 * margin:  # (a NaN velocity re-filters too)
            scatter_history(hist, lhist, kmap)
            lstart, lnbj, lshift, lhist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift, hist)
            travel = 0.0
            chunk_peaks[P_NEAR_FILTERS] += 1.0
            stale = True
        if near:
            chunk_peaks[P_NEAR_PAIRS] = lnbj.shape[0]
        if fbuf is not None:
            if stale:
                rows, halo_start, halo_idx = thread_blocks(lstart, lnbj, nt)
                stale = False
        if ext:
            for k in range(D_SIZE):
                diag[k] = 0.0
        else:
            _begin_forces(vel, radius, charge, gamma, fconst, drag_mode, extp, seed, step, dt, rotation, force,
                          torque, diag)
        _interaction_forces(pos, vel, omega, radius, mass, charge, model, cp, cpw, pair_laws, wall_laws,
                            rotation, walls, whist, lstart, lnbj, lshift, lhist, force, torque, dt, diag, fbuf,
                            tbuf, dbuf, pairs, (rows, halo_start, halo_idx))
        t_done += dt
        if fuse:
            # the checks of the forces (overlap) and of the time now, those of the kicked state later
            st, p, stop = _end_step_checked(OK, -1, guards, diag, chunk_peaks, t_done)
            if stop:
                # the call ends here: this step's second half kick now, and the status _end_step_checked
                # gives the plain path (the overlap first, then the kicked state's)
                cst, cpart = _kick_check(pos, vel, omega, force, torque, kick, rotation, guards)
                if st == OK and cst != OK:
                    st = cst
                    p = cpart
                if near:
                    scatter_history(hist, lhist, kmap)
                return st, s + 1, p, start, nbj, shift, hist, ref_pos, nbuild, t_done
            pending = True
        else:
            cst, cpart = _kick_check(pos, vel, omega, force, torque, kick, rotation, guards)
            st, p, stop = _end_step_checked(cst, cpart, guards, diag, chunk_peaks, t_done)
            if stop:
                if near:
                    scatter_history(hist, lhist, kmap)
                return st, s + 1, p, start, nbj, shift, hist, ref_pos, nbuild, t_done
    if near:
        scatter_history(hist, lhist, kmap)
    if pending:
        cst, cpart = _kick_check(pos, vel, omega, force, torque, kick, rotation, guards)
        if cst != OK:
            return cst, nsteps, cpart, start, nbj, shift, hist, ref_pos, nbuild, t_done
    if force_rebuild_at_end:
        # deterministic restart point: list rebuilt from these exact positions
        start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass, inertia,
                                               charge, gamma, fconst, frozen, whist, order, cutoff, skin, lo,
                                               length, periodic, start, nbj, hist, ref_pos)
        nbuild += 1
    return OK, nsteps, -1, start, nbj, shift, hist, ref_pos, nbuild, t_done


@njit(cache=True)
def _run_overdamped(nsteps, dt, step0, phi, n_iter,
                    pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
                    drag_mode, extp, seed, model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist,
                    start, nbj, shift, hist, ref_pos, cutoff, skin, lo, length, periodic, guards, diag,
                    chunk_peaks, force_rebuild_at_end, fbuf, tbuf, dbuf, order):
    """Up to ``nsteps`` steps of Brownian dynamics with the pair, wall and constant forces
    (Euler-Maruyama, x' = x + F dt / gamma + sqrt(2 kB T dt / gamma) N(0, 1), the counter-based
    numbers of the Brownian force; ``vel`` holds the drift F / gamma), the step shortened so that no
    drift step exceeds ``guards[G_MAX_STEP]`` (m, 0 = off); with ``guards[G_STICK]`` a particle
    reaching the substrate sticks there (``frozen`` = 1, no longer moved), else its centre is reflected
    at z = R; the chunk ends early once the time reaches ``guards[G_T_STOP]``."""
    n = pos.shape[0]
    nbuild = 0
    # absolute time, one step at a time from the state's own clock: the same bits however a run is split
    # into calls (adding a per-call sum to the clock rounded differently for each split)
    t_done = guards[G_T_START]
    bd_kT = extp[5]
    # forces without drag and Brownian force (see _forces)
    extp = extp.copy()
    extp[5] = 0.0
    drag_mode = DRAG_NONE
    # with non-contact laws the forces are taken over the inner list (sim.neighbors.inner_list) of the pairs
    # within their range + ``margin``, re-filtered from the whole list whenever a particle moved more than
    # 0.45 margin (the slack keeps round-off out of the guarantee) or the whole list was rebuilt: the pairs
    # beyond the cut-off (a third to a half of the list, EPD study) are not visited, and the forces are
    # the same bit for bit.  The history lives in ``ihist`` meanwhile and goes back into ``hist`` before
    # every rebuild and at the end.  Serial pair kernel only: the threaded one splits the rows by pair count,
    # so its sums depend on the list it is given.
    inner = pair_laws.shape[0] > 0 and fbuf is None
    margin = 0.4 * skin
    istart, inbj, ishift, ihist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift, hist)
    iref = pos.copy()
    for s in range(nsteps):
        step = step0 + s + 1
        dts = dt
        if guards[G_MAX_STEP] > 0.0:
            # dts = min(dt, min_i max_step gamma_i / |F_i|) over the free particles.  For one gamma the
            # bound falls with |F|^2 (a correctly rounded sqrt and division are monotone), so a particle
            # with the gamma of the last bound computed and no larger |F|^2 than its largest cannot lower
            # the minimum: its square root and division are skipped (the same minimum bit for bit)
            g_last = np.nan
            f2_top = 0.0
            for i in range(n):
                if frozen[i] == 0.0:
                    f2 = force[i, 0] * force[i, 0] + force[i, 1] * force[i, 1] + force[i, 2] * force[i, 2]
                    if f2 > 0.0 and (gamma[i] != g_last or f2 > f2_top):
                        lim = guards[G_MAX_STEP] * gamma[i] / math.sqrt(f2)
                        if lim < dts:
                            dts = lim
                        if gamma[i] != g_last:
                            g_last = gamma[i]
                            f2_top = f2
                        elif f2 > f2_top:
                            f2_top = f2
        stick = guards[G_STICK] != 0.0
        bottom = guards[G_HAS_BOTTOM] != 0.0
        # the Brownian step sqrt(2 kB T dts / gamma) (m) recomputed only when gamma changes from the last free
        # particle's (the same expression, so the same value bit for bit)
        g_sd = np.nan
        sd = 0.0
        for i in range(n):
            if frozen[i] != 0.0:
                continue
            if gamma[i] != g_sd:
                g_sd = gamma[i]
                sd = math.sqrt(2.0 * bd_kT * dts / gamma[i]) if bd_kT > 0.0 else 0.0
            for c in range(3):
                v = force[i, c] / gamma[i]
                vel[i, c] = v
                pos[i, c] += v * dts
                if sd > 0.0:
                    pos[i, c] += sd * counter_normal(seed, step, 3 * i + c)
            if bottom and pos[i, 2] <= radius[i]:
                if stick:
                    pos[i, 2] = radius[i]
                    frozen[i] = 1.0
                    vel[i, 0] = 0.0
                    vel[i, 1] = 0.0
                    vel[i, 2] = 0.0
                else:
                    # hard, frictionless substrate: reflecting boundary for the centre at z = R
                    pos[i, 2] = 2.0 * radius[i] - pos[i, 2]
        t_done += dts
        if needs_rebuild(pos, ref_pos, skin):
            if inner:
                scatter_history(hist, ihist, kmap)
            start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass,
                                                   inertia, charge, gamma, fconst, frozen, whist, order,
                                                   cutoff, skin, lo, length, periodic, start, nbj, hist,
                                                   ref_pos)
            nbuild += 1
            if inner:
                istart, inbj, ishift, ihist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift,
                                                               hist)
                _copy_rows(iref, pos)
        elif inner and needs_rebuild(pos, iref, 0.9 * margin):
            scatter_history(hist, ihist, kmap)
            istart, inbj, ishift, ihist, kmap = inner_list(pos, radius, cutoff, margin, start, nbj, shift, hist)
            _copy_rows(iref, pos)
        if inner:
            _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                    model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist, istart, inbj, ishift, ihist,
                    force, torque, diag, fbuf, tbuf, dbuf)
        else:
            _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                    model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist, start, nbj, shift, hist,
                    force, torque, diag, fbuf, tbuf, dbuf)
        for i in range(n):
            if frozen[i] != 0.0:
                force[i, 0] = 0.0
                force[i, 1] = 0.0
                force[i, 2] = 0.0
        st, p, stop = _end_step(pos, vel, radius, guards, diag, chunk_peaks, t_done)
        if stop:
            if inner:
                scatter_history(hist, ihist, kmap)
            return st, s + 1, p, start, nbj, shift, hist, ref_pos, nbuild, t_done
    if inner:
        scatter_history(hist, ihist, kmap)
    if force_rebuild_at_end:
        start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass, inertia,
                                               charge, gamma, fconst, frozen, whist, order, cutoff, skin, lo,
                                               length, periodic, start, nbj, hist, ref_pos)
        nbuild += 1
    return OK, nsteps, -1, start, nbj, shift, hist, ref_pos, nbuild, t_done


@njit(cache=True)
def _run_phi(nsteps, dt, step0, phi, n_iter,
             pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst, frozen,
             drag_mode, extp, seed, model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist,
             start, nbj, shift, hist, ref_pos, cutoff, skin, lo, length, periodic, guards, diag,
             chunk_peaks, force_rebuild_at_end, fbuf, tbuf, dbuf, order):
    """Up to ``nsteps`` steps of the seed's eq. 3.28-3.29 phi-scheme with ``n_iter`` fixed-point
    iterations on the end-of-step forces (phi = 0: forward Euler)."""
    n = pos.shape[0]
    nbuild = 0
    t_done = 0.0
    # buffers (allocated once per chunk)
    x0 = np.empty_like(pos)
    v0 = np.empty_like(vel)
    w0 = np.empty_like(omega)
    f0 = np.empty_like(force)
    t0 = np.empty_like(torque)
    for s in range(nsteps):
        step = step0 + s + 1
        # phi-scheme: v1 = v0 + dt/m (phi F1 + (1-phi) F0); x1 = x0 + dt (phi v1 + (1-phi) v0)
        x0[:, :] = pos
        v0[:, :] = vel
        w0[:, :] = omega
        f0[:, :] = force
        t0[:, :] = torque
        hist0 = hist.copy()
        whist0 = whist.copy()
        for i in range(n):
            for c in range(3):
                vel[i, c] = v0[i, c] + dt / mass[i] * f0[i, c]
                pos[i, c] = x0[i, c] + dt * v0[i, c]
                if rotation:
                    omega[i, c] = w0[i, c] + dt / inertia[i] * t0[i, c]
        for it in range(n_iter if phi > 0.0 else 0):
            hist[:, :] = hist0
            whist[:, :] = whist0
            _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                    model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist, start, nbj, shift, hist,
                    force, torque, diag, fbuf, tbuf, dbuf)
            change = 0.0
            vscale = 0.0
            for i in range(n):
                for c in range(3):
                    vnew = v0[i, c] + dt / mass[i] * (phi * force[i, c] + (1.0 - phi) * f0[i, c])
                    d = abs(vnew - vel[i, c])
                    if d > change:
                        change = d
                    if abs(vnew) > vscale:
                        vscale = abs(vnew)
                    vel[i, c] = vnew
                    pos[i, c] = x0[i, c] + dt * (phi * vel[i, c] + (1.0 - phi) * v0[i, c])
                    if rotation:
                        omega[i, c] = w0[i, c] + dt / inertia[i] * (phi * torque[i, c] + (1.0 - phi) * t0[i, c])
            # fixed-point convergence: relative change of the end-of-step velocities
            if change <= guards[G_TOL] * (vscale + 1e-300):
                break
        hist[:, :] = hist0
        whist[:, :] = whist0
        if needs_rebuild(pos, ref_pos, skin):
            start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass,
                                                   inertia, charge, gamma, fconst, frozen, whist, order,
                                                   cutoff, skin, lo, length, periodic, start, nbj, hist,
                                                   ref_pos)
            nbuild += 1
        _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                model, cp, cpw, pair_laws, wall_laws, rotation, walls, whist, start, nbj, shift, hist,
                force, torque, diag, fbuf, tbuf, dbuf)
        t_done += dt
        st, p, stop = _end_step(pos, vel, radius, guards, diag, chunk_peaks, t_done)
        if stop:
            return st, s + 1, p, start, nbj, shift, hist, ref_pos, nbuild, t_done
    if force_rebuild_at_end:
        start, nbj, shift, hist = _rebuild_any(pos, image, vel, omega, force, torque, radius, mass, inertia,
                                               charge, gamma, fconst, frozen, whist, order, cutoff, skin, lo,
                                               length, periodic, start, nbj, hist, ref_pos)
        nbuild += 1
    return OK, nsteps, -1, start, nbj, shift, hist, ref_pos, nbuild, t_done


#: the stepper kernel of each integrator code (DEMSystem.run)
STEPPERS = {VERLET: _run_verlet, PHI_SCHEME: _run_phi, OVERDAMPED: _run_overdamped}


# --------------------------------------------------------------------------- system


class DEMSystem:
    """State, parameters and neighbour list of a DEM simulation.

    Parameters
    ----------
    pos, vel : (N, 3) arrays
        Positions (m) and velocities (m/s).
    radius, mass : (N,) arrays
        Radii (m), masses (kg).
    charge : (N,) array, optional
        Charges (C), used by the near-field law and the magnetic force.
    model : int
        Contact law: 0 none, 1 Hooke/Coulomb, 2 seed power law
        (:mod:`sim.forces.contact`).
    cp, cpw : arrays
        Particle-particle and particle-wall parameters of ``model``.
    pair_laws, wall_laws : (L, LAW_WIDTH) arrays, optional
        Non-contact law tables of :mod:`sim.forces.nearfield` (particle-particle
        and particle-wall; e.g. screened Coulomb, van der Waals).
    nf_model, nfp : int, array
        One pair law by code and parameters (older form of ``pair_laws``).
    rotation : bool
        Integrate angular velocities (needed whenever tangential forces act).
    walls : (W, 6) array
        Planes (point, inward unit normal); the substrate is ``[0,0,0, 0,0,1]``.
    box_lo, box_length : (3,) arrays; periodic : (3,) ints
        Periodic box (only periodic axes are used).
    fconst : (N, 3) array
        Constant external force (N).
    drag_mode : int; gamma : (N,); extp : (9,)
        Drag (0 none, 1 Stokes ``gamma (v_f - v)``, 2 seed's piecewise law),
        ``extp = [v_f (3), rho_f, mu, kB T, B (3)]``.
    dt : float
        Time step (s).
    skin : float
        Verlet skin (m); default 0.1 of the smallest diameter... see code.
    seed : int
        Key of the counter-based Brownian random numbers.
    max_overlap, v_max : float
        Blow-up limits (overlap / radius, speed in m/s).
    integrator, phi, n_iter, tol :
        0: velocity Verlet; 1: the seed's phi-scheme (eq. 3.28-3.29) with at
        most ``n_iter`` fixed-point iterations, stopped when the relative
        change of the velocities falls below ``tol``.
    threads : int
        1: serial pair kernel (bitwise reproducible); T > 1: the threaded
        kernel with T blocks (reproducible for the same T, round-off
        differences from the serial sum).
    near_margin : float, optional
        Margin (m) of the velocity-Verlet stepper's near sub-list (:func:`_run_verlet`; the same
        forces bit for bit, fewer pairs visited per step); default :data:`NEAR_FRACTION` of the skin,
        0 = off.
    sort : bool
        Cell-ordered memory: at every neighbour-list rebuild the particles
        are re-ordered by cell (then id) in every per-particle array, so
        the partners of a particle are near it in memory (faster for large
        N; the summation order of the pair forces changes, so results differ
        from ``sort=False`` by round-off).  The arrays are then in *slot*
        order: ``particle_order[s]`` is the id of the particle in slot ``s``;
        :meth:`by_id` returns an array in id order, and :meth:`get_state`,
        ``fail_particle`` and checkpoints use ids.
    """

    def __init__(self, pos, vel, radius, mass, charge=None, *, model=1, cp=None, cpw=None, nf_model=0,
                 nfp=None, pair_laws=None, wall_laws=None, rotation=True, walls=None, box_lo=(0, 0, 0), box_length=(1, 1, 1),
                 periodic=(0, 0, 0), fconst=None, drag_mode=DRAG_NONE, gamma=None, extp=None, dt=1e-6,
                 skin=None, cutoff=0.0, seed=0, max_overlap=0.5, v_max=np.inf, integrator=0, phi=0.0,
                 n_iter=3, threads=1, tol=1e-10, substrate=None, max_step=0.0, sort=False, near_margin=None):
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        self.pos = f64(np.array(pos, dtype=np.float64, copy=True))
        n = len(self.pos)
        self.vel = f64(np.array(vel, dtype=np.float64, copy=True))
        self.radius = f64(radius)
        self.mass = f64(mass)
        self.inertia = f64(0.4 * self.mass * self.radius**2)
        self.charge = f64(np.zeros(n) if charge is None else charge)
        self.omega = np.zeros((n, 3))
        self.image = np.zeros((n, 3))
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
        self.model = int(model)
        self.cp = f64(np.zeros(12) if cp is None else cp)
        self.cpw = f64(self.cp if cpw is None else cpw)
        if pair_laws is None:
            pair_laws = law_table(law_row(nf_model, nfp)) if nf_model else law_table()
        self.pair_laws = f64(np.reshape(pair_laws, (-1, LAW_WIDTH)))
        self.wall_laws = f64(np.reshape(law_table() if wall_laws is None else wall_laws, (-1, LAW_WIDTH)))
        self.rotation = bool(rotation)
        self.walls = f64(np.zeros((0, 6)) if walls is None else np.reshape(walls, (-1, 6)))
        self.whist = np.zeros((n * len(self.walls), 3))
        self.lo = f64(box_lo)
        self.length = f64(box_length)
        self.periodic = np.ascontiguousarray(periodic, dtype=np.int64)
        self.fconst = f64(np.zeros((n, 3)) if fconst is None else np.broadcast_to(fconst, (n, 3)))
        self.drag_mode = int(drag_mode)
        self.gamma = f64(np.zeros(n) if gamma is None else np.broadcast_to(gamma, (n,)))
        self.extp = f64(np.zeros(9) if extp is None else extp)
        self.dt = float(dt)
        self.cutoff = float(cutoff)
        self.skin = float(0.2 * self.radius.min() if skin is None else skin)
        self.seed = int(seed)
        if substrate not in (None, "stick", "reflect"):
            raise ValueError("substrate must be None, 'stick' or 'reflect'")
        bottom = self._has_bottom() or substrate is not None
        # G_* indices
        self.guards = f64([max_overlap, v_max, 1.0 if bottom else 0.0, tol, 1.0 if substrate == "stick" else 0.0,
                           max_step, 0.0, 0.0, 0.0,
                           NEAR_FRACTION * self.skin if near_margin is None else float(near_margin)])
        self.frozen = np.zeros(n)  # 1: stuck on the substrate (overdamped stepper), no longer moved
        self.integrator = int(integrator)
        self.phi = float(phi)
        self.n_iter = int(n_iter)
        self.threads = int(threads)
        self.sort = bool(sort)
        self.particle_order = np.arange(n, dtype=np.int64)  # slot -> particle id (identity unless sort)
        # own every per-particle array (no caller's array or read-only view): the kernels write them (the
        # cell re-ordering permutes them in place), and one array type means one compiled kernel
        for k in ("radius", "mass", "inertia", "charge", "gamma", "fconst"):
            setattr(self, k, np.array(getattr(self, k), dtype=np.float64, order="C", copy=True))
        self.step = 0
        self.t = 0.0
        self.n_builds = 0
        self.diag = np.zeros(D_SIZE)
        self.chunk_peaks = np.zeros(5)  # P_* indices
        self.status = OK
        self.fail_particle = -1
        from sim.neighbors import wrap_positions as _wrap

        _wrap(self.pos, self.image, self.lo, self.length, self.periodic)
        self._rebuild(history=None)
        self.compute_forces()

    # ------------------------------------------------------------------ helpers
    def _has_bottom(self):
        return any(w[2] == 0.0 and w[5] == 1.0 for w in self.walls)

    @property
    def n(self):
        return len(self.pos)

    def _rebuild(self, history):
        from sim.neighbors import build_neighbor_list

        if self.sort:
            # history (CSR over the current slots) is carried through the re-ordering by the kernel
            if history is None:
                history = (np.zeros(self.n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
            if self.n and np.any(self.periodic):
                build_neighbor_list(self.pos[:1], self.radius, self.cutoff, self.skin, self.lo, self.length,
                                    self.periodic)  # box-size check with its UserError
            self.ref_pos = np.empty_like(self.pos)
            self.start, self.nbj, self.shift, self.hist = rebuild_sorted(
                self.pos, self.image, self.vel, self.omega, self.force, self.torque, self.radius, self.mass,
                self.inertia, self.charge, self.gamma, self.fconst, self.frozen, self.whist, self.particle_order,
                self.cutoff, self.skin, self.lo, self.length, self.periodic, history[0], history[1],
                np.ascontiguousarray(history[2], dtype=np.float64), self.ref_pos)
            self.n_builds += 1
            return
        start, nbj, shift = build_neighbor_list(self.pos, self.radius, self.cutoff, self.skin, self.lo,
                                                self.length, self.periodic)
        if history is None:
            self.hist = np.zeros((len(nbj), 3))
        else:
            self.hist = carry_history(history[0], history[1], history[2], start, nbj)
        self.start, self.nbj, self.shift = start, nbj, shift
        self.ref_pos = self.pos.copy()
        self.n_builds += 1

    def compute_forces(self):
        """Evaluate forces and torques at the current state (updates contact history)."""
        drag_mode, extp = self.drag_mode, self.extp
        if self.integrator == OVERDAMPED:  # as in _run_overdamped: no drag or Brownian force
            drag_mode, extp = DRAG_NONE, self.extp.copy()
            extp[5] = 0.0
        _forces(self.pos, self.vel, self.omega, self.radius, self.mass, self.charge, self.gamma, self.fconst,
                drag_mode, extp, self.seed, self.step, self.dt, self.model, self.cp, self.cpw,
                self.pair_laws, self.wall_laws, self.rotation, self.walls, self.whist, self.start, self.nbj,
                self.shift, self.hist, self.force, self.torque, self.diag, *self._buffers())

    def _buffers(self):
        """``(fbuf, tbuf, dbuf)`` of the threaded pair kernel (T > 1 threads), or ``(None, None, None)`` for
        the serial one (see :func:`_interaction_forces`)."""
        t = int(self.threads)
        if t > 1:
            return np.zeros((t, self.n, 3)), np.zeros((t, self.n, 3)), np.zeros((2 * t, D_SIZE))
        return None, None, None

    @property
    def unwrapped(self):
        """Unwrapped positions (m), continuous across periodic boundaries."""
        return self.pos + self.image * self.length[None, :]

    def run(self, nsteps, rebuild_at_end=False, poll=None, chunker=None, until=None):
        """Advance ``nsteps`` steps; returns the status code (0 = fine).

        On a blow-up the state is left at the failing step and
        ``self.fail_particle`` names the particle. ``self.chunk_peaks`` holds the
        largest overlap ratio, k/m and eta/m met over these steps.

        With ``chunker`` (:class:`sim.driver.WallClockChunker`) the steps are
        taken in kernel calls of bounded wall time and ``poll()`` is called
        between them (it may raise, e.g. on a signal); the result is
        bit-identical to one call (the kernel carries no per-call state but its
        buffers, and the end-of-run rebuild is done in the last call only).

        ``until`` (s): stop at the first step that reaches this time (for the
        overdamped stepper, whose steps vary in length).
        """
        self.chunk_peaks = np.zeros(5)
        stepper = STEPPERS[self.integrator]
        fbuf, tbuf, dbuf = self._buffers()  # once per call (zeros: the threaded kernel leaves its halo buffers zero)
        left = int(nsteps)
        status = OK
        t0 = self.t
        done_here = 0
        while left > 0:
            od = self.integrator == OVERDAMPED
            self.guards[G_T_START] = self.t if od else 0.0
            if until is not None:
                if self.t >= until:
                    break
                self.guards[G_T_STOP] = until if od else until - self.t
            k = left if chunker is None else min(left, chunker.size)
            if chunker is not None:
                chunker.start()
            # the velocity-Verlet stepper may answer REPLAY (a blow-up found a pass late): the call is then
            # repeated from a copy of the state at its start without that fusion, which ends exactly where
            # the plain stepper ends (same steps, same state)
            snap = self._snapshot() if self.integrator == VERLET else None
            out = self._call(stepper, k, bool(rebuild_at_end) and k == left, fbuf, tbuf, dbuf)
            if out[0] == REPLAY:
                self._restore(snap)
                self.guards[G_PLAIN] = 1.0
                try:
                    out = self._call(stepper, k, bool(rebuild_at_end) and k == left, fbuf, tbuf, dbuf)
                finally:
                    self.guards[G_PLAIN] = 0.0
            status, done, part, self.start, self.nbj, self.shift, self.hist, self.ref_pos, nb, t_done = out
            if chunker is not None:
                chunker.done(done)   # the chunker sizes calls in steps (k above), so it is told steps
            self.step += done
            done_here += done
            # fixed steps: t = t0 + (steps of this call) dt, the rounding of one kernel call whatever the
            # split; the overdamped stepper's steps vary in length, and it returns its absolute clock
            self.t = t_done if od else t0 + done_here * self.dt
            self.n_builds += nb
            self.status = status
            self.fail_particle = int(self.particle_order[part]) if part >= 0 else part
            left -= done
            self.guards[G_T_STOP] = 0.0
            if status != OK:
                return status
            if poll is not None and left > 0:
                poll()
        return status

    def _call(self, stepper, k, rebuild_at_end, fbuf, tbuf, dbuf):
        """One call of the stepper kernel for ``k`` steps on this system's arrays; returns its tuple."""
        return stepper(k, self.dt, self.step, self.phi, self.n_iter,
                       self.pos, self.image, self.vel, self.omega, self.force, self.torque, self.radius,
                       self.mass, self.inertia, self.charge, self.gamma, self.fconst, self.frozen,
                       self.drag_mode,
                       self.extp, self.seed, self.model, self.cp, self.cpw, self.pair_laws,
                       self.wall_laws, self.rotation, self.walls, self.whist, self.start, self.nbj,
                       self.shift, self.hist, self.ref_pos, self.cutoff, self.skin, self.lo, self.length,
                       self.periodic, self.guards, self.diag, self.chunk_peaks,
                       rebuild_at_end, fbuf, tbuf, dbuf,
                       self.particle_order if self.sort else None)

    #: every array a stepper call may change (in place, or by returning a new neighbour list)
    _KERNEL_ARRAYS = ("pos", "image", "vel", "omega", "force", "torque", "radius", "mass", "inertia", "charge",
                      "gamma", "fconst", "frozen", "whist", "particle_order", "start", "nbj", "shift", "hist",
                      "ref_pos", "diag", "chunk_peaks")

    def _snapshot(self):
        """Copies of :attr:`_KERNEL_ARRAYS` (the state at the start of a stepper call)."""
        return {k: getattr(self, k).copy() for k in self._KERNEL_ARRAYS}

    def _restore(self, snap):
        """Back to a :meth:`_snapshot`, in place (callers may hold the arrays)."""
        for k, a in snap.items():
            cur = getattr(self, k)
            if cur.shape == a.shape:
                cur[...] = a
            else:
                setattr(self, k, a.copy())

    # ------------------------------------------------------------------ state I/O
    STATE_ARRAYS = ("pos", "image", "vel", "omega", "force", "torque", "whist", "fconst", "radius", "mass",
                    "charge", "gamma", "frozen")

    def get_state(self):
        """Neighbour-list-independent snapshot (dict of arrays/scalars).

        Contact history is stored as (i, j, spring) triples of the non-zero
        entries, so it can be mapped onto any list built later.
        """
        d = {k: self.by_id(getattr(self, k)) for k in self.STATE_ARRAYS}
        ii = np.repeat(np.arange(self.n), np.diff(self.start))
        nz = np.any(self.hist != 0.0, axis=1)
        hi, hj, hv = self.particle_order[ii[nz]], self.particle_order[self.nbj[nz]], self.hist[nz].copy()
        swap = hi > hj  # stored under the smaller id; the spring is that particle's (sign flips with the roles)
        hi[swap], hj[swap] = hj[swap], hi[swap].copy()
        hv[swap] = -hv[swap]
        d["hist_i"] = hi
        d["hist_j"] = hj
        d["hist_v"] = hv
        d["step"] = np.int64(self.step)
        d["t"] = np.float64(self.t)
        d["dt"] = np.float64(self.dt)
        return d

    def set_state(self, d):
        """Restore a snapshot from :meth:`get_state` (rebuilds the neighbour list)."""
        for k in self.STATE_ARRAYS:
            if k == "frozen" and k not in d:  # checkpoints written before the overdamped stepper
                self.frozen = np.zeros(len(d["pos"]))
                continue
            # a copy: the snapshot must survive the run (run_dem rolls back to the same snapshot again)
            setattr(self, k, np.array(d[k], dtype=np.float64, order="C", copy=True))
        self.step = int(d["step"])
        self.t = float(d["t"])
        self.dt = float(d["dt"])
        self.particle_order = np.arange(self.n, dtype=np.int64)  # the snapshot is in id order
        hi = np.asarray(d["hist_i"], dtype=np.int64)
        order = np.argsort(hi, kind="stable")
        hi = hi[order]
        ostart = np.zeros(self.n + 1, dtype=np.int64)
        np.add.at(ostart, hi + 1, 1)
        ostart = np.cumsum(ostart)
        self._rebuild(history=(ostart, np.asarray(d["hist_j"], dtype=np.int64)[order],
                               np.ascontiguousarray(np.asarray(d["hist_v"], dtype=np.float64)[order].reshape(-1, 3))))

    def by_id(self, a):
        """Copy of a per-particle array (or ``whist``, W rows per particle) in particle-id order."""
        a = np.asarray(a)
        if not self.sort or self.n == 0:
            return a.copy()
        block = a.shape[0] // self.n
        out = np.empty_like(a)
        if block == 1:
            out[self.particle_order] = a
        elif block > 1:
            rows = (self.particle_order[:, None] * block + np.arange(block)[None, :]).ravel()
            out[rows] = a
        return out

    def kinetic_energy(self):
        """Translational + rotational kinetic energy (J)."""
        e = 0.5 * np.sum(self.mass * np.sum(self.vel**2, axis=1))
        if self.rotation:
            e += 0.5 * np.sum(self.inertia * np.sum(self.omega**2, axis=1))
        return float(e)

    def critical_dt(self):
        """Critical explicit step (s) from the stiffest contact now present.

        ``2/omega (sqrt(1 + zeta^2) - zeta)`` with ``omega^2 = max k/m_eff`` and
        ``zeta = max(eta/m_eff) / (2 omega)``: the stability limit of
        velocity Verlet for a damped linear oscillator.  ``inf`` without contacts.
        """
        return critical_step(self.diag[D_MAX_W2], self.diag[D_MAX_DAMP])


def critical_step(w2, damp_rate):
    """Stability limit of velocity Verlet for ``x'' + c x' + w2 x = 0`` (s)."""
    if w2 <= 0 and damp_rate <= 0:
        return np.inf
    if w2 <= 0:
        return 2.0 / damp_rate
    w = math.sqrt(w2)
    zeta = damp_rate / (2.0 * w)
    return 2.0 / w * (math.sqrt(1.0 + zeta * zeta) - zeta)


# --------------------------------------------------------------------------- scenes

def scene_walls(scene):
    """Wall planes (W, 6) of a scene: substrate, solid side walls, top plane."""
    L = scene.domain.size
    w = []
    b = scene.boundaries
    if b.bottom_wall:
        w.append([0, 0, 0, 0, 0, 1])
    if b.x == "wall":
        w += [[0, 0, 0, 1, 0, 0], [L[0], 0, 0, -1, 0, 0]]
    if b.y == "wall":
        w += [[0, 0, 0, 0, 1, 0], [0, L[1], 0, 0, -1, 0]]
    if b.top == "wall":
        w.append([0, 0, L[2], 0, 0, -1])
    return np.array(w, dtype=np.float64).reshape(-1, 6)


def _power_force(cp, delta, ri, rj, wall):
    """Seed power-law contact force magnitude (N) at overlap ``delta`` (vectorised)."""
    delta = np.asarray(delta, dtype=float)
    if wall:
        eps = delta / ri
        d = ri - delta
        a2 = ri * ri - d * d
    else:
        d = ri + rj - delta
        eps = delta / (ri + rj)
        li = 0.5 * (d + (ri * ri - rj * rj) / d)
        a2 = ri * ri - li * li
    area = np.pi * np.clip(a2, 0, None)
    return cp[0] * eps ** cp[1] * area, area


def auto_dt(inter, radius, mass, fconst, gamma=None, drag=False, v0=None, height=1.0, n_layers=None, charge=None):
    """Time step (s) from the physics, and a dict saying why.

    * contact: ``dt_safety`` x the velocity-Verlet stability limit of the
      stiffest contact (Hooke: ``kn`` with the smallest reduced mass; power law:
      the stiffness ``dF/d delta`` and damping ``c_cd A_c`` at a representative
      overlap - the larger of the impact overlap, from the kinetic energy of a
      particle that falls ``height`` under the external force, and the static
      overlap under ``n_layers`` particles' weight);
    * non-contact laws (near-field, van der Waals...): ``dt_safety`` x the
      stability limit of their largest stiffness |dF/dr| near contact
      (:func:`sim.forces.nearfield.law_scales`, sampled, law-agnostic); their
      largest force sets ``law_speed`` (terminal speed with drag), which the
      run's runaway-speed guard allows for;
    * drag: ``0.2 m / gamma`` (momentum relaxation time);
    * motion: a particle moves at most 5 % of the smallest radius per step.
    """
    from sim.forces.contact import CONTACT_HOOKE, CONTACT_POWER

    rmin = float(np.min(radius))
    mmin = float(np.min(mass))
    amax = float(np.max(np.linalg.norm(fconst, axis=1) / mass)) if len(mass) else 0.0
    vfree = math.sqrt(2.0 * amax * height)
    vterm = np.inf
    if drag and gamma is not None and np.all(np.asarray(gamma) > 0):
        vterm = float(np.max(np.linalg.norm(fconst, axis=1) / gamma))
    vimp = min(vfree, vterm) + (float(np.max(np.linalg.norm(v0, axis=1))) if v0 is not None and len(v0) else 0.0)
    why = {}
    dts = []
    if n_layers is None:
        n_layers = max(1.0, len(mass) ** (1.0 / 3.0))
    for wall, cp in ((False, inter.cp), (True, inter.cpw)):
        meff = mmin if wall else 0.5 * mmin
        if inter.model == CONTACT_HOOKE:
            w2 = cp[0] / meff
            dc = critical_step(w2, 2.0 * cp[2] * math.sqrt(w2))
        elif inter.model == CONTACT_POWER:
            rj = rmin
            deltas = np.geomspace(1e-7 * rmin, 0.5 * rmin, 4000)
            F, area = _power_force(cp, deltas, rmin, rj, wall)
            energy = np.concatenate([[0.0], np.cumsum(0.5 * (F[1:] + F[:-1]) * np.diff(deltas))])
            k_imp = np.searchsorted(energy, 0.5 * meff * vimp**2)
            k_stat = np.searchsorted(F, n_layers * mmin * amax)
            k = min(max(k_imp, k_stat, 1), len(deltas) - 2)
            stiff = (F[k + 1] - F[k - 1]) / (deltas[k + 1] - deltas[k - 1])
            dc = critical_step(stiff / meff, cp[2] * area[k] / meff)
            why[f"{'wall' if wall else 'pair'}_overlap_rep"] = float(deltas[k])
        else:
            continue
        why[f"{'wall' if wall else 'pair'}_critical_dt"] = dc
        dts.append(inter.dt_safety * dc)
    if len(inter.pair_laws) or len(inter.wall_laws):
        from sim.forces.nearfield import law_scales

        fl, kl = law_scales(inter.pair_laws, inter.wall_laws, radius, np.zeros(1) if charge is None else charge)
        if kl > 0:
            dc = critical_step(kl / (0.5 * mmin), 0.0)
            why["law_critical_dt"] = dc
            dts.append(inter.dt_safety * dc)
        if fl > 0:
            if drag and gamma is not None and np.all(np.asarray(gamma) > 0):
                why["law_speed"] = fl / float(np.min(gamma))
            else:
                why["law_speed"] = math.sqrt(fl * 0.2 * rmin / mmin)
    if drag and gamma is not None and np.all(np.asarray(gamma) > 0):
        tr = float(np.min(mass / gamma))
        why["momentum_relaxation_time"] = tr
        dts.append(0.2 * tr)
    if vimp > 0:
        why["impact_speed"] = vimp
        dts.append(0.05 * rmin / vimp)
    dt = float(min(dts)) if dts else 1e-6
    why["dt"] = dt
    return dt, why


def system_from_scene(scene, state=None, dt=None, sort=False, threads=1):
    """Build a :class:`DEMSystem` for a scene with pair interactions; returns ``(system, state)``.

    ``sort`` and ``threads`` are :class:`DEMSystem`'s options (cell-ordered memory, pair-kernel threads).
    """
    from sim.state import build_state, constant_force

    inter = scene.interactions
    st = build_state(scene) if state is None else state
    fconst = constant_force(scene, st)
    fl = scene.fluid
    drag_mode = DRAG_SEED if fl.viscosity > 0 else DRAG_NONE
    extp = np.array([*fl.velocity, fl.density, fl.viscosity, scene.kT, *scene.fields.B], dtype=np.float64)
    periodic = (int(scene.boundaries.x == "periodic"), int(scene.boundaries.y == "periodic"), 0)
    system = DEMSystem(st.pos, st.vel, st.radius, st.mass, st.charge, model=inter.model, cp=inter.cp,
                       cpw=inter.cpw, pair_laws=inter.pair_laws, wall_laws=inter.wall_laws,
                       rotation=inter.rotation, walls=scene_walls(scene), box_lo=(0, 0, 0),
                       box_length=scene.domain.size, periodic=periodic, fconst=fconst, drag_mode=drag_mode,
                       gamma=st.gamma, extp=extp, dt=1e-9 if dt is None else dt, skin=inter.skin,
                       cutoff=inter.cutoff, seed=scene.seed, max_overlap=inter.max_overlap, sort=sort,
                       threads=threads, **_integrator_options(scene))
    return system, st


def _integrator_options(scene):
    """integrator.kind = "trapezoidal" selects the seed's phi-scheme (eq. 3.28-3.29) with
    fixed-point iterations; everything else uses velocity Verlet."""
    it = scene.integrator
    if it.kind == "trapezoidal":
        return dict(integrator=PHI_SCHEME, phi=it.phi, n_iter=it.max_iterations, tol=it.tolerance)
    return dict(integrator=VERLET)


def _frame_df(frame, system):
    n = system.n
    up = system.by_id(system.unwrapped)
    vel = system.by_id(system.vel)
    import pandas as pd

    return pd.DataFrame({
        "frame": np.full(n, frame, dtype=np.int64), "t": np.full(n, system.t), "particle": np.arange(n, dtype=np.int64),
        "x": up[:, 0], "y": up[:, 1], "z": up[:, 2],
        "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2], "radius": system.by_id(system.radius),
    })


class DEMResult:
    """What :func:`run_dem` did: attributes like :class:`sim.run.RunResult` plus a summary dict.

    ``result["steps"]`` etc. read the summary (keys: steps, wall_time_s,
    n_frames, dt_final, dt_min, dt_max, max_overlap_ratio, n_builds,
    rollbacks, resumed_from_step).
    """

    already_complete = False  # as sim.run.RunResult: True only for a --resume of a finished run

    def __init__(self, trajectories, scene_json, n_frames, wall_time_s, summary, system):
        self.trajectories = trajectories
        self.scene_json = scene_json
        self.choice = None
        self.n_frames = n_frames
        self.wall_time_s = wall_time_s
        self.summary = summary
        self.system = system

    def __getitem__(self, k):
        return self.summary[k]

    def keys(self):
        return self.summary.keys()


def dem_threads(scene=None, threads=None):
    """Threads of the DEM pair kernel: ``threads`` if given, else the scene's ``contact.threads`` (when the
    schema has it), else the environment variable ``PTRACK_THREADS``, else 1 (serial, bit-reproducible)."""
    import os

    from ptrack.errors import UserError

    if threads is None and scene is not None and scene.interactions is not None:
        threads = getattr(scene.interactions, "threads", None)
    src = "threads"
    if threads is None and os.environ.get("PTRACK_THREADS"):
        threads, src = os.environ["PTRACK_THREADS"], "PTRACK_THREADS"
    if threads is None:
        return 1
    try:
        t = int(threads)
    except (TypeError, ValueError):
        t = 0
    if t < 1:
        raise UserError(f"{src} = {threads!r} is not a positive whole number", "give 1, 2, ... threads")
    return t


def busy_cores_warning(threads, load=None, ncpu=None):
    """Why a ``threads``-thread DEM run would be slow on this machine now, or None.

    Every step of a threaded run waits at its parallel regions for the slowest thread, so a thread that
    shares its core with another process holds the whole step, often past the time of one thread (README,
    "DEM on 2 threads").  ``load``: the 1-minute load average (default
    ``os.getloadavg()``), read as the cores other processes use; ``ncpu``: the cores this process may
    use (default its CPU affinity).

    Examples
    --------
    >>> from sim.dem import busy_cores_warning
    >>> busy_cores_warning(2, load=0.1, ncpu=2) is None
    True
    >>> busy_cores_warning(2, load=1.9, ncpu=2).startswith("load average 1.9")
    True
    """
    import os

    if threads <= 1:
        return None
    if ncpu is None:
        ncpu = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if threads > ncpu:
        return (f"{threads} threads on {ncpu} core(s): threads share cores and every step waits for them; "
                f"use --threads {ncpu} or fewer")
    if load is None:
        try:
            load = os.getloadavg()[0]
        except OSError:
            return None
    if load + threads > ncpu + 0.5:
        return (f"load average {load:.1f} on {ncpu} cores: other processes hold cores, and a {threads}-thread run "
                "waits at every step for a thread that lost its core (often slower than one thread); "
                "use --threads 1, or run when the machine is quiet")
    return None


def run_dem(scene, out_dir, resume=False, progress=True, checkpoint_every=None, max_rollbacks=12, threads=None):
    """Run a scene with pair interactions; stream ``trajectories.parquet``.

    Parameters
    ----------
    scene : sim.scene.Scene
        With ``scene.interactions`` from :func:`sim.interactions.parse_interactions`.
    out_dir : path-like
        Receives ``trajectories.parquet`` (frame, t, particle, x, y, z
        unwrapped, vx, vy, vz, radius), ``scene.json`` (resolved scene, dt and
        why), ``checkpoint.npz`` (every ``checkpoint_every`` frames) and, on a
        blow-up, ``last_good_state.npz``. A folder holding an earlier run gets
        that run's files moved into ``previous/`` (one generation) (:func:`sim.driver.prepare_out_dir`).
    resume : bool
        Continue from ``out_dir/checkpoint.npz``; the result equals the
        uninterrupted run bit for bit. The checkpoint, its committed table
        segments and the scene (with its seed) must belong together, else the
        resume is refused and nothing is written.
    progress : bool
        tqdm bar on stderr.
    checkpoint_every : int, optional
        Output frames between checkpoints (default ``contact.checkpoint_every``).
    threads : int, optional
        Pair-kernel threads (:func:`dem_threads`: default the scene's, else
        ``PTRACK_THREADS``, else 1). With T > 1 the pair sums are taken in T
        blocks: reproducible for a given T, round-off apart from T = 1.

    The particles are kept in cell order in memory (``DEMSystem(sort=True)``);
    the table is in particle-id order as always.

    Returns
    -------
    DEMResult

    Raises
    ------
    UserError
        Blow-up (overlap, NaN, substrate crossing, runaway speed) naming the
        step, the particle and a suggested dt; the frames so far stay in the
        trajectories file (marked incomplete) and the last good state is in
        ``last_good_state.npz``. Overlapping particles at the start (blamed on
        the placement). A resume without a matching checkpoint.
    KeyboardInterrupt
        SIGINT or SIGTERM: the frames so far are in the table (marked
        incomplete) and the last checkpoint with its segments is kept for
        ``resume``.
    """
    import json
    import sys
    from pathlib import Path

    from tqdm import tqdm

    from ptrack.errors import UserError, atomic_output
    from sim.checkpoint import load_checkpoint, save_checkpoint, scene_fingerprint
    from sim.driver import (InterruptGuard, Periodic, RunFailure, SegmentedTable, WallClockChunker,
                            discard_if_empty, prepare_out_dir, run_frames)

    t_wall = time.perf_counter()
    inter = scene.interactions
    out_dir = Path(out_dir)
    traj_path = out_dir / "trajectories.parquet"
    ck_path = out_dir / "checkpoint.npz"
    scene_json = out_dir / "scene.json"
    sdict = scene.to_dict()
    fp = scene_fingerprint(sdict)  # covers the seed (a scene field)
    data = head = None
    if resume:
        # refused at once, before any work or any write
        data, head = load_checkpoint(ck_path, fp)
        if not (out_dir / ".segments").is_dir():
            raise UserError(f"{out_dir} has a checkpoint but no committed table segments (the run finished, "
                            "or it was written by an older version)", "rerun without --resume")
        created = False
    else:
        created = prepare_out_dir(out_dir)
    try:
        nthreads = dem_threads(scene, threads)
        busy = busy_cores_warning(nthreads)
        if busy:
            logging.getLogger("sim.dem").warning("warning: %s", busy)
        system, st = system_from_scene(scene, sort=True, threads=nthreads)
        _check_start(system, inter)
    except UserError:
        discard_if_empty(out_dir, created)
        raise
    ck_every = inter.checkpoint_every if checkpoint_every is None else int(checkpoint_every)
    fixed_dt = scene.time.dt is not None
    dt_auto, why = auto_dt(inter, st.radius, st.mass, system.fconst, st.gamma, drag=system.drag_mode != DRAG_NONE,
                           v0=st.vel, height=float(np.max(st.pos[:, 2])) if st.n else 1.0, charge=st.charge)
    dt0 = scene.time.dt if fixed_dt else dt_auto
    system.dt = dt0
    # runaway-speed limit: 20x the largest speed the external forces, the non-contact laws, the initial
    # velocities and thermal motion can explain
    v_ref = max(why.get("impact_speed", 0.0), why.get("law_speed", 0.0),
                float(np.max(np.linalg.norm(st.vel, axis=1))) if st.n else 0.0,
                5.0 * math.sqrt(scene.kT / float(np.min(st.mass))) if scene.kT > 0 else 0.0)
    if v_ref > 0:
        system.guards[G_V_MAX] = 20.0 * v_ref
    why["v_max"] = float(system.guards[G_V_MAX])
    n_out = int(round(scene.time.final / scene.time.output_interval))
    dt_out = scene.time.output_interval
    resolved = {"scene": sdict, "engine": "dem", "contact_model": inter.model_name,
                "integrator": "phi-scheme (seed eq. 3.28-3.29, fixed-point)" if system.integrator == PHI_SCHEME
                else "velocity Verlet",
                "dt": dt0, "dt_mode": "fixed (time.dt)" if fixed_dt else "auto + adaptive" if inter.adaptive_dt else "auto",
                "dt_reason": why, "n_output_frames": n_out + 1, "units": "SI",
                "coordinates": "unwrapped across periodic sides"}
    meta = {"source": "sim-dem", "frame_interval": dt_out, "scene": scene.source, "dt": dt0, "seed": scene.seed,
            "contact_model": inter.model_name, "run": fp}
    frame = 0
    resumed_from = None
    if resume:
        table = SegmentedTable(out_dir, meta, committed=head.get("segments", []))
        table.check_committed(fp, int(head["frame"]))
        system.set_state(data)
        frame = int(head["frame"])
        resumed_from = system.step
    else:
        table = SegmentedTable(out_dir, meta)
    with atomic_output(scene_json, "w") as fh:
        json.dump(resolved, fh, indent=2, default=float)
    bar = tqdm(total=n_out, initial=frame, desc="dem", unit="frame", disable=not progress, file=sys.stderr)
    summary = {"steps": 0, "dt_min": system.dt, "dt_max": system.dt, "max_overlap_ratio": 0.0, "rollbacks": 0,
               "n_builds": 0}
    chunker = WallClockChunker(first=max(1, 200_000 // max(system.n, 1)))
    guard = InterruptGuard()
    trigger = Periodic(ck_every)

    def advance(frame, k):
        """One output frame, with the dt policy: rollback and retry with a smaller dt on a blow-up
        (adaptive dt), else stop with the last good state saved; afterwards adapt dt to the contacts."""
        t_next = (frame + 1) * dt_out
        good = system.get_state()
        good_dt = system.dt
        tries = 0
        # the neighbour list is rebuilt at the end of checkpoint frames (in the resumed run too)
        is_ck = trigger.ahead(frame + 1)
        while True:
            nsteps = max(1, int(round((t_next - system.t) / system.dt)))
            status = system.run(nsteps, rebuild_at_end=is_ck, poll=guard.check, chunker=chunker)
            if status == OK:
                break
            bad_step, bad_p = system.step, system.fail_particle
            crit = critical_step(system.chunk_peaks[P_W2], system.chunk_peaks[P_DAMP])
            suggest = min(system.dt / 4.0, inter.dt_safety * crit)
            if fixed_dt or not inter.adaptive_dt or tries >= max_rollbacks:
                system.set_state(good)
                system.dt = good_dt
                np.savez(out_dir / "last_good_state.npz", **good)
                reason = STATUS_TEXT[status]
                if fixed_dt:
                    fix = f"reduce time.dt to about {suggest:.2g} s or use time.dt = \"auto\""
                else:
                    # dt is automatic already: advising "auto" would be circular
                    fix = (f"the automatic dt ({good_dt:.3g} s, {tries} rollbacks) did not resolve it: lower "
                           f"contact.dt_safety (now {inter.dt_safety:g}), or check the stiffness, charges and "
                           "fields of the scene")
                err = UserError(
                    f"DEM blow-up at step {bad_step} (t = {bad_step * good_dt:.6g} s): {reason}, particle "
                    f"{bad_p} (dt = {good_dt:.3g} s); frames so far in {traj_path}, last good state in "
                    f"{out_dir / 'last_good_state.npz'}", fix)
                raise RunFailure(f"blow-up at step {bad_step}: {reason}", err)
            # adaptive: roll back to the start of the frame and retry with a smaller step
            system.set_state(good)
            system.dt = min(good_dt, suggest) if tries == 0 else system.dt * 0.5
            tries += 1
            summary["rollbacks"] += 1
        summary["max_overlap_ratio"] = max(summary["max_overlap_ratio"], float(system.chunk_peaks[P_OVERLAP]))
        df = _frame_df(frame + 1, system)
        if not fixed_dt and inter.adaptive_dt:
            crit = critical_step(system.chunk_peaks[P_W2], system.chunk_peaks[P_DAMP])
            vmax = float(np.sqrt(np.max(np.sum(system.vel**2, axis=1)))) if system.n else 0.0
            # shrink when the contacts present are stiffer than the a-priori
            # estimate; never grow beyond it (new impacts come unannounced)
            target = min(inter.dt_safety * crit, 0.05 * float(np.min(system.radius)) / max(vmax, 1e-300), dt0)
            system.dt = float(min(target, 1.25 * system.dt))
        summary["dt_min"] = min(summary["dt_min"], system.dt)
        summary["dt_max"] = max(summary["dt_max"], system.dt)
        return df, 1

    def checkpoint(frame, names):
        save_checkpoint(ck_path, system.get_state(), {"frame": frame, "fingerprint": fp, "seed": scene.seed,
                                                      "segments": names})

    run_frames(table=table, traj_path=traj_path, meta=meta, frame=frame, n_out=n_out, advance=advance,
               first=None if resume else _frame_df(0, system), checkpoint=checkpoint, trigger=trigger,
               guard=guard, bar=bar)
    wall = time.perf_counter() - t_wall
    summary.update({"steps": int(system.step), "wall_time_s": wall, "n_frames": n_out + 1, "dt_final": system.dt,
                    "n_builds": int(system.n_builds), "resumed_from_step": resumed_from,
                    "n_particles": int(system.n), "threads": int(system.threads)})
    with atomic_output(out_dir / "dem_summary.json", "w") as fh:
        json.dump(summary, fh, indent=2, default=float)
    return DEMResult(traj_path, scene_json, n_out + 1, wall, summary, system)


def _check_start(system, inter):
    """Refuse a start whose particles already overlap beyond the blow-up limit (a placement problem,
    not a time-step one)."""
    from ptrack.errors import UserError

    ov = float(system.diag[D_MAX_OVERLAP])
    if ov > inter.max_overlap:
        i = int(system.particle_order[int(system.diag[D_MAX_OVERLAP_I])])
        raise UserError(f"the starting positions overlap: particle {i} overlaps a neighbour or a wall by {ov:.3g} "
                        f"of its radius (limit contact.max_overlap = {inter.max_overlap:g})",
                        "place the particles without overlap: a larger domain or placement_z range, fewer "
                        "particles, or a smaller radius_variation")
