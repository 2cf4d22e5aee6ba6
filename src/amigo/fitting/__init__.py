"""Fitting science and calibrator exposures with the forward model (paper, "Model Fitting").

- :mod:`~amigo.fitting.params`: the fitted parameters of one filter;
- :mod:`~amigo.fitting.filter_fit`: the joint fit of one filter's exposures;
- :mod:`~amigo.fitting.newton`: its least-squares problem for :mod:`amigo.solvers`;
- :mod:`~amigo.fitting.ramp_fit`: science fits through the base model's ramp model.
"""
