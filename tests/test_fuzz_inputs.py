"""Every reader, fed hostile variants of valid files (hypothesis), keeps its promise: it
returns, or raises InputError naming the file; never another exception, never a hang,
never a changed input, never a partial output (tests/fuzz_cases.py says how files are
damaged; docs/reliability.md what is promised).

The readers are those the commands call before any computation: ``amigo info``'s
identification, ``amigo process`` (whole, on small ramps: it writes a calslope file or
nothing), ``amigo fit``'s per-file reader (level-2 and calslope), ``amigo detect``'s
(calvis and OIFITS) and the base-model loader. ``benchmarks/fuzz_inputs.py`` runs the
same cases longer and prints their outcomes by kind.
"""

from __future__ import annotations

import contextlib
import signal
import warnings
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from amigo.errors import InputError
from fuzz_cases import Mutation, Rejected, apply, digest, fits_mutations, npz_mutations
from jwst_files import write_level2, write_uncal

#: Cases per seed in the test suite (the benchmark runs more: benchmarks/fuzz_inputs.py,
#: 1000 per kind in docs/reliability.md). 150 keeps every damage of fuzz_cases.py drawn
#: several times per kind within the CI budget (400 took 207 s of the suite's 2-core time).
EXAMPLES = 150
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=10),  # a hang is a failure, not a slow test
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,  # the same cases on every run: CI is reproducible
    database=None,
)


def _star(shape=(80, 80), peak=3.0e4) -> np.ndarray:
    y, x = np.mgrid[: shape[0], : shape[1]]
    return peak * np.exp(-((x - 40.3) ** 2 + (y - 39.6) ** 2) / (2 * 2.0**2)) + 5.0


