"""Time to fit one exposure and one science/calibrator pair (``amigo fit`` machinery).

Synthetic level-2 images of one filter (default F480M, 9 wavelengths, the default 51 x 51
knot grid) are made with the optics of issue 3: a single-star calibrator and a binary
science target. Prints a table of wall times on this machine: basis (load or build), the
fit of one exposure (including the compilation of the model), its float64 Hessians, and
the whole extraction of a pair (compiled by then). ``benchmarks/fit_com1093.py`` times
``amigo fit`` on real pairs, as a user runs it.

    python benchmarks/fit.py [--filter F480M] [--iterations N]

The fit settings are ``amigo fit``'s defaults (:class:`amigo.fitting.filter_fit.FitConfig`) unless
``--iterations`` changes the number of natural-gradient iterations before the
Levenberg-Marquardt finish.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import jax.numpy as jnp
import numpy as np

from amigo.fitting.filter_fit import FilterFit, FitConfig, FitExposure, latent_information
from amigo.likelihood.pixels import ImageData
from amigo.model.basis import load_basis
from amigo.model.image import FilterSetup, Instrument
from amigo.model.optics import LinearSpectrum, NRMOptics
from amigo.observables.extract import extract_filter


def scene(instrument, filter_name, sources, photons, rng):
    optics = NRMOptics.create(zernikes_nm=jnp.asarray(rng.normal(0, 3.0, (7, 10))))
    spectrum = LinearSpectrum.from_filter(filter_name, instrument.n_wavelengths)
    ill = sum(f * optics.illuminance(spectrum, jnp.asarray(p)) for p, f in sources)
    model = np.asarray(instrument.detector(ill, photons), float)
    sigma = np.sqrt(model.clip(0) + 100.0)
    mask = np.ones(model.shape, bool)
    mask[:4] = False
    return ImageData(model + sigma * rng.normal(size=model.shape), sigma, mask)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filter", default="F480M")
    parser.add_argument("--iterations", type=int, default=FitConfig().max_iterations)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    instrument = Instrument.nominal()
    rows = []

    t = time.perf_counter()
    basis, info = load_basis(instrument, args.filter)
    rows.append(
        ("basis (load or build)", time.perf_counter() - t, f"{info.n_amp}+{info.n_phase} modes")
    )
    cal = scene(instrument, args.filter, [((0.01, 0.02), 1.0)], 1e8, rng)
    sci = scene(
        instrument, args.filter, [((0.0, 0.0), 1 / 1.01), ((0.12, 0.09), 0.01 / 1.01)], 1e8, rng
    )
    config = FitConfig(max_iterations=args.iterations)

    # One exposure: a calibrator alone (wavefront, visibilities, position, flux). The first
    # fit in the process includes the compilation of every jitted function.
    setup = FilterSetup.create(args.filter, instrument, basis)
    fit = FilterFit(instrument, setup, [FitExposure("cal", "calibrator", "CAL", cal)])
    result = fit.fit(config)
    t = time.perf_counter()
    latent_information(
        fit, result.params, fisher=result.fisher, exact_exposures=result.exact_exposures
    )
    t_hess = time.perf_counter() - t
    rows.append(
        (
            "1 exposure: fit (incl. compilation)",
            result.seconds,
            f"{result.iterations} Jacobians, converged={result.converged}",
        )
    )
    rows.append(("1 exposure: float64 Hessian + nuisances", t_hess, ""))
    rows.append(("1 exposure: total", result.seconds + t_hess, ""))

    # A science/calibrator pair, the whole extraction (fit, Hessians, kernel, DISCOs).
    t = time.perf_counter()
    product = extract_filter(
        instrument,
        args.filter,
        [FitExposure("cal", "calibrator", "CAL", cal), FitExposure("sci", "science", "SCI", sci)],
        config,
    )
    rows.append(
        (
            "pair: fit + DISCOs",
            time.perf_counter() - t,
            f"{product.result.iterations} Jacobians, converged={product.result.converged}",
        )
    )

    print(
        f"\namigo fit benchmark, {args.filter}, {instrument.n_wavelengths} wavelengths, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"jax {jax.__version__} on {jax.default_backend()}"
    )
    print(f"{'step':45s} {'seconds':>9s}  notes")
    for name, seconds, note in rows:
        print(f"{name:45s} {seconds:9.1f}  {note}")


if __name__ == "__main__":
    main()
