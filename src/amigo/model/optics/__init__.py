"""Differentiable optical model of NIRISS AMI (the paper's 'Optical Model').

Public API::

    from amigo.model.optics import NRMOptics, OpticsConfig, PointSource

    optics = NRMOptics.create()                       # static (fast) mask, SUB80 at 3x
    source = PointSource.create("F430M", flux=1e6)
    psfs = optics.psfs(source.spectrum.wavelengths_m, source.position_arcsec)  # (9, 240, 240)
    image_3x = optics.illuminance(source.spectrum, source.position_arcsec)    # (240, 240)

See docs/optics.md for the model, its conventions and its validation.
"""

from amigo.model.optics.aperture import (
    Aperture,
    PupilGrid,
    StaticAperture,
    n_polynomial_terms,
    polynomial_powers,
    soft_hexagon,
    zernike_basis,
)
from amigo.model.optics.model import ARCSEC_TO_RAD, NRMOptics, OpticsConfig, PointSource, cast
from amigo.model.optics.propagation import (
    box_fir_taps,
    cubic_upsample_taps,
    fresnel_defocus,
    integrate_pixels,
    mft,
    mft_symmetric,
    pixel_transfer,
)
from amigo.model.optics.spectrum import AbstractSpectrum, LinearSpectrum, SEDSpectrum, monochromatic

__all__ = [
    "ARCSEC_TO_RAD",
    "AbstractSpectrum",
    "Aperture",
    "LinearSpectrum",
    "NRMOptics",
    "OpticsConfig",
    "PointSource",
    "PupilGrid",
    "SEDSpectrum",
    "StaticAperture",
    "box_fir_taps",
    "cast",
    "cubic_upsample_taps",
    "fresnel_defocus",
    "integrate_pixels",
    "mft",
    "mft_symmetric",
    "monochromatic",
    "n_polynomial_terms",
    "pixel_transfer",
    "polynomial_powers",
    "soft_hexagon",
    "zernike_basis",
]
