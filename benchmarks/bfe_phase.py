"""Each account of the brighter-fatter effect against the simulator's, at each pixel
phase (prints a table).

    python benchmarks/bfe_phase.py [--filter F380M] [--scenario go1843] [--nints 7046]
        [--phases "0.21,0.06;-0.17,0.22"] [--grid 4] [--sim-oversample 3]

The HD 206893-like scenario fails only when its calibrator sits at another pixel phase
than the science star and the simulator has a brighter-fatter effect (docs/detect.md):
this measures how the model's accounts of that effect follow it as the star moves within
a pixel, without noise and without the fit.

For the scenario's calibrator star in one filter, at each sub-pixel offset (the given
phases, the training scenario's five, marked ``*``, and an N x N grid): the simulator's
noiseless charge at the last read with its boundary shifts on and off (every other
detector effect off; its rate on ``--sim-oversample`` sub-pixels), and the model's ramp
on the same illuminance (3 sub-pixels; the optics rendered once at the least common
multiple and binned, the intra-pixel bowl in the rate for both) with each account of the
migration and without: the shipped network, and the physical account of
``amigo.model.detector.boundary`` with two field shapes (``R 3, h 0.5``: its default;
``R 2, h 0``: the simulator's). Per phase and account: the strength (least-squares
ratio of the charge moved to the simulator's), the correlation of the two patterns, the
chi2 of the simulator's effect at the depth of ``--nints`` integrations (Poisson
variance of the last read), and the chi2 of what the account leaves of it once scaled
by one ratio for every phase. ~10 s on 2 CPU cores at ``--grid 0``, 1 min at 12
sub-pixels. docs/detector.md, "The charge migration at each pixel phase".
"""

from __future__ import annotations

import argparse
import dataclasses

import jax.numpy as jnp
import numpy as np

from amigo import niriss
from amigo.model.base import default_model_path, load_base_model
from amigo.model.detector.boundary import BoundaryShift
from amigo.model.detector.ramp import IntraPixelResponse
from amigo.simulation.detector import (
    DetectorConfig,
    RampSimulator,
    draw_detector,
    intra_pixel_response,
)
from amigo.simulation.run import _orientation, _photon_scale, default_illumination
from amigo.simulation.scenarios import load_scenario
from amigo.simulation.scene import REFERENCE_PIXEL_XY, detector_scene
from amigo.simulation.state import draw_instrument_state

#: The training scenario's base offset and its dither (cal4481_train.toml).
TRAINING_OFFSET = (0.1, -0.1)
TRAINING_DITHER = ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5), (0.25, 0.25))


