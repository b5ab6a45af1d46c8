"""Tests of the synthetic microscope (sim.render): optics against analytic results,
camera statistics against the noise model, geometry against ground truth, files
and metadata, determinism, CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy.optimize import least_squares
from scipy.special import j1

from ptrack.cli import main
from ptrack.table import make_table, read_table
from sim.render import (Camera, Optics, expected_frames, expose, localisation_crlb, psf_image, render_calibration,
                        render_frames, render_movie)
from sim.render.optics import sample_pixel_size

PX = 6.5e-6 / 63.0  # default sample pixel, m


def one_particle(x_px, y_px, z=0.0, frames=1, dt=0.1, vx=0.0, vy=0.0, **cols):
    f = np.arange(frames)
    return make_table(f, f * dt, np.zeros(frames, int), (x_px + vx * f) * PX * np.ones(frames),
                      (y_px + vy * f) * PX * np.ones(frames), np.full(frames, z), meta={"frame_interval": dt},
                      **{k: np.full(frames, v) for k, v in cols.items()})


# ---------------------------------------------------------------- optics

def test_airy_first_dark_ring_at_0p61_lambda_over_na():
    for na, wl in [(0.75, 519e-9), (0.5, 600e-9)]:
        o = Optics(na=na, wavelength=wl)
        os_ = 16
        img = psf_image(o, PX, 0.0, size=48, oversample=os_, pixel_integrated=False)
        c = 24 * os_
        # azimuthal average of the point-sampled intensity around the source
        yy, xx = np.indices(img.shape)
        r = np.hypot(yy - c, xx - c) / os_ * PX
        bins = np.arange(0, 1.5 * 0.61 * wl / na, PX / os_ / 2)
        idx = np.digitize(r.ravel(), bins)
        prof = np.bincount(idx, img.ravel(), minlength=len(bins) + 1)[1:len(bins)] / np.maximum(
            np.bincount(idx, minlength=len(bins) + 1)[1:len(bins)], 1)
        rmid = 0.5 * (bins[1:] + bins[:-1])
        k = np.argmin(prof[len(prof) // 3:]) + len(prof) // 3
        expected = 0.61 * wl / na
        assert abs(rmid[k] - expected) / expected < 0.02, (rmid[k], expected)
        # and the whole profile is the Airy pattern [2 J1(v)/v]^2
        prof_ax = img[c, c:c + 6 * os_] / img[c, c]
        v = 2 * np.pi * na * (np.arange(6 * os_) / os_ * PX) / wl
        airy = np.ones_like(v)
        airy[1:] = (2 * j1(v[1:]) / v[1:]) ** 2
        assert np.max(np.abs(prof_ax - airy)) < 2e-3


def test_flux_conserved_and_peak_where_truth_says():
    cam = Camera(photons=12345.0, background=0.0)
    for z, radius in [(0.0, 0.0), (2e-6, 250e-9), (-1.5e-6, 0.0)]:
        t = one_particle(70.3, 67.8, z=z)  # the patch (PSF tails included) lies inside the frame
        img = next(expected_frames(t, (140, 140), Optics(astigmatism=1e-7), cam, radius=radius))
        assert img.sum() == pytest.approx(12345.0, rel=1e-6)
        assert img.min() > -1e-6 * img.max()  # an intensity, no ringing below zero worth the name
    # in focus the brightest pixel is the one containing the particle
    img = next(expected_frames(one_particle(40.3, 37.8), (80, 80), Optics(), cam))
    iy, ix = np.unravel_index(np.argmax(img), img.shape)
    assert (iy, ix) == (38, 40)


def _moments(img, level=0.0):
    """Centroid and rms widths (px); ``level``: fraction of the peak subtracted (clipped) first,
    to measure the core of the image without the far Airy tails."""
    img = np.clip(img - level * img.max(), 0, None)
    yy, xx = np.indices(img.shape)
    w = img / img.sum()
    mx, my = (w * xx).sum(), (w * yy).sum()
    return mx, my, np.sqrt((w * (xx - mx) ** 2).sum()), np.sqrt((w * (yy - my) ** 2).sum())


def test_astigmatism_swaps_x_and_y_widths_across_focus():
    o = Optics(astigmatism=1.2e-7)
    cam = Camera(photons=1e4, background=0.0)
    dz = 1.0e-6
    above = next(expected_frames(one_particle(80, 80, z=dz), (160, 160), o, cam))
    below = next(expected_frames(one_particle(80, 80, z=-dz), (160, 160), o, cam))
    _, _, sxa, sya = _moments(above, 0.05)
    _, _, sxb, syb = _moments(below, 0.05)
    # elongated along different axes on the two sides of focus
    assert max(sxa, sya) > 1.3 * min(sxa, sya) and (sxa - sya) * (sxb - syb) < 0
    assert sxa == pytest.approx(syb, rel=0.02) and sya == pytest.approx(sxb, rel=0.02)  # mirror images
    # without astigmatism the defocused image is round and the same on both sides
    o0 = Optics()
    a0 = next(expected_frames(one_particle(80, 80, z=dz), (160, 160), o0, cam))
    _, _, sx0, sy0 = _moments(a0, 0.05)
    assert sx0 == pytest.approx(sy0, rel=1e-6)


def test_defocus_widens_the_image_by_the_geometric_cone():
    o = Optics()
    cam = Camera(photons=1e4, background=0.0)
    img = next(expected_frames(one_particle(64, 64, z=6e-6), (128, 128), o, cam))
    # the defocused image is a disk of radius ~ |dz| tan(theta) (plus diffraction): 2nd moment of a
    # uniform disk of radius a is a/2 per axis
    a = 6e-6 * o.half_angle_tan / PX
    _, _, sx, sy = _moments(img)
    assert sx == pytest.approx(a / 2, rel=0.15) and sy == pytest.approx(sx, rel=1e-6)


def test_far_defocused_particle_has_its_own_patch_and_keeps_flux():
    cam = Camera(photons=1e4, background=0.0)
    f = np.zeros(2, int)
    both = make_table(f, f * 0.1, [0, 1], [60 * PX, 200 * PX], [60 * PX, 200 * PX], [0.0, 12e-6],
                      meta={"frame_interval": 0.1})
    img = next(expected_frames(both, (400, 400), None, cam))
    assert img.sum() == pytest.approx(2e4, rel=1e-6)
    alone = next(expected_frames(both.iloc[:1], (400, 400), None, cam))
    win = (slice(45, 76), slice(45, 76))  # outside the far particle's patch
    np.testing.assert_allclose(img[win], alone[win], rtol=1e-6, atol=1e-9)
    # the far particle is a wide faint disk of radius ~ 12 um tan(theta)
    far = img - alone
    r = 12e-6 * Optics().half_angle_tan / PX
    yy, xx = np.indices(far.shape)
    inside = np.hypot(yy - 200, xx - 200) < 0.8 * r
    assert far[inside].mean() == pytest.approx(1e4 / (np.pi * r * r), rel=0.3)
    assert far.max() < 0.01 * alone.max()


def test_particle_size_blurs_and_keeps_flux():
    cam = Camera(photons=1e4, background=0.0)
    small = next(expected_frames(one_particle(60, 60), (120, 120), None, cam, radius=0.0))
    big = next(expected_frames(one_particle(60, 60), (120, 120), None, cam, radius=1.0e-6))
    assert big.sum() == pytest.approx(small.sum(), rel=1e-6)
    # independent check in real space: the point image convolved with the projected ball
    # (density ~ sqrt(R^2 - r^2)), the kernel integrated over sub-pixel points
    from scipy.signal import fftconvolve

    R = 1.0e-6 / PX
    sub = 9
    o = (np.arange(sub) + 0.5) / sub - 0.5
    m = int(np.ceil(R)) + 1
    yy, xx = np.mgrid[-m:m + 1, -m:m + 1]
    r2 = (xx[..., None, None] + o[None, None, None, :]) ** 2 + (yy[..., None, None] + o[None, None, :, None]) ** 2
    K = np.sqrt(np.clip(R * R - r2, 0, None)).mean(axis=(-1, -2))
    K /= K.sum()
    ref = fftconvolve(small, K, mode="same")
    win = (slice(40, 81), slice(40, 81))
    assert np.max(np.abs(big[win] - ref[win])) < 0.01 * ref[win].max()
    assert big.max() < 0.5 * small.max()


# ---------------------------------------------------------------- camera

@pytest.mark.parametrize("photons", [30.0, 3000.0])
def test_camera_mean_and_variance_match_model(photons):
    cam = Camera(quantum_efficiency=0.7, read_noise=1.6, gain=2.2, offset=100.0)
    rng = np.random.default_rng(7)
    img = expose(np.full((400, 400), photons), cam, rng).astype(float)
    e = cam.quantum_efficiency * photons
    mean = cam.gain * e + cam.offset
    var = cam.gain ** 2 * (e + cam.read_noise ** 2) + 1.0 / 12.0  # + rounding to whole ADU
    n = img.size
    assert abs(img.mean() - mean) < 5 * np.sqrt(var / n)
    assert abs(img.var() - var) < 5 * var * np.sqrt(2.0 / n)


def test_camera_clips_to_bit_depth():
    cam = Camera(bit_depth=12)
    img = expose(np.full((10, 10), 1e7), cam, np.random.default_rng(0))
    assert img.dtype == np.uint16 and img.max() == 4095


def test_frames_mean_matches_expected_image():
    t = one_particle(20.2, 18.6, z=0.3e-6, frames=200)
    cam = Camera(photons=2e4, background=10.0)
    exp_img = next(expected_frames(t.iloc[:1], (40, 40), None, cam))
    frames = np.array(list(render_frames(t, (40, 40), None, cam, seed=3)), dtype=float)
    mean = frames.mean(axis=0)
    pred = cam.expected_adu(exp_img)
    sd = np.sqrt(cam.gain ** 2 * (cam.quantum_efficiency * exp_img + cam.read_noise ** 2) / len(frames))
    assert np.max(np.abs(mean - pred) / sd) < 5.0


# ---------------------------------------------------------------- geometry / localisation

def _airy_model(p, xx, yy, na=0.75, wl=519e-9, sub=8):
    """Pixel-integrated Airy disk (midpoint rule, sub x sub points per pixel) + constant background."""
    A, x0, y0, b = p
    o = (np.arange(sub) + 0.5) / sub - 0.5
    dx = xx[..., None, None] + o[None, None, None, :] - x0
    dy = yy[..., None, None] + o[None, None, :, None] - y0
    v = 2 * np.pi * na * np.hypot(dx, dy) * PX / wl
    v = np.maximum(v, 1e-9)
    return A * ((2 * j1(v) / v) ** 2).mean(axis=(-1, -2)) + b


def test_independent_fit_finds_ground_truth_within_0p01_px(tmp_path):
    rng = np.random.default_rng(11)
    cam = Camera(photons=2e6, background=20.0)
    n = 6
    xs, ys = 12.0 + rng.uniform(0, 1, n), 14.0 + rng.uniform(0, 1, n)
    f = np.arange(n)
    t = make_table(f, f * 0.1, f, xs * PX, ys * PX, np.zeros(n), meta={"frame_interval": 0.1})
    paths = render_movie(t, tmp_path, (28, 28), None, cam, seed=5, progress=False)
    truth = read_table(paths["truth"])
    movie = tifffile.imread(paths["movie"]).astype(float)
    errs = []
    for k in range(n):
        row = truth[truth["frame"] == k].iloc[0]
        cx, cy = int(round(row["x_px"])), int(round(row["y_px"]))
        yy, xx = np.mgrid[cy - 8:cy + 9, cx - 8:cx + 9]
        img = movie[k][yy, xx]
        p0 = [img.max() - img.min(), cx + 0.2, cy - 0.2, img.min()]
        w = 1.0 / np.sqrt(np.maximum(img - cam.offset, 1.0) * cam.gain + 1.0)
        fit = least_squares(lambda p: ((_airy_model(p, xx, yy) - img) * w).ravel(), p0, x_scale=[1e4, 0.1, 0.1, 10])
        errs.append((fit.x[1] - row["x_px"], fit.x[2] - row["y_px"]))
        assert row["x_px"] == pytest.approx(xs[k]) and row["y_px"] == pytest.approx(ys[k])
    errs = np.array(errs)
    assert np.max(np.abs(errs)) < 0.01, errs


def test_motion_blur_is_centred_on_truth_and_elongated():
    cam = Camera(photons=1e5, background=0.0)
    t = one_particle(72.0, 80.0, frames=3, vx=8.0)  # 8 px per frame along x, exposure = frame interval
    still = list(expected_frames(t, (160, 160), None, cam))[1]
    blur = list(expected_frames(t, (160, 160), None, cam, motion_blur_substeps=16))[1]
    mx, my, sx, sy = _moments(blur)
    assert mx == pytest.approx(80.0, abs=0.02) and my == pytest.approx(80.0, abs=0.02)
    assert blur.sum() == pytest.approx(1e5, rel=1e-6)
    # the blurred frame is the mean of still images at the 16 sub-positions spread over the exposure
    xs = 80.0 + 8.0 * ((np.arange(16) + 0.5) / 16 - 0.5)
    f = np.arange(16)
    subs = make_table(f, f * 0.1, f, xs * PX, np.full(16, 80.0 * PX), np.zeros(16), meta={"frame_interval": 0.1})
    ref = np.mean(list(expected_frames(subs, (160, 160), None, cam)), axis=0)
    win = (slice(52, 109), slice(52, 109))  # inside both patches (their far tails wrap differently)
    np.testing.assert_allclose(blur[win], ref[win], atol=3e-4 * blur.max())
    assert blur.max() < 0.6 * still.max()


def test_brightfield_particles_are_dark_on_bright_background():
    cam = Camera(photons=2e4, background=1000.0)
    img = next(render_frames(one_particle(20.0, 22.0), (40, 40), None, cam, brightfield=True, seed=0)).astype(float)
    assert np.median(img) > cam.expected_adu(900)
    iy, ix = np.unravel_index(np.argmin(img), img.shape)
    assert abs(ix - 20) <= 1 and abs(iy - 22) <= 1


def test_nan_z_renders_in_focus_and_focal_plane_shifts_defocus():
    cam = Camera(photons=1e4, background=0.0)
    a = next(expected_frames(one_particle(16, 16, z=np.nan), (32, 32), None, cam))
    b = next(expected_frames(one_particle(16, 16, z=0.0), (32, 32), None, cam))
    c = next(expected_frames(one_particle(16, 16, z=1e-6), (32, 32), None, cam, focal_plane=1e-6))
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(c, b, atol=1e-9)


# ---------------------------------------------------------------- files, metadata, determinism

def _small_table(n_frames=5, n=4, seed=0):
    rng = np.random.default_rng(seed)
    f = np.repeat(np.arange(n_frames), n)
    p = np.tile(np.arange(n), n_frames)
    x = rng.uniform(5, 40, n * n_frames) * PX
    y = rng.uniform(5, 30, n * n_frames) * PX
    z = rng.uniform(-1e-6, 1e-6, n * n_frames)
    return make_table(f, f * 0.25, p, x, y, z, meta={"frame_interval": 0.25})


def test_movie_metadata_pixel_size_and_frame_interval(tmp_path):
    paths = render_movie(_small_table(), tmp_path / "m", (36, 48), seed=1, progress=False, compression="zlib")
    with tifffile.TiffFile(paths["movie"]) as tf:
        assert len(tf.pages) == 5 and tf.pages[0].shape == (36, 48) and tf.pages[0].dtype == np.uint16
        ij = tf.imagej_metadata
        assert ij["finterval"] == pytest.approx(0.25)
        assert ij["unit"] == "um"
        num, den = tf.pages[0].tags["XResolution"].value
        assert den / num * 1e-6 == pytest.approx(PX, rel=1e-6)  # um per pixel -> m
        info = json.loads(ij["Info"])
        assert info["pixel_size"] == pytest.approx(PX, rel=1e-12) and info["frame_interval"] == 0.25
    truth = read_table(paths["truth"])
    assert truth.attrs["ptrack"]["pixel_size"] == pytest.approx(PX)
    assert {"x_px", "y_px", "photons", "signal", "defocus", "in_frame"} <= set(truth.columns)
    np.testing.assert_allclose(truth["x_px"] * PX, truth["x"], rtol=1e-12)
    params = json.loads(paths["params"].read_text())
    assert params["optics"]["na"] == 0.75 and params["n_frames"] == 5


def test_same_seed_byte_identical_other_seed_differs(tmp_path):
    t = _small_table()
    a = render_movie(t, tmp_path / "a", (36, 48), seed=42, progress=False)
    b = render_movie(t, tmp_path / "b", (36, 48), seed=42, progress=False)
    c = render_movie(t, tmp_path / "c", (36, 48), seed=43, progress=False)
    assert a["movie"].read_bytes() == b["movie"].read_bytes()
    assert a["movie"].read_bytes() != c["movie"].read_bytes()
    fa = list(render_frames(t, (36, 48), seed=42))
    np.testing.assert_array_equal(np.array(fa), tifffile.imread(a["movie"]))


def test_movie_pages_cover_frame_gaps(tmp_path):
    t = _small_table(n_frames=6)
    t = t[t["frame"] != 3].copy()
    t.attrs["ptrack"] = {"frame_interval": 0.25}
    paths = render_movie(t, tmp_path, (36, 48), seed=0, progress=False)
    assert len(tifffile.TiffFile(paths["movie"]).pages) == 6
    assert len(list(render_frames(t, (36, 48)))) == 5


def test_calibration_stack_files_and_content(tmp_path):
    o = Optics(astigmatism=1e-7)
    cam = Camera(photons=5e4, background=5.0)
    paths = render_calibration(tmp_path, -2e-6, 2e-6, 0.5e-6, shape=(48, 48), optics=o, camera=cam, seed=0,
                               progress=False)
    z = pd.read_csv(paths["z"])
    assert list(z.columns) == ["page", "z"] and len(z) == 9
    np.testing.assert_allclose(z["z"], np.linspace(-2e-6, 2e-6, 9), atol=1e-15)
    stack = tifffile.imread(paths["stack"]).astype(float)
    assert stack.shape == (9, 48, 48)
    focus = stack[4] - cam.offset
    iy, ix = np.unravel_index(np.argmax(focus), focus.shape)
    assert (iy, ix) == (23, 23)
    # the pages above and below focus are elongated along different axes
    hi, lo = np.clip(stack[6] - cam.offset - 5, 0, None), np.clip(stack[2] - cam.offset - 5, 0, None)
    _, _, sxh, syh = _moments(hi)
    _, _, sxl, syl = _moments(lo)
    assert (sxh - syh) * (sxl - syl) < 0
    with tifffile.TiffFile(paths["stack"]) as tf:
        assert tf.imagej_metadata["spacing"] == pytest.approx(0.5)


def test_bad_input_is_a_user_error(tmp_path):
    from ptrack.errors import UserError

    with pytest.raises(UserError):
        Optics(na=1.2)
    with pytest.raises(UserError):
        Camera(quantum_efficiency=1.5)
    with pytest.raises(UserError):
        list(render_frames(_small_table(), (0, 10)))
    with pytest.raises(UserError):
        render_calibration(tmp_path, 1e-6, -1e-6, 1e-7, progress=False)
    with pytest.raises(UserError):  # exposure longer than the frame interval (0.25 s)
        list(render_frames(_small_table(), (36, 48), camera=Camera(exposure=0.3)))
    with pytest.raises(UserError):  # pixel coarser than Nyquist
        list(render_frames(_small_table(), (10, 10), Optics(magnification=20)))


# ---------------------------------------------------------------- CLI

def test_cli_render_and_calibration(tmp_path, capsys):
    t = _small_table()
    src = tmp_path / "traj.csv"
    t.to_csv(src, index=False)
    out = tmp_path / "movie"
    assert main(["render", str(src), "--out", str(out), "--shape", "36", "48", "--seed", "3",
                 "--focal-plane", "-2e-7", "--astigmatism", "1e-7", "--photons", "8000"]) == 0
    for name in ("movie.tif", "truth.parquet", "params.json", "preview.png"):
        assert (out / name).is_file()
    p = json.loads((out / "params.json").read_text())
    assert p["focal_plane"] == -2e-7 and p["camera"]["photons"] == 8000 and p["optics"]["astigmatism"] == 1e-7
    out2 = tmp_path / "movie2"
    assert main(["render", str(src), "--out", str(out2), "--shape", "36", "48", "--seed", "3",
                 "--focal-plane", "-2e-7", "--astigmatism", "1e-7", "--photons", "8000"]) == 0
    assert (out / "movie.tif").read_bytes() == (out2 / "movie.tif").read_bytes()
    cal = tmp_path / "cal"
    assert main(["render-calibration", "--out", str(cal), "--z-range", "-1e-6", "1e-6", "--z-step", "5e-7",
                 "--shape", "32", "32"]) == 0
    assert len(pd.read_csv(cal / "calib_z.csv")) == 5 and (cal / "calib_montage.png").is_file()
    capsys.readouterr()
    assert main(["render", str(tmp_path / "missing.parquet"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:")
    assert not (tmp_path / "x").exists()
    assert main(["render", str(src), "--out", str(tmp_path / "y"), "--na", "1.5"]) == 2


# ---------------------------------------------------------------- shipped data

DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic"


def test_shipped_datasets_are_consistent():
    from sim.render.datasets import stokes_einstein

    for name in ("diffusion2d", "diffusion3d", "epd_brightfield"):
        d = DATA / name
        params = json.loads((d / "params.json").read_text())
        truth = read_table(d / "truth.parquet")
        with tifffile.TiffFile(d / "movie.tif") as tf:
            assert len(tf.pages) == params["n_frames"] == truth["frame"].max() + 1
            assert tf.pages[0].shape == tuple(params["shape"])
        assert "Regenerate with:" in (d / "README.txt").read_text()
        # epd_brightfield is imaged at 20x (325 nm pixels), the others at 63x
        px = 6.5e-6 / 20.0 if name == "epd_brightfield" else PX
        assert truth.attrs["ptrack"]["pixel_size"] == pytest.approx(px)
    p2 = json.loads((DATA / "diffusion2d" / "params.json").read_text())
    assert p2["D_true"] == pytest.approx(stokes_einstein(250e-9), rel=1e-12)
    assert p2["D_truth_tracks"] == pytest.approx(p2["D_true"], rel=0.04)
    z = pd.read_csv(DATA / "diffusion3d" / "calib_z.csv")
    truth3 = read_table(DATA / "diffusion3d" / "truth.parquet")
    assert z["z"].min() <= truth3["z"].min() and truth3["z"].max() <= z["z"].max()
    epd = read_table(DATA / "epd_brightfield" / "truth.parquet")
    first, last = epd[epd["frame"] == 0], epd[epd["frame"] == epd["frame"].max()]
    assert last["z"].mean() < first["z"].mean()
    # the brightfield calibration stack covers every height of the movie; all particles above focus
    pe = json.loads((DATA / "epd_brightfield" / "params.json").read_text())
    ze = pd.read_csv(DATA / "epd_brightfield" / "calib_z.csv")
    assert ze["z"].min() <= epd["z"].min() and epd["z"].max() <= ze["z"].max()
    assert epd["z"].min() - pe["focal_plane"] > 3e-6
    cp = json.loads((DATA / "epd_brightfield" / "calib_params.json").read_text())
    assert cp["brightfield"] and cp["pixel_size"] == pytest.approx(pe["pixel_size"])
    assert cp["focal_plane"] == pe["focal_plane"]
    # deposited rows sit at contact; the truth's drift is the Henry velocity plus settling
    dep = epd["deposited"].astype(bool)
    assert np.allclose(epd.loc[dep, "z"], pe["radius"]) and (~dep).sum() > 300
    assert pe["vz_drift"] == pytest.approx(-(pe["v_henry"] + pe["v_sedimentation"]))
    assert sum(f.stat().st_size for f in (DATA / "epd_brightfield").iterdir()) < 3.2e6


def test_shipped_truth_is_what_the_dataset_command_makes():
    """The committed ground truth equals the trajectories the generator makes now (seeded)."""
    from sim.render.datasets import SCENES

    for name, scene in SCENES.items():
        sc = scene()
        shipped = read_table(DATA / name / "truth.parquet")
        t = sc["table"]
        assert len(shipped) == len(t)
        for c in ("frame", "particle", "x", "y", "z", "t"):
            np.testing.assert_array_equal(shipped[c].to_numpy(), t[c].to_numpy(), err_msg=f"{name}.{c}")
        params = json.loads((DATA / name / "params.json").read_text())
        assert params["seed"] == sc["seed"] and params["shape"] == list(sc["shape"])


def test_very_far_defocus_falls_back_to_the_geometric_blur_ellipse():
    from sim.render.movie import MAX_PATCH

    cam = Camera(photons=1e6, background=0.0)
    o = Optics(astigmatism=1e-7)
    dz = 80e-6  # blur radius ~ 530 px: beyond the wave-optics patch limit
    c = 600
    img = next(expected_frames(one_particle(c, c, z=dz), (2 * c, 2 * c), o, cam))
    lf = 2 * o.medium_index * o.astigmatism / o.na ** 2
    rx, ry = (dz - lf) * o.half_angle_tan / PX, (dz + lf) * o.half_angle_tan / PX
    assert 2 * rx > MAX_PATCH
    assert img.sum() == pytest.approx(1e6, rel=0.01)  # pixel-counted vs analytic ellipse area
    assert img[c, c] == pytest.approx(1e6 / (np.pi * rx * ry), rel=1e-9)
    assert img[c, int(c + 0.995 * rx)] > 0 and img[c, int(c + 1.005 * rx) + 1] == 0
    assert img[int(c + 0.995 * ry), c] > 0 and img[int(c + 1.005 * ry) + 1, c] == 0


def test_edge_cases_of_the_input_table(tmp_path):
    from ptrack.errors import UserError

    t = _small_table()
    # a photons column sets the brightness per row; negative photons are refused
    t2 = t.assign(photons=np.where(t["particle"] == 0, 0.0, 5000.0))
    paths = render_movie(t2, tmp_path / "ph", (36, 48), seed=0, progress=False)
    truth = read_table(paths["truth"])
    assert (truth.loc[truth["particle"] == 0, "signal"] == 0).all()
    assert (truth.loc[truth["particle"] != 0, "signal"] > 0).all()
    with pytest.raises(UserError):
        list(render_frames(t.assign(photons=-1.0), (36, 48)))
    # NaN positions are a user error, not a crash
    bad = t.copy()
    bad.loc[0, "x"] = np.nan
    with pytest.raises(UserError):
        list(render_frames(bad, (36, 48)))
    with pytest.raises(UserError):
        render_movie(t.iloc[:0], tmp_path / "empty", (36, 48), progress=False)
    # a particle far outside the frame costs nothing and adds nothing
    far = make_table([0], [0.0], [0], [1.0], [1.0], [0.0], meta={"frame_interval": 0.1})
    img = next(expected_frames(far, (20, 20), None, Camera(background=3.0)))
    assert np.all(img == 3.0)


def test_localisation_scatter_matches_the_cramer_rao_bound():
    """End-to-end check of PSF + noise: an Airy fit to rendered noisy frames scatters as the
    Cramer-Rao bound computed from the expected image and the camera model says."""
    cam = Camera(photons=2000.0, background=10.0)
    n = 100
    rng = np.random.default_rng(1)
    xs, ys = 20 + rng.uniform(-0.5, 0.5, n), 20 + rng.uniform(-0.5, 0.5, n)
    f = np.arange(n)
    t = make_table(f, f * 0.1, f, xs * PX, ys * PX, np.zeros(n), meta={"frame_interval": 0.1})
    frames = np.array(list(render_frames(t, (40, 40), None, cam, seed=2)), float)
    crlb = localisation_crlb(cam, 20.2, 19.9, shape=(40, 40))
    yy, xx = np.mgrid[13:28, 13:28]
    errs = []
    for k in range(n):
        e = (frames[k][yy, xx] - cam.offset) / cam.gain
        w = 1 / np.sqrt(np.maximum(e, 0) + cam.read_noise ** 2 + 1)
        fit = least_squares(lambda p: ((_airy_model(p, xx, yy, sub=4) - e) * w).ravel(),
                            [e.max(), 20, 20, np.median(e)], x_scale=[100, 0.1, 0.1, 1])
        errs.append(fit.x[1] - xs[k])
    ratio = np.std(errs) / crlb
    assert 0.85 < ratio < 1.35, (np.std(errs), crlb)
    assert abs(np.mean(errs)) < 3 * crlb / np.sqrt(n)


def test_movie_particles_match_their_calibration_page():
    """Movie (PSF-stack interpolation, patch classes) and calibration (exact planes) agree: normalised
    cross-correlation against the calibration pages finds each particle's true z (GDPT-style)."""
    from sim.render.calibration import calibration_images

    o = Optics(astigmatism=1.2e-7)
    cam = Camera(photons=1e4, background=0.0)
    zc = np.round(np.arange(-2e-6, 2.0001e-6, 0.1e-6), 12)
    pages = np.array(list(calibration_images(zc, (41, 41), o, cam, position=(20, 20), noise=False)))
    pz = pages - pages.mean(axis=(1, 2), keepdims=True)
    pz /= np.linalg.norm(pz.reshape(len(zc), -1), axis=1)[:, None, None]
    rng = np.random.default_rng(4)
    ztrue = rng.uniform(-1.8e-6, 1.8e-6, 8)
    f = np.zeros(8, int)
    xs = 30 + 60 * np.arange(8)
    t = make_table(f, f * 0.1, np.arange(8), xs * PX, np.full(8, 30 * PX), ztrue, meta={"frame_interval": 0.1})
    img = next(expected_frames(t, (60, 500), o, cam))
    for k in range(8):
        crop = img[10:51, xs[k] - 20:xs[k] + 21]
        c = crop - crop.mean()
        cm = np.tensordot(pz, c / np.linalg.norm(c), axes=([1, 2], [0, 1]))
        j = int(np.argmax(cm))
        y0, y1, y2 = cm[j - 1], cm[j], cm[j + 1]
        zfit = zc[j] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) * 0.1e-6
        assert cm[j] > 0.99
        assert abs(zfit - ztrue[k]) < 0.02e-6, (zfit, ztrue[k])


