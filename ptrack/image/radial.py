"""Centres of images that are not Gaussian blobs: radial symmetry (Parthasarathy 2012).

A defocused brightfield particle is a bright centre in a dark ring, or a dark
centre in a bright ring; a defocused fluorescent bead is a ring. A Gaussian
fit of such an image lands beside it (on the ring). The radial-symmetry
centre assumes only that the image is rotationally symmetric: every
intensity gradient points at the centre, so the centre is the point closest
(weighted least squares) to all the lines through the pixel-corner
gradients (R. Parthasarathy, Nature Methods 9, 724, 2012). It is closed-form
(no iterations, no model), polarity-free and ~1.1-1.5x the Cramer-Rao bound
on blobs and rings alike.

The uncertainty reported is the least-squares one: the weighted scatter of
the gradient lines about the centre times the inverse normal matrix.

The radial-symmetry centre uses a window of fixed size and weights the
gradients by 1 / distance, so the outer parts of a large ring or halo count
little (measured 2-3x the bound on 6-9 px rings). :func:`profile_centres`
then fits the image with a free radial profile (a cubic B-spline of the
radius) about a free centre, over the image's full extent measured from the
data (:func:`image_extent`): 1.1-1.2x the bound on rings and bright centres
in dark rings, where the Gaussian fit or the radial-symmetry centre are
1.5-3x. :func:`has_dip` tells an image a Gaussian does not describe (a ring
of the opposite sign around the centre).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .fit import _chol, _chol_inv_diag, _chol_solve

__all__ = ["radial_centres", "profile_centres", "image_extent", "has_dip"]


@nb.njit(cache=True)
def _radial_one(img, r, c, half, out):
    h, w = img.shape
    r0 = max(0, r - half)
    r1 = min(h - 1, r + half)
    c0 = max(0, c - half)
    c1 = min(w - 1, c + half)
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    if nr < 4 or nc < 4:
        return False
    # gradients at the pixel corners (r + 1/2, c + 1/2) from the 2x2 neighbourhood
    gx = np.empty((nr - 1, nc - 1))
    gy = np.empty((nr - 1, nc - 1))
    for i in range(nr - 1):
        for j in range(nc - 1):
            a = float(img[r0 + i, c0 + j])
            b = float(img[r0 + i, c0 + j + 1])
            cc = float(img[r0 + i + 1, c0 + j])
            d = float(img[r0 + i + 1, c0 + j + 1])
            gx[i, j] = 0.5 * ((b - a) + (d - cc))
            gy[i, j] = 0.5 * ((cc - a) + (d - b))
    # 3x3 box smoothing of the gradients (as Parthasarathy): less noise in the line directions
    sx = np.zeros_like(gx)
    sy = np.zeros_like(gy)
    m, n = gx.shape
    for i in range(m):
        for j in range(n):
            ax = 0.0
            ay = 0.0
            k = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii = i + di
                    jj = j + dj
                    if 0 <= ii < m and 0 <= jj < n:
                        ax += gx[ii, jj]
                        ay += gy[ii, jj]
                        k += 1
            sx[i, j] = ax / k
            sy[i, j] = ay / k
    # starting point: the gradient-magnitude-weighted centroid
    sw = 0.0
    xc = 0.0
    yc = 0.0
    for i in range(m):
        for j in range(n):
            g2 = sx[i, j] ** 2 + sy[i, j] ** 2
            sw += g2
            xc += g2 * (c0 + j + 0.5)
            yc += g2 * (r0 + i + 0.5)
    if sw <= 0:
        return False
    xc /= sw
    yc /= sw
    for _ in range(2):          # weights by distance to the current centre: 1 refinement
        a11 = 0.0
        a12 = 0.0
        a22 = 0.0
        b1 = 0.0
        b2 = 0.0
        wsum = 0.0
        for i in range(m):
            for j in range(n):
                g2 = sx[i, j] ** 2 + sy[i, j] ** 2
                if g2 <= 0:
                    continue
                px = c0 + j + 0.5
                py = r0 + i + 0.5
                dist = math.sqrt((px - xc) ** 2 + (py - yc) ** 2) + 0.5
                wgt = g2 / dist
                ux = sx[i, j] / math.sqrt(g2)
                uy = sy[i, j] / math.sqrt(g2)
                # projector onto the normal of the line: I - u u^T
                p11 = 1.0 - ux * ux
                p12 = -ux * uy
                p22 = 1.0 - uy * uy
                a11 += wgt * p11
                a12 += wgt * p12
                a22 += wgt * p22
                b1 += wgt * (p11 * px + p12 * py)
                b2 += wgt * (p12 * px + p22 * py)
                wsum += wgt
        det = a11 * a22 - a12 * a12
        if det <= 1e-12 * (a11 + a22) ** 2 or wsum <= 0:
            return False
        xc = (a22 * b1 - a12 * b2) / det
        yc = (a11 * b2 - a12 * b1) / det
    # residual: weighted squared distances of the lines from the centre
    rss = 0.0
    cnt = 0
    for i in range(m):
        for j in range(n):
            g2 = sx[i, j] ** 2 + sy[i, j] ** 2
            if g2 <= 0:
                continue
            px = c0 + j + 0.5
            py = r0 + i + 0.5
            dist = math.sqrt((px - xc) ** 2 + (py - yc) ** 2) + 0.5
            wgt = g2 / dist
            ux = sx[i, j] / math.sqrt(g2)
            uy = sy[i, j] / math.sqrt(g2)
            cr = (xc - px) * uy - (yc - py) * ux
            rss += wgt * cr * cr
            cnt += 1
    # weighted least-squares variance; the 3x3 smoothing correlates neighbouring lines, which this
    # ignores (measured on rings and blobs: within ~1.5x of the scatter, see tests/test_real_images.py)
    s2 = rss / max(cnt - 2.0, 1.0)
    out[0] = xc
    out[1] = yc
    out[2] = s2 * a22 / det
    out[3] = s2 * a11 / det
    return abs(xc - c) <= half and abs(yc - r) <= half


@nb.njit(cache=True)
def _radial_all(img, rows, cols, halves, res, ok):
    out = np.empty(4)
    for k in range(rows.shape[0]):
        ok[k] = _radial_one(img, rows[k], cols[k], halves[k], out)
        res[k, :] = out


def radial_centres(img, rows, cols, half):
    """Radial-symmetry centres of the images around (rows, cols).

    Parameters
    ----------
    img : 2D array
        Frame (any polarity, background need not be removed).
    rows, cols : array_like of int
        Starting pixels.
    half : int or array_like of int
        Half-width of each square window (px); it should hold the whole
        image, rings included (about 3x the image's scale).

    Returns
    -------
    dict of ndarrays
        ``x``, ``y`` (px), ``var_x``, ``var_y`` (px^2, least-squares
        uncertainty), ``ok`` (bool).
    """
    rows = np.ascontiguousarray(rows, np.int64)
    cols = np.ascontiguousarray(cols, np.int64)
    halves = np.broadcast_to(np.asarray(half, np.int64), rows.shape).copy()
    img = np.ascontiguousarray(img)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        img = img.astype(np.float32)
    res = np.zeros((len(rows), 4))
    ok = np.zeros(len(rows), np.bool_)
    if len(rows):
        _radial_all(img, rows, cols, halves, res, ok)
    return {"x": res[:, 0], "y": res[:, 1], "var_x": res[:, 2], "var_y": res[:, 3], "ok": ok}


# ---------------------------------------------------------------------------------------------
# centre-symmetric least-squares fit: a free radial profile (cubic B-spline) around a free centre
# ---------------------------------------------------------------------------------------------

@nb.njit(cache=True, inline="always")
def _bspline(t):
    # centred cubic B-spline and its derivative
    a = abs(t)
    if a < 1.0:
        v = 2.0 / 3.0 - a * a + 0.5 * a * a * a
        d = -2.0 * a + 1.5 * a * a
    elif a < 2.0:
        u = 2.0 - a
        v = u * u * u / 6.0
        d = -0.5 * u * u
    else:
        return 0.0, 0.0
    return v, (d if t >= 0 else -d)


# Gauss-Newton steps of the profile fit, and the damped steps allowed after them to a fit that has not converged
# (a fit still moving after 8 steps oscillates about its optimum, the profile refitted to the noise as the centre
# moves. Damping from step 12 instead of 40 cut the steps of bright centres in dark rings by 30 % at the same
# accuracy; from step 8 instead of 12, the real movie's profile fits (a third of them still moving at step 12) took
# 11 % less time, and the fits it changed on the image-model cases are as close to the truth: RMS error 0.2936 ->
# 0.2939 px over 149 of them at bf z=+1.5, 0.1458 -> 0.1442 px over 110 at fluor z=+6, the rest within 1 %)
_MAX_ITER = 8
_DAMPED_ITER = 40
# a fit stops at a step of the centre below this share of its standard error: the last Gauss-Newton steps shrink
# linearly (the profile is refitted to the noise as the centre moves, at a rate ~1/2 per step), so the error left
# is about one step: 10 % of the standard error adds ~1 % to the variance (5 % took 15 % more steps for the same
# RMSE on the image-model cases)
_STOP = 0.1


@nb.njit(cache=True)
def _profile_one(img, r, c, half, x0, y0, n2, gw, out):
    # image = P(|p - centre|) + background terms over the pixels within `half` of the start (x0, y0);
    # P an even cubic B-spline with 1 px knots (coefficients c_|j|); background: a gradient and the two
    # quadratic terms a radial profile cannot absorb (x^2 - y^2, x y: curved illumination, dust).
    # Gauss-Newton on the centre and the (linear) rest jointly; covariance s^2 (J^T J)^-1
    h, w = img.shape
    if r - half < 0 or c - half < 0 or r + half >= h or c + half >= w:
        return False
    K = int(half) + 3                   # profile coefficients c_0 .. c_{K-1}
    NL = K + 4                          # linear parameters: profile, gx, gy, qa, qb
    IX = NL
    IY = NL + 1
    npar = NL + 2
    rad2 = (half - 0.5) ** 2
    hq = 1.0 / (half * half)
    w_bg = 1.0 / (n2 + 0.0)
    # the pixels within the disc about the start (fixed over the iterations), in raster order
    n_in = 0
    pi_ = np.empty((2 * half + 1) * (2 * half + 1), np.int64)
    pj_ = np.empty((2 * half + 1) * (2 * half + 1), np.int64)
    for i in range(r - half, r + half + 1):
        for j in range(c - half, c + half + 1):
            if not (j - x0) ** 2 + (i - y0) ** 2 > rad2:
                pi_[n_in] = i
                pj_[n_in] = j
                n_in += 1
    xc = x0
    yc = y0
    # each pixel's radius, first knot, whether it is the full case, and its four B-splines and their derivatives
    BR = np.empty(n_in)
    BK = np.empty(n_in, np.int64)
    BF = np.empty(n_in, np.bool_)
    BV = np.empty((n_in, 8))
    theta = np.zeros(npar)
    A = np.empty((npar, npar))
    rhs = np.empty((npar, 3))
    sol = np.empty((npar, 3))
    A0 = np.empty((npar, npar))
    ysc = np.empty(npar)
    idx = np.empty(8, np.int64)
    val = np.empty(8)
    ok = False
    rss = 0.0
    npix = 0
    st = 1.0
    sd = 0.0
    it = 0
    damp = 1.0
    px_ = 0.0
    py_ = 0.0
    for it in range(_MAX_ITER + _DAMPED_ITER):
        A[:, :] = 0.0
        rhs[:, :] = 0.0
        rss = 0.0
        npix = 0
        r0_ = r1_ = r2_ = r3_ = rx_ = ry_ = 0.0
        a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
        x0_ = x1_ = x2_ = x3_ = y0_ = y1_ = y2_ = y3_ = axx = axy = ayy = 0.0
        # two passes over the pixels: the radius, first knot and four B-splines of each (independent of each
        # other), then the model, residual and normal-equation sums from them in the same order (the same
        # arithmetic as one pass; 9 % faster on the real movie's profile fits)
        for p_ in range(n_in):
            dx = pj_[p_] - xc
            dy = pi_[p_] - yc
            rho = math.sqrt(dx * dx + dy * dy)
            k0 = int(math.floor(rho)) - 1
            BR[p_] = rho
            BK[p_] = k0
            fl = False
            if k0 >= 0 and k0 + 3 < K:
                v0, d0 = _bspline(rho - k0)
                v1, d1 = _bspline(rho - (k0 + 1))
                v2, d2 = _bspline(rho - (k0 + 2))
                v3, d3 = _bspline(rho - (k0 + 3))
                BV[p_, 0] = v0
                BV[p_, 1] = v1
                BV[p_, 2] = v2
                BV[p_, 3] = v3
                BV[p_, 4] = d0
                BV[p_, 5] = d1
                BV[p_, 6] = d2
                BV[p_, 7] = d3
                fl = not ((v0 == 0.0 and d0 == 0.0) or (v1 == 0.0 and d1 == 0.0) or
                          (v2 == 0.0 and d2 == 0.0) or (v3 == 0.0 and d3 == 0.0))
            BF[p_] = fl
        for p_ in range(n_in):
            # (the usual case, full: rho >= 1, so no mirrored knot, and all four coefficients k0..k0 + 3
            # inside the profile and nonzero, the four B-splines summed as the loop below does; else that loop,
            # which folds the mirrored knots)
            i = pi_[p_]
            j = pj_[p_]
            dx = j - xc
            dy = i - yc
            rho = BR[p_]
            k0 = BK[p_]
            m = 0.0
            dp = 0.0
            nz = 0
            full = BF[p_]
            v0 = BV[p_, 0]
            v1 = BV[p_, 1]
            v2 = BV[p_, 2]
            v3 = BV[p_, 3]
            d0 = BV[p_, 4]
            d1 = BV[p_, 5]
            d2 = BV[p_, 6]
            d3 = BV[p_, 7]
            if full:
                m += theta[k0] * v0
                dp += theta[k0] * d0
                m += theta[k0 + 1] * v1
                dp += theta[k0 + 1] * d1
                m += theta[k0 + 2] * v2
                dp += theta[k0 + 2] * d2
                m += theta[k0 + 3] * v3
                dp += theta[k0 + 3] * d3
            for jj in range(k0, k0 + 4 if not full else k0):
                v, d = _bspline(rho - jj)
                kk = abs(jj)
                if kk >= K or (v == 0.0 and d == 0.0):
                    continue
                # fold the mirrored knot onto its coefficient
                found = -1
                for q in range(nz):
                    if idx[q] == kk:
                        found = q
                if found >= 0:
                    val[found] += v
                else:
                    idx[nz] = kk
                    val[nz] = v
                    nz += 1
                m += theta[kk] * v
                dp += theta[kk] * d
            # the background terms: linear parameters K..K+3 with values l0..l3
            u = j - c
            t = i - r
            l0 = float(u)
            l1 = float(t)
            l2 = (u * u - t * t) * hq
            l3 = u * t * hq
            m += theta[K] * l0
            m += theta[K + 1] * l1
            m += theta[K + 2] * l2
            m += theta[K + 3] * l3
            res = float(img[i, j]) - m
            # weights: 1 / variance, the background's n2 plus the shot noise of the image (gw per count);
            # without shot noise (least-squares images, gw = 0) the constant 1 / n2, the same value without a
            # division in every pixel's chain of dependent operations (~18 % of the fit)
            wt = w_bg if gw == 0.0 else 1.0 / (n2 + gw * max(m, 0.0))
            rss += wt * res * res
            npix += 1
            # derivative of the model with respect to the centre: -P'(rho) (p - centre) / rho
            if rho > 1e-9:
                ddx = -dp * dx / rho
                ddy = -dp * dy / rho
            else:
                ddx = 0.0
                ddy = 0.0
            res *= wt
            ddxw = ddx * wt
            ddyw = ddy * wt
            # the normal equations' sums, each entry the same products in the same pixel order as a full
            # matrix's lower triangle (the Cholesky reads no other; mirrored below for the LU fallback).
            # Spline rows (indices < K, scattered by the knots) in A, their background and centre entries
            # in adjacent columns; the background rows' other entries, whose indices are fixed, and the
            # centre's in scalars (a scattered update through memory costs several times a register add)
            w0 = l0 * wt
            w1 = l1 * wt
            w2 = l2 * wt
            w3 = l3 * wt
            if full:
                # the same sums as the loop below, unrolled over the four consecutive coefficients
                a0 = A[k0]
                a1 = A[k0 + 1]
                a2 = A[k0 + 2]
                a3 = A[k0 + 3]
                rhs[k0, 0] += v0 * res
                rhs[k0 + 1, 0] += v1 * res
                rhs[k0 + 2, 0] += v2 * res
                rhs[k0 + 3, 0] += v3 * res
                vp0 = v0 * wt
                vp1 = v1 * wt
                vp2 = v2 * wt
                vp3 = v3 * wt
                a0[k0] += vp0 * v0
                a1[k0] += vp1 * v0
                a1[k0 + 1] += vp1 * v1
                a2[k0] += vp2 * v0
                a2[k0 + 1] += vp2 * v1
                a2[k0 + 2] += vp2 * v2
                a3[k0] += vp3 * v0
                a3[k0 + 1] += vp3 * v1
                a3[k0 + 2] += vp3 * v2
                a3[k0 + 3] += vp3 * v3
                a0[K] += w0 * v0
                a0[K + 1] += w1 * v0
                a0[K + 2] += w2 * v0
                a0[K + 3] += w3 * v0
                a0[IX] += vp0 * ddx
                a0[IY] += vp0 * ddy
                a1[K] += w0 * v1
                a1[K + 1] += w1 * v1
                a1[K + 2] += w2 * v1
                a1[K + 3] += w3 * v1
                a1[IX] += vp1 * ddx
                a1[IY] += vp1 * ddy
                a2[K] += w0 * v2
                a2[K + 1] += w1 * v2
                a2[K + 2] += w2 * v2
                a2[K + 3] += w3 * v2
                a2[IX] += vp2 * ddx
                a2[IY] += vp2 * ddy
                a3[K] += w0 * v3
                a3[K + 1] += w1 * v3
                a3[K + 2] += w2 * v3
                a3[K + 3] += w3 * v3
                a3[IX] += vp3 * ddx
                a3[IY] += vp3 * ddy
            for p in range(nz):
                ip = idx[p]
                v = val[p]
                rhs[ip, 0] += v * res
                vp = v * wt
                for q in range(nz):
                    iq = idx[q]
                    if iq <= ip:
                        A[ip, iq] += vp * val[q]
                # the background rows' spline entries (K + a, ip), summed in the spline row's adjacent
                # columns K..K+3 beside its centre entries (mirrored to the lower triangle below)
                A[ip, K] += w0 * v
                A[ip, K + 1] += w1 * v
                A[ip, K + 2] += w2 * v
                A[ip, K + 3] += w3 * v
                A[ip, IX] += vp * ddx
                A[ip, IY] += vp * ddy
            r0_ += l0 * res
            a00 += w0 * l0
            x0_ += w0 * ddx
            y0_ += w0 * ddy
            r1_ += l1 * res
            a10 += w1 * l0
            a11 += w1 * l1
            x1_ += w1 * ddx
            y1_ += w1 * ddy
            r2_ += l2 * res
            a20 += w2 * l0
            a21 += w2 * l1
            a22 += w2 * l2
            x2_ += w2 * ddx
            y2_ += w2 * ddy
            r3_ += l3 * res
            a30 += w3 * l0
            a31 += w3 * l1
            a32 += w3 * l2
            a33 += w3 * l3
            x3_ += w3 * ddx
            y3_ += w3 * ddy
            rx_ += ddx * res
            ry_ += ddy * res
            axx += ddxw * ddx
            axy += ddxw * ddy
            ayy += ddyw * ddy
        for q in range(K):
            for a in range(4):
                A[K + a, q] = A[q, K + a]
        rhs[K, 0] = r0_
        rhs[K + 1, 0] = r1_
        rhs[K + 2, 0] = r2_
        rhs[K + 3, 0] = r3_
        rhs[IX, 0] = rx_
        rhs[IY, 0] = ry_
        A[K, K] = a00
        A[K + 1, K] = a10
        A[K + 1, K + 1] = a11
        A[K + 2, K] = a20
        A[K + 2, K + 1] = a21
        A[K + 2, K + 2] = a22
        A[K + 3, K] = a30
        A[K + 3, K + 1] = a31
        A[K + 3, K + 2] = a32
        A[K + 3, K + 3] = a33
        A[K, IX] = x0_
        A[K + 1, IX] = x1_
        A[K + 2, IX] = x2_
        A[K + 3, IX] = x3_
        A[K, IY] = y0_
        A[K + 1, IY] = y1_
        A[K + 2, IY] = y2_
        A[K + 3, IY] = y3_
        A[IX, IX] = axx
        A[IX, IY] = axy
        A[IY, IY] = ayy
        if npix <= npar + 2:
            return False
        for q in range(NL):
            A[IX, q] = A[q, IX]
            A[IY, q] = A[q, IY]
        A[IY, IX] = A[IX, IY]
        if it == 0:
            # the profile is still zero: solve the linear part with the centre held
            for q in range(npar):
                A[IX, q] = 0.0
                A[q, IX] = 0.0
                A[IY, q] = 0.0
                A[q, IY] = 0.0
            A[IX, IX] = 1.0
            A[IY, IY] = 1.0
            rhs[IX, 0] = 0.0
            rhs[IY, 0] = 0.0
        for q in range(npar):
            A[q, q] += 1e-9 * A[q, q] + 1e-12
        A0[:, :] = A
        # the normal matrix is symmetric positive definite (regularised): an in-place Cholesky solve (a
        # general solve with pivoting, and its copies, cost ~40 % of the fit); LU only if it fails
        if _chol(A0, npar):
            _chol_solve(A0, rhs[:, 0], ysc, npar)
            sol[:, 0] = ysc
            sol[IX, 1] = _chol_inv_diag(A0, npar, IX, ysc)
            sol[IY, 2] = _chol_inv_diag(A0, npar, IY, ysc)
        else:
            for q in range(NL):             # the upper triangle of the linear block, for the general solve
                for q2 in range(q):
                    A[q2, q] = A[q, q2]
            rhs[IX, 1] = 1.0
            rhs[IY, 2] = 1.0
            sol[:, :] = np.linalg.solve(A, rhs)
        # a step of the centre of at most 1 px
        st = math.sqrt(sol[IX, 0] ** 2 + sol[IY, 0] ** 2)
        f = 1.0 if st <= 1.0 else 1.0 / st
        if it >= _MAX_ITER:
            # not converged in _MAX_ITER steps: the centre oscillates (the profile refitted to the noise as the
            # centre moves); each reversal of the step halves the steps from here on
            if sol[IX, 0] * px_ + sol[IY, 0] * py_ < 0:
                damp *= 0.5
            f *= damp
            st *= damp
        px_ = sol[IX, 0]
        py_ = sol[IY, 0]
        for q in range(NL):
            theta[q] += sol[q, 0]
        xc += f * sol[IX, 0]
        yc += f * sol[IY, 0]
        if abs(xc - x0) > 0.5 * half or abs(yc - y0) > 0.5 * half:
            return False
        if it > 0:
            s2 = rss / max(npix - npar, 1)
            out[2] = s2 * sol[IX, 1]
            out[3] = s2 * sol[IY, 2]
            sd = math.sqrt(max(0.5 * (out[2] + out[3]), 0.0))
            # noise makes the last steps shrink only linearly (the profile is refitted to the noise as
            # the centre moves): stop at a step of _STOP x the standard error
            if st < max(1e-4, _STOP * sd):
                ok = True
                break
    if not ok:
        return False
    out[0] = xc
    out[1] = yc
    out[4] = it
    return True


@nb.njit(cache=True)
def _profile_all(img, rows, cols, halves, x0, y0, n2, gw, res, ok, iters):
    out = np.empty(5)
    for k in range(rows.shape[0]):
        ok[k] = _profile_one(img, rows[k], cols[k], halves[k], x0[k], y0[k], n2[k], gw, out)
        if ok[k]:
            res[k, :] = out[:4]
            iters[k] = out[4]


def profile_centres(img, rows, cols, half, x0=None, y0=None, noise=1.0, shot: float = 0.0):
    """Centres of rotationally symmetric images by a least-squares fit of a free radial profile.

    The image around each start is modelled as ``P(|p - c|) + g . (p - p0)``:
    an arbitrary radial profile ``P`` (an even cubic B-spline with 1 px
    knots: a blob, a ring, a bright centre in a dark ring all fit) about a free
    centre ``c``, plus a background gradient. The fit (Gauss-Newton over the
    centre and, linearly, the profile and gradient) uses every pixel within
    ``half`` of the start, so the whole extent of a ring informs the centre;
    its uncertainty is the least-squares covariance ``s^2 (J^T J)^-1``.

    Parameters
    ----------
    img : 2D array
        Background-subtracted frame (any polarity).
    rows, cols : array_like of int
        Pixels the windows are centred on.
    half : int or array_like of int
        Radius (px) of each fit window; it should hold the whole image.
    x0, y0 : array_like of float, optional
        Starting centres (px), default the pixels.
    noise : float or array_like
        Background noise (counts rms) at each image.
    shot : float
        Variance per count of image above the background (the gain, for
        Poisson counts; 0: the noise is the background's alone). The fit is
        weighted by 1 / (noise^2 + shot x model): the Poisson likelihood's
        weights, updated as the profile is refitted.

    Returns
    -------
    dict of ndarrays
        ``x``, ``y`` (px), ``var_x``, ``var_y`` (px^2), ``ok`` (bool; False where
        the window leaves the frame or the fit did not converge), ``iterations``
        (Gauss-Newton steps of the converged fits, 0 for the others).
    """
    rows = np.ascontiguousarray(rows, np.int64)
    cols = np.ascontiguousarray(cols, np.int64)
    halves = np.broadcast_to(np.asarray(half, np.int64), rows.shape).copy()
    x0 = cols.astype(np.float64) if x0 is None else np.ascontiguousarray(x0, np.float64)
    y0 = rows.astype(np.float64) if y0 is None else np.ascontiguousarray(y0, np.float64)
    img = np.ascontiguousarray(img)
    if img.dtype not in (np.float32, np.float64):
        img = img.astype(np.float32)
    n2 = np.ascontiguousarray(np.broadcast_to(np.asarray(noise, np.float64) ** 2, rows.shape)) + 1e-12
    # windows centred on the pixel nearest each start
    ok_start = np.isfinite(x0) & np.isfinite(y0)
    rows = np.where(ok_start, np.round(np.nan_to_num(y0)), rows).astype(np.int64)
    cols = np.where(ok_start, np.round(np.nan_to_num(x0)), cols).astype(np.int64)
    x0 = np.where(ok_start, x0, cols).astype(np.float64)
    y0 = np.where(ok_start, y0, rows).astype(np.float64)
    res = np.full((len(rows), 4), np.nan)
    ok = np.zeros(len(rows), np.bool_)
    iters = np.zeros(len(rows))
    if len(rows):
        _profile_all(img, rows, cols, halves, x0, y0, n2, float(shot), res, ok, iters)
    return {"x": res[:, 0], "y": res[:, 1], "var_x": res[:, 2], "var_y": res[:, 3], "ok": ok, "iterations": iters}


def _as_n(v, n, dtype):
    """``v`` as a contiguous 1-D array of ``n`` values of ``dtype`` (a scalar repeated n times); an array that
    already is one is returned as it is (broadcast_to and its copy cost more than the kernels of a sparse frame)."""
    a = np.asarray(v, dtype)
    if a.ndim == 1 and a.shape[0] == n and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(np.broadcast_to(a, (n,)))


@nb.njit(cache=True)
def _annulus_sums(img, xc, yc, R, sums, cnt, bins):
    # sum and pixel count of img in 1 px annuli (b = round(r)) about (xc, yc), out to R px. Each row in two
    # passes: the annulus of every pixel into `bins` (>= 2 R + 1 ints; the square roots do not depend on each
    # other and vectorise), then the sums in the row's order (~20 % faster than one pass; the same sums)
    h, w = img.shape
    rc = int(round(yc))
    cc = int(round(xc))
    j0 = max(0, cc - R)
    j1 = min(w, cc + R + 1)
    for i in range(max(0, rc - R), min(h, rc + R + 1)):
        for j in range(j0, j1):
            bins[j - j0] = int(math.sqrt((j - xc) ** 2 + (i - yc) ** 2) + 0.5)
        row = img[i]
        for j in range(j0, j1):
            b = bins[j - j0]
            if b <= R:
                sums[b] += row[j]
                cnt[b] += 1


@nb.njit(cache=True)
def _extent_all(img, x0, y0, noise, rmin, rmax, k_sig, gap, out):
    # per image: the largest radius (px) whose 1 px annulus mean differs from zero by more than k_sig
    # standard errors, within rmax, before `gap` consecutive annuli beyond rmin that do not (0: no such
    # stop); rmin when none does
    rm = 0
    for k in range(x0.shape[0]):
        rm = max(rm, int(rmax[k]))
    bins = np.empty(2 * rm + 1, np.int64)
    for k in range(x0.shape[0]):
        R = int(rmax[k])
        sums = np.zeros(R + 1)
        cnt = np.zeros(R + 1)
        xc = x0[k]
        yc = y0[k]
        if not (math.isfinite(xc) and math.isfinite(yc)):
            out[k] = rmin[k]
            continue
        _annulus_sums(img, xc, yc, R, sums, cnt, bins)
        e = 0
        quiet = 0
        for b in range(R + 1):
            if cnt[b] > 0 and abs(sums[b] / cnt[b]) > k_sig * noise[k] / math.sqrt(cnt[b]):
                e = b
                quiet = 0
            elif b > rmin[k]:
                quiet += 1
                if gap > 0 and quiet >= gap:
                    break
        out[k] = max(float(rmin[k]), float(e))


#: Consecutive quiet annuli (1 px each, beyond ``rmin``) at which :func:`image_extent` stops looking further out
EXTENT_GAP = 3


def image_extent(img, x0, y0, noise, rmin, rmax, k_sig: float = 4.0, gap: int | None = None):
    """Radius (px) out to which each image stands out of the noise.

    The azimuthal mean of ``img`` (background-subtracted) in 1 px annuli
    about each centre; the extent is the largest radius whose annulus mean
    differs from zero by more than ``k_sig`` standard errors (``noise`` /
    sqrt(pixels)), at least ``rmin`` and at most ``rmax``, searched outwards
    until ``gap`` consecutive annuli beyond ``rmin`` are not significant
    (default :data:`EXTENT_GAP`; 0: out to ``rmax``). A ring, a halo or the
    damped rings of a defocused brightfield particle are all included (one
    annulus at a zero crossing of the profile does not stop the search);
    dust or a neighbour's light further out, past a quiet gap, is not.

    Returns
    -------
    ndarray of float (px)
    """
    n = len(np.atleast_1d(x0))
    b = lambda v, t: _as_n(v, n, t)
    out = np.zeros(n)
    if n:
        _extent_all(np.ascontiguousarray(img), b(x0, np.float64), b(y0, np.float64), b(noise, np.float64),
                    b(rmin, np.float64), b(rmax, np.float64), float(k_sig),
                    int(EXTENT_GAP if gap is None else gap), out)
    return out


@nb.njit(cache=True)
def _annulus_sums_disc(img, xc, yc, R, sums, cnt, bins):
    # _annulus_sums (its two passes per row), the pixels farther than R + 1 px (whose annulus is beyond R) given
    # the annulus R + 1 without their square root: the same sums in the same order
    h, w = img.shape
    rc = int(round(yc))
    cc = int(round(xc))
    lim = (R + 1.0) ** 2
    j0 = max(0, cc - R)
    j1 = min(w, cc + R + 1)
    for i in range(max(0, rc - R), min(h, rc + R + 1)):
        dy2 = (i - yc) ** 2
        for j in range(j0, j1):
            d2 = (j - xc) ** 2 + dy2
            bins[j - j0] = int(math.sqrt(d2) + 0.5) if d2 <= lim else R + 1
        row = img[i]
        for j in range(j0, j1):
            b = bins[j - j0]
            if b <= R:
                sums[b] += row[j]
                cnt[b] += 1


@nb.njit(cache=True)
def _dip_all(img, x0, y0, noise, rmax, k_sig, out):
    # per image (particles positive): an annulus of the opposite sign, k_sig standard errors below zero
    # and below the level just outside it, at 1.5 px or more from the centre
    rm = 0
    for k in range(x0.shape[0]):
        rm = max(rm, int(rmax[k]))
    sums = np.zeros(rm + 1)
    cnt = np.zeros(rm + 1)
    bins = np.empty(2 * rm + 1, np.int64)
    for k in range(x0.shape[0]):
        R = int(rmax[k])
        sums[:] = 0.0
        cnt[:] = 0.0
        xc = x0[k]
        yc = y0[k]
        _annulus_sums_disc(img, xc, yc, R, sums, cnt, bins)
        found = False
        for b in range(2, R - 1):
            if cnt[b] == 0 or cnt[b + 2] == 0:
                continue
            m = sums[b] / cnt[b]
            se = noise[k] / math.sqrt(cnt[b])
            outside = max(sums[b + 1] / max(cnt[b + 1], 1.0), sums[b + 2] / cnt[b + 2])
            if m < -k_sig * se and m < outside - k_sig * se and m < sums[0] / max(cnt[0], 1.0) - k_sig * se:
                found = True
                break
        out[k] = found


def has_dip(img, x0, y0, noise, rmax, k_sig: float = 4.0):
    """Whether each image (particles positive) has a ring of the opposite sign around it.

    True when a 1 px annulus (2 px or more from the centre, within ``rmax``)
    has an azimuthal mean more than ``k_sig`` standard errors below zero,
    below the centre and below the annuli just outside it: a bright centre in
    a dark ring (or the reverse), which a Gaussian does not describe.

    Returns
    -------
    ndarray of bool
    """
    n = len(np.atleast_1d(x0))
    b = lambda v, t: _as_n(v, n, t)
    out = np.zeros(n, np.bool_)
    if n:
        _dip_all(np.ascontiguousarray(img), b(x0, np.float64), b(y0, np.float64), b(noise, np.float64),
                 b(rmax, np.float64), float(k_sig), out)
    return out
