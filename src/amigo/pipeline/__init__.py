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
``amigo.run(sci, cal, "out")`` does process, fit and detect in one go,
``amigo.run_manifest("targets.toml", "out")`` many targets in parallel on Dask;
``amigo.train(cal_files, "model.npz")`` trains a base model on calibration exposures.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from amigo.cachedir import enable_compilation_cache
from amigo.pipeline._basis import BasisReport, bases
from amigo.pipeline._detect import DetectResult, detect
from amigo.pipeline._fit import FitResult, fit
from amigo.pipeline._manifest import ManifestResult, TargetOutcome, run_manifest
from amigo.pipeline._process import ProcessResult, process
from amigo.pipeline._run import RunResult, run
from amigo.pipeline._train import TrainResult, train
from amigo.runtime import configure_xla

PathLike = str | os.PathLike[str]

# Bitwise reproducible products, faster CPU compilation and programs with one source line
# per operation, where JAX has not started yet (amigo.runtime): before the cache, whose
# folder depends on the last.
configure_xla()
# Compiled programs persist between processes for the API as for the commands (the cache
# folder of :mod:`amigo.cachedir`; ``JAX_COMPILATION_CACHE_DIR=""`` turns it off).
enable_compilation_cache()

__all__ = [
    "BasisReport",
    "DetectResult",
    "FitResult",
    "ManifestResult",
    "ProcessResult",
    "RunResult",
    "TargetOutcome",
    "TrainResult",
    "bases",
    "detect",
    "fit",
    "open",
    "process",
    "run",
    "run_manifest",
    "simulate",
    "train",
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


def simulate(
    scenario: str | PathLike,
    out: PathLike,
    *,
    seed: int = 0,
    full: bool = False,
    only: Sequence[str] = (),
    noise_seed: int | None = None,
) -> list[Any]:
    """Simulate raw ramps of a scenario (a built-in name: ``cal4481``, ``com1093``,
    ``go1843``, ``demo``; or a TOML file), as ``amigo simulate``: ``out/<stem>_uncal.fits``
    and ``out/<stem>_truth.json`` per exposure. ``full``: the program's numbers of
    integrations; ``only``: stems (prefixes) of the exposures to write; ``noise_seed``:
    the exposures' noise from this seed, the telescope and detector from ``seed``.
    Returns the written exposures (``.uncal``, ``.truth``: paths)."""
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

    return simulate_scenario(
        loaded, os.fspath(out), seed=seed, full=full, select=select, noise_seed=noise_seed
    )
