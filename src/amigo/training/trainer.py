"""Base-model training: the whole instrument model, calibrated on calibration exposures.

The paper's "Base Model Training and Calibration", as code:

* **Joint fit.** Every parameter of :class:`~amigo.model.base.BaseModel` is trained
  together with the per-exposure source parameters (position, flux) of the calibration
  exposures, on the slope likelihood (:mod:`amigo.likelihood.slopes`).
* **Four groups of parameters, three data sets.** *Physical* parameters (aberrations,
  defocus, hole positions and sizes, jitter, rotation, anisotropy, intra-pixel response), the
  per-pixel *dark* current and the *network* learn from the calibration exposures; the
  *pixel* parameters (flat field and per-pixel non-linearity) learn only from the
  flat-field exposures (whose uniform light cannot tell a pixel's dark current from its
  sensitivity; the calibrators' background pixels can); *validation*
  exposures get their own positions and fluxes fitted every epoch but never touch the
  instrument (their loss is only reported, and selects the best network).
* **Optimisers.** Physical and per-exposure parameters take Fisher-preconditioned
  Nesterov momentum steps: the gradient of each parameter is divided by its Fisher
  diagonal ``F_ii = sum (dz/dtheta_i)^2`` (z: whitened residuals), computed from the
  Jacobian of the linear-detector model by forward-mode autodiff, so that a learning
  rate of order one is a Newton step per parameter whatever the data's signal level
  (a diagonal natural gradient). The pixel and dark parameters do the same with a
  per-pixel Fisher diagonal. The network uses Adam.
* **Batches and stages.** Calibration exposures are split into batches visited in a
  random order every epoch. Stage 0 trains the physical parameters with the network
  off (linear charge accumulation); every later stage restarts the network from new
  random weights and trains it jointly with the physical parameters, starting from the
  best physical state found so far (the paper's staged optimisation).
* **Checkpoints.** The full training state is written after every epoch (atomically);
  :func:`train` with ``resume=True`` continues from it.
* **Level-2 calibrators.** Trained on the STScI pipeline's level-2 images
  (``_cal``/``_calints``/``_rateints``) instead of calslope files, the model is the one
  behind the pipeline (:meth:`~amigo.model.base.BaseModel.for_level2`: no dark, no
  non-linearity), each image is compared with the pipeline's slope estimator applied to
  the model's ramp (:mod:`amigo.likelihood.slopes`), so the network still learns the
  brighter-fatter bending, and the per-pixel group learnt from the calibrators is the
  *residual sensitivity* the pipeline's flat leaves (in place of the dark current), with
  a Gaussian prior of width :attr:`~amigo.training.data.TrainSettings.sensitivity_prior` around one: dithers
  move the PSF over the pixels and so tell a pixel's response from the PSF's shape.
* **Dark residual (level 2).** After the steps, the per-pixel offsets of each group read
  that the pipeline's dark subtraction left (:mod:`amigo.model.detector.dark_residual`) are
  solved in closed form from the calibrators' residuals at their fitted states, under a
  Gaussian prior of :attr:`~amigo.training.data.TrainSettings.dark_prior_dn` per read, and stored in the model
  with the dark reference file they belong to (:func:`~amigo.training.exposure.solve_dark_residual`).
* **1/f stripes (level 2).** A level-2 image keeps the read-out's 1/f noise as stripes
  along its columns, correlated over tens of rows (:mod:`amigo.likelihood.stripes`). As
  in ``amigo fit``, they are marginalised: after the warm-up, each calibration and
  validation image's stripes (``tau``, ``ell``) are measured in the halo of its residual
  under the starting model, and its likelihood is whitened for them from then on
  (:meth:`Trainer.measure_stripes`); measured again when the network comes on after the
  network-off stage (a model far from the data has column-varying misfit that would be
  taken for stripes), and not after: the best network is chosen among states whose
  losses then compare.
  Without it the optics, the residual sensitivity and the network bend towards each
  image's stripes. :attr:`~amigo.training.data.TrainSettings.stripes` turns it off.
* **Loss curve.** ``amigo.train`` draws the calibration and validation losses against
  the step into ``MODEL_loss.png`` (:func:`loss_curve_path`).

The module holds the :class:`Trainer` and :func:`train`; the parameter groups are in
:mod:`~amigo.training.groups`, the Fisher information in :mod:`~amigo.training.fisher`
(the momentum optimiser in :mod:`amigo.solvers.natural_gradient`), the settings, data and
state in :mod:`~amigo.training.data`, and the per-exposure and closed-form pieces in
:mod:`~amigo.training.exposure`.

Everything is float32 unless the caller enables 64-bit JAX (the metadata records it).
"""

from __future__ import annotations

import functools
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from amigo._version import __version__, source_commit
from amigo.errors import InputError
from amigo.likelihood.slopes import (
    FitStatistics,
    FlatParams,
    PointSourceParams,
    SlopeData,
    fit_statistics,
    initial_flat,
    initial_point_source,
)
from amigo.likelihood.stripes import column_whiteners, stripes_around_peak
from amigo.model.base import (
    BaseModel,
    BaseModelConfig,
    PupilCache,
    fill_leaves,
    open_npz,
    read_record,
    save_base_model,
    write_leaves,
)
from amigo.model.detector.boundary import BoundaryShift
from amigo.model.detector.ramp import ChargeMigrationNetwork
from amigo.model.detector.reset import Superbias
from amigo.model.optics.model import strong_types
from amigo.progress import step as report_step
from amigo.solvers.natural_gradient import FisherMomentum
from amigo.training.data import (
    CHECKPOINT_FORMAT,
    History,
    TrainingData,
    TrainSettings,
    TrainState,
    same_data,
)
from amigo.training.exposure import FIT_ITERATIONS, solve_dark_residual
from amigo.training.fisher import (
    compiled_model,
    dark_fisher,
    exposure_fisher_block,
    fisher_diagonal,
    fisher_matrix,
    loss_and_grad,
    pixel_fisher,
    pixel_newton,
)
from amigo.training.groups import (
    dark_mask,
    false_like,
    less_common_mode,
    merge,
    physical_mask,
    physical_step_limits,
    pin_mask_centroid,
    pixel_mask,
    seen_by,
    split,
)
from amigo.training.parallel import batch_loss_and_grads, data_mesh

# ---------------------------------------------------------------------------- the trainer


