"""Hindered diffusion of a sphere near a plane wall.

One implementation for two users: the analysis corrects a measured diffusion
coefficient for the particle's height (or infers the height from the measured
reduction, as the seed does with its eq. 4.1), and the simulator calls the
same numba kernels inside its Brownian-dynamics loop for the height-dependent
mobility and the ``kB T dM/dz`` drift term.

Throughout, ``h`` is the height of the particle CENTRE above the wall (m) and
``a`` the particle radius (m); the gap between sphere surface and wall is
``h - a``. The kernels take the dimensionless ``x = h / a > 1``. All ratios
are mobility (= diffusion-coefficient) ratios ``D/D0`` with ``D0`` the bulk
Stokes-Einstein value.

Parallel to the wall (``D_par/D0``)
    * ``first_order``: ``1 - 9/16 (a/h)`` (the seed's eq. 4.1, Faxen's series
      truncated after its first term).
    * ``faxen``: Faxen's series to ``(a/h)^5``:
      ``1 - 9/16 a/h + 1/8 (a/h)^3 - 45/256 (a/h)^4 - 1/16 (a/h)^5``.
      Within 1 % of the exact result for ``h/a > 1.56``; at contact it tends
      to 0.324 instead of 0.
    * ``lubrication``: Goldman, Cox & Brenner (1967) near-contact asymptotes
      of the four resistance functions of a sphere translating and rotating
      next to the wall, combined into the mobility of a torque-free (freely
      rotating) sphere, which is what Brownian motion samples:
      ``D/D0 = -T_r / (F_t T_r - F_r T_t)`` with, for ``L = ln((h-a)/a)``,
      ``F_t = 8/15 L - 0.9588``, ``F_r = -2/15 L - 0.2526``,
      ``T_t = -1/10 L - 0.1895``, ``T_r = 2/5 L - 0.3817``.
      Valid for gaps below a few per cent of ``a``.
    * ``auto`` (recommended): the lubrication form near contact and Faxen's
      series further out, joined by a C1 smoothstep weight in ``ln(gap/a)``
      between gap/a = 0.02 and 0.7. The result is continuous, has a
      continuous derivative, increases monotonically with ``h`` and goes
      from 0 at contact to 1 far away. Against the exact bispherical
      solution (O'Neill 1964; Goldman, Cox & Brenner 1967 tables) it is
      within 0.9 % at every tabulated height (``bench/bench_wall.py``
      prints the table); the switch interval is where neither asymptote
      alone is good (Faxen is 4 % low at h/a = 1.1, GCB 3 % high).

Perpendicular to the wall (``D_perp/D0``)
    * ``brenner``: Brenner's (1961) exact series in bispherical coordinates,
      summed until the terms are below 1e-17 of the sum; for gaps below
      1e-4 a the Cox & Brenner (1967) near-contact expansion
      ``lambda = a/g + 1/5 ln(a/g) + 0.971264`` is used (relative
      difference to the series at the switch ~1e-8).
    * ``bevan_prieve``: Bevan & Prieve's (2000) closed form in the gap
      ``g = h - a``: ``(6 g^2 + 2 a g) / (6 g^2 + 9 a g + 2 a^2)``, within
      0.71 % of Brenner's series everywhere (largest at h/a = 1.058); the
      cheapest form (~2 ns per call).

Numba kernels (scalar, ``@njit(cache=True)``, argument ``x = h/a``):

* ``parallel_ratio_nb``, ``parallel_ratio_derivative_nb`` (d/dx),
  ``parallel_ratio_and_derivative_nb`` (both in one call): the recommended
  parallel form, ~15 ns per call.
* ``perpendicular_ratio_nb``, ``perpendicular_ratio_derivative_nb``,
  ``perpendicular_ratio_and_derivative_nb``: Brenner's series through a
  precomputed cubic-Hermite table in ln(gap/a) (built at import, ~0.06 s);
  relative difference to the directly summed series < 1e-11 for the ratio
  and < 2e-8 for the derivative, ~20 ns per call instead of 1-20 us.
* ``perpendicular_ratio_series_nb`` / ``..._series_derivative_nb``: the
  series summed directly; ``perpendicular_ratio_bp_nb`` /
  ``perpendicular_ratio_bp_derivative_nb``: Bevan-Prieve;
  ``faxen_ratio_nb``, ``lubrication_ratio_nb``.

A derivative with respect to ``h`` is the ``d/dx`` value divided by ``a``.
For ``x <= 1`` (overlap with the wall, which a DEM contact model allows) the
kernels return 0 for the ratio and 0 for the derivative: the caller should
clamp the gap to a physical minimum (surface roughness, a few nm) first.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..errors import UserError

__all__ = [
    "parallel_ratio",
    "perpendicular_ratio",
    "parallel_ratio_derivative",
    "perpendicular_ratio_derivative",
    "height_from_ratio",
    "hindered_D",
    "unhindered_D",
    "parallel_ratio_nb",
    "parallel_ratio_derivative_nb",
    "perpendicular_ratio_nb",
    "perpendicular_ratio_derivative_nb",
    "perpendicular_ratio_and_derivative_nb",
    "parallel_ratio_and_derivative_nb",
    "perpendicular_ratio_series_nb",
    "perpendicular_ratio_series_derivative_nb",
    "perpendicular_ratio_bp_nb",
    "perpendicular_ratio_bp_derivative_nb",
    "faxen_ratio_nb",
    "lubrication_ratio_nb",
    "PARALLEL_METHODS",
    "PERPENDICULAR_METHODS",
    "wall_evidence",
    "WALL_EVIDENCE_DCHI2",
    "WALL_FIT_P",
]

PARALLEL_METHODS = ("auto", "faxen", "first_order", "lubrication")
PERPENDICULAR_METHODS = ("brenner", "brenner_table", "bevan_prieve")

# Blend window of the recommended parallel mobility, in gap/a (see module docstring).
BLEND_GAP_LOW = 0.02
BLEND_GAP_HIGH = 0.7
# Below this gap/a Brenner's series is replaced by the Cox-Brenner expansion.
BRENNER_ASYMPTOTE_GAP = 1e-4
# Goldman, Cox & Brenner (1967) near-contact constants (their eqs. 2.65, 3.13).
_GCB_FT = (8.0 / 15.0, -0.9588)
_GCB_FR = (-2.0 / 15.0, -0.2526)
_GCB_TT = (-0.1, -0.1895)
_GCB_TR = (0.4, -0.3817)
# Cox & Brenner (1967) constant of the perpendicular near-contact expansion.
_COX_BRENNER_C = 0.971264


# --------------------------------------------------------------------------
# numba kernels (x = h/a)
# --------------------------------------------------------------------------
@njit(cache=True)
def faxen_ratio_nb(x):
    """Faxen's parallel series ``D_par/D0`` to (a/h)^5; ``x = h/a``."""
    if x <= 1.0:
        return 0.0
    xi = 1.0 / x
    xi3 = xi * xi * xi
    return 1.0 - 0.5625 * xi + 0.125 * xi3 - 0.17578125 * xi3 * xi - 0.0625 * xi3 * xi * xi


