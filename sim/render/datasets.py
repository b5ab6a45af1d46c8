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
    Brightfield (dark particles on a bright field), 16 polystyrene particles
    of 0.8 um starting 2.4-14 um above the electrode (z = 0) and drifting down
    at the Henry velocity ``v = 2 eps eps0 zeta E f(kappa a) / (3 mu)``
    (exact Henry f, from :mod:`sim.electrokinetics`; zeta -40 mV, E 250 V/m,
    Debye length 100 nm: 5.25 um/s) plus Stokes settling (0.018 um/s) and
    Brownian motion, sticking on contact (z = R; truth column ``deposited``);
    30 fps as in the seed's EPD observations, 100 frames, 128x128 px.
    Imaged so that GDPT can measure the drift: 20x / NA 0.4 air objective,
    550 nm, 325 nm pixels, focal plane 3 um below the electrode (every
    particle above focus, outside the depth of field), and a brightfield
    calibration stack (``calib.tif``, ``calib_z.csv``) over z = 0.4-15.4 um
    in 0.25 um steps. No wall hydrodynamics (free-space mobility down to
    contact). ``params.json`` holds ``v_henry``, ``v_sedimentation``,
    ``vz_drift``, ``D_true``, ``focal_plane`` and each particle's contact frame.
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
    """Trajectories and rendering settings of ``epd_brightfield`` (no rendering).

    Designed so that the drift towards the substrate can be measured from the
    movie by GDPT: a 20x / NA 0.4 air objective and 6.5 um camera pixels (325 nm
    in the sample, Nyquist-sampled at 550 nm), where the geometric defocus blur
    grows by ``tan(asin(0.4 / 1.333))`` = 0.31 um per um, so a particle 20 um
    above focus is a ring 40 px across (at NA 0.75 and 103 nm pixels it would be
    a disk of ~260 px and undetectable). The focal plane is 3 um below the
    electrode surface (z = 0), so all particles are on one side of focus (no
    +- ambiguity) and at least 3.4 um from it, outside the depth of field
    (~+-2.3 um) where the image hardly changes with z: GDPT's z error on this
    movie is ~0.3 um below 10 um and ~0.7 um at 10-15 um (ptrack pipeline of
    23 Nov 2026, bench/bench_velocity.py --movie), against ~1 um near the
    substrate with the focus on it. The brightfield calibration
    stack covers z = R (contact) .. 15.4 um, every height of the movie.
    """
    from sim.electrokinetics import henry_function, henry_velocity

    from ptrack.constants import STANDARD_GRAVITY

    R = 0.4e-6                     # 0.8 um polystyrene, seed chapter 4
    rho_p, rho_f = 1050.0, 998.2   # kg/m^3, polystyrene and water at 20 C
    zeta = -0.040                  # V
    debye = 100e-9                 # m, dilute aqueous suspension
    E = 250.0                      # V/m, towards the substrate (weak field: 5 um/s, slow enough to follow at 30 fps)
    f = float(henry_function(R / debye))
    v = abs(float(henry_velocity(E, zeta, R, debye, EPS_WATER, MU_WATER)))  # m/s, 2 eps eps0 |zeta| E f / (3 mu)
    # Stokes settling adds 0.018 um/s (0.35 % of v): included so that the truth is the physics
    v_sed = 2.0 / 9.0 * (rho_p - rho_f) * STANDARD_GRAVITY * R**2 / MU_WATER
    vz = -(v + v_sed)
    D = stokes_einstein(R)
    optics = Optics(na=0.4, wavelength=550e-9, magnification=20.0)   # brightfield, green filter
    # brightfield as extinction: a 0.8 um PS sphere removes about twice its cross-section (0.5 um^2) of the
    # illumination, 10x the 0.106 um^2 of a pixel; bright illumination (10000 photons/px, 6000 e-, a fifth
    # of an sCMOS well) as for fast brightfield imaging
    camera = Camera(photons=100000.0, background=10000.0)
    px = sample_pixel_size(optics, camera.pixel_pitch)    # 325 nm
    H = W = 128
    dt, F, N = 1.0 / 30.0, 100, 16
    z_top = 14e-6
    focal_plane = -3e-6            # focus 3 um below the electrode surface: every height >= 3.4 um from focus
    rng = np.random.default_rng(seed)
    margin = 18 * px               # the blur disk of a particle 15 um above the substrate has a radius of 18 px
    lo = np.array([margin, margin])
    hi = np.array([(W - 1) * px - margin, (H - 1) * px - margin])
    xy = rng.uniform(lo, hi, size=(N, 2))
    z = R + rng.uniform(2e-6, z_top - R, size=N)
    sub = 20
    h = dt / sub
    pos = np.empty((F, N, 3))
    pos[0] = np.c_[xy, z]
    stuck = np.zeros(N, bool)
    contact_frame = np.full(N, -1)
    # Overdamped Brownian dynamics with free-space mobility (no wall hydrodynamics: the hindrance is
    # below 10 % only for gaps above ~5 radii, so rows within 2 um of the substrate are slower in reality)
    for i in range(1, F):
        for _ in range(sub):
            mov = ~stuck
            step = math.sqrt(2 * D * h) * rng.standard_normal((N, 3))
            xy[mov] = _reflect(xy[mov] + step[mov, :2], lo, hi)
            z[mov] = z[mov] + vz * h + step[mov, 2]
            hit = mov & (z <= R)
            z[hit] = R                  # deposited: sticks on contact (irreversible)
            stuck |= hit
        contact_frame[stuck & (contact_frame < 0)] = i
        pos[i] = np.c_[xy, z]
    table = _table_from(pos, dt, {"pixel_size": px, "frame_interval": dt, "radius": R,
                                  "source": "sim.render.datasets epd_brightfield"}, R)
    cf = np.where(contact_frame < 0, F, contact_frame)
    table["deposited"] = table["frame"].to_numpy() >= cf[table["particle"].to_numpy()]
    # calibration: a particle on the substrate, the stage stepped through z; 4 frames averaged per height
    # (4x the photons of a movie frame, same contrast), as a careful calibration does
    n_avg = 4
    calib = {"z_min": R, "z_max": R + 15e-6, "z_step": 0.25e-6, "shape": (64, 64), "radius": R,
             "camera": Camera(photons=n_avg * camera.photons, background=n_avg * camera.background),
             "seed": seed + 2, "brightfield": True, "frames_averaged": n_avg}
    extra = {"dataset": "epd_brightfield", "radius": R, "zeta": zeta, "debye_length": debye, "field": E,
             "henry_f": f, "henry_f_formula": "exact (sim.electrokinetics.henry_function)", "v_henry": v,
             "v_sedimentation": v_sed, "particle_density": rho_p, "fluid_density": rho_f,
             "vz_drift": vz, "D_true": D, "walk_seed": seed, "start_heights": [R + 2e-6, z_top],
             "deposit": "particles stick at z = R (contact with the substrate at z = 0); truth column 'deposited' "
                        "is True from the first frame after contact",
             "contact_frame": [int(c) if c >= 0 else None for c in contact_frame],
             "focal_plane_note": "focal plane 3 um below the electrode surface (z = 0): all particles above focus, "
                                 "at least 3.4 um from it, where the defocused image changes fast with z",
             "wall_hydrodynamics": "none (free-space mobility down to contact)",
             "calibration": {"stack": "calib.tif", "z": "calib_z.csv", "z_min": calib["z_min"],
                             "z_max": calib["z_max"], "z_step": calib["z_step"], "brightfield": True,
                             "photons": calib["camera"].photons, "background": calib["camera"].background,
                             "frames_averaged": n_avg}}
    return {"table": table, "shape": (H, W), "optics": optics, "camera": camera,
            "focal_plane": focal_plane, "brightfield": True, "seed": seed + 1, "extra": extra, "calibration": calib}


