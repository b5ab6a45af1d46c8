"""GDPT crowding: the seeds of a joint fit of merged images (the local maxima of a window's correlation map)."""
import numpy as np

from ptrack.calibration import _best_in_window, _prepare_matching, build_calibration


def _blob(shape, y, x, s, amp):
    """An elliptical Gaussian whose axes swap with the sign of s - 3 (an astigmatic image), photons ~ amp."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    sy, sx = s, 6.0 - s
    return amp * np.exp(-0.5 * (((yy - y) / sy) ** 2 + ((xx - x) / sx) ** 2))


def test_window_peaks_find_both_images_of_a_merged_pair():
    """Two images 14 px apart at opposite heights: the window's correlation map has a maximum on each, more than
    ``sep`` px apart, best first; without ``n_peaks`` the single best (row, col, corr) as before."""
    rng = np.random.default_rng(0)
    z = np.linspace(-1e-6, 1e-6, 9)
    sig = np.linspace(1.5, 4.5, 9)
    stack = np.stack([_blob((41, 41), 20.0, 20.0, s, 100.0) + rng.normal(0, 1.0, (41, 41)) for s in sig])
    cal = build_calibration(stack, z, 1e-7, template_size=31)
    frame = _blob((80, 80), 40.0, 33.0, sig[1], 100.0) + _blob((80, 80), 40.0, 47.0, sig[7], 100.0)
    frame += rng.normal(0, 1.0, frame.shape)
    padded, pad, tmpl = _prepare_matching(frame, cal, 1.5, 4)
    pk = _best_in_window(padded, pad, tmpl, cal, 25, 55, 25, 55, 7, n_peaks=2, sep=8.0)
    assert len(pk) == 2 and pk[0][2] >= pk[1][2]
    got = sorted(c for _r, c, _v in pk)
    # a seed, at the pixel of the representative templates' map, pulled a little by the other image's light: the
    # match started there searches +-4 px
    assert abs(got[0] - 33) <= 4 and abs(got[1] - 47) <= 4, pk
    assert all(abs(r - 40) <= 4 for r, _c, _v in pk), pk
    best = _best_in_window(padded, pad, tmpl, cal, 25, 55, 25, 55, 7)
    assert best[2] == max(v for _r, _c, v in pk)
