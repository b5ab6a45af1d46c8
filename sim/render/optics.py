"""Scalar Fourier-optics point-spread function with defocus and astigmatism.

The microscope is modelled by its pupil function: a disk of radius
``NA / lambda`` (cycles/m in the sample) carrying the defocus phase of a point
source a distance ``dz`` above the focal plane in a medium of index ``n``,

    phi_def(k) = 2 pi dz sqrt((n / lambda)^2 - k^2),

plus an astigmatism term for a cylindrical lens,

    phi_ast(k) = 2 pi (A / lambda) rho^2 cos(2 theta),   rho = k lambda / NA,

with ``A`` (m) the wavefront amplitude at the pupil edge. The x and y line
foci then sit at ``dz = +/- 2 n A / NA^2`` (paraxial; the full wave model puts
them about 15 % further out at NA 0.75 in water), so defocused images on
the two sides of focus are elongated along different axes: the image of a
particle is unique in z, as the GDPT method needs (seed, chapter 4).
The amplitude PSF is the inverse Fourier transform of the pupil; the intensity
PSF is its squared modulus. In focus, with ``A = 0``, this is the Airy disk
with its first dark ring at ``0.61 lambda / NA``.

Everything that follows the intensity PSF is done on its optical transfer
function (OTF, the Fourier transform of the intensity):

* integration over the square camera pixel: multiply by
  ``sinc(fx p) sinc(fy p)`` (exact, not point sampling);
* blur by the particle's projected size: multiply by the Fourier transform of
  a uniformly emitting ball of radius R projected on the image plane,
  ``3 (sin x - x cos x) / x^3`` with ``x = 2 pi k R``;
* sub-pixel placement: multiply by a phase ramp (exact Fourier shift).

Because the intensity PSF is band-limited to ``2 NA / lambda`` and the sample
pixel (103 nm for the default 63x objective and 6.5 um camera pixels) is
finer than the Nyquist limit ``lambda / (4 NA)`` (173 nm), the pixel values
obtained by an inverse FFT on the pixel grid are exact: no oversampling, no
interpolation error in x and y. Defocus is interpolated linearly between the
planes of a precomputed OTF stack (fine z grid, :attr:`Optics.psf_z_step`).

Field-dependent focus (default off): a real objective's focal surface is not
a plane. :attr:`Optics.field_curvature` (Petzval curvature) and
:attr:`Optics.field_tilt` (a tilted sample or coverslip) give its height
above the nominal focal plane at a lateral position (x, y) of the sample,

    z_f(x, y) = C (r / R)^2 + T_x (x - x_c) / R + T_y (y - y_c) / R,

``r`` the distance from the optical axis (x_c, y_c) (:attr:`Optics.field_center`,
default the centre of the rendered frame), ``R`` = :attr:`Optics.field_radius`
and C, T_x, T_y in m (the focal shift at ``R`` from the axis). A particle at
height z is then rendered with the defocus ``z - focal_plane - z_f(x, y)``
(:meth:`Optics.focal_shift`): the same image as a particle ``z_f`` lower on
the axis, so a calibration recorded at one place in the field reads z off by
``-z_f`` elsewhere (what :mod:`ptrack.gdpt.field` corrects). The PSF itself
does not change across the field (no field-dependent astigmatism or coma).

Approximations (stated, not hidden): scalar diffraction with a uniform
(unapodised) pupil; no spherical aberration from the refractive-index
mismatch between the air objective and the water sample (the defocus phase
uses the medium index, i.e. z is the particle's distance from the focal plane
in the medium); the size blur projects the whole ball into one defocus plane.
All lengths are SI (m).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.fft as sfft

from ptrack.errors import UserError, check_positive


@dataclass
class Optics:
    """Microscope optics (SI units). Defaults follow the seed's set-up (chapter 4):
    Zeiss LD Achroplan 63x / NA 0.75 air objective, FITC emission (519 nm),
    particles in water.

    Attributes
    ----------
    na : float
        Numerical aperture of the objective.
    wavelength : float
        Emission wavelength in vacuum, m.
    medium_index : float
        Refractive index of the sample medium (water 1.333); sets the defocus phase.
    immersion_index : float
        Refractive index of the immersion medium (air 1.0); NA may not exceed it.
    magnification : float
        Total magnification from sample to camera.
    astigmatism : float
        Astigmatic wavefront amplitude at the pupil edge, m (cylindrical lens).
        0 = none. The line foci sit about ``+/- 2 n A / NA^2`` from focus
        (paraxial); for A > 0 images above focus are elongated along y, below
        focus along x.
    psf_z_step : float
        Spacing of the precomputed PSF planes, m (linear interpolation between).
    psf_margin : float
        Extra patch radius beyond the geometric defocus blur, in units of the
        Airy radius ``0.61 lambda / NA`` (tails of the PSF kept around each particle).
    field_curvature : float
        Field curvature: height of the focal surface above the nominal focal
        plane at :attr:`field_radius` from the optical axis, m (quadratic in
        the distance from the axis). 0 = flat field (default).
    field_tilt : (float, float)
        Tilt of the focal surface: its height at :attr:`field_radius` from
        the axis along +x and along +y, m. (0, 0) = none (default).
    field_radius : float
        Reference distance from the axis for ``field_curvature`` and
        ``field_tilt``, m (default 50 um, about the half-diagonal of the
        default 63x field).
    field_center : (float, float) or None
        (x, y) of the optical axis in the sample, m (table coordinates, from
        the centre of pixel (0, 0)); None: the centre of the rendered frame.
    """

    na: float = 0.75
    wavelength: float = 519e-9
    medium_index: float = 1.333
    immersion_index: float = 1.0
    magnification: float = 63.0
    astigmatism: float = 0.0
    psf_z_step: float = 50e-9
    psf_margin: float = 8.0
    field_curvature: float = 0.0
    field_tilt: tuple = (0.0, 0.0)
    field_radius: float = 50e-6
    field_center: tuple | None = None

    def __post_init__(self):
        self._check_field()
        for name in ("na", "wavelength", "medium_index", "immersion_index", "magnification", "psf_z_step", "psf_margin"):
            check_positive(f"optics.{name}", getattr(self, name))
        if not math.isfinite(float(self.astigmatism)):
            raise UserError(f"optics.astigmatism = {self.astigmatism!r} is not finite", "give the astigmatism in m (0 for none)")
        if self.na > self.immersion_index:
            raise UserError(
                f"optics.na = {self.na} exceeds the immersion index {self.immersion_index}",
                "an objective's NA cannot exceed the refractive index of its immersion medium",
            )
        if self.na >= self.medium_index:
            raise UserError(
                f"optics.na = {self.na} is not below the medium index {self.medium_index}",
                "this scalar model needs NA < refractive index of the sample medium",
            )

    @property
    def airy_radius(self) -> float:
        """First dark ring of the in-focus Airy disk, 0.61 lambda/NA (m) (exactly 3.8317/(2 pi) lambda/NA)."""
        return 3.831705970207512 / (2 * np.pi) * self.wavelength / self.na

    @property
    def line_focus_offset(self) -> float:
        """Distance of the astigmatic line foci from the focal plane, 2 n A / NA^2 (m, paraxial)."""
        return 2.0 * self.medium_index * abs(self.astigmatism) / self.na ** 2

    @property
    def half_angle_tan(self) -> float:
        """tan of the marginal-ray angle in the medium (geometric blur radius per unit defocus)."""
        s = self.na / self.medium_index
        return s / math.sqrt(1.0 - s * s)

    def _check_field(self):
        """Validate (and normalise to floats / tuples) the field-dependent focus parameters."""
        if not math.isfinite(float(self.field_curvature)):
            raise UserError(f"optics.field_curvature = {self.field_curvature!r} is not finite",
                            "give the focal shift at field_radius in m (0 for a flat field)")
        self.field_curvature = float(self.field_curvature)
        for name, fix in (("field_tilt", "give (tx, ty): the focal shift at field_radius along x and y, m"),
                          ("field_center", "give (x, y) of the optical axis in m, or None for the frame centre")):
            v = getattr(self, name)
            if v is None and name == "field_center":
                continue
            try:
                a, b = (float(u) for u in v)
            except (TypeError, ValueError):
                raise UserError(f"optics.{name} = {v!r} is not two numbers", fix) from None
            if not (math.isfinite(a) and math.isfinite(b)):
                raise UserError(f"optics.{name} = {v!r} is not finite", fix)
            setattr(self, name, (a, b))
        check_positive("optics.field_radius", self.field_radius)

    @property
    def field_dependent(self) -> bool:
        """True when the focal surface is not flat (field curvature or tilt set)."""
        return self.field_curvature != 0.0 or self.field_tilt != (0.0, 0.0)

    def focal_shift(self, x, y, center=None):
        """Height of the focal surface above the nominal focal plane at sample position (x, y), m.

        Parameters
        ----------
        x, y : float or array_like
            Lateral position in the sample, m (table coordinates).
        center : (float, float), optional
            (x, y) of the optical axis, m, used when :attr:`field_center` is
            None (the renderer passes the centre of its frame); default (0, 0).

        Returns
        -------
        ndarray (float64, the broadcast shape of x and y)
            ``C (r/R)^2 + T_x (x - x_c)/R + T_y (y - y_c)/R``; exactly 0 when
            the field is flat, so a particle's defocus is unchanged bit for bit.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if not self.field_dependent:
            return np.zeros(np.broadcast(x, y).shape)
        xc, yc = self.field_center if self.field_center is not None else (center if center is not None else (0.0, 0.0))
        u = (x - float(xc)) / self.field_radius
        v = (y - float(yc)) / self.field_radius
        return self.field_curvature * (u * u + v * v) + self.field_tilt[0] * u + self.field_tilt[1] * v

    def to_dict(self) -> dict:
        """The parameters as a dict (``Optics(**d)`` rebuilds it). The field-dependent focus keys are left out
        while the field is flat and the axis not set, so the params.json of an existing render is unchanged."""
        d = asdict(self)
        if not self.field_dependent and self.field_center is None and self.field_radius == 50e-6:
            for k in ("field_curvature", "field_tilt", "field_radius", "field_center"):
                d.pop(k)
        return d


