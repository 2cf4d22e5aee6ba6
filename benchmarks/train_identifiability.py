"""What dithered level-2 calibrator images can tell about the optics `amigo train` fits
(prints a table; docs/detector.md, "What dithered level-2 images identify").

    python benchmarks/train_identifiability.py [--dither 0.15] [--exposures 8]
        [--shape 40] [--pupil 64] [--wavelengths 3] [--flux 4e5] [--photons-per-dn 1000]
        [--hold centres sizes defocus geometry]

Builds a level-2 model (``BaseModel.create(...).for_level2()``, F430M, no network) with
an aberrated truth, and the Fisher information of the parameters training updates as
physical (``amigo.training.groups.physical_mask``: per-hole Noll Zernikes, defocus, hole
centres and sizes, the detector's jitter and geometry, the intra-pixel response) from
``--exposures`` point-source images at dither offsets of up to ``--dither`` arcsec, each
pixel's variance ``4 + model / photons_per_dn`` (DN per group squared). For each Zernike
mode it prints the standard error with every physical parameter free (what training
can learn; ``--hold`` fixes some of them), with only the Zernikes free, and with everything else fixed; and how many
of the Fisher matrix's eigenvalues (in its unit-free correlation form) are below 1e-6:
directions the images barely see. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def standard_errors(fisher: np.ndarray, pistons: np.ndarray, rtol: float = 1e-6) -> np.ndarray:
    """Marginal standard errors from a Fisher matrix, ``inf`` for a parameter with any
    part in a direction the data do not see. The mean of the ``pistons`` (indices) is
    pinned first: the model removes it, so it is an exact null direction, and the
    pistons' errors are then about those relative to their mean (the pin adds
    ``1 / (n mean diag)`` to each piston's variance, a few per cent). The matrix is inverted in its
    correlation form (unit-free: hole centres in metres beside Zernikes in nm), keeping
    eigenvalues above ``rtol`` of the largest (the Fisher matrix is float32 arithmetic: below
    ~1e-6 an eigenvalue is round-off); a plain pseudo-inverse would instead
    invert round-off (a tiny negative eigenvalue gives a negative variance) or drop an
    unseen direction's variance (zero instead of unbounded)."""
    matrix = fisher.copy()
    matrix[np.ix_(pistons, pistons)] += np.mean(np.diag(fisher)[pistons]) / pistons.size
    scale = np.sqrt(np.diag(matrix))
    seen = scale > 0
    unit = matrix[np.ix_(seen, seen)] / np.outer(scale[seen], scale[seen])
    values, vectors = np.linalg.eigh(unit)
    keep = values > rtol * values.max()
    variance = (vectors[:, keep] ** 2 / values[keep]).sum(axis=1)
    hidden = (vectors[:, ~keep] ** 2).sum(axis=1) > 1e-6
    errors = np.full(fisher.shape[0], np.inf)
    errors[seen] = np.where(hidden, np.inf, np.sqrt(variance) / scale[seen])
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dither", type=float, default=0.15, help="largest offset (arcsec)")
    parser.add_argument("--exposures", type=int, default=8, choices=range(1, 10))
    parser.add_argument("--shape", type=int, default=40, help="image side (pixels)")
    parser.add_argument("--pupil", type=int, default=64, help="pupil grid (pixels)")
    parser.add_argument("--wavelengths", type=int, default=3)
    parser.add_argument("--flux", type=float, default=4e5, help="electrons per integration")
    parser.add_argument("--photons-per-dn", type=float, default=1000.0)
    parser.add_argument("--aberration", type=float, default=40.0, help="truth, nm rms")
    parser.add_argument(
        "--hold",
        nargs="*",
        default=[],
        choices=["centres", "sizes", "defocus", "geometry"],
        help="parameters held at the truth in the first column (hole centres, hole sizes, "
        "the Fresnel defocus, the detector's rotation, anisotropy, skew and scale)",
    )
    args = parser.parse_args()

    import equinox as eqx
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from amigo.likelihood.slopes import PointSourceParams, SlopeData, point_source_slopes
    from amigo.model.base import BaseModel, BaseModelConfig
    from amigo.training.fisher import fisher_matrix
    from amigo.training.groups import physical_mask, split

    start = time.perf_counter()
    n = args.shape
    config = BaseModelConfig(
        filters=("F430M",),
        shape=(n, n),
        pupil_npix=args.pupil,
        n_wavelengths=args.wavelengths,
        dark_residual_groups=0,
    )
    base = BaseModel.create(config, linear=True).for_level2()
    rng = np.random.default_rng(5)
    truth = np.zeros(base.zernikes_nm["F430M"].shape)
    truth[:, :4] = rng.normal(0.0, args.aberration, (truth.shape[0], 4))  # Noll 1-4
    base = eqx.tree_at(lambda m: m.zernikes_nm["F430M"], base, jnp.asarray(truth, jnp.float32))
    cache = base.pupil_cache()
    s = args.dither
    offsets = [(0, 0), (-s, -s), (s, -s), (-s, s), (s, s), (s, 0), (-s, 0), (0, s), (0, -s)]
    tgroup = 0.07544
    blank = np.ones((n, n))
    mask = physical_mask(base, "F430M")
    vector, unravel = ravel_pytree(split(base, physical_mask(base)))
    index = unravel(jnp.arange(vector.size, dtype=vector.dtype))
    columns = np.asarray(ravel_pytree(eqx.filter(index, mask))[0]).astype(int)
    where = {c: k for k, c in enumerate(columns)}
    zernikes = np.vectorize(where.get)(np.asarray(index.zernikes_nm["F430M"]).astype(int))
    fisher = np.zeros((columns.size, columns.size))
    for k, offset in enumerate(offsets[: args.exposures]):
        source = PointSourceParams(jnp.asarray(offset, jnp.float32), jnp.asarray(args.flux))
        layout = SlopeData.from_rate_image(
            blank, blank, blank > 0, ngroups=5, group_time_s=tgroup, filter_name="F430M"
        )
        model = np.asarray(point_source_slopes(base, cache, source, layout), np.float64)[0]
        error = np.sqrt(4.0 + np.abs(model) / args.photons_per_dn)
        data = SlopeData.from_rate_image(
            model / tgroup,
            error / tgroup,
            blank > 0,
            ngroups=5,
            group_time_s=tgroup,
            filter_name="F430M",
            name=f"dither{k}",
        )
        f, _ = fisher_matrix(base, source, data, cache, mask)
        fisher += np.asarray(f, np.float64)

    held_leaves = {
        "centres": [index.hole_centres_m],
        "sizes": [index.hole_sizes_m],
        "defocus": [index.defocus_nm["F430M"]],
        "geometry": [
            index.detector.rotation_deg,
            index.detector.anisotropy,
            index.detector.skew_deg,
            index.detector.scale,
        ],
    }
    held = {
        where[int(i)]
        for name in args.hold
        for leaf in held_leaves[name]
        for i in np.ravel(np.asarray(leaf))
        if int(i) in where
    }
    kept = np.array([k for k in range(columns.size) if k not in held])
    position = {k: j for j, k in enumerate(kept)}
    reduced = fisher[np.ix_(kept, kept)]
    errors = standard_errors(reduced, np.vectorize(position.get)(zernikes[:, 0]))
    free = errors[np.vectorize(position.get)(zernikes)].mean(axis=0)
    block = zernikes.ravel()
    alone = standard_errors(
        fisher[np.ix_(block, block)], np.arange(0, block.size, zernikes.shape[1])
    )
    alone = alone.reshape(zernikes.shape).mean(axis=0)
    fixed = (1.0 / np.sqrt(np.clip(np.diag(fisher), 1e-300, None)))[zernikes].mean(axis=0)
    scale = np.sqrt(np.clip(np.diag(fisher), 1e-300, None))
    eigenvalues = np.linalg.eigvalsh(fisher / np.outer(scale, scale))
    print(
        f"\n{args.exposures} level-2 images, {n}x{n} pixels, dithers up to {s} arcsec, "
        f"{args.wavelengths} wavelengths, pupil {args.pupil}; truth {args.aberration} nm rms "
        f"in Noll 1-4 per hole; {columns.size} physical parameters; "
        f"{time.perf_counter() - start:.0f} s"
    )
    first = "every physical parameter free"
    if args.hold:
        first = f"free but {', '.join(args.hold)}"
    print(f"| Noll mode | {first} | Zernikes alone free | all else fixed |")
    print("|---|---|---|---|")
    for j in range(zernikes.shape[1]):
        print(f"| {j + 1} | {free[j]:.2f} nm | {alone[j]:.2f} nm | {fixed[j]:.3f} nm |")
    print(
        f"eigenvalues of the Fisher matrix in correlation form below 1e-6 (directions the "
        f"images barely see): {(eigenvalues < 1e-6).sum()} of {eigenvalues.size}"
    )
    print(
        "(each hole's error averaged over the 7 holes; pistons relative to their mean, which the "
        "model removes; inf: partly in a direction the images do not see)"
    )


if __name__ == "__main__":
    main()
