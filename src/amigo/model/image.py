"""Image-level forward model of one exposure (STScI level-2 data).

::

    wavelengths, weights (filter x linear SED)       position (optical frame, arcsec)
          |                                                   |
    optics (issue 3): mask + Zernikes + Fresnel defocus -> PSF_lambda (n_lambda, 240, 240)
          |  visibilities: IFFT(OTF_lambda * exp(log V(b = f lambda)))      (amigo.model.visibility)
          |  weighted sum over wavelengths, pixel integration
          |  linear detector (issue 3): jitter, rotation/anisotropy, 3x3 binning
          |  x flux
    image (80, 80), DN/s

Who owns what
-------------
:class:`Instrument`
    The base model: everything that is *not* fitted to science data (mask geometry,
    jitter, detector rotation and anisotropy, the nominal aberrations and defocus). Issue
    8 will ship a calibrated one; until then the nominal instrument of issues 2/3 is used.
:class:`FilterSetup`
    What is fixed per filter during a fit: wavelengths and filter weights, the
    visibility :class:`~amigo.model.visibility.Injector` and :class:`~amigo.model.visibility.LatentBasis`.
:class:`OpticsParams`, :class:`SourceParams`, :class:`ExposureParams`
    The fitted parameters, shared per filter (aberrations, defocus: from calibrators),
    per target and filter (latent visibilities, spectral slope), per exposure (position,
    flux). :mod:`amigo.fitting.filter_fit` wires the sharing.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Float

from amigo import niriss as nis
from amigo._version import __version__
from amigo.errors import InputError
from amigo.io.files import require_file
from amigo.model.detector.linear import LinearDetector
from amigo.model.optics import LinearSpectrum, NRMOptics, cast
from amigo.model.optics.aperture import HoleWindows
from amigo.model.optics.propagation import integration_matrix
from amigo.model.visibility import Injector, LatentBasis, UVGrid

if TYPE_CHECKING:
    from amigo.model.base import BaseModel

T = TypeVar("T")

#: Number of wavelengths propagated per filter. Source: AMIGO paper (9 by default).
DEFAULT_N_WAVELENGTHS = 9
#: Detector pixels of optical field computed beyond each edge of SUB80, so that sources
#: can be shifted by up to this much in the Fourier domain with no light missing at the
#: field edges (4 px: 3e-6 of the peak against 2e-3 without; see tests/test_model.py).
FIELD_MARGIN_PIX = 4
#: FFT size of the visibility injection for the (80 + 2 * margin) * 3 = 264 sample field.
INJECTION_FFT_SIZE = 512


class Instrument(eqx.Module):
    """The base model: the instrument state held fixed when fitting science data.

    Attributes
    ----------
    optics
        :class:`~amigo.model.optics.NRMOptics` (static mask), whose ``zernikes_nm`` and
        ``defocus_nm`` are the starting point of the per-filter :class:`OpticsParams`.
    detector
        :class:`~amigo.model.detector.linear.LinearDetector`.
    n_wavelengths
        Wavelengths per filter.
    name
        Name and version of the base model (written into ``fit_summary.json``).
    """

    optics: NRMOptics
    detector: LinearDetector
    n_wavelengths: int = eqx.field(static=True, default=DEFAULT_N_WAVELENGTHS)
    name: str = eqx.field(static=True, default=f"nominal-{__version__}")

    @classmethod
    def nominal(cls, n_wavelengths: int = DEFAULT_N_WAVELENGTHS) -> Instrument:
        """The uncalibrated nominal instrument (instrument facts, no aberrations)."""
        return cls(
            optics=NRMOptics.create(),
            detector=LinearDetector.create(),
            n_wavelengths=n_wavelengths,
            name=f"nominal-{__version__} (uncalibrated: no base model trained yet)",
        )

    @classmethod
    def from_base_model(
        cls,
        base: BaseModel,
        filter_name: str,
        name: str = "amigo base model",
        detector: str = "linear",
    ) -> Instrument:
        """The image-level instrument of one filter from a trained
        :class:`~amigo.model.base.BaseModel`: its mask (fitted hole positions), wavefront
        and defocus of that filter, its linear detector (jitter, geometry) and its IPC
        kernel. The base model's ramp and read models are not part of it: they act
        on calslope data through :mod:`amigo.fitting.ramp_fit`; ``detector`` (``"full"``,
        ``"linear"`` or ``"boundary"``) only names the one in use."""
        optics = base.optics(filter_name, base.pupil_cache())
        # Images see the base model's own IPC kernel (its read model applies it to ramps).
        linear = eqx.tree_at(
            lambda d: d.ipc_kernel, base.detector, base.read.ipc_kernel, is_leaf=lambda x: x is None
        )
        return cls(
            optics=optics,
            detector=linear,
            n_wavelengths=int(base.config.n_wavelengths),
            name=f"{name} ({filter_name}; {detector} detector)",
        )

    def with_geometry(self, geometry: Float[Array, " 4"]) -> Instrument:
        """This instrument with the detector geometry ``[rotation_deg, anisotropy,
        skew_deg, scale]`` (:data:`amigo.model.detector.linear.GEOMETRY_NAMES`; differentiable)."""
        return eqx.tree_at(lambda i: i.detector, self, self.detector.with_geometry(geometry))

    @property
    def psf_pixel_rad(self) -> float:
        return float(self.optics.config.psf_pixel_rad)

    @property
    def psf_size(self) -> int:
        """Samples per side of the detector's oversampled grid (240)."""
        return int(self.optics.config.npix_psf)

    @property
    def oversample(self) -> int:
        return int(self.optics.config.oversample)

    @property
    def field_size(self) -> int:
        """Samples per side of the optical field computed (240 + 2 margins = 264)."""
        return self.psf_size + 2 * FIELD_MARGIN_PIX * self.oversample

    def wide_optics(self, optics_params: OpticsParams) -> NRMOptics:
        """The optics with the given wavefront, on the field widened by the margins."""
        o = self.optics
        config = dataclasses.replace(
            o.config, npix_detector=o.config.npix_detector + 2 * FIELD_MARGIN_PIX
        )
        return NRMOptics(
            aperture=o.aperture,
            zernikes_nm=optics_params.zernikes_nm,
            defocus_nm=optics_params.defocus_nm,
            hole_amplitudes=o.hole_amplitudes,
            grid=o.grid,
            config=config,
        )


