"""Brownian diffusion vs Stokes-Einstein: the 12 cases of the seed's Table 3.1.

R = 1, 10, 100, 1000 nm x mu = 1e-4, 1e-3, 1e-2 Pa s at T = 293 K; particle
density 2200 kg/m^3 (silica), fluid density 1000 kg/m^3, no gravity, no
field, no walls (free diffusion, as in the seed). Each case simulates
``replicates`` x ``particles`` independent particles with the exact joint
position-velocity OU integrator (exact for any dt, so the D error is purely
statistical) for ``frames`` output frames, one frame interval being
1000 momentum relaxation times m/gamma (so the inertial correction to the
covariance-based estimate, D[1 - e^-a (1 - e^-a)/a] at a = 1000, is nil).
D comes from the shared covariance-based estimator
(:func:`ptrack.msd.cve_from_positions`, x, y and z); its 95 % confidence
interval from the spread of the per-particle estimates (whole particles, not
displacements), with the Student t quantile. Per-case 95 % intervals each
cover with probability 0.95, so all 12 cover together only with probability
0.95^12 = 0.54; the study also reports simultaneous (Sidak) 95 % intervals,
which all cover together with probability 0.95 (bench/bench_integrators.py
checks the coverage over 200 seeds).

Writes ``diffusion.csv``, ``diffusion.png`` (D_sim vs D_SE like the seed's
Fig. 3.8, and the relative error with its CI per case) and, with ``--json``,
``{"cases": [...], "max_error_pct", "wall_time_s"}``.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from ptrack.constants import BOLTZMANN
from sim.studies._dask import add_study_arguments, case_seed, run_cases
from sim.studies._output import case_records, save_figure, write_csv, write_json

RADII = (1e-9, 1e-8, 1e-7, 1e-6)
VISCOSITIES = (1e-4, 1e-3, 1e-2)
TEMPERATURE = 293.0
PARTICLE_DENSITY = 2200.0
FLUID_DENSITY = 1000.0
RELAXATION_TIMES_PER_FRAME = 1000.0


def diffusion_cases(replicates: int = 20, particles: int = 10, frames: int = 5000, seed: int = 0,
                    radii=RADII, viscosities=VISCOSITIES, integrator: str = "ou_exact",
                    frame_interval: float | None = None) -> list[dict]:
    """The study's cases (dicts) in table order (viscosity major, radius minor, as Table 3.1)."""
    cases = []
    for mu in viscosities:
        for R in radii:
            i = len(cases)
            cases.append({"radius": R, "viscosity": mu, "temperature": TEMPERATURE, "n_particles": replicates * particles,
                          "replicates": replicates, "frames": frames, "seed": case_seed(seed, i),
                          "integrator": integrator, "frame_interval": frame_interval})
    return cases


def simulate_case(case: dict) -> dict:
    """Simulate one case and estimate D. Returns the case dict with D_analytical, D_sim, D_ci95, error_pct."""
    from scipy import stats

    from ptrack.msd import cve_from_positions, stokes_einstein
    from sim.integrate import choose_integrator
    from sim.run import Stepper
    from sim.scene import build_state, constant_force, scene_from_dict

    t0 = time.perf_counter()
    R, mu, T = case["radius"], case["viscosity"], case["temperature"]
    n = int(case["n_particles"])
    mass = PARTICLE_DENSITY * 4 / 3 * math.pi * R ** 3
    tau = mass / (6 * math.pi * mu * R)
    frame_dt = case.get("frame_interval") or RELAXATION_TIMES_PER_FRAME * tau
    L = max(1e3 * R, 1e-6)
    raw = {
        "seed": int(case["seed"]),
        "particles": {"count": n, "radius": R, "density": PARTICLE_DENSITY},
        "fluid": {"density": FLUID_DENSITY, "viscosity": mu, "temperature": T},
        "gravity": {"enabled": False},
        "domain": {"size": [L, L, L]},
        "boundaries": {"bottom_wall": False},
        "time": {"final": frame_dt * case["frames"], "output_interval": frame_dt},
        "integrator": {"kind": case.get("integrator", "ou_exact")},
    }
    scene = scene_from_dict(raw)
    state = build_state(scene)
    fc = constant_force(scene, state)
    choice = choose_integrator(scene, state, fc)
    stepper = Stepper(scene, state, fc, choice)
    nf = int(case["frames"])
    pos = np.empty((nf + 1, n, 3))
    pos[0] = state.pos
    stepper.advance(nf, pos[1:], np.empty((nf, n, 3)))
    traj = np.ascontiguousarray(pos.transpose(1, 0, 2))  # (n_particles, n_frames, 3)
    D_p, D_var = cve_from_positions(traj, frame_dt, motion_blur=0.0)
    D_p = np.asarray(D_p, dtype=float)
    D_sim = float(D_p.mean())
    se = float(D_p.std(ddof=1) / math.sqrt(n))
    q = float(stats.t.ppf(0.975, n - 1))
    D_se = float(stokes_einstein(R, mu, T))
    out = dict(case)
    out.update({
        "D_analytical": D_se, "D_sim": D_sim, "D_se_err": se, "D_ci95": [D_sim - q * se, D_sim + q * se],
        "D_closed_form_err": float(math.sqrt(np.sum(D_var)) / n),
        "error_pct": 100.0 * abs(D_sim / D_se - 1.0),
        "ci_covers": bool(D_sim - q * se <= D_se <= D_sim + q * se),
        "tau": tau, "frame_interval": frame_dt, "dt": choice.dt, "integrator_used": choice.kind,
        "n_displacements": n * nf * 3, "case_wall_time_s": time.perf_counter() - t0,
    })
    return out


