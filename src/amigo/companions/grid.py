"""Vectorised grid search: the best contrast of one more companion at every sky position.

For every position ``theta`` of a square grid (dRA, dDec in mas) and every filter, the flux
ratio ``c`` of a companion added to a fixed *background* scene (the primary and the
companions already found) is solved by a few Gauss-Newton steps on the exact model::

    V(c) = (N + c e(theta)) / (D + c),   N, D: background numerator and total flux

starting from ``c = 0`` (the first step is the linear least-squares contrast). ``c`` may be
negative: the signed estimate and its error are what the contrast limits need; a
detection only counts positive contrasts. Returned per filter: the contrast, its 1-sigma
error (from the Gauss-Newton curvature) and ``dchi2 = chi2(background) - chi2(c)``.

Speed: the band-averaged phasors factorise over the grid axes,
``e(x, y) = sum_l w_l exp(-2 pi i b_x x / l) exp(-2 pi i b_y y / l)``, so no complex
exponential is evaluated per grid point; positions are processed in column chunks by
one jitted, vmapped program. For linear observables (calvis files) that program only
makes each position's inner products per group of observables
(:func:`grid_statistics`), which do not depend on the groups' error scales: the search
makes them once per background scene and solves the grid again for each set of scales
in NumPy.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from amigo import programs, runtime
from amigo.companions.models import MAS_TO_RAD, scene_terms
from amigo.companions.observables import (
    Dataset,
    Observables,
    padded_scale_vector,
    program_view,
    single_precision,
)
from amigo.companions.significance import log_chi2_sf, sigma_from_log_p

#: Bounds of the contrast solved at each grid point (flux ratios).
CONTRAST_BOUNDS: tuple[float, float] = (-0.5, 0.95)


@dataclass(frozen=True)
class Grid:
    """A square grid of sky offsets, ``x`` = dRA (east positive), ``y`` = dDec (mas)."""

    x_mas: np.ndarray
    y_mas: np.ndarray
    rmax_mas: float
    step_mas: float

    @classmethod
    def square(cls, rmax_mas: float, step_mas: float) -> Grid:
        n = int(np.floor(rmax_mas / step_mas + 1e-9))
        axis = np.arange(-n, n + 1) * float(step_mas)
        return cls(
            x_mas=axis, y_mas=axis.copy(), rmax_mas=float(rmax_mas), step_mas=float(step_mas)
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(n_y, n_x): maps are indexed ``[dDec, dRA]``."""
        return self.y_mas.size, self.x_mas.size

    @property
    def radius_mas(self) -> np.ndarray:
        return np.hypot(self.x_mas[None, :], self.y_mas[:, None])

    def valid(self, iwa_mas: float) -> np.ndarray:
        """(n_y, n_x) True outside ``iwa_mas`` and inside ``rmax_mas``."""
        r = self.radius_mas
        return (r >= iwa_mas) & (r <= self.rmax_mas)


#: Grid positions per finest fringe spacing (:func:`default_step_mas`).
STEPS_PER_FRINGE = 5.0


def default_step_mas(dataset: Dataset) -> float:
    """A fifth of the finest fringe spacing: ``lambda_min / (5 B_max)``, in mas.

    Peaks are refined by fits, so a third would find them; a fifth is for the contrast
    curves, whose annuli are one step wide: near the inner working angle the limit
    climbs by a magnitude in ~100 mas. On NIRISS 29-36 mas (three filters, F480M)."""
    fringe = min(b.min_wavelength_m / b.max_baseline_m for b in dataset.blocks)
    return fringe / MAS_TO_RAD / STEPS_PER_FRINGE


def inner_working_angle_mas(blocks: tuple[Observables, ...] | list[Observables]) -> float:
    """``lambda / (2 B_max)`` (mas) at the blocks' mean wavelength and longest baseline."""
    wavelength = float(np.mean([b.mean_wavelength_m for b in blocks]))
    baseline = max(b.max_baseline_m for b in blocks)
    return wavelength / (2.0 * baseline) / MAS_TO_RAD


