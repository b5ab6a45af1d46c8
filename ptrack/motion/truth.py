"""Matching found particles to a ground truth (synthetic movies): the one rule used by the main job, tests and benches."""
from __future__ import annotations

import numpy as np
import pandas as pd


def match_truth(found: pd.DataFrame, truth: pd.DataFrame, max_px: float = 2.0, columns=("x_px", "y_px"),
                mutual: bool = False):
    """Pair each found localisation with the nearest true particle of the same frame.

    Parameters
    ----------
    found, truth : DataFrame
        Tables with ``frame`` and the position ``columns``.
    max_px : float
        Largest distance of a pair (units of ``columns``; px by default).
    columns : sequence of str
        Position columns compared.
    mutual : bool
        Keep only mutual nearest pairs (the true particle's nearest found one is
        that found one too): a one-to-one matching, for precision and recall
        counts where two localisations of one particle must not both count.

    Returns
    -------
    (found_index, truth_index) : ndarray, ndarray
        Index labels of the pairs closer than ``max_px`` (unless ``mutual``,
        a true particle may be the nearest of several found ones).

    Examples
    --------
    >>> import pandas as pd
    >>> f = pd.DataFrame({"frame": [0, 0], "x_px": [1.1, 9.0], "y_px": [1.0, 9.0]})
    >>> t = pd.DataFrame({"frame": [0, 0], "x_px": [1.0, 5.0], "y_px": [1.0, 5.0]})
    >>> match_truth(f, t)
    (array([0]), array([0]))
    >>> f2 = pd.DataFrame({"frame": [0, 0], "x_px": [1.1, 1.5], "y_px": [1.0, 1.0]})   # two on one particle
    >>> match_truth(f2, t)[1], match_truth(f2, t, mutual=True)
    (array([0, 0]), (array([0]), array([0])))
    """
    from scipy.spatial import cKDTree

    cols = list(columns)
    fi, ti = [np.zeros(0, dtype=found.index.dtype)], [np.zeros(0, dtype=truth.index.dtype)]
    tg = {f: g for f, g in truth.groupby("frame")}
    for f, g in found.groupby("frame"):
        t = tg.get(f)
        if t is None or len(t) == 0:
            continue
        fx, tx = g[cols].to_numpy(float), t[cols].to_numpy(float)
        d, j = cKDTree(tx).query(fx)
        ok = d < max_px
        if mutual:
            _, back = cKDTree(fx).query(tx)
            ok &= back[j] == np.arange(len(fx))
        fi.append(g.index.to_numpy()[ok])
        ti.append(t.index.to_numpy()[j[ok]])
    return np.concatenate(fi), np.concatenate(ti)
