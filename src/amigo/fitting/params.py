"""The fitted parameters of one filter: what :mod:`amigo.fitting.filter_fit` fits and
:mod:`amigo.fitting.newton` lays out as one vector."""

from __future__ import annotations

import equinox as eqx

from amigo.model.image import ExposureParams, OpticsParams, SourceParams


class FitParams(eqx.Module):
    """All fitted parameters of one filter.

    Attributes
    ----------
    exposures
        :class:`~amigo.model.image.ExposureParams` stacked over exposures (leading axis E).
    sources
        :class:`~amigo.model.image.SourceParams` stacked over targets (leading axis S).
    optics
        :class:`~amigo.model.image.OpticsParams` of the filter.
    """

    exposures: ExposureParams
    sources: SourceParams
    optics: OpticsParams