@dataclass(frozen=True)
class ContrastMap:
    """Per-filter result of the grid search, maps of shape (n_y, n_x).

    ``contrast`` (signed flux ratio), ``sigma`` (its 1-sigma error), ``dchi2`` (chi2
    improvement over the background scene), ``chi2_background`` and ``n_obs`` (scalars
    for the Absil limits), ``iwa_mas`` (the masked inner radius of this filter).
    """

    filter_name: str
    contrast: np.ndarray
    sigma: np.ndarray
    dchi2: np.ndarray
    chi2_background: float
    n_obs: int
    iwa_mas: float

    @property
    def significance(self) -> np.ndarray:
        """Signed significance ``sign(c) sqrt(dchi2)`` (one parameter at a fixed position)."""
        return np.sign(self.contrast) * np.sqrt(np.clip(self.dchi2, 0.0, None))


@dataclass(frozen=True)
class GridResult:
    """Grid search over all filters: per-filter maps and the joint detection map."""

    grid: Grid
    maps: tuple[ContrastMap, ...]
    iwa_mas: float

    @property
    def valid(self) -> np.ndarray:
        return self.grid.valid(self.iwa_mas)

    @property
    def joint_dchi2(self) -> np.ndarray:
        """Sum over filters of the chi2 gain of positive contrasts (0 where masked)."""
        total = sum(np.where(m.contrast > 0, np.clip(m.dchi2, 0, None), 0.0) for m in self.maps)
        return np.where(self.valid, total, 0.0)

    @property
    def joint_significance(self) -> np.ndarray:
        """Gaussian-equivalent significance of the joint map (dof = number of filters)."""
        return sigma_from_chi2(self.joint_dchi2, len(self.maps))

    def peaks(self, n: int = 5) -> list[tuple[float, float, float]]:
        """The ``n`` highest local maxima of the joint map: (dRA, dDec, dchi2), best first."""
        values = self.joint_dchi2
        local = (
            (values == ndimage.maximum_filter(values, size=3, mode="nearest"))
            & self.valid
            & (values > 0)
        )
        iy, ix = np.nonzero(local)
        order = np.argsort(values[iy, ix])[::-1][:n]
        return [
            (
                float(self.grid.x_mas[ix[k]]),
                float(self.grid.y_mas[iy[k]]),
                float(values[iy[k], ix[k]]),
            )
            for k in order
        ]


def sigma_from_chi2(dchi2: np.ndarray | float, dof: int) -> np.ndarray:
    """Gaussian-equivalent significance of a chi2 improvement with ``dof`` parameters.

    ``n`` such that the two-sided normal tail beyond ``n`` equals the chi2 tail beyond
    ``dchi2``: for one parameter this is exactly ``sqrt(dchi2)``. Computed in log space so
    that very strong detections (dchi2 ~ 1e4) stay finite.
    """
    dchi2 = np.clip(np.asarray(dchi2, dtype=float), 0.0, None)
    if dof == 1:
        return np.sqrt(dchi2)
    return sigma_from_log_p(log_chi2_sf(dchi2, dof))


# ---------------------------------------------------------------------------- solver
class _Background(eqx.Module):
    """Per-block background scene terms: numerator (n_uv,) and total flux (scalar)."""

    numerators: tuple[jax.Array, ...]
    denominators: tuple[jax.Array, ...]


def axis_phasors(block: Observables, axis_mas: np.ndarray, column: int) -> np.ndarray:
    """exp(-2 pi i b_axis * axis / lambda): (n_axis, n_uv, n_wl), in NumPy (the grid's
    axes change size from one search step to the next, and eager JAX would compile its
    operations again for every size)."""
    path = (
        np.asarray(axis_mas, float)[:, None, None]
        * MAS_TO_RAD
        * np.asarray(block.uv_m, float)[None, :, column, None]
    )
    return np.exp(-2j * np.pi * path / np.asarray(block.wavelengths_m, float)[None])


