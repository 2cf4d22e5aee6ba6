"""From fitted exposures to calibrated interferometric observables.

:mod:`~amigo.observables.kernel` holds the linear algebra (kernel projection, calibration,
DISCOs; paper, "Kernel Amplitudes & Phases"); :mod:`~amigo.observables.extract` runs it on
the fits of one filter.
"""
