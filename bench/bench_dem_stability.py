"""Stability sweep: contact stiffness x time step on the reference deposition scene.

For every (kn, dt) the reference scene of ``bench_dem.py`` (Hooke contact,
restitution 0.3, friction 0.4, 109.81 m/s^2 toward the wall, periodic sides)
with N particles runs for ``t_end`` seconds with blow-up detection on.
Afterwards the final state is judged independently of the detector:
physical = all finite, every centre above the wall, max overlap < 0.5 R,
kinetic energy below the work the external force can do.  Outcomes:

* ``ok``      finished and physical
* ``caught``  the engine stopped with a blow-up status (overlap / NaN / wall / speed)
* ``SILENT``  finished without a report but the state is unphysical (must never happen)

The ``auto`` column runs each stiffness with :func:`sim.dem.auto_dt`.
The theoretical critical step ``2/omega (sqrt(1+zeta^2) - zeta)`` of a
particle-particle contact (reduced mass m/2) is printed for reference.

Usage: ``.venv/bin/python bench/bench_dem_stability.py [--n 300] [--t-end 0.12]``
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_dem import ACC, R, RHO, reference_positions  # noqa: E402


def make(n, kn, dt, seed=0):
    from sim.dem import DEMSystem
    from sim.forces.contact import CONTACT_HOOKE, hooke_params

    side = 2.5 * np.sqrt(n / 1000.0)
    pos, rad = reference_positions(n, side, seed)
    mass = RHO * 4.0 / 3.0 * np.pi * rad**3
    cp = hooke_params(kn, 0.3, kt=2.0 / 7.0 * kn, mu=0.4)
    v_ref = math.sqrt(2 * ACC * 0.5)
    return DEMSystem(pos, np.zeros_like(pos), rad, mass, model=CONTACT_HOOKE, cp=cp, cpw=cp, rotation=True,
                     walls=[[0, 0, 0, 0, 0, 1]], box_length=(side, side, 1.0), periodic=(1, 1, 0),
                     fconst=mass[:, None] * np.array([0, 0, -ACC]), dt=dt, skin=0.01, seed=seed,
                     max_overlap=0.5, v_max=20 * v_ref), mass


def judge(s, mass):
    from sim.forces.contact import D_MAX_OVERLAP

    finite = np.isfinite(s.pos).all() and np.isfinite(s.vel).all()
    above = finite and (s.pos[:, 2] > 0).all()
    ke = s.kinetic_energy() if finite else np.inf
    work = float(np.sum(mass * ACC * 0.5))  # the field can do at most m a h of work (h <= 0.5 m)
    return finite and above and ke <= 1.5 * work and s.diag[D_MAX_OVERLAP] < 0.5


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--t-end", type=float, default=0.12)
    ap.add_argument("--kn", type=float, nargs="+", default=[1e6, 1e7, 1e8, 1e9, 1e10])
    ap.add_argument("--dt", type=float, nargs="+", default=[1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3])
    args = ap.parse_args(argv)
    from sim.dem import STATUS_TEXT, auto_dt, critical_step
    from sim.forces.contact import restitution_beta
    from sim.interactions import Interactions

    make(50, 1e6, 1e-5)[0].run(5)  # compile
    counts = {"ok": 0, "caught": 0, "SILENT": 0}
    print(f"N = {args.n}, t_end = {args.t_end} s; outcome per dt (ok / caught: reason / SILENT)")
    rows = []
    t0 = time.perf_counter()
    for kn in args.kn:
        m = RHO * 4 / 3 * np.pi * R**3
        w2 = kn / (0.5 * m)  # particle-particle contact: reduced mass m/2
        crit = critical_step(w2, 2 * restitution_beta(0.3) * math.sqrt(w2))
        s, mass = make(args.n, kn, 1e-6)
        it = Interactions(model=1, cp=s.cp, cpw=s.cpw, dt_safety=0.2)
        dt_auto, _ = auto_dt(it, s.radius, s.mass, s.fconst, height=0.5)
        line = []
        for dt in args.dt + [dt_auto]:
            s, mass = make(args.n, kn, dt)
            nsteps = int(round(args.t_end / dt))
            st = s.run(nsteps)
            if st != 0:
                out = "caught:" + {1: "overlap", 2: "nan", 3: "wall", 4: "speed"}[st]
                counts["caught"] += 1
            elif judge(s, mass):
                out = "ok"
                counts["ok"] += 1
            else:
                out = "SILENT"
                counts["SILENT"] += 1
            line.append(out)
            rows.append((kn, dt, out, dt > crit))
        print(f"kn = {kn:8.1e} N/m  dt_crit(pair) = {crit:9.3e} s  auto dt = {dt_auto:9.3e} s")
        for dt, o in zip(args.dt + [dt_auto], line):
            tag = "auto" if dt == dt_auto else ""
            print(f"    dt = {dt:9.2e} s {'(dt > dt_crit)' if dt > crit else '              '} -> {o} {tag}")
    print()
    print("| kn (N/m) | dt (s) | dt > critical | outcome |")
    print("|---|---|---|---|")
    for kn, dt, o, over in rows:
        print(f"| {kn:.0e} | {dt:.2e} | {'yes' if over else 'no'} | {o} |")
    print(f"\ntotals: {counts}; wall time {time.perf_counter() - t0:.1f} s")
    auto_bad = [r for r in rows[len(args.dt)::len(args.dt) + 1] if r[2] != "ok"]
    print("automatic dt stable for every stiffness:", not auto_bad)
    return 0 if counts["SILENT"] == 0 and not auto_bad else 1


if __name__ == "__main__":
    sys.exit(main())
