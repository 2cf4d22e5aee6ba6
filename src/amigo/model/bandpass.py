"""The effective bandpass of NIRISS AMI from physics: filter x detector QE x stellar photons.

amigo propagates ``n`` wavelengths per filter (:func:`amigo.niriss.filter_bins`), each
weighted by the number of *detected photo-electrons* it contributes. Physically that
weight density is

    w(lambda) = T(lambda) * QE(lambda) * N(lambda)

with ``T`` the filter throughput, ``QE`` the detector quantum efficiency and ``N`` the
star's photon flux density (photons per unit time, area and wavelength). This module
builds ``w`` on the filter's tabulation grid, applies a calibratable width correction and
bins it exactly as :func:`amigo.niriss.filter_bins` bins the throughput alone. Pure
NumPy: the result is a fixed set of wavelengths and weights that the JAX model consumes.

Conventions
-----------
* Wavelengths in metres everywhere; temperatures in kelvin.
* **Photon counting.** Every weight counts photons (equivalently photo-electrons), never
  energy: a source given as energy flux ``F_lambda`` enters as ``N = F_lambda * lambda / (h c)``.
  "Effective wavelength" here is therefore the photon-weighted mean
  ``int lambda w dlambda / int w dlambda`` (synphot's ``Observation.effective_wavelength``,
  SVO's ``WavelengthPhot``; with a flat ``N`` it is SVO's ``WavelengthMean`` and synphot's
  ``avgwave``).
* Weights returned by :func:`effective_curve` are dimensionless, normalised to a peak of
  one; :class:`~amigo.niriss.FilterBins` weights sum to one.

What the filter curves are
--------------------------
:func:`amigo.niriss.filter_curve` reads the SVO Filter Profile Service VOTables shipped
by the ``svo_filters`` package ("JWST/NIRISS.F430M" etc.). Their metadata
(:func:`svo_parameters`) describe them as "NIRISS F430M filter", profile reference the
Universite de Montreal NIRISS filter page, ``DetectorType = 1`` (SVO's code for a photon
counter: the curve multiplies photon flux). They are **filter-only** transmissions: the
peaks are 0.75-0.92 (F480M-F380M), far above what telescope x instrument optics x QE would
give (~0.3-0.5). So the detector QE is *not* already in ``T`` and is applied here once; the OTE and NIRISS mirror
reflectivities (gold, nearly flat over 3.6-5.1 um) are left out.

Detector QE (an empirical model, see :func:`detector_qe`)
----------------------------------------------------------
No NIRISS QE table is available offline. NIRISS uses a Teledyne HgCdTe H2RG with a 5.2 um
cutoff (JDox, "NIRISS Filters"), the same ~5 um-cutoff device family as NIRCam's long-wave
detectors. We model its QE as the quadratic through the average NIRCam long-wave QE that
JDox ("NIRCam Detector Performance") tabulates: 80 % at 3 um, 90 % at 4 um, 60 % at 5 um:

    QE(lambda) = 0.90 - 0.10 x - 0.20 x^2,    x = (lambda - 4 um) / 1 um,

held at 0.80 below 3 um and clipped at zero. It peaks (0.9125) at 3.75 um and falls to half
its peak at 5.26 um, consistent with the stated 5.2 um cutoff. **Assumptions**: that the
NIRISS detector's QE has the NIRCam long-wave average *shape* (the NIRCam team's
polynomial fits of its two long-wave detectors give 0.52 and 0.71 at 5 um: individual
devices differ by ~+-10 % there, which mostly affects F480M); the quadratic between the anchors;
and the constant below 3 um (only F277W, which is uncalibrated, reaches there). Only the
shape matters: the weights are normalised, so the QE's absolute level drops out.

Stellar spectrum and the default
--------------------------------
``teff_k`` selects a blackbody photon spectrum (:func:`photon_blackbody`). No model
atmosphere grid (Phoenix etc.) is available offline; real stars differ from a blackbody by
their molecular bands (H2O, and CO near 4.6 um in cool stars, inside F480M), which the
fitted SED slope of :class:`~amigo.model.optics.LinearSpectrum` absorbs to first order, or which a
user can supply as an SED of their own. ``teff_k=None`` (the default) means a
**flat photon spectrum**, ``N = const``, because (1) it is the convention of the published
filter wavelengths (SVO ``WavelengthMean``, synphot ``avgwave``), so amigo's numbers
compare directly with the documentation; (2) it reproduces amigo's throughput-only bins, so
the paper's fitted linear SED ``1 + m (lambda - lambda_c)`` keeps its meaning as the whole
stellar colour (a Rayleigh-Jeans star has ``m ~ -3 / lambda_c ~ -0.7`` per um); and (3) any
fixed default temperature would be wrong for many AMI targets (M dwarfs to A stars).

JWST headers carry no stellar temperature or spectral type (the ``target`` block of the
JWST data-model core schema has TARGPROP, TARGNAME, TARGTYPE, TARGCAT, TARGDESC, the
coordinates, their uncertainties and the proper motion, nothing more), so amigo reads no Teff
from the header: **Teff comes from the user**.

The calibratable correction
---------------------------
``width_scale`` (``s > 0``) stretches the effective curve about its mean wavelength
``mu``: a sample ``(lambda_i, w_i)`` moves to ``(mu + s (lambda_i - mu), w_i)``, i.e.
``w_s(lambda) = w(mu + (lambda - mu) / s)`` (peak kept at one; the normalisation of the
bins removes the Jacobian ``1/s``). Because the map is affine, the weighted mean stays
exactly ``mu`` and the rms width becomes exactly ``s`` times the original, also for the
trapezoid sums used here. ``s = 1`` is no correction; fit ``s`` per filter on calibrators.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from amigo import niriss
from amigo.niriss import FilterBins

# Physical constants, SI, exact by the 2019 SI definitions (CODATA 2018).
PLANCK_J_S: float = 6.62607015e-34
SPEED_OF_LIGHT_M_S: float = 299792458.0
BOLTZMANN_J_K: float = 1.380649e-23

#: Cutoff wavelength of the NIRISS H2RG (m). Source: JDox "NIRISS Filters" ("the NIRISS
#: detector (5.2 um cutoff)"). Used only as a consistency check of :func:`detector_qe`.
NIRISS_CUTOFF_M: float = 5.2e-6

#: Anchors of the QE model, (wavelength m, QE). Source: JDox "NIRCam Detector
#: Performance", average long-wavelength-channel QE (80 % @ 3 um, 90 % @ 4 um, 60 % @ 5 um).
QE_ANCHORS: tuple[tuple[float, float], ...] = ((3.0e-6, 0.80), (4.0e-6, 0.90), (5.0e-6, 0.60))

#: Quadratic QE coefficients ``(c0, c1, c2)`` in ``x = (lambda - 4 um) / um``: the unique
#: quadratic through :data:`QE_ANCHORS`.
QE_QUADRATIC: tuple[float, float, float] = (0.90, -0.10, -0.20)

_UM = 1e-6


def _trapezoid(y: np.ndarray, x: np.ndarray) -> float:
    """Trapezoid-rule integral (``np.trapezoid`` needs NumPy 2; amigo allows 1.26)."""
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


def photon_blackbody(wavelength_m: np.ndarray, teff_k: float) -> np.ndarray:
    """Photon spectral radiance of a blackbody (photons s^-1 m^-2 sr^-1 per metre).

    Planck's law divided by the photon energy ``h c / lambda``:
    ``N(lambda) = 2 c / lambda^4 / (exp(h c / (lambda k T)) - 1)``. Any normalisation of
    it gives the same bins; this one is the physical radiance.
    """
    if not np.isfinite(teff_k) or teff_k <= 0:
        raise ValueError(f"effective temperature must be a positive number of kelvin, got {teff_k}")
    lam = np.asarray(wavelength_m, dtype=float)
    x = PLANCK_J_S * SPEED_OF_LIGHT_M_S / (lam * BOLTZMANN_J_K * float(teff_k))
    return 2.0 * SPEED_OF_LIGHT_M_S / lam**4 / np.expm1(x)


def detector_qe(wavelength_m: np.ndarray) -> np.ndarray:
    """Modelled quantum efficiency of the NIRISS detector (electrons per photon, 0-1).

    ``0.90 - 0.10 x - 0.20 x^2`` with ``x = (lambda - 4 um)/um`` for lambda >= 3 um, held at
    its 3 um value (0.80) below, clipped at zero; see the module docstring for the source
    (JDox NIRCam long-wave average) and the assumptions.
    """
    lam = np.asarray(wavelength_m, dtype=float)
    x = (np.maximum(lam, QE_ANCHORS[0][0]) - 4.0 * _UM) / _UM
    c0, c1, c2 = QE_QUADRATIC
    return np.clip(c0 + c1 * x + c2 * x**2, 0.0, None)


def effective_wavelength(wavelength_m: np.ndarray, weight: np.ndarray) -> float:
    """Weighted mean wavelength ``int lambda w / int w`` (m), trapezoid rule on the samples.

    With photon-counting weights (as everywhere in amigo) this is the photon-weighted mean
    wavelength, synphot's ``Observation.effective_wavelength``.
    """
    lam = np.asarray(wavelength_m, dtype=float)
    w = np.asarray(weight, dtype=float)
    return float(_trapezoid(lam * w, lam) / _trapezoid(w, lam))


def rms_width(wavelength_m: np.ndarray, weight: np.ndarray) -> float:
    """Weighted rms width ``sqrt(int (lambda - mean)^2 w / int w)`` (m), trapezoid rule.

    For a throughput curve alone this is synphot's ``SpectralElement.rmswidth``.
    """
    lam = np.asarray(wavelength_m, dtype=float)
    w = np.asarray(weight, dtype=float)
    mean = effective_wavelength(lam, w)
    return float(np.sqrt(_trapezoid((lam - mean) ** 2 * w, lam) / _trapezoid(w, lam)))


def pivot_wavelength(wavelength_m: np.ndarray, weight: np.ndarray) -> float:
    """Pivot wavelength ``sqrt(int lambda w / int (w / lambda))`` (m), trapezoid rule."""
    lam = np.asarray(wavelength_m, dtype=float)
    w = np.asarray(weight, dtype=float)
    return float(np.sqrt(_trapezoid(lam * w, lam) / _trapezoid(w / lam, lam)))


def effective_curve(
    filter_name: str,
    teff_k: float | None = None,
    width_scale: float = 1.0,
    *,
    include_qe: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Photon-counting effective bandpass ``T x QE x N`` of an AMI filter.

    Parameters
    ----------
    filter_name
        AMI filter (F380M, F430M, F480M; F277W with a warning).
    teff_k
        Stellar effective temperature (K) of a blackbody photon spectrum; ``None`` (default)
        is a flat photon spectrum (see the module docstring for why).
    width_scale
        Calibratable stretch ``s > 0`` of the curve about its mean wavelength: samples move
        to ``mu + s (lambda - mu)`` with unchanged weights, so the mean is conserved and
        the rms width multiplied by exactly ``s``.
    include_qe
        Multiply by :func:`detector_qe` (default). ``False`` gives the filter x source curve.

    Returns
    -------
    wavelength_m, weight
        The filter's tabulation grid (stretched when ``s != 1``), metres ascending, and
        the photon weight density there, dimensionless with a peak of one.
    """
    if not (np.isfinite(width_scale) and width_scale > 0):
        raise ValueError(f"width_scale must be a positive number, got {width_scale}")
    wavelength, weight = niriss.filter_curve(filter_name)
    weight = np.array(weight, dtype=float)
    if include_qe:
        weight = weight * detector_qe(wavelength)
    if teff_k is not None:
        sed = photon_blackbody(wavelength, teff_k)
        weight = weight * (sed / sed.max())
    weight = weight / weight.max()
    wavelength = np.array(wavelength, dtype=float)
    if width_scale != 1.0:
        mean = effective_wavelength(wavelength, weight)
        wavelength = mean + float(width_scale) * (wavelength - mean)
    return wavelength, weight


