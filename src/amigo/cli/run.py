"""``amigo run --sci UNCAL... --cal UNCAL... --out DIR``: process, fit and detect in one go
(level-2 images or calslope files instead of raw ramps: fit and detect, in one process).

Everything is written directly under ``DIR``, with the names of the individual commands
(docs/interfaces): ``<stem>_calslope.fits`` (``amigo process``), the calvis, OIFITS,
``fit_summary.json`` and ``plots/`` (``amigo fit``), ``companions.json``,
``contrast_limits.csv``, ``contrast_maps.fits`` and the detection figures (``amigo
detect``).

``amigo run --manifest targets.toml --out DIR [--workers N | --scheduler ADDRESS]``: every
target of the manifest (:mod:`amigo.io.manifest`) into ``DIR/<name>/``, in parallel on
Dask distributed, with a summary table (:mod:`amigo.pipeline._manifest`).
"""

from __future__ import annotations

from pathlib import Path

import click

from amigo.cli.detect import rmax_option, step_option
from amigo.cli.fit import exposures_option, model_options, superbias_option


@click.command("run")
@exposures_option(
    "sci",
    "Science exposures: raw ramps (_uncal.fits), or level-2 images / calslope files, "
    "which skip processing (several after one flag, or the flag repeated).",
    required=False,
)
@exposures_option(
    "cal",
    "Calibrator exposures, as --sci (several after one flag, or repeated).",
    required=False,
)
@click.option(
    "--manifest",
    type=click.Path(path_type=Path),
    default=None,
    help="A TOML list of science/calibrator sets (instead of --sci/--cal): each target "
    "runs into OUT/<name>/, in parallel on Dask (docs/interfaces.md).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="With --manifest: worker processes of the local Dask cluster [default: one per "
    "two CPU cores, at most one per target].",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="With --manifest: run on this existing Dask scheduler (e.g. tcp://host:8786, a "
    "dask-jobqueue cluster's) instead of a local cluster.",
)
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@model_options
@rmax_option
@step_option
@click.option("--no-hmc", is_flag=True, help="Skip the NUTS posterior in the companion search.")
@superbias_option(
    "Raw dark ramps (_uncal.fits) of the same detector: processed with the rest, they give "
    "each pixel's reset level, and the first group's photons enter the fit"
)
@click.option(
    "--force",
    is_flag=True,
    help="Process, fit and search everything again [default: keep complete calslope "
    "products, fitted filters and the search of the same inputs and options, e.g. after "
    "an interruption].",
)
def command(
    sci: tuple[Path, ...],
    cal: tuple[Path, ...],
    out: Path,
    model: Path | None,
    detector: str | None,
    knots: int | None,
    knot_spacing: float | None,
    rmax_mas: float,
    no_hmc: bool,
    step_mas: float | None = None,
    superbias: tuple[Path, ...] = (),
    no_first_group: bool = False,
    force: bool = False,
    manifest: Path | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
) -> int:
    """Raw ramps to companions: amigo process, amigo fit and amigo detect in one go.

    Level-2 images (_cal, _calints, _rateints) or calslope files skip the processing:
    amigo fit and amigo detect in one process.

    All outputs go directly under OUT, named as by the individual commands. Exit status
    as amigo fit's (3: some filters without products, 4: none). With --manifest, each
    target into OUT/<name>/ (3: some targets failed, 4: all).
    """
    if no_first_group and superbias:
        raise click.BadParameter(
            "cannot be combined with --no-first-group", param_hint="--superbias"
        )
    if manifest is not None:
        if sci or cal or superbias:
            raise click.BadParameter(
                "give the exposures in the manifest, not also with --sci/--cal/--superbias",
                param_hint="--manifest",
            )
        if workers is not None and scheduler is not None:
            raise click.BadParameter("cannot be combined with --scheduler", param_hint="--workers")
        from amigo.pipeline import run_manifest

        done = run_manifest(
            manifest,
            out,
            workers=workers,
            scheduler=scheduler,
            force=force,
            model=None if model is None else str(model),
            detector=detector,
            knots=knots,
            knot_spacing=knot_spacing,
            rmax_mas=rmax_mas,
            step_mas=step_mas,
            hmc=not no_hmc,
            first_group=not no_first_group,
        )
        click.echo(done.table())
        click.echo(f"summary: {out / 'manifest_summary.json'}")
        return done.status
    if workers is not None or scheduler is not None:
        raise click.BadParameter("only with --manifest", param_hint="--workers/--scheduler")
    for name, given in (("--sci", sci), ("--cal", cal)):
        if not given:
            raise click.UsageError(f"Missing option '{name}' (or give --manifest).")
    from amigo.pipeline import run

    result = run(
        sci,
        cal,
        out,
        model=model,
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        rmax_mas=rmax_mas,
        step_mas=step_mas,
        hmc=not no_hmc,
        superbias=superbias,
        first_group=not no_first_group,
        force=force,
        keep_products=False,  # files only: each filter's memory is freed after it
    )
    return result.status
