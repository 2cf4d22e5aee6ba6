"""Read interferometric observables from standard OIFITS files (v1 and v2).

What is read: squared visibilities (``OI_VIS2``), closure phases (``OI_T3``: ``T3PHI``),
their wavelengths (``OI_WAVELENGTH``, matched by ``INSNAME``), flags, the target name, and
closure-phase covariance when a file carries one: an OIFITS2 ``OI_CORR`` table (referenced
by the ``CORRINDX_T3PHI`` / ``CORRINDX_VIS2DATA`` columns) or a ``CPCOV`` image HDU (as
written by AMICAL-derived tools: ``(n_wl, n_cp, n_cp)``, radians squared). ``OI_VIS``
(VISAMP/VISPHI) is ignored: for aperture masking its amplitudes duplicate ``OI_VIS2`` and
its phases are not calibrated.

Baselines are read from the ``UCOORD/VCOORD`` (and ``U1COORD`` ...) columns, never from
``OI_ARRAY`` station positions: pipelines disagree on hole-coordinate conventions (see
docs/detect.md), while u and v are defined by the standard.

Sign convention (OIFITS standard, Pauls et al. 2005; Duvert et al. 2017): ``u`` points
east and ``v`` north, and a scene of point sources with flux ``c_k`` at sky offsets
``(dRA_k, dDec_k)`` (radians, dRA positive to the east) has the complex visibility::

    V(u, v) = sum_k c_k exp(-2 pi i (u dRA_k + v dDec_k) / lambda) / sum_k c_k

The closure phase of a triangle is ``arg[V(u1, v1) V(u2, v2) V*(u1 + u2, v1 + v2)]``.
Peer pipelines do not all honour this sign: a closure-phase sign error puts a companion at
the diametrically opposite position angle.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np
from astropy.io import fits

from amigo.errors import InputError
from amigo.io.files import damaged, require_file
from amigo.io.jwst import open_fits


@dataclass(frozen=True)
class OIVis2:
    """Squared visibilities, one entry per (row, spectral channel) that is not flagged.

    Attributes
    ----------
    u_m, v_m
        (n,) baseline coordinates (m), u east, v north.
    wavelength_m, bandwidth_m
        (n,) effective wavelength and bandwidth of each entry (m).
    value, error
        (n,) squared visibility and its 1-sigma error.
    covariance
        (n, n) covariance from ``OI_CORR``, or ``None``.
    """

    u_m: np.ndarray
    v_m: np.ndarray
    wavelength_m: np.ndarray
    bandwidth_m: np.ndarray
    value: np.ndarray
    error: np.ndarray
    covariance: np.ndarray | None = None


@dataclass(frozen=True)
class OIT3:
    """Closure phases, one entry per (row, spectral channel) that is not flagged.

    Attributes
    ----------
    u1_m, v1_m, u2_m, v2_m
        (n,) the two baselines of each triangle (m); the third is ``-(u1 + u2)``.
    wavelength_m, bandwidth_m
        (n,) as in :class:`OIVis2`.
    phase_rad, error_rad
        (n,) closure phase and 1-sigma error, radians.
    stations
        (n, 3) station indices of the triangle (labels only, to know which triangles
        share baselines), or ``None``.
    exposure
        (n,) which exposure each entry belongs to: its table and ``MJD`` (flagged
        entries are left out after this is known, so that a missing triangle does not
        shift the others), as consecutive integers.
    covariance
        (n, n) covariance in rad^2 from ``OI_CORR`` or a ``CPCOV`` HDU, or ``None``.
    """

    u1_m: np.ndarray
    v1_m: np.ndarray
    u2_m: np.ndarray
    v2_m: np.ndarray
    wavelength_m: np.ndarray
    bandwidth_m: np.ndarray
    phase_rad: np.ndarray
    error_rad: np.ndarray
    stations: np.ndarray | None = None
    covariance: np.ndarray | None = None
    exposure: np.ndarray | None = None


@dataclass(frozen=True)
class OIFits:
    """The observables of one OIFITS file.

    ``filter_name`` comes from the primary ``FILTER`` or ``FILT`` keyword when present
    (AMI files), else it is built from the mean wavelength (``"4.82um"``).
    """

    path: str
    target: str
    filter_name: str
    vis2: OIVis2 | None
    t3: OIT3 | None
    header: fits.Header


def is_oifits(path: str | os.PathLike[str]) -> bool:
    """True if ``path`` is a FITS file with an ``OI_VIS2`` or ``OI_T3`` table."""
    try:  # open_fits refuses a FIFO, a directory... without opening it
        with open_fits(path) as hdul:
            return any(h.name in ("OI_VIS2", "OI_T3") for h in hdul)
    except InputError:
        return False


def read_oifits(path: str | os.PathLike[str]) -> OIFits:
    """Read V2 and closure phases from an OIFITS file; raise :class:`InputError` if unusable."""
    path = os.fspath(require_file(path, "OIFITS file"))
    with open_fits(path) as hdul, damaged(path, "OIFITS file"):
        if not any(h.name in ("OI_VIS2", "OI_T3") for h in hdul):
            raise InputError(path, "has neither OI_VIS2 nor OI_T3 table: not an OIFITS file")
        wavelengths = _wavelength_tables(hdul, path)
        corr = _correlation_matrix(hdul, path)
        vis2_parts = [_read_vis2(h, wavelengths, corr, path) for h in hdul if h.name == "OI_VIS2"]
        tables = [h for h in hdul if h.name == "OI_T3"]
        t3_parts = [_read_t3(h, wavelengths, corr, path, i) for i, h in enumerate(tables)]
        vis2 = _concat_vis2([p for p in vis2_parts if p is not None])
        t3 = _concat_t3([p for p in t3_parts if p is not None])
        if t3 is not None and t3.covariance is None and "CPCOV" in hdul:
            t3 = _attach_cpcov(t3, hdul["CPCOV"], t3_parts, path)
        if vis2 is None and t3 is None:
            raise InputError(path, "every V2 and closure phase is flagged or invalid")
        primary = hdul[0].header.copy()
        target = _target_name(hdul, primary)
        filter_name = _filter_name(primary, vis2, t3)
    return OIFits(
        path=path, target=target, filter_name=filter_name, vis2=vis2, t3=t3, header=primary
    )


# ------------------------------------------------------------------------------ internals
@dataclass(frozen=True)
class _Part:
    """Entries of one table before concatenation; ``keep`` masks flagged/invalid entries."""

    data: dict[str, np.ndarray]
    keep: np.ndarray
    covariance: np.ndarray | None


def _wavelength_tables(hdul: fits.HDUList, path: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    tables: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for h in hdul:
        if h.name != "OI_WAVELENGTH":
            continue
        insname = str(h.header.get("INSNAME", "")).strip()
        wave = np.atleast_1d(np.asarray(h.data["EFF_WAVE"], dtype=float))
        band = np.atleast_1d(np.asarray(h.data["EFF_BAND"], dtype=float))
        if np.any(~np.isfinite(wave)) or np.any(wave <= 0):
            raise InputError(path, f"OI_WAVELENGTH {insname!r} has non-positive EFF_WAVE")
        tables[insname] = (wave, np.where(np.isfinite(band) & (band > 0), band, 0.0))
    if not tables:
        raise InputError(path, "has no OI_WAVELENGTH table")
    return tables


def _lookup_wavelengths(header: fits.Header, tables: dict, path: str) -> tuple[np.ndarray, ...]:
    insname = str(header.get("INSNAME", "")).strip()
    if insname in tables:
        return tables[insname]
    if len(tables) == 1:
        return next(iter(tables.values()))
    raise InputError(
        path,
        f"{header.get('EXTNAME')} refers to INSNAME {insname!r} which has no OI_WAVELENGTH table",
    )


def _channels(column: np.ndarray, n_rows: int, n_wl: int) -> np.ndarray:
    """Shape a per-(row, channel) column as (n_rows, n_wl)."""
    array = np.asarray(column)
    return (
        array.reshape(n_rows, n_wl)
        if array.size == n_rows * n_wl
        else np.broadcast_to(array.reshape(n_rows, -1)[:, :1], (n_rows, n_wl))
    )


def _flags(table: fits.FITS_rec, n_rows: int, n_wl: int) -> np.ndarray:
    if "FLAG" not in table.columns.names:
        return np.zeros((n_rows, n_wl), dtype=bool)
    flag = np.asarray(table["FLAG"])
    if flag.dtype.kind in "US":  # some writers store 'T'/'F' characters
        flag = np.char.strip(flag.astype(str)) == "T"
    return _channels(flag.astype(bool), n_rows, n_wl)


def _read_vis2(hdu, wavelengths, corr, path) -> _Part | None:
    table = hdu.data
    if table is None or len(table) == 0:
        return None
    wave, band = _lookup_wavelengths(hdu.header, wavelengths, path)
    n, n_wl = len(table), wave.size
    value = _channels(table["VIS2DATA"], n, n_wl).astype(float)
    error = _channels(table["VIS2ERR"], n, n_wl).astype(float)
    u = np.repeat(np.asarray(table["UCOORD"], float)[:, None], n_wl, axis=1)
    v = np.repeat(np.asarray(table["VCOORD"], float)[:, None], n_wl, axis=1)
    keep = ~_flags(table, n, n_wl) & np.isfinite(value) & np.isfinite(error) & (error > 0)
    keep &= np.isfinite(u) & np.isfinite(v)
    data = {
        "u_m": u,
        "v_m": v,
        "value": value,
        "error": error,
        "wavelength_m": np.broadcast_to(wave, (n, n_wl)),
        "bandwidth_m": np.broadcast_to(band, (n, n_wl)),
    }
    covariance = _covariance_from_corr(table, "CORRINDX_VIS2DATA", corr, error, path)
    return _Part({k: np.asarray(a).ravel() for k, a in data.items()}, keep.ravel(), covariance)


def _read_t3(hdu, wavelengths, corr, path, table_index: int = 0) -> _Part | None:
    table = hdu.data
    if table is None or len(table) == 0:
        return None
    wave, band = _lookup_wavelengths(hdu.header, wavelengths, path)
    n, n_wl = len(table), wave.size
    unit = str(hdu.columns["T3PHI"].unit or "deg").strip().lower()
    to_rad = 1.0 if unit.startswith("rad") else np.pi / 180.0
    phase = _channels(table["T3PHI"], n, n_wl).astype(float) * to_rad
    error = _channels(table["T3PHIERR"], n, n_wl).astype(float) * to_rad
    cols = {
        name: np.repeat(np.asarray(table[name], float)[:, None], n_wl, axis=1)
        for name in ("U1COORD", "V1COORD", "U2COORD", "V2COORD")
    }
    keep = ~_flags(table, n, n_wl) & np.isfinite(phase) & np.isfinite(error) & (error > 0)
    for array in cols.values():
        keep &= np.isfinite(array)
    data = {
        "u1_m": cols["U1COORD"],
        "v1_m": cols["V1COORD"],
        "u2_m": cols["U2COORD"],
        "v2_m": cols["V2COORD"],
        "phase_rad": phase,
        "error_rad": error,
        "wavelength_m": np.broadcast_to(wave, (n, n_wl)),
        "bandwidth_m": np.broadcast_to(band, (n, n_wl)),
    }
    if "STA_INDEX" in table.columns.names:
        stations = np.asarray(table["STA_INDEX"]).reshape(n, 3)
        data["stations"] = np.repeat(stations[:, None, :], n_wl, axis=1)
    # An exposure is a table and an MJD (OIFITS2 requires the column), known per row
    # before flagged entries are dropped.
    mjd = np.asarray(table["MJD"], float) if "MJD" in table.columns.names else np.zeros(n)
    data["exposure_key"] = np.repeat(
        np.column_stack([np.full(n, float(table_index)), np.nan_to_num(mjd)])[:, None, :],
        n_wl,
        axis=1,
    )
    covariance = _covariance_from_corr(table, "CORRINDX_T3PHI", corr, error, path)
    columns = {"stations": 3, "exposure_key": 2}  # entries of several values
    flat = {
        k: np.asarray(a).reshape(n * n_wl, columns[k]) if k in columns else np.asarray(a).ravel()
        for k, a in data.items()
    }
    return _Part(flat, keep.ravel(), covariance)


def _correlation_matrix(hdul: fits.HDUList, path: str) -> np.ndarray | None:
    """The dense correlation matrix of an OIFITS2 ``OI_CORR`` table (1-based indices)."""
    if "OI_CORR" not in hdul:
        return None
    h = hdul["OI_CORR"]
    try:
        ndata = int(h.header["NDATA"])
        iindx = np.asarray(h.data["IINDX"], int) - 1
        jindx = np.asarray(h.data["JINDX"], int) - 1
        values = np.asarray(h.data["CORR"], float)
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(path, f"malformed OI_CORR table ({error})") from None
    if np.any((iindx < 0) | (iindx >= ndata) | (jindx < 0) | (jindx >= ndata)):
        raise InputError(path, "OI_CORR indices fall outside 1..NDATA")
    corr = np.eye(ndata)
    corr[iindx, jindx] = values
    corr[jindx, iindx] = values
    return corr


def _covariance_from_corr(table, column: str, corr, error: np.ndarray, path: str):
    if corr is None or column not in table.columns.names:
        return None
    start = np.asarray(table[column], int) - 1  # first channel of each row
    n_wl = error.shape[1]
    if np.all(start < 0):  # column present but unused (-1 / 0 means 'no correlation')
        return None
    if np.any(start < 0):
        raise InputError(path, f"{column} is set for some rows only")
    index = (start[:, None] + np.arange(n_wl)[None, :]).ravel()
    if index.max() >= corr.shape[0]:
        raise InputError(path, f"{column} points beyond OI_CORR NDATA")
    sigma = error.ravel()
    return corr[np.ix_(index, index)] * np.outer(sigma, sigma)


def _attach_cpcov(t3: OIT3, hdu, parts: list, path: str) -> OIT3:
    """Attach a ``CPCOV`` image (n_wl, n_cp, n_cp) to the closure phases, in rad^2."""
    if len([p for p in parts if p is not None]) != 1:
        warnings.warn(f"{path}: CPCOV ignored (several OI_T3 tables)", stacklevel=3)
        return t3
    part = next(p for p in parts if p is not None)
    cube = np.asarray(hdu.data, dtype=float)
    cube = cube.reshape((-1, *cube.shape[-2:])) if cube.ndim >= 2 else cube
    n_entries = part.keep.size
    n_wl = cube.shape[0]
    n_cp = cube.shape[-1]
    if cube.ndim != 3 or cube.shape[1] != n_cp or n_cp * n_wl != n_entries:
        raise InputError(
            path,
            f"CPCOV has shape {cube.shape}, which does not match the "
            f"{n_entries} closure phases of OI_T3",
        )
    # Entries are ordered (row, channel); the cube is (channel, row, row).
    full = np.zeros((n_entries, n_entries))
    for k in range(n_wl):
        index = np.arange(n_cp) * n_wl + k
        full[np.ix_(index, index)] = cube[k]
    # Units: BUNIT if given, else decided by comparing the diagonal with T3PHIERR.
    sigma_all = part.data["error_rad"]
    unit = str(hdu.header.get("BUNIT", "")).strip().lower()
    diag = np.sqrt(np.clip(np.diag(full), 0, None))
    if unit.startswith("deg"):
        full = full * (np.pi / 180.0) ** 2
    elif not unit.startswith("rad"):
        ratio = np.median(diag / sigma_all)
        if 0.2 < ratio < 5:
            pass  # already rad^2
        elif 0.2 < ratio * np.pi / 180.0 < 5:
            full = full * (np.pi / 180.0) ** 2
        else:
            raise InputError(
                path,
                "CPCOV units cannot be established (its diagonal matches "
                "T3PHIERR neither in rad^2 nor in deg^2)",
            )
    keep = part.keep
    covariance = full[np.ix_(keep, keep)]
    if not np.all(np.isfinite(covariance)):
        raise InputError(path, "CPCOV holds non-finite values")
    return OIT3(**{**t3.__dict__, "covariance": covariance})


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        out[i : i + b.shape[0], i : i + b.shape[0]] = b
        i += b.shape[0]
    return out


def _concat(parts: list[_Part], error_key: str):
    if not parts:
        return None, None
    data = {
        k: np.concatenate([p.data[k][p.keep] for p in parts])
        for k in parts[0].data
        if all(k in p.data for p in parts)
    }
    if data[error_key].size == 0:
        return None, None
    if any(p.covariance is not None for p in parts):
        blocks = []
        for p in parts:
            cov = p.covariance if p.covariance is not None else np.diag(p.data[error_key] ** 2)
            blocks.append(cov[np.ix_(p.keep, p.keep)])
        return data, _block_diag(blocks)
    return data, None


def _concat_vis2(parts: list[_Part]) -> OIVis2 | None:
    data, cov = _concat(parts, "error")
    return None if data is None else OIVis2(**data, covariance=cov)


def _concat_t3(parts: list[_Part]) -> OIT3 | None:
    data, cov = _concat(parts, "error_rad")
    if data is None:
        return None
    data.setdefault("stations", None)
    keys = data.pop("exposure_key", None)
    exposure = None if keys is None else np.unique(keys, axis=0, return_inverse=True)[1].ravel()
    return OIT3(**data, covariance=cov, exposure=exposure)


def _target_name(hdul: fits.HDUList, primary: fits.Header) -> str:
    if "OI_TARGET" in hdul and hdul["OI_TARGET"].data is not None and len(hdul["OI_TARGET"].data):
        return str(hdul["OI_TARGET"].data["TARGET"][0]).strip()
    return str(primary.get("OBJECT", "")).strip()


def _filter_name(primary: fits.Header, vis2: OIVis2 | None, t3: OIT3 | None) -> str:
    for key in ("FILTER", "FILT"):
        value = str(primary.get(key, "")).strip().upper()
        if value:
            return value
    waves = np.concatenate([x.wavelength_m for x in (vis2, t3) if x is not None])
    return f"{np.mean(waves) * 1e6:.2f}um"
