"""Scenarios: what to simulate, read from TOML files.

A scenario is a set of exposures of targets (a primary with point companions) in AMI
filters, plus the spread of the random instrument state and overrides of the detector
model. The built-in scenarios ship as TOML files in ``amigo/data/scenarios`` (copy one
and edit it); :func:`load_scenario` accepts a built-in name or a path. The file format is
documented in docs/simulate.md and by the shipped files themselves.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from amigo import niriss
from amigo.errors import InputError
from amigo.simulation.detector import DetectorConfig
from amigo.simulation.scene import SkyCompanion, Target, dither_offsets
from amigo.simulation.state import StateSpread

EXPOSURE_ROLES = ("science", "calibrator", "flat")
ILLUMINATIONS = ("auto", "analytic", "optics")


@dataclass(frozen=True)
class ExposureSpec:
    """One exposure (one file) of a scenario, dithers already expanded.

    Photon budget: exactly one of ``photons_full`` (expected detected photons in SUB80
    over the ``nints_full`` integrations, as in the paper's tables) or ``peak_dn`` (the
    expected signal of the brightest pixel at the last group, DN above bias, before
    detector effects) sets the photon rate. The rate is the same whatever number of
    integrations is simulated, so a quick run has the real well depths and fewer photons.
    """

    role: str
    target: Target | None
    filter: str
    ngroups: int
    nints: int
    nints_full: int
    observation: int
    visit: int
    visit_group: int
    sequence: int
    activity: int
    exposure: int
    pa_aper_deg: float
    offset_pix: tuple[float, float]
    dither_pattern: str
    dither_position: int
    dither_total: int
    dither_offset_pix: tuple[float, float] = (0.0, 0.0)
    photons_full: float | None = None
    peak_dn: float | None = None

    def stem(self, program: int) -> str:
        """JWST-style file stem, e.g. ``jw01093012001_03102_00001_nis``."""
        return (
            f"jw{program:05d}{self.observation:03d}{self.visit:03d}_"
            f"{self.visit_group:02d}{self.sequence:1d}{self.activity:02d}_"
            f"{self.exposure:05d}_nis"
        )


@dataclass(frozen=True)
class Scenario:
    """A parsed scenario file."""

    name: str
    description: str
    program: int
    date_obs: str
    time_obs: str
    exposures: tuple[ExposureSpec, ...]
    spread: StateSpread = field(default_factory=StateSpread)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    illumination: str = "auto"
    n_wavelengths: int = 15
    oversample: int = 4
    source: str = ""

    @property
    def filters(self) -> tuple[str, ...]:
        """Filters used, in the order of :data:`amigo.niriss.FILTERS`."""
        used = {e.filter for e in self.exposures}
        return tuple(f for f in niriss.FILTERS if f in used)


def builtin_names() -> list[str]:
    """Names of the scenarios shipped with amigo."""
    folder = resources.files("amigo") / "data" / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a built-in scenario by name, or a scenario TOML file by path.

    Raises :class:`~amigo.errors.InputError` naming the file and the problem.
    """
    text_name = str(name_or_path)
    if text_name in builtin_names():
        resource = resources.files("amigo") / "data" / "scenarios" / f"{text_name}.toml"
        return parse_scenario(resource.read_text(encoding="utf-8"), f"<builtin {text_name}>")
    path = Path(name_or_path)
    if not path.is_file():
        raise InputError(
            path,
            f"no such scenario file, and not a built-in scenario ({', '.join(builtin_names())})",
        )
    return parse_scenario(path.read_text(encoding="utf-8"), str(path))


