"""``amigo basis``: build (or find) the latent visibility bases and plot their spectra."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("basis")
@click.option(
    "--filter",
    "filters",
    multiple=True,
    type=click.Choice(["F380M", "F430M", "F480M", "F277W"], case_sensitive=False),
    help="Filter (repeat; default: the three calibrated filters).",
)
@click.option(
    "--model",
    type=click.Path(path_type=Path),
    default=None,
    help="Base model file (default: the nominal instrument).",
)
@click.option(
    "--plots",
    type=click.Path(path_type=Path),
    default=None,
    help="Folder for the eigenvalue-spectrum figures (default: the cache folder).",
)
def command(filters: tuple[str, ...], model: Path | None, plots: Path | None) -> None:
    """Build the latent visibility basis of each filter and cache it.

    Prints the number of modes kept per filter and writes a figure of the eigenvalue
    spectrum with the truncation marked. Bases are cached (see docs/fit.md), so `amigo fit`
    does not rebuild them.
    """
    from amigo.pipeline import bases

    for report in bases(filters, model=model, plots=plots):
        info = report.info
        click.echo(
            f"{report.filter_name}: {info.n_amp} amplitude + {info.n_phase} phase modes "
            f"({info.n_knots_support} knots inside the OTF support; key {info.key}); "
            f"spectrum: {report.figure}"
        )
