"""Calibrated observables of one target in one filter: ``<TARGPROP>_<FILTER>_calvis.fits``.

A calvis file is self-contained: from it alone a reader can evaluate the likelihood of any
sky brightness model. It holds

* the observables ``y`` (DISCOs: calibrated kernel amplitudes and phases rotated into the
  eigenbasis of their covariance) with 1-sigma errors; they are statistically independent,
  so the likelihood is a product of 1-D normals;
* the linear map ``D`` (``n_obs x 2 n_uv``) from the log complex visibility at ``n_uv``
  listed uv points to the observables::

      y_model = D @ concatenate([log|V(b_1..n_uv)|, arg V(b_1..n_uv)])    # (n_obs,)

  (log-amplitudes first, then phases in radians);
* the uv points ``b`` (metres) in the *calvis uv frame*: the pupil frame of
  :mod:`amigo.niriss` (axes along detector x and y); a point source at angular offset
  ``theta = (theta_x, theta_y)`` (radians, in that frame) has ``V(b) = exp(-2 pi i b.theta
  / lambda)``;
* the filter's wavelengths and weights (the visibility of a scene is the weighted sum of its
  monochromatic complex visibilities, see docs/detect.md);
* the 2x2 matrix ``S`` mapping a sky offset ``(dRA east, dDec north)`` in mas to the angular
  offset in the uv frame (mas along pupil x, y): ``theta_uv = S @ [dRA, dDec]``. The fitter
  computes it from the orientation keywords and the detector rotation/anisotropy; readers
  only apply it;
* the orientation keywords (``PA_APER``, ``VPARITY``, ``V3I_YANG``, ``ROLL_REF``), the
  number of photons used (``NPHOT``), the science and calibrator file names, ``AMIGOVER``.

The exact extension list is documented in docs/formats.md and is part of the public
contract: extend it, never change it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits

from amigo._version import __version__
from amigo.errors import InputError
from amigo.io.atomic import atomic_path
from amigo.io.files import damaged, require_file
from amigo.io.jwst import open_fits
from amigo.orientation import Orientation

#: Value of the ``CONTENT`` keyword that identifies a calvis file.
CONTENT = "AMIGO_CALVIS"
#: Revision of the calvis layout (``CALVREV``); bumped only by backward-compatible extensions.
FORMAT_REVISION = 1
#: The kinds of observable, as written in the ``KIND`` column.
KINDS: tuple[str, ...] = ("amplitude", "phase")


def calvis_filename(target: str, filter_name: str) -> str:
    """The standard file name ``<TARGPROP>_<FILTER>_calvis.fits`` (spaces become '-')."""
    return f"{target.strip().replace(' ', '-')}_{filter_name.strip().upper()}_calvis.fits"


def nominal_sky_to_uv(orientation: Orientation) -> np.ndarray:
    """Sky-to-uv matrix of an ideal detector (no rotation or anisotropy relative to the optics).

    Maps ``(dRA, dDec)`` in mas to the offset in mas along detector x and y (pixels times
    the per-axis SIAF scales), which is the calvis uv frame when the optical image is not
    rotated on the pixel grid. The fitter should compose it with its fitted detector
    rotation/anisotropy; tests use it to build realistic files.
    """
    return np.column_stack(
        [np.array(orientation.sky_to_detector_arcsec(*unit)) * 1000.0 for unit in ((1, 0), (0, 1))]
    )


@dataclass(frozen=True)
class CalVis:
    """Calibrated observables of one target in one filter (all arrays float64).

    Attributes
    ----------
    values, errors
        (n_obs,) observables and their 1-sigma errors (independent).
    kinds
        (n_obs,) each ``"amplitude"`` or ``"phase"``: from which part of the log
        visibility the observable was built (one error scale is fitted per kind).
    disco_matrix
        (n_obs, 2 n_uv) map from ``[log|V|, arg V]`` (radians) at ``uv_m`` to observables.
    uv_m
        (n_uv, 2) uv points (m) in the calvis uv frame (pupil x, y).
    wavelengths_m, weights
        (n_wl,) the filter's wavelengths (m) and weights (summing to one).
    sky_to_uv
        (2, 2) matrix: ``[dRA, dDec]`` (mas) -> uv-frame offset (mas).
    orientation
        Orientation keywords of the science exposures.
    n_photons
        Number of photons used for the science observables (for the photon rule of thumb).
    target, filter_name
        ``TARGPROP`` and filter.
    science_files, calibrator_files
        Names of the input files the observables came from.
    header
        Extra primary-header cards (read back as written).
    """

    values: np.ndarray
    errors: np.ndarray
    kinds: tuple[str, ...]
    disco_matrix: np.ndarray
    uv_m: np.ndarray
    wavelengths_m: np.ndarray
    weights: np.ndarray
    sky_to_uv: np.ndarray
    orientation: Orientation
    n_photons: float
    target: str
    filter_name: str
    science_files: tuple[str, ...] = ()
    calibrator_files: tuple[str, ...] = ()
    header: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n_obs(self) -> int:
        return int(self.values.shape[0])

    @property
    def n_uv(self) -> int:
        return int(self.uv_m.shape[0])

    def validate(self, path: str | os.PathLike[str] | None = None) -> None:
        """Raise :class:`InputError` naming ``path`` if the arrays are inconsistent."""
        _validate(self, path)

    def write(self, path: str | os.PathLike[str]) -> Path:
        """Write atomically to ``path``; returns the path."""
        self.validate(path)
        hdul = _to_hdulist(self)
        with atomic_path(path) as tmp:
            hdul.writeto(tmp)
        return Path(path)


def write_calvis(
    path: str | os.PathLike[str],
    *,
    values: Any,
    errors: Any,
    kinds: Sequence[str],
    disco_matrix: Any,
    uv_m: Any,
    wavelengths_m: Any,
    weights: Any,
    sky_to_uv: Any,
    orientation: Orientation | Mapping[str, Any],
    n_photons: float,
    target: str,
    filter_name: str,
    science_files: Sequence[str] = (),
    calibrator_files: Sequence[str] = (),
    header: Mapping[str, Any] | None = None,
) -> Path:
    """Write a calvis file from plain arrays (the fitter's entry point).

    All arguments are as in :class:`CalVis`; ``orientation`` may be an
    :class:`~amigo.orientation.Orientation` or a header-like mapping with ``PA_APER`` /
    ``ROLL_REF``. Raises ``ValueError`` on inconsistent arrays (a programming error in the
    caller, not a user's bad file).
    """
    if not isinstance(orientation, Orientation):
        orientation = Orientation.from_header(orientation)
    calvis = CalVis(
        values=np.asarray(values, dtype=float),
        errors=np.asarray(errors, dtype=float),
        kinds=tuple(str(k) for k in kinds),
        disco_matrix=np.asarray(disco_matrix, dtype=float),
        uv_m=np.asarray(uv_m, dtype=float),
        wavelengths_m=np.asarray(wavelengths_m, dtype=float),
        weights=np.asarray(weights, dtype=float),
        sky_to_uv=np.asarray(sky_to_uv, dtype=float),
        orientation=orientation,
        n_photons=float(n_photons),
        target=str(target),
        filter_name=str(filter_name).strip().upper(),
        science_files=tuple(os.path.basename(str(f)) for f in science_files),
        calibrator_files=tuple(os.path.basename(str(f)) for f in calibrator_files),
        header=dict(header or {}),
    )
    try:
        calvis.validate()
    except InputError as error:
        raise ValueError(error.problem) from None
    return calvis.write(path)


def is_calvis(path: str | os.PathLike[str]) -> bool:
    """True if ``path`` is a FITS file whose primary header says it is a calvis file."""
    try:  # open_fits refuses a FIFO, a directory... without opening it
        with open_fits(path) as hdul:
            return str(hdul[0].header.get("CONTENT", "")).strip().upper() == CONTENT
    except InputError:
        return False


def read_calvis(path: str | os.PathLike[str]) -> CalVis:
    """Read and validate a calvis file; raise :class:`InputError` if it is unusable."""
    path = os.fspath(require_file(path, "calvis file"))
    with open_fits(path) as hdul, damaged(path, "calvis file"):
        primary = hdul[0].header
        if str(primary.get("CONTENT", "")).strip().upper() != CONTENT:
            raise InputError(path, f"is not a calvis file (CONTENT is not {CONTENT!r})")
        for name in ("DISCO", "DISCO_MATRIX", "UV", "WAVELENGTH", "SKY_TO_UV"):
            if name not in hdul:
                raise InputError(path, f"calvis file lacks the {name} extension")
        try:
            disco = hdul["DISCO"].data
            values = np.asarray(disco["VALUE"], dtype=float)
            errors = np.asarray(disco["ERROR"], dtype=float)
            kinds = tuple(str(k).strip().lower() for k in disco["KIND"])
            matrix = np.asarray(hdul["DISCO_MATRIX"].data, dtype=float)
            uv = hdul["UV"].data
            uv_m = np.column_stack([np.asarray(uv["U"], float), np.asarray(uv["V"], float)])
            wl = hdul["WAVELENGTH"].data
            wavelengths = np.asarray(wl["WAVELENGTH"], dtype=float)
            weights = np.asarray(wl["WEIGHT"], dtype=float)
            sky_to_uv = np.asarray(hdul["SKY_TO_UV"].data, dtype=float)
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(path, f"malformed calvis extension ({error})") from None
        try:
            orientation = Orientation.from_header(primary)
        except KeyError as error:
            raise InputError(path, f"orientation keywords missing ({error})") from None
        if not str(primary.get("FILTER", "")).strip():
            # Which filter the observables are of: filters are searched jointly, by name.
            raise InputError(path, "calvis file lacks the FILTER keyword")
        n_sci, n_cal = _file_count(path, primary, "NSCI"), _file_count(path, primary, "NCAL")
        reserved = _reserved_keys(n_sci, n_cal)
        extra = {
            key: primary[key]
            for key in primary
            if key not in reserved
            and key not in ("COMMENT", "HISTORY", "")
            and not key.startswith(("NAXIS", "SIMPLE", "BITPIX", "EXTEND"))
        }
        calvis = CalVis(
            values=values,
            errors=errors,
            kinds=kinds,
            disco_matrix=matrix,
            uv_m=uv_m,
            wavelengths_m=wavelengths,
            weights=weights,
            sky_to_uv=sky_to_uv,
            orientation=orientation,
            n_photons=float(primary.get("NPHOT", np.nan)),
            target=str(primary.get("TARGPROP", "")).strip(),
            filter_name=str(primary.get("FILTER", "")).strip().upper(),
            science_files=tuple(
                str(primary[f"SCI_{i}"]) for i in range(1, n_sci + 1) if f"SCI_{i}" in primary
            ),
            calibrator_files=tuple(
                str(primary[f"CAL_{i}"]) for i in range(1, n_cal + 1) if f"CAL_{i}" in primary
            ),
            header=extra,
        )
    calvis.validate(path)
    return calvis


# ------------------------------------------------------------------------------ internals
_ORIENTATION_KEYS = ("PA_APER", "VPARITY", "V3I_YANG", "ROLL_REF")


def _file_count(path: str, primary: fits.Header, key: str) -> int:
    """``NSCI``/``NCAL``: how many ``SCI_n``/``CAL_n`` keywords follow; a count the header
    cannot hold (more than its cards) is damage, not a loop to run."""
    value = primary.get(key, 0)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= len(primary):
        raise InputError(path, f"{key} is {value!r}: expected the number of input-file keywords")
    return value


def _reserved_keys(n_sci: int, n_cal: int) -> set[str]:
    keys = {
        "CONTENT",
        "CALVREV",
        "AMIGOVER",
        "TARGPROP",
        "FILTER",
        "NPHOT",
        "NSCI",
        "NCAL",
        "TELESCOP",
        "INSTRUME",
        *_ORIENTATION_KEYS,
    }
    keys |= {f"SCI_{i}" for i in range(1, n_sci + 1)}
    keys |= {f"CAL_{i}" for i in range(1, n_cal + 1)}
    return keys


def _validate(c: CalVis, path: str | os.PathLike[str] | None) -> None:
    def bad(problem: str) -> InputError:
        return InputError(path, problem)

    n_obs = c.values.shape[0] if c.values.ndim == 1 else -1
    if n_obs < 1:
        raise bad(f"VALUE must be a non-empty 1-D array, got shape {c.values.shape}")
    if c.errors.shape != (n_obs,) or len(c.kinds) != n_obs:
        raise bad(
            f"VALUE, ERROR and KIND lengths differ ({n_obs}, {c.errors.shape}, {len(c.kinds)})"
        )
    if c.uv_m.ndim != 2 or c.uv_m.shape[1] != 2 or c.uv_m.shape[0] < 1:
        raise bad(f"UV must hold (n_uv, 2) points, got shape {c.uv_m.shape}")
    n_uv = c.uv_m.shape[0]
    if c.disco_matrix.shape != (n_obs, 2 * n_uv):
        raise bad(
            f"DISCO_MATRIX has shape {c.disco_matrix.shape}, expected "
            f"(n_obs, 2 n_uv) = ({n_obs}, {2 * n_uv})"
        )
    unknown = sorted(set(c.kinds) - set(KINDS))
    if unknown:
        raise bad(f"KIND values {unknown} are not among {KINDS}")
    for name, array in (
        ("VALUE", c.values),
        ("ERROR", c.errors),
        ("DISCO_MATRIX", c.disco_matrix),
        ("UV", c.uv_m),
        ("WAVELENGTH", c.wavelengths_m),
        ("WEIGHT", c.weights),
        ("SKY_TO_UV", c.sky_to_uv),
    ):
        if not np.all(np.isfinite(array)):
            raise bad(f"{name} holds non-finite values")
    if np.any(c.errors <= 0):
        raise bad("ERROR must be positive")
    if (
        c.wavelengths_m.ndim != 1
        or c.wavelengths_m.size < 1
        or c.weights.shape != c.wavelengths_m.shape
    ):
        raise bad("WAVELENGTH and WEIGHT must be 1-D arrays of equal, non-zero length")
    if np.any(c.wavelengths_m <= 0) or np.any(c.wavelengths_m > 1e-4):
        raise bad("WAVELENGTH must be in metres (0 < lambda < 1e-4)")
    if np.any(c.weights < 0) or c.weights.sum() <= 0:
        raise bad("WEIGHT must be non-negative with a positive sum")
    if c.sky_to_uv.shape != (2, 2) or abs(np.linalg.det(c.sky_to_uv)) < 1e-6:
        raise bad(f"SKY_TO_UV must be an invertible 2x2 matrix, got {c.sky_to_uv!r}")
    if not (np.isnan(c.n_photons) or c.n_photons > 0):
        raise bad(f"NPHOT must be positive, got {c.n_photons}")


def _to_hdulist(c: CalVis) -> fits.HDUList:
    primary = fits.PrimaryHDU()
    h = primary.header
    h["CONTENT"] = (CONTENT, "calibrated observables, one target and filter")
    h["CALVREV"] = (FORMAT_REVISION, "revision of the calvis layout")
    h["AMIGOVER"] = (__version__, "amigo version")
    h["TELESCOP"] = "JWST"
    h["INSTRUME"] = "NIRISS"
    h["TARGPROP"] = c.target
    h["FILTER"] = c.filter_name
    for key, value in c.orientation.to_header().items():
        h[key] = value
    h["NPHOT"] = (float(c.n_photons), "photons used for the science observables")
    h["NSCI"] = (len(c.science_files), "number of science input files")
    for i, name in enumerate(c.science_files, start=1):
        h[f"SCI_{i}"] = name
    h["NCAL"] = (len(c.calibrator_files), "number of calibrator input files")
    for i, name in enumerate(c.calibrator_files, start=1):
        h[f"CAL_{i}"] = name
    for key, value in c.header.items():
        if key not in h:
            h[key] = value

    disco = fits.BinTableHDU.from_columns(
        [
            fits.Column("VALUE", "D", array=c.values),
            fits.Column("ERROR", "D", array=c.errors),
            fits.Column("KIND", "10A", array=np.array(c.kinds)),
        ],
        name="DISCO",
    )
    disco.header["COMMENT"] = "Independent calibrated observables y with 1-sigma errors."
    matrix = fits.ImageHDU(c.disco_matrix.astype(np.float64), name="DISCO_MATRIX")
    matrix.header["NOBS"] = c.n_obs
    matrix.header["NUV"] = c.n_uv
    matrix.header["COMMENT"] = "y = D @ [log|V(uv)|, arg V(uv) (rad)]; D is (NOBS, 2*NUV)."
    uv = fits.BinTableHDU.from_columns(
        [
            fits.Column("U", "D", unit="m", array=c.uv_m[:, 0]),
            fits.Column("V", "D", unit="m", array=c.uv_m[:, 1]),
        ],
        name="UV",
    )
    uv.header["COMMENT"] = "Pupil frame (x, y along detector x, y); V(b)=exp(-2 pi i b.theta/lam)."
    wl = fits.BinTableHDU.from_columns(
        [
            fits.Column("WAVELENGTH", "D", unit="m", array=c.wavelengths_m),
            fits.Column("WEIGHT", "D", array=c.weights),
        ],
        name="WAVELENGTH",
    )
    sky = fits.ImageHDU(c.sky_to_uv.astype(np.float64), name="SKY_TO_UV")
    sky.header["COMMENT"] = "theta_uv (mas, pupil x,y) = SKY_TO_UV @ [dRA east, dDec north] (mas)."
    return fits.HDUList([primary, disco, matrix, uv, wl, sky])
