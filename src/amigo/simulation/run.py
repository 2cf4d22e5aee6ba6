"""Simulate a whole scenario: every exposure to ``_uncal.fits`` + ``_truth.json``.

Randomness: one :class:`numpy.random.SeedSequence` from the user's seed spawns, in this
order, the instrument state, the detector's per-pixel truth and one stream per exposure
(in scenario order), so the same seed and scenario give byte-identical files, and the
exposures do not depend on how many integrations the others have.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from astropy.time import TimeDelta

from amigo import niriss
from amigo._version import __version__
from amigo.orientation import Orientation
from amigo.progress import step, track
from amigo.simulation.detector import DetectorConfig, RampSimulator, draw_detector
from amigo.simulation.illumination import AnalyticNRM, Illumination, UniformIllumination
from amigo.simulation.optics_illumination import OpticalModelIllumination
from amigo.simulation.scenarios import ExposureSpec, Scenario
from amigo.simulation.scene import REFERENCE_PIXEL_XY, DetectorScene, DetectorSource, detector_scene
from amigo.simulation.state import InstrumentState, draw_instrument_state
from amigo.simulation.writer import (
    UncalWriter,
    exposure_duration_s,
    primary_header,
    sci_header,
    start_time,
    uncal_primary_cards,
    write_truth,
)

#: Gap between consecutive exposures of a scenario (s), for the time keywords.
EXPOSURE_GAP_S: float = 60.0


@dataclass(frozen=True)
class SimulatedExposure:
    """Paths of what one exposure wrote."""

    uncal: Path
    truth: Path


def default_illumination(scenario: Scenario) -> Illumination:
    """The optical model a scenario asks for.

    ``auto`` and ``optics``: the project's optical model at simulation fidelity
    (:class:`~amigo.simulation.optics_illumination.OpticalModelIllumination`); ``analytic``:
    the closed-form :class:`~amigo.simulation.illumination.AnalyticNRM` (no JAX, no
    intra-hole aberrations; fast, for tests and quick looks).
    """
    if scenario.illumination == "analytic":
        return AnalyticNRM(n_wavelengths=scenario.n_wavelengths)
    return OpticalModelIllumination(n_wavelengths=scenario.n_wavelengths)


def _photon_scale(spec: ExposureSpec, unit_rate: np.ndarray, oversample: int, gain: float) -> float:
    """Factor turning a unit-primary-rate image into the exposure's photon rate."""
    k = oversample
    n = unit_rate.shape[0] // k
    pixels = unit_rate.reshape(n, k, n, k).sum(axis=(1, 3))
    integration_s = spec.ngroups * niriss.GROUP_TIME_S
    if spec.photons_full is not None:
        target_rate = spec.photons_full / (spec.nints_full * integration_s)
        return target_rate / float(pixels.sum())
    assert spec.peak_dn is not None
    return spec.peak_dn * gain / (float(pixels.max()) * integration_s)


def _orientation(spec: ExposureSpec) -> Orientation:
    return Orientation.from_roll((spec.pa_aper_deg - niriss.V3_IDL_Y_ANGLE_DEG) % 360.0)


