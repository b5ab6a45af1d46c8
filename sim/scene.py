"""Simulation scenes: what is simulated, read from TOML and validated into dataclasses.

A scene file (stdlib :mod:`tomllib`) has these sections; every value is SI
(m, s, kg, C, V/m, T, Pa s, K). Unknown keys and bad values (NaN, negative
radius, wrong type) are rejected with a :class:`~ptrack.errors.UserError`
naming the key, the value and what was expected.

.. code-block:: toml

    seed = 1                        # integer; same seed -> same trajectories

    [particles]
    count = 100
    radius = 1.0e-7                 # mean radius R (m)
    radius_variation = 0.0          # alpha_Rad of eq. 3.39: R_i = R (1 + alpha c_i), c_i in [-1, 1]
    density = 2200.0                # kg/m^3
    # charge: at most one of
    charge = -1.0e-17               # C, or
    charge_per_mass = -1.0          # C/kg (q/m), or
    zeta_potential = -0.05          # V, with fluid.debye_length and fluid.relative_permittivity (eq. 3.33)
    initial_velocity = "zero"       # "zero" (= fluid velocity) | "terminal" (alias "henry") | "thermal"

    [fluid]
    density = 1000.0
    viscosity = 1.0e-3
    temperature = 293.0             # 0 switches Brownian motion off
    velocity = [0.0, 0.0, 0.0]      # uniform fluid velocity v_f
    relative_permittivity = 80.0
    debye_length = 5.0e-8           # or debye_ratio = R / lambda_D

    [fields]
    E = [0.0, 0.0, -1.0e4]          # V/m
    B = [0.0, 0.0, 0.0]             # T

    [gravity]                       # ON by default, with buoyancy
    enabled = true
    g = [0.0, 0.0, -9.80665]
    buoyancy = true

    [domain]
    size = [1e-5, 1e-5, 2e-5]       # box [0, Lx] x [0, Ly] x [0, Lz]
    placement_z = [0.0, 2e-5]       # initial positions are drawn in this z range (default: whole box)

    [boundaries]
    x = "open"                      # "open" | "periodic" | "wall"
    y = "open"
    bottom_wall = true              # substrate at z = 0 (reflecting for free particles)
    top = "open"                    # "open" | "wall" (reflecting plane at z = Lz)

    [time]
    dt = "auto"                     # or a number (s)
    final = 1.0e-3
    output_interval = 1.0e-5

    [integrator]
    kind = "auto"                   # "auto" | "ou_exact" | "overdamped" | "trapezoidal"
    phi = 0.0                       # trapezoidal parameter (0 explicit Euler, 0.5 trapezoidal, 1 backward Euler)
    tolerance = 1e-12               # fixed-point tolerance for phi > 0 (relative)
    max_iterations = 100
    hindered_mobility = false       # near-wall mobility (overdamped only)

Pair-interaction sections (``contact``, ``bonding``, ``friction``,
``nearfield``, ``walls``, ``vdw``: :data:`sim.interactions.SECTIONS`) are passed raw to
``sim.interactions.parse_interactions(raw, scene)`` and stored in
:attr:`Scene.interactions` (``None`` when the file has none of them).

This module is the schema only: every key is checked by :mod:`sim.validate`.
The physics of a scene (:func:`build_state`, :func:`constant_force`,
:func:`particle_charge`, :class:`State`) lives in :mod:`sim.state` and is
re-exported here for old callers. :attr:`Boundaries.modes` encodes the
boundaries as integers (:data:`OPEN`, :data:`PERIODIC`, :data:`WALL`) for
numba kernels.
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptrack.constants import BOLTZMANN, STANDARD_GRAVITY, VACUUM_PERMITTIVITY
from ptrack.errors import UserError, require_file
from sim.interactions import SECTIONS, parse_interactions
from sim.state import State, build_state, constant_force, debye_length_of, particle_charge  # noqa: F401 (re-export)
from sim.validate import boolean, choice, integer, number, section, vec3

INTERACTION_SECTIONS = SECTIONS  # the pair-interaction sections, defined once in sim.interactions
BOUNDARY_KINDS = ("open", "periodic", "wall")
INTEGRATORS = ("auto", "ou_exact", "overdamped", "trapezoidal")
INITIAL_VELOCITIES = ("zero", "terminal", "henry", "thermal")

# integer codes of boundary modes used by numba kernels
OPEN, PERIODIC, WALL = 0, 1, 2
_MODE_CODE = {"open": OPEN, "periodic": PERIODIC, "wall": WALL}


# --------------------------------------------------------------------------- dataclasses
@dataclass
class Particles:
    """Particle population. SI units: radius m, density kg/m^3, charge C, charge_per_mass C/kg, zeta V."""
    count: int
    radius: float
    density: float
    radius_variation: float = 0.0
    charge: float | None = None
    charge_per_mass: float | None = None
    zeta_potential: float | None = None
    initial_velocity: str = "zero"


@dataclass
class Fluid:
    """Surrounding fluid. density kg/m^3, viscosity Pa s, temperature K, velocity m/s, debye_length m."""
    density: float = 1000.0
    viscosity: float = 1.0e-3
    temperature: float = 293.0
    velocity: tuple = (0.0, 0.0, 0.0)
    relative_permittivity: float = 80.0
    debye_length: float | None = None
    debye_ratio: float | None = None


@dataclass
class Fields:
    """Uniform external fields: E (V/m), B (T)."""
    E: tuple = (0.0, 0.0, 0.0)
    B: tuple = (0.0, 0.0, 0.0)


@dataclass
class Gravity:
    """Gravity (on by default) with buoyancy (on by default): F = (m - rho_f V) g."""
    enabled: bool = True
    g: tuple = (0.0, 0.0, -STANDARD_GRAVITY)
    buoyancy: bool = True


@dataclass
class Domain:
    """Box [0, Lx] x [0, Ly] x [0, Lz] (m); initial z positions drawn in placement_z."""
    size: tuple
    placement_z: tuple | None = None


@dataclass
class Boundaries:
    """Side boundaries ("open" | "periodic" | "wall"), substrate at z = 0, top plane."""
    x: str = "open"
    y: str = "open"
    bottom_wall: bool = True
    top: str = "open"

    @property
    def modes(self) -> np.ndarray:
        """Integer codes (OPEN=0, PERIODIC=1, WALL=2) for the lower and upper face of x, y, z, shape (2, 3).

        Row 0: lower faces (x=0, y=0, z=0); row 1: upper faces (x=Lx, y=Ly, z=Lz).
        """
        lo = [_MODE_CODE[self.x], _MODE_CODE[self.y], WALL if self.bottom_wall else OPEN]
        hi = [_MODE_CODE[self.x], _MODE_CODE[self.y], _MODE_CODE[self.top]]
        return np.ascontiguousarray(np.array([lo, hi], dtype=np.int64))


@dataclass
class TimeSpec:
    """dt (s, or None for "auto"), final time (s), output interval (s)."""
    final: float
    output_interval: float
    dt: float | None = None


@dataclass
class IntegratorSpec:
    """Time integrator choice and its parameters."""
    kind: str = "auto"
    phi: float = 0.0
    tolerance: float = 1e-12
    max_iterations: int = 100
    hindered_mobility: bool = False


@dataclass
class Scene:
    """A validated simulation scene (see the module docstring for the TOML layout)."""
    particles: Particles
    fluid: Fluid = field(default_factory=Fluid)
    fields: Fields = field(default_factory=Fields)
    gravity: Gravity = field(default_factory=Gravity)
    domain: Domain = field(default_factory=lambda: Domain(size=(1e-5, 1e-5, 1e-5)))
    boundaries: Boundaries = field(default_factory=Boundaries)
    time: TimeSpec = field(default_factory=lambda: TimeSpec(final=1e-3, output_interval=1e-5))
    integrator: IntegratorSpec = field(default_factory=IntegratorSpec)
    seed: int = 0
    interactions: object = None
    source: str | None = None
    raw_interactions: dict | None = None

    @property
    def kT(self) -> float:
        """Thermal energy kB T (J)."""
        return BOLTZMANN * self.fluid.temperature

    def to_dict(self) -> dict:
        """JSON-serialisable dict of the resolved scene (interactions as their raw sections)."""
        d = {}
        for f in dataclasses.fields(self):
            if f.name in ("interactions", "raw_interactions"):
                continue
            v = getattr(self, f.name)
            d[f.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
        d["time"]["dt"] = "auto" if self.time.dt is None else self.time.dt
        if self.raw_interactions:
            d["interactions"] = self.raw_interactions
        return d


# --------------------------------------------------------------------------- parsing
def scene_from_dict(raw: dict, source: str | None = None) -> Scene:
    """Validate a scene given as a (TOML-like) dict; see the module docstring for the keys.

    Raises
    ------
    UserError
        Unknown section or key, wrong type, non-finite or out-of-range value,
        inconsistent settings (two charge definitions, output interval above
        the final time...).
    """
    top_allowed = ("seed", "particles", "fluid", "fields", "gravity", "domain", "boundaries", "time",
                   "integrator") + INTERACTION_SECTIONS
    unknown = [k for k in raw if k not in top_allowed]
    if unknown:
        raise UserError(f"unknown scene key or section {unknown[0]!r}", f"allowed: {', '.join(top_allowed)}")
    seed = integer("", "seed", raw.get("seed", 0), nonneg=True)

    s = section(raw, "particles", ("count", "radius", "radius_variation", "density", "charge",
                                    "charge_per_mass", "zeta_potential", "initial_velocity"), required=True)
    for k in ("count", "radius", "density"):
        if k not in s:
            raise UserError(f"scene lacks particles.{k}", f"give particles.{k} (SI units)")
    p = Particles(
        count=integer("particles", "count", s["count"], positive=True),
        radius=number("particles", "radius", s["radius"], positive=True),
        density=number("particles", "density", s["density"], positive=True),
        radius_variation=number("particles", "radius_variation", s.get("radius_variation", 0.0), lo=0.0, hi=0.99),
        charge=None if "charge" not in s else number("particles", "charge", s["charge"]),
        charge_per_mass=None if "charge_per_mass" not in s else number("particles", "charge_per_mass", s["charge_per_mass"]),
        zeta_potential=None if "zeta_potential" not in s else number("particles", "zeta_potential", s["zeta_potential"]),
        initial_velocity=choice("particles", "initial_velocity", s.get("initial_velocity", "zero"), INITIAL_VELOCITIES),
    )
    given = [k for k in ("charge", "charge_per_mass", "zeta_potential") if k in s]
    if len(given) > 1:
        raise UserError(f"scene gives both particles.{given[0]} and particles.{given[1]}",
                        "define the charge once: charge (C), charge_per_mass (C/kg) or zeta_potential (V)")

    s = section(raw, "fluid", ("density", "viscosity", "temperature", "velocity", "relative_permittivity",
                                "debye_length", "debye_ratio"))
    f = Fluid(
        density=number("fluid", "density", s.get("density", 1000.0), nonneg=True),
        viscosity=number("fluid", "viscosity", s.get("viscosity", 1e-3), positive=True),
        temperature=number("fluid", "temperature", s.get("temperature", 293.0), nonneg=True),
        velocity=vec3("fluid", "velocity", s.get("velocity", [0.0, 0.0, 0.0])),
        relative_permittivity=number("fluid", "relative_permittivity", s.get("relative_permittivity", 80.0), positive=True),
        debye_length=None if "debye_length" not in s else number("fluid", "debye_length", s["debye_length"], positive=True),
        debye_ratio=None if "debye_ratio" not in s else number("fluid", "debye_ratio", s["debye_ratio"], positive=True),
    )
    if f.debye_length is not None and f.debye_ratio is not None:
        raise UserError("scene gives both fluid.debye_length and fluid.debye_ratio",
                        "give one of them (debye_ratio = R / lambda_D)")
    if p.zeta_potential is not None and f.debye_length is None and f.debye_ratio is None:
        raise UserError("particles.zeta_potential needs the Debye length",
                        "add fluid.debye_length (m) or fluid.debye_ratio (R / lambda_D)")

    s = section(raw, "fields", ("E", "B"))
    fl = Fields(E=vec3("fields", "E", s.get("E", [0.0, 0.0, 0.0])), B=vec3("fields", "B", s.get("B", [0.0, 0.0, 0.0])))

    s = section(raw, "gravity", ("enabled", "g", "buoyancy"))
    g = Gravity(enabled=boolean("gravity", "enabled", s.get("enabled", True)),
                g=vec3("gravity", "g", s.get("g", [0.0, 0.0, -STANDARD_GRAVITY])),
                buoyancy=boolean("gravity", "buoyancy", s.get("buoyancy", True)))

    s = section(raw, "domain", ("size", "placement_z"), required=True)
    if "size" not in s:
        raise UserError("scene lacks domain.size", "give domain.size = [Lx, Ly, Lz] in m")
    size = vec3("domain", "size", s["size"], positive=True)
    pz = None
    if "placement_z" in s:
        v = s["placement_z"]
        if not isinstance(v, (list, tuple)) or len(v) != 2:
            raise UserError(f"scene key domain.placement_z = {v!r} is not [z_min, z_max]", "give two heights in m")
        pz = (number("domain", "placement_z[0]", v[0], nonneg=True), number("domain", "placement_z[1]", v[1], positive=True))
        if not pz[0] < pz[1] <= size[2]:
            raise UserError(f"scene key domain.placement_z = {list(v)!r} is not inside [0, Lz = {size[2]}]",
                            "give 0 <= z_min < z_max <= Lz")
    d = Domain(size=size, placement_z=pz)

    s = section(raw, "boundaries", ("x", "y", "bottom_wall", "top"))
    b = Boundaries(x=choice("boundaries", "x", s.get("x", "open"), BOUNDARY_KINDS),
                   y=choice("boundaries", "y", s.get("y", "open"), BOUNDARY_KINDS),
                   bottom_wall=boolean("boundaries", "bottom_wall", s.get("bottom_wall", True)),
                   top=choice("boundaries", "top", s.get("top", "open"), ("open", "wall")))

    s = section(raw, "time", ("dt", "final", "output_interval"), required=True)
    for k in ("final", "output_interval"):
        if k not in s:
            raise UserError(f"scene lacks time.{k}", f"give time.{k} in s")
    final = number("time", "final", s["final"], positive=True)
    out = number("time", "output_interval", s["output_interval"], positive=True)
    if out > final * (1 + 1e-12):
        raise UserError(f"scene key time.output_interval = {out!r} exceeds time.final = {final!r}",
                        "give an output interval no longer than the run")
    dt_raw = s.get("dt", "auto")
    if dt_raw == "auto":
        dt = None
    else:
        if isinstance(dt_raw, str):
            raise UserError(f"scene key time.dt = {dt_raw!r} is not allowed", 'give "auto" or a positive number (s)')
        dt = number("time", "dt", dt_raw, positive=True)
        if dt > out * (1 + 1e-12):
            raise UserError(f"scene key time.dt = {dt!r} exceeds time.output_interval = {out!r}",
                            "give dt <= output_interval")
    t = TimeSpec(final=final, output_interval=out, dt=dt)

    s = section(raw, "integrator", ("kind", "phi", "tolerance", "max_iterations", "hindered_mobility"))
    it = IntegratorSpec(kind=choice("integrator", "kind", s.get("kind", "auto"), INTEGRATORS),
                        phi=number("integrator", "phi", s.get("phi", 0.0), lo=0.0, hi=1.0),
                        tolerance=number("integrator", "tolerance", s.get("tolerance", 1e-12), positive=True),
                        max_iterations=integer("integrator", "max_iterations", s.get("max_iterations", 100), positive=True),
                        hindered_mobility=boolean("integrator", "hindered_mobility", s.get("hindered_mobility", False)))
    if it.hindered_mobility and not b.bottom_wall:
        raise UserError("integrator.hindered_mobility = true needs boundaries.bottom_wall = true",
                        "switch the substrate on or the hindered mobility off")

    rmax = p.radius * (1 + p.radius_variation)
    if min(size) < 2 * rmax:
        raise UserError(f"scene key domain.size = {list(size)!r} is smaller than a particle diameter {2 * rmax!r}",
                        "enlarge the domain")

    scene = Scene(particles=p, fluid=f, fields=fl, gravity=g, domain=d, boundaries=b, time=t, integrator=it,
                  seed=seed, source=source)
    raw_int = {k: raw[k] for k in INTERACTION_SECTIONS if k in raw}
    if raw_int:
        scene.raw_interactions = raw_int
        scene.interactions = parse_interactions(raw_int, scene)
    return scene


def load_scene(path) -> Scene:
    """Read and validate a scene TOML file.

    Raises
    ------
    UserError
        Missing/unreadable file, TOML syntax error, or any invalid key/value.
    """
    path = require_file(path, "scene file")
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"scene file {path} is not valid TOML: {exc}", "fix the TOML syntax")
    return scene_from_dict(raw, source=str(path))


__all__ = ["Scene", "Particles", "Fluid", "Fields", "Gravity", "Domain", "Boundaries", "TimeSpec",
           "IntegratorSpec", "State", "load_scene", "scene_from_dict", "build_state", "constant_force",
           "particle_charge", "OPEN", "PERIODIC", "WALL", "VACUUM_PERMITTIVITY"]
