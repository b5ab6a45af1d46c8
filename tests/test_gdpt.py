"""GDPT with calibration stacks as people record them: full frames, coarse steps, several beads, metadata heights.

The main optics here is written in this file and shares nothing with the project's renderer: an astigmatic
Gaussian (widths sigma_x,y = s0 sqrt(1 + ((z -+ c) / d)^2), pixel-integrated, Poisson noise), whose image grows
~linearly with |z| like a defocused one and whose elongation flips across focus like a cylindrical lens's.
"""
import warnings

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy.special import erf

from ptrack.calibration import build_calibration, load_calibration, locate_frame_3d
from ptrack.errors import UserError
from ptrack.motion.truth import match_truth

S0, C, D = 1.3, 3e-6, 2e-6        # px, m, m
PX = 1e-7                          # m per pixel


def widths(z):
    z = np.asarray(z, float)
    return S0 * np.sqrt(1 + ((z - C) / D) ** 2), S0 * np.sqrt(1 + ((z + C) / D) ** 2)


def gaussian_frame(shape, xs, ys, zs, photons, bg, rng):
    """Pixel-integrated astigmatic Gaussians (expected photons -> Poisson counts), uint16."""
    H, W = shape
    img = np.full((H, W), float(bg))
    for x, y, z in zip(xs, ys, zs):
        sx, sy = widths(z)
        h = int(6 * max(sx, sy)) + 3
        c0, c1 = max(int(x) - h, 0), min(int(x) + h + 1, W)
        r0, r1 = max(int(y) - h, 0), min(int(y) + h + 1, H)
        if c1 <= c0 or r1 <= r0:
            continue
        gx = np.diff(0.5 * erf((np.arange(c0, c1 + 1) - 0.5 - x) / (np.sqrt(2) * sx)))
        gy = np.diff(0.5 * erf((np.arange(r0, r1 + 1) - 0.5 - y) / (np.sqrt(2) * sy)))
        img[r0:r1, c0:c1] += photons * gy[:, None] * gx[None, :]
    return rng.poisson(img).astype(np.uint16)


def _score(df, xs, ys, zs, r=2.0):
    """(true particles with a localisation within r px, z errors of those, localisations) by the one rule."""
    if len(df) == 0:
        return 0, np.array([]), 0
    truth = pd.DataFrame({"frame": 0, "x_px": np.asarray(xs, float), "y_px": np.asarray(ys, float)})
    found = pd.DataFrame({"frame": 0, "x_px": df["x_px"].to_numpy(float), "y_px": df["y_px"].to_numpy(float)})
    ti, fi = match_truth(truth, found, r)        # each true particle to its nearest localisation (roles swapped)
    return len(ti), df["z"].to_numpy()[fi] - np.asarray(zs)[ti], len(df)


@pytest.mark.parametrize("half", [10e-6, 20e-6, 30e-6])
def test_full_frame_coarse_stack_independent_optics(half):
    """One bead in the middle of 512^2 pages, 2 um steps over +-half: isolated particles at random heights come
    back with recall >= 0.95 and z RMSE < 1 % of the depth (the step is 2-7 % of it: resolved far below it)."""
    rng = np.random.default_rng(int(half * 1e6))
    z = np.arange(-half, half + 1e-12, 2e-6)
    stack = np.stack([gaussian_frame((512, 512), [255.3], [256.6], [zk], 2e5, 20.0, rng) for zk in z])
    cal = build_calibration(stack, z, PX)
    assert cal.info["rejected"] == {} and cal.info["n_sub"] > 1
    assert cal.size < 200            # templates cut to the image, not the 512 px page
    g = np.arange(4) * 120 + 75.0
    found = n = n_det = 0
    errs = []
    for _ in range(2):
        xs, ys = (a.ravel() + rng.uniform(-3, 3, 16) for a in np.meshgrid(g, g))
        zs = rng.uniform(-0.95 * half, 0.95 * half, 16)
        df = locate_frame_3d(gaussian_frame((512, 512), xs, ys, zs, 2e5, 20.0, rng), cal)
        k, e, m = _score(df, xs, ys, zs)
        found, n, n_det = found + k, n + 16, n_det + m
        errs.extend(e)
    errs = np.array(errs)
    assert found / n >= 0.95 and found / n_det >= 0.95
    rmse = np.sqrt(np.mean(errs ** 2))
    assert rmse < 0.01 * cal.depth, (rmse, cal.depth)


