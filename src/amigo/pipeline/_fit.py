"""The work of ``amigo fit`` (:func:`amigo.pipeline.fit`): files -> calibrated observables.

Reads the science and calibrator files, leaves out exposures without a star, groups the
exposures by filter, fits each filter jointly (:func:`amigo.observables.extract.extract_filter`),
writes per science target and filter a calvis and an OIFITS file, the plots and
``fit_summary.json`` (rewritten after each filter), and keeps the filters whose products
a previous run left complete for the same inputs (:mod:`amigo.pipeline.outcome`).
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from amigo.errors import InputError
from amigo.progress import warn

if TYPE_CHECKING:
    from amigo.likelihood.pixels import ImageData


@dataclass
class FitResult:
    """What :func:`amigo.pipeline.fit` did.

    Attributes
    ----------
    out
        The output folder.
    summary
        The contents of ``out/fit_summary.json`` (per exposure and per filter: statuses,
        goodness of fit, fitted geometry; docs/interfaces.md).
    status
        0 every filter has products; 3 some filters failed or exposures were left out;
        4 no filter has products (:mod:`amigo.pipeline.outcome`).
    products
        Filter -> :class:`~amigo.observables.extract.FilterProduct` of the filters fitted in this call
        (the fit, its images and models, the DISCOs); filters kept from an earlier run
        are not in it (``force=True`` fits them again).
    """

    out: Path
    summary: dict[str, Any]
    status: int
    products: dict[str, Any] = field(default_factory=dict)

    def _files(self, suffix: str) -> list[Path]:
        from amigo.pipeline.outcome import USABLE

        filters = self.summary.get("filters", {})
        return [
            self.out / name
            for _, record in sorted(filters.items())
            if record.get("status") in USABLE
            for name in record.get("products", [])
            if name.endswith(suffix)
        ]

    @property
    def calvis(self) -> list[Path]:
        """The calvis files of the filters with products, in filter order."""
        return self._files("_calvis.fits")

    @property
    def oifits(self) -> list[Path]:
        """The OIFITS files of the filters with products, in filter order."""
        return self._files(".oifits")

    def plot_residuals(self, file: str | None = None) -> list:
        """Figures of data, model, residuals in sigma and their histogram, one per
        exposure (``file``: only that exposure's, by file name). Exposures of filters
        kept from an earlier run show the figure that run saved in ``out/plots``."""
        import matplotlib.image as mpimg
        import matplotlib.pyplot as plt

        from amigo.plots.fit import exposure_figure

        figures = []
        for record in self.summary.get("exposures", []):
            name = record.get("file")
            if (file is not None and name != file) or record.get("status") not in (
                "ok",
                "unconverged",
            ):
                continue
            product = self.products.get(record.get("filter"))
            names = [e.name for e in product.fit.exposures] if product else []
            if name in names:
                assert product is not None  # names is empty without a product
                e = names.index(name)
                exposure = product.fit.exposures[e]
                figures.append(exposure_figure(exposure.image, product.models[e], product.stats[e]))
                continue
            saved = self.out / "plots" / f"{Path(name).name.removesuffix('.fits')}_fit.png"
            if saved.is_file():
                figure, axis = plt.subplots(figsize=(12, 3.2))
                axis.imshow(mpimg.imread(saved))
                axis.set_axis_off()
                axis.set_title(f"{name} (saved by the run that fitted it)")
                figures.append(figure)
        if file is not None and not figures:
            raise InputError(None, f"no fitted exposure {file!r} in {self.out}")
        return figures


def fit(
    sci: Sequence[str | Path],
    cal: Sequence[str | Path],
    out: str | Path,
    *,
    model: str | Path | None = None,
    detector: str | None = None,
    knots: int | None = None,
    knot_spacing: float | None = None,
    max_iterations: int | None = None,
    polish: int = 0,
    wavefront_prior: float | None = None,
    superbias: Sequence[str | Path] = (),
    first_group: bool = True,
    force: bool = False,
    keep_products: bool = True,
) -> FitResult:
    """Fit science and calibrator exposures and extract calibrated observables, as ``amigo
    fit``: per science target and filter ``out/<TARGPROP>_<FILTER>_calvis.fits`` and
    ``.oifits``, with ``out/fit_summary.json`` and ``out/plots``.

    ``sci``, ``cal``: level-2 images or calslope files (not both kinds). ``model``: a base
    model (``.npz``) or instrument file (default: the shipped model for the data's
    level); ``detector``: ``"full"``, ``"linear"`` or ``"boundary"`` (default: as
    docs/fit.md says);
    ``knots``, ``knot_spacing``: the uv grid of the latent visibilities;
    ``max_iterations``, ``polish``: optimiser bounds; ``wavefront_prior``: nm rms prior on
    the calibrators' wavefront; ``superbias``: calslope darks giving each pixel's reset
    level (calslope inputs; default the model's); ``first_group=False`` fits the group
    differences only; ``force``: fit filters whose products are already complete;
    ``keep_products=False``: the result's ``products`` stay empty (the command line's
    choice: each filter's fit, Fisher matrices and Hessians, ~0.2 GB for a real filter,
    are freed once its files are written, instead of held to the end).

    Returns a :class:`FitResult` (``.status``, ``.calvis``, ``.summary``,
    ``.plot_residuals()``). Numerical failures end their filter, not the call
    (``.status`` 3 or 4, docs/reliability.md).
    """
    sci_paths, cal_paths = tuple(map(Path, sci)), tuple(map(Path, cal))
    superbias_paths = tuple(map(Path, superbias))
    out = Path(out)
    model = None if model is None else Path(model)
    check_roles(sci_paths, cal_paths, superbias_paths, first_group)
    check_model_options(model, detector, knots, knot_spacing)
    level = _check_inputs(sci_paths, cal_paths, detector)
    grid = _grid(knots, knot_spacing)

    import dataclasses

    from amigo._version import __version__
    from amigo.fitting.filter_fit import FitConfig
    from amigo.io.files import fingerprint
    from amigo.pipeline.outcome import exit_status, fit_key, kept_records, previous_summary
    from amigo.progress import step

    fit_model = _fit_model(model, detector, level)
    reset = _reset_level(superbias_paths, level, fit_model, not first_group)
    read = []
    ramps = {}
    excluded = []  # (role, ReadExposure) of the exposures without a star to fit
    given: dict[str, list] = defaultdict(list)  # filter -> (role, meta) of every input
    for role, paths in (("science", sci_paths), ("calibrator", cal_paths)):
        for path in paths:
            item = _read_fit_exposure(path, role, level, reset)
            given[item.meta.filter].append((role, item.meta))
            if item.problem is not None:
                excluded.append((role, item))
                continue
            read.append((item.exposure, item.meta))
            ramps[item.exposure.name] = item.ramp
    for filter_name, inputs in given.items():
        if "science" not in {role for role, _ in inputs}:
            step(f"{filter_name}: calibrators only (no science exposure): skipped")
    by_filter: dict[str, list] = defaultdict(list)
    for fit_exposure, meta in key_targets(read):
        by_filter[meta.filter].append((fit_exposure, meta))
    for items in by_filter.values():
        _check_orientations(items)
    fitted = {
        name: by_filter.get(name, [])
        for name, inputs in sorted(given.items())
        if any(role == "science" for role, _ in inputs)
    }
    _refuse_if_nothing_left(fitted, excluded)
    for filter_name, inputs in given.items():
        if "science" in (roles := {role for role, _ in inputs}) and "calibrator" not in roles:
            # A science target observed in more filters than its calibrator (a dithered
            # calibrator visit in F480M alone): the other filters are fitted, this one is
            # reported failed (exit status 3).
            warn(f"{filter_name}: no calibrator exposure: its science exposures are not fitted")
    config = FitConfig(polish_steps=polish)
    if wavefront_prior is not None:
        config = dataclasses.replace(
            config, newton=dataclasses.replace(config.newton, wavefront_prior_nm=wavefront_prior)
        )
    if max_iterations is not None:
        config = dataclasses.replace(config, max_iterations=max_iterations)
    detector_model = None
    if fit_model.base is not None:
        from amigo.fitting.ramp_fit import RampDetector

        detector_model = RampDetector(fit_model.base, ramps)
        for name, ramp in ramps.items():
            for note in (_charge_loss_note(ramp), _dark_reference_note(fit_model.base, ramp)):
                if note is not None:
                    step(f"{name}: {note}")
        for fit_exposure, meta in read:
            if (note := _flat_reference_note(fit_model, meta)) is not None:
                step(f"{fit_exposure.name}: {note}")
    settings = {
        "amigo_version": __version__,
        "level": level,
        "model": fit_model.source,
        "detector": fit_model.detector,
        "grid": [knots, knot_spacing],
        "config": repr(config),
        "superbias": [fingerprint(p) for p in superbias_paths],
        "first_group": reset is not None,
        "reading": READING_REVISION,
    }

    out.mkdir(parents=True, exist_ok=True)
    previous = {} if force else previous_summary(out)
    summary_exposures = [
        _unfitted_record(
            item.meta.path.name,
            role,
            item.meta.target,
            item.meta.filter,
            "excluded",
            cast(str, item.problem),  # excluded holds only the exposures with a problem
        )
        for role, item in excluded
    ]
    for _, item in excluded:
        warn(f"{item.meta.path}: {item.problem}: left out of the fit")
    filters_summary: dict[str, dict] = {}
    summary: dict[str, Any] = {}
    products = {}
    names = []
    fitted_one = False  # a filter was fitted in this call
    for filter_name, items in fitted.items():
        instrument = fit_model.instrument(filter_name)
        names.append(instrument.name)
        key = fit_key(settings, [(e.role, e.target, fingerprint(m.path)) for e, m in items])
        kept = None if force else kept_records(out, filter_name, key, previous)
        if kept is not None:
            record, records = kept
            records = [r for r in records if r.get("status") != "excluded"]
            step(f"{filter_name}: products up to date in {out}, kept (--force fits again)")
        else:
            if fitted_one:
                _release_compiled_programs()
            record, records, product = _fit_filter(
                instrument, filter_name, items, config, out, grid, detector_model, reset, key
            )
            fitted_one = True
            if product is not None and keep_products:
                products[filter_name] = product
            del product
        filters_summary[filter_name] = record
        summary_exposures.extend(records)
        # After each filter: an interrupted run keeps what it finished (kept_records).
        summary = _write_summary(
            out,
            "; ".join(dict.fromkeys(names)),
            fit_model.detector,
            summary_exposures,
            filters_summary,
        )
    step(f"wrote {out / 'fit_summary.json'}")
    _report(filters_summary, summary_exposures)
    return FitResult(
        out=out,
        summary=summary,
        status=exit_status(filters_summary, summary_exposures),
        products=products,
    )


def _release_compiled_programs() -> None:
    """Free the compiled programs of the filter fitted last, before the next filter's.

    A filter's large programs serve no other filter: its name, the rows of its injection
    band and its latent counts are compiled into them (docs/performance.md, "Programs
    compiled twice, and what two filters share"). Kept, every filter's stayed in memory
    to the end of the run. They stay in the disk cache; the few small programs that two
    filters do share are read back from it. The memory they and the last filter's arrays
    held goes back to the system (:mod:`amigo.heap`).
    """
    from amigo import heap

    heap.release_programs()


def _superbias(paths: tuple[Path, ...], level: str):
    """The :class:`~amigo.model.detector.reset.Superbias` of the ``--superbias`` files."""
    if level != "calslope":
        raise InputError(
            paths[0], "--superbias needs calslope inputs (level-2 images have no first group)"
        )
    from amigo.io.calslope import read_calslope
    from amigo.model.detector.reset import estimate_superbias

    return estimate_superbias([read_calslope(p) for p in paths])


def _check_inputs(sci: tuple[Path, ...], cal: tuple[Path, ...], detector: str | None) -> str:
    """Validate the kinds of the inputs (and ``--detector`` against them); return
    ``"calslope"`` or ``"level2"``."""
    from amigo.io.jwst import LEVEL2_KINDS, data_kind

    kinds = {path: data_kind(path) for path in (*sci, *cal)}
    for path, kind in kinds.items():
        if kind == "uncal":
            raise InputError(path, "is a raw ramp (uncal): run 'amigo process' first")
    check_one_level(kinds)
    check_detector_level(kinds, detector)
    return "level2" if next(iter(kinds.values())) in LEVEL2_KINDS else "calslope"


def check_detector_level(kinds: dict[Path, str], detector: str | None) -> None:
    """``--detector boundary`` needs raw ramps or their calslope files: its strength is
    measured in the group differences (:meth:`RampDetector.calibrate_migration`), which a
    level-2 image does not have. :class:`~amigo.errors.InputError` naming the first
    level-2 input (``kinds``: :func:`amigo.io.jwst.data_kind` of each input)."""
    from amigo.io.jwst import LEVEL2_KINDS

    if detector != "boundary":
        return
    for path, kind in kinds.items():
        if kind in LEVEL2_KINDS:
            raise InputError(
                path, "is a level-2 image: --detector boundary needs calslope files (raw ramps)"
            )


#: The detector models of ``--detector``.
DETECTORS = ("full", "linear", "boundary")


def _kind_words(kind: str) -> str:
    """A file kind of :func:`amigo.io.jwst.data_kind` in a message."""
    from amigo.io.jwst import LEVEL2_KINDS

    if kind in LEVEL2_KINDS:
        return f"a level-2 image ({kind})"
    return "a raw ramp" if kind == "uncal" else "a raw-ramp product (calslope)"


def check_one_level(kinds: dict[Path, str]) -> None:
    """Inputs of one call are of one level: level-2 images (``cal``, ``calints``,
    ``rateints``... together), or raw ramps and their calslope products
    (:func:`amigo.io.jwst.data_kind`'s kinds): :class:`~amigo.errors.InputError` naming
    the first file of another level than the first file's."""
    from amigo.io.jwst import LEVEL2_KINDS

    items = list(kinds.items())
    if not items:
        return
    first, first_kind = items[0]
    for path, kind in items[1:]:
        if (kind in LEVEL2_KINDS) != (first_kind in LEVEL2_KINDS):
            raise InputError(
                path,
                f"is {_kind_words(kind)}, {first.name} {_kind_words(first_kind)}: one call "
                "fits one level (raw ramps and their calslope files, or level-2 images)",
            )


def check_model_options(
    model: str | Path | None,
    detector: str | None,
    knots: int | None,
    knot_spacing: float | None,
) -> None:
    """The fit's model options, checked before any work (``amigo run`` and a manifest's
    targets check them before processing raw ramps): :class:`~amigo.errors.InputError`."""
    from amigo.io.files import require_file

    if detector not in (None, *DETECTORS):
        raise InputError(
            None, f"--detector must be one of {', '.join(DETECTORS)}, not {detector!r}"
        )
    _grid(knots, knot_spacing)
    if model is not None:
        require_file(model, "model file")


@dataclass(frozen=True)
class FitModel:
    """What ``--model``/``--detector`` resolve to.

    Attributes
    ----------
    instrument
        Filter -> image-level :class:`~amigo.model.image.Instrument`.
    base
        The base model whose ramp and read models sit in front of calslope fits (with
        its network for ``full``, without for ``linear``, with the physical account for
        ``boundary``), or ``None`` (images fitted as
        they are: level-2 files, or calslope files with an instrument file).
    detector
        ``"full"``, ``"linear"`` or ``"boundary"`` (``fit_summary.json``).
    source
        The model file's name and content fingerprint, or ``"nominal"``: part of the
        identity of a fit (a re-run keeps products of the same model).
    flat_references
        Filter -> the flat-field reference files behind the level-2 images the base model
        learnt its residual sensitivity from (its record; empty where it records none).
    """

    instrument: Callable[[str], Any]
    base: Any
    detector: str
    source: str = "nominal"
    flat_references: dict[str, tuple[str, ...]] = field(default_factory=dict)


def _fit_model(model: Path | None, detector: str | None, level: str) -> FitModel:
    """Resolve the options: calslope files default to the shipped base model with the
    physical charge-migration account in its network's place (``boundary``; ``full``
    keeps the network); level-2 images to the shipped model trained on real level-2 calibrators
    (:func:`amigo.model.base.level2_model_path`; the nominal instrument where none is
    shipped) with its ramp seen through the pipeline's slope estimator
    (:class:`amigo.fitting.ramp_fit.Level2Input`; a model trained on ramps, or the nominal
    instrument, fits level-2 images with the linear detector unless ``--detector
    full``)."""
    from amigo.model.image import Instrument, load_instrument

    if model is None and level == "level2":
        from amigo.model.base import level2_model_path

        model = level2_model_path()
    if model is None and (level == "calslope" or detector in ("full", "boundary")):
        from amigo.model.base import default_model_path

        model = default_model_path()
    if model is None:
        nominal = Instrument.nominal()
        return FitModel(lambda filter_name: nominal, None, "linear")
    from amigo.io.files import fingerprint, require_file

    source = f"{model.name}:{fingerprint(require_file(model, 'model file'))}"
    if model.suffix.lower() != ".npz":
        if detector in ("full", "boundary"):
            raise InputError(
                model,
                f"--detector {detector} needs a trained base model (.npz), not an instrument file",
            )
        instrument = load_instrument(model)
        return FitModel(lambda filter_name: instrument, None, "linear", source)
    from amigo.model.base import load_base_model, read_metadata
    from amigo.model.detector.boundary import BoundaryShift

    base = load_base_model(model)
    if level == "calslope" and base.config.data_level == "level2":
        raise InputError(
            model,
            "was trained on level-2 images (it has no dark current or non-linearity); "
            "calslope files from raw ramps need a model trained on ramps",
        )
    record = read_metadata(model)
    trained = record.get("trained_on", "?").split(":")[0]
    scenario = record.get("scenario", "?").split(" ")[0]
    # e.g. "(trained on cal4481, simulated ...)"; "(trained on real JWST ...)" when the
    # scenario's first word only repeats the description.
    about = trained if scenario == "?" or trained.startswith(scenario) else f"{scenario}, {trained}"
    # The model's version: its format, when it was trained and by which amigo.
    version = (
        f"format {record.get('format_version', '?')}, trained {str(record.get('date') or '?')[:10]} "
        f"with amigo {record.get('amigo_version', '?')}"
    )
    name = f"{model.name} ({version} on {about})"
    if level == "level2" and detector is None and base.config.data_level == "level2":
        # A model trained behind the pipeline is made for level-2 images with its
        # detector: on held-out real images it fits closer to the noise than the same
        # optics with the linear detector (docs/detector.md).
        detector = "full"
    if level == "calslope" and detector is None and not base.linear:
        # Raw ramps default to the physical account of the charge migration, its strength
        # measured in each filter's data: on ramps written by independent code it fits
        # every exposure closer to the noise than the simulator-trained network, with one
        # strength for every filter, and on the HD 206893-like scenario its companion
        # positions are honest where the network's are biased (docs/detector.md,
        # docs/fidelity.md, docs/detect.md). ``--detector full`` keeps the network.
        detector = "boundary"
    if level == "level2" and detector != "full":
        mode, ramp = "linear", None
    else:
        ramp = base
        if detector == "boundary" and not isinstance(base.ramp.network, BoundaryShift):
            # The physical account in the network's place: its strength is measured in
            # every filter's data (RampDetector.calibrate_migration).
            ramp = base.with_network(BoundaryShift.create())
        elif detector == "linear":
            ramp = base.with_linear_detector()
        # Named by what the ramp holds (a model file may hold the physical account).
        mode = ramp.detector_mode
        if level == "level2" and mode == "boundary":
            # As check_detector_level: its strength is measured in group differences.
            raise InputError(
                model,
                "holds the physical charge-migration account, which needs calslope files "
                "(raw ramps), not level-2 images",
            )
        if level == "level2":
            ramp = ramp.for_level2()  # dark, flat and linearity already corrected
    return FitModel(
        lambda filter_name: Instrument.from_base_model(base, filter_name, name, mode),
        ramp,
        mode,
        source,
        _flat_references(record),
    )


def _flat_references(record: dict) -> dict[str, tuple[str, ...]]:
    """Filter -> flat references of a base model's level-2 calibration files (its
    metadata's ``data`` record, :meth:`amigo.training.data.TrainingData.describe`)."""
    found: dict[str, set[str]] = defaultdict(set)
    data = record.get("data")
    for item in data.get("calibration", []) if isinstance(data, dict) else []:
        if isinstance(item, dict) and "flat_reference" in item and item.get("filter"):
            found[str(item["filter"])].add(str(item["flat_reference"]))
    return {name: tuple(sorted(refs)) for name, refs in found.items()}


def _flat_reference_note(fit_model: FitModel, meta) -> str | None:
    """For a level-2 image divided by another flat than the base model's calibrators of
    its filter (or by none where they were divided by one, or the reverse), what that
    means (``None`` otherwise, or where the model records no flat)."""
    from amigo.training.data import NO_FLAT

    known = fit_model.flat_references.get(meta.filter, ())
    reference = meta.flat_reference or NO_FLAT
    if fit_model.base is None or not known or reference in known:
        return None
    divided = "divided by no flat" if reference == NO_FLAT else f"flat-fielded with {reference}"
    behind = ", ".join("no flat" if k == NO_FLAT else k for k in known)
    return (
        f"{divided}; the base model's residual pixel sensitivity was learnt behind "
        f"{behind}: applied as learnt (another flat costs pixel fidelity, not the calibrated "
        "observables, the base model's README; no flat against one costs the whole flat)"
    )


#: Revision of how a fit reads its inputs into a likelihood, part of every fit's key
#: (:func:`amigo.pipeline.outcome.fit_key`): the package's version does not change with
#: every commit, so products a previous reading made for the same files and options
#: would otherwise be kept. 2: level-2 files as the archive writes them today (the
#: charge-migration step's cut, MJy/sr, SATURATED values left out). Raise it whenever
#: the same inputs would be fitted differently.
READING_REVISION = 2


@dataclass(frozen=True)
class ReadExposure:
    """One input file of a fit, read.

    Attributes
    ----------
    exposure
        The :class:`~amigo.fitting.filter_fit.FitExposure` (``None`` where ``problem`` is set).
    meta
        Its :class:`~amigo.io.jwst.ExposureMeta`.
    ramp
        Its ``RampInput`` (calslope) or ``Level2Input`` (``None`` where ``problem``).
    problem
        Why the exposure has no star to fit (too few usable pixels, no flux above the
        noise), or ``None``: such an exposure is left out of its filter.
    """

    exposure: Any
    meta: Any
    ramp: Any = None
    problem: str | None = None


def _read_fit_exposure(path: Path, role: str, level: str, superbias=None) -> ReadExposure:
    """One input file, read and reduced to what the fit needs; a calslope file keeps its
    first group in the likelihood when ``superbias`` is given. A damaged or foreign file
    raises :class:`InputError`; an image without a star is returned with its problem."""
    from amigo.errors import TooFewPixels
    from amigo.fitting.filter_fit import FitExposure
    from amigo.likelihood.pixels import ImageData

    ramp: Any = None  # RampInput (calslope) or Level2Input
    if level == "calslope":
        from amigo.fitting.ramp_fit import RampInput
        from amigo.io.calslope import read_calslope
        from amigo.io.jwst import meta_from_headers

        product = read_calslope(path)
        if product.slope_dn.shape[0] == 0 and superbias is None:
            raise InputError(
                path,
                "has one group per integration: its only measurement is the first read, "
                "which needs the detector's reset level (--superbias DARKS, or a base "
                "model trained with --darks)",
            )
        meta = meta_from_headers(
            path, product.primary_header, product.slope_header, kind="calslope"
        )
        try:
            ramp = RampInput.create(product, meta.group_time_s, superbias)
            image = ramp.image(None)
        except TooFewPixels as error:
            return ReadExposure(None, meta, problem=error.problem)
    else:
        from amigo.fitting.ramp_fit import Level2Input
        from amigo.io.jwst import read_exposure

        exposure = read_exposure(path)
        meta = exposure.meta
        try:
            image = ImageData.from_exposure(exposure)
        except TooFewPixels as error:
            return ReadExposure(None, meta, problem=error.problem)
        from amigo.likelihood.pixels import pipeline_groups

        groups = pipeline_groups(exposure)
        ramp = Level2Input(
            image, meta.ngroups, meta.nframes, meta.group_time_s, meta.dark_reference,
            None if groups is None else groups.groups,
            "" if groups is None else groups.describe(),
        )  # fmt: skip
    problem = star_problem(image)
    if problem is not None:
        return ReadExposure(None, meta, problem=problem)
    return ReadExposure(FitExposure(path.name, role, meta.target, image), meta, ramp)


#: Smallest signal-to-noise ratio of an image's total flux that counts as a star: an AMI
#: target gives thousands; an exposure of the dark sky, or a damaged file, about zero.
MIN_STAR_SNR = 25.0
#: Largest fraction of an image's flux in its brightest pixel that a star through the
#: mask can give: its PSF puts 1.5 % there in F480M (amigo's nominal optics), 1.7-1.9 %
#: on the 40 real COM 1093 images. A hot pixel or a cosmic ray on an empty image: ~100 %.
MAX_PEAK_FRACTION = 0.25
#: Least height of an image's brightest pixel above the image's median, in units of that
#: pixel's error, for a star: pure noise over 6,000 pixels reaches about 4; the real COM
#: 1093 images 400 to 650.
MIN_PEAK_SIGMA = 10.0


def star_problem(image: ImageData) -> str | None:
    """Why an image has no star to fit, or ``None``. Tested over the usable pixels: a
    brightest pixel less than :data:`MIN_PEAK_SIGMA` errors above the median (a flat
    field), more than :data:`MAX_PEAK_FRACTION` of the flux in one pixel (a hot pixel),
    or the total flux, in units of its own error, below
    :data:`MIN_STAR_SNR` (an all-negative image, a dark, a shutter closed), which a fit
    would otherwise chase to z-scores of 1e5."""
    import numpy as np

    mask = image.mask
    total = float(np.sum(image.data[mask]))
    error = float(np.sqrt(np.sum(image.error[mask] ** 2)))
    snr = total / error if error > 0 else 0.0
    if not snr >= MIN_STAR_SNR:
        return (
            f"no star: the image's total flux is {snr:.1f} times its error "
            f"(at least {MIN_STAR_SNR:g} expected of an AMI target)"
        )
    brightest = int(np.argmax(np.where(mask, image.data, -np.inf)))
    value = float(image.data.flat[brightest])
    height = (value - float(np.median(image.data[mask]))) / float(image.error.flat[brightest])
    if not height >= MIN_PEAK_SIGMA:
        return (
            f"no star: the brightest pixel stands {height:.1f} times its error above the "
            f"image's median (a flat field or the sky; at least {MIN_PEAK_SIGMA:g} expected)"
        )
    peak = value / total
    if peak > MAX_PEAK_FRACTION:
        return (
            f"no star: {100 * peak:.0f} % of the image's flux is in one pixel (a hot pixel "
            f"or a cosmic ray; the mask's PSF puts a few per cent there)"
        )
    return None


def key_targets(items: list) -> list:
    """``(FitExposure, ExposureMeta)`` pairs with each exposure's target keyed by role.

    Exposures of one target share latent visibilities in the fit, so a star given both as
    science and as calibrator (the standard null test: one visit against another) must
    not become one target: its calibrator exposures are renamed ``"<name> (cal obs
    <OBSERVTN>)"``. Science targets keep their names (the product files are named after
    them); a calibrator star that is nobody's science keeps its name too.
    """
    import dataclasses

    science = {e.target for e, _ in items if e.role == "science"}
    keyed = []
    for exposure, meta in items:
        if exposure.role == "calibrator" and exposure.target in science:
            visit = f" obs {meta.observation}" if meta.observation else ""
            exposure = dataclasses.replace(exposure, target=f"{exposure.target} (cal{visit})")
        keyed.append((exposure, meta))
    return keyed


def check_roles(
    sci: tuple[Path, ...], cal: tuple[Path, ...], superbias: tuple[Path, ...], first_group: bool
) -> None:
    """Refuse a file given in two roles, and superbias files without the first group
    (of ``fit`` and of ``run``, before any work)."""
    overlap = set(sci) & set(cal)
    if overlap:
        raise InputError(sorted(overlap)[0], "is given both as --sci and --cal")
    # Exposures are known by their file names: a file given twice (or two files of one
    # name) would count its pixels twice.
    seen: dict[str, Path] = {}
    for path in (*sci, *cal):
        if Path(path).name in seen:
            first = seen[Path(path).name]
            same = Path(path).resolve() == first.resolve()
            raise InputError(
                path, "is given twice" if same else f"has the same name as {first}: rename one"
            )
        seen[Path(path).name] = Path(path)
    if superbias and not first_group:
        raise InputError(None, "--superbias cannot be combined with --no-first-group")
    # A reset level measured on a fitted exposure itself would count its slopes twice.
    overlap = set(superbias) & (set(sci) | set(cal))
    if overlap:
        raise InputError(sorted(overlap)[0], "is given both as --superbias and as --sci/--cal")
    from amigo.io.files import require_file

    for path in superbias:  # a missing dark file is said so, before the levels' rules
        require_file(path, "superbias file")


def _reset_level(paths: tuple[Path, ...], level: str, fit_model: FitModel, off: bool):
    """The superbias of a fit: from ``--superbias`` files, else the base model's (calslope
    inputs), else ``None`` (always with ``--no-first-group``; :func:`check_roles` has
    refused superbias files then)."""
    if off:
        return None
    if paths:
        superbias, source = _superbias(paths, level), f"{len(paths)} file(s)"
    elif fit_model.base is None or level != "calslope":
        return None
    else:
        superbias = fit_model.base.superbias
        source = f"the base model ({fit_model.base.config.superbias_files} dark file(s))"
    if superbias is not None:
        from amigo.progress import step

        about = superbias.summary()
        step(
            f"superbias from {source}: {about['pixels_known']} pixels, "
            f"median error {about['median_error_dn']:.2f} DN"
        )
    return superbias


def _refuse_if_nothing_left(fitted: dict[str, list], excluded: list) -> None:
    """Bad input rather than a result: when no filter has both a science and a
    calibrator exposure left, the first exposure without a star is refused, or, where
    none was left out, the first science exposure of a filter without a calibrator."""
    if any({"science", "calibrator"} <= {e.role for e, _ in items} for items in fitted.values()):
        return
    if excluded:
        _, item = excluded[0]
        raise InputError(item.meta.path, item.problem)
    for filter_name, items in fitted.items():
        if items and all(e.role == "science" for e, _ in items):
            raise InputError(items[0][1].path, f"no calibrator exposure in {filter_name}")


def _fit_filter(
    instrument, filter_name: str, items, config, out: Path, grid, detector, reset, key: str
) -> tuple[dict, list[dict], Any]:
    """Fit one filter and write its products; a numerical failure, or no science or
    calibrator exposure left, becomes a ``"failed"`` record (no products) instead of an
    exception. Returns the filter's record, its exposures' records and its
    :class:`~amigo.observables.extract.FilterProduct` (``None`` where it failed)."""
    from amigo.errors import NumericalFailure

    roles = {e.role for e, _ in items}
    missing = [r for r in ("science", "calibrator") if r not in roles]
    try:
        if missing:
            raise NumericalFailure("exposures", f"no usable {missing[0]} exposure left")
        product = _run_filter(
            instrument, filter_name, items, config, out, grid, detector, reset is not None, key
        )
    except NumericalFailure as failure:
        warn(f"{filter_name}: failed ({failure}); no products for it (fit_summary.json)")
        record = {"status": "failed", "problem": str(failure), "fit_key": key, "products": []}
        records = [
            _unfitted_record(e.name, e.role, e.target, filter_name, "failed", str(failure))
            for e, _ in items
        ]
        return record, records, None
    return product["filter"], product["exposures"], product["product"]


def _unfitted_record(
    file: str, role: str, target: str, filter_name: str, status: str, problem: str
) -> dict[str, Any]:
    """The ``fit_summary.json`` record of an exposure without a fit (``status``
    ``"excluded"`` or ``"failed"``): every key of the interfaces contract, its numbers
    null (``converged`` false), and the ``problem``."""
    from amigo.model.detector.linear import GEOMETRY_NAMES

    return {
        "file": file,
        "role": role,
        "target": target,
        "filter": filter_name,
        "npix": None,
        "chi2": None,
        "dof": None,
        "zscore_std": None,
        "converged": False,
        "iterations": None,
        "seconds": None,
        # The fitted geometry's keys too (docs/interfaces.md: every key, numbers null).
        **{
            f"{name}{tail}": None
            for name in (*GEOMETRY_NAMES, "jitter_mas")
            for tail in ("", "_err")
        },
        "status": status,
        "problem": problem,
    }


def _report(filters: dict[str, dict], exposures: list[dict]) -> None:
    """Warnings for the filters whose products are flagged or missing, and one line for
    each exposure whose fit did not converge (``exposures``: fit_summary.json's records)."""
    for record in exposures:
        if record.get("status") == "unconverged" and not record.get("converged"):
            decrement = record.get("newton_decrement")
            reached = "" if decrement is None else f", Newton decrement {decrement:.2g}"
            warn(
                f"{record['filter']}: {record['file']} ({record['role']}) did not converge "
                f"(iterations: {record.get('iterations')}{reached})"
            )
    unconverged = [name for name, f in filters.items() if f["status"] == "unconverged"]
    if unconverged:
        warn(
            f"the fit did not converge in {', '.join(unconverged)}; its products are "
            "written and flagged (CONVERGD = F in the calvis header, 'converged': false per "
            "exposure in fit_summary.json): check the residual images (plots/) before "
            "using them"
        )
    failed = [name for name, f in filters.items() if f["status"] == "failed"]
    if failed:
        warn(
            f"no products for {', '.join(failed)} "
            f"({len(filters) - len(failed)} of {len(filters)} filters have them)"
        )


def _grid(knots: int | None, spacing: float | None):
    """The uv knot grid from the options (``None``: the defaults)."""
    if knots is None and spacing is None:
        return None
    from amigo.model.visibility import DEFAULT_KNOT_SPACING_M, DEFAULT_N_KNOTS, UVGrid

    try:
        return UVGrid(
            DEFAULT_N_KNOTS if knots is None else knots,
            DEFAULT_KNOT_SPACING_M if spacing is None else spacing,
        )
    except ValueError as error:
        raise InputError(None, f"--knots/--knot-spacing: {error}") from None


def _check_orientations(items) -> None:
    """Exposures of one science target in one filter share visibilities: same roll
    required. A calibrator's exposures are exempt: a point source looks the same at any
    roll, and its visits drift by ~0.04 deg per hour (COM 1093's PA_APER), so two of
    them a few hours apart would otherwise be refused."""
    by_target = defaultdict(list)
    for exposure, meta in items:
        if exposure.role == "science":
            by_target[exposure.target].append(meta)
    for metas in by_target.values():
        pas = [m.orientation.pa_aper_deg for m in metas]
        spread = max((p - pas[0] + 180) % 360 - 180 for p in pas) - min(
            (p - pas[0] + 180) % 360 - 180 for p in pas
        )
        if spread > 0.1:
            raise InputError(
                metas[0].path,
                f"exposures of {metas[0].target} in {metas[0].filter} have roll angles "
                f"{spread:.2f} deg apart; fit each roll separately",
            )


def _charge_loss_note(ramp) -> str | None:
    """What the pipeline's charge-migration step did to a level-2 image's ramps, for the
    terminal (``None`` where it cut none by its default threshold, or the input is not a
    level-2 image)."""
    from amigo.likelihood.pixels import VARIANCE_SOURCE

    used = getattr(ramp, "groups_used", None)
    rule = getattr(ramp, "groups_rule", "")
    if used is None:
        if VARIANCE_SOURCE in rule:  # the header says it ran; VAR_POISSON says: no cut
            return (
                f"the header says the pipeline's charge-migration step ran, but it cut no "
                f"ramp ({rule}): fitted over all groups"
            )
        return None
    kept = used[ramp.data.mask & (used < ramp.ngroups)]
    if kept.size == 0:
        return None
    span = f"{kept.min()}" if kept.min() == kept.max() else f"{kept.min()}-{kept.max()}"
    return (
        f"the pipeline's charge-migration step cut the ramps of {kept.size} pixels (to "
        f"{span} of {ramp.ngroups} groups; {ramp.groups_rule}): their model ramps are "
        "fitted over the same groups"
    )


def _dark_reference_note(base, ramp) -> str | None:
    """For a level-2 image behind another dark reference file than the one the base
    model's read offsets were measured behind, what the fit does instead (``None``
    otherwise)."""
    reference = getattr(ramp, "dark_reference", "")
    config = base.config
    if not reference or config.dark_residual_groups == 0 or reference == config.dark_reference:
        return None
    return (
        f"processed with the dark reference {reference}; the base model's read offsets "
        f"were measured behind {config.dark_reference}: fitted without them, with their "
        "prior's noise added ('amigo train --steps 0 --init MODEL' on calibrators behind "
        "this dark measures them; docs/detector.md)"
    )


def _detector_record(detector, name: str) -> dict:
    """What the fit did with the base model's detector for one exposure:
    for level-2 images, ``detector_amplitude`` (and ``_err``), the amplitude of what the
    model's detector adds to the linear image measured in the image (1: as the model
    says; below 0.5 the image is fitted with the linear image alone, as under
    ``--detector linear``); for level-2 images with a dark residual in the model,
    ``dark_pattern_amplitude`` (and ``_err``), the amplitude of the model's
    read offsets measured in the image (1: as the model says; below 0.5 the image is
    fitted without them), and ``read_offset_sigma_dn_s``, the median noise added for the
    offsets the model does not know; for calslope exposures under the full detector,
    ``migration_amplitude`` (and ``_err``), the amplitude of the network's charge
    migration measured in the exposure's filter, and ``migration_applied``, whether the
    fit rescaled the network by it; for level-2 images the pipeline's charge-migration
    step ran on, ``charge_loss_pixels``, the usable pixels whose ramps it cut short (their
    model ramps are fitted over the same groups); ``{}`` where nothing applies."""
    if detector is None:
        return {}
    import numpy as np

    record: dict[str, Any] = {}
    ramp = detector.inputs.get(name)
    if getattr(ramp, "groups_used", None) is not None:
        cut = (ramp.groups_used < ramp.ngroups) & ramp.data.mask
        record["charge_loss_pixels"] = int(np.sum(cut))
    if name in detector.detector_amplitudes:
        amplitude, error = detector.detector_amplitudes[name]
        record["detector_amplitude"] = _json_number(amplitude, 4)
        record["detector_amplitude_err"] = _json_number(error, 4)
    if name in detector.migration_amplitudes:
        amplitude, error, applied = detector.migration_amplitudes[name]
        record["migration_amplitude"] = _json_number(amplitude, 4)
        record["migration_amplitude_err"] = _json_number(error, 4)
        record["migration_applied"] = bool(applied)
    if name in detector.pattern_amplitudes:
        amplitude, error = detector.pattern_amplitudes[name]
        record["dark_pattern_amplitude"] = _json_number(amplitude, 4)
        record["dark_pattern_amplitude_err"] = _json_number(error, 4)
    if name in detector.added_sigma_dn_s:
        record["read_offset_sigma_dn_s"] = _json_number(detector.added_sigma_dn_s[name], 4)
    return record


def _run_filter(
    instrument,
    filter_name,
    items,
    config,
    out: Path,
    grid=None,
    detector=None,
    first_group: bool = False,
    key: str = "",
) -> dict:
    """Fit one filter, write its calvis, OIFITS and plot files; return its records for
    ``fit_summary.json`` (``"filter"``: the filter's, ``"exposures"``: its exposures').
    ``key``: the fit's identity (:func:`amigo.pipeline.outcome.fit_key`), recorded in
    the products so that a re-run can keep them."""
    import numpy as np

    from amigo import niriss as nis
    from amigo.io.calvis import calvis_filename, write_calvis
    from amigo.io.oifits_write import write_oifits
    from amigo.model.detector.linear import sky_to_optical_matrix
    from amigo.observables.extract import extract_filter
    from amigo.plots.basis import spectrum_figure
    from amigo.plots.fit import exposure_figure, save_figure
    from amigo.progress import step

    exposures = [e for e, _ in items]
    metas = {e.name: m for e, m in items}
    product = extract_filter(
        instrument, filter_name, exposures, config, grid=grid, detector=detector
    )
    fit = product.fit
    plots = out / "plots"
    save_figure(spectrum_figure(product.basis_info), plots / f"basis_{filter_name}.png")
    for e, exposure in enumerate(fit.exposures):
        stem = Path(exposure.name).name.removesuffix(".fits")
        figure = exposure_figure(exposure.image, product.models[e], product.stats[e])
        save_figure(figure, plots / f"{stem}_fit.png")

    bins = nis.filter_bins(filter_name, instrument.n_wavelengths)
    blue, red = nis.half_power_limits(filter_name)
    params = product.result.params
    # The fitted detector geometry (calibrators) places the sky on the optical frame.
    fitted = instrument.with_geometry(params.optics.geometry)
    geometry = _geometry_record(product.result)
    status = "ok" if product.result.converged else "unconverged"
    written = []
    for target_product in product.products:
        target = target_product.target
        sci_items = [(e, metas[e.name]) for e in exposures if e.target == target]
        cal_names = [e.name for e in exposures if e.role == "calibrator"]
        orientation = sci_items[0][1].orientation
        sky_to_uv = sky_to_optical_matrix(orientation, fitted.detector)
        # Photons the fit used: the fitted count rate times the time its values span
        # (ExposureMeta.photon_time_s: the slopes', or every group's with the first group
        # in the likelihood), never EFFEXPTM, which counts the first group's photons
        # whether the fit used them or not.
        photons = 0.0
        for e, exposure in enumerate(fit.exposures):
            if exposure.target == target:
                seconds = metas[exposure.name].photon_time_s(first_group)
                photons += float(np.exp(params.exposures.log_flux[e])) * seconds * nis.GAIN_E_PER_DN
        discos = target_product.discos
        basis = fit.setup.basis
        assert basis is not None  # FilterFit refuses a setup without its latent basis
        calvis_path = out / calvis_filename(target, filter_name)
        write_calvis(
            calvis_path,
            values=discos.values,
            errors=discos.errors,
            kinds=discos.kinds,
            disco_matrix=discos.matrix,
            uv_m=basis.knots_m(),
            wavelengths_m=bins.wavelengths_m,
            weights=bins.weights,
            sky_to_uv=sky_to_uv,
            orientation=orientation,
            n_photons=photons,
            target=target,
            filter_name=filter_name,
            science_files=[e.name for e, _ in sci_items],
            calibrator_files=cal_names,
            header={
                "NAMP": (basis.n_amp, "latent log-amplitude modes"),
                "NPHA": (basis.n_phase, "latent phase modes"),
                "NNUIS": (discos.kernel.n_nuisance, "nuisance parameters nulled"),
                # Products of an unconverged fit are still written, but flagged.
                "CONVERGD": (bool(product.result.converged), "fit converged (fit_summary.json)"),
                "NDISCDRP": (discos.dropped, "DISCOs dropped: variance not positive"),
                "FITKEY": (key, "identity of inputs and settings (amigo fit)"),
            },
        )
        step(f"wrote {calvis_path}")
        n_b = len(nis.baselines_m())
        oifits_path = out / f"{calvis_path.name.removesuffix('_calvis.fits')}.oifits"
        meta = sci_items[0][1]
        write_oifits(
            oifits_path,
            target=target,
            filter_name=filter_name,
            wavelength_m=bins.central_wavelength_m,
            bandwidth_m=red - blue,
            log_amp=target_product.baseline_log_vis[:n_b],
            phase_rad=target_product.baseline_log_vis[n_b:],
            covariance=target_product.baseline_covariance,
            sky_to_uv=sky_to_uv,
            date_obs=meta.date_obs,
            int_time_s=float(meta.primary_header.get("EFFEXPTM") or 0.0),
            science_files=[e.name for e, _ in sci_items],
            n_photons=photons,
        )
        step(f"wrote {oifits_path}")
        written += [calvis_path.name, oifits_path.name]
    info = product.basis_info
    record = product.detector
    detector_summary = {}
    if record is not None:
        detector_summary = {
            "detector": {
                "mode": record.mode,
                "rounds": len(record.changes),
                "correction_changes_sigma": [round(c, 5) for c in record.changes],
                "converged": record.converged,
                "seconds": round(record.seconds, 2),
            }
        }
    return {
        "product": product,
        "exposures": [
            {
                "file": s.name,
                "role": s.role,
                "target": s.target,
                "filter": s.filter,
                "npix": s.npix,
                "chi2": _json_number(s.chi2, 3),
                "dof": _json_number(s.dof, 3),
                "zscore_std": _json_number(s.zscore_std, 5),
                "zscore_std_whitened": _json_number(s.zscore_std_whitened, 5),
                "status": status,
                "converged": s.converged,
                "iterations": s.iterations,
                "seconds": round(s.seconds, 2),
                "loss_change": _json_number(product.result.loss_change, 12),
                "newton_decrement": _json_number(product.result.newton_decrement, 12),
                **geometry["filter"],
                **geometry["exposures"][e],
                **_detector_record(detector, s.name),
                "column_stripes_dn_s": _json_number(float(product.fit.stripe_sigma[e]), 4),
                "column_stripes_length_pix": _json_number(float(product.fit.stripe_length[e]), 1),
            }
            for e, s in enumerate(product.stats)
        ],
        "filter": {
            "status": status,
            "fit_key": key,
            "products": written,
            "discos_dropped": sum(t.discos.dropped for t in product.products),
            "converged": bool(product.result.converged),
            "basis_amplitude_modes": info.n_amp,
            "basis_phase_modes": info.n_phase,
            "kernel_amplitudes": int(product.kernel.amp.shape[0]),
            "kernel_phases": int(product.kernel.phase.shape[0]),
            "seconds": round(product.seconds, 2),
            **detector_summary,
        },
    }


def _json_number(value: float, digits: int) -> float | None:
    """``value`` rounded, or ``None`` (JSON null) where it is not finite."""
    import math

    return round(float(value), digits) if math.isfinite(value) else None


def _geometry_record(result) -> dict:
    """The fitted detector geometry of the filter (``rotation_deg``, ``anisotropy``,
    ``skew_deg``, ``scale``), its band taper (``band_taper_per_um2``) and each exposure's
    ``jitter_mas``, with ``_err`` twins
    (marginal standard errors from the fit's Fisher matrix, priors included; null where
    the fit did not confirm its optimum in float64)."""
    import numpy as np

    from amigo.fitting.newton import Layout
    from amigo.model.detector.linear import GEOMETRY_NAMES
    from amigo.solvers.levenberg_marquardt import marginal_errors

    params = result.params
    layout = Layout.of(params)
    values = np.asarray(params.optics.geometry, np.float64)
    # From the solver's decompositions of the matrix (0.4-0.5 s a filter on 2 cores to
    # decompose it again).
    geometry, band, jitter_indices = layout.geometry, layout.band, layout.jitters
    indices = np.concatenate([geometry, band, jitter_indices])
    all_errors = marginal_errors(result.fisher, indices, result.fisher_solves)
    errors = all_errors[: len(geometry)]
    taper_error = all_errors[len(geometry)]
    jitter_errors = all_errors[len(geometry) + len(band) :]
    filter_record = {}
    for name, value, error in zip(GEOMETRY_NAMES, values, errors, strict=True):
        filter_record[name] = _json_number(value, 6)
        filter_record[f"{name}_err"] = _json_number(error, 6)
    filter_record["band_taper_per_um2"] = _json_number(float(params.optics.band_taper_per_um2), 4)
    filter_record["band_taper_per_um2_err"] = _json_number(taper_error, 4)
    jitters = np.abs(np.asarray(params.exposures.jitter_mas, np.float64))
    exposures = [
        {"jitter_mas": _json_number(j, 4), "jitter_mas_err": _json_number(err, 4)}
        for j, err in zip(jitters, jitter_errors, strict=True)
    ]
    return {"filter": filter_record, "exposures": exposures}


def _write_summary(
    out: Path, model_name: str, detector: str, exposures: list[dict], filters: dict
) -> dict[str, Any]:
    """Write ``out/fit_summary.json`` atomically; return what it holds."""
    from amigo._version import __version__
    from amigo.io.atomic import write_text

    summary = {
        "amigo_version": __version__,
        "model": model_name,
        "detector": detector,
        "exposures": exposures,
        "filters": filters,
    }
    write_text(out / "fit_summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
