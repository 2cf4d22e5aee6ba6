"""Identify any file amigo reads and summarise it in one row (for ``amigo info``).

Kinds: JWST exposures (``uncal``, ``rate``, ``rateints``, ``cal``, ``calints``), amigo
products (``calslope``, ``calvis``) and ``oifits``. Identification looks at the HDUs, not
at the file name, so renamed files are still recognised.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits

from amigo import niriss
from amigo.errors import InputError
from amigo.io import jwst
from amigo.io.calvis import CONTENT as CALVIS_CONTENT
from amigo.io.files import damaged
from amigo.orientation import Orientation


@dataclass(frozen=True)
class FileSummary:
    """One row of ``amigo info``.

    ``peak`` is the brightest usable pixel with its unit: accumulated DN between the first
    and last group (mean over integrations) for ramps, DN/s for level 2, DN/group for
    calslope; empty for observables. ``pa_y_deg`` is the sky position angle (east of north)
    of detector +y, ``None`` where the file has no orientation.
    """

    path: Path
    kind: str
    target: str = ""
    filter: str = ""
    groups_x_ints: str = ""
    peak: str = ""
    pa_y_deg: float | None = None
    verdict: str = "ok"
    valid: bool = True


def _hdu_names(hdul: fits.HDUList) -> set[str]:
    return {hdu.name.upper() for hdu in hdul}


def _format_peak(value: float, unit: str) -> str:
    return f"{value:,.0f} {unit}" if np.isfinite(value) else "-"


def _ramp_peak(path: Path) -> float:
    """Mean over integrations of (last - first group), maximum over usable pixels (DN)."""
    total = None
    count = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jwst.AmiWarning)  # already reported by read_header
        for block in jwst.iter_ramps(path, chunk=64):
            diff = (block[:, -1] - block[:, 0]).sum(axis=0)
            total = diff if total is None else total + diff
            count += block.shape[0]
    assert total is not None
    mean = total / count
    return float(mean[~niriss.reference_row_mask(*mean.shape)].max())


def _summarise_exposure(path: Path) -> FileSummary:
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        meta = jwst.read_header(path)
    if meta.kind == "uncal":
        # One group has no rise to measure (its read holds the bias): no peak then.
        peak = _format_peak(_ramp_peak(path), "DN") if meta.ngroups > 1 else "-"
    else:
        exposure = jwst.read_exposure(path)
        values = np.where(exposure.usable, exposure.data, -np.inf)
        if values.ndim == 3:
            values = np.where(exposure.usable.all(axis=0), exposure.data.mean(axis=0), -np.inf)
        # the exposure's unit: read_exposure turns MJy/sr back into DN/s
        peak = _format_peak(float(values.max()), exposure.meta.bunit)
    notes = list(meta.notes)
    if meta.in_mjy_per_sr:
        notes.append("MJy/sr, read in DN/s through PHOTMJSR")
    if meta.charge_migration_flagged:
        notes.append("the pipeline's charge-migration step ran (S_CHGMIG)")
    verdict = "ok" if not notes else "ok (" + "; ".join(notes) + ")"
    return FileSummary(
        path=path,
        kind=meta.kind,
        target=meta.target,
        filter=meta.filter,
        groups_x_ints=f"{meta.ngroups} x {meta.nints}",
        peak=peak,
        pa_y_deg=meta.orientation.pa_of_detector_y_deg(),
        verdict=verdict,
    )


def _summarise_calslope(path: Path, hdul: fits.HDUList) -> FileSummary:
    from amigo.io.calslope import read_calslope

    read_calslope(path)  # validated as amigo fit reads it: InputError for what it refuses
    primary = hdul[0].header
    slope = hdul["SLOPE"]
    target = primary.get("TARGPROP") or primary.get("TARGNAME") or "UNKNOWN"
    try:
        orientation = Orientation.from_header(slope.header, primary)
        pa = orientation.pa_of_detector_y_deg()
    except KeyError:
        pa = None
    data = np.asarray(slope.data, dtype=float)
    if data.ndim != 3:
        raise InputError(path, f"SLOPE has {data.ndim} dimensions, expected 3")
    peak = float(np.nanmax(data.mean(axis=0)[~niriss.reference_row_mask(*data.shape[-2:])]))
    return FileSummary(
        path=path,
        kind="calslope",
        target=str(target),
        filter=str(primary.get("FILTER", "")),
        groups_x_ints=f"{primary.get('NGROUPS', data.shape[0] + 1)} x {primary.get('NINTS', '?')}",
        peak=_format_peak(peak, "DN/group"),
        pa_y_deg=pa,
    )


def _summarise_calvis(path: Path, hdul: fits.HDUList) -> FileSummary:
    from amigo.io.calvis import read_calvis

    read_calvis(path)  # validated as amigo detect reads it
    primary = hdul[0].header
    target = primary.get("TARGPROP") or primary.get("TARGNAME") or "UNKNOWN"
    pa = None
    try:
        pa = Orientation.from_header(primary).pa_of_detector_y_deg()
    except KeyError:
        pass
    return FileSummary(
        path=path,
        kind="calvis",
        target=str(target),
        filter=str(primary.get("FILTER", "")),
        pa_y_deg=pa,
    )


def _nearest_filter(wavelengths_m: np.ndarray) -> str:
    """The AMI filter whose half-power band holds the mean wavelength, else ``""``."""
    mean = float(np.mean(wavelengths_m))
    for name in niriss.CALIBRATED_FILTERS:
        blue, red = niriss.half_power_limits(name)
        if blue <= mean <= red:
            return f"{name}?"  # inferred from the wavelengths, not read from a keyword
    return ""


def _summarise_oifits(path: Path, hdul: fits.HDUList) -> FileSummary:
    from amigo.io.oifits import read_oifits

    read_oifits(path)  # validated as amigo detect reads it
    names = _hdu_names(hdul)
    target = ""
    if "OI_TARGET" in names:
        targets = hdul["OI_TARGET"].data["TARGET"]
        target = ", ".join(sorted({str(t).strip() for t in targets}))
    counts = []
    for table, label in (("OI_VIS2", "V2"), ("OI_T3", "CP"), ("OI_VIS", "VIS")):
        if table in names:
            n = sum(len(h.data) for h in hdul if h.name.upper() == table)
            counts.append(f"{n} {label}")
    filter_name = str(hdul[0].header.get("FILTER", "")).strip()
    if not filter_name and "OI_WAVELENGTH" in names:
        filter_name = _nearest_filter(np.asarray(hdul["OI_WAVELENGTH"].data["EFF_WAVE"], float))
    return FileSummary(
        path=path,
        kind="oifits",
        target=target,
        filter=filter_name,
        groups_x_ints=", ".join(counts),
    )


def summarise(path: str | os.PathLike[str]) -> FileSummary:
    """Identify and validate one file; never raises for a bad file (the row says why)."""
    path = Path(path)
    try:
        with damaged(path, "file"):
            with jwst.open_fits(path) as hdul:
                names = _hdu_names(hdul)
                if "SLOPE" in names:
                    return _summarise_calslope(path, hdul)
                content = str(hdul[0].header.get("CONTENT", "")).strip().upper()
                if content == CALVIS_CONTENT or "DISCO" in names:
                    return _summarise_calvis(path, hdul)
                if names & {"OI_VIS2", "OI_T3", "OI_VIS"}:
                    return _summarise_oifits(path, hdul)
            return _summarise_exposure(path)
    except InputError as error:
        return FileSummary(path=path, kind="?", verdict=f"invalid: {error.problem}", valid=False)
