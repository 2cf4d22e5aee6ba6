"""The ``*_calslope.fits`` product: raw ramps reduced to mean slopes and their covariance.

Layout (the public contract of docs/interfaces; ``ng`` groups, ``(ny, nx)`` = (80, 80))::

    PRIMARY    the uncal primary header + AMIGOVER, ADC_CORR (T/F), NSIGCLIP, and the
               processing record (SATLEVEL, MINSUP, CLIPSAMP, NREJRAMP, NREJSLOP, NBADPIX,
               UNCALFIL, UNCALSUM: its fingerprint, ONEOVERF: the 1/f treatment, absent
               from older files = none)
    SLOPE      float32 (ng-1, ny, nx)        mean group differences, DN per group; its
               header is the uncal SCI header (WCS and orientation keywords included)
    SLOPE_COV  float32 (ng-1, ng-1, ny, nx)  covariance of SLOPE, DN^2
    SLOPE_SUP  float32 (ng-1, ny, nx)        integrations used for each slope
    RAMP       float32 (ng, ny, nx)          mean ADC-corrected ramp, DN (bias included)
    RAMP_COV   float32 (ng, ng, ny, nx)      covariance of RAMP, DN^2
    RAMP_SUP   float32 (ng, ny, nx)          integrations used for each group
    BADPIX     uint8   (ny, nx)              1 = do not use
    BADPIX_WHY uint8   (ny, nx)              why (bit mask, see BAD_REASONS);
                                             an amigo extension beyond the contract

Undefined values (no integration kept) are NaN, and their pixels are flagged in BADPIX.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from astropy.io import fits

from amigo._version import __version__
from amigo.errors import InputError
from amigo.io.atomic import atomic_path
from amigo.io.files import damaged, fingerprint
from amigo.io.jwst import open_fits

#: Bits of the bad-pixel reason map (BADPIX_WHY); BADPIX = (BADPIX_WHY != 0).
BAD_REFERENCE: int = 1  # reference row of SUB80: no light
BAD_LOW_SUPPORT: int = 2  # some slope kept in fewer integrations than the minimum support
BAD_DQ: int = 4  # PIXELDQ has DO_NOT_USE
BAD_SATURATED: int = 8  # saturated in more than max_saturated_fraction of the integrations
BAD_NO_NOISE: int = 16  # a slope with zero or non-finite variance (dead or stuck pixel)

BAD_REASONS: dict[int, str] = {
    BAD_REFERENCE: "reference row",
    BAD_LOW_SUPPORT: "low support",
    BAD_DQ: "DQ DO_NOT_USE",
    BAD_SATURATED: "saturated",
    BAD_NO_NOISE: "no noise",
}


class SlopeArrays(Protocol):
    """What :func:`write_calslope` writes: :class:`amigo.processing.ramps.SlopeProduct` (the
    file format does not depend on how the arrays were made). Shapes as in the module
    notes."""

    # Read-only (properties), so that a frozen dataclass satisfies the protocol.
    @property
    def slope_dn(self) -> np.ndarray: ...
    @property
    def slope_cov_dn2(self) -> np.ndarray: ...
    @property
    def slope_support(self) -> np.ndarray: ...
    @property
    def ramp_dn(self) -> np.ndarray: ...
    @property
    def ramp_cov_dn2(self) -> np.ndarray: ...
    @property
    def ramp_support(self) -> np.ndarray: ...
    @property
    def badpix(self) -> np.ndarray: ...
    @property
    def badpix_reason(self) -> np.ndarray: ...

    def header_cards(self) -> Mapping[str, tuple[Any, str]]:
        """Keyword -> (value, comment) of the processing, for the primary header."""
        ...


#: Extensions every calslope file has, in order.
EXTENSIONS: tuple[str, ...] = (
    "SLOPE",
    "SLOPE_COV",
    "SLOPE_SUP",
    "RAMP",
    "RAMP_COV",
    "RAMP_SUP",
    "BADPIX",
)

#: Keywords describing an HDU's data, never copied from one file's SCI header to another.
_STRUCTURAL = {
    "XTENSION",
    "BITPIX",
    "NAXIS",
    "PCOUNT",
    "GCOUNT",
    "BSCALE",
    "BZERO",
    "BLANK",
    "EXTNAME",
    "EXTVER",
    "CHECKSUM",
    "DATASUM",
    "SIMPLE",
    "EXTEND",
}


def calslope_name(uncal_path: str | os.PathLike[str]) -> str:
    """``<stem>_calslope.fits`` for an input ``<stem>_uncal.fits`` (or ``<stem>.fits``)."""
    name = Path(uncal_path).name
    for suffix in ("_uncal.fits.gz", "_uncal.fits", ".fits.gz", ".fits", ".fit"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)] + "_calslope.fits"
    return name + "_calslope.fits"


def _data_header(header: fits.Header) -> fits.Header:
    """A copy of ``header`` without the keywords that describe the data layout."""
    out = fits.Header()
    for card in header.cards:
        key = card.keyword
        if key in _STRUCTURAL or (key.startswith("NAXIS") and key[5:].isdigit()):
            continue
        out.append(card, end=True)
    return out


@dataclass(frozen=True)
class CalSlope:
    """The content of a calslope file (shapes as in the module docstring; float64 arrays).

    Attributes
    ----------
    slope_dn, slope_cov_dn2, slope_support, ramp_dn, ramp_cov_dn2, ramp_support
        Means (DN), covariances of the means (DN^2) and integration counts.
    badpix
        (ny, nx) bool, True = do not use.
    badpix_reason
        (ny, nx) uint8 bit mask, or ``None`` for files written without it.
    primary_header, slope_header
        The PRIMARY header and the SLOPE header (the uncal SCI header).
    path
        Where it was read from (``None`` for a product built in memory).
    """

    slope_dn: np.ndarray
    slope_cov_dn2: np.ndarray
    slope_support: np.ndarray
    ramp_dn: np.ndarray
    ramp_cov_dn2: np.ndarray
    ramp_support: np.ndarray
    badpix: np.ndarray
    badpix_reason: np.ndarray | None
    primary_header: fits.Header = field(repr=False)
    slope_header: fits.Header = field(repr=False)
    path: Path | None = None

    @property
    def ngroups(self) -> int:
        return int(self.ramp_dn.shape[0])

    @property
    def adc_corrected(self) -> bool:
        return bool(self.primary_header.get("ADC_CORR", False))

    @property
    def nsigma(self) -> float:
        return float(self.primary_header["NSIGCLIP"])

    @property
    def unusable(self) -> np.ndarray:
        """(ny, nx) True where a likelihood must not use the pixel: flagged in BADPIX, or
        any of its slopes undefined."""
        return self.badpix | ~np.all(np.isfinite(self.slope_dn), axis=0)


def write_calslope(
    path: str | os.PathLike[str],
    product: SlopeArrays,
    primary_header: fits.Header,
    sci_header: fits.Header,
    *,
    uncal_name: str | None = None,
    uncal_fingerprint: str | None = None,
) -> Path:
    """Write ``product`` to ``path`` atomically; return the path.

    Parameters
    ----------
    path
        Output file (``<stem>_calslope.fits``).
    product
        The result of :func:`amigo.processing.ramps.process_ramps`.
    primary_header, sci_header
        The uncal file's PRIMARY and SCI headers (copied, never modified).
    uncal_name
        Name of the input file, recorded as UNCALFIL.
    uncal_fingerprint
        :func:`amigo.io.files.fingerprint` of the input, recorded as UNCALSUM (a re-run
        skips a file whose product records its input and settings, :func:`is_up_to_date`).
    """
    path = Path(path)
    primary = _data_header(primary_header)
    # Values that describe this file rather than the exposure: the file name and type, and
    # no stdatamodels class (a RampModel label would make stdatamodels misread it).
    primary["FILENAME"] = path.name
    primary["FILETYPE"] = "calslope"
    primary.remove("DATAMODL", ignore_missing=True)
    primary["AMIGOVER"] = (__version__, "amigo version that wrote this file")
    for key, card in product.header_cards().items():
        primary[key] = card
    if uncal_name is not None:
        primary["UNCALFIL"] = (uncal_name, "raw-ramp file processed")
    if uncal_fingerprint is not None:
        primary["UNCALSUM"] = (uncal_fingerprint, "fingerprint of that file (size, ends)")

    slope_header = _data_header(sci_header)
    slope_header["BUNIT"] = ("DN", "per group")

    def image(
        data: np.ndarray,
        name: str,
        header: fits.Header | None = None,
        bunit: str | None = None,
        dtype: type = np.float32,
    ) -> fits.ImageHDU:
        hdu = fits.ImageHDU(np.asarray(data, dtype=dtype), header=header, name=name)
        if bunit is not None:
            hdu.header["BUNIT"] = bunit
        return hdu

    reason_header = fits.Header()
    for bit, why in BAD_REASONS.items():
        reason_header[f"BIT{bit.bit_length() - 1}"] = (why, f"value {bit}")
    hdul = fits.HDUList(
        [
            fits.PrimaryHDU(header=primary),
            image(product.slope_dn, "SLOPE", slope_header),
            image(product.slope_cov_dn2, "SLOPE_COV", bunit="DN2"),
            image(product.slope_support, "SLOPE_SUP"),
            image(product.ramp_dn, "RAMP", bunit="DN"),
            image(product.ramp_cov_dn2, "RAMP_COV", bunit="DN2"),
            image(product.ramp_support, "RAMP_SUP"),
            image(product.badpix, "BADPIX", dtype=np.uint8),
            image(product.badpix_reason, "BADPIX_WHY", reason_header, dtype=np.uint8),
        ]
    )
    with atomic_path(path) as tmp:
        hdul.writeto(tmp)
    return path


def is_up_to_date(
    product_path: Path, uncal_path: Path, settings_cards: Mapping[str, tuple[Any, str]]
) -> bool:
    """Whether ``product_path`` is a complete, valid calslope file of ``uncal_path`` (same
    name and :func:`~amigo.io.files.fingerprint`) processed by this amigo version with the
    settings whose header cards are ``settings_cards``
    (:meth:`amigo.processing.ramps.ProcessSettings.header_cards`): ``amigo process`` then skips
    it (restart after an interruption)."""
    if not product_path.is_file():
        return False
    try:
        header = read_calslope(product_path).primary_header
    except InputError:
        return False  # damaged or incomplete: processed again
    expected = {
        "UNCALFIL": uncal_path.name,
        "UNCALSUM": fingerprint(uncal_path),
        "AMIGOVER": __version__,
        **{key: value for key, (value, _) in settings_cards.items()},
    }
    return all(header.get(key) == value for key, value in expected.items())


def read_calslope(path: str | os.PathLike[str]) -> CalSlope:
    """Read and validate a calslope file; raise :class:`InputError` if it is not one."""
    path = Path(path)
    with open_fits(path) as hdul, damaged(path, "calslope file"):
        missing = [name for name in EXTENSIONS if name not in hdul]
        if missing:
            raise InputError(path, f"not a calslope file: no {', '.join(missing)} extension")
        if "NSIGCLIP" not in hdul[0].header:
            raise InputError(path, "not a calslope file: no NSIGCLIP keyword")
        try:
            arrays = {name: np.array(hdul[name].data, dtype=np.float64) for name in EXTENSIONS}
        except Exception as error:
            raise InputError(path, f"data cannot be read ({error})") from None
        reason = np.array(hdul["BADPIX_WHY"].data, dtype=np.uint8) if "BADPIX_WHY" in hdul else None
        primary, slope_header = hdul[0].header.copy(), hdul["SLOPE"].header.copy()

    ramp = arrays["RAMP"]
    if ramp.ndim != 3 or ramp.shape[0] < 1:
        raise InputError(path, f"RAMP has shape {ramp.shape}, expected (ngroups >= 1, ny, nx)")
    ng, ny, nx = ramp.shape
    expected = {
        "SLOPE": (ng - 1, ny, nx),
        "SLOPE_COV": (ng - 1, ng - 1, ny, nx),
        "SLOPE_SUP": (ng - 1, ny, nx),
        "RAMP_COV": (ng, ng, ny, nx),
        "RAMP_SUP": (ng, ny, nx),
        "BADPIX": (ny, nx),
    }
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise InputError(path, f"{name} has shape {arrays[name].shape}, expected {shape}")
    for name in ("SLOPE_SUP", "RAMP_SUP"):
        counts = arrays[name]
        if not np.all(np.isfinite(counts) & (counts >= 0) & (counts == np.round(counts))):
            raise InputError(path, f"{name} holds values that are not integration counts")
    if not np.all(np.isin(arrays["BADPIX"], (0, 1))):
        raise InputError(path, "BADPIX holds values other than 0 and 1")
    return CalSlope(
        slope_dn=arrays["SLOPE"],
        slope_cov_dn2=arrays["SLOPE_COV"],
        slope_support=arrays["SLOPE_SUP"],
        ramp_dn=ramp,
        ramp_cov_dn2=arrays["RAMP_COV"],
        ramp_support=arrays["RAMP_SUP"],
        badpix=arrays["BADPIX"] != 0,
        badpix_reason=reason,
        primary_header=primary,
        slope_header=slope_header,
        path=path,
    )
