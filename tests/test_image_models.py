"""An independent judge of the image pipeline: a second, deliberately plain image model written here.

Nothing of ``sim.render`` is used. The model (all lengths in px, photons = e-):

- **fluorescence in focus**: the Airy pattern ``[2 J1(v)/v]^2`` with ``v = pi r / a``
  (``a = lambda / (2 NA)`` = 2.2 px, first dark ring at 1.22 a = 2.7 px), integrated
  over each pixel (5x5 sub-samples);
- **fluorescence out of focus**: the geometric blur disk of radius ``R = 1.5 px/um * |z|``
  (half its light in a bright rim at R), blurred by a Gaussian of 0.9 px;
- **absorption brightfield**: transmission ``1 - A exp(-r^2 / 2 s0^2) + B tanh(z / z1) J0(k r)
  exp(-r^2 / 2 w^2)``: an absorbing core plus a damped J0 (transport-of-intensity) term whose
  sign flips with the sign of the defocus z (z > 0: bright centre in a dark ring; z < 0: dark
  centre in a bright ring) and whose rings spread with |z|;
- **uneven illumination**: a linear gradient (+-15 %) times vignetting (-30 % at the corners),
  multiplying the background (fluorescence: the excitation, so the beads too) or the
  transmitted field (brightfield);
- **dust**: large faint blobs (sigma 10-18 px; fluorescence 15-40 % of the background, added;
  brightfield 3-8 % absorbing, multiplied);
- **camera**: Poisson photons, gain 1, offset 100 counts, Gaussian read noise 1.5 e-.

Particles sit on a jittered 40 px grid: isolated (the largest image reaches ~13 px). For each
polarity x defocus, :func:`ptrack.locate` with no option at all must give recall and precision
>= 0.95 (a match within 1 px, or 0.5 x the ring radius for big rings) and an RMSE per axis
<= 1.5 x the Cramer-Rao bound of this model (Fisher information of the Poisson + read-noise
likelihood, by central differences of the expected image, with the brightness and the
background level as nuisance parameters, per particle). bench/bench_image_models.py prints
the same table beside trackpy's.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfc, j0, j1

# ---------------------------------------------------------------------------------------------
# the image model
# ---------------------------------------------------------------------------------------------

SHAPE = (360, 360)      # px
SPACING = 40            # px between particles (isolated)
HALF = 18               # patch half-width (px) holding one particle's image
SUB = 5                 # sub-samples per pixel side (pixel integration)
OFFSET, READ_NOISE = 100.0, 1.5   # counts, e- (gain 1)

AIRY_A = 2.2            # lambda / (2 NA), px
BLUR = 0.9              # Gaussian blur of the defocused fluorescence disk, px
DISK_PER_UM = 1.5       # geometric blur radius per um of defocus, px
N_PHOTONS, BG = 4000.0, 30.0        # fluorescence: photons per bead, background photons per px (mean field)
FIELD = 400.0           # brightfield: transmitted photons per px
ABS_A, ABS_S = 0.25, 1.4             # absorbing core: depth, width (px)
TIE_B, TIE_Z1 = 0.35, 1.0            # defocus term: amplitude, saturation defocus (um)

#: the cases: (name, kind, defocus in um)
CASES = ([("fluor", "fluor", z) for z in (0.0, 1.0, 2.0, 4.0, 6.0)]
         + [("bf", "bf", z) for z in (-3.0, -1.5, 0.0, 1.5, 3.0)])


def case_id(case):
    """Short label of a case, e.g. ``fluor z=+2.0``."""
    return f"{case[1]} z={case[2]:+.1f}"


def _bf_ring(z):
    # first zero (px) and damping width (px) of the J0 term at defocus z (um)
    r1 = 2.0 + 0.8 * abs(z)
    return r1, 1.3 * r1 + 1.0


def profile(kind, z, r):
    """Radial profile at distance ``r`` (px) from the centre.

    Fluorescence: photons per px^2 of a unit-integral image. Brightfield: the
    contrast ``T - 1`` of the transmission T.
    """
    r = np.asarray(r, float)
    if kind == "fluor":
        if z == 0.0:
            v = np.pi * np.maximum(r, 1e-9) / AIRY_A
            return (2 * j1(v) / v) ** 2 * np.pi / (4 * AIRY_A ** 2)   # integral over the plane: 1
        R = DISK_PER_UM * abs(z)
        disk = 0.5 * erfc((r - R) / (math.sqrt(2) * BLUR))
        rim = np.exp(-(r - R) ** 2 / (2 * BLUR ** 2))
        # normalise numerically on a fine radial grid
        rr = np.linspace(0, R + 8 * BLUR, 4000)
        dn = 0.5 * erfc((rr - R) / (math.sqrt(2) * BLUR))
        rn = np.exp(-(rr - R) ** 2 / (2 * BLUR ** 2))
        nd = np.trapezoid(dn * 2 * np.pi * rr, rr)
        nr = np.trapezoid(rn * 2 * np.pi * rr, rr)
        return 0.5 * disk / nd + 0.5 * rim / nr
    r1, w = _bf_ring(z)
    k = 2.404826 / r1
    return -ABS_A * np.exp(-r ** 2 / (2 * ABS_S ** 2)) + TIE_B * math.tanh(z / TIE_Z1) * j0(k * r) * np.exp(-r ** 2 / (2 * w ** 2))


def image_radius(kind, z):
    """Radius (px) of the particle's image: the ring radius, or the first dark ring in focus."""
    if kind == "fluor":
        return 1.22 * AIRY_A if z == 0.0 else max(DISK_PER_UM * abs(z), 1.22 * AIRY_A)
    return 3.8317 / (2.404826 / _bf_ring(z)[0]) if z != 0.0 else 2.0 * ABS_S   # the first ring's extremum


