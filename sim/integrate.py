"""Time integration of free (non-interacting) particles: exact OU, overdamped BD, trapezoidal.

Three integrators, each a numba kernel that advances all particles over
``nframes`` output frames of ``steps`` time steps and stores the frames:

``ou_exact``
    The exact joint position-velocity Ornstein-Uhlenbeck update for Stokes
    drag + constant forces + Brownian noise. With tau = m / gamma,
    a = dt / tau, D = kB T / gamma and u = v_f + F / gamma the drift velocity,
    per component::

        v' = u + (v - u) e^-a + xi_v
        x' = x + u dt + (v - u) tau (1 - e^-a) + xi_x
        Var xi_v = kB T / m (1 - e^-2a)
        Var xi_x = D tau (2a - 3 + 4 e^-a - e^-2a)
        Cov     = D (1 - e^-a)^2

    Exact for any dt (no stability limit; a velocity-only OU update with
    x' = x + v' dt would overestimate D by about dt / tau).
``overdamped``
    Brownian dynamics (Euler-Maruyama) x' = x + (v_f + M F) dt + kB T dM/dz dt
    + sqrt(2 kB T M dt) N(0, 1) for dt >> tau, M = 1 / gamma, optionally with
    the near-wall hindered mobility of :mod:`ptrack.wall` (M_par, M_perp
    depending on the height) and its spurious-drift correction kB T dM_perp/dz,
    without which particles pile up at the wall.
``trapezoidal``
    The seed's generalised trapezoidal rule (eq. 3.28-3.29) on m dv/dt = F:
    v' = v + dt/m (phi F(v') + (1 - phi) F(v)), x' = x + dt (phi v' + (1 - phi) v).
    phi = 0 is explicit (forward) Euler, stable only for dt < 2 tau; for
    phi > 0 the implicit equation is solved by fixed-point iterations to a
    relative tolerance, with the drag written gamma phi_D(Re) (v_f - v') and
    only the factor phi_D(Re) (and v x B) lagged, so the iteration converges
    for any dt when phi >= 1/2. Handles the piecewise drag law (Re > 1) and
    magnetic fields, which the exact update does not.

Random numbers: the counter-based :func:`sim.forces.brownian.counter_normal`
keyed by (seed, step, particle and component), the scheme of the DEM engine
too; with ``noise = False`` (T = 0) no random number is drawn.

Boundaries (all kernels): ``modes`` (2, 3) int array from
:attr:`sim.scene.Boundaries.modes`, lower faces in row 0 and upper faces in
row 1, 0 = open, 1 = periodic (wrap into [0, L)), 2 = wall (specular
reflection of the particle at contact, centre at R from the plane).
"""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
from numba import njit

from ptrack.errors import UserError
from sim.forces.body import magnetic_force
from sim.forces.brownian import brownian_sigma, counter_normal
from sim.forces.drag import drag_factor, max_reynolds
from sim.scene import PERIODIC, WALL

log = logging.getLogger("sim.integrate")

OVERDAMPED_RATIO = 1.0e4  # "auto" uses overdamped BD when the step is at least this many m/gamma

# near-wall mobility ratios: the one implementation, in ptrack.wall (no fallback: a broken
# ptrack.wall must fail the tests, not make them skip)
from ptrack.wall import parallel_ratio_nb, perpendicular_ratio_derivative_nb, perpendicular_ratio_nb  # noqa: E402


# --------------------------------------------------------------------------- helpers
@njit(cache=True, nogil=True)
def _apply_boundaries(pos, vel, i, radius, box, modes, flip_velocity):
    for k in range(3):
        L = box[k]
        if modes[0, k] == PERIODIC:  # both faces
            x = pos[i, k]
            if x < 0.0 or x >= L:
                x = x - L * math.floor(x / L)
                if x >= L:
                    x = 0.0
                pos[i, k] = x
            continue
        r = radius
        for _ in range(4):  # repeated reflection if a step crosses both walls (tiny boxes)
            moved = False
            if modes[0, k] == WALL and pos[i, k] < r:
                pos[i, k] = 2.0 * r - pos[i, k]
                if flip_velocity:
                    vel[i, k] = abs(vel[i, k])
                moved = True
            if modes[1, k] == WALL and pos[i, k] > L - r:
                pos[i, k] = 2.0 * (L - r) - pos[i, k]
                if flip_velocity:
                    vel[i, k] = -abs(vel[i, k])
                moved = True
            if not moved:
                break


