"""Real images (trackpy's own brightfield test movie) and a simple image model that is not our renderer."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.special import erf

from ptrack.locate import locate, mortensen_sigma
from ptrack.motion import detection_scores

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "trackpy_image_sequence"


@pytest.mark.skipif(not (REAL / "frames").is_dir(), reason="shared real data not present")
def test_trackpy_movie_default_settings():
    """Frame 1 of trackpy's movie, no option at all: polarity found (dark), >= 95 % of trackpy's 344
    positions within 1 px (measured 96.5 %). Extras against the reference (72 %) are not bounded here: trackpy's
    minmass=140 cuts its in-focus mass mode (its mass histogram has its valley at ~100, and ~100 in-focus
    particles lie between 100 and 140), and its separation=10 px drops in-focus particles 5-10 px from a
    brighter one; no knob-free rule reproduces those two cuts. Bounded instead: every extra must be a feature
    trackpy's own locate finds with the cuts relaxed."""
    import cv2

    ref = pd.read_csv(REAL / "reference" / "trackpy_locate_frame0.csv")[["x", "y"]].to_numpy()
    im = cv2.imread(str(REAL / "frames" / "T76S3F00001.png"), cv2.IMREAD_UNCHANGED)
    df = locate(im)
    assert (df["polarity"] == -1).all()
    assert (df["frame"] == 0).all()
    xy = df[["x_px", "y_px"]].to_numpy()
    d = detection_scores(xy, ref, max_px=1.0)["nearest"]     # each reference position to our nearest one
    assert (d < 1.0).mean() >= 0.95, (d < 1.0).mean()
    assert np.median(d) < 0.3
    # the extras (72 % of 344) are not ghosts: trackpy's own locate reports them once its two cuts are
    # relaxed (minmass 140 -> 60, below the valley of its mass histogram at ~100; separation 10 -> 5 px, so
    # particles 5-10 px from a brighter one count). Measured: 10.7 % of ours are not such a feature
    trackpy = pytest.importorskip("trackpy")
    trackpy.quiet()
    f = trackpy.locate(255 - im, diameter=9, minmass=60, separation=5)
    extra = 1 - detection_scores(xy, f[["x", "y"]].to_numpy(), max_px=1.0)["precision"]
    assert extra <= 0.15, extra


def _erf_spot(x0, y0, s, shape):
    H, W = shape
    k = np.sqrt(2) * s
    ex = 0.5 * (erf((np.arange(W) - x0 + 0.5) / k) - erf((np.arange(W) - x0 - 0.5) / k))
    ey = 0.5 * (erf((np.arange(H) - y0 + 0.5) / k) - erf((np.arange(H) - y0 - 0.5) / k))
    return np.outer(ey, ex)


def _ring(x0, y0, radius, width, shape):
    """A thin annulus (Gaussian radial profile), sampled 4x per pixel and averaged: a defocused image."""
    H, W = shape
    o = (np.arange(4) + 0.5) / 4 - 0.5
    yy = np.arange(H)[:, None, None, None] + o[None, None, :, None]
    xx = np.arange(W)[None, :, None, None] + o[None, None, None, :]
    r = np.hypot(xx - x0, yy - y0)
    return np.exp(-(r - radius) ** 2 / (2 * width ** 2)).mean(axis=(2, 3))


def _grid(shape, spacing, rng, margin=16):
    gy, gx = np.meshgrid(np.arange(margin, shape[0] - margin + 1, spacing),
                         np.arange(margin, shape[1] - margin + 1, spacing), indexing="ij")
    return gx.ravel() + rng.uniform(-0.5, 0.5, gx.size), gy.ravel() + rng.uniform(-0.5, 0.5, gx.size)


def _scores(df, xs, ys, r=2.0):
    """Recall, precision, RMSE per axis (px) within r px: ptrack.motion.detection_scores."""
    s = detection_scores(df[["x_px", "y_px"]].to_numpy(), np.c_[xs, ys], max_px=r)
    return s["recall"], s["precision"], s["rmse"]


@pytest.mark.parametrize("s", [1.2, 2.0, 3.0])
def test_model_gaussian_spots_at_several_sizes_near_the_bound(s):
    """Fluorescence: Gaussian spots of one size per frame (defocus), Poisson noise, uneven
    illumination; no option: recall and precision >= 0.95, RMSE <= 1.5x Mortensen's bound."""
    rng = np.random.default_rng(11)
    shape = (192, 192)
    N, b0 = 3000.0, 20.0
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    illum = b0 * (1 + 0.8 * np.exp(-((xx - 60) ** 2 + (yy - 120) ** 2) / (2 * 70.0 ** 2)))
    rec, prec, errs = [], [], []
    for _ in range(3):
        xs, ys = _grid(shape, 24, rng)
        lam = illum + sum(N * _erf_spot(x, y, s, shape) for x, y in zip(xs, ys))
        frame = rng.poisson(lam).astype(np.uint16)
        df = locate(frame)
        r, p, e = _scores(df, xs, ys)
        rec.append(r)
        prec.append(p)
        errs.append(e)
        assert (df["polarity"] == 1).all()
    bound = mortensen_sigma(N, illum.mean(), s)
    rmse = np.sqrt(np.mean(np.square(errs), axis=0))
    assert min(rec) >= 0.95 and min(prec) >= 0.95, (rec, prec)
    assert np.all(rmse <= 1.5 * bound), (rmse, bound)