#: First line of an instrument file since format 2; a JSON line of the instrument's static
#: settings (``n_wavelengths``, ``name``) follows, then its arrays (equinox leaves). A
#: format-1 file holds the arrays alone: its static settings were not saved, and it loads
#: with the nominal ones (an instrument saved with 3 wavelengths was fitted with 9).
INSTRUMENT_MAGIC = b"AMIGO-INSTRUMENT 2\n"


def save_instrument(instrument: Instrument, path: str | Path) -> None:
    """Write an :class:`Instrument` to ``path`` (atomically): its static settings and its
    arrays, so that :func:`load_instrument` gives back the same instrument."""
    import json

    from amigo.io.atomic import atomic_path

    settings = {"n_wavelengths": int(instrument.n_wavelengths), "name": str(instrument.name)}
    with atomic_path(path) as tmp, open(tmp, "wb") as stream:
        stream.write(INSTRUMENT_MAGIC)
        stream.write(json.dumps(settings).encode() + b"\n")
        eqx.tree_serialise_leaves(stream, instrument)


def load_instrument(path: str | os.PathLike[str]) -> Instrument:
    """Load an instrument written by :func:`save_instrument` (format 2, or format 1: the
    arrays alone, loaded with the nominal static settings).

    Raises :class:`~amigo.errors.InputError` if the file does not match the structure.
    """
    import json

    path = require_file(path, "base-model file")
    tagged = False  # a file that says it is an instrument (format 2)
    try:
        with open(path, "rb") as stream:
            tagged = stream.read(len(INSTRUMENT_MAGIC)) == INSTRUMENT_MAGIC
            if tagged:
                settings = json.loads(stream.readline())
                n_wavelengths = int(settings["n_wavelengths"])
                if n_wavelengths < 1:
                    raise ValueError(f"n_wavelengths {n_wavelengths}")
                nominal = Instrument.nominal(n_wavelengths)
                like = Instrument(
                    nominal.optics, nominal.detector, n_wavelengths, str(settings["name"])
                )
            else:
                stream.seek(0)
                like = Instrument.nominal()
            return eqx.tree_deserialise_leaves(stream, like)
    except Exception as error:  # equinox, json and int() raise several types
        if not tagged:  # any other file: equinox's message would name a leaf, not the file
            raise InputError(
                path, "is neither a trained base model (.npz) nor an amigo instrument file"
            ) from None
        raise InputError(
            path, f"is not an amigo instrument file of this version ({error})"
        ) from None


