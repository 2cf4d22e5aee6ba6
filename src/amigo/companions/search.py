"""The companion search as ``amigo detect`` runs it.

1. **Grid search** (:mod:`~amigo.companions.grid`) for one more companion on top of the
   companions already found, in every filter; the joint detection map sums the filters'
   chi2 gains of positive contrasts.
2. **Candidates**: the highest local maxima of the joint map are refined by a joint
   least-squares fit of all companions (:mod:`~amigo.companions.fit`); the best refined
   candidate's chi2 gain over the previous scene gives its significance (Gaussian
   equivalent, one degree of freedom per filter: ``sqrt(dchi2)`` in one filter).
3. **Error scales**: significances use the errors multiplied by, per filter and
   observable kind, ``max(1, sqrt(chi2 / N))`` of the scene *with* the candidate: data
   that scatter more than their errors do not produce detections, and errors are never
   shrunk to make one.
4. **Detection** (:mod:`~amigo.companions.significance`): the candidate's significance is
   corrected for the trials of the grid (its false-alarm probability anywhere in the
   searched field) and must reach the threshold; a candidate that the joint fit places
   inside the inner working angle, or whose per-filter contrasts no stellar spectrum
   has, is reported as a rejected candidate, not a detection. Accept, refit all
   companions jointly and go back to 1; otherwise stop.
5. **Posterior** (:mod:`~amigo.companions.posterior`) of all companions jointly over all
   filters and, when there are several filters, per filter.
6. **Limits** (:mod:`~amigo.companions.limits`) from a last grid search on the
   companion-subtracted data, with the fitted ``sigma_scale``.

``detection_sigma`` is the *global* significance (trials included); the local one and
the false-alarm probability are reported beside it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import numpy as np

from amigo import heap
from amigo.companions import fit as fitting
from amigo.companions.grid import (
    Grid,
    GridResult,
    contrast_grid,
    default_step_mas,
    grid_statistics,
    inner_working_angle_mas,
)
from amigo.companions.limits import ContrastCurve, contrast_limits, photon_limit_dmag
from amigo.companions.observables import KIND_NAMES, Dataset
from amigo.companions.posterior import ESS_TARGET, Posterior, Priors, sample_posterior
from amigo.companions.significance import (
    IWA_SIGMA,
    Significance,
    SpectrumTest,
    effective_trials,
    inside_working_angle,
    significance,
    spectrum_test,
)
from amigo.companions.subspace import signal_spaces
from amigo.orientation import separation_pa
from amigo.progress import step

#: Candidates whose chi2 gain is within this of the best are followed as alternatives.
ALIAS_DCHI2 = 25.0
#: Most hypotheses followed per search level.
BEAM_WIDTH = 3

#: chi2 a candidate's fit may leave ungained (its Gauss-Newton decrement): the candidates
#: rank peaks and give their significance, for which 1e-2 in chi2 is nothing (aliases are
#: followed within 25, detections are 5 sigma). At 1e-3 (on AB Dor the chi2 left was at
#: most 0.018 more than at full convergence, half the evaluations) three of AB Dor's
#: second-companion candidates crawled 200 steps at a decrement of 0.005-0.009, gaining
#: ~1e-4 per step, once its DISCOs' errors carried the 1/f stripes (docs/fidelity.md).
#: The scene finally reported is fitted again to full convergence.
CANDIDATE_CHI2_TOLERANCE = 1e-2


@dataclass(frozen=True)
class SearchSettings:
    """Options of :func:`detect` (the command-line options of ``amigo detect``)."""

    rmax_mas: float = 1000.0
    step_mas: float | None = None
    threshold_sigma: float = 5.0
    max_companions: int = 3
    n_candidates: int = 20
    primary_diameter_mas: float = 0.0
    hmc: bool = True
    per_filter: bool = True
    num_warmup: int | None = None  # posterior.WARMUP_LAPLACE or WARMUP_ADAPTIVE
    num_samples: int = 1000
    num_chains: int = 2
    ess_target: float = ESS_TARGET
    seed: int = 0
    limit_sigma: float = 3.0
    priors: Priors = field(default_factory=Priors)


@dataclass(frozen=True)
class Estimate:
    """A companion's position and photometry with 1-sigma errors (one fit or posterior)."""

    dra_mas: float
    ddec_mas: float
    dra_err_mas: float
    ddec_err_mas: float
    sep_mas: float
    sep_err_mas: float
    pa_deg: float
    pa_err_deg: float
    dmag: dict[str, float]
    dmag_err: dict[str, float]


