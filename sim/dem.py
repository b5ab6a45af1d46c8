"""The DEM engine: velocity-Verlet (or the seed's phi-scheme) time stepping of
spheres with contact, bonding, friction, near-field and wall forces.

Layout (jax-md / HOOMD style: small pieces composed by the caller):

* :class:`DEMSystem` holds the state as contiguous float64 arrays (structure
  of arrays), the force-model parameters, the box and the neighbour list with
  per-entry contact history.  ``system.run(n)`` advances ``n`` steps inside one
  compiled kernel (:func:`_run_chunk`): no Python per step, no allocation per
  step (the list is rebuilt - and only then allocated - when some particle
  moved more than half the skin).
* :func:`run_dem` runs a :class:`sim.scene.Scene` that has pair interactions:
  automatic and adaptive dt, streamed output through
  :class:`ptrack.table.TrajectoryWriter` (unwrapped coordinates), atomic
  checkpoints and ``resume``, blow-up detection with the last good state saved.

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

import math
import time

import numpy as np
from numba import njit

from sim.forces.contact import (D_MAX_DAMP, D_MAX_OVERLAP, D_MAX_OVERLAP_I, D_MAX_W2, D_N_CONTACTS, D_SIZE,
                                pair_forces, wall_forces)
from sim.forces.drag import drag_force_scalar
from sim.neighbors import _build, carry_history, needs_rebuild, wrap_positions

OK, BLOWUP_OVERLAP, BLOWUP_NAN, BLOWUP_WALL, BLOWUP_SPEED = 0, 1, 2, 3, 4
STATUS_TEXT = {
    BLOWUP_OVERLAP: "overlap beyond the allowed fraction of a radius",
    BLOWUP_NAN: "NaN or infinite position/velocity",
    BLOWUP_WALL: "particle centre went through the substrate",
    BLOWUP_SPEED: "runaway speed (kinetic energy)",
}

DRAG_NONE, DRAG_STOKES, DRAG_SEED = 0, 1, 2

# --------------------------------------------------------------------------- random numbers


@njit(cache=True, inline="always")
def _mix64(z):
    # splitmix64 finaliser on uint64
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def counter_normal(seed, step, index):
    """Standard normal number keyed by (seed, step, index): same key, same number."""
    key = np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(step) * np.uint64(0xD1B54A32D192ED03) \
        + np.uint64(index) * np.uint64(0x8CB92BA72F3D8DD7)
    a = _mix64(key)
    b = _mix64(a + np.uint64(0x9E3779B97F4A7C15))
    u1 = ((a >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740993.0)  # (0, 1]
    u2 = (b >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


# --------------------------------------------------------------------------- force evaluation


@njit(cache=True)
def _external(pos, vel, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt, force):
    """Constant force + drag + magnetic Lorentz + Brownian, added to ``force``.

    ``extp = [vf_x, vf_y, vf_z, rho_f, mu, kT, B_x, B_y, B_z]``.
    """
    n = pos.shape[0]
    magnetic = extp[6] != 0.0 or extp[7] != 0.0 or extp[8] != 0.0
    kT = extp[5]
    for i in range(n):
        fx = fconst[i, 0]
        fy = fconst[i, 1]
        fz = fconst[i, 2]
        if drag_mode == 1:
            g = gamma[i]
            fx += g * (extp[0] - vel[i, 0])
            fy += g * (extp[1] - vel[i, 1])
            fz += g * (extp[2] - vel[i, 2])
        elif drag_mode == 2:
            dx, dy, dz = drag_force_scalar(extp[0] - vel[i, 0], extp[1] - vel[i, 1], extp[2] - vel[i, 2],
                                           radius[i], extp[3], extp[4])
            fx += dx
            fy += dy
            fz += dz
        if magnetic:
            q = charge[i]
            vx = vel[i, 0]
            vy = vel[i, 1]
            vz = vel[i, 2]
            fx += q * (vy * extp[8] - vz * extp[7])
            fy += q * (vz * extp[6] - vx * extp[8])
            fz += q * (vx * extp[7] - vy * extp[6])
        if kT > 0.0:
            s = math.sqrt(2.0 * gamma[i] * kT / dt)
            fx += s * counter_normal(seed, step, 3 * i)
            fy += s * counter_normal(seed, step, 3 * i + 1)
            fz += s * counter_normal(seed, step, 3 * i + 2)
        force[i, 0] += fx
        force[i, 1] += fy
        force[i, 2] += fz


@njit(cache=True)
def _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
            model, cp, cpw, nf_model, nfp, rotation, walls, whist, start, nbj, shift, hist,
            force, torque, diag):
    force[:, :] = 0.0
    if rotation:
        torque[:, :] = 0.0
    for k in range(D_SIZE):
        diag[k] = 0.0
    _external(pos, vel, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt, force)
    if model != 0 or nf_model != 0:
        pair_forces(pos, vel, omega, radius, mass, charge, start, nbj, shift, hist, force, torque,
                    model, cp, nf_model, nfp, rotation, dt, diag)
    if walls.shape[0] > 0 and model != 0:
        wall_forces(pos, vel, omega, radius, mass, walls, whist, force, torque, model, cpw, rotation, dt, diag)


@njit(cache=True)
def _check(pos, vel, radius, limits):
    """Return (status, particle) for NaN, substrate crossing, runaway speed."""
    vmax2 = limits[1] * limits[1]
    bottom = limits[2] != 0.0
    for i in range(pos.shape[0]):
        z = pos[i, 2]
        v2 = vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1] + vel[i, 2] * vel[i, 2]
        if not (math.isfinite(pos[i, 0]) and math.isfinite(pos[i, 1]) and math.isfinite(z)
                and math.isfinite(v2)):
            return BLOWUP_NAN, i
        if bottom and z < 0.0:
            return BLOWUP_WALL, i
        if v2 > vmax2:
            return BLOWUP_SPEED, i
    return OK, -1


@njit(cache=True)
def _run_chunk(nsteps, dt, step0, integrator, phi, n_iter,
               pos, image, vel, omega, force, torque, radius, mass, inertia, charge, gamma, fconst,
               drag_mode, extp, seed, model, cp, cpw, nf_model, nfp, rotation, walls, whist,
               start, nbj, shift, hist, ref_pos, cutoff, skin, lo, length, periodic, limits, diag,
               force_rebuild_at_end):
    """Advance up to ``nsteps`` steps.  Returns
    ``(status, steps_done, particle, start, nbj, shift, hist, ref_pos, n_builds)``.

    integrator 0: velocity Verlet (kick-drift-kick; velocity-dependent forces
    use the half-step velocity, as in LAMMPS).  integrator 1: the seed's
    eq. 3.28-3.29 phi-scheme with ``n_iter`` fixed-point iterations on the
    end-of-step forces (phi = 0: forward Euler).
    """
    n = pos.shape[0]
    nbuild = 0
    hdt = 0.5 * dt
    # buffers for the phi-scheme (allocated once per chunk)
    if integrator == 1:
        x0 = np.empty_like(pos)
        v0 = np.empty_like(vel)
        w0 = np.empty_like(omega)
        f0 = np.empty_like(force)
        t0 = np.empty_like(torque)
    else:
        x0 = np.empty((0, 3))
        v0 = np.empty((0, 3))
        w0 = np.empty((0, 3))
        f0 = np.empty((0, 3))
        t0 = np.empty((0, 3))
    for s in range(nsteps):
        step = step0 + s + 1
        if integrator == 0:
            for i in range(n):
                im = hdt / mass[i]
                vel[i, 0] += im * force[i, 0]
                vel[i, 1] += im * force[i, 1]
                vel[i, 2] += im * force[i, 2]
                pos[i, 0] += dt * vel[i, 0]
                pos[i, 1] += dt * vel[i, 1]
                pos[i, 2] += dt * vel[i, 2]
            if rotation:
                for i in range(n):
                    ii = hdt / inertia[i]
                    omega[i, 0] += ii * torque[i, 0]
                    omega[i, 1] += ii * torque[i, 1]
                    omega[i, 2] += ii * torque[i, 2]
            if needs_rebuild(pos, ref_pos, skin):
                wrap_positions(pos, image, lo, length, periodic)
                ns, nj, nsh = _build(pos, radius, cutoff, skin, lo, length, periodic)
                hist = carry_history(start, nbj, hist, ns, nj)
                start = ns
                nbj = nj
                shift = nsh
                ref_pos[:, :] = pos
                nbuild += 1
            _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                    model, cp, cpw, nf_model, nfp, rotation, walls, whist, start, nbj, shift, hist,
                    force, torque, diag)
            for i in range(n):
                im = hdt / mass[i]
                vel[i, 0] += im * force[i, 0]
                vel[i, 1] += im * force[i, 1]
                vel[i, 2] += im * force[i, 2]
            if rotation:
                for i in range(n):
                    ii = hdt / inertia[i]
                    omega[i, 0] += ii * torque[i, 0]
                    omega[i, 1] += ii * torque[i, 1]
                    omega[i, 2] += ii * torque[i, 2]
        else:
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
                        model, cp, cpw, nf_model, nfp, rotation, walls, whist, start, nbj, shift, hist,
                        force, torque, diag)
                for i in range(n):
                    for c in range(3):
                        vel[i, c] = v0[i, c] + dt / mass[i] * (phi * force[i, c] + (1.0 - phi) * f0[i, c])
                        pos[i, c] = x0[i, c] + dt * (phi * vel[i, c] + (1.0 - phi) * v0[i, c])
                        if rotation:
                            omega[i, c] = w0[i, c] + dt / inertia[i] * (phi * torque[i, c] + (1.0 - phi) * t0[i, c])
            hist[:, :] = hist0
            whist[:, :] = whist0
            if needs_rebuild(pos, ref_pos, skin):
                wrap_positions(pos, image, lo, length, periodic)
                ns, nj, nsh = _build(pos, radius, cutoff, skin, lo, length, periodic)
                hist = carry_history(start, nbj, hist, ns, nj)
                start = ns
                nbj = nj
                shift = nsh
                ref_pos[:, :] = pos
                nbuild += 1
            _forces(pos, vel, omega, radius, mass, charge, gamma, fconst, drag_mode, extp, seed, step, dt,
                    model, cp, cpw, nf_model, nfp, rotation, walls, whist, start, nbj, shift, hist,
                    force, torque, diag)
        if diag[D_MAX_OVERLAP] > limits[0]:
            return BLOWUP_OVERLAP, s + 1, int(diag[D_MAX_OVERLAP_I]), start, nbj, shift, hist, ref_pos, nbuild
        st, p = _check(pos, vel, radius, limits)
        if st != OK:
            return st, s + 1, p, start, nbj, shift, hist, ref_pos, nbuild
    if force_rebuild_at_end:
        # deterministic restart point: list rebuilt from these exact positions
        wrap_positions(pos, image, lo, length, periodic)
        ns, nj, nsh = _build(pos, radius, cutoff, skin, lo, length, periodic)
        hist = carry_history(start, nbj, hist, ns, nj)
        start = ns
        nbj = nj
        shift = nsh
        ref_pos[:, :] = pos
        nbuild += 1
    return OK, nsteps, -1, start, nbj, shift, hist, ref_pos, nbuild


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
    nf_model, nfp : int, array
        Near-field law and parameters (:mod:`sim.forces.nearfield`).
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
    """

    def __init__(self, pos, vel, radius, mass, charge=None, *, model=1, cp=None, cpw=None, nf_model=0,
                 nfp=None, rotation=True, walls=None, box_lo=(0, 0, 0), box_length=(1, 1, 1),
                 periodic=(0, 0, 0), fconst=None, drag_mode=DRAG_NONE, gamma=None, extp=None, dt=1e-6,
                 skin=None, cutoff=0.0, seed=0, max_overlap=0.5, v_max=np.inf, integrator=0, phi=0.0,
                 n_iter=3):
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
        self.nf_model = int(nf_model)
        self.nfp = f64(np.zeros(5) if nfp is None else nfp)
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
        self.limits = f64([max_overlap, v_max, 1.0 if self._has_bottom() else 0.0])
        self.integrator = int(integrator)
        self.phi = float(phi)
        self.n_iter = int(n_iter)
        self.step = 0
        self.t = 0.0
        self.n_builds = 0
        self.diag = np.zeros(D_SIZE)
        self.status = OK
        self.fail_particle = -1
        from sim.neighbors import wrap_positions as _wrap

        _wrap(self.pos, self.image, self.lo, self.length, self.periodic)
        self._rebuild(history=None)
        self.compute_forces()

    # ------------------------------------------------------------------ helpers
    def _has_bottom(self):
        return any(np.allclose(w, [w[0], w[1], 0.0, 0.0, 0.0, 1.0]) for w in getattr(self, "walls", []))

    @property
    def n(self):
        return len(self.pos)

    def _rebuild(self, history):
        from sim.neighbors import build_neighbor_list

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
        _forces(self.pos, self.vel, self.omega, self.radius, self.mass, self.charge, self.gamma, self.fconst,
                self.drag_mode, self.extp, self.seed, self.step, self.dt, self.model, self.cp, self.cpw,
                self.nf_model, self.nfp, self.rotation, self.walls, self.whist, self.start, self.nbj,
                self.shift, self.hist, self.force, self.torque, self.diag)

    @property
    def unwrapped(self):
        """Unwrapped positions (m), continuous across periodic boundaries."""
        return self.pos + self.image * self.length[None, :]

    def run(self, nsteps, rebuild_at_end=False):
        """Advance ``nsteps`` steps; returns the status code (0 = fine).

        On a blow-up the state is left at the failing step and
        ``self.fail_particle`` names the particle.
        """
        out = _run_chunk(int(nsteps), self.dt, self.step, self.integrator, self.phi, self.n_iter,
                         self.pos, self.image, self.vel, self.omega, self.force, self.torque, self.radius,
                         self.mass, self.inertia, self.charge, self.gamma, self.fconst, self.drag_mode,
                         self.extp, self.seed, self.model, self.cp, self.cpw, self.nf_model, self.nfp,
                         self.rotation, self.walls, self.whist, self.start, self.nbj, self.shift, self.hist,
                         self.ref_pos, self.cutoff, self.skin, self.lo, self.length, self.periodic, self.limits,
                         self.diag, bool(rebuild_at_end))
        status, done, part, self.start, self.nbj, self.shift, self.hist, self.ref_pos, nb = out
        self.step += done
        self.t += done * self.dt
        self.n_builds += nb
        self.status = status
        self.fail_particle = part
        return status

    # ------------------------------------------------------------------ state I/O
    STATE_ARRAYS = ("pos", "image", "vel", "omega", "force", "torque", "whist", "fconst", "radius", "mass",
                    "charge", "gamma")

    def get_state(self):
        """Neighbour-list-independent snapshot (dict of arrays/scalars).

        Contact history is stored as (i, j, spring) triples of the non-zero
        entries, so it can be mapped onto any list built later.
        """
        d = {k: getattr(self, k).copy() for k in self.STATE_ARRAYS}
        ii = np.repeat(np.arange(self.n), np.diff(self.start))
        nz = np.any(self.hist != 0.0, axis=1)
        d["hist_i"] = ii[nz]
        d["hist_j"] = self.nbj[nz]
        d["hist_v"] = self.hist[nz]
        d["step"] = np.int64(self.step)
        d["t"] = np.float64(self.t)
        d["dt"] = np.float64(self.dt)
        return d

    def set_state(self, d):
        """Restore a snapshot from :meth:`get_state` (rebuilds the neighbour list)."""
        for k in self.STATE_ARRAYS:
            setattr(self, k, np.ascontiguousarray(d[k], dtype=np.float64))
        self.step = int(d["step"])
        self.t = float(d["t"])
        self.dt = float(d["dt"])
        hi = np.asarray(d["hist_i"], dtype=np.int64)
        order = np.argsort(hi, kind="stable")
        hi = hi[order]
        ostart = np.zeros(self.n + 1, dtype=np.int64)
        np.add.at(ostart, hi + 1, 1)
        ostart = np.cumsum(ostart)
        self._rebuild(history=(ostart, np.asarray(d["hist_j"], dtype=np.int64)[order],
                               np.ascontiguousarray(np.asarray(d["hist_v"], dtype=np.float64)[order].reshape(-1, 3))))

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
