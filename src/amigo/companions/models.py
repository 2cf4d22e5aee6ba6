"""Visibility models of a primary star with point-source companions.

Conventions (docs/detect.md)
----------------------------
Offsets are on the sky in mas, ``(dRA, dDec)`` with dRA positive to the east. Baselines
``b`` (m) are expressed in the same sky-aligned frame (each data block maps its own uv
frame onto the sky once, see :mod:`amigo.companions.observables`), so that a point source
at offset ``theta`` has the monochromatic visibility ``exp(-2 pi i b . theta / lambda)``
(the OIFITS sign convention).

A scene of a primary (a point, or a uniform disc of diameter ``d``) and companions of flux
ratios ``c_k`` has the complex visibility::

    V(b) = (V_primary(b) + sum_k c_k e_k(b)) / (1 + sum_k c_k)

where each term is averaged over the filter: ``e_k(b) = sum_l w_l exp(-2 pi i b . theta_k
/ lambda_l)`` with the filter's normalised weights ``w_l``. Averaging the *complex*
visibility (rather than the observables) is right for every observable amigo reads: the
image is linear in each monochromatic visibility, so a splodge- or forward-model-based
measurement at baseline ``b`` sees the throughput-weighted sum of the monochromatic
visibilities there; the observables are then taken from that sum.

Companion fluxes are assumed grey within one filter (one contrast per filter).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array

#: The models' array inputs: NumPy (as read from files) or JAX (traced) arrays.
AnyArray = Array | np.ndarray

#: One milliarcsecond in radians.
MAS_TO_RAD: float = np.pi / (180.0 * 3600.0 * 1000.0)

#: Largest disc argument pi d |b| / lambda for which the series of 2 J1(x)/x is used.
DISC_MAX_ARGUMENT: float = 12.0


def point_phasors(
    uv_m: AnyArray,
    wavelengths_m: AnyArray,
    weights: AnyArray,
    offsets_mas: AnyArray,
) -> Array:
    """Band-averaged visibility of a unit point source at each offset.

    Shapes: ``uv_m`` (n_uv, 2) m; ``wavelengths_m``, ``weights`` (n_uv, n_wl);
    ``offsets_mas`` (..., 2); result (..., n_uv) complex: for every uv point ``b``,
    ``sum_l w_l exp(-2 pi i b . theta / lambda_l)``; ``weights`` sum to one over the last
    axis.
    """
    path_m = jnp.tensordot(offsets_mas, uv_m.T, axes=1) * MAS_TO_RAD  # b . theta, metres
    phase = -2.0 * jnp.pi * path_m[..., None] / wavelengths_m
    return jnp.sum(weights * jnp.exp(1j * phase), axis=-1)


def disc_visibility(
    uv_m: AnyArray,
    wavelengths_m: AnyArray,
    weights: AnyArray,
    diameter_mas: float | Array,
) -> Array:
    """Band-averaged visibility ``2 J1(x)/x`` of a uniform disc, ``x = pi d |b| / lambda``.

    Shapes as :func:`point_phasors`; result (n_uv,) real.

    Uses the power series of ``2 J1(x)/x`` (30 terms), accurate to 1e-10 in float64 for
    ``x <= DISC_MAX_ARGUMENT`` (a 100 mas disc on the 5.3 m AMI baselines at 3.8 um has
    x = 2.1). Larger discs are outside the regime a point-like primary model describes.
    """
    radius_m = jnp.hypot(uv_m[:, 0], uv_m[:, 1])
    x = jnp.pi * diameter_mas * MAS_TO_RAD * radius_m[:, None] / wavelengths_m
    return jnp.sum(weights * airy_amplitude(x), axis=-1)


def airy_amplitude(x: Array, n_terms: int = 30) -> Array:
    """``2 J1(x) / x`` (1 at x = 0) by its power series sum_k (-1)^k (x/2)^2k / (k! (k+1)!)."""
    q = -((x / 2.0) ** 2)
    term = jnp.ones_like(x)
    total = term
    for k in range(1, n_terms):
        term = term * q / (k * (k + 1))
        total = total + term
    return total


def scene_visibility(
    uv_m: AnyArray,
    wavelengths_m: AnyArray,
    weights: AnyArray,
    offsets_mas: AnyArray,
    contrasts: AnyArray,
    primary_diameter_mas: float = 0.0,
) -> Array:
    """Complex visibility of a primary plus ``n_comp`` companions (flux ratios ``contrasts``).

    Shapes: ``offsets_mas`` (n_comp, 2) sky offsets; ``contrasts`` (n_comp,); the rest as
    :func:`point_phasors`; result (n_uv,) complex.

    ``primary_diameter_mas = 0`` is an unresolved primary (visibility 1).
    """
    numerator, denominator = scene_terms(
        uv_m, wavelengths_m, weights, offsets_mas, contrasts, primary_diameter_mas
    )
    return numerator / denominator


def scene_terms(
    uv_m: AnyArray,
    wavelengths_m: AnyArray,
    weights: AnyArray,
    offsets_mas: AnyArray,
    contrasts: AnyArray,
    primary_diameter_mas: float = 0.0,
) -> tuple[Array, Array]:
    """Numerator (complex, per uv point) and denominator (total flux) of the scene visibility.

    Kept apart so that the grid search can add one more companion to a fixed background
    scene cheaply: ``V = (N + c e) / (D + c)``.
    """
    if primary_diameter_mas:
        primary = disc_visibility(uv_m, wavelengths_m, weights, primary_diameter_mas)
    else:
        # In the baselines' precision: a default float64 here would promote a float32
        # evaluation (Dataset.single_precision) back to float64 from this point on.
        primary = jnp.ones_like(uv_m[:, 0])
    numerator = primary.astype(jnp.result_type(primary, 1j))
    if offsets_mas.shape[0]:
        phasors = point_phasors(uv_m, wavelengths_m, weights, offsets_mas)  # (n_comp, n_uv)
        numerator = numerator + jnp.sum(contrasts[:, None] * phasors, axis=0)
    return numerator, 1.0 + jnp.sum(contrasts)


def contrast_to_dmag(contrast: np.ndarray | float) -> np.ndarray:
    """Flux ratio -> magnitude difference ``-2.5 log10(c)``."""
    return -2.5 * np.log10(contrast)


def dmag_to_contrast(dmag: np.ndarray | float) -> np.ndarray:
    """Magnitude difference -> flux ratio ``10**(-dmag / 2.5)``."""
    return 10.0 ** (-np.asarray(dmag) / 2.5)