def match_radius(kind, z):
    """Distance (px) within which a detection counts as the particle: 1 px, or 0.5 x a big ring's radius."""
    return max(1.0, 0.5 * image_radius(kind, z))


def patch(kind, z, x, y, r0, c0, n=2 * HALF + 1):
    """The pixel-integrated profile over the ``n`` x ``n`` pixels whose top-left pixel is (r0, c0)."""
    o = (np.arange(SUB) + 0.5) / SUB - 0.5
    rows = r0 + np.arange(n)
    cols = c0 + np.arange(n)
    yy = (rows[:, None] + o[None, :]).reshape(-1)
    xx = (cols[:, None] + o[None, :]).reshape(-1)
    r = np.hypot(xx[None, :] - x, yy[:, None] - y)
    p = profile(kind, z, r)
    return p.reshape(n, SUB, n, SUB).mean(axis=(1, 3))


def fields(shape, rng, kind):
    """Illumination (relative, mean ~1) and dust of a frame (fluorescence: added photons; brightfield: factor)."""
    H, W = shape
    yy, xx = np.mgrid[:H, :W].astype(float)
    g = rng.uniform(0, 2 * np.pi)
    grad = 1 + 0.15 * (np.cos(g) * (xx / W - 0.5) + np.sin(g) * (yy / H - 0.5)) * 2
    rc2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    illum = grad * (1 - 0.3 * rc2)
    illum /= illum.mean()
    n_dust = 4
    dust = np.zeros(shape) if kind == "fluor" else np.ones(shape)
    for _ in range(n_dust):
        dx, dy = rng.uniform(0, W), rng.uniform(0, H)
        s = rng.uniform(10, 18)
        blob = np.exp(-((xx - dx) ** 2 + (yy - dy) ** 2) / (2 * s ** 2))
        if kind == "fluor":
            dust += rng.uniform(0.15, 0.4) * BG * blob
        else:
            dust *= 1 - rng.uniform(0.03, 0.08) * blob
    return illum, dust


def positions(shape, rng, spacing=SPACING, margin=HALF + 2):
    """Jittered grid (px): true x (columns), y (rows)."""
    gy, gx = np.meshgrid(np.arange(margin, shape[0] - margin + 1, spacing, dtype=float),
                         np.arange(margin, shape[1] - margin + 1, spacing, dtype=float), indexing="ij")
    j = 0.5 * spacing - HALF - 1
    return (gx.ravel() + rng.uniform(-j, j, gx.size) + rng.uniform(-0.5, 0.5, gx.size),
            gy.ravel() + rng.uniform(-j, j, gx.size) + rng.uniform(-0.5, 0.5, gx.size))


def expected(case, shape, rng):
    """Expected image (photons, without offset) and the frame's ingredients.

    Returns (mu, xs, ys, illum, dust) with mu in photons per px.
    """
    _, kind, z = case
    illum, dust = fields(shape, rng, kind)
    xs, ys = positions(shape, rng)
    if kind == "fluor":
        mu = BG * illum + dust
    else:
        contrast = np.zeros(shape)
    for x, y in zip(xs, ys):
        r0, c0 = int(round(y)) - HALF, int(round(x)) - HALF
        p = patch(kind, z, x, y, r0, c0)
        sl = (slice(r0, r0 + 2 * HALF + 1), slice(c0, c0 + 2 * HALF + 1))
        if kind == "fluor":
            mu[sl] += N_PHOTONS * illum[int(round(y)), int(round(x))] * p
        else:
            contrast[sl] += p
    if kind == "bf":
        mu = FIELD * illum * dust * (1 + contrast)
    return mu, xs, ys, illum, dust


