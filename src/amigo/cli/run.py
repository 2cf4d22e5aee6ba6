"""``amigo run --sci UNCAL... --cal UNCAL... --out DIR``: process, fit and detect in one go.

Everything is written directly under ``DIR``, with the names of the individual commands
(docs/interfaces): ``<stem>_calslope.fits`` (``amigo process``), the calvis, OIFITS,
``fit_summary.json`` and ``plots/`` (``amigo fit``), ``companions.json``,
``contrast_limits.csv`` and the detection figures (``amigo detect``).
"""

from __future__ import annotations

from pathlib import Path

import click

from amigo.cli.fit import exposures_option, model_options, superbias_option
from amigo.errors import InputError


def pipeline(
    ctx: click.Context,
    sci: tuple[Path, ...],
    cal: tuple[Path, ...],
    out: Path,
    *,
    model: Path | None = None,
    detector: str | None = None,
    knots: int | None = None,
    knot_spacing: float | None = None,
    rmax_mas: float = 1000.0,
    no_hmc: bool = False,
    superbias: tuple[Path, ...] = (),
    no_first_group: bool = False,
    force: bool = False,
) -> tuple[list[Path], int]:
    """Run process -> fit -> detect; return the calvis files that were searched and the
    exit status of the fit (:mod:`amigo.cli.fit_outcome`; detect is skipped when no
    filter has products).
    ``superbias``: raw ramps (darks) processed with the rest and given to ``amigo fit
    --superbias``, so the first group's photons enter the fit; ``no_first_group`` as
    ``amigo fit --no-first-group``; ``force``: process, fit and search everything again
    (``--force`` of each command; by default complete products of the same inputs are
    kept)."""
    from amigo.cli import detect, fit, process
    from amigo.io.calslope import calslope_name
    from amigo.progress import step

    overlap = set(sci) & set(cal)
    if overlap:
        raise InputError(sorted(overlap)[0], "is given both as --sci and --cal")
    inputs = tuple(dict.fromkeys((*sci, *cal, *superbias)))
    step(f"run: processing {len(inputs)} raw exposures")
    ctx.invoke(process.command, uncal=inputs, out_dir=out, force=force)
    slopes = {path: out / calslope_name(path) for path in inputs}
    step("run: fitting")
    status = ctx.invoke(
        fit.command,
        sci=tuple(slopes[p] for p in sci),
        cal=tuple(slopes[p] for p in cal),
        out=out,
        model=model,
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        superbias=tuple(slopes[p] for p in superbias),
        no_first_group=no_first_group,
        force=force,
    )
    # The products of this fit, as its summary lists them (not every calvis file in OUT:
    # one of an earlier fit of a filter that failed this time is not this run's).
    calvis = fitted_calvis(out)
    if not calvis:
        if status:
            return calvis, status  # fit_summary.json and the warnings say why
        raise InputError(out, "amigo fit wrote no calvis file (no science exposure?)")
    step(f"run: searching {len(calvis)} calvis file(s) for companions")
    ctx.invoke(
        detect.command,
        files=tuple(calvis),
        out_dir=out,
        rmax_mas=rmax_mas,
        no_hmc=no_hmc,
        force=force,
    )
    return calvis, status


def fitted_calvis(out: Path) -> list[Path]:
    """The calvis files of the usable filters in ``out/fit_summary.json``, in filter
    order."""
    from amigo.cli.fit_outcome import USABLE, previous_summary

    filters = previous_summary(out).get("filters", {})
    return [
        out / name
        for _, record in sorted(filters.items())
        if record.get("status") in USABLE
        for name in record.get("products", [])
        if name.endswith("_calvis.fits")
    ]


@click.command("run")
@exposures_option(
    "sci", "Raw science ramps (_uncal.fits; several after one flag, or the flag repeated)."
)
@exposures_option("cal", "Raw calibrator ramps (_uncal.fits; several after one flag, or repeated).")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@model_options
@click.option("--rmax-mas", type=float, default=1000.0, show_default=True, help="Search radius.")
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
@click.pass_context
def command(
    ctx: click.Context,
    sci: tuple[Path, ...],
    cal: tuple[Path, ...],
    out: Path,
    model: Path | None,
    detector: str | None,
    knots: int | None,
    knot_spacing: float | None,
    rmax_mas: float,
    no_hmc: bool,
    superbias: tuple[Path, ...] = (),
    no_first_group: bool = False,
    force: bool = False,
) -> None:
    """Raw ramps to companions: amigo process, amigo fit and amigo detect in one go.

    All outputs go directly under OUT, named as by the individual commands. Exit status
    as amigo fit's (3: some filters without products, 4: none).
    """
    _, status = pipeline(
        ctx,
        sci,
        cal,
        out,
        model=model,
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        rmax_mas=rmax_mas,
        no_hmc=no_hmc,
        superbias=superbias,
        no_first_group=no_first_group,
        force=force,
    )
    return status