@njit(cache=True)
def ou_coefficients(a):
    """Dimensionless OU coefficients for a = dt / tau.

    Returns (e, em, gvv, gxx, gxv, gcond): e = exp(-a), em = 1 - exp(-a),
    Var v = (kT/m) gvv, Var x = D tau gxx, Cov = D gxv, and the variance of x
    conditional on the v increment, D tau gcond (series for small a to avoid
    cancellation).
    """
    e = math.exp(-a)
    em = -math.expm1(-a)
    gvv = em * (2.0 - em)
    gxv = em * em
    if a < 0.02:
        a2 = a * a
        a3 = a2 * a
        gxx = a3 * (2.0 / 3.0 - a / 2.0 + 7.0 / 30.0 * a2 - a3 / 12.0)
        gcond = a3 * (1.0 / 6.0 - a2 / 60.0 + 17.0 / 10080.0 * a2 * a2)
    else:
        gxx = 2.0 * a - 2.0 * em - em * em
        gcond = gxx - em * em * em / (2.0 - em)
    return e, em, gvv, gxx, gxv, gcond


# --------------------------------------------------------------------------- kernels
@njit(cache=True, nogil=True)
def ou_exact_kernel(pos, vel, radius, mass, gamma, fconst, vf, kT, dt, steps, nframes, box, modes,
                    out_pos, out_vel, noise, i0, i1, seed, step0):
    """Exact OU update of particles ``i0 <= i < i1``; frames stored in out_pos/out_vel (nframes, N, 3).

    Random numbers: :func:`sim.forces.brownian.counter_normal` keyed by
    (seed, step, index), steps counted from ``step0`` (the steps done before
    this call), so a run split into calls over particle blocks or frames
    draws the numbers of one call.
    """
    for i in range(i0, i1):
        tau = mass[i] / gamma[i]
        a = dt / tau
        e, em, gvv, gxx, gxv, gcond = ou_coefficients(a)
        D = kT / gamma[i]
        sv = math.sqrt(kT / mass[i] * gvv)
        cx = D * gxv / sv if sv > 0.0 else 0.0
        sx = math.sqrt(max(D * tau * gcond, 0.0))
        u0 = vf[0] + fconst[i, 0] / gamma[i]
        u1 = vf[1] + fconst[i, 1] / gamma[i]
        u2 = vf[2] + fconst[i, 2] / gamma[i]
        for f in range(nframes):
            for s in range(steps):
                step = step0 + f * steps + s + 1
                for k in range(3):
                    u = u0 if k == 0 else (u1 if k == 1 else u2)
                    dv = vel[i, k] - u
                    if noise:
                        z1 = counter_normal(seed, step, 6 * i + 2 * k)
                        z2 = counter_normal(seed, step, 6 * i + 2 * k + 1)
                        pos[i, k] += u * dt + dv * tau * em + cx * z1 + sx * z2
                        vel[i, k] = u + dv * e + sv * z1
                    else:
                        pos[i, k] += u * dt + dv * tau * em
                        vel[i, k] = u + dv * e
                _apply_boundaries(pos, vel, i, radius[i], box, modes, True)
            for k in range(3):
                out_pos[f, i, k] = pos[i, k]
                out_vel[f, i, k] = vel[i, k]


WALL_TABLE_POINTS = 20001
WALL_TABLE_GAP_RANGE = (1e-8, 99.0)   # gap (h - a) / a covered by the tables; beyond: direct evaluation


