"""detect's full-size inverse-noise maps: float32, kept in a movie's cache across map refreshes."""
import numpy as np

from ptrack.image import detect as D


def _frame(seed, shape=(200, 260)):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    img = 30.0 + 10.0 * xx / shape[1]
    for _ in range(25):
        y, x = rng.uniform(10, shape[0] - 10), rng.uniform(10, shape[1] - 10)
        img = img + 300.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.5 ** 2))
    return rng.poisson(img).astype(np.uint16)


def test_inverse_noise_maps_are_the_tile_grids_interpolated_and_reuse_their_array():
    cache = {}
    D.detect(_frame(0), cache=cache)
    ivs = cache["ivs_full"]
    assert ivs.dtype == np.float32 and ivs.shape[0] == len(D.DEFAULT_SCALES)
    # the same bilinear interpolation between tile centres as the row-block path (float64), to float32 rounding
    H, W = ivs.shape[1:]
    ref = D._inverse_noise_rows(cache["invs"], H, W, 0, H)
    assert np.allclose(ivs, ref, rtol=3e-7, atol=0)
    # a refresh of the maps writes into the same array
    cache["age"] = D.MAP_REFRESH
    D.detect(_frame(1), cache=cache)
    assert cache["age"] == 1 and cache["ivs_full"] is ivs


def test_scale_index_from_the_full_maps_is_the_best_snr_scale():
    f = _frame(2)
    cache = {}
    det = D.detect(f, cache=cache)
    import cv2

    work = cv2.medianBlur(f, 3).astype(np.float32)
    ladder = sorted(set(det["scales"]) | {2 * s for s in det["scales"]})
    blurs = dict(zip(ladder, D._blur_ladder(work, ladder)))
    b1s = tuple(blurs[s] for s in det["scales"])
    b2s = tuple(blurs[2 * s] for s in det["scales"])
    rows, cols = det["rows"], det["cols"]
    k = D._scale_at_full(b1s, b2s, cache["ivs_full"], 1.0, rows, cols)
    z = np.array([(b1s[i][rows, cols] - b2s[i][rows, cols]).astype(np.float64) * cache["ivs_full"][i][rows, cols]
                  for i in range(len(b1s))])
    assert len(rows) > 10 and np.array_equal(k, np.argmax(z, axis=0))
    assert np.allclose(z.max(0), det["snr"][:len(rows)], rtol=1e-6)   # the SNR map is float32


def test_tile_medians_and_mads_are_numpys():
    rng = np.random.default_rng(4)
    for th, tw in ((16, 16), (17, 16), (5, 7), (3, 3), (1, 4), (1, 1), (2, 1)):
        for kind in ("normal", "ties", "heavy", "constant", "signed zeros"):
            shape = (3 * th, 4 * tw)
            if kind == "normal":
                x = rng.normal(0, 3, shape)
            elif kind == "ties":
                x = rng.integers(0, 5, shape)
            elif kind == "heavy":      # Cauchy tails over many binades, both signs
                x = 1e3 * rng.standard_cauchy(shape)
            elif kind == "constant":
                x = np.full(shape, -2.5)
            else:
                x = np.where(rng.random(shape) < 0.5, -0.0, 0.0) + rng.integers(-1, 2, shape)
            sub = x.astype(np.float32)
            med, mad = D._tile_med_mad(sub, 3, 4, th, tw)
            for a in range(3):
                for b in range(4):
                    t = sub[a * th:(a + 1) * th, b * tw:(b + 1) * tw].astype(np.float64).ravel()
                    m = np.float32(np.median(t))
                    assert med[a, b] == m
                    dev = np.abs(t.astype(np.float32) - m).astype(np.float64)
                    assert mad[a, b] == np.float32(1.4826 * np.median(dev))


