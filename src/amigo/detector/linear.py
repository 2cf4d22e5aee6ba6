"""Linear detector model: jitter, detector rotation and anisotropy, pixel binning, flux.

The optical model produces the illuminance on an oversampled grid aligned with the
optical (pupil) frame. The detector pixel grid is slightly rotated and anisotropic
with respect to it. This module maps one onto the other (the paper's 'Linear Detector
Model'):

1. instrumental jitter: a Gaussian blur of the oversampled image (optical frame);
2. resampling onto the detector's oversampled grid by cubic interpolation through the
   linear map :func:`geometry_matrix` (rotation and y/x anisotropy);
3. summing each ``oversample x oversample`` block into a detector pixel and scaling by
   the source flux.

Frames and the geometry matrix
------------------------------
Offsets are measured from the centre of the field (the corner shared by the four
central pixels of the 80 x 80 subarray, i.e. detector pixel coordinate 39.5 along each
axis, 0-based). An offset ``p`` in the optical frame, in units of the mean pixel scale
:data:`amigo.instrument.PIXEL_SCALE_ARCSEC`, lands at the detector offset (pixels)::

    d = G p,    G = S(a) R(phi),    R(phi) = [[cos, -sin], [sin, cos]],
                                    S(a) = diag(a^(1/2), a^(-1/2))

so the image is rotated counter-clockwise (from +x towards +y) by ``phi =
rotation_deg`` on the detector, and a detector pixel spans ``a = anisotropy`` times more
sky along y than along x (``a^(-1/2)`` and ``a^(1/2)`` times the mean scale along x and
y). ``det G = 1``: the resampling conserves flux. The paper's values are ~0.56 deg and
~1.0077 (:data:`amigo.instrument.DETECTOR_ROTATION_DEG`, ``DETECTOR_ANISOTROPY``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo import instrument
from amigo.optics.propagation import keys_cubic

MAS_PER_ARCSEC = 1000.0


def geometry_matrix(rotation_deg: Array | float, anisotropy: Array | float) -> Float[Array, "2 2"]:
    """(2, 2) matrix ``G``: optical offset (mean pixels) -> detector offset (pixels)."""
    phi = jnp.deg2rad(rotation_deg)
    c, s = jnp.cos(phi), jnp.sin(phi)
    root = jnp.sqrt(anisotropy)
    return jnp.array([[root * c, -root * s], [s / root, c / root]])


def gaussian_blur(image: Float[Array, "n m"], sigma_px: Array | float, radius: int) -> Array:
    """Separable Gaussian blur of the last two axes (taps ``-radius..radius``, unit sum).

    Zero outside the array. With the normalised taps, the total is conserved wherever the
    image is negligible within ``radius`` of its edges.
    """
    k = jnp.arange(-radius, radius + 1, dtype=image.dtype)
    taps = jnp.exp(-0.5 * (k / sigma_px) ** 2)
    taps = taps / jnp.sum(taps)
    n, m = image.shape[-2:]
    padded = jnp.pad(image, [(0, 0)] * (image.ndim - 2) + [(radius, radius), (radius, radius)])
    rows = sum(taps[i] * padded[..., :, i : i + m] for i in range(2 * radius + 1))
    return sum(taps[i] * rows[..., i : i + n, :] for i in range(2 * radius + 1))


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
    out = jnp.zeros_like(image)
    for k in range(-reach, reach + 1):
        shifted = jax.lax.slice_in_dim(padded, reach + k, reach + k + n, axis=axis)
        out = out + keys_cubic(u - k) * shifted
    return out


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
    (:func:`_shift_along`); displacements must stay below ``reach - 1`` samples (checked
    at run time; :func:`displacement_reach` gives the reach a matrix needs).
    """
    n, m = image.shape[-2:]
    a = jnp.linalg.inv(matrix)
    y = jnp.arange(n, dtype=image.dtype)[:, None] - 0.5 * (n - 1)
    x = jnp.arange(m, dtype=image.dtype)[None, :] - 0.5 * (m - 1)
    # Displacements (target minus own coordinate) of the two passes, each (n, m).
    ux = (a[0, 0] - a[0, 1] * a[1, 0] / a[1, 1] - 1) * x + (a[0, 1] / a[1, 1]) * y
    uy = a[1, 0] * x + (a[1, 1] - 1) * y
    too_far = jnp.maximum(jnp.abs(ux).max(), jnp.abs(uy).max()) >= reach - 1
    image = eqx.error_if(image, too_far, "detector geometry exceeds the resampling reach")
    return _shift_along(_shift_along(image, ux, -1, reach), uy, -2, reach)