class Trainer:
    """The staged optimisation of the module docstring, one epoch at a time.

    ``Trainer(data, settings)`` starts from an untrained model, or from ``initial``
    (fine-tuning, with ``settings.init`` naming it); :meth:`run` trains
    ``settings.steps`` steps (checkpointing after each epoch when given a path);
    :meth:`result` is the best model. :func:`train` wraps it for the CLI.
    """

    def __init__(
        self,
        data: TrainingData,
        settings: TrainSettings,
        config: BaseModelConfig | None = None,
        cache: PupilCache | None = None,
        initial: BaseModel | None = None,
        devices: Sequence[Any] | None = None,
    ) -> None:
        self.data = data
        self.settings = settings
        # The calibrators' pixels, where the dark current's prior takes its median (once).
        self._cal_pixels: np.ndarray | None = None
        # Batches are data-parallel over these (default: every device JAX sees).
        self.mesh = data_mesh(devices)
        if (initial is None) != (settings.init is None):
            raise ValueError("settings.init names the initial model: give both or neither")
        where = "--cal" if initial is None else settings.init
        if settings.detector not in ("full", "boundary"):
            raise InputError("--detector", f"must be full or boundary, not {settings.detector!r}")
        if settings.detector == "boundary" and data.level2:
            # As amigo fit: the account's strength is seen in the group differences.
            raise InputError(
                "--detector", "boundary needs calslope files (raw ramps), not level-2 images"
            )
        if initial is not None:
            config = initial.config
            holds = isinstance(initial.ramp.network, BoundaryShift)
            if holds and settings.detector != "boundary":
                raise InputError(
                    where,
                    "holds the physical charge-migration account: train it with --detector "
                    "boundary",
                )
            if settings.detector == "boundary" and not holds:
                # The maps are fine-tuned beside the account, from its starting strength.
                initial = initial.with_network(BoundaryShift.create())
            if initial.linear and settings.steps > 0:
                raise InputError(where, "has no network to fine-tune (a linear model)")
            if tuple(config.shape) != tuple(data.cal[0].shape):
                raise InputError(
                    where, f"models {config.shape} pixels, the data have {data.cal[0].shape}"
                )
        config = config or BaseModelConfig(filters=data.filters, shape=data.cal[0].shape)
        missing = [f for f in data.filters if f not in config.filters]
        if missing:
            raise InputError(where, f"the model configuration has no optics for {missing}")
        base = BaseModel.create(config, linear=True) if initial is None else initial
        if settings.drift_modes > base.config.n_zernike:
            raise InputError(
                "--drift-modes",
                f"{settings.drift_modes}: the model has {base.config.n_zernike} Zernikes per hole",
            )
        data.check()
        if data.level2:
            base = base.for_level2()  # the model behind the pipeline
        elif base.config.data_level == "level2":
            raise InputError(where, "was trained on level-2 images: raw ramps need a ramp model")
        base = strong_types(base)  # one compiled program per step function (see there)
        self.cache = base.pupil_cache() if cache is None else cache
        self.rng = np.random.default_rng(settings.seed)
        self.history = History()
        self.step = 0
        self.seconds = 0.0
        self.state = self._initial_state(base)
        self.fisher: dict[str, Any] | None = None
        self.stopped_early = False
        #: Each level-2 image's stripes, ``{"cal": [[tau_dn_s, ell_rows], ...], "val":
        #: [...]}`` in the data's order (:meth:`measure_stripes`); empty: none measured.
        self.stripes: dict[str, list[list[float]]] = {}

    # -------------------------------------------------------------- state
    def _precision(self) -> dict[str, Any]:
        """The Fisher information of :meth:`compute_fisher`, which comes before any step."""
        if self.fisher is None:
            raise RuntimeError("compute_fisher() comes before the first step")
        return self.fisher

    def _initial_state(self, base: BaseModel) -> TrainState:
        s = self.settings

        # Each exposure's position, flux and (drift_modes > 0) a small wavefront drift.
        def source(d: SlopeData) -> PointSourceParams:
            return initial_point_source(base, d).with_drift(s.drift_modes, s.drift_prior_nm)

        cal = tuple(source(d) for d in self.data.cal)
        flats = tuple(initial_flat(base, d) for d in self.data.flats)
        val = tuple(source(d) for d in self.data.val)
        network = self._fresh_network(base, 1) if base.linear else base.ramp.network
        return TrainState(
            base=base,
            cal_params=cal,
            flat_params=flats,
            val_params=val,
            physical_opt=FisherMomentum.init(
                ravel_pytree(split(base, physical_mask(base)))[0], s.physical_lr, s.momentum
            ),
            pixel_opt=FisherMomentum.init(split(base, pixel_mask(base)), s.pixel_lr, s.momentum),
            dark_opt=FisherMomentum.init(split(base, dark_mask(base)), s.dark_lr, s.momentum),
            cal_opt=FisherMomentum.init(cal, s.exposure_lr, s.momentum),
            flat_opt=FisherMomentum.init(flats, s.exposure_lr, s.momentum),
            val_opt=FisherMomentum.init(val, s.exposure_lr, s.momentum),
            adam_state=optax.adam(self._account_lr()).init(eqx.filter(network, eqx.is_array)),
            best_base=base.with_network(network),
            best_loss=jnp.asarray(np.inf),
        )

    def _fresh_network(self, base: BaseModel, stage: int) -> ChargeMigrationNetwork | BoundaryShift:
        """A new account of the charge migration: the network from the seed and
        ``stage``'s random weights, or the physical account at its starting strength."""
        if self.settings.detector == "boundary":
            return BoundaryShift.create()
        c = base.config
        key = jax.random.fold_in(jax.random.PRNGKey(self.settings.seed), stage)
        return ChargeMigrationNetwork(
            key,
            width=c.network_width,
            depth=c.network_depth,
            charge_scale_e=c.charge_scale_e,
            init_scale=self.settings.network_init_scale,
        )

    def _account_lr(self) -> float:
        """Adam's learning rate of the charge migration's account: the network's
        ``network_lr``, or :data:`BOUNDARY_LR` for the physical account."""
        return BOUNDARY_LR if self.settings.detector == "boundary" else self.settings.network_lr

    # -------------------------------------------------------------- warm-up
    def warm_up(self, iterations: int = 3) -> None:
        """Newton steps on every exposure's own parameters (position and flux, or a
        flat's level) with the instrument fixed: the centroid and total-flux starting
        values are too rough for the joint fit. Keeps each exposure's Fisher diagonal
        for :meth:`compute_fisher`."""
        state, base, cache = self.state, self.state.base, self.cache
        nothing = false_like(physical_mask(base))
        sets = {
            "cal_params": self.data.cal,
            "flat_params": self.data.flats,
            "val_params": self.data.val,
        }
        groups, self._exposure_fisher = [], {}
        for name, datasets in sets.items():
            params, fishers = list(getattr(state, name)), []
            for i, d in enumerate(datasets):
                p = params[i]
                fisher = fisher_diagonal(base, p, d, cache, nothing)[1]
                for _ in range(iterations):
                    _, (_, grad) = loss_and_grad(base, p, d, cache)
                    if _drifting(p):
                        # Position and flux only: a drift's diagonal Newton step ignores
                        # how each hole's tilt trades with the position.
                        grad = eqx.tree_at(lambda q: q.drift_nm, grad, 0 * grad.drift_nm)
                    p = jax.tree.map(lambda x, g, f: x - g / jnp.maximum(f, 1e-30), p, grad, fisher)
                params[i] = p
                fishers.append(fisher)
            groups.append(tuple(params))
            self._exposure_fisher[name] = fishers
        report_step("train: warm-up of positions and fluxes done")
        self.state = eqx.tree_at(
            lambda s: (s.cal_params, s.flat_params, s.val_params), state, tuple(groups)
        )

    # -------------------------------------------------------------- 1/f stripes
    def measure_stripes(self) -> None:
        """Measure each level-2 calibration and validation image's 1/f stripes in the
        halo of its residual at the current state (:func:`stripes_around_peak`, the star at
        the model's peak, as ``amigo fit`` does) and whiten its likelihood for them from
        here on (:meth:`SlopeData.with_stripes`). Does nothing for calslope data (``amigo
        process`` removes their stripes) or with ``settings.stripes`` off."""
        if not (self.settings.stripes and self.data.level2):
            return
        state, base, cache = self.state, self.state.base, self.cache
        measured: dict[str, list[list[float]]] = {}
        for key, params, datasets in (
            ("cal", state.cal_params, self.data.cal),
            ("val", state.val_params, self.data.val),
        ):
            measured[key] = []
            for p, d in zip(params, datasets, strict=True):
                plain = d.with_stripes(None)
                model = np.asarray(compiled_model(base, p, plain, cache)[0], np.float64)
                residual = (np.asarray(plain.slopes_dn[0], np.float64) - model) / d.group_time_s
                tau, length = stripes_around_peak(residual, _inverse_sigma_dn_s(plain), model)
                measured[key].append([tau, length])
        self.stripes = measured
        self.history.stripes_step.append(self.step)
        self._apply_stripes()
        kept = [tau for pairs in measured.values() for tau, _ in pairs if tau > 0]
        report_step(
            f"train: 1/f stripes in {len(kept)} of "
            f"{len(self.data.cal) + len(self.data.val)} images"
            + (f" ({min(kept):.2f}-{max(kept):.2f} DN/s)" if kept else "")
        )
        # The exposures' own Fisher diagonals of the warm-up were taken without them.
        self._exposure_fisher = {}

    def _apply_stripes(self) -> None:
        """Whiten the data for :attr:`stripes` (a checkpoint's, or just measured)."""

        def whitened(datasets: list[SlopeData], pairs: list[list[float]]) -> list[SlopeData]:
            out = []
            for d, (tau, length) in zip(datasets, pairs, strict=True):
                if tau <= 0:
                    out.append(d.with_stripes(None))
                    continue
                inverse_sigma = _inverse_sigma_dn_s(d)[None]
                out.append(d.with_stripes(column_whiteners(inverse_sigma, [tau], [length])[0]))
            return out

        if not self.stripes:
            return
        self.data = replace(
            self.data,
            cal=whitened(self.data.cal, self.stripes["cal"]),
            val=whitened(self.data.val, self.stripes["val"]),
        )

    # -------------------------------------------------------------- Fisher diagonals
    def compute_fisher(self) -> None:
        """Fisher matrices of every Fisher-preconditioned parameter at the current state.

        The shared physical parameters use the full Fisher matrix: for each filter, the
        Jacobian of its first calibration exposure times the number of its exposures (the
        dithers of one star differ only by sub-pixel offsets), summed over filters, then
        damped (``F + damping * diag F``) and inverted once. Every exposure gets the
        Fisher diagonal of its own position and flux; the pixel parameters sum the
        per-pixel Fisher diagonals of the flats.
        """
        state, base, cache = self.state, self.state.base, self.cache
        full = physical_mask(base)
        vector, unravel = ravel_pytree(split(base, full))
        index_tree = unravel(jnp.arange(vector.size, dtype=jnp.float32))
        total = np.zeros((vector.size, vector.size))
        by_filter: dict[str, list[int]] = {}
        for i, d in enumerate(self.data.cal):
            by_filter.setdefault(d.filter, []).append(i)
        for filt, indices in by_filter.items():
            report_step(f"train: Fisher matrix of the physical parameters, {filt}")
            i = indices[0]
            mask = physical_mask(base, filt)
            f_base, _ = fisher_matrix(base, state.cal_params[i], self.data.cal[i], cache, mask)
            columns = np.asarray(ravel_pytree(eqx.filter(index_tree, mask))[0]).astype(int)
            total[np.ix_(columns, columns)] += len(indices) * f_base
        diagonal = np.diagonal(total).copy()
        unseen = diagonal <= 0  # parameters the data do not see: never move them
        diagonal[unseen] = 1.0
        damped = total + self.settings.damping * np.diag(diagonal)
        damped[unseen, :] = 0.0
        damped[:, unseen] = 0.0
        damped[unseen, unseen] = np.inf
        inverse = np.linalg.pinv(np.where(np.isinf(damped), 0.0, damped), hermitian=True)
        inverse[unseen, :] = 0.0
        inverse[:, unseen] = 0.0
        nothing = false_like(full)
        stored = getattr(self, "_exposure_fisher", {})

        def exposure_fisher(name: str, params, datasets) -> list[Any]:
            if name in stored:
                return list(stored[name])
            return [
                fisher_diagonal(base, p, d, cache, nothing)[1]
                for p, d in zip(params, datasets, strict=True)
            ]

        # Each exposure's own parameters (the warm-up's Fisher when there was one).
        cal_fisher = exposure_fisher("cal_params", state.cal_params, self.data.cal)
        val_fisher = exposure_fisher("val_params", state.val_params, self.data.val)
        flat_fisher = exposure_fisher("flat_params", state.flat_params, self.data.flats)
        pixel = {
            "diag": jax.tree.map(jnp.zeros_like, split(base, pixel_mask(base))),
            "cross": jnp.zeros_like(base.ramp.flat),
        }
        for p, d in zip(state.flat_params, self.data.flats, strict=True):
            diagonal, cross = pixel_fisher(base, p, d)
            pixel = {
                "diag": jax.tree.map(jnp.add, pixel["diag"], diagonal),
                "cross": pixel["cross"] + cross,
            }
        # The dark current: every calibration exposure's pixels (the batch gradient is
        # scaled up to the whole set, so its Fisher is the whole set's too).
        dark = jax.tree.map(jnp.zeros_like, split(base, dark_mask(base)))
        for q, d in zip(state.cal_params, self.data.cal, strict=True):
            dark = jax.tree.map(jnp.add, dark, dark_fisher(base, q, d, cache))
        dark = jax.tree.map(lambda f: jnp.where(f > 0, f, jnp.inf), dark)
        self.fisher = {
            # Each drifting exposure's block (checkpointed: a resumed run steps the same).
            "drift_cal": self._block_inverses(state.cal_params, self.data.cal),
            "drift_val": self._block_inverses(state.val_params, self.data.val),
            "physical": jnp.asarray(inverse, vector.dtype),
            "pixel": pixel,
            "dark": dark,
            "cal": tuple(cal_fisher),
            "val": tuple(val_fisher),
            "flat": tuple(flat_fisher),
        }

    def _block_inverses(
        self, params: Sequence[Any], datasets: Sequence[SlopeData]
    ) -> tuple[jax.Array, ...]:
        """For each exposure with a wavefront drift, the inverse of its own parameters'
        damped Fisher block, as ``(n + 1, n)``: the inverse of its correlation form, then
        the scales ``sqrt(diag)`` (the inverse is ``C / outer(scale, scale)``; ``(1, 0)``
        for the others). Its drift trades with its position, which a diagonal step would
        ignore. The block's diagonal spans ~24 decades (position in arcsec, flux in
        electrons): a plain pseudo-inverse would drop the flux's direction as round-off,
        and the unit-free form keeps its precision in float32."""
        out: list[jax.Array] = []
        for p, d in zip(params, datasets, strict=True):
            if not _drifting(p):
                out.append(jnp.zeros((1, 0)))
                continue
            block = exposure_fisher_block(self.state.base, p, d, self.cache)
            damped = block + self.settings.damping * np.diag(np.diag(block))
            scale = np.sqrt(np.diag(damped))  # > 0: the drift's prior is in the block
            inverse = np.linalg.inv(damped / np.outer(scale, scale))
            out.append(jnp.asarray(np.vstack([inverse, scale]), p.flux_e.dtype))
        return tuple(out)

    def _drift_step(
        self,
        kind: str,
        params: tuple[Any, ...],
        moved: tuple[Any, ...],
        grads: Sequence[Any],
        which: Any,
    ) -> tuple[Any, ...]:
        """``moved`` (the diagonal steps from ``params``) with the exposures ``which``
        that have a drift stepped instead from ``params`` on their whole block
        (:meth:`_block_inverses`), within a trust region: 1 nm of drift, 2 mas of
        position, 2 % of flux per step."""
        inverses = self._precision()[f"drift_{kind}"]
        out = list(moved)
        for i in which:
            if inverses[i].shape[1] == 0:
                continue
            vector, unravel = ravel_pytree(params[i])
            stored = np.asarray(inverses[i], np.float64)
            inverse, scale = stored[:-1], stored[-1]
            gradient = np.asarray(ravel_pytree(grads[i])[0], np.float64)
            step = self.settings.exposure_lr * (inverse @ (gradient / scale)) / scale
            p = params[i]
            limit = ravel_pytree(
                PointSourceParams(
                    jnp.full_like(p.position_arcsec, 2e-3),
                    0.02 * jnp.abs(p.flux_e),
                    jnp.ones_like(p.drift_nm),
                    p.drift_prior_nm,
                )
            )[0]
            shrink = min(1.0, float(np.min(np.asarray(limit) / np.maximum(np.abs(step), 1e-30))))
            out[i] = unravel(vector - jnp.asarray(shrink * step, vector.dtype))
        return tuple(out)

    def _fisher_skeleton(self) -> dict[str, Any]:
        """Arrays shaped like :meth:`compute_fisher`'s (to read a checkpoint into)."""
        state = self.state
        n = ravel_pytree(split(state.base, physical_mask(state.base)))[0].size
        zeros = functools.partial(jax.tree.map, jnp.zeros_like)
        return {
            "physical": jnp.zeros((n, n), state.base.hole_centres_m.dtype),
            "pixel": {
                "diag": zeros(split(state.base, pixel_mask(state.base))),
                "cross": jnp.zeros_like(state.base.ramp.flat),
            },
            "dark": zeros(split(state.base, dark_mask(state.base))),
            "cal": zeros(state.cal_params),
            "val": zeros(state.val_params),
            "flat": zeros(state.flat_params),
            "drift_cal": _block_skeleton(state.cal_params),
            "drift_val": _block_skeleton(state.val_params),
        }

    # -------------------------------------------------------------- steps
    def _batches(self) -> list[list[int]]:
        order = self.rng.permutation(len(self.data.cal))
        n = max(1, min(self.settings.n_batches, len(order)))
        return [list(map(int, b)) for b in np.array_split(order, n)]

    def train_step(self, batch: list[int], use_network: bool) -> float:
        """Update the physical parameters, the network (if on) and the batch's source
        parameters from the calibration exposures in ``batch``; returns the batch's chi2/2
        per slope value before the step."""
        state, base = self.state, self.state.base
        n_cal = len(self.data.cal)
        loss, values = 0.0, 0
        grads = [jax.tree.map(jnp.zeros_like, p) for p in state.cal_params]
        # Every exposure's loss and gradients; on several devices, data-parallel.
        batch_values, grad_base, batch_grads = batch_loss_and_grads(
            base,
            [state.cal_params[i] for i in batch],
            [self.data.cal[i] for i in batch],
            self.cache,
            self.mesh,
        )
        for i, value, gp in zip(batch, batch_values, batch_grads, strict=True):
            if not np.isfinite(float(value)):
                # e.g. a detector geometry beyond the resampling's reach (NaN images)
                raise FloatingPointError(
                    f"training diverged at step {self.step + 1}: the loss of calibration "
                    f"exposure {i} is not finite"
                )
            loss, values = loss + float(value), values + self.data.cal[i].n_values
            grads[i] = gp
        assert grad_base is not None  # a batch is never empty
        # Source parameters of the exposures in the batch (the others keep their state).
        moved, moved_opt = state.cal_opt.update(
            state.cal_params, tuple(grads), self._precision()["cal"]
        )
        inside = set(batch)
        moved = self._drift_step("cal", state.cal_params, tuple(moved), grads, batch)
        cal_params = tuple(moved[i] if i in inside else state.cal_params[i] for i in range(n_cal))
        velocity = tuple(
            moved_opt.velocity[i] if i in inside else state.cal_opt.velocity[i]
            for i in range(n_cal)
        )
        cal_opt = eqx.tree_at(lambda o: o.velocity, moved_opt, velocity)
        # Physical parameters: the batch gradient stands for the whole set.
        mask = physical_mask(base)
        scale = n_cal / len(batch)
        g_phys = jax.tree.map(lambda g: g * scale, split(grad_base, mask))
        vector, unravel = ravel_pytree(split(base, mask))
        moved_vector, physical_opt = state.physical_opt.update_vector(
            vector,
            ravel_pytree(g_phys)[0],
            self._precision()["physical"],
            ravel_pytree(physical_step_limits(base))[0],
        )
        base = merge(base, unravel(moved_vector), mask)
        base = pin_mask_centroid(base)
        # The dark current of every pixel, from the same batch gradient, once the optics
        # have settled (network-on stages): a per-pixel offset would otherwise soak up
        # the residuals of a still-wrong PSF.
        dark_opt = state.dark_opt
        if use_network:
            mask = dark_mask(base)
            g_dark = jax.tree.map(lambda g: g * scale, split(grad_base, mask))
            fisher = self._precision()["dark"]
            if self.data.level2:
                g_dark, fisher = self._sensitivity_prior(base, g_dark, fisher)
            elif self.settings.dark_current_prior > 0:
                g_dark, fisher = self._dark_current_prior(base, g_dark, fisher)
            dark, dark_opt = dark_opt.update(split(base, mask), g_dark, fisher)
            if self.data.level2:
                dark = self._without_common_mode(split(base, mask), dark)
            base = merge(base, dark, mask)
        adam_state = state.adam_state
        if use_network and base.ramp.network is not None:
            weights = eqx.filter(base.ramp.network, eqx.is_array)
            g_net = eqx.filter(grad_base.ramp.network, eqx.is_array)
            updates, adam_state = optax.adam(self._account_lr()).update(g_net, adam_state, weights)
            base = base.with_network(eqx.apply_updates(base.ramp.network, updates))
        base = eqx.tree_at(
            lambda m: m.detector.jitter_arcsec, base, jnp.abs(base.detector.jitter_arcsec)
        )
        base, cal_params = self._drifts_to_static(base, cal_params)
        self.state = eqx.tree_at(
            lambda s: (s.base, s.cal_params, s.cal_opt, s.physical_opt, s.dark_opt, s.adam_state),
            state,
            (base, cal_params, cal_opt, physical_opt, dark_opt, adam_state),
        )
        return loss / max(values, 1)

    def _drifts_to_static(
        self, base: BaseModel, cal_params: tuple[Any, ...]
    ) -> tuple[BaseModel, tuple[Any, ...]]:
        """Move the calibrators' mean wavefront drift of each filter into its static
        Zernikes. Every calibration image stays the same (static + drift is unchanged for
        each of them; a validation exposure's drift is its own and stays), and what the
        exposures share becomes the optics: an exposure's own drift, with its fast
        per-exposure steps, would otherwise keep the static error that the static
        optics' slower, trust-region-limited steps should learn."""
        filters: dict[str, list[int]] = {}
        for i, (p, d) in enumerate(zip(cal_params, self.data.cal, strict=True)):
            if _drifting(p):
                filters.setdefault(d.filter, []).append(i)
        params = list(cal_params)
        static = dict(base.zernikes_nm)
        for filter_name, members in filters.items():
            mean = jnp.mean(jnp.stack([params[i].drift_nm for i in members]), axis=0)
            modes = mean.shape[1]
            static[filter_name] = static[filter_name].at[:, :modes].add(mean)
            for i in members:
                params[i] = eqx.tree_at(lambda q: q.drift_nm, params[i], params[i].drift_nm - mean)
        if filters:
            base = eqx.tree_at(lambda m: m.zernikes_nm, base, static)
        return base, tuple(params)

    def _sensitivity_prior(self, base: BaseModel, grad: BaseModel, fisher: BaseModel):
        """Add the Gaussian prior ``(s - 1)^2 / (2 sigma^2)`` on each pixel's residual
        sensitivity ``s`` to its gradient and Fisher diagonal (level-2 training)."""
        precision = 1.0 / self.settings.sensitivity_prior**2
        return _with_map_prior(lambda m: m.ramp.flat, base, grad, fisher, 1.0, precision)

    def _dark_current_prior(self, base: BaseModel, grad: BaseModel, fisher: BaseModel):
        """Add the population prior ``(d - m)^2 / (2 sigma^2)`` on each pixel's dark
        current ``d`` (electrons per group) to its gradient and Fisher diagonal; ``m`` is
        the median dark over the calibrators' pixels now (robust to the pixels the prior
        is there for), held fixed within the step."""
        precision = 1.0 / self.settings.dark_current_prior**2
        centre = jnp.median(base.read.dark_e_per_group[self._calibrator_pixels()])
        return _with_map_prior(
            lambda m: m.read.dark_e_per_group, base, grad, fisher, centre, precision
        )

    def _calibrator_pixels(self) -> np.ndarray:
        """The pixels the calibrators see (:func:`seen_by`), taken once: the data do not
        change during training."""
        if self._cal_pixels is None:
            self._cal_pixels = seen_by(self.data.cal)
        return self._cal_pixels

    def _without_common_mode(self, before: BaseModel, after: BaseModel) -> BaseModel:
        """The sensitivity step less its mean over the calibrators' pixels: the mean
        sensitivity is degenerate with every exposure's flux, which carries it (pixels no
        calibrator sees have an infinite Fisher diagonal: their step is zero)."""
        step = less_common_mode(after.ramp.flat - before.ramp.flat, self._calibrator_pixels())
        return eqx.tree_at(lambda m: m.ramp.flat, after, before.ramp.flat + step)

    def flat_step(self) -> float:
        """Update the flat field, the non-linearity and the flats' levels from the
        flat-field exposures; returns their chi2/2 per value before the step."""
        state, base = self.state, self.state.base
        if not self.data.flats:
            return float("nan")
        grad_base, grads, loss, values = None, [], 0.0, 0
        for p, d in zip(state.flat_params, self.data.flats, strict=True):
            value, (gb, gp) = loss_and_grad(base, p, d, self.cache)
            loss, values = loss + float(value), values + d.n_values
            grad_base = gb if grad_base is None else jax.tree.map(jnp.add, grad_base, gb)
            grads.append(gp)
        assert grad_base is not None  # there are flats (checked above)
        flat_params, flat_opt = state.flat_opt.update(
            state.flat_params, tuple(grads), self._precision()["flat"]
        )
        mask = pixel_mask(base)
        # A joint Newton step of each pixel's (flat, non-linearity) pair (zero where no
        # flat constrains it), then momentum on it (unit "Fisher": already preconditioned).
        direction = pixel_newton(
            split(grad_base, mask), self._precision()["pixel"], self.settings.damping
        )
        # The flat's mean is degenerate with every flux: the flats' levels carry it, the
        # flat's step has none (a common-mode step would jolt every calibrator's flux).
        used = seen_by(self.data.flats)
        step = less_common_mode(direction.ramp.flat, used)
        direction = eqx.tree_at(lambda m: m.ramp.flat, direction, step)
        ones = jax.tree.map(jnp.ones_like, direction)
        pixel, pixel_opt = state.pixel_opt.update(split(base, mask), direction, ones)
        base = merge(base, pixel, mask)
        # Pinned to one against rounding drift.
        base = eqx.tree_at(
            lambda m: m.ramp.flat, base, base.ramp.flat / jnp.mean(base.ramp.flat[used])
        )
        self.state = eqx.tree_at(
            lambda s: (s.base, s.flat_params, s.flat_opt, s.pixel_opt),
            state,
            (base, flat_params, flat_opt, pixel_opt),
        )
        return loss / max(values, 1)

    def validation_step(self) -> float:
        """Fit the validation exposures' own positions and fluxes one step (the
        instrument is untouched); returns their chi2/2 per value before the step."""
        state = self.state
        if not self.data.val:
            return float("nan")
        grads, loss, values = [], 0.0, 0
        for p, d in zip(state.val_params, self.data.val, strict=True):
            value, (_, gp) = loss_and_grad(state.base, p, d, self.cache)
            loss, values = loss + float(value), values + d.n_values
            grads.append(gp)
        val_params, val_opt = state.val_opt.update(
            state.val_params, tuple(grads), self._precision()["val"]
        )
        val_params = self._drift_step(
            "val", state.val_params, tuple(val_params), grads, range(len(grads))
        )
        self.state = eqx.tree_at(lambda s: (s.val_params, s.val_opt), state, (val_params, val_opt))
        return loss / max(values, 1)

    # -------------------------------------------------------------- stages, epochs
    def start_stage(self, stage: int) -> None:
        """Stage >= 1: a new network from new random weights (and a fresh Adam state) on
        the best physical state so far (stage 1: the end of the network-off stage). When
        fine-tuning, stage 1 keeps the initial model's network (fresh Adam state)."""
        if stage == 0:
            return
        state = self.state
        source = (
            state.best_base if stage > 1 and bool(jnp.isfinite(state.best_loss)) else state.base
        )
        mask = physical_mask(source)
        base = merge(state.base, split(source, mask), mask)
        keep = stage == 1 and self.settings.init is not None
        # The physical account is not restarted: a restart would only forget its strength.
        keep = keep or (
            self.settings.detector == "boundary" and state.base.ramp.network is not None
        )
        network = state.base.ramp.network if keep else self._fresh_network(base, stage)
        s = self.settings
        self.state = eqx.tree_at(
            lambda st: (st.base, st.adam_state, st.physical_opt),
            state,
            (
                base.with_network(network),
                optax.adam(self._account_lr()).init(eqx.filter(network, eqx.is_array)),
                FisherMomentum.init(ravel_pytree(split(base, mask))[0], s.physical_lr, s.momentum),
            ),
        )
        if keep and self.settings.detector == "boundary":
            report_step(f"train: stage {stage}: the physical charge-migration account continues")
        elif keep:
            report_step(f"train: stage 1: fine-tuning the network of {self.settings.init}")
        elif self.settings.detector == "boundary":
            report_step(f"train: stage {stage}: the physical charge-migration account on")
        else:
            report_step(f"train: stage {stage}: network restarted from new weights (seed {stage})")

    def epoch(self) -> dict[str, float]:
        """One pass over the calibration batches (stopping at ``settings.steps``), then
        one flat-field step and one validation step; returns the epoch's losses."""
        if self.fisher is None:
            self.warm_up()
            self.measure_stripes()
            self.compute_fisher()
        losses = []
        for batch in self._batches():
            if self.step >= self.settings.steps:
                break
            stage = self.settings.stage_of(self.step)
            if self.step == 0 or stage != self.settings.stage_of(self.step - 1):
                self.start_stage(stage)
                if stage == 1 and self.step > 0:
                    # After the network-off stage the optics fit: measured again there,
                    # the stripes no longer hold the starting model's misfit. Every
                    # network-on state (the best is chosen among them) has these.
                    self.measure_stripes()
                    self.compute_fisher()
            losses.append(self.train_step(batch, use_network=stage > 0))
            self.history.step.append(self.step)
            self.history.stage.append(stage)
            self.history.loss.append(losses[-1])
            self.step += 1
        flat = self.flat_step()
        val = self.validation_step()
        cal = float(np.mean(losses)) if losses else float("nan")
        h = self.history
        h.epoch_step.append(self.step)
        h.cal_loss.append(cal)
        h.flat_loss.append(flat)
        h.val_loss.append(val)
        # The best network-on state, judged on validation data when there are any.
        score = val if np.isfinite(val) else cal
        if self.state.base.ramp.network is not None and score < float(self.state.best_loss):
            self.state = eqx.tree_at(
                lambda s: (s.best_base, s.best_loss),
                self.state,
                (self.state.base, jnp.asarray(score, self.state.best_loss.dtype)),
            )
        return {"cal": cal, "flat": flat, "val": val}

    def run(
        self,
        checkpoint: Path | None = None,
        progress: bool = True,
        time_limit_s: float | None = None,
    ) -> None:
        """Train until ``settings.steps`` (or, with ``time_limit_s``, until the end of
        the first epoch past that many seconds of training), checkpointing after every
        epoch."""
        reporter = _Reporter(self.settings.steps, self.step, progress)
        try:
            while self.step < self.settings.steps:
                if time_limit_s is not None and self.seconds > time_limit_s:
                    report_step(f"train: time limit reached at step {self.step}")
                    self.stopped_early = True
                    break
                start = time.perf_counter()
                losses = self.epoch()
                self.seconds += time.perf_counter() - start
                if checkpoint is not None:
                    self.save_checkpoint(checkpoint)
                reporter.update(self.step, self.settings.stage_of(max(self.step - 1, 0)), losses)
        finally:
            reporter.close()

    def result(self) -> BaseModel:
        """The trained model: the best network-on state (the current one if none)."""
        state = self.state
        if bool(jnp.isfinite(state.best_loss)):
            return state.best_base
        return state.base

    def statistics(self, base: BaseModel | None = None) -> list[FitStatistics]:
        """Fit statistics of every exposure under ``base`` (default: :meth:`result`),
        with the current source parameters."""
        base = self.result() if base is None else base
        out = []
        state = self.state
        sets: tuple[tuple[Sequence[SlopeData], Sequence[PointSourceParams | FlatParams]], ...] = (
            (self.data.cal, state.cal_params),
            (self.data.flats, state.flat_params),
            (self.data.val, state.val_params),
        )
        for datasets, params in sets:
            for p, d in zip(params, datasets, strict=True):
                model = compiled_model(base, p, d, self.cache)
                out.append(fit_statistics(model, d, p.n_free()))
        return out

    # -------------------------------------------------------------- checkpoints
    def save_checkpoint(self, path: Path) -> None:
        """Write the whole training state (atomically) to ``path``."""
        record = {
            "format": CHECKPOINT_FORMAT,
            "format_version": 2,
            "step": self.step,
            "seconds": self.seconds,
            "settings": asdict(self.settings),
            "config": self.state.base.config.to_json(),
            "data": self.data.describe(),
            "network_on": self.state.base.ramp.network is not None,
            "history": asdict(self.history),
            "rng": self.rng.bit_generator.state,
            "stripes": self.stripes,
        }
        write_leaves(path, (self.state, self.fisher), record)

    def _settings_differ(self, stored: dict[str, Any]) -> list[str]:
        """The settings in which a checkpoint's differ from these (none: it resumes). A
        setting added since the checkpoint was written counts at the value that does what
        the code did before it (:data:`SETTINGS_BEFORE_THEY_EXISTED`); the dark current's
        prior does nothing in level-2 training, so its value does not count there."""
        current = _tuples_to_lists(asdict(self.settings))
        stored = {**SETTINGS_BEFORE_THEY_EXISTED, **stored}
        if self.data.level2:
            current.pop("dark_current_prior")
            stored.pop("dark_current_prior")
        return sorted(k for k in current.keys() | stored.keys() if current.get(k) != stored.get(k))

    def load_checkpoint(self, path: Path) -> None:
        """Continue from a checkpoint written by :meth:`save_checkpoint` for the same
        data and settings (:class:`InputError` otherwise)."""
        with open_npz(path, "checkpoint") as data:
            record = read_record(path, data, CHECKPOINT_FORMAT)
            if not same_data(record["data"], self.data.describe()):
                raise InputError(path, "checkpoint was written for other training data")
            differ = self._settings_differ(record["settings"])
            if differ:
                raise InputError(
                    path,
                    f"checkpoint was written with other training settings ({', '.join(differ)})",
                )
            config = _tuples_to_lists(self.state.base.config.to_json())
            if "config" in record and record["config"] != config:
                raise InputError(path, "checkpoint was written for another model configuration")
            skeleton = self.state
            if record["network_on"]:
                skeleton = eqx.tree_at(
                    lambda s: s.base,
                    skeleton,
                    skeleton.base.with_network(self._fresh_network(skeleton.base, 1)),
                )
            self.state, self.fisher = fill_leaves(
                path, (skeleton, self._fisher_skeleton()), data, allow_infinite=True
            )
        self.step = int(record["step"])
        self.seconds = float(record["seconds"])
        self.history = History(**record["history"])
        self.rng.bit_generator.state = record["rng"]
        self.stripes = record.get("stripes", {})
        self._apply_stripes()


