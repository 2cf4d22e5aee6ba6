"""Writers of simulated products: level-1b ``_uncal.fits`` (streamed) and ``_truth.json``.

The uncal file is a plain FITS file in the layout stdatamodels' ``Level1bModel`` reads
(PRIMARY with ``DATAMODL = 'Level1bModel'`` and the exposure keywords, then ``SCI`` as
``uint16`` stored as int16 with ``BZERO = 32768``, shape (nints, ngroups, 80, 80)). The
PRIMARY HDU and the SCI header are written first and the integrations are streamed
after them one by one, so memory stays bounded whatever NINTS is; the file is written
under a temporary name and renamed into place when complete.

The SCI header carries the orientation keywords (``ROLL_REF``, ``V3I_YANG``,
``VPARITY``, ``PA_APER``) and a celestial FITS WCS (``RA---TAN``/``DEC--TAN``) whose CD
matrix is :meth:`amigo.orientation.Orientation.detector_to_sky_matrix`, so the WCS and the
orientation keywords agree by construction; ``CRPIX`` is the primary star's position and
``CRVAL`` the target's coordinates. The SCI array is 4-D, so a FITS WCS reader sees four
axes: take the celestial part (``astropy.wcs.WCS(header).celestial``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.time import Time, TimeDelta

from amigo import niriss
from amigo._version import __version__
from amigo.io.atomic import atomic_path, write_text
from amigo.orientation import Orientation

DEG_PER_MAS = 1.0 / 3.6e6

#: V2/V3 of the NIS_AMI1 aperture reference point (arcsec).
#: Source: V2_REF / V3_REF of the COM 1093 level-2 SCI headers (SIAF NIS_AMI1).
V2_REF_ARCSEC: float = -296.072739
V3_REF_ARCSEC: float = -762.714999


def start_time(date_obs: str, time_obs: str) -> Time:
    """UTC start time from DATE-OBS / TIME-OBS strings."""
    return Time(f"{date_obs}T{time_obs}", format="isot", scale="utc")


def exposure_duration_s(nints: int, ngroups: int) -> float:
    """Elapsed time of an exposure: one reset frame per integration plus its groups."""
    return nints * (ngroups + 1) * niriss.FRAME_TIME_S


def primary_header(cards: dict[str, Any]) -> fits.Header:
    """A PRIMARY header from ``{keyword: value}`` or ``{keyword: (value, comment)}``."""
    header = fits.Header()
    for key, value in cards.items():
        header[key] = value
    return header


def uncal_primary_cards(
    *,
    program: int,
    observation: int,
    visit: int,
    visit_group: int,
    sequence: int,
    activity: int,
    exposure: int,
    filter_name: str,
    exp_type: str,
    pupil: str,
    target_name: str,
    catalog_name: str,
    ra_deg: float,
    dec_deg: float,
    nints: int,
    ngroups: int,
    start: Time,
    dither_pattern: str,
    dither_position: int,
    dither_total: int,
    dither_offset_arcsec: tuple[float, float],
    filename: str,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The PRIMARY keywords of a simulated NIRISS AMI level-1b file."""
    duration = exposure_duration_s(nints, ngroups)
    end = start + TimeDelta(duration, format="sec")
    mid = start + TimeDelta(0.5 * duration, format="sec")
    visit_id = f"{program:05d}{observation:03d}{visit:03d}"
    effective_int = ngroups * niriss.GROUP_TIME_S
    cards: dict[str, Any] = {
        "DATE": (start.isot[:10], "[yyyy-mm-dd] simulated file: the obs. date"),
        "ORIGIN": ("amigo", "organization responsible for creating file"),
        "FILENAME": (filename, "name of the file"),
        "FILETYPE": ("uncalibrated", "type of data in the file"),
        "DATAMODL": ("Level1bModel", "type of data model"),
        "TELESCOP": ("JWST", "telescope used to acquire the data"),
        "AMISIM": (True, "simulated by amigo (truth in _truth.json)"),
        "AMIGOVER": (__version__, "amigo version that wrote this file"),
        "PROGRAM": (f"{program:05d}", "program number"),
        "OBSERVTN": (f"{observation:03d}", "observation number"),
        "VISIT": (f"{visit:03d}", "visit number"),
        "VISITGRP": (f"{visit_group:02d}", "visit group identifier"),
        "SEQ_ID": (f"{sequence:d}", "parallel sequence identifier"),
        "ACT_ID": (f"{activity:02d}", "activity identifier"),
        "EXPOSURE": (f"{exposure:d}", "exposure request number"),
        "VISIT_ID": (visit_id, "visit identifier"),
        "OBS_ID": (
            f"V{visit_id}P0000000{visit_group:02d}{sequence:1d}{activity:02d}",
            "programmatic observation identifier",
        ),
        "TARGPROP": (target_name, "proposer's name for the target"),
        "TARGNAME": (catalog_name, "standard astronomical catalog name for target"),
        "TARG_RA": (ra_deg, "[deg] target RA at mid time of exposure"),
        "TARG_DEC": (dec_deg, "[deg] target Dec at mid time of exposure"),
        "INSTRUME": ("NIRISS", "instrument used to acquire the data"),
        "DETECTOR": ("NIS", "name of detector used to acquire the data"),
        "FILTER": (filter_name, "name of the filter element used"),
        "PUPIL": (pupil, "name of the pupil element used"),
        "EXP_TYPE": (exp_type, "type of data in the exposure"),
        "READPATT": ("NISRAPID", "readout pattern"),
        "NINTS": (nints, "number of integrations in exposure"),
        "NGROUPS": (ngroups, "number of groups in integration"),
        "NFRAMES": (1, "number of frames per group"),
        "GROUPGAP": (0, "number of frames dropped between groups"),
        "NRSTSTRT": (1, "number of resets at start of exposure"),
        "NRESETS": (1, "number of resets between integrations"),
        "ZEROFRAM": (False, "T if a zero frame was read separately"),
        "TSAMPLE": (SAMPLE_TIME_US, "[us] time between samples"),
        "TFRAME": (niriss.FRAME_TIME_S, "[s] time between frames"),
        "TGROUP": (niriss.GROUP_TIME_S, "[s] time between groups"),
        "EFFINTTM": (effective_int, "[s] effective integration time"),
        "EFFEXPTM": (nints * effective_int, "[s] effective exposure time"),
        "DURATION": (duration, "[s] total duration of exposure"),
        "DATE-OBS": (start.isot[:10], "[yyyy-mm-dd] UTC date at start of exposure"),
        "TIME-OBS": (start.isot[11:23], "[hh:mm:ss.sss] UTC time at start of exposure"),
        "EXPSTART": (start.mjd, "[d] exposure start time in MJD"),
        "EXPMID": (mid.mjd, "[d] exposure mid time in MJD"),
        "EXPEND": (end.mjd, "[d] exposure end time in MJD"),
        "INTSTART": (1, "starting integration number in this segment"),
        "INTEND": (nints, "ending integration number in this segment"),
        "SUBARRAY": (niriss.SUBARRAY, "subarray used"),
        "SUBSTRT1": (niriss.SUBARRAY_START_X, "starting pixel in axis 1 direction"),
        "SUBSTRT2": (niriss.SUBARRAY_START_Y, "starting pixel in axis 2 direction"),
        "SUBSIZE1": (niriss.SUBARRAY_SIZE, "number of pixels in axis 1 direction"),
        "SUBSIZE2": (niriss.SUBARRAY_SIZE, "number of pixels in axis 2 direction"),
        "FASTAXIS": (-2, "fast readout axis direction"),
        "SLOWAXIS": (-1, "slow readout axis direction"),
        "APERNAME": ("NIS_AMI1", "PRD science aperture used"),
        "PPS_APER": ("NIS_AMI1", "original AperName supplied by PPS"),
        "PATTTYPE": (dither_pattern if dither_total > 1 else "NONE", "primary dither pattern"),
        "NUMDTHPT": (dither_total, "total number of points in pattern"),
        "PATT_NUM": (dither_position, "position number in primary pattern"),
        "XOFFSET": (dither_offset_arcsec[0], "[arcsec] x offset from pattern start"),
        "YOFFSET": (dither_offset_arcsec[1], "[arcsec] y offset from pattern start"),
    }
    if extra:
        cards.update(extra)
    return cards


