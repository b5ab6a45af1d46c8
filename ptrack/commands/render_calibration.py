"""Render a defocus calibration stack: one particle at the frame centre stepped through z.

Writes DIR/calib.tif (one 16-bit page per height; ImageJ metadata: pixel size,
z spacing; JSON in the 'Info' property), DIR/calib_z.csv (columns page, z in
m; defocus = z - focal plane), DIR/calib_params.json and DIR/calib_montage.png.
Defaults: a stack ``ptrack track --calib`` can use as it is, for the default
63x / NA 0.75 objective and camera: -3..+3 um in 0.1 um steps (beyond a few um
of defocus the image of a particle with 5000 photons spreads into the noise:
the seed's +-60 um stage scan in 2 um steps, --z-range -6e-5 6e-5 --z-step 2e-6,
shows the bead only within about +-5 um), with a cylindrical-lens astigmatism
of 1.2e-7 m (about 0.23 waves at the pupil edge) so that +z and -z look
different (without it a particle above focus matches the page below focus as
well: the sign of z is undefined), and 20000 photons per page (4 default
movie frames averaged: a 5000-photon template's own noise biased z by 0.16 um
and x by 0.45 px at 2.6 um of defocus). Render the movie with the same
--astigmatism. SI units (m).
"""
from __future__ import annotations

import numpy as np


def add_arguments(p):
    from sim.render.calibration import DEFAULT_ASTIGMATISM as ASTIGMATISM
    from sim.render.calibration import DEFAULT_PHOTONS as PHOTONS
    from sim.render.calibration import DEFAULT_Z_RANGE as Z_RANGE
    from sim.render.calibration import DEFAULT_Z_STEP as Z_STEP
    from sim.render.options import add_optics_camera_arguments

    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--z-range", type=float, nargs=2, metavar=("ZMIN", "ZMAX"), default=Z_RANGE,
                   help=f"lowest and highest particle height, m (default {Z_RANGE[0]:g} {Z_RANGE[1]:g}: every page "
                        "shows the bead with the default optics and photons)")
    p.add_argument("--z-step", type=float, default=Z_STEP, help=f"height step, m (default {Z_STEP:g})")
    p.add_argument("--shape", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="page height and width, pixels (default: holds the image at the largest defocus, up to 512)")
    p.add_argument("--focal-plane", type=float, default=0.0, metavar="Z", help="height of the focal plane, m (default 0)")
    # astigmatic by default: +z and -z pages differ (render the movie with the same --astigmatism); pages as
    # bright as 4 default movie frames averaged
    add_optics_camera_arguments(p, astigmatism=ASTIGMATISM, photons=PHOTONS)


def run(a) -> int:
    from ptrack.errors import output_dir
    from sim.render.calibration import render_calibration
    from sim.render.options import brightfield_from_args, check_out_dir, optics_camera_from_args, preview_pages, save_montage, spread_indices

    out = check_out_dir(a.out)
    with output_dir(out, "--out", all_or_nothing=True):  # no half folder if a write fails
        optics, camera = optics_camera_from_args(a)
        paths = render_calibration(out, a.z_range[0], a.z_range[1], a.z_step, shape=tuple(a.shape) if a.shape else None, optics=optics,
                                   camera=camera, focal_plane=a.focal_plane, radius=a.radius or 0.0,
                                   brightfield=brightfield_from_args(a), seed=a.seed, compression="zlib" if a.compress else None,
                                   scatter_phase=a.scatter_phase)
        z = np.loadtxt(paths["z"], delimiter=",", skiprows=1)[:, 1].reshape(-1)
        pages = spread_indices(len(z), 12, include=int(np.argmin(np.abs(z - a.focal_plane))))
        imgs = preview_pages(paths["stack"], pages)
        # large pages: show the middle, where the particle is, at a size the montage can show (the largest image fits)
        H, W = imgs[0].shape
        h = min(H, W, 256) // 2
        imgs = [im[H // 2 - h:H // 2 + h, W // 2 - h:W // 2 + h] for im in imgs]
        png = save_montage(imgs, [f"z = {z[k] * 1e6:+.2f} µm" for k in pages], out / "calib_montage.png",
                           title=f"calibration stack (z in µm; central {2 * h} x {2 * h} px, smoothed)", smooth=True)
        print(f"rendered {len(z)} calibration planes from {z[0] * 1e6:+.2f} to {z[-1] * 1e6:+.2f} µm")
        for k, v in paths.items():
            print(f"  {k}: {v}")
        print(f"  montage: {png}")
    return 0
