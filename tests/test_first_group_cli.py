"""`amigo process` then `amigo fit --superbias` on raw ramps written by tests/ramp_sim.py
(not amigo's simulator): the first group enters the fit and NPHOT counts it, at two groups
and at one (where the first read is the only measurement) (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from astropy.io import fits

from jwst_files import nominal_star
from ramp_sim import GAIN_E_PER_DN, simulate, write_uncal

pytestmark = pytest.mark.slow

NINTS, TGROUP = 60, 0.07544


@pytest.mark.parametrize(("ngroups", "source"), [(2, "model"), (1, "files")])
def test_fit_with_superbias_uses_every_group(tmp_path, capsys, ngroups, source):
    """``source``: the superbias comes from ``--superbias`` files, or from a base model
    that ``amigo train --darks`` stored it in."""
    from amigo.cli import main
    from amigo.model.base import BaseModel, BaseModelConfig, save_base_model
    from amigo.model.image import Instrument, save_instrument

    rng = np.random.default_rng(11)
    bias = 11000.0 + 200.0 * rng.standard_normal((80, 80))
    flux_dn_s = 3.0e6  # entering the mask; peak ~ 20,000 DN per group
    image = nominal_star("F480M", flux_dn_s)
    raw = tmp_path / "raw"
    raw.mkdir()
    files = {}
    for name, observation, nints, groups, rate in (
        ("sci", "001", NINTS, ngroups, image),
        ("cal", "002", NINTS, ngroups, image),
        ("dark", "003", 400, 2, np.zeros((80, 80))),  # a superbias needs two groups
    ):
        ramps = simulate(rng, nints, groups, rate * TGROUP, bias, read_dn=12.0)
        files[name] = write_uncal(
            raw / f"jw09999{observation}001_03102_00001_nis_uncal.fits",
            ramps.raw,
            TARGPROP=f"STAR-{name}",
            TARGNAME=f"STAR-{name}",
            OBSERVTN=observation,
        )
    slopes = tmp_path / "calslope"

    def run(args):
        try:
            main([str(a) for a in args])
        except SystemExit as exit_:
            return exit_.code
        return 0

    assert run(["process", *files.values(), "--out", slopes]) == 0
    calslope = {k: slopes / v.name.replace("_uncal", "_calslope") for k, v in files.items()}
    model = tmp_path / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), model)
    out = tmp_path / "fit"
    args = ["fit", "--sci", calslope["sci"], "--cal", calslope["cal"], "--out", out,
            "--knots", 27, "--knot-spacing", 0.5]  # fmt: skip
    if source == "files":
        args += ["--model", model]
        if ngroups == 1:  # no slope: without a superbias there is nothing to fit
            assert run(args) == 2
            message = capsys.readouterr().err
            assert calslope["sci"].name in message and "--superbias" in message
            assert not out.exists()
        assert run([*args, "--superbias", calslope["dark"]]) == 0
        assert "superbias from 1 file(s)" in capsys.readouterr().err
    else:  # train --darks stores it; fit finds it in the model
        base, trained = tmp_path / "base.npz", tmp_path / "trained.npz"
        config = BaseModelConfig(filters=("F480M",), n_wavelengths=3)
        save_base_model(BaseModel.create(config, linear=True), base)
        train = ["train", "--init", base, "--steps", 0, "--cal", calslope["cal"],
                 "--darks", calslope["dark"], "--out", trained]  # fmt: skip
        assert run(train) == 0
        assert run([*args, "--model", trained, "--superbias", calslope["dark"],
                    "--no-first-group"]) == 2  # fmt: skip
        assert run([*args, "--model", trained]) == 0
        assert "superbias from the base model (1 dark file(s)" in capsys.readouterr().err
    summary = json.loads((out / "fit_summary.json").read_text())
    for exposure in summary["exposures"]:
        # NGROUPS values per pixel (the first group, then the slopes), fitted to the noise
        assert exposure["npix"] * ngroups - exposure["dof"] < 0.1 * exposure["npix"]
        assert exposure["zscore_std"] == pytest.approx(1.0, abs=0.1)
    # NPHOT: every group's photons, NINTS * NGROUPS * TGROUP of the star's count rate
    calvis = next(out.glob("*_calvis.fits"))
    photons = fits.getval(calvis, "NPHOT")
    expected = flux_dn_s * GAIN_E_PER_DN * NINTS * ngroups * TGROUP
    assert photons == pytest.approx(expected, rel=0.05)