def frame(case, rng, shape=SHAPE, crb_every=4):
    """One camera frame of a case: (uint16 counts, true x, true y, CRB per axis in px).

    The bound is computed for every ``crb_every``-th particle (it varies only
    with the illumination; the RMS over a quarter of them is within a few per
    cent of the RMS over all).
    """
    mu, xs, ys, illum, dust = expected(case, shape, rng)
    counts = rng.poisson(mu) + OFFSET + READ_NOISE * rng.normal(size=shape)
    crb = np.array([crb_xy(case, x, y, illum, dust) for x, y in zip(xs[::crb_every], ys[::crb_every])])
    return np.clip(np.round(counts), 0, 65535).astype(np.uint16), xs, ys, crb


def fisher_crb(mu, derivs, read_noise=READ_NOISE):
    """Cramer-Rao bounds (standard deviations) of the parameters of an expected image.

    Parameters
    ----------
    mu : array
        Expected photons per pixel.
    derivs : sequence of arrays
        Derivatives of ``mu`` with respect to each parameter.
    read_noise : float
        Gaussian read noise (e- rms): the likelihood of each pixel is taken
        as Gaussian-Poisson with variance ``mu + read_noise^2`` (the usual
        sCMOS approximation).

    Returns
    -------
    array
        sqrt of the diagonal of the inverse Fisher matrix.
    """
    J = np.stack([np.ravel(d) for d in derivs])
    F = (J / (np.ravel(mu) + read_noise ** 2)) @ J.T
    return np.sqrt(np.diag(np.linalg.inv(F)))


def crb_xy(case, x, y, illum, dust, h=1e-3):
    """Cramer-Rao bound (px, RMS of the x and y bounds) of one particle of this model.

    Fisher information (:func:`fisher_crb`) over the particle's patch,
    parameters (x, y, brightness, background level); the x and y derivatives
    by central differences of the rendered expected image.
    """
    _, kind, z = case
    r0, c0 = int(round(y)) - HALF, int(round(x)) - HALF
    sl = (slice(r0, r0 + 2 * HALF + 1), slice(c0, c0 + 2 * HALF + 1))
    il, du = illum[sl], dust[sl]

    def mu(xx, yy):
        p = patch(kind, z, xx, yy, r0, c0)
        if kind == "fluor":
            sig = N_PHOTONS * illum[int(round(y)), int(round(x))] * p
            return BG * il + du + sig, sig, BG * il + du
        bgf = FIELD * il * du
        return bgf * (1 + p), bgf * p, bgf
    m, sig, bg = mu(x, y)
    dx = (mu(x + h, y)[0] - mu(x - h, y)[0]) / (2 * h)
    dy = (mu(x, y + h)[0] - mu(x, y - h)[0]) / (2 * h)
    c = fisher_crb(m, [dx, dy, sig, bg])
    return float(np.sqrt(0.5 * (c[0] ** 2 + c[1] ** 2)))


def scores(x_found, y_found, xs, ys, radius):
    """Recall, precision and RMSE per axis (px) of detections against the truth.

    The toolkit's one rule, :func:`ptrack.motion.detection_scores`: each
    detection is paired with its nearest true particle when closer than
    ``radius`` px; recall is the fraction of true particles paired, precision
    the fraction of detections paired, the RMSE over the pairs and both axes.
    """
    from ptrack.motion import detection_scores

    f = np.c_[np.asarray(x_found, float), np.asarray(y_found, float)]
    if len(f) == 0:
        return 0.0, 0.0, np.nan
    s = detection_scores(f, np.c_[xs, ys], max_px=radius)
    return s["recall"], s["precision"], float(np.sqrt(np.mean(s["rmse"] ** 2)))


def run_case(case, locator, n_frames=2, seed=0):
    """Render ``n_frames`` frames of a case, locate with ``locator(frame) -> (x, y)``, score.

    Returns a dict: recall, precision, rmse (px per axis), crb (px, RMS over
    the particles), ratio rmse / crb, n (particles).
    """
    rng = np.random.default_rng([seed, CASES.index(case)])
    fx, fy, tx, ty, crbs = [], [], [], [], []
    shift = 0.0
    for _ in range(n_frames):
        img, xs, ys, crb = frame(case, rng)
        x, y = locator(img)
        # frames side by side: one scoring over all particles
        fx.append(np.asarray(x, float) + shift)
        fy.append(np.asarray(y, float))
        tx.append(xs + shift)
        ty.append(ys)
        crbs.append(crb)
        shift += 10 * SHAPE[1]
    rec, prec, rmse = scores(np.concatenate(fx), np.concatenate(fy), np.concatenate(tx), np.concatenate(ty),
                             match_radius(case[1], case[2]))
    crb = float(np.sqrt(np.mean(np.concatenate(crbs) ** 2)))
    return {"recall": rec, "precision": prec, "rmse": rmse, "crb": crb, "ratio": rmse / crb,
            "n": int(sum(len(t) for t in tx))}


