"""Throughput of the DEM engine on the Hooke/Coulomb reference scene (vs LAMMPS).

Reference scene (``scenes/hooke_reference.toml`` for N = 1000): Hooke contact
kn = 1e9 N/m, restitution 0.3 (particle-particle and wall), kt = 2/7 kn,
friction 0.4; R = 0.05 m, density 1540 kg/m^3; periodic x, y box of side
2.5 m * sqrt(N/1000); centres placed at random without overlap at
z = 0.1-0.45 m, at rest; uniform acceleration 109.81 m/s^2 toward the wall at
z = 0; dt = 1e-6 s.  LAMMPS 2025 (pair gran/hooke/history, one thread of this
machine): 2.2e7 particle-steps/s for N = 1000, 2.0e7 for N = 15000.

Usage::

    .venv/bin/python bench/bench_dem.py                 # N = 1e3, 1.5e4, 1e5
    .venv/bin/python bench/bench_dem.py --steps 100000 --sizes 1000

Prints N, steps, threads, wall and CPU time, particle-steps/s (wall),
contacts per particle at the end, neighbour-list builds.  The threaded pair
kernel (threads = 2) pays a fork/join per step; on a loaded 2-core machine
that costs more than it saves (see the report), so the engine's default is
the serial, bitwise-reproducible kernel.  For large N fewer steps are run
(``--steps-big``) and the cost per step is extrapolated: that is said in the
``note`` column.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

R = 0.05
RHO = 1540.0
ACC = 109.81


@njit(cache=True)
def _rsa_periodic(n, r, side, zlo, zhi, seed, max_tries):
    """Random sequential addition of equal spheres, periodic in x and y."""
    np.random.seed(seed)
    nc = max(1, int(side / (2 * r)))
    ncz = max(1, int((zhi - zlo) / (2 * r)) + 1)
    cs = side / nc
    head = -np.ones(nc * nc * ncz, dtype=np.int64)
    nxt = -np.ones(n, dtype=np.int64)
    pos = np.empty((n, 3))
    d2 = 4 * r * r
    for i in range(n):
        ok = False
        for _ in range(max_tries):
            x = np.random.random() * side
            y = np.random.random() * side
            z = zlo + np.random.random() * (zhi - zlo)
            cx = int(x / cs) % nc
            cy = int(y / cs) % nc
            cz = min(int((z - zlo) / (2 * r)), ncz - 1)
            ok = True
            for ox in range(-1, 2):
                for oy in range(-1, 2):
                    for oz in range(-1, 2):
                        az = cz + oz
                        if az < 0 or az >= ncz:
                            continue
                        c = (((cx + ox) % nc) * nc + (cy + oy) % nc) * ncz + az
                        j = head[c]
                        while j >= 0:
                            dx = x - pos[j, 0]
                            dy = y - pos[j, 1]
                            dx -= side * np.rint(dx / side)
                            dy -= side * np.rint(dy / side)
                            dz = z - pos[j, 2]
                            if dx * dx + dy * dy + dz * dz < d2:
                                ok = False
                                break
                            j = nxt[j]
                        if not ok:
                            break
                    if not ok:
                        break
                if not ok:
                    break
            if ok:
                pos[i, 0] = x
                pos[i, 1] = y
                pos[i, 2] = z
                c = (cx * nc + cy) * ncz + cz
                nxt[i] = head[c]
                head[c] = i
                break
        if not ok:
            return pos[:i]
    return pos


def reference_positions(n, side, seed=0):
    """Random non-overlapping centres in [0, side)^2 x [0.1, 0.45] m (periodic x, y)."""
    pos = _rsa_periodic(n, R, side, 0.1, 0.45, seed, 100000)
    if len(pos) < n:
        raise RuntimeError(f"placed only {len(pos)} of {n} particles")
    # number the particles in cell order (x, y columns): neighbours sit close in memory
    c = np.floor(pos[:, :2] / (4 * R)).astype(np.int64)
    order = np.lexsort((pos[:, 2], c[:, 1], c[:, 0]))
    return np.ascontiguousarray(pos[order]), np.full(n, R)


def reference_system(n, dt=1e-6, seed=0, threads=1):
    """DEMSystem of the reference scene with ``n`` particles."""
    from sim.dem import DEMSystem
    from sim.forces.contact import CONTACT_HOOKE, hooke_params

    side = 2.5 * np.sqrt(n / 1000.0)
    pos, rad = reference_positions(n, side, seed)
    mass = RHO * 4.0 / 3.0 * np.pi * rad**3
    cp = hooke_params(1e9, 0.3, kt=2.0 / 7.0 * 1e9, mu=0.4)
    fconst = mass[:, None] * np.array([0.0, 0.0, -ACC])[None, :]
    return DEMSystem(pos, np.zeros_like(pos), rad, mass, model=CONTACT_HOOKE, cp=cp, cpw=cp, rotation=True,
                     walls=[[0, 0, 0, 0, 0, 1]], box_lo=(0, 0, 0), box_length=(side, side, 1.0),
                     periodic=(1, 1, 0), fconst=fconst, dt=dt, skin=0.1 * 2 * R, seed=seed,
                     max_overlap=0.5, v_max=100.0, threads=threads)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 15000, 100000])
    ap.add_argument("--steps", type=int, default=100000, help="steps for N <= 1000")
    ap.add_argument("--steps-big", type=int, default=10000, help="steps for N > 1000 (cost extrapolated)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--contact-window", action="store_true",
                    help="for N > 1000 also time --steps-big steps in the packed phase (after an untimed "
                         "fast-forward to --ff-time with dt = 4e-6 s)")
    ap.add_argument("--ff-time", type=float, default=0.12, help="fast-forward target time (s), default 0.12")
    args = ap.parse_args(argv)
    import numba

    from sim.forces.contact import D_N_CONTACTS

    # compile once outside the timings
    for th in args.threads:
        s = reference_system(200, threads=th)
        s.run(10)
    rows = []

    def timed_run(s, n, steps, th, note_of):
        # run `steps` steps of system s, time them, add a table row and print it; note_of(wall) -> note
        t0 = time.perf_counter()
        c0 = time.process_time()
        st = s.run(steps)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        rate = n * steps / wall
        note = note_of(wall)
        rows.append((n, steps, th, wall, rate, s.diag[D_N_CONTACTS] / n, s.n_builds, st, note, cpu))
        print(f"N={n:7d} steps={steps:7d} threads={th} wall={wall:8.2f} s cpu={cpu:8.2f} s {rate:10.3e} particle-steps/s  "
              f"contacts/particle={s.diag[D_N_CONTACTS] / n:5.2f} builds={s.n_builds:5d} status={st} {note}",
              flush=True)

    for n in args.sizes:
        steps = args.steps if n <= 1000 else min(args.steps, args.steps_big)
        for th in args.threads:
            if th > numba.config.NUMBA_NUM_THREADS:
                continue
            numba.set_num_threads(th)
            s = reference_system(n, threads=th)
            timed_run(s, n, steps, th, lambda wall: "" if steps == args.steps else
                      f"first {steps} steps (free fall), {args.steps} extrapolated: {wall * args.steps / steps:.1f} s")
            if n > 1000 and args.contact_window:
                s.dt = 4e-6
                s.run(int(round((args.ff_time - s.t) / 4e-6)))  # untimed fast-forward into the packed phase
                s.dt = 1e-6
                timed_run(s, n, steps, th, lambda wall: f"packed phase t = {args.ff_time:g} s: {steps} steps, "
                          f"{args.steps} extrapolated: {wall * args.steps / steps:.1f} s")
    print()
    print("| N | steps | threads | wall (s) | CPU (s) | particle-steps/s (wall) | contacts/particle | LAMMPS 1 thread | ratio | note |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    lammps = {1000: 2.2e7, 15000: 2.0e7}
    for n, steps, th, wall, rate, cpp, nb, st, note, cpu in rows:
        ref = lammps.get(n)
        print(f"| {n} | {steps} | {th} | {wall:.2f} | {cpu:.2f} | {rate:.3e} | {cpp:.2f} | {f'{ref:.1e}' if ref else '-'} | "
              f"{rate / ref if ref else float('nan'):.2f} | {note} |")


if __name__ == "__main__":
    main()
