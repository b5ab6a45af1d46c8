"""D per axis with standard errors from a trajectories table: :func:`estimate_diffusion`.

The estimate itself is :mod:`ptrack.motion.cve` or :mod:`ptrack.motion.ols`
(one function per axis each); this module prepares the tracks, corrects the
field of view and the drift, and picks the error: a bootstrap over whole
particles (resampling single displacements would ignore their correlations
and give errors about 2x too small), or the closed-form model error with
fewer than :data:`MIN_PARTICLES_BOOTSTRAP` particles.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..errors import UserError
from .cve import component_cve, cve_axis, cve_sums_ragged
from .drift import drift_corrected
from .fov import fov_arrays, resolve_fov
from .msd import default_max_lag, ensemble_from_sums, msd_sums
from .ols import ols_axis
from .tracks import AXES, axis_components, check_motion_blur, parse_axes, prepare_tracks


#: below this many particles the closed-form (model) standard error is reported
MIN_PARTICLES_BOOTSTRAP = 10


@dataclass
class DiffusionResult:
    """Diffusion coefficients per axis with errors (all SI).

    Attributes
    ----------
    D, D_err : dict axis -> float
        D (m^2/s) and its standard error; ``se_method`` says which error.
    D_err_model, D_err_boot : dict axis -> float
        Closed-form (model) and bootstrap-over-particles errors (NaN if not
        computed).
    sigma_loc : dict axis -> float
        Localisation error (m, standard deviation per component).
    n_particles, n_displacements : int
        Tracks used and frame-to-frame displacements.
    estimator : str
        ``"cve"`` or ``"ols"``.
    n_lags : dict axis -> int or None
        Lags used by the OLS fit.
    frame_interval, motion_blur : float
    se_method : str
        ``"bootstrap"`` or ``"model"``.
    drift_corrected : bool
    msd : DataFrame
        The ensemble MSD (:func:`ensemble_msd` layout) for plots.
    fit : dict axis -> dict
        ``slope`` (m^2/s), ``offset`` (m^2), ``n_dims``, ``t_max`` (s, end of
        the fitted range) of the model ``MSD = offset + slope t``.
    """

    D: dict
    D_err: dict
    D_err_model: dict
    D_err_boot: dict
    sigma_loc: dict
    n_particles: int
    n_displacements: int
    estimator: str
    n_lags: dict
    frame_interval: float
    motion_blur: float
    se_method: str
    drift_corrected: bool = False
    msd: pd.DataFrame | None = None
    fit: dict = field(default_factory=dict)

    def table(self) -> pd.DataFrame:
        """The seed's Table 4.1 layout, one row: D_<axis> and D_<axis>_err side by side (m^2/s)."""
        row = {}
        for a in self.D:
            row[f"D_{a}"] = self.D[a]
            row[f"D_{a}_err"] = self.D_err[a]
        return pd.DataFrame([row])

    def to_dict(self) -> dict:
        """JSON-ready summary (no MSD table)."""
        f = lambda d: {k: (None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v) for k, v in d.items()}
        return {
            "D": f(self.D), "D_err": f(self.D_err), "D_err_model": f(self.D_err_model),
            "D_err_boot": f(self.D_err_boot), "sigma_loc": f(self.sigma_loc),
            "n_particles": int(self.n_particles), "n_displacements": int(self.n_displacements),
            "estimator": self.estimator, "n_lags": dict(self.n_lags), "frame_interval": self.frame_interval,
            "motion_blur": self.motion_blur, "se_method": self.se_method, "drift_corrected": self.drift_corrected,
            "fit": {a: f(v) for a, v in self.fit.items()},
            "units": {"D": "m^2/s", "sigma_loc": "m", "frame_interval": "s"},
        }


def boot_weights(n_p, n_boot, rng):
    """(n_boot, n_p) counts of whole particles resampled with replacement."""
    return rng.multinomial(n_p, np.full(n_p, 1.0 / n_p), size=n_boot).astype(float)


