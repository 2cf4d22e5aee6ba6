"""Readers of JWST AMI exposures and every input error they must report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from amigo import niriss
from amigo.errors import InputError
from amigo.io import jwst
from jwst_files import write_level2, write_uncal


def ramps(nints=3, ngroups=4, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.integers(10000, 12000, (1, 1, 80, 80))
    rate = rng.uniform(0, 200, (1, 1, 80, 80))
    groups = np.arange(1, ngroups + 1)[None, :, None, None]
    return (base + rate * groups + rng.normal(0, 5, (nints, ngroups, 80, 80))).astype(np.uint16)


def test_read_uncal(tmp_path):
    data = ramps()
    path = write_uncal(tmp_path / "jw04481001001_01101_00001_nis_uncal.fits", data)
    exposure = jwst.read_exposure(path, need_slopes=True)
    meta = exposure.meta
    assert meta.kind == "uncal" and meta.is_ramp
    assert (meta.target, meta.filter, meta.ngroups, meta.nints) == ("TEST-STAR", "F430M", 4, 3)
    assert meta.group_time_s == pytest.approx(0.07544)
    assert (meta.program, meta.observation, meta.visit, meta.exposure) == (
        "04481",
        "001",
        "001",
        "1",
    )
    assert meta.stem == "jw04481001001_01101_00001_nis"
    assert meta.orientation.pa_aper_deg == pytest.approx(100.56126717)
    assert exposure.data.dtype == np.float64 and exposure.data.shape == (3, 4, 80, 80)
    np.testing.assert_array_equal(exposure.data, data.astype(float))
    assert exposure.usable.shape == (80, 80)
    assert not exposure.usable[:4].any() and exposure.usable[4:].all()


def test_iter_ramps_streams_the_same_data(tmp_path):
    data = ramps(nints=7)
    path = write_uncal(tmp_path / "a_uncal.fits", data)
    chunks = list(jwst.iter_ramps(path, chunk=3))
    assert [c.shape[0] for c in chunks] == [3, 3, 1]
    np.testing.assert_array_equal(np.concatenate(chunks), data.astype(float))
    with_dq = list(jwst.iter_ramps(path, chunk=5, with_dq=True))
    assert with_dq[0][1] is None


def test_read_mirage_uncal_with_warning(mirage_uncal):
    with pytest.warns(jwst.AmiWarning, match="NIS_IMAGE"):
        exposure = jwst.read_exposure(mirage_uncal, need_slopes=True)
    assert exposure.data.shape == (5, 6, 80, 80)
    assert exposure.meta.filter == "F480M"
    assert exposure.meta.orientation.pa_aper_deg == pytest.approx(274.5518758131237 + 0.56987)
    assert exposure.data.min() >= 0 and exposure.data.max() < 65536


def test_read_real_cal(com1093_dir):
    exposure = jwst.read_exposure(com1093_dir / "jw01093012001_03102_00001_nis_cal.fits")
    meta = exposure.meta
    assert (meta.kind, meta.target, meta.filter, meta.ngroups, meta.nints) == (
        "cal",
        "AB-DOR",
        "F480M",
        5,
        69,
    )
    assert meta.bunit == "DN/s"
    assert exposure.data.shape == exposure.err.shape == exposure.dq.shape == (80, 80)
    assert not exposure.usable[:4].any()
    assert exposure.usable[4:].mean() > 0.95
    do_not_use = (exposure.dq & jwst.DQ_DO_NOT_USE) != 0
    assert not exposure.usable[do_not_use].any()


def test_slope_time_counts_the_photons_between_first_and_last_read(com1093_dir):
    """The real AB Dor headers: EFFINTTM is NGROUPS * TGROUP, the photons a slope uses
    arrive in (NGROUPS - 1) * TGROUP; at two groups EFFEXPTM counts twice the slope's."""
    for stem, ngroups, nints in (("03104", 2, 160), ("03105", 13, 29)):
        path = com1093_dir / f"jw01093012001_{stem}_00001_nis_cal.fits"
        meta = jwst.read_exposure(path).meta
        header = meta.primary_header
        assert (meta.ngroups, meta.nints) == (ngroups, nints)
        assert meta.slope_time_s == pytest.approx(nints * (ngroups - 1) * 0.07544, rel=1e-6)
        effexptm = header["NINTS"] * header["EFFINTTM"]
        assert effexptm / meta.slope_time_s == pytest.approx(ngroups / (ngroups - 1), rel=1e-3)
        # with the first group in the likelihood every group's photons count: EFFEXPTM's
        assert meta.photon_time_s(first_group=True) == pytest.approx(effexptm, rel=1e-3)


