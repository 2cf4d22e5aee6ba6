"""Likelihoods: how the forward model's prediction meets the data.

:mod:`~amigo.likelihood.pixels` holds the Gaussian likelihoods of level-2 images and of
calslope slopes; :mod:`~amigo.likelihood.slopes` composes the base model with a calslope
exposure (the training problem's model and its whitened residuals).
"""
