"""The optics figures render to PNG files (Agg) from a real model."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from amigo import niriss
from amigo.model.optics import NRMOptics, OpticsConfig, PointSource
from amigo.plots import optics as plots


def test_optics_figures_are_written(tmp_path):
    config = OpticsConfig(npix_detector=40, pupil_npix=96)
    z = jnp.asarray(np.random.default_rng(0).normal(0, 20, (7, 10)))
    optics = NRMOptics.create(config, zernikes_nm=z)
    source = PointSource.create("F430M", n_wavelengths=3)
    image = np.asarray(optics.illuminance(source.spectrum, source.position_arcsec))
    scale = config.pixel_scale_arcsec / config.oversample
    figures = {
        "pupil.png": plots.pupil_figure(optics),
        "psf.png": plots.psf_figure(image, scale),
        "power.png": plots.power_spectrum_figure(image, scale, 4.3e-6),
    }
    for name, fig in figures.items():
        path = plots.save(fig, tmp_path / name)
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The power spectrum figure overlays all 21 baselines (and their mirrors).
    ax = figures["power.png"].axes[0]
    offsets = np.concatenate([c.get_offsets() for c in ax.collections])
    assert len(offsets) == 2 * len(niriss.baseline_pairs()) == 42
