"""The detector geometry and the jitter are fitted (not frozen): a simulated calibrator
made with a known rotation, skew, anisotropy and jitter away from the nominal values is
fitted back by the Levenberg-Marquardt solver of ``amigo fit``."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.basis import load_basis
from amigo.fitting import FilterFit, FitConfig, FitExposure
from amigo.likelihood import ImageData
from amigo.model import ExposureParams, FilterSetup, Instrument, OpticsParams, image_from_log_vis
from amigo.visibility import UVGrid


@pytest.mark.slow
def test_fit_recovers_a_known_rotation_skew_and_jitter(tmp_path, monkeypatch):
    monkeypatch.setenv("AMIGO_CACHE_DIR", str(tmp_path))
    instrument = Instrument.nominal(n_wavelengths=2)
    basis, _ = load_basis(instrument, "F480M", UVGrid(5, 1.3))
    setup = FilterSetup.create("F480M", instrument, basis)
    nominal = np.asarray(instrument.detector.geometry())
    # Truth: 0.25 deg more clockwise, 0.3 deg more skew, 0.2 % more anisotropy; jitter
    # 8 mas (nominal 21.4) -- far outside the errors of a bright exposure.
    truth = nominal + np.array([-0.25, 2e-3, 0.3, 0.0])
    jitter_mas = 8.0
    optics = OpticsParams.from_instrument(instrument)
    optics = OpticsParams(
        optics.zernikes_nm,
        optics.defocus_nm,
        jnp.asarray(truth, jnp.float32),
        jnp.zeros((), jnp.float32),
    )
    exposure = ExposureParams(
        jnp.asarray([0.02, -0.01], jnp.float32), jnp.log(jnp.float32(2e7)), jnp.float32(jitter_mas)
    )
    image = np.asarray(
        image_from_log_vis(instrument, setup, optics, jnp.zeros(()), exposure, None, None),
        np.float64,
    )
    rng = np.random.default_rng(0)
    sigma = np.sqrt(image + 30.0**2)
    data = ImageData(image + sigma * rng.normal(size=image.shape), sigma, np.ones_like(image, bool))
    fit = FilterFit(instrument, setup, [FitExposure("c", "calibrator", "C", data)])
    result = fit.fit(FitConfig())
    fitted = np.asarray(result.params.optics.geometry, np.float64)
    jitter = abs(float(result.params.exposures.jitter_mas[0]))
    print(f"\ntruth {truth}, fitted {fitted}; jitter truth {jitter_mas}, fitted {jitter:.2f} mas")
    assert result.converged
    assert fitted[0] == pytest.approx(truth[0], abs=0.02)  # rotation (deg)
    assert fitted[2] == pytest.approx(truth[2], abs=0.03)  # skew (deg)
    assert fitted[1] == pytest.approx(truth[1], abs=5e-4)  # anisotropy
    assert jitter == pytest.approx(jitter_mas, abs=3.0)
