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


def cubic_resample(image: Float[Array, "n m"], matrix: Float[Array, "2 2"]) -> Float[Array, "n m"]:
    """Resample ``image`` through the linear map ``matrix`` about the array centre.

    The output sample at offset ``d`` (in samples, from the centre) takes the value of
    the input at ``matrix^-1 d``, by Keys cubic interpolation (zero outside the input).
    For ``det(matrix) = 1`` this moves the image by ``matrix`` while conserving its sum
    (for a well-sampled image away from the edges).
    """
    n, m = image.shape[-2:]
    inverse = jnp.linalg.inv(matrix)
    dy, dx = jnp.meshgrid(
        jnp.arange(n, dtype=image.dtype) - 0.5 * (n - 1),
        jnp.arange(m, dtype=image.dtype) - 0.5 * (m - 1),
        indexing="ij",
    )
    sx = inverse[0, 0] * dx + inverse[0, 1] * dy + 0.5 * (m - 1)
    sy = inverse[1, 0] * dx + inverse[1, 1] * dy + 0.5 * (n - 1)
    x0, y0 = jnp.floor(sx), jnp.floor(sy)
    padded = jnp.pad(image, 2)  # zero outside; indices shift by 2
    out = jnp.zeros_like(sx)
    for j in range(-1, 3):
        wy = keys_cubic(sy - (y0 + j))
        iy = jnp.clip(y0.astype(int) + j + 2, 0, n + 3)
        for i in range(-1, 3):
            wx = keys_cubic(sx - (x0 + i))
            ix = jnp.clip(x0.astype(int) + i + 2, 0, m + 3)
            out = out + wy * wx * padded[iy, ix]
    return out


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
    """

    jitter_arcsec: Float[Array, ""]
    rotation_deg: Float[Array, ""]
    anisotropy: Float[Array, ""]
    oversample: int = eqx.field(static=True, default=3)
    pixel_scale_arcsec: float = eqx.field(static=True, default=instrument.PIXEL_SCALE_ARCSEC)
    jitter_radius: int = eqx.field(static=True, default=6)

    @classmethod
    def create(
        cls,
        jitter_arcsec: float = instrument.JITTER_SIGMA_ARCSEC,
        rotation_deg: float = instrument.DETECTOR_ROTATION_DEG,
        anisotropy: float = instrument.DETECTOR_ANISOTROPY,
        oversample: int = 3,
        jitter_radius: int = 6,
    ) -> LinearDetector:
        return cls(
            jnp.asarray(float(jitter_arcsec)),
            jnp.asarray(float(rotation_deg)),
            jnp.asarray(float(anisotropy)),
            oversample=oversample,
            jitter_radius=jitter_radius,
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

    # ------------------------------------------------------------------ image
    def jitter(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Gaussian jitter blur on the oversampled optical grid."""
        sigma = self.jitter_arcsec * self.oversample / self.pixel_scale_arcsec
        return gaussian_blur(image, sigma, self.jitter_radius)

    def resample(self, image: Float[Array, "n m"]) -> Float[Array, "n m"]:
        """Optical oversampled grid -> detector oversampled grid (cubic, flux conserving)."""
        return cubic_resample(image, self.matrix())

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
