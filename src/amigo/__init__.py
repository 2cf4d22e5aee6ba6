"""amigo: a differentiable forward model of JWST NIRISS aperture masking interferometry.

The package turns raw JWST NIRISS AMI ramps (or STScI level-2 images) into calibrated
interferometric observables (kernel amplitudes and phases, "DISCOs") and companion
detections. Importing :mod:`amigo` is cheap: JAX is only imported by the modules that
model the instrument.

The Python API: ``amigo.open``, ``amigo.process``, ``amigo.fit``, ``amigo.detect``,
``amigo.simulate``, ``amigo.run``, ``amigo.run_manifest`` and ``amigo.train``
(:mod:`amigo.pipeline`, where examples are).
"""

from typing import Any

from amigo._version import __version__
from amigo.errors import AmigoError, InputError, NumericalFailure

#: The Python API (:mod:`amigo.pipeline`), imported on first use so that ``import amigo``
#: stays cheap.
API = ("open", "process", "fit", "detect", "simulate", "run", "run_manifest", "train")

__all__ = ["AmigoError", "InputError", "NumericalFailure", "__version__", *API]


def __getattr__(name: str) -> Any:
    if name in API:
        import amigo.pipeline

        return getattr(amigo.pipeline, name)
    raise AttributeError(f"module 'amigo' has no attribute {name!r}")
