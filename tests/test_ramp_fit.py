"""Science fits through the base model's detector (amigo.fitting.ramp_fit).

* Units and the correction, against direct calculations: with a detector that is linear,
  flat (between and within pixels), free of IPC and non-linearity the base model's slopes equal the fit's image times
  the group time (the correction vanishes); with the default IPC kernel the correction is
  that kernel applied to the image, minus the image, computed here by an explicit 5 x 5
  convolution.
* The fixed-point iteration, end to end: slopes simulated *with the shipped network*
  (brighter-fatter charge migration) and Gaussian noise of the right covariance are fitted
  by ``extract_filter(..., detector=RampDetector(...))``; the residuals at the end are the
  full model's and must be pure noise (chi2/dof within 3 sigma of 1), the position and
  flux recovered; the brighter-fatter signal in the data is checked to be far above the
  noise (so that a model without the network could not pass).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from astropy.io import fits

from amigo.fitting.filter_fit import FilterFit, FitConfig, FitExposure
from amigo.fitting.newton import psfs_of
from amigo.fitting.ramp_fit import RampDetector, RampInput, _slopes_and_image
from amigo.io.calslope import CalSlope
from amigo.likelihood.pixels import ImageData
from amigo.model.base import load_base_model
from amigo.model.basis import load_basis
from amigo.model.detector.ramp import IntraPixelResponse
from amigo.model.detector.read import default_ipc_kernel
from amigo.model.image import FilterSetup, Instrument, OpticsParams
from amigo.model.visibility import UVGrid
from amigo.observables.extract import extract_filter

FILTER = "F480M"
GROUP_TIME_S = 0.07544
NGROUPS = 8
NINTS = 60
READ_NOISE_DN = 12.0
ELECTRONS = 3.0e6  # per integration in the field: peak pixels near 30,000 DN


@pytest.fixture(scope="module")
def setting(tmp_path_factory):
    """The shipped base model, its instrument with 3 wavelengths, a 27 x 27 basis."""
    import os

    cache = tmp_path_factory.mktemp("cache")
    old = os.environ.get("AMIGO_CACHE_DIR")
    os.environ["AMIGO_CACHE_DIR"] = str(cache)
    base = load_base_model()
    full = Instrument.from_base_model(base, FILTER)
    instrument = Instrument(
        optics=full.optics, detector=full.detector, n_wavelengths=3, name="test"
    )
    basis, _ = load_basis(instrument, FILTER, UVGrid(27, 0.5))
    setup = FilterSetup.create(FILTER, instrument, basis)
    yield base, instrument, setup
    if old is None:
        os.environ.pop("AMIGO_CACHE_DIR", None)
    else:
        os.environ["AMIGO_CACHE_DIR"] = old


def _theta(setup, instrument, position_arcsec, log_flux):
    """The local vector ``[x, y, log_flux, slope, jitter_mas, latents]`` (newton.py)."""
    n_latent = setup.basis.n_amp + setup.basis.n_phase
    jitter_mas = 1000.0 * float(instrument.detector.jitter_arcsec)
    return jnp.asarray(
        [*position_arcsec, log_flux, 0.0, jitter_mas, *np.zeros(n_latent)], jnp.float32
    )


def _truth(base, instrument, setup, position_arcsec, electrons=ELECTRONS, first_group=False):
    """(slopes DN per group, image DN/s, log_flux) of a point source; with
    ``first_group`` the first read (DN since the reset) in front of the slopes."""
    scale = base.read.gain_e_per_dn * NGROUPS * GROUP_TIME_S
    log_flux = float(np.log(electrons / scale))
    anchor = jnp.zeros(2, jnp.float32)
    psfs = psfs_of(instrument, setup, OpticsParams.from_instrument(instrument), anchor)
    slopes, image = _slopes_and_image(
        base,
        instrument,
        setup,
        psfs,
        anchor,
        _theta(setup, instrument, position_arcsec, log_flux),
        jnp.asarray(scale, jnp.float32),
        NGROUPS,
        first_group,
    )
    return np.asarray(slopes, float), np.asarray(image, float), log_flux


def _without_ipc(instrument: Instrument) -> Instrument:
    """The instrument with a linear detector that has no IPC kernel."""
    return dataclasses.replace(
        instrument, detector=dataclasses.replace(instrument.detector, ipc_kernel=None)
    )


def _ipc(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Explicit 5 x 5 convolution with zero padding."""
    padded = np.pad(image, 2)
    out = np.zeros_like(image)
    ny, nx = image.shape
    for dy in range(5):
        for dx in range(5):
            out += kernel[dy, dx] * padded[4 - dy : 4 - dy + ny, 4 - dx : 4 - dx + nx]
    return out


