"""Accuracy and speed of the near-wall mobility functions (ptrack.wall) and of
Henry's function (sim.electrokinetics).

Run:  .venv/bin/python bench/bench_wall.py
Prints: (1) parallel D/D0 of each method against the exact bispherical
solution (O'Neill 1964 / Dean & O'Neill 1963, as tabulated by Goldman, Cox &
Brenner 1967) for a torque-free sphere; (2) perpendicular: Brenner's series
against the exact table and Bevan-Prieve against Brenner; (3) the cost of
each numba kernel per call inside an njit loop (what the simulator pays);
(4) Henry's function against a 60-digit evaluation and Swan-Furst's error.
"""
from __future__ import annotations

import math
import time
from decimal import Decimal, getcontext

import numpy as np
from numba import njit

from ptrack import wall
from sim import electrokinetics as ek

# h/a, F_t, F_r (= T_t), T_r, lambda_perp (nan: not stored)
EXACT = np.array([
    [1.001, 4.6400382, 0.66548246, 4.1839783, 1002.3508],
    [1.01, 3.422533, 0.36868987, 2.9877302, 101.89617],
    [1.02, 3.0626292, 0.28508539, 2.6456529, 51.760734],
    [1.03, 2.855257, 0.23868768, 2.453524, 35.015909],
    [1.05, 2.5989633, 0.18390045, 2.2232813, 21.58582],
    [1.1, 2.264303, 0.11835113, 1.9398016, 11.459157],
    [1.15, 2.0785583, 0.085995332, 1.7943146, 8.0553547],
    [1.2, 1.9527071, 0.066183544, 1.7021856, 6.3408867],
    [1.3, 1.7855781, 0.04306008, 1.5900077, 4.6107198],
    [1.4, 1.675528, 0.030151472, 1.5239268, 3.7356172],
    [1.45, 1.6327617, 0.025692745, 1.5002174, 3.4416342],
    [1.5, 1.5957066, 0.022098616, 1.4806607, 3.2053903],
    [1.56, 1.557162, 0.018635219, 1.4613532, 2.9765446],
    [1.59, 1.5398829, 0.017176213, 1.4530579, 2.8792288],
    [1.7, 1.4854156, 0.012967281, 1.4284548, 2.5923964],
    [1.8, 1.4452127, 0.010249938, 1.4118883, 2.3987688],
    [2.0, 1.3827524, 0.006699615, 1.3890447, 2.1255356],
    [4.0, 1.1619561, 0.00044241, 1.3398954, 1.380204],
])


def table_parallel():
    x = EXACT[:, 0]
    exact = EXACT[:, 3] / (EXACT[:, 1] * EXACT[:, 3] - EXACT[:, 2] ** 2)
    methods = ["first_order", "faxen", "lubrication", "auto"]
    print("Parallel D/D0: relative error (%) against the exact torque-free mobility")
    print(f"{'h/a':>6s} {'exact':>8s} " + " ".join(f"{m:>12s}" for m in methods))
    worst = {m: 0.0 for m in methods}
    for i, xi in enumerate(x):
        row = []
        for m in methods:
            err = wall.parallel_ratio(xi, 1.0, m) / exact[i] - 1
            row.append(f"{100 * err:+12.3f}")
            worst[m] = max(worst[m], abs(err))
        print(f"{xi:6.3f} {exact[i]:8.5f} " + " ".join(row))
    print(f"{'max':>15s} " + " ".join(f"{100 * worst[m]:12.3f}" for m in methods))
    fax = np.abs(wall.parallel_ratio(x, 1.0, "faxen") / exact - 1)
    print(f"Faxen within 1 % for h/a >= {x[fax < 0.01].min():.2f} (tabulated heights)\n")


def table_perpendicular():
    x = EXACT[:, 0]
    lam = 1.0 / wall.perpendicular_ratio(x, 1.0)
    rel = np.max(np.abs(lam / EXACT[:, 4] - 1))
    print(f"Perpendicular: Brenner series vs exact table, max relative difference {rel:.2e} "
          f"({len(x)} heights, h/a 1.001-4; the largest is at h/a = 1.001, where the tabulated value is "
          f"truncated: the series summed to convergence in plain float gives the same as ptrack)")
    xs = 1 + np.geomspace(1e-8, 1e4, 200001)
    bp = wall.perpendicular_ratio(xs, 1.0, "bevan_prieve") / wall.perpendicular_ratio(xs, 1.0) - 1
    i = int(np.argmax(np.abs(bp)))
    rt = wall.perpendicular_ratio(xs, 1.0, "brenner_table") / wall.perpendicular_ratio(xs, 1.0) - 1
    dt = (wall.perpendicular_ratio_derivative(xs, 1.0, "brenner_table")
          / wall.perpendicular_ratio_derivative(xs, 1.0) - 1)
    print(f"Brenner table (numba default) vs series: max relative error {np.max(np.abs(rt)):.1e} (ratio), "
          f"{np.max(np.abs(dt)):.1e} (d/dh)")
    print(f"Bevan-Prieve vs Brenner: max |relative error| {100 * abs(bp[i]):.3f} % at h/a = {xs[i]:.4f} "
          f"(200001 heights, gap/a 1e-8 to 1e4)\n")


