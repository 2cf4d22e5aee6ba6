"""The observables a companion can move: the signal subspace of the Absil test.

The Absil et al. (2011) limit (:mod:`amigo.companions.limits`) asks when the chi2 of the
observables under "background + companion" would reject the background at ``n`` sigma.
Its threshold grows with the number ``N`` of observables the chi2 counts (``t_N - N`` ~
``n sqrt(2 N)``), and so its limit depends on how finely a tool samples the uv plane,
not only on what the data know. amigo's DISCOs sample the latent visibilities on the
fit's knot grid (0.26 m apart by default): ~930 per filter and exposure, while the
visibility of a companion within the search radius ``r_max`` varies on the scale
``lambda / r_max`` (2.2 m at 450 mas and 4.8 um). Most DISCO directions carry no
companion signal anywhere in the searched field; in the chi2 they add only noise.

A faint companion at ``theta`` changes the whitened observables ``z`` by
``c w(theta)`` (first order in its flux ratio ``c``; ``w`` the derivative of ``z``
through ``d log V / dc = e(theta) / V_p - 1``, ``e`` the band-averaged phasor and
``V_p`` the primary's visibility). :func:`signal_basis` finds the smallest set of
orthonormal directions (the leading eigenvectors of ``sum_theta w w^T`` over the
search's valid positions) that keeps at least :data:`SIGNAL_ENERGY_KEPT` of ``|w|^2``
at every position. The Absil test is then the chi2 of the ``k`` projections of the
residuals (a chi2 with ``k`` degrees of freedom for pure noise, as the full one is with
``N``): a matched-subspace energy detector (Scharf & Friedlander 1994). Its threshold no
longer depends on the uv sampling: a finer knot grid gives more DISCOs and the same
``k``. The subspace depends on the instrument, the band and the searched region only,
never on the data's values; the fitted contrast and its error at a position are the
grid's own (the kept energy changes the error by at most
``(1 / SIGNAL_ENERGY_KEPT)^(1/2) - 1`` = 0.05 %).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from amigo.companions.grid import (
    Grid,
    axis_phasors,
    background_residuals,
    filter_blocks,
    inner_working_angle_mas,
)
from amigo.companions.models import disc_visibility
from amigo.companions.observables import Dataset, Observables

#: Name of the subspace of all filters together (the combined curve's).
COMBINED = "combined"
#: Fraction of a companion's whitened signal energy kept at every searched position.
SIGNAL_ENERGY_KEPT = 0.999
#: Directions whose projections :func:`signal_basis` adds at once while it looks for k.
BASIS_BLOCK = 32


@dataclass(frozen=True)
class SignalSpace:
    """One filter's signal subspace (or all filters', :func:`combined_space`) and the
    background's chi2 in it.

    ``dof``: its dimension ``k``; ``n_obs``: the observables ``N``; ``kept``: the
    smallest fraction of a position's signal energy it keeps; ``valid`` (n_y, n_x): the
    grid positions it was made for; ``signals`` (n_valid, k) and ``residuals`` (k,):
    those positions' signals and the background scene's residuals (with the search's
    error scales) in its coordinates.
    """

    filter_name: str
    dof: int
    n_obs: int
    kept: float
    valid: np.ndarray = field(repr=False)
    signals: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)

    @property
    def chi2_background(self) -> float:
        """The chi2 of the background scene's residuals projected on the subspace."""
        return float(np.sum(self.residuals**2))


