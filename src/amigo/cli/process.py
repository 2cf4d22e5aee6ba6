"""``amigo process UNCAL... --out DIR``: raw ramps -> ``DIR/<stem>_calslope.fits``.

Each file is processed on its own: a bad input prints one line naming it and the others
are still processed; the exit status is 2 at the end if any file failed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.command("process")
@click.argument("uncal", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the calslope files (created if needed).",
)
@click.option(
    "--sigma",
    default=3.0,
    show_default=True,
    type=click.FloatRange(min=0, min_open=True),
    help="Outlier clipping threshold, in robust standard deviations.",
)
@click.option(
    "--no-adc",
    is_flag=True,
    help="Do not correct the ADC integral non-linearity (always correct it for science).",
)
@click.option(
    "--saturation-dn",
    default=None,
    type=click.FloatRange(min=0, min_open=True),
    help="Raw count at which a group is saturated [default: 65535, the ADC full scale].",
)
@click.option(
    "--one-over-f",
    "one_over_f",
    default="stripes",
    show_default=True,
    type=click.Choice(["stripes", "none"]),
    help="1/f noise: remove each column's offset per integration and group difference, "
    "measured on the faint pixels and reference rows (stripes), or leave it (none).",
)
@click.option(
    "--force",
    is_flag=True,
    help="Process every file again [default: skip a file whose calslope product is "
    "complete and records this input, these options and this amigo version].",
)
def command(
    uncal: tuple[Path, ...],
    out_dir: Path,
    sigma: float,
    no_adc: bool,
    saturation_dn: float | None,
    one_over_f: str,
    force: bool = False,
) -> None:
    """Reduce raw ramps (uncal files) to mean slopes and their covariance (calslope files).

    Corrects the ADC non-linearity, removes 1/f column stripes, rejects outliers (cosmic
    rays) at SIGMA along the integrations, first on the ramps then on the slopes, and
    writes means, covariances of the means, supports and a bad-pixel map
    (docs/process.md).
    """
    from amigo.pipeline import process

    result = process(
        uncal,
        out_dir,
        sigma=sigma,
        adc=not no_adc,
        saturation_dn=saturation_dn,
        one_over_f=one_over_f,
        force=force,
    )
    if result.failed:  # each named on its own line already: the interface's one line
        sys.exit(2)
