"""The optical model of NIRISS AMI: mask + wavefront -> per-wavelength PSFs -> illuminance.

Data flow (one exposure)::

    spectrum (wavelengths, weights)      source position (optical frame, arcsec)
            |                                      |
    pupil = sharpen(sum_h a_h hole_h) * exp(2 pi i OPD / lambda),
            OPD = sum_hj z_hj Z_hj + source tilt + defocus (the "pupil" defocus method)
            |  MFT to the (80 * oversample)^2 focal grid
            |  [or Fresnel defocus by the angular-spectrum transfer function]
    monochromatic PSFs (n_lambda, 240, 240): point samples, each normalised to unit power
            |  weighted sum over wavelengths (visibility injection goes here, per lambda)
            |  pixel integration (sub-pixel box integrals)
    illuminance (240, 240): the fraction of the source's photons in each sub-pixel

The linear detector (:mod:`amigo.model.detector.linear`) then applies jitter, the detector
rotation/anisotropy and the flux, and bins to 80 x 80 pixels.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jaxtyping import Array, Complex, Float

from amigo import niriss, programs
from amigo.model.optics import propagation
from amigo.model.optics.aperture import (
    Aperture,
    HoleWindows,
    MaskModel,
    PupilGrid,
    StaticAperture,
)
from amigo.model.optics.spectrum import AbstractSpectrum, LinearSpectrum

ARCSEC_TO_RAD = float(np.pi / (180.0 * 3600.0))


@dataclasses.dataclass(frozen=True)
class OpticsConfig:
    """Fidelity and geometry settings of the optical model (static, hashable).

    Attributes
    ----------
    npix_detector
        Detector pixels per side of the modelled field (80 for SUB80).
    oversample
        Sub-pixels per detector pixel per axis of the optical grid (3).
    pixel_scale_arcsec
        Mean detector pixel scale; the optical grid's pitch is this over ``oversample``.
    pupil_npix
        Pupil pixels across ``pupil_diameter_m`` (the grid is cropped to the mask). The
        soft holes are treated as pixel averages and sharpened back
        (:func:`~amigo.model.optics.propagation.pupil_sharpen_taps`), so 128 (5 cm pixels, 15
        across a hole) is accurate to ~5e-4 of the PSF peak.
    pupil_diameter_m
        Diameter whose sampling sets the pupil pitch, and the radius unit of the
        global distortion and of the defocus parameter.
    softening_px
        Width of the soft hole edges, in (sub-sampled) pupil pixels; 1 is best.
    supersample
        Sub-samples per pupil pixel per axis when drawing the holes (pixel averages
        closer to exact: 2 halves the PSF error at 4x the drawing cost).
    n_zernike
        Noll Zernike modes per hole (10: four radial orders).
    zernike_radius_factor
        Radius of each hole's Zernike disc over the hole circumradius.
    fresnel
        Apply the Fresnel defocus (two FFTs per wavelength); off gives pure Fraunhofer.
    fresnel_pad
        Zero-padding factor of the focal field for the defocus.
    defocus_method
        ``"angular_spectrum"`` (the paper's: transfer function applied to the padded
        focal field, two FFTs per wavelength) or ``"pupil"`` (the same quadratic OPD
        added in the pupil; identical but for the light the finite focal field loses
        or wraps, and free).
    pixel_integration
        ``"fir"``, ``"cubic"`` (the paper's scheme) or ``"none"``
        (see :func:`amigo.model.optics.propagation.integrate_pixels`).
    """

    npix_detector: int = niriss.SUBARRAY_SIZE
    oversample: int = 3
    pixel_scale_arcsec: float = niriss.PIXEL_SCALE_ARCSEC
    pupil_npix: int = 128
    pupil_diameter_m: float = niriss.PUPIL_DIAMETER_M
    softening_px: float = 1.0
    supersample: int = 1
    n_zernike: int = 10
    zernike_radius_factor: float = 1.2
    fresnel: bool = True
    fresnel_pad: int = 2
    defocus_method: str = "pupil"
    pixel_integration: str = "fir"

    @property
    def npix_psf(self) -> int:
        """Samples per side of the oversampled optical grid (240 for SUB80 at 3x)."""
        return self.npix_detector * self.oversample

    @property
    def psf_pixel_rad(self) -> float:
        """Pitch of the oversampled optical grid (radians)."""
        return self.pixel_scale_arcsec / self.oversample * ARCSEC_TO_RAD


class NRMOptics(eqx.Module):
    """The mask, the wavefront and the propagation of NIRISS AMI.

    Build it with :meth:`create`; call :meth:`frozen` for the fast path with a
    precomputed mask. All array fields are parameters (fit any subset with equinox
    filtering); ``grid`` and ``config`` are fixed.

    Attributes
    ----------
    aperture
        :class:`~amigo.model.optics.aperture.Aperture` (dynamic: its geometry is fittable) or
        :class:`~amigo.model.optics.aperture.StaticAperture` (fast, fixed geometry), or
        any other :class:`~amigo.model.optics.aperture.MaskModel` (a base model's holes).
    zernikes_nm
        (7, n_zernike) Noll Zernike coefficients per hole, rms OPD in nm. The mean
        piston over the holes is removed in :meth:`pupil` (global piston is not
        observable), so that direction has exactly zero gradient.
    defocus_nm
        Fresnel defocus, the Noll Z4 coefficient (rms nm) over the circle of diameter
        ``config.pupil_diameter_m``: OPD = 2 sqrt(3) defocus (r / R)^2 + constant.
        Positive values add OPD towards the pupil edge. Unused if ``config.fresnel``
        is off.
    hole_amplitudes
        (7,) amplitude transmission of each hole (reflectivity terms; default 1).
    grid
        The pupil sampling.
    config
        :class:`OpticsConfig`.
    """

    aperture: Aperture | StaticAperture | MaskModel
    zernikes_nm: Float[Array, "7 nz"]
    defocus_nm: Float[Array, ""]
    hole_amplitudes: Float[Array, " 7"]
    grid: PupilGrid
    config: OpticsConfig = eqx.field(static=True)

    @classmethod
    def create(
        cls,
        config: OpticsConfig | None = None,
        aperture: Aperture | None = None,
        zernikes_nm: Any = None,
        defocus_nm: float = 0.0,
        static: bool = True,
    ) -> NRMOptics:
        """Model with the nominal mask (or ``aperture``) and the given wavefront.

        ``static=True`` precomputes the mask (fast path); ``False`` keeps it dynamic.
        """
        config = OpticsConfig() if config is None else config
        aperture = Aperture.nominal() if aperture is None else aperture
        grid = PupilGrid.for_mask(config.pupil_npix, config.pupil_diameter_m)
        z = jnp.zeros((niriss.N_HOLES, config.n_zernike)) if zernikes_nm is None else zernikes_nm
        optics = cls(
            aperture=aperture,
            zernikes_nm=jnp.asarray(z),
            defocus_nm=jnp.asarray(float(defocus_nm)),
            hole_amplitudes=jnp.ones(niriss.N_HOLES),
            grid=grid,
            config=config,
        )
        return optics.frozen() if static else optics

    def frozen(self) -> NRMOptics:
        """The same model with the mask precomputed (the fast, non-fittable-mask path)."""
        if isinstance(self.aperture, StaticAperture):
            return self
        c = self.config
        static = StaticAperture.from_aperture(
            self.aperture,
            self.grid,
            c.n_zernike,
            c.zernike_radius_factor,
            c.softening_px,
            c.supersample,
        )
        return eqx.tree_at(lambda o: o.aperture, self, static)

    # ------------------------------------------------------------------ pupil
    @eqx.filter_jit
    def pupil(self) -> tuple[Float[Array, "ny nx"], Float[Array, "ny nx"]]:
        """Amplitude transmission and OPD (metres) on the pupil grid, each (ny, nx).

        The amplitude is the sharpened pixel average of the mask (it slightly overshoots
        1 and undershoots 0 along the hole edges); the OPD is defined everywhere.
        """
        amplitude, opd_m, _ = self._pupil_and_power()
        return amplitude, opd_m

    @eqx.filter_jit
    def pupil_power(self) -> Float[Array, ""]:
        """Power through the mask in pupil pixels: ``sum_h a_h^2 * area_h / pixel^2``."""
        return self._pupil_and_power()[2]

    def _pupil_and_power(self) -> tuple[Array, Array, Array]:
        c = self.config
        holes = self.aperture.hole_transmissions(self.grid, c.softening_px, c.supersample)
        # The soft holes are pixel averages of the mask; sharpen them back (in band) so
        # the MFT of the sampled pupil is the transform of the continuous one.
        amplitude = propagation.separable_filter(
            jnp.tensordot(self.hole_amplitudes, holes, 1), propagation.pupil_sharpen_taps()
        )
        # The soft edges stand for a binary mask whose area is the sum of the soft
        # transmission (not of its square): the power is sum_h a_h^2 * area_h.
        power = jnp.sum(self.hole_amplitudes**2 * jnp.sum(holes, axis=(-2, -1)))
        z = self.zernikes_nm
        z = z.at[:, 0].add(-jnp.mean(z[:, 0]))  # global piston is unobservable
        basis = self.aperture.zernike_basis(self.grid, c.n_zernike, c.zernike_radius_factor)
        opd_m = 1e-9 * jnp.einsum("hj,hjyx->yx", z, basis)
        return amplitude, opd_m, power

    # ------------------------------------------------------------------ propagation
    def focal_grid_rad(self) -> Float[Array, " m"]:
        """(npix_psf,) angles of the optical grid's sample centres along x or y (rad)."""
        c = self.config
        return propagation.centred_axis(c.npix_psf, c.psf_pixel_rad, dtype=self.grid.x_m.dtype)

    @eqx.filter_jit
    def focal_fields(
        self, wavelengths_m: Float[Array, " n"], position_arcsec: Float[Array, " 2"]
    ) -> Complex[Array, "n m m"]:
        """(n, m, m) complex focal fields, scaled so ``|E|^2`` is a normalised PSF.

        ``position_arcsec`` is the source offset ``(x, y)`` in the optical frame. The
        image is shifted exactly, by the pupil tilt ``OPD = x theta_x + y theta_y``
        (the wavelength-independent MFT matrices then carry no parameter, which keeps
        the gradient cheap).
        """
        c = self.config
        re, im = self._fraunhofer_parts(wavelengths_m, position_arcsec)
        e = jax.lax.complex(re, im)
        if c.fresnel and c.defocus_method != "pupil":
            wavelengths = jax.lax.stop_gradient(jnp.asarray(wavelengths_m))
            e = jax.vmap(
                lambda field, wavelength: propagation.fresnel_defocus(
                    field,
                    c.psf_pixel_rad,
                    wavelength,
                    self.defocus_nm,
                    0.5 * c.pupil_diameter_m,
                    c.fresnel_pad,
                )
            )(e, wavelengths)
        return e

    def _fraunhofer_parts(
        self, wavelengths_m: Float[Array, " n"], position_arcsec: Float[Array, " 2"]
    ) -> tuple[Float[Array, "n m m"], Float[Array, "n m m"]]:
        """Real and imaginary parts of the normalised focal fields before any
        angular-spectrum defocus (with the "pupil" defocus method, the final fields)."""
        wavelengths = jax.lax.stop_gradient(jnp.asarray(wavelengths_m))
        return self._focal_fields(*self._pupil_fields(wavelengths, position_arcsec), wavelengths)

    def _focal_fields(
        self, pupil_re: Array, pupil_im: Array, norm: Array, wavelengths: Array
    ) -> tuple[Float[Array, "n m m"], Float[Array, "n m m"]]:
        """Normalised focal fields (real, imaginary) of the pupil fields of
        :meth:`_pupil_fields`, one transform per wavelength."""
        x, y = self.grid.x_m, self.grid.y_m
        e_re, e_im = jax.vmap(lambda a, b, w: self._transform(a, b, x, y, w))(
            pupil_re, pupil_im, wavelengths
        )
        return e_re * norm[:, None, None], e_im * norm[:, None, None]

    def _pupil_fields(
        self, wavelengths: Float[Array, " n"], position_arcsec: Float[Array, " 2"]
    ) -> tuple[Float[Array, "n ny nx"], Float[Array, "n ny nx"], Float[Array, " n"]]:
        """Real and imaginary parts of the pupil field ``A exp(2 pi i OPD / lambda)`` at
        each wavelength (the source's tilt included), and the normalisation of each
        wavelength's transform (:meth:`_field_norm`). The wavelengths are constants of
        the gradient: the MFT matrices depend on them alone."""
        amplitude, opd_m, power = self._pupil_and_power()
        opd_m = self._tilted_opd(opd_m, position_arcsec)
        phase = (2.0 * jnp.pi / wavelengths)[:, None, None] * opd_m
        norm = jax.vmap(lambda w: self._field_norm(w, power))(wavelengths)
        return amplitude * jnp.cos(phase), amplitude * jnp.sin(phase), norm

    def _tilted_opd(self, opd_m: Array, position_arcsec: Array) -> Array:
        """The OPD with the source's tilt (and the pupil-plane defocus, if that method)."""
        c = self.config
        x, y = self.grid.x_m, self.grid.y_m
        pos = jnp.asarray(position_arcsec) * ARCSEC_TO_RAD
        opd_m = opd_m + x[None, :] * pos[0] + y[:, None] * pos[1]
        if c.fresnel and c.defocus_method == "pupil":
            opd_m = opd_m + defocus_opd_m(self.grid, self.defocus_nm, 0.5 * c.pupil_diameter_m)
        return opd_m

    def _field_norm(self, wavelength: Array, power: Array) -> Array:
        """Scale of the MFT that makes ``|E|^2`` a normalised PSF. Parseval: the sum of
        ``|E|^2 dtheta^2`` over the plane is ``lambda^2 dx^2`` times the pupil power."""
        return self.grid.pixel_m * self.config.psf_pixel_rad / (wavelength * jnp.sqrt(power))

    def _transform(
        self, re: Array, im: Array, x_m: Array, y_m: Array, wavelength: Array
    ) -> tuple[Array, Array]:
        """Unnormalised focal field (real, imaginary) of a pupil field on the pixel
        centres ``x_m``, ``y_m`` (the whole grid or a window of it)."""
        c = self.config
        theta = jax.lax.stop_gradient(self.focal_grid_rad())
        if c.npix_psf % 2 == 0:  # the grid holds -t with every t (and no zero)
            half = theta[c.npix_psf // 2 :]
            return propagation.mft_symmetric(re, im, x_m, y_m, wavelength, half, half)
        e = propagation.mft(jax.lax.complex(re, im), x_m, y_m, wavelength, theta, theta)
        return e.real, e.imag

    def wavefront_psf_tangents(
        self,
        wavelengths_m: Float[Array, " n"],
        position_arcsec: Float[Array, " 2"],
        windows: HoleWindows,
    ) -> tuple[Float[Array, "n m m"], Callable[[Array], Float[Array, "j n m m"]]]:
        """The PSFs (as :meth:`psfs`) and a function ``hole -> (n_zernike, n, m, m)``:
        their derivatives with respect to that hole's Zernike coefficients (per nm).

        The same numbers as forward-mode differentiation of :meth:`psfs`, for a fraction
        of the cost. A coefficient ``z_hj`` adds ``1e-9 z_hj Z_hj`` to the OPD, which
        moves the pupil field ``A exp(i phi)`` by ``i k A exp(i phi) 1e-9 Z_hj`` (``k =
        2 pi / lambda``): zero outside the support of hole ``h``'s polynomials. So the
        field's tangent ``dE`` is the transform of that hole's window of the pupil alone
        (``windows``, :func:`~amigo.model.optics.aperture.hole_windows`): a 43-pixel
        window of the 220 x 222 grid of the 256-pixel pupil makes the two matrix
        products of the transform about 5 and 26 times smaller. The PSF's tangent is
        ``2 (Re E Re dE + Im E Im dE)``.

        The piston coefficients are the raw ones: :meth:`pupil` removes the mean piston
        over the holes, so the derivative with respect to ``z_h0`` is this function's
        piston tangent of hole ``h`` less the mean of all holes' piston tangents. That
        needs every hole; the caller subtracts it (linear, at any later stage).

        Only for Fraunhofer propagation (or the "pupil" defocus method, which is part of
        the OPD): the angular-spectrum defocus moves the fields after the transform.
        ``hole`` may be traced (``jax.lax.map`` over the holes compiles one step).
        """
        c = self.config
        if c.fresnel and c.defocus_method != "pupil":
            raise ValueError("hole-window tangents need the pupil defocus method")
        wavelengths = jax.lax.stop_gradient(jnp.asarray(wavelengths_m))
        k = 2.0 * jnp.pi / wavelengths  # (n,)
        pupil_re, pupil_im, norm = self._pupil_fields(wavelengths, position_arcsec)
        e_re, e_im = self._focal_fields(pupil_re, pupil_im, norm, wavelengths)
        psfs = e_re**2 + e_im**2
        x, y = self.grid.x_m, self.grid.y_m
        basis = self.aperture.zernike_basis(self.grid, c.n_zernike, c.zernike_radius_factor)
        origins = jnp.asarray(windows.origins, jnp.int32)  # (h, 2)
        size = windows.size
        n_wave = wavelengths.shape[0]

        def of_hole(hole: Array) -> Array:
            row, col = origins[hole, 0], origins[hole, 1]
            z = jax.lax.dynamic_slice(basis[hole], (0, row, col), (basis.shape[1], size, size))
            window = (0, row, col), (n_wave, size, size)
            f_re = jax.lax.dynamic_slice(pupil_re, *window)
            f_im = jax.lax.dynamic_slice(pupil_im, *window)
            xs = jax.lax.dynamic_slice(x, (col,), (size,))
            ys = jax.lax.dynamic_slice(y, (row,), (size,))
            # dField = i k 1e-9 Z (f_re + i f_im) = k 1e-9 Z (-f_im + i f_re): (j, n, s, s).
            scale = (1e-9 * k)[None, :, None, None] * z[:, None]

            def one(d_re, d_im, wavelength, scale_e):
                t_re, t_im = self._transform(d_re, d_im, xs, ys, wavelength)
                return t_re * scale_e, t_im * scale_e

            per_wave = jax.vmap(one, in_axes=(0, 0, 0, 0))
            de_re, de_im = jax.vmap(per_wave, in_axes=(0, 0, None, None))(
                -scale * f_im[None], scale * f_re[None], wavelengths, norm
            )
            return 2.0 * (e_re[None] * de_re + e_im[None] * de_im)

        return psfs, of_hole

    @programs.jit
    def psfs(
        self, wavelengths_m: Float[Array, " n"], position_arcsec: Float[Array, " 2"]
    ) -> Float[Array, "n m m"]:
        """(n, m, m) monochromatic PSFs: point samples of the intensity.

        Each PSF is the fraction of the photons of that wavelength entering the mask
        per unit sample area: its sum over the infinite plane is one (over the SUB80
        field it is a little less). Not pixel integrated: see :meth:`integrate_pixels`.
        """
        c = self.config
        if c.fresnel and c.defocus_method != "pupil":
            e = self.focal_fields(wavelengths_m, position_arcsec)
            return e.real**2 + e.imag**2
        re, im = self._fraunhofer_parts(wavelengths_m, position_arcsec)
        return re**2 + im**2

    @eqx.filter_jit
    def integrate_pixels(self, image: Float[Array, "... m m"]) -> Float[Array, "... m m"]:
        """Point samples -> integrals over the oversampled sub-pixels (config method)."""
        return propagation.integrate_pixels(image, self.config.pixel_integration)

    # Compiled as one program: evaluated op by op (outside a caller's jit) the optics
    # cost minutes of per-primitive tracing on a 2-core CPU.
    @eqx.filter_jit
    def illuminance(
        self, spectrum: AbstractSpectrum, position_arcsec: Float[Array, " 2"]
    ) -> Float[Array, "m m"]:
        """Broadband, pixel-integrated image of a unit-flux point source, (m, m).

        ``sum_lambda w_lambda psf_lambda`` integrated over sub-pixels: the fraction of
        the source's photons landing in each sub-pixel of the optical grid.
        """
        psfs = self.psfs(spectrum.wavelengths_m, position_arcsec)
        return self.integrate_pixels(jnp.tensordot(spectrum.weights(), psfs, 1))


class PointSource(eqx.Module):
    """An unresolved source seen through the optics.

    Attributes
    ----------
    position_arcsec
        (2,) offset ``(x, y)`` of the source in the optical frame, arcsec from the
        centre of the field. Use :mod:`amigo.model.detector.linear` to convert from detector
        pixels or sky offsets.
    flux
        Total photons (or DN/s, or electrons: the unit of the output image) entering
        the mask in the band during the exposure or per unit time.
    spectrum
        The band's wavelengths and weights (default: :class:`LinearSpectrum`).
    """

    position_arcsec: Float[Array, " 2"]
    flux: Float[Array, ""]
    spectrum: AbstractSpectrum

    @classmethod
    def create(
        cls,
        filter_name: str,
        position_arcsec: npt.ArrayLike = (0.0, 0.0),
        flux: float = 1.0,
        n_wavelengths: int = 9,
        slope_per_um: float = 0.0,
    ) -> PointSource:
        return cls(
            position_arcsec=jnp.asarray(np.asarray(position_arcsec, dtype=float)),
            flux=jnp.asarray(float(flux)),
            spectrum=LinearSpectrum.from_filter(filter_name, n_wavelengths, slope_per_um),
        )


def defocus_opd_m(grid: PupilGrid, defocus_nm: Array, radius_m: float) -> Array:
    """(ny, nx) quadratic OPD ``2 sqrt(3) defocus (r / R)^2`` (metres), Z4 without piston."""
    r2 = grid.x_m[None, :] ** 2 + grid.y_m[:, None] ** 2
    return (2.0 * propagation.SQRT3 * 1e-9) * defocus_nm * r2 / radius_m**2


def strong_types(tree: Any) -> Any:
    """``tree`` with every weakly typed array leaf made strongly typed (same dtype).

    A model built from Python numbers holds weakly typed scalars; the first optimiser
    update returns them strongly typed. A compiled function is keyed on the weak flag, so
    without this every program a training step runs was compiled twice: once for the
    warm-up's model, once for the updated one (measured: ``loss_and_grad`` of a small
    training, 9 s more of compilation).
    """

    def conv(leaf):
        if isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer):
            if leaf.weak_type:
                return jnp.asarray(np.asarray(leaf))  # through the host, as in cast
        return leaf

    return jax.tree.map(conv, tree)


def cast(tree: Any, dtype: Any) -> Any:
    """Cast every floating-point array leaf of a pytree to ``dtype`` (e.g. float32)."""

    target = np.dtype(dtype)

    def conv(leaf):
        if not isinstance(leaf, jax.Array | np.ndarray):
            return leaf
        if not jnp.issubdtype(leaf.dtype, jnp.floating):
            return leaf
        if isinstance(leaf, jax.Array) and leaf.dtype == target:
            return leaf
        if isinstance(leaf, jax.core.Tracer):
            return leaf.astype(target)
        # Through the host, not an XLA conversion: outside a jit every new shape would
        # compile its own conversion program (each costs a compilation; a model has
        # dozens of leaf shapes).
        return jnp.asarray(np.asarray(leaf).astype(target))

    return jax.tree.map(conv, tree)
