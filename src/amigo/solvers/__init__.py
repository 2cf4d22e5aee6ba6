"""Model-agnostic solvers: they see vectors, losses, gradients and Fisher matrices, never
the instrument. :mod:`~amigo.solvers.levenberg_marquardt` is the damped Gauss-Newton
solver of the fits."""
