"""ptrack.motion.detection_scores: recall, precision, RMSE and nearest distances through the one matching rule."""
import numpy as np
import pandas as pd
import pytest

from ptrack.motion import detection_scores, match_truth


def _t(frame, x, y):
    return pd.DataFrame({"frame": frame, "x_px": x, "y_px": y})


def test_counts_rmse_and_nearest_by_frame():
    truth = _t([0, 0, 1, 1], [0.0, 10.0, 0.0, 10.0], [0.0, 0.0, 0.0, 0.0])
    # frame 0: (0, 0) hit at (+0.3, -0.4), (10, 0) missed, one false detection far away; frame 1: (10, 0) hit at
    # (-0.6, +0.8), (0, 0) missed; the nearest distances stay within each frame
    found = _t([0, 0, 1], [0.3, 50.0, 9.4], [-0.4, 50.0, 0.8])
    s = detection_scores(found, truth, max_px=2.0)
    assert s["recall"] == 0.5 and s["precision"] == pytest.approx(2 / 3)
    assert s["n_found"] == 3 and s["n_truth"] == 4
    assert s["rmse"] == pytest.approx(np.sqrt([(0.09 + 0.36) / 2, (0.16 + 0.64) / 2]))
    np.testing.assert_allclose(s["nearest"], [0.5, np.hypot(9.7, 0.4), np.hypot(9.4, 0.8), 1.0])
    fi, ti = s["pairs"]
    assert fi.tolist() == [0, 2] and ti.tolist() == [0, 3]


def test_positions_not_labels_arrays_and_empty():
    truth = _t([0, 0], [0.0, 5.0], [0.0, 0.0]).set_index(pd.Index([7, 7]))      # duplicate labels
    found = _t([0], [4.5], [0.0]).set_index(pd.Index([3]))
    s = detection_scores(found, truth, max_px=1.0)
    assert s["pairs"][0].tolist() == [0] and s["pairs"][1].tolist() == [1]
    a = detection_scores([[4.5, 0.0]], [[0.0, 0.0], [5.0, 0.0]], max_px=1.0)      # plain arrays: one frame
    assert a["recall"] == s["recall"] == 0.5 and a["precision"] == 1.0
    e = detection_scores(np.zeros((0, 2)), [[0.0, 0.0]])
    assert e["recall"] == 0.0 and e["precision"] == 0.0 and np.isnan(e["rmse"]).all() and e["nearest"][0] == np.inf
    assert np.isnan(detection_scores([[0.0, 0.0]], np.zeros((0, 2)))["recall"])


def test_duplicates_count_once_for_recall_and_are_dropped_when_mutual():
    truth = _t([0], [0.0], [0.0])
    found = _t([0, 0], [0.2, -0.5], [0.0, 0.0])                    # two localisations of one particle
    s = detection_scores(found, truth)
    assert s["recall"] == 1.0 and s["precision"] == 1.0
    assert s["rmse"][0] == pytest.approx(np.sqrt((0.04 + 0.25) / 2))
    m = detection_scores(found, truth, mutual=True)
    assert m["recall"] == 1.0 and m["precision"] == 0.5 and m["rmse"][0] == pytest.approx(0.2)
    assert [p.tolist() for p in m["pairs"]] == [list(v) for v in match_truth(found, truth, mutual=True)]
