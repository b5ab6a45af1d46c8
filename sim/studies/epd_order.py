"""Order of EPD deposits against Peclet number and Debye length (Giera et al.,
the seed's future-work Fig. 3.24), at Giera's size: 15 000 particles per deposit.

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
makes its values 1.5x too high); the default grid (:data:`FULL`) spans
Giera's Pe = 26.5-858 (6 pi form), i.e. 17.7-572.  Each (Pe, a/lambda_D,
replicate) case is an independent dask task; with ``--out`` every finished
case is its own JSON under ``cases/`` (skipped when the command is run
again), a running case checkpoints its state and continues bit-identically,
and ``--collect`` analyses whatever has finished.  The trend is the
least-squares slope of the solid-like fraction against log10 Pe over all
deposits of one a/lambda_D, with its t-test p-value (:func:`summarise`).

Giera et al. found the order falling as Pe rises.  Their particles also
attract by van der Waals (the DLVO primary minimum), so a hard push sticks
them where they land.  Here the particles only repel (screened Coulomb and
the contact spring), and the layers on the mobile substrate stay ordered at
every Pe (a/lambda_D = 5, Pe 540: 0.71 for the whole deposit, 0.40 for its
interior).  At 600
particles (``results/epd_order_n600``, 3 replicates) the order of the whole
deposit is flat in Pe at a/lambda_D = 5 (p = 0.8) and falls at 10
(-0.13 +- 0.03 per decade, p = 0.001), while the order of the interior
(above the substrate layers, below the top) falls at both (-0.21 +- 0.07,
p = 0.02; -0.44 +- 0.05, p < 1e-5): the Pe dependence is in the bulk of the
deposit, and the whole-deposit number mixes it with the substrate layers.
The order also keeps growing while the buried layers anneal after the last
particle arrives (1500 particles, Pe 50: solid-like fraction 0.54 at 1.1 x
the transport time, 0.87 at 2 x).  The observable is therefore the deposit
at ``t_end = (1 + settle) x`` the transport time ``height / v`` (plus
``20 a^2 / (D Pe)``), with ``settle = 1``: a shorter settle would change it.

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
from sim.driver import WallClockChunker
from sim.forces.contact import CONTACT_HOOKE
from sim.forces.nearfield import NF_YUKAWA, law_row, law_table

DEFAULTS = dict(radius=100e-9, temperature=293.0, viscosity=1e-3, eps_r=80.0, psi=0.05, n_particles=15_000,
                side_radii=None, height_radii=None, volume_fraction=0.04, dt_reduced=2e-4, settle=1.0,
                contact_stiffness_kT=5.0e3, skin_radii=0.5)

#: the full study (Giera et al.'s 15 000 particles): Pe spanning Giera's 26.5-858 (their 6 pi form; 17.7-572 in
#: the corrected 4 pi one), two Debye lengths, three replicates per case
FULL = dict(pe=[20.0, 60.0, 180.0, 540.0], a_over_lambda=[5.0, 10.0], n_particles=15_000, replicates=3)
#: the CI-sized version (--quick)
QUICK = dict(pe=[20.0, 180.0], a_over_lambda=[5.0], n_particles=150, replicates=2)
#: steps per kernel call: fixed, so that a run resumed from a checkpoint is bit-identical to an uninterrupted one
CHUNK_STEPS = 20_000


def build_case(case: dict):
    """The engine system of one (Pe, a/lambda_D) deposit and its times.

    Returns ``(system, info)``: a :class:`sim.dem.DEMSystem` on the
    overdamped stepper with every particle placed in the dilute start, and a
    dict with ``side``, ``height`` (m, box), ``t_end`` (s) and ``gamma``.
    """
    from sim.forces.contact import hooke_params
    from sim.forces.nearfield import yukawa_prefactor
    from sim.placement import place_particles

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
                       extp=np.array([0.0, 0.0, 0.0, 0.0, 0.0, kT, 0.0, 0.0, 0.0]), dt=dt0,
                       skin=case.get("skin_radii", 0.3) * a,
                       cutoff=cut, seed=int(case["seed"]), integrator=OVERDAMPED,
                       substrate="stick" if case.get("substrate", "stick") == "stick" else "reflect",
                       max_step=0.01 * a, max_overlap=np.inf)
    return system, {"side": side, "height": height, "t_end": t_end, "gamma": gamma, "cut": cut}


def run_case(case: dict, checkpoint=None, state=None, progress=None) -> dict:
    """One (Pe, a/lambda_D) deposit; returns order metrics.

    Parameters
    ----------
    case : dict
        :data:`DEFAULTS` with ``pe``, ``a_over_lambda``, ``seed`` (and ``substrate``).
    checkpoint : callable, optional
        ``checkpoint(system)`` after every kernel call of :data:`CHUNK_STEPS` steps (it decides whether to save).
    state : dict, optional
        A :meth:`sim.dem.DEMSystem.get_state` snapshot taken at a chunk end: the run continues from it and
        gives the same numbers as the uninterrupted run (each chunk ends with a neighbour-list rebuild, the
        one :meth:`~sim.dem.DEMSystem.set_state` does).
    progress : callable, optional
        ``progress(system, t_end)`` after every chunk.
    """
    system, info = build_case(case)
    if state is not None:
        system.set_state(state)
    t_end = info["t_end"]
    max_steps = 200_000_000
    # kernel calls of ~0.25 s wall time inside each chunk (bit-identical to one call): a signal stops a
    # 15 000-particle case within a second instead of after the chunk's minutes
    chunker = WallClockChunker(first=max(1, 200_000 // max(system.n, 1)))
    while system.t < t_end and system.step < max_steps:
        if system.run(min(CHUNK_STEPS, max_steps - system.step), until=t_end, rebuild_at_end=True,
                      chunker=chunker) != OK:
            raise RuntimeError(f"EPD-order case: {STATUS_TEXT[system.status]} at step {system.step}")
        if progress is not None:
            progress(system, t_end)
        if checkpoint is not None and system.t < t_end:
            checkpoint(system)
    return analyse_deposit(case, system, info)


def analyse_deposit(case: dict, system, info: dict) -> dict:
    """Order metrics of the final deposit of one case (see the module docstring)."""
    from scipy.spatial import cKDTree

    from sim.analysis import solid_like, steinhardt_q6

    a = case["radius"]
    side, height = info["side"], info["height"]
    rad = system.radius
    pos = system.pos
    n = len(pos)
    stuck = system.frozen != 0.0
    t, steps = system.t, system.step
    stuck = stuck if case.get("substrate", "stick") == "stick" else pos[:, 2] < rad * 1.05
    # deposit: everything below the top surface that has arrived
    z = pos[:, 2]
    arrived = z < np.quantile(z, 0.98) + 4 * a
    # neighbours: up to the first minimum of g(r), estimated as 1.3 x the median nearest distance
    tree = cKDTree(np.mod(pos, [side, side, 1e9]), boxsize=[side, side, 1e9])
    dnn, _ = tree.query(np.mod(pos, [side, side, 1e9]), k=2)
    r_cut = 1.3 * float(np.median(dnn[:, 1]))
    q6 = steinhardt_q6(pos, r_cut=r_cut, length=[side, side, 1e9], periodic=[1, 1, 0])
    solid, nconn = solid_like(pos, r_cut=r_cut, length=[side, side, 1e9], periodic=[1, 1, 0])
    interior = arrived & (z > 3 * a) & (z < np.quantile(z, 0.9))
    sel = interior if interior.sum() >= 10 else arrived
    return {"pe": case["pe"], "a_over_lambda": case["a_over_lambda"], "n_particles": n, "steps": int(steps),
            "t_end": t, "solid_fraction": float(solid[arrived].mean()),
            "solid_fraction_interior": float(solid[sel].mean()),
            "q6_mean": float(np.nanmean(q6[arrived])), "stuck_on_substrate": int(stuck.sum()),
            "r_cut": r_cut, "nn_distance": float(np.median(dnn[:, 1])), "side": side, "height": height,
            "deposit_height": float(np.quantile(z, 0.95) + a)}


def add_arguments(p):
    from sim.studies._dask import add_study_arguments

    add_study_arguments(p)
    p.add_argument("--pe", type=float, nargs="+", default=None,
                   help=f"Peclet numbers (default {' '.join(f'{v:g}' for v in FULL['pe'])})")
    p.add_argument("--a-over-lambda", type=float, nargs="+", default=None,
                   help=f"radius / Debye length values (default {' '.join(f'{v:g}' for v in FULL['a_over_lambda'])})")
    p.add_argument("--particles", type=int, default=None,
                   help=f"particles per deposit (default {FULL['n_particles']}, --quick {QUICK['n_particles']})")
    p.add_argument("--substrate", choices=("stick", "contact"), default="contact",
                   help="contact: a hard frictionless substrate, particles stay laterally mobile (default); "
                        "stick: particles stick on first contact with the substrate")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0,
                   help="with --out: save a running case's state this often (wall clock, default 5)")
    p.add_argument("--collect", action="store_true",
                   help="with --out: run nothing, analyse the cases already finished there (partial results too)")


def cases_for(args) -> list[dict]:
    """The grid of cases of a command line: a/lambda_D, then replicate, then Pe (cheapest first)."""
    from ptrack.errors import UserError

    grid = QUICK if args.quick else FULL
    pes = args.pe or grid["pe"]
    als = args.a_over_lambda or grid["a_over_lambda"]
    n = args.particles or grid["n_particles"]
    for v in pes + als:
        if not (v > 0 and math.isfinite(v)):
            raise UserError(f"Pe and a/lambda_D must be positive, got {v}", "give positive values")
    if n < 20:
        raise UserError(f"--particles {n} is too few for a deposit", "give at least 20")
    reps = args.replicates or grid["replicates"]
    if reps < 1:
        raise UserError(f"--replicates {reps}", "give at least 1")
    out = []
    # the seed of a case depends only on (base seed, a/lambda, Pe, replicate): adding a Pe or a replicate
    # leaves the other cases (and their finished files) as they are
    for al in als:
        for r in range(reps):
            for pe in sorted(pes, reverse=True):
                seed = case_seed(args.seed, int(round(al * 1000)), int(round(pe * 1000)), r)
                out.append(dict(DEFAULTS, pe=pe, a_over_lambda=al, n_particles=n, seed=seed, rep=r,
                                substrate=args.substrate))
    return out


def case_seed(base: int, *keys: int) -> int:
    """Integer seed of one case from the base seed and the case's integer keys."""
    return int(np.random.SeedSequence([int(base), *[int(k) for k in keys]]).generate_state(1)[0] & 0x7FFFFFFF)


