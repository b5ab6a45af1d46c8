"""Render a trajectories table as a synthetic microscope movie with exact ground truth.

Writes DIR/movie.tif (16-bit multi-page TIFF, ImageJ metadata: pixel size and
frame interval; the same numbers as JSON in the ImageJ 'Info' property),
DIR/truth.parquet (the table with x_px, y_px, photons, signal, defocus,
in_frame), DIR/params.json and DIR/preview.png. Scalar Fourier-optics PSF
(defocus, optional astigmatism), pixel integration, particle size blur,
Poisson shot noise, read noise, gain, offset, clipping. All options in SI
units (m, s); defaults follow the seed's set-up (63x / NA 0.75 air objective,
519 nm, Andor Zyla 5.5).
"""
from __future__ import annotations

import json
import sys

import numpy as np


def add_arguments(p):
    from sim.render.options import add_optics_camera_arguments

    p.add_argument("trajectories", metavar="TRAJ", help="trajectories table (Parquet or CSV; frame, t, particle, x, y, z in m)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--shape", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="frame height and width, pixels (default: just enclosing the trajectories plus a margin)")
    p.add_argument("--focal-plane", type=float, default=0.0, metavar="Z", help="height of the focal plane, m (default 0)")
    p.add_argument("--exposure", type=float, default=None, help="exposure time, s (default: the frame interval)")
    p.add_argument("--motion-blur", type=int, default=0, metavar="S", help="average S sub-positions over the exposure (default 0: off)")
    add_optics_camera_arguments(p)


def run(a) -> int:
    from ptrack.errors import UserError, output_dir
    from ptrack.table import read_table
    from sim.render.movie import render_movie
    from sim.render.optics import sample_pixel_size
    from sim.render.options import brightfield_from_args, check_out_dir, optics_camera_from_args, preview_pages, save_montage, spread_indices

    table = read_table(a.trajectories)
    if len(table) == 0:
        raise UserError(f"trajectories table {a.trajectories} is empty", "give a table with at least one row")
    out = check_out_dir(a.out)
    with output_dir(out, "--out", all_or_nothing=True):  # no half folder if a write fails
        optics, camera = optics_camera_from_args(a, exposure=a.exposure)
        px = sample_pixel_size(optics, camera.pixel_pitch)
        if a.shape is None:
            xmax = float(np.nanmax(table["x"].to_numpy())) / px
            ymax = float(np.nanmax(table["y"].to_numpy())) / px
            if xmax > 16384 or ymax > 16384 or xmax < 0 or ymax < 0:
                raise UserError(f"trajectories span up to ({xmax:.0f}, {ymax:.0f}) px at {px * 1e9:.1f} nm/px",
                                "give --shape H W (and positions in m)")
            shape = (int(np.ceil(ymax)) + 16, int(np.ceil(xmax)) + 16)
        else:
            shape = tuple(a.shape)
        paths = render_movie(table, out, shape, optics, camera, focal_plane=a.focal_plane, brightfield=brightfield_from_args(a),
                             motion_blur_substeps=a.motion_blur, seed=a.seed, radius=a.radius, scatter_phase=a.scatter_phase,
                             compression="zlib" if a.compress else None,
                             extra_params={"command": "ptrack render " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["render"] else None,
                                           "input": str(a.trajectories)})
        params = json.loads(paths["params"].read_text())
        nf = params["n_frames"]
        pages = spread_indices(nf, 6)
        from ptrack.table import read_table as _rt

        truth = _rt(paths["truth"])
        overlay = []
        for k in pages:
            s = truth[truth["frame"] == k]
            overlay.append((s["x_px"].to_numpy(), s["y_px"].to_numpy()))
        # particles in one part of a large frame: preview that part, not a frame with the particles in a corner
        from sim.render.options import crop_box

        sel = truth[truth["frame"].isin(pages)]
        r0, r1, c0, c1 = crop_box(sel["x_px"].to_numpy(), sel["y_px"].to_numpy(), shape)
        imgs = [im[r0:r1, c0:c1] for im in preview_pages(paths["movie"], pages)]
        overlay = [(x - c0, y - r0) for x, y in overlay]
        where = "" if (r1 - r0, c1 - c0) == tuple(shape) else f" (rows {r0}-{r1 - 1}, columns {c0}-{c1 - 1})"
        png = save_montage(imgs, [f"frame {k}" for k in pages], out / "preview.png",
                           overlay=overlay, title=f"rendered frames{where}; red circles: ground truth")
        print(f"rendered {nf} frames of {shape[0]} x {shape[1]} px ({px * 1e9:.1f} nm/px, {params['frame_interval']:g} s/frame)")
        for k, v in paths.items():
            print(f"  {k}: {v}")
        print(f"  preview: {png}")
    return 0
