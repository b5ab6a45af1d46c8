"""Field-dependent GDPT calibration (ptrack.gdpt.field) and the renderer's field-dependent focus (sim.render.optics).

Two independent image models, each with a calibration stack of 9 beads on a 3 x 3 grid and a movie of particles
elsewhere in the field, heights known:

* our renderer with field curvature + tilt (the focal surface bends 0.4 um at 10 um from the axis and tilts
  0.2 um along x): a single (bead-averaged) calibration reads z off by -0.3 .. +0.45 um depending on where
  the particle is; the field-dependent calibration must remove it;
* an astigmatic Gaussian written here (widths sigma_x,y(z) = s0 sqrt(1 + ((z -/+ c)/d)^2)) whose astigmatism c
  grows along x: a scale-type z error, not an offset.
"""
from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.special import erf

from ptrack.calibration import locate_frame_3d
from ptrack.errors import UserError
from ptrack.gdpt.field import (BASES, FieldCalibration, _fit_pages, build_field_calibration, correct_z,
                               field_basis, invert_reading, load_field_calibration, locate_frame_field)
from ptrack.motion import detection_scores, match_truth
from ptrack.table import make_table
from sim.render.camera import Camera
from sim.render.movie import expected_frames, render_frames
from sim.render.optics import Optics, sample_pixel_size

GRID = np.array([40.0, 128.0, 216.0])


def _grid(g):
    bx, by = np.meshgrid(g, g)
    return bx.ravel(), by.ravel()


def _scatter(n_frames, per_frame, lo, hi, zlim, min_dist, seed):
    """(frame, x_px, y_px, z) of isolated particles at random places and heights."""
    rng = np.random.default_rng(seed)
    rows = []
    for f in range(n_frames):
        pts = []
        while len(pts) < per_frame:
            p = rng.uniform(lo, hi, 2)
            if all(np.hypot(*(p - q)) > min_dist for q in pts):
                pts.append(p)
        rows += [(f, p[0], p[1], rng.uniform(-zlim, zlim)) for p in pts]
    return np.array(rows)


def _errors(found, truth, tol=3.0):
    """(x_px, y_px, z_true, z_read, z, truth row) of each found particle paired with the nearest true one of its
    frame within tol px (the toolkit's one rule, ptrack.motion.match_truth)."""
    t = pd.DataFrame({"frame": truth[:, 0].astype(int), "x_px": truth[:, 1], "y_px": truth[:, 2]})
    fi, ti = match_truth(found, t, max_px=tol)
    return np.column_stack([truth[ti, 1:4], found.loc[fi, "z_read"], found.loc[fi, "z"], ti])


def _locate_all(frames, fc):
    dfs = []
    for f, img in enumerate(frames):
        df = locate_frame_field(img, fc)
        df["frame"] = f
        dfs.append(df)
    return pd.concat(dfs, ignore_index=True)


# --- the renderer's field-dependent focus ---------------------------------------------------------------

def test_focal_shift_formula_and_default_off():
    o = Optics(field_curvature=0.4e-6, field_tilt=(0.2e-6, -0.1e-6), field_radius=10e-6)
    x = np.array([0.0, 10e-6, 0.0, -5e-6])
    y = np.array([0.0, 0.0, 10e-6, 5e-6])
    want = 0.4e-6 * (x ** 2 + y ** 2) / 1e-10 + 0.2e-6 * x / 1e-5 - 0.1e-6 * y / 1e-5
    assert np.allclose(o.focal_shift(x, y), want, rtol=0, atol=1e-15)
    # the axis: field_center, else the centre the renderer passes
    assert np.allclose(o.focal_shift(x + 3e-6, y, center=(3e-6, 0.0)), want, atol=1e-15)
    o2 = Optics(field_curvature=0.4e-6, field_radius=10e-6, field_center=(1e-6, 2e-6))
    assert o2.focal_shift(1e-6, 2e-6, center=(0.0, 0.0)) == 0.0
    flat = Optics()
    assert not flat.field_dependent and np.all(flat.focal_shift(x, y) == 0.0)
    # params.json of existing renders unchanged; a field-dependent one round-trips
    assert set(flat.to_dict()) == {"na", "wavelength", "medium_index", "immersion_index", "magnification",
                                   "astigmatism", "psf_z_step", "psf_margin"}
    assert Optics(**o.to_dict()) == o
    for bad in ({"field_tilt": 3.0}, {"field_curvature": float("nan")}, {"field_radius": 0.0},
                {"field_center": (1.0, float("inf"))}):
        with pytest.raises(UserError):
            Optics(**bad)


