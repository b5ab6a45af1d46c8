"""Detection and localisation against ground truth and the Cramer-Rao (Mortensen) bound."""
import numpy as np
import pandas as pd
import pytest
from scipy.special import erf

from ptrack.motion import match_truth
from ptrack.locate import cramer_rao_bound, estimate_sigma, find_peaks, fit_spots, locate, mortensen_sigma
from ptrack.preprocess import prepare


def gaussian_frame(xs, ys, shape, s, photons, bg, gain, offset, rng, read_noise=1.0):
    """Pixel-integrated Gaussian spots, Poisson photons, camera gain/offset/read noise -> uint16."""
    H, W = shape
    cols, rows = np.arange(W), np.arange(H)
    lam = np.full(shape, float(bg))
    k = np.sqrt(2) * s
    for x, y in zip(xs, ys):
        ex = 0.5 * (erf((cols - x + 0.5) / k) - erf((cols - x - 0.5) / k))
        ey = 0.5 * (erf((rows - y + 0.5) / k) - erf((rows - y - 0.5) / k))
        lam += photons * np.outer(ey, ex)
    e = rng.poisson(lam) + rng.normal(0, read_noise, shape)
    return np.clip(np.round(e * gain + offset), 0, 65535).astype(np.uint16)


def grid_positions(shape, spacing, rng, margin=10):
    gy, gx = np.meshgrid(np.arange(margin, shape[0] - margin + 1, spacing), np.arange(margin, shape[1] - margin + 1, spacing),
                         indexing="ij")
    return gx.ravel() + rng.uniform(-1, 1, gx.size), gy.ravel() + rng.uniform(-1, 1, gx.size)


def match(found_xy, true_xy, r=2.0):
    """One frame through the toolkit's one truth-matching rule (ptrack.motion.match_truth).

    Returns (found - true offsets of the pairs, mask of found spots that have a true one within r px,
    number of distinct true spots matched).
    """
    found_xy, true_xy = np.asarray(found_xy, float).reshape(-1, 2), np.asarray(true_xy, float).reshape(-1, 2)
    f = pd.DataFrame({"frame": np.zeros(len(found_xy), int), "x_px": found_xy[:, 0], "y_px": found_xy[:, 1]})
    t = pd.DataFrame({"frame": np.zeros(len(true_xy), int), "x_px": true_xy[:, 0], "y_px": true_xy[:, 1]})
    fi, ti = match_truth(f, t, max_px=r)
    ok = np.zeros(len(found_xy), bool)
    ok[fi] = True
    return found_xy[fi] - true_xy[ti], ok, len(np.unique(ti))


def test_mortensen_formula_limits():
    # no background: the bound is sigma_a / sqrt(N)
    sa = np.sqrt(1.3 ** 2 + 1 / 12)
    assert mortensen_sigma(1000, 0.0, 1.3) == pytest.approx(sa / np.sqrt(1000), rel=1e-6)
    # with background: against direct numerical integration of Mortensen eq. 5
    N, b, s = 2000, 12.0, 1.4
    sa2 = s * s + 1 / 12
    tau = 2 * np.pi * sa2 * b / N
    t = np.linspace(1e-9, 1, 200001)
    integral = np.trapezoid(np.log(t) / (1 + t / tau), t)
    assert mortensen_sigma(N, b, s) == pytest.approx(np.sqrt(sa2 / N / (1 + integral)), rel=1e-3)
    assert mortensen_sigma(N, b, s) > mortensen_sigma(N, 0, s)


def test_mle_reaches_cramer_rao_on_gaussian_spots():
    rng = np.random.default_rng(3)
    s, N, bg, gain, offset = 1.3, 2000.0, 10.0, 2.0, 100.0
    errs, reported, recall, found, n_true = [], [], 0, 0, 0
    for _ in range(6):
        xs, ys = grid_positions((160, 160), 20, rng)
        frame = gaussian_frame(xs, ys, (160, 160), s, N, bg, gain, offset, rng)
        df = locate(frame, sigma=s, gain=gain, offset=offset, read_noise=1.0)
        e, ok, nrec = match(df[["x_px", "y_px"]].to_numpy(), np.c_[xs, ys])
        errs.append(e)
        reported.append(df["sigma_x_px"].to_numpy()[ok])
        recall += nrec
        found += len(df)
        n_true += len(xs)
        assert ok.all()                      # no false positive
    e = np.concatenate(errs)
    crlb = mortensen_sigma(N, bg + 1.0 / 1.0, s)   # read noise 1 e- adds ~1 photon-equivalent variance
    rmse = np.sqrt((e ** 2).mean(0))
    assert recall == n_true and found == n_true
    assert np.all(np.abs(e.mean(0)) < 0.01)          # unbiased (no pixel locking)
    assert np.all(rmse < 1.15 * crlb), (rmse, crlb)
    assert np.all(rmse > 0.8 * crlb)                  # and not suspiciously better than the bound
    # the per-spot uncertainty (inverse Fisher information) predicts the scatter
    assert np.median(np.concatenate(reported)) == pytest.approx(rmse.mean(), rel=0.15)