@dataclass(frozen=True)
class Companion:
    """A detected companion: its estimate, significance and how it was obtained.

    ``detection_sigma`` is the global significance (trials of the grid included),
    ``significance`` has the local one and the false-alarm probability too.
    """

    id: int
    estimate: Estimate
    detection_sigma: float
    method: str
    per_filter: dict[str, Estimate] = field(default_factory=dict)
    significance: Significance | None = None


@dataclass(frozen=True)
class Rejected:
    """A candidate above the threshold that is not a detection, and why: ``reason`` is
    ``"inner_working_angle"`` or ``"spectrum"`` (``note`` says it in words)."""

    estimate: Estimate
    significance: Significance
    reason: str
    note: str
    spectrum: SpectrumTest | None = None


@dataclass(frozen=True)
class _Context:
    """What the search judges candidates by: the inner working angle (mas), the number
    of independent positions searched and each filter's mean wavelength (um)."""

    iwa_mas: float
    trials: float
    wavelengths_um: np.ndarray
    rejected: dict = field(default_factory=dict)

    def significance(self, dataset: Dataset, dchi2: float) -> Significance:
        return significance(dchi2, dataset.n_filters, self.trials)


@dataclass(frozen=True)
class DetectionResult:
    """Everything :func:`detect` found; see :mod:`amigo.companions.products` for files."""

    dataset: Dataset
    settings: SearchSettings
    grid: Grid
    detection_maps: tuple[GridResult, ...]
    residual_map: GridResult
    companions: tuple[Companion, ...]
    fit: fitting.CompanionFitResult | None
    posterior: Posterior | None
    per_filter_posteriors: dict[str, Posterior]
    group_scales: np.ndarray
    limits: tuple[ContrastCurve, ...]
    photon_counts: dict[str, float]
    warnings: tuple[str, ...]
    rejected: tuple[Rejected, ...] = ()
    trials: float = 1.0
    #: The search's inner working angle (mas): all filters' mean wavelength over twice
    #: the longest baseline, for the rejection and the trials (each filter's maps and
    #: curves start at its own).
    iwa_mas: float = 0.0

    @property
    def sigma_scale(self) -> dict[str, float]:
        """One error scale per filter: the rms over its groups, weighted by observables."""
        counts = self.dataset.group_counts()
        out = {}
        for f in self.dataset.filters:
            index = [g for g, (name, _) in enumerate(self.dataset.groups) if name == f]
            n = counts[index]
            out[f] = float(np.sqrt(np.sum(n * self.group_scales[index] ** 2) / np.sum(n)))
        return out

    @property
    def sigma_scale_by_kind(self) -> dict[str, dict[str, float]]:
        out: dict[str, dict[str, float]] = {}
        for g, (f, kind) in enumerate(self.dataset.groups):
            out.setdefault(f, {})[kind] = float(self.group_scales[g])
        return out

    @property
    def photon_limit_dmag(self) -> dict[str, float]:
        return {f: photon_limit_dmag(n) for f, n in self.photon_counts.items()}


def _mean_wavelengths(dataset: Dataset) -> dict[str, float]:
    """Mean wavelength (m) of each filter's observables, for separations in lambda/D."""
    return {
        f: float(np.mean([b.mean_wavelength_m for b in dataset.blocks if b.filter_name == f]))
        for f in dataset.filters
    }