@njit(cache=True)
def faxen_ratio_derivative_nb(x):
    """d(Faxen ratio)/dx, ``x = h/a``."""
    if x <= 1.0:
        return 0.0
    xi = 1.0 / x
    dxi = -0.5625 + 0.375 * xi * xi - 0.703125 * xi ** 3 - 0.3125 * xi ** 4
    return -dxi * xi * xi


@njit(cache=True)
def _lubrication_parts(x):
    # returns ratio and d ratio / dx of the GCB torque-free parallel mobility
    g = x - 1.0
    L = math.log(g)
    ft = _GCB_FT[0] * L + _GCB_FT[1]
    fr = _GCB_FR[0] * L + _GCB_FR[1]
    tt = _GCB_TT[0] * L + _GCB_TT[1]
    tr = _GCB_TR[0] * L + _GCB_TR[1]
    num = -tr
    den = ft * tr - fr * tt
    dnum = -_GCB_TR[0]
    dden = _GCB_FT[0] * tr + ft * _GCB_TR[0] - _GCB_FR[0] * tt - fr * _GCB_TT[0]
    r = num / den
    dr_dL = (dnum * den - num * dden) / (den * den)
    return r, dr_dL / g


@njit(cache=True)
def lubrication_ratio_nb(x):
    """Goldman-Cox-Brenner near-contact parallel ratio (torque-free sphere); ``x = h/a``."""
    if x <= 1.0:
        return 0.0
    return _lubrication_parts(x)[0]


@njit(cache=True)
def lubrication_ratio_derivative_nb(x):
    """d(lubrication ratio)/dx, ``x = h/a``."""
    if x <= 1.0:
        return 0.0
    return _lubrication_parts(x)[1]


@njit(cache=True)
def parallel_ratio_and_derivative_nb(x):
    """Recommended ``D_par/D0`` and its derivative d/dx at ``x = h/a`` (one call, both)."""
    if x <= 1.0:
        return 0.0, 0.0
    g = x - 1.0
    if g >= BLEND_GAP_HIGH:
        return faxen_ratio_nb(x), faxen_ratio_derivative_nb(x)
    if g <= BLEND_GAP_LOW:
        return _lubrication_parts(x)
    s0 = math.log(BLEND_GAP_LOW)
    span = math.log(BLEND_GAP_HIGH) - s0
    t = (math.log(g) - s0) / span
    w = 1.0 - t * t * (3.0 - 2.0 * t)          # weight of the lubrication form
    dw_dx = -6.0 * t * (1.0 - t) / span / g
    rl, dl = _lubrication_parts(x)
    rf = faxen_ratio_nb(x)
    df = faxen_ratio_derivative_nb(x)
    return w * rl + (1.0 - w) * rf, w * dl + (1.0 - w) * df + dw_dx * (rl - rf)


@njit(cache=True)
def parallel_ratio_nb(x):
    """Recommended parallel mobility ratio ``D_par/D0`` at ``x = h/a`` (0 for x <= 1)."""
    return parallel_ratio_and_derivative_nb(x)[0]


@njit(cache=True)
def parallel_ratio_derivative_nb(x):
    """d(D_par/D0)/dx at ``x = h/a`` for the recommended form (divide by a for d/dh)."""
    return parallel_ratio_and_derivative_nb(x)[1]