def last_read(
    rate: np.ndarray, k: int, config: DetectorConfig, ngroups: int, realisation
) -> np.ndarray:
    """(80, 80) electrons at the last read: the simulator's own integration, noiseless,
    from a rate ``k`` times oversampled."""
    sim = RampSimulator(rate, k, realisation, config, ngroups)
    ramp, _ = sim.integration(np.random.default_rng(0))
    return ramp[-1] * config.gain_e_per_dn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="go1843")
    parser.add_argument("--filter", default="F380M")
    parser.add_argument("--nints", type=int, default=7046)
    parser.add_argument("--phases", default="0.21,0.06;-0.17,0.22")
    parser.add_argument("--grid", type=int, default=4, help="also an N x N grid of phases")
    parser.add_argument(
        "--sim-oversample",
        type=int,
        default=3,
        help="the simulator's sub-pixels per pixel axis (its strips are 1/K pixel wide; "
        "the model's stay 3)",
    )
    args = parser.parse_args()

    scenario = load_scenario(args.scenario)
    k = args.sim_oversample
    fine = int(np.lcm(3, k))  # rendered once at this oversampling, binned to k and to 3
    spec = next(s for s in scenario.exposures if s.role == "calibrator" and s.filter == args.filter)
    rng = np.random.default_rng(0)
    state = draw_instrument_state(rng, scenario.spread, scenario.filters)
    # The intra-pixel bowl is applied below on the finest grid, for both sides alike.
    on = DetectorConfig.ideal(bfe=True)
    off = on.replace(bfe=False)
    realisation = draw_detector(np.random.default_rng(1), on)
    illumination = default_illumination(scenario)
    base = load_base_model(default_model_path())
    linear = base.with_linear_detector()
    accounts = {"network": base}
    for radius, depth in ((3, 0.5), (2, 0.0)):
        # At the simulator's strength: the table's ratios then say how the two differ.
        strength = on.bfe_strength_pix_per_e
        shift = BoundaryShift.create(strength, radius_pix=radius, depth_pix=depth)
        accounts[f"boundary R{radius} h{depth:g}"] = base.with_network(shift)
    integration_s = spec.ngroups * niriss.GROUP_TIME_S

    phases = [tuple(map(float, p.split(","))) for p in args.phases.split(";") if p]
    trained = [(TRAINING_OFFSET[0] + dx, TRAINING_OFFSET[1] + dy) for dx, dy in TRAINING_DITHER]
    grid = [((i + 0.5) / args.grid - 0.5, (j + 0.5) / args.grid - 0.5)
            for j in range(args.grid) for i in range(args.grid)]  # fmt: skip
    rows = []
    scale = None
    for offset in phases + trained + grid:
        xy = (REFERENCE_PIXEL_XY[0] + offset[0], REFERENCE_PIXEL_XY[1] + offset[1])
        assert spec.target is not None
        scene = detector_scene(spec.target, spec.filter, _orientation(spec), xy, 1.0)
        unit = illumination.render(scene, spec.filter, state, fine)
        if scale is None:  # one flux for every phase: the scenario's at the first
            scale = _photon_scale(spec, unit, fine, on.gain_e_per_dn)
        rate = (
            unit * scale * np.tile(intra_pixel_response(fine, on.intra_pixel_edge_loss), (80, 80))
        )
        sim_rate = _bin(rate, fine // k)
        physics = last_read(sim_rate, k, on, spec.ngroups, realisation)
        plain = last_read(sim_rate, k, off, spec.ngroups, realisation)
        # The model's ramp on the same illuminance, its own intra-pixel response and flat
        # set to none (the bowl is in the rate) so that only the migration differs.
        electrons = jnp.asarray(_bin(rate, fine // 3) * integration_s, jnp.float32)
        lin = np.asarray(_plain_ramp(linear)(electrons, spec.ngroups))[-1]
        moved = {
            name: np.asarray(_plain_ramp(model)(electrons, spec.ngroups))[-1] - lin
            for name, model in accounts.items()
        }
        rows.append((offset, physics - plain, moved, plain, offset in trained))
    common = {}
    for name in accounts:
        num = sum(float(np.sum(r[2][name] * r[1])) for r in rows)
        common[name] = num / sum(float(np.sum(r[1] ** 2)) for r in rows)
    print(
        f"{args.scenario} calibrator, {args.filter}, {spec.ngroups} groups, simulator at "
        f"{k}x, "
        f"peak {max(r[3].max() for r in rows):.0f} e-; chi2 at {args.nints} integrations; "
        "strengths as fractions of the simulator's; common strength: "
        + ", ".join(f"{name} {value:.3f}" for name, value in common.items())
    )
    print(
        "| phase (pix) | chi2 of the effect | "
        + " | ".join(f"{n}: strength | correlation | chi2 left" for n in accounts)
        + " |"
    )
    print("|---|---|" + "---|---|---|" * len(accounts))
    for offset, physics, moved, plain, is_trained in rows:
        variance = np.maximum(plain, 1.0) / args.nints
        cells = [f"({offset[0]:+.2f}, {offset[1]:+.2f}){'*' if is_trained else ''}"]
        cells.append(f"{np.sum(physics**2 / variance):.0f}")
        for name, pattern in moved.items():
            left = pattern - common[name] * physics
            strength = float(np.sum(pattern * physics) / np.sum(physics * physics))
            corr = float(np.corrcoef(pattern.ravel(), physics.ravel())[0, 1])
            cells += [f"{strength:.3f}", f"{corr:.4f}", f"{np.sum(left**2 / variance):.0f}"]
        print("| " + " | ".join(cells) + " |", flush=True)


def _bin(image: np.ndarray, factor: int) -> np.ndarray:
    """Sum ``factor`` x ``factor`` blocks."""
    ny, nx = image.shape[0] // factor, image.shape[1] // factor
    return image.reshape(ny, factor, nx, factor).sum(axis=(1, 3))


def _plain_ramp(base):
    """The base model's ramp with a unit flat and a flat intra-pixel response (the
    simulator's ideal detector has neither; the intra-pixel bowl is in the rate)."""
    ramp = dataclasses.replace(
        base.ramp, flat=jnp.ones_like(base.ramp.flat), intra_pixel=IntraPixelResponse()
    )
    return ramp


if __name__ == "__main__":
    main()
