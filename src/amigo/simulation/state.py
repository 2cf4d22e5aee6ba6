"""The simulator's random instrument state: the optical truth a fit has to recover.

A scenario draws ONE state from its seed and uses it for all of its exposures (a
program's science target and calibrator see the same telescope), so calibration works on
simulated data as it does on real data. Every number is written to the truth file.

Conventions
-----------
* Per-hole aberrations are Noll-ordered Zernike coefficients (Noll 1..10: 1 piston,
  2 tip (x), 3 tilt (y), 4 defocus, 5-6 astigmatism, 7-8 coma, 9-10 trefoil), as
  optical path difference in nm,
  on a disc of radius :data:`HOLE_ZERNIKE_RADIUS_M` centred on each hole (1.2 times the
  hole's circumradius, as in the AMIGO paper's aperture model). Zernikes are normalised to
  unit RMS over their disc, so a coefficient is the RMS OPD of that mode.
* Defocus is the Noll-4 coefficient (RMS OPD, nm) over the circumscribed pupil of
  diameter :data:`amigo.niriss.PUPIL_DIAMETER_M`, one value per filter (the paper
  recovers a different defocus in each filter).
* The pupil distortion is a small linear map ``D`` (dimensionless, 2x2) acting on the hole
  centres, ``c -> (I + D) c``, plus an independent shift of each hole (m).
* Jitter is the standard deviation (mas) of a Gaussian blur of the image.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from amigo import niriss

#: Number of Noll Zernike modes per hole (Noll 1..10).
N_ZERNIKES: int = 10
#: Radius (m) of the disc on which each hole's Zernikes are defined: 1.2 x the hexagon's
#: circumradius (0.80 m flat-to-flat). Source: AMIGO paper / research code aperture model.
HOLE_ZERNIKE_RADIUS_M: float = 1.2 * niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3.0)


@dataclass(frozen=True)
class StateSpread:
    """How widely the random instrument state is drawn (the scenario's ``[instrument]``).

    Attributes
    ----------
    zernike_rms_nm
        Standard deviation (nm) of every per-hole Zernike coefficient (Noll 1..10; hole 0
        piston is fixed at 0 because a global piston is unobservable).
    defocus_rms_nm
        Standard deviation (nm RMS OPD) of the per-filter defocus.
    pupil_distortion_rms
        Standard deviation of each element of the 2x2 linear pupil distortion.
    hole_shift_rms_m
        Standard deviation (m) of each hole's independent x/y shift.
    jitter_mas
        Mean Gaussian jitter (mas); the drawn value scatters by ``jitter_scatter``
        (fractional RMS) around it.
    jitter_scatter
        Fractional scatter of the jitter.
    """

    zernike_rms_nm: float = 20.0
    defocus_rms_nm: float = 30.0
    pupil_distortion_rms: float = 2.0e-3
    hole_shift_rms_m: float = 3.0e-3
    jitter_mas: float = niriss.JITTER_SIGMA_ARCSEC * 1000.0
    jitter_scatter: float = 0.1

    @classmethod
    def from_mapping(cls, values: dict[str, Any]) -> StateSpread:
        """Build from a TOML table, refusing unknown keys (``ValueError`` names them)."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown [instrument] keys {unknown}; known: {sorted(known)}")
        return cls(**{k: float(v) for k, v in values.items()})


@dataclass(frozen=True)
class InstrumentState:
    """One random realisation of the optical state.

    Attributes
    ----------
    zernike_nm
        (7, 10) per-hole Noll Zernike coefficients, RMS OPD in nm.
    defocus_nm
        Per-filter defocus, Noll-4 RMS OPD over the full pupil, nm.
    pupil_distortion
        (2, 2) linear distortion of the hole centres (dimensionless).
    hole_shift_m
        (7, 2) extra shift of each hole centre (m), in the pupil frame.
    jitter_mas
        Gaussian jitter sigma (mas).
    """

    zernike_nm: np.ndarray
    defocus_nm: dict[str, float]
    pupil_distortion: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    hole_shift_m: np.ndarray = field(default_factory=lambda: np.zeros((niriss.N_HOLES, 2)))
    jitter_mas: float = 0.0

    @classmethod
    def perfect(cls, filters: tuple[str, ...] = niriss.FILTERS) -> InstrumentState:
        """An aberration-free, undistorted, jitter-free state (for tests and null checks)."""
        return cls(
            zernike_nm=np.zeros((niriss.N_HOLES, N_ZERNIKES)),
            defocus_nm={f: 0.0 for f in filters},
        )

    def hole_centres_m(self) -> np.ndarray:
        """(7, 2) hole centres after distortion and shifts (m, pupil frame)."""
        nominal = np.asarray(niriss.HOLE_CENTRES_M)
        return nominal @ (np.eye(2) + self.pupil_distortion).T + self.hole_shift_m

    def to_json(self) -> dict[str, Any]:
        """JSON-ready description (lists of floats)."""
        return {
            "zernike_convention": "Noll 1..10 per hole, RMS OPD nm, disc radius "
            f"{HOLE_ZERNIKE_RADIUS_M:.6f} m centred on each hole",
            "zernike_nm": self.zernike_nm.tolist(),
            "defocus_convention": "Noll 4 RMS OPD nm over the circumscribed pupil "
            f"(diameter {niriss.PUPIL_DIAMETER_M} m)",
            "defocus_nm": dict(self.defocus_nm),
            "pupil_distortion": self.pupil_distortion.tolist(),
            "hole_shift_m": self.hole_shift_m.tolist(),
            "hole_centres_m": self.hole_centres_m().tolist(),
            "jitter_mas": self.jitter_mas,
        }


def draw_instrument_state(
    rng: np.random.Generator,
    spread: StateSpread,
    filters: tuple[str, ...] = niriss.FILTERS,
) -> InstrumentState:
    """Draw a random :class:`InstrumentState`.

    The draws happen in a fixed order (Zernikes, defocus per filter in the order of
    :data:`amigo.niriss.FILTERS`, distortion, shifts, jitter), so a seed always gives
    the same state whatever subset of filters a scenario uses.
    """
    zernike = rng.normal(0.0, spread.zernike_rms_nm, (niriss.N_HOLES, N_ZERNIKES))
    zernike[0, 0] = 0.0  # global piston is unobservable: pin hole 0's piston
    defocus_all = rng.normal(0.0, spread.defocus_rms_nm, len(niriss.FILTERS))
    defocus = {
        name: float(value)
        for name, value in zip(niriss.FILTERS, defocus_all, strict=True)
        if name in filters
    }
    distortion = rng.normal(0.0, spread.pupil_distortion_rms, (2, 2))
    shifts = rng.normal(0.0, spread.hole_shift_rms_m, (niriss.N_HOLES, 2))
    jitter = spread.jitter_mas * (1.0 + spread.jitter_scatter * rng.normal())
    return InstrumentState(
        zernike_nm=zernike,
        defocus_nm=defocus,
        pupil_distortion=distortion,
        hole_shift_m=shifts,
        jitter_mas=float(max(jitter, 0.0)),
    )