@njit(cache=True)
def _brenner_lambda(x):
    # Brenner's (1961) correction factor lambda = D0/D_perp and d lambda/dx.
    g = x - 1.0
    if g < BRENNER_ASYMPTOTE_GAP:
        lam = 1.0 / g + 0.2 * math.log(1.0 / g) + _COX_BRENNER_C
        return lam, -1.0 / (g * g) - 0.2 / g
    return _brenner_series(x)


@njit(cache=True)
def _brenner_series(x):
    # the series itself (any x > 1; slow for x -> 1)
    g = x - 1.0
    s = math.sqrt(g * (x + 1.0))            # sinh(alpha), exact near contact
    c = x                                    # cosh(alpha)
    alpha = math.log1p(g + s)                # acosh(x) without cancellation
    s2a = 2.0 * s * c                        # sinh(2 alpha)
    c2a = 2.0 * c * c - 1.0                  # cosh(2 alpha)
    ss = s * s
    total = 0.0
    dtotal = 0.0
    for n in range(1, 1000000):
        m = 2.0 * n + 1.0
        A = m * alpha
        k = n * (n + 1.0) / ((2.0 * n - 1.0) * (2.0 * n + 3.0))
        ea = math.exp(-A)
        # bracket of Brenner's series written as M/D - with
        # M = N - D = 2 - 2 e^-A + m sinh 2a + m^2 sinh^2 a (no cancellation)
        M = -2.0 * math.expm1(-A) + m * s2a + m * m * ss
        Mp = 2.0 * m * ea + 2.0 * m * c2a + m * m * s2a        # dM/dalpha
        if A < 30.0:
            sh = math.sinh(0.5 * A)
            D = 4.0 * sh * sh - m * m * ss
            Dp = 2.0 * m * math.sinh(A) - m * m * s2a           # dD/dalpha
            B = M / D
            Bp = (Mp * D - M * Dp) / (D * D)
        else:                                                   # scaled by e^-A
            Ds = 1.0 - 2.0 * ea + ea * ea - m * m * ss * ea
            Dps = m * (1.0 - ea * ea) - m * m * s2a * ea
            B = M * ea / Ds
            Bp = ea * (Mp / Ds - M * Dps / (Ds * Ds))
        term = k * B
        dterm = k * Bp
        total += term
        dtotal += dterm
        if n > 2 and abs(term) <= 1e-17 * abs(total) and abs(dterm) <= 1e-17 * abs(dtotal):
            break
    lam = 4.0 / 3.0 * s * total
    dlam_dalpha = 4.0 / 3.0 * (c * total + s * dtotal)
    return lam, dlam_dalpha / s


@njit(cache=True)
def perpendicular_ratio_series_and_derivative_nb(x):
    """Brenner's exact ``D_perp/D0`` and d/dx at ``x = h/a`` summed directly (0, 0 for x <= 1).

    Costs ~1 us per call for gaps above 0.1 a and up to ~20-50 us near contact;
    :func:`perpendicular_ratio_and_derivative_nb` gives the same to 1e-11 in ~20 ns.
    """
    if x <= 1.0:
        return 0.0, 0.0
    lam, dlam = _brenner_lambda(x)
    return 1.0 / lam, -dlam / (lam * lam)


@njit(cache=True)
def perpendicular_ratio_series_nb(x):
    """Brenner's exact perpendicular ratio ``D_perp/D0`` at ``x = h/a`` (direct series)."""
    return perpendicular_ratio_series_and_derivative_nb(x)[0]


@njit(cache=True)
def perpendicular_ratio_series_derivative_nb(x):
    """d(D_perp/D0)/dx of Brenner's series at ``x = h/a`` (direct series)."""
    return perpendicular_ratio_series_and_derivative_nb(x)[1]


@njit(cache=True)
def perpendicular_ratio_bp_nb(x):
    """Bevan & Prieve (2000) closed form of ``D_perp/D0`` at ``x = h/a`` (gap g = x - 1)."""
    if x <= 1.0:
        return 0.0
    g = x - 1.0
    return (6.0 * g * g + 2.0 * g) / (6.0 * g * g + 9.0 * g + 2.0)


@njit(cache=True)
def perpendicular_ratio_bp_derivative_nb(x):
    """d/dx of the Bevan-Prieve perpendicular ratio at ``x = h/a``."""
    if x <= 1.0:
        return 0.0
    g = x - 1.0
    num = 6.0 * g * g + 2.0 * g
    den = 6.0 * g * g + 9.0 * g + 2.0
    return ((12.0 * g + 2.0) * den - num * (12.0 * g + 9.0)) / (den * den)


# --------------------------------------------------------------------------
# Brenner's series as a table: the fast exact-to-1e-10 form for hot loops
# --------------------------------------------------------------------------
# Near contact the series needs ~40/alpha terms (16-44 us per call at
# gap/a = 1e-3), too slow for a Brownian-dynamics step. The smooth factor
# c(u) = D_perp(Brenner) / D_perp(Bevan-Prieve), u = ln(gap/a), lies within
# 0.71 % of 1 for all gaps; it is tabulated once (at import, ~0.06 s) with its
# exact derivative on a uniform grid in u over gap/a = 1e-4 .. 1e4 and
# interpolated by cubic Hermite polynomials. Below gap/a = 1e-4 the same
# Cox-Brenner expansion as the series is used, above 1e4 the far-field
# expansion 1 - 9/8 xi + 1/2 xi^3 - 135/256 xi^4 (error < 1e-20).
# bench/bench_wall.py measures the error against the series.
_TABLE_U0 = math.log(BRENNER_ASYMPTOTE_GAP)
_TABLE_U1 = math.log(1e4)
_TABLE_DU = 0.005