def _plain(base):
    """The base model with a linear, flat detector: no IPC, dark or non-linearity."""
    linear = base.with_linear_detector()
    identity = np.zeros((5, 5))
    identity[2, 2] = 1.0
    return dataclasses.replace(
        linear,
        ramp=dataclasses.replace(
            linear.ramp, flat=jnp.ones((80, 80)), intra_pixel=IntraPixelResponse()
        ),
        read=dataclasses.replace(
            linear.read,
            ipc_kernel=jnp.asarray(identity),
            nonlinearity=jnp.zeros((80, 80)),
            dark_e_per_group=jnp.asarray(0.0),
        ),
    )


def test_correction_vanishes_for_a_linear_detector_and_is_the_ipc_otherwise(setting):
    base, instrument, setup = setting
    plain = _plain(base)
    # The fit's image without IPC (the instrument's linear detector has the base model's).
    no_ipc = _without_ipc(instrument)
    slopes, image, _ = _truth(plain, no_ipc, setup, (0.02, -0.01))
    expected = image * GROUP_TIME_S
    assert slopes.shape == (NGROUPS - 1, 80, 80)
    # float32 differences of reads of up to ~30,000 DN
    np.testing.assert_allclose(
        slopes, np.broadcast_to(expected, slopes.shape), atol=1e-4 * expected.max()
    )
    ipc = dataclasses.replace(
        plain, read=dataclasses.replace(plain.read, ipc_kernel=jnp.asarray(default_ipc_kernel()))
    )
    slopes, image, _ = _truth(ipc, no_ipc, setup, (0.02, -0.01))
    expected = _ipc(image, np.asarray(default_ipc_kernel())) * GROUP_TIME_S
    np.testing.assert_allclose(
        slopes, np.broadcast_to(expected, slopes.shape), atol=1e-4 * expected.max()
    )
    # ... and the IPC is not negligible: the correction is what is left
    assert np.abs(expected - image * GROUP_TIME_S).max() > 50 * 1e-4 * expected.max()


def test_first_read_is_one_group_of_signal_through_the_detector_model(setting):
    """With the first group in the likelihood the detector model's values are its first
    read (the charge since the reset, no bias) and then its slopes: for a linear flat
    detector each is ``t_g`` times the linear image, so the correction vanishes for the
    first value as for the slopes; with the network the first read and the first slope
    differ by the charge migration, not by a group of signal."""
    base, instrument, setup = setting
    no_ipc = _without_ipc(instrument)
    values, image, _ = _truth(_plain(base), no_ipc, setup, (0.02, -0.01), first_group=True)
    assert values.shape == (NGROUPS, 80, 80)
    expected = image * GROUP_TIME_S
    np.testing.assert_allclose(
        values, np.broadcast_to(expected, values.shape), atol=1e-4 * expected.max()
    )
    values, image, _ = _truth(base, instrument, setup, (0.02, -0.01), first_group=True)
    slopes, _, _ = _truth(base, instrument, setup, (0.02, -0.01))
    np.testing.assert_allclose(values[1:], slopes, atol=1e-5 * slopes.max())
    peak = np.unravel_index(np.argmax(image), image.shape)
    assert abs(values[0][peak] / slopes[0][peak] - 1) < 0.05


