"""The work of ``amigo run`` (:func:`amigo.pipeline.run`): raw ramps -> companions.

process -> fit -> detect, each step keeping what an earlier run left complete for the
same inputs (``force`` redoes all three). Files that are already slopes (the archive's
level-2 ``_cal``/``_calints``/``_rateints`` images, or calslope files) skip the first
step: a user's MAST files of either level go through one command and one process (the
start-up, imports and compiled programs paid once, not once per command).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from amigo.errors import InputError, ReportedInputError
from amigo.pipeline._detect import DetectResult, check_sampler_device, check_search_grid, detect
from amigo.pipeline._fit import (
    FitResult,
    check_detector_level,
    check_model_options,
    check_one_level,
    check_roles,
    fit,
)
from amigo.pipeline._process import ProcessResult, process


@dataclass
class RunResult:
    """What :func:`amigo.pipeline.run` did: the three steps' results (``detect`` is
    ``None`` when no filter has products), and the fit's exit status
    (:mod:`amigo.pipeline.outcome`)."""

    process: ProcessResult
    fit: FitResult
    detect: DetectResult | None

    @property
    def status(self) -> int:
        return self.fit.status

    @property
    def calvis(self) -> list[Path]:
        """The calvis files searched."""
        return self.fit.calvis


def run(
    sci: Sequence[str | Path],
    cal: Sequence[str | Path],
    out: str | Path,
    *,
    model: str | Path | None = None,
    detector: str | None = None,
    knots: int | None = None,
    knot_spacing: float | None = None,
    rmax_mas: float = 1000.0,
    step_mas: float | None = None,
    hmc: bool = True,
    superbias: Sequence[str | Path] = (),
    first_group: bool = True,
    force: bool = False,
    keep_products: bool = True,
) -> RunResult:
    """Raw ramps to companions, as ``amigo run``: :func:`process`, :func:`fit` and
    :func:`detect` into ``out``, each keeping what an earlier run left complete for the
    same inputs (``force`` redoes all three); level-2 images and calslope files go
    straight to :func:`fit`. ``superbias``: raw dark ramps, processed
    with the rest, whose reset levels let the first group's photons into the fit.
    ``step_mas``: the search grid's step (None: :func:`detect`'s default).
    ``keep_products``: as :func:`fit`'s."""
    from amigo.io.calslope import calslope_name
    from amigo.io.jwst import data_kind
    from amigo.progress import step

    sci_paths, cal_paths = tuple(map(Path, sci)), tuple(map(Path, cal))
    superbias_paths = tuple(map(Path, superbias))
    out = Path(out)
    check_roles(sci_paths, cal_paths, superbias_paths, first_group)
    one_science_target(sci_paths)
    kinds = check_before_work(
        sci_paths, cal_paths, model, detector, knots, knot_spacing, rmax_mas, step_mas
    )
    kinds.update({p: data_kind(p) for p in superbias_paths if p not in kinds})
    inputs = tuple(dict.fromkeys((*sci_paths, *cal_paths, *superbias_paths)))
    # Raw ramps are processed; level-2 images and calslope files are slopes already.
    raw = tuple(p for p in inputs if kinds[p] == "uncal")
    processed = ProcessResult()
    if raw:
        step(f"run: processing {len(raw)} raw exposures")
        processed = process(raw, out, force=force)
    if processed.failed:  # each named on its own line already
        raise ReportedInputError(
            None, f"{len(processed.failed)} of {len(raw)} raw file(s) could not be processed"
        )
    slopes = {path: out / calslope_name(path) if path in raw else path for path in inputs}
    step("run: fitting")
    fitted = fit(
        [slopes[p] for p in sci_paths],
        [slopes[p] for p in cal_paths],
        out,
        model=model,
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        superbias=[slopes[p] for p in superbias_paths],
        first_group=first_group,
        force=force,
        keep_products=keep_products,
    )
    # The products of this fit, as its summary lists them (not every calvis file in OUT:
    # one of an earlier fit of a filter that failed this time is not this run's).
    calvis = fitted.calvis
    if not calvis:
        if fitted.status:
            return RunResult(processed, fitted, None)  # the warnings say why
        raise InputError(out, "amigo fit wrote no calvis file (no science exposure?)")
    step(f"run: searching {len(calvis)} calvis file(s) for companions")
    found = detect(calvis, out, rmax_mas=rmax_mas, step_mas=step_mas, hmc=hmc, force=force)
    return RunResult(processed, fitted, found)


def check_before_work(
    sci: Sequence[Path],
    cal: Sequence[Path],
    model: str | Path | None,
    detector: str | None,
    knots: int | None,
    knot_spacing: float | None,
    rmax_mas: float,
    step_mas: float | None = None,
) -> dict[Path, str]:
    """Every option and the inputs' levels, before any work (processing raw ramps takes
    minutes: a usage error found after it would be found late), for :func:`run` and for
    each target of a manifest before the first runs. Returns the inputs' kinds
    (:func:`amigo.io.jwst.data_kind`); :class:`~amigo.errors.InputError` otherwise."""
    from amigo.io.jwst import data_kind

    check_model_options(model, detector, knots, knot_spacing)
    check_search_grid(rmax_mas, step_mas)
    check_sampler_device()
    kinds = {Path(p): data_kind(p) for p in (*sci, *cal)}
    check_one_level(kinds)
    check_detector_level(kinds, detector)
    return kinds


def one_science_target(sci: Sequence[Path]) -> None:
    """``amigo run`` (and a manifest's target) searches one star: science files of two
    targets (``TARGPROP``, else ``TARGNAME``) are refused before any work, naming the first
    file of the second target. ``amigo fit`` takes several targets at once; each target's
    calvis files are then searched apart (``amigo detect`` refuses two targets).
    A file whose primary header cannot be read is passed over: the readers name it."""
    from astropy.io import fits

    first: tuple[str, Path] | None = None
    for path in sci:
        try:
            header = fits.getheader(path)
        except Exception:  # damaged or missing: the readers refuse it in their own words
            continue
        target = str(header.get("TARGPROP") or header.get("TARGNAME") or "").strip()
        if first is None:
            first = (target, Path(path))
        elif target != first[0]:
            raise InputError(
                path,
                f"is of target {target!r}, {first[1].name} of {first[0]!r}: amigo run "
                "searches one science target (amigo fit takes several; then amigo detect "
                "each target's calvis files, or list the targets in a --manifest)",
            )