@njit(cache=True)
def _build_brenner_table(u0, du, n):
    c = np.empty(n)
    dc = np.empty(n)
    for i in range(n):
        g = math.exp(u0 + i * du)
        x = 1.0 + g
        lam, dlam = _brenner_series(x)
        rb = 1.0 / lam
        drb = -dlam / (lam * lam)
        bp = perpendicular_ratio_bp_nb(x)
        dbp = perpendicular_ratio_bp_derivative_nb(x)
        c[i] = rb / bp
        dc[i] = g * (drb * bp - rb * dbp) / (bp * bp)      # dc/du
    return c, dc


_TABLE_N = int(round((_TABLE_U1 - _TABLE_U0) / _TABLE_DU)) + 1
_TABLE_C, _TABLE_DC = _build_brenner_table(_TABLE_U0, _TABLE_DU, _TABLE_N)


@njit(cache=True)
def perpendicular_ratio_fast_and_derivative_nb(x):
    """Brenner's ``D_perp/D0`` and d/dx from the precomputed table (rel. error < 1e-11; ~20 ns).

    ``x = h/a``; returns ``(0, 0)`` for ``x <= 1``.
    """
    if x <= 1.0:
        return 0.0, 0.0
    g = x - 1.0
    if g < BRENNER_ASYMPTOTE_GAP:
        lam = 1.0 / g + 0.2 * math.log(1.0 / g) + _COX_BRENNER_C
        dlam = -1.0 / (g * g) - 0.2 / g
        return 1.0 / lam, -dlam / (lam * lam)
    u = math.log(g)
    if u >= _TABLE_U1:
        xi = 1.0 / x
        r = 1.0 - xi * (1.125 - xi * xi * (0.5 - 0.52734375 * xi))
        dr_dxi = -1.125 + 1.5 * xi * xi - 2.109375 * xi ** 3
        return r, -dr_dxi * xi * xi
    s = (u - _TABLE_U0) / _TABLE_DU
    i = int(s)
    if i >= _TABLE_N - 1:
        i = _TABLE_N - 2
    t = s - i
    c0 = _TABLE_C[i]
    c1 = _TABLE_C[i + 1]
    m0 = _TABLE_DC[i] * _TABLE_DU
    m1 = _TABLE_DC[i + 1] * _TABLE_DU
    t2 = t * t
    t3 = t2 * t
    c = (2 * t3 - 3 * t2 + 1) * c0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * c1 + (t3 - t2) * m1
    dc_dt = (6 * t2 - 6 * t) * c0 + (3 * t2 - 4 * t + 1) * m0 + (-6 * t2 + 6 * t) * c1 + (3 * t2 - 2 * t) * m1
    dc_dx = dc_dt / _TABLE_DU / g
    bp = perpendicular_ratio_bp_nb(x)
    dbp = perpendicular_ratio_bp_derivative_nb(x)
    return bp * c, dbp * c + bp * dc_dx


@njit(cache=True)
def perpendicular_ratio_fast_nb(x):
    """Brenner's ``D_perp/D0`` at ``x = h/a`` from the table (fast form of the series)."""
    return perpendicular_ratio_fast_and_derivative_nb(x)[0]


@njit(cache=True)
def perpendicular_ratio_fast_derivative_nb(x):
    """d(D_perp/D0)/dx at ``x = h/a`` from the table (divide by a for d/dh)."""
    return perpendicular_ratio_fast_and_derivative_nb(x)[1]


# The kernels the simulator calls: Brenner's series through the table (same
# values as the series to < 1e-9, ~1000x faster near contact).
perpendicular_ratio_and_derivative_nb = perpendicular_ratio_fast_and_derivative_nb
perpendicular_ratio_nb = perpendicular_ratio_fast_nb
perpendicular_ratio_derivative_nb = perpendicular_ratio_fast_derivative_nb


# method codes used by the array loops
_CODES = {
    ("parallel", "auto"): 0,
    ("parallel", "faxen"): 1,
    ("parallel", "first_order"): 2,
    ("parallel", "lubrication"): 3,
    ("perpendicular", "brenner"): 10,
    ("perpendicular", "bevan_prieve"): 11,
    ("perpendicular", "brenner_table"): 12,
}


@njit(cache=True)
def _ratio_code(x, code):
    if code == 0:
        return parallel_ratio_nb(x)
    if code == 1:
        return faxen_ratio_nb(x)
    if code == 2:
        return 1.0 - 0.5625 / x
    if code == 3:
        return lubrication_ratio_nb(x)
    if code == 10:
        return perpendicular_ratio_series_nb(x)
    if code == 12:
        return perpendicular_ratio_fast_nb(x)
    return perpendicular_ratio_bp_nb(x)


