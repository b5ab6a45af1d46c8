"""A movie's simulated twin: infer its physics from its own tracks, simulate, render, track, compare.

Tracks the movie (2D, or 3D with --calib); infers the radius from D with the
wall correction (each particle's measured height in 3D, --height in 2D), or
the viscosity when --radius is given; with --field, the electrophoretic
velocity from the drift along z (sedimentation subtracted when --density is
given), the zeta potential (Henry's exact function) and the charge; the
number density, the heights, and the camera (background, noise, photons per
particle, spot size, motion blur) from the movie. Writes them as an editable
scene.toml (a valid 'ptrack simulate' scene) and render.toml, simulates on
the engine (overdamped Brownian dynamics, wall mobility, field, gravity and
buoyancy) in a periodic box larger than the view, renders with the same
optics and camera, tracks with the same settings, and compares measured
against twin tracks and twin tracks against the twin's truth with 'ptrack
compare'. --set KEY=VALUE overrides an inferred value (what-if twins), e.g.
--set particles.radius=3.25e-7. SI units.
"""
from __future__ import annotations

import argparse
import json
import re

from ..errors import atomic_output
from .track import add_track_arguments, track_kwargs


def add_arguments(p: argparse.ArgumentParser) -> None:
    p._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
    p.add_argument("movie", metavar="MOVIE", help="TIFF movie (or folder / glob of frames)")
    add_track_arguments(p)
    g = p.add_argument_group("physics (SI units)")
    g.add_argument("--temperature", type=float, required=True, help="K")
    g.add_argument("--viscosity", type=float, required=True, help="Pa s (inferred instead when --radius is given)")
    g.add_argument("--radius", type=float, help="particle radius, m: given, the viscosity is inferred")
    g.add_argument("--field", type=float, help="electric field E_z, V/m (+z away from the electrode): zeta from the drift")
    g.add_argument("--density", type=float, help="particle density, kg/m^3: sedimentation (gravity and buoyancy)")
    g.add_argument("--fluid-density", type=float, default=998.2, help="kg/m^3 (default 998.2, water at 20 C)")
    g.add_argument("--debye-length", type=float, default=100e-9, help="m, for Henry's function (default 1e-7)")
    g.add_argument("--permittivity", type=float, default=78.5, help="relative permittivity (default 78.5, water)")
    g.add_argument("--height", type=float, help="2D: centre height above the wall, m (wall correction); default bulk")
    g.add_argument("--wall-z", type=float, default=0.0, help="3D: z of the wall in the calibration's frame, m (default 0)")
    g.add_argument("--no-wall", action="store_true",
                   help="3D: no substrate near the particles (bulk around focus): reflecting planes beyond the "
                        "measured heights, no hindrance")
    g.add_argument("--no-wall-hydrodynamics", action="store_true",
                   help="free-space mobility down to the wall (no hindrance in the inference or the twin)")
    g = p.add_argument_group("optics (not measurable from the movie; defaults: the seed's 63x / NA 0.75, 519 nm)")
    g.add_argument("--na", type=float, default=0.75, help="numerical aperture (default 0.75)")
    g.add_argument("--wavelength", type=float, default=519e-9, help="m (default 5.19e-7)")
    g.add_argument("--medium-index", type=float, default=1.333, help="default 1.333")
    g.add_argument("--astigmatism", type=float, default=0.0, help="m (default 0)")
    g.add_argument("--pixel-pitch", type=float, default=6.5e-6, help="camera pixel pitch, m (magnification = pitch / pixel size)")
    g.add_argument("--qe", type=float, default=0.6, help="quantum efficiency (default 0.6)")
    g.add_argument("--focal-plane", type=float,
                   help="3D: focal plane in the calibration's z, m (default: calib_params.json beside --calib, else 0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override an inferred value: particles.radius, fluid.viscosity, fields.E, optics.na, "
                        "camera.photons, view.focal_plane ... (repeatable)")
    p.add_argument("--calibrate", type=int, default=0, metavar="N",
                   help="rounds of pipeline calibration: measure on the twin what tracking does to D and v_z "
                        "(its truth against its tracks), correct the movie's values by it, make the twin again "
                        "(default 0)")
    p.add_argument("--seed", type=int, default=1, help="simulation / rendering seed (default 1)")
    p.add_argument("--n-boot", type=int, default=200, help="particle bootstrap resamples (default 200)")
    p.add_argument("--level", type=float, default=0.05, help="family-wise error rate per comparison (Holm)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--json", metavar="OUT", help="write every number (radius_m, zeta_V, verdicts ...) as JSON")
    p.add_argument("--progress", action="store_true", help="progress bars on stderr")


