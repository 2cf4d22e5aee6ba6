"""The work of ``amigo detect`` (:func:`amigo.pipeline.detect`): calibrated observables ->
companions, posteriors and contrast limits.

A search whose ``companions.json`` (written last, after the CSV and the figures) records
the same inputs, options and version is kept unless ``force``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from amigo.errors import InputError


@dataclass
class DetectResult:
    """What :func:`amigo.pipeline.detect` did.

    Attributes
    ----------
    out
        The output folder.
    document
        The contents of ``out/companions.json`` (docs/interfaces.md).
    result
        The :class:`~amigo.companions.search.DetectionResult` of a search run by this
        call (maps, limits, posteriors), ``None`` where an earlier search was kept.
    """

    out: Path
    document: dict[str, Any]
    result: Any = None

    @property
    def companions(self) -> list[dict[str, Any]]:
        """The detected companions, as in ``companions.json``."""
        return list(self.document.get("companions", []))


#: The smallest search radius (mas) ``--rmax-mas`` accepts.
MIN_RMAX_MAS = 1.0


def check_search_grid(rmax_mas: float, step_mas: float | None = None) -> None:
    """:class:`~amigo.errors.InputError` for a search radius below :data:`MIN_RMAX_MAS`
    (or not a number), or a grid step (``None``: the default) that is not a positive
    number smaller than the radius: checked before any work, by ``detect``, ``run`` and a
    manifest."""
    if not MIN_RMAX_MAS <= rmax_mas < float("inf"):
        raise InputError(
            None,
            f"--rmax-mas must be a finite radius of at least {MIN_RMAX_MAS:g} mas, not {rmax_mas}",
        )
    if step_mas is not None and not 0 < step_mas < rmax_mas:
        raise InputError(
            None,
            f"--step-mas ({step_mas}) must be a positive step smaller than --rmax-mas ({rmax_mas})",
        )


def check_sampler_device() -> None:
    """:class:`~amigo.errors.InputError` for an ``AMIGO_SAMPLER_DEVICE`` that is not a
    setting (:func:`amigo.runtime.sampler_device_setting`): read only where NUTS runs, so
    checked before any work, by ``detect``, ``run`` and a manifest."""
    from amigo.runtime import sampler_device_setting

    try:
        sampler_device_setting()
    except ValueError as error:
        raise InputError(None, str(error)) from None


def detect(
    files: Sequence[str | Path],
    out: str | Path,
    *,
    rmax_mas: float = 1000.0,
    threshold: float = 5.0,
    step_mas: float | None = None,
    max_companions: int = 3,
    observables: str = "all",
    cp_correlation: str = "baseline",
    primary_diameter_mas: float = 0.0,
    hmc: bool = True,
    per_filter: bool = True,
    warmup: int | None = None,
    samples: int = 1000,
    chains: int = 2,
    seed: int = 0,
    force: bool = False,
    ess: int = 400,
) -> DetectResult:
    """Search calvis or OIFITS files for companions, as ``amigo detect``: writes
    ``out/companions.json``, ``out/contrast_limits.csv``, ``out/contrast_maps.fits`` and
    figures.

    Keywords (the command's options, defaults in brackets): ``rmax_mas`` (1000), ``threshold``
    (5 sigma), ``step_mas`` (None: lambda_min / 5 B_max), ``max_companions`` (3),
    ``observables`` (``"all"``, ``"phase"``, ``"amplitude"``), ``cp_correlation``
    (``"baseline"``, ``"independent"``), ``primary_diameter_mas`` (0), ``hmc`` (True),
    ``per_filter`` (True), ``warmup`` (None: 150 steps tuning the step size from
    Laplace's covariance, 500 adapting the mass matrix where that covariance is not
    available), ``samples`` (1000: the most drawn per chain), ``chains`` (2), ``seed``
    (0), ``force`` (False: keep a search of the same inputs and options), ``ess`` (400:
    stop drawing once every parameter's mean and error percentiles have this effective
    sample size; 0 draws all ``samples``).
    Returns a :class:`DetectResult` (``.companions``, ``.document``, ``.result``).
    """
    options = dict(locals())  # the parameters, before any other name is bound
    check_search_grid(rmax_mas, step_mas)
    check_sampler_device()
    settings = {k: v for k, v in options.items() if k not in ("files", "out", "force")}
    files = [str(f) for f in files]
    out = Path(out)
    _refuse_repeats(files)  # before a kept search of the same list could be returned
    key = _detect_key(files, settings)
    kept = None if force else _kept_search(out, key)
    if kept is not None:
        print(
            f"{out / 'companions.json'}: up to date (same inputs and options), "
            "kept (--force searches again)"
        )
        return DetectResult(out, kept)
    import jax

    # Fits, Hessians and HMC need float64. A context rather than the global switch, so a
    # process that calls this (tests, notebooks) keeps its own precision after.
    with jax.enable_x64(True):
        result, document = _search(
            files, out, rmax_mas, threshold, step_mas, max_companions, observables,
            cp_correlation, primary_diameter_mas, hmc, per_filter, warmup, samples,
            chains, seed, key, ess,
        )  # fmt: skip
    return DetectResult(out, document, result)


def _detect_key(files, settings: dict) -> str:
    """Identity of a search: 16 hex characters of the SHA-256 of the amigo version, the
    options and the input files' names and content fingerprints."""
    import hashlib
    import json

    from amigo._version import __version__
    from amigo.io.files import fingerprint, require_file

    inputs = [(Path(f).name, fingerprint(require_file(f, "input file"))) for f in files]
    text = json.dumps(
        {"version": __version__, "settings": settings, "inputs": inputs}, sort_keys=True
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _kept_search(out: Path, key: str) -> dict | None:
    """The companions.json of a complete search with identity ``key`` in ``out`` (it is
    written last and records the key; contrast_limits.csv and contrast_maps.fits must be
    there: a folder searched before the maps existed is searched again), or ``None``."""
    import json

    try:
        document = json.loads((out / "companions.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    complete = (
        isinstance(document, dict)
        and document.get("detect_key") == key
        and (out / "contrast_limits.csv").is_file()
        and (out / "contrast_maps.fits").is_file()
    )
    return document if complete else None


def _search(
    files,
    out_dir,
    rmax_mas,
    threshold,
    step_mas,
    max_companions,
    observables,
    cp_correlation,
    primary_diameter_mas,
    hmc,
    per_filter,
    warmup,
    samples,
    chains,
    seed,
    key: str = "",
    ess: int = 400,
):
    """Load, search, write the products (companions.json last, recording ``key``) and
    print the findings; return the search's DetectionResult and the companions.json
    document."""
    import numpy as np

    from amigo.companions import observables as obs
    from amigo.companions import products
    from amigo.companions.search import SearchSettings, detect
    from amigo.plots import companions as plots
    from amigo.progress import step, warn

    blocks = [obs.load(f, cp_correlation=cp_correlation, observables=observables) for f in files]
    _refuse_other_targets(files, blocks)
    for path, block in zip(files, blocks, strict=True):
        step(f"{path}: {block.filter_name}, {block.n_obs} observables, {block.n_uv} uv points")
        if not np.isfinite(block.n_photons):  # a calvis without NPHOT, an OIFITS without T3
            warn(f"{path}: no photon count: no photon-rule limit for {block.filter_name}")
    dataset = obs.Dataset.from_blocks(blocks)
    settings = SearchSettings(
        rmax_mas=rmax_mas,
        step_mas=step_mas,
        threshold_sigma=threshold,
        max_companions=max_companions,
        primary_diameter_mas=primary_diameter_mas,
        hmc=hmc,
        per_filter=per_filter,
        num_warmup=warmup,
        num_samples=samples,
        num_chains=chains,
        seed=seed,
        ess_target=ess,
    )
    result = detect(dataset, settings)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # companions.json last: a search interrupted before it is not taken for complete.
    products.write_contrast_csv(out / "contrast_limits.csv", result)
    products.write_contrast_maps(out / "contrast_maps.fits", result)
    plots.write_all(result, out)
    document = products.write_companions_json(
        out / "companions.json", result, list(files), {"detect_key": key}
    )

    if not result.companions:
        print(f"no companion above {threshold:g} sigma within {rmax_mas:g} mas")
    for c in result.companions:
        e = c.estimate
        dmag = ", ".join(f"{f} {e.dmag[f]:.3f}±{e.dmag_err[f]:.3f}" for f in dataset.filters)
        print(
            f"companion {c.id}: sep {e.sep_mas:.2f}±{e.sep_err_mas:.2f} mas, "
            f"PA {e.pa_deg:.2f}±{e.pa_err_deg:.2f} deg, dmag {dmag}, "
            f"{c.detection_sigma:.1f} sigma ({c.method}"
            + (
                ""
                if c.significance is None
                else f"; false-alarm probability {c.significance.false_alarm_probability:.2g}"
            )
            + ")"
        )
    for r in result.rejected:
        print(f"not a detection: {r.note}")
    scales = ", ".join(f"{f} {v:.2f}" for f, v in result.sigma_scale.items())
    print(f"sigma_scale: {scales}")
    for message in result.warnings:
        print(f"warning: {message}", file=sys.stderr)
    print(
        f"wrote {out / 'companions.json'}, {out / 'contrast_limits.csv'}, "
        f"{out / 'contrast_maps.fits'} and figures"
    )
    return result, document


def _refuse_repeats(files) -> None:
    """A file given twice would count its observables twice (every chi2 gain doubled,
    a 3.6-sigma candidate read as 5.1): refused, as a bad input, whether by the same
    path or as a copy under another name (the same content fingerprint)."""
    from amigo.io.files import fingerprint, require_file

    seen: dict[Path, str] = {}
    contents: dict[str, str] = {}
    for path in files:
        resolved = Path(path).resolve()
        if resolved in seen:
            raise InputError(path, "is given twice")
        content = fingerprint(require_file(path, "calvis or OIFITS file"))
        if content in contents:
            raise InputError(path, f"has the content of {contents[content]}: given twice")
        seen[resolved] = contents[content] = str(path)
    _refuse_shared_exposures(files)


def _refuse_shared_exposures(files) -> None:
    """Two products of the same science exposure (a fit's calvis and OIFITS files, or
    the calvis files of two fits of one exposure against different calibrators) hold
    the same photons: searched together their information would count twice, as a file
    given twice does. Refused where the files name their science exposures (``SCI_1``...
    in the primary header: amigo's calvis and OIFITS files), an exposure being its file
    name without the product suffix, in any case (:func:`amigo.io.jwst.exposure_stem`: its
    ``_cal`` and ``_calslope`` files are one exposure); blank names and files whose header
    cannot be read are left to the readers. Another tool's file with ``SCI_n`` cards is
    compared too: the same exposure is the same photons whoever wrote the file."""
    import re

    from astropy.io import fits

    from amigo.io.jwst import exposure_stem

    owner: dict[str, str] = {}
    for path in files:
        try:
            header = fits.getheader(path, 0)
        except (OSError, ValueError):  # the readers report what is wrong with it
            continue
        # Every SCI_n card, whatever NSCI says (a damaged count is the reader's to report).
        names = {
            exposure_stem(value): value.strip()
            for key, value in header.items()
            if re.fullmatch(r"SCI_\d+", key) and isinstance(value, str) and value.strip()
        }
        for stem, name in sorted(names.items()):
            if stem in owner:
                raise InputError(
                    path,
                    f"was made from the science exposure {name}, as {owner[stem]} was: "
                    "its information would count twice",
                )
            owner[stem] = str(path)


def _refuse_other_targets(files, blocks) -> None:
    """One search is one star: calvis files of different science targets (``amigo
    detect out/*_calvis.fits`` after a fit of two targets) are refused, naming the first
    file of another target. OIFITS files are not checked (other tools name targets in
    their own ways), nor calvis files without a target name."""
    from amigo.io.calvis import is_calvis

    first: tuple[Path, str] | None = None
    for path, block in zip(files, blocks, strict=True):
        if not is_calvis(path) or not block.target:
            continue
        if first is None:
            first = (Path(path), block.target)
        elif block.target != first[1]:
            raise InputError(
                path,
                f"is of target {block.target!r}, {first[0].name} of {first[1]!r}: "
                "detect one target at a time",
            )