def simulate_exposure(
    spec: ExposureSpec,
    scenario: Scenario,
    *,
    out_dir: Path,
    state: InstrumentState,
    detector_truth: Any,
    config: DetectorConfig,
    illumination: Illumination,
    rng: np.random.Generator,
    full: bool,
    seed: int,
    start_mjd_offset_s: float,
    noise_seed: int | None = None,
) -> SimulatedExposure:
    """Simulate one exposure and write its uncal and truth files."""
    stem = spec.stem(scenario.program)
    nints = spec.nints_full if full else spec.nints
    k = scenario.oversample
    orientation = _orientation(spec)
    primary_xy = (
        REFERENCE_PIXEL_XY[0] + spec.offset_pix[0],
        REFERENCE_PIXEL_XY[1] + spec.offset_pix[1],
    )
    if spec.role == "flat":
        scene = DetectorScene((DetectorSource(*primary_xy, 1.0),))
        model: Illumination = UniformIllumination()
    else:
        assert spec.target is not None
        scene = detector_scene(spec.target, spec.filter, orientation, primary_xy, 1.0)
        model = illumination
    unit_rate = model.render(scene, spec.filter, state, k)
    scale = _photon_scale(spec, unit_rate, k, config.gain_e_per_dn)
    rate = unit_rate * scale
    scene = scene.scaled(scale)

    simulator = RampSimulator(rate, k, detector_truth, config, spec.ngroups)
    start = start_time(scenario.date_obs, scenario.time_obs) + TimeDelta(
        start_mjd_offset_s, format="sec"
    )
    # XOFFSET/YOFFSET: the dither offset in the ideal frame (arcsec), to first order.
    ideal = np.asarray(niriss.SCI_TO_IDEAL_ARCSEC_PER_PIX) @ np.asarray(spec.dither_offset_pix)
    dither_arcsec = (float(ideal[0]), float(ideal[1]))
    target = spec.target
    cards = uncal_primary_cards(
        program=scenario.program,
        observation=spec.observation,
        visit=spec.visit,
        visit_group=spec.visit_group,
        sequence=spec.sequence,
        activity=spec.activity,
        exposure=spec.exposure,
        filter_name=spec.filter,
        exp_type="NIS_LAMP" if spec.role == "flat" else "NIS_AMI",
        pupil="CLEARP" if spec.role == "flat" else "NRM",
        target_name=target.name if target else "FLAT",
        catalog_name=target.catalog_name if target else "FLAT",
        ra_deg=target.ra_deg if target else 0.0,
        dec_deg=target.dec_deg if target else 0.0,
        nints=nints,
        ngroups=spec.ngroups,
        start=start,
        dither_pattern=spec.dither_pattern,
        dither_position=spec.dither_position,
        dither_total=spec.dither_total,
        dither_offset_arcsec=dither_arcsec,
        filename=f"{stem}_uncal.fits",
        extra={
            "SIMSCEN": (scenario.name, "amigo simulate scenario"),
            "SIMSEED": (int(seed), "amigo simulate seed"),
            "SIMFULL": (bool(full), "T if --full (the program's integrations)"),
            "SIMROLE": (spec.role, "science, calibrator or flat"),
            **(
                {}
                if noise_seed is None
                else {"SIMNSEED": (int(noise_seed), "amigo simulate noise seed")}
            ),
        },
    )
    sci = sci_header(
        nints=nints,
        ngroups=spec.ngroups,
        orientation=orientation,
        primary_xy_pix=primary_xy,
        ra_deg=target.ra_deg if target else 0.0,
        dec_deg=target.dec_deg if target else 0.0,
        reference_xy_pix=REFERENCE_PIXEL_XY,
    )
    uncal_path = out_dir / f"{stem}_uncal.fits"
    photons: list[float] = []
    dark: list[float] = []
    cosmic_rays: list[dict[str, float]] = []
    saturated: list[int] = []
    peak_signal_dn = 0.0
    with UncalWriter(uncal_path, primary_header(cards), sci) as writer:
        for integration in track(range(nints), f"simulate {stem}"):
            ramp, truth = simulator.integration(rng)
            writer.write(ramp)
            photons.append(truth.photons)
            dark.append(truth.dark_e)
            saturated.append(truth.saturated_pixels)
            for hit in truth.cosmic_rays:
                cosmic_rays.append({"integration": integration, **hit})
            last = ramp[-1].astype(float) - (detector_truth.bias_dn if config.bias else 0.0)
            peak_signal_dn = max(peak_signal_dn, float(last.max()))

    truth_path = out_dir / f"{stem}_truth.json"
    integration_s = spec.ngroups * niriss.GROUP_TIME_S
    in_fov_rate = float(rate.sum())
    truth_doc = {
        "amigo_version": __version__,
        "kind": "amigo-simulate-truth",
        "scenario": scenario.name,
        "scenario_source": scenario.source,
        "seed": int(seed),
        "noise_seed": None if noise_seed is None else int(noise_seed),
        "full": bool(full),
        "uncal": uncal_path.name,
        "exposure": {
            "stem": stem,
            "role": spec.role,
            "target": target.name if target else None,
            "filter": spec.filter,
            "ngroups": spec.ngroups,
            "nints": nints,
            "nints_full": spec.nints_full,
            "group_time_s": niriss.GROUP_TIME_S,
            "dither_pattern": spec.dither_pattern,
            "dither_position": spec.dither_position,
            "dither_total": spec.dither_total,
        },
        "orientation": {
            "pa_aper_deg": orientation.pa_aper_deg,
            "roll_ref_deg": orientation.roll_ref_deg,
            "v3i_yang_deg": orientation.v3_idl_y_angle_deg,
            "vparity": orientation.vparity,
        },
        "scene": _scene_truth(spec, scene, orientation),
        "illumination": {
            **model.describe(),
            "oversample": k,
            "photons_per_s_in_subarray": in_fov_rate,
            "expected_peak_pixel_dn_last_group": float(
                rate.reshape(80, k, 80, k).sum(axis=(1, 3)).max()
                * integration_s
                / config.gain_e_per_dn
            ),
        },
        "instrument_state": state.to_json(),
        "photons": {
            "definition": "photo-electrons collected in SUB80 (flat-field and intra-pixel "
            "response applied, before saturation), excluding dark current and cosmic rays",
            "expected_per_integration": in_fov_rate * integration_s,
            "detected_per_integration": photons,
            "detected_total": float(np.sum(photons)),
            "expected_total": in_fov_rate * integration_s * nints,
            "expected_total_full": in_fov_rate * integration_s * spec.nints_full,
            "dark_electrons_per_integration": dark,
        },
        "peak_signal_dn_last_group": peak_signal_dn,
        "saturated_pixels_per_integration": saturated,
        "cosmic_rays": cosmic_rays,
        "detector": {
            "config": config.to_json(),
            "ipc_kernel": simulator.ipc.tolist(),
            "bfe_coefficients_x_pix_per_e": simulator.coeff_x.tolist(),
            "bfe_coefficients_y_pix_per_e": simulator.coeff_y.tolist(),
            "per_pixel": detector_truth.to_json(),
        },
    }
    write_truth(truth_path, truth_doc)
    return SimulatedExposure(uncal_path, truth_path)


