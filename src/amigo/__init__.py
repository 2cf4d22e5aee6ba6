"""amigo: a differentiable forward model of JWST NIRISS aperture masking interferometry.

The package turns raw JWST NIRISS AMI ramps (or STScI level-2 images) into calibrated
interferometric observables (kernel amplitudes and phases, "DISCOs") and companion
detections. Importing :mod:`amigo` is cheap: JAX is only imported by the modules that
model the instrument.
"""

from amigo._version import __version__
from amigo.errors import AmigoError, InputError

__all__ = ["AmigoError", "InputError", "__version__"]