@pytest.mark.parametrize("B", [0.0, 9.0, 3e4])
def test_poisson_sampler_is_exact_for_every_kind_of_pixel(B):
    """Background-only, faint-tail (pooled), moderate (inversion), bright (numpy) and below-background
    pixels all get Poisson counts with the right mean and variance."""
    from sim.render.camera import poisson

    levels = [0.0, 0.01, 0.1, 0.2, 0.3, 1.0, 10.0, 100.0] + ([-3.0, -8.9] if B > 0 else [])
    if B > 1e4:
        levels = [0.0, 100.0, -500.0]
    m = 20000
    lam = np.repeat(B + np.array(levels), m)
    rng = np.random.default_rng(5)
    x = np.mean([poisson(lam, rng, background=B) for _ in range(3)], axis=0)  # 3 frames averaged
    x1 = poisson(lam, rng, background=B)
    for i, lv in enumerate(levels):
        mu = B + lv
        sl = slice(i * m, (i + 1) * m)
        if mu == 0:
            assert np.all(x1[sl] == 0)
            continue
        assert abs(x[sl].mean() - mu) < 5 * np.sqrt(mu / (3 * m)), (lv, x[sl].mean(), mu)
        assert abs(x1[sl].var() - mu) < 5 * mu * np.sqrt(2 / m) + 5 * np.sqrt(mu / m), (lv, x1[sl].var(), mu)
        assert np.all(x1[sl] == np.round(x1[sl])) and x1[sl].min() >= 0


