"""The Gaussian fit's kernels: the pixel integrals' erf and the one-spot least-squares evaluation."""
import math

import numpy as np
from scipy.special import erf

from ptrack.image import fit as F


def test_erf_from_gauss_within_its_stated_error():
    z = np.linspace(-6, 6, 4001)
    got = np.array([F._erf_gauss(v, math.exp(-v * v)) for v in z])
    assert np.max(np.abs(got - erf(z))) < 1.5e-7
    assert got[2000] == 0.0 or abs(got[2000]) < 1e-8      # odd: erf(0) = 0


def test_pixel_integrals_match_the_exact_erf_differences():
    # the profile (values and derivatives) against scipy's erf, for widths and offsets the fits meet
    for s in (0.6, 1.0, 1.7, 3.0, 6.0):
        for x in (0.0, 0.37, 0.5, 0.93):
            n0, n = -12, 25
            e, dx, ds = np.empty(n), np.empty(n), np.empty(n)
            F._erf_profile(n0, n, x, s, e, dx, ds)
            edges = np.arange(n0, n0 + n + 1) - 0.5 - x
            exact = 0.5 * np.diff(erf(edges / (math.sqrt(2) * s)))
            assert np.max(np.abs(e - exact)) < 2e-7
            g = np.exp(-edges ** 2 / (2 * s * s)) / (math.sqrt(2 * math.pi) * s)
            assert np.allclose(dx, -np.diff(g), atol=1e-13)
            assert np.allclose(ds, -np.diff(edges * g) / s, atol=1e-13)


def test_one_spot_least_squares_evaluation_is_the_generic_one_bit_for_bit():
    rng = np.random.default_rng(3)
    img = rng.normal(50.0, 4.0, (40, 50)).astype(np.float32)
    for trial in range(20):
        half = int(rng.integers(3, 9))
        r0, c0 = int(rng.integers(0, 40 - 2 * half)), int(rng.integers(0, 50 - 2 * half))
        n = 2 * half + 1
        th = np.array([c0 + half + rng.uniform(-1, 1), r0 + half + rng.uniform(-1, 1), rng.uniform(50, 5000),
                       rng.uniform(-5, 60), rng.uniform(0.7, 3.0)])
        gain, offset = rng.uniform(0.5, 3.0), rng.uniform(0, 10)
        out = []
        for one in (False, True):
            w = F._work(1, n)
            J, g = np.zeros((5, 5)), np.zeros(5)
            if one:
                f = F._eval_ls1(img, r0, n, c0, n, th, gain, offset, w[0], w[1], J, g, w[10], w[11], w[13], w[14],
                                w[15], w[16])
            else:
                f = F._eval_ls(img, r0, n, c0, n, th, 1, gain, offset, w[0], w[1], J, g, w[10], w[11], w[12], w[13],
                               w[14], w[15], w[16])
            out.append((f, J.copy(), g.copy()))
        assert out[0][0] == out[1][0]
        assert np.array_equal(out[0][1], out[1][1]) and np.array_equal(out[0][2], out[1][2])


def test_one_spot_poisson_evaluation_is_the_generic_one_bit_for_bit():
    rng = np.random.default_rng(5)
    img = rng.poisson(30.0, (40, 50)).astype(np.uint16)
    for trial in range(20):
        half = int(rng.integers(3, 9))
        r0, c0 = int(rng.integers(0, 40 - 2 * half)), int(rng.integers(0, 50 - 2 * half))
        n = 2 * half + 1
        th = np.array([c0 + half + rng.uniform(-1, 1), r0 + half + rng.uniform(-1, 1), rng.uniform(50, 5000),
                       rng.uniform(0.0, 40.0), rng.uniform(0.7, 3.0)])
        gain, offset, rvar = rng.uniform(0.5, 3.0), rng.uniform(0, 10), rng.uniform(0, 4)
        out = []
        for one in (False, True):
            w = F._work(1, n)
            J, g = np.zeros((5, 5)), np.zeros(5)
            if one:
                f = F._eval_poisson1(img, r0, n, c0, n, th, gain, offset, rvar, w[0], w[1], J, g)
            else:
                f = F._eval_poisson(img, r0, n, c0, n, th, 1, gain, offset, rvar, w[0], w[1], J, g, w[9])
            out.append((f, J.copy(), g.copy()))
        assert out[0][0] == out[1][0]
        assert np.array_equal(out[0][1], out[1][1]) and np.array_equal(out[0][2], out[1][2])