@njit(cache=True)
def _derivative_code(x, code):
    if code == 0:
        return parallel_ratio_derivative_nb(x)
    if code == 1:
        return faxen_ratio_derivative_nb(x)
    if code == 2:
        return 0.5625 / (x * x)
    if code == 3:
        return lubrication_ratio_derivative_nb(x)
    if code == 10:
        return perpendicular_ratio_series_derivative_nb(x)
    if code == 12:
        return perpendicular_ratio_fast_derivative_nb(x)
    return perpendicular_ratio_bp_derivative_nb(x)


@njit(cache=True)
def _map_ratio(x, code, out):
    for i in range(x.size):
        out[i] = _ratio_code(x[i], code)


@njit(cache=True)
def _map_derivative(x, code, out):
    for i in range(x.size):
        out[i] = _derivative_code(x[i], code)


@njit(cache=True)
def _invert(r, code, log_gap_lo, log_gap_hi, out):
    # bisection in u = ln(gap/a); every method is monotone on [lo, hi]
    for i in range(r.size):
        lo = log_gap_lo
        hi = log_gap_hi
        target = r[i]
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if _ratio_code(1.0 + math.exp(mid), code) < target:
                lo = mid
            else:
                hi = mid
            if hi - lo <= 1e-15 * max(1.0, abs(mid)):
                break
        out[i] = 1.0 + math.exp(0.5 * (lo + hi))


# --------------------------------------------------------------------------
# numpy-facing API
# --------------------------------------------------------------------------
def _code(direction: str, method: str | None) -> int:
    if direction not in ("parallel", "perpendicular"):
        raise UserError(f"direction = {direction!r} is not known", "use 'parallel' or 'perpendicular'")
    if method is None:
        method = "auto" if direction == "parallel" else "brenner"
    if method == "recommended":
        method = "auto" if direction == "parallel" else "brenner"
    key = (direction, method)
    if key not in _CODES:
        allowed = PARALLEL_METHODS if direction == "parallel" else PERPENDICULAR_METHODS
        raise UserError(f"method = {method!r} is not known for the {direction} direction",
                        f"use one of {', '.join(allowed)}")
    return _CODES[key]


def _as_float_array(name, value):
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{name} = {value!r} is not numeric", f"give {name} as a number or array in SI units")
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{name} contains non-finite values", f"give finite {name} values")
    return arr


def _reduced_height(h, a):
    """Validate h (centre height, m) and a (radius, m); return x = h/a as float64 array."""
    h = _as_float_array("height h", h)
    a = _as_float_array("radius a", a)
    try:
        hb, ab = np.broadcast_arrays(h, a)
    except ValueError:
        raise UserError(f"height h (shape {h.shape}) and radius a (shape {a.shape}) do not broadcast",
                        "give one radius or one per height")
    if np.any(ab <= 0):
        raise UserError(f"radius a = {float(ab.min())!r} m must be positive", "give the particle radius in m")
    x = hb / ab
    if np.any(x <= 1.0):
        i = int(np.argmin(x.ravel()))
        raise UserError(
            f"height h = {float(hb.ravel()[i])!r} m is not above the particle radius a = {float(ab.ravel()[i])!r} m: "
            "h is the CENTRE height, so h > a is required",
            "give the distance from the wall to the particle centre (gap + radius)",
        )
    return x


def _check_broadcast(name, arr, ratio):
    try:
        np.broadcast_shapes(np.shape(arr), np.shape(ratio))
    except ValueError:
        raise UserError(f"{name} (shape {np.shape(arr)}) does not broadcast against the heights "
                        f"(shape {np.shape(ratio)})", f"give one {name} or one per height")


def _apply(kernel, x, code):
    flat = np.ascontiguousarray(x, dtype=np.float64).ravel()
    out = np.empty_like(flat)
    kernel(flat, code, out)
    out = out.reshape(np.shape(x))
    return out if out.ndim else float(out)


def parallel_ratio(h, a, method: str = "auto"):
    """Parallel diffusion (mobility) ratio ``D_par/D0`` of a sphere near a plane wall.

    Parameters
    ----------
    h : float or array_like
        Height of the particle CENTRE above the wall, m (must exceed ``a``).
    a : float or array_like
        Particle radius, m (broadcast against ``h``).
    method : {"auto", "faxen", "first_order", "lubrication"}
        ``auto`` (recommended): Goldman-Cox-Brenner lubrication near contact
        blended into Faxen's series (within 0.9 % of the exact solution);
        ``faxen``: Faxen's series to (a/h)^5; ``first_order``: the seed's
        eq. 4.1, ``1 - 9/16 a/h``; ``lubrication``: the GCB near-contact form
        alone (for gaps below ~0.02 a).

    Returns
    -------
    float or ndarray
        ``D_par/D0`` (dimensionless), same shape as the broadcast inputs.
    """
    return _apply(_map_ratio, _reduced_height(h, a), _code("parallel", method))


def perpendicular_ratio(h, a, method: str = "brenner"):
    """Perpendicular diffusion (mobility) ratio ``D_perp/D0`` of a sphere near a plane wall.

    Parameters
    ----------
    h : float or array_like
        Height of the particle CENTRE above the wall, m (must exceed ``a``).
    a : float or array_like
        Particle radius, m.
    method : {"brenner", "brenner_table", "bevan_prieve"}
        ``brenner``: Brenner's (1961) exact series summed directly;
        ``brenner_table``: the same through the interpolation table the numba
        kernels use (relative difference < 1e-11); ``bevan_prieve``: the
        closed form of Bevan & Prieve (2000) in the gap ``h - a`` (within
        0.7 % of Brenner).

    Returns
    -------
    float or ndarray
        ``D_perp/D0`` (dimensionless).
    """
    return _apply(_map_ratio, _reduced_height(h, a), _code("perpendicular", method))


