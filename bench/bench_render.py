"""Benchmark of the synthetic microscope (sim.render): speed, memory and accuracy.

Prints two tables:

* speed: case, frames, wall time, frames/s, steady frames/s (after the first
  frame, i.e. without the PSF stack and numba cache loading), CPU seconds and
  steady frames per CPU-second (load-independent: the renderer runs on one
  core, so on an idle machine wall = CPU), peak RSS (each
  case runs in a fresh subprocess so its peak memory is its own; wall time
  excludes interpreter start-up and imports);
* accuracy: the PSF against the analytic Airy disk, flux conservation, and
  the sub-pixel placement checked by an independent Airy fit.

Usage: python bench/bench_render.py [--quick] [--no-big]
  --quick   fewer frames (smoke run)
  --no-big  skip the 2560 x 2160 x 130-frame movie (1.4 GB written to a temp dir)
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PX = 6.5e-6 / 63.0


def _table(n_particles, n_frames, H, W, zspan=0.0, seed=0, dt=0.1, D=0.86e-12):
    from ptrack.table import make_table

    rng = np.random.default_rng(seed)
    x0 = rng.uniform(10, W - 10, n_particles) * PX
    y0 = rng.uniform(10, H - 10, n_particles) * PX
    z0 = rng.uniform(-zspan, zspan, n_particles) if zspan else np.zeros(n_particles)
    steps = rng.standard_normal((n_frames, n_particles, 3)) * np.sqrt(2 * D * dt)
    steps[0] = 0
    if not zspan:
        steps[:, :, 2] = 0.0  # 2D: particles stay in the focal plane
    pos = np.cumsum(steps, axis=0) + np.stack([x0, y0, z0], axis=1)[None]
    if zspan:  # reflect z into [-zspan, zspan]
        L = 2 * zspan
        u = np.mod(pos[:, :, 2] + zspan, 2 * L)
        pos[:, :, 2] = np.where(u > L, 2 * L - u, u) - zspan
    f = np.repeat(np.arange(n_frames), n_particles)
    p = np.tile(np.arange(n_particles), n_frames)
    return make_table(f, f * dt, p, pos[:, :, 0].ravel(), pos[:, :, 1].ravel(), pos[:, :, 2].ravel(),
                      meta={"frame_interval": dt})


_CPU = {}


def _consume(gen):
    """Iterate frames; return (count, seconds to the first frame, seconds for the rest).

    Also records the CPU time of the frames after the first (``_CPU['rest']``):
    the renderer is single-threaded, so CPU seconds are what an idle machine's
    wall clock would show, whatever the load of a shared machine.
    """
    t0 = time.perf_counter()
    n = 0
    t1 = t0
    c1 = time.process_time()
    for _ in gen:
        n += 1
        if n == 1:
            t1 = time.perf_counter()
            c1 = time.process_time()
    _CPU["rest"] = time.process_time() - c1
    return n, t1 - t0, time.perf_counter() - t1


def case(name: str, quick: bool) -> dict:
    from sim.render import Camera, Optics, render_calibration, render_frames, render_movie

    F = 30 if quick else 130
    t0 = time.perf_counter()
    c0 = time.process_time()
    if name == "512x512, 50 particles, in focus":
        tab = _table(50, F, 512, 512)
        n, first, rest = _consume(render_frames(tab, (512, 512), seed=1))
    elif name == "512x512, 50 particles, z +-3 um, astigmatism":
        tab = _table(50, F, 512, 512, zspan=3e-6)
        n, first, rest = _consume(render_frames(tab, (512, 512), Optics(astigmatism=1.2e-7), seed=1))
    elif name == "512x512, 50 particles, motion blur 8":
        tab = _table(50, F, 512, 512)
        n, first, rest = _consume(render_frames(tab, (512, 512), motion_blur_substeps=8, seed=1))
    elif name == "512x512, 50 particles, brightfield":
        tab = _table(50, F, 512, 512, zspan=1e-6)
        n, first, rest = _consume(render_frames(tab, (512, 512), camera=Camera(photons=2e4, background=1000.0),
                                                brightfield=True, seed=1))
    elif name == "512x512, 50 particles, coherent brightfield":
        tab = _table(50, F, 512, 512, zspan=1e-6)
        n, first, rest = _consume(render_frames(tab, (512, 512), camera=Camera(photons=3000.0, background=1000.0),
                                                brightfield="coherent", seed=1))
    elif name == "2560x2160 movie to TIFF, 200 particles":
        tab = _table(200, F, 2160, 2560)
        with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as d:
            paths = render_movie(tab, d, (2160, 2560), seed=1, progress=False)
            size = paths["movie"].stat().st_size
        n = F
        return {"frames": n, "wall": time.perf_counter() - t0, "bytes": size, "first": None, "rest": None,
                "cpu": time.process_time() - c0, "cpu_rest": None,
                "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    elif name == "calibration +-60 um / 2 um, 64x64 (seed default)":
        with tempfile.TemporaryDirectory() as d:
            # the seed's stack, given explicitly (render_calibration's own defaults are now -3..+3 um / 0.1 um)
            from sim.render.camera import Camera
            from sim.render.optics import Optics

            render_calibration(d, -60e-6, 60e-6, 2e-6, optics=Optics(), camera=Camera(), progress=False)
        n = 61
        first, rest = None, None
    else:
        raise SystemExit(f"unknown case {name}")
    return {"frames": n, "wall": time.perf_counter() - t0, "first": first, "rest": rest,
            "cpu": time.process_time() - c0, "cpu_rest": _CPU.get("rest") if rest is not None else None,
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


CASES = [
    "512x512, 50 particles, in focus",
    "512x512, 50 particles, z +-3 um, astigmatism",
    "512x512, 50 particles, motion blur 8",
    "512x512, 50 particles, brightfield",
    "512x512, 50 particles, coherent brightfield",
    "calibration +-60 um / 2 um, 64x64 (seed default)",
    "2560x2160 movie to TIFF, 200 particles",
]


def accuracy() -> list[tuple[str, str]]:
    from scipy.optimize import least_squares
    from scipy.special import j1

    from ptrack.table import make_table
    from sim.render import Camera, Optics, expected_frames, psf_image

    rows = []
    o = Optics()
    os_ = 16
    img = psf_image(o, PX, 0.0, size=48, oversample=os_, pixel_integrated=False)
    c = 24 * os_
    prof = img[c, c:c + 8 * os_] / img[c, c]
    r = np.arange(8 * os_) / os_ * PX
    v = 2 * np.pi * o.na * r / o.wavelength
    airy = np.ones_like(v)
    airy[1:] = (2 * j1(v[1:]) / v[1:]) ** 2
    k = np.argmin(prof[os_ * 2:os_ * 6]) + 2 * os_
    # sub-sample minimum by a parabola through the three lowest points
    y0, y1, y2 = prof[k - 1:k + 2]
    kmin = k + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    ring = kmin / os_ * PX
    rows.append(("first dark ring vs 0.61 lambda/NA (in focus)", f"{(ring / o.airy_radius - 1) * 100:+.3f} %"))
    rows.append(("max |PSF - Airy| / peak, r < 8 px", f"{np.max(np.abs(prof - airy)):.1e}"))
    cam = Camera(photons=1e5, background=0.0)
    f = np.zeros(1, int)
    t = make_table(f, f * 0.1, f, [100.37 * PX], [101.81 * PX], [1.3e-6], meta={"frame_interval": 0.1})
    e = next(expected_frames(t, (200, 200), Optics(astigmatism=1e-7), cam, radius=250e-9))  # patch inside the frame
    rows.append(("flux: sum(image) / photons - 1 (defocused, astigmatic, R = 250 nm)", f"{e.sum() / 1e5 - 1:+.1e}"))
    # sub-pixel placement: noise-free in-focus images fitted with an independent pixel-integrated Airy model
    rng = np.random.default_rng(3)
    errs = []
    sub = 8
    oo = (np.arange(sub) + 0.5) / sub - 0.5
    for _ in range(20):
        x, y = 30 + rng.uniform(-0.5, 0.5), 30 + rng.uniform(-0.5, 0.5)
        t = make_table(f, f * 0.1, f, [x * PX], [y * PX], [0.0], meta={"frame_interval": 0.1})
        im = next(expected_frames(t, (60, 60), None, cam))
        yy, xx = np.mgrid[22:39, 22:39]
        d = im[yy, xx]

        def model(p):
            dx = xx[..., None, None] + oo[None, None, None, :] - p[1]
            dy = yy[..., None, None] + oo[None, None, :, None] - p[2]
            vv = np.maximum(2 * np.pi * o.na * np.hypot(dx, dy) * PX / o.wavelength, 1e-9)
            return p[0] * ((2 * j1(vv) / vv) ** 2).mean(axis=(-1, -2)) + p[3]

        fit = least_squares(lambda p: (model(p) - d).ravel(), [d.max(), 30.0, 30.0, 0.0], x_scale=[1e3, 0.1, 0.1, 1])
        errs.append(np.hypot(fit.x[1] - x, fit.x[2] - y))
    rows.append(("sub-pixel placement: Airy-fit position error, max over 20 (noise-free)", f"{max(errs):.1e} px"))
    # PSF stack interpolation in z (50 nm planes) against the exact PSF at the same defocus
    from sim.render.calibration import calibration_images

    oa = Optics(astigmatism=1.2e-7)
    for z in (1.025e-6, 3.025e-6, 10.025e-6):
        t = make_table([0, 0], [0.0, 0.0], [0, 1], [60 * PX, 400 * PX], [60 * PX, 400 * PX], [z, z + 0.2e-6],
                       meta={"frame_interval": 0.1})
        a = next(expected_frames(t, (121, 121), oa, cam))
        ex = next(calibration_images([z], (121, 121), oa, cam, position=(60, 60), noise=False))
        rows.append((f"z-interpolated PSF vs exact, max |diff| / peak, defocus {z * 1e6:.3f} um",
                     f"{np.abs(a - ex).max() / ex.max():.1e}"))
    # end to end (PSF + noise): Airy-fit scatter on noisy frames vs the Cramer-Rao bound
    from sim.render import localisation_crlb, render_frames

    for photons in (500.0, 2000.0, 20000.0):
        camn = Camera(photons=photons, background=10.0)
        n = 200
        rng = np.random.default_rng(1)
        xs, ys = 20 + rng.uniform(-0.5, 0.5, n), 20 + rng.uniform(-0.5, 0.5, n)
        fr = np.arange(n)
        t = make_table(fr, fr * 0.1, fr, xs * PX, ys * PX, np.zeros(n), meta={"frame_interval": 0.1})
        frames = np.array(list(render_frames(t, (40, 40), None, camn, seed=2)), float)
        crlb = localisation_crlb(camn, 20.2, 19.9, shape=(40, 40))
        yy, xx = np.mgrid[12:29, 12:29]

        def model(p):
            dx = xx[..., None, None] + oo[None, None, None, :] - p[1]
            dy = yy[..., None, None] + oo[None, None, :, None] - p[2]
            vv = np.maximum(2 * np.pi * o.na * np.hypot(dx, dy) * PX / o.wavelength, 1e-9)
            return p[0] * ((2 * j1(vv) / vv) ** 2).mean(axis=(-1, -2)) + p[3]

        errs = []
        for k in range(n):
            e = (frames[k][yy, xx] - camn.offset) / camn.gain
            w = 1 / np.sqrt(np.maximum(e, 0) + camn.read_noise ** 2 + 1)
            fit = least_squares(lambda p: ((model(p) - e) * w).ravel(), [e.max(), 20, 20, np.median(e)],
                                x_scale=[100, 0.1, 0.1, 1])
            errs.append(fit.x[1] - xs[k])
        rows.append((f"Airy-fit x scatter / Cramer-Rao bound, {photons:.0f} photons, 200 noisy frames",
                     f"{np.std(errs) / crlb:.3f}  (CRLB {crlb * PX * 1e9:.2f} nm = {crlb:.4f} px)"))
    # camera statistics
    from sim.render import expose

    cam = Camera()
    a = expose(np.full((512, 512), 100.0), cam, np.random.default_rng(0)).astype(float)
    m = cam.gain * cam.quantum_efficiency * 100 + cam.offset
    var = cam.gain ** 2 * (cam.quantum_efficiency * 100 + cam.read_noise ** 2) + 1 / 12
    rows.append(("camera mean / model - 1 (100 photons, 512^2 px)", f"{a.mean() / m - 1:+.1e}"))
    rows.append(("camera variance / model - 1 (100 photons, 512^2 px)", f"{a.var() / var - 1:+.1e}"))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-big", action="store_true")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.case:
        print(json.dumps(case(a.case, a.quick)))
        return
    print(f"sim.render benchmark ({os.cpu_count()} CPUs; machine may be shared: times are upper bounds)")
    print(f"{'case':52s} {'frames':>6s} {'wall s':>8s} {'frames/s':>9s} {'steady f/s':>10s} {'CPU s':>7s} "
          f"{'steady f/CPU-s':>14s} {'peak RSS MB':>12s}")
    for name in CASES:
        if a.no_big and name.startswith("2560"):
            continue
        cmd = [sys.executable, __file__, "--case", name] + (["--quick"] if a.quick else [])
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"{name:52s} FAILED: {r.stderr.strip().splitlines()[-1] if r.stderr else r.returncode}")
            continue
        d = json.loads(r.stdout.strip().splitlines()[-1])
        extra = f"   ({d['bytes'] / 1e9:.2f} GB written)" if "bytes" in d else ""
        steady = f"{(d['frames'] - 1) / d['rest']:10.1f}" if d.get("rest") else f"{'-':>10s}"
        steady_cpu = f"{(d['frames'] - 1) / d['cpu_rest']:14.1f}" if d.get("cpu_rest") else f"{'-':>14s}"
        print(f"{name:52s} {d['frames']:6d} {d['wall']:8.2f} {d['frames'] / d['wall']:9.1f} {steady} {d['cpu']:7.2f} "
              f"{steady_cpu} {d['rss_mb']:12.0f}{extra}")
    print()
    print(f"{'accuracy check':72s} value")
    for k, v in accuracy():
        print(f"{k:72s} {v}")


if __name__ == "__main__":
    main()