def bin_curve(name: str, wavelength_m: np.ndarray, weight: np.ndarray, n: int) -> FilterBins:
    """Bin a weight curve into ``n`` wavelengths exactly as
    :func:`~amigo.niriss.filter_bins` does (:func:`amigo.niriss.bin_curve`)."""
    return niriss.bin_curve(name, wavelength_m, weight, n)


def effective_bins(
    filter_name: str,
    n: int = 9,
    teff_k: float | None = None,
    width_scale: float = 1.0,
    *,
    include_qe: bool = True,
) -> FilterBins:
    """:func:`effective_curve` binned into ``n`` wavelengths (see :func:`bin_curve`).

    With ``teff_k=None, width_scale=1, include_qe=False`` this is
    :func:`amigo.niriss.filter_bins` (to rounding). ``central_wavelength_m`` of the
    result is the photon-weighted mean of the effective curve over its support (the wings
    below 1 % of the peak, cut as in ``filter_bins``, move it by at most 2.4e-5 relative).
    """
    name = niriss.check_filter(filter_name)
    wavelength, weight = effective_curve(name, teff_k, width_scale, include_qe=include_qe)
    return bin_curve(name, wavelength, weight, n)


def svo_parameters(filter_name: str) -> dict[str, str | float]:
    """The PARAM metadata of the shipped SVO VOTable (numbers as floats, in its units).

    Wavelength-like values are in Angstrom, as the file states (``WavelengthUnit``).
    """
    name = niriss.check_filter(filter_name)
    root = ET.fromstring(niriss.svo_votable(name))
    params: dict[str, str | float] = {}
    for element in root.iter():
        if not element.tag.endswith("PARAM"):
            continue
        value = element.get("value", "")
        if element.get("datatype") in ("float", "double"):
            params[element.get("name", "")] = float(value)
        else:
            params[element.get("name", "")] = value
    return params
