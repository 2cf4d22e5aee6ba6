"""The project's differentiable optical model as the simulator's illumination.

:class:`OpticalModelIllumination` renders a scene with :class:`amigo.model.optics.NRMOptics`
(sampled pupil with soft hexagonal holes, 10 Zernikes per hole, MFT, Fresnel defocus,
pixel integration) and :class:`amigo.model.detector.linear.LinearDetector` (jitter, detector
rotation and anisotropy), at a higher fidelity than the fitting model uses by default:
more wavelengths (15 instead of 9), a finer sub-pixel grid (the detector's 4x instead of
3x) and a finer pupil (512 pixels across instead of 256). Every element of the drawn
:class:`~amigo.simulation.state.InstrumentState` enters:

* ``zernike_nm`` -> ``NRMOptics.zernikes_nm`` (same convention: Noll 1..10 per hole, RMS
  nm, disc 1.2 x the hole circumradius);
* ``defocus_nm[filter]`` -> ``NRMOptics.defocus_nm`` (Noll 4 RMS nm over the pupil,
  applied as a Fresnel defocus);
* the hole centres after ``pupil_distortion`` and ``hole_shift_m`` ->
  ``Aperture.centres_m``;
* ``jitter_mas`` -> ``LinearDetector.jitter_arcsec``.

The optics runs in JAX (float64 inside a ``jax.enable_x64(True)`` context, since a
simulator's truth should not carry float32 rounding), compiled once per shape and reused
for every source and exposure.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from amigo import niriss
from amigo.simulation.scene import DetectorScene
from amigo.simulation.state import InstrumentState


@functools.cache
def _compiled_render() -> Any:
    """The jitted ``(optics, detector, spectrum, position) -> detector-grid illuminance``."""
    import equinox as eqx

    @eqx.filter_jit
    def render(optics, detector, spectrum, position_arcsec):
        return detector.illuminance(optics.illuminance(spectrum, position_arcsec))

    return render


@dataclass(frozen=True)
class OpticalModelIllumination:
    """:mod:`amigo.model.optics` at simulation fidelity (see the module doc).

    Attributes
    ----------
    n_wavelengths
        Wavelength bins across the filter.
    pupil_npix
        Pupil samples across the JWST pupil diameter.
    pixel_integration
        Sub-pixel integration scheme of :func:`amigo.model.optics.integrate_pixels`.
    """

    n_wavelengths: int = 15
    pupil_npix: int = 512
    pixel_integration: str = "fir"

    def describe(self) -> dict[str, Any]:
        return {
            "model": "amigo.model.optics",
            "description": "NRMOptics (sampled soft-edged pupil, 10 Zernikes per hole, MFT, "
            "Fresnel defocus, pixel integration) + LinearDetector (jitter; SIAF-derived "
            f"geometry {niriss.nominal_geometry()})",
            "n_wavelengths": self.n_wavelengths,
            "pupil_npix": self.pupil_npix,
            "pixel_integration": self.pixel_integration,
            "zernikes_used": list(range(1, 11)),
        }

    def render(
        self, scene: DetectorScene, filter_name: str, state: InstrumentState, oversample: int
    ) -> np.ndarray:
        import jax
        import jax.numpy as jnp

        from amigo.model.detector.linear import LinearDetector
        from amigo.model.optics import LinearSpectrum, NRMOptics, OpticsConfig
        from amigo.model.optics.aperture import Aperture

        k = int(oversample)
        n = niriss.SUBARRAY_SIZE
        with jax.enable_x64(True):
            config = OpticsConfig(
                oversample=k,
                pupil_npix=self.pupil_npix,
                pixel_integration=self.pixel_integration,
            )
            optics = NRMOptics.create(
                config,
                aperture=Aperture.nominal(centres_m=state.hole_centres_m()),
                zernikes_nm=jnp.asarray(state.zernike_nm, dtype=jnp.float64),
                defocus_nm=float(state.defocus_nm.get(filter_name, 0.0)),
                static=True,
            )
            detector = LinearDetector.create(jitter_arcsec=state.jitter_mas / 1000.0, oversample=k)
            spectrum = LinearSpectrum.from_filter(filter_name, self.n_wavelengths)
            render = _compiled_render()
            rate = np.zeros((n * k, n * k))
            centre = 0.5 * (n - 1)  # the optical grid is centred on the field centre
            for source in scene.sources:
                if source.photons_per_s == 0:
                    continue
                offset = jnp.asarray([source.x_pix - centre, source.y_pix - centre])
                position = detector.detector_to_optical(offset)
                image = render(optics, detector, spectrum, position)
                rate += source.photons_per_s * np.asarray(image, dtype=float)
        return rate
