"""Electrophoretic terminal velocity vs Henry's law: the seed's 27 suspensions x 6 fields (Table 3.2).

R = 10, 100, 1000 nm x mu = 1e-4, 1e-3, 1e-2 Pa s x eps_r = 2, 40, 80, with
zeta = -0.05 V, R / lambda_D = 2, E = (0, 0, -E) for E = 10 ... 1e6 V/m,
fluid density 1000 kg/m^3, particle density 2200 kg/m^3, no gravity.
The charge is eq. 3.33 with Henry's exact function
(:func:`sim.electrokinetics.colloid_charge`).

What is simulated: each suspension is one task in which the particles of
all six fields are integrated together, from rest, with the seed's scheme
(generalised trapezoidal rule with phi = 0, i.e. forward Euler) and the
piecewise drag law of eq. 3.2-3.5, at T = 0 (no Brownian force: the
terminal velocity is the deterministic part of the motion, and at T = 0
``--replicates`` identical particles are run only to exercise the
vectorised kernel). dt = 0.2 of the linearised momentum relaxation time;
the run goes on until the velocity changes by less than 1e-14 relative
between output frames (5 relaxation times apart).

Per case: the simulated terminal velocity; the exact Henry velocity
(eq. 3.34 with exact f); Swan and Furst's approximation (eq. 3.35, about
0.15 % off at R / lambda = 2: an approximation error, not a simulation
error); the force-balance steady state of eq. 3.36 (fixed-point iteration,
:func:`sim.electrokinetics.steady_state_velocity`); the Reynolds number and
the Peclet number Pe = 4 pi R^2 |E zeta| eps eps0 f / (kB T) at T = 293 K
(the seed's eq. 3.37 prints 6 pi, making its Pe 1.5x too high). Cases with
Re > 1 leave Stokes' law (the seed's 21.5 % and 34.5 % outliers) and are
flagged with their Re.

Writes ``electrophoresis.csv`` (all cases), ``electrophoresis_table.csv``
(mean error per Pe decade vs exact Henry, Swan-Furst and force balance, the
seed's Table 3.2 layout), ``electrophoresis.png`` (like Fig. 3.15) and, with
``--json``, ``{"cases": [...], "wall_time_s"}``.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from sim.studies._dask import add_study_arguments, case_seed, run_cases
from sim.studies._output import case_records, save_figure, write_csv, write_json

RADII = (1e-8, 1e-7, 1e-6)
VISCOSITIES = (1e-4, 1e-3, 1e-2)
PERMITTIVITIES = (2.0, 40.0, 80.0)
FIELDS = (1e1, 1e2, 1e3, 1e4, 1e5, 1e6)
ZETA = -0.05
DEBYE_RATIO = 2.0
TEMPERATURE_PE = 293.0
PARTICLE_DENSITY = 2200.0
FLUID_DENSITY = 1000.0


def suspensions(seed: int = 0, replicates: int = 1, radii=RADII, viscosities=VISCOSITIES,
                permittivities=PERMITTIVITIES, fields=FIELDS) -> list[dict]:
    """One task description per suspension (radius, viscosity, eps_r) with its list of fields."""
    out = []
    for R in radii:
        for mu in viscosities:
            for eps in permittivities:
                out.append({"radius": R, "viscosity": mu, "eps_r": eps, "fields": list(fields),
                            "replicates": replicates, "seed": case_seed(seed, len(out))})
    return out


def simulate_suspension(task: dict, max_frames: int = 2000) -> list[dict]:
    """Simulate one suspension at all its fields; return one result dict per field."""
    from sim.electrokinetics import (henry_velocity, peclet_number, reynolds_number,
                                     steady_state_velocity)
    from sim.integrate import choose_integrator, momentum_relaxation_time
    from sim.run import Stepper
    from sim.scene import build_state, scene_from_dict

    t0 = time.perf_counter()
    R, mu, eps = task["radius"], task["viscosity"], task["eps_r"]
    fields = np.asarray(task["fields"], dtype=float)
    reps = int(task["replicates"])
    n = len(fields) * reps
    mass = PARTICLE_DENSITY * 4 / 3 * math.pi * R ** 3
    tau = mass / (6 * math.pi * mu * R)
    L = max(1e3 * R, 1e-5)
    raw = {
        "seed": int(task["seed"]),
        "particles": {"count": n, "radius": R, "density": PARTICLE_DENSITY, "zeta_potential": ZETA},
        "fluid": {"density": FLUID_DENSITY, "viscosity": mu, "temperature": 0.0, "relative_permittivity": eps,
                  "debye_ratio": DEBYE_RATIO},
        "fields": {"E": [0.0, 0.0, -1.0]},
        "gravity": {"enabled": False},
        "domain": {"size": [L, L, L]},
        "boundaries": {"bottom_wall": False},
        "time": {"final": 5 * tau * max_frames, "output_interval": 5 * tau},
        "integrator": {"kind": "trapezoidal", "phi": 0.0},
    }
    scene = scene_from_dict(raw)
    state = build_state(scene)
    E_part = np.repeat(fields, reps)                      # field magnitude per particle
    fconst = np.zeros((n, 3))
    fconst[:, 2] = state.charge * (-E_part)               # q E with E = (0, 0, -E)
    choice = choose_integrator(scene, state, fconst)
    stepper = Stepper(scene, state, fconst, choice)
    prev = state.vel[:, 2].copy()
    frames = 0
    converged = False
    while frames < max_frames:
        stepper.advance(1)
        frames += 1
        vz = state.vel[:, 2]
        if frames > 4 and np.all(np.abs(vz - prev) <= 1e-14 * np.abs(vz)):
            converged = True
            break
        prev = vz.copy()
    lam = R / DEBYE_RATIO
    results = []
    for j, E in enumerate(fields):
        sl = slice(j * reps, (j + 1) * reps)
        v_sim = float(np.mean(state.vel[sl, 2]))
        q = float(state.charge[j * reps])
        v_h = float(henry_velocity(-E, ZETA, R, lam, eps, mu))
        v_sf = float(henry_velocity(-E, ZETA, R, lam, eps, mu, henry="swan_furst"))
        v_bal = float(steady_state_velocity(q * -E, R, FLUID_DENSITY, mu))
        re = float(reynolds_number(v_sim, R, FLUID_DENSITY, mu))
        pe = float(peclet_number(E, ZETA, R, lam, eps, TEMPERATURE_PE))
        results.append({
            "radius": R, "viscosity": mu, "eps_r": eps, "E": float(E), "charge": q,
            "v_sim": v_sim, "v_henry_exact": v_h, "v_henry_sf": v_sf, "v_balance": v_bal, "Re": re, "Pe": pe,
            "err_henry": abs(v_sim / v_h - 1), "err_henry_sf": abs(v_sim / v_sf - 1),
            "err_balance": abs(v_sim / v_bal - 1), "re_gt_1": re > 1.0,
            "dt": choice.dt, "tau": float(momentum_relaxation_time(mass, 6 * math.pi * mu * R)),
            "t_sim": frames * scene.time.output_interval, "steps": frames * choice.steps_per_output,
            "converged": converged, "task_wall_time_s": time.perf_counter() - t0,
        })
    return results


def pe_decade_table(cases: list[dict]):
    """Mean percent error per Pe decade (the seed's Table 3.2) in three columns."""
    import pandas as pd

    df = pd.DataFrame(cases)
    df["pe_decade"] = np.floor(np.log10(df["Pe"])).astype(int)
    g = df.groupby("pe_decade")
    tab = pd.DataFrame({
        "Pe_order": [f"1e{k}" for k in g.groups.keys()],
        "n_cases": g.size().to_numpy(),
        "err_vs_henry_exact_pct": 100 * g["err_henry"].mean().to_numpy(),
        "err_vs_swan_furst_pct": 100 * g["err_henry_sf"].mean().to_numpy(),
        "err_vs_force_balance_pct": 100 * g["err_balance"].mean().to_numpy(),
        "max_Re": g["Re"].max().to_numpy(),
    })
    return tab


def run_study(replicates: int = 1, seed: int = 0, scheduler=None, use_dask: bool = True, workers=None,
              progress: bool = True, radii=RADII, viscosities=VISCOSITIES, permittivities=PERMITTIVITIES,
              fields=FIELDS) -> dict:
    """Run all suspensions; return ``{"cases": [...], "wall_time_s", "summary"}``."""
    t0 = time.perf_counter()
    tasks = suspensions(seed, replicates, radii, viscosities, permittivities, fields)
    res = run_cases(simulate_suspension, tasks, scheduler=scheduler, use_dask=use_dask, workers=workers,
                    progress=progress, desc="suspensions")
    cases = [c for r in res for c in r]
    stokes = [c for c in cases if not c["re_gt_1"]]
    summary = {
        "n_cases": len(cases),
        "n_re_gt_1": len(cases) - len(stokes),
        "max_err_henry_re_le_1": max((c["err_henry"] for c in stokes), default=float("nan")),
        "max_err_balance": max(c["err_balance"] for c in cases),
        "max_err_swan_furst_re_le_1": max((c["err_henry_sf"] for c in stokes), default=float("nan")),
        "all_converged": all(c["converged"] for c in cases),
    }
    return {"cases": cases, "wall_time_s": time.perf_counter() - t0, "summary": summary}


def write_outputs(result: dict, out_dir, json_path=None) -> list[Path]:
    """Write electrophoresis.csv, electrophoresis_table.csv, electrophoresis.png (and the JSON)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    cases = result["cases"]
    paths = []
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        df = pd.DataFrame(cases)
        paths.append(write_csv(df, out_dir / "electrophoresis.csv"))
        paths.append(write_csv(pe_decade_table(cases), out_dir / "electrophoresis_table.csv"))
        fig, ax = plt.subplots(1, 3, figsize=(17, 4.8))
        pe = df["Pe"].to_numpy()
        ratio = (df["v_sim"] / df["v_henry_exact"]).to_numpy()
        hi = df["re_gt_1"].to_numpy()
        ax[0].semilogx(pe[~hi], ratio[~hi], "o", ms=4, label="Re <= 1")
        ax[0].semilogx(pe[hi], ratio[hi], "o", color="red", ms=6, label="Re > 1 (piecewise drag)")
        for p_, r_, re_ in zip(pe[hi], ratio[hi], df["Re"].to_numpy()[hi]):
            ax[0].annotate(f"Re={re_:.2g}", (p_, r_), textcoords="offset points", xytext=(4, -10), fontsize=7,
                           color="red")
        ax[0].axhline(1.0, color="k", lw=0.8)
        ax[0].set(xlabel="Pe = 4 pi R^2 |E zeta| eps eps0 f / kT", ylabel="v_sim / v_Henry(exact f)",
                  title="Terminal velocity / Henry velocity (cf. seed Fig. 3.15)")
        ax[0].legend(fontsize=8)
        floor = 1e-17
        for col, mk, lab in (("err_henry", "o", "vs exact Henry"), ("err_henry_sf", "s", "vs Swan-Furst Henry"),
                             ("err_balance", "^", "vs force balance (eq. 3.36)")):
            ax[1].loglog(pe, np.maximum(df[col].to_numpy(), floor), mk, ms=4, mfc="none", label=lab)
        ax[1].loglog(pe[hi], np.maximum(df["err_henry"].to_numpy()[hi], floor), "o", color="red", ms=7,
                     label="Re > 1 cases")
        ax[1].axhline(1e-4, color="0.5", ls="--", lw=0.8)
        ax[1].set(xlabel="Pe", ylabel="|v_sim / v_ref - 1|",
                  title="Relative error per reference (Swan-Furst: its 0.15 % approximation)")
        ax[1].legend(fontsize=7)
        x = np.abs(df["v_henry_exact"].to_numpy())
        ax[2].loglog(x[~hi], np.abs(df["v_sim"].to_numpy())[~hi], "o", ms=4, label="Re <= 1")
        ax[2].loglog(x[hi], np.abs(df["v_sim"].to_numpy())[hi], "o", color="red", ms=6, label="Re > 1")
        ax[2].loglog([x.min(), x.max()], [x.min(), x.max()], "k-", lw=0.8, label="v = v_Henry")
        ax[2].set(xlabel="|v_Henry| (m/s)", ylabel="|v_sim| (m/s)", title="Simulated vs Henry velocity")
        ax[2].legend(fontsize=8)
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / "electrophoresis.png"))
    if json_path is not None:
        keys = ("radius", "viscosity", "eps_r", "E", "v_sim", "v_henry_exact", "v_henry_sf", "v_balance", "Re", "Pe",
                "err_henry", "err_henry_sf", "err_balance", "re_gt_1")
        doc = {"cases": case_records(cases, keys), "wall_time_s": result["wall_time_s"],
               "summary": result["summary"],
               "notes": ["T = 0 (deterministic terminal velocity), forward Euler (phi = 0) with the piecewise drag law",
                         "Pe uses 4 pi (the seed's eq. 3.37 prints 6 pi: its Pe values are 1.5x too high)",
                         "Re > 1 cases leave Stokes drag: the terminal velocity then differs from Henry's"]}
        paths.append(write_json(doc, json_path))
    return paths


def add_arguments(p) -> None:
    add_study_arguments(p)


def run(args) -> int:
    from ptrack.errors import check_positive

    reps = args.replicates if args.replicates is not None else 1
    check_positive("--replicates", reps)
    kw = {}
    if args.quick:
        kw = {"radii": (1e-7, 1e-6), "viscosities": (1e-4, 1e-3), "permittivities": (2.0, 80.0)}
    res = run_study(replicates=reps, seed=args.seed, scheduler=args.scheduler, use_dask=not args.no_dask,
                    workers=args.workers, **kw)
    paths = write_outputs(res, args.out or "study_electrophoresis", args.json)
    s = res["summary"]
    print("Electrophoresis study: T = 0, forward Euler (phi = 0), piecewise drag; zeta = -50 mV, R/lambda_D = 2; "
          "velocities in µm/s; Pe with 4 pi (seed eq. 3.37's 6 pi is 1.5x too high)")
    print(f"{'R (nm)':>7} {'mu':>7} {'eps':>4} {'E (V/m)':>8} {'v_sim':>12} {'v_Henry':>12} {'Re':>9} {'Pe':>9} "
          f"{'err_H':>9} {'err_SF':>9} {'err_bal':>9}")
    for c in res["cases"]:
        flag = "  Re > 1" if c["re_gt_1"] else ""
        print(f"{c['radius'] * 1e9:>7g} {c['viscosity']:>7g} {c['eps_r']:>4g} {c['E']:>8g} {c['v_sim'] * 1e6:>12.5g} "
              f"{c['v_henry_exact'] * 1e6:>12.5g} {c['Re']:>9.3g} {c['Pe']:>9.3g} {c['err_henry']:>9.2e} "
              f"{c['err_henry_sf']:>9.2e} {c['err_balance']:>9.2e}{flag}")
    print("\nMean error per Pe decade (%), cf. seed Table 3.2:")
    print(pe_decade_table(res["cases"]).to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"\nmax error vs exact Henry (Re <= 1): {s['max_err_henry_re_le_1']:.2e}; vs force balance (all): "
          f"{s['max_err_balance']:.2e}; vs Swan-Furst (Re <= 1): {s['max_err_swan_furst_re_le_1']:.2e} "
          f"(approximation error of Swan-Furst's f); {s['n_re_gt_1']} of {s['n_cases']} cases with Re > 1; "
          f"wall time {res['wall_time_s']:.1f} s")
    for p in paths:
        print(f"wrote {p}")
    return 0
