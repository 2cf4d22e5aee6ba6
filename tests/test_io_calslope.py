"""The calslope file: layout exactly as in docs/interfaces, headers carried over, round trip."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from amigo import __version__
from amigo.errors import InputError
from amigo.io.calslope import EXTENSIONS, calslope_name, read_calslope, write_calslope
from amigo.processing.ramps import ArraySource, ProcessSettings, process_ramps
from ramp_sim import PRIMARY_KEYWORDS, SCI_KEYWORDS, simulate, write_uncal


@pytest.fixture(scope="module")
def product():
    rng = np.random.default_rng(10)
    ramps = simulate(rng, 12, 4, rng.uniform(50, 500, (80, 80)))
    return process_ramps(ArraySource(ramps.raw), ProcessSettings(nsigma=2.5))


def _headers():
    primary = fits.Header()
    for key, value in {**PRIMARY_KEYWORDS, "NINTS": 12, "NGROUPS": 4}.items():
        primary[key] = value
    sci = fits.Header()
    sci["BZERO"] = 32768
    for key, value in SCI_KEYWORDS.items():
        sci[key] = value
    return primary, sci


def test_layout_matches_the_interface(tmp_path, product):
    primary, sci = _headers()
    path = write_calslope(tmp_path / "x_calslope.fits", product, primary, sci, uncal_name="x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x_calslope.fits"]  # no temp left
    with fits.open(path) as hdul:
        names = [hdu.name for hdu in hdul]
        assert names == ["PRIMARY", *EXTENSIONS, "BADPIX_WHY"]
        ng = 4
        shapes = {
            "SLOPE": (ng - 1, 80, 80),
            "SLOPE_COV": (ng - 1, ng - 1, 80, 80),
            "SLOPE_SUP": (ng - 1, 80, 80),
            "RAMP": (ng, 80, 80),
            "RAMP_COV": (ng, ng, 80, 80),
            "RAMP_SUP": (ng, 80, 80),
        }
        for name, shape in shapes.items():
            assert hdul[name].data.shape == shape
            assert hdul[name].data.dtype == np.dtype(">f4")
        assert hdul["BADPIX"].data.dtype == np.uint8
        assert set(np.unique(hdul["BADPIX"].data)) <= {0, 1}
        head = hdul[0].header
        assert head["AMIGOVER"] == __version__
        assert head["ADC_CORR"] is True
        assert head["NSIGCLIP"] == 2.5
        for key in ("TARGPROP", "FILTER", "PUPIL", "NINTS", "NGROUPS", "PROGRAM"):
            assert head[key] == primary[key]
        slope = hdul["SLOPE"].header
        for key in ("ROLL_REF", "V3I_YANG", "VPARITY", "PA_APER"):
            assert slope[key] == sci[key]
        assert "BZERO" not in slope
    assert primary["DATAMODL"] == "Level1bModel"  # the caller's headers are not modified


def test_round_trip(tmp_path, product):
    primary, sci = _headers()
    path = write_calslope(tmp_path / "y_calslope.fits", product, primary, sci)
    back = read_calslope(path)
    for ours, theirs in (
        (product.slope_dn, back.slope_dn),
        (product.slope_cov_dn2, back.slope_cov_dn2),
        (product.slope_support, back.slope_support),
        (product.ramp_dn, back.ramp_dn),
        (product.ramp_cov_dn2, back.ramp_cov_dn2),
        (product.ramp_support, back.ramp_support),
    ):
        np.testing.assert_array_equal(theirs, ours.astype(np.float32))
    np.testing.assert_array_equal(back.badpix, product.badpix)
    np.testing.assert_array_equal(back.badpix_reason, product.badpix_reason)
    assert back.ngroups == 4 and back.adc_corrected and back.nsigma == 2.5


def test_reader_rejects_other_files(tmp_path):
    uncal = write_uncal(tmp_path / "a_uncal.fits", np.zeros((1, 2, 80, 80)))
    with pytest.raises(InputError, match="not a calslope file"):
        read_calslope(uncal)
    junk = tmp_path / "junk_calslope.fits"
    junk.write_text("hello")
    with pytest.raises(InputError, match="not a FITS file"):
        read_calslope(junk)


def test_output_names():
    assert (
        calslope_name("/d/jw01_03102_00001_nis_uncal.fits") == "jw01_03102_00001_nis_calslope.fits"
    )
    assert calslope_name("sim.fits") == "sim_calslope.fits"