def test_nearest_other_detection_is_the_kd_tree_one():
    from scipy.spatial import cKDTree

    from ptrack.image.locate import _nearest_other

    rng = np.random.default_rng(7)
    for n in (2, 3, 50, 600):
        rows = rng.integers(0, 300, n)
        cols = rng.integers(0, 400, n)
        if n > 3:
            rows[1], cols[1] = rows[0], cols[0]          # a duplicate: distance 0
        pts = np.c_[cols, rows].astype(float)
        ref = cKDTree(pts).query(pts, k=2)[0][:, 1]
        assert np.allclose(_nearest_other(rows, cols), ref, rtol=1e-15, atol=0)
    assert np.isinf(_nearest_other(np.array([3]), np.array([4]))).all()


def _neighbour_tasks_by_kd_tree(rows, cols, radius, max_group):
    # the groups as the k-d tree forms them (the reference of _neighbour_tasks)
    from scipy.spatial import cKDTree

    n = len(rows)
    pts = np.c_[cols, rows].astype(float)
    d, idx = cKDTree(pts).query(pts, k=min(max_group, n), distance_upper_bound=radius)
    has = np.isfinite(d[:, 1])
    keys = np.sort(np.where(np.isfinite(d), idx, n)[has], axis=1)
    return has, {tuple(k[k < n]) for k in keys}


def test_joint_fit_groups_are_the_kd_tree_ones():
    rng = np.random.default_rng(8)
    for trial in range(30):
        n = int(rng.integers(2, 300))
        side = int(rng.integers(20, 400))
        rows, cols = rng.integers(0, side, n), rng.integers(0, side, n)
        radius = float(rng.choice([5.0, 7.82, 10.0, 3.0]))
        for max_group in (2, 3, 5):
            grouped, ptr, members, report = F._neighbour_tasks(rows, cols, radius, max_group)
            has, groups = _neighbour_tasks_by_kd_tree(rows, cols, radius, max_group)
            assert np.array_equal(grouped, has)
            got = {tuple(members[ptr[t]:ptr[t + 1]]) for t in range(len(ptr) - 1)}
            crowded = any(len(g) == max_group for g in groups)
            if not crowded:          # (crowded: which of equally distant neighbours is nearest is the tree's choice)
                assert got == groups
            # every grouped spot is reported exactly once, from a task holding it
            rep = members[report]
            assert sorted(rep.tolist()) == sorted(np.nonzero(has)[0].tolist())


def test_ring_like_with_an_offset_table_is_the_per_pixel_rule():
    from ptrack.image.locate import _ring_like

    rng = np.random.default_rng(10)
    H, W = 70, 90
    yy, xx = np.mgrid[:H, :W]
    sub = rng.normal(0.0, 2.0, (H, W))
    sub += 50 * np.exp(-((yy - 30) ** 2 + (xx - 40) ** 2) / 4.0) - 20 * np.exp(-(np.hypot(yy - 30, xx - 40) - 5) ** 2)
    sub = sub.astype(np.float32)
    rows = np.r_[30, rng.integers(0, H, 40)].astype(np.int64)
    cols = np.r_[40, rng.integers(0, W, 40)].astype(np.int64)
    scale = rng.uniform(1.0, 4.0, len(rows))
    out = np.zeros(len(rows), np.bool_)
    _ring_like(sub, rows, cols, scale, 2.0, out)
    for k in range(len(rows)):
        s, r0, c0 = scale[k], rows[k], cols[k]
        half = int(math.ceil(3.0 * s)) + 1
        rs = np.arange(max(0, r0 - half), min(H, r0 + half + 1))
        cs = np.arange(max(0, c0 - half), min(W, c0 + half + 1))
        sums = np.zeros(3)
        cnt = np.zeros(3)
        for r in rs:                              # the kernel's rule, in its summation order
            for c in cs:
                d = math.sqrt((r - r0) ** 2 + (c - c0) ** 2)
                band = 0 if d <= max(1.0, 0.6 * s) else 1 if s <= d <= 2 * s else 2 if 2 * s < d <= 3 * s else -1
                if band >= 0:
                    sums[band] += sub[r, c]
                    cnt[band] += 1
        core, mid = sums[0] / max(cnt[0], 1), sums[1] / max(cnt[1], 1)
        outer = sums[2] / max(cnt[2], 1)
        nn = cnt[1] if mid < outer else cnt[2]
        assert out[k] == (core < mid or min(mid, outer) < -4.0 * 2.0 / math.sqrt(max(nn, 1)))
    assert out[0]


