"""ptrack.gdpt.ncc: the direct small-map correlation agrees with OpenCV's TM_CCOEFF_NORMED."""
import cv2
import numpy as np
import pytest

from ptrack.gdpt import ncc as N


@pytest.mark.parametrize("T,m", [(5, 1), (17, 4), (51, 2), (51, 4), (75, 5), (93, 1), (121, 2)])
def test_direct_matches_opencv(T, m):
    # up to 75 px: each shift one flat dot product; 93 and 121 px span more than FLAT_MAX: row by row
    rng = np.random.default_rng(T * 10 + m)
    yy, xx = np.mgrid[:T, :T] - T // 2
    t = (np.exp(-(xx ** 2 + yy ** 2) / (0.1 * T * T)) + 0.05 * rng.random((T, T))).astype(np.float32)
    big = (50 + 100 * rng.random((T + 2 * m + 6, T + 2 * m + 6))).astype(np.float32)
    win = big[3:3 + T + 2 * m, 2:2 + T + 2 * m]            # a strided view, as the matcher passes
    got = N.ncc(win, t)
    ref = cv2.matchTemplate(np.ascontiguousarray(win), t, cv2.TM_CCOEFF_NORMED)
    assert got.shape == ref.shape and got.dtype == np.float32
    assert (2 * m + 1) ** 2 <= N.DIRECT_MAX
    np.testing.assert_allclose(got, ref, atol=2e-6)


def test_corners_are_ncc_of_each_page_at_its_own_corner():
    """ncc_corners (refine_full's batch) = ncc of each page's template on the window at its corner, bit for bit."""
    rng = np.random.default_rng(9)
    tm = N.Templates(rng.random((T, T)).astype(np.float32) for T in (7, 12, 31, 45))
    img = (100 * rng.random((90, 80))).astype(np.float32)
    pages, tops, lefts = [3, 0, 2, 2, 1], [0, 40, 10, 11, 70], [30, 5, 47, 46, 0]
    got = N.ncc_corners(img, tm, pages, tops, lefts, 3)
    for q, (k, r, c) in enumerate(zip(pages, tops, lefts)):
        T = tm[k].shape[0]
        assert np.array_equal(got[q], N.ncc(img[r:r + T + 2, c:c + T + 2], tm[k]))


def test_zero_mean_templates_are_cached_per_templates_object():
    rng = np.random.default_rng(8)
    tm = N.Templates(rng.random((T, T)).astype(np.float32) for T in (5, 8, 13))
    zflat, tns = tm.zero_mean
    assert tm.zero_mean[0] is zflat
    flat, offs, sizes = tm.packed
    for k, t in enumerate(tm):
        z = zflat[offs[k]:offs[k] + t.size].reshape(t.shape)
        np.testing.assert_allclose(z, t - t.astype(np.float64).mean(), atol=1e-6)
        assert abs(tns[k] - float(((t - t.astype(np.float64).mean()) ** 2).sum())) < 1e-5 * tns[k]


def test_layout_is_the_zero_mean_template_on_the_window_row_length():
    rng = np.random.default_rng(10)
    tm = N.Templates(rng.random((T, T)).astype(np.float32) for T in (5, 9, 95))
    zflat, _ = tm.zero_mean
    flat, offs, sizes = tm.packed
    lflat, loffs = tm.layout(4)
    for k, T in enumerate(sizes):
        lay = lflat[loffs[k]:loffs[k + 1]]
        if (T - 1) * (T + 4) + T > N.FLAT_MAX:
            assert lay.size == 0            # correlated row by row
            continue
        want = np.zeros((T, T + 4), np.float32)
        want[:, :T] = zflat[offs[k]:offs[k] + T * T].reshape(T, T)
        assert np.array_equal(lay, want.ravel()[:(T - 1) * (T + 4) + T])
    assert tm.layout(4)[0] is lflat


def test_constant_window_is_minus_one():
    t = np.random.default_rng(1).random((9, 9)).astype(np.float32)
    assert np.all(N.ncc(np.zeros((13, 13), np.float32), t) == -1.0)


def test_large_maps_use_opencv():
    rng = np.random.default_rng(2)
    t = rng.random((9, 9)).astype(np.float32)
    img = rng.random((64, 64)).astype(np.float32)
    np.testing.assert_array_equal(N.ncc(img, t), cv2.matchTemplate(img, t, cv2.TM_CCOEFF_NORMED))


def test_pages_match_one_by_one():
    """ncc_pages (packed templates, crops, a sub-range of shifts) = ncc per page on the window _match_one cuts."""
    rng = np.random.default_rng(3)
    tm = N.Templates(rng.random((T, T)).astype(np.float32) for T in (7, 9, 13, 15))
    img = rng.random((60, 60)).astype(np.float32)
    ri, ci, m = 30, 28, 3
    n = 2 * m + 1
    for crop, rows, cols in ((0, None, None), (7, None, None), (0, (1, 6), (2, 7))):
        got = N.ncc_pages(img, ri, ci, m, tm, [0, 2, 3] if crop == 0 else [1, 3], crop=crop, rows=rows, cols=cols)
        for q, k in enumerate([0, 2, 3] if crop == 0 else [1, 3]):
            t = tm[k]
            Tc = crop or t.shape[0]
            o = (t.shape[0] - Tc) // 2
            h = Tc // 2
            ref = np.full((n, n), -1.0, np.float32)
            a0, a1 = rows or (0, n)
            b0, b1 = cols or (0, n)
            ref[a0:a1, b0:b1] = N.ncc(img[ri - h - m + a0:ri + h - m + a1, ci - h - m + b0:ci + h - m + b1],
                                      t[o:o + Tc, o:o + Tc])
            np.testing.assert_array_equal(got[q], ref)