def _pm(v, e, s, unit):
    if v is None:
        return "-"
    return f"{v * s:.4g}" + (f" +- {e * s:.2g}" if e is not None else "") + f" {unit}"


def run(args) -> int:
    from ..compare import format_table, to_json
    from ..twin import run_twin

    # every numeric option was checked against its range by ptrack.cli (ptrack.options, the one table)
    kw = track_kwargs(args)
    optics = {"na": args.na, "wavelength": args.wavelength, "medium_index": args.medium_index,
              "astigmatism": args.astigmatism}
    camera = {"pixel_pitch": args.pixel_pitch, "quantum_efficiency": args.qe}
    if kw.get("read_noise"):
        camera["read_noise"] = kw["read_noise"]
    res = run_twin(args.movie, args.out, kw, args.temperature, args.viscosity, radius=args.radius, field=args.field,
                   density=args.density, fluid_density=args.fluid_density, height=args.height, wall_z=args.wall_z,
                   wall=not args.no_wall,
                   wall_hydrodynamics=not args.no_wall_hydrodynamics, debye_length=args.debye_length,
                   permittivity=args.permittivity, optics=optics, camera=camera, focal_plane=args.focal_plane,
                   overrides=args.set, seed=args.seed, n_boot=args.n_boot, level=args.level, progress=args.progress,
                   calibrate=args.calibrate)
    p = res["parameters"]
    print(f"{args.movie}: {p['n_tracks']} tracks; inferred ({p['inferred']} from D_xy = "
          f"{_pm(p['D']['xy'], p['D_err']['xy'], 1e12, 'µm²/s')}, wall ratio {p['wall_ratio']:.4g}):")
    print(f"  radius    {_pm(res['radius_m'], res['radius_err_m'], 1e9, 'nm')}")
    print(f"  viscosity {_pm(res['viscosity_Pa_s'], res['viscosity_err_Pa_s'], 1e3, 'mPa s')}")
    if res["zeta_V"] is not None:
        print(f"  zeta      {_pm(res['zeta_V'], res['zeta_err_V'], 1e3, 'mV')}  (Henry f = {p['henry_f']:.4f}; "
              f"v_ep = {p['v_electrophoretic_m_s'] * 1e6:.4g} µm/s)")
        print(f"  charge    {_pm(res['charge_C'], res['charge_err_C'], 1 / 1.602176634e-19, 'e')}")
    for h in res["calibration_history"]:
        b = ", ".join(f"{k} x{v[0]:.4g} +- {v[0] * v[1]:.2g}" for k, v in h["bias"].items())
        print(f"  pipeline calibration round {h['iteration']}: twin truth / twin tracks: {b}")
    if res["overrides"]:
        print(f"  overridden: {', '.join(res['overrides'])} (twin radius {res['twin_radius_m'] * 1e9:.4g} nm)")
    print(format_table(res["measured_vs_twin"]))
    print(format_table(res["twin_vs_truth"]))
    print("meaning:")
    for m in res["meaning"]:
        print(f"  - {m}")
    t = res["timings_s"]
    print("time: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in t.items()))
    print(f"wrote {res['files']['scene']}, {res['files']['report']}")
    if args.json:
        to_json(res, args.json)
        print(f"wrote {args.json}")
    return 0