def test_model_defocused_fluorescence_rings_radial_symmetry_near_the_bound():
    """Defocused fluorescent beads: bright rings (radius 5 px) with a dark centre, Poisson noise. No option:
    each ring is one detection (not a necklace), its centre by radial symmetry within 1.6x the exact
    Cramer-Rao bound of this image model (measured 1.44-1.52x), and the reported uncertainty within
    2x of the scatter."""
    rng = np.random.default_rng(7)
    shape = (192, 192)
    xs, ys = _grid(shape, 32, rng)
    lam = np.full(shape, 20.0)
    for x, y in zip(xs, ys):
        rr = _ring(x, y, 5.0, 1.0, shape)
        lam += 4000 * rr / rr.sum()
    df = locate(rng.poisson(lam).astype(np.uint16))
    r, p, e = _scores(df, xs, ys)
    assert r >= 0.95 and p >= 0.95, (r, p)
    assert (df["method"] == "radial").mean() > 0.9
    # exact bound of the model: Fisher information of the expected image, by central differences
    small = (48, 48)

    def mu(x):
        rr = _ring(x, 24.3, 5.0, 1.0, small)
        return 20 + 4000 * rr / rr.sum()

    d = (mu(24.3 + 1e-3) - mu(24.3 - 1e-3)) / 2e-3
    bound = 1 / np.sqrt(np.sum(d * d / mu(24.3)))
    assert np.all(e <= 1.6 * bound), (e, bound)
    assert 0.5 < df["sigma_x_px"].median() / e.mean() < 2.0


def brightfield_rings_frame(sign, rng, shape=(192, 192)):
    """One absorption-brightfield frame of defocused particles on a 32 px grid: a centre of sign ``sign``
    inside a ring of the other, on a field brighter to the right, with three faint dark dust blobs.
    Returns (uint16 frame, true x, true y) in px. Shared with bench/bench_detect.py."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    field = 2000.0 * (1 + 0.2 * xx / shape[1])
    dust = np.prod([1 - 0.04 * np.exp(-((xx - dx) ** 2 + (yy - dy) ** 2) / (2 * 14.0 ** 2))
                    for dx, dy in rng.uniform(0, 192, (3, 2))], axis=0)
    xs, ys = _grid(shape, 32, rng)
    img = np.ones(shape)
    for x, y in zip(xs, ys):
        img += sign * (0.25 * _erf_spot(x, y, 1.6, shape) * 2 * np.pi * 1.6 ** 2 / 4
                       - 0.12 * _ring(x, y, 5.0, 1.2, shape))
    return rng.poisson(np.clip(field * img * dust / 3, 0, None)).astype(np.uint16), xs, ys


@pytest.mark.parametrize("sign", [1, -1])
def test_model_brightfield_rings_both_polarities(sign):
    """Absorption brightfield out of focus: a centre of one sign inside a ring of the other (sign=+1:
    bright centre, dark ring; -1: dark centre, bright ring) on an uneven bright field with dust (large
    faint dark blobs); no option: recall and precision >= 0.95, centres within 0.3 px RMS."""
    frame, xs, ys = brightfield_rings_frame(sign, np.random.default_rng(5))
    df = locate(frame)
    r, p, e = _scores(df, xs, ys)
    assert r >= 0.95 and p >= 0.95, (r, p)
    assert np.all(e < 0.3), e


def test_profile_centres_exact_on_symmetric_images_with_a_background_gradient():
    """The free radial-profile fit (ptrack.image.radial.profile_centres) finds the centre of noise-free
    rotationally symmetric images of three kinds (a thin ring, a bright centre in a dark J0 ring, a
    Gaussian) to < 0.01 px on a sloped, curved background from a start 0.6 px off; image_extent reaches
    the ring, has_dip tells the bright centre in a dark ring from the Gaussian."""
    from scipy.special import j0

    from ptrack.image.radial import has_dip, image_extent, profile_centres

    shape = (64, 64)
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(float)
    x0, y0 = 31.37, 32.71
    r = np.hypot(xx - x0, yy - y0)
    bg = 0.02 * (xx - 32) - 0.015 * (yy - 32) + 2e-4 * ((xx - 32) ** 2 - (yy - 32) ** 2)
    images = {"ring": 10 * np.exp(-(r - 7.0) ** 2 / 2.0), "bf": 5 * j0(0.6 * r) * np.exp(-r ** 2 / 50.0),
              "gauss": 10 * np.exp(-r ** 2 / 8.0)}
    for name, im in images.items():
        pf = profile_centres(im + bg, [33], [31], 14, [x0 + 0.6], [y0 - 0.4], noise=0.1)
        assert pf["ok"][0], name
        assert abs(pf["x"][0] - x0) < 0.01 and abs(pf["y"][0] - y0) < 0.01, (name, pf["x"], pf["y"])
    ext = image_extent(images["ring"], [x0], [y0], [0.1], [3], [20])
    assert 8 <= ext[0] <= 12, ext
    dips = has_dip(np.stack([images["bf"], images["gauss"]]).reshape(-1, 64), [x0, x0], [y0, y0 + 64], [0.1, 0.1],
                   [15, 15])
    assert dips.tolist() == [True, False], dips