def parallel_ratio_derivative(h, a, method: str = "auto"):
    """d(D_par/D0)/dh in 1/m (h = centre height, a = radius, both m)."""
    x = _reduced_height(h, a)
    return _apply(_map_derivative, x, _code("parallel", method)) / np.asarray(a, dtype=np.float64)


def perpendicular_ratio_derivative(h, a, method: str = "brenner"):
    """d(D_perp/D0)/dh in 1/m (h = centre height, a = radius, both m).

    ``kB T d(D_perp/D0)/dh / (6 pi mu a)`` is the spurious-drift velocity
    that Brownian dynamics with a height-dependent mobility must add.
    """
    x = _reduced_height(h, a)
    return _apply(_map_derivative, x, _code("perpendicular", method)) / np.asarray(a, dtype=np.float64)


def hindered_D(D0, h, a, direction: str = "parallel", method: str | None = None):
    """Diffusion coefficient near a wall, ``D0 * ratio(h/a)``, m^2/s.

    Parameters
    ----------
    D0 : float or array_like
        Bulk (Stokes-Einstein) diffusion coefficient, m^2/s.
    h : float or array_like
        Centre height above the wall, m.
    a : float or array_like
        Particle radius, m.
    direction : {"parallel", "perpendicular"}
    method : str, optional
        As in :func:`parallel_ratio` / :func:`perpendicular_ratio`; default
        the recommended one (``auto`` / ``brenner``).
    """
    D0 = _as_float_array("D0", D0)
    if np.any(D0 < 0):
        raise UserError("D0 must be non-negative", "give D0 in m^2/s")
    code = _code(direction, method)
    ratio = _apply(_map_ratio, _reduced_height(h, a), code)
    _check_broadcast("D0", D0, ratio)
    out = D0 * ratio
    return out if np.ndim(out) else float(out)


def height_from_ratio(ratio, a, direction: str = "parallel", method: str | None = None):
    """Centre height ``h`` (m) at which the wall reduces ``D/D0`` to ``ratio``.

    Parameters
    ----------
    ratio : float or array_like
        Measured ``D/D0``, strictly between 0 and 1.
    a : float or array_like
        Particle radius, m.
    direction : {"parallel", "perpendicular"}
    method : str, optional
        Model to invert (default: the recommended one). ``first_order`` is the
        seed's eq. 4.1 inverted in closed form, ``h = 9 a / (16 (1 - ratio))``,
        which only gives ``h > a`` for ratios above 7/16.

    Returns
    -------
    float or ndarray
        Height of the particle centre above the wall, m.

    Raises
    ------
    UserError
        Ratio outside (0, 1), or below what the chosen model can produce
        for any physical gap (e.g. Faxen's series never drops below 0.324).
    """
    r = _as_float_array("ratio D/D0", ratio)
    a_arr = _as_float_array("radius a", a)
    if np.any(a_arr <= 0):
        raise UserError("radius a must be positive", "give the particle radius in m")
    try:
        np.broadcast_shapes(r.shape, a_arr.shape)
    except ValueError:
        raise UserError(f"ratio (shape {r.shape}) and radius a (shape {a_arr.shape}) do not broadcast",
                        "give one radius or one per ratio")
    if np.any((r <= 0) | (r >= 1)):
        bad = float(np.ravel(r)[np.argmax(np.ravel((r <= 0) | (r >= 1)))])
        raise UserError(f"ratio D/D0 = {bad!r} is outside (0, 1)",
                        "a wall only slows diffusion: give 0 < D/D0 < 1 (D measured over D0 in bulk)")
    code = _code(direction, method)
    if code == 2:
        x = 0.5625 / (1.0 - r)
        if np.any(x <= 1.0):
            bad = float(np.ravel(r)[np.argmin(np.ravel(x))])
            raise UserError(
                f"ratio D/D0 = {bad!r} is below 7/16 = 0.4375, which eq. 4.1 (1 - 9/16 a/h) cannot reach for h > a",
                "use the full model (method='auto')",
            )
        h = x * a_arr
        return h if np.ndim(h) else float(h)
    log_lo = math.log(1e-15)
    log_hi = math.log(0.5) if code == 3 else math.log(1e15)
    r_lo = _ratio_code(1.0 + math.exp(log_lo), code)
    r_hi = _ratio_code(1.0 + math.exp(log_hi), code)
    if np.any(r < r_lo):
        name = {0: "the recommended parallel model", 1: "Faxen's series", 3: "the lubrication form",
                10: "Brenner's series", 11: "Bevan-Prieve"}[code]
        raise UserError(
            f"ratio D/D0 = {float(np.min(r))!r} is below {r_lo:.4g}, the smallest value {name} gives for a physical gap",
            "use method='auto' (parallel) or check D0 and the measured D" if code in (1, 3) else "check D0 and the measured D",
        )
    if np.any(r > r_hi):
        raise UserError(
            f"ratio D/D0 = {float(np.max(r))!r} is above {r_hi:.15g}, the largest the model gives in its range",
            "use method='auto' for gaps above 0.5 a" if code == 3 else "the wall effect is too small to measure a height",
        )
    flat = np.ascontiguousarray(r, dtype=np.float64).ravel()
    out = np.empty_like(flat)
    # Brenner's series is inverted through its table (same values to 1e-11,
    # 1000x faster near contact); the bracket ends were checked above.
    _invert(flat, 12 if code == 10 else code, log_lo, log_hi, out)
    h = out.reshape(r.shape) * a_arr
    return h if np.ndim(h) else float(h)