def test_tile_stats_by_numpy_sort_are_the_radix_ones_bit_for_bit():
    # numpy's vectorised sort may swap the signs of zeros and puts NaNs last: the sorted path must still give
    # the radix kernel's bits (the zeros' run rewritten in radix order; a NaN falls back to the radix kernel)
    rng = np.random.default_rng(11)
    for th, tw in ((16, 16), (17, 16), (5, 7), (3, 3), (1, 4), (2, 1), (11, 13)):
        for kind in ("normal", "ties", "signed zeros", "zeros only", "nan"):
            for _ in range(3):
                shape = (3 * th, 4 * tw)
                if kind == "normal":
                    x = rng.normal(0, 3, shape)
                elif kind == "ties":
                    x = rng.integers(-2, 3, shape)
                elif kind == "signed zeros":
                    x = np.where(rng.random(shape) < 0.5, -0.0, 0.0) + rng.integers(-1, 2, shape)
                elif kind == "zeros only":
                    x = np.where(rng.random(shape) < 0.5, -0.0, 0.0)
                else:
                    x = rng.normal(0, 3, shape)
                    x[rng.integers(0, shape[0]), rng.integers(0, shape[1])] = np.nan
                sub = np.ascontiguousarray(x.astype(np.float32))
                for a, b in zip(D._tile_med_mad(sub, 3, 4, th, tw), D._tile_stats(sub, 3, 4, th, tw)):
                    assert np.array_equal(a.view(np.uint32), b.view(np.uint32)), (th, tw, kind)


def test_ring_evidence_dip_tests_on_the_frame_are_the_mosaic_ones():
    from ptrack.image import rings as RG
    from ptrack.image.radial import has_dip

    rng = np.random.default_rng(6)
    H, W, h = 90, 120, 10
    yy, xx = np.mgrid[:H, :W]
    frame = rng.poisson(40.0, (H, W)).astype(np.float64)
    # dark-ringed bright spots (dips) and plain spots, some at the border (patches repeat the edge)
    centres = [(5, 7), (45, 60), (80, 110), (30, 20), (60, 95), (2, 118)]
    for k, (r, c) in enumerate(centres):
        d2 = (yy - r) ** 2 + (xx - c) ** 2
        frame += 400 * np.exp(-d2 / 4.0) - (150 * np.exp(-(np.sqrt(d2) - 5.0) ** 2 / 2.0) if k % 2 else 0)
    frame = np.clip(frame, 0, None).astype(np.uint16)
    bg = np.full((H, W), 40.0, np.float32) + rng.normal(0, 0.5, (H, W)).astype(np.float32)
    rows = np.array([c[0] for c in centres] + list(rng.integers(0, H, 30)), np.int64)
    cols = np.array([c[1] for c in centres] + list(rng.integers(0, W, 30)), np.int64)
    noise = np.full(len(rows), 6.3)
    for sign in (1.0, -1.0):
        m = len(rows)
        mosaic = np.empty((2 * h + 1, (2 * h + 1) * m), np.float32)
        RG._patch_mosaic(frame, bg, rows, cols, h, sign, mosaic)
        ref = has_dip(mosaic, h + (2 * h + 1) * np.arange(m, dtype=float), np.full(m, float(h)), noise,
                      np.full(m, float(h)))
        got = np.zeros(m, np.bool_)
        RG._patch_dips(frame, bg, rows, cols, h, sign, noise, 4.0, got)
        assert np.array_equal(got, ref)
        if sign > 0:
            assert got[[1, 3]].all()     # the ringed ones away from the corner


def test_noise_map_median_from_a_sub_sample_is_the_full_median():
    det = D.detect(_frame(3, shape=(300, 420)))
    rn = det["noise_map"]
    assert det["noise_map_median"] == float(np.median(rn[::4, ::4]))
    assert abs(det["noise_map_median"] / float(np.median(rn)) - 1) < 2e-3


