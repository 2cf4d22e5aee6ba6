"""What the pipeline's dark subtraction leaves in a level-2 image, and how it is measured.

The STScI pipeline subtracts a dark *reference ramp* from every integration, group by
group (``dark_current`` step, the reference file named by the level-2 header's
``R_DARK``), before it fits each pixel's slope. That reference is itself an average of a
finite number of dark ramps: each of its group frames carries its own noise, a fixed
offset ``f_p(g)`` (DN) of pixel ``p`` in group read ``g``. Subtracted from every
integration alike, it does not average down over integrations; it enters the level-2
image as the pipeline's slope estimator applied to the offsets of the first NGROUPS
reads::

    rate_p += est_N(f_p(0), ..., f_p(N - 1))          (DN/s)

For pixels limited by read noise (the faint halo, most of an AMI image) the estimator is
the ordinary least-squares slope, ``est_N(f) = sum_g (g - (N-1)/2) f(g) / (t_g N (N^2 -
1) / 12)``: a pattern fixed on the detector whose amplitude *and shape* change with
NGROUPS (two exposures with 9 and 12 groups see patterns correlated by ``sqrt(60/143) =
0.65``, the 12-group one ``60/143 = 0.42`` times the 9-group one projected on it).

On real level-2 calibrators the halo residual of one star reappears in other stars,
filters and visits with the NGROUPS scaling above, and cancels in the difference of two
exposures with the same configuration. docs/detector.md ("The dark residual: what the
pipeline's dark subtraction leaves") gives the measurements, and what learned offsets do
to held-out calibrators.

So a model behind the pipeline holds ``f`` (``BaseModel.read.group_offsets_dn``, (G, ny,
nx)) and applies it only to images processed with the same ``R_DARK``. The offsets are
linear parameters of the image: given the model's ramps at the calibrators' fitted
states, :class:`OffsetSystem` accumulates each pixel's normal equations and solves them
under a white Gaussian prior of width ``prior_dn`` per group read (the offsets' own
scale, which the prior also uses to share what one NGROUPS measures with another).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from amigo import programs
from amigo.model.detector.pipeline_slope import pipeline_group_slope

#: Prior width of each group read's offset (DN): of 0.8 / 1.6 / 3.2 / 6.4, the width whose
#: offsets, solved from some real calibrator visits, best predict a held-out visit's halo
#: (docs/detector.md gives the comparison).
DEFAULT_PRIOR_DN = 1.6


def offset_jacobian(
    differences_dn: Float[Array, "m ny nx"],
    n_offsets: int,
    group_time: float,
    gain: float,
    nframes: int = 1,
    groups_used: Int[ArrayLike, "ny nx"] | None = None,
) -> Float[Array, "G ny nx"]:
    """``d est / d f(g)`` for ``g < n_offsets``: how the pipeline's slope of each pixel
    (DN per group, :func:`pipeline_group_slope`) moves with an offset of its group read
    ``g`` (DN), at the ramp whose group differences are ``differences_dn``.

    The weights the pipeline picks from each pixel's S/N are those of this ramp; reads
    past the ramp's end, or past the groups the pipeline fitted (``groups_used``, per
    pixel; ``None``: all), have no effect (zero rows).
    """
    ngroups = differences_dn.shape[0] + 1
    # The group differences of a unit offset of each read, one row per read. An argument
    # of the compiled program, not a constant in it: XLA would spend seconds folding the
    # estimator's cumulative products over a constant.
    unit = np.diff(np.eye(ngroups)[: min(n_offsets, ngroups)], axis=1)
    used = None if groups_used is None else jnp.asarray(groups_used, jnp.int32)
    columns = _responses(jnp.asarray(differences_dn), jnp.asarray(unit, differences_dn.dtype),
                         group_time, gain, nframes, used)  # fmt: skip
    return jnp.pad(columns, ((0, max(n_offsets - ngroups, 0)), (0, 0), (0, 0)))


@programs.jit
def _responses(
    differences, unit_differences, group_time: float, gain: float, nframes: int, groups_used
):
    """The estimator's response (G, ny, nx) to each row of ``unit_differences`` (G, m)."""

    def slope(d):
        return pipeline_group_slope(d, group_time, gain, nframes, groups_used)

    def response(row):
        tangent = jnp.broadcast_to(row[:, None, None], differences.shape)
        return jax.jvp(slope, (differences,), (tangent,))[1]

    return jax.vmap(response)(unit_differences)


