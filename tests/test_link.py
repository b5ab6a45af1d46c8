"""The numba linker (ptrack.linknb) against trackpy.link, and ptrack.link's fallback to trackpy."""
import numpy as np
import pandas as pd
import pytest

trackpy = pytest.importorskip("trackpy")

from ptrack.errors import UserError  # noqa: E402
from ptrack.link import ADAPTIVE_STEP, ADAPTIVE_STOP, link  # noqa: E402
from ptrack.linknb import link_ids  # noqa: E402


def _trackpy_ids(f, rng, memory, pos, stop=ADAPTIVE_STOP, step=ADAPTIVE_STEP):
    trackpy.quiet()
    out = trackpy.link(f[["frame", *pos]].copy(), rng, memory=memory, pos_columns=pos, t_column="frame",
                       adaptive_stop=stop, adaptive_step=step)
    pid = np.empty(len(f), np.int64)
    pid[out.index.to_numpy()] = out["particle"].to_numpy()
    return pid


def _same_partition(a, b):
    pairs = np.unique(np.c_[a, b], axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def _movie(rng, n, box, n_frames, step, ndim=2, drop=0.15, skip=None):
    """Random walkers that blink (memory), with births, an empty frame and optionally a missing frame number."""
    p = rng.uniform(0, box, (n, ndim))
    rows = []
    for t in range(n_frames):
        p = p + rng.normal(0, step, p.shape)
        keep = rng.random(n) > drop
        if t == n_frames // 2:
            keep[:] = False
        rows += [(t, *q) for q in p[keep]]
        rows += [(t, *q) for q in rng.uniform(0, box, (3, ndim))]
    cols = ["frame", "z", "y", "x"][:1] + ["z", "y", "x"][3 - ndim:]
    f = pd.DataFrame(rows, columns=cols)
    if skip is not None:
        f = f[f["frame"] != skip]
    return f.sort_values("frame", kind="stable").reset_index(drop=True).astype({"frame": np.int64})


@pytest.mark.parametrize("seed", range(6))
def test_same_trajectories_as_trackpy(seed):
    rng = np.random.default_rng(seed)
    ndim = 3 if seed % 3 == 2 else 2
    f = _movie(rng, int(rng.integers(50, 300)), 80.0, 10, float(rng.uniform(1, 4)), ndim=ndim,
               skip=3 if seed % 2 else None)
    pos = ["z", "y", "x"][3 - ndim:]
    sr = float(rng.uniform(3, 9))
    rng_ = (2 * sr, sr, sr) if ndim == 3 else (sr, sr)
    for memory in (0, 3):
        a = _trackpy_ids(f, rng_, memory, pos)
        b = link_ids(f["frame"].to_numpy(), f[pos].to_numpy(), rng_, memory, ADAPTIVE_STOP, ADAPTIVE_STEP)
        assert _same_partition(a, b)


def test_adaptive_splits_as_trackpy():
    # dense enough that subnetworks are too large at the given range: trackpy's adaptive search splits them
    rng = np.random.default_rng(11)
    f = _movie(rng, 400, 60.0, 6, 2.0)
    pos = ["y", "x"]
    with pytest.raises(trackpy.linking.SubnetOversizeException):
        _trackpy_ids(f, (8.0, 8.0), 2, pos, stop=None)
    a = _trackpy_ids(f, (8.0, 8.0), 2, pos)
    b = link_ids(f["frame"].to_numpy(), f[pos].to_numpy(), (8.0, 8.0), 2, ADAPTIVE_STOP, ADAPTIVE_STEP)
    assert _same_partition(a, b)
    # without adaptive search both give up
    assert link_ids(f["frame"].to_numpy(), f[pos].to_numpy(), (8.0, 8.0), 2, None) is None


def test_gives_up_where_trackpy_raises():
    # every point within a tiny range of many others: still oversize at adaptive_stop, so the fast path
    # returns None and link() reports trackpy's failure
    rng = np.random.default_rng(3)
    f = pd.DataFrame({"frame": np.repeat([0, 1], 40), "y_px": rng.uniform(0, 0.2, 80), "x_px": rng.uniform(0, 0.2, 80)})
    assert link_ids(f["frame"].to_numpy(), f[["y_px", "x_px"]].to_numpy(), 1.0, 0, ADAPTIVE_STOP,
                    ADAPTIVE_STEP) is None
    with pytest.raises(UserError, match="linking failed"):
        link(f, search_range=1.0)


def test_link_matches_trackpy_with_estimated_range():
    rng = np.random.default_rng(5)
    f = _movie(rng, 150, 200.0, 30, 1.5).rename(columns={"y": "y_px", "x": "x_px"})
    out = link(f)
    sr = out.attrs["link"]["search_range_px"]
    a = _trackpy_ids(f, (sr, sr), 3, ["y_px", "x_px"])
    assert _same_partition(a, out["particle"].to_numpy())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nn_steps_are_mutual_nearest_neighbours(seed):
    """ptrack.linknb.nn_steps (the sweep in x) gives the steps of scipy's mutual nearest neighbours, in their
    order, between consecutive frames only (a missing frame number breaks the chain)."""
    from scipy.spatial import cKDTree

    from ptrack.link import _nn_steps

    rng = np.random.default_rng(seed)
    frames = np.sort(rng.choice([0, 1, 2, 4, 5, 6], 400))
    x = rng.uniform(0, 200, 400)
    x[::7] = np.round(x[::7])                   # equal x values in a frame
    y = rng.uniform(0, 50, 400)
    dx, dy = _nn_steps(frames, x, y)
    want_x, want_y = [], []
    for f in (0, 1, 4, 5):
        a = np.c_[x[frames == f], y[frames == f]]
        b = np.c_[x[frames == f + 1], y[frames == f + 1]]
        ib = cKDTree(a).query(b)[1]
        ia = cKDTree(b).query(a)[1]
        mutual = ib[ia] == np.arange(len(a))
        want_x.append(b[ia[mutual], 0] - a[mutual, 0])
        want_y.append(b[ia[mutual], 1] - a[mutual, 1])
    assert len(dx) > 100
    np.testing.assert_array_equal(dx, np.concatenate(want_x))
    np.testing.assert_array_equal(dy, np.concatenate(want_y))


def test_robust_step_is_numpys_median_and_percentile_to_the_bit():
    # ptrack.linknb.robust_step (one numba call) against the numpy expression it replaces, with ties, zeros,
    # heavy tails and lengths 1 to 3000 (odd and even: both medians, every percentile interpolation case)
    from ptrack.linknb import _median, _percentile, robust_step

    rng = np.random.default_rng(21)
    for t in range(600):
        m = int(rng.integers(1, 3000)) if t % 4 else int(rng.integers(1, 9))
        d = rng.normal(size=m) * rng.uniform(0.01, 10)
        if t % 3 == 0:
            d = np.round(d, 1)
        if t % 5 == 0:
            d[: m // 3] = 0.0
        if t % 7 == 0:
            d = rng.standard_cauchy(m)
        want = max(5.0 * 1.4826 * np.median(np.abs(d - np.median(d))), 1.5 * np.percentile(np.abs(d), 99))
        assert robust_step(d) == want
        assert _median(d) == np.median(d)
        for q in (0.0, 1.0, 50.0, 99.0, 100.0):
            assert _percentile(np.abs(d), q) == np.percentile(np.abs(d), q)
