"""The target manifest of ``amigo run --manifest FILE``: a program's science/calibrator sets.

A TOML file with one ``[[target]]`` table per set; paths are relative to the manifest's
folder, and each target's products go to ``OUT/<name>/``::

    # targets.toml
    [options]                     # optional: amigo run's options for every target
    rmax_mas = 800.0
    hmc = false

    [[target]]
    name = "ab-dor"               # optional: the folder under OUT (default: first sci stem)
    sci = ["jw01093012001_03102_00001_nis_uncal.fits"]
    cal = ["jw01093015001_03102_00001_nis_uncal.fits"]

    [[target]]
    name = "hd-36805"
    sci = ["raw/jw01093018001_03102_00001_nis_cal.fits"]   # level-2 files work too
    cal = ["raw/jw01093015001_03102_00001_nis_cal.fits"]
    rmax_mas = 400.0              # any option, for this target only

A target's inputs are raw ramps (``_uncal``: process, fit and detect, as ``amigo run``) or
level-2 / calslope files (fit and detect); ``superbias`` (a list of dark files) is a
target's own key. Options (:data:`OPTIONS`): ``model``, ``detector``, ``knots``,
``knot_spacing``, ``rmax_mas``, ``step_mas``, ``hmc``, ``first_group``. A target's own keys override
``[options]``, which override the command line's.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from amigo.errors import InputError

#: Option -> the type its value must have (``float`` accepts integers too).
OPTIONS: dict[str, type] = {
    "model": str,
    "detector": str,
    "knots": int,
    "knot_spacing": float,
    "rmax_mas": float,
    "step_mas": float,
    "hmc": bool,
    "first_group": bool,
}
#: Keys of a ``[[target]]`` table besides :data:`OPTIONS`.
TARGET_KEYS = ("name", "sci", "cal", "superbias")
#: A target's name becomes a folder: letters, digits, ``.``, ``_`` and ``-`` only.
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
#: Suffixes stripped from a science file's name to make a default target name.
_STEM_SUFFIXES = ("_uncal", "_calints", "_rateints", "_calslope", "_cal", "_rate")


@dataclass(frozen=True)
class Target:
    """One science/calibrator set of a manifest.

    Attributes
    ----------
    name
        Its output folder's name (unique in the manifest).
    sci, cal, superbias
        Absolute input paths.
    options
        The options of :data:`OPTIONS` this target sets (``[options]`` merged with its own
        keys; ``model`` as an absolute path).
    """

    name: str
    sci: tuple[Path, ...]
    cal: tuple[Path, ...]
    superbias: tuple[Path, ...] = ()
    options: Mapping[str, Any] = field(default_factory=dict)


def default_name(path: Path) -> str:
    """The target name of a science file: its name without ``.fits`` and the JWST suffix."""
    stem = path.name.removesuffix(".fits")
    for suffix in _STEM_SUFFIXES:
        if stem.endswith(suffix):
            return stem.removesuffix(suffix)
    return stem


def _files(manifest: Path, where: str, value: Any, required: bool) -> tuple[Path, ...]:
    """A list of input files (relative to the manifest's folder) that must exist."""
    if value is None and not required:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise InputError(manifest, f"{where} must be a non-empty list of file names")
    paths = []
    for item in value:
        path = Path(item) if os.path.isabs(item) else manifest.parent / item
        if not path.is_file():
            raise InputError(manifest, f"{where}: {item} does not exist")
        paths.append(path.resolve())
    return tuple(paths)


def _options(manifest: Path, where: str, table: Mapping[str, Any]) -> dict[str, Any]:
    """The :data:`OPTIONS` of ``table``, type-checked (``model`` made absolute)."""
    out: dict[str, Any] = {}
    for key, value in table.items():
        if key in TARGET_KEYS and where != "[options]":
            continue
        if key not in OPTIONS:
            known = ", ".join([*TARGET_KEYS, *OPTIONS] if where != "[options]" else OPTIONS)
            raise InputError(manifest, f"{where}: unknown key {key!r} (known: {known})")
        kind = OPTIONS[key]
        ok = isinstance(value, kind) and not (kind is int and isinstance(value, bool))
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            ok, value = True, float(value)
        if not ok:
            raise InputError(manifest, f"{where}: {key} must be a {kind.__name__}, not {value!r}")
        if key == "model":
            model = Path(value) if os.path.isabs(value) else manifest.parent / value
            if not model.is_file():
                raise InputError(manifest, f"{where}: model {value} does not exist")
            value = str(model.resolve())
        out[key] = value
    return out


def read_manifest(path: str | os.PathLike[str]) -> list[Target]:
    """The targets of a manifest, in its order, every input checked to exist.

    Raises :class:`~amigo.errors.InputError` naming the manifest and the problem (not TOML,
    no target, an unknown key, a missing file, two targets of one name).
    """
    manifest = Path(path)
    try:
        document = tomllib.loads(manifest.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(manifest, "does not exist") from None
    except IsADirectoryError:
        raise InputError(manifest, "is a folder, not a manifest file") from None
    except UnicodeDecodeError:
        raise InputError(manifest, "is not a text (TOML) file") from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(manifest, f"is not valid TOML ({error})") from None
    unknown = sorted(set(document) - {"options", "target"})
    if unknown:
        raise InputError(manifest, f"unknown table {unknown[0]!r} (known: options, target)")
    common = document.get("options", {})
    if not isinstance(common, dict):
        raise InputError(manifest, "[options] must be a table")
    defaults = _options(manifest, "[options]", common)
    tables = document.get("target", [])
    if not isinstance(tables, list) or not tables:
        raise InputError(manifest, "has no [[target]] table")
    targets: list[Target] = []
    for number, table in enumerate(tables, start=1):
        where = f"target {number}"
        if not isinstance(table, dict):
            raise InputError(manifest, f"{where} must be a table")
        sci = _files(manifest, f"{where}: sci", table.get("sci"), required=True)
        cal = _files(manifest, f"{where}: cal", table.get("cal"), required=True)
        superbias = _files(manifest, f"{where}: superbias", table.get("superbias"), False)
        name = table.get("name", default_name(sci[0]))
        if not isinstance(name, str) or not NAME.match(name):
            raise InputError(
                manifest, f"{where}: name {name!r} must be letters, digits, '.', '_' or '-'"
            )
        if any(t.name == name for t in targets):
            raise InputError(manifest, f"{where}: a target named {name!r} comes earlier")
        options = defaults | _options(manifest, f"{where} ({name})", table)
        targets.append(Target(name, sci, cal, superbias, options))
    return targets