def make_seeds(folder: Path) -> dict[str, Path]:
    """One small valid file of every kind amigo reads."""
    from amigo.model.base import BaseModel, BaseModelConfig, save_base_model
    from amigo.processing.ramps import process_file
    from detect_helpers import write_sim_calvis, write_sim_oifits

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    rate = _star()
    ramps = 10000.0 + np.cumsum(
        rng.poisson(np.broadcast_to(rate * 0.075, (4, 3, 80, 80))), axis=1
    ).astype(float)
    seeds = {
        "uncal": write_uncal(folder / "jw1_uncal.fits", np.minimum(ramps, 65535)),
        "cal": write_level2(folder / "jw2_cal.fits", rate, np.sqrt(rate) + 1.0),
        "calints": write_level2(
            folder / "jw3_calints.fits",
            np.stack([rate] * 3),
            np.stack([np.sqrt(rate) + 1.0] * 3),
        ),
        "calvis": write_sim_calvis(folder / "sim_calvis.fits", "F480M", [], rng),
        "oifits": write_sim_oifits(folder / "sim.oifits", rng, None),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seeds["calslope"], _ = process_file(seeds["uncal"], folder)
    model = BaseModel.create(BaseModelConfig(filters=("F480M",), n_wavelengths=3), linear=True)
    seeds["model"] = save_base_model(model, folder / "model.npz")
    return seeds


def _read_uncal(path: Path, out: Path) -> None:
    from amigo.io.identify import summarise
    from amigo.processing.ramps import process_file

    summarise(path)
    try:
        process_file(path, out)
    except InputError:
        # Nothing partial: no calslope, no temporary file.
        assert not any(out.iterdir()), sorted(p.name for p in out.iterdir())
        raise


def _read_for_fit(level: str):
    def read(path: Path, out: Path) -> None:
        from amigo.io.identify import summarise
        from amigo.pipeline._fit import _read_fit_exposure

        del out
        summarise(path)
        _read_fit_exposure(path, "science", level)

    return read


def _read_observables(path: Path, out: Path) -> None:
    from amigo.companions.observables import load
    from amigo.io.identify import summarise

    del out
    summarise(path)
    load(path)


def _read_model(path: Path, out: Path) -> None:
    from amigo.model.base import load_base_model, read_metadata

    del out
    read_metadata(path)
    load_base_model(path)


READERS = {
    "uncal": _read_uncal,
    "cal": _read_for_fit("level2"),
    "calints": _read_for_fit("level2"),
    "calslope": _read_for_fit("calslope"),
    "calvis": _read_observables,
    "oifits": _read_observables,
    "model": _read_model,
}


#: Seconds a reader may take on one small file before it counts as hanging.
CASE_SECONDS = 30.0
#: Seconds astropy may take to write a damaged variant (it takes milliseconds, or loops).
APPLY_SECONDS = 2.0


@contextlib.contextmanager
def time_limit(seconds: float, mutation: Mutation):
    """Raise ``TimeoutError`` naming ``mutation`` if the block runs longer than
    ``seconds`` (SIGALRM: the block is interrupted, not waited for)."""

    def alarm(signum, frame):
        raise TimeoutError(f"{mutation.describe()}: still running after {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(kind: str, seed: Path, mutation: Mutation, work: Path) -> str:
    """Apply ``mutation`` to ``seed``, run the kind's readers on it, check the promise;
    return ``accepted``, ``refused`` or ``not applicable``. Any broken promise raises."""
    case = work / seed.name
    out = work / "out"
    for stale in (case, *(out.iterdir() if out.exists() else ())):
        stale.unlink(missing_ok=True)
    out.mkdir(exist_ok=True)
    try:
        # astropy can loop for ever writing some damaged headers: the case is then skipped
        with time_limit(APPLY_SECONDS, mutation):
            apply(mutation, seed, case)
    except (Rejected, TimeoutError):
        return "not applicable"
    before = digest(case)
    try:
        with warnings.catch_warnings(), time_limit(CASE_SECONDS, mutation):
            warnings.simplefilter("ignore")
            READERS[kind](case, out)
        result = "accepted"
    except InputError as error:
        assert error.path is not None and Path(error.path).name == case.name, str(error)
        assert "\n" not in str(error), str(error)
        result = "refused"
    assert digest(case) == before, f"{mutation.describe()} changed the input"
    return result


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return make_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.mark.parametrize("kind", ["uncal", "cal", "calints", "calslope", "calvis", "oifits"])
def test_every_reader_keeps_its_promise_on_damaged_fits(kind, seeds, tmp_path):
    assert outcome(kind, seeds[kind], Mutation("keyword", 0, "TELESCOP"), tmp_path) == "accepted"

    @FUZZ
    @given(mutation=fits_mutations())
    def check(mutation: Mutation) -> None:
        outcome(kind, seeds[kind], mutation, tmp_path)

    check()


def test_the_model_loader_keeps_its_promise_on_damaged_archives(seeds, tmp_path):
    @FUZZ
    @given(mutation=npz_mutations())
    def check(mutation: Mutation) -> None:
        outcome("model", seeds["model"], mutation, tmp_path)

    check()


@pytest.mark.parametrize("kind", ["uncal", "cal", "calslope", "calvis", "oifits", "model"])
def test_not_a_regular_file_is_refused_without_blocking(kind, seeds, tmp_path):
    """A FIFO would block ``open()`` forever; a directory and an empty file are refused."""
    import os

    name = seeds[kind].name
    fifo = tmp_path / "fifo" / name
    fifo.parent.mkdir()
    os.mkfifo(fifo)
    folder = tmp_path / "dir" / name
    folder.mkdir(parents=True)
    empty = tmp_path / "empty" / name
    empty.parent.mkdir()
    empty.write_bytes(b"")
    out = tmp_path / "out"
    out.mkdir()
    for path, words in ((fifo, "FIFO"), (folder, "directory"), (empty, "")):
        with pytest.raises(InputError, match=words) as error:
            READERS[kind](path, out)
        assert error.value.path is not None and Path(error.value.path).name == name
