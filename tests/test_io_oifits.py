"""OIFITS reading: peer files, flags, covariance (CPCOV and OI_CORR)."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from amigo.errors import InputError
from amigo.io.oifits import is_oifits, read_oifits
from detect_helpers import write_sim_oifits


def test_reads_a_peer_file(oifits_dir):
    path = oifits_dir / "NuHor_F480M.oifits"
    oi = read_oifits(path)
    with fits.open(path) as hdul:
        t3 = hdul["OI_T3"].data
        v2 = hdul["OI_VIS2"].data
        np.testing.assert_allclose(oi.t3.phase_rad, np.deg2rad(t3["T3PHI"]))
        np.testing.assert_allclose(oi.t3.error_rad, np.deg2rad(t3["T3PHIERR"]))
        np.testing.assert_allclose(oi.vis2.value, v2["VIS2DATA"])
        np.testing.assert_allclose(oi.vis2.u_m, v2["UCOORD"])
    assert oi.filter_name == "F480M"
    assert oi.target == "Nu Hor"
    assert oi.vis2.value.size == 21 and oi.t3.phase_rad.size == 35
    assert oi.t3.stations.shape == (35, 3)
    assert oi.vis2.wavelength_m[0] == pytest.approx(4.817e-6, rel=1e-4)
    assert oi.t3.covariance is None


def test_cpcov_image_becomes_a_covariance_in_rad2(oifits_dir):
    oi = read_oifits(oifits_dir / "fouriever_sim_ABDor_F480M_cpcov.oifits")
    with fits.open(oifits_dir / "fouriever_sim_ABDor_F480M_cpcov.oifits") as hdul:
        cube = hdul["CPCOV"].data
    assert oi.t3.covariance.shape == (35, 35)
    np.testing.assert_allclose(oi.t3.covariance, cube[0])
    # Its diagonal is the square of T3PHIERR (the file's errors are in degrees).
    np.testing.assert_allclose(np.sqrt(np.diag(oi.t3.covariance)), oi.t3.error_rad, rtol=0.02)


def test_flags_and_oi_corr(tmp_path):
    path = write_sim_oifits(tmp_path / "sim.oifits", np.random.default_rng(0), None)
    rho = 0.4
    with fits.open(path) as hdul:
        t3 = hdul["OI_T3"]
        flags = np.zeros(35, bool)
        flags[[3, 10]] = True
        n = len(t3.data)
        # Correlation rho between closure phases 0 and 1, via OIFITS2 OI_CORR.
        kept = [
            fits.Column(c.name, c.format, unit=c.unit, array=t3.data[c.name])
            for c in t3.columns
            if c.name != "FLAG"
        ]
        new_t3 = fits.BinTableHDU.from_columns(
            [
                *kept,
                fits.Column("FLAG", "L", array=flags),
                fits.Column("CORRINDX_T3PHI", "J", array=np.arange(1, n + 1)),
            ],
            header=t3.header,
            name="OI_T3",
        )
        corr = fits.BinTableHDU.from_columns(
            [
                fits.Column("IINDX", "J", array=[1]),
                fits.Column("JINDX", "J", array=[2]),
                fits.Column("CORR", "D", array=[rho]),
            ],
            name="OI_CORR",
        )
        corr.header["NDATA"] = n
        hdul["OI_T3"] = new_t3
        hdul.append(corr)
        hdul.writeto(tmp_path / "corr.oifits")
    oi = read_oifits(tmp_path / "corr.oifits")
    assert oi.t3.phase_rad.size == 33
    sigma = oi.t3.error_rad
    assert oi.t3.covariance[0, 1] == pytest.approx(rho * sigma[0] * sigma[1])
    np.testing.assert_allclose(np.diag(oi.t3.covariance), sigma**2)
    assert oi.t3.covariance[0, 2] == 0.0


def test_not_oifits(tmp_path):
    fits.HDUList([fits.PrimaryHDU(np.zeros(3))]).writeto(tmp_path / "image.fits")
    assert not is_oifits(tmp_path / "image.fits")
    with pytest.raises(InputError, match="neither OI_VIS2 nor OI_T3"):
        read_oifits(tmp_path / "image.fits")
