"""Trajectories table -> arrays for the estimators: the one place for axes, frame interval, motion blur, sorting.

Every estimator of :mod:`ptrack.motion` goes through these functions, so a
table is checked, sorted and timed by one rule:

- :func:`parse_axes`: MSD axes (``x``, ``y``, ``z``, ``xy``, ``xz``, ``yz``,
  ``xyz``) and :func:`axis_components` the coordinate columns they use. Code
  that works per coordinate (velocities) takes the components of the axes,
  so ``"xy"`` means the x and y columns everywhere.
- :func:`frame_interval`: seconds per frame.
- :func:`check_motion_blur`: the motion-blur parameter R (library and
  command line), and :func:`motion_blur_from_exposure` /
  :func:`exposure_from_motion_blur`: R <-> the exposure of a uniform shutter.
- :func:`sort_tracks` (rows sorted by particle and frame) and
  :func:`prepare_tracks` (dense-in-time arrays with NaN in the gaps, for the
  MSD and CVE kernels), built on it.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..errors import UserError

#: axis name -> the coordinate columns summed in its MSD
AXES = {
    "x": ("x",), "y": ("y",), "z": ("z",),
    "xy": ("x", "y"), "xz": ("x", "z"), "yz": ("y", "z"), "xyz": ("x", "y", "z"),
}
#: coordinate columns of a trajectories table, in order
COMPONENTS = ("x", "y", "z")
#: default longest lag (frames) of MSD tables
DEFAULT_MAX_LAG = 100
from ..constants import MOTION_BLUR_MAX  # noqa: E402  (the one range, shared with ptrack.options)
#: largest |coordinate| (m) accepted: squares and sums of squares of larger values overflow float64
MAX_COORDINATE = 1e150


def check_coordinates(column: str, values) -> float:
    """The largest finite |value| of a coordinate column (m); UserError beyond :data:`MAX_COORDINATE`.

    The one rule for "is this a position in m" shared by the estimators and
    the renderer (``sim.render``): NaN (a missing z) is allowed, infinity and
    magnitudes whose squares overflow (and infinity) are not.
    """
    v = np.asarray(values, dtype=float)
    big = float(np.nanmax(np.abs(v))) if (~np.isnan(v)).any() else 0.0
    if not big <= MAX_COORDINATE:
        raise UserError(f"column '{column}' holds {big:.3g}: not a position in m (squared displacements overflow)",
                        "give positions in m (a microscope field is about 1e-4 m)")
    return big


def parse_axes(axes) -> tuple:
    """MSD axes from ``"x,y,xy"``, ``("x", "xy")`` ...: a tuple of names from :data:`AXES`.

    Examples
    --------
    >>> parse_axes("x, y, xy")
    ('x', 'y', 'xy')
    >>> axis_components(parse_axes("xyz"))
    ('x', 'y', 'z')
    """
    if isinstance(axes, str):
        axes = [a.strip().lower() for a in axes.split(",") if a.strip()]
    axes = tuple(str(a).lower() for a in axes)
    if not axes:
        raise UserError("no axes given", f"choose from {', '.join(AXES)}")
    for a in axes:
        if a not in AXES:
            raise UserError(f"unknown axis '{a}'", f"choose from {', '.join(AXES)}")
    if len(set(axes)) != len(axes):
        raise UserError(f"repeated axis in {axes!r}", "name each axis once")
    return axes


def axis_components(axes) -> tuple:
    """Coordinate columns used by the axes (parsed or not), in x, y, z order."""
    names = {c for a in parse_axes(axes) for c in AXES[a]}
    return tuple(c for c in COMPONENTS if c in names)


def check_motion_blur(motion_blur, name: str = "motion_blur") -> float:
    """The motion-blur parameter R as a float in [0, 1/4), or a UserError: the one rule (and message) of the toolkit.

    R = (exposure / frame interval) / 6 for a uniform exposure
    (:func:`motion_blur_from_exposure`): 1/6 with the shutter open the whole
    frame, 0 for instantaneous positions (simulations). The command-line
    option ``--motion-blur`` is checked by this function too
    (:data:`ptrack.options.MOTION_BLUR`).

    Parameters
    ----------
    motion_blur : float
        R (dimensionless).
    name : str
        How the value is named in the message (``"--motion-blur"`` on the command line).

    Examples
    --------
    >>> check_motion_blur(1 / 6) == 1 / 6
    True
    >>> check_motion_blur(0.3, "--motion-blur")
    Traceback (most recent call last):
    ...
    ptrack.errors.UserError: --motion-blur = 0.3 outside [0, 1/4); use exposure / frame interval / 6: 1/6 for a shutter open the whole frame, 0 for instantaneous
    """
    fix = "use exposure / frame interval / 6: 1/6 for a shutter open the whole frame, 0 for instantaneous"
    try:
        if isinstance(motion_blur, bool):
            raise TypeError
        R = float(motion_blur)
    except (TypeError, ValueError):
        raise UserError(f"{name} = {motion_blur!r} is not a number", fix)
    if not (math.isfinite(R) and 0.0 <= R < MOTION_BLUR_MAX):
        raise UserError(f"{name} = {motion_blur!r} outside [0, 1/4)", fix)
    return R


#: R of a uniform exposure lasting the whole frame interval (the largest R a uniform shutter gives)
FULL_FRAME_MOTION_BLUR = 1.0 / 6.0


def motion_blur_from_exposure(exposure: float, frame_interval: float) -> float:
    """R of a uniform exposure: (exposure / frame interval) / 6; the inverse of :func:`exposure_from_motion_blur`.

    Parameters
    ----------
    exposure : float
        Time the shutter is open per frame, s (0: instantaneous).
    frame_interval : float
        Time between frames, s.

    Returns
    -------
    float
        R in [0, 1/6] (an exposure longer than the frame interval by more than
        1e-9 relative is a UserError).

    Examples
    --------
    >>> motion_blur_from_exposure(0.1, 0.1) == FULL_FRAME_MOTION_BLUR, motion_blur_from_exposure(0.0, 0.1)
    (True, 0.0)
    """
    exposure, frame_interval = float(exposure), float(frame_interval)
    if not (math.isfinite(frame_interval) and frame_interval > 0):
        raise UserError(f"frame interval {frame_interval!r} s is not positive", "give the time between frames in s")
    R = exposure / frame_interval / 6.0
    if not (math.isfinite(R) and 0.0 <= R <= FULL_FRAME_MOTION_BLUR * (1 + 1e-9)):
        raise UserError(f"exposure {exposure:g} s is not within 0 .. the frame interval {frame_interval:g} s",
                        "give the exposure time per frame in s (at most the frame interval)")
    return min(R, FULL_FRAME_MOTION_BLUR)


def exposure_from_motion_blur(motion_blur: float, frame_interval: float) -> float:
    """Exposure (s) of a uniform shutter giving R: 6 R x frame interval; the inverse of :func:`motion_blur_from_exposure`.

    Parameters
    ----------
    motion_blur : float
        R >= 0 (dimensionless). A measured R above 1/6 (noise, or a
        non-uniform exposure) gets the whole frame interval: no uniform
        exposure gives more.
    frame_interval : float
        Time between frames, s.

    Examples
    --------
    >>> round(exposure_from_motion_blur(0.1, 0.1), 12), exposure_from_motion_blur(0.2, 0.1)
    (0.06, 0.1)
    """
    R, frame_interval = float(motion_blur), float(frame_interval)
    if not (math.isfinite(R) and R >= 0):
        raise UserError(f"motion blur R = {motion_blur!r} is not a number >= 0", "give R = exposure / frame interval / 6")
    if not (math.isfinite(frame_interval) and frame_interval > 0):
        raise UserError(f"frame interval {frame_interval!r} s is not positive", "give the time between frames in s")
    return min(R / FULL_FRAME_MOTION_BLUR, 1.0) * frame_interval


def frame_interval(df: pd.DataFrame) -> float:
    """Frame interval (s) of a trajectories or localisation table: the one rule of the toolkit.

    From the ``t`` column: the median of dt / dframe between consecutive
    rows of the same particle (between consecutive frames when the table has
    no ``particle`` column or no particle has two rows). The metadata
    ``frame_interval`` is used only when ``t`` cannot give one (a single
    frame); if both exist and differ by more than 1 %, ``t`` is used and a
    warning names both.

    Examples
    --------
    >>> import pandas as pd
    >>> frame_interval(pd.DataFrame({"frame": [0, 1, 3], "t": [0.0, 0.1, 0.3], "particle": [0, 0, 0]}))
    0.1
    """
    meta = df.attrs.get("ptrack", {}) or {}
    dt_meta = meta.get("frame_interval")
    dt = None
    if "t" in df.columns and "frame" in df.columns and len(df) > 1:
        f = df["frame"].to_numpy().astype(np.int64)
        t = df["t"].to_numpy(dtype=float)
        if "particle" in df.columns:
            p = df["particle"].to_numpy()
            order = np.lexsort((f, p))
            f, t, p = f[order], t[order], p[order]
            same = (p[1:] == p[:-1]) & (f[1:] != f[:-1])
        else:
            same = np.zeros(len(f) - 1, bool)
        if not same.any():
            u, i = np.unique(f, return_index=True)
            f, t = u, t[i]
            same = np.ones(len(f) - 1, bool)
        if same.any():
            dt = float(np.median((t[1:] - t[:-1])[same] / (f[1:] - f[:-1])[same]))
            if not (math.isfinite(dt) and dt > 0):
                raise UserError(f"frame interval from the 't' column is {dt!r} s", "'t' must increase with 'frame'")
    if dt is None:
        if dt_meta is None:
            raise UserError("cannot find the frame interval: one frame only and no 'frame_interval' metadata",
                            "give tracks of at least two frames")
        dt = float(dt_meta)
    elif dt_meta is not None and math.isfinite(float(dt_meta)) and abs(float(dt_meta) / dt - 1) > 0.01:
        warnings.warn(f"the 't' column gives {dt:g} s per frame, the metadata frame_interval {float(dt_meta):g} s; "
                      "using the 't' column", stacklevel=2)
    if not (math.isfinite(dt) and dt > 0):
        raise UserError(f"frame interval = {dt!r} s", "give a positive frame interval")
    return dt


@dataclass
class SortedTracks:
    """Rows of a trajectories table sorted by (particle, frame).

    Attributes
    ----------
    particles : ndarray (n_p,)
        Particle ids.
    off : ndarray (n_p + 1,)
        Row offsets of each particle.
    frames : ndarray (N,)
        Frame of each sorted row.
    vals : ndarray (k, N)
        The requested components (m), NaN where missing.
    dt : float
        Frame interval, s (:func:`frame_interval`).
    order : ndarray (N,)
        Sorted row -> row of the table.
    """

    particles: np.ndarray
    off: np.ndarray
    frames: np.ndarray
    vals: np.ndarray
    dt: float
    order: np.ndarray


def sort_tracks(df: pd.DataFrame, components) -> SortedTracks:
    """Check a trajectories table and sort its rows by (particle, frame): the one track preparation.

    Raises a UserError for a missing column, an empty table, z requested from
    a 2D table, or a particle seen twice in one frame.
    """
    components = tuple(components)
    for c in ("frame", "t", "particle", *components):
        if c not in df.columns:
            raise UserError(f"trajectories table lacks column '{c}'", "a trajectories table needs frame, t, particle, x, y, z")
    if len(df) == 0:
        raise UserError("the trajectories table is empty", "track some particles first")
    if "z" in components and not np.isfinite(df["z"].to_numpy(dtype=float)).any():
        raise UserError("z axis requested but the table is 2D (z is NaN everywhere)", "use the axes x, y, xy")
    part = df["particle"].to_numpy().astype(np.int64)
    frame = df["frame"].to_numpy().astype(np.int64)
    order = np.lexsort((frame, part))
    part, frame = part[order], frame[order]
    same = part[1:] == part[:-1]
    dup = same & (frame[1:] == frame[:-1])
    if dup.any():
        i = int(np.flatnonzero(dup)[0])
        raise UserError(f"particle {part[i]} appears twice in frame {frame[i]}", "each particle may appear once per frame")
    dt = frame_interval(df)
    starts = np.flatnonzero(np.r_[True, ~same])
    off = np.r_[starts, len(part)].astype(np.int64)
    vals = np.full((len(components), len(part)), np.nan)
    for j, c in enumerate(components):
        vals[j] = df[c].to_numpy(dtype=float)[order]
        check_coordinates(c, vals[j])
    return SortedTracks(part[starts], off, np.ascontiguousarray(frame), np.ascontiguousarray(vals), dt, order)


@dataclass
class Tracks:
    """Tracks laid out dense in time for the numba kernels: slot ``off[p] + frame - first[p]``, NaN in gaps."""

    particles: np.ndarray      # particle ids (n_p,)
    first: np.ndarray          # first frame of each particle (n_p,)
    off: np.ndarray            # offsets into the dense arrays (n_p + 1,)
    comps: dict                # component name -> dense float64 array (total,)
    dt: float                  # frame interval, s
    n_rows: np.ndarray         # rows (positions) per particle

    def stack(self, names):
        return np.ascontiguousarray(np.vstack([self.comps[c] for c in names]))


def prepare_tracks(df: pd.DataFrame, components, min_rows: int = 2) -> Tracks:
    """:func:`sort_tracks`, then the dense-in-time layout of the tracks with at least ``min_rows`` positions."""
    components = tuple(components)
    st = sort_tracks(df, components)
    n_rows = np.diff(st.off)
    keep = n_rows >= min_rows
    if not keep.any():
        raise UserError(f"every track is shorter than {min_rows} frames (longest: {int(n_rows.max())})",
                        f"give tracks of at least {min_rows} frames")
    starts, ends = st.off[:-1], st.off[1:]
    first = st.frames[starts]
    span = np.where(keep, st.frames[ends - 1] - first + 1, 0)
    off = np.zeros(len(starts) + 1, dtype=np.int64)
    np.cumsum(span, out=off[1:])
    row_p = np.repeat(np.arange(len(starts)), n_rows)
    rows_kept = keep[row_p]
    idx = off[row_p] + st.frames - first[row_p]
    comps = {}
    for j, c in enumerate(components):
        v = np.full(off[-1], np.nan)
        v[idx[rows_kept]] = st.vals[j][rows_kept]
        comps[c] = v
    sel = np.flatnonzero(keep)
    off_k = np.r_[off[sel], off[-1]].astype(np.int64)
    return Tracks(particles=st.particles[sel], first=first[sel].astype(np.int64), off=off_k,
                  comps=comps, dt=st.dt, n_rows=n_rows[sel])


def resolve_motion_blur(df: pd.DataFrame, motion_blur=None) -> tuple[float, str]:
    """The motion-blur parameter R to use for a table, and where it came from.

    In this order: ``motion_blur`` if given; the table's metadata
    (``motion_blur``; 0 for simulated positions, ``source`` starting with
    "sim", which are instantaneous; or ``exposure`` / ``frame_interval`` / 6
    for a uniform exposure); the metadata of the movie the table was tracked
    from (``source``: :func:`movie_exposure_metadata`, e.g. the renderer's
    ``params.json``); the data, when the table carries the localiser's
    precision (``sigma_x``, ``sigma_y`` in m: :func:`motion_blur_from_data`);
    else 1/6 (a shutter open the whole frame), said so.

    Returns
    -------
    (R, source)
        R in [0, 1/4) and one of ``"given"``, ``"metadata"``, ``"data"``,
        ``"default"`` followed by a short explanation.

    Examples
    --------
    >>> import pandas as pd
    >>> resolve_motion_blur(pd.DataFrame({"frame": [0], "t": [0.0], "particle": [0], "x": [0.0], "y": [0.0]}))
    (0.16666666666666666, 'default: R = 1/6 (shutter open the whole frame) assumed; give --motion-blur')
    """
    if motion_blur is not None:
        return check_motion_blur(motion_blur), "given"
    meta = df.attrs.get("ptrack", {}) or {}
    src = str(meta.get("source", ""))
    if meta.get("kind") == "simulated" or (src.startswith("sim") and "render_movie" not in src):
        # simulated positions and the ground truth of rendered movies are sampled at instants
        if not _number(meta.get("motion_blur")):
            return 0.0, "metadata: simulated positions are instantaneous"
    got = _blur_from_metadata(meta)
    if got is not None:
        return got[0], f"metadata: {got[1]}"
    if src and meta.get("kind") != "simulated":
        movie_meta = movie_exposure_metadata(src)
        got = _blur_from_metadata(movie_meta) if movie_meta else None
        if got is not None:
            return got[0], f"movie metadata ({movie_meta['_file']}): {got[1]}"
    R, _ = motion_blur_from_data(df)
    if R is not None:
        return R, "data: the localiser's sigma in the CVE's localisation variance"
    return 1 / 6, "default: R = 1/6 (shutter open the whole frame) assumed; give --motion-blur"


def _number(v) -> bool:
    """True for a finite real number (not a bool, not text such as "none (short exposure)")."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)


