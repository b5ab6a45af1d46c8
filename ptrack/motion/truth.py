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


def _as_table(a, columns) -> pd.DataFrame:
    """A found/truth table with positional rows: a DataFrame as is, or an (n, len(columns)) array as frame 0."""
    if isinstance(a, pd.DataFrame):
        return a.reset_index(drop=True)
    a = np.asarray(a, float).reshape(-1, len(columns))
    t = pd.DataFrame(a, columns=list(columns))
    t.insert(0, "frame", 0)
    return t


def detection_scores(found, truth, max_px: float = 2.0, columns=("x_px", "y_px"), mutual: bool = False) -> dict:
    """Recall, precision and RMSE of found particles against a ground truth, by :func:`match_truth`.

    Parameters
    ----------
    found, truth : DataFrame or array_like
        Tables with ``frame`` and the position ``columns``, or ``(n, len(columns))``
        position arrays of one frame (no frame column).
    max_px : float
        Largest distance of a pair (units of ``columns``; px by default).
    columns : sequence of str
        Position columns compared.
    mutual : bool
        One-to-one pairs only (see :func:`match_truth`).

    Returns
    -------
    dict
        ``pairs`` : (found_pos, truth_pos), row positions (0 .. n-1) of the
        :func:`match_truth` pairs; ``recall`` : distinct true particles paired /
        true particles (nan without truth); ``precision`` : found ones paired /
        found ones (0 when nothing is found); ``rmse`` : ndarray, RMS of
        found - true per column over the pairs (units of ``columns``; nan
        without pairs); ``nearest`` : ndarray, distance of every true particle
        to its nearest found one of its frame, at any range (inf when its frame
        has none), in the order of ``truth``; ``n_found``, ``n_truth`` : int.

    Examples
    --------
    >>> import numpy as np
    >>> s = detection_scores([[1.1, 1.0], [9.0, 9.0]], [[1.0, 1.0], [5.0, 5.0]], max_px=2.0)
    >>> s["recall"], s["precision"], np.round(s["rmse"], 3).tolist()
    (0.5, 0.5, [0.1, 0.0])
    >>> np.round(s["nearest"], 3).tolist()          # (5, 5): 5.587 px to (1.1, 1), 5.657 to (9, 9)
    [0.1, 5.587]
    """
    cols = list(columns)
    f, t = _as_table(found, cols), _as_table(truth, cols)
    fi, ti = match_truth(f, t, max_px, cols, mutual)
    fi, ti = np.asarray(fi, int), np.asarray(ti, int)
    fx, tx = f[cols].to_numpy(float), t[cols].to_numpy(float)
    e = fx[fi] - tx[ti]
    rmse = np.sqrt((e ** 2).mean(axis=0)) if len(e) else np.full(len(cols), np.nan)
    # the same rule with the roles swapped and no range: each true particle's nearest found one
    tn, fn = match_truth(t, f, np.inf, cols)
    nearest = np.full(len(t), np.inf)
    nearest[np.asarray(tn, int)] = np.sqrt(((tx[np.asarray(tn, int)] - fx[np.asarray(fn, int)]) ** 2).sum(axis=1))
    return {"pairs": (fi, ti), "recall": len(np.unique(ti)) / len(t) if len(t) else np.nan,
            "precision": len(np.unique(fi)) / len(f) if len(f) else 0.0, "rmse": rmse, "nearest": nearest,
            "n_found": len(f), "n_truth": len(t)}