def test_estimate_sigma_and_hot_pixels():
    rng = np.random.default_rng(4)
    xs, ys = grid_positions((120, 120), 24, rng)
    frame = gaussian_frame(xs, ys, (120, 120), 1.7, 3000, 8, 1.0, 50, rng)
    assert estimate_sigma([frame], offset=50) == pytest.approx(1.7, rel=0.05)
    frame[7, 9] = 60000                                # a hot pixel is not a particle
    df = locate(frame, sigma=1.7, offset=50)
    _, ok, nrec = match(df[["x_px", "y_px"]].to_numpy(), np.c_[xs, ys])
    assert ok.all() and nrec == len(xs)


def test_separation_merges_nothing_when_spots_are_apart_and_find_peaks_returns_sorted_types():
    img = np.zeros((40, 40), np.float32)
    img[10, 10] = img[10, 17] = 100.0
    r, c, v = find_peaks(img, 1.0, threshold=1.0, median=False)
    assert sorted(zip(r.tolist(), c.tolist())) == [(10, 10), (10, 17)]
    r, c, v = find_peaks(img, 1.0, threshold=1.0, separation=8, median=False)
    assert len(r) == 1


def test_fit_brightfield_least_squares():
    rng = np.random.default_rng(5)
    xs, ys = grid_positions((80, 80), 20, rng)
    dark = gaussian_frame(xs, ys, (80, 80), 1.5, 4000, 0, 1.0, 0, rng, read_noise=0)
    frame = (3000 - dark.astype(float) + rng.normal(0, 5, dark.shape)).astype(np.uint16)   # dark spots on bright field
    img = prepare(frame, brightfield=True)
    rows, cols, _ = find_peaks(img, 1.5)
    fit = fit_spots(img, rows, cols, 1.5, poisson=False)
    e, ok, nrec = match(np.c_[fit["x"], fit["y"]], np.c_[xs, ys])
    assert nrec == len(xs) and np.sqrt((e ** 2).mean()) < 0.1


def test_rendered_airy_spots_within_1p2_of_cramer_rao():
    """The renderer's diffraction PSF (63x NA 0.75, 519 nm, 103 nm pixels) at 2000 detected photons."""
    render = pytest.importorskip("sim.render")
    from ptrack.table import make_table

    cam = render.Camera(photons=2000 / 0.6, background=20.0)
    px = render.sample_pixel_size(render.Optics(), cam.pixel_pitch)
    rng = np.random.default_rng(6)
    rows = []
    for f in range(8):
        xs, ys = grid_positions((150, 150), 18, rng, margin=12)
        rows.append(pd.DataFrame({"frame": f, "particle": np.arange(len(xs)), "x_px": xs, "y_px": ys}))
    truth = pd.concat(rows, ignore_index=True)
    table = make_table(truth["frame"], truth["frame"] * 0.1, truth["particle"], truth["x_px"] * px, truth["y_px"] * px,
                       np.zeros(len(truth)), meta={"frame_interval": 0.1})
    errs, n_found, n_rec, n_true, fitted_s = [], 0, 0, 0, []
    for f, frame in enumerate(render.render_frames(table, shape=(150, 150), camera=cam, seed=7)):
        t = truth[truth["frame"] == f]
        df = locate(frame, sigma=1.4, gain=cam.gain, offset=cam.offset, read_noise=cam.read_noise)
        e, ok, nrec = match(df[["x_px", "y_px"]].to_numpy(), t[["x_px", "y_px"]].to_numpy())
        errs.append(e)
        n_found += len(df)
        n_rec += nrec
        n_true += len(t)
        fitted_s.append(df["size"].to_numpy())
        assert ok.all()
    e = np.concatenate(errs)
    # the exact bound of the rendered (Airy) PSF, from its Fisher information
    psf = render.psf_image(render.Optics(), px, 0.0, size=32, oversample=8)
    crb = np.array(cramer_rao_bound(psf, 8, 2000.0, 20 * 0.6, cam.read_noise))
    rmse = np.sqrt((e ** 2).mean(0))
    assert n_rec / n_true >= 0.98 and n_rec / n_found >= 0.98
    assert np.all(np.abs(e.mean(0)) < 0.01)
    assert np.all(rmse < 1.2 * crb), (rmse, crb)
    assert np.all(rmse > 0.9 * crb)


