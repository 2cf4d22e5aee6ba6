"""Joint least-squares fit of a primary and several companions to a dataset.

Parameters: each companion's sky offset (dRA, dDec in mas, shared by all filters) and its
log10 flux ratio in every filter. The fit minimises the sum of squared whitened residuals
(errors multiplied by the fixed group error scales) with Levenberg-Marquardt; the Laplace
covariance is the inverse Gauss-Newton Hessian ``(J^T J)^-1`` at the optimum.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from amigo import programs, runtime
from amigo.companions.models import scene_visibility
from amigo.companions.observables import Dataset, Observables, program_view

#: Lowest log10 flux ratio allowed in the fits (a companion 25 magnitudes fainter).
LOG10_CONTRAST_FLOOR = -10.0
#: log10 flux ratio below which a candidate's fit (one with a chi2 tolerance) has ended:
#: 15 magnitudes, nothing the chi2 still sees (:func:`fit_companions_many`).
CANDIDATE_LOG10_CONTRAST_END = -6.0
#: A fit has converged when a step lowers chi2 by less than this fraction of it.
CHI2_RTOL = 1e-10


# Compiled as one program per dataset layout and companion count: evaluated op by op,
# every primitive of every block is compiled on its own (minutes on a small CPU).
@eqx.filter_jit
def block_residuals(
    dataset: Dataset,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    primary_diameter_mas: float = 0.0,
) -> tuple[jax.Array, ...]:
    """Unscaled whitened residuals of each block for companions ``offsets_mas`` (K, 2) with
    flux ratios ``contrasts`` (K, n_filters)."""
    return tuple(
        block_residual(
            block, offsets_mas, contrasts[:, dataset.filter_index(i)], primary_diameter_mas
        )
        for i, block in enumerate(dataset.blocks)
    )


def own_residuals(
    dataset: Dataset,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    primary_diameter_mas: float = 0.0,
) -> tuple[np.ndarray, ...]:
    """:func:`block_residuals` (NumPy) evaluated on the dataset's
    :func:`~amigo.companions.observables.program_view`, whose compiled program another
    target's files of the same buckets share, and taken back to each block's own rows."""
    view = program_view(dataset)
    padded = block_residuals(view.dataset, offsets_mas, contrasts, primary_diameter_mas)
    return tuple(np.asarray(r)[rows] for r, rows in zip(padded, view.rows, strict=True))


def block_residual(
    block: Observables,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    primary_diameter_mas: float = 0.0,
) -> jax.Array:
    """Unscaled whitened residuals (n_obs,) of one block for companions ``offsets_mas``
    (K, 2) with flux ratios ``contrasts`` (K,) in the block's filter."""
    vis = scene_visibility(
        block.uv_m,
        block.wavelengths_m,
        block.weights,
        offsets_mas,
        contrasts,
        primary_diameter_mas,
    )
    return block.residuals(vis)


def group_chi2(
    dataset: Dataset, residuals: tuple[jax.Array | np.ndarray, ...]
) -> tuple[np.ndarray, ...]:
    """(chi2, number of observables) per group, from unscaled residuals."""
    chi2 = np.zeros(dataset.n_groups)
    count = np.zeros(dataset.n_groups, dtype=int)
    for i, r in enumerate(residuals):
        g = dataset.group_index(i)
        np.add.at(chi2, g, np.asarray(r) ** 2)
        np.add.at(count, g, 1)
    return chi2, count


def estimate_scales(
    dataset: Dataset,
    offsets_mas: npt.ArrayLike,
    contrasts: npt.ArrayLike,
    primary_diameter_mas: float = 0.0,
) -> np.ndarray:
    """Maximum-likelihood error scales ``sqrt(chi2_g / n_g)`` per group for a given scene."""
    residuals = own_residuals(
        dataset, jnp.asarray(offsets_mas), jnp.asarray(contrasts), primary_diameter_mas
    )
    chi2, count = group_chi2(dataset, residuals)
    return np.sqrt(chi2 / np.maximum(count, 1))