def _with_map_prior(
    leaf: Callable[[BaseModel], Any],
    base: BaseModel,
    grad: BaseModel,
    fisher: BaseModel,
    centre: Any,
    precision: float,
) -> tuple[BaseModel, BaseModel]:
    """``grad`` and ``fisher`` with the Gaussian prior ``precision (x - centre)^2 / 2`` on
    each pixel of the map ``leaf(base)`` added: its gradient and its Fisher diagonal."""
    grad = eqx.tree_at(leaf, grad, leaf(grad) + precision * (leaf(base) - centre))
    # Pixels no calibrator sees had an infinite Fisher (never move): keep them so.
    f = leaf(fisher)
    fisher = eqx.tree_at(leaf, fisher, jnp.where(jnp.isinf(f), f, f + precision))
    return grad, fisher


#: Settings added to :class:`TrainSettings` after checkpoints were first written, at the
#: value that trains as the code did before them (a checkpoint without the key ran so).
SETTINGS_BEFORE_THEY_EXISTED: dict[str, Any] = {"dark_current_prior": 0.0, "detector": "full"}

#: Adam's learning rate of the physical account's strength (units of
#: :data:`~amigo.model.detector.boundary.STRENGTH_UNIT`, 1e-6 pixel per electron) and
#: anisotropy: Adam moves a parameter by about this much per step, so 200 steps can span
#: the simulator's 1.4-2.1e-6 to JWST's 3-5.5e-6 (docs/fidelity.md), and the last steps'
#: noise is a few 1e-8 pixel per electron, a per cent of the strength.
BOUNDARY_LR = 0.02


