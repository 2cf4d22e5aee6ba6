"""Timing of the optical model + linear detector on this machine (prints a table).

    python benchmarks/optics.py [--repeats 20] [--filter F430M] [--quick]

Rows: the 9-wavelength broadband image (optics -> 240x240 illuminance -> 80x80 detector
image), and the same with the gradient of a chi^2 loss with respect to every optical
parameter (70 Zernikes, defocus, 7 hole amplitudes, source position, flux, spectral
slope, jitter, rotation, anisotropy; plus the mask geometry - 18 global and 70 per-hole
distortion coefficients, hole centres and size - for the dynamic mask), for the static
(precomputed) and dynamic (fittable) mask, in float32 and float64, with the two defocus
methods. Times are wall-clock per call of a jitted function after compilation: the
minimum and the median of ``--repeats`` calls (the minimum is the figure least affected
by other processes sharing the CPU). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import equinox as eqx
import jax
import jax.numpy as jnp

from amigo.model.detector import LinearDetector
from amigo.model.optics import NRMOptics, OpticsConfig, PointSource


def build(filter_name: str, config: OpticsConfig, static: bool):
    optics = NRMOptics.create(config, static=static)
    optics = eqx.tree_at(lambda o: o.zernikes_nm, optics, optics.zernikes_nm + 20.0)
    source = PointSource.create(filter_name, position_arcsec=(0.01, -0.02), flux=1e7)
    detector = LinearDetector.create()
    return optics, source, detector


def fittable(model, static: bool):
    """(parameters, rest): every optical/source/detector parameter, nothing else."""
    spec = jax.tree.map(lambda _: False, model)
    picks = [
        lambda m: m[0].zernikes_nm,
        lambda m: m[0].defocus_nm,
        lambda m: m[0].hole_amplitudes,
        lambda m: m[1].position_arcsec,
        lambda m: m[1].flux,
        lambda m: m[1].spectrum.slope_per_um,
        lambda m: m[2].jitter_arcsec,
        lambda m: m[2].rotation_deg,
        lambda m: m[2].anisotropy,
    ]
    if not static:
        picks += [
            lambda m: m[0].aperture.global_distortion,
            lambda m: m[0].aperture.hole_distortion,
            lambda m: m[0].aperture.centres_m,
            lambda m: m[0].aperture.flat_to_flat_m,
        ]
    spec = eqx.tree_at(lambda s: [p(s) for p in picks], spec, [True] * len(picks))
    return eqx.partition(model, spec)


def image(model):
    optics, source, detector = model
    return detector(optics.illuminance(source.spectrum, source.position_arcsec), source.flux)


def timed(fn, *args, repeats: int) -> tuple[float, float]:
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times), 1e3 * statistics.median(times)


def run_case(filter_name, config, static, dtype, repeats):
    with jax.enable_x64(dtype == "float64"):
        model = build(filter_name, config, static)
        data = jax.lax.stop_gradient(image(model)) * 1.01
        params, rest = fittable(model, static)

        forward = eqx.filter_jit(image)

        @eqx.filter_jit
        def loss_and_grad(params, rest):
            def loss(p):
                return jnp.sum((image(eqx.combine(p, rest)) - data) ** 2)

            return eqx.filter_value_and_grad(loss)(params)

        n_params = sum(x.size for x in jax.tree.leaves(params))
        fwd = timed(forward, model, repeats=repeats)
        grad = timed(loss_and_grad, params, rest, repeats=repeats)
        return n_params, fwd, grad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--filter", default="F430M")
    parser.add_argument("--quick", action="store_true", help="default configuration only")
    args = parser.parse_args()

    device = jax.devices()[0]
    print(f"# amigo optics benchmark: {args.filter}, 9 wavelengths, SUB80 at 3x (240x240)")
    print(
        f"# jax {jax.__version__} on {device.platform} ({device.device_kind}); "
        f"{os.cpu_count()} CPU cores; {platform.processor() or platform.machine()}; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    base = OpticsConfig()
    cases = [
        ("pupil", 128, static, dtype)
        for static in (True, False)
        for dtype in ("float32", "float64")
    ]
    if args.quick:
        cases = cases[:1]
    else:
        cases += [
            ("angular_spectrum", 128, True, "float32"),
            ("angular_spectrum", 128, False, "float32"),
            ("pupil", 96, True, "float32"),
            ("pupil", 256, True, "float32"),
        ]
    print(
        "| defocus | pupil px | mask | dtype | parameters | image ms (min / median) "
        "| image + gradient ms (min / median) |"
    )
    print("|---|---|---|---|---|---|---|")
    for method, npix, static, dtype in cases:
        config = dataclasses.replace(base, defocus_method=method, pupil_npix=npix)
        n, fwd, grad = run_case(args.filter, config, static, dtype, args.repeats)
        mask = "static" if static else "dynamic"
        print(
            f"| {method} | {npix} | {mask} | {dtype} | {n} | {fwd[0]:.1f} / {fwd[1]:.1f} "
            f"| {grad[0]:.1f} / {grad[1]:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