def _blur_from_metadata(meta: dict):
    """(R, explanation) from metadata keys, or None: ``motion_blur`` (a number; text is ignored),
    ``motion_blur_substeps`` = 0 of the renderer (positions drawn at an instant: R = 0), or ``exposure`` (s) /
    ``frame_interval`` (s) / 6 for a uniform exposure."""
    if not meta:
        return None
    if _number(meta.get("motion_blur")):
        try:
            return check_motion_blur(meta["motion_blur"]), "motion_blur"
        except UserError:
            pass
    sub = meta.get("motion_blur_substeps")
    if _number(sub) and int(sub) == 0 and str(meta.get("source", "")).startswith("sim.render"):
        return 0.0, "rendered without motion blur (motion_blur_substeps = 0)"
    exp, fi = meta.get("exposure"), meta.get("frame_interval")
    if _number(exp) and _number(fi):
        try:
            R = motion_blur_from_exposure(exp, fi)
        except UserError:  # an exposure longer than the frame: not a uniform shutter, the metadata are not used
            return None
        return R, f"exposure {float(exp):g} s / frame interval {float(fi):g} s / 6"
    return None


def movie_exposure_metadata(source) -> dict | None:
    """Exposure metadata of the movie a table was tracked from (its ``source``), or None.

    Read, in this order: ``params.json`` beside the movie (written by
    :func:`sim.render.render_movie`: ``exposure``, ``frame_interval``,
    ``motion_blur_substeps``, ``source``) and the JSON of the TIFF's ImageJ
    ``Info`` property (``exposure``, ``motion_blur`` when a writer puts them
    there). The first that holds exposure information is returned, with its
    file name under ``"_file"``. Nothing is guessed: a movie without such
    metadata gives None.
    """
    import json
    from pathlib import Path

    try:
        p = Path(str(source))
        if not p.exists():
            return None
        folder = p if p.is_dir() else p.parent
        keys = ("motion_blur", "exposure", "motion_blur_substeps")
        par = folder / "params.json"
        if par.is_file():
            with open(par) as fh:
                d = json.load(fh)
            mv = d.get("movie", "movie.tif")
            if isinstance(d, dict) and any(k in d for k in keys) and (p.is_dir() or p.name == mv
                                                                       or p.name == "movie.tif"):
                return {**d, "_file": par.name}
        if p.is_file() and p.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(p) as tif:
                info = (tif.imagej_metadata or {}).get("Info") if tif.is_imagej else None
            if info:
                d = json.loads(info)
                if isinstance(d, dict) and any(k in d for k in keys):
                    return {**d, "_file": p.name}
    except (OSError, ValueError, TypeError):
        return None
    return None