def signal_vectors(
    blocks: Sequence[Observables], offsets_mas: np.ndarray, primary_diameter_mas: float = 0.0
) -> np.ndarray:
    """(n_pos, sum of the blocks' n_obs) whitened first-order signal ``w`` of a
    companion at each of ``offsets_mas`` (n_pos, 2) sky offsets (mas), per unit flux
    ratio, the blocks' observables concatenated (unit error scales).

    The band-averaged phasors factorise over the two sky axes (as the grid's do,
    :func:`~amigo.companions.grid.axis_phasors`): one complex exponential per distinct
    offset on each axis, then a product summed over the band for each position, row by
    row of equal ``y``. In NumPy: the number of positions changes with the search's
    radius and inner working angle, and eager JAX would compile for every shape.
    """
    offsets = np.asarray(offsets_mas, float).reshape(-1, 2)
    x_axis, x_index = np.unique(offsets[:, 0], return_inverse=True)
    y_axis, y_index = np.unique(offsets[:, 1], return_inverse=True)
    rows = [np.flatnonzero(y_index == j) for j in range(y_axis.size)]
    parts = []
    for block in blocks:
        uv, wl, w = (jnp.asarray(a) for a in (block.uv_m, block.wavelengths_m, block.weights))
        primary = (
            np.asarray(disc_visibility(uv, wl, w, primary_diameter_mas))
            if primary_diameter_mas > 0
            else np.ones(block.n_uv)
        )
        x_phasors = axis_phasors(block, x_axis, 0) * np.asarray(block.weights)[None]
        y_phasors = axis_phasors(block, y_axis, 1)
        whiten = _signal_whitener(block, primary)
        out = np.empty((offsets.shape[0], block.n_obs))
        for j, row in enumerate(rows):
            # sum_l w_l exp_x[i, u, l] exp_y[j, u, l]: (positions of the row, n_uv)
            phasors = np.einsum("iul,ul->iu", x_phasors[x_index[row]], y_phasors[j])
            out[row] = whiten(phasors / primary - 1.0)
        parts.append(out)
    return np.concatenate(parts, axis=1)


def _signal_whitener(block: Observables, primary: np.ndarray):
    """``d log V`` (n, n_uv) complex -> the whitened observables' change (n, n_obs), the
    block's linear chain (design, exponential rows, projection, errors) as NumPy arrays."""
    design = block.design
    # V2 = exp(2 log|V|): the chain rule's factor is the primary's own V2, exp of the
    # linear map of its log visibility (a disc's is real: no phase).
    log_primary = np.concatenate([np.log(np.abs(primary)), np.zeros(primary.size)])
    exp_factor = np.where(np.asarray(block.exp_rows), np.exp(design @ log_primary), 1.0)
    projection = None if block.projection is None else np.asarray(block.projection)
    errors = np.asarray(block.errors)

    def whiten(d_log: np.ndarray) -> np.ndarray:
        d_raw = (np.concatenate([d_log.real, d_log.imag], axis=1) @ design.T) * exp_factor
        if projection is not None:
            d_raw = d_raw @ projection.T
        return d_raw / errors

    return whiten


def signal_basis(
    signals: np.ndarray, energy_kept: float = SIGNAL_ENERGY_KEPT
) -> tuple[np.ndarray, float]:
    """The fewest orthonormal directions that keep ``energy_kept`` of every row's energy.

    ``signals`` (n_pos, N): one whitened signal per searched position. Returns the basis
    (N, k), leading eigenvectors of ``signals^T signals``, and the smallest fraction of
    a row's energy it keeps.
    """
    gram = signals.T @ signals
    values, vectors = np.linalg.eigh(gram)
    keep = values[::-1] > 0
    values, vectors = values[::-1][keep], vectors[:, ::-1][:, keep]
    energy = np.sum(signals**2, axis=1)
    live = energy > 0
    if not np.any(live):
        return vectors[:, :0], 1.0
    rows, energy = signals[live], energy[live]
    # The eigenvalues are the energies the directions keep summed over positions, so the
    # least-kept position keeps at most their cumulative fraction: fewer directions than
    # reach ``energy_kept`` on that sum cannot do. Projections start there (one less, for
    # rounding), in blocks, instead of on all N directions.
    start = int(np.searchsorted(np.cumsum(values) / np.sum(values), energy_kept))
    start = max(0, min(start - 1, vectors.shape[1] - 1))
    kept = np.sum((rows @ vectors[:, :start]) ** 2, axis=1) / energy
    worst = np.empty(0)
    for lo in range(start, vectors.shape[1], BASIS_BLOCK):
        block = vectors[:, lo : lo + BASIS_BLOCK]
        cumulative = kept[:, None] + np.cumsum((rows @ block) ** 2, axis=1) / energy[:, None]
        worst = cumulative.min(axis=0)  # the least-kept position with lo + 1, lo + 2, ...
        reached = np.flatnonzero(worst >= energy_kept)
        if reached.size:
            k = lo + int(reached[0]) + 1
            return vectors[:, :k], float(worst[reached[0]])
        kept = cumulative[:, -1]
    return vectors, float(worst[-1]) if worst.size else 1.0


