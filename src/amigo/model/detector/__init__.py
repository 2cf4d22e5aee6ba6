"""Detector models: linear geometry (:mod:`amigo.model.detector.linear`), the non-linear ramp
(brighter-fatter) model (:mod:`amigo.model.detector.ramp`) and the read-out (:mod:`amigo.model.detector.read`)."""

from amigo.model.detector.linear import (
    GEOMETRY_NAMES,
    LinearDetector,
    bin_pixels,
    cubic_resample,
    displacement_reach,
    fourier_gaussian_blur,
    geometry_matrix,
    sky_to_optical_matrix,
)

__all__ = [
    "GEOMETRY_NAMES",
    "LinearDetector",
    "bin_pixels",
    "cubic_resample",
    "displacement_reach",
    "fourier_gaussian_blur",
    "geometry_matrix",
    "sky_to_optical_matrix",
]