def _gauss_newton(residual_and_jacobian, r0, n_steps):
    """A few bounded Gauss-Newton steps on one scalar contrast, from c = 0."""
    lo, hi = CONTRAST_BOUNDS
    c = jnp.zeros((), dtype=r0.dtype)
    for _ in range(n_steps):
        r, j = residual_and_jacobian(c)
        curvature = jnp.dot(j, j)
        # At the origin the companion is the primary (no signal, zero curvature): stay at 0.
        safe = jnp.where(curvature > 0, curvature, 1.0)
        c = jnp.clip(c - jnp.where(curvature > 0, jnp.dot(j, r) / safe, 0.0), lo, hi)
    r, j = residual_and_jacobian(c)
    curvature = jnp.dot(j, j)
    safe = jnp.where(curvature > 0, curvature, 1.0)
    sigma = jnp.where(curvature > 0, 1.0 / jnp.sqrt(safe), jnp.inf)
    # chi2(0) - chi2(c) written as a product of small differences: no cancellation.
    dchi2 = jnp.sum((r0 - r) * (r0 + r))
    return c, sigma, dchi2


def _solve_position(blocks, background, scales, r0, phasors, n_steps):
    """Exact model: Gauss-Newton with forward-mode derivatives; returns (c, sigma, dchi2)."""

    def residual(c):
        parts = []
        for block, num, den, scale, e in zip(
            blocks,
            background.numerators,
            background.denominators,
            scales,
            phasors,
            strict=True,
        ):
            parts.append(block.residuals((num + c * e) / (den + c)) / scale)
        return jnp.concatenate(parts)

    return _gauss_newton(lambda c: jax.jvp(residual, (c,), (jnp.ones_like(c),)), r0, n_steps)


#: Terms of the series of log V(c) used by the fast path for linear (calvis) blocks.
SERIES_TERMS = 3


def _series_statistics(blocks, background, r0, phasors, onehot):
    """Linear observables (y = D log V): the series of log V in powers of c, reduced to
    the inner products its Gauss-Newton solution needs.

    ``log V(c) = log(N + c e) - log(D + c) = log V(0) + sum_k (-1)^(k+1)/k c^k
    [(e/N)^k - D^-k]``, converging for ``c |e/N| < 1``; with 3 terms the relative error of
    the model is about c^3 / 4: 2.5e-4 at c = 0.1, 7e-3 at c = 0.3 (the grid only starts
    the exact fits). With ``m_k = D t_k / error`` (the whitened image of the k-th term),
    the residual is ``r(c) = r0 + sum_k c^k m_k`` and everything the solver needs is, per
    group ``g`` of observables (the onehot columns): ``A_g = m_k . m_l`` (K, K) and
    ``b_g = m_k . r0`` (K,). These do not depend on the groups' error scales, which
    only weight them: a new set of scales costs no product with the observable matrices.
    """
    terms = []
    for block, num, den, e in zip(
        blocks, background.numerators, background.denominators, phasors, strict=True
    ):
        # Powers by repeated products: a power with a traced exponent is exp(k log z),
        # several times the cost of the whole series.
        ratio, inverse = e / num, 1.0 / den
        ratio_k, inverse_k, series_k = ratio, inverse, []
        for k in range(1, SERIES_TERMS + 1):
            series_k.append((-1.0) ** (k + 1) / k * (ratio_k - inverse_k))
            ratio_k, inverse_k = ratio_k * ratio, inverse_k * inverse
        series = jnp.stack(series_k)  # (K, n_uv)
        log_terms = jnp.concatenate([series.real, series.imag], axis=1)  # (K, 2 n_uv)
        terms.append(block.linear_part(log_terms) / block.errors)  # (K, n_obs)
    m = jnp.concatenate(terms, axis=1)
    gram = jnp.einsum("ko,lo,og->gkl", m, m, onehot)
    cross = jnp.einsum("ko,o,og->gk", m, r0, onehot)
    return gram, cross