def bin_pixels(image: Float[Array, "... n m"], factor: int) -> Float[Array, "... n/f m/f"]:
    """Sum ``factor x factor`` blocks of the last two axes."""
    n, m = image.shape[-2:]
    shape = (*image.shape[:-2], n // factor, factor, m // factor, factor)
    return image.reshape(shape).sum(axis=(-3, -1))


class LinearDetector(eqx.Module):
    """Jitter, rotation/anisotropy resampling and binning of an oversampled illuminance.

    Attributes
    ----------
    jitter_arcsec
        Gaussian sigma of the instrumental jitter (arcsec; the paper finds ~0.021).
    rotation_deg
        Rotation ``phi`` of the image on the detector (see module notes).
    anisotropy
        y/x pixel-scale ratio ``a`` (see module notes).
    oversample
        Sub-pixels per detector pixel per axis of the input illuminance.
    pixel_scale_arcsec
        Mean pixel scale (the optical grid's unit).
    jitter_radius
        Half width of the jitter kernel in sub-pixels (static; keep it >= 4 sigma).
    resample_reach
        Stencil reach of the resampling (static; see :func:`cubic_resample`).
    """

    jitter_arcsec: Float[Array, ""]
    rotation_deg: Float[Array, ""]
    anisotropy: Float[Array, ""]
    oversample: int = eqx.field(static=True, default=3)
    pixel_scale_arcsec: float = eqx.field(static=True, default=instrument.PIXEL_SCALE_ARCSEC)
    jitter_radius: int = eqx.field(static=True, default=6)
    resample_reach: int = eqx.field(static=True, default=3)

    @classmethod
    def create(
        cls,
        jitter_arcsec: float = instrument.JITTER_SIGMA_ARCSEC,
        rotation_deg: float = instrument.DETECTOR_ROTATION_DEG,
        anisotropy: float = instrument.DETECTOR_ANISOTROPY,
        oversample: int = 3,
        jitter_radius: int = 6,
        npix: int = instrument.SUBARRAY_SIZE,
    ) -> LinearDetector:
        """Detector with the given geometry; the resampling reach is sized for twice the
        rotation and anisotropy given (so that a fit can move them), at least 3."""
        with jax.ensure_compile_time_eval():  # a constant, even when built under jit
            doubled = np.asarray(geometry_matrix(2 * rotation_deg, anisotropy**2))
        n = npix * oversample
        return cls(
            jnp.asarray(float(jitter_arcsec)),
            jnp.asarray(float(rotation_deg)),
            jnp.asarray(float(anisotropy)),
            oversample=oversample,
            jitter_radius=jitter_radius,
            resample_reach=max(3, displacement_reach(np.asarray(doubled), (n, n))),
        )

    # ------------------------------------------------------------------ geometry
    def matrix(self) -> Float[Array, "2 2"]:
        """(2, 2) ``G``: optical offset (mean pixels) -> detector offset (pixels)."""
        return geometry_matrix(self.rotation_deg, self.anisotropy)

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
        scales = jnp.array([instrument.PIXEL_SCALE_X_ARCSEC, instrument.PIXEL_SCALE_Y_ARCSEC])
        return self.detector_to_optical(jnp.asarray(offset_arcsec) / scales)

    def optical_to_detector_arcsec(self, position_arcsec: Float[Array, "... 2"]) -> Array:
        """Optical-frame offset (arcsec) -> detector offset in arcsec along x and y
        (inverse of :meth:`detector_arcsec_to_optical`)."""
        scales = jnp.array([instrument.PIXEL_SCALE_X_ARCSEC, instrument.PIXEL_SCALE_Y_ARCSEC])
        return self.optical_to_detector(position_arcsec) * scales

    # ------------------------------------------------------------------ image
    def jitter(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Gaussian jitter blur on the oversampled optical grid."""
        sigma = self.jitter_arcsec * self.oversample / self.pixel_scale_arcsec
        return gaussian_blur(image, sigma, self.jitter_radius)

    def resample(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Optical oversampled grid -> detector oversampled grid (cubic, flux conserving)."""
        return cubic_resample(image, self.matrix(), self.resample_reach)

    def illuminance(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Jittered, resampled illuminance on the detector's oversampled grid (unit flux).

        This is the input of the non-linear ramp model, which works on sub-pixels.
        """
        return self.resample(self.jitter(image))

    def __call__(self, image: Float[Array, "n m"], flux: Array | float) -> Float[Array, "n/o m/o"]:
        """Detector image ``flux * bin(resample(jitter(image)))`` in pixels, e.g. (80, 80).

        ``image`` is a unit-flux oversampled illuminance (optical frame), e.g. from
        :meth:`amigo.optics.NRMOptics.illuminance`; ``flux`` sets the output's unit
        (photons, electrons or DN/s).
        """
        return flux * bin_pixels(self.illuminance(image), self.oversample)


def sky_to_optical_matrix(orientation, detector: LinearDetector) -> np.ndarray:
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