@dataclass(frozen=True)
class CompanionFitResult:
    """Best fit of ``K`` companions in ``F`` filters.

    Attributes
    ----------
    offsets_mas
        (K, 2) sky offsets (dRA, dDec).
    log10_contrasts
        (K, F) log10 flux ratios.
    covariance
        (2K + KF, 2K + KF) Laplace covariance of ``[offsets.ravel(), log10c.ravel()]``.
    chi2
        Total chi2 with the scaled errors.
    group_scales
        (n_groups,) the error scales used.
    converged
        Whether the optimiser met its tolerance.
    """

    offsets_mas: np.ndarray
    log10_contrasts: np.ndarray
    covariance: np.ndarray
    chi2: float
    group_scales: np.ndarray
    converged: bool

    @property
    def contrasts(self) -> np.ndarray:
        return 10.0**self.log10_contrasts

    @property
    def n_companions(self) -> int:
        return int(self.offsets_mas.shape[0])

    def offset_errors_mas(self) -> np.ndarray:
        """(K, 2) 1-sigma errors of dRA, dDec."""
        k = self.n_companions
        return np.sqrt(np.diag(self.covariance)[: 2 * k]).reshape(k, 2)

    def log10_contrast_errors(self) -> np.ndarray:
        """(K, F) 1-sigma errors of log10 flux ratios."""
        k = self.n_companions
        return np.sqrt(np.diag(self.covariance)[2 * k :]).reshape(k, -1)


def _block_columns(k: int, n_filters: int, f: int) -> np.ndarray:
    """Indices, in the flat parameters ``[offsets.ravel(), log10c.ravel()]`` of ``k``
    companions, of those a block of filter ``f`` depends on: every offset and the
    companions' contrasts in ``f``."""
    return np.concatenate([np.arange(2 * k), 2 * k + np.arange(k) * n_filters + f])


@programs.jit
def _residual_and_jacobian(flat, args):
    """Residual vector and its Jacobian of flattened parameters ``[offsets.ravel(),
    log10c.ravel()]`` (forward mode: few parameters, many residuals).

    ``args = (dataset, scale_vectors, k, diameter)``, ``k`` and ``diameter`` static; a
    module-level function (not a closure) so that the compiled program is reused by every
    fit of the same dataset layout. Each block is differentiated only along the
    parameters it depends on (the offsets and its own filter's contrasts): the other
    filters' contrast columns are zeros that would cost as many products with the
    observable matrix as any other column (2K + K of 2K + KF tangents per block instead
    of all; a third fewer for one companion in three filters).
    """
    dataset, scale_vectors, k, diameter = args
    residuals, jacobians = [], []
    for i, block in enumerate(dataset.blocks):
        columns = _block_columns(k, dataset.n_filters, dataset.filter_index(i))

        def residual(sub, block=block, scale=scale_vectors[i]):
            # A companion brighter than the primary is the same binary seen from the other
            # star: flux ratios are kept in [1e-10, 1] so that each has one representation.
            log10c = jnp.clip(sub[2 * k :], LOG10_CONTRAST_FLOOR, 0.0)
            offsets = sub[: 2 * k].reshape(k, 2)
            return block_residual(block, offsets, 10.0**log10c, diameter) / scale

        jacobian, r = jax.jacfwd(lambda y, f=residual: (f(y),) * 2, has_aux=True)(flat[columns])
        residuals.append(r)
        jacobians.append(jnp.zeros((r.size, flat.size), r.dtype).at[:, columns].set(jacobian))
    return jnp.concatenate(residuals), jnp.concatenate(jacobians, axis=0)


@programs.jit
def _residuals_and_jacobians(flats, args):
    """:func:`_residual_and_jacobian` of several points at once (B, n): residuals (B, m)
    and Jacobians (B, m, n). One pass over the observable matrices serves every point (a
    batch of 20 cost 2.3 ms a point against 7.7 ms alone on AB Dor's three filters)."""
    return jax.vmap(lambda flat: _residual_and_jacobian(flat, args))(flats)


#: Accepted steps over which a fit with a chi2 tolerance that gains no more than the
#: tolerance per step has stalled (:class:`_Marquardt`).
STALL_STEPS = 10