def test_level2_correction_is_the_pipeline_slope_of_the_model_ramp(setting):
    """The level-2 forward model: the pipeline's estimator on the base model's ramp.

    * For a linear, flat detector without IPC the correction vanishes (to float32).
    * With the network (brighter-fatter), ``for_level2`` (flat, dark, non-linearity off:
      the pipeline corrected them) gives a correction that is, pixel by pixel, the mean
      of the calslope correction over the ramp's slopes divided by the group time, to
      1e-3 of the peak: the pipeline's weights are symmetric about the ramp's middle,
      so for a smoothly bending ramp its slope is the mean slope. Computed by two routes,
      the stcal-equivalent estimator and the plain mean of group differences.
    * A flat in the base model does not reach a level-2 correction.
    """
    from amigo.fitting.ramp_fit import Level2Input

    base, instrument, setup = setting
    data = ImageData(np.zeros((80, 80)), np.ones((80, 80)), np.ones((80, 80), bool))
    level2 = Level2Input(data, NGROUPS, 1, GROUP_TIME_S)
    linear = base.with_linear_detector().for_level2()
    identity = np.zeros((5, 5))
    identity[2, 2] = 1.0
    plain = dataclasses.replace(
        linear,
        ramp=dataclasses.replace(linear.ramp, intra_pixel=IntraPixelResponse()),
        read=dataclasses.replace(linear.read, ipc_kernel=jnp.asarray(identity)),
    )
    slopes, image, _ = _truth(plain, _without_ipc(instrument), setup, (0.02, -0.01))
    correction = level2.correction(slopes, image)
    assert correction.shape == (80, 80)
    np.testing.assert_allclose(correction, 0.0, atol=2e-4 * image.max())

    full = base.for_level2()
    slopes, image, _ = _truth(full, instrument, setup, (0.02, -0.01))
    correction = level2.correction(slopes, image)
    calslope_route = (slopes - image[None] * GROUP_TIME_S).mean(axis=0) / GROUP_TIME_S
    np.testing.assert_allclose(correction, calslope_route, atol=1e-3 * image.max())
    # ... and the brighter-fatter part is well above that agreement.
    assert np.abs(correction).max() > 10 * 1e-3 * image.max()

    flat = 1.0 + 0.05 * np.random.default_rng(0).standard_normal((80, 80))
    flatted = dataclasses.replace(base, ramp=dataclasses.replace(base.ramp, flat=jnp.asarray(flat)))
    slopes_flat, _, _ = _truth(flatted.for_level2(), instrument, setup, (0.02, -0.01))
    np.testing.assert_allclose(slopes_flat, slopes, rtol=1e-5, atol=1e-3)


def test_detector_rounds_take_level2_and_first_group_inputs(setting):
    """One ``RampDetector`` pass over a level-2 image and a calslope exposure with its
    first group: the level-2 correction is an image (DN/s), the calslope one has NGROUPS
    values per pixel, the first read's among them (a route that once broke for level-2
    inputs, which have no first group)."""
    from amigo.fitting.ramp_fit import Level2Input
    from amigo.model.detector.reset import Superbias, with_first_group

    base, instrument, setup = setting
    slopes, image, _ = _truth(base, instrument, setup, (0.02, -0.01))
    mask = np.ones((80, 80), bool)
    level2 = Level2Input(ImageData(image, np.sqrt(np.abs(image)) + 1.0, mask), NGROUPS, 1,
                         GROUP_TIME_S)  # fmt: skip
    product = _calslope(slopes, np.random.default_rng(6), "b")
    known = Superbias(np.zeros((80, 80)), np.ones((80, 80)))
    ramp = RampInput(with_first_group(product, known), GROUP_TIME_S, first_group=True)
    exposures = [
        FitExposure("a", "calibrator", "STAR", level2.data),
        FitExposure("b", "calibrator", "STAR", ramp.image(None)),
    ]
    fit = FilterFit(instrument, setup, exposures)
    detector = RampDetector(base, {"a": level2, "b": ramp})
    level2_d, ramp_d = detector.corrections(fit, fit.initial_params())
    assert level2_d.shape == (80, 80) and np.isfinite(level2_d).all()
    assert ramp_d.shape == (NGROUPS, 80, 80) and np.isfinite(ramp_d).all()


