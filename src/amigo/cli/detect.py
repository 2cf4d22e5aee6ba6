"""``amigo detect FILE... --out DIR``: companion search, posteriors and contrast limits."""

from __future__ import annotations

import click

from amigo.pipeline._detect import MIN_RMAX_MAS

#: ``--rmax-mas``, shared by ``detect`` and ``run``.
rmax_option = click.option(
    "--rmax-mas",
    type=click.FloatRange(min=MIN_RMAX_MAS),
    default=1000.0,
    show_default=True,
    help="Search radius (mas).",
)
#: ``--step-mas``, shared by ``detect`` and ``run``.
step_option = click.option(
    "--step-mas",
    type=click.FloatRange(min=0.1),
    default=None,
    help="Grid step (mas); default lambda_min / (5 B_max).",
)


@click.command(name="detect")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder (created if needed).",
)
@rmax_option
@click.option(
    "--threshold",
    type=click.FloatRange(min=0.0, min_open=True),
    default=5.0,
    show_default=True,
    help="Detection threshold (Gaussian-equivalent sigma).",
)
@step_option
@click.option(
    "--max-companions",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    help="Stop after this many companions.",
)
@click.option(
    "--observables",
    type=click.Choice(["all", "phase", "amplitude"]),
    default="all",
    show_default=True,
    help="Observables to fit: all, phase-type only (kernel or closure phases: for OIFITS "
    "whose V2 are poorly calibrated) or amplitude-type only.",
)
@click.option(
    "--cp-correlation",
    type=click.Choice(["baseline", "independent"]),
    default="baseline",
    show_default=True,
    help="OIFITS closure phases without covariance: correlated through shared "
    "baselines, or independent.",
)
@click.option(
    "--primary-diameter-mas",
    type=click.FloatRange(min=0.0),
    default=0.0,
    show_default=True,
    help="Uniform-disc diameter of the primary (0: unresolved).",
)
@click.option("--no-hmc", is_flag=True, help="Skip NUTS; report least-squares (Laplace) errors.")
@click.option("--no-per-filter", is_flag=True, help="Skip the per-filter fits.")
@click.option(
    "--warmup",
    type=click.IntRange(min=10),
    default=None,
    help="NUTS warm-up steps per chain [default: 150, tuning the step size with Laplace's "
    "covariance as the mass matrix; 500, adapting the mass matrix, where that covariance "
    "is not positive definite].",
)
@click.option(
    "--samples",
    type=click.IntRange(min=10),
    default=1000,
    show_default=True,
    help="NUTS samples per chain, at most (see --ess).",
)
@click.option(
    "--ess",
    type=click.IntRange(min=0),
    default=400,
    show_default=True,
    help="Stop drawing NUTS samples once every parameter's mean and error percentiles "
    "have this effective sample size (0: draw all --samples).",
)
@click.option(
    "--chains", type=click.IntRange(min=1), default=2, show_default=True, help="NUTS chains."
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed of NUTS.")
@click.option(
    "--force",
    is_flag=True,
    help="Search again [default: keep the products in DIR when its companions.json records "
    "the same input files, options and version].",
)
def command(
    files: tuple[str, ...],
    out_dir: str,
    rmax_mas: float,
    threshold: float,
    step_mas: float | None,
    max_companions: int,
    observables: str,
    cp_correlation: str,
    primary_diameter_mas: float,
    no_hmc: bool,
    no_per_filter: bool,
    warmup: int | None,
    samples: int,
    chains: int,
    seed: int,
    ess: int = 400,
    force: bool = False,
) -> None:
    """Search calibrated observables (calvis or OIFITS FILEs) for companions.

    Writes DIR/companions.json, DIR/contrast_limits.csv, DIR/contrast_maps.fits and
    figures (DIR/*.png).
    """
    from amigo.pipeline import detect

    detect(
        files,
        out_dir,
        rmax_mas=rmax_mas,
        threshold=threshold,
        step_mas=step_mas,
        max_companions=max_companions,
        observables=observables,
        cp_correlation=cp_correlation,
        primary_diameter_mas=primary_diameter_mas,
        hmc=not no_hmc,
        per_filter=not no_per_filter,
        warmup=warmup,
        samples=samples,
        chains=chains,
        seed=seed,
        force=force,
        ess=ess,
    )
