"""``amigo train --cal ... --flats ... --val ... [--darks ...] --out MODEL``: train a base model.

All instrument parameters and the charge-migration network are fitted jointly to the
calibration exposures; the flat field and per-pixel non-linearity to the flat-field
exposures only; the validation exposures are fitted (their own positions and fluxes) but
never calibrate anything (docs/detector.md, "Training"). The calibration and validation
exposures are calslope files (from raw ramps) or, all of them, the pipeline's level-2
images: then the model stands behind the pipeline and learns each pixel's residual
sensitivity from the calibrators (:mod:`amigo.training.trainer`). The loss curve is drawn
into ``MODEL_loss.png``.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import click

from amigo.cli.options import ManyValues
from amigo.errors import InputError

_FILES = click.Path(dir_okay=False, path_type=Path)


@click.command("train")
@click.option(
    "--cal",
    "cal",
    cls=ManyValues,
    required=True,
    type=_FILES,
    help="Calibration exposure of a point-source calibrator: calslope files, or the "
    "pipeline's level-2 images (_cal/_calints/_rateints, DN/s; not mixed with calslope); "
    "several may follow.",
)
@click.option(
    "--flats",
    "flats",
    cls=ManyValues,
    type=_FILES,
    help="Flat-field calslope file (uniform illumination); several may follow.",
)
@click.option(
    "--val",
    "val",
    cls=ManyValues,
    type=_FILES,
    help="Validation exposure, of the same kind as --cal (fitted, never used to "
    "calibrate); several may follow.",
)
@click.option(
    "--darks",
    "darks",
    cls=ManyValues,
    type=_FILES,
    help="Dark calslope files (at least 2 groups) of the same detector: each pixel's reset "
    "level (superbias) is measured on them and stored in the model, so that fits of "
    "calslope files count the first group's photons; several may follow [default: none, "
    "or the --init model's].",
)
@click.option("--out", "out", required=True, type=_FILES, help="Base-model file to write (.npz).")
@click.option(
    "--steps",
    default=200,
    show_default=True,
    type=click.IntRange(min=0),
    help="Optimisation steps (one calibration batch each); 0 with --init: none, only the "
    "dark residual of level-2 images is solved afresh (e.g. for images processed with "
    "another dark reference file).",
)
@click.option(
    "--batches",
    default=5,
    show_default=True,
    type=click.IntRange(min=1),
    help="Calibration batches per epoch.",
)
@click.option(
    "--stages",
    default=None,
    help="Steps per stage, comma separated: stage 0 with the network off, then one "
    "stage per network restart [default: 1/5 off, the rest over two restarts].",
)
@click.option(
    "--network-lr",
    default=3e-3,
    show_default=True,
    type=float,
    help="Adam learning rate of the network.",
)
@click.option(
    "--seed",
    default=0,
    show_default=True,
    type=click.IntRange(min=0),
    help="Seed of the network weights and the batch order.",
)
@click.option(
    "--diagonal",
    is_flag=True,
    help="Ignore the covariances between a pixel's slopes [default: the full sample "
    "covariance where a file averages >= 10 integrations per slope, else a pooled "
    "estimate, as amigo fit].",
)
@click.option(
    "--time-limit",
    "time_limit",
    default=None,
    type=click.FloatRange(min=0),
    help="Stop after this many minutes of training (at the end of an epoch).",
)
@click.option("--resume", is_flag=True, help="Continue from MODEL.ckpt.npz if it exists.")
@click.option(
    "--init",
    "init",
    default=None,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Fine-tune this base model (e.g. the shipped one) instead of starting afresh: "
    "no network-off stage; --stages then lists network-on stages, the first keeping "
    "the model's network.",
)
@click.option(
    "--pupil-npix",
    "pupil_npix",
    default=None,
    type=click.IntRange(min=32),
    help="Pupil samples across the telescope pupil [default: the --init model's, else 256].",
)
@click.option(
    "--defocus-method",
    "defocus_method",
    default=None,
    type=click.Choice(["pupil", "angular_spectrum"]),
    help="How the optics applies the defocus [default: the --init model's, else pupil].",
)
@click.option(
    "--sensitivity-prior",
    "sensitivity_prior",
    default=0.01,
    show_default=True,
    type=click.FloatRange(min=0, min_open=True),
    help="Level-2 training: width of the Gaussian prior on each pixel's residual "
    "sensitivity around 1 (what the pipeline's flat leaves).",
)
@click.option(
    "--dark-current-prior",
    "dark_current_prior",
    default=0.13,
    show_default=True,
    type=click.FloatRange(min=0),
    help="Calslope training: width (electrons per group) of the Gaussian population prior "
    "on each pixel's dark current around the calibrators' median dark (0: none); keeps "
    "the star's bright pixels from taking a misfit for dark current. The default is the "
    "simulated detector's scatter: for a real detector give its dark reference file's.",
)
@click.option(
    "--dark-prior",
    "dark_prior",
    default=None,
    type=click.FloatRange(min=0),
    help="Level-2 training: width (DN) of the prior on each pixel's per-group read offsets "
    "that the pipeline's dark subtraction left, solved after the steps (0: none) "
    "[default: 1.6, measured on COM 1093].",
)
@click.option(
    "--stripes/--no-stripes",
    "stripes",
    default=True,
    show_default=True,
    help="Level-2 training: marginalise each image's 1/f column stripes (measured after "
    "the warm-up), as amigo fit does.",
)
@click.option(
    "--drift-modes",
    "drift_modes",
    default=0,
    show_default=True,
    type=click.IntRange(min=0, max=66),
    help="Each exposure's own small wavefront drift: per-hole Noll Zernikes 1..N (3: "
    "piston, tip, tilt), learnt beside the static optics; 0: none (not yet measured on "
    "real calibrators, docs/detector.md).",
)
@click.option(
    "--drift-prior",
    "drift_prior",
    default=5.0,
    show_default=True,
    type=click.FloatRange(min=0, min_open=True),
    help="Width (rms nm) of the Gaussian prior on each drift coefficient around zero.",
)
@click.option(
    "--detector",
    "detector",
    default="full",
    show_default=True,
    type=click.Choice(["full", "boundary"]),
    help="The charge migration's account trained beside the per-pixel maps: 'full' (the "
    "network) or 'boundary' (the physical account's strength and anisotropy, as amigo "
    "fit --detector boundary uses it; calslope files only).",
)
@click.option("--float64", "float64", is_flag=True, help="Train in float64 (default float32).")
@click.option(
    "--provenance",
    "provenance_file",
    default=None,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="JSON object merged into the model's metadata (where the data came from: "
    "'trained_on', 'scenario', 'seed', ...).",
)
def command(
    cal: tuple[Path, ...],
    flats: tuple[Path, ...],
    val: tuple[Path, ...],
    darks: tuple[Path, ...],
    out: Path,
    steps: int,
    batches: int,
    stages: str | None,
    network_lr: float,
    seed: int,
    diagonal: bool,
    time_limit: float | None,
    resume: bool,
    init: Path | None,
    pupil_npix: int | None,
    defocus_method: str | None,
    sensitivity_prior: float,
    dark_current_prior: float,
    dark_prior: float | None,
    stripes: bool,
    drift_modes: int,
    drift_prior: float,
    detector: str,
    float64: bool,
    provenance_file: Path | None,
) -> None:
    """Train the base model (instrument state and BFE network) on calibration data."""
    from amigo.cli import fail_input
    from amigo.pipeline import train

    stage_steps: tuple[int, ...] = ()
    if stages:
        try:
            stage_steps = tuple(int(x) for x in stages.split(","))
        except ValueError:
            raise click.BadParameter(
                "a comma-separated list of integers", param_hint="--stages"
            ) from None
    # The command exactly as given (file paths included): the record says what made the model.
    root = click.get_current_context().find_root().obj
    argv = root["argv"] if isinstance(root, dict) and "argv" in root else ["train"]
    provenance = {"command": "amigo " + shlex.join(argv)}
    try:
        if provenance_file is not None:
            provenance.update(_provenance(provenance_file))
        result = train(
            cal,
            out,
            flats=flats,
            val=val,
            darks=darks,
            steps=steps,
            batches=batches,
            stage_steps=stage_steps,
            network_lr=network_lr,
            seed=seed,
            diagonal=diagonal,
            time_limit_min=time_limit,
            resume=resume,
            init=init,
            pupil_npix=pupil_npix,
            defocus_method=defocus_method,
            sensitivity_prior=sensitivity_prior,
            dark_current_prior=dark_current_prior,
            dark_prior=dark_prior,
            stripes=stripes,
            drift_modes=drift_modes,
            drift_prior=drift_prior,
            detector=detector,
            float64=float64,
            provenance=provenance,
        )
    except InputError as error:
        if error.path in ("--steps", "--stages"):
            raise click.BadParameter(error.problem, param_hint=str(error.path)) from None
        fail_input(error)
        return
    metadata = result.metadata
    final = metadata["history"]
    if final["cal_loss"]:
        losses = (
            f"last losses (chi2/2 per value): cal {final['cal_loss'][-1]:.4g}, "
            f"val {final['val_loss'][-1]:.4g}"
        )
    else:  # --steps 0: the model kept, only the closed-form parts solved
        z = [s["zscore_std"] for s in metadata["statistics"] if s["role"] == "calibrator"]
        losses = f"model kept; calibrators' pixel z-score std {min(z):.3f}-{max(z):.3f}"
    click.echo(
        f"{out}: {metadata['steps_done']} steps in {metadata['training_seconds']:.0f} s; "
        f"{losses}; loss curve {result.loss_curve}"
    )


def _provenance(path: Path) -> dict:
    """The JSON object of ``--provenance``; :class:`InputError` for anything else."""
    try:
        extra = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise InputError(path, f"not a JSON file ({error})") from None
    if not isinstance(extra, dict):
        raise InputError(path, "must hold a JSON object")
    return extra