def _make(name: str, out: Path) -> dict:
    sc = SCENES[name]()
    paths = render_movie(sc["table"], out, sc["shape"], sc["optics"], sc["camera"], focal_plane=sc["focal_plane"],
                         brightfield=sc["brightfield"], seed=sc["seed"], compression="zlib", extra_params=sc["extra"])
    cal = sc.get("calibration")
    if cal:
        paths.update(render_calibration(out, cal["z_min"], cal["z_max"], cal["z_step"], shape=cal["shape"],
                                        optics=sc["optics"], camera=cal["camera"], radius=cal["radius"],
                                        focal_plane=sc["focal_plane"], brightfield=cal.get("brightfield", False),
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
        "  calib.tif, calib_z.csv, calib_params.json  (diffusion3d, epd_brightfield) defocus calibration",
        "                 stack and its z (m)",
        "",
    ]
    summary = {
        "diffusion2d": "2D Brownian motion near focus, R = 250 nm, 10 fps, 130 frames, 192x192 px; D_true in params.json",
        "diffusion3d": "3D Brownian motion over +-2.5 um with astigmatism, 100 frames, 160x160 px; calibration +-3 um / 0.1 um",
        "epd_brightfield": "brightfield, 0.8 um particles drifting onto the substrate at the Henry velocity, 30 fps,\n"
                           "                  100 frames, 20x/NA 0.4; brightfield calibration 0.4-15.4 um / 0.25 um",
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