@njit(cache=True)
def _fill_wall_tables(u0, du, par, perp, dperp):
    for j in range(par.shape[0]):
        x = 1.0 + math.exp(u0 + j * du)
        par[j] = parallel_ratio_nb(x)
        perp[j] = perpendicular_ratio_nb(x)
        dperp[j] = perpendicular_ratio_derivative_nb(x)


_WALL_TABLES = None


def wall_tables():
    """Tabulated near-wall mobility ratios for the BD kernel: (u0, du, par, perp, dperp).

    The ratios of :mod:`ptrack.wall` (Brenner's series for the perpendicular
    ratio needs many terms near contact) are tabulated once on a uniform grid
    in u = ln((h - a) / a) over gaps 1e-8 ... 99 radii (20001 points, linear
    interpolation: relative error ~1e-7) and evaluated directly beyond.
    """
    global _WALL_TABLES
    if _WALL_TABLES is None:
        lo, hi = WALL_TABLE_GAP_RANGE
        u0 = math.log(lo)
        du = (math.log(hi) - u0) / (WALL_TABLE_POINTS - 1)
        par = np.empty(WALL_TABLE_POINTS)
        perp = np.empty(WALL_TABLE_POINTS)
        dperp = np.empty(WALL_TABLE_POINTS)
        _fill_wall_tables(u0, du, par, perp, dperp)
        _WALL_TABLES = (u0, du, par, perp, dperp)
    return _WALL_TABLES


@njit(cache=True, nogil=True)
def _wall_lookup(x, u0, du, par, perp, dperp):
    """(M_par/M0, M_perp/M0, d(M_perp/M0)/dx) at x = h / a from the tables."""
    g = x - 1.0
    if g <= 0.0:
        return par[0], perp[0], dperp[0]
    u = math.log(g)
    t = (u - u0) / du
    last = par.shape[0] - 1
    if t >= last:
        return parallel_ratio_nb(x), perpendicular_ratio_nb(x), perpendicular_ratio_derivative_nb(x)
    if t <= 0.0:
        return par[0], perp[0], dperp[0]
    j = int(t)
    w = t - j
    return (par[j] + w * (par[j + 1] - par[j]), perp[j] + w * (perp[j + 1] - perp[j]),
            dperp[j] + w * (dperp[j + 1] - dperp[j]))


@njit(cache=True, nogil=True)
def overdamped_kernel(pos, vel, radius, gamma, fconst, vf, kT, dt, steps, nframes, box, modes,
                      out_pos, out_vel, noise, hindered, u0, du, tpar, tperp, tdperp, i0, i1, seed, step0):
    """Euler-Maruyama Brownian dynamics; ``vel`` receives the deterministic drift velocity.

    With ``hindered`` the mobility parallel / perpendicular to the z = 0 wall
    is scaled by the ratios of :mod:`ptrack.wall` at h / R (h = centre height,
    tabulated by :func:`wall_tables`) and the drift kB T dM_perp/dz dt is added.
    Particles ``i0 <= i < i1``, random numbers keyed from ``step0`` (see :func:`ou_exact_kernel`).
    """
    for i in range(i0, i1):
        m0 = 1.0 / gamma[i]
        a = radius[i]
        for f in range(nframes):
            for s in range(steps):
                step = step0 + f * steps + s + 1
                mpar = m0
                mperp = m0
                drift = 0.0
                if hindered:
                    rpar, rperp, rd = _wall_lookup(pos[i, 2] / a, u0, du, tpar, tperp, tdperp)
                    mpar = m0 * rpar
                    mperp = m0 * rperp
                    drift = kT * m0 * rd / a
                for k in range(3):
                    mk = mperp if k == 2 else mpar
                    v = vf[k] + mk * fconst[i, k]
                    if k == 2:
                        v += drift
                    vel[i, k] = v
                    dx = v * dt
                    if noise:
                        dx += math.sqrt(2.0 * kT * mk * dt) * counter_normal(seed, step, 3 * i + k)
                    pos[i, k] += dx
                _apply_boundaries(pos, vel, i, a, box, modes, False)
            for k in range(3):
                out_pos[f, i, k] = pos[i, k]
                out_vel[f, i, k] = vel[i, k]