def _drifting(params: Any) -> bool:
    """Whether an exposure's parameters hold a wavefront drift (a point source trained
    with ``drift_modes`` > 0; never a flat field)."""
    return getattr(params, "drift_nm", None) is not None


def _block_skeleton(params: Sequence[Any]) -> tuple[jax.Array, ...]:
    """Zeros shaped like :meth:`Trainer._block_inverses` of ``params``."""
    out = []
    for p in params:
        if not _drifting(p):
            out.append(jnp.zeros((1, 0)))
            continue
        n = ravel_pytree(p)[0].size
        out.append(jnp.zeros((n + 1, n), p.flux_e.dtype))
    return tuple(out)


def _tuples_to_lists(value: Any) -> Any:
    """JSON turns tuples into lists: compare settings in that form."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in value.items()}


class _Reporter:
    """Progress with the latest losses: a rich bar on a terminal, one line per epoch
    elsewhere."""

    def __init__(self, total: int, done: int, enabled: bool) -> None:
        self.enabled = enabled
        self.progress = None
        if enabled and sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

            self.progress = Progress(
                TextColumn("train"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.description}"),
            )
            self.progress.start()
            self.task = self.progress.add_task("", total=total, completed=done)

    def update(self, step: int, stage: int, losses: dict[str, float]) -> None:
        # A loss with no data behind it (no flat-field or validation files) is NaN: left
        # out rather than printed as "flat nan".
        parts = [f"stage {stage} loss {losses['cal']:.4g}"]
        parts += [f"{k} {losses[k]:.4g}" for k in ("flat", "val") if np.isfinite(losses[k])]
        text = " ".join(parts) + " (chi2/2 per value)"
        if self.progress is not None:
            self.progress.update(self.task, completed=step, description=text)
        elif self.enabled:
            report_step(f"train: step {step}: {text}")

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()


# ---------------------------------------------------------------------------- entry point


def train(
    data: TrainingData,
    out: Path,
    settings: TrainSettings,
    config: BaseModelConfig | None = None,
    resume: bool = False,
    provenance: dict[str, Any] | None = None,
    progress: bool = True,
    time_limit_s: float | None = None,
    initial: BaseModel | None = None,
    superbias: Superbias | None = None,
) -> tuple[BaseModel, dict[str, Any]]:
    """Train a base model and write it to ``out`` (checkpoint: ``out`` + ``.ckpt.npz``);
    from ``initial`` when fine-tuning (``settings.init`` names its file). ``superbias``
    (measured on dark exposures, :func:`amigo.model.detector.reset.estimate_superbias`) is
    stored in the model; without it the model keeps ``initial``'s, if any.

    Returns the model and the metadata written with it.
    """
    out = Path(out)
    checkpoint = checkpoint_path(out)
    trainer = Trainer(data, settings, config, initial=initial)
    if resume and checkpoint.is_file():
        trainer.load_checkpoint(checkpoint)
        report_step(f"train: resumed from {checkpoint} at step {trainer.step}")
    elif resume:
        report_step(f"train: no checkpoint at {checkpoint}; starting afresh")
    if settings.steps == 0:
        # Fine-tuning of the closed-form parts only (the dark residual): the model stays
        # as it is; the exposures' positions and fluxes are fitted under it.
        trainer.warm_up(iterations=FIT_ITERATIONS)
        trainer.measure_stripes()
    else:
        trainer.run(checkpoint, progress, time_limit_s)
    model = trainer.result()
    if superbias is not None:
        model = model.with_superbias(superbias)
    elif initial is not None and initial.superbias is not None:
        model = model.with_superbias(initial.superbias)
    dark_residual = None
    if data.level2 and settings.dark_prior_dn > 0:
        model, dark_residual = solve_dark_residual(
            model, data.cal, trainer.state.cal_params, trainer.cache, settings.dark_prior_dn
        )
    stats = trainer.statistics(model)
    dtype = str(np.asarray(model.hole_centres_m).dtype)
    metadata = {
        "trained_on": "simulated or real calibration exposures listed in 'data'",
        "source_commit": source_commit(),  # the CLI's provenance holds the one at its start
        **(provenance or {}),
        "data": data.describe(),
        "settings": asdict(settings),
        "history": asdict(trainer.history),
        "stripes": _stripes_record(trainer),
        "statistics": [s.to_json() for s in stats],
        "dtype": dtype,
        "amigo_version": __version__,
        "jax_version": jax.__version__,
        "equinox_version": eqx.__version__,
        "numpy_version": np.__version__,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "training_seconds": round(trainer.seconds, 1),
        "steps_done": trainer.step,
        "stopped_by_time_limit": trainer.stopped_early,
        "machine": machine_description(),
        "n_parameters": model.n_parameters,
    }
    if dark_residual is not None:
        metadata["dark_residual"] = dark_residual
    if model.superbias is not None:
        metadata["superbias"] = model.superbias.summary()
    save_base_model(model, out, metadata)
    return model, metadata


def _inverse_sigma_dn_s(data: SlopeData) -> np.ndarray:
    """(ny, nx) ``1 / ERR`` (DN/s)^-1 of a level-2 image, 0 where unused."""
    white = np.asarray(data.whitening, np.float64)[:, 0, 0].reshape(data.shape)
    return white * data.group_time_s


def _stripes_record(trainer: Trainer) -> list[dict[str, Any]]:
    """Each image's measured stripes for the model's metadata (empty: none measured)."""
    out = []
    for key, datasets in (("cal", trainer.data.cal), ("val", trainer.data.val)):
        for d, (tau, length) in zip(datasets, trainer.stripes.get(key, []), strict=False):
            out.append(
                {
                    "name": d.name,
                    "tau_dn_s": round(float(tau), 4),
                    "length_rows": round(float(length), 2) if np.isfinite(length) else None,
                }
            )
    return out


def checkpoint_path(out: Path) -> Path:
    """Where :func:`train` keeps its checkpoint for the model file ``out``."""
    return out.with_name(out.name + ".ckpt.npz")


def loss_curve_path(out: Path) -> Path:
    """Where :func:`train` draws the loss curve of the model file ``out``."""
    return out.with_name(out.name.removesuffix(".npz") + "_loss.png")


def machine_description() -> str:
    """CPU/GPU, core count and platform, for the metadata."""
    import os

    device = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            names = [
                line.split(":", 1)[1].strip() for line in handle if line.startswith("model name")
            ]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (
        f"{device.platform}:{device.device_kind}; {cpu}; {os.cpu_count()} cores; "
        f"{platform.system()} {platform.release()}"
    )
