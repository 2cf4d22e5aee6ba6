"""Hostile variants of valid files, as hypothesis strategies (tests/test_fuzz_inputs.py and
benchmarks/fuzz_inputs.py).

A *seed* is a small valid file of one kind (raw ramps, a level-2 image, a calslope,
calvis or OIFITS file, a base model). A :class:`Mutation` turns it into a hostile
variant the way files go wrong in practice: a keyword deleted, retyped or out of range;
an array refilled with NaN/inf/zeros/negatives, cut to another shape or cast to another
type; an extension dropped; the file cut at a byte offset (a truncated download) or
bytes overwritten (a damaged disk); for a model archive, an array or its JSON record
changed. :data:`PROMISE` is what every reader must do with any variant: return, or raise
:class:`~amigo.errors.InputError` naming the file; never another exception, never hang,
never touch the input.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits
from hypothesis import strategies as st

PROMISE = "returns, or raises InputError naming the file"

#: Keywords the readers interpret (each is tried on every HDU of a FITS seed), plus
#: whatever keywords the chosen header holds.
KEYWORDS = (
    "NGROUPS", "NINTS", "NFRAMES", "TGROUP", "TFRAME", "FILTER", "PUPIL", "SUBARRAY",
    "EXP_TYPE", "INSTRUME", "TELESCOP", "PA_APER", "ROLL_REF", "V3I_YANG", "VPARITY",
    "BUNIT", "TARGPROP", "DATE-OBS", "NSIGCLIP", "CONTENT", "NPHOT", "AMIGOPRD", "EXTNAME",
    "NAXIS", "NAXIS1", "BZERO", "OI_REVN", "INSNAME", "ARRNAME",
)  # fmt: skip

_TEXT = st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=12)
#: New keyword values: absent (``None``: the keyword is deleted), text, integers of any
#: size and sign, finite floats (FITS headers cannot hold NaN), booleans.
VALUES = st.one_of(
    st.none(),
    _TEXT,
    st.integers(-(2**40), 2**40),
    st.sampled_from([0, -1, 1, 2, 65535, 10**9]),
    st.floats(allow_nan=False, allow_infinity=False, width=32),
    st.booleans(),
)
#: How an array is damaged.
FILLS = ("nan", "inf", "-inf", "zero", "negative", "huge")
RESHAPES = ("cut_last_axis", "drop_axis", "add_axis", "empty")
DTYPES = ("int16", "uint8", "int64", "float64", "bool")


@dataclass(frozen=True)
class Mutation:
    """One way of damaging a seed file.

    Attributes
    ----------
    kind
        ``keyword``, ``fill``, ``reshape``, ``dtype``, ``drop_hdu``, ``truncate``,
        ``bytes``, ``npz_array``, ``npz_drop``, ``npz_record``.
    where
        HDU index or array number (taken modulo the count), or byte offset fraction.
    key
        Keyword name, or the fill/reshape/dtype/record choice.
    value
        New keyword value, or the bytes written.
    """

    kind: str
    where: int | float = 0
    key: str = ""
    value: Any = None

    def describe(self) -> str:
        value = "" if self.value is None else f"={self.value!r}"[:40]
        return f"{self.kind}[{self.where}]{self.key}{value}"


def fits_mutations() -> st.SearchStrategy[Mutation]:
    """Mutations of a FITS file."""
    hdu = st.integers(0, 15)
    return st.one_of(
        st.builds(Mutation, st.just("keyword"), hdu, st.sampled_from(KEYWORDS), VALUES),
        st.builds(Mutation, st.just("keyword"), hdu, st.just("*"), VALUES),
        st.builds(Mutation, st.just("fill"), hdu, st.sampled_from(FILLS)),
        st.builds(Mutation, st.just("reshape"), hdu, st.sampled_from(RESHAPES)),
        st.builds(Mutation, st.just("dtype"), hdu, st.sampled_from(DTYPES)),
        st.builds(Mutation, st.just("drop_hdu"), st.integers(1, 15)),
        *file_mutations(),
    )


def npz_mutations() -> st.SearchStrategy[Mutation]:
    """Mutations of a base-model archive."""
    index = st.integers(0, 200)
    return st.one_of(
        st.builds(Mutation, st.just("npz_array"), index, st.sampled_from(FILLS + RESHAPES)),
        st.builds(Mutation, st.just("npz_array"), index, st.sampled_from(DTYPES)),
        st.builds(Mutation, st.just("npz_drop"), index),
        st.builds(
            Mutation,
            st.just("npz_record"),
            st.just(0),
            st.sampled_from(["format", "format_version", "config", "network", "dtype", "*"]),
            VALUES,
        ),
        *file_mutations(),
    )


def file_mutations() -> tuple[st.SearchStrategy[Mutation], ...]:
    """Byte-level damage, for any file."""
    fraction = st.floats(0.0, 1.0, allow_nan=False)
    return (
        st.builds(Mutation, st.just("truncate"), fraction),
        st.builds(
            Mutation, st.just("bytes"), fraction, st.just(""), st.binary(min_size=1, max_size=64)
        ),
    )


def digest(path: Path) -> str:
    """SHA-256 of a file (inputs must be unchanged by every command)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Rejected(Exception):
    """The mutation does not apply to this seed (e.g. no such array); skip the case."""


