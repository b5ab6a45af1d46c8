"""Templates between calibration pages: coarse stage steps resolved far below the step.

A defocused image grows with defocus (the geometric blur: radius ~ |dz|
tan(asin(NA/n)); with a cylindrical lens, separately along x and y). Blending
two pages 2 um apart gives two rings, not one in between. So neighbouring
pages are first registered by an anisotropic scaling about the particle
centre (the (s_x, s_y) that best maps page k onto page k+1, by normalised
cross-correlation), and a template at fraction t of the step is the blend
(1 - t) A + t B of page k scaled by s^t and page k+1 scaled by s^(t-1)
(image morphing; flux conserved). For a pure change of scale (geometric
defocus, an astigmatic Gaussian) this is exact; near focus, where the
pages differ in shape, it falls back to a cross-fade of images alike in size.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["scale_about_centre", "register_scale", "interpolate_templates", "default_fine_step"]


def scale_about_centre(t, sx: float, sy: float, T_out: int) -> np.ndarray:
    """Template ``t`` (particle centre on its centre pixel) scaled by (sx, sy) about its centre, flux kept.

    Output is T_out x T_out (odd), centre on its centre pixel.
    """
    import cv2

    hi = (t.shape[0] // 2, t.shape[1] // 2)
    ho = T_out // 2
    M = np.float32([[sx, 0, ho - sx * hi[1]], [0, sy, ho - sy * hi[0]]])
    if sx < 1 or sy < 1:
        # shrinking: pre-blur so that bilinear sampling does not alias the fringes
        s = max(0.0, 0.5 * math.sqrt(max(1 / min(sx, sy) ** 2 - 1, 0.0)))
        if s > 0.3:
            t = cv2.GaussianBlur(np.ascontiguousarray(t, np.float32), (0, 0), s)
    out = cv2.warpAffine(np.ascontiguousarray(t, np.float32), M, (T_out, T_out), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out / np.float32(sx * sy)


def _ncc(a, b) -> float:
    a = a - a.mean()
    b = b - b.mean()
    d = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / d if d > 0 else -1.0


def _widths(t):
    """Second-moment widths (sigma_y, sigma_x, px) of the positive part of a centred template."""
    w = np.clip(t, 0, None).astype(np.float64)
    s = w.sum()
    if s <= 0:
        return 1.0, 1.0
    h = t.shape[0] // 2
    r = np.arange(t.shape[0]) - h
    sy = math.sqrt(max(float((w.sum(1) * r * r).sum() / s), 0.25))
    sx = math.sqrt(max(float((w.sum(0) * r * r).sum() / s), 0.25))
    return sy, sx


def register_scale(a, b, max_side: int = 64):
    """(sx, sy) such that ``a`` scaled by them about its centre best matches ``b`` (both centred templates).

    Started from the ratio of second-moment widths and refined by Nelder-Mead
    on the normalised cross-correlation, on copies reduced to ``max_side`` px
    (the scale of a large defocused image is set by its outline, not its
    finest fringe).
    """
    import cv2
    from scipy.optimize import minimize

    T = max(a.shape[0], b.shape[0])
    f = max(1, int(math.ceil(T / max_side)))
    if f > 1:
        def red(t):
            Tn = int(math.ceil(t.shape[0] / f)) | 1
            tt = scale_about_centre(t, 1.0, 1.0, Tn * f)
            return cv2.resize(tt, (Tn, Tn), interpolation=cv2.INTER_AREA)
        a, b = red(a), red(b)
    ya, xa = _widths(a)
    yb, xb = _widths(b)
    x0 = np.log([xb / xa, yb / ya])
    Tb = b.shape[0]

    def cost(p):
        return -_ncc(scale_about_centre(a, math.exp(p[0]), math.exp(p[1]), Tb), b)

    best = min((x0, np.zeros(2)), key=cost)
    res = minimize(cost, best, method="Nelder-Mead", options={"xatol": 2e-3, "fatol": 1e-5, "maxiter": 120})
    p = res.x if res.fun <= cost(best) else best
    return float(math.exp(p[0])), float(math.exp(p[1]))


def default_fine_step(z) -> float:
    """Spacing of the interpolated templates (m): the calibration step where it is 0.3 um or less, else the step
    divided into parts of at most 0.2 um (and at most 16 parts; at most ~400 templates in all)."""
    z = np.asarray(z, float)
    step = float(np.median(np.diff(z)))
    if step <= 0.3e-6:
        return step         # fine enough as recorded (the parabola through Cm(z) resolves a fraction of it)
    fine = min(step, 0.2e-6)
    depth = float(z[-1] - z[0])
    return max(fine, step / 16, depth / 400)


def interpolate_templates(templates, z, fine_step: float):
    """Centred templates on a z grid no coarser than ``fine_step`` from centred page templates.

    Parameters
    ----------
    templates : list of K 2D float32, particle centre on each one's centre pixel
    z : array (K,), increasing (m)
    fine_step : float (m)

    Returns
    -------
    templates : list of 2D float32 (centred)
    z : ndarray
    page : ndarray of int
        For each output template, the page it was made from (k for t < 0.5 of the step after page k, k + 1 above).
    scales : ndarray (K - 1, 2)
        (sx, sy) registered between neighbouring pages.
    """
    z = np.asarray(z, float)
    K = len(z)
    out, zz, src, scales = [], [], [], np.ones((max(K - 1, 0), 2))
    for k in range(K - 1):
        a, b = templates[k], templates[k + 1]
        n = max(1, int(math.ceil((z[k + 1] - z[k]) / fine_step - 1e-6)))
        if n > 1:
            sx, sy = register_scale(a, b)
            scales[k] = (sx, sy)
        for j in range(n):
            t = j / n
            if j == 0:
                out.append(a)
            else:
                T = int(round((1 - t) * a.shape[0] + t * b.shape[0])) | 1
                A = scale_about_centre(a, sx ** t, sy ** t, T)
                B = scale_about_centre(b, sx ** (t - 1), sy ** (t - 1), T)
                out.append(((1 - t) * A + t * B).astype(np.float32))
            zz.append(z[k] + t * (z[k + 1] - z[k]))
            src.append(k if t < 0.5 else k + 1)
    out.append(templates[-1])
    zz.append(z[-1])
    src.append(K - 1)
    return out, np.array(zz), np.array(src, int), scales
