"""End to end through ``amigo simulate``: files, headers, orientation, reproducibility."""

from __future__ import annotations

import json

import numpy as np
import pytest
from astropy.coordinates import SkyCoord
from astropy.io import fits
from astropy.wcs import WCS
from scipy import optimize

from amigo.cli import main
from amigo.orientation import Orientation, separation_pa

SWITCHES_OFF = "\n".join(
    f"{name} = false"
    for name in (
        "poisson", "flat_field", "intra_pixel", "bfe", "ipc", "nonlinearity", "dark_current",
        "bias", "reset_noise", "read_noise", "one_over_f", "cosmic_rays", "adc_inl", "saturation",
    )
)  # fmt: skip


def scenario_text(*, companion: bool = True, detector: str = "") -> str:
    """A small, fast scenario: one star, optionally with a companion 400 mas due east."""
    text = f"""
name = "east-test"
program = 99
date_obs = "2025-01-02"
time_obs = "03:04:05.000"
illumination = "analytic"
n_wavelengths = 2
oversample = 2

[detector]
{detector}

[[targets]]
name = "STAR"
catalog_name = "HD 1"
ra_deg = 150.0
dec_deg = 30.0
"""
    if companion:
        text += """
  [[targets.companions]]
  sep_mas = 400.0
  pa_deg = 90.0
  dmag = { F430M = 0.5 }
"""
    text += """
[[exposures]]
role = "science"
target = "STAR"
filter = "F430M"
observation = 1
ngroups = 4
nints = 3
nints_full = 6
photons_full = 1.5e7
pa_aper_deg = 217.0
offset_pix = [0.2, -0.3]
"""
    return text


