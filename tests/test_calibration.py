"""GDPT: calibration templates, z by normalised cross-correlation, errors on bad calibrations."""
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import tifffile

from ptrack.calibration import (build_calibration, check_pixel_size, load_calibration, locate_3d, locate_frame_3d,
                                match_templates, read_calib_z)
from ptrack.errors import UserError
from ptrack.motion.truth import match_truth
from ptrack.preprocess import prepare

render = pytest.importorskip("sim.render")

OPTICS = render.Optics(astigmatism=1.2e-7)
CAMERA = render.Camera(photons=20000.0, background=15.0)
PX = render.sample_pixel_size(OPTICS, CAMERA.pixel_pitch)
Z = np.round(np.arange(-2e-6, 2.0001e-6, 0.1e-6), 12)
STEP = 0.1e-6


def _nearest_true(df, xs, ys):
    """Each localisation's nearest true particle (any range) and its distance, px, by the one matching rule."""
    found = pd.DataFrame({"frame": 0, "x_px": df["x_px"].to_numpy(float), "y_px": df["y_px"].to_numpy(float)})
    truth = pd.DataFrame({"frame": 0, "x_px": np.asarray(xs, float), "y_px": np.asarray(ys, float)})
    fi, ti = match_truth(found, truth, np.inf)
    near = np.full(len(found), -1)
    near[fi] = ti
    dmin = np.hypot(found["x_px"].to_numpy() - truth["x_px"].to_numpy()[near],
                    found["y_px"].to_numpy() - truth["y_px"].to_numpy()[near])
    return near, dmin


@pytest.fixture(scope="module")
def calib():
    stack = np.stack(list(render.calibration_images(Z, shape=(72, 72), optics=OPTICS, camera=CAMERA, seed=1)))
    return build_calibration(stack, Z, PX, source="test")


def test_calibration_pages_recovered(calib):
    """Pages of an independent noisy stack come back at their own z, a small fraction of the step."""
    errs, cms, dxy = [], [], []
    for z, img in zip(Z, render.calibration_images(Z, shape=(72, 72), optics=OPTICS, camera=CAMERA, seed=2)):
        df = locate_3d(prepare(img, background="none"), calib)
        assert len(df) == 1
        errs.append(df["z"].iloc[0] - z)
        cms.append(df["cm"].iloc[0])
        dxy.append((df["x_px"].iloc[0] - 35.0, df["y_px"].iloc[0] - 35.0))
    assert np.abs(dxy).max() < 0.5 and np.sqrt(np.mean(np.square(dxy))) < 0.15   # x, y from the correlation peak
    errs = np.abs(errs)
    # 20 nm-level noise: a fifth of the 0.1 um step
    assert np.median(errs) < 0.3 * STEP and errs.max() < 1.0 * STEP, errs / STEP
    assert min(cms) > 0.9


def test_calibration_pages_themselves_no_interpolation_bias(calib):
    """The stack's own pages (identical images) come back at their z: the sub-step fit adds no bias."""
    errs = []
    for k in range(1, len(Z) - 1):
        img = np.zeros((90, 90), np.float32)
        t = calib.templates[k]
        img[20:20 + t.shape[0], 25:25 + t.shape[1]] = t
        df = locate_3d(img, calib, smooth=0.0)
        assert len(df) == 1 and df["cm"].iloc[0] > 0.999
        errs.append(df["z"].iloc[0] - Z[k])
        assert df["y_px"].iloc[0] == pytest.approx(20 + calib.centers[k, 0], abs=0.02)
    assert np.median(np.abs(errs)) < 0.07 * STEP and np.abs(errs).max() < 0.2 * STEP


