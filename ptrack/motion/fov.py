"""Field-of-view correction: particles are tracked only while inside the field, so long steps are lost more often.

:func:`resolve_fov` turns the user's ``field_of_view`` into extents per
component; :func:`fov_weight` is the inverse-probability (Horvitz-Thompson)
weight the MSD and CVE kernels give each displacement.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
from numba import njit

from ..errors import UserError
from .tracks import Tracks


@njit(cache=True, inline="always")
def fov_weight(extent, length):
    """Inverse probability that a path segment of this extent lies inside a field of this length.

    For particles spread uniformly over the field, a segment spanning
    ``extent`` along an axis is seen whole (and so linked and counted) for a
    fraction ``1 - extent/length`` of its possible positions: long steps are
    lost at the edges more often than short ones, which biases the MSD low
    by about ``1.6 s / L`` (s the step standard deviation). Weighting each
    displacement by the inverse (Horvitz-Thompson) removes that bias. Clamped
    at 10 for segments nearly as long as the field.
    """
    q = 1.0 - extent / length
    return 1.0 / q if q > 0.1 else 10.0


def resolve_fov(df: pd.DataFrame, field_of_view) -> dict:
    """Field of view as ``{component: extent (m)}``; empty for none.

    ``field_of_view``: None (no correction), ``"auto"`` (the image: the
    range of the positions in x and y), a sequence of component names (their
    ranges, e.g. ``("x", "y", "z")`` when z is limited by the calibrated
    range and particles leave it), or a dict component -> extent (m) or
    (lo, hi).
    """
    if field_of_view is None:
        return {}
    if isinstance(field_of_view, str) and field_of_view != "auto":
        raise UserError(f"field_of_view = {field_of_view!r}", "give None, 'auto', component names or a dict component -> extent in m")
    if isinstance(field_of_view, str) or (isinstance(field_of_view, (tuple, list))
                                          and all(isinstance(c, str) for c in field_of_view)):
        names = ("x", "y") if isinstance(field_of_view, str) else tuple(field_of_view)
        out = {}
        for c in names:
            if c not in ("x", "y", "z") or c not in df.columns:
                raise UserError(f"field_of_view names {c!r}, not a position column of the table", "use x, y or z")
            v = df[c].to_numpy(dtype=float)
            v = v[np.isfinite(v)]
            if v.size and v.max() > v.min():
                out[c] = float(v.max() - v.min())
        return out
    out = {}
    for c, v in dict(field_of_view).items():
        if c not in ("x", "y", "z"):
            raise UserError(f"field_of_view has component {c!r}", "use x, y or z")
        ext = float(v[1]) - float(v[0]) if isinstance(v, (tuple, list, np.ndarray)) else float(v)
        if not (math.isfinite(ext) and ext > 0):
            raise UserError(f"field_of_view[{c!r}] = {v!r} is not a positive extent", "give the field's size in m")
        out[c] = ext
    return out


def fov_arrays(tr: Tracks, fov: dict):
    """(limited coordinates (n_f, total), their extents (n_f,)) for the numba kernels."""
    if not fov:
        return np.empty((0, tr.off[-1])), np.empty(0)
    return tr.stack(list(fov)), np.array(list(fov.values()), dtype=float)