def test_renderer_field_curvature_is_a_defocus_offset():
    """With the focus bent, a particle renders exactly as one at z - z_f(x, y) in a flat field; off = identical."""
    o = Optics(astigmatism=0.12e-6, field_curvature=0.5e-6, field_tilt=(0.2e-6, 0.0), field_radius=8e-6)
    flat = Optics(astigmatism=0.12e-6)
    cam = Camera()
    px = sample_pixel_size(o, cam.pixel_pitch)
    H, W = 96, 128
    x = np.array([10.0, 64.0, 115.0]) * px
    y = np.array([12.0, 48.0, 80.0]) * px
    z = np.array([0.8e-6, -0.5e-6, 0.2e-6])
    meta = {"frame_interval": 0.1}
    tb = make_table([0, 0, 0], [0.0] * 3, [0, 1, 2], x, y, z, meta=meta)
    zf = o.focal_shift(x, y, center=((W - 1) / 2 * px, (H - 1) / 2 * px))
    assert np.ptp(zf) > 0.2e-6
    got = next(expected_frames(tb, (H, W), o, cam))
    ref = next(expected_frames(make_table([0, 0, 0], [0.0] * 3, [0, 1, 2], x, y, z - zf, meta=meta), (H, W), flat, cam))
    assert np.allclose(got, ref, rtol=1e-6, atol=1e-6 * ref.max())
    # and it is not the flat render
    plain = next(expected_frames(tb, (H, W), flat, cam))
    assert np.abs(plain - got).max() > 0.05 * (plain.max() - cam.background)
    # off (explicitly zero) = the default, bit for bit, noise included
    a = next(render_frames(tb, (H, W), Optics(astigmatism=0.12e-6, field_curvature=0.0, field_tilt=(0, 0)), cam, seed=3))
    b = next(render_frames(tb, (H, W), flat, cam, seed=3))
    assert np.array_equal(a, b)


def test_calibration_page_off_axis_sees_the_focal_shift():
    """A calibration bead away from the page centre is rendered at its defocus on the curved focal surface."""
    from sim.render.calibration import calibration_images

    o = Optics(field_curvature=0.5e-6, field_radius=5e-6)
    cam = Camera()
    px = sample_pixel_size(o, cam.pixel_pitch)
    H = W = 64
    pos = (12.0, 50.0)
    zf = float(o.focal_shift(pos[0] * px, pos[1] * px, center=((W - 1) / 2 * px, (H - 1) / 2 * px)))
    assert zf > 0.1e-6
    z = np.array([-1e-6, 0.0, 1e-6])
    a = np.stack(list(calibration_images(z, (H, W), o, cam, position=pos, noise=False)))
    b = np.stack(list(calibration_images(z - zf, (H, W), Optics(), cam, position=pos, noise=False)))
    assert np.allclose(a, b, rtol=1e-9, atol=1e-9)
    c = np.stack(list(calibration_images(z, (H, W), Optics(), cam, position=pos, noise=False)))
    assert np.abs(a - c).max() > 0.05 * (c.max() - cam.background)


# --- the correction itself (no images) ------------------------------------------------------------------

