"""Raw ramps -> slopes: the only calibration amigo applies to raw data (paper, "Data
Processing Pipeline").

:mod:`amigo.processing.ramps` turns an ``_uncal`` file's groups into the calslope product
(per-pixel mean slopes, their covariance and support); :mod:`amigo.processing.flat` does
the same for the flat-field exposures that training uses. Imports only :mod:`amigo.io` and
the package's foundation modules.
"""