@dataclass
class OffsetSystem:
    """Per-pixel normal equations of the group offsets, accumulated over exposures.

    Attributes
    ----------
    precision
        (ny, nx, G, G) ``sum_e w J J^T``.
    projection
        (ny, nx, G) ``sum_e w J r``.
    ngroups
        NGROUPS of the exposures added, in order.
    """

    precision: np.ndarray
    projection: np.ndarray
    ngroups: list[int]

    @classmethod
    def empty(cls, n_offsets: int, shape: tuple[int, int]) -> OffsetSystem:
        ny, nx = shape
        return cls(np.zeros((ny, nx, n_offsets, n_offsets)), np.zeros((ny, nx, n_offsets)), [])

    @property
    def n_offsets(self) -> int:
        return self.projection.shape[-1]

    def add(
        self,
        jacobian: Float[Array, "G ny nx"],
        residual: np.ndarray,
        weight: np.ndarray,
        ngroups: int,
    ) -> None:
        """One exposure: ``jacobian`` from :func:`offset_jacobian`, its ``residual``
        (ny, nx) data less model and ``weight`` (ny, nx) inverse variance (0 where a
        pixel is not used), both in the jacobian's unit (DN per group)."""
        j = np.moveaxis(np.asarray(jacobian, np.float64), 0, -1)  # (ny, nx, G)
        w = np.asarray(weight, np.float64)[..., None]
        self.precision += (w * j)[..., :, None] * j[..., None, :]
        self.projection += (w * j) * np.asarray(residual, np.float64)[..., None]
        self.ngroups.append(int(ngroups))

    def solve(self, prior_dn: float, current: np.ndarray | None = None) -> np.ndarray:
        """(G, ny, nx) maximum a-posteriori offsets (DN) under a white Gaussian prior of
        width ``prior_dn``, the residuals having been taken with ``current`` offsets in
        the model (``None``: none): ``(P + I / s^2) (f - f0) = b - f0 / s^2``."""
        g = self.n_offsets
        f0 = np.zeros_like(self.projection) if current is None else np.moveaxis(current, 0, -1)
        matrix = self.precision + np.eye(g) / prior_dn**2
        step = np.linalg.solve(matrix, (self.projection - f0 / prior_dn**2)[..., None])[..., 0]
        return np.moveaxis(f0 + step, -1, 0)

    def posterior_cholesky(self, prior_dn: float) -> np.ndarray:
        """(G, G, ny, nx) lower-triangular ``L`` with ``L L^T`` the posterior covariance
        (DN^2) of each pixel's offsets, ``(P + I / s^2)^-1``: what the solve left
        unknown (see :func:`offset_variance`)."""
        g = self.n_offsets
        covariance = np.linalg.inv(self.precision + np.eye(g) / prior_dn**2)
        covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
        return np.moveaxis(np.linalg.cholesky(covariance), (-2, -1), (0, 1))


def offset_variance(
    jacobian: Float[ArrayLike, "N ny nx"],
    prior_dn: float,
    posterior_cholesky: Float[ArrayLike, "G G ny nx"] | None = None,
) -> np.ndarray:
    """(ny, nx) variance of the pipeline's slope (DN per group, squared) from the offsets
    the model does not know: ``J^T C J`` for the read offsets of an image with ``N``
    group reads, ``jacobian`` their effect on the slope (:func:`offset_jacobian` with
    ``n_offsets = N``).

    ``C`` is the posterior covariance ``L L^T`` (``posterior_cholesky``) on the first
    ``G`` reads and the prior ``prior_dn^2 I`` on any later ones; without a posterior
    (the image is behind another dark reference file than the one the offsets were
    measured behind, or none were) every read has the prior: ``prior_dn^2 sum_g J_g^2``.
    The variance is additive to the image's ERR^2 (the pipeline's ERR leaves the
    reference's noise out), diagonal (the offsets are independent between pixels) and
    the same in every exposure of one dark reference and NGROUPS.
    """
    j = np.asarray(jacobian, np.float64)
    if posterior_cholesky is None:
        return prior_dn**2 * np.sum(j * j, axis=0)
    chol = np.asarray(posterior_cholesky, np.float64)
    known = min(chol.shape[0], j.shape[0])
    # (L^T J)_k = sum_g L_gk J_g over the reads the posterior covers.
    projected = np.einsum("gkyx,gyx->kyx", chol[:known, :known], j[:known])
    return np.sum(projected**2, axis=0) + prior_dn**2 * np.sum(j[known:] ** 2, axis=0)


def level2_offset_response(
    rate_dn_s: Float[ArrayLike, "ny nx"],
    ngroups: int,
    group_time: float,
    gain: float,
    nframes: int = 1,
    groups_used: Int[ArrayLike, "ny nx"] | None = None,
) -> np.ndarray:
    """(ngroups, ny, nx) response of the pipeline's slope (DN per group) to an offset of
    each read (DN) for a level-2 image of ``rate_dn_s`` (:func:`offset_jacobian` on the
    ramp of the image's own rate, negative rates counting as none, over the groups the
    pipeline fitted: ``groups_used``, ``None`` for all)."""
    per_group = np.clip(np.nan_to_num(np.asarray(rate_dn_s, np.float64)), 0.0, None) * group_time
    differences = np.broadcast_to(per_group, (ngroups - 1, *per_group.shape))
    jacobian = offset_jacobian(
        jnp.asarray(differences), ngroups, group_time, gain, nframes, groups_used
    )
    return np.asarray(jacobian, np.float64)


#: Pixels fainter than this fraction of an image's peak measure its dark pattern
#: (:func:`pattern_amplitude`): the halo, where read noise, not the PSF model, rules.
HALO_FRACTION = 0.01


def pattern_amplitude(
    residual: np.ndarray, pattern: np.ndarray, variance: np.ndarray, use: np.ndarray
) -> tuple[float, float]:
    """``(a, sigma_a)``: the weighted least-squares amplitude of ``pattern`` in
    ``residual`` (both (ny, nx), one unit) over the pixels ``use``, with inverse-variance
    weights, and its standard error. An image behind the dark reference whose offsets
    the model holds shows them at ``a = 1``; one that never had them (a simulation
    whose header names the file) at ``a = 0``, with ``sigma_a`` of a few 0.01 on a SUB80
    halo."""
    w = np.where(use, 1.0 / np.where(variance > 0, variance, np.inf), 0.0)
    norm = float(np.sum(w * pattern**2))
    if norm <= 0:
        return float("nan"), float("inf")
    return float(np.sum(w * residual * pattern)) / norm, norm**-0.5