def test_coherent_brightfield_contrast_follows_the_scatter_phase():
    """B |1 + sigma a|^2: a weak phase object (phase pi/2) is invisible in focus and has opposite
    contrast above and below focus; an extinction (phase pi) is dark in focus and symmetric in z."""
    cam = Camera(photons=300.0, background=1000.0)
    zs = np.array([-0.6e-6, 0.0, 0.6e-6])
    f = np.zeros(3, int)
    t = make_table(f, f * 0.1, np.arange(3), (60 + 120 * np.arange(3)) * PX, np.full(3, 60 * PX), zs,
                   meta={"frame_interval": 0.1})

    def centres(phase):
        img = next(expected_frames(t, (120, 360), None, cam, brightfield="coherent", scatter_phase=phase))
        return img[60, [60, 180, 300]] - cam.background, img

    (below, focus, above), _ = centres(np.pi / 2)
    # in focus the interference term vanishes: only the scattered intensity |sigma a|^2 B is left
    fluo = next(expected_frames(t, (120, 360), None, Camera(photons=300.0, background=0.0)))[60, [60, 180, 300]]
    assert focus == pytest.approx(fluo[1], rel=1e-3)
    assert (below - fluo[0]) * (above - fluo[2]) < 0 and abs(below - fluo[0]) > 3 * fluo[1]
    (below, focus, above), img = centres(np.pi)
    assert focus < -0.2 * cam.background
    assert below == pytest.approx(above, rel=1e-3)
    # coherent calibration pages equal the movie rendering at the same defocus
    from sim.render.calibration import calibration_images

    page = next(calibration_images([0.6e-6], (120, 120), None, cam, position=(60, 60), brightfield="coherent",
                                   noise=False, scatter_phase=np.pi))
    np.testing.assert_allclose(page[40:81, 40:81], img[40:81, 280:321], rtol=0, atol=2e-3 * cam.background)
    from ptrack.errors import UserError

    with pytest.raises(UserError):
        list(render_frames(t, (120, 360), camera=Camera(background=0.0), brightfield="coherent"))
    with pytest.raises(UserError):
        list(render_frames(t, (120, 360), brightfield="darkfield"))


