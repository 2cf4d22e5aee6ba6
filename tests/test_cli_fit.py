"""`amigo fit` input handling (fast: nothing is fitted) and the level-2 reduction."""

from __future__ import annotations

import numpy as np
from astropy.io import fits
from click.testing import CliRunner

from amigo.cli import cli
from amigo.io.jwst import read_exposure
from amigo.likelihood import ImageData
from jwst_files import write_level2, write_uncal


def _run(args):
    from amigo.cli import main

    try:
        main(args)
    except SystemExit as exit_:
        return exit_.code
    return 0


def test_calslope_mixed_with_level2_or_full_detector_without_base_model_is_refused(
    tmp_path, capsys
):
    calslope = tmp_path / "x_calslope.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((2, 80, 80)), name="SLOPE")]).writeto(
        calslope
    )
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)))
    code = _run(["fit", "--sci", str(calslope), "--cal", str(cal), "--out", str(tmp_path / "o")])
    assert code == 2
    err = capsys.readouterr().err
    assert "mixing" in err and "Traceback" not in err
    other = tmp_path / "y_calslope.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((2, 80, 80)), name="SLOPE")]).writeto(
        other
    )
    # The full detector needs a trained base model, not an instrument file.
    from amigo.model import Instrument, save_instrument

    instrument = tmp_path / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), instrument)
    args = ["fit", "--sci", str(calslope), "--cal", str(other), "--out", str(tmp_path / "o")]
    assert _run([*args, "--model", str(instrument), "--detector", "full"]) == 2
    err = capsys.readouterr().err
    assert "--detector full needs a trained base model" in err and "nominal.eqx" in err
    assert not (tmp_path / "o").exists()


def test_uncal_and_detector_full_are_refused(tmp_path, capsys):
    uncal = write_uncal(tmp_path / "r_uncal.fits", np.zeros((1, 3, 80, 80)))
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)))
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    assert _run(["fit", "--sci", str(uncal), "--cal", str(cal), "--out", str(tmp_path)]) == 2
    assert "amigo process" in capsys.readouterr().err
    args = [
        "fit",
        "--sci",
        str(sci),
        "--cal",
        str(cal),
        "--out",
        str(tmp_path),
        "--detector",
        "full",
    ]
    assert _run(args) == 2
    err = capsys.readouterr().err
    assert "--detector full is not available for level-2 images" in err
    assert _run(["fit", "--sci", str(sci), "--cal", str(sci), "--out", str(tmp_path)]) == 2


def test_help_lists_the_options():
    result = CliRunner().invoke(cli, ["fit", "--help"])
    assert result.exit_code == 0
    for option in ("--sci", "--cal", "--out", "--model", "--detector"):
        assert option in result.output


def test_calints_are_averaged_with_errors_of_the_mean(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.normal(100.0, 1.0, (4, 80, 80))
    err = np.full_like(data, 2.0)
    dq = np.zeros(data.shape, np.uint32)
    dq[1, 40, 40] = 1  # DO_NOT_USE in one integration
    path = write_level2(tmp_path / "a_calints.fits", data, err, dq)
    image = ImageData.from_exposure(read_exposure(path))
    assert image.n_integrations == 4
    np.testing.assert_allclose(image.data[50, 50], data[:, 50, 50].mean(), rtol=1e-6)
    np.testing.assert_allclose(image.error[50, 50], 1.0, rtol=1e-6)  # 2 / sqrt(4)
    used = data[[0, 2, 3], 40, 40]
    np.testing.assert_allclose(image.data[40, 40], used.mean(), rtol=1e-6)
    np.testing.assert_allclose(image.error[40, 40], 2 / np.sqrt(3), rtol=1e-6)
    assert not image.mask[:4].any()  # reference rows