class FilterSetup(eqx.Module):
    """Everything fixed for one filter during a fit.

    Attributes
    ----------
    name
        Filter.
    wavelengths_m, filter_weights
        (n,) bin wavelengths (m) and integrated throughputs (sum to one).
    central_wavelength_m
        Throughput-weighted mean wavelength (m): the pivot of the linear SED.
    injector
        Visibility injection for these wavelengths.
    grid
        The knot grid of the log-visibilities.
    basis
        Latent visibility basis of the filter (``None`` while the basis is being built).
    band_taper_per_um2
        The band-shape correction ``tau`` of :class:`~amigo.model.optics.LinearSpectrum`
        (``None``: 0); fitted per filter with the instrument block.
    """

    name: str = eqx.field(static=True)
    wavelengths_m: Float[Array, " n"]
    filter_weights: Float[Array, " n"]
    central_wavelength_m: Float[Array, ""]
    injector: Injector
    grid: UVGrid = eqx.field(static=True)
    basis: LatentBasis | None = None
    band_taper_per_um2: Float[Array, ""] | None = None

    @classmethod
    def create(
        cls,
        name: str,
        instrument: Instrument,
        basis: LatentBasis | None = None,
        grid: UVGrid | None = None,
        dtype: DTypeLike = np.float32,
        bins: nis.FilterBins | None = None,
    ) -> FilterSetup:
        """Setup of filter ``name``; ``grid`` defaults to the basis's (or the default).
        ``bins``: the wavelengths and weights (default: the filter throughput binned,
        :func:`amigo.niriss.filter_bins`; :func:`amigo.model.bandpass.effective_bins` gives
        the physical band of a star)."""
        grid = basis.grid if basis is not None else (grid or UVGrid())
        if bins is None:
            bins = nis.filter_bins(name, instrument.n_wavelengths)
        elif len(bins.wavelengths_m) != instrument.n_wavelengths:
            raise ValueError(
                f"{len(bins.wavelengths_m)} wavelengths given, the instrument propagates "
                f"{instrument.n_wavelengths}"
            )
        injector = Injector.build(
            grid,
            bins.wavelengths_m,
            instrument.psf_pixel_rad,
            instrument.field_size,
            fft_size=INJECTION_FFT_SIZE,
            dtype=dtype,
        )
        return cls(
            name=name,
            wavelengths_m=jnp.asarray(bins.wavelengths_m, dtype),
            filter_weights=jnp.asarray(bins.weights, dtype),
            central_wavelength_m=jnp.asarray(bins.central_wavelength_m, dtype),
            injector=injector,
            grid=grid,
            basis=basis,
        )

    def spectrum(self, slope_per_um: Array) -> LinearSpectrum:
        """The filter's :class:`~amigo.model.optics.LinearSpectrum` with SED slope ``m`` (and
        the setup's band-shape correction)."""
        taper = 0.0 if self.band_taper_per_um2 is None else self.band_taper_per_um2
        return LinearSpectrum(
            wavelengths_m=self.wavelengths_m,
            filter_weights=self.filter_weights,
            central_wavelength_m=self.central_wavelength_m,
            slope_per_um=slope_per_um,
            taper_per_um2=taper,
        )

    def with_band_taper(self, taper_per_um2: Array) -> FilterSetup:
        """This setup with the band-shape correction ``tau`` (differentiable)."""
        return eqx.tree_at(
            lambda s: s.band_taper_per_um2,
            self,
            jnp.asarray(taper_per_um2),
            is_leaf=lambda x: x is None,
        )