def test_invert_reading_exact_for_linear_response():
    """Reading zr = a + (1 + b) z is inverted exactly, inside and beyond the tabulated heights."""
    z = np.linspace(-2e-6, 2e-6, 21)
    a = np.array([0.3e-6, -0.2e-6, 0.0])
    b = np.array([0.1, -0.15, 0.0])
    D = a[:, None] + b[:, None] * z[None, :]
    zt = np.array([1.234e-6, -1.9e-6, 2.5e-6])
    zr = a + (1 + b) * zt
    assert np.allclose(invert_reading(z, D, zr), zt, rtol=0, atol=1e-15)
    assert np.isnan(invert_reading(z, D, np.array([np.nan, 0.0, 0.0]))[0])


def test_field_surface_fit_recovers_tilt_and_curvature():
    """Per-page errors that follow a known tilt + curvature surface are fitted exactly and predicted between beads."""
    bx, by = _grid(GRID)
    K = 7
    z = np.linspace(-1e-6, 1e-6, K)
    origin, scale = (128.0, 128.0), 125.0
    U = np.repeat(((bx - origin[0]) / scale)[:, None], K, 1)
    V = np.repeat(((by - origin[1]) / scale)[:, None], K, 1)
    true = np.stack([0.1e-6 + 0.02 * z, 0.3e-6 * np.ones(K), -0.1e-6 * np.ones(K), 0.25e-6 + 0.05 * z], 1)   # (K, 4)
    E = np.einsum("bkp,kp->bk", np.stack([field_basis(U[:, k], V[:, k], "tilt+curvature") for k in range(K)], 1), true)
    E[2, 3] = np.nan                                     # a page one bead was not read on
    coef = _fit_pages(U, V, E, "tilt+curvature")
    assert np.allclose(coef, true, rtol=0, atol=1e-18)
    fc = FieldCalibration(None, z, np.c_[bx, by], E, "tilt+curvature", coef, origin, scale)
    xq, yq = np.array([70.0, 180.0]), np.array([150.0, 60.0])
    uq, vq = (xq - 128) / 125, (yq - 128) / 125
    want = field_basis(uq, vq, "tilt+curvature") @ true.T
    assert np.allclose(fc.reading_error(xq, yq), want, atol=1e-18)
    # a particle at 0.37 um there reads 0.37 um + d(0.37 um); corrected back
    zt = 0.37e-6
    zr = zt + np.array([np.interp(zt, z, w) for w in want])
    assert np.allclose(fc.correct(xq, yq, zr), zt, atol=1e-12)
    with pytest.raises(UserError):
        field_basis([0.0], [0.0], "cubic")
    assert BASES["quadratic"] == 6


# --- end to end: the renderer's field curvature -----------------------------------------------------------

