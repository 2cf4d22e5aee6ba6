"""The charge-migration network against a brighter-fatter effect amigo did not write.

``benchmarks/independent_sim.py`` (no amigo code) moves pixel boundaries by the field of
the charge already collected (a point charge's boundary-normal field, summed over the
pixels within three of the boundary) and lets the photo-electrons falling in the swept
strips change pixel. The shipped base model's network learned its migration from amigo's
own simulator, whose brighter-fatter effect is written differently (sub-pixel strips of
the oversampled image, another kernel). For the same AMI illumination, flat and
intra-pixel response, the two must move charge in the same pattern; the ratio of their
amplitudes is the physical strength the network stands for (docs/fidelity.md, "Raw
ramps with a brighter-fatter effect").
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("poppy", reason="poppy (the test extra) computes the independent PSF")
pytest.importorskip("pysiaf", reason="pysiaf (the test extra) maps the pixels")
pytest.importorskip("synphot", reason="synphot (the test extra) weighs the band")
pytest.importorskip("svo_filters", reason="svo_filters holds the filter curves")

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "independent_sim.py"


@pytest.fixture(scope="module")
def isim():
    spec = importlib.util.spec_from_file_location("independent_sim", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    # A coarser band and a smaller field than the benchmark's: the core is what migrates.
    module.N_WAVELENGTHS = 5
    module.FINE_NPIX = 401
    return module


def test_network_migration_follows_boundary_shift_physics(isim) -> None:
    from amigo.model.base import default_model_path, load_base_model

    base = load_base_model(default_model_path())
    maps = isim.load_detector_maps(default_model_path())
    rng = np.random.default_rng(0)
    opd = isim.wavefront_m(rng.normal(0.0, isim.ZERNIKE_NM_RMS * 1e-9, size=8))
    psf = isim.polychromatic_psf("F480M", 4500.0, isim.pupil_amplitude(), opd, 12.0)
    star = (46.23, 40.69)
    # HD 37093's F480M exposure: 1.66e6 e-/s in the subarray, 12 groups of 75.44 ms.
    integration_s = 12 * 0.07544
    electrons = 1.66e6 * integration_s

    # The network's input: the 3 x 3 sub-pixel illuminance (e- per integration).
    isim.SUBSAMPLE = 3
    sub3 = isim.pixel_subsamples(psf, star)
    illuminance = (sub3 * (electrons / sub3.sum())).transpose(0, 2, 1, 3).reshape(240, 240)
    illuminance = jnp.asarray(illuminance, jnp.float32)
    linear_ramp = base.ramp.__class__(
        network=None,
        flat=base.ramp.flat,
        intra_pixel=base.ramp.intra_pixel,
        n_substeps=base.ramp.n_substeps,
        max_shift_pix=base.ramp.max_shift_pix,
    )
    network = (
        np.asarray(base.ramp(illuminance, 12))[-1] - np.asarray(linear_ramp(illuminance, 12))[-1]
    )

    # The independent physics at 1e-6 pixels per electron, same flat and response.
    isim.SUBSAMPLE = 5
    sub5 = isim.pixel_subsamples(psf, star)
    sub5 = sub5 * (electrons / integration_s / sub5.sum())
    sub5 = sub5 * isim.intra_pixel_weights(maps["intra"]) * maps["flat"][:, :, None, None]
    physics = isim.migrated_charge(sub5, integration_s, 1.0e-6)

    peak = float(np.asarray(linear_ramp(illuminance, 12))[-1].max())
    assert 0.01 < np.abs(physics).max() / peak < 0.05  # a per-cent effect at ~24k e-
    # Charge is conserved by both: what leaves the core arrives around it.
    assert abs(physics.sum()) < 1e-6 * np.abs(physics).sum()
    assert abs(float(network.sum())) < 1e-3 * float(np.abs(network).sum())
    correlation = np.corrcoef(network.ravel(), physics.ravel())[0, 1]
    strength = float(network.ravel() @ physics.ravel() / (physics.ravel() @ physics.ravel()))
    print(f"correlation {correlation:.4f}, strength {strength:.3f}e-6 pix/e-, peak {peak:.0f} e-")
    assert correlation > 0.98, correlation
    # The network moves as much charge as boundaries shifting 1.2-1.8e-6 pixel per electron.
    assert 1.2 < strength < 1.8, strength