def unhindered_D(D, h, a, direction: str = "parallel", method: str | None = None):
    """Bulk diffusion coefficient from one measured at centre height ``h``: ``D / ratio(h/a)``, m^2/s.

    The inverse of :func:`hindered_D`: corrects a diffusion coefficient
    measured near the wall (e.g. D_x, D_y of particles at a known height) to
    the value far from it, for comparison with Stokes-Einstein.

    Parameters
    ----------
    D : float or array_like
        Measured diffusion coefficient, m^2/s.
    h : float or array_like
        Centre height above the wall, m.
    a : float or array_like
        Particle radius, m.
    direction, method : as in :func:`hindered_D`.
    """
    D = _as_float_array("D", D)
    code = _code(direction, method)
    ratio = _apply(_map_ratio, _reduced_height(h, a), code)
    _check_broadcast("D", D, ratio)
    out = D / ratio
    return out if np.ndim(out) else float(out)


# --------------------------------------------------------------------------
# does the data show a hydrodynamic wall?
# --------------------------------------------------------------------------
#: Delta chi^2 (no-wall model minus wall model, both with one free D0) at or above which the data are taken to
#: show a hydrodynamic wall: a likelihood ratio of exp(3) ~ 20 in favour of the wall
WALL_EVIDENCE_DCHI2 = 6.0
#: p-value of the wall model's chi^2 below which it does not explain the data even when it beats a flat D
WALL_FIT_P = 1e-3
#: smallest gap over the radius used for a measured height at or below contact (noisy z near the wall)
_MIN_GAP = 1e-3


def _point_cve(st, comps):
    """Per interior point of each track: the CVE estimate of D pooled over ``comps`` and the row it is at.

    ``q_n = mean_c[(d_{n-1}^2 + d_n^2) / (4 dt) + d_{n-1} d_n / dt]`` with ``d_n`` the step from row n to n+1;
    its expectation is D at any localisation noise and motion blur (Vestergaard et al. 2014).
    """
    P = len(st.particles)
    seg = np.repeat(np.arange(P), np.diff(st.off))
    step = (seg[1:] == seg[:-1]) & (np.diff(st.frames) == 1)
    q = np.zeros(len(seg) - 2) if len(seg) > 2 else np.zeros(0)
    for j in range(len(comps)):
        d = np.where(step, np.diff(st.vals[j]), np.nan)
        q += (d[:-1] ** 2 + d[1:] ** 2) / (4 * st.dt) + d[:-1] * d[1:] / st.dt
    q /= len(comps)
    return q, seg[1:-1], np.arange(1, len(seg) - 1)