def test_cli_coherent_brightfield(tmp_path):
    t = _small_table()
    src = tmp_path / "traj.parquet"
    from ptrack.table import write_table

    write_table(t, src)
    out = tmp_path / "bf"
    assert main(["render", str(src), "--out", str(out), "--shape", "36", "48", "--brightfield",
                 "--brightfield-model", "coherent", "--background", "500", "--photons", "2000",
                 "--scatter-phase", "3.0"]) == 0
    p = json.loads((out / "params.json").read_text())
    assert p["mode"] == "coherent" and p["scatter_phase"] == 3.0 and p["brightfield"] is True
    assert main(["render-calibration", "--out", str(tmp_path / "cal"), "--z-range", "-1e-6", "1e-6",
                 "--z-step", "1e-6", "--shape", "32", "32", "--brightfield"]) == 0
    cp = json.loads((tmp_path / "cal" / "calib_params.json").read_text())
    assert cp["brightfield"] == "absorption"


@pytest.mark.parametrize("cam", [Camera(background=20.0), Camera(background=3.0, read_noise=0.0, gain=1.7, offset=2.0),
                                 Camera(background=50.0, read_noise=4.0, offset=0.0, bit_depth=8)])
def test_camera_adu_distribution_equals_direct_simulation(cam):
    """The fast path (compound background distribution, pooled tails) gives the same ADU histogram as
    a direct simulation of Poisson + Gaussian + gain/offset + rounding + clipping."""
    rng = np.random.default_rng(9)
    img = np.full((300, 300), cam.background)
    img[:, 150:] += np.linspace(0.0, 2.0, 150)[None, :]  # faint tails and moderate light
    fast = np.concatenate([expose(img, cam, rng).ravel() for _ in range(3)]).astype(np.int64)
    lam = np.tile(img.ravel() * cam.quantum_efficiency, 3)
    e = rng.poisson(lam) + cam.read_noise * rng.standard_normal(lam.size)
    direct = np.clip(np.floor(cam.gain * e + cam.offset + 0.5), 0, cam.max_adu).astype(np.int64)
    for half in (slice(0, 150), slice(150, 300)):
        sel = np.zeros((300, 300), bool)
        sel[:, half] = True
        sel = np.tile(sel.ravel(), 3)
        a = np.bincount(fast[sel], minlength=cam.max_adu + 1)
        b = np.bincount(direct[sel], minlength=cam.max_adu + 1)
        keep = (a + b) > 20
        chi2 = np.sum((a[keep] - b[keep]) ** 2 / (a[keep] + b[keep]))
        dof = keep.sum() - 1
        assert chi2 < dof + 5 * np.sqrt(2 * dof), (chi2, dof)
        assert abs(a[~keep].sum() - b[~keep].sum()) < 5 * np.sqrt(a[~keep].sum() + b[~keep].sum() + 1)


