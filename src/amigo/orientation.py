"""Sky orientation of NIRISS AMI exposures: detector offsets <-> sky offsets.

This module decides every position angle amigo reports. The convention is the one of the
files' own FITS WCS (see docs/orientation.md)::

            N (+dDec)                      detector +y points at PA = PA_APER
            ^                              (east of north); detector +x points at
            |                              PA_APER + 90 * VPARITY = PA_APER - 90 for
    E  <----+                              NIRISS (VPARITY = -1).
  (+dRA)

The mapping is linear and exact to first order in the offset (offsets of an AMI field are
< 3 arcsec): a detector offset ``(dx, dy)`` in pixels is first mapped to the ideal frame
with the NIS_AMI1 linear distortion (per-axis scales and a small skew,
:data:`amigo.niriss.SCI_TO_IDEAL_ARCSEC_PER_PIX`), then rotated onto the sky::

    [dRA, dDec] = R(PA_APER, VPARITY) @ M_sci->ideal @ [dx, dy]

with ``R``'s columns the sky directions (east, north components) of ideal ``+x`` and
``+y``. ``PA_APER`` is taken from the header when present, else ``ROLL_REF + V3I_YANG``
(the identity JWST uses to write it).

The functions take and return NumPy arrays; :meth:`Orientation.sky_to_detector_matrix`
gives the 2x2 matrix for code that needs to apply the mapping inside JAX.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from amigo import niriss

MAS_PER_ARCSEC = 1000.0


@dataclass(frozen=True)
class Orientation:
    """Orientation of one exposure on the sky.

    Attributes
    ----------
    pa_aper_deg
        Position angle (deg, east of north) of the ideal ``+y`` axis at the aperture
        reference point (keyword ``PA_APER``).
    vparity
        Parity of the ideal frame (keyword ``VPARITY``; -1 for NIRISS).
    v3_idl_y_angle_deg
        Angle from V3 to ideal ``+y`` (keyword ``V3I_YANG``).
    roll_ref_deg
        Position angle of V3 at the reference point (keyword ``ROLL_REF``), or ``None``.
    """

    pa_aper_deg: float
    vparity: int = niriss.VIDL_PARITY
    v3_idl_y_angle_deg: float = niriss.V3_IDL_Y_ANGLE_DEG
    roll_ref_deg: float | None = None

    @classmethod
    def from_roll(
        cls,
        roll_ref_deg: float,
        v3_idl_y_angle_deg: float | None = None,
        vparity: int | None = None,
    ) -> Orientation:
        """Orientation from the V3 roll angle, as JWST computes ``PA_APER``."""
        yang = niriss.V3_IDL_Y_ANGLE_DEG if v3_idl_y_angle_deg is None else v3_idl_y_angle_deg
        parity = niriss.VIDL_PARITY if vparity is None else int(vparity)
        return cls(
            pa_aper_deg=float((roll_ref_deg + yang) % 360.0),
            vparity=parity,
            v3_idl_y_angle_deg=float(yang),
            roll_ref_deg=float(roll_ref_deg),
        )

    @classmethod
    def from_header(cls, *headers: Mapping[str, Any]) -> Orientation:
        """Read the orientation keywords from one or more FITS headers (first found wins).

        Raises ``KeyError`` naming the keywords when neither ``PA_APER`` nor ``ROLL_REF``
        is present.
        """

        def get(key: str) -> Any:
            for header in headers:
                if key in header and header[key] is not None:
                    return header[key]
            return None

        parity = get("VPARITY")
        yang = get("V3I_YANG")
        roll = get("ROLL_REF")
        pa = get("PA_APER")
        if pa is not None:
            return cls(
                pa_aper_deg=float(pa) % 360.0,
                vparity=niriss.VIDL_PARITY if parity is None else int(parity),
                v3_idl_y_angle_deg=niriss.V3_IDL_Y_ANGLE_DEG if yang is None else float(yang),
                roll_ref_deg=None if roll is None else float(roll),
            )
        if roll is None:
            raise KeyError("neither PA_APER nor ROLL_REF is present")
        return cls.from_roll(float(roll), None if yang is None else float(yang), parity)

    def to_header(self) -> dict[str, float | int]:
        """The keywords that reproduce this orientation (for files amigo writes)."""
        cards: dict[str, float | int] = {
            "PA_APER": self.pa_aper_deg,
            "VPARITY": self.vparity,
            "V3I_YANG": self.v3_idl_y_angle_deg,
        }
        cards["ROLL_REF"] = (
            self.roll_ref_deg
            if self.roll_ref_deg is not None
            else (self.pa_aper_deg - self.v3_idl_y_angle_deg) % 360.0
        )
        return cards

    # ---------------------------------------------------------------- matrices
    def ideal_to_sky_matrix(self) -> np.ndarray:
        """2x2 matrix mapping ideal-frame offsets to ``(dRA east, dDec north)``, same units."""
        pa_y = np.deg2rad(self.pa_aper_deg)
        pa_x = pa_y + np.deg2rad(90.0 * self.vparity)
        # Columns: (east, north) components of the unit vectors of ideal +x and +y.
        return np.array([[np.sin(pa_x), np.sin(pa_y)], [np.cos(pa_x), np.cos(pa_y)]])

    def detector_to_sky_matrix(self) -> np.ndarray:
        """2x2 matrix: detector offset (pixels, ``[dx, dy]``) -> sky offset (mas)."""
        return (
            self.ideal_to_sky_matrix()
            @ np.asarray(niriss.SCI_TO_IDEAL_ARCSEC_PER_PIX)
            * MAS_PER_ARCSEC
        )

    def sky_to_detector_matrix(self) -> np.ndarray:
        """2x2 matrix: sky offset (mas, ``[dRA, dDec]``) -> detector offset (pixels)."""
        return np.linalg.inv(self.detector_to_sky_matrix())

    # ---------------------------------------------------------------- mappings
    def detector_to_sky(self, dx_pix: Any, dy_pix: Any) -> tuple[np.ndarray, np.ndarray]:
        """Detector offset (pixels along x, y) -> sky offset ``(dRA, dDec)`` in mas."""
        out = self.detector_to_sky_matrix() @ np.stack(np.broadcast_arrays(dx_pix, dy_pix))
        return out[0], out[1]

    def sky_to_detector(self, dra_mas: Any, ddec_mas: Any) -> tuple[np.ndarray, np.ndarray]:
        """Sky offset ``(dRA east, dDec north)`` in mas -> detector offset in pixels."""
        out = self.sky_to_detector_matrix() @ np.stack(np.broadcast_arrays(dra_mas, ddec_mas))
        return out[0], out[1]

    def sky_to_detector_arcsec(self, dra_mas: Any, ddec_mas: Any) -> tuple[np.ndarray, np.ndarray]:
        """Sky offset (mas) -> detector offset in arcsec along detector x and y.

        "Arcsec along x" is pixels times the SIAF x scale (likewise for y).
        """
        dx, dy = self.sky_to_detector(dra_mas, ddec_mas)
        return dx * niriss.PIXEL_SCALE_X_ARCSEC, dy * niriss.PIXEL_SCALE_Y_ARCSEC

    def detector_arcsec_to_sky(
        self, dx_arcsec: Any, dy_arcsec: Any
    ) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`sky_to_detector_arcsec`."""
        return self.detector_to_sky(
            np.asarray(dx_arcsec) / niriss.PIXEL_SCALE_X_ARCSEC,
            np.asarray(dy_arcsec) / niriss.PIXEL_SCALE_Y_ARCSEC,
        )

    def pa_of_detector_y_deg(self) -> float:
        """Position angle (deg east of north, 0..360) of detector ``+y``."""
        dra, ddec = self.detector_to_sky(0.0, 1.0)
        return float(np.rad2deg(np.arctan2(dra, ddec)) % 360.0)


def separation_pa(dra_mas: Any, ddec_mas: Any) -> tuple[np.ndarray, np.ndarray]:
    """Sky offset -> (separation in mas, position angle in deg east of north, 0..360)."""
    dra = np.asarray(dra_mas, dtype=float)
    ddec = np.asarray(ddec_mas, dtype=float)
    return np.hypot(dra, ddec), np.rad2deg(np.arctan2(dra, ddec)) % 360.0


def offset_from_separation_pa(sep_mas: Any, pa_deg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(separation mas, PA deg east of north) -> sky offset ``(dRA east, dDec north)`` mas."""
    sep = np.asarray(sep_mas, dtype=float)
    pa = np.deg2rad(np.asarray(pa_deg, dtype=float))
    return sep * np.sin(pa), sep * np.cos(pa)
