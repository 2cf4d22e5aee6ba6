"""From exposures of one filter to calibrated observables: fit -> Hessians -> kernel -> DISCOs.

This is the work of ``amigo fit`` for one filter (:func:`extract_filter`), as a function a
script can call. Steps:

1. the latent basis of the filter (:func:`amigo.model.basis.load_basis`: shipped, cached or built);
2. the joint fit of all exposures (:class:`amigo.fitting.filter_fit.FilterFit`);
3. the Hessians of the latent visibilities at the optimum and the calibrators' nuisance
   cross terms, float64 (:func:`amigo.fitting.filter_fit.latent_information`);
4. per target: latent values and covariance; calibrators combined (inverse-covariance
   weighted) into one reference;
5. the kernel from the latent response to the nuisances at the calibrators' state (and to
   the visibilities of the knots the fringes do not reach, :func:`amigo.observables.kernel.
   envelope_knots`), and the DISCOs of every science target (:mod:`amigo.observables.kernel`);
6. calibrated log-visibilities at the 21 mask baselines (for OIFITS).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import numpy as np

from amigo import niriss as nis
from amigo.errors import numerical, require_finite
from amigo.fitting.filter_fit import (
    FilterFit,
    FilterFitResult,
    FitConfig,
    FitExposure,
    LatentInformation,
    latent_information,
)
from amigo.fitting.ramp_fit import DetectorRecord, RampDetector, fit_through_detector
from amigo.likelihood.stripes import decorrelate
from amigo.model.basis import BasisInfo, load_basis
from amigo.model.image import FilterSetup, Instrument
from amigo.model.visibility import UVGrid
from amigo.observables import kernel as obs
from amigo.progress import step


@dataclass
class ExposureStats:
    """Goodness of fit of one exposure (the keys of ``fit_summary.json``)."""

    name: str
    role: str
    target: str
    filter: str
    npix: int
    chi2: float
    dof: float
    zscore_std: float
    #: The z-score spread with the 1/f column stripes' covariance whitened too (what the
    #: likelihood uses; ``zscore_std`` where no stripes were measured).
    zscore_std_whitened: float
    converged: bool
    iterations: int
    seconds: float


@dataclass
class TargetProduct:
    """Calibrated observables of one science target in one filter.

    Attributes
    ----------
    target
        Target name.
    discos
        :class:`amigo.observables.kernel.Discos`.
    calibrated_latent, calibrated_covariance
        ``x_sci - x_cal`` and ``C_sci + C_cal`` (latent ``[amp, phase]``).
    baseline_log_vis, baseline_covariance
        (42,) ``[log|V|, arg V]`` at the 21 mask baselines and its covariance.
    """

    target: str
    discos: obs.Discos
    calibrated_latent: np.ndarray
    calibrated_covariance: np.ndarray
    baseline_log_vis: np.ndarray
    baseline_covariance: np.ndarray


@dataclass
class FilterProduct:
    """Everything :func:`extract_filter` produced for one filter."""

    filter_name: str
    fit: FilterFit
    result: FilterFitResult
    basis_info: BasisInfo
    stats: list[ExposureStats]
    models: np.ndarray
    products: list[TargetProduct]
    kernel: obs.Kernel
    #: the float64 latent Hessians and nuisance cross terms the products rest on
    information: LatentInformation
    seconds: float
    detector: DetectorRecord | None = None


def baseline_map(setup: FilterSetup) -> np.ndarray:
    """(42, m_a + m_p) map: latent ``[amp, phase]`` -> ``[log|V|, arg V]`` at the 21 baselines."""
    basis = setup.basis
    assert basis is not None, "the filter setup has no latent basis"
    grid = basis.grid
    weights = grid.point_weights(nis.baselines_m())  # (21, n^2) on the full grid
    s_amp, s_pha = grid.fold_matrix()  # (n^2, n_half)
    knots = np.asarray(basis.knots)
    amp = weights @ s_amp[:, knots] @ np.asarray(basis.amp, float)
    pha = weights @ s_pha[:, knots] @ np.asarray(basis.phase, float)
    out = np.zeros((2 * len(weights), amp.shape[1] + pha.shape[1]))
    out[: len(weights), : amp.shape[1]] = amp
    out[len(weights) :, amp.shape[1] :] = pha
    return out


def exposure_stats(
    fit: FilterFit, result: FilterFitResult, models: np.ndarray, seconds_each: float
) -> list[ExposureStats]:
    """chi2, dof and z-score spread of every exposure at the optimum.

    ``dof`` = values in the likelihood (pixels, or slopes for calslope exposures) minus
    the parameters the exposure pays for: its position, flux and jitter (4), its share of
    its target's latent visibilities and slope, and (calibrators) its share of the 76
    instrument parameters (wavefront, detector geometry, band taper).
    """
    p = result.params
    n_latent = p.sources.amp.shape[1] + p.sources.phase.shape[1] + 1
    n_optics = p.optics.zernikes_nm.size + 1 + p.optics.geometry.size + 1
    per_target = np.bincount(fit.source_index, minlength=len(fit.targets))
    n_cal = max(int(fit.is_calibrator.sum()), 1)
    whiteners = fit.exposure_whiteners()
    inverse_sigma = np.asarray(fit.pixels.inverse_sigma, np.float64)
    stats = []
    for e, exposure in enumerate(fit.exposures):
        image = exposure.image
        z = image.zscores(models[e])  # pixels, or slopes for a calslope exposure
        z_whitened = z
        if whiteners[e] is not None and image.whitened_slopes is None:  # a level-2 image
            pixels = (np.asarray(fit.pixels.data[e], np.float64) - models[e]) * inverse_sigma[e]
            z_whitened = decorrelate(pixels, whiteners[e])[inverse_sigma[e] > 0]
        share = 4 + n_latent / per_target[fit.source_index[e]]
        if fit.is_calibrator[e]:
            share += n_optics / n_cal
        stats.append(
            ExposureStats(
                name=exposure.name,
                role=exposure.role,
                target=exposure.target,
                filter=fit.setup.name,
                npix=int(image.n_pixels),
                chi2=float(np.sum(z * z)),
                dof=float(z.size - share),
                zscore_std=float(np.std(z)),
                zscore_std_whitened=float(np.std(z_whitened)),
                converged=bool(result.converged),
                iterations=int(result.iterations),
                seconds=float(seconds_each),
            )
        )
    return stats


def extract_filter(
    instrument: Instrument,
    filter_name: str,
    exposures: list[FitExposure],
    config: FitConfig | None = None,
    grid: UVGrid | None = None,
    detector: RampDetector | None = None,
) -> FilterProduct:
    """Fit the exposures of one filter and extract every science target's DISCOs.

    ``grid`` is the knot grid of the latent basis (default :class:`UVGrid`'s 51 x 51).
    ``detector`` puts the base model's ramp and read models in front of the fit of
    calslope exposures (:mod:`amigo.fitting.ramp_fit`); ``None`` fits the images as they are.
    """
    start = time.perf_counter()
    config = FitConfig() if config is None else config
    roles = {e.role for e in exposures}
    if "calibrator" not in roles:
        raise ValueError(f"{filter_name}: no calibrator exposure")
    if "science" not in roles:
        raise ValueError(f"{filter_name}: no science exposure")
    basis, basis_info = load_basis(instrument, filter_name, grid)
    setup = FilterSetup.create(filter_name, instrument, basis)
    label = f"fit {filter_name}"
    step(
        f"{label}: {len(exposures)} exposures, {len(dict.fromkeys(e.target for e in exposures))} targets"
    )
    record = None
    # The solvers' linear algebra (NumPy on the host) can meet a matrix without a result
    # (eigh of a Fisher matrix gone non-finite): a failure of this filter, not of the run.
    with numerical("fit"):
        if detector is None:
            fit = FilterFit(instrument, setup, exposures)
            result = fit.fit(config, label=label)
        else:
            fit, result, record = fit_through_detector(
                instrument, setup, exposures, config, detector, label
            )
    step(
        f"{label}: {'converged' if result.converged else 'NOT converged'} after "
        f"{result.iterations} iterations (loss change {result.loss_change:.3g}, "
        f"Newton decrement {result.newton_decrement:.3g} per exposure)"
    )
    params = result.params
    # A fit that ran into NaN has no optimum to take Hessians at: a failure of the
    # filter, reported as such (amigo fit goes on with the other filters).
    require_finite("fit", "fitted parameters", *jax.tree_util.tree_leaves(params))
    with numerical("latent Hessians"):
        information = latent_information(
            fit, result.params, label, result.fisher, result.exact_exposures
        )
    require_finite(
        "latent Hessians",
        "Hessian entries",
        *information.hessian,
        information.cal_hessian,
        information.cross,
    )
    latents = np.concatenate(
        [np.asarray(params.sources.amp, float), np.asarray(params.sources.phase, float)], axis=1
    )
    with numerical("latent covariance"):
        covariances = [obs.covariance_from_hessian(h) for h in information.hessian]
    with numerical("calibration kernel"):
        products, kernel = _calibrate(fit, latents, covariances, information)
    models = np.asarray(fit.models(params), dtype=float)
    # Finite parameters can still overflow the images (a wavefront fitted to a hot pixel):
    # no goodness of fit, and no trust in the products, without finite model images.
    require_finite("model images", "model pixel values", models)
    seconds = time.perf_counter() - start
    stats = exposure_stats(fit, result, models, seconds / fit.n_exposures)
    return FilterProduct(
        filter_name=filter_name,
        fit=fit,
        result=result,
        basis_info=basis_info,
        stats=stats,
        models=models,
        products=products,
        kernel=kernel,
        information=information,
        seconds=seconds,
        detector=record,
    )


def kernel_nuisances(
    fit: FilterFit, information: LatentInformation
) -> tuple[np.ndarray, list[str]]:
    """The directions the DISCOs are made blind to: ``(G, names)``.

    ``G`` (m_a + m_p, n) holds, column by column, how a fit of the calibrators' latent
    visibilities moves for a unit error in each nuisance of ``information`` (named by
    :attr:`LatentInformation.nuisances`), then for the log-amplitude and the phase of
    every envelope knot (:func:`amigo.observables.kernel.envelope_knots`), named
    ``env_amp_<i>`` and ``env_phase_<i>`` by the knot's index among the basis's knots.
    ``benchmarks/inner_limit.py`` selects columns by name to measure what each nuisance
    costs the contrast limits.
    """
    basis = fit.setup.basis
    assert basis is not None  # FilterFit refuses a setup without its latent basis
    nuisance = obs.nuisance_regression(information.cal_hessian, information.cross)
    names = list(information.nuisances)
    # The knots the fringes do not reach are instrumental too (obs.envelope_knots): on
    # a real null pair their calibrated phases made a false 5-sigma candidate (docs/fit.md).
    # Scaled to the largest nuisance column so that the rank threshold keeps them.
    outside = obs.envelope_knots(basis.knots_m(), nis.baselines_m(), nis.HOLE_FLAT_TO_FLAT_M)
    envelope = obs.knot_nuisance(basis.latent_from_knots(), outside)
    scale = float(np.max(np.linalg.norm(nuisance, axis=0), initial=1.0))
    index = np.flatnonzero(outside)
    names += [f"env_amp_{k}" for k in index] + [f"env_phase_{k}" for k in index]
    return np.concatenate([nuisance, envelope * scale], axis=1), names


def _calibrate(
    fit: FilterFit,
    latents: np.ndarray,
    covariances: list[np.ndarray],
    information: LatentInformation,
) -> tuple[list[TargetProduct], obs.Kernel]:
    """Steps 4-6 of :func:`extract_filter`: the kernel of the calibrators' nuisances and
    every science target's DISCOs and baseline log-visibilities.

    ``latents``: (n_targets, m_a + m_p) fitted latent ``[amp, phase]``; ``covariances``
    their (m, m) covariances, in the order of ``fit.targets``.
    """
    setup = fit.setup
    basis = setup.basis
    assert basis is not None  # FilterFit refuses a setup without its latent basis
    roles = fit.target_roles()
    to_knots = basis.latent_from_knots()
    nuisance, _ = kernel_nuisances(fit, information)
    kernel = obs.build_kernel(nuisance, basis.n_amp)
    cal_idx = [i for i, t in enumerate(fit.targets) if roles[t] == "calibrator"]
    cal_value, cal_cov = obs.combine(
        [latents[i] for i in cal_idx], [covariances[i] for i in cal_idx]
    )
    to_baselines = baseline_map(setup)
    products = []
    for i, target in enumerate(fit.targets):
        if roles[target] != "science":
            continue
        discos = obs.discos(latents[i], covariances[i], cal_value, cal_cov, kernel, to_knots)
        value = latents[i] - cal_value
        cov = covariances[i] + cal_cov
        products.append(
            TargetProduct(
                target=target,
                discos=discos,
                calibrated_latent=value,
                calibrated_covariance=cov,
                baseline_log_vis=to_baselines @ value,
                baseline_covariance=to_baselines @ cov @ to_baselines.T,
            )
        )
    return products, kernel
