"""``amigo fit --sci FILE... --cal FILE... --out DIR``: fit exposures, extract DISCOs.

Writes, per science target and filter, ``<TARGPROP>_<FILTER>_calvis.fits`` and
``<TARGPROP>_<FILTER>.oifits``; and ``fit_summary.json`` and ``plots/*.png`` (see
docs/fit.md and the interfaces contract).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from amigo.cli.options import ManyValues

#: A command function being decorated with options.
FC = TypeVar("FC", bound=Callable[..., Any])


def exposures_option(name: str, text: str, required: bool = True) -> Callable[[FC], FC]:
    """The ``--sci``/``--cal`` option of ``fit`` and ``run``: several files after one flag
    (``--sci A B C``, as a shell glob gives them) or the flag repeated."""
    return click.option(
        f"--{name}",
        name,
        cls=ManyValues,
        required=required,
        type=click.Path(path_type=Path),
        help=text,
    )


def superbias_option(text: str) -> Callable[[FC], FC]:
    """The optional ``--superbias FILE...`` of ``fit`` and ``run`` (several files after
    one flag, or the flag repeated; ``text`` says which files) and ``--no-first-group``."""

    def decorate(command: FC) -> FC:
        command = click.option(
            "--no-first-group",
            "no_first_group",
            is_flag=True,
            help="Fit the group differences only, even where the base model holds a superbias.",
        )(command)
        return click.option(
            "--superbias",
            "superbias",
            cls=ManyValues,
            type=click.Path(path_type=Path),
            default=(),
            help=f"{text} [default: the base model's superbias where it holds one "
            "('amigo train --darks'), else none: slopes only].",
        )(command)

    return decorate


_MODEL_OPTIONS = [
    click.option(
        "--model",
        "model",
        type=click.Path(path_type=Path),
        default=None,
        help="Base model: a trained base model (.npz, e.g. from 'amigo train'), or an "
        "instrument file (default: the shipped base model for calslope files; for level-2 "
        "images the shipped model trained on real level-2 calibrators, or the nominal "
        "instrument where none is shipped).",
    ),
    click.option(
        "--detector",
        type=click.Choice(["full", "linear", "boundary"]),
        default=None,
        help="Detector model: 'boundary' (the default for calslope files: the base "
        "model with its charge-migration network replaced by pixel boundaries moved by "
        "the charge's field, its strength measured in each filter's data; "
        "docs/detector.md), 'full' (the base model's charge-migration network; the "
        "default for level-2 images under a model trained on level-2 images, whose ramp "
        "then goes through the JWST pipeline's slope estimator) or 'linear' (network "
        "off; the default for level-2 images under any other model, fitted as they are).",
    ),
    click.option(
        "--knots",
        type=int,
        default=None,
        help="Knots per axis of the uv grid of the latent visibilities (odd; default 51).",
    ),
    click.option(
        "--knot-spacing",
        type=float,
        default=None,
        help="Spacing of the uv knots in metres (default 0.259).",
    ),
]


def model_options(command: FC) -> FC:
    """The fit-model options ``--model``, ``--detector``, ``--knots``, ``--knot-spacing``
    shared by ``fit`` and ``run``."""
    for option in reversed(_MODEL_OPTIONS):
        command = option(command)
    return command


@click.command("fit")
@exposures_option("sci", "Science exposures (several after one flag, or the flag repeated).")
@exposures_option(
    "cal", "Calibrator (PSF reference) exposures (several after one flag, or repeated)."
)
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@model_options
@click.option(
    "--max-iterations",
    type=click.IntRange(min=0),
    default=None,
    help="Natural-gradient steps before the Levenberg-Marquardt finish (an optional first "
    "stage; none by default).",
)
@click.option(
    "--polish",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="BFGS polish steps after the natural-gradient descent.",
)
@click.option(
    "--wavefront-prior",
    "wavefront_prior",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Gaussian prior (nm rms per Zernike coefficient and on the defocus) holding the "
    "calibrators' wavefront near the base model's [default: none].",
)
@superbias_option(
    "Calslope files of the same detector (darks preferably) to measure each pixel's reset "
    "level from; the first group's photons then enter the fit (calslope inputs only)"
)
@click.option(
    "--force",
    is_flag=True,
    help="Fit every filter again [default: keep a filter whose products in OUT are "
    "complete and record the same inputs, model, options and version].",
)
def command(
    sci: tuple[Path, ...],
    cal: tuple[Path, ...],
    out: Path,
    model: Path | None,
    detector: str | None,
    max_iterations: int | None,
    polish: int,
    wavefront_prior: float | None,
    knots: int | None,
    knot_spacing: float | None,
    superbias: tuple[Path, ...] = (),
    no_first_group: bool = False,
    force: bool = False,
) -> int:
    """Fit the instrument model to each exposure and extract calibrated observables.

    Science and calibrator files are grouped by filter (from their headers); in each
    filter all exposures are fitted jointly (visibilities shared per target, wavefront
    from the calibrators), then each science target gets a calvis file of DISCOs and
    an OIFITS file of calibrated V2 and closure phases.

    Exit status: 0 every filter has products; 3 some filters failed or exposures were
    left out, the others' products are written; 4 no filter has products
    (fit_summary.json says why, per filter and exposure).
    """
    if no_first_group and superbias:
        raise click.BadParameter(
            "cannot be combined with --no-first-group", param_hint="--superbias"
        )
    from amigo.pipeline import fit

    result = fit(
        sci,
        cal,
        out,
        model=model,
        detector=detector,
        knots=knots,
        knot_spacing=knot_spacing,
        max_iterations=max_iterations,
        polish=polish,
        wavefront_prior=wavefront_prior,
        superbias=superbias,
        first_group=not no_first_group,
        force=force,
        keep_products=False,  # files only: each filter's memory is freed after it
    )
    return result.status