def case_name(case: dict) -> str:
    """File stem of one case: ``al5_pe60_n15000_rep0_contact``."""
    return (f"al{case['a_over_lambda']:g}_pe{case['pe']:g}_n{int(case['n_particles'])}_rep{int(case['rep'])}_"
            f"{case.get('substrate', 'stick')}")


def _same_case(a: dict, b: dict) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def run_case_in(case: dict, folder, checkpoint_s: float = 300.0) -> dict:
    """Run one case with its result written to ``folder/<case_name>.json``, resumable.

    A finished case (its JSON holds the same case dict) is read back, not run
    again. A running case saves its state to ``<case_name>.ckpt.npz`` every
    ``checkpoint_s`` seconds of wall clock and continues from there when
    started again (same numbers as an uninterrupted run). A ``.lock`` file
    (holding the process id) keeps two processes off the same case, so several
    processes can share one folder.
    """
    import os
    import time

    from ptrack.errors import UserError, atomic_output

    folder = Path(folder)
    name = case_name(case)
    done_path = folder / f"{name}.json"
    if done_path.exists():
        doc = json.loads(done_path.read_text())
        if not _same_case(doc["case"], case):
            raise UserError(f"{done_path} holds another case (other parameters or seed)",
                            "give another --out folder, or remove that file")
        return doc["result"]
    ckpt = folder / f"{name}.ckpt.npz"
    lock = folder / f"{name}.lock"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    except FileExistsError:
        pid = int((lock.read_text().strip() or "0"))
        try:
            os.kill(pid, 0)
            alive = pid != os.getpid()
        except (ProcessLookupError, PermissionError, OverflowError):
            alive = False
        if alive:
            return {"skipped": name, "running_in_pid": pid}
        lock.unlink(missing_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    try:
        state = None
        if ckpt.exists():
            with np.load(ckpt, allow_pickle=False) as z:
                if not _same_case(json.loads(str(z["case_json"])), case):
                    raise UserError(f"{ckpt} is the checkpoint of another case", "remove it or give another --out")
                state = {k: z[k] for k in z.files if k not in ("case_json", "wall_s")}
                wall0 = float(z["wall_s"])
            print(f"[epd-order] {name}: resumed at t/t_end step {int(state['step'])}", file=sys.stderr, flush=True)
        else:
            wall0 = 0.0
        t_start = time.perf_counter()
        last = [t_start]

        def wall():
            return wall0 + time.perf_counter() - t_start

        def save(system):
            if time.perf_counter() - last[0] < checkpoint_s:
                return
            d = system.get_state()
            with atomic_output(ckpt, None) as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, case_json=json.dumps(case, sort_keys=True), wall_s=wall(), **d)
            last[0] = time.perf_counter()

        def progress(system, t_end):
            print(f"[epd-order] {name}: t/t_end {system.t / t_end:.3f}, step {system.step}, wall {wall():.0f} s",
                  file=sys.stderr, flush=True)

        result = run_case(case, checkpoint=save, state=state, progress=progress)
        result["wall_s"] = wall()
        result["seed"] = case["seed"]
        result["rep"] = case["rep"]
        with atomic_output(done_path, "w") as fh:
            json.dump({"case": case, "result": result, "command": " ".join(sys.argv)}, fh, indent=2)
        ckpt.unlink(missing_ok=True)
        return result
    finally:
        lock.unlink(missing_ok=True)


