"""Scenes on the sky and their placement on the SUB80 detector.

A :class:`Target` is a primary star plus any number of point companions
(:class:`SkyCompanion`) given on the sky (separation in mas, position angle in degrees
east of north, delta-magnitude per filter). :func:`detector_scene` places them on the
detector through :class:`amigo.orientation.Orientation`, the same orientation whose
keywords are written into the simulated file, so the file's own header (and its FITS
WCS) maps every source back to its sky position.

Pixel coordinates are 0-based NumPy indices of SUB80 with pixel ``(y, x)`` centred on
the integer coordinates ``(y, x)``; arrays are indexed ``[y, x]``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from amigo import niriss
from amigo.orientation import Orientation, offset_from_separation_pa

#: Aperture reference pixel of NIS_AMI1 in SUB80, 0-based (x, y): the FITS keywords of
#: real AMI products put CRPIX1/2 = (46, 41) (1-based) there.
#: Source: SCI headers of the COM 1093 level-2 files.
REFERENCE_PIXEL_XY: tuple[float, float] = (45.0, 40.0)

#: Named sub-pixel dither patterns: offsets (dx, dy) in pixels added to the pointing.
#: "5-POINT-SUBPIXEL" samples the pixel phase in both axes (corners of a half-pixel square
#: and its centre); it is this package's choice, standing in for the pattern of CAL 4481.
DITHER_PATTERNS: dict[str, tuple[tuple[float, float], ...]] = {
    "NONE": ((0.0, 0.0),),
    "5-POINT-SUBPIXEL": ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5), (0.25, 0.25)),
}


@dataclass(frozen=True)
class SkyCompanion:
    """A point companion on the sky.

    Attributes
    ----------
    sep_mas
        Separation from the primary (mas).
    pa_deg
        Position angle, degrees east of north (the files' FITS WCS convention).
    dmag
        Magnitude difference to the primary, per filter name.
    """

    sep_mas: float
    pa_deg: float
    dmag: Mapping[str, float]

    def flux_ratio(self, filter_name: str) -> float:
        """Companion / primary flux ratio in a filter (``KeyError`` if not given)."""
        return float(10.0 ** (-0.4 * self.dmag[filter_name]))

    def offset_mas(self) -> tuple[float, float]:
        """Sky offset ``(dRA east, dDec north)`` in mas."""
        dra, ddec = offset_from_separation_pa(self.sep_mas, self.pa_deg)
        return float(dra), float(ddec)


@dataclass(frozen=True)
class Target:
    """A primary star (and companions) as written in the file headers.

    Attributes
    ----------
    name
        Proposer's name (keyword ``TARGPROP``), e.g. ``"AB-DOR"``.
    catalog_name
        Catalogue name (keyword ``TARGNAME``).
    ra_deg, dec_deg
        Position of the primary (keywords ``TARG_RA``, ``TARG_DEC``).
    companions
        Point companions.
    """

    name: str
    catalog_name: str
    ra_deg: float
    dec_deg: float
    companions: tuple[SkyCompanion, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class DetectorSource:
    """A point source on the detector.

    Attributes
    ----------
    x_pix, y_pix
        Position (0-based SUB80 pixel coordinates, pixel centres on integers).
    photons_per_s
        Detected photon rate of the source summed over the whole focal plane (not only
        SUB80), photons/s.
    """

    x_pix: float
    y_pix: float
    photons_per_s: float


@dataclass(frozen=True)
class DetectorScene:
    """The sources of one exposure in detector coordinates (what an illumination renders)."""

    sources: tuple[DetectorSource, ...]

    def scaled(self, factor: float) -> DetectorScene:
        """The same scene with every photon rate multiplied by ``factor``."""
        return DetectorScene(
            tuple(DetectorSource(s.x_pix, s.y_pix, s.photons_per_s * factor) for s in self.sources)
        )


def detector_scene(
    target: Target,
    filter_name: str,
    orientation: Orientation,
    primary_xy_pix: tuple[float, float],
    primary_photons_per_s: float = 1.0,
) -> DetectorScene:
    """Place a target's primary and companions on the detector.

    Parameters
    ----------
    target
        The primary and its companions.
    filter_name
        Selects each companion's delta-magnitude.
    orientation
        Sky orientation of the exposure (the one written to the file).
    primary_xy_pix
        Detector position (x, y) of the primary, 0-based pixels.
    primary_photons_per_s
        Photon rate of the primary; companions get ``primary * 10**(-0.4 dmag)``.
    """
    x0, y0 = primary_xy_pix
    sources = [DetectorSource(float(x0), float(y0), float(primary_photons_per_s))]
    for companion in target.companions:
        dra, ddec = companion.offset_mas()
        dx, dy = orientation.sky_to_detector(dra, ddec)
        sources.append(
            DetectorSource(
                float(x0 + dx),
                float(y0 + dy),
                float(primary_photons_per_s * companion.flux_ratio(filter_name)),
            )
        )
    return DetectorScene(tuple(sources))


def dither_offsets(pattern: str | Sequence[Sequence[float]]) -> tuple[tuple[float, float], ...]:
    """Resolve a dither pattern: a name of :data:`DITHER_PATTERNS` or explicit (dx, dy) list."""
    if isinstance(pattern, str):
        key = pattern.strip().upper()
        if key not in DITHER_PATTERNS:
            raise ValueError(
                f"unknown dither pattern {pattern!r}; known: {sorted(DITHER_PATTERNS)}"
            )
        return DITHER_PATTERNS[key]
    offsets = tuple((float(p[0]), float(p[1])) for p in pattern)
    if not offsets or any(len(p) != 2 for p in pattern):
        raise ValueError("an explicit dither pattern is a non-empty list of [dx, dy] pairs")
    return offsets


def inside_subarray(x_pix: float, y_pix: float, margin_pix: float = 0.0) -> bool:
    """Whether a position lies on SUB80 (at least ``margin_pix`` from its edges)."""
    n = niriss.SUBARRAY_SIZE
    lo, hi = -0.5 + margin_pix, n - 0.5 - margin_pix
    return bool(lo <= x_pix <= hi and lo <= y_pix <= hi)


def pixel_grid(oversample: int, n_pix: int = niriss.SUBARRAY_SIZE) -> np.ndarray:
    """Centres (pixels) of the ``n_pix * oversample`` sub-pixels along one axis.

    Pixel ``i`` spans ``[i - 0.5, i + 0.5]``; its sub-pixels are ``1/oversample`` wide.
    """
    k = int(oversample)
    return (np.arange(n_pix * k) + 0.5) / k - 0.5