def signal_spaces(
    dataset: Dataset,
    grid: Grid,
    residual_offsets_mas: np.ndarray | None,
    residual_contrasts: np.ndarray | None,
    group_scales: np.ndarray,
    primary_diameter_mas: float = 0.0,
) -> dict[str, SignalSpace]:
    """Per filter, the signal subspace of a search over ``grid`` (its positions between
    the filter's inner working angle and ``grid.rmax_mas``) and the chi2 in it of the
    residuals of the background scene (companions at ``residual_offsets_mas`` (K, 2)
    with flux ratios ``residual_contrasts`` (K, n_filters)), the observables scaled by
    ``group_scales`` (n_groups,); with several filters also :data:`COMBINED`'s
    (:func:`combined_space`)."""
    offsets = np.zeros((0, 2)) if residual_offsets_mas is None else residual_offsets_mas
    fluxes = np.zeros((0, dataset.n_filters)) if residual_contrasts is None else residual_contrasts
    x, y = np.meshgrid(grid.x_mas, grid.y_mas)  # (n_y, n_x), as the maps
    spaces = {}
    for f, name in enumerate(dataset.filters):
        index = filter_blocks(dataset, f)
        blocks = [dataset.blocks[i] for i in index]
        scales = np.concatenate(
            [np.asarray(group_scales, float)[dataset.group_index(i)] for i in index]
        )
        residuals = background_residuals(
            dataset, index, offsets, fluxes[:, f], primary_diameter_mas
        )
        valid = grid.valid(inner_working_angle_mas(blocks))
        positions = np.stack([x[valid], y[valid]], axis=-1)
        # The search's errors are the files' times the scales: so are its signals.
        signals = signal_vectors(blocks, positions, primary_diameter_mas) / scales
        basis, kept = signal_basis(signals)
        spaces[name] = SignalSpace(
            filter_name=name,
            dof=basis.shape[1],
            n_obs=residuals.size,
            kept=kept,
            valid=valid,
            signals=signals @ basis,
            residuals=basis.T @ (residuals / scales),
        )
    if dataset.n_filters > 1:
        spaces[COMBINED] = combined_space(list(spaces.values()))
    return spaces


def combined_space(spaces: list[SignalSpace]) -> SignalSpace:
    """The signal subspace of a companion with one flux ratio in every filter (the
    combined curve's model): at each position valid in every filter its signal is the
    filters' signals side by side, which lie in the filters' own subspaces; their span
    is found in those coordinates (``sum k_f`` of them), and is smaller than the sum."""
    valid = np.logical_and.reduce([s.valid for s in spaces])
    signals = np.concatenate([s.signals[valid[s.valid]] for s in spaces], axis=1)
    residuals = np.concatenate([s.residuals for s in spaces])
    basis, kept = signal_basis(signals)
    return SignalSpace(
        filter_name=COMBINED,
        dof=basis.shape[1],
        n_obs=sum(s.n_obs for s in spaces),
        kept=kept * min(s.kept for s in spaces),
        valid=valid,
        signals=signals @ basis,
        residuals=basis.T @ residuals,
    )