def estimate_diffusion(df: pd.DataFrame, axes=("x", "y", "xy"), estimator: str = "cve", motion_blur: float = 1 / 6,
                       n_boot: int = 200, seed=0, subtract_drift: bool = False, max_lag=None,
                       field_of_view=None) -> DiffusionResult:
    """Diffusion coefficient per axis with standard errors.

    Parameters
    ----------
    df : DataFrame
        Trajectories table (gaps allowed). Tracks need at least 3 frames.
    axes : sequence of str
        Any of ``x, y, z, xy, xz, yz, xyz``; an n-component axis uses
        ``MSD = 2 n D t``.
    estimator : {"cve", "ols"}
        Covariance-based estimator, or least squares over the optimal number
        of lags.
    motion_blur : float
        R in [0, 1/4) (:func:`ptrack.motion.tracks.check_motion_blur`): 1/6 for a camera shutter open the whole frame
        (default, measured data), 0 for instantaneous positions (simulations).
        Only the localisation error (and the CVE's error model) depend on it;
        D does not.
    n_boot : int
        Bootstrap resamples of whole particles (0: model errors only).
    seed : int or numpy.random.Generator
        For the bootstrap.
    subtract_drift : bool
        Remove the common drift (per frame step) first, with the (1 - 1/M)
        bias correction.
    max_lag : int, optional
        Longest lag of the stored MSD table (frames).
    field_of_view : None, "auto", component names, or dict component -> extent (m) or (lo, hi)
        The region in which particles can be seen (the image, and in 3D the
        calibrated z range if particles leave it). A particle is tracked only while it stays
        inside, so long displacements near the edges are lost more often
        than short ones and the measured MSD is biased low by about
        ``1.6 s / L`` per limited axis (s the step standard deviation, L the
        extent: -3.4 % for 4 px steps in a 192 px field). With the field
        given, every displacement is weighted by the inverse probability
        that a segment of its extent fits in the field (uniformly spread
        particles), which removes the bias. ``"auto"`` takes the range of the
        positions in x and y (the image); names such as ``("x", "y", "z")``
        take the range of those components. None: no correction
        (simulations without a field).

    Returns
    -------
    DiffusionResult

    Examples
    --------
    Free particles seen through a 30 µm camera field (their tracks cut by its
    edges), D = 1 µm²/s, 20 nm localisation error, no motion blur:

    >>> from ptrack.motion import brownian_field
    >>> df = brownian_field(n_frames=50, size=30e-6, density=0.06e12, D=1e-12, dt=0.1, sigma=20e-9, seed=0)
    >>> res = estimate_diffusion(df, axes="x,y,xy", motion_blur=0.0, field_of_view="auto")
    >>> res.se_method, abs(res.D["xy"] - 1e-12) < 3 * res.D_err["xy"]
    ('bootstrap', True)
    >>> res.table().columns.tolist()                # the seed's Table 4.1 layout, m^2/s
    ['D_x', 'D_x_err', 'D_y', 'D_y_err', 'D_xy', 'D_xy_err']
    """
    axes = parse_axes(axes)
    estimator = str(estimator).lower()
    if estimator not in ("cve", "ols"):
        raise UserError(f"unknown estimator '{estimator}'", "choose 'cve' or 'ols'")
    R = check_motion_blur(motion_blur)
    n_boot = int(n_boot)
    if n_boot < 0:
        raise UserError(f"n_boot = {n_boot} is negative", "give 0 or a positive number of resamples")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    comps = axis_components(axes)
    fov = resolve_fov(df, field_of_view)
    tr = prepare_tracks(df, tuple(dict.fromkeys(comps + tuple(fov))), min_rows=3)
    fv, fl = fov_arrays(tr, fov)               # positions in the field: before any drift correction
    if subtract_drift:
        tr = drift_corrected(tr, comps)
    dt = tr.dt
    n_p = len(tr.particles)
    L = default_max_lag(tr, max_lag)
    cs = cve_sums_ragged(tr.stack(comps), tr.off, fv, fl)            # (n_p, k, 4)
    if np.any(cs[:, :, 3].sum(axis=0) == 0):
        raise UserError("no track has three consecutive frames", "give tracks with at least 3 consecutive positions")
    use_boot = n_boot > 0 and n_p >= MIN_PARTICLES_BOOTSTRAP
    W = boot_weights(n_p, n_boot, rng) if n_boot > 0 and n_p >= 2 else None
    comp = component_cve(cs, comps, dt, R)     # per component: sigma, eps and the CVE itself
    sums = msd_sums(tr, axes, L, (fv, fl))
    n_disp = np.maximum(np.diff(tr.off) - 1, 1)
    res = dict(D={}, D_err={}, D_err_model={}, D_err_boot={}, sigma_loc={}, n_lags={}, fit={})
    for a in axes:
        names = AXES[a]
        if estimator == "cve":
            e = cve_axis(cs, comp, [comps.index(c) for c in names], names, dt, R, W)
        else:
            e = ols_axis(*sums[a], n_disp, len(names), dt, R, W, a)
        for key in ("D", "D_err_model", "D_err_boot", "sigma_loc", "n_lags", "fit"):
            res[key][a] = e[key]
        res["D_err"][a] = e["D_err_boot"] if use_boot and np.isfinite(e["D_err_boot"]) else e["D_err_model"]
    return DiffusionResult(n_particles=n_p, n_displacements=int(cs[:, 0, 1].sum()), estimator=estimator,
                           frame_interval=dt, motion_blur=R, se_method="bootstrap" if use_boot else "model",
                           drift_corrected=bool(subtract_drift), msd=ensemble_from_sums(sums, axes, dt, L), **res)

