"""The image-level forward model: Fourier-shift positions, flux, units."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.model.image import (
    ExposureParams,
    FilterSetup,
    Instrument,
    OpticsParams,
    image_from_log_vis,
    locate,
)


@pytest.mark.slow
def test_fourier_shift_equals_pupil_tilt_and_conserves_flux():
    """Positions are applied as Fourier phase ramps on PSFs of a widened field; the optics
    model of issue 3 applies them as a pupil tilt. Both must give the same image."""
    instrument = Instrument.nominal(n_wavelengths=3)
    setup = FilterSetup.create("F430M", instrument)
    position = jnp.array([0.05, -0.031])
    flux = 1e6
    ours = image_from_log_vis(
        instrument,
        setup,
        OpticsParams.from_instrument(instrument),
        jnp.zeros(()),
        ExposureParams(position, jnp.log(flux), instrument.detector.jitter_arcsec * 1000),
        None,
        None,
    )
    spectrum = setup.spectrum(jnp.zeros(()))
    reference = instrument.detector(instrument.optics.illuminance(spectrum, position), flux)
    ours, reference = np.asarray(ours), np.asarray(reference)
    # Measured 3e-6 of the peak with the 4-pixel margin (2e-3 without).
    assert np.abs(ours - reference).max() < 2e-5 * reference.max()
    np.testing.assert_allclose(ours.sum(), reference.sum(), rtol=1e-5)


@pytest.mark.slow
def test_locate_recovers_a_shift():
    instrument = Instrument.nominal(n_wavelengths=3)
    setup = FilterSetup.create("F480M", instrument)
    optics = OpticsParams.from_instrument(instrument)

    def image(position, flux):
        return np.asarray(
            image_from_log_vis(
                instrument,
                setup,
                optics,
                jnp.zeros(()),
                ExposureParams(
                    jnp.asarray(position), jnp.log(flux), instrument.detector.jitter_arcsec * 1e3
                ),
                None,
                None,
            )
        )

    template = image([0.0, 0.0], 1.0)
    truth = np.array([0.12, -0.07])  # arcsec, optical frame
    data = image(truth, 5e5)
    mask = np.ones_like(data, bool)
    position, flux = locate(data, mask, template, instrument.detector)
    np.testing.assert_allclose(position, truth, atol=0.01)  # well within a pixel (0.065")
    np.testing.assert_allclose(flux, 5e5, rtol=0.05)


def test_an_instrument_file_keeps_its_wavelengths(tmp_path):
    """``save_instrument`` / ``load_instrument`` round trip: the static settings too (an
    instrument saved with 3 wavelengths is fitted with 3, not the nominal 9); a format-1
    file (arrays alone) loads with the nominal settings; a damaged header is one
    InputError naming the file."""
    import equinox as eqx

    from amigo.errors import InputError
    from amigo.model.image import DEFAULT_N_WAVELENGTHS, load_instrument, save_instrument

    instrument = Instrument.nominal(n_wavelengths=3)
    instrument = eqx.tree_at(lambda i: i.optics.defocus_nm, instrument, jnp.float32(12.5))
    save_instrument(instrument, tmp_path / "three.eqx")
    loaded = load_instrument(tmp_path / "three.eqx")
    assert loaded.n_wavelengths == 3 and loaded.name == instrument.name
    assert eqx.tree_equal(loaded, instrument)
    eqx.tree_serialise_leaves(tmp_path / "old.eqx", instrument)  # format 1
    old = load_instrument(tmp_path / "old.eqx")
    assert old.n_wavelengths == DEFAULT_N_WAVELENGTHS != 3
    assert float(old.optics.defocus_nm) == 12.5
    damaged = tmp_path / "damaged.eqx"
    damaged.write_bytes((tmp_path / "three.eqx").read_bytes().replace(b'"n_wavelengths"', b"x"))
    with pytest.raises(InputError, match=r"damaged\.eqx"):
        load_instrument(damaged)
