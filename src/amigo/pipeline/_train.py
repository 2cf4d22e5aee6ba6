"""``amigo.train``: a base model trained on calibration exposures (``amigo train``'s job).

Checks every input in seconds (before the model's modules are imported), measures the
superbias on the darks, trains (:func:`amigo.training.trainer.train`), writes the model
file and draws its loss curve beside it.
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from amigo.errors import InputError
from amigo.progress import warn

PathLike = str | os.PathLike[str]

#: Memory mappings that training on full-size calibration data has been seen to need.
#: XLA's CPU backend maps every compiled kernel separately, and the steps with the
#: network compile into tens of thousands of kernels: one run held 32,000 mappings after
#: its first network-on compilation and crashed (LLVM "Cannot allocate memory", then a
#: segfault) at the Linux default limit of 65,530.
MAP_COUNT_NEEDED = 262_144


@dataclass
class TrainResult:
    """What :func:`train` wrote: the model file, its loss curve (PNG), the metadata
    stored in the model (``history``, ``statistics`` per exposure, provenance), and the
    trained :class:`~amigo.model.base.BaseModel` itself."""

    model: Path
    loss_curve: Path
    metadata: dict[str, Any]
    base_model: Any


def train(
    cal: Sequence[PathLike],
    out: PathLike,
    *,
    flats: Sequence[PathLike] = (),
    val: Sequence[PathLike] = (),
    darks: Sequence[PathLike] = (),
    steps: int = 200,
    batches: int = 5,
    stage_steps: Sequence[int] = (),
    network_lr: float = 3e-3,
    seed: int = 0,
    diagonal: bool = False,
    time_limit_min: float | None = None,
    resume: bool = False,
    init: PathLike | None = None,
    pupil_npix: int | None = None,
    defocus_method: str | None = None,
    sensitivity_prior: float = 0.01,
    dark_current_prior: float = 0.13,
    dark_prior: float | None = None,
    stripes: bool = True,
    drift_modes: int = 0,
    drift_prior: float = 5.0,
    detector: str = "full",
    float64: bool = False,
    provenance: dict[str, Any] | None = None,
) -> TrainResult:
    """Train a base model on calibration exposures, as ``amigo train`` (its options, by
    the same names; ``stage_steps``: ``--stages`` as integers).

    ``cal``/``val`` are calslope files or, all of them, level-2 images; ``flats`` flat-field
    calslope files; ``darks`` calslope darks for the superbias (calslope training only).
    ``provenance`` is merged into the model's metadata. Raises
    :class:`~amigo.errors.InputError` for an unusable input, before any training.
    """
    cal_paths = tuple(Path(p) for p in cal)
    flat_paths = tuple(Path(p) for p in flats)
    val_paths = tuple(Path(p) for p in val)
    init_path = None if init is None else Path(init)
    out = Path(out)
    if steps == 0 and init_path is None:
        raise InputError("--steps", "0 needs --init (a model to keep)")
    if stage_steps and (sum(stage_steps) != steps or min(stage_steps) < 1):
        raise InputError("--stages", f"positive steps summing to --steps ({steps})")
    from amigo._version import source_commit

    # Taken now: the code that trains is the code imported at the start.
    record: dict[str, Any] = {
        "source_commit": source_commit(),
        "float": "float64" if float64 else "float32",
    }
    record.update(provenance or {})
    # Unusable inputs fail here, in seconds, before the model's modules are imported
    # (tens of seconds on a small machine).
    check_inputs((*cal_paths, *flat_paths, *val_paths), init_path)
    superbias = measure_superbias(tuple(Path(p) for p in darks), cal_paths[0])
    _warn_about_memory_maps()
    import jax

    with jax.enable_x64(float64):
        import jax.numpy as jnp

        from amigo.model.base import BaseModelConfig, load_base_model, read_metadata
        from amigo.model.optics import cast
        from amigo.training.data import TrainingData, TrainSettings
        from amigo.training.trainer import train as train_model

        dtype = jnp.float64 if float64 else jnp.float32
        optics: dict[str, Any] = {
            k: v
            for k, v in (("pupil_npix", pupil_npix), ("defocus_method", defocus_method))
            if v is not None
        }
        initial = config = None
        data = TrainingData.read(cal_paths, flat_paths, val_paths, diagonal=diagonal, dtype=dtype)
        if init_path is not None:
            initial = cast(load_base_model(init_path), dtype).with_config(**optics)
            record["initial_model"] = _initial_summary(init_path, read_metadata(init_path))
        elif optics:
            config = BaseModelConfig(filters=data.filters, shape=data.cal[0].shape, **optics)
        settings = TrainSettings(
            steps=steps,
            n_batches=batches,
            stage_steps=tuple(stage_steps),
            network_lr=network_lr,
            seed=seed,
            diagonal=diagonal,
            init=None if init_path is None else str(init_path),
            sensitivity_prior=sensitivity_prior,
            dark_current_prior=dark_current_prior,
            stripes=stripes,
            drift_modes=drift_modes,
            drift_prior_nm=drift_prior,
            detector=detector,
            **({} if dark_prior is None else {"dark_prior_dn": dark_prior}),
        )
        model, metadata = train_model(
            data,
            out,
            settings,
            config=config,
            resume=resume,
            time_limit_s=None if time_limit_min is None else 60.0 * time_limit_min,
            provenance=record,
            initial=initial,
            superbias=superbias,
        )
    from amigo.plots.optics import save
    from amigo.plots.training import loss_curve_figure
    from amigo.training.data import History
    from amigo.training.trainer import loss_curve_path

    curve = loss_curve_path(out)
    save(loss_curve_figure(History(**metadata["history"]), title=out.name), curve)
    return TrainResult(model=out, loss_curve=curve, metadata=metadata, base_model=model)


def check_inputs(slope_files: tuple[Path, ...], init: Path | None) -> None:
    """Raise the one-line :class:`InputError` if a calslope file or level-2 image cannot be
    read, the two kinds are mixed, or ``init`` is not a model archive (reads the files
    fully: the same checks as training's reader)."""
    from amigo.io.calslope import read_calslope
    from amigo.io.jwst import is_level2, read_exposure

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


def measure_superbias(darks: tuple[Path, ...], first_cal: Path) -> Any:
    """The superbias measured on ``darks`` (``None`` without); :class:`InputError` for a
    file that cannot give one, or when the training data are level-2 images (the pipeline
    has subtracted the bias: a level-2 model has no first read to use it)."""
    if not darks:
        return None
    from amigo.io.calslope import read_calslope
    from amigo.io.jwst import is_level2
    from amigo.model.detector.reset import estimate_superbias

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


def _initial_summary(path: Path, metadata: dict[str, Any]) -> dict[str, Any]:
    """What the fine-tuned model's metadata records of the model it started from."""
    from amigo.model.base import OPTICS_SETTINGS

    keys = ("date", "command", "trained_on", "steps_done", "amigo_version", "dtype")
    config = metadata.get("config", {})
    optics = {k: config[k] for k in OPTICS_SETTINGS if k in config}
    # The file's digest names it after its path has been overwritten (a shipped model
    # fine-tuned into its own place).
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    return {
        "path": str(path),
        "sha256": digest,
        **{k: metadata[k] for k in keys if k in metadata},
        "optics": optics,
    }


def _warn_about_memory_maps() -> None:
    """Tell the user, before hours of training, if the kernel's mapping limit is low."""
    path = Path("/proc/sys/vm/max_map_count")
    try:
        limit = int(path.read_text().strip())
    except (OSError, ValueError):
        return  # not Linux, or not readable: nothing to say
    if limit < MAP_COUNT_NEEDED:
        warn(
            f"vm.max_map_count is {limit}; training can exhaust it (XLA maps each "
            f"compiled kernel separately) and crash. Raise it first, as root: "
            f"sysctl -w vm.max_map_count={MAP_COUNT_NEEDED}"
        )
