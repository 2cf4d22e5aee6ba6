"""The base model's optics fidelity floor at CAL 4481 depth (prints a table).

    python benchmarks/optics_fidelity.py [--filters F380M] [--pupils 128,256]
                                         [--methods angular_spectrum,pupil]
                                         [--offsets X,Y;X,Y] [--nints N]

A noiseless image of the simulator's optics (:class:`amigo.simulation.OpticalModelIllumination`:
512-pixel pupil, 15 wavelengths, 4x sub-pixels) with the instrument state that
``amigo simulate --seed 0`` draws is fitted with the base model's optics at each setting
(its pupil sampling and defocus method; 9 wavelengths, 3x sub-pixels), every optical
parameter free (70 Zernikes, defocus, hole centres, jitter, detector rotation and
anisotropy, position, flux), weighted by the noise of one held-out exposure of
``cal4481_heldout.toml`` at the programme's depth (photon noise of ``nints_full``
integrations of a ``peak_dn`` peak, plus 300 e-^2 of read noise per integration). The
chi2 left is what the optics alone cannot reach: a floor under the z-score of any model
using that setting. Levenberg-Marquardt in float64 on the exact forward-mode Jacobian.
A few minutes per setting on a 2-core CPU. Not a test: nothing is asserted.

``--offsets`` places the star at other sub-pixel offsets from the reference pixel (the
exposure's own by default), one table row each: how the floor depends on the pixel phase,
which calibration against a star elsewhere in its pixel does not cancel (docs/detect.md,
the HD 206893-like scenario). ``--nints`` sets the depth (the exposure's ``nints_full``
by default).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from importlib import resources
from typing import Any

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from amigo import niriss
from amigo.model.base import BaseModel, BaseModelConfig
from amigo.model.detector.linear import bin_pixels
from amigo.simulation.optics_illumination import OpticalModelIllumination
from amigo.simulation.run import REFERENCE_PIXEL_XY
from amigo.simulation.scenarios import load_scenario
from amigo.simulation.scene import DetectorScene, DetectorSource
from amigo.simulation.state import draw_instrument_state

READ_VARIANCE_E2 = 300.0


def reference(spec, state) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Noiseless data (e- over the exposure) and its noise, from the simulator's optics."""
    xy = (REFERENCE_PIXEL_XY[0] + spec.offset_pix[0], REFERENCE_PIXEL_XY[1] + spec.offset_pix[1])
    scene = DetectorScene((DetectorSource(*xy, 1.0),))
    image = bin_pixels(
        jnp.asarray(OpticalModelIllumination().render(scene, spec.filter, state, 4)), 4
    )
    image = image / image.sum()
    total = spec.nints_full * spec.peak_dn * niriss.GAIN_E_PER_DN / image.max()
    data = image * total
    sigma = np.sqrt(data + spec.nints_full * READ_VARIANCE_E2)
    return data, sigma, xy


