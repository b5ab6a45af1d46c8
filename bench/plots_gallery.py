"""Every analysis and deposition figure in one folder, to judge them by eye (a dev script, not a benchmark).

Usage: python bench/plots_gallery.py [OUT_DIR]   (default out/gallery)

Uses the shipped synthetic data (data/synthetic/) and, for the deposition
views, a synthetic deposit; needs no tracking run. Prints each file written.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ptrack import plot  # noqa: E402
from ptrack.analysis import analyze_table, write_report  # noqa: E402
from ptrack.io import open_movie  # noqa: E402
from ptrack.motion import particle_velocity, velocity_profile  # noqa: E402
from ptrack.table import read_table  # noqa: E402

DATA = ROOT / "data" / "synthetic"


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    # 2D movie: the true tracks as the camera sees them, over its first frame
    d = DATA / "diffusion2d"
    truth = read_table(d / "truth.parquet")
    truth = truth[truth["in_frame"].astype(bool)] if "in_frame" in truth else truth
    with open_movie(d / "movie.tif") as mv:
        img = np.asarray(mv[0], float)
        px = mv.pixel_size
    truth.attrs.setdefault("ptrack", {})["pixel_size"] = px
    print(plot.plot_tracks(img, truth, out / "tracks.png", frame=0) and out / "tracks.png")
    a = analyze_table(truth, radius=250e-9, viscosity=1e-3, temperature=293.15, motion_blur=0.0, height=1e-6)
    rep = write_report(a, out / "report_2d")
    for f in sorted(rep.iterdir()):
        print(f)
    plot.plot_msd(a.diffusion, out / "msd.png", title="diffusion2d truth: ensemble MSD",
                  reported={k: (a.summary["D"][k], a.summary["D_err"][k], a.summary["D_method"]) for k in a.summary["D"]})
    print(out / "msd.png")
    plot.plot_D_per_particle(a.per_particle, "xy", out / "D_per_particle.png", D_ensemble=a.summary["D"]["xy"],
                             D_stokes_einstein=a.summary["D_stokes_einstein"])
    print(out / "D_per_particle.png")
    # 3D: velocity figure of the EPD truth
    e = read_table(DATA / "epd_brightfield" / "truth.parquet")
    vel = particle_velocity(e, axes="xyz", motion_blur=0.0)
    prof = velocity_profile(e, bins=5, motion_blur=0.0, vel=vel)
    plot.plot_velocity(e, vel, out / "velocity.png", profile=prof, title="EPD truth: drift velocities")
    print(out / "velocity.png")
    plot.plot_cm_vs_z(read_table(DATA / "diffusion3d" / "truth.parquet"), out / "cm_vs_z.png")
    print(out / "cm_vs_z.png")
    # deposition views: a synthetic deposit (a monolayer with a few particles on top), 4 times
    from sim.views import snapshot_png, snapshots_png

    rng = np.random.default_rng(0)
    box = (20e-6, 20e-6, 10e-6)
    R = 0.5e-6
    frames = []
    for k, t in enumerate((0.0, 0.5, 1.0, 2.0)):
        n = 60 + 40 * k
        pos = np.c_[rng.uniform(0, box[0], n), rng.uniform(0, box[1], n),
                    np.where(rng.random(n) < 0.15, 3 * R, R) + rng.uniform(0, 6e-6 * (1 - t / 2), n)]
        frames.append((t, pos, np.full(n, R), rng.integers(0, 8, n)))
    snapshots_png(out / "snapshots.png", frames, box=box)
    print(out / "snapshots.png")
    t, pos, rad, cn = frames[-1]
    snapshot_png(out / "final_deposit.png", pos, rad, cn, box=box, title=f"final deposit, t = {t:g} s")
    print(out / "final_deposit.png")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "out" / "gallery")
