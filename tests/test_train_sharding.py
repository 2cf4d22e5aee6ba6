"""Data-parallel training (``jax.sharding``, issue 25): on two devices (CPU devices made by
``XLA_FLAGS=--xla_force_host_platform_device_count=2``, in a child process, since JAX reads
the flag when it starts) a training step lays the batch's exposures across both and takes
the same step as on one device."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from conftest import two_device_env

CHILD = textwrap.dedent(
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.flatten_util import ravel_pytree

    import test_calibration as tc
    from amigo.likelihood.slopes import PointSourceParams
    from amigo.model.base import BaseModel
    from amigo.training import parallel
    from amigo.training.data import TrainingData, TrainSettings
    from amigo.training.groups import physical_mask, split
    from amigo.training.trainer import Trainer

    assert len(jax.devices()) == 2, jax.devices()
    cache = BaseModel.create(tc.SMALL, linear=True).pupil_cache()
    truth = BaseModel.create(tc.SMALL, linear=True)
    positions = [[0.02, 0.0], [-0.01, 0.02], [0.0, -0.015]]  # 3 exposures: one is padding
    cal = [
        tc._synthetic(truth, PointSourceParams(jnp.array(p), jnp.asarray(4e5)), 4, 4.0, i, cache)
        for i, p in enumerate(positions)
    ]
    data = TrainingData(cal, [], [])
    settings = TrainSettings(steps=2, n_batches=1, stage_steps=(2,))

    # The sharded program's inputs span both devices, and it sums across them.
    seen = []
    sharded = parallel._sharded_loss_and_grads

    def spy(base, params, data, cache, weights):
        seen.append(len(weights.sharding.device_set))
        return sharded(base, params, data, cache, weights)

    parallel._sharded_loss_and_grads = spy
    runs = {}
    for label, devices in (("one", jax.devices()[:1]), ("two", jax.devices())):
        trainer = Trainer(data, settings, tc.SMALL, cache, devices=devices)
        trainer.compute_fisher()

        def physical(base):
            return np.asarray(ravel_pytree(split(base, physical_mask(base)))[0], np.float64)

        start = physical(trainer.state.base)
        loss = trainer.train_step([0, 1, 2], use_network=False)
        runs[label] = (loss, physical(trainer.state.base) - start)
    assert seen == [2], seen
    (loss1, step1), (loss2, step2) = runs["one"], runs["two"]
    assert np.isclose(loss1, loss2, rtol=1e-5), (loss1, loss2)
    # The same step, to the rounding of float32 sums taken in another order.
    diff = float(np.abs(step1 - step2).max() / np.abs(step1).max())
    assert diff < 1e-3, diff
    print("sharded step equals the sequential one:", diff, float(loss1))
    """
)


def test_a_training_step_on_two_devices_equals_one_on_one():
    env = two_device_env()
    done = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "sharded step equals the sequential one" in done.stdout