@njit(cache=True)
def _loop(kind, xs):
    s = 0.0
    for i in range(xs.size):
        x = xs[i]
        if kind == 0:
            s += wall.parallel_ratio_nb(x)
        elif kind == 1:
            r, d = wall.parallel_ratio_and_derivative_nb(x)
            s += r + d
        elif kind == 2:
            s += wall.perpendicular_ratio_series_nb(x)
        elif kind == 3:
            r, d = wall.perpendicular_ratio_series_and_derivative_nb(x)
            s += r + d
        elif kind == 6:
            r, d = wall.perpendicular_ratio_and_derivative_nb(x)
            s += r + d
        elif kind == 4:
            s += wall.perpendicular_ratio_bp_nb(x) + wall.perpendicular_ratio_bp_derivative_nb(x)
        else:
            s += wall.faxen_ratio_nb(x)
    return s


def table_speed():
    rng = np.random.default_rng(1)
    n = 200_000
    ranges = {"gap/a 1e-4..0.1": (1e-4, 0.1), "gap/a 0.1..10": (0.1, 10.0)}
    names = ["parallel (auto)", "parallel + d/dh", "perp Brenner series", "perp series + d/dh",
             "perp Bevan-Prieve + d/dh", "Faxen", "perp Brenner table + d/dh"]
    print(f"Kernel cost per call in an njit loop ({n} log-uniform heights, warm cache, best of 3)")
    print(f"{'kernel':<26s} " + " ".join(f"{k:>18s}" for k in ranges))
    for kind, name in enumerate(names):
        row = []
        for lo, hi in ranges.values():
            xs = 1 + np.exp(rng.uniform(math.log(lo), math.log(hi), n))
            m = n if kind not in (2, 3) else n // 20       # the direct series is slow near contact
            _loop(kind, xs[:10])
            best = math.inf
            for _ in range(3):
                t = time.perf_counter()
                _loop(kind, xs[:m])
                best = min(best, time.perf_counter() - t)
            row.append(f"{best / m * 1e9:15.0f} ns")
        print(f"{name:<26s} " + " ".join(row))
    print()


def henry_reference(x: float) -> float:
    getcontext().prec = 60
    X = Decimal(repr(x))
    t = Decimal(0)
    for k in range(6000, 0, -1):
        t = Decimal(k) / (1 + Decimal(k) / (X + t))
    s = 1 / (X + t)
    return float((96 + 6 * X ** 2 - 10 * X ** 3 - X ** 4 + X ** 5 + X ** 4 * (12 - X ** 2) * s) / 96)


def table_henry():
    xs = [0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 50.0, 200.0, 1000.0]
    print("Henry's function f(ka) (convention 1 .. 3/2): module vs 60-digit reference, Swan-Furst error")
    print(f"{'ka':>8s} {'f exact':>18s} {'rel. diff':>10s} {'Swan-Furst':>11s}")
    for x in xs:
        f = ek.henry_function(x)
        ref = henry_reference(x)
        sf = ek.henry_function_swan_furst(x) / f - 1
        print(f"{x:8.1f} {f:18.15f} {f / ref - 1:10.1e} {100 * sf:+10.3f}%")
    grid = np.geomspace(1e-4, 1e6, 100001)
    sf = ek.henry_function_swan_furst(grid) / ek.henry_function(grid) - 1
    i = int(np.argmax(np.abs(sf)))
    print(f"Swan-Furst max error {100 * abs(sf[i]):.3f} % at ka = {grid[i]:.3f} (seed claims 0.1 %)")
    t = time.perf_counter()
    ek.henry_function(grid)
    print(f"henry_function: {(time.perf_counter() - t) / grid.size * 1e9:.0f} ns per value ({grid.size} values)\n")


if __name__ == "__main__":
    table_parallel()
    table_perpendicular()
    table_speed()
    table_henry()
