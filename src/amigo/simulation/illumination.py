"""Illumination: the photon-rate image that falls on the detector.

An *illumination* is any object with a ``render`` method that turns a
:class:`~amigo.simulation.scene.DetectorScene` (point sources in detector pixels with their
photon rates), a filter and an :class:`~amigo.simulation.state.InstrumentState` into the
photon rate on an oversampled SUB80 grid::

    rate = illumination.render(scene, "F430M", state, oversample=4)
    rate.shape == (80 * 4, 80 * 4)       # photons / s per sub-pixel, [y, x]

and a ``describe()`` method returning a JSON-ready dict for the truth file. The detector
(:mod:`amigo.simulation.detector`) never looks inside: the optics is pluggable.

This module provides:

* :class:`AnalyticNRM`: the Fraunhofer image of the 7 hexagonal holes in closed form
  (sum over holes of the analytic Fourier transform of a hexagon times the hole's phase
  ramp), polychromatic over :func:`amigo.niriss.filter_bins`, point-sampled on a grid
  finer than the output and averaged into sub-pixels, then blurred by the Gaussian
  jitter. It includes per-hole piston (fringe phases), per-hole tip/tilt (envelope
  shifts), the defocus's effect on each hole (the piston and tilt of the pupil's
  quadratic phase at the hole), the hole-position distortion and the detector's
  rotation and anisotropy (the geometry of :mod:`amigo.model.detector.linear`). It ignores the higher-order (Noll >= 4) shape of
  the wavefront *within* each hole; an optical model that propagates a sampled pupil is
  needed for those: :mod:`amigo.simulation.optics_illumination`, the default.
* :class:`UniformIllumination`: a flat field (uniformly illuminated detector).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from amigo import niriss
from amigo.simulation.scene import DetectorScene, pixel_grid
from amigo.simulation.state import HOLE_ZERNIKE_RADIUS_M, InstrumentState

RAD_PER_ARCSEC = np.pi / (180.0 * 3600.0)


class Illumination(Protocol):
    """What the simulator needs from an optical model."""

    def render(
        self, scene: DetectorScene, filter_name: str, state: InstrumentState, oversample: int
    ) -> np.ndarray:
        """Photon rate (photons/s per sub-pixel), shape (80*oversample, 80*oversample)."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-ready description of the model and its fidelity settings."""
        ...


# --------------------------------------------------------------------------------------
# Closed-form Fraunhofer image of the mask
# --------------------------------------------------------------------------------------


def hexagon_vertices_m(flat_to_flat_m: float = niriss.HOLE_FLAT_TO_FLAT_M) -> np.ndarray:
    """(6, 2) vertices of a hole, counter-clockwise, with flat top and bottom edges.

    Flats are horizontal because vertically adjacent holes of the mask sit on segment
    centres 1.32 m (one segment flat-to-flat) apart along y.
    """
    radius = flat_to_flat_m / np.sqrt(3.0)
    angles = np.deg2rad(60.0 * np.arange(6))
    return radius * np.stack([np.cos(angles), np.sin(angles)], axis=-1)


def polygon_fourier_transform(qx: np.ndarray, qy: np.ndarray, vertices_m: np.ndarray) -> np.ndarray:
    """Fourier transform of the indicator of a convex polygon centred anywhere.

    ``F(q) = integral over the polygon of exp(-2 pi i q . r) d^2r`` evaluated in closed
    form with the divergence theorem: for ``q != 0``::

        F(q) = i / (2 pi |q|^2) * sum_edges (q . n_k) L_k exp(-2 pi i q . m_k) sinc(q . d_k)

    with ``n_k`` the outward normal, ``L_k`` the length, ``m_k`` the midpoint and ``d_k``
    the vector of edge ``k`` (``sinc(x) = sin(pi x)/(pi x)``); ``F(0)`` is the area.

    Parameters
    ----------
    qx, qy
        Spatial frequencies (cycles per metre), any broadcastable shapes.
    vertices_m
        (n, 2) vertices in counter-clockwise order (m).

    Returns
    -------
    Complex array of the broadcast shape (m^2).
    """
    qx, qy = np.broadcast_arrays(np.asarray(qx, float), np.asarray(qy, float))
    v = np.asarray(vertices_m, float)
    a, b = v, np.roll(v, -1, axis=0)
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    normal = np.stack([d[:, 1], -d[:, 0]], axis=-1) / length[:, None]  # outward for CCW
    mid = 0.5 * (a + b)
    q2 = qx**2 + qy**2
    total = np.zeros(qx.shape, complex)
    for k in range(len(v)):
        qn = qx * normal[k, 0] + qy * normal[k, 1]
        qm = qx * mid[k, 0] + qy * mid[k, 1]
        qd = qx * d[k, 0] + qy * d[k, 1]
        total += qn * length[k] * np.exp(-2j * np.pi * qm) * np.sinc(qd)
    area = 0.5 * np.abs(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))
    small = q2 * area < 1e-12  # |q| much smaller than 1/size: the series is just the area
    safe_q2 = np.where(small, 1.0, q2)
    return np.where(small, area, 1j * total / (2.0 * np.pi * safe_q2))


