"""Shared fixtures: paths to the development data in ../shared (skipped when absent)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

#: The shared development data lives beside the repository; a user's clone has none.
SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
SHARED_DATA = SHARED / "data"

# Keep JAX on the CPU and quiet in tests, whatever machine runs them.
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# One persistent XLA compilation cache for the whole session, the `amigo` subprocesses
# included (they inherit the environment): many tests compile the same programs (the
# fitting engine, the ramp model at the same shapes), and on a 2-core CPU compiling is
# most of their time. Every program is kept, the small ones too: each process (two
# workers, dozens of `amigo` subprocesses) would otherwise compile the same element-wise
# operations again, at 0.3-1 s each. Set before JAX is imported; removed when the
# session ends.
_JAX_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _JAX_CACHE = tempfile.mkdtemp(prefix="amigo-tests-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _JAX_CACHE
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# amigo's own cache (latent bases, 10-16 s to build each) likewise: one folder for the
# session, shared by the workers and their `amigo` subprocesses, and nothing written to
# the home folder of whoever runs the tests. Tests of the cache itself set their own.
_AMIGO_CACHE = None
if "AMIGO_CACHE_DIR" not in os.environ:
    _AMIGO_CACHE = tempfile.mkdtemp(prefix="amigo-tests-cache-")
    os.environ["AMIGO_CACHE_DIR"] = _AMIGO_CACHE

# What the `amigo` command sets before JAX starts (amigo.runtime): the tests that run a
# command in this process and compare it with a child process (the Dask manifest) then
# run under the same XLA flags.
from amigo.runtime import configure_xla  # noqa: E402  (imports neither JAX nor NumPy)

configure_xla()


#: Tests slower than this are named, with their time, as they finish (a CI log that is cut
#: off at its time limit still shows where the time went; --durations prints only at the end).
SLOW_TEST_REPORT_S = 60.0
_CONFIG = None


def two_device_env() -> dict[str, str]:
    """The environment of a child process whose JAX has two CPU devices
    (``--xla_force_host_platform_device_count=2``; JAX reads the flag when it starts), the
    suite's own XLA flags kept (amigo.runtime's faster CPU compilation: a child compiled
    its programs in 35 s with them, 54 s without, 2-core AMD EPYC) and the tests' folder
    importable."""
    tests = os.path.dirname(os.path.abspath(__file__))
    flags = [os.environ.get("XLA_FLAGS", ""), "--xla_force_host_platform_device_count=2"]
    return {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": " ".join(flags).strip(),
        "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")]),
    }


def pytest_configure(config):
    global _CONFIG
    _CONFIG = config


def pytest_runtest_logreport(report):
    # Only the controlling process prints (xdist workers have no terminal of their own).
    if _CONFIG is None or hasattr(_CONFIG, "workerinput") or report.duration < SLOW_TEST_REPORT_S:
        return
    reporter = _CONFIG.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"[slow] {report.duration:7.1f} s {report.when:8} {report.nodeid}")


#: Seconds each of the longest test files takes on one worker (2-core AMD EPYC without
#: AVX-512, 2026-12-02 evening, -n 2, summed from a --junitxml report at 5e637c8;
#: the two workers' sums, 2136 s, against a wall time of 1100 s).
#: pytest-xdist (--dist loadfile) hands whole files to the two workers in collection
#: order, so a long file collected last runs alone at the end while the other worker
#: idles (the Dask manifest file, 513 s, did); collecting the longest first
#: (longest-processing-time-first scheduling) keeps both busy to the end. Only the order
#: depends on these figures: a stale or missing entry costs time, never a test (the
#: previous table, of 2026-11-28, had no entry for two files of 72 and 130 s and ranked
#: the level-2 training file, 204 s, at 84 s).
LONG_FILES_S = {
    "test_fit_outcomes.py": 203,
    "test_train_level2.py": 187,
    "test_manifest.py": 174,
    "test_companions_search.py": 142,
    "test_ramp_fit.py": 126,
    "test_newton.py": 123,
    "test_companions_posterior.py": 120,
    "test_cli_demo.py": 115,
    "test_calibration.py": 95,
    "test_first_group_cli.py": 93,
    "test_train_stripes.py": 74,
    "test_fuzz_inputs.py": 71,
    "test_cli_train.py": 66,
    "test_cli_detect.py": 49,
    "test_fit_synthetic.py": 47,
    "test_optics.py": 46,
    "test_interrupted.py": 36,
    "test_train_sharding.py": 36,
    "test_docs.py": 34,
    "test_api.py": 30,
    "test_dark_residual.py": 27,
    "test_stripes.py": 23,
    "test_ramp.py": 21,
    "test_basemodel.py": 20,
    "test_visibility.py": 19,
    "test_pipeline_slope.py": 15,
    "test_detector_linear.py": 13,
    "test_boundary_shift.py": 13,
    "test_basis.py": 11,
}


#: Files that compile the same programs as an earlier file of LONG_FILES_S and must not
#: start beside it. The two workers start with the first two files; had both been fits
#: of the small level-2 configuration (3 wavelengths, 27 x 27 knots), both would compile
#: it cold at once (measured: the per-filter outcomes and the Dask manifest, 350 -> 441 s
#: and 513 -> 542 s). Behind the demo (seventh of the long files in the table of
#: 2026-12-02 evening) the manifest starts minutes after the per-filter outcomes began,
#: and finds their programs in the suite's compilation cache.
AFTER = {"test_manifest.py": "test_cli_demo.py"}


def _file_order() -> dict[str, int]:
    """Rank of each long file: longest first, each file of AFTER moved behind its file."""
    names = sorted(LONG_FILES_S, key=lambda name: -LONG_FILES_S[name])
    for name, before in AFTER.items():
        names.remove(name)
        names.insert(names.index(before) + 1, name)
    return {name: rank for rank, name in enumerate(names)}


def pytest_collection_modifyitems(session, config, items):
    # A stable sort: the tests of a file keep their order (module fixtures, readability).
    rank = _file_order()
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_sessionfinish(session, exitstatus):
    for folder in (_JAX_CACHE, _AMIGO_CACHE):
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(
            f"development data not available: {path} (it lives in ../shared, beside the repo)"
        )
    return path


@pytest.fixture(scope="session")
def com1093_dir() -> Path:
    """Real COM 1093 level-2 files (AB Dor and HD 37093)."""
    return _require(SHARED_DATA / "jwst" / "com1093")


@pytest.fixture(scope="session")
def mirage_uncal() -> Path:
    """A MIRAGE-written uncal file (EXP_TYPE NIS_IMAGE, PUPIL NRM)."""
    return _require(SHARED_DATA / "jwst" / "mirage" / "jw00793001001_01101_00001_nis_uncal.fits")


@pytest.fixture(scope="session")
def oifits_dir() -> Path:
    """OIFITS files written by other pipelines."""
    return _require(SHARED_DATA / "oifits")


@pytest.fixture
def x64():
    """Run a test with 64-bit JAX (gradients vs finite differences, Hessians, HMC).

    A context, not a global switch, so that test order never changes precision.
    """
    import jax

    with jax.enable_x64(True):
        yield
