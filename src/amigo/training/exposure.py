"""Closed-form and per-exposure pieces of training: the fit of one exposure's position
and flux under a fixed model, and the dark residual that the pipeline's dark subtraction
left in level-2 images, solved from the calibrators' residuals."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from amigo.likelihood.slopes import (
    FitStatistics,
    PointSourceParams,
    SlopeData,
    fit_statistics,
    initial_params,
)
from amigo.model.base import (
    BaseModel,
    PupilCache,
)
from amigo.model.detector.dark_residual import DEFAULT_PRIOR_DN, OffsetSystem, offset_jacobian
from amigo.model.detector.pipeline_slope import pipeline_group_slope
from amigo.progress import step as report_step
from amigo.training.fisher import compiled_model, fisher_diagonal, loss_and_grad, per_layout
from amigo.training.groups import false_like, physical_mask

#: Fraction of the model image counted as model error when the dark residual is solved
#: (:func:`solve_dark_residual`): keeps PSF residuals in the bright core out of it.
MODEL_ERROR = 0.01


@per_layout
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
        estimate = np.asarray(
            pipeline_group_slope(differences, d.group_time_s, gain, d.nframes, d.groups_used),
            np.float64,
        )
        jacobian = offset_jacobian(
            differences, groups, d.group_time_s, gain, d.nframes, d.groups_used
        )
        white = np.asarray(d.whitening, np.float64)[:, 0, 0].reshape(d.shape)
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
    nothing = false_like(physical_mask(base))
    fisher = None
    for k in range(iterations):
        if k % 2 == 0:
            fisher = fisher_diagonal(base, params, data, cache, nothing)[1]
        _, (_, grad) = loss_and_grad(base, params, data, cache)
        params = jax.tree.map(lambda x, g, f: x - g / jnp.maximum(f, 1e-30), params, grad, fisher)
    return params, fit_statistics(compiled_model(base, params, data, cache), data, params.n_free())
