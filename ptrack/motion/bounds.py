"""Error models of the diffusion estimators: the CVE's closed-form variance and the Cramer-Rao bound on D."""
from __future__ import annotations

import numpy as np


def cve_variance(D, sigma2, dt, n, motion_blur=0.0):
    """Closed-form variance of the 1D CVE for one track of ``n`` displacements.

    Vestergaard et al. 2014, eq. (18)::

        var(D_hat) = D^2 [ (6 + 4 eps + 2 eps^2) / n + 4 (1 + eps)^2 / n^2 ],
        eps = sigma^2 / (D dt) - 2 R.

    Parameters
    ----------
    D : float or array_like
        Diffusion coefficient, m^2/s.
    sigma2 : float or array_like
        Localisation variance, m^2.
    dt : float
        Frame interval, s.
    n : int or array_like
        Number of displacements of the track.
    motion_blur : float
        R (1/6 full-frame exposure, 0 instantaneous).

    Returns
    -------
    ndarray or float
        Variance of D_hat, (m^2/s)^2.
    """
    D = np.asarray(D, dtype=float)
    n = np.asarray(n, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = np.asarray(sigma2, dtype=float) / (D * dt) - 2.0 * motion_blur
        v = D**2 * ((6 + 4 * eps + 2 * eps**2) / n + 4 * (1 + eps) ** 2 / n**2)
    return v


def _eps_eigen(n: int):
    k = np.arange(1, n + 1)
    return np.cos(k * np.pi / (n + 1))


def crlb_diffusion(D, sigma, dt, n, motion_blur=0.0, n_tracks=1, dims=1):
    """Cramer-Rao lower bound on the variance of an unbiased estimate of D.

    For Brownian motion observed with Gaussian localisation noise (standard
    deviation ``sigma``) and motion blur ``R``, the ``n`` displacements of a
    track are Gaussian with a tridiagonal Toeplitz covariance
    (Vestergaard et al. 2014): diagonal ``2 D dt (1 - 2R) + 2 sigma^2``,
    off-diagonal ``2 R D dt - sigma^2``. Its eigenvectors do not depend on the
    parameters, so the Fisher information of (D, sigma^2) is a sum over the
    eigenvalues ``l_k = c0 + 2 c1 cos(k pi / (n + 1))``:
    ``I_ij = 1/2 sum_k (d_i l_k)(d_j l_k) / l_k^2``. sigma^2 is treated as
    unknown (estimated jointly). Independent axes and tracks add information.

    Parameters
    ----------
    D : float
        m^2/s.
    sigma : float
        Localisation error (standard deviation), m.
    dt : float
        Frame interval, s.
    n : int
        Displacements per track.
    motion_blur : float
        R.
    n_tracks, dims : int
        Number of independent tracks and of axes pooled.

    Returns
    -------
    float
        Minimal variance of D_hat, (m^2/s)^2.
    """
    R = motion_blur
    c = _eps_eigen(int(n))
    s2 = sigma**2
    lam = 2 * D * dt * (1 - 2 * R) + 2 * s2 + 2 * (2 * R * D * dt - s2) * c
    dD = dt * (2 * (1 - 2 * R) + 4 * R * c)
    ds = 2 - 2 * c
    f = 0.5 * n_tracks * dims
    I = np.array([[np.sum(dD * dD / lam**2), np.sum(dD * ds / lam**2)],
                  [np.sum(dD * ds / lam**2), np.sum(ds * ds / lam**2)]]) * f
    return float(np.linalg.inv(I)[0, 0])