def sample_pixel_size(optics: Optics, camera_pixel: float) -> float:
    """Pixel size in the sample, m: camera pixel pitch / magnification."""
    return float(camera_pixel) / float(optics.magnification)


def check_sampling(optics: Optics, pixel: float) -> None:
    """Raise UserError if the sample pixel is coarser than the Nyquist limit lambda/(4 NA).

    The exact pixel integration of this module needs the intensity PSF
    (band limit 2 NA / lambda) sampled at or above Nyquist.
    """
    limit = optics.wavelength / (4.0 * optics.na)
    if pixel > limit:
        raise UserError(
            f"sample pixel {pixel * 1e9:.1f} nm is coarser than the Nyquist limit lambda/(4 NA) = {limit * 1e9:.1f} nm",
            "raise the magnification or use smaller camera pixels",
        )


MAX_PATCH = 8192       # px a side: one complex plane of this size is 1 GiB


def patch_size(optics: Optics, pixel: float, max_defocus: float, max_radius: float = 0.0) -> int:
    """Side (pixels, even, FFT-friendly) of the square patch rendered around each particle.

    Covers the geometric defocus blur ``(|dz| + line-focus offset) tan(theta)``,
    the particle radius and :attr:`Optics.psf_margin` Airy radii of PSF tails.
    """
    r = (abs(max_defocus) + optics.line_focus_offset) * optics.half_angle_tan
    r += optics.psf_margin * optics.airy_radius + 2.0 * max_radius
    n = int(math.ceil(2.0 * r / pixel)) + 2
    if n > MAX_PATCH:
        # e.g. --astigmatism 0.5 (meant in waves, read as 0.5 m of wavefront): a patch of ~1e9 px a side
        raise UserError(f"a particle image {n} px across ({2 * r * 1e6:.3g} µm: defocus {abs(max_defocus) * 1e6:.3g} µm, "
                        f"astigmatism {optics.astigmatism:g} m, NA {optics.na:g}) exceeds the {MAX_PATCH} px limit",
                        "give astigmatism in m of wavefront (e.g. 1.2e-7, not waves) and heights in m within tens of µm "
                        "of the focal plane")
    n = max(n, 16)
    n = sfft.next_fast_len(n, real=True)
    while n % 2:
        n = sfft.next_fast_len(n + 1, real=True)
    return n


