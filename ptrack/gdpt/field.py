"""Field-dependent GDPT calibration: a z correction that varies smoothly across the field of view.

A calibration stack records the image of a bead at known stage heights z_k
at *one* place in the field. Real objectives are not the same everywhere:
the focal surface is curved (Petzval field curvature) or tilted against the
sample (a tilted coverslip or stage), and astigmatism grows away from the
axis. A particle at the edge of the field at height z then looks like the
calibration bead at another height, and GDPT reads it off by up to a
micrometre however good the templates are (``sim.render.optics.Optics``
renders such optics with ``field_curvature`` / ``field_tilt``).

When the stack holds several beads spread over the field (stuck on the same
glass, stepped together), each bead is its own calibration of the place it
sits at. This module keeps *one* template stack for matching (the beads
registered and averaged by :func:`ptrack.calibration.build_calibration`, the
least noisy templates and one matching pass per particle) and learns, from
the beads, how that stack *reads* at each place in the field:

1. every page of the stack is located exactly as a movie frame is
   (:func:`ptrack.calibration.locate_frame_3d`), and each bead's reading
   ``zr_b(z_k)`` is kept: its own z-response curve (offset, scale and any
   nonlinearity);
2. at each page height z_k the reading error ``d_k = zr - z_k`` of the beads
   is fitted by a low-order polynomial surface in the image position
   (constant; tilt ``1, x, y``; tilt + curvature ``1, x, y, x^2 + y^2``; full
   quadratic), the order chosen from the number of beads so that the fit is
   overdetermined, or taken from the nearest bead (``basis="nearest"``);
3. a particle read at ``zr`` at image position (x, y) gets the height z
   whose predicted reading ``z + d(x, y, z)`` equals ``zr`` (linear
   interpolation between page heights; the map is monotone in z).

Why a smooth correction of one averaged stack, not a template stack per
region: the beads' readings carry every field effect that moves z (a focal
shift is a pure offset, a change of astigmatism a change of scale: both are
in the curve), a smooth surface interpolates between beads and extrapolates
a little beyond them where nearest-bead stacks jump, a single bead's
templates are several times noisier than the average of all, and matching
once against one stack costs what an uncorrected calibration costs. The
price: the averaged templates blur what differs between beads, which lowers
Cm slightly; the correction is calibrated on the same averaged templates, so
it stays consistent.

All heights in m, image positions in px (``x_px`` along columns, ``y_px``
along rows).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..errors import UserError
from ..motion.truth import match_truth

__all__ = ["FieldCalibration", "BASES", "field_basis", "read_beads", "build_field_calibration",
           "load_field_calibration", "correct_z", "locate_frame_field"]

# name -> number of terms; "auto" picks the largest with at least one bead more than terms
BASES = {"constant": 1, "tilt": 3, "tilt+curvature": 4, "quadratic": 6}


def field_basis(u, v, basis: str) -> np.ndarray:
    """Polynomial terms of the field model at normalised image positions (u, v).

    Parameters
    ----------
    u, v : array_like (N,)
        Image position relative to the beads' centre, in units of their spread (dimensionless).
    basis : str
        One of :data:`BASES`: ``constant`` (1), ``tilt`` (1, u, v),
        ``tilt+curvature`` (1, u, v, u^2 + v^2: a tilted paraboloid, field
        curvature about any axis position), ``quadratic`` (1, u, v, u^2, uv, v^2).

    Returns
    -------
    ndarray (N, P)
    """
    u = np.atleast_1d(np.asarray(u, np.float64))
    v = np.atleast_1d(np.asarray(v, np.float64))
    one = np.ones_like(u)
    if basis == "constant":
        cols = [one]
    elif basis == "tilt":
        cols = [one, u, v]
    elif basis == "tilt+curvature":
        cols = [one, u, v, u * u + v * v]
    elif basis == "quadratic":
        cols = [one, u, v, u * u, u * v, v * v]
    else:
        raise UserError(f"field basis {basis!r} is not known", f"give one of {', '.join(BASES)}, 'nearest' or 'auto'")
    return np.stack(cols, 1)


def auto_basis(n_beads: int) -> str:
    """The richest basis with fewer terms than beads (an overdetermined fit), ``constant`` for 1-2 beads."""
    best = "constant"
    for name, p in BASES.items():
        if n_beads >= p + 1:
            best = name
    return best


@dataclass
class FieldCalibration:
    """One template stack for matching plus a z correction that varies across the field.

    Attributes
    ----------
    calib : ptrack.calibration.Calibration
        The templates (all beads registered and averaged).
    z : ndarray (K,)
        Page heights the correction is tabulated at, m, increasing.
    bead_xy : ndarray (B, 2)
        (x_px, y_px) of each bead (median over its pages), px.
    bead_err : ndarray (B, K)
        Each bead's reading on ``calib`` minus the page height, m (NaN: not read).
    basis : str
        ``nearest`` or a key of :data:`BASES`.
    coef : ndarray (K, P)
        Per page height, the coefficients of the reading error over
        :func:`field_basis` (m); unused for ``nearest``.
    origin : (float, float)
        (x_px, y_px) the positions are measured from, px.
    scale : float
        px per unit of the normalised position.
    info : dict
        ``n_beads``, ``basis``, ``fit_rms`` (m, beads about the model),
        ``loo_rms`` (m, each bead predicted by the model fitted without it: the
        error of the correction between beads), ``bead_bias`` (m, each
        bead's median reading error: the bias a single calibration leaves
        there), ``read_seconds``.
    """

    calib: object
    z: np.ndarray
    bead_xy: np.ndarray
    bead_err: np.ndarray
    basis: str
    coef: np.ndarray
    origin: tuple
    scale: float
    info: dict = field(default_factory=dict)

    def _uv(self, x_px, y_px):
        return ((np.asarray(x_px, np.float64) - self.origin[0]) / self.scale,
                (np.asarray(y_px, np.float64) - self.origin[1]) / self.scale)

    def reading_error(self, x_px, y_px) -> np.ndarray:
        """Predicted reading error ``d(x, y, z_k)`` at each page height for particles at (x_px, y_px).

        Parameters
        ----------
        x_px, y_px : array_like (N,)
            Image positions, px.

        Returns
        -------
        ndarray (N, K), m
            What the averaged calibration reads minus the true height, for a
            particle at height ``z[k]`` at that place.
        """
        x_px = np.atleast_1d(np.asarray(x_px, np.float64))
        y_px = np.atleast_1d(np.asarray(y_px, np.float64))
        if self.basis == "nearest":
            return _nearest_error(self.bead_xy, self.bead_err, x_px, y_px)
        u, v = self._uv(x_px, y_px)
        return field_basis(u, v, self.basis) @ self.coef.T

    def correct(self, x_px, y_px, z_read) -> np.ndarray:
        """True heights of particles read at ``z_read`` (m) at image positions (x_px, y_px) (px), m.

        Inverts ``z -> z + d(x, y, z)`` (monotone, linear between page
        heights; beyond the first and last page the error of that page is
        subtracted). NaN readings stay NaN.
        """
        zr = np.atleast_1d(np.asarray(z_read, np.float64))
        D = self.reading_error(x_px, y_px)
        return invert_reading(self.z, D, zr)


def invert_reading(z, D, zr) -> np.ndarray:
    """Heights whose predicted reading ``z + D[i]`` equals ``zr[i]``; vectorised over rows.

    Parameters
    ----------
    z : ndarray (K,), increasing, m
    D : ndarray (N, K), m
        Reading error of each particle's place at each height.
    zr : ndarray (N,), m

    Returns
    -------
    ndarray (N,), m
    """
    z = np.asarray(z, np.float64)
    K = len(z)
    M = z[None, :] + D
    # the reading is monotone in z; enforce it against noise. j: first height whose reading exceeds zr, so
    # M[j - 1] <= zr < M[j] (never a zero-width interval)
    M = np.maximum.accumulate(M, axis=1)
    j = (M <= zr[:, None]).sum(1)
    out = np.full(len(zr), np.nan)
    lo = j == 0
    hi = j == K
    mid = ~lo & ~hi
    rows = np.arange(len(zr))
    out[lo] = zr[lo] - D[lo, 0]
    out[hi] = zr[hi] - D[hi, K - 1]
    jm = j[mid]
    rm = rows[mid]
    m0, m1 = M[rm, jm - 1], M[rm, jm]
    w = (zr[mid] - m0) / (m1 - m0)
    out[mid] = z[jm - 1] + w * (z[jm] - z[jm - 1])
    out[~np.isfinite(zr)] = np.nan
    return out


def _nearest_error(bead_xy, bead_err, x_px, y_px) -> np.ndarray:
    """Per particle and page: the error of the nearest bead read on that page (NaN if no bead was)."""
    d2 = (x_px[:, None] - bead_xy[None, :, 0]) ** 2 + (y_px[:, None] - bead_xy[None, :, 1]) ** 2   # (N, B)
    K = bead_err.shape[1]
    out = np.zeros((len(x_px), K))
    for k in range(K):                       # pages, not particles
        ok = np.isfinite(bead_err[:, k])
        if not ok.any():
            out[:, k] = np.nan
            continue
        dd = np.where(ok[None, :], d2, np.inf)
        out[:, k] = bead_err[np.argmin(dd, axis=1), k]
    return _fill_pages(out.T).T


def _fill_pages(c) -> np.ndarray:
    """Rows (pages) of ``c`` (K, P) that are NaN filled from the nearest valid pages (linear between)."""
    c = np.array(c, np.float64)
    K = c.shape[0]
    ok = np.all(np.isfinite(c), axis=1)
    if not ok.any():
        return np.zeros_like(c)
    k = np.arange(K)
    for p in range(c.shape[1]):
        c[:, p] = np.interp(k, k[ok], c[ok, p])
    return c


def read_beads(stack, z, calib, tolerance: float | None = None, **locate_options):
    """Each bead of a calibration stack read on a calibration, page by page, as a movie frame would be.

    Parameters
    ----------
    stack : array (K, H, W)
        The raw pages (ADU), in the order of ``z``.
    z : array (K,)
        Their heights, m.
    calib : ptrack.calibration.Calibration
        Built from this stack (``info["bead_xy"]``, ``info["rejected_per_bead"]``
        name the beads and the pages each was rejected on).
    tolerance : float, optional
        Largest distance (px) of a detection from the bead's median position;
        default a quarter of the largest template + 5 px (the bead's lateral
        drift through the stack).
    **locate_options
        Passed to :func:`ptrack.calibration.locate_frame_3d`.

    Returns
    -------
    xy : ndarray (B, K, 2)
        (x_px, y_px) of each bead on each page (NaN: not read), px.
    zr : ndarray (B, K)
        Its height read on ``calib``, m (NaN: not read, or a page the
        calibration rejected for that bead).
    """
    from ..calibration import locate_frame_3d

    stack = np.asarray(stack)
    z = np.asarray(z, np.float64)
    if stack.ndim != 3 or len(stack) != len(z):
        raise UserError(f"calibration stack of shape {stack.shape} with {len(z)} heights", "give one height per page")
    bxy = np.array(calib.info.get("bead_xy") or [], np.float64).reshape(-1, 2)
    B, K = len(bxy), len(z)
    rej = calib.info.get("rejected_per_bead") or [{} for _ in range(B)]
    tol = float(tolerance) if tolerance is not None else 0.25 * calib.size + 5.0
    order = np.argsort(z, kind="stable")      # rejected_per_bead counts pages in sorted-z order
    xy = np.full((B, K, 2), np.nan)
    zr = np.full((B, K), np.nan)
    signed = bool(calib.info.get("signed", False))
    for rank, k in enumerate(order):           # pages, a few dozen: not a hot path
        df = locate_frame_3d(stack[k], calib, brightfield=signed, **locate_options)
        if not len(df):
            continue
        px, py, pz = (df[c].to_numpy(np.float64) for c in ("x_px", "y_px", "z"))
        # each bead its mutually nearest detection within tol (a detection nearer to another bead is that
        # bead's), by the one matching rule
        found = pd.DataFrame({"frame": 0, "x_px": px, "y_px": py})
        beads = pd.DataFrame({"frame": 0, "x_px": bxy[:, 0], "y_px": bxy[:, 1]})
        for i, b in zip(*match_truth(found, beads, tol, mutual=True)):
            if rank in rej[b]:
                continue
            xy[b, k] = (px[i], py[i])
            zr[b, k] = pz[i]
    return xy, zr


def _fit_pages(U, V, E, basis: str):
    """Least-squares coefficients (K, P) of the reading errors E (B, K) over the basis at bead positions U, V."""
    B, K = E.shape
    P = BASES[basis]
    coef = np.full((K, P), np.nan)
    for k in range(K):                          # pages
        ok = np.isfinite(E[:, k]) & np.isfinite(U[:, k]) & np.isfinite(V[:, k])
        if ok.sum() < P:
            continue
        A = field_basis(U[ok, k], V[ok, k], basis)
        c, _, rank, sv = np.linalg.lstsq(A, E[ok, k], rcond=None)
        # beads missing on this page may leave the rest on a line: the surface is not determined there
        if rank < P or sv[-1] < 1e-3 * sv[0]:
            continue
        coef[k] = c
    return _fill_pages(coef)


def _drop_misreads(E, step: float):
    """NaN where a bead's reading error jumps away from its neighbours' (a misread page), in place.

    A bead's reading error changes slowly with z: each is compared with the
    median of the 5 pages around it; readings further than 5 robust
    standard deviations of those differences (at least a quarter of the step) are dropped.
    """
    B, K = E.shape
    for b in range(B):                          # beads
        idx = np.nonzero(np.isfinite(E[b]))[0]
        if len(idx) < 5:
            continue
        e = E[b, idx]
        med = np.array([np.median(e[max(0, i - 2):i + 3]) for i in range(len(e))])
        r = e - med
        s = 1.4826 * float(np.median(np.abs(r)))
        E[b, idx[np.abs(r) > max(5.0 * s, 0.25 * step)]] = np.nan
    return E


def build_field_calibration(stack, z, pixel_size=None, calib=None, basis: str = "auto", brightfield=None,
                            max_beads: int | None = None, fine_step="auto", tolerance: float | None = None,
                            **locate_options) -> FieldCalibration:
    """A field-dependent calibration from a stack with several beads across the field.

    Parameters
    ----------
    stack : array (K, H, W)
        Raw calibration pages (ADU), one per height.
    z : array (K,)
        Page heights (stage positions), m.
    pixel_size : float, optional
        m per pixel (stored on the calibration).
    calib : ptrack.calibration.Calibration, optional
        The averaged templates, if already built from this stack
        (:func:`ptrack.calibration.build_calibration`); else built here with
        ``brightfield``, ``max_beads`` and ``fine_step``.
    basis : str
        ``auto`` (the richest polynomial with fewer terms than beads: 3
        beads -> ``tilt``, 5 -> ``tilt+curvature``, 7 or more ->
        ``quadratic``), a key of :data:`BASES`, or ``nearest`` (each
        particle takes the z-response curve of the nearest bead, no smoothing).
    brightfield, max_beads, fine_step
        As :func:`ptrack.calibration.build_calibration`.
    tolerance : float, optional
        See :func:`read_beads`.
    **locate_options
        Passed to :func:`ptrack.calibration.locate_frame_3d` (use the same
        as for the movie).

    Returns
    -------
    FieldCalibration

    Raises
    ------
    UserError
        The stack shows fewer than 2 beads read on 3 or more pages (a field
        map needs beads at several places).
    """
    from ..calibration import build_calibration

    t0 = time.perf_counter()
    stack = np.asarray(stack)
    z = np.asarray(z, np.float64)
    if calib is None:
        calib = build_calibration(stack, z, pixel_size, brightfield=brightfield, max_beads=max_beads,
                                  fine_step=fine_step)
    xy, zr = read_beads(stack, z, calib, tolerance, **locate_options)
    order = np.argsort(z)
    z, xy, zr = z[order], xy[:, order], zr[:, order]
    step = float(np.median(np.diff(z))) if len(z) > 1 else 0.0
    E = zr - z[None, :]
    # readings within half a step of the calibrated range's ends are clipped there, not measured
    lo, hi = float(calib.z[0]), float(calib.z[-1])
    E[(zr < lo + 0.5 * step) | (zr > hi - 0.5 * step)] = np.nan
    _drop_misreads(E, step)
    used = np.sum(np.isfinite(E), axis=1) >= 3
    if used.sum() < 2:
        raise UserError(f"the calibration stack shows {int(used.sum())} bead(s) read on 3 or more pages",
                        "a field-dependent calibration needs beads at several places in the field (2 or more; "
                        "5 or more for field curvature)")
    xy, E = xy[used], E[used]
    bead_xy = np.nanmedian(xy, axis=1)
    origin = (float(bead_xy[:, 0].mean()), float(bead_xy[:, 1].mean()))
    scale = float(max(np.hypot(bead_xy[:, 0] - origin[0], bead_xy[:, 1] - origin[1]).max(), 1.0))
    U = (xy[:, :, 0] - origin[0]) / scale
    V = (xy[:, :, 1] - origin[1]) / scale
    nb = int(len(bead_xy))
    if basis == "auto":
        basis = auto_basis(nb)
    if basis != "nearest":
        if basis not in BASES:
            field_basis([0.0], [0.0], basis)       # raises the UserError naming the choices
        if BASES[basis] > nb:
            raise UserError(f"field basis {basis!r} has {BASES[basis]} terms but the stack has {nb} beads",
                            "give a smaller basis or 'auto'")
        coef = _fit_pages(U, V, E, basis)
    else:
        coef = np.zeros((len(z), 0))
    fc = FieldCalibration(calib, z, bead_xy, E, basis, coef, origin, scale)
    # fit residual and leave-one-out error (the correction's error between beads)
    pred = np.full_like(E, np.nan)
    loo = np.full_like(E, np.nan)
    for b in range(nb):                        # beads (a handful)
        pb = np.array([fc.reading_error([xy[b, k, 0]], [xy[b, k, 1]])[0, k] if np.isfinite(E[b, k]) else np.nan
                       for k in range(len(z))])
        pred[b] = pb
        keep = np.arange(nb) != b
        if basis == "nearest":
            if keep.sum():
                loo[b] = _nearest_error(bead_xy[keep], E[keep], bead_xy[b:b + 1, 0], bead_xy[b:b + 1, 1])[0]
        elif keep.sum() >= BASES[basis]:
            cb = _fit_pages(U[keep], V[keep], E[keep], basis)
            loo[b] = np.einsum("kp,kp->k", field_basis(U[b], V[b], basis), cb)
    with np.errstate(invalid="ignore"):
        fit_rms = float(np.sqrt(np.nanmean((E - pred) ** 2)))
        loo_rms = float(np.sqrt(np.nanmean((E - loo) ** 2))) if np.isfinite(loo).any() else float("nan")
    fc.info = {"n_beads": nb, "basis": basis, "fit_rms": fit_rms, "loo_rms": loo_rms,
               "bead_bias": np.nanmedian(E, axis=1), "read_seconds": time.perf_counter() - t0}
    return fc


def load_field_calibration(path, calib=None, basis: str = "auto", locate_options: dict | None = None,
                           **calibration_options) -> FieldCalibration:
    """Read a calibration stack file and build its field-dependent calibration.

    Parameters
    ----------
    path : path
        Calibration stack (any format of :func:`ptrack.io.open_movie`).
    calib : ptrack.calibration.Calibration, optional
        Already loaded from ``path`` by :func:`ptrack.calibration.load_calibration`
        (not built twice); else loaded here with ``calibration_options``.
    basis : str
        See :func:`build_field_calibration`.
    locate_options : dict, optional
        Passed to :func:`ptrack.calibration.locate_frame_3d` (the movie's: ``snr``, ``cm_min``...).
    **calibration_options
        Passed to :func:`ptrack.calibration.load_calibration` (heights:
        ``z_csv``, ``z_step``, ``z0``; ``pixel_size``, ``brightfield``...).

    Returns
    -------
    FieldCalibration
    """
    from ..calibration import load_calibration
    from ..io import open_movie

    cal = calib if calib is not None else load_calibration(path, **calibration_options)
    with open_movie(path, pixel_size=calibration_options.get("pixel_size")) as mv:
        stack = np.stack([mv[i] for i in range(len(mv))])
    z = cal.info.get("stack_z")
    if z is None:
        z = _stack_heights(path, len(stack), calibration_options)
    return build_field_calibration(stack, np.asarray(z, np.float64), cal.pixel_size, calib=cal, basis=basis,
                                   **(locate_options or {}))


def _stack_heights(path, n_pages: int, opts: dict) -> np.ndarray:
    """Heights of every page in file order, found as :func:`ptrack.calibration.load_calibration` finds them
    (used when its Calibration does not carry ``info["stack_z"]``)."""
    from ..calibration import read_calib_z
    from .heights import heights_from_metadata, z_csv_beside

    if opts.get("z_csv") is not None:
        return read_calib_z(opts["z_csv"], n_pages)
    if opts.get("z_step") is not None:
        return float(opts.get("z0", 0.0)) + float(opts["z_step"]) * np.arange(n_pages)
    beside = z_csv_beside(path)
    if beside is not None:
        return read_calib_z(beside, n_pages)
    meta = heights_from_metadata(path, n_pages, float(opts.get("z0", 0.0)))
    if meta is None:
        raise UserError("the heights of the calibration pages are not given",
                        "give z_csv (columns page, z in m) or z_step, or put calib_z.csv beside the stack")
    return np.asarray(meta[0], np.float64)


def correct_z(table: pd.DataFrame, fcal: FieldCalibration, pixel_size: float | None = None,
              z_col: str = "z") -> pd.DataFrame:
    """A located table (one frame or many) with z corrected for where each particle is in the field.

    Parameters
    ----------
    table : DataFrame
        With ``x_px``, ``y_px`` (px) or ``x``, ``y`` (m, then ``pixel_size``
        or the calibration's), and ``z`` (m, read on ``fcal.calib``).
    fcal : FieldCalibration
    pixel_size : float, optional
        m per pixel, to convert ``x``, ``y`` when there are no px columns.
    z_col : str
        The height column.

    Returns
    -------
    DataFrame
        A copy: ``z`` corrected (m), ``z_read`` the uncorrected reading (m).
    """
    out = table.copy()
    if "x_px" in out.columns and "y_px" in out.columns:
        x, y = out["x_px"].to_numpy(np.float64), out["y_px"].to_numpy(np.float64)
    else:
        px = pixel_size or getattr(fcal.calib, "pixel_size", None)
        if not px or "x" not in out.columns:
            raise UserError("the table has no x_px, y_px columns and no pixel size is known",
                            "give pixel_size (m) or a table with x_px, y_px")
        x, y = out["x"].to_numpy(np.float64) / px, out["y"].to_numpy(np.float64) / px
    zr = out[z_col].to_numpy(np.float64)
    out["z_read"] = zr
    out[z_col] = fcal.correct(x, y, zr) if len(out) else zr
    return out


def locate_frame_field(raw, fcal: FieldCalibration, **options) -> pd.DataFrame:
    """Particles and their heights in one raw frame, z corrected across the field.

    :func:`ptrack.calibration.locate_frame_3d` on ``fcal.calib`` (same
    ``options``), then :func:`correct_z`.

    Returns
    -------
    DataFrame
        As :func:`ptrack.calibration.locate_frame_3d`, ``z`` corrected and
        ``z_read`` the reading on the averaged stack (m).
    """
    from ..calibration import locate_frame_3d

    return correct_z(locate_frame_3d(raw, fcal.calib, **options), fcal)
