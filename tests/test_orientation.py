"""Sky orientation: round trips, a hand-computed case and agreement with the FITS WCS."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from hypothesis import given
from hypothesis import strategies as st

from amigo import niriss
from amigo.orientation import Orientation, offset_from_separation_pa, separation_pa

angles = st.floats(0, 360, allow_nan=False)
offsets = st.floats(-3000, 3000, allow_nan=False)


@given(angles, offsets, offsets)
def test_sky_detector_round_trip(pa, dra, ddec):
    o = Orientation(pa_aper_deg=pa)
    dx, dy = o.sky_to_detector(dra, ddec)
    back = o.detector_to_sky(dx, dy)
    assert np.allclose(back, (dra, ddec), atol=1e-9)
    ax, ay = o.sky_to_detector_arcsec(dra, ddec)
    assert np.allclose(o.detector_arcsec_to_sky(ax, ay), (dra, ddec), atol=1e-9)


@given(st.floats(0.1, 5000), angles)
def test_separation_pa_round_trip(sep, pa):
    dra, ddec = offset_from_separation_pa(sep, pa)
    s, p = separation_pa(dra, ddec)
    assert s == pytest.approx(sep, rel=1e-12)
    assert abs((p - pa + 180) % 360 - 180) < 1e-9


def test_hand_computed_case():
    """PA_APER = 90: detector +y points east, detector +x points at PA_APER - 90 = 0
    (north) because VPARITY = -1.

    Ignoring the 0.24 deg skew (checked against the WCS separately), one pixel along +y is
    ~65.72 mas east and one pixel along +x is ~65.33 mas north.
    """
    o = Orientation(pa_aper_deg=90.0, vparity=-1)
    dra, ddec = o.detector_to_sky(0.0, 1.0)
    assert dra == pytest.approx(65.724, abs=1e-3)
    assert ddec == pytest.approx(0.0, abs=0.03)
    dra, ddec = o.detector_to_sky(1.0, 0.0)
    assert dra == pytest.approx(0.0, abs=0.3)
    assert ddec == pytest.approx(65.325, abs=1e-3)
    # A companion due east (PA 90) lands on detector +y.
    dx, dy = o.sky_to_detector(*offset_from_separation_pa(100.0, 90.0))
    assert dy == pytest.approx(100 / 65.724, rel=1e-3)
    assert abs(dx) < 0.01
    assert o.pa_of_detector_y_deg() == pytest.approx(90.0, abs=0.05)


def test_from_roll_reproduces_pa_aper():
    o = Orientation.from_roll(171.7649906070351, 0.56126717, -1)
    assert o.pa_aper_deg == pytest.approx(172.3262577770351, abs=1e-9)
    header = o.to_header()
    assert Orientation.from_header(header) == o
    with pytest.raises(KeyError):
        Orientation.from_header({"VPARITY": -1})


def _wcs_offset_pa(wcs: WCS, x0: float, y0: float, dx: float, dy: float) -> tuple[float, float]:
    c0 = wcs.pixel_to_world(x0, y0)
    c1 = wcs.pixel_to_world(x0 + dx, y0 + dy)
    dra, ddec = c0.spherical_offsets_to(c1)
    return separation_pa(dra.to_value("mas"), ddec.to_value("mas"))


def test_agrees_with_fits_wcs_of_real_files(com1093_dir):
    """Detector offsets map to the same sky offset as astropy.wcs, within 0.2 deg (we get
    ~0.001 deg) and 0.1 % in separation, in every direction, for all seven files."""
    rng = np.random.default_rng(1)
    files = sorted(com1093_dir.glob("*_cal.fits"))
    assert len(files) == 7
    for path in files:
        primary = fits.getheader(path, 0)
        sci = fits.getheader(path, "SCI")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wcs = WCS(sci)
        o = Orientation.from_header(sci, primary)
        for _ in range(12):
            dx, dy = rng.uniform(-15, 15, 2)
            sep_wcs, pa_wcs = _wcs_offset_pa(wcs, 40.0, 40.0, dx, dy)
            sep, pa = separation_pa(*o.detector_to_sky(dx, dy))
            assert abs((pa - pa_wcs + 180) % 360 - 180) < 0.2
            assert sep == pytest.approx(sep_wcs, rel=1e-3)
        # Without PA_APER the same orientation follows from ROLL_REF + V3I_YANG.
        reduced = {k: sci[k] for k in ("ROLL_REF", "V3I_YANG", "VPARITY")}
        assert Orientation.from_header(reduced).pa_aper_deg == pytest.approx(
            o.pa_aper_deg, abs=1e-6
        )


def test_ab_dor_c_published_offset_gives_wcs_position_angle(com1093_dir):
    """The data README's detector offset of AB Dor C, (dy, dx) = (-1.7, -5.1) pixels, is at
    PA ~280.5 deg east of north through our convention (the paper's 169.5 deg is this
    angle with RA and Dec swapped: 90 - 280.5 = -190.5 = 169.5 mod 360)."""
    path = com1093_dir / "jw01093012001_03102_00001_nis_cal.fits"
    o = Orientation.from_header(fits.getheader(path, "SCI"))
    sep, pa = separation_pa(*o.detector_to_sky(-5.1, -1.7))
    assert pa == pytest.approx(280.5, abs=1.0)
    assert sep == pytest.approx(352, abs=15)  # ~5.4 pixels; the fit gives 329 mas
    assert (90 - pa) % 360 == pytest.approx(169.5, abs=1.0)


def test_mean_pixel_scale_used_by_matrix():
    o = Orientation(pa_aper_deg=0.0)
    m = o.detector_to_sky_matrix()
    assert np.abs(np.linalg.det(m)) == pytest.approx(
        niriss.PIXEL_SCALE_X_ARCSEC * niriss.PIXEL_SCALE_Y_ARCSEC * 1e6, rel=1e-3
    )
