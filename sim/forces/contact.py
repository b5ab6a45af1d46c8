"""Contact forces between spheres and between spheres and plane walls.

Two contact laws, selected by an integer ``model`` so one compiled kernel
serves every scene (the branch is taken once per pair and predicted well):

``CONTACT_HOOKE`` (1): linear spring-dashpot with Coulomb friction and a
    tangential spring with history, as in LAMMPS ``pair gran/hooke/history``.
    Normal force on i: ``F_n = kn delta - eta (v_r . n)`` along ``n`` (from j to
    i), ``eta = 2 beta sqrt(kn m_eff)``, ``beta = -ln e / sqrt(pi^2 + ln^2 e)``
    so that an isolated binary impact has restitution exactly ``e``
    (linear damped oscillator; ``m_eff = m_i m_j/(m_i+m_j)``, ``m_i`` for a
    wall).  Tangential: spring ``s += v_t dt`` (kept in the tangent plane),
    ``F_t = -kt s - eta_t v_t``, capped at ``mu |F_n|`` with the spring reset to
    the slip limit.  ``eta_t = damp_t_ratio * eta``.
    Parameter array: ``[kn, kt, beta, damp_t_ratio, mu]``.

``CONTACT_POWER`` (2): the seed's law (eq. 3.10-3.23, after Zohdi):
    normal contact ``K |eps|^p A_c``, strain ``eps = delta/(R_i+R_j)``, contact
    area ``A_c = pi (R_i^2 - L_i^2)``; dissipation ``c_cd (v_j,n - v_i,n) A_c``;
    normal bond ``-K_nb |eps|^p_b A_c`` (attractive) while ``eps >= eps*``;
    regularised stick-slip friction and the rotational (tangential) bond.
    Parameter array:
    ``[K, p, c_cd, K_nb, K_rb, p_b, eps_star, K_f, mu_s, mu_d, bonding, friction]``.

    Corrections to the seed, all physically motivated:

    * Eq. 3.20 / 3.23 write the stick and bond forces as
      ``K |v_t| A_c dt``, i.e. a viscous force whose strength depends on the
      simulation step.  We read ``|v_t| dt`` as the tangential displacement
      increment and accumulate it in a tangential spring ``s`` (history), so the
      stick force is ``-K_f A_c s`` (``-K_rb A_c s`` for the bond): identical to
      the seed on the first step of a contact, independent of dt afterwards.
      When ``K_f A_c |s| >= mu_s |F_c|`` the contact slips with
      ``mu_d |F_c|`` and the spring is reset to that force.
    * For a wall the seed's strain ``delta/(R_i + R_w)`` vanishes as
      ``R_w -> infinity``; we use ``delta / R_i`` (the particle's own strain).
      The wall contact area is ``pi (R_i^2 - d^2)``, d = centre-to-plane
      distance, which is the seed's ``A_c`` in the ``R_w -> infinity`` limit.

Rotation: the tangential velocity at the contact includes
``-(R_i w_i + R_j w_j) x n``; tangential forces produce torques
``-R_i n x F_t`` on both bodies.  Every pair is evaluated once and applied as
+F to i and -F to j (Newton's third law to round-off).

Near-field forces of :mod:`sim.forces.nearfield` are added in the same pass.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from sim.forces.nearfield import LAW_WIDTH, MAX_TUPLE_LAWS, fast_pow, law_tuples, pair_law_force, pair_law_force_t

CONTACT_NONE = 0
CONTACT_HOOKE = 1
CONTACT_POWER = 2

# diagnostics array layout (returned through ``diag``)
D_MAX_OVERLAP = 0      # max delta / min(R_i, R_j)
D_MAX_OVERLAP_I = 1    # particle with that overlap
D_MAX_W2 = 2           # max k_eff / m_eff over contacts (1/s^2)
D_MAX_DAMP = 3         # max eta / m_eff over contacts (1/s)
D_N_CONTACTS = 4
D_SIZE = 5


def restitution_beta(e):
    """``beta = -ln e / sqrt(pi^2 + ln^2 e)``: damping ratio giving restitution ``e``."""
    if not 0.0 < e <= 1.0:
        raise ValueError("restitution must be in (0, 1]")
    le = math.log(e)
    return -le / math.sqrt(math.pi**2 + le * le)


@njit(cache=True, inline="always")
def param_tuple(cp):
    """The contact parameters as a 12-tuple (zero-padded): the form :func:`_law` takes."""
    m = cp.shape[0]
    return (cp[0] if m > 0 else 0.0, cp[1] if m > 1 else 0.0, cp[2] if m > 2 else 0.0, cp[3] if m > 3 else 0.0,
            cp[4] if m > 4 else 0.0, cp[5] if m > 5 else 0.0, cp[6] if m > 6 else 0.0, cp[7] if m > 7 else 0.0,
            cp[8] if m > 8 else 0.0, cp[9] if m > 9 else 0.0, cp[10] if m > 10 else 0.0,
            cp[11] if m > 11 else 0.0)


@njit(cache=True, inline="always")
def _law(model, cp, delta, nx, ny, nz, d, ri, rj, wall, meff, sqkm, invm,
         vrx, vry, vrz, wsx, wsy, wsz, sx, sy, sz, dt):
    """Contact force on i (along n from j to i) and the tangential part.

    ``cp`` is the parameter tuple of :func:`param_tuple`; ``meff`` the effective mass (kg) and, for
    the Hooke law, ``sqkm = sqrt(kn meff)`` (kg/s) and ``invm = 1 / meff`` (1/kg), which the caller
    gives (:func:`_hooke_mass_terms`: a row of equal-mass partners shares them); ``ws = R_i w_i + R_j w_j``
    (for a wall: ``R_i w_i``); ``s`` the tangential spring of this contact (m).
    Returns ``(fx, fy, fz, tfx, tfy, tfz, sx, sy, sz, w2, dr)``: total force on i,
    its tangential part, the updated spring, and k/m_eff (1/s^2) and eta/m_eff
    (1/s) for the time-step diagnostics.  Scalars in and out: array arguments
    of a function called per contact cost reference counting in the hot loop.
    """
    vn = vrx * nx + vry * ny + vrz * nz
    # tangential relative velocity at the contact point
    cx = wsy * nz - wsz * ny
    cy = wsz * nx - wsx * nz
    cz = wsx * ny - wsy * nx
    vtx = vrx - vn * nx - cx
    vty = vry - vn * ny - cy
    vtz = vrz - vn * nz - cz
    fn = 0.0
    fc = 0.0
    kt_eff = 0.0
    damp_t = 0.0
    mu_s = 0.0
    mu_d = 0.0
    if model == CONTACT_HOOKE:
        kn = cp[0]
        eta = 2.0 * cp[2] * sqkm
        fc = kn * delta
        fn = fc - eta * vn
        kt_eff = cp[1]
        damp_t = cp[3] * eta
        mu_s = cp[4]
        mu_d = cp[4]
        w2 = kn * invm
        dr = eta * invm
    else:
        if wall:
            eps = delta / ri
            a2 = ri * ri - d * d
            dadd = 2.0 * d  # d(a^2)/d(delta) = -d(a^2)/dd
            deps = 1.0 / ri
        else:
            rs = ri + rj
            eps = delta / rs
            li = 0.5 * (d + (ri * ri - rj * rj) / d)
            a2 = ri * ri - li * li
            dli = 0.5 * (1.0 - (ri * ri - rj * rj) / (d * d))
            dadd = 2.0 * li * dli
            deps = 1.0 / rs
        if a2 < 0.0:
            a2 = 0.0
        area = math.pi * a2
        p = cp[1]
        ep = fast_pow(eps, p)
        fc = cp[0] * ep * area
        fn = fc - cp[2] * vn * area
        bonded = cp[10] != 0.0 and eps >= cp[6]
        if bonded:
            fn -= cp[3] * fast_pow(eps, cp[5]) * area
        if cp[11] != 0.0:
            kt_eff = cp[7] * area
            mu_s = cp[8]
            mu_d = cp[9]
        else:
            mu_s = np.inf  # bond without friction: no slip limit
        if bonded:
            kt_eff += cp[4] * area
        # stiffness for the time-step estimate: dF/d(delta)
        kk = cp[0] * (p * fast_pow(eps, p - 1.0) * deps * area + ep * math.pi * dadd)
        w2 = kk / meff
        dr = cp[2] * area / meff
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    tfx = 0.0
    tfy = 0.0
    tfz = 0.0
    if kt_eff > 0.0:
        # project the stored spring onto the current tangent plane (as LAMMPS
        # gran/hooke/history does; the length change is second order in the rotation)
        sn = sx * nx + sy * ny + sz * nz
        sx -= sn * nx
        sy -= sn * ny
        sz -= sn * nz
        sx += vtx * dt
        sy += vty * dt
        sz += vtz * dt
        tfx = -kt_eff * sx - damp_t * vtx
        tfy = -kt_eff * sy - damp_t * vty
        tfz = -kt_eff * sz - damp_t * vtz
        ft2 = tfx * tfx + tfy * tfy + tfz * tfz
        if model == CONTACT_HOOKE:
            flim = mu_s * abs(fn)
            fslip = flim
        else:
            flim = mu_s * abs(fc)
            fslip = mu_d * abs(fc)
        if ft2 > flim * flim:
            ft = math.sqrt(ft2)
            if ft > 0.0:
                sc = fslip / ft
                tfx *= sc
                tfy *= sc
                tfz *= sc
            if model == CONTACT_HOOKE:
                # LAMMPS: spring consistent with the capped force
                sx = -(tfx + damp_t * vtx) / kt_eff
                sy = -(tfy + damp_t * vty) / kt_eff
                sz = -(tfz + damp_t * vtz) / kt_eff
            else:
                sx = -tfx / kt_eff
                sy = -tfy / kt_eff
                sz = -tfz / kt_eff
        fx += tfx
        fy += tfy
        fz += tfz
    return fx, fy, fz, tfx, tfy, tfz, sx, sy, sz, w2, dr


@njit(cache=True, inline="always")
def _hooke_mass_terms(model, cp, meff):
    """``(sqrt(kn meff), 1 / meff)`` of the Hooke law (kg/s, 1/kg) for the effective mass ``meff`` (kg);
    zeros for the other laws, which do not use them.  One square root and one division, the hot path's
    cost per contact: :func:`_pair_rows` computes them once per row for partners of the row's mass."""
    if model == CONTACT_HOOKE:
        return math.sqrt(cp[0] * meff), 1.0 / meff
    return 0.0, 0.0


