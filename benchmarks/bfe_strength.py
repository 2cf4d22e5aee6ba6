"""The shipped networks' charge migration against an independent brighter-fatter effect.

    python benchmarks/bfe_strength.py [--filters F480M,F430M,F380M] [--fluxes 1,2]
        [--offsets "dx,dy;dx,dy" --nints 7046]

For each shipped base model (the one trained on amigo's simulator, the one trained on
real COM 1093 level-2 files) and filter, the charge its network moves by the last read of
an integration of HD 37093's exposure in that filter (1.66e6 e-/s over the subarray,
NGROUPS 12 / 9 / 4 of 75.44 ms in F480M / F430M / F380M; ``--fluxes`` scales the flux) is
compared with the charge moved by the physical boundary shifts of
``benchmarks/independent_sim.py`` (:func:`migrated_charge`, no amigo code) for the same
illumination (that script's poppy/pysiaf/synphot PSF, 5 wavelengths), flat and
intra-pixel response (the model's own). Printed per row: the peak pixel's charge, the
largest charge moved as a fraction of it, the correlation of the two patterns over the
subarray, and the physical strength (pixels of boundary shift per electron) that moves
as much charge as the network (the least-squares ratio of the patterns at 1e-6).

A network that learned a physical brighter-fatter effect correlates with it and keeps its
strength as the flux grows (the effect is linear in the charge). ~20 s on 2 CPU cores.

``--offsets`` prints the phase table instead (the simulator-trained network, or with
``--account boundary`` amigo's physical account, the star moved by each sub-pixel
offset): the network's strength at each, and the chi2 of the
physics and of what the network leaves of it (scaled by one strength for every offset)
at the depth of ``--nints`` integrations. docs/detector.md, "The charge migration at
each pixel phase".
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import jax.numpy as jnp
import numpy as np

SCRIPT = Path(__file__).resolve().parent / "independent_sim.py"
NGROUPS = {"F480M": 12, "F430M": 9, "F380M": 4}
GROUP_TIME_S = 0.07544
RATE_E_S = 1.66e6  # HD 37093 (COM 1093 obs 15) in the subarray
STAR_SCI = (46.23, 40.69)


def independent_sim():
    spec = importlib.util.spec_from_file_location("independent_sim", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    # A coarser band and a smaller field than the simulation's: the core is what migrates.
    vars(module).update(N_WAVELENGTHS=5, FINE_NPIX=401)
    return module


def compare(
    isim,
    model_path: Path,
    psf: np.ndarray,
    ngroups: int,
    flux: float,
    star: tuple[float, float] = STAR_SCI,
    account: str = "network",
) -> dict:
    """One row: the model's network against the physics at 1e-6 pix/e-, the star at
    ``star`` (1-based science pixels). Also returns the two patterns and the charge
    (``network``, ``physics``, ``charge``: (80, 80) electrons) for the phase table.
    ``account="boundary"``: amigo's physical account (``--detector boundary``, its
    default shape at 1e-6 pix/e-) in the network's place."""
    from amigo.model.base import load_base_model
    from amigo.model.detector.boundary import BoundaryShift

    base = load_base_model(model_path)
    if account == "boundary":
        base = base.with_network(BoundaryShift.create(1.0e-6))
    maps = isim.load_detector_maps(model_path)
    integration_s = ngroups * GROUP_TIME_S
    electrons = RATE_E_S * integration_s * flux
    isim.SUBSAMPLE = 3  # the network's 3 x 3 sub-pixels
    sub3 = isim.pixel_subsamples(psf, star)
    illuminance = (sub3 * (electrons / sub3.sum())).transpose(0, 2, 1, 3).reshape(240, 240)
    illuminance = jnp.asarray(illuminance, jnp.float32)
    linear = base.with_linear_detector().ramp
    charge = np.asarray(linear(illuminance, ngroups))[-1]
    network = np.asarray(base.ramp(illuminance, ngroups))[-1] - charge
    isim.SUBSAMPLE = 5
    sub5 = isim.pixel_subsamples(psf, star)
    sub5 = sub5 * (electrons / integration_s / sub5.sum())
    sub5 = sub5 * isim.intra_pixel_weights(maps["intra"]) * maps["flat"][:, :, None, None]
    physics = isim.migrated_charge(sub5, integration_s, 1.0e-6).ravel()
    return {
        "peak_e": float(charge.max()),
        "moved": float(np.abs(network).max() / charge.max()),
        "correlation": float(np.corrcoef(network.ravel(), physics)[0, 1]),
        "strength": float(network.ravel() @ physics / (physics @ physics)),
        "network": network,
        "physics": physics.reshape(network.shape),
        "charge": charge,
    }