def test_dip_test_is_the_annulus_rule():
    from ptrack.image import radial as RA

    rng = np.random.default_rng(12)
    H, W = 80, 100
    yy, xx = np.mgrid[:H, :W]
    img = rng.normal(0.0, 1.0, (H, W))
    centres = [(20.3, 30.6), (50.0, 70.2), (4.4, 95.1), (60.7, 15.5)]
    for k, (y, x) in enumerate(centres):
        d = np.hypot(yy - y, xx - x)
        img += 40 * np.exp(-d ** 2 / 4.0) - (12 * np.exp(-(d - 5.0) ** 2) if k % 2 == 0 else 0)
    img = img.astype(np.float32)
    x0 = np.r_[[c[1] for c in centres], rng.uniform(0, W, 30)]
    y0 = np.r_[[c[0] for c in centres], rng.uniform(0, H, 30)]
    rmax = rng.integers(4, 12, len(x0)).astype(float)
    got = RA.has_dip(img, x0, y0, 1.0, rmax)
    for k in range(len(x0)):                        # the rule on _annulus_sums (every window pixel)
        R = int(rmax[k])
        sums, cnt = np.zeros(R + 1), np.zeros(R + 1)
        RA._annulus_sums(img, x0[k], y0[k], R, sums, cnt, np.empty(2 * R + 1, np.int64))
        # (the kernel's annuli against numpy's: every pixel of the window, b = round(r) <= R)
        rc, cc = int(round(y0[k])), int(round(x0[k]))
        win = (slice(max(0, rc - R), min(H, rc + R + 1)), slice(max(0, cc - R), min(W, cc + R + 1)))
        b_np = np.floor(np.hypot(xx[win] - x0[k], yy[win] - y0[k]) + 0.5).astype(int)
        inside = b_np <= R
        assert np.array_equal(cnt, np.bincount(b_np[inside], minlength=R + 1)[:R + 1])
        assert np.allclose(sums, np.bincount(b_np[inside], img[win][inside].astype(float), minlength=R + 1)[:R + 1],
                           rtol=1e-12, atol=1e-9)
        found = False
        for b in range(2, R - 1):
            if cnt[b] == 0 or cnt[b + 2] == 0:
                continue
            m, se = sums[b] / cnt[b], 1.0 / math.sqrt(cnt[b])
            outside = max(sums[b + 1] / max(cnt[b + 1], 1.0), sums[b + 2] / cnt[b + 2])
            if m < -4 * se and m < outside - 4 * se and m < sums[0] / max(cnt[0], 1.0) - 4 * se:
                found = True
                break
        assert got[k] == found
    assert got[0] and got[2] and not got[1]


def test_two_spot_least_squares_evaluation_is_the_generic_one_bit_for_bit():
    rng = np.random.default_rng(13)
    img = rng.normal(50.0, 4.0, (50, 60)).astype(np.float32)
    for trial in range(20):
        nr, nc = int(rng.integers(7, 20)), int(rng.integers(7, 25))
        r0, c0 = int(rng.integers(0, 50 - nr)), int(rng.integers(0, 60 - nc))
        th = np.array([c0 + rng.uniform(2, nc - 2), r0 + rng.uniform(2, nr - 2), rng.uniform(50, 5000),
                       c0 + rng.uniform(2, nc - 2), r0 + rng.uniform(2, nr - 2), rng.uniform(50, 5000),
                       rng.uniform(-5, 60), rng.uniform(0.7, 3.0)])
        gain, offset = rng.uniform(0.5, 3.0), rng.uniform(0, 10)
        out = []
        for two in (False, True):
            w = F._work(2, max(nr, nc))
            J, g = np.zeros((8, 8)), np.zeros(8)
            if two:
                f = F._eval_ls2(img, r0, nr, c0, nc, th, gain, offset, w[0], w[1], J, g, w[10], w[11], w[13], w[14],
                                w[15], w[16])
            else:
                f = F._eval_ls(img, r0, nr, c0, nc, th, 2, gain, offset, w[0], w[1], J, g, w[10], w[11], w[12],
                               w[13], w[14], w[15], w[16])
            out.append((f, J.copy(), g.copy()))
        assert out[0][0] == out[1][0]
        assert np.array_equal(out[0][1], out[1][1]) and np.array_equal(out[0][2], out[1][2])