@njit(cache=True, nogil=True)
def _drag_gamma(g0, stokes, radius, rho_f, mu, ux, uy, uz):
    """Drag coefficient (kg/s) at the fluid-relative velocity u = v_f - v (m/s).

    The Stokes ``g0`` if ``stokes``, else ``g0 phi_D(Re)`` with the piecewise law at
    Re = 2 a rho_f |u| / mu.
    """
    if stokes:
        return g0
    return g0 * drag_factor(2.0 * radius * rho_f * math.sqrt(ux * ux + uy * uy + uz * uz) / mu)


@njit(cache=True, nogil=True)
def trapezoidal_kernel(pos, vel, radius, mass, gamma, charge, fconst, vf, B, rho_f, mu, kT, dt,
                       steps, nframes, box, modes, out_pos, out_vel, noise, phi, tol, max_iter, stokes, i0, i1,
                       seed, step0):
    """Generalised trapezoidal rule (eq. 3.28-3.29). Returns the number of non-converged steps.

    ``fconst`` already holds q E and gravity; the drag (Stokes if ``stokes``,
    else the piecewise law) and q v x B are evaluated here; the Brownian force
    (variance 2 gamma kT / dt with the Stokes gamma) is drawn once per step and
    held over it. (Fluctuation-dissipation is exact only for the linear,
    Stokes drag; at Re > 1 the thermal force is negligible against the drive.)
    Particles ``i0 <= i < i1``, random numbers keyed from ``step0`` (see :func:`ou_exact_kernel`).
    """
    failures = 0
    v0 = np.empty(3)
    v1 = np.empty(3)
    vn = np.empty(3)
    f0 = np.empty(3)
    fb = np.empty(3)
    for i in range(i0, i1):
        m = mass[i]
        g0 = gamma[i]
        q = charge[i]
        sb = brownian_sigma(g0, kT, dt) if noise else 0.0
        for f in range(nframes):
            for s in range(steps):
                step = step0 + f * steps + s + 1
                for k in range(3):
                    v0[k] = vel[i, k]
                    fb[k] = sb * counter_normal(seed, step, 3 * i + k) if noise else 0.0
                # force at the start of the step
                ux = vf[0] - v0[0]
                uy = vf[1] - v0[1]
                uz = vf[2] - v0[2]
                gd = _drag_gamma(g0, stokes, radius[i], rho_f, mu, ux, uy, uz)
                mx, my, mz = magnetic_force(q, v0[0], v0[1], v0[2], B[0], B[1], B[2])
                f0[0] = fconst[i, 0] + fb[0] + gd * ux + mx
                f0[1] = fconst[i, 1] + fb[1] + gd * uy + my
                f0[2] = fconst[i, 2] + fb[2] + gd * uz + mz
                if phi == 0.0:
                    for k in range(3):
                        v1[k] = v0[k] + dt / m * f0[k]
                else:
                    for k in range(3):
                        v1[k] = v0[k]
                    converged = False
                    for it in range(max_iter):
                        g1 = _drag_gamma(g0, stokes, radius[i], rho_f, mu, vf[0] - v1[0], vf[1] - v1[1], vf[2] - v1[2])
                        c = phi * dt / m
                        l0, l1, l2 = magnetic_force(q, v1[0], v1[1], v1[2], B[0], B[1], B[2])
                        # implicit in the linear drag term: v' (1 + c g1) = v0 + c (F_c + F_b + g1 v_f + q v x B) + (1 - phi) dt/m f0
                        vn[0] = (v0[0] + c * (fconst[i, 0] + fb[0] + g1 * vf[0] + l0) + (1.0 - phi) * dt / m * f0[0]) / (1.0 + c * g1)
                        vn[1] = (v0[1] + c * (fconst[i, 1] + fb[1] + g1 * vf[1] + l1) + (1.0 - phi) * dt / m * f0[1]) / (1.0 + c * g1)
                        vn[2] = (v0[2] + c * (fconst[i, 2] + fb[2] + g1 * vf[2] + l2) + (1.0 - phi) * dt / m * f0[2]) / (1.0 + c * g1)
                        d2 = 0.0
                        s2 = 0.0
                        for k in range(3):
                            d2 += (vn[k] - v1[k]) ** 2
                            s2 += vn[k] ** 2 + v0[k] ** 2
                            v1[k] = vn[k]
                        if d2 <= tol * tol * s2 or d2 == 0.0:
                            converged = True
                            break
                    if not converged:
                        failures += 1
                for k in range(3):
                    pos[i, k] += dt * (phi * v1[k] + (1.0 - phi) * v0[k])
                    vel[i, k] = v1[k]
                _apply_boundaries(pos, vel, i, radius[i], box, modes, True)
            for k in range(3):
                out_pos[f, i, k] = pos[i, k]
                out_vel[f, i, k] = vel[i, k]
    return failures


