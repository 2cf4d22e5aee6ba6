"""Propagation: matrix Fourier transform, Fresnel defocus, pixel integration.

Sign conventions (tested in tests/test_optics.py)
-------------------------------------------------
* The pupil field is ``A(x, y) exp(+2 pi i OPD(x, y) / lambda)``.
* The focal field is ``E(theta) = sum_x A(x) exp(-2 pi i x . theta / lambda)``: an OPD
  that increases along ``+x`` (a tilt ``OPD = t x``) moves the image to ``theta_x = +t``.
* Focal-plane angles ``theta`` (radians) are measured in the optical frame, whose axes are
  the pupil axes (detector axes up to the small rotation of the detector model). The
  image of an on-axis source is centred on the centre of the array (the corner shared
  by the four central pixels for an even number of pixels).
"""

from __future__ import annotations

import functools
from typing import cast

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Complex, Float

#: Defocus is parameterised as the Noll Z4 coefficient (rms OPD) over a circle of this
#: radius factor times the pupil radius, i.e. OPD(r) = 2 sqrt(3) c (r / R)^2 + piston.
SQRT3 = float(np.sqrt(3.0))


def centred_axis(n: int, pitch: float | Array, dtype: DTypeLike | None = None) -> Array:
    """(n,) coordinates ``(k - (n - 1) / 2) * pitch`` of ``n`` pixel centres."""
    return (jnp.arange(n, dtype=dtype) - 0.5 * (n - 1)) * pitch


@eqx.filter_jit
def mft(
    field: Complex[Array, "ny nx"],
    x_m: Float[Array, " nx"],
    y_m: Float[Array, " ny"],
    wavelength_m: Array | float,
    theta_x_rad: Float[Array, " mx"],
    theta_y_rad: Float[Array, " my"],
) -> Complex[Array, "my mx"]:
    """Fraunhofer field ``sum_x A(x) exp(-2 pi i x . theta / lambda)`` on a theta grid.

    A separable matrix Fourier transform (two matrix products): exact at any output
    sampling, with no zero padding. Unnormalised (the caller scales it).
    """
    scale = -2j * jnp.pi / wavelength_m
    tx = jnp.exp(scale * jnp.outer(theta_x_rad, x_m))
    ty = jnp.exp(scale * jnp.outer(theta_y_rad, y_m))
    return ty @ (field @ tx.T)


@eqx.filter_jit
def mft_symmetric(
    field_re: Float[Array, "ny nx"],
    field_im: Float[Array, "ny nx"],
    x_m: Float[Array, " nx"],
    y_m: Float[Array, " ny"],
    wavelength_m: Array | float,
    theta_x_rad: Float[Array, " hx"],
    theta_y_rad: Float[Array, " hy"],
) -> tuple[Float[Array, "2hy 2hx"], Float[Array, "2hy 2hx"]]:
    """:func:`mft` on a focal grid symmetric about zero, in real arithmetic.

    ``theta_x_rad`` and ``theta_y_rad`` are the *positive half* ``t`` of the grids; the
    output is on ``concatenate([-t[::-1], t])`` along each axis, e.g. the upper 120 of the
    240 samples of :func:`centred_axis`. Returns the real and imaginary parts of the
    same field as :func:`mft`, each (2 hy, 2 hx).

    Why: ``exp(-i k t x) = cos(k t x) - i sin(k t x)`` and the grid holds ``-t`` with
    every ``t``, so one real cosine and one real sine matrix of half the outputs serve
    both signs. A complex field times a real matrix is two real products instead of four
    (and XLA's real matrix products are faster than its complex ones): several times
    faster than :func:`mft`, forward and with the gradient (docs/optics.md gives the
    measured speed), agreeing to float rounding (tested). The pupil grid need not be
    symmetric.
    """
    k = 2.0 * jnp.pi / wavelength_m
    phase_x = k * jnp.outer(theta_x_rad, x_m)  # (hx, nx)
    phase_y = k * jnp.outer(theta_y_rad, y_m)  # (hy, ny)
    ny, hx, hy = field_re.shape[0], theta_x_rad.shape[0], theta_y_rad.shape[0]
    # Along x, in one product: [a; b] @ [cos | sin]^T = [[a c, a s], [b c, b s]].
    q = (
        jnp.concatenate([field_re, field_im])
        @ jnp.concatenate([jnp.cos(phase_x), jnp.sin(phase_x)]).T
    )
    ac, as_, bc, bs = q[:ny, :hx], q[:ny, hx:], q[ny:, :hx], q[ny:, hx:]
    # (a + ib)(c -+ is) at +-t: real a c +- b s, imaginary b c -+ a s.
    g_re = jnp.concatenate([(ac - bs)[:, ::-1], ac + bs], axis=1)  # (ny, 2 hx)
    g_im = jnp.concatenate([(bc + as_)[:, ::-1], bc - as_], axis=1)
    # Along y, the same with the complex intermediate g = g_re + i g_im on the right.
    m = 2 * hx
    r = jnp.concatenate([jnp.cos(phase_y), jnp.sin(phase_y)]) @ jnp.concatenate(
        [g_re, g_im], axis=1
    )
    c_re, c_im, s_re, s_im = r[:hy, :m], r[:hy, m:], r[hy:, :m], r[hy:, m:]
    e_re = jnp.concatenate([(c_re - s_im)[::-1], c_re + s_im])
    e_im = jnp.concatenate([(c_im + s_re)[::-1], c_im - s_re])
    return e_re, e_im