def _photon_counts(dataset: Dataset) -> dict[str, float]:
    out = {}
    for f in dataset.filters:
        values = [b.n_photons for b in dataset.blocks if b.filter_name == f]
        if all(np.isfinite(v) for v in values):
            out[f] = float(np.sum(values))
    return out


@dataclass(frozen=True)
class _Candidate:
    """One more companion, refined: the joint fit, its chi2 gain and the scales used."""

    fit: fitting.CompanionFitResult
    dchi2: float
    scales: np.ndarray


def _search_one(
    dataset: Dataset,
    grid: Grid,
    current: fitting.CompanionFitResult | None,
    settings: SearchSettings,
) -> tuple[GridResult, list[_Candidate]]:
    """Grid-search one more companion; refine the best peaks; settle the error scales.

    Returns the grid and the refined candidates, best (largest chi2 gain) first.
    """
    k = 0 if current is None else current.n_companions
    offsets = np.zeros((0, 2)) if current is None else current.offsets_mas
    log10c = np.zeros((0, dataset.n_filters)) if current is None else current.log10_contrasts
    scales = np.ones(dataset.n_groups)
    diameter = settings.primary_diameter_mas
    candidates: list[_Candidate] = []
    # The grid's products with the observable matrices depend on the background scene,
    # not on the error scales: made once, solved again for each set of scales.
    statistics = grid_statistics(dataset, grid, offsets, 10.0**log10c, diameter)
    # A peak found again with new scales starts from its fit with the previous ones:
    # the scales only reweight the groups, so the optimum moves little.
    previous: dict[tuple[float, float], fitting.CompanionFitResult] = {}
    for _ in range(3):  # error scales depend on the candidate, the candidate on the scales
        result = contrast_grid(
            dataset, grid, offsets, 10.0**log10c, scales, diameter, statistics=statistics
        )
        if k:
            chi2_before = _chi2(dataset, offsets, log10c, scales, diameter)
        else:
            chi2_before = fitting.background_chi2(dataset, scales, diameter)
        peaks = [(x, y) for x, y, _ in result.peaks(settings.n_candidates)]
        starts = []
        for x, y in peaks:
            before = previous.get((x, y))
            if before is not None:
                starts.append((before.offsets_mas, before.log10_contrasts))
                continue
            iy = int(np.argmin(np.abs(grid.y_mas - y)))
            ix = int(np.argmin(np.abs(grid.x_mas - x)))
            start = [np.log10(max(m.contrast[iy, ix], m.sigma[iy, ix], 1e-8)) for m in result.maps]
            starts.append((np.vstack([offsets, [[x, y]]]), np.vstack([log10c, [start]])))
        # The peaks' fits are independent: fitted side by side, each evaluation of all the
        # running fits one pass over the observable matrices.
        trials = fitting.fit_companions_many(
            dataset, starts, scales, diameter, chi2_tolerance=CANDIDATE_CHI2_TOLERANCE
        )
        candidates = [_Candidate(t, chi2_before - t.chi2, scales) for t in trials]
        previous = dict(zip(peaks, trials, strict=True))
        if not candidates:
            return result, []
        candidates.sort(key=lambda c: -c.dchi2)
        best = candidates[0].fit
        new_scales = np.maximum(
            1.0, fitting.estimate_scales(dataset, best.offsets_mas, best.contrasts, diameter)
        )
        if np.allclose(new_scales, scales, rtol=0.02):
            break
        scales = new_scales
    return result, candidates


def _chi2(dataset, offsets, log10c, scales, diameter) -> float:
    return fitting.scaled_chi2(dataset, offsets, 10.0**log10c, scales, diameter)


@dataclass(frozen=True)
class _Hypothesis:
    """A scene on the search path: its fit, significances and the maps that led to it."""

    fit: fitting.CompanionFitResult | None
    chi2: float  # with unit error scales, to rank hypotheses on the same footing
    significances: tuple[Significance, ...]
    maps: tuple[GridResult, ...]


