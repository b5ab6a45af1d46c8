"""Preprocessing: inversion, background (spatial/temporal), threshold, median; brightfield needs inversion."""
import numpy as np
import pytest

from ptrack.errors import UserError
from ptrack.motion import detection_scores
from ptrack.preprocess import (invert, median3, noise_sigma, prepare, subtract_background,
                               temporal_background, threshold)


def spots(shape, xs, ys, amp, s):
    rr, cc = np.indices(shape)
    out = np.zeros(shape)
    for x, y in zip(xs, ys):
        out += amp * np.exp(-((cc - x) ** 2 + (rr - y) ** 2) / (2 * s * s))
    return out


def test_invert():
    f = np.array([[10, 200], [65535, 0]], np.uint16)
    np.testing.assert_array_equal(invert(f, 65535), [[65525, 65335], [0, 65535]])
    assert invert(f).max() == 65535 and invert(f).dtype == np.float32


def test_spatial_background_removes_gradient_keeps_spots():
    rng = np.random.default_rng(0)
    shape = (200, 240)
    rr, cc = np.indices(shape)
    bg = 300 + 0.8 * cc + 0.3 * rr + 40 * np.sin(rr / 60.0)
    xs, ys = rng.uniform(20, 220, 12), rng.uniform(20, 180, 12)
    sig = spots(shape, xs, ys, 500.0, 1.5)
    frame = rng.normal(bg + sig, 5.0)
    img = prepare(frame, bg_size=20)
    resid = img - sig
    far = sig < 1.0
    assert abs(np.median(resid[far])) < 1.0          # background to ~0 within a fifth of the noise
    assert np.abs(resid[far]).mean() < 2.0 * 5.0 * 0.8
    peaks = img[np.round(ys).astype(int), np.round(xs).astype(int)]
    true_peaks = sig[np.round(ys).astype(int), np.round(xs).astype(int)]
    np.testing.assert_allclose(peaks, true_peaks, rtol=0.06, atol=15)
    assert noise_sigma(resid) == pytest.approx(5.0, rel=0.15)


def test_temporal_background_and_subtract():
    rng = np.random.default_rng(1)
    pattern = rng.uniform(100, 400, (40, 50))
    frames = []
    for i in range(15):                               # a spot moving across a fixed-pattern background
        frames.append(pattern + spots(pattern.shape, [5 + 3 * i], [20], 800, 1.5))
    bg = temporal_background(np.array(frames), n_sample=15)
    np.testing.assert_allclose(bg, pattern, atol=1e-3)
    out = subtract_background(frames[7], bg)
    assert out[20, 26] > 700 and abs(np.median(out)) < 1e-3
    with pytest.raises(UserError, match="shape"):
        prepare(frames[0], background=np.zeros((3, 3)))
    with pytest.raises(UserError, match="not known"):
        prepare(frames[0], background="rolling-ball")


def test_median_and_threshold():
    img = np.zeros((9, 9), np.float32)
    img[4, 4] = 1000
    assert median3(img).max() == 0                    # hot pixel removed
    t = threshold(np.arange(10, dtype=np.float32).reshape(2, 5), 4.5)
    assert (t[t > 0] >= 5).all() and (t == 0).sum() == 5


def test_brightfield_needs_and_gets_inversion():
    render = pytest.importorskip("sim.render")
    from ptrack.locate import locate
    from ptrack.table import make_table

    cam = render.Camera(photons=30000.0, background=3000.0)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    rng = np.random.default_rng(2)
    gy, gx = np.meshgrid(np.arange(15, 110, 20), np.arange(15, 110, 20), indexing="ij")
    xs, ys = gx.ravel() + rng.uniform(-1, 1, gx.size), gy.ravel() + rng.uniform(-1, 1, gx.size)
    n = len(xs)
    table = make_table(np.zeros(n, int), np.zeros(n), np.arange(n), xs * px, ys * px, np.zeros(n))
    frame = next(render.render_frames(table, shape=(120, 120), camera=cam, brightfield=True, seed=3))
    assert np.median(frame) > frame[np.round(ys).astype(int), np.round(xs).astype(int)].mean()   # dark particles

    def recall(df):          # fraction of the particles found within 1 px, number of detections farther
        s = detection_scores(df, np.c_[xs, ys], max_px=1.0)
        return s["recall"], s["n_found"] - len(s["pairs"][0])

    r_bf, false_bf = recall(locate(frame, sigma=1.4, brightfield=True))
    r_plain, _ = recall(locate(frame, sigma=1.4, gain=cam.gain, offset=cam.offset))
    assert r_bf >= 0.95 and false_bf == 0
    assert r_plain < 0.2


def test_signed_background_keeps_both_lobes_of_brightfield_rings():
    """Defocused brightfield rings (a dark ring with a bright centre) on a sloping field: the signed (running
    median) background follows the field and leaves both lobes of every ring, with their sign, nothing
    thresholded."""
    rng = np.random.default_rng(5)
    shape = (160, 200)
    rr, cc = np.indices(shape)
    field = 1000 + 0.5 * cc + 0.2 * rr
    ring = np.zeros(shape)
    centres = [(40, 40), (100, 50), (160, 45), (70, 115), (130, 120)]
    for x, y in centres:
        d = np.hypot(cc - x, rr - y)
        ring += -120 * np.exp(-((d - 9) ** 2) / 8.0) + 80 * np.exp(-(d ** 2) / 8.0)
    raw = field + ring + rng.normal(0, 5, shape)
    far = np.ones(shape, bool)
    for x, y in centres:
        far &= np.hypot(cc - x, rr - y) > 16
    for size in (40, 60, 100):
        img = prepare(raw, brightfield=True, bg_size=size, max_value=2000.0, signed=True)
        err = img + ring          # inverted: the dark ring positive, the bright centre negative
        assert abs(np.median(err[far])) < 2.0 and np.std(err[far]) < 7.0, size    # noise sigma 5
        assert np.abs(err[~far]).mean() < 5.0, size
        assert img[~far].min() < -50 and img[~far].max() > 80                      # both signs kept
