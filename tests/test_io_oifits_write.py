"""The OIFITS2 writer: opens with the `oifits` package and reads back through amigo."""

from __future__ import annotations

import warnings

import numpy as np

from amigo import niriss
from amigo.io.oifits import read_oifits
from amigo.io.oifits_write import closure_matrix, write_oifits
from amigo.orientation import Orientation


def _binary_log_vis(uv_m, wavelength_m, offset_rad, contrast):
    vis = (1 + contrast * np.exp(-2j * np.pi * uv_m @ offset_rad / wavelength_m)) / (1 + contrast)
    return np.log(np.abs(vis)), np.angle(vis)


def test_closure_matrix_cancels_hole_phases():
    """Closure phases are immune to per-hole pistons: T applied to (p_j - p_i) is zero."""
    rng = np.random.default_rng(0)
    pistons = rng.normal(size=niriss.N_HOLES)
    i, j = np.array(niriss.baseline_pairs()).T
    np.testing.assert_allclose(closure_matrix() @ (pistons[j] - pistons[i]), 0.0, atol=1e-12)
    assert closure_matrix().shape == (35, 21)


def test_oifits_round_trip(tmp_path):
    import oifits

    wavelength = 4.3e-6
    orientation = Orientation(pa_aper_deg=172.3)
    # An ideal detector: sky offsets (mas) -> pupil-frame offsets (mas) through the WCS.
    sky_to_uv = np.column_stack(
        [np.array(orientation.sky_to_detector_arcsec(*unit)) * 1000 for unit in ((1, 0), (0, 1))]
    )
    mas = np.pi / 180 / 3600 / 1000
    offset_sky = np.array([-120.0, 60.0])  # dRA, dDec (mas)
    offset_uv = sky_to_uv @ offset_sky * mas
    log_amp, phase = _binary_log_vis(niriss.baselines_m(), wavelength, offset_uv, 0.05)
    rng = np.random.default_rng(1)
    a = rng.normal(size=(42, 42)) * 1e-3
    cov = a @ a.T + 1e-6 * np.eye(42)
    path = write_oifits(
        tmp_path / "T_F430M.oifits",
        target="AB-DOR",
        filter_name="F430M",
        wavelength_m=wavelength,
        bandwidth_m=2e-7,
        log_amp=log_amp,
        phase_rad=phase,
        covariance=cov,
        sky_to_uv=sky_to_uv,
        date_obs="2022-06-01",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = oifits.open(str(path), quiet=True)
    assert len(data.vis2) == 21 and len(data.t3) == 35
    assert data.target[0].target.strip() == "AB-DOR"

    read = read_oifits(path)
    # V2 and closure phases agree with the binary evaluated directly on the sky (u east,
    # v north): the writer's baselines transform is consistent with the calvis frame.
    u, v = read.vis2.u_m, read.vis2.v_m
    sky_offset = offset_sky * mas
    vis = 1 + 0.05 * np.exp(-2j * np.pi * (u * sky_offset[0] + v * sky_offset[1]) / wavelength)
    np.testing.assert_allclose(read.vis2.value, np.abs(vis / 1.05) ** 2, rtol=1e-10)
    t3 = read.t3
    v1 = 1 + 0.05 * np.exp(
        -2j * np.pi * (t3.u1_m * sky_offset[0] + t3.v1_m * sky_offset[1]) / wavelength
    )
    v2 = 1 + 0.05 * np.exp(
        -2j * np.pi * (t3.u2_m * sky_offset[0] + t3.v2_m * sky_offset[1]) / wavelength
    )
    u3, v3 = t3.u1_m + t3.u2_m, t3.v1_m + t3.v2_m
    v3c = np.conj(
        1 + 0.05 * np.exp(-2j * np.pi * (u3 * sky_offset[0] + v3 * sky_offset[1]) / wavelength)
    )
    np.testing.assert_allclose(t3.phase_rad, np.angle(v1 * v2 * v3c), atol=1e-10)
    # Covariance: the closure phases' covariance read back from OI_CORR equals T C T^T.
    t = closure_matrix()
    np.testing.assert_allclose(t3.covariance, t @ cov[21:, 21:] @ t.T, rtol=1e-6)


def test_creation_date_follows_source_date_epoch(monkeypatch):
    """DATE is today (UTC) unless SOURCE_DATE_EPOCH fixes it (a run resumed after
    midnight then writes the bytes of an uninterrupted one); a value that is not a
    number of seconds is ignored, as the convention says."""
    import datetime

    from amigo.io.oifits_write import creation_date

    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    before = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
    today = creation_date()
    after = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
    assert today in (before, after)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", str(19_000 * 86_400 + 86_399))  # last second
    assert creation_date() == "2022-01-08"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    assert creation_date() in (before, after)


def test_the_photon_count_and_science_files_travel_with_the_file(tmp_path):
    """amigo's OIFITS file carries the fit's photon count (NPHOT) and science files
    (SCI_n) as its calvis file does: detection reads the count instead of estimating it
    from the closure phases' errors (Ireland 2013's N_p = 1.5 N_h^2 / sigma_CP^2), which it
    still does for a file without it."""
    from astropy.io import fits

    from amigo.companions.observables import from_oifits
    from detect_helpers import write_point_source_oifits

    with_count = write_point_source_oifits(
        tmp_path / "a.oifits", science_files=["jw_a_cal.fits"], n_photons=3.2e9
    )
    header = fits.getheader(with_count, 0)
    assert header["NPHOT"] == 3.2e9 and (header["NSCI"], header["SCI_1"]) == (1, "jw_a_cal.fits")
    block = from_oifits(read_oifits(with_count))
    assert (block.n_photons, block.photon_source) == (3.2e9, "NPHOT")

    # Another tool's file with a keyword of that name: not read (not the standard's).
    foreign = tmp_path / "foreign.oifits"
    with fits.open(with_count) as hdul:
        hdul[0].header["PROCSOFT"] = "AMICAL"
        hdul.writeto(foreign)
    assert from_oifits(read_oifits(foreign)).photon_source == "closure-phase errors"

    without = from_oifits(read_oifits(write_point_source_oifits(tmp_path / "b.oifits")))
    assert without.photon_source == "closure-phase errors"
    # sigma_CP of each closure phase: three baseline phases of 1e-2 rad each in quadrature
    sigma_cp = np.sqrt(3) * 1e-2
    np.testing.assert_allclose(without.n_photons, 1.5 * 7**2 / sigma_cp**2, rtol=1e-5)