def _unit_chi2(dataset: Dataset, fit: fitting.CompanionFitResult | None, diameter: float) -> float:
    ones = np.ones(dataset.n_groups)
    if fit is None:
        return fitting.background_chi2(dataset, ones, diameter)
    return _chi2(dataset, fit.offsets_mas, fit.log10_contrasts, ones, diameter)


def _beam_search(
    dataset: Dataset, grid: Grid, settings: SearchSettings, notes: list[str], context: _Context
) -> _Hypothesis:
    """Iterative search, keeping near-degenerate alternatives (aliases) alive.

    A sparse uv coverage has aliases: positions where one companion fits almost as well
    as at the truth, and a second, fainter companion can tip the balance towards the wrong
    one. Every candidate whose chi2 gain is within :data:`ALIAS_DCHI2` of the best is
    followed as a separate hypothesis (at most :data:`BEAM_WIDTH` per level); the final
    scene is the one with the lowest chi2.
    """
    diameter = settings.primary_diameter_mas
    beam = [_Hypothesis(None, _unit_chi2(dataset, None, diameter), (), ())]
    finished: list[_Hypothesis] = []
    for level in range(settings.max_companions + 1):
        expansions: list[_Hypothesis] = []
        for i, parent in enumerate(beam):
            # Near-equal alternatives are searched each (aliases): which one, said.
            which = f" (alternative {i + 1} of {len(beam)})" if len(beam) > 1 else ""
            step(
                f"grid search {level + 1}{which}: {grid.shape[0]}x{grid.shape[1]} positions, "
                f"{grid.step_mas:.1f} mas steps, {dataset.n_filters} filter(s)"
            )
            result, candidates = _search_one(dataset, grid, parent.fit, settings)
            finished.append(
                _Hypothesis(parent.fit, parent.chi2, parent.significances, (*parent.maps, result))
            )
            for rank, cand in enumerate(candidates):
                if cand.dchi2 < candidates[0].dchi2 - ALIAS_DCHI2:
                    break
                sig = context.significance(dataset, cand.dchi2)
                if rank == 0:
                    dra, ddec = cand.fit.offsets_mas[-1]
                    step(
                        f"  best candidate at dRA={dra:.1f} dDec={ddec:.1f} mas: "
                        f"{sig.sigma:.1f} sigma ({sig.local_sigma:.1f} local, false-alarm "
                        f"probability {sig.false_alarm_probability:.2g})"
                    )
                # "not >=": a NaN significance (a chi2 gain that is not finite) is no
                # detection.
                below = not sig.sigma >= settings.threshold_sigma
                if below or _outside(cand.fit, settings, notes):
                    continue
                if _rejected(dataset, cand.fit, sig, context):
                    if rank == 0:
                        break  # its aliases explain the same signal
                    continue
                expansions.append(
                    _Hypothesis(
                        cand.fit,
                        _unit_chi2(dataset, cand.fit, diameter),
                        (*parent.significances, sig),
                        (*parent.maps, result),
                    )
                )
        if not expansions:
            break
        expansions.sort(key=lambda h: h.chi2)
        if level == settings.max_companions:
            notes.append(
                f"stopped at --max-companions={settings.max_companions}: one more candidate "
                f"exceeds the threshold ({expansions[0].significances[-1].sigma:.1f} sigma)"
            )
            break
        beam = expansions[:BEAM_WIDTH]
        finished = []  # a deeper level supersedes the shallower scenes
    # The final scene: among the searches that found nothing more, the lowest chi2.
    best = min(finished, key=lambda h: h.chi2)
    for other in finished:
        if other is best or other.fit is None or best.fit is None:
            continue
        moved = np.max(np.hypot(*(other.fit.offsets_mas - best.fit.offsets_mas).T))
        if other.chi2 - best.chi2 < ALIAS_DCHI2 and moved > grid.step_mas:
            positions = ", ".join(f"({x:.0f}, {y:.0f})" for x, y in other.fit.offsets_mas)
            notes.append(
                f"possible alias: companions at (dRA, dDec) = {positions} mas fit almost as "
                f"well (chi2 larger by {other.chi2 - best.chi2:.1f}); see detection_maps.png"
            )
    return best


