"""`amigo fit` input handling (fast: nothing is fitted) and the level-2 reduction."""

from __future__ import annotations

import numpy as np
from astropy.io import fits
from click.testing import CliRunner

from amigo.cli import cli
from amigo.io.jwst import read_exposure
from amigo.likelihood.pixels import ImageData
from jwst_files import nominal_star, write_level2, write_uncal


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
    assert "c_cal.fits: is a level-2 image (cal), x_calslope.fits a raw-ramp product" in err
    assert "one level" in err and "Traceback" not in err and err.count("\n") == 1
    other = tmp_path / "y_calslope.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((2, 80, 80)), name="SLOPE")]).writeto(
        other
    )
    # The full detector needs a trained base model, not an instrument file.
    from amigo.model.image import Instrument, save_instrument

    instrument = tmp_path / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), instrument)
    args = ["fit", "--sci", str(calslope), "--cal", str(other), "--out", str(tmp_path / "o")]
    assert _run([*args, "--model", str(instrument), "--detector", "full"]) == 2
    err = capsys.readouterr().err
    assert "--detector full needs a trained base model" in err and "nominal.eqx" in err
    assert _run([*args, "--model", str(instrument), "--detector", "boundary"]) == 2
    err = capsys.readouterr().err
    assert "--detector boundary needs a trained base model" in err and err.count("\n") == 1
    # The physical account's strength is measured in group differences: not in level-2.
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    level2 = ["fit", "--sci", str(sci), "--cal", str(cal), "--out", str(tmp_path / "o")]
    assert _run([*level2, "--detector", "boundary"]) == 2
    err = capsys.readouterr().err
    assert "s_cal.fits: is a level-2 image: --detector boundary needs calslope" in err
    assert err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_uncal_and_one_file_in_both_roles_are_refused(tmp_path, capsys):
    uncal = write_uncal(tmp_path / "r_uncal.fits", np.zeros((1, 3, 80, 80)))
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)))
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    assert _run(["fit", "--sci", str(uncal), "--cal", str(cal), "--out", str(tmp_path)]) == 2
    assert "amigo process" in capsys.readouterr().err
    assert _run(["fit", "--sci", str(sci), "--cal", str(sci), "--out", str(tmp_path)]) == 2
    assert "is given both as --sci and --cal" in capsys.readouterr().err


def test_superbias_needs_calslope_inputs(tmp_path, capsys):
    """The first group exists only in raw-ramp products: --superbias with level-2 images
    is one line and exit 2, before anything is fitted or written."""
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)))
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    out = tmp_path / "o"
    args = ["fit", "--sci", str(sci), "--cal", str(cal), "--out", str(out)]
    other = write_level2(tmp_path / "d_cal.fits", np.ones((80, 80)))
    assert _run([*args, "--superbias", str(other)]) == 2
    err = capsys.readouterr().err
    assert "--superbias needs calslope inputs" in err and "d_cal.fits" in err
    assert "Traceback" not in err and not out.exists()
    # a fitted exposure cannot give its own reset level (its slopes would count twice)
    assert _run([*args, "--superbias", str(cal)]) == 2
    err = capsys.readouterr().err
    assert "both as --superbias and as --sci/--cal" in err and "c_cal.fits" in err


def test_help_lists_the_options():
    result = CliRunner().invoke(cli, ["fit", "--help"])
    assert result.exit_code == 0
    for option in ("--sci", "--cal", "--out", "--model", "--detector", "--superbias"):
        assert option in result.output


