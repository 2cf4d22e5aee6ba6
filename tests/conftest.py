"""Shared fixtures: paths to the development data in ../shared (skipped when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

#: The shared development data lives beside the repository; a user's clone has none.
SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
SHARED_DATA = SHARED / "data"

# Keep JAX on the CPU and quiet in tests, whatever machine runs them.
os.environ.setdefault("JAX_PLATFORMS", "cpu")


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