def test_full_frame_coarse_stack_renderer():
    """The same with the project's renderer (NA 0.75, astigmatic lens, defocused rings): +-10 um in 2 um steps."""
    render = pytest.importorskip("sim.render")
    optics = render.Optics(astigmatism=3e-7)
    cam = render.Camera(photons=1e6, background=15.0)
    z = np.arange(-10e-6, 10.0001e-6, 2e-6)
    stack = np.stack(list(render.calibration_images(z, shape=(512, 512), optics=optics, camera=cam, seed=1)))
    px = render.sample_pixel_size(optics, cam.pixel_pitch)
    cal = build_calibration(stack, z, px)
    assert cal.info["rejected"] == {}
    rng = np.random.default_rng(3)
    xy = np.array([[110.0, 160.0], [360.0, 290.0], [250.0, 130.0], [340.0, 420.0], [120.0, 400.0]]) + rng.uniform(
        -0.5, 0.5, (5, 2))
    zs = np.array([-9.5e-6, -4.7e-6, 0.3e-6, 4.9e-6, 9.4e-6])
    table = pd.DataFrame({"frame": 0, "t": 0.0, "particle": np.arange(5), "x": xy[:, 0] * px, "y": xy[:, 1] * px,
                          "z": zs})
    frame = next(iter(render.render_frames(table, shape=(512, 512), optics=optics, camera=cam, seed=4)))
    df = locate_frame_3d(frame, cal)
    k, e, m = _score(df, xy[:, 0], xy[:, 1], zs)
    assert k == 5 and m == 5
    assert np.sqrt(np.mean(e ** 2)) < 0.01 * cal.depth, e


def test_several_beads_averaged_and_bad_pages_named():
    """Three beads on full frames: averaged into one calibration whose spread gives a z error; a bead near the
    edge is dropped on the pages where its (growing) image is cut; blank pages are rejected and named."""
    rng = np.random.default_rng(7)
    z = np.arange(-8e-6, 8.0001e-6, 1e-6)
    beads = [(130.4, 140.2), (380.7, 260.3), (250.2, 12.0)]     # the last one 12 px from the top edge
    pages = [gaussian_frame((512, 512), [b[0] for b in beads], [b[1] for b in beads], [zk] * 3, 2e5, 20.0, rng)
             for zk in z]
    blank = rng.poisson(20.0, (512, 512)).astype(np.uint16)
    stack = np.stack(pages + [blank])
    zz = np.append(z, 9e-6)
    with pytest.warns(UserWarning, match="rejected: 17"):
        cal = build_calibration(stack, zz, PX)
    assert cal.info["n_beads"] == 3
    assert list(cal.info["rejected"]) == [17] and "no bead" in cal.info["rejected"][17]
    # the edge bead: where its image's 95 % light disc reaches past 12 px (|z| > ~6 um) it is cut by the edge
    edge = [i for i, xy in enumerate(cal.info["bead_xy"]) if xy[1] < 50]
    assert len(edge) == 1
    cut = cal.info["rejected_per_bead"][edge[0]]
    assert "edge" in cut[16] and all(k not in cut for k in range(4, 13))      # whole within 4 um of focus
    assert max(cal.info["beads_per_page"]) == 3 and min(cal.info["beads_per_page"]) == 2
    # identical beads: no offset between them, and a z error estimate far below the step
    assert np.nanmax(np.abs(cal.info["bead_dz"])) < 0.3e-6
    assert 0 < cal.info["z_error_beads"] < 0.1e-6
    assert cal.info["z_error"] >= cal.info["z_error_beads"]