#: TSAMPLE keyword value (microseconds). Source: AMI products (TSAMPLE = 10.0).
SAMPLE_TIME_US: float = 10.0


def sci_header(
    *,
    nints: int,
    ngroups: int,
    orientation: Orientation,
    primary_xy_pix: tuple[float, float],
    ra_deg: float,
    dec_deg: float,
    reference_xy_pix: tuple[float, float],
) -> fits.Header:
    """The SCI header: uint16 4-D image, orientation keywords and a consistent TAN WCS.

    ``primary_xy_pix`` and ``reference_xy_pix`` are 0-based (x, y) pixel positions of the
    primary star and of the aperture reference point.
    """
    n = niriss.SUBARRAY_SIZE
    header = fits.Header()
    header["XTENSION"] = "IMAGE"
    header["BITPIX"] = 16
    header["NAXIS"] = 4
    header["NAXIS1"] = n
    header["NAXIS2"] = n
    header["NAXIS3"] = int(ngroups)
    header["NAXIS4"] = int(nints)
    header["PCOUNT"] = 0
    header["GCOUNT"] = 1
    header["BZERO"] = 32768
    header["BSCALE"] = 1
    header["EXTNAME"] = ("SCI", "extension name")
    header["BUNIT"] = ("DN", "physical units of the array values")
    for key, value in orientation.to_header().items():
        comment = {
            "PA_APER": "[deg] Position angle of aperture used",
            "VPARITY": "Relative sense of rotation, Ideal xy vs V2V3",
            "V3I_YANG": "[deg] Angle from V3 axis to Ideal y axis",
            "ROLL_REF": "[deg] V3 roll angle at the ref point (N over E)",
        }[key]
        header[key] = (value, comment)
    cd = orientation.detector_to_sky_matrix() * DEG_PER_MAS
    header["RADESYS"] = ("ICRS", "name of the coordinate reference frame")
    header["CRPIX1"] = (primary_xy_pix[0] + 1.0, "axis 1 coordinate of the reference pixel")
    header["CRPIX2"] = (primary_xy_pix[1] + 1.0, "axis 2 coordinate of the reference pixel")
    header["CRVAL1"] = (ra_deg, "first axis value at the reference pixel")
    header["CRVAL2"] = (dec_deg, "second axis value at the reference pixel")
    header["CTYPE1"] = ("RA---TAN", "first axis coordinate type")
    header["CTYPE2"] = ("DEC--TAN", "second axis coordinate type")
    header["CUNIT1"] = ("deg", "first axis units")
    header["CUNIT2"] = ("deg", "second axis units")
    header["CD1_1"] = (cd[0, 0], "linear transformation matrix element")
    header["CD1_2"] = (cd[0, 1], "linear transformation matrix element")
    header["CD2_1"] = (cd[1, 0], "linear transformation matrix element")
    header["CD2_2"] = (cd[1, 1], "linear transformation matrix element")
    # Sky position of the aperture reference point (the tangent-plane offset from the
    # primary, small enough for the linear form).
    dx = reference_xy_pix[0] - primary_xy_pix[0]
    dy = reference_xy_pix[1] - primary_xy_pix[1]
    dra_mas, ddec_mas = orientation.detector_to_sky(dx, dy)
    header["RA_REF"] = (
        ra_deg + float(dra_mas) * DEG_PER_MAS / math.cos(math.radians(dec_deg)),
        "[deg] Right ascension of the reference point",
    )
    header["DEC_REF"] = (
        dec_deg + float(ddec_mas) * DEG_PER_MAS,
        "[deg] Declination of the reference point",
    )
    header["V2_REF"] = (V2_REF_ARCSEC, "[arcsec] Telescope V2 coord of reference point")
    header["V3_REF"] = (V3_REF_ARCSEC, "[arcsec] Telescope V3 coord of reference point")
    return header