def _prune(
    dataset: Dataset,
    scene: _Hypothesis,
    settings: SearchSettings,
    notes: list[str],
    context: _Context,
) -> _Hypothesis:
    """Backward elimination on the final scene: every companion must stand at the
    threshold *given all the others*.

    The beam search adds companions one at a time and keeps the deepest scene; following
    an alias, it can reach a scene in which a companion accepted early is no longer needed
    once a later one is in (the later one explaining the same signal). For each
    companion, the scene is refitted without it and its chi2 gain converted to a
    significance, with the error scales of the whole scene; the weakest one below the
    threshold is dropped and the test repeated. The significances returned are these
    conditional ones.
    """
    diameter = settings.primary_diameter_mas
    fit = scene.fit
    while fit is not None:
        k = fit.n_companions
        scales = np.maximum(
            1.0, fitting.estimate_scales(dataset, fit.offsets_mas, fit.contrasts, diameter)
        )
        full = _chi2(dataset, fit.offsets_mas, fit.log10_contrasts, scales, diameter)
        sigmas, rests = [], []
        for i in range(k):
            keep = [j for j in range(k) if j != i]
            if keep:
                rest = fitting.fit_companions(
                    dataset, fit.offsets_mas[keep], fit.log10_contrasts[keep], scales, diameter
                )
                without = _chi2(dataset, rest.offsets_mas, rest.log10_contrasts, scales, diameter)
            else:
                rest, without = None, fitting.background_chi2(dataset, scales, diameter)
            sigmas.append(context.significance(dataset, max(without - full, 0.0)))
            rests.append(rest)
        weakest = int(np.argmin([s.sigma for s in sigmas]))
        if sigmas[weakest].sigma >= settings.threshold_sigma:
            return _Hypothesis(fit, _unit_chi2(dataset, fit, diameter), tuple(sigmas), scene.maps)
        dra, ddec = fit.offsets_mas[weakest]
        notes.append(
            f"the companion found at (dRA, dDec) = ({dra:.0f}, {ddec:.0f}) mas is only "
            f"{sigmas[weakest].sigma:.1f} sigma given the others: dropped"
        )
        fit = rests[weakest]
    return _Hypothesis(None, _unit_chi2(dataset, None, diameter), (), scene.maps)


def _filter_wavelengths_um(dataset: Dataset) -> np.ndarray:
    """(F,) mean wavelength (um) of each filter's observables."""
    return np.array(
        [
            1e6 * np.mean([b.mean_wavelength_m for b in dataset.blocks if b.filter_name == f])
            for f in dataset.filters
        ]
    )


