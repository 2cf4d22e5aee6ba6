"""Readers of JWST NIRISS AMI exposures: raw ramps (level 1b) and STScI level 2.

One entry point per need:

* :func:`read_header` opens a file, identifies it and validates everything a reader needs
  without loading the pixels: it returns :class:`ExposureMeta` or raises
  :class:`~amigo.errors.InputError` naming the file and the problem.
* :func:`read_exposure` returns an :class:`Exposure`: metadata plus data, errors, DQ and a
  ``usable`` mask in which the 4 reference rows of SUB80, DQ ``DO_NOT_USE`` pixels and
  non-finite values are False. Arrays always keep the full 80x80 SUB80 shape (the forward
  model predicts all 80x80 pixels); reference rows are *flagged*, never trimmed, so that
  pixel indices mean the same thing in every product.
* :func:`iter_ramps` streams the integrations of a raw-ramp file in chunks (memory bounded
  whatever NINTS is), for :mod:`amigo.processing.ramps`.

Kinds: ``uncal`` (SCI uint16, (nints, ngroups, ny, nx)), ``rateints`` / ``calints``
(SCI float DN/s, (nints, ny, nx)), ``rate`` / ``cal`` (SCI float DN/s, (ny, nx)).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits

from amigo import niriss
from amigo.errors import InputError
from amigo.io.files import damaged, is_number, require_file
from amigo.orientation import Orientation

#: DQ bit flags used by amigo. Source: JWST pipeline DQ definitions (jwst-formats-and-stack).
DQ_DO_NOT_USE = 1
DQ_SATURATED = 2
DQ_JUMP_DET = 4
DQ_REFERENCE_PIXEL = 2**31

RAMP_KINDS = ("uncal",)
IMAGE_KINDS = ("cal", "rate")
CUBE_KINDS = ("calints", "rateints")
KINDS = RAMP_KINDS + IMAGE_KINDS + CUBE_KINDS

#: Exposure types of flat-field (lamp) exposures: accepted with any pupil, because they
#: calibrate the pixels (flat field, non-linearity), not the optics.
FLAT_EXP_TYPES = ("NIS_LAMP", "NIS_FLAT")

#: Keywords every AMI exposure must carry (primary header).
REQUIRED_KEYWORDS = ("INSTRUME", "FILTER", "PUPIL", "EXP_TYPE", "SUBARRAY", "NGROUPS", "NINTS")

_SUFFIX = re.compile(r"_(uncal|rateints|calints|rate|cal)\.fits(\.gz)?$", re.IGNORECASE)
#: The products of one exposure: JWST's levels and amigo's calslope, or a bare FITS name
#: (``calslope_name`` makes ``foo_calslope.fits`` of ``foo.fits``).
_PRODUCT_SUFFIX = re.compile(
    r"(_(uncal|rateints|calints|rate|cal|calslope))?\.fits?(\.gz)?$", re.IGNORECASE
)


def exposure_stem(name: str) -> str:
    """The exposure a product's file name belongs to: its base name without the product
    suffix, in lower case (``jw..._nis`` for ``jw..._nis_cal.fits``,
    ``JW..._NIS_CAL.FITS`` and ``jw..._nis_calslope.fits``; ``foo`` for ``foo.fits``)."""
    return _PRODUCT_SUFFIX.sub("", os.path.basename(name.strip())).lower()


class AmiWarning(UserWarning):
    """The file is usable but unusual (e.g. EXP_TYPE NIS_IMAGE with the NRM pupil)."""


@dataclass(frozen=True)
class ExposureMeta:
    """Validated metadata of one exposure.

    Attributes
    ----------
    path
        The file.
    kind
        One of :data:`KINDS`.
    target
        Target as proposed (``TARGPROP``), else ``TARGNAME``, else ``"UNKNOWN"``.
    filter, pupil, exp_type, subarray
        Instrument configuration (``FILTER`` is an AMI filter, ``PUPIL`` is ``NRM``).
    ngroups, nints, nframes
        Read-out pattern.
    group_time_s, frame_time_s
        ``TGROUP`` and ``TFRAME`` (s).
    program, observation, visit, exposure
        JWST identifiers as strings (``"01093"``, ``"012"``, ...), empty when absent.
    date_obs
        ``DATE-OBS`` and ``TIME-OBS`` joined, empty when absent.
    orientation
        Sky orientation from the orientation keywords.
    bunit
        Unit of SCI (``"DN"`` for ramps, ``"DN/s"`` for level 2).
    primary_header, sci_header
        The headers as read (copies), to carry over into products.
    notes
        Warnings raised while validating (also emitted as :class:`AmiWarning`).
    """

    path: Path
    kind: str
    target: str
    filter: str
    pupil: str
    exp_type: str
    subarray: str
    ngroups: int
    nints: int
    nframes: int
    group_time_s: float
    frame_time_s: float
    program: str
    observation: str
    visit: str
    exposure: str
    date_obs: str
    orientation: Orientation
    bunit: str
    primary_header: fits.Header = field(repr=False)
    sci_header: fits.Header = field(repr=False)
    sci_shape: tuple[int, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def stem(self) -> str:
        """File name without its product suffix (``jw..._nis`` for ``jw..._nis_uncal.fits``)."""
        return _SUFFIX.sub("", self.path.name) if _SUFFIX.search(self.path.name) else self.path.stem

    @property
    def is_ramp(self) -> bool:
        return self.kind in RAMP_KINDS

    @property
    def _unit(self) -> str:
        """BUNIT as the unit tests compare it: upper case, without spaces."""
        return self.bunit.strip().upper().replace(" ", "")

    @property
    def in_dn_per_s(self) -> bool:
        """Whether BUNIT is a count rate in DN/s (level-2 images before the pipeline's
        photometric calibration; :func:`read_exposure` undoes that calibration, MJy/sr,
        with the file's PHOTMJSR)."""
        return self._unit in ("DN/S", "DNS-1", "DN.S**-1")

    @property
    def in_mjy_per_sr(self) -> bool:
        """Whether BUNIT is a surface brightness in MJy/sr (the pipeline's photom step)."""
        return self._unit in ("MJY/SR", "MJYSR-1", "MJY.SR**-1")

    @property
    def slope_time_s(self) -> float:
        """Seconds of photon collection a slope fit uses, all integrations together.

        ``NINTS * (NGROUPS - 1) * TGROUP``: a slope (the pipeline's or amigo's group
        differences) measures the charge between the first and the last group read, so the
        photons that arrived before the first read are not in it. ``EFFEXPTM`` counts
        ``NGROUPS * TGROUP`` per integration and over-counts by ``NGROUPS / (NGROUPS - 1)``
        (twice at two groups). With one group the read itself is the measurement
        (``NINTS * TGROUP``).
        """
        return self.photon_time_s(first_group=False)

    def photon_time_s(self, first_group: bool = False) -> float:
        """Seconds of photon collection a fit uses: :attr:`slope_time_s`, or with the
        first group in the likelihood (a known superbias, :mod:`amigo.model.detector.reset`)
        every group time, ``NINTS * NGROUPS * TGROUP`` (the first read comes one group
        time after the reset)."""
        used = self.ngroups if first_group or self.ngroups < 2 else self.ngroups - 1
        return float(self.nints * used * self.group_time_s)

    @property
    def dark_reference(self) -> str:
        """The dark reference file the pipeline subtracted (``R_DARK`` without its
        ``crds://`` prefix; empty when the header names none, e.g. raw ramps, or says the
        dark step did not run: ``S_DARK`` other than COMPLETE)."""
        step = str(self.primary_header.get("S_DARK", "COMPLETE")).strip().upper()
        if step != "COMPLETE":
            return ""
        return str(self.primary_header.get("R_DARK", "")).strip().removeprefix("crds://")

    @property
    def flat_reference(self) -> str:
        """The flat-field reference file the pipeline divided by (``R_FLAT`` without its
        ``crds://`` prefix; empty where the header names none or says the flat-field step
        did not run: ``S_FLAT`` other than COMPLETE)."""
        if str(self.primary_header.get("S_FLAT", "")).strip().upper() != "COMPLETE":
            return ""
        return str(self.primary_header.get("R_FLAT", "")).strip().removeprefix("crds://")

    @property
    def charge_migration_flagged(self) -> bool:
        """Whether the pipeline's charge-migration step ran on this level-2 image
        (``S_CHGMIG = 'COMPLETE'``): groups above its threshold were left out of the ramp
        fit (:func:`amigo.model.detector.pipeline_slope.charge_loss_groups`)."""
        step = str(self.primary_header.get("S_CHGMIG", "")).strip().upper()
        return self.kind in LEVEL2_KINDS and step == "COMPLETE"

    @property
    def is_flat(self) -> bool:
        """A flat-field (lamp) exposure, used only to calibrate per-pixel response."""
        return self.exp_type in FLAT_EXP_TYPES


@dataclass(frozen=True)
class Exposure:
    """An exposure's pixels and metadata.

    Attributes
    ----------
    meta
        :class:`ExposureMeta`.
    data
        ``uncal``: (nints, ngroups, 80, 80) float64 raw counts in DN (BZERO applied).
        ``rateints``/``calints``: (nints, 80, 80) float64 DN/s. ``rate``/``cal``: (80, 80).
        A level-2 file in MJy/sr is divided by its PHOTMJSR here (``meta.bunit`` then says
        DN/s; ``meta.sci_header`` keeps the file's BUNIT and PHOTMJSR as written).
    err
        1-sigma errors of ``data`` (level 2 only), same shape, or ``None``.
    dq
        uint32 DQ flags broadcastable to ``data`` (level 2 DQ, or uncal PIXELDQ), or ``None``.
    usable
        bool, shape of ``data`` without the ramp axes for uncal ((80, 80)) and the shape of
        ``data`` for level 2: False on reference rows, DO_NOT_USE pixels and non-finite
        values (and non-positive errors).
    var_poisson
        Level 2 with ``meta.charge_migration_flagged``: the VAR_POISSON extension ((DN/s)^2,
        shape of ``data``), the variance of the photons the pipeline's ramp fit counted;
        ``None`` otherwise or where absent.
    """

    meta: ExposureMeta
    data: np.ndarray
    err: np.ndarray | None
    dq: np.ndarray | None
    usable: np.ndarray
    var_poisson: np.ndarray | None = None


# ------------------------------------------------------------------------------ helpers
def open_fits(path: str | os.PathLike[str]) -> fits.HDUList:
    """Open a FITS file, turning every failure into one InputError.

    Checks that the path is a regular file, that it starts like a FITS file, that every
    HDU parses (astropy reads a damaged header into a placeholder HDU, or fails later on
    a card it cannot parse), that the HDUs follow each other (a negative or absurd size
    keyword can send astropy's reader back to an earlier HDU, for ever: at most
    :data:`MAX_HDUS` are read), and that the file is as long as its headers say (a
    truncated download). Used by every FITS reader of amigo.
    """
    path = require_file(path, "FITS file")
    try:
        with open(path, "rb") as handle:
            start = handle.read(30)
    except OSError as error:
        raise InputError(path, f"cannot be read ({error.strerror or error})") from None
    if not start.startswith(b"SIMPLE  ="):
        raise InputError(path, "not a FITS file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hdul = fits.open(path, memmap=False, lazy_load_hdus=True)
    except Exception as error:  # astropy raises several types for damaged files
        raise InputError(path, f"cannot be read as FITS ({error})") from None
    try:
        _read_structure(path, hdul)
        _check_complete(path, hdul)
    except BaseException:
        hdul.close()
        raise
    return hdul


#: Most HDUs a FITS file amigo reads may have (JWST products have about ten).
MAX_HDUS = 64
#: The HDU classes amigo can read; astropy uses others for headers it could not parse.
_READABLE_HDUS = (fits.PrimaryHDU, fits.ImageHDU, fits.BinTableHDU, fits.TableHDU)


def _read_structure(path: Path, hdul: fits.HDUList) -> None:
    """Load the HDUs one by one (see :func:`open_fits`), parsing every header card."""
    previous = -1
    for index in range(MAX_HDUS + 1):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                hdu = hdul[index]
                location = hdul.fileinfo(index)["hdrLoc"] if hasattr(hdu, "fileinfo") else None
        except IndexError:
            return  # every HDU read
        except Exception as error:
            raise InputError(path, f"HDU {index} cannot be read ({error})") from None
        if index == MAX_HDUS:
            raise InputError(path, f"has more than {MAX_HDUS} HDUs: not an AMI product")
        if not isinstance(hdu, _READABLE_HDUS):
            raise InputError(path, f"HDU {index} is damaged: its header cannot be parsed")
        if location is None or location <= previous:
            raise InputError(path, f"HDU {index} overlaps the one before: damaged sizes")
        previous = location
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for card in hdu.header.cards:
                    card.value  # noqa: B018 -- parsing is the check
        except Exception as error:
            raise InputError(path, f"HDU {index} has an unreadable header card ({error})") from None


def _check_complete(path: Path, hdul: fits.HDUList) -> None:
    """Raise if the file is shorter than its headers say (a truncated download)."""
    size = path.stat().st_size
    for index in range(len(hdul)):
        info = hdul.fileinfo(index)
        if info is None:
            continue
        end = info["datLoc"] + info["datSpan"]
        if end > size:
            name = hdul[index].name or f"HDU {index}"
            raise InputError(
                path, f"truncated file: {name} needs {end} bytes but the file has {size}"
            )


def _get(headers: tuple[fits.Header, ...], key: str) -> Any:
    for header in headers:
        if key in header and header[key] is not None and header[key] != "":
            return header[key]
    return None


def _count(path: Path, headers: tuple[fits.Header, ...], key: str, default: int | None) -> int:
    """Keyword ``key`` as a positive integer (``default`` when absent; ``None``: required)."""
    value = _get(headers, key)
    if value is None:
        if default is None:
            raise InputError(path, f"missing required keyword {key}")
        return default
    if not is_number(value) or not math.isfinite(value) or value != int(value) or value < 1:
        raise InputError(path, f"{key} is {value!r}: expected a positive integer")
    return int(value)


def _positive_seconds(path: Path, headers: tuple[fits.Header, ...], key: str) -> float | None:
    """Keyword ``key`` as a positive finite time (s), ``None`` when absent."""
    value = _get(headers, key)
    if value is None:
        return None
    if not is_number(value) or not math.isfinite(value) or value <= 0:
        raise InputError(path, f"{key} is {value!r}: expected a positive time in seconds")
    return float(value)


def _check_orientation_keywords(path: Path, headers: tuple[fits.Header, ...]) -> None:
    """The angles finite numbers and VPARITY +1 or -1, where present: the values
    :meth:`~amigo.orientation.Orientation.from_header` reads from ``headers`` (the first
    header holding a keyword wins, as there)."""

    def first(key: str) -> Any:
        return next((h[key] for h in headers if key in h and h[key] is not None), None)

    for key in ("PA_APER", "ROLL_REF", "V3I_YANG"):
        value = first(key)
        if value is not None and (not is_number(value) or not math.isfinite(value)):
            raise InputError(path, f"{key} is {value!r}: expected an angle in degrees")
    parity = first("VPARITY")
    if parity is not None and (not is_number(parity) or parity not in (1, -1)):
        raise InputError(path, f"VPARITY is {parity!r}: expected +1 or -1")


def _array_like(
    path: Path, hdu: fits.ImageHDU, name: str, shape: tuple[int, ...], dtype: type = np.float64
) -> np.ndarray:
    """The data of extension ``name`` as ``dtype``, of the SCI ``shape`` (a per-pixel map
    of a cube's frame shape also serves); :class:`InputError` otherwise."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # casting NaN or negatives: judged by the caller
            array: np.ndarray = np.array(hdu.data, dtype=dtype)
    except Exception as error:
        raise InputError(path, f"{name} data cannot be read ({error})") from None
    if array.shape != tuple(shape) and array.shape != tuple(shape[-2:]):
        raise InputError(path, f"{name} has shape {array.shape}, SCI has {tuple(shape)}")
    return array


def _optional_array(
    path: Path, hdul: fits.HDUList, name: str, shape: tuple[int, ...]
) -> np.ndarray | None:
    """Extension ``name`` of exactly the SCI ``shape``, or ``None`` where it is absent,
    unreadable or of another shape: information a fit can do without (a damaged one is
    not a reason to refuse the file)."""
    hdu = _ext(hdul, name)
    if hdu is None:
        return None
    try:
        array = _array_like(path, hdu, name, shape)
    except InputError:
        return None
    return array if array.shape == tuple(shape) else None


def _ext(hdul: fits.HDUList, name: str) -> fits.ImageHDU | None:
    try:
        return hdul[name]
    except KeyError:
        return None


def _kind(path: Path, hdul: fits.HDUList, sci: fits.ImageHDU) -> str:
    naxis = sci.header.get("NAXIS", 0)
    integer = sci.header.get("BITPIX", -32) > 0
    match = _SUFFIX.search(path.name)
    suffix = match.group(1).lower() if match else None
    if naxis == 4:
        if not integer:
            raise InputError(path, "SCI is 4-D but not integer: not a raw (uncal) ramp")
        return "uncal"
    if naxis == 3:
        return suffix if suffix in CUBE_KINDS else "calints"
    if naxis == 2:
        return suffix if suffix in IMAGE_KINDS else "cal"
    raise InputError(path, f"SCI has {naxis} dimensions: expected 4 (uncal), 3 or 2 (level 2)")


# ------------------------------------------------------------------------------ public API
def read_header(path: str | os.PathLike[str], *, need_slopes: bool = False) -> ExposureMeta:
    """Identify and validate a NIRISS AMI exposure without reading its pixels.

    Parameters
    ----------
    path
        A JWST uncal, rate(ints) or cal(ints) file.
    need_slopes
        Also require at least two groups (slopes need two reads).

    Raises
    ------
    InputError
        Not a FITS file, truncated, not NIRISS, PUPIL not NRM, unsupported subarray,
        missing keywords, wrong dimensionality, one group when slopes are needed.
    """
    path = Path(path)
    hdul = open_fits(path)
    try:
        with damaged(path, "JWST exposure"):
            return _validate(path, hdul, need_slopes=need_slopes)
    finally:
        hdul.close()


def _validate(path: Path, hdul: fits.HDUList, *, need_slopes: bool) -> ExposureMeta:
    primary = hdul[0].header
    sci = _ext(hdul, "SCI")
    if sci is None:
        if _ext(hdul, "OI_VIS2") is not None or _ext(hdul, "OI_T3") is not None:
            raise InputError(path, "is an OIFITS file, not a JWST exposure")
        raise InputError(path, "has no SCI extension: not a JWST exposure")
    return meta_from_headers(
        path,
        primary,
        sci.header,
        kind=lambda: _kind(path, hdul, sci),
        need_slopes=need_slopes,
    )


def meta_from_headers(
    path: Path,
    primary: fits.Header,
    sci_header: fits.Header,
    *,
    kind: str | Callable[[], str],
    need_slopes: bool = False,
) -> ExposureMeta:
    """Validate an exposure's PRIMARY and SCI headers into :class:`ExposureMeta`.

    ``kind`` is the product kind, or a function deciding it (called after the instrument
    checks, so that a foreign file is reported as such first). Used by
    :func:`read_header` and for amigo's own products that carry the uncal headers
    (calslope).
    """
    headers = (primary, sci_header)

    telescope = _get(headers, "TELESCOP")
    if telescope is not None and str(telescope).strip().upper() != "JWST":
        raise InputError(path, f"TELESCOP is {telescope!r}, expected 'JWST'")
    instrument_name = _get(headers, "INSTRUME")
    if instrument_name is None:
        raise InputError(path, "missing required keyword INSTRUME")
    if str(instrument_name).strip().upper() != "NIRISS":
        raise InputError(path, f"INSTRUME is {instrument_name!r}, expected 'NIRISS'")
    missing = [key for key in REQUIRED_KEYWORDS if _get(headers, key) is None]
    if missing:
        raise InputError(path, f"missing required keyword(s) {', '.join(missing)}")

    pupil = str(_get(headers, "PUPIL")).strip().upper()
    exp_type = str(_get(headers, "EXP_TYPE")).strip().upper()
    notes: list[str] = []
    if exp_type in FLAT_EXP_TYPES:
        notes.append(f"flat-field exposure ({exp_type}, PUPIL {pupil!r})")
    elif pupil != "NRM":
        raise InputError(path, f"PUPIL is {pupil!r}, expected 'NRM' (not an AMI exposure)")
    elif exp_type != "NIS_AMI":
        if exp_type in ("NIS_IMAGE", "NIS_TACQ", "NIS_TACONFIRM", "NIS_FOCUS"):
            notes.append(f"EXP_TYPE is {exp_type!r} with PUPIL 'NRM': treated as AMI")
        else:
            raise InputError(path, f"EXP_TYPE is {exp_type!r}: not an AMI exposure")

    subarray = str(_get(headers, "SUBARRAY")).strip().upper()
    if subarray != niriss.SUBARRAY:
        raise InputError(path, f"SUBARRAY is {subarray!r}: only SUB80 is supported")

    try:
        filter_name = niriss.check_filter(str(_get(headers, "FILTER")))
    except ValueError as error:
        raise InputError(path, str(error)) from None
    if filter_name not in niriss.CALIBRATED_FILTERS:
        notes.append(f"{filter_name} is not calibrated (the paper and the base model exclude it)")

    kind = kind() if callable(kind) else kind
    shape = tuple(int(sci_header[f"NAXIS{i}"]) for i in range(sci_header["NAXIS"], 0, -1))
    if shape[-2:] != (niriss.SUBARRAY_SIZE, niriss.SUBARRAY_SIZE):
        raise InputError(path, f"SCI frames are {shape[-2]}x{shape[-1]}, expected 80x80 (SUB80)")

    ngroups = _count(path, headers, "NGROUPS", None)
    nints = _count(path, headers, "NINTS", None)
    nframes = _count(path, headers, "NFRAMES", 1)
    if kind == "uncal":
        if shape[0] != nints or shape[1] != ngroups:
            raise InputError(
                path,
                f"SCI has {shape[0]} integrations x {shape[1]} groups but the header says "
                f"NINTS={nints}, NGROUPS={ngroups}",
            )
        if need_slopes and ngroups < 2:
            raise InputError(path, "has one group per integration: slopes need at least 2")
    elif kind in CUBE_KINDS and shape[0] < 1:
        raise InputError(path, "SCI has no integrations")

    _check_orientation_keywords(path, (sci_header, primary))
    try:
        orientation = Orientation.from_header(sci_header, primary)
    except KeyError:
        raise InputError(path, "missing orientation keywords (PA_APER or ROLL_REF)") from None

    group_time = _positive_seconds(path, headers, "TGROUP")
    frame_time = _positive_seconds(path, headers, "TFRAME")
    if group_time is None:
        if kind == "uncal":
            raise InputError(path, "missing required keyword TGROUP")
        group_time = niriss.GROUP_TIME_S
    target = _get(headers, "TARGPROP") or _get(headers, "TARGNAME") or "UNKNOWN"
    date = " ".join(str(v) for v in (_get(headers, "DATE-OBS"), _get(headers, "TIME-OBS")) if v)
    bunit = str(sci_header.get("BUNIT", "DN" if kind == "uncal" else "DN/s"))

    for note in notes:
        warnings.warn(f"{path.name}: {note}", AmiWarning, stacklevel=3)
    return ExposureMeta(
        path=path,
        kind=kind,
        target=str(target).strip(),
        filter=filter_name,
        pupil=pupil,
        exp_type=exp_type,
        subarray=subarray,
        ngroups=ngroups,
        nints=nints,
        nframes=nframes,
        group_time_s=float(group_time),
        frame_time_s=float(frame_time) if frame_time is not None else float(group_time),
        program=str(_get(headers, "PROGRAM") or ""),
        observation=str(_get(headers, "OBSERVTN") or ""),
        visit=str(_get(headers, "VISIT") or ""),
        exposure=str(_get(headers, "EXPOSURE") or ""),
        date_obs=date,
        orientation=orientation,
        bunit=bunit,
        primary_header=primary.copy(),
        sci_header=sci_header.copy(),
        sci_shape=shape,
        notes=tuple(notes),
    )


#: Kinds of the STScI pipeline's level-2 images (its ramp fits), as :func:`read_header`
#: names them.
LEVEL2_KINDS = ("cal", "calints", "rateints", "rate")


def data_kind(path: str | os.PathLike[str]) -> str:
    """``"calslope"``, ``"uncal"`` or a level-2 kind (:data:`LEVEL2_KINDS`), from the
    headers only; :class:`~amigo.errors.InputError` for a file that is none of them."""
    path = Path(path)
    if path.name.lower().endswith("_calslope.fits"):
        return "calslope"
    with open_fits(path) as hdul:
        if "SLOPE" in hdul:
            return "calslope"
        with damaged(path, "JWST exposure"):
            return _validate(path, hdul, need_slopes=False).kind


def is_level2(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a level-2 image (:func:`data_kind`)."""
    return data_kind(path) in LEVEL2_KINDS


def read_exposure(path: str | os.PathLike[str], *, need_slopes: bool = False) -> Exposure:
    """Read a whole exposure (see :class:`Exposure` for shapes and units).

    For large raw-ramp files prefer :func:`iter_ramps`, which streams integrations.
    """
    path = Path(path)
    hdul = open_fits(path)
    try:
        with damaged(path, "JWST exposure"):
            return _read_exposure(path, hdul, need_slopes)
    finally:
        hdul.close()


def _read_exposure(path: Path, hdul: fits.HDUList, need_slopes: bool) -> Exposure:
    """The body of :func:`read_exposure` (the file is open; the caller closes it)."""
    meta = _validate(path, hdul, need_slopes=need_slopes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            data = np.array(hdul["SCI"].data, dtype=np.float64)
        except Exception as error:
            raise InputError(path, f"SCI data cannot be read ({error})") from None
    frame_shape = data.shape[-2:]
    usable = ~niriss.reference_row_mask(*frame_shape)
    if meta.kind == "uncal":
        dq_hdu = _ext(hdul, "PIXELDQ")
        dq = None if dq_hdu is None else np.asarray(dq_hdu.data, dtype=np.uint32)
        if dq is not None:
            usable &= (dq & DQ_DO_NOT_USE) == 0
        return Exposure(meta=meta, data=data, err=None, dq=dq, usable=usable)

    err_hdu, dq_hdu = _ext(hdul, "ERR"), _ext(hdul, "DQ")
    err = None if err_hdu is None else _array_like(path, err_hdu, "ERR", data.shape)
    # Read only where it is used (pixels.pipeline_groups): a cube's worth of memory.
    var_poisson = None
    if meta.charge_migration_flagged:
        var_poisson = _optional_array(path, hdul, "VAR_POISSON", data.shape)
    dq = None if dq_hdu is None else _array_like(path, dq_hdu, "DQ", data.shape, np.uint32)
    flagged = np.zeros(data.shape, dtype=bool)
    if dq is not None:
        flagged |= np.broadcast_to((dq & DQ_DO_NOT_USE) != 0, data.shape)
    nonfinite = ~np.isfinite(data)
    bad_nonfinite = nonfinite & ~flagged & ~niriss.reference_row_mask(*frame_shape)
    if bad_nonfinite.any():
        raise InputError(
            path,
            f"SCI has {int(bad_nonfinite.sum())} NaN/inf values in pixels not flagged DO_NOT_USE",
        )
    usable = np.broadcast_to(usable, data.shape) & ~flagged & ~nonfinite
    if err is not None:
        usable &= np.isfinite(err) & (err > 0)
    if meta.in_mjy_per_sr:
        # The photom step multiplied SCI and ERR by PHOTMJSR ((MJy/sr) per (DN/s), its
        # time-dependence correction included); dividing by it gives the count rate back.
        factor = photometric_conversion(path, meta)
        data = data / factor
        err = None if err is None else err / factor
        var_poisson = None if var_poisson is None else var_poisson / factor**2
        meta = dataclasses.replace(meta, bunit="DN/s")
    return Exposure(meta, data, err, dq, usable, var_poisson)


def photometric_conversion(path: Path, meta: ExposureMeta) -> float:
    """PHOTMJSR of a level-2 image in MJy/sr (SCI header, else primary): the factor the
    pipeline's photom step multiplied the count rates by; :class:`InputError` when the
    file has none or it is not a positive number."""
    for header in (meta.sci_header, meta.primary_header):
        value = header.get("PHOTMJSR")
        if value is None:
            continue
        if not is_number(value) or not math.isfinite(float(value)) or float(value) <= 0:
            raise InputError(path, f"PHOTMJSR is {value!r}: expected a positive number")
        return float(value)
    raise InputError(
        path,
        f"BUNIT is {meta.bunit!r} but PHOTMJSR is missing: the count rates cannot be recovered",
    )


def iter_ramps(
    path: str | os.PathLike[str], chunk: int = 256, *, with_dq: bool = False
) -> Iterator[Any]:
    """Stream the integrations of a raw-ramp (uncal) file.

    Parameters
    ----------
    path
        An uncal file (one group per integration is allowed: its reads are the ramps).
    chunk
        Number of integrations per yielded array.
    with_dq
        Also yield the GROUPDQ chunk (uint8/uint32, same shape) or ``None`` when the file
        has none (level-1b files from STScI carry none; RampModel files do).

    Yields
    ------
    ramps
        float64 (n, ngroups, 80, 80) raw counts in DN with BZERO applied, ``n <= chunk``;
        or ``(ramps, groupdq)`` when ``with_dq``.
    """
    path = Path(path)
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    hdul = open_fits(path)
    try:
        meta = _validate(path, hdul, need_slopes=False)
        if meta.kind != "uncal":
            raise InputError(path, f"is a {meta.kind} product, not raw ramps (uncal)")
        sci = hdul["SCI"]
        gdq = _ext(hdul, "GROUPDQ") if with_dq else None
        for start in range(0, meta.nints, chunk):
            stop = min(start + chunk, meta.nints)
            try:
                block = np.asarray(sci.section[start:stop], dtype=np.float64)
            except Exception as error:
                raise InputError(path, f"SCI data cannot be read ({error})") from None
            if with_dq:
                dq_block = None if gdq is None else np.asarray(gdq.section[start:stop])
                yield block, dq_block
            else:
                yield block
    finally:
        hdul.close()


def read_pixel_dq(path: str | os.PathLike[str]) -> np.ndarray | None:
    """The PIXELDQ (80, 80) uint32 flags of a ramp file, or ``None`` when it has none."""
    hdul = open_fits(Path(path))
    try:
        hdu = _ext(hdul, "PIXELDQ")
        return None if hdu is None else np.asarray(hdu.data, dtype=np.uint32)
    finally:
        hdul.close()