def collect(folder) -> list[dict]:
    """Results of every finished case under ``folder`` (``*.json`` written by :func:`run_case_in`)."""
    out = []
    for p in sorted(Path(folder).glob("al*_pe*_n*_rep*.json")):
        doc = json.loads(p.read_text())
        out.append(dict(doc["result"], substrate=doc["case"].get("substrate"), seed=doc["case"]["seed"],
                        rep=doc["case"]["rep"]))
    return out


def summarise(df, column: str = "solid_fraction"):
    """Per (a/lambda_D, Pe): mean, SD and SEM over replicates; per a/lambda_D: the trend in log10 Pe.

    The trend is the least-squares slope of ``column`` against ``log10 Pe``
    over every replicate (each deposit one point), with its standard error
    and the two-sided p-value of the t-test of slope = 0 (``n - 2`` degrees
    of freedom); ``None`` where fewer than 3 deposits or 2 Pe values exist.

    Returns
    -------
    table : DataFrame
    trend : dict
        ``{a_over_lambda: {"slope", "se", "p", "n", "n_pe"}}``.
    """
    from scipy import stats

    g = df.groupby(["a_over_lambda", "pe"], as_index=False).agg(
        n_rep=(column, "size"), order=(column, "mean"), order_sd=(column, "std"),
        interior=("solid_fraction_interior", "mean"), interior_sd=("solid_fraction_interior", "std"),
        q6=("q6_mean", "mean"), q6_sd=("q6_mean", "std"), steps=("steps", "mean"), n=("n_particles", "first"),
        wall_s=("wall_s", "mean") if "wall_s" in df else ("steps", "size"))
    g["order_sem"] = g.order_sd / np.sqrt(g.n_rep)
    g["interior_sem"] = g.interior_sd / np.sqrt(g.n_rep)
    g["q6_sem"] = g.q6_sd / np.sqrt(g.n_rep)
    trend = {}
    for al, gg in df.groupby("a_over_lambda"):
        x, y = np.log10(gg.pe.to_numpy(float)), gg[column].to_numpy(float)
        if len(x) < 3 or len(np.unique(x)) < 2:
            trend[float(al)] = None
            continue
        fit = stats.linregress(x, y)
        p = float(fit.pvalue) if np.isfinite(fit.pvalue) else None
        trend[float(al)] = {"slope": float(fit.slope), "se": float(fit.stderr), "p": p, "n": int(len(x)),
                            "n_pe": int(len(np.unique(x)))}
    return g, trend


