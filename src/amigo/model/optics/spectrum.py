"""Spectral model: the wavelengths propagated through the optics and their weights.

A spectrum is any equinox module with ``wavelengths_m`` (n,) and a ``weights()`` method
returning (n,) non-negative weights that sum to one. The weights are the product of the
filter's integrated throughput in each wavelength bin and the source's relative spectral
energy distribution (photons per unit wavelength) at the bin's wavelength; the total flux
is a separate parameter of the source, so the spectrum only shapes the band.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo import niriss

M_PER_UM = 1e-6


class AbstractSpectrum(eqx.Module):
    """Interface of every spectrum used by the optical model."""

    wavelengths_m: eqx.AbstractVar[Float[Array, " n"]]

    def weights(self) -> Float[Array, " n"]:
        """(n,) relative photon weights of :attr:`wavelengths_m`, summing to one."""
        raise NotImplementedError


class LinearSpectrum(AbstractSpectrum):
    """The paper's default: filter bins times a linear SED ``1 + m (lambda - lambda_c)``.

    Attributes
    ----------
    wavelengths_m
        (n,) bin wavelengths, metres (see :func:`amigo.niriss.filter_bins`).
    filter_weights
        (n,) integrated filter throughput of each bin (any normalisation).
    central_wavelength_m
        ``lambda_c``, metres: the throughput-weighted mean wavelength of the band.
    slope_per_um
        ``m``, the fractional change of the SED per micron of wavelength. The weights
        stay positive for ``|m| < 1 / (half band width in um)`` (about 7 per um for the
        medium-band filters); the model does not clip them, to keep gradients exact.
    taper_per_um2
        ``tau``, a calibratable correction of the band's shape: the weights are multiplied
        by ``exp(-tau (lambda - lambda_c)^2)`` (lambda in um). ``tau > 0`` narrows the
        effective band (its rms width by a fraction ~``0.43 tau s^2`` for a band of rms
        width ``s`` um; docs/optics.md gives the measured values), ``tau < 0`` widens it. It absorbs what the filter curve, the detector QE and the star's
        spectrum do not describe.
    """

    wavelengths_m: Float[Array, " n"]
    filter_weights: Float[Array, " n"]
    central_wavelength_m: Float[Array, ""]
    slope_per_um: Float[Array, ""]
    taper_per_um2: Float[Array, ""] | float = 0.0

    @classmethod
    def from_filter(
        cls, name: str, n_wavelengths: int = 9, slope_per_um: float = 0.0
    ) -> LinearSpectrum:
        """Spectrum for an AMI filter sampled at ``n_wavelengths`` bins (default 9)."""
        bins = niriss.filter_bins(name, n_wavelengths)
        return cls(
            wavelengths_m=jnp.asarray(bins.wavelengths_m),
            filter_weights=jnp.asarray(bins.weights),
            central_wavelength_m=jnp.asarray(bins.central_wavelength_m),
            slope_per_um=jnp.asarray(float(slope_per_um)),
        )

    def sed(self) -> Float[Array, " n"]:
        """(n,) relative SED ``1 + m (lambda - lambda_c)`` at the bin wavelengths."""
        return 1.0 + self.slope_per_um * (self.wavelengths_m - self.central_wavelength_m) / M_PER_UM

    def weights(self) -> Float[Array, " n"]:
        offset_um = (self.wavelengths_m - self.central_wavelength_m) / M_PER_UM
        w = self.filter_weights * self.sed() * jnp.exp(-self.taper_per_um2 * offset_um**2)
        return w / jnp.sum(w)


class SEDSpectrum(AbstractSpectrum):
    """Filter bins times a user-supplied differentiable SED.

    ``sed`` is any callable (an equinox module, to make its parameters fittable) mapping
    (n,) wavelengths in metres to (n,) relative photon flux densities.
    """

    wavelengths_m: Float[Array, " n"]
    filter_weights: Float[Array, " n"]
    sed: Callable[[Float[Array, " n"]], Float[Array, " n"]]

    @classmethod
    def from_filter(cls, name: str, sed: Callable, n_wavelengths: int = 9) -> SEDSpectrum:
        bins = niriss.filter_bins(name, n_wavelengths)
        return cls(jnp.asarray(bins.wavelengths_m), jnp.asarray(bins.weights), sed)

    def weights(self) -> Float[Array, " n"]:
        w = self.filter_weights * self.sed(self.wavelengths_m)
        return w / jnp.sum(w)


def monochromatic(wavelength_m: float) -> LinearSpectrum:
    """A single wavelength of unit weight (for tests and monochromatic studies)."""
    wl = np.array([float(wavelength_m)])
    return LinearSpectrum(jnp.asarray(wl), jnp.ones(1), jnp.asarray(wl[0]), jnp.asarray(0.0))