@pytest.fixture(scope="module")
def curved_field():
    """Calibration stack (9 beads, +-3 um / 0.2 um) and a 6-frame movie, with a curved and tilted focal surface."""
    o = Optics(astigmatism=0.12e-6, field_curvature=0.4e-6, field_tilt=(0.2e-6, 0.0), field_radius=10e-6)
    cam = Camera(photons=20000)
    px = sample_pixel_size(o, cam.pixel_pitch)
    H = W = 256
    bx, by = _grid(GRID)
    zk = np.round(np.arange(-3e-6, 3e-6 + 1e-9, 0.2e-6), 12)
    K, B = len(zk), len(bx)
    fr = np.repeat(np.arange(K), B)
    stack_tb = make_table(fr, fr * 1.0, np.tile(np.arange(B), K), np.tile(bx, K) * px, np.tile(by, K) * px,
                          np.repeat(zk, B), meta={"frame_interval": 1.0})
    stack = np.stack(list(render_frames(stack_tb, (H, W), o, cam, seed=1)))
    truth = _scatter(6, 6, 30.0, 226.0, 2.2e-6, 60.0, seed=5)
    tb = make_table(truth[:, 0].astype(int), truth[:, 0], np.arange(len(truth)), truth[:, 1] * px, truth[:, 2] * px,
                    truth[:, 3], meta={"frame_interval": 1.0})
    frames = list(render_frames(tb, (H, W), o, cam, seed=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fc = build_field_calibration(stack, zk, px)
    shift = o.focal_shift(truth[:, 1] * px, truth[:, 2] * px, center=((W - 1) / 2 * px, (H - 1) / 2 * px))
    return fc, frames, truth, shift, px, stack, zk


def test_field_calibration_removes_field_curvature_bias(curved_field):
    fc, frames, truth, shift, px, _, _ = curved_field
    assert fc.info["n_beads"] == 9 and fc.basis == "quadratic"
    found = _locate_all(frames, fc)
    m = _errors(found, truth)
    assert len(m) >= 0.95 * len(truth)
    e_single = m[:, 3] - m[:, 2]
    e_field = m[:, 4] - m[:, 2]
    # the single calibration reads -z_f(x, y) + its mean over the beads: a bias that varies with position
    zf = shift[m[:, 5].astype(int)]                       # the focal shift at each paired true particle
    assert np.ptp(e_single) > 0.5e-6
    assert np.corrcoef(e_single, -zf)[0, 1] > 0.95
    assert np.sqrt(np.mean(e_single ** 2)) > 0.15e-6
    # the field-dependent calibration removes it: no trend with the focal shift, RMSE < 50 nm (< 0.9 % of depth)
    rms = np.sqrt(np.mean(e_field ** 2))
    assert rms < 50e-9, rms
    assert abs(np.mean(e_field)) < 20e-9
    assert abs(np.polyfit(zf, e_field, 1)[0]) < 0.1
    # the model's own error estimate between beads is of the same size
    assert fc.info["loo_rms"] < 60e-9


def test_correct_z_on_an_si_table(curved_field):
    """A table with x, y in m (no px columns) is corrected with the calibration's pixel size."""
    fc, frames, truth, shift, px, _, _ = curved_field
    df = locate_frame_3d(frames[0], fc.calib)
    a = correct_z(df, fc)
    si = pd.DataFrame({"x": df["x_px"] * px, "y": df["y_px"] * px, "z": df["z"]})
    b = correct_z(si, fc)
    assert np.allclose(a["z"], b["z"], atol=1e-12) and np.allclose(b["z_read"], df["z"])
    with pytest.raises(UserError):
        correct_z(pd.DataFrame({"z": [0.0]}), fc)


def test_load_field_calibration_from_a_file(tmp_path):
    """A stack written as a TIFF with calib_z.csv beside it gives the same field map as the stack in memory."""
    import tifffile

    rng = np.random.default_rng(3)
    bx = np.array([30.0, 130.0, 80.0, 30.0, 130.0])
    by = np.array([30.0, 30.0, 80.0, 130.0, 130.0])
    zk = np.round(np.arange(-0.8e-6, 0.8e-6 + 1e-9, 0.1e-6), 12)
    stack = np.stack([_gauss_frame(bx, by, np.full(5, zi), (160, 160), rng) for zi in zk])
    tifffile.imwrite(tmp_path / "calib.tif", stack, imagej=True)
    with open(tmp_path / "calib_z.csv", "w") as fh:
        fh.write("page,z\n" + "".join(f"{i},{float(v)!r}\n" for i, v in enumerate(zk)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fl = load_field_calibration(tmp_path / "calib.tif", pixel_size=1e-7)
        fm = build_field_calibration(stack, zk, 1e-7, calib=fl.calib)
    assert fl.basis == fm.basis == "tilt+curvature" and fl.info["n_beads"] == 5
    assert np.allclose(fl.coef, fm.coef, rtol=0, atol=1e-12)
    assert np.allclose(fl.z, zk)


def test_one_bead_is_refused():
    o = Optics(astigmatism=0.12e-6)
    cam = Camera(photons=20000)
    px = sample_pixel_size(o, cam.pixel_pitch)
    zk = np.round(np.arange(-1e-6, 1e-6 + 1e-9, 0.25e-6), 12)
    tb = make_table(np.arange(len(zk)), np.arange(len(zk)) * 1.0, np.zeros(len(zk), int), np.full(len(zk), 32 * px),
                    np.full(len(zk), 32 * px), zk, meta={"frame_interval": 1.0})
    stack = np.stack(list(render_frames(tb, (64, 64), o, cam, seed=1)))
    with pytest.raises(UserError, match="several places"):
        build_field_calibration(stack, zk, px)


# --- end to end: independent optics (astigmatism growing along x) -----------------------------------------

S0, D0 = 1.3, 0.5e-6            # in-focus width (px) and depth scale (m) of the Gaussian model


def _astig(x_px):
    """Astigmatic focal offset c (m) of the Gaussian model: 0.15 um at the left bead column, 0.6 um at the right."""
    return 0.375e-6 + 0.225e-6 * (np.asarray(x_px) - 100.0) / 70.0


def _gauss_frame(xs, ys, zs, shape, rng, photons=8000.0, bg=15.0):
    """Pixel-integrated astigmatic Gaussians (widths s0 sqrt(1 + ((z -/+ c(x))/d)^2)), Poisson noise, offset 100."""
    H, W = shape
    c = _astig(xs)
    sx = S0 * np.sqrt(1 + ((zs - c) / D0) ** 2)
    sy = S0 * np.sqrt(1 + ((zs + c) / D0) ** 2)
    ex = 0.5 * (erf((np.arange(W + 1)[None, :] - 0.5 - xs[:, None]) / (np.sqrt(2) * sx[:, None])))
    ey = 0.5 * (erf((np.arange(H + 1)[None, :] - 0.5 - ys[:, None]) / (np.sqrt(2) * sy[:, None])))
    px_x, px_y = np.diff(ex, axis=1), np.diff(ey, axis=1)                     # (N, W), (N, H)
    mu = bg + photons * px_y.T @ px_x
    return (rng.poisson(mu) + 100).astype(np.uint16)


def test_field_calibration_independent_astigmatic_gaussian():
    rng = np.random.default_rng(11)
    shape = (200, 200)
    bx, by = _grid(np.array([30.0, 100.0, 170.0]))
    zk = np.round(np.arange(-1.5e-6, 1.5e-6 + 1e-9, 0.1e-6), 12)
    stack = np.stack([_gauss_frame(bx, by, np.full(len(bx), zi), shape, rng) for zi in zk])
    truth = _scatter(6, 5, 25.0, 175.0, 1.1e-6, 40.0, seed=7)
    frames = [_gauss_frame(truth[truth[:, 0] == f, 1], truth[truth[:, 0] == f, 2], truth[truth[:, 0] == f, 3],
                           shape, rng) for f in range(6)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fc = build_field_calibration(stack, zk, 1e-7)
    assert fc.info["n_beads"] == 9
    # the stack itself shows the field dependence: at the same height the left and right bead columns read
    # up to ~0.4 um apart on the averaged templates
    left, right = fc.bead_xy[:, 0] < 60, fc.bead_xy[:, 0] > 140
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        split = np.nanmean(fc.bead_err[left], 0) - np.nanmean(fc.bead_err[right], 0)
    assert np.nanmax(np.abs(split)) > 0.25e-6
    m = _errors(_locate_all(frames, fc), truth)
    assert len(m) >= 0.95 * len(truth)
    e_single = m[:, 3] - m[:, 2]
    e_field = m[:, 4] - m[:, 2]
    rms_single = np.sqrt(np.mean(e_single ** 2))
    rms_field = np.sqrt(np.mean(e_field ** 2))
    assert rms_single > 50e-9
    assert rms_field < 0.4 * rms_single and rms_field < 30e-9, (rms_single, rms_field)
    # the worst particle: off by a good fraction of a micrometre before, a few tens of nm after
    assert np.abs(e_single).max() > 0.1e-6 and np.abs(e_field).max() < 0.6 * np.abs(e_single).max()


# --- through ptrack track --calib STACK --field-calib ----------------------------------------------------------

def test_track_field_calib_end_to_end(tmp_path, curved_field):
    """`ptrack track --calib calib.tif --field-calib` removes the field-curvature bias of the plain calibration."""
    import json

    import tifffile

    from ptrack.cli import main
    from ptrack.table import read_table

    fc, _, _, _, px, stack, zk = curved_field
    o = Optics(astigmatism=0.12e-6, field_curvature=0.4e-6, field_tilt=(0.2e-6, 0.0), field_radius=10e-6)
    cam = Camera(photons=20000)
    H = W = 256
    # 12 particles held still over 6 frames (tracks to link), spread over the field and the depth
    rng = np.random.default_rng(7)
    gx, gy = np.meshgrid(np.linspace(40, 216, 4), np.linspace(50, 206, 3))
    x0, y0 = gx.ravel() + rng.uniform(-5, 5, 12), gy.ravel() + rng.uniform(-5, 5, 12)
    z0 = rng.uniform(-2e-6, 2e-6, 12)
    n_f = 6
    fr = np.repeat(np.arange(n_f), 12)
    tb = make_table(fr, fr * 0.1, np.tile(np.arange(12), n_f), np.tile(x0, n_f) * px, np.tile(y0, n_f) * px,
                    np.tile(z0, n_f), meta={"frame_interval": 0.1})
    movie = np.stack(list(render_frames(tb, (H, W), o, cam, seed=3)))
    tifffile.imwrite(tmp_path / "movie.tif", movie, imagej=True, metadata={"axes": "TYX"})
    tifffile.imwrite(tmp_path / "calib.tif", stack, imagej=True, metadata={"axes": "ZYX"})
    with open(tmp_path / "calib_z.csv", "w") as fh:
        fh.write("page,z\n" + "".join(f"{i},{float(v)!r}\n" for i, v in enumerate(zk)))
    shift = o.focal_shift(x0 * px, y0 * px, center=((W - 1) / 2 * px, (H - 1) / 2 * px))
    rms = {}
    for name, extra in (("plain", []), ("field", ["--field-calib"])):
        out, js = tmp_path / f"{name}.parquet", tmp_path / f"{name}.json"
        args = ["track", str(tmp_path / "movie.tif"), "--calib", str(tmp_path / "calib.tif"), "--pixel-size",
                repr(px), "--frame-interval", "0.1", "--out", str(out), "--json", str(js), *extra]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert main(args) == 0
        t = read_table(out)
        g = t.groupby("particle")[["x", "y", "z"]].mean()
        # each track's mean position paired with the nearest true particle within 3 px (ptrack.motion.match_truth)
        fi, ti = detection_scores(np.c_[g["x"].to_numpy(), g["y"].to_numpy()] / px, np.c_[x0, y0], max_px=3.0)["pairs"]
        assert len(fi) >= 11
        err = g["z"].to_numpy()[fi] - z0[ti]
        rms[name] = float(np.sqrt(np.mean(err ** 2)))
        s = json.loads(js.read_text())
        # GDPT's own split of the z stage: this movie's share only (its parts cannot exceed the stage)
        st = s["stage_times_s"]
        parts = [v for k, v in st.items() if k.startswith("z.")]
        assert "z.match" in st and all(v >= 0 for v in parts) and sum(parts) <= st["z"] * 1.01 + 1e-3, st
        if name == "field":
            assert s["calibration"]["field"]["n_beads"] == 9
            assert "field_calibration" in s["stage_times_s"]
            # z_read is kept beside the corrected z
            assert "z" in t
    # the plain calibration carries the focal surface (spread > 0.5 um over these positions); the field one does not
    assert np.ptp(shift) > 0.5e-6
    assert rms["plain"] > 0.15e-6 and rms["field"] < 60e-9, rms
