"""1/f stripes in the level-2 training loss (issue 22): the loss ``amigo train``
minimises is the stripes' marginal likelihood, and the trainer measures them.

The reference is the dense covariance of each column, ``C = diag(err^2) + tau^2 K``,
solved directly; the stripes are drawn from that Gaussian process into an image of the
model's own point source, so the residual under the true source is noise and stripes.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.likelihood.slopes import (
    PointSourceParams,
    SlopeData,
    fit_statistics,
    point_source_slopes,
    whitened_residuals,
)
from amigo.likelihood.stripes import column_whiteners, stripe_kernel
from amigo.model.base import BaseModel, BaseModelConfig
from amigo.training.data import TrainingData, TrainSettings
from amigo.training.fisher import loss_and_grad
from amigo.training.trainer import Trainer

TGROUP = 0.07544
NGROUPS = 6
TAU_DN_S = 2.0
LENGTH_ROWS = 10.0


def _column_draws(rng, tau, length, shape):
    factor = np.linalg.cholesky(tau**2 * stripe_kernel(shape[0], length) + 1e-9 * np.eye(shape[0]))
    return factor @ rng.standard_normal(shape)


@pytest.fixture(scope="module")
def striped():
    """A small model behind the pipeline, its point source, and a level-2 image of it
    with white noise and stripes (tau 2 DN/s over 10 rows; the halo's noise ~1.4 DN/s)."""
    config = BaseModelConfig(filters=("F480M",), shape=(80, 80), n_wavelengths=3, pupil_npix=32)
    base = BaseModel.create(config, linear=True).for_level2()
    cache = base.pupil_cache()
    truth = PointSourceParams(jnp.array([0.01, -0.02]), jnp.asarray(4e5))
    used = np.ones((80, 80), bool)
    used[:4] = False  # reference rows
    template = SlopeData.from_rate_image(
        np.zeros((80, 80)), np.ones((80, 80)), used, ngroups=NGROUPS, group_time_s=TGROUP
    )
    rate = np.asarray(point_source_slopes(base, cache, truth, template)[0], np.float64) / TGROUP
    rng = np.random.default_rng(3)
    error = np.sqrt(np.abs(rate) / 20.0 + 2.0)
    noisy = rate + error * rng.standard_normal(rate.shape)
    noisy += _column_draws(rng, TAU_DN_S, LENGTH_ROWS, rate.shape)
    data = SlopeData.from_rate_image(noisy, error, used, ngroups=NGROUPS, group_time_s=TGROUP)
    return config, base, cache, truth, data, rate, error, used


def test_the_whitened_loss_is_the_columns_dense_likelihood(striped):
    _, base, cache, truth, data, rate, error, used = striped
    inverse_sigma = np.where(used, 1.0 / error, 0.0)
    whitener = column_whiteners(inverse_sigma[None], TAU_DN_S, LENGTH_ROWS)[0]
    with_stripes = data.with_stripes(whitener)
    residual = (np.asarray(data.slopes_dn[0], np.float64) / TGROUP - rate) * used  # DN/s
    model = jnp.asarray(rate * TGROUP, data.slopes_dn.dtype)[None]
    z = np.asarray(whitened_residuals(model, with_stripes), np.float64).ravel()
    kernel = stripe_kernel(80, LENGTH_ROWS)
    dense = 0.0
    for c in range(80):
        rows = used[:, c]
        cov = np.diag(error[rows, c] ** 2) + TAU_DN_S**2 * kernel[np.ix_(rows, rows)]
        dense += residual[rows, c] @ np.linalg.solve(cov, residual[rows, c])
    assert np.sum(z**2) == pytest.approx(dense, rel=2e-5)  # float32 data
    assert not z.reshape(80, 80)[~used].any()  # unused pixels stay out
    # The training loss is half of it at the data's own model.
    value, _ = loss_and_grad(base, truth, with_stripes, cache)
    model_chi2 = np.sum(
        np.asarray(
            whitened_residuals(
                jnp.asarray(point_source_slopes(base, cache, truth, data)), with_stripes
            )
        )
        ** 2
    )
    assert float(value) == pytest.approx(0.5 * model_chi2, rel=1e-5)
    # The statistics: the plain z-scores as amigo fit reports them, and the whitened.
    stats = fit_statistics(model, with_stripes)
    plain = residual[used] / error[used]
    assert stats.zscore_std == pytest.approx(np.std(plain), rel=1e-4)
    assert stats.zscore_std_whitened == pytest.approx(np.std(z.reshape(80, 80)[used]), rel=1e-4)
    assert stats.zscore_std > 1.3 > 1.15 > stats.zscore_std_whitened > 0.85
    assert "zscore_std_whitened" not in fit_statistics(model, data).to_json()
    with pytest.raises(ValueError, match="shape"):
        data.with_stripes(whitener[:, :10])


def test_the_trainer_measures_and_whitens_the_stripes(striped, tmp_path):
    config, _, cache, _, data, _, _, _ = striped
    training = TrainingData(cal=[data], flats=[], val=[data])
    trainer = Trainer(training, TrainSettings(steps=1, n_batches=1), config, cache)
    trainer.warm_up(iterations=6)
    trainer.measure_stripes()
    (tau, length), (tau_val, _) = trainer.stripes["cal"][0], trainer.stripes["val"][0]
    assert tau == pytest.approx(TAU_DN_S, rel=0.2) and tau_val == tau
    # One image's length is loose (tests/test_stripes.py: a factor 1.5 over 20 images).
    assert LENGTH_ROWS / 2.5 < length < 2.5 * LENGTH_ROWS
    assert trainer.data.cal[0].stripes is not None and trainer.data.val[0].stripes is not None
    assert training.cal[0].stripes is None  # the caller's data are not modified
    stats = trainer.statistics(trainer.state.base)
    assert stats[0].zscore_std > 1.3 and 0.85 < stats[0].zscore_std_whitened < 1.15
    assert trainer.history.stripes_step == [0]
    # From scratch: measured again where the network comes on after the network-off
    # stage (the optics then fit), once.
    settings = TrainSettings(steps=3, n_batches=1, stage_steps=(1, 2))
    staged = Trainer(training, settings, config, cache)
    checkpoint = tmp_path / "ckpt.npz"
    staged.run(checkpoint, progress=False)
    assert staged.history.stripes_step == [0, 1]
    assert staged.stripes["cal"][0][0] == pytest.approx(TAU_DN_S, rel=0.2)
    # The checkpoint keeps them: a resumed training whitens as the one it continues.
    resumed = Trainer(training, settings, config, cache)
    resumed.load_checkpoint(checkpoint)
    assert resumed.stripes == staged.stripes
    np.testing.assert_array_equal(resumed.data.cal[0].stripes, staged.data.cal[0].stripes)
    # Off: nothing measured, nothing whitened.
    off = Trainer(training, TrainSettings(steps=1, n_batches=1, stripes=False), config, cache)
    off.measure_stripes()
    assert off.stripes == {} and off.data.cal[0].stripes is None


def test_progress_line_leaves_out_losses_without_data(capsys):
    """A training without flat-field files has no flat loss (NaN): the progress line
    says nothing of it rather than 'flat nan'; a validation loss is shown when there is one."""
    from amigo.training.trainer import _Reporter

    reporter = _Reporter(total=8, done=0, enabled=True)
    reporter.update(4, 1, {"cal": 0.667, "flat": float("nan"), "val": 1.399})
    reporter.update(8, 1, {"cal": 0.5, "flat": 0.25, "val": float("nan")})
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        "train: step 4: stage 1 loss 0.667 val 1.399 (chi2/2 per value)",
        "train: step 8: stage 1 loss 0.5 flat 0.25 (chi2/2 per value)",
    ]