def motion_blur_from_data(df: pd.DataFrame, n_boot: int = 0, seed=0) -> tuple:
    """The motion-blur parameter R the data imply, given the localiser's precision: the one rule.

    For observed Brownian steps the CVE's moments are ``<dx^2> = 2 D dt (1 - 2R)
    + 2 sigma^2`` and ``<dx_n dx_n+1> = 2 R D dt - sigma^2`` (Vestergaard et al.
    2014), so with sigma from the localiser (columns ``sigma_x``, ``sigma_y``,
    m) ``R = (sigma^2 + <dx_n dx_n+1>) / (<dx^2> + 2 <dx_n dx_n+1>)``, pooled
    over x and y; the denominator is 2 D dt, so no D is needed.

    Parameters
    ----------
    df : DataFrame
        Trajectories table with ``sigma_x`` and/or ``sigma_y``.
    n_boot : int
        Bootstrap resamples over particles for the error (0: no error).
    seed : int or Generator

    Returns
    -------
    (R, R_err)
        R clipped to [0, 1/6] (None when the table does not tell it: no
        sigma columns, no consecutive steps); R_err the bootstrap standard
        deviation of the unclipped R (NaN with ``n_boot=0``).

    Examples
    --------
    >>> from ptrack.motion import brownian_field
    >>> df = brownian_field(n_frames=60, size=30e-6, density=0.2e12, D=1e-12, dt=0.1, sigma=30e-9, seed=1)
    >>> df["sigma_x"] = df["sigma_y"] = 30e-9
    >>> R, err = motion_blur_from_data(df, n_boot=100)
    >>> R < 3 * err            # instantaneous positions: R = 0 within its error
    True
    """
    comps = [c for c in ("x", "y") if f"sigma_{c}" in df.columns and c in df.columns]
    if len(comps) < 1 or not {"frame", "particle", "t"} <= set(df.columns):
        return None, None
    try:
        st = sort_tracks(df, comps)
    except UserError:
        return None, None
    P = len(st.particles)
    seg = np.repeat(np.arange(P), np.diff(st.off))
    step = (seg[1:] == seg[:-1]) & (np.diff(st.frames) == 1)
    # per-particle sums: s2 (sum, count), d^2 (sum, count), d_n d_n+1 (sum, count), pooled over the components
    sums = np.zeros((6, P))
    for j, c in enumerate(comps):
        v = st.vals[j]
        s2 = df[f"sigma_{c}"].to_numpy(dtype=float)[st.order] ** 2
        d = np.where(step, np.diff(v), np.nan)
        prod = d[1:] * d[:-1]
        for k, (x, g) in enumerate(((s2, seg), (d * d, seg[1:]), (prod, seg[1:-1]))):
            ok = np.isfinite(x)
            sums[2 * k] += np.bincount(g[ok], weights=x[ok], minlength=P)
            sums[2 * k + 1] += np.bincount(g[ok], minlength=P)
    tot = sums.sum(axis=1)
    if tot[1] == 0 or tot[3] == 0 or tot[5] == 0:
        return None, None

    def r_of(t):
        m2, m11 = t[2] / t[3], t[4] / t[5]
        den = m2 + 2 * m11
        return np.where(den > 0, (t[0] / t[1] + m11) / np.where(den > 0, den, 1.0), np.nan)

    R = float(r_of(tot))
    if not math.isfinite(R):
        return None, None
    err = math.nan
    if int(n_boot) > 0 and P > 1:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        W = rng.multinomial(P, np.full(P, 1 / P), size=int(n_boot)).astype(float)
        tb = W @ sums.T                                  # (n_boot, 6)
        with np.errstate(invalid="ignore", divide="ignore"):
            Rb = r_of(tb.T)
        Rb = Rb[np.isfinite(Rb)]
        if Rb.size > 1:
            err = float(np.std(Rb, ddof=1))
    return float(np.clip(R, 0.0, 1 / 6)), err