def _calslope(slopes: np.ndarray, rng, name: str) -> CalSlope:
    """A calslope product: ``slopes`` plus Gaussian noise of the slopes' covariance
    (photon noise of each slope, and read noise correlating neighbouring slopes)."""
    gain = 1.61
    m = slopes.shape[0]
    poisson = np.clip(slopes, 0, None) / gain  # DN^2 per slope, one integration
    cov = np.zeros((m, m, 80, 80))
    for i in range(m):
        cov[i, i] = poisson[i] + 2 * READ_NOISE_DN**2
        if i + 1 < m:
            cov[i, i + 1] = cov[i + 1, i] = -(READ_NOISE_DN**2)
    cov /= NINTS
    chol = np.linalg.cholesky(np.moveaxis(cov, (0, 1), (2, 3)))  # (80, 80, m, m)
    noise = np.einsum("yxij,yxj->iyx", chol, rng.normal(size=(80, 80, m)))
    ng = m + 1
    return CalSlope(
        slope_dn=slopes + noise,
        slope_cov_dn2=cov,
        slope_support=np.full((m, 80, 80), float(NINTS)),
        ramp_dn=np.zeros((ng, 80, 80)),
        ramp_cov_dn2=np.zeros((ng, ng, 80, 80)),
        ramp_support=np.full((ng, 80, 80), float(NINTS)),
        badpix=np.zeros((80, 80), bool),
        badpix_reason=None,
        primary_header=fits.Header(),
        slope_header=fits.Header(),
        path=Path(f"{name}_calslope.fits"),
    )


def test_a_fit_on_corrected_data_keeps_the_psf_anchor(setting):
    """Each detector round refits on corrected slopes: its fit must compute the PSFs where
    the first fit did, or the parameters carried over describe another model (a rebuilt
    fit fell back to the field centre, and the refits stalled)."""
    base, instrument, setup = setting
    slopes, _, _ = _truth(base, instrument, setup, (0.15, -0.10))  # ~2 pixels off centre
    ramp = RampInput(_calslope(slopes, np.random.default_rng(5), "a"), GROUP_TIME_S)
    exposures = [FitExposure("a", "calibrator", "STAR", ramp.image(None))]
    fit = FilterFit(instrument, setup, exposures)
    params = fit.initial_params()
    assert np.linalg.norm(np.asarray(fit.anchor)) > 0.1  # located near the star
    corrected = fit.with_exposures(exposures)
    np.testing.assert_array_equal(corrected.anchor, fit.anchor)
    # Equal to float32 rounding, not bit for bit: two calls of one compiled program in
    # flight at once (JAX dispatches asynchronously) were seen to round differently on a
    # 2-core CPU (1e-7 of the peak). A fit that lost the anchor moves the PSF by pixels.
    expected = np.asarray(fit.models(params))
    np.testing.assert_allclose(
        np.asarray(corrected.models(params)), expected, rtol=0, atol=1e-6 * expected.max()
    )
    with pytest.raises(ValueError, match="other exposures"):
        fit.with_exposures([FitExposure("b", "calibrator", "STAR", ramp.image(None))])