def _hexagon_transform_real(qx: np.ndarray, qy: np.ndarray, vertices_m: np.ndarray) -> np.ndarray:
    """:func:`polygon_fourier_transform` for a centrally symmetric hexagon (real-valued).

    Opposite edges pair up into ``(q.n) L sinc(q.d) sin(2 pi q.m) / (pi |q|^2)``: half the
    edges and no complex exponentials, which matters on ~10^6 samples per wavelength.
    """
    v = np.asarray(vertices_m, float)
    a, b = v[:3], v[1:4]
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    normal = np.stack([d[:, 1], -d[:, 0]], axis=-1) / length[:, None]
    mid = 0.5 * (a + b)
    q2 = qx**2 + qy**2
    total = np.zeros(np.broadcast(qx, qy).shape)
    for k in range(3):
        qn = qx * normal[k, 0] + qy * normal[k, 1]
        qm = qx * mid[k, 0] + qy * mid[k, 1]
        qd = qx * d[k, 0] + qy * d[k, 1]
        total += qn * length[k] * np.sinc(qd) * np.sin(2.0 * np.pi * qm)
    area = 1.5 * np.sqrt(3.0) * float(np.sum(v[0] ** 2))
    small = q2 * area < 1e-12
    return np.where(small, area, total / (np.pi * np.where(small, 1.0, q2)))


def detector_to_optical_matrix_rad() -> np.ndarray:
    """2x2 matrix mapping a detector offset (pixels, [dx, dy]) to an optical angle (rad).

    The inverse of the SIAF-derived geometry ``G`` of :mod:`amigo.model.detector.linear`
    (:func:`amigo.niriss.nominal_geometry_matrix`; NumPy, so the analytic model
    needs no JAX), times the mean pixel scale.
    """
    geometry = niriss.nominal_geometry_matrix()
    return np.linalg.inv(geometry) * niriss.PIXEL_SCALE_ARCSEC * RAD_PER_ARCSEC


def hole_phases_and_tilts(
    state: InstrumentState, filter_name: str
) -> tuple[np.ndarray, np.ndarray]:
    """Per-hole piston OPD (m) and OPD gradient (m/m, shape (7, 2)) of the state.

    From the Noll 1-3 coefficients of each hole plus the full-pupil defocus evaluated at
    the hole: ``OPD = sqrt(3) d (2 r^2 / R^2 - 1)`` has, at a hole centred on ``c``,
    piston ``sqrt(3) d (2 |c|^2/R^2 - 1)`` and gradient ``4 sqrt(3) d c / R^2``.
    """
    z = np.asarray(state.zernike_nm, float) * 1e-9
    centres = state.hole_centres_m()
    piston = z[:, 0].copy()
    # Noll 2 = 2 rho cos(theta), Noll 3 = 2 rho sin(theta): gradient 2 a / R.
    gradient = 2.0 * z[:, 1:3] / HOLE_ZERNIKE_RADIUS_M
    defocus = state.defocus_nm.get(filter_name, 0.0) * 1e-9
    radius = 0.5 * niriss.PUPIL_DIAMETER_M
    r2 = np.sum(centres**2, axis=-1)
    piston = piston + np.sqrt(3.0) * defocus * (2.0 * r2 / radius**2 - 1.0)
    gradient = gradient + 4.0 * np.sqrt(3.0) * defocus * centres / radius**2
    return piston, gradient


def nrm_intensity(
    theta_x_rad: np.ndarray,
    theta_y_rad: np.ndarray,
    wavelength_m: float,
    centres_m: np.ndarray,
    piston_m: np.ndarray,
    gradient: np.ndarray,
) -> np.ndarray:
    """Monochromatic image of the mask for a unit photon rate, per steradian.

    ``|sum_h F_hex(q - t_h / lambda) exp(2 pi i (p_h / lambda - q . c_h))|^2 /
    (lambda^2 A)`` at ``q = theta / lambda``, with ``A`` the total open area so that the
    image integrates to one over the sky (Parseval); ``p_h`` is the piston OPD and
    ``t_h`` the OPD gradient of hole ``h`` centred on ``c_h``.

    Parameters
    ----------
    theta_x_rad, theta_y_rad
        Angles in the optical (pupil-aligned) frame, radians, broadcastable.
    wavelength_m
        Wavelength (m).
    centres_m, piston_m, gradient
        (7, 2) hole centres (m), (7,) piston OPD (m), (7, 2) OPD gradient (m/m).
    """
    vertices = hexagon_vertices_m()
    total_area = len(centres_m) * 1.5 * np.sqrt(3.0) * float(np.sum(vertices[0] ** 2))
    qx = np.asarray(theta_x_rad) / wavelength_m
    qy = np.asarray(theta_y_rad) / wavelength_m
    field = np.zeros(np.broadcast(qx, qy).shape, complex)
    for h in range(len(centres_m)):
        # A tilt shifts this hole's envelope by gradient / lambda in q; the piston and
        # the hole's position set its fringe phase.
        envelope = _hexagon_transform_real(
            qx - gradient[h, 0] / wavelength_m, qy - gradient[h, 1] / wavelength_m, vertices
        )
        phase = (
            2.0
            * np.pi
            * (piston_m[h] / wavelength_m - (qx * centres_m[h, 0] + qy * centres_m[h, 1]))
        )
        field += envelope * np.exp(1j * phase)
    return np.abs(field) ** 2 / (wavelength_m**2 * total_area)