class OpticsParams(eqx.Module):
    """Per-filter instrument state: fitted on calibrators, fixed for science targets.

    Attributes
    ----------
    zernikes_nm
        (7, 10) Noll Zernike coefficients per hole (rms nm).
    defocus_nm
        Fresnel defocus (Noll Z4 over the pupil, rms nm; see :class:`~amigo.model.optics.NRMOptics`).
    geometry
        (4,) detector geometry ``[rotation_deg, anisotropy, skew_deg, scale]``
        (:data:`amigo.model.detector.linear.GEOMETRY_NAMES`).
    band_taper_per_um2
        The band-shape correction ``tau`` (:class:`~amigo.model.optics.LinearSpectrum`).
    """

    zernikes_nm: Float[Array, "7 nz"]
    defocus_nm: Float[Array, ""]
    geometry: Float[Array, " 4"]
    band_taper_per_um2: Float[Array, ""]

    @classmethod
    def from_instrument(cls, instrument: Instrument) -> OpticsParams:
        dtype = instrument.optics.zernikes_nm.dtype
        return cls(
            instrument.optics.zernikes_nm,
            instrument.optics.defocus_nm,
            instrument.detector.geometry().astype(dtype),
            jnp.zeros((), dtype),
        )


class SourceParams(eqx.Module):
    """Per target and filter: latent visibilities and spectral slope.

    Attributes
    ----------
    amp, phase
        (m_a,), (m_p,) latent log-amplitudes and phases (see :class:`LatentBasis`).
    slope_per_um
        Linear SED slope ``m`` (per micron).
    """

    amp: Float[Array, " ma"]
    phase: Float[Array, " mp"]
    slope_per_um: Float[Array, ""]

    @classmethod
    def point(cls, basis: LatentBasis, dtype: DTypeLike = jnp.float32) -> SourceParams:
        """A point source (``V = 1``) with a flat SED."""
        return cls(
            jnp.zeros(basis.n_amp, dtype), jnp.zeros(basis.n_phase, dtype), jnp.zeros((), dtype)
        )


class ExposureParams(eqx.Module):
    """Per exposure: position of the source, its flux and the pointing jitter.

    Attributes
    ----------
    position_arcsec
        (2,) offset ``(x, y)`` from the field centre in the optical frame (arcsec).
    log_flux
        Natural log of the flux entering the mask, in the image unit (DN/s for level 2).
    jitter_mas
        Gaussian sigma of the exposure's jitter (mas; its sign is irrelevant, the blur
        depends on its square).
    """

    position_arcsec: Float[Array, " 2"]
    log_flux: Float[Array, ""]
    jitter_mas: Float[Array, ""]


def filter_psfs(
    instrument: Instrument,
    setup: FilterSetup,
    optics_params: OpticsParams,
    anchor_arcsec: Float[Array, " 2"] | None = None,
) -> Float[Array, "l 264 264"]:
    """(n_lambda, 264, 264) monochromatic PSFs (unit power each) on the widened field.

    Computed once per filter and shared by every exposure of the filter, for a source at
    ``anchor_arcsec`` (optical frame; default the centre): each exposure's offset from the
    anchor is applied as a Fourier phase ramp in the visibility injection, which equals
    the optics' pupil tilt for a band-limited PSF, at no extra propagation cost. The
    margins keep this exact for offsets up to :data:`FIELD_MARGIN_PIX` pixels.
    """
    optics = instrument.wide_optics(optics_params)
    dtype = setup.wavelengths_m.dtype
    anchor = jnp.zeros(2, dtype) if anchor_arcsec is None else anchor_arcsec
    return optics.psfs(setup.wavelengths_m, anchor)


def filter_psf_tangents(
    instrument: Instrument,
    setup: FilterSetup,
    optics_params: OpticsParams,
    anchor_arcsec: Float[Array, " 2"],
    windows: HoleWindows,
) -> tuple[Float[Array, "l 264 264"], Callable[[Array], Float[Array, "j l 264 264"]]]:
    """:func:`filter_psfs` and the function ``hole -> (n_zernike, n_lambda, 264, 264)``
    of their derivatives with respect to that hole's Zernike coefficients (nm), by
    :meth:`~amigo.model.optics.NRMOptics.wavefront_psf_tangents` (raw pistons: see
    there)."""
    optics = instrument.wide_optics(optics_params)
    return optics.wavefront_psf_tangents(setup.wavelengths_m, anchor_arcsec, windows)