@pytest.mark.parametrize("n_beads", [1, 2])
def test_z_error_estimate_against_truth(n_beads):
    """Calibration.info["z_error"] predicts the z RMSE of particles measured on the calibration (truth known):
    within 0.7-2x of it, for one bead (no spread between beads to go by) and for two (whose spread alone is
    far below the measured error)."""
    rng = np.random.default_rng(40 + n_beads)
    z = np.arange(-6e-6, 6.0001e-6, 1e-6)
    bx, by = [60.3, 180.6][:n_beads], [70.2, 150.7][:n_beads]
    stack = np.stack([gaussian_frame((240, 240), bx, by, [zk] * n_beads, 2e4, 20.0, rng) for zk in z])
    cal = build_calibration(stack, z, PX)
    g = np.arange(3) * 70 + 50.0
    errs = []
    for _ in range(4):
        xs, ys = (a.ravel() + rng.uniform(-3, 3, 9) for a in np.meshgrid(g, g))
        zs = rng.uniform(-5.5e-6, 5.5e-6, 9)
        df = locate_frame_3d(gaussian_frame((240, 240), xs, ys, zs, 2e4, 20.0, rng), cal)
        errs.extend(_score(df, xs, ys, zs)[1])
    assert len(errs) >= 30
    rmse = float(np.sqrt(np.mean(np.square(errs))))
    assert 0.7 * rmse <= cal.info["z_error"] <= 2.0 * rmse, (cal.info["z_error"], rmse)
    if n_beads == 2:
        assert cal.info["z_error_beads"] < 0.7 * rmse


