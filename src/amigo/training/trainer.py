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
  a Gaussian prior of width :attr:`TrainSettings.sensitivity_prior` around one: dithers
  move the PSF over the pixels and so tell a pixel's response from the PSF's shape.
* **Dark residual (level 2).** After the steps, the per-pixel offsets of each group read
  that the pipeline's dark subtraction left (:mod:`amigo.model.detector.dark_residual`) are
  solved in closed form from the calibrators' residuals at their fitted states, under a
  Gaussian prior of :attr:`TrainSettings.dark_prior_dn` per read, and stored in the model
  with the dark reference file they belong to (:func:`solve_dark_residual`).
* **Loss curve.** :func:`train` draws the calibration and validation losses against the
  step into ``MODEL_loss.png`` (:func:`loss_curve_path`).

Everything is float32 unless the caller enables 64-bit JAX (the metadata records it).
"""

from __future__ import annotations

import functools
import platform
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from amigo import niriss
from amigo._version import __version__, source_commit
from amigo.errors import InputError
from amigo.likelihood.slopes import (
    FitStatistics,
    FlatParams,
    PointSourceParams,
    SlopeData,
    fit_statistics,
    initial_params,
    model_slopes,
    whiten,
    whitened_residuals,
)
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
from amigo.model.detector.dark_residual import DEFAULT_PRIOR_DN, OffsetSystem, offset_jacobian
from amigo.model.detector.pipeline_slope import pipeline_group_slope
from amigo.model.detector.ramp import ChargeMigrationNetwork
from amigo.model.detector.reset import Superbias
from amigo.progress import step as report_step

# ---------------------------------------------------------------------------- parameter groups
#
# Physical and pixel parameters are handled on the *linear* view of the model (network
# subtree None), so that their trees have one structure whether or not the network is on.


def _false_like(tree: Any) -> Any:
    return jax.tree.map(lambda _: False, tree)


def _physical_leaves(m: BaseModel) -> tuple:
    """The physical parameters trained on calibration exposures, in a fixed order (the
    selector shared by :func:`physical_mask` and :func:`physical_step_limits`)."""
    return (
        m.zernikes_nm,
        m.defocus_nm,
        m.hole_centres_m,
        m.hole_sizes_m,
        m.detector.jitter_arcsec,
        m.detector.rotation_deg,
        m.detector.anisotropy,
        m.detector.skew_deg,
        m.detector.scale,
        m.ramp.intra_pixel.coefficients,
    )


def physical_mask(base: BaseModel, filter_name: str | None = None) -> BaseModel:
    """Boolean pytree over ``base.with_linear_detector()``: True on the physical
    parameters (trained on calibrators); only one filter's optics if ``filter_name``."""
    linear = base.with_linear_detector()

    def on(k: str) -> bool:
        return filter_name is None or k == filter_name

    return eqx.tree_at(
        _physical_leaves,
        _false_like(linear),
        (
            {k: on(k) for k in linear.zernikes_nm},
            {k: on(k) for k in linear.defocus_nm},
            True,
            True,
            True,
            True,
            True,
            True,
            True,
            True,
        ),
    )


def physical_step_limits(base: BaseModel) -> BaseModel:
    """Largest move of each physical parameter in one step (the trust region), shaped
    like ``split(base, physical_mask(base))``: 2 nm of aberration, 5 nm of defocus, 2 mm
    of hole position, 1 mm of hole size, 1 mas of jitter, 0.05 deg of rotation, 5e-4 of anisotropy, 0.05 deg
    of skew, 5e-4 of scale, 0.05 of intra-pixel response."""
    physical = split(base, physical_mask(base))
    limits = (
        {k: jnp.full_like(v, 2.0) for k, v in physical.zernikes_nm.items()},
        {k: jnp.full_like(v, 5.0) for k, v in physical.defocus_nm.items()},
        jnp.full_like(physical.hole_centres_m, 2e-3),
        jnp.full_like(physical.hole_sizes_m, 1e-3),
        jnp.full_like(physical.detector.jitter_arcsec, 1e-3),
        jnp.full_like(physical.detector.rotation_deg, 0.05),
        jnp.full_like(physical.detector.anisotropy, 5e-4),
        jnp.full_like(physical.detector.skew_deg, 0.05),
        jnp.full_like(physical.detector.scale, 5e-4),
        jnp.full_like(physical.ramp.intra_pixel.coefficients, 0.05),
    )
    return eqx.tree_at(
        _physical_leaves,
        physical,
        limits,
    )


def pixel_mask(base: BaseModel) -> BaseModel:
    """Boolean pytree over the linear view: True on the flat field and non-linearity
    (trained on flat fields only)."""
    linear = base.with_linear_detector()
    return eqx.tree_at(
        lambda m: (m.ramp.flat, m.read.nonlinearity), _false_like(linear), (True, True)
    )


