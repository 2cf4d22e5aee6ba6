"""Stop-gap reader of raw ramps, used only until :mod:`amigo.io.jwst` is on main.

It offers the subset of ``amigo.io.jwst`` that :mod:`amigo.process` needs, with the same
names and signatures (``read_header``, ``iter_ramps``, ``read_pixel_dq``), and only the
checks processing depends on. Delete this module once ``amigo.io.jwst`` has landed.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits

from amigo.errors import InputError


@dataclass(frozen=True)
class ExposureMeta:
    """The metadata processing needs (a subset of ``amigo.io.jwst.ExposureMeta``)."""

    path: Path
    kind: str
    ngroups: int
    nints: int
    primary_header: fits.Header = field(repr=False)
    sci_header: fits.Header = field(repr=False)
    sci_shape: tuple[int, ...] = ()


def _open(path: Path) -> fits.HDUList:
    if not path.is_file():
        raise InputError(path, "no such file")
    with open(path, "rb") as handle:
        if not handle.read(30).startswith(b"SIMPLE  ="):
            raise InputError(path, "not a FITS file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hdul = fits.open(path, memmap=False, lazy_load_hdus=False)
    except Exception as error:  # astropy raises several types for damaged files
        raise InputError(path, f"cannot be read as FITS ({error})") from None
    size = path.stat().st_size
    for index in range(len(hdul)):
        info = hdul.fileinfo(index)
        if info is not None and info["datLoc"] + info["datSpan"] > size:
            hdul.close()
            raise InputError(path, f"truncated file: HDU {index} is incomplete")
    return hdul


def _get(headers: tuple[fits.Header, ...], key: str) -> Any:
    for header in headers:
        if key in header and header[key] not in (None, ""):
            return header[key]
    return None


def read_header(path: str | os.PathLike[str], *, need_slopes: bool = False) -> ExposureMeta:
    """Validate a raw-ramp file enough to process it; raise :class:`InputError` otherwise."""
    path = Path(path)
    hdul = _open(path)
    try:
        primary = hdul[0].header
        if "SCI" not in hdul:
            raise InputError(path, "has no SCI extension: not a JWST exposure")
        sci = hdul["SCI"].header
        headers = (primary, sci)
        name = _get(headers, "INSTRUME")
        if name is None or str(name).strip().upper() != "NIRISS":
            raise InputError(path, f"INSTRUME is {name!r}, expected 'NIRISS'")
        pupil = str(_get(headers, "PUPIL")).strip().upper()
        if pupil != "NRM":
            raise InputError(path, f"PUPIL is {pupil!r}, expected 'NRM' (not an AMI exposure)")
        if sci.get("NAXIS") != 4 or sci.get("BITPIX", -32) < 0:
            raise InputError(path, "SCI is not a 4-D integer cube: not a raw (uncal) ramp")
        shape = tuple(int(sci[f"NAXIS{i}"]) for i in (4, 3, 2, 1))
        try:
            nints, ngroups = int(_get(headers, "NINTS")), int(_get(headers, "NGROUPS"))
        except TypeError:
            raise InputError(path, "missing required keyword(s) NINTS, NGROUPS") from None
        if shape[:2] != (nints, ngroups):
            raise InputError(
                path,
                f"SCI has {shape[0]} integrations x {shape[1]} groups but the header says "
                f"NINTS={nints}, NGROUPS={ngroups}",
            )
        if need_slopes and ngroups < 2:
            raise InputError(path, "has one group per integration: slopes need at least 2")
        return ExposureMeta(path, "uncal", ngroups, nints, primary.copy(), sci.copy(), shape)
    finally:
        hdul.close()


def iter_ramps(
    path: str | os.PathLike[str], chunk: int = 256, *, with_dq: bool = False
) -> Iterator[Any]:
    """Yield float64 (n, ngroups, ny, nx) raw counts (BZERO applied), or with GROUPDQ."""
    path = Path(path)
    meta = read_header(path, need_slopes=True)
    hdul = _open(path)
    try:
        sci = hdul["SCI"]
        gdq = hdul["GROUPDQ"] if with_dq and "GROUPDQ" in hdul else None
        for start in range(0, meta.nints, chunk):
            stop = min(start + chunk, meta.nints)
            block = np.asarray(sci.section[start:stop], dtype=np.float64)
            if with_dq:
                yield block, None if gdq is None else np.asarray(gdq.section[start:stop])
            else:
                yield block
    finally:
        hdul.close()


def read_pixel_dq(path: str | os.PathLike[str]) -> np.ndarray | None:
    """PIXELDQ (ny, nx) uint32, or ``None`` when the file has none."""
    hdul = _open(Path(path))
    try:
        return np.asarray(hdul["PIXELDQ"].data, dtype=np.uint32) if "PIXELDQ" in hdul else None
    finally:
        hdul.close()