@eqx.filter_jit
def fresnel_defocus(
    field: Complex[Array, "m m"],
    pixel_rad: float,
    wavelength_m: Array | float,
    defocus_nm: Array | float,
    radius_m: float,
    pad: int = 2,
) -> Complex[Array, "m m"]:
    """Defocus a focal-plane field with the angular-spectrum transfer function.

    The field is zero-padded ``pad`` times, Fourier transformed (its spectrum is the
    pupil field, at pupil coordinate ``r = lambda |f|`` for spatial frequency ``f`` in
    cycles per radian), multiplied by ``exp(2 pi i OPD(r) / lambda)`` with the achromatic
    quadratic OPD ``OPD(r) = 2 sqrt(3) defocus (r / radius_m)^2`` (the Noll Z4 coefficient
    ``defocus`` over a circle of radius ``radius_m``, without its piston), transformed
    back and cropped to the original size. This is a defocus of the detector, with the
    light that leaves the field of view lost and none entering it from outside.
    """
    m = field.shape[-1]
    big = pad * m
    lo = (big - m) // 2
    padded = jnp.zeros((*field.shape[:-2], big, big), field.dtype)
    padded = padded.at[..., lo : lo + m, lo : lo + m].set(field)
    f = jnp.fft.fftfreq(big, d=pixel_rad).astype(field.real.dtype)  # cycles / radian
    r2 = (wavelength_m * f[:, None]) ** 2 + (wavelength_m * f[None, :]) ** 2  # m^2
    opd_m = (2.0 * SQRT3 * 1e-9) * defocus_nm * r2 / radius_m**2
    transfer = jnp.exp((2j * jnp.pi / wavelength_m) * opd_m)
    out = jnp.fft.ifft2(jnp.fft.fft2(padded) * transfer)
    return out[..., lo : lo + m, lo : lo + m]


# --------------------------------------------------------------------------------------
# Pixel integration
# --------------------------------------------------------------------------------------


@functools.cache
def fit_symmetric_fir(target: str, half_width: int, band: float) -> np.ndarray:
    """Symmetric FIR taps (unit DC gain) fitted by least squares on ``|f| <= band``.

    ``target``: ``"box"`` for ``sinc(f)`` (integration over one sample) or ``"unbox"``
    for ``1 / sinc(f)`` (undoing it); ``f`` in cycles per sample.
    """
    f = np.linspace(0.0, band, 512)
    k = np.arange(1, half_width + 1)
    # H(f) = 1 + 2 sum_k c_k (cos(2 pi f k) - 1): unit gain at f = 0 for any c.
    design = 2.0 * (np.cos(2 * np.pi * np.outer(f, k)) - 1.0)
    response = np.sinc(f) if target == "box" else 1.0 / np.sinc(f)
    c, *_ = np.linalg.lstsq(design, response - 1.0, rcond=None)
    return np.concatenate([c[::-1], [1.0 - 2.0 * c.sum()], c])


def pupil_sharpen_taps() -> np.ndarray:
    """7 taps undoing the pixel average of an anti-aliased pupil (``1 / sinc``) in band.

    Soft-edged holes drawn on a grid are (close to) pixel averages of the true mask:
    the mask convolved with a one-pixel box, whose transform multiplies the focal field
    by ``sinc(theta_x p / lambda) sinc(theta_y p / lambda)``. The SUB80 field only
    reaches ``theta p / lambda < 0.18`` for pupil pixels ``p`` up to 5 cm at 3.8 um
    (0.27 at 2.4 um), where this filter restores the transform to 2e-4 (its response
    times ``sinc`` is within 1.7e-4 of one for ``|f| <= 0.18``). It is applied to the
    amplitude, before the phase, so it holds for any wavefront; with it the PSF of a
    128-pixel pupil matches the analytic one to 6e-4 of its peak (3e-3 without).
    """
    return fit_symmetric_fir("unbox", 3, 0.3)


