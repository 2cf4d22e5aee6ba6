"""The trained parameters in groups: which leaves of the base model each data set
calibrates (physical, pixel, dark, network), as boolean masks over the model's tree, and
the split/merge of a model along a mask.

Physical and pixel parameters are handled on the *linear* view of the model (network
subtree None), so that their trees have one structure whether or not the network is on.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from amigo import niriss
from amigo.likelihood.slopes import (
    SlopeData,
)
from amigo.model.base import (
    BaseModel,
)

#
# Physical and pixel parameters are handled on the *linear* view of the model (network
# subtree None), so that their trees have one structure whether or not the network is on.


def false_like(tree: Any) -> Any:
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
        false_like(linear),
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
        lambda m: (m.ramp.flat, m.read.nonlinearity), false_like(linear), (True, True)
    )


def calibrator_pixels(m: BaseModel):
    """The per-pixel leaf trained on the calibrators: the dark current of a model of raw
    ramps, the residual sensitivity (the flat) of a model behind the pipeline."""
    return m.ramp.flat if m.config.data_level == "level2" else m.read.dark_e_per_group


def dark_mask(base: BaseModel) -> BaseModel:
    """Boolean pytree over the linear view: True on the per-pixel leaf trained on the
    calibrators (:func:`calibrator_pixels`: the dark current, or for a level-2 model
    the residual sensitivity)."""
    linear = base.with_linear_detector()
    return eqx.tree_at(calibrator_pixels, false_like(linear), True)


def seen_by(datasets: Sequence[SlopeData]) -> np.ndarray:
    """(ny, nx) True where a pixel enters the likelihood of any of ``datasets``."""
    return np.logical_or.reduce([np.asarray(d.used) > 0 for d in datasets])


def less_common_mode(step: Array, used: np.ndarray) -> Array:
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