def _rejected(
    dataset: Dataset,
    fit: fitting.CompanionFitResult,
    sig: Significance,
    context: _Context,
) -> bool:
    """Whether the newest companion of a candidate scene is not a detection although it
    passes the threshold: inside the inner working angle, or with per-filter contrasts
    that no stellar spectrum has. Rejections are recorded once in ``context.rejected``
    (keyed by position; companions.json and the terminal list them)."""
    k = fit.n_companions - 1
    estimate = _estimate_from_fit(fit, k, dataset.filters)
    contrasts = fit.contrasts[k]
    errors = contrasts * np.log(10.0) * fit.log10_contrast_errors()[k]
    spectrum = spectrum_test(contrasts, errors, context.wavelengths_um)
    where = f"(dRA, dDec) = ({estimate.dra_mas:.0f}, {estimate.ddec_mas:.0f}) mas"
    dmags = ", ".join(f"{f} {m:.2f}" for f, m in estimate.dmag.items())
    if inside_working_angle(estimate.sep_mas, estimate.sep_err_mas, context.iwa_mas):
        reason = "inner_working_angle"
        note = (
            f"a {sig.sigma:.1f}-sigma candidate at {where} is {estimate.sep_mas:.1f} +- "
            f"{estimate.sep_err_mas:.1f} mas from the star, inside the inner working angle "
            f"({context.iwa_mas:.0f} mas) by more than {IWA_SIGMA:g} sigma, where a "
            "companion cannot be told from a calibration error: not a detection"
        )
    elif not spectrum.consistent:
        reason = "spectrum"
        note = (
            f"a {sig.sigma:.1f}-sigma candidate at {where} has delta-mags {dmags} that no "
            f"stellar spectrum gives (chi2 {spectrum.chi2:.1f} for {spectrum.dof} dof, "
            f"p = {spectrum.p_value:.2g}): residual structure, not a detection"
        )
    else:
        return False
    key = (round(estimate.dra_mas), round(estimate.ddec_mas))
    if key not in context.rejected:
        context.rejected[key] = Rejected(estimate, sig, reason, note, spectrum)
    return True


def _outside(fit: fitting.CompanionFitResult, settings: SearchSettings, notes: list[str]) -> bool:
    """Whether the joint fit of a candidate scene put a companion beyond the search
    radius (the grid starts inside it, but the least-squares fit is unbounded); if so,
    say so in ``notes``: signal from outside the searched field is not a detection."""
    separations = np.hypot(*fit.offsets_mas.T)
    if separations.max() <= settings.rmax_mas:
        return False
    dra, ddec = fit.offsets_mas[int(np.argmax(separations))]
    note = (
        f"a candidate moved to (dRA, dDec) = ({dra:.0f}, {ddec:.0f}) mas "
        f"({separations.max():.0f} mas) in the joint fit, beyond the search radius "
        f"({settings.rmax_mas:.0f} mas): not reported; search a larger radius (--rmax-mas) "
        "to test it"
    )
    if note not in notes:
        notes.append(note)
    return True


def _release_programs() -> None:
    """Drop JAX's in-memory compiled programs after a posterior.

    Each posterior's sampling loops are programs of their own (new closures, new shapes
    per filter), which JAX's caches keep for the life of the process: on AB Dor's three
    filters the four posteriors took the peak from 0.73 to 1.60 GB, and 1.11 GB with
    this (2026-11-29). What runs after reloads its programs from the persistent
    compilation cache (seconds). The memory goes back to the system (:mod:`amigo.heap`).
    """
    heap.release_programs()


def _estimate_from_samples(dra, ddec, log10c, filters) -> Estimate:
    sep, pa = separation_pa(dra, ddec)
    centre = (
        np.rad2deg(np.arctan2(np.mean(np.sin(np.deg2rad(pa))), np.mean(np.cos(np.deg2rad(pa)))))
        % 360.0
    )
    pa = centre + (pa - centre + 180.0) % 360.0 - 180.0  # unwrap around the mean direction

    def stat(x):
        lo, mid, hi = np.percentile(x, [15.865, 50.0, 84.135])
        return float(mid), float(0.5 * (hi - lo))

    dmag = -2.5 * log10c
    return Estimate(
        dra_mas=stat(dra)[0],
        ddec_mas=stat(ddec)[0],
        dra_err_mas=stat(dra)[1],
        ddec_err_mas=stat(ddec)[1],
        sep_mas=stat(sep)[0],
        sep_err_mas=stat(sep)[1],
        pa_deg=stat(pa)[0] % 360.0,
        pa_err_deg=stat(pa)[1],
        dmag={f: stat(dmag[:, i])[0] for i, f in enumerate(filters)},
        dmag_err={f: stat(dmag[:, i])[1] for i, f in enumerate(filters)},
    )


