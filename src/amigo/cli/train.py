"""``amigo train --cal ... --flats ... --val ... [--darks ...] --out MODEL``: train a base model.

All instrument parameters and the charge-migration network are fitted jointly to the
calibration exposures; the flat field and per-pixel non-linearity to the flat-field
exposures only; the validation exposures are fitted (their own positions and fluxes) but
never calibrate anything (docs/detector.md, "Training"). The calibration and validation
exposures are calslope files (from raw ramps) or, all of them, the pipeline's level-2
images: then the model stands behind the pipeline and learns each pixel's residual
sensitivity from the calibrators (:mod:`amigo.calibration`). The loss curve is drawn
into ``MODEL_loss.png``.
"""

from __future__ import annotations

import json
import shlex
import zipfile
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
    "--dark-prior",
    "dark_prior",
    default=None,
    type=click.FloatRange(min=0),
    help="Level-2 training: width (DN) of the prior on each pixel's per-group read offsets "
    "that the pipeline's dark subtraction left, solved after the steps (0: none) "
    "[default: 1.6, measured on COM 1093].",
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
    dark_prior: float | None,
    float64: bool,
    provenance_file: Path | None,
) -> None:
    """Train the base model (instrument state and BFE network) on calibration data."""
    from amigo.cli import fail_input

    stage_steps: tuple[int, ...] = ()
    if steps == 0 and init is None:
        raise click.BadParameter("0 needs --init (a model to keep)", param_hint="--steps")
    if stages:
        try:
            stage_steps = tuple(int(x) for x in stages.split(","))
        except ValueError:
            raise click.BadParameter(
                "a comma-separated list of integers", param_hint="--stages"
            ) from None
        if sum(stage_steps) != steps or min(stage_steps) < 1:
            raise click.BadParameter(
                f"positive steps summing to --steps ({steps})", param_hint="--stages"
            )
    # The command exactly as given (file paths included): the record says what made the model.
    root = click.get_current_context().find_root().obj
    argv = root["argv"] if isinstance(root, dict) and "argv" in root else ["train"]
    from amigo._version import source_commit

    # Taken now: the code that trains is the code imported at the start.
    provenance = {
        "command": "amigo " + shlex.join(argv),
        "source_commit": source_commit(),
        "float": "float64" if float64 else "float32",
    }
    if provenance_file is not None:
        try:
            extra = json.loads(provenance_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as error:
            fail_input(InputError(provenance_file, f"not a JSON file ({error})"))
            return
        if not isinstance(extra, dict):
            fail_input(InputError(provenance_file, "must hold a JSON object"))
            return
        provenance.update(extra)
    # Unusable inputs fail here, in seconds, before the model's modules are imported
    # (tens of seconds on a small machine).
    _check_inputs((*cal, *flats, *val), init)
    superbias = _superbias(darks, cal[0])
    _warn_about_memory_maps()
    import jax

    with jax.enable_x64(float64):
        import jax.numpy as jnp

        from amigo.basemodel import BaseModelConfig, load_base_model, read_metadata
        from amigo.calibration import TrainingData, TrainSettings, train
        from amigo.optics import cast

        dtype = jnp.float64 if float64 else jnp.float32
        optics = {
            k: v
            for k, v in (("pupil_npix", pupil_npix), ("defocus_method", defocus_method))
            if v is not None
        }
        initial = config = None
        try:
            data = TrainingData.read(cal, flats, val, diagonal=diagonal, dtype=dtype)
            if init is not None:
                initial = cast(load_base_model(init), dtype).with_config(**optics)
                provenance["initial_model"] = _summary(init, read_metadata(init))
            elif optics:
                config = BaseModelConfig(filters=data.filters, shape=data.cal[0].shape, **optics)
        except InputError as error:
            fail_input(error)
            return
        settings = TrainSettings(
            steps=steps,
            n_batches=batches,
            stage_steps=stage_steps,
            network_lr=network_lr,
            seed=seed,
            diagonal=diagonal,
            init=None if init is None else str(init),
            sensitivity_prior=sensitivity_prior,
            **({} if dark_prior is None else {"dark_prior_dn": dark_prior}),
        )
        try:
            _, metadata = train(
                data,
                out,
                settings,
                config=config,
                resume=resume,
                time_limit_s=None if time_limit is None else 60.0 * time_limit,
                provenance=provenance,
                initial=initial,
                superbias=superbias,
            )
        except InputError as error:
            fail_input(error)
            return
    from amigo.calibration import loss_curve_path

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
        f"{losses}; loss curve {loss_curve_path(out)}"
    )