def test_coherent_field_phase_is_relative_to_the_illumination():
    # the forward-scattered amplitude (k = 0 of the field) does not change as the particle moves
    # along z: the illumination propagates with it. An absolute phase 2 pi n dz / lambda here
    # made the brightfield contrast repeat every lambda / n.
    from sim.render.optics import Optics, otf_planes

    optics = Optics()
    n_med, lam = optics.medium_index, optics.wavelength
    dz = np.array([1.0e-6, 1.0e-6 + 0.25 * lam / n_med, 1.0e-6 + lam / n_med, 2.0e-6])
    _, re, im = otf_planes(optics, 100e-9, 64, dz, field=True)
    a0 = re[:, 0, 0] + 1j * im[:, 0, 0]
    np.testing.assert_allclose(a0, a0[0], rtol=1e-6, atol=1e-9 * abs(a0[0]))
    # and the image does not repeat after lambda / n (it did, exactly, with the absolute phase)
    assert np.abs(re[2] - re[0]).max() > 0.05 * np.abs(re[0]).max()


def test_impossible_patch_and_undetermined_frame_interval_are_user_errors(tmp_path):
    """Astigmatism given in waves (0.5, read as 0.5 m) is refused before any allocation; a multi-frame table whose
    t does not increase has no frame interval (no silent 1 s); the default calibration page holds the image or warns."""
    from ptrack.errors import UserError
    from sim.render.calibration import page_shape_for, render_calibration
    from sim.render.movie import frame_interval_of
    from sim.render.optics import patch_size, sample_pixel_size

    o = Optics(astigmatism=0.5)
    with pytest.raises(UserError, match="astigmatism"):
        patch_size(o, sample_pixel_size(o, Camera().pixel_pitch), 60e-6)
    with pytest.raises(UserError, match="astigmatism"):
        render_calibration(tmp_path / "a", -2e-6, 2e-6, 1e-6, optics=o, progress=False)
    assert not (tmp_path / "a" / "calib.tif").exists()
    bad = pd.DataFrame({"frame": [0, 1, 2], "t": [0.0, 0.0, 0.0], "particle": 0, "x": 0.0, "y": 0.0, "z": 0.0})
    with pytest.raises(UserError, match="frame interval"):
        frame_interval_of(bad)
    with pytest.warns(UserWarning, match="single-frame"):
        assert frame_interval_of(bad.iloc[:1]) == 1.0
    z = np.arange(-10e-6, 10.0001e-6, 2e-6)
    H, W = page_shape_for(z, Optics(), Camera())
    assert 140 < H == W <= 512          # +-10 um at NA 0.75 in water: the ring is ~160 px across
    with pytest.warns(UserWarning, match="cut the particle image beyond"):
        page_shape_for(z, Optics(), Camera(), shape=(64, 64))
