"""``amigo train`` through the command line, on small calslope files written here.

The training runs call the command in this process (``amigo.cli.main``, what the console
script runs): the three runs of one test then share their compiled programs in memory,
where three interpreters would each trace and load them again (a training step's programs
take minutes to compile on a 2-core CPU). Bad inputs are checked in a subprocess, which
also proves that no traceback reaches the terminal.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from astropy.io import fits

from amigo.io.calslope import write_calslope
from amigo.likelihood.slopes import FlatParams, PointSourceParams, predict_slopes
from amigo.model.base import (
    BaseModel,
    BaseModelConfig,
    load_base_model,
    read_metadata,
    save_base_model,
)
from amigo.processing.ramps import ProcessSettings, SlopeProduct

SRC = str(Path(__file__).resolve().parents[1] / "src")
SHAPE = (16, 16)


def amigo_here(capsys, *args: str) -> tuple[int, str, str]:
    """``amigo *args`` in this process: (exit status, stdout, stderr)."""
    from amigo.cli import main

    capsys.readouterr()
    try:
        main(list(args))
        status = 0
    except SystemExit as exit_:
        status = exit_.code or 0
    printed = capsys.readouterr()
    return status, printed.out, printed.err


def train_here(capsys, *args: str) -> tuple[int, str]:
    """``amigo *args`` in this process: (exit status, what it wrote to stderr)."""
    status, _, stderr = amigo_here(capsys, *args)
    return status, stderr


def run_amigo(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": SRC, "JAX_PLATFORMS": "cpu"}
    env.pop("AMIGO_DEBUG", None)
    return subprocess.run(
        [sys.executable, "-m", "amigo", *args], capture_output=True, text=True, env=env, check=False
    )


def _write(path: Path, model_dn: np.ndarray, filter_name: str, seed: int) -> Path:
    """A calslope file holding noisy ``model_dn`` slopes with diagonal covariances."""
    rng = np.random.default_rng(seed)
    m, ny, nx = model_dn.shape
    var = 25.0 + np.abs(model_dn) / 20.0
    slopes = model_dn + rng.normal(size=model_dn.shape) * np.sqrt(var)
    cov = np.zeros((m, m, ny, nx))
    for g in range(m):
        cov[g, g] = var[g]
    product = SlopeProduct(
        slope_dn=slopes, slope_cov_dn2=cov, slope_support=np.full(slopes.shape, 20.0),
        ramp_dn=np.zeros((m + 1, ny, nx)), ramp_cov_dn2=np.zeros((m + 1, m + 1, ny, nx)),
        ramp_support=np.full((m + 1, ny, nx), 20.0), badpix=np.zeros((ny, nx), bool),
        badpix_reason=np.zeros((ny, nx), np.uint8), settings=ProcessSettings(), nints=20,
        n_sample=20, n_rejected_ramp=0, n_rejected_slope=0,
    )  # fmt: skip
    primary = fits.Header()
    primary["FILTER"] = filter_name
    primary["PUPIL"] = "NRM"
    return write_calslope(path, product, primary, fits.Header())


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("train")
    config = BaseModelConfig(filters=("F430M",), shape=SHAPE, n_wavelengths=9)
    truth = BaseModel.create(config, linear=True)
    cache = truth.pupil_cache()
    source = PointSourceParams(jnp.array([0.03, -0.02]), jnp.asarray(5e5))
    unit = truth.illuminance("F430M", source.position_arcsec, cache)
    star = np.asarray(predict_slopes(truth, source.flux_e * unit, 4), np.float64)
    flat = np.asarray(
        predict_slopes(truth, jnp.full((48, 48), FlatParams(jnp.asarray(2e4)).level_e / 9), 4)
    )
    return {
        "cal": _write(folder / "cal_calslope.fits", star, "F430M", 1),
        "flat": _write(folder / "flat_calslope.fits", flat.astype(np.float64), "CLEAR", 2),
        "val": _write(folder / "val_calslope.fits", star, "F430M", 3),
        "folder": folder,
    }


@pytest.mark.slow
def test_train_writes_a_model_with_its_record_and_resumes(files, capsys):
    # All three runs compute the optics on one pupil grid (192 samples, defocus by
    # angular spectrum): they compile the same programs, and the later runs reuse them.
    out = files["folder"] / "model.npz"
    optics = ["--pupil-npix", "192", "--defocus-method", "angular_spectrum"]
    args = ["train", "--cal", str(files["cal"]), "--flats", str(files["flat"]),
            "--val", str(files["val"]), "--out", str(out), "--steps", "2", "--stages", "1,1",
            "--batches", "1", *optics]  # fmt: skip
    status, stderr = train_here(capsys, *args)
    assert status == 0, stderr
    assert "Traceback" not in stderr
    model = load_base_model(out)
    assert not model.linear and model.config.shape == SHAPE
    assert (model.config.pupil_npix, model.config.defocus_method) == (192, "angular_spectrum")
    record = read_metadata(out)
    assert record["command"] == "amigo " + " ".join(args)  # as given, whoever called it
    assert record["data"]["calibration"][0]["name"] == "cal"
    assert record["data"]["flats"][0]["name"] == "flat"
    assert record["data"]["validation"][0]["name"] == "val"
    assert record["steps_done"] == 2 and record["dtype"] == "float32"
    assert len(record["history"]["loss"]) == 2
    checkpoint = out.with_name(out.name + ".ckpt.npz")
    assert checkpoint.is_file()
    status, stderr = train_here(capsys, *args, "--resume")
    assert status == 0, stderr
    assert "resumed" in stderr
    assert read_metadata(out)["history"] == record["history"]

    # Fine-tuning: training continues from the model, network included (no network-off
    # stage, no restart), and the new file records where it started ...
    # ... here from a model that computes its optics on the default grid (256 samples,
    # defocus in the pupil), brought to the finer settings by the flags, as a model
    # trained with older defaults is brought to the current ones.
    older = files["folder"] / "older.npz"
    save_base_model(
        model.with_config(pupil_npix=256, defocus_method="pupil"), older, {"date": "older"}
    )
    tuned_path = files["folder"] / "tuned.npz"
    tuned_args = [*args[:7], "--out", str(tuned_path), "--steps", "1", "--batches", "1"]
    status, stderr = train_here(
        capsys, *tuned_args, "--init", str(older), *optics, "--dark-current-prior", "0.5"
    )
    assert status == 0, stderr
    tuned_config = load_base_model(tuned_path).config
    assert (tuned_config.pupil_npix, tuned_config.defocus_method) == (192, "angular_spectrum")
    assert "fine-tuning the network" in stderr
    tuned_record = read_metadata(tuned_path)
    assert tuned_record["initial_model"]["path"] == str(older)
    assert tuned_record["initial_model"]["date"] == "older"
    assert tuned_record["initial_model"]["optics"]["pupil_npix"] == 256
    assert tuned_record["settings"]["init"] == str(older)
    assert tuned_record["settings"]["dark_current_prior"] == 0.5
    # The starting file is named by its digest too (its path may be overwritten later).
    digest = hashlib.sha256(older.read_bytes()).hexdigest()
    assert tuned_record["initial_model"]["sha256"] == digest
    assert tuned_record["history"]["stage"] == [1]
    # One Adam step moves each weight by at most about the learning rate (3e-3): the
    # network is the initial model's, not new random weights.
    start, tuned = model.ramp.network, load_base_model(tuned_path).ramp.network
    for a, b in zip(start.layers, tuned.layers, strict=True):
        assert float(jnp.max(jnp.abs(a.weight - b.weight))) <= 3.5e-3
        assert not np.array_equal(np.asarray(a.weight), np.asarray(b.weight))


def test_bad_inputs_exit_2_with_one_line(tmp_path, files, capsys):
    # One mistake in a child process: what reaches the terminal has no traceback. The
    # others in this process (each child would spend ~3 s starting Python and JAX).
    missing = run_amigo(
        "train", "--cal", str(tmp_path / "nope.fits"), "--out", str(tmp_path / "m.npz")
    )
    assert missing.returncode == 2
    assert "nope.fits" in missing.stderr and "Traceback" not in missing.stderr
    not_fits = tmp_path / "x_calslope.fits"
    not_fits.write_text("hello")

    def refused(*args: str) -> str:
        status, _, stderr = amigo_here(capsys, "train", *args, "--out", str(tmp_path / "m.npz"))
        assert status == 2, stderr
        assert "Traceback" not in stderr, stderr
        return stderr

    assert "x_calslope.fits" in refused("--cal", str(not_fits))
    assert "--stages" in refused("--cal", str(files["cal"]), "--steps", "3", "--stages", "1,1")
    nothing = refused("--cal", str(files["cal"]), "--steps", "0")
    assert "--steps" in nothing and "--init" in nothing
    assert "x_calslope.fits" in refused("--cal", str(files["cal"]), "--init", str(not_fits))
    assert "x_calslope.fits" in refused("--cal", str(files["cal"]), "--darks", str(not_fits))
    assert not (tmp_path / "m.npz").exists()
