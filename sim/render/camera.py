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


# Poisson draws by inversion of the CDF for small means (from uniform numbers
# drawn by the numpy Generator, so results follow the seed); means above this
# go to numpy's Generator.poisson.
_SMALL_MEAN = 40.0


@njit(cache=True)
def _poisson_small(lam, u, out, big_mask):
    """Inversion sampling of Poisson(lam) for lam <= _SMALL_MEAN; flags larger means in big_mask."""
    n = lam.size
    for i in range(n):
        m = lam[i]
        if m <= 0.0:
            out[i] = 0.0
            continue
        if m > 40.0:
            big_mask[i] = True
            continue
        p = math.exp(-m)
        c = p
        k = 0
        ui = u[i]
        while ui > c and k < 200:
            k += 1
            p *= m / k
            c += p
        out[i] = k


@njit(cache=True)
def _to_adu(e, read, gain, offset, maxv, out):
    n = e.size
    for i in range(n):
        v = gain * (e[i] + read[i]) + offset
        v = math.floor(v + 0.5)
        if v < 0.0:
            v = 0.0
        elif v > maxv:
            v = maxv
        out[i] = np.uint16(v)


def poisson(lam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson draws (float64) with means ``lam``, deterministic for a given Generator state.

    Small means by CDF inversion in a numba kernel (fast), large means with
    ``rng.poisson``. Exact in distribution for both.
    """
    flat = np.ascontiguousarray(lam, dtype=np.float64).ravel()
    u = rng.random(flat.size)
    out = np.empty(flat.size)
    big = np.zeros(flat.size, dtype=np.bool_)
    _poisson_small(flat, u, out, big)
    if big.any():
        out[big] = rng.poisson(flat[big])
    return out.reshape(np.shape(lam))


def expose(photons: np.ndarray, camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """Turn expected photons per pixel into a noisy uint16 camera frame.

    Parameters
    ----------
    photons : ndarray (H, W), float
        Expected photons reaching each pixel during the exposure (>= 0).
    camera : Camera
    rng : numpy.random.Generator

    Returns
    -------
    ndarray (H, W), uint16
    """
    lam = np.maximum(photons, 0.0) * camera.quantum_efficiency
    e = poisson(lam, rng)
    if camera.read_noise > 0:
        read = rng.standard_normal(e.size) * camera.read_noise
    else:
        read = np.zeros(e.size)
    out = np.empty(e.size, dtype=np.uint16)
    _to_adu(e.ravel(), read, float(camera.gain), float(camera.offset), float(camera.max_adu), out)
    return out.reshape(np.shape(photons))
