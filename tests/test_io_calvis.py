"""The calvis file format: round trip, validation, orientation helper."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from amigo.errors import InputError
from amigo.io.calvis import (
    calvis_filename,
    is_calvis,
    nominal_sky_to_uv,
    read_calvis,
    write_calvis,
)
from amigo.orientation import Orientation


def _arrays(rng, n_obs=7, n_uv=4, n_wl=3):
    return dict(
        values=rng.normal(size=n_obs),
        errors=rng.uniform(0.5, 1.5, size=n_obs),
        kinds=["amplitude"] * 3 + ["phase"] * (n_obs - 3),
        disco_matrix=rng.normal(size=(n_obs, 2 * n_uv)),
        uv_m=rng.normal(size=(n_uv, 2)),
        wavelengths_m=np.linspace(4.6e-6, 5.0e-6, n_wl),
        weights=np.full(n_wl, 1.0 / n_wl),
        sky_to_uv=np.array([[0.1, 0.99], [-0.99, 0.1]]),
    )


def test_round_trip_keeps_every_array_and_keyword(tmp_path):
    rng = np.random.default_rng(0)
    arrays = _arrays(rng)
    orientation = Orientation.from_roll(171.7)
    path = write_calvis(
        tmp_path / calvis_filename("AB DOR", "f480m"),
        **arrays,
        orientation=orientation,
        n_photons=3.2e8,
        target="AB DOR",
        filter_name="f480m",
        science_files=["/data/jw01093012001_03102_00001_nis_cal.fits"],
        calibrator_files=["jw01093015001_03102_00001_nis_cal.fits"],
        header={"FITSTAT": "ok"},
    )
    assert path.name == "AB-DOR_F480M_calvis.fits"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temp file left
    assert is_calvis(path)
    back = read_calvis(path)
    for key in (
        "values",
        "errors",
        "disco_matrix",
        "uv_m",
        "wavelengths_m",
        "weights",
        "sky_to_uv",
    ):
        np.testing.assert_array_equal(getattr(back, key), arrays[key])
    assert back.kinds == tuple(arrays["kinds"])
    assert back.filter_name == "F480M" and back.target == "AB DOR"
    assert back.n_photons == 3.2e8
    assert back.science_files == ("jw01093012001_03102_00001_nis_cal.fits",)
    assert back.calibrator_files == ("jw01093015001_03102_00001_nis_cal.fits",)
    assert back.orientation.pa_aper_deg == pytest.approx(orientation.pa_aper_deg)
    assert back.header["FITSTAT"] == "ok"
    with fits.open(path) as hdul:
        assert [h.name for h in hdul] == [
            "PRIMARY",
            "DISCO",
            "DISCO_MATRIX",
            "UV",
            "WAVELENGTH",
            "SKY_TO_UV",
        ]
        for key in ("AMIGOVER", "PA_APER", "VPARITY", "V3I_YANG", "ROLL_REF", "NPHOT"):
            assert key in hdul[0].header


def test_writer_rejects_inconsistent_arrays(tmp_path):
    arrays = _arrays(np.random.default_rng(1))
    arrays["disco_matrix"] = arrays["disco_matrix"][:, :-1]
    with pytest.raises(ValueError, match="DISCO_MATRIX"):
        write_calvis(
            tmp_path / "x_calvis.fits",
            **arrays,
            orientation={"PA_APER": 10.0},
            n_photons=1e6,
            target="X",
            filter_name="F380M",
        )
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda h: h["DISCO"].data["ERROR"].__setitem__(0, -1.0), "ERROR must be positive"),
        (lambda h: h.__delitem__("SKY_TO_UV"), "lacks the SKY_TO_UV"),
        (lambda h: h[0].header.__setitem__("CONTENT", "OTHER"), "not a calvis file"),
        (lambda h: h["DISCO_MATRIX"].__setattr__("data", np.zeros((2, 2))), "DISCO_MATRIX"),
    ],
)
def test_reader_names_the_problem(tmp_path, mutate, message):
    arrays = _arrays(np.random.default_rng(2))
    path = write_calvis(
        tmp_path / "x_calvis.fits",
        **arrays,
        orientation={"PA_APER": 10.0},
        n_photons=1e6,
        target="X",
        filter_name="F380M",
    )
    with fits.open(path) as hdul:
        mutate(hdul)
        hdul.writeto(tmp_path / "bad.fits")
    with pytest.raises(InputError, match=message) as info:
        read_calvis(tmp_path / "bad.fits")
    assert info.value.path.endswith("bad.fits")


def test_reader_rejects_non_fits(tmp_path):
    path = tmp_path / "notes_calvis.fits"
    path.write_text("not a FITS file")
    assert not is_calvis(path)
    with pytest.raises(InputError, match="FITS"):
        read_calvis(path)


def test_nominal_sky_to_uv_follows_the_orientation():
    """Independent check: detector +y points at PA_APER; detector +x at PA_APER - 90."""
    pa = 172.3
    matrix = nominal_sky_to_uv(Orientation(pa_aper_deg=pa))
    for direction_deg, axis in ((pa, 1), (pa - 90.0, 0)):
        east, north = np.sin(np.deg2rad(direction_deg)), np.cos(np.deg2rad(direction_deg))
        uv = matrix @ np.array([east, north]) * 100.0
        assert uv[axis] == pytest.approx(100.0, rel=0.01)
        assert abs(uv[1 - axis]) < 1.0  # the 0.24 deg skew of the ideal frame
