"""Hamaker's law: EPD onto a substrate with perfect sticking, deposited number per area vs time.

Charged colloids (charge from the zeta potential by eq. 3.33 with Henry's
exact function, :func:`sim.electrokinetics.colloid_charge`) move by
overdamped Brownian dynamics in a field pointing them at the substrate
(z = 0) and stick on first contact (centre height <= R).  While the bulk next
to the substrate is not yet depleted (the depletion front, which starts at
the top of the box, moves down at v_H), the flux onto the substrate is
exactly ``C_s v_H`` in steady state (drift-diffusion with an absorbing wall:
``j = v c - D dc/dz`` is constant and equals ``C_s v_H`` far from the wall),
so the deposited number per area grows linearly with slope ``C_s v_H``
(Hamaker's law, seed eq. 2.1 with sticking efficiency f = 1).  The slope of
the simulated deposit is fitted over the middle of that window and compared
with ``C_s v_H`` from :func:`sim.electrokinetics.henry_velocity`.

The particles do not interact (dilute suspension), so only their heights
matter; the box is laterally periodic and has a reflecting top.  Density is
matched (no sedimentation).  They move on the engine's overdamped stepper
(:class:`sim.dem.DEMSystem`, ``integrator=OVERDAMPED``, sticking substrate),
the same stepper and counter-based random numbers as every other run.  The Peclet number is the corrected one,
``Pe = v_H R / D_SE = 4 pi R^2 |E zeta| eps eps0 f / (kB T)`` (the seed's
eq. 3.37 prints 6 pi, which makes its values 1.5x too high).

Cases (fields giving Pe ~ 5, 11, 22) run as independent dask tasks.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from ptrack.constants import BOLTZMANN

DEFAULTS = dict(radius=100e-9, zeta=-0.05, eps_r=80.0, viscosity=1.0e-3, temperature=293.0, debye_ratio=2.0,
                height_radii=50.0, n_particles=100_000)


def deposit_steps(z0, radius, side, force, gamma, kT, dt, nsteps, seed):
    """Deposition step of non-interacting particles on the engine's overdamped stepper with a sticking substrate.

    Parameters
    ----------
    z0 : (N,) array
        Start heights of the centres (m); x and y are drawn uniformly in the periodic ``side`` x ``side``
        box from ``seed`` (they do not matter: the particles do not interact).
    radius, side : float
        Particle radius and lateral box side (m).
    force : float
        Constant force along z (N; negative: toward the substrate at z = 0).
    gamma, kT : float
        Stokes drag coefficient (kg/s) and thermal energy (J).
    dt : float
        Time step (s), fixed.
    nsteps : int
        Steps to take.
    seed : int
        Key of the counter-based random numbers (:func:`sim.forces.brownian.counter_normal`).

    Returns
    -------
    (N,) int64 array
        The step at which each particle stuck (centre height <= R), -1 for never.

    :class:`sim.dem.DEMSystem` with ``integrator=OVERDAMPED``, no contact or
    pair law, ``substrate="stick"``: Euler-Maruyama in x, y, z with the
    engine's counter-based numbers; a particle reaching z = R is frozen there.
    The step of each arrival is read after every step. (Until this version the
    study had an integrator of its own, in z alone with a reflecting top; the
    top is gone: the depletion front that starts there is still 20 radii above
    the substrate at the end of the fit window, so it does not change the flux.)
    """
    from sim.dem import OK, OVERDAMPED, STATUS_TEXT, DEMSystem
    from sim.forces.contact import CONTACT_NONE

    n = len(z0)
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.random((n, 2)) * side, np.asarray(z0, dtype=float)])
    system = DEMSystem(pos, np.zeros_like(pos), np.full(n, radius), np.ones(n), None, model=CONTACT_NONE,
                       rotation=False, box_length=(side, side, 1.0), periodic=(1, 1, 0),
                       fconst=np.array([0.0, 0.0, force]), gamma=np.full(n, gamma),
                       extp=np.array([0.0, 0.0, 0.0, 0.0, 0.0, kT, 0.0, 0.0, 0.0]), dt=dt, skin=2.0 * radius,
                       seed=int(seed), integrator=OVERDAMPED, substrate="stick", max_step=0.0, max_overlap=np.inf)
    dep = -np.ones(n, dtype=np.int64)
    for _ in range(int(nsteps)):
        if system.run(1) != OK:
            raise RuntimeError(f"Hamaker case: {STATUS_TEXT[system.status]} at step {system.step}")
        new = (system.frozen != 0.0) & (dep < 0)
        dep[new] = system.step
    return dep


def run_case(case: dict) -> dict:
    """Simulate one field strength; returns the fitted and theoretical slopes."""
    from sim.electrokinetics import colloid_charge, henry_velocity, peclet_number

    R = case["radius"]
    lam = R / case["debye_ratio"]
    E = case["field"]  # along +z; a negative zeta gives a force toward z = 0
    q = colloid_charge(case["zeta"], R, lam, case["eps_r"])
    gamma = 6.0 * math.pi * case["viscosity"] * R
    v_drift = -q * E / gamma  # speed toward the substrate (positive)
    v_h = abs(float(henry_velocity(E, case["zeta"], R, lam, case["eps_r"], case["viscosity"])))
    v_h_sf = abs(float(henry_velocity(E, case["zeta"], R, lam, case["eps_r"], case["viscosity"], henry="swan_furst")))
    kT = BOLTZMANN * case["temperature"]
    D = kT / gamma
    H = case["height_radii"] * R
    n = int(case["n_particles"])
    area = case.get("area", 1.0)  # only heights matter; the per-area numbers use the box area
    t_end = 0.8 * (H - R) / v_drift
    dt = min(0.02 * R / v_drift, 0.002 * R * R / D)
    nsteps = int(math.ceil(t_end / dt))
    z0 = R + np.random.default_rng(case["seed"]).random(n) * (H - R)
    # the lateral box only sets how many (non-interacting) neighbours the engine lists, not the physics
    side = math.sqrt(case["area"]) if "area" in case else 3e-4 * math.sqrt(n / 1e5)
    dep = deposit_steps(z0, R, side, q * E, gamma, kT, dt, nsteps, int(case["seed"]))
    c_s = n / (area * (H - R))
    t = np.linspace(0.0, nsteps * dt, 201)
    steps_done = dep[dep > 0]
    counts = np.searchsorted(np.sort(steps_done * dt), t, side="right") / area
    window = (t >= 0.15 * t_end) & (t <= 0.75 * t_end)
    slope, icpt = np.polyfit(t[window], counts[window], 1)
    theory = c_s * v_h
    pe = float(peclet_number(E, case["zeta"], R, lam, case["eps_r"], case["temperature"]))
    return {"field": E, "pe": pe, "v_h": v_h, "v_h_swan_furst": v_h_sf, "v_drift": v_drift, "D": D, "c_s": c_s,
            "slope_sim": float(slope), "slope_theory": float(theory), "rel_err": float(abs(slope / theory - 1.0)),
            "n_particles": n, "n_deposited": int(len(steps_done)), "dt": dt, "steps": nsteps, "t_end": t_end,
            "t": t.tolist(), "n_per_area": counts.tolist(), "area": area, "fit_intercept": float(icpt)}


def add_arguments(p):
    from sim.studies._dask import add_study_arguments

    add_study_arguments(p)
    p.add_argument("--particles", type=int, default=None, help=f"particles per case (default {DEFAULTS['n_particles']})")


def cases_for(args) -> list[dict]:
    n = args.particles or (20_000 if args.quick else DEFAULTS["n_particles"])
    if n < 100:
        from ptrack.errors import UserError

        raise UserError(f"--particles {n} is too few for a slope", "give at least 100 particles")
    fields = [1.0e4] if args.quick else [5.0e3, 1.0e4, 2.0e4]
    side = (n / 100_000) ** 0.5 * 3e-4  # lateral box side: C_s ~ 2.3e17 m^-3 (volume fraction ~ 1e-3)
    return [dict(DEFAULTS, field=E, n_particles=n, seed=args.seed * 1000 + k, area=side * side)
            for k, E in enumerate(fields)]


def run(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ptrack.errors import atomic_output
    from sim.studies._dask import run_cases

    cases = cases_for(args)
    res = run_cases(run_case, cases, scheduler=args.scheduler, use_dask=not args.no_dask and len(cases) > 1,
                    workers=args.workers, desc="hamaker")
    print("Hamaker's law, perfect sticking: deposited number per area vs t, slope vs C_s v_H "
          "(Pe = v_H R / D_SE with 4 pi; the seed's eq. 3.37 has 6 pi)")
    print(f"{'E (V/m)':>9} {'Pe':>7} {'v_H (µm/s)':>11} {'C_s (1/m^3)':>12} {'slope sim':>11} {'C_s v_H':>11} "
          f"{'rel err':>8} {'deposited':>9}")
    for r in res:
        print(f"{r['field']:9.3g} {r['pe']:7.2f} {r['v_h'] * 1e6:11.3f} {r['c_s']:12.4g} {r['slope_sim']:11.4g} "
              f"{r['slope_theory']:11.4g} {100 * r['rel_err']:7.2f}% {r['n_deposited']:9d}")
    main = res[len(res) // 2]
    summary = {"slope_sim": main["slope_sim"], "slope_theory": main["slope_theory"], "rel_err": main["rel_err"],
               "cases": [{k: v for k, v in r.items() if k not in ("t", "n_per_area")} for r in res]}
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for r in res:
            t = np.asarray(r["t"])
            ax.plot(t * 1e3, np.asarray(r["n_per_area"]) / 1e12, label=f"sim, Pe = {r['pe']:.1f}")
            ax.plot(t * 1e3, (r["slope_theory"] * t + r["fit_intercept"]) / 1e12, "k--", lw=0.8)
        ax.set_xlabel("t (ms)")
        ax.set_ylabel("deposited per area (1/µm²)")
        ax.set_title("Hamaker's law: dashed = slope C_s v_H")
        ax.legend()
        with atomic_output(out / "hamaker.png", None) as tmp:
            fig.savefig(tmp, dpi=120, format="png")
        plt.close(fig)
        import pandas as pd

        with atomic_output(out / "hamaker.csv", None) as tmp:
            pd.DataFrame(summary["cases"]).to_csv(tmp, index=False)
        print(f"wrote {out / 'hamaker.png'} and {out / 'hamaker.csv'}", file=sys.stderr)
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(summary, fh, indent=2)
    return 0