def phase_table(
    isim,
    model_path: Path,
    psf: np.ndarray,
    ngroups: int,
    offsets,
    nints: int,
    account: str = "network",
):
    """Rows for the star at each sub-pixel offset (pixels) from ``STAR_SCI``: the
    network's strength there, and what is left of the physics once the network is scaled
    by one strength for all offsets (the least-squares one over them), as chi2 at the
    depth of ``nints`` integrations (Poisson variance of the last read, summed over the
    subarray); ``chi2_pattern`` is the scaled physics' own chi2 at that depth."""
    rows = [
        compare(isim, model_path, psf, ngroups, 1.0, (STAR_SCI[0] + dx, STAR_SCI[1] + dy), account)
        for dx, dy in offsets
    ]
    num = sum(float(np.sum(r["network"] * r["physics"])) for r in rows)
    den = sum(float(np.sum(r["physics"] ** 2)) for r in rows)
    common = num / den
    for r, (dx, dy) in zip(rows, offsets, strict=True):
        variance = np.maximum(r["charge"], 1.0) / nints
        left = r["network"] - common * r["physics"]
        r["offset"] = (dx, dy)
        r["chi2_left"] = float(np.sum(left**2 / variance))
        r["chi2_pattern"] = float(np.sum((common * r["physics"]) ** 2 / variance))
    return common, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filters", default="F480M,F430M,F380M")
    parser.add_argument("--fluxes", default="1,2")
    parser.add_argument(
        "--offsets",
        default="",
        help='sub-pixel star offsets "dx,dy;dx,dy" (pixels): the phase table instead',
    )
    parser.add_argument("--nints", type=int, default=7046, help="depth of the phase table")
    parser.add_argument(
        "--account",
        choices=("network", "boundary"),
        default="network",
        help="the phase table's account of the migration: the simulator-trained network, "
        "or the physical account of --detector boundary",
    )
    args = parser.parse_args()
    from amigo.model.base import default_model_path, level2_model_path

    models = {"simulator-trained": default_model_path(), "real level-2": level2_model_path()}
    isim = independent_sim()
    rng = np.random.default_rng(0)
    opd = isim.wavefront_m(rng.normal(0.0, isim.ZERNIKE_NM_RMS * 1e-9, size=8))
    amplitude = isim.pupil_amplitude()
    if args.offsets:
        offsets = [tuple(map(float, o.split(","))) for o in args.offsets.split(";")]
        print(f"{args.nints} integrations, chi2 over the 6400 pixels")
        print(
            "| filter | offset (pix) | strength (1e-6) | common | chi2 of scaled physics | chi2 left |"
        )
        print("|---|---|---|---|---|---|")
        for filter_name in args.filters.split(","):
            psf = isim.polychromatic_psf(filter_name, 4500.0, amplitude, opd, 12.0)
            common, rows = phase_table(
                isim,
                default_model_path(),
                psf,
                NGROUPS[filter_name],
                offsets,
                args.nints,
                args.account,
            )
            for r in rows:
                cells = [filter_name, str(r["offset"]), f"{r['strength']:.3f}", f"{common:.3f}"]
                cells += [f"{r['chi2_pattern']:.0f}", f"{r['chi2_left']:.0f}"]
                print("| " + " | ".join(cells) + " |", flush=True)
        return
    print(
        "| filter | model | flux | peak (e-) | moved (of peak) | correlation | strength (1e-6 pix/e-) |"
    )
    print("|---|---|---|---|---|---|---|")
    for filter_name in args.filters.split(","):
        psf = isim.polychromatic_psf(filter_name, 4500.0, amplitude, opd, 12.0)
        for name, path in models.items():
            if path is None:
                continue
            for flux in map(float, args.fluxes.split(",")):
                r = compare(isim, path, psf, NGROUPS[filter_name], flux)
                print(
                    f"| {filter_name} | {name} | {flux:g} | {r['peak_e']:.0f} | "
                    f"{100 * r['moved']:.2f} % | {r['correlation']:.3f} | {r['strength']:.2f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