def _estimate_from_fit(fit: fitting.CompanionFitResult, k: int, filters) -> Estimate:
    dra, ddec = fit.offsets_mas[k]
    cov = fit.covariance[2 * k : 2 * k + 2, 2 * k : 2 * k + 2]
    sep, pa = separation_pa(dra, ddec)
    # Linear propagation to polar coordinates.
    j_sep = np.array([dra, ddec]) / sep
    j_pa = np.rad2deg(np.array([ddec, -dra]) / sep**2)
    err = fit.log10_contrast_errors()[k]
    return Estimate(
        dra_mas=float(dra),
        ddec_mas=float(ddec),
        dra_err_mas=float(np.sqrt(cov[0, 0])),
        ddec_err_mas=float(np.sqrt(cov[1, 1])),
        sep_mas=float(sep),
        sep_err_mas=float(np.sqrt(j_sep @ cov @ j_sep)),
        pa_deg=float(pa),
        pa_err_deg=float(np.sqrt(j_pa @ cov @ j_pa)),
        dmag={f: float(-2.5 * fit.log10_contrasts[k, i]) for i, f in enumerate(filters)},
        dmag_err={f: float(2.5 * err[i]) for i, f in enumerate(filters)},
    )


def detect(dataset: Dataset, settings: SearchSettings | None = None) -> DetectionResult:
    """Search, fit, sample and bound companions in ``dataset`` (runs in float64)."""
    settings = settings or SearchSettings()
    with jax.enable_x64(True):
        return _detect(dataset, settings)