def _scene_truth(
    spec: ExposureSpec, scene: DetectorScene, orientation: Orientation
) -> dict[str, Any]:
    primary = scene.sources[0]
    doc: dict[str, Any] = {
        "primary": {
            "x_pix": primary.x_pix,
            "y_pix": primary.y_pix,
            "photons_per_s": primary.photons_per_s,
            "offset_from_reference_pix": list(spec.offset_pix),
            "ra_deg": spec.target.ra_deg if spec.target else None,
            "dec_deg": spec.target.dec_deg if spec.target else None,
        },
        "companions": [],
        "pixel_convention": "0-based [y, x] indices of SUB80, pixel centres on integers",
    }
    if spec.target is None:
        doc["primary"]["note"] = "flat field: uniform illumination, photons_per_s is the total"
        return doc
    for companion, source in zip(spec.target.companions, scene.sources[1:], strict=True):
        dra, ddec = companion.offset_mas()
        doc["companions"].append(
            {
                "sep_mas": companion.sep_mas,
                "pa_deg": companion.pa_deg,
                "dra_mas": dra,
                "ddec_mas": ddec,
                "dmag": companion.dmag[spec.filter],
                "flux_ratio": companion.flux_ratio(spec.filter),
                "x_pix": source.x_pix,
                "y_pix": source.y_pix,
                "dx_pix": source.x_pix - primary.x_pix,
                "dy_pix": source.y_pix - primary.y_pix,
                "photons_per_s": source.photons_per_s,
            }
        )
    return doc


def simulate_scenario(
    scenario: Scenario,
    out_dir: str | os.PathLike[str],
    *,
    seed: int = 0,
    full: bool = False,
    illumination: Illumination | None = None,
    detector: DetectorConfig | None = None,
    select: Callable[[ExposureSpec], bool] | None = None,
    noise_seed: int | None = None,
) -> list[SimulatedExposure]:
    """Simulate every exposure of a scenario into ``out_dir``.

    Parameters
    ----------
    scenario
        From :func:`amigo.simulation.scenarios.load_scenario`.
    out_dir
        Output folder (created).
    seed
        Master seed (a non-negative integer).
    full
        Use the program's numbers of integrations (``nints_full``) instead of the quick
        defaults.
    illumination
        Optical model; default :func:`default_illumination`.
    detector
        Detector configuration; default the scenario's.
    select
        Only simulate the exposures for which this returns True (the random streams of
        the others are still spawned, so results do not depend on the selection).
    noise_seed
        Draw the exposures' random streams (photon and dark shot noise, reset, read and
        1/f noise, cosmic rays) from this seed instead, keeping the telescope and the
        detector that ``seed`` draws: the same sky through the same instrument with other
        noise (e.g. to measure the scatter of a fit against its errors). ``None``: from ``seed``, as before.
    """
    if int(seed) < 0:
        raise ValueError("seed must be a non-negative integer")
    if noise_seed is not None and int(noise_seed) < 0:
        raise ValueError("noise_seed must be a non-negative integer")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    root = np.random.SeedSequence(int(seed))
    state_seq, detector_seq, *exposure_seqs = root.spawn(2 + len(scenario.exposures))
    if noise_seed is not None:
        # Spawned alike, so that noise_seed == seed draws the same noise as no noise seed.
        _, _, *exposure_seqs = np.random.SeedSequence(int(noise_seed)).spawn(
            2 + len(scenario.exposures)
        )
    state = draw_instrument_state(
        np.random.default_rng(state_seq), scenario.spread, scenario.filters
    )
    config = detector or scenario.detector
    detector_truth = draw_detector(np.random.default_rng(detector_seq), config)
    model = illumination or default_illumination(scenario)
    step(
        f"simulate {scenario.name}: {len(scenario.exposures)} exposures, seed {seed}"
        f"{', full' if full else ''}, optics: {model.describe()['model']}"
    )
    written = []
    offset_s = 0.0
    for spec, seq in zip(scenario.exposures, exposure_seqs, strict=True):
        nints = spec.nints_full if full else spec.nints
        if select is None or select(spec):
            written.append(
                simulate_exposure(
                    spec,
                    scenario,
                    out_dir=out,
                    state=state,
                    detector_truth=detector_truth,
                    config=config,
                    illumination=model,
                    rng=np.random.default_rng(seq),
                    full=full,
                    seed=seed,
                    start_mjd_offset_s=offset_s,
                    noise_seed=noise_seed,
                )
            )
        offset_s += exposure_duration_s(nints, spec.ngroups) + EXPOSURE_GAP_S
    return written
