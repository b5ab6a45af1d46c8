"""Knob-free detection: false alarms on empty frames, polarity, per-particle size."""
import numpy as np
import pytest
from scipy.special import erf

from ptrack.image.detect import detect, false_alarm_threshold


def _empty(kind, rng, shape=(1024, 1024)):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    if kind == "poisson":
        return rng.poisson(20.0, shape)
    if kind == "poisson_dim":
        return rng.poisson(2.0, shape)
    if kind == "scmos":
        # per-pixel read noise (gamma-distributed rms, a few hot-noise pixels), gain 2, offset 100
        rms = rng.gamma(2.0, 1.5, shape)
        return np.round(100 + 2.0 * rng.poisson(20.0, shape) + rms * rng.normal(size=shape))
    if kind == "uneven":
        lam = 50 + 400 * np.exp(-((xx - 300) ** 2 + (yy - 600) ** 2) / (2 * 250.0 ** 2))
        return rng.poisson(lam)
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["poisson", "poisson_dim", "scmos", "uneven"])
def test_empty_frames_about_one_false_detection_per_million_pixels(kind):
    rng = np.random.default_rng(1)
    n = 0
    npx = 0
    for _ in range(2):
        f = _empty(kind, rng).astype(np.float32)
        for pol in (1, -1):
            n += len(detect(f, polarity=pol, offset=100.0 if kind == "scmos" else 0.0)["rows"])
            npx += f.size
    # stated rate 1e-6 per px; 8 Mpx examined: expect ~8, refuse 3x more
    assert n / npx * 1e6 < 3.0, n / npx * 1e6


def test_threshold_decreases_with_rate_and_snr_override():
    assert false_alarm_threshold((1.0, 2.0), 1e-4) < false_alarm_threshold((1.0, 2.0), 1e-6)
    rng = np.random.default_rng(0)
    f = rng.poisson(20.0, (128, 128)).astype(np.float32)
    assert detect(f, snr=3.0)["threshold"] == 3.0


def _spot(x0, y0, s, shape):
    H, W = shape
    k = np.sqrt(2) * s
    ex = 0.5 * (erf((np.arange(W) - x0 + 0.5) / k) - erf((np.arange(W) - x0 - 0.5) / k))
    ey = 0.5 * (erf((np.arange(H) - y0 + 0.5) / k) - erf((np.arange(H) - y0 - 0.5) / k))
    return np.outer(ey, ex)


@pytest.mark.parametrize("sign", [1, -1])
def test_polarity_from_data_and_sizes_per_particle(sign):
    rng = np.random.default_rng(2)
    shape = (160, 160)
    pos = [(30, 30, 1.2), (100, 40, 1.2), (40, 110, 3.0), (120, 120, 3.0)]
    lam = np.full(shape, 500.0)
    for x, y, s in pos:
        lam += sign * 6000 * _spot(x, y, s, shape) * (s / 1.2) ** 2 / 3
    d = detect(rng.poisson(np.clip(lam, 0, None)).astype(np.float32))
    assert d["polarity"] == sign
    assert len(d["rows"]) == 4
    order = np.argsort(d["cols"] + 1000 * (d["rows"] > 80))
    sizes = d["scale"][order]
    assert sizes[:2].max() < sizes[2:].min()


# ---------------------------------------------------------------------------------------------
# ring centres by the rim's vote (ptrack.image.rings)
# ---------------------------------------------------------------------------------------------

def _ring_image(x0, y0, R, shape, photons=4000.0, blur=0.9):
    """A defocused fluorescent bead: half its light in a uniform disk of radius R, half in a rim at R (px)."""
    from scipy.special import erfc

    yy, xx = np.mgrid[:shape[0], :shape[1]]
    r = np.hypot(xx - x0, yy - y0)
    disk = 0.5 * erfc((r - R) / (np.sqrt(2) * blur))
    rim = np.exp(-(r - R) ** 2 / (2 * blur ** 2))
    return photons * (0.5 * disk / disk.sum() + 0.5 * rim / rim.sum())


@pytest.mark.parametrize("kind", ["poisson", "scmos", "uneven"])
def test_ring_maps_alone_keep_their_false_alarm_rate_on_empty_frames(kind):
    """The ring maps, run on empty frames whatever the gate says: at most their share of the stated rate."""
    import cv2

    from ptrack.image.detect import DEFAULT_SCALES, FALSE_ALARM_RATE, RING_RATE_SHARE, bandpass, noise_maps
    from ptrack.image.rings import RING_RADII, ring_maps_candidates, ring_scale

    rng = np.random.default_rng(3)
    f = _empty(kind, rng).astype(np.float32)
    work = cv2.medianBlur(f, 3)
    bg, nz = noise_maps(f, tile=64, step=2)
    n = 0
    for pol in (1, -1):
        bands = {s: pol * bandpass(work, s) for s in {ring_scale(R, DEFAULT_SCALES) for R in RING_RADII}}
        n += len(ring_maps_candidates(bands, pol * (f - bg), nz, RING_RATE_SHARE * FALSE_ALARM_RATE,
                                      DEFAULT_SCALES)["rows"])
    # 2 x 1 Mpx examined at 0.5e-6 per px: ~1 expected (the bound is conservative); refuse 3x the rate
    assert n / (2 * f.size) < 3 * RING_RATE_SHARE * FALSE_ALARM_RATE, n


