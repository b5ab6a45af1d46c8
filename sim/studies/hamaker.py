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
matched (no sedimentation).  The Peclet number is the corrected one,
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
from numba import njit

from ptrack.constants import BOLTZMANN
from sim.forces.brownian import counter_normal

DEFAULTS = dict(radius=100e-9, zeta=-0.05, eps_r=80.0, viscosity=1.0e-3, temperature=293.0, debye_ratio=2.0,
                height_radii=50.0, n_particles=100_000)


@njit(cache=True, nogil=True)
def _bd_stick(z, radius, height, v, D, dt, nsteps, seed):
    """Heights ``z`` (m, start) of non-interacting particles under drift -v (toward z = 0) and diffusion D.

    Returns the deposition step of every particle (-1: never deposited).
    Reflecting top at ``height``; absorbing (sticking) plane at ``z = radius``.
    The heights alone matter, so this is the overdamped update of the engine
    reduced to z (one random number per particle and step instead of three),
    with the engine's counter-based random numbers
    (:func:`sim.forces.brownian.counter_normal`).
    """
    n = z.shape[0]
    dep = -np.ones(n, dtype=np.int64)
    s = math.sqrt(2.0 * D * dt)
    for i in range(n):
        zi = z[i]
        for k in range(nsteps):
            zi += -v * dt + s * counter_normal(seed, k + 1, i)
            if zi > height:
                zi = 2.0 * height - zi
            if zi <= radius:
                dep[i] = k + 1
                break
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
    dep = _bd_stick(z0, R, H, v_drift, D, dt, nsteps, int(case["seed"]))
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
    print(f"{'E (V/m)':>9} {'Pe':>7} {'v_H (um/s)':>11} {'C_s (1/m^3)':>12} {'slope sim':>11} {'C_s v_H':>11} "
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
        ax.set_ylabel("deposited per area (1/um^2)")
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
