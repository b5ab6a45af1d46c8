"""Electrokinetics of a charged colloid: Debye length, Henry's function, charge,
electrophoretic (Henry) velocity, Peclet and Reynolds numbers, the seed's
piecewise drag law and the steady-state velocity from the force balance.

Conventions
-----------
* SI units everywhere: m, s, V, V/m, C, Pa s, kg/m^3, K; ionic strength in
  mol/m^3 (= mmol/L; 1 mol/L = 1000 mol/m^3).
* ``ka`` is ``R / lambda_D`` (the seed's ``R_p / lambda_D``, often written
  kappa a).
* Henry's function ``f`` is used in the convention ``f in [1, 3/2]``:
  ``f -> 1`` for thick double layers (``ka -> 0``, Hueckel) and ``f -> 3/2``
  for thin ones (``ka -> inf``, Smoluchowski), with the Henry velocity
  ``v_H = 2 eps_r eps0 zeta E f / (3 mu)`` (seed eq. 3.34). (Other texts
  write ``f' = 2 f / 3 in [2/3, 1]`` and ``v = eps zeta E f' / mu``.)
* The colloid charge of seed eq. 3.33 (Giera et al.) is exactly
  ``q = 4 pi eps_r eps0 zeta R f(ka)`` with ``f`` Henry's exact function, so
  that a sphere with Stokes drag reaches ``q E / (6 pi mu R) = v_H``.

Where the seed is wrong this module does what is physically right:

* The Peclet number is ``Pe = v_H R / D_SE = 4 pi R^2 |E zeta| eps_r eps0 f / (kB T)``.
  The seed's eq. 3.37 prints ``6 pi``, which makes its Pe values 1.5x too high.
* Seed eq. 3.36 (force balance ``qE = C_D pi R^2 rho v^2``) drops the 1/2 of
  the drag law eq. 3.2; with it the Stokes limit would give half the Stokes
  velocity. The balance here uses the drag of eq. 3.2 with its 1/2.
* The drag-coefficient branches of eq. 3.5 are made continuous (C_D and
  C_D Re): at Re = 400 and 2e6 by taking the constant of the upper branch
  from the lower one (0.08 % and 0.4 % changes), and across the drag
  crisis by a power-law descent from Re = 2e5 to the seed's curve at 3e5
  instead of a 6x jump at 3e5 (see :func:`drag_coefficient`). For Re <= 1
  the law is exactly Stokes'.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import special

from ptrack.constants import AVOGADRO, BOLTZMANN, ELEMENTARY_CHARGE, STANDARD_GRAVITY, VACUUM_PERMITTIVITY
from ptrack.errors import UserError

__all__ = [
    "debye_length",
    "henry_function",
    "henry_function_swan_furst",
    "colloid_charge",
    "henry_velocity",
    "peclet_number",
    "reynolds_number",
    "drag_coefficient",
    "drag_coefficient_nb",
    "drag_force_nb",
    "drag_force",
    "buoyant_weight",
    "steady_state_velocity",
]


def _arr(name, value, positive=False, nonneg=False):
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{name} = {value!r} is not numeric", f"give {name} as a number in SI units")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{name} = {value!r} is not finite", f"give a finite {name}")
    if positive and np.any(a <= 0):
        raise UserError(f"{name} = {value!r} must be positive", f"give a positive {name} in SI units")
    if nonneg and np.any(a < 0):
        raise UserError(f"{name} = {value!r} must be non-negative", f"give a non-negative {name} in SI units")
    return a


def _broadcast(**arrays):
    """np.broadcast_arrays with a UserError naming the shapes on mismatch."""
    try:
        return np.broadcast_arrays(*arrays.values())
    except ValueError:
        shapes = ", ".join(f"{k} {np.shape(v)}" for k, v in arrays.items())
        raise UserError(f"array shapes do not broadcast: {shapes}", "give scalars or arrays of one common shape")


def _double_layer_inputs(zeta, radius, debye, eps_r) -> dict:
    """Validated zeta (V), radius (m), Debye length (m) and eps_r, keyed by name for :func:`_broadcast`."""
    return {"zeta": _arr("zeta", zeta), "radius": _arr("radius", radius, positive=True),
            "debye": _arr("debye", debye, positive=True), "eps_r": _arr("eps_r", eps_r, positive=True)}


def _out(x):
    x = np.asarray(x)
    return x if x.ndim else float(x)


# --------------------------------------------------------------------------
# Debye length and Henry's function
# --------------------------------------------------------------------------
def debye_length(ionic_strength, eps_r: float = 78.5, temperature: float = 298.15):
    """Debye screening length ``lambda_D = sqrt(eps_r eps0 kB T / (2 N_A e^2 I))``, m.

    Parameters
    ----------
    ionic_strength : float or array_like
        Ionic strength ``I = 1/2 sum_i c_i z_i^2`` in mol/m^3 (= mmol/L; for a
        1:1 salt, the salt concentration). 1 mM -> 9.6 nm in water at 25 C.
    eps_r : float
        Relative permittivity of the solvent (water: 78.5 at 25 C).
    temperature : float
        Absolute temperature, K.
    """
    I = _arr("ionic_strength", ionic_strength, positive=True)
    eps_r = float(_arr("eps_r", eps_r, positive=True))
    T = float(_arr("temperature", temperature, positive=True))
    lam = np.sqrt(eps_r * VACUUM_PERMITTIVITY * BOLTZMANN * T / (2.0 * AVOGADRO * ELEMENTARY_CHARGE ** 2 * I))
    return _out(lam)


def _henry_asymptotic(x):
    # f = 3/2 + sum_k c_k / x^k with c_k = (-1)^k (k+3)! ((k+5)(k+4) - 12) / 96,
    # from the large-x expansion of e^x E1(x); used for x >= 200 (error < 1e-16).
    total = np.zeros_like(x)
    for k in range(15, 0, -1):
        c = (-1) ** k * math.factorial(k + 3) * ((k + 5) * (k + 4) - 12) / 96.0
        total = (total + c) / x
    return 1.5 + total


def henry_function(ka):
    """Henry's exact function ``f(ka)`` for a sphere (convention ``f in [1, 3/2]``).

    Henry (1931); closed form with the exponential integral as written by
    Ohshima (1994) and, as a charge, by Giera et al. (the seed's eq. 3.33)::

        96 f = 96 + 6 x^2 - 10 x^3 - x^4 + x^5 + x^4 (12 - x^2) e^x E1(x),  x = ka

    The polynomial and the ``e^x E1`` term cancel catastrophically for large
    ``x`` (both grow as x^5 while f -> 3/2), so for ``x > 5`` the equivalent
    form with the remainder of the asymptotic series of ``e^x E1`` is used::

        96 f = 144 + 288/x - 1440/x^2 + 720 (12/x^2 - 1) e^x E7(x)

    and for ``x >= 200`` the asymptotic expansion
    ``f = 3/2 - 9/(2x) + 75/(2x^2) - 330/x^3 + ...``. Accurate to ~1e-15.

    Parameters
    ----------
    ka : float or array_like
        ``R / lambda_D`` (particle radius over Debye length), > 0.

    Returns
    -------
    float or ndarray
        ``f`` with ``f(0) = 1`` and ``f(inf) = 3/2``.
    """
    x = _arr("ka (R/lambda_D)", ka, nonneg=True)
    f = np.empty_like(x, dtype=np.float64)
    small = x <= 5.0
    mid = (x > 5.0) & (x < 200.0)
    large = x >= 200.0
    if np.any(small):
        xs = x[small]
        with np.errstate(invalid="ignore", divide="ignore"):
            e1 = np.where(xs > 0, np.exp(xs) * special.exp1(np.where(xs > 0, xs, 1.0)), 0.0)
            tail = np.where(xs > 0, xs ** 4 * (12.0 - xs * xs) * e1, 0.0)
        f[small] = (96.0 + 6.0 * xs ** 2 - 10.0 * xs ** 3 - xs ** 4 + xs ** 5 + tail) / 96.0
    if np.any(mid):
        xm = x[mid]
        e7 = np.exp(xm) * special.expn(7, xm)
        f[mid] = (144.0 + 288.0 / xm - 1440.0 / xm ** 2 + 720.0 * (12.0 / xm ** 2 - 1.0) * e7) / 96.0
    if np.any(large):
        f[large] = _henry_asymptotic(x[large])
    return _out(f)


def henry_function_swan_furst(ka):
    """Swan & Furst (2012) approximation of Henry's function (the seed's eq. 3.35).

    ``f ~ (16 + 18 x + 3 x^2) / (16 + 18 x + 2 x^2)``, ``x = ka``, convention
    ``f in [1, 3/2]``. It is exact in both limits; its largest error against
    :func:`henry_function` is about 0.2 % (0.147 % at ka = 2, the seed's case).
    """
    x = _arr("ka (R/lambda_D)", ka, nonneg=True)
    return _out((16.0 + 18.0 * x + 3.0 * x * x) / (16.0 + 18.0 * x + 2.0 * x * x))


def _f(ka, henry):
    if henry == "exact":
        return np.asarray(henry_function(ka))
    if henry == "swan_furst":
        return np.asarray(henry_function_swan_furst(ka))
    raise UserError(f"henry = {henry!r} is not known", "use 'exact' or 'swan_furst'")


# --------------------------------------------------------------------------
# charge, velocity, dimensionless numbers
# --------------------------------------------------------------------------
def colloid_charge(zeta, radius, debye, eps_r, henry: str = "exact"):
    """Effective colloid charge ``q = 4 pi eps_r eps0 zeta R f(R/lambda_D)``, C (seed eq. 3.33).

    With Stokes drag the terminal velocity ``q E / (6 pi mu R)`` of this
    charge is exactly the Henry velocity :func:`henry_velocity`.

    Parameters
    ----------
    zeta : float or array_like
        Zeta potential, V (sign carries to q).
    radius : float or array_like
        Particle radius R, m.
    debye : float or array_like
        Debye length lambda_D, m.
    eps_r : float or array_like
        Relative permittivity of the fluid.
    henry : {"exact", "swan_furst"}
        Henry's function to use.
    """
    zeta, R, lam, eps_r = _broadcast(**_double_layer_inputs(zeta, radius, debye, eps_r))
    return _out(4.0 * math.pi * eps_r * VACUUM_PERMITTIVITY * zeta * R * _f(R / lam, henry))


def henry_velocity(field, zeta, radius, debye, eps_r, viscosity, henry: str = "exact"):
    """Henry electrophoretic velocity ``v_H = 2 eps_r eps0 zeta E f(R/lambda_D) / (3 mu)``, m/s (seed eq. 3.34).

    Parameters
    ----------
    field : float or array_like
        Electric field E, V/m (a component or magnitude; v has its sign
        times the sign of zeta).
    zeta : float or array_like
        Zeta potential, V.
    radius, debye : float or array_like
        Particle radius and Debye length, m.
    eps_r : float or array_like
        Relative permittivity.
    viscosity : float or array_like
        Dynamic viscosity mu, Pa s.
    henry : {"exact", "swan_furst"}
    """
    E = _arr("field", field)
    inputs = _double_layer_inputs(zeta, radius, debye, eps_r)
    mu = _arr("viscosity", viscosity, positive=True)
    E, zeta, R, lam, eps_r, mu = _broadcast(field=E, **inputs, viscosity=mu)
    return _out(2.0 * eps_r * VACUUM_PERMITTIVITY * zeta * E * _f(R / lam, henry) / (3.0 * mu))


def peclet_number(field, zeta, radius, debye, eps_r, temperature, henry: str = "exact"):
    """Electrophoretic Peclet number ``Pe = |v_H| R / D_SE = 4 pi R^2 |E zeta| eps_r eps0 f / (kB T)``.

    The seed's eq. 3.37 prints ``6 pi`` instead of ``4 pi``; since
    ``D_SE = kB T / (6 pi mu R)`` and ``v_H = 2 eps eps0 zeta E f / (3 mu)``,
    ``v_H R / D_SE = 4 pi ...``: the seed's Pe values are 1.5x too high.
    The viscosity cancels, so it is not a parameter.

    Parameters
    ----------
    field : V/m; zeta : V; radius, debye : m; eps_r : -; temperature : K.
    """
    E = _arr("field", field)
    inputs = _double_layer_inputs(zeta, radius, debye, eps_r)
    T = _arr("temperature", temperature, positive=True)
    E, zeta, R, lam, eps_r, T = _broadcast(field=E, **inputs, temperature=T)
    return _out(4.0 * math.pi * R ** 2 * np.abs(E * zeta) * eps_r * VACUUM_PERMITTIVITY * _f(R / lam, henry)
                / (BOLTZMANN * T))


def reynolds_number(velocity, radius, fluid_density, viscosity):
    """Particle Reynolds number ``Re = rho_f |v| 2R / mu`` (seed eq. 3.4).

    Parameters
    ----------
    velocity : m/s (relative to the fluid; sign ignored); radius : m;
    fluid_density : kg/m^3; viscosity : Pa s.
    """
    v = _arr("velocity", velocity)
    R = _arr("radius", radius, positive=True)
    rho = _arr("fluid_density", fluid_density, positive=True)
    mu = _arr("viscosity", viscosity, positive=True)
    v, R, rho, mu = _broadcast(velocity=v, radius=R, fluid_density=rho, viscosity=mu)
    return _out(rho * np.abs(v) * 2.0 * R / mu)


# --------------------------------------------------------------------------
# drag law (seed eq. 3.2-3.5)
# --------------------------------------------------------------------------
# Seed eq. 3.5 (Biringen & Chow):  C_D = 24/Re (Re <= 1); 24/Re^0.646 (1 < Re <= 400);
# 0.5 (400 < Re <= 3e5); 0.000366 Re^0.4275 (3e5 < Re <= 2e6); 0.18 (Re > 2e6).
# The seed's constants leave C_D (and hence C_D*Re and the force) discontinuous:
#   * at Re = 400: 24/400^0.646 = 0.50042 vs 0.5 (0.08 % jump) -> the plateau
#     here is 24/400^0.646 so that C_D is continuous;
#   * at Re = 2e6: 0.000366 (2e6)^0.4275 = 0.18081 vs 0.18 (0.4 % jump) -> the
#     last branch here is 0.000366 (2e6)^0.4275;
#   * at Re = 3e5 the seed drops from 0.5 to 0.0804 (the drag crisis, a factor
#     6.2). A drop of the force with increasing speed makes the force balance
#     ambiguous; here the drag crisis is a continuous power-law descent from
#     the plateau at Re = 2e5 to the seed's curve at Re = 3e5 (measured drag
#     curves fall over roughly this interval), so C_D*Re is continuous
#     everywhere and equal to the seed's law outside 2e5 < Re < 3e5 (and for
#     Re <= 1, the only range that matters for colloids, it is exactly Stokes).
_CD_RE1 = 1.0
_CD_RE2 = 400.0
_CD_PLATEAU = 24.0 / 400.0 ** 0.646
_CD_CRISIS_START = 2.0e5
_CD_RE3 = 3.0e5
_CD_RE4 = 2.0e6
_CD_C4 = 0.000366
_CD_LAST = 0.000366 * 2.0e6 ** 0.4275
_CD_AT_RE3 = 0.000366 * 3.0e5 ** 0.4275
_CD_CRISIS_EXP = math.log(_CD_AT_RE3 / _CD_PLATEAU) / math.log(_CD_RE3 / _CD_CRISIS_START)


@njit(cache=True)
def drag_coefficient_nb(re):
    """Drag coefficient ``C_D(Re)`` of the seed's eq. 3.5, made continuous (scalar, numba).

    For ``Re <= 1`` this is Stokes' ``24/Re`` (so ``1/2 C_D pi R^2 rho v^2 =
    6 pi mu R v``); ``Re = 0`` returns ``inf`` (use :func:`drag_force_nb`).
    """
    if re <= _CD_RE1:
        if re <= 0.0:
            return np.inf
        return 24.0 / re
    if re <= _CD_RE2:
        return 24.0 * re ** -0.646
    if re <= _CD_CRISIS_START:
        return _CD_PLATEAU
    if re <= _CD_RE3:
        return _CD_PLATEAU * (re / _CD_CRISIS_START) ** _CD_CRISIS_EXP
    if re <= _CD_RE4:
        return _CD_C4 * re ** 0.4275
    return _CD_LAST


@njit(cache=True)
def drag_force_nb(speed, radius, fluid_density, viscosity):
    """Magnitude of the drag force ``1/2 C_D pi R^2 rho_f v^2`` (seed eq. 3.2), N; scalar numba kernel.

    Written as ``C_D Re * pi mu R v / 4`` so that it is finite (Stokes) at v = 0.
    """
    if speed <= 0.0:
        return 0.0
    re = 2.0 * radius * fluid_density * speed / viscosity
    if re <= _CD_RE1:
        return 6.0 * math.pi * viscosity * radius * speed
    return drag_coefficient_nb(re) * re * math.pi * viscosity * radius * speed / 4.0


@njit(cache=True)
def _map_cd(re, out):
    for i in range(re.size):
        out[i] = drag_coefficient_nb(re[i])


def drag_coefficient(re):
    """Drag coefficient ``C_D(Re)`` (seed eq. 3.5, continuous version), vectorised.

    Branches: ``24/Re`` (Re <= 1), ``24 Re^-0.646`` (1 < Re <= 400), plateau
    0.5004 (400 < Re <= 2e5), power-law drag crisis to the seed's curve at
    3e5, ``0.000366 Re^0.4275`` (3e5 < Re <= 2e6), 0.1808 beyond. See the
    module source for how and why the seed's branches were joined.

    Parameters
    ----------
    re : float or array_like
        Particle Reynolds number (>= 0).
    """
    re = _arr("Re", re, nonneg=True)
    flat = np.ascontiguousarray(re, dtype=np.float64).ravel()
    out = np.empty_like(flat)
    _map_cd(flat, out)
    return _out(out.reshape(re.shape))


@njit(cache=True)
def _map_drag(v, R, rho, mu, out):
    for i in range(v.size):
        out[i] = drag_force_nb(v[i], R[i], rho[i], mu[i])


def drag_force(speed, radius, fluid_density, viscosity):
    """Drag force magnitude ``1/2 C_D(Re) pi R^2 rho_f v^2`` (N), vectorised over arrays.

    Parameters
    ----------
    speed : m/s (>= 0, relative to the fluid); radius : m; fluid_density : kg/m^3;
    viscosity : Pa s. All broadcast together.
    """
    arrs = _broadcast(speed=_arr("speed", speed, nonneg=True), radius=_arr("radius", radius, positive=True),
                      fluid_density=_arr("fluid_density", fluid_density, positive=True),
                      viscosity=_arr("viscosity", viscosity, positive=True))
    shape = arrs[0].shape
    flat = [np.ascontiguousarray(a, dtype=np.float64).ravel() for a in arrs]
    out = np.empty(flat[0].size)
    _map_drag(flat[0], flat[1], flat[2], flat[3], out)
    return _out(out.reshape(shape))


def buoyant_weight(radius, particle_density, fluid_density, g: float = STANDARD_GRAVITY):
    """Weight minus buoyancy ``(rho_p - rho_f) 4/3 pi R^3 g``, N (positive = sinks)."""
    R = _arr("radius", radius, positive=True)
    return _out((_arr("particle_density", particle_density, positive=True)
                 - _arr("fluid_density", fluid_density, positive=True)) * 4.0 / 3.0 * math.pi * R ** 3 * g)


@njit(cache=True)
def _cd_balance(re, above_crisis):
    # C_D used inside the force balance. It equals drag_coefficient_nb wherever
    # the lowest-speed root can lie, and is monotone in force elsewhere, so the
    # fixed point is unique and is that root:
    #  * force <= drag at the crisis start (Re = 2e5): the root has Re <= 2e5,
    #    where drag rises monotonically; the plateau is continued past 2e5.
    #  * larger force: drag stays below it for all Re <= 3e5, so the root has
    #    Re > 3e5; the branch 0.000366 Re^0.4275 is continued below 3e5.
    if above_crisis:
        if re < _CD_RE3:
            return _CD_C4 * re ** 0.4275
        return drag_coefficient_nb(re)
    if re > _CD_CRISIS_START:
        return _CD_PLATEAU
    return drag_coefficient_nb(re)


@njit(cache=True)
def _steady(force, radius, rho, mu, rtol, max_iter, v_out, re_out, it_out):
    # Fixed-point iteration of seed eq. 3.36 with the 1/2 of eq. 3.2:
    #   v <- sqrt(2 F / (C_D(Re(v)) pi R^2 rho)),
    # started from the Stokes velocity (exact when Re <= 1, so it converges
    # at the first step in the colloidal regime). Each branch C_D ~ Re^p
    # makes the map v -> c v^(-p/2) a contraction (|p/2| <= 0.5), so it
    # converges linearly. Across the drag crisis (2e5 < Re < 3e5) the drag
    # force falls with speed and the balance can have three roots; the
    # lowest-speed one (the one a particle accelerating from rest reaches) is
    # selected through _cd_balance.
    for i in range(force.size):
        F = abs(force[i])
        R = radius[i]
        if F == 0.0:
            v_out[i] = 0.0
            re_out[i] = 0.0
            it_out[i] = 0
            continue
        v_crisis = _CD_CRISIS_START * mu[i] / (2.0 * R * rho[i])
        f_crisis = 0.5 * _CD_PLATEAU * math.pi * R * R * rho[i] * v_crisis * v_crisis
        above = F > f_crisis
        v = F / (6.0 * math.pi * mu[i] * R)
        n = 0
        converged = False
        while n < max_iter:
            n += 1
            re = 2.0 * R * rho[i] * v / mu[i]
            cd = _cd_balance(re, above)
            v_new = math.sqrt(2.0 * F / (cd * math.pi * R * R * rho[i]))
            if abs(v_new - v) <= rtol * v_new:
                v = v_new
                converged = True
                break
            v = v_new
        v_out[i] = math.copysign(v, force[i])
        re_out[i] = 2.0 * R * rho[i] * v / mu[i]
        it_out[i] = n if converged else -1


def steady_state_velocity(force, radius, fluid_density, viscosity, rtol: float = 1e-12, max_iter: int = 10000,
                          return_info: bool = False):
    """Terminal velocity where the drag of eq. 3.2 balances a constant force (seed eq. 3.36).

    Solves ``1/2 C_D(Re(v)) pi R^2 rho_f v^2 = |F|`` by the seed's fixed-point
    iteration ``v <- sqrt(2 |F| / (C_D(Re(v)) pi R^2 rho_f))`` (the seed's
    printed eq. 3.36 lacks the 1/2 of eq. 3.2, which would halve the Stokes
    velocity), started from the Stokes velocity ``|F| / (6 pi mu R)``.
    Where the balance has several solutions (forces whose speed falls in the
    drag crisis, 2e5 < Re < 3e5) the lowest speed is returned: the one a
    particle accelerating from rest reaches.

    Parameters
    ----------
    force : float or array_like
        Net driving force along the line of motion, N: ``q E`` plus the
        buoyant weight (see :func:`buoyant_weight`) projected on it. The sign
        is kept in the result.
    radius : m; fluid_density : kg/m^3; viscosity : Pa s (broadcast).
    rtol : float
        Relative change between iterates at which to stop.
    max_iter : int
        Iteration cap.
    return_info : bool
        Also return the Reynolds number and the iteration count.

    Returns
    -------
    v : float or ndarray
        Signed terminal velocity, m/s. With ``return_info``: ``(v, Re, n_iter)``.

    Raises
    ------
    UserError
        If the iteration has not converged to ``rtol`` after ``max_iter`` steps.
    """
    F, R, rho, mu = _broadcast(force=_arr("force", force), radius=_arr("radius", radius, positive=True),
                               fluid_density=_arr("fluid_density", fluid_density, positive=True),
                               viscosity=_arr("viscosity", viscosity, positive=True))
    if not (0 < rtol < 1):
        raise UserError(f"rtol = {rtol!r} must be in (0, 1)", "use e.g. 1e-12")
    shape = F.shape
    flat = [np.ascontiguousarray(a, dtype=np.float64).ravel() for a in (F, R, rho, mu)]
    v = np.empty(flat[0].size)
    re = np.empty_like(v)
    it = np.empty(v.size, dtype=np.int64)
    _steady(flat[0], flat[1], flat[2], flat[3], float(rtol), int(max_iter), v, re, it)
    if np.any(it < 0):
        i = int(np.argmax(it < 0))
        raise UserError(
            f"steady-state velocity did not converge to rtol={rtol:g} in {max_iter} iterations "
            f"(force {flat[0][i]:.4g} N, radius {flat[1][i]:.4g} m, last Re {re[i]:.4g})",
            "raise max_iter or loosen rtol",
        )
    v = v.reshape(shape)
    if return_info:
        return _out(v), _out(re.reshape(shape)), _out(it.reshape(shape))
    return _out(v)