class _Marquardt:
    """One problem's Levenberg-Marquardt iteration (Marquardt's diagonal scaling), stepped
    from outside so that several problems can share each evaluation.

    Each iteration: :meth:`proposal` gives the next point to evaluate (or ``None``: the
    problem has finished, or its damped system was singular and the damping grew), then
    :meth:`accept` takes the residuals and Jacobian there.
    """

    def __init__(
        self,
        x: np.ndarray,
        r: np.ndarray,
        j: np.ndarray,
        rtol: float,
        decrement_tol: float,
        floors: np.ndarray | None = None,
    ):
        self.x, self.r, self.j = x, r, j
        # Per parameter, a value below which it no longer changes the chi2 (a flux ratio
        # run to nothing): a fit with a tolerance that crosses one has finished.
        self.floors = floors
        self.chi2 = float(r @ r)
        self.damping = 1e-3
        self.rtol, self.decrement_tol = rtol, decrement_tol
        self.finished = self.converged = False
        self._step = np.zeros_like(x)
        self._accepted = [self.chi2]  # chi2 after each accepted step

    def _finish(self) -> None:
        self.finished = self.converged = True

    def proposal(self) -> np.ndarray | None:
        fisher = self.j.T @ self.j
        gradient = self.j.T @ self.r
        if self.decrement_tol > 0.0:
            newton = np.linalg.lstsq(fisher, gradient, rcond=None)[0]
            if float(gradient @ newton) <= self.decrement_tol:
                self._finish()
                return None
        scale = np.maximum(np.diag(fisher), 1e-30)
        try:
            self._step = np.linalg.solve(fisher + self.damping * np.diag(scale), -gradient)
        except np.linalg.LinAlgError:
            self.damping *= 10.0
            return None
        return self.x + self._step

    def accept(self, r_new: np.ndarray, j_new: np.ndarray) -> None:
        chi2_new = float(r_new @ r_new)
        if np.isfinite(chi2_new) and chi2_new <= self.chi2:
            self.x, self.r, self.j = self.x + self._step, r_new, j_new
            gain, self.chi2 = self.chi2 - chi2_new, chi2_new
            self.damping = max(self.damping / 3.0, 1e-12)
            self._accepted.append(chi2_new)
            if gain <= self.rtol * max(self.chi2, 1.0):
                self._finish()
            elif self.floors is not None and np.any(self.x < self.floors):
                self._finish()
            elif (
                self.decrement_tol > 0.0
                and len(self._accepted) > STALL_STEPS
                and self._accepted[-STALL_STEPS - 1] - chi2_new <= STALL_STEPS * self.decrement_tol
            ):
                # Crawling: in a curved valley Gauss-Newton's decrement overstates what the
                # steps gain, and each gains a nearly constant fraction of what is left
                # (0.93 on AB Dor's search: what is left is then ~13 steps' gains). When
                # the last steps gained no more than the tolerance each, the rest is a
                # tenth of a chi2 or so: nothing for ranking candidates.
                self._finish()
        else:
            self.damping *= 4.0
            if self.damping > 1e10:
                self._finish()  # no downhill step left: a (local) minimum


Evaluate = Callable[[list[np.ndarray]], list[tuple[np.ndarray, np.ndarray]]]