@pytest.mark.parametrize("m", [2, 4, 5])
def test_strided_pages_are_the_full_maps_every_step_th_shift(m):
    """ncc_pages_strided(step=2) is ncc_pages' map at every 2nd shift of each axis, bit for bit (same sums)."""
    rng = np.random.default_rng(3)
    tm = N.Templates([rng.random((T, T)).astype(np.float32) for T in (9, 21, 31)])
    img = (100 * rng.random((120, 120))).astype(np.float32)
    full = N.ncc_pages(img, 60, 61, m, tm, [0, 1, 2])
    coarse = N.ncc_pages_strided(img, 60, 61, m, tm, [0, 1, 2], 2)
    assert coarse.shape == (3, m + 1, m + 1)
    assert np.array_equal(full[:, ::2, ::2], coarse)


def test_parabola_vertex_of_the_least_squares_fit():
    """_quadratic_peak's window fit is the least-squares parabola's vertex (np.polyfit), clipped to the window."""
    from ptrack.calibration import _quadratic_peak

    rng = np.random.default_rng(4)
    z = np.round(np.arange(-3e-6, 3.0001e-6, 0.1e-6), 12)
    for _ in range(200):
        z0, width = rng.uniform(-2.9e-6, 2.9e-6), rng.uniform(0.3e-6, 2e-6)
        c = 0.99 - 0.1 * ((z - z0) / width) ** 2 + rng.normal(0, 1e-3, z.size)
        k = int(np.argmax(c))
        lo, hi = max(0, k - 4), min(z.size, k + 5)
        a, b, _ = np.polyfit(z[lo:hi] - z[k], c[lo:hi], 2)
        want = z[k] + np.clip(-b / (2 * a), z[lo] - z[k], z[hi - 1] - z[k]) if a < 0 else z[k]
        assert abs(_quadratic_peak(z, c, k, n_points=9) - want) < 1e-15


def test_direct_max_raises_the_direct_sum_limit():
    """ncc(..., direct_max): a 15 x 15 map (past DIRECT_MAX, as _best_in_window's) by the direct sum, which agrees
    with OpenCV to float32 rounding (by default such a map is OpenCV's own)."""
    rng = np.random.default_rng(12)
    T = 41
    yy, xx = np.mgrid[:T, :T] - T // 2
    t = (np.exp(-(xx ** 2 + yy ** 2) / (0.1 * T * T)) + 0.05 * rng.random((T, T))).astype(np.float32)
    win = (50 + 100 * rng.random((T + 14, T + 14))).astype(np.float32)
    ref = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)
    assert 15 * 15 > N.DIRECT_MAX
    np.testing.assert_array_equal(N.ncc(win, t), ref)
    got = N.ncc(win, t, direct_max=225)
    assert np.array_equal(got, N._ncc_direct(win, t))
    np.testing.assert_allclose(got, ref, atol=2e-6)


def test_frame_spectrum_ncc_is_opencv_normed_map_and_floor_keeps_the_maxima_above_it():
    """FrameSpectrum.ncc_max (one FFT of the frame, cached template spectra, integral-image normalisation) gives
    OpenCV's TM_CCOEFF_NORMED at the requested corners, folded into the running maximum over pages; with a floor,
    every value at or above it (and its page) is the same as without."""
    import cv2

    from ptrack.gdpt.ncc import FrameSpectrum, Templates

    rng = np.random.default_rng(4)
    img = np.zeros((120, 130), np.float32)
    img[20:100, 15:115] = rng.normal(0, 1, (80, 100))
    yy, xx = np.mgrid[:80, :100]
    img[20:100, 15:115] += 6 * np.exp(-((yy - 40) ** 2 + (xx - 55) ** 2) / 30.0)
    tm = Templates(np.outer(*[np.exp(-0.5 * (np.arange(T) - T // 2) ** 2 / s ** 2)] * 2).astype(np.float32)
                   + rng.normal(0, 0.01, (T, T)).astype(np.float32) for T, s in ((9, 1.5), (15, 3.0), (21, 4.0)))
    fs = FrameSpectrum(img)
    H, W = 70, 90
    cmap = np.full((H, W), -1.0, np.float32)
    which = np.zeros((H, W), np.int32)
    want = np.full((H, W), -1.0, np.float32)
    wk = np.zeros((H, W), np.int32)
    for k, (top, left) in enumerate(((25, 20), (22, 18), (19, 16))):
        fs.ncc_max(tm, k, top, left, cmap, which)
        R = cv2.matchTemplate(img, tm[k], cv2.TM_CCOEFF_NORMED)[top:top + H, left:left + W]
        wk[R > want] = k
        np.maximum(want, R, out=want)
        assert np.abs(cmap - want).max() < 2e-4
    assert np.mean(which == wk) > 0.999
    c2 = np.full((H, W), -1.0, np.float32)
    w2 = np.zeros((H, W), np.int32)
    for k, (top, left) in enumerate(((25, 20), (22, 18), (19, 16))):
        fs.ncc_max(tm, k, top, left, c2, w2, floor=0.3)
    hi = cmap >= 0.3
    assert hi.sum() > 20 and np.array_equal(c2[hi], cmap[hi]) and np.array_equal(w2[hi], which[hi])
    assert np.all(c2[~hi] < 0.3)
    with pytest.raises(ValueError):
        fs.ncc_max(tm, 2, 110, 0, cmap, which)
