"""Training the base model on calibration exposures (paper, "Base Model Training and
Calibration"): :mod:`~amigo.training.trainer`."""
