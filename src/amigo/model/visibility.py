"""Interferometric visibilities injected into monochromatic PSFs through their OTFs.

The paper's section "Interferometric Visibility Model". A source that is not a point is
described by its complex visibility ``V(b)`` at baselines ``b`` (metres, pupil frame). Its
image is ``sum_lambda w_lambda * (PSF_lambda convolved with the source)``; in the Fourier
domain of one wavelength the convolution is a product::

    image_lambda = IFFT( OTF_lambda(f) * V(b = f * lambda) ),   OTF_lambda = FFT(PSF_lambda)

with ``f`` the spatial frequency (cycles per radian) of the FFT grid of the (zero-padded)
oversampled PSF, so ``b = f * lambda`` metres. A point source has ``V = 1`` everywhere.

Parameterisation
----------------
``log V = log|V| + i arg V`` is given at the knots of a square, Hermitian grid of
baselines (:class:`UVGrid`, default 51 x 51 knots 0.259 m apart, covering +-6.48 m, beyond
the OTF support of the mask, whose longest baseline plus hole size is ~6.2 m). Hermitian
means ``log|V|(-b) = log|V|(b)`` and ``arg V(-b) = -arg V(b)`` (a real sky): the free
values are those of the half plane (knot index after the centre in raster order), 1300
log-amplitudes and 1300 phases. The centre knot is fixed at ``log V = 0`` (``V(0) = 1``:
the total flux is a separate parameter).

The knots are interpolated onto each wavelength's FFT grid with the separable cubic
convolution kernel of Keys (1981, a = -1/2): ``logV(f lambda) = W_y logV_knots W_x^T``,
where ``W_y``, ``W_x`` are small dense matrices precomputed per wavelength
(:func:`interpolation_matrices`). Outside the knot grid ``log V = 0`` (``V = 1``).

Sign convention: a point source at angular offset ``theta`` (radians, pupil/optical frame)
shifts the image by ``theta`` and has ``V(b) = exp(-2 pi i b . theta / lambda)``, the
convention of numpy's forward FFT (and of the calvis files).
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Float

#: Default knot grid: 51 x 51 knots, 0.259 m apart. Source: AMIGO research code (a grid of
#: +-6.48 m that covers the OTF support of the NIRISS mask, ~6.2 m).
DEFAULT_N_KNOTS: int = 51
DEFAULT_KNOT_SPACING_M: float = 0.259

#: Keys (1981) cubic-convolution parameter (a = -1/2 reproduces quadratics exactly).
_KEYS_A = -0.5


def keys_kernel(t: np.ndarray) -> np.ndarray:
    """Keys cubic convolution kernel at offsets ``t`` (knot units); support ``|t| < 2``."""
    t = np.abs(np.asarray(t, dtype=float))
    a = _KEYS_A
    near = ((a + 2) * t - (a + 3)) * t**2 + 1
    far = ((a * t - 5 * a) * t + 8 * a) * t - 4 * a
    return np.where(t <= 1, near, np.where(t < 2, far, 0.0))


@dataclass(frozen=True)
class UVGrid:
    """The Hermitian grid of baselines on which log-visibilities are parameterised.

    Attributes
    ----------
    n_knots
        Knots per axis (odd, so that the grid has a centre knot at ``b = 0``).
    spacing_m
        Distance between knots (m).
    """

    n_knots: int = DEFAULT_N_KNOTS
    spacing_m: float = DEFAULT_KNOT_SPACING_M

    def __post_init__(self) -> None:
        if self.n_knots < 3 or self.n_knots % 2 == 0:
            raise ValueError(f"n_knots must be odd and >= 3, got {self.n_knots}")
        if self.spacing_m <= 0:
            raise ValueError(f"spacing_m must be positive, got {self.spacing_m}")

    @property
    def centre(self) -> int:
        """Flat (raster) index of the ``b = 0`` knot."""
        return (self.n_knots**2 - 1) // 2

    @property
    def n_half(self) -> int:
        """Number of free knots (the half plane after the centre in raster order)."""
        return self.centre

    @property
    def extent_m(self) -> float:
        """Largest knot coordinate (m)."""
        return (self.n_knots - 1) / 2 * self.spacing_m

    def axis_m(self) -> np.ndarray:
        """(n_knots,) knot coordinates along one axis (m), ascending, symmetric about 0."""
        return (np.arange(self.n_knots) - (self.n_knots - 1) / 2) * self.spacing_m

    def knots_m(self) -> np.ndarray:
        """(n_knots**2, 2) knot baselines ``(u, v)`` (m) in raster order (v rows, u columns)."""
        v, u = np.meshgrid(self.axis_m(), self.axis_m(), indexing="ij")
        return np.column_stack([u.ravel(), v.ravel()])

    def half_indices(self) -> np.ndarray:
        """(n_half,) flat indices of the free knots; their mirrors are ``n**2 - 1 - index``."""
        return np.arange(self.centre + 1, self.n_knots**2)

    def half_knots_m(self) -> np.ndarray:
        """(n_half, 2) baselines (m) of the free knots."""
        return self.knots_m()[self.half_indices()]

    def to_full(
        self, log_amp_half: Float[Array, "... n_half"], phase_half: Float[Array, "... n_half"]
    ) -> tuple[Float[Array, "... n n"], Float[Array, "... n n"]]:
        """Hermitian (n, n) log-amplitude and phase grids from the free half-plane values.

        ``full[k] = half[k]`` after the centre, ``full[mirror(k)] = +half[k]`` (amplitude) or
        ``-half[k]`` (phase) before it, and 0 at the centre. Works on NumPy and JAX arrays.
        """
        xp = jnp if isinstance(log_amp_half, jnp.ndarray) else np
        zero = xp.zeros((*log_amp_half.shape[:-1], 1), dtype=log_amp_half.dtype)
        # Raster order: [mirror of the last half knot, ..., mirror of the first] + centre +
        # [first half knot, ..., last]; the mirror of half index i is centre - 1 - i.
        amp = xp.concatenate([log_amp_half[..., ::-1], zero, log_amp_half], axis=-1)
        pha = xp.concatenate([-phase_half[..., ::-1], zero, phase_half], axis=-1)
        shape = (*log_amp_half.shape[:-1], self.n_knots, self.n_knots)
        return amp.reshape(shape), pha.reshape(shape)

    def fold_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(n**2, n_half) matrices ``S_a``, ``S_p`` with ``full = S @ half`` (see :meth:`to_full`)."""
        n2 = self.n_knots**2
        s_amp = np.zeros((n2, self.n_half))
        s_pha = np.zeros((n2, self.n_half))
        half = self.half_indices()
        cols = np.arange(self.n_half)
        s_amp[half, cols] = 1.0
        s_amp[n2 - 1 - half, cols] = 1.0
        s_pha[half, cols] = 1.0
        s_pha[n2 - 1 - half, cols] = -1.0
        return s_amp, s_pha

    def interpolate(
        self, log_amp_full: np.ndarray, phase_full: np.ndarray, uv_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Evaluate full (n, n) grids at arbitrary baselines ``uv_m`` (k, 2) with the same
        cubic kernel as the injection (NumPy; for outputs such as OIFITS)."""
        w = self.point_weights(uv_m)
        return w @ np.ravel(log_amp_full), w @ np.ravel(phase_full)

    def point_weights(self, uv_m: np.ndarray) -> np.ndarray:
        """(k, n**2) interpolation weights of baselines ``uv_m`` (k, 2) on the full grid."""
        uv_m = np.atleast_2d(np.asarray(uv_m, dtype=float))
        wu = _axis_weights(uv_m[:, 0], self)
        wv = _axis_weights(uv_m[:, 1], self)
        return (wv[:, :, None] * wu[:, None, :]).reshape(len(uv_m), -1)


def _axis_weights(b_m: np.ndarray, grid: UVGrid) -> np.ndarray:
    """(k, n_knots) cubic weights of coordinates ``b_m`` (m) on one knot axis.

    Coordinates outside the grid (beyond the last knot) get all-zero weights, i.e.
    ``log V = 0`` there; knots beyond the edge count as zero.
    """
    t = np.asarray(b_m, dtype=float)[:, None] / grid.spacing_m + (grid.n_knots - 1) / 2
    knots = np.arange(grid.n_knots)[None, :]
    weights = keys_kernel(t - knots)
    inside = (t >= 0) & (t <= grid.n_knots - 1)
    return np.where(inside, weights, 0.0)


def interpolation_matrices(
    grid: UVGrid, fft_size: int, pixel_scale_rad: float, wavelength_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Interpolation from the knots to one wavelength's rfft2 grid, restricted to a band.

    The ``fft_size`` x ``fft_size`` FFT of an image sampled at ``pixel_scale_rad`` has
    frequencies ``fftfreq(fft_size, pixel_scale_rad)`` along y (rows) and
    ``rfftfreq(...)`` along x (columns), i.e. baselines ``f * wavelength_m``.

    Returns
    -------
    rows
        (ny_band,) indices of the FFT rows whose baseline lies within the knot grid.
    w_y
        (ny_band, n_knots) weights of those rows.
    w_x
        (nx_band, n_knots) weights of the first ``nx_band`` columns.
    nx_band
        Number of leading rfft columns within the knot grid.
    """
    fy = np.fft.fftfreq(fft_size, d=pixel_scale_rad) * wavelength_m
    fx = np.fft.rfftfreq(fft_size, d=pixel_scale_rad) * wavelength_m
    rows = np.nonzero(np.abs(fy) <= grid.extent_m)[0]
    nx_band = int(np.count_nonzero(np.abs(fx) <= grid.extent_m))
    return rows, _axis_weights(fy[rows], grid), _axis_weights(fx[:nx_band], grid), nx_band


class Injector(eqx.Module):
    """Injects a log-visibility grid (and a position shift) into monochromatic PSFs.

    Build it once per filter sampling with :meth:`build`; calling it is pure JAX.

    Attributes
    ----------
    w_y
        (n_lambda, ny_band, n_knots) row interpolation weights (zero-padded per wavelength).
    w_x
        (n_lambda, nx_band, n_knots) column interpolation weights.
    rows
        (ny_band,) FFT row indices of the band (static).
    freq_y, freq_x
        (fft_size,), (fft_size // 2 + 1,) FFT frequencies in cycles per *pixel* of the
        oversampled grid (for position shifts).
    fft_size, psf_size, nx_band
        Static sizes.
    """

    w_y: Float[Array, "l ny k"]
    w_x: Float[Array, "l nx k"]
    freq_y: Float[Array, " fy"]
    freq_x: Float[Array, " fx"]
    rows: tuple[int, ...] = eqx.field(static=True)
    fft_size: int = eqx.field(static=True)
    psf_size: int = eqx.field(static=True)
    nx_band: int = eqx.field(static=True)

    @classmethod
    def build(
        cls,
        grid: UVGrid,
        wavelengths_m: np.ndarray,
        pixel_scale_rad: float,
        psf_size: int = 240,
        fft_size: int | None = None,
        dtype: DTypeLike = np.float32,
    ) -> Injector:
        """Precompute the interpolation weights for ``wavelengths_m`` (n_lambda,).

        ``pixel_scale_rad`` is the oversampled PSF pixel (radians, optical frame);
        ``fft_size`` defaults to twice ``psf_size`` (zero padding keeps the circular
        convolution with the source from wrapping PSF wings across the field).
        """
        fft_size = 2 * psf_size if fft_size is None else int(fft_size)
        if fft_size < psf_size:
            raise ValueError(f"fft_size {fft_size} is smaller than the PSF ({psf_size})")
        wavelengths_m = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
        parts = [
            interpolation_matrices(grid, fft_size, pixel_scale_rad, wl) for wl in wavelengths_m
        ]
        # One common band for all wavelengths: the bluest wavelength reaches furthest in
        # pixels; redder ones get zero weights (V = 1) in the extra rows and columns.
        rows = np.unique(np.concatenate([p[0] for p in parts]))
        # The band must be [0..k] and [fft_size - k'..fft_size - 1] (see _band).
        n_pos = int(np.count_nonzero(rows < fft_size // 2))
        if not (
            np.array_equal(rows[:n_pos], np.arange(n_pos))
            and np.array_equal(rows[n_pos:], np.arange(fft_size - (len(rows) - n_pos), fft_size))
        ):
            raise ValueError("the knot grid reaches the Nyquist frequency: use a finer PSF grid")
        nx_band = max(p[3] for p in parts)
        fy = np.fft.fftfreq(fft_size, d=pixel_scale_rad)
        fx = np.fft.rfftfreq(fft_size, d=pixel_scale_rad)
        w_y = np.stack([_axis_weights(fy[rows] * wl, grid) for wl in wavelengths_m])
        w_x = np.stack([_axis_weights(fx[:nx_band] * wl, grid) for wl in wavelengths_m])
        return cls(
            w_y=jnp.asarray(w_y, dtype=dtype),
            w_x=jnp.asarray(w_x, dtype=dtype),
            freq_y=jnp.asarray(np.fft.fftfreq(fft_size), dtype=dtype),
            freq_x=jnp.asarray(np.fft.rfftfreq(fft_size), dtype=dtype),
            rows=tuple(int(r) for r in rows),
            fft_size=fft_size,
            psf_size=psf_size,
            nx_band=nx_band,
        )

    def log_visibility(
        self, log_amp: Float[Array, "k k"], phase: Float[Array, "k k"]
    ) -> tuple[Array, Array]:
        """(n_lambda, ny_band, nx_band) log-amplitude and phase on each FFT band."""
        amp = jnp.einsum("lyi,ij,lxj->lyx", self.w_y, log_amp, self.w_x)
        pha = jnp.einsum("lyi,ij,lxj->lyx", self.w_y, phase, self.w_x)
        return amp, pha

    def otf(self, psfs: Float[Array, "l n n"]) -> Array:
        """(n_lambda, fft_size, fft_size // 2 + 1) OTFs of the zero-padded PSFs."""
        return jnp.fft.rfft2(psfs, s=(self.fft_size, self.fft_size))

    def __call__(
        self,
        psfs: Float[Array, "l n n"],
        log_amp: Float[Array, "k k"] | None = None,
        phase: Float[Array, "k k"] | None = None,
        shift_pix: Float[Array, 2] | None = None,
    ) -> Float[Array, "l n n"]:
        """Monochromatic images of the source: PSFs convolved with the visibility's scene.

        Parameters
        ----------
        psfs
            (n_lambda, n, n) oversampled PSFs, optical frame, indexed ``[y, x]``.
        log_amp, phase
            (n_knots, n_knots) Hermitian log-amplitude and phase grids (or ``None``: 1).
        shift_pix
            Optional ``(dx, dy)`` shift of the whole scene, in oversampled pixels (applied
            as a Fourier phase ramp, exact for band-limited PSFs).

        Returns
        -------
        (n_lambda, n, n) images with the same total flux per wavelength as ``psfs`` (the
        centre knot is fixed, so ``V(0) = 1``).
        """
        otf = self.otf(psfs)
        excess = self._excess(otf, log_amp, phase)
        if excess is not None:
            otf = otf + jax.vmap(self._embed)(excess)
        images = jnp.fft.irfft2(self._shifted(otf, shift_pix), s=(self.fft_size, self.fft_size))
        return images[:, : self.psf_size, : self.psf_size]

    def broadband(
        self,
        psfs: Float[Array, "l n n"],
        weights: Float[Array, " l"],
        log_amp: Float[Array, "k k"] | None = None,
        phase: Float[Array, "k k"] | None = None,
        shift_pix: Float[Array, 2] | None = None,
    ) -> Float[Array, "n n"]:
        """``sum_l weights[l] * self(psfs, log_amp, phase, shift_pix)[l]``, (n, n).

        The same image as weighting the monochromatic images of :meth:`__call__`, at a
        fraction of the cost, which matters because the fit differentiates it once per
        latent visibility (forward mode, ~1100 columns per exposure):

        * every wavelength's PSF is sampled on the same grid, so their spectra share one
          FFT grid and the weighted sum is taken there: one inverse FFT instead of one
          per wavelength (the inverse FFT is linear; the shift is achromatic in pixels);
        * the visibility differs from 1 only inside the band of the knot grid (a tenth
          of the FFT grid), so the spectrum is written as the point source's,
          ``sum_l w_l OTF_l``, plus ``sum_l w_l OTF_l (V_l - 1)`` computed on the band
          alone and zero-padded: the part that depends on the visibilities (and hence
          every Jacobian column) never touches the rest of the grid;
        * that part is brought back to the image by its own inverse transform, pruned to
          what is non-zero and what is kept (:meth:`_band_image`): the point source's
          image and the visibilities' are added after the transforms (which are linear),
          so a latent column's tangent never enters the full-grid transform.
        """
        image, band = self.broadband_parts(psfs, weights, log_amp, phase, shift_pix)
        if band is None:
            return image
        return image + self._band_image(band, shift_pix)

    def broadband_parts(
        self,
        psfs: Float[Array, "l n n"],
        weights: Float[Array, " l"],
        log_amp: Float[Array, "k k"] | None = None,
        phase: Float[Array, "k k"] | None = None,
        shift_pix: Float[Array, 2] | None = None,
    ) -> tuple[Float[Array, "n n"], Array | None]:
        """The two parts of :meth:`broadband`: the point source's image (n, n), shifted,
        and the visibilities' band ``sum_l w_l OTF_l (V_l - 1)`` (ny_band, nx_band),
        complex, not yet shifted (``None`` without visibilities). The image is the first
        plus ``Re(E_y band E_x^T)`` with the matrices of :meth:`band_axes`."""
        weights = weights.astype(psfs.dtype)
        # The transform is linear: the point source's spectrum is the transform of the
        # weighted PSF, one FFT instead of one per wavelength.
        spectrum = self._shifted(self.otf(jnp.tensordot(weights, psfs, 1)), shift_pix)
        image = jnp.fft.irfft2(spectrum, s=(self.fft_size, self.fft_size))
        image = image[: self.psf_size, : self.psf_size]
        if log_amp is None and phase is None:
            return image, None
        excess = self._excess_on_band(self.band_otf(psfs), log_amp, phase)
        return image, jnp.tensordot(weights, excess, 1)

    def band_otf(self, psfs: Float[Array, "l n n"]) -> Array:
        """(n_lambda, ny_band, nx_band) OTFs of the zero-padded PSFs on the band alone:
        ``self._band(self.otf(psfs))``, computed as two real matrix products.

        Why not the FFT: the band is a tenth of the rfft grid, and a discrete Fourier
        transform restricted to it costs fewer operations than it sounds, at the speed
        of matrix products. Measured on 2 CPU cores (nine 264^2 PSFs, float32): the
        pass along x that keeps 76 of 265 columns takes 2.0 ms as a matrix product
        against 11 ms as an FFT of every row, and the whole band 5 ms against 28 ms for
        ``rfft2``. Every evaluation of the model pays it, and so does every column of
        the instrument block's Jacobian (its tangents move the PSFs).

        The phases ``2 pi k n / N`` are reduced modulo ``N`` in integers before the
        cosine, as in :meth:`band_axes`.
        """
        size = psfs.shape[-1]
        n = np.arange(size)
        fx = np.arange(self.nx_band)
        turns_x = ((fx[:, None] * n[None, :]) % self.fft_size) / self.fft_size
        turns_y = ((np.asarray(self.rows)[:, None] * n[None, :]) % self.fft_size) / self.fft_size
        dtype = psfs.dtype
        # Along x: A = psf (cos - i sin)^T as one product with [cos | sin]^T.
        cos_sin_x = np.concatenate([np.cos(2 * np.pi * turns_x), np.sin(2 * np.pi * turns_x)])
        a = psfs @ jnp.asarray(cos_sin_x.T, dtype)  # (l, n, 2 nx): [A_re | -A_im]
        # Along y: B = (C - i S) A with A = a_c - i a_s, as one product [C; S] @ [a_c | a_s].
        cos_sin_y = np.concatenate([np.cos(2 * np.pi * turns_y), np.sin(2 * np.pi * turns_y)])
        b = jnp.asarray(cos_sin_y, dtype) @ a  # (l, 2 ny, 2 nx)
        ny, nx = len(self.rows), self.nx_band
        c_c, c_s, s_c, s_s = b[:, :ny, :nx], b[:, :ny, nx:], b[:, ny:, :nx], b[:, ny:, nx:]
        # (C - i S)(a_c - i a_s) = (C a_c - S a_s) - i (C a_s + S a_c).
        return jax.lax.complex(c_c - s_s, -(c_s + s_c))

    def band_axes(
        self, shift_pix: Float[Array, 2] | None, start: int, size: int, dtype: DTypeLike
    ) -> tuple[Array, Array]:
        """Complex matrices ``E_y`` (size, ny_band) and ``E_x`` (size, nx_band) with
        ``Re(E_y band E_x^T)`` equal to ``_band_image(band, shift_pix)[start:start + size,
        start:start + size]``: the inverse transform of the band as two matrix products.

        Row ``n`` of ``E_y`` holds ``exp(2 pi i r n / N) / N`` for the band's rows ``r``;
        ``E_x`` the same for its columns ``k``, doubled for ``k > 0`` (the Hermitian half
        of the spectrum not stored), so that the real part is ``irfft``'s; each column
        times the shift's phase ramp. The phases are reduced modulo ``N`` in integers
        before the exponential: ``2 pi r n / N`` reaches ~1600 rad, where float32 would
        lose 1e-4 rad.
        """
        n = np.arange(start, start + size)[:, None]
        rows = np.asarray(self.rows)[None, :]
        cols = np.arange(self.nx_band)[None, :]
        size_fft = self.fft_size
        e_y = np.exp(2j * np.pi * ((n * rows) % size_fft) / size_fft) / size_fft
        e_x = np.exp(2j * np.pi * ((n * cols) % size_fft) / size_fft) / size_fft
        e_x[:, 1:] *= 2.0
        complex_dtype = jnp.result_type(dtype, 1j)
        e_y, e_x = jnp.asarray(e_y, complex_dtype), jnp.asarray(e_x, complex_dtype)
        if shift_pix is None:
            return e_y, e_x
        ramp_y, ramp_x = self._band_ramps(shift_pix)
        return e_y * ramp_y[None, :], e_x * ramp_x[None, :]

    def _band_ramps(self, shift_pix: Float[Array, 2]) -> tuple[Array, Array]:
        """The phase ramps of :meth:`_shifted` on the band's rows (ny_band,) and columns
        (nx_band,)."""
        ramp_y = jnp.exp(-2j * jnp.pi * self.freq_y[np.asarray(self.rows)] * shift_pix[1])
        ramp_x = jnp.exp(-2j * jnp.pi * self.freq_x[: self.nx_band] * shift_pix[0])
        return ramp_y, ramp_x

    def _band_image(self, band: Array, shift_pix: Array | None) -> Float[Array, "n n"]:
        """The kept (psf_size, psf_size) corner of ``irfft2`` of a band array (ny_band,
        nx_band), shifted by ``shift_pix``, zero elsewhere on the rfft grid.

        ``irfft2`` is a complex inverse FFT along the rows followed by a real inverse FFT
        along the last axis. Only the band's ``nx_band`` columns are non-zero in the
        first and only ``psf_size`` rows of its result are kept for the second, so the
        two passes transform ``nx_band`` columns (of ``fft_size // 2 + 1``) and
        ``psf_size`` rows (of ``fft_size``): the same numbers as :meth:`_embed` then
        ``irfft2``, for about a third of the work.
        """
        if shift_pix is not None:
            ramp_y, ramp_x = self._band_ramps(shift_pix)
            band = band * ramp_y[:, None] * ramp_x[None, :]
        n_pos = self._n_positive_rows
        gap = jnp.zeros((self.fft_size - len(self.rows), self.nx_band), band.dtype)
        columns = jnp.concatenate([band[:n_pos], gap, band[n_pos:]], axis=0)
        rows = jnp.fft.ifft(columns, axis=0)[: self.psf_size]
        return jnp.fft.irfft(rows, n=self.fft_size, axis=-1)[:, : self.psf_size]

    def _excess(self, otf: Array, log_amp: Array | None, phase: Array | None) -> Array | None:
        """(n_lambda, ny_band, nx_band) ``OTF (V - 1)`` on the band (``V = 1`` outside
        it), or ``None`` when no visibility is given."""
        if log_amp is None and phase is None:
            return None
        return self._excess_on_band(self._band(otf), log_amp, phase)

    def _excess_on_band(self, band_otf: Array, log_amp: Array | None, phase: Array | None) -> Array:
        """``OTF (V - 1)`` from the OTFs on the band (n_lambda, ny_band, nx_band)."""
        log_amp = jnp.zeros(self.w_y.shape[-1:] * 2) if log_amp is None else log_amp
        phase = jnp.zeros_like(log_amp) if phase is None else phase
        amp, pha = self.log_visibility(log_amp, phase)
        return band_otf * jnp.expm1(amp + 1j * pha)

    def _shifted(self, spectrum: Array, shift_pix: Array | None) -> Array:
        """``spectrum`` (..., fft, fft // 2 + 1) times the phase ramp of a ``(dx, dy)``
        shift in oversampled pixels (unchanged for ``None``)."""
        if shift_pix is None:
            return spectrum
        ramp_x = jnp.exp(-2j * jnp.pi * self.freq_x * shift_pix[0])
        ramp_y = jnp.exp(-2j * jnp.pi * self.freq_y * shift_pix[1])
        return spectrum * ramp_y[:, None] * ramp_x[None, :]

    @property
    def _n_positive_rows(self) -> int:
        """Band rows at non-negative frequencies (the first ones of :attr:`rows`)."""
        return int(np.count_nonzero(np.asarray(self.rows) < self.fft_size // 2))

    def _band(self, otf: Array) -> Array:
        """The band's rows and leading columns of an rfft grid ``(..., fft, fft // 2 + 1)``:
        the non-negative rows ``0..k`` then the negative ones, as :attr:`rows` lists them."""
        n_pos = self._n_positive_rows
        n_neg = len(self.rows) - n_pos
        top = otf[..., :n_pos, : self.nx_band]
        bottom = otf[..., self.fft_size - n_neg :, : self.nx_band]
        return jnp.concatenate([top, bottom], axis=-2)

    def _embed(self, band: Array) -> Array:
        """Zero-pad a band array (ny_band, nx_band) to the rfft grid (inverse of :meth:`_band`)."""
        n_pos = self._n_positive_rows
        gap = self.fft_size - len(self.rows)
        full = jnp.concatenate(
            [band[:n_pos], jnp.zeros((gap, self.nx_band), band.dtype), band[n_pos:]], axis=0
        )
        return jnp.pad(full, ((0, 0), (0, self.fft_size // 2 + 1 - self.nx_band)))


def point_source_visibility(
    uv_m: np.ndarray, wavelength_m: float | np.ndarray, offset_rad: np.ndarray
) -> np.ndarray:
    """Complex ``V = exp(-2 pi i b . theta / lambda)`` of a unit point source at ``offset_rad``.

    ``uv_m`` (..., 2), ``offset_rad`` (2,) in the pupil frame; returns complex (...).
    """
    phase = -2 * np.pi * (np.asarray(uv_m) @ np.asarray(offset_rad)) / wavelength_m
    return np.exp(1j * phase)


def binary_log_visibility(
    uv_m: np.ndarray,
    wavelengths_m: np.ndarray,
    weights: np.ndarray,
    offset_rad: np.ndarray,
    contrast: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``(log|V|, arg V)`` of a primary at the origin plus a companion of flux ratio
    ``contrast`` at ``offset_rad`` (pupil frame), averaged over the band.

    ``V(b) = sum_l w_l (1 + c exp(-2 pi i b.theta / lambda_l)) / (1 + c)``. This is the
    model the calvis files are evaluated with.
    """
    uv_m = np.asarray(uv_m, dtype=float)
    vis = np.zeros(uv_m.shape[:-1], dtype=complex)
    weights = np.asarray(weights, dtype=float) / np.sum(weights)
    for wl, w in zip(np.atleast_1d(wavelengths_m), np.atleast_1d(weights), strict=True):
        vis += w * (1 + contrast * point_source_visibility(uv_m, wl, offset_rad))
    vis /= 1 + contrast
    return np.log(np.abs(vis)), np.angle(vis)


class LatentBasis(eqx.Module):
    """Orthonormal latent basis of the log-visibilities of one filter.

    ``log|V|`` at the free knots is ``amp @ alpha`` and ``arg V`` is ``phase @ beta``
    (zero at knots the basis does not reach). Build with :mod:`amigo.model.basis`.

    Attributes
    ----------
    amp, phase
        (n_used, m_a), (n_used, m_p) orthonormal columns over the used knots.
    knots
        (n_used,) indices of the used knots among the grid's free (half-plane) knots.
    grid
        The :class:`UVGrid`.
    """

    amp: Float[Array, "u ma"]
    phase: Float[Array, "u mp"]
    knots: tuple[int, ...] = eqx.field(static=True)
    grid: UVGrid = eqx.field(static=True)

    @property
    def n_amp(self) -> int:
        return int(self.amp.shape[1])

    @property
    def n_phase(self) -> int:
        return int(self.phase.shape[1])

    def half(
        self, alpha: Float[Array, " ma"], beta: Float[Array, " mp"]
    ) -> tuple[Float[Array, " h"], Float[Array, " h"]]:
        """Log-amplitude and phase at all free knots, each (n_half,)."""
        idx = np.asarray(self.knots)
        zero = jnp.zeros(self.grid.n_half, dtype=self.amp.dtype)
        return zero.at[idx].set(self.amp @ alpha), zero.at[idx].set(self.phase @ beta)

    def grids(
        self, alpha: Float[Array, " ma"], beta: Float[Array, " mp"]
    ) -> tuple[Float[Array, "k k"], Float[Array, "k k"]]:
        """Hermitian (n_knots, n_knots) log-amplitude and phase grids."""
        return self.grid.to_full(*self.half(alpha, beta))

    def knots_m(self) -> np.ndarray:
        """(n_used, 2) baselines (m) of the used knots."""
        return self.grid.half_knots_m()[np.asarray(self.knots)]

    def latent_from_knots(self) -> np.ndarray:
        """(m_a + m_p, 2 n_used) ``B^T``: knot ``[log|V|, arg V]`` -> latents (NumPy float64).

        The basis is orthonormal, so this is the least-squares projection onto it.
        """
        a = np.asarray(self.amp, dtype=float)
        p = np.asarray(self.phase, dtype=float)
        out = np.zeros((a.shape[1] + p.shape[1], 2 * a.shape[0]))
        out[: a.shape[1], : a.shape[0]] = a.T
        out[a.shape[1] :, a.shape[0] :] = p.T
        return out
