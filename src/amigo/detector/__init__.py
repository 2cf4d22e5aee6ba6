"""Detector models: the linear detector geometry (:mod:`amigo.detector.linear`)."""

from amigo.detector.linear import (
    LinearDetector,
    bin_pixels,
    cubic_resample,
    displacement_reach,
    gaussian_blur,
    geometry_matrix,
    sky_to_optical_matrix,
)

__all__ = [
    "LinearDetector",
    "bin_pixels",
    "cubic_resample",
    "displacement_reach",
    "gaussian_blur",
    "geometry_matrix",
    "sky_to_optical_matrix",
]