def _detect(given: Dataset, settings: SearchSettings) -> DetectionResult:
    # The observables go to the device once: every compiled call below would copy them.
    dataset = jax.device_put(given)
    diameter = settings.primary_diameter_mas
    step_mas = settings.step_mas or default_step_mas(dataset)
    grid = Grid.square(settings.rmax_mas, step_mas)
    notes: list[str] = []
    iwa = inner_working_angle_mas(dataset.blocks)
    context = _Context(
        iwa_mas=iwa,
        trials=effective_trials(settings.rmax_mas, iwa),
        wavelengths_um=_filter_wavelengths_um(dataset),
    )
    scene = _beam_search(dataset, grid, settings, notes, context)
    path = _prune(dataset, scene, settings, notes, context)
    current = path.fit
    significances = list(path.significances)
    maps = list(path.maps)

    k = 0 if current is None else current.n_companions
    scales_ml = fitting.estimate_scales(
        dataset,
        np.zeros((0, 2)) if current is None else current.offsets_mas,
        np.zeros((0, dataset.n_filters)) if current is None else current.contrasts,
        diameter,
    )
    final_fit = None
    posterior = None
    per_filter_post: dict[str, Posterior] = {}
    companions: list[Companion] = []
    group_scales = scales_ml
    if k:
        assert current is not None  # k > 0 only with a fitted scene
        final_fit = fitting.fit_companions(
            dataset, current.offsets_mas, current.log10_contrasts, scales_ml, diameter
        )
        if not final_fit.converged:
            notes.append("the joint least-squares fit did not converge to its tolerance")
        estimates = [_estimate_from_fit(final_fit, i, dataset.filters) for i in range(k)]
        per_filter_est: list[dict[str, Estimate]] = [{} for _ in range(k)]
        method = "fit"
        if settings.hmc:
            step(
                f"NUTS: {k} companion(s), {dataset.n_filters} filter(s), "
                f"{settings.num_chains}x({settings.num_warmup or 'auto'}+{settings.num_samples}) "
                "steps"
            )
            posterior = sample_posterior(
                dataset,
                final_fit,
                scales_ml,
                num_warmup=settings.num_warmup,
                num_samples=settings.num_samples,
                num_chains=settings.num_chains,
                seed=settings.seed,
                priors=settings.priors,
                primary_diameter_mas=diameter,
                ess_target=settings.ess_target,
            )
            notes.extend(posterior.warnings)
            _release_programs()
            s = posterior.samples
            estimates = [
                _estimate_from_samples(
                    s["dra"][:, i], s["ddec"][:, i], s["log10c"][:, i, :], dataset.filters
                )
                for i in range(k)
            ]
            group_scales = np.median(s["scale"], axis=0)
            method = "hmc"
        if settings.per_filter and dataset.n_filters > 1:
            for f_index, f in enumerate(dataset.filters):
                sub = dataset.subset(f)
                sub_scales = fitting.estimate_scales(
                    sub, final_fit.offsets_mas, final_fit.contrasts[:, [f_index]], diameter
                )
                sub_fit = fitting.fit_companions(
                    sub,
                    final_fit.offsets_mas,
                    final_fit.log10_contrasts[:, [f_index]],
                    sub_scales,
                    diameter,
                )
                if settings.hmc:
                    step(f"NUTS: {f} alone")
                    post = sample_posterior(
                        sub,
                        sub_fit,
                        sub_scales,
                        num_warmup=settings.num_warmup,
                        num_samples=settings.num_samples,
                        num_chains=settings.num_chains,
                        seed=settings.seed + 1 + f_index,
                        priors=settings.priors,
                        primary_diameter_mas=diameter,
                        ess_target=settings.ess_target,
                    )
                    notes.extend(f"{f}: {w}" for w in post.warnings)
                    _release_programs()
                    per_filter_post[f] = post
                    for i in range(k):
                        per_filter_est[i][f] = _estimate_from_samples(
                            post.samples["dra"][:, i],
                            post.samples["ddec"][:, i],
                            post.samples["log10c"][:, i, :],
                            (f,),
                        )
                else:
                    for i in range(k):
                        per_filter_est[i][f] = _estimate_from_fit(sub_fit, i, (f,))
        companions = [
            Companion(
                id=i + 1,
                estimate=estimates[i],
                detection_sigma=significances[i].sigma,
                method=method,
                per_filter=per_filter_est[i],
                significance=significances[i],
            )
            for i in range(k)
        ]

    for companion in companions:
        e = companion.estimate
        if e.sep_mas < context.iwa_mas:
            notes.append(
                f"companion {companion.id} is fitted at {e.sep_mas:.1f} +- {e.sep_err_mas:.1f} "
                f"mas, inside the inner working angle ({context.iwa_mas:.0f} mas) but within "
                f"{IWA_SIGMA:g} sigma of it: a detection, whose separation and contrast are "
                "degenerate there (a closer companion is a brighter one)"
            )

    # Limits on the companion-subtracted data, with the fitted error scales.
    step("contrast limits on the companion-subtracted data")
    # The same scene (the fitted companions, the error scales) for both: the maps and the
    # subspace's chi2 are of one set of residuals.
    subtracted = (
        dataset,
        grid,
        None if final_fit is None else final_fit.offsets_mas,
        None if final_fit is None else final_fit.contrasts,
        group_scales,
        diameter,
    )
    residual = contrast_grid(*subtracted)
    photons = _photon_counts(dataset)
    spaces = signal_spaces(*subtracted)
    limits = contrast_limits(
        residual,
        settings.limit_sigma,
        photon_counts=photons,
        wavelengths_m=_mean_wavelengths(dataset),
        signal_spaces=spaces,
    )
    return DetectionResult(
        dataset=given,
        settings=settings,
        grid=grid,
        detection_maps=tuple(maps),
        residual_map=residual,
        companions=tuple(companions),
        fit=final_fit,
        posterior=posterior,
        per_filter_posteriors=per_filter_post,
        group_scales=np.asarray(group_scales, dtype=float),
        limits=tuple(limits),
        photon_counts=photons,
        warnings=tuple(notes),
        rejected=tuple(context.rejected.values()),
        trials=context.trials,
        iwa_mas=context.iwa_mas,
    )


__all__ = [
    "KIND_NAMES",
    "Companion",
    "DetectionResult",
    "Estimate",
    "Rejected",
    "SearchSettings",
    "detect",
]