def _calibrator_pixels(m: BaseModel):
    """The per-pixel leaf trained on the calibrators: the dark current of a model of raw
    ramps, the residual sensitivity (the flat) of a model behind the pipeline."""
    return m.ramp.flat if m.config.data_level == "level2" else m.read.dark_e_per_group


def dark_mask(base: BaseModel) -> BaseModel:
    """Boolean pytree over the linear view: True on the per-pixel leaf trained on the
    calibrators (:func:`_calibrator_pixels`: the dark current, or for a level-2 model
    the residual sensitivity)."""
    linear = base.with_linear_detector()
    return eqx.tree_at(_calibrator_pixels, _false_like(linear), True)


def _seen_by(datasets: Sequence[SlopeData]) -> np.ndarray:
    """(ny, nx) True where a pixel enters the likelihood of any of ``datasets``."""
    return np.logical_or.reduce([np.asarray(d.used) > 0 for d in datasets])


def _less_common_mode(step: Array, used: np.ndarray) -> Array:
    """A per-pixel step less its mean over the ``used`` pixels (the others as they are)."""
    return jnp.where(used, step - jnp.mean(step[used]), step)


def pin_mask_centroid(base: BaseModel) -> BaseModel:
    """``base`` with its hole centres moved together so that their mean is the nominal
    mask's.

    Moving the whole mask across the pupil multiplies the focal-plane field by a phase
    ramp: the image does not change, only which part of the wavefront each hole samples,
    which the per-hole Zernikes describe anyway. The data do not constrain that common
    shift, so training let it drift (19 mm across 400 steps of the first real-data model,
    2.4 % of a hole); pinning it leaves the 12 relative positions free.
    """
    nominal = jnp.asarray(niriss.HOLE_CENTRES_M, base.hole_centres_m.dtype)
    centres = base.hole_centres_m
    shift = jnp.mean(centres - nominal, axis=0)
    return eqx.tree_at(lambda m: m.hole_centres_m, base, centres - shift)


def split(tree: BaseModel, mask: BaseModel) -> BaseModel:
    """The leaves of ``tree`` (a model or a gradient) selected by ``mask`` (None elsewhere)."""
    return eqx.filter(tree.with_linear_detector(), mask)


def merge(base: BaseModel, part: BaseModel, mask: BaseModel) -> BaseModel:
    """``base`` with the leaves selected by ``mask`` replaced by those of ``part``."""
    rest = eqx.filter(base.with_linear_detector(), mask, inverse=True)
    return eqx.combine(part, rest).with_network(base.ramp.network)


# ---------------------------------------------------------------------------- compiled pieces


def _per_layout(function):
    """``eqx.filter_jit(function)``, called with every :class:`SlopeData` argument reduced
    to what the computation reads (:meth:`SlopeData.layout`): the exposures of one filter
    and number of groups then share one traced and compiled program. With the file name,
    role and value count in the key, every exposure traced and lowered its own (seconds
    each on a CPU: a training on 33 calibrator files traced each program 33 times)."""
    compiled = eqx.filter_jit(function)

    @functools.wraps(function)
    def call(*args):
        return compiled(*(a.layout() if isinstance(a, SlopeData) else a for a in args))

    return call


@_per_layout
def _loss_and_grad(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache):
    """``(chi2 / 2, (d/dbase, d/dparams))`` of one exposure (compiled once per filter and
    number of groups)."""

    def loss(bp):
        b, p = bp
        return 0.5 * jnp.sum(whitened_residuals(model_slopes(b, cache, p, data), data) ** 2)

    return eqx.filter_value_and_grad(loss)((base, params))


@_per_layout
def _model(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache):
    return model_slopes(base, cache, params, data)


@_per_layout
def _fisher(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any):
    linear = base.with_linear_detector()
    diff, static = eqx.partition((linear, params), (mask, jax.tree.map(lambda _: True, params)))
    vector, unravel = ravel_pytree(diff)

    def residuals(v):
        b, p = eqx.combine(unravel(v), static)
        return whitened_residuals(model_slopes(b, cache, p, data), data).ravel()

    jac = jax.jacfwd(residuals)(vector)  # (n_values, n_params)
    return jac.T @ jac


