"""Order of EPD deposits against Peclet number and Debye length (Giera et al.,
the seed's future-work Fig. 3.24), laptop-sized.

Charged colloids (radius a) drift at the Henry-like speed ``v = Pe D / a``
toward a sticking substrate by overdamped Brownian dynamics, repelling each
other by a screened-Coulomb (Yukawa / DLVO double-layer) force
``F = U (kappa + 1/r)``, ``U = 4 pi eps eps0 psi^2 a^2 exp(-kappa (r - 2a)) / r``
(:mod:`sim.forces.nearfield`, model 2) plus a stiff contact spring
(:mod:`sim.forces.contact`, Hooke without damping) that keeps cores apart
when the field pushes hard.  A particle sticks when it touches the substrate;
particles above it are free to rearrange under the field, the repulsion and
thermal motion (``--substrate stick``).  The default, ``--substrate
contact``, is a hard frictionless substrate on which particles stay laterally
mobile: random sticking freezes a disordered first layer that templates an
amorphous deposit at every Pe (solid-like fraction < 5 % in our runs), so
only the mobile substrate shows the Pe dependence.  Once everything has arrived, the final deposit is analysed
with the ten Wolde solid-like criterion on Steinhardt q6 (the "relative
order" ``N_ordered / N`` of Giera et al.) and the mean q6.

Pe is the corrected one, ``Pe = v_H a / D_SE`` (the seed's eq. 3.37 with 6 pi
makes its values 1.5x too high).  Each (Pe, a/lambda_D) case is an
independent dask task.  Expected trend: order falls as Pe rises (particles
have less time to find lattice sites before the next layer buries them).

Time stepping: the engine's overdamped stepper (:class:`sim.dem.DEMSystem`
with ``integrator=OVERDAMPED``: the same pair kernel, laws and counter-based
random numbers as every other run), Euler-Maruyama with a step ``dt =
min(dt0, 0.01 a gamma / F_max)`` chosen each step from the largest
deterministic force, so that no particle moves more than 1 % of its radius by
drift in one step (stiff close encounters are resolved); the Brownian
increment uses the same dt. (Until this version the study had an integrator
of its own with numba's global generator: same scheme, other random numbers.)
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from ptrack.constants import BOLTZMANN, VACUUM_PERMITTIVITY
from sim.dem import OK, OVERDAMPED, STATUS_TEXT, DEMSystem
from sim.forces.contact import CONTACT_HOOKE
from sim.forces.nearfield import NF_YUKAWA, law_row, law_table

DEFAULTS = dict(radius=100e-9, temperature=293.0, viscosity=1e-3, eps_r=80.0, psi=0.05, n_particles=300,
                side_radii=None, height_radii=None, volume_fraction=0.04, dt_reduced=2e-4, settle=1.0,
                contact_stiffness_kT=5.0e3)


def run_case(case: dict) -> dict:
    """One (Pe, a/lambda_D) deposit; returns order metrics."""
    from sim.analysis import solid_like, steinhardt_q6
    from sim.forces.contact import hooke_params
    from sim.forces.nearfield import yukawa_prefactor

    a = case["radius"]
    kT = BOLTZMANN * case["temperature"]
    gamma = 6 * math.pi * case["viscosity"] * a
    D = kT / gamma
    lam = a / case["a_over_lambda"]
    kappa = 1.0 / lam
    A = yukawa_prefactor(case["eps_r"], case["psi"])
    # range where the pair energy falls to 0.01 kT
    u_contact = A * a * a / (2 * a)
    cut = 2 * a + lam * max(1.0, math.log(max(u_contact / (0.01 * kT), 1.0)))
    cut = min(cut, 2 * a + 8 * lam)
    laws = law_table(law_row(NF_YUKAWA, [A, kappa, cut]))
    cp = hooke_params(case["contact_stiffness_kT"] * kT / a**2, 1.0, mu=0.0)
    n = int(case["n_particles"])
    vol = n * 4 / 3 * math.pi * a**3 / case["volume_fraction"]
    side = case["side_radii"] * a if case.get("side_radii") else (vol / (1.5 * (vol ** (1 / 3)))) ** 0.5
    side = max(side, 2.2 * (cut + 0.3 * a))
    height = vol / side**2
    rng = np.random.default_rng(case["seed"])
    # random sequential placement without core overlap (rejection with the neighbour grid of sim.placement)
    from sim.placement import place_particles

    pos, rad = place_particles(n, a, 0.0, (0.0, 0.0, 2 * a), (side, side, 2 * a + height), seed=rng)
    pe = case["pe"]
    v = pe * D / a
    f_field = gamma * v
    t_end = (height / v) * (1.0 + case["settle"]) + 20 * a * a / D / max(pe, 1.0)
    dt0 = case["dt_reduced"] * a * a / D
    pos = np.ascontiguousarray(pos)
    # overdamped Brownian dynamics with the pair forces on the engine (sim.dem, OVERDAMPED): drift
    # steps of at most 0.01 a, a sticking (or reflecting) substrate, counter-based random numbers
    system = DEMSystem(pos, np.zeros_like(pos), np.ascontiguousarray(rad), np.full(n, 1.0), None,
                       model=CONTACT_HOOKE, cp=cp, pair_laws=laws, rotation=False, walls=None,
                       box_length=(side, side, 10 * height), periodic=(1, 1, 0),
                       fconst=np.array([0.0, 0.0, -f_field]), gamma=np.full(n, gamma),
                       extp=np.array([0.0, 0.0, 0.0, 0.0, 0.0, kT, 0.0, 0.0, 0.0]), dt=dt0, skin=0.3 * a,
                       cutoff=cut, seed=int(case["seed"]), integrator=OVERDAMPED,
                       substrate="stick" if case.get("substrate", "stick") == "stick" else "reflect",
                       max_step=0.01 * a, max_overlap=np.inf)
    max_steps = 20_000_000
    while system.t < t_end and system.step < max_steps:
        if system.run(min(200_000, max_steps - system.step), until=t_end) != OK:
            raise RuntimeError(f"EPD-order case: {STATUS_TEXT[system.status]} at step {system.step}")
    pos = system.pos
    stuck = system.frozen != 0.0
    t, steps = system.t, system.step
    stuck = stuck if case.get("substrate", "stick") == "stick" else pos[:, 2] < rad * 1.05
    # deposit: everything below the top surface that has arrived
    z = pos[:, 2]
    arrived = z < np.quantile(z, 0.98) + 4 * a
    # neighbours: up to the first minimum of g(r), estimated as 1.3 x the median nearest distance
    from scipy.spatial import cKDTree

    tree = cKDTree(np.mod(pos, [side, side, 1e9]), boxsize=[side, side, 1e9])
    dnn, _ = tree.query(np.mod(pos, [side, side, 1e9]), k=2)
    r_cut = 1.3 * float(np.median(dnn[:, 1]))
    q6 = steinhardt_q6(pos, r_cut=r_cut, length=[side, side, 1e9], periodic=[1, 1, 0])
    solid, nconn = solid_like(pos, r_cut=r_cut, length=[side, side, 1e9], periodic=[1, 1, 0])
    interior = arrived & (z > 3 * a) & (z < np.quantile(z, 0.9))
    sel = interior if interior.sum() >= 10 else arrived
    return {"pe": pe, "a_over_lambda": case["a_over_lambda"], "n_particles": n, "steps": int(steps), "t_end": t,
            "solid_fraction": float(solid[arrived].mean()), "solid_fraction_interior": float(solid[sel].mean()),
            "q6_mean": float(np.nanmean(q6[arrived])), "stuck_on_substrate": int(stuck.sum()),
            "r_cut": r_cut, "nn_distance": float(np.median(dnn[:, 1])), "side": side, "height": height,
            "deposit_height": float(np.quantile(z, 0.95) + a)}


def add_arguments(p):
    from sim.studies._dask import add_study_arguments

    add_study_arguments(p)
    p.add_argument("--pe", type=float, nargs="+", default=None, help="Peclet numbers (default 2 10 50 250)")
    p.add_argument("--a-over-lambda", type=float, nargs="+", default=None,
                   help="radius / Debye length values (default 2 5 10)")
    p.add_argument("--particles", type=int, default=None, help="particles per deposit (default 300)")
    p.add_argument("--substrate", choices=("stick", "contact"), default="contact",
                   help="contact: a hard frictionless substrate, particles stay laterally mobile (default); "
                        "stick: particles stick on first contact with the substrate")


def cases_for(args) -> list[dict]:
    from ptrack.errors import UserError

    pes = args.pe or ([5.0, 100.0] if args.quick else [2.0, 10.0, 50.0, 250.0])
    als = args.a_over_lambda or ([3.0] if args.quick else [2.0, 5.0, 10.0])
    n = args.particles or (120 if args.quick else DEFAULTS["n_particles"])
    for v in pes + als:
        if not v > 0:
            raise UserError(f"Pe and a/lambda_D must be positive, got {v}", "give positive values")
    if n < 20:
        raise UserError(f"--particles {n} is too few for a deposit", "give at least 20")
    reps = args.replicates or 1
    out = []
    k = 0
    for al in als:
        for pe in pes:
            for r in range(reps):
                out.append(dict(DEFAULTS, pe=pe, a_over_lambda=al, n_particles=n, seed=args.seed * 10007 + k, rep=r,
                                substrate=args.substrate))
                k += 1
    return out


def run(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    from ptrack.errors import atomic_output
    from sim.studies._dask import run_cases

    cases = cases_for(args)
    res = run_cases(run_case, cases, scheduler=args.scheduler, use_dask=not args.no_dask and len(cases) > 1,
                    workers=args.workers, desc="epd-order")
    df = pd.DataFrame(res)
    g = df.groupby(["a_over_lambda", "pe"], as_index=False).agg(
        solid_fraction=("solid_fraction", "mean"), solid_sd=("solid_fraction", "std"),
        solid_interior=("solid_fraction_interior", "mean"), q6=("q6_mean", "mean"), steps=("steps", "mean"),
        n=("n_particles", "first"))
    print("EPD deposit order vs Pe (= v_H a / D_SE, 4 pi form) and a/lambda_D: ten Wolde solid-like fraction "
          "(relative order N_ordered/N) and mean q6")
    print(f"{'a/lambda':>9} {'Pe':>7} {'solid frac':>10} {'interior':>9} {'q6':>6} {'steps':>9}")
    for _, r in g.iterrows():
        print(f"{r.a_over_lambda:9.2f} {r.pe:7.1f} {r.solid_fraction:10.3f} {r.solid_interior:9.3f} {r.q6:6.3f} "
              f"{int(r.steps):9d}")
    # trend: Spearman-like sign of the order vs Pe for each a/lambda
    trend = {}
    for al, gg in g.groupby("a_over_lambda"):
        gg = gg.sort_values("pe")
        if len(gg) > 1:
            trend[float(al)] = float(np.corrcoef(np.log(gg.pe), gg.q6)[0, 1])
    summary = {"cases": res, "trend_q6_vs_log_pe": trend}
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        for al, gg in g.groupby("a_over_lambda"):
            gg = gg.sort_values("pe")
            ax[0].plot(gg.pe, gg.solid_fraction, "-o", label=f"a/lambda_D = {al:g}")
            ax[1].plot(gg.pe, gg.q6, "-o", label=f"a/lambda_D = {al:g}")
        for a_ in ax:
            a_.set_xscale("log")
            a_.set_xlabel("Pe = v_H a / D")
            a_.legend()
        ax[0].set_ylabel("relative order N_ordered / N (solid-like)")
        ax[1].set_ylabel("mean q6")
        fig.tight_layout()
        with atomic_output(out / "epd_order.png", None) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
        with atomic_output(out / "epd_order.csv", None) as tmp:
            df.to_csv(tmp, index=False)
        print(f"wrote {out / 'epd_order.png'} and {out / 'epd_order.csv'}", file=sys.stderr)
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(summary, fh, indent=2)
    return 0