def test_heights_beside_in_metadata_and_implausible(tmp_path):
    """calib_z.csv beside the stack is found without a flag; ImageJ spacing and OME PhysicalSizeZ are read;
    a step or origin in micrometres given as metres, or a step far too small for the images, is refused."""
    rng = np.random.default_rng(2)
    z = np.arange(-6e-6, 6.0001e-6, 1e-6)
    stack = np.stack([gaussian_frame((96, 96), [47.5], [48.0], [zk], 2e5, 20.0, rng) for zk in z])
    ij = tmp_path / "ij" / "stack.tif"
    ij.parent.mkdir()
    tifffile.imwrite(ij, stack, imagej=True, resolution=(10.0, 10.0), metadata={"axes": "ZYX", "unit": "um",
                                                                                "spacing": 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = load_calibration(ij, z0=-6e-6)
        assert "ImageJ spacing" in cal.info["z_source"]
        assert cal.z[0] == pytest.approx(-6e-6) and cal.z[-1] == pytest.approx(6e-6)
        assert cal.pixel_size == pytest.approx(1e-7)
        pd.DataFrame({"page": np.arange(len(z)), "z": z + 1e-6}).to_csv(ij.parent / "calib_z.csv", index=False)
        cal = load_calibration(ij)
        assert cal.info["z_source"].endswith("calib_z.csv") and cal.z[0] == pytest.approx(-5e-6)
        ome = tmp_path / "stack.ome.tif"
        tifffile.imwrite(ome, stack, metadata={"axes": "ZYX", "PhysicalSizeZ": 1.0, "PhysicalSizeZUnit": "µm",
                                               "PhysicalSizeX": 0.1, "PhysicalSizeXUnit": "µm"})
        cal = load_calibration(ome)
        assert "OME" in cal.info["z_source"] and np.diff(cal.info["page_z"]) == pytest.approx(1e-6)
        for kw in ({"z_step": 1.0}, {"z_step": 1e-6, "z0": -6.0}, {"z_step": 1e-9}):
            with pytest.raises(UserError):
                load_calibration(ij, **kw)


@pytest.mark.parametrize("z", [-6e-6, -3e-6, 0.0, 4e-6, 8e-6])
def test_symmetric_centre_of_defocused_images(z):
    """The centre of a noisy defocused astigmatic image (independent optics: widths up to 6 S0) from its point
    symmetry is within 0.1 px of the truth on average over sub-pixel places, and closer than the region's own
    thresholded centroid (:func:`ptrack.gdpt.stack.find_beads`) is."""
    from ptrack.gdpt.stack import find_beads, symmetric_centre

    rng = np.random.default_rng(11)
    err, err0 = [], []
    for _ in range(24):
        x, y = 60 + rng.uniform(-0.5, 0.5), 58 + rng.uniform(-0.5, 0.5)
        img = gaussian_frame((120, 120), [x], [y], [z], 4000.0, 20.0, rng)
        beads, p, _ = find_beads(img)
        b = max(beads, key=lambda b: b["flux"])
        cy, cx = symmetric_centre(p, b["y"], b["x"], b["r95"])
        err.append((cx - x, cy - y))
        err0.append((b["x"] - x, b["y"] - y))
    err, err0 = np.array(err), np.array(err0)
    assert np.all(np.abs(err.mean(0)) < 0.1), err.mean(0)
    assert np.sqrt(np.mean(err ** 2)) <= np.sqrt(np.mean(err0 ** 2)) + 0.02, (err, err0)


def test_weighted_ncc_is_the_weighted_correlation_at_every_shift():
    """ptrack.calibration._weighted_ncc against the weighted Pearson correlation written out per shift; all weights
    1: OpenCV's TM_CCOEFF_NORMED."""
    import cv2

    from ptrack.calibration import _weighted_ncc

    rng = np.random.default_rng(4)
    t = rng.normal(size=(9, 9)).astype(np.float32)
    win = rng.normal(size=(13, 13)).astype(np.float32)
    w = np.ones_like(win)
    np.testing.assert_allclose(_weighted_ncc(win, w, t), cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED), atol=1e-5)
    w = rng.uniform(0.0, 1.0, size=win.shape).astype(np.float32)
    got = _weighted_ncc(win, w, t)
    for i in range(5):
        for j in range(5):
            ww, x = w[i:i + 9, j:j + 9].astype(float), win[i:i + 9, j:j + 9].astype(float)
            tm, xm = (ww * t).sum() / ww.sum(), (ww * x).sum() / ww.sum()
            want = (ww * (t - tm) * (x - xm)).sum() / np.sqrt((ww * (t - tm) ** 2).sum() * (ww * (x - xm) ** 2).sum())
            assert abs(got[i, j] - want) < 1e-4


def test_still_core_is_the_step_by_step_check():
    """_still_there's numba kernel (_still_core) gives the answers of the NumPy steps (_still_steps), also with the
    thresholds on the correlation maximum and at the SNR itself (where its amplitude bound leaves it undecided)."""
    import math

    import ptrack.calibration as C
    from ptrack.calibration import Calibration
    from ptrack.gdpt.ncc import Templates, ncc

    rng = np.random.default_rng(11)
    tm = Templates(np.outer(*[np.exp(-0.5 * (np.arange(T) - T // 2) ** 2 / s ** 2)] * 2).astype(np.float32)
                   for T, s in ((9, 1.5), (15, 3.0), (41, 8.0)))
    cal = Calibration(list(tm), np.array([0.0, 1e-6, 2e-6]), np.array([[4.0, 4.0], [7.0, 7.0], [20.4, 19.6]]), None,
                      "test", {})
    pad = 25
    img = rng.normal(0, 1, (90, 90)).astype(np.float32)
    for y, x, k in ((30, 30, 1), (50, 44, 2), (70, 20, 0)):
        T = tm[k].shape[0]
        img[y - T // 2:y + T // 2 + 1, x - T // 2:x + T // 2 + 1] += 30 * tm[k]
    padded = np.pad(img, pad)
    n = 0
    for r, c, k in zip(rng.integers(-5, 95, 60), rng.integers(-5, 95, 60), rng.integers(0, 3, 60)):
        t = tm[k]
        T = t.shape[0]
        top, left = r + pad - int(round(cal.centers[k, 0])) - 1, c + pad - int(round(cal.centers[k, 1])) - 1
        cms, snrs = [-1.0, 0.3], [-np.inf, 0.5, 5.0]
        if top >= 0 and left >= 0 and top + T + 2 <= padded.shape[0] and left + T + 2 <= padded.shape[1]:
            win = padded[top:top + T + 2, left:left + T + 2]
            R = ncc(win, t)
            i, j = divmod(int(np.argmax(R)), 3)
            den = float(np.dot(t.ravel(), t.ravel()))
            snr = float(np.vdot(t, np.ascontiguousarray(win[i:i + T, j:j + T]))) / den * math.sqrt(den)
            cms.append(float(R.max()))
            snrs += [snr, snr * (1 + 1e-7), snr * (1 - 1e-7)]
        for cm in cms:
            for sm in snrs:
                args = (padded, pad, tm, cal, r, c, k, cm, sm, 1.0)
                assert C._still_there(*args) == C._still_steps(*args)
                n += C._still_there(*args)
    assert n > 0


def test_snr_bound_bounds_the_residual_check():
    """The bound that lets later rounds skip candidates (ptrack.calibration._snr_bound) is never below the SNR the
    full check (_still_there) finds: just above the bound, the check says no; just below, it may say yes."""
    from ptrack.calibration import Calibration, _snr_bound, _still_there

    rng = np.random.default_rng(7)
    tm = [np.outer(*[np.exp(-0.5 * (np.arange(T) - T // 2) ** 2 / s ** 2)] * 2).astype(np.float32)
          for T, s in ((9, 1.5), (15, 3.0))]
    cal = Calibration(tm, np.array([0.0, 1e-6]), np.array([[4.0, 4.0], [7.0, 7.0]]), None, "test", {})
    pad = 10
    img = rng.normal(0, 1, (80, 80)).astype(np.float32)
    for y, x in ((30, 30), (50, 44)):
        img[y - 7:y + 8, x - 7:x + 8] += 40 * tm[1]
    padded = np.pad(img, pad)
    rr, cc = rng.integers(5, 75, 40), rng.integers(5, 75, 40)
    kk = rng.integers(0, 2, 40)
    b = _snr_bound(padded, pad, tm, cal, rr, cc, kk, 1.0)
    assert np.all(np.isfinite(b))
    for r, c, k, bi in zip(rr, cc, kk, b):
        assert not _still_there(padded, pad, tm, cal, r, c, k, -1.0, bi + 1e-4 * abs(bi) + 1e-6, 1.0)
    assert any(_still_there(padded, pad, tm, cal, r, c, k, -1.0, bi - 1e-3 * abs(bi), 1.0) for r, c, k, bi in zip(rr, cc, kk, b))


def test_smooth_pages_keeps_quadratic_z_variation_and_cuts_noise():
    """Pixel values quadratic in z pass the z smoothing unchanged (also at the ends); white noise keeps the
    quadratic Savitzky-Golay filter's variance factor (3 (3 w^2 - 7) / (4 w (w^2 - 4)), 0.486 for 5 pages) in
    the interior; unevenly stepped stacks are returned as they are."""
    from ptrack.gdpt.build import smooth_pages

    rng = np.random.default_rng(3)
    K, w = 40, 5
    z = 1e-6 + 0.25e-6 * np.arange(K)
    a, b, c = (rng.normal(size=(8, 9)) for _ in range(3))
    zn = (z - z.mean()) / 1e-6
    pages = [(a + b * q + c * q * q).astype(np.float32) for q in zn]
    out = smooth_pages(pages, z, w)
    np.testing.assert_allclose(np.stack(out), np.stack(pages), atol=2e-4)
    noise = [rng.normal(size=(64, 64)).astype(np.float32) for _ in range(K)]
    var = np.var(np.stack(smooth_pages(noise, z, w))[w:-w])
    expect = 3 * (3 * w * w - 7) / (4 * w * (w * w - 4))
    assert abs(var / expect - 1) < 0.03
    zu = z.copy()
    zu[5:] += 0.1e-6
    assert smooth_pages(noise, zu, w) is noise
    assert smooth_pages(noise, z, 1) is noise


def test_stage_times_summed_in_the_calibration():
    """locate_frame_3d adds the wall seconds of its stages to calib.info["stage_times_s"], summed over frames: every
    stage is there, none negative, their sum within the calls' own elapsed time, and a second frame adds to them.
    The particles still come back (within 2 px, z within 1 % of the depth of the truth)."""
    import time

    rng = np.random.default_rng(3)
    half = 10e-6
    z = np.arange(-half, half + 1e-12, 2e-6)
    stack = np.stack([gaussian_frame((256, 256), [127.3], [128.6], [zk], 2e5, 20.0, rng) for zk in z])
    cal = build_calibration(stack, z, PX)
    xs, ys, zs = np.array([70.2, 180.6]), np.array([80.4, 170.9]), np.array([-4e-6, 5e-6])
    frame = gaussian_frame((256, 256), xs, ys, zs, 2e5, 20.0, rng)
    t0 = time.perf_counter()
    df = locate_frame_3d(frame, cal)
    el1 = time.perf_counter() - t0
    st = dict(cal.info["stage_times_s"])
    assert {"prepare", "mask", "candidates", "match", "split", "refine", "edge"} <= set(st), st
    assert min(st.values()) >= 0 and sum(st.values()) <= el1 + 1e-3
    k, e, _ = _score(df, xs, ys, zs)
    assert k == 2 and np.abs(e).max() < 0.01 * cal.depth, (k, e)
    t0 = time.perf_counter()
    locate_frame_3d(frame, cal)
    el2 = time.perf_counter() - t0
    st2 = cal.info["stage_times_s"]
    assert all(st2[s] >= st[s] for s in st) and sum(st2.values()) > sum(st.values())
    assert sum(st2.values()) <= el1 + el2 + 2e-3


def test_hit_index_prepared_candidates_give_the_same_checks():
    """_HitIndex.prepare (distances and overlap SNRs of all candidates against the hits at a round's start, in one
    array operation) then nearest_q / overlap_q, with hits added after it, equal nearest / overlap_snr exactly."""
    from ptrack.calibration import _HitIndex

    rng = np.random.default_rng(5)
    tm = [np.zeros((T, T), np.float32) for T in (9, 15, 21, 31)]

    def hit():
        return {"y_px": rng.uniform(0, 200), "x_px": rng.uniform(0, 200), "page": int(rng.integers(0, 4)),
                "top": int(rng.integers(0, 220)), "left": int(rng.integers(0, 220)), "snr": rng.uniform(-5, 300)}

    idx = _HitIndex([hit() for _ in range(12)], tm)
    rr, cc = rng.integers(0, 200, 300), rng.integers(0, 200, 300)
    cand = [{"page": int(k), "top": t, "left": lf} for k, t, lf in zip(rng.integers(0, 4, 300),
                                                                         rng.integers(0, 220, 300),
                                                                         rng.integers(0, 220, 300))]
    idx.prepare(rr, cc, np.array([h["top"] for h in cand]), np.array([h["left"] for h in cand]),
                np.array([tm[h["page"]].shape[0] for h in cand]))
    n_ov = 0
    for q in range(300):
        if q in (100, 200):
            idx.add(hit())
        assert idx.nearest_q(q, rr[q], cc[q]) == idx.nearest(rr[q], cc[q])
        assert idx.overlap_q(q, cand[q]) == idx.overlap_snr(cand[q])
        n_ov += idx.overlap_snr(cand[q]) > 0
    assert 30 < n_ov < 290
    empty = _HitIndex([], tm)
    empty.prepare(rr[:5], cc[:5])
    assert empty.nearest_q(0, rr[0], cc[0]) == np.inf


def test_model_sums_are_numpys_float32_sums():
    """_model_sums (sum t^2, sum t w, sum max(t, 0) in one numba pass) gives NumPy's float32 pairwise sums exactly,
    for blocks below, at and above numpy's 128-element pairwise block and sizes up to full-resolution templates, and
    _Residual.model returns the same hit and model with it as with the NumPy sums."""
    from ptrack import calibration as C

    rng = np.random.default_rng(3)
    for T in (1, 2, 7, 8, 11, 12, 16, 23, 48, 61, 150, 301):
        t = (rng.standard_normal((T, T)) * rng.uniform(0.01, 50)).astype(np.float32)
        img = (rng.standard_normal((T + 9, T + 13)) * 30).astype(np.float32)
        a, b = int(rng.integers(0, 10)), int(rng.integers(0, 14))
        w = img[a:a + T, b:b + T]
        d, n, p = C._model_sums(t, img, a, b)
        assert d == (t * t).sum() and n == (t * w).sum() and p == np.maximum(t, 0.0).sum()
    tm = [(np.exp(-((np.arange(21) - 10.0) ** 2)[:, None] / 18 - ((np.arange(21) - 10.0) ** 2)[None] / 30)
           - 0.05).astype(np.float32)]
    padded = np.zeros((90, 90), np.float32)
    padded[10:80, 10:80] = (rng.standard_normal((70, 70)) * 0.1).astype(np.float32)
    padded[30:51, 33:54] += 3.0 * tm[0]
    res = C._Residual(padded, 10, tm, 0.1)
    old = C._MODEL_SUMS
    try:
        for di, dj in ((0.0, 0.0), (0.3, -0.2)):
            out = []
            for flag in (False, True):
                C._MODEL_SUMS = flag
                h = {"page": 0, "top": 30, "left": 33, "di": di, "dj": dj}
                sl, mod = res.model(h, cap=2.0)
                out.append((h, sl, mod))
            assert out[0][0] == out[1][0] and out[0][1] == out[1][1] and np.array_equal(out[0][2], out[1][2])
            assert out[0][2].dtype == out[1][2].dtype == np.float32 and out[0][0]["amp"] > 2.5
    finally:
        C._MODEL_SUMS = old