def _pupil_grid(optics: Optics, pixel: float, n: int):
    """Spatial frequencies (cycles/m) of an n x n grid with spacing ``pixel``; pupil mask and phase pieces."""
    f = np.fft.fftfreq(n, d=pixel)
    fy, fx = f[:, None], f[None, :]
    k2 = fx * fx + fy * fy
    kc = optics.na / optics.wavelength
    # Soft (area-weighted) pupil edge: a hard circle on a coarse frequency grid
    # shifts the rings; a one-sample linear ramp across the edge removes most of it.
    df = 1.0 / (n * pixel)
    k = np.sqrt(k2)
    mask = np.clip((kc - k) / df + 0.5, 0.0, 1.0)
    kz = np.sqrt(np.maximum((optics.medium_index / optics.wavelength) ** 2 - k2, 0.0))
    astig = (fx * fx - fy * fy) / kc ** 2  # rho^2 cos(2 theta)
    return mask, kz, astig


def _amp_grid_factor(optics: Optics, pixel: float, n: int, min_pupil_samples: float = 48.0) -> int:
    """Integer m so that the pupil radius on the (m n)-point grid spans >= min_pupil_samples samples."""
    kc = optics.na / optics.wavelength
    per = kc * n * pixel  # pupil radius in samples on the n-grid
    return max(1, int(math.ceil(min_pupil_samples / per)))