def illuminance_from_psfs(
    instrument: Instrument,
    setup: FilterSetup,
    psfs: Float[Array, "l 264 264"],
    slope_per_um: Array,
    position_arcsec: Float[Array, " 2"],
    log_amp: Float[Array, "k k"] | None,
    phase: Float[Array, "k k"] | None,
    anchor_arcsec: Float[Array, " 2"] | None = None,
) -> Float[Array, "240 240"]:
    """Unit-flux, pixel-integrated illuminance (240, 240) on the optical frame's 3x grid,
    before the detector, from :func:`filter_psfs` and log-visibility grids: the
    visibilities injected into each wavelength's PSF, shifted to ``position_arcsec``,
    weighted by the spectrum. The fit, the ramp model and :func:`image_from_psfs` take the
    same illuminance already blurred by the jitter from :func:`jittered_illuminance`,
    which computes it in two parts; this is the plain path it is tested against."""
    config = instrument.optics.config
    pixel_arcsec = config.pixel_scale_arcsec / config.oversample
    offset = position_arcsec if anchor_arcsec is None else (position_arcsec - anchor_arcsec)
    spectrum = setup.spectrum(slope_per_um)
    image = setup.injector.broadband(
        psfs, spectrum.weights(), log_amp, phase, shift_pix=offset / pixel_arcsec
    )
    lo = FIELD_MARGIN_PIX * config.oversample
    image = image[lo : lo + instrument.psf_size, lo : lo + instrument.psf_size]
    return instrument.optics.integrate_pixels(image)


def jittered_illuminance(
    instrument: Instrument,
    setup: FilterSetup,
    psfs: Float[Array, "l 264 264"],
    slope_per_um: Array,
    position_arcsec: Float[Array, " 2"],
    log_amp: Float[Array, "k k"] | None,
    phase: Float[Array, "k k"] | None,
    anchor_arcsec: Float[Array, " 2"] | None,
    jitter_arcsec: Array,
) -> Float[Array, "240 240"]:
    """:func:`illuminance_from_psfs` blurred by the jitter (``jitter_arcsec``): the
    detector's input after :meth:`~amigo.model.detector.linear.LinearDetector.jitter`.

    The same numbers, computed in two parts. The point source's image is cropped,
    integrated over sub-pixels and blurred as before. The visibilities' part goes from
    its band of the uv plane to the blurred image in two matrix products: the inverse
    transform (:meth:`~amigo.model.visibility.Injector.band_axes`), the crop, the
    sub-pixel integration (:func:`~amigo.model.optics.propagation.integration_matrix`)
    and the jitter (:meth:`~amigo.model.detector.linear.LinearDetector.jitter_matrix`)
    all act on each axis alone, so they compose into one complex matrix per axis,
    ``L = M F E``, and the part is ``Re(L_y band L_x^T)``. Every latent column of a
    Jacobian is then two small products instead of four 2-D FFTs.
    """
    config = instrument.optics.config
    pixel_arcsec = config.pixel_scale_arcsec / config.oversample
    offset = position_arcsec if anchor_arcsec is None else (position_arcsec - anchor_arcsec)
    shift = offset / pixel_arcsec
    spectrum = setup.spectrum(slope_per_um)
    image, band = setup.injector.broadband_parts(
        psfs, spectrum.weights(), log_amp, phase, shift_pix=shift
    )
    lo, size = FIELD_MARGIN_PIX * config.oversample, instrument.psf_size
    detector = instrument.detector.with_jitter(jitter_arcsec)
    image = image[lo : lo + size, lo : lo + size]
    blurred = detector.jitter(instrument.optics.integrate_pixels(image))
    if band is None:
        return blurred
    dtype = image.dtype
    axis = detector.jitter_matrix(size, dtype) @ jnp.asarray(
        integration_matrix(size, config.pixel_integration), dtype
    )
    e_y, e_x = setup.injector.band_axes(shift, lo, size, dtype)
    # Real arithmetic: (a + ib)(c + id) as real products (XLA's are faster than complex).
    ly_re, ly_im = axis @ e_y.real, axis @ e_y.imag
    lx_re, lx_im = axis @ e_x.real, axis @ e_x.imag
    p_re = ly_re @ band.real - ly_im @ band.imag
    p_im = ly_re @ band.imag + ly_im @ band.real
    return blurred + p_re @ lx_re.T - p_im @ lx_im.T


