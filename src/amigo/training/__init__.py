"""Training the base model on calibration exposures (paper, "Base Model Training and
Calibration").

- :mod:`~amigo.training.trainer`: the trainer, its stages, epochs and checkpoints;
- :mod:`~amigo.training.groups`: which parameters each data set calibrates;
- :mod:`~amigo.training.fisher`: the Fisher information that preconditions the steps;
- :mod:`~amigo.training.data`: settings, training data, state and loss history;
- :mod:`~amigo.training.exposure`: one exposure's fit and the closed-form dark residual.
"""
