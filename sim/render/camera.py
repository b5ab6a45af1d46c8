"""Camera model: photons -> electrons -> ADU.

For each pixel with an expected number of photons ``N`` (particle light plus
background) during one exposure:

    electrons  e ~ Poisson(QE * N)                      shot noise
    e' = e + Normal(0, read_noise)                       read noise (e- rms)
    ADU = clip(round(gain * e' + offset), 0, 2^bits - 1)

so that, away from clipping, ``mean = gain * QE * N + offset`` and
``variance = gain^2 (QE * N + read_noise^2)`` (+ 1/12 ADU^2 from rounding).
Defaults: Andor Zyla 5.5 sCMOS in 16-bit mode as used in the seed's
experiments (6.5 um pixels, QE about 0.6 at 519 nm, about 1.2 e- rms read
noise, 30 000 e- well over 65 535 levels i.e. about 0.46 e-/ADU, baseline
offset 100 ADU).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from ptrack.errors import UserError, check_positive


@dataclass
class Camera:
    """Camera and illumination (SI units; photons and electrons are counts).

    Attributes
    ----------
    pixel_pitch : float
        Physical pixel size on the sensor, m (Zyla 5.5: 6.5 um).
    quantum_efficiency : float
        Detected fraction of the photons reaching the sensor (0-1].
    read_noise : float
        Read noise, electrons rms.
    gain : float
        ADU per electron.
    offset : float
        Baseline, ADU.
    bit_depth : int
        ADC bits (values clip at 2^bit_depth - 1).
    photons : float
        Photons per particle per exposure reaching the sensor (fluorescence);
        in brightfield the photons each particle removes from the background
        (extinction). A table column ``photons`` overrides it per row.
    background : float
        Background photons per pixel per exposure (brightfield: the bright field).
    exposure : float or None
        Exposure time, s (for motion blur); None = the frame interval.
    """

    pixel_pitch: float = 6.5e-6
    quantum_efficiency: float = 0.6
    read_noise: float = 1.2
    gain: float = 2.17
    offset: float = 100.0
    bit_depth: int = 16
    photons: float = 5000.0
    background: float = 20.0
    exposure: float | None = None

    def __post_init__(self):
        check_positive("camera.pixel_pitch", self.pixel_pitch)
        q = check_positive("camera.quantum_efficiency", self.quantum_efficiency)
        if q > 1:
            raise UserError(f"camera.quantum_efficiency = {q} exceeds 1", "give a fraction between 0 and 1")
        check_positive("camera.read_noise", self.read_noise, allow_zero=True)
        check_positive("camera.gain", self.gain)
        check_positive("camera.offset", self.offset, allow_zero=True)
        check_positive("camera.photons", self.photons, allow_zero=True)
        check_positive("camera.background", self.background, allow_zero=True)
        if self.exposure is not None:
            check_positive("camera.exposure", self.exposure)
        if int(self.bit_depth) != self.bit_depth or not 1 <= int(self.bit_depth) <= 16:
            raise UserError(f"camera.bit_depth = {self.bit_depth!r} is not an integer in 1..16",
                            "frames are written as uint16; give 8, 12 or 16")
        self.bit_depth = int(self.bit_depth)

    @property
    def max_adu(self) -> int:
        return (1 << self.bit_depth) - 1

    def expected_adu(self, photons):
        """Mean ADU for an expected photon count (no clipping)."""
        return self.gain * self.quantum_efficiency * np.asarray(photons) + self.offset

    def to_dict(self) -> dict:
        return asdict(self)


# Poisson draws. A frame is mostly a constant background B (photo-electrons per
# pixel) plus particle light on a few pixels: Poisson(B + r) = Poisson(B) + Poisson(r)
# for r >= 0, so the background part is drawn by inverting a precomputed CDF table
# (guide table, one uniform per pixel) and only pixels with r > 0 need more:
# * faint tails (0 < r < _TINY): independent Poisson(r_i) counts on many pixels are
#   one Poisson process: draw the total N ~ Poisson(sum r_i) and drop the N events
#   on the pixels with probabilities r_i / sum r (exact; costs O(N), not O(pixels));
# * _TINY <= r <= _SMALL_MEAN: CDF inversion with a second uniform;
# * r > _SMALL_MEAN: numpy's Generator.poisson.
# Pixels below the background (brightfield dips) draw Poisson(lam) directly.
# All random numbers come from the caller's numpy Generator: same seed, same frame.
_SMALL_MEAN = 40.0
_TINY = 0.25


def _poisson_cdf_table(mean: float) -> np.ndarray:
    """CDF of Poisson(mean) up to where it reaches 1 in float64."""
    if mean <= 0:
        return np.ones(1)
    from scipy.special import gammaln

    kmax = int(mean + 12.0 * math.sqrt(mean) + 30)
    k = np.arange(kmax + 1)
    cdf = np.cumsum(np.exp(k * math.log(mean) - mean - gammaln(k + 1.0)))
    cdf = np.minimum(cdf / cdf[-1], 1.0)  # the mass beyond kmax is < 1e-30
    cdf[-1] = 1.0
    return cdf


@njit(cache=True)
def _table_draw(cdf, guide, u):
    """Smallest k with cdf[k] >= u (u uniform in [0, 1)), starting the search from the guide table."""
    k = guide[int(u * guide.size)]
    while cdf[k] < u:
        k += 1
    return k


@njit(cache=True)
def _poisson_inversion(r, u):
    """Poisson(r) count for a small mean r by inverting the CDF at the uniform u (capped at 400)."""
    p = math.exp(-r)
    cum = p
    kk = 0
    while u > cum and kk < 400:
        kk += 1
        p *= r / kk
        cum += p
    return kk


@njit(cache=True)
def _round_clip(v, maxv):
    """round(v) clipped to [0, maxv] (the ADC)."""
    v = math.floor(v + 0.5)
    if v < 0.0:
        v = 0.0
    elif v > maxv:
        v = maxv
    return v


@njit(cache=True)
def _classify(ph, scale, B, eps, tiny, cls):
    """Class of each pixel's mean lam = max(ph, 0) * scale against the background mean B:
    0 background only; 1 background + small residual (inversion); 2 + large residual;
    3 below background; 4 background + faint residual r < tiny (pooled Poisson process).
    Returns (number of class 1, number of class 4, sum of the class-4 residuals)."""
    n1 = 0
    n4 = 0
    r4 = 0.0
    for i in range(ph.size):
        r = max(ph[i], 0.0) * scale - B
        if r > eps:
            if r < tiny:
                cls[i] = 4
                n4 += 1
                r4 += r
            elif r <= _SMALL_MEAN:
                cls[i] = 1
                n1 += 1
            else:
                cls[i] = 2
        elif r < -eps:
            cls[i] = 3
        else:
            cls[i] = 0
    return n1, n4, r4


@njit(cache=True)
def _scatter_events(ph, scale, B, cls, n4, u, out, cum, idx):
    """Drop len(u) events (u uniform in [0, sum r)) on the class-4 pixels with probability ~ r_i.

    Each event adds 1 to ``out`` at its pixel: used by :func:`poisson` (``out`` holds the
    background counts) and by :func:`expose` (``out`` = the zeroed extra counts)."""
    j = 0
    acc = 0.0
    for i in range(ph.size):
        if cls[i] == 4:
            acc += max(ph[i], 0.0) * scale - B
            cum[j] = acc
            idx[j] = i
            j += 1
    for k in range(u.size):
        t = u[k] * acc
        lo = 0
        hi = n4 - 1
        while lo < hi:
            mid = (lo + hi) >> 1
            if cum[mid] > t:
                hi = mid
            else:
                lo = mid + 1
        out[idx[lo]] += 1.0


@njit(cache=True)
def _guide_table(cdf, G):
    """guide[g] = smallest k with cdf[k] >= g / G (start of the linear search for u in [g/G, (g+1)/G))."""
    guide = np.empty(G, dtype=np.int64)
    k = 0
    for g in range(G):
        t = g / G
        while cdf[k] < t:
            k += 1
        guide[g] = k
    return guide


@njit(cache=True)
def _poisson_split(ph, scale, B, cdf, guide, u1, cls, u2, out):
    j = 0
    for i in range(ph.size):
        c = cls[i]
        if c == 3:
            out[i] = 0.0  # filled by the caller
            continue
        k = float(_table_draw(cdf, guide, u1[i]))  # background part
        if c == 1:
            k += _poisson_inversion(max(ph[i], 0.0) * scale - B, u2[j])
            j += 1
        out[i] = k


@njit(cache=True)
def _to_adu(e, z, read_noise, gain, offset, maxv, out):
    """ADU = clip(round(gain * (electrons + read_noise * z) + offset), 0, maxv), z standard normal."""
    n = e.size
    for i in range(n):
        out[i] = np.uint16(_round_clip(gain * (e[i] + read_noise * z[i]) + offset, maxv))


class Workspace:
    """Reusable scratch arrays for :func:`expose` (frame after frame of one size: no page faults)."""

    def __init__(self):
        self._bufs: dict = {}

    def get(self, name: str, n: int, dtype) -> np.ndarray:
        b = self._bufs.get(name)
        if b is None or b.size != n or b.dtype != np.dtype(dtype):
            b = np.empty(n, dtype=dtype)
            self._bufs[name] = b
        return b


def _classify_and_draw(flat, scale, B, rng, work):
    """Classify the pixels against the background mean ``B`` (see :func:`_classify`) and draw their uniforms.

    Returns (cls, n4, r4, u1, u2): u1 one per pixel (the background or ADU table draw),
    u2 one per class-1 pixel (the residual's CDF inversion).
    """
    n = flat.size
    cls = work.get("cls", n, np.int8)
    n1, n4, r4 = _classify(flat, scale, B, 1e-9 * max(B, 1.0), _TINY, cls)
    u1 = rng.random(n, out=work.get("u1", n, np.float64))
    u2 = rng.random(n1)
    return cls, n4, r4, u1, u2


def _add_pooled_events(flat, scale, B, cls, n4, r4, rng, out, work):
    """Faint-tail (class 4) pixels: N ~ Poisson(sum r) events dropped with probability ~ r_i, added to ``out``."""
    if n4:
        n = flat.size
        events = rng.random(int(rng.poisson(r4)))
        _scatter_events(flat, scale, B, cls, n4, events, out, work.get("cum", n, np.float64),
                        work.get("idx", n, np.int64))


def poisson(lam: np.ndarray, rng: np.random.Generator, background: float | None = None, scale: float = 1.0,
            work: Workspace | None = None) -> np.ndarray:
    """Poisson draws (float64) with means ``max(lam, 0) * scale``; deterministic for a given Generator state.

    ``background``: the common mean of most pixels (after scaling; default:
    the median); only the excess over it costs a second draw. Exact in
    distribution (the split is the additivity of independent Poisson
    variables). ``work``: scratch arrays to reuse (the result may live in it).
    """
    flat = np.ascontiguousarray(lam, dtype=np.float64).ravel()
    if flat.size == 0:
        return np.zeros(np.shape(lam))
    scale = float(scale)
    B = float(np.median(np.maximum(flat, 0.0) * scale)) if background is None else float(background)
    B = max(B, 0.0)
    work = work or Workspace()
    n = flat.size
    if B > 2e4:  # a very bright field: the CDF table would be large; numpy's sampler per pixel
        return rng.poisson(np.maximum(flat, 0.0) * scale).astype(np.float64).reshape(np.shape(lam))
    cdf = _poisson_cdf_table(B)
    cls, n4, r4, u1, u2 = _classify_and_draw(flat, scale, B, rng, work)
    out = work.get("e", n, np.float64)
    _poisson_split(flat, scale, B, cdf, _guide_table(cdf, 4 * cdf.size), u1, cls, u2, out)
    _add_pooled_events(flat, scale, B, cls, n4, r4, rng, out, work)
    big = cls == 2
    if big.any():
        out[big] += rng.poisson(np.maximum(flat[big], 0.0) * scale - B)
    low = cls == 3
    if low.any():
        out[low] = rng.poisson(np.maximum(flat[low], 0.0) * scale)
    return out.reshape(np.shape(lam))


def _adu_table(B: float, read_noise: float, gain: float, offset: float, maxv: float):
    """Distribution of the ADU of a background-only pixel, clip(round(gain (Poisson(B) + read N(0,1)) + offset)).

    Returns (j0, cdf over j0, j0 + 1, ...). Exact up to float rounding: the
    Poisson table holds all mass to 1e-30, the normal CDF is evaluated exactly.
    """
    from scipy.special import ndtr

    pk = np.diff(np.r_[0.0, _poisson_cdf_table(B)])
    k = np.arange(pk.size, dtype=np.float64)
    lo = max(0, int(math.floor(gain * (-8.0 * read_noise) + offset - 1)))
    hi = min(int(maxv), int(math.ceil(gain * (k[-1] + 8.0 * read_noise) + offset + 1)))
    j = np.arange(lo, hi + 1, dtype=np.float64)
    if read_noise > 0:
        # P(j | k) = Phi(((j + 0.5 - off) / g - k) / s) - Phi(((j - 0.5 - off) / g - k) / s); clipped ends
        upper = ndtr((((j + 0.5 - offset) / gain)[None, :] - k[:, None]) / read_noise)
        upper[:, -1] = 1.0 if hi == int(maxv) else upper[:, -1]
        cdf = pk @ upper
    else:
        adu = np.clip(np.floor(gain * k + offset + 0.5), lo, hi).astype(np.int64) - lo
        cdf = np.cumsum(np.bincount(adu, weights=pk, minlength=j.size))
    cdf = np.minimum(cdf / cdf[-1], 1.0)
    cdf[-1] = 1.0
    return lo, cdf


@njit(cache=True)
def _count_explicit(cls, extra):
    n = 0
    for i in range(cls.size):
        c = cls[i]
        if c == 1 or c == 2 or c == 3 or (c == 4 and extra[i] > 0.0):
            n += 1
    return n


@njit(cache=True)
def _expose_kernel(ph, scale, B, cls, u1, u2, extra, big, low, z, cdf, guide, acdf, aguide, j0,
                   read_noise, gain, offset, maxv, out):
    """ADU per pixel. Background-only pixels (no residual light, or faint-tail pixels that got no
    event of the pooled process) take their ADU straight from the compound background distribution
    (one uniform, no normal); the others add their residual counts and read noise explicitly."""
    j1 = 0
    jb = 0
    jl = 0
    jz = 0
    for i in range(ph.size):
        c = cls[i]
        u = u1[i]
        if c == 0 or (c == 4 and extra[i] == 0.0):
            out[i] = np.uint16(j0 + _table_draw(acdf, aguide, u))
            continue
        if c == 3:
            k = low[jl]
            jl += 1
        else:
            k = float(_table_draw(cdf, guide, u))
            if c == 1:
                k += _poisson_inversion(max(ph[i], 0.0) * scale - B, u2[j1])
                j1 += 1
            elif c == 2:
                k += big[jb]
                jb += 1
            else:
                k += extra[i]
        out[i] = np.uint16(_round_clip(gain * (k + read_noise * z[jz]) + offset, maxv))
        jz += 1


_ADU_TABLES: dict = {}


def expose(photons: np.ndarray, camera: Camera, rng: np.random.Generator, work: Workspace | None = None) -> np.ndarray:
    """Turn expected photons per pixel into a noisy uint16 camera frame.

    Exact sampling of the camera model for every pixel. Pixels that receive
    only the background draw their ADU from the exact compound distribution
    of ``clip(round(gain (Poisson(QE b) + read N(0, 1)) + offset))`` (one
    uniform number); the others draw their electrons (background by table,
    extra light by inversion / pooled events / numpy) and their read noise.

    Parameters
    ----------
    photons : ndarray (H, W), float
        Expected photons reaching each pixel during the exposure (>= 0).
    camera : Camera
    rng : numpy.random.Generator
    work : Workspace, optional
        Scratch arrays reused from frame to frame.

    Returns
    -------
    ndarray (H, W), uint16
    """
    work = work or Workspace()
    qe = float(camera.quantum_efficiency)
    B = float(camera.background) * qe
    flat = np.ascontiguousarray(photons, dtype=np.float64).ravel()
    n = flat.size
    out = np.empty(n, dtype=np.uint16)
    if n == 0:
        return out.reshape(np.shape(photons))
    gain, offset, read, maxv = float(camera.gain), float(camera.offset), float(camera.read_noise), float(camera.max_adu)
    if B > 2e4:  # very bright field: plain per-pixel sampling
        e = rng.poisson(np.maximum(flat, 0.0) * qe).astype(np.float64)
        zz = rng.standard_normal(n, dtype=np.float32)
        _to_adu(e, zz, read, gain, offset, maxv, out)
        return out.reshape(np.shape(photons))
    key = (B, read, gain, offset, maxv)
    tables = _ADU_TABLES.get(key)
    if tables is None:
        cdf = _poisson_cdf_table(B)
        j0, acdf = _adu_table(B, read, gain, offset, maxv)
        tables = (cdf, _guide_table(cdf, 4 * cdf.size), j0, acdf, _guide_table(acdf, 4 * acdf.size))
        if len(_ADU_TABLES) > 32:
            _ADU_TABLES.clear()
        _ADU_TABLES[key] = tables
    cdf, guide, j0, acdf, aguide = tables
    cls, n4, r4, u1, u2 = _classify_and_draw(flat, qe, B, rng, work)
    extra = work.get("extra", n, np.float64)
    extra.fill(0.0)
    _add_pooled_events(flat, qe, B, cls, n4, r4, rng, extra, work)
    bigm = cls == 2
    big = rng.poisson(np.maximum(flat[bigm], 0.0) * qe - B).astype(np.float64) if bigm.any() else np.zeros(0)
    lowm = cls == 3
    low = rng.poisson(np.maximum(flat[lowm], 0.0) * qe).astype(np.float64) if lowm.any() else np.zeros(0)
    nz = _count_explicit(cls, extra)
    z = rng.standard_normal(nz, dtype=np.float32) if read > 0 else np.zeros(nz, dtype=np.float32)
    _expose_kernel(flat, qe, B, cls, u1, u2, extra, big, low, z, cdf, guide, acdf, aguide, j0,
                   read, gain, offset, maxv, out)
    return out.reshape(np.shape(photons))