def apply(mutation: Mutation, seed: Path, target: Path) -> None:
    """Write ``seed`` damaged by ``mutation`` to ``target``; :class:`Rejected` when it does
    not apply (astropy refuses to write that header, the seed has no such array)."""
    raw = seed.read_bytes()
    kind = mutation.kind
    if kind == "truncate":
        target.write_bytes(raw[: int(mutation.where * len(raw))])
        return
    if kind == "bytes":
        offset = min(int(mutation.where * len(raw)), len(raw) - 1)
        data = bytearray(raw)
        chunk = mutation.value[: len(raw) - offset]
        data[offset : offset + len(chunk)] = chunk
        target.write_bytes(bytes(data))
        return
    if kind.startswith("npz_"):
        target.write_bytes(_mutate_npz(mutation, raw))
        return
    try:
        with fits.open(io.BytesIO(raw)) as hdul:
            hdus = fits.HDUList([h.copy() for h in hdul])
        _mutate_fits(mutation, hdus)
        buffer = io.BytesIO()
        hdus.writeto(buffer, output_verify="silentfix")
    except Rejected:
        raise
    except Exception as error:  # astropy refuses many headers and arrays on writing
        raise Rejected(f"astropy cannot write it: {error}") from None
    target.write_bytes(buffer.getvalue())


def _damaged(array: np.ndarray, how: str) -> np.ndarray:
    if how in FILLS:
        value = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf, "zero": 0.0,
                 "negative": -1.0, "huge": 1e30}[how]  # fmt: skip
        if not np.issubdtype(array.dtype, np.floating) and how in ("nan", "inf", "-inf", "huge"):
            array = array.astype(np.float32)
        out = np.array(array, copy=True)
        out[...] = value if np.issubdtype(out.dtype, np.floating) else np.clip(value, -1, 0)
        return out
    if how in RESHAPES and array.ndim == 0:
        raise Rejected("a scalar has no axis to change")
    if how == "cut_last_axis":
        return np.ascontiguousarray(array[..., : max(1, array.shape[-1] // 2)])
    if how == "drop_axis":
        return np.ascontiguousarray(array[0]) if array.ndim > 1 else array[:0]
    if how == "add_axis":
        return np.ascontiguousarray(array[None])
    if how == "empty":
        return array[:0]
    return array.astype(how)  # a dtype name


def _mutate_fits(mutation: Mutation, hdus: fits.HDUList) -> None:
    index = int(mutation.where) % len(hdus)
    hdu = hdus[index]
    if mutation.kind == "keyword":
        header = hdu.header
        key = mutation.key
        if key == "*":  # a keyword the header holds
            keys = [k for k in header if k not in ("SIMPLE", "XTENSION", "END", "")]
            if not keys:
                raise Rejected("empty header")
            # crc32, not hash(): the same case must pick the same keyword in every process
            key = keys[zlib.crc32(repr(mutation.value).encode()) % len(keys)]
        if mutation.value is None:
            header.remove(key, ignore_missing=True, remove_all=True)
        else:
            header[key] = mutation.value
        return
    if mutation.kind == "drop_hdu":
        if len(hdus) < 2:
            raise Rejected("no extension to drop")
        del hdus[1 + (index - 1) % (len(hdus) - 1)]
        return
    if not isinstance(hdu, fits.ImageHDU | fits.PrimaryHDU) or hdu.data is None:
        raise Rejected("not an image HDU")
    hdu.data = _damaged(np.asarray(hdu.data), mutation.key)


def _mutate_npz(mutation: Mutation, raw: bytes) -> bytes:
    with np.load(io.BytesIO(raw), allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    names = sorted(n for n in arrays if n != "__metadata__")
    name = names[int(mutation.where) % len(names)]
    if mutation.kind == "npz_drop":
        del arrays[name]
    elif mutation.kind == "npz_array":
        arrays[name] = _damaged(arrays[name], mutation.key)
    else:  # npz_record
        record = json.loads(str(arrays["__metadata__"]))
        key = mutation.key
        if key == "*":
            arrays["__metadata__"] = np.array(str(mutation.value))
        else:
            if mutation.value is None:
                record.pop(key, None)
            else:
                record[key] = mutation.value
            arrays["__metadata__"] = np.array(json.dumps(record))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def is_npz(path: Path) -> bool:
    return zipfile.is_zipfile(path)