# --------------------------------------------------------------------------- choices
def momentum_relaxation_time(mass, gamma) -> np.ndarray:
    """tau = m / gamma (s) per particle: the time over which a velocity forgets itself."""
    return np.asarray(mass, dtype=float) / np.asarray(gamma, dtype=float)


def _drag_slope(re: float) -> float:
    """d ln(phi_D) / d ln(Re) of the drag factor (0 in the Stokes regime)."""
    if re <= 1.0:
        return 0.0
    return math.log(drag_factor(re * 1.001) / drag_factor(re)) / math.log(1.001)


def effective_relaxation_time(mass, gamma, re) -> float:
    """Smallest linearised relaxation time m / (dF/dv) over particles at Reynolds numbers ``re`` (s).

    For the piecewise law F = gamma phi_D(Re) u, dF/du = gamma phi_D (1 + dln phi_D / dln Re).
    """
    mass = np.atleast_1d(np.asarray(mass, float))
    gamma = np.atleast_1d(np.asarray(gamma, float))
    re = np.broadcast_to(np.atleast_1d(np.asarray(re, float)), mass.shape)
    fac = np.array([drag_factor(float(r)) * (1.0 + _drag_slope(float(r))) for r in re])
    return float(np.min(mass / (gamma * fac)))


def max_stable_dt(kind: str, phi: float, tau_eff: float, cyclotron_rate: float = 0.0) -> float:
    """Largest time step (s) the integrator takes stably for relaxation time ``tau_eff``.

    ``ou_exact`` and ``overdamped`` have no limit (inf). For the trapezoidal
    rule on dv/dt = -v / tau: |1 - (1 - phi) a| / (1 + phi a) < 1 requires
    dt < 2 tau / (1 - 2 phi) when phi < 1/2 (explicit Euler: 2 tau); the
    lagged magnetic term in the fixed-point iteration adds dt < 1 / (phi q B / m).
    """
    if kind != "trapezoidal":
        return math.inf
    lim = math.inf
    if phi < 0.5:
        lim = 2.0 * tau_eff / (1.0 - 2.0 * phi)
    if phi > 0 and cyclotron_rate > 0:
        lim = min(lim, 1.0 / (phi * cyclotron_rate))
    return lim


@dataclasses.dataclass
class IntegratorChoice:
    """What the run uses: integrator kind, phi, dt (s), steps per output frame, and why."""
    kind: str
    dt: float
    steps_per_output: int
    phi: float
    reason: str
    tau_min: float
    re_estimate: float
    max_stable_dt: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _estimate_reynolds(scene, state, fconst) -> float:
    vf = np.asarray(scene.fluid.velocity, dtype=np.float64)
    u_term = fconst / state.gamma[:, None]  # Stokes terminal velocity relative to the fluid
    re_term = 2.0 * state.radius * scene.fluid.density * np.linalg.norm(u_term, axis=1) / scene.fluid.viscosity
    re_now = max_reynolds(state.vel, vf, state.radius, scene.fluid.density, scene.fluid.viscosity)
    return float(max(re_term.max(initial=0.0), re_now))