def _check_inputs(slope_files: tuple[Path, ...], init: Path | None) -> None:
    """Exit with the one-line error if a calslope file or level-2 image cannot be read
    or ``--init`` is not a model archive (reads the files fully: the same checks as
    training's reader)."""
    from amigo.cli import fail_input
    from amigo.io.calslope import read_calslope
    from amigo.io.jwst import is_level2, read_exposure

    try:
        kinds = {}
        for path in slope_files:
            kinds[path] = is_level2(path)
            if kinds[path]:
                read_exposure(path)
            else:
                read_calslope(path)
        # One model stands either in front of the pipeline (ramps) or behind it (level 2).
        odd = [p for p in slope_files if kinds[p] != kinds[slope_files[0]]]
        if odd:
            first = "a level-2 image" if kinds[odd[0]] else "a calslope file"
            raise InputError(
                odd[0],
                f"is {first}; level-2 images and calslope files cannot be mixed in one training",
            )
        if init is not None and not zipfile.is_zipfile(init):
            raise InputError(init, "not a base-model file (the .npz archive amigo train writes)")
    except InputError as error:
        fail_input(error)


def _superbias(darks: tuple[Path, ...], first_cal: Path):
    """The superbias measured on ``darks`` (``None`` without); exits with the one-line
    error for a file that cannot give one, or when the training data are level-2 images
    (the pipeline has subtracted the bias: a level-2 model has no first read to use it)."""
    if not darks:
        return None
    from amigo.cli import fail_input
    from amigo.detector.reset import estimate_superbias
    from amigo.io.calslope import read_calslope
    from amigo.io.jwst import is_level2

    try:
        if is_level2(first_cal):
            raise InputError(
                darks[0], "--darks needs calslope training data (level-2 images have no bias)"
            )
        superbias = estimate_superbias([read_calslope(path) for path in darks])
        shape = read_calslope(first_cal).badpix.shape
        if superbias.level_dn.shape != shape:
            raise InputError(
                darks[0],
                f"frames of {superbias.level_dn.shape} differ from the training files' {shape}",
            )
        return superbias
    except InputError as error:
        fail_input(error)
        return None


def _summary(path: Path, metadata: dict) -> dict:
    """What the fine-tuned model's metadata records of the model it started from."""
    from amigo.basemodel import OPTICS_SETTINGS

    keys = ("date", "command", "trained_on", "steps_done", "amigo_version", "dtype")
    config = metadata.get("config", {})
    optics = {k: config[k] for k in OPTICS_SETTINGS if k in config}
    return {"path": str(path), **{k: metadata[k] for k in keys if k in metadata}, "optics": optics}


#: Memory mappings that training on full-size calibration data has been seen to need.
#: XLA's CPU backend maps every compiled kernel separately, and the steps with the
#: network compile into tens of thousands of kernels: on 2026-11-23 one run held 32,000
#: mappings after its first network-on compilation and crashed (LLVM "Cannot allocate
#: memory", then a segfault) at the Linux default limit of 65,530.
MAP_COUNT_NEEDED = 262_144


def _warn_about_memory_maps() -> None:
    """Tell the user, before hours of training, if the kernel's mapping limit is low."""
    path = Path("/proc/sys/vm/max_map_count")
    try:
        limit = int(path.read_text().strip())
    except (OSError, ValueError):
        return  # not Linux, or not readable: nothing to say
    if limit < MAP_COUNT_NEEDED:
        click.echo(
            f"note: vm.max_map_count is {limit}; training can exhaust it (XLA maps each "
            f"compiled kernel separately) and crash. Raise it first, as root: "
            f"sysctl -w vm.max_map_count={MAP_COUNT_NEEDED}",
            err=True,
        )