def test_slope_time_of_one_group_is_the_read(tmp_path):
    path = write_level2(tmp_path / "a_cal.fits", np.ones((80, 80)), overrides={"NGROUPS": 1})
    meta = jwst.read_exposure(path).meta
    assert meta.slope_time_s == pytest.approx(meta.nints * meta.group_time_s)


def test_read_calints_and_flagged_nan(tmp_path):
    sci = np.full((2, 80, 80), 5.0)
    dq = np.zeros((2, 80, 80), np.uint32)
    sci[1, 40, 41] = np.nan
    dq[1, 40, 41] = jwst.DQ_DO_NOT_USE
    path = write_level2(tmp_path / "x_calints.fits", sci, dq=dq)
    exposure = jwst.read_exposure(path)
    assert exposure.meta.kind == "calints"
    assert exposure.usable.shape == (2, 80, 80)
    assert not exposure.usable[1, 40, 41] and exposure.usable[0, 40, 41]
    path = write_level2(tmp_path / "x_rateints.fits", sci, dq=dq)
    assert jwst.read_header(path).kind == "rateints"


# ------------------------------------------------------------------------------ errors
def expect_error(path: Path, match: str, **kwargs) -> None:
    with pytest.raises(InputError, match=match) as info:
        jwst.read_exposure(path, **kwargs)
    assert info.value.path == str(path)
    assert "\n" not in str(info.value)


def test_a_photometrically_calibrated_image_is_read_back_in_dn_per_s(tmp_path):
    """A level-2 image the pipeline's photom step converted to MJy/sr (SCI and ERR times
    PHOTMJSR) reads as the count rates it came from; without a usable PHOTMJSR it is
    refused with one line naming the keyword."""
    rng = np.random.default_rng(5)
    rate = rng.uniform(0.0, 3e4, (80, 80))
    err = np.sqrt(rate / 30.0 + 4.0)
    step = {"S_CHGMIG": "COMPLETE"}  # VAR_POISSON is read (pixels.pipeline_groups uses it)
    first = write_level2(tmp_path / "a_cal.fits", rate, err, overrides=step)
    conversion = 0.8573  # (MJy/sr) per (DN/s), the size of NIRISS's
    path = write_level2(
        tmp_path / "b_cal.fits", rate * conversion, err * conversion, overrides=step
    )
    for name, scale in ((first, 1.0), (path, conversion**2)):
        with fits.open(name, mode="update") as hdul:
            hdul.append(fits.ImageHDU((rate / 30.0 * scale).astype(np.float32), name="VAR_POISSON"))
    with fits.open(path, mode="update") as hdul:
        hdul["SCI"].header["BUNIT"] = "MJy/sr"
        hdul["SCI"].header["PHOTMJSR"] = conversion
    plain = jwst.read_exposure(first)
    calibrated = jwst.read_exposure(path)
    assert calibrated.meta.bunit == "DN/s" and calibrated.meta.in_dn_per_s
    np.testing.assert_allclose(calibrated.data, plain.data, rtol=2e-7)
    np.testing.assert_allclose(calibrated.err, plain.err, rtol=2e-7)
    np.testing.assert_allclose(calibrated.var_poisson, plain.var_poisson, rtol=4e-7)
    assert plain.var_poisson is not None
    np.testing.assert_array_equal(calibrated.usable, plain.usable)
    with fits.open(path) as hdul:  # the input is not touched
        assert hdul["SCI"].header["BUNIT"] == "MJy/sr"
    for value, match in ((None, "PHOTMJSR is missing"), (0.0, "PHOTMJSR is 0.0")):
        with fits.open(path, mode="update") as hdul:
            if value is None:
                del hdul["SCI"].header["PHOTMJSR"]
            else:
                hdul["SCI"].header["PHOTMJSR"] = value
        with pytest.raises(InputError, match=match):
            jwst.read_exposure(path)


def test_not_a_fits_file(tmp_path):
    path = tmp_path / "notes_cal.fits"
    path.write_text("these are my notes\n")
    expect_error(path, "not a FITS file")


def test_missing_file(tmp_path):
    expect_error(tmp_path / "absent_cal.fits", "no such file")


def test_truncated_file(tmp_path):
    full = write_uncal(tmp_path / "full_uncal.fits", ramps())
    cut = tmp_path / "cut_uncal.fits"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    expect_error(cut, "truncated")