def fisher_matrix(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Fisher (Gauss-Newton) matrix ``J^T J`` of the whitened residuals ``z`` of the
    *linear-detector* model, from the exact Jacobian (forward mode, one column per
    parameter), for the base-model leaves selected by ``mask`` (a
    :func:`physical_mask`-like tree) and every per-exposure parameter.

    Returns ``(F_base, F_params)``: the block of the selected base parameters, in the
    order of ``ravel_pytree(split(base, mask))``, and the diagonal of the per-exposure
    block (float64 NumPy).
    """
    # The linear view: one compiled function whether or not the network is on.
    linear = base.with_linear_detector()
    matrix = np.asarray(_fisher(linear, params, data, cache, mask), dtype=np.float64)
    n_base = ravel_pytree(split(base, mask))[0].size
    return matrix[:n_base, :n_base], np.diagonal(matrix)[n_base:]


def fisher_diagonal(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any
) -> tuple[Any, Any]:
    """The diagonals of :func:`fisher_matrix`, shaped like ``split(base, mask)`` and
    ``params``."""
    f_base, f_params = fisher_matrix(base, params, data, cache, mask)
    unravel_base = ravel_pytree(split(base, mask))[1]
    unravel_params = ravel_pytree(params)[1]
    return unravel_base(jnp.asarray(np.diagonal(f_base))), unravel_params(jnp.asarray(f_params))


@_per_layout
def pixel_fisher(
    base: BaseModel, params: FlatParams, data: SlopeData
) -> tuple[BaseModel, Float[Array, "ny nx"]]:
    """Per-pixel 2 x 2 Fisher matrix of the flat field and the non-linearity from one
    flat field: its diagonal, shaped like ``split(base, pixel_mask(base))``, and the
    (ny, nx) cross term. A pixel's parameters act (IPC aside) on that pixel's slopes
    only, so one forward-mode pass with a tangent of ones gives every pixel's derivative
    at once. Under one light level the two are strongly correlated (the non-linearity
    bends the ramp, the flat scales it): the cross term is what keeps a Newton step of
    the pair from overshooting (see :func:`pixel_newton`)."""

    def slopes(flat, nonlinearity):
        b = eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), base, (flat, nonlinearity))
        return model_slopes(b, None, params, data)  # type: ignore[arg-type]

    primals = (base.ramp.flat, base.read.nonlinearity)
    dz = []
    for index in range(2):
        tangents = tuple(
            jnp.ones_like(p) if i == index else jnp.zeros_like(p) for i, p in enumerate(primals)
        )
        _, dslopes = jax.jvp(slopes, primals, tangents)
        dz.append(whiten(dslopes, data))  # the derivative of W (data - model), up to sign
    diagonal = tuple(jnp.sum(d**2, axis=1).reshape(data.shape) for d in dz)
    cross = jnp.sum(dz[0] * dz[1], axis=1).reshape(data.shape)
    mask = pixel_mask(base)
    tree = eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), split(base, mask), diagonal)
    return tree, cross


def pixel_newton(grad: BaseModel, fisher: dict[str, Any], damping: float) -> BaseModel:
    """``(F + damping diag F)^-1 g`` per pixel for the (flat, non-linearity) pair, ``F``
    the per-pixel 2 x 2 Fisher matrix (``fisher``: ``"diag"`` shaped like ``grad``,
    ``"cross"`` (ny, nx)); zero where a pixel is not constrained."""
    a = fisher["diag"].ramp.flat * (1.0 + damping)
    b = fisher["diag"].read.nonlinearity * (1.0 + damping)
    c = fisher["cross"]
    g_f, g_n = grad.ramp.flat, grad.read.nonlinearity
    det = a * b - c**2
    ok = (a > 0) & (b > 0) & jnp.isfinite(det) & (det > 0)
    det = jnp.where(ok, det, 1.0)
    step_f = jnp.where(ok, (b * g_f - c * g_n) / det, 0.0)
    step_n = jnp.where(ok, (a * g_n - c * g_f) / det, 0.0)
    return eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), grad, (step_f, step_n))


@_per_layout
def dark_fisher(
    base: BaseModel, params: PointSourceParams, data: SlopeData, cache: PupilCache
) -> BaseModel:
    """Per-pixel Fisher diagonal of the calibrators' per-pixel leaf (the dark current, or
    a level-2 model's residual sensitivity) from one calibration exposure, shaped like
    ``split(base, dark_mask(base))`` (one forward-mode pass with a tangent of ones, as
    :func:`pixel_fisher`; a pixel's dark charge or sensitivity, IPC and charge migration
    aside, reaches only that pixel's slopes)."""

    def slopes(value):
        b = eqx.tree_at(_calibrator_pixels, base, value)
        return model_slopes(b, cache, params, data)

    value = _calibrator_pixels(base)
    _, dslopes = jax.jvp(slopes, (value,), (jnp.ones_like(value),))
    dz = whiten(dslopes, data)
    per_pixel = jnp.sum(dz**2, axis=1).reshape(data.shape)
    return eqx.tree_at(_calibrator_pixels, split(base, dark_mask(base)), per_pixel)


# ---------------------------------------------------------------------------- optimiser


class FisherMomentum(eqx.Module):
    """Nesterov momentum on Fisher-preconditioned gradients (a diagonal natural gradient).

    ``v <- mu v + g / F``; ``theta <- theta - lr (g / F + mu v)``. ``lr = 1`` is a Newton
    step per parameter for a quadratic loss with a diagonal Hessian.
    """

    velocity: Any
    learning_rate: float = eqx.field(static=True, default=0.5)
    momentum: float = eqx.field(static=True, default=0.6)

    @classmethod
    def init(cls, params: Any, learning_rate: float = 0.5, momentum: float = 0.6):
        return cls(jax.tree.map(jnp.zeros_like, params), learning_rate, momentum)

    def update(self, params: Any, grads: Any, fisher: Any, floor: float = 1e-30):
        """One step; returns ``(new_params, new_optimiser)``."""
        scaled = jax.tree.map(lambda g, f: g / jnp.maximum(f, floor), grads, fisher)
        velocity = jax.tree.map(lambda v, s: self.momentum * v + s, self.velocity, scaled)
        new = jax.tree.map(
            lambda p, s, v: p - self.learning_rate * (s + self.momentum * v),
            params,
            scaled,
            velocity,
        )
        return new, eqx.tree_at(lambda o: o.velocity, self, velocity)

    def update_vector(
        self,
        vector: jax.Array,
        grad: jax.Array,
        preconditioner: jax.Array,
        limit: jax.Array | None = None,
    ):
        """The same step on a flat parameter vector with a full preconditioning matrix
        (the inverse of the damped Fisher matrix): a Gauss-Newton direction. ``limit``
        (same shape) is a trust region: the whole step is shrunk so that no parameter
        moves by more than its limit (far from the optimum a Gauss-Newton step of the
        optics can be wildly non-linear)."""
        scaled = preconditioner @ grad
        velocity = self.momentum * self.velocity + scaled
        delta = self.learning_rate * (scaled + self.momentum * velocity)
        if limit is not None:
            shrink = jnp.minimum(1.0, jnp.min(limit / jnp.maximum(jnp.abs(delta), 1e-30)))
            delta, velocity = delta * shrink, velocity * shrink
        return vector - delta, eqx.tree_at(lambda o: o.velocity, self, velocity)


# ---------------------------------------------------------------------------- settings, data


@dataclass(frozen=True)
class TrainSettings:
    """Hyper-parameters of :func:`train` (all recorded in the model's metadata).

    ``steps`` batch steps in all (0, with ``init``: none; only the closed-form dark
    residual of level-2 training is solved afresh); ``stage_steps`` the steps of each stage (stage 0 with
    the network off, then one stage per network restart); by default a fifth of the
    steps with the network off and the rest split over two network restarts.

    ``init`` (the path of a base model, recorded here): fine-tuning. Training starts
    from that model, network included, so stage 0 is empty: ``stage_steps`` (default all
    ``steps``) then lists the stages with the network on, the first continuing the
    model's network and every later one restarting it.

    ``sensitivity_prior``: standard deviation of the Gaussian prior on each pixel's
    residual sensitivity around one when training on level-2 images (the pipeline's flat
    is good to about a per cent; unused otherwise).

    ``dark_prior_dn``: level-2 training: width (DN) of the prior on the per-group read
    offsets the pipeline's dark subtraction left (:func:`solve_dark_residual`); 0: none
    solved.
    """

    steps: int = 200
    n_batches: int = 5
    stage_steps: tuple[int, ...] = ()
    init: str | None = None
    physical_lr: float = 0.5
    pixel_lr: float = 0.8
    dark_lr: float = 0.25
    exposure_lr: float = 0.5
    momentum: float = 0.6
    network_lr: float = 3e-3
    network_init_scale: float = 0.01
    damping: float = 0.1
    seed: int = 0
    diagonal: bool = False
    sensitivity_prior: float = 0.01
    dark_prior_dn: float = DEFAULT_PRIOR_DN

    def stages(self) -> list[int]:
        if self.init is not None:
            return [0, *(self.stage_steps or (self.steps,))]
        if self.stage_steps:
            return list(self.stage_steps)
        first = max(1, self.steps // 5)
        rest = self.steps - first
        if rest <= 1:
            return [first, rest] if rest else [first]
        return [first, rest - rest // 2, rest // 2]

    def stage_of(self, step: int) -> int:
        return int(np.searchsorted(np.cumsum(self.stages()), step, side="right"))


@dataclass
class TrainingData:
    """Calibration, flat-field and validation exposures (:class:`SlopeData`)."""

    cal: list[SlopeData]
    flats: list[SlopeData]
    val: list[SlopeData]

    @classmethod
    def read(
        cls,
        cal: Sequence[str | Path],
        flats: Sequence[str | Path] = (),
        val: Sequence[str | Path] = (),
        diagonal: bool = False,
        dtype=jnp.float32,
    ) -> TrainingData:
        if not cal:
            raise InputError("--cal", "at least one calibration exposure is needed")
        read = SlopeData.read
        return cls(
            cal=[read(p, "calibrator", diagonal, dtype) for p in cal],
            flats=[read(p, "flat", diagonal, dtype) for p in flats],
            val=[read(p, "validation", diagonal, dtype) for p in val],
        )

    @property
    def filters(self) -> tuple[str, ...]:
        return tuple(sorted({d.filter for d in self.cal + self.val}))

    @property
    def level2(self) -> bool:
        """Whether the exposures are level-2 images (:meth:`check` makes them all one
        kind)."""
        return bool(self.cal) and self.cal[0].level2

    def check(self) -> None:
        """Refuse a mix of level-2 images and calslope files (one model cannot stand both
        in front of and behind the pipeline) and flat fields with level-2 images (the
        :class:`Trainer` checks its data)."""
        kinds = {d.level2 for d in self.cal + self.val}
        if len(kinds) > 1:
            odd = next(d for d in self.cal + self.val if d.level2 != self.cal[0].level2)
            raise InputError(
                odd.name, "level-2 images and calslope files cannot be mixed in one training"
            )
        if self.level2 and self.flats:
            raise InputError(
                self.flats[0].name,
                "flat fields train the detector of raw ramps; a level-2 model learns the "
                "residual sensitivity from the calibrators",
            )

    def describe(self) -> dict[str, Any]:
        def one(d: SlopeData) -> dict[str, Any]:
            described = {"name": d.name, "filter": d.filter, "ngroups": d.ngroups}
            if d.level2:
                described["level"] = "level2"
                described["dark_reference"] = d.dark_reference
            return {**described, "values": d.n_values}

        return {
            "calibration": [one(d) for d in self.cal],
            "flats": [one(d) for d in self.flats],
            "validation": [one(d) for d in self.val],
        }


class TrainState(eqx.Module):
    """Everything that changes during training (what a checkpoint holds)."""

    base: BaseModel
    cal_params: tuple[PointSourceParams, ...]
    flat_params: tuple[FlatParams, ...]
    val_params: tuple[PointSourceParams, ...]
    physical_opt: FisherMomentum
    pixel_opt: FisherMomentum
    dark_opt: FisherMomentum
    cal_opt: FisherMomentum
    flat_opt: FisherMomentum
    val_opt: FisherMomentum
    adam_state: Any
    best_base: BaseModel
    best_loss: jax.Array


@dataclass
class History:
    """Losses: per step (calibration batch, chi2/2 per slope value) and per epoch."""

    step: list[int] = field(default_factory=list)
    stage: list[int] = field(default_factory=list)
    loss: list[float] = field(default_factory=list)
    epoch_step: list[int] = field(default_factory=list)
    cal_loss: list[float] = field(default_factory=list)
    flat_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)


CHECKPOINT_FORMAT = "amigo-train-checkpoint"


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
    ) -> None:
        self.data = data
        self.settings = settings
        if (initial is None) != (settings.init is None):
            raise ValueError("settings.init names the initial model: give both or neither")
        where = "--cal" if initial is None else settings.init
        if initial is not None:
            config = initial.config
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
        data.check()
        if data.level2:
            base = base.for_level2()  # the model behind the pipeline
        elif base.config.data_level == "level2":
            raise InputError(where, "was trained on level-2 images: raw ramps need a ramp model")
        self.cache = base.pupil_cache() if cache is None else cache
        self.rng = np.random.default_rng(settings.seed)
        self.history = History()
        self.step = 0
        self.seconds = 0.0
        self.state = self._initial_state(base)
        self.fisher: dict[str, Any] | None = None
        self.stopped_early = False

    # -------------------------------------------------------------- state
    def _initial_state(self, base: BaseModel) -> TrainState:
        s = self.settings
        cal = tuple(initial_params(base, d) for d in self.data.cal)
        flats = tuple(initial_params(base, d) for d in self.data.flats)
        val = tuple(initial_params(base, d) for d in self.data.val)
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
            adam_state=optax.adam(s.network_lr).init(eqx.filter(network, eqx.is_array)),
            best_base=base.with_network(network),
            best_loss=jnp.asarray(np.inf),
        )

    def _fresh_network(self, base: BaseModel, stage: int) -> ChargeMigrationNetwork:
        c = base.config
        key = jax.random.fold_in(jax.random.PRNGKey(self.settings.seed), stage)
        return ChargeMigrationNetwork(
            key,
            width=c.network_width,
            depth=c.network_depth,
            charge_scale_e=c.charge_scale_e,
            init_scale=self.settings.network_init_scale,
        )

    # -------------------------------------------------------------- warm-up
    def warm_up(self, iterations: int = 3) -> None:
        """Newton steps on every exposure's own parameters (position and flux, or a
        flat's level) with the instrument fixed: the centroid and total-flux starting
        values are too rough for the joint fit. Keeps each exposure's Fisher diagonal
        for :meth:`compute_fisher`."""
        state, base, cache = self.state, self.state.base, self.cache
        nothing = _false_like(physical_mask(base))
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
                    _, (_, grad) = _loss_and_grad(base, p, d, cache)
                    p = jax.tree.map(lambda x, g, f: x - g / jnp.maximum(f, 1e-30), p, grad, fisher)
                params[i] = p
                fishers.append(fisher)
            groups.append(tuple(params))
            self._exposure_fisher[name] = fishers
        report_step("train: warm-up of positions and fluxes done")
        self.state = eqx.tree_at(
            lambda s: (s.cal_params, s.flat_params, s.val_params), state, tuple(groups)
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
        nothing = _false_like(full)
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
        for p, d in zip(state.cal_params, self.data.cal, strict=True):
            dark = jax.tree.map(jnp.add, dark, dark_fisher(base, p, d, cache))
        dark = jax.tree.map(lambda f: jnp.where(f > 0, f, jnp.inf), dark)
        self.fisher = {
            "physical": jnp.asarray(inverse, vector.dtype),
            "pixel": pixel,
            "dark": dark,
            "cal": tuple(cal_fisher),
            "val": tuple(val_fisher),
            "flat": tuple(flat_fisher),
        }

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
        grad_base, loss, values = None, 0.0, 0
        grads = [jax.tree.map(jnp.zeros_like, p) for p in state.cal_params]
        for i in batch:
            d = self.data.cal[i]
            value, (gb, gp) = _loss_and_grad(base, state.cal_params[i], d, self.cache)
            if not np.isfinite(float(value)):
                # e.g. a detector geometry beyond the resampling's reach (NaN images)
                raise FloatingPointError(
                    f"training diverged at step {self.step + 1}: the loss of calibration "
                    f"exposure {i} is not finite"
                )
            loss, values = loss + float(value), values + d.n_values
            grad_base = gb if grad_base is None else jax.tree.map(jnp.add, grad_base, gb)
            grads[i] = gp
        # Source parameters of the exposures in the batch (the others keep their state).
        moved, moved_opt = state.cal_opt.update(state.cal_params, tuple(grads), self.fisher["cal"])
        inside = set(batch)
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
            self.fisher["physical"],
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
            fisher = self.fisher["dark"]
            if self.data.level2:
                g_dark, fisher = self._sensitivity_prior(base, g_dark, fisher)
            dark, dark_opt = dark_opt.update(split(base, mask), g_dark, fisher)
            if self.data.level2:
                dark = self._without_common_mode(split(base, mask), dark)
            base = merge(base, dark, mask)
        adam_state = state.adam_state
        if use_network and base.ramp.network is not None:
            weights = eqx.filter(base.ramp.network, eqx.is_array)
            g_net = eqx.filter(grad_base.ramp.network, eqx.is_array)
            updates, adam_state = optax.adam(self.settings.network_lr).update(
                g_net, adam_state, weights
            )
            base = base.with_network(eqx.apply_updates(base.ramp.network, updates))
        base = eqx.tree_at(
            lambda m: m.detector.jitter_arcsec, base, jnp.abs(base.detector.jitter_arcsec)
        )
        self.state = eqx.tree_at(
            lambda s: (s.base, s.cal_params, s.cal_opt, s.physical_opt, s.dark_opt, s.adam_state),
            state,
            (base, cal_params, cal_opt, physical_opt, dark_opt, adam_state),
        )
        return loss / max(values, 1)

    def _sensitivity_prior(self, base: BaseModel, grad: BaseModel, fisher: BaseModel):
        """Add the Gaussian prior ``(s - 1)^2 / (2 sigma^2)`` on each pixel's residual
        sensitivity ``s`` to its gradient and Fisher diagonal (level-2 training)."""
        precision = 1.0 / self.settings.sensitivity_prior**2
        flat = base.ramp.flat
        grad = eqx.tree_at(lambda m: m.ramp.flat, grad, grad.ramp.flat + precision * (flat - 1.0))
        # Pixels no calibrator sees had an infinite Fisher (never move): keep them so.
        f = fisher.ramp.flat
        fisher = eqx.tree_at(
            lambda m: m.ramp.flat, fisher, jnp.where(jnp.isinf(f), f, f + precision)
        )
        return grad, fisher

    def _without_common_mode(self, before: BaseModel, after: BaseModel) -> BaseModel:
        """The sensitivity step less its mean over the calibrators' pixels: the mean
        sensitivity is degenerate with every exposure's flux, which carries it (pixels no
        calibrator sees have an infinite Fisher diagonal: their step is zero)."""
        step = _less_common_mode(after.ramp.flat - before.ramp.flat, _seen_by(self.data.cal))
        return eqx.tree_at(lambda m: m.ramp.flat, after, before.ramp.flat + step)

    def flat_step(self) -> float:
        """Update the flat field, the non-linearity and the flats' levels from the
        flat-field exposures; returns their chi2/2 per value before the step."""
        state, base = self.state, self.state.base
        if not self.data.flats:
            return float("nan")
        grad_base, grads, loss, values = None, [], 0.0, 0
        for p, d in zip(state.flat_params, self.data.flats, strict=True):
            value, (gb, gp) = _loss_and_grad(base, p, d, self.cache)
            loss, values = loss + float(value), values + d.n_values
            grad_base = gb if grad_base is None else jax.tree.map(jnp.add, grad_base, gb)
            grads.append(gp)
        flat_params, flat_opt = state.flat_opt.update(
            state.flat_params, tuple(grads), self.fisher["flat"]
        )
        mask = pixel_mask(base)
        # A joint Newton step of each pixel's (flat, non-linearity) pair (zero where no
        # flat constrains it), then momentum on it (unit "Fisher": already preconditioned).
        direction = pixel_newton(
            split(grad_base, mask), self.fisher["pixel"], self.settings.damping
        )
        # The flat's mean is degenerate with every flux: the flats' levels carry it, the
        # flat's step has none (a common-mode step would jolt every calibrator's flux).
        used = _seen_by(self.data.flats)
        step = _less_common_mode(direction.ramp.flat, used)
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
            value, (_, gp) = _loss_and_grad(state.base, p, d, self.cache)
            loss, values = loss + float(value), values + d.n_values
            grads.append(gp)
        val_params, val_opt = state.val_opt.update(
            state.val_params, tuple(grads), self.fisher["val"]
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
        network = state.base.ramp.network if keep else self._fresh_network(base, stage)
        s = self.settings
        self.state = eqx.tree_at(
            lambda st: (st.base, st.adam_state, st.physical_opt),
            state,
            (
                base.with_network(network),
                optax.adam(s.network_lr).init(eqx.filter(network, eqx.is_array)),
                FisherMomentum.init(ravel_pytree(split(base, mask))[0], s.physical_lr, s.momentum),
            ),
        )
        if keep:
            report_step(f"train: stage 1: fine-tuning the network of {self.settings.init}")
        else:
            report_step(f"train: stage {stage}: network restarted from new weights (seed {stage})")

    def epoch(self) -> dict[str, float]:
        """One pass over the calibration batches (stopping at ``settings.steps``), then
        one flat-field step and one validation step; returns the epoch's losses."""
        if self.fisher is None:
            self.warm_up()
            self.compute_fisher()
        losses = []
        for batch in self._batches():
            if self.step >= self.settings.steps:
                break
            stage = self.settings.stage_of(self.step)
            if self.step == 0 or stage != self.settings.stage_of(self.step - 1):
                self.start_stage(stage)
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
        sets = (
            (self.data.cal, self.state.cal_params, 3),
            (self.data.flats, self.state.flat_params, 1),
            (self.data.val, self.state.val_params, 3),
        )
        for datasets, params, n_free in sets:
            for p, d in zip(params, datasets, strict=True):
                out.append(fit_statistics(_model(base, p, d, self.cache), d, n_free))
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
        }
        write_leaves(path, (self.state, self.fisher), record)

    def load_checkpoint(self, path: Path) -> None:
        """Continue from a checkpoint written by :meth:`save_checkpoint` for the same
        data and settings (:class:`InputError` otherwise)."""
        with open_npz(path, "checkpoint") as data:
            record = read_record(path, data, CHECKPOINT_FORMAT)
            if record["data"] != self.data.describe():
                raise InputError(path, "checkpoint was written for other training data")
            if _tuples_to_lists(asdict(self.settings)) != record["settings"]:
                raise InputError(path, "checkpoint was written with other training settings")
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
            self.state, self.fisher = fill_leaves(path, (skeleton, self._fisher_skeleton()), data)
        self.step = int(record["step"])
        self.seconds = float(record["seconds"])
        self.history = History(**record["history"])
        self.rng.bit_generator.state = record["rng"]


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
        text = (
            f"stage {stage} loss {losses['cal']:.4g} flat {losses['flat']:.4g} "
            f"val {losses['val']:.4g} (chi2/2 per value)"
        )
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


#: Fraction of the model image counted as model error when the dark residual is solved
#: (:func:`solve_dark_residual`): keeps PSF residuals in the bright core out of it.
MODEL_ERROR = 0.01


@_per_layout
def _ramp_differences(base: BaseModel, params: PointSourceParams, data: SlopeData, cache):
    """(ngroups - 1, ny, nx) group differences (DN per group) of a point source's model
    ramp: what the pipeline's estimator sees, before it."""
    unit = base.illuminance(data.filter, params.position_arcsec, cache)
    return base.slopes(params.flux_e * unit, data.ngroups)


def solve_dark_residual(
    base: BaseModel,
    datasets: Sequence[SlopeData],
    params: Sequence[PointSourceParams],
    cache: PupilCache,
    prior_dn: float = DEFAULT_PRIOR_DN,
    model_error: float = MODEL_ERROR,
) -> tuple[BaseModel, dict[str, Any]]:
    """``base`` with the per-group read offsets that best explain the level-2
    calibrators ``datasets`` at their fitted ``params`` (see
    :mod:`amigo.model.detector.dark_residual`), and a record of the solve.

    Each pixel's variance in the solve is its noise plus ``(model_error * model)^2``: the
    PSF model's own errors where the star is bright (1-4 % of the signal in the cores of
    the COM 1093 calibrators) must not be taken for a detector offset. The offsets there
    come from the prior and the halo's exposures, where the noise is read noise.

    Only images behind one dark reference file can share offsets: those of the most
    common ``R_DARK`` are used (the others are listed as skipped). Offsets are solved for
    the reads of the longest ramp among them; the model's own offsets, where they were
    measured behind the same file with as many reads, are the starting point (the
    residuals are taken with them), else they are dropped first. The model keeps the
    posterior's Cholesky factor and ``prior_dn`` with them: the uncertainty of the
    offsets, which fits add to the images' variance.
    """
    usable = [(d, p) for d, p in zip(datasets, params, strict=True) if d.level2]
    references = sorted({d.dark_reference for d, _ in usable if d.dark_reference})
    if not references:
        return base, {"solved": False, "reason": "no level-2 image names its dark reference"}
    reference = max(references, key=lambda r: sum(d.dark_reference == r for d, _ in usable))
    chosen = [(d, p) for d, p in usable if d.dark_reference == reference]
    groups = max(d.ngroups for d, _ in chosen)
    config = base.config
    same = config.dark_reference == reference and config.dark_residual_groups == groups
    model = base if same else base.with_dark_residual(None)
    current = np.asarray(base.read.group_offsets_dn, np.float64) if same else None
    system = OffsetSystem.empty(groups, config.shape)
    gain = model.read.gain_e_per_dn
    for d, p in chosen:
        differences = _ramp_differences(model, p, d, cache)
        estimate = pipeline_group_slope(differences, d.group_time_s, gain, d.nframes)
        jacobian = offset_jacobian(differences, groups, d.group_time_s, gain, d.nframes)
        white = np.asarray(d.whitening, np.float64)[:, 0, 0].reshape(d.shape)
        estimate = np.asarray(estimate, np.float64)
        with np.errstate(divide="ignore"):
            variance = np.where(white > 0, 1.0 / white**2, np.inf) + (model_error * estimate) ** 2
        residual = np.asarray(d.slopes_dn[0], np.float64) - estimate
        system.add(jacobian, residual * (white > 0), 1.0 / variance, d.ngroups)
    offsets = system.solve(prior_dn, current)
    # What the calibrators left unknown of each pixel's offsets: the variance an image at
    # NGROUPS they did not cover inherits (BaseModel.dark_offset_terms).
    chol = system.posterior_cholesky(prior_dn)
    rms = float(np.sqrt(np.mean(offsets**2)))
    report_step(
        f"train: dark residual: {groups} group reads solved from {len(chosen)} exposures "
        f"behind {reference} (rms {rms:.2f} DN)"
    )
    record = {
        "solved": True,
        "reference": reference,
        "prior_dn": prior_dn,
        "model_error": model_error,
        "groups": groups,
        "exposures": [d.name for d, _ in chosen],
        "skipped": [d.name for d, _ in usable if d.dark_reference != reference],
        "rms_dn": round(rms, 4),
    }
    return base.with_dark_residual(offsets, reference, chol, prior_dn), record


#: Newton steps of an exposure's own parameters under a fixed instrument (fit_exposure).
FIT_ITERATIONS = 8


def fit_exposure(
    base: BaseModel,
    data: SlopeData,
    cache: PupilCache,
    iterations: int = FIT_ITERATIONS,
    params: Any = None,
) -> tuple[Any, FitStatistics]:
    """Fit one exposure's own parameters (position and flux of a point source, or a flat's
    level) with the instrument fixed: Newton steps preconditioned by the Fisher diagonal
    (recomputed every other step). A stand-in for the fitting engine of ``amigo fit``,
    used for validation and the acceptance figures (docs/detector.md)."""
    params = initial_params(base, data) if params is None else params
    nothing = _false_like(physical_mask(base))
    fisher = None
    for k in range(iterations):
        if k % 2 == 0:
            fisher = fisher_diagonal(base, params, data, cache, nothing)[1]
        _, (_, grad) = _loss_and_grad(base, params, data, cache)
        params = jax.tree.map(lambda x, g, f: x - g / jnp.maximum(f, 1e-30), params, grad, fisher)
    n_free = len(jax.tree.leaves(params)) + (1 if isinstance(params, PointSourceParams) else 0)
    return params, fit_statistics(_model(base, params, data, cache), data, n_free)