def _solve_statistics(gram, cross, weights, n_steps):
    """Gauss-Newton on the series model from its inner products, vectorised over positions.

    ``gram`` (..., G, K, K), ``cross`` (..., G, K): :func:`_series_statistics` per
    position; ``weights`` (G,) ``1 / scale^2`` of each group. Returns (c, sigma, dchi2)
    (...,): the same steps as :func:`_gauss_newton`, with ``j . j``, ``j . r`` and the chi2
    gain written through the inner products (``r = r0 + sum_k c^k m_k``,
    ``j = sum_k k c^(k-1) m_k``).
    """
    a = np.einsum("...gkl,g->...kl", gram, weights)
    b = np.einsum("...gk,g->...k", cross, weights)
    powers = np.arange(1, SERIES_TERMS + 1)
    lo, hi = CONTRAST_BOUNDS

    def moments(c):
        p = c[..., None] ** powers  # (..., K) c^k
        dp = powers * c[..., None] ** (powers - 1)  # (..., K) k c^(k-1)
        curvature = np.einsum("...k,...kl,...l->...", dp, a, dp)
        slope = np.einsum("...k,...k->...", dp, b + np.einsum("...kl,...l->...k", a, p))
        return p, curvature, slope

    c = np.zeros(a.shape[:-2])
    for _ in range(n_steps):
        _, curvature, slope = moments(c)
        # At the origin the companion is the primary (no signal, zero curvature): stay at 0.
        safe = np.where(curvature > 0, curvature, 1.0)
        c = np.clip(c - np.where(curvature > 0, slope / safe, 0.0), lo, hi)
    p, curvature, _ = moments(c)
    sigma = np.where(curvature > 0, 1.0 / np.sqrt(np.where(curvature > 0, curvature, 1.0)), np.inf)
    # chi2(0) - chi2(c) = -(2 p . b + p A p): small terms only, no cancellation.
    dchi2 = -(2.0 * np.einsum("...k,...k->...", p, b) + np.einsum("...k,...kl,...l->...", p, a, p))
    return c, sigma, dchi2


@eqx.filter_jit
def _chunk_statistics(blocks, background, r0, onehot, x_phasors, y_phasors):
    # e[j, i, u] = sum_l w_l exp_x[i, u, l] exp_y[j, u, l]  (weights folded into x_phasors)
    phasors = tuple(
        jnp.einsum("iul,jul->jiu", ex, ey) for ex, ey in zip(x_phasors, y_phasors, strict=True)
    )
    n_y, n_i = phasors[0].shape[:2]
    flat = tuple(p.reshape(n_y * n_i, -1) for p in phasors)
    gram, cross = jax.vmap(lambda *e: _series_statistics(blocks, background, r0, e, onehot))(*flat)
    return gram.reshape(n_y, n_i, *gram.shape[1:]), cross.reshape(n_y, n_i, *cross.shape[1:])


@eqx.filter_jit
def _solve_chunk(blocks, background, scales, r0, x_phasors, y_phasors, n_steps):
    # e[j, i, u] = sum_l w_l exp_x[i, u, l] exp_y[j, u, l]  (weights folded into x_phasors)
    phasors = tuple(
        jnp.einsum("iul,jul->jiu", ex, ey) for ex, ey in zip(x_phasors, y_phasors, strict=True)
    )
    n_y, n_i = phasors[0].shape[:2]
    flat = tuple(p.reshape(n_y * n_i, -1) for p in phasors)
    solve = jax.vmap(lambda *e: _solve_position(blocks, background, scales, r0, e, n_steps))
    c, sigma, dchi2 = solve(*flat)
    return (c.reshape(n_y, n_i), sigma.reshape(n_y, n_i), dchi2.reshape(n_y, n_i))


