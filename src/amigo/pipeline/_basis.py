"""``amigo.bases``: build (or find in the cache) the latent visibility bases of some filters
and draw their eigenvalue spectra (``amigo basis``'s job)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PathLike = str | os.PathLike[str]


@dataclass
class BasisReport:
    """One filter's basis: its :class:`~amigo.model.basis.BasisInfo` (``n_amp``,
    ``n_phase``, ``n_knots_support``, ``key``, eigenvalues) and the figure drawn."""

    filter_name: str
    info: Any
    figure: Path


def bases(
    filters: Sequence[str] = (),
    *,
    model: PathLike | None = None,
    plots: PathLike | None = None,
) -> list[BasisReport]:
    """Build the latent visibility basis of each filter (default: the three calibrated
    filters) for the instrument of ``model`` (an instrument file; default: the nominal
    instrument) and cache it, so that ``amigo fit`` does not rebuild it. Draws each
    eigenvalue spectrum, truncation marked, into ``plots`` (default: the cache folder)."""
    from amigo import niriss
    from amigo.model.basis import cache_dir, load_basis
    from amigo.model.image import Instrument, load_instrument
    from amigo.plots.basis import spectrum_figure
    from amigo.plots.fit import save_figure

    instrument = Instrument.nominal() if model is None else load_instrument(model)
    folder = cache_dir() if plots is None else Path(plots)
    reports = []
    for name in [f.upper() for f in filters] or list(niriss.CALIBRATED_FILTERS):
        _, info = load_basis(instrument, name)
        path = save_figure(spectrum_figure(info), folder / f"basis_{name}.png")
        reports.append(BasisReport(name, info, path))
    return reports
