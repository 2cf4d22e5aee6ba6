"""Training on the pipeline's level-2 images (issue 22, item 2).

Function level: the reader turns a level-2 image into one "slope" per pixel; the model
compares it with the pipeline's estimator applied to the model's ramp, which must equal
stcal's own fit of that ramp (the independent reference); the model behind the pipeline
keeps what it learnt. Command line: ``amigo train`` on real COM 1093 calibrator files
(../shared), the model file and the loss curve it writes, and the inputs it refuses.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from astropy.io import fits

from amigo import niriss
from amigo.errors import InputError
from amigo.likelihood.slopes import PointSourceParams, SlopeData, point_source_slopes
from amigo.model.base import BaseModel, BaseModelConfig, load_base_model, read_metadata
from amigo.model.detector.pipeline_slope import MODEL_READ_NOISE_CDS_DN
from amigo.model.optics import cast
from jwst_files import write_level2
from test_cli_train import _write, amigo_here, run_amigo
from test_pipeline_slope import _stcal

TGROUP = 0.07544
SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
CALIBRATORS = SHARED / "data" / "jwst" / "com1093-calibrators"


def _image(rng) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[:80, :80]
    rate = 50.0 + 2e4 * np.exp(-((xx - 40.3) ** 2 + (yy - 39.6) ** 2) / 18.0)
    rate += rng.normal(0.0, 3.0, rate.shape)
    return rate, np.sqrt(np.abs(rate) / 30.0 + 4.0)


def test_a_level2_file_becomes_one_slope_per_pixel(tmp_path):
    rate, err = _image(np.random.default_rng(1))
    dq = np.zeros((80, 80), np.uint32)
    dq[40, 40] = 2  # SATURATED: its slope came from fewer groups than NGROUPS
    dq[10, 12] = 1  # DO_NOT_USE
    path = write_level2(
        tmp_path / "jw_star_cal.fits", rate, err, dq, overrides={"NGROUPS": 7, "FILTER": "F480M"}
    )
    data = SlopeData.read(path, "calibrator")
    assert data.level2 and data.ngroups == 7 and data.nframes == 1
    assert data.group_time_s == pytest.approx(TGROUP)
    assert data.name == "jw_star" and data.filter == "F480M"
    assert data.slopes_dn.shape == (1, 80, 80)
    used = np.asarray(data.used) > 0
    expected = ~niriss.reference_row_mask(80, 80)
    expected[40, 40] = expected[10, 12] = False
    np.testing.assert_array_equal(used, expected)
    assert data.n_values == int(expected.sum())
    np.testing.assert_allclose(
        np.asarray(data.slopes_dn[0])[used], (rate * TGROUP)[used], rtol=1e-6
    )
    whitening = np.asarray(data.whitening).reshape(80, 80)
    np.testing.assert_allclose(whitening[used], 1.0 / (err * TGROUP)[used], rtol=1e-6)
    assert not whitening[~used].any()
    with pytest.raises(InputError, match="calslope"):
        SlopeData.read(path, "flat")
    mjy = write_level2(tmp_path / "mjy_cal.fits", rate, err)
    with fits.open(mjy, mode="update") as hdul:
        hdul["SCI"].header["BUNIT"] = "MJy/sr"  # a photometrically calibrated image
    with pytest.raises(InputError, match="PHOTMJSR is missing"):
        SlopeData.read(mjy, "calibrator")


@pytest.fixture(scope="module")
def bent_model() -> tuple[BaseModel, SlopeData, PointSourceParams]:
    """A small linear-network model with a strong classical non-linearity (so that the
    ramp bends and the pipeline's slope differs from the mean group difference), and a
    level-2 exposure of 8 groups."""
    config = BaseModelConfig(filters=("F480M",), shape=(80, 80), n_wavelengths=3, pupil_npix=64)
    base = BaseModel.create(config, linear=True)
    base = eqx_set_nonlinearity(base, -2e-6)
    rate, err = _image(np.random.default_rng(2))
    used = np.ones((80, 80), bool)
    data = SlopeData.from_rate_image(rate, err, used, ngroups=8, group_time_s=TGROUP)
    return base, data, PointSourceParams(jnp.array([0.02, -0.01]), jnp.asarray(2e6))


def eqx_set_nonlinearity(base: BaseModel, value: float) -> BaseModel:
    import equinox as eqx

    return eqx.tree_at(
        lambda m: m.read.nonlinearity, base, jnp.full_like(base.read.nonlinearity, value)
    )


def _model_image_and_ramp(base, data, source):
    """The level-2 model image of ``data`` ((ny, nx) DN per group), the model ramp's
    group differences and the ramp itself (from 0), in float64."""
    cache = base.pupil_cache()
    with jax.enable_x64(True):
        level2 = np.asarray(point_source_slopes(base, cache, source, data), np.float64)[0]
        ramp_kind = dataclasses.replace(data, level2=False)
        differences = np.asarray(point_source_slopes(base, cache, source, ramp_kind), np.float64)
    ramp = np.concatenate([np.zeros((1, *differences.shape[1:])), np.cumsum(differences, axis=0)])
    return level2, differences, ramp


def _stcal_slope(ramp: np.ndarray, gain: float) -> dict:
    """stcal's ramp fit of one integration's model ramp ((groups, 80, 80) DN, no flags),
    at the model's read noise and gain."""
    rate, _ = _stcal(
        ramp[None],
        np.zeros((1, *ramp.shape), bool),
        tgroup=TGROUP,
        tframe=TGROUP,
        nframes=1,
        groupgap=0,
        read_noise=np.full((80, 80), MODEL_READ_NOISE_CDS_DN),
        gain=np.full((80, 80), gain),
    )
    return rate


def test_the_model_image_is_stcal_s_fit_of_the_model_ramp(bent_model):
    base, data, source = bent_model
    level2, differences, ramp = _model_image_and_ramp(base, data, source)
    assert differences.shape == (7, 80, 80)
    rate = _stcal_slope(ramp, base.read.gain_e_per_dn)
    bright = differences.mean(axis=0) > 20.0
    assert bright.sum() > 50
    np.testing.assert_allclose(level2[bright] / TGROUP, rate["slope"][bright], rtol=2e-5)
    # The classical non-linearity bends the ramp by a quadratic, and the pipeline's weights
    # are symmetric about the ramp's middle: its slope is the chord's, the mean difference
    # (docs/pipeline_slope.md), whereas the differences themselves fall along the ramp.
    mean = differences.mean(axis=0)
    np.testing.assert_allclose(level2[bright], mean[bright], rtol=1e-5)
    assert np.all(differences[-1][bright] < (1 - 5e-4) * differences[0][bright])


def test_a_newer_pipelines_charge_migration_is_followed(tmp_path, bent_model):
    """A level-2 file the charge-migration step ran on (``S_CHGMIG = 'COMPLETE'``, jwst
    >= 1.12) had its groups above 25,000 DN left out of the ramp fit: the model's ramp is
    fitted over the same groups, in training (SlopeData) and in fits (Level2Input); a
    file without the keyword (COM 1093's CAL_VER 1.5.3) over all of them."""
    from amigo.model.detector.pipeline_slope import charge_loss_groups
    from amigo.pipeline._fit import _read_fit_exposure

    rate, err = _image(np.random.default_rng(3))
    rate = rate * 5.0  # peak 1e5 DN/s: 7,500 DN a group, over 25,000 DN by the 4th of 8
    overrides = {"NGROUPS": 8, "FILTER": "F480M"}
    old = write_level2(tmp_path / "old_cal.fits", rate, err, overrides=overrides)
    new = write_level2(
        tmp_path / "new_cal.fits", rate, err, overrides={**overrides, "S_CHGMIG": "COMPLETE"}
    )
    expected = charge_loss_groups(rate, 8, TGROUP, TGROUP)
    assert expected.min() == 3 and 5 < np.sum(expected < 8) < 200
    assert SlopeData.read(old, "calibrator").groups_used is None
    data = SlopeData.read(new, "calibrator")
    np.testing.assert_array_equal(np.asarray(data.groups_used), expected)
    assert _read_fit_exposure(old, "science", "level2").ramp.groups_used is None
    fitted = _read_fit_exposure(new, "science", "level2").ramp
    np.testing.assert_array_equal(fitted.groups_used, expected)
    # what amigo fit says of it: a line on the terminal, and fit_summary.json's record
    from types import SimpleNamespace

    from amigo.pipeline._fit import _charge_loss_note, _detector_record

    n_cut = int(np.sum((expected < 8) & fitted.data.mask))
    assert _charge_loss_note(fitted).startswith(
        f"the pipeline's charge-migration step cut the ramps of {n_cut} pixels (to 3-7 of 8 "
        "groups; threshold 25,000 DN, the step's default in jwst (version unknown))"
    )

    detector = SimpleNamespace(
        inputs={"new": fitted}, detector_amplitudes={}, migration_amplitudes={},
        pattern_amplitudes={}, added_sigma_dn_s={},
    )  # fmt: skip
    assert _detector_record(detector, "new") == {"charge_loss_pixels": n_cut}

    # the model image: stcal's fit of the model ramp over those groups
    base, _, source = bent_model
    level2, differences, ramp = _model_image_and_ramp(base, data, source)
    flags = np.arange(8)[:, None, None] >= expected[None]
    stcal_rate, _ = _stcal(
        ramp[None], flags[None], tgroup=TGROUP, tframe=TGROUP, nframes=1, groupgap=0,
        read_noise=np.full((80, 80), MODEL_READ_NOISE_CDS_DN),
        gain=np.full((80, 80), base.read.gain_e_per_dn), chargeloss=True,
    )  # fmt: skip
    bright = differences.mean(axis=0) > 20.0
    np.testing.assert_allclose(level2[bright] / TGROUP, stcal_rate["slope"][bright], rtol=2e-5)
    # and the Level2Input's correction is the same estimate, less the linear image
    linear = differences.mean(axis=0) / TGROUP
    correction = fitted.correction(differences, linear)
    np.testing.assert_allclose((correction + linear)[bright], level2[bright] / TGROUP, rtol=1e-5)


def test_the_steps_threshold_follows_the_pipeline_version_and_a_cut_of_nothing_is_none(tmp_path):
    """The step's default threshold was 30,000 DN in jwst 1.12.0-1.12.1 and is 25,000 DN
    since (its spec in each version); a file on which its rule cuts nothing (a faint
    star, or 2 groups) is fitted as a file without the step (``None``: one program)."""
    from amigo.io.jwst import read_exposure
    from amigo.likelihood.pixels import charge_loss_threshold_dn, pipeline_groups
    from amigo.model.detector.pipeline_slope import charge_loss_groups

    assert charge_loss_threshold_dn("1.12.0") == charge_loss_threshold_dn("1.12.1") == 30000.0
    for version in ("1.12.2", "1.14.0", "1.20.2", "2.0", "", "unknown"):
        assert charge_loss_threshold_dn(version) == 25000.0
    rate, err = _image(np.random.default_rng(4))
    rate = rate * 5.0
    step = {"NGROUPS": 8, "FILTER": "F480M", "S_CHGMIG": "COMPLETE"}
    for version, threshold in (("1.12.1", 30000.0), ("1.16.0", 25000.0)):
        path = write_level2(
            tmp_path / f"v{version}_cal.fits", rate, err, overrides={**step, "CAL_VER": version}
        )
        expected = charge_loss_groups(rate, 8, TGROUP, TGROUP, threshold_dn=threshold)
        np.testing.assert_array_equal(pipeline_groups(read_exposure(path)).groups, expected)
    assert not np.array_equal(
        charge_loss_groups(rate, 8, TGROUP, TGROUP, threshold_dn=30000.0),
        charge_loss_groups(rate, 8, TGROUP, TGROUP),
    )
    faint = write_level2(tmp_path / "faint_cal.fits", rate / 10.0, err, overrides=step)
    short = write_level2(tmp_path / "short_cal.fits", rate, err, overrides={**step, "NGROUPS": 2})
    nothing = pipeline_groups(read_exposure(faint))
    assert nothing.groups is None and nothing.threshold_dn == 25000.0
    assert pipeline_groups(read_exposure(short)) is None  # the step leaves 2 groups alone


def test_the_threshold_a_files_poisson_variance_shows(tmp_path):
    """The step's threshold may come from a CRDS parameter file, which the level-2 file
    does not record; its VAR_POISSON does (the ramp fit's photon variance is
    ``R / (g TGROUP (n - 1))`` over the ``n`` groups it fitted, stcal). A file cut at
    30,000 DN where its version's default is 25,000 is cut as its VAR_POISSON says, with
    5 % scatter on it; one cut at the default keeps the default."""
    from amigo.io.jwst import read_exposure
    from amigo.likelihood.pixels import pipeline_groups
    from amigo.model.detector.pipeline_slope import charge_loss_groups

    rng = np.random.default_rng(7)
    rate, err = _image(rng)
    rate = rate * 5.0
    nints, ngroups = 20, 8
    step = {"NGROUPS": ngroups, "NINTS": nints, "FILTER": "F480M", "S_CHGMIG": "COMPLETE"}
    for true_threshold in (30000.0, 25000.0):
        n = charge_loss_groups(rate, ngroups, TGROUP, TGROUP, threshold_dn=true_threshold)
        assert not np.array_equal(
            n,
            charge_loss_groups(
                rate, ngroups, TGROUP, TGROUP, 1, 3e4 if true_threshold < 3e4 else 2.5e4
            ),
        )
        variance = np.clip(rate, 1.0, None) / (niriss.GAIN_E_PER_DN * TGROUP * (n - 1) * nints)
        variance *= 1.0 + 0.05 * rng.standard_normal(variance.shape)
        path = write_level2(
            tmp_path / f"t{true_threshold:.0f}_cal.fits", rate, err,
            overrides={**step, "CAL_VER": "1.16.0"},
        )  # fmt: skip
        with fits.open(path, mode="update") as hdul:
            hdul.append(fits.ImageHDU(variance.astype(np.float32), name="VAR_POISSON"))
        groups = pipeline_groups(read_exposure(path))
        np.testing.assert_array_equal(groups.groups, n)
        if true_threshold == 25000.0:
            assert groups.threshold_dn == 25000.0 and "default" in groups.source
        else:
            assert groups.source == "the file's VAR_POISSON"
            cut_the_same = charge_loss_groups(
                rate, ngroups, TGROUP, TGROUP, threshold_dn=groups.threshold_dn
            )
            np.testing.assert_array_equal(cut_the_same, n)


def test_saturated_and_flagged_pixels_cut_their_neighbours_as_the_step_does(tmp_path):
    """The step reads the ramps, not the pixel DQ: a saturated pixel (its later groups,
    or all of them, over 25,000 DN) cuts its four neighbours as any bright pixel does.
    The groups amigo takes (:func:`pipeline_groups`) against the step's rule applied to
    the ramps themselves, written out here: a partly saturated peak (SATURATED, its
    value the slope of the groups before), a pixel saturated from its first group (NaN,
    SATURATED + DO_NOT_USE), and a bright pixel flagged DO_NOT_USE with a value."""
    from amigo.io.jwst import read_exposure
    from amigo.likelihood.pixels import pipeline_groups
    from test_pipeline_slope import _charge_migration_flags

    ngroups = 8
    yy, xx = np.mgrid[:80, :80]
    rate = 50.0 + 1e5 * np.exp(-((xx - 40.0) ** 2 + (yy - 40.0) ** 2) / 6.0)  # DN/s
    rate[20, 20] = 1e6  # over 25,000 DN in its first group
    rate[60, 30] = 9e4  # a hot pixel flagged DO_NOT_USE, its value kept
    ramps = (rate[None] * (np.arange(ngroups)[:, None, None] + 1) * TGROUP)[None]
    flags = _charge_migration_flags(ramps)[0]
    expected = np.maximum(np.sum(~flags, axis=0), 2)
    saturation = 40000.0  # DN: the peak saturates from its 6th group on
    sci, dq = rate.copy(), np.zeros((80, 80), np.uint32)
    dq[ramps[0].max(axis=0) > saturation] |= 2
    dq[20, 20] |= 1
    sci[20, 20] = np.nan
    dq[60, 30] |= 1
    assert dq[40, 40] == 2 and np.sum(dq == 2) >= 1
    path = write_level2(
        tmp_path / "sat_cal.fits", sci, np.sqrt(np.abs(rate) / 30.0 + 4.0), dq,
        overrides={"NGROUPS": ngroups, "FILTER": "F480M", "S_CHGMIG": "COMPLETE"},
    )  # fmt: skip
    used = pipeline_groups(read_exposure(path)).groups
    for y, x in ((19, 20), (21, 20), (20, 19), (20, 21), (60, 31), (41, 40), (40, 39)):
        assert used[y, x] == expected[y, x] < ngroups, (y, x)
    np.testing.assert_array_equal(used, expected)


def test_the_flat_behind_a_model_and_behind_an_image(tmp_path):
    """A level-2 model's residual sensitivity stands behind the flat its calibrators were
    divided by: training records each calibrator's R_FLAT, and ``amigo fit`` names an
    image divided by another flat of that filter (one line; nothing where the model
    records no flat, as the shipped COM 1093 model, trained before the record existed)."""
    from types import SimpleNamespace

    from amigo.pipeline._fit import FitModel, _flat_reference_note, _flat_references

    rate, err = _image(np.random.default_rng(5))
    flat = {"FILTER": "F480M", "S_FLAT": "COMPLETE", "R_FLAT": "crds://jwst_niriss_flat_0277.fits"}
    path = write_level2(tmp_path / "flat_cal.fits", rate, err, overrides=flat)
    data = SlopeData.read(path, "calibrator")
    assert data.flat_reference == "jwst_niriss_flat_0277.fits"
    assert data.layout().flat_reference == ""  # not part of a compiled program's key
    unflat = write_level2(
        tmp_path / "unflat_cal.fits", rate, err, overrides={**flat, "S_FLAT": "SKIPPED"}
    )
    assert SlopeData.read(unflat, "calibrator").flat_reference == ""
    from amigo.training.data import TrainingData

    described = TrainingData(cal=[data], flats=[], val=[]).describe()
    assert described["calibration"][0]["flat_reference"] == "jwst_niriss_flat_0277.fits"

    record = {"data": described}
    refs = _flat_references(record)
    assert refs == {"F480M": ("jwst_niriss_flat_0277.fits",)}
    model = FitModel(lambda f: None, object(), "full", "m", refs)
    newer = SimpleNamespace(filter="F480M", flat_reference="jwst_niriss_flat_0301.fits")
    note = _flat_reference_note(model, newer)
    assert note is not None and "0301" in note and "behind jwst_niriss_flat_0277.fits" in note
    same = SimpleNamespace(filter="F480M", flat_reference="jwst_niriss_flat_0277.fits")
    other_filter = SimpleNamespace(filter="F430M", flat_reference="jwst_niriss_flat_0301.fits")
    assert _flat_reference_note(model, same) is None
    assert _flat_reference_note(model, other_filter) is None
    unrecorded = FitModel(lambda f: None, object(), "full", "m", _flat_references({}))
    assert _flat_reference_note(unrecorded, newer) is None
    # a _rateints image (divided by no flat) against a model learnt behind one, and back
    none = SimpleNamespace(filter="F480M", flat_reference="")
    assert "divided by no flat" in _flat_reference_note(model, none)
    unflat_data = SlopeData.read(unflat, "calibrator")
    described = TrainingData(cal=[unflat_data], flats=[], val=[]).describe()
    assert described["calibration"][0]["flat_reference"] == "(none)"
    behind_none = FitModel(
        lambda f: None, object(), "full", "m", _flat_references({"data": described})
    )
    assert "learnt behind no flat" in _flat_reference_note(behind_none, same)
    assert _flat_reference_note(behind_none, none) is None
    # a checkpoint written before the flats were recorded still resumes; another flat not
    from amigo.training.data import same_data

    current = TrainingData(cal=[data], flats=[], val=[]).describe()
    before = {k: [{f: v for f, v in d.items() if f != "flat_reference"} for d in items]
              for k, items in current.items()}  # fmt: skip
    assert same_data(before, current) and same_data(current, current)
    assert not same_data(described, current)


def test_the_model_behind_the_pipeline_keeps_what_it_learnt():
    config = BaseModelConfig(filters=("F480M",), shape=(8, 8))
    base = BaseModel.create(config, linear=True)
    base = eqx_set_nonlinearity(base, 1e-6)
    behind = base.for_level2()
    assert behind.config.data_level == "level2" and base.config.data_level == "ramp"
    assert not np.asarray(behind.read.nonlinearity).any()
    import equinox as eqx

    learnt = eqx.tree_at(lambda m: m.ramp.flat, behind, behind.ramp.flat * 1.01)
    assert learnt.for_level2() is learnt  # its flat is the residual sensitivity: kept


needs_shared = pytest.mark.skipif(
    not CALIBRATORS.is_dir(), reason=f"COM 1093 calibrator files not found in {CALIBRATORS}"
)


@pytest.mark.slow
@needs_shared
def test_amigo_train_on_real_level2_calibrators(tmp_path, capsys):
    # One dither of HD 36805 (obs 20), from scratch with the network off (stage 0 only) on
    # a coarse pupil: what is tested here is the command on real files (23 s on a 2-core
    # CPU; with a validation file and a 64-pixel pupil it took 40 s); the shipped
    # real-data model shows the training itself. The command runs in this process (as
    # in test_cli_train); the refusal below runs as a subprocess.
    cal = [str(CALIBRATORS / "jw01093020001_03102_00001_nis_cal.fits")]
    out = tmp_path / "real.npz"
    args = ["train", "--cal", *cal, "--out", str(out), "--steps", "2"]
    args += ["--stages", "2", "--batches", "1", "--pupil-npix", "32"]
    # With the exposure's own wavefront drift (piston, tip, tilt per hole), as an option.
    args += ["--drift-modes", "3", "--drift-prior", "5"]
    status, stdout, stderr = amigo_here(capsys, *args)
    assert status == 0, stderr[-3000:]
    assert "loss curve" in stdout
    png = out.with_name("real_loss.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = read_metadata(out)
    assert record["config"]["data_level"] == "level2"
    names = [e["name"] for e in record["data"]["calibration"]]
    assert names == ["jw01093020001_03102_00001_nis"]
    assert all(e["level"] == "level2" for e in record["data"]["calibration"])
    # What made the model: the command as given, and the code's commit (None outside git).
    assert record["command"].startswith("amigo train --cal ") and cal[0] in record["command"]
    commit = record["source_commit"]
    assert commit is None or len(commit.removesuffix("+dirty")) == 40
    history = record["history"]
    assert len(history["cal_loss"]) == 2 and history["cal_loss"][-1] < history["cal_loss"][0]
    print("level-2 training losses", json.dumps(history["cal_loss"]))
    # The file's 1/f stripes, measured after the warm-up and marginalised in the loss.
    assert [s["name"] for s in record["stripes"]] == names
    assert record["stripes"][0]["tau_dn_s"] >= 0 and record["settings"]["stripes"]
    assert record["settings"]["drift_modes"] == 3 and record["settings"]["drift_prior_nm"] == 5
    # A drift of more Zernikes than the model has is refused in one line, before training.
    more = ["train", "--cal", *cal, "--out", str(tmp_path / "x.npz"), "--drift-modes", "12"]
    status, _, stderr = amigo_here(capsys, *more)
    assert status == 2 and "--drift-modes: 12: the model has 10 Zernikes per hole" in stderr
    assert not (tmp_path / "x.npz").exists()
    print("stripes", record["stripes"], record["statistics"])
    # The dark residual: solved after the steps, behind the file's dark reference, for
    # its 9 group reads (docs/detector.md); --steps 0 solves it afresh, nothing else.
    dark = record["dark_residual"]
    assert dark["reference"] == "jwst_niriss_dark_0178.fits" and dark["groups"] == 9
    assert dark["exposures"] == names and 0 < dark["rms_dn"] < 5
    again = tmp_path / "again.npz"
    args = ["train", "--cal", *cal, "--out", str(again), "--steps", "0", "--init", str(out)]
    status, _, stderr = amigo_here(capsys, *args)
    assert status == 0, stderr[-3000:]
    assert read_metadata(again)["steps_done"] == 0 and "dark residual" in stderr
    before, after = load_base_model(out), load_base_model(again)
    assert after.config.dark_reference == "jwst_niriss_dark_0178.fits"
    np.testing.assert_array_equal(after.zernikes_nm["F480M"], before.zernikes_nm["F480M"])

    # One model cannot stand both in front of and behind the pipeline: the model trained
    # here refuses calslope files, and a training refuses a mix of the two kinds.
    from amigo.pipeline._fit import _fit_model

    with pytest.raises(InputError, match="level-2"):
        _fit_model(out, None, "calslope")
    calslope = _write(tmp_path / "ramp_calslope.fits", np.full((3, 16, 16), 50.0), "F480M", 0)
    mixed = run_amigo(
        "train", "--cal", cal[0], "--val", str(calslope), "--out", str(tmp_path / "x")
    )
    assert mixed.returncode == 2, mixed.stderr
    error = mixed.stderr.strip().splitlines()[-1]  # (after a note on memory maps, if any)
    assert "cannot be mixed" in error and "ramp_calslope.fits" in error, mixed.stderr


def test_with_the_network_the_model_image_is_still_stcal_s_fit_of_the_model_ramp(bent_model):
    """The same check with the charge-migration network on (issue 22 asks for both): the
    network moves charge between pixels group by group, so the ramps bend in ways no
    single non-linearity coefficient makes; the pipeline's estimator must still be
    stcal's fit of whatever ramp the model produces."""
    linear_base, data, source = bent_model
    config = linear_base.config
    base = BaseModel.create(config, key=jax.random.PRNGKey(3), network_init_scale=1.0)
    base = eqx_set_nonlinearity(base, -2e-6)
    assert not base.linear
    with jax.enable_x64(True):  # the network's weights in the float64 of the comparison
        base = cast(base, jnp.float64)
    level2, differences, ramp = _model_image_and_ramp(base, data, source)
    _, linear_differences, _ = _model_image_and_ramp(linear_base, data, source)
    bright = differences.mean(axis=0) > 20.0
    assert bright.sum() > 50
    # The network does change the ramps, by far more than the agreement asked below.
    change = np.abs(differences - linear_differences)[:, bright] / differences[:, bright]
    assert change.max() > 1e-3
    rate = _stcal_slope(ramp, base.read.gain_e_per_dn)
    np.testing.assert_allclose(level2[bright] / TGROUP, rate["slope"][bright], rtol=2e-5)
    print(
        f"network's largest change of a group difference {change.max():.2e}; model image "
        f"against stcal: max relative difference "
        f"{np.max(np.abs(level2[bright] / TGROUP / rate['slope'][bright] - 1)):.2e}"
    )


def _hole_wavefront(base: BaseModel, cache, inside: np.ndarray) -> np.ndarray:
    """The wavefront over the holes (nm, the pupil's pixels ``inside``): the per-hole
    Zernikes' OPD plus the Fresnel defocus's, less its best-fitting piston and tilt."""
    from amigo.model.optics.model import defocus_opd_m

    optics = base.optics("F430M", cache)
    _, opd = optics.pupil()
    radius = 0.5 * optics.config.pupil_diameter_m
    opd = np.asarray(opd + defocus_opd_m(optics.grid, optics.defocus_nm, radius)) * 1e9
    yy, xx = np.nonzero(inside)
    plane = np.stack([np.ones(yy.size), xx, yy], axis=1)
    values = opd[inside]
    return values - plane @ np.linalg.lstsq(plane, values, rcond=None)[0]


@pytest.mark.slow
def test_training_on_dithered_level2_images_recovers_the_wavefront_and_pixel_response():
    """Issue 22's unit check: level-2 calibrators simulated through a model with a known
    wavefront (Noll 1-6 on every hole, 38 nm rms over the holes), a known residual
    sensitivity (1 % per pixel, the prior's width) and each exposure's own piston drift
    (4 nm rms per hole), 8 dithered images at a bright star's photon noise (4e6
    electrons per integration); training from the nominal model recovers all three.

    Compared is the wavefront over the holes, not the Zernike coefficients one by one:
    with the pupil's defocus method the Fresnel defocus is a quadratic over the pupil,
    which over each hole is exactly a piston, a tilt and a defocus, so the per-hole Noll
    1-4 and the defocus parameter trade without changing any image
    (benchmarks/train_identifiability.py: their errors are unbounded with both free);
    and the wavefront's overall piston and tilt are the star's position."""
    import equinox as eqx

    from amigo.training.data import TrainingData, TrainSettings
    from amigo.training.trainer import Trainer

    n, flux = 40, 4e6
    config = BaseModelConfig(
        filters=("F430M",), shape=(n, n), pupil_npix=64, n_wavelengths=3, dark_residual_groups=0
    )
    rng = np.random.default_rng(5)
    zernikes = np.zeros((niriss.N_HOLES, config.n_zernike))
    zernikes[:, :6] = rng.normal(0.0, 25.0, (niriss.N_HOLES, 6))
    sensitivity = 1.0 + 0.01 * rng.normal(size=(n, n))
    truth = eqx.tree_at(
        lambda m: (m.zernikes_nm["F430M"], m.ramp.flat),
        BaseModel.create(config, linear=True).for_level2(),
        (jnp.asarray(zernikes, jnp.float32), jnp.asarray(sensitivity, jnp.float32)),
    )
    cache = truth.pupil_cache()

    # Each calibrator's own wavefront of the moment: a piston drift per hole, 4 nm rms.
    drifts = rng.normal(0.0, 4.0, (8, niriss.N_HOLES))
    drifts -= drifts.mean(axis=0)  # what the exposures share is the static wavefront's

    def image(position, seed: int, name: str, role: str, drift=None) -> SlopeData:
        blank = np.ones((n, n))
        layout = SlopeData.from_rate_image(
            blank, blank, blank > 0, ngroups=5, group_time_s=TGROUP, filter_name="F430M"
        )
        source = PointSourceParams(jnp.asarray(position, jnp.float32), jnp.asarray(flux))
        if drift is not None:
            source = source.with_drift(1, 1.0)
            source = eqx.tree_at(lambda q: q.drift_nm, source, jnp.asarray(drift[:, None]))
        model = np.asarray(point_source_slopes(truth, cache, source, layout), np.float64)[0]
        # Photon variance of a 5-group slope (~ value / (gain (n - 1))) and read noise.
        variance = 4.0 + np.abs(model) / (truth.read.gain_e_per_dn * 4)
        noisy = model + np.random.default_rng(seed).normal(size=model.shape) * np.sqrt(variance)
        return SlopeData.from_rate_image(
            noisy / TGROUP,
            np.sqrt(variance) / TGROUP,
            blank > 0,
            ngroups=5,
            group_time_s=TGROUP,
            filter_name="F430M",
            name=name,
            role=role,
        )

    s = 0.15  # arcsec: the dithers move the PSF by ~2 pixels, telling response from PSF
    offsets = [(0, 0), (-s, -s), (s, -s), (-s, s), (s, s), (s, 0), (-s, 0), (0, s)]
    cal = [image(o, k, f"dither{k}", "calibrator", drifts[k]) for k, o in enumerate(offsets)]
    val = [image((0.05, -0.04), 99, "held", "validation")]
    # Network off for 10 steps, then on with the residual sensitivity for 20.
    settings = TrainSettings(
        steps=30,
        n_batches=1,
        stage_steps=(10, 20),
        dark_prior_dn=0.0,
        stripes=False,
        drift_modes=3,  # piston, tip and tilt per hole, each exposure its own
        drift_prior_nm=5.0,
    )
    trainer = Trainer(TrainingData(cal, [], val), settings, config, cache)
    start = trainer.state.base
    while trainer.step < settings.steps:
        losses = trainer.epoch()
    trained = trainer.state.base

    amplitude, _ = truth.optics("F430M", cache).pupil()
    inside = np.asarray(amplitude) > 0.5
    wavefront = _hole_wavefront(truth, cache, inside)
    before = _hole_wavefront(start, cache, inside) - wavefront
    after = _hole_wavefront(trained, cache, inside) - wavefront
    rms = lambda v: float(np.sqrt(np.mean(v**2)))  # noqa: E731
    bright = sum(np.asarray(d.slopes_dn[0]) for d in cal)
    bright = bright > np.percentile(bright, 70)
    learnt = np.asarray(trained.ramp.flat)[bright]
    correlation = np.corrcoef(learnt, sensitivity[bright])[0, 1]
    print(
        f"wavefront error {rms(before):.1f} -> {rms(after):.1f} nm rms (truth {rms(wavefront):.1f}); "
        f"sensitivity in the brightest 30 % of pixels: correlation {correlation:.3f}, error "
        f"{np.std(learnt - sensitivity[bright]):.4f} (truth's scatter "
        f"{np.std(sensitivity[bright]):.4f}); losses {losses}"
    )
    assert rms(wavefront) > 30.0 and rms(before) > 0.9 * rms(wavefront)
    assert rms(after) < 0.25 * rms(wavefront)  # measured: 0.13 (0.16 without drifts)
    assert correlation > 0.7  # measured: 0.83
    assert np.std(learnt - sensitivity[bright]) < 0.7 * np.std(sensitivity[bright])  # 0.55
    assert losses["cal"] < 0.6 and losses["val"] < 0.6  # at the noise: 0.5 per value
    # Each calibrator's drift, learnt beside the static optics (per-hole piston, tip and
    # tilt under a 5 nm prior): its pistons relative to the holes' mean.
    learnt_drift = np.array([np.asarray(p.drift_nm)[:, 0] for p in trainer.state.cal_params])
    learnt_drift -= learnt_drift.mean(axis=1, keepdims=True)
    true_drift = drifts - drifts.mean(axis=1, keepdims=True)
    drift_correlation = np.corrcoef(learnt_drift.ravel(), true_drift.ravel())[0, 1]
    print(
        f"piston drifts: correlation {drift_correlation:.3f}, error "
        f"{rms(learnt_drift - true_drift):.2f} nm (truth {rms(true_drift):.2f} nm)"
    )
    assert drift_correlation > 0.5  # measured: 0.70 (30 steps, 1 nm per step at most)
    assert rms(learnt_drift - true_drift) < 0.85 * rms(true_drift)  # measured: 0.72
