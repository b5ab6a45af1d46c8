"""Calibration of ``ptrack compare``'s tests: false-"differs" rate and power, at the shipped movie sizes.

Null: pairs of independent simulations with the same parameters (the shipped
datasets' own walks, ``sim.render.datasets.brownian_walk``, in the same
geometry: start area larger than the view, rows kept only while a particle is
in the view, so tracks enter, leave and come back as in the movies). Each
pair goes through :func:`ptrack.compare.compare_tables`; the table gives, per
quantity, the fraction of pairs with an uncorrected p below the level (should
be about the level) and the fraction called "differs" after Holm, and the
family-wise rate (any quantity "differs"; Holm keeps it at or below the level).

Power: the same with D 10 % higher in the second table of each pair: the
fraction of pairs where D and the MSD come out "differs".

    python bench/bench_compare.py [--pairs 100] [--power-pairs 50] [--n-perm 1000]

Sizes: diffusion2d (54 particles started, 192 x 192 px of 103 nm, 130 frames
at 10 fps), diffusion3d (28 particles, 160 x 160 px, 100 frames, z in
+-2.5 um) and the EPD movie's size (16 particles, 128 x 128 px of 325 nm,
100 frames at 30 fps; free 3D diffusion of 0.8 um particles, no drift).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ptrack.compare import compare_tables  # noqa: E402
from ptrack.table import make_table  # noqa: E402
from sim.render.datasets import brownian_walk, stokes_einstein  # noqa: E402

SIZES = {
    # name: particles, frames, dt, px, view px, margin px, z half-range (None: 2D), radius
    "diffusion2d": (54, 130, 0.1, 6.5e-6 / 63, 192, 48, 0.4e-6, 250e-9, False),
    "diffusion3d": (28, 100, 0.1, 6.5e-6 / 63, 160, 40, 2.5e-6, 250e-9, True),
    "epd_size": (16, 100, 1 / 30, 6.5e-6 / 20, 128, 18, 6e-6, 400e-9, True),
}


def table(name: str, seed: int, d_factor: float = 1.0):
    n, F, dt, px, W, m, zh, R, three_d = SIZES[name]
    D = stokes_einstein(R) * d_factor
    ext = m * px
    pos = brownian_walk(n, F, dt, D, [-ext, -ext, -zh], [(W - 1) * px + ext, (W - 1) * px + ext, zh], seed=seed)
    fr = np.repeat(np.arange(F), n)
    pa = np.tile(np.arange(n), F)
    x, y, z = (pos[:, :, k].ravel() for k in range(3))
    inside = (x > -0.5 * px) & (x < (W - 0.5) * px) & (y > -0.5 * px) & (y < (W - 0.5) * px)
    return make_table(fr[inside], fr[inside] * dt, pa[inside], x[inside], y[inside],
                      z[inside] if three_d else None, meta={"frame_interval": dt, "pixel_size": px})


def run_pairs(name, n_pairs, d_factor, n_perm, n_boot, seed0):
    rows = []
    for i in range(n_pairs):
        a = table(name, seed0 + 2 * i)
        b = table(name, seed0 + 2 * i + 1, d_factor)
        dt = SIZES[name][2]
        comp = compare_tables([a, b], lags=[dt, 5 * dt, 20 * dt], n_boot=n_boot, n_perm=n_perm, seed=i,
                              motion_blur=0.0)["comparisons"][0]
        rows.append(comp)
    return rows


def summarise(rows, level=0.05):
    keys = list(dict.fromkeys(k for r in rows for k in r["quantities"]))
    out = {}
    for k in keys:
        q = [r["quantities"].get(k, {"p_value": None, "verdict": "insufficient"}) for r in rows]
        p = np.array([x["p_value"] if x["p_value"] is not None else np.nan for x in q], float)
        v = [x["verdict"] for x in q]
        out[k] = (np.nanmean(p < level) if np.isfinite(p).any() else np.nan, np.mean([x == "differs" for x in v]),
                  np.mean([x == "insufficient" for x in v]))
    fw = np.mean([r["n_differs"] > 0 for r in rows])
    return out, fw


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=100, help="null pairs for diffusion2d (default 100)")
    ap.add_argument("--null-pairs-other", type=int, default=40, help="null pairs for the other sizes (default 40)")
    ap.add_argument("--power-pairs", type=int, default=50, help="pairs with D +10 %% per size (default 50)")
    ap.add_argument("--n-perm", type=int, default=1000)
    ap.add_argument("--n-boot", type=int, default=200)
    a = ap.parse_args(argv)
    print("# ptrack compare: calibration of the tests (level 0.05; Holm over each comparison)")
    print("# machine: 2 cores shared with other jobs; times are indicative")
    for name in SIZES:
        t0 = time.perf_counter()
        n_null = a.pairs if name == "diffusion2d" else a.null_pairs_other
        null = run_pairs(name, n_null, 1.0, a.n_perm, a.n_boot, 1000)
        t_null = time.perf_counter() - t0
        s, fw = summarise(null)
        t1 = time.perf_counter()
        alt = run_pairs(name, a.power_pairs, 1.1, a.n_perm, a.n_boot, 5000)
        t_alt = time.perf_counter() - t1
        sp, _ = summarise(alt)
        n_tr = np.mean([r["quantities"]["D_x"]["a"]["n_particles"] for r in null if r["quantities"]["D_x"]["a"]])
        print(f"\n## {name}: {n_null} null pairs ({t_null / n_null:.2f} s per comparison), {a.power_pairs} pairs "
              f"with D x1.1; ~{n_tr:.0f} tracks per table")
        print(f"{'quantity':<24s} {'null p<0.05':>12s} {'null differs':>13s} {'insufficient':>13s} "
              f"{'power p<0.05':>13s} {'power differs':>14s}")
        for k in s:
            print(f"{k:<24s} {s[k][0]:>12.3f} {s[k][1]:>13.3f} {s[k][2]:>13.2f} {sp[k][0]:>13.3f} {sp[k][1]:>14.3f}")
        rates = [v[0] for k, v in s.items() if np.isfinite(v[0]) and v[2] == 0]
        print(f"mean per-test false p<0.05 rate over the {len(rates)} decided quantities: {np.mean(rates):.3f}; "
              f"family-wise false 'differs' (any quantity, after Holm): {fw:.3f}")
        pw = np.mean([("differs" in (r["verdicts"].get("D_x"), r["verdicts"].get("D_y"))) for r in alt])
        print(f"power against D +10 %: D_x or D_y 'differs' in {pw:.2f} of the pairs; "
              f"D_x alone {sp['D_x'][1]:.2f} (uncorrected p<0.05: {sp['D_x'][0]:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