@pytest.mark.parametrize("fwhm_apart", [1.3, 1.0])
def test_close_pairs_both_found_and_unbiased(fwhm_apart):
    """Two spots 1.3 FWHM apart (two maxima of the matched filter, formerly one suppressed by the 2.5 sigma
    separation) and 1.0 FWHM apart (a single maximum: split by the two-spot likelihood test) are both found,
    and the joint fit keeps their centres unbiased (fitted one by one, each is pulled towards the other)."""
    rng = np.random.default_rng(11)
    s, N, bg, gain, offset = 1.5, 3000.0, 10.0, 2.0, 100.0
    d = fwhm_apart * 2.3548 * s
    errs, along = [], []
    for _ in range(4):
        cx, cy = grid_positions((160, 160), 28, rng, margin=16)
        ang = rng.uniform(0, np.pi, cx.size)
        ux, uy = np.cos(ang) * d / 2, np.sin(ang) * d / 2
        xs, ys = np.r_[cx + ux, cx - ux], np.r_[cy + uy, cy - uy]
        frame = gaussian_frame(xs, ys, (160, 160), s, N, bg, gain, offset, rng)
        df = locate(frame, sigma=s, gain=gain, offset=offset, read_noise=1.0)
        found = df[["x_px", "y_px"]].to_numpy()
        true = np.c_[xs, ys]
        back, ok, n_distinct = match(true, found, r=1.0)       # each true spot to its nearest localisation
        assert ok.all(), f"{np.sum(~ok)} of {len(true)} spots missed"
        assert n_distinct == len(true) and len(df) == len(true)     # one localisation each
        e = -back                                                   # found - true, in the order of true
        errs.append(e)
        # error along the pair axis (a one-by-one fit pulls each centre towards its partner: negative)
        n = len(cx)
        along.append(np.r_[(e[:n, 0] * ux + e[:n, 1] * uy), -(e[n:, 0] * ux + e[n:, 1] * uy)] / (d / 2))
    e = np.concatenate(errs)
    rmse = np.sqrt(np.mean(np.sum(e ** 2, axis=1) / 2))
    assert rmse < 0.1, rmse
    along = np.concatenate(along)
    assert abs(np.mean(along)) < 4 * np.std(along) / np.sqrt(len(along)) + 0.01, np.mean(along)


def test_stage_times_in_the_cache_survive_a_map_refresh():
    # locate sums its stages' wall seconds over the frames sharing a cache, across detect's refresh of the maps
    from ptrack.image.detect import MAP_REFRESH

    rng = np.random.default_rng(4)
    xs, ys = grid_positions((96, 96), 20, rng)
    cache = {}
    n = 0
    for i in range(MAP_REFRESH + 2):
        f = gaussian_frame(xs, ys, (96, 96), 1.3, 2000.0, 20.0, 1.0, 100.0, rng)
        n += len(locate(f, offset=100.0, frame_no=i, cache=cache))
        if i == 0:
            after_first = dict(cache["stage_times_s"])
    assert n > 0
    tm = cache["stage_times_s"]
    assert set(tm) == {"detect", "fit", "centres"}
    assert all(v >= 0 for v in tm.values())
    assert tm["detect"] > after_first["detect"] and tm["fit"] > after_first["fit"]   # not reset by the refresh
    assert cache["age"] == 2        # the maps were measured again after MAP_REFRESH frames


@pytest.mark.parametrize("dark", [False, True])
def test_batch_is_locate_frame_by_frame_with_one_cache_and_the_first_polarity(dark):
    # ptrack.image.locate.batch (trackpy.batch's role, the movie's table made once) gives the table of locate on
    # each frame with one cache, the polarity decided on the first frame with particles and then fixed
    from ptrack.locate import batch

    rng = np.random.default_rng(11)
    frames = [np.full((80, 80), 100, np.uint16)]         # a blank first frame: no particle, no polarity yet
    for i in range(4):
        xs, ys = grid_positions((80, 80), 18, rng)
        f = gaussian_frame(xs, ys, (80, 80), 1.4, 2500.0, 30.0, 1.0, 100.0, rng)
        frames.append((4000 - f).astype(np.uint16) if dark else f)
    cache = {}
    pol = None
    chunks = []
    for i, f in enumerate(frames):
        df = locate(f, offset=0.0 if dark else 100.0, brightfield=pol, frame_no=10 + 2 * i, cache=cache)
        pol = bool(df["polarity"].iloc[0] < 0) if len(df) and pol is None else pol
        chunks.append(df)
    want = pd.concat(chunks, ignore_index=True)
    got = batch(frames, offset=0.0 if dark else 100.0, frame_numbers=range(10, 20, 2))
    assert len(got) > 4 * 9 and (got["frame"] != 10).all()
    assert set(got["polarity"]) == {-1 if dark else 1}
    pd.testing.assert_frame_equal(got, want)
    assert list(batch([]).columns) == list(want.columns) and len(batch([])) == 0
    assert batch([]).dtypes.equals(want.dtypes)