def test_other_instrument(tmp_path):
    expect_error(write_uncal(tmp_path / "n_uncal.fits", ramps(), {"INSTRUME": "NIRCAM"}), "NIRCAM")


def test_pupil_not_nrm(tmp_path):
    expect_error(write_uncal(tmp_path / "p_uncal.fits", ramps(), {"PUPIL": "CLEARP"}), "PUPIL")


def test_non_ami_exposure_type(tmp_path):
    expect_error(
        write_uncal(tmp_path / "e_uncal.fits", ramps(), {"EXP_TYPE": "NIS_SOSS"}), "EXP_TYPE"
    )


def test_unsupported_subarray(tmp_path):
    expect_error(write_uncal(tmp_path / "s_uncal.fits", ramps(), {"SUBARRAY": "SUB256"}), "SUB80")


def test_non_ami_filter(tmp_path):
    expect_error(write_uncal(tmp_path / "f_uncal.fits", ramps(), {"FILTER": "F150W"}), "F150W")


def test_wrong_frame_size(tmp_path):
    data = np.zeros((2, 3, 64, 64), np.uint16)
    expect_error(write_uncal(tmp_path / "w_uncal.fits", data), "80x80")


@pytest.mark.parametrize("keyword", ["FILTER", "NGROUPS", "SUBARRAY"])
def test_missing_keywords(tmp_path, keyword):
    expect_error(write_uncal(tmp_path / "k_uncal.fits", ramps(), drop=(keyword,)), keyword)


def test_missing_orientation(tmp_path):
    path = write_uncal(tmp_path / "o_uncal.fits", ramps(), drop=("PA_APER", "ROLL_REF"))
    expect_error(path, "orientation")


def test_wrong_dimensionality(tmp_path):
    path = tmp_path / "d_uncal.fits"
    hdul = fits.open(write_uncal(path, ramps()))
    hdul["SCI"].data = np.zeros((2, 2, 2, 80, 80), np.int16)
    hdul.writeto(tmp_path / "d5_uncal.fits")
    expect_error(tmp_path / "d5_uncal.fits", "dimensions")


def test_header_disagrees_with_data(tmp_path):
    path = write_uncal(tmp_path / "h_uncal.fits", ramps(), {"NGROUPS": 9})
    expect_error(path, "NGROUPS=9")


def test_nan_in_unflagged_pixels(tmp_path):
    sci = np.ones((80, 80))
    sci[50, 50] = np.inf
    expect_error(write_level2(tmp_path / "n_cal.fits", sci), "NaN/inf")


def test_one_group_ramp_when_slopes_needed(tmp_path):
    path = write_uncal(tmp_path / "g_uncal.fits", ramps(ngroups=1))
    assert jwst.read_exposure(path).data.shape == (3, 1, 80, 80)
    expect_error(path, "slopes need at least 2", need_slopes=True)
    # Streaming (amigo process) takes it: the first read is the measurement.
    blocks = list(jwst.iter_ramps(path, chunk=2))
    assert [b.shape for b in blocks] == [(2, 1, 80, 80), (1, 1, 80, 80)]


def test_oifits_is_not_an_exposure(oifits_dir):
    expect_error(oifits_dir / "NuHor_F480M.oifits", "OIFITS")


def test_reference_rows_consistent_across_kinds(tmp_path, com1093_dir):
    level2 = jwst.read_exposure(com1093_dir / "jw01093015001_03104_00001_nis_cal.fits")
    raw = jwst.read_exposure(write_uncal(tmp_path / "r_uncal.fits", ramps()))
    reference = niriss.reference_row_mask()
    assert not level2.usable[reference].any() and not raw.usable[reference].any()
    # The pipeline flags the same rows as reference pixels.
    assert np.all(level2.dq[reference] & jwst.DQ_REFERENCE_PIXEL)


def test_flat_field_lamp_exposures_are_accepted_with_any_pupil(tmp_path):
    path = write_uncal(
        tmp_path / "flat_uncal.fits", ramps(), {"EXP_TYPE": "NIS_LAMP", "PUPIL": "CLEARP"}
    )
    with pytest.warns(jwst.AmiWarning, match="flat-field"):
        meta = jwst.read_header(path, need_slopes=True)
    assert meta.is_flat and meta.pupil == "CLEARP"
    # Only lamp exposures: a sky image through the clear pupil is still not AMI.
    image = write_uncal(
        tmp_path / "img_uncal.fits", ramps(), {"EXP_TYPE": "NIS_IMAGE", "PUPIL": "CLEARP"}
    )
    expect_error(image, "PUPIL")