def run_cli(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    return int(exit_info.value.code or 0)


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """One simulation with every default effect on (seed 7)."""
    folder = tmp_path_factory.mktemp("sim")
    path = folder / "east.toml"
    path.write_text(scenario_text(), encoding="utf-8")
    assert run_cli("simulate", str(path), "--out", str(folder / "a"), "--seed", "7") == 0
    return path, folder


STEM = "jw00099001001_01101_00001_nis"


def test_files_validate_and_open_with_the_readers(default_run):
    from stdatamodels.jwst.datamodels import Level1bModel

    from amigo.io.jwst import read_header

    _, folder = default_run
    uncal = folder / "a" / f"{STEM}_uncal.fits"
    with Level1bModel(str(uncal)) as model:
        model.validate()
        assert model.data.shape == (3, 4, 80, 80) and model.data.dtype == np.uint16
        assert model.meta.exposure.type == "NIS_AMI"
        assert model.meta.instrument.pupil == "NRM"
        assert model.meta.subarray.name == "SUB80"
        assert model.meta.observation.program_number == "00099"
    meta = read_header(uncal)
    assert (meta.kind, meta.ngroups, meta.nints, meta.filter) == ("uncal", 4, 3, "F430M")
    assert run_cli("info", str(uncal)) == 0
    with fits.open(uncal) as hdul:
        primary, sci = hdul[0].header, hdul["SCI"].header
        for key in ("TARGPROP", "PROGRAM", "OBSERVTN", "VISIT", "EXPOSURE", "TARG_RA", "TARG_DEC",
                    "DATE-OBS", "TIME-OBS", "EXPSTART", "READPATT", "TFRAME", "TGROUP",
                    "SUBSTRT1", "SUBSTRT2", "SUBSIZE1", "SUBSIZE2", "NFRAMES", "GROUPGAP"):  # fmt: skip
            assert key in primary, key
        for key in ("ROLL_REF", "V3I_YANG", "VPARITY", "PA_APER"):
            assert key in sci, key
        assert sci["PA_APER"] == pytest.approx(217.0)
        assert sci["ROLL_REF"] == pytest.approx(217.0 - sci["V3I_YANG"])
        raw = hdul["SCI"].data
        # Bias ~12000 DN, and the star's signal on top of it.
        assert 10000 < np.median(raw[:, 0]) < 14000
        assert (raw[:, -1].astype(float) - raw[:, 0]).max() > 1000
    truth = json.loads((folder / "a" / f"{STEM}_truth.json").read_text())
    assert truth["uncal"] == uncal.name and truth["seed"] == 7
    assert len(truth["photons"]["detected_per_integration"]) == 3
    assert truth["photons"]["expected_total_full"] == pytest.approx(1.5e7, rel=1e-9)
    assert np.mean(truth["photons"]["detected_per_integration"]) == pytest.approx(
        truth["photons"]["expected_per_integration"], rel=0.01
    )
    assert truth["scene"]["companions"][0]["pa_deg"] == 90.0
    assert set(truth["detector"]["per_pixel"]) == {
        "flat",
        "nonlinearity_c2_per_e",
        "bias_dn",
        "dark_e_per_s",
    }
    assert np.asarray(truth["instrument_state"]["zernike_nm"]).shape == (7, 10)


def test_same_seed_identical_files_other_seed_different(default_run, tmp_path):
    path, folder = default_run
    assert run_cli("simulate", str(path), "--out", str(tmp_path / "b"), "--seed", "7") == 0
    assert run_cli("simulate", str(path), "--out", str(tmp_path / "c"), "--seed", "8") == 0
    for suffix in ("_uncal.fits", "_truth.json"):
        first = (folder / "a" / f"{STEM}{suffix}").read_bytes()
        assert (tmp_path / "b" / f"{STEM}{suffix}").read_bytes() == first
        assert (tmp_path / "c" / f"{STEM}{suffix}").read_bytes() != first


def test_a_noise_seed_keeps_the_telescope_and_detector_and_draws_other_noise(default_run, tmp_path):
    """--noise-seed: the instrument state and the detector's per-pixel maps of --seed,
    other noise; a noise seed equal to the seed draws the same counts as none."""
    path, folder = default_run
    out = tmp_path / "n"
    assert (
        run_cli("simulate", str(path), "--out", str(out), "--seed", "7", "--noise-seed", "9") == 0
    )
    same = tmp_path / "s"
    assert (
        run_cli("simulate", str(path), "--out", str(same), "--seed", "7", "--noise-seed", "7") == 0
    )
    first = json.loads((folder / "a" / f"{STEM}_truth.json").read_text())
    other = json.loads((out / f"{STEM}_truth.json").read_text())
    assert other["seed"] == 7 and other["noise_seed"] == 9 and first["noise_seed"] is None
    assert other["detector"] == first["detector"]
    assert other["instrument_state"] == first["instrument_state"]
    data = fits.getdata(folder / "a" / f"{STEM}_uncal.fits", "SCI")
    assert not np.array_equal(fits.getdata(out / f"{STEM}_uncal.fits", "SCI"), data)
    assert np.array_equal(fits.getdata(same / f"{STEM}_uncal.fits", "SCI"), data)
    assert fits.getheader(out / f"{STEM}_uncal.fits")["SIMNSEED"] == 9


def _last_group(folder):
    return fits.getdata(folder / f"{STEM}_uncal.fits", "SCI")[0, -1].astype(float)


@pytest.mark.filterwarnings("ignore::astropy.wcs.FITSFixedWarning")  # 4-D SCI: wcslib pads CD
def test_companion_at_pa_90_lands_east_per_header_and_wcs(tmp_path):
    """Simulate with and without the companion (noiseless, linear detector), find it in the
    difference image, and map its pixel position to the sky with the file's own header
    (amigo.orientation) and independently with astropy's WCS of the SCI header."""
    for name, companion in (("with", True), ("without", False)):
        path = tmp_path / f"{name}.toml"
        path.write_text(scenario_text(companion=companion, detector=SWITCHES_OFF), encoding="utf-8")
        assert run_cli("simulate", str(path), "--out", str(tmp_path / name)) == 0
    template = _last_group(tmp_path / "without")  # the primary alone, at (45.2, 39.7)
    data = _last_group(tmp_path / "with")
    y0, x0 = np.unravel_index(np.argmax(data - template), data.shape)
    star_x, star_y = 45.2, 39.7  # reference pixel (45, 40) + offset_pix
    # Fit data = a * template + b * (template shifted by (dx, dy)): the exposure's total
    # photon count is fixed, so the primary is fainter when the companion shares it. The
    # shift uses the Fourier theorem (the images are band-limited): an estimate
    # independent of the simulator's geometry.
    spectrum = np.fft.fft2(template)
    fy = np.fft.fftfreq(80)[:, None]
    fx = np.fft.fftfreq(80)[None, :]

    def misfit(shift):
        shifted = np.fft.ifft2(
            spectrum * np.exp(-2j * np.pi * (fx * shift[0] + fy * shift[1]))
        ).real
        design = np.stack([template.ravel(), shifted.ravel()], 1)
        coeffs = np.linalg.lstsq(design, data.ravel(), rcond=None)[0]
        return np.sum((data.ravel() - design @ coeffs) ** 2)

    start = (x0 - round(star_x), y0 - round(star_y))
    best = optimize.minimize(
        misfit, start, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6}
    )
    xc, yc = star_x + best.x[0], star_y + best.x[1]

    with fits.open(tmp_path / "with" / f"{STEM}_uncal.fits") as hdul:
        primary, sci = hdul[0].header, hdul["SCI"].header
    orientation = Orientation.from_header(primary, sci)
    dra, ddec = orientation.detector_to_sky(xc - star_x, yc - star_y)
    sep, pa = separation_pa(dra, ddec)
    assert dra > 390 and abs(ddec) < 5  # east
    assert pa == pytest.approx(90.0, abs=0.5) and sep == pytest.approx(400.0, abs=3.0)

    wcs = WCS(sci).celestial
    assert wcs.naxis == 2
    star = wcs.pixel_to_world(star_x, star_y)
    assert star.ra.deg == pytest.approx(150.0) and star.dec.deg == pytest.approx(30.0)
    found = wcs.pixel_to_world(xc, yc)
    assert star.position_angle(found).deg == pytest.approx(90.0, abs=0.5)
    assert star.separation(found).mas == pytest.approx(400.0, abs=3.0)
    # The WCS and the orientation keywords agree for any offset (to the TAN projection's
    # second order over a few arcsec).
    for dx, dy in ((10.0, 0.0), (0.0, 10.0), (-7.0, 13.0)):
        sky = wcs.pixel_to_world(star_x + dx, star_y + dy)
        sep_o, pa_o = separation_pa(*orientation.detector_to_sky(dx, dy))
        assert star.separation(sky).mas == pytest.approx(float(sep_o), rel=1e-5)
        assert star.position_angle(sky).deg == pytest.approx(float(pa_o), abs=1e-4)
    assert isinstance(star, SkyCoord)


def test_full_uses_the_programs_integrations_and_photons(default_run, tmp_path):
    path, _ = default_run
    assert run_cli("simulate", str(path), "--out", str(tmp_path), "--full") == 0
    assert fits.getheader(tmp_path / f"{STEM}_uncal.fits")["NINTS"] == 6
    truth = json.loads((tmp_path / f"{STEM}_truth.json").read_text())
    assert truth["full"] is True
    assert truth["photons"]["expected_total"] == pytest.approx(1.5e7, rel=1e-9)
    # Flat field (mean ~1) and Poisson noise: within 1 %.
    assert truth["photons"]["detected_total"] == pytest.approx(1.5e7, rel=0.01)


def test_cli_errors_exit_2_with_one_line(tmp_path, capsys):
    assert run_cli("simulate", "no-such-scenario", "--out", str(tmp_path)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no-such-scenario" in err[0]
    bad = tmp_path / "bad.toml"
    bad.write_text(scenario_text().replace("ngroups = 4", "ngroups = 0"), encoding="utf-8")
    assert run_cli("simulate", str(bad), "--out", str(tmp_path)) == 2
    assert "positive integer" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.fits"))