def trend_text(trend: dict, what: str = "order") -> list[str]:
    """One line per a/lambda_D stating the trend and its significance."""
    lines = []
    for al, t in trend.items():
        if t is None:
            lines.append(f"a/lambda_D = {al:g}: too few deposits for a trend (need >= 3 over >= 2 Pe)")
            continue
        word = "falls" if t["slope"] < 0 else "rises"
        sig = "significant at 5 %" if t["p"] is not None and t["p"] < 0.05 else "not significant at 5 %"
        lines.append(f"a/lambda_D = {al:g}: {what} {word} with Pe, slope {t['slope']:+.3f} +- {t['se']:.3f} per "
                     f"decade of Pe (t-test p = {t['p']:.2g}, {t['n']} deposits at {t['n_pe']} Pe; {sig})")
    return lines


def plot(table, trend, path, title="", trend_interior=None):
    """Order (solid-like fraction) of the whole deposit and of its interior, and mean q6, against Pe:
    mean +- SEM over replicates, with the fitted trends."""
    import matplotlib.pyplot as plt

    from sim.studies._output import save_figure

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.3))
    panels = ((ax[0], "order", "order_sem", trend, "relative order N_solid / N (ten Wolde q6)"),
              (ax[1], "interior", "interior_sem", trend_interior or {},
               "order of the interior (z > 3a, below the top 10 %)"))
    for k, (al, gg) in enumerate(table.groupby("a_over_lambda")):
        gg = gg.sort_values("pe")
        col = f"C{k}"
        for a_, y, e, tr, _ in panels:
            a_.errorbar(gg.pe, gg[y], yerr=gg[e].fillna(0.0), fmt="o", color=col, capsize=3,
                        label=f"a/lambda_D = {al:g} (n = {'/'.join(str(int(v)) for v in gg.n_rep)})")
            t = tr.get(float(al))
            if t is not None:
                xs = np.linspace(np.log10(gg.pe.min()), np.log10(gg.pe.max()), 20)
                w = gg.n_rep.to_numpy(float)
                icpt = float(np.average(gg[y], weights=w) - t["slope"] * np.average(np.log10(gg.pe), weights=w))
                a_.plot(10**xs, icpt + t["slope"] * xs, "--", color=col, lw=1,
                        label=f"slope {t['slope']:+.2f} +- {t['se']:.2f}/decade, p = {t['p']:.2g}")
        ax[2].errorbar(gg.pe, gg.q6, yerr=gg.q6_sem.fillna(0.0), fmt="-o", color=col, capsize=3,
                       label=f"a/lambda_D = {al:g}")
    pes = np.unique(table.pe.to_numpy(float))
    for a_ in ax:
        a_.set_xscale("log")
        a_.set_xticks(pes, [f"{v:g}" for v in pes])
        a_.minorticks_off()
        a_.set_xlabel("Pe = v_H a / D_SE (4 pi form)")
        a_.legend(fontsize=7)
    for a_, _, _, _, label in panels:
        a_.set_ylabel(label)
        a_.set_ylim(-0.02, 1.02)
    ax[2].set_ylabel("mean q6")
    fig.suptitle(title or "EPD deposit order, mean +- SEM over replicates", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def run(args) -> int:
    import functools

    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    from ptrack.errors import UserError, check_writable
    from sim.studies._dask import run_cases
    from sim.studies._output import write_csv, write_json

    cases = cases_for(args)
    if args.collect and not args.out:
        raise UserError("--collect needs --out", "give the folder of an earlier run with --out")
    if args.out:
        out = Path(args.out)
        check_writable(out, "--out", directory=True)
        folder = out / "cases"
        if args.collect:
            res = collect(folder)
            if not res:
                raise UserError(f"no finished cases in {folder}", "run the study into that folder first")
        else:
            func = functools.partial(run_case_in, folder=folder, checkpoint_s=60.0 * args.checkpoint_minutes)
            res = run_cases(func, cases, scheduler=args.scheduler, use_dask=not args.no_dask and len(cases) > 1,
                            workers=args.workers, desc="epd-order")
            skipped = [r for r in res if "skipped" in r]
            res = [r for r in res if "skipped" not in r]
            for r in skipped:
                print(f"[epd-order] {r['skipped']} is running in process {r['running_in_pid']}: left to it",
                      file=sys.stderr)
    else:
        res = run_cases(run_case, cases, scheduler=args.scheduler, use_dask=not args.no_dask and len(cases) > 1,
                        workers=args.workers, desc="epd-order")
        for r, c in zip(res, cases):
            r["rep"], r["seed"] = c["rep"], c["seed"]
    df = pd.DataFrame(res)
    table, trend = summarise(df)
    trend_in = summarise(df, "solid_fraction_interior")[1]
    n_expected = len(cases)
    print("EPD deposit order vs Pe (= v_H a / D_SE, 4 pi form; the seed's eq. 3.37 has 6 pi, 1.5x higher) and "
          "a/lambda_D: ten Wolde solid-like fraction (relative order N_ordered/N), mean +- SD over replicates")
    print(f"{'a/lambda':>9} {'Pe':>7} {'reps':>4} {'order':>7} {'+-SD':>6} {'interior':>8} {'q6':>6} "
          f"{'steps':>9} {'wall s':>8}")
    for _, r in table.iterrows():
        print(f"{r.a_over_lambda:9.2f} {r.pe:7.1f} {int(r.n_rep):4d} {r.order:7.3f} {r.order_sd:6.3f} "
              f"{r.interior:8.3f} {r.q6:6.3f} {int(r.steps):9d} {r.wall_s:8.0f}")
    lines = trend_text(trend) + trend_text(trend_in, "interior order")
    for line in lines:
        print(line)
    if args.out and args.collect:
        print(f"{len(df)} finished deposits in {folder} (this command line's grid has {n_expected})")
    summary = {"cases": df.to_dict(orient="records"), "table": table.to_dict(orient="records"),
               "trend_solid_fraction_vs_log10_pe": {str(k): v for k, v in trend.items()},
               "trend_interior_vs_log10_pe": {str(k): v for k, v in trend_in.items()}, "trend_text": lines,
               "n_cases_finished": len(df), "n_cases_grid": n_expected}
    if args.out:
        plot(table, trend, out / "epd_order.png",
             title=f"EPD deposit order, N = {'/'.join(str(v) for v in sorted(set(df.n_particles)))}, "
                   f"mean +- SEM over replicates", trend_interior=trend_in)
        write_csv(df, out / "epd_order_cases.csv")
        write_csv(table, out / "epd_order.csv")
        print(f"wrote {out / 'epd_order.png'}, {out / 'epd_order.csv'} and {out / 'epd_order_cases.csv'}",
              file=sys.stderr)
    if args.json:
        from ptrack.table import to_jsonable

        write_json(to_jsonable(summary, finite=True), args.json)
    return 0