@functools.cache
def box_fir_taps(half_width: int = 4, band: float = 0.3) -> np.ndarray:
    """Symmetric FIR taps whose response matches a one-sample box integral in band.

    Integrating a band-limited image over the box of one sample (a sub-pixel of the
    oversampled grid) multiplies its spectrum by ``sinc(f) = sin(pi f) / (pi f)`` (``f``
    in cycles per sample). The image of the mask is band limited well inside Nyquist
    (at 3x oversampling ``|f| < 0.18`` for F380M, ``< 0.27`` for F277W), so a short
    filter fitted to ``sinc`` on ``|f| <= band`` integrates it exactly up to the fit
    error (9 taps: at most 2.2e-5 of the transfer function for ``|f| <= 0.27``, against
    6e-3 for the paper's cubic 3x -> 9x -> 3x scheme at ``|f| <= 0.18`` and 5e-2 for no
    integration). Least squares, with unit DC gain exactly.

    Returns
    -------
    (2 * half_width + 1,) taps, summing to one.
    """
    return fit_symmetric_fir("box", half_width, band)


def keys_cubic(t: Array | np.ndarray, a: float = -0.5) -> Array | np.ndarray:
    """Keys cubic-convolution kernel (``a = -0.5``: the classic "cubic" interpolant)."""
    xp = jnp if isinstance(t, Array) else np
    t = xp.abs(t)
    near = ((a + 2) * t - (a + 3)) * t * t + 1
    far = ((a * t - 5 * a) * t + 8 * a) * t - 4 * a
    return xp.where(t <= 1, near, xp.where(t < 2, far, 0.0))


@functools.cache
def cubic_upsample_taps(factor: int = 3) -> np.ndarray:
    """FIR taps equal to: cubic-upsample by ``factor``, then average each block back.

    The paper's scheme (3x -> 9x by cubic interpolation -> mean back to 3x) is linear
    and shift invariant, hence a 5-tap filter: the mean over the ``factor`` sub-sample
    offsets of the cubic kernel weights.
    """
    offsets = (np.arange(factor) - (factor - 1) / 2) / factor
    k = np.arange(-2, 3)
    return np.mean([keys_cubic(t - k) for t in offsets], axis=0)


def separable_filter(image: Float[Array, "... n m"], taps: np.ndarray) -> Array:
    """Convolve the last two axes with the same symmetric 1-D ``taps`` (zero outside)."""
    r = (len(taps) - 1) // 2
    n, m = image.shape[-2:]
    padded = jnp.pad(image, [(0, 0)] * (image.ndim - 2) + [(r, r), (r, r)])
    # cast: sum() starts from the int 0, which typeshed cannot add to an Array.
    rows = cast(Array, sum(float(w) * padded[..., :, i : i + m] for i, w in enumerate(taps)))
    return cast(Array, sum(float(w) * rows[..., i : i + n, :] for i, w in enumerate(taps)))


@eqx.filter_jit
def integrate_pixels(image: Float[Array, "... n m"], method: str = "fir") -> Array:
    """Turn point samples of an oversampled intensity into integrals over sub-pixels.

    ``method``: ``"fir"`` (default, :func:`box_fir_taps`), ``"cubic"`` (the paper's
    3x -> 9x -> 3x cubic scheme, :func:`cubic_upsample_taps`) or ``"none"``. All three
    conserve the total (the taps sum to one) away from the array edges.
    """
    if method == "none":
        return image
    if method == "fir":
        return separable_filter(image, box_fir_taps())
    if method == "cubic":
        return separable_filter(image, cubic_upsample_taps())
    raise ValueError(f"unknown pixel integration method {method!r} (fir, cubic, none)")


def integration_matrix(size: int, method: str = "fir") -> np.ndarray:
    """(size, size) matrix ``F`` of :func:`integrate_pixels` along one axis (its taps on
    the diagonals, zero outside the array as there): ``integrate_pixels(X) = F X F^T``."""
    if method == "none":
        return np.eye(size)
    if method not in ("fir", "cubic"):
        raise ValueError(f"unknown pixel integration method {method!r} (fir, cubic, none)")
    taps = box_fir_taps() if method == "fir" else cubic_upsample_taps()
    r = (len(taps) - 1) // 2
    # separable_filter: out[i] = sum_k taps[k] x[i + k - r].
    matrix = np.zeros((size, size))
    for k, w in enumerate(taps):
        matrix += float(w) * np.eye(size, k=k - r)
    return matrix


def pixel_transfer(frequency_per_sample: Array, method: str = "fir") -> Array:
    """Transfer function of :func:`integrate_pixels` along one axis.

    For code that works on the optical transfer function (e.g. visibility injection):
    multiply the OTF by ``pixel_transfer(fx) * pixel_transfer(fy)`` with ``f`` in cycles
    per oversampled sample, instead of filtering the image.
    """
    if method == "none":
        return jnp.ones_like(frequency_per_sample)
    taps = box_fir_taps() if method == "fir" else cubic_upsample_taps()
    r = (len(taps) - 1) // 2
    k = np.arange(-r, r + 1)
    return jnp.sum(
        jnp.asarray(taps) * jnp.cos(2 * jnp.pi * frequency_per_sample[..., None] * k), axis=-1
    )
