"""Defaults a new user meets (issue 13): units written µm, and the twin's camera exposure from the blur it measured.

The other defaults of issue 13 have their guards beside the code they test:
3D wall from the data, corrected only when D falls with height as a wall makes it (test_analysis::
test_3d_wall_comes_from_the_data_not_the_focal_plane, test_wall::test_analyze_corrects_for_a_wall_only_when_the_data_show_one), R from the metadata
or the data (test_analysis, test_pipeline::test_cli_analyze_and_missing_calibration), the field-of-view
correction on for camera tables (test_msd_cmd::test_msd_command_corrects_the_field_of_view_by_default_for_camera_tables),
calib_z.csv found beside the stack (test_gdpt), outputs in the working folder (test_msd_cmd, test_velocity).
"""
import ast
import re
from pathlib import Path

import pytest

from ptrack.twin import twin_exposure

ROOT = Path(__file__).resolve().parents[1]

#: "um" as a unit word (um, um^2, um², um/s, um&sup2;), not inside a longer name.
UM = re.compile(r"(?<![A-Za-z_&])um(\^2|²|/s|&sup2;)?(?![A-Za-z_])")
#: Strings that are unit tokens read from or written to file metadata (ImageJ's "um", OME's Z-um), not text.
UNIT_TOKENS = {"um", "Z-um"}
#: Files that still write "um", with how many literals: this list may only shrink. sim/render/datasets.py's are
#: the shipped datasets' own description texts (params.json, README.txt): changing them changes the shipped files.
PENDING = {"sim/render/datasets.py": 5}


def um_literals(path: Path) -> list[tuple[int, str]]:
    """(line, text) of the string literals of a module (docstrings excepted) that write a length unit as 'um'."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
            and n.value.strip() not in UNIT_TOKENS and UM.search(n.value)]


def test_the_unit_scan_finds_um_and_not_words_or_mu():
    assert UM.search("D (um^2/s)") and UM.search("1.2 um") and UM.search("um&sup2;") and UM.search("(um)")
    assert not UM.search("µm²/s") and not UM.search("medium") and not UM.search("sum of um_x")


def test_output_text_writes_micrometres_as_µm():
    hits = {}
    for p in sorted([*(ROOT / "ptrack").rglob("*.py"), *(ROOT / "sim").rglob("*.py")]):
        found = um_literals(p)
        if found:
            hits[str(p.relative_to(ROOT))] = found
    new = {k: v for k, v in hits.items() if len(v) > PENDING.get(k, 0)}
    assert not new, f"'um' written where 'µm' belongs (give µm): {new}"


@pytest.mark.parametrize("R, R_err, dt, want", [
    (0.1, 0.01, 0.1, (0.06, 0.1, 8)),            # a shutter open 60 % of the frame: R = 0.6 / 6
    (0.3, 0.01, 0.05, (0.05, 1 / 6, 8)),         # more blur than a full-frame exposure gives: capped at 1/6
    (0.02, 0.001, 0.1, (None, 0.0, 0)),          # too small to matter: instantaneous
    (0.1, 0.06, 0.1, (None, 0.0, 0)),            # not significant (under 2 errors)
])
def test_twin_renders_the_blur_it_measured_and_analyses_with_that_R(R, R_err, dt, want):
    e, r, n = twin_exposure({"R": R, "R_err": R_err}, dt)
    assert (r, n) == (pytest.approx(want[1]), want[2])
    if want[0] is None:
        assert e is None
    else:
        assert e == pytest.approx(want[0])
        assert r == pytest.approx(e / dt / 6)    # the R of a uniform exposure e in a frame dt
    assert twin_exposure(None, dt) == (None, 0.0, 0)


def test_no_analysis_module_switches_the_matplotlib_backend():
    """Plot code builds Figure objects (ptrack.plot.new_figure): no pyplot, no matplotlib.use outside the CLI, so a
    notebook's backend and open figures survive ptrack.compare.plot_comparison and the ptrack.plot functions."""
    offenders = []
    for p in sorted((ROOT / "ptrack").rglob("*.py")):
        if p.relative_to(ROOT).as_posix() == "ptrack/cli.py":          # the command line sets Agg once
            continue
        for n in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            mods = ([a.name for a in n.names] if isinstance(n, ast.Import)
                    else [f"{n.module}.{a.name}" for a in n.names] if isinstance(n, ast.ImportFrom) and n.module else [])
            if any(m.startswith("matplotlib.pyplot") for m in mods) or (
                    isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr in ("use", "switch_backend")
                    and isinstance(n.func.value, ast.Name) and n.func.value.id in ("matplotlib", "plt", "mpl")):
                offenders.append(f"{p.relative_to(ROOT)}:{n.lineno}")
    assert not offenders, offenders