def wall_evidence(df, radius: float, wall_z: float, n_bins: int | None = None, n_boot: int = 200, seed=0,
                  threshold: float = WALL_EVIDENCE_DCHI2) -> dict | None:
    """Does D parallel to the wall fall with height as a hydrodynamic wall at ``wall_z`` makes it (Brenner / Faxen)?

    The CVE estimate of D_par (x and y pooled) of every interior point of every
    track is binned by the point's height ``h = z - wall_z`` (quantile bins); each
    bin's D and its error (bootstrap over particles) are fitted by two models
    with one free parameter each: no wall (``D = D0``, flat) and a wall at
    ``wall_z`` (``D = D0 <parallel_ratio(h, a)>`` over the bin's points). The
    difference of their chi^2, ``delta_chi2 = chi2_flat - chi2_wall`` (twice
    the log-likelihood ratio), decides: ``"wall"`` at or above ``threshold``
    if the wall model also fits (chi^2 p-value >= :data:`WALL_FIT_P`; else
    ``"neither"``, e.g. particles stuck on the substrate), ``"no wall"`` at or
    below ``-threshold``, else ``"undecided"``.

    Only D parallel to the wall is used: D_z near a *reflecting* plane (a
    confined sample without hydrodynamic hindrance) also comes out low,
    because steps that would cross the plane are folded back, so D_z cannot
    tell a hydrodynamic wall from a confinement.

    Parameters
    ----------
    df : DataFrame
        Trajectories table with finite z (m).
    radius : float
        Particle radius a, m.
    wall_z : float
        z of the wall, m; points at or below contact are taken at a gap of
        1e-3 a.
    n_bins : int, optional
        Height bins (default: one per ~150 points, 4 to 12).
    n_boot : int
        Bootstrap resamples over particles for the bins' errors.
    seed : int or Generator
    threshold : float
        Delta chi^2 needed to decide (:data:`WALL_EVIDENCE_DCHI2`).

    Returns
    -------
    dict or None
        ``favours`` ("wall", "no wall", "undecided", "neither"),
        ``delta_chi2``, ``chi2_flat``, ``chi2_wall``, ``dof``, ``p_flat``,
        ``p_wall``, ``threshold``, ``D0_flat``,
        ``D0_flat_err``, ``D0_wall``, ``D0_wall_err`` (m^2/s), ``mean_ratio``
        (mean of ``parallel_ratio`` over all points: the D measured over the
        tracks is ``D0 * mean_ratio`` if the wall is there), ``bins`` (list of
        ``h_mean_m``, ``D``, ``D_err``, ``ratio``, ``n``), ``n_points``. None
        when the table has too few points (fewer than 3 bins of 20).

    Examples
    --------
    >>> import numpy as np, pandas as pd
    >>> rng = np.random.default_rng(0)
    >>> n, F, dt, D = 60, 200, 0.1, 1e-12
    >>> z = rng.uniform(0.5e-6, 5e-6, n)[None, :] * np.ones((F, 1))     # particles at fixed heights: D flat
    >>> xy = np.cumsum(rng.normal(0, np.sqrt(2 * D * dt), (2, F, n)), axis=1)
    >>> df = pd.DataFrame({"frame": np.repeat(np.arange(F), n), "t": np.repeat(np.arange(F) * dt, n),
    ...                    "particle": np.tile(np.arange(n), F), "x": xy[0].ravel(), "y": xy[1].ravel(), "z": z.ravel()})
    >>> wall_evidence(df, radius=0.25e-6, wall_z=0.0)["favours"]
    'no wall'
    """
    from .tracks import sort_tracks

    a = float(radius)
    st = sort_tracks(df, ("x", "y"))
    z = df["z"].to_numpy(dtype=float)[st.order]
    q, part, row = _point_cve(st, ("x", "y"))
    h = z[row] - float(wall_z)
    ok = np.isfinite(q) & np.isfinite(h)
    q, part, h = q[ok], part[ok], h[ok]
    nb = int(n_bins) if n_bins is not None else int(np.clip(len(q) // 150, 4, 12))
    if len(q) < 20 * max(nb, 3) or nb < 2:
        return None
    edges = np.quantile(h, np.linspace(0, 1, nb + 1))
    b = np.clip(np.searchsorted(edges, h, side="right") - 1, 0, nb - 1)
    ratio = parallel_ratio(np.maximum(h, a * (1 + _MIN_GAP)), a)
    P = len(st.particles)
    key = part * nb + b
    S = np.bincount(key, weights=q, minlength=P * nb).reshape(P, nb)
    N = np.bincount(key, minlength=P * nb).reshape(P, nb).astype(float)
    n_b = N.sum(axis=0)
    D_b = S.sum(axis=0) / n_b
    r_b = np.bincount(b, weights=ratio, minlength=nb) / n_b
    h_b = np.bincount(b, weights=h, minlength=nb) / n_b
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    W = rng.multinomial(P, np.full(P, 1 / P), size=max(int(n_boot), 20)).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        Db = (W @ S) / (W @ N)
    err = np.nanstd(Db, axis=0, ddof=1)
    good = np.isfinite(err) & (err > 0)
    if good.sum() < 3:
        return None
    w = 1 / err[good] ** 2
    Dg, rg = D_b[good], r_b[good]
    D_flat = float(np.sum(w * Dg) / np.sum(w))
    D_wall = float(np.sum(w * rg * Dg) / np.sum(w * rg * rg))
    chi_flat = float(np.sum(w * (Dg - D_flat) ** 2))
    chi_wall = float(np.sum(w * (Dg - D_wall * rg) ** 2))
    delta = chi_flat - chi_wall
    from scipy.stats import chi2 as _chi2

    dof = int(good.sum() - 1)
    p_wall, p_flat = float(_chi2.sf(chi_wall, dof)), float(_chi2.sf(chi_flat, dof))
    if delta >= threshold:
        # the better of two bad fits is no evidence: stuck (deposited) particles, D ~ 0 at the bottom, also make
        # the flat model worse than the wall, yet no wall ratio explains them
        favours = "wall" if p_wall >= WALL_FIT_P else "neither"
    else:
        favours = "no wall" if delta <= -threshold else "undecided"
    return {"favours": favours, "delta_chi2": delta, "chi2_flat": chi_flat, "chi2_wall": chi_wall,
            "dof": dof, "p_flat": p_flat, "p_wall": p_wall, "threshold": float(threshold), "wall_z_m": float(wall_z),
            "D0_flat": D_flat, "D0_flat_err": float(1 / np.sqrt(np.sum(w))),
            "D0_wall": D_wall, "D0_wall_err": float(1 / np.sqrt(np.sum(w * rg * rg))),
            "mean_ratio": float(np.mean(ratio)), "n_points": int(len(q)), "n_particles": int(P),
            "bins": [{"h_mean_m": float(h_b[i]), "D": float(D_b[i]), "D_err": float(err[i]), "ratio": float(r_b[i]),
                      "n": int(n_b[i])} for i in range(nb)],
            "test": "D_par per height bin (CVE per point, bootstrap errors over particles) fitted flat and as "
                    "D0 * parallel_ratio(h); delta_chi2 = chi2_flat - chi2_wall"}
