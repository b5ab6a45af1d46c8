"""Matching found particles to a ground truth (synthetic movies): the one rule used by the main job, tests and benches."""
from __future__ import annotations

import numpy as np
import pandas as pd


def match_truth(found: pd.DataFrame, truth: pd.DataFrame, max_px: float = 2.0, columns=("x_px", "y_px")):
    """Pair each found localisation with the nearest true particle of the same frame.

    Parameters
    ----------
    found, truth : DataFrame
        Tables with ``frame`` and the position ``columns``.
    max_px : float
        Largest distance of a pair (units of ``columns``; px by default).
    columns : sequence of str
        Position columns compared.

    Returns
    -------
    (found_index, truth_index) : ndarray, ndarray
        Index labels of the pairs closer than ``max_px`` (a true particle may
        be the nearest of several found ones).

    Examples
    --------
    >>> import pandas as pd
    >>> f = pd.DataFrame({"frame": [0, 0], "x_px": [1.1, 9.0], "y_px": [1.0, 9.0]})
    >>> t = pd.DataFrame({"frame": [0, 0], "x_px": [1.0, 5.0], "y_px": [1.0, 5.0]})
    >>> match_truth(f, t)
    (array([0]), array([0]))
    """
    from scipy.spatial import cKDTree

    cols = list(columns)
    fi, ti = [np.zeros(0, dtype=found.index.dtype)], [np.zeros(0, dtype=truth.index.dtype)]
    tg = {f: g for f, g in truth.groupby("frame")}
    for f, g in found.groupby("frame"):
        t = tg.get(f)
        if t is None or len(t) == 0:
            continue
        d, j = cKDTree(t[cols].to_numpy(float)).query(g[cols].to_numpy(float))
        ok = d < max_px
        fi.append(g.index.to_numpy()[ok])
        ti.append(t.index.to_numpy()[j[ok]])
    return np.concatenate(fi), np.concatenate(ti)