@njit(cache=True)
def _pair_rows(i0, i1, pos, vel, omega, radius, mass, charge, start, nbj, shift, hist,
               force, torque, model, cp, laws, rotation, dt, diag, jlim, hforce, htorque):
    """Pair forces of the list rows ``i0 <= i < i1`` (partners j anywhere).

    ``laws``: the non-contact law table of :mod:`sim.forces.nearfield` (L, LAW_WIDTH), summed
    for every listed pair; L = 0 for contact only.

    A partner's share goes to ``force[j]``, ``torque[j]`` when ``j < jlim`` and to ``hforce[j]``,
    ``htorque[j]`` otherwise (the threaded kernel, :func:`pair_forces_parallel`: a thread writes only
    the rows it owns and a halo buffer; the serial kernel gives ``jlim = n``, so the same arithmetic).
    """
    far_laws = laws.shape[0] > 0
    nl = laws.shape[0]
    tuple_laws = nl <= MAX_TUPLE_LAWS
    codes, lparams = law_tuples(laws)
    c = param_tuple(cp)
    ncontact = 0
    for i in range(i0, i1):
        k0 = start[i]
        k1 = start[i + 1]
        if k0 == k1:
            continue  # no partners: adding zero forces is a no-op (up to the sign of a zero)
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        ri = radius[i]
        mi = mass[i]
        # the effective mass with a touching partner of the same mass and its Hooke terms, computed at the
        # row's first such contact and reused: the same expressions as per pair, so bit for bit the same
        # values (equal-mass packings: every pair); lazily, so rows without contacts pay nothing
        have_ii = False
        meff_ii = 0.0
        sq_ii = 0.0
        inv_ii = 0.0
        vxi = vel[i, 0]
        vyi = vel[i, 1]
        vzi = vel[i, 2]
        fxi = 0.0
        fyi = 0.0
        fzi = 0.0
        txi = 0.0
        tyi = 0.0
        tzi = 0.0
        for k in range(k0, k1):
            j = nbj[k]
            dx = xi - pos[j, 0] + shift[k, 0]
            dy = yi - pos[j, 1] + shift[k, 1]
            dz = zi - pos[j, 2] + shift[k, 2]
            rsq = dx * dx + dy * dy + dz * dz
            rj = radius[j]
            rs = ri + rj
            fx = 0.0
            fy = 0.0
            fz = 0.0
            touching = model != CONTACT_NONE and rsq < rs * rs
            if not touching and not far_laws:
                if hist[k, 0] != 0.0 or hist[k, 1] != 0.0 or hist[k, 2] != 0.0:
                    hist[k, 0] = 0.0
                    hist[k, 1] = 0.0
                    hist[k, 2] = 0.0
                continue
            r = math.sqrt(rsq)
            inv = 1.0 / r
            nx = dx * inv
            ny = dy * inv
            nz = dz * inv
            if touching:
                ncontact += 1
                delta = rs - r
                rmin = ri if ri < rj else rj
                ov = delta / rmin
                if ov > diag[0]:
                    diag[0] = ov
                    diag[1] = i
                mj = mass[j]
                if mj == mi:
                    if not have_ii:
                        meff_ii = mi * mj / (mi + mj)
                        sq_ii, inv_ii = _hooke_mass_terms(model, c, meff_ii)
                        have_ii = True
                    meff = meff_ii
                    sqkm = sq_ii
                    invm = inv_ii
                else:
                    meff = mi * mj / (mi + mj)
                    sqkm, invm = _hooke_mass_terms(model, c, meff)
                vrx = vxi - vel[j, 0]
                vry = vyi - vel[j, 1]
                vrz = vzi - vel[j, 2]
                if rotation:
                    wsx = ri * omega[i, 0] + rj * omega[j, 0]
                    wsy = ri * omega[i, 1] + rj * omega[j, 1]
                    wsz = ri * omega[i, 2] + rj * omega[j, 2]
                else:
                    wsx = 0.0
                    wsy = 0.0
                    wsz = 0.0
                fx, fy, fz, tfx, tfy, tfz, sx, sy, sz, w2, dr = _law(model, c, delta, nx, ny, nz, r, ri, rj, False,
                                                                     meff, sqkm, invm, vrx, vry, vrz, wsx, wsy, wsz,
                                                                     hist[k, 0], hist[k, 1], hist[k, 2], dt)
                hist[k, 0] = sx
                hist[k, 1] = sy
                hist[k, 2] = sz
                if w2 > diag[2]:
                    diag[2] = w2
                if dr > diag[3]:
                    diag[3] = dr
                if rotation:
                    # torque = (-R n) x F_t on i and (R_j n) x (-F_t) on j
                    cx = ny * tfz - nz * tfy
                    cy = nz * tfx - nx * tfz
                    cz = nx * tfy - ny * tfx
                    txi -= ri * cx
                    tyi -= ri * cy
                    tzi -= ri * cz
                    if j < jlim:
                        torque[j, 0] -= rj * cx
                        torque[j, 1] -= rj * cy
                        torque[j, 2] -= rj * cz
                    else:
                        htorque[j, 0] -= rj * cx
                        htorque[j, 1] -= rj * cy
                        htorque[j, 2] -= rj * cz
            elif hist[k, 0] != 0.0 or hist[k, 1] != 0.0 or hist[k, 2] != 0.0:
                hist[k, 0] = 0.0
                hist[k, 1] = 0.0
                hist[k, 2] = 0.0
            if far_laws:
                if tuple_laws:
                    fm = pair_law_force_t(nl, codes, lparams, r, ri, rj, charge[i], charge[j])
                else:
                    fm = pair_law_force(laws, r, ri, rj, charge[i], charge[j])
                fx += fm * nx
                fy += fm * ny
                fz += fm * nz
            fxi += fx
            fyi += fy
            fzi += fz
            if j < jlim:
                force[j, 0] -= fx
                force[j, 1] -= fy
                force[j, 2] -= fz
            else:
                hforce[j, 0] -= fx
                hforce[j, 1] -= fy
                hforce[j, 2] -= fz
        force[i, 0] += fxi
        force[i, 1] += fyi
        force[i, 2] += fzi
        if rotation:
            torque[i, 0] += txi
            torque[i, 1] += tyi
            torque[i, 2] += tzi
    diag[4] += ncontact


