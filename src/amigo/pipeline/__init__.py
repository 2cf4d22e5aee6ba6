"""amigo's Python API: the command line's jobs as functions a script or notebook calls.

Every ``amigo`` command is a thin layer over one of these (the command parses its options,
calls the function and turns its result into an exit status). The functions write the
same files as the commands (docs/interfaces.md), print the same progress lines on
stderr, raise :class:`~amigo.errors.InputError` for a bad input, and return what they did::

    import amigo

    exposure = amigo.open("jw01093012001_03102_00001_nis_cal.fits")
    print(exposure.meta.target, exposure.meta.filter, exposure.data.shape)

    fitted = amigo.fit(
        sci=["jw01093012001_03102_00001_nis_cal.fits"],
        cal=["jw01093015001_03102_00001_nis_cal.fits"],
        out="fit",
    )
    print(fitted.status, fitted.calvis)  # 0, [PosixPath('fit/AB-DOR_F480M_calvis.fits')]
    print(fitted.summary["exposures"][0]["zscore_std"])
    figures = fitted.plot_residuals()  # data, model, residuals, histogram per exposure

    found = amigo.detect(fitted.calvis, out="fit")
    for companion in found.companions:
        print(companion["sep_mas"], companion["pa_deg"], companion["dmag"])

From raw ramps: ``amigo.simulate("demo", "raw")`` writes simulated ones,
``amigo.process(uncal_files, "out")`` reduces them to calslope files, and
``amigo.run(sci, cal, "out")`` does process, fit and detect in one go.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from amigo.pipeline._detect import DetectResult, detect_files
from amigo.pipeline._fit import FitResult, fit_files
from amigo.pipeline._process import ProcessResult, process_files
from amigo.pipeline._run import RunResult, run_files

PathLike = str | os.PathLike[str]

__all__ = [
    "DetectResult",
    "FitResult",
    "ProcessResult",
    "RunResult",
    "detect",
    "fit",
    "open",
    "process",
    "run",
    "simulate",
]


def open(path: PathLike) -> Any:
    """Read any file amigo knows, by what it holds (not its name).

    Returns a :class:`~amigo.io.jwst.Exposure` for raw ramps and level-2 images
    (``_uncal``, ``_cal``, ``_calints``, ``_rateints``; ``.meta`` holds the header
    facts, ``.data`` the pixels in DN or DN/s), a :class:`~amigo.io.calslope.CalSlope`
    for ``amigo process`` products, a :class:`~amigo.io.calvis.CalVis` for calvis files
    and an :class:`~amigo.io.oifits.OIFits` for OIFITS files; raises
    :class:`~amigo.errors.InputError` for anything else.
    """
    from amigo.io.calslope import read_calslope
    from amigo.io.calvis import is_calvis, read_calvis
    from amigo.io.jwst import data_kind, read_exposure
    from amigo.io.oifits import is_oifits, read_oifits

    if is_calvis(path):
        return read_calvis(path)
    if is_oifits(path):
        return read_oifits(path)
    if data_kind(path) == "calslope":
        return read_calslope(path)
    return read_exposure(path)


def process(
    uncal: Sequence[PathLike],
    out: PathLike,
    *,
    sigma: float = 3.0,
    adc: bool = True,
    saturation_dn: float | None = None,
    one_over_f: str = "stripes",
    force: bool = False,
) -> ProcessResult:
    """Raw ramps (``_uncal.fits``) to ``out/<stem>_calslope.fits``, as ``amigo process``.

    ``sigma``: outlier clipping threshold (robust standard deviations); ``adc``: correct
    the ADC's integral non-linearity; ``saturation_dn``: raw count of saturation
    (default the ADC full scale); ``one_over_f``: ``"stripes"`` removes 1/f column
    offsets, ``"none"`` leaves them; ``force``: process files whose product is already
    complete. A bad file is reported (``ProcessResult.failed``) and the others go on.
    """
    return process_files(
        [Path(p) for p in uncal],
        Path(out),
        sigma=sigma,
        adc=adc,
        saturation_dn=saturation_dn,
        one_over_f=one_over_f,
        force=force,
    )


def fit(
    sci: Sequence[PathLike],
    cal: Sequence[PathLike],
    out: PathLike,
    *,
    model: PathLike | None = None,
    detector: str | None = None,
    knots: int | None = None,
    knot_spacing: float | None = None,
    max_iterations: int | None = None,
    polish: int = 0,
    wavefront_prior: float | None = None,
    superbias: Sequence[PathLike] = (),
    first_group: bool = True,
    force: bool = False,
) -> FitResult:
    """Fit science and calibrator exposures and extract calibrated observables, as ``amigo
    fit``: per science target and filter ``out/<TARGPROP>_<FILTER>_calvis.fits`` and
    ``.oifits``, with ``out/fit_summary.json`` and ``out/plots``.

    ``sci``, ``cal``: level-2 images or calslope files (not both kinds). ``model``: a base
    model (``.npz``) or instrument file (default: the shipped model for the data's
    level); ``detector``: ``"full"`` or ``"linear"`` (default: as docs/fit.md says);
    ``knots``, ``knot_spacing``: the uv grid of the latent visibilities;
    ``max_iterations``, ``polish``: optimiser bounds; ``wavefront_prior``: nm rms prior on
    the calibrators' wavefront; ``superbias``: calslope darks giving each pixel's reset
    level (calslope inputs; default the model's); ``first_group=False`` fits the group
    differences only; ``force``: fit filters whose products are already complete.

    Returns a :class:`FitResult` (``.status``, ``.calvis``, ``.summary``,
    ``.plot_residuals()``). Numerical failures end their filter, not the call
    (``.status`` 3 or 4, docs/reliability.md).
    """
    return fit_files(
        [Path(p) for p in sci],
        [Path(p) for p in cal],
        Path(out),
        model=None if model is None else Path(model),
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        max_iterations=max_iterations,
        polish=polish,
        wavefront_prior=wavefront_prior,
        superbias=[Path(p) for p in superbias],
        first_group=first_group,
        force=force,
    )


def detect(files: Sequence[PathLike], out: PathLike, **options: Any) -> DetectResult:
    """Search calvis or OIFITS files for companions, as ``amigo detect``: writes
    ``out/companions.json``, ``out/contrast_limits.csv`` and figures.

    ``options`` (keywords, the command's options): ``rmax_mas`` (1000), ``threshold``
    (5 sigma), ``step_mas`` (None: lambda_min / 3 B_max), ``max_companions`` (3),
    ``observables`` (``"all"``, ``"phase"``, ``"amplitude"``), ``cp_correlation``
    (``"baseline"``, ``"independent"``), ``primary_diameter_mas`` (0), ``hmc`` (True),
    ``per_filter`` (True), ``warmup`` (500), ``samples`` (1000), ``chains`` (2),
    ``seed`` (0), ``force`` (False: keep a search of the same inputs and options).
    Returns a :class:`DetectResult` (``.companions``, ``.document``, ``.result``).
    """
    return detect_files(list(files), Path(out), **options)


def simulate(
    scenario: str | PathLike,
    out: PathLike,
    *,
    seed: int = 0,
    full: bool = False,
    only: Sequence[str] = (),
) -> list[Any]:
    """Simulate raw ramps of a scenario (a built-in name: ``cal4481``, ``com1093``,
    ``go1843``, ``demo``; or a TOML file), as ``amigo simulate``: ``out/<stem>_uncal.fits``
    and ``out/<stem>_truth.json`` per exposure. ``full``: the program's numbers of
    integrations; ``only``: stems (prefixes) of the exposures to write. Returns the
    written exposures (``.uncal``, ``.truth``: paths)."""
    from amigo.errors import InputError
    from amigo.simulation.run import simulate_scenario
    from amigo.simulation.scenarios import load_scenario

    loaded = load_scenario(str(scenario))
    select = None
    if only:
        stems = [e.stem(loaded.program) for e in loaded.exposures]
        for prefix in only:
            if not any(s.startswith(prefix) for s in stems):
                raise InputError(None, f"--only {prefix!r} matches no exposure of {loaded.name}")

        def select(spec: Any) -> bool:
            return any(spec.stem(loaded.program).startswith(p) for p in only)

    return simulate_scenario(loaded, os.fspath(out), seed=seed, full=full, select=select)


def run(
    sci: Sequence[PathLike],
    cal: Sequence[PathLike],
    out: PathLike,
    *,
    model: PathLike | None = None,
    detector: str | None = None,
    knots: int | None = None,
    knot_spacing: float | None = None,
    rmax_mas: float = 1000.0,
    hmc: bool = True,
    superbias: Sequence[PathLike] = (),
    first_group: bool = True,
    force: bool = False,
) -> RunResult:
    """Raw ramps to companions, as ``amigo run``: :func:`process`, :func:`fit` and
    :func:`detect` into ``out``, each keeping what an earlier run left complete for the
    same inputs (``force`` redoes all three). ``superbias``: raw dark ramps, processed
    with the rest, whose reset levels let the first group's photons into the fit."""
    return run_files(
        [Path(p) for p in sci],
        [Path(p) for p in cal],
        Path(out),
        model=None if model is None else Path(model),
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        rmax_mas=rmax_mas,
        hmc=hmc,
        superbias=[Path(p) for p in superbias],
        first_group=first_group,
        force=force,
    )
