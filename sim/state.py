"""Particles of a scene as arrays (physics, not schema).

:func:`build_state` turns a validated :class:`sim.scene.Scene` into a
:class:`State` of contiguous float64 arrays (radius, mass, charge, Stokes
gamma, positions, velocities); :func:`constant_force` gives the
per-particle constant external force (q E + gravity with buoyancy);
:func:`particle_charge` the charge from q, q/m or the zeta potential
(eq. 3.33). Kept apart from :mod:`sim.scene` (the TOML schema), which
re-exports these names for old callers.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

@dataclass
class State:
    """Per-particle arrays (contiguous float64, SI) built from a scene by :func:`build_state`.

    Attributes
    ----------
    radius, mass, charge, gamma : (N,) arrays
        m, kg, C, and the Stokes drag coefficient 6 pi mu R (kg/s).
    pos, vel : (N, 3) arrays
        Positions (m) and velocities (m/s).
    t : float
        Time (s).
    """
    radius: np.ndarray
    mass: np.ndarray
    charge: np.ndarray
    gamma: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    t: float = 0.0

    @property
    def n(self) -> int:
        return len(self.radius)

    def copy(self) -> "State":
        return State(*(np.array(getattr(self, f.name), copy=True) if isinstance(getattr(self, f.name), np.ndarray)
                       else getattr(self, f.name) for f in dataclasses.fields(self)))


def debye_length_of(scene, radius):
    """Debye length (m) for each radius: fluid.debye_length, or radius / fluid.debye_ratio."""
    if scene.fluid.debye_length is not None:
        return np.full_like(np.asarray(radius, dtype=float), scene.fluid.debye_length)
    if scene.fluid.debye_ratio is not None:
        return np.asarray(radius, dtype=float) / scene.fluid.debye_ratio
    return None


def particle_charge(scene, radius: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Charge per particle (C): given directly, from q/m, or from the zeta potential by eq. 3.33.

    Eq. 3.33 is evaluated by :func:`sim.electrokinetics.colloid_charge`, i.e.
    q = 4 pi eps_r eps0 zeta R f(R / lambda_D) with Henry's exact function f.
    """
    p = scene.particles
    if p.charge is not None:
        return np.full(len(radius), p.charge)
    if p.charge_per_mass is not None:
        return p.charge_per_mass * mass
    if p.zeta_potential is not None:
        from sim.electrokinetics import colloid_charge
        lam = debye_length_of(scene, radius)
        return np.asarray(colloid_charge(p.zeta_potential, radius, lam, scene.fluid.relative_permittivity),
                          dtype=np.float64) * np.ones(len(radius))
    return np.zeros(len(radius))


def constant_force(scene, state: State) -> np.ndarray:
    """Velocity-independent external force per particle (N), shape (N, 3), contiguous.

    q E (Lorentz, electric part) plus gravity with buoyancy, (m - rho_f V) g,
    if gravity is enabled (buoyancy can be switched off in the scene).
    """
    from sim.forces.body import gravity_buoyancy_force
    f = state.charge[:, None] * np.asarray(scene.fields.E, dtype=np.float64)[None, :]
    if scene.gravity.enabled:
        rho_f = scene.fluid.density if scene.gravity.buoyancy else 0.0
        f = f + gravity_buoyancy_force(state.mass, state.radius, rho_f, scene.gravity.g)
    return np.ascontiguousarray(f, dtype=np.float64)


def build_state(scene, seed=None) -> State:
    """Particles of a scene: radii (eq. 3.39), masses, charges, positions and velocities.

    Positions come from :func:`sim.placement.place_particles` (sequential random
    non-overlapping placement with a cell hash). Initial velocities per
    ``particles.initial_velocity``: ``zero`` (at rest relative to the fluid,
    i.e. v = v_f); ``terminal``/``henry``: the
    Stokes terminal velocity v_f + F_const / gamma (with the eq. 3.33 charge
    this is the Henry velocity, as the seed initialises its deposition runs);
    ``thermal``: Maxwell-Boltzmann, each component N(0, kB T / m).

    Parameters
    ----------
    scene : Scene
    seed : int or numpy.random.Generator, optional
        Defaults to ``scene.seed``.
    """
    from sim.forces.drag import stokes_gamma
    from sim.placement import place_particles

    rng = np.random.default_rng(scene.seed if seed is None else seed)
    p = scene.particles
    lo = (0.0, 0.0, 0.0)
    hi = tuple(scene.domain.size)
    if scene.domain.placement_z is not None:
        lo = (0.0, 0.0, scene.domain.placement_z[0])
        hi = (hi[0], hi[1], scene.domain.placement_z[1])
    pos, radius = place_particles(p.count, p.radius, p.radius_variation, lo, hi, seed=rng)
    mass = p.density * 4.0 / 3.0 * np.pi * radius ** 3
    gamma = stokes_gamma(radius, scene.fluid.viscosity)
    charge = particle_charge(scene, radius, mass)
    st = State(radius=radius, mass=mass, charge=np.ascontiguousarray(charge, dtype=np.float64), gamma=gamma,
               pos=pos, vel=np.zeros((p.count, 3)))
    vf = np.asarray(scene.fluid.velocity, dtype=np.float64)
    if p.initial_velocity in ("terminal", "henry"):
        st.vel = np.ascontiguousarray(vf[None, :] + constant_force(scene, st) / gamma[:, None])
    elif p.initial_velocity == "thermal":
        st.vel = np.ascontiguousarray(vf[None, :] + rng.standard_normal((p.count, 3)) * np.sqrt(scene.kT / mass)[:, None])
    else:
        st.vel = np.ascontiguousarray(np.broadcast_to(vf, (p.count, 3)).copy())
    return st


__all__ = ["State", "build_state", "constant_force", "particle_charge", "debye_length_of"]