def test_calints_are_averaged_with_errors_of_the_mean(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.normal(100.0, 1.0, (4, 80, 80))
    err = np.full_like(data, 2.0)
    dq = np.zeros(data.shape, np.uint32)
    dq[1, 40, 40] = 1  # DO_NOT_USE in one integration
    dq[2, 41, 41] = 2  # SATURATED in one: a slope of fewer groups than NGROUPS
    dq[:, 42, 42] = 2  # SATURATED in all
    path = write_level2(tmp_path / "a_calints.fits", data, err, dq)
    image = ImageData.from_exposure(read_exposure(path))
    assert image.n_integrations == 4
    np.testing.assert_allclose(image.data[50, 50], data[:, 50, 50].mean(), rtol=1e-6)
    np.testing.assert_allclose(image.error[50, 50], 1.0, rtol=1e-6)  # 2 / sqrt(4)
    for (y, x), kept in (((40, 40), [0, 2, 3]), ((41, 41), [0, 1, 3])):
        np.testing.assert_allclose(image.data[y, x], data[kept, y, x].mean(), rtol=1e-6)
        np.testing.assert_allclose(image.error[y, x], 2 / np.sqrt(3), rtol=1e-6)
    assert not image.mask[42, 42]
    assert not image.mask[:4].any()  # reference rows


def test_several_files_after_one_flag_or_the_flag_repeated(tmp_path, capsys):
    """``--sci A B --cal C D`` (the README's syntax, shell globs) and ``--sci A --sci B``
    both give every file to the command: the raw ramp given second is found and refused
    by name, not rejected by the parser as an extra argument."""
    uncal = write_uncal(tmp_path / "r_uncal.fits", np.zeros((1, 3, 80, 80)))
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    cal = [write_level2(tmp_path / f"c{i}_cal.fits", np.ones((80, 80))) for i in range(2)]
    out = str(tmp_path / "o")
    spellings = [
        ["--sci", str(sci), str(uncal), "--cal", *map(str, cal), "--out", out],
        ["--cal", *map(str, cal), "--sci", str(sci), str(uncal), "--out", out],
        ["--sci", str(sci), "--sci", str(uncal), "--cal", str(cal[0]), "--out", out],
    ]
    for args in spellings:
        assert _run(["fit", *args]) == 2
        err = capsys.readouterr().err
        assert "r_uncal.fits" in err and "amigo process" in err, err
        assert "unexpected extra argument" not in err
    assert not (tmp_path / "o").exists()
    # `amigo run` takes the same syntax (here refused for the level-2 file it is given).
    assert _run(["run", "--sci", str(sci), str(cal[0]), "--cal", str(cal[1]), "--out", out]) == 2
    assert "unexpected extra argument" not in capsys.readouterr().err


def test_the_same_star_as_science_and_calibrator_stays_two_targets(tmp_path):
    """The null test (one visit of a star against another): the calibrator exposures get
    their own target, named with their observation; other calibrators keep their names."""
    from amigo.fitting.filter_fit import FitExposure
    from amigo.pipeline._fit import key_targets

    def item(name, role, observation, target="HD-37093"):
        path = write_level2(
            tmp_path / name,
            np.ones((80, 80)),
            overrides={"TARGPROP": target, "OBSERVTN": observation},
        )
        meta = read_exposure(path).meta
        return FitExposure(
            name, role, meta.target, ImageData.from_exposure(read_exposure(path))
        ), meta

    items = [
        item("a_cal.fits", "science", "016"),
        item("b_cal.fits", "calibrator", "015"),
        item("c_cal.fits", "calibrator", "018", target="HD-36805"),
    ]
    keyed = key_targets(items)
    assert [e.target for e, _ in keyed] == ["HD-37093", "HD-37093 (cal obs 015)", "HD-36805"]
    assert [e.role for e, _ in keyed] == ["science", "calibrator", "calibrator"]


def test_level2_images_default_to_the_shipped_real_data_model(tmp_path, monkeypatch):
    """Level-2 images take the model trained on real level-2 calibrators when one is
    shipped (with its detector unless --detector linear), the nominal instrument with the
    linear detector otherwise; calslope files keep the simulated-ramp model."""
    import equinox as eqx
    import jax.numpy as jnp

    import amigo.model.base as basemodel
    from amigo.model.base import BaseModel, BaseModelConfig, save_base_model
    from amigo.pipeline._fit import _fit_model

    config = BaseModelConfig(filters=("F480M",), n_wavelengths=3, pupil_npix=64)
    model = BaseModel.create(config).for_level2()
    model = eqx.tree_at(lambda m: m.defocus_nm["F480M"], model, jnp.asarray(30.0))
    path = save_base_model(model, tmp_path / "real.npz", {"trained_on": "real: test"})
    monkeypatch.setattr(basemodel, "level2_model_path", lambda: None)
    nominal = _fit_model(None, None, "level2")
    assert nominal.base is None and nominal.detector == "linear"
    monkeypatch.setattr(basemodel, "level2_model_path", lambda: path)
    real = _fit_model(None, None, "level2")  # a model made for level 2: its detector
    assert real.detector == "full" and real.base.config.data_level == "level2"
    assert float(real.instrument("F480M").optics.defocus_nm) == 30.0
    # What fit_summary.json's "model" says (it once held the detector's repr): the file,
    # its version (format, training date, amigo's version) and what it was trained on.
    from amigo.model.base import read_metadata

    record = read_metadata(path)
    name = real.instrument("F480M").name
    assert name == (
        f"real.npz (format {record['format_version']}, trained ? with amigo ? on real) "
        "(F480M; full detector)"
    ), name  # "?": what a model saved by save_base_model alone does not record
    linear = _fit_model(None, "linear", "level2")
    assert linear.detector == "linear" and linear.base is None
    assert float(linear.instrument("F480M").optics.defocus_nm) == 30.0
    ramp = _fit_model(None, None, "calslope")
    assert ramp.base.config.data_level == "ramp"


def test_images_without_a_star_are_named_for_what_they_show():
    """A dark (no flux), a flat field (flux, no peak) and a hot pixel on an empty image
    (a peak holding all the flux) are not stars; a star through the mask is, with its
    1-2 % of the flux in the brightest pixel."""
    from amigo.pipeline._fit import star_problem

    rng = np.random.default_rng(4)
    error = np.full((80, 80), 2.0)
    mask = np.ones((80, 80), bool)

    def problem(data):
        return star_problem(ImageData(data=data, error=error, mask=mask, n_integrations=1))

    noise = 2.0 * rng.standard_normal((80, 80))
    assert "total flux is" in problem(noise)
    assert "brightest pixel stands" in problem(100.0 + noise)
    hot = noise.copy()
    hot[40, 40] = 1e6
    assert "% of the image's flux is in one pixel" in problem(hot)
    y, x = np.mgrid[:80, :80]
    star = 3e3 * np.exp(-((x - 40.0) ** 2 + (y - 40.0) ** 2) / (2 * 4.0**2))  # 1 % at peak
    assert problem(star + noise) is None


def test_a_file_given_twice_or_a_filter_without_calibrator_alone_is_refused(tmp_path, capsys):
    """Exposures are known by their file names: the same file twice (its pixels counted
    twice), or two files of one name, is one line and exit 2. A science filter without a
    calibrator, when no other filter can be fitted, is a bad input too (with another
    filter fitted it is that filter's failure instead: tests/test_fit_outcomes.py)."""
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)))
    sci = write_level2(tmp_path / "s_cal.fits", np.ones((80, 80)))
    out = tmp_path / "o"
    assert _run(["fit", "--sci", str(sci), str(sci), "--cal", str(cal), "--out", str(out)]) == 2
    assert "s_cal.fits: is given twice" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    twin = write_level2(tmp_path / "other" / "c_cal.fits", np.ones((80, 80)))
    assert _run(["fit", "--sci", str(sci), "--cal", str(cal), str(twin), "--out", str(out)]) == 2
    assert "has the same name as" in capsys.readouterr().err
    star = nominal_star("F430M")
    sci = write_level2(tmp_path / "star_cal.fits", star)
    blue = write_level2(tmp_path / "b_cal.fits", star, overrides={"FILTER": "F380M"})
    assert _run(["fit", "--sci", str(sci), "--cal", str(blue), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "star_cal.fits: no calibrator exposure in F430M" in err and "Traceback" not in err
    assert not out.exists()


def test_a_calibrators_visits_may_differ_in_roll_a_science_targets_may_not():
    """The roll check holds a science target's exposures to 0.1 deg (its visibilities
    rotate with the sky); a calibrator's visits, a point source's, may drift apart."""
    from types import SimpleNamespace

    import pytest

    from amigo.errors import InputError
    from amigo.pipeline._fit import _check_orientations

    def item(role: str, pa: float):
        meta = SimpleNamespace(
            path=f"{role}_{pa}.fits",
            target="STAR",
            filter="F480M",
            orientation=SimpleNamespace(pa_aper_deg=pa),
        )
        return SimpleNamespace(role=role, target="STAR"), meta

    _check_orientations([item("calibrator", 171.98), item("calibrator", 172.55)])
    with pytest.raises(InputError, match=r"roll angles 0\.57 deg apart"):
        _check_orientations([item("science", 171.98), item("science", 172.55)])
