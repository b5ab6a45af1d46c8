"""The synthetic datasets shipped in ``data/synthetic`` (regenerate: ``python -m sim.render.datasets --out data/synthetic``).

Three deterministic datasets (fixed seeds), each with its movie, exact ground
truth and parameters, small enough to commit:

``diffusion2d``
    500 nm silica-like particles (R = 250 nm) diffusing in water at 293.15 K
    (viscosity 1.0 mPa s, the seed's values, chapter 4), imaged like the seed's
    2D experiment: 63x / NA 0.75, 519 nm, Zyla 5.5, 10 fps, 130 frames.
    Brownian walk with ``D = kB T / (6 pi mu R)`` in 3D; x, y reflect at walls
    are free (particles start in an area larger than the view and enter and
    leave it as in a real experiment: the truth column ``in_frame`` says which
    rows are in view), z reflects within +-0.4 um of the focal plane (near focus).
    ``params.json`` holds ``D_true`` and the D of the ground-truth tracks.
``diffusion3d``
    The same particles diffusing in 3D over +-2.5 um around focus, with a
    cylindrical-lens astigmatism, and a calibration stack (``calib.tif``,
    ``calib_z.csv``) over +-3 um in 0.1 um steps.
``epd_brightfield``
    Brightfield (dark particles on a bright field), 0.8 um polystyrene
    particles drifting down to the substrate at the Henry velocity
    ``v = 2 eps eps0 zeta E f(kappa a) / (3 mu)`` (exact Henry f, from
    :mod:`sim.electrokinetics`) plus Brownian motion, sticking on
    contact (z = R); 30 fps as in the seed's EPD observations; the focal plane
    is on the substrate so particles come into focus as they deposit.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from ptrack.constants import BOLTZMANN
from ptrack.table import make_table

from .calibration import render_calibration
from .camera import Camera
from .movie import render_movie
from .optics import Optics, sample_pixel_size

T_ROOM = 293.15          # K, seed chapter 4
MU_WATER = 1.0e-3        # Pa s, seed chapter 4
EPS_WATER = 78.5         # relative permittivity of water


def stokes_einstein(radius: float, temperature: float = T_ROOM, viscosity: float = MU_WATER) -> float:
    """D = kB T / (6 pi mu R), m^2/s."""
    return BOLTZMANN * temperature / (6 * math.pi * viscosity * radius)


def _reflect(v, lo, hi):
    """Fold positions into [lo, hi] by mirror reflection (any number of bounces)."""
    L = hi - lo
    u = np.mod(v - lo, 2 * L)
    return lo + np.where(u > L, 2 * L - u, u)


def brownian_walk(n_particles: int, n_frames: int, dt: float, D: float, lo, hi, seed=0, substeps: int = 10,
                  start=None, reflect=(False, False, True)):
    """Seeded 3D Brownian walk, sampled every ``dt``; chosen axes have reflecting walls.

    The walk is integrated with ``substeps`` steps per frame so that
    reflections at the walls are resolved finer than the frame interval.
    Free axes are exact (Gaussian increments of variance ``2 D dt``).

    Parameters
    ----------
    lo, hi : array_like (3,)
        Box corners, m: the start region, and the walls of the reflecting axes.
    start : ndarray (n_particles, 3), optional
        Initial positions, default uniform in the box.
    reflect : 3 bools
        Which axes reflect at ``lo``/``hi`` (default: only z).

    Returns
    -------
    ndarray (n_frames, n_particles, 3), m
    """
    rng = np.random.default_rng(seed)
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    pos = rng.uniform(lo, hi, size=(n_particles, 3)) if start is None else np.array(start, float)
    out = np.empty((n_frames, n_particles, 3))
    out[0] = pos
    s = math.sqrt(2 * D * dt / substeps)
    refl = np.asarray(reflect, bool)
    for f in range(1, n_frames):
        for _ in range(substeps):
            pos = pos + s * rng.standard_normal(pos.shape)
            pos[:, refl] = _reflect(pos[:, refl], lo[refl], hi[refl])
        out[f] = pos
    return out


def _table_from(pos, dt, meta, radius):
    F, N, _ = pos.shape
    frame = np.repeat(np.arange(F), N)
    particle = np.tile(np.arange(N), F)
    return make_table(frame, frame * dt, particle, pos[:, :, 0].ravel(), pos[:, :, 1].ravel(), pos[:, :, 2].ravel(),
                      meta=meta, radius=np.full(F * N, radius))


def _d_from_truth(pos, dt):
    """Per-axis D from the frame-to-frame displacements of the true tracks (x, y), m^2/s."""
    d = np.diff(pos[:, :, :2], axis=0)
    return float(np.mean(d ** 2) / (2 * dt))


def _readme(path: Path, name: str, text: str):
    cmd = "python -m sim.render.datasets --out data/synthetic --only " + name
    path.write_text(f"Regenerate with: {cmd}   (all datasets: make data)\n{text.strip()}\n")


def diffusion2d_scene(seed: int = 20201) -> dict:
    """Trajectories and rendering settings of ``diffusion2d`` (no rendering)."""
    R = 250e-9
    D = stokes_einstein(R)
    optics, camera = Optics(), Camera(photons=3000.0, background=15.0)
    px = sample_pixel_size(optics, camera.pixel_pitch)
    H = W = 192
    ext = 48 * px  # particles start in an area 48 px wider on each side: they enter and leave the view freely
    dt, F, N = 0.1, 130, 54
    pos = brownian_walk(N, F, dt, D, [-ext, -ext, -0.4e-6], [(W - 1) * px + ext, (H - 1) * px + ext, 0.4e-6],
                        seed=seed)
    meta = {"pixel_size": px, "frame_interval": dt, "source": "sim.render.datasets diffusion2d",
            "temperature": T_ROOM, "viscosity": MU_WATER, "radius": R, "D_true": D}
    extra = {"dataset": "diffusion2d", "D_true": D, "D_truth_tracks": _d_from_truth(pos, dt), "radius": R,
             "temperature": T_ROOM, "viscosity": MU_WATER, "walk_seed": seed,
             "walls": "x, y free (particles enter and leave the view; truth column in_frame); z reflects at +-0.4 um",
             "motion_blur": "none (short exposure)"}
    return {"table": _table_from(pos, dt, meta, R), "shape": (H, W), "optics": optics, "camera": camera,
            "focal_plane": 0.0, "brightfield": False, "seed": seed + 1, "extra": extra}


def diffusion3d_scene(seed: int = 20202) -> dict:
    """Trajectories and rendering settings of ``diffusion3d`` (no rendering)."""
    R = 250e-9
    D = stokes_einstein(R)
    optics = Optics(astigmatism=0.12e-6)
    camera = Camera(photons=4000.0, background=15.0)
    px = sample_pixel_size(optics, camera.pixel_pitch)
    H = W = 160
    ext = 40 * px
    dt, F, N = 0.1, 100, 28
    zlim = 2.5e-6
    pos = brownian_walk(N, F, dt, D, [-ext, -ext, -zlim], [(W - 1) * px + ext, (H - 1) * px + ext, zlim],
                        seed=seed)
    meta = {"pixel_size": px, "frame_interval": dt, "source": "sim.render.datasets diffusion3d",
            "temperature": T_ROOM, "viscosity": MU_WATER, "radius": R, "D_true": D}
    calib = {"z_min": -3e-6, "z_max": 3e-6, "z_step": 1e-7, "shape": (72, 72), "radius": R,
             "camera": Camera(photons=20000.0, background=15.0), "seed": seed + 2}
    extra = {"dataset": "diffusion3d", "D_true": D, "D_truth_tracks": _d_from_truth(pos, dt), "radius": R,
             "walk_seed": seed, "walls": "x, y free (particles enter and leave the view; truth column in_frame); z reflects at +-2.5 um",
             "calibration": {"stack": "calib.tif", "z": "calib_z.csv", "z_min": calib["z_min"], "z_max": calib["z_max"],
                             "z_step": calib["z_step"], "photons": calib["camera"].photons}}
    return {"table": _table_from(pos, dt, meta, R), "shape": (H, W), "optics": optics, "camera": camera,
            "focal_plane": 0.0, "brightfield": False, "seed": seed + 1, "extra": extra, "calibration": calib}


def epd_brightfield_scene(seed: int = 20203) -> dict:
    """Trajectories and rendering settings of ``epd_brightfield`` (no rendering)."""
    from sim.electrokinetics import henry_function, henry_velocity

    R = 0.4e-6                     # 0.8 um polystyrene, seed chapter 4
    zeta = -0.040                  # V
    debye = 100e-9                 # m, dilute aqueous suspension
    E = 250.0                      # V/m, towards the substrate (weak field: slow enough to follow)
    f = float(henry_function(R / debye))
    v = abs(float(henry_velocity(E, zeta, R, debye, EPS_WATER, MU_WATER)))  # m/s, 2 eps eps0 |zeta| E f / (3 mu)
    D = stokes_einstein(R)
    optics = Optics()
    camera = Camera(photons=12000.0, background=800.0)
    px = sample_pixel_size(optics, camera.pixel_pitch)
    H = W = 128
    dt, F, N = 1.0 / 30.0, 100, 12
    rng = np.random.default_rng(seed)
    margin = 12 * px
    lo = np.array([margin, margin])
    hi = np.array([(W - 1) * px - margin, (H - 1) * px - margin])
    xy = rng.uniform(lo, hi, size=(N, 2))
    z = R + rng.uniform(1e-6, 12e-6, size=N)
    sub = 10
    h = dt / sub
    pos = np.empty((F, N, 3))
    pos[0] = np.c_[xy, z]
    stuck = np.zeros(N, bool)
    for i in range(1, F):
        for _ in range(sub):
            mov = ~stuck
            step = math.sqrt(2 * D * h) * rng.standard_normal((N, 3))
            xy[mov] = _reflect(xy[mov] + step[mov, :2], lo, hi)
            z[mov] = z[mov] - v * h + step[mov, 2]
            hit = mov & (z <= R)
            z[hit] = R                  # deposited: sticks on contact (irreversible)
            stuck |= hit
        pos[i] = np.c_[xy, z]
    meta = {"pixel_size": px, "frame_interval": dt, "source": "sim.render.datasets epd_brightfield", "radius": R}
    extra = {"dataset": "epd_brightfield", "radius": R, "zeta": zeta, "debye_length": debye, "field": E,
             "henry_f": f, "henry_f_formula": "exact (sim.electrokinetics.henry_function)", "v_henry": v,
             "vz_drift": -v, "D_true": D, "walk_seed": seed,
             "deposit": "particles stick at z = R (contact with the substrate at z = 0)",
             "focal_plane_note": "focal plane on the particles' centres at contact (z = R)"}
    return {"table": _table_from(pos, dt, meta, R), "shape": (H, W), "optics": optics, "camera": camera,
            "focal_plane": R, "brightfield": True, "seed": seed + 1, "extra": extra}


def _make(name: str, out: Path) -> dict:
    sc = SCENES[name]()
    paths = render_movie(sc["table"], out, sc["shape"], sc["optics"], sc["camera"], focal_plane=sc["focal_plane"],
                         brightfield=sc["brightfield"], seed=sc["seed"], compression="zlib", extra_params=sc["extra"])
    cal = sc.get("calibration")
    if cal:
        paths.update(render_calibration(out, cal["z_min"], cal["z_max"], cal["z_step"], shape=cal["shape"],
                                        optics=sc["optics"], camera=cal["camera"], radius=cal["radius"],
                                        seed=cal["seed"], compression="zlib"))
    keys = list(SCENES)
    nxt = keys[keys.index(name) + 1] if keys.index(name) + 1 < len(keys) else None
    text = __doc__.split(f"``{name}``")[1]
    if nxt:
        text = text.split(f"``{nxt}``")[0]
    _readme(out / "README.txt", name, text)
    return paths


def make_diffusion2d(out: Path) -> dict:
    return _make("diffusion2d", Path(out))


def make_diffusion3d(out: Path) -> dict:
    return _make("diffusion3d", Path(out))


def make_epd_brightfield(out: Path) -> dict:
    return _make("epd_brightfield", Path(out))


SCENES = {"diffusion2d": diffusion2d_scene, "diffusion3d": diffusion3d_scene, "epd_brightfield": epd_brightfield_scene}
DATASETS = {"diffusion2d": make_diffusion2d, "diffusion3d": make_diffusion3d, "epd_brightfield": make_epd_brightfield}


def write_index(root: Path) -> Path:
    """``root/README.txt``: what the datasets are, the files in each, and how to regenerate them."""
    lines = [
        "Synthetic microscope datasets with exact ground truth (sim.render).",
        "Regenerate all: make data   (= python -m sim.render.datasets --out data/synthetic; deterministic seeds)",
        "",
        "Files in each directory:",
        "  movie.tif      16-bit multi-page TIFF (ImageJ metadata: pixel size, frame interval;",
        "                 SI values as JSON in the ImageJ 'Info' property)",
        "  truth.parquet  ground-truth trajectories (ptrack table: frame, t, particle, x, y, z in m,",
        "                 x_px, y_px, photons, signal, defocus, radius, in_frame)",
        "  params.json    every rendering parameter (optics, camera, seeds, D_true, ...)",
        "  calib.tif, calib_z.csv, calib_params.json  (diffusion3d) defocus calibration stack and its z (m)",
        "",
    ]
    summary = {
        "diffusion2d": "2D Brownian motion near focus, R = 250 nm, 10 fps, 130 frames, 192x192 px; D_true in params.json",
        "diffusion3d": "3D Brownian motion over +-2.5 um with astigmatism, 100 frames, 160x160 px; calibration +-3 um / 0.1 um",
        "epd_brightfield": "brightfield, 0.8 um particles drifting onto the substrate at the Henry velocity, 30 fps, 100 frames",
    }
    for name in SCENES:
        lines.append(f"  {name + '/':18s}{summary.get(name, '')}")
    path = root / "README.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m sim.render.datasets", description=__doc__.splitlines()[0])
    p.add_argument("--out", default="data/synthetic", help="output directory (default data/synthetic)")
    p.add_argument("--only", choices=sorted(DATASETS), action="append", help="make only this dataset (repeatable)")
    a = p.parse_args(argv)
    root = Path(a.out)
    for name in a.only or list(DATASETS):
        t0 = time.perf_counter()
        DATASETS[name](root / name)
        size = sum(f.stat().st_size for f in (root / name).iterdir() if f.is_file())
        print(f"{name}: {size / 1e6:.2f} MB in {time.perf_counter() - t0:.1f} s -> {root / name}", file=sys.stderr)
    write_index(root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