@njit(cache=True)
def pair_forces(pos, vel, omega, radius, mass, charge, start, nbj, shift, hist,
                force, torque, model, cp, laws, rotation, dt, diag):
    """Accumulate all particle-particle forces over a half neighbour list.

    ``force`` and ``torque`` (N, 3) are added to (not cleared); ``model`` is the contact law
    code with parameters ``cp``; ``laws`` the non-contact law table.  ``diag`` (5,)
    receives max overlap ratio, its particle, max k/m, max eta/m, contacts.
    """
    _pair_rows(0, pos.shape[0], pos, vel, omega, radius, mass, charge, start, nbj, shift, hist,
               force, torque, model, cp, laws, rotation, dt, diag, pos.shape[0], force, torque)


@njit(cache=True)
def thread_blocks(start, nbj, nt):
    """Split a half neighbour list into ``nt`` blocks of consecutive rows for :func:`pair_forces_parallel`.

    Returns ``(rows, halo_start, halo_idx)``: block t holds the rows ``rows[t] <= i < rows[t + 1]``
    (about equal cost, counted as one per row plus one per listed pair), and ``halo_idx[halo_start[t]:
    halo_start[t + 1]]`` are the distinct partners ``j >= rows[t + 1]`` of its rows, in first-seen
    order: the only rows of another block that block t writes (a half list has ``j > i``).
    """
    n = start.shape[0] - 1
    rows = np.empty(nt + 1, dtype=np.int64)
    rows[0] = 0
    rows[nt] = n
    total = start[n] + n
    i = 0
    for t in range(1, nt):
        goal = (t * total) // nt
        while i < n and start[i] + i < goal:
            i += 1
        rows[t] = i
    halo_start = np.zeros(nt + 1, dtype=np.int64)
    halo_idx = np.empty(start[n], dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    q = 0
    for t in range(nt - 1):
        lim = rows[t + 1]
        for k in range(start[rows[t]], start[lim]):
            j = nbj[k]
            if j >= lim and mark[j] != t:
                mark[j] = t
                halo_idx[q] = j
                q += 1
        halo_start[t + 1] = q
    halo_start[nt] = q
    return rows, halo_start, halo_idx[:q]


@njit(cache=True, parallel=True)
def pair_forces_parallel(rows, halo_start, halo_idx, pos, vel, omega, radius, mass, charge, start, nbj, shift,
                         hist, force, torque, model, cp, laws, rotation, dt, diag, fbuf, tbuf, dbuf, pairs,
                         walls, whist, cpw, wall_contacts):
    """Threaded pair forces (``pairs``) and wall contact forces (``wall_contacts``), added to ``force``
    and ``torque``, over the blocks of :func:`thread_blocks` (``T = rows.shape[0] - 1`` threads).

    Thread t owns the rows of its block: it adds their pair sums and their shares of pairs with partners
    in the block straight into ``force``/``torque``, and its shares for partners of later blocks into its
    halo buffers ``fbuf[t]``, ``tbuf[t]`` ((T, N, 3), zero on entry and left zero: only the rows in its
    halo list are added to ``force`` afterwards and cleared); the wall contacts of its own particles follow.
    Contact history entries belong to one row, and wall history to one particle, so no two threads write
    the same memory.  ``dbuf`` (2T, D_SIZE): per-thread pair and wall diagnostics, combined in a fixed order.
    The result is deterministic for a given T and list; it differs from the serial sums only by the order
    of the additions (round-off).
    """
    nt = rows.shape[0] - 1
    nw = walls.shape[0]
    for t in prange(nt):
        i0 = rows[t]
        i1 = rows[t + 1]
        for k in range(D_SIZE):
            dbuf[t, k] = 0.0
            dbuf[nt + t, k] = 0.0
        if i1 > i0:
            if pairs:
                _pair_rows(i0, i1, pos, vel, omega, radius, mass, charge, start, nbj, shift, hist, force, torque,
                           model, cp, laws, rotation, dt, dbuf[t], i1, fbuf[t], tbuf[t])
            if wall_contacts:
                # the wall kernel on this block's particles (slices: its particle index is local)
                wall_forces(pos[i0:i1], vel[i0:i1], omega[i0:i1], radius[i0:i1], mass[i0:i1], walls,
                            whist[i0 * nw:i1 * nw], force[i0:i1], torque[i0:i1], model, cpw, rotation, dt,
                            dbuf[nt + t])
                dbuf[nt + t, D_MAX_OVERLAP_I] += i0
    for t in range(nt - 1):
        hf = fbuf[t]
        ht = tbuf[t]
        for q in range(halo_start[t], halo_start[t + 1]):
            j = halo_idx[q]
            for c in range(3):
                force[j, c] += hf[j, c]
                hf[j, c] = 0.0
            if rotation:
                for c in range(3):
                    torque[j, c] += ht[j, c]
                    ht[j, c] = 0.0
    # pairs before walls, blocks in order: the serial kernel's order of the strict maxima
    for t in range(2 * nt):
        if dbuf[t, D_MAX_OVERLAP] > diag[D_MAX_OVERLAP]:
            diag[D_MAX_OVERLAP] = dbuf[t, D_MAX_OVERLAP]
            diag[D_MAX_OVERLAP_I] = dbuf[t, D_MAX_OVERLAP_I]
        if dbuf[t, D_MAX_W2] > diag[D_MAX_W2]:
            diag[D_MAX_W2] = dbuf[t, D_MAX_W2]
        if dbuf[t, D_MAX_DAMP] > diag[D_MAX_DAMP]:
            diag[D_MAX_DAMP] = dbuf[t, D_MAX_DAMP]
        diag[D_N_CONTACTS] += dbuf[t, D_N_CONTACTS]


@njit(cache=True, inline="always")
def wall_contact(model, c, d, ri, mi, sqkm, invm, vx, vy, vz, ox, oy, oz, nx, ny, nz, sx, sy, sz, rotation, dt):
    """Contact of a sphere (radius ``ri``, mass ``mi``, velocity ``v``, angular velocity ``o``,
    tangential spring ``s``) whose centre is ``d`` from a wall plane of inward normal ``n``; call it
    only when ``d < ri``.  ``c``: :func:`param_tuple`; ``sqkm, invm``: :func:`_hooke_mass_terms` of
    ``mi`` (the wall's effective mass is the sphere's).  Returns ``(fx, fy, fz, tx, ty, tz, sx, sy, sz,
    w2, dr)``: force, torque, updated spring and the time-step diagnostics of :func:`_law`."""
    delta = ri - d
    dd = d if d > 0.0 else 0.0
    if rotation:
        wsx = ri * ox
        wsy = ri * oy
        wsz = ri * oz
    else:
        wsx = 0.0
        wsy = 0.0
        wsz = 0.0
    fx, fy, fz, tfx, tfy, tfz, sx, sy, sz, w2, dr = _law(model, c, delta, nx, ny, nz, dd, ri, 0.0, True, mi,
                                                         sqkm, invm, vx, vy, vz, wsx, wsy, wsz, sx, sy, sz, dt)
    tx = 0.0
    ty = 0.0
    tz = 0.0
    if rotation:
        tx = ri * (ny * tfz - nz * tfy)
        ty = ri * (nz * tfx - nx * tfz)
        tz = ri * (nx * tfy - ny * tfx)
    return fx, fy, fz, tx, ty, tz, sx, sy, sz, w2, dr


@njit(cache=True)
def wall_forces(pos, vel, omega, radius, mass, walls, whist, force, torque, model, cp,
                rotation, dt, diag):
    """Forces from plane walls.  ``walls`` (W, 6): a point on the plane and its
    unit normal pointing into the domain.  ``whist`` (N*W, 3) tangential springs
    (row ``i*W + w``).  A particle touches wall w when its centre is closer than
    its radius to the plane (or behind it).  Every stepper of :mod:`sim.dem`
    calls this function: the wall law has one copy."""
    n = pos.shape[0]
    nw = walls.shape[0]
    c = param_tuple(cp)
    ncontact = 0
    # the Hooke mass terms of the last mass seen: recomputed only when the mass changes (equal-mass
    # packings: once), the same values bit for bit
    m_last = np.nan
    sqkm = 0.0
    invm = 0.0
    for w in range(nw):
        px = walls[w, 0]
        py = walls[w, 1]
        pz = walls[w, 2]
        nx = walls[w, 3]
        ny = walls[w, 4]
        nz = walls[w, 5]
        for i in range(n):
            d = (pos[i, 0] - px) * nx + (pos[i, 1] - py) * ny + (pos[i, 2] - pz) * nz
            ri = radius[i]
            k = i * nw + w
            if d >= ri:
                if whist[k, 0] != 0.0 or whist[k, 1] != 0.0 or whist[k, 2] != 0.0:
                    whist[k, 0] = 0.0
                    whist[k, 1] = 0.0
                    whist[k, 2] = 0.0
                continue
            ncontact += 1
            ov = (ri - d) / ri
            if ov > diag[0]:
                diag[0] = ov
                diag[1] = i
            mi = mass[i]
            if mi != m_last:
                sqkm, invm = _hooke_mass_terms(model, c, mi)
                m_last = mi
            fx, fy, fz, tx, ty, tz, sx, sy, sz, w2, dr = wall_contact(
                model, c, d, ri, mi, sqkm, invm, vel[i, 0], vel[i, 1], vel[i, 2], omega[i, 0], omega[i, 1], omega[i, 2],
                nx, ny, nz, whist[k, 0], whist[k, 1], whist[k, 2], rotation, dt)
            whist[k, 0] = sx
            whist[k, 1] = sy
            whist[k, 2] = sz
            if w2 > diag[2]:
                diag[2] = w2
            if dr > diag[3]:
                diag[3] = dr
            force[i, 0] += fx
            force[i, 1] += fy
            force[i, 2] += fz
            if rotation:
                torque[i, 0] -= tx
                torque[i, 1] -= ty
                torque[i, 2] -= tz
    diag[4] += ncontact


def hooke_params(kn, restitution, kt=None, mu=0.0, damp_t_ratio=0.5):
    """Parameter array of the Hooke/Coulomb law (``kt`` defaults to 2/7 kn)."""
    kt = 2.0 / 7.0 * kn if kt is None else kt
    return np.array([kn, kt, restitution_beta(restitution), damp_t_ratio, mu], dtype=np.float64)


def power_params(K, p=2.0, c_cd=0.0, K_nb=0.0, K_rb=0.0, p_b=2.0, eps_star=np.inf, K_f=0.0,
                 mu_s=0.0, mu_d=0.0, bonding=False, friction=False):
    """Parameter array of the seed's power-law law (see module docstring)."""
    return np.array([K, p, c_cd, K_nb, K_rb, p_b, eps_star, K_f, mu_s, mu_d,
                     1.0 if bonding else 0.0, 1.0 if friction else 0.0], dtype=np.float64)


def contact_force_pair(model, cp, xi, xj, ri, rj, mi, mj, vi=(0, 0, 0), vj=(0, 0, 0),
                       wi=(0, 0, 0), wj=(0, 0, 0), dt=1e-6, hist=None):
    """Force on particle i from one contact with j (Python helper for tests/hand checks).

    Returns ``(force_i (3,), force_j (3,), torque_i (3,), torque_j (3,), history (3,))``.
    """
    pos = np.array([xi, xj], dtype=np.float64)
    vel = np.array([vi, vj], dtype=np.float64)
    om = np.array([wi, wj], dtype=np.float64)
    rad = np.array([ri, rj], dtype=np.float64)
    mass = np.array([mi, mj], dtype=np.float64)
    start = np.array([0, 1, 1], dtype=np.int64)
    nbj = np.array([1], dtype=np.int64)
    shift = np.zeros((1, 3))
    h = np.zeros((1, 3)) if hist is None else np.array(hist, dtype=np.float64).reshape(1, 3)
    f = np.zeros((2, 3))
    t = np.zeros((2, 3))
    diag = np.zeros(D_SIZE)
    pair_forces(pos, vel, om, rad, mass, np.zeros(2), start, nbj, shift, h, f, t, int(model),
                np.asarray(cp, dtype=np.float64), np.zeros((0, LAW_WIDTH)), True, float(dt), diag)
    return f[0], f[1], t[0], t[1], h[0]