@dataclass(frozen=True)
class _FilterScene:
    """One filter's blocks with a fixed background scene, ready for the grid."""

    blocks: tuple[Observables, ...]  # padded (observables.program_view)
    background: _Background
    residuals: tuple[jax.Array, ...]  # per block, whitened, unit error scales
    x_phasors: tuple[np.ndarray, ...]  # (n_x, n_uv, n_wl), band weights folded in
    y_phasors: tuple[jax.Array, ...]  # (n_y, n_uv, n_wl)
    groups: np.ndarray  # (n_obs padded,) group index of each observable, n_groups: padded
    n_obs: int  # the blocks' own observables
    iwa_mas: float  # the files' inner working angle


def filter_blocks(dataset: Dataset, f: int) -> list[int]:
    """Indices of the blocks of filter ``f``."""
    return [i for i in range(len(dataset.blocks)) if dataset.filter_index(i) == f]


def _filter_scene(
    dataset: Dataset, f: int, grid: Grid, offsets: np.ndarray, flux: np.ndarray, diameter: float
) -> _FilterScene:
    index = filter_blocks(dataset, f)
    # The padded blocks: another target's files of the same buckets share the programs.
    # Padded rows' residuals and series are 0 and their group is none of the dataset's.
    view = program_view(dataset)
    blocks = tuple(view.dataset.blocks[i] for i in index)
    terms = [
        _background_terms(b, jnp.asarray(offsets), jnp.asarray(flux[:, f]), diameter)
        for b in blocks
    ]
    return _FilterScene(
        blocks=blocks,
        background=_Background(tuple(t[0] for t in terms), tuple(t[1] for t in terms)),
        residuals=tuple(t[2] for t in terms),
        x_phasors=tuple(
            axis_phasors(b, grid.x_mas, 0) * np.asarray(b.weights)[None] for b in blocks
        ),
        y_phasors=tuple(jnp.asarray(axis_phasors(b, grid.y_mas, 1)) for b in blocks),
        groups=np.concatenate([np.asarray(view.groups[i]) for i in index]),
        n_obs=sum(dataset.blocks[i].n_obs for i in index),
        iwa_mas=inner_working_angle_mas([dataset.blocks[i] for i in index]),
    )


