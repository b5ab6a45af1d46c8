"""Compile the simulator's kernels into numba's on-disk cache, so that the first real run starts warm.

Numba compiles a kernel on its first call and caches the machine code on disk
(``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``); a later process
loads it in milliseconds. This command makes those first calls: it runs every
shipped scene (``scenes/*.toml``) for a few steps with a few particles, so
that each integrator, contact law and wall kernel a shipped scene uses is
compiled once, at install time (``make venv`` runs it) rather than inside a
user's first simulation or in every new dask worker. It also matches a tiny
synthetic GDPT frame (:func:`warm_gdpt`), which compiles the correlation
kernels of ``ptrack.gdpt.ncc`` that every 3D (``--calib``) run calls, and links
two tiny frames (:func:`warm_link`: the numba linker of ``ptrack.linknb``,
~20 s to compile, which every ``ptrack track`` calls) and tracks five tiny
synthetic movies (:func:`warm_track`: the detector, fits and ring centres of
``ptrack.image``, ~20-45 s to compile), and analyses a small synthetic table
(:func:`warm_analysis`: MSD/CVE, wall correction, velocities). Nothing
it writes is kept (the runs go to a temporary folder). Running it again with
a warm cache takes a few seconds.

Why not ahead-of-time compilation: numba's AOT module is deprecated, and the
cache already holds exactly the specialisations a run needs.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

N_PARTICLES = 24  # enough for pairs in contact and a neighbour list; the kernels' types do not depend on N
STEPS = 3


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def shipped_scenes() -> list[Path]:
    """The shipped scene files (source tree or installed package data)."""
    from sim.studies.deposition import SCENES

    return sorted(Path(SCENES).glob("*.toml"))


def short_scene(raw: dict):
    """The scene of ``raw`` cut to :data:`N_PARTICLES` particles and :data:`STEPS` steps (or 3 ns with dt = auto)."""
    from sim.scene import scene_from_dict

    raw = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    parts = raw.setdefault("particles", {})
    parts["count"] = min(int(parts.get("count", N_PARTICLES)), N_PARTICLES)
    t = raw.setdefault("time", {})
    dt = t.get("dt", "auto")
    final = STEPS * float(dt) if not isinstance(dt, str) else 3e-9
    t["final"] = final
    t["output_interval"] = final
    return scene_from_dict(raw, source="warmup")


def warm_gdpt() -> int:
    """Match a 96 x 96 frame of two astigmatic Gaussian images against a 9-page calibration (a few ms warm).

    Goes through :func:`ptrack.calibration.locate_frame_3d`, so the numba kernels of ``ptrack.gdpt.ncc``
    (cache=True) are compiled for the argument types a real 3D run passes them.

    Returns
    -------
    int
        Particles found (2 when the matcher works).
    """
    import numpy as np

    from ..calibration import build_calibration, locate_frame_3d

    yy, xx = np.mgrid[0:96, 0:96].astype(float)

    def frame(spots):
        img = np.full((96, 96), 100.0)
        for x, y, z in spots:       # widths 1.5 sqrt(1 + ((z -+ 0.5) / 0.6)^2) px, z in um: astigmatic
            sx, sy = 1.5 * np.hypot(1.0, (z - 0.5) / 0.6), 1.5 * np.hypot(1.0, (z + 0.5) / 0.6)
            img += 4e4 / (2 * np.pi * sx * sy) * np.exp(-0.5 * (((xx - x) / sx) ** 2 + ((yy - y) / sy) ** 2))
        return img.astype(np.float32)

    z = np.linspace(-2.0, 2.0, 9)
    cal = build_calibration(np.stack([frame([(47.5, 48.0, zk)]) for zk in z]), z * 1e-6, 1e-7)
    return len(locate_frame_3d(frame([(30.3, 31.6, -0.7), (66.2, 63.9, 1.1)]), cal))


def warm_link() -> int:
    """Link two frames of two points by :func:`ptrack.linknb.link_ids`, and take their first range estimate's
    nearest-neighbour steps (:func:`ptrack.link._nn_steps`): compiles or loads both linkers' kernels.

    Returns
    -------
    int
        Trajectories found (2 when the linker works).
    """
    import numpy as np

    from ..link import _nn_steps
    from ..linknb import link_ids

    pos = np.array([[10.0, 10.0], [30.0, 30.0], [10.5, 10.2], [29.6, 30.3]])
    frames = np.array([0, 0, 1, 1])
    ids = link_ids(frames, pos, 2.0, memory=1, adaptive_stop=0.3, adaptive_step=0.8)
    _nn_steps(frames, pos[:, 0], pos[:, 1])
    return len(np.unique(ids))


def _warm_movies(rng):
    """Small movies (6 frames of 128 x 128, uint16, brightfield also uint8) of the kinds of image ``ptrack track`` meets:
    fluorescence spots of two sizes with an overlapping pair, dark particles on an uneven bright field (with
    dust), and rings of both kinds (bright centre in a dark ring; fluorescence rings), so the detector, the
    ring vote, the joint and isolated fits and the radial-profile centres all run."""
    import numpy as np

    yy, xx = np.mgrid[0:128, 0:128].astype(float)
    centres = np.array([[30.0, 30.0], [30.0, 96.0], [96.0, 30.0], [96.0, 96.0], [64.0, 64.0], [72.0, 65.0],
                        [30.0, 62.0], [37.0, 64.0], [96.0, 62.0], [98.4, 63.0]])
    # two overlapping pairs (joint fits) and an unresolved one (the split test)

    def spots(f, amp, sig):
        out = np.zeros((128, 128))
        for k, (x, y) in enumerate(centres + 0.4 * f):
            out += amp * np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / sig[k % len(sig)] ** 2)
        return out

    def rings(f, radius, width, centre_amp):
        out = np.zeros((128, 128))
        for x, y in centres[:4] + 0.4 * f:
            r = np.hypot(xx - x, yy - y)
            out += np.exp(-0.5 * ((r - radius) / width) ** 2) + centre_amp * np.exp(-0.5 * (r / width) ** 2)
        return out

    light = 1.0 + 0.3 * xx / 128.0
    movies = {
        "fluorescence": [100.0 + spots(f, 400.0, (1.5, 3.0)) for f in range(6)],
        "brightfield": [light * (2000.0 - spots(f, 900.0, (2.5,))) - 600.0 * np.exp(-((xx - 110) ** 2 + (yy - 12) ** 2) / 30.0)
                        for f in range(6)],
        "rings": [light * (1500.0 - 500.0 * rings(f, 6.0, 1.3, -1.6)) if f % 2 == 0 else 100.0 + 300.0 * rings(f, 7.0, 1.5, 0.0)
                  for f in range(6)],
    }
    out = {}
    for name, fr in movies.items():
        counts = rng.poisson(np.stack(fr)).astype(float)
        out[name] = np.clip(counts, 0, 65535).astype(np.uint16)
        if name != "fluorescence":   # brightfield cameras often save 8 bits: kernels specialise on the dtype
            out[name + "_8bit"] = np.clip(counts * (250.0 / counts.max()), 0, 255).astype(np.uint8)
    return out


def warm_track() -> int:
    """Track five small synthetic movies through :func:`ptrack.pipeline.track_movie` (the path of ``ptrack track``):
    compiles or loads the image kernels of ``ptrack.image`` (detection, ring vote, fits, radial centres),
    ~20-45 s cold, which a user's first ``ptrack track`` would otherwise pay.

    Returns
    -------
    int
        Localisations found over the movies.
    """
    import numpy as np
    import tifffile

    from ..pipeline import track_movie

    n = 0
    with tempfile.TemporaryDirectory(prefix="ptrack-warmup-") as tmp:
        for name, stack in _warm_movies(np.random.default_rng(7)).items():
            path = Path(tmp) / f"{name}.tif"
            tifffile.imwrite(path, stack)
            _, summary = track_movie(path, out=Path(tmp) / f"{name}.parquet", pixel_size=1e-7, frame_interval=0.1,
                                     min_length=2, progress=False)
            n += int(summary.get("n_localisations", 0))
    return n


def warm_analysis() -> int:
    """Analyse a small synthetic table of drifting 3D tracks (diffusion by CVE and OLS, the wall correction,
    velocities): compiles or loads the kernels of ``ptrack.motion`` and ``ptrack.velocity`` (~6 s cold).

    Returns
    -------
    int
        Rows of the synthetic table (320).
    """
    from ..analysis import analyze_table
    from ..motion.synthetic import drifting_tracks
    from ..msd import estimate_diffusion
    from ..velocity import ensemble_velocity, particle_velocity, trim_deposited, velocity_profile

    tab = drifting_tracks(8, 40, 1e-12, 0.05, (0.0, 0.0, -1e-6), sigma=2e-8, seed=1)
    analyze_table(tab, radius=5e-7, viscosity=1e-3, temperature=293.0, wall_z=-2e-6, n_boot=10)
    estimate_diffusion(tab, axes=("x", "y", "z"), estimator="cve", motion_blur=0.0, field_of_view="auto")
    estimate_diffusion(tab, axes=("x", "y", "xy"), estimator="ols", motion_blur=0.0)
    vel = particle_velocity(tab, axes="xyz", motion_blur=0.0)
    ensemble_velocity(vel, seed=0)
    trim_deposited(tab, float(tab["z"].min()) + 1e-7, 0.5e-6)
    velocity_profile(tab, bins=3, motion_blur=0.0, vel=vel)
    return len(tab)


def run(args) -> int:
    from sim.run import run_scene

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ptrack-warmup-") as tmp:
        for path in shipped_scenes():
            t1 = time.perf_counter()
            with open(path, "rb") as fh:
                scene = short_scene(tomllib.load(fh))
            run_scene(scene, Path(tmp) / path.stem, progress=False)
            if not args.quiet:
                print(f"warmup: {path.name} compiled / loaded in {time.perf_counter() - t1:.1f} s", file=sys.stderr)
    t1 = time.perf_counter()
    warm_gdpt()
    if not args.quiet:
        print(f"warmup: GDPT correlation kernels compiled / loaded in {time.perf_counter() - t1:.1f} s", file=sys.stderr)
    t1 = time.perf_counter()
    warm_link()
    if not args.quiet:
        print(f"warmup: linker compiled / loaded in {time.perf_counter() - t1:.1f} s", file=sys.stderr)
    t1 = time.perf_counter()
    warm_track()
    if not args.quiet:
        print(f"warmup: image kernels (detection, fits, ring centres) compiled / loaded in {time.perf_counter() - t1:.1f} s",
              file=sys.stderr)
    t1 = time.perf_counter()
    warm_analysis()
    if not args.quiet:
        print(f"warmup: analysis kernels (MSD, CVE, wall correction, velocity) compiled / loaded in "
              f"{time.perf_counter() - t1:.1f} s", file=sys.stderr)
    if not args.quiet:
        print(f"warmup: numba cache ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