def run_study(replicates: int = 20, particles: int = 10, frames: int = 5000, seed: int = 0, scheduler=None,
              use_dask: bool = True, workers=None, progress: bool = True, radii=RADII, viscosities=VISCOSITIES,
              integrator: str = "ou_exact", frame_interval: float | None = None) -> dict:
    """Run the 12 cases; return ``{"cases": [...], "max_error_pct", "wall_time_s", ...}``."""
    t0 = time.perf_counter()
    cases = diffusion_cases(replicates, particles, frames, seed, radii, viscosities, integrator, frame_interval)
    res = run_cases(simulate_case, cases, scheduler=scheduler, use_dask=use_dask, workers=workers,
                    progress=progress, desc="diffusion cases")
    wall = time.perf_counter() - t0
    # simultaneous (family-wise) 95 % intervals over all cases (Sidak): all cover at once with probability 0.95
    from scipy import stats
    level = 0.95 ** (1.0 / len(res))
    for c in res:
        q = float(stats.t.ppf(0.5 + level / 2, c["n_particles"] - 1))
        c["D_ci95_family"] = [c["D_sim"] - q * c["D_se_err"], c["D_sim"] + q * c["D_se_err"]]
        c["family_ci_covers"] = bool(c["D_ci95_family"][0] <= c["D_analytical"] <= c["D_ci95_family"][1])
    return {
        "cases": res,
        "n_family_ci_covering": sum(c["family_ci_covers"] for c in res),
        "max_error_pct": max(c["error_pct"] for c in res),
        "n_ci_covering": sum(c["ci_covers"] for c in res),
        "wall_time_s": wall,
        "settings": {"replicates": replicates, "particles_per_replicate": particles, "frames": frames, "seed": seed,
                     "temperature_K": TEMPERATURE, "particle_density": PARTICLE_DENSITY,
                     "fluid_density": FLUID_DENSITY,
                     "frame_interval": frame_interval if frame_interval else "1000 m/gamma", "estimator": "CVE (x, y, z)",
                     "integrator": integrator, "boltzmann": BOLTZMANN},
    }


