"""The seed's deposition examples 1-3 (section 3.3.3): charged spheres in air
driven onto a substrate, analysed by coordination number.

``--example 1``: 1000 uniform spheres, open sides, t_f = 0.1 s;
``--example 2``: periodic sides, t_f = 0.15 s; ``--example 3``: periodic
sides and variable radius (alpha_Rad = 0.2), t_f = 0.5 s.  All with the
seed's parameter list (R = 0.05 m, silica in air, E = [0, 0, 100] V/m,
q/m = -1 C/kg, K_p = 1e9, c_cd = 1e8, ...; see ``scenes/deposition_example*.toml``)
and dt = 1e-6 s.  The run uses the DEM engine (:func:`sim.dem.run_dem`); the
output directory receives the trajectories, snapshots coloured by
coordination number (seed Figs. 3.17-3.22), the mean coordination number
against time (Fig. 3.20b / 3.22b), the deposited count against time, the
final height profile, an extended-XYZ file for OVITO, and a table.

Coordination number: neighbours closer than ``cn_factor (R_i + R_j)``
(default 1.1).  The order metrics (Steinhardt q6, ten Wolde solid-like
fraction) use ``1.2 (R_i + R_j)``.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from ptrack.errors import UserError, atomic_output

# the source tree keeps scenes/ at the top; an installed wheel ships them as sim/scenes/ (setup.py)
SCENES = next((p for p in (Path(__file__).resolve().parents[2] / "scenes", Path(__file__).resolve().parents[1] / "scenes")
               if p.is_dir()), Path(__file__).resolve().parents[2] / "scenes")


def add_arguments(p):
    from sim.studies._dask import add_study_arguments

    add_study_arguments(p)
    p.add_argument("--example", type=int, choices=(1, 2, 3), default=1, help="seed example number (default 1)")
    p.add_argument("--scene", default=None, help="run this scene TOML instead of an example")
    p.add_argument("--resume", action="store_true", help="continue the run from its checkpoint")
    p.add_argument("--cn-factor", type=float, default=1.1,
                   help="coordination neighbours: centre distance < factor (R_i + R_j) (default 1.1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def quick_scene(scene, count=200, t_max=0.1):
    """A smaller version of a deposition scene: fewer particles in a box with the
    same height and number density, at most ``t_max`` simulated seconds."""
    p = scene.particles
    f = (count / p.count) ** 0.5
    L = scene.domain.size
    size = (L[0] * f, L[1] * f, L[2])
    final = min(scene.time.final, t_max)
    out = min(scene.time.output_interval, final / 10)
    return dataclasses.replace(scene, particles=dataclasses.replace(p, count=count),
                               domain=dataclasses.replace(scene.domain, size=size),
                               time=dataclasses.replace(scene.time, final=final, output_interval=out))


def analyse(df, scene, cn_factor=1.1):
    """Per-frame mean CN and deposited count; final-frame structure metrics."""
    from sim.analysis import (coordination_numbers, deposit_height, deposited_mask, height_profile,
                              packing_fraction, solid_like, steinhardt_q6)

    L = np.asarray(scene.domain.size, dtype=float)
    per = [scene.boundaries.x == "periodic", scene.boundaries.y == "periodic", False]
    box = dict(length=L, periodic=per) if any(per) else {}
    frames = np.sort(df["frame"].unique())
    times, mean_cn, n_dep = [], [], []
    cn_by_frame = {}
    for fr in frames:
        g = df[df["frame"] == fr].sort_values("particle")
        pos = g[["x", "y", "z"]].to_numpy()
        rad = g["radius"].to_numpy()
        cn = coordination_numbers(pos, rad, cn_factor=cn_factor, **box)
        cn_by_frame[int(fr)] = (float(g["t"].iloc[0]), pos, rad, cn)
        times.append(float(g["t"].iloc[0]))
        mean_cn.append(float(cn.mean()))
        n_dep.append(int(deposited_mask(pos, rad, **box).sum()))
    t_last, pos, rad, cn = cn_by_frame[int(frames[-1])]
    q6 = steinhardt_q6(pos, rad, cn_factor=1.2, **box)
    solid, _ = solid_like(pos, rad, cn_factor=1.2, **box)
    h = deposit_height(pos, rad)
    rmean = float(rad.mean())
    if any(per):
        area = L[0] * L[1]
    else:
        from scipy.spatial import ConvexHull

        dep = deposited_mask(pos, rad)
        pts = pos[dep][:, :2] if dep.sum() >= 3 else pos[:, :2]
        area = float(ConvexHull(pts).volume) if len(pts) >= 3 else float(np.pi * rmean**2)
    z0, z1 = 2 * rmean, h - 2 * rmean
    phi = packing_fraction(pos, rad, area, z0, z1) if z1 > z0 + rmean else float("nan")
    zc, prof = height_profile(pos, rad, area, bins=40)
    inner = cn[(pos[:, 2] > z0) & (pos[:, 2] < z1)] if z1 > z0 else cn
    return {
        "times": times, "mean_cn": mean_cn, "deposited": n_dep, "frames": cn_by_frame,
        "mean_cn_final": mean_cn[-1], "mean_cn_interior": float(inner.mean()) if len(inner) else float("nan"),
        "q6_mean": float(np.nanmean(q6)) if np.isfinite(q6).any() else float("nan"),
        "solid_fraction": float(solid.mean()), "deposit_height": h, "packing_fraction": phi,
        "profile": (zc, prof), "area": area, "deposited_final": n_dep[-1],
    }


def run(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ptrack.table import read_table
    from sim.dem import run_dem
    from sim.scene import load_scene
    from sim.views import snapshot_png, snapshots_png, write_extxyz

    path = Path(args.scene) if args.scene else SCENES / f"deposition_example{args.example}.toml"
    scene = load_scene(path)
    if scene.interactions is None or not scene.interactions.any_pair_force:
        raise UserError(f"scene {path} has no contact or near-field section", "add [contact] (see scenes/deposition_example1.toml)")
    if args.seed:
        scene = dataclasses.replace(scene, seed=scene.seed + int(args.seed))
    if args.quick:
        scene = quick_scene(scene)
    if args.cn_factor <= 1.0:
        raise UserError(f"--cn-factor {args.cn_factor} must exceed 1", "give e.g. 1.1 (10 % gap)")
    out = Path(args.out or f"deposition_example{args.example}")
    out.mkdir(parents=True, exist_ok=True)
    cpu0 = time.process_time()
    res = run_dem(scene, out / "run", resume=args.resume, progress=not args.quiet)
    cpu = time.process_time() - cpu0
    df = read_table(res.trajectories)
    an = analyse(df, scene, args.cn_factor)
    L = scene.domain.size
    per = (scene.boundaries.x == "periodic", scene.boundaries.y == "periodic", False)
    # figures
    keys = sorted(an["frames"])
    pick = [keys[int(round(k))] for k in np.linspace(0, len(keys) - 1, 4)]
    box = L if any(per) else None
    if any(per):  # draw periodic frames wrapped into the box
        for k in list(an["frames"]):
            t_k, p_k, r_k, c_k = an["frames"][k]
            p_k = p_k.copy()
            for a in range(2):
                if per[a]:
                    p_k[:, a] = np.mod(p_k[:, a], L[a])
            an["frames"][k] = (t_k, p_k, r_k, c_k)
    vmax = max(12, max(int(an["frames"][k][3].max()) for k in pick))
    snapshots_png(out / "snapshots.png", [an["frames"][k] for k in pick], box=box, vmax=vmax)
    t_f, pos, rad, cn = an["frames"][keys[-1]]
    snapshot_png(out / "final_deposit.png", pos, rad, cn, box=box,
                 title=f"t = {t_f:.3g} s, mean CN = {cn.mean():.2f}", vmax=vmax)
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].plot(an["times"], an["mean_cn"], "-o", ms=3)
    ax[0].set_xlabel("t (s)")
    ax[0].set_ylabel("mean coordination number")
    ax[1].plot(an["times"], an["deposited"], "-o", ms=3)
    ax[1].set_xlabel("t (s)")
    ax[1].set_ylabel("deposited particles")
    zc, prof = an["profile"]
    ax[2].plot(prof, zc)
    ax[2].set_xlabel("solid volume fraction")
    ax[2].set_ylabel("z (m)")
    fig.suptitle(f"{path.name}: {res['n_particles']} particles, {res['steps']} steps")
    fig.tight_layout()
    with atomic_output(out / "coordination_vs_time.png", None) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    write_extxyz(out / "deposit.extxyz",
                 ({"t": an["frames"][k][0], "pos": an["frames"][k][1], "radius": an["frames"][k][2],
                   "cn": an["frames"][k][3]} for k in keys), box=L, periodic=per, extra_names=("cn",))
    summary = {"n_particles": int(res["n_particles"]), "steps": int(res["steps"]), "wall_time_s": float(res["wall_time_s"]),
               "cpu_time_s": cpu, "mean_cn_final": an["mean_cn_final"], "max_overlap_ratio": float(res["max_overlap_ratio"]),
               "mean_cn_interior": an["mean_cn_interior"], "q6_mean": an["q6_mean"],
               "solid_fraction": an["solid_fraction"], "packing_fraction": an["packing_fraction"],
               "deposit_height": an["deposit_height"], "deposited_final": an["deposited_final"],
               "dt_min": float(res["dt_min"]), "dt_max": float(res["dt_max"]), "scene": str(path),
               "quick": bool(args.quick), "cn_factor": args.cn_factor}
    with atomic_output(out / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    import pandas as pd

    with atomic_output(out / "cn_vs_time.csv", None) as tmp:
        pd.DataFrame({"t": an["times"], "mean_cn": an["mean_cn"], "deposited": an["deposited"]}).to_csv(tmp, index=False)
    print(f"deposition {path.name}{' (quick)' if args.quick else ''}")
    print(f"{'particles':>10} {'steps':>8} {'wall (s)':>9} {'cpu (s)':>8} {'mean CN':>8} {'CN inner':>9} "
          f"{'q6':>6} {'solid':>6} {'phi':>6} {'height (m)':>10} {'max overlap/R':>13}")
    print(f"{summary['n_particles']:10d} {summary['steps']:8d} {summary['wall_time_s']:9.1f} {cpu:8.1f} "
          f"{summary['mean_cn_final']:8.2f} {summary['mean_cn_interior']:9.2f} {summary['q6_mean']:6.3f} "
          f"{summary['solid_fraction']:6.3f} {summary['packing_fraction']:6.3f} {summary['deposit_height']:10.3f} "
          f"{summary['max_overlap_ratio']:13.4f}")
    print(f"wrote {out}/snapshots.png, final_deposit.png, coordination_vs_time.png, deposit.extxyz, summary.json",
          file=sys.stderr)
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump({k: summary[k] for k in ("n_particles", "steps", "wall_time_s", "mean_cn_final",
                                               "max_overlap_ratio")} | summary, fh, indent=2)
    return 0