def parse_scenario(text: str, source: str = "<string>") -> Scenario:
    """Parse scenario TOML text (``source`` names it in error messages)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise InputError(source, f"not valid TOML: {error}") from None
    try:
        return _build(data, source)
    except (KeyError, TypeError, ValueError) as error:
        message = error.args[0] if error.args else str(error)
        if isinstance(error, KeyError):
            message = f"missing key {message!r}"
        raise InputError(source, str(message)) from None


# --------------------------------------------------------------------------------------
# Parsing helpers
# --------------------------------------------------------------------------------------

_TOP_KEYS = {
    "name", "description", "program", "date_obs", "time_obs", "illumination",
    "n_wavelengths", "oversample", "instrument", "detector", "targets", "exposures",
}  # fmt: skip
_TARGET_KEYS = {"name", "catalog_name", "ra_deg", "dec_deg", "companions"}
_COMPANION_KEYS = {"sep_mas", "pa_deg", "dmag"}
_EXPOSURE_KEYS = {
    "role", "target", "filter", "ngroups", "nints", "nints_full", "observation", "visit",
    "visit_group", "sequence", "activity", "exposure", "pa_aper_deg", "offset_pix", "dither",
    "photons_full", "peak_dn",
}  # fmt: skip


def _check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in {where}; allowed: {sorted(allowed)}")


def _companion(table: Mapping[str, Any], where: str) -> SkyCompanion:
    _check_keys(table, _COMPANION_KEYS, where)
    dmag = {niriss.check_filter(k): float(v) for k, v in dict(table["dmag"]).items()}
    return SkyCompanion(sep_mas=float(table["sep_mas"]), pa_deg=float(table["pa_deg"]), dmag=dmag)


def _target(table: Mapping[str, Any], index: int) -> Target:
    where = f"[[targets]] #{index + 1}"
    _check_keys(table, _TARGET_KEYS, where)
    companions = tuple(
        _companion(c, f"{where} companion #{j + 1}")
        for j, c in enumerate(table.get("companions", []))
    )
    dec = float(table["dec_deg"])
    if not -90.0 <= dec <= 90.0:
        raise ValueError(f"{where}: dec_deg {dec} outside [-90, 90]")
    return Target(
        name=str(table["name"]),
        catalog_name=str(table.get("catalog_name", table["name"])),
        ra_deg=float(table["ra_deg"]) % 360.0,
        dec_deg=dec,
        companions=companions,
    )


def _positive_int(
    table: Mapping[str, Any], key: str, where: str, default: int | None = None
) -> int:
    value = table.get(key, default)
    if value is None:
        raise ValueError(f"missing key {key!r} in {where}")
    if int(value) != value or int(value) < 1:
        raise ValueError(f"{key} in {where} must be a positive integer, got {value!r}")
    return int(value)


def _exposures(
    table: Mapping[str, Any], index: int, targets: dict[str, Target]
) -> list[ExposureSpec]:
    where = f"[[exposures]] #{index + 1}"
    _check_keys(table, _EXPOSURE_KEYS, where)
    role = str(table.get("role", "science"))
    if role not in EXPOSURE_ROLES:
        raise ValueError(f"role {role!r} in {where}; expected one of {EXPOSURE_ROLES}")
    target = None
    if role != "flat":
        name = str(table["target"])
        if name not in targets:
            raise ValueError(f"{where} names target {name!r}, not defined in [[targets]]")
        target = targets[name]
    filter_name = niriss.check_filter(str(table["filter"]))
    if target is not None:
        for companion in target.companions:
            if filter_name not in companion.dmag:
                raise ValueError(f"a companion of {target.name} has no dmag for {filter_name}")
    ngroups = _positive_int(table, "ngroups", where)
    nints = _positive_int(table, "nints", where)
    nints_full = _positive_int(table, "nints_full", where, nints)
    photons = table.get("photons_full")
    peak = table.get("peak_dn")
    if (photons is None) == (peak is None):
        raise ValueError(f"{where}: give exactly one of photons_full and peak_dn")
    if (photons is not None and float(photons) <= 0) or (peak is not None and float(peak) <= 0):
        raise ValueError(f"{where}: photons_full / peak_dn must be positive")
    offset = tuple(float(v) for v in table.get("offset_pix", (0.0, 0.0)))
    if len(offset) != 2:
        raise ValueError(f"{where}: offset_pix must be [dx, dy]")
    pattern = table.get("dither", "NONE")
    offsets = dither_offsets(pattern)
    pattern_name = pattern.upper() if isinstance(pattern, str) else "CUSTOM"
    first = _positive_int(table, "exposure", where, 1)
    specs = []
    for position, (ddx, ddy) in enumerate(offsets):
        specs.append(
            ExposureSpec(
                role=role,
                target=target,
                filter=filter_name,
                ngroups=ngroups,
                nints=nints,
                nints_full=nints_full,
                observation=_positive_int(table, "observation", where),
                visit=_positive_int(table, "visit", where, 1),
                visit_group=_positive_int(table, "visit_group", where, 1),
                sequence=_positive_int(table, "sequence", where, 1),
                activity=_positive_int(table, "activity", where, 1),
                exposure=first + position,
                pa_aper_deg=float(table.get("pa_aper_deg", 0.0)) % 360.0,
                offset_pix=(offset[0] + ddx, offset[1] + ddy),
                dither_pattern=pattern_name,
                dither_position=position + 1,
                dither_total=len(offsets),
                dither_offset_pix=(ddx, ddy),
                photons_full=None if photons is None else float(photons),
                peak_dn=None if peak is None else float(peak),
            )
        )
    return specs


def _build(data: Mapping[str, Any], source: str) -> Scenario:
    _check_keys(data, _TOP_KEYS, "the top level")
    targets: dict[str, Target] = {}
    for i, table in enumerate(data.get("targets", [])):
        target = _target(table, i)
        if target.name in targets:
            raise ValueError(f"target {target.name!r} is defined twice")
        targets[target.name] = target
    exposures: list[ExposureSpec] = []
    for i, table in enumerate(data.get("exposures", [])):
        exposures.extend(_exposures(table, i, targets))
    if not exposures:
        raise ValueError("no [[exposures]]")
    program = int(data["program"])
    stems = [e.stem(program) for e in exposures]
    duplicated = sorted({s for s in stems if stems.count(s) > 1})
    if duplicated:
        raise ValueError(f"two exposures would write the same file: {duplicated}")
    illumination = str(data.get("illumination", "auto"))
    if illumination not in ILLUMINATIONS:
        raise ValueError(f"illumination {illumination!r}; expected one of {ILLUMINATIONS}")
    oversample = int(data.get("oversample", 4))
    if oversample < 2:
        raise ValueError("oversample must be >= 2")
    return Scenario(
        name=str(data["name"]),
        description=str(data.get("description", "")),
        program=program,
        date_obs=str(data.get("date_obs", "2024-01-01")),
        time_obs=str(data.get("time_obs", "00:00:00.000")),
        exposures=tuple(exposures),
        spread=StateSpread.from_mapping(dict(data.get("instrument", {}))),
        detector=DetectorConfig.from_mapping(dict(data.get("detector", {}))),
        illumination=illumination,
        n_wavelengths=int(data.get("n_wavelengths", 15)),
        oversample=oversample,
        source=source,
    )