def write_outputs(result: dict, out_dir, json_path=None) -> list[Path]:
    """Write diffusion.csv, diffusion.png (and the JSON); return the paths written."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    paths = []
    cases = result["cases"]
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        df = pd.DataFrame([{"viscosity_Pa_s": c["viscosity"], "radius_m": c["radius"],
                            "D_analytical_m2_s": c["D_analytical"], "D_sim_m2_s": c["D_sim"],
                            "D_ci95_lo": c["D_ci95"][0], "D_ci95_hi": c["D_ci95"][1],
                            "error_pct": c["error_pct"], "ci_covers": c["ci_covers"],
                            "D_ci95_family_lo": c["D_ci95_family"][0], "D_ci95_family_hi": c["D_ci95_family"][1],
                            "family_ci_covers": c["family_ci_covers"],
                            "n_displacements": c["n_displacements"]} for c in cases])
        paths.append(write_csv(df, out_dir / "diffusion.csv"))
        fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
        markers = {1e-4: "o", 1e-3: "s", 1e-2: "^"}
        for mu in sorted({c["viscosity"] for c in cases}):
            cs = [c for c in cases if c["viscosity"] == mu]
            x = np.array([c["D_analytical"] for c in cs])
            y = np.array([c["D_sim"] for c in cs])
            lo = y - np.array([c["D_ci95"][0] for c in cs])
            hi = np.array([c["D_ci95"][1] for c in cs]) - y
            ax[0].errorbar(x, y, yerr=[lo, hi], fmt=markers.get(mu, "o"), label=f"mu = {mu:g} Pa s", capsize=3)
            rel = 100 * (y / x - 1)
            ax[1].errorbar(x, rel, yerr=[100 * lo / x, 100 * hi / x], fmt=markers.get(mu, "o"), capsize=3,
                           label=f"mu = {mu:g} Pa s")
        allx = np.array([c["D_analytical"] for c in cases])
        lims = [allx.min() / 2, allx.max() * 2]
        ax[0].plot(lims, lims, "k-", lw=0.8, label="Stokes-Einstein")
        ax[0].set(xscale="log", yscale="log", xlabel="D_SE (m^2/s)", ylabel="D_sim (m^2/s)",
                  title="Simulated vs Stokes-Einstein D (95 % CI)")
        ax[0].legend(fontsize=8)
        ax[1].axhline(0, color="k", lw=0.8)
        ax[1].axhspan(-1, 1, color="0.9", zorder=0, label="+-1 %")
        ax[1].set(xscale="log", xlabel="D_SE (m^2/s)", ylabel="D_sim / D_SE - 1 (%)",
                  title=f"max error {result['max_error_pct']:.2f} % (seed: 10.2 %)")
        ax[1].legend(fontsize=8)
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / "diffusion.png"))
    if json_path is not None:
        keys = ("radius", "viscosity", "D_analytical", "D_sim", "D_ci95", "error_pct", "ci_covers", "D_ci95_family",
                "family_ci_covers", "n_displacements")
        doc = {"cases": case_records(cases, keys), "max_error_pct": result["max_error_pct"],
               "n_ci_covering": result["n_ci_covering"], "n_family_ci_covering": result["n_family_ci_covering"],
               "wall_time_s": result["wall_time_s"],
               "settings": result["settings"]}
        paths.append(write_json(doc, json_path))
    return paths


def add_arguments(p) -> None:
    add_study_arguments(p)
    p.add_argument("--particles", type=int, default=10, help="particles per replicate (default 10, as the seed)")
    p.add_argument("--frames", type=int, default=None, help="output frames per particle (default 5000; --quick 500)")
    p.add_argument("--frame-interval", type=float, default=None, metavar="SECONDS",
                   help="fixed frame interval for every case, e.g. a camera's 0.01 s (default: 1000 m/gamma per "
                        "case; the inertial bias of the estimate is D e^-a (1 - e^-a) / a at a = interval / (m/gamma))")
    p.add_argument("--integrator", choices=("ou_exact", "overdamped"), default="ou_exact",
                   help="time integrator (both exact for free particles; default ou_exact)")


def run(args) -> int:
    from ptrack.errors import UserError, check_positive

    reps = args.replicates if args.replicates is not None else (4 if args.quick else 20)
    frames = args.frames if args.frames is not None else (500 if args.quick else 5000)
    for name, v in (("--replicates", reps), ("--particles", args.particles), ("--frames", frames)):
        check_positive(name, v)
    if frames < 3:
        raise UserError(f"--frames {frames} is too few", "the covariance estimator needs at least 3 frames")
    if args.frame_interval is not None:
        check_positive("--frame-interval", args.frame_interval)
    if reps * args.particles < 2:
        raise UserError("one particle per case gives no confidence interval", "use --replicates/--particles >= 2")
    out = args.out or "study_diffusion"
    res = run_study(replicates=reps, particles=args.particles, frames=frames, seed=args.seed,
                    scheduler=args.scheduler, use_dask=not args.no_dask, workers=args.workers,
                    integrator=args.integrator, frame_interval=args.frame_interval)
    paths = write_outputs(res, out, args.json)
    print(f"Diffusion study: {reps} x {args.particles} particles x {frames} frames per case, {args.integrator} integrator, "
          f"CVE estimator over x, y, z (D in µm²/s)")
    print(f"{'mu (Pa s)':>10} {'R (nm)':>8} {'D_SE':>12} {'D_sim':>12} {'95% CI':>27} {'err %':>7} covers")
    for c in res["cases"]:
        lo, hi = c["D_ci95"]
        print(f"{c['viscosity']:>10g} {c['radius'] * 1e9:>8g} {c['D_analytical'] * 1e12:>12.5g} {c['D_sim'] * 1e12:>12.5g} "
              f"[{lo * 1e12:>11.5g}, {hi * 1e12:>11.5g}] {c['error_pct']:>7.3f} {'yes' if c['ci_covers'] else 'NO'}")
    n = len(res["cases"])
    print(f"max error {res['max_error_pct']:.3f} % (seed Table 3.1: 10.2 %); per-case 95 % CI covers D_SE in "
          f"{res['n_ci_covering']}/{n} cases (each covers with probability 0.95, so all {n} only with "
          f"probability {0.95 ** n:.2f}); simultaneous 95 % CIs (Sidak over {n} cases) cover in "
          f"{res['n_family_ci_covering']}/{n}; wall time {res['wall_time_s']:.1f} s")
    for p in paths:
        print(f"wrote {p}")
    return 0