def _marquardt_all(
    evaluate: Evaluate,
    starts: list[np.ndarray],
    max_steps: int,
    rtol: float,
    decrement_tol: float,
    floors: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Run :class:`_Marquardt` from each start in lockstep, every iteration evaluating the
    points of all problems still running in one call of ``evaluate`` (points -> their
    ``(r, J)``, in order). Each problem takes exactly the steps it would take alone."""
    states = [
        _Marquardt(np.asarray(x, dtype=float), r, j, rtol, decrement_tol, floors)
        for x, (r, j) in zip(starts, evaluate([np.asarray(x, float) for x in starts]), strict=True)
    ]
    for _ in range(max_steps):
        running = [s for s in states if not s.finished]
        if not running:
            break
        proposed = [(s, s.proposal()) for s in running]
        todo = [(s, point) for s, point in proposed if point is not None]
        if todo:
            values = evaluate([point for _, point in todo])
            for (s, _), (r, j) in zip(todo, values, strict=True):
                s.accept(r, j)
    return [(s.x, s.r, s.j, s.converged) for s in states]


def levenberg_marquardt(
    function: Callable[[np.ndarray], tuple[Any, Any]],
    x0: np.ndarray,
    max_steps: int = 200,
    rtol: float = CHI2_RTOL,
    decrement_tol: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Minimise ``|r(x)|^2`` by Levenberg-Marquardt with Marquardt's diagonal scaling.

    ``function(x) -> (r, J)``. A small host-side loop around one jitted residual+Jacobian
    call: the problems have at most a few tens of parameters, and compiling this is much
    cheaper than compiling a general solver. Returns ``(x, r, J, converged)``; converged
    means the relative chi2 decrease fell below ``rtol``, or, before any further
    evaluation, the Gauss-Newton decrement ``g^T (J^T J)^+ g`` (``g = J^T r``: the chi2
    the linearised model could still gain) fell to ``decrement_tol`` or below.

    The decrement matters for fits that end slowly: a candidate at a noise peak whose
    flux ratio runs towards zero in log10 flattens chi2 without a minimum, and Gauss-
    Newton then gains a nearly constant fraction per step (0.93 on AB Dor's search:
    100-odd evaluations to reach ``rtol``) while the chi2 left to gain is already
    negligible.
    """

    def evaluate(points: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        out = []
        for x in points:
            r, j = function(x)
            out.append((np.asarray(r), np.asarray(j)))
        return out

    return _marquardt_all(evaluate, [np.asarray(x0)], max_steps, rtol, decrement_tol)[0]


def fit_companions(
    dataset: Dataset,
    offsets_mas: np.ndarray,
    log10_contrasts: np.ndarray,
    group_scales: np.ndarray | None = None,
    primary_diameter_mas: float = 0.0,
    max_steps: int = 200,
    chi2_tolerance: float = 0.0,
) -> CompanionFitResult:
    """Levenberg-Marquardt fit of all companions jointly, from the given starting point.

    Parameters
    ----------
    offsets_mas, log10_contrasts
        (K, 2) and (K, F) starting values.
    group_scales
        (n_groups,) fixed error scales (``None``: ones).
    chi2_tolerance
        Stop once the linearised model could gain no more than this in chi2
        (:func:`levenberg_marquardt`'s ``decrement_tol``); 0 (default): converge to the
        relative chi2 change of :data:`CHI2_RTOL` (1e-10).
    """
    return fit_companions_many(
        dataset,
        [(offsets_mas, log10_contrasts)],
        group_scales,
        primary_diameter_mas,
        max_steps,
        chi2_tolerance,
    )[0]


def fit_companions_many(
    dataset: Dataset,
    starts: list[tuple[np.ndarray, np.ndarray]],
    group_scales: np.ndarray | None = None,
    primary_diameter_mas: float = 0.0,
    max_steps: int = 200,
    chi2_tolerance: float = 0.0,
) -> list[CompanionFitResult]:
    """:func:`fit_companions` from each of several starts ``(offsets_mas (K, 2),
    log10_contrasts (K, F))``, all with the same ``K``: independent fits whose
    evaluations are batched (:func:`_residuals_and_jacobians`). A fit takes the same steps
    as alone; its numbers may differ in their last bits (the batched products sum in
    another order). One start is evaluated unbatched, by the program of a single fit.
    """
    if not starts:
        return []
    scales = np.ones(dataset.n_groups) if group_scales is None else np.asarray(group_scales)
    # The observables padded to bucket sizes (program_view): the programs of another
    # target's files are then usually the ones on disk. Padded rows have residual 0 and
    # Jacobian rows 0, so chi2, J^T J and J^T r are the dataset's own.
    view = program_view(dataset)
    scale_vectors = view.scale_vectors(scales)
    firsts = []
    for offsets_mas, log10_contrasts in starts:
        offsets0 = np.asarray(offsets_mas, dtype=float).reshape(-1, 2)
        log10c0 = np.clip(
            np.asarray(log10_contrasts, dtype=float).reshape(offsets0.shape[0], -1),
            LOG10_CONTRAST_FLOOR + 1,
            -1e-3,
        )
        firsts.append((offsets0, log10c0))
    counts = {offsets0.shape[0] for offsets0, _ in firsts}
    if len(counts) > 1:
        raise ValueError(f"every start must have the same number of companions, got {counts}")
    k = counts.pop()
    args = (view.dataset, scale_vectors, k, float(primary_diameter_mas))

    def single(point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, j = _residual_and_jacobian(jnp.asarray(point), args)
        return np.asarray(r), np.asarray(j)

    def evaluate(points: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        if len(points) <= _singles_up_to():
            # A few points: each by the single fit's program, side by side (one per core).
            return programs.side_by_side(single, points, workers=runtime.cores())
        # Padded to a few sizes (repeating the last point), so that a handful of compiled
        # programs serve every count of running fits.
        size = _batch_size(len(points))
        padded = np.stack(points + [points[-1]] * (size - len(points)))
        r, j = (np.asarray(a) for a in _residuals_and_jacobians(jnp.asarray(padded), args))
        return [(r[i], j[i]) for i in range(len(points))]

    y0s = [np.concatenate([o.ravel(), c.ravel()]) for o, c in firsts]
    # With a tolerance (candidates), a flux ratio below 1e-6 (15 mag) ends the fit: it
    # would crawl towards zero in log10, the chi2 no longer changing (docs/detect.md).
    floors = None
    if chi2_tolerance > 0.0:
        n_contrasts = y0s[0].size - 2 * k
        floors = np.concatenate(
            [np.full(2 * k, -np.inf), np.full(n_contrasts, CANDIDATE_LOG10_CONTRAST_END)]
        )
    fits = _marquardt_all(evaluate, y0s, max_steps, CHI2_RTOL, chi2_tolerance, floors)
    out = []
    for best, residual, jacobian, converged in fits:
        covariance = np.linalg.pinv(jacobian.T @ jacobian, rcond=1e-12, hermitian=True)
        out.append(
            CompanionFitResult(
                offsets_mas=best[: 2 * k].reshape(k, 2),
                log10_contrasts=np.clip(best[2 * k :].reshape(k, -1), LOG10_CONTRAST_FLOOR, 0.0),
                covariance=covariance,
                chi2=float(residual @ residual),
                group_scales=scales,
                converged=converged,
            )
        )
    return out


def _singles_up_to() -> int:
    """Up to how many points :func:`fit_companions_many` evaluates one by one, side by
    side on the CPU's cores, rather than as a padded batch.

    On a 2-core CPU (AB Dor's three filters, one companion) a single point took 9.3 ms
    and a batch of 8, 39 ms: up to three rounds of singles on every core cost less than
    one batch. Most evaluations of a search come when few fits are still running (2 of
    them in 53 of 240 evaluations, at most 6 in 114). On an accelerator the batch: its
    cost hardly grows with its size. Which points go which way depends only on their
    count: a run takes the same path every time.
    """
    if jax.default_backend() != "cpu":
        return 1
    return 3 * runtime.cores()


def _batch_size(n: int) -> int:
    """The compiled batch that holds ``n`` points: 8, then multiples of 8."""
    return -(-n // 8) * 8


def scaled_chi2(
    dataset: Dataset,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    group_scales: np.ndarray,
    primary_diameter_mas: float = 0.0,
) -> float:
    """chi2 of a scene (companions at ``offsets_mas`` (n, 2) with linear ``contrasts``
    (n, F)) with every group's errors multiplied by its scale (summed in NumPy)."""
    parts = own_residuals(dataset, offsets_mas, contrasts, primary_diameter_mas)
    scales = dataset.scale_vectors(group_scales)
    return float(
        sum(
            np.sum((np.asarray(r) / np.asarray(s)) ** 2) for r, s in zip(parts, scales, strict=True)
        )
    )


def background_chi2(
    dataset: Dataset, group_scales: np.ndarray, primary_diameter_mas: float = 0.0
) -> float:
    """chi2 of the primary alone (no companion), with scaled errors."""
    empty = jnp.zeros((0, 2))
    no_contrast = jnp.zeros((0, dataset.n_filters))
    return scaled_chi2(dataset, empty, no_contrast, group_scales, primary_diameter_mas)
