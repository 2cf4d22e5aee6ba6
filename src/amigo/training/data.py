"""What training reads and keeps: its settings, the training data (calibration, flat
and validation exposures), the state it checkpoints and the loss history."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from amigo.errors import InputError
from amigo.likelihood.slopes import (
    FlatParams,
    PointSourceParams,
    SlopeData,
)
from amigo.model.base import (
    BaseModel,
)
from amigo.model.detector.dark_residual import DEFAULT_PRIOR_DN
from amigo.solvers.natural_gradient import FisherMomentum


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

    ``dark_current_prior``: training on calslope files: standard deviation (electrons
    per group) of the Gaussian population prior on each pixel's dark current around the
    median dark of the calibrators' pixels; 0: none. The calibrators' bright pixels cannot
    tell a dark current of a few electrons per group from a misfit of the charge migration
    or the optics (thousands of electrons per group of photons), and without the prior
    their dark absorbs it where the training's dithers put the star, and calibrates
    wrongly at other pixel phases (docs/detector.md, "Training", the dark current's
    population prior); in background pixels the data outweigh it. The default is the robust
    pixel-to-pixel scatter (1.4826 MAD) of the dark the shipped model had learnt without
    it, over the calibrators' pixels (0.133).

    ``dark_prior_dn``: level-2 training: width (DN) of the prior on the per-group read
    offsets the pipeline's dark subtraction left (:func:`solve_dark_residual`); 0: none
    solved.

    ``stripes``: level-2 training: marginalise each image's 1/f column stripes, measured
    after the warm-up and again when the network comes on after the network-off stage
    (:meth:`~amigo.training.trainer.Trainer.measure_stripes`).

    ``drift_modes``, ``drift_prior_nm``: each calibration and validation exposure's own
    small wavefront drift, the per-hole Noll Zernikes 1..``drift_modes`` (0: none) under
    a Gaussian prior of ``drift_prior_nm`` around zero
    (:class:`~amigo.likelihood.slopes.PointSourceParams`): the static optics learn what
    the exposures share, not one exposure's wavefront of the moment.

    ``detector``: the account of the charge migration trained beside the maps: ``"full"``
    (the network) or ``"boundary"`` (the physical account,
    :class:`~amigo.model.detector.boundary.BoundaryShift`: its strength and anisotropy,
    by Adam at :data:`~amigo.training.trainer.BOUNDARY_LR`, kept across stages; calslope
    training only).
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
    dark_current_prior: float = 0.13
    dark_prior_dn: float = DEFAULT_PRIOR_DN
    stripes: bool = True
    drift_modes: int = 0
    drift_prior_nm: float = 5.0
    detector: str = "full"

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


#: What a training's ``data`` record says of a level-2 image the pipeline divided by no
#: flat (``flat_reference``).
NO_FLAT = "(none)"


def same_data(stored: dict[str, Any], current: dict[str, Any]) -> bool:
    """Whether a checkpoint's ``data`` record describes the data of ``current``
    (:meth:`TrainingData.describe`); a record written before the flat references were
    recorded matches on everything else."""
    if stored.keys() != current.keys():
        return False
    for key, items in current.items():
        old = stored[key]
        if len(old) != len(items):
            return False
        for before, now in zip(old, items, strict=True):
            if "flat_reference" not in before:
                now = {k: v for k, v in now.items() if k != "flat_reference"}
            if before != now:
                return False
    return True


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
                # NO_FLAT where the pipeline divided by none (a _rateints image): the
                # residual sensitivity a model learns then holds the whole flat.
                described["flat_reference"] = d.flat_reference or NO_FLAT
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
    #: The steps at which the 1/f stripes were measured (level-2 training).
    stripes_step: list[int] = field(default_factory=list)


CHECKPOINT_FORMAT = "amigo-train-checkpoint"