class UncalWriter:
    """Stream integrations into a level-1b uncal file (atomically renamed when complete).

    Use as a context manager::

        with UncalWriter(path, primary, sci) as writer:
            for ramp in ramps:              # (ngroups, 80, 80) uint16 each
                writer.write(ramp)

    The file appears under ``path`` only if every integration declared in the SCI header
    was written and no exception escaped the block.
    """

    def __init__(
        self, path: str | os.PathLike[str], primary: fits.Header, sci: fits.Header
    ) -> None:
        self.path = Path(path)
        self.primary = primary
        self.sci = sci
        self.nints = int(sci["NAXIS4"])
        self.shape = (int(sci["NAXIS3"]), int(sci["NAXIS2"]), int(sci["NAXIS1"]))
        self.written = 0
        self._stack = contextlib.ExitStack()
        self._stream: fits.StreamingHDU | None = None

    def __enter__(self) -> UncalWriter:
        tmp = self._stack.enter_context(atomic_path(self.path))
        fits.PrimaryHDU(header=self.primary).writeto(tmp)
        # A str, not a Path: astropy's StreamingHDU reduces a Path to its bare name.
        self._stream = fits.StreamingHDU(os.fspath(tmp), self.sci)
        return self

    def write(self, ramp: np.ndarray) -> None:
        """Append one integration, (ngroups, ny, nx) ``uint16``."""
        if self._stream is None:
            raise RuntimeError("UncalWriter.write outside its with-block")
        if ramp.shape != self.shape or ramp.dtype != np.uint16:
            raise ValueError(
                f"integration must be uint16 {self.shape}, got {ramp.dtype} {ramp.shape}"
            )
        if self.written >= self.nints:
            raise ValueError(f"all {self.nints} integrations are already written")
        # uint16 -> int16 with BZERO = 32768: flipping the top bit subtracts 32768.
        self._stream.write((ramp ^ np.uint16(0x8000)).view(np.int16).astype(">i2"))
        self.written += 1

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        if exc_type is None and self.written != self.nints:
            error = ValueError(f"only {self.written} of {self.nints} integrations were written")
            self._stack.__exit__(type(error), error, None)
            raise error
        self._stack.__exit__(exc_type, exc, tb)


def write_truth(path: str | os.PathLike[str], truth: dict[str, Any]) -> None:
    """Write the truth dictionary as indented JSON (atomically)."""
    write_text(path, json.dumps(truth, indent=1, allow_nan=False) + "\n")