def _reynolds_at_balance(scene, state, fconst) -> np.ndarray:
    """Re at the drag-force balance |F| = gamma phi_D(Re) |u| per particle (fixed point on Re)."""
    fmag = np.linalg.norm(fconst, axis=1)
    c = 2.0 * state.radius * scene.fluid.density / scene.fluid.viscosity
    re = c * fmag / state.gamma
    for _ in range(200):
        new = np.array([c[i] * fmag[i] / (state.gamma[i] * drag_factor(float(r))) for i, r in enumerate(re)])
        if np.allclose(new, re, rtol=1e-12, atol=0):
            break
        re = new
    return re


def choose_integrator(scene, state, fconst) -> IntegratorChoice:
    """Pick integrator and dt from the physics, or check the user's choice; say why.

    ``auto``: overdamped BD if near-wall hindered mobility is requested;
    the trapezoidal rule if the Reynolds number (Stokes terminal speed, or
    the initial velocities) exceeds 1 (piecewise drag) or B != 0; otherwise
    overdamped BD if the step (dt, or the output interval) is at least
    1e4 m/gamma (the velocity has no memory from one step to the next, and
    BD needs half the random numbers), else the exact OU update. dt "auto": the output interval for the exact update
    of free particles (it is exact for any dt), refined so that the drift
    moves a particle by at most 5 % of its radius per step when walls are
    present (reflecting a free Brownian step at a plane is exact by the
    method of images); 0.2 of the
    smallest (linearised) relaxation time for the trapezoidal rule; and a
    1 %-of-radius step for overdamped runs with hindered mobility.

    Raises
    ------
    UserError
        A time step the chosen integrator cannot take stably (names the largest
        stable dt), or a combination the integrator cannot represent.
    """
    spec = scene.integrator
    tau = momentum_relaxation_time(state.mass, state.gamma)
    tau_min = float(tau.min())
    re_est = _estimate_reynolds(scene, state, fconst)
    bmag = float(np.linalg.norm(scene.fields.B))
    why = []
    kind = spec.kind
    if kind == "auto":
        if spec.hindered_mobility:
            kind = "overdamped"
            why.append("near-wall hindered mobility requested -> overdamped Brownian dynamics")
        elif re_est > 1.0:
            kind = "trapezoidal"
            why.append(f"Reynolds number up to {re_est:.3g} > 1 -> piecewise drag law -> trapezoidal rule")
        elif bmag > 0:
            kind = "trapezoidal"
            why.append("magnetic field B != 0 (velocity-dependent Lorentz force) -> trapezoidal rule")
        else:
            step = scene.time.dt if scene.time.dt is not None else scene.time.output_interval
            tau_max = float(tau.max())
            if step >= OVERDAMPED_RATIO * tau_max:
                kind = "overdamped"
                why.append(f"Stokes drag (Re <= {max(re_est, 0):.3g} <= 1), B = 0 and dt = {step:.3g} s >= "
                           f"{OVERDAMPED_RATIO:g} m/gamma = {OVERDAMPED_RATIO * tau_max:.3g} s: velocities relax "
                           "within a step -> overdamped Brownian dynamics (exact for free particles; velocity "
                           "column = drift velocity)")
            else:
                kind = "ou_exact"
                why.append(f"Stokes drag (Re <= {max(re_est, 0):.3g} <= 1), B = 0 -> exact OU update "
                           f"(m/gamma = {tau_min:.3g} s; exact for any dt)")
    else:
        why.append(f"integrator {kind!r} requested")
    if kind in ("ou_exact", "overdamped") and re_est > 1.0:
        raise UserError(f"integrator {kind!r} assumes Stokes drag but the Reynolds number reaches {re_est:.3g} > 1",
                        'use kind = "trapezoidal" (piecewise drag law) or "auto"')
    if kind in ("ou_exact", "overdamped") and bmag > 0:
        raise UserError(f"integrator {kind!r} cannot include the magnetic force q v x B (|B| = {bmag:g} T)",
                        'use kind = "trapezoidal" or "auto"')
    if spec.hindered_mobility and kind != "overdamped":
        raise UserError(f"integrator.hindered_mobility needs the overdamped integrator, not {kind!r}",
                        'set kind = "overdamped" or "auto"')
    phi = spec.phi if kind == "trapezoidal" else 0.0
    if kind == "trapezoidal" and spec.kind == "auto" and phi == 0.0:
        phi = 0.5
        why.append("phi = 1/2 (trapezoidal rule: second order, exact equipartition with Stokes drag)")
    re_bal = _reynolds_at_balance(scene, state, fconst)
    tau_eff = effective_relaxation_time(state.mass, state.gamma, np.maximum(re_bal, re_est if kind == "trapezoidal" else 0))
    qm = np.abs(state.charge) / state.mass
    lim = max_stable_dt(kind, phi, tau_eff, float(qm.max(initial=0.0)) * bmag)
    out = scene.time.output_interval
    walls = bool(np.any(scene.boundaries.modes == WALL))
    dt = scene.time.dt
    if dt is None:
        if kind == "ou_exact":
            dt = out
            if walls:
                # reflecting a free Brownian step at a plane is exact (method of images), so only the
                # drift limits dt: |u| dt <= 5 % of the radius
                speed = np.linalg.norm(fconst / state.gamma[:, None], axis=1)
                lim_w = np.min(_step_limit(np.zeros_like(speed), speed, 0.05 * state.radius))
                if lim_w < dt:
                    dt = lim_w
                    why.append("dt limited so that the drift moves a particle by <= 5 % of its radius per step (walls)")
        elif kind == "trapezoidal":
            dt = min(out, 0.2 * tau_eff)
            why.append(f"dt = 0.2 x relaxation time {tau_eff:.3g} s")
        else:
            dt = out
            if walls or spec.hindered_mobility:
                # hindered mobility: the diffusive step must resolve the mobility gradient near the wall
                # (1 % of the radius); plain reflecting walls: only the drift limits dt (5 % of the radius)
                D = scene.kT / state.gamma if spec.hindered_mobility else np.zeros(state.n)
                speed = np.linalg.norm(fconst / state.gamma[:, None], axis=1)
                frac = 0.01 if spec.hindered_mobility else 0.05
                lim_w = np.min(_step_limit(D, speed, frac * state.radius))
                if lim_w < dt:
                    dt = lim_w
                    why.append(f"dt limited so that a step moves a particle by <= {frac:.0%} of its radius")
            if dt < 10 * tau_min:
                why.append(f"warning: dt = {dt:.3g} s is not >> m/gamma = {tau_min:.3g} s; overdamped velocities are drift only")
    if dt > lim:
        raise UserError(
            f"time step dt = {dt:.3g} s is unstable for the {kind} integrator with phi = {phi:g} "
            f"(relaxation time m/gamma = {tau_eff:.3g} s; largest stable dt = {lim:.3g} s)",
            f"set time.dt below {lim:.3g} s, or use integrator kind = \"ou_exact\"/\"auto\"")
    steps = max(1, int(math.ceil(out / dt * (1 - 1e-12))))
    dt = out / steps
    why.append(f"dt = {dt:.4g} s, {steps} step(s) per output interval {out:.4g} s")
    reason = "; ".join(why)
    log.info("integrator: %s", reason)
    return IntegratorChoice(kind=kind, dt=dt, steps_per_output=steps, phi=phi, reason=reason, tau_min=tau_min,
                            re_estimate=re_est, max_stable_dt=lim)


def _step_limit(D, speed, dx):
    """Largest dt with sqrt(2 D dt) + speed dt <= dx (elementwise, s)."""
    D = np.asarray(D, float)
    speed = np.asarray(speed, float)
    dx = np.asarray(dx, float)
    # solve speed * s^2 + sqrt(2 D) s - dx = 0 for s = sqrt(dt)
    b = np.sqrt(2.0 * D)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(speed > 0, (-b + np.sqrt(b * b + 4 * speed * dx)) / (2 * np.where(speed > 0, speed, 1.0)),
                     dx / np.where(b > 0, b, 1.0))
    return np.where((speed > 0) | (b > 0), s * s, np.inf)
