"""Hindered diffusion near a wall: the D/D0 ratios for a particle height, or the height for a measured ratio.

Give the particle radius and either the height of the particle CENTRE above
the wall (--height) or a measured D/D0 (--ratio). Inputs are SI (m); the
output prints lengths in nm and µm with their names. Parallel ratios: first
order (the seed's eq. 4.1, 1 - 9/16 a/h), Faxen's series, and the recommended
form (Goldman-Cox-Brenner lubrication near contact blended into Faxen);
perpendicular: Brenner's exact series and Bevan & Prieve's closed form.
"""
from __future__ import annotations

import json
import math

from ..errors import UserError, atomic_output
from .. import wall


def add_arguments(parser):
    parser.add_argument("--radius", required=True, type=float, metavar="R",
                        help="particle radius a, m (e.g. 250e-9)")
    g = parser.add_mutually_exclusive_group(required=True)
    g.add_argument("--height", type=float, metavar="H",
                   help="height of the particle CENTRE above the wall, m (must exceed the radius)")
    g.add_argument("--ratio", type=float, metavar="D_OVER_D0",
                   help="measured D/D0 (0 < ratio < 1); prints the centre height that explains it")
    parser.add_argument("--direction", choices=("parallel", "perpendicular"), default="parallel",
                        help="direction in which --ratio was measured (default parallel, i.e. D_x, D_y)")
    parser.add_argument("--first-order", action="store_true",
                        help="use only the seed's eq. 4.1 (1 - 9/16 a/h) for the parallel result")
    parser.add_argument("--D0", type=float, metavar="D0",
                        help="bulk diffusion coefficient, m^2/s: with --height also print the hindered D values")
    parser.add_argument("--plot", metavar="PNG",
                        help="also plot D/D0 of every model against the gap h - a, marking the result")
    parser.add_argument("--json", metavar="OUT", help="also write the results (SI units) to this JSON file")


def _length(v):
    if not math.isfinite(v):
        return "n/a"
    if abs(v) < 1e-6:
        return f"{v * 1e9:.1f} nm"
    return f"{v * 1e6:.4g} µm"


def _try(fn):
    try:
        return fn(), None
    except UserError as exc:
        return None, exc.cause


def run(args) -> int:
    # --radius, --height, --ratio, --D0: checked against their ranges by ptrack.cli (ptrack.options)
    a = float(args.radius)
    result = {"radius_m": a}
    lines = [f"particle radius a = {_length(a)}"]
    if args.height is not None:
        h = float(args.height)
        if h <= a:
            raise UserError(f"--height {h!r} m is not above the radius {a!r} m: the height is that of the particle CENTRE",
                            "give gap + radius")
        result.update(height_m=h, gap_m=h - a, h_over_a=h / a)
        par = {"first_order": wall.parallel_ratio(h, a, "first_order")}
        if not args.first_order:
            par["faxen"] = wall.parallel_ratio(h, a, "faxen")
            par["recommended"] = wall.parallel_ratio(h, a, "auto")
        perp = {"brenner": wall.perpendicular_ratio(h, a, "brenner"),
                "bevan_prieve": wall.perpendicular_ratio(h, a, "bevan_prieve")}
        result["parallel"] = par
        result["perpendicular"] = perp
        lines.append(f"centre height h = {_length(h)}  (gap h - a = {_length(h - a)}, h/a = {h / a:.4g})")
        lines.append("D_parallel/D0:")
        names = {"first_order": "first order, eq. 4.1 (1 - 9/16 a/h)", "faxen": "Faxen series to (a/h)^5",
                 "recommended": "recommended (GCB lubrication + Faxen)"}
        for k, v in par.items():
            lines.append(f"  {names[k]:<40s} {v:.5f}")
        lines.append("D_perpendicular/D0:")
        lines.append(f"  {'Brenner (1961) exact series':<40s} {perp['brenner']:.5f}")
        lines.append(f"  {'Bevan & Prieve (2000)':<40s} {perp['bevan_prieve']:.5f}")
        if args.D0 is not None:
            D0 = float(args.D0)
            result["D0_m2_per_s"] = D0
            result["D_parallel_m2_per_s"] = {k: D0 * v for k, v in par.items()}
            result["D_perpendicular_m2_per_s"] = {k: D0 * v for k, v in perp.items()}
            best = par.get("recommended", par["first_order"])
            lines.append(f"with D0 = {D0 * 1e12:.4g} µm²/s: D_parallel = {D0 * best * 1e12:.4g} µm²/s, "
                         f"D_perpendicular = {D0 * perp['brenner'] * 1e12:.4g} µm²/s")
    else:
        r = args.ratio
        if args.D0 is not None:
            raise UserError("--D0 is used with --height only", "with --ratio, divide the measured D by D0 yourself")
        result.update(ratio=r, direction=args.direction)
        lines.append(f"measured D/D0 = {r:.5g} ({args.direction} to the wall)")
        if args.direction == "parallel":
            methods = [("first_order", "first order, eq. 4.1")]
            if not args.first_order:
                methods += [("faxen", "Faxen series to (a/h)^5"), ("auto", "recommended (GCB + Faxen)")]
        else:
            methods = [("brenner", "Brenner (1961) exact series"), ("bevan_prieve", "Bevan & Prieve (2000)")]
        heights = {}
        reasons = []
        lines.append("centre height h that gives this ratio:")
        for key, label in methods:
            h, why = _try(lambda key=key: wall.height_from_ratio(r, a, args.direction, key))
            name = "recommended" if key == "auto" else key
            if h is None:
                heights[name] = None
                reasons.append(why)
                lines.append(f"  {label:<32s} not reachable: {why}")
            else:
                heights[name] = h
                lines.append(f"  {label:<32s} h = {_length(h)}  (gap {_length(h - a)}, h/a = {h / a:.4g})")
        if all(v is None for v in heights.values()):
            raise UserError(f"no model gives D/D0 = {r!r} for a physical height ({reasons[-1]})",
                            "check the measured D and D0" + ("" if not args.first_order else ", or drop --first-order"))
        result["height_m"] = heights
    print("\n".join(lines))
    if args.plot:
        marks = [args.height] if args.height is not None else [v for v in result["height_m"].values() if v]
        from ..plot import plot_wall_ratios

        plot_wall_ratios(a, marks, args.ratio, path=args.plot)
        print(f"wrote {args.plot}")
    if args.json:
        with atomic_output(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
        print(f"wrote {args.json}")
    return 0