def _ring_test_reference(frame, bg, noise, sign, r0, c0, s):
    # _ring_test's rule written out per pixel (atan2 and sqrt at each one)
    import math

    h, w = frame.shape
    half = int(math.ceil(2.2 * s)) + 1
    sec, nsec, core, ncore = np.zeros(8), np.zeros(8), 0.0, 0
    for r in range(max(0, r0 - half), min(h, r0 + half + 1)):
        for c in range(max(0, c0 - half), min(w, c0 + half + 1)):
            d = math.sqrt((r - r0) ** 2 + (c - c0) ** 2)
            v = sign * (frame[r, c] - bg[r, c])
            if d <= max(0.5 * s, 1.0):
                core += v
                ncore += 1
            elif 0.7 * s <= d <= 2.2 * s:
                a = int((math.atan2(r - r0, c - c0) + math.pi) / (2 * math.pi) * 8) % 8
                sec[a] += v
                nsec[a] += 1
    if ncore == 0 or nsec.min() == 0:
        return False
    m = sec / nsec
    se = noise[r0, c0] / math.sqrt(nsec.min())
    return bool(m.min() > core / ncore + 3.0 * se and m.min() > 0.4 * m.max() and m.max() > 0)


def test_ring_test_with_offset_tables_is_the_per_pixel_rule():
    rng = np.random.default_rng(9)
    H, W = 80, 100
    yy, xx = np.mgrid[:H, :W]
    img = rng.normal(20.0, 2.0, (H, W))
    for (r, c) in ((20, 20), (50, 70), (3, 95)):              # rings (one at the border)
        img += 60.0 * np.exp(-(np.hypot(yy - r, xx - c) - 4.0) ** 2 / 2.0)
    img = img.astype(np.float32)
    bg = np.full((H, W), 20.0, np.float32)
    noise = np.full((H, W), 2.0, np.float32)
    rows = np.r_[20, 50, 3, rng.integers(0, H, 40)].astype(np.int64)
    cols = np.r_[20, 70, 95, rng.integers(0, W, 40)].astype(np.int64)
    scale = rng.choice([2.0, 2.83, 4.0], len(rows))
    for sign in (1.0, -1.0):
        out = np.zeros(len(rows), np.bool_)
        D._ring_test(img, bg, noise, sign, rows, cols, scale, out)
        ref = [_ring_test_reference(img, bg, noise, sign, r, c, s) for r, c, s in zip(rows, cols, scale)]
        assert out.tolist() == ref
    out = np.zeros(3, np.bool_)
    D._ring_test(img, bg, noise, 1.0, rows[:3], cols[:3], np.full(3, 2.0), out)
    assert out[:2].all()


def test_fast_median_is_numpys():
    from ptrack.image.preprocess import fast_median

    rng = np.random.default_rng(11)
    for dtype in (np.float32, np.float64):
        for n in (1, 2, 3, 4, 5, 10, 11, 255, 256, 4096):
            for kind in ("normal", "ties"):
                a = rng.normal(3, 2, n) if kind == "normal" else rng.integers(0, 4, n).astype(float)
                a = a.astype(dtype)
                keep = a.copy()
                ref = float(np.median(a))
                assert fast_median(a) == ref and fast_median(a.reshape(1, -1)[:, ::1]) == ref
                assert np.array_equal(a, keep)          # the input is not reordered
    b = np.array([1.0, np.nan, 2.0])
    assert np.isnan(fast_median(b))
    assert fast_median(np.arange(10, dtype=np.float32).reshape(2, 5)[:, ::2]) == float(np.median(
        np.arange(10, dtype=np.float32).reshape(2, 5)[:, ::2]))


def test_blur_ladder_kernels_reach_three_sigmas():
    f = np.zeros((41, 41), np.float32)
    f[20, 20] = 1.0
    b = D._blur_ladder(f, [1.0, 2.0])
    assert b[0][20, 23] > 0 and b[0][20, 24] == 0 and b[0][24, 20] == 0
    assert abs(float(b[0].sum()) - 1.0) < 1e-5           # still normalised
    # the second rung blurs the first by sqrt(2^2 - 1) = 1.73 px: 3 + 6 px reach in all
    assert b[1][20, 29] > 0 and b[1][20, 30] == 0


