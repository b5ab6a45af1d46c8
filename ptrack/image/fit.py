"""Sub-pixel localisation: maximum-likelihood Gaussian fits at the Cramer-Rao bound.

Localisation: a maximum-likelihood fit of a pixel-integrated 2D Gaussian
(position, photons, background, width) to the raw counts of each spot,
converted to photons with the camera gain and offset, with sCMOS/CCD read
noise folded in (Poisson + read-noise variance, the "+ sigma^2" shift of
Huang et al. 2013). The likelihood is maximised by Levenberg-Marquardt
damped Fisher scoring in a numba kernel, started from the local centroid.
The MLE reaches the Cramer-Rao lower bound (Mortensen et al. 2010, Smith et
al. 2010), whereas least squares loses a factor 16/9 in variance; the
inverse Fisher information at the estimate is each particle's uncertainty
(``sigma_x``, ``sigma_y``). For brightfield images (no Poisson model after
inversion) a least-squares fit of the same model is used.

Cost: one pass over a fit window per accepted step (objective, score and
Fisher matrix together; the last step, below the tolerance, is taken
without one), 5x5 to 17x17 systems by an in-place Cholesky, no allocation
per spot. The least-squares path uses that the model is separable in x and
y: its Gauss-Newton matrix comes from 1-D Gram matrices of the erf
profiles, and the pixel loop only forms row sums. Least-squares fits of one
and two spots solve the photons and background in closed form at every
evaluation (variable projection: the same optimum, the steps taken on the
centres and width), their pixel loop projecting the data on the column
profiles; a least-squares step that reverses the last one along a line
(Gauss-Newton overshooting on images a Gaussian does not describe exactly)
is cut to the alternating series' sum.

Pixel coordinates follow trackpy: ``x`` along columns, ``y`` along rows, the
centre of pixel (0, 0) at (0, 0).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .preprocess import fast_median

__all__ = ["fit_spots", "mortensen_sigma", "cramer_rao_bound"]

_SQRT2 = math.sqrt(2.0)
_SQRT2PI = math.sqrt(2.0 * math.pi)
# convergence of the fits: the centre's last step below this (px)
_XTOL = 1e-3
# least-squares fits (brightfield) stop when the centre's last step is below this fraction of its standard
# error, if that is more than _XTOL: the remaining error is <= ~0.1 standard errors (+0.5 % variance), and
# halo images (not Gaussian) crawl for ~10 iterations below it
_RTOL = 0.05


@nb.njit(cache=True, inline="always")
def _chol(A, P):
    # in-place Cholesky factor (lower triangle) of the P x P leading block of A; False when A is not
    # numerically positive definite
    for j in range(P):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        A[j, j] = d
        for i in range(j + 1, P):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / d
    return True


@nb.njit(cache=True, inline="always")
def _chol_solve(L, b, x, P):
    # x = A^-1 b from the Cholesky factor L of A (_chol)
    for i in range(P):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(P - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, P):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


@nb.njit(cache=True, inline="always")
def _chol_inv_diag(L, P, ia, y):
    # (A^-1)_{ia, ia} = |L^-1 e_ia|^2 from the Cholesky factor L of A; y is scratch (length >= P)
    s2 = 0.0
    for i in range(P):
        if i < ia:
            y[i] = 0.0
            continue
        s = 1.0 if i == ia else 0.0
        for k in range(ia, i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
        s2 += y[i] * y[i]
    return s2


#: the fits' pixel integrals use :func:`_erf_gauss` (False: libm's erf, ~2x the cost of a profile)
_FAST_ERF = True


@nb.njit(cache=True, inline="always")
def _erf_gauss(z, g):
    # erf(z) from g = exp(-z^2), which the profile has at every pixel edge anyway: Abramowitz & Stegun 7.1.26,
    # |error| <= 1.5e-7 (a pixel integral off by <= 1.4e-7 of the spot's photons: 1e-3 photons of a
    # 5000-photon spot, far below its shot noise), a division and a polynomial instead of libm's erf
    t = 1.0 / (1.0 + 0.3275911 * abs(z))
    y = 1.0 - ((((1.061405429 * t - 1.453152027) * t + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t * g
    return y if z >= 0 else -y


@nb.njit(cache=True)
def _erf_profile(n0, n, x, s, e, de_dx, de_ds):
    # pixel-integrated unit Gaussian over pixels n0..n0+n-1 centred at x, width s, and its derivatives in x
    # and s. Each pixel edge's erf is computed once (an edge is shared by two pixels), and the Gaussian at
    # the edges by the recurrence exp(-(b+1)^2 c) = exp(-b^2 c) exp(-(2b+1) c), whose factor is itself
    # multiplied by exp(-2c) from edge to edge (two products instead of an exp; direct where the factors
    # would leave the floating-point range); the erf from that Gaussian (_erf_gauss)
    inv = 1.0 / (_SQRT2 * s)
    c2 = 1.0 / (2.0 * s * s)
    k1 = 1.0 / (_SQRT2PI * s)
    k2 = k1 / s
    b = n0 - x - 0.5
    gb = math.exp(-b * b * c2)
    eb = _erf_gauss(b * inv, gb) if _FAST_ERF else math.erf(b * inv)
    rec = b * b * c2 < 600.0 and (b + n) * (b + n) * c2 < 600.0 and abs(2.0 * b + 1.0) * c2 < 600.0
    q = math.exp(-(2.0 * b + 1.0) * c2) if rec else 0.0
    rr = math.exp(-2.0 * c2)
    for i in range(n):
        a = b + 1.0
        if rec:
            ga = gb * q
            q *= rr
        else:
            ga = math.exp(-a * a * c2)
        ea = _erf_gauss(a * inv, ga) if _FAST_ERF else math.erf(a * inv)
        e[i] = 0.5 * (ea - eb)
        de_dx[i] = -(ga - gb) * k1
        de_ds[i] = -(a * ga - b * gb) * k2
        b = a
        eb = ea
        gb = ga


@nb.njit(cache=True, inline="always")
def _pixel_loglik(d, mu, rvar, poisson):
    # one pixel's term of the fit objective: d = measured photons, mu = model photons. Poisson
    # log-likelihood with the read-noise variance rvar added to both (sCMOS approximation; mu floored at
    # 1e-9), or -(d - mu)^2 / 2 for least squares.
    if poisson:
        mu += rvar
        d += rvar
        if mu < 1e-9:
            mu = 1e-9
        if d > 0:
            return d * math.log(mu) - mu
        return -mu
    return -0.5 * (d - mu) ** 2


@nb.njit(cache=True, inline="always")
def _photons(v, offset, ig, plain):
    # a pixel's counts as photons, (v - offset) / gain with ig = 1 / gain; plain (gain 1, offset 0): the value
    # itself, (v - 0) x 1 = v exactly, without the subtraction and product
    return float(v) if plain else (v - offset) * ig


@nb.njit(cache=True, inline="always")
def _photons_div(v, offset, gain, plain):
    # a pixel's counts as photons by the division, (v - offset) / gain (the fits' starting values: background and
    # centroid); plain (gain 1, offset 0): the value itself, (v - 0) / 1 = v exactly, without the division
    return float(v) if plain else (v - offset) / gain


@nb.njit(cache=True, inline="always")
def _border_mean(img, r0, nr, c0, nc, gain, offset):
    # mean photons on the border pixels of the window rows r0..r0+nr-1, cols c0..c0+nc-1: the starting
    # background of the single and the joint fit. Only the border is visited (in raster order: the first and
    # last rows whole, the first and last pixel of the rows between): the same sum as testing every pixel of the
    # window
    plain = gain == 1.0 and offset == 0.0
    bsum = 0.0
    nb_ = 0
    for i in range(nr):
        row = img[r0 + i]
        step = 1 if (i == 0 or i == nr - 1) else max(nc - 1, 1)
        for j in range(0, nc, step):
            bsum += _photons_div(row[c0 + j], offset, gain, plain)
            nb_ += 1
    return bsum / max(nb_, 1)


@nb.njit(cache=True)
def _group_objective(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys):
    # log-likelihood (Poisson) or -RSS/2 of K Gaussians (x, y, N each) on a shared background and width
    b = th[3 * K]
    s = th[3 * K + 1]
    for k in range(K):
        _erf_profile(c0, nc, th[3 * k], s, ex[k], dxx[k], dxs[k])
        _erf_profile(r0, nr, th[3 * k + 1], s, ey[k], dyy[k], dys[k])
    f = 0.0
    for i in range(nr):
        for j in range(nc):
            mu = b
            for k in range(K):
                mu += th[3 * k + 2] * ex[k, j] * ey[k, i]
            f += _pixel_loglik((img[r0 + i, c0 + j] - offset) / gain, mu, rvar, poisson)
    return f


@nb.njit(cache=True)
def _work(K, n):
    # scratch of a fit of up to K spots in windows of up to n pixels per side: the 1-D functions of the
    # separable model along columns (FX) and rows (FY), row 3k + 0 / 1 / 2 = spot k's erf profile e, de/dx,
    # de/ds, row 3K = 1 (the background); two (J, g) pairs (current and trial); the damped matrix, the
    # step, the trial parameters, the per-pixel derivatives (Poisson path); the 1-D Gram matrices, the
    # residual's row sums and the separable terms (coefficient, column function, row function, start of
    # each parameter's terms) of the least-squares path; the last accepted step (_lm)
    P = 3 * K + 2
    Q = 3 * K + 1
    T = 5 * K + 1
    FX = np.ones((Q, n))
    FY = np.ones((Q, n))
    return (FX, FY, np.zeros((P, P)), np.zeros(P), np.zeros((P, P)), np.zeros(P), np.zeros((P, P)), np.zeros(P),
            np.zeros(P), np.zeros(P), np.zeros((Q, Q)), np.zeros((Q, Q)), np.zeros(Q), np.zeros(T),
            np.zeros(T, np.int64), np.zeros(T, np.int64), np.zeros(P + 1, np.int64), np.zeros(P))


@nb.njit(cache=True, inline="always")
def _profiles(th, K, r0, nr, c0, nc, FX, FY):
    s = th[3 * K + 1]
    for k in range(K):
        _erf_profile(c0, nc, th[3 * k], s, FX[3 * k], FX[3 * k + 1], FX[3 * k + 2])
        _erf_profile(r0, nr, th[3 * k + 1], s, FY[3 * k], FY[3 * k + 1], FY[3 * k + 2])


@nb.njit(cache=True, inline="always")
def _terms(th, K, TC, TA, TB, TP):
    # the separable terms of each parameter's derivative d mu / d th_p as (coefficient TC, column function
    # TA, row function TB), those of parameter p at TP[p]..TP[p+1]-1: x_k = N_k d_k(col) e_k(row),
    # y_k = N_k e_k d_k, N_k = e_k e_k, background = 1 1, width = sum_k N_k (s_k e_k + e_k s_k); function
    # index 3k + {0: e, 1: d, 2: s} of spot k, 3K for 1 (the rows of _work's FX, FY)
    P = 3 * K + 2
    t = 0
    for k in range(K):
        N = th[3 * k + 2]
        TP[3 * k] = t
        TC[t] = N
        TA[t] = 3 * k + 1
        TB[t] = 3 * k
        t += 1
        TP[3 * k + 1] = t
        TC[t] = N
        TA[t] = 3 * k
        TB[t] = 3 * k + 1
        t += 1
        TP[3 * k + 2] = t
        TC[t] = 1.0
        TA[t] = 3 * k
        TB[t] = 3 * k
        t += 1
    TP[3 * K] = t
    TC[t] = 1.0
    TA[t] = 3 * K
    TB[t] = 3 * K
    t += 1
    TP[3 * K + 1] = t
    for k in range(K):
        N = th[3 * k + 2]
        TC[t] = N
        TA[t] = 3 * k + 2
        TB[t] = 3 * k
        t += 1
        TC[t] = N
        TA[t] = 3 * k
        TB[t] = 3 * k + 2
        t += 1
    TP[P] = t


@nb.njit(cache=True, inline="always")
def _ls_fisher(th, K, nr, nc, FX, FY, J, Gx, Gy, TC, TA, TB, TP):
    # the Gauss-Newton matrix J of the separable least-squares model: the 1-D Gram matrices Gx, Gy of the
    # column and row functions (FX, FY), then each entry as the sum over the parameters' separable terms
    # (_terms) of coefficient products times a Gx and a Gy entry
    P = 3 * K + 2
    Q = 3 * K + 1
    for a in range(Q):
        for bb in range(a, Q):
            sx = 0.0
            for j in range(nc):
                sx += FX[a, j] * FX[bb, j]
            sy = 0.0
            for i in range(nr):
                sy += FY[a, i] * FY[bb, i]
            Gx[a, bb] = sx
            Gx[bb, a] = sx
            Gy[a, bb] = sy
            Gy[bb, a] = sy
    _terms(th, K, TC, TA, TB, TP)
    for p in range(P):
        for q in range(p, P):
            v = 0.0
            for tp in range(TP[p], TP[p + 1]):
                for tq in range(TP[q], TP[q + 1]):
                    v += TC[tp] * TC[tq] * Gx[TA[tp], TA[tq]] * Gy[TB[tp], TB[tq]]
            J[p, q] = v
            J[q, p] = v


@nb.njit(cache=True, inline="always")
def _gram4(F, n):
    # the 10 distinct entries of the Gram matrix of the first four rows of F over n samples, each summed over
    # the samples in order from 0.0 (the dot products of _ls_fisher, in one pass: independent chains)
    s00 = s01 = s02 = s03 = s11 = s12 = s13 = s22 = s23 = s33 = 0.0
    for j in range(n):
        f0 = F[0, j]
        f1 = F[1, j]
        f2 = F[2, j]
        f3 = F[3, j]
        s00 += f0 * f0
        s01 += f0 * f1
        s02 += f0 * f2
        s03 += f0 * f3
        s11 += f1 * f1
        s12 += f1 * f2
        s13 += f1 * f3
        s22 += f2 * f2
        s23 += f2 * f3
        s33 += f3 * f3
    return s00, s01, s02, s03, s11, s12, s13, s22, s23, s33


@nb.njit(cache=True, inline="always")
def _ls_fisher1(th, nr, nc, FX, FY, J):
    # _ls_fisher for one spot (K = 1) written out: the separable terms of _terms (x: N d e, y: N e d, N: e e,
    # background: 1 1, width: N s e + N e s; functions 0 = e, 1 = d, 2 = s, 3 = 1) multiplied in the same
    # order from 0.0 (bit-identical), without the generic loops over the term lists (~2/3 of _ls_fisher's time)
    N = th[2]
    x00, x01, x02, x03, x11, x12, x13, x22, x23, x33 = _gram4(FX, nc)
    y00, y01, y02, y03, y11, y12, y13, y22, y23, y33 = _gram4(FY, nr)
    NN = N * N
    j00 = 0.0 + NN * x11 * y00
    j01 = 0.0 + NN * x01 * y01
    j02 = 0.0 + N * 1.0 * x01 * y00
    j03 = 0.0 + N * 1.0 * x13 * y03
    j04 = 0.0 + NN * x12 * y00 + NN * x01 * y02
    j11 = 0.0 + NN * x00 * y11
    j12 = 0.0 + N * 1.0 * x00 * y01
    j13 = 0.0 + N * 1.0 * x03 * y13
    j14 = 0.0 + NN * x02 * y01 + NN * x00 * y12
    j22 = 0.0 + 1.0 * 1.0 * x00 * y00
    j23 = 0.0 + 1.0 * 1.0 * x03 * y03
    j24 = 0.0 + 1.0 * N * x02 * y00 + 1.0 * N * x00 * y02
    j33 = 0.0 + 1.0 * 1.0 * x33 * y33
    j34 = 0.0 + 1.0 * N * x23 * y03 + 1.0 * N * x03 * y23
    j44 = 0.0 + NN * x22 * y00 + NN * x02 * y02 + NN * x02 * y02 + NN * x00 * y22
    J[0, 0] = j00
    J[0, 1] = J[1, 0] = j01
    J[0, 2] = J[2, 0] = j02
    J[0, 3] = J[3, 0] = j03
    J[0, 4] = J[4, 0] = j04
    J[1, 1] = j11
    J[1, 2] = J[2, 1] = j12
    J[1, 3] = J[3, 1] = j13
    J[1, 4] = J[4, 1] = j14
    J[2, 2] = j22
    J[2, 3] = J[3, 2] = j23
    J[2, 4] = J[4, 2] = j24
    J[3, 3] = j33
    J[3, 4] = J[4, 3] = j34
    J[4, 4] = j44


@nb.njit(cache=True, inline="always")
def _gram7(F, n):
    # _gram4 for the first seven rows (28 distinct entries, the 3 K + 1 = 7 functions of two spots)
    s00 = s01 = s02 = s03 = s04 = s05 = s06 = s11 = s12 = s13 = s14 = s15 = s16 = s22 = 0.0
    s23 = s24 = s25 = s26 = s33 = s34 = s35 = s36 = s44 = s45 = s46 = s55 = s56 = s66 = 0.0
    for j in range(n):
        f0 = F[0, j]
        f1 = F[1, j]
        f2 = F[2, j]
        f3 = F[3, j]
        f4 = F[4, j]
        f5 = F[5, j]
        f6 = F[6, j]
        s00 += f0 * f0
        s01 += f0 * f1
        s02 += f0 * f2
        s03 += f0 * f3
        s04 += f0 * f4
        s05 += f0 * f5
        s06 += f0 * f6
        s11 += f1 * f1
        s12 += f1 * f2
        s13 += f1 * f3
        s14 += f1 * f4
        s15 += f1 * f5
        s16 += f1 * f6
        s22 += f2 * f2
        s23 += f2 * f3
        s24 += f2 * f4
        s25 += f2 * f5
        s26 += f2 * f6
        s33 += f3 * f3
        s34 += f3 * f4
        s35 += f3 * f5
        s36 += f3 * f6
        s44 += f4 * f4
        s45 += f4 * f5
        s46 += f4 * f6
        s55 += f5 * f5
        s56 += f5 * f6
        s66 += f6 * f6
    return (s00, s01, s02, s03, s04, s05, s06, s11, s12, s13, s14, s15, s16, s22,
            s23, s24, s25, s26, s33, s34, s35, s36, s44, s45, s46, s55, s56, s66)


@nb.njit(cache=True, inline="always")
def _ls_fisher2(th, nr, nc, FX, FY, J):
    # _ls_fisher for two spots (K = 2) written out as _ls_fisher1: spot k's functions 3k + {0: e, 1: d, 2: s},
    # 6 = 1; parameters x0 y0 N0 x1 y1 N1 background width; the same products in the same order (bit-identical)
    N0 = th[2]
    N1 = th[5]
    N0N0 = N0 * N0
    N0N1 = N0 * N1
    N1N1 = N1 * N1
    (x00, x01, x02, x03, x04, x05, x06, x11, x12, x13, x14, x15, x16, x22,
     x23, x24, x25, x26, x33, x34, x35, x36, x44, x45, x46, x55, x56, x66) = _gram7(FX, nc)
    (y00, y01, y02, y03, y04, y05, y06, y11, y12, y13, y14, y15, y16, y22,
     y23, y24, y25, y26, y33, y34, y35, y36, y44, y45, y46, y55, y56, y66) = _gram7(FY, nr)
    j00 = 0.0 + N0N0 * x11 * y00
    j01 = 0.0 + N0N0 * x01 * y01
    j02 = 0.0 + N0 * x01 * y00
    j03 = 0.0 + N0N1 * x14 * y03
    j04 = 0.0 + N0N1 * x13 * y04
    j05 = 0.0 + N0 * x13 * y03
    j06 = 0.0 + N0 * x16 * y06
    j07 = 0.0 + N0N0 * x12 * y00 + N0N0 * x01 * y02 + N0N1 * x15 * y03 + N0N1 * x13 * y05
    j11 = 0.0 + N0N0 * x00 * y11
    j12 = 0.0 + N0 * x00 * y01
    j13 = 0.0 + N0N1 * x04 * y13
    j14 = 0.0 + N0N1 * x03 * y14
    j15 = 0.0 + N0 * x03 * y13
    j16 = 0.0 + N0 * x06 * y16
    j17 = 0.0 + N0N0 * x02 * y01 + N0N0 * x00 * y12 + N0N1 * x05 * y13 + N0N1 * x03 * y15
    j22 = 0.0 + x00 * y00
    j23 = 0.0 + N1 * x04 * y03
    j24 = 0.0 + N1 * x03 * y04
    j25 = 0.0 + x03 * y03
    j26 = 0.0 + x06 * y06
    j27 = 0.0 + N0 * x02 * y00 + N0 * x00 * y02 + N1 * x05 * y03 + N1 * x03 * y05
    j33 = 0.0 + N1N1 * x44 * y33
    j34 = 0.0 + N1N1 * x34 * y34
    j35 = 0.0 + N1 * x34 * y33
    j36 = 0.0 + N1 * x46 * y36
    j37 = 0.0 + N0N1 * x24 * y03 + N0N1 * x04 * y23 + N1N1 * x45 * y33 + N1N1 * x34 * y35
    j44 = 0.0 + N1N1 * x33 * y44
    j45 = 0.0 + N1 * x33 * y34
    j46 = 0.0 + N1 * x36 * y46
    j47 = 0.0 + N0N1 * x23 * y04 + N0N1 * x03 * y24 + N1N1 * x35 * y34 + N1N1 * x33 * y45
    j55 = 0.0 + x33 * y33
    j56 = 0.0 + x36 * y36
    j57 = 0.0 + N0 * x23 * y03 + N0 * x03 * y23 + N1 * x35 * y33 + N1 * x33 * y35
    j66 = 0.0 + x66 * y66
    j67 = 0.0 + N0 * x26 * y06 + N0 * x06 * y26 + N1 * x56 * y36 + N1 * x36 * y56
    j77 = (0.0 + N0N0 * x22 * y00 + N0N0 * x02 * y02 + N0N1 * x25 * y03 + N0N1 * x23 * y05 + N0N0 * x02 * y02
           + N0N0 * x00 * y22 + N0N1 * x05 * y23 + N0N1 * x03 * y25 + N0N1 * x25 * y03 + N0N1 * x05 * y23
           + N1N1 * x55 * y33 + N1N1 * x35 * y35 + N0N1 * x23 * y05 + N0N1 * x03 * y25 + N1N1 * x35 * y35
           + N1N1 * x33 * y55)
    J[0, 0] = j00
    J[0, 1] = J[1, 0] = j01
    J[0, 2] = J[2, 0] = j02
    J[0, 3] = J[3, 0] = j03
    J[0, 4] = J[4, 0] = j04
    J[0, 5] = J[5, 0] = j05
    J[0, 6] = J[6, 0] = j06
    J[0, 7] = J[7, 0] = j07
    J[1, 1] = j11
    J[1, 2] = J[2, 1] = j12
    J[1, 3] = J[3, 1] = j13
    J[1, 4] = J[4, 1] = j14
    J[1, 5] = J[5, 1] = j15
    J[1, 6] = J[6, 1] = j16
    J[1, 7] = J[7, 1] = j17
    J[2, 2] = j22
    J[2, 3] = J[3, 2] = j23
    J[2, 4] = J[4, 2] = j24
    J[2, 5] = J[5, 2] = j25
    J[2, 6] = J[6, 2] = j26
    J[2, 7] = J[7, 2] = j27
    J[3, 3] = j33
    J[3, 4] = J[4, 3] = j34
    J[3, 5] = J[5, 3] = j35
    J[3, 6] = J[6, 3] = j36
    J[3, 7] = J[7, 3] = j37
    J[4, 4] = j44
    J[4, 5] = J[5, 4] = j45
    J[4, 6] = J[6, 4] = j46
    J[4, 7] = J[7, 4] = j47
    J[5, 5] = j55
    J[5, 6] = J[6, 5] = j56
    J[5, 7] = J[7, 5] = j57
    J[6, 6] = j66
    J[6, 7] = J[7, 6] = j67
    J[7, 7] = j77


@nb.njit(cache=True)
def _eval_poisson(img, r0, nr, c0, nc, th, K, gain, offset, rvar, FX, FY, J, g, dm):
    # Poisson log-likelihood f (read-noise shift), score g and Fisher information J at th, in one pass
    # over the pixels. Returns (f, rss).
    P = 3 * K + 2
    _profiles(th, K, r0, nr, c0, nc, FX, FY)
    for a in range(P):
        g[a] = 0.0
        for bb in range(P):
            J[a, bb] = 0.0
    f = 0.0
    rss = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        for j in range(nc):
            mu = th[3 * K]
            ds_ = 0.0
            for k in range(K):
                N = th[3 * k + 2]
                exj = FX[3 * k, j]
                eyi = FY[3 * k, i]
                e = exj * eyi
                mu += N * e
                dm[3 * k] = N * FX[3 * k + 1, j] * eyi
                dm[3 * k + 1] = N * exj * FY[3 * k + 1, i]
                dm[3 * k + 2] = e
                ds_ += N * (FX[3 * k + 2, j] * eyi + exj * FY[3 * k + 2, i])
            dm[3 * K] = 1.0
            dm[3 * K + 1] = ds_
            d = _photons(img[r0 + i, c0 + j], offset, ig, plain)
            rss += (d - mu) ** 2
            m = mu + rvar
            dd = d + rvar
            if m < 1e-9:
                m = 1e-9
            if dd > 0:
                f += dd * math.log(m) - m
            else:
                f -= m
            wgt = 1.0 / m
            res = dd * wgt - 1.0
            for a in range(P):
                g[a] += res * dm[a]
                wa = wgt * dm[a]
                for bb in range(a, P):
                    J[a, bb] += wa * dm[bb]
    for a in range(P):
        for bb in range(a):
            J[a, bb] = J[bb, a]
    return f, rss


@nb.njit(cache=True)
def _eval_ls(img, r0, nr, c0, nc, th, K, gain, offset, FX, FY, J, g, Gx, Gy, rrow, TC, TA, TB, TP):
    # the least-squares objective -RSS/2, its gradient g and the Gauss-Newton matrix J at th, using that
    # the model is separable: every derivative is a sum of products of a column function and a row
    # function (FX, FY: a spot's e, de/dx, de/ds; 1 for the background), so J is assembled from the 1-D
    # Gram matrices Gx, Gy and the pixel loop only forms the residual's row sums (rrow). Returns (f, rss).
    P = 3 * K + 2
    Q = 3 * K + 1
    _profiles(th, K, r0, nr, c0, nc, FX, FY)
    bg = th[3 * K]
    for a in range(P):
        g[a] = 0.0
    rss = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        for a in range(Q):
            rrow[a] = 0.0
        for j in range(nc):
            mu = bg
            for k in range(K):
                mu += th[3 * k + 2] * FX[3 * k, j] * FY[3 * k, i]
            r = _photons(img[r0 + i, c0 + j], offset, ig, plain) - mu
            rss += r * r
            for a in range(Q):
                rrow[a] += r * FX[a, j]
        for k in range(K):
            N = th[3 * k + 2]
            eyi = FY[3 * k, i]
            g[3 * k] += N * rrow[3 * k + 1] * eyi
            g[3 * k + 1] += N * rrow[3 * k] * FY[3 * k + 1, i]
            g[3 * k + 2] += rrow[3 * k] * eyi
            g[3 * K + 1] += N * (rrow[3 * k + 2] * eyi + rrow[3 * k] * FY[3 * k + 2, i])
        g[3 * K] += rrow[3 * K]
    _ls_fisher(th, K, nr, nc, FX, FY, J, Gx, Gy, TC, TA, TB, TP)
    return -0.5 * rss, rss


@nb.njit(cache=True)
def _eval_poisson1(img, r0, nr, c0, nc, th, gain, offset, rvar, FX, FY, J, g):
    # _eval_poisson for one spot (K = 1), the same operations in the same order (bit-identical), with the score
    # and the 15 Fisher terms in scalars: the generic per-pixel updates of J through memory cost ~2x the pixels
    _profiles(th, 1, r0, nr, c0, nc, FX, FY)
    b = th[3]
    N = th[2]
    ex = FX[0]
    dxf = FX[1]
    sxf = FX[2]
    ey = FY[0]
    dyf = FY[1]
    syf = FY[2]
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    g3 = 0.0
    g4 = 0.0
    j00 = 0.0
    j01 = 0.0
    j02 = 0.0
    j03 = 0.0
    j04 = 0.0
    j11 = 0.0
    j12 = 0.0
    j13 = 0.0
    j14 = 0.0
    j22 = 0.0
    j23 = 0.0
    j24 = 0.0
    j33 = 0.0
    j34 = 0.0
    j44 = 0.0
    f = 0.0
    rss = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        eyi = ey[i]
        dyi = dyf[i]
        syi = syf[i]
        row = img[r0 + i]
        for j in range(nc):
            exj = ex[j]
            e = exj * eyi
            mu = b + N * e
            d0 = N * dxf[j] * eyi
            d1 = N * exj * dyi
            d2 = e
            d4 = N * (sxf[j] * eyi + exj * syi)
            d = _photons(row[c0 + j], offset, ig, plain)
            rss += (d - mu) ** 2
            m = mu + rvar
            dd = d + rvar
            if m < 1e-9:
                m = 1e-9
            if dd > 0:
                f += dd * math.log(m) - m
            else:
                f -= m
            wgt = 1.0 / m
            res = dd * wgt - 1.0
            g0 += res * d0
            g1 += res * d1
            g2 += res * d2
            g3 += res
            g4 += res * d4
            wa = wgt * d0
            j00 += wa * d0
            j01 += wa * d1
            j02 += wa * d2
            j03 += wa
            j04 += wa * d4
            wa = wgt * d1
            j11 += wa * d1
            j12 += wa * d2
            j13 += wa
            j14 += wa * d4
            wa = wgt * d2
            j22 += wa * d2
            j23 += wa
            j24 += wa * d4
            j33 += wgt
            j34 += wgt * d4
            wa = wgt * d4
            j44 += wa * d4
    g[0] = g0
    g[1] = g1
    g[2] = g2
    g[3] = g3
    g[4] = g4
    J[0, 0] = j00
    J[0, 1] = J[1, 0] = j01
    J[0, 2] = J[2, 0] = j02
    J[0, 3] = J[3, 0] = j03
    J[0, 4] = J[4, 0] = j04
    J[1, 1] = j11
    J[1, 2] = J[2, 1] = j12
    J[1, 3] = J[3, 1] = j13
    J[1, 4] = J[4, 1] = j14
    J[2, 2] = j22
    J[2, 3] = J[3, 2] = j23
    J[2, 4] = J[4, 2] = j24
    J[3, 3] = j33
    J[3, 4] = J[4, 3] = j34
    J[4, 4] = j44
    return f, rss


@nb.njit(cache=True)
def _eval_ls1(img, r0, nr, c0, nc, th, gain, offset, FX, FY, J, g, Gx, Gy, TC, TA, TB, TP):
    # _eval_ls for one spot (K = 1), the same operations in the same order (bit-identical), with the residual's
    # row sums in scalars: the generic loops over the K spots and the Q column functions cost ~2x the pixels
    _profiles(th, 1, r0, nr, c0, nc, FX, FY)
    bg = th[3]
    N = th[2]
    ex = FX[0]
    dx = FX[1]
    sx_ = FX[2]
    ey = FY[0]
    dy = FY[1]
    sy_ = FY[2]
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    g3 = 0.0
    g4 = 0.0
    rss = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        q0 = 0.0
        q1 = 0.0
        q2 = 0.0
        q3 = 0.0
        eyi = ey[i]
        row = img[r0 + i]
        for j in range(nc):
            mu = bg + N * ex[j] * eyi
            r = _photons(row[c0 + j], offset, ig, plain) - mu
            rss += r * r
            q0 += r * ex[j]
            q1 += r * dx[j]
            q2 += r * sx_[j]
            q3 += r
        g0 += N * q1 * eyi
        g1 += N * q0 * dy[i]
        g2 += q0 * eyi
        g4 += N * (q2 * eyi + q0 * sy_[i])
        g3 += q3
    g[0] = g0
    g[1] = g1
    g[2] = g2
    g[3] = g3
    g[4] = g4
    _ls_fisher1(th, nr, nc, FX, FY, J)
    return -0.5 * rss, rss


@nb.njit(cache=True)
def _eval_vp1(img, r0, nr, c0, nc, th, gain, offset, FX, FY, J, g):
    # variable projection for one spot (K = 1, least squares): the photons N and background b that minimise
    # the RSS at th's centre and width, written into th[2], th[3], then -RSS/2, its gradient and the
    # Gauss-Newton matrix there (as _eval_ls1). The model is separable, so the pixel loop forms only the
    # data's row projections onto the column functions (d e, d de/dx, d de/ds, d) and the sum of d^2: the
    # optimal N, b (a 2 x 2 system), the RSS and the gradient follow from those and the 1-D Gram matrices.
    # At the optimal N, b their gradient entries are zero, so a Gauss-Newton step on the five parameters
    # moves the centre and width by the reduced (Kaufman) step and the fit iterates on those three only.
    _profiles(th, 1, r0, nr, c0, nc, FX, FY)
    ey = FY[0]
    dy = FY[1]
    sy_ = FY[2]
    ex = FX[0]
    dx = FX[1]
    sx_ = FX[2]
    pe = 0.0        # sum d e_x e_y
    px = 0.0        # sum d de_x e_y
    py = 0.0        # sum d e_x de_y
    ps = 0.0        # sum d (ds_x e_y + e_x ds_y)
    pd = 0.0        # sum d
    pdd = 0.0       # sum d^2
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        q0 = 0.0
        q1 = 0.0
        q2 = 0.0
        q3 = 0.0
        q4 = 0.0
        row = img[r0 + i]
        for j in range(nc):
            d = _photons(row[c0 + j], offset, ig, plain)
            q0 += d * ex[j]
            q1 += d * dx[j]
            q2 += d * sx_[j]
            q3 += d
            q4 += d * d
        eyi = ey[i]
        pe += q0 * eyi
        px += q1 * eyi
        py += q0 * dy[i]
        ps += q2 * eyi + q0 * sy_[i]
        pd += q3
        pdd += q4
    x00, x01, x02, x03, x11, x12, x13, x22, x23, x33 = _gram4(FX, nc)
    y00, y01, y02, y03, y11, y12, y13, y22, y23, y33 = _gram4(FY, nr)
    see = x00 * y00         # sum e^2
    se = x03 * y03          # sum e
    sn = x33 * y33          # pixels
    det = see * sn - se * se
    N = th[2]
    b = th[3]
    if det > 0:
        Nv = (sn * pe - se * pd) / det
        if Nv > 0:
            # the optimal photons and background; where the optimum is no spot (N <= 0: a start off the
            # image), th's own N, b are kept and the step moves all five jointly, as _eval_ls1's
            N = Nv
            b = (see * pd - se * pe) / det
            th[2] = N
            th[3] = b
    rss = pdd - 2.0 * (N * pe + b * pd) + N * N * see + 2.0 * N * b * se + b * b * sn
    if rss < 0.0:
        rss = 0.0
    # gradient of -RSS/2: sum r dmu/dth, r = d - b - N e
    g[0] = N * (px - b * x13 * y03 - N * x01 * y00)
    g[1] = N * (py - b * x03 * y13 - N * x00 * y01)
    g[2] = pe - b * se - N * see
    g[3] = pd - b * sn - N * se
    g[4] = N * (ps - b * (x23 * y03 + x03 * y23) - N * (x02 * y00 + x00 * y02))
    NN = N * N
    J[0, 0] = NN * x11 * y00
    J[0, 1] = J[1, 0] = NN * x01 * y01
    J[0, 2] = J[2, 0] = N * x01 * y00
    J[0, 3] = J[3, 0] = N * x13 * y03
    J[0, 4] = J[4, 0] = NN * x12 * y00 + NN * x01 * y02
    J[1, 1] = NN * x00 * y11
    J[1, 2] = J[2, 1] = N * x00 * y01
    J[1, 3] = J[3, 1] = N * x03 * y13
    J[1, 4] = J[4, 1] = NN * x02 * y01 + NN * x00 * y12
    J[2, 2] = see
    J[2, 3] = J[3, 2] = se
    J[2, 4] = J[4, 2] = N * x02 * y00 + N * x00 * y02
    J[3, 3] = sn
    J[3, 4] = J[4, 3] = N * x23 * y03 + N * x03 * y23
    J[4, 4] = NN * x22 * y00 + 2.0 * NN * x02 * y02 + NN * x00 * y22
    return -0.5 * rss, rss


@nb.njit(cache=True)
def _eval_ls2(img, r0, nr, c0, nc, th, gain, offset, FX, FY, J, g, Gx, Gy, TC, TA, TB, TP):
    # _eval_ls for two spots (K = 2, the joint fits of close pairs), the same operations in the same order
    # (bit-identical), with the residual's seven row sums and the eight score terms in scalars
    _profiles(th, 2, r0, nr, c0, nc, FX, FY)
    bg = th[6]
    N0 = th[2]
    N1 = th[5]
    ex0 = FX[0]
    dx0 = FX[1]
    sx0 = FX[2]
    ex1 = FX[3]
    dx1 = FX[4]
    sx1 = FX[5]
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    g3 = 0.0
    g4 = 0.0
    g5 = 0.0
    g6 = 0.0
    g7 = 0.0
    rss = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        q0 = 0.0
        q1 = 0.0
        q2 = 0.0
        q3 = 0.0
        q4 = 0.0
        q5 = 0.0
        q6 = 0.0
        e0i = FY[0, i]
        e1i = FY[3, i]
        row = img[r0 + i]
        for j in range(nc):
            mu = bg + N0 * ex0[j] * e0i
            mu = mu + N1 * ex1[j] * e1i
            r = _photons(row[c0 + j], offset, ig, plain) - mu
            rss += r * r
            q0 += r * ex0[j]
            q1 += r * dx0[j]
            q2 += r * sx0[j]
            q3 += r * ex1[j]
            q4 += r * dx1[j]
            q5 += r * sx1[j]
            q6 += r
        g0 += N0 * q1 * e0i
        g1 += N0 * q0 * FY[1, i]
        g2 += q0 * e0i
        g7 += N0 * (q2 * e0i + q0 * FY[2, i])
        g3 += N1 * q4 * e1i
        g4 += N1 * q3 * FY[4, i]
        g5 += q3 * e1i
        g7 += N1 * (q5 * e1i + q3 * FY[5, i])
        g6 += q6
    g[0] = g0
    g[1] = g1
    g[2] = g2
    g[3] = g3
    g[4] = g4
    g[5] = g5
    g[6] = g6
    g[7] = g7
    _ls_fisher2(th, nr, nc, FX, FY, J)
    return -0.5 * rss, rss


@nb.njit(cache=True)
def _eval_vp2(img, r0, nr, c0, nc, th, gain, offset, FX, FY, J, g):
    # _eval_vp1 for two spots (K = 2): the photons N0, N1 and the background b that minimise the RSS at the
    # centres and width (a 3 x 3 system), then -RSS/2, its gradient and the Gauss-Newton matrix there (as
    # _eval_ls2), from the data's row projections onto the seven column functions and the 1-D Gram matrices.
    # Where the optimum has a part without photons, th's own N0, N1, b are kept (a joint step, as _eval_ls2's).
    _profiles(th, 2, r0, nr, c0, nc, FX, FY)
    ex0 = FX[0]
    dx0 = FX[1]
    sx0 = FX[2]
    ex1 = FX[3]
    dx1 = FX[4]
    sx1 = FX[5]
    pe0 = px0 = py0 = ps0 = pe1 = px1 = py1 = ps1 = pd = pdd = 0.0
    ig = 1.0 / gain
    plain = ig == 1.0 and offset == 0.0
    for i in range(nr):
        q0 = q1 = q2 = q3 = q4 = q5 = q6 = q7 = 0.0
        row = img[r0 + i]
        for j in range(nc):
            d = _photons(row[c0 + j], offset, ig, plain)
            q0 += d * ex0[j]
            q1 += d * dx0[j]
            q2 += d * sx0[j]
            q3 += d * ex1[j]
            q4 += d * dx1[j]
            q5 += d * sx1[j]
            q6 += d
            q7 += d * d
        e0i = FY[0, i]
        e1i = FY[3, i]
        pe0 += q0 * e0i
        px0 += q1 * e0i
        py0 += q0 * FY[1, i]
        ps0 += q2 * e0i + q0 * FY[2, i]
        pe1 += q3 * e1i
        px1 += q4 * e1i
        py1 += q3 * FY[4, i]
        ps1 += q5 * e1i + q3 * FY[5, i]
        pd += q6
        pdd += q7
    (x00, x01, x02, x03, x04, x05, x06, x11, x12, x13, x14, x15, x16, x22,
     x23, x24, x25, x26, x33, x34, x35, x36, x44, x45, x46, x55, x56, x66) = _gram7(FX, nc)
    (y00, y01, y02, y03, y04, y05, y06, y11, y12, y13, y14, y15, y16, y22,
     y23, y24, y25, y26, y33, y34, y35, y36, y44, y45, y46, y55, y56, y66) = _gram7(FY, nr)
    # the linear block: sums of E0^2, E0 E1, E1^2, E0, E1, and the pixel count
    a00 = x00 * y00
    a01 = x03 * y03
    a11 = x33 * y33
    a02 = x06 * y06
    a12 = x36 * y36
    a22 = x66 * y66
    N0 = th[2]
    N1 = th[5]
    b = th[6]
    # the symmetric 3 x 3 system by its adjugate
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det > 0:
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        n0 = (c00 * pe0 + c01 * pe1 + c02 * pd) / det
        n1 = (c01 * pe0 + c11 * pe1 + c12 * pd) / det
        if n0 > 0 and n1 > 0:
            N0 = n0
            N1 = n1
            b = (c02 * pe0 + c12 * pe1 + c22 * pd) / det
            th[2] = N0
            th[5] = N1
            th[6] = b
    rss = (pdd - 2.0 * (N0 * pe0 + N1 * pe1 + b * pd) + N0 * N0 * a00 + N1 * N1 * a11 + b * b * a22
           + 2.0 * (N0 * N1 * a01 + N0 * b * a02 + N1 * b * a12))
    if rss < 0.0:
        rss = 0.0
    # gradient of -RSS/2: sum r dmu/dth, r = d - b - N0 e0 - N1 e1 (functions 0 e0, 1 d0, 2 s0, 3 e1, 4 d1,
    # 5 s1, 6 one)
    g[0] = N0 * (px0 - b * x16 * y06 - N0 * x01 * y00 - N1 * x13 * y03)
    g[1] = N0 * (py0 - b * x06 * y16 - N0 * x00 * y01 - N1 * x03 * y13)
    g[2] = pe0 - b * a02 - N0 * a00 - N1 * a01
    g[3] = N1 * (px1 - b * x46 * y36 - N0 * x04 * y03 - N1 * x34 * y33)
    g[4] = N1 * (py1 - b * x36 * y46 - N0 * x03 * y04 - N1 * x33 * y34)
    g[5] = pe1 - b * a12 - N0 * a01 - N1 * a11
    g[6] = pd - b * a22 - N0 * a02 - N1 * a12
    g[7] = (N0 * (ps0 - b * (x26 * y06 + x06 * y26) - N0 * (x02 * y00 + x00 * y02) - N1 * (x23 * y03 + x03 * y23))
            + N1 * (ps1 - b * (x56 * y36 + x36 * y56) - N0 * (x05 * y03 + x03 * y05) - N1 * (x35 * y33 + x33 * y35)))
    _ls_fisher2(th, nr, nc, FX, FY, J)
    return -0.5 * rss, rss


#: one-spot fits by :func:`_eval_ls1` and :func:`_eval_poisson1` (False: the generic :func:`_eval_ls` and
#: :func:`_eval_poisson`; the same numbers)
_LS1 = True
#: one-spot least-squares fits by variable projection (:func:`_eval_vp1`: photons and background solved at
#: each evaluation, the steps taken on centre and width; False: :func:`_eval_ls1`, all five jointly)
_VARPRO = True
#: least-squares steps that reverse the last one along a line within acos(sqrt(_OSC_COS2)) (~18 deg) are cut
#: to the alternating series' sum (False: taken whole)
_OSC_SUM = True
_OSC_COS2 = 0.9
#: least-squares steps that continue the last one along a line (within acos(sqrt(_AIT_COS2)), ~8 deg) at a steady
#: ratio rho in _AIT_RHO (the last ratio within 10 %) are extended to the geometric series' sum, 1 / (1 - rho) of
#: them (Aitken): Gauss-Newton converges only linearly on images a Gaussian does not describe exactly (halos,
#: overlapping pairs), at rho ~0.85 on the real movie's slowest pairs, and stops one step short of a sum ~6 steps
#: long. Against fits converged to 1e-9 px this brings the real movie's joint fits from a max 0.32 to 0.12 SE
#: (isolated 1.0 to 0.73 SE) in fewer iterations (False: taken as they are)
_AIT_SUM = True
_AIT_COS2 = 0.98
_AIT_RHO = (0.3, 0.95)


@nb.njit(cache=True, inline="always")
def _evaluate(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, w, J, g):
    if poisson:
        if K == 1 and _LS1:
            return _eval_poisson1(img, r0, nr, c0, nc, th, gain, offset, rvar, w[0], w[1], J, g)
        return _eval_poisson(img, r0, nr, c0, nc, th, K, gain, offset, rvar, w[0], w[1], J, g, w[9])
    if K == 1 and _VARPRO:
        return _eval_vp1(img, r0, nr, c0, nc, th, gain, offset, w[0], w[1], J, g)
    if K == 1 and _LS1:
        return _eval_ls1(img, r0, nr, c0, nc, th, gain, offset, w[0], w[1], J, g, w[10], w[11], w[13], w[14], w[15],
                         w[16])
    if K == 2 and _VARPRO:
        return _eval_vp2(img, r0, nr, c0, nc, th, gain, offset, w[0], w[1], J, g)
    if K == 2 and _LS1:
        return _eval_ls2(img, r0, nr, c0, nc, th, gain, offset, w[0], w[1], J, g, w[10], w[11], w[13], w[14], w[15],
                         w[16])
    return _eval_ls(img, r0, nr, c0, nc, th, K, gain, offset, w[0], w[1], J, g, w[10], w[11], w[12], w[13], w[14],
                    w[15], w[16])


@nb.njit(cache=True)
def _lm(img, r0, nr, c0, nc, th, K, sigma0, gain, offset, rvar, poisson, max_iter, bound_pos, w, var):
    # Levenberg-Marquardt damped Fisher scoring (Gauss-Newton for least squares) of K spots sharing
    # background and width, th = (x_1, y_1, N_1, ..., x_K, y_K, N_K, background, width), started at th.
    # Each trial point is evaluated once for the objective, the score and the Fisher matrix together, so
    # an accepted step costs one pass over the window, and the last step (the centres move by less than
    # the tolerance) is taken without one. var = diagonal of the inverse Fisher information at the
    # result (scaled by the residual variance for least squares). bound_pos: trial centres must stay
    # within 1 px of the window. Returns (converged, objective, iterations).
    P = 3 * K + 2
    J = w[2]
    g = w[3]
    Jt = w[4]
    gt = w[5]
    A = w[6]
    step = w[7]
    trial = w[8]
    prev = w[17]
    has_prev = False
    rho_last = -10.0        # the ratio of the last two steps along one line (_AIT_SUM), -10: none
    npix = nr * nc
    f, rss = _evaluate(img, r0, nr, c0, nc, th, K, gain, offset, rvar, poisson, w, J, g)
    lam = 1e-3
    it = 0
    converged = False
    while it < max_iter:
        it += 1
        # converged when the centre moves by < _XTOL px: 1e-3 px is >= 20x below the bound of any spot we
        # localise (0.02-0.1 px), and brightfield images with halos (not Gaussian) crawl below it for ~10
        # more iterations; least squares stops at _RTOL of the standard error of the worst-determined
        # centre when that is larger
        tol = _XTOL
        if not poisson:
            for a in range(P):
                for bb in range(P):
                    A[a, bb] = J[a, bb]
                A[a, a] += 1e-12
            if _chol(A, P):
                sdmin = 1e300
                for k in range(K):
                    v = _chol_inv_diag(A, P, 3 * k, gt) * rss / max(npix - P, 1)
                    sdmin = min(sdmin, math.sqrt(v) if v > 0 else 0.0)
                tol = max(_XTOL, _RTOL * sdmin)
        improved = False
        small = False
        for try_ in range(12):
            for a in range(P):
                for bb in range(P):
                    A[a, bb] = J[a, bb]
                A[a, a] += lam * J[a, a] + 1e-12
            if not _chol(A, P):
                lam *= 10.0
                continue
            _chol_solve(A, g, step, P)
            raw_small = True
            for k in range(K):
                if abs(step[3 * k]) >= tol or abs(step[3 * k + 1]) >= tol:
                    raw_small = False
            fct = 1.0
            if _OSC_SUM and not poisson and try_ == 0 and has_prev:
                # least squares of images a Gaussian does not describe exactly (halos, pairs): the Gauss-Newton
                # steps can alternate in sign at a ratio rho near -1 (each step overshoots the optimum), which
                # the objective accepts every time; a step that reverses the last accepted one along the same
                # line (in the centres and width) is cut to the sum of that series, 1 / (1 - rho) of it
                dot = 0.0
                pp = 0.0
                ss = 0.0
                for a in range(P):
                    if a % 3 != 2 and a != 3 * K:
                        dot += step[a] * prev[a]
                        pp += prev[a] * prev[a]
                        ss += step[a] * step[a]
                rho_now = -10.0
                if pp > 0.0 and dot < 0.0 and dot * dot >= _OSC_COS2 * pp * ss:
                    rho = dot / pp
                    if rho > -1.0:
                        fct = 1.0 / (1.0 - rho)
                        for a in range(P):
                            step[a] *= fct
                elif _AIT_SUM and pp > 0.0 and dot > 0.0 and dot * dot >= _AIT_COS2 * pp * ss:
                    # the same series converging from one side (see _AIT_SUM): extended, unless this step already
                    # ends the fit; a trial the objective refuses falls back to the step itself (try 1)
                    rho = dot / pp
                    if (not raw_small and _AIT_RHO[0] <= rho <= _AIT_RHO[1]
                            and abs(rho - rho_last) <= 0.1 * rho):
                        fct = 1.0 / (1.0 - rho)
                        for a in range(P):
                            step[a] *= fct
                    rho_now = rho
                rho_last = rho_now
            bad = False
            small = raw_small
            for a in range(P):
                trial[a] = th[a] + step[a]
            for k in range(K):
                if trial[3 * k + 2] <= 0:
                    bad = True
                if bound_pos and (trial[3 * k] < c0 - 1 or trial[3 * k] > c0 + nc or trial[3 * k + 1] < r0 - 1
                                  or trial[3 * k + 1] > r0 + nr):
                    bad = True
                if abs(step[3 * k]) >= tol or abs(step[3 * k + 1]) >= tol:
                    small = False
            s = trial[3 * K + 1]
            if bad or s < 0.25 * sigma0 or s > 4.0 * sigma0 or (poisson and trial[3 * K] < -rvar):
                small = False
                lam *= 10.0
                continue
            if small:
                # a step below the tolerance ends the fit: taken without evaluating it (the objective,
                # the score and the Fisher matrix change by a negligible amount)
                for a in range(P):
                    th[a] = trial[a]
                break
            ft, rsst = _evaluate(img, r0, nr, c0, nc, trial, K, gain, offset, rvar, poisson, w, Jt, gt)
            if ft >= f:
                for a in range(P):
                    th[a] = trial[a]
                J, Jt = Jt, J
                g, gt = gt, g
                f = ft
                rss = rsst
                lam = max(lam * 0.1, 1e-7)
                improved = True
                for a in range(P):
                    prev[a] = step[a] / fct     # the Gauss-Newton step itself
                has_prev = True
                break
            lam *= 10.0
        if not improved or small:
            converged = True
            break
    # covariance: inverse Fisher information at the last evaluated point (J), scaled by the residual
    # variance for least squares
    scale = 1.0 if poisson else rss / max(npix - P, 1)
    for a in range(P):
        for bb in range(P):
            A[a, bb] = J[a, bb]
        A[a, a] += 1e-12
    if _chol(A, P):
        for a in range(P):
            var[a] = _chol_inv_diag(A, P, a, gt) * scale
    else:
        for a in range(P):
            var[a] = np.nan
    return converged, f, it


@nb.njit(cache=True)
def _fit_one(img, r, c, half, sigma0, gain, offset, rvar, poisson, max_iter, out, cov, w):
    # one spot alone in the window of half-width half around pixel (r, c), started from the border mean
    # (background) and the centroid of the excess; out = (x, y, N, b, s), cov = their variances.
    # Returns (ok, iterations).
    h, wd = img.shape
    r0 = max(0, r - half)
    r1 = min(h - 1, r + half)
    c0 = max(0, c - half)
    c1 = min(wd - 1, c + half)
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    b0 = _border_mean(img, r0, nr, c0, nc, gain, offset)
    plain = gain == 1.0 and offset == 0.0
    sw = 0.0
    sx = 0.0
    sy = 0.0
    for i in range(nr):
        row = img[r0 + i]
        for j in range(nc):
            v = _photons_div(row[c0 + j], offset, gain, plain) - b0
            # the excess only: a pixel at or below b0 (or NaN) adds exact zeros (the sums are >= +0), a select
            # instead of a branch that a noisy window mispredicts at every other pixel
            v = v if v > 0 else 0.0
            sw += v
            sx += v * (c0 + j)
            sy += v * (r0 + i)
    if sw <= 0:
        return False, 0
    out[0] = sx / sw
    out[1] = sy / sw
    out[2] = sw
    out[3] = max(b0, 0.0) if poisson else b0
    out[4] = sigma0
    converged, _, it = _lm(img, r0, nr, c0, nc, out, 1, sigma0, gain, offset, rvar, poisson, max_iter, False, w, cov)
    ok = converged and abs(out[0] - c) <= half and abs(out[1] - r) <= half and out[2] > 0
    return ok, it


@nb.njit(cache=True)
def _moments(img, r, c, half, x, y, bg):
    # eccentricity from the second moments of the background-subtracted spot
    h, w = img.shape
    sw = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for rr in range(max(0, r - half), min(h - 1, r + half) + 1):
        for cc in range(max(0, c - half), min(w - 1, c + half) + 1):
            v = img[rr, cc] - bg
            # as _fit_one's centroid: pixels at or below the background add exact zeros (x, y are finite
            # fitted centres), a select instead of a mispredicted branch
            v = v if v > 0 else 0.0
            sw += v
            sxx += v * (cc - x) ** 2
            syy += v * (rr - y) ** 2
            sxy += v * (cc - x) * (rr - y)
    if sw <= 0:
        return 0.0
    a = sxx / sw
    b = syy / sw
    d = sxy / sw
    tr = a + b
    det = math.sqrt(max((a - b) ** 2 + 4 * d * d, 0.0))
    l1 = 0.5 * (tr + det)
    l2 = 0.5 * (tr - det)
    if l1 <= 0:
        return 0.0
    return math.sqrt(max(1.0 - max(l2, 0.0) / l1, 0.0))


@nb.njit(cache=True)
def _fit_all(img, rows, cols, half, sigma0, gain, offset, rvar, poisson, max_iter):
    n = rows.shape[0]
    params = np.zeros((n, 5))
    var = np.zeros((n, 5))
    ok = np.zeros(n, np.bool_)
    ecc = np.zeros(n)
    out = np.empty(5)
    cv = np.empty(5)
    w = _work(1, 2 * half + 1)
    for k in range(n):
        good, it = _fit_one(img, rows[k], cols[k], half, sigma0, gain, offset, rvar, poisson, max_iter, out, cv, w)
        params[k] = out
        var[k] = cv
        ok[k] = good
        if good:
            ecc[k] = _moments(img, rows[k], cols[k], half, out[0], out[1], out[3] * gain + offset)
    return params, var, ok, ecc


@nb.njit(cache=True)
def _fit_group(img, r0, r1, c0, c1, x0, y0, amp, sigma0, gain, offset, rvar, poisson, max_iter, th, var):
    # joint maximum-likelihood fit of K = len(x0) overlapping spots in the window rows r0..r1, cols c0..c1:
    # parameters th = (x_1, y_1, N_1, ..., x_K, y_K, N_K, background, width); var = diagonal of the
    # inverse Fisher information (scaled by the residual variance for least squares).
    # Returns (converged, log-likelihood).
    K = x0.shape[0]
    nr = r1 - r0 + 1
    nc = c1 - c0 + 1
    b0 = _border_mean(img, r0, nr, c0, nc, gain, offset)
    sw = 0.0
    for i in range(nr):
        for j in range(nc):
            v = (img[r0 + i, c0 + j] - offset) / gain - b0
            sw += v if v > 0 else 0.0       # the excess (a select: see _fit_one)
    asum = 0.0
    for k in range(K):
        asum += max(amp[k], 1e-12)
    for k in range(K):
        th[3 * k] = x0[k]
        th[3 * k + 1] = y0[k]
        th[3 * k + 2] = max(sw * max(amp[k], 1e-12) / asum, 1.0)
    th[3 * K] = max(b0, 0.0) if poisson else b0
    th[3 * K + 1] = sigma0
    w = _work(K, max(nr, nc))
    converged, f, _ = _lm(img, r0, nr, c0, nc, th, K, sigma0, gain, offset, rvar, poisson, max_iter, True, w, var)
    return converged, f


@nb.njit(cache=True)
def _fit_tasks(img, rows, cols, amps, ptr, members, report, half, sigma0, gain, offset, rvar, poisson, max_iter,
               params, var, ok, ecc):
    # joint fits of groups of neighbouring spots: task t fits members[ptr[t]:ptr[t+1]] together in the union
    # of their (2 half + 1)^2 windows and writes the results of the members flagged in report
    h, w = img.shape
    for t in range(ptr.shape[0] - 1):
        m = members[ptr[t]:ptr[t + 1]]
        K = m.shape[0]
        r0 = h
        r1 = 0
        c0 = w
        c1 = 0
        x0 = np.empty(K)
        y0 = np.empty(K)
        a0 = np.empty(K)
        for k in range(K):
            q = m[k]
            r0 = min(r0, max(0, rows[q] - half))
            r1 = max(r1, min(h - 1, rows[q] + half))
            c0 = min(c0, max(0, cols[q] - half))
            c1 = max(c1, min(w - 1, cols[q] + half))
            x0[k] = cols[q]
            y0[k] = rows[q]
            a0[k] = amps[q]
        th = np.empty(3 * K + 2)
        vv = np.empty(3 * K + 2)
        conv, _ = _fit_group(img, r0, r1, c0, c1, x0, y0, a0, sigma0, gain, offset, rvar, poisson, max_iter, th, vv)
        for k in range(K):
            if not report[ptr[t] + k]:
                continue
            q = m[k]
            params[q, 0] = th[3 * k]
            params[q, 1] = th[3 * k + 1]
            params[q, 2] = th[3 * k + 2]
            params[q, 3] = th[3 * K]
            params[q, 4] = th[3 * K + 1]
            var[q, 0] = vv[3 * k]
            var[q, 1] = vv[3 * k + 1]
            var[q, 2] = vv[3 * k + 2]
            var[q, 3] = vv[3 * K]
            var[q, 4] = vv[3 * K + 1]
            good = (conv and abs(th[3 * k] - cols[q]) <= half and abs(th[3 * k + 1] - rows[q]) <= half
                    and th[3 * k + 2] > 0)
            ok[q] = good
            if good:
                ecc[q] = _moments(img, rows[q], cols[q], half, th[3 * k], th[3 * k + 1], th[3 * K] * gain + offset)


@nb.njit(cache=True)
def _split_spots(img, rows, cols, params, cand, half, sigma0, gain, offset, rvar, poisson, max_iter, min_llr,
                 out, var, accepted, llr):
    # For each candidate spot q = cand[k] (fitted alone, suspiciously wide or elongated), fit two spots
    # started on either side of the centre along the major axis of the spot's second moments, in the
    # same window. Accept when the likelihood gains more than min_llr (log units), both parts carry
    # >= 15 % of the photons and they are >= sigma0 apart: two spots closer than ~2.8 sigma merge into
    # one maximum of the matched filter, so detection alone cannot separate them.
    h, w = img.shape
    K1 = np.empty(5)
    ex = np.empty((2, 2 * half + 1))
    ey = np.empty((2, 2 * half + 1))
    dxx = np.empty((2, 2 * half + 1))
    dxs = np.empty((2, 2 * half + 1))
    dyy = np.empty((2, 2 * half + 1))
    dys = np.empty((2, 2 * half + 1))
    th = np.empty(8)
    vv = np.empty(8)
    x0 = np.empty(2)
    y0 = np.empty(2)
    a0 = np.ones(2)
    for k in range(cand.shape[0]):
        q = cand[k]
        r = rows[q]
        c = cols[q]
        r0 = max(0, r - half)
        r1 = min(h - 1, r + half)
        c0 = max(0, c - half)
        c1 = min(w - 1, c + half)
        nr = r1 - r0 + 1
        nc = c1 - c0 + 1
        xc = params[q, 0]
        yc = params[q, 1]
        bgc = params[q, 3]
        # single-spot likelihood in this window
        K1[0] = xc
        K1[1] = yc
        K1[2] = params[q, 2]
        K1[3] = bgc
        K1[4] = params[q, 4]
        f1 = _group_objective(img, r0, nr, c0, nc, K1, 1, gain, offset, rvar, poisson, ex, ey, dxx, dxs, dyy, dys)
        # major axis of the excess
        sw = 0.0
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for i in range(nr):
            for j in range(nc):
                v = (img[r0 + i, c0 + j] - offset) / gain - bgc
                v = v if v > 0 else 0.0     # the excess, exact zeros elsewhere (a select: see _fit_one)
                dx = c0 + j - xc
                dy = r0 + i - yc
                sw += v
                sxx += v * dx * dx
                syy += v * dy * dy
                sxy += v * dx * dy
        if sw <= 0:
            continue
        a = sxx / sw
        b = syy / sw
        d_ = sxy / sw
        ang = 0.5 * math.atan2(2 * d_, a - b)
        det = math.sqrt(max((a - b) ** 2 + 4 * d_ * d_, 0.0))
        sep = 2.0 * math.sqrt(max(det, 0.25))
        sep = min(max(sep, 1.0 * sigma0), 3.0 * sigma0)
        ca = math.cos(ang) * 0.5 * sep
        sa = math.sin(ang) * 0.5 * sep
        x0[0] = xc + ca
        y0[0] = yc + sa
        x0[1] = xc - ca
        y0[1] = yc - sa
        conv, f2 = _fit_group(img, r0, r1, c0, c1, x0, y0, a0, sigma0, gain, offset, rvar, poisson, max_iter, th, vv)
        gain_ll = f2 - f1
        if not poisson:
            # least squares: f = -RSS/2 in image units; in log-likelihood units divide by the noise
            # variance, estimated from the two-spot residual
            s2 = -2.0 * f2 / max(nr * nc - 8, 1)
            gain_ll = gain_ll / max(s2, 1e-300)
        llr[k] = gain_ll
        if not conv or gain_ll < min_llr:
            continue
        N1 = th[2]
        N2 = th[5]
        dd = math.hypot(th[0] - th[3], th[1] - th[4])
        if min(N1, N2) < 0.15 * (N1 + N2) or dd < sigma0:
            continue
        ok2 = True
        for m in range(2):
            if abs(th[3 * m] - c) > half or abs(th[3 * m + 1] - r) > half:
                ok2 = False
        if not ok2:
            continue
        accepted[k] = True
        for m in range(2):
            out[k, m, 0] = th[3 * m]
            out[k, m, 1] = th[3 * m + 1]
            out[k, m, 2] = th[3 * m + 2]
            out[k, m, 3] = th[6]
            out[k, m, 4] = th[7]
            var[k, m, 0] = vv[3 * m]
            var[k, m, 1] = vv[3 * m + 1]
            var[k, m, 2] = vv[3 * m + 2]
            var[k, m, 3] = vv[6]
            var[k, m, 4] = vv[7]


@nb.njit(cache=True)
def _within_radius(x, y, order, radius, k):
    # each point with all the others closer than radius (strictly, as cKDTree's distance_upper_bound), itself
    # included, as a sorted row of k indices padded with n; crowded: some point has more than k - 1 such
    # neighbours (then its nearest k - 1 are wanted, which the caller takes from a k-d tree). The points are
    # sorted by y (order) and searched up and down the sorted list while the y gap is within radius.
    n = x.shape[0]
    keys = np.full((n, k), n, np.int64)
    r2 = radius * radius
    crowded = False
    for a in range(n):
        ia = order[a]
        m = 1
        keys[ia, 0] = ia
        for step in (1, -1):
            b = a + step
            while 0 <= b < n:
                ib = order[b]
                dy = y[ib] - y[ia]
                if dy * dy >= r2:
                    break
                dx = x[ib] - x[ia]
                if math.sqrt(dx * dx + dy * dy) < radius:
                    if m < k:
                        keys[ia, m] = ib
                    m += 1
                b += step
        if m > k:
            crowded = True
        keys[ia, :min(m, k)].sort()
    return keys, crowded


@nb.njit(cache=True)
def _tasks_from_keys(keys, n):
    # _neighbour_tasks' (grouped, ptr, members, report) from the sorted neighbour rows `keys` (padded with n) of
    # the n spots, each group coded as one integer in base n + 1 ((n + 1)^K < 2^62): the distinct groups in
    # increasing code (the lexicographic order of their rows, as np.unique gives them), members in order, each
    # spot with a neighbour reported from its own group's task at its place among the members
    m, K = keys.shape
    grouped = np.zeros(m, np.bool_)
    owners = np.empty(m, np.int64)
    cnt = 0
    for a in range(m):
        if keys[a, 1] < n:
            owners[cnt] = a
            grouped[a] = True
            cnt += 1
    code = np.empty(cnt, np.int64)
    for t in range(cnt):
        v = 0
        for j in range(K):
            v = v * (n + 1) + keys[owners[t], j]
        code[t] = v
    order = np.argsort(code)
    inv = np.empty(cnt, np.int64)
    first = np.empty(cnt, np.int64)
    nu = 0
    for q in range(cnt):
        t = order[q]
        if q == 0 or code[t] != code[order[q - 1]]:
            first[nu] = t
            nu += 1
        inv[t] = nu - 1
    ptr = np.zeros(nu + 1, np.int64)
    for u in range(nu):
        a = owners[first[u]]
        k = 0
        for j in range(K):
            if keys[a, j] < n:
                k += 1
        ptr[u + 1] = ptr[u] + k
    members = np.empty(ptr[nu], np.int64)
    for u in range(nu):
        a = owners[first[u]]
        p = ptr[u]
        for j in range(K):
            if keys[a, j] < n:
                members[p] = keys[a, j]
                p += 1
    report = np.zeros(ptr[nu], np.bool_)
    for t in range(cnt):
        a = owners[t]
        below = 0
        for j in range(K):
            if keys[a, j] < a:
                below += 1
        report[ptr[inv[t]] + below] = True
    return grouped, ptr, members, report


def _neighbour_tasks(rows, cols, radius: float, max_group: int):
    """Groups for joint fitting: each spot with neighbours closer than ``radius`` (px) is fitted together
    with its nearest ``max_group - 1`` of them; identical groups are fitted once.

    Returns (grouped mask, ptr, members, report) in the layout of :func:`_fit_tasks`.
    """
    from scipy.spatial import cKDTree

    n = len(rows)
    grouped = np.zeros(n, bool)
    empty = (grouped, np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.bool_))
    if n < 2 or max_group < 2:
        return empty
    kq = min(max_group, n)
    y = np.asarray(rows, np.float64)
    keys, crowded = _within_radius(np.asarray(cols, np.float64), y, np.argsort(y, kind="stable"),
                                   float(radius), kq)
    if crowded:
        # a spot with more neighbours in reach than a group holds: its nearest ones by the k-d tree
        pts = np.c_[cols, rows].astype(float)
        d, idx = cKDTree(pts, balanced_tree=False, compact_nodes=False).query(pts, k=kq, distance_upper_bound=radius)
        idx = np.where(np.isfinite(d), idx, n)              # missing neighbours -> n (sorted last)
        keys = np.sort(idx, axis=1)
    K = keys.shape[1]
    if (n + 1.0) ** K < 2.0 ** 62:
        # each sorted group as one integer in base n + 1 (same order as the rows), the tasks from their sort in
        # one numba pass (the numpy steps below cost ~10x more on a frame's few hundred spots)
        return _tasks_from_keys(keys, n)
    has = keys[:, 1] < n
    if not has.any():
        return empty
    grouped[has] = True
    keys = keys[has]
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = np.asarray(inv).ravel()
    counts = (uniq < n).sum(axis=1)
    ptr = np.zeros(len(uniq) + 1, np.int64)
    ptr[1:] = np.cumsum(counts)
    members = uniq[uniq < n].astype(np.int64)               # row-major: each task's members in order
    report = np.zeros(len(members), np.bool_)
    owners = np.nonzero(has)[0]
    # each grouped spot is reported from its own task (members are sorted, so its place is a count)
    report[ptr[inv] + (keys < owners[:, None]).sum(axis=1)] = True
    return grouped, ptr, members, report


def fit_spots(img, rows, cols, sigma: float, gain: float = 1.0, offset: float = 0.0, read_noise: float = 0.0,
              poisson: bool = True, half: int | None = None, max_iter: int = 40, amps=None,
              group_radius: float | None = None, max_group: int = 5, split: bool = False,
              split_width: float = 1.1, split_ecc: float = 0.6, split_llr: float = 12.0):
    """Fit a pixel-integrated Gaussian to each spot by maximum likelihood.

    Parameters
    ----------
    img : 2D array
        Raw frame in camera counts (``poisson=True``), or any background-
        subtracted image (``poisson=False``: least squares).
    rows, cols : array_like of int
        Starting pixels (from :func:`find_peaks`).
    sigma : float
        Starting spot width (px); the width is fitted within [sigma/4, 4 sigma].
    gain : float
        Camera counts per photon (ADU per detected photo-electron).
    offset : float
        Camera baseline (counts at zero light).
    read_noise : float
        RMS read noise (photo-electrons).
    poisson : bool
        Maximum likelihood with Poisson (+ read noise) statistics; else least squares.
    half : int, optional
        Half-width of the fitting window (px), default ceil(3 sigma), at least 3.
    amps : array_like, optional
        Relative brightness of each spot (e.g. the detection signal), used to
        share the photons between jointly fitted spots at the start.
    group_radius : float, optional
        Spots closer than this (px; default ``half + 2 sigma``, where a
        neighbour's light reaches into the fit window) are fitted jointly:
        each with its nearest ``max_group - 1`` neighbours, as a sum of
        Gaussians (own position and photons, shared background and width) over
        the union of their windows. Fitting them one by one would pull each
        centre towards its neighbour (or lose the fit), which drops or biases
        exactly the displacements where particles approach each other. 0
        disables joint fitting.
    max_group : int
        Largest number of spots in one joint fit.
    split : bool
        Test each spot fitted alone whose width exceeds ``split_width *
        sigma`` or whose eccentricity exceeds ``split_ecc`` for being two
        unresolved spots (closer than ~2.8 sigma, one maximum of the matched
        filter): a two-spot fit replaces it when the log-likelihood gains more
        than ``split_llr``, both parts carry >= 15 % of the photons and they
        are >= sigma apart. The output then has more rows than the input;
        ``index`` maps each row to its input spot.

    Returns
    -------
    dict of ndarrays
        ``x``, ``y`` (px), ``photons``, ``bg`` (photons/px), ``s`` (px),
        ``var_x``, ``var_y`` (px^2), ``ok`` (bool), ``ecc``, ``index`` (input
        spot of each row: ``arange(len(rows))`` unless spots were split).
    """
    rows = np.ascontiguousarray(rows, np.int64)
    cols = np.ascontiguousarray(cols, np.int64)
    half = max(3, int(math.ceil(3 * sigma))) if half is None else int(half)
    img = np.ascontiguousarray(img)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        img = img.astype(np.float32)
    radius = half + 2.0 * float(sigma) if group_radius is None else float(group_radius)
    if radius > 0 and len(rows) > 1:
        grouped, ptr, members, report = _neighbour_tasks(rows, cols, radius, int(max_group))
    else:
        grouped = np.zeros(len(rows), bool)
    # the cheap path: spots without a neighbour are fitted alone; spots with one only in their joint fit
    # (a single fit of them would be overwritten)
    alone = np.nonzero(~grouped)[0]
    p = np.zeros((len(rows), 5))
    v = np.zeros((len(rows), 5))
    ok = np.zeros(len(rows), bool)
    ecc = np.zeros(len(rows))
    if len(alone):
        p[alone], v[alone], ok[alone], ecc[alone] = _fit_all(img, rows[alone], cols[alone], half, float(sigma),
                                                             float(gain), float(offset), float(read_noise) ** 2,
                                                             bool(poisson), int(max_iter))
    if grouped.any():
        a = np.ones(len(rows)) if amps is None else np.ascontiguousarray(amps, np.float64)
        _fit_tasks(img, rows, cols, a, ptr, members, report, half, float(sigma), float(gain), float(offset),
                   float(read_noise) ** 2, bool(poisson), int(max_iter), p, v, ok, ecc)
    index = np.arange(len(rows))
    if split and len(rows):
        # "wide" relative to the spots' own typical width (median over the isolated fits, when there are
        # enough), not the starting width: a start off by 20 % must not send every spot to the split test
        iso = ok & ~grouped
        ref = fast_median(p[iso, 4]) if iso.sum() >= 10 else float(sigma)
        cand = np.nonzero(ok & ~grouped & ((p[:, 4] > split_width * ref) | (ecc > split_ecc)))[0]
        if len(cand):
            out = np.zeros((len(cand), 2, 5))
            vout = np.zeros((len(cand), 2, 5))
            acc = np.zeros(len(cand), np.bool_)
            llr = np.full(len(cand), np.nan)
            _split_spots(img, rows, cols, p, cand.astype(np.int64), half, float(sigma), float(gain), float(offset),
                         float(read_noise) ** 2, bool(poisson), int(max_iter), float(split_llr), out, vout, acc, llr)
            if acc.any():
                q = cand[acc]
                p[q], v[q] = out[acc, 0], vout[acc, 0]
                p = np.concatenate([p, out[acc, 1]])
                v = np.concatenate([v, vout[acc, 1]])
                ok = np.concatenate([ok, np.ones(len(q), bool)])
                index = np.concatenate([index, q])
                ecc = np.concatenate([ecc, np.zeros(len(q))])
                for i in np.r_[q, np.arange(len(rows), len(p))]:   # split spots only: a few per frame
                    x, y, b = p[i, 0], p[i, 1], p[i, 3]
                    ecc[i] = _moments(img, int(round(y)), int(round(x)), half, x, y, b * gain + offset)
    return {"x": p[:, 0], "y": p[:, 1], "photons": p[:, 2], "bg": p[:, 3], "s": p[:, 4],
            "var_x": v[:, 0], "var_y": v[:, 1], "ok": ok, "ecc": ecc, "index": index}


def mortensen_sigma(photons, bg, s, a: float = 1.0):
    """Cramer-Rao localisation precision of a maximum-likelihood Gaussian fit (Mortensen et al. 2010, eq. 5).

    Parameters
    ----------
    photons : float or array
        Detected photons per spot.
    bg : float or array
        Background photons per pixel.
    s : float or array
        Gaussian width of the PSF (px, without pixelation).
    a : float
        Pixel size (same unit as ``s``; 1 for px).

    Returns
    -------
    float or ndarray
        Standard deviation per axis, in the unit of ``s``.
    """
    from scipy.special import spence

    N = np.asarray(photons, float)
    b = np.asarray(bg, float)
    sa2 = np.asarray(s, float) ** 2 + a * a / 12.0
    tau = 2 * np.pi * sa2 * b / (N * a * a)
    with np.errstate(divide="ignore", invalid="ignore"):
        # int_0^1 ln t / (1 + t/tau) dt = tau * Li2(-1/tau), Li2(z) = spence(1 - z)
        integral = np.where(tau > 1e-12, tau * spence(1.0 + 1.0 / np.maximum(tau, 1e-300)), 0.0)
    return np.sqrt(sa2 / N / (1.0 + integral))


def cramer_rao_bound(psf, oversample: int, photons: float, background: float, read_noise: float = 0.0):
    """Exact Cramer-Rao bound on x and y (px) for a sampled PSF, from its Fisher information.

    Mortensen's formula (:func:`mortensen_sigma`) assumes a Gaussian PSF; a
    real (Airy) PSF puts photons into its rings, so its bound differs. This
    computes the bound of the true pixelated PSF with Poisson photons and
    Gaussian read noise (as extra Poisson-like variance).

    Parameters
    ----------
    psf : 2D array
        Pixel-integrated PSF sampled every 1/``oversample`` px, centred on a
        sample whose indices are multiples of ``oversample`` (the layout of
        ``sim.render.psf_image(..., oversample=k)``).
    oversample : int
    photons : float
        Detected photons per spot.
    background : float
        Background photons per pixel.
    read_noise : float
        e- rms.

    Returns
    -------
    (float, float)
        Standard deviation bound for x (columns) and y (rows), px, for a
        spot centred on a pixel.
    """
    ov = int(oversample)
    P = np.asarray(psf, float)
    c = np.unravel_index(int(np.argmax(P)), P.shape)
    P = np.roll(P, (-(c[0] % ov), -(c[1] % ov)), axis=(0, 1))   # put the peak on the pixel grid
    I0 = P[0::ov, 0::ov]
    norm = I0.sum()
    mu = photons * I0 / norm + background + read_noise ** 2
    out = []
    for axis in (1, 0):
        if axis == 1:
            plus, minus = P[0::ov, 1::ov], np.roll(P[0::ov, ov - 1::ov], 1, axis=1)
        else:
            plus, minus = P[1::ov, 0::ov], np.roll(P[ov - 1::ov, 0::ov], 1, axis=0)
        d = photons * (plus - minus) / (2.0 / ov) / norm
        out.append(1.0 / np.sqrt(np.sum(d * d / mu)))
    return out[0], out[1]
