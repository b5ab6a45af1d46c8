"""Stokes-Einstein diffusion coefficient (the bulk reference for every measured D)."""
from __future__ import annotations

import numpy as np

from ..constants import BOLTZMANN
from ..errors import UserError


def stokes_einstein(radius, viscosity, temperature=293.15):
    """Stokes-Einstein diffusion coefficient ``kB T / (6 pi mu r)``.

    Parameters
    ----------
    radius : float or array_like
        Particle radius, m.
    viscosity : float or array_like
        Dynamic viscosity of the fluid, Pa s.
    temperature : float or array_like
        Absolute temperature, K (default 293.15 K, room temperature).

    Returns
    -------
    float or ndarray
        D, m^2/s (broadcast over the inputs).
    """
    r = np.asarray(radius, dtype=float)
    mu = np.asarray(viscosity, dtype=float)
    T = np.asarray(temperature, dtype=float)
    for name, v in (("radius", r), ("viscosity", mu), ("temperature", T)):
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise UserError(f"{name} = {v.tolist()!r} must be finite and positive", f"give {name} in SI units")
    d = BOLTZMANN * T / (6.0 * np.pi * mu * r)
    return float(d) if d.ndim == 0 else d



#: largest D (m^2/s) a colloid can have: 10x a small molecule in water (1e-9 m^2/s)
D_MAX_PLAUSIBLE = 1e-8


def implausible_D_note(D) -> str | None:
    """A warning when D (m^2/s) is far too large for a colloid, e.g. a pixel table read as metres; else None.

    Examples
    --------
    >>> implausible_D_note(4e-13) is None
    True
    >>> implausible_D_note(0.5).split(":")[0]
    'D = 0.5 m^2/s is not physical for a particle in a liquid (a small molecule in water has 1e-9)'
    """
    D = float(D)
    if np.isfinite(D) and D > D_MAX_PLAUSIBLE:
        return (f"D = {D:.3g} m^2/s is not physical for a particle in a liquid (a small molecule in water has 1e-9): "
                "are the positions in pixels or µm? The table's x, y, z must be in m (x = x_px * pixel size)")
    return None