def test_best_over_scales_in_float32_is_the_float64_pass_bit_for_bit():
    # float32 inverse-noise maps are multiplied in float32; float64 ones (the same values) in float64 and
    # rounded to the float32 map: the same maps, both signs, with and without the other sign's map
    rng = np.random.default_rng(21)
    h, w, ns = 37, 53, 4
    b1s = tuple((rng.normal(0, 1, (h, w)) * 10.0 ** rng.uniform(-2, 3)).astype(np.float32) for _ in range(ns))
    b2s = tuple((b + rng.normal(0, 1, (h, w)) * 10.0 ** rng.uniform(-2, 3)).astype(np.float32) for b in b1s)
    ivs = (10.0 ** rng.uniform(-3, 2, (ns, h, w))).astype(np.float32)
    for sign in (1.0, -1.0):
        for both in (False, True):
            out = []
            for iv in (ivs, ivs.astype(np.float64)):
                best, neg = np.empty((h, w), np.float32), np.empty((h, w) if both else (1, 1), np.float32)
                D._best_over_scales(b1s, b2s, iv, 0, sign, best, neg, both)
                out.append((best, neg))
            assert np.array_equal(out[0][0], out[1][0]) and (not both or np.array_equal(out[0][1], out[1][1]))
            z = np.max([sign * (b1s[i] - b2s[i]).astype(np.float64) * ivs[i] for i in range(ns)], axis=0)
            assert np.array_equal(out[0][0], z.astype(np.float32))
            if both:
                zn = np.max([-sign * (b1s[i] - b2s[i]).astype(np.float64) * ivs[i] for i in range(ns)], axis=0)
                assert np.array_equal(out[0][1], zn.astype(np.float32))


def test_a_dropped_cache_gives_its_work_arrays_to_the_next_one():
    # the arrays a dropped cache owned (blur ladder, inverse-noise maps, scratch arrays, the frame's background
    # and noise maps) are reused by the next cache (no fresh memory to fault in on a movie's first frame), with
    # the same detections, except those a caller still holds (here a returned detect result's maps and an
    # array read from the cache); a cache of another frame shape takes new ones
    f = _frame(5)
    c1 = {}
    d1 = D.detect(f, cache=c1)
    mine = {id(a) for a in c1["blur_pool"]["owned"].arrays}
    held = c1["ivs_full"]
    assert id(held) in mine and id(d1["background_map"]) in mine and len(mine) >= 1 + len(D.DEFAULT_SCALES)
    del c1
    c2 = {}
    d2 = D.detect(f, cache=c2)
    again = {id(a) for a in c2["blur_pool"]["owned"].arrays}
    kept = {id(held), id(d1["background_map"]), id(d1["noise_map"])}
    assert mine - kept <= again and not kept & again
    for k in ("rows", "cols", "scale", "snr", "signal"):
        assert np.array_equal(d1[k], d2[k])
    assert np.array_equal(d1["background_map"], d2["background_map"])
    d3 = D.detect(_frame(6, shape=(150, 170)), cache={})
    ref = D.detect(_frame(6, shape=(150, 170)))
    for k in ("rows", "cols", "scale", "snr", "signal"):
        assert np.array_equal(d3[k], ref[k])


def test_scratch_arrays_are_kept_from_frame_to_frame_with_the_same_detections(monkeypatch):
    # with a cache, the frame's float32 copy, its median, the best-over-scales map and the half-size blurs are
    # written into the cache's arrays frame after frame; the detections are those without them
    f0, f1 = _frame(7), _frame(8)
    c = {}
    D.detect(f0, cache=c)
    arrays = dict(c["blur_pool"]["scratch"])
    assert {"f32", "median", "work", "best"} <= set(arrays)
    half = list(c["blur_pool"]["half"])
    d1 = D.detect(f1, cache=c)
    assert all(c["blur_pool"]["scratch"][k] is a for k, a in arrays.items() if k != "best_other")
    assert all(a is b for a, b in zip(c["blur_pool"]["half"], half))
    monkeypatch.setattr(D, "_RECYCLE_BYTES", 0)
    ref = {}
    D.detect(f0, cache=ref)
    assert "owned" not in ref["blur_pool"]
    r1 = D.detect(f1, cache=ref)
    for k in ("rows", "cols", "scale", "snr", "signal", "polarity"):
        assert np.array_equal(d1[k], r1[k])