def floor(spec, state, pupil_npix: int, method: str) -> tuple[float, int, float]:
    """(best chi2, pixels, seconds) of the base-model optics at one setting."""
    data, sigma, xy = reference(spec, state)
    f = spec.filter
    config = BaseModelConfig(pupil_npix=pupil_npix, defocus_method=method)
    with jax.enable_x64(True):
        base = BaseModel.create(config, linear=True)
        cache = base.pupil_cache()
        centre = 0.5 * (niriss.SUBARRAY_SIZE - 1)
        start = {
            "zernikes": jnp.asarray(state.zernike_nm),
            "defocus": jnp.asarray(state.defocus_nm[f]),
            "holes": jnp.asarray(state.hole_centres_m()),
            "jitter": jnp.asarray(state.jitter_mas / 1000.0),
            "rotation": base.detector.rotation_deg,
            "anisotropy": base.detector.anisotropy,
            "position": base.detector.detector_to_optical(
                jnp.asarray([xy[0] - centre, xy[1] - centre])
            ),
            "log_flux": jnp.log(jnp.asarray(data.sum())),
        }
        vector, unravel = ravel_pytree(start)
        rows = slice(niriss.N_REFERENCE_ROWS, None)  # the reference rows see no light

        def residuals(v):
            p = unravel(v)
            model = eqx.tree_at(
                lambda m: (
                    m.zernikes_nm[f],
                    m.defocus_nm[f],
                    m.hole_centres_m,
                    m.detector.jitter_arcsec,
                    m.detector.rotation_deg,
                    m.detector.anisotropy,
                ),
                base,
                tuple(
                    p[k]
                    for k in ("zernikes", "defocus", "holes", "jitter", "rotation", "anisotropy")
                ),
            )
            image = model.illuminance(f, p["position"], cache)
            image = bin_pixels(image, 3) * jnp.exp(p["log_flux"])
            return ((image - data) / sigma)[rows].ravel()

        res = jax.jit(residuals)
        jac = jax.jit(jax.jacfwd(residuals))
        started = time.perf_counter()
        r = np.asarray(res(vector))
        chi2, damping = float(r @ r), 1e-3
        for _ in range(30):
            J = np.asarray(jac(vector))
            g, H = J.T @ r, J.T @ J
            scale = np.sqrt(np.diag(H)) + 1e-300
            improved = False
            while damping < 1e8:
                scaled = H / np.outer(scale, scale) + damping * np.eye(len(scale))
                trial = vector - np.linalg.solve(scaled, g / scale) / scale
                r_trial = np.asarray(res(trial))
                if float(r_trial @ r_trial) < chi2:
                    fall = chi2 - float(r_trial @ r_trial)
                    vector, r, chi2 = trial, r_trial, float(r_trial @ r_trial)
                    damping = max(damping / 3.0, 1e-9)
                    improved = True
                    break
                damping *= 5.0
            if not improved or fall < 1e-3 * max(chi2, 1.0):
                break
    return chi2, int(r.size), time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--filters", default="F380M")
    parser.add_argument("--pupils", default="128,256")
    parser.add_argument("--methods", default="angular_spectrum,pupil")
    parser.add_argument(
        "--offsets",
        default=None,
        help="sub-pixel offsets of the star, 'x,y;x,y' (pixels; default: the exposure's)",
    )
    parser.add_argument("--nints", type=int, default=None, help="integrations (depth)")
    args = parser.parse_args()
    path = resources.files("amigo") / "data" / "base_model" / "cal4481_heldout.toml"
    scenario = load_scenario(str(path))
    state_seed = np.random.SeedSequence(0).spawn(2 + len(scenario.exposures))[0]
    state = draw_instrument_state(
        np.random.default_rng(state_seed), scenario.spread, scenario.filters
    )
    wanted = args.filters.split(",")
    specs: dict[str, Any] = {}
    for spec in scenario.exposures:  # the first exposure of each filter (observation 3)
        specs.setdefault(spec.filter, spec)
    offsets = (
        [tuple(float(v) for v in pair.split(",")) for pair in args.offsets.split(";")]
        if args.offsets
        else [None]
    )
    print(
        f"{'filter':<6} {'offset (pix)':>13} {'nints':>6} {'pupil':>5} {'defocus':<17} "
        f"{'chi2 floor':>10} {'pixels':>6} {'s':>5}"
    )
    for name in wanted:
        for offset in offsets:
            spec = specs[name]
            if offset is not None:
                spec = dataclasses.replace(spec, offset_pix=offset)
            if args.nints is not None:
                spec = dataclasses.replace(spec, nints_full=args.nints)
            where = f"{spec.offset_pix[0]:+.2f},{spec.offset_pix[1]:+.2f}"
            for pupil in (int(p) for p in args.pupils.split(",")):
                for method in args.methods.split(","):
                    chi2, n, seconds = floor(spec, state, pupil, method)
                    print(
                        f"{name:<6} {where:>13} {spec.nints_full:>6} {pupil:>5} {method:<17} "
                        f"{chi2:>10.0f} {n:>6} {seconds:>5.0f}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