def test_defocused_rings_give_one_detection_at_each_centre():
    """Rings of radius 5-10 px (recall 0 without the ring maps: every blob detection lands on a rim)."""
    rng = np.random.default_rng(4)
    shape = (240, 240)
    truth = [(40.3, 42.6, 9.0), (120.7, 40.2, 7.0), (200.2, 41.5, 5.0), (41.8, 120.4, 10.0),
             (119.6, 121.3, 9.0), (199.4, 118.8, 6.0), (80.5, 199.7, 8.0), (160.1, 200.3, 9.0)]
    lam = np.full(shape, 30.0)
    for x, y, R in truth:
        lam += _ring_image(x, y, R, shape)
    d = detect(rng.poisson(lam).astype(np.float32))
    assert d["polarity"] == 1
    found = np.c_[d["cols"], d["rows"]].astype(float)
    assert len(found) == len(truth), found
    for x, y, R in truth:
        dist = np.hypot(found[:, 0] - x, found[:, 1] - y)
        k = int(np.argmin(dist))
        assert dist[k] < 1.5 and d["ring"][k], (x, y, R, found[k])


def test_blob_frames_do_not_call_the_ring_maps(monkeypatch):
    """Spots of several sizes are round, not rim pieces: the gate keeps the ring maps (and their cost) away."""
    import ptrack.image.detect as D

    called = []
    orig = D.ring_maps_candidates
    monkeypatch.setattr(D, "ring_maps_candidates", lambda *a, **k: called.append(1) or orig(*a, **k))
    rng = np.random.default_rng(5)
    shape = (256, 256)
    lam = np.full(shape, 40.0)
    for k in range(36):
        x, y = 20 + 40 * (k % 6) + rng.uniform(-3, 3), 20 + 40 * (k // 6) + rng.uniform(-3, 3)
        s = (1.0, 1.5, 2.5)[k % 3]
        lam += 3000 * _spot(x, y, s, shape)
    d = detect(rng.poisson(lam).astype(np.float32))
    assert len(d["rows"]) == 36 and not d["ring"].any()
    assert not called


def test_ring_support_wants_the_ring_all_round():
    """A bright spot at distance R from a point covers one or two sectors of its annulus: not a ring."""
    from ptrack.image.rings import ring_support

    shape = (80, 80)
    ring = _ring_image(40.0, 40.0, 8.0, shape)
    spot = 2000 * _spot(48.0, 40.0, 1.2, shape)
    args = dict(rows=[40], cols=[40], radius=[8.0], width=[2.0], sign=[1.0], noise=[1.0])
    assert ring_support(ring, **args)[0]
    assert not ring_support(spot, **args)[0]
    # a dark ring (negative in the image) is a ring of sign -1, not of sign +1
    assert ring_support(-ring, **dict(args, sign=[-1.0]))[0]
    assert not ring_support(-ring, **args)[0]


def _maxima_brute(z, thr, edge, signed):
    # 8-neighbour maxima by the rule, written plainly: v = z (or |z|) not at or below thr, no neighbour (times the
    # pixel's sign) above v, no earlier neighbour in raster order equal to it
    H, W = z.shape
    out = []
    for r in range(edge, H - edge):
        for c in range(edge, W - edge):
            v = abs(z[r, c]) if signed else z[r, c]
            if v <= thr:
                continue
            sg = (1.0 if z[r, c] > 0 else -1.0) if signed else 1.0
            nb = [(sg * z[r + dr, c + dc], (dr, dc)) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
            if all(not (u > v or (u == v and (dr < 0 or (dr == 0 and dc < 0)))) for u, (dr, dc) in nb):
                out.append((r, c))
    return out


def test_local_maxima_as_the_rule_with_ties_nans_and_empty_runs():
    from ptrack.image.peaks import local_maxima

    rng = np.random.default_rng(3)
    for t in range(40):
        H, W = int(rng.integers(3, 40)), int(rng.integers(3, 90))     # rows shorter and longer than a scan run
        z = rng.normal(size=(H, W)).astype(np.float32 if t % 2 else np.float64)
        if t % 3 == 0:
            z = np.round(z * 2) / 2                                     # ties
        if t % 4 == 0:
            z[rng.random(z.shape) < 0.03] = np.nan
        if t % 5 == 0:
            z[:, : W // 2] = -5.0                                       # runs with |z| above thr, none above it
        for signed in (False, True):
            for edge in (1, 2):
                for thr in (-0.5, 1.0, 2.5):
                    r, c = local_maxima(z, thr, edge, signed)
                    assert r.dtype == np.int64 and c.dtype == np.int64
                    assert list(zip(r.tolist(), c.tolist())) == _maxima_brute(z, thr, edge, signed)


def test_detect_reads_any_byte_order_and_dtype_as_the_same_values():
    # a frame as tifffile may hand it over (big-endian) or as a float or int: the same counts, the same detections
    # (a dozen spots: enough candidates for the ring evidence's dip tests, which read the frame; and a ring)
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:128, :128]
    spots = 30 + sum(500 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 8) for x, y in rng.uniform(10, 118, (12, 2)))
    ring = 30 + 800 * np.exp(-((np.hypot(xx - 64.2, yy - 60.7) - 6) ** 2) / 2)
    for mu in (spots, ring):
        img = rng.poisson(mu)
        ref = detect(img.astype("<u2"))
        assert len(ref["rows"]) >= 1
        for dt in (">u2", ">f4", "<f8", "<i4"):
            d = detect(img.astype(dt))
            for k in ("rows", "cols", "scale", "snr", "ring"):
                assert np.array_equal(d[k], ref[k]), (dt, k)
