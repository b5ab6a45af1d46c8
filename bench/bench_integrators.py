"""Integrators: run time against D error over a sweep of dt, and the explicit scheme's stability boundary.

Part 1 (the diffusion study's physics): R = 100 nm silica (2200 kg/m^3) in
water-like fluid (mu = 1e-3 Pa s, T = 293 K), m/gamma = tau = 4.9 ns.
For each integrator and dt/tau from 0.01 to 1e4, N particles are started
from equilibrium (thermal velocities) and D is estimated with the shared
CVE estimator from frames Delta = max(20 tau, dt) apart (the inertial bias
of the CVE at Delta = 20 tau is e^-20 ~ 2e-9, nil). Printed: wall time,
D_sim / D_SE - 1 with its standard error, and m <v^2> / kB T
(equipartition; the overdamped integrator has no thermal velocity).
Explicit trapezoidal runs past their stability limit are run anyway
(bypassing the refusal) to show what the refusal prevents.

Part 2: the stability boundary of the trapezoidal rule with phi = 0
(forward Euler) and phi = 0.25, found by bisection on dt (a velocity
perturbation grows or decays over 4000 steps), against the predictions
2 tau / (1 - 2 phi); and the same for the piecewise drag at Re ~ 15 (R = 1 um, mu = 1e-4 Pa s), where
the prediction uses the linearised relaxation time m / (dF/dv).

Part 3: calibration of the diffusion study's 95 % confidence intervals:
the fraction of independent seeds whose CI covers D_SE (R = 100 nm,
mu = 1e-3 Pa s, 200 particles x 1000 frames per seed) should be ~0.95; the
chance that all 12 cases of one study cover is then 0.95^12 = 0.54.

Run: .venv/bin/python bench/bench_integrators.py [--quick]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from ptrack.constants import BOLTZMANN
from ptrack.msd import cve_from_positions
from sim.integrate import IntegratorChoice, effective_relaxation_time, trapezoidal_kernel
from sim.run import Stepper
from sim.scene import build_state, constant_force, scene_from_dict

R, MU, T, RHO_P, RHO_F = 1e-7, 1e-3, 293.0, 2200.0, 1000.0


def scene(n, out, seed=1, temperature=T, radius=R, mu=MU):
    return scene_from_dict({
        "seed": seed,
        "particles": {"count": n, "radius": radius, "density": RHO_P, "initial_velocity": "thermal"},
        "fluid": {"density": RHO_F, "viscosity": mu, "temperature": temperature},
        "gravity": {"enabled": False},
        "domain": {"size": [1e-3, 1e-3, 1e-3]},
        "boundaries": {"bottom_wall": False},
        "time": {"final": out * 10, "output_interval": out},
    })


def run_case(kind, phi, dt_tau, n, frames, seed=1):
    mass = RHO_P * 4 / 3 * math.pi * R ** 3
    gamma = 6 * math.pi * MU * R
    tau = mass / gamma
    dt = dt_tau * tau
    delta = max(20 * tau, dt)
    steps = max(1, round(delta / dt))
    sc = scene(n, delta, seed)
    st = build_state(sc)
    fc = constant_force(sc, st)
    ch = IntegratorChoice(kind=kind, dt=delta / steps, steps_per_output=steps, phi=phi, reason="bench",
                          tau_min=tau, re_estimate=0.0, max_stable_dt=math.inf)
    stepper = Stepper(sc, st, fc, ch, seed=seed)
    stepper.advance(1)  # compile outside the timing
    st = build_state(sc)
    stepper = Stepper(sc, st, fc, ch, seed=seed)
    pos = np.empty((frames + 1, n, 3))
    vel = np.empty((frames, n, 3))
    pos[0] = st.pos
    t0 = time.perf_counter()
    with np.errstate(all="ignore"):
        stepper.advance(frames, pos[1:], vel)
    wall = time.perf_counter() - t0
    if not (np.isfinite(pos).all() and np.abs(pos).max() < 1.0):
        return {"wall": wall, "err": math.nan, "se": math.nan, "equi": math.nan, "status": "UNSTABLE (diverged)",
                "dt_tau": delta / steps / tau}
    D0 = BOLTZMANN * T / gamma
    D, _ = cve_from_positions(np.ascontiguousarray(pos.transpose(1, 0, 2)), delta, motion_blur=0.0)
    err = 100 * (np.mean(D) / D0 - 1)
    se = 100 * np.std(D, ddof=1) / math.sqrt(n) / D0
    equi = mass * np.mean(vel ** 2) / (BOLTZMANN * T) if kind != "overdamped" else math.nan
    return {"wall": wall, "err": err, "se": se, "equi": equi, "status": "ok", "steps": steps * frames * n,
            "dt_tau": delta / steps / tau}


def grows(phi, dt, mass, gamma, radius, rho_f, mu, fz, v_start, v_ref, nsteps=4000):
    """True if a velocity perturbation of the trapezoidal rule grows over nsteps."""
    pos = np.zeros((1, 3))
    vel = np.array([[0.0, 0.0, v_start]])
    out_p = np.empty((1, 1, 3))
    out_v = np.empty((1, 1, 3))
    fconst = np.array([[0.0, 0.0, fz]])
    modes = np.zeros((2, 3), dtype=np.int64)
    with np.errstate(all="ignore"):
        trapezoidal_kernel(pos, vel, np.array([radius]), np.array([mass]), np.array([gamma]), np.zeros(1), fconst,
                           np.zeros(3), np.zeros(3), rho_f, mu, 0.0, dt, nsteps, 1, np.full(3, 1e300), modes,
                           out_p, out_v, False, phi, 1e-13, 200, fz == 0.0, 0, 1, 0, 0)
    d = abs(vel[0, 2] - v_ref)
    return not (np.isfinite(d) and d <= abs(v_start - v_ref))


def boundary(phi, mass, gamma, radius, rho_f, mu, fz, v_ref, pert, lo, hi):
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if grows(phi, mid, mass, gamma, radius, rho_f, mu, fz, v_ref + pert, v_ref):
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer particles/frames and dt values")
    args = ap.parse_args()
    n, frames = (100, 200) if args.quick else (200, 400)
    dts = [0.1, 1.9, 100.0] if args.quick else [0.05, 0.1, 0.5, 1.0, 1.9, 2.5, 10.0, 100.0, 1e3, 1e4]
    mass = RHO_P * 4 / 3 * math.pi * R ** 3
    gamma = 6 * math.pi * MU * R
    tau = mass / gamma
    print(f"Part 1: R = {R * 1e9:g} nm, mu = {MU:g} Pa s, T = {T:g} K, tau = m/gamma = {tau:.3g} s; "
          f"{n} particles x {frames} frames (Delta = max(20 tau, dt)), CVE over x, y, z")
    print(f"{'integrator':<18} {'dt/tau':>8} {'wall (s)':>9} {'Mstep/s':>8} {'D err %':>9} {'+- SE %':>8} "
          f"{'m<v2>/kT':>9}  status")
    print("(dt is adjusted to divide the frame interval; forward Euler's expected m<v2>/kT is 1 / (1 - dt / 2 tau))")
    integrators = [("ou_exact", 0.0), ("overdamped", 0.0), ("trapezoidal", 0.0), ("trapezoidal", 0.5),
                   ("trapezoidal", 1.0)]
    for kind, phi in integrators:
        for dt_tau in dts:
            r = run_case(kind, phi, dt_tau, n, frames)
            name = kind if kind != "trapezoidal" else f"trapezoidal phi={phi:g}"
            rate = r.get("steps", 0) / r["wall"] / 1e6 if r["wall"] > 0 else math.nan
            print(f"{name:<18} {r['dt_tau']:>8.4g} {r['wall']:>9.3f} {rate:>8.1f} {r['err']:>9.3f} {r['se']:>8.3f} "
                  f"{r['equi']:>9.4f}  {r['status']}")

    print("\nPart 2: stability boundary of the trapezoidal rule (perturbation growth over 4000 steps, bisection)")
    print(f"{'case':<34} {'phi':>5} {'measured dt_max':>16} {'predicted':>12} {'ratio':>7}")
    for phi in (0.0, 0.25):
        meas = boundary(phi, mass, gamma, R, RHO_F, MU, 0.0, 0.0, 1e-3, 0.5 * tau, 20 * tau)
        pred = 2 * tau / (1 - 2 * phi)
        print(f"{'Stokes drag, R = 100 nm':<34} {phi:>5g} {meas:>16.6g} {pred:>12.6g} {meas / pred:>7.4f}")
    # piecewise drag at Re ~ 15 (R = 1 um, mu = 1e-4 Pa s)
    from sim.electrokinetics import steady_state_velocity
    R2, mu2 = 1e-6, 1e-4
    m2 = RHO_P * 4 / 3 * math.pi * R2 ** 3
    g2 = 6 * math.pi * mu2 * R2
    F = 3.8e-9
    v_ss = float(steady_state_velocity(F, R2, RHO_F, mu2))
    re = 2 * R2 * RHO_F * v_ss / mu2
    tau_eff = effective_relaxation_time(m2, g2, re)
    meas = boundary(0.0, m2, g2, R2, RHO_F, mu2, F, v_ss, 1e-6 * v_ss, 0.1 * tau_eff, 20 * tau_eff)
    pred = 2 * tau_eff
    print(f"{f'piecewise drag, Re = {re:.2f}':<34} {0:>5g} {meas:>16.6g} {pred:>12.6g} {meas / pred:>7.4f}"
          f"   (Stokes 2 m/gamma = {2 * m2 / g2:.4g} s would be {2 * m2 / g2 / meas:.2f}x too large)")


    from scipy import stats

    from sim.studies.diffusion import diffusion_cases, simulate_case
    n_seeds = 20 if args.quick else 200
    t0 = time.perf_counter()
    cover, errs = [], []
    for seed in range(n_seeds):
        case = diffusion_cases(replicates=20, particles=10, frames=1000, seed=seed, radii=(R,), viscosities=(MU,))[0]
        r = simulate_case(case)
        cover.append(r["ci_covers"])
        errs.append(r["D_sim"] / r["D_analytical"] - 1)
    k = int(np.sum(cover))
    lo, hi = stats.beta.ppf([0.025, 0.975], k + 0.5, n_seeds - k + 0.5)
    print(f"\nPart 3: 95 % CI coverage over {n_seeds} seeds: {k}/{n_seeds} = {k / n_seeds:.3f} "
          f"(Jeffreys 95 % interval {lo:.3f}-{hi:.3f}); mean D error {100 * np.mean(errs):+.3f} % "
          f"+- {100 * np.std(errs, ddof=1) / math.sqrt(n_seeds):.3f} % (bias check); {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