def otf_planes(optics: Optics, pixel: float, n: int, defocus, dtype=np.complex128, field: bool = False):
    """Pixel-integrated optical transfer functions for the given defocus values.

    Parameters
    ----------
    optics : Optics
    pixel : float
        Sample pixel size, m.
    n : int
        Patch side, pixels (even).
    defocus : array_like
        Particle height above the focal plane, m, one per plane.

    dtype : numpy dtype
        complex128 (default) or complex64 (half the memory of a large stack).
    field : bool
        Also return the transforms of the amplitude PSF (for coherent
        brightfield): ``rfft2`` of the pixel-averaged real and imaginary parts
        of the field ``a``, normalised so that ``sum |a|^2 = 1`` over pixels.

    Returns
    -------
    ndarray, complex, shape (len(defocus), n, n // 2 + 1)
        ``rfft2`` of the pixel-integrated intensity PSF centred on pixel (0, 0)
        (wrapped), normalised so that the DC term (total flux) is 1.
        The intensity is computed on an m-times larger grid (fine pupil
        sampling) and wrapped onto the n-grid by taking every m-th frequency,
        which conserves flux exactly.
    (re, im) : two more such arrays, only if ``field``.
    """
    defocus = np.atleast_1d(np.asarray(defocus, dtype=np.float64))
    m = _amp_grid_factor(optics, pixel, n)
    big = n * m
    mask, kz, astig = _pupil_grid(optics, pixel, big)
    sel = mask > 0
    base_phase = 2 * np.pi * (optics.astigmatism / optics.wavelength) * astig[sel]
    kz_sel = 2 * np.pi * kz[sel]
    if field:
        # The field interferes with the unscattered illumination, a plane wave along z that gains
        # 2 pi n dz / lambda itself: only the defocus phase relative to it, (kz - n/lambda) dz, is
        # physical. Without this the coherent brightfield contrast repeated every lambda/n (0.39 um
        # in water at 519 nm). The intensity PSF is blind to this global phase, so it is left as it
        # was there (bit-identical renders).
        kz_sel = kz_sel - 2 * np.pi * optics.medium_index / optics.wavelength
    amp_mask = mask[sel]
    fpx = np.fft.fftfreq(n)  # cycles/pixel
    rpx = np.fft.rfftfreq(n)
    pix = np.sinc(fpx)[:, None] * np.sinc(rpx)[None, :]
    out = np.empty((len(defocus), n, n // 2 + 1), dtype=dtype)
    if field:
        out_re = np.empty_like(out)
        out_im = np.empty_like(out)
    pupil = np.zeros((big, big), dtype=np.complex128)
    for i, dz in enumerate(defocus):
        pupil[sel] = amp_mask * np.exp(1j * (kz_sel * dz + base_phase))
        amp = sfft.ifft2(pupil, workers=1)
        inten = amp.real ** 2 + amp.imag ** 2
        otf = sfft.rfft2(inten, workers=1)
        otf = otf[::m, ::m]
        norm = otf[0, 0].real
        out[i] = otf / norm * pix
        if field:
            a = amp / math.sqrt(norm)  # sum |a|^2 = 1 on the pixel grid
            out_re[i] = sfft.rfft2(a.real, workers=1)[::m, ::m] * pix
            out_im[i] = sfft.rfft2(a.imag, workers=1)[::m, ::m] * pix
    if field:
        return out, out_re, out_im
    return out


def size_transfer(k, radius: float):
    """Fourier transform of a uniform ball of radius ``radius`` (m) projected onto a plane.

    ``k`` in cycles/m. Equals ``3 (sin x - x cos x) / x^3`` with ``x = 2 pi k R``; 1 at k = 0.
    """
    x = 2 * np.pi * np.asarray(k, dtype=np.float64) * radius
    out = np.ones_like(x)
    big = x > 1e-3
    xb = x[big]
    out[big] = 3.0 * (np.sin(xb) - xb * np.cos(xb)) / xb ** 3
    small = ~big
    out[small] = 1.0 - x[small] ** 2 / 10.0
    return out


@dataclass
class PSFStack:
    """OTF planes on a uniform defocus grid, for fast rendering of many particles.

    Attributes
    ----------
    z0, dz : float
        Defocus of plane 0 and plane spacing, m.
    otf : ndarray, complex64, (nz, n, n//2+1)
    pixel : float
        Sample pixel size, m.
    n : int
        Patch side, pixels.
    """

    z0: float
    dz: float
    otf: np.ndarray
    pixel: float
    n: int
    kr: np.ndarray = field(repr=False, default=None)  # |k| in cycles/m on the rfft grid
    field_re: np.ndarray | None = field(repr=False, default=None)  # amplitude PSF, real part (coherent brightfield)
    field_im: np.ndarray | None = field(repr=False, default=None)

    def __post_init__(self):
        if self.kr is None:
            f = np.fft.fftfreq(self.n, d=self.pixel)
            r = np.fft.rfftfreq(self.n, d=self.pixel)
            self.kr = np.sqrt(f[:, None] ** 2 + r[None, :] ** 2)

    @property
    def nz(self) -> int:
        return self.otf.shape[0]


def build_psf_stack(optics: Optics, pixel: float, zmin: float, zmax: float, max_radius: float = 0.0,
                    n: int | None = None, max_bytes: float = 256e6, with_field: bool = False) -> PSFStack:
    """Precompute OTF planes covering defocus ``[zmin, zmax]`` (m).

    The plane spacing is :attr:`Optics.psf_z_step`, coarsened if the stack
    would exceed ``max_bytes`` (very large defocus ranges). ``with_field``:
    also the amplitude-PSF planes (coherent brightfield; 3x the memory).
    """
    check_sampling(optics, pixel)
    if n is None:
        n = patch_size(optics, pixel, max(abs(zmin), abs(zmax)), max_radius)
    step = float(optics.psf_z_step)
    plane_bytes = n * (n // 2 + 1) * 8 * (3 if with_field else 1)
    span = max(zmax - zmin, 0.0)
    nz = int(math.floor(span / step + 1e-9)) + 2
    if nz * plane_bytes > max_bytes:
        nz = max(2, int(max_bytes // plane_bytes))
        step = span / (nz - 1) if span > 0 else step
    zs = zmin + step * np.arange(nz)
    if with_field:
        otf, re, im = otf_planes(optics, pixel, n, zs, dtype=np.complex64, field=True)
        return PSFStack(z0=float(zmin), dz=step, otf=otf, pixel=pixel, n=n, field_re=re, field_im=im)
    otf = otf_planes(optics, pixel, n, zs, dtype=np.complex64)
    return PSFStack(z0=float(zmin), dz=step, otf=otf, pixel=pixel, n=n)


def psf_image(optics: Optics, pixel: float, defocus: float = 0.0, size: int = 64, oversample: int = 1,
              pixel_integrated: bool = True, radius: float = 0.0) -> np.ndarray:
    """The PSF as an image, centred on pixel ``(size // 2, size // 2)`` of the output grid.

    Parameters
    ----------
    optics : Optics
    pixel : float
        Sample pixel size, m.
    defocus : float
        Height of the source above the focal plane, m.
    size : int
        Side of the output in camera pixels (even).
    oversample : int
        Output sampling of ``pixel / oversample`` (exact band-limited
        interpolation by zero-padding the OTF).
    pixel_integrated : bool
        Integrate over the camera pixel (True, what a camera records) or sample
        the intensity at points (False, for comparing with the Airy formula).
    radius : float
        Particle radius, m (projected-ball blur).

    Returns
    -------
    ndarray (size*oversample, size*oversample)
        Fraction of the source's light per camera-pixel area, sampled every
        ``pixel / oversample``, the source at index ``(size // 2) * oversample``;
        the values sum to ``oversample**2`` (to 1 for ``oversample = 1``), up to
        the light outside the image, which wraps around.
    """
    size = int(size) + int(size) % 2
    n = size
    otf = otf_planes(optics, pixel, n, [defocus])[0]
    f = np.fft.fftfreq(n)
    r = np.fft.rfftfreq(n)
    if not pixel_integrated:
        with np.errstate(divide="ignore", invalid="ignore"):
            otf = otf / (np.sinc(f)[:, None] * np.sinc(r)[None, :])
    if radius > 0:
        otf = otf * size_transfer(np.sqrt(f[:, None] ** 2 + r[None, :] ** 2) / pixel, radius)
    c = n // 2
    otf = otf * np.exp(-2j * np.pi * (f[:, None] * c + r[None, :] * c))
    N = n * oversample
    big = np.zeros((N, N // 2 + 1), dtype=np.complex128)
    h = n // 2
    big[:h, : h + 1] = otf[:h]
    big[N - h:, : h + 1] = otf[h:]
    # the Nyquist row/column of the n-grid is zero (band limit), so no splitting is needed
    return sfft.irfft2(big, s=(N, N)) * (oversample ** 2)