def integrate_subpixels(samples: np.ndarray, jitter_sigma: float = 0.0) -> np.ndarray:
    """Integrate a band-limited image, point-sampled at sub-pixel centres, over sub-pixels.

    The intensity of a finite pupil is band-limited, so multiplying its spectrum by the
    transfer function of the sub-pixel box (``sinc(fx) sinc(fy)``, ``f`` in cycles per
    sub-pixel) integrates it over each sub-pixel *exactly* (in units of the sample
    value times the sub-pixel area), provided the samples are above Nyquist and the
    image falls to ~0 at the array edges (callers pad). A Gaussian jitter of
    ``jitter_sigma`` sub-pixels is applied in the same product.
    """
    fy = np.fft.fftfreq(samples.shape[0])[:, None]
    fx = np.fft.rfftfreq(samples.shape[1])[None, :]
    transfer = np.sinc(fx) * np.sinc(fy)
    if jitter_sigma > 0:
        transfer = transfer * np.exp(-2.0 * (np.pi * jitter_sigma) ** 2 * (fx**2 + fy**2))
    return np.fft.irfft2(np.fft.rfft2(samples) * transfer, s=samples.shape)


@dataclass(frozen=True)
class AnalyticNRM:
    """Closed-form polychromatic image of the non-redundant mask (see the module doc).

    The image is evaluated at the sub-pixel centres of a grid extended by
    ``pad_pix`` pixels on each side, integrated over the sub-pixels exactly in Fourier
    space (:func:`integrate_subpixels`, with the jitter) and cropped to SUB80.

    Attributes
    ----------
    n_wavelengths
        Wavelength bins across the filter (:func:`amigo.niriss.filter_bins`).
    pad_pix
        Extra pixels computed around SUB80 so the Fourier-space integration does not wrap
        the PSF wings around.
    """

    n_wavelengths: int = 15
    pad_pix: int = 10

    def describe(self) -> dict[str, Any]:
        return {
            "model": "analytic-nrm",
            "description": "closed-form Fraunhofer image of 7 hexagonal holes; per-hole piston "
            "and tip/tilt and the defocus's piston/tilt at each hole; no intra-hole "
            "higher-order aberrations; exact sub-pixel integration of the band-limited image",
            "n_wavelengths": self.n_wavelengths,
            "pad_pix": self.pad_pix,
            "zernikes_used": [1, 2, 3],
        }

    def render(
        self, scene: DetectorScene, filter_name: str, state: InstrumentState, oversample: int
    ) -> np.ndarray:
        k = int(oversample)
        if k < 2:
            raise ValueError("oversample must be >= 2 to sample the image above Nyquist")
        pad = int(self.pad_pix)
        bins = niriss.filter_bins(filter_name, self.n_wavelengths)
        to_optical = detector_to_optical_matrix_rad()
        solid_angle = abs(np.linalg.det(to_optical)) / k**2  # sr per sub-pixel
        centres = state.hole_centres_m()
        piston_m, gradient = hole_phases_and_tilts(state, filter_name)
        axis = pixel_grid(k, niriss.SUBARRAY_SIZE + 2 * pad) - pad
        samples = np.zeros((axis.size, axis.size))
        for source in scene.sources:
            if source.photons_per_s == 0:
                continue
            dx = axis[None, :] - source.x_pix
            dy = axis[:, None] - source.y_pix
            theta_x = to_optical[0, 0] * dx + to_optical[0, 1] * dy
            theta_y = to_optical[1, 0] * dx + to_optical[1, 1] * dy
            for wavelength, weight in zip(bins.wavelengths_m, bins.weights, strict=True):
                intensity = nrm_intensity(theta_x, theta_y, wavelength, centres, piston_m, gradient)
                samples += (source.photons_per_s * weight * solid_angle) * intensity
        sigma_sub = state.jitter_mas / (niriss.PIXEL_SCALE_ARCSEC * 1000.0) * k
        image = integrate_subpixels(samples, sigma_sub)
        n = niriss.SUBARRAY_SIZE * k
        return image[pad * k : pad * k + n, pad * k : pad * k + n]


@dataclass(frozen=True)
class UniformIllumination:
    """A uniformly illuminated detector (flat-field exposures).

    ``render`` ignores the scene's positions and spreads the scene's total photon rate
    evenly over the 80x80 pixels.
    """

    def describe(self) -> dict[str, Any]:
        return {"model": "uniform", "description": "uniform illumination (flat field)"}

    def render(
        self, scene: DetectorScene, filter_name: str, state: InstrumentState, oversample: int
    ) -> np.ndarray:
        n = niriss.SUBARRAY_SIZE * int(oversample)
        total = sum(s.photons_per_s for s in scene.sources)
        return np.full((n, n), total / n**2)
