"""Truth simulator of raw NIRISS AMI ramps with physical detector effects.

``amigo simulate SCENARIO --out DIR`` writes level-1b ``_uncal.fits`` files and their
``_truth.json``. The pieces, each usable on its own:

* :mod:`~amigo.simulation.scene`: targets and companions on the sky, their detector
  positions (through :mod:`amigo.orientation`), dither patterns.
* :mod:`~amigo.simulation.state`: the random optical state (aberrations, defocus, pupil
  distortion, jitter) recorded as truth.
* :mod:`~amigo.simulation.illumination`: pluggable optical models returning the
  oversampled photon-rate image (an analytic NRM image; a flat field).
* :mod:`~amigo.simulation.detector`: the detector's own physics, integration by
  integration (brighter-fatter boundary shifts, IPC, non-linearity, noise, ADC...),
  independent of the fitting model's detector.
* :mod:`~amigo.simulation.scenarios`: scenario TOML files (built-ins in
  ``amigo/data/scenarios``).
* :mod:`~amigo.simulation.writer` and :mod:`~amigo.simulation.run`: streamed files.

See docs/simulate.md.
"""

from amigo.simulation.detector import (
    DetectorConfig,
    DetectorRealisation,
    RampSimulator,
    draw_detector,
)
from amigo.simulation.illumination import AnalyticNRM, Illumination, UniformIllumination
from amigo.simulation.run import simulate_scenario
from amigo.simulation.scenarios import Scenario, builtin_names, load_scenario, parse_scenario
from amigo.simulation.scene import (
    DetectorScene,
    DetectorSource,
    SkyCompanion,
    Target,
    detector_scene,
)
from amigo.simulation.state import InstrumentState, StateSpread, draw_instrument_state

__all__ = [
    "AnalyticNRM",
    "DetectorConfig",
    "DetectorRealisation",
    "DetectorScene",
    "DetectorSource",
    "Illumination",
    "InstrumentState",
    "RampSimulator",
    "Scenario",
    "SkyCompanion",
    "StateSpread",
    "Target",
    "UniformIllumination",
    "builtin_names",
    "detector_scene",
    "draw_detector",
    "draw_instrument_state",
    "load_scenario",
    "parse_scenario",
    "simulate_scenario",
]
