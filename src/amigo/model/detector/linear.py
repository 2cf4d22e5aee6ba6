"""Linear detector model: jitter, the detector's geometry, pixel binning, flux.

The optical model produces the illuminance on an oversampled grid aligned with the
optical (pupil) frame. The detector pixel grid is slightly rotated, stretched and skewed
with respect to it. This module maps one onto the other (the paper's 'Linear Detector
Model'):

1. instrumental jitter: a Gaussian blur of the oversampled image (optical frame), applied
   as the exact Gaussian transfer function in Fourier space, so any sigma >= 0 works;
2. resampling onto the detector's oversampled grid by cubic interpolation through the
   linear map :func:`geometry_matrix`;
3. summing each ``oversample x oversample`` block into a detector pixel and scaling by
   the source flux;
4. inter-pixel capacitance (IPC): a 5x5 convolution of the pixel image (level-2 images
   keep it: the JWST pipeline does not remove it). The ramp model of calslope fits uses
   :meth:`LinearDetector.illuminance` and applies IPC in its own read-out instead.

Frames and the geometry matrix (the sign convention, stated once)
-----------------------------------------------------------------
Offsets are measured from the centre of the field (the corner shared by the four
central pixels of the 80 x 80 subarray, i.e. detector pixel coordinate 39.5 along each
axis, 0-based). The optical frame is amigo's pupil frame (``x = -V2``, ``y = +V3``, see
:func:`amigo.niriss.pupil_to_v2v3_matrix`). An offset ``p`` in the optical frame, in
units of the mean pixel scale :data:`amigo.niriss.PIXEL_SCALE_ARCSEC`, lands at the
detector offset (pixels)::

    d = G p,    G = s D(a) K(phi, kappa),    D(a) = diag(a^(1/2), a^(-1/2)),
    K = [[cos(phi - kappa/2), -sin(phi + kappa/2)],
         [sin(phi - kappa/2),  cos(phi + kappa/2)]]

* ``phi = rotation_deg``: the image turns by ``phi`` from detector +x towards +y
  (counter-clockwise as the DMS image is displayed, origin at the bottom left);
* ``kappa = skew_deg``: the images of the optical axes are ``90 + kappa`` degrees apart;
* ``a = anisotropy``: a detector pixel spans ``a`` times more sky along y than along x;
* ``s = scale``: magnification relative to the mean pixel scale.

``det G = s^2 cos(kappa)``; the resampling divides by it, so flux is conserved.
:func:`amigo.niriss.geometry_parameters` inverts the map. The nominal ``G`` is
derived from the SIAF (:func:`amigo.niriss.nominal_geometry_matrix`): rotation
-0.444 deg (clockwise), anisotropy 1.0060, skew -0.259 deg, scale 1.00001 for NIS_AMI1.
(The AMIGO research code's "+0.561 deg" is the SIAF's V3IdlYAngle applied to the
*coordinates* in its resampler, i.e. the image turned the other way; docs/geometry.md.)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Float

from amigo import niriss, programs
from amigo.model.optics.propagation import keys_cubic

if TYPE_CHECKING:
    from amigo.orientation import Orientation

MAS_PER_ARCSEC = 1000.0
#: Order of the geometry vector of :meth:`LinearDetector.geometry` (fits and files).
GEOMETRY_NAMES = ("rotation_deg", "anisotropy", "skew_deg", "scale")


def geometry_matrix(
    rotation_deg: Array | float,
    anisotropy: Array | float,
    skew_deg: Array | float = 0.0,
    scale: Array | float = 1.0,
) -> Float[Array, "2 2"]:
    """(2, 2) matrix ``G``: optical offset (mean pixels) -> detector offset (pixels).

    See the module notes for the definition of the four numbers; with ``skew_deg = 0``
    and ``scale = 1`` it is ``D(a) R(phi)``, a rotation followed by an area-preserving
    stretch along the detector axes.
    """
    # Plain numbers give a NumPy matrix: evaluated op by op, JAX compiles every primitive
    # (seconds on a small CPU) for what is a constant.
    values = (rotation_deg, anisotropy, skew_deg, scale)
    xp = np if all(isinstance(v, float | int | np.floating | np.ndarray) for v in values) else jnp
    half = 0.5 * xp.deg2rad(skew_deg)
    phi = xp.deg2rad(rotation_deg)
    root = xp.sqrt(anisotropy)
    k = xp.array(
        [[xp.cos(phi - half), -xp.sin(phi + half)], [xp.sin(phi - half), xp.cos(phi + half)]]
    )
    return scale * xp.array([[root], [1.0 / root]]) * k


@eqx.filter_jit
def fourier_gaussian_blur(image: Float[Array, "... n m"], sigma: Array | float, pad: int) -> Array:
    """Gaussian blur (sigma in samples, any value >= 0) of the last two axes.

    Multiplies the spectrum by the Gaussian's transfer function
    ``exp(-2 pi^2 sigma^2 f^2)``: the exact convolution of the band-limited interpolant of
    the samples, smooth in ``sigma`` (so a fit can move it through 0), conserving the sum
    exactly. ``pad`` zero samples on each side keep the circular convolution from wrapping
    light across the edges.
    """
    n, m = image.shape[-2:]
    widths = [(0, 0)] * (image.ndim - 2) + [(pad, pad), (pad, pad)]
    padded = jnp.pad(image, widths)
    fy = jnp.fft.fftfreq(n + 2 * pad)[:, None]
    fx = jnp.fft.rfftfreq(m + 2 * pad)[None, :]
    transfer = jnp.exp(-2.0 * jnp.pi**2 * jnp.square(sigma) * (fx**2 + fy**2))
    spectrum = jnp.fft.rfft2(padded) * transfer.astype(padded.dtype)
    blurred = jnp.fft.irfft2(spectrum, s=padded.shape[-2:])
    return blurred[..., pad : pad + n, pad : pad + m].astype(image.dtype)


def displacement_reach(matrix: np.ndarray, shape: tuple[int, int]) -> int:
    """Smallest stencil reach (samples) that :func:`cubic_resample` needs for ``matrix``.

    The largest displacement ``|G^-1 d - d|`` over the array (at its corners) plus the
    two samples of the cubic kernel's support.
    """
    n, m = shape
    corners = np.array(
        [[sx * 0.5 * (m - 1), sy * 0.5 * (n - 1)] for sx in (-1, 1) for sy in (-1, 1)]
    )
    shift = corners @ (np.linalg.inv(np.asarray(matrix)) - np.eye(2)).T
    return int(np.floor(np.abs(shift).max())) + 2


def _shift_along(image: Array, u: Array, axis: int, reach: int) -> Array:
    """``out[k] = image(k + u[k])`` along ``axis`` (-1 or -2), Keys cubic, zero outside.

    A fixed stencil of ``2 reach + 1`` shifted copies weighted by the cubic kernel of the
    per-sample displacement ``u``: slices and element-wise products only (gathering at
    data-dependent indices would make the gradient a slow scatter on CPUs).
    """
    n = image.shape[axis]
    pad = [(0, 0)] * image.ndim
    pad[axis] = (reach, reach)
    padded = jnp.pad(image, pad)
    taps = np.arange(-reach, reach + 1)
    # The kernel's weights for every tap at once, (2 reach + 1, n, m): one copy of its
    # piecewise polynomial in the graph, not one per tap (the graph's size sets the
    # compile time, most of a CPU run's). The weighted sum stays a loop of slices, which
    # XLA fuses into one pass; stacking the shifted copies would write them all to memory
    # (per tangent, in a Jacobian: several times slower).
    weights = keys_cubic(u - taps.reshape((-1,) + (1,) * u.ndim).astype(u.dtype))
    out = jnp.zeros_like(image)
    for i, k in enumerate(taps):
        start = reach + int(k)
        shifted = jax.lax.slice_in_dim(padded, start, start + n, axis=axis)
        out = out + weights[i] * shifted
    return out


@eqx.filter_jit
def cubic_resample(
    image: Float[Array, "n m"], matrix: Float[Array, "2 2"], reach: int = 3
) -> Float[Array, "n m"]:
    """Resample ``image`` through the linear map ``matrix`` about the array centre.

    The output sample at offset ``d`` (in samples, from the centre) takes the value of
    the input at ``p = A d`` with ``A = matrix^-1``, by cubic (Keys) interpolation, zero
    outside the input. For ``det(matrix) = 1`` this moves the image by ``matrix`` while
    conserving its sum (to the interpolation error, for a well-sampled image).

    Done in two one-dimensional passes (the classic separable decomposition of an affine
    resampling): along x, every input row ``y'`` is sampled at
    ``x' = (a11 - a12 a21 / a22) x + (a12 / a22) y'``; then along y, every column at
    ``y' = a21 x + a22 y``; composed, ``(x', y') = A (x, y)``. The map is close to the
    identity, so each pass reads a fixed stencil of ``2 reach + 1`` shifted copies
    (:func:`_shift_along`); displacements must stay below ``reach - 1`` samples
    (:func:`displacement_reach` gives the reach a matrix needs). Beyond that the result is
    NaN: the solvers reject a step whose loss is not finite, and training stops on it.
    (Not ``eqx.error_if``: its host callback keeps every program that contains it out of
    JAX's persistent compilation cache, and the fit's programs take minutes to compile.)
    """
    n, m = image.shape[-2:]
    a = jnp.linalg.inv(matrix)
    y = jnp.arange(n, dtype=image.dtype)[:, None] - 0.5 * (n - 1)
    x = jnp.arange(m, dtype=image.dtype)[None, :] - 0.5 * (m - 1)
    # Displacements (target minus own coordinate) of the two passes, each (n, m).
    ux = (a[0, 0] - a[0, 1] * a[1, 0] / a[1, 1] - 1) * x + (a[0, 1] / a[1, 1]) * y
    uy = a[1, 0] * x + (a[1, 1] - 1) * y
    too_far = jnp.maximum(jnp.abs(ux).max(), jnp.abs(uy).max()) >= reach - 1
    resampled = _shift_along(_shift_along(image, ux, -1, reach), uy, -2, reach)
    return jnp.where(too_far, jnp.asarray(jnp.nan, image.dtype), resampled)


@eqx.filter_jit
def bin_pixels(image: Float[Array, "... n m"], factor: int) -> Float[Array, "... n/f m/f"]:
    """Sum ``factor x factor`` blocks of the last two axes."""
    n, m = image.shape[-2:]
    shape = (*image.shape[:-2], n // factor, factor, m // factor, factor)
    return image.reshape(shape).sum(axis=(-3, -1))


class LinearDetector(eqx.Module):
    """Jitter, geometric resampling and binning of an oversampled illuminance.

    Attributes
    ----------
    jitter_arcsec
        Gaussian sigma of the instrumental jitter (arcsec; the paper finds ~0.021). Any
        value >= 0; the blur depends on its square only.
    rotation_deg, anisotropy, skew_deg, scale
        The detector geometry ``G`` (see module notes; nominal values from the SIAF).
    oversample
        Sub-pixels per detector pixel per axis of the input illuminance.
    pixel_scale_arcsec
        Mean pixel scale (the optical grid's unit).
    ipc_kernel
        (5, 5) IPC kernel applied to the binned image by :meth:`__call__`
        (:func:`amigo.model.detector.read.default_ipc_kernel`), or ``None`` for none.
    jitter_pad
        Zero samples added on each side before the Fourier-space jitter blur (static).
    resample_reach
        Stencil reach of the resampling (static; see :func:`cubic_resample`).
    """

    jitter_arcsec: Float[Array, ""]
    rotation_deg: Float[Array, ""]
    anisotropy: Float[Array, ""]
    skew_deg: Float[Array, ""]
    scale: Float[Array, ""]
    ipc_kernel: Float[Array, "5 5"] | None = None
    oversample: int = eqx.field(static=True, default=3)
    pixel_scale_arcsec: float = eqx.field(static=True, default=niriss.PIXEL_SCALE_ARCSEC)
    jitter_pad: int = eqx.field(static=True, default=8)
    resample_reach: int = eqx.field(static=True, default=3)

    @classmethod
    def create(
        cls,
        jitter_arcsec: float = niriss.JITTER_SIGMA_ARCSEC,
        rotation_deg: float | None = None,
        anisotropy: float | None = None,
        skew_deg: float | None = None,
        scale: float | None = None,
        oversample: int = 3,
        jitter_pad: int = 8,
        npix: int = niriss.SUBARRAY_SIZE,
        ipc: bool = True,
    ) -> LinearDetector:
        """Detector with the given geometry (``None``: the SIAF-derived nominal value,
        :func:`amigo.niriss.nominal_geometry`). The resampling reach is sized for a
        geometry twice as far from the identity as the one given (so that a fit can move
        it), and at least 3. ``ipc``: apply the default IPC kernel to binned images."""
        from amigo.model.detector.read import default_ipc_kernel

        nominal = niriss.nominal_geometry()
        rotation = nominal.rotation_deg if rotation_deg is None else rotation_deg
        aniso = nominal.anisotropy if anisotropy is None else anisotropy
        skew = nominal.skew_deg if skew_deg is None else skew_deg
        mag = nominal.scale if scale is None else scale
        doubled = np.asarray(
            geometry_matrix(
                2 * float(rotation), float(aniso) ** 2, 2 * float(skew), float(mag) ** 2
            )
        )
        n = npix * oversample
        return cls(
            jnp.asarray(float(jitter_arcsec)),
            jnp.asarray(float(rotation)),
            jnp.asarray(float(aniso)),
            jnp.asarray(float(skew)),
            jnp.asarray(float(mag)),
            jnp.asarray(default_ipc_kernel()) if ipc else None,
            oversample=oversample,
            jitter_pad=jitter_pad,
            resample_reach=max(3, displacement_reach(np.asarray(doubled), (n, n))),
        )

    def with_geometry(self, geometry: Float[Array, " 4"]) -> LinearDetector:
        """This detector with ``geometry = [rotation_deg, anisotropy, skew_deg, scale]``
        (:data:`GEOMETRY_NAMES`; differentiable)."""
        g = jnp.asarray(geometry)
        return eqx.tree_at(
            lambda d: (d.rotation_deg, d.anisotropy, d.skew_deg, d.scale),
            self,
            (g[0], g[1], g[2], g[3]),
        )

    def with_jitter(self, jitter_arcsec: Array | float) -> LinearDetector:
        """This detector with another jitter sigma (arcsec; differentiable)."""
        return eqx.tree_at(lambda d: d.jitter_arcsec, self, jnp.asarray(jitter_arcsec))

    def geometry(self) -> Float[Array, " 4"]:
        """``[rotation_deg, anisotropy, skew_deg, scale]`` (:data:`GEOMETRY_NAMES`)."""
        return jnp.stack([self.rotation_deg, self.anisotropy, self.skew_deg, self.scale])

    # ------------------------------------------------------------------ geometry
    def matrix(self) -> Float[Array, "2 2"]:
        """(2, 2) ``G``: optical offset (mean pixels) -> detector offset (pixels)."""
        return geometry_matrix(self.rotation_deg, self.anisotropy, self.skew_deg, self.scale)

    def optical_to_detector(self, position_arcsec: Float[Array, "... 2"]) -> Float[Array, "... 2"]:
        """Optical-frame offset ``(x, y)`` (arcsec) -> detector offset ``(dx, dy)`` (pixels)."""
        p = jnp.asarray(position_arcsec) / self.pixel_scale_arcsec
        return p @ self.matrix().T

    def detector_to_optical(self, offset_pix: Float[Array, "... 2"]) -> Float[Array, "... 2"]:
        """Detector offset ``(dx, dy)`` (pixels) -> optical-frame offset (arcsec)."""
        return (jnp.asarray(offset_pix) @ jnp.linalg.inv(self.matrix()).T) * self.pixel_scale_arcsec

    def detector_arcsec_to_optical(self, offset_arcsec: Float[Array, "... 2"]) -> Array:
        """Detector offset in arcsec along x and y (pixels times the SIAF per-axis scales,
        as :meth:`amigo.orientation.Orientation.sky_to_detector_arcsec` returns) ->
        optical-frame offset (arcsec)."""
        scales = jnp.array([niriss.PIXEL_SCALE_X_ARCSEC, niriss.PIXEL_SCALE_Y_ARCSEC])
        return self.detector_to_optical(jnp.asarray(offset_arcsec) / scales)

    def optical_to_detector_arcsec(self, position_arcsec: Float[Array, "... 2"]) -> Array:
        """Optical-frame offset (arcsec) -> detector offset in arcsec along x and y
        (inverse of :meth:`detector_arcsec_to_optical`)."""
        scales = jnp.array([niriss.PIXEL_SCALE_X_ARCSEC, niriss.PIXEL_SCALE_Y_ARCSEC])
        return self.optical_to_detector(position_arcsec) * scales

    # ------------------------------------------------------------------ image
    @eqx.filter_jit
    def jitter(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Gaussian jitter blur on the oversampled optical grid."""
        return fourier_gaussian_blur(image, self._jitter_samples(), self.jitter_pad)

    def _jitter_samples(self) -> Array:
        """The jitter's Gaussian sigma in samples of the oversampled grid."""
        return self.jitter_arcsec * self.oversample / self.pixel_scale_arcsec

    def jitter_matrix(self, size: int, dtype: DTypeLike) -> Float[Array, "n n"]:
        """(size, size) matrix ``M`` of the jitter blur along one axis: :meth:`jitter` of an
        image ``X`` is ``M X M^T`` (the Gaussian's transfer function is the product of
        one per axis, and padding, transforms and crop act on each axis alone).

        Column ``j`` is the blurred image of a unit sample at ``j``, made by the same
        padded transforms as :func:`fourier_gaussian_blur`, so the two agree to rounding.
        """
        sigma = self._jitter_samples()
        pad, n = self.jitter_pad, size + 2 * self.jitter_pad
        eye = jnp.pad(jnp.eye(size, dtype=dtype), ((pad, pad), (0, 0)))
        f = jnp.fft.rfftfreq(n).astype(dtype)
        transfer = jnp.exp(-2.0 * jnp.pi**2 * jnp.square(sigma).astype(dtype) * f**2)
        blurred = jnp.fft.irfft(jnp.fft.rfft(eye, axis=0) * transfer[:, None], n=n, axis=0)
        return blurred[pad : pad + size].astype(dtype)

    @programs.jit
    def resample(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Optical oversampled grid -> detector oversampled grid (cubic, flux conserving:
        the resampled samples are divided by ``det G``)."""
        matrix = self.matrix()
        return cubic_resample(image, matrix, self.resample_reach) / jnp.linalg.det(matrix)

    # The image entry points are compiled as one program each: evaluated op by op the
    # resampling costs a minute of per-primitive compilation on a 2-core CPU.
    @eqx.filter_jit
    def illuminance(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Jittered, resampled illuminance on the detector's oversampled grid (unit flux).

        This is the input of the non-linear ramp model, which works on sub-pixels.
        """
        return self.resample(self.jitter(image))

    @eqx.filter_jit
    def __call__(self, image: Float[Array, "n m"], flux: Array | float) -> Float[Array, "n/o m/o"]:
        """Detector image ``IPC(flux * bin(resample(jitter(image))))`` in pixels, e.g.
        (80, 80).

        ``image`` is a unit-flux oversampled illuminance (optical frame), e.g. from
        :meth:`amigo.model.optics.NRMOptics.illuminance`; ``flux`` sets the output's unit
        (photons, electrons or DN/s).
        """
        return self.after_jitter(self.jitter(image), flux)

    def after_jitter(
        self, image: Float[Array, "n m"], flux: Array | float
    ) -> Float[Array, "n/o m/o"]:
        """:meth:`__call__` of an illuminance the jitter has already blurred (the fit
        blurs the visibilities' part of its image on the way from the uv plane,
        :func:`amigo.model.image.jittered_illuminance`)."""
        pixels = flux * bin_pixels(self.resample(image), self.oversample)
        if self.ipc_kernel is None:
            return pixels
        from amigo.model.detector.read import convolve_ipc

        return convolve_ipc(pixels, self.ipc_kernel.astype(pixels.dtype))


def sky_to_optical_matrix(orientation: Orientation, detector: LinearDetector) -> np.ndarray:
    """(2, 2) matrix: sky offset ``(dRA east, dDec north)`` in mas -> optical offset (mas).

    Sky -> detector pixels through the exposure's WCS orientation
    (:meth:`amigo.orientation.Orientation.sky_to_detector_matrix`), then detector ->
    optical frame through ``G^-1`` times the mean pixel scale. Companions given on the
    sky are placed in the optical model with this matrix, so that they land on the
    detector pixels the WCS predicts.
    """
    to_pixels = np.asarray(orientation.sky_to_detector_matrix())
    to_optical = np.linalg.inv(np.asarray(detector.matrix())) * detector.pixel_scale_arcsec
    # mas -> pixels -> arcsec; times 1000 for mas -> mas.
    return to_optical @ to_pixels * MAS_PER_ARCSEC
