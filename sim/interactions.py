"""Pair-interaction sections of a scene: ``contact``, ``bonding``, ``friction``,
``nearfield``, ``walls``, validated into an :class:`Interactions` object.

Keys (SI units; every section optional, unknown keys rejected):

.. code-block:: toml

    [contact]
    model = "hooke"            # "hooke" (linear spring-dashpot, LAMMPS hooke/history) | "power" (seed eq. 3.12)
    # hooke
    kn = 1.0e9                 # normal stiffness (N/m)
    restitution = 0.3          # coefficient of restitution e in (0, 1] (sets the damping)
    kt = 2.857e8               # tangential spring (N/m), default 2/7 kn
    tangential_damping_ratio = 0.5   # eta_t / eta_n
    # power (seed)
    K = 1.0e9                  # K_p (N/m^2)
    exponent = 2.0             # p_p
    damping = 1.0e8            # c_cd (N s/m^3), eq. 3.17
    # numerics
    skin = 0.01                # Verlet skin (m), default 0.1 of the smallest diameter
    dt_safety = 0.2            # dt = dt_safety * critical step of the stiffest contact
    adaptive_dt = true         # re-estimate dt from the contacts present during the run
    max_overlap = 0.5          # blow-up when an overlap exceeds this fraction of a radius
    checkpoint_every = 50      # output frames between checkpoints (0 = none)

    [bonding]                  # seed eq. 3.19, 3.23 (power law only)
    K_nb = 1.0e8               # normal bond (N/m^2)
    K_rb = 1.0e5               # rotational (tangential) bond (N/m^3)
    exponent = 2.0             # p_b
    critical_strain = 0.02     # eps*

    [friction]
    mu = 0.4                   # hooke: Coulomb coefficient
    mu_s = 0.4                 # power: static coefficient
    mu_d = 0.3                 # power: dynamic coefficient
    K_f = 1.0e9                # power: tangential compliance constant (N/m^3)

    [nearfield]
    model = "seed"             # "seed" (eq. 3.24-3.25) | "yukawa" (screened Coulomb)
    alpha1 = 0.5               # seed: abar_1 (attraction), N m^b1 / C^2
    alpha2 = 0.05              # seed: abar_2 (repulsion)
    beta1 = 1.0
    beta2 = 2.0
    surface_potential = -0.05  # yukawa: psi (V); uses fluid.relative_permittivity
    debye_length = 1e-8        # yukawa: default from the fluid section
    cutoff = 0.15              # centre-to-centre cut-off (m)

    [walls]                    # particle-wall values; default: the particle-particle ones
    kn = 1.0e9                 # hooke
    restitution = 0.3
    kt = 2.857e8
    mu = 0.4
    K = 1.0e11                 # power: K_w
    exponent = 2.0             # p_w
    damping = 1.0e8
    K_nb = 1.0e10
    K_rb = 1.0e7
    K_f = 1.0e9
    mu_s = 0.4
    mu_d = 0.3

    [vdw]                      # DLVO van der Waals attraction (sim/forces/vdw.py), pairs and walls
    hamaker = 1.0e-20          # Hamaker constant A (J), particle-particle
    wall_hamaker = 1.0e-20     # particle-wall (default: hamaker)
    min_gap = 4.0e-10          # gap (m) below which the force is held constant
    cutoff_gap = 2.0e-7        # surface-to-surface cut-off (m), default 2 radii
    wavelength = 1.0e-7        # Gregory's retardation wavelength (m), 0 = non-retarded

Which walls exist comes from the scene's ``[boundaries]``: the substrate at
z = 0 (``bottom_wall``), solid side walls where ``x``/``y`` = "wall", a top
plane where ``top = "wall"``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ptrack.errors import UserError
from sim.validate import missing as _missing, number as _num  # one validator for every scene key
from sim.forces.contact import CONTACT_HOOKE, CONTACT_NONE, CONTACT_POWER, hooke_params, power_params
from sim.forces import vdw
from sim.forces.nearfield import NF_NONE, NF_SEED, NF_YUKAWA, law_row, law_table, yukawa_prefactor

# Non-contact laws that are one file each: [section] -> module with SECTION, KEYS, CODE, WALL (acts on
# the wall planes too) and parse_section(sec, scene) -> (parameter row, reach in m). A new law of this
# kind adds one entry here and one branch in sim.forces.nearfield's dispatchers.
LAW_SECTIONS = {vdw.SECTION: vdw}

_ALLOWED = {
    "contact": ("model", "kn", "restitution", "kt", "tangential_damping_ratio", "K", "exponent", "damping",
                "skin", "dt_safety", "adaptive_dt", "max_overlap", "checkpoint_every"),
    "bonding": ("K_nb", "K_rb", "exponent", "critical_strain"),
    "friction": ("mu", "mu_s", "mu_d", "K_f"),
    "nearfield": ("model", "alpha1", "alpha2", "beta1", "beta2", "surface_potential", "debye_length", "cutoff"),
    "walls": ("kn", "restitution", "kt", "mu", "K", "exponent", "damping", "K_nb", "K_rb", "K_f", "mu_s", "mu_d",
              "tangential_damping_ratio"),
    **{name: mod.KEYS for name, mod in LAW_SECTIONS.items()},
}
SECTIONS = tuple(_ALLOWED)  # every pair-interaction section a scene may hold


@dataclass
class Interactions:
    """Validated pair-interaction settings (arrays ready for the numba kernels).

    Attributes
    ----------
    model : int
        Contact law code (0 none, 1 Hooke, 2 power law).
    cp, cpw : ndarray
        Particle-particle and particle-wall parameters (see :mod:`sim.forces.contact`).
    friction, bonding : bool
    nf_model : int; nfp : ndarray
        The [nearfield] law and parameters (see :mod:`sim.forces.nearfield`).
    law_rows, wall_law_rows : list of ndarray
        Rows of the other non-contact laws (``LAW_SECTIONS``), pairs and walls.
    cutoff : float
        Largest centre-to-centre reach of a non-contact law (m), 0 without one.
    skin, dt_safety, max_overlap : float
    adaptive_dt : bool
    checkpoint_every : int
    raw : dict
        The sections as given.
    """
    model: int = CONTACT_NONE
    cp: np.ndarray = field(default_factory=lambda: np.zeros(12))
    cpw: np.ndarray = field(default_factory=lambda: np.zeros(12))
    friction: bool = False
    bonding: bool = False
    nf_model: int = NF_NONE
    nfp: np.ndarray = field(default_factory=lambda: np.zeros(5))
    law_rows: list = field(default_factory=list)
    wall_law_rows: list = field(default_factory=list)
    cutoff: float = 0.0
    skin: float | None = None
    dt_safety: float = 0.2
    adaptive_dt: bool = True
    max_overlap: float = 0.5
    checkpoint_every: int = 50
    raw: dict = field(default_factory=dict)

    @property
    def any_pair_force(self) -> bool:
        """True when some particle-particle or particle-wall force is switched on."""
        return self.model != CONTACT_NONE or len(self.pair_laws) > 0 or len(self.wall_laws) > 0

    @property
    def pair_laws(self) -> np.ndarray:
        """Law table (L, LAW_WIDTH) of the particle-particle non-contact laws."""
        rows = ([law_row(self.nf_model, self.nfp)] if self.nf_model != NF_NONE else []) + list(self.law_rows)
        return law_table(*rows)

    @property
    def wall_laws(self) -> np.ndarray:
        """Law table (L, LAW_WIDTH) of the particle-wall non-contact laws."""
        return law_table(*self.wall_law_rows)

    @property
    def rotation(self) -> bool:
        """Tangential forces act, so angular velocities must be integrated."""
        return self.friction or self.bonding

    @property
    def model_name(self) -> str:
        return {CONTACT_NONE: "none", CONTACT_HOOKE: "hooke", CONTACT_POWER: "power"}[self.model]


def parse_interactions(raw: dict, scene=None) -> Interactions:
    """Validate the raw ``contact``/``bonding``/``friction``/``nearfield``/``walls`` sections.

    Parameters
    ----------
    raw : dict
        ``{section: {key: value}}`` as read from TOML.
    scene : sim.scene.Scene, optional
        For defaults that depend on the fluid (Debye length, permittivity).

    Raises
    ------
    UserError
        Unknown section/key, wrong type, out-of-range value or inconsistent
        combination (e.g. bonding without the power-law contact).
    """
    for sec, body in raw.items():
        if sec not in _ALLOWED:
            raise UserError(f"unknown interaction section [{sec}]", f"allowed: {', '.join(_ALLOWED)}")
        if not isinstance(body, dict):
            raise UserError(f"scene entry {sec} = {body!r} is not a section", f"write it as [{sec}] with keys")
        bad = [k for k in body if k not in _ALLOWED[sec]]
        if bad:
            raise UserError(f"unknown scene key {sec}.{bad[0]}", f"allowed in [{sec}]: {', '.join(_ALLOWED[sec])}")
    c = raw.get("contact", {})
    b = raw.get("bonding", {})
    f = raw.get("friction", {})
    nf = raw.get("nearfield", {})
    w = raw.get("walls", {})
    it = Interactions(raw={k: dict(v) for k, v in raw.items()})

    model = c.get("model", "hooke" if ("contact" in raw or "walls" in raw or "friction" in raw) else "none")
    if model not in ("hooke", "power", "none"):
        raise UserError(f"scene key contact.model = {model!r} is not allowed", 'give "hooke" or "power"')
    if model == "none" and ("bonding" in raw or "friction" in raw):
        raise UserError("[bonding]/[friction] given without a [contact] law", "add [contact] with model = ...")
    it.skin = None if "skin" not in c else _num("contact", "skin", c["skin"], positive=True)
    it.dt_safety = _num("contact", "dt_safety", c.get("dt_safety", 0.2), positive=True, hi=1.0)
    ad = c.get("adaptive_dt", True)
    if not isinstance(ad, bool):
        raise UserError(f"scene key contact.adaptive_dt = {ad!r} is not true/false", "give true or false")
    it.adaptive_dt = ad
    it.max_overlap = _num("contact", "max_overlap", c.get("max_overlap", 0.5), positive=True, hi=2.0)
    ce = c.get("checkpoint_every", 50)
    if isinstance(ce, bool) or not isinstance(ce, int) or ce < 0:
        raise UserError(f"scene key contact.checkpoint_every = {ce!r} is not a non-negative integer",
                        "give the number of output frames between checkpoints (0 = none)")
    it.checkpoint_every = ce

    if model == "hooke":
        if "bonding" in raw:
            raise UserError("[bonding] is part of the seed's power-law contact", 'set contact.model = "power"')
        for k in ("K", "exponent", "damping"):
            if k in c:
                raise UserError(f"scene key contact.{k} belongs to the power-law contact",
                                'set contact.model = "power" or use kn/restitution')
        kn = _num("contact", "kn", c.get("kn", None) if "kn" in c else _missing("contact", "kn"), positive=True)
        e = _num("contact", "restitution", c.get("restitution", 0.5), positive=True, hi=1.0)
        kt = _num("contact", "kt", c.get("kt", 2.0 / 7.0 * kn), nonneg=True)
        tdr = _num("contact", "tangential_damping_ratio", c.get("tangential_damping_ratio", 0.5), nonneg=True)
        for k in ("mu_s", "mu_d", "K_f"):
            if k in f:
                raise UserError(f"scene key friction.{k} belongs to the power-law contact",
                                "use friction.mu with the hooke contact")
        mu = _num("friction", "mu", f.get("mu", 0.0), nonneg=True)
        it.friction = mu > 0 and kt > 0
        it.model = CONTACT_HOOKE
        it.cp = hooke_params(kn, e, kt=kt, mu=mu, damp_t_ratio=tdr)
        for k in ("K", "exponent", "damping", "K_nb", "K_rb", "K_f", "mu_s", "mu_d"):
            if k in w:
                raise UserError(f"scene key walls.{k} belongs to the power-law contact", "use kn/restitution/kt/mu")
        kn_w = _num("walls", "kn", w.get("kn", kn), positive=True)
        it.cpw = hooke_params(kn_w, _num("walls", "restitution", w.get("restitution", e), positive=True, hi=1.0),
                              kt=_num("walls", "kt", w.get("kt", kt if "kn" not in w else 2.0 / 7.0 * kn_w), nonneg=True),
                              mu=_num("walls", "mu", w.get("mu", mu), nonneg=True),
                              damp_t_ratio=_num("walls", "tangential_damping_ratio",
                                                w.get("tangential_damping_ratio", tdr), nonneg=True))
        it.friction = it.friction or (it.cpw[4] > 0 and it.cpw[1] > 0)
    elif model == "power":
        for k in ("kn", "restitution", "kt", "tangential_damping_ratio"):
            if k in c:
                raise UserError(f"scene key contact.{k} belongs to the hooke contact",
                                'set contact.model = "hooke" or use K/exponent/damping')
        if "mu" in f:
            raise UserError("scene key friction.mu belongs to the hooke contact",
                            "use friction.mu_s, mu_d and K_f with the power-law contact")
        K = _num("contact", "K", c["K"] if "K" in c else _missing("contact", "K"), positive=True)
        p = _num("contact", "exponent", c.get("exponent", 2.0), positive=True)
        ccd = _num("contact", "damping", c.get("damping", 0.0), nonneg=True)
        bonding = "bonding" in raw
        K_nb = _num("bonding", "K_nb", b.get("K_nb", 0.0), nonneg=True)
        K_rb = _num("bonding", "K_rb", b.get("K_rb", 0.0), nonneg=True)
        p_b = _num("bonding", "exponent", b.get("exponent", 2.0), positive=True)
        eps_star = _num("bonding", "critical_strain", b.get("critical_strain", 0.02), positive=True)
        friction = "friction" in raw
        mu_s = _num("friction", "mu_s", f.get("mu_s", 0.0), nonneg=True)
        mu_d = _num("friction", "mu_d", f.get("mu_d", mu_s), nonneg=True)
        if mu_d > mu_s:
            raise UserError(f"scene key friction.mu_d = {mu_d} exceeds friction.mu_s = {mu_s}",
                            "the dynamic friction coefficient must not exceed the static one")
        K_f = _num("friction", "K_f", f.get("K_f", 0.0), nonneg=True)
        it.model = CONTACT_POWER
        it.bonding = bonding
        it.friction = friction and K_f > 0
        it.cp = power_params(K, p, ccd, K_nb, K_rb, p_b, eps_star, K_f, mu_s, mu_d, bonding, it.friction)
        for k in ("kn", "restitution", "kt", "mu"):
            if k in w:
                raise UserError(f"scene key walls.{k} belongs to the hooke contact", "use K/exponent/damping/...")
        it.cpw = power_params(_num("walls", "K", w.get("K", K), positive=True),
                              _num("walls", "exponent", w.get("exponent", p), positive=True),
                              _num("walls", "damping", w.get("damping", ccd), nonneg=True),
                              _num("walls", "K_nb", w.get("K_nb", K_nb), nonneg=True),
                              _num("walls", "K_rb", w.get("K_rb", K_rb), nonneg=True),
                              p_b, eps_star,
                              _num("walls", "K_f", w.get("K_f", K_f), nonneg=True),
                              _num("walls", "mu_s", w.get("mu_s", mu_s), nonneg=True),
                              _num("walls", "mu_d", w.get("mu_d", mu_d), nonneg=True),
                              bonding, it.friction)

    if nf:
        nm = nf.get("model", "seed")
        cutoff = _num("nearfield", "cutoff", nf["cutoff"] if "cutoff" in nf else _missing("nearfield", "cutoff"),
                      positive=True)
        if nm == "seed":
            for k in ("surface_potential", "debye_length"):
                if k in nf:
                    raise UserError(f"scene key nearfield.{k} belongs to the yukawa model", 'set nearfield.model = "yukawa"')
            it.nf_model = NF_SEED
            it.nfp = np.array([_num("nearfield", "alpha1", nf.get("alpha1", 0.0), nonneg=True),
                               _num("nearfield", "alpha2", nf.get("alpha2", 0.0), nonneg=True),
                               _num("nearfield", "beta1", nf.get("beta1", 1.0), positive=True),
                               _num("nearfield", "beta2", nf.get("beta2", 2.0), positive=True),
                               cutoff], dtype=np.float64)
        elif nm == "yukawa":
            for k in ("alpha1", "alpha2", "beta1", "beta2"):
                if k in nf:
                    raise UserError(f"scene key nearfield.{k} belongs to the seed model", 'set nearfield.model = "seed"')
            psi = _num("nearfield", "surface_potential", nf["surface_potential"] if "surface_potential" in nf
                       else _missing("nearfield", "surface_potential"))
            lam = nf.get("debye_length")
            if lam is None and scene is not None:
                lam = scene.fluid.debye_length
                if lam is None and scene.fluid.debye_ratio is not None:
                    lam = scene.particles.radius / scene.fluid.debye_ratio
            if lam is None:
                _missing("nearfield", "debye_length")
            lam = _num("nearfield", "debye_length", lam, positive=True)
            eps_r = scene.fluid.relative_permittivity if scene is not None else 80.0
            it.nf_model = NF_YUKAWA
            it.nfp = np.array([yukawa_prefactor(eps_r, psi), 1.0 / lam, cutoff, 0.0, 0.0], dtype=np.float64)
        else:
            raise UserError(f"scene key nearfield.model = {nm!r} is not allowed", 'give "seed" or "yukawa"')
        it.cutoff = cutoff
    for name, mod in LAW_SECTIONS.items():
        if name in raw:
            row, reach = mod.parse_section(raw[name], scene)
            it.law_rows.append(law_row(mod.CODE, row))
            if mod.WALL:
                it.wall_law_rows.append(law_row(mod.CODE, row))
            it.cutoff = max(it.cutoff, reach)
    if scene is not None and it.any_pair_force:
        _check_box(it, scene)
    return it


def _check_box(it: Interactions, scene) -> None:
    rmax = scene.particles.radius * (1 + scene.particles.radius_variation)
    reach = max(2 * rmax, it.cutoff) + (it.skin if it.skin is not None else 0.2 * rmax)
    for ax, mode, L in (("x", scene.boundaries.x, scene.domain.size[0]), ("y", scene.boundaries.y, scene.domain.size[1])):
        if mode == "periodic" and L < 2 * reach:
            raise UserError(f"periodic domain.size along {ax} = {L} m is shorter than twice the interaction range "
                            f"{reach:.4g} m", "enlarge the domain or reduce nearfield.cutoff / contact.skin")