def ptrack_locator(img):
    """ptrack's default :func:`ptrack.locate` (no option): detections (x, y) in px."""
    from ptrack.locate import locate

    df = locate(img)
    return df["x_px"].to_numpy(), df["y_px"].to_numpy()


# ---------------------------------------------------------------------------------------------
# checks of the model itself (a judge must be right before it judges)
# ---------------------------------------------------------------------------------------------

def test_model_profiles_integrate_to_one_and_flip_with_defocus():
    r = np.linspace(0, 60, 200001)
    for z in (0.0, 1.0, 4.0):
        total = np.trapezoid(profile("fluor", z, r) * 2 * np.pi * r, r)
        # the Airy tail beyond 60 px holds 2 / (pi v) ~ 0.7 % of the light
        assert abs(total - 1) < (0.01 if z == 0 else 1e-4), (z, total)
    assert profile("bf", 1.5, 0.0) > 0 > profile("bf", 1.5, image_radius("bf", 1.5))
    assert profile("bf", -1.5, 0.0) < 0 < profile("bf", -1.5, image_radius("bf", -1.5))
    assert profile("bf", 0.0, 0.0) == pytest.approx(-ABS_A)
    # pixel integration conserves the light of a patch-sized image
    p = patch("fluor", 2.0, 18.3, 18.7, 0, 0)
    assert p.sum() == pytest.approx(1.0, abs=2e-3)


def test_fisher_bound_of_a_pixelated_gaussian_is_the_closed_form():
    """The Fisher machinery (finite differences, nuisance brightness) reproduces the closed form
    sigma^2 = (s^2 + 1/12) / N of a pixel-integrated Gaussian spot without background, and the bound
    of the model's own Airy spot lies between the photon-only and 3x the photon-only figures."""
    from scipy.special import erf

    def gauss(x0, y0, s=1.5, n=21):
        e = lambda c: 0.5 * (erf((np.arange(n) - c + 0.5) / (math.sqrt(2) * s))
                             - erf((np.arange(n) - c - 0.5) / (math.sqrt(2) * s)))
        return np.outer(e(y0), e(x0))
    N, h = 1e4, 1e-4
    m = N * gauss(10.3, 9.8)
    dx = N * (gauss(10.3 + h, 9.8) - gauss(10.3 - h, 9.8)) / (2 * h)
    dy = N * (gauss(10.3, 9.8 + h) - gauss(10.3, 9.8 - h)) / (2 * h)
    c = fisher_crb(m, [dx, dy, m / N], read_noise=0.0)
    assert c[0] == pytest.approx(math.sqrt((1.5 ** 2 + 1 / 12) / N), rel=2e-3)
    assert c[1] == pytest.approx(c[0], rel=1e-6)
    # a wrong derivative step or a missing nuisance would show here: the photon-count bound is sqrt(N)
    assert c[2] == pytest.approx(math.sqrt(N), rel=1e-3)
    a = crb_xy(("fluor", "fluor", 0.0), 100.2, 100.7, np.ones(SHAPE), np.zeros(SHAPE))
    s_eq = 0.42 * AIRY_A   # the Airy core's Gaussian equivalent, 0.21 lambda / NA
    assert s_eq / math.sqrt(N_PHOTONS) < a < 3 * s_eq / math.sqrt(N_PHOTONS), a


# ---------------------------------------------------------------------------------------------
# the judgement
# ---------------------------------------------------------------------------------------------

#: cases where ptrack's default locate fails the criteria, with the measured failure (strict xfail)
KNOWN_FAILURES: dict[str, str] = {
    # none since the ring maps (ptrack.image.rings): "fluor z=+6.0" (ring of radius 9 px: recall 0.006 before) and
    # "bf z=+1.5" (bright centre in a dark ring: recall 0.86, RMSE 1.51x the bound before) pass. An ML fit of the
    # true model reaches 0.9-1.2x the bound in every case (bench/bench_image_models.py --ml): the bound is attainable.
}


def _param(case):
    cid = case_id(case)
    marks = [pytest.mark.xfail(strict=True, reason=KNOWN_FAILURES[cid])] if cid in KNOWN_FAILURES else []
    return pytest.param(case, id=cid, marks=marks)


@pytest.mark.parametrize("case", [_param(c) for c in CASES])
def test_default_locate_on_the_independent_model(case):
    res = run_case(case, ptrack_locator)
    assert res["recall"] >= 0.95 and res["precision"] >= 0.95, res
    assert res["ratio"] <= 1.5, res