def test_migration_scale_scales_the_charge_moved(setting):
    """``BaseModel.with_migration_scale(s)``: the network's last layer times ``s`` moves
    ``s`` times the charge (the displacements stay far inside their bound), 0 none."""
    base, instrument, setup = setting
    position = (0.02, -0.01)
    linear, _, _ = _truth(base.with_linear_detector(), instrument, setup, position)
    trained, _, _ = _truth(base, instrument, setup, position)
    moved = trained - linear
    assert np.abs(moved).max() > 1e-3 * trained.max()  # there is migration to scale
    none, _, _ = _truth(base.with_migration_scale(0.0), instrument, setup, position)
    np.testing.assert_allclose(none, linear, atol=1e-5 * trained.max())
    for scale in (0.5, 2.0):
        scaled, _, _ = _truth(base.with_migration_scale(scale), instrument, setup, position)
        # To first order in the scale: the charge moved also changes the charge that
        # drives the migration, a second-order term (measured: 3.5 % of the largest move
        # at half the scale, 7 % at twice, i.e. ~7 % per unit of |scale - 1|).
        error = np.abs(scaled - linear - scale * moved).max() / (scale * np.abs(moved).max())
        assert error < 0.1 * abs(scale - 1.0) + 0.005, (scale, error)
    with pytest.raises(ValueError, match="no charge migration"):
        base.with_linear_detector().with_migration_scale(2.0)


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1.0, 1.6])
def test_fixed_point_fit_leaves_pure_noise_with_the_network(setting, scale):
    """Data made by the base model's own detector (``scale`` 1), or by one whose charge
    migration is 1.6 times the network's: the fit measures the migration's amplitude
    (``calibrate_migration``), keeps the network as it is in the first case and rescales
    it in the second, and leaves noise."""
    base, instrument, setup = setting
    rng = np.random.default_rng(3)
    truth = {"sci": (0.031, -0.018), "cal": (-0.024, 0.012)}
    inputs, exposures, log_fluxes = {}, [], {}
    made_by = base if scale == 1.0 else base.with_migration_scale(scale)
    for name, role, target in (("sci", "science", "STAR-A"), ("cal", "calibrator", "STAR-B")):
        slopes, _, log_fluxes[name] = _truth(made_by, instrument, setup, truth[name])
        inputs[name] = RampInput(_calslope(slopes, rng, name), GROUP_TIME_S)
        exposures.append(FitExposure(name, role, target, inputs[name].image(None)))
    config = FitConfig()
    grid = UVGrid(27, 0.5)
    detector = RampDetector(base, inputs)
    product = extract_filter(instrument, FILTER, exposures, config, grid=grid, detector=detector)
    assert product.detector is not None and product.detector.converged
    assert product.detector.mode == "full"
    assert product.result.converged
    for name in ("sci", "cal"):
        amplitude, error, applied = detector.migration_amplitudes[name]
        assert amplitude == pytest.approx(scale, abs=max(0.08, 4 * error))
        assert applied == (scale != 1.0)
    params = product.result.params
    positions = np.asarray(params.exposures.position_arcsec, float)
    for e, name in enumerate(("sci", "cal")):
        stats = product.stats[e]
        tolerance = 3 * np.sqrt(2 / stats.dof)
        assert abs(stats.chi2 / stats.dof - 1) < tolerance, stats
        # Absolute positions share the calibrator's wavefront tilt, which trades with the
        # calibrator's position (marginal errors 0.36 / 0.55 mas in x / y from the fit's
        # Fisher matrix, measured): within 3 of those.
        np.testing.assert_allclose(positions[e], truth[name], atol=1.6e-3)
        assert float(params.exposures.log_flux[e]) == pytest.approx(log_fluxes[name], abs=5e-3)
    # The offset between the two stars does not depend on the tilt (error ~0.1 mas;
    # measured -0.08 / -0.15 mas): within 0.3 mas.
    offset = np.subtract(truth["sci"], truth["cal"])
    np.testing.assert_allclose(positions[0] - positions[1], offset, atol=3e-4)
    # The test has teeth: the charge migration in these data is far above the noise.
    # Network on minus network off at the truth, whitened by the slopes' variances: a
    # linear detector would leave this in the residuals (unless other parameters
    # absorbed part of it), the full model must not.
    for e, name in enumerate(("sci", "cal")):
        with_network, _, _ = _truth(base, instrument, setup, truth[name])
        without, _, _ = _truth(base.with_linear_detector(), instrument, setup, truth[name])
        variance = np.einsum("iiyx->iyx", inputs[name].product.slope_cov_dn2)
        mask = exposures[e].image.mask
        signal = ((with_network - without) ** 2 / variance)[:, mask].sum()
        assert signal > 5 * 3 * np.sqrt(2 * product.stats[e].dof)  # 5x the band tested above