def test_the_renderer_times_a_table_by_the_toolkits_frame_interval_rule():
    """sim.render.movie.frame_interval_of is ptrack.motion.frame_interval (t first, not the metadata first); the
    metadata value is kept only when t agrees with it, and 1 s only for a single frame without metadata."""
    import warnings

    import numpy as np

    from ptrack.table import make_table
    from sim.render.movie import frame_interval_of

    fr = np.repeat(np.arange(5), 2)
    t = make_table(fr, fr * 0.1, np.tile([0, 1], 5), np.zeros(10), np.zeros(10), meta={"frame_interval": 0.1})
    assert frame_interval_of(t) == 0.1                      # the exact metadata value, not t's rounding
    t.attrs["ptrack"]["frame_interval"] = 0.5               # metadata that contradicts t: t wins, with a warning
    with pytest.warns(UserWarning, match="'t' column gives 0.1 s"):
        assert frame_interval_of(t) == pytest.approx(0.1)
    one = make_table([0], [0.0], [0], [0.0], [0.0])
    one.attrs["ptrack"] = {}
    with pytest.warns(UserWarning, match="single-frame"):
        assert frame_interval_of(one) == 1.0
    one.attrs["ptrack"] = {"frame_interval": 0.2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert frame_interval_of(one) == 0.2


def test_the_twin_takes_the_implied_blur_from_the_one_rule():
    import numpy as np

    from ptrack.motion import brownian_tracks
    from ptrack.motion.tracks import motion_blur_from_data
    from ptrack.table import make_table
    from ptrack.twin import _implied_motion_blur

    p = brownian_tracks(60, 80, 8.6e-13, 0.1, 30e-9, 0.1, n_dims=2, seed=5)
    fr = np.tile(np.arange(80), 60)
    df = make_table(fr, fr * 0.1, np.repeat(np.arange(60), 80), p[..., 0].ravel(), p[..., 1].ravel(),
                    meta={"frame_interval": 0.1}, sigma_x=np.full(fr.size, 30e-9), sigma_y=np.full(fr.size, 30e-9))
    mb = _implied_motion_blur(df)
    R, err = motion_blur_from_data(df, n_boot=300, seed=0)
    assert (mb["R"], mb["R_err"]) == (R, err) and abs(R - 0.1) < 3 * err
    assert mb["sigma_loc_m"] == pytest.approx(30e-9)


def test_twin_reads_a_2d_table_with_z_0_as_2d():
    """A 2D table written with z = 0 in every row has no heights: the twin uses the given height for the wall
    hindrance (the one 3D rule, ptrack.motion.velocity.default_axes). Read as heights (z = 0: every particle at
    the wall), the hindrance was lost and the radius came out 409 nm for a true 300 nm (12 of its errors)."""
    import math

    from ptrack.constants import BOLTZMANN
    from ptrack.twin import infer_parameters
    from ptrack.velocity import drifting_tracks
    from ptrack.wall import parallel_ratio

    T, mu, R, h = 293.15, 1e-3, 300e-9, 600e-9
    D = BOLTZMANN * T / (6 * math.pi * mu * R) * float(parallel_ratio(h, R))   # a particle at height h
    t = drifting_tracks(60, 80, D, 0.1, 0.0, sigma=15e-9, seed=1,
                        meta={"frame_interval": 0.1, "pixel_size": 1e-7, "frame_shape": [200, 200]})
    t["z"] = 0.0
    p = infer_parameters(t, T, mu, height=h, n_boot=100)
    assert p["three_d"] is False
    assert p["wall_ratio"] == pytest.approx(float(parallel_ratio(h, p["radius_m"])), rel=1e-9)
    assert abs(p["radius_m"] - R) < 3 * p["radius_err_m"]
