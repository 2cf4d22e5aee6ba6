"""The 1/f stripe correction of ``amigo process`` (docs/process.md, "1/f noise").

Synthetic ramps (tests/ramp_sim.py: Poisson photons, Gaussian read noise) of a compact
bright source with extended faint wings, plus known column stripes: one offset per
integration, group and column, as SUB80's column-by-column read-out makes 1/f noise.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from amigo import niriss
from amigo.cli import main
from amigo.io.calslope import read_calslope
from amigo.processing.ramps import (
    ArraySource,
    ProcessSettings,
    SlopeProduct,
    fit_stripe_model,
    process_ramps,
    stripe_offsets,
    usable_groups,
)
from ramp_sim import simulate, write_uncal

NINTS, NGROUPS, READ_DN, STRIPE_DN = 30, 6, 9.0, 3.0


def scene() -> np.ndarray:
    """(80, 80) DN per group: a 3000 DN/group core, wings of 30 exp(-r / 12) DN/group
    (5.7 at 20 pixels, 2.5 at 30: a column median of the faint pixels is not zero), a
    2 DN/group background and dark reference rows."""
    y, x = np.indices((80, 80))
    r = np.hypot(x - 45.3, y - 40.6)
    flux = 2.0 + 3000.0 * np.exp(-(r**2) / (2 * 2.0**2)) + 30.0 * np.exp(-r / 12.0)
    flux[: niriss.N_REFERENCE_ROWS] = 0.0
    return flux


@pytest.fixture(scope="module")
def data() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(21)
    flux = scene()
    clean = simulate(rng, NINTS, NGROUPS, flux, read_dn=READ_DN, adc=False).raw
    stripes = STRIPE_DN * rng.standard_normal((NINTS, NGROUPS, 80))  # (int, group, column)
    striped = np.rint(clean + stripes[:, :, None, :])
    return {"flux": flux, "clean": clean, "striped": striped, "stripes": stripes}


def process(raw: np.ndarray, method: str) -> SlopeProduct:
    return process_ramps(ArraySource(raw), ProcessSettings(adc_correction=False, one_over_f=method))


def z_scores(product: SlopeProduct, flux: np.ndarray) -> np.ndarray:
    sigma = np.sqrt(np.einsum("kkyx->kyx", product.slope_cov_dn2))
    return (product.slope_dn - flux) / sigma


def column_z(product: SlopeProduct, flux: np.ndarray) -> float:
    """Std over columns and slopes of sum(z) / sqrt(n) over a column's faint pixels: 1
    for independent errors, larger for errors shared along a column."""
    faint = ~product.badpix & (flux < 20.0)
    z = np.where(faint, z_scores(product, flux), 0.0)
    return float((z.sum(axis=1) / np.sqrt(faint.sum(axis=0))).std())


def test_stripe_offsets_recover_the_injected_stripes(data):
    ramps = data["striped"]
    usable = usable_groups(ramps)
    model = fit_stripe_model(ramps, usable)
    # The reference rows and the faint pixels, not the core (3000 DN/group) or inner wings.
    per_column = model.pixels_per_column
    assert per_column.min() >= 40 and per_column.max() <= 80
    assert model.weight[40, 45] == 0 and np.all(model.weight[:4] > 0)
    offsets, _ = stripe_offsets(
        np.diff(ramps, axis=1), usable[:, -1], model.weight, model.scale_dn, model.limit_dn
    )
    true = np.diff(data["stripes"], axis=1)
    true -= true.mean(axis=1, keepdims=True)  # measurable: the mean-free part
    error = offsets - true
    noise = np.sqrt(np.median(model.noise_dn2))  # expected error of one estimate
    assert 0.8 * noise < error.std() < 1.2 * noise
    assert error.std() < 0.4 * true.std()  # 1.5 DN (the noise of ~70 pixels) vs 4.2
    assert abs(error.mean()) < 0.05  # no leak of the wings' signal
    # The stripes' variance is measured (sample of 30 integrations x 80 columns).
    assert model.variance_dn2 == pytest.approx(true.var(), rel=0.1)
    assert 0.8 < np.median(model.gain) < 0.95


def test_stripes_are_removed_from_the_slopes_and_the_source_stays_unbiased(data):
    flux = data["flux"]
    plain = process(data["striped"], "none")
    fixed = process(data["striped"], "stripes")
    reference = process(data["clean"], "none")
    assert fixed.stripes is not None and plain.stripes is None

    # The stripes in the mean slopes (mean-free part, which the method measures) and
    # what was removed: one offset per column and slope, the column median of the change.
    injected = np.diff(data["stripes"], axis=1).mean(axis=0)
    injected -= injected.mean(axis=0)
    good = ~plain.badpix & ~fixed.badpix
    removed = np.nanmedian(np.where(good, plain.slope_dn - fixed.slope_dn, np.nan), axis=1)
    floor = np.sqrt(np.median(fixed.stripes.noise_dn2) / NINTS)  # noise of the estimate
    left = injected - removed
    assert injected.std() > 2.5 * floor
    assert left.std() < 1.3 * floor
    assert abs(left.mean()) < 0.3 * floor

    # Errors along a column: shared with the stripes in, not once they are removed (the
    # correction also removes the mean-free part of the faint pixels' own column mean:
    # below 1). Independent errors (no stripes) give ~1. Measured: 2.75, 0.85, 1.10.
    assert column_z(plain, flux) > 2.0
    assert column_z(fixed, flux) < 1.1
    assert 0.85 < column_z(reference, flux) < 1.2  # 1.10: z std is ~1.05 at 30 x 6

    # The source: slopes of the core agree with the truth within their errors, as well
    # as without stripes.
    core = ~fixed.badpix & (flux > 500.0)
    assert core.sum() > 30
    for product in (fixed, reference):
        z = z_scores(product, flux)[:, core]
        assert abs(z.mean()) < 0.15
        assert 0.85 < z.std() < 1.15
    bias = (fixed.slope_dn - flux)[:, core].mean()
    sigma = np.sqrt(np.einsum("kkyx->kyx", fixed.slope_cov_dn2)[:, core].mean() / core.sum())
    assert abs(bias) < 3 * sigma
    # The per-pixel errors stay honest everywhere.
    use = ~fixed.badpix
    assert 0.93 < z_scores(fixed, flux)[:, use].std() < 1.07


def test_no_harm_without_stripes(data):
    flux = data["flux"]
    plain = process(data["clean"], "none")
    fixed = process(data["clean"], "stripes")
    # Nothing to find: the gain is small, the scatter grows by < 1 %, columns stay fine.
    assert fixed.stripes.variance_dn2 < 0.1 * np.median(fixed.stripes.noise_dn2)
    assert np.median(fixed.stripes.gain) < 0.1
    use = ~plain.badpix & ~fixed.badpix
    ratio = z_scores(fixed, flux)[:, use].std() / z_scores(plain, flux)[:, use].std()
    assert ratio < 1.01
    change = np.abs(fixed.slope_dn - plain.slope_dn)[:, use]
    assert np.median(change) < 0.05 * np.median(
        np.sqrt(np.einsum("kkyx->kyx", plain.slope_cov_dn2))[:, use]
    )
    assert column_z(fixed, flux) < column_z(plain, flux) + 0.05


def test_a_column_without_stripe_pixels_takes_the_common_mode():
    rng = np.random.default_rng(3)
    common = rng.normal(0.0, 5.0, (4, 3))  # (integration, difference), same in all columns
    slopes = rng.normal(0.0, 1.0, (4, 3, 20, 6)) + common[:, :, None, None]
    weight = np.ones((20, 6))
    weight[:, 2] = 0.0  # no stripe pixel in column 2
    scale = np.full((20, 6), 1.2)
    limit = np.full((20, 6), 50.0)  # allows for the stripes
    offsets, keep = stripe_offsets(slopes, np.ones((4, 20, 6), bool), weight, scale, limit)
    assert not keep[:, :, 2].any()
    others = offsets[:, :, [0, 1, 3, 4, 5]]
    np.testing.assert_allclose(offsets[:, :, 2], others.mean(axis=2))
    np.testing.assert_allclose(offsets.sum(axis=1), 0.0, atol=1e-12)  # mean-free
    expected = common - common.mean(axis=1, keepdims=True)
    assert np.abs(others - expected[:, :, None]).max() < 1.0  # 20 pixels of unit noise
    with pytest.raises(ValueError, match="one_over_f"):
        ProcessSettings(one_over_f="rows")


def test_too_few_groups_or_integrations_change_nothing(data):
    raw = data["striped"]
    for subset in (raw[:, :2], raw[:1]):
        usable = usable_groups(subset)
        model = fit_stripe_model(subset, usable)
        assert not model.active
    product = process(raw[:, :2], "stripes")
    np.testing.assert_array_equal(product.slope_dn, process(raw[:, :2], "none").slope_dn)


def run(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    return int(exit_info.value.code or 0)


def test_cli_option_and_header_keyword(tmp_path, data):
    raw = data["striped"][:10, :4] + 10000.0  # a bias, as in real files
    uncal = write_uncal(tmp_path / "jw01093012001_03102_00001_nis_uncal.fits", raw)
    name = "jw01093012001_03102_00001_nis_calslope.fits"
    assert run("process", str(uncal), "--out", str(tmp_path / "default")) == 0
    assert run("process", str(uncal), "--out", str(tmp_path / "none"), "--one-over-f", "none") == 0
    default = read_calslope(tmp_path / "default" / name)
    plain = read_calslope(tmp_path / "none" / name)
    assert default.primary_header["ONEOVERF"] == "stripes"
    assert plain.primary_header["ONEOVERF"] == "none"
    assert not np.allclose(default.slope_dn, plain.slope_dn, equal_nan=True)
    # Files written before the keyword existed still load.
    old = tmp_path / "old_calslope.fits"
    with fits.open(tmp_path / "none" / name) as hdul:
        del hdul[0].header["ONEOVERF"]
        hdul.writeto(old)
    assert "ONEOVERF" not in read_calslope(old).primary_header
    assert run("process", str(uncal), "--out", str(tmp_path), "--one-over-f", "rows") == 2
