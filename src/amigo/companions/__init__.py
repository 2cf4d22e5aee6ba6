"""Companion detection from calibrated interferometric observables (calvis or OIFITS).

Modules, in the order of the analysis:

* :mod:`~amigo.companions.observables` - calvis/OIFITS files -> independent observables;
* :mod:`~amigo.companions.models` - visibilities of a primary with point companions;
* :mod:`~amigo.companions.grid` - vectorised contrast grid and detection maps;
* :mod:`~amigo.companions.fit` - joint least-squares fit of several companions;
* :mod:`~amigo.companions.posterior` - numpyro NUTS posteriors;
* :mod:`~amigo.companions.limits` - Ruffio (2018) and Absil contrast limits;
* :mod:`~amigo.companions.search` - the whole search, as ``amigo detect`` runs it;
* :mod:`~amigo.plots.companions` and :mod:`~amigo.companions.products` - outputs.
"""
