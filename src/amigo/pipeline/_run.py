"""The work of ``amigo run`` (:func:`amigo.pipeline.run`): raw ramps -> companions.

process -> fit -> detect, each step keeping what an earlier run left complete for the
same inputs (``force`` redoes all three).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from amigo.errors import InputError
from amigo.pipeline._detect import DetectResult, detect
from amigo.pipeline._fit import FitResult, check_roles, fit
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
    hmc: bool = True,
    superbias: Sequence[str | Path] = (),
    first_group: bool = True,
    force: bool = False,
    keep_products: bool = True,
) -> RunResult:
    """Raw ramps to companions, as ``amigo run``: :func:`process`, :func:`fit` and
    :func:`detect` into ``out``, each keeping what an earlier run left complete for the
    same inputs (``force`` redoes all three). ``superbias``: raw dark ramps, processed
    with the rest, whose reset levels let the first group's photons into the fit.
    ``keep_products``: as :func:`fit`'s."""
    from amigo.io.calslope import calslope_name
    from amigo.progress import step

    sci_paths, cal_paths = tuple(map(Path, sci)), tuple(map(Path, cal))
    superbias_paths = tuple(map(Path, superbias))
    out = Path(out)
    check_roles(sci_paths, cal_paths, superbias_paths, first_group)
    inputs = tuple(dict.fromkeys((*sci_paths, *cal_paths, *superbias_paths)))
    step(f"run: processing {len(inputs)} raw exposures")
    processed = process(inputs, out, force=force)
    if processed.failed:  # each named on its own line already
        raise InputError(
            None, f"{len(processed.failed)} of {len(inputs)} raw file(s) could not be processed"
        )
    slopes = {path: out / calslope_name(path) for path in inputs}
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
    found = detect(calvis, out, rmax_mas=rmax_mas, hmc=hmc, force=force)
    return RunResult(processed, fitted, found)