def test_heights_between_pages_and_off_centre(calib):
    rng = np.random.default_rng(3)
    zs = rng.uniform(-1.9e-6, 1.9e-6, 25)
    errs, xy = [], []
    for i, z in enumerate(zs):
        pos = (30 + rng.uniform(0, 10), 31 + rng.uniform(0, 10))
        img = next(render.calibration_images([z], shape=(72, 72), optics=OPTICS, camera=CAMERA, position=pos, seed=10 + i))
        df = locate_3d(prepare(img, background="none"), calib)
        assert len(df) == 1
        errs.append(df["z"].iloc[0] - z)
        xy.append((df["x_px"].iloc[0] - pos[0], df["y_px"].iloc[0] - pos[1]))
    errs = np.asarray(errs)
    depth = Z[-1] - Z[0]
    # ~1 % of the calibrated range here (25 particles, some cut by the frame edge); bench_pipeline
    # measures it on many isolated particles
    assert np.sqrt(np.mean(errs ** 2)) < 0.02 * depth
    assert np.median(np.abs(errs)) < 0.5 * STEP
    assert np.sqrt(np.mean(np.square(xy))) < 0.2


def test_low_correlation_is_rejected(calib):
    """Pure noise does not match: the best of 41 templates x 81 shifts on smoothed noise reaches Cm 0.3-0.6 by
    chance (seed-dependent; one seed at 0.5 decided nothing), so several seeds and a margin above that."""
    best = []
    for seed in range(4, 10):
        noise = np.random.default_rng(seed).normal(0, 10, (72, 72)).astype(np.float32)
        assert len(match_templates(noise, [36], [36], calib, cm_min=0.7)) == 0
        best.append(match_templates(noise, [36], [36], calib, cm_min=-1.0)["cm"].max())
    assert np.median(best) < 0.6


def test_read_calib_z(tmp_path):
    p = tmp_path / "z.csv"
    pd.DataFrame({"page": [2, 0, 1], "z": [2e-6, 0.0, 1e-6]}).to_csv(p, index=False)
    np.testing.assert_allclose(read_calib_z(p, 3), [0, 1e-6, 2e-6])
    with pytest.raises(UserError, match="pages"):
        read_calib_z(p, 4)
    pd.DataFrame({"page": [0, 1, 2], "z": [0, 1, 2]}).to_csv(p, index=False)
    with pytest.raises(UserError, match="micrometres"):
        read_calib_z(p, 3)
    pd.DataFrame({"slice": [0, 1, 2], "z": [0, 1e-6, 2e-6]}).to_csv(p, index=False)
    with pytest.raises(UserError, match="page, z"):
        read_calib_z(p, 3)


def test_calibration_errors(tmp_path, calib):
    with pytest.raises(UserError, match="pixel size"):
        check_pixel_size(calib, PX * 2)
    check_pixel_size(calib, PX * 1.001)
    with pytest.raises(UserError, match="--calib-z|--calib-step"):
        load_calibration(tmp_path / "nothing.tif")
    with pytest.raises(UserError, match="at least 3"):
        build_calibration(np.zeros((2, 10, 10)), [0, 1e-7])