# One program: run op by op, the scene and the residuals of each block cost ~0.1 s (AB
# Dor's search builds nine of them, docs/performance.md, "Work side by side").
@programs.jit
def _background_terms(
    block: Observables, offsets_mas: jax.Array, contrasts: jax.Array, diameter: float
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A block's background scene: :func:`scene_terms`' numerator (n_uv,) and total flux,
    and the block's whitened residuals (n_obs,) with unit error scales."""
    numerator, denominator = scene_terms(
        block.uv_m, block.wavelengths_m, block.weights, offsets_mas, contrasts, diameter
    )
    return numerator, denominator, block.residuals(numerator / denominator)


def background_residuals(
    dataset: Dataset,
    index: Sequence[int],
    offsets_mas: np.ndarray,
    contrasts: np.ndarray,
    diameter: float,
) -> np.ndarray:
    """The whitened residuals (unit error scales) of blocks ``index`` under the
    background scene (companions at ``offsets_mas`` (K, 2) with flux ratios ``contrasts``
    (K,)), concatenated (sum of their n_obs,): the grid's own program on the padded view,
    its real rows."""
    view = program_view(dataset)
    return np.concatenate(
        [
            np.asarray(
                _background_terms(
                    view.dataset.blocks[i],
                    jnp.asarray(offsets_mas),
                    jnp.asarray(contrasts),
                    diameter,
                )[2]
            )[view.rows[i]]
            for i in index
        ]
    )


def _over_columns(function, scene: _FilterScene, grid: Grid, chunk_columns: int | None):
    """``function(x_phasors_chunk)`` over chunks of grid columns, outputs joined on axis 1.

    Chunks hold about 2e5 uv-point evaluations (``chunk_columns`` columns if given); the
    last is padded so that one compiled shape serves every chunk. The chunks are
    independent: evaluated side by side, one per core (:func:`amigo.programs.side_by_side`;
    their matrix products run on one thread each)."""
    n_uv = sum(b.n_uv for b in scene.blocks)
    n_x = grid.x_mas.size
    step = chunk_columns or max(1, min(n_x, int(2e5 // (n_uv * grid.y_mas.size)) or 1))

    def columns(start: int) -> list[np.ndarray]:
        stop = min(start + step, n_x)
        pad = step - (stop - start)
        chunk = tuple(
            jnp.asarray(np.pad(x[start:stop], ((0, pad), (0, 0), (0, 0)))) for x in scene.x_phasors
        )
        return [np.asarray(a)[:, : stop - start] for a in function(chunk)]

    starts = list(range(0, n_x, step))
    # The first alone: it compiles (or reads) the program that the others then share.
    outputs = [columns(starts[0])]
    outputs += programs.side_by_side(columns, starts[1:], workers=runtime.cores())
    return tuple(np.concatenate(parts, axis=1) for parts in zip(*outputs, strict=True))


@dataclass(frozen=True)
class FilterStatistics:
    """What the grid search of one filter's linear (calvis) observables needs, for one
    background scene and any error scales (:func:`_series_statistics`).

    ``gram`` (n_y, n_x, G, K, K) and ``cross`` (n_y, n_x, G, K) per position and group;
    ``background`` (G,) each group's chi2 of the background scene; ``groups`` (G,) the
    dataset's index of each group; all with unit error scales.
    """

    gram: np.ndarray
    cross: np.ndarray
    background: np.ndarray
    groups: np.ndarray
    n_obs: int
    iwa_mas: float


def grid_statistics(
    dataset: Dataset,
    grid: Grid,
    offsets_mas: np.ndarray | None = None,
    contrasts: np.ndarray | None = None,
    primary_diameter_mas: float = 0.0,
    chunk_columns: int | None = None,
) -> tuple[FilterStatistics | None, ...]:
    """Per filter, the grid's :class:`FilterStatistics` for a background scene (``None``
    for a filter with non-linear observables, e.g. OIFITS, solved exactly each time).

    The expensive part of :func:`contrast_grid` (a product of every position's series
    with the observable matrices); pass it to :func:`contrast_grid` to solve the grid
    again for other error scales.
    """
    offsets = np.zeros((0, 2)) if offsets_mas is None else np.asarray(offsets_mas, float)
    flux = np.zeros((0, dataset.n_filters)) if contrasts is None else np.asarray(contrasts, float)
    out: list[FilterStatistics | None] = []
    for f in range(dataset.n_filters):
        if not all(dataset.blocks[i].linear for i in filter_blocks(dataset, f)):
            out.append(None)  # contrast_grid builds this filter's scene and solves it exactly
            continue
        scene = _filter_scene(dataset, f, grid, offsets, flux, primary_diameter_mas)
        groups = np.unique(scene.groups[scene.groups < dataset.n_groups])
        onehot = jnp.asarray((scene.groups[:, None] == groups[None, :]).astype(float))
        r0 = jnp.concatenate(scene.residuals)
        # The products in float32: twice the rate of float64 on a CPU, and their rounding
        # (relative ~1e-6 in the inner products) is far below what moves a map (measured:
        # docs/performance.md). The solves that follow are float64.
        # Cast once, the x phasors included, not chunk by chunk.
        single = dataclasses.replace(
            scene,
            blocks=single_precision(scene.blocks),
            background=single_precision(scene.background),
            x_phasors=single_precision(scene.x_phasors),
            y_phasors=single_precision(scene.y_phasors),
        )
        r0_single, onehot_single = single_precision((r0, onehot))
        gram, cross = _over_columns(
            lambda xs, sc=single, r=r0_single, o=onehot_single: _chunk_statistics(
                sc.blocks, sc.background, r, o, xs, sc.y_phasors
            ),
            single,
            grid,
            chunk_columns,
        )
        out.append(
            FilterStatistics(
                gram=gram.astype(np.float64),
                cross=cross.astype(np.float64),
                background=np.asarray(jnp.einsum("o,o,og->g", r0, r0, onehot)),
                groups=groups,
                n_obs=scene.n_obs,
                iwa_mas=scene.iwa_mas,
            )
        )
    return tuple(out)


def contrast_grid(
    dataset: Dataset,
    grid: Grid,
    offsets_mas: np.ndarray | None = None,
    contrasts: np.ndarray | None = None,
    group_scales: np.ndarray | None = None,
    primary_diameter_mas: float = 0.0,
    n_steps: int = 3,
    chunk_columns: int | None = None,
    statistics: tuple[FilterStatistics | None, ...] | None = None,
) -> GridResult:
    """Solve the contrast of one more companion at every grid position, per filter.

    Parameters
    ----------
    dataset
        The observables.
    grid
        Positions to test.
    offsets_mas, contrasts
        Background companions: (K, 2) sky offsets and (K, n_filters) flux ratios
        (``None`` for none).
    group_scales
        (n_groups,) error scales (``None``: ones).
    primary_diameter_mas
        Uniform-disc diameter of the primary (0: unresolved).
    n_steps
        Gauss-Newton steps per position (3 reaches 1e-6 relative accuracy for c < 0.1).
    chunk_columns
        Grid columns per jitted call (default: about 2e5 uv-point evaluations per call).
    statistics
        :func:`grid_statistics` of the same dataset, grid and background (computed here
        when ``None``).
    """
    offsets = np.zeros((0, 2)) if offsets_mas is None else np.asarray(offsets_mas, float)
    flux = np.zeros((0, dataset.n_filters)) if contrasts is None else np.asarray(contrasts, float)
    scales_all = np.ones(dataset.n_groups) if group_scales is None else np.asarray(group_scales)
    if statistics is None:
        statistics = grid_statistics(
            dataset, grid, offsets, flux, primary_diameter_mas, chunk_columns
        )
    maps = []
    for f, name in enumerate(dataset.filters):
        known = statistics[f]
        if known is not None:
            weights = 1.0 / scales_all[known.groups] ** 2
            c, sigma, dchi2 = _solve_statistics(known.gram, known.cross, weights, n_steps)
            chi2_background, n_obs, iwa = (
                float(known.background @ weights),
                known.n_obs,
                known.iwa_mas,
            )
        else:
            scene = _filter_scene(dataset, f, grid, offsets, flux, primary_diameter_mas)
            ends = np.cumsum([b.n_obs for b in scene.blocks])[:-1]
            scales = tuple(
                jnp.asarray(x)
                for x in np.split(padded_scale_vector(scales_all, scene.groups), ends)
            )
            r0 = jnp.concatenate([r / x for r, x in zip(scene.residuals, scales, strict=True)])
            c, sigma, dchi2 = _over_columns(
                lambda xs, sc=scene, s=scales, r=r0: _solve_chunk(
                    sc.blocks, sc.background, s, r, xs, sc.y_phasors, n_steps
                ),
                scene,
                grid,
                chunk_columns,
            )
            chi2_background, n_obs = float(jnp.sum(r0**2)), scene.n_obs
            iwa = scene.iwa_mas
        maps.append(
            ContrastMap(
                filter_name=name,
                contrast=c,
                sigma=sigma,
                dchi2=dchi2,
                chi2_background=chi2_background,
                n_obs=n_obs,
                iwa_mas=iwa,
            )
        )
    iwa = max(m.iwa_mas for m in maps)
    return GridResult(grid=grid, maps=tuple(maps), iwa_mas=iwa)