def image_from_psfs(
    instrument: Instrument,
    setup: FilterSetup,
    psfs: Float[Array, "l 264 264"],
    slope_per_um: Array,
    exposure: ExposureParams,
    log_amp: Float[Array, "k k"] | None,
    phase: Float[Array, "k k"] | None,
    anchor_arcsec: Float[Array, " 2"] | None = None,
) -> Float[Array, "80 80"]:
    """The 80 x 80 detector image (DN/s) from :func:`filter_psfs` and log-visibility grids
    (the detector applied to :func:`illuminance_from_psfs`, computed as the fit does,
    through :func:`jittered_illuminance`)."""
    blurred = jittered_illuminance(
        instrument,
        setup,
        psfs,
        slope_per_um,
        exposure.position_arcsec,
        log_amp,
        phase,
        anchor_arcsec,
        exposure.jitter_mas / 1000.0,
    )
    return instrument.detector.after_jitter(blurred, jnp.exp(exposure.log_flux))


def image_from_log_vis(
    instrument: Instrument,
    setup: FilterSetup,
    optics_params: OpticsParams,
    slope_per_um: Array,
    exposure: ExposureParams,
    log_amp: Float[Array, "k k"] | None,
    phase: Float[Array, "k k"] | None,
) -> Float[Array, "80 80"]:
    """The 80 x 80 detector image for given log-visibility grids (see module notes), with
    the detector geometry of ``optics_params``."""
    instrument = instrument.with_geometry(optics_params.geometry)
    setup = setup.with_band_taper(optics_params.band_taper_per_um2)
    psfs = filter_psfs(instrument, setup, optics_params)
    return image_from_psfs(instrument, setup, psfs, slope_per_um, exposure, log_amp, phase)


def exposure_image(
    instrument: Instrument,
    setup: FilterSetup,
    optics_params: OpticsParams,
    source: SourceParams,
    exposure: ExposureParams,
) -> Float[Array, "80 80"]:
    """The 80 x 80 model image (DN/s) of one exposure."""
    if setup.basis is None:
        raise ValueError(f"filter setup {setup.name} has no latent basis")
    log_amp, phase = setup.basis.grids(source.amp, source.phase)
    return image_from_log_vis(
        instrument, setup, optics_params, source.slope_per_um, exposure, log_amp, phase
    )


def locate(
    data: np.ndarray,
    mask: np.ndarray,
    template: np.ndarray,
    detector: LinearDetector,
) -> tuple[np.ndarray, float]:
    """Initial position and flux of a star from its image.

    Cross-correlates the masked data with a centred model ``template`` (same shape),
    refines the integer peak with a parabola, and returns the optical-frame position
    (arcsec) and the flux scale ``sum(data) / sum(template)`` over the mask.
    """
    d = np.where(mask, data, 0.0)
    t = np.where(mask, template, 0.0)
    corr = np.real(np.fft.ifft2(np.fft.fft2(d) * np.conj(np.fft.fft2(t))))
    iy, ix = np.unravel_index(np.argmax(corr), corr.shape)

    def vertex(m1: float, c0: float, p1: float) -> float:
        denom = m1 - 2 * c0 + p1
        return 0.0 if denom == 0 else 0.5 * (m1 - p1) / denom

    n, m = corr.shape
    dy = vertex(corr[(iy - 1) % n, ix], corr[iy, ix], corr[(iy + 1) % n, ix])
    dx = vertex(corr[iy, (ix - 1) % m], corr[iy, ix], corr[iy, (ix + 1) % m])
    # Shifts beyond half the field wrap to negative offsets.
    shift_y = (iy + n // 2) % n - n // 2 + dy
    shift_x = (ix + m // 2) % m - m // 2 + dx
    position = np.asarray(detector.detector_to_optical(jnp.array([shift_x, shift_y])))
    flux = float(np.sum(d) / np.sum(t)) if np.sum(t) > 0 else 1.0
    return position, flux


def float64(tree: T) -> T:
    """Cast every floating array of a pytree to float64 (inside ``jax.enable_x64``)."""
    return cast(tree, jnp.float64)