def test_written_out_gauss_newton_matrices_are_the_generic_one_bit_for_bit():
    # _ls_fisher1 / _ls_fisher2 (one and two spots) against the term-list loops of _ls_fisher, on arbitrary
    # column and row functions (not only erf profiles) and amplitudes of either sign
    rng = np.random.default_rng(17)
    for K, fn in ((1, F._ls_fisher1), (2, F._ls_fisher2)):
        for trial in range(50):
            nr, nc = int(rng.integers(3, 26)), int(rng.integers(3, 26))
            w = F._work(K, max(nr, nc))
            FX, FY = w[0], w[1]
            FX[:3 * K] = rng.normal(0, 1, FX[:3 * K].shape) * 10.0 ** rng.uniform(-3, 1)
            FY[:3 * K] = rng.normal(0, 1, FY[:3 * K].shape) * 10.0 ** rng.uniform(-3, 1)
            th = rng.normal(0, 1, 3 * K + 2) * 10.0 ** rng.uniform(-1, 4)
            J0, J1 = np.zeros((3 * K + 2, 3 * K + 2)), np.full((3 * K + 2, 3 * K + 2), np.nan)
            F._ls_fisher(th, K, nr, nc, FX, FY, J0, w[10], w[11], w[13], w[14], w[15], w[16])
            fn(th, nr, nc, FX, FY, J1)
            assert np.array_equal(J0, J1)


def test_variable_projection_evaluations_solve_the_linear_parameters_and_match_the_joint_ones():
    # _eval_vp1 / _eval_vp2 write the photons and background minimising the RSS at the centres and width; at
    # those, the objective, gradient (zero along the linear parameters) and Gauss-Newton matrix are the joint
    # evaluation's (_eval_ls1 / _eval_ls2), and no other linear parameters give a smaller RSS
    rng = np.random.default_rng(23)
    yy, xx = np.mgrid[0:50, 0:60]
    for K, lin in ((1, (2, 3)), (2, (2, 5, 6))):
        for trial in range(20):
            nr, nc = int(rng.integers(7, 20)), int(rng.integers(7, 25))
            r0, c0 = int(rng.integers(0, 50 - nr)), int(rng.integers(0, 60 - nc))
            th = np.zeros(3 * K + 2)
            img = rng.normal(5.0, 4.0, (50, 60))
            for k in range(K):
                th[3 * k:3 * k + 3] = c0 + rng.uniform(2, nc - 2), r0 + rng.uniform(2, nr - 2), rng.uniform(500, 5000)
                img += th[3 * k + 2] / (2 * np.pi * 1.5 ** 2) * np.exp(
                    -((xx - th[3 * k] - 0.3) ** 2 + (yy - th[3 * k + 1]) ** 2) / (2 * 1.5 ** 2))
            th[3 * K:] = rng.uniform(-5, 60), rng.uniform(0.9, 2.5)
            img = img.astype(np.float32)
            gain, offset = rng.uniform(0.5, 3.0), rng.uniform(0, 10)
            w = F._work(K, max(nr, nc))
            J, g = np.zeros((3 * K + 2, 3 * K + 2)), np.zeros(3 * K + 2)
            tv = th.copy()
            vp = F._eval_vp1 if K == 1 else F._eval_vp2
            f, rss = vp(img, r0, nr, c0, nc, tv, gain, offset, w[0], w[1], J, g)
            assert all(tv[a] > 0 for a in lin[:-1])
            J0, g0 = np.zeros_like(J), np.zeros_like(g)
            joint = F._eval_ls1 if K == 1 else F._eval_ls2
            f0, rss0 = joint(img, r0, nr, c0, nc, tv.copy(), gain, offset, w[0], w[1], J0, g0, w[10], w[11], w[13],
                             w[14], w[15], w[16])
            assert abs(rss - rss0) <= 1e-9 * rss0
            assert np.allclose(J, J0, rtol=1e-12, atol=0)
            assert np.allclose(g, g0, rtol=1e-6, atol=1e-6 * np.abs(g0).max())
            assert np.all(np.abs(g0[list(lin)]) < 1e-7 * np.abs(g0).max() + 1e-6 * math.sqrt(rss0))
            for _ in range(5):      # any other photons / background: a larger RSS
                tb = tv.copy()
                tb[list(lin)] += rng.normal(0, 1, len(lin)) * np.r_[[50.0] * (len(lin) - 1), 1.0]
                fb, rb = joint(img, r0, nr, c0, nc, tb, gain, offset, w[0], w[1], J0, g0, w[10], w[11], w[13],
                               w[14], w[15], w[16])
                assert rb > rss0
