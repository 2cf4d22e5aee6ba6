"""The 1/f stripe correction of ``amigo process`` on the project's simulator (prints a table).

    python benchmarks/one_over_f.py [--nints 30] [--ngroups 8] [--filter F430M]
                                    [--peaks 30000,3000] [--seed 0]

A single star (the analytic NRM image, the exposure's brightest pixel at ``peak`` DN at
the last group) is simulated with the full default detector physics
(:class:`amigo.simulation.detector.DetectorConfig`: photon and read noise, BFE, IPC,
non-linearity, cosmic rays, ADC, ...) twice from the same seeds: with 1/f noise
(``one_over_f_dn`` = 1.5 DN per column and group) and without. Each is processed with
``ProcessSettings(one_over_f="none")`` and ``"stripes"``. The truth is the simulator's
noiseless ramp (the same detector with every random effect, the bias and the ADC
non-linearity off), whose group differences are the expected slopes.

Columns, over the good pixels outside the reference rows and all slopes: ``z`` =
(slope - truth) / sqrt(reported variance); its standard deviation and mean; the same for
the faint pixels (truth below 20 DN per group, where 1/f matters most); ``col z``: the
standard deviation over columns and slopes of ``sum(z) / sqrt(n)`` over a column's faint
pixels, which is 1 when the pixels' errors are independent (what the likelihood
assumes) and grows with errors shared along a column (below 1: the correction also
removes the mean-free part of each column's own noise, since the faint pixels are the
ones it measures the stripes with); ``stripes``: the RMS over columns and slopes of the
1/f offsets left in the mean slopes (DN per group), from the simulator's own 1/f draws
(recorded) minus what the correction removed (the column median of the slope change);
``sigma``: the median reported slope error of the faint pixels (DN per group); ``1/f
var``: the stripes' variance the correction measured (DN^2, mean-free per difference)
and the median gain it applied. Not a test: nothing is asserted. About a minute on a
2-core CPU.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from amigo import niriss
from amigo.processing.ramps import ArraySource, ProcessSettings, SlopeProduct, process_ramps
from amigo.simulation import detector as simulator_detector
from amigo.simulation.detector import DetectorConfig, RampSimulator, draw_detector
from amigo.simulation.illumination import AnalyticNRM
from amigo.simulation.scene import REFERENCE_PIXEL_XY, DetectorScene, DetectorSource
from amigo.simulation.state import StateSpread, draw_instrument_state

FAINT_DN = 20.0


def simulate(
    rate: np.ndarray, config: DetectorConfig, realisation, ngroups: int, nints: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """(nints, ngroups, 80, 80) raw counts, and the 1/f offsets in the mean slopes
    (ngroups - 1, 80 columns; zero without 1/f), DN per group."""
    recorded: list[np.ndarray] = []
    original = simulator_detector.one_over_f_columns

    def recording(*args, **kwargs):
        columns = original(*args, **kwargs)
        recorded.append(columns)
        return columns

    simulator = RampSimulator(rate, 4, realisation, config, ngroups)
    rng = np.random.default_rng(seed)
    simulator_detector.one_over_f_columns = recording
    try:
        raw = np.stack([simulator.integration(rng)[0] for _ in range(nints)])
    finally:
        simulator_detector.one_over_f_columns = original
    stripes = np.zeros((ngroups - 1, 80))
    if recorded:
        stripes = np.diff(np.stack(recorded), axis=1).mean(axis=0)
    return raw.astype(np.float64), stripes


def truth_slopes(rate: np.ndarray, realisation, ngroups: int) -> np.ndarray:
    """(ngroups - 1, 80, 80) expected group differences (DN per group)."""
    config = DetectorConfig.noiseless(bias=False, adc_inl=False)
    ramp, _ = RampSimulator(rate, 4, realisation, config, ngroups).integration(
        np.random.default_rng(0)
    )
    return np.diff(ramp, axis=0)


def scores(product: SlopeProduct, truth: np.ndarray, stripes_left: np.ndarray) -> dict[str, float]:
    sigma = np.sqrt(np.einsum("kkyx->kyx", product.slope_cov_dn2))
    z = (product.slope_dn - truth) / sigma
    good = ~product.badpix & ~niriss.reference_row_mask()
    faint = good & (truth.mean(axis=0) < FAINT_DN)
    column = np.where(faint, z, 0.0).sum(axis=1) / np.sqrt(faint.sum(axis=0))
    column = column[:, faint.sum(axis=0) >= 10]
    stripes = product.stripes
    return {
        "z std": float(z[:, good].std()),
        "z mean": float(z[:, good].mean()),
        "faint z std": float(z[:, faint].std()),
        "col z": float(column.std()),
        "stripes": float(np.sqrt(np.mean(stripes_left**2))),
        "sigma": float(np.median(sigma[:, faint])),
        "faint px": float(faint.sum()),
        "var": stripes.variance_dn2 if stripes is not None else float("nan"),
        "gain": float(np.median(stripes.gain)) if stripes is not None else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nints", type=int, default=30)
    parser.add_argument("--ngroups", type=int, default=8)
    parser.add_argument("--filter", default="F430M")
    parser.add_argument("--peaks", default="30000,3000", help="brightest pixel, DN at last group")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    start = time.perf_counter()
    state = draw_instrument_state(np.random.default_rng(args.seed), StateSpread())
    x0, y0 = REFERENCE_PIXEL_XY
    unit = AnalyticNRM(n_wavelengths=9).render(
        DetectorScene((DetectorSource(x0 + 0.12, y0 - 0.27, 1.0),)), args.filter, state, 4
    )
    pixels = unit.reshape(80, 4, 80, 4).sum(axis=(1, 3))
    config = DetectorConfig()
    realisation = draw_detector(np.random.default_rng(args.seed + 1), config)
    print(
        f"{args.filter}, {args.nints} integrations x {args.ngroups} groups, 1/f "
        f"{config.one_over_f_dn} DN per column and group, read noise {config.read_noise_dn} DN, "
        f"seed {args.seed}"
    )
    header = (
        f"{'peak DN':>8} {'1/f':>4} {'correction':>10} {'z std':>6} {'z mean':>7} "
        f"{'faint z std':>11} {'col z':>6} {'stripes':>7} {'sigma':>6} {'1/f var':>8} "
        f"{'gain':>5}"
    )
    print(header)
    print("-" * len(header))
    for peak in (float(p) for p in args.peaks.split(",")):
        rate = (
            unit * peak * niriss.GAIN_E_PER_DN / (pixels.max() * args.ngroups * niriss.GROUP_TIME_S)
        )
        truth = truth_slopes(rate, realisation, args.ngroups)
        for one_over_f in (True, False):
            raw, injected = simulate(
                rate,
                config.replace(one_over_f=one_over_f),
                realisation,
                args.ngroups,
                args.nints,
                args.seed + 2,
            )
            plain = None
            for method in ("none", "stripes"):
                product = process_ramps(ArraySource(raw), ProcessSettings(one_over_f=method))
                plain = product if plain is None else plain
                # The correction is one offset per column: the column median of the change.
                good = ~product.badpix & ~plain.badpix
                change = np.where(good, plain.slope_dn - product.slope_dn, np.nan)
                removed = np.nanmedian(change, axis=1)
                s = scores(product, truth, injected - removed)
                print(
                    f"{peak:>8.0f} {'on' if one_over_f else 'off':>4} {method:>10} "
                    f"{s['z std']:>6.3f} {s['z mean']:>+7.3f} {s['faint z std']:>11.3f} "
                    f"{s['col z']:>6.2f} {s['stripes']:>7.3f} {s['sigma']:>6.3f} "
                    f"{s['var']:>8.2f} {s['gain']:>5.2f}"
                )
        print(f"{'':>8} faint pixels (truth < {FAINT_DN:g} DN/group): {s['faint px']:.0f}")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
