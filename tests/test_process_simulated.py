"""Processing the project's own simulated ramps: slope means agree with the simulator's
truth within the errors that `amigo process` reports.

A uniformly illuminated (flat-field) exposure gives an expected slope for every pixel from
the truth file alone: the expected photo-electrons of the integration shared in proportion
to the true flat field, plus the true per-pixel dark current. Noise, bias, reset, 1/f,
cosmic rays and the ADC non-linearity are on; the effects that move charge between pixels
or bend the response (brighter-fatter, IPC, non-linearity) are off, since the expectation
would then need the fitting model itself.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from amigo import niriss
from amigo.cli import main
from amigo.io.calslope import read_calslope

SCENARIO = """
name = "flat-truth"
program = 98
date_obs = "2025-01-02"
time_obs = "03:04:05.000"

[detector]
nonlinearity = false
bfe = false
ipc = false

[[exposures]]
role = "flat"
filter = "F430M"
observation = 1
ngroups = 5
nints = 40
peak_dn = 4000
"""


def run(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    return int(exit_info.value.code or 0)


def test_slopes_of_simulated_flat_agree_with_truth(tmp_path):
    scenario = tmp_path / "flat.toml"
    scenario.write_text(SCENARIO, encoding="utf-8")
    assert run("simulate", str(scenario), "--out", str(tmp_path / "sim"), "--seed", "3") == 0
    (uncal,) = (tmp_path / "sim").glob("*_uncal.fits")
    (truth_file,) = (tmp_path / "sim").glob("*_truth.json")
    assert run("process", str(uncal), "--out", str(tmp_path / "proc")) == 0
    (calslope,) = (tmp_path / "proc").glob("*_calslope.fits")

    truth = json.loads(truth_file.read_text())
    product = read_calslope(calslope)
    flat = np.asarray(truth["detector"]["per_pixel"]["flat"])
    dark_e_per_s = np.asarray(truth["detector"]["per_pixel"]["dark_e_per_s"])
    ngroups = truth["exposure"]["ngroups"]
    group_time = truth["exposure"]["group_time_s"]
    electrons = truth["photons"]["expected_per_integration"] * flat / flat.sum()
    expected_dn = (electrons / ngroups + dark_e_per_s * group_time) / niriss.GAIN_E_PER_DN

    use = ~product.badpix.astype(bool) & ~niriss.reference_row_mask()
    assert use.sum() > 0.9 * 76 * 80
    residual = product.slope_dn - expected_dn[None]
    sigma = np.sqrt(np.einsum("iiyx->iyx", product.slope_cov_dn2))
    z = (residual / sigma)[:, use]
    assert abs(z.mean()) < 0.05  # no bias: 0.05 sigma over ~24,000 slopes
    assert 0.9 < z.std() < 1.15  # errors are honest (1/f noise adds a little)
    # Full covariance: the chi-square per pixel of its correlated slopes. The covariance is
    # estimated from the same n integrations, and the inverse of a sample covariance is
    # biased high: E[S^-1] = Sigma^-1 (n - 1) / (n - p - 2) (Wishart, p = ngroups - 1
    # slopes), so chi2 / p is expected at 39 / 34 = 1.147 here, not 1.
    cov = product.slope_cov_dn2.transpose(2, 3, 0, 1)[use]
    r = residual.transpose(1, 2, 0)[use]
    chi2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(cov), r)
    n, p = truth["exposure"]["nints"], ngroups - 1
    assert chi2.mean() / p == pytest.approx((n - 1) / (n - p - 2), abs=0.05)