def test_cli_3d_and_pixel_size_mismatch(tmp_path, calib):
    """3D tracking from the command line; a calibration with another pixel size is refused, no output."""
    from ptrack.table import make_table, read_table

    stack = np.stack(list(render.calibration_images(Z, shape=(72, 72), optics=OPTICS, camera=CAMERA, seed=5)))
    res = (1e-6 / PX, 1e-6 / PX)
    tifffile.imwrite(tmp_path / "calib.tif", stack, imagej=True, resolution=res, metadata={"unit": "um"})
    tifffile.imwrite(tmp_path / "calib_wrong.tif", stack, imagej=True, resolution=(res[0] / 2, res[1] / 2),
                     metadata={"unit": "um"})
    pd.DataFrame({"page": np.arange(len(Z)), "z": Z}).to_csv(tmp_path / "calib_z.csv", index=False)
    # a movie: 3 particles at fixed heights drifting sideways
    n_f, pid = 8, np.arange(3)
    fr = np.repeat(np.arange(n_f), 3)
    p = np.tile(pid, n_f)
    x = (np.array([30.0, 90.0, 60.0])[p] + 0.7 * fr) * PX
    y = (np.array([30.0, 40.0, 95.0])[p] + 0.3 * fr) * PX
    z = np.array([-1.23e-6, 0.41e-6, 1.57e-6])[p]
    truth = make_table(fr, fr * 0.1, p, x, y, z, meta={"frame_interval": 0.1})
    info = render.render_movie(truth, tmp_path / "m", shape=(128, 128), optics=OPTICS, camera=CAMERA, seed=6,
                               progress=False)
    out = tmp_path / "traj.parquet"
    base = [sys.executable, "-m", "ptrack", "track", str(info["movie"]), "--out", str(out),
            "--calib-z", str(tmp_path / "calib_z.csv"), "--gain", "2.17", "--offset", "100"]
    r = subprocess.run(base + ["--calib", str(tmp_path / "calib_wrong.tif")], capture_output=True, text=True)
    assert r.returncode == 2 and "pixel size" in r.stderr and not out.exists()
    r = subprocess.run(base + ["--calib", str(tmp_path / "calib.tif")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    t = read_table(out)
    assert t["particle"].nunique() == 3 and len(t) == 3 * n_f
    got = t.groupby("particle")["z"].mean().sort_values().to_numpy()
    np.testing.assert_allclose(got, [-1.23e-6, 0.41e-6, 1.57e-6], atol=0.04e-6)
    assert t["cm"].min() > 0.8
    assert t.attrs["ptrack"]["calib_depth"] == pytest.approx(4e-6)


def test_edge_cut_and_overlapping_defocused_images_no_spurious(calib):
    """A frame with an image cut by the frame edge and two defocused (ring-like, astigmatic) images that
    overlap: each particle is found once, at its x, y and z, and nothing else is reported."""
    from ptrack.table import make_table

    cam = render.Camera(photons=4000.0, background=15.0)
    # (x, y) px and z: cut by the left edge; two defocused images 13 px apart (their images overlap);
    # one in focus for reference
    xs = np.array([3.0, 60.0, 73.0, 100.0])
    ys = np.array([40.0, 44.0, 50.0, 20.0])
    zs = np.array([0.6e-6, -1.5e-6, 1.4e-6, 0.0])
    n_f = 4
    fr = np.repeat(np.arange(n_f), len(xs))
    p = np.tile(np.arange(len(xs)), n_f)
    table = make_table(fr, fr * 0.1, p, xs[p] * PX, ys[p] * PX, zs[p], meta={"frame_interval": 0.1})
    for f, frame in enumerate(render.render_frames(table, shape=(90, 120), optics=OPTICS, camera=cam, seed=21)):
        df = locate_3d(prepare(frame, bg_size=3 * calib.size), calib)
        assert len(df) == len(xs), df
        near, dmin = _nearest_true(df, xs, ys)
        assert sorted(near) == list(range(len(xs))), df        # one detection per particle
        alone = (near == 0) | (near == 3)
        assert dmin[alone].max() < 0.5 and dmin.max() < 2.0, df
        # z: the overlapping pair is measured with its neighbour's fitted image removed (a few % of the depth)
        dz = np.abs(df["z"].to_numpy() - zs[near])
        assert dz.max() < 0.3e-6 and dz[alone].max() < 0.1e-6, df
        assert df["cm"].min() > 0.8
        assert df["edge"].to_numpy()[near == 0].all() and not df["edge"].to_numpy()[near == 3].any()


# --- brightfield GDPT: 20x NA 0.4 air objective, 0.8 um particles 1-15 um above the focal plane -------------------
BF_OPT = render.Optics(na=0.4, magnification=20.0, wavelength=550e-9)
BF_CAM = render.Camera(photons=30000.0, background=800.0)
BF_PX = render.sample_pixel_size(BF_OPT, BF_CAM.pixel_pitch)
BF_Z = np.round(np.arange(1e-6, 15.001e-6, 0.5e-6), 12)
BF_STEP = 0.5e-6
BF_KW = dict(optics=BF_OPT, camera=BF_CAM, brightfield=True, radius=0.4e-6)
# depth of field n lambda / NA^2: inside it the image barely changes with z, so z is poorly defined there
BF_DOF = BF_OPT.medium_index * BF_OPT.wavelength / BF_OPT.na ** 2


@pytest.fixture(scope="module")
def bf_calib():
    stack = np.stack(list(render.calibration_images(BF_Z, shape=(64, 64), seed=1, **BF_KW)))
    return build_calibration(stack, BF_Z, BF_PX, brightfield=True, source="bf")


def _z_crb(z, h=0.1e-6):
    """Cramer-Rao bound of z (m) for one brightfield image at height z: Poisson noise of the bright field plus
    read noise, Fisher information sum (d mu / dz)^2 / var from the noise-free images at z +- h."""
    a, b, c = (next(render.calibration_images([zz], shape=(64, 64), noise=False, **BF_KW)) for zz in (z - h, z, z + h))
    qe = BF_CAM.quantum_efficiency
    var = b * qe + BF_CAM.read_noise ** 2
    return 1.0 / np.sqrt((((c - a) * qe / (2 * h)) ** 2 / var).sum())


def _bf_bound(z, floor=0.6):
    # GDPT is no efficient estimator and its templates are single noisy pages as noisy as the image itself
    # (sqrt 2): 5 x sqrt 2 x the bound, and never below ``floor`` calibration steps
    return max(5 * np.sqrt(2) * _z_crb(z), floor * BF_STEP)


def test_brightfield_prepare_is_signed_and_calibration_signed(bf_calib):
    """Brightfield frames are inverted but not thresholded; the background under a ring is not pulled down."""
    from ptrack.calibration import prepare_gdpt

    assert bf_calib.info["signed"]
    img = next(render.calibration_images([12e-6], shape=(96, 96), seed=3, **BF_KW))
    p = prepare_gdpt(img, bf_calib, brightfield=True)
    assert p.min() < -3 * np.std(p[:10, :10]) and p.max() > 5 * np.std(p[:10, :10])   # both signs kept
    # the median background keeps the particle-free field at 0 (an opening would sit on the noise minima)
    assert abs(np.median(p[:12])) < 0.2 * np.std(p[:12])
    with pytest.raises(UserError, match="brightfield"):
        prepare_gdpt(img, bf_calib, brightfield=False)


def test_brightfield_stack_pages_recovered(bf_calib):
    """An independent noisy brightfield stack: each page comes back at its z within the Cramer-Rao-based bound
    (outside the depth of field, where z is defined by the growing defocus blur)."""
    from ptrack.calibration import prepare_gdpt

    errs, bounds, dxy = [], [], []
    for z, img in zip(BF_Z, render.calibration_images(BF_Z, shape=(64, 64), seed=2, **BF_KW)):
        df = locate_3d(prepare_gdpt(img, bf_calib, brightfield=True), bf_calib)
        assert len(df) == 1
        dxy.append((df["x_px"].iloc[0] - 31, df["y_px"].iloc[0] - 31))
        if z > BF_DOF:
            errs.append(df["z"].iloc[0] - z)
            bounds.append(_bf_bound(z))
        else:
            assert abs(df["z"].iloc[0] - z) < BF_DOF / 2       # inside the depth of field: only coarse
    # x, y from the correlation peak of a blurred, noisy ring (1 px = 325 nm here)
    assert np.abs(dxy).max() < 1.0 and np.sqrt(np.mean(np.square(dxy))) < 0.3, dxy
    errs, bounds = np.abs(errs), np.asarray(bounds)
    assert np.all(errs < bounds), np.c_[errs, bounds] * 1e9
    assert np.sqrt(np.mean(errs ** 2)) < 0.03 * (BF_Z[-1] - BF_Z[0])


def test_brightfield_movie_several_defocus_values(bf_calib):
    """A rendered brightfield movie frame (dark particles on a bright field, 5 heights): every particle is found
    once, at its x, y and z (z within the bound above), nothing else."""
    from ptrack.calibration import prepare_gdpt
    from ptrack.table import make_table

    zs = np.array([5.3e-6, 7.6e-6, 9.1e-6, 11.7e-6, 13.8e-6])
    xs = np.array([30.3, 90.6, 150.2, 60.8, 121.4])
    ys = np.array([35.5, 40.1, 30.7, 100.4, 105.9])
    n_f = 2
    fr = np.repeat(np.arange(n_f), len(xs))
    p = np.tile(np.arange(len(xs)), n_f)
    table = make_table(fr, fr * 0.1, p, xs[p] * BF_PX, ys[p] * BF_PX, zs[p], meta={"frame_interval": 0.1})
    # at 325 nm pixels (Nyquist for NA 0.4) a particle at another sub-pixel position than the calibration
    # particle has a differently pixelated image, which correlates best a little off its height: a systematic
    # error of up to a calibration step (measured over 8 frames of these particles: 200-440 nm bias, 100-150 nm
    # spread), so the floor here is one step
    bounds = np.array([_bf_bound(z, floor=1.0) for z in zs])
    for frame in render.render_frames(table, shape=(140, 180), seed=7, **BF_KW):
        df = locate_3d(prepare_gdpt(frame, bf_calib, brightfield=True), bf_calib)
        assert len(df) == len(xs), df
        near, dmin = _nearest_true(df, xs, ys)
        assert sorted(near) == list(range(len(xs))) and dmin.max() < 0.6, df
        dz = np.abs(df["z"].to_numpy() - zs[near])
        assert np.all(dz < bounds[near]), (dz * 1e9, bounds[near] * 1e9)


@pytest.mark.parametrize("sep_um,z1,z2,angle", [(0.6, -1.2e-6, 1.0e-6, 0.0), (0.8, 0.5e-6, -1.5e-6, 0.9),
                                                (1.0, 1.5e-6, -0.3e-6, 2.0), (0.7, -1.6e-6, -0.4e-6, 4.0)])
def test_close_pair_at_different_heights(calib, sep_um, z1, z2, angle):
    """Two particles 0.6-1 um apart (6-10 px; their defocused images overlap almost entirely) at different z,
    in a frame with two more particles (as in any movie frame: they give the typical brightness): both are
    found, each at its own x, y and z, not one merged match at a compromise height. Measured over 8 frames of
    these four pairs: 31 of 32 frames right (the miss: a compact image with an elongated one 0.8 um away,
    matched as one, flagged by its residual chi2); here at least 3 of 4 frames per pair, and no wrong z
    reported without a high chi2."""
    from ptrack.table import make_table

    cam = render.Camera(photons=4000.0, background=15.0)
    sep = sep_um * 1e-6 / PX
    xs = np.array([60.3, 60.3 + sep * np.cos(angle), 20.0, 100.0])
    ys = np.array([55.6, 55.6 + sep * np.sin(angle), 20.0, 20.0])
    zs = np.array([z1, z2, 0.2e-6, -0.7e-6])
    n_f = 4
    fr = np.repeat(np.arange(n_f), len(xs))
    p = np.tile(np.arange(len(xs)), n_f)
    table = make_table(fr, fr * 0.1, p, xs[p] * PX, ys[p] * PX, zs[p], meta={"frame_interval": 0.1})
    good = 0
    for frame in render.render_frames(table, shape=(110, 130), optics=OPTICS, camera=cam, seed=int(sep_um * 100)):
        df = locate_3d(prepare(frame, bg_size=3 * calib.size), calib)
        near, dmin = _nearest_true(df, xs, ys)
        dz = np.abs(df["z"].to_numpy() - zs[near])
        # whatever is reported sits on a particle (within 1.5 px = 150 nm) at its z (5 % of the 4 um depth),
        # or its window is left badly explained (chi2 > 4: the frame's models miss light there) and says so
        ok = (dmin < 1.5) & (dz < 0.2e-6)
        assert np.all(ok | (df["chi2"].to_numpy() > 4)), (df, zs)
        good += len(df) == len(xs) and sorted(near) == list(range(len(xs)))
    assert good >= 3, good


def test_masked_ncc_equals_opencv_masked_mode():
    """The edge-cut correlation (visible part of the template only) is OpenCV's masked TM_CCOEFF_NORMED."""
    import cv2

    from ptrack.calibration import _masked_ncc

    rng = np.random.default_rng(8)
    win = rng.normal(size=(49, 47)).astype(np.float32)
    t = rng.normal(size=(41, 41)).astype(np.float32)
    for r0, r1, c0, c1 in ((3, 41, 0, 30), (0, 20, 5, 41), (0, 41, 0, 41)):
        mask = np.zeros_like(t)
        mask[r0:r1, c0:c1] = 1
        ref = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED, mask=mask)
        np.testing.assert_allclose(_masked_ncc(win, t, r0, r1, c0, c1), ref, atol=1e-5)


def test_locate_frame_3d_is_prepare_then_locate(calib):
    """The pipeline's one call gives the same particles as preparing and matching in two steps."""
    from ptrack.calibration import locate_frame_3d, prepare_gdpt

    img = next(iter(render.calibration_images([0.3e-6], shape=(72, 72), optics=OPTICS, camera=CAMERA, seed=5)))
    raw = img.astype(np.float32) + 100.0
    a = locate_frame_3d(raw, calib, background="spatial", snr=6.0, cm_min=0.5)
    b = locate_3d(prepare_gdpt(raw, calib, background="spatial"), calib, snr=6.0, cm_min=0.5)
    assert len(a) == 1
    pd.testing.assert_frame_equal(a, b)
    assert a["z"].iloc[0] == pytest.approx(0.3e-6, abs=0.05e-6)



def _calibration_cli_end_to_end(tmp_path, cal_args, optics):
    """``ptrack render-calibration --out DIR [cal_args]``, a movie of 4 particles within +-2.6 um of focus rendered
    with ``optics`` and the default camera, ``ptrack track movie --calib DIR/calib.tif``: (true z, median z of the
    track nearest each particle, or NaN)."""
    from ptrack.cli import main
    from ptrack.table import make_table, read_table

    assert main(["render-calibration", "--out", str(tmp_path / "cal")] + cal_args) == 0
    if optics is None:      # the movie seen through the calibration's own optics (as written in calib_params.json)
        import json

        optics = render.Optics(**json.loads((tmp_path / "cal" / "calib_params.json").read_text())["optics"])
    px = render.sample_pixel_size(optics, render.Camera().pixel_pitch)
    xs, ys = np.array([70.0, 190.0, 70.0, 190.0]), np.array([70.0, 70.0, 190.0, 190.0])
    zs = np.array([-2.6e-6, -1.2e-6, 1.1e-6, 2.4e-6])
    fr = np.repeat(np.arange(6), 4)
    p = np.tile(np.arange(4), 6)
    table = make_table(fr, fr * 0.1, p, (xs[p] + 0.3 * fr) * px, ys[p] * px, zs[p],
                       meta={"frame_interval": 0.1, "pixel_size": px})
    render.render_movie(table, tmp_path / "mv", (256, 256), optics=optics, seed=3, progress=False)
    main(["track", str(tmp_path / "mv" / "movie.tif"), "--calib", str(tmp_path / "cal" / "calib.tif"),
          "--out", str(tmp_path / "t.parquet")])
    if not (tmp_path / "t.parquet").exists():
        return zs, np.full(4, np.nan)
    med = read_table(tmp_path / "t.parquet").groupby("particle")[["x_px", "y_px", "z"]].median()
    # each true particle's nearest track (median position) within 3 px, by the one matching rule
    truth = pd.DataFrame({"frame": 0, "x_px": np.asarray(xs, float) + 0.75, "y_px": np.asarray(ys, float)})
    tracks = pd.DataFrame({"frame": 0, "x_px": med["x_px"].to_numpy(float), "y_px": med["y_px"].to_numpy(float)})
    ti, mi = match_truth(truth, tracks, 3.0)
    got = np.full(len(truth), np.nan)
    got[ti] = med["z"].to_numpy()[mi]
    return zs, got


@pytest.mark.slow
def test_render_calibration_defaults_track_end_to_end(tmp_path):
    """``ptrack render-calibration`` with every default gives a stack ``ptrack track --calib`` uses end to end:
    each of 4 particles (default camera, the calibration's optics: its default astigmatism; within +-2.6 um of
    focus, on both sides) tracked at its own height (median z within 0.5 um) and place (within 3 px)."""
    zs, got = _calibration_cli_end_to_end(tmp_path, [], None)
    assert np.all(np.abs(got - zs) < 0.5e-6), (zs, got)



@pytest.mark.parametrize("astigmatism, page, z_range", [
    (1.2e-7, 64, (-3e-6, 3e-6)),        # cropped pages, the bead in the centre
    (1.2e-7, 200, (-3e-6, 3e-6)),       # full-frame pages, the bead 13 px off the page centre, at a sub-pixel place
    (0.0, 200, (0.0, 3e-6)),            # no astigmatism (rings), one side of focus
])
def test_xy_unbiased_at_every_defocus(astigmatism, page, z_range):
    """Isolated particles at random sub-pixel places: the mean x, y error is below 0.1 px in every z bin (the
    template's reference point is the bead's centre on every page, and its own noise does not shift the matches:
    each template is symmetrised about the bead; with the page's noise kept, the full-frame case was 0.12-0.13 px
    off at +2 um)."""
    optics = render.Optics(astigmatism=astigmatism)
    cam = cam_cal = render.Camera(photons=20000.0, background=15.0)
    px = render.sample_pixel_size(optics, cam.pixel_pitch)
    z = np.round(np.arange(z_range[0], z_range[1] + 1e-12, 0.2e-6), 12)
    pos = ((page - 1) // 2 + 11.3, (page - 1) // 2 - 7.6) if page > 100 else None
    cal = build_calibration(np.stack(list(render.calibration_images(z, shape=(page, page), optics=optics,
                                                                    camera=cam_cal, seed=1, position=pos))), z, px)
    rng = np.random.default_rng(7)
    bins = np.linspace(z_range[0], z_range[1], 7)[1:-1] if z_range[0] < 0 else np.linspace(*z_range, 6)[1:]
    for zb in bins:
        err = []
        for _ in range(16):
            x, y = 40 + rng.uniform(-0.5, 0.5), 40 + rng.uniform(-0.5, 0.5)
            img = next(render.calibration_images([zb], shape=(80, 80), optics=optics, camera=cam, position=(x, y),
                                                 seed=int(rng.integers(1 << 30))))
            df = locate_frame_3d(img, cal)
            ti, fi = match_truth(pd.DataFrame({"frame": [0], "x_px": [x], "y_px": [y]}),
                                 pd.DataFrame({"frame": 0, "x_px": df["x_px"].to_numpy(float),
                                               "y_px": df["y_px"].to_numpy(float)}), 2.0)
            assert len(fi) == 1, (zb, df)        # the particle's nearest localisation, within 2 px
            i = int(fi[0])
            err.append((df["x_px"].iloc[i] - x, df["y_px"].iloc[i] - y))
        mean = np.mean(err, axis=0)
        assert np.all(np.abs(mean) < 0.1), (zb, mean)


def test_snr_bound_from_candidate_spectra_equals_opencv_bound():
    """_snr_bound from _candidates' FFT correlations of the same frame (_BOUND_FFT) gives OpenCV's bound (to its
    float32 rounding), +inf where the window leaves the frame, as the per-page TM_CCORR path."""
    import ptrack.calibration as C
    from ptrack.calibration import Calibration
    from ptrack.gdpt.ncc import Templates

    rng = np.random.default_rng(3)
    tm = Templates(np.outer(*[np.exp(-0.5 * (np.arange(T) - T // 2) ** 2 / s ** 2)] * 2).astype(np.float32)
                   for T, s in ((9, 1.5), (13, 2.5), (19, 4.0)))
    cal = Calibration(list(tm), np.array([0.0, 1e-6, 2e-6]), np.array([[4.0, 4.0], [6.0, 6.0], [9.0, 9.0]]), None,
                      "test", {})
    pad = 12
    img = rng.normal(0, 1, (90, 90)).astype(np.float32)
    for (y, x), k in zip(((30, 30), (50, 44), (70, 20), (3, 60)), (2, 1, 0, 2)):
        T = tm[k].shape[0]
        h = T // 2
        img[max(y - h, 0):y + h + 1, x - h:x + h + 1] += 50 * tm[k][max(h - y, 0):]
    padded = np.pad(img, pad)
    mask = np.ones(img.shape, bool)
    spectra = {}
    rr, cc, _, kk = C._candidates(padded, pad, tm, cal, img.shape, mask, 3, -1.0, with_page=True, spectra=spectra)
    rr, cc, kk = np.concatenate([rr, [-5, 95, 45]]), np.concatenate([cc, [0, 95, 1]]), np.concatenate([kk, [2, 2, 1]])
    assert set(spectra["C"]) == {0, 1, 2}
    a = C._snr_bound(padded, pad, tm, cal, rr, cc, kk, 0.7)
    b = C._snr_bound(padded, pad, tm, cal, rr, cc, kk, 0.7, spectra)
    assert np.array_equal(np.isfinite(a), np.isfinite(b)) and not np.isfinite(a).all() and np.isfinite(a).sum() > 20
    fin = np.isfinite(a)
    np.testing.assert_allclose(b[fin], a[fin], rtol=1e-5, atol=1e-3)
    old = C._BOUND_FFT
    try:
        C._BOUND_FFT = False
        np.testing.assert_array_equal(C._snr_bound(padded, pad, tm, cal, rr, cc, kk, 0.7, spectra), a)
    finally:
        C._BOUND_FFT = old


def test_frame_spectrum_shared_variances_give_the_same_maxima():
    """FrameSpectrum.ncc_max with the windows' variances from box_var (_box_var, _ncc_region_max_var; one map per
    template size, shared by the pages of that size) gives bitwise the maxima and pages of the per-page kernel."""
    from ptrack.gdpt.ncc import FrameSpectrum, Templates

    rng = np.random.default_rng(5)
    tm = Templates(rng.normal(0, 1, (T, T)).astype(np.float32) + np.float32(2.0) for T in (9, 15, 9, 21, 15))
    img = rng.normal(0, 1, (70, 64)).astype(np.float32)
    img[20:41, 30:51] += 3 * tm[3]
    img[:5] = 0.0                                         # a constant strip (zero padding): -1 there
    for floor in (-1.0, 0.3):
        maps = []
        for shared in (False, True):
            fs = FrameSpectrum(img)
            cmap = np.full((40, 38), -1.0, np.float32)
            which = np.zeros(cmap.shape, np.int32)
            for k, (top, left) in enumerate(((0, 0), (3, 2), (1, 5), (0, 4), (6, 1))):
                fs.ncc_max(tm, k, top, left, cmap, which, floor, shared_var=shared)
            maps.append((cmap, which))
        assert maps[0][0].tobytes() == maps[1][0].tobytes() and np.array_equal(maps[0][1], maps[1][1])
        assert (maps[0][1] > 0).any() and (maps[0][0] > 0.3).any()


def test_add_window_equals_numpy_in_place_slice_ops():
    """_Residual.add / subtract by _add_window (_WINDOW_ADD) leave bitwise NumPy's in-place slice sums; windows
    that do not fit take the NumPy path."""
    import ptrack.calibration as C

    rng = np.random.default_rng(9)
    img = rng.normal(0, 10, (60, 70)).astype(np.float32)
    mod = rng.normal(0, 3, (21, 21)).astype(np.float32)
    res = C._Residual(img.copy(), 5, None, 1.0)
    ref = img.copy()
    sl = (slice(7, 28), slice(40, 61))
    res.subtract(sl, mod)
    ref[sl] -= mod
    assert res.img.tobytes() == ref.tobytes()
    res.add(sl, mod * np.float32(0.7))
    ref[sl] += mod * np.float32(0.7)
    assert res.img.tobytes() == ref.tobytes()
    assert not res._fast((slice(50, 71), slice(0, 21)), mod)            # leaves the frame
    assert not res._fast(sl, mod.astype(np.float64))
    old = C._WINDOW_ADD
    try:
        C._WINDOW_ADD = False
        assert not res._fast(sl, mod)
    finally:
        C._WINDOW_ADD = old


@pytest.mark.parametrize("shape, rad, p", [((171, 171), 21, 0.002), ((64, 90), 15, 0.01), ((40, 33), 7, 0.05),
                                           ((10, 80), 3, 0.2), ((30, 30), 20, 0.0)])
def test_grow_mask_by_rows_equals_opencv_elliptic_dilation(shape, rad, p):
    """_grow_mask through _dilate_rows (_MASK_ROWS) gives cv2.dilate's mask with the elliptic element, edges
    included."""
    import cv2

    import ptrack.calibration as C

    sig = (np.random.default_rng(rad).random(shape) < p).astype(np.uint8)
    sig[0, -1] = 1 if p else 0                          # a signal pixel in a corner
    ref = cv2.dilate(sig, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))) > 0
    got = C._grow_mask(sig, rad)
    assert C._ellipse_rows(rad) is not None and got.dtype == bool and np.array_equal(got, ref)
