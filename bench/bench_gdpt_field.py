"""Field-dependent GDPT calibration: z bias and RMSE against field position, single vs field-dependent calibration.

Two image models, each a calibration stack of 9 beads on a 3 x 3 grid (stepped together) and a movie of isolated
particles at random places and heights:

A. our renderer (sim.render) with a curved and tilted focal surface: Optics(field_curvature=0.4 um,
   field_tilt=(0.2 um, 0), field_radius=10 um), astigmatism 0.12 um, 256^2 px, stack +-3 um / 0.2 um;
A0. the same with a flat field (reference: the precision the correction should reach; not with --quick);
B. an astigmatic Gaussian written in tests/test_gdpt_field.py (independent of the renderer) whose astigmatism
   grows along x (c = 0.15 -> 0.6 um across the bead columns), 200^2 px, stack +-1.5 um / 0.1 um.

Calibrations compared on the same movie frames:
  one bead    the centre bead alone (a crop of the stack around it: what a one-bead stack gives);
  averaged    all 9 beads registered and averaged (ptrack.calibration.build_calibration), no correction;
  field       averaged templates + the smooth field map (ptrack.gdpt.field, basis "auto" = quadratic);
  nearest     averaged templates + the nearest bead's reading curve (basis "nearest").
Errors by zone (A: distance from the frame centre; B: x) and overall: bias (mean), RMSE, largest error and the
scale error (slope of the error against z, %); times per stage.

command: .venv/bin/python bench/bench_gdpt_field.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_gdpt_field import GRID, _gauss_frame, _grid, _scatter  # noqa: E402  (the test's models)

from ptrack.calibration import build_calibration, locate_frame_3d  # noqa: E402
from ptrack.gdpt.field import build_field_calibration, correct_z  # noqa: E402
from sim.render.camera import Camera  # noqa: E402
from sim.render.movie import render_frames  # noqa: E402
from sim.render.optics import Optics, sample_pixel_size  # noqa: E402
from ptrack.motion import detection_scores  # noqa: E402
from ptrack.table import make_table  # noqa: E402


def case_renderer(n_frames, flat: bool = False):
    o = Optics(astigmatism=0.12e-6, field_curvature=0.0 if flat else 0.4e-6, field_tilt=(0.0 if flat else 0.2e-6, 0.0),
               field_radius=10e-6)
    cam = Camera(photons=20000)
    px = sample_pixel_size(o, cam.pixel_pitch)
    H = W = 256
    bx, by = _grid(GRID)
    zk = np.round(np.arange(-3e-6, 3e-6 + 1e-9, 0.2e-6), 12)
    K, B = len(zk), len(bx)
    fr = np.repeat(np.arange(K), B)
    tb = make_table(fr, fr * 1.0, np.tile(np.arange(B), K), np.tile(bx, K) * px, np.tile(by, K) * px,
                    np.repeat(zk, B), meta={"frame_interval": 1.0})
    t0 = time.perf_counter()
    stack = np.stack(list(render_frames(tb, (H, W), o, cam, seed=1)))
    truth = _scatter(n_frames, 6, 30.0, 226.0, 2.2e-6, 60.0, seed=5)
    mt = make_table(truth[:, 0].astype(int), truth[:, 0], np.arange(len(truth)), truth[:, 1] * px, truth[:, 2] * px,
                    truth[:, 3], meta={"frame_interval": 1.0})
    frames = list(render_frames(mt, (H, W), o, cam, seed=2))
    t_render = time.perf_counter() - t0
    name = "A0: renderer, flat field (the same without field curvature: the precision to reach)" if flat else \
        "A: renderer, curved + tilted focal surface"
    return name, stack, zk, px, frames, truth, (128.0, 128.0), 32, t_render, "r"


def case_gaussian(n_frames):
    rng = np.random.default_rng(11)
    shape = (200, 200)
    bx, by = _grid(np.array([30.0, 100.0, 170.0]))
    zk = np.round(np.arange(-1.5e-6, 1.5e-6 + 1e-9, 0.1e-6), 12)
    t0 = time.perf_counter()
    stack = np.stack([_gauss_frame(bx, by, np.full(len(bx), zi), shape, rng) for zi in zk])
    truth = _scatter(n_frames, 5, 25.0, 175.0, 1.1e-6, 40.0, seed=7)
    frames = [_gauss_frame(truth[truth[:, 0] == f, 1], truth[truth[:, 0] == f, 2], truth[truth[:, 0] == f, 3],
                           shape, rng) for f in range(n_frames)]
    t_render = time.perf_counter() - t0
    return "B: independent astigmatic Gaussian, astigmatism growing along x", stack, zk, 1e-7, frames, truth, \
        (100.0, 100.0), 22, t_render, "x"


def _match(df, truth, f, tol=3.0):
    """(x_true, y_true, z_true, z_found) of each localisation of frame ``f`` paired with the nearest true particle
    closer than ``tol`` px (ptrack.motion.detection_scores: the one truth-matching rule)."""
    t = truth[truth[:, 0] == f]
    fi, ti = detection_scores(df[["x_px", "y_px"]].to_numpy(float), t[:, 1:3], max_px=tol)["pairs"]
    z = df["z"].to_numpy(float)
    return [(t[j, 1], t[j, 2], t[j, 3], z[i]) for i, j in zip(fi, ti)]


def run_case(case, n_frames):
    name, stack, zk, px, frames, truth, centre, half_crop, t_render, bin_by = case(n_frames)
    K, H, W = stack.shape
    print(f"\n## {name}")
    print(f"stack {K} pages of {H}x{W} px, 9 beads; movie {len(frames)} frames, {len(truth)} particles, "
          f"|z| <= {np.abs(truth[:, 3]).max() * 1e6:.1f} um (rendered in {t_render:.1f} s)")
    times = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        cy, cx = int(centre[1]), int(centre[0])
        hc = int(1.5 * half_crop)
        one = build_calibration(stack[:, cy - hc:cy + hc + 1,
                                      cx - hc:cx + hc + 1], zk, px)
        times["one bead: build"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        avg = build_calibration(stack, zk, px)
        times["averaged: build"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        fc = build_field_calibration(stack, zk, px, calib=avg)
        times["field: read beads + fit"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        fn = build_field_calibration(stack, zk, px, calib=avg, basis="nearest")
        times["nearest: read beads + fit"] = time.perf_counter() - t0
    rows = {m: [] for m in ("one bead", "averaged", "field", "nearest")}
    t_loc = {"one bead": 0.0, "averaged": 0.0}
    t_cor = {"field": 0.0, "nearest": 0.0}
    for f, img in enumerate(frames):
        t0 = time.perf_counter()
        d1 = locate_frame_3d(img, one)
        t_loc["one bead"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        da = locate_frame_3d(img, avg)
        t_loc["averaged"] += time.perf_counter() - t0
        rows["one bead"] += _match(d1, truth, f)
        rows["averaged"] += _match(da, truth, f)
        for key, cal in (("field", fc), ("nearest", fn)):
            t0 = time.perf_counter()
            dc = correct_z(da, cal)
            t_cor[key] += time.perf_counter() - t0
            rows[key] += _match(dc, truth, f)
    nf = len(frames)
    print(f"field map: basis {fc.basis}, fit rms {fc.info['fit_rms'] * 1e9:.1f} nm, leave-one-bead-out rms "
          f"{fc.info['loo_rms'] * 1e9:.1f} nm; nearest-bead leave-one-out rms {fn.info['loo_rms'] * 1e9:.1f} nm")
    print("bead bias on the averaged templates (nm, median over pages): "
          + " ".join(f"({x:.0f},{y:.0f}):{b * 1e9:+.0f}" for (x, y), b in zip(fc.bead_xy, fc.info["bead_bias"])))
    # zones: distance from the frame centre (focal surface curved about it) or x (astigmatism grows along x)
    def coord(xy):
        return np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) if bin_by == "r" else xy[:, 0]

    r_all = coord(truth[:, 1:3])
    edges = np.quantile(r_all, [0, 1 / 3, 2 / 3, 1.0])
    edges[-1] += 1e-9
    label = "r from centre px" if bin_by == "r" else "x px"
    print(f"\n{'calibration':<10} {label:>16} {'n':>4} {'recall':>6} {'bias nm':>8} {'RMSE nm':>8} "
          f"{'max |dz| nm':>11} {'scale %':>8} {'% depth':>8}")
    depth = float(zk[-1] - zk[0])

    def line(key, what, e, zt, n, n_true):
        sc = 100 * np.polyfit(zt, e, 1)[0] if n > 2 else float("nan")
        print(f"{key:<10} {what:>16} {n:4d} {n / max(n_true, 1):6.2f} {e.mean() * 1e9:+8.1f} "
              f"{np.sqrt(np.mean(e ** 2)) * 1e9:8.1f} {np.abs(e).max() * 1e9:11.0f} {sc:+8.2f} "
              f"{100 * np.sqrt(np.mean(e ** 2)) / depth:8.2f}")

    for key, m in rows.items():
        a = np.array(m)
        r = coord(a[:, :2])
        e = a[:, 3] - a[:, 2]
        for i in range(3):
            sel = (r >= edges[i]) & (r < edges[i + 1])
            n_true = int(((r_all >= edges[i]) & (r_all < edges[i + 1])).sum())
            line(key, f"{edges[i]:7.0f} - {edges[i + 1]:6.0f}", e[sel], a[sel, 2], int(sel.sum()), n_true)
        line(key, "all", e, a[:, 2], len(e), len(truth))
    print("\ntimes (s): " + ", ".join(f"{k} {v:.2f}" for k, v in times.items()))
    print("per frame (ms): " + ", ".join(f"locate ({k}) {1e3 * v / nf:.0f}" for k, v in t_loc.items())
          + ", " + ", ".join(f"correct ({k}) {1e3 * v / nf:.2f}" for k, v in t_cor.items()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer movie frames")
    a = ap.parse_args(argv)
    print("# Field-dependent GDPT calibration (ptrack.gdpt.field)")
    print("command: .venv/bin/python bench/bench_gdpt_field.py" + (" --quick" if a.quick else ""))
    n = 6 if a.quick else 20
    run_case(case_renderer, n)
    if not a.quick:
        run_case(lambda k: case_renderer(k, flat=True), n)
    run_case(case_gaussian, n)


if __name__ == "__main__":
    main()
