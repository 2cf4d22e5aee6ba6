"""Detection's programs on padded observables (``observables.program_view``) give the
numbers of the files as read: the grid search's statistics and a companion fit, each
against the same computation on an unpadded view (to rounding)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from amigo.companions import fit as fitting
from amigo.companions import grid as grid_search
from amigo.companions import observables as obs
from detect_helpers import sim_dataset

TRUTH = (-210.0, 95.0, 0.012)


def _unpadded(dataset: obs.Dataset) -> obs.ProgramView:
    """The identity view: the blocks as read, their own group indices."""
    n = len(dataset.blocks)
    return obs.ProgramView(
        dataset=dataset,
        groups=tuple(dataset.group_index(i).astype(np.int32) for i in range(n)),
        rows=tuple(np.arange(b.n_obs) for b in dataset.blocks),
    )


@pytest.fixture
def dataset(tmp_path) -> obs.Dataset:
    return sim_dataset(tmp_path, ("F430M", "F480M"), [TRUTH], np.random.default_rng(11), "P")


def test_the_grid_on_padded_observables_is_the_files_grid(dataset, monkeypatch):
    with jax.enable_x64(True):
        grid = grid_search.Grid.square(400.0, 40.0)
        padded = grid_search.grid_statistics(dataset, grid)
        monkeypatch.setattr(grid_search, "program_view", _unpadded)
        plain = grid_search.grid_statistics(dataset, grid)
    for f, (p, q) in enumerate(zip(padded, plain, strict=True)):
        assert p is not None and q is not None
        assert p.n_obs == q.n_obs == dataset.blocks[f].n_obs  # one block per filter
        assert p.iwa_mas == q.iwa_mas
        np.testing.assert_array_equal(p.groups, q.groups)
        np.testing.assert_allclose(p.background, q.background, rtol=1e-10)
        # float32 products: their rounding, relative to the largest entries
        np.testing.assert_allclose(p.gram, q.gram, rtol=1e-4, atol=1e-5 * np.abs(q.gram).max())
        np.testing.assert_allclose(p.cross, q.cross, rtol=1e-4, atol=1e-5 * np.abs(q.cross).max())


def test_a_fit_on_padded_observables_is_the_files_fit(dataset, monkeypatch):
    start = (np.array([[TRUTH[0] + 3.0, TRUTH[1] - 2.0]]), np.log10(np.full((1, 2), 0.01)))
    scales = np.array([1.1, 0.9, 1.2, 0.8])[: dataset.n_groups]
    with jax.enable_x64(True):
        padded = fitting.fit_companions(dataset, *start, scales)
        padded_scales = fitting.estimate_scales(dataset, padded.offsets_mas, padded.contrasts)
        monkeypatch.setattr(fitting, "program_view", _unpadded)
        plain = fitting.fit_companions(dataset, *start, scales)
        plain_scales = fitting.estimate_scales(dataset, plain.offsets_mas, plain.contrasts)
    assert padded.converged and plain.converged
    np.testing.assert_allclose(padded.chi2, plain.chi2, rtol=1e-9)
    np.testing.assert_allclose(padded.offsets_mas, plain.offsets_mas, atol=1e-6)
    np.testing.assert_allclose(padded.log10_contrasts, plain.log10_contrasts, atol=1e-8)
    np.testing.assert_allclose(padded.covariance, plain.covariance, rtol=1e-6)
    np.testing.assert_allclose(padded_scales, plain_scales, rtol=1e-9)
