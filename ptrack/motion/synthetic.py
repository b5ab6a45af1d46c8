"""Synthetic tracks with exactly known statistics, for tests, benchmarks and examples.

- :func:`brownian_tracks`: gap-free arrays of free Brownian motion with
  localisation noise and motion blur (exact in distribution).
- :func:`brownian_field`: what a camera sees of free particles in a square
  view (particles enter and leave it).
- :func:`drifting_tracks`: a trajectories table of drifting Brownian
  particles with noise, blur and gaps.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from ..errors import UserError
from .tracks import check_motion_blur


def brownian_tracks(n_particles: int, n_frames: int, D: float, dt: float, sigma: float = 0.0,
                    motion_blur: float = 0.0, n_dims: int = 1, seed=0) -> np.ndarray:
    """Observed positions of free Brownian particles with localisation noise and motion blur.

    Exact in distribution: the observed displacements of Brownian motion
    averaged over the exposure (blur R) plus independent Gaussian noise
    (standard deviation ``sigma``) form a Gaussian moving-average process of
    order 1 with variance ``2 D dt (1 - 2R) + 2 sigma^2`` and lag-1 covariance
    ``2 R D dt - sigma^2`` (Vestergaard et al. 2014); they are drawn as such.

    Parameters
    ----------
    n_particles, n_frames : int
    D : float
        m^2/s.
    dt : float
        Frame interval, s.
    sigma : float
        Localisation error, m.
    motion_blur : float
        R in [0, 1/4) (1/6: shutter open the whole frame; :func:`ptrack.motion.tracks.check_motion_blur`).
    n_dims : int
        Independent components.
    seed : int or Generator

    Returns
    -------
    ndarray
        ``(n_particles, n_frames)`` if ``n_dims == 1`` else
        ``(n_particles, n_frames, n_dims)``, m; tracks start near 0.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    R = check_motion_blur(motion_blur)
    c0 = 2 * D * dt * (1 - 2 * R) + 2 * sigma**2
    c1 = 2 * R * D * dt - sigma**2
    p_ = math.sqrt(max(c0 + 2 * c1, 0.0))
    m_ = math.sqrt(max(c0 - 2 * c1, 0.0))
    a, b = (p_ + m_) / 2, (p_ - m_) / 2
    z = rng.standard_normal((n_particles, n_frames, n_dims))
    d = a * z[:, 1:, :] + b * z[:, :-1, :]
    pos = np.empty((n_particles, n_frames, n_dims))
    # first observation: a (blurred) position plus its noise: offset b z_0 keeps the MA structure exact
    pos[:, 0, :] = b * z[:, 0, :]
    np.cumsum(d, axis=1, out=pos[:, 1:, :])
    pos[:, 1:, :] += pos[:, :1, :]
    return pos[:, :, 0] if n_dims == 1 else pos


def brownian_field(n_frames: int, size: float, density: float, D: float, dt: float, sigma: float = 0.0,
                   drift=(0.0, 0.0), seed=0) -> pd.DataFrame:
    """What a camera sees of free Brownian particles: a trajectories table of those inside a square view.

    Particles start uniformly over a periodic box wider than the view by six
    step lengths on each side (so the density in view stays uniform) and
    enter and leave the view as in a real experiment; a particle keeps its id
    when it comes back. Positions carry Gaussian localisation noise.

    Parameters
    ----------
    n_frames : int
    size : float
        Side of the view [0, size)^2, m.
    density : float
        Particles per m^2.
    D : float
        m^2/s.
    dt : float
        Frame interval, s.
    sigma : float
        Localisation error per axis, m (also written as ``sigma_x``, ``sigma_y``).
    drift : (vx, vy)
        m/s.
    seed : int or numpy.random.Generator

    Returns
    -------
    DataFrame
        Trajectories table (``frame``, ``t``, ``particle``, ``x``, ``y``, ``sigma_x``, ``sigma_y``).
    """
    from ..table import make_table

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    s = math.sqrt(2 * D * dt)
    margin = 6 * s
    Lb = size + 2 * margin
    X = rng.uniform(0, Lb, (rng.poisson(density * Lb * Lb), 2))
    fr, pa, xs, ys = [], [], [], []
    for f in range(n_frames):
        if f:
            X = np.mod(X + s * rng.standard_normal(X.shape) + np.asarray(drift, float) * dt, Lb)
        Y = X - margin
        ok = np.flatnonzero(np.all((Y >= 0) & (Y < size), axis=1))
        fr.append(np.full(ok.size, f))
        pa.append(ok)
        xs.append(Y[ok, 0] + sigma * rng.standard_normal(ok.size))
        ys.append(Y[ok, 1] + sigma * rng.standard_normal(ok.size))
    fr, pa = np.concatenate(fr), np.concatenate(pa)
    n = len(fr)
    return make_table(fr, fr * dt, pa, np.concatenate(xs), np.concatenate(ys), meta={"frame_interval": dt},
                      sigma_x=np.full(n, float(sigma)), sigma_y=np.full(n, float(sigma)))



def drifting_tracks(n_particles: int, n_frames: int, D: float, dt: float, v, sigma: float = 0.0,
                    motion_blur: float = 0.0, gap_fraction: float = 0.0, seed=0, meta: dict | None = None
                    ) -> pd.DataFrame:
    """Trajectories table of drifting Brownian particles with localisation noise, blur and gaps.

    Exact in distribution: per axis the observed positions are a drift ``v t``
    plus :func:`brownian_tracks` (moving-average increments with
    variance ``2 D dt (1 - 2R) + 2 sigma^2`` and lag-1 covariance
    ``2 R D dt - sigma^2``); then a fraction ``gap_fraction`` of the frames
    (never the first or last of a track) is removed at random.

    Parameters
    ----------
    n_particles, n_frames : int
    D : float
        m^2/s.
    dt : float
        Frame interval, s.
    v : float or array_like (3,)
        Drift velocity (vx, vy, vz), m/s; a scalar drifts along x only.
    sigma : float
        Localisation error, m.
    motion_blur : float
        R in [0, 1/4).
    gap_fraction : float
        Fraction of frames dropped, in [0, 1).
    seed : int or Generator
    meta : dict, optional
        Table metadata (``frame_interval`` is set).

    Returns
    -------
    DataFrame
        Trajectories table (3D: x, y, z).
    """
    from ..table import make_table

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    vv = np.zeros(3)
    if np.ndim(v) == 0:
        vv[0] = float(v)
    else:
        vv[:] = np.asarray(v, dtype=float)
    if not 0.0 <= gap_fraction < 1.0:
        raise UserError(f"gap_fraction = {gap_fraction!r} outside [0, 1)", "give a fraction of frames to drop")
    pos = brownian_tracks(n_particles, n_frames, D, dt, sigma=sigma, motion_blur=motion_blur, n_dims=3, seed=rng)
    t = np.arange(n_frames) * dt
    pos = pos + vv[None, None, :] * t[None, :, None]
    frame = np.tile(np.arange(n_frames), n_particles)
    particle = np.repeat(np.arange(n_particles), n_frames)
    keep = np.ones(n_particles * n_frames, bool)
    if gap_fraction > 0:
        drop = rng.random(n_particles * n_frames) < gap_fraction
        drop &= (frame > 0) & (frame < n_frames - 1)
        keep = ~drop
    m = dict(meta or {})
    m["frame_interval"] = dt
    flat = pos.reshape(-1, 3)
    return make_table(frame[keep], (frame * dt)[keep], particle[keep], flat[keep, 0], flat[keep, 1], flat[keep, 2],
                      meta=m)
